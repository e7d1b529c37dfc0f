"""GNSS position and velocity measurements with antenna lever arm.

Position: ``r = p + R l - z`` (..., 3) in m, world frame; ``l`` is the antenna position in
the body frame. Jacobian: ``dr/ddp = I``, ``dr/ddtheta = -R [l]x`` (right perturbation).

Velocity (a receiver's Doppler velocity, or speed and course over ground): the antenna
moves with ``v + R (w x l)``, ``w = gyro - b_g`` the body rate, so
``r = v + R (w x l) - z`` (..., 3) in m/s, world frame. Jacobian: ``dr/ddv = I``,
``dr/ddtheta = -R [w x l]x``, ``dr/ddb_g = R [l]x`` (``w x l`` changes by
``-db_g x l = [l]x db_g``).

Heading (a dual-antenna receiver): the baseline ``b`` from the primary to the secondary
antenna (body frame) points along ``u = R b`` in the world (ENU), whose azimuth clockwise
from north is ``psi = atan2(u_e, u_n)``. ``r = wrap(psi - z)`` (..., 1) in rad, wrapped to
(-pi, pi]. Jacobian: ``dr/ddtheta = [u_n, -u_e, 0] / (u_e^2 + u_n^2) (-R [b]x)``; the
antenna positions do not enter (only the baseline's direction). Undefined where the
baseline points straight up or down (``u_e = u_n = 0``).
"""

from __future__ import annotations

__all__ = [
    "azimuth_and_gradient",
    "azimuth_residual",
    "gnss_heading_residual",
    "gnss_residual",
    "gnss_velocity_residual",
]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_BG, IDX_P, IDX_THETA, IDX_V
from msf_torch.geometry.se2 import wrap_angle
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


def azimuth_and_gradient(
    world: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Azimuth clockwise from north of world (ENU) vectors and its gradient.

    Args:
        world: (..., 3) vectors, e.g. an antenna baseline ``R b``.

    Returns:
        azimuth (...,) rad ``atan2(e, n)``, gradient (..., 3) ``[n, -e, 0] / (e^2 + n^2)``,
        and defined (...,) bool: the vector has a horizontal part (where it has none the
        gradient is 0).
    """
    east, north = world[..., 0], world[..., 1]
    horizontal = east**2 + north**2
    defined = horizontal > 1e-12 * (world**2).sum(-1).clamp_min(1e-300)
    safe = torch.where(defined, horizontal, torch.ones_like(horizontal))
    gradient = torch.stack((north, -east, torch.zeros_like(east)), -1) / safe[..., None]
    gradient = torch.where(defined[..., None], gradient, torch.zeros_like(gradient))
    return torch.atan2(east, north), gradient, defined


def azimuth_residual(
    rotation: torch.Tensor, body_vector: torch.Tensor, measured: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual (..., 1) rad and Jacobian (..., 1, 15) of the azimuth of a body-frame vector
    seen in the world: ``wrap(azimuth(R v) - measured)``.

    Args:
        rotation: (..., 3, 3) body -> world (ENU).
        body_vector: (..., 3) or (3,) the vector in the body frame (only its direction
            matters): an antenna baseline, a magnetometer's corrected field.
        measured: (...,) the azimuth it should have, clockwise from north, rad.

    Returns:
        ``wrap(psi - measured)`` in (-pi, pi] and its Jacobian (only the attitude columns
        are non-zero, ``-g^T R [v]x`` with ``g`` the azimuth's gradient). A vector pointing
        straight up or down has no azimuth: residual and Jacobian are then zero.
    """
    arm = body_vector.expand(*rotation.shape[:-2], 3)
    world = (rotation @ arm[..., None]).squeeze(-1)
    azimuth, d_azimuth, defined = azimuth_and_gradient(world)
    residual = torch.where(defined, wrap_angle(azimuth - measured), torch.zeros_like(azimuth))
    jac = error_state_jacobian(
        1,
        [(IDX_THETA, -(d_azimuth[..., None, :] @ rotation @ so3.hat(arm)))],
        like=rotation,
    )
    return residual[..., None], jac


def gnss_heading_residual(
    rotation: torch.Tensor, baseline: torch.Tensor, measured: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dual-antenna GNSS heading residual (..., 1) rad and Jacobian (..., 1, 15).

    Args:
        rotation: (..., 3, 3) body -> world (ENU).
        baseline: (..., 3) or (3,) primary -> secondary antenna in the body frame, m (only
            its direction matters).
        measured: (...,) baseline azimuth clockwise from north, rad.

    Returns:
        ``wrap(psi - measured)`` in (-pi, pi] and its Jacobian (only the attitude
        columns are non-zero). A baseline pointing straight up or down has no azimuth:
        residual and Jacobian are then zero (the update does nothing).
    """
    return azimuth_residual(rotation, baseline, measured)
