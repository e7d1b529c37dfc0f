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
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) ``[w, x, y, z]`` with w >= 0.

    Shepperd's method: the four candidate quaternions are formed from the four diagonal
    combinations and the best-conditioned one is kept. Square roots use the double-``where``
    form, so gradients are finite everywhere (the identity, axis rotations, a half turn).
    """
    m00, m11, m22 = rot[..., 0, 0], rot[..., 1, 1], rot[..., 2, 2]
    four_sq = torch.stack(
        (
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ),
        -1,
    )
    positive = four_sq > 0
    q_abs = torch.where(positive, torch.sqrt(torch.where(positive, four_sq, 1.0)), 0.0)
    r21_12 = rot[..., 2, 1] - rot[..., 1, 2]
    r02_20 = rot[..., 0, 2] - rot[..., 2, 0]
    r10_01 = rot[..., 1, 0] - rot[..., 0, 1]
    r10p01 = rot[..., 1, 0] + rot[..., 0, 1]
    r02p20 = rot[..., 0, 2] + rot[..., 2, 0]
    r21p12 = rot[..., 2, 1] + rot[..., 1, 2]
    candidates = (
        torch.stack(
            (
                torch.stack((q_abs[..., 0] ** 2, r21_12, r02_20, r10_01), -1),
                torch.stack((r21_12, q_abs[..., 1] ** 2, r10p01, r02p20), -1),
                torch.stack((r02_20, r10p01, q_abs[..., 2] ** 2, r21p12), -1),
                torch.stack((r10_01, r02p20, r21p12, q_abs[..., 3] ** 2), -1),
            ),
            -2,
        )
        / (2.0 * q_abs.clamp_min(0.1))[..., None]
    )
    best = torch.nn.functional.one_hot(q_abs.argmax(-1), 4).to(rot.dtype)
    quat = (candidates * best[..., None]).sum(-2)
    quat = quat / quat.norm(dim=-1, keepdim=True)
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
