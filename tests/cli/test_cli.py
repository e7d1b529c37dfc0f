"""End-to-end checks of the ``msf`` command line on small simulated runs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.io.native import write_native
from msf_torch.io.tum import read_tum, write_tum
from msf_torch.sim import SimConfig, simulate_run


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    run = simulate_run(SimConfig(duration_s=30.0, slip_episodes=1, slip_margin_s=(8.0, 5.0)), 3)
    path = write_native(run.sequence, folder / "run.npz")
    return run, path


def _last_json(capsys):
    out = capsys.readouterr().out.strip().splitlines()
    return json.loads(out[-1])


def test_run_writes_outputs_and_prints_summary(short_run, tmp_path, capsys):
    _, path = short_run
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--progress", "off"]) == 0
    summary = _last_json(capsys)
    for key in ("sequence", "duration_s", "imu_samples", "wall_s", "realtime_factor", "ate_rmse_m"):
        assert key in summary
    assert summary["device"] == "cpu"  # the default of --device
    assert summary["imu_samples"] == 6001
    assert summary["ate_rmse_m"] < 2.0
    for name in ("trajectory.tum", "diagnostics.csv", "summary.json", "overview.png"):
        assert (out / name).stat().st_size > 0
    assert not list(out.glob("*.tmp*"))
    traj = read_tum(out / "trajectory.tum")
    assert traj.length == summary["epochs"]
    header = (out / "diagnostics.csv").read_text().splitlines()[0].split(",")
    assert header[:2] == ["t", "var_px"] and "slip_factor" in header and "gnss_nis" in header
    assert json.loads((out / "summary.json").read_text()) == summary


def test_gnss_outage_is_scored_against_withheld_fixes(short_run, tmp_path, capsys):
    _, path = short_run
    args = ["run", str(path), "--out", str(tmp_path), "--gnss-outage", "10:20", "--no-plot"]
    assert main(args) == 0
    summary = _last_json(capsys)
    assert summary["outage_distance_m"] > 5.0
    assert summary["outage_drift_pct"] == pytest.approx(
        100 * summary["outage_max_error_m"] / summary["outage_distance_m"], rel=1e-3
    )
    assert summary["measurements"]["gnss"]["present"] < 30


def test_eval_matches_library_ate(short_run, tmp_path, capsys):
    run, _ = short_run
    ref = tmp_path / "ref.tum"
    write_tum(run.sequence.ground_truth, ref)
    est = tmp_path / "est.tum"
    shifted = run.sequence.ground_truth.map(lambda x: x)
    shifted.position = shifted.position + 0.5
    write_tum(shifted, est)
    assert main(["eval", str(est), str(ref), "--align", "none"]) == 0
    result = _last_json(capsys)
    assert result["ate"]["rmse"] == pytest.approx(np.sqrt(3 * 0.25), rel=1e-9)
    assert main(["eval", str(est), str(ref), "--align", "se3"]) == 0
    assert _last_json(capsys)["ate"]["rmse"] < 1e-9
    lines = est.read_text().splitlines()
    header, first, second = lines[:3]
    est.write_text("\n".join([header, second, first, *lines[3:]]) + "\n")  # two poses swapped
    assert main(["eval", str(est), str(ref), "--align", "none"]) == 2
    assert "--sort for msf run and msf eval" in capsys.readouterr().err
    assert main(["eval", str(est), str(ref), "--align", "none", "--sort"]) == 0
    assert _last_json(capsys)["ate"]["rmse"] == pytest.approx(np.sqrt(3 * 0.25), rel=1e-9)


def test_simulate_is_deterministic(tmp_path, capsys):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    for path in (a, b):
        assert (
            main(
                [
                    "simulate",
                    "--duration",
                    "10",
                    "--seed",
                    "4",
                    "--slip-episodes",
                    "0",
                    "--gnss-outages",
                    "0",
                    "--out",
                    str(path),
                ]
            )
            == 0
        )
    first, second = np.load(a), np.load(b)
    assert all(np.array_equal(first[k], second[k]) for k in first.files)
    assert _last_json(capsys)["imu_samples"] == 2001


def test_bad_input_names_file_line_and_field(tmp_path, capsys):
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0.0,0,0,0,0,0,9.8\n0.01,0,0,zero,0,0,9.8\n"
    )
    assert main(["run", str(folder), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "imu.csv:3" in err and "gyro_z" in err


def test_backwards_time_needs_sort(tmp_path, capsys):
    folder = tmp_path / "unsorted"
    folder.mkdir()
    rows = [f"{t:.2f},0,0,0,0,0,9.80665" for t in np.arange(0, 3, 0.01)]
    rows[100], rows[101] = rows[101], rows[100]
    (folder / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + "\n".join(rows) + "\n"
    )
    assert main(["run", str(folder), "--out", str(tmp_path / "o"), "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert "imu.csv:" in err and "--sort for msf run" in err  # names the option it has
    assert main(["run", str(folder), "--out", str(tmp_path / "o"), "--no-plot", "--sort"]) == 0


def test_version_matches_the_installed_distribution(capsys):
    """``msf --version`` names the version pip installed (package metadata, read
    independently of the code) and the torch it runs on."""
    import importlib.metadata

    import torch

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"msf {importlib.metadata.version('msf_torch')} ("), line
    assert f"torch {torch.__version__}" in line


@pytest.mark.parametrize(
    ("device", "message"),
    [
        ("mps", "expected cpu, cuda or cuda:N, got 'mps'"),
        ("gpu0", "expected cpu, cuda or cuda:N, got 'gpu0'"),
        ("cuda:64", "cuda:64: "),
    ],
)
def test_run_device_is_checked_before_any_work(tmp_path, capsys, device, message):
    """``msf run --device``: a device torch cannot use here stops the command at once, with
    the reason (no CUDA in this torch, or no such CUDA device)."""
    with pytest.raises(SystemExit) as stop:
        main(["run", "--device", device, "--out", str(tmp_path / "o")])
    assert stop.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_simulate_too_short_for_its_slip_episodes_says_what_to_change(tmp_path, capsys):
    out = str(tmp_path / "s.npz")
    assert main(["simulate", "--duration", "5", "--out", out]) == 2
    err = capsys.readouterr().err
    assert "3 slip episodes" in err and "use fewer slip episodes or a longer duration_s" in err
    assert main(["simulate", "--duration", "5", "--slip-episodes", "0", "--out", out]) == 2
    assert "use fewer GNSS outages or a longer duration_s" in capsys.readouterr().err
    args = ["simulate", "--duration", "5", "--slip-episodes", "0", "--gnss-outages", "0"]
    assert main([*args, "--out", out]) == 0


def test_diagnostics_has_each_pose_source_per_epoch(tmp_path, capsys):
    # a VO + LiDAR weather run: present / accepted / NIS per pose source, per epoch, add
    # up to the summary's counts (there were no pose:<name> columns, only the summary's)
    path, out = tmp_path / "w.npz", tmp_path / "out"
    args = ["simulate", "--duration", "10", "--seed", "2", "--weather", "--gnss-outages", "0"]
    assert main([*args, "--slip-episodes", "0", "--out", str(path)]) == 0
    assert main(["run", str(path), "--out", str(out), "--no-plot", "--no-learned"]) == 0
    counts = _last_json(capsys)["measurements"]
    table = np.genfromtxt(out / "diagnostics.csv", delimiter=",", names=True, deletechars="")
    for name in ("pose:vo", "pose:lidar"):
        assert counts[name]["present"] > 50
        assert table[f"{name}_present"].sum() == counts[name]["present"]
        assert table[f"{name}_accepted"].sum() == counts[name]["accepted"]
        nis = table[f"{name}_nis"][table[f"{name}_accepted"] == 1]
        assert np.isfinite(nis).all() and 0.0 < np.median(nis) < 20.0


def test_simulated_gnss_velocities_are_written_and_fused(tmp_path, capsys):
    path, out = tmp_path / "v", tmp_path / "out"
    args = ["simulate", "--duration", "12", "--seed", "3", "--gnss-velocity"]
    assert main([*args, "--gnss-outages", "0", "--slip-episodes", "0", "--out", str(path)]) == 0
    assert _last_json(capsys)["gnss_velocities"] == 13
    header = (path / "gnss_velocity.csv").read_text().splitlines()[0]
    assert header == "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz"
    assert main(["run", str(path), "--out", str(out), "--no-plot", "--no-learned"]) == 0
    counts = _last_json(capsys)["measurements"]["gnss_velocity"]
    assert counts["present"] == 12 and counts["accepted"] == 12  # t = 0 is the start


def test_simulated_gnss_headings_are_written_and_fused(tmp_path, capsys):
    path, out = tmp_path / "h", tmp_path / "out"
    args = ["simulate", "--duration", "12", "--seed", "3", "--gnss-heading"]
    assert main([*args, "--gnss-outages", "0", "--slip-episodes", "0", "--out", str(path)]) == 0
    assert _last_json(capsys)["gnss_headings"] == 13
    header = (path / "gnss_heading.csv").read_text().splitlines()[0]
    assert header == "t,heading,sigma_heading"
    assert main(["run", str(path), "--out", str(out), "--no-plot", "--no-learned"]) == 0
    counts = _last_json(capsys)["measurements"]["gnss_heading"]
    assert counts["present"] == 12 and counts["accepted"] == 12  # t = 0 sets the start


def test_diagnostics_of_a_run_without_pose_sources_has_no_source_columns(short_run, tmp_path):
    _, path = short_run
    assert main(["run", str(path), "--out", str(tmp_path), "--no-plot", "--no-learned"]) == 0
    header = (tmp_path / "diagnostics.csv").read_text().splitlines()[0].split(",")
    assert not [column for column in header if column.startswith("pose:")]
