"""Noise tuning by maximum likelihood of the innovations (frontend.tuning), against a
linear-Gaussian system whose noise is known: the filter reduces to a linear KF on
``[p, v]`` (level, known attitude, zero gyro; tests/frontend/test_eskf_filterpy.py), the
data are drawn from that very model (white accelerometer noise of density ``q``, fixes
whose noise is ``SCALE`` times their declared sigmas), and the tuned values must find ``q``
and ``SCALE`` from a start 5x off, without the truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from error_state_checks import level_sequence

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.frontend.tuning import _noise, counted_blocks, innovation_nll, tune_noise

DTYPE = torch.float64
G = 9.80665
ACCEL_DENSITY = 0.3  # m/s^2/sqrt(Hz), the data's
SCALE = 2.0  # the fixes' noise over their declared sigma


def _config(**changes) -> EskfConfig:
    return EskfConfig(
        gyro_noise_density=0.0,
        accel_noise_density=ACCEL_DENSITY,
        gyro_bias_rw_density=0.0,
        accel_bias_rw_density=0.0,
        gravity_mps2=G,
        init_position_sigma_m=0.2,
        init_velocity_sigma_mps=5.0,  # a piece may start moving: velocity 0 +- 5 m/s
        init_roll_pitch_sigma_rad=0.0,
        init_yaw_sigma_rad=0.0,
        init_gyro_bias_sigma_radps=0.0,
        init_accel_bias_sigma_mps2=0.0,
        init_min_gnss_distance_m=1e9,
        nhc="off",
        zupt=False,
        gate_probability=1.0,
        slip_detection=False,
        imu_interpolated_min_samples=0,
    ).replace(**changes)


def _linear_run(seed: int, duration: float, imu_rate: float = 50.0, gnss_every: int = 10):
    """A run drawn from the filter's own linear model: the body (level, not turning) is
    still for its first second, then moves with a smooth random acceleration; the
    accelerometer adds white noise of density ACCEL_DENSITY, each fix noise of SCALE x its
    declared sigma."""
    rng = np.random.default_rng(seed)
    n = int(duration * imu_rate) + 1
    dt = 1.0 / imu_rate
    t = np.arange(n) * dt
    accel = np.zeros((n, 3))
    moving = t > 1.0
    accel[moving] = 0.5 * np.sin(np.outer(t[moving], [0.3, 0.23, 0.11]) + [0.0, 1.0, 2.0])
    accel[:, 2] *= 0.2
    vel = np.concatenate((np.zeros((1, 3)), np.cumsum(accel[:-1] * dt, 0)))
    pos = np.concatenate((np.zeros((1, 3)), np.cumsum(vel[:-1] * dt + 0.5 * accel[:-1] * dt**2, 0)))
    measured = accel + [0.0, 0.0, G] + ACCEL_DENSITY / math.sqrt(dt) * rng.normal(size=(n, 3))
    measured[~moving] = [0.0, 0.0, G]  # level and still: the roll/pitch window reads g
    g_idx = np.arange(0, n, gnss_every)
    sigma = rng.uniform(0.02, 0.06, (g_idx.size, 3))
    fixes = pos[g_idx] + SCALE * sigma * rng.normal(size=(g_idx.size, 3))
    fixes[0] = pos[0]
    seq = level_sequence(f"linear{seed}", t, measured, g_idx, fixes, sigma)
    return seq


def test_gradient_of_the_innovation_likelihood_matches_finite_differences():
    seq = _linear_run(1, 8.0)
    cfg = _config()
    base = EskfNoise.from_config(cfg)
    names = ["accel_noise_density", "gnss_sigma_scale"]
    with torch.no_grad():
        counted = counted_blocks(run_eskf(seq, cfg))

    def objective(theta: torch.Tensor) -> torch.Tensor:
        return innovation_nll(run_eskf(seq, cfg, noise=_noise(base, names, theta)), counted)[0]

    theta = torch.tensor([0.3, -0.2], dtype=DTYPE, requires_grad=True)
    objective(theta).backward()
    step = 1e-5
    numeric = []
    with torch.no_grad():
        for i in range(2):
            shift = torch.zeros(2, dtype=DTYPE)
            shift[i] = step
            numeric.append(float(objective(theta + shift) - objective(theta - shift)) / (2 * step))
    np.testing.assert_allclose(theta.grad.numpy(), numeric, rtol=1e-6)


def test_tuning_finds_the_noise_of_a_linear_system_without_the_truth():
    runs = [_linear_run(seed, 60.0) for seed in (2, 3)]
    start = _config(accel_noise_density=ACCEL_DENSITY / 5.0, gnss_sigma_scale=5.0)
    # one piece per run: a piece cut from the middle would level its attitude from a
    # moving, noisy accelerometer, which this linear reduction holds exact (sigma 0)
    result = tune_noise(
        runs,
        start,
        ["accel_noise_density", "gnss_sigma_scale"],
        piece_s=61.0,
        max_evaluations=20,
    )
    tuned = result.config
    assert tuned.accel_noise_density == pytest.approx(ACCEL_DENSITY, rel=0.15)
    assert tuned.gnss_sigma_scale == pytest.approx(SCALE, rel=0.1)
    assert result.nll_final < result.nll_initial
    # consistent after: a fix's NIS averages its 3 rows
    before, after = result.mean_nis["gnss"]
    assert abs(after - 3.0) < 0.3 < abs(before - 3.0)
    assert result.parameters["gnss_sigma_scale"]["ratio"] == pytest.approx(
        tuned.gnss_sigma_scale / 5.0
    )
    assert result.pieces == 2 and not result.at_bound


def test_the_tuned_config_is_the_noise_that_was_optimised():
    """``_tuned_config`` (what ``msf tune --out`` writes) gives, through
    ``EskfNoise.from_config``, the very noise tensors the objective saw (``_noise``), for
    every tunable key and a pose source, starting from non-default scales."""
    from msf_torch.frontend.tuning import TUNABLE, _tuned_config

    cfg = _config(
        gyro_noise_density=1e-3,
        gyro_bias_rw_density=1e-5,
        accel_bias_rw_density=1e-4,
        gnss_sigma_scale=1.7,
        pose_source_variance_scale={"vo": 0.4, "lidar": 2.0},
    )
    names = [*TUNABLE, "pose:vo", "pose:wheel_odom"]
    theta = torch.linspace(-1.2, 1.5, len(names), dtype=DTYPE)
    optimised = _noise(EskfNoise.from_config(cfg), names, theta)
    written = EskfNoise.from_config(_tuned_config(cfg, names, theta.tolist()))
    for field in (
        "wheel_speed_sigma",
        "wheel_lateral_sigma",
        "wheel_yaw_rate_sigma",
        "nhc_sigma",
        "zupt_sigma",
        "gnss_sigma_scale",
    ):
        torch.testing.assert_close(getattr(written, field), getattr(optimised, field))
    for density in (
        "gyro_noise_density",
        "accel_noise_density",
        "gyro_bias_rw_density",
        "accel_bias_rw_density",
    ):
        torch.testing.assert_close(getattr(written.imu, density), getattr(optimised.imu, density))
    assert set(written.pose_source_scale) == {"vo", "lidar", "wheel_odom"}
    for name, value in optimised.pose_source_scale.items():
        torch.testing.assert_close(
            written.pose_source_scale[name], torch.as_tensor(value, dtype=DTYPE)
        )
