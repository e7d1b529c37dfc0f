"""Pose measurements: absolute poses and the mean angular rate of a drifting pose source.

Absolute pose (visual / LiDAR odometry in a world-fixed map, or a prior):
``r = [p - z_p,  Log(R_z^T R)]`` (..., 6): position in m (world), rotation in rad (body).
Jacobian: ``dr_p/ddp = I``; ``dr_theta/ddtheta = J_r^-1(r_theta)`` (right perturbation).

Mean angular rate of a pose source over an interval ``dt`` (odometry, drift-free): the
relative rotation gives ``z_w = Log(R_k-1^T R_k) / dt``, the gyro its bias-corrected mean
``w_bar - b_g`` over the same interval: ``r = w_bar - b_g - z_w`` (..., 3) rad/s, Jacobian
``-I`` at ``db_g``. (A source's mean body velocity uses the wheels' residual,
``sensors.wheel.body_velocity_residual``.)
"""

from __future__ import annotations

__all__ = ["pose_residual", "mean_rate_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_BG, IDX_P, IDX_THETA
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


def mean_rate_residual(
    mean_gyro: torch.Tensor, gyro_bias: torch.Tensor, measured_rate: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean angular-rate residual (..., 3) rad/s and Jacobian (..., 3, 15).

    Args:
        mean_gyro: (..., 3) mean raw gyro rate over the interval, rad/s.
        gyro_bias: (..., 3) rad/s.
        measured_rate: (..., 3) ``Log(R_k-1^T R_k) / dt`` of the source, rad/s (body).
    """
    residual = mean_gyro - gyro_bias - measured_rate
    eye = so3.identity(residual.dtype, residual.device)
    jac = error_state_jacobian(
        3, [(IDX_BG, -eye.expand(*residual.shape[:-1], 3, 3))], like=residual
    )
    return residual, jac
