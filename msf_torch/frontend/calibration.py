"""Online calibration states appended to the ESKF error state.

With ``EskfConfig.calibrate_wheels`` and/or ``calibrate_time_offsets`` the error state grows
from 15 to ``15 + n`` entries, in this order:

* ``wheel_radius_ratio_left``, ``wheel_radius_ratio_right``: true / nominal wheel radius
  (dimensionless; the encoder readings are rim speeds at the nominal radius), start at
  ``calibration_wheel_radius_ratio``;
* ``wheel_track_m``: track width, starts at ``wheel_track_m``;
* ``time_offset_s:<sensor>``: one per entry of ``calibrate_time_offsets`` (``"gnss"``,
  ``"pose:<name>"``), starts at ``calibration_time_offset_s`` (default 0).

Each is a random walk (``calibration_*_rw_density``) with a Gaussian prior
(``calibration_*_sigma``), additive error (``k = k_hat + dk``), and enters only the
measurement models of ``sensors.calibration``; the propagation leaves it unchanged. The
calibration block needs no invariant-coordinate change, so the ESKF appends it to its
right-invariant covariance as is.
"""

from __future__ import annotations

__all__ = ["CalibrationLayout", "WHEEL_STATES"]

from dataclasses import dataclass

import torch

from msf_torch.frontend.config import EskfConfig

WHEEL_STATES = ("wheel_radius_ratio_left", "wheel_radius_ratio_right", "wheel_track_m")
_TIME_PREFIX = "time_offset_s:"


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
    """

    names: tuple[str, ...]
    initial: torch.Tensor
    prior_sigma: torch.Tensor
    rw_density: torch.Tensor
    wheels: bool
    time_offset_index: dict[str, int]

    @classmethod
    def from_config(
        cls, cfg: EskfConfig, sensors: tuple[str, ...], dtype=torch.float64, device=None
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
        if not names:
            return None

        def t(values: list[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=dtype, device=device)

        return cls(tuple(names), t(initial), t(sigma), t(walk), cfg.calibrate_wheels, index)

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
