"""docs/robot-logs.md runs as written: its bash block's commands, on a simulated drive written
as the raw logs the page describes (IMU CSV, 16-bit encoder counts, NMEA), give an estimate
near the true path, map files and a score against the fixes."""

from __future__ import annotations

import datetime
import json
import math
import shlex
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.eval.metrics import ate
from msf_torch.io.geodesy import enu_to_geodetic
from msf_torch.io.tum import read_tum
from msf_torch.sim import SimConfig, simulate_run

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "robot-logs.md"
START_UNIX = 1634601580.0
ORIGIN = (49.0125, 8.4172, 160.0)
COUNTS_PER_REV = 1024
RADIUS_M = 0.1
GPX = "{http://www.topografix.com/GPX/1/1}"


def _commands() -> list[str]:
    """The lines of the page's bash block."""
    text = PAGE.read_text()
    block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    return [line for line in block.splitlines() if line.strip()]


def _nmea(body: str) -> str:
    checksum = 0
    for char in body:
        checksum ^= ord(char)
    return f"${body}*{checksum:02X}"


def _degrees_minutes(value: float, width: int) -> str:
    degrees = int(abs(value))
    return f"{degrees:0{width}d}{(abs(value) - degrees) * 60:011.8f}"


def _write_logs(folder: Path, seq) -> None:
    folder.mkdir()
    imu = seq.imu
    table = np.column_stack([imu.t[0].numpy(), imu.gyro[0].numpy(), imu.accel[0].numpy()])
    rows = "".join(",".join(repr(float(x)) for x in row) + "\n" for row in table)
    (folder / "imu.csv").write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + rows)
    # the encoder board: running counts of the true wheel angles, 16-bit counters
    wheel = seq.wheel
    t = wheel.t[0].numpy()
    lines = ["stamp,left,right,battery"]
    for side in ("left_speed", "right_speed"):
        speed = getattr(wheel, side)[0].numpy()
        angle = np.concatenate(([0.0], np.cumsum(speed[1:] * np.diff(t)))) / RADIUS_M
        counts = np.floor(angle * COUNTS_PER_REV / (2 * math.pi)).astype(np.int64) % 65536
        if side == "left_speed":
            left = counts
        else:
            right = counts
    lines += [f"{float(a)!r},{b},{c},12.1" for a, b, c in zip(t, left, right, strict=True)]
    (folder / "ticks.csv").write_text("\n".join(lines) + "\n")
    # the receiver: GGA (MSL height + geoid separation), GST sigmas, UTC times, RMC dates
    # with the true speed (knots) and course (degrees true) over ground
    gnss = seq.gnss
    lat, lon, height = enu_to_geodetic(gnss.position[0].numpy(), ORIGIN)
    truth_t, truth_p = seq.ground_truth.t[0].numpy(), seq.ground_truth.position[0].numpy()
    truth_v = np.gradient(truth_p, truth_t, axis=0)
    east, north = (np.interp(gnss.t[0].numpy(), truth_t, truth_v[:, i]) for i in (0, 1))
    knots = np.hypot(east, north) * 3600 / 1852
    course = np.degrees(np.arctan2(east, north)) % 360
    separation = 47.5
    out = []
    for k, tk in enumerate(gnss.t[0].numpy()):
        when = datetime.datetime.fromtimestamp(START_UNIX + float(tk), datetime.UTC)
        utc = f"{when:%H%M%S}.{when.microsecond // 10000:02d}"
        gga = [
            "GNGGA",
            utc,
            _degrees_minutes(lat[k], 2),
            "N",
            _degrees_minutes(lon[k], 3),
            "E",
            "4",
            "14",
            "0.6",
            f"{height[k] - separation:.4f}",
            "M",
            f"{separation:.3f}",
            "M",
            "",
            "",
        ]
        out.append(_nmea(",".join(gga)))
        out.append(_nmea(f"GNGST,{utc},0.03,0.02,0.02,0.0,0.020,0.020,0.040"))
        motion = f"{knots[k]:.3f},{course[k]:.2f}"
        out.append(_nmea(f"GNRMC,{utc},A,,,,,{motion},{when:%d%m%y},,,D"))
    (folder / "gps.nmea").write_text("\r\n".join(out) + "\r\n")


@pytest.fixture(scope="module")
def drive():
    config = SimConfig(
        duration_s=60.0,
        wheel_rate_hz=50.0,
        wheel_radius_m=RADIUS_M,
        encoder_ticks_per_rev=None,
        wheel_scale_sigma=0.0,
        wheel_speed_noise_mps=0.0,
        gnss_sigma_horizontal_m=0.02,
        gnss_sigma_vertical_m=0.04,
        gnss_outages_s=(),
        slip_episodes=0,
    )
    return simulate_run(config, 21).sequence


def test_the_page_runs_as_written(drive, tmp_path, monkeypatch, capsys) -> None:
    _write_logs(tmp_path / "logs", drive)
    monkeypatch.chdir(tmp_path)
    summaries = []
    for line in _commands():
        words = shlex.split(line.split("#", 1)[0])
        if words[:2] == ["mkdir", "-p"]:  # the shell steps of the block
            parts = line.split("&&")
            Path(shlex.split(parts[0])[2]).mkdir(parents=True, exist_ok=True)
            source, target = shlex.split(parts[1])[1:]
            shutil.copy(source, target)
            continue
        assert words[0] == "msf", line
        assert main(words[1:]) == 0, (line, capsys.readouterr().err)
        summaries.append(json.loads(capsys.readouterr().out.strip().splitlines()[-1]))
    encoders, nmea, run, score = summaries
    assert encoders["counts"]["rollovers"]["left"] >= 1
    assert encoders["speed_resolution_mps"][0] == pytest.approx(0.0307, abs=1e-3)
    assert nmea["fixes"] == drive.gnss.t.shape[1] and nmea["origin_from"] == "first fix"
    assert nmea["velocities"] == nmea["fixes"]
    assert nmea["velocity_out"] == str(Path("run") / "gnss_velocity.csv")
    assert run["measurements"]["gnss"]["accepted"] >= 55
    estimate = read_tum(tmp_path / "out" / "trajectory.tum")
    truth = drive.ground_truth
    # the ENU frame of the fixes starts at the first fix, the simulator's within its
    # noise (2 cm) of it
    error = ate(estimate, truth, align="none", max_dt=0.01)["rmse"]
    assert error < 0.10  # measured 0.031 m (0.032 m without the velocities)
    # the fixes' own noise: 2 cm east and north, 4 cm up (measured 0.045 m)
    assert score["reference_kind"] == "gnss" and score["ate"]["rmse"] < 0.06
    kml = (tmp_path / "out" / "trajectory.kml").read_text()
    assert "<LineString>" in kml and "GNSS fixes" in kml
    # the GPX track on the UTC clock: the estimate's first epoch at START_UNIX + t
    gpx = ET.parse(tmp_path / "out" / "trajectory.gpx").getroot()
    first = gpx.find(f"{GPX}trk/{GPX}trkseg/{GPX}trkpt/{GPX}time").text
    stamp = datetime.datetime.fromisoformat(first).timestamp()
    assert stamp == pytest.approx(START_UNIX + float(estimate.t[0, 0]), abs=1e-6)
