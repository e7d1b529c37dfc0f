"""Back-end preintegration between keyframes.

References: ``zoh_step`` looped sample by sample in the world frame (direct integration),
the simulator's continuous ground truth, re-integration with a changed bias, an autograd
Jacobian of the increments w.r.t. the noise of every sample (for the recursive covariance),
and closed-form constant-rate arcs for the wheels.
"""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.backend.preintegration import (
    ImuIntervals,
    cut_imu,
    preintegrate_imu,
    preintegrate_wheel,
    recursive_covariance,
)
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.imu import preintegrate, propagate_nominal, zoh_step
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.wheeled import ImuNoiseSpec

DTYPE = torch.float64
GRAVITY = gravity_world()


def _noise_free_run(duration: float = 12.0):
    config = SimConfig(duration_s=duration, imu_noise=ImuNoiseSpec.zero(), slip_episodes=0)
    return simulate_run(config, seed=3)


def test_cut_imu_splits_samples_at_keyframe_times():
    times = torch.arange(0.0, 1.0001, 0.1, dtype=DTYPE)
    gyro = torch.arange(times.numel() * 3, dtype=DTYPE).reshape(-1, 3)
    keyframes = torch.tensor([0.05, 0.33, 0.33 + 1e-9, 0.9], dtype=DTYPE)
    cut = cut_imu(times, gyro, gyro, keyframes)
    torch.testing.assert_close(cut.dt.sum(-1), keyframes.diff(), rtol=0, atol=1e-15)
    # first interval: half of sample 0, samples 1 and 2, 0.03 s of sample 3
    torch.testing.assert_close(cut.dt[0, :4], torch.tensor([0.05, 0.1, 0.1, 0.03], dtype=DTYPE))
    torch.testing.assert_close(cut.gyro[0, :4], gyro[:4])
    torch.testing.assert_close(cut.gyro[1, 0], gyro[3])


def test_increments_equal_direct_integration_of_simulated_imu():
    run = _noise_free_run()
    imu = run.sequence.imu
    times = imu.t[0]
    keyframes = torch.tensor([0.5, 1.737, 3.0, 4.2501, 7.9, 11.0], dtype=DTYPE)
    cut = cut_imu(times, imu.gyro[0], imu.accel[0], keyframes)
    zero = torch.zeros(keyframes.numel() - 1, 3, dtype=DTYPE)
    pre = preintegrate_imu(cut, zero, zero)
    # direct integration: zoh_step from the true state at keyframe i, piece by piece
    for k in range(keyframes.numel() - 1):
        t0 = keyframes[k]
        p, v, r = _truth_at(run, t0)
        p_i, v_i, r_i = p, v, r
        for piece in range(cut.dt.shape[1]):
            p, v, r = zoh_step(
                p, v, r, cut.gyro[k, piece], cut.accel[k, piece], cut.dt[k, piece], GRAVITY
            )
        pred_p, pred_v, pred_r = propagate_nominal(
            p_i,
            v_i,
            r_i,
            pre.delta_t[k],
            pre.delta_rotation[k],
            pre.delta_velocity[k],
            pre.delta_position[k],
            GRAVITY,
        )
        torch.testing.assert_close(pred_p, p, rtol=0, atol=1e-9)
        torch.testing.assert_close(pred_v, v, rtol=0, atol=1e-10)
        torch.testing.assert_close(pred_r, r, rtol=0, atol=1e-12)
        # and the continuous truth at keyframe j, within the ZOH discretisation error (200 Hz)
        q, w, s = _truth_at(run, keyframes[k + 1])
        assert (pred_p - q).norm() < 5e-3 * float(pre.delta_t[k]) ** 2 + 1e-3
        assert (pred_v - w).norm() < 5e-3
        assert so3.log(s.mT @ pred_r).norm() < 1e-3


def _truth_at(run, t: torch.Tensor):
    """Continuous truth from the simulator's analytic path at time t (s)."""
    state = run.path.evaluate(t.reshape(1).numpy())
    return (
        torch.as_tensor(state.position[0], dtype=DTYPE),
        torch.as_tensor(state.velocity[0], dtype=DTYPE),
        torch.as_tensor(state.rotation[0], dtype=DTYPE),
    )


def test_bias_correction_is_first_order_exact():
    gen = torch.Generator().manual_seed(7)
    gyro = 0.8 * torch.randn(200, 3, generator=gen, dtype=DTYPE)
    accel = torch.randn(200, 3, generator=gen, dtype=DTYPE) + torch.tensor(
        [0.0, 0.0, 9.8], dtype=DTYPE
    )
    dt = torch.full((200,), 0.005, dtype=DTYPE)
    bias_g = torch.tensor([0.01, -0.02, 0.005], dtype=DTYPE)
    bias_a = torch.tensor([0.1, 0.05, -0.2], dtype=DTYPE)
    pre = preintegrate_imu(ImuIntervals(gyro, accel, dt), bias_g, bias_a)
    direction_g = torch.tensor([0.3, -0.5, 0.8], dtype=DTYPE)
    direction_a = torch.tensor([-0.6, 0.2, 0.4], dtype=DTYPE)
    errors = []
    for size in (1e-2, 5e-3):
        new_g, new_a = bias_g + size * direction_g, bias_a + size * 10 * direction_a
        rot, vel, pos = pre.corrected(new_g, new_a)
        again = preintegrate(gyro, accel, dt, new_g, new_a)
        errors.append(
            max(
                float(so3.log(again.delta_rotation.mT @ rot).norm()),
                float((again.delta_velocity - vel).norm()),
                float((again.delta_position - pos).norm()),
            )
        )
    # second-order remainder: halving the change quarters the error
    assert errors[0] < 1e-3
    assert 3.0 < errors[0] / errors[1] < 5.0


@pytest.mark.parametrize("per_axis", [False, True])
def test_recursive_covariance_equals_noise_jacobian(per_axis):
    """The recursion against autograd noise Jacobians; ``per_axis``: every sample's six
    channels with their own variance multipliers (the smoothers' IMU-gap model)."""
    gen = torch.Generator().manual_seed(11)
    count = 60
    gyro = 1.2 * torch.randn(count, 3, generator=gen, dtype=DTYPE)
    accel = 3.0 * torch.randn(count, 3, generator=gen, dtype=DTYPE)
    dt = 0.01 + 0.01 * torch.rand(count, generator=gen, dtype=DTYPE)
    scales = (
        1.0 + 50.0 * torch.rand(2, count, 3, generator=gen, dtype=DTYPE)
        if per_axis
        else torch.ones(2, count, 3, dtype=DTYPE)
    )
    zero = torch.zeros(3, dtype=DTYPE)
    nominal = preintegrate(gyro, accel, dt, zero, zero)

    def errors(noise_g: torch.Tensor, noise_a: torch.Tensor) -> torch.Tensor:
        pre = preintegrate(gyro + noise_g, accel + noise_a, dt, zero, zero)
        theta = so3.log(nominal.delta_rotation.mT @ pre.delta_rotation)
        return torch.cat((pre.delta_position, pre.delta_velocity, theta))

    zeros = torch.zeros(count, 3, dtype=DTYPE)
    jac_g, jac_a = torch.autograd.functional.jacobian(errors, (zeros, zeros))
    weight = [(scale / dt[:, None]).reshape(-1) for scale in scales]
    expect_g = (jac_g.reshape(9, -1) * weight[0]) @ jac_g.reshape(9, -1).T
    expect_a = (jac_a.reshape(9, -1) * weight[1]) @ jac_a.reshape(9, -1).T
    if per_axis:
        cov_g, cov_a = recursive_covariance(gyro, accel, dt, zero, zero, *scales)
    else:
        cov_g, cov_a = recursive_covariance(gyro, accel, dt, zero, zero)
    torch.testing.assert_close(cov_g, expect_g, rtol=1e-9, atol=1e-15)
    torch.testing.assert_close(cov_a, expect_a, rtol=1e-9, atol=1e-15)
    if not per_axis:  # the filter's closed form agrees to O(|w| dt)
        assert (nominal.cov_unit_gyro - cov_g).abs().max() / cov_g.abs().max() < 5e-2


def test_wheel_increment_constant_arc_and_covariance():
    speed, yaw_rate, track = 1.5, 0.4, 0.6
    count, step = 50, 0.02
    left = torch.full((count,), speed - yaw_rate * track / 2, dtype=DTYPE)
    right = torch.full((count,), speed + yaw_rate * track / 2, dtype=DTYPE)
    dt = torch.full((count,), step, dtype=DTYPE)
    increment, cov = preintegrate_wheel(left, right, dt, track, 0.05)
    total = count * step
    expect = torch.tensor(
        [
            speed / yaw_rate * math.sin(yaw_rate * total),
            speed / yaw_rate * (1 - math.cos(yaw_rate * total)),
            yaw_rate * total,
        ],
        dtype=DTYPE,
    )
    torch.testing.assert_close(increment, expect, rtol=0, atol=1e-12)

    def increment_of(speeds: torch.Tensor) -> torch.Tensor:
        return preintegrate_wheel(speeds[:count], speeds[count:], dt, track, 0.05)[0]

    jac = torch.autograd.functional.jacobian(increment_of, torch.cat((left, right)))
    torch.testing.assert_close(cov, 0.05**2 * jac @ jac.T, rtol=1e-9, atol=1e-15)
    slipping = preintegrate_wheel(
        left, right, dt, track, 0.05, slip=torch.full((count,), 0.5, dtype=DTYPE)
    )[1]
    torch.testing.assert_close(slipping, 4.0 * cov)
