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
    "Se2Kind",
    "SE2",
    "Se2BetweenFactor",
    "se2_between_residual",
    "se2_log",
    "held_vertices",
    "pose_graph_2d_problem",
]

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from msf_torch.backend.factors import _Binary, _Evaluated
from msf_torch.backend.problem import Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import VariableKind
from msf_torch.geometry.se2 import between, compose, rotation, wrap_angle
from msf_torch.io.g2o import PoseGraph
from msf_torch.io.g2o_2d import PoseGraph2D

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
    """The B = 1 least-squares problem of a planar pose graph.

    Args:
        graph: N vertices, E edges (any device; float64 recommended).
        robust: kernel applied to every edge, or None.
        fixed: row indices of the vertices held constant; None holds the file's ``FIX``
            vertices, else the first vertex.
        group: name of the variable group.

    Returns:
        a :class:`~msf_torch.backend.problem.Problem` with group ``group`` (:data:`SE2`,
        values (1, N, 3)) and one :class:`Se2BetweenFactor` type (E,).

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
    return Problem({group: (SE2, values)}, [factor], fixed={group: held})
