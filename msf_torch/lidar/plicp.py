"""Point-to-line ICP (PLICP) between 2D scans, batched over scan pairs.

Problem: find the pose ``q = [x, y, theta]`` of the current scan's frame in the reference
scan's frame (``p_ref = R(theta) p_cur + t``) that minimises the point-to-line distances

    J(q) = sum_i w_i (n_i^T (R(theta) p_i + t - a_i))^2

where ``p_i`` is a current point and ``(a_i, n_i)`` the line of the reference scan it is
matched to (anchor point and unit normal). One iteration (Censi 2008):

1. **Lines** (once per reference scan, :func:`fit_lines`): each reference point's line is
   fitted (principal axes) to its scan neighbours within ``line_window`` beams that lie
   within ``line_max_gap_m`` of it; the anchor is their centroid. Censi uses the segment to
   the nearest neighbour; with range noise comparable to the beam spacing that segment's
   direction is noise, so a few neighbours are fitted. A point with fewer than 3 such
   neighbours, or whose fit leaves an rms distance above ``line_max_rms_m`` (a corner, an
   edge), gets no line.
2. **Correspondences** (:func:`correspondences`): each current point, moved by the current
   ``q``, is matched to the nearest anchor if that lies within ``max_correspondence_m``
   (0.5 m); of the matches, the ``keep_fraction`` (80 %) with the smallest point-to-line
   distance are kept (trimmed ICP).
3. **Step** (:func:`point_to_line_step`): with the matches fixed, ``J`` is minimised
   exactly. With ``x = [t_x, t_y, cos theta, sin theta]``, ``J = x^T A x - 2 h^T x + c``;
   eliminating ``t`` leaves ``f(theta) = r^T S r - 2 g^T r`` on the unit circle
   ``r = [cos theta, sin theta]``, whose stationary points are the roots of a quartic in
   ``z = exp(i theta)`` (roots of its companion matrix); the root with the least ``f`` is
   polished by Newton steps and ``t`` follows linearly. A tiny prior
   ``mu |t - t_k|^2`` (``mu = 1e-9 trace(A_tt)``) keeps the solve finite when a direction
   is unconstrained.
4. **Degeneracy** (solution remapping, Zhang, Kaess and Singh 2016): with the Gauss-Newton
   Hessian ``H = sum_i w_i J_i J_i^T``, ``J_i = [n_i, n_i^T R'(theta) p_i]``, scaled to
   metres (rotation times the rms range ``L`` of the matched points), directions whose
   eigenvalue is below ``degeneracy_ratio`` times the largest get no update: along a
   featureless corridor the estimate keeps its initial value (the wheel-odometry guess)
   instead of wandering with the noise.
5. **Convergence**: stop when the step is below ``epsilon_xy_m`` and ``epsilon_theta_rad``
   (converged), when fewer than ``min_correspondences`` matches remain (failed), or after
   ``max_iterations``.

Covariance (for the ESKF as a pose source; Censi 2007): the estimate ``q`` is a function of
the ranges ``z`` of *both* scans (the current points directly, the reference points through
the fitted lines), so to first order, with the final kept matches fixed,

    C = H^-1 G H^-1,    G = M Sigma_z M^T,    M = d g / d z,    g = sum_i w_i e_i J_i

(:func:`point_to_line_gradient_covariance`), ``Sigma_z`` the scanner's range noise
``diag((range_sigma_m + range_sigma_rel r_k)^2)`` over every beam of both scans. A line's
anchor and normal move with each range fitted into it, so matches that share reference
points are correlated and ``M`` carries that. The previous ``sigma^2 H^-1`` (one scan's
noise, ``sigma`` from the trimmed residuals, one sigma for every range) was too small: mean
NEES 14-18 where 3 is expected (docs/lidar2d.md). The selection of the kept matches by their
residuals (trimming) is not modelled. ``H`` is inverted in the scaled eigenbasis; a
direction whose eigenvalue is below ``degeneracy_ratio`` times the largest carries no scan
information (the estimate there is the initial guess) and reports ``unobserved_sigma_m``
instead, uncorrelated with the rest (flagged in ``degenerate``).

References:
    A. Censi, "An ICP variant using a point-to-line metric", ICRA 2008.
    A. Censi, "An accurate closed-form estimate of ICP's covariance", ICRA 2007.
    D. Chetverikov et al., "The Trimmed Iterative Closest Point algorithm", ICPR 2002.
    J. Zhang, M. Kaess, S. Singh, "On degeneracy of optimization-based state estimation
    problems", ICRA 2016.

Example:
    >>> import torch
    >>> from msf_torch.geometry.se2 import between
    >>> from msf_torch.lidar.plicp import PlicpConfig, plicp, scan_points
    >>> from msf_torch.sim.lidar2d import LidarSpec, scan_at, warehouse_map
    >>> spec = LidarSpec()
    >>> poses = torch.tensor([[3.0, 10.0, 1.5], [3.3, 10.2, 1.6]], dtype=torch.float64)
    >>> ranges, _ = scan_at(warehouse_map(), poses, spec)  # noise-free
    >>> points, valid = scan_points(ranges, spec.angles())
    >>> config = PlicpConfig(epsilon_xy_m=1e-12, epsilon_theta_rad=1e-12)
    >>> result = plicp(points[:1], valid[:1], points[1:], valid[1:],
    ...                torch.zeros(1, 3, dtype=torch.float64), config)
    >>> bool((result.pose[0] - between(poses[0], poses[1])).abs().max() < 1e-9)
    True
"""

from __future__ import annotations

__all__ = [
    "PlicpConfig",
    "ReferenceLines",
    "Correspondences",
    "PlicpResult",
    "scan_points",
    "fit_lines",
    "correspondences",
    "point_to_line_step",
    "point_to_line_hessian",
    "point_to_line_gradient_covariance",
    "plicp",
]

import math
from dataclasses import dataclass

import torch

from msf_torch.geometry.se2 import transform_points, wrap_angle


@dataclass(frozen=True)
class PlicpConfig:
    """PLICP settings (see the module docstring).

    Attributes:
        max_correspondence_m: largest distance from a moved current point to its anchor, m.
        keep_fraction: share of the matches kept each iteration (smallest residuals).
        max_iterations: most iterations.
        epsilon_xy_m: converged when the translation step is below this, m ...
        epsilon_theta_rad: ... and the rotation step below this, rad.
        line_window: neighbours on each side (in beams) fitted into a reference line.
        line_max_gap_m: neighbours farther than this from the centre point are left out, m.
        line_max_rms_m: lines whose fit rms exceeds this are dropped, m.
        min_correspondences: fewer kept matches fail the pair.
        degeneracy_ratio: scaled-Hessian eigenvalue ratio below which a direction is
            treated as unobserved.
        unobserved_sigma_m: 1-sigma reported along an unobserved direction, m (rotation:
            this divided by the rms range of the matched points, rad).
        range_sigma_m: the scanner's range noise at zero range, m ...
        range_sigma_rel: ... and its growth per metre of range (m/m): a range ``r`` has
            noise ``N(0, (range_sigma_m + range_sigma_rel r)^2)``, independent per beam
            (defaults: the simulator's SICK TiM571-class scanner). The covariance propagates
            it from both scans (see the module docstring).
    """

    max_correspondence_m: float = 0.5
    keep_fraction: float = 0.8
    max_iterations: int = 50
    epsilon_xy_m: float = 1e-4
    epsilon_theta_rad: float = 1e-4
    line_window: int = 10
    line_max_gap_m: float = 0.2
    line_max_rms_m: float = 0.03
    min_correspondences: int = 10
    degeneracy_ratio: float = 1e-2
    unobserved_sigma_m: float = 1.0
    range_sigma_m: float = 0.01
    range_sigma_rel: float = 0.001

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        for name in (
            "max_correspondence_m",
            "epsilon_xy_m",
            "epsilon_theta_rad",
            "line_max_gap_m",
            "line_max_rms_m",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"PlicpConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.keep_fraction <= 1:
            raise ValueError(
                f"PlicpConfig.keep_fraction must be in (0, 1], got {self.keep_fraction}"
            )
        if self.max_iterations < 1 or self.line_window < 1 or self.min_correspondences < 3:
            raise ValueError(
                "PlicpConfig: max_iterations >= 1, line_window >= 1 and "
                "min_correspondences >= 3 are required"
            )
        if not (
            self.range_sigma_m >= 0
            and self.range_sigma_rel >= 0
            and self.range_sigma_m + self.range_sigma_rel > 0
        ):
            raise ValueError(
                "PlicpConfig: range_sigma_m and range_sigma_rel must be >= 0 and not both 0, "
                f"got {self.range_sigma_m!r} and {self.range_sigma_rel!r}"
            )
        if not 0 <= self.degeneracy_ratio < 1:
            raise ValueError(
                f"PlicpConfig.degeneracy_ratio must be in [0, 1), got {self.degeneracy_ratio}"
            )


@dataclass
class ReferenceLines:
    """Lines of reference scans.

    Attributes:
        anchor: (B, M, 2) a point on each line (the fitted centroid), m.
        normal: (B, M, 2) unit normal.
        valid: (B, M) bool, the point has a line.
        member: (B, M, 2w + 1) bool, reference point ``m + o - w`` (``o`` = 0 .. 2w, ``w`` =
            ``line_window``) is one of the points fitted into line ``m``.
    """

    anchor: torch.Tensor
    normal: torch.Tensor
    valid: torch.Tensor
    member: torch.Tensor


@dataclass
class Correspondences:
    """Matches of current points to reference lines at a pose.

    Attributes:
        anchor: (B, N, 2) anchor of each current point's line, m (0 where unmatched).
        normal: (B, N, 2) its unit normal.
        residual: (B, N) signed point-to-line distance at the pose, m (0 where unmatched).
        keep: (B, N) bool, matched and among the best ``keep_fraction``.
        count: (B,) kept matches.
        matched: (B, N) bool, within ``max_correspondence_m`` of an anchor (before trimming).
        matched_normal: (B, N, 2) the unit normal of every match (0 where unmatched).
        index: (B, N) the reference line (point index) each current point is matched to
            (meaningful where ``matched``).
    """

    anchor: torch.Tensor
    normal: torch.Tensor
    residual: torch.Tensor
    keep: torch.Tensor
    count: torch.Tensor
    matched: torch.Tensor
    matched_normal: torch.Tensor
    index: torch.Tensor


@dataclass
class PlicpResult:
    """Per-pair PLICP outcome.

    Attributes:
        pose: (B, 3) ``[x, y, theta]`` of the current scan in the reference frame, m, rad.
        covariance: (B, 3, 3) of ``pose``, m^2, m rad, rad^2.
        iterations: (B,) steps taken.
        converged: (B,) bool, the step fell below the epsilons.
        failed: (B,) bool, too few matches.
        degenerate: (B,) bool, some direction was unobserved at the end.
        condition: (B,) smallest / largest eigenvalue of the scaled Hessian.
        correspondences: (B,) kept matches at the end.
        residual_rms: (B,) rms point-to-line distance of the kept matches, m.
    """

    pose: torch.Tensor
    covariance: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    failed: torch.Tensor
    degenerate: torch.Tensor
    condition: torch.Tensor
    correspondences: torch.Tensor
    residual_rms: torch.Tensor


def scan_points(ranges: torch.Tensor, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Scans (B, K) of ranges (m; NaN, inf or <= 0 = no return, as scanners that report 0
    for a missing echo) at beam angles (K,) rad -> points (B, K, 2) in the sensor frame (0
    where invalid) and validity (B, K).

    Raises:
        ValueError: ``angles`` is not (K,) for ranges (..., K) (names both shapes).
    """
    if angles.ndim != 1 or ranges.shape[-1:] != angles.shape:
        raise ValueError(
            f"scan_points: ranges (..., K) and angles (K,) needed, got ranges "
            f"{tuple(ranges.shape)} and angles {tuple(angles.shape)}"
        )
    valid = torch.isfinite(ranges) & (ranges > 0)
    r = torch.where(valid, ranges, 0.0)
    points = torch.stack((r * torch.cos(angles), r * torch.sin(angles)), -1)
    return points, valid


def fit_lines(points: torch.Tensor, valid: torch.Tensor, config: PlicpConfig) -> ReferenceLines:
    """Lines through each point's scan neighbourhood (step 1 of the module docstring).

    Args:
        points: (B, M, 2) reference points in scan order, m.
        valid: (B, M) bool.
        config: ``line_window``, ``line_max_gap_m``, ``line_max_rms_m``.
    """
    w = config.line_window
    _, m = valid.shape
    offsets = torch.arange(-w, w + 1, device=points.device)
    index = torch.arange(m, device=points.device)[:, None] + offsets  # (M, 2w + 1)
    inside = (index >= 0) & (index < m)
    index = index.clamp(0, m - 1)
    neighbours = points[:, index]  # (B, M, 2w + 1, 2)
    member = valid[:, index] & inside & valid[..., None]
    gap = (neighbours - points[:, :, None]).norm(dim=-1)
    member = member & (gap <= config.line_max_gap_m)
    weight = member.to(points.dtype)
    count = weight.sum(-1)
    centroid = (weight[..., None] * neighbours).sum(-2) / count.clamp(min=1.0)[..., None]
    centred = (neighbours - centroid[:, :, None]) * weight[..., None]
    scatter = centred.mT @ centred / count.clamp(min=1.0)[..., None, None]  # (B, M, 2, 2)
    # smallest eigenpair of a symmetric 2x2 in closed form
    sxx, sxy, syy = scatter[..., 0, 0], scatter[..., 0, 1], scatter[..., 1, 1]
    half_trace = 0.5 * (sxx + syy)
    radius = torch.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    smallest = (half_trace - radius).clamp(min=0.0)
    # the normal is perpendicular to the principal direction (angle phi, tan 2 phi =
    # 2 sxy / (sxx - syy))
    phi = 0.5 * torch.atan2(2.0 * sxy, sxx - syy)
    normal = torch.stack((-torch.sin(phi), torch.cos(phi)), -1)
    ok = (count >= 3) & (smallest.sqrt() <= config.line_max_rms_m)
    return ReferenceLines(anchor=centroid, normal=normal, valid=ok, member=member)


def correspondences(
    pose: torch.Tensor,
    points: torch.Tensor,
    valid: torch.Tensor,
    lines: ReferenceLines,
    config: PlicpConfig,
) -> Correspondences:
    """Nearest-anchor matches within ``max_correspondence_m``, trimmed to the best
    ``keep_fraction`` by point-to-line distance (step 2 of the module docstring).

    Args:
        pose: (B, 3) current estimate of the current scan in the reference frame.
        points: (B, N, 2) current points, m.
        valid: (B, N) bool.
        lines: the reference scans' lines (B, M, ...).
        config: ``max_correspondence_m``, ``keep_fraction``.
    """
    moved = transform_points(pose, points)
    # squared distances |m|^2 - 2 m.a + |a|^2 (one batched matrix product); invalid anchors
    # sit at infinity
    far = torch.where(lines.valid, (lines.anchor**2).sum(-1), math.inf)
    square = torch.baddbmm(far[:, None, :], moved, lines.anchor.mT, alpha=-2.0)
    index = square.argmin(dim=-1)  # (B, N)
    gather = index[..., None].expand(-1, -1, 2)
    anchor = torch.gather(lines.anchor, 1, gather)
    normal = torch.gather(lines.normal, 1, gather)
    nearest = (moved - anchor).norm(dim=-1)
    line_ok = torch.gather(lines.valid, 1, index)
    matched = valid & line_ok & (nearest <= config.max_correspondence_m)
    residual = torch.where(matched, ((moved - anchor) * normal).sum(-1), 0.0)
    size = torch.where(matched, residual.abs(), math.inf)
    rank = size.argsort(dim=-1).argsort(dim=-1)
    n_matched = matched.sum(-1)
    n_keep = torch.ceil(config.keep_fraction * n_matched.to(points.dtype)).long()
    keep = matched & (rank < n_keep[:, None])
    zero = torch.zeros_like(anchor)
    return Correspondences(
        anchor=torch.where(keep[..., None], anchor, zero),
        normal=torch.where(keep[..., None], normal, zero),
        residual=torch.where(keep, residual, 0.0),
        keep=keep,
        count=keep.sum(-1),
        matched=matched,
        matched_normal=torch.where(matched[..., None], normal, zero),
        index=index,
    )


def _theta_objective(theta, s_mat, g):
    c, s = torch.cos(theta), torch.sin(theta)
    quad = s_mat[..., 0, 0, None] * c * c + 2 * s_mat[..., 0, 1, None] * c * s
    quad = quad + s_mat[..., 1, 1, None] * s * s
    return quad - 2.0 * (g[..., 0, None] * c + g[..., 1, None] * s)


def point_to_line_step(
    points: torch.Tensor,
    anchor: torch.Tensor,
    normal: torch.Tensor,
    weight: torch.Tensor,
    prior_xy: torch.Tensor,
    prior_weight: float = 1e-9,
) -> torch.Tensor:
    """Exact minimiser of ``sum_i w_i (n_i^T (R(theta) p_i + t - a_i))^2 + mu |t - t_0|^2``
    (step 3 of the module docstring), ``mu = prior_weight * trace(A_tt)``.

    Args:
        points: (B, N, 2) current points in their own frame, m.
        anchor: (B, N, 2) matched line anchors, m.
        normal: (B, N, 2) matched unit normals.
        weight: (B, N) weights ``w_i`` (0 drops a match).
        prior_xy: (B, 2) ``t_0``, m.
        prior_weight: relative weight of the prior.

    Returns:
        (B, 3) ``[t_x, t_y, theta]``, the global minimiser over theta.
    """
    nx, ny = normal[..., 0], normal[..., 1]
    px, py = points[..., 0], points[..., 1]
    u = torch.stack((nx, ny, nx * px + ny * py, ny * px - nx * py), -1)  # (B, N, 4)
    d = (normal * anchor).sum(-1)
    wu = weight[..., None] * u
    a_mat = wu.mT @ u  # (B, 4, 4)
    h = (wu * d[..., None]).sum(-2)  # (B, 4)
    eye2 = torch.eye(2, dtype=points.dtype, device=points.device)
    mu = prior_weight * (a_mat[:, 0, 0] + a_mat[:, 1, 1]) + torch.finfo(points.dtype).tiny
    a_tt = a_mat[:, :2, :2] + mu[:, None, None] * eye2
    a_tr = a_mat[:, :2, 2:]
    h_t = h[:, :2] + mu[:, None] * prior_xy
    h_r = h[:, 2:]
    solve_r = torch.linalg.solve(a_tt, a_tr)  # A1^-1 A2
    solve_h = torch.linalg.solve(a_tt, h_t[..., None])[..., 0]  # A1^-1 h_t
    s_mat = a_mat[:, 2:, 2:] - a_tr.mT @ solve_r
    g = h_r - (a_tr.mT @ solve_h[..., None])[..., 0]
    # f'(theta) = P sin 2θ + Q cos 2θ + 2 g1 sin θ - 2 g2 cos θ; times 2 z^2 with z = e^{iθ}:
    # (Q - iP) z^4 - 2 (g2 + i g1) z^3 + 2 (i g1 - g2) z + (Q + iP) = 0
    p_coef = s_mat[:, 1, 1] - s_mat[:, 0, 0]
    q_coef = 2.0 * s_mat[:, 0, 1]
    g1, g2 = g[:, 0], g[:, 1]
    c4 = torch.complex(q_coef, -p_coef)
    c3 = torch.complex(-2.0 * g2, -2.0 * g1)
    c1 = torch.complex(-2.0 * g2, 2.0 * g1)
    c0 = torch.complex(q_coef, p_coef)
    scale = torch.stack((c4.abs(), c3.abs()), -1).amax(-1).clamp(min=torch.finfo(points.dtype).tiny)
    quartic = c4.abs() > 1e-12 * scale
    lead = torch.where(quartic, c4, torch.ones_like(c4))
    batch = points.shape[0]
    companion = torch.zeros(batch, 4, 4, dtype=c4.dtype, device=points.device)
    companion[:, 1, 0] = 1.0
    companion[:, 2, 1] = 1.0
    companion[:, 3, 2] = 1.0
    companion[:, 0, 3] = -c0 / lead
    companion[:, 1, 3] = -c1 / lead
    companion[:, 3, 3] = -c3 / lead
    roots = torch.linalg.eigvals(companion)  # (B, 4)
    # when c4 = c0 = 0 the stationary points solve c3 z^2 + c1 = 0
    safe_c3 = torch.where(c3.abs() > 0, c3, torch.ones_like(c3))
    square = torch.sqrt(-c1 / safe_c3)
    quadratic = torch.stack((square, -square), -1)
    root_angles = torch.where(
        quartic[:, None], torch.angle(roots), torch.angle(quadratic[:, :1]).expand(-1, 4)
    )
    grid = torch.arange(8, dtype=points.dtype, device=points.device) * (math.pi / 4)
    candidates = torch.cat((root_angles, torch.angle(quadratic), grid.expand(batch, -1)), -1)
    values = _theta_objective(candidates, s_mat, g)
    theta = torch.gather(candidates, 1, values.argmin(-1, keepdim=True))[:, 0]
    for _ in range(3):  # Newton polish on f(theta)
        c2, s2 = torch.cos(2 * theta), torch.sin(2 * theta)
        c1_, s1_ = torch.cos(theta), torch.sin(theta)
        first = p_coef * s2 + q_coef * c2 + 2 * g1 * s1_ - 2 * g2 * c1_
        second = 2 * p_coef * c2 - 2 * q_coef * s2 + 2 * g1 * c1_ + 2 * g2 * s1_
        step = torch.where(second > 0, first / torch.where(second > 0, second, 1.0), 0.0)
        theta = theta - step
    r = torch.stack((torch.cos(theta), torch.sin(theta)), -1)
    t = solve_h - (solve_r @ r[..., None])[..., 0]
    return torch.cat((t, wrap_angle(theta)[:, None]), -1)


def _residual_jacobian(pose: torch.Tensor, points: torch.Tensor, normal: torch.Tensor):
    """``J_i = [n_i, n_i^T R'(theta) p_i]`` (B, N, 3): the point-to-line residual's
    derivative by ``[x, y, theta]`` at ``pose`` (B, 3); points and normals (B, N, 2)."""
    c, s = torch.cos(pose[:, 2:3]), torch.sin(pose[:, 2:3])
    px, py = points[..., 0], points[..., 1]
    d_theta = normal[..., 0] * (-s * px - c * py) + normal[..., 1] * (c * px - s * py)
    return torch.cat((normal, d_theta[..., None]), -1)


def point_to_line_hessian(
    pose: torch.Tensor, points: torch.Tensor, normal: torch.Tensor, weight: torch.Tensor
) -> torch.Tensor:
    """Gauss-Newton Hessian ``sum_i w_i J_i J_i^T`` (B, 3, 3) of the point-to-line cost at
    ``pose`` (B, 3), ``J_i = [n_i, n_i^T R'(theta) p_i]``; points and normals (B, N, 2),
    weights (B, N)."""
    jac = _residual_jacobian(pose, points, normal)  # (B, N, 3)
    return (weight[..., None] * jac).mT @ jac


def _range_noise(points: torch.Tensor, config: PlicpConfig):
    """Beam direction (..., 2) and range sigma (...,) m of sensor-frame points (..., 2)."""
    r = points.norm(dim=-1)
    direction = points / r.clamp(min=torch.finfo(points.dtype).tiny)[..., None]
    return direction, config.range_sigma_m + config.range_sigma_rel * r


def point_to_line_gradient_covariance(
    pose: torch.Tensor,
    reference_points: torch.Tensor,
    lines: ReferenceLines,
    current_points: torch.Tensor,
    corr: Correspondences,
    config: PlicpConfig,
) -> torch.Tensor:
    """Covariance ``G = M Sigma_z M^T`` (B, 3, 3) of the cost gradient
    ``g = sum_i w_i e_i J_i`` under the range noise of both scans, to first order.

    ``M = d g / d z`` (B, 3, K_ref + K_cur) with ``z`` every range of both scans and
    ``Sigma_z = diag(sigma(r_k)^2)``, ``sigma(r) = range_sigma_m + range_sigma_rel r``, each
    range moving its point along its beam ``u_k`` (points are in the sensor frame). With the
    matches fixed, ``d g / d z = sum_i w_i J_i d e_i / d z``. The residual
    ``e_i = n^T (m_i - a)`` of current point ``m_i = R p_i + t`` against line ``(a, n)``,
    direction ``d``, fitted to reference points ``p_k``, ``k`` in ``K_j`` (``c`` of them,
    ``alpha_k = d^T (p_k - a)``, ``A = sum alpha_k^2``), moves with

    * its own range: ``d e_i / d r_i = n^T R u_i``;
    * each fitted range (centroid ``d a = d p_k / c``; principal-axis normal
      ``d n = -d alpha_k n^T d p_k / A``):
      ``d e_i / d r_k = -(1 / c + s_i alpha_k / A) n^T u_k`` with ``s_i = d^T (m_i - a)``.

    Terms proportional to the noise itself (``e_i d J_i / d z``; the fitted points' offsets
    ``n^T (p_k - a)`` from their line) are dropped: first order in the noise, exact on
    noise-free scans at the true pose.

    A reference point sits in up to ``2 line_window + 1`` lines, each matched by several
    current points: those matches are correlated, which summing ``M``'s columns over the
    reference ranges keeps (Censi 2007 with the line fit in the measurement function).

    Args:
        pose: (B, 3) the estimate ``[x, y, theta]``, m, rad.
        reference_points: (B, M, 2) reference scan points in its sensor frame, m.
        lines: their :func:`fit_lines` lines.
        current_points: (B, N, 2) current scan points in its sensor frame, m.
        corr: the kept matches at ``pose`` (:func:`correspondences`).
        config: ``range_sigma_m``, ``range_sigma_rel``.

    Returns:
        (B, 3, 3) ``G``: m^2 (translation block), m^3 (cross terms), m^4 (rotation).
    """
    width = lines.member.shape[-1]  # 2w + 1
    batch, m = reference_points.shape[:2]
    weight = corr.keep.to(pose.dtype)
    jac = weight[..., None] * _residual_jacobian(pose, current_points, corr.normal)  # (B, N, 3)
    normal = corr.normal
    direction = torch.stack((normal[..., 1], -normal[..., 0]), -1)
    # the current scan: one range per match
    beam, sigma = _range_noise(current_points, config)
    c, s = torch.cos(pose[:, 2:3]), torch.sin(pose[:, 2:3])
    turned = torch.stack(
        (c * beam[..., 0] - s * beam[..., 1], s * beam[..., 0] + c * beam[..., 1]), -1
    )
    own = jac * (sigma * (normal * turned).sum(-1))[..., None]  # (B, N, 3)
    # the reference scan: the ranges fitted into each matched line
    offsets = torch.arange(width, device=pose.device) - width // 2
    index = (corr.index[..., None] + offsets).clamp(0, m - 1)  # (B, N, 2w + 1)
    member = torch.gather(lines.member, 1, corr.index[..., None].expand(-1, -1, width))
    member = (member & corr.keep[..., None]).to(pose.dtype)
    flat = index.flatten(1)[..., None]  # (B, N (2w + 1), 1)
    fitted_points = torch.gather(reference_points, 1, flat.expand(-1, -1, 2))
    fitted_points = fitted_points.view(batch, -1, width, 2)  # (B, N, 2w + 1, 2)
    fitted = fitted_points - corr.anchor[:, :, None]
    alpha = (fitted * direction[:, :, None]).sum(-1)
    count = member.sum(-1).clamp(min=1.0)
    spread = (member * alpha**2).sum(-1)  # A; 0 only without members
    spread = torch.where(spread > 0, spread, 1.0)
    moved = transform_points(pose, current_points)
    along = ((moved - corr.anchor) * direction).sum(-1)[..., None] / spread[..., None]  # s_i / A
    ref_beam, _ = _range_noise(fitted_points, config)
    across = (ref_beam * normal[:, :, None]).sum(-1)
    de = -member * (1.0 / count[..., None] + along * alpha) * across  # (B, N, 2w + 1)
    columns = torch.zeros(batch, m, 3, dtype=pose.dtype, device=pose.device)
    columns.scatter_add_(1, flat.expand(-1, -1, 3), (de[..., None] * jac[:, :, None]).flatten(1, 2))
    _, ref_sigma = _range_noise(reference_points, config)
    columns = columns * ref_sigma[..., None]
    return own.mT @ own + columns.mT @ columns


def _scaled_eigen(hessian, points, weight, ratio):
    """Eigen-decomposition of ``D H D`` (``D = diag(1, 1, 1 / L)``) and ``D``'s diagonal."""
    w_sum = weight.sum(-1).clamp(min=1.0)
    length = torch.sqrt((weight * (points**2).sum(-1)).sum(-1) / w_sum).clamp(min=1e-3)
    scale = torch.stack((torch.ones_like(length), torch.ones_like(length), 1.0 / length), -1)
    scaled = hessian * scale[:, :, None] * scale[:, None, :]
    values, vectors = torch.linalg.eigh(scaled)
    top = values[:, -1:].clamp(min=torch.finfo(values.dtype).tiny)
    good = values >= ratio * top
    return values, vectors, good, scale, top


def plicp(
    reference_points: torch.Tensor,
    reference_valid: torch.Tensor,
    current_points: torch.Tensor,
    current_valid: torch.Tensor,
    initial: torch.Tensor,
    config: PlicpConfig | None = None,
) -> PlicpResult:
    """Align B current scans to B reference scans (see the module docstring).

    Memory grows as ``B * N * M`` doubles (the squared-distance table); chunk long batches.

    Args:
        reference_points: (B, M, 2) reference scan points in scan order, m.
        reference_valid: (B, M) bool.
        current_points: (B, N, 2) current scan points, m.
        current_valid: (B, N) bool.
        initial: (B, 3) initial guess of the current scan's pose in the reference frame
            (e.g. from wheel odometry; zeros = identity).
        config: settings (default :class:`PlicpConfig`).

    Raises:
        ValueError: the shapes disagree (names them) or a setting is out of range.
    """
    config = config or PlicpConfig()
    config.validate()
    batch = initial.shape[0]
    for name, tensor, dims in (
        ("reference_points", reference_points, 3),
        ("current_points", current_points, 3),
        ("reference_valid", reference_valid, 2),
        ("current_valid", current_valid, 2),
    ):
        if tensor.ndim != dims or tensor.shape[0] != batch:
            raise ValueError(
                f"plicp: {name} must have {dims} dims and batch {batch}, got {tuple(tensor.shape)}"
            )
    if initial.ndim != 2 or initial.shape[-1] != 3:
        raise ValueError(f"plicp: initial must be (B, 3), got {tuple(initial.shape)}")
    for kind, points, valid in (
        ("reference", reference_points, reference_valid),
        ("current", current_points, current_valid),
    ):
        if points.shape[-1] != 2 or valid.shape != points.shape[:-1]:
            raise ValueError(
                f"plicp: {kind}_points must be (B, n, 2) and {kind}_valid (B, n), got "
                f"{tuple(points.shape)} and {tuple(valid.shape)}"
            )
    lines = fit_lines(reference_points, reference_valid, config)
    pose = initial.clone()
    device = initial.device
    active = torch.ones(batch, dtype=torch.bool, device=device)
    converged = torch.zeros_like(active)
    failed = torch.zeros_like(active)
    iterations = torch.zeros(batch, dtype=torch.long, device=device)
    for _ in range(config.max_iterations):
        # work on the pairs still iterating only
        rows = active.nonzero()[:, 0]
        sub_lines = ReferenceLines(
            lines.anchor[rows], lines.normal[rows], lines.valid[rows], lines.member[rows]
        )
        points, sub_pose = current_points[rows], pose[rows]
        corr = correspondences(sub_pose, points, current_valid[rows], sub_lines, config)
        enough = corr.count >= config.min_correspondences
        failed[rows[~enough]] = True
        active[rows[~enough]] = False
        weight = corr.keep.to(pose.dtype)
        solved = point_to_line_step(points, corr.anchor, corr.normal, weight, sub_pose[:, :2])
        delta = torch.cat(
            (solved[:, :2] - sub_pose[:, :2], wrap_angle(solved[:, 2:] - sub_pose[:, 2:])), -1
        )
        geometry = corr.matched.to(pose.dtype)
        hessian = point_to_line_hessian(solved, points, corr.matched_normal, geometry)
        _, vectors, good, scale, _ = _scaled_eigen(
            hessian, points, geometry, config.degeneracy_ratio
        )
        scaled = delta / scale
        kept = vectors @ (good.to(pose.dtype)[..., None] * (vectors.mT @ scaled[..., None]))
        delta = kept[..., 0] * scale
        stepped = torch.cat(
            (sub_pose[:, :2] + delta[:, :2], wrap_angle(sub_pose[:, 2:] + delta[:, 2:])), -1
        )
        moved = rows[enough]
        pose[moved] = stepped[enough]
        iterations[moved] += 1
        small = (delta[:, :2].norm(dim=-1) < config.epsilon_xy_m) & (
            delta[:, 2].abs() < config.epsilon_theta_rad
        )
        done = rows[enough & small]
        converged[done] = True
        active[done] = False
        if not bool(active.any()):
            break
    corr = correspondences(pose, current_points, current_valid, lines, config)
    weight = corr.keep.to(pose.dtype)
    hessian = point_to_line_hessian(pose, current_points, corr.normal, weight)
    values, vectors, good, scale, top = _scaled_eigen(
        hessian, current_points, weight, config.degeneracy_ratio
    )
    count = corr.count.to(pose.dtype)
    # Censi's H^-1 G H^-1 in the scaled eigenbasis (q_s = D^-1 q: H_s = D H D, g_s = D g);
    # unobserved directions get unobserved_sigma_m and no correlation
    gradient = point_to_line_gradient_covariance(
        pose, reference_points, lines, current_points, corr, config
    )
    gradient = vectors.mT @ (gradient * scale[:, :, None] * scale[:, None, :]) @ vectors
    inverse = torch.where(good, 1.0 / torch.where(good, values, 1.0), 0.0)
    unobserved = (~good).to(values.dtype) * config.unobserved_sigma_m**2
    eigen = inverse[:, :, None] * gradient * inverse[:, None, :] + torch.diag_embed(unobserved)
    covariance = (vectors @ eigen @ vectors.mT) * (scale[:, :, None] * scale[:, None, :])
    return PlicpResult(
        pose=pose,
        covariance=covariance,
        iterations=iterations,
        converged=converged,
        failed=failed | (corr.count < config.min_correspondences),
        degenerate=~good.all(-1),
        condition=values[:, 0] / top[:, 0],
        correspondences=corr.count,
        residual_rms=torch.sqrt((corr.residual**2).sum(-1) / count.clamp(min=1.0)),
    )
