"""``msf simulate --magnetometer`` then ``msf run``: the summary counts the magnetometer's
readings and those left out as disturbed, against the simulator's anomaly labels."""

from __future__ import annotations

import json

import numpy as np

from msf_torch.cli import main
from msf_torch.io import load_sequence


def test_run_summary_counts_disturbed_readings(tmp_path, capsys):
    out = tmp_path / "sim"
    args = ["simulate", "--duration", "40", "--seed", "4", "--magnetometer"]
    assert (
        main([*args, "--magnetometer-anomalies", "3", "--gnss-outages", "0", "--out", str(out)])
        == 0
    )
    written = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert written["magnetometer_readings"] == 2001
    assert main(["run", str(out), "--out", str(tmp_path / "run"), "--no-plot", "--no-learned"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["magnetometer_readings"] == 2001
    seq = load_sequence(out)
    t = seq.magnetometer.t[0].numpy()
    labelled = np.zeros(t.size, dtype=bool)
    for start, end in seq.labels["magnetic_anomaly"][0].numpy():
        labelled |= (t >= start) & (t <= end)
    # about the labelled readings: up to half again more (anomaly fields under the label's
    # 5 % threshold still turn the field off the gyro's turn; the first readings)
    assert labelled.sum() > 100
    assert labelled.sum() * 0.9 <= summary["magnetometer_disturbed"] <= labelled.sum() * 1.5
    counts = summary["measurements"]["magnetometer"]
    assert counts["accepted"] >= 0.9 * counts["present"] > 0


def test_wrong_references_warn(tmp_path, capsys):
    """A field magnitude 20 % off leaves most readings out as disturbed, an inclination
    0.3 rad off has the filter reject most headings: each run warns, naming the key."""
    out = tmp_path / "sim"
    args = ["simulate", "--duration", "40", "--seed", "5", "--magnetometer", "--gnss-outages"]
    assert main([*args, "0", "--out", str(out)]) == 0
    capsys.readouterr()
    for key, value, hint in (
        ("magnetometer_field_uT", 48.0 * 1.2, "check magnetometer_field_uT"),
        ("magnetometer_inclination_rad", 1.05 - 0.3, "check magnetometer_declination_rad"),
    ):
        config = tmp_path / f"{key}.yaml"
        config.write_text(f"{key}: {value}\n")
        run = ["run", str(out), "--config", str(config), "--out", str(tmp_path / key)]
        assert main([*run, "--no-plot", "--no-learned"]) == 0
        assert hint in capsys.readouterr().err
    assert (
        main(["run", str(out), "--out", str(tmp_path / "plain"), "--no-plot", "--no-learned"]) == 0
    )
    assert "magnetometer" not in capsys.readouterr().err
