"""Planar rigid motions SE(2) as ``(..., 3)`` tensors ``[x, y, theta]`` (m, m, rad).

A pose ``a = [x, y, theta]`` maps a point ``p`` of its own frame to the parent frame as
``R(theta) p + [x, y]``. Composition ``compose(a, b)`` is the pose of frame ``b`` expressed in
``a``'s parent (``a`` then ``b``); ``between(a, b) = compose(inverse(a), b)`` is ``b`` seen
from ``a``. Angles are wrapped to ``(-pi, pi]``. Batch dimensions broadcast.

Example:
    >>> import torch
    >>> a = torch.tensor([1.0, 0.0, 1.5707963267948966], dtype=torch.float64)
    >>> compose(a, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)).round(decimals=6)
    tensor([1.0000, 1.0000, 1.5708], dtype=torch.float64)
"""

from __future__ import annotations

__all__ = [
    "wrap_angle",
    "rotation",
    "compose",
    "inverse",
    "between",
    "chain",
    "transform_points",
    "align_points",
]

import math

import torch


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Angle (...) rad wrapped to ``(-pi, pi]``."""
    return angle - 2.0 * math.pi * torch.ceil((angle - math.pi) / (2.0 * math.pi))


def rotation(theta: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 2, 2) of angles (...) rad."""
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a (+) b``: poses (..., 3) -> (..., 3)."""
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return torch.stack((x, y, wrap_angle(a[..., 2] + b[..., 2])), -1)


def inverse(a: torch.Tensor) -> torch.Tensor:
    """``a^-1``: poses (..., 3) -> (..., 3)."""
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return torch.stack((x, y, wrap_angle(-a[..., 2])), -1)


def between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a^-1 (+) b``, the pose of ``b`` in the frame of ``a``: (..., 3) -> (..., 3)."""
    return compose(inverse(a), b)


def chain(start: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """Poses (M + 1, 3) from ``start`` (3,) and relative steps (M, 3): pose k + 1 =
    ``compose(pose k, steps[k])``, in closed form (headings by a cumulative sum, positions
    by one of the rotated steps) instead of M sequential compositions."""
    zero = steps.new_zeros(1)
    heading = start[2] + torch.cat((zero, torch.cumsum(steps[:, 2], 0)))
    c, s = torch.cos(heading[:-1]), torch.sin(heading[:-1])
    moves = torch.stack((c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]), -1)
    position = start[0:2] + torch.cat((steps.new_zeros(1, 2), torch.cumsum(moves, 0)))
    return torch.cat((position, wrap_angle(heading)[:, None]), -1)


def transform_points(pose: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Points (..., N, 2) of a frame mapped by its pose (..., 3) into the parent frame."""
    return points @ rotation(pose[..., 2]).mT + pose[..., None, :2]


def align_points(estimate: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """The rigid motion (3,) ``[x, y, theta]`` that best maps points ``estimate`` (N, 2) onto
    ``reference`` (N, 2) in least squares (Umeyama / Kabsch without scale): apply it with
    :func:`transform_points`."""
    mean_e, mean_r = estimate.mean(0), reference.mean(0)
    cross = (estimate - mean_e).T @ (reference - mean_r)  # (2, 2)
    theta = torch.atan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
    shift = mean_r - rotation(theta) @ mean_e
    return torch.cat((shift, theta[None]))
