"""Vehicle pseudo-measurements: non-holonomic constraint (NHC) and zero-velocity update.

NHC: a car or wheeled robot without wheel data does not slide sideways or jump, so the
body-frame velocity of the rear-axle point ``l`` has zero lateral and vertical parts:
``r = [R^T v + [w]x l]_{y,z} - 0``. These are rows 1-2 of the wheel residual's body
velocity (one formula, :func:`msf_torch.sensors.wheel.body_velocity_residual`).

Zero velocity: ``r = v - 0`` when the vehicle is detected stationary.
"""

from __future__ import annotations

__all__ = ["nonholonomic_residual", "zero_velocity_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_V
from msf_torch.sensors._jacobian import error_state_jacobian
from msf_torch.sensors.wheel import body_velocity_residual


def nonholonomic_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lateral and vertical body velocity (..., 2) m/s and Jacobian (..., 2, 15).

    Args: as :func:`msf_torch.sensors.wheel.body_velocity_residual` (no measurement: 0).
    """
    zero = torch.zeros_like(velocity)
    residual, jac = body_velocity_residual(velocity, rotation, gyro, gyro_bias, lever_arm, zero)
    return residual[..., 1:3], jac[..., 1:3, :]


def zero_velocity_residual(velocity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``r = v`` (..., 3) m/s with Jacobian (..., 3, 15) (identity at dv)."""
    eye = so3.identity(velocity.dtype, velocity.device)
    jac = error_state_jacobian(3, [(IDX_V, eye.expand(*velocity.shape[:-1], 3, 3))], like=velocity)
    return velocity, jac
