"""Initial roll and pitch (frontend.init) from a still accelerometer, against the rotation
scipy builds from the true angles: at rest the accelerometer reads ``f = R^T (0, 0, g)``, and
with no heading source the yaw starts at 0, so the initial attitude must be
``Rz(0) Ry(pitch) Rx(roll)`` itself."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from msf_torch import load_sequence_config
from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.init import initial_state, levelling_specific_force
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import ImuSamples, Sequence, WheelSamples

DTYPE = torch.float64
G = 9.80665
ROLL_PITCH = [(0.3, -0.2), (-1.1, 0.6), (2.5, 1.2)]  # rad; the last one upside down


def test_roll_and_pitch_from_a_still_accelerometer():
    truth = Rotation.from_euler("ZYX", [[0.0, pitch, roll] for roll, pitch in ROLL_PITCH])
    rot = truth.as_matrix()  # (B, 3, 3) body -> world
    batch, n = rot.shape[0], 101
    accel = np.einsum("bji,j->bi", rot, [0.0, 0.0, G])  # R^T (0, 0, g)
    seq = Sequence(
        names=[f"still{b}" for b in range(batch)],
        imu=ImuSamples(
            t=torch.linspace(0.0, 1.0, n, dtype=DTYPE).expand(batch, n).clone(),
            gyro=torch.zeros(batch, n, 3, dtype=DTYPE),
            accel=torch.as_tensor(accel)[:, None, :].expand(batch, n, 3).clone(),
            mask=torch.ones(batch, n, dtype=torch.bool),
        ),
    )
    seq.check()
    state, _ = initial_state(seq, EskfConfig(gravity_mps2=G))
    np.testing.assert_allclose(state.rotation.numpy(), rot, rtol=0, atol=1e-12)


def _moving_start(lever_arm, *, wheel_start_s=0.0):
    """A robot that starts moving: constant body rate ``omega``, the axle centre (at
    ``lever_arm``) speeding up along body x at 2 m/s^2, so the IMU reads
    ``f = dv_b/dt + omega x v_b + R(t)^T (0, 0, g)`` with ``R(t) = R0 Exp(omega t)`` and
    ``v_b = (v(t), 0, 0) - omega x lever_arm``; exact samples, wheel speeds at 25 Hz."""
    omega = np.array([0.08, -0.12, 0.7])
    start = Rotation.from_euler("ZYX", [0.4, 0.15, -0.1])
    imu_t = np.linspace(0.0, 1.0, 201)
    speed = 1.0 + 2.0 * imu_t
    rot = (start * Rotation.from_rotvec(imu_t[:, None] * omega)).as_matrix()
    body_velocity = speed[:, None] * np.array([1.0, 0.0, 0.0]) - np.cross(omega, lever_arm)
    accel = (
        np.array([2.0, 0.0, 0.0])
        + np.cross(omega, body_velocity)
        + np.einsum("kji,j->ki", rot, [0.0, 0.0, G])
    )
    wheel_t = np.arange(wheel_start_s, 1.0 + 1e-9, 0.04)
    wheel_speed = torch.as_tensor(1.0 + 2.0 * wheel_t)[None]
    seq = Sequence(
        names=["moving"],
        imu=ImuSamples(
            t=torch.as_tensor(imu_t)[None],
            gyro=torch.as_tensor(omega).expand(1, imu_t.size, 3).clone(),
            accel=torch.as_tensor(accel)[None],
            mask=torch.ones(1, imu_t.size, dtype=torch.bool),
        ),
        wheel=WheelSamples(
            t=torch.as_tensor(wheel_t)[None],
            left_speed=wheel_speed.clone(),
            right_speed=wheel_speed.clone(),
            mask=torch.ones(1, wheel_t.size, dtype=torch.bool),
        ),
    )
    seq.check()
    return seq, start, accel


def _tilt_error(rotation: np.ndarray, truth: Rotation) -> float:
    """Angle (rad) between the estimated and the true gravity direction in the body axes."""
    up, true_up = rotation.T @ [0.0, 0.0, 1.0], truth.as_matrix().T @ [0.0, 0.0, 1.0]
    return float(np.arccos(np.clip(up @ true_up, -1.0, 1.0)))


def test_moving_start_levelled_with_wheel_speeds_and_gyro():
    lever_arm = np.array([-0.3, 0.05, -0.1])
    seq, start, accel = _moving_start(lever_arm)
    cfg = EskfConfig(gravity_mps2=G, wheel_lever_arm_m=lever_arm.tolist())
    state, _ = initial_state(seq, cfg)
    assert _tilt_error(state.rotation[0].numpy(), start) < 1e-9
    # the plain mean over the same window is tilted by the acceleration and the turn
    window = seq.imu.t[0].numpy() <= cfg.init_window_s
    plain = levelling_specific_force(
        seq.imu.t[0].numpy()[window], accel[window], seq.imu.gyro[0].numpy()[window], None, cfg
    )
    np.testing.assert_allclose(plain, accel[window].mean(0), rtol=0, atol=1e-12)
    plain_up = plain / np.linalg.norm(plain)
    true_up = start.as_matrix().T @ [0.0, 0.0, 1.0]
    assert np.arccos(plain_up @ true_up) > 0.15


def test_wheel_speeds_that_start_late_leave_the_plain_mean():
    seq, start, accel = _moving_start(np.zeros(3), wheel_start_s=0.2)
    cfg = EskfConfig(gravity_mps2=G)
    state, _ = initial_state(seq, cfg)
    window = seq.imu.t[0].numpy() <= cfg.init_window_s
    f = accel[window].mean(0)
    roll, pitch = np.arctan2(f[1], f[2]), np.arctan2(-f[0], np.hypot(f[1], f[2]))
    up = state.rotation[0].numpy().T @ [0.0, 0.0, 1.0]
    expected = Rotation.from_euler("ZYX", [0.0, pitch, roll]).as_matrix().T @ [0.0, 0.0, 1.0]
    np.testing.assert_allclose(up, expected, rtol=0, atol=1e-12)


def _fast_start_tilts(plain, wheels=True, **sim_changes) -> tuple[list[float], list[float]]:
    """Fast drives (3 m/s, 0.8 rad/s turns) over 8-degree slopes 10-30 m long, with the
    ADIS16470's noise and turn-on biases, seeds 100-115: the initial tilt error (rad)
    against the simulator's truth, levelled and with ``plain(seq, cfg)`` (the sequence and
    config that leave the plain mean); ``wheels=False`` takes the wheels out."""
    sim = SimConfig(
        duration_s=3.0,
        mean_speed_mps=3.0,
        turn_rate_peak_rad_s=0.8,
        terrain_slope_deg=8.0,
        terrain_wavelength_m=(10.0, 30.0),
        **sim_changes,
    )
    levelled, unlevelled = [], []
    for seed in range(100, 116):
        seq = simulate_run(sim, seed).sequence
        if not wheels:
            seq = replace(seq, wheel=None)
        cfg = load_sequence_config(seq.meta)
        truth = Rotation.from_quat(seq.ground_truth.quaternion[0, 0].numpy()[[1, 2, 3, 0]])
        state, _ = initial_state(seq, cfg)
        levelled.append(_tilt_error(state.rotation[0].numpy(), truth))
        state, _ = initial_state(*plain(seq, cfg))
        unlevelled.append(_tilt_error(state.rotation[0].numpy(), truth))
    return levelled, unlevelled


def test_moving_start_on_rough_ground_against_the_simulated_truth():
    """With 1024-tick encoders; plain: the same without wheels."""
    levelled, plain = _fast_start_tilts(lambda seq, cfg: (replace(seq, wheel=None), cfg))
    # the accelerometer's turn-on bias (5 mg: 0.005 rad) is what is left
    assert max(levelled) < 0.025 and np.median(levelled) < 0.012
    assert np.median(plain) > 0.04 and max(plain) > 0.15


def test_moving_start_without_wheels_levelled_with_gnss_velocities():
    """Without wheels, with a 10-Hz GNSS velocity (0.05 m/s noise): the speed over ground
    along body x stands in for the wheels; with ``nhc: off`` (a platform that may slide
    sideways) the plain mean stays."""
    levelled, plain = _fast_start_tilts(
        lambda seq, cfg: (seq, cfg.replace(nhc="off")),
        wheels=False,
        gnss_velocity=True,
        gnss_rate_hz=10.0,
    )
    assert max(levelled) < 0.045 and np.median(levelled) < 0.015
    assert np.median(plain) > 0.05 and max(plain) > 0.15
