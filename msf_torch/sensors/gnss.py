"""GNSS position measurement with antenna lever arm.

``r = p + R l - z`` (..., 3) in m, world frame; ``l`` is the antenna position in the body
frame. Jacobian: ``dr/ddp = I``, ``dr/ddtheta = -R [l]x`` (right perturbation).
"""

from __future__ import annotations

__all__ = ["gnss_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_P, IDX_THETA
from msf_torch.sensors._jacobian import error_state_jacobian


def gnss_residual(
    position: torch.Tensor, rotation: torch.Tensor, lever_arm: torch.Tensor, measured: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """GNSS residual (..., 3) m and Jacobian (..., 3, 15).

    Args:
        position: (..., 3) IMU position in the world, m.
        rotation: (..., 3, 3) body -> world.
        lever_arm: (..., 3) antenna in the body frame, m.
        measured: (..., 3) antenna fix in the world frame, m.
    """
    arm_world = (rotation @ lever_arm[..., None]).squeeze(-1)
    residual = position + arm_world - measured
    eye = so3.identity(position.dtype, position.device)
    lead = residual.shape[:-1]
    jac = error_state_jacobian(
        3,
        [
            (IDX_P, eye.expand(*lead, 3, 3)),
            (IDX_THETA, -rotation @ so3.hat(lever_arm).expand(*lead, 3, 3)),
        ],
        like=position,
    )
    return residual, jac
