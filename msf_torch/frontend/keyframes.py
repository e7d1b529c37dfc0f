"""Keyframe selection over the front end's per-epoch output.

A keyframe is a front-end epoch that the back end keeps as a state variable. Walking along
one sequence's epochs, the next keyframe after keyframe ``i`` is the first epoch ``j > i``
at which any threshold is passed:

* time: ``t_j - t_i >= max_interval_s``;
* distance: the path length travelled from ``i`` to ``j`` (sum of the front end's position
  steps) ``>= max_distance_m``;
* attitude: ``|Log(R_i^T R_j)| >= max_rotation_rad``;
* or ``j`` is a *forced* epoch (e.g. one carrying a GNSS fix, so the back end applies the
  fix at its own time, exactly).

The first and the last real epoch are always keyframes. The walk loops over keyframes
(not epochs); each step finds the time and distance crossings by ``searchsorted`` on the
cumulative time and path length, and the attitude crossing with one batched ``Log`` over
the epochs up to them. Selection is preprocessing: it loops over the B sequences, whose
keyframe counts differ, and returns them padded.
"""

from __future__ import annotations

__all__ = ["KeyframeConfig", "Keyframes", "select_keyframes"]

import math
from dataclasses import dataclass

import torch

from msf_torch.geometry import so3


@dataclass
class KeyframeConfig:
    """Thresholds of :func:`select_keyframes` (``math.inf`` switches one off).

    The defaults suit a small wheeled robot (about 1.5 m/s): a keyframe at least every
    second, every metre or every 0.2 rad (11 degrees) of turn.

    Attributes:
        max_interval_s: the longest time between keyframes, s.
        max_distance_m: the longest path between keyframes, m.
        max_rotation_rad: the largest attitude change between keyframes, rad.
    """

    max_interval_s: float = 1.0
    max_distance_m: float = 1.0
    max_rotation_rad: float = 0.2

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first threshold that is not a positive number."""
        for key in ("max_interval_s", "max_distance_m", "max_rotation_rad"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and not math.isnan(value) and value > 0):
                raise ValueError(f"keyframe threshold '{key}' must be > 0, got {value!r}")


@dataclass
class Keyframes:
    """Selected keyframes of B sequences, padded to the longest (K).

    Attributes:
        index: (B, K) int64 epoch index into the front end's (B, E + 1) output; padding
            repeats the last keyframe.
        t: (B, K) keyframe times, s.
        mask: (B, K) bool, real keyframes.
    """

    index: torch.Tensor
    t: torch.Tensor
    mask: torch.Tensor

    def counts(self) -> torch.Tensor:
        """(B,) number of keyframes per sequence."""
        return self.mask.sum(-1)


def _select_one(
    t: torch.Tensor,
    position: torch.Tensor,
    rotation: torch.Tensor,
    forced: torch.Tensor,
    config: KeyframeConfig,
) -> torch.Tensor:
    """Keyframe indices (K,) into one sequence's real epochs ``t`` (n,), ``position``
    (n, 3), ``rotation`` (n, 3, 3), ``forced`` (n,) bool."""
    n = t.numel()
    if n == 1:
        return torch.zeros(1, dtype=torch.long, device=t.device)
    steps = (position[1:] - position[:-1]).norm(dim=-1)
    path = torch.cat((steps.new_zeros(1), torch.cumsum(steps, 0)))
    arange = torch.arange(n, device=t.device)
    # next forced epoch strictly after each epoch (n - 1 = the last epoch, always kept)
    forced = forced.clone()
    forced[-1] = True
    marks = torch.where(forced, arange, torch.full_like(arange, n - 1))
    next_forced = torch.flip(torch.cummin(torch.flip(marks, (0,)), 0).values, (0,))
    next_forced = torch.cat((next_forced[1:], next_forced.new_full((1,), n - 1)))
    selected = [0]
    i = 0
    while i < n - 1:
        limits = torch.stack(
            (
                torch.searchsorted(t, t[i : i + 1] + config.max_interval_s),
                torch.searchsorted(path, path[i : i + 1] + config.max_distance_m),
            )
        ).squeeze(-1)
        j = int(min(int(limits.min()), int(next_forced[i]), n - 1))
        j = max(j, i + 1)
        if math.isfinite(config.max_rotation_rad) and j > i + 1:
            turned = so3.log(rotation[i].mT @ rotation[i + 1 : j + 1]).norm(dim=-1)
            over = torch.nonzero(turned >= config.max_rotation_rad)
            if over.numel():
                j = i + 1 + int(over[0])
        selected.append(j)
        i = j
    return torch.tensor(selected, dtype=torch.long, device=t.device)


def select_keyframes(
    t: torch.Tensor,
    position: torch.Tensor,
    rotation: torch.Tensor,
    mask: torch.Tensor,
    config: KeyframeConfig | None = None,
    force: torch.Tensor | None = None,
) -> Keyframes:
    """Select keyframes from per-epoch front-end estimates.

    Args:
        t: (B, E) epoch times, s (increasing over real epochs).
        position: (B, E, 3) world, m.
        rotation: (B, E, 3, 3) body -> world.
        mask: (B, E) bool, real epochs.
        config: thresholds; default :class:`KeyframeConfig()`.
        force: optional (B, E) bool, epochs that must be keyframes.
    Returns:
        :class:`Keyframes` (B, K).

    Example:
        >>> t = torch.arange(5.0, dtype=torch.float64)[None]
        >>> pos = torch.zeros(1, 5, 3, dtype=torch.float64)
        >>> rot = torch.eye(3, dtype=torch.float64).expand(1, 5, 3, 3)
        >>> cfg = KeyframeConfig(max_interval_s=2.0)
        >>> select_keyframes(t, pos, rot, torch.ones(1, 5, dtype=torch.bool), cfg).index
        tensor([[0, 2, 4]])
    """
    config = config or KeyframeConfig()
    config.validate()
    per_seq = []
    for b in range(t.shape[0]):
        real = torch.nonzero(mask[b]).squeeze(-1)
        if real.numel() == 0:
            raise ValueError(f"sequence {b} has no epochs to select keyframes from")
        forced = force[b, real] if force is not None else torch.zeros_like(real, dtype=torch.bool)
        local = _select_one(t[b, real], position[b, real], rotation[b, real], forced, config)
        per_seq.append(real[local])
    width = max(s.numel() for s in per_seq)
    index = torch.stack([torch.cat((s, s[-1:].expand(width - s.numel()))) for s in per_seq])
    keep = (
        torch.arange(width, device=t.device)[None]
        < torch.tensor([s.numel() for s in per_seq], device=t.device)[:, None]
    )
    return Keyframes(index=index, t=torch.gather(t, 1, index), mask=keep)
