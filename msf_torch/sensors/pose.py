"""Absolute pose measurement (visual / LiDAR odometry in a world-fixed map, or a prior).

``r = [p - z_p,  Log(R_z^T R)]`` (..., 6): position in m (world), rotation in rad (body).
Jacobian: ``dr_p/ddp = I``; ``dr_theta/ddtheta = J_r^-1(r_theta)`` (right perturbation).
"""

from __future__ import annotations

__all__ = ["pose_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_P, IDX_THETA
from msf_torch.sensors._jacobian import error_state_jacobian


def pose_residual(
    position: torch.Tensor,
    rotation: torch.Tensor,
    measured_position: torch.Tensor,
    measured_rotation: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose residual (..., 6) and Jacobian (..., 6, 15).

    Args:
        position: (..., 3) m. rotation: (..., 3, 3) body -> world.
        measured_position: (..., 3) m. measured_rotation: (..., 3, 3).
    """
    r_theta = so3.log(measured_rotation.mT @ rotation)
    residual = torch.cat((position - measured_position, r_theta), -1)
    eye = so3.identity(position.dtype, position.device)
    lead = residual.shape[:-1]
    jr_inv = torch.linalg.inv(so3.right_jacobian(r_theta))
    top = error_state_jacobian(3, [(IDX_P, eye.expand(*lead, 3, 3))], like=position)
    bottom = error_state_jacobian(3, [(IDX_THETA, jr_inv)], like=position)
    return residual, torch.cat((top, bottom), -2)
