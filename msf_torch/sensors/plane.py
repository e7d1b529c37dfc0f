"""Planar-motion ("pose plane") residual for ground vehicles.

Between poses i and j, relative to the local ground plane of pose i (its body x-y plane):
no relative roll, pitch or height change,
``r = [phi_x, phi_y, e_z^T R_i^T (p_j - p_i)]`` (3,) with ``phi = Log(R_i^T R_j)``
(rad, rad, m). A soft constraint: its noise says how flat the ground is.
"""

from __future__ import annotations

__all__ = ["plane_residual"]

import torch

from msf_torch.geometry import so3


def plane_residual(
    position_i: torch.Tensor,
    rotation_i: torch.Tensor,
    position_j: torch.Tensor,
    rotation_j: torch.Tensor,
) -> torch.Tensor:
    """Planar-motion residual (..., 3) of poses i and j: positions (..., 3) m, rotations
    (..., 3, 3) body -> world."""
    phi = so3.log(rotation_i.mT @ rotation_j)
    height = (rotation_i.mT @ (position_j - position_i)[..., None]).squeeze(-1)[..., 2:3]
    return torch.cat((phi[..., 0:2], height), -1)
