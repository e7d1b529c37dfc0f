"""Planar pose graphs (SE(2)): the variable kind, the relative-pose factor and the problem of
a :class:`~msf_torch.io.g2o_2d.PoseGraph2D`, solved by
:func:`~msf_torch.backend.posegraph.optimize_pose_graph` with GTSAM's cost.

Variables (:data:`SE2`): storage ``[x, y, theta]`` (m, m, rad), tangent ``xi = [rho_x,
rho_y, omega]`` in the body frame, moved by the exponential map as GTSAM's ``Pose2``
retraction moves them, ``T <- T Exp(xi)``:

    Exp(xi) = (V(omega) rho, omega),  V(w) = [[sin w, cos w - 1], [1 - cos w, sin w]] / w

(heading wrapped to (-pi, pi]). Edges (:class:`Se2BetweenFactor`): GTSAM's
``BetweenFactor<Pose2>`` error, the SE(2) logarithm of the error pose
``E = Z^-1 T_i^-1 T_j = (t, theta)`` (theta wrapped to (-pi, pi]):

    e = Log(E) = [A t_x + a t_y, -a t_x + A t_y, theta],  a = theta / 2,  A = a cot(a)

(``V(theta)^-1 t``). Jacobians, by the chain rule through E's parameters ``(t, theta)``:
``de/dE = [[A, a, A' t_x + t_y / 2], [-a, A, A' t_y - t_x / 2], [0, 0, 1]]`` with
``A' = dA/dtheta``; a step of j moves E by ``E Exp(xi_j)``, i.e. ``dE/dxi_j =
[[R(theta), 0], [0, 1]]``; a step of i by ``Z^-1 Exp(-xi_i) T_i^-1 T_j``, i.e.
``dE/dxi_i = [[-R(-theta_z), R(-theta_z) S d], [0, 0, -1]]`` with ``d = R(-theta_i)
(p_j - p_i)`` and ``S = [[0, 1], [-1, 0]]``. (GTSAM's gtsam wheel is built with the
exponential-map ``Pose2`` chart; g2o's ``EdgeSE2`` uses ``[t, theta]`` of the same error
pose, which agrees to first order.)

Example::

    from msf_torch.backend.posegraph import optimize_pose_graph
    from msf_torch.io import gtsam_pose_graph_path, read_pose_graph_2d
    graph = read_pose_graph_2d(gtsam_pose_graph_path("w10000.graph"))
    result = optimize_pose_graph(graph)
    result.final_cost, result.graph.positions  # GTSAM-convention cost; (N, 2) m
"""

from __future__ import annotations

__all__ = [
    "POINT2",
    "Point2Kind",
    "Se2Kind",
    "SE2",
    "Se2BearingRangeFactor",
    "Se2BetweenFactor",
    "se2_bearing_range_residual",
    "se2_between_residual",
    "se2_log",
    "held_vertices",
    "pose_graph_2d_problem",
]

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from msf_torch.backend.factors import _Binary, _Evaluated, sqrt_information
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import VariableKind
from msf_torch.geometry.se2 import between, compose, rotation, wrap_angle
from msf_torch.io.g2o import PoseGraph
from msf_torch.io.g2o_2d import PoseGraph2D

LANDMARK_GROUP = "landmark"
"""Variable group of a 2-D graph's landmarks (:data:`POINT2`) in :func:`pose_graph_2d_problem`."""
_SMALL_ANGLE = 1e-4  # rad: below it the series forms (error ~theta^6)


def _exp_translation(rho: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """``V(omega) rho`` (..., 2) of the SE(2) exponential for rho (..., 2), omega (...)."""
    small = omega.abs() < _SMALL_ANGLE
    safe = torch.where(small, torch.ones_like(omega), omega)
    sin_w = torch.where(small, 1.0 - omega**2 / 6.0, torch.sin(safe) / safe)
    cos_w = torch.where(small, omega / 2.0 - omega**3 / 24.0, (1.0 - torch.cos(safe)) / safe)
    x = sin_w * rho[..., 0] - cos_w * rho[..., 1]
    y = cos_w * rho[..., 0] + sin_w * rho[..., 1]
    return torch.stack((x, y), -1)


def se2_log(pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SE(2) logarithm of poses ``(t, theta)`` (..., 3) (GTSAM's ``Pose2.Logmap``).

    Returns:
        ``xi`` (..., 3) ``[rho_x, rho_y, omega]`` (omega = theta wrapped to (-pi, pi]), and
        ``A = (omega / 2) cot(omega / 2)`` (...) with its derivative ``dA/domega`` (...).
    """
    omega = wrap_angle(pose[..., 2])
    half = 0.5 * omega
    small = omega.abs() < _SMALL_ANGLE
    safe = torch.where(small, torch.ones_like(half), half)
    tan_half = torch.tan(safe)
    big_a = torch.where(small, 1.0 - omega**2 / 12.0, safe / tan_half)
    slope = torch.where(
        small,
        -omega / 6.0,
        0.5 / tan_half - 0.5 * safe / torch.sin(safe) ** 2,
    )
    t_x, t_y = pose[..., 0], pose[..., 1]
    xi = torch.stack((big_a * t_x + half * t_y, -half * t_x + big_a * t_y, omega), -1)
    return xi, big_a, slope


@dataclass(frozen=True)
class Se2Kind(VariableKind):
    """Planar poses ``[x, y, theta]`` moved by ``T Exp(xi)`` (GTSAM's ``Pose2`` retraction)."""

    def retract(self, value: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """``T Exp(step)`` for values (..., 3) and steps (..., 3); heading in (-pi, pi]."""
        local = _exp_translation(step[..., 0:2], step[..., 2])
        return compose(value, torch.cat((local, step[..., 2:3]), -1))


SE2 = Se2Kind("se2", 3, 3)


@dataclass(frozen=True)
class Point2Kind(VariableKind):
    """Planar points ``[x, y]`` (m); steps add."""

    def retract(self, value: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """``value + step`` (..., 2)."""
        return value + step


POINT2 = Point2Kind("point2", 2, 2)


def se2_between_residual(
    pose_i: torch.Tensor,
    pose_j: torch.Tensor,
    measured_translation: torch.Tensor,
    measured_heading: torch.Tensor,
    jacobians: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Error ``Log(Z^-1 T_i^-1 T_j)`` (GTSAM's ``BetweenFactor<Pose2>``) and its Jacobians.

    Args:
        pose_i, pose_j: (..., 3) ``[x, y, theta]`` (m, m, rad).
        measured_translation: (..., 2) m and measured_heading: (...) rad of ``Z = T_i^-1 T_j``.
        jacobians: also return the Jacobians.

    Returns:
        residual (..., 3) ``[rho_x, rho_y, omega]`` (m, m, rad; omega in (-pi, pi]) and the
        Jacobians (..., 3, 3) w.r.t. the tangent steps of i and j (module docstring), or
        None, None.
    """
    measured = torch.cat((measured_translation, measured_heading[..., None]), -1)
    relative = between(pose_i, pose_j)  # T_i^-1 T_j
    error = between(measured, relative)  # Z^-1 T_i^-1 T_j
    residual, big_a, slope = se2_log(error)
    if not jacobians:
        return residual, None, None
    lead = residual.shape[:-1]
    half = 0.5 * residual[..., 2]
    t_x, t_y = error[..., 0], error[..., 1]
    zero, one = torch.zeros_like(half), torch.ones_like(half)
    log_jac = torch.stack(
        (
            torch.stack((big_a, half, slope * t_x + 0.5 * t_y), -1),
            torch.stack((-half, big_a, slope * t_y - 0.5 * t_x), -1),
            torch.stack((zero, zero, one), -1),
        ),
        -2,
    )
    rot_z_t = rotation(-measured_heading)
    moved_i = residual.new_zeros(*lead, 3, 3)
    moved_i[..., 0:2, 0:2] = -rot_z_t
    swapped = torch.stack((relative[..., 1], -relative[..., 0]), -1)  # S d
    moved_i[..., 0:2, 2] = (rot_z_t @ swapped[..., None]).squeeze(-1)
    moved_i[..., 2, 2] = -1.0
    moved_j = residual.new_zeros(*lead, 3, 3)
    moved_j[..., 0:2, 0:2] = rotation(error[..., 2])
    moved_j[..., 2, 2] = 1.0
    return residual, log_jac @ moved_i, log_jac @ moved_j


class Se2BetweenFactor(_Evaluated, _Binary):
    """Relative planar pose (odometry, loop closure) between :data:`SE2` variables:
    :func:`se2_between_residual`, GTSAM's ``BetweenFactor<Pose2>`` error.

    Args:
        group, index_i, index_j: variables (F,). translation: (B|1, F, 2) m and heading:
        (B|1, F) rad of the measured ``T_i^-1 T_j``. covariance: (B|1, F, 3, 3) in
        ``[x, y, theta]``. kernel: robust kernel, or None for plain least squares.
    """

    batched = ("translation", "heading")

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        translation: torch.Tensor,
        heading: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index_i, index_j, covariance, kernel)
        self.translation, self.heading = translation, heading

    def _evaluate(self, values, jacobians: bool):
        lead = values[0].shape[:-1]
        residual, jac_i, jac_j = se2_between_residual(
            values[0],
            values[1],
            self.translation.expand(*lead, 2),
            self.heading.expand(*lead),
            jacobians,
        )
        return residual, [jac_i, jac_j] if jacobians else None


def se2_bearing_range_residual(
    pose: torch.Tensor,
    point: torch.Tensor,
    measured_bearing: torch.Tensor,
    measured_range: torch.Tensor,
    jacobians: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Bearing and range of a point seen from a pose, against the measured ones (GTSAM's
    ``BearingRangeFactor<Pose2, Point2>`` error) and the Jacobians.

    With ``d = R(theta)^T (l - p)`` the point in the pose's frame and ``r = |d|``:
    ``e = [wrap(atan2(d_y, d_x) - b), r - z]``. A step ``xi = [rho, omega]`` of the pose
    (``T Exp(xi)``) moves ``d`` by ``-rho - omega [-d_y, d_x]`` to first order, a step of
    the point by ``R(theta)^T``, so ``de/dxi = [[d_y / r^2, -d_x / r^2, -1], [-d_x / r,
    -d_y / r, 0]]`` and ``de/dl = [[-d_y, d_x] / r^2; d^T / r] R(theta)^T``.

    Args:
        pose: (..., 3) ``[x, y, theta]`` (m, m, rad). point: (..., 2) m, world frame.
        measured_bearing: (...) rad, from the pose's x axis, counter-clockwise.
        measured_range: (...) m.
        jacobians: also return the Jacobians.

    Returns:
        residual (..., 2) ``[rad, m]`` (bearing error in (-pi, pi]) and the Jacobians
        (..., 2, 3) w.r.t. the pose's tangent step and (..., 2, 2) w.r.t. the point, or
        None, None.
    """
    rot_t = rotation(pose[..., 2]).mT
    local = (rot_t @ (point - pose[..., 0:2])[..., None]).squeeze(-1)
    d_x, d_y = local[..., 0], local[..., 1]
    distance = torch.hypot(d_x, d_y)
    residual = torch.stack(
        (
            wrap_angle(torch.atan2(d_y, d_x) - measured_bearing),
            distance - measured_range,
        ),
        -1,
    )
    if not jacobians:
        return residual, None, None
    tiny = torch.finfo(pose.dtype).tiny
    inv_r = 1.0 / distance.clamp_min(tiny)
    inv_r2 = inv_r * inv_r
    zero = torch.zeros_like(d_x)
    jac_pose = torch.stack(
        (
            torch.stack((d_y * inv_r2, -d_x * inv_r2, -torch.ones_like(d_x)), -1),
            torch.stack((-d_x * inv_r, -d_y * inv_r, zero), -1),
        ),
        -2,
    )
    local_jac = torch.stack(
        (
            torch.stack((-d_y * inv_r2, d_x * inv_r2), -1),
            torch.stack((d_x * inv_r, d_y * inv_r), -1),
        ),
        -2,
    )
    return residual, jac_pose, local_jac @ rot_t


class Se2BearingRangeFactor(_Evaluated, Factor):
    """Bearing and range from an :data:`SE2` pose to a :data:`POINT2` landmark (a LiDAR
    tree-trunk or reflector detection): :func:`se2_bearing_range_residual`, GTSAM's
    ``BearingRangeFactor<Pose2, Point2>`` error.

    Args:
        pose_group, pose_index: the poses (F,). point_group, point_index: the landmarks (F,).
        bearings: (B|1, F) rad and ranges: (B|1, F) m, measured.
        covariance: (B|1, F, 2, 2) in ``[bearing, range]`` (rad^2, m^2).
        kernel: robust kernel, or None for plain least squares.
    """

    batched = ("bearings", "ranges")

    def __init__(
        self,
        pose_group: str,
        pose_index: torch.Tensor,
        point_group: str,
        point_index: torch.Tensor,
        bearings: torch.Tensor,
        ranges: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        self.slots = ((pose_group, pose_index.long()), (point_group, point_index.long()))
        self.sqrt_information = sqrt_information(covariance)
        self.kernel = kernel
        self.bearings, self.ranges = bearings, ranges

    def _evaluate(self, values, jacobians: bool):
        pose, point = values
        lead = pose.shape[:-1]
        residual, jac_pose, jac_point = se2_bearing_range_residual(
            pose, point, self.bearings.expand(lead), self.ranges.expand(lead), jacobians
        )
        return residual, [jac_pose, jac_point] if jacobians else None


def held_vertices(
    graph: PoseGraph | PoseGraph2D, fixed: Sequence[int] | torch.Tensor | None
) -> torch.Tensor:
    """(N,) bool mask of the vertices a pose-graph solve holds (the gauge): the rows
    ``fixed``, or when None the file's ``FIX`` vertices, else the first vertex.

    Raises:
        ValueError: a fixed row outside ``[0, N)``.
    """
    n = graph.num_vertices
    device = graph.positions.device
    if fixed is None:
        fixed = graph.fixed_rows() if graph.fixed_ids else (0,)
    index = torch.as_tensor(fixed, dtype=torch.int64, device=device).reshape(-1)
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n):
        raise ValueError(f"fixed vertex indices must lie in [0, {n}), got {index.tolist()}")
    held = torch.zeros(n, dtype=torch.bool, device=device)
    held[index] = True
    return held


def pose_graph_2d_problem(
    graph: PoseGraph2D,
    robust: RobustKernel | None = None,
    fixed: Sequence[int] | torch.Tensor | None = None,
    group: str = "pose",
) -> Problem:
    """The B = 1 least-squares problem of a planar pose graph, with its landmarks if any.

    Args:
        graph: N vertices, E edges, L landmarks, O sightings (any device; float64
            recommended).
        robust: kernel applied to every edge and sighting, or None.
        fixed: row indices of the vertices held constant; None holds the file's ``FIX``
            vertices, else the first vertex.
        group: name of the pose group.

    Returns:
        a :class:`~msf_torch.backend.problem.Problem` with group ``group`` (:data:`SE2`,
        values (1, N, 3)) and one :class:`Se2BetweenFactor` type (E,); with landmarks also
        group :data:`LANDMARK_GROUP` (:data:`POINT2`, values (1, L, 2)) and one
        :class:`Se2BearingRangeFactor` type (O,).

    Raises:
        ValueError: a malformed graph or a fixed index outside ``[0, N)``.
    """
    graph.check()
    dtype = graph.positions.dtype
    held = held_vertices(graph, fixed)
    covariance = torch.linalg.inv(graph.edge_information.to(dtype))
    factor = Se2BetweenFactor(
        group,
        graph.edge_index[:, 0],
        graph.edge_index[:, 1],
        graph.edge_translations.to(dtype)[None],
        graph.edge_headings.to(dtype)[None],
        covariance[None],
        kernel=robust,
    )
    headings = wrap_angle(graph.headings.to(dtype))
    values = torch.cat((graph.positions.to(dtype), headings[:, None]), -1)[None]
    variables = {group: (SE2, values)}
    factors: list[Factor] = [factor]
    if graph.num_landmarks:
        variables[LANDMARK_GROUP] = (POINT2, graph.landmark_positions.to(dtype)[None])
    if graph.num_observations:
        sigmas = graph.observation_sigmas.to(dtype)
        factors.append(
            Se2BearingRangeFactor(
                group,
                graph.observation_index[:, 0],
                LANDMARK_GROUP,
                graph.observation_index[:, 1],
                graph.observation_bearings.to(dtype)[None],
                graph.observation_ranges.to(dtype)[None],
                torch.diag_embed(sigmas * sigmas)[None],
                kernel=robust,
            )
        )
    return Problem(variables, factors, fixed={group: held})
