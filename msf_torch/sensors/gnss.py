"""GNSS position and velocity measurements with antenna lever arm.

Position: ``r = p + R l - z`` (..., 3) in m, world frame; ``l`` is the antenna position in
the body frame. Jacobian: ``dr/ddp = I``, ``dr/ddtheta = -R [l]x`` (right perturbation).

Velocity (a receiver's Doppler velocity, or speed and course over ground): the antenna
moves with ``v + R (w x l)``, ``w = gyro - b_g`` the body rate, so
``r = v + R (w x l) - z`` (..., 3) in m/s, world frame. Jacobian: ``dr/ddv = I``,
``dr/ddtheta = -R [w x l]x``, ``dr/ddb_g = R [l]x`` (``w x l`` changes by
``-db_g x l = [l]x db_g``).
"""

from __future__ import annotations

__all__ = ["gnss_residual", "gnss_velocity_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_BG, IDX_P, IDX_THETA, IDX_V
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


def gnss_velocity_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    measured: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """GNSS velocity residual (..., 3) m/s and Jacobian (..., 3, 15).

    Args:
        velocity: (..., 3) IMU velocity in the world, m/s.
        rotation: (..., 3, 3) body -> world.
        gyro: (..., 3) raw gyro reading at the measurement time, rad/s.
        gyro_bias: (..., 3) rad/s.
        lever_arm: (..., 3) antenna in the body frame, m.
        measured: (..., 3) antenna velocity in the world frame (east, north, up), m/s.
    """
    rate = gyro - gyro_bias
    arm_velocity = torch.linalg.cross(rate, lever_arm.expand_as(rate))
    residual = velocity + (rotation @ arm_velocity[..., None]).squeeze(-1) - measured
    lead = residual.shape[:-1]
    eye = so3.identity(velocity.dtype, velocity.device)
    jac = error_state_jacobian(
        3,
        [
            (IDX_V, eye.expand(*lead, 3, 3)),
            (IDX_THETA, -rotation @ so3.hat(arm_velocity)),
            (IDX_BG, rotation @ so3.hat(lever_arm).expand(*lead, 3, 3)),
        ],
        like=velocity,
    )
    return residual, jac
