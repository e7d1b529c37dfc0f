"""Chi-square innovation gating.

A measurement block with residual ``r`` and innovation covariance ``S = H P H^T + R`` passes
when its normalised innovation squared ``NIS = r^T S^-1 r`` lies below the chi-square
quantile of its dimension at the configured probability.
"""

from __future__ import annotations

__all__ = ["chi2_threshold", "normalized_innovation"]

import math

import torch
from scipy.stats import chi2


def chi2_threshold(dof: int, probability: float) -> float:
    """Chi-square quantile for ``dof`` at ``probability`` (inf when probability is 1)."""
    if probability >= 1.0:
        return math.inf
    return float(chi2.ppf(probability, dof))


def normalized_innovation(residual: torch.Tensor, innovation_cov: torch.Tensor) -> torch.Tensor:
    """``r^T S^-1 r`` (...,) for residual (..., m) and covariance (..., m, m)."""
    chol = torch.linalg.cholesky(innovation_cov)
    white = torch.linalg.solve_triangular(chol, residual[..., None], upper=False)
    return (white * white).sum((-2, -1))
