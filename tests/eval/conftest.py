"""Shared helpers for the eval tests: seeded synthetic runs, a tiny TUM writer/reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from msf_torch.types import Trajectory


def write_tum(path: Path, t: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray) -> Path:
    """Write ``t x y z qx qy qz qw`` lines with ``repr`` floats (exact round trip)."""
    rows = np.column_stack((t, xyz, quat_xyzw))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join(repr(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def read_tum_local(path: Path) -> Trajectory:
    """Read a TUM file into a B = 1 float64 Trajectory (test-local reader)."""
    mat = np.loadtxt(path, comments="#", ndmin=2)
    t = torch.from_numpy(mat[:, 0])[None]
    xyz = torch.from_numpy(mat[:, 1:4])[None]
    quat_wxyz = torch.from_numpy(mat[:, [7, 4, 5, 6]])[None]
    return Trajectory(t=t, position=xyz, quaternion=quat_wxyz, mask=torch.ones_like(t, dtype=bool))


def synthetic_run(seed: int, n_ref: int = 300, keep: float = 0.8, jitter: float = 0.004):
    """A smooth 3-D reference and a noisy, rotated, scaled, resampled estimate of it.

    Returns dict with numpy arrays: ref_t, ref_xyz, ref_q (xyzw), est_t, est_xyz, est_q.
    Estimate times are a random subset of reference times with +-``jitter`` s noise,
    plus a few stamps outside the reference range.
    """
    rng = np.random.default_rng(seed)
    t = 1.6e9 + 0.1 * np.arange(n_ref)
    yaw = np.cumsum(rng.normal(0.0, 0.05, n_ref))
    speed = 1.0 + 0.3 * np.sin(0.02 * np.arange(n_ref))
    step = np.stack((np.cos(yaw), np.sin(yaw), 0.05 * rng.normal(size=n_ref)), -1)
    xyz = np.cumsum(0.1 * speed[:, None] * step, 0)
    roll_pitch = 0.05 * rng.normal(size=(n_ref, 2))
    rot_ref = Rotation.from_euler("zyx", np.column_stack((yaw, roll_pitch)))
    idx = np.sort(rng.choice(n_ref, size=int(keep * n_ref), replace=False))
    est_t = t[idx] + rng.uniform(-jitter, jitter, idx.size)
    est_t = np.concatenate(([t[0] - 1.0], est_t, [t[-1] + 1.0]))  # unmatched stamps
    idx = np.concatenate(([idx[0]], idx, [idx[-1]]))
    # Estimate: drifted copy in a different frame with a different scale.
    drift = np.cumsum(rng.normal(0.0, 0.01, (idx.size, 3)), 0)
    g_rot = Rotation.from_rotvec(rng.normal(size=3))
    g_scale, g_trans = 0.8, rng.normal(size=3) * 5.0
    est_xyz = g_scale * g_rot.apply(xyz[idx] + drift) + g_trans
    noise = Rotation.from_rotvec(0.02 * rng.normal(size=(idx.size, 3)))
    est_rot = g_rot * rot_ref[idx] * noise
    return {
        "ref_t": t,
        "ref_xyz": xyz,
        "ref_q": rot_ref.as_quat(),
        "est_t": est_t,
        "est_xyz": est_xyz,
        "est_q": est_rot.as_quat(),
    }


@pytest.fixture
def tum_pair(tmp_path):
    """Factory: seed -> (estimate path, reference path) of a synthetic run."""

    def make(seed: int = 0, **kwargs) -> tuple[Path, Path]:
        run = synthetic_run(seed, **kwargs)
        est = write_tum(tmp_path / f"est_{seed}.tum", run["est_t"], run["est_xyz"], run["est_q"])
        ref = write_tum(tmp_path / f"ref_{seed}.tum", run["ref_t"], run["ref_xyz"], run["ref_q"])
        return est, ref

    return make


@pytest.fixture
def read_local():
    """The test-local TUM reader, path -> Trajectory (B = 1, float64)."""
    return read_tum_local


@pytest.fixture
def run_factory():
    """The synthetic run generator (see :func:`synthetic_run`)."""
    return synthetic_run
