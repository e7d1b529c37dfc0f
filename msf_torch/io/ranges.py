"""Odometry + range-beacon runs from CSV files: a wheeled robot's odometry poses, ranges to
anchors (UWB anchors, radio beacons) and the anchors' positions; read into a
:class:`RangeRun` for :mod:`msf_torch.backend.range2d` (``msf ranges``).

Files (CSV with a header line, columns in any order; ``#`` comment lines and blank lines are
skipped; times in s, lengths in m, angles in rad)
    * odometry: ``t,x,y,heading`` -- the robot's wheel-odometry poses in its odometry frame
      (a ``nav_msgs/Odometry`` topic exported, heading = yaw). Consecutive rows give the
      odometry steps (the pose of row k + 1 seen from row k); the run's poses sit at these
      times.
    * ranges: ``t,anchor,range`` -- anchor ids are integers.
    * anchors: ``anchor,x,y`` -- the anchors' positions in the map frame (surveyed, or a
      first guess when they are solved for); no file when their positions are unknown.
    * truth (optional): ``t,x,y`` -- reference positions in the map frame (RTK, a motion
      capture), interpolated linearly to the pose times for the error figures.

Rules
    A missing or unknown column, a value that is not a finite number, odometry times that do
    not increase, a duplicate anchor id, an anchor id or range that is not a whole number or
    is negative, a range to an anchor the anchors file does not list, and an odometry step or
    interpolated truth position that overflows the float range are DataErrors naming file,
    line and column. Ranges out of time order are sorted (``meta``
    counts them); ranges before the first or after the last odometry time are dropped
    (counted in ``meta["ranges_outside"]``), as are ranges inside a gap of the odometry
    (more than two median odometry periods from the pose before and the pose after; counted
    in ``meta["ranges_in_gaps"]``): a range is attached to the first pose at or after its
    time, and across a gap that pose can be far from where the range was taken. Anchors left
    with no range are listed in ``meta["anchors_without_ranges"]`` (held, they play no part;
    solved, they stay at their first guess). The truth must span the odometry's times to
    within one of its own sample periods (a 5 Hz reference may end before 10 Hz odometry).
    With an anchors file, a median range over 20 times the size of the scene (odometry and
    anchors) is a DataError: ranges in mm or cm.
"""

from __future__ import annotations

__all__ = ["RangeRun", "read_range_run", "write_anchors"]

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.se2 import between, chain
from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_write
from msf_torch.io.errors import DataError


@dataclass
class RangeRun:
    """One run of odometry and anchor ranges (float64 CPU tensors).

    Attributes:
        name: a label (file stem or dataset name).
        pose_t: (M + 1,) s, the time of each pose.
        odometry: (M, 3) ``[dx, dy, dheading]`` (m, m, rad): pose k + 1 in pose k's frame.
        range_t: (K,) s, non-decreasing. range_anchor: (K,) int64 anchor id of each range.
        ranges: (K,) m, as measured.
        anchor_ids: (L,) int64. anchors: (L, 2) m, positions in the map frame.
        truth: (M + 1, 3) ``[x, y, heading]`` at the pose times in the map frame (heading
            NaN where the source has none), or None.
        meta: what the reader did and noticed.
    """

    name: str
    pose_t: torch.Tensor
    odometry: torch.Tensor
    range_t: torch.Tensor
    range_anchor: torch.Tensor
    ranges: torch.Tensor
    anchor_ids: torch.Tensor
    anchors: torch.Tensor
    truth: torch.Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def range_pose_index(self) -> torch.Tensor:
        """(K,) int64 pose each range is attached to: the first pose at or after its time."""
        index = torch.searchsorted(self.pose_t, self.range_t)
        return index.clamp(max=self.pose_t.shape[0] - 1)

    def range_pose_fraction(self) -> torch.Tensor:
        """(K,) where each range's time lies between the pose before it (0) and the pose
        :meth:`range_pose_index` attaches it to (1): ``(t - t_{j-1}) / (t_j - t_{j-1})``;
        1 for a range at or before the first pose or after the last."""
        after = self.range_pose_index()
        before = (after - 1).clamp(min=0)
        span = self.pose_t[after] - self.pose_t[before]
        fraction = (self.range_t - self.pose_t[before]) / torch.where(span > 0, span, 1.0)
        return torch.where(span > 0, fraction.clamp(0.0, 1.0), torch.ones_like(fraction))

    def range_positions(self, poses: torch.Tensor) -> torch.Tensor:
        """(K, 2) positions at the range times, linearly interpolated between the poses
        (M + 1, >= 2) around each range (:meth:`range_pose_fraction`)."""
        after = self.range_pose_index()
        before = (after - 1).clamp(min=0)
        fraction = self.range_pose_fraction().to(poses.dtype)[:, None]
        return (1.0 - fraction) * poses[before, 0:2] + fraction * poses[after, 0:2]

    def thinned(self, every: int) -> RangeRun:
        """The run with every ``every``-th odometry pose (the steps between composed into
        one), the truth at those poses and the ranges up to the last pose kept: the same run
        as a slower odometry would have logged it.

        Raises:
            ValueError: ``every`` below 1.
        """
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        poses = self.odometry_poses(self.odometry.new_zeros(3))
        keep = torch.arange(0, poses.shape[0], every, device=poses.device)
        inside = self.range_t <= self.pose_t[keep[-1]]
        return dataclasses.replace(
            self,
            pose_t=self.pose_t[keep],
            odometry=between(poses[keep[:-1]], poses[keep[1:]]),
            truth=None if self.truth is None else self.truth[keep],
            range_t=self.range_t[inside],
            range_anchor=self.range_anchor[inside],
            ranges=self.ranges[inside],
        )

    def range_anchor_rows(self) -> torch.Tensor:
        """(K,) int64 row of ``anchors`` each range is to."""
        return torch.searchsorted(self.anchor_ids, self.range_anchor)

    def odometry_poses(self, start: torch.Tensor | None = None) -> torch.Tensor:
        """Dead reckoning: (M + 1, 3) poses chained from ``start`` (3,) by the odometry
        (default: the truth's first pose when there is a truth, else the origin)."""
        if start is None:
            has_truth = self.truth is not None and bool(torch.isfinite(self.truth[0]).all())
            start = self.truth[0] if has_truth else self.odometry.new_zeros(3)
        return chain(start.to(self.odometry.dtype), self.odometry)


_UNITS_RATIO = 20.0
"""A median range this many times the scene's size (the odometry's and the anchors' extent)
means the ranges are not in metres: the robot ranges anchors around it."""


def _read(path: str | os.PathLike[str], required: list[str]) -> tuple[Any, np.ndarray]:
    table = _tables.read_table(path)
    _tables.check_columns(table, required)
    values = table.floats(required)
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = (int(x) for x in np.argwhere(bad)[0])
        raise DataError(table.path, "not finite", line=int(table.lines[row]), field=required[col])
    return table, values


def _whole(table: Any, values: np.ndarray, name: str) -> np.ndarray:
    """A column of non-negative whole numbers as int64, else a DataError naming the row."""
    bad = (values < 0) | (values != np.floor(values)) | (values >= 2**62)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            table.path,
            f"not a non-negative whole number: {float(values[row])!r}",
            line=int(table.lines[row]),
            field=name,
        )
    return values.astype(np.int64)


def read_range_run(
    odometry: str | os.PathLike[str],
    ranges: str | os.PathLike[str],
    anchors: str | os.PathLike[str] | None = None,
    truth: str | os.PathLike[str] | None = None,
) -> RangeRun:
    """Read a run from its CSV files (module docstring).

    Args:
        odometry, ranges: the files. anchors: the anchors file, or None when their positions
            are unknown (range-only SLAM without guesses): the ids are those the ranges
            name, the positions NaN. truth: optional reference positions.

    Returns:
        a :class:`RangeRun`; ``meta`` holds the files, the ranges sorted and dropped, and
        the truth's coverage.

    Raises:
        DataError: naming file, line and column (module docstring).
    """
    odo_table, odo = _read(odometry, ["t", "x", "y", "heading"])
    if odo.shape[0] < 2:
        raise DataError(odo_table.path, f"need at least 2 odometry rows, got {odo.shape[0]}")
    back = np.flatnonzero(np.diff(odo[:, 0]) <= 0)
    if back.size:
        raise DataError(
            odo_table.path,
            "odometry times must increase",
            line=int(odo_table.lines[back[0] + 1]),
            field="t",
        )
    range_table, rng = _read(ranges, ["t", "anchor", "range"])
    range_ids = _whole(range_table, rng[:, 1], "anchor")
    if anchors is None:
        anchor_ids = np.unique(range_ids)
        anc = np.full((anchor_ids.size, 3), np.nan)
        anchor_path = None
    else:
        anchor_table, anc = _read(anchors, ["anchor", "x", "y"])
        anchor_path = anchor_table.path
        anchor_ids = _whole(anchor_table, anc[:, 0], "anchor")
        order = np.argsort(anchor_ids, kind="stable")
        repeated = np.flatnonzero(np.diff(anchor_ids[order]) == 0)
        if repeated.size:
            row = int(order[repeated[0] + 1])
            raise DataError(
                anchor_table.path,
                f"anchor {anchor_ids[row]} is listed twice",
                line=int(anchor_table.lines[row]),
                field="anchor",
            )
    if (rng[:, 2] < 0).any():
        row = int(np.flatnonzero(rng[:, 2] < 0)[0])
        raise DataError(
            range_table.path,
            f"negative range {float(rng[row, 2])!r}",
            line=int(range_table.lines[row]),
            field="range",
        )
    unknown = ~np.isin(range_ids, anchor_ids)
    if unknown.any():
        row = int(np.flatnonzero(unknown)[0])
        raise DataError(
            range_table.path,
            f"range to anchor {range_ids[row]}, which {Path(str(anchor_path)).name} does not "
            f"list ({sorted(anchor_ids.tolist())})",
            line=int(range_table.lines[row]),
            field="anchor",
        )
    time_order = np.argsort(rng[:, 0], kind="stable")
    reordered = int((time_order != np.arange(time_order.size)).sum())
    rng, range_ids = rng[time_order], range_ids[time_order]
    inside = (rng[:, 0] >= odo[0, 0]) & (rng[:, 0] <= odo[-1, 0])
    period = float(np.median(np.diff(odo[:, 0])))
    after = np.clip(np.searchsorted(odo[:, 0], rng[:, 0]), 0, odo.shape[0] - 1)
    before = np.clip(after - 1, 0, odo.shape[0] - 1)
    in_gap = inside & (
        np.minimum(odo[after, 0] - rng[:, 0], rng[:, 0] - odo[before, 0]) > 2.0 * period
    )
    meta: dict[str, Any] = {
        "files": {
            "odometry": odo_table.path,
            "ranges": range_table.path,
            "anchors": anchor_path,
        },
        "ranges_reordered": reordered,
        "ranges_outside": int((~inside).sum()),
        "ranges_in_gaps": int(in_gap.sum()),
    }
    kept = inside & ~in_gap
    rng, range_ids, range_lines = rng[kept], range_ids[kept], range_table.lines[time_order][kept]
    if anchors is not None and rng.shape[0]:
        scene = float(np.hypot(*np.ptp(np.concatenate((odo[:, 1:3], anc[:, 1:3])), axis=0)))
        if np.median(rng[:, 2]) > _UNITS_RATIO * max(scene, 1.0):
            raise DataError(
                range_table.path,
                f"the median range {np.median(rng[:, 2]):.4g} is over {_UNITS_RATIO:g} times "
                f"the size of the scene ({scene:.4g} m across the odometry and the anchors): "
                "ranges in mm or cm? ranges are in metres",
                line=int(range_lines[0]),
                field="range",
            )
    meta["anchors_without_ranges"] = sorted(set(anchor_ids.tolist()) - set(range_ids.tolist()))

    def f64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    poses = f64(odo[:, 1:4])
    steps = between(poses[:-1], poses[1:])
    if not bool(torch.isfinite(steps).all()):
        step, col = (int(x) for x in torch.nonzero(~torch.isfinite(steps))[0])
        raise DataError(
            odo_table.path,
            f"the odometry step from line {int(odo_table.lines[step])} overflows (the "
            "positions are too large)",
            line=int(odo_table.lines[step + 1]),
            field=("x", "y", "heading")[col],
        )
    reference = None
    if truth is not None:
        truth_table, ref = _read(truth, ["t", "x", "y"])
        meta["files"]["truth"] = truth_table.path
        if ref.shape[0] < 2 or (np.diff(ref[:, 0]) <= 0).any():
            raise DataError(truth_table.path, "need 2 or more rows with increasing times")
        step = float(np.median(np.diff(ref[:, 0])))  # a slower reference may end early
        if odo[0, 0] < ref[0, 0] - step or odo[-1, 0] > ref[-1, 0] + step:
            raise DataError(
                truth_table.path,
                f"covers {ref[0, 0]:.3f}..{ref[-1, 0]:.3f} s, not the odometry's "
                f"{odo[0, 0]:.3f}..{odo[-1, 0]:.3f} s",
            )
        xy = np.stack([np.interp(odo[:, 0], ref[:, 0], ref[:, k]) for k in (1, 2)], -1)
        if not np.isfinite(xy).all():
            pose, col = (int(x) for x in np.argwhere(~np.isfinite(xy))[0])
            row = int(np.clip(np.searchsorted(ref[:, 0], odo[pose, 0]), 1, ref.shape[0] - 1))
            raise DataError(
                truth_table.path,
                f"the truth interpolated to the pose at {odo[pose, 0]!r} s overflows (the "
                "positions are too large)",
                line=int(truth_table.lines[row]),
                field="xy"[col],
            )
        reference = torch.cat((f64(xy), torch.full((xy.shape[0], 1), float("nan"))), -1)
    order = np.argsort(anchor_ids)
    return RangeRun(
        name=Path(odometry).stem,
        pose_t=f64(odo[:, 0]),
        odometry=steps,
        range_t=f64(rng[:, 0]),
        range_anchor=torch.as_tensor(range_ids),
        ranges=f64(rng[:, 2]),
        anchor_ids=torch.as_tensor(anchor_ids[order]),
        anchors=f64(anc[order, 1:3]),
        truth=reference,
        meta=meta,
    )


def write_anchors(path: str | os.PathLike[str], ids: torch.Tensor, positions: torch.Tensor) -> Path:
    """Write anchors as the CSV ``anchor,x,y`` that :func:`read_range_run` reads (atomically).

    Args:
        path: the file (parent folders created). ids: (L,) int. positions: (L, 2) m.

    Returns:
        the path written.
    """
    target = Path(path)
    with atomic_write(target, newline="") as handle:
        handle.write("anchor,x,y\n")
        for anchor, (x, y) in zip(ids.tolist(), positions.tolist(), strict=True):
            handle.write(f"{anchor},{x!r},{y!r}\n")
    return target
