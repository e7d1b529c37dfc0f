"""Quaternion conversions, Hamilton scalar-first ``[w, x, y, z]`` (see ``conventions``).

Thin, documented wrappers over ``pytorch_kinematics.transforms``; the TUM order
``[x, y, z, w]`` is converted here and nowhere else.
"""

from __future__ import annotations

__all__ = ["quat_to_matrix", "matrix_to_quat", "wxyz_to_xyzw", "xyzw_to_wxyz", "yaw_matrix"]

import torch
from pytorch_kinematics import transforms as _tf


def quat_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (..., 4) ``[w, x, y, z]`` -> rotation matrix (..., 3, 3).

    The quaternion is normalised first, so slightly denormalised file input is accepted.
    """
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return _tf.quaternion_to_matrix(quat)


def matrix_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) ``[w, x, y, z]`` with w >= 0."""
    quat = _tf.matrix_to_quaternion(rot)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def wxyz_to_xyzw(quat: torch.Tensor) -> torch.Tensor:
    """Reorder (..., 4) from ``[w, x, y, z]`` to ``[x, y, z, w]`` (TUM, ROS, scipy order)."""
    return quat[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(quat: torch.Tensor) -> torch.Tensor:
    """Reorder (..., 4) from ``[x, y, z, w]`` to ``[w, x, y, z]``."""
    return quat[..., [3, 0, 1, 2]]


def yaw_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """Rotation about world z by ``yaw`` (...,) rad -> (..., 3, 3)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rows = (
        torch.stack((c, -s, zero), -1),
        torch.stack((s, c, zero), -1),
        torch.stack((zero, zero, one), -1),
    )
    return torch.stack(rows, -2)
