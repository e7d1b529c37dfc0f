"""Timestamp association and Umeyama least-squares alignment of trajectories.

:func:`associate` pairs the poses of an estimate and a reference by nearest timestamp with the
exact rule of evo's ``sync.associate_trajectories`` (``SyncMethod.nearest_time``), so that the
metrics in :mod:`msf_torch.eval.metrics` score the same pose pairs as ``evo_ape`` / ``evo_rpe``.

:func:`umeyama` solves ``dst ~= s R src + t`` in the least-squares sense for a batch of point
sets with masks, as evo's ``geometry.umeyama_alignment`` does for one.

Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two
point patterns", IEEE PAMI 13(4), 1991.
"""

from __future__ import annotations

__all__ = ["associate", "umeyama", "apply_similarity"]

import torch

from msf_torch.types import Trajectory


def _first_unsorted(t: torch.Tensor) -> int | None:
    """Index of the first sample whose time is smaller than its predecessor's, else None."""
    if t.numel() < 2:
        return None
    bad = torch.nonzero(t[1:] < t[:-1])
    return None if bad.numel() == 0 else int(bad[0, 0]) + 1


def _match_sorted(
    short: torch.Tensor, long: torch.Tensor, max_dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """evo's ``matching_time_indices`` for sorted ``long`` stamps, vectorised.

    For every stamp of ``short`` (M,), the nearest stamp of ``long`` (L,) within ``max_dt``; on
    an exact tie the earlier one. Returns (indices into short, indices into long), both (K,).
    """
    inf = torch.tensor(float("inf"), dtype=long.dtype, device=long.device)
    inside = (short >= long[0] - max_dt) & (short <= long[-1] + max_dt)
    upper = torch.searchsorted(long, short, right=True).clamp_max(long.numel() - 1)
    lower = (upper - 1).clamp_min(0)
    diff_ub = long[upper] - short
    diff_lb = torch.where(upper > 0, short - long[lower], inf)
    take_upper = (diff_ub <= max_dt) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_dt) & (diff_lb <= diff_ub)
    keep = inside & (take_upper | take_lower)
    best = torch.where(take_upper, upper, lower)
    short_idx = torch.nonzero(keep).reshape(-1)
    return short_idx, best[short_idx]


def associate(
    est: Trajectory, ref: Trajectory, max_dt: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pair estimate and reference poses by nearest timestamp (evo's rule).

    Only real samples (``mask`` True) take part. Like evo's
    ``associate_trajectories(traj_ref, traj_est, max_diff)``, the trajectory with fewer real
    poses drives the search (the estimate when both have as many): each of its poses is paired
    with the nearest pose of the other one if their times differ by at most ``max_dt``, and on
    an exact tie with the earlier one. A pose of the longer trajectory may be used more than
    once. Pairs come out in the order of the shorter trajectory's poses.

    Args:
        est: estimated trajectory with B = 1, time-sorted.
        ref: reference trajectory with B = 1, time-sorted.
        max_dt: largest accepted time difference, s.

    Returns:
        ``(est_idx, ref_idx)``: (K,) int64 indices into the N axis of ``est`` and ``ref``, so
        ``est.position[0, est_idx]`` and ``ref.position[0, ref_idx]`` are the K matched poses.

    Raises:
        ValueError: B is not 1, times are not sorted, or no pair matches.

    Example:
        >>> est_idx, ref_idx = associate(est, ref, max_dt=0.01)  # doctest: +SKIP
    """
    for name, traj in (("est", est), ("ref", ref)):
        traj.check(name)
        if traj.batch_size != 1:
            raise ValueError(
                f"associate needs B = 1, got {name} with B = {traj.batch_size}; "
                "use Trajectory.select(i) per sequence"
            )
    est_real = torch.nonzero(est.mask[0]).reshape(-1)
    ref_real = torch.nonzero(ref.mask[0]).reshape(-1)
    t_est, t_ref = est.t[0, est_real], ref.t[0, ref_real]
    for name, t in (("est", t_est), ("ref", t_ref)):
        bad = _first_unsorted(t)
        if bad is not None:
            raise ValueError(
                f"{name} times are not sorted: real sample {bad} at t = {float(t[bad])} s "
                f"comes after t = {float(t[bad - 1])} s"
            )
    if t_est.numel() == 0 or t_ref.numel() == 0:
        raise ValueError(
            f"associate needs poses in both trajectories; est has {t_est.numel()}, "
            f"ref has {t_ref.numel()}"
        )
    # evo: traj_1 = reference, traj_2 = estimate; "second_longer" makes the reference short.
    if t_est.numel() > t_ref.numel():
        ref_k, est_k = _match_sorted(t_ref, t_est, max_dt)
    else:
        est_k, ref_k = _match_sorted(t_est, t_ref, max_dt)
    if est_k.numel() == 0:
        raise ValueError(
            f"found no matching timestamps between estimate and reference with max_dt = {max_dt} s "
            f"(estimate {float(t_est[0]):.6f}..{float(t_est[-1]):.6f} s, reference "
            f"{float(t_ref[0]):.6f}..{float(t_ref[-1]):.6f} s)"
        )
    return est_real[est_k], ref_real[ref_k]


def umeyama(
    src: torch.Tensor,
    dst: torch.Tensor,
    mask: torch.Tensor | None = None,
    with_scale: bool = False,
    strict: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched Umeyama alignment: the similarity minimising ``sum ||dst - (s R src + t)||^2``.

    Math (per problem, over its real points, n of them):
        ``mu_x, mu_y`` means; ``sigma_x^2 = 1/n sum ||x - mu_x||^2``;
        ``Sigma_xy = 1/n sum (y - mu_y)(x - mu_x)^T = U D V^T``;
        ``S = diag(1, .., 1, det(U) det(V) < 0 ? -1 : 1)``; ``R = U S V^T``;
        ``s = tr(D S) / sigma_x^2`` (1 without scale); ``t = mu_y - s R mu_x``.
    This is evo's ``geometry.umeyama_alignment``, vectorised over B.

    Args:
        src: (B, N, M) points to move (the estimate), usually M = 3, m.
        dst: (B, N, M) target points (the reference), m.
        mask: (B, N) bool, True where the pair is real; None means all real.
        with_scale: also estimate the scale ``s`` (Sim(M)); else ``s = 1`` (SE(M)).
        strict: raise ``ValueError`` naming the problems whose cross-covariance has fewer
            than M - 1 singular values above machine epsilon (no real points, one point, or
            all points on one line for M = 3), as evo does; with ``strict=False`` such
            problems get ``R = I``, ``s = 1`` and ``t = mu_y - mu_x`` instead.

    Returns:
        ``(rotation (B, M, M), translation (B, M), scale (B,))`` with
        ``dst ~= scale * rotation @ src + translation``.

    Shape:
        B problems solved at once, with no Python loop over B.

    Example:
        >>> R, t, s = umeyama(est_xyz, ref_xyz, mask, with_scale=True)  # doctest: +SKIP
        >>> aligned = apply_similarity(est_xyz, R, t, s)  # doctest: +SKIP
    """
    if src.shape != dst.shape or src.dim() != 3:
        raise ValueError(
            f"umeyama needs src and dst of equal shape (B, N, M); got {tuple(src.shape)} and "
            f"{tuple(dst.shape)}"
        )
    batch, _, dim = src.shape
    if mask is None:
        mask = torch.ones(src.shape[:2], dtype=torch.bool, device=src.device)
    if mask.shape != src.shape[:2]:
        raise ValueError(f"mask must be {tuple(src.shape[:2])}, got {tuple(mask.shape)}")
    weight = mask.to(src.dtype)[..., None]  # (B, N, 1)
    count = weight.sum(1)  # (B, 1)
    safe_count = count.clamp_min(1.0)
    mean_x = (weight * src).sum(1) / safe_count  # (B, M)
    mean_y = (weight * dst).sum(1) / safe_count
    xc = (src - mean_x[:, None]) * weight
    yc = (dst - mean_y[:, None]) * weight
    sigma_x = (xc * xc).sum((1, 2)) / safe_count[:, 0]  # (B,)
    cov = yc.transpose(1, 2) @ xc / safe_count[..., None]  # (B, M, M)
    u, d, vh = torch.linalg.svd(cov)
    eps = torch.finfo(src.dtype).eps
    degenerate = ((d > eps).sum(-1) < dim - 1) | (count[:, 0] < 1)
    if strict and bool(degenerate.any()):
        bad = torch.nonzero(degenerate).reshape(-1).tolist()
        raise ValueError(
            f"degenerate covariance rank in problems {bad}: Umeyama alignment is not possible "
            "(too few or collinear points)"
        )
    flip = (torch.linalg.det(u) * torch.linalg.det(vh)) < 0.0  # (B,)
    s_diag = torch.ones(batch, dim, dtype=src.dtype, device=src.device)
    s_diag[:, -1] = torch.where(flip, -1.0, 1.0).to(src.dtype)
    rotation = u @ torch.diag_embed(s_diag) @ vh
    if with_scale:
        scale = (d * s_diag).sum(-1) / sigma_x.clamp_min(torch.finfo(src.dtype).tiny)
    else:
        scale = torch.ones(batch, dtype=src.dtype, device=src.device)
    if bool(degenerate.any()):
        eye = torch.eye(dim, dtype=src.dtype, device=src.device).expand(batch, dim, dim)
        rotation = torch.where(degenerate[:, None, None], eye, rotation)
        scale = torch.where(degenerate, torch.ones_like(scale), scale)
    translation = mean_y - scale[:, None] * (rotation @ mean_x[..., None])[..., 0]
    return rotation, translation, scale


def apply_similarity(
    points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor, scale: torch.Tensor
) -> torch.Tensor:
    """``s R p + t`` for points (B, N, M) with rotation (B, M, M), translation (B, M), scale (B,).

    Returns (B, N, M), in the units of ``translation`` (m).
    """
    return scale[:, None, None] * (points @ rotation.transpose(1, 2)) + translation[:, None]
