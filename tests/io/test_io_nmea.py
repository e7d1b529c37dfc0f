"""NMEA 0183 logs (msf_torch.io.nmea, ``msf nmea``): a generated log with known geodetic
points, times across midnight, GST sigmas, RMC / VTG velocities, a corrupted line, a no-fix
GGA and sentences that are skipped; pynmea2 as the independent reference for every GGA and
for speeds, courses and HDT headings; velocities and headings against closed forms; bad
input."""

from __future__ import annotations

import calendar
import json
import math
import signal
import warnings

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.io import DataError, read_native
from msf_torch.io.geodesy import geodetic_to_enu
from msf_torch.io.nmea import NmeaLog, read_nmea, write_gnss_csv

N_EPOCHS = 40
START_UNIX = calendar.timegm((2021, 10, 18, 23, 59, 40))  # + 0.5 s: midnight at epoch 20
CORRUPT_EPOCH = 7
NO_GST_EPOCHS = (4, 11, 25)
DATE_EPOCHS = (3, 13, 23, 33)  # an RMC after these GGAs: fixes 0-2 get the date back-filled
VTG_EPOCHS = (0, 15, 30)  # a VTG after these GGAs
SEPARATION_M = 47.5
KNOT_MPS = 1852 / 3600  # the international nautical mile per hour


def _checksum(body: str) -> str:
    value = 0
    for char in body.encode("ascii"):
        value ^= char
    return f"{value:02X}"


def _sentence(body: str) -> str:
    return f"${body}*{_checksum(body)}"


def _with_field(sentence: str, index: int, value: str) -> str:
    """``sentence`` with field ``index`` (0: the address) set to ``value``, checksum redone."""
    fields = sentence[1:].split("*")[0].split(",")
    fields[index] = value
    return _sentence(",".join(fields))


def _dm(value: float, width: int) -> str:
    """``[d]ddmm.mmmmmmmm`` of |value| degrees."""
    degrees = int(abs(value))
    return f"{degrees:0{width}d}{(abs(value) - degrees) * 60.0:011.8f}"


def _utc(k: int) -> str:
    seconds = (START_UNIX + k) % 86400
    return f"{seconds // 3600:02d}{seconds // 60 % 60:02d}{seconds % 60:02d}.50"


def _truth() -> dict[str, np.ndarray]:
    """A ~200 m loop about 49 N 8.4 E: N_EPOCHS points, 1 Hz from 23:59:40.5 UTC."""
    angle = np.linspace(0.0, 2.0 * np.pi, N_EPOCHS, endpoint=False)
    return {
        "t": START_UNIX + np.arange(N_EPOCHS) + 0.5,
        "latitude": 49.0 + 0.00028 * np.sin(angle),
        "longitude": 8.4 + 0.000425 * np.cos(angle),
        "msl": 110.0 + 0.5 * np.sin(2.0 * angle),
        "sigma_enu": np.stack(
            (
                0.02 + 0.001 * np.arange(N_EPOCHS),
                0.01 + 0.001 * np.arange(N_EPOCHS),
                0.05 + 0 * angle,
            ),
            -1,
        ),
    }


def _gga(k: int, truth: dict[str, np.ndarray], talker: str = "GN") -> str:
    lat, lon = truth["latitude"][k], truth["longitude"][k]
    fields = [
        f"{talker}GGA",
        _utc(k),
        _dm(lat, 2),
        "N" if lat >= 0 else "S",
        _dm(lon, 3),
        "E" if lon >= 0 else "W",
        "4" if k % 3 else "5",
        f"{10 + k % 5:02d}",
        f"{0.6 + 0.01 * k:.2f}",
        f"{truth['msl'][k]:.4f}",
        "M",
        f"{SEPARATION_M:.3f}",
        "M",
        "1.0",
        "0000",
    ]
    return _sentence(",".join(fields))


def _gst(k: int, truth: dict[str, np.ndarray]) -> str:
    east, north, up = truth["sigma_enu"][k]
    return _sentence(f"GPGST,{_utc(k)},0.8,0.05,0.03,12.5,{north:.3f},{east:.3f},{up:.3f}")


def _rmc(k: int) -> str:
    day = (START_UNIX + k) // 86400
    date = np.datetime64(int(day), "D").astype(object)
    return _sentence(f"GNRMC,{_utc(k)},A,4900.000,N,00824.000,E,0.5,10.0,{date:%d%m%y},,,D")


def _log_lines(truth: dict[str, np.ndarray]) -> tuple[list[str], int]:
    """The log's lines and the 1-based line number of the corrupted GGA."""
    lines = [
        _sentence("GPGGA,235939.50,,,,,0,00,99.99,,,,,,"),  # the receiver's no-fix form
        _sentence("GLGSV,1,1,02,65,30,120,40,66,45,200,42"),
        "",
    ]
    corrupt_line = 0
    for k in range(N_EPOCHS):
        gga = _gga(k, truth)
        if k == CORRUPT_EPOCH:  # one serial byte flipped in the latitude
            gga = gga.replace(",4900.", ",4901.", 1)
            corrupt_line = len(lines) + 1
        lines.append(gga)
        if k not in NO_GST_EPOCHS:
            lines.append(_gst(k, truth))
        if k in DATE_EPOCHS:
            lines.append(_rmc(k))
        if k % 15 == 0:
            lines.append(_sentence("GPVTG,10.0,T,,M,0.5,N,0.9,K,D"))
            lines.append(_sentence("GPGSV,1,1,01,05,30,120,40"))
    return lines, corrupt_line


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """(path, truth, corrupted line) of the generated log."""
    truth = _truth()
    lines, corrupt_line = _log_lines(truth)
    path = tmp_path_factory.mktemp("nmea") / "drive.nmea"
    path.write_text("\r\n".join(lines) + "\r\n")
    return path, truth, corrupt_line


@pytest.fixture(scope="module")
def log(generated) -> NmeaLog:
    with pytest.warns(UserWarning, match="skipped"):
        return read_nmea(generated[0])


def test_generated_log_parses_to_the_points(generated, log):
    path, truth, corrupt_line = generated
    keep = np.arange(N_EPOCHS) != CORRUPT_EPOCH
    assert len(log) == N_EPOCHS - 1
    assert log.time_source == "utc"
    np.testing.assert_allclose(log.latitude_deg, truth["latitude"][keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.longitude_deg, truth["longitude"][keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.altitude_m, truth["msl"][keep] + SEPARATION_M, rtol=0, atol=1e-4)
    # UNIX times across midnight: dates back-filled, rolled over, then taken from the RMC
    np.testing.assert_array_equal(log.t, truth["t"][keep])
    assert log.t[20 - 1] - log.t[19 - 1] == 1.0  # 23:59:59.5 -> 00:00:00.5 (one fix dropped)
    expected_sigma = truth["sigma_enu"][keep].copy()
    no_gst = np.isin(np.arange(N_EPOCHS)[keep], NO_GST_EPOCHS)
    expected_sigma[no_gst] = np.nan
    np.testing.assert_allclose(log.sigma_enu, expected_sigma, rtol=0, atol=5e-4)
    assert np.isnan(log.sigma_enu[no_gst]).all() and np.isfinite(log.sigma_enu[~no_gst]).all()
    np.testing.assert_array_equal(log.quality, np.where(np.arange(N_EPOCHS) % 3, 4, 5)[keep])
    assert log.counts["kept"] == N_EPOCHS - 1
    assert log.counts["no_fix"] == 1
    assert log.counts["bad_checksum"] == 1
    assert log.counts["gst_unmatched"] == 1  # the corrupted epoch's GST
    assert log.counts["GGA"] == N_EPOCHS  # the no-fix one, not the corrupted one
    assert log.counts["GSV"] == 4 and log.counts["VTG"] == 3 and log.counts["RMC"] == 4
    assert log.counts["duplicate_time"] == 0 and log.counts["quality_not_kept"] == 0
    assert not log.geoid_separation_missing
    assert corrupt_line not in log.lines.tolist()
    # 0.5 kn at 10 deg from each RMC and VTG, at its epoch's time (VTG: the GGA before it),
    # across midnight with the dates back-filled as the fixes'
    epochs = sorted(DATE_EPOCHS + VTG_EPOCHS)
    np.testing.assert_array_equal(log.velocity_t, truth["t"][epochs])
    speed, course = 0.5 * KNOT_MPS, math.radians(10.0)
    expected = np.tile([speed * math.sin(course), speed * math.cos(course), np.nan], (7, 1))
    np.testing.assert_allclose(log.velocity_enu, expected, rtol=0, atol=1e-15)
    assert log.counts["velocity_kept"] == 7 and log.counts["velocity_duplicate"] == 0


def test_warning_lists_what_was_skipped(generated):
    path, _, corrupt_line = generated
    with pytest.warns(UserWarning) as record:
        read_nmea(path, qualities=(5,))
    messages = [str(w.message) for w in record]
    assert len(messages) == 1
    text = messages[0]
    assert f"bad_checksum 1 (lines {corrupt_line})" in text
    assert "no_fix 1" in text and "GSV 4" in text and "VTG" not in text and "velocity" not in text
    below = sum(1 for k in range(N_EPOCHS) if k % 3 and k != CORRUPT_EPOCH)  # quality 4
    assert f"quality_not_kept {below}" in text


def test_every_gga_equals_pynmea2(generated, log):
    pynmea2 = pytest.importorskip("pynmea2")
    lines = generated[0].read_text().splitlines()
    for i, number in enumerate(log.lines.tolist()):
        msg = pynmea2.parse(lines[number - 1], check=True)
        assert log.latitude_deg[i] == pytest.approx(msg.latitude, abs=1e-12)
        assert log.longitude_deg[i] == pytest.approx(msg.longitude, abs=1e-12)
        assert log.altitude_m[i] == float(msg.altitude) + float(msg.geo_sep)
        assert log.quality[i] == int(msg.gps_qual)
        assert log.satellites[i] == int(msg.num_sats)
        assert log.hdop[i] == float(msg.horizontal_dil)
    # and pynmea2 rejects the corrupted line too
    with pytest.raises(pynmea2.ChecksumError):
        pynmea2.parse(lines[generated[2] - 1], check=True)


def test_to_gnss_is_geodetic_to_enu(generated, log):
    gnss, origin = log.to_gnss()
    first = (log.latitude_deg[0], log.longitude_deg[0], log.altitude_m[0])
    assert origin == first
    enu = geodetic_to_enu(log.latitude_deg, log.longitude_deg, log.altitude_m, first)
    assert gnss.position.dtype == torch.float64 and gnss.position.shape == (1, len(log), 3)
    np.testing.assert_array_equal(gnss.position[0].numpy(), enu)
    np.testing.assert_array_equal(gnss.position[0, 0].numpy(), np.zeros(3))
    np.testing.assert_array_equal(gnss.sigma[0].numpy(), log.sigma_enu)
    assert gnss.mask.all()

    truth = generated[1]
    keep = np.arange(N_EPOCHS) != CORRUPT_EPOCH
    given = (49.0, 8.4, 150.0)
    moved, used = log.to_gnss(origin=given, t0=START_UNIX)
    assert used == given
    expected = geodetic_to_enu(
        truth["latitude"][keep], truth["longitude"][keep], truth["msl"][keep] + SEPARATION_M, given
    )
    np.testing.assert_allclose(moved.position[0].numpy(), expected, rtol=0, atol=2e-4)
    np.testing.assert_array_equal(moved.t[0].numpy(), truth["t"][keep] - START_UNIX)
    loop = np.linalg.norm(np.diff(expected[:, :2], axis=0), axis=1).sum()
    assert 180.0 < loop < 220.0  # the ~200 m loop


def _write(tmp_path, lines: list[str], name: str = "log.nmea"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_receive_stamps_and_missing_date(tmp_path):
    truth = _truth()
    stamps = 1634601580.25 + np.arange(5) * 1.001
    lines = [f"{float(stamps[k])!r}{',' if k % 2 else '  '}{_gga(k, truth)}" for k in range(5)]
    path = _write(tmp_path, lines)
    log = read_nmea(path)
    assert log.time_source == "receive"
    np.testing.assert_array_equal(log.t, stamps)
    with pytest.warns(UserWarning, match="no RMC or ZDA date"):
        utc = read_nmea(path, time="utc")
    assert utc.time_source == "utc"
    np.testing.assert_array_equal(utc.t, (START_UNIX % 86400) + 0.5 + np.arange(5))

    # one GGA without a stamp: auto falls back to UTC, receive is an error naming the line
    lines[3] = _gga(3, truth)
    path = _write(tmp_path, lines + [_sentence("GPZDA,235945.50,18,10,2021,00,00")])
    assert read_nmea(path).time_source == "utc"
    with pytest.raises(DataError) as err:
        read_nmea(path, time="receive")
    assert err.value.line == 4 and err.value.field == "receive_time"


def test_midnight_rollover_without_a_date(tmp_path):
    truth = _truth()
    path = _write(tmp_path, [_gga(k, truth) for k in range(17, 23)])
    with pytest.warns(UserWarning, match="no RMC or ZDA date"):
        log = read_nmea(path)
    np.testing.assert_array_equal(log.t, 86380.5 + np.arange(17, 23))


def test_missing_geoid_separation_and_duplicates(tmp_path):
    truth = _truth()
    lines = [
        _gga(0, truth),
        _gga(0, truth, talker="GP"),  # the same epoch from a second talker
        _with_field(_gga(1, truth), 11, ""),
    ]
    with pytest.warns(UserWarning) as record:
        log = read_nmea(_write(tmp_path, lines), time="utc")
    text = " ".join(str(w.message) for w in record)
    assert "duplicate_time 1" in text and "1 of 2 fixes have no geoid separation" in text
    assert log.geoid_separation_missing and log.counts["duplicate_time"] == 1
    np.testing.assert_allclose(
        log.altitude_m, [truth["msl"][0] + SEPARATION_M, truth["msl"][1]], atol=1e-4
    )
    with pytest.raises(DataError, match="time goes back") as err, pytest.warns(UserWarning):
        read_nmea(_write(tmp_path, [_gga(2, truth), _gga(1, truth)]))
    assert err.value.line == 2 and err.value.field == "utc_time"


def test_date_sentence_before_the_gga_at_midnight(tmp_path):
    """An RMC of 00:00:00.5 with the new date before that epoch's GGA: the RMC's own time
    rolls the day, so the GGA is not moved a second day on."""
    truth = _truth()
    lines = [line for k in range(17, 23) for line in (_rmc(k), _gga(k, truth))]
    log = read_nmea(_write(tmp_path, lines))
    np.testing.assert_array_equal(log.t, truth["t"][17:23])


def test_gst_attaches_to_the_nearest_fix_of_its_time(tmp_path):
    """A log over a day: 12:00:00 UTC occurs twice; each GST goes to its own day's fix."""
    truth = _truth()

    def at(hhmmss: str, k: int) -> str:
        return _with_field(_gga(k, truth), 1, hhmmss)

    lines = [
        at("120000.50", 0),
        _sentence("GPGST,120000.50,0.8,0.05,0.03,12.5,0.011,0.012,0.013"),
        at("200000.50", 1),
        at("040000.50", 2),
        at("120000.50", 3),
        _sentence("GPGST,120000.50,0.8,0.05,0.03,12.5,0.021,0.022,0.023"),
        _rmc(0),
    ]
    log = read_nmea(_write(tmp_path, lines))
    assert log.counts["gst_unmatched"] == 0
    np.testing.assert_array_equal(log.sigma_enu[0], [0.012, 0.011, 0.013])
    np.testing.assert_array_equal(log.sigma_enu[3], [0.022, 0.021, 0.023])
    assert np.isnan(log.sigma_enu[1:3]).all()
    # the RMC (18 Oct, 23:59:40.5) dates the last fix's day, so the first is on 17 Oct
    assert log.t[3] - log.t[0] == 86400.0
    assert log.t[0] == calendar.timegm((2021, 10, 17, 12, 0, 0)) + 0.5


@pytest.mark.parametrize(
    ("latitude", "longitude"), [(-33.8568, 151.2153), (64.1466, -21.9426), (-0.0001, -0.0002)]
)
def test_hemispheres_equal_pynmea2(tmp_path, latitude, longitude):
    pynmea2 = pytest.importorskip("pynmea2")
    truth = _truth()
    truth["latitude"] = np.full(N_EPOCHS, latitude)
    truth["longitude"] = np.full(N_EPOCHS, longitude)
    line = _gga(0, truth)
    with pytest.warns(UserWarning, match="no RMC"):
        log = read_nmea(_write(tmp_path, [line]))
    msg = pynmea2.parse(line, check=True)
    assert log.latitude_deg[0] == pytest.approx(latitude, abs=1e-9)
    assert log.longitude_deg[0] == pytest.approx(longitude, abs=1e-9)
    assert log.latitude_deg[0] == pytest.approx(msg.latitude, abs=1e-12)
    assert log.longitude_deg[0] == pytest.approx(msg.longitude, abs=1e-12)


@pytest.mark.parametrize(
    ("index", "value", "field"),
    [
        (1, "2359x0.50", "utc_time"),
        (1, "256161.00", "utc_time"),
        (2, "49O0.1234", "latitude"),
        (2, "4960.0000", "latitude"),
        (3, "Q", "latitude_hemisphere"),
        (4, "", "longitude"),
        (5, "X", "longitude_hemisphere"),
        (6, "A", "quality"),
        (7, "1.5", "satellites"),
        (8, "-1", "hdop"),
        (9, "", "altitude"),
        (10, "F", "altitude_unit"),
        (11, "47,5", "separation_unit"),
    ],
)
def test_malformed_gga_names_line_and_field(tmp_path, index, value, field):
    truth = _truth()
    lines = [_gga(0, truth), _with_field(_gga(1, truth), index, value)]
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, lines))
    assert err.value.line == 2 and err.value.field == field
    # without its checksum the malformed sentence is read (and rejected) too
    lines[1] = lines[1].split("*")[0]
    with pytest.raises(DataError):
        read_nmea(_write(tmp_path, lines))


@pytest.mark.parametrize(
    ("line", "field"),
    [
        ("GPGST,235940.50,0.8,0.05,0.03,12.5,-0.01,0.02,0.05", "sigma_latitude"),
        ("GPGST,235940.50,0.8,0.05,0.03,12.5,0.01,abc,0.05", "sigma_longitude"),
        ("GPGST,235940.50,0.8,0.05,0.03,12.5,0.01,0.02", "sigma_altitude"),
        ("GNRMC,235940.50,A,4900.000,N,00824.000,E,0.5,10.0,311321,,,D", "date"),
        ("GNZDA,235940.50,31,02,2021,00,00", "date"),
    ],
)
def test_malformed_gst_and_dates(tmp_path, line, field):
    lines = [_gga(0, _truth()), _sentence(line)]
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, lines))
    assert err.value.line == 2 and err.value.field == field


def test_missing_file_and_no_gga(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_nmea(tmp_path / "absent.nmea")
    path = _write(tmp_path, ["t,x,y,z", _sentence("GPGSV,1,1,01,05,30,120,40")])
    with pytest.raises(DataError, match="no GGA sentence.*GSV 1"):
        read_nmea(path)
    with pytest.raises(ValueError, match="time must be"):
        read_nmea(path, time="gps")


@pytest.mark.parametrize(
    ("index", "value", "field"),
    [(6, "1" * 5000, "quality"), (7, "18446744073709551616", "satellites")],
)
def test_fuzzer_digit_runs_in_count_fields(tmp_path, index, value, field):
    """Fuzzer finds: a quality of 5000 digits passed int()'s digit limit (ValueError), a
    satellite count over int64 broke the column (OverflowError), a 20-digit ZDA year broke
    datetime.date (OverflowError)."""
    truth = _truth()
    lines = [_gga(0, truth), _with_field(_gga(1, truth), index, value)]
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, lines))
    assert (err.value.line, err.value.field) == (2, field)
    lines[1] = _sentence("GNZDA,235940.50,18,10," + "1" * 20 + ",00,00")
    with pytest.raises(DataError, match="expected day, month, year") as err:
        read_nmea(_write(tmp_path, lines))
    assert (err.value.line, err.value.field) == (2, "date")


@pytest.mark.parametrize(
    ("index", "field"), [(8, "hdop"), (9, "altitude"), (11, "geoid_separation")]
)
def test_fuzzer_numbers_beyond_the_float_range(tmp_path, index, field):
    """Fuzzer finds: 400 nines in a GGA or GST number were read as inf and kept."""
    truth = _truth()
    lines = [_gga(0, truth), _with_field(_gga(1, truth), index, "9" * 400)]
    with pytest.raises(DataError, match="beyond the float range") as err:
        read_nmea(_write(tmp_path, lines))
    assert (err.value.line, err.value.field) == (2, field)
    gst = _sentence(f"GPGST,{_utc(0)},0.8,0.05,0.03,12.5,0.01,0.02,{'9' * 400}")
    with pytest.raises(DataError, match="beyond the float range") as err:
        read_nmea(_write(tmp_path, [_gga(0, truth), gst]))
    assert (err.value.line, err.value.field) == (2, "sigma_altitude")


def test_fuzzer_long_digit_run_is_rejected_at_once(tmp_path):
    """Fuzzer finds: a 200,000-digit cell that is not a number (or a receive stamp that is
    not one) made the number patterns backtrack quadratically: minutes per line."""

    def too_slow(signum: int, frame: object) -> None:
        raise TimeoutError("read_nmea took over 30 s")

    truth = _truth()
    digits = "1" * 200_000 + "x"
    previous = signal.signal(signal.SIGALRM, too_slow)
    signal.alarm(30)
    try:
        with pytest.raises(DataError, match="not a number") as err:
            read_nmea(_write(tmp_path, [_gga(0, truth), _with_field(_gga(1, truth), 9, digits)]))
        assert (err.value.line, err.value.field) == (2, "altitude")
        with pytest.warns(UserWarning, match="unreadable_prefix 1"):
            log = read_nmea(_write(tmp_path, [f"{digits} {_gga(0, truth)}"]), time="utc")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert len(log) == 1


def test_cli_writes_a_gnss_csv_that_read_native_reads(generated, tmp_path, capsys):
    path = generated[0]
    out = tmp_path / "run" / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(out), "--t0", str(START_UNIX)]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert "msf nmea: warning:" in captured.err and "bad_checksum 1" in captured.err
    # dated UTC times: the folder's t = 0 is UNIX START_UNIX
    assert summary["time_origin_ns"] == START_UNIX * 1_000_000_000
    assert json.loads((out.parent / "meta.json").read_text())["time_origin_ns"] == (
        START_UNIX * 1_000_000_000
    )
    assert summary["fixes"] == N_EPOCHS - 1
    assert summary["fixes_with_sigma"] == N_EPOCHS - 1 - len(NO_GST_EPOCHS)
    assert summary["counts"]["bad_checksum"] == 1
    assert summary["time_source"] == "utc"
    assert summary["t_range_s"] == [0.5, N_EPOCHS - 0.5]
    with pytest.warns(UserWarning):
        log = read_nmea(path)
    assert summary["origin"] == [log.latitude_deg[0], log.longitude_deg[0], log.altitude_m[0]]
    assert math.isclose(summary["median_sigma_enu_m"][2], 0.05)

    (out.parent / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.81\n1,0,0,0,0,0,9.81\n"
    )
    seq = read_native(out.parent)
    gnss, _ = log.to_gnss(t0=START_UNIX)
    np.testing.assert_array_equal(seq.gnss.t.numpy(), gnss.t.numpy())
    np.testing.assert_array_equal(seq.gnss.position.numpy(), gnss.position.numpy())
    np.testing.assert_array_equal(seq.gnss.sigma.numpy(), gnss.sigma.numpy())

    assert seq.meta["time_origin_ns"] == START_UNIX * 1_000_000_000

    origin = "49.0,8.4,150.0"
    assert main(["nmea", str(path), "--out", str(out), "--origin", origin, "--time", "utc"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["origin"] == [49.0, 8.4, 150.0]
    assert summary["t_range_s"][0] == START_UNIX + 0.5
    assert summary["time_origin_ns"] == 0 and "time_origin_ns changed" in captured.err
    # without a date the times are seconds of the day: no time origin is stored
    undated = _write(tmp_path, [_gga(k, _truth()) for k in range(3)], "undated.nmea")
    folder = tmp_path / "undated"
    assert main(["nmea", str(undated), "--out", str(folder / "gnss.csv")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["time_origin_ns"] is None
    assert "time_origin_ns" not in json.loads((folder / "meta.json").read_text())


def test_cli_keeps_the_folders_origin_in_meta_json(generated, tmp_path, capsys):
    path = generated[0]
    out = tmp_path / "run" / "gnss.csv"
    out.parent.mkdir()
    (out.parent / "meta.json").write_text('{"wheel_track_m": 0.5}')
    assert main(["nmea", str(path), "--out", str(out)]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["origin_from"] == "first fix"
    meta = json.loads((out.parent / "meta.json").read_text())
    assert meta == {"gnss_origin": first["origin"], "time_origin_ns": 0, "wheel_track_m": 0.5}
    before = out.read_text()
    # a second conversion (another quality set, say) stays in the same ENU frame
    assert main(["nmea", str(path), "--out", str(out)]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["origin_from"] == "meta.json" and again["origin"] == first["origin"]
    assert out.read_text() == before
    assert main(["nmea", str(path), "--out", str(out), "--origin", "49.0,8.4,150.0"]) == 0
    captured = capsys.readouterr()
    assert "gnss_origin changed" in captured.err
    assert json.loads((out.parent / "meta.json").read_text())["gnss_origin"] == [49.0, 8.4, 150.0]
    (out.parent / "meta.json").write_text('{"gnss_origin": [49.0, 8.4]}')
    assert main(["nmea", str(path), "--out", str(out)]) == 2
    assert "gnss_origin" in capsys.readouterr().err


def test_cli_errors(generated, tmp_path, capsys):
    assert main(["nmea", str(tmp_path / "absent.nmea"), "--out", str(tmp_path / "g.csv")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["nmea", str(generated[0]), "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    path = _write(tmp_path, [_sentence("GPGGA,235939.50,,,,,0,00,99.99,,,,,,")])
    assert main(["nmea", str(path), "--out", str(tmp_path / "g.csv")]) == 2
    assert "no fix kept" in capsys.readouterr().err


def test_write_gnss_csv_without_sigmas(tmp_path, log):
    gnss, _ = log.to_gnss()
    gnss.sigma[:] = torch.nan
    path = write_gnss_csv(tmp_path / "gnss.csv", gnss)
    assert path.read_text().splitlines()[0] == "t,x,y,z"


def test_quality_codes_are_a_set_not_a_ranking(tmp_path, capsys):
    """Dead-reckoning (6), manual (7) and simulated (8) fixes are not measurements: the
    default keeps 1-5 only; ``qualities`` picks codes (RTK fixed alone: 4), and so does the
    CLI's ``--quality``."""
    truth = _truth()
    codes = [1, 4, 5, 6, 7, 8, 2, 4]
    lines = [_with_field(_gga(k, truth), 6, str(q)) for k, q in enumerate(codes)]
    path = _write(tmp_path, lines)
    with pytest.warns(UserWarning, match="quality_not_kept 3"):
        log = read_nmea(path)
    assert log.quality.tolist() == [1, 4, 5, 2, 4]
    with pytest.warns(UserWarning, match="quality_not_kept 6"):
        rtk = read_nmea(path, qualities=(4,))
    assert rtk.lines.tolist() == [2, 8]
    for bad in ((), (0,), (10,), (True,)):
        with pytest.raises(ValueError, match="quality codes"):
            read_nmea(path, qualities=bad)
    out = tmp_path / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(out), "--quality", "4,5"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["fixes"] == 3
    with pytest.raises(SystemExit):
        main(["nmea", str(path), "--out", str(out), "--quality", "4,x"])
    assert "GGA quality codes 1-9" in capsys.readouterr().err


def test_zero_gst_sigma_is_not_given_and_overflowing_height_is_refused(tmp_path):
    """A GST sigma of 0 (a field the receiver did not compute) reads as NaN, not as an exact
    fix; an altitude plus geoid separation beyond the float range is a DataError on the
    separation (each number alone is finite)."""
    truth = _truth()
    gst = _sentence(f"GPGST,{_utc(0)},0.8,0.05,0.03,12.5,0.0,0.020,-0.0")
    log = read_nmea(_write(tmp_path, [_gga(0, truth), gst], "zero.nmea"))
    assert np.isnan(log.sigma_enu[0, 1]) and np.isnan(log.sigma_enu[0, 2])
    assert log.sigma_enu[0, 0] == pytest.approx(0.02)
    huge = "1" * 309
    gga = _with_field(_with_field(_gga(0, truth), 9, huge), 11, huge)
    with pytest.raises(DataError) as info:
        read_nmea(_write(tmp_path, [gga], "sum.nmea"))
    assert (info.value.line, info.value.field) == (1, "geoid_separation")


def _rmc_velocity(k: int, status: str, knots: str, course: str, mode: str) -> str:
    """The RMC of epoch ``k`` with its status, speed (knots), course and mode indicator."""
    day = (START_UNIX + k) // 86400
    date = np.datetime64(int(day), "D").astype(object)
    position = "4900.000,N,00824.000,E"
    return _sentence(f"GNRMC,{_utc(k)},{status},{position},{knots},{course},{date:%d%m%y},,,{mode}")


def test_speed_and_course_over_ground_are_enu_velocities(tmp_path):
    """Course 90 deg at 1 kn is 1852/3600 m/s east; 36 km/h at 180 deg is 10 m/s south;
    speed 0 with an empty course is (0, 0); the up component is not measured (NaN); a VTG
    takes the UTC time of the sentence before it; what is not a measurement is counted."""
    truth = _truth()
    lines = [
        _sentence("GNVTG,45.0,T,,M,2.0,N,3.704,K,A"),  # 1: no UTC time before it: untimed
        _rmc_velocity(0, "A", "1.0", "90.0", "A"),  # 2: kept
        _gga(0, truth),
        _sentence("GNVTG,90.0,T,,M,1.0,N,1.852,K,A"),  # 4: the RMC's epoch again: duplicate
        _gga(1, truth),
        _sentence("GNVTG,180.0,T,,M,,N,36.0,K,D"),  # 6: km/h only: kept at epoch 1
        _rmc_velocity(2, "A", "0.0", "", "A"),  # 7: stationary: kept
        _gga(2, truth),
        _rmc_velocity(3, "A", "0.004", "", "A"),  # below the heading threshold: no course
        _gga(3, truth),
        _rmc_velocity(4, "V", "1.0", "90.0", "N"),  # invalid
        _sentence("GNVTG,,T,,M,,N,,K,N"),  # invalid (u-blox without a fix)
        _gga(4, truth),
        _sentence("GNVTG,30.0,T,,M,1.0,N,1.852,K,E"),  # dead reckoning
        _rmc_velocity(5, "A", "", "", "A"),  # empty speed
        _gga(5, truth),
        _sentence("GPGGA,235946.50,,,,,0,00,99.99,,,,,,"),  # no fix: the clock is lost
        _sentence("GNVTG,30.0,T,,M,1.0,N,1.852,K,A"),  # untimed
    ]
    with pytest.warns(UserWarning) as record:
        log = read_nmea(_write(tmp_path, lines))
    text = " ".join(str(w.message) for w in record)
    np.testing.assert_array_equal(log.velocity_t, truth["t"][:3])
    np.testing.assert_array_equal(log.velocity_lines, [2, 6, 7])
    assert log.velocity_enu[0, 0] == 1852 / 3600 and abs(log.velocity_enu[0, 1]) < 1e-16
    np.testing.assert_allclose(log.velocity_enu[1, :2], [0.0, -10.0], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(log.velocity_enu[2, :2], [0.0, 0.0])
    assert np.isnan(log.velocity_enu[:, 2]).all()
    expected = {
        "velocity_kept": 3,
        "velocity_untimed": 2,
        "velocity_same_epoch": 1,
        "velocity_duplicate": 0,
        "velocity_no_course": 1,
        "velocity_invalid": 2,
        "velocity_mode_not_kept": 1,
        "velocity_empty": 1,
    }
    assert {name: log.counts[name] for name in expected} == expected
    for name, count in expected.items():
        warned = count and name not in ("velocity_kept", "velocity_same_epoch")
        assert (f"{name} {count}" in text) == bool(warned), name

    velocity = log.to_gnss_velocity(t0=START_UNIX)
    assert velocity.velocity.dtype == torch.float64 and velocity.velocity.shape == (1, 3, 3)
    np.testing.assert_array_equal(velocity.t[0].numpy(), [0.5, 1.5, 2.5])
    np.testing.assert_array_equal(velocity.velocity[0].numpy(), log.velocity_enu)
    assert torch.isnan(velocity.sigma).all() and velocity.mask.all()


@pytest.mark.parametrize(("knots", "course"), [("0.5", "10.0"), ("12.345", "271.75"), ("3", "0")])
def test_rmc_and_vtg_speed_and_course_equal_pynmea2(tmp_path, knots, course):
    pynmea2 = pytest.importorskip("pynmea2")
    truth = _truth()
    rmc = _rmc_velocity(0, "A", knots, course, "R")
    vtg = _sentence(f"GPVTG,{course},T,,M,{knots},N,,K,F")
    zda = _sentence("GPZDA,235940.50,18,10,2021,00,00")
    for line in (rmc, vtg):
        log = read_nmea(_write(tmp_path, [zda, _gga(0, truth), line]))
        msg = pynmea2.parse(line, check=True)
        if line is rmc:
            speed_kn, course_deg = float(msg.spd_over_grnd), float(msg.true_course)
        else:
            speed_kn, course_deg = float(msg.spd_over_grnd_kts), float(msg.true_track)
        speed, heading = speed_kn * 1852 / 3600, math.radians(course_deg)
        np.testing.assert_allclose(
            log.velocity_enu[0, :2],
            [speed * math.sin(heading), speed * math.cos(heading)],
            rtol=1e-15,
            atol=1e-15,
        )


def test_velocities_on_the_receive_clock(tmp_path):
    """time='receive': each velocity has its own line's stamp; an RMC and a VTG of one epoch
    (two stamps) are one velocity; auto falls back to UTC when a velocity line has none."""
    truth = _truth()
    lines = [
        f"100.00,{_gga(0, truth)}",
        f"100.01,{_rmc_velocity(0, 'A', '1.0', '0.0', 'A')}",
        f"100.02,{_sentence('GNVTG,0.0,T,,M,1.0,N,1.852,K,A')}",
        f"101.00,{_gga(1, truth)}",
        f"101.02,{_sentence('GNVTG,0.0,T,,M,2.0,N,3.704,K,A')}",
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an RMC and a VTG of one epoch: nothing to warn of
        log = read_nmea(_write(tmp_path, lines))
    assert log.time_source == "receive"
    np.testing.assert_array_equal(log.t, [100.0, 101.0])
    np.testing.assert_array_equal(log.velocity_t, [100.01, 101.02])
    np.testing.assert_array_equal(log.velocity_enu[:, 1], [KNOT_MPS, 2.0 * 1852 / 3600])
    assert log.counts["velocity_same_epoch"] == 1 and log.counts["velocity_duplicate"] == 0

    lines[4] = lines[4].split(",", 1)[1]  # the last VTG without its stamp
    path = _write(tmp_path, lines)
    utc = read_nmea(path)
    assert utc.time_source == "utc"
    np.testing.assert_array_equal(utc.velocity_t, utc.t)
    with pytest.raises(DataError) as err:
        read_nmea(path, time="receive")
    assert (err.value.line, err.value.field) == (5, "receive_time")


@pytest.mark.parametrize(
    ("sentence", "field"),
    [
        ("GNRMC,235940.50,X,4900.000,N,00824.000,E,0.5,10.0,181021,,,A", "status"),
        ("GNRMC,235940.50,A,4900.000,N,00824.000,E,0.5,10.0,181021,,,Q", "mode"),
        ("GNRMC,235940.50,A,4900.000,N,00824.000,E,-0.5,10.0,181021,,,A", "speed_knots"),
        ("GNRMC,235940.50,A,4900.000,N,00824.000,E,0.5,1O.0,181021,,,A", "course"),
        ("GNRMC,235940.50,A,4900.000,N,00824.000,E,0.5,360.5,181021,,,A", "course"),
        ("GNRMC,2359x0.50,A,4900.000,N,00824.000,E,0.5,10.0,,,,A", "utc_time"),
        ("GNVTG,10.0,M,,M,0.5,N,0.9,K,A", "course_unit"),
        ("GNVTG,10.0,T,,M,0.5,K,0.9,K,A", "speed_knots_unit"),
        ("GNVTG,10.0,T,,M,0.5,N,0.9,N,A", "speed_kmh_unit"),
        ("GNVTG,10.0,T,,M,,N,1e3,K,A", "speed_kmh"),
        ("GNVTG,-1.0,T,,M,0.5,N,0.9,K,A", "course"),
        ("GNVTG,10.0,T,,M,0.5,N,0.9,K,Z", "mode"),
    ],
)
def test_malformed_velocity_sentences_name_line_and_field(tmp_path, sentence, field):
    lines = [_gga(0, _truth()), _sentence(sentence)]
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, lines))
    assert (err.value.line, err.value.field) == (2, field)
    with pytest.raises(DataError):  # and without its checksum
        read_nmea(_write(tmp_path, [lines[0], lines[1].split("*")[0]]))


def test_cli_writes_gnss_velocity_csv_unless_told_not_to(generated, tmp_path, capsys):
    path = generated[0]
    out = tmp_path / "run" / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(out), "--t0", str(START_UNIX)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    velocity_csv = out.parent / "gnss_velocity.csv"
    assert summary["velocities"] == 7 and summary["velocity_out"] == str(velocity_csv)
    assert velocity_csv.read_text().splitlines()[0] == "t,vx,vy,vz"
    (out.parent / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.81\n1,0,0,0,0,0,9.81\n"
    )
    seq = read_native(out.parent)
    with pytest.warns(UserWarning):
        expected = read_nmea(path).to_gnss_velocity(t0=START_UNIX)
    np.testing.assert_array_equal(seq.gnss_velocity.t.numpy(), expected.t.numpy())
    np.testing.assert_array_equal(seq.gnss_velocity.velocity.numpy(), expected.velocity.numpy())
    assert torch.isnan(seq.gnss_velocity.sigma).all()

    # --no-velocity writes none, and names a file of an earlier conversion left there
    assert main(["nmea", str(path), "--out", str(out), "--no-velocity"]) == 0
    captured = capsys.readouterr()
    assert f"{velocity_csv} (not from this conversion) is left as it is" in captured.err
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["velocity_out"] is None and summary["velocities"] == 7
    other = tmp_path / "other" / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(other), "--no-velocity"]) == 0
    assert not (other.parent / "gnss_velocity.csv").exists()
    capsys.readouterr()
    # a log without RMC / VTG speeds writes no velocity table
    plain = _write(tmp_path, [_gga(k, _truth()) for k in range(3)] + [_rmc(2)])
    bare = tmp_path / "bare" / "gnss.csv"
    assert main(["nmea", str(plain), "--out", str(bare)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["velocities"] == 1


def test_hdt_and_ths_headings_take_the_epoch_of_the_time_before_them(tmp_path):
    """HDT and THS degrees true -> rad in [0, 2 pi) at the UTC time read before them (as VTG);
    one heading per epoch; THS modes other than A, empty fields and untimed ones counted."""
    truth = _truth()
    lines = [
        _sentence("GNHDT,45.0,T"),  # 1: no UTC time before it: untimed
        _gga(0, truth),
        _sentence("GNHDT,90.0,T"),  # 3: kept at epoch 0
        _sentence("GNTHS,91.0,A"),  # 4: epoch 0 again: same epoch, not warned
        _gga(1, truth),
        _sentence("GNTHS,359.5,A"),  # 6: kept at epoch 1
        _gga(2, truth),
        _sentence("GNTHS,10.0,E"),  # dead reckoning
        _sentence("GNTHS,12.0,M"),  # manual input
        _sentence("GNTHS,,V"),  # not valid
        _sentence("GNHDT,,T"),  # empty: no heading this epoch
        _sentence("GPHDT,360.0,T"),  # 12: kept at epoch 2, as 0 rad
        _sentence("GPGGA,235943.50,,,,,0,00,99.99,,,,,,"),  # no fix: the clock is lost
        _sentence("GNHDT,5.0,T"),  # untimed
        _rmc(3),
    ]
    with pytest.warns(UserWarning) as record:
        log = read_nmea(_write(tmp_path, lines))
    text = " ".join(str(w.message) for w in record)
    np.testing.assert_array_equal(log.heading_t, truth["t"][:3])
    np.testing.assert_array_equal(log.heading_lines, [3, 6, 12])
    np.testing.assert_allclose(
        log.heading_rad, [math.pi / 2, math.radians(359.5), 0.0], rtol=0, atol=1e-15
    )
    expected = {
        "heading_kept": 3,
        "heading_untimed": 2,
        "heading_same_epoch": 1,
        "heading_duplicate": 0,
        "heading_mode_not_kept": 2,
        "heading_invalid": 1,
        "heading_empty": 1,
        "HDT": 5,
        "THS": 5,
    }
    assert {name: log.counts[name] for name in expected} == expected
    for name, count in expected.items():
        warned = (
            count
            and name.startswith("heading")
            and name
            not in (
                "heading_kept",
                "heading_same_epoch",
            )
        )
        assert (f"{name} {count}" in text) == bool(warned), name
    assert "other sentences" not in text  # HDT and THS are read
    assert log.velocity_t.size == 1 and len(log) == 3  # the rest of the log is unchanged

    heading = log.to_gnss_heading(t0=START_UNIX)
    assert heading.heading.dtype == torch.float64 and heading.heading.shape == (1, 3)
    np.testing.assert_array_equal(heading.t[0].numpy(), [0.5, 1.5, 2.5])
    np.testing.assert_array_equal(heading.heading[0].numpy(), log.heading_rad)
    assert torch.isnan(heading.sigma).all() and heading.mask.all()


@pytest.mark.parametrize("degrees", ["0.5", "123.456", "271.75"])
def test_hdt_heading_equals_pynmea2(tmp_path, degrees):
    pynmea2 = pytest.importorskip("pynmea2")
    hdt = _sentence(f"GPHDT,{degrees},T")
    log = read_nmea(
        _write(tmp_path, [_sentence("GPZDA,235940.50,18,10,2021,00,00"), _gga(0, _truth()), hdt])
    )
    expected = math.radians(float(pynmea2.parse(hdt, check=True).heading))
    assert log.heading_rad.tolist() == [expected]


def test_headings_on_the_receive_clock(tmp_path):
    """time='receive': each heading has its own line's stamp; auto falls back to UTC when a
    heading line has none, and time='receive' then names it."""
    truth = _truth()
    lines = [
        f"100.00,{_gga(0, truth)}",
        f"100.02,{_sentence('GNHDT,10.0,T')}",
        f"101.00,{_gga(1, truth)}",
        f"101.03,{_sentence('GNTHS,20.0,A')}",
    ]
    log = read_nmea(_write(tmp_path, lines))
    assert log.time_source == "receive"
    np.testing.assert_array_equal(log.heading_t, [100.02, 101.03])
    lines[3] = lines[3].split(",", 1)[1]  # the THS without its stamp
    path = _write(tmp_path, lines)
    with pytest.warns(UserWarning, match="no RMC or ZDA date"):
        utc = read_nmea(path)
    assert utc.time_source == "utc"
    np.testing.assert_array_equal(utc.heading_t, utc.t)
    with pytest.raises(DataError) as err:
        read_nmea(path, time="receive")
    assert (err.value.line, err.value.field) == (4, "receive_time")


@pytest.mark.parametrize(
    ("sentence", "field"),
    [
        ("GNHDT,10.0,M", "heading_unit"),
        ("GNHDT,1O.0,T", "heading"),
        ("GNHDT,-1.0,T", "heading"),
        ("GNTHS,360.5,A", "heading"),
        ("GNTHS,10.0,Q", "mode"),
        ("GNTHS,10.0", "mode"),
    ],
)
def test_malformed_heading_sentences_name_line_and_field(tmp_path, sentence, field):
    lines = [_gga(0, _truth()), _sentence(sentence)]
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, lines))
    assert (err.value.line, err.value.field) == (2, field)


def test_cli_writes_gnss_heading_csv_unless_told_not_to(tmp_path, capsys):
    truth = _truth()
    lines = []
    for k in range(4):
        lines += [_gga(k, truth), _sentence(f"GNHDT,{10.0 * k + 5.0},T")]
    path = _write(tmp_path, [*lines, _rmc(3)])
    out = tmp_path / "run" / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(out), "--t0", str(START_UNIX)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    heading_csv = out.parent / "gnss_heading.csv"
    assert summary["headings"] == 4 and summary["heading_out"] == str(heading_csv)
    assert heading_csv.read_text().splitlines()[0] == "t,heading"
    (out.parent / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.81\n1,0,0,0,0,0,9.81\n"
    )
    heading = read_native(out.parent).gnss_heading
    np.testing.assert_array_equal(heading.t[0].numpy(), [0.5, 1.5, 2.5, 3.5])
    np.testing.assert_allclose(
        heading.heading[0].numpy(), np.radians([5.0, 15.0, 25.0, 35.0]), rtol=0, atol=1e-15
    )
    assert torch.isnan(heading.sigma).all()
    # --no-heading writes none, and names a file of an earlier conversion left there
    assert main(["nmea", str(path), "--out", str(out), "--no-heading"]) == 0
    captured = capsys.readouterr()
    assert f"{heading_csv} (not from this conversion) is left as it is" in captured.err
    assert json.loads(captured.out.strip().splitlines()[-1])["heading_out"] is None
    other = tmp_path / "other" / "gnss.csv"
    assert main(["nmea", str(path), "--out", str(other), "--no-heading"]) == 0
    assert not (other.parent / "gnss_heading.csv").exists()
    # a log without HDT / THS writes no heading table
    plain = _write(tmp_path, [_gga(k, truth) for k in range(3)], name="plain.nmea")
    bare = tmp_path / "bare" / "gnss.csv"
    assert main(["nmea", str(plain), "--out", str(bare)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["headings"] == 0 and summary["heading_out"] is None
    assert not (bare.parent / "gnss_heading.csv").exists()


def test_fuzzer_hdt_without_any_field_is_an_empty_heading(tmp_path):
    """Fuzzer finds: ``$GNHDT`` with its fields dropped raised IndexError."""
    truth = _truth()
    with pytest.warns(UserWarning, match="heading_empty 1"):
        log = read_nmea(_write(tmp_path, [_gga(0, truth), _sentence("GNHDT")]))
    assert log.heading_t.size == 0 and log.counts["HDT"] == 1
    with pytest.raises(DataError) as err:
        read_nmea(_write(tmp_path, [_gga(0, truth), _sentence("GNTHS")]))
    assert (err.value.line, err.value.field) == (2, "mode")
