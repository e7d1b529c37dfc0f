"""Helper to place Jacobian blocks into the 15-column error-state layout."""

from __future__ import annotations

__all__ = ["error_state_jacobian"]

import torch

from msf_torch.geometry.conventions import ERROR_STATE_DIM


def error_state_jacobian(
    rows: int, blocks: list[tuple[slice, torch.Tensor]], like: torch.Tensor
) -> torch.Tensor:
    """Build ``H`` (..., rows, 15) from ``[(conventions.IDX_*, (..., rows, 3)), ...]``;
    columns not named are zero. Blocks share their leading dims (or are expanded to the
    longest)."""
    lead = max((b.shape[:-2] for _, b in blocks), key=len)
    by_start = {s.start: b for s, b in blocks}
    cols = []
    for start in range(0, ERROR_STATE_DIM, 3):
        block = by_start.get(start)
        if block is None:
            block = torch.zeros(*lead, rows, 3, dtype=like.dtype, device=like.device)
        cols.append(block.expand(*lead, rows, 3))
    return torch.cat(cols, -1)
