"""Online calibration states appended to the ESKF error state.

With ``EskfConfig.calibrate_wheels`` and/or ``calibrate_time_offsets`` the error state grows
from 15 to ``15 + n`` entries, in this order:

* ``wheel_radius_ratio_left``, ``wheel_radius_ratio_right``: true / nominal wheel radius
  (dimensionless; the encoder readings are rim speeds at the nominal radius), start at
  ``calibration_wheel_radius_ratio``;
* ``wheel_track_m``: track width, starts at ``wheel_track_m``;
* ``time_offset_s:<sensor>``: one per entry of ``calibrate_time_offsets`` (``"gnss"``,
  ``"pose:<name>"``), starts at ``calibration_time_offset_s`` (default 0);
* ``lever_arm_m:gnss:{x,y,z}`` (``calibrate_gnss_lever_arm``): the GNSS antenna lever arm in
  the body frame, starts at ``gnss_lever_arm_m``;
* per entry ``"pose:<name>"`` of ``calibrate_pose_extrinsics``: ``lever_arm_m:pose:<name>:
  {x,y,z}`` (the source's origin in the body frame) and ``rotation_rad:pose:<name>:{x,y,z}``
  (its mounting rotation sensor -> body as a rotation vector), start at
  ``calibration_pose_lever_arm_m`` / ``calibration_pose_rotation_rad`` (default 0);
* ``rotation_rad:imu_body:{x,y,z}`` (``calibrate_imu_body_rotation``): the rotation vehicle
  -> body (IMU) of the wheel and non-holonomic models, starts at
  ``calibration_imu_body_rotation_rad``;
* ``heading_offset_rad:gnss_heading`` (``calibrate_gnss_heading_offset``, runs with
  dual-antenna headings): the turn about body z of the antenna baseline
  (``sensors.calibration.heading_offset_residual``), starts at
  ``calibration_gnss_heading_offset_rad``, prior sigma ``calibration_rotation_sigma_rad``;
* ``declination_rad:magnetometer`` (``calibrate_magnetometer_declination``, runs with a
  magnetometer): the azimuth of magnetic north the heading residual compares with
  (``r = wrap(azimuth(R f) - D)``, ``dr/dD = -1``), starts at
  ``magnetometer_declination_rad``, prior sigma
  ``calibration_magnetometer_declination_sigma_rad``, walk
  ``calibration_rotation_rw_density``. Observable wherever another heading reference
  (GNSS track through motion, dual-antenna heading) is.

Each is a random walk (``calibration_*_rw_density``) with a Gaussian prior
(``calibration_*_sigma``), additive error (``k = k_hat + dk``; the rotations: right error
``M = M_hat Exp(dphi)``, their estimates reported as rotation vectors), and enters only the
measurement models of ``sensors.calibration``; the propagation leaves it unchanged. The
calibration block needs no invariant-coordinate change, so the ESKF appends it to its
right-invariant covariance as is.

Observability. A state is flagged observable on a run (:func:`observability`) when its
variance has fallen below ``calibration_observable_ratio`` (0.25: its sigma halved) of the
variance it would have without measurements, ``sigma_0^2 + q^2 (t - t_0)``. Directions the
run does not excite (a pose source's vertical lever arm without roll or pitch rates, the
roll of the IMU-to-vehicle rotation on level ground) keep their prior and are flagged.
"""

from __future__ import annotations

__all__ = ["CalibrationLayout", "CalibrationMemory", "WHEEL_STATES", "observability"]

from dataclasses import dataclass, field

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.geometry import so3

WHEEL_STATES = ("wheel_radius_ratio_left", "wheel_radius_ratio_right", "wheel_track_m")
_TIME_PREFIX = "time_offset_s:"
_AXES = ("x", "y", "z")


@dataclass
class CalibrationMemory:
    """The calibration states at the last epoch of a chunk, for the next chunk's ``run_eskf``
    (``EskfResult.calibration_memory``), so a run filtered in chunks calibrates as one run.

    Attributes:
        names: the n state names (the next chunk's layout must have the same).
        value: (B, n) estimates (units in the names).
        covariance: (B, 15 + n, 15 + n) joint covariance of the conventional navigation
            error and the calibration errors (drifting source frames left out).
    """

    names: tuple[str, ...]
    value: torch.Tensor
    covariance: torch.Tensor


@dataclass
class CalibrationLayout:
    """Which calibration states a run carries, where, and their priors.

    Attributes:
        names: the n state names, in error-state order after the 15 navigation entries.
        initial: (n,) initial values (units in the names).
        prior_sigma: (n,) initial 1-sigma.
        rw_density: (n,) random-walk density, unit per sqrt(s).
        wheels: the three wheel states are present (columns 0-2).
        time_offset_index: sensor key (``"gnss"``, ``"pose:<name>"``) -> column.
        gnss_lever_index: first of the three GNSS lever-arm columns, or None.
        pose_extrinsic_index: ``"pose:<name>"`` -> first column of its lever arm (3), then
            its mounting rotation (3).
        imu_body_index: first of the three IMU-to-vehicle rotation columns, or None.
        heading_offset_index: the dual-antenna heading offset's column, or None.
        declination_index: the magnetometer declination's column, or None.
        rotation_index: first columns of every rotation triplet (right error, composed on
            injection).
    """

    names: tuple[str, ...]
    initial: torch.Tensor
    prior_sigma: torch.Tensor
    rw_density: torch.Tensor
    wheels: bool
    time_offset_index: dict[str, int]
    gnss_lever_index: int | None = None
    pose_extrinsic_index: dict[str, int] = field(default_factory=dict)
    imu_body_index: int | None = None
    rotation_index: tuple[int, ...] = ()
    heading_offset_index: int | None = None
    declination_index: int | None = None

    @classmethod
    def from_config(
        cls,
        cfg: EskfConfig,
        sensors: tuple[str, ...],
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> CalibrationLayout | None:
        """Layout for the switches in ``cfg`` (None when all are off).

        Args:
            cfg: the filter settings.
            sensors: result keys of the run (``"gnss"``, ``"pose:<name>"``, ...); a time
                offset listed for a sensor the run does not have is skipped.
        """
        names: list[str] = []
        initial: list[float] = []
        sigma: list[float] = []
        walk: list[float] = []
        if cfg.calibrate_wheels:
            names += list(WHEEL_STATES)
            initial += [*map(float, cfg.calibration_wheel_radius_ratio), float(cfg.wheel_track_m)]
            sigma += [cfg.calibration_wheel_radius_sigma] * 2
            sigma.append(cfg.calibration_wheel_track_sigma_m)
            walk += [cfg.calibration_wheel_rw_density] * 2
            walk.append(cfg.calibration_wheel_track_rw_density)
        index = {}
        for sensor in cfg.calibrate_time_offsets:
            if sensor not in sensors:
                continue
            index[sensor] = len(names)
            names.append(_TIME_PREFIX + sensor)
            initial.append(float(cfg.calibration_time_offset_s.get(sensor, 0.0)))
            sigma.append(cfg.calibration_time_offset_sigma_s)
            walk.append(cfg.calibration_time_offset_rw_density)
        rotations: list[int] = []

        def add(prefix: str, start: list[float], rotation: bool) -> int:
            column = len(names)
            names.extend(f"{prefix}:{axis}" for axis in _AXES)
            initial.extend(float(x) for x in start)
            if rotation:
                rotations.append(column)
                sigma.extend([cfg.calibration_rotation_sigma_rad] * 3)
                walk.extend([cfg.calibration_rotation_rw_density] * 3)
            else:
                sigma.extend([cfg.calibration_lever_arm_sigma_m] * 3)
                walk.extend([cfg.calibration_lever_arm_rw_density] * 3)
            return column

        gnss_lever = None
        if cfg.calibrate_gnss_lever_arm and "gnss" in sensors:
            gnss_lever = add("lever_arm_m:gnss", list(cfg.gnss_lever_arm_m), False)
        extrinsic = {}
        for sensor in cfg.calibrate_pose_extrinsics:
            if sensor not in sensors:
                continue
            extrinsic[sensor] = add(
                "lever_arm_m:" + sensor,
                cfg.calibration_pose_lever_arm_m.get(sensor, [0.0] * 3),
                False,
            )
            add(
                "rotation_rad:" + sensor,
                cfg.calibration_pose_rotation_rad.get(sensor, [0.0] * 3),
                True,
            )
        imu_body = None
        if cfg.calibrate_imu_body_rotation:
            imu_body = add(
                "rotation_rad:imu_body", list(cfg.calibration_imu_body_rotation_rad), True
            )

        def angle(name: str, start: float, prior_sigma: float) -> int:
            """One angle state (rad) walking like the rotations; its column."""
            names.append(name)
            initial.append(float(start))
            sigma.append(prior_sigma)
            walk.append(cfg.calibration_rotation_rw_density)
            return len(names) - 1

        heading_offset = None
        if cfg.calibrate_gnss_heading_offset and "gnss_heading" in sensors:
            heading_offset = angle(
                "heading_offset_rad:gnss_heading",
                cfg.calibration_gnss_heading_offset_rad,
                cfg.calibration_rotation_sigma_rad,
            )
        declination = None
        if cfg.calibrate_magnetometer_declination and "magnetometer" in sensors:
            declination = angle(
                "declination_rad:magnetometer",
                cfg.magnetometer_declination_rad,
                cfg.calibration_magnetometer_declination_sigma_rad,
            )
        if not names:
            return None

        def t(values: list[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=dtype, device=device)

        return cls(
            tuple(names),
            t(initial),
            t(sigma),
            t(walk),
            cfg.calibrate_wheels,
            index,
            gnss_lever,
            extrinsic,
            imu_body,
            tuple(rotations),
            heading_offset,
            declination,
        )

    @property
    def size(self) -> int:
        """n, the number of calibration states."""
        return len(self.names)

    def prior_covariance(self, batch: int) -> torch.Tensor:
        """(B, n, n) diagonal prior covariance."""
        return torch.diag_embed(self.prior_sigma**2).expand(batch, self.size, self.size)

    def process_noise(self, delta_t: torch.Tensor) -> torch.Tensor:
        """(B, n, n) random-walk covariance over epochs of length ``delta_t`` (B,) s."""
        return torch.diag_embed(self.rw_density**2 * delta_t[:, None])

    def rotation_matrix(self, values: torch.Tensor, column: int) -> torch.Tensor:
        """(B, 3, 3) rotation of the triplet starting at ``column`` of ``values`` (B, n)."""
        return so3.exp(values[:, column : column + 3])

    def inject(self, values: torch.Tensor, correction: torch.Tensor) -> torch.Tensor:
        """Estimates (B, n) after a correction ``correction`` (B, n): added, except the
        rotation triplets, ``Log(Exp(phi) Exp(dphi))``."""
        updated = values + correction
        if not self.rotation_index:
            return updated
        parts = list(updated.unbind(-1))
        for column in self.rotation_index:
            block = slice(column, column + 3)
            composed = so3.log(so3.exp(values[:, block]) @ so3.exp(correction[:, block]))
            parts[column : column + 3] = composed.unbind(-1)
        return torch.stack(parts, -1)


def observability(
    layout: CalibrationLayout,
    variance: torch.Tensor,
    elapsed_s: torch.Tensor,
    threshold: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Information gained on each calibration state, and whether that makes it observable.

    Args:
        layout: the run's calibration states.
        variance: (B, ..., n) their posterior variances.
        elapsed_s: (B, ...) time since the start, s.
        threshold: ``calibration_observable_ratio``.
    Returns:
        ratio (B, ..., n): posterior variance over ``sigma_0^2 + q^2 elapsed`` (the variance
        without measurements; 1 = nothing learned), and observable (B, ..., n) bool:
        ``ratio < threshold``.
    """
    unobserved = layout.prior_sigma**2 + layout.rw_density**2 * elapsed_s[..., None]
    ratio = variance / unobserved
    return ratio, ratio < threshold
