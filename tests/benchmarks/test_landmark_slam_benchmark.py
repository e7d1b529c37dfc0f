"""``benchmarks/landmark_slam.py`` on ``example.graph`` (seconds): the four pipelines (ours and
GTSAM's LM from the file's start, our incremental start, GTSAM ISAM2 + LM) reach the same
optimum of load2D's problem, and the record says so. Skips without the ``gtsam`` wheel."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("gtsam")

from benchmarks import landmark_slam  # noqa: E402


def test_four_pipelines_agree_on_example_graph(capsys, one_torch_thread):
    assert landmark_slam.main(["--graph", "example.graph", "--chunk", "30"]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    inputs = record["inputs"]
    assert (inputs["poses"], inputs["landmarks"], inputs["sightings"]) == (95, 24, 422)
    assert inputs["initial_cost"][0] == pytest.approx(inputs["initial_cost"][1], rel=1e-12)
    finals = [
        record["ours"]["file_start"]["final_cost"],
        record["peer"]["file_start"]["final_cost"],
        record["ours"]["incremental"]["final_cost"],
        record["peer"]["incremental"]["final_cost"],
    ]
    assert max(finals) == pytest.approx(min(finals), rel=1e-9)
    assert record["reported"]["incremental_reaches_isam2_lm_cost"]
    assert record["accuracy"]["incremental_solution_diff"]["max_landmark_diff_m"] < 1e-6
    assert record["peer"]["incremental"]["isam2_cost"] >= finals[3]
