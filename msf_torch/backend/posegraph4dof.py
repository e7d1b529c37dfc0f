"""Four-degree-of-freedom poses for pose graphs of visual-inertial runs (x, y, z, yaw).

An IMU makes roll and pitch observable (gravity), so after visual-inertial odometry only the
position and the yaw drift. The loop-closing pose graph then moves each pose by a world
translation and a rotation about the world vertical, holding roll and pitch:

    p <- p + dp,    R <- Rz(dpsi) R          (tangent [dp (3, world, m), dpsi (rad)])

(:data:`YAW_POSITION`; storage ``[p, R row-major]`` like ``pose`` and ``se3``). The edges
keep the full relative-pose residual of :func:`msf_torch.sensors.pose.relative_pose_residual`
(``Log_SE3(Z^-1 T_i^-1 T_j)``, 6 rows): the optimum is the least-squares pose graph
restricted to the poses whose roll and pitch equal the odometry's. Its Jacobian w.r.t. the
4-dim step is the ``se3`` Jacobian times the derivative of the ``se3`` step that the 4-dim
step makes, ``Rz(dpsi) R = R Exp(R^T e_z dpsi)`` and ``p + dp = p + R (R^T dp)``:

    d[rho, phi] / d[dp, dpsi] = [[R^T, 0], [0, R^T e_z]]       (6, 4)

(:class:`YawBetweenFactor`). Use ``optimize_pose_graph(graph, dof=4)``
(:mod:`msf_torch.backend.posegraph`).

Reference: T. Qin, P. Li and S. Shen, "VINS-Mono", IEEE T-RO 34(4), 2018, section VIII
(4-DoF pose graph; there the residual itself is 4-dim).
"""

from __future__ import annotations

__all__ = ["YawPositionKind", "YAW_POSITION", "YawBetweenFactor", "yaw_position_map"]

from dataclasses import dataclass

import torch

from msf_torch.backend.factors import BetweenFactor
from msf_torch.backend.variables import VariableKind, pack_pose, unpack_pose
from msf_torch.sensors.pose import relative_pose_residual


def _yaw_rotation(yaw: torch.Tensor) -> torch.Tensor:
    """``Rz(yaw)`` (..., 3, 3) of angles (...) rad."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rows = (torch.stack((c, -s, zero), -1), torch.stack((s, c, zero), -1))
    return torch.stack((*rows, torch.stack((zero, zero, one), -1)), -2)


@dataclass(frozen=True)
class YawPositionKind(VariableKind):
    """Pose variables moved by a world translation and a world-vertical rotation."""

    def retract(self, value: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """``p + dp``, ``Rz(dpsi) R`` for values (..., 12) and steps (..., 4)."""
        position, rotation = unpack_pose(value)
        return pack_pose(position + step[..., 0:3], _yaw_rotation(step[..., 3]) @ rotation)


YAW_POSITION = YawPositionKind("yaw_position", 12, 4)


def yaw_position_map(rotation: torch.Tensor) -> torch.Tensor:
    """``d[rho, phi] / d[dp, dpsi]`` (..., 6, 4) at rotations (..., 3, 3) body -> world."""
    lead = rotation.shape[:-2]
    out = rotation.new_zeros(*lead, 6, 4)
    out[..., 0:3, 0:3] = rotation.mT
    out[..., 3:6, 3] = rotation.mT[..., :, 2]
    return out


class YawBetweenFactor(BetweenFactor):
    """Relative pose between :data:`YAW_POSITION` variables: the 6-row residual of
    :class:`~msf_torch.backend.factors.BetweenFactor`, Jacobians (B, F, 6, 4) by the chain
    rule of the module docstring. Arguments as for ``BetweenFactor``."""

    def _evaluate(self, values, jacobians: bool):
        p_i, r_i = unpack_pose(values[0])
        p_j, r_j = unpack_pose(values[1])
        xi, jac_i, jac_j = relative_pose_residual(
            p_i, r_i, p_j, r_j, self.rotation.expand_as(r_i), self.translation.expand_as(p_i)
        )
        if not jacobians:
            return xi, None
        return xi, [jac_i @ yaw_position_map(r_i), jac_j @ yaw_position_map(r_j)]
