"""The simulator's continuous truth: kinematic consistency of pose, velocity, IMU signals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import STANDARD_GRAVITY
from msf_torch.sim import ImuNoiseSpec, SimConfig, simulate_run


def _rotation_log(rot: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3), via ``geometry.so3.log``."""
    return so3.log(torch.from_numpy(rot)).numpy()


@pytest.fixture(scope="module")
def run():
    return simulate_run(SimConfig(duration_s=60.0), seed=3)


def test_body_velocity_is_forward_only(run):
    rot = run.truth.rotation[0].numpy()
    vel = run.truth.velocity[0].numpy()
    body = np.einsum("nji,nj->ni", rot, vel)
    assert np.abs(body[:, 1:]).max() < 1e-9
    np.testing.assert_allclose(body[:, 0], run.truth.speed[0].numpy(), rtol=1e-12)
    assert body[:, 0].min() > 0.3
    # proper rotations
    np.testing.assert_allclose(
        rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_ground_truth_stream_matches_truth(run):
    seq = run.sequence
    np.testing.assert_array_equal(seq.ground_truth.position.numpy(), run.truth.position.numpy())
    from msf_torch.geometry.quaternion import quat_to_matrix

    rot = quat_to_matrix(seq.ground_truth.quaternion)
    np.testing.assert_allclose(rot.numpy(), run.truth.rotation.numpy(), atol=1e-12)


def test_velocity_and_specific_force_match_finite_differences(run):
    path = run.path
    t = np.linspace(0.5, 59.5, 400)
    h = 1e-2  # fourth-order stencils: truncation ~1e-10, round-off ~1e-10 m/s^2
    p = [path.evaluate(t + k * h).position for k in (-2, -1, 0, 1, 2)]
    vel_fd = (p[0] - 8 * p[1] + 8 * p[3] - p[4]) / (12 * h)
    acc_fd = (-p[0] + 16 * p[1] - 30 * p[2] + 16 * p[3] - p[4]) / (12 * h * h)
    state = path.evaluate(t)
    np.testing.assert_allclose(state.velocity, vel_fd, atol=1e-9)
    # independent specific force: R^T (a_fd - g)
    gravity = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    f_fd = np.einsum("nji,nj->ni", state.rotation, acc_fd - gravity)
    err = np.abs(state.specific_force - f_fd).max()
    assert err < 1e-9 * STANDARD_GRAVITY, err


def test_angular_velocity_matches_finite_differences(run):
    path = run.path
    t = np.linspace(0.5, 59.5, 400)
    h = 1e-4
    r_minus, r_plus = path.evaluate(t - h).rotation, path.evaluate(t + h).rotation
    omega_fd = _rotation_log(np.swapaxes(r_minus, -1, -2) @ r_plus) / (2 * h)
    omega = path.evaluate(t).angular_velocity
    np.testing.assert_allclose(omega, omega_fd, atol=1e-8)
    # a ground robot: yaw rate dominates, roll and pitch rates are small but non-zero
    assert np.abs(omega[:, 2]).max() > 0.05
    assert 1e-4 < np.abs(omega[:, :2]).max() < 0.1


def test_noise_free_imu_integrates_to_truth():
    config = SimConfig(duration_s=10.0, imu_rate_hz=1000.0, imu_noise=ImuNoiseSpec.zero())
    run = simulate_run(config, seed=11)
    imu = run.sequence.imu
    gyro, accel = imu.gyro[0].numpy(), imu.accel[0].numpy()
    np.testing.assert_array_equal(gyro, run.truth.angular_velocity[0].numpy())
    dt = 1.0 / config.imu_rate_hz
    gravity = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    rot = run.truth.rotation[0, 0].numpy().copy()
    pos = run.truth.position[0, 0].numpy().copy()
    vel = run.truth.velocity[0, 0].numpy().copy()
    acc = rot @ accel[0] + gravity
    # second-order scheme: midpoint rotation, trapezoidal velocity, matching position
    steps = so3.exp(torch.from_numpy(0.5 * (gyro[:-1] + gyro[1:]) * dt)).numpy()
    for k in range(len(gyro) - 1):
        rot_next = rot @ steps[k]
        acc_next = rot_next @ accel[k + 1] + gravity
        pos = pos + vel * dt + (acc / 3.0 + acc_next / 6.0) * dt * dt
        vel = vel + 0.5 * (acc + acc_next) * dt
        rot, acc = rot_next, acc_next
    truth_rot = run.truth.rotation[0, -1].numpy()
    angle_err = np.linalg.norm(_rotation_log((rot.T @ truth_rot)[None]))
    vel_err = np.linalg.norm(vel - run.truth.velocity[0, -1].numpy())
    pos_err = np.linalg.norm(pos - run.truth.position[0, -1].numpy())
    assert angle_err < 1e-7
    assert vel_err < 1e-6
    assert pos_err < 1e-5


def test_path_evaluate_rejects_times_outside_run(run):
    with pytest.raises(ValueError, match="times must lie"):
        run.path.evaluate(np.array([run.config.duration_s + 10.0]))


def test_terrain_gives_gentle_pitch_and_roll(run):
    rot = run.truth.rotation[0].numpy()
    tilt = np.degrees(np.arccos(np.clip(rot[:, 2, 2], -1, 1)))
    assert 0.5 < tilt.max() < 15.0
    assert dataclasses.is_dataclass(run.config)
