"""The initial yaw's sigma against a Monte Carlo of the initialiser itself.

One fixed planar drive (curving, speed varying) is read B times with fresh sensor noise: a
turn-on gyro bias, gyro white noise, and GNSS fixes with different east and north sigmas.
``initial_state`` aligns each dead-reckoned track with its fixes (2-D Kabsch); the spread
of its yaw errors over the draws is the reference the modelled variance
(``frontend.init.alignment_yaw_variance``) must match; the gain by which the yaw error
follows the gyro bias is checked against the regression of one on the other. The two settings
have true sigmas far from the old constant 0.05 rad (about 0.02 and 0.075 rad), so a
constant fails the test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.init import alignment_yaw_variance, initial_state
from msf_torch.types import GnssFixes, ImuSamples, Sequence, WheelSamples

RATE_HZ = 100.0
DURATION_S = 30.0
YAW0 = 0.7  # true initial heading, rad


def drive() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Times (N,) s, speed (N,) m/s, yaw rate (N,) rad/s and positions (N, 2) m of the drive,
    integrated with the initialiser's own rule (heading and position at sample k from the
    samples before it), so that noise-free readings reproduce it exactly."""
    t = np.arange(int(DURATION_S * RATE_HZ) + 1) / RATE_HZ
    speed = 1.5 + 0.4 * np.sin(2 * math.pi * t / 23.0)
    yaw_rate = 0.25 * np.cos(2 * math.pi * t / 17.0) + 0.02
    dt = np.diff(t, append=t[-1])
    heading = YAW0 + np.cumsum(yaw_rate * dt) - yaw_rate * dt
    step = np.stack((speed * np.cos(heading), speed * np.sin(heading)), 1) * dt[:, None]
    position = np.vstack((np.zeros(2), np.cumsum(step, 0)[:-1]))
    return t, speed, yaw_rate, position


def readings(
    draws: int, gyro_bias_sigma: float, gyro_density: float, fix_sigma: tuple[float, float]
) -> tuple[Sequence, np.ndarray]:
    """``draws`` noisy readings of :func:`drive` as one batch, and the drawn yaw gyro biases
    (draws,) rad/s. GNSS at 1 Hz on IMU sample times; the wheels read the speed exactly."""
    rng = np.random.default_rng(7)
    t, speed, yaw_rate, position = drive()
    n = t.size
    bias = rng.normal(0.0, gyro_bias_sigma, draws)
    gyro = np.zeros((draws, n, 3))
    gyro[..., 2] = (
        yaw_rate + bias[:, None] + rng.normal(0.0, gyro_density * RATE_HZ**0.5, (draws, n))
    )
    accel = np.broadcast_to(np.array([0.0, 0.0, 9.80665]), (draws, n, 3))
    fixes = np.arange(0, n, int(RATE_HZ))
    sigma = np.array([*fix_sigma, 1.0])
    gnss = np.concatenate((position[fixes], np.zeros((fixes.size, 1))), 1)
    gnss = gnss + rng.normal(0.0, 1.0, (draws, fixes.size, 3)) * sigma

    def tensor(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    every = torch.ones(draws, n, dtype=torch.bool)
    times = tensor(np.broadcast_to(t, (draws, n)))
    seq = Sequence(
        names=[f"draw{i}" for i in range(draws)],
        imu=ImuSamples(t=times, gyro=tensor(gyro), accel=tensor(accel), mask=every),
        wheel=WheelSamples(
            t=times,
            left_speed=tensor(np.broadcast_to(speed, (draws, n))),
            right_speed=tensor(np.broadcast_to(speed, (draws, n))),
            mask=every,
        ),
        gnss=GnssFixes(
            t=tensor(np.broadcast_to(t[fixes], (draws, fixes.size))),
            position=tensor(gnss),
            sigma=tensor(np.broadcast_to(sigma, (draws, fixes.size, 3))),
            mask=torch.ones(draws, fixes.size, dtype=torch.bool),
        ),
    )
    return seq, bias


@pytest.mark.parametrize(
    ("gyro_bias_sigma", "gyro_density", "fix_sigma"),
    [
        (0.0, 5e-3, (0.3, 0.8)),  # angle random walk and anisotropic fixes: ~0.02 rad
        (1e-2, 1e-4, (1.0, 1.0)),  # turn-on bias dominates: ~0.075 rad
    ],
)
def test_yaw_sigma_matches_monte_carlo(gyro_bias_sigma, gyro_density, fix_sigma):
    draws = 1000
    seq, bias = readings(draws, gyro_bias_sigma, gyro_density, fix_sigma)
    cfg = EskfConfig(
        init_gyro_bias_sigma_radps=max(gyro_bias_sigma, 1e-9),
        gyro_noise_density=gyro_density,
        init_yaw_sigma_rad=1e-6,  # no floor: the model alone
        init_max_track_s=DURATION_S,
    )
    state, cov = initial_state(seq, cfg)
    yaw = torch.atan2(state.rotation[:, 1, 0], state.rotation[:, 0, 0]).numpy()
    error = np.angle(np.exp(1j * (YAW0 - yaw)))  # truth minus estimate, rad
    model = cov[:, 8, 8].numpy()
    # the sample variance of N(0, s^2) draws is s^2 chi2(n - 1) / (n - 1): two-sided 99.9 %
    low, high = stats.chi2.ppf([0.0005, 0.9995], draws - 1) / (draws - 1)
    empirical = float(np.mean(error**2))
    ratio = empirical / float(model.mean())
    assert low <= ratio <= high, (ratio, empirical**0.5, model.mean() ** 0.5)
    # the old constant fails the same test
    assert not low <= empirical / 0.05**2 <= high, empirical**0.5
    if gyro_bias_sigma > 0:
        # the gain by which the yaw error follows the gyro bias, on the noise-free drive,
        # against the regression slope of the drawn errors on the drawn biases
        t, _, _, position = drive()
        fixes = np.arange(0, t.size, int(RATE_HZ))
        # the fixes the initialiser fits: up to init_min_gnss_distance_m from the first
        reach = np.linalg.norm(position[fixes] - position[0], axis=1)
        fixes = fixes[: int(np.argmax(reach >= cfg.init_min_gnss_distance_m)) + 1]
        track = position[fixes] - position[fixes].mean(0)
        step = np.diff(position, axis=0, append=position[-1:])
        inside = t <= t[fixes[-1]]
        _, gain = alignment_yaw_variance(
            track, np.ones_like(track), t[fixes], t[inside], step[inside], 0.0, 0.0
        )
        slope, _, _, _, slope_err = stats.linregress(bias, error)
        assert abs(slope - gain) <= 4 * slope_err + 0.02 * abs(gain), (slope, slope_err, gain)


def test_alignment_variance_of_fix_noise_on_a_line():
    """Isotropic fixes along a straight centred track, no gyro error: ``sigma^2 / sum r^2``."""
    track = np.stack((np.linspace(-10.0, 10.0, 21), np.zeros(21)), 1)
    var, gain = alignment_yaw_variance(
        track, np.full((21, 2), 0.5), np.arange(21.0), np.zeros(1), np.zeros((1, 2)), 1e-3, 1e-4
    )
    assert var == pytest.approx(0.25 / 770.0, rel=1e-12)
    assert gain == 0.0
