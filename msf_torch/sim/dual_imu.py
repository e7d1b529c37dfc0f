"""Redundant IMUs on one body: N MEMS IMUs with datasheet noise, static or moving, with truth.

Noise models (:class:`~msf_torch.sim.wheeled.ImuNoiseSpec`, continuous-time densities):

* **TDK InvenSense ICM-20602** (datasheet DS-000176, typical values): gyro rate noise
  spectral density 0.004 deg/s/sqrt(Hz); accelerometer noise spectral density
  100 micro-g/sqrt(Hz).
* **TDK InvenSense ICM-20689** (datasheet DS-000143, typical values): gyro rate noise
  spectral density 0.008 deg/s/sqrt(Hz); accelerometer noise spectral density
  100 micro-g/sqrt(Hz).

These are the figures as we know them from the datasheets' sensor-specification tables; the
datasheets themselves could not be re-read in this offline session, so check them against
the PDFs before relying on the second digit. Neither datasheet specifies in-run bias
stability (they give board-level initial offsets: gyro +-1 deg/s, accelerometer +-25 to
+-60 mg, which a start-up calibration removes). The bias model below is therefore an
**assumption**, of the order that Allan-deviation studies report for consumer six-axis MEMS
of this class: in-run gyro bias instability 5 deg/h (ICM-20602) and 8 deg/h (ICM-20689),
accelerometer 40 and 60 micro-g, each turned into a random walk over tau = 100 s
(``rw = instability / sqrt(tau)``, the convention of ``ImuNoiseSpec.adis16470``); residual
turn-on offsets after a static calibration, 1 sigma per axis: gyro 0.05 deg/s,
accelerometer 2 mg (the same for both parts).

Scenarios (truth sampled at ``rate_hz``):

* ``"static"``: the body at rest with a random tilt (roll, pitch uniform in +-10 deg, yaw
  uniform), ``omega = 0``, ``f = R^T [0, 0, g]``;
* ``"moving"``: the wheeled robot of :mod:`msf_torch.sim.wheeled` (``simulate_run`` with a
  perfect IMU gives the truth: attitude over 5-degree terrain, turns and speed changes, so
  linear accelerations of a few tenths of m/s^2 that an accelerometer cannot tell from
  gravity).

Random streams: the path and the static attitude come from the run seed; each IMU's
turn-on offsets from its **unit seed** (the same physical pair keeps its offsets across
runs, so weights calibrated on one run of a pair can be tested on another); white noise and
bias walks from the run seed, independently per IMU.

Example:
    >>> run = simulate_dual_imu("static", run_seeds=[1, 2], unit_seeds=[10, 11], duration_s=2.0)
    >>> run.gyro.shape
    torch.Size([2, 2, 201, 3])
"""

from __future__ import annotations

__all__ = [
    "SCENARIOS",
    "icm20602_noise",
    "icm20689_noise",
    "DualImuRun",
    "simulate_dual_imu",
]

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.geometry.conventions import STANDARD_GRAVITY
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sim.wheeled import ImuNoiseSpec, SimConfig, simulate_run

SCENARIOS = ("static", "moving")

_DEG = math.pi / 180.0
_MICRO_G = 1e-6 * STANDARD_GRAVITY
_TAU_S = 100.0  # bias correlation time of the random-walk model
_TURN_ON_GYRO = 0.05 * _DEG  # rad/s, residual after a static calibration (assumption)
_TURN_ON_ACCEL = 2e-3 * STANDARD_GRAVITY  # m/s^2, residual after calibration (assumption)


def _spec(
    name: str, gyro_dps_rthz: float, accel_ug_rthz: float, gyro_bi_dph: float, accel_bi_ug: float
) -> ImuNoiseSpec:
    root_tau = math.sqrt(_TAU_S)
    return ImuNoiseSpec(
        gyro_noise_density=gyro_dps_rthz * _DEG,
        accel_noise_density=accel_ug_rthz * _MICRO_G,
        gyro_bias_rw_density=gyro_bi_dph * _DEG / 3600.0 / root_tau,
        accel_bias_rw_density=accel_bi_ug * _MICRO_G / root_tau,
        gyro_bias_sigma0=_TURN_ON_GYRO,
        accel_bias_sigma0=_TURN_ON_ACCEL,
        name=name,
    )


def icm20602_noise() -> ImuNoiseSpec:
    """TDK InvenSense ICM-20602: 0.004 deg/s/sqrt(Hz) = 6.98e-5 rad/s/sqrt(Hz) gyro,
    100 micro-g/sqrt(Hz) = 9.81e-4 m/s^2/sqrt(Hz) accelerometer (datasheet DS-000176);
    bias instability and turn-on residuals assumed (module docstring)."""
    return _spec("ICM-20602", 0.004, 100.0, 5.0, 40.0)


def icm20689_noise() -> ImuNoiseSpec:
    """TDK InvenSense ICM-20689: 0.008 deg/s/sqrt(Hz) = 1.40e-4 rad/s/sqrt(Hz) gyro,
    100 micro-g/sqrt(Hz) = 9.81e-4 m/s^2/sqrt(Hz) accelerometer (datasheet DS-000143);
    bias instability and turn-on residuals assumed (module docstring)."""
    return _spec("ICM-20689", 0.008, 100.0, 8.0, 60.0)


@dataclass
class DualImuRun:
    """B runs of N IMUs on one body, float64 CPU tensors.

    Attributes:
        t: (T,) sample times, s (shared by all runs and IMUs).
        gyro: (B, N, T, 3) rad/s.
        accel: (B, N, T, 3) m/s^2.
        rotation: (B, T, 3, 3) true body -> world.
        quaternion: (B, T, 4) the same, ``[w, x, y, z]``.
        angular_velocity: (B, T, 3) true body rate, rad/s.
        specific_force: (B, T, 3) true, m/s^2.
        gyro_bias, accel_bias: (B, N, T, 3) the biases in the samples.
        specs: the N noise models.
        scenario: ``"static"`` or ``"moving"``.
        run_seeds, unit_seeds: the seeds used.
    """

    t: torch.Tensor
    gyro: torch.Tensor
    accel: torch.Tensor
    rotation: torch.Tensor
    quaternion: torch.Tensor
    angular_velocity: torch.Tensor
    specific_force: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor
    specs: tuple[ImuNoiseSpec, ...]
    scenario: str
    run_seeds: tuple[int, ...]
    unit_seeds: tuple[int, ...]

    @property
    def dt(self) -> float:
        """Sample interval, s."""
        return float(self.t[1] - self.t[0])


def _static_truth(seed: int, n_samples: int, gravity: float) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    roll, pitch = rng.uniform(-10.0, 10.0, 2) * _DEG
    yaw = rng.uniform(-math.pi, math.pi)
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rot = np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    force = rot.T @ np.array([0.0, 0.0, gravity])
    return (
        np.broadcast_to(rot, (n_samples, 3, 3)),
        np.zeros((n_samples, 3)),
        np.broadcast_to(force, (n_samples, 3)),
    )


def _moving_truth(seed: int, duration_s: float, rate_hz: float) -> tuple[np.ndarray, ...]:
    config = SimConfig(
        duration_s=duration_s,
        imu_rate_hz=rate_hz,
        imu_noise=ImuNoiseSpec.zero(),
        terrain_slope_deg=5.0,
    )
    truth = simulate_run(config, seed).truth
    return (
        truth.rotation[0].numpy(),
        truth.angular_velocity[0].numpy(),
        truth.specific_force[0].numpy(),
    )


def simulate_dual_imu(
    scenario: str,
    run_seeds: Sequence[int],
    unit_seeds: Sequence[int],
    duration_s: float = 60.0,
    rate_hz: float = 100.0,
    specs: Sequence[ImuNoiseSpec] | None = None,
) -> DualImuRun:
    """Simulate B runs (one per run seed) of the N IMUs in ``specs`` on one body.

    Args:
        scenario: ``"static"`` or ``"moving"``.
        run_seeds: B non-negative ints (truth, white noise, bias walks).
        unit_seeds: B ints, the physical unit pair of each run (turn-on offsets); repeat a
            unit seed to test the same hardware in another run.
        duration_s: run length, s (samples at ``0, dt, ..., duration_s``).
        rate_hz: IMU rate, Hz.
        specs: N >= 1 noise models; default ``(icm20602_noise(), icm20689_noise())``.
    Returns:
        :class:`DualImuRun`.
    Raises:
        ValueError: unknown scenario, mismatched seed lists, non-positive duration or rate.
    """
    if scenario not in SCENARIOS:
        raise ValueError(
            f"simulate_dual_imu: scenario must be one of {SCENARIOS}, got {scenario!r}"
        )
    if len(run_seeds) != len(unit_seeds) or not run_seeds:
        raise ValueError("simulate_dual_imu: run_seeds and unit_seeds need the same length >= 1")
    if not (duration_s > 0 and rate_hz > 0):
        raise ValueError("simulate_dual_imu: duration_s and rate_hz must be > 0")
    specs = tuple(specs) if specs is not None else (icm20602_noise(), icm20689_noise())
    dt = 1.0 / rate_hz
    n_samples = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n_samples) * dt
    gyro, accel, gyro_bias, accel_bias, rots, rates, forces = [], [], [], [], [], [], []
    for run_seed, unit_seed in zip(run_seeds, unit_seeds, strict=True):
        if scenario == "static":
            rot, omega, force = _static_truth(int(run_seed), n_samples, STANDARD_GRAVITY)
        else:
            rot, omega, force = _moving_truth(int(run_seed), duration_s, rate_hz)
        rots.append(rot)
        rates.append(omega)
        forces.append(force)
        unit_streams = np.random.SeedSequence([int(unit_seed), 20602]).spawn(len(specs))
        run_streams = np.random.SeedSequence([int(run_seed), 20689]).spawn(len(specs))
        per_imu = ([], [], [], [])
        for spec, unit_stream, run_stream in zip(specs, unit_streams, run_streams, strict=True):
            unit_rng, run_rng = (
                np.random.default_rng(unit_stream),
                np.random.default_rng(run_stream),
            )
            offset_g = unit_rng.normal(0.0, spec.gyro_bias_sigma0, 3)
            offset_a = unit_rng.normal(0.0, spec.accel_bias_sigma0, 3)
            step_g, step_a = spec.bias_step_sigmas(dt)
            white_g, white_a = spec.white_sigmas(dt)
            walk_g = np.cumsum(run_rng.normal(0.0, step_g, (n_samples, 3)), 0)
            walk_a = np.cumsum(run_rng.normal(0.0, step_a, (n_samples, 3)), 0)
            bias_g = offset_g + walk_g - walk_g[:1]
            bias_a = offset_a + walk_a - walk_a[:1]
            per_imu[0].append(omega + bias_g + run_rng.normal(0.0, white_g, (n_samples, 3)))
            per_imu[1].append(force + bias_a + run_rng.normal(0.0, white_a, (n_samples, 3)))
            per_imu[2].append(bias_g)
            per_imu[3].append(bias_a)
        for out, values in zip((gyro, accel, gyro_bias, accel_bias), per_imu, strict=True):
            out.append(np.stack(values))

    def tensor(values: list[np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.stack(values), dtype=np.float64))

    rotation = tensor(rots)
    return DualImuRun(
        t=torch.from_numpy(t),
        gyro=tensor(gyro),
        accel=tensor(accel),
        rotation=rotation,
        quaternion=matrix_to_quat(rotation),
        angular_velocity=tensor(rates),
        specific_force=tensor(forces),
        gyro_bias=tensor(gyro_bias),
        accel_bias=tensor(accel_bias),
        specs=specs,
        scenario=scenario,
        run_seeds=tuple(int(s) for s in run_seeds),
        unit_seeds=tuple(int(s) for s in unit_seeds),
    )
