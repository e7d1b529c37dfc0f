"""``benchmarks/posegraph2d.py`` on the small graphs (``--graph w100.graph --quick``, a few
seconds): every file reads to GTSAM's load2D initial cost, and ours reaches GTSAM's final
cost and solution. Skips without the ``gtsam`` wheel (its Data folder holds the graphs)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("gtsam")

from benchmarks import posegraph2d  # noqa: E402


def test_small_graphs_match_gtsam(capsys, one_torch_thread):
    assert posegraph2d.main(["--graph", "w100.graph", "--quick"]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["inputs"]["poses"] == 100 and record["inputs"]["edges"] == 300
    assert record["readers_agree"]
    names = {s["graph"] for s in record["small_graphs"]}
    assert "w10000.graph" not in names and "pose2example.txt" in names
    assert "victoria_park.txt" not in names  # a main graph only (seconds per solve)
    example = next(s for s in record["small_graphs"] if s["graph"] == "example.graph")
    assert (example["landmarks"], example["sightings"]) == (24, 422)
    assert example["solution_diff"]["max_landmark_diff_m"] <= 1e-6
    assert record["targets"]["cost"]["met"]
    for run in [record["accuracy"]["tight"], *record["small_graphs"]]:
        assert run["final_cost_rel_diff"] <= 1e-6
        assert run["solution_diff"]["max_position_diff_m"] <= 1e-6
        assert run["solution_diff"]["max_heading_diff_rad"] <= 1e-6
    assert record["peer"]["tight"]["prior_cost"] == 0.0
