"""Gaussian noise models with unit-named constructors and whitening.

A noise model holds a covariance ``Sigma`` (..., D, D). Constructors say which unit they
take (standard deviations, variances or square-root information), so sigma/variance
mix-ups cannot pass silently. The ESKF uses ``covariance``; a least-squares back end uses
``whiten`` (``L^-1 r`` with ``Sigma = L L^T``), so both consumers share one object.
"""

from __future__ import annotations

__all__ = ["GaussianNoise"]

from dataclasses import dataclass

import torch


@dataclass
class GaussianNoise:
    """Zero-mean Gaussian noise with covariance ``covariance`` (..., D, D)."""

    covariance: torch.Tensor

    @classmethod
    def from_sigmas(cls, sigmas: torch.Tensor) -> GaussianNoise:
        """Diagonal model from standard deviations (..., D), in the measurement's units."""
        return cls(torch.diag_embed(sigmas * sigmas))

    @classmethod
    def from_variances(cls, variances: torch.Tensor) -> GaussianNoise:
        """Diagonal model from variances (..., D), in squared measurement units."""
        return cls(torch.diag_embed(variances))

    @classmethod
    def from_covariance(cls, covariance: torch.Tensor) -> GaussianNoise:
        """Full model from a covariance (..., D, D)."""
        return cls(covariance)

    @classmethod
    def from_sqrt_information(cls, sqrt_information: torch.Tensor) -> GaussianNoise:
        """Full model from a square-root information matrix ``W`` (..., D, D),
        ``Sigma^-1 = W^T W``."""
        information = sqrt_information.mT @ sqrt_information
        return cls(torch.linalg.inv(information))

    @property
    def dim(self) -> int:
        """D."""
        return self.covariance.shape[-1]

    def whiten(self, residual: torch.Tensor) -> torch.Tensor:
        """Whitened residual ``L^-1 r`` (..., D) with ``Sigma = L L^T``; its squared norm is the
        Mahalanobis distance ``r^T Sigma^-1 r``."""
        chol = torch.linalg.cholesky(self.covariance)
        return torch.linalg.solve_triangular(chol, residual.unsqueeze(-1), upper=False).squeeze(-1)

    def mahalanobis2(self, residual: torch.Tensor) -> torch.Tensor:
        """``r^T Sigma^-1 r`` (...,)."""
        white = self.whiten(residual)
        return (white * white).sum(-1)
