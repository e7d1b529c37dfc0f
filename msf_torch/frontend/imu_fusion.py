"""Fusing the attitude posteriors of N >= 2 IMUs on one body, three ways, plus PSO.

Each IMU's filter (``frontend.attitude_ukf``) gives a posterior ``(q_i, omega_i, P_i)`` over
the error state ``x = [dtheta, domega]`` (body-side attitude perturbation). All IMUs are
assumed mounted with aligned axes on the same rigid body, so they estimate the same state.
Posteriors are compared in the chart at a reference attitude ``q_ref``:
``x_i = [Log(q_ref^-1 (x) q_i), omega_i]`` (to first order ``P_i`` carries over); the fused
``x`` maps back with ``q = q_ref (x) Exp(x_theta)``, and the reference moves to the fused
attitude for a second pass.

1. **Information fusion** (covariance weights, :func:`information_fusion`): independent
   errors, ``P = (sum_i P_i^-1)^-1``, ``x = P sum_i P_i^-1 x_i``.
2. **Error-compensation posterior** (:func:`error_compensation_fusion`): the IMUs' errors
   are not independent (on one body they share the linear acceleration that the
   accelerometers mistake for gravity). The difference of two posteriors
   ``d_ij = x_j - x_i`` is observable without truth; its second moment
   ``C_ij = E[d_ij^2] = P_i + P_j - 2 P_ij`` gives the cross-covariance
   ``P_ij = (P_i + P_j - C_ij) / 2``, with ``C_ij`` tracked by exponential forgetting
   (:func:`disagreement_moments`). Per axis (world-frame attitude axes, so that the two
   tilt axes are apart from the unobservable yaw; body rate axes), the fused value is the
   best linear unbiased estimate with the N x N covariance ``Sigma`` (diagonal ``P_i``,
   off-diagonal ``P_ij`` with the correlation bounded by ``max_correlation``):
   ``w = Sigma^-1 1 / (1^T Sigma^-1 1)``. For N = 2 this is the Bar-Shalom-Campo formula
   ``x = x_1 + (P_1 - P_12) / (P_1 + P_2 - 2 P_12) (x_2 - x_1)``: the reference estimate
   compensated by the part of the disagreement that is its own error. Weights are kept
   non-negative (renormalised): the filters' ``P_i`` do not contain unmodelled errors
   (turn-on offsets, linear acceleration), and a BLUE built on them extrapolates far
   outside the estimates when their difference is large against ``C_ij`` (seen on the
   simulated static runs).
3. **Searched weights** (:func:`weighted_fusion` with weights found by
   :func:`particle_swarm_minimize`): per IMU and per body axis a weight, normalised over
   the IMUs; ``x_theta = sum_i w_i * x_theta_i`` (the rate likewise).

All functions take leading dims ``(...)`` (e.g. ``(B, T)``) with the IMU axis just before
the state axes, and are differentiable.
"""

from __future__ import annotations

__all__ = [
    "FusedAttitude",
    "SwarmResult",
    "information_fusion",
    "error_compensation_fusion",
    "disagreement_moments",
    "weighted_fusion",
    "particle_swarm_minimize",
]

from collections.abc import Callable
from dataclasses import dataclass

import torch

from msf_torch.frontend.adaptive import forgetting_weight
from msf_torch.geometry.quaternion import quat_conjugate as _qconj
from msf_torch.geometry.quaternion import quat_exp as _qexp
from msf_torch.geometry.quaternion import quat_log as _qlog
from msf_torch.geometry.quaternion import quat_multiply as _qmul
from msf_torch.geometry.quaternion import quat_to_matrix


@dataclass
class FusedAttitude:
    """A fused posterior (leading dims ``(...)``).

    Attributes:
        quaternion: (..., 4) ``[w, x, y, z]``, w >= 0.
        rate: (..., 3) rad/s.
        covariance: (..., 6, 6) or None (searched weights give none).
    """

    quaternion: torch.Tensor
    rate: torch.Tensor
    covariance: torch.Tensor | None = None


@dataclass
class SwarmResult:
    """Outcome of :func:`particle_swarm_minimize`.

    Attributes:
        position: (D,) best point found.
        value: its objective value.
        history: (iterations + 1,) best value after each iteration (index 0: initial swarm).
    """

    position: torch.Tensor
    value: float
    history: torch.Tensor


def _canonical(quat: torch.Tensor) -> torch.Tensor:
    return torch.where(quat[..., :1] < 0, -quat, quat)


def _chart(quats: torch.Tensor, rates: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """(..., N, 6) ``[Log(q_ref^-1 q_i), omega_i]``."""
    theta = _qlog(_qmul(_qconj(reference)[..., None, :], quats))
    return torch.cat((theta, rates), -1)


def _check(quats: torch.Tensor, rates: torch.Tensor) -> None:
    if quats.shape[-1] != 4 or rates.shape[-1] != 3 or quats.shape[:-1] != rates.shape[:-1]:
        raise ValueError(
            f"quaternions (..., N, 4) and rates (..., N, 3) expected, got "
            f"{tuple(quats.shape)} and {tuple(rates.shape)}"
        )
    if quats.shape[-2] < 2:
        raise ValueError(f"fusion needs N >= 2 IMUs, got {quats.shape[-2]}")


def information_fusion(
    quats: torch.Tensor, rates: torch.Tensor, covariances: torch.Tensor, passes: int = 2
) -> FusedAttitude:
    """Covariance-weighted (information) fusion of N posteriors.

    Args:
        quats: (..., N, 4); rates: (..., N, 3); covariances: (..., N, 6, 6).
        passes: re-linearisations at the fused attitude (>= 1).
    Returns:
        :class:`FusedAttitude` with ``P = (sum P_i^-1)^-1``.
    Raises:
        ValueError: ``passes < 1``, or shapes disagree.
    """
    if passes < 1:
        raise ValueError(f"information_fusion: passes must be >= 1, got {passes}")
    _check(quats, rates)
    information = torch.linalg.inv(covariances)
    fused_cov = torch.linalg.inv(information.sum(-3))
    reference = quats[..., 0, :]
    for _ in range(passes):
        x = _chart(quats, rates, reference)
        mean = (fused_cov @ (information @ x[..., None]).sum(-3))[..., 0]
        reference = _qmul(reference, _qexp(mean[..., :3]))
    rate = mean[..., 3:]
    return FusedAttitude(_canonical(reference), rate, 0.5 * (fused_cov + fused_cov.mT))


def disagreement_moments(
    quats: torch.Tensor, rates: torch.Tensor, forgetting: float
) -> torch.Tensor:
    """Causal exponentially weighted per-axis second moments of the pairwise differences.

    ``C_ij(t) = sum_k<=t b^(t-k) d_ij(k)^2 / sum_k<=t b^(t-k)`` (elementwise) with
    ``d_ij = [Log(q_j (x) q_i^-1), omega_j - omega_i]`` (world-side attitude difference;
    weights of ``frontend.adaptive.forgetting_weight``).

    Args:
        quats: (B, N, T, 4); rates: (B, N, T, 3) posteriors over time.
        forgetting: b in (0, 1) per sample.
    Returns:
        (B, N, N, T, 6), symmetric in (i, j); zeros on i == j; T = 0 gives T = 0.
    """
    _check(quats.movedim(2, 1), rates.movedim(2, 1))
    batch, n_imu, n_samples = quats.shape[:3]
    if n_samples == 0:
        return quats.new_zeros(batch, n_imu, n_imu, 0, 6)
    theta = _qlog(_qmul(quats[:, None, :], _qconj(quats)[:, :, None]))  # (B, N, N, T, 3)
    squared = torch.cat((theta, rates[:, None, :] - rates[:, :, None]), -1) ** 2
    moment = torch.zeros(batch, n_imu, n_imu, 6, dtype=quats.dtype, device=quats.device)
    out = []
    for k in range(n_samples):
        weight = forgetting_weight(torch.tensor(float(k), dtype=quats.dtype), forgetting)
        moment = (1.0 - weight) * moment + weight * squared[:, :, :, k]
        out.append(moment)
    return torch.stack(out, 3)


def _world_variances(quats: torch.Tensor, covariances: torch.Tensor) -> torch.Tensor:
    """(..., N, 6) per-axis variances: world-frame attitude ``diag(R P_tt R^T)`` and rate."""
    rot = quat_to_matrix(quats)
    attitude = torch.diagonal(rot @ covariances[..., :3, :3] @ rot.mT, dim1=-2, dim2=-1)
    rate = torch.diagonal(covariances[..., 3:, 3:], dim1=-2, dim2=-1)
    return torch.cat((attitude, rate), -1)


def error_compensation_fusion(
    quats: torch.Tensor,
    rates: torch.Tensor,
    covariances: torch.Tensor,
    disagreement: torch.Tensor,
    max_correlation: float = 0.99,
    passes: int = 2,
) -> FusedAttitude:
    """Per-axis best linear unbiased fusion with correlations from the observed disagreement.

    Args:
        quats: (..., N, 4); rates: (..., N, 3); covariances: (..., N, 6, 6).
        disagreement: (..., N, N, 6) per-axis second moments ``C_ij`` of ``x_j - x_i``
            (:func:`disagreement_moments`, moved to the same leading dims).
        max_correlation: bound on ``|P_ij| / sqrt(P_i P_j)``.
        passes: re-linearisations at the fused attitude.
    Returns:
        :class:`FusedAttitude`; its covariance is diagonal, per axis the variance
        ``w^T Sigma w`` of the weights used (world attitude axes, body rate axes): the BLUE
        variance ``1 / (1^T Sigma^-1 1)`` where no weight was clipped, more where one was.
    """
    _check(quats, rates)
    n_imu = quats.shape[-2]
    var = _world_variances(quats, covariances)  # (..., N, 6)
    var_i, var_j = var[..., :, None, :], var[..., None, :, :]
    bound = max_correlation * torch.sqrt(var_i * var_j)
    cross = torch.maximum(torch.minimum(0.5 * (var_i + var_j - disagreement), bound), -bound)
    eye = torch.eye(n_imu, dtype=torch.bool, device=quats.device)[..., None]
    sigma = torch.where(eye, var_i.expand_as(cross), cross).movedim(-1, -3)  # (..., 6, N, N)
    ones = torch.ones(*sigma.shape[:-1], 1, dtype=quats.dtype, device=quats.device)
    solved = torch.linalg.solve(sigma, ones)[..., 0]  # (..., 6, N)
    weights = solved.clamp_min(0.0)
    weights = weights / weights.sum(-1, keepdim=True)  # (..., 6, N)
    fused_var = (weights[..., None, :] @ sigma @ weights[..., :, None])[..., 0, 0]
    weights = weights.movedim(-2, -1)  # (..., N, 6)
    reference = quats[..., 0, :]
    for _ in range(passes):
        theta = _qlog(_qmul(quats, _qconj(reference)[..., None, :]))  # world side
        reference = _qmul(_qexp((weights[..., :3] * theta).sum(-2)), reference)
    rate = (weights[..., 3:] * rates).sum(-2)
    return FusedAttitude(_canonical(reference), rate, torch.diag_embed(fused_var))


def weighted_fusion(
    quats: torch.Tensor, rates: torch.Tensor, weights: torch.Tensor, passes: int = 2
) -> FusedAttitude:
    """Per-axis weighted mean of N attitudes and rates.

    Args:
        quats: (..., N, 4); rates: (..., N, 3).
        weights: (..., N, 3) non-negative, per IMU and body axis; normalised over N here
            (equal weights: ``torch.ones``).
        passes: re-linearisations at the fused attitude.
    Returns:
        :class:`FusedAttitude` (no covariance).
    """
    _check(quats, rates)
    norm = weights / weights.sum(-2, keepdim=True)
    reference = quats[..., 0, :]
    for _ in range(passes):
        theta = _qlog(_qmul(_qconj(reference)[..., None, :], quats))
        reference = _qmul(reference, _qexp((norm * theta).sum(-2)))
    return FusedAttitude(_canonical(reference), (norm * rates).sum(-2))


def particle_swarm_minimize(
    objective: Callable[[torch.Tensor], torch.Tensor],
    lower: torch.Tensor,
    upper: torch.Tensor,
    particles: int = 30,
    iterations: int = 50,
    inertia: float = 0.8,
    cognitive: float = 0.5,
    social: float = 0.5,
    generator: torch.Generator | None = None,
) -> SwarmResult:
    """Particle swarm optimisation in a box (global-best topology).

    ``v <- w v + c1 r1 (p_best - x) + c2 r2 (g_best - x)``, ``x <- clamp(x + v)``, with
    ``r1, r2 ~ U(0, 1)`` per particle and dimension; initial positions uniform in the box,
    velocities uniform in ``+-0.1 (upper - lower)``.

    Args:
        objective: maps (P, D) candidates to (P,) values (all particles in one call).
        lower, upper: (D,) bounds.
        particles, iterations: swarm size and number of updates.
        inertia, cognitive, social: w, c1, c2.
        generator: random source (CPU), for reproducibility.
    Returns:
        :class:`SwarmResult`.
    """
    lower = torch.as_tensor(lower)
    upper = torch.as_tensor(upper, dtype=lower.dtype)
    if lower.shape != upper.shape or lower.dim() != 1 or not bool((upper > lower).all()):
        raise ValueError("particle_swarm_minimize: lower < upper, both (D,), required")
    span = upper - lower
    dims = lower.shape[0]

    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator, dtype=lower.dtype).to(lower.device)

    position = lower + uniform(particles, dims) * span
    velocity = (2.0 * uniform(particles, dims) - 1.0) * 0.1 * span
    values = objective(position)
    best_pos, best_val = position.clone(), values.clone()
    g = int(torch.argmin(best_val))
    global_pos, global_val = best_pos[g].clone(), best_val[g].clone()
    history = [global_val.clone()]
    for _ in range(iterations):
        r1, r2 = uniform(particles, dims), uniform(particles, dims)
        velocity = (
            inertia * velocity
            + cognitive * r1 * (best_pos - position)
            + social * r2 * (global_pos - position)
        )
        position = torch.maximum(torch.minimum(position + velocity, upper), lower)
        values = objective(position)
        improved = values < best_val
        best_pos = torch.where(improved[:, None], position, best_pos)
        best_val = torch.where(improved, values, best_val)
        g = int(torch.argmin(best_val))
        if best_val[g] < global_val:
            global_pos, global_val = best_pos[g].clone(), best_val[g].clone()
        history.append(global_val.clone())
    return SwarmResult(global_pos, float(global_val), torch.stack(history))
