"""``benchmarks/gnss_heading.py`` on two short simulated runs (a few seconds): the JSON
line's keys and finite figures, and the check that headings on and off simulate the same
run. Skips without the ``gtsam`` wheel."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

pytest.importorskip("gtsam")

from benchmarks import gnss_heading  # noqa: E402
from msf_torch.sim import SimConfig, simulate_run  # noqa: E402

SHORT = ["--duration-s", "45", "--outage-after-s", "22", "--outage-s", "10"]
COLUMNS = (*gnss_heading.OURS, *gnss_heading.PEERS)


def test_smoke_run_json_line(capsys, one_torch_thread):
    assert gnss_heading.main(["--seeds", "2", *SHORT]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["benchmark"] == "gnss_heading"
    for key in ("inputs", "ours", "peer", "columns", "ratio", "accuracy", "runs", "machine"):
        assert key in record
    assert record["inputs"]["seeds"] == [100, 101] and record["inputs"]["gnss_velocity"] is False
    assert set(record["columns"]) == set(COLUMNS) == set(record["accuracy"])
    for name in COLUMNS:
        figures = record["columns"][name]
        for key in (*gnss_heading.ALL_METRICS, "wall_s"):
            assert math.isfinite(figures[key]) and figures[key] > 0.0, (name, key)
    for name in (*gnss_heading.SMOOTHED, *gnss_heading.PEERS):
        smoothed = record["columns"][name]["smoothed"]
        assert set(gnss_heading.ALL_METRICS) <= set(smoothed)
        assert all(math.isfinite(smoothed[k]) for k in gnss_heading.ALL_METRICS)
    for name, value in record["ratio"].items():
        assert math.isfinite(value) and value > 0.0, name
    assert record["ratio"]["wall_ours_over_peer"] == pytest.approx(
        record["ours"]["wall_s"] / record["peer"]["wall_s"], rel=1e-5
    )
    for row in record["runs"]:
        start, end = row["outage_s"]
        assert 22.0 <= start and end - start == pytest.approx(10.0) and end <= 45.0
        assert set(COLUMNS) <= set(row)
        # the headings hold the yaw: within 0.5 deg RMS for ours and the peer (0.15-0.26)
        assert row["ours"]["yaw_rmse_deg"] < 0.5 and row["peer"]["yaw_rmse_deg"] < 0.5


def test_same_run_check():
    config = SimConfig(duration_s=20.0, gnss_heading=True, gnss_velocity=True)
    with_heading = simulate_run(config, seed=5).sequence
    without = simulate_run(dataclasses.replace(config, gnss_heading=False), seed=5).sequence
    gnss_heading.check_same_run(with_heading, without)  # the simulator keeps them equal
    moved = dataclasses.replace(
        without, gnss=without.gnss.map(lambda x: x + 1e-12 if x.is_floating_point() else x)
    )
    with pytest.raises(RuntimeError, match="gnss"):
        gnss_heading.check_same_run(with_heading, moved)
    with pytest.raises(RuntimeError, match="heading stream"):
        gnss_heading.check_same_run(with_heading, with_heading)
    relabelled = dataclasses.replace(
        without, labels={**without.labels, "slip": torch.zeros(1, 1, 2, dtype=torch.float64)}
    )
    with pytest.raises(RuntimeError, match="labels"):
        gnss_heading.check_same_run(with_heading, relabelled)
