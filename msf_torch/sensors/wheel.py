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

__all__ = [
    "wheel_speed_and_yaw_rate",
    "body_velocity_residual",
    "wheel_residual",
    "wheel_increment_residual",
]

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


def wheel_increment_residual(
    position_i: torch.Tensor,
    rotation_i: torch.Tensor,
    position_j: torch.Tensor,
    rotation_j: torch.Tensor,
    increment: torch.Tensor,
    lever_arm: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Preintegrated planar wheel odometry between poses i and j (back-end keyframes).

    ``r = [(R_i^T (a_j - a_i))_{x,y} - (dx, dy), wrap(yaw(R_i^T R_j) - dyaw)]`` (..., 3),
    with ``a = p + R l`` the axle centre and ``[dx, dy, dyaw]`` the increment in the body
    frame of i (m, m, rad).

    Args:
        position_i, position_j: (..., 3) m. rotation_i, rotation_j: (..., 3, 3).
        increment: (..., 3). lever_arm: (3,) axle centre in the body frame, m.
    Returns:
        residual (..., 3) and Jacobians w.r.t. ``[dp, dtheta]`` of i and of j (..., 3, 6).
    """
    arm = lever_arm.expand_as(position_i)
    axle_i = position_i + (rotation_i @ arm[..., None]).squeeze(-1)
    axle_j = position_j + (rotation_j @ arm[..., None]).squeeze(-1)
    local = (rotation_i.mT @ (axle_j - axle_i)[..., None]).squeeze(-1)
    rel = rotation_i.mT @ rotation_j
    yaw = torch.atan2(rel[..., 1, 0], rel[..., 0, 0])
    dyaw = yaw - increment[..., 2]
    dyaw = torch.atan2(torch.sin(dyaw), torch.cos(dyaw))
    residual = torch.cat((local[..., 0:2] - increment[..., 0:2], dyaw[..., None]), -1)

    offset = (rotation_i.mT @ (axle_j - position_i)[..., None]).squeeze(-1)  # local + arm
    m00, m10, m20 = rel[..., 0, 0], rel[..., 1, 0], rel[..., 2, 0]
    norm2 = (m00 * m00 + m10 * m10)[..., None]
    # yaw = atan2(m10, m00); i turns rel by Exp(-th_i) on the left, j by Exp(th_j) on the right
    yaw_i = torch.stack((m00 * m20, m10 * m20, -(m00 * m00 + m10 * m10)), -1) / norm2
    yaw_j = (
        torch.stack(
            (
                torch.zeros_like(m00),
                m10 * rel[..., 0, 2] - m00 * rel[..., 1, 2],
                m00 * rel[..., 1, 1] - m10 * rel[..., 0, 1],
            ),
            -1,
        )
        / norm2
    )
    zeros = torch.zeros_like(position_i)
    jac_i = torch.cat(
        (
            torch.cat((-rotation_i.mT[..., 0:2, :], so3.hat(offset)[..., 0:2, :]), -1),
            torch.cat((zeros, yaw_i), -1)[..., None, :],
        ),
        -2,
    )
    jac_j = torch.cat(
        (
            torch.cat((rotation_i.mT[..., 0:2, :], -(rel @ so3.hat(arm))[..., 0:2, :]), -1),
            torch.cat((zeros, yaw_j), -1)[..., None, :],
        ),
        -2,
    )
    return residual, jac_i, jac_j
