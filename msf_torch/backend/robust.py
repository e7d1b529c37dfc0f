"""Robust kernels (M-estimators) applied per factor, in GTSAM's convention.

A factor's whitened residual ``e`` (..., R) has squared norm ``s = |e|^2``. Without a kernel
its cost is ``s / 2``; with a kernel of scale ``k`` it is ``rho(|e|)``, where ``rho`` equals
``s / 2`` near zero. The least-squares solver applies a kernel by iteratively re-weighted
least squares: residual and Jacobian rows are scaled by ``sqrt(w(|e|))`` with
``w = rho'(|e|) / |e|``, which has the same gradient as ``rho`` (GTSAM's
``noiseModel::Robust`` does the same).

=============== ========================================= ==============================
kernel          rho(e)                                    w(e)
=============== ========================================= ==============================
huber           e^2/2 (|e|<=k); k|e| - k^2/2              1; k/|e|
cauchy          k^2/2 log(1 + e^2/k^2)                    1 / (1 + e^2/k^2)
geman_mcclure   k^2 e^2 / (2 (k^2 + e^2))                 k^4 / (k^2 + e^2)^2
tukey           k^2/6 (1 - (1 - e^2/k^2)^3) (|e|<=k); k^2/6   (1 - e^2/k^2)^2; 0
=============== ========================================= ==============================
"""

from __future__ import annotations

__all__ = ["KERNELS", "RobustKernel"]

from dataclasses import dataclass

import torch

KERNELS = ("huber", "cauchy", "geman_mcclure", "tukey")


@dataclass(frozen=True)
class RobustKernel:
    """A named M-estimator with its scale ``k`` (in whitened units, i.e. sigmas).

    Attributes:
        name: one of :data:`KERNELS`.
        scale: ``k`` > 0.
    """

    name: str
    scale: float

    def __post_init__(self) -> None:
        if self.name not in KERNELS:
            raise ValueError(f"unknown robust kernel {self.name!r}; choose one of {KERNELS}")
        if not self.scale > 0:
            raise ValueError(f"robust kernel scale must be > 0, got {self.scale}")

    def loss(self, squared_norm: torch.Tensor) -> torch.Tensor:
        """``rho(sqrt(s))`` (...,) for squared whitened norms ``s`` (...,)."""
        k2 = self.scale**2
        s = squared_norm
        if self.name == "huber":
            e = torch.sqrt(s.clamp_min(k2))
            return torch.where(s <= k2, 0.5 * s, self.scale * e - 0.5 * k2)
        if self.name == "cauchy":
            return 0.5 * k2 * torch.log1p(s / k2)
        if self.name == "geman_mcclure":
            return 0.5 * k2 * s / (k2 + s)
        inside = 1.0 - (1.0 - s.clamp_max(k2) / k2) ** 3
        return k2 / 6.0 * inside

    def weight(self, squared_norm: torch.Tensor) -> torch.Tensor:
        """IRLS weight ``w = rho'(e) / e`` (...,) for squared whitened norms ``s`` (...,)."""
        k2 = self.scale**2
        s = squared_norm
        if self.name == "huber":
            return torch.where(
                s <= k2, torch.ones_like(s), self.scale / torch.sqrt(s.clamp_min(k2))
            )
        if self.name == "cauchy":
            return 1.0 / (1.0 + s / k2)
        if self.name == "geman_mcclure":
            return k2 * k2 / (k2 + s) ** 2
        return torch.where(s <= k2, (1.0 - s / k2) ** 2, torch.zeros_like(s))
