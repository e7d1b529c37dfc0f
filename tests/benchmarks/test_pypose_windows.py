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

from benchmarks import windows  # noqa: E402

ARGS = ["--windows", "4", "--size", "5", "--repeats", "1", "--threads", "1", "--no-theseus"]


def _record(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    assert windows.main(argv) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_pypose_reaches_our_final_cost_and_gtsams(capsys, one_torch_thread):
    pytest.importorskip("pypose")
    record = _record(capsys, [*ARGS, "--pypose-windows", "2"])
    block = record["pypose"]
    assert block["windows"] == [0, 3]  # evenly spaced, both ends
    assert block["initial_cost_rel_diff_vs_ours"]["max"] <= 1e-12  # the same problem
    assert block["hit_max_iterations"] == 0
    assert block["final_cost_rel_diff_vs_ours"]["max"] <= 1e-6
    assert block["final_cost_rel_diff"]["max"] <= 1e-6  # vs GTSAM
    expected = record["ours"]["windows_per_s"] / block["windows_per_s"]
    assert record["ratio_vs_pypose"] == pytest.approx(expected, rel=1e-4)  # JSON rounding


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
