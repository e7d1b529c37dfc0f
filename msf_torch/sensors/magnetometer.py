"""Magnetometer fused as a heading (tilt-compensated through the filter's own attitude).

A three-axis magnetometer reads ``m = W^-1 (R^T f_w) + b`` (body frame, uT): the local
earth field ``f_w`` (world, ENU) seen in the body, distorted by the vehicle's soft iron
``W^-1`` and offset by its hard iron ``b``. The correction ``f_b = W (m - b)`` (config
``magnetometer_hard_iron_uT``, ``magnetometer_soft_iron``; fitted by
:mod:`msf_torch.sensors.magnetometer_calibration` or ``msf magcal``) gives the field in
the body frame. Turned into the world, ``R f_b`` points to magnetic north: its horizontal
part's azimuth (clockwise from true north) is the local declination ``D``. The residual is

    r = wrap(azimuth(R f_b) - D)    (..., 1) rad,

with Jacobian ``dr/ddtheta = -g^T R [f_b]x`` (``g`` the azimuth's gradient,
:func:`msf_torch.sensors.gnss.azimuth_and_gradient`): the same model as a dual-antenna
baseline's azimuth, with the measured field as the body vector. Only the heading is
fused: the field's dip (inclination) is left out, so a disturbance that tilts the field
cannot pull roll and pitch, which gravity holds. Through ``R`` the residual is tilt
compensated by the filter's attitude (roll and pitch errors enter through the field's
vertical part, which the Jacobian carries).

Noise: per-axis white noise ``sigma`` (uT) on ``f_b`` moves the azimuth by
``sigma / H`` (rad), ``H`` the horizontal magnitude of ``R f_b``; a floor added in
quadrature (``magnetometer_heading_floor_rad``) stands for the calibration's residual
distortion, which does not average out.
"""

from __future__ import annotations

__all__ = [
    "corrected_field",
    "field_dip",
    "magnetometer_heading_residual",
    "magnetometer_heading_variance",
]

import torch

from msf_torch.sensors.gnss import azimuth_residual


def corrected_field(
    raw: torch.Tensor, hard_iron: torch.Tensor, soft_iron: torch.Tensor
) -> torch.Tensor:
    """Hard- and soft-iron corrected field ``W (m - b)``.

    Args:
        raw: (..., 3) magnetometer readings, uT.
        hard_iron: (3,) or (..., 3) offset ``b``, uT.
        soft_iron: (3, 3) or (..., 3, 3) correction matrix ``W`` (identity: none).

    Returns:
        (..., 3) the field in the body frame, uT.
    """
    return ((raw - hard_iron)[..., None, :] * soft_iron).sum(-1)


def field_dip(rotation: torch.Tensor, field_body: torch.Tensor) -> torch.Tensor:
    """Dip of the field below the horizon as the attitude sees it, (...,) rad.

    Args:
        rotation: (..., 3, 3) body -> world (ENU).
        field_body: (..., 3) corrected field, uT.

    Returns:
        ``atan2(-u_z, |u_h|)`` of ``u = R f_b`` (positive: pointing below the horizon).
    """
    world = (rotation @ field_body[..., None]).squeeze(-1)
    return torch.atan2(-world[..., 2], torch.linalg.vector_norm(world[..., :2], dim=-1))


def magnetometer_heading_residual(
    rotation: torch.Tensor, field_body: torch.Tensor, declination: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Magnetometer heading residual (..., 1) rad and Jacobian (..., 1, 15).

    Args:
        rotation: (..., 3, 3) body -> world (ENU).
        field_body: (..., 3) corrected field (:func:`corrected_field`), uT.
        declination: () or (...,) magnetic north's azimuth clockwise from true north
            (east of north positive), rad.

    Returns:
        ``wrap(azimuth(R f_b) - D)`` in (-pi, pi] and its Jacobian (attitude columns only).
        A field with no horizontal part (at a magnetic pole) gives zeros.
    """
    measured = torch.as_tensor(declination, dtype=rotation.dtype, device=rotation.device)
    return azimuth_residual(rotation, field_body, measured.expand(rotation.shape[:-2]))


def magnetometer_heading_variance(
    rotation: torch.Tensor,
    field_body: torch.Tensor,
    sigma: torch.Tensor | float,
    floor: float,
) -> torch.Tensor:
    """Variance (...,) rad^2 of the magnetometer heading: ``sigma^2 / H^2 + floor^2``.

    Args:
        rotation: (..., 3, 3) body -> world.
        field_body: (..., 3) corrected field, uT.
        sigma: () or (...,) per-axis field noise, uT.
        floor: heading floor, rad (residual calibration distortion).

    Returns:
        (...,) variance; where the field has no horizontal part the noise term is capped at
        ``pi^2`` (the update then carries next to nothing).
    """
    world = (rotation @ field_body[..., None]).squeeze(-1)
    horizontal = world[..., 0] ** 2 + world[..., 1] ** 2
    sigma = torch.as_tensor(sigma, dtype=rotation.dtype, device=rotation.device)
    noise = (sigma**2 / horizontal.clamp_min(1e-300)).clamp_max(torch.pi**2)
    return noise + floor**2
