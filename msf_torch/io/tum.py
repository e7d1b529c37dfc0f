"""TUM trajectory files: ``t x y z qx qy qz qw`` per line, space separated.

The TUM RGB-D benchmark format, read and written by evo, rpg_trajectory_evaluation and most
SLAM systems. Times in s, positions in m, the quaternion (body -> world) in ``[x, y, z, w]``
order in the file and ``[w, x, y, z]`` in memory (``msf_torch.geometry.conventions``).
Lines starting with ``#`` and blank lines are ignored.
"""

from __future__ import annotations

__all__ = ["TUM_COLUMNS", "read_tum", "write_tum"]

import os
from pathlib import Path

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_write
from msf_torch.types import Trajectory

TUM_COLUMNS = ["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
"""Column names of a TUM file, in file order (used in error messages)."""


def read_tum(path: str | os.PathLike[str], sort: bool = False) -> Trajectory:
    """Read a TUM trajectory file.

    Rules: a line must have 8 numbers; a non-finite value or a zero quaternion raises
    DataError (a trajectory carries no meta to count dropped poses in, and an estimate
    with NaN must not pass silently); times going backwards raise DataError unless ``sort``
    (stable sort); a pose whose time exactly repeats the previous one is dropped (the first
    is kept). Quaternions are normalised.

    Args:
        path: the TUM file.
        sort: stably sort by time instead of raising on backwards timestamps.

    Returns:
        a :class:`~msf_torch.types.Trajectory` with B = 1: ``t`` (1, N) s, ``position``
        (1, N, 3) m, ``quaternion`` (1, N, 4) ``[w, x, y, z]``, ``mask`` (1, N) all True.

    Raises:
        DataError: naming the file, line and column of bad input.
    """
    table = _tables.read_table(path, delimiter=None, header="none", names=TUM_COLUMNS)
    data = table.finite_floats(TUM_COLUMNS, "poses")
    quat = data[:, [7, 4, 5, 6]]
    _tables.check_quaternions(table.path, quat, lines=table.lines, name="qw")
    arrays = {"t": data[:, 0], "position": data[:, 1:4], "quaternion": quat}
    report = _tables.CleanReport()
    arrays = _tables.clean_stream(report, "tum", table.path, arrays, lines=table.lines, sort=sort)
    arrays["quaternion"] = _tables.normalise_quaternions(arrays["quaternion"])
    return _tables.stream_from_arrays(Trajectory, arrays)


def _time_text(t: float) -> str:
    """Shortest exact decimal for a time, never in exponent notation."""
    return np.format_float_positional(t, unique=True, trim="0")


def write_tum(traj: Trajectory, path: str | os.PathLike[str]) -> Path:
    """Write a B = 1 trajectory as a TUM file, atomically and at full float64 precision.

    Only real poses (mask True) are written. Each number is written as the shortest decimal
    that reads back to the same float64 (times in positional notation), so ``read_tum``
    and evo's ``file_interface.read_tum_trajectory_file`` recover exactly the stored values.
    A ``# t x y z qx qy qz qw`` comment heads the file.

    Args:
        traj: the trajectory, B = 1; ``t`` (1, N) s, ``position`` (1, N, 3) m,
            ``quaternion`` (1, N, 4) ``[w, x, y, z]``.
        path: the output file.

    Returns:
        the path written.

    Raises:
        ValueError: B != 1, or a non-finite time, position or quaternion (named by index).
    """
    if traj.batch_size != 1:
        raise ValueError(f"write_tum writes one trajectory, got B = {traj.batch_size}")
    traj.check("trajectory")
    traj = traj.compact()

    def host(x: torch.Tensor) -> np.ndarray:
        return x[0].detach().to(device="cpu", dtype=torch.float64).numpy()

    t, pos, quat = host(traj.t), host(traj.position), host(traj.quaternion)
    values = np.hstack((pos, quat[:, [1, 2, 3, 0]]))
    finite = np.isfinite(values).all(axis=1) & np.isfinite(t)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(
            f"trajectory pose {i} (t = {float(t[i])!r}) is not finite; a TUM file cannot hold it"
        )
    target = Path(path)
    with atomic_write(target, newline="") as handle:
        handle.write("# " + " ".join(TUM_COLUMNS) + "\n")
        for time, row in zip(t.tolist(), values.tolist(), strict=True):
            handle.write(_time_text(time) + " " + " ".join(map(repr, row)) + "\n")
    return target
