"""``msf run A B ...``: several sequences in one batched front-end run, each written as a
single run would be, plus ``runs.csv`` and a batch summary."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.io.native import write_native
from msf_torch.io.tum import read_tum
from msf_torch.sim import SimConfig, simulate_run


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch")
    paths = []
    for seed, duration in ((3, 30.0), (5, 24.0)):  # different lengths: padded in the batch
        config = SimConfig(duration_s=duration, slip_episodes=1, slip_margin_s=(8.0, 5.0))
        paths.append(write_native(simulate_run(config, seed).sequence, folder / f"r{seed}.npz"))
    return paths


def _last_json(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_batch_writes_each_sequence_as_a_single_run_would(runs, tmp_path, capsys):
    outage = ["--gnss-outage", "8:16"]
    batch_dir = tmp_path / "batch"
    args = ["run", *map(str, runs), str(runs[0]), "--out", str(batch_dir), "--no-plot"]
    assert main([*args, "--progress", "off", *outage]) == 0
    batch = _last_json(capsys)
    assert batch["sequences"] == 3
    assert batch["names"] == ["r3", "r5", "r3-2"]  # repeated names made unique
    assert batch["imu_samples"] == 6001 + 4801 + 6001
    assert batch["realtime_factor"] == pytest.approx(84.0 / batch["wall_s"], rel=1e-2)
    assert json.loads((batch_dir / "summary.json").read_text()) == batch
    with open(batch_dir / "runs.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["sequence"] for row in rows] == ["r3", "r5", "r3"]
    for index, (path, name) in enumerate(zip([*runs, runs[0]], batch["names"], strict=True)):
        single_dir = tmp_path / f"single{index}"
        single_args = ["run", str(path), "--out", str(single_dir), "--no-plot", *outage]
        assert main([*single_args, "--progress", "off"]) == 0
        single = _last_json(capsys)
        own = json.loads((batch_dir / name / "summary.json").read_text())
        assert own["batch"] == {"size": 3, "index": index}
        for key in ("epochs", "imu_samples", "ate_rmse_m", "outage_drift_pct", "measurements"):
            assert own[key] == single[key], key
        assert float(rows[index]["ate_rmse_m"]) == single["ate_rmse_m"]
        assert float(rows[index]["slip_f1"]) == single["slip_detection"]["f1"]
        got, want = (
            read_tum(batch_dir / name / "trajectory.tum"),
            read_tum(single_dir / "trajectory.tum"),
        )
        assert got.length == want.length == single["epochs"]
        np.testing.assert_allclose(got.position.numpy(), want.position.numpy(), rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.quaternion.numpy(), want.quaternion.numpy(), atol=1e-9)
        diagnostics = (batch_dir / name / "diagnostics.csv").read_text().splitlines()
        assert len(diagnostics) == 1 + single["epochs"]  # padding epochs are not written


def test_batch_refuses_an_outage_outside_a_sequence(runs, tmp_path, capsys):
    args = ["run", *map(str, runs), "--out", str(tmp_path), "--no-plot", "--progress", "off"]
    assert main([*args, "--gnss-outage", "27:29"]) == 2
    assert "sequence r5: the outage window" in capsys.readouterr().err


def test_batch_smooths_each_sequence_as_a_single_run_would(runs, tmp_path, capsys):
    common = ["--no-plot", "--progress", "off", "--smooth", "full"]
    batch_dir = tmp_path / "batch"
    assert main(["run", *map(str, runs), "--out", str(batch_dir), *common]) == 0
    batch = _last_json(capsys)
    assert batch["smoother_wall_s"] > 0
    with open(batch_dir / "runs.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    for index, (path, name) in enumerate(zip(runs, batch["names"], strict=True)):
        single_dir = tmp_path / f"single{index}"
        assert main(["run", str(path), "--out", str(single_dir), *common]) == 0
        single = _last_json(capsys)
        own = json.loads((batch_dir / name / "summary.json").read_text())
        assert own["smoother"]["keyframes"] == single["smoother"]["keyframes"]
        assert own["smoother"]["converged"] and own["frontend_wall_s"] == batch["wall_s"]
        for key in ("ate_rmse_m", "frontend_ate_rmse_m"):
            assert own[key] == pytest.approx(single[key], abs=2e-4), key
            assert float(rows[index][key]) == own[key]
        got = read_tum(batch_dir / name / "trajectory.tum")
        want = read_tum(single_dir / "trajectory.tum")
        assert got.length == want.length
        np.testing.assert_allclose(got.position.numpy(), want.position.numpy(), rtol=0, atol=1e-6)


def test_batch_needs_one_config(runs, tmp_path, capsys):
    run = simulate_run(SimConfig(duration_s=20.0), 8)
    sequence = run.sequence
    meta = dict(sequence.meta)
    meta["sensor"] = {**meta.get("sensor", {}), "wheel_track_m": 0.61}  # another robot
    other = write_native(dataclasses.replace(sequence, meta=meta), tmp_path / "robot2.npz")
    args = ["run", str(runs[0]), str(other), "--out", str(tmp_path / "out"), "--no-plot"]
    assert main([*args, "--progress", "off"]) == 2
    err = capsys.readouterr().err
    assert "differs from" in err and "wheel_track_m" in err and "robot2.npz" in err
    pinned = tmp_path / "pinned.yaml"  # a key the config sets is not taken from metadata
    pinned.write_text("wheel_track_m: 0.5\n")
    assert main([*args, "--progress", "off", "--config", str(pinned)]) == 0
    assert _last_json(capsys)["sequences"] == 2
