"""Weather for simulated runs: a labelled schedule and physical sensor-degradation models.

A :class:`WeatherSchedule` splits a run into contiguous segments, each with one condition
from :data:`CONDITIONS`. Each condition is a :class:`WeatherCondition`: meteorological
visibility, illuminance, rain rate, scene contrast and ground friction. Sensor models turn
those quantities into degraded streams:

* **Atmospheric extinction** (:func:`extinction_coefficient`). Aerosol (fog, haze, snow)
  extinction from the meteorological visibility ``V`` by Koschmieder's law,
  ``beta = 3.912 / V`` at 550 nm (2 % contrast threshold, ``ln 50 = 3.912``), scaled to
  another wavelength with Kim's size-distribution exponent ``(lambda / 550 nm)^-q(V)``. Rain
  adds ``alpha = a R^b`` (wavelength-independent for mm-sized drops) with Carbonneau's
  free-space-optics fit ``A = 1.076 R^0.67`` dB/km (``R`` in mm/h).
* **Visual odometry** (:class:`CameraModel`). A feature with intrinsic Michelson contrast
  ``c`` at depth ``d`` is seen with contrast ``c T``, ``T = exp(-beta d)``. On a pixel signal of
  ``S`` photoelectrons (auto-exposure target, or ``k E`` when the exposure is capped at low
  illuminance ``E``) with read noise ``r``, its contrast-to-noise ratio is
  ``CNR = c T S / sqrt(S + r^2)``. With scene contrasts exponential of mean ``c_mean``, the
  expected number of features above the detection threshold ``CNR_min`` is
  ``n = N_scene exp(-CNR_min sqrt(S + r^2) / (c_mean T S))``. A frame tracks
  ``Poisson(n)`` features; below ``min_tracked_features`` it is dropped (mask False), above it
  the pose noise is ``sigma = sigma_1 / sqrt(features)`` (position and rotation).
* **LiDAR odometry** (:class:`LidarModel`). With received power ``~ exp(-2 alpha R) / R^2``,
  the maximum range ``R_max`` for the reference target obeys ``R_max exp(alpha R_max) = R_0``,
  i.e. ``R_max = W(alpha R_0) / alpha`` (Lambert W). Surfaces lie at exponentially distributed
  distances of mean ``L``, so a fraction ``1 - exp(-R_max / L)`` of the scan points return; a
  fraction ``p_spur = 1 - exp(-alpha g)`` of the beams is backscattered by particles inside
  the near gate ``g`` (spurious returns, discarded). Point-to-plane registration has position
  information ``H = (n / sigma_pt^2) sum_i n_i n_i^T / n``: surface normals are isotropic in
  the open (``H = n / (3 sigma_pt^2) I``); in a corridor only a fraction ``f`` of them faces
  along the corridor axis ``a``, ``H = (n / sigma_pt^2) (f a a^T + (1 - f) / 2 (I - a a^T))``,
  so the covariance ``H^-1`` is largest along the corridor (degeneracy).
* **Unmodelled error** (both pose sources). An odometry front end reports the covariance its
  estimator can compute: nominal per-feature (per-point) noise over the number of features
  (points) it used. Weather adds error that this covariance does not see, so the emitted
  white noise has covariance ``k^2`` times the reported one (``k`` = ``error_scale``):

  - VO, contrast: corner localisation error is inversely proportional to the feature's
    contrast-to-noise ratio (Cramér-Rao bound of edge / corner localisation). With scene
    contrasts exponential, the CNR of a detected feature is ``CNR_min + X``,
    ``X ~ Exp(m)``, ``m = c_mean T S / sqrt(S + r^2)`` (the exponential is memoryless), so
    ``E[1/CNR^2] = (1/m) (1/a - (1/m) e^(a/m) E_1(a/m))`` with ``a = CNR_min``. The reported
    ``sigma_1`` is calibrated on clear-daylight features (``T = 1``, full signal, contrast
    ``calibration_contrast``).
  - VO, motion blur: the exposure ``t_e = t_max S / (k E)`` grows to ``t_max`` in the dark;
    image points move at ``f (|omega| + v / d)`` px/s (rotation plus translation parallax at
    the feature depth), smearing a feature over ``b = f (|omega| + v / d) t_e`` px, a box
    of variance ``b^2 / 12``. Per-feature variance ``sigma_px^2 E[1/CNR^2] / E_ref[1/CNR^2]
    + b^2 / 12`` against the reported ``sigma_px^2``.
  - LiDAR, clutter: a multi-echo LiDAR also reports echoes of fog, rain or snow particles
    beyond the near gate, out to ``g_c`` where particle backscatter falls below the
    detection threshold: per beam with probability ``p_c = e^(-alpha g) (1 - e^(-alpha
    (g_c - g)))``. Registration cannot tell them from surface points: it reports
    ``sigma_pt^2 / (n_s + n_c)``, while a clutter point's residual after the robust kernel
    has sigma ``sigma_c``, so ``k^2 = (n_s + n_c sigma_c^2 / sigma_pt^2) / (n_s + n_c)``.

* **Drift** (both pose sources): the odometry frame wanders from the world frame as a random
  walk in distance travelled ``s``: position increments ``N(0, q_p^2 ds)`` drawn in the body
  frame and rotated to world, rotation increments ``N(0, q_theta^2 ds)`` (body), each
  step times the sample's ``error_scale`` ``k`` (drift accumulates the frame-to-frame
  errors, which grow with the same per-feature error). A source's per-sample covariance
  describes its white noise only (before ``k``); the drift is returned separately
  (:class:`PoseSourceTruth`) so that it can be evaluated.
* **Wheels** (:class:`WheelModel`, :func:`weather_slip_config`). High-traction-demand events
  (kerbs, bumps, starts) arrive at rate ``lambda_0``; their peak friction demand is
  exponential with mean ``mu_d``. One slips when its demand exceeds the ground's friction
  coefficient ``mu``: slip episodes arrive at ``lambda_0 exp(-mu / mu_d)``, and the slip ratio
  is the unmet share of the demand, ``s = x / (x + mu)`` with excess ``x ~ Exp(mu_d)``
  (memoryless), so ``P(s <= q) = 1 - exp(-mu q / ((1 - q) mu_d))``.
* **GNSS** (:class:`GnssModel`). In urban intervals (:class:`Environment`), multipath makes
  fix errors multivariate Student-t with ``nu`` degrees of freedom and per-axis scale ``s``
  (covariance ``s^2 nu / (nu - 2)``, reported as the fix sigma), and outages arrive as a
  Poisson process of rate ``lambda_out`` with exponential durations. GNSS at L band is not
  measurably attenuated by rain, fog or snow, so weather leaves it alone.

Pose measurements follow :func:`msf_torch.sensors.pose.pose_residual`:
``r = [p - z_p, Log(R_z^T R)]``. The emitted error ``e`` (drift plus white noise) gives
``z_p = p - e_p``, ``R_z = R Exp(-e_theta)``, so the residual at the truth is exactly ``e``.

References:
    H. Koschmieder, "Theorie der horizontalen Sichtweite", Beitr. Phys. freien Atm. 12, 1924.
    I. Kim, B. McArthur, E. Korevaar, "Comparison of laser beam propagation at 785 nm and
    1550 nm in fog and haze for optical wireless communications", Proc. SPIE 4214, 2001.
    T. Carbonneau, D. Wisely, "Opportunities and challenges for optical wireless", Proc. SPIE
    3232, 1998. H. Pacejka, *Tire and Vehicle Dynamics*, 3rd ed., 2012 (friction levels).

Example:
    >>> from msf_torch.sim import SimConfig, simulate_run
    >>> from msf_torch.sim.weather import WeatherSchedule, apply_weather
    >>> run = simulate_run(SimConfig(duration_s=60.0), seed=1)
    >>> schedule = WeatherSchedule.random(60.0, seed=3)
    >>> wet = apply_weather(run, schedule, seed=4)
    >>> sorted(wet.pose_sources)
    ['lidar', 'vo']
"""

from __future__ import annotations

__all__ = [
    "CONDITIONS",
    "KOSCHMIEDER_CONSTANT",
    "VISIBLE_WAVELENGTH_NM",
    "CARBONNEAU_RAIN_DB_PER_KM",
    "CARBONNEAU_RAIN_EXPONENT",
    "DEFAULT_CONDITIONS",
    "WeatherCondition",
    "WeatherSegment",
    "WeatherSchedule",
    "Environment",
    "CameraModel",
    "LidarModel",
    "WheelModel",
    "GnssModel",
    "PoseSourceTruth",
    "WeatherRun",
    "extinction_coefficient",
    "rain_extinction",
    "apply_weather",
    "weather_slip_config",
    "draw_outages",
]

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.special import exp1, lambertw

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sim.wheeled import SimConfig, SimulatedRun
from msf_torch.types import GnssFixes, PoseMeasurements, Sequence

CONDITIONS: tuple[str, ...] = ("sunny", "rain", "fog", "night", "snow")
"""Weather conditions; labels are ``"weather:<condition>"``."""

KOSCHMIEDER_CONSTANT = math.log(50.0)
"""``-ln(0.02) = 3.912``: extinction times meteorological visibility (2 % contrast)."""

VISIBLE_WAVELENGTH_NM = 550.0
"""Wavelength at which meteorological visibility is defined, nm."""

CARBONNEAU_RAIN_DB_PER_KM = 1.076
CARBONNEAU_RAIN_EXPONENT = 0.67
"""Rain attenuation ``A = 1.076 R^0.67`` dB/km, ``R`` in mm/h (Carbonneau and Wisely 1998)."""


def extinction_coefficient(
    visibility_m: float | np.ndarray,
    wavelength_nm: float = VISIBLE_WAVELENGTH_NM,
    rain_rate_mm_h: float | np.ndarray = 0.0,
) -> np.ndarray:
    """Atmospheric extinction coefficient, 1/m (aerosol by Koschmieder and Kim, plus rain).

    ``beta = 3.912 / V (lambda / 550 nm)^-q(V) + alpha_rain(R)`` with Kim's exponent ``q``:
    1.6 for ``V > 50 km``, 1.3 for 6-50 km, ``0.16 V + 0.34`` for 1-6 km, ``V - 0.5`` for
    0.5-1 km and 0 below 0.5 km (``V`` in km).

    Args:
        visibility_m: meteorological visibility ``V`` (...,), m (> 0).
        wavelength_nm: optical wavelength, nm.
        rain_rate_mm_h: rain rate ``R`` (...,), mm/h.

    Returns:
        (...,) float64 extinction, 1/m.
    """
    vis = np.asarray(visibility_m, np.float64)
    if np.any(vis <= 0):
        raise ValueError(f"extinction_coefficient: visibility must be > 0 m, got {vis!r}")
    km = vis / 1000.0
    q = np.select(
        [km > 50.0, km > 6.0, km > 1.0, km > 0.5],
        [np.full_like(km, 1.6), np.full_like(km, 1.3), 0.16 * km + 0.34, km - 0.5],
        default=0.0,
    )
    aerosol = KOSCHMIEDER_CONSTANT / vis * (wavelength_nm / VISIBLE_WAVELENGTH_NM) ** (-q)
    return aerosol + rain_extinction(rain_rate_mm_h)


def rain_extinction(rain_rate_mm_h: float | np.ndarray) -> np.ndarray:
    """Rain extinction ``alpha = a R^b``, 1/m, from Carbonneau's ``1.076 R^0.67`` dB/km.

    ``a = 1.076 ln(10) / 10 / 1000 = 2.478e-4`` 1/m per (mm/h)^0.67, ``b = 0.67``.

    Args:
        rain_rate_mm_h: ``R`` (...,), mm/h (>= 0).
    """
    rate = np.asarray(rain_rate_mm_h, np.float64)
    if np.any(rate < 0):
        raise ValueError(f"rain_extinction: rain rate must be >= 0 mm/h, got {rate!r}")
    per_m = CARBONNEAU_RAIN_DB_PER_KM * math.log(10.0) / 10.0 / 1000.0
    return per_m * rate**CARBONNEAU_RAIN_EXPONENT


# --------------------------------------------------------------------------------------------
# Conditions and schedule
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WeatherCondition:
    """The physical quantities of one weather condition.

    Attributes:
        name: one of :data:`CONDITIONS` (or a custom name).
        visibility_m: meteorological visibility from aerosol (fog, haze, snowfall), m.
        illuminance_lux: scene illuminance, lux.
        rain_rate_mm_h: rain rate, mm/h.
        scene_contrast: mean Michelson contrast ``c_mean`` of candidate image features.
        friction_mu: tyre-ground friction coefficient ``mu``.
    """

    name: str
    visibility_m: float
    illuminance_lux: float
    rain_rate_mm_h: float
    scene_contrast: float
    friction_mu: float

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of the fields."""
        return dataclasses.asdict(self)


DEFAULT_CONDITIONS: dict[str, WeatherCondition] = {
    # clear air V ~ 20 km, direct sun ~ 2e4 lux, dry asphalt mu ~ 0.8
    "sunny": WeatherCondition("sunny", 20000.0, 20000.0, 0.0, 0.10, 0.8),
    # moderate rain 8 mm/h under overcast ~ 2e3 lux, wet asphalt mu ~ 0.5
    "rain": WeatherCondition("rain", 10000.0, 2000.0, 8.0, 0.10, 0.5),
    # fog V = 80 m (WMO "thick fog" < 200 m), damp ground mu ~ 0.7
    "fog": WeatherCondition("fog", 80.0, 3000.0, 0.0, 0.10, 0.7),
    # street lighting ~ 10 lux, dry ground
    "night": WeatherCondition("night", 20000.0, 10.0, 0.0, 0.10, 0.8),
    # moderate snowfall V ~ 800 m, overcast, low-texture snow cover, packed snow mu ~ 0.2
    "snow": WeatherCondition("snow", 800.0, 3000.0, 0.0, 0.05, 0.2),
}
"""Preset conditions (values typical of the cited literature and road-friction tables)."""


@dataclass(frozen=True)
class WeatherSegment:
    """One schedule segment ``[t_start, t_end]`` s with one condition."""

    t_start: float
    t_end: float
    condition: str


@dataclass(frozen=True)
class WeatherSchedule:
    """Contiguous weather segments covering ``[0, duration_s]``.

    Consecutive segments share their boundary time; a time on a boundary belongs to the later
    segment (the last segment includes ``duration_s``).

    Attributes:
        segments: in time order, the first starting at 0, each starting where the previous
            ends.
    """

    segments: tuple[WeatherSegment, ...]

    def __post_init__(self) -> None:
        if not self.segments:
            raise ValueError("WeatherSchedule: needs at least one segment")
        if self.segments[0].t_start != 0.0:
            raise ValueError(
                f"WeatherSchedule: segment 0 must start at 0 s, got {self.segments[0].t_start}"
            )
        for k, seg in enumerate(self.segments):
            if not seg.t_end > seg.t_start:
                raise ValueError(f"WeatherSchedule: segment {k} is empty or reversed: {seg}")
            if k and seg.t_start != self.segments[k - 1].t_end:
                raise ValueError(
                    f"WeatherSchedule: segment {k} starts at {seg.t_start} s, segment {k - 1} "
                    f"ends at {self.segments[k - 1].t_end} s (gap or overlap)"
                )

    @property
    def duration_s(self) -> float:
        """End of the last segment, s."""
        return self.segments[-1].t_end

    @classmethod
    def constant(cls, condition: str, duration_s: float) -> WeatherSchedule:
        """One condition over ``[0, duration_s]``."""
        return cls((WeatherSegment(0.0, float(duration_s), condition),))

    @classmethod
    def from_boundaries(cls, boundaries_s: list[float], conditions: list[str]) -> WeatherSchedule:
        """Segments ``[b_k, b_{k+1}]`` with ``conditions[k]``; ``boundaries_s[0]`` must be 0."""
        if len(boundaries_s) != len(conditions) + 1:
            raise ValueError(
                f"WeatherSchedule.from_boundaries: {len(boundaries_s)} boundaries for "
                f"{len(conditions)} conditions (need one more boundary)"
            )
        return cls(
            tuple(
                WeatherSegment(float(boundaries_s[k]), float(boundaries_s[k + 1]), c)
                for k, c in enumerate(conditions)
            )
        )

    @classmethod
    def random(
        cls,
        duration_s: float,
        seed: int,
        conditions: tuple[str, ...] = CONDITIONS,
        mean_segment_s: float = 30.0,
        min_segment_s: float = 10.0,
    ) -> WeatherSchedule:
        """Draw a schedule: segment lengths ``min + Exp(mean - min)`` s; the first condition
        uniform, each next one uniform among the others (no repeats back to back). A last
        remainder shorter than ``min_segment_s`` joins the previous segment.

        Args:
            duration_s: run length, s.
            seed: non-negative int.
            conditions: the conditions to draw from.
            mean_segment_s: mean segment length, s (>= ``min_segment_s``).
            min_segment_s: shortest segment, s (> 0).
        """
        if not 0 < min_segment_s <= mean_segment_s:
            raise ValueError(
                "WeatherSchedule.random: need 0 < min_segment_s <= mean_segment_s, got "
                f"{min_segment_s}, {mean_segment_s}"
            )
        if not conditions:
            raise ValueError("WeatherSchedule.random: conditions is empty")
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed))))
        bounds = [0.0]
        while bounds[-1] < duration_s:
            bounds.append(
                bounds[-1] + min_segment_s + rng.exponential(mean_segment_s - min_segment_s)
            )
        bounds[-1] = float(duration_s)
        if len(bounds) > 2 and bounds[-1] - bounds[-2] < min_segment_s:
            del bounds[-2]
        names = [conditions[int(rng.integers(len(conditions)))]]
        while len(names) < len(bounds) - 1:
            others = [c for c in conditions if c != names[-1]] or list(conditions)
            names.append(others[int(rng.integers(len(others)))])
        return cls.from_boundaries(bounds, names)

    def index_at(self, t: np.ndarray) -> np.ndarray:
        """Segment index (N,) int64 at times ``t`` (N,) s (clipped to the schedule)."""
        starts = np.array([s.t_start for s in self.segments])
        return np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)

    def labels(self, conditions: tuple[str, ...] = CONDITIONS) -> dict[str, torch.Tensor]:
        """``"weather:<c>"`` -> (1, K_c, 2) float64 intervals s, for every ``c`` in
        ``conditions`` and in the schedule (K_c = 0 where a condition does not occur)."""
        names = list(dict.fromkeys([*conditions, *(s.condition for s in self.segments)]))
        out = {}
        for name in names:
            rows = [[s.t_start, s.t_end] for s in self.segments if s.condition == name]
            out[f"weather:{name}"] = torch.tensor(rows, dtype=torch.float64).reshape(1, -1, 2)
        return out

    def to_dict(self) -> list[dict[str, Any]]:
        """JSON-friendly list of segments."""
        return [dataclasses.asdict(s) for s in self.segments]


@dataclass(frozen=True)
class Environment:
    """Places along the run (not weather), as time intervals ``((t0, t1), ...)`` s.

    Attributes:
        corridors_s: LiDAR-degenerate corridors; the corridor axis is the direction of travel.
        urban_s: urban canyons (GNSS multipath and outages).
    """

    corridors_s: tuple[tuple[float, float], ...] = ()
    urban_s: tuple[tuple[float, float], ...] = ()

    def labels(self) -> dict[str, torch.Tensor]:
        """``"env:corridor"`` and ``"env:urban"`` -> (1, K, 2) float64 intervals, s."""
        return {
            "env:corridor": _intervals_tensor(self.corridors_s),
            "env:urban": _intervals_tensor(self.urban_s),
        }


# --------------------------------------------------------------------------------------------
# Sensor models
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraModel:
    """Visual-odometry pose source (see the module docstring for the equations).

    Attributes:
        rate_hz: frame rate, Hz.
        scene_features: ``N_scene``, candidate features in view (Harris/FAST corners).
        feature_depth_m: typical feature depth ``d``, m.
        target_signal_electrons: auto-exposure target signal per pixel, e-.
        electrons_per_lux: signal per lux at the longest exposure ``k``, e-/lux.
        read_noise_electrons: read noise ``r``, e- rms.
        detection_cnr: contrast-to-noise ratio ``CNR_min`` a feature needs to be detected.
        min_tracked_features: fewer tracked features drop the frame (tracking lost).
        position_sigma_one_feature_m: ``sigma_1`` position (per axis, world), m.
        rotation_sigma_one_feature_rad: ``sigma_1`` rotation (per axis, body), rad.
        drift_position_m_per_sqrt_m: ``q_p``, m/sqrt(m).
        drift_rotation_rad_per_sqrt_m: ``q_theta``, rad/sqrt(m).
        focal_length_px: focal length ``f``, px.
        max_exposure_s: ``t_max``, longest exposure (signal ``k E`` is reached there), s.
        feature_sigma_px: ``sigma_px``, localisation error of a clear-daylight feature, px.
        calibration_contrast: ``c_mean`` of the clear-daylight scene on which ``sigma_1``
            was calibrated.
    """

    rate_hz: float = 10.0
    scene_features: float = 500.0
    feature_depth_m: float = 10.0
    target_signal_electrons: float = 5000.0
    electrons_per_lux: float = 50.0
    read_noise_electrons: float = 3.0
    detection_cnr: float = 5.0
    min_tracked_features: int = 30
    position_sigma_one_feature_m: float = 0.5
    rotation_sigma_one_feature_rad: float = 0.02
    drift_position_m_per_sqrt_m: float = 0.01
    drift_rotation_rad_per_sqrt_m: float = 1e-3
    focal_length_px: float = 450.0
    max_exposure_s: float = 0.03
    feature_sigma_px: float = 0.3
    calibration_contrast: float = 0.10

    def signal_electrons(self, illuminance_lux: np.ndarray) -> np.ndarray:
        """Pixel signal ``S = min(target, k E)`` (...,), e-."""
        return np.minimum(
            self.target_signal_electrons,
            self.electrons_per_lux * np.asarray(illuminance_lux, np.float64),
        )

    def expected_features(self, condition: WeatherCondition) -> float:
        """``n = N_scene exp(-CNR_min sqrt(S + r^2) / (c_mean T S))`` for ``condition``."""
        beta = extinction_coefficient(
            condition.visibility_m, rain_rate_mm_h=condition.rain_rate_mm_h
        )
        transmittance = math.exp(-float(beta) * self.feature_depth_m)
        signal = float(self.signal_electrons(condition.illuminance_lux))
        noise = math.sqrt(signal + self.read_noise_electrons**2)
        exponent = self.detection_cnr * noise / (condition.scene_contrast * transmittance * signal)
        return self.scene_features * math.exp(-exponent)

    def sigmas(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and rotation (rad) sigma per axis, (...,) each, for ``features``."""
        root = np.sqrt(np.maximum(np.asarray(features, np.float64), 1.0))
        return self.position_sigma_one_feature_m / root, self.rotation_sigma_one_feature_rad / root

    def mean_cnr(self, condition: WeatherCondition) -> float:
        """``m = c_mean T S / sqrt(S + r^2)``, mean CNR of the scene's candidate features."""
        beta = extinction_coefficient(
            condition.visibility_m, rain_rate_mm_h=condition.rain_rate_mm_h
        )
        transmittance = math.exp(-float(beta) * self.feature_depth_m)
        signal = float(self.signal_electrons(condition.illuminance_lux))
        noise = math.sqrt(signal + self.read_noise_electrons**2)
        return condition.scene_contrast * transmittance * signal / noise

    def inverse_cnr_squared(self, mean_cnr: float) -> float:
        """``E[1 / CNR^2]`` of detected features, ``CNR = CNR_min + Exp(mean_cnr)``."""
        a, m = self.detection_cnr, mean_cnr
        z = a / m
        # e^z E_1(z); asymptotic series where exp(z) would overflow
        if z < 300.0:
            scaled = math.exp(z) * float(exp1(z))
        else:
            scaled = (1 - 1 / z + 2 / z**2 - 6 / z**3 + 24 / z**4) / z
        return (1.0 / a - scaled / m) / m

    def exposure_s(self, illuminance_lux: float) -> float:
        """``t_e = t_max S / (k E)``, s."""
        signal = float(self.signal_electrons(illuminance_lux))
        return self.max_exposure_s * signal / (self.electrons_per_lux * illuminance_lux)

    def error_scale(
        self, condition: WeatherCondition, speed: np.ndarray, angular_rate: np.ndarray
    ) -> np.ndarray:
        """``k`` (N,): true over reported sigma from contrast and motion blur.

        Args:
            condition: the weather.
            speed: (N,) m/s.
            angular_rate: (N,) ``|omega|``, rad/s.
        """
        clear = dataclasses.replace(
            DEFAULT_CONDITIONS["sunny"],
            visibility_m=1e9,
            illuminance_lux=self.target_signal_electrons / self.electrons_per_lux * 1e3,
            scene_contrast=self.calibration_contrast,
        )
        ratio = self.inverse_cnr_squared(self.mean_cnr(condition)) / self.inverse_cnr_squared(
            self.mean_cnr(clear)
        )
        image_rate = np.asarray(angular_rate) + np.asarray(speed) / self.feature_depth_m
        blur_px = self.focal_length_px * image_rate * self.exposure_s(condition.illuminance_lux)
        return np.sqrt(ratio + blur_px**2 / 12.0 / self.feature_sigma_px**2)


@dataclass(frozen=True)
class LidarModel:
    """LiDAR-odometry pose source (see the module docstring for the equations).

    Attributes:
        rate_hz: scan rate, Hz.
        wavelength_nm: laser wavelength, nm.
        clear_range_m: ``R_0``, maximum range for the reference target without extinction, m.
        scene_depth_m: ``L``, mean distance of the surfaces around the robot, m.
        near_gate_m: ``g``, near-field gate in which particle backscatter gives spurious
            returns, m.
        scan_points: registration constraints per scan with every point returning; the valid
            points of a scan are ``Binomial(scan_points, (1 - exp(-R_max / L)) (1 - p_spur))``.
        min_valid_points: fewer valid points drop the scan.
        point_sigma_m: ``sigma_pt``, point-to-plane residual, m.
        rotation_sigma_one_point_rad: rotation sigma per axis for one point, rad (scales
            ``1 / sqrt(points)``).
        corridor_axial_normal_fraction: ``f``, share of surface normals along the corridor
            axis in a corridor (1/3 means isotropic).
        drift_position_m_per_sqrt_m: ``q_p``, m/sqrt(m).
        drift_rotation_rad_per_sqrt_m: ``q_theta``, rad/sqrt(m).
        clutter_range_m: ``g_c``, range out to which particle echoes are detected, m.
        clutter_residual_sigma_m: ``sigma_c``, residual of a clutter point after the
            registration's robust kernel, m.
    """

    rate_hz: float = 10.0
    wavelength_nm: float = 905.0
    clear_range_m: float = 100.0
    scene_depth_m: float = 20.0
    near_gate_m: float = 2.0
    scan_points: int = 400
    min_valid_points: int = 60
    point_sigma_m: float = 0.2
    rotation_sigma_one_point_rad: float = 0.02
    corridor_axial_normal_fraction: float = 0.02
    drift_position_m_per_sqrt_m: float = 0.002
    drift_rotation_rad_per_sqrt_m: float = 2e-4
    clutter_range_m: float = 10.0
    clutter_residual_sigma_m: float = 1.0

    def extinction(self, condition: WeatherCondition) -> float:
        """``alpha`` at the laser wavelength, 1/m."""
        return float(
            extinction_coefficient(
                condition.visibility_m, self.wavelength_nm, condition.rain_rate_mm_h
            )
        )

    def max_range(self, alpha: float) -> float:
        """``R_max = W(alpha R_0) / alpha`` (``R_0`` as alpha -> 0), m."""
        if alpha * self.clear_range_m < 1e-12:
            return self.clear_range_m
        return float(lambertw(alpha * self.clear_range_m).real) / alpha

    def spurious_probability(self, alpha: float) -> float:
        """``p_spur = 1 - exp(-alpha g)``."""
        return -math.expm1(-alpha * self.near_gate_m)

    def clutter_probability(self, alpha: float) -> float:
        """``p_c = e^(-alpha g) (1 - e^(-alpha (g_c - g)))``, particle echo past the gate."""
        gap = max(self.clutter_range_m - self.near_gate_m, 0.0)
        return math.exp(-alpha * self.near_gate_m) * -math.expm1(-alpha * gap)

    def error_scale(self, surface_points: np.ndarray, clutter_points: np.ndarray) -> np.ndarray:
        """``k = sqrt((n_s + n_c sigma_c^2 / sigma_pt^2) / (n_s + n_c))`` (N,)."""
        surface = np.asarray(surface_points, np.float64)
        clutter = np.asarray(clutter_points, np.float64)
        ratio = (self.clutter_residual_sigma_m / self.point_sigma_m) ** 2
        return np.sqrt((surface + clutter * ratio) / np.maximum(surface + clutter, 1.0))

    def expected_points(self, condition: WeatherCondition) -> float:
        """Valid points ``n (1 - exp(-R_max / L)) (1 - p_spur)``."""
        alpha = self.extinction(condition)
        in_range = -math.expm1(-self.max_range(alpha) / self.scene_depth_m)
        return self.scan_points * in_range * (1.0 - self.spurious_probability(alpha))

    def position_covariance(
        self, points: np.ndarray, axis: np.ndarray, corridor: np.ndarray
    ) -> np.ndarray:
        """``H^-1`` (N, 3, 3) world, m^2.

        Args:
            points: (N,) valid points.
            axis: (N, 3) unit corridor axis (world).
            corridor: (N,) bool, True inside a corridor.
        """
        frac = np.where(corridor, self.corridor_axial_normal_fraction, 1.0 / 3.0)
        outer = axis[:, :, None] * axis[:, None, :]
        # H^-1 = sigma^2 / n (a a^T / f + (I - a a^T) 2 / (1 - f)): a a^T and I - a a^T are
        # complementary projectors, so their weights invert separately.
        along = 1.0 / frac
        across = 2.0 / (1.0 - frac)
        scale = self.point_sigma_m**2 / np.maximum(points, 1.0)
        eye = np.eye(3)
        return scale[:, None, None] * (
            along[:, None, None] * outer + across[:, None, None] * (eye - outer)
        )


@dataclass(frozen=True)
class WheelModel:
    """Friction-limited slip (see the module docstring).

    Attributes:
        traction_event_rate_per_min: ``lambda_0``, high-traction-demand events per minute.
        traction_demand_mean: ``mu_d``, mean peak friction demand of an event.
    """

    traction_event_rate_per_min: float = 2.0
    traction_demand_mean: float = 0.15

    def slip_rate_per_min(self, mu: float) -> float:
        """Slip episodes per minute ``lambda_0 exp(-mu / mu_d)``."""
        return self.traction_event_rate_per_min * math.exp(-mu / self.traction_demand_mean)

    def slip_ratio_quantile(self, mu: float, p: float) -> float:
        """Quantile ``p`` of ``s = x / (x + mu)``, ``x ~ Exp(mu_d)``: ``y / (y + mu)`` with
        ``y = -mu_d ln(1 - p)``."""
        excess = -self.traction_demand_mean * math.log1p(-p)
        return excess / (excess + mu)


@dataclass(frozen=True)
class GnssModel:
    """Urban GNSS: Student-t multipath errors and Poisson outages (see the module docstring).

    Attributes:
        urban_dof: ``nu`` of the multivariate Student-t error (> 2).
        urban_scale_horizontal_m: scale ``s`` east and north, m.
        urban_scale_vertical_m: scale ``s`` up, m.
        urban_outage_rate_per_min: ``lambda_out``, outage starts per minute inside urban
            intervals.
        urban_outage_mean_s: mean outage duration, s.
    """

    urban_dof: float = 3.0
    urban_scale_horizontal_m: float = 1.5
    urban_scale_vertical_m: float = 3.0
    urban_outage_rate_per_min: float = 0.5
    urban_outage_mean_s: float = 8.0

    def __post_init__(self) -> None:
        if not self.urban_dof > 2.0:
            raise ValueError(
                f"GnssModel.urban_dof must be > 2 (finite covariance), got {self.urban_dof!r}"
            )

    def urban_sigma(self) -> np.ndarray:
        """(3,) per-axis standard deviation ``s sqrt(nu / (nu - 2))``, m."""
        scale = np.array(
            [
                self.urban_scale_horizontal_m,
                self.urban_scale_horizontal_m,
                self.urban_scale_vertical_m,
            ]
        )
        return scale * math.sqrt(self.urban_dof / (self.urban_dof - 2.0))


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass
class PoseSourceTruth:
    """What a pose source did at each of its N samples (numpy float64, B dropped).

    Attributes:
        t: (N,) s.
        condition: (N,) segment index into the schedule.
        expected_count: (N,) expected features (VO) or valid points (LiDAR).
        count: (N,) realised features (Poisson) or valid points (Binomial).
        drift: (N, 6) ``[dp (world, m), dtheta (body, rad)]`` of the odometry frame.
        noise: (N, 6) white error, same layout; the emitted error is ``drift + noise``.
        corridor: (N,) bool, inside a corridor (LiDAR; all False for VO).
        error_scale: (N,) ``k``, emitted white-noise sigma over the reported one.
        clutter: (N,) particle echoes taken as points (LiDAR; zeros for VO).
    """

    t: np.ndarray
    condition: np.ndarray
    expected_count: np.ndarray
    count: np.ndarray
    drift: np.ndarray
    noise: np.ndarray
    corridor: np.ndarray
    error_scale: np.ndarray
    clutter: np.ndarray


@dataclass
class WeatherRun:
    """A simulated run with weather applied.

    Attributes:
        sequence: shallow copy of ``truth.sequence`` (unchanged streams share tensors) with
            GNSS degraded (velocities and headings, when the run has them, removed in
            the new urban outages with the fixes), ``poses`` the chosen source (or None),
            ``pose_sources`` both sources (the same tensors as :attr:`pose_sources`),
            labels extended with ``"weather:<c>"``, ``"env:corridor"``, ``"env:urban"``
            and the merged ``"gnss_outage"``, and ``meta["weather"]``.
        pose_sources: ``"vo"`` and ``"lidar"`` streams (B = 1), dropped samples masked False
            and zero-filled.
        source_truth: per source, counts, drift and white noise (:class:`PoseSourceTruth`).
        schedule: the weather schedule.
        environment: the corridors and urban intervals.
        truth: the clean simulated run.
        seed: the weather seed.
    """

    sequence: Sequence
    pose_sources: dict[str, PoseMeasurements]
    source_truth: dict[str, PoseSourceTruth]
    schedule: WeatherSchedule
    environment: Environment
    truth: SimulatedRun
    seed: int


# --------------------------------------------------------------------------------------------
# Applying weather
# --------------------------------------------------------------------------------------------


def _intervals_tensor(intervals: Any) -> torch.Tensor:
    return torch.tensor(np.asarray(intervals, np.float64).reshape(-1, 2))[None]


def _inside(t: np.ndarray, intervals: Any) -> np.ndarray:
    hit = np.zeros(t.shape, dtype=bool)
    for start, end in np.asarray(intervals, np.float64).reshape(-1, 2):
        hit |= (t >= start) & (t <= end)
    return hit


def _merge(intervals: np.ndarray) -> np.ndarray:
    """Sorted union (K, 2) of closed intervals (M, 2)."""
    merged: list[list[float]] = []
    for start, end in intervals[np.argsort(intervals[:, 0], kind="stable")]:
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], float(end))
        else:
            merged.append([float(start), float(end)])
    return np.asarray(merged, np.float64).reshape(-1, 2)


def draw_outages(
    intervals: Any, rate_per_min: float, mean_s: float, rng: np.random.Generator
) -> np.ndarray:
    """Poisson outages inside ``intervals``: starts at ``rate_per_min / 60`` per s, each
    lasting ``Exp(mean_s)`` s (clipped to its interval). Returns (K, 2) s, merged."""
    rows = []
    for start, end in np.asarray(intervals, np.float64).reshape(-1, 2):
        count = rng.poisson(rate_per_min / 60.0 * (end - start))
        starts = np.sort(rng.uniform(start, end, count))
        ends = np.minimum(starts + rng.exponential(mean_s, count), end)
        rows.append(np.stack((starts, ends), -1))
    if not rows:
        return np.zeros((0, 2))
    return _merge(np.concatenate(rows, 0))


def _drift(
    rotation: np.ndarray,
    distance: np.ndarray,
    q_position: float,
    q_rotation: float,
    rng: np.random.Generator,
    scale: np.ndarray,
) -> np.ndarray:
    """(N, 6) random-walk drift from per-sample distances (N,) m, steps times ``scale``
    (N,); zero at the first sample."""
    root = (np.sqrt(distance) * scale)[:, None]
    step_p = np.einsum("nij,nj->ni", rotation, rng.normal(0.0, 1.0, (len(distance), 3))) * root
    step_r = rng.normal(0.0, 1.0, (len(distance), 3)) * root
    steps = np.concatenate((q_position * step_p, q_rotation * step_r), -1)
    steps[0] = 0.0
    return np.cumsum(steps, 0)


def _pose_stream(
    t: np.ndarray,
    position: np.ndarray,
    rotation: np.ndarray,
    error: np.ndarray,
    covariance: np.ndarray,
    keep: np.ndarray,
) -> PoseMeasurements:
    """Measured poses ``z_p = p - e_p``, ``R_z = R Exp(-e_theta)``; dropped samples zero."""
    rot = torch.from_numpy(rotation)
    measured = rot @ so3.exp(-torch.from_numpy(np.ascontiguousarray(error[:, 3:])))
    quat = matrix_to_quat(measured)
    mask = torch.from_numpy(keep)
    zero = ~mask
    position_z = torch.from_numpy(position - error[:, :3])
    cov = torch.from_numpy(np.ascontiguousarray(covariance))
    position_z[zero] = 0.0
    quat[zero] = 0.0
    cov[zero] = 0.0
    return PoseMeasurements(
        t=torch.from_numpy(t)[None],
        position=position_z[None],
        quaternion=quat[None],
        covariance=cov[None],
        mask=mask[None],
    )


def _sample_times(duration_s: float, rate_hz: float) -> np.ndarray:
    count = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    return np.arange(count) / rate_hz


def _block_diag(position_cov: np.ndarray, rotation_var: np.ndarray) -> np.ndarray:
    """(N, 6, 6) from (N, 3, 3) position covariance and (N,) isotropic rotation variance."""
    out = np.zeros((len(rotation_var), 6, 6))
    out[:, :3, :3] = position_cov
    out[:, 3:, 3:] = rotation_var[:, None, None] * np.eye(3)
    return out


def _sample_error(
    covariance: np.ndarray, drift: np.ndarray, rng: np.random.Generator, scale: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """White noise ``k L z`` (N, 6) with ``L L^T = covariance``, ``k = scale`` (N,), and
    ``drift + noise``."""
    chol = np.linalg.cholesky(covariance)
    noise = np.einsum("nij,nj->ni", chol, rng.normal(0.0, 1.0, (len(covariance), 6)))
    noise = noise * scale[:, None]
    return noise, drift + noise


def apply_weather(
    run: SimulatedRun,
    schedule: WeatherSchedule,
    seed: int,
    *,
    environment: Environment | None = None,
    conditions: Mapping[str, WeatherCondition] | None = None,
    camera: CameraModel | None = None,
    lidar: LidarModel | None = None,
    gnss: GnssModel | None = None,
    pose_source: str | None = None,
    unreported_error: bool = False,
) -> WeatherRun:
    """Degrade a simulated run under ``schedule``: VO and LiDAR pose streams, GNSS, labels.

    Independent random streams (``SeedSequence(seed).spawn(3)``: VO, LiDAR, GNSS) make the
    result bit-identical for the same run, schedule, models and seed. Pose sources sample at
    ``k / rate_hz`` over ``[0, duration]``, with truth from ``run.path``.

    Wheels are not touched here: friction acts through the slip episodes, so draw the run's
    config with :func:`weather_slip_config` before :func:`~msf_torch.sim.simulate_run`.

    Args:
        run: from :func:`~msf_torch.sim.simulate_run`.
        schedule: must cover the run (``duration_s`` equal to the run's).
        seed: non-negative int.
        environment: corridors and urban intervals (default: none).
        conditions: condition name -> :class:`WeatherCondition` (default
            :data:`DEFAULT_CONDITIONS`); must hold every condition in the schedule.
        camera, lidar, gnss: models (defaults as documented on each class).
        pose_source: ``"vo"``, ``"lidar"`` or None (default): the stream also put in
            ``sequence.poses``, where the filter fuses it as absolute poses. Both streams are
            always in ``sequence.pose_sources``, fused as odometry; name one here only for a
            filter configured with ``pose_sources`` that excludes it, or it is used twice.
        unreported_error: emit the weather error the sources do not report (VO contrast
            and motion blur, LiDAR clutter: ``error_scale`` ``k``, see the module
            docstring). False (default) keeps ``k = 1`` and draws no clutter: the declared
            covariances are then exact, the idealisation the filter-consistency tests use.

    Returns:
        :class:`WeatherRun`, float64 CPU tensors, B = 1.

    Raises:
        ValueError: schedule and run durations differ, a condition is unknown, the seed is
            negative or ``pose_source`` is not a source.
    """
    environment = environment or Environment()
    conditions = dict(conditions or DEFAULT_CONDITIONS)
    camera, lidar, gnss = camera or CameraModel(), lidar or LidarModel(), gnss or GnssModel()
    duration = run.config.duration_s
    if not math.isclose(schedule.duration_s, duration, rel_tol=0.0, abs_tol=1e-9):
        raise ValueError(
            f"apply_weather: schedule covers {schedule.duration_s} s, the run {duration} s"
        )
    missing = sorted({s.condition for s in schedule.segments} - set(conditions))
    if missing:
        raise ValueError(f"apply_weather: no WeatherCondition for {missing}")
    if pose_source not in ("vo", "lidar", None):
        raise ValueError(
            f"apply_weather: pose_source must be 'vo', 'lidar' or None, got {pose_source!r}"
        )
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"apply_weather: seed must be a non-negative int, got {seed!r}")
    rng_vo, rng_lidar, rng_gnss = (
        np.random.Generator(np.random.PCG64(s)) for s in np.random.SeedSequence(int(seed)).spawn(3)
    )
    segment_conditions = [conditions[s.condition] for s in schedule.segments]
    sources: dict[str, PoseMeasurements] = {}
    source_truth: dict[str, PoseSourceTruth] = {}

    # VO ---------------------------------------------------------------------------------
    t_vo = _sample_times(duration, camera.rate_hz)
    state = run.path.evaluate(t_vo)
    seg = schedule.index_at(t_vo)
    expected = np.array([camera.expected_features(c) for c in segment_conditions])[seg]
    features = rng_vo.poisson(expected).astype(np.float64)
    sig_p, sig_r = camera.sigmas(features)
    cov = _block_diag(sig_p[:, None, None] ** 2 * np.eye(3), sig_r**2)
    rate = np.linalg.norm(state.angular_velocity, axis=-1)
    scale = np.ones(len(t_vo))
    for k, condition in enumerate(segment_conditions):
        here = (seg == k) & unreported_error
        scale[here] = camera.error_scale(condition, state.speed[here], rate[here])
    distance = np.linalg.norm(np.diff(state.position, axis=0, prepend=state.position[:1]), axis=-1)
    drift = _drift(
        state.rotation,
        distance,
        camera.drift_position_m_per_sqrt_m,
        camera.drift_rotation_rad_per_sqrt_m,
        rng_vo,
        scale,
    )
    noise, error = _sample_error(cov, drift, rng_vo, scale)
    keep = features >= camera.min_tracked_features
    sources["vo"] = _pose_stream(t_vo, state.position, state.rotation, error, cov, keep)
    source_truth["vo"] = PoseSourceTruth(
        t_vo,
        seg,
        expected,
        features,
        drift,
        noise,
        np.zeros(len(t_vo), dtype=bool),
        scale,
        np.zeros(len(t_vo)),
    )

    # LiDAR ------------------------------------------------------------------------------
    t_li = _sample_times(duration, lidar.rate_hz)
    state = run.path.evaluate(t_li)
    seg = schedule.index_at(t_li)
    expected = np.array([lidar.expected_points(c) for c in segment_conditions])[seg]
    points = rng_lidar.binomial(lidar.scan_points, expected / lidar.scan_points).astype(np.float64)
    p_clutter = np.array(
        [lidar.clutter_probability(lidar.extinction(c)) for c in segment_conditions]
    )[seg]
    clutter = (
        rng_lidar.binomial(lidar.scan_points, p_clutter).astype(np.float64)
        if unreported_error
        else np.zeros(len(t_li))
    )
    accepted = points + clutter
    horizontal = state.velocity * np.array([1.0, 1.0, 0.0])
    axis = horizontal / np.linalg.norm(horizontal, axis=-1, keepdims=True)
    corridor = _inside(t_li, environment.corridors_s)
    pos_cov = lidar.position_covariance(accepted, axis, corridor)
    rot_var = lidar.rotation_sigma_one_point_rad**2 / np.maximum(accepted, 1.0)
    cov = _block_diag(pos_cov, rot_var)
    scale = lidar.error_scale(points, clutter)
    distance = np.linalg.norm(np.diff(state.position, axis=0, prepend=state.position[:1]), axis=-1)
    drift = _drift(
        state.rotation,
        distance,
        lidar.drift_position_m_per_sqrt_m,
        lidar.drift_rotation_rad_per_sqrt_m,
        rng_lidar,
        scale,
    )
    noise, error = _sample_error(cov, drift, rng_lidar, scale)
    keep = points >= lidar.min_valid_points
    sources["lidar"] = _pose_stream(t_li, state.position, state.rotation, error, cov, keep)
    source_truth["lidar"] = PoseSourceTruth(
        t_li, seg, expected, points, drift, noise, corridor, scale, clutter
    )

    # GNSS -------------------------------------------------------------------------------
    old = run.sequence.gnss
    t_g = old.t[0].numpy()
    new_outages = draw_outages(
        environment.urban_s, gnss.urban_outage_rate_per_min, gnss.urban_outage_mean_s, rng_gnss
    )
    urban = _inside(t_g, environment.urban_s)
    g_state = run.path.evaluate(t_g)
    lever = np.asarray(run.config.gnss_lever_arm_m, np.float64)
    antenna = g_state.position + np.einsum("nij,j->ni", g_state.rotation, lever)
    scale = gnss.urban_sigma() * math.sqrt((gnss.urban_dof - 2.0) / gnss.urban_dof)
    chi2 = rng_gnss.chisquare(gnss.urban_dof, len(t_g))
    t_error = (
        rng_gnss.normal(0.0, 1.0, (len(t_g), 3)) * scale / np.sqrt(chi2 / gnss.urban_dof)[:, None]
    )
    position = old.position[0].numpy().copy()
    sigma = old.sigma[0].numpy().copy()
    position[urban] = antenna[urban] + t_error[urban]
    sigma[urban] = gnss.urban_sigma()
    keep = old.mask[0].numpy() & ~_inside(t_g, new_outages)
    degraded_gnss = GnssFixes(
        t=old.t[:, keep],
        position=torch.from_numpy(position[keep])[None],
        sigma=torch.from_numpy(sigma[keep])[None],
        mask=old.mask[:, keep],
    )
    # an urban outage takes the receiver's velocities and headings with its fixes
    receiver = {}
    for name in ("gnss_velocity", "gnss_heading"):
        stream = getattr(run.sequence, name)
        if stream is not None:
            outside = torch.from_numpy(~_inside(stream.t[0].numpy(), new_outages))
            receiver[name] = stream.map(lambda x, k=outside: x[:, k])

    # sequence ---------------------------------------------------------------------------
    old_outages = run.sequence.labels["gnss_outage"][0].numpy()
    labels = dict(run.sequence.labels)
    labels["gnss_outage"] = torch.from_numpy(_merge(np.concatenate((old_outages, new_outages), 0)))[
        None
    ]
    labels.update(schedule.labels())
    labels.update(environment.labels())
    meta = dict(run.sequence.meta)
    meta["weather"] = {
        "seed": int(seed),
        "schedule": schedule.to_dict(),
        "conditions": {name: c.to_dict() for name, c in conditions.items()},
        "environment": {
            k: [list(x) for x in v] for k, v in dataclasses.asdict(environment).items()
        },
        "camera": dataclasses.asdict(camera),
        "lidar": dataclasses.asdict(lidar),
        "gnss": dataclasses.asdict(gnss),
        "pose_source": pose_source,
    }
    if unreported_error:  # absent when off: metadata of earlier runs stays as it was
        meta["weather"]["unreported_error"] = True
    sequence = dataclasses.replace(
        run.sequence,
        gnss=degraded_gnss,
        **receiver,
        poses=sources[pose_source] if pose_source else None,
        labels=labels,
        meta=meta,
        pose_sources=dict(sources),
    )
    sequence.check()
    return WeatherRun(
        sequence=sequence,
        pose_sources=sources,
        source_truth=source_truth,
        schedule=schedule,
        environment=environment,
        truth=run,
        seed=int(seed),
    )


def weather_slip_config(
    config: SimConfig,
    schedule: WeatherSchedule,
    seed: int,
    *,
    wheel: WheelModel | None = None,
    conditions: Mapping[str, WeatherCondition] | None = None,
) -> SimConfig:
    """``config`` with slip episodes drawn from the schedule's ground friction.

    The episode count is ``Poisson(sum_k lambda(mu_k) T_k / 60)`` over the segments (capped at
    the number that fits ``config``'s margins, gaps and longest duration). The slip-ratio range
    is the 10 %-90 % quantile band at the rate-weighted friction ``mu_eff`` (duration-weighted
    when no slip is expected)
    (``SimConfig`` draws ratios uniformly in it); lock ratios stay as configured. Episodes are
    placed by :func:`~msf_torch.sim.simulate_run` uniformly over the run, not per segment.

    Args:
        config: the base run settings (its ``duration_s`` must equal the schedule's).
        schedule: the weather schedule.
        seed: non-negative int.
        wheel: the slip model (default :class:`WheelModel`).
        conditions: condition name -> :class:`WeatherCondition` (default presets).
    """
    wheel = wheel or WheelModel()
    conditions = dict(conditions or DEFAULT_CONDITIONS)
    if not math.isclose(schedule.duration_s, config.duration_s, rel_tol=0.0, abs_tol=1e-9):
        raise ValueError(
            f"weather_slip_config: schedule covers {schedule.duration_s} s, the config "
            f"{config.duration_s} s"
        )
    mus = np.array([conditions[s.condition].friction_mu for s in schedule.segments])
    lengths = np.array([s.t_end - s.t_start for s in schedule.segments])
    expected = np.array([wheel.slip_rate_per_min(m) for m in mus]) * lengths / 60.0
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed))))
    count = int(rng.poisson(expected.sum()))
    room = config.duration_s - sum(config.slip_margin_s) + config.slip_min_gap_s
    fits = int(room // (config.slip_duration_s[1] + config.slip_min_gap_s))
    count = min(count, max(fits, 0))
    weights = expected if expected.sum() > 0 else lengths
    mu_eff = float((weights * mus).sum() / weights.sum())
    band = (wheel.slip_ratio_quantile(mu_eff, 0.1), wheel.slip_ratio_quantile(mu_eff, 0.9))
    return dataclasses.replace(config, slip_episodes=count, slip_ratio=band)
