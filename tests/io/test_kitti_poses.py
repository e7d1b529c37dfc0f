"""KITTI pose files: written poses read back by evo's reader and by ours, exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.io import DataError, read_kitti_poses, write_kitti_poses
from msf_torch.types import Trajectory


def _trajectory(n: int = 25, seed: int = 0) -> Trajectory:
    gen = torch.Generator().manual_seed(seed)
    rot = so3.exp(torch.randn(n, 3, generator=gen, dtype=torch.float64) * 2.0)
    return Trajectory(
        t=(100.0 + torch.arange(n, dtype=torch.float64) / 7.0)[None],
        position=torch.randn(1, n, 3, generator=gen, dtype=torch.float64) * 50,
        quaternion=matrix_to_quat(rot)[None],
        mask=torch.ones(1, n, dtype=torch.bool),
    )


def test_kitti_poses_read_back_by_evo_and_ours(tmp_path: Path) -> None:
    from evo.tools import file_interface

    traj = _trajectory()
    path = write_kitti_poses(traj, tmp_path / "poses.txt", tmp_path / "times.txt")
    lines = path.read_text().splitlines()
    assert len(lines) == 25 and all(len(line.split()) == 12 for line in lines)
    rot = quat_to_matrix(traj.quaternion[0]).numpy()
    first = np.array(lines[0].split(), dtype=np.float64).reshape(3, 4)
    assert np.array_equal(first[:, :3], rot[0]) and np.array_equal(first[:, 3], traj.position[0, 0])
    evo_traj = file_interface.read_kitti_poses_file(str(path))
    want = np.tile(np.eye(4), (25, 1, 1))
    want[:, :3, :3], want[:, :3, 3] = rot, traj.position[0].numpy()
    np.testing.assert_array_equal(np.stack(evo_traj.poses_se3), want)
    back = read_kitti_poses(path, tmp_path / "times.txt")
    assert torch.equal(back.t, traj.t) and torch.equal(back.position, traj.position)
    torch.testing.assert_close(back.quaternion, traj.quaternion, rtol=0, atol=1e-15)
    no_times = read_kitti_poses(path)
    assert torch.equal(no_times.t[0], torch.arange(25, dtype=torch.float64))


def test_kitti_errors(tmp_path: Path) -> None:
    path = write_kitti_poses(_trajectory(3), tmp_path / "poses.txt")
    (tmp_path / "times.txt").write_text("0.0\n1.0\n")
    with pytest.raises(DataError, match="2 times for 3 poses"):
        read_kitti_poses(path, tmp_path / "times.txt")
    (tmp_path / "times.txt").write_text("0.0\n1.0\n1.0\n")
    with pytest.raises(DataError, match="does not increase") as caught:
        read_kitti_poses(path, tmp_path / "times.txt")
    assert caught.value.line == 3
    (tmp_path / "bad.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DataError):
        read_kitti_poses(tmp_path / "bad.txt")
    broken = _trajectory(3)
    broken.position[0, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="pose 1"):
        write_kitti_poses(broken, tmp_path / "x.txt")
