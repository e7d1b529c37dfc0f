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

Multiplying all of ``Phi P Phi^T`` also inflates the directions the measurement does not
see (an INS's biases, an attitude filter's yaw): repeated at every epoch they grow
geometrically (covariance wind-up, as in recursive least squares without directional
forgetting). :func:`inflate_along_measurements` adds ``(lambda - 1)`` times only the part
of ``Phi P Phi^T`` that the measurement explains, ``A M^-1 A^T`` with
``A = Phi P Phi^T H^T``: in the measurement space it is the same as full fading
(``H P^- H^T = lambda M + H Q H^T``, cross covariance ``lambda A``, hence the same gain),
and states uncorrelated with the measurement keep their covariance.

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
acts). :class:`BlockAdaptation` applies both to a filter's stacked measurement vector
made of named blocks (the ESKF's wheel / GNSS / pose / ... blocks).
"""

from __future__ import annotations

__all__ = [
    "forgetting_weight",
    "clipped_outer",
    "update_innovation_covariance",
    "fading_factor",
    "inflate_along_measurements",
    "project_positive_definite",
    "sage_husa_update",
    "BlockAdaptation",
]

import math
from collections.abc import Sequence

import torch

from msf_torch.frontend.gating import chi2_threshold


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

    Where S is not positive definite nothing is clipped.

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
    chol, info = torch.linalg.cholesky_ex(innovation_cov)
    eye = torch.eye(innovation.shape[-1], dtype=innovation.dtype, device=innovation.device)
    chol = torch.where((info == 0)[..., None, None], chol, eye)
    white = torch.linalg.solve_triangular(chol, innovation[..., None], upper=False)
    nis = (white**2).sum((-2, -1))
    clip = (nis > max_nis) & (info == 0)
    scale = torch.where(clip, max_nis / nis.clamp_min(max_nis), 1.0)
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
    max_factor: float | None = None,
) -> torch.Tensor:
    """Strong-tracking fading factor ``lambda = max(1, tr N / tr M)``, optionally capped.

    ``N = V - H Q H^T - beta R``, ``M = H Phi P Phi^T H^T``.

    Args:
        innovation_estimate: (..., m, m) V (:func:`update_innovation_covariance`).
        predicted: (..., m, m) M, the propagated covariance without process noise, mapped
            into the measurement space.
        measurement_cov: (..., m, m) R.
        process_in_measurement: (..., m, m) ``H Q H^T`` or None (0: e.g. a UKF whose
            ``M`` already contains Q).
        softening: beta >= 1 makes the factor less eager.
        max_factor: upper bound on lambda, or None.
    Returns:
        (...) lambda in [1, max_factor]; 1 where ``tr M`` is 0.
    """
    diff = innovation_estimate - softening * measurement_cov
    if process_in_measurement is not None:
        diff = diff - process_in_measurement
    numerator = torch.diagonal(diff, dim1=-2, dim2=-1).sum(-1)
    denominator = torch.diagonal(predicted, dim1=-2, dim2=-1).sum(-1)
    positive = denominator > 0
    ratio = numerator / torch.where(positive, denominator, 1.0)
    return torch.where(positive, ratio, 1.0).clamp(1.0, max_factor)


def inflate_along_measurements(
    propagated: torch.Tensor,
    jacobian: torch.Tensor,
    factor: torch.Tensor,
    row_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Directional fading ``Phi P Phi^T + (lambda - 1) A M^-1 A^T``.

    ``A = Phi P Phi^T H^T``, ``M = H Phi P Phi^T H^T`` over the rows in ``row_mask``.
    With ``H = I`` this is ``lambda Phi P Phi^T``, the classic full fading.

    Where M is singular because rows measure the same direction (two strong-tracking blocks
    at one epoch: two pose sources' rate rows, GNSS and a pose position), ``M^-1`` is
    replaced by ``(M + eps I)^-1`` with ``eps = 1e-12 max diag M``: the same inflation,
    ``P H^T M^+ H P``, to within about ``eps`` over M's smallest non-zero eigenvalue.

    Args:
        propagated: (..., n, n) ``Phi P Phi^T``.
        jacobian: (..., m, n) H.
        factor: (...) lambda >= 1.
        row_mask: (..., m) 1/0 (or bool), the rows that count; None = all.
    Returns:
        (..., n, n); ``propagated`` unchanged where even that fails (no inflation there).
    """
    if row_mask is not None:
        mask = row_mask.to(jacobian.dtype)
        jacobian = jacobian * mask[..., :, None]
    cross = propagated @ jacobian.mT  # (..., n, m)
    seen = jacobian @ cross
    eye = torch.eye(seen.shape[-1], dtype=seen.dtype, device=seen.device)
    jitter = 1e-12 * torch.diagonal(seen, dim1=-2, dim2=-1).amax(-1)
    if row_mask is not None:
        seen = seen + torch.diag_embed(1.0 - mask)
    chol, info = torch.linalg.cholesky_ex(seen)
    ok = info == 0
    if not bool(ok.all()):  # rank-deficient M: regularised (see above)
        chol_reg, info_reg = torch.linalg.cholesky_ex(seen + jitter[..., None, None] * eye)
        chol = torch.where(ok[..., None, None], chol, chol_reg)
        ok = ok | (info_reg == 0)
    chol = torch.where(ok[..., None, None], chol, eye)
    explained = cross @ torch.cholesky_solve(cross.mT, chol)
    extra = (factor - 1.0).where(ok, 0.0)[..., None, None] * explained
    return propagated + 0.5 * (extra + extra.mT)


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


class BlockAdaptation:
    """Sage-Husa R and strong tracking over a stacked measurement vector of named blocks.

    Per epoch, for each block present in a sequence (all B at once):

    1. Sage-Husa blocks: ``R_hat`` is updated with the block's innovation and
       ``H P^- H^T`` (``P^- = Phi P Phi^T + Q``, before fading; the nominal R of the
       block's first measurement is the prior, worth ``prior_samples`` samples; floor
       ``noise_floor`` x the nominal R's smallest eigenvalue) and replaces the block's R.
    2. Strong-tracking blocks: ``V`` is updated with the innovation; each present block
       gives ``lambda_k`` (:func:`fading_factor`, with the R of step 1);
       ``lambda = max_k lambda_k`` (1 where none), at most ``max_factor``, inflates
       ``Phi P Phi^T`` along the rows of the present strong-tracking blocks
       (:func:`inflate_along_measurements`), then ``P^- = ... + Q``. Full fading of the
       15-state ESKF covariance at every GNSS epoch made the bias covariance grow
       geometrically and the filter diverge on simulated runs; the cap keeps a filter
       whose R is too small from chasing its measurements without bound.

    Innovations are clipped at the chi-square quantile ``clip_probability`` of the block's
    dimension against the block's innovation covariance before adaptation.

    Args:
        names, dims: the blocks of the stacked vector, in order, and their row counts.
        noise_blocks, tracking_blocks: names of the blocks to adapt (others are ignored).
        batch: B.
        forgetting: b in (0, 1).
        prior_samples, noise_floor, softening, clip_probability, max_factor: see above.
        dtype, device: of the adapted R blocks and tracking state.
    """

    def __init__(
        self,
        names: Sequence[str],
        dims: Sequence[int],
        noise_blocks: Sequence[str],
        tracking_blocks: Sequence[str],
        batch: int,
        forgetting: float,
        prior_samples: float = 10.0,
        noise_floor: float = 0.1,
        softening: float = 1.0,
        clip_probability: float = 0.9999,
        max_factor: float | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        _check_forgetting(forgetting)
        offsets = [sum(dims[:k]) for k in range(len(dims))]
        self._slices = {n: slice(o, o + d) for n, o, d in zip(names, offsets, dims, strict=True)}
        self._column = {n: k for k, n in enumerate(names)}
        self.noise_blocks = [n for n in names if n in noise_blocks]
        self.tracking_blocks = [n for n in names if n in tracking_blocks]
        self._forgetting = forgetting
        self._prior_samples = prior_samples
        self._noise_floor = noise_floor
        self._softening = softening
        self._max_factor = max_factor
        self._clip = {}
        for n, d in zip(names, dims, strict=True):
            level = chi2_threshold(d, clip_probability)
            self._clip[n] = level if math.isfinite(level) else None
        self._batch, self._dtype, self._device = batch, dtype, device

        def zeros(*shape: int) -> torch.Tensor:
            return torch.zeros(*shape, dtype=dtype, device=device)

        size = {n: d for n, d in zip(names, dims, strict=True)}
        self._r_hat = {n: zeros(batch, size[n], size[n]) for n in self.noise_blocks}
        self._r_count = {n: zeros(batch) for n in self.noise_blocks}
        self._v = {n: zeros(batch, size[n], size[n]) for n in self.tracking_blocks}
        self._v_count = {n: zeros(batch) for n in self.tracking_blocks}
        self._fading: dict[int, torch.Tensor] = {}
        self._noise: dict[int, dict[str, torch.Tensor]] = {}

    @property
    def enabled(self) -> bool:
        """Whether any block is adapted."""
        return bool(self.noise_blocks or self.tracking_blocks)

    def memory(self, carried: dict[str, dict] | None = None) -> dict[str, dict]:
        """The adapted state now, for the next chunk of the run (``GateMemory.adaptation``):
        ``{"r_hat": {block: (B, d, d)}, "r_count": {block: (B,)}, "v": ..., "v_count":
        ...}``, this chunk's blocks and, from ``carried`` (the memory this chunk started
        from), the blocks it did not measure, unchanged."""
        out = {
            "r_hat": dict(self._r_hat),
            "r_count": dict(self._r_count),
            "v": dict(self._v),
            "v_count": dict(self._v_count),
        }
        for key, values in (carried or {}).items():
            for name, value in values.items():
                out[key].setdefault(name, value)
        return out

    def restore(self, memory: dict[str, dict] | None) -> None:
        """Continue from a previous chunk's :meth:`memory` (its blocks that this chunk
        adapts; the others stay as they start)."""
        for key, mine in (
            ("r_hat", self._r_hat),
            ("r_count", self._r_count),
            ("v", self._v),
            ("v_count", self._v_count),
        ):
            for name, value in (memory or {}).get(key, {}).items():
                if name in mine and value.shape == mine[name].shape:
                    mine[name] = value.to(dtype=self._dtype, device=self._device).clone()

    def step(
        self,
        epoch: int,
        propagated: torch.Tensor,
        process: torch.Tensor,
        jacobian: torch.Tensor,
        residual: torch.Tensor,
        measurement_cov: torch.Tensor,
        present: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Adapt one epoch.

        Args:
            epoch: index, for :meth:`history`.
            propagated: (B, n, n) ``Phi P Phi^T``.
            process: (B, n, n) Q.
            jacobian: (B, M, n) stacked H.
            residual: (B, M) stacked innovations (either sign).
            measurement_cov: (B, M, M) stacked nominal R.
            present: (B, K) bool, block k has a measurement.
        Returns:
            ``P^-`` (B, n, n) and the stacked R to use (B, M, M). A sequence with a
            non-finite input (e.g. an overflowing propagation) is not adapted: its blocks
            count as absent, its non-finite ``P^-`` comes back unchanged for the divergence
            guard (``frontend.guard``) to reset, and its R is the nominal one.
        """
        usable = (
            torch.isfinite(propagated + process).flatten(-2).all(-1)
            & torch.isfinite(jacobian).flatten(-2).all(-1)
            & torch.isfinite(residual).all(-1)
            & torch.isfinite(measurement_cov).flatten(-2).all(-1)
        )
        passthrough = None
        if not bool(usable.all()):  # stand-ins keep eigh / Cholesky away from inf and NaN
            passthrough = propagated + process, measurement_cov
            keep = usable[:, None, None]
            propagated = torch.where(
                keep,
                propagated,
                torch.eye(propagated.shape[-1], dtype=self._dtype, device=self._device),
            )
            process = torch.where(keep, process, 0.0)
            jacobian = torch.where(keep, jacobian, 0.0)
            residual = torch.where(usable[:, None], residual, 0.0)
            measurement_cov = torch.where(
                keep,
                measurement_cov,
                torch.eye(residual.shape[-1], dtype=self._dtype, device=self._device),
            )
            present = present & usable[:, None]
        predicted = propagated + process
        r_cov = measurement_cov.clone() if self.noise_blocks else measurement_cov
        for name in self.noise_blocks:
            rows = self._slices[name]
            here = present[:, self._column[name]]
            h = jacobian[:, rows]
            nominal = measurement_cov[:, rows, rows]
            eye = torch.eye(nominal.shape[-1], dtype=self._dtype, device=self._device)
            nominal = torch.where(here[:, None, None], nominal, eye)
            count = self._r_count[name]
            previous = torch.where((count > 0)[:, None, None], self._r_hat[name], nominal)
            h_p_ht = h @ predicted @ h.mT
            floor = self._noise_floor * torch.linalg.eigvalsh(nominal)[:, 0]
            updated = sage_husa_update(
                previous,
                residual[:, rows],
                h_p_ht,
                count,
                self._forgetting,
                floor,
                self._prior_samples,
                h_p_ht + previous,
                self._clip[name],
            )
            self._r_hat[name] = torch.where(here[:, None, None], updated, self._r_hat[name])
            self._r_count[name] = count + here.to(self._dtype)
            r_cov[:, rows, rows] = torch.where(
                here[:, None, None], self._r_hat[name], measurement_cov[:, rows, rows]
            )
        fading = torch.ones(self._batch, dtype=self._dtype, device=self._device)
        row_mask = torch.zeros_like(residual)
        for name in self.tracking_blocks:
            rows = self._slices[name]
            here = present[:, self._column[name]]
            h = jacobian[:, rows]
            block_r = r_cov[:, rows, rows]
            eye = torch.eye(block_r.shape[-1], dtype=self._dtype, device=self._device)
            block_r = torch.where(here[:, None, None], block_r, eye)
            count = self._v_count[name]
            innovation_cov = h @ predicted @ h.mT + block_r
            v = update_innovation_covariance(
                self._v[name],
                residual[:, rows],
                count,
                self._forgetting,
                innovation_cov,
                self._clip[name],
            )
            self._v[name] = torch.where(here[:, None, None], v, self._v[name])
            self._v_count[name] = count + here.to(self._dtype)
            lam = fading_factor(
                self._v[name],
                h @ propagated @ h.mT,
                block_r,
                h @ process @ h.mT,
                self._softening,
                self._max_factor,
            )
            fading = torch.maximum(fading, torch.where(here, lam, 1.0))
            row_mask[:, rows] = here.to(self._dtype)[:, None]
        if self.tracking_blocks:
            faded = inflate_along_measurements(propagated, jacobian, fading, row_mask)
            predicted = faded + process
        self._fading[epoch] = fading
        self._noise[epoch] = dict(self._r_hat)
        if passthrough is not None:
            keep = usable[:, None, None]
            predicted = torch.where(keep, predicted, passthrough[0])
            r_cov = torch.where(keep, r_cov, passthrough[1])
        return predicted, r_cov

    def history(self, n_epochs: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Per-epoch record, index 0 the initial state (as the filter's results).

        Returns:
            fading (B, E + 1), 1 where nothing was adapted; and per Sage-Husa block the
            ``R_hat`` in force after each epoch (B, E + 1, d, d), carried over epochs
            without the block, zeros before its first measurement.
        """
        ones = torch.ones(self._batch, dtype=self._dtype, device=self._device)
        fading = [ones] + [self._fading.get(e, ones) for e in range(n_epochs)]
        noise = {}
        for name in self.noise_blocks:
            current = torch.zeros_like(self._r_hat[name])
            steps = [current]
            for e in range(n_epochs):
                if e in self._noise:
                    current = self._noise[e][name]
                steps.append(current)
            noise[name] = torch.stack(steps, 1)
        return torch.stack(fading, 1), noise
