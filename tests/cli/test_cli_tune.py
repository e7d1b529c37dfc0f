"""``msf tune``: a simulated run read with a config whose GNSS sigmas are 3x too small and
whose gyro noise is 10x too large; the tuned keys written as a config that ``msf run``
reads; the errors a user meets."""

from __future__ import annotations

import json

import pytest

from msf_torch.cli import main
from msf_torch.frontend.config import load_config
from msf_torch.io.native import write_native
from msf_torch.sim import SimConfig, simulate_run


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("tune") / "run.npz"
    write_native(simulate_run(SimConfig(duration_s=40.0), seed=5).sequence, path)
    return path


def test_tune_fixes_a_bad_start_and_writes_a_config(run_file, tmp_path, capsys):
    start = tmp_path / "start.yaml"
    start.write_text("gyro_noise_density: 1.0e-3\ngnss_sigma_scale: 0.3\nmax_epoch_s: 0.5\n")
    out = tmp_path / "tuned.yaml"
    args = [
        str(run_file),
        "--config",
        str(start),
        "--params",
        "gyro_noise_density,gnss_sigma_scale",
    ]
    code = main(["tune", *args, "--piece-s", "20", "--max-evaluations", "6", "--out", str(out)])
    captured = capsys.readouterr()
    summary = _last_json(captured.out)
    assert code == 0
    assert summary["pieces"] == 2 and summary["evaluations"] <= 6
    cut_off = "stopped at --max-evaluations 6 while still improving" in captured.err
    assert cut_off == (not summary["converged"])
    assert summary["nll_per_measurement_final"] < summary["nll_per_measurement_initial"]
    # the simulated receiver's noise is its declared sigma (scale 1), the gyro's ~1e-4
    assert 0.6 < summary["parameters"]["gnss_sigma_scale"]["tuned"] < 1.5
    assert summary["parameters"]["gyro_noise_density"]["ratio"] < 0.5
    before, after = summary["mean_nis"]["gnss"]
    assert abs(after - 3.0) < abs(before - 3.0)
    tuned = load_config(out)  # a valid front-end config: the start's keys, the tuned values
    assert tuned.max_epoch_s == 0.5
    assert tuned.gnss_sigma_scale == pytest.approx(
        summary["parameters"]["gnss_sigma_scale"]["tuned"]
    )
    assert "maximum likelihood" in out.read_text().splitlines()[0]
    assert (
        main(
            ["run", str(run_file), "--config", str(out), "--out", str(tmp_path / "o"), "--no-plot"]
        )
        == 0
    )


def test_tune_errors_name_the_parameter(run_file, capsys):
    assert main(["tune", str(run_file), "--params", "gyro_noise", "--max-evaluations", "1"]) == 2
    err = capsys.readouterr().err
    assert "'gyro_noise' is not a tunable parameter" in err and "gyro_noise_density" in err
    assert main(["tune", str(run_file), "--params", "pose:vo", "--max-evaluations", "1"]) == 2
    assert "'pose:vo' is not a pose source the filter fuses here (fused: none)" in (
        capsys.readouterr().err
    )
    assert main(["tune", str(run_file), "--params", "nhc_sigma_mps", "--max-evaluations", "1"]) == 2
    assert "'nhc_sigma_mps' needs nhc measurements" in capsys.readouterr().err  # wheels: no NHC
    assert main(["tune", str(run_file), "--burn-in-s", "40", "--max-evaluations", "1"]) == 2
    assert "burn_in_s must lie in [0, piece_s)" in capsys.readouterr().err


def test_msf_run_reports_the_innovations_and_warns_of_an_overconfident_sensor(
    run_file, tmp_path, capsys
):
    bad = tmp_path / "bad.yaml"
    bad.write_text("gnss_sigma_scale: 0.3\n")
    assert main(["run", str(run_file), "--out", str(tmp_path / "a"), "--no-plot"]) == 0
    captured = capsys.readouterr()
    good = _last_json(captured.out)["innovations"]
    assert 0.5 < good["gnss"]["ratio"] < 1.5 and good["gnss"]["rows"] == 3
    assert "innovations are" not in captured.err
    code = main(
        ["run", str(run_file), "--config", str(bad), "--out", str(tmp_path / "b"), "--no-plot"]
    )
    captured = capsys.readouterr()
    ratio = _last_json(captured.out)["innovations"]["gnss"]["ratio"]
    assert code == 0 and ratio > 3.0
    assert f"the gnss innovations are {ratio:.1f}x the spread the filter models" in captured.err
    assert "msf tune" in captured.err
