"""Theseus as the second peer of ``benchmarks/windows.py`` (KITTI windows, IMU + GPS + prior).

Small runs of the benchmark itself (4 windows of 5 keyframes, one repeat): Theseus's LM on
the same Problem reaches our final cost and GTSAM's to 1e-6 relative; without Theseus the
record says how to install it. The drive ships with the ``gtsam`` wheel, which the benchmark
imports, so both skip without it; the first also needs ``theseus`` (not in CI).
"""

from __future__ import annotations

import json
from typing import Any

import pytest

pytest.importorskip("gtsam")

from benchmarks import windows  # noqa: E402
from benchmarks.peers.theseus_windows import INSTALL  # noqa: E402

ARGS = [
    "--windows",
    "4",
    "--size",
    "5",
    "--repeats",
    "1",
    "--threads",
    "1",
    "--pypose-windows",
    "0",
]


def _record(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    assert windows.main(argv) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_theseus_reaches_our_final_cost_and_gtsams(capsys, one_torch_thread):
    pytest.importorskip("theseus")
    record = _record(capsys, ARGS)
    block = record["theseus"]
    assert block["cost_functions"] == 1 + 5 + 4  # prior, GPS per keyframe, IMU per interval
    assert block["status"] == {"CONVERGED": 4}
    assert block["initial_cost_rel_diff_vs_ours"]["max"] <= 1e-12  # the same problem
    assert block["final_cost_rel_diff_vs_ours"]["max"] <= 1e-6
    assert block["final_cost_rel_diff"]["max"] <= 1e-6  # vs GTSAM
    expected = block["solve_s"] / record["ours"]["solve_s"]
    assert record["ratio_vs_theseus"] == pytest.approx(expected, rel=1e-4)
    assert record["accuracy"]["final_cost_rel_diff"]["max"] <= 1e-6  # ours vs GTSAM, as before


def test_without_theseus_the_record_says_how_to_install_it(capsys, monkeypatch, one_torch_thread):
    def missing() -> None:
        raise ImportError("No module named 'theseus'")

    monkeypatch.setattr(windows, "import_theseus", missing)
    record = _record(capsys, ARGS)
    assert record["theseus"] == {"skipped": f"theseus-ai not installed: {INSTALL}"}
    assert record["ratio_vs_theseus"] is None
    assert record["target_met"]["final_cost"]
