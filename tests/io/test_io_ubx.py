"""u-blox UBX logs (``msf_torch.io.ubx``): NAV-PVT frames written by pyubx2 (an independent
encoder) read back to the values given; frames mixed with other messages, NMEA text, a
broken checksum, a cut-off end; the old 84-byte NAV-PVT; ``msf ubx`` then ``msf run`` on a
simulated drive written as an IMU CSV and a UBX log."""

from __future__ import annotations

import calendar
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.eval.metrics import ate
from msf_torch.io import DataError, read_native
from msf_torch.io.geodesy import enu_to_geodetic
from msf_torch.io.tum import read_tum
from msf_torch.io.ubx import read_ubx
from msf_torch.sim import SimConfig, simulate_run

pyubx2 = pytest.importorskip("pyubx2")

BASE = {
    "iTOW": 123000,
    "year": 2024,
    "month": 3,
    "day": 5,
    "hour": 12,
    "min": 30,
    "second": 15,
    "validDate": 1,
    "validTime": 1,
    "fullyResolved": 1,
    "nano": -12345,
    "fixType": 3,
    "gnssFixOk": 1,
    "carrSoln": 2,
    "numSV": 17,
    "lon": 8.4172345,
    "lat": 49.0125678,
    "height": 160123,
    "hMSL": 112000,
    "hAcc": 1234,
    "vAcc": 2345,
    "velN": 1500,
    "velE": -250,
    "velD": 30,
    "gSpeed": 1520,
    "headMot": 350.5,
    "sAcc": 80,
    "headAcc": 1.5,
    "pDOP": 1.23,
}


def _pvt(**changes) -> bytes:
    return pyubx2.UBXMessage("NAV", "NAV-PVT", pyubx2.GET, **(BASE | changes)).serialize()


def _write(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "log.ubx"
    path.write_bytes(data)
    return path


def test_nav_pvt_values_equal_what_pyubx2_encoded(tmp_path):
    log = read_ubx(_write(tmp_path, _pvt() + _pvt(second=16, nano=250_000_000, carrSoln=1)))
    start = calendar.timegm((2024, 3, 5, 12, 30, 15, 0, 0, 0))
    np.testing.assert_allclose(log.t, [start - 12345e-9, start + 1.25], rtol=0, atol=1e-6)
    assert log.latitude_deg[0] == pytest.approx(49.0125678, abs=1e-12)
    assert log.longitude_deg[0] == pytest.approx(8.4172345, abs=1e-12)
    assert log.height_m[0] == pytest.approx(160.123, abs=1e-12)
    np.testing.assert_allclose(log.sigma_enu[0], [1.234, 1.234, 2.345], rtol=0, atol=1e-12)
    # NED mm/s -> ENU m/s
    np.testing.assert_allclose(log.velocity_enu[0], [-0.25, 1.5, -0.03], rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.velocity_sigma[0], [0.08] * 3, rtol=0, atol=1e-12)
    assert log.carrier.tolist() == [2, 1] and log.satellites.tolist() == [17, 17]
    assert log.counts["kept"] == 2 and log.counts["01-07"] == 2
    gnss, origin = log.to_gnss(t0=start)
    assert origin == (49.0125678, 8.4172345, 160.123)
    np.testing.assert_allclose(gnss.position[0, 0].numpy(), 0.0, atol=1e-9)
    velocity = log.to_gnss_velocity(t0=start)
    np.testing.assert_allclose(velocity.t[0].numpy(), gnss.t[0].numpy())


def test_frames_among_other_data_and_damaged_ones(tmp_path):
    broken = bytearray(_pvt(second=17))
    broken[30] ^= 0xFF  # a flipped payload byte: the checksum fails
    data = b"".join(
        [
            b"$GPGGA,123015.00,,,,,0,00,99.99,,,,,,*65\r\n",  # NMEA text between frames
            _pvt(),
            pyubx2.UBXMessage("NAV", "NAV-STATUS", pyubx2.GET).serialize(),
            _pvt(second=16, fixType=2),  # 2-D: not kept by default
            bytes(broken),
            _pvt(second=18, gnssFixOk=0),  # no fix
            _pvt(second=19, validTime=0),  # time not valid
            _pvt(second=20),
            _pvt(second=20),  # repeated time
            _pvt(second=21)[:50],  # the log ends inside a frame
        ]
    )
    with pytest.warns(UserWarning) as caught:
        log = read_ubx(_write(tmp_path, data))
    assert len(caught) == 1
    message = str(caught[0].message)
    for name in ("bad_checksum 1", "truncated 1", "no_fix 1", "fix_type_not_kept 1"):
        assert name in message
    assert "time_invalid 1" in message and "duplicate_time 1" in message
    assert log.counts["kept"] == 2 and log.counts["01-03"] == 1
    assert log.t[1] - log.t[0] == pytest.approx(5.0, abs=1e-9)
    assert read_ubx(_write(tmp_path, data), fix_types=(2, 3)).counts["kept"] == 3


def test_old_84_byte_nav_pvt_and_a_wrong_length(tmp_path):
    frame = _pvt()
    body = frame[2:6] + frame[6 : 6 + 84]
    body = body[:2] + (84).to_bytes(2, "little") + body[4:]
    a = b = 0
    for byte in body:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    old = b"\xb5\x62" + body + bytes((a, b))
    log = read_ubx(_write(tmp_path, old))
    assert len(log) == 1 and log.latitude_deg[0] == pytest.approx(49.0125678, abs=1e-12)
    body = body[:2] + (40).to_bytes(2, "little") + body[4:44]
    a = b = 0
    for byte in body:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    with pytest.raises(DataError) as err:
        read_ubx(_write(tmp_path, b"xy" + b"\xb5\x62" + body + bytes((a, b))))
    assert err.value.field == "length" and "byte 2" in err.value.problem


def test_msf_ubx_then_msf_run_on_a_simulated_drive(tmp_path, capsys):
    start_unix = 1_700_000_000.0
    origin = (47.3769, 8.5417, 408.0)
    run = simulate_run(SimConfig(duration_s=40.0, gnss_velocity=True, slip_episodes=0), seed=6)
    seq = run.sequence
    folder = tmp_path / "run"
    folder.mkdir()
    imu = seq.imu
    rows = np.column_stack([imu.t[0].numpy(), imu.gyro[0].numpy(), imu.accel[0].numpy()])
    text = "".join(",".join(repr(float(x)) for x in row) + "\n" for row in rows)
    (folder / "imu.csv").write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + text)
    lat, lon, height = enu_to_geodetic(seq.gnss.position[0].numpy(), origin)
    velocity = seq.gnss_velocity.velocity[0].numpy()
    frames = []
    for k, t in enumerate(seq.gnss.t[0].numpy()):
        stamp = start_unix + float(t)
        whole = math.floor(stamp)
        y, mo, d, h, mi, s = time.gmtime(whole)[:6]
        frames.append(
            _pvt(
                year=y,
                month=mo,
                day=d,
                hour=h,
                min=mi,
                second=s,
                nano=round((stamp - whole) * 1e9),
                lat=float(lat[k]),
                lon=float(lon[k]),
                height=round(height[k] * 1000),
                hAcc=500,
                vAcc=1000,
                velN=round(velocity[k, 1] * 1000),
                velE=round(velocity[k, 0] * 1000),
                velD=round(-velocity[k, 2] * 1000),
                sAcc=50,
            )
        )
    log_path = tmp_path / "gnss.ubx"
    log_path.write_bytes(b"".join(frames))
    args = ["ubx", str(log_path), "--out", str(folder / "gnss.csv"), "--t0", str(start_unix)]
    args += ["--origin", ",".join(map(str, origin))]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["fixes"] == summary["velocities"] == seq.gnss.length
    assert summary["time_origin_ns"] == round(start_unix * 1e9)
    converted = read_native(folder)
    # positions back to the simulated ENU within the 1e-7 deg (1.1 cm) / mm encoding
    np.testing.assert_allclose(
        converted.gnss.position[0].numpy(), seq.gnss.position[0].numpy(), rtol=0, atol=0.015
    )
    np.testing.assert_allclose(converted.gnss.t[0].numpy(), seq.gnss.t[0].numpy(), atol=1e-6)
    assert float(converted.gnss_velocity.sigma[0, 0, 0]) == pytest.approx(0.05)
    assert converted.meta["time_origin_ns"] == round(start_unix * 1e9)
    out = tmp_path / "out"
    assert main(["run", str(folder), "--out", str(out), "--no-plot", "--no-learned"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    counts = result["measurements"]
    assert counts["gnss_velocity"]["accepted"] >= seq.gnss.length - 2
    score = ate(read_tum(out / "trajectory.tum"), seq.ground_truth, align="none", max_dt=0.02)
    assert score["rmse"] < 0.5


def test_a_file_without_ubx_frames_is_a_data_error(tmp_path):
    nmea = b"$GPGGA,123015.00,4900.75,N,00825.03,E,1,08,0.9,112.0,M,48.1,M,,*4B\r\n"
    with pytest.raises(DataError, match="not a UBX log: no frame with a valid checksum"):
        read_ubx(_write(tmp_path, nmea * 20))
    with pytest.raises(DataError, match="an empty file"):
        read_ubx(_write(tmp_path, b""))
