"""PyPose as the third peer of ``benchmarks/windows.py`` (KITTI windows, IMU + GPS + prior).

A small run of the benchmark itself (4 windows of 5 keyframes, one repeat, PyPose on 2 of
them): PyPose's LM on the same Problem starts from our cost and reaches our final cost and
GTSAM's to 1e-6 relative; without PyPose the record says how to install it. Skips without
``gtsam`` (the drive ships with its wheel) or ``pypose`` (not in CI's extra).
"""

from __future__ import annotations

import json
from typing import Any

import pytest

pytest.importorskip("gtsam")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks import windows  # noqa: E402

ARGS = ["--windows", "4", "--size", "5", "--repeats", "1", "--threads", "1", "--no-theseus"]


def _record(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    assert windows.main(argv) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_pypose_reaches_our_final_cost_and_gtsams(capsys, one_torch_thread):
    pytest.importorskip("pypose")
    record = _record(capsys, [*ARGS, "--pypose-windows", "2"])
    block = record["pypose"]
    assert block["windows"] == 2
    assert block["window_indices"] == [0, 3]  # evenly spaced, both ends
    assert block["initial_cost_rel_diff_vs_ours"]["max"] <= 1e-10  # the same problem
    assert block["hit_max_iterations"] == 0
    assert block["final_cost_rel_diff_vs_ours"]["max"] <= 1e-6
    assert block["final_cost_rel_diff"]["max"] <= 1e-6  # vs GTSAM
    expected = record["ours"]["windows_per_s"] / block["windows_per_s"]
    assert record["ratio_vs_pypose"] == pytest.approx(expected, rel=1e-4)  # JSON rounding


def _one_window(start: int, size: int) -> Any:
    """Our Problem (B = 1) for the KITTI window of ``size`` keyframes from fix ``start``."""
    from msf_torch.backend.preintegration import ImuIntervals, preintegrate_imu_tangent
    from msf_torch.io import load_sequence

    seq = load_sequence("kitti-gtsam")
    meta = seq.meta["imu_noise"]
    gps_t = seq.gnss.t[0].numpy()
    states, _ = windows.eskf_states(seq, gps_t)
    intervals = windows.gps_intervals(
        seq.imu.t[0].numpy(), seq.imu.accel[0].numpy(), seq.imu.gyro[0].numpy(), gps_t
    )
    gyro, accel, dt = (torch.as_tensor(intervals[k]) for k in ("gyro", "acc", "dt"))
    zeros = torch.zeros(gps_t.size - 1, 3, dtype=torch.float64)
    pre = preintegrate_imu_tangent(
        ImuIntervals(gyro, accel, dt), zeros, zeros, float(meta["integration_sigma"])
    )
    cpu = torch.device("cpu")
    noise = windows._noise(meta, cpu)
    position = seq.gnss.position[0].numpy()
    return windows.build_ours(states, position, np.array([start]), size, pre, noise, cpu)


def test_pypose_jacobian_follows_its_own_update(one_torch_thread):
    """The Jacobian PyPose's LM takes (``modjac``) equals central differences of the
    residuals under PyPose's own parameter update (``add_``: its SE3 retraction), so its LM
    solves our problem and not a mis-linearised one (reading the SE3 storage directly gave
    Jacobians by the quaternion's components, off by 7e4 on the rotation columns)."""
    pytest.importorskip("pypose")
    import copy

    from pypose.optim.functional import modjac

    from benchmarks.peers.pypose_windows import window_module

    module = window_module(_one_window(37, 5))
    jacobian = modjac(module, input=(None,), flatten=True)  # (R, 5 x 7 + 5 x 9)
    poses = 5 * 7
    assert torch.count_nonzero(jacobian[:, 6:poses:7]) == 0  # SE3's 7th storage column
    step = 1e-6
    for column in (0, 3, 5, 7 + 4, poses + 2, poses + 9 + 7):
        moved = []
        for sign in (1.0, -1.0):
            copy_ = copy.deepcopy(module)
            with torch.no_grad():
                if column < poses:
                    delta = torch.zeros(5, 7, dtype=torch.float64)
                    delta[column // 7, column % 7] = sign * step
                    copy_.pose.add_(delta)
                else:
                    copy_.rest.view(-1)[column - poses] += sign * step
                moved.append(copy_())
        numeric = (moved[0] - moved[1]) / (2 * step)
        scale = numeric.abs().max().clamp_min(1.0)
        assert (jacobian[:, column] - numeric).abs().max() <= 1e-6 * scale, column


def test_without_pypose_the_record_says_so(capsys, monkeypatch, one_torch_thread):
    import builtins

    real_import = builtins.__import__

    def no_pypose(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "pypose" or name.startswith("pypose."):
            raise ImportError("No module named 'pypose'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pypose)
    record = _record(capsys, ARGS)
    assert record["pypose"] == {"skipped": "pypose not installed: pip install pypose"}
    assert record["ratio_vs_pypose"] is None
    assert record["target_met"]["final_cost"]
