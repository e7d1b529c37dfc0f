"""Pinhole camera: reprojection of a world landmark.

The camera sits at ``T_body_cam = (R_bc, t_bc)`` on the body; a world point ``l`` is at
``c = R_bc^T (R^T (l - p) - t_bc)`` in the camera and projects to ``(c_x/c_z, c_y/c_z)``
(normalized image coordinates) or, with intrinsics ``(fx, fy, cx, cy)``, to pixels.
``r = projection - measured``; Jacobians w.r.t. the error state ``[dp, dv, dtheta, ...]``
(right perturbation) and the landmark.

:class:`CameraRig` holds a rectified stereo pinhole pair (intrinsics, baseline, mount on the
body) for the renderer (``msf_torch.sim.render``) and the visual front end
(``msf_torch.vision``).
"""

from __future__ import annotations

__all__ = ["CameraRig", "reprojection_residual"]

import math
from dataclasses import dataclass

import numpy as np
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


@dataclass(frozen=True)
class CameraRig:
    """A rectified stereo pair of pinhole cameras on the body (no lens distortion).

    Camera frame: x right, y down, z forward (optical axis). The left camera sits at
    ``mount_position_m`` in the body frame (x forward, y left, z up), looking along body x,
    pitched down by ``mount_pitch_deg``; the right camera is the left one moved by
    ``baseline_m`` along the left camera's x axis (same orientation, same intrinsics). A
    camera point ``c`` projects to pixel ``(fx c_x / c_z + cx, fy c_y / c_z + cy)``; pixel
    centres are at integer coordinates, ``(0, 0)`` is the centre of the top-left pixel.

    Attributes:
        width, height: image size, px.
        fx, fy: focal lengths, px. cx, cy: principal point, px.
        baseline_m: stereo baseline, m (0 for a monocular camera).
        mount_position_m: left camera centre in the body frame, m.
        mount_pitch_deg: downward tilt of the optical axis, deg.
    """

    width: int = 640
    height: int = 480
    fx: float = 400.0
    fy: float = 400.0
    cx: float = 319.5
    cy: float = 239.5
    baseline_m: float = 0.12
    mount_position_m: tuple[float, float, float] = (0.3, 0.0, 0.8)
    mount_pitch_deg: float = 10.0

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` px, as :func:`reprojection_residual` takes them."""
        return (self.fx, self.fy, self.cx, self.cy)

    def matrix(self) -> np.ndarray:
        """Intrinsic matrix K (3, 3) float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def body_rotation_cam(self) -> np.ndarray:
        """``R_bc`` (3, 3) float64, camera -> body (columns: camera axes in the body frame)."""
        pitch = math.radians(self.mount_pitch_deg)
        c, s = math.cos(pitch), math.sin(pitch)
        # optical axis forward and down, x to the body's right, y completing the frame
        z_axis = np.array([c, 0.0, -s])
        x_axis = np.array([0.0, -1.0, 0.0])
        return np.stack((x_axis, np.cross(z_axis, x_axis), z_axis), -1)

    def body_translation_cam(self, right: bool = False) -> np.ndarray:
        """Centre (3,) float64 of the left (or right) camera in the body frame, m."""
        centre = np.asarray(self.mount_position_m, np.float64)
        if right:
            centre = centre + self.baseline_m * self.body_rotation_cam()[:, 0]
        return centre

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of camera-frame points (..., 3) (in front: ``c_z > 0``)."""
        points = np.asarray(points_cam, np.float64)
        z = points[..., 2]
        return np.stack(
            (self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy), -1
        )
