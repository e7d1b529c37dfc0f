"""Normalised estimation error squared (NEES) and its chi-square consistency test.

For an estimator that reports covariance ``P`` of its error ``e`` (D-dimensional), a consistent
filter has ``NEES = e^T P^-1 e ~ chi2(D)``. Averaged over ``n_runs`` independent Monte-Carlo
runs, ``n_runs * ANEES ~ chi2(D * n_runs)``, so the average NEES should lie in
``[chi2.ppf((1 - prob) / 2, D n_runs), chi2.ppf((1 + prob) / 2, D n_runs)] / n_runs`` with
probability ``prob``.

Reference: Y. Bar-Shalom, X. R. Li, T. Kirubarajan, *Estimation with Applications to Tracking
and Navigation*, 2001, sec. 5.4.2.
"""

from __future__ import annotations

__all__ = [
    "nees",
    "average_nees",
    "chi2_interval",
    "fraction_inside",
    "navigation_errors",
]

import torch
from scipy import stats

from msf_torch.geometry import so3
from msf_torch.geometry.invariant import invariant_difference, invariant_maps
from msf_torch.types import NavState


def nees(
    error: torch.Tensor, covariance: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """``e^T P^-1 e`` per sample, by a Cholesky solve (no explicit inverse).

    Args:
        error: (B, N, D) estimation error (estimate minus truth, in the state's units; for a
            rotation the error-state ``dtheta`` in rad).
        covariance: (B, N, D, D) symmetric positive-definite covariance of that error.
        mask: (B, N) bool, True where the sample is real; None means all. Masked samples
            are not factorised (their covariance may be zeros) and get NEES 0.

    Returns:
        (B, N) NEES, dimensionless.

    Raises:
        ValueError: shapes disagree, or a real sample's covariance is not positive definite
            (the message names the first such (b, n)).

    Example:
        >>> value = nees(x_hat - x_true, P, mask)  # doctest: +SKIP
    """
    if error.dim() != 3 or covariance.shape != (*error.shape, error.shape[-1]):
        raise ValueError(
            f"nees needs error (B, N, D) and covariance (B, N, D, D); got {tuple(error.shape)} "
            f"and {tuple(covariance.shape)}"
        )
    if mask is None:
        mask = torch.ones(error.shape[:2], dtype=torch.bool, device=error.device)
    if mask.shape != error.shape[:2]:
        raise ValueError(f"mask must be {tuple(error.shape[:2])}, got {tuple(mask.shape)}")
    dim = error.shape[-1]
    eye = torch.eye(dim, dtype=covariance.dtype, device=covariance.device)
    cov = torch.where(mask[..., None, None], covariance, eye)
    chol, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        b, n = torch.nonzero(info != 0)[0].tolist()
        raise ValueError(
            f"covariance at (b={b}, n={n}) is not positive definite (Cholesky failed at "
            f"minor {int(info[b, n])})"
        )
    err = torch.where(mask[..., None], error, torch.zeros_like(error))
    white = torch.linalg.solve_triangular(chol, err[..., None], upper=False)[..., 0]
    return (white * white).sum(-1)


def navigation_errors(
    truth: NavState,
    estimate: NavState,
    covariance: torch.Tensor,
    coordinates: str = "invariant",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 15-dim error of a navigation estimate and its covariance, ready for :func:`nees`.

    ``"conventional"``: ``[p - p_hat, v - v_hat, Log(R_hat^T R), b_g - b_g_hat,
    b_a - b_a_hat]`` against the reported covariance (``geometry.conventions``).
    ``"invariant"``: the exact right-invariant error ``geometry.invariant.invariant_difference``
    (truth against estimate) with the bias differences, against ``T^-1 P T^-T``: the
    coordinates the front end keeps its covariance in. Both agree to first order; where the
    filter knows a combination very precisely (a wheel's lateral velocity) the second-order
    part of the conventional error (``|v| psi^2 / 2`` for a heading error ``psi``) can exceed
    that precision, so only the invariant form tests the filter's own claim exactly.

    Args:
        truth, estimate: NavState with (B, N, ...) fields (SI units).
        covariance: (B, N, 15, 15) the estimator's conventional covariance.
        coordinates: ``"invariant"`` or ``"conventional"``.

    Returns:
        error (B, N, 15) and covariance (B, N, 15, 15), symmetric.
    """
    bias = torch.cat(
        (truth.gyro_bias - estimate.gyro_bias, truth.accel_bias - estimate.accel_bias), -1
    )
    if coordinates == "conventional":
        nav = torch.cat(
            (
                truth.position - estimate.position,
                truth.velocity - estimate.velocity,
                so3.log(estimate.rotation.mT @ truth.rotation),
            ),
            -1,
        )
        return torch.cat((nav, bias), -1), covariance
    if coordinates != "invariant":
        raise ValueError(f"coordinates must be 'invariant' or 'conventional', got {coordinates!r}")
    nav = invariant_difference(
        truth.position,
        truth.velocity,
        truth.rotation,
        estimate.position,
        estimate.velocity,
        estimate.rotation,
    )
    lead = covariance.shape[:-2]
    _, to_inv = invariant_maps(
        estimate.position.reshape(-1, 3),
        estimate.velocity.reshape(-1, 3),
        estimate.rotation.reshape(-1, 3, 3),
    )
    flat = covariance.reshape(-1, *covariance.shape[-2:])
    mapped = (to_inv @ flat @ to_inv.mT).reshape(*lead, *covariance.shape[-2:])
    return torch.cat((nav, bias), -1), 0.5 * (mapped + mapped.mT)


def average_nees(values: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Average NEES over runs: (R, N) per-run NEES -> (N,) ANEES.

    Args:
        values: (R, N) NEES of R Monte-Carlo runs on a common time grid.
        mask: (R, N) bool; a step averages only its real runs. None means all.

    Returns:
        (N,) mean over runs; NaN at a step where no run is real.
    """
    if values.dim() != 2:
        raise ValueError(f"values must be (R, N), got {tuple(values.shape)}")
    if mask is None:
        return values.mean(0)
    weight = mask.to(values.dtype)
    total = torch.where(mask, values, torch.zeros_like(values)).sum(0)
    count = weight.sum(0)
    nan = torch.full_like(total, float("nan"))
    return torch.where(count > 0, total / count.clamp_min(1.0), nan)


def chi2_interval(dof: int, n_runs: int = 1, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` acceptance interval of the NEES averaged over ``n_runs`` runs.

    ``(chi2.ppf((1 - prob) / 2, dof n_runs), chi2.ppf((1 + prob) / 2, dof n_runs)) / n_runs``.

    Args:
        dof: state dimension D of one NEES value.
        n_runs: number of independent runs averaged (1 for a single NEES value).
        prob: probability mass inside the interval, in (0, 1).

    Returns:
        ``(low, high)``, dimensionless.

    Example:
        >>> chi2_interval(3, n_runs=50)  # doctest: +ELLIPSIS
        (2.359..., 3.716...)
    """
    if dof < 1 or n_runs < 1:
        raise ValueError(f"dof and n_runs must be >= 1, got dof={dof}, n_runs={n_runs}")
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob must be in (0, 1), got {prob}")
    k = dof * n_runs
    low = float(stats.chi2.ppf(0.5 * (1.0 - prob), k)) / n_runs
    high = float(stats.chi2.ppf(0.5 * (1.0 + prob), k)) / n_runs
    return low, high


def fraction_inside(
    nees_values: torch.Tensor,
    dof: int,
    n_runs: int = 1,
    prob: float = 0.95,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Fraction of (average) NEES values inside :func:`chi2_interval` ``(dof, n_runs, prob)``.

    A consistent estimator gives a fraction near ``prob``.

    Args:
        nees_values: (..., N) NEES values, each an average over ``n_runs`` runs (use
            :func:`average_nees`) or single-run values with ``n_runs = 1``.
        dof: state dimension D.
        n_runs: runs averaged in each value.
        prob: interval probability.
        mask: (..., N) bool, True where a value counts; None means all (NaN values never
            count).

    Returns:
        (...,) fraction in [0, 1] over the last axis (NaN where nothing counts).
    """
    low, high = chi2_interval(dof, n_runs, prob)
    valid = ~torch.isnan(nees_values)
    if mask is not None:
        if mask.shape != nees_values.shape:
            raise ValueError(f"mask must be {tuple(nees_values.shape)}, got {tuple(mask.shape)}")
        valid = valid & mask
    inside = (nees_values >= low) & (nees_values <= high) & valid
    dtype = nees_values.dtype if nees_values.is_floating_point() else torch.float64
    return inside.to(dtype).sum(-1) / valid.to(dtype).sum(-1)
