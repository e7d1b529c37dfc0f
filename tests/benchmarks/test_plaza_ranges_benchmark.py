"""``benchmarks/plaza_ranges.py`` once (``--repeats 1``, a few seconds): settings from
Plaza1, Plaza2 solved by ours and GTSAM on the same graph. Skips without the ``gtsam`` wheel
(its Data folder holds the runs)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("gtsam")

from benchmarks import plaza_ranges  # noqa: E402


def test_plaza2_matches_gtsam_and_beats_dead_reckoning(capsys, tmp_path, one_torch_thread):
    figure = tmp_path / "plaza2.png"
    assert plaza_ranges.main(["--repeats", "1", "--plot", str(figure)]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    inputs = record["inputs"]
    assert (inputs["test_run"], inputs["calibration_run"]) == ("Plaza2", "Plaza1")
    assert (inputs["odometry_steps"], inputs["ranges"], inputs["beacons"]) == (4090, 1816, 4)
    assert 2.5 < inputs["calibration"]["range_bias_m"] < 3.2  # Plaza1's ranges read long
    assert record["ours"]["status"] == "converged"
    assert record["accuracy"]["initial_cost_rel_diff"] < 1e-12
    assert record["accuracy"]["final_cost_rel_diff"] < 1e-9
    assert record["accuracy"]["max_position_diff_m"] < 1e-5
    assert record["ours"]["error"]["rmse_m"] < 0.6
    assert record["dead_reckoning"]["error"]["rmse_m"] > 25.0
    assert record["ratio"] > 0
    slam = record["slam"]  # beacons unknown: the same optimum as GTSAM, a rigid turn off
    assert slam["accuracy"]["final_cost_rel_diff"] < 1e-8
    assert slam["ours"]["aligned_error"]["rmse_m"] < 0.6
    assert max(slam["beacons"]["aligned_error_m"]) < 1.5
    assert max(slam["beacons"]["error_m"]) < max(slam["beacons"]["initial_error_m"])
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_calibrating_on_the_test_run_is_refused(capsys):
    with pytest.raises(SystemExit, match="other run"):
        plaza_ranges.main(["--test", "Plaza2", "--calibrate", "Plaza2"])
