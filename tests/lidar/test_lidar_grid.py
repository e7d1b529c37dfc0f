"""Occupancy grid: exact ray traversal against segment-box geometry, the log-odds update,
and the map_server PNG + YAML round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from msf_torch.io.errors import DataError
from msf_torch.lidar.grid import (
    GridConfig,
    OccupancyGrid,
    logit,
    occupancy_grid,
    ray_cells,
    read_map,
    write_map,
)

F64 = torch.float64


def _cells_by_geometry(start, end, origin, res, tol=1e-9):
    """Cells whose interior the segment crosses over a positive length (Liang-Barsky)."""
    x0, y0 = origin
    lo = np.floor((np.minimum(start, end) - (x0, y0)) / res).astype(int) - 1
    hi = np.floor((np.maximum(start, end) - (x0, y0)) / res).astype(int) + 1
    d = end - start
    out = set()
    for row in range(lo[1], hi[1] + 1):
        for col in range(lo[0], hi[0] + 1):
            box_lo = np.array([x0 + col * res, y0 + row * res])
            box_hi = box_lo + res
            t0, t1 = 0.0, 1.0
            for axis in range(2):
                if abs(d[axis]) < 1e-300:
                    if not box_lo[axis] < start[axis] < box_hi[axis]:
                        t0, t1 = 1.0, 0.0
                    continue
                a = (box_lo[axis] - start[axis]) / d[axis]
                b = (box_hi[axis] - start[axis]) / d[axis]
                t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
            if t1 - t0 > tol:
                out.add((row, col))
    return out


def test_ray_cells_match_segment_box_geometry():
    rng = np.random.default_rng(0)
    origin, res = (-3.3, -2.1), 0.25
    start = rng.uniform(-2, 2, (60, 2))
    end = start + rng.uniform(-2.5, 2.5, (60, 2))
    end[:5, 1] = start[:5, 1]  # horizontal
    end[5:10, 0] = start[5:10, 0]  # vertical
    segment, cells, is_end = ray_cells(torch.tensor(start), torch.tensor(end), origin, res)
    for k in range(60):
        mine = cells[segment == k].tolist()
        assert len(mine) == len(set(map(tuple, mine)))  # each cell once, in order
        expected = _cells_by_geometry(start[k], end[k], origin, res)
        assert set(map(tuple, mine)) == expected
        # consecutive cells share an edge (no corner passes for random segments)
        steps = np.abs(np.diff(np.array(mine), axis=0)).sum(1)
        assert np.all(steps == 1)
        end_cell = mine[int(torch.nonzero(is_end[segment == k])[0, 0])]
        assert end_cell == mine[-1]
        assert tuple(end_cell) == tuple(
            np.floor((end[k][::-1] - np.array(origin)[::-1]) / res).astype(int)
        )
        assert int(is_end[segment == k].sum()) == 1


def test_log_odds_of_one_and_repeated_beams():
    config = GridConfig(resolution_m=0.1, margin_m=0.5)
    poses = torch.tensor([[0.05, 0.05, 0.0]], dtype=F64)
    angles = torch.zeros(1, dtype=F64)
    ranges = torch.tensor([[1.0]], dtype=F64)  # end at x = 1.05: cell column 10 from 0.05
    grid = occupancy_grid(poses, ranges, angles, config, extent=(0.0, 0.0, 2.0, 1.0))
    row = grid.log_odds[0]
    assert row[:10].tolist() == pytest.approx([logit(0.4)] * 10)
    assert float(row[10]) == pytest.approx(logit(0.7))
    assert float(row[11:].abs().max()) == 0.0 and float(grid.log_odds[1:].abs().max()) == 0.0
    # twenty identical scans: hits clamp at logit(0.97), misses at logit(0.12)
    many = occupancy_grid(
        poses.expand(20, 3), ranges.expand(20, 1), angles, config, extent=(0.0, 0.0, 2.0, 1.0)
    )
    assert float(many.log_odds[0, 10]) == pytest.approx(logit(0.97))
    assert float(many.log_odds[0, 3]) == pytest.approx(logit(0.12))
    # the clamp is applied after each scan, not at the end: 3 misses then 1 hit on cell 5
    mixed = occupancy_grid(
        torch.tensor([[0.05, 0.05, 0.0]] * 4, dtype=F64),
        torch.tensor([[1.0], [1.0], [1.0], [0.5]], dtype=F64),
        angles, config, extent=(0.0, 0.0, 2.0, 1.0), chunk=2,
    )  # fmt: skip
    expected = max(3 * logit(0.4), logit(0.12)) + logit(0.7)
    assert float(mixed.log_odds[0, 5]) == pytest.approx(expected)


def test_zero_and_non_finite_ranges_are_no_return():
    """Beams reporting 0 m, NaN or inf change no cell: only the 1 m beam updates the grid
    (the previous code counted a 0 m beam as a hit in the sensor's own cell)."""
    config = GridConfig(resolution_m=0.1, margin_m=0.5)
    poses = torch.tensor([[0.05, 0.05, 0.0]], dtype=F64)
    angles = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=F64)
    extent = (-2.0, -2.0, 2.0, 2.0)
    ranges = torch.tensor([[1.0, 0.0, math.nan, math.inf]], dtype=F64)
    grid = occupancy_grid(poses, ranges, angles, config, extent=extent)
    alone = occupancy_grid(poses, ranges[:, :1], angles[:1], config, extent=extent)
    assert torch.equal(grid.log_odds, alone.log_odds)
    assert float(grid.log_odds[20, 20]) == pytest.approx(logit(0.4))  # the sensor's cell


def test_bad_shapes_are_named():
    """Angles of another beam count than the ranges, or no scan without an extent: a
    ValueError naming what is wrong (the previous code failed inside a broadcast or a
    reduction)."""
    poses = torch.zeros(3, 3, dtype=F64)
    with pytest.raises(ValueError, match=r"got \(3, 3\), \(3, 10\) and \(9,\)"):
        occupancy_grid(poses, torch.ones(3, 10, dtype=F64), torch.zeros(9, dtype=F64))
    with pytest.raises(ValueError, match="give extent"):
        occupancy_grid(poses[:0], torch.ones(0, 4, dtype=F64), torch.zeros(4, dtype=F64))


def test_beams_in_a_room_mark_walls_occupied_and_inside_free():
    from msf_torch.sim.lidar2d import LidarSpec, SegmentMap, scan_at

    room = SegmentMap(
        "box",
        torch.tensor([[[0, 0], [6, 0]], [[6, 0], [6, 4]], [[6, 4], [0, 4]], [[0, 4], [0, 0]]],
                     dtype=F64),
        torch.tensor([[1.0, 1.0], [5.0, 3.0]], dtype=F64),
    )  # fmt: skip
    spec = LidarSpec(fov_deg=360.0 - 0.5, max_incidence_deg=90.0)
    poses = torch.tensor([[1.5, 1.2, 0.3], [4.1, 2.9, -2.0], [3.0, 2.0, 1.0]], dtype=F64)
    ranges, _ = scan_at(room, poses, spec)
    config = GridConfig(resolution_m=0.1)
    grid = occupancy_grid(poses, ranges, spec.angles(), config, extent=(-0.5, -0.5, 6.5, 4.5))
    trinary = grid.trinary()
    rows, cols = torch.nonzero(trinary == 1, as_tuple=True)
    centre_x = -0.5 + (cols.double() + 0.5) * 0.1
    centre_y = -0.5 + (rows.double() + 0.5) * 0.1
    to_wall = torch.stack(
        (centre_x.abs(), (centre_x - 6).abs(), centre_y.abs(), (centre_y - 4).abs()), -1
    ).amin(-1)
    assert len(rows) > 100
    assert float(to_wall.max()) <= 0.1 * math.sqrt(2) / 2 + 1e-12  # the cell holds a wall
    inner = trinary[10:40, 10:60]  # 0.5 m inside every wall
    assert bool((inner == 0).all())


def test_map_server_round_trip(tmp_path):
    config = GridConfig(resolution_m=0.2)
    log_odds = torch.zeros(3, 4, dtype=F64)
    log_odds[0, 0] = 3.0  # occupied, bottom-left
    log_odds[2, 3] = -3.0  # free, top-right
    grid = OccupancyGrid(log_odds, 0.2, (-1.0, 2.5), config)
    png, yaml_path = write_map(grid, tmp_path / "maps" / "floor")
    assert png.name == "floor.png" and yaml_path.name == "floor.yaml"
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["image"] == "floor.png"
    assert meta["resolution"] == 0.2 and meta["origin"] == [-1.0, 2.5, 0.0]
    assert meta["negate"] == 0
    assert meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196
    from PIL import Image

    pixels = np.asarray(Image.open(png))
    assert pixels.shape == (3, 4)
    assert pixels[2, 0] == 0  # bottom-left is the last image row
    assert pixels[0, 3] == 254
    assert pixels[1, 1] == 205
    back = read_map(yaml_path)
    assert np.array_equal(back.trinary, grid.trinary().numpy())
    assert back.origin == (-1.0, 2.5, 0.0) and back.resolution_m == 0.2


def test_read_map_names_missing_keys(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("image: x.png\nresolution: 0.05\n")
    with pytest.raises(DataError, match="origin"):
        read_map(path)
