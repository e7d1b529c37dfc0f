"""Front end: batched error-state Kalman filter (ESKF) over the residuals of ``sensors``.

``eskf`` (propagate / update over a batch of sequences, :func:`~msf_torch.frontend.eskf.run_eskf`),
``config`` (the flat settings dataclass), ``schedule`` (IMU samples cut into filter epochs),
``init`` (initial state), ``gating`` (chi-square and multi-model source-fault tests),
``adaptive`` (Sage-Husa and strong tracking), ``guard`` (unusable samples, divergence resets),
``calibration`` (online calibration states), ``slip`` (wheel slip factor), ``source_frames``
(drifting pose-source frames), ``stream`` (a run fed piece by piece as it arrives),
``keyframes``, ``attitude_ukf`` and ``imu_fusion`` (several IMUs on one body).
"""
