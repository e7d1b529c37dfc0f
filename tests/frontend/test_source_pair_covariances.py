"""A pose-source pair's declared covariances and mean gyro rate, against independent forms.

With per-sample, anisotropic covariances ``C_k`` (6x6, position block first) and pose
times between IMU samples, the schedule must give, for each pair ``(k - 1, k)``:

* ``C_v = R_m^T (C_p,k + C_p,k-1) R_m / dt^2`` with ``R_m`` the mid-interval attitude
  (scipy's ``Slerp`` at the middle time);
* ``C_w = (dR^T C_r,k-1 dR + C_r,k) / dt^2`` with ``dR = R_k-1^T R_k``;
* the mean raw gyro rate over ``[t_k-1, t_k]``: the integral of the zero-order-held samples
  (each sample holds until the next), summed here overlap by overlap, divided by ``dt``.

The existing test draws isotropic, equal covariances at times on the IMU grid, where a
covariance that skips the rotation, repeats one end, or a gyro mean that drops the partial
samples at the pair's ends all give the same numbers.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.schedule import build_schedule
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import PoseMeasurements


def test_pair_covariances_and_mean_gyro_match_independent_forms():
    run = simulate_run(SimConfig(duration_s=6.0), seed=3)
    rng = np.random.default_rng(5)
    count = 40
    t = 0.5 + 0.1 * np.arange(count) + 0.0037  # between IMU samples
    rotations = Rotation.from_rotvec(np.cumsum(0.3 * rng.standard_normal((count, 3)), 0))
    position = np.cumsum(rng.standard_normal((count, 3)), 0)
    a = rng.standard_normal((count, 6, 6))
    covariance = 1e-4 * (a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(6))
    matrices = rotations.as_matrix()
    source = PoseMeasurements(
        t=torch.from_numpy(t)[None],
        position=torch.from_numpy(position)[None],
        quaternion=matrix_to_quat(torch.from_numpy(matrices))[None],
        covariance=torch.from_numpy(covariance)[None],
        mask=torch.ones(1, count, dtype=torch.bool),
    )
    seq = dataclasses.replace(run.sequence, pose_sources={"vo": source})
    sched = build_schedule(seq, EskfConfig())
    here = sched.source_mask[0, :, 0]
    assert int(here.sum()) == count - 1
    dt = 0.1
    mid = Slerp(t, rotations)(0.5 * (t[1:] + t[:-1])).as_matrix()
    pos_sum = covariance[1:, :3, :3] + covariance[:-1, :3, :3]
    expected_v = np.swapaxes(mid, -1, -2) @ pos_sum @ mid / dt**2
    turn = np.swapaxes(matrices[:-1], -1, -2) @ matrices[1:]
    rot_start = np.swapaxes(turn, -1, -2) @ covariance[:-1, 3:, 3:] @ turn
    expected_w = (rot_start + covariance[1:, 3:, 3:]) / dt**2
    np.testing.assert_allclose(
        sched.source_covariance[0, here, 0].numpy(), expected_v, rtol=1e-9, atol=0
    )
    np.testing.assert_allclose(
        sched.source_rate_covariance[0, here, 0].numpy(), expected_w, rtol=1e-9, atol=0
    )

    imu_mask = seq.imu.mask[0].numpy()
    imu_t = seq.imu.t[0].numpy()[imu_mask]
    gyro = seq.imu.gyro[0].numpy()[imu_mask]
    hold_end = np.append(imu_t[1:], np.inf)
    lo, hi = t[:-1, None], t[1:, None]
    overlap = np.clip(np.minimum(hi, hold_end) - np.maximum(lo, imu_t), 0.0, None)  # (P, N)
    expected_gyro = overlap @ gyro / dt
    np.testing.assert_allclose(
        sched.source_gyro_mean[0, here, 0].numpy(), expected_gyro, rtol=0, atol=1e-9
    )
