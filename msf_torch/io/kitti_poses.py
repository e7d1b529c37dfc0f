"""KITTI odometry pose files: one pose per line, the 12 entries of ``[R | t]`` row-major.

The format of the KITTI odometry benchmark's ``poses/XX.txt`` (read by evo's
``evo_traj kitti`` / ``evo_ape kitti``): line ``i`` holds
``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz``, the pose of the body in the world frame
(``p_world = R p_body + t``), space separated. The file has no times; KITTI keeps them in a
separate ``times.txt`` (one time in s per line), which :func:`write_kitti_poses` writes
alongside when asked. Poses are written as they are (not re-based on the first pose).

The frames are whatever the file holds; nothing is re-oriented on read. The benchmark's
ground truth is the left camera's pose in the first camera frame (camera axes: x right,
y down, z forward), not a body pose in msf_torch's gravity-aligned ENU world (z up), so
compare an estimate with it after an SE(3) alignment (:mod:`msf_torch.eval`) or after
applying the camera-to-body calibration.
"""

from __future__ import annotations

__all__ = ["read_kitti_poses", "write_kitti_poses"]

import os
from pathlib import Path

import numpy as np
import torch

from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_write
from msf_torch.io.errors import DataError
from msf_torch.types import Trajectory

_COLUMNS = ["r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz"]
ROTATION_TOLERANCE = 1e-3
"""Largest ``|R^T R - I|`` entry a pose's 3x3 block may have (files written with 6-9
significant digits are orthonormal to ~1e-6); beyond it the line is rejected."""


def write_kitti_poses(
    trajectory: Trajectory,
    path: str | os.PathLike[str],
    times_path: str | os.PathLike[str] | None = None,
) -> Path:
    """Write a B = 1 trajectory as a KITTI pose file (and optionally its times file).

    Each number is the shortest decimal that reads back to the same float64; both files are
    written atomically.

    Args:
        trajectory: poses, B = 1: ``t`` (1, N) s, ``position`` (1, N, 3) m, ``quaternion``
            (1, N, 4) ``[w, x, y, z]``.
        path: the pose file.
        times_path: where to write the times (one per line, s), or None.

    Returns:
        the pose file's path.

    Raises:
        ValueError: B != 1 or a non-finite pose (named by index).
    """
    if trajectory.batch_size != 1:
        raise ValueError(
            f"write_kitti_poses writes one trajectory, got B = {trajectory.batch_size}"
        )
    traj = trajectory.compact()
    rot = quat_to_matrix(traj.quaternion[0].detach().to(torch.float64)).numpy()
    pos = traj.position[0].detach().to(torch.float64).numpy()
    t = traj.t[0].detach().to(torch.float64).numpy()
    rows = np.concatenate((rot, pos[:, :, None]), -1).reshape(-1, 12)
    finite = np.isfinite(rows).all(axis=1) & np.isfinite(t)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"trajectory pose {i} (t = {float(t[i])!r}) is not finite")
    target = Path(path)
    with atomic_write(target, newline="") as handle:
        for row in rows.tolist():
            handle.write(" ".join(map(repr, row)) + "\n")
    if times_path is not None:
        with atomic_write(times_path, newline="") as handle:
            for time in t.tolist():
                handle.write(np.format_float_positional(time, unique=True, trim="0") + "\n")
    return target


def read_kitti_poses(
    path: str | os.PathLike[str], times_path: str | os.PathLike[str] | None = None
) -> Trajectory:
    """Read a KITTI pose file (and its times file, else times 0, 1, 2, ... s).

    Rotations must be orthonormal within :data:`ROTATION_TOLERANCE` with determinant > 0;
    they are converted to unit quaternions (``[w, x, y, z]``).

    Returns:
        a :class:`~msf_torch.types.Trajectory` with B = 1, float64.

    Raises:
        DataError: a line without 12 numbers, a non-finite entry, a 3x3 block that is not a
            rotation, a times file of another length, or times that do not increase (naming
            file and line).
    """
    table = _tables.read_table(path, delimiter=None, header="none", names=_COLUMNS)
    data = table.finite_floats(_COLUMNS, "poses")
    n = data.shape[0]
    if times_path is None:
        t = np.arange(n, dtype=np.float64)
    else:
        times = _tables.read_table(times_path, delimiter=None, header="none", names=["t"])
        t = times.finite_floats(["t"], "times")[:, 0]
        if t.shape[0] != n:
            raise DataError(times.path, f"{t.shape[0]} times for {n} poses in {table.path}")
        back = np.flatnonzero(~(t[1:] > t[:-1]))
        if back.size:
            i = int(back[0]) + 1
            raise DataError(
                times.path,
                f"time {float(t[i])!r} does not increase",
                line=int(times.lines[i]),
                field="t",
            )
    matrices = data.reshape(n, 3, 4)
    rotations = matrices[:, :, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        off = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(rotations)
    bad = np.flatnonzero(~(off <= ROTATION_TOLERANCE) | ~(det > 0))
    if bad.size:
        i = int(bad[0])
        raise DataError(
            table.path,
            f"pose {i}: the 3x3 block is not a rotation (max |R^T R - I| = {off[i]:.3g}, "
            f"det = {det[i]:.3g})",
            line=int(table.lines[i]),
        )
    quat = matrix_to_quat(torch.as_tensor(rotations))
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return Trajectory(
        t=torch.as_tensor(t)[None],
        position=torch.as_tensor(matrices[:, :, 3].copy())[None],
        quaternion=quat[None],
        mask=torch.ones(1, n, dtype=torch.bool),
    )
