"""Adaptive noise: strong-tracking fading factor and Sage-Husa measurement-noise estimation.

Both track the innovation ``nu_k`` (measurement minus prediction; the sign does not matter
here, only ``nu nu^T`` enters) with exponential forgetting. With forgetting factor
``b`` (0 < b < 1; 0.95-0.99 in practice) the ``k``-th sample (0-based) of a stream is mixed
in with weight

    d_k = (1 - b) / (1 - b^(k + 1 + k0)),

so that after ``n`` samples the estimate is the exponentially weighted mean
``sum_j b^(n-1-j) X_j / sum_j b^(n-1-j)`` of the samples, with a prior worth ``k0``
samples in front (``k0 = 0``: the first sample replaces the prior; :func:`forgetting_weight`).

Strong tracking (Zhou & Frank 1996; the "suboptimal fading factor"): the innovation
covariance is estimated as ``V_k`` (:func:`update_innovation_covariance`), and with
``M = H Phi P Phi^T H^T`` (the predicted covariance seen by the measurement before process
noise) and ``N = V - H Q H^T - beta R`` the fading factor

    lambda = max(1, tr N / tr M)

inflates the predicted covariance, ``P^- = lambda Phi P Phi^T + Q`` (:func:`fading_factor`).
When the filter's model matches, ``E[V] = H P^- H^T + R`` and lambda stays near 1; a
model mismatch (an unmodelled manoeuvre, a jump) makes the innovations larger than the
filter believes, and lambda > 1 makes it forget the past faster.

Sage-Husa (Sage & Husa 1969) estimates the measurement-noise covariance from
``E[nu nu^T] = H P^- H^T + R``:

    R_k = (1 - d_k) R_(k-1) + d_k (nu nu^T - H P^- H^T)

(:func:`sage_husa_update`). The bracket is indefinite for a single sample, so ``R_k`` can
lose positive definiteness; it is projected back onto ``{R : eig(R) >= r_min}``
(:func:`project_positive_definite`, the Frobenius-nearest such matrix), only where needed.

Outliers: a single gross innovation would inflate ``V`` or ``R`` for ``1 / (1 - b)``
samples. With ``max_nis`` the outer product ``nu nu^T`` is scaled by
``min(1, max_nis / NIS)``, ``NIS = nu^T S^-1 nu`` against the innovation covariance ``S``
the filter used, so one sample can move the estimate by at most ``max_nis`` "sigmas
squared" (a robust, Huber-like clip); a real, lasting change still drives the estimate up
geometrically, by up to a factor ``1 + d (max_nis / m - 1)`` per sample.

Everything is batched over leading dims, float64-ready and differentiable (the max and the
clip are piecewise smooth; the projection differentiates through ``eigh`` only where it
acts).
"""

from __future__ import annotations

__all__ = [
    "forgetting_weight",
    "clipped_outer",
    "update_innovation_covariance",
    "fading_factor",
    "project_positive_definite",
    "sage_husa_update",
]

import torch


def _check_forgetting(forgetting: float) -> None:
    if not 0.0 < forgetting < 1.0:
        raise ValueError(f"forgetting factor b must lie in (0, 1), got {forgetting!r}")


def forgetting_weight(
    count: torch.Tensor, forgetting: float, prior_count: float = 0.0
) -> torch.Tensor:
    """Mixing weight ``d_k = (1 - b) / (1 - b^(k + 1 + k0))`` of the ``k``-th sample.

    Args:
        count: (...) samples already mixed in (k, 0-based index of the new one).
        forgetting: b in (0, 1).
        prior_count: k0 >= 0, how many samples the prior is worth.
    Returns:
        (...) weights in (0, 1] (1 for the first sample when ``k0 = 0``).
    """
    _check_forgetting(forgetting)
    if prior_count < 0:
        raise ValueError(f"prior_count must be >= 0, got {prior_count!r}")
    exponent = count + 1.0 + prior_count
    return (1.0 - forgetting) / (1.0 - forgetting**exponent)


def clipped_outer(
    innovation: torch.Tensor,
    innovation_cov: torch.Tensor | None = None,
    max_nis: float | None = None,
) -> torch.Tensor:
    """``s nu nu^T`` with ``s = min(1, max_nis / (nu^T S^-1 nu))`` (``s = 1`` without a clip).

    Args:
        innovation: (..., m).
        innovation_cov: (..., m, m) S, needed when ``max_nis`` is given.
        max_nis: clip level (e.g. a chi-square gate), or None.
    Returns:
        (..., m, m).
    """
    outer = innovation[..., :, None] * innovation[..., None, :]
    if max_nis is None:
        return outer
    if innovation_cov is None:
        raise ValueError("clipped_outer: max_nis needs innovation_cov")
    chol = torch.linalg.cholesky(innovation_cov)
    white = torch.linalg.solve_triangular(chol, innovation[..., None], upper=False)
    nis = (white**2).sum((-2, -1))
    scale = torch.where(nis > max_nis, max_nis / nis.clamp_min(max_nis), 1.0)
    return outer * scale[..., None, None]


def update_innovation_covariance(
    previous: torch.Tensor,
    innovation: torch.Tensor,
    count: torch.Tensor,
    forgetting: float,
    innovation_cov: torch.Tensor | None = None,
    max_nis: float | None = None,
) -> torch.Tensor:
    """Exponentially faded innovation covariance ``V_k = (1 - d_k) V_(k-1) + d_k nu nu^T``.

    ``d_k`` from :func:`forgetting_weight` with no prior (the first sample sets ``V``).

    Args:
        previous: (..., m, m) ``V_(k-1)`` (ignored where ``count == 0``).
        innovation: (..., m) ``nu_k``.
        count: (...) samples already in ``V_(k-1)``.
        forgetting: b in (0, 1).
        innovation_cov, max_nis: optional outlier clip (:func:`clipped_outer`).
    Returns:
        (..., m, m) ``V_k``.
    """
    weight = forgetting_weight(count, forgetting)[..., None, None]
    sample = clipped_outer(innovation, innovation_cov, max_nis)
    return (1.0 - weight) * previous + weight * sample


def fading_factor(
    innovation_estimate: torch.Tensor,
    predicted: torch.Tensor,
    measurement_cov: torch.Tensor,
    process_in_measurement: torch.Tensor | None = None,
    softening: float = 1.0,
) -> torch.Tensor:
    """Strong-tracking fading factor ``lambda = max(1, tr N / tr M)``.

    ``N = V - H Q H^T - beta R``, ``M = H Phi P Phi^T H^T``.

    Args:
        innovation_estimate: (..., m, m) V (:func:`update_innovation_covariance`).
        predicted: (..., m, m) M, the propagated covariance without process noise, mapped
            into the measurement space.
        measurement_cov: (..., m, m) R.
        process_in_measurement: (..., m, m) ``H Q H^T`` or None (0: e.g. a UKF whose
            ``M`` already contains Q).
        softening: beta >= 1 makes the factor less eager.
    Returns:
        (...) lambda >= 1; 1 where ``tr M`` is 0.
    """
    diff = innovation_estimate - softening * measurement_cov
    if process_in_measurement is not None:
        diff = diff - process_in_measurement
    numerator = torch.diagonal(diff, dim1=-2, dim2=-1).sum(-1)
    denominator = torch.diagonal(predicted, dim1=-2, dim2=-1).sum(-1)
    positive = denominator > 0
    ratio = numerator / torch.where(positive, denominator, 1.0)
    return torch.where(positive, ratio, 1.0).clamp_min(1.0)


def project_positive_definite(matrix: torch.Tensor, min_eigenvalue: torch.Tensor) -> torch.Tensor:
    """Nearest (Frobenius) symmetric matrix with every eigenvalue >= ``min_eigenvalue``.

    The symmetric part is returned unchanged where it already satisfies the bound (checked
    by a Cholesky of ``A - r_min I``); elsewhere its eigenvalues are clamped from below.
    The eigen-decomposition runs on a stand-in where no projection is needed, so the
    gradient stays finite for matrices with repeated eigenvalues (e.g. ``s I``).

    Args:
        matrix: (..., m, m).
        min_eigenvalue: () or (...) r_min > 0.
    Returns:
        (..., m, m) symmetric positive definite.
    """
    sym = 0.5 * (matrix + matrix.mT)
    size = sym.shape[-1]
    eye = torch.eye(size, dtype=sym.dtype, device=sym.device)
    floor = torch.as_tensor(min_eigenvalue, dtype=sym.dtype, device=sym.device)
    floor = floor.expand(sym.shape[:-2])
    _, info = torch.linalg.cholesky_ex((sym - floor[..., None, None] * eye).detach())
    needs = info != 0
    if not bool(needs.any()):
        return sym
    distinct = torch.diag(torch.arange(1, size + 1, dtype=sym.dtype, device=sym.device))
    safe = torch.where(needs[..., None, None], sym, distinct)
    values, vectors = torch.linalg.eigh(safe)
    clamped = torch.maximum(values, floor[..., None])
    projected = (vectors * clamped[..., None, :]) @ vectors.mT
    return torch.where(needs[..., None, None], 0.5 * (projected + projected.mT), sym)


def sage_husa_update(
    previous: torch.Tensor,
    innovation: torch.Tensor,
    predicted_measurement_cov: torch.Tensor,
    count: torch.Tensor,
    forgetting: float,
    min_eigenvalue: torch.Tensor,
    prior_count: float = 0.0,
    innovation_cov: torch.Tensor | None = None,
    max_nis: float | None = None,
) -> torch.Tensor:
    """One Sage-Husa step ``R_k = (1 - d_k) R_(k-1) + d_k (nu nu^T - H P^- H^T)``, kept PD.

    Args:
        previous: (..., m, m) ``R_(k-1)`` (the nominal R before the first sample).
        innovation: (..., m) ``nu_k`` against the predicted state.
        predicted_measurement_cov: (..., m, m) ``H P^- H^T``.
        count: (...) samples already mixed in.
        forgetting: b in (0, 1).
        min_eigenvalue: () or (...) floor of the projection (:func:`project_positive_definite`).
        prior_count: k0, what the nominal R is worth in samples.
        innovation_cov, max_nis: optional outlier clip (:func:`clipped_outer`).
    Returns:
        (..., m, m) ``R_k``, symmetric with eigenvalues >= ``min_eigenvalue``.
    """
    weight = forgetting_weight(count, forgetting, prior_count)[..., None, None]
    sample = clipped_outer(innovation, innovation_cov, max_nis) - predicted_measurement_cov
    return project_positive_definite((1.0 - weight) * previous + weight * sample, min_eigenvalue)
