"""Simulated runs with wrong calibration: wheel radii, track width, sensor time offsets and
extrinsics.

A run of :func:`msf_torch.sim.wheeled.simulate_run` (no slip, no random wheel scale error)
is changed so that the filter's believed calibration is off by known amounts:

* wheel radii: the filter believes ``r_b = r (1 + e)`` for each wheel, so an encoder reading
  (rim speed at the believed radius) is ``true * (1 + e)``; the true radius ratio (state
  ``k`` of ``frontend.calibration``) is ``1 / (1 + e)``;
* track width: the filter is told ``D_b = D (1 + d)``: the config's ``wheel_track_m`` is the
  believed value (the same for every run, so runs batch), the run drives with
  ``D = D_b / (1 + d)``;
* time offsets: a GNSS fix or a camera (VO) pose taken at IMU time ``t`` is stamped
  ``t - t_d``, so the sample stamped ``t_s`` was taken at ``t_s + t_d`` (the convention of
  ``sensors.calibration``).

Extrinsics (opt-in, default 0 = the runs above, bit for bit; their own seed stream). The
filter believes the IMU is aligned with the vehicle, the camera sits at the IMU with its
axes, and the GNSS antenna at ``config.gnss_lever_arm_m``; the truth differs by:

* IMU-to-vehicle rotation ``V = Exp(phi_V)`` (vehicle -> IMU): the IMU frame is the
  vehicle's (the simulated path's) rotated, ``R_wi = R_wv V^T``; gyro and accelerometer
  samples are rotated into it (``V w``, ``V f``), the ground-truth attitude is ``R_wi``;
* GNSS lever arm in the IMU frame ``l = l_b + dl``;
* camera lever arm ``l_c`` (IMU frame) and mounting rotation ``M = Exp(phi_M)`` (camera ->
  IMU): the VO poses are those of the camera, ``(p + R_wi l_c, R_wi M)``.

Each error has a fixed magnitude and a random sign per run (its own seed stream). The
camera is a visual-odometry pose source ``"vo"``: the true pose at ``t_s + t_d`` with
white noise (declared) and a random-walk drift per metre travelled (undeclared), as
``sim.weather.CameraModel`` models it.
"""

from __future__ import annotations

__all__ = [
    "CalibrationTruth",
    "CalibrationRun",
    "calibration_sim_config",
    "simulate_calibration_run",
]

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.sim.wheeled import SimConfig, SimulatedRun, simulate_run
from msf_torch.types import GnssFixes, PoseMeasurements, Sequence, WheelSamples


@dataclass
class CalibrationTruth:
    """The true calibration of a run and what the filter is told.

    Attributes:
        radius_ratio: (2,) true / believed radius ``[k_l, k_r]``.
        track_width_m: true track width, m.
        believed_track_width_m: the track width the filter is given, m.
        time_offset_s: sensor key (``"gnss"``, ``"pose:vo"``) -> true ``t_d``, s.
        gnss_lever_arm_m: (3,) true antenna lever arm, IMU frame, m.
        camera_lever_arm_m: (3,) true camera origin, IMU frame, m.
        camera_rotation_rad: (3,) true camera mounting rotation (camera -> IMU), rotation
            vector.
        imu_body_rotation_rad: (3,) true rotation vehicle -> IMU, rotation vector.
    """

    radius_ratio: np.ndarray
    track_width_m: float
    believed_track_width_m: float
    time_offset_s: dict[str, float]
    gnss_lever_arm_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    camera_lever_arm_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    camera_rotation_rad: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    imu_body_rotation_rad: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def vector(self, names: tuple[str, ...]) -> np.ndarray:
        """True values in the order of ``frontend.calibration`` state ``names`` (n,)."""
        values = {
            "wheel_radius_ratio_left": float(self.radius_ratio[0]),
            "wheel_radius_ratio_right": float(self.radius_ratio[1]),
            "wheel_track_m": self.track_width_m,
        }
        values |= {f"time_offset_s:{k}": v for k, v in self.time_offset_s.items()}
        for prefix, vector in (
            ("lever_arm_m:gnss", self.gnss_lever_arm_m),
            ("lever_arm_m:pose:vo", self.camera_lever_arm_m),
            ("rotation_rad:pose:vo", self.camera_rotation_rad),
            ("rotation_rad:imu_body", self.imu_body_rotation_rad),
        ):
            values |= {f"{prefix}:{axis}": float(x) for axis, x in zip("xyz", vector, strict=True)}
        return np.array([values[n] for n in names])


@dataclass
class CalibrationRun:
    """A miscalibrated run (B = 1).

    Attributes:
        sequence: measurements as the filter sees them (scaled wheel readings, GNSS and VO
            stamped on their own clocks), ground truth at the IMU times.
        corrected: the same measurements with the true calibration applied, for an oracle
            filter told the believed track width: wheel readings replaced by the rim speeds
            that give the true speed and yaw rate at ``D_b`` (``v -/+ omega D_b / 2``), stamps
            moved to the IMU clock.
        truth: the true calibration.
        run: the underlying clean run.
    """

    sequence: Sequence
    corrected: Sequence
    truth: CalibrationTruth
    run: SimulatedRun


def calibration_sim_config(duration_s: float = 180.0, **overrides: Any) -> SimConfig:
    """The benchmark's vehicle: a fast field robot (4 m/s mean, 0.6 m track, 0.2 m wheels)
    with RTK-grade GNSS at 5 Hz (0.05 m / 0.1 m) and two 30-s GNSS outages, no slip;
    ``overrides`` replace any :class:`SimConfig` field (its units)."""
    settings = {
        "duration_s": duration_s,
        "mean_speed_mps": 4.0,
        "wheel_track_m": 0.6,
        "wheel_radius_m": 0.2,
        "wheel_scale_sigma": 0.0,
        "gnss_rate_hz": 5.0,
        "gnss_sigma_horizontal_m": 0.05,
        "gnss_sigma_vertical_m": 0.1,
        "gnss_outages_s": ((60.0, 90.0), (130.0, 160.0)) if duration_s >= 170.0 else None,
        "slip_episodes": 0,
    }
    settings.update(overrides)
    return SimConfig(**settings)


def _tensor(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.array(x, dtype=np.float64, order="C"))[None]


def _camera_stream(
    run: SimulatedRun,
    imu_body: np.ndarray,
    lever_arm: np.ndarray,
    mount: np.ndarray,
    offset_s: float,
    rate_hz: float,
    position_sigma_m: float,
    rotation_sigma_rad: float,
    drift_m_per_sqrt_m: float,
    drift_rad_per_sqrt_m: float,
    drift_side: str,
    rng: np.random.Generator,
) -> tuple[PoseMeasurements, PoseMeasurements]:
    """VO poses stamped on the camera clock, and the same poses on the IMU clock.

    ``imu_body`` (3, 3) vehicle -> IMU, ``lever_arm`` (3,) m and ``mount`` (3, 3) the camera
    in the IMU frame; identity / zero leave the poses those of the path. ``drift_side``:
    ``"body"``: rotation drift ``R Exp(d)`` and position drift added to the true pose, or
    ``"chained"``: the poses chain the true relative poses, each followed by that step's
    drift increment ``(dd_p, Exp(dd))`` in the previous pose's frame (a VO that integrates
    relative motion).
    """
    duration = run.config.duration_s
    taken = np.arange(int(np.floor(duration * rate_hz)) + 1) / rate_hz
    taken = taken[(taken - offset_s >= 0.0) & (taken <= duration)]
    state = run.path.evaluate(taken)
    position, attitude = state.position, state.rotation
    if lever_arm.any() or (mount != np.eye(3)).any() or (imu_body != np.eye(3)).any():
        attitude = attitude @ imu_body.T
        position = position + attitude @ lever_arm
        attitude = attitude @ mount
    step = np.linalg.norm(np.diff(state.position, axis=0), axis=-1)
    root = np.sqrt(np.concatenate(([0.0], step)))[:, None]
    drift_p = np.cumsum(drift_m_per_sqrt_m * root * rng.normal(size=(len(taken), 3)), 0)
    drift_r = np.cumsum(drift_rad_per_sqrt_m * root * rng.normal(size=(len(taken), 3)), 0)
    noise_p = position_sigma_m * rng.normal(size=(len(taken), 3))
    noise_r = rotation_sigma_rad * rng.normal(size=(len(taken), 3))
    if drift_side == "chained":
        step_turn = so3.exp(torch.from_numpy(np.diff(drift_r, axis=0))).numpy()
        step_shift = np.diff(drift_p, axis=0)
        relative_turn = attitude[:-1].transpose(0, 2, 1) @ attitude[1:]
        relative_step = np.einsum("nji,nj->ni", attitude[:-1], np.diff(position, axis=0))
        chained_p, chained_r = position.copy(), attitude.copy()
        for k in range(1, len(taken)):
            previous = chained_r[k - 1]
            chained_p[k] = chained_p[k - 1] + previous @ (relative_step[k - 1] + step_shift[k - 1])
            chained_r[k] = previous @ relative_turn[k - 1] @ step_turn[k - 1]
        position, attitude = chained_p, chained_r
        error_p, error_r = noise_p, noise_r
    else:
        error_p, error_r = drift_p + noise_p, drift_r + noise_r
    rotation = torch.from_numpy(attitude) @ so3.exp(torch.from_numpy(error_r))
    cov = np.zeros((len(taken), 6, 6))
    cov[:, :3, :3] = position_sigma_m**2 * np.eye(3)
    cov[:, 3:, 3:] = rotation_sigma_rad**2 * np.eye(3)

    def stream(stamps: np.ndarray) -> PoseMeasurements:
        return PoseMeasurements(
            t=_tensor(stamps),
            position=_tensor(position + error_p),
            quaternion=matrix_to_quat(rotation)[None],
            covariance=_tensor(cov),
            mask=torch.ones((1, len(taken)), dtype=torch.bool),
        )

    return stream(taken - offset_s), stream(taken)


def simulate_calibration_run(
    seed: int,
    config: SimConfig | None = None,
    radius_error: float = 0.05,
    track_error: float = 0.03,
    time_offset_s: float = 0.02,
    camera_rate_hz: float = 10.0,
    camera_position_sigma_m: float = 0.03,
    camera_rotation_sigma_rad: float = 1.2e-3,
    camera_drift_m_per_sqrt_m: float = 0.01,
    camera_drift_rad_per_sqrt_m: float = 1e-3,
    camera_drift_side: str = "body",
    gnss_lever_arm_error_m: float = 0.0,
    camera_lever_arm_error_m: float = 0.0,
    camera_rotation_error_rad: float = 0.0,
    imu_body_rotation_error_rad: float = 0.0,
) -> CalibrationRun:
    """One miscalibrated run with known truth.

    Args:
        seed: non-negative int (the clean run and the error signs).
        config: the run's settings (default :func:`calibration_sim_config`); its
            ``wheel_track_m`` is the believed track width ``D_b``.
        radius_error: ``|e|`` of each wheel's believed radius (random sign per wheel).
        track_error: ``|d|`` of the believed track width (random sign).
        time_offset_s: ``|t_d|`` of GNSS and of the camera, s (random signs).
        camera_rate_hz: VO rate, Hz.
        camera_position_sigma_m, camera_rotation_sigma_rad: declared white noise per pose
            (defaults: ``sim.weather.CameraModel`` with 280 tracked features).
        camera_drift_m_per_sqrt_m, camera_drift_rad_per_sqrt_m: VO drift (random walk per
            metre travelled).
        camera_drift_side: ``"body"`` (default): the rotation drift multiplies the attitude
            on the body side, position drift is added independently, so the VO's body-frame
            velocities turn with the accumulated rotation drift (which aliases with the
            camera's mounting rotation); ``"chained"``: a VO that chains relative poses,
            each step followed by its drift increment (relative motion stays consistent).
        gnss_lever_arm_error_m: ``|dl|`` per axis of the antenna lever arm (random signs);
            the believed lever arm is ``config.gnss_lever_arm_m``.
        camera_lever_arm_error_m: ``|l_c|`` per axis of the camera lever arm (believed 0).
        camera_rotation_error_rad: ``|phi_M|`` per axis of the camera mounting rotation.
        imu_body_rotation_error_rad: ``|phi_V|`` per axis of the IMU-to-vehicle rotation.
    Returns:
        :class:`CalibrationRun`.
    """
    if camera_drift_side not in ("body", "chained"):
        raise ValueError(
            f"camera_drift_side must be 'body' or 'chained', got {camera_drift_side!r}"
        )
    config = config or calibration_sim_config()
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 6006])))
    sign = rng.choice([-1.0, 1.0], 5)
    radius = 1.0 + radius_error * sign[0:2]
    believed_track = config.wheel_track_m
    true_track = believed_track / (1.0 + track_error * sign[2])
    offsets = {"gnss": time_offset_s * sign[3], "pose:vo": time_offset_s * sign[4]}
    extrinsic_rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 6007])))
    extrinsic_sign = extrinsic_rng.choice([-1.0, 1.0], (4, 3))
    believed_lever = np.asarray(config.gnss_lever_arm_m, np.float64)
    gnss_lever = believed_lever + gnss_lever_arm_error_m * extrinsic_sign[0]
    camera_lever = camera_lever_arm_error_m * extrinsic_sign[1]
    camera_rotation = camera_rotation_error_rad * extrinsic_sign[2]
    imu_body_rotation = imu_body_rotation_error_rad * extrinsic_sign[3]
    imu_body = so3.exp(torch.from_numpy(imu_body_rotation)).numpy()
    mount = so3.exp(torch.from_numpy(camera_rotation)).numpy()
    truth = CalibrationTruth(
        1.0 / radius,
        true_track,
        believed_track,
        offsets,
        gnss_lever,
        camera_lever,
        camera_rotation,
        imu_body_rotation,
    )
    # the simulator's body is the vehicle: its antenna lever arm is V^T l
    run = simulate_run(
        dataclasses.replace(
            config,
            wheel_track_m=true_track,
            gnss_lever_arm_m=tuple(float(x) for x in imu_body.T @ gnss_lever),
        ),
        seed,
    )

    seq = run.sequence
    wheel = WheelSamples(
        t=seq.wheel.t,
        left_speed=seq.wheel.left_speed * radius[0],
        right_speed=seq.wheel.right_speed * radius[1],
        mask=seq.wheel.mask,
    )
    gnss_t = seq.gnss.t - offsets["gnss"]
    keep = gnss_t[0] >= 0.0

    def fixes(stamps: torch.Tensor) -> GnssFixes:
        return GnssFixes(
            t=stamps[:, keep],
            position=seq.gnss.position[:, keep],
            sigma=seq.gnss.sigma[:, keep],
            mask=seq.gnss.mask[:, keep],
        )

    camera, camera_imu_clock = _camera_stream(
        run,
        imu_body,
        camera_lever,
        mount,
        offsets["pose:vo"],
        camera_rate_hz,
        camera_position_sigma_m,
        camera_rotation_sigma_rad,
        camera_drift_m_per_sqrt_m,
        camera_drift_rad_per_sqrt_m,
        camera_drift_side,
        rng,
    )
    meta = dict(seq.meta)
    meta["sensor"] = dict(
        meta["sensor"],
        wheel_track_m=believed_track,
        gnss_lever_arm_m=[float(x) for x in believed_lever],
    )
    speed = 0.5 * (seq.wheel.left_speed + seq.wheel.right_speed)
    turn = (seq.wheel.right_speed - seq.wheel.left_speed) * (0.5 * believed_track / true_track)
    meta["calibration_truth"] = {
        "radius_ratio": [float(x) for x in truth.radius_ratio],
        "track_width_m": truth.track_width_m,
        "believed_track_width_m": believed_track,
        "time_offset_s": {k: float(v) for k, v in offsets.items()},
        "gnss_lever_arm_m": [float(x) for x in gnss_lever],
        "camera_lever_arm_m": [float(x) for x in camera_lever],
        "camera_rotation_rad": [float(x) for x in camera_rotation],
        "imu_body_rotation_rad": [float(x) for x in imu_body_rotation],
    }
    imu, ground_truth = seq.imu, seq.ground_truth
    if imu_body_rotation.any():  # the IMU frame is the vehicle's rotated by V^T
        to_imu = torch.from_numpy(imu_body)
        imu = dataclasses.replace(
            imu,
            gyro=(to_imu @ imu.gyro[..., None]).squeeze(-1),
            accel=(to_imu @ imu.accel[..., None]).squeeze(-1),
        )
        attitude = quat_to_matrix(ground_truth.quaternion) @ to_imu.T
        ground_truth = dataclasses.replace(ground_truth, quaternion=matrix_to_quat(attitude))
    sequence = dataclasses.replace(
        seq,
        names=[f"sim_calibration_seed{int(seed)}"],
        imu=imu,
        ground_truth=ground_truth,
        wheel=wheel,
        gnss=fixes(gnss_t),
        pose_sources={"vo": camera},
        meta=meta,
    )
    corrected = dataclasses.replace(
        sequence,
        wheel=dataclasses.replace(seq.wheel, left_speed=speed - turn, right_speed=speed + turn),
        gnss=fixes(seq.gnss.t),
        pose_sources={"vo": camera_imu_clock},
    )
    sequence.check()
    corrected.check()
    return CalibrationRun(sequence, corrected, truth, run)
