"""``msf ranges``: odometry + anchor ranges from CSV files (a simulated run with known truth)
and the real Plaza2 run shipped with gtsam; the errors a user meets."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.io.tum import read_tum

ANCHORS = {3: (0.0, 0.0), 7: (30.0, 0.0), 11: (30.0, 20.0), 12: (0.0, 20.0)}
START = (4.0, 3.0, 0.6)


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def csv_run(tmp_path_factory):
    """A robot driving two laps of a rounded rectangle among four anchors: odometry poses in
    its own frame (0.5 % scale error, 1 mrad/m heading drift), ranges every 0.5 s with 5 cm
    noise and a few 5-m outliers, the truth in the anchors' frame."""
    folder = tmp_path_factory.mktemp("ranges")
    rng = np.random.default_rng(3)
    dt, speed = 0.1, 1.0
    t = np.arange(0.0, 160.0, dt)
    turn_rate = np.where((t % 40.0) < 30.0, 0.0, (math.pi / 2) / 10.0)
    heading = START[2] + np.concatenate(([0.0], np.cumsum(turn_rate[:-1] * dt)))
    x = START[0] + np.concatenate(([0.0], np.cumsum(speed * dt * np.cos(heading[:-1]))))
    y = START[1] + np.concatenate(([0.0], np.cumsum(speed * dt * np.sin(heading[:-1]))))
    odo_heading = np.concatenate(([0.0], np.cumsum((turn_rate[:-1] + 1e-3 * speed) * dt)))
    step = 1.005 * speed * dt
    odo_x = np.concatenate(([0.0], np.cumsum(step * np.cos(odo_heading[:-1]))))
    odo_y = np.concatenate(([0.0], np.cumsum(step * np.sin(odo_heading[:-1]))))
    with open(folder / "odometry.csv", "w") as f:
        f.write("t,x,y,heading\n")
        for row in zip(t, odo_x, odo_y, odo_heading, strict=True):
            f.write(",".join(map(repr, map(float, row))) + "\n")
    with open(folder / "truth.csv", "w") as f:
        f.write("t,x,y\n")
        for row in zip(t, x, y, strict=True):
            f.write(",".join(map(repr, map(float, row))) + "\n")
    with open(folder / "anchors.csv", "w") as f:
        f.write("anchor,x,y\n")
        for anchor, (ax, ay) in ANCHORS.items():
            f.write(f"{anchor},{ax},{ay}\n")
    with open(folder / "ranges.csv", "w") as f:
        f.write("# UWB log\nt,anchor,range\n")
        ids = list(ANCHORS)
        for k, time in enumerate(t[5::5]):
            index = 5 + 5 * k
            anchor = ids[k % 4]
            ax, ay = ANCHORS[anchor]
            true_range = math.hypot(ax - x[index], ay - y[index])
            noise = rng.normal(0.0, 0.05) + (5.0 if k % 97 == 13 else 0.0)
            f.write(f"{float(time)!r},{anchor},{float(true_range + noise)!r}\n")
    return folder


def _files(folder) -> list[str]:
    return [
        "--odometry",
        str(folder / "odometry.csv"),
        "--ranges",
        str(folder / "ranges.csv"),
        "--anchors",
        str(folder / "anchors.csv"),
        "--truth",
        str(folder / "truth.csv"),
        "--range-sigma",
        "0.05",
    ]


def test_csv_run_with_the_start_searched(csv_run, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["ranges", *_files(csv_run), "--out", str(out), "--plot", str(out / "r.png")]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["start_searched"] and summary["status"] == "converged"
    assert abs(summary["start"][0] - START[0]) < 0.5 and abs(summary["start"][1] - START[1]) < 0.5
    assert abs(math.remainder(summary["start"][2] - START[2], 2 * math.pi)) < 0.15
    assert summary["truth_error"]["rmse_m"] < 0.1  # dead reckoning drifts metres
    trajectory = read_tum(out / "trajectory.tum")
    assert trajectory.position.shape[1] == summary["poses"] == 1600
    assert (out / "r.png").read_bytes()[:4] == b"\x89PNG"


def test_csv_run_with_the_start_given_and_anchors_solved(csv_run, tmp_path, capsys):
    start = ",".join(map(str, START))
    out = tmp_path / "slam"
    args = ["ranges", *_files(csv_run), "--start", start, "--solve-anchors", "--out", str(out)]
    assert main(args) == 0
    summary = _last_json(capsys.readouterr().out)
    assert not summary["start_searched"] and summary["settings"]["solve_anchors"]
    # the map's heading rests on the start prior alone (0.05 rad): looser than localisation
    assert summary["truth_error"]["rmse_m"] < 0.15
    solved = np.loadtxt(out / "anchors.csv", delimiter=",", skiprows=1)
    assert solved[:, 0].tolist() == sorted(ANCHORS)
    truth = np.array([ANCHORS[int(a)] for a in solved[:, 0]])
    assert np.abs(solved[:, 1:] - truth).max() < 0.2


def test_plaza2_shipped_run(tmp_path, capsys):
    pytest.importorskip("gtsam")
    assert main(["ranges", "plaza2", "--out", str(tmp_path)]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert (summary["poses"], summary["ranges"], summary["anchors"]) == (4091, 1816, 4)
    assert 2.5 < summary["settings"]["range_bias_m"] < 3.2  # calibrated on Plaza1
    assert summary["truth_error"]["rmse_m"] < 0.6


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["plaza2", "--odometry", "o.csv"], "not both"),
        (["--odometry", "o.csv"], "give --odometry, --ranges and --anchors"),
    ],
)
def test_inputs_must_be_one_kind(extra, message, capsys):
    assert main(["ranges", *extra]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--range-sigma", "0", "expected a number > 0"),
        ("--odometry-noise", "1,2", "expected three numbers"),
        ("--start", "1,2,nan", "expected a finite number"),
        ("--robust", "l1", "unknown kernel"),
    ],
)
def test_bad_options_are_refused(option, value, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["ranges", "--odometry", "o.csv", option, value])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_a_range_to_an_unlisted_anchor_names_file_and_line(csv_run, tmp_path, capsys):
    ranges = tmp_path / "ranges.csv"
    ranges.write_text("t,anchor,range\n1.0,3,4.0\n2.0,99,5.0\n")
    args = ["ranges", *_files(csv_run)]
    args[args.index("--ranges") + 1] = str(ranges)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "ranges.csv:3" in err and "anchor 99" in err


def test_output_paths_of_the_wrong_kind_are_refused_before_solving(csv_run, tmp_path, capsys):
    """Were a FileExistsError / IsADirectoryError traceback after the whole solve."""
    a_file = tmp_path / "out.txt"
    a_file.write_text("")
    assert main(["ranges", *_files(csv_run), "--out", str(a_file)]) == 2
    assert f"--out {a_file} is a file" in capsys.readouterr().err
    assert main(["ranges", *_files(csv_run), "--plot", str(tmp_path)]) == 2
    assert f"--plot {tmp_path} is a folder" in capsys.readouterr().err


def test_slam_without_an_anchors_file(csv_run, tmp_path, capsys):
    """Range-only SLAM from nothing: anchor ids from the ranges, positions multilaterated,
    the map in the odometry's start frame; errors reported after a rigid alignment."""
    args = [a for a in _files(csv_run)]
    anchors_at = args.index("--anchors")
    del args[anchors_at : anchors_at + 2]
    out = tmp_path / "scratch"
    assert main(["ranges", *args, "--solve-anchors", "--out", str(out)]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["start"] == [0.0, 0.0, 0.0] and not summary["start_searched"]
    assert summary["truth_error"]["aligned"] and summary["truth_error"]["rmse_m"] < 0.15
    solved = np.loadtxt(out / "anchors.csv", delimiter=",", skiprows=1)
    assert solved[:, 0].tolist() == sorted(ANCHORS)
    true = np.array([ANCHORS[a] for a in sorted(ANCHORS)])
    spacing = np.linalg.norm(solved[:, None, 1:] - solved[None, :, 1:], axis=-1)
    assert np.abs(spacing - np.linalg.norm(true[:, None] - true[None], axis=-1)).max() < 0.3
    assert main(["ranges", *args]) == 2  # held anchors need their positions
    assert "--anchors may be left out with --solve-anchors" in capsys.readouterr().err
