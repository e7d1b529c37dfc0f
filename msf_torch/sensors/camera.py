"""Pinhole camera: reprojection of a world landmark.

The camera sits at ``T_body_cam = (R_bc, t_bc)`` on the body; a world point ``l`` is at
``c = R_bc^T (R^T (l - p) - t_bc)`` in the camera and projects to ``(c_x/c_z, c_y/c_z)``
(normalized image coordinates) or, with intrinsics ``(fx, fy, cx, cy)``, to pixels.
``r = projection - measured``; Jacobians w.r.t. the error state ``[dp, dv, dtheta, ...]``
(right perturbation) and the landmark.
"""

from __future__ import annotations

__all__ = ["reprojection_residual"]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_P, IDX_THETA
from msf_torch.sensors._jacobian import error_state_jacobian


def reprojection_residual(
    position: torch.Tensor,
    rotation: torch.Tensor,
    landmark: torch.Tensor,
    body_rotation_cam: torch.Tensor,
    body_translation_cam: torch.Tensor,
    measured: torch.Tensor,
    intrinsics: tuple[float, float, float, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reprojection residual (..., 2) with Jacobians.

    Args:
        position: (..., 3) body in the world, m. rotation: (..., 3, 3) body -> world.
        landmark: (..., 3) world point, m.
        body_rotation_cam, body_translation_cam: (3, 3), (3,) camera in the body frame.
        measured: (..., 2) normalized coordinates, or pixels with ``intrinsics``.
        intrinsics: ``(fx, fy, cx, cy)`` in px, or None for normalized coordinates.
    Returns:
        residual (..., 2), Jacobian w.r.t. the error state (..., 2, 15), Jacobian w.r.t. the
        landmark (..., 2, 3).
    """
    body = (rotation.mT @ (landmark - position)[..., None]).squeeze(-1)
    to_cam = body_rotation_cam.mT
    cam = (to_cam @ (body - body_translation_cam)[..., None]).squeeze(-1)
    inv_z = 1.0 / cam[..., 2:3]
    normalized = cam[..., 0:2] * inv_z
    zeros = torch.zeros_like(inv_z)
    d_proj = torch.stack(
        (
            torch.cat((inv_z, zeros, -normalized[..., 0:1] * inv_z), -1),
            torch.cat((zeros, inv_z, -normalized[..., 1:2] * inv_z), -1),
        ),
        -2,
    )
    projected = normalized
    if intrinsics is not None:
        fx, fy, cx, cy = intrinsics
        projected = torch.stack((fx * normalized[..., 0] + cx, fy * normalized[..., 1] + cy), -1)
        d_proj = d_proj * torch.tensor([fx, fy], dtype=cam.dtype, device=cam.device)[:, None]
    d_landmark = d_proj @ to_cam @ rotation.mT
    d_theta = d_proj @ to_cam @ so3.hat(body)
    jac = error_state_jacobian(2, [(IDX_P, -d_landmark), (IDX_THETA, d_theta)], like=position)
    return projected - measured, jac, d_landmark
