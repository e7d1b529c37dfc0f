"""Right-invariant error coordinates of the navigation state, written once.

The front end keeps its covariance in right-invariant (world-frame) coordinates
``xi = [xi_p, xi_v, xi_R, db_g, db_a]`` (15,): to first order

    dtheta = R^T xi_R,   dv = xi_v - [v]x xi_R,   dp = xi_p - [p]x xi_R,   db = db

(``dx = T xi``, :func:`invariant_maps`; ``dx`` the conventional error of
``geometry.conventions``). The state ``xi`` away from an estimate is (:func:`invariant_retract`)

    R = Exp(xi_R) R_hat,   v = Exp(xi_R) v_hat + xi_v,   p = p_hat + xi_p - [p_hat]x xi_R,

i.e. the group action of SE_2(3) with its origin moved to the estimate's own position: a
correction turns the velocity and the attitude and shifts the position, but never swings the
position about the world origin. (Rotating ``p_hat`` about the origin, ``Exp(xi_R) p_hat``,
adds ``1/2 [xi_R]x^2 p_hat`` at second order: 14 m for a 0.1 rad heading correction 2.8 km
from the origin, enough to make the filter diverge; the two retractions agree to first order,
so the covariance algebra is the same.) The front end goes one step further and keeps its
covariance about that moving origin, where the ``[p]x`` terms vanish (passing a zero
position to :func:`invariant_maps`). In these coordinates the unobservable global yaw is a
constant direction whatever the estimate (Barrau & Bonnabel, "The invariant extended Kalman
filter as a stable observer", IEEE TAC 62(4), 2017).

The coordinates agree with the conventional error to first order only: where the filter
knows a combination very precisely (a wheel's forward or lateral velocity, to mm/s), the
second-order part of the conventional error (``dv`` carries ``1/2 [xi_R]x^2 v``, about
``|v| psi^2 / 2`` for a heading error ``psi``) can exceed that precision, so a consistency test
of this filter is exact only in its own coordinates (:func:`invariant_difference`).
"""

from __future__ import annotations

__all__ = ["invariant_maps", "invariant_retract", "invariant_difference"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import ERROR_STATE_DIM


def invariant_maps(
    position: torch.Tensor, velocity: torch.Tensor, rotation: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Maps between the right-invariant error and the conventional error state.

    ``dx = T xi`` to first order (module docstring). In these coordinates the global-yaw
    direction, unobservable without a heading source, is a constant vector whatever the
    estimate, so propagation and updates linearised at different estimates cannot invent
    heading information.

    Args:
        position: (B, 3) estimate, m.
        velocity: (B, 3) estimate, m/s.
        rotation: (B, 3, 3) estimate, body -> world.

    Returns:
        ``T`` (B, 15, 15) (invariant -> conventional) and its inverse.
    """
    batch = position.shape[0]
    eye = so3.identity(position.dtype, position.device, ERROR_STATE_DIM)
    hat_p, hat_v = so3.hat(position), so3.hat(velocity)
    to_conv = eye.expand(batch, ERROR_STATE_DIM, ERROR_STATE_DIM).clone()
    to_conv[:, 0:9, 6:9] = torch.cat((-hat_p, -hat_v, rotation.mT), -2)
    to_inv = eye.expand(batch, ERROR_STATE_DIM, ERROR_STATE_DIM).clone()
    to_inv[:, 0:9, 6:9] = (
        torch.cat(
            (hat_p, hat_v, so3.identity(position.dtype, position.device).expand(batch, 3, 3)), -2
        )
        @ rotation
    )
    return to_conv, to_inv


def invariant_retract(
    position: torch.Tensor, velocity: torch.Tensor, rotation: torch.Tensor, xi: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The navigation part of the state ``xi`` away from the estimate (module docstring).

    Args:
        position, velocity: (..., 3) estimate, m and m/s.
        rotation: (..., 3, 3) estimate.
        xi: (..., >= 9) invariant error; ``xi[..., 0:9] = [xi_p, xi_v, xi_R]`` is used.

    Returns:
        ``(p + xi_p - [p]x xi_R, Exp(xi_R) v + xi_v, Exp(xi_R) R)``, shapes as the inputs.
    """
    xi_rot = xi[..., 6:9]
    turn = so3.exp(xi_rot)
    return (
        position + xi[..., 0:3] + torch.linalg.cross(xi_rot, position),
        (turn @ velocity[..., None]).squeeze(-1) + xi[..., 3:6],
        turn @ rotation,
    )


def invariant_difference(
    position: torch.Tensor,
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    reference_position: torch.Tensor,
    reference_velocity: torch.Tensor,
    reference_rotation: torch.Tensor,
) -> torch.Tensor:
    """Exact navigation part of the invariant error that takes a reference to a state.

    The inverse of :func:`invariant_retract`: ``xi_R = Log(R R_ref^T)``,
    ``xi_v = v - Exp(xi_R) v_ref``, ``xi_p = p - p_ref + [p_ref]x xi_R``. With the state the
    truth and the reference the estimate this is the filter's own error, whose covariance is
    the filter's invariant covariance ``T^-1 P T^-T``.

    Args:
        position, velocity: (..., 3) state, m and m/s; rotation (..., 3, 3).
        reference_position, reference_velocity: (..., 3); reference_rotation (..., 3, 3).

    Returns:
        (..., 9) ``[xi_p, xi_v, xi_R]`` in m, m/s, rad (world frame).
    """
    xi_rot = so3.log(rotation @ reference_rotation.mT)
    turn = so3.exp(xi_rot)
    return torch.cat(
        (
            position - reference_position - torch.linalg.cross(xi_rot, reference_position),
            velocity - (turn @ reference_velocity[..., None]).squeeze(-1),
            xi_rot,
        ),
        -1,
    )
