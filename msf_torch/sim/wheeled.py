"""Labelled wheeled-robot runs with known truth: IMU, wheel encoders, GNSS, slip, outages.

The truth is a smooth 3D ground trajectory built from analytic functions of time:

* horizontal speed ``s(t) = s_mean (1 + sum_k a_k sin(w_k t + phi_k))`` (never below
  ``s_mean (1 - speed_variation)``);
* heading ``psi(t) = psi_0 + r_0 t + sum_k A_k sin(w_k t + phi_k)`` (the direction of travel);
* horizontal position ``(x, y)(t) = integral_0^t s [cos psi, sin psi] dt`` (8-point
  Gauss-Legendre on 0.1 s knots: exact to machine precision for these smooth integrands);
* height ``z = h(x, y)``, a sum of a few 2D sinusoids with slopes of a few degrees.

Attitude follows the ground: body x is the unit velocity (the robot drives forward, so the
body-frame velocity is exactly ``[v, 0, 0]``), body z is the terrain normal (orthogonal to the
velocity because the velocity is tangent to the surface), body y = z x x. Angular velocity
(body) and specific force ``f = R^T (a - g_world)`` (body) are the instantaneous values of
the continuous truth from analytic first and second derivatives (chain rule through the
terrain gradient and Hessian), not finite differences.

Sensors (conventions in :mod:`msf_torch.geometry.conventions`):

* IMU at ``imu_rate_hz``: ``gyro = omega + b_g + n_g``, ``accel = f + b_a + n_a``, white
  noise with ``sigma = density / sqrt(dt)``, biases a random walk with increment
  ``sigma = rw_density * sqrt(dt)`` from a turn-on value ``N(0, sigma0^2)``. Default noise:
  Analog Devices ADIS16470 (:meth:`ImuNoiseSpec.adis16470`).
* Wheels (differential drive, track ``D``) at ``wheel_rate_hz``: true rim speeds
  ``v_l = v - omega_z D / 2``, ``v_r = v + omega_z D / 2`` from the body forward speed ``v``
  and the body yaw rate ``omega_z``; read as ``true * (1 + e) * slip_factor + noise``, then
  counted as encoder ticks (see :func:`simulate_run`).
* GNSS at ``gnss_rate_hz``: antenna position ``p + R @ lever_arm`` plus Gaussian noise, no
  fixes inside outages. With ``gnss_velocity``, at the same times the antenna velocity
  ``v + R (omega x lever_arm)`` plus Gaussian noise of ``gnss_velocity_sigma_mps``
  (``Sequence.gnss_velocity``, a receiver's Doppler velocity), also none inside outages.
  With ``gnss_heading``, at the same times a dual-antenna heading: the azimuth of
  ``R @ gnss_heading_baseline_m`` clockwise from north plus Gaussian noise of
  ``gnss_heading_sigma_rad``, in [0, 2 pi) (``Sequence.gnss_heading``), none inside outages.
* With ``magnetometer``, a three-axis magnetometer at ``magnetometer_rate_hz``
  (``Sequence.magnetometer``): the earth's field seen in the body, soft- and hard-iron
  distorted, with local anomalies along the route (:mod:`msf_torch.sim.magnetometer`;
  label ``"magnetic_anomaly"``).

Labels (``Sequence.labels``, (1, K, 2) intervals ``[t_start, t_end]`` in s): ``"slip"``
(episode types in ``meta["sensor"]["slip_types"]``, details in ``meta["slip_episodes"]``) and
``"gnss_outage"``.

Example:
    >>> from msf_torch.sim import sample_slip_config, simulate_run
    >>> run = simulate_run(sample_slip_config(), seed=7)
    >>> run.sequence.imu.gyro.shape
    torch.Size([1, 24001, 3])
    >>> run.sequence.labels["slip"].shape
    torch.Size([1, 3, 2])
"""

from __future__ import annotations

__all__ = [
    "SLIP_TYPES",
    "ImuNoiseSpec",
    "SimConfig",
    "GroundPath",
    "PathState",
    "SlipEpisode",
    "SimTruth",
    "SimulatedRun",
    "simulate_run",
    "default_slip_config",
    "gnss_denied_slip_config",
    "sample_slip_config",
]

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.conventions import STANDARD_GRAVITY
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sim.magnetometer import simulate_magnetometer
from msf_torch.types import (
    GnssFixes,
    GnssHeading,
    GnssVelocity,
    ImuSamples,
    Magnetometer,
    Sequence,
    Trajectory,
    WheelSamples,
)

SLIP_TYPES: tuple[str, ...] = ("spin", "skid", "lock")
"""Slip episode types: ``spin`` (both wheels read ``true * (1 + s)``), ``skid`` (one wheel
reads ``true * (1 +/- s)``, a yaw-rate disagreement), ``lock`` (both wheels read
``true * (1 - s)``, down to zero while the robot keeps moving, e.g. sliding downhill)."""

_DEG = math.pi / 180.0

# Analog Devices ADIS16470, datasheet Rev. C, typical values.
_ADIS16470_ARW_DEG_SQRT_H = 0.34  # angular random walk, deg/sqrt(h)
_ADIS16470_GYRO_INSTABILITY_DEG_H = 8.0  # in-run gyro bias stability, deg/h
_ADIS16470_VRW_M_S_SQRT_H = 0.037  # velocity random walk, m/s/sqrt(h)
_ADIS16470_ACCEL_INSTABILITY_UG = 13.0  # in-run accel bias stability, micro-g

_GL8_NODES, _GL8_WEIGHTS = np.polynomial.legendre.leggauss(8)
_GL4_NODES, _GL4_WEIGHTS = np.polynomial.legendre.leggauss(4)


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuNoiseSpec:
    """Continuous-time IMU noise densities and turn-on bias spread.

    Discretised at sample interval ``dt``: white noise ``sigma = density / sqrt(dt)``; bias
    random-walk increment ``sigma = rw_density * sqrt(dt)``.

    Attributes:
        gyro_noise_density: gyro white noise, rad/s/sqrt(Hz) (= rad/sqrt(s)).
        accel_noise_density: accel white noise, m/s^2/sqrt(Hz) (= m/s/sqrt(s)).
        gyro_bias_rw_density: gyro bias random walk, rad/s^2/sqrt(Hz) (= rad/s/sqrt(s)).
        accel_bias_rw_density: accel bias random walk, m/s^3/sqrt(Hz) (= m/s^2/sqrt(s)).
        gyro_bias_sigma0: 1-sigma turn-on gyro bias per axis, rad/s.
        accel_bias_sigma0: 1-sigma turn-on accel bias per axis, m/s^2.
        name: the sensor these numbers describe.
    """

    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_rw_density: float
    accel_bias_rw_density: float
    gyro_bias_sigma0: float
    accel_bias_sigma0: float
    name: str = "custom"

    @classmethod
    def adis16470(
        cls,
        bias_correlation_time_s: float = 100.0,
        gyro_turn_on_deg_s: float = 0.2,
        accel_turn_on_mg: float = 5.0,
    ) -> ImuNoiseSpec:
        """Analog Devices ADIS16470 (datasheet Rev. C, typical values).

        Conversions:

        * gyro noise density = ARW / 60 * pi / 180: 0.34 deg/sqrt(h)
          -> 9.89e-5 rad/s/sqrt(Hz);
        * accel noise density = VRW / 60: 0.037 m/s/sqrt(h) -> 6.17e-4 m/s^2/sqrt(Hz);
        * bias random walk: in-run bias stability ``sigma_b`` taken as the 1-sigma drift of a
          random walk over the correlation time ``tau``: ``rw = sigma_b / sqrt(tau)``. With
          tau = 100 s: gyro 8 deg/h = 3.88e-5 rad/s -> 3.88e-6 rad/s^2/sqrt(Hz); accel
          13 micro-g = 1.27e-4 m/s^2 -> 1.27e-5 m/s^3/sqrt(Hz);
        * turn-on bias spread (not a datasheet in-run figure; a moderate choice for a
          calibrated unit after power cycling): gyro 0.2 deg/s = 3.49e-3 rad/s, accel
          5 mg = 4.90e-2 m/s^2 per axis.

        Args:
            bias_correlation_time_s: tau, s.
            gyro_turn_on_deg_s: 1-sigma turn-on gyro bias, deg/s.
            accel_turn_on_mg: 1-sigma turn-on accel bias, milli-g.
        """
        gyro_instability = _ADIS16470_GYRO_INSTABILITY_DEG_H * _DEG / 3600.0  # rad/s
        accel_instability = _ADIS16470_ACCEL_INSTABILITY_UG * 1e-6 * STANDARD_GRAVITY  # m/s^2
        root_tau = math.sqrt(bias_correlation_time_s)
        return cls(
            gyro_noise_density=_ADIS16470_ARW_DEG_SQRT_H * _DEG / 60.0,
            accel_noise_density=_ADIS16470_VRW_M_S_SQRT_H / 60.0,
            gyro_bias_rw_density=gyro_instability / root_tau,
            accel_bias_rw_density=accel_instability / root_tau,
            gyro_bias_sigma0=gyro_turn_on_deg_s * _DEG,
            accel_bias_sigma0=accel_turn_on_mg * 1e-3 * STANDARD_GRAVITY,
            name="ADIS16470",
        )

    @classmethod
    def zero(cls) -> ImuNoiseSpec:
        """A perfect IMU: no noise, no bias."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, name="ideal")

    def white_sigmas(self, dt: float) -> tuple[float, float]:
        """Per-sample white-noise sigmas ``(gyro rad/s, accel m/s^2)`` at interval ``dt`` s."""
        root = math.sqrt(dt)
        return self.gyro_noise_density / root, self.accel_noise_density / root

    def bias_step_sigmas(self, dt: float) -> tuple[float, float]:
        """Per-sample bias increment sigmas ``(gyro rad/s, accel m/s^2)`` at interval ``dt`` s."""
        root = math.sqrt(dt)
        return self.gyro_bias_rw_density * root, self.accel_bias_rw_density * root

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of the fields."""
        return dataclasses.asdict(self)


@dataclass
class SimConfig:
    """Everything that shapes a simulated run; the seed is passed separately.

    Ranges are ``(low, high)`` tuples drawn uniformly per run.

    Attributes:
        duration_s: run length, s. IMU samples at ``0, dt, ..., duration_s``.
        imu_rate_hz: IMU (and ground-truth) rate, Hz.
        wheel_rate_hz: wheel encoder rate, Hz.
        gnss_rate_hz: GNSS fix rate, Hz.
        wheel_track_m: distance D between the wheel contact points, m.
        wheel_radius_m: nominal wheel radius, m.
        encoder_ticks_per_rev: encoder resolution; ``None`` gives an ideal tachometer that
            reports the instantaneous rim speed at the sample time.
        wheel_scale_sigma: 1-sigma of the per-wheel scale error ``e`` (true vs nominal radius)
            so that a reading is ``true * (1 + e)``; drawn once per run for each wheel.
        wheel_speed_noise_mps: white noise on each wheel speed reading, m/s.
        mean_speed_mps: mean horizontal speed, m/s.
        speed_variation: peak relative speed swing; speed stays in
            ``mean * [1 - variation, 1 + variation]``.
        speed_components: number of sinusoids in the speed profile.
        speed_period_s: period range of the speed sinusoids, s.
        turn_rate_peak_rad_s: peak heading rate of the sinusoidal turns, rad/s.
        turn_components: number of sinusoids in the heading.
        turn_period_s: period range of the heading sinusoids, s.
        mean_turn_rate_rad_s: constant heading drift magnitude (random sign), rad/s.
        terrain_components: number of 2D sinusoids in the terrain height.
        terrain_slope_deg: peak slope of each terrain sinusoid, deg.
        terrain_wavelength_m: wavelength range of the terrain sinusoids, m.
        imu_noise: IMU noise densities (default ADIS16470).
        gnss_sigma_horizontal_m: GNSS 1-sigma noise east and north, m.
        gnss_sigma_vertical_m: GNSS 1-sigma noise up, m.
        gnss_lever_arm_m: antenna position in the body frame, m.
        gnss_outages_s: explicit outage intervals ``((t0, t1), ...)`` in s; overrides the
            random ones when not None.
        gnss_outage_count: number of random outages.
        gnss_outage_duration_s: duration range of random outages, s.
        gnss_outage_over_slip: place each random outage over a distinct slip episode,
            containing it when long enough (needs ``gnss_outage_count <= slip_episodes``).
        gnss_outage_margin_s: no random outage starts before this time, s (lets a filter
            initialise).
        gnss_velocity: also emit GNSS velocities at the fix times (``Sequence.gnss_velocity``).
        gnss_velocity_sigma_mps: their 1-sigma noise east, north, up, m/s.
        gnss_heading: also emit dual-antenna headings at the fix times
            (``Sequence.gnss_heading``).
        gnss_heading_sigma_rad: their 1-sigma noise, rad.
        gnss_heading_baseline_m: primary -> secondary antenna in the body frame, m.
        gnss_heading_time_offset_s: a heading stamped ``t`` is the one at ``t + offset`` (s;
            negative: the receiver's latency, stamps late), the filter's ``t_d`` convention.
        magnetometer: also emit magnetometer readings (``Sequence.magnetometer``;
            :mod:`msf_torch.sim.magnetometer`).
        magnetometer_rate_hz: their rate, Hz.
        magnetometer_sigma_uT: per-axis white noise, uT.
        magnetometer_field_uT, magnetometer_inclination_rad, magnetometer_declination_rad:
            the local earth field: magnitude (uT), dip below the horizon (rad, positive
            down) and magnetic north's azimuth clockwise from true north (rad).
        magnetometer_hard_iron_uT: hard-iron offset ``b``, uT.
        magnetometer_distortion: soft-iron distortion ``S`` (9 numbers, row by row); the
            correction a filter needs is its inverse.
        magnetometer_anomaly_count: number of local anomalies along the route.
        magnetometer_anomaly_uT: range of their peak field, uT.
        magnetometer_anomaly_radius_m: range of their radius, m.
        slip_episodes: number of slip episodes.
        slip_types: the types to use (subset of ``SLIP_TYPES``); all appear before any repeats.
        slip_duration_s: episode duration range (label interval, ramps included), s.
        slip_ratio: range of the slip ratio ``s`` for ``spin`` and ``skid``.
        lock_ratio: range of ``s`` for ``lock`` (reading ``true * (1 - s)``; 1 = fully locked).
        slip_ramp_s: raised-cosine onset and offset time inside each episode, s.
        slip_min_gap_s: least time between episodes, s.
        slip_margin_s: ``(start, end)`` margins of the run kept free of slip, s.
    """

    duration_s: float = 120.0
    imu_rate_hz: float = 200.0
    wheel_rate_hz: float = 25.0
    gnss_rate_hz: float = 1.0
    # wheels
    wheel_track_m: float = 0.55
    wheel_radius_m: float = 0.15
    encoder_ticks_per_rev: int | None = 1024
    wheel_scale_sigma: float = 0.005
    wheel_speed_noise_mps: float = 0.01
    # motion
    mean_speed_mps: float = 1.5
    speed_variation: float = 0.4
    speed_components: int = 3
    speed_period_s: tuple[float, float] = (10.0, 60.0)
    turn_rate_peak_rad_s: float = 0.3
    turn_components: int = 3
    turn_period_s: tuple[float, float] = (15.0, 60.0)
    mean_turn_rate_rad_s: float = 0.02
    terrain_components: int = 3
    terrain_slope_deg: float = 2.5
    terrain_wavelength_m: tuple[float, float] = (30.0, 100.0)
    # IMU
    imu_noise: ImuNoiseSpec = field(default_factory=ImuNoiseSpec.adis16470)
    # GNSS
    gnss_sigma_horizontal_m: float = 0.5
    gnss_sigma_vertical_m: float = 1.0
    gnss_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gnss_outages_s: tuple[tuple[float, float], ...] | None = None
    gnss_outage_count: int = 0
    gnss_outage_duration_s: tuple[float, float] = (20.0, 40.0)
    gnss_outage_over_slip: bool = False
    gnss_outage_margin_s: float = 10.0
    gnss_velocity: bool = False
    gnss_velocity_sigma_mps: tuple[float, float, float] = (0.05, 0.05, 0.1)
    gnss_heading: bool = False
    gnss_heading_sigma_rad: float = 0.005
    gnss_heading_baseline_m: tuple[float, float, float] = (1.0, 0.0, 0.0)
    gnss_heading_time_offset_s: float = 0.0
    # magnetometer
    magnetometer: bool = False
    magnetometer_rate_hz: float = 50.0
    magnetometer_sigma_uT: float = 0.3
    magnetometer_field_uT: float = 48.0
    magnetometer_inclination_rad: float = 1.05
    magnetometer_declination_rad: float = 0.0
    magnetometer_hard_iron_uT: tuple[float, float, float] = (0.0, 0.0, 0.0)
    magnetometer_distortion: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    magnetometer_anomaly_count: int = 0
    magnetometer_anomaly_uT: tuple[float, float] = (10.0, 40.0)
    magnetometer_anomaly_radius_m: tuple[float, float] = (2.0, 5.0)
    # slip
    slip_episodes: int = 0
    slip_types: tuple[str, ...] = SLIP_TYPES
    slip_duration_s: tuple[float, float] = (2.0, 6.0)
    slip_ratio: tuple[float, float] = (0.3, 0.8)
    lock_ratio: tuple[float, float] = (0.6, 1.0)
    slip_ramp_s: float = 0.2
    slip_min_gap_s: float = 5.0
    slip_margin_s: tuple[float, float] = (10.0, 5.0)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        positive = (
            "duration_s",
            "imu_rate_hz",
            "wheel_rate_hz",
            "gnss_rate_hz",
            "wheel_track_m",
            "wheel_radius_m",
            "mean_speed_mps",
            "magnetometer_rate_hz",
            "magnetometer_sigma_uT",
            "magnetometer_field_uT",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"SimConfig.{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = (
            "wheel_scale_sigma",
            "wheel_speed_noise_mps",
            "turn_rate_peak_rad_s",
            "mean_turn_rate_rad_s",
            "terrain_slope_deg",
            "gnss_sigma_horizontal_m",
            "gnss_sigma_vertical_m",
            "gnss_outage_count",
            "slip_episodes",
            "slip_ramp_s",
            "slip_min_gap_s",
            "gnss_outage_margin_s",
            "speed_components",
            "turn_components",
            "terrain_components",
            "magnetometer_anomaly_count",
        )
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"SimConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in (
            "speed_period_s",
            "turn_period_s",
            "terrain_wavelength_m",
            "gnss_outage_duration_s",
            "slip_duration_s",
            "slip_ratio",
            "lock_ratio",
            "magnetometer_anomaly_uT",
            "magnetometer_anomaly_radius_m",
        ):
            low, high = getattr(self, name)
            if not 0 <= low <= high:
                raise ValueError(
                    f"SimConfig.{name} must be (low, high) with 0 <= low <= high, "
                    f"got {getattr(self, name)!r}"
                )
        for name in ("speed_period_s", "turn_period_s", "terrain_wavelength_m"):
            if getattr(self, name)[0] <= 0:
                raise ValueError(f"SimConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 <= self.speed_variation < 1:
            raise ValueError(
                f"SimConfig.speed_variation must be in [0, 1), got {self.speed_variation!r}"
            )
        if self.mean_speed_mps * (1 - self.speed_variation) < 0.3:
            raise ValueError(
                "SimConfig: mean_speed_mps * (1 - speed_variation) must be >= 0.3 "
                "m/s (the robot never stops)"
            )
        if len(self.slip_margin_s) != 2 or min(self.slip_margin_s) < 0:
            raise ValueError(
                f"SimConfig.slip_margin_s must be (start, end) >= 0, got {self.slip_margin_s!r}"
            )
        if self.lock_ratio[1] > 1:
            raise ValueError(f"SimConfig.lock_ratio must lie in [0, 1], got {self.lock_ratio!r}")
        if self.encoder_ticks_per_rev is not None and self.encoder_ticks_per_rev <= 0:
            raise ValueError(
                f"SimConfig.encoder_ticks_per_rev must be > 0 or None, "
                f"got {self.encoder_ticks_per_rev!r}"
            )
        sigma = self.gnss_velocity_sigma_mps
        if len(sigma) != 3 or not all(x > 0 for x in sigma):
            raise ValueError(
                f"SimConfig.gnss_velocity_sigma_mps must be 3 values > 0, got {sigma!r}"
            )
        if not self.gnss_heading_sigma_rad > 0:
            raise ValueError(
                f"SimConfig.gnss_heading_sigma_rad must be > 0, got {self.gnss_heading_sigma_rad!r}"
            )
        if (
            len(self.gnss_heading_baseline_m) != 3
            or math.hypot(*self.gnss_heading_baseline_m[:2]) == 0
        ):
            raise ValueError(
                "SimConfig.gnss_heading_baseline_m must be 3 entries with a horizontal part, "
                f"got {self.gnss_heading_baseline_m!r}"
            )
        if self.magnetometer_anomaly_radius_m[0] <= 0:
            raise ValueError("SimConfig.magnetometer_anomaly_radius_m must be > 0")
        if len(self.magnetometer_hard_iron_uT) != 3:
            raise ValueError("SimConfig.magnetometer_hard_iron_uT must have 3 entries")
        if (
            len(self.magnetometer_distortion) != 9
            or abs(np.linalg.det(np.reshape(self.magnetometer_distortion, (3, 3)))) < 1e-9
        ):
            raise ValueError(
                "SimConfig.magnetometer_distortion must be 9 numbers (3 x 3, row by row) with "
                f"a non-zero determinant, got {self.magnetometer_distortion!r}"
            )
        if len(self.gnss_lever_arm_m) != 3:
            raise ValueError(
                f"SimConfig.gnss_lever_arm_m must have 3 entries, got {self.gnss_lever_arm_m!r}"
            )
        unknown = [kind for kind in self.slip_types if kind not in SLIP_TYPES]
        if unknown or (self.slip_episodes > 0 and not self.slip_types):
            raise ValueError(
                f"SimConfig.slip_types must be a non-empty subset of {SLIP_TYPES}, "
                f"got {self.slip_types!r}"
            )
        if self.slip_episodes > 0 and 2 * self.slip_ramp_s > self.slip_duration_s[0]:
            raise ValueError("SimConfig: 2 * slip_ramp_s must not exceed slip_duration_s[0]")
        if self.gnss_outages_s is not None:
            for k, interval in enumerate(self.gnss_outages_s):
                if len(interval) != 2 or not interval[0] < interval[1]:
                    raise ValueError(
                        f"SimConfig.gnss_outages_s[{k}] must be (t0, t1) with "
                        f"t0 < t1, got {interval!r}"
                    )
        elif self.gnss_outage_over_slip and self.gnss_outage_count > self.slip_episodes:
            raise ValueError(
                f"SimConfig: gnss_outage_over_slip needs gnss_outage_count "
                f"({self.gnss_outage_count}) <= slip_episodes "
                f"({self.slip_episodes})"
            )

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict (tuples become lists, ``imu_noise`` a nested dict)."""
        return _listify(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SimConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"SimConfig.from_dict: unknown keys {unknown}")
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key == "imu_noise" and isinstance(value, dict):
                value = ImuNoiseSpec(**value)
            elif key == "gnss_outages_s" and value is not None:
                value = tuple(tuple(float(x) for x in pair) for pair in value)
            elif isinstance(value, list):
                value = tuple(value)
            kwargs[key] = value
        return cls(**kwargs)


def _listify(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _listify(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_listify(v) for v in value]
    return value


def default_slip_config(
    duration_s: float = 120.0, slip_episodes: int = 3, **overrides: Any
) -> SimConfig:
    """A run with ``slip_episodes`` labelled slip episodes (all types) and GNSS throughout.

    ``overrides`` are further ``SimConfig`` fields.
    """
    return SimConfig(duration_s=duration_s, slip_episodes=slip_episodes, **overrides)


def gnss_denied_slip_config(
    duration_s: float = 180.0,
    gnss_available_s: float = 25.0,
    slip_episodes: int = 6,
    reacquire_period_s: float | None = None,
    reacquire_window_s: float = 5.0,
    **overrides: Any,
) -> SimConfig:
    """Slip benchmark where wheel odometry matters: GNSS only at the start, then out.

    GNSS fixes exist for the first ``gnss_available_s`` seconds (to initialise heading and
    biases); after that GNSS is out until the end, or, when ``reacquire_period_s`` is given,
    out except for ``reacquire_window_s`` of fixes at the end of every period. All slip
    episodes fall after ``gnss_available_s + 5`` s, i.e. inside the outage.
    """
    outages: list[tuple[float, float]] = []
    start = gnss_available_s
    if reacquire_period_s is None:
        outages.append((start, duration_s + 1.0))
    else:
        if reacquire_period_s <= reacquire_window_s:
            raise ValueError("reacquire_period_s must exceed reacquire_window_s")
        while start < duration_s:
            end = start + reacquire_period_s - reacquire_window_s
            outages.append((start, min(end, duration_s + 1.0)))
            start += reacquire_period_s
    settings: dict[str, Any] = {
        "duration_s": duration_s,
        "slip_episodes": slip_episodes,
        "gnss_outages_s": tuple(outages),
        "slip_margin_s": (gnss_available_s + 5.0, 5.0),
    }
    settings.update(overrides)
    return SimConfig(**settings)


def sample_slip_config(**overrides: Any) -> SimConfig:
    """The bundled sample (``datasets/sample_slip``, seed 7): 120 s, 3 slip episodes (one of
    each type), one 30 s GNSS outage that contains a slip episode."""
    settings: dict[str, Any] = {
        "duration_s": 120.0,
        "slip_episodes": 3,
        "gnss_outage_count": 1,
        "gnss_outage_duration_s": (30.0, 30.0),
        "gnss_outage_over_slip": True,
    }
    settings.update(overrides)
    return SimConfig(**settings)


# --------------------------------------------------------------------------------------------
# Analytic ground trajectory
# --------------------------------------------------------------------------------------------


@dataclass
class PathState:
    """The continuous truth at query times (numpy float64), N = number of times.

    Attributes:
        t: (N,) s.
        position: (N, 3) world, m.
        velocity: (N, 3) world, m/s.
        acceleration: (N, 3) world, m/s^2.
        rotation: (N, 3, 3) body -> world.
        angular_velocity: (N, 3) body, rad/s.
        specific_force: (N, 3) body, ``R^T (a - g_world)``, m/s^2.
        speed: (N,) body forward speed ``|velocity|``, m/s.
    """

    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    rotation: np.ndarray
    angular_velocity: np.ndarray
    specific_force: np.ndarray
    speed: np.ndarray


class GroundPath:
    """A smooth 3D ground trajectory from analytic functions; see the module docstring.

    Evaluate anywhere in ``[-pad_s, duration_s + pad_s]`` with :meth:`evaluate`.

    Args:
        duration_s: run length, s.
        mean_speed: s_mean, m/s.
        speed_amp, speed_freq, speed_phase: (K,) relative amplitudes, rad/s, rad.
        heading0: psi_0, rad. turn_rate0: r_0, rad/s.
        turn_amp, turn_freq, turn_phase: (K,) heading amplitudes rad, rad/s, rad.
        terrain_amp: (M,) m. terrain_wavevector: (M, 2) rad/m. terrain_phase: (M,) rad.
        knot_dt: quadrature knot spacing, s. pad_s: evaluation margin, s.
    """

    def __init__(
        self,
        *,
        duration_s: float,
        mean_speed: float,
        speed_amp: np.ndarray,
        speed_freq: np.ndarray,
        speed_phase: np.ndarray,
        heading0: float,
        turn_rate0: float,
        turn_amp: np.ndarray,
        turn_freq: np.ndarray,
        turn_phase: np.ndarray,
        terrain_amp: np.ndarray,
        terrain_wavevector: np.ndarray,
        terrain_phase: np.ndarray,
        knot_dt: float = 0.1,
        pad_s: float = 2.0,
    ) -> None:
        self.duration_s = float(duration_s)
        self.mean_speed = float(mean_speed)
        self.speed_amp = np.asarray(speed_amp, np.float64)
        self.speed_freq = np.asarray(speed_freq, np.float64)
        self.speed_phase = np.asarray(speed_phase, np.float64)
        self.heading0 = float(heading0)
        self.turn_rate0 = float(turn_rate0)
        self.turn_amp = np.asarray(turn_amp, np.float64)
        self.turn_freq = np.asarray(turn_freq, np.float64)
        self.turn_phase = np.asarray(turn_phase, np.float64)
        self.terrain_amp = np.asarray(terrain_amp, np.float64)
        self.terrain_wavevector = np.asarray(terrain_wavevector, np.float64).reshape(-1, 2)
        self.terrain_phase = np.asarray(terrain_phase, np.float64)
        self.pad_s = float(pad_s)
        self.knot_dt = float(knot_dt)
        n_seg = int(math.ceil((self.duration_s + 2 * self.pad_s) / self.knot_dt))
        self._knots = np.arange(n_seg + 1) * self.knot_dt - self.pad_s
        seg = self._gauss_legendre(self._knots[:-1], self._knots[1:])
        self._cum = np.concatenate((np.zeros((1, 2)), np.cumsum(seg, 0)), 0)
        self._height0 = 0.0
        self._xy0 = np.zeros(2)
        self._xy0 = self.horizontal_position(np.zeros(1))[0]
        self._height0 = float(self.terrain(np.zeros((1, 2)))[0][0])

    @classmethod
    def random(cls, config: SimConfig, rng: np.random.Generator) -> GroundPath:
        """Draw a path from ``config``'s motion and terrain settings."""

        def weights(count: int) -> np.ndarray:
            raw = rng.uniform(0.5, 1.0, count)
            return raw / raw.sum() if count else raw

        ks = config.speed_components
        speed_freq = 2 * math.pi / rng.uniform(*config.speed_period_s, ks)
        speed_amp = config.speed_variation * weights(ks)
        speed_phase = rng.uniform(-math.pi, math.pi, ks)
        kt = config.turn_components
        turn_freq = 2 * math.pi / rng.uniform(*config.turn_period_s, kt)
        turn_amp = config.turn_rate_peak_rad_s * weights(kt) / turn_freq
        turn_phase = rng.uniform(-math.pi, math.pi, kt)
        heading0 = rng.uniform(-math.pi, math.pi)
        turn_rate0 = config.mean_turn_rate_rad_s * rng.choice((-1.0, 1.0))
        km = config.terrain_components
        wavelength = rng.uniform(*config.terrain_wavelength_m, km)
        direction = rng.uniform(-math.pi, math.pi, km)
        knorm = 2 * math.pi / wavelength
        wavevector = knorm[:, None] * np.stack((np.cos(direction), np.sin(direction)), -1)
        terrain_amp = math.tan(config.terrain_slope_deg * _DEG) / knorm
        terrain_phase = rng.uniform(-math.pi, math.pi, km)
        return cls(
            duration_s=config.duration_s,
            mean_speed=config.mean_speed_mps,
            speed_amp=speed_amp,
            speed_freq=speed_freq,
            speed_phase=speed_phase,
            heading0=heading0,
            turn_rate0=turn_rate0,
            turn_amp=turn_amp,
            turn_freq=turn_freq,
            turn_phase=turn_phase,
            terrain_amp=terrain_amp,
            terrain_wavevector=wavevector,
            terrain_phase=terrain_phase,
        )

    # analytic pieces ------------------------------------------------------------------------

    def horizontal_speed(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``s(t)`` m/s and ``s'(t)`` m/s^2, each (N,)."""
        arg = t[:, None] * self.speed_freq + self.speed_phase
        s = self.mean_speed * (1.0 + np.sin(arg) @ self.speed_amp)
        ds = self.mean_speed * (np.cos(arg) @ (self.speed_amp * self.speed_freq))
        return s, ds

    def heading(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``psi(t)`` rad and ``psi'(t)`` rad/s, each (N,)."""
        arg = t[:, None] * self.turn_freq + self.turn_phase
        psi = self.heading0 + self.turn_rate0 * t + np.sin(arg) @ self.turn_amp
        dpsi = self.turn_rate0 + np.cos(arg) @ (self.turn_amp * self.turn_freq)
        return psi, dpsi

    def terrain(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height (N,) m, gradient (N, 2), Hessian (N, 2, 2) 1/m at horizontal points (N, 2)."""
        k = self.terrain_wavevector
        arg = xy @ k.T + self.terrain_phase  # (N, M)
        sin, cos = np.sin(arg), np.cos(arg)
        height = sin @ self.terrain_amp - self._height0
        grad = (cos * self.terrain_amp) @ k
        outer = k[:, :, None] * k[:, None, :]  # (M, 2, 2)
        hess = -np.einsum("nm,mij->nij", sin * self.terrain_amp, outer)
        return height, grad, hess

    def _horizontal_velocity(self, t: np.ndarray) -> np.ndarray:
        s, _ = self.horizontal_speed(t)
        psi, _ = self.heading(t)
        return s[:, None] * np.stack((np.cos(psi), np.sin(psi)), -1)

    def _gauss_legendre(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``integral_a^b u(t) dt`` (N, 2) by 8-point Gauss-Legendre per interval."""
        mid, half = 0.5 * (a + b), 0.5 * (b - a)
        nodes = mid[:, None] + half[:, None] * _GL8_NODES  # (N, 8)
        u = self._horizontal_velocity(nodes.reshape(-1)).reshape(*nodes.shape, 2)
        return half[:, None] * np.einsum("nkd,k->nd", u, _GL8_WEIGHTS)

    def _check_times(self, t: np.ndarray) -> None:
        low, high = -self.pad_s, self.duration_s + self.pad_s
        if t.size and (t.min() < low or t.max() > high):
            raise ValueError(
                f"GroundPath: times must lie in [{low}, {high}] s, got [{t.min()}, {t.max()}]"
            )

    def horizontal_position(self, t: np.ndarray) -> np.ndarray:
        """``(x, y)(t)`` (N, 2) m, with ``(x, y)(0) = 0``."""
        t = np.asarray(t, np.float64).reshape(-1)
        self._check_times(t)
        idx = np.floor((t - self._knots[0]) / self.knot_dt).astype(np.int64)
        idx = np.clip(idx, 0, len(self._knots) - 2)
        return self._cum[idx] + self._gauss_legendre(self._knots[idx], t) - self._xy0

    def evaluate(self, t: np.ndarray) -> PathState:
        """The continuous truth at times ``t`` (N,) s; see :class:`PathState`."""
        t = np.asarray(t, np.float64).reshape(-1)
        s, ds = self.horizontal_speed(t)
        psi, dpsi = self.heading(t)
        cos, sin = np.cos(psi), np.sin(psi)
        u = s[:, None] * np.stack((cos, sin), -1)
        du = ds[:, None] * np.stack((cos, sin), -1) + (s * dpsi)[:, None] * np.stack(
            (-sin, cos), -1
        )
        xy = self.horizontal_position(t)
        height, grad, hess = self.terrain(xy)
        hess_u = np.einsum("nij,nj->ni", hess, u)
        zdot = (grad * u).sum(-1)
        zddot = (hess_u * u).sum(-1) + (grad * du).sum(-1)
        position = np.concatenate((xy, height[:, None]), -1)
        velocity = np.concatenate((u, zdot[:, None]), -1)
        accel = np.concatenate((du, zddot[:, None]), -1)
        speed = np.linalg.norm(velocity, axis=-1)
        e1 = velocity / speed[:, None]
        normal = np.concatenate((-grad, np.ones_like(height)[:, None]), -1)
        normal_norm = np.linalg.norm(normal, axis=-1)
        e3 = normal - (normal * e1).sum(-1, keepdims=True) * e1
        e3 = e3 / np.linalg.norm(e3, axis=-1, keepdims=True)
        e2 = np.cross(e3, e1)
        rotation = np.stack((e1, e2, e3), -1)  # columns: body axes in world
        # R^T dR/dt = hat(omega): omega_z = e2.e1', omega_y = -e3.e1', omega_x = -e2.e3'
        dnormal = np.concatenate((-hess_u, np.zeros_like(height)[:, None]), -1)
        omega = np.stack(
            (
                -(e2 * dnormal).sum(-1) / normal_norm,
                -(e3 * accel).sum(-1) / speed,
                (e2 * accel).sum(-1) / speed,
            ),
            -1,
        )
        gravity = np.array([0.0, 0.0, -STANDARD_GRAVITY])
        specific_force = np.einsum("nji,nj->ni", rotation, accel - gravity)
        return PathState(
            t=t,
            position=position,
            velocity=velocity,
            acceleration=accel,
            rotation=rotation,
            angular_velocity=omega,
            specific_force=specific_force,
            speed=speed,
        )


# --------------------------------------------------------------------------------------------
# Slip, wheels, IMU, GNSS
# --------------------------------------------------------------------------------------------


@dataclass
class SlipEpisode:
    """One labelled slip episode.

    Attributes:
        t_start, t_end: label interval, s (the reading departs strictly inside it).
        kind: one of ``SLIP_TYPES``.
        ratio: slip ratio ``s``.
        wheel: the wheel that departs: ``"both"``, ``"left"`` or ``"right"``.
        left_factor, right_factor: reading multipliers at full slip (1 = unaffected).
        ramp_s: raised-cosine onset / offset time, s.
    """

    t_start: float
    t_end: float
    kind: str
    ratio: float
    wheel: str
    left_factor: float
    right_factor: float
    ramp_s: float

    def weight(self, t: np.ndarray) -> np.ndarray:
        """Slip weight in [0, 1] at times ``t`` (N,): 0 outside, raised-cosine ramps."""
        rise = np.clip((t - self.t_start) / self.ramp_s, 0.0, 1.0)
        fall = np.clip((self.t_end - t) / self.ramp_s, 0.0, 1.0)
        ramp = np.minimum(rise, fall)
        return 0.5 * (1.0 - np.cos(math.pi * ramp))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for ``Sequence.meta``."""
        return dataclasses.asdict(self)


def _place_intervals(
    durations: np.ndarray, low: float, high: float, gap: float, rng: np.random.Generator, what: str
) -> np.ndarray:
    """Non-overlapping intervals (K, 2) in [low, high], at least ``gap`` apart, random slack."""
    count = len(durations)
    slack = (high - low) - durations.sum() - max(count - 1, 0) * gap
    if slack < 0:
        raise ValueError(
            f"SimConfig: {count} {what} of total {durations.sum():.1f} s with "
            f"{gap} s gaps do not fit in [{low:.1f}, {high:.1f}] s (use fewer {what} or a "
            "longer duration_s)"
        )
    spare = rng.dirichlet(np.ones(count + 1)) * slack
    out = np.empty((count, 2))
    t = low
    for k in range(count):
        t += spare[k]
        out[k] = (t, t + durations[k])
        t += durations[k] + gap
    return out


def _draw_slip_episodes(config: SimConfig, rng: np.random.Generator) -> list[SlipEpisode]:
    count = config.slip_episodes
    if count == 0:
        return []
    durations = rng.uniform(*config.slip_duration_s, count)
    low = config.slip_margin_s[0]
    high = config.duration_s - config.slip_margin_s[1]
    intervals = _place_intervals(durations, low, high, config.slip_min_gap_s, rng, "slip episodes")
    kinds: list[str] = []
    while len(kinds) < count:
        kinds.extend(config.slip_types[i] for i in rng.permutation(len(config.slip_types)))
    episodes = []
    for k in range(count):
        slip = rng.uniform(*config.slip_ratio)
        lock = rng.uniform(*config.lock_ratio)
        right_wheel = bool(rng.integers(2))
        sign = float(rng.choice((-1.0, 1.0)))
        kind = kinds[k]
        wheel = "both"
        if kind == "spin":
            ratio, left, right = slip, 1.0 + slip, 1.0 + slip
        elif kind == "skid":
            ratio = slip
            wheel = "right" if right_wheel else "left"
            left, right = (1.0, 1.0 + sign * slip) if right_wheel else (1.0 + sign * slip, 1.0)
        else:  # lock
            ratio, left, right = lock, 1.0 - lock, 1.0 - lock
        episodes.append(
            SlipEpisode(
                t_start=float(intervals[k, 0]),
                t_end=float(intervals[k, 1]),
                kind=kind,
                ratio=float(ratio),
                wheel=wheel,
                left_factor=float(left),
                right_factor=float(right),
                ramp_s=config.slip_ramp_s,
            )
        )
    return episodes


def _slip_factors(t: np.ndarray, episodes: list[SlipEpisode]) -> tuple[np.ndarray, np.ndarray]:
    """Left and right reading multipliers (N,) at times ``t``."""
    left, right = np.ones_like(t), np.ones_like(t)
    for ep in episodes:
        w = ep.weight(t)
        left = left + (ep.left_factor - 1.0) * w
        right = right + (ep.right_factor - 1.0) * w
    return left, right


def _gnss_outages(
    config: SimConfig, episodes: list[SlipEpisode], rng: np.random.Generator
) -> np.ndarray:
    """Sorted, merged outage intervals (K, 2) s."""
    if config.gnss_outages_s is not None:
        raw = np.asarray(config.gnss_outages_s, np.float64).reshape(-1, 2)
    elif config.gnss_outage_count == 0:
        raw = np.zeros((0, 2))
    else:
        count = config.gnss_outage_count
        durations = rng.uniform(*config.gnss_outage_duration_s, count)
        if config.gnss_outage_over_slip:
            chosen = rng.choice(len(episodes), size=count, replace=False)
            offsets = rng.uniform(0.2, 0.8, count)
            raw = np.empty((count, 2))
            for k, (idx, dur) in enumerate(zip(chosen, durations, strict=True)):
                ep = episodes[int(idx)]
                spare = max(dur - (ep.t_end - ep.t_start), 0.0)
                start = ep.t_start - offsets[k] * spare
                # honour the start margin where the episode allows it
                start = max(start, min(config.gnss_outage_margin_s, ep.t_start))
                raw[k] = (start, start + dur)
        else:
            raw = _place_intervals(
                durations, config.gnss_outage_margin_s, config.duration_s, 5.0, rng, "GNSS outages"
            )
    raw = np.clip(raw, 0.0, config.duration_s)
    raw = raw[raw[:, 1] > raw[:, 0]]
    raw = raw[np.argsort(raw[:, 0], kind="stable")]
    merged: list[list[float]] = []
    for start, end in raw:
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([float(start), float(end)])
    return np.asarray(merged, np.float64).reshape(-1, 2)


def _rim_speeds(state: PathState, track: float) -> tuple[np.ndarray, np.ndarray]:
    half = 0.5 * track * state.angular_velocity[:, 2]
    return state.speed - half, state.speed + half


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass
class SimTruth:
    """Per-IMU-sample truth, float64 tensors with B = 1 (N = IMU samples).

    Attributes:
        t: (1, N) s.
        position: (1, N, 3) world, m.
        velocity: (1, N, 3) world, m/s.
        rotation: (1, N, 3, 3) body -> world.
        angular_velocity: (1, N, 3) body, rad/s (the noise-free, bias-free gyro).
        specific_force: (1, N, 3) body, m/s^2 (the noise-free, bias-free accelerometer).
        speed: (1, N) body forward speed, m/s.
        gyro_bias: (1, N, 3) rad/s, the bias in each gyro sample.
        accel_bias: (1, N, 3) m/s^2.
        slip_mask_imu: (1, N) bool, True inside a labelled slip interval.
        wheel_scale_error: (1, 2) ``[e_left, e_right]``; reading = true * (1 + e).
    """

    t: torch.Tensor
    position: torch.Tensor
    velocity: torch.Tensor
    rotation: torch.Tensor
    angular_velocity: torch.Tensor
    specific_force: torch.Tensor
    speed: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor
    slip_mask_imu: torch.Tensor
    wheel_scale_error: torch.Tensor


@dataclass
class SimulatedRun:
    """A simulated run and its truth.

    Attributes:
        sequence: the measurements as a :class:`~msf_torch.types.Sequence` (B = 1) with
            ground truth, labels ``"slip"`` and ``"gnss_outage"``, and ``meta``.
        truth: per-IMU-sample truth.
        wheel_truth: true rim speeds (instantaneous, no scale error, slip or noise) at the
            wheel sample times, m/s.
        slip_episodes: the episodes, in time order (rows of ``labels["slip"]``).
        path: the analytic trajectory, to evaluate the truth at any time.
        config: the configuration used.
        seed: the seed used.
    """

    sequence: Sequence
    truth: SimTruth
    wheel_truth: WheelSamples
    slip_episodes: list[SlipEpisode]
    path: GroundPath
    config: SimConfig
    seed: int


def _tensor(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.array(x, dtype=np.float64, order="C"))[None]


def simulate_run(config: SimConfig, seed: int, *, path_seed: int | None = None) -> SimulatedRun:
    """Simulate one labelled wheeled-robot run.

    Independent random streams (``numpy.random.SeedSequence(seed).spawn``) drive the path,
    the IMU, the wheels, the slip episodes and GNSS, so changing e.g. the IMU noise leaves the
    path and the slip episodes of a seed unchanged. Same config and seed give bit-identical
    output.

    Wheel readings (time stamps ``k / wheel_rate_hz``, k >= 1): the modelled rim speed is
    ``true * (1 + e) * slip_factor(t)``. With ``encoder_ticks_per_rev = None`` the reading is
    that speed at the stamp plus white noise. Otherwise it is the mean over the preceding
    interval ``dt`` (Gauss-Legendre) plus white noise, integrated to distance and counted as
    whole encoder ticks of length ``2 pi r / ticks`` (nominal radius); the reading is
    ``(ticks_k - ticks_{k-1}) * tick_length / dt``. Cumulative counting, as a real encoder
    does, so no fraction of a tick is lost between samples.

    Args:
        config: the run's settings (validated here).
        seed: non-negative int.
        path_seed: non-negative int or None. When given, the path (route and terrain: the
            "map") is drawn from this seed's path stream instead of ``seed``'s, so
            ``simulate_run(c, s, path_seed=m)`` drives the path of ``simulate_run(c, m)`` with
            the sensor noise, slip and GNSS of seed ``s`` (the path does not depend on
            ``duration_s``: a shorter run drives a prefix of it). Recorded as
            ``meta["sim"]["path_seed"]``.

    Returns:
        :class:`SimulatedRun` with float64 CPU tensors, B = 1.

    Raises:
        ValueError: a config value is out of range or the episodes do not fit.
    """
    config.validate()
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"simulate_run: seed must be a non-negative int, got {seed!r}")
    if path_seed is not None and (not isinstance(path_seed, (int, np.integer)) or path_seed < 0):
        raise ValueError(
            f"simulate_run: path_seed must be a non-negative int or None, got {path_seed!r}"
        )
    # a sixth stream for the GNSS velocity noise, a seventh for the heading noise and an
    # eighth for the magnetometer leave the first five (and every run without them) as
    # they were
    streams = np.random.SeedSequence(int(seed)).spawn(8)
    if path_seed is not None:
        streams[0] = np.random.SeedSequence(int(path_seed)).spawn(5)[0]
    rng_path, rng_imu, rng_wheel, rng_slip, rng_gnss, rng_gnss_velocity, rng_heading, rng_mag = (
        np.random.Generator(np.random.PCG64(s)) for s in streams
    )
    path = GroundPath.random(config, rng_path)

    # IMU ------------------------------------------------------------------------------------
    dt = 1.0 / config.imu_rate_hz
    n_imu = int(math.floor(config.duration_s * config.imu_rate_hz + 1e-9)) + 1
    t_imu = np.arange(n_imu) * dt
    state = path.evaluate(t_imu)
    noise = config.imu_noise
    sig_g, sig_a = noise.white_sigmas(dt)
    step_g, step_a = noise.bias_step_sigmas(dt)
    bias_g0 = rng_imu.normal(0.0, noise.gyro_bias_sigma0, 3)
    bias_a0 = rng_imu.normal(0.0, noise.accel_bias_sigma0, 3)
    walk_g = rng_imu.normal(0.0, step_g, (n_imu - 1, 3))
    walk_a = rng_imu.normal(0.0, step_a, (n_imu - 1, 3))
    white_g = rng_imu.normal(0.0, sig_g, (n_imu, 3))
    white_a = rng_imu.normal(0.0, sig_a, (n_imu, 3))
    bias_g = bias_g0 + np.concatenate((np.zeros((1, 3)), np.cumsum(walk_g, 0)), 0)
    bias_a = bias_a0 + np.concatenate((np.zeros((1, 3)), np.cumsum(walk_a, 0)), 0)
    gyro = state.angular_velocity + bias_g + white_g
    accel = state.specific_force + bias_a + white_a

    # slip and wheels ------------------------------------------------------------------------
    episodes = _draw_slip_episodes(config, rng_slip)
    dt_w = 1.0 / config.wheel_rate_hz
    n_w = int(math.floor(config.duration_s * config.wheel_rate_hz + 1e-9))
    t_w = np.arange(1, n_w + 1) * dt_w
    scale = 1.0 + rng_wheel.normal(0.0, config.wheel_scale_sigma, 2)
    wheel_noise = rng_wheel.normal(0.0, config.wheel_speed_noise_mps, (n_w, 2))

    def modelled(t: np.ndarray) -> np.ndarray:
        left, right = _rim_speeds(path.evaluate(t), config.wheel_track_m)
        slip_l, slip_r = _slip_factors(t, episodes)
        return np.stack((left * scale[0] * slip_l, right * scale[1] * slip_r), -1)

    true_left, true_right = _rim_speeds(path.evaluate(t_w), config.wheel_track_m)
    if config.encoder_ticks_per_rev is None:
        wheel_speed = modelled(t_w) + wheel_noise
    else:
        nodes = (t_w - 0.5 * dt_w)[:, None] + 0.5 * dt_w * _GL4_NODES  # (n_w, 4)
        mean = (
            np.einsum("nkd,k->nd", modelled(nodes.reshape(-1)).reshape(n_w, 4, 2), _GL4_WEIGHTS)
            * 0.5
        )
        distance = np.cumsum((mean + wheel_noise) * dt_w, 0)
        tick = 2.0 * math.pi * config.wheel_radius_m / config.encoder_ticks_per_rev
        ticks = np.floor(distance / tick)
        ticks = np.concatenate((np.zeros((1, 2)), ticks), 0)
        wheel_speed = np.diff(ticks, axis=0) * tick / dt_w

    # GNSS -----------------------------------------------------------------------------------
    outages = _gnss_outages(config, episodes, rng_gnss)
    n_g = int(math.floor(config.duration_s * config.gnss_rate_hz + 1e-9)) + 1
    t_g_all = np.arange(n_g) / config.gnss_rate_hz
    sigma = np.array(
        [
            config.gnss_sigma_horizontal_m,
            config.gnss_sigma_horizontal_m,
            config.gnss_sigma_vertical_m,
        ]
    )
    gnss_noise = rng_gnss.normal(0.0, 1.0, (n_g, 3)) * sigma
    keep = np.ones(n_g, dtype=bool)
    for start, end in outages:
        keep &= ~((t_g_all >= start) & (t_g_all <= end))
    t_g = t_g_all[keep]
    g_state = path.evaluate(t_g)
    lever = np.asarray(config.gnss_lever_arm_m, np.float64)
    antenna = g_state.position + np.einsum("nij,j->ni", g_state.rotation, lever)
    gnss_position = antenna + gnss_noise[keep]
    gnss_velocity = None
    if config.gnss_velocity:
        velocity_sigma = np.asarray(config.gnss_velocity_sigma_mps, np.float64)
        velocity_noise = rng_gnss_velocity.normal(0.0, 1.0, (n_g, 3)) * velocity_sigma
        arm_rate = np.cross(g_state.angular_velocity, lever)
        antenna_velocity = g_state.velocity + np.einsum("nij,nj->ni", g_state.rotation, arm_rate)
        gnss_velocity = GnssVelocity(
            t=_tensor(t_g),
            velocity=_tensor(antenna_velocity + velocity_noise[keep]),
            sigma=_tensor(np.broadcast_to(velocity_sigma, (len(t_g), 3))),
            mask=torch.ones((1, len(t_g)), dtype=torch.bool),
        )
    gnss_heading = None
    if config.gnss_heading:
        heading_noise = rng_heading.normal(0.0, config.gnss_heading_sigma_rad, n_g)
        taken = path.evaluate(np.clip(t_g + config.gnss_heading_time_offset_s, 0.0, None))
        baseline = np.einsum(
            "nij,j->ni", taken.rotation, np.asarray(config.gnss_heading_baseline_m, np.float64)
        )
        azimuth = np.arctan2(baseline[:, 0], baseline[:, 1]) + heading_noise[keep]
        gnss_heading = GnssHeading(
            t=_tensor(t_g),
            heading=_tensor(np.mod(azimuth, 2.0 * math.pi)),
            sigma=_tensor(np.full(len(t_g), config.gnss_heading_sigma_rad)),
            mask=torch.ones((1, len(t_g)), dtype=torch.bool),
        )

    magnetometer = None
    magnetometer_labels, magnetometer_meta = {}, {}
    if config.magnetometer:
        t_m, readings, anomaly_intervals, magnetometer_meta = simulate_magnetometer(
            config, path, rng_mag
        )
        magnetometer = Magnetometer(
            t=_tensor(t_m),
            field=_tensor(readings),
            sigma=_tensor(np.full(len(t_m), config.magnetometer_sigma_uT)),
            mask=torch.ones((1, len(t_m)), dtype=torch.bool),
        )
        magnetometer_labels = {"magnetic_anomaly": _tensor(anomaly_intervals)}
        magnetometer_meta = {"magnetometer": magnetometer_meta}

    # assemble -------------------------------------------------------------------------------
    slip_intervals = np.array([[ep.t_start, ep.t_end] for ep in episodes]).reshape(-1, 2)
    slip_mask = np.zeros(n_imu, dtype=bool)
    for start, end in slip_intervals:
        slip_mask |= (t_imu >= start) & (t_imu <= end)

    rotation_t = _tensor(state.rotation)
    imu = ImuSamples(
        t=_tensor(t_imu),
        gyro=_tensor(gyro),
        accel=_tensor(accel),
        mask=torch.ones((1, n_imu), dtype=torch.bool),
    )
    wheel = WheelSamples(
        t=_tensor(t_w),
        left_speed=_tensor(wheel_speed[:, 0]),
        right_speed=_tensor(wheel_speed[:, 1]),
        mask=torch.ones((1, n_w), dtype=torch.bool),
    )
    wheel_truth = WheelSamples(
        t=_tensor(t_w),
        left_speed=_tensor(true_left),
        right_speed=_tensor(true_right),
        mask=torch.ones((1, n_w), dtype=torch.bool),
    )
    gnss = GnssFixes(
        t=_tensor(t_g),
        position=_tensor(gnss_position),
        sigma=_tensor(np.broadcast_to(sigma, (len(t_g), 3))),
        mask=torch.ones((1, len(t_g)), dtype=torch.bool),
    )
    ground_truth = Trajectory(
        t=_tensor(t_imu),
        position=_tensor(state.position),
        quaternion=matrix_to_quat(rotation_t),
        mask=torch.ones((1, n_imu), dtype=torch.bool),
    )
    meta: dict[str, Any] = {
        "sensor": {
            "wheel_track_m": config.wheel_track_m,
            "wheel_radius_m": config.wheel_radius_m,
            "encoder_ticks_per_rev": config.encoder_ticks_per_rev,
            "wheel_speed_noise_mps": config.wheel_speed_noise_mps,
            "imu_noise": noise.to_dict(),
            "imu_model": noise.name,
            "gnss_sigma_m": [float(x) for x in sigma],
            "gnss_lever_arm_m": [float(x) for x in lever],
            "slip_types": [ep.kind for ep in episodes],
        },
        "sim": {
            **config.to_dict(),
            "seed": int(seed),
            **({} if path_seed is None else {"path_seed": int(path_seed)}),
        },
        "slip_episodes": [ep.to_dict() for ep in episodes],
        "truth": {"wheel_scale_error": [float(x) for x in scale - 1.0]},
        **magnetometer_meta,
    }
    sequence = Sequence(
        names=[f"sim_wheeled_seed{int(seed)}"],
        imu=imu,
        wheel=wheel,
        gnss=gnss,
        gnss_velocity=gnss_velocity,
        gnss_heading=gnss_heading,
        ground_truth=ground_truth,
        magnetometer=magnetometer,
        labels={
            "slip": _tensor(slip_intervals),
            "gnss_outage": _tensor(outages),
            **magnetometer_labels,
        },
        meta=meta,
    )
    sequence.check()
    truth = SimTruth(
        t=_tensor(t_imu),
        position=_tensor(state.position),
        velocity=_tensor(state.velocity),
        rotation=rotation_t,
        angular_velocity=_tensor(state.angular_velocity),
        specific_force=_tensor(state.specific_force),
        speed=_tensor(state.speed),
        gyro_bias=_tensor(bias_g),
        accel_bias=_tensor(bias_a),
        slip_mask_imu=torch.from_numpy(slip_mask)[None],
        wheel_scale_error=_tensor(scale - 1.0),
    )
    return SimulatedRun(
        sequence=sequence,
        truth=truth,
        wheel_truth=wheel_truth,
        slip_episodes=episodes,
        path=path,
        config=config,
        seed=int(seed),
    )
