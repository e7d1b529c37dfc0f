"""Log-odds occupancy grids from 2D scans and poses; ROS ``map_server`` PNG + YAML output.

Grid: cell ``(row i, column j)`` covers ``[x0 + j res, x0 + (j + 1) res) x
[y0 + i res, y0 + (i + 1) res)`` in the map frame (row 0 at the bottom, ``origin = (x0, y0)``
its lower-left corner). Each cell holds the log-odds ``l = log(p / (1 - p))`` of being
occupied, 0 (p = 0.5) before any observation.

Inverse sensor model, per beam with a return: every cell the beam crosses before its end
point gets ``l_miss = log(p_miss / (1 - p_miss))``, the cell holding the end point gets
``l_hit``; a cell crossed by several beams of a scan gets one update per beam. Scans are
applied in order and the log-odds are clamped to ``[logit(p_min), logit(p_max)]`` after each
scan. Defaults are OctoMap's (``p_hit = 0.7``, ``p_miss = 0.4``, clamping 0.12 and 0.97).
Beams without a return (NaN, inf or a range <= 0) are skipped (a dropout cannot be told
from open space).

Ray traversal is exact and vectorised: the parameters ``s in (0, 1)`` at which a beam's
segment crosses the vertical grid lines ``x = x0 + k res`` and the horizontal ones are
merged and sorted; the cell of each interval between consecutive crossings is the one that
holds the interval's midpoint. So a cell counts as crossed exactly when the segment passes
through its interior over a positive length (a segment that only touches a corner does not
count).

Output (:func:`write_map`) follows ROS ``map_server`` / ``map_saver``: a grey image with
row 0 at the top (largest y); occupied (``p > occupied_thresh``) 0, free
(``p < free_thresh``) 254, unknown 205; and a YAML file with ``image``, ``resolution``,
``origin: [x0, y0, yaw]``, ``negate``, ``occupied_thresh``, ``free_thresh`` (and
``mode: trinary``).

Example:
    >>> import torch
    >>> from msf_torch.lidar.grid import GridConfig, occupancy_grid
    >>> poses = torch.zeros(1, 3, dtype=torch.float64)
    >>> grid = occupancy_grid(poses, torch.tensor([[2.0]], dtype=torch.float64),
    ...                       torch.zeros(1, dtype=torch.float64), GridConfig(resolution_m=0.5))
    >>> grid.log_odds.shape
    torch.Size([4, 8])
"""

from __future__ import annotations

__all__ = [
    "GridConfig",
    "OccupancyGrid",
    "OccupancyMap",
    "logit",
    "ray_cells",
    "occupancy_grid",
    "write_map",
    "read_map",
]

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from msf_torch.geometry.se2 import transform_points
from msf_torch.io.atomic import atomic_write
from msf_torch.io.errors import DataError


def logit(p: float) -> float:
    """``log(p / (1 - p))``."""
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class GridConfig:
    """Occupancy-grid settings.

    Attributes:
        resolution_m: cell side, m.
        p_hit: occupancy probability that one return puts on its end cell.
        p_miss: occupancy probability that one beam puts on a cell it crosses.
        p_min: lower clamp of a cell's probability.
        p_max: upper clamp.
        margin_m: free border around the observed area when the extent is automatic, m.
        occupied_thresh: ``map_server`` threshold: a cell is occupied above it.
        free_thresh: ``map_server`` threshold: a cell is free below it.
    """

    resolution_m: float = 0.05
    p_hit: float = 0.7
    p_miss: float = 0.4
    p_min: float = 0.12
    p_max: float = 0.97
    margin_m: float = 1.0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        if not self.resolution_m > 0:
            raise ValueError(f"GridConfig.resolution_m must be > 0, got {self.resolution_m}")
        if not 0.5 < self.p_hit < 1 or not 0 < self.p_miss < 0.5:
            raise ValueError("GridConfig: need 0.5 < p_hit < 1 and 0 < p_miss < 0.5")
        if not 0 < self.p_min < 0.5 < self.p_max < 1:
            raise ValueError("GridConfig: need 0 < p_min < 0.5 < p_max < 1")
        if not 0 <= self.free_thresh < self.occupied_thresh <= 1:
            raise ValueError("GridConfig: need 0 <= free_thresh < occupied_thresh <= 1")
        if self.margin_m < 0:
            raise ValueError(f"GridConfig.margin_m must be >= 0, got {self.margin_m}")


@dataclass
class OccupancyGrid:
    """A log-odds grid.

    Attributes:
        log_odds: (H, W) per cell, row 0 at the bottom (smallest y).
        resolution_m: cell side, m.
        origin: ``(x0, y0)`` of the lower-left corner of cell (0, 0), m.
        config: the settings that built it.
    """

    log_odds: torch.Tensor
    resolution_m: float
    origin: tuple[float, float]
    config: GridConfig

    def probability(self) -> torch.Tensor:
        """Occupancy probability (H, W)."""
        return torch.sigmoid(self.log_odds)

    def trinary(self) -> torch.Tensor:
        """(H, W) int8: 1 occupied, 0 free, -1 unknown, by ``map_server``'s thresholds."""
        p = self.probability()
        out = torch.full_like(p, -1, dtype=torch.int8)
        out[p > self.config.occupied_thresh] = 1
        out[p < self.config.free_thresh] = 0
        return out


@dataclass
class OccupancyMap:
    """A map read back from ``map_server`` files.

    Attributes:
        occupancy: (H, W) occupancy probability as ``map_server`` reads the pixels
            (``(255 - v) / 255``, or ``v / 255`` with ``negate``), row 0 at the bottom.
        trinary: (H, W) int8: 1 occupied, 0 free, -1 unknown.
        resolution_m: cell side, m.
        origin: ``(x0, y0, yaw)`` of the lower-left pixel, m and rad.
    """

    occupancy: np.ndarray
    trinary: np.ndarray
    resolution_m: float
    origin: tuple[float, float, float]


def ray_cells(
    start: torch.Tensor,
    end: torch.Tensor,
    origin: tuple[float, float],
    resolution_m: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cells crossed by segments ``start -> end`` (see the module docstring).

    The grid lines each segment crosses are enumerated flat (work grows with the total
    number of crossings, not with segments x the longest one), merged per segment by one
    sort on ``segment + s / 2`` (float64: crossings closer than about ``1e-10 R`` in ``s``
    may swap, which matters only for rays passing within that of a grid corner).

    Args:
        start: (R, 2) segment starts, m.
        end: (R, 2) segment ends, m.
        origin: grid origin ``(x0, y0)``, m.
        resolution_m: cell side, m.

    Returns:
        segment (P,) index of the segment each entry belongs to, cells (P, 2) integer
        ``(row, column)`` in order along each segment, and is_end (P,) bool, True for the
        cell that holds the segment's end point. Segments passing exactly through a grid
        corner skip the zero-length interval there.
    """
    x0, y0 = origin
    offset = torch.tensor([x0, y0], dtype=start.dtype, device=start.device)
    rel_start = (start - offset) / resolution_m
    rel_end = (end - offset) / resolution_m
    delta = rel_end - rel_start  # (R, 2), in cells
    count_r = start.shape[0]
    ray_ids = torch.arange(count_r, device=start.device)
    params = [
        torch.zeros(count_r, dtype=start.dtype, device=start.device),
        torch.ones(count_r, dtype=start.dtype, device=start.device),
    ]
    owners = [ray_ids, ray_ids]
    for axis in range(2):
        a, b = rel_start[:, axis], rel_end[:, axis]
        # grid lines k strictly between the two ends
        first = torch.floor(torch.minimum(a, b)).long() + 1
        last = torch.ceil(torch.maximum(a, b)).long() - 1
        count = (last - first + 1).clamp(min=0)
        owner = torch.repeat_interleave(ray_ids, count)
        begin = torch.cumsum(count, 0) - count
        k = first[owner] + torch.arange(owner.shape[0], device=start.device) - begin[owner]
        params.append((k.to(start.dtype) - a[owner]) / delta[owner, axis])
        owners.append(owner)
    s_all = torch.cat(params)
    owner_all = torch.cat(owners)
    # one sort on segment + s / 2 (s in [0, 1]): orders by segment, then along it
    order = torch.sort(owner_all.to(s_all.dtype) + 0.5 * s_all).indices
    s_sorted, owner_sorted = s_all[order], owner_all[order]
    lo, hi = s_sorted[:-1], s_sorted[1:]
    valid = (owner_sorted[:-1] == owner_sorted[1:]) & (hi > lo)
    segment = owner_sorted[:-1][valid]
    mid = 0.5 * (lo[valid] + hi[valid])
    point = rel_start[segment] + mid[:, None] * delta[segment]
    cells = torch.floor(point).long().flip(-1)  # (row = y, column = x)
    return segment, cells, hi[valid] == 1.0


def occupancy_grid(
    poses: torch.Tensor,
    ranges: torch.Tensor,
    angles: torch.Tensor,
    config: GridConfig | None = None,
    extent: tuple[float, float, float, float] | None = None,
    chunk: int = 16,
) -> OccupancyGrid:
    """Build a log-odds grid from scans taken at ``poses`` (see the module docstring).

    Args:
        poses: (N, 3) sensor poses ``[x, y, yaw]`` in the map frame, m and rad.
        ranges: (N, K) ranges, m; NaN, inf or <= 0 = no return (skipped).
        angles: (K,) beam angles in the sensor frame, rad.
        config: settings (default :class:`GridConfig`).
        extent: ``(x_min, y_min, x_max, y_max)`` of the grid, m; default the bounding box of
            the poses and end points plus ``margin_m``.
        chunk: scans traversed in one vectorised block (memory grows with the cells their
            rays cross).

    Raises:
        ValueError: the shapes disagree (names them), no scan and no ``extent``, or a
            setting is out of range.
    """
    config = config or GridConfig()
    config.validate()
    if (
        poses.ndim != 2
        or poses.shape[-1] != 3
        or ranges.ndim != 2
        or ranges.shape[0] != poses.shape[0]
        or angles.shape != ranges.shape[1:]
    ):
        raise ValueError(
            f"occupancy_grid: poses (N, 3), ranges (N, K) and angles (K,) needed, got "
            f"{tuple(poses.shape)}, {tuple(ranges.shape)} and {tuple(angles.shape)}"
        )
    res = config.resolution_m
    valid = torch.isfinite(ranges) & (ranges > 0)
    r = torch.where(valid, ranges, 0.0)
    local = torch.stack((r * torch.cos(angles), r * torch.sin(angles)), -1)  # (N, K, 2)
    ends = transform_points(poses, local)
    if extent is None:
        if poses.shape[0] == 0:
            raise ValueError("occupancy_grid: no scan to size the grid by; give extent")
        both = torch.cat((ends[valid], poses[:, :2]))
        low = both.min(0).values - config.margin_m
        high = both.max(0).values + config.margin_m
        extent = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
    x_min, y_min, x_max, y_max = extent
    width = max(1, int(math.ceil((x_max - x_min) / res)))
    height = max(1, int(math.ceil((y_max - y_min) / res)))
    origin = (x_min, y_min)
    log_odds = torch.zeros(height * width, dtype=poses.dtype, device=poses.device)
    l_hit, l_miss = logit(config.p_hit), logit(config.p_miss)
    l_min, l_max = logit(config.p_min), logit(config.p_max)
    cells_total = height * width
    for block in torch.arange(poses.shape[0], device=poses.device).split(chunk):
        keep = valid[block]  # (b, K)
        if not bool(keep.any()):
            continue
        stop = ends[block][keep]
        start = poses[block, None, :2].expand(-1, keep.shape[1], -1)[keep]
        scan = torch.arange(block.shape[0], device=poses.device)[:, None].expand_as(keep)[keep]
        segment, cells, is_end = ray_cells(start, stop, origin, res)
        inside = (
            (cells[:, 0] >= 0) & (cells[:, 0] < height) & (cells[:, 1] >= 0) & (cells[:, 1] < width)
        )
        update = torch.where(is_end, l_hit, l_miss).to(log_odds.dtype)
        key = (scan[segment] * cells_total + cells[:, 0] * width + cells[:, 1])[inside]
        unique, inverse = torch.unique(key, return_inverse=True)  # sorted: by scan, then cell
        summed = torch.zeros(unique.shape[0], dtype=log_odds.dtype, device=log_odds.device)
        summed = summed.index_add_(0, inverse, update[inside])
        cell = unique % cells_total
        bounds = torch.searchsorted(
            unique, torch.arange(block.shape[0] + 1, device=unique.device) * cells_total
        ).tolist()
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):  # scans in order, clamped
            touched = cell[lo:hi]
            log_odds[touched] = (log_odds[touched] + summed[lo:hi]).clamp(l_min, l_max)
    return OccupancyGrid(log_odds.reshape(height, width), res, origin, config)


def write_map(grid: OccupancyGrid, path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``grid`` as ``map_server`` files: ``path`` with suffix ``.png`` and ``.yaml``.

    Args:
        grid: the grid.
        path: the output stem (``maps/floor`` writes ``maps/floor.png`` and
            ``maps/floor.yaml``; a given suffix is replaced).

    Returns:
        (PNG path, YAML path).
    """
    from PIL import Image

    stem = Path(path)
    png, yaml_path = stem.with_suffix(".png"), stem.with_suffix(".yaml")
    png.parent.mkdir(parents=True, exist_ok=True)
    trinary = grid.trinary().cpu().numpy()
    pixels = np.full(trinary.shape, 205, dtype=np.uint8)
    pixels[trinary == 1] = 0
    pixels[trinary == 0] = 254
    image = Image.fromarray(pixels[::-1].copy(), mode="L")  # row 0 at the top
    with atomic_write(png, "wb") as handle:
        image.save(handle, format="PNG")
    text = (
        f"image: {png.name}\n"
        f"mode: trinary\n"
        f"resolution: {grid.resolution_m!r}\n"
        f"origin: [{grid.origin[0]!r}, {grid.origin[1]!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {grid.config.occupied_thresh!r}\n"
        f"free_thresh: {grid.config.free_thresh!r}\n"
    )
    with atomic_write(yaml_path, "w", encoding="utf-8") as handle:
        handle.write(text)
    return png, yaml_path


def read_map(path: str | os.PathLike[str]) -> OccupancyMap:
    """Read ``map_server`` files (the YAML and the image it names, relative to the YAML).

    Raises:
        DataError: a key is missing or malformed, or the image cannot be read.
    """
    import yaml
    from PIL import Image

    yaml_path = Path(path)
    with open(yaml_path, encoding="utf-8") as handle:
        meta = yaml.safe_load(handle) or {}
    for key in ("image", "resolution", "origin", "occupied_thresh", "free_thresh"):
        if key not in meta:
            raise DataError(yaml_path, "missing key", field=key)
    origin = meta["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise DataError(yaml_path, f"expected [x, y, yaw], got {origin!r}", field="origin")
    image_path = yaml_path.parent / str(meta["image"])
    try:
        with Image.open(image_path) as image:
            pixels = np.asarray(image.convert("L"), dtype=np.float64)[::-1]
    except OSError as err:
        raise DataError(image_path, f"cannot read the image: {err}") from err
    negate = int(meta.get("negate", 0))
    occupancy = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
    trinary = np.full(occupancy.shape, -1, dtype=np.int8)
    trinary[occupancy > float(meta["occupied_thresh"])] = 1
    trinary[occupancy < float(meta["free_thresh"])] = 0
    return OccupancyMap(
        occupancy=occupancy,
        trinary=trinary,
        resolution_m=float(meta["resolution"]),
        origin=(float(origin[0]), float(origin[1]), float(origin[2])),
    )
