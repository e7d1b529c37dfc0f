"""Differential-drive wheel odometry as a body-velocity and yaw-rate measurement.

Kinematics (rim speeds ``v_l``, ``v_r`` in m/s, track width ``D`` in m):

    v = (v_r + v_l) / 2,    omega = (v_r - v_l) / D

The wheel residual compares the predicted velocity of the axle centre in the body frame,
``R^T v + [w]x l`` (``l`` = axle-centre lever arm from the IMU, ``w`` = bias-corrected gyro
rate), with ``[v, 0, 0]`` (the lateral and vertical zeros are the non-holonomic
constraint), and the bias-corrected gyro yaw rate ``w_z`` with ``omega``:

    r = [R^T v + [w]x l - (v, 0, 0),  (w_m,z - b_g,z) - omega]     (4,)

Sign convention ``r = h(x) - z``; Jacobian w.r.t. ``[dp, dv, dtheta, db_g, db_a]``.
"""

from __future__ import annotations

__all__ = ["wheel_speed_and_yaw_rate", "body_velocity_residual", "wheel_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_BG, IDX_THETA, IDX_V
from msf_torch.sensors._jacobian import error_state_jacobian


def wheel_speed_and_yaw_rate(
    left_speed: torch.Tensor, right_speed: torch.Tensor, track_width: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward speed (m/s) and yaw rate (rad/s) from rim speeds (...,) and track width (m)."""
    return 0.5 * (right_speed + left_speed), (right_speed - left_speed) / track_width


def body_velocity_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    measured: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Body-frame velocity of a point at ``lever_arm`` against a measurement.

    Args:
        velocity: (..., 3) world velocity of the IMU, m/s.
        rotation: (..., 3, 3) body -> world.
        gyro: (..., 3) raw gyro rate at the measurement time, rad/s.
        gyro_bias: (..., 3) rad/s.
        lever_arm: (..., 3) point position in the body frame, m.
        measured: (..., 3) measured body-frame velocity of that point, m/s.
    Returns:
        residual (..., 3) m/s and Jacobian (..., 3, 15).
    """
    v_body = (rotation.mT @ velocity[..., None]).squeeze(-1)
    omega = gyro - gyro_bias
    predicted = v_body + torch.linalg.cross(omega, lever_arm.expand_as(omega))
    residual = predicted - measured
    jac = error_state_jacobian(
        3,
        [
            (IDX_V, rotation.mT),
            (IDX_THETA, so3.hat(v_body)),
            (IDX_BG, so3.hat(lever_arm).expand(*omega.shape[:-1], 3, 3)),
        ],
        like=velocity,
    )
    return residual, jac


def wheel_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    left_speed: torch.Tensor,
    right_speed: torch.Tensor,
    track_width: torch.Tensor | float,
    lever_arm: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Full wheel residual (..., 4) = body velocity (3) and yaw rate (1), Jacobian (..., 4, 15).

    Args: as :func:`body_velocity_residual`; ``left_speed``/``right_speed`` (...,) m/s rim
    speeds; ``track_width`` m.
    """
    speed, yaw_rate = wheel_speed_and_yaw_rate(left_speed, right_speed, track_width)
    zero = torch.zeros_like(speed)
    measured = torch.stack((speed, zero, zero), -1)
    r_vel, h_vel = body_velocity_residual(velocity, rotation, gyro, gyro_bias, lever_arm, measured)
    r_yaw = (gyro[..., 2] - gyro_bias[..., 2] - yaw_rate)[..., None]
    h_yaw = _yaw_rate_jacobian(h_vel)
    return torch.cat((r_vel, r_yaw), -1), torch.cat((h_vel, h_yaw), -2)


def _yaw_rate_jacobian(like: torch.Tensor) -> torch.Tensor:
    """(..., 1, 15) Jacobian of ``w_m,z - b_g,z`` w.r.t. the error state: -1 at db_g,z."""
    row = torch.zeros(like.shape[-1], dtype=like.dtype, device=like.device)
    row[IDX_BG.start + 2] = -1.0
    return row.expand(*like.shape[:-2], 1, like.shape[-1])
