"""Quaternion conversions, Hamilton scalar-first ``[w, x, y, z]`` (see ``conventions``).

Thin, documented wrappers over ``pytorch_kinematics.transforms``; the TUM order
``[x, y, z, w]`` is converted here and nowhere else.
"""

from __future__ import annotations

__all__ = [
    "quat_to_matrix",
    "matrix_to_quat",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
    "yaw_matrix",
    "quat_multiply",
    "quat_conjugate",
    "quat_exp",
    "quat_log",
]

import functools
import math

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
    # one-hot of the largest |q_i| by scatter (one_hot reads its input's range: no vmap)
    best = torch.zeros_like(q_abs).scatter(-1, q_abs.argmax(-1, keepdim=True), 1.0)
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


@functools.lru_cache(maxsize=8)
@torch.inference_mode(False)  # cached: an ordinary tensor, never an inference one
def _product_table(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(4, 4, 4) T with ``(a (x) b)_k = sum_ij T_kij a_i b_j`` (Hamilton, scalar first)."""
    table = torch.zeros(4, 4, 4, dtype=dtype, device=device)
    signs = {
        0: ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
        1: ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
        2: ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
        3: ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)),
    }
    for k, terms in signs.items():
        for i, j, sign in terms:
            table[k, i, j] = sign
    return table


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a (x) b`` of (..., 4) quaternions (broadcasting); one einsum, so
    cheap on small batches. ``R(a (x) b) = R(a) R(b)``."""
    a, b = torch.broadcast_tensors(a, b)
    return torch.einsum("kij,...i,...j->...k", _product_table(a.dtype, a.device), a, b)


def quat_conjugate(quat: torch.Tensor) -> torch.Tensor:
    """``[w, -x, -y, -z]`` (..., 4): the inverse of a unit quaternion."""
    return quat * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=quat.dtype, device=quat.device)


def quat_exp(phi: torch.Tensor) -> torch.Tensor:
    """``Exp`` of rotation vectors (..., 3) rad -> unit quaternions (..., 4), ``R = so3.exp``.

    ``[cos(a / 2), sinc(a / 2) phi / 2]`` with ``a = |phi|``; ``torch.sinc`` keeps value and
    gradient finite at 0 (the 1e-300 only guards the square root).
    """
    angle = torch.sqrt((phi * phi).sum(-1, keepdim=True) + 1e-300)
    return torch.cat((torch.cos(0.5 * angle), 0.5 * torch.sinc(angle / (2 * math.pi)) * phi), -1)


def quat_log(quat: torch.Tensor) -> torch.Tensor:
    """``Log`` of unit quaternions (..., 4) -> rotation vectors (..., 3), angle in [0, pi].

    ``q`` and ``-q`` give the same; ``2 atan2(|v|, w) v / |v|`` with a double-``where``
    Taylor branch near the identity (finite gradients there).
    """
    quat = torch.where(quat[..., :1] < 0, -quat, quat)
    w, vec = quat[..., :1], quat[..., 1:]
    norm2 = (vec * vec).sum(-1, keepdim=True)
    small = norm2 < 1e-16
    safe_norm = torch.sqrt(torch.where(small, 1.0, norm2))
    safe_w = torch.where(small, w, 1.0)
    scale = torch.where(
        small,
        2.0 / safe_w * (1.0 - norm2 / (3.0 * safe_w * safe_w)),
        2.0 * torch.atan2(safe_norm, w) / safe_norm,
    )
    return scale * vec
