"""KITTI raw OXTS drives: a simulated run written in the devkit's layout reads back as the
run (IMU, poses through the geodetic conversion and the ZYX Euler angles, 1 Hz GNSS), the
format is detected, ``msf run`` runs it and malformed files name file, line and field."""

from __future__ import annotations

import datetime
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io import detect_format, load_sequence
from msf_torch.io.errors import DataError
from msf_torch.io.geodesy import enu_to_geodetic
from msf_torch.io.kitti_raw import OXTS_FIELDS, read_kitti_raw
from msf_torch.sim import SimConfig, simulate_run

ORIGIN = (49.011212804408, 8.4228850417969, 112.83492279053)
START = datetime.datetime(2011, 9, 30, 12, 40, 0, 123456, tzinfo=datetime.UTC)
START_NS = int(START.timestamp()) * 1_000_000_000 + 123_456_789


def write_drive(folder: Path, seq) -> Path:
    """``seq`` (ground truth at the IMU times) as ``folder/oxts`` of a KITTI raw drive."""
    oxts = folder / "oxts"
    (oxts / "data").mkdir(parents=True)
    t = seq.imu.t[0].numpy()
    truth = seq.ground_truth
    assert np.array_equal(truth.t[0].numpy(), t)
    lat, lon, alt = enu_to_geodetic(truth.position[0].numpy(), ORIGIN)
    rot = quat_to_matrix(truth.quaternion[0]).numpy()
    roll = np.arctan2(rot[:, 2, 1], rot[:, 2, 2])
    pitch = -np.arcsin(rot[:, 2, 0])
    yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    gyro, accel = seq.imu.gyro[0].numpy(), seq.imu.accel[0].numpy()
    stamps = []
    for k in range(t.size):
        ns = START_NS + round(t[k] * 1e9)
        when = datetime.datetime.fromtimestamp(ns // 1_000_000_000, datetime.UTC)
        stamps.append(f"{when:%Y-%m-%d %H:%M:%S}.{ns % 1_000_000_000:09d}")
        values = dict.fromkeys(OXTS_FIELDS, 0.0)
        values.update(lat=lat[k], lon=lon[k], alt=alt[k], roll=roll[k], pitch=pitch[k])
        values.update(yaw=yaw[k], pos_accuracy=0.05, numsats=9, posmode=5, navstat=4)
        values.update(zip(("ax", "ay", "az"), accel[k], strict=True))
        values.update(zip(("wx", "wy", "wz"), gyro[k], strict=True))
        line = " ".join(repr(float(values[name])) for name in OXTS_FIELDS)
        (oxts / "data" / f"{k:010d}.txt").write_text(line + "\n")
    (oxts / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    return folder


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    config = SimConfig(duration_s=12.0, slip_episodes=0, gnss_outages_s=(), imu_rate_hz=100.0)
    seq = simulate_run(config, 5).sequence
    return seq, write_drive(tmp_path_factory.mktemp("kitti") / "2011_09_30_drive_0001_extract", seq)


def test_drive_reads_back_as_the_run(drive) -> None:
    seq, folder = drive
    assert detect_format(folder) == "kitti-raw" and detect_format(folder / "oxts") == "kitti-raw"
    raw = load_sequence(folder)
    assert raw.names == ["2011_09_30_drive_0001_extract"]
    assert raw.meta["time_origin_ns"] == START_NS
    assert raw.meta["gnss_origin"] == pytest.approx(list(ORIGIN), abs=1e-12)
    assert raw.meta["oxts_posmode"] == {"5": seq.imu.t.shape[1]}
    t = seq.imu.t[0] - seq.imu.t[0, 0]
    np.testing.assert_allclose(raw.imu.t[0], t, atol=2e-9)  # nanosecond stamps
    np.testing.assert_allclose(raw.imu.gyro, seq.imu.gyro, atol=1e-15)
    np.testing.assert_allclose(raw.imu.accel, seq.imu.accel, atol=1e-15)
    truth = raw.ground_truth
    assert float((truth.position - seq.ground_truth.position).abs().max()) < 1e-6
    turn = quat_to_matrix(truth.quaternion).mT @ quat_to_matrix(seq.ground_truth.quaternion)
    angle = torch.linalg.matrix_norm(turn - torch.eye(3, dtype=turn.dtype))
    assert float(angle.max()) < 1e-9
    # GNSS: the first sample of each second, sigma [pos_accuracy, pos_accuracy, NaN]
    fix_t = raw.gnss.t[0].numpy()
    np.testing.assert_allclose(fix_t, np.arange(math.ceil(t[-1].item() + 1e-9)), atol=2e-9)
    sigma = raw.gnss.sigma[0].numpy()
    assert np.all(sigma[:, :2] == 0.05) and np.isnan(sigma[:, 2]).all()


def test_msf_run_on_the_drive(drive, tmp_path, capsys) -> None:
    _, folder = drive
    out = tmp_path / "out"
    args = ["run", str(folder), "--out", str(out), "--no-plot", "--export", "geojson"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["ate_rmse_m"] < 0.5  # IMU + 1 Hz GNSS on the simulated drive
    doc = json.loads((out / "trajectory.geojson").read_text())
    first = doc["features"][0]["geometry"]["coordinates"][0]
    assert first[1] == pytest.approx(ORIGIN[0], abs=1e-4)
    assert first[0] == pytest.approx(ORIGIN[1], abs=1e-4)


def _copy(folder: Path, target: Path) -> Path:
    (target / "oxts" / "data").mkdir(parents=True)
    for file in (folder / "oxts").rglob("*.txt"):
        (target / file.relative_to(folder)).write_text(file.read_text())
    return target


@pytest.mark.parametrize(
    ("edit", "where", "line", "field"),
    [
        (
            lambda o: _edit_line(o / "timestamps.txt", 3, "2011-09-30 12:40:00,5"),
            "timestamps.txt",
            3,
            "timestamp",
        ),
        (
            lambda o: _edit_line(o / "timestamps.txt", 2, "2011-13-30 12:40:00.5"),
            "timestamps.txt",
            2,
            "timestamp",
        ),
        (lambda o: (o / "data" / "0000000004.txt").unlink(), "0000000004.txt", None, None),
        (
            lambda o: _edit_line(o / "data" / "0000000002.txt", 1, "1 2 3"),
            "0000000002.txt",
            1,
            None,
        ),
        (
            lambda o: _edit_value(o / "data" / "0000000006.txt", "yaw", "east"),
            "0000000006.txt",
            1,
            "yaw",
        ),
    ],
)
def test_malformed_drive_names_file_line_and_field(drive, tmp_path, edit, where, line, field):
    _, folder = drive
    copy = _copy(folder, tmp_path / "bad")
    edit(copy / "oxts")
    with pytest.raises(DataError) as err:
        read_kitti_raw(copy)
    assert Path(err.value.path).name == where
    assert (err.value.line, err.value.field) == (line, field)


def _edit_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")


def _edit_value(path: Path, name: str, text: str) -> None:
    cells = path.read_text().split()
    cells[OXTS_FIELDS.index(name)] = text
    path.write_text(" ".join(cells) + "\n")


def test_rules_on_time_and_rate(drive, tmp_path) -> None:
    _, folder = drive
    copy = _copy(folder, tmp_path / "back")
    stamps = (copy / "oxts" / "timestamps.txt").read_text().splitlines()
    stamps[5], stamps[6] = stamps[6], stamps[5]
    (copy / "oxts" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    with pytest.raises(DataError, match="time goes backwards"):
        read_kitti_raw(copy)
    seq = read_kitti_raw(copy, sort=True, gnss_rate_hz=2.0)
    assert seq.meta["sorted"]["imu"] == 1
    assert np.all(np.diff(seq.gnss.t[0].numpy()) == pytest.approx(0.5, abs=1e-6))
    with pytest.raises(ValueError, match="gnss_rate_hz"):
        read_kitti_raw(copy, gnss_rate_hz=0.0)
    with pytest.raises(DataError, match="not a KITTI raw drive"):
        read_kitti_raw(tmp_path)


def test_synced_drive_and_extra_files_are_warned(drive, tmp_path) -> None:
    _, folder = drive
    copy = _copy(folder, tmp_path / "sync")
    oxts = copy / "oxts"
    stamps = (oxts / "timestamps.txt").read_text().splitlines()
    kept = list(range(0, len(stamps), 10))  # 10 Hz, as a synced drive
    for new, old in enumerate(kept):
        (oxts / "data" / f"{new:010d}.txt").write_text(
            (oxts / "data" / f"{old:010d}.txt").read_text()
        )
    (oxts / "timestamps.txt").write_text("\n".join(stamps[k] for k in kept) + "\n")
    with pytest.warns(UserWarning) as caught:
        seq = read_kitti_raw(copy)
    text = " ".join(str(w.message) for w in caught)
    assert "a synced drive?" in text and "more data files than the" in text
    assert seq.imu.t.shape[1] == len(kept)
