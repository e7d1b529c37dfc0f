"""Dual-IMU simulator (sim/dual_imu.py): datasheet conversions, noise statistics, truth, seeds."""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.geometry.conventions import STANDARD_GRAVITY
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.dual_imu import icm20602_noise, icm20689_noise, simulate_dual_imu
from msf_torch.sim.wheeled import ImuNoiseSpec


def test_datasheet_conversions():
    a, b = icm20602_noise(), icm20689_noise()
    deg = math.pi / 180
    assert a.gyro_noise_density == pytest.approx(0.004 * deg)  # 6.98e-5 rad/s/sqrt(Hz)
    assert b.gyro_noise_density == pytest.approx(0.008 * deg)
    assert a.accel_noise_density == pytest.approx(100e-6 * STANDARD_GRAVITY)
    assert b.accel_noise_density == pytest.approx(100e-6 * STANDARD_GRAVITY)
    # bias instability / sqrt(100 s): 5 deg/h and 40 micro-g for the ICM-20602
    assert a.gyro_bias_rw_density == pytest.approx(5 * deg / 3600 / 10)
    assert a.accel_bias_rw_density == pytest.approx(40e-6 * STANDARD_GRAVITY / 10)
    assert (a.name, b.name) == ("ICM-20602", "ICM-20689")


def test_static_noise_statistics_and_truth():
    run = simulate_dual_imu("static", [5], [9], duration_s=200.0, rate_hz=100.0)
    assert run.gyro.shape == (1, 2, 20001, 3)
    rot = run.rotation[0, 0]
    force = rot.mT @ torch.tensor([0.0, 0.0, STANDARD_GRAVITY], dtype=torch.float64)
    torch.testing.assert_close(run.specific_force[0, 0], force)
    roll_pitch = torch.stack((torch.atan2(rot[2, 1], rot[2, 2]), -torch.asin(rot[2, 0])))
    assert float(roll_pitch.abs().max()) <= 10 * math.pi / 180
    for n, spec in enumerate(run.specs):
        white_g, white_a = spec.white_sigmas(run.dt)
        gyro_noise = run.gyro[0, n] - run.gyro_bias[0, n]
        accel_noise = run.accel[0, n] - run.accel_bias[0, n] - force
        torch.testing.assert_close(
            gyro_noise.std(0), torch.full((3,), white_g, dtype=torch.float64), rtol=0.03, atol=0
        )
        torch.testing.assert_close(
            accel_noise.std(0), torch.full((3,), white_a, dtype=torch.float64), rtol=0.03, atol=0
        )
        # the bias walk's increments have the random-walk sigma
        steps = run.gyro_bias[0, n].diff(dim=0).std(0)
        step_g, _ = spec.bias_step_sigmas(run.dt)
        torch.testing.assert_close(
            steps, torch.full((3,), step_g, dtype=torch.float64), rtol=0.03, atol=0
        )


def test_unit_seed_keeps_the_turn_on_offsets():
    run = simulate_dual_imu("static", [1, 2, 3], [7, 7, 8], duration_s=1.0)
    first = run.accel_bias[:, :, 0]
    torch.testing.assert_close(first[0], first[1], atol=0, rtol=0)  # same unit pair
    assert float((first[0] - first[2]).abs().max()) > 0  # another pair
    assert float((run.gyro[0] - run.gyro[1]).abs().max()) > 0  # independent run noise


def test_moving_truth_is_the_wheeled_robot():
    run = simulate_dual_imu("moving", [4], [4], duration_s=5.0, rate_hz=50.0)
    config = SimConfig(
        duration_s=5.0, imu_rate_hz=50.0, imu_noise=ImuNoiseSpec.zero(), terrain_slope_deg=5.0
    )
    truth = simulate_run(config, 4).truth
    torch.testing.assert_close(run.rotation, truth.rotation)
    torch.testing.assert_close(run.angular_velocity, truth.angular_velocity)
    assert float(run.angular_velocity.abs().max()) > 0.05


def test_argument_checks():
    with pytest.raises(ValueError, match="scenario"):
        simulate_dual_imu("flying", [1], [1])
    with pytest.raises(ValueError, match="same length"):
        simulate_dual_imu("static", [1, 2], [1])
