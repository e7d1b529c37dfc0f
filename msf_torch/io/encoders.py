"""Wheel encoders: cumulative counts (ticks) or wheel angles -> the wheel speeds msf fuses.

Robots log their encoders as running counts (an embedded board's tick counters) or as wheel
angles (ROS ``JointState.position``). The front end wants rim speeds (``WheelSamples``,
m/s). Between two readings ``k - 1`` and ``k`` a wheel turns ``d_angle``; its mean rim speed
over that interval is ``radius * d_angle / (t_k - t_(k-1))``, stamped at the middle of the
interval (where a mean speed is the instantaneous speed to second order). With counts,
``d_angle = 2 pi d_count / counts_per_rev``; a counter that wraps (a 16- or 32-bit register)
is unwrapped with ``rollover`` (the count at which it wraps: 65536, 2**32): each step is
taken as the one in ``[-rollover / 2, rollover / 2)``. One count of resolution gives a speed
quantisation of ``2 pi radius / (counts_per_rev dt)`` (e.g. 1 cm/s for a 0.1 m wheel, 1024
counts and 60 ms between readings): the configured ``wheel_speed_sigma_mps`` should cover
it.

Counts file: a CSV with a header holding the time column (s) and one column per side
(default names ``t``, ``left_ticks``, ``right_ticks``; other columns are ignored). Blank
lines and ``#`` comments are skipped. The rules of :mod:`msf_torch.io.native` apply:
non-finite rows dropped and counted, time going backwards an error (unless ``sort``), a
repeated stamp dropped.

On the command line: ``msf encoders ticks.csv --ticks-per-rev 1024 --radius 0.1 --out
run/wheel.csv`` (a native ``wheel.csv``).
"""

from __future__ import annotations

__all__ = ["EncoderLog", "read_encoder_counts", "wheel_speeds_from_angles", "write_wheel_csv"]

import math
import os
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.io.native import write_stream_csv
from msf_torch.types import WheelSamples


def wheel_speeds_from_angles(
    t: np.ndarray, left_rad: np.ndarray, right_rad: np.ndarray, radius_m: SequenceABC[float]
) -> WheelSamples:
    """Mean rim speeds between consecutive wheel-angle readings (B = 1).

    Args:
        t: (N,) strictly increasing reading times, s.
        left_rad, right_rad: (N,) unwrapped wheel angles of each side, rad (forward
            positive).
        radius_m: ``(left, right)`` wheel radii, m.

    Returns:
        ``WheelSamples`` with N - 1 samples: ``t`` the interval midpoints (s),
        ``left_speed`` / ``right_speed`` m/s, float64.

    Raises:
        ValueError: times not strictly increasing, or mismatched lengths.
    """
    t = np.asarray(t, dtype=np.float64)
    left, right = (np.asarray(x, dtype=np.float64) for x in (left_rad, right_rad))
    if not (t.shape == left.shape == right.shape) or t.ndim != 1:
        raise ValueError(f"t, left and right must be (N,) alike, got {t.shape}, {left.shape}")
    step = np.diff(t)
    if np.any(step <= 0):
        raise ValueError("wheel reading times must increase strictly")
    if len(radius_m) != 2:
        raise ValueError(f"radius_m must be (left, right), got {list(radius_m)}")
    middle = t[:-1] + 0.5 * step
    speeds = [
        float(radius) * np.diff(angle) / step
        for radius, angle in zip(radius_m, (left, right), strict=True)
    ]
    n = middle.size
    return WheelSamples(
        t=torch.as_tensor(middle).reshape(1, n),
        left_speed=torch.as_tensor(speeds[0]).reshape(1, n),
        right_speed=torch.as_tensor(speeds[1]).reshape(1, n),
        mask=torch.ones(1, n, dtype=torch.bool),
    )


def _unwrapped(counts: np.ndarray, rollover: float | None) -> np.ndarray:
    """Running counts with the counter's wraps undone (``rollover`` None: as they are)."""
    if rollover is None or counts.size == 0:
        return counts
    step = np.diff(counts)
    step = (step + rollover / 2) % rollover - rollover / 2
    return counts[0] + np.concatenate(([0.0], np.cumsum(step)))


@dataclass
class EncoderLog:
    """Encoder counts read from a file (:func:`read_encoder_counts`).

    Attributes:
        source: the file read.
        t: (N,) reading times, s (increasing).
        left, right: (N,) running counts of each side, unwrapped.
        counts: the cleaning report (``dropped_nonfinite``, ``dropped_duplicates``,
            ``sorted``, ``rollovers``: wraps undone per side).
    """

    source: str
    t: np.ndarray
    left: np.ndarray
    right: np.ndarray
    counts: dict[str, Any] = field(default_factory=dict)

    def wheel_speeds(
        self, counts_per_rev: SequenceABC[float], radius_m: SequenceABC[float]
    ) -> WheelSamples:
        """Mean rim speeds between consecutive readings (module docstring), B = 1.

        Args:
            counts_per_rev: ``(left, right)`` counts per wheel revolution (> 0).
            radius_m: ``(left, right)`` wheel radii, m (> 0).

        Raises:
            ValueError: a non-positive or non-finite count or radius; fewer than 2 readings.
            DataError: a speed that is not finite (readings too close in time).
        """
        for name, pair in (("counts_per_rev", counts_per_rev), ("radius_m", radius_m)):
            if len(pair) != 2 or not all(math.isfinite(x) and x > 0 for x in pair):
                raise ValueError(f"{name} must be two positive numbers, got {list(pair)}")
        if self.t.size < 2:
            raise ValueError(f"{self.source}: {self.t.size} reading(s); speeds need at least 2")
        to_rad = [2.0 * math.pi / c for c in counts_per_rev]
        wheel = wheel_speeds_from_angles(
            self.t, self.left * to_rad[0], self.right * to_rad[1], radius_m
        )
        finite = torch.isfinite(wheel.left_speed[0]) & torch.isfinite(wheel.right_speed[0])
        if not bool(finite.all()):
            k = int((~finite).nonzero()[0])
            raise DataError(
                self.source,
                f"the speed between the readings at {self.t[k]!r} s and {self.t[k + 1]!r} s "
                "is not finite (counts too large, or readings too close in time)",
            )
        return wheel


def read_encoder_counts(
    path: str | os.PathLike[str],
    columns: SequenceABC[str] = ("t", "left_ticks", "right_ticks"),
    rollover: float | None = None,
    sort: bool = False,
) -> EncoderLog:
    """Read running encoder counts from a CSV file (module docstring).

    Args:
        path: the CSV file.
        columns: names of the time (s), left-count and right-count columns.
        rollover: the count at which the counters wrap (e.g. 65536), or None.
        sort: sort rows whose times go backwards instead of raising.

    Returns:
        an :class:`EncoderLog`.

    Raises:
        DataError: a missing column, a cell that is not a number (file, line, column), time
            going backwards, no rows. ValueError: a bad ``columns`` or ``rollover``.
    """
    if len(columns) != 3 or len(set(columns)) != 3:
        raise ValueError(f"columns must be three distinct names, got {list(columns)}")
    if rollover is not None and not (math.isfinite(rollover) and rollover > 0):
        raise ValueError(f"rollover must be a positive count, got {rollover!r}")
    table = _tables.read_table(path)
    header = table.header or []
    for name in columns:
        if name not in header:
            raise DataError(
                path,
                f"no column {name!r} (header: {', '.join(header) or 'empty'})",
                line=table.header_line,
                field=name,
            )
    values = table.floats(list(columns))
    report = _tables.CleanReport()
    clean = _tables.clean_stream(
        report,
        "wheel",
        str(path),
        {"t": values[:, 0], "left": values[:, 1], "right": values[:, 2]},
        lines=table.lines,
        sort=sort,
        time_name=columns[0],
    )
    if clean["t"].size == 0:
        raise DataError(path, "no encoder readings")
    left, right = (_unwrapped(clean[k], rollover) for k in ("left", "right"))
    wraps = {
        side: int(np.count_nonzero(np.diff(raw) != np.diff(done)))
        for side, raw, done in (("left", clean["left"], left), ("right", clean["right"], right))
    }
    meta = report.to_meta()
    counts = {key: meta[key]["wheel"] for key in ("dropped_nonfinite", "dropped_duplicates")}
    counts.update(sorted=meta["sorted"]["wheel"], rollovers=wraps)
    return EncoderLog(str(path), clean["t"], left, right, counts)


def write_wheel_csv(path: str | os.PathLike[str], wheel: WheelSamples) -> Path:
    """Write a B = 1 wheel stream as a native ``wheel.csv`` (``t,left_speed,right_speed``;
    s, m/s), atomically; real samples only.

    Raises:
        ValueError: B != 1.
    """
    return write_stream_csv(path, "wheel", wheel)
