"""Pose measurements: absolute poses and the mean angular rate of a drifting pose source.

Absolute pose (visual / LiDAR odometry in a world-fixed map, or a prior):
``r = [p - z_p,  Log(R_z^T R)]`` (..., 6): position in m (world), rotation in rad (body).
Jacobian: ``dr_p/ddp = I``; ``dr_theta/ddtheta = J_r^-1(r_theta)`` (right perturbation).

Mean angular rate of a pose source over an interval ``dt`` (odometry, drift-free): the
relative rotation gives ``z_w = Log(R_k-1^T R_k) / dt``, the gyro its bias-corrected mean
``w_bar - b_g`` over the same interval: ``r = w_bar - b_g - z_w`` (..., 3) rad/s, Jacobian
``-I`` at ``db_g``. (A source's mean body velocity uses the wheels' residual,
``sensors.wheel.body_velocity_residual``.)

Pose of a drifting source against its own frame (``pose_source_fusion: drifting_frame``):
the source reports the body pose displaced by a slowly wandering offset ``(t_o, phi_o)``,
``z_p = p + t_o``, ``R_z = R Exp(phi_o)`` (``t_o`` world, m; ``phi_o`` body, rad: the error
model of ``msf_torch.sim.weather``), so
``r = [p + t_o - z_p,  Log(R_z^T R Exp(phi_o))]`` (..., 6). With the right errors
``R = R_hat Exp(dtheta)``, ``Exp(phi_o) = Exp(phi_hat) Exp(dphi)``:
``dr_p/ddp = dr_p/ddt = I``, ``dr_theta/ddtheta = J_r^-1(r_theta) Exp(phi_o)^T``,
``dr_theta/ddphi = J_r^-1(r_theta)``.
"""

from __future__ import annotations

__all__ = [
    "pose_residual",
    "mean_rate_residual",
    "relative_pose_residual",
    "drifting_frame_pose_residual",
    "drifting_frame_offset",
]

import torch

from msf_torch.geometry import se3, so3
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


def relative_pose_residual(
    position_i: torch.Tensor,
    rotation_i: torch.Tensor,
    position_j: torch.Tensor,
    rotation_j: torch.Tensor,
    measured_rotation: torch.Tensor,
    measured_translation: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Relative pose (odometry, loop closure): ``r = Log_SE3(Z^-1 T_i^-1 T_j)`` (..., 6) in
    [rho, phi] order (translation part first; GTSAM's ``BetweenFactor<Pose3>`` error).

    Args:
        position_i, position_j: (..., 3) m. rotation_i, rotation_j: (..., 3, 3).
        measured_rotation: (..., 3, 3), measured_translation: (..., 3) m: ``Z = T_i^-1 T_j``.
    Returns:
        residual (..., 6) and Jacobians (..., 6, 6) w.r.t. the body-frame SE(3) steps
        ``T <- T exp([rho, phi])`` of i and of j: ``-J_r^-1(r) Ad(T_j^-1 T_i)`` and
        ``J_r^-1(r)``.
    """
    rel_r, rel_t = se3.relative(rotation_i, position_i, rotation_j, position_j)
    err_r, err_t = se3.relative(measured_rotation, measured_translation, rel_r, rel_t)
    xi = se3.log(err_r, err_t)
    jr_inv = se3.right_jacobian_inverse(xi)
    inv_r, inv_t = rel_r.mT, -(rel_r.mT @ rel_t[..., None]).squeeze(-1)
    return xi, -jr_inv @ se3.adjoint(inv_r, inv_t), jr_inv


def drifting_frame_pose_residual(
    position: torch.Tensor,
    rotation: torch.Tensor,
    frame_translation: torch.Tensor,
    frame_rotation: torch.Tensor,
    measured_position: torch.Tensor,
    measured_rotation: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose residual of a drifting source (..., 6) against its offset ``(t_o, phi_o)``.

    Args:
        position: (..., 3) m. rotation: (..., 3, 3) body -> world.
        frame_translation: (..., 3) ``t_o``, m (world). frame_rotation: (..., 3) ``phi_o``,
            rad (body).
        measured_position: (..., 3) m. measured_rotation: (..., 3, 3).
    Returns:
        residual ``[p + t_o - z_p, Log(R_z^T R Exp(phi_o))]`` (..., 6), its Jacobian
        (..., 6, 15) w.r.t. the error state and (..., 6, 6) w.r.t. the offset error
        ``[dt, dphi]``.
    """
    offset_rot = so3.exp(frame_rotation)
    r_theta = so3.log(measured_rotation.mT @ rotation @ offset_rot)
    residual = torch.cat((position + frame_translation - measured_position, r_theta), -1)
    lead = residual.shape[:-1]
    eye = so3.identity(position.dtype, position.device).expand(*lead, 3, 3)
    jr_inv = torch.linalg.inv(so3.right_jacobian(r_theta))
    top = error_state_jacobian(3, [(IDX_P, eye)], like=position)
    bottom = error_state_jacobian(3, [(IDX_THETA, jr_inv @ offset_rot.mT)], like=position)
    zeros = torch.zeros_like(eye)
    frame = torch.cat((torch.cat((eye, zeros), -1), torch.cat((zeros, jr_inv), -1)), -2)
    return residual, torch.cat((top, bottom), -2), frame


def drifting_frame_offset(
    position: torch.Tensor,
    rotation: torch.Tensor,
    measured_position: torch.Tensor,
    measured_rotation: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The offset that makes :func:`drifting_frame_pose_residual` zero: ``t_o = z_p - p``
    (..., 3) m and ``phi_o = Log(R^T R_z)`` (..., 3) rad (its offset Jacobian is then I).

    Args:
        position: (..., 3) m. rotation: (..., 3, 3). measured_position: (..., 3) m.
        measured_rotation: (..., 3, 3).
    """
    return measured_position - position, so3.log(rotation.mT @ measured_rotation)
