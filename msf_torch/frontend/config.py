"""Front-end configuration: one flat dataclass, loadable from YAML with key-naming errors.

Units are in the field names. Defaults suit a small wheeled robot with a MEMS IMU of the
ADIS16470 class (see ``msf_torch.sim``); dataset loaders may supply their own IMU noise
(e.g. the KITTI metadata file), which :func:`config_for_sequence` applies unless the YAML
sets the value explicitly.
"""

from __future__ import annotations

__all__ = [
    "EskfConfig",
    "MEASUREMENT_BLOCKS",
    "load_config",
    "read_config_keys",
    "config_for_sequence",
    "load_sequence_config",
    "packaged_config",
]

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msf_torch.io.errors import DataError
from msf_torch.io.native import GEOMETRY_KEYS
from msf_torch.io.yaml_files import YamlDocument, did_you_mean, named_key, read_yaml

MEASUREMENT_BLOCKS = (
    "wheel",
    "nhc",
    "zupt",
    "gnss",
    "gnss_velocity",
    "gnss_heading",
    "magnetometer",
    "pose",
)
"""The filter's measurement blocks (``frontend.eskf.SENSORS``), besides ``pose:<name>``."""


@dataclass
class EskfConfig:
    """ESKF front-end settings (all SI units, named in the field)."""

    # IMU noise densities (continuous time)
    gyro_noise_density: float = 9.9e-5  # rad/s/sqrt(Hz)
    accel_noise_density: float = 6.2e-4  # m/s^2/sqrt(Hz)
    gyro_bias_rw_density: float = 3.9e-6  # rad/s^2/sqrt(Hz)
    accel_bias_rw_density: float = 1.3e-5  # m/s^3/sqrt(Hz)
    gravity_mps2: float = 9.80665
    # initial state
    init_window_s: float = 0.5  # accelerometer averaging for roll/pitch
    init_min_gnss_distance_m: float = 20.0  # GNSS travel used to fix the initial yaw
    init_max_track_s: float = 30.0  # ... looked for in the first fixes up to this long
    # a GNSS velocity (Sequence.gnss_velocity) this fast gives the course over ground, the
    # initial heading when its modelled variance beats the track's (frontend.init)
    init_min_gnss_speed_mps: float = 1.0
    init_position_sigma_m: float = 1.0
    init_velocity_sigma_mps: float = 0.5
    init_roll_pitch_sigma_rad: float = 0.03  # tilt from a moving accelerometer (motion part)
    init_yaw_sigma_unknown_rad: float = 3.141592653589793  # no heading source at all
    # heading sigma when the first pose measurement gives the heading (and the attitude scale
    # of a reset's sigma cap); a GNSS-track heading gets the sigma of the estimate made
    # instead (frontend.init.alignment_yaw_variance), with no floor: over sim seeds
    # 100-899 that model alone gives yaw error / sigma of std 0.97, a constant 0.05 gave 0.68
    init_yaw_sigma_rad: float = 0.05
    init_gyro_bias_sigma_radps: float = 3.5e-3
    init_accel_bias_sigma_mps2: float = 0.05
    init_gyro_bias_radps: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    init_accel_bias_mps2: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # IMU gaps
    imu_gap_s: float = 0.1  # a sample interval longer than this is a gap
    imu_gap_noise_scale: float = 100.0  # variance multiplier over a gap
    # over a gap of T s the true rate and specific force leave the held sample as a random
    # walk of this density per body axis [x, y, z]: the gap's pieces get white noise of
    # density q^2 T^2 / 3 on top (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz); 0 turns it off; as the
    # smoothers' keys of the same names)
    imu_gap_gyro_rw_density: list[float] = field(default_factory=lambda: [0.005, 0.005, 0.06])
    imu_gap_accel_rw_density: list[float] = field(default_factory=lambda: [0.2, 0.2, 0.02])
    # the walk skips an epoch holding more gap than this, s (a blind dropout: no update in
    # it; the walk's yaw sigma q_z sqrt(T^3 / 3) is 0.5 rad at 6 s): past it the updates
    # after the gap do not recover from the walk's covariance, the divergence guard's reset
    # does recover from the x imu_gap_noise_scale alone (docs/frontend.md, "Faulty input")
    imu_gap_walk_max_blind_s: float = 6.0
    # runs of at least this many samples that lie exactly on the line through their
    # neighbours in all six channels were filled in by the recorder, not measured
    # (``sensors.imu_gaps``): they count as a gap too; 0 turns the check off
    imu_interpolated_min_samples: int = 10
    # wheel odometry
    wheel_track_m: float = 0.55
    wheel_lever_arm_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    wheel_speed_sigma_mps: float = 0.05
    wheel_lateral_sigma_mps: float = 0.05
    wheel_yaw_rate_sigma_radps: float = 0.05
    # the wheel yaw rate (v_r - v_l) / D carries the left/right radius mismatch as a bias
    # proportional to speed; by default it feeds only the slip factor, not the state
    wheel_yaw_rate_update: bool = False
    # non-holonomic constraint (vehicles without wheel data)
    nhc: str = "auto"  # auto (when a sequence has no wheel data) | on | off
    nhc_rate_hz: float = 2.0  # its epochs where no measurement is nearer
    # an epoch ends at least this often where nothing else ends one (the NHC's own rate
    # where it is on): a trajectory sample and a propagation step through a GNSS outage
    max_epoch_s: float = 0.5
    nhc_sigma_mps: float = 0.1
    nhc_lever_arm_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # zero-velocity update
    zupt: bool = True
    zupt_sigma_mps: float = 0.01
    zupt_wheel_speed_mps: float = 0.005
    zupt_gyro_radps: float = 0.01
    zupt_accel_std_mps2: float = 0.05
    zupt_window_s: float = 0.5
    # stationarity from the IMU alone cannot tell standing still from smooth constant-velocity
    # driving, so it is off unless asked for; wheel-based detection is always on with zupt
    zupt_imu_detector: bool = False
    # GNSS
    gnss_sigma_m: list[float] = field(default_factory=lambda: [0.5, 0.5, 1.0])
    # multiplier on every fix's sigma, the file's or gnss_sigma_m (msf tune fits it)
    gnss_sigma_scale: float = 1.0
    gnss_lever_arm_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # GNSS velocity (Sequence.gnss_velocity: Doppler, or speed and course over ground) of the
    # same antenna: default per-axis sigma east, north, up (m/s) where the data gives none
    gnss_velocity_sigma_mps: list[float] = field(default_factory=lambda: [0.1, 0.1, 0.2])
    # dual-antenna GNSS heading (Sequence.gnss_heading): the baseline from the primary to the
    # secondary antenna in the body frame (m; only its direction counts: [1, 0, 0] when the
    # receiver reports the heading of the body's x axis, as most are set up to), and the
    # default sigma (rad) where the data gives none
    gnss_heading_baseline_m: list[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])
    gnss_heading_sigma_rad: float = 0.01
    # magnetometer (Sequence.magnetometer), fused as a heading (sensors.magnetometer): the
    # azimuth of the corrected field W (m - b) turned into the world must be the local
    # declination (magnetic north's azimuth clockwise from true north, east positive, rad).
    # Hard iron b (uT, body frame) and soft iron W (9 numbers, row-major 3 x 3) as
    # `msf magcal` fits them; per-axis noise (uT) where the data gives none; a heading floor
    # (rad, in quadrature) for the calibration's residual distortion; at most
    # magnetometer_rate_hz readings fused per second (the first of each 1 / rate bin).
    # Readings whose corrected magnitude departs from the local field's by more than the
    # relative tolerance, or whose dip below the horizon (seen through the filter's
    # attitude) departs from the local inclination by more than the dip tolerance (rad),
    # are disturbed (steel, motors, currents) and not fused. The local field magnitude
    # (uT) and inclination (rad, positive down): 0 = from each run (the median corrected
    # magnitude; the median angle between the corrected field and the accelerometer),
    # which a run filtered in pieces takes per piece; at the magnetic equator give 1e-3.
    magnetometer_declination_rad: float = 0.0
    magnetometer_hard_iron_uT: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    magnetometer_soft_iron: list[float] = field(
        default_factory=lambda: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    )
    magnetometer_sigma_uT: float = 0.5
    magnetometer_heading_floor_rad: float = 0.03
    magnetometer_rate_hz: float = 2.0
    magnetometer_field_uT: float = 0.0
    magnetometer_field_tolerance: float = 0.1
    magnetometer_inclination_rad: float = 0.0
    magnetometer_dip_tolerance_rad: float = 0.1
    # a reading whose change from the readings up to this many seconds before is not the
    # gyro's turn is disturbed (frontend.schedule.rotation_inconsistent); 0 = no such test
    magnetometer_consistency_s: float = 3.0
    # named pose sources (Sequence.pose_sources: VO, LiDAR odometry) fused as odometry: the
    # body-frame mean velocity between consecutive valid samples of a source (see
    # frontend.schedule); "auto" = every source present, a list = those names, [] = none
    pose_sources: str | list[str] = "auto"
    # bound on the acceleration a that makes the interval's mean velocity differ from the
    # velocity at its end: (a dt / 2)^2 joins the variance of each velocity row
    pose_source_accel_sigma_mps2: float = 1.0
    pose_source_max_gap_s: float = 0.5  # consecutive samples further apart are not paired
    # also fuse the mean body rate of the relative rotation against the mean gyro rate (it
    # observes the gyro bias, hence bounds the heading drift)
    pose_source_rate_update: bool = True
    # how pose sources enter: "velocity" (the odometry rows above) or "drifting_frame": each
    # sample as an absolute pose against the source's own frame, whose offset (world
    # translation t_o, body rotation phi_o: z_p = p + t_o, R_z = R Exp(phi_o)) is a 6-DoF
    # state per source, a random walk in distance travelled, re-initialised from the current
    # estimate at a source's first pair and after every gap (frontend.source_frames)
    pose_source_fusion: str = "velocity"
    # drifting_frame: the offset's random-walk densities (datasheet drift of the odometry,
    # per sqrt(metre) travelled; times the source's variance scale) ...
    pose_source_drift_position_m_per_sqrt_m: float = 0.01
    pose_source_drift_rotation_rad_per_sqrt_m: float = 1e-3
    # ... and per source name [m/sqrt(m), rad/sqrt(m)], overriding the two above
    pose_source_drift: dict[str, list[float]] = field(default_factory=dict)
    # per source name: multiplier on its declared covariance (variances; default 1; msf tune)
    pose_source_variance_scale: dict[str, float] = field(default_factory=dict)
    # chi-square gating (probability of the acceptance region; 1.0 disables)
    gate_probability: float = 0.9999
    gate_pseudo_measurements: bool = False  # also gate NHC and zero-velocity updates
    # absolute sensors (GNSS, pose) and pose sources pass after this many rejections in a row
    gate_reopen_after: int = 3
    # wheel slip factor
    slip_detection: bool = True
    slip_sensitivity: float = 3.0  # factor = exp(-q / (2 k^2)), q = normalised disagreement
    slip_recovery_per_s: float = 1.0  # how fast the factor may rise again, 1/s
    slip_skip_below: float = 0.2  # wheel updates skipped below this factor
    slip_flag_below: float = 0.5  # a wheel epoch counts as slipping below this factor
    # time tolerance when merging measurement times, s
    time_tolerance_s: float = 1e-6
    # divergence guard (frontend.guard): a sequence whose state or covariance turns
    # non-finite or not positive definite, or whose accepted gated block has a NIS above
    # this many times its gate, is reset to its last good state ...
    divergence_nis_scale: float = 10.0
    # ... with the covariance multiplied by this, once per divergence episode, no sigma
    # raised past divergence_max_sigma_factor x its init_*_sigma (attitude: pi)
    divergence_inflation: float = 100.0
    divergence_max_sigma_factor: float = 20.0
    # adaptive noise (frontend.adaptive); both lists empty = off, results as without
    # Sage-Husa estimate of the measurement noise R of these blocks: "gnss", "pose",
    # "pose:<name>" (not wheel/NHC/ZUPT: the slip factor and the pseudo-measurements set
    # their own noise)
    adaptive_noise_sensors: list[str] = field(default_factory=list)
    # strong tracking: a fading factor from the innovations of these blocks (any sensor key)
    # inflates the predicted covariance
    strong_tracking_sensors: list[str] = field(default_factory=list)
    adaptive_forgetting: float = 0.95  # b of the exponential fading, 0.95-0.99 in practice
    adaptive_prior_samples: float = 10.0  # what the nominal R is worth, in samples
    adaptive_noise_floor: float = 0.1  # R_hat eigenvalues >= this x the nominal R's smallest
    strong_tracking_softening: float = 1.0  # beta in N = V - H Q H^T - beta R
    strong_tracking_max_factor: float = 10.0  # cap on the fading factor
    # one innovation moves R_hat or V by at most this chi-square quantile (1.0: no clip)
    adaptive_clip_probability: float = 0.9999
    # multi-model source-fault detection (frontend.gating): each pose source gets a UKF of
    # the increments it reports; a source whose residuals differ from the other sources' by
    # more than T = c v / f + T_0 over the window and whose two-tailed Z-test fails is
    # excluded (weight 0) until its recent residuals are calm again. Off: results unchanged
    source_fault_detection: bool = False
    source_fault_window: int = 10  # samples in each source's residual window
    source_fault_speed_factor: float = 1.0  # c (1: one sample's travel)
    source_fault_min_threshold_m: float = 0.05  # T_0
    source_fault_z_enter: float = 3.0  # max |Z| over the window that excludes a source
    source_fault_z_exit: float = 1.5  # max |Z| over the last exit samples that re-admits it
    source_fault_exit_samples: int = 3
    # stiffness of the models: random-walk densities of body velocity and rate; a model
    # that adapts fast absorbs a lasting fault before the test sees it
    source_fault_accel_sigma_mps2: float = 0.1
    source_fault_angular_accel_sigma_radps2: float = 0.1
    source_fault_rotation_lever_m: float = 1.0  # m per rad of a heading residual
    # online calibration (frontend.calibration): states appended to the error state, each a
    # random walk; all off = results unchanged. Wheels: radius ratios k_l, k_r (true / nominal
    # radius, readings are rim speeds at the nominal radius) and the track width (starts at
    # wheel_track_m); the wheel yaw-rate row is then fused (it observes the track width)
    calibrate_wheels: bool = False
    calibration_wheel_radius_ratio: list[float] = field(default_factory=lambda: [1.0, 1.0])
    calibration_wheel_radius_sigma: float = 0.1  # prior 1-sigma of each ratio
    calibration_wheel_track_sigma_m: float = 0.05  # prior 1-sigma of the track width
    calibration_wheel_rw_density: float = 1e-5  # ratio random walk, 1/sqrt(s)
    calibration_wheel_track_rw_density: float = 1e-5  # m/sqrt(s)
    # time offsets t_d (sample stamped t_s was taken at t_s + t_d on the IMU clock) of these
    # sensors: "gnss", "pose:<name>" (pose sources)
    calibrate_time_offsets: list[str] = field(default_factory=list)
    calibration_time_offset_s: dict[str, float] = field(default_factory=dict)  # initial t_d
    calibration_time_offset_sigma_s: float = 0.05  # prior 1-sigma
    calibration_time_offset_rw_density: float = 1e-5  # s/sqrt(s)
    # extrinsics (lever arms in the body = IMU frame, rotations as rotation vectors, rad):
    # GNSS antenna lever arm (starts at gnss_lever_arm_m); per pose source "pose:<name>" its
    # lever arm and mounting rotation (sensor -> body; start at the values below, default 0:
    # the source measures the body); IMU-to-vehicle rotation (vehicle -> body) of the wheel
    # and non-holonomic models
    calibrate_gnss_lever_arm: bool = False
    calibrate_pose_extrinsics: list[str] = field(default_factory=list)
    calibration_pose_lever_arm_m: dict[str, list[float]] = field(default_factory=dict)
    calibration_pose_rotation_rad: dict[str, list[float]] = field(default_factory=dict)
    calibrate_imu_body_rotation: bool = False
    calibration_imu_body_rotation_rad: list[float] = field(default_factory=lambda: [0.0] * 3)
    # dual-antenna heading offset: the baseline gnss_heading_baseline_m turned about body z
    # by this angle (rad; starts at calibration_gnss_heading_offset_rad)
    calibrate_gnss_heading_offset: bool = False
    calibration_gnss_heading_offset_rad: float = 0.0
    # magnetometer declination (the azimuth of magnetic north, plus the sensor's mounting yaw
    # error, which acts alike on level ground): starts at magnetometer_declination_rad with
    # this prior sigma (rad; a declination looked up for the site is known to ~0.01 rad)
    calibrate_magnetometer_declination: bool = False
    calibration_magnetometer_declination_sigma_rad: float = 0.3
    calibration_lever_arm_sigma_m: float = 0.3  # prior 1-sigma per axis
    calibration_rotation_sigma_rad: float = 0.05  # prior 1-sigma per axis (and the offset)
    calibration_lever_arm_rw_density: float = 1e-5  # m/sqrt(s)
    calibration_rotation_rw_density: float = 1e-6  # rad/sqrt(s)
    # a calibration state counts as observable on a run when its variance has fallen below
    # this fraction of the variance it would have without measurements (prior + random walk)
    calibration_observable_ratio: float = 0.25

    def replace(self, **changes: Any) -> EskfConfig:
        """A copy with ``changes`` applied (names are checked)."""
        return dataclasses.replace(self, **changes)

    def differing_keys(self, other: EskfConfig) -> list[str]:
        """Names of the settings whose values differ from ``other``'s, in field order."""
        return [
            f.name
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != getattr(other, f.name)
        ]

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad key."""
        self._validate_types()
        positive = [
            "gyro_noise_density",
            "accel_noise_density",
            "gravity_mps2",
            "wheel_track_m",
            "wheel_speed_sigma_mps",
            "wheel_lateral_sigma_mps",
            "wheel_yaw_rate_sigma_radps",
            "nhc_rate_hz",
            "max_epoch_s",
            "nhc_sigma_mps",
            "zupt_sigma_mps",
            "gnss_sigma_scale",
            "imu_gap_s",
            "imu_gap_noise_scale",
            "imu_gap_walk_max_blind_s",
            "slip_sensitivity",
            "pose_source_max_gap_s",
            "divergence_nis_scale",
            "divergence_max_sigma_factor",
            "init_min_gnss_speed_mps",
        ]
        self._require_numbers(positive, positive=True)
        count = self.imu_interpolated_min_samples
        if not (isinstance(count, int) and not isinstance(count, bool) and count >= 0):
            raise ValueError(
                f"config key 'imu_interpolated_min_samples' must be an integer >= 0, got {count!r}"
            )
        if self.nhc not in ("auto", "on", "off"):
            raise ValueError(f"config key 'nhc' must be auto, on or off, got {self.nhc!r}")
        self._require_numbers(("pose_source_accel_sigma_mps2",), positive=False)
        names = self.pose_sources
        if names != "auto" and not (
            isinstance(names, list)
            and all(isinstance(n, str) and n for n in names)
            and len(set(names)) == len(names)
        ):
            raise ValueError(
                f"config key 'pose_sources' must be 'auto' or a list of distinct source names, "
                f"got {names!r}"
            )
        inflation = self.divergence_inflation
        if not (isinstance(inflation, (int, float)) and math.isfinite(inflation)) or inflation < 1:
            raise ValueError(
                f"config key 'divergence_inflation' must be a number >= 1, got {inflation!r}"
            )
        if not 0.0 < self.gate_probability <= 1.0:
            raise ValueError("config key 'gate_probability' must lie in (0, 1]")
        self._validate_adaptive()
        self._validate_source_faults()
        self._validate_source_fusion()
        self._validate_calibration()
        for key in (
            "wheel_lever_arm_m",
            "nhc_lever_arm_m",
            "gnss_lever_arm_m",
            "gnss_sigma_m",
            "gnss_velocity_sigma_mps",
            "gnss_heading_baseline_m",
            "magnetometer_hard_iron_uT",
            "init_gyro_bias_radps",
            "init_accel_bias_mps2",
            "imu_gap_gyro_rw_density",
            "imu_gap_accel_rw_density",
        ):
            value = getattr(self, key)
            if len(value) != 3:
                raise ValueError(f"config key '{key}' must have 3 entries, got {value!r}")
        if math.hypot(*self.gnss_heading_baseline_m[:2]) < 1e-3:
            raise ValueError(
                "config key 'gnss_heading_baseline_m' must be a baseline direction with a "
                "horizontal part longer than 1 mm (a vertical baseline has no heading), got "
                f"{self.gnss_heading_baseline_m!r}"
            )
        self._validate_magnetometer()

    def _validate_magnetometer(self) -> None:
        """Raise ``ValueError`` naming the first bad magnetometer key."""
        soft = self.magnetometer_soft_iron
        if len(soft) != 9 or abs(_det3(soft)) < 1e-9:
            raise ValueError(
                "config key 'magnetometer_soft_iron' must be 9 numbers (a 3 x 3 matrix, row "
                f"by row) with a non-zero determinant, got {soft!r}"
            )
        self._require_numbers(
            (
                "magnetometer_rate_hz",
                "magnetometer_field_tolerance",
                "magnetometer_dip_tolerance_rad",
            ),
            True,
        )
        if abs(self.magnetometer_inclination_rad) > math.pi / 2:
            raise ValueError("config key 'magnetometer_inclination_rad' must lie in [-pi/2, pi/2]")
        self._require_numbers(
            (
                "magnetometer_field_uT",
                "magnetometer_heading_floor_rad",
                "magnetometer_consistency_s",
            ),
            False,
        )

    def _validate_types(self) -> None:
        """Raise ``ValueError`` naming the first key whose value does not have its field's
        type (``float``: a finite number, ``int``, ``bool``, ``str``, ``list[float]``: a list
        or tuple of finite numbers, ``list[str]``), or that is a negative density or a sigma
        not above 0."""

        def number(x: Any) -> bool:
            return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

        checks = {
            "float": (number, "a finite number"),
            "int": (lambda x: isinstance(x, int) and not isinstance(x, bool), "an integer"),
            "bool": (lambda x: isinstance(x, bool), "true or false"),
            "str": (lambda x: isinstance(x, str), "a string"),
            "list[float]": (
                lambda x: isinstance(x, (list, tuple)) and all(number(v) for v in x),
                "a list of finite numbers",
            ),
            "list[str]": (
                lambda x: isinstance(x, (list, tuple)) and all(isinstance(v, str) for v in x),
                "a list of strings",
            ),
        }
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type in checks:
                ok, what = checks[f.type]
                if not ok(value):
                    raise ValueError(f"config key '{f.name}' must be {what}, got {value!r}")
            if f.type not in ("float", "list[float]"):
                continue
            values = value if isinstance(value, (list, tuple)) else [value]
            if "density" in f.name and any(v < 0 for v in values):
                raise ValueError(f"config key '{f.name}' must not be negative, got {value!r}")
            if "sigma" in f.name and f.name not in _ZERO_SIGMA_ALLOWED:
                if any(v <= 0 for v in values):
                    raise ValueError(
                        f"config key '{f.name}' is a standard deviation: it must be above 0, "
                        f"got {value!r}"
                    )

    def _require_numbers(self, keys: Iterable[str], positive: bool) -> None:
        """Raise ``ValueError`` naming the first of ``keys`` whose value is not a finite
        number above 0 (``positive``) or at least 0."""
        for key in keys:
            value = getattr(self, key)
            ok = isinstance(value, (int, float)) and math.isfinite(value)
            if not (ok and (value > 0 if positive else value >= 0)):
                kind = "positive" if positive else "non-negative"
                raise ValueError(f"config key '{key}' must be a {kind} number, got {value!r}")

    def _validate_calibration(self) -> None:
        """Raise ``ValueError`` naming the first bad online-calibration key."""
        self._require_numbers(
            (
                "calibration_wheel_radius_sigma",
                "calibration_wheel_track_sigma_m",
                "calibration_time_offset_sigma_s",
            ),
            positive=True,
        )
        self._require_numbers(
            (
                "calibration_wheel_rw_density",
                "calibration_wheel_track_rw_density",
                "calibration_time_offset_rw_density",
            ),
            positive=False,
        )
        ratio = self.calibration_wheel_radius_ratio
        if not (
            isinstance(ratio, list)
            and len(ratio) == 2
            and all(isinstance(r, (int, float)) and math.isfinite(r) and r > 0 for r in ratio)
        ):
            raise ValueError(
                f"config key 'calibration_wheel_radius_ratio' must be two positive numbers, "
                f"got {ratio!r}"
            )
        names = self.calibrate_time_offsets
        if not (
            isinstance(names, list)
            and all(
                isinstance(n, str)
                and (n in ("gnss", "gnss_heading") or (n.startswith("pose:") and len(n) > 5))
                for n in names
            )
            and len(set(names)) == len(names)
        ):
            raise ValueError(
                f"config key 'calibrate_time_offsets' must be a list of distinct 'gnss', "
                f"'gnss_heading' or 'pose:<name>', got {names!r}"
            )
        self._validate_extrinsic_calibration()
        offsets = self.calibration_time_offset_s
        if not isinstance(offsets, dict) or not all(
            k in names and isinstance(v, (int, float)) and math.isfinite(v)
            for k, v in offsets.items()
        ):
            raise ValueError(
                f"config key 'calibration_time_offset_s' must map sensors listed in "
                f"'calibrate_time_offsets' to finite seconds, got {offsets!r}"
            )

    def _validate_extrinsic_calibration(self) -> None:
        """Raise ``ValueError`` naming the first bad lever-arm / rotation calibration key."""
        self._require_numbers(
            (
                "calibration_lever_arm_sigma_m",
                "calibration_rotation_sigma_rad",
            ),
            positive=True,
        )
        self._require_numbers(
            (
                "calibration_lever_arm_rw_density",
                "calibration_rotation_rw_density",
            ),
            positive=False,
        )
        ratio = self.calibration_observable_ratio
        if not (isinstance(ratio, (int, float)) and 0 < ratio < 1):
            raise ValueError(
                f"config key 'calibration_observable_ratio' must lie in (0, 1), got {ratio!r}"
            )
        names = self.calibrate_pose_extrinsics
        if not (
            isinstance(names, list)
            and all(isinstance(n, str) and n.startswith("pose:") and len(n) > 5 for n in names)
            and len(set(names)) == len(names)
        ):
            raise ValueError(
                f"config key 'calibrate_pose_extrinsics' must be a list of distinct "
                f"'pose:<name>', got {names!r}"
            )

        def vector(value: Any) -> bool:
            return (
                isinstance(value, list)
                and len(value) == 3
                and all(isinstance(x, (int, float)) and math.isfinite(x) for x in value)
            )

        for key in ("calibration_pose_lever_arm_m", "calibration_pose_rotation_rad"):
            value = getattr(self, key)
            if not isinstance(value, dict) or not all(
                k in names and vector(v) for k, v in value.items()
            ):
                raise ValueError(
                    f"config key '{key}' must map sources listed in 'calibrate_pose_extrinsics' "
                    f"to 3 finite numbers, got {value!r}"
                )
        if not vector(self.calibration_imu_body_rotation_rad):
            raise ValueError(
                f"config key 'calibration_imu_body_rotation_rad' must have 3 finite numbers, "
                f"got {self.calibration_imu_body_rotation_rad!r}"
            )

    def _validate_source_fusion(self) -> None:
        """Raise ``ValueError`` naming the first bad pose-source fusion key."""
        if self.pose_source_fusion not in ("velocity", "drifting_frame"):
            raise ValueError(
                f"config key 'pose_source_fusion' must be velocity or drifting_frame, "
                f"got {self.pose_source_fusion!r}"
            )
        self._require_numbers(
            (
                "pose_source_drift_position_m_per_sqrt_m",
                "pose_source_drift_rotation_rad_per_sqrt_m",
            ),
            positive=False,
        )
        drift = self.pose_source_drift
        if not isinstance(drift, dict) or not all(
            isinstance(k, str)
            and isinstance(v, list)
            and len(v) == 2
            and all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0 for x in v)
            for k, v in drift.items()
        ):
            raise ValueError(
                f"config key 'pose_source_drift' must map source names to two non-negative "
                f"numbers [m/sqrt(m), rad/sqrt(m)], got {drift!r}"
            )
        scales = self.pose_source_variance_scale
        if not isinstance(scales, dict) or not all(
            isinstance(k, str)
            and isinstance(v, (int, float))
            and not isinstance(v, bool)
            and math.isfinite(v)
            and v > 0
            for k, v in scales.items()
        ):
            raise ValueError(
                f"config key 'pose_source_variance_scale' must map source names to positive "
                f"numbers, got {scales!r}"
            )
        calibrated = [
            n
            for n in (*self.calibrate_time_offsets, *self.calibrate_pose_extrinsics)
            if n.startswith("pose:")
        ]
        if self.pose_source_fusion == "drifting_frame" and calibrated:
            raise ValueError(
                f"config key 'pose_source_fusion': drifting_frame does not calibrate pose "
                f"sources (time offsets, extrinsics of {calibrated}); use velocity"
            )

    def _validate_source_faults(self) -> None:
        """Raise ``ValueError`` naming the first bad source-fault key."""
        for key in ("source_fault_window", "source_fault_exit_samples"):
            value = getattr(self, key)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"config key '{key}' must be an integer >= 1, got {value!r}")
        self._require_numbers(
            (
                "source_fault_speed_factor",
                "source_fault_min_threshold_m",
                "source_fault_z_enter",
                "source_fault_rotation_lever_m",
            ),
            positive=False,
        )
        self._require_numbers(
            (
                "source_fault_accel_sigma_mps2",
                "source_fault_angular_accel_sigma_radps2",
            ),
            positive=True,
        )
        if not 0 < self.source_fault_z_exit <= self.source_fault_z_enter:
            raise ValueError(
                "config keys 'source_fault_z_exit' and 'source_fault_z_enter' must satisfy "
                "0 < z_exit <= z_enter"
            )

    def _validate_adaptive(self) -> None:
        """Raise ``ValueError`` naming the first bad adaptive-noise key."""
        blocks = MEASUREMENT_BLOCKS
        for key, allowed in (
            (
                "adaptive_noise_sensors",
                ("gnss", "gnss_velocity", "gnss_heading", "magnetometer", "pose"),
            ),
            ("strong_tracking_sensors", blocks),
        ):
            names = getattr(self, key)
            if not isinstance(names, list) or not all(
                isinstance(n, str) and (n in allowed or (n.startswith("pose:") and len(n) > 5))
                for n in names
            ):
                raise ValueError(
                    f"config key '{key}' must be a list of {', '.join(allowed)} or "
                    f"'pose:<name>', got {names!r}"
                )
        if not 0.0 < self.adaptive_forgetting < 1.0:
            raise ValueError("config key 'adaptive_forgetting' must lie in (0, 1)")
        if not 0.0 < self.adaptive_clip_probability <= 1.0:
            raise ValueError("config key 'adaptive_clip_probability' must lie in (0, 1]")
        if not self.strong_tracking_max_factor >= 1.0:
            raise ValueError("config key 'strong_tracking_max_factor' must be >= 1")
        self._require_numbers(
            (
                "adaptive_noise_floor",
                "strong_tracking_softening",
            ),
            positive=True,
        )
        self._require_numbers(("adaptive_prior_samples",), positive=False)


_ZERO_SIGMA_ALLOWED = frozenset({"pose_source_accel_sigma_mps2"})
"""Sigma keys that may be 0 (the other ``*sigma*`` keys must be above 0)."""


def _config_error(document: YamlDocument | None, err: Exception, keys: Iterable[str]) -> ValueError:
    """A validation error located at the line of the first key it names (when read from a
    file), else the error with the file prefixed."""
    if document is None:
        return ValueError(str(err))
    bad = named_key(err, keys)
    if bad is None:
        return DataError(document.path, str(err))
    return document.error(str(err), bad)


def read_config_keys(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a front-end YAML config as written (the ``smoother:``
    section included), read with :func:`msf_torch.io.yaml_files.read_yaml`.

    Use its keys as ``explicit`` in :func:`config_for_sequence`, so a dataset's metadata
    does not replace what the file sets::

        cfg = config_for_sequence(load_config(path), seq.meta, set(read_config_keys(path)))

    Raises:
        DataError: the file is unreadable, not YAML, has a key twice, or is not a mapping.
    """
    return dict(_read_mapping(path).data)


def _read_mapping(path: str | Path) -> YamlDocument:
    """The YAML document of a config file whose top level is a mapping (empty: ``{}``)."""
    document = read_yaml(path, "front-end config")
    if document.data is None:
        document.data = {}
    if not isinstance(document.data, dict):
        raise DataError(document.path, "the config must be a mapping of keys to values")
    return document


def load_config(path: str | Path | None = None, **overrides: Any) -> EskfConfig:
    """Read an :class:`EskfConfig` from YAML (:func:`msf_torch.io.yaml_files.read_yaml`:
    YAML 1.2 numbers and booleans), then apply ``overrides``.

    A ``smoother:`` mapping belongs to the back end
    (``msf_torch.backend.window.load_smoother_config``) and is skipped here.

    Raises:
        DataError: (a ``ValueError``) naming the file, line and key: an unknown key (with
            the closest known ones), a bad value, a YAML syntax error, a key given twice.
        ValueError: a bad key or value in ``overrides``.
    """
    values: dict[str, Any] = {}
    document = None
    if path is not None:
        document = _read_mapping(path)
        values.update(document.data)
    values.update(overrides)
    values.pop("smoother", None)
    known = {f.name for f in dataclasses.fields(EskfConfig)}
    for key in values:
        if key not in known:
            problem = f"unknown config key '{key}'{did_you_mean(key, known)}"
            if document is None or key in overrides:
                raise ValueError(problem)
            raise document.error(problem, key)
    try:
        config = EskfConfig(**values)
        config.validate()
    except (TypeError, ValueError) as err:
        raise _config_error(document, err, values) from None
    return config


_NOISE_FROM_META = {
    "gyro_noise_sigma": "gyro_noise_density",
    "accel_noise_sigma": "accel_noise_density",
    "gyro_bias_rw_sigma": "gyro_bias_rw_density",
    "accel_bias_rw_sigma": "accel_bias_rw_density",
}


def config_for_sequence(config: EskfConfig, meta: dict[str, Any], explicit: set[str]) -> EskfConfig:
    """Fill IMU noise densities and sensor geometry from a dataset's metadata.

    ``meta`` is ``Sequence.meta`` (B = 1); values come from ``meta["imu_noise"]`` (dataset
    files such as KITTI's metadata) and ``meta["sensor"]`` (native ``meta.json`` / the
    simulator: IMU noise, wheel track, GNSS sigma, and the lever arms and antenna baseline
    of ``io.native.GEOMETRY_KEYS``); ``meta["platform"] == "aerial"`` (EuRoC's MAV) turns
    the non-holonomic constraint off (``nhc: auto`` would apply it to any run without
    wheels). Keys in ``explicit`` (set by the user's YAML or CLI; a YAML's are
    ``set(read_config_keys(path))``) are left alone.
    """
    changes: dict[str, Any] = {}
    imu_noise = meta.get("imu_noise") or meta.get("sensor", {}).get("imu_noise") or {}
    for meta_key, cfg_key in _NOISE_FROM_META.items():
        if meta_key in imu_noise and cfg_key not in explicit:
            changes[cfg_key] = float(imu_noise[meta_key])
    for cfg_key in (
        "gyro_noise_density",
        "accel_noise_density",
        "gyro_bias_rw_density",
        "accel_bias_rw_density",
    ):
        if cfg_key in imu_noise and cfg_key not in explicit:
            changes[cfg_key] = float(imu_noise[cfg_key])
    if meta.get("platform") == "aerial" and "nhc" not in explicit:
        changes["nhc"] = "off"  # an aerial vehicle slides sideways: no wheels, no constraint
    sensor = meta.get("sensor", {})
    if "wheel_track_m" in sensor and "wheel_track_m" not in explicit:
        changes["wheel_track_m"] = float(sensor["wheel_track_m"])
    for key in GEOMETRY_KEYS:  # lever arms and baseline, m, body axes
        if key in sensor and key not in explicit:
            changes[key] = [float(x) for x in sensor[key]]
    if "gnss_sigma_m" in sensor and "gnss_sigma_m" not in explicit:
        sigma = sensor["gnss_sigma_m"]
        changes["gnss_sigma_m"] = (
            [float(s) for s in sigma] if isinstance(sigma, list) else [float(sigma)] * 3
        )
    return config.replace(**changes) if changes else config


def load_sequence_config(
    meta: dict[str, Any], path: str | Path | None = None, **overrides: Any
) -> EskfConfig:
    """The front-end config for a sequence: :func:`load_config` of ``path`` (None:
    defaults) with ``overrides``, then :func:`config_for_sequence` filling what neither
    the file nor ``overrides`` sets from the sequence's metadata (``Sequence.meta``, e.g.
    the IMU noise of a dataset) -- what ``msf run --config`` does.

    Example:
        >>> cfg = load_sequence_config(seq.meta, "my_robot.yaml")  # doctest: +SKIP
    """
    explicit = set(overrides)
    if path is not None:
        explicit |= set(read_config_keys(path))
    return config_for_sequence(load_config(path, **overrides), meta, explicit)


def packaged_config(name: str) -> Path | None:
    """Path of the config shipped for a named dataset (``msf_torch/configs/NAME.yaml``), if any."""
    path = Path(__file__).resolve().parent.parent / "configs" / f"{name}.yaml"
    return path if path.is_file() else None


def _det3(m: list[float]) -> float:
    """Determinant of a 3 x 3 matrix given as 9 numbers, row by row."""
    return (
        m[0] * (m[4] * m[8] - m[5] * m[7])
        - m[1] * (m[3] * m[8] - m[5] * m[6])
        + m[2] * (m[3] * m[7] - m[4] * m[6])
    )
