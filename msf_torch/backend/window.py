"""Keyframe smoothers over a run: full batch and sliding window with marginalisation.

Both smoothers work on a :class:`KeyframeGraph`, built once from a sequence and the front
end's output (:func:`build_graph`), and pose their least-squares problems with the same
factor builder (:meth:`KeyframeGraph.factors`). One ``nav_state`` variable per keyframe
(:mod:`msf_torch.frontend.keyframes`); factors:

* IMU preintegration between consecutive keyframes (exact ZOH increments and recursive
  covariance, :mod:`msf_torch.backend.preintegration`), linearised at the front end's bias
  estimate at the interval start. A sample held over an IMU gap (or filled in by the
  recorder) gets the front end's variance multiplier plus the unknown motion over the gap:
  a random walk of the true rate and specific force away from the held sample, per body
  axis (``imu_gap_gyro_rw_density``, ``imu_gap_accel_rw_density``; a ground vehicle turns
  about z and accelerates in x, y: defaults ``[0.005, 0.005, 0.06]`` rad/s^2/sqrt(Hz) and
  ``[0.2, 0.2, 0.02]`` m/s^3/sqrt(Hz), from the simulated robot's held-sample errors over
  10-s stretches: 0.004, 0.005, 0.10 rad/s and 0.32, 0.25, 0.014 m/s^2 rms), so the
  gap's variance grows as ``T^3`` (:func:`_gap_noise_scales`);
* GNSS fixes with the configured robust kernel. **Every epoch that carries a fix is forced
  to be a keyframe**, so a fix constrains the state at its own time exactly, with no
  propagation or interpolation error (the front end already cuts its epochs at fix times);
* a prior on the first keyframe: the front end's state there and its covariance (the
  initial state and covariance, before any update of the filter). When the initialisation
  took position and heading from the first GNSS fixes (``frontend.init``), those fixes
  also enter as factors, so they count twice: once through the prior, with the prior's
  (larger) initial sigmas, and once as fixes;
* magnetometer headings (``MagnetometerFactor``, the front end's residual
  ``wrap(azimuth(R W (m - b)) - D)`` and variance ``sigma^2 / H^2 + floor^2``, under the
  GNSS kernel): the readings the front end fused (``accepted["magnetometer"]``: undisturbed
  in magnitude, turning with the gyro, at most ``magnetometer_rate_hz`` a second, inside
  the dip tolerance and its gate), each carried by the gyro to the keyframe at or before
  it (no keyframe is forced: at 2 Hz that would halve the time a window spans). Their
  variance is evaluated at the front end's attitude, its floor part multiplied by
  ``magnetometer_correlation_s * magnetometer_rate_hz`` (the floor's errors are correlated
  for seconds, and the smoother sums a whole run's readings); the declination is the front
  end's final estimate when it calibrated one;
* wheel odometry between keyframes when the sequence has wheels: each reading holds its
  rim speeds over the interval before its stamp (encoders report the mean over it); its
  rim-speed sigma is ``sqrt(2) * wheel_speed_sigma_mps`` (so the forward speed has the
  front end's sigma), divided by the front end's slip factor at that reading. The yaw row
  is switched off (huge variance) unless ``wheel_yaw_rate_update`` is set, as in the front
  end: the wheel yaw rate carries the radius mismatch;
* the non-holonomic constraint and zero velocity at keyframes where the front end applied
  them; optionally planar motion between keyframes (ground vehicles).

Wheel calibration (``calibrate_wheels``, full batch only): one ``wheel_calib`` variable per
run, ``c = [k_l, k_r, D]`` (radius ratios true / nominal and track width, m, as the front
end's states of :mod:`msf_torch.frontend.calibration`), constant over the run (radii and
track change with load and tyre pressure over hours, not within a run; one variable keeps
the problem a chain plus one border). Each wheel factor recomputes its increment from the
interval's readings at ``c`` (:class:`~msf_torch.backend.factors.CalibratedWheelOdometryFactor`)
and its yaw row is kept (the radius difference is seen only there, as in the front end).
The front end must calibrate its wheels as well
(``calibrate_wheels``): its slip factors weight the wheel factors, and an uncalibrated front
end's slip detector takes miscalibrated wheels for slipping ones.
Prior: the front end's *initial* calibration and sigmas (``calibration_wheel_radius_ratio``,
``wheel_track_m``, ``calibration_wheel_radius_sigma``, ``calibration_wheel_track_sigma_m``):
its final estimate has seen the same wheel readings, so it is only the starting value (when
the front end calibrated its wheels; else the prior mean). The Hessian is block tridiagonal
plus a dense border of three columns, so LM takes its general dense or sparse path; the
marginal covariances come from the chain's Schur complements with the border eliminated
(:func:`bordered_chain_covariance`), still in O(K).

Full batch (:func:`smooth_full`): all keyframes in one LM solve (sparse Cholesky beyond
1500 unknowns). The per-keyframe marginal covariances come from the chain structure of the
problem (every factor joins one keyframe or two consecutive ones, so the Gauss-Newton
Hessian is block tridiagonal): a forward pass of Schur complements and a backward pass
``Sigma_k = S_k^-1 + G_k Sigma_{k+1} G_k^T`` with ``G_k = S_k^-1 H_{k,k+1}`` give the
diagonal blocks of ``H^-1`` in O(K) (:func:`chain_covariance`).

Sliding window (:func:`smooth_window`): windows of ``window_size`` keyframes that slide by
``window_step``. After each window's LM solve the oldest ``window_step`` keyframes leave it:
their estimates are emitted (fixed-lag output) and they are marginalised. The Gauss-Newton
system of every factor that touches them (the previous marginal prior included) is built
dense at the current estimate ``x0`` and the leaving block is removed by the Schur
complement, leaving ``(H_m, g_m)`` on the first keyframe that stays (on a chain it is the
only one connected). With ``H_m = S^T S`` (Cholesky) and ``e = S^-T g_m`` this becomes a
:class:`~msf_torch.backend.factors.MarginalPriorFactor` ``r = S (x [-] x0) + e``, whose cost
``0.5 |S dx + e|^2`` equals ``0.5 dx^T H_m dx + g_m^T dx`` up to a constant. Rank
deficiency (a direction no factor observes, e.g. global yaw without GNSS or a prior):
``H_m`` gets ``marginal_floor * diag(H_m)`` added on its diagonal before the Cholesky
(diagonal entries below 1e-12 of the largest are raised to that), a relative weak prior
(1e-9 of each coordinate's own information by default) that only keeps the factorisation
defined and shifts the estimate by that relative amount; the floor grows tenfold while the
Cholesky still fails.
A window that covers the whole run is exactly the full batch.

Starting values: the first window starts from the front end's keyframe states, as the full
batch does; a keyframe entering a later window starts from the IMU prediction off the
previous keyframe's estimate in the window before. Predicting the first window as well
would dead-reckon through all of it from the initial state, whose tilt (about 1 deg) and
unestimated biases put its last keyframe hundreds of metres off without wheels (60-s IMU +
GNSS sims, 40 s: 300-900 m); LM may then stop at ``max_iterations`` metres from the
optimum, and the marginal prior carries that into the next windows (seed 1: window ATE
3.78 m, front end 0.42 m; from the front end's states 0.22 m, as the full batch).

Accuracy of the window: marginalisation is exact for the linearised problem, but each
keyframe is linearised once, at its estimate when it leaves (no first-estimate Jacobians),
and a fixed-lag estimate does not see beyond the window. On 30-s simulated runs (GNSS sigma
0.5 m, seeds 4-6) the last keyframe ends 0.08-0.21 m from the full batch with 40-keyframe
windows (the default), 0.09-0.29 m with 20 and 0.5-0.6 m with 10 (the filter's last epoch:
0.14-0.20 m). Through a GNSS outage longer than the window a window learns of the outage's
end only when it gets there, so there its error is a filter's, not a smoother's (bundled
sample, 30-s outage: ATE 0.33 m with 40 keyframes, 0.80 m with 20; the front end 0.50 m).

Output: the smoothed keyframe states, and (``output="frontend"``, the default) the
trajectory at every front-end epoch (:func:`interpolate_imu`): between keyframes ``i`` and
``j`` each epoch's state is keyframe ``i``'s smoothed state carried through the IMU with its
smoothed biases (the smoother's own motion model), plus the time fraction of the mismatch
left at keyframe ``j``. The front end's posterior is not used between keyframes: it holds
the jumps of its measurement updates (metres at the first fix after an outage, a few
centimetres at each wheel update when slip ends), which would show as ramps and kinks.

These smoothers take one sequence (B = 1): keyframe counts differ between sequences.
"""

from __future__ import annotations

__all__ = [
    "NOISE_KEYS",
    "SHORT_INTERVAL_PERIODS",
    "SmootherConfig",
    "load_smoother_config",
    "KeyframeGraph",
    "build_graph",
    "SmootherResult",
    "smooth_full",
    "smooth_window",
    "smooth",
    "chain_covariance",
    "bordered_chain_covariance",
    "smooth_full_calibrated",
    "OutputMotion",
    "interpolate_imu",
]

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from msf_torch.backend import factors as F
from msf_torch.backend.lm import LMConfig, LMResult, solve
from msf_torch.backend.preintegration import (
    ImuIntervals,
    cut_imu,
    imu_covariance,
    preintegrate_imu,
    preintegrate_wheel,
)
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.robust import KERNELS, RobustKernel
from msf_torch.backend.variables import (
    NAV_STATE,
    WHEEL_CALIBRATION,
    pack_nav_state,
    unpack_nav_state,
)
from msf_torch.frontend.calibration import WHEEL_STATES
from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, EskfResult, _intra_op_threads
from msf_torch.frontend.guard import sanitize_sequence
from msf_torch.frontend.keyframes import KeyframeConfig, select_keyframes
from msf_torch.frontend.schedule import UNMEASURED_SIGMA, corrected_magnetometer, gap_lengths
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.io.yaml_files import did_you_mean, named_key, read_yaml
from msf_torch.sensors.calibration import shifted_heading_residual
from msf_torch.sensors.imu import Preintegrated, propagate_nominal
from msf_torch.sensors.imu_gaps import gap_walk_scale, interpolated_imu_samples
from msf_torch.sensors.magnetometer import magnetometer_heading_variance
from msf_torch.types import Sequence, Trajectory

_GROUP = "state"
_CALIB = "wheel_calibration"
NOISE_KEYS = (
    "gyro_noise_density",
    "accel_noise_density",
    "gyro_bias_rw_density",
    "accel_bias_rw_density",
    "gnss_sigma_m",
    "nhc_sigma_mps",
    "zupt_sigma_mps",
    "wheel_speed_sigma_mps",
    "imu_gap_noise_scale",
)
"""EskfConfig keys that ``SmootherConfig.noise`` may replace for the back end."""
_YAW_OFF_VARIANCE = 1e4  # rad^2: the wheel yaw row carries no information
SHORT_INTERVAL_PERIODS = 1.5
"""Keyframe intervals shorter than this many IMU periods (about one sample) get a 1e-2
relative diagonal floor on their preintegration covariance instead of 1e-6."""


@dataclass
class SmootherConfig:
    """Back-end smoother settings; the ``smoother:`` section of the run's YAML config.

    Attributes:
        keyframe_interval_s, keyframe_distance_m, keyframe_rotation_rad: keyframe
            thresholds (:class:`~msf_torch.frontend.keyframes.KeyframeConfig`); s, m, rad.
        gnss_kernel: robust kernel on GNSS fixes: ``huber``, ``cauchy``, ``geman_mcclure``,
            ``tukey`` or ``none``.
        gnss_kernel_scale: its scale in whitened units (sigmas).
        wheel: use wheel odometry between keyframes when the sequence has wheels.
        calibrate_wheels: estimate the wheel radius ratios and track width as one
            variable of the run (full batch only; needs ``wheel``).
        gnss_velocity: GNSS velocities (``Sequence.gnss_velocity``) at their keyframes, under
            the GNSS fixes' kernel.
        gnss_heading: dual-antenna GNSS headings (``Sequence.gnss_heading``) at their
            keyframes, under the GNSS fixes' kernel.
        magnetometer: magnetometer headings (``Sequence.magnetometer``): the readings the
            front end fused, each carried by the gyro to the keyframe before it, under the
            GNSS fixes' kernel.
        magnetometer_correlation_s: the heading floor's errors (calibration residue, weak
            disturbances under the front end's thresholds) stay correlated over about this
            long, s: of the readings fused in that span one counts as independent, so the
            floor's variance is multiplied by ``max(1, magnetometer_correlation_s *
            magnetometer_rate_hz)`` (0: the front end's variance).
        nhc: non-holonomic constraint at keyframes where the front end applied it.
        zero_velocity: zero velocity at keyframes the front end found stationary.
        plane: planar motion between consecutive keyframes (ground vehicles).
        plane_tilt_sigma_rad: sigma of the relative roll and pitch, rad.
        plane_height_sigma_m: sigma of the height change in the plane of keyframe i, m.
        window_size: keyframes per sliding window (>= 2).
        window_step: keyframes marginalised per slide (>= 1, < window_size).
        marginal_floor: relative diagonal floor of the marginal Hessian.
        max_iterations: LM iterations per solve.
        relative_tolerance: LM's relative cost-decrease tolerance.
        linear_solver: ``auto``, ``dense`` or ``sparse`` (full batch; windows are dense).
        covariance: compute the per-keyframe marginal covariance blocks (15 x 15).
        output: ``frontend`` (smoothed trajectory at every front-end epoch) or
            ``keyframes`` (keyframe states only).
        noise: front-end noise settings the back end replaces, ``{EskfConfig key: value}``
            for the keys in :data:`NOISE_KEYS` (e.g. a GNSS sigma calibrated on the
            smoother's own residuals where the front end's is inflated for its gating).
        imu_gap_gyro_rw_density: over an IMU gap the true angular rate walks away from the
            held sample as a random walk of this density per body axis ``[x, y, z]``,
            rad/s^2/sqrt(Hz) (see :func:`_gap_noise_scales`); 0 turns it off.
        imu_gap_accel_rw_density: the same for the specific force, ``[x, y, z]``,
            m/s^3/sqrt(Hz).
    """

    keyframe_interval_s: float = 1.0
    keyframe_distance_m: float = 1.0
    keyframe_rotation_rad: float = 0.2
    gnss_kernel: str = "huber"
    gnss_kernel_scale: float = 3.0
    wheel: bool = True
    calibrate_wheels: bool = False
    gnss_velocity: bool = True
    gnss_heading: bool = True
    magnetometer: bool = True
    magnetometer_correlation_s: float = 2.0
    nhc: bool = True
    zero_velocity: bool = True
    plane: bool = False
    plane_tilt_sigma_rad: float = 0.02
    plane_height_sigma_m: float = 0.05
    window_size: int = 40
    window_step: int = 1
    marginal_floor: float = 1e-9
    max_iterations: int = 50
    relative_tolerance: float = 1e-9
    linear_solver: str = "auto"
    covariance: bool = True
    output: str = "frontend"
    noise: dict[str, Any] = dataclasses.field(default_factory=dict)
    imu_gap_gyro_rw_density: list[float] = dataclasses.field(
        default_factory=lambda: [0.005, 0.005, 0.06]
    )
    imu_gap_accel_rw_density: list[float] = dataclasses.field(
        default_factory=lambda: [0.2, 0.2, 0.02]
    )

    def keyframes(self) -> KeyframeConfig:
        """The keyframe thresholds as a :class:`KeyframeConfig`."""
        return KeyframeConfig(
            self.keyframe_interval_s, self.keyframe_distance_m, self.keyframe_rotation_rad
        )

    def kernel(self) -> RobustKernel | None:
        """The GNSS robust kernel, or None."""
        if self.gnss_kernel == "none":
            return None
        return RobustKernel(self.gnss_kernel, float(self.gnss_kernel_scale))

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad key (as ``smoother.KEY``)."""

        def bad(key: str, what: str) -> ValueError:
            return ValueError(
                f"config key 'smoother.{key}' must be {what}, got {getattr(self, key)!r}"
            )

        for key in (
            "keyframe_interval_s",
            "keyframe_distance_m",
            "keyframe_rotation_rad",
            "gnss_kernel_scale",
            "plane_tilt_sigma_rad",
            "plane_height_sigma_m",
            "marginal_floor",
            "relative_tolerance",
        ):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad(key, "a positive number")
            if math.isnan(value) or value <= 0:
                raise bad(key, "a positive number")
        switches = (
            "wheel",
            "calibrate_wheels",
            "gnss_velocity",
            "gnss_heading",
            "magnetometer",
            "nhc",
            "zero_velocity",
            "plane",
        )
        for key in (*switches, "covariance"):
            if not isinstance(getattr(self, key), bool):
                raise bad(key, "true or false")
        value = self.magnetometer_correlation_s
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not 0 <= value < math.inf
        ):
            raise bad("magnetometer_correlation_s", "a non-negative number")
        if self.calibrate_wheels and not self.wheel:
            raise bad("calibrate_wheels", "false when 'smoother.wheel' is false")
        for key, low in (("window_size", 2), ("window_step", 1), ("max_iterations", 1)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise bad(key, f"an integer >= {low}")
        if self.window_step >= self.window_size:
            raise bad("window_step", "smaller than window_size")
        if self.gnss_kernel not in (*KERNELS, "none"):
            raise bad("gnss_kernel", f"one of {(*KERNELS, 'none')}")
        if self.linear_solver not in ("auto", "dense", "sparse"):
            raise bad("linear_solver", "auto, dense or sparse")
        if self.output not in ("frontend", "keyframes"):
            raise bad("output", "frontend or keyframes")
        for key in ("imu_gap_gyro_rw_density", "imu_gap_accel_rw_density"):
            value = getattr(self, key)
            if not (
                isinstance(value, (list, tuple))
                and len(value) == 3
                and all(
                    isinstance(x, (int, float))
                    and not isinstance(x, bool)
                    and math.isfinite(x)
                    and x >= 0
                    for x in value
                )
            ):
                raise bad(key, "three non-negative numbers [x, y, z]")
        if not isinstance(self.noise, dict):
            raise bad("noise", "a mapping of front-end noise keys to values")
        for key in self.noise:
            if key not in NOISE_KEYS:
                raise ValueError(
                    f"config key 'smoother.noise.{key}' is not a noise key; choose from "
                    f"{NOISE_KEYS}"
                )
        try:
            EskfConfig().replace(**self.noise).validate()
        except ValueError as err:
            raise ValueError(f"config section 'smoother.noise': {err}") from err

    def apply_noise(self, cfg: EskfConfig) -> EskfConfig:
        """``cfg`` with the back end's noise replacements applied."""
        return cfg.replace(**self.noise) if self.noise else cfg


def load_smoother_config(path: str | Path | None = None, **overrides: Any) -> SmootherConfig:
    """Read the ``smoother:`` mapping of a YAML run config (absent: defaults), then apply
    ``overrides``.

    Raises:
        DataError: (a ``ValueError``) naming the file, line and key: an unknown key (with the
            closest known ones), a bad value, a YAML problem (:func:`read_yaml`).
        ValueError: a bad key or value in ``overrides``.
    """
    values: dict[str, Any] = {}
    document = None
    if path is not None:
        document = read_yaml(path, "config")
        loaded = document.data
        section = loaded.get("smoother", {}) if isinstance(loaded, dict) else {}
        if section is None:
            section = {}
        if not isinstance(section, dict):
            raise document.error("must be a mapping of keys to values", "smoother")
        values.update(section)
    values.update(overrides)
    known = {f.name for f in dataclasses.fields(SmootherConfig)}
    for key in values:
        if key not in known:
            problem = f"unknown config key 'smoother.{key}'{did_you_mean(key, known)}"
            if document is None or key in overrides:
                raise ValueError(problem)
            raise document.error(problem, "smoother", key)
    try:
        config = SmootherConfig(**values)
        config.validate()
    except (TypeError, ValueError) as err:
        if document is None:
            raise
        bad = named_key(err, values, "smoother.")
        keys = ("smoother",) if bad is None else ("smoother", bad)
        raise document.error(str(err), *keys) from None
    return config


def _slice_pre(pre: Preintegrated, index: torch.Tensor) -> Preintegrated:
    """Intervals ``index`` of increments with leading (1, K - 1)."""
    fields = dataclasses.fields(Preintegrated)
    return Preintegrated(**{f.name: getattr(pre, f.name)[:, index] for f in fields})


@dataclass
class KeyframeGraph:
    """One sequence's measurements organised by keyframe (B = 1, K keyframes).

    Index tensors are int64 keyframe indices (an interval ``i`` joins keyframes i and i+1);
    measurement tensors have a leading batch dim of 1.

    Attributes:
        t: (K,) keyframe times, s.
        epoch: (K,) the keyframes' indices into the front end's epochs.
        initial: (1, K, 21) front-end nav states at the keyframes.
        prior_covariance: (1, 1, 15, 15) front-end covariance at the first keyframe.
        imu: increments (1, K - 1); imu_covariance (1, K - 1, 15, 15).
        gravity: (3,) m/s^2 world.
        gnss_index (G,), gnss_position (1, G, 3) m, gnss_covariance (1, G, 3, 3) m^2,
        gnss_lever_arm (3,) m, gnss_kernel: robust kernel or None (also on the velocities).
        gnss_velocity_index (V,), gnss_velocity (1, V, 3) m/s (0 on an axis not given),
        gnss_velocity_gyro (1, V, 3) rad/s, gnss_velocity_covariance (1, V, 3, 3) (m/s)^2.
        gnss_heading_index (H,), gnss_heading (1, H) rad, gnss_heading_covariance
        (1, H, 1, 1) rad^2, gnss_heading_baseline (3,) m.
        magnetometer_index (M,), magnetometer_field (1, M, 3) corrected field, uT,
        magnetometer_declination (1, M) rad, magnetometer_covariance (1, M, 1, 1) rad^2.
        wheel_index (W,) intervals, wheel_increment (1, W, 3) [m, m, rad],
        wheel_covariance (1, W, 3, 3), wheel_lever_arm (3,) m.
        nhc_index (N,), nhc_gyro (1, N, 3) rad/s, nhc_covariance (1, N, 2, 2),
        nhc_lever_arm (3,) m.
        zupt_index (Z,), zupt_covariance (1, Z, 3, 3).
        plane_covariance: (1, 1, 3, 3) or None (no plane factors).
        wheel_samples: wheel calibration only: per wheel interval the readings it was
            integrated from, left and right rim speeds (1, W, L) m/s and durations
            (1, W, L) s (0 = padding); else None.
        calibration_initial: (1, 1, 3) starting value of ``[k_l, k_r, D]``, or None
            (no calibration variable).
        calibration_prior: its prior mean (1, 1, 3) and covariance (1, 1, 3, 3), or None.
    """

    t: torch.Tensor
    epoch: torch.Tensor
    initial: torch.Tensor
    prior_covariance: torch.Tensor
    imu: Preintegrated
    imu_covariance: torch.Tensor
    gravity: torch.Tensor
    gnss_index: torch.Tensor
    gnss_position: torch.Tensor
    gnss_covariance: torch.Tensor
    gnss_lever_arm: torch.Tensor
    gnss_kernel: RobustKernel | None
    gnss_velocity_index: torch.Tensor
    gnss_velocity: torch.Tensor
    gnss_velocity_gyro: torch.Tensor
    gnss_velocity_covariance: torch.Tensor
    gnss_heading_index: torch.Tensor
    gnss_heading: torch.Tensor
    gnss_heading_covariance: torch.Tensor
    gnss_heading_baseline: torch.Tensor
    magnetometer_index: torch.Tensor
    magnetometer_field: torch.Tensor
    magnetometer_declination: torch.Tensor
    magnetometer_covariance: torch.Tensor
    wheel_index: torch.Tensor
    wheel_increment: torch.Tensor
    wheel_covariance: torch.Tensor
    wheel_lever_arm: torch.Tensor
    nhc_index: torch.Tensor
    nhc_gyro: torch.Tensor
    nhc_covariance: torch.Tensor
    nhc_lever_arm: torch.Tensor
    zupt_index: torch.Tensor
    zupt_covariance: torch.Tensor
    plane_covariance: torch.Tensor | None
    wheel_samples: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    calibration_initial: torch.Tensor | None = None
    calibration_prior: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def size(self) -> int:
        """K, the number of keyframes."""
        return int(self.t.numel())

    @property
    def calibrated(self) -> bool:
        """Whether the graph carries the wheel calibration variable."""
        return self.calibration_initial is not None

    def values(
        self, states: torch.Tensor, calibration: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """Variable values of :meth:`problem`: nav states (1, K', 21) and, when calibrated,
        the calibration (1, 1, 3) (default its starting value)."""
        out = {_GROUP: states}
        if self.calibrated:
            out[_CALIB] = self.calibration_initial if calibration is None else calibration
        return out

    def factors(self, first: int, last: int, unary_last: bool = True) -> list[Factor]:
        """Factor types over keyframes ``[first, last)``, indexed from ``first``.

        Args:
            first, last: keyframe range.
            unary_last: include the unary factors of keyframe ``last - 1`` (False when the
                range is the block being marginalised plus the keyframe that stays).
        Returns:
            the non-empty factor types: every unary factor on the range (see
            ``unary_last``), every binary factor on an interval inside it, and the prior
            when the range starts at keyframe 0.
        """
        stop = last if unary_last else last - 1
        out: list[Factor] = []

        def unary(index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            keep = (index >= first) & (index < stop)
            return keep, index[keep] - first

        def binary(index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            keep = (index >= first) & (index + 1 < last)
            return keep, index[keep] - first, index[keep] + 1 - first

        if first == 0 and stop > 0:
            zero = torch.zeros(1, dtype=torch.long, device=self.t.device)
            out.append(
                F.NavStatePriorFactor(_GROUP, zero, self.initial[:, :1], self.prior_covariance)
            )
            if self.calibration_prior is not None:
                out.append(F.VectorPriorFactor(_CALIB, zero, *self.calibration_prior))
        intervals = torch.arange(self.size - 1, device=self.t.device)
        keep, i, j = binary(intervals)
        if i.numel():
            out.append(
                F.ImuPreintegrationFactor(
                    _GROUP,
                    i,
                    j,
                    _slice_pre(self.imu, intervals[keep]),
                    self.imu_covariance[:, keep],
                    self.gravity,
                )
            )
            if self.plane_covariance is not None:
                cov = self.plane_covariance.expand(1, i.numel(), 3, 3)
                out.append(F.PlaneFactor(_GROUP, i, j, cov, None))
        keep, i, j = binary(self.wheel_index)
        if i.numel() and self.wheel_samples is not None:
            left, right, dt = self.wheel_samples
            out.append(
                F.CalibratedWheelOdometryFactor(
                    _GROUP,
                    i,
                    j,
                    _CALIB,
                    left[:, keep],
                    right[:, keep],
                    dt[:, keep],
                    self.wheel_covariance[:, keep],
                    float(self.calibration_prior[0][0, 0, 2]),
                    self.wheel_lever_arm,
                )
            )
        elif i.numel():
            out.append(
                F.WheelOdometryFactor(
                    _GROUP,
                    i,
                    j,
                    self.wheel_increment[:, keep],
                    self.wheel_covariance[:, keep],
                    self.wheel_lever_arm,
                )
            )
        keep, i = unary(self.gnss_index)
        if i.numel():
            out.append(
                F.GnssFactor(
                    _GROUP,
                    i,
                    self.gnss_position[:, keep],
                    self.gnss_covariance[:, keep],
                    self.gnss_lever_arm,
                    self.gnss_kernel,
                )
            )
        keep, i = unary(self.gnss_velocity_index)
        if i.numel():
            out.append(
                F.GnssVelocityFactor(
                    _GROUP,
                    i,
                    self.gnss_velocity[:, keep],
                    self.gnss_velocity_gyro[:, keep],
                    self.gnss_velocity_covariance[:, keep],
                    self.gnss_lever_arm,
                    self.gnss_kernel,
                )
            )
        keep, i = unary(self.gnss_heading_index)
        if i.numel():
            out.append(
                F.GnssHeadingFactor(
                    _GROUP,
                    i,
                    self.gnss_heading[:, keep],
                    self.gnss_heading_covariance[:, keep],
                    self.gnss_heading_baseline,
                    self.gnss_kernel,
                )
            )
        keep, i = unary(self.magnetometer_index)
        if i.numel():
            out.append(
                F.MagnetometerFactor(
                    _GROUP,
                    i,
                    self.magnetometer_field[:, keep],
                    self.magnetometer_declination[:, keep],
                    self.magnetometer_covariance[:, keep],
                    self.gnss_kernel,
                )
            )
        keep, i = unary(self.nhc_index)
        if i.numel():
            out.append(
                F.NonholonomicFactor(
                    _GROUP,
                    i,
                    self.nhc_gyro[:, keep],
                    self.nhc_covariance[:, keep],
                    self.nhc_lever_arm,
                )
            )
        keep, i = unary(self.zupt_index)
        if i.numel():
            out.append(F.ZeroVelocityFactor(_GROUP, i, self.zupt_covariance[:, keep], None))
        return out

    def problem(
        self,
        values: torch.Tensor,
        first: int = 0,
        last: int | None = None,
        calibration: torch.Tensor | None = None,
    ) -> Problem:
        """The least-squares problem over keyframes ``[first, last)`` (default: all) with
        values (1, last - first, 21), and when calibrated the calibration variable (group
        ``"wheel_calibration"``, (1, 1, 3), default its starting value) after them."""
        last = self.size if last is None else last
        variables: dict[str, tuple] = {_GROUP: (NAV_STATE, values)}
        if self.calibrated:
            variables[_CALIB] = (WHEEL_CALIBRATION, self.values(values, calibration)[_CALIB])
        return Problem(variables, self.factors(first, last))


def _cut_channels(
    times: torch.Tensor, channels: torch.Tensor, keyframe_times: torch.Tensor
) -> ImuIntervals:
    """Cut a zero-order-hold stream of up to 6 channels (T, C) at keyframe times with
    :func:`~msf_torch.backend.preintegration.cut_imu`; channels come back in ``gyro``
    (first three) and ``accel`` (next three), (K - 1, L, 3) each."""
    padded = torch.zeros(channels.shape[0], 6, dtype=channels.dtype, device=channels.device)
    padded[:, : channels.shape[1]] = channels
    return cut_imu(times, padded[:, 0:3], padded[:, 3:6], keyframe_times)


def _wheel_intervals(
    seq: Sequence,
    frontend: EskfResult,
    cfg: EskfConfig,
    keyframe_times: torch.Tensor,
    calibrate: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...] | None]:
    """Wheel increments between keyframes: (W,) interval index, (1, W, 3), (1, W, 3, 3),
    and with ``calibrate`` the readings of each interval (left, right rim speeds and
    durations, (1, W, L) each; the yaw row is then kept), else None."""
    wheel = seq.wheel
    keep = wheel.mask[0]
    stamp = wheel.t[0, keep]
    dtype, device = stamp.dtype, stamp.device
    empty = (
        torch.zeros(0, dtype=torch.long, device=device),
        torch.zeros(1, 0, 3, dtype=dtype, device=device),
        torch.zeros(1, 0, 3, 3, dtype=dtype, device=device),
    )
    if stamp.numel() < 2:
        return (*empty, None)
    epoch_t = frontend.t[0, frontend.mask[0]]
    epoch_slip = frontend.slip_factor[0, frontend.mask[0]]
    at = (torch.searchsorted(epoch_t, stamp, right=True) - 1).clamp(0, epoch_t.numel() - 1)
    slip = epoch_slip[at]
    # each reading holds over the interval before its stamp (mean rim speed over it)
    start = torch.cat((stamp[:1] - (stamp[1] - stamp[0]), stamp[:-1]))
    ones = torch.ones_like(stamp)
    channels = torch.stack((wheel.left_speed[0, keep], wheel.right_speed[0, keep], slip, ones), -1)
    lo = torch.minimum(start[:1], keyframe_times[:1])
    hi = torch.maximum(stamp[-1:], keyframe_times[-1:])
    times = torch.cat((lo, start, stamp[-1:], hi))
    filler = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=dtype, device=device)
    channels = torch.cat((filler, channels, filler, filler))
    # equal times: cut_imu keeps zero-length pieces out; the stable sort keeps order
    cut = _cut_channels(times, channels, keyframe_times)
    covered = cut.accel[..., 0]
    dt = cut.dt * covered
    span = keyframe_times[1:] - keyframe_times[:-1]
    usable = dt.sum(-1) >= 0.9 * span
    index = torch.nonzero(usable).squeeze(-1)
    if index.numel() == 0:
        return (*empty, None)
    increment, covariance = preintegrate_wheel(
        cut.gyro[index, :, 0],
        cut.gyro[index, :, 1],
        dt[index],
        cfg.wheel_track_m,
        math.sqrt(2.0) * cfg.wheel_speed_sigma_mps,
        cut.gyro[index, :, 2].clamp(1e-3, 1.0),
    )
    if not (cfg.wheel_yaw_rate_update or calibrate):
        covariance = covariance.clone()
        covariance[..., 2, :] = 0.0
        covariance[..., :, 2] = 0.0
        covariance[..., 2, 2] = _YAW_OFF_VARIANCE
    samples = None
    if calibrate:
        # a piece's two rim-speed noises drive three rows: an interval of one piece has a
        # singular covariance; the IMU's 1e-6 relative diagonal floor keeps it definite
        floor = 1e-6 * torch.diagonal(covariance, dim1=-2, dim2=-1)
        covariance = covariance + torch.diag_embed(floor)
        samples = (cut.gyro[None, index, :, 0], cut.gyro[None, index, :, 1], dt[None, index])
    return index, increment[None], covariance[None], samples


def _gap_noise_scales(
    length: torch.Tensor, cfg: EskfConfig, smoother: SmootherConfig
) -> torch.Tensor:
    """Per-sample, per-axis variance multipliers (T, 6) of the gyro's (columns 0-2) and the
    accelerometer's (3-5) white noise: 1 for a measured sample (``length`` 0), and for one
    held over a gap of ``T = length`` s

        imu_gap_noise_scale + (q / n)^2 T^2 / 3,

    ``n`` the sensor's noise density, ``q`` the smoother's ``imu_gap_gyro_rw_density`` /
    ``imu_gap_accel_rw_density`` of that body axis. Over a gap the true signal leaves the
    held sample as a random walk, error ``e(tau)`` of variance ``q^2 tau``; its integral over
    the gap (the angle or velocity error) has variance ``q^2 T^3 / 3``, growing with the
    gap far faster than white noise (``~T``). That error is one constant-like offset, shared
    by every keyframe interval inside the gap, while the IMU factors are independent: the
    gap is given white noise of density ``q^2 T^2 / 3`` instead, whose integral over the
    whole gap has the same variance whatever keyframes fall inside it."""
    dtype, device = length.dtype, length.device
    walk = torch.tensor(
        [*smoother.imu_gap_gyro_rw_density, *smoother.imu_gap_accel_rw_density],
        dtype=dtype,
        device=device,
    )
    density = torch.tensor(
        [cfg.gyro_noise_density] * 3 + [cfg.accel_noise_density] * 3, dtype=dtype, device=device
    )
    held = cfg.imu_gap_noise_scale + gap_walk_scale(length, walk, density)
    return torch.where(length[:, None] > 0, held, 1.0).to(dtype)


def build_graph(
    seq: Sequence,
    frontend: EskfResult,
    cfg: EskfConfig,
    smoother: SmootherConfig | None = None,
) -> KeyframeGraph:
    """Select keyframes and gather every measurement between and at them (B = 1).

    Args:
        seq: the sequence the front end ran on (outage fixes already withheld).
        frontend: :func:`~msf_torch.frontend.eskf.run_eskf`'s result on ``seq``.
        cfg: the front end's settings (noise, lever arms, gravity, gap handling).
        smoother: smoother settings; default :class:`SmootherConfig()`.
    Returns:
        :class:`KeyframeGraph`.
    """
    smoother = smoother or SmootherConfig()
    smoother.validate()
    cfg = smoother.apply_noise(cfg)
    seq, _ = sanitize_sequence(seq)  # the samples the front end used (no NaN fix, heading)
    if seq.batch_size != 1 or frontend.t.shape[0] != 1:
        raise ValueError(f"the smoothers take one sequence (B = 1), got B = {seq.batch_size}")
    dtype, device = frontend.t.dtype, frontend.t.device
    force = frontend.present["gnss"] & frontend.mask
    for stream in ("gnss_velocity", "gnss_heading"):
        if getattr(smoother, stream) and stream in frontend.present:
            force = force | (frontend.present[stream] & frontend.mask)
    keyframes = select_keyframes(
        frontend.t, frontend.position, frontend.rotation, frontend.mask, smoother.keyframes(), force
    )
    epoch = keyframes.index[0]
    t = keyframes.t[0]
    if t.numel() < 2:
        raise ValueError(f"sequence '{seq.names[0]}': fewer than two keyframes to smooth")
    initial = pack_nav_state(
        frontend.position[:, epoch],
        frontend.velocity[:, epoch],
        frontend.rotation[:, epoch],
        frontend.gyro_bias[:, epoch],
        frontend.accel_bias[:, epoch],
    )
    prior_covariance = frontend.covariance[:, epoch[:1]]

    # IMU between keyframes, with the front end's gap variance multiplier
    imu_keep = seq.imu.mask[0]
    imu_t = seq.imu.t[0, imu_keep]
    gyro, accel = seq.imu.gyro[0, imu_keep], seq.imu.accel[0, imu_keep]
    spacing = torch.cat((imu_t[1:] - imu_t[:-1], imu_t.new_zeros(1)))
    filled = interpolated_imu_samples(imu_t, gyro, accel, cfg.imu_interpolated_min_samples)
    length = gap_lengths(
        imu_t.detach().cpu().numpy(), spacing.detach().cpu().numpy(), filled, cfg.imu_gap_s
    )
    gap_length = torch.as_tensor(length, dtype=dtype, device=imu_t.device)
    scales = _gap_noise_scales(gap_length, cfg, smoother)
    cut = cut_imu(imu_t, gyro, accel, t)
    noise_scale = cut_imu(imu_t, scales[:, :3], scales[:, 3:], t)
    intervals = ImuIntervals(cut.gyro[None], cut.accel[None], cut.dt[None])
    pre = preintegrate_imu(
        intervals,
        frontend.gyro_bias[:, epoch[:-1]],
        frontend.accel_bias[:, epoch[:-1]],
        noise_scale=noise_scale.gyro[None],
        accel_noise_scale=noise_scale.accel[None],
    )
    noise = EskfNoise.from_config(cfg, dtype, device)
    imu_cov = imu_covariance(pre, noise.imu)
    # a piece's accelerometer noise drives dp and dv along one direction: an interval of one
    # or two pieces has a (nearly) singular covariance; a 1e-6 relative diagonal floor keeps
    # it definite without changing longer intervals' information measurably. An interval
    # shorter than SHORT_INTERVAL_PERIODS IMU periods (a fix just after the first sample or
    # just after a keyframe) gets 1e-2: with 1e-6 its information leaves the Gauss-Newton
    # matrix singular in float64, and LM cannot take a step
    period = spacing[:-1].median() if imu_t.numel() > 1 else imu_t.new_ones(())
    short = pre.delta_t[0] < SHORT_INTERVAL_PERIODS * period
    floor = torch.where(short, 1e-2, 1e-6).to(dtype)[None, :, None]
    imu_cov = imu_cov + torch.diag_embed(floor * torch.diagonal(imu_cov, dim1=-2, dim2=-1))

    # GNSS: fixes and velocities at keyframe times (every epoch of one is a keyframe)
    tol = 2.0 * cfg.time_tolerance_s
    gnss_index, gnss_position, gnss_sigma = _at_keyframes(
        seq.gnss, "position", t, tol, cfg.gnss_sigma_m
    )
    gnss_covariance = torch.diag_embed(gnss_sigma**2)
    velocity_stream = seq.gnss_velocity if smoother.gnss_velocity else None
    gnss_velocity_index, gnss_velocity, velocity_sigma = _at_keyframes(
        velocity_stream, "velocity", t, tol, cfg.gnss_velocity_sigma_mps
    )
    unmeasured = torch.isnan(gnss_velocity)  # the up axis of a horizontal-only receiver
    gnss_velocity = torch.where(unmeasured, 0.0, gnss_velocity)
    velocity_sigma = torch.where(unmeasured, UNMEASURED_SIGMA, velocity_sigma)
    gnss_velocity_covariance = torch.diag_embed(velocity_sigma**2)
    heading_stream = seq.gnss_heading if smoother.gnss_heading else None
    gnss_heading_index, gnss_heading, heading_sigma = _at_keyframes(
        heading_stream, "heading", t, tol, [cfg.gnss_heading_sigma_rad], vector=False
    )
    gnss_heading_covariance = (heading_sigma**2)[..., None, None]
    magnetometer = _magnetometer_at_keyframes(
        seq if smoother.magnetometer else None,
        frontend,
        cfg,
        epoch,
        (imu_t, gyro, accel),
        tol,
        smoother.magnetometer_correlation_s,
    )

    # wheels
    wheel_index = torch.zeros(0, dtype=torch.long, device=device)
    wheel_increment = torch.zeros(1, 0, 3, dtype=dtype, device=device)
    wheel_covariance = torch.zeros(1, 0, 3, 3, dtype=dtype, device=device)
    wheel_samples = None
    if smoother.wheel and seq.wheel is not None and bool(seq.wheel.mask.any()):
        wheel_index, wheel_increment, wheel_covariance, wheel_samples = _wheel_intervals(
            seq, frontend, cfg, t, smoother.calibrate_wheels
        )
    calibration_initial, calibration_prior = None, None
    if smoother.calibrate_wheels and not set(WHEEL_STATES) <= set(frontend.calibration_names):
        raise ValueError(
            "config key 'smoother.calibrate_wheels' needs the front end's 'calibrate_wheels' "
            "as well: without it the front end's slip detector takes miscalibrated wheels "
            "for slipping ones and its slip factors switch them off"
        )
    if smoother.calibrate_wheels:
        calibration_initial, calibration_prior = _wheel_calibration_prior(frontend, cfg, dtype)

    # pseudo-measurements where the front end applied them
    nhc_index = torch.zeros(0, dtype=torch.long, device=device)
    if smoother.nhc:
        nhc_index = torch.nonzero(frontend.present["nhc"][0, epoch]).squeeze(-1)
    held = (torch.searchsorted(imu_t, t + cfg.time_tolerance_s, right=True) - 1).clamp_min(0)
    nhc_gyro = gyro[held][nhc_index][None]
    heading_baseline = _heading_baseline(frontend, cfg, dtype, device)
    gnss_heading = _heading_at_keyframes(
        frontend, epoch, gnss_heading_index, gnss_heading, gyro[held], heading_baseline
    )
    gnss_velocity_gyro = gyro[held][gnss_velocity_index][None]
    nhc_covariance = (cfg.nhc_sigma_mps**2 * torch.eye(2, dtype=dtype, device=device)).expand(
        1, nhc_index.numel(), 2, 2
    )
    zupt_index = torch.zeros(0, dtype=torch.long, device=device)
    if smoother.zero_velocity:
        zupt_index = torch.nonzero(frontend.present["zupt"][0, epoch]).squeeze(-1)
    zupt_covariance = (cfg.zupt_sigma_mps**2 * torch.eye(3, dtype=dtype, device=device)).expand(
        1, zupt_index.numel(), 3, 3
    )
    plane_covariance = None
    if smoother.plane:
        tilt, height = smoother.plane_tilt_sigma_rad, smoother.plane_height_sigma_m
        plane_covariance = torch.diag(
            torch.tensor([tilt**2, tilt**2, height**2], dtype=dtype, device=device)
        )
        plane_covariance = plane_covariance[None, None]

    def arm(values: list[float]) -> torch.Tensor:
        return torch.tensor(values, dtype=dtype, device=device)

    return KeyframeGraph(
        t=t,
        epoch=epoch,
        initial=initial,
        prior_covariance=prior_covariance,
        imu=pre,
        imu_covariance=imu_cov,
        gravity=gravity_world(cfg.gravity_mps2, dtype, device),
        gnss_index=gnss_index,
        gnss_position=gnss_position,
        gnss_covariance=gnss_covariance,
        gnss_lever_arm=arm(cfg.gnss_lever_arm_m),
        gnss_kernel=smoother.kernel(),
        gnss_velocity_index=gnss_velocity_index,
        gnss_velocity=gnss_velocity,
        gnss_velocity_gyro=gnss_velocity_gyro,
        gnss_velocity_covariance=gnss_velocity_covariance,
        gnss_heading_index=gnss_heading_index,
        gnss_heading=gnss_heading,
        gnss_heading_covariance=gnss_heading_covariance,
        gnss_heading_baseline=heading_baseline,
        magnetometer_index=magnetometer[0],
        magnetometer_field=magnetometer[1],
        magnetometer_declination=magnetometer[2],
        magnetometer_covariance=magnetometer[3],
        wheel_index=wheel_index,
        wheel_increment=wheel_increment,
        wheel_covariance=wheel_covariance,
        wheel_lever_arm=arm(cfg.wheel_lever_arm_m),
        nhc_index=nhc_index,
        nhc_gyro=nhc_gyro,
        nhc_covariance=nhc_covariance,
        nhc_lever_arm=arm(cfg.nhc_lever_arm_m),
        zupt_index=zupt_index,
        zupt_covariance=zupt_covariance,
        plane_covariance=plane_covariance,
        wheel_samples=wheel_samples,
        calibration_initial=calibration_initial,
        calibration_prior=calibration_prior,
    )


def _at_keyframes(
    stream,
    field: str,
    t: torch.Tensor,
    tol: float,
    default_sigma: list[float],
    vector: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A GNSS stream's samples at keyframe times ``t`` (K,) s (within ``tol``): keyframe
    indices (G,), the ``field`` values (1, G, 3) and sigmas (1, G, 3) ((1, G) each for a
    scalar stream, ``vector=False``), a sigma that is not finite and positive replaced by
    ``default_sigma`` (as the front end reads them)."""
    dtype, device = t.dtype, t.device
    if stream is None or not bool(stream.mask.any()):
        empty = torch.zeros(1, 0, *((3,) if vector else ()), dtype=dtype, device=device)
        return torch.zeros(0, dtype=torch.long, device=device), empty, empty.clone()
    keep = stream.mask[0]
    times = stream.t[0, keep]
    nearest = torch.searchsorted(t, times).clamp(1, t.numel() - 1)
    left_closer = (times - t[nearest - 1]).abs() <= (t[nearest] - times).abs()
    nearest = torch.where(left_closer, nearest - 1, nearest)
    matched = (t[nearest] - times).abs() <= tol
    values = getattr(stream, field)[:, keep][:, matched]
    sigma = stream.sigma[:, keep][:, matched]
    default = torch.tensor(default_sigma, dtype=dtype, device=device)
    sigma = torch.where(torch.isfinite(sigma) & (sigma > 0), sigma, default)
    return nearest[matched], values, sigma


def _magnetometer_at_keyframes(
    seq: Sequence | None,
    frontend: EskfResult,
    cfg: EskfConfig,
    epoch: torch.Tensor,
    imu: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    tol: float,
    correlation_s: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The magnetometer readings the front end fused (``accepted["magnetometer"]``), each
    carried to the keyframe at or before it (front-end epochs ``epoch`` (K,)).

    A reading at ``t_r`` after keyframe ``k`` sees the body turned by ``dR`` (the raw gyro
    less the front end's gyro bias at ``k``, zero-order hold, over ``[t_k, t_r]``), so the
    field in keyframe ``k``'s body frame is ``dR W (m - b)`` and its azimuth through ``R_k``
    is the reading's heading. The carried field is fixed: a gyro bias error ``e`` turns it
    by ``e (t_r - t_k)`` (1e-3 rad/s over a 1-s keyframe interval: 1e-3 rad against the
    0.03-rad heading floor), and the keyframe count stays that of the other sensors.

    Args:
        seq: the sanitised sequence, or None (the factor switched off: none).
        frontend: the front end's result on it.
        cfg: hard and soft iron, noise, floor, declination.
        epoch: (K,) the keyframes' front-end epochs.
        imu: the IMU samples in use: times (T,) s, gyro (T, 3) rad/s, accel (T, 3) m/s^2.
        tol: time tolerance matching an epoch to its reading, s.
        correlation_s: ``SmootherConfig.magnetometer_correlation_s``, s.

    Returns:
        keyframe indices (M,), carried fields (1, M, 3) uT, declinations (1, M) rad
        (``magnetometer_declination_rad``, or the front end's final estimate when it
        calibrated it) and heading variances (1, M, 1, 1) rad^2 at the front end's attitude
        at the reading.
    """
    dtype, device = frontend.t.dtype, frontend.t.device
    index = torch.zeros(0, dtype=torch.long, device=device)
    stream = None if seq is None else seq.magnetometer
    fused = index
    if stream is not None and bool(stream.mask.any()):
        fused = torch.nonzero(frontend.accepted["magnetometer"][0] & frontend.mask[0])
        fused = fused.squeeze(-1)
    t = frontend.t[0, epoch]
    target = frontend.t[0, fused]
    inside = (target >= t[0]) & (target <= t[-1])
    fused, target = fused[inside], target[inside]
    if fused.numel():
        keep = stream.mask[0]
        times = stream.t[0, keep].to(dtype)
        right = torch.searchsorted(times, target).clamp(max=times.numel() - 1)
        left = (right - 1).clamp_min(0)
        nearest = torch.where(
            (target - times[left]).abs() <= (times[right] - target).abs(), left, right
        )
        matched = (times[nearest] - target).abs() <= tol
        fused, nearest, target = fused[matched], nearest[matched], target[matched]
    if fused.numel() == 0:
        empty = torch.zeros(1, 0, dtype=dtype, device=device)
        return index, empty[..., None].expand(1, 0, 3), empty, empty[..., None, None]
    field, sigma = corrected_magnetometer(
        stream.field[:, keep][:, nearest].to(dtype),
        stream.sigma[:, keep][:, nearest].to(dtype),
        cfg,
    )
    # the floor's errors stay correlated over about correlation_s: of the readings fused in
    # that span, one counts as independent
    floor = cfg.magnetometer_heading_floor_rad * math.sqrt(
        max(1.0, correlation_s * cfg.magnetometer_rate_hz)
    )
    variance = magnetometer_heading_variance(frontend.rotation[:, fused], field, sigma, floor)
    # the gyro's turn from the keyframe before each reading: cut the IMU at the keyframes
    # and the readings together, then multiply each reading's pieces since its keyframe
    count = t.numel()
    grid, order = torch.sort(torch.cat((t, target)), stable=True)
    position = torch.empty_like(order)
    position[order] = torch.arange(order.numel(), device=device)
    anchor = torch.cummax(
        torch.where(order < count, torch.arange(order.numel(), device=device), 0), 0
    ).values
    cut = cut_imu(*imu, grid)
    index = torch.searchsorted(t, target, right=True) - 1
    bias = frontend.gyro_bias[0, epoch][order[anchor[:-1]]]
    step = preintegrate_imu(
        ImuIntervals(cut.gyro[None], cut.accel[None], cut.dt[None]),
        bias[None],
        torch.zeros_like(bias)[None],
        covariance="closed_form",
    ).delta_rotation[0]
    at = position[count:]
    turn = so3.identity(dtype, device).expand(at.numel(), 3, 3)
    rank, last = at - anchor[at], step.shape[0] - 1
    for r in range(int(rank.max())):
        turn = torch.where(
            (r < rank)[:, None, None], turn @ step[(anchor[at] + r).clamp(max=last)], turn
        )
    field = (turn @ field[0, :, :, None])[None, ..., 0]
    declination = torch.full_like(variance, cfg.magnetometer_declination_rad)
    name = "declination_rad:magnetometer"
    if frontend.calibration is not None and name in frontend.calibration_names:
        estimate = frontend.calibration[0, -1, frontend.calibration_names.index(name)]
        declination = estimate.to(dtype).expand_as(variance)
    return index, field, declination, variance[..., None, None]


def _heading_baseline(
    frontend: EskfResult, cfg: EskfConfig, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """The dual-antenna baseline (3,) m, body frame: ``cfg.gnss_heading_baseline_m``, turned
    about body z by the front end's final heading-offset estimate when it calibrated one
    (``calibrate_gnss_heading_offset``; the smoother holds it fixed)."""
    baseline = torch.tensor(cfg.gnss_heading_baseline_m, dtype=dtype, device=device)
    name = "heading_offset_rad:gnss_heading"
    if frontend.calibration is None or name not in frontend.calibration_names:
        return baseline
    offset = frontend.calibration[0, -1, frontend.calibration_names.index(name)].to(dtype)
    turn = so3.exp(torch.stack((torch.zeros_like(offset), torch.zeros_like(offset), offset)))
    return turn @ baseline


def _heading_at_keyframes(
    frontend: EskfResult,
    epoch: torch.Tensor,
    index: torch.Tensor,
    heading: torch.Tensor,
    gyro: torch.Tensor,
    baseline: torch.Tensor,
) -> torch.Tensor:
    """Headings (1, H) rad at their keyframes' times: as measured, or, when the front end
    calibrated the headings' time offset ``t_d`` (``calibrate_time_offsets:
    [gnss_heading]``), less ``t_d`` times the azimuth rate of the baseline at the keyframe
    (the front end's attitude and gyro bias there, the raw gyro ``gyro`` (K, 3) held at each
    keyframe), as the front end predicts them (``sensors.calibration.shifted_heading_residual``)."""
    name = "time_offset_s:gnss_heading"
    if frontend.calibration is None or name not in frontend.calibration_names:
        return heading
    time_offset = frontend.calibration[0, -1, frontend.calibration_names.index(name)]
    keyframe = epoch[index]
    zeros = torch.zeros(index.numel(), dtype=heading.dtype, device=heading.device)
    *_, azimuth_rate = shifted_heading_residual(
        frontend.rotation[0, keyframe],
        gyro[index],
        frontend.gyro_bias[0, keyframe],
        baseline,
        zeros,
        zeros,
        heading[0],
    )
    return heading - time_offset.to(heading.dtype) * azimuth_rate[:, 0, 0][None]


def _wheel_calibration_prior(
    frontend: EskfResult, cfg: EskfConfig, dtype: torch.dtype
) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """Starting value (1, 1, 3) of ``[k_l, k_r, D]`` and its prior mean (1, 1, 3) and
    covariance (1, 1, 3, 3): the front end's initial calibration and sigmas; the start is
    the front end's final estimate when it calibrated its wheels, else the prior mean."""
    device = frontend.t.device
    mean = torch.tensor(
        [*map(float, cfg.calibration_wheel_radius_ratio), float(cfg.wheel_track_m)],
        dtype=dtype,
        device=device,
    )
    sigma = torch.tensor(
        [cfg.calibration_wheel_radius_sigma] * 2 + [cfg.calibration_wheel_track_sigma_m],
        dtype=dtype,
        device=device,
    )
    start = mean
    names = frontend.calibration_names
    if frontend.calibration is not None and all(name in names for name in WHEEL_STATES):
        columns = [names.index(name) for name in WHEEL_STATES]
        start = frontend.calibration[0, -1, columns].to(dtype)
    return start[None, None].clone(), (mean[None, None], torch.diag(sigma**2)[None, None])


def chain_covariance(problem: Problem, values: dict[str, torch.Tensor]) -> torch.Tensor:
    """Marginal covariances (B, K, D, D) of the K variables of a chain problem.

    Every factor must join one variable or two consecutive ones (``j = i + 1``), so the
    Gauss-Newton Hessian ``J^T J`` at ``values`` is block tridiagonal; its inverse's
    diagonal blocks follow from a forward pass of Schur complements
    ``S_k = H_kk - H_{k-1,k}^T S_{k-1}^-1 H_{k-1,k}`` and a backward pass
    ``Sigma_k = S_k^-1 + G_k Sigma_{k+1} G_k^T``, ``G_k = S_k^-1 H_{k,k+1}``, in O(K).
    The problem must have one variable group and no fixed variables.

    Raises:
        ValueError: a factor joins non-consecutive variables or more than two.
    """
    (name,) = problem.values.keys()
    value = values[name]
    batch, count = value.shape[:2]
    dim = problem.kinds[name].tangent_dim
    diag = value.new_zeros(batch, count, dim, dim)
    upper = value.new_zeros(batch, max(count - 1, 0), dim, dim)
    for factor, (_, jacs, _) in zip(problem.factors, problem.whitened(values), strict=True):
        index = [idx for _, idx in factor.slots]
        if len(index) == 1:
            diag = diag.index_add(1, index[0], jacs[0].mT @ jacs[0])
            continue
        if len(index) != 2:
            raise ValueError("chain_covariance: a factor joins more than two variables")
        first, second = index
        if not bool((second == first + 1).all()):
            raise ValueError("chain_covariance: a factor joins non-consecutive variables")
        diag = diag.index_add(1, first, jacs[0].mT @ jacs[0])
        diag = diag.index_add(1, second, jacs[1].mT @ jacs[1])
        upper = upper.index_add(1, first, jacs[0].mT @ jacs[1])
    schur = [diag[:, 0]]
    for k in range(1, count):
        link = upper[:, k - 1]
        schur.append(diag[:, k] - link.mT @ torch.linalg.solve(schur[-1], link))
    inverse = [torch.linalg.inv(s) for s in schur]
    covariance = [inverse[-1]]
    for k in range(count - 2, -1, -1):
        gain = inverse[k] @ upper[:, k]
        covariance.append(inverse[k] + gain @ covariance[-1] @ gain.mT)
    return torch.stack(covariance[::-1], 1)


def bordered_chain_covariance(
    problem: Problem, values: dict[str, torch.Tensor], border: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Marginal covariances of a chain of K variables bordered by one global variable.

    The chain group's factors join one variable or two consecutive ones, and any factor may
    also join the single variable of group ``border`` (e.g. a run's wheel calibration), so
    the Gauss-Newton Hessian is ``[[A, B], [B^T, C]]`` with ``A`` block tridiagonal. With
    ``X = A^-1 B`` (block forward / back substitution) the border's covariance is
    ``Sigma_c = (C - B^T X)^-1`` and the chain's diagonal blocks are
    ``(A^-1)_kk + X_k Sigma_c X_k^T`` (``(A^-1)_kk`` as in :func:`chain_covariance`); O(K).
    The problem must have the chain group first, ``border`` second and nothing fixed.

    Returns:
        chain covariances (B, K, D, D) and the border's covariance (B, M, M).
    Raises:
        ValueError: a factor joins non-consecutive chain variables or more than two.
    """
    chain_name = next(name for name in problem.values if name != border)
    value = values[chain_name]
    batch, count = value.shape[:2]
    dim = problem.kinds[chain_name].tangent_dim
    width = problem.kinds[border].tangent_dim
    diag = value.new_zeros(batch, count, dim, dim)
    upper = value.new_zeros(batch, max(count - 1, 0), dim, dim)
    cross = value.new_zeros(batch, count, dim, width)
    corner = value.new_zeros(batch, width, width)
    for factor, (_, jacs, _) in zip(problem.factors, problem.whitened(values), strict=True):
        slots = list(zip(factor.slots, jacs, strict=True))
        chain = [(idx, jac) for (group, idx), jac in slots if group != border]
        rim = [jac for (group, _), jac in slots if group == border]
        if len(chain) > 2 or len(rim) > 1:
            raise ValueError("bordered_chain_covariance: a factor joins more than two variables")
        if len(chain) == 2 and not bool((chain[1][0] == chain[0][0] + 1).all()):
            raise ValueError("bordered_chain_covariance: a factor joins non-consecutive variables")
        for idx, jac in chain:
            diag = diag.index_add(1, idx, jac.mT @ jac)
            if rim:
                cross = cross.index_add(1, idx, jac.mT @ rim[0])
        if len(chain) == 2:
            upper = upper.index_add(1, chain[0][0], chain[0][1].mT @ chain[1][1])
        if rim:
            corner = corner + (rim[0].mT @ rim[0]).sum(1)
    inverse = [torch.linalg.inv(diag[:, 0])]
    forward = [cross[:, 0]]
    for k in range(1, count):
        link = upper[:, k - 1]
        schur = diag[:, k] - link.mT @ inverse[-1] @ link
        inverse.append(torch.linalg.inv(schur))
        forward.append(cross[:, k] - link.mT @ inverse[-2] @ forward[-1])
    solved = [inverse[-1] @ forward[-1]]  # X = A^-1 B, from the last block back
    covariance = [inverse[-1]]
    for k in range(count - 2, -1, -1):
        gain = inverse[k] @ upper[:, k]
        solved.append(inverse[k] @ forward[k] - gain @ solved[-1])
        covariance.append(inverse[k] + gain @ covariance[-1] @ gain.mT)
    solved_x = torch.stack(solved[::-1], 1)  # (B, K, D, M)
    border_cov = torch.linalg.inv(corner - (cross.mT @ solved_x).sum(1))
    chain_cov = torch.stack(covariance[::-1], 1) + solved_x @ border_cov[:, None] @ solved_x.mT
    return chain_cov, border_cov


@dataclass
class SmootherResult:
    """Outcome of a smoother on one sequence (B = 1, K keyframes).

    Attributes:
        mode: ``"full"`` or ``"window"``.
        t: (1, K) keyframe times, s.
        states: (1, K, 21) smoothed nav states
            (:func:`~msf_torch.backend.variables.pack_nav_state`).
        covariance: (1, K, 15, 15) marginal covariances of the error state
            ``[dp, dv, dtheta (body), db_g, db_a]`` (full batch: smoothed; window:
            conditioned on the window a keyframe left from), or None (``covariance`` off).
        lm: the LM results (one for the full batch, one per window).
        initial_cost, cost: the full problem's cost at the front end's keyframe states and
            at the smoothed states (the same yardstick for both modes).
        wall_s: seconds for graph building and solving.
        output: the smoothed trajectory (keyframes or front-end epochs, per ``output``).
        output_motion: velocity, gyro bias and covariance at ``output``'s epochs
            (:func:`interpolate_imu`).
        calibration_names: the calibration variable's entries (``calibrate_wheels``:
            ``frontend.calibration.WHEEL_STATES``), or ().
        calibration: (1, 3) its estimate ``[k_l, k_r, D]``, or None.
        calibration_sigma: (1, 3) marginal 1-sigma from the solved information matrix, or
            None (also when ``covariance`` is off).
    """

    mode: str
    t: torch.Tensor
    states: torch.Tensor
    covariance: torch.Tensor | None
    lm: list[LMResult]
    initial_cost: float
    cost: float
    wall_s: float
    output: Trajectory
    output_motion: OutputMotion
    calibration_names: tuple[str, ...] = ()
    calibration: torch.Tensor | None = None
    calibration_sigma: torch.Tensor | None = None

    def trajectory(self) -> Trajectory:
        """The smoothed keyframe poses as a :class:`Trajectory` (1, K)."""
        position, _, rotation, _, _ = unpack_nav_state(self.states)
        return Trajectory(
            t=self.t,
            position=position,
            quaternion=matrix_to_quat(rotation),
            mask=torch.ones_like(self.t, dtype=torch.bool),
        )

    def summary(self) -> dict[str, Any]:
        """Plain-number figures: mode, keyframes, solves, iterations, costs, status."""
        iterations = [int(r.iterations.sum()) for r in self.lm]
        status = sorted({s for r in self.lm for s in r.status})
        out: dict[str, Any] = {
            "mode": self.mode,
            "keyframes": int(self.t.shape[1]),
            "solves": len(self.lm),
            "iterations": sum(iterations),
            "max_iterations_per_solve": max(iterations),
            "initial_cost": self.initial_cost,
            "cost": self.cost,
            "converged": all(bool(r.converged.all()) for r in self.lm),
            "status": status,
            "wall_s": self.wall_s,
            "output_poses": int(self.output.mask.sum()),
        }
        if self.calibration is not None:
            sigma = self.calibration_sigma
            out["calibration"] = {
                name: {
                    "estimate": float(self.calibration[0, k]),
                    "sigma": None if sigma is None else float(sigma[0, k]),
                }
                for k, name in enumerate(self.calibration_names)
            }
        return out


def _lm_config(smoother: SmootherConfig, solver: str) -> LMConfig:
    """LM settings of the smoothers: Levenberg's identity damping from 1e-9 (nearly
    Gauss-Newton). Marquardt's ``diag(H)`` scaling would tie the damping to the bias rows,
    whose random-walk information (1e10 and more) dwarfs the curvature of the weakly
    observed directions (yaw, biases through the IMU) and slows the first steps tenfold."""
    return LMConfig(
        max_iterations=smoother.max_iterations,
        relative_tolerance=smoother.relative_tolerance,
        linear_solver=solver,
        damping="identity",
        initial_damping=1e-9,
    )


def smooth_full(
    graph: KeyframeGraph, smoother: SmootherConfig | None = None
) -> tuple[torch.Tensor, torch.Tensor | None, list[LMResult]]:
    """Full-batch smoothing of every keyframe in one LM solve (a calibrated graph's
    calibration estimate comes from :func:`smooth_full_calibrated`).

    Returns:
        states (1, K, 21), marginal covariances (1, K, 15, 15) or None, ``[LMResult]``.
    """
    smoother = smoother or SmootherConfig()
    states, covariance, results, _, _ = smooth_full_calibrated(graph, smoother)
    return states, covariance, results


def smooth_full_calibrated(
    graph: KeyframeGraph, smoother: SmootherConfig | None = None
) -> tuple[
    torch.Tensor,
    torch.Tensor | None,
    list[LMResult],
    torch.Tensor | None,
    torch.Tensor | None,
]:
    """:func:`smooth_full` that also returns the calibration variable (calibrated graphs).

    Returns:
        states (1, K, 21), marginal covariances (1, K, 15, 15) or None, ``[LMResult]``,
        calibration (1, 3) ``[k_l, k_r, D]`` or None, its covariance (1, 3, 3) or None.
    """
    smoother = smoother or SmootherConfig()
    problem = graph.problem(graph.initial)
    result = solve(problem, _lm_config(smoother, smoother.linear_solver))
    states = result.values[_GROUP]
    covariance, calibration, calibration_cov = None, None, None
    if graph.calibrated:
        calibration = result.values[_CALIB][:, 0]
    if smoother.covariance and graph.calibrated:
        covariance, calibration_cov = bordered_chain_covariance(problem, result.values, _CALIB)
    elif smoother.covariance:
        covariance = chain_covariance(problem, result.values)
    return states, covariance, [result], calibration, calibration_cov


def _marginalize(
    graph: KeyframeGraph,
    values: torch.Tensor,
    start: int,
    stop: int,
    previous: F.MarginalPriorFactor | None,
    floor: float,
) -> F.MarginalPriorFactor:
    """Marginalise keyframes ``[start, stop)`` into a prior on keyframe ``stop``.

    Args:
        values: (1, K, 21) current estimates (the linearisation point ``x0``).
        previous: the marginal prior on keyframe ``start`` (indexed 0) or None.
        floor: relative diagonal floor (see the module docstring).
    Returns:
        the new :class:`~msf_torch.backend.factors.MarginalPriorFactor` on keyframe
        ``stop``, indexed 0 (the next window starts there).
    """
    factors = graph.factors(start, stop + 1, unary_last=False)
    if previous is not None:
        factors.append(previous)
    local = values[:, start : stop + 1]
    problem = Problem({_GROUP: (NAV_STATE, local)}, factors)
    lin = problem.linearize({_GROUP: local})
    hessian, gradient = lin.hessian, lin.gradient
    m = NAV_STATE.tangent_dim * (stop - start)
    h_mm, h_mr, h_rr = hessian[:, :m, :m], hessian[:, :m, m:], hessian[:, m:, m:]
    chol_mm = torch.linalg.cholesky(h_mm)
    solved = torch.cholesky_solve(torch.cat((h_mr, gradient[:, :m, None]), -1), chol_mm)
    h_marg = h_rr - h_mr.mT @ solved[..., :-1]
    g_marg = gradient[:, m:] - (h_mr.mT @ solved[..., -1:]).squeeze(-1)
    h_marg = 0.5 * (h_marg + h_marg.mT)
    diagonal = torch.diagonal(h_marg, dim1=-2, dim2=-1)
    scale = diagonal.clamp_min(1e-12 * diagonal.amax(-1, keepdim=True).clamp_min(1e-300))
    level = floor
    for _ in range(12):
        chol, info = torch.linalg.cholesky_ex(h_marg + torch.diag_embed(level * scale))
        if not bool(info.any()):
            break
        level = level * 10.0
    else:
        raise FloatingPointError(f"marginal Hessian of keyframes {start}:{stop} not definite")
    offset = torch.linalg.solve_triangular(chol, g_marg[..., None], upper=False).squeeze(-1)
    slots = ((_GROUP, torch.zeros(1, dtype=torch.long, device=values.device)),)
    origin = [values[:, stop : stop + 1]]
    return F.MarginalPriorFactor(slots, origin, chol.mT[:, None], offset[:, None])


def _predict(graph: KeyframeGraph, state: torch.Tensor, interval: int) -> torch.Tensor:
    """Nav state (1, 21) at keyframe ``interval + 1`` from ``state`` (1, 21) at keyframe
    ``interval`` through the bias-corrected IMU increments (dead reckoning)."""
    position, velocity, rotation, gyro_bias, accel_bias = unpack_nav_state(state)
    pre = _slice_pre(graph.imu, torch.tensor([interval], device=state.device))
    d_rot, d_vel, d_pos = pre.corrected(gyro_bias[:, None], accel_bias[:, None])
    p, v, r = propagate_nominal(
        position,
        velocity,
        rotation,
        pre.delta_t[:, 0],
        d_rot[:, 0],
        d_vel[:, 0],
        d_pos[:, 0],
        graph.gravity,
    )
    return pack_nav_state(p, v, r, gyro_bias, accel_bias)


def smooth_window(
    graph: KeyframeGraph,
    smoother: SmootherConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, list[LMResult]]:
    """Sliding-window smoothing with marginalisation (fixed-lag output).

    Windows of ``window_size`` keyframes slide by ``window_step``; a keyframe's output is
    its estimate in the last window that held it. The first window starts from the front
    end's keyframe states, as the full batch does; a keyframe entering a later window starts
    from the IMU prediction off the previous keyframe's current estimate (at most
    ``window_step`` intervals of dead reckoning with smoothed biases; see the module
    docstring).

    Args:
        graph: the keyframe graph.
        smoother: settings; default :class:`SmootherConfig()`.
        progress: optional callback ``(keyframes_emitted, K)``.
    Returns:
        states (1, K, 21), marginal covariances (1, K, 15, 15) or None, one ``LMResult``
        per window.
    """
    smoother = smoother or SmootherConfig()
    if graph.calibrated:
        raise ValueError("smoother.calibrate_wheels: the sliding window does not calibrate")
    count = graph.size
    size, step = smoother.window_size, smoother.window_step
    values = graph.initial.clone()
    output = graph.initial.clone()
    dim = NAV_STATE.tangent_dim
    covariance = torch.zeros(1, count, dim, dim, dtype=values.dtype, device=values.device)
    results: list[LMResult] = []
    marginal: F.MarginalPriorFactor | None = None
    # keyframes before `filled` hold a starting value: the first window the front end's
    start, filled = 0, min(size, count)
    config = _lm_config(smoother, "dense")
    while True:
        end = min(start + size, count)
        for k in range(filled, end):
            values[:, k] = _predict(graph, values[:, k - 1], k - 1)
        filled = max(filled, end)
        factors = graph.factors(start, end)
        if marginal is not None:
            factors.append(marginal)
        problem = Problem({_GROUP: (NAV_STATE, values[:, start:end])}, factors)
        result = solve(problem, config)
        results.append(result)
        values[:, start:end] = result.values[_GROUP]
        leaving = end - start if end == count else step
        output[:, start : start + leaving] = values[:, start : start + leaving]
        if smoother.covariance:
            lin = problem.linearize(result.values)
            inverse = torch.linalg.inv(lin.hessian)[:, : leaving * dim, : leaving * dim]
            grid = inverse.reshape(1, leaving, dim, leaving, dim)
            blocks = torch.diagonal(grid, dim1=1, dim2=3).permute(0, 3, 1, 2)
            covariance[:, start : start + leaving] = blocks
        if progress is not None:
            progress(start + leaving, count)
        if end == count:
            break
        marginal = _marginalize(
            graph, values, start, start + step, marginal, smoother.marginal_floor
        )
        start += step
    return output, (covariance if smoother.covariance else None), results


@dataclass
class OutputMotion:
    """Velocity, gyro bias and error-state covariance at the epochs of an output
    trajectory (B = 1, N epochs), for exports that carry a twist and covariances.

    Attributes:
        velocity: (1, N, 3) world, m/s.
        gyro_bias: (1, N, 3) rad/s.
        covariance: (1, N, 15, 15) over ``[dp, dv, dtheta (body), db_g, db_a]``, or None.
    """

    velocity: torch.Tensor
    gyro_bias: torch.Tensor
    covariance: torch.Tensor | None


def interpolate_imu(
    seq: Sequence,
    t: torch.Tensor,
    keyframe_index: torch.Tensor,
    states: torch.Tensor,
    covariance: torch.Tensor | None,
    gravity: torch.Tensor,
) -> tuple[Trajectory, OutputMotion]:
    """The smoothed trajectory at times ``t`` between the keyframes, by the IMU (B = 1).

    Between keyframes i and j each epoch's state is keyframe i's smoothed state carried
    forward through the IMU samples (zero-order hold, keyframe i's smoothed biases: the
    smoother's own motion model), plus the fraction ``w`` (time) of the mismatch left at
    keyframe j (position and velocity linearly, rotation along the geodesic), so the output
    is the smoothed state at every keyframe and follows the IMU's motion in between; the
    front end's measurement updates inside the interval do not enter. The gyro bias is
    interpolated linearly; the covariance is ``(1 - w) Sigma_i + w Sigma_j`` of the
    keyframes' marginals, an approximation (positive definite, exact at the keyframes) that
    leaves out the IMU's own uncertainty over the sub-keyframe motion.

    Args:
        seq: the sequence (its IMU; B = 1).
        t: (E,) output times, s, increasing, from the first keyframe to the last.
        keyframe_index: (K,) the keyframes' positions in ``t`` (K >= 1).
        states: (1, K, 21) smoothed nav states.
        covariance: (1, K, 15, 15) their marginal covariances, or None.
        gravity: (3,) m/s^2 world.
    Returns:
        :class:`Trajectory` (1, E) and :class:`OutputMotion` at ``t``.
    Raises:
        ValueError: ``states`` and ``keyframe_index`` disagree on K, or the first and last
            keyframes are not the first and last output times (epochs outside the
            keyframes would get the wrong interval's state).
    """
    position, velocity, rotation, gyro_bias, accel_bias = unpack_nav_state(states[0])
    count = t.numel()
    if states.shape[1] != keyframe_index.numel():
        raise ValueError(
            f"interpolate_imu: {states.shape[1]} keyframe states for "
            f"{keyframe_index.numel()} keyframe positions"
        )
    ends = (int(keyframe_index[0]), int(keyframe_index[-1]))
    if ends != (0, count - 1):
        raise ValueError(
            f"interpolate_imu: the output times must run from the first keyframe to the "
            f"last, i.e. keyframe positions 0 and {count - 1} of {count}; got {ends[0]} and "
            f"{ends[1]}"
        )
    if keyframe_index.numel() == 1:
        trajectory = Trajectory(
            t=t[None],
            position=position[None],
            quaternion=matrix_to_quat(rotation)[None],
            mask=torch.ones(1, 1, dtype=torch.bool, device=t.device),
        )
        return trajectory, OutputMotion(velocity[None], gyro_bias[None], covariance)
    keep = seq.imu.mask[0]
    cut = cut_imu(seq.imu.t[0, keep], seq.imu.gyro[0, keep], seq.imu.accel[0, keep], t)
    # the keyframe interval of every epoch-to-epoch step and of every epoch
    last = keyframe_index.numel() - 2
    epochs = torch.arange(count, device=t.device)
    step_seg = torch.searchsorted(keyframe_index, epochs[:-1], right=True) - 1
    seg = (torch.searchsorted(keyframe_index, epochs, right=True) - 1).clamp(0, last)
    pre = preintegrate_imu(
        ImuIntervals(cut.gyro[None], cut.accel[None], cut.dt[None]),
        gyro_bias[step_seg][None],
        accel_bias[step_seg][None],
        covariance="closed_form",
    )
    out_p, out_v, out_r = position[seg].clone(), velocity[seg].clone(), rotation[seg].clone()
    # carry every keyframe forward at once, one epoch per pass
    p, v, r = position[:-1], velocity[:-1], rotation[:-1]
    length = keyframe_index[1:] - keyframe_index[:-1]
    for m in range(int(length.max())):
        moving = m < length
        step = torch.where(moving, keyframe_index[:-1] + m, 0)
        p_new, v_new, r_new = propagate_nominal(
            p,
            v,
            r,
            pre.delta_t[0, step],
            pre.delta_rotation[0, step],
            pre.delta_velocity[0, step],
            pre.delta_position[0, step],
            gravity,
        )
        p = torch.where(moving[:, None], p_new, p)
        v = torch.where(moving[:, None], v_new, v)
        r = torch.where(moving[:, None, None], r_new, r)
        inside = moving & (m + 1 < length)
        target = (keyframe_index[:-1] + m + 1)[inside]
        out_p[target], out_v[target], out_r[target] = p[inside], v[inside], r[inside]
    # p, v, r now hold each keyframe carried to the next one: spread the mismatch
    lo, hi = keyframe_index[seg], keyframe_index[seg + 1]
    weight = ((t - t[lo]) / (t[hi] - t[lo]).clamp_min(1e-12)).clamp(0.0, 1.0)[:, None]
    turn = so3.log(r.mT @ rotation[1:])[seg]
    out_p = out_p + weight * (position[1:] - p)[seg]
    out_v = out_v + weight * (velocity[1:] - v)[seg]
    out_r = out_r @ so3.exp(weight * turn)
    bias = (1.0 - weight) * gyro_bias[seg] + weight * gyro_bias[seg + 1]
    # the keyframes themselves: their smoothed states
    out_p[keyframe_index], out_v[keyframe_index], out_r[keyframe_index] = (
        position,
        velocity,
        rotation,
    )
    bias[keyframe_index] = gyro_bias
    blended = None
    if covariance is not None:
        w = weight[..., None]
        blended = (1.0 - w) * covariance[0, seg] + w * covariance[0, seg + 1]
        blended[keyframe_index] = covariance[0]
        blended = blended[None]
    trajectory = Trajectory(
        t=t[None],
        position=out_p[None],
        quaternion=matrix_to_quat(out_r)[None],
        mask=torch.ones(1, count, dtype=torch.bool, device=t.device),
    )
    return trajectory, OutputMotion(out_v[None], bias[None], blended)


def smooth(
    seq: Sequence,
    frontend: EskfResult,
    cfg: EskfConfig,
    smoother: SmootherConfig | None = None,
    mode: str = "full",
    progress: Callable[[int, int], None] | None = None,
) -> SmootherResult:
    """Smooth one sequence after the front end: keyframes, graph, solve, output.

    Args:
        seq: the sequence the front end ran on.
        frontend: its :class:`~msf_torch.frontend.eskf.EskfResult`.
        cfg: the front end's settings.
        smoother: smoother settings; default :class:`SmootherConfig()`.
        mode: ``"full"`` (:func:`smooth_full`) or ``"window"`` (:func:`smooth_window`).
        progress: optional callback ``(done, total)`` (windows: keyframes emitted).
    Returns:
        :class:`SmootherResult`.
    """
    if mode not in ("full", "window"):
        raise ValueError(f"smoother mode must be 'full' or 'window', got {mode!r}")
    smoother = smoother or SmootherConfig()
    if mode == "window" and smoother.calibrate_wheels:
        raise ValueError(
            "config key 'smoother.calibrate_wheels' is supported by the full batch only "
            "(msf run --smooth full)"
        )
    start = time.perf_counter()
    calibration, calibration_cov = None, None
    seq, _ = sanitize_sequence(seq)  # as the front end read it (build_graph does too)
    with _intra_op_threads(1):  # small matrices: thread hand-offs cost more than they save
        graph = build_graph(seq, frontend, cfg, smoother)
        if mode == "full":
            states, covariance, results, calibration, calibration_cov = smooth_full_calibrated(
                graph, smoother
            )
            if progress is not None:
                progress(1, 1)
        else:
            states, covariance, results = smooth_window(graph, smoother, progress)
        wall = time.perf_counter() - start
        if covariance is not None:  # the inverses leave ~1e-12 asymmetry, which exports carry
            covariance = 0.5 * (covariance + covariance.mT)
        whole = graph.problem(graph.initial)
        solved = None if calibration is None else calibration[:, None]
        costs = whole.cost(graph.values(graph.initial)), whole.cost(graph.values(states, solved))
    if smoother.output == "frontend":
        real = torch.nonzero(frontend.mask[0]).squeeze(-1)
        output, motion = interpolate_imu(
            seq,
            frontend.t[0, real],
            torch.searchsorted(real, graph.epoch),
            states,
            covariance,
            graph.gravity,
        )
    else:
        _, velocity, _, gyro_bias, _ = unpack_nav_state(states)
        motion = OutputMotion(velocity, gyro_bias, covariance)
        position, _, rotation, _, _ = unpack_nav_state(states)
        output = Trajectory(
            t=graph.t[None],
            position=position,
            quaternion=matrix_to_quat(rotation),
            mask=torch.ones(1, graph.size, dtype=torch.bool, device=graph.t.device),
        )
    return SmootherResult(
        mode=mode,
        t=graph.t[None],
        states=states,
        covariance=covariance,
        lm=results,
        initial_cost=float(costs[0]),
        cost=float(costs[1]),
        wall_s=wall,
        output=output,
        output_motion=motion,
        calibration_names=WHEEL_STATES if calibration is not None else (),
        calibration=calibration,
        calibration_sigma=None
        if calibration_cov is None
        else torch.diagonal(calibration_cov, dim1=-2, dim2=-1).sqrt(),
    )
