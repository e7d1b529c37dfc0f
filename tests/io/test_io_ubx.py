"""u-blox UBX logs (``msf_torch.io.ubx``): NAV-PVT frames written by pyubx2 (an independent
encoder) read back to the values given; frames mixed with other messages, NMEA text, a
broken checksum, a cut-off end; the old 84-byte NAV-PVT; NAV-RELPOSNED headings (F9P
version 1, M8P version 0) timed by the NAV-PVT of their iTOW; ``msf ubx`` then ``msf run``
on a simulated drive with a dual-antenna heading written as an IMU CSV and a UBX log."""

from __future__ import annotations

import calendar
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.eval.metrics import ate
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
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


HEADING = {
    "version": 1,
    "iTOW": 123000,
    "relPosN": 80,
    "relPosE": 60,
    "relPosLength": 100,
    "relPosHeading": 36.86990,
    "accHeading": 0.25,
    "gnssFixOK": 1,
    "diffSoln": 1,
    "relPosValid": 1,
    "carrSoln": 2,
    "isMoving": 1,
    "relPosHeadingValid": 1,
}


def _relposned(**changes) -> bytes:
    fields = HEADING | changes
    if fields["version"] == 0:  # the M8P layout has no relPosLength / heading fields
        fields = {
            k: v for k, v in fields.items() if not k.startswith(("relPosL", "relPosH", "acc"))
        }
    return pyubx2.UBXMessage("NAV", "NAV-RELPOSNED", pyubx2.GET, **fields).serialize()


def _reframe(frame: bytes, length: int) -> bytes:
    """``frame`` with its payload cut to ``length`` bytes and its checksum redone."""
    body = frame[2:4] + length.to_bytes(2, "little") + frame[6 : 6 + length]
    a = b = 0
    for byte in body:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    return b"\xb5\x62" + body + bytes((a, b))


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


GPS_EPOCH_UNIX = 315964800  # 1980-01-06 00:00:00 UTC
GPS_LEAP_S = 18  # GPS - UTC since 2017


def _yaw_errors(trajectory, truth) -> np.ndarray:
    """(N,) rad: the yaw of truth^T estimate at each estimate time (truth at the same time to
    1 ms)."""
    t, truth_t = trajectory.t[0], truth.t[0]
    j = torch.searchsorted(truth_t, t).clamp(max=truth_t.shape[0] - 1)
    assert float((truth_t[j] - t).abs().max()) < 1e-3
    estimate = quat_to_matrix(trajectory.quaternion[0])
    reference = quat_to_matrix(truth.quaternion[0, j])
    return so3.log(reference.mT @ estimate)[:, 2].numpy()


def _ubx_drive(seq, start_unix: float, origin: tuple[float, float, float]) -> bytes:
    """The simulated fixes, velocities and dual-antenna headings as one NAV-PVT and one
    NAV-RELPOSNED (after it, as u-blox orders them) per epoch, iTOW from the UTC time."""
    lat, lon, height = enu_to_geodetic(seq.gnss.position[0].numpy(), origin)
    velocity = seq.gnss_velocity.velocity[0].numpy()
    heading = seq.gnss_heading
    assert torch.equal(heading.t, seq.gnss.t)  # the simulator gives both at the fix times
    degrees = np.degrees(heading.heading[0].numpy())
    sigma_deg = np.degrees(heading.sigma[0].numpy())
    frames = []
    for k, t in enumerate(seq.gnss.t[0].numpy()):
        stamp = start_unix + float(t)
        whole = math.floor(stamp)
        itow = round((stamp - GPS_EPOCH_UNIX + GPS_LEAP_S) % 604800 * 1000)
        y, mo, d, h, mi, s = time.gmtime(whole)[:6]
        frames.append(
            _pvt(
                iTOW=itow,
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
        frames.append(
            _relposned(iTOW=itow, relPosHeading=float(degrees[k]), accHeading=float(sigma_deg[k]))
        )
    return b"".join(frames)


def test_msf_ubx_then_msf_run_on_a_simulated_drive(tmp_path, capsys):
    """A dual-antenna drive (baseline along the body x axis, the configured default): msf ubx
    writes every heading, msf run fuses them, and the yaw error stays below that of the same
    log converted without them (--no-heading)."""
    start_unix = 1_700_000_000.0
    origin = (47.3769, 8.5417, 408.0)
    config = SimConfig(duration_s=40.0, gnss_velocity=True, gnss_heading=True, slip_episodes=0)
    run = simulate_run(config, seed=6)
    seq = run.sequence
    log_path = tmp_path / "gnss.ubx"
    log_path.write_bytes(_ubx_drive(seq, start_unix, origin))
    imu = seq.imu
    rows = np.column_stack([imu.t[0].numpy(), imu.gyro[0].numpy(), imu.accel[0].numpy()])
    text = "".join(",".join(repr(float(x)) for x in row) + "\n" for row in rows)
    yaw = {}
    for name, extra in (("heading", []), ("none", ["--no-heading"])):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "imu.csv").write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + text)
        args = ["ubx", str(log_path), "--out", str(folder / "gnss.csv"), "--t0", str(start_unix)]
        assert main([*args, "--origin", ",".join(map(str, origin)), *extra]) == 0
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert summary["fixes"] == summary["velocities"] == summary["headings"] == seq.gnss.length
        assert summary["time_origin_ns"] == round(start_unix * 1e9)
        converted = read_native(folder)
        if name == "none":
            assert summary["heading_out"] is None and converted.gnss_heading is None
        else:
            assert summary["heading_out"] == str(folder / "gnss_heading.csv")
            assert summary["median_heading_sigma_rad"] == pytest.approx(0.005, rel=1e-3)
            # the headings back within the 1e-5 deg encoding, at the fix times
            heading = converted.gnss_heading
            np.testing.assert_allclose(heading.t.numpy(), converted.gnss.t.numpy(), atol=0)
            np.testing.assert_allclose(
                heading.heading.numpy(), seq.gnss_heading.heading.numpy(), rtol=0, atol=2e-7
            )
        # positions back to the simulated ENU within the 1e-7 deg (1.1 cm) / mm encoding
        np.testing.assert_allclose(
            converted.gnss.position[0].numpy(), seq.gnss.position[0].numpy(), rtol=0, atol=0.015
        )
        np.testing.assert_allclose(converted.gnss.t[0].numpy(), seq.gnss.t[0].numpy(), atol=1e-6)
        assert float(converted.gnss_velocity.sigma[0, 0, 0]) == pytest.approx(0.05)
        assert converted.meta["time_origin_ns"] == round(start_unix * 1e9)
        out = tmp_path / f"out_{name}"
        assert main(["run", str(folder), "--out", str(out), "--no-plot", "--no-learned"]) == 0
        result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        counts = result["measurements"]
        assert counts["gnss_velocity"]["accepted"] >= seq.gnss.length - 2
        if name == "heading":
            assert counts["gnss_heading"]["accepted"] >= seq.gnss.length - 2
        else:
            assert "gnss_heading" not in counts
        trajectory = read_tum(out / "trajectory.tum")
        score = ate(trajectory, seq.ground_truth, align="none", max_dt=0.02)
        assert score["rmse"] < 0.5
        yaw[name] = np.sqrt(np.mean(_yaw_errors(trajectory, seq.ground_truth) ** 2))
    # RMS over the run: 0.0025 rad with the headings, 0.039 rad without
    assert yaw["heading"] < 0.01 and yaw["heading"] < 0.5 * yaw["none"]


def test_a_file_without_ubx_frames_is_a_data_error(tmp_path):
    nmea = b"$GPGGA,123015.00,4900.75,N,00825.03,E,1,08,0.9,112.0,M,48.1,M,,*4B\r\n"
    with pytest.raises(DataError, match="not a UBX log: no frame with a valid checksum"):
        read_ubx(_write(tmp_path, nmea * 20))
    with pytest.raises(DataError, match="an empty file"):
        read_ubx(_write(tmp_path, b""))


def test_nav_relposned_headings_get_the_time_of_their_nav_pvt(tmp_path):
    """relPosHeading and accHeading (1e-5 deg) as rad; the UTC time of the NAV-PVT of the same
    iTOW (before or after it in the file, kept as a fix or not); what gives no vehicle heading
    is counted and named in the one warning."""
    data = b"".join(
        [
            _pvt(),
            _relposned(),  # kept at the first PVT's time
            _relposned(iTOW=124000, relPosHeading=359.99999, accHeading=0.0),  # PVT after it
            _pvt(iTOW=124000, second=16, nano=250_000_000),
            _relposned(iTOW=124000),  # the same epoch again
            _pvt(iTOW=125000, second=17, fixType=2),  # 2-D: no fix kept, a valid time
            _relposned(iTOW=125000, relPosHeading=-90.0),
            _relposned(iTOW=125000, relPosHeadingValid=0),
            _relposned(iTOW=125000, gnssFixOK=0),
            _relposned(iTOW=125000, relPosValid=0),
            _relposned(iTOW=125000, isMoving=0),  # a fixed base station: not a heading
            _relposned(version=0, iTOW=125000),  # M8P: no heading field
            _relposned(iTOW=126000),  # no NAV-PVT of this epoch
            _pvt(iTOW=127000, second=18, validTime=0),
            _relposned(iTOW=127000),  # its PVT has no valid time
        ]
    )
    with pytest.warns(UserWarning) as caught:
        log = read_ubx(_write(tmp_path, data))
    assert len(caught) == 1
    message = str(caught[0].message)
    for name in ("heading_invalid 3", "heading_fixed_base 1", "heading_duplicate 1"):
        assert name in message
    assert "heading_no_field 1 (NAV-RELPOSNED version 0, M8P, has no relPosHeading)" in message
    assert "heading_untimed 2" in message and "heading_kept" not in message
    assert log.counts["heading_kept"] == 3 and log.counts["01-3C"] == 11
    start = calendar.timegm((2024, 3, 5, 12, 30, 15, 0, 0, 0)) - 12345e-9
    np.testing.assert_allclose(log.heading_t - start, [0.0, 1.25 + 12345e-9, 2.0], atol=1e-6)
    encoded = pyubx2.UBXReader.parse(_relposned())  # the values as pyubx2 rounded them
    degrees = np.array([encoded.relPosHeading, 359.99999, 270.0])
    np.testing.assert_allclose(log.heading_rad, np.radians(degrees), rtol=0, atol=1e-12)
    sigma = np.radians(encoded.accHeading)
    np.testing.assert_allclose(log.heading_sigma_rad[[0, 2]], sigma, rtol=1e-12)
    assert np.isnan(log.heading_sigma_rad[1])  # accHeading 0: not computed, not exact
    assert log.heading_offsets.tolist() == [100, 172, 516]  # 100-byte PVT, 72-byte frames
    assert len(log) == 2 and log.t[0] == log.heading_t[0]
    heading = log.to_gnss_heading(t0=start)
    assert heading.heading.shape == heading.sigma.shape == heading.t.shape == (1, 3)
    np.testing.assert_allclose(heading.t[0].numpy(), log.heading_t - start)
    assert heading.mask.all() and heading.heading.dtype == torch.float64


def test_nav_relposned_of_a_wrong_length_names_its_byte(tmp_path):
    full = _relposned()
    for frame, shown in ((_reframe(full, 40), "version 1 and a 40-byte"), (full[:-2], "")):
        if not shown:  # version 0 with the 64-byte layout
            body = bytearray(full)
            body[6] = 0
            frame = _reframe(bytes(body), 64)
            shown = "version 0 and a 64-byte"
        with pytest.raises(DataError) as err:
            read_ubx(_write(tmp_path, _pvt() + frame))
        assert err.value.field == "length" and f"byte 100 has {shown}" in err.value.problem
    log = read_ubx(_write(tmp_path, _pvt()))  # no NAV-RELPOSNED: no heading, nothing warned
    assert log.heading_t.shape == log.heading_rad.shape == (0,)
    assert log.to_gnss_heading().t.shape == (1, 0)
