"""Encoder counts -> wheel speeds: the mean rate between readings in closed form, 16-bit
counters that wrap, quantisation within one count, and ``msf encoders`` writing a native
``wheel.csv``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.io.encoders import read_encoder_counts, wheel_speeds_from_angles
from msf_torch.io.errors import DataError
from msf_torch.io.native import read_native

COUNTS_PER_REV = 2048.0
RADIUS = (0.1, 0.105)


def _angles(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wheel angles (rad): a robot speeding up, then turning."""
    left = 20.0 * t + 2.0 * np.sin(0.7 * t)
    right = 22.0 * t + 1.5 * (1.0 - np.cos(0.4 * t))
    return left, right


def _rates(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return 20.0 + 1.4 * np.cos(0.7 * t), 22.0 + 0.6 * np.sin(0.4 * t)


def _log(path: Path, t: np.ndarray, left, right, header="t,left_ticks,right_ticks") -> Path:
    rows = "".join(
        f"{float(a)!r},{float(b)!r},{float(c)!r}\n" for a, b, c in zip(t, left, right, strict=True)
    )
    path.write_text(header + "\n" + rows)
    return path


@pytest.fixture()
def readings():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.015, 0.025, 2000))
    left, right = _angles(t)
    return t, left * COUNTS_PER_REV / (2 * math.pi), right * COUNTS_PER_REV / (2 * math.pi)


def test_speeds_are_the_mean_rates_at_midpoints(tmp_path, readings) -> None:
    t, left, right = readings
    log = read_encoder_counts(_log(tmp_path / "ticks.csv", t, left, right))
    wheel = log.wheel_speeds((COUNTS_PER_REV, COUNTS_PER_REV), RADIUS)
    middle = 0.5 * (t[1:] + t[:-1])
    np.testing.assert_allclose(wheel.t[0].numpy(), middle, rtol=0, atol=1e-12)
    angle_l, angle_r = _angles(t)
    np.testing.assert_allclose(
        wheel.left_speed[0].numpy(), RADIUS[0] * np.diff(angle_l) / np.diff(t), rtol=1e-9
    )
    # the mean rate is the midpoint rate to second order: dt^2 / 24 of the angle's third
    # derivative (here at most 2 * 0.7^3 rad/s^3)
    rate_l, rate_r = _rates(middle)
    bound = np.diff(t).max() ** 2 / 24 * 2 * 0.7**3 * RADIUS[0]
    assert np.abs(wheel.left_speed[0].numpy() - RADIUS[0] * rate_l).max() < 1.01 * bound
    assert np.abs(wheel.right_speed[0].numpy() - RADIUS[1] * rate_r).max() < 1e-5


def test_wrapping_counters_and_whole_ticks(tmp_path, readings) -> None:
    t, left, right = readings
    ticks_l, ticks_r = np.floor(left), np.floor(right)  # what an encoder reports
    wrapped = _log(tmp_path / "ticks16.csv", t, ticks_l % 65536, ticks_r % 65536)
    log = read_encoder_counts(wrapped, rollover=65536)
    expected = (int(ticks_l[-1] // 65536), int(ticks_r[-1] // 65536))
    assert (log.counts["rollovers"]["left"], log.counts["rollovers"]["right"]) == expected
    assert min(expected) >= 3  # the counters wrapped (measured 3 and 4 times)
    np.testing.assert_array_equal(log.left - log.left[0], ticks_l - ticks_l[0])
    wheel = log.wheel_speeds((COUNTS_PER_REV, COUNTS_PER_REV), RADIUS)
    exact = wheel_speeds_from_angles(
        t, left * 2 * math.pi / COUNTS_PER_REV, right * 2 * math.pi / COUNTS_PER_REV, RADIUS
    )
    # whole ticks: within one count per interval of the exact mean rate
    resolution = 2 * math.pi * RADIUS[0] / (COUNTS_PER_REV * np.diff(t))
    error = np.abs(wheel.left_speed[0].numpy() - exact.left_speed[0].numpy())
    assert np.all(error <= resolution * (1 + 1e-9))
    # read without the rollover, a wrap is a speed of hundreds of m/s
    raw = read_encoder_counts(wrapped).wheel_speeds((COUNTS_PER_REV,) * 2, RADIUS)
    assert float(raw.left_speed.abs().max()) > 100.0


def test_cli_writes_a_wheel_csv(tmp_path, readings, capsys) -> None:
    t, left, right = readings
    log = tmp_path / "enc.csv"
    rows = "".join(
        f"{float(a)!r},7,{int(b) % 65536},{int(c) % 65536}\n"
        for a, b, c in zip(t, left, right, strict=True)
    )
    log.write_text("stamp,battery,l,r\n" + rows)
    out = tmp_path / "run" / "wheel.csv"
    args = ["encoders", str(log), "--out", str(out), "--ticks-per-rev", "2048"]
    args += ["--radius", "0.1,0.105", "--rollover", "65536", "--columns", "stamp,l,r"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["readings"] == t.size and summary["samples"] == t.size - 1
    assert summary["counts"]["rollovers"]["left"] >= 3
    assert summary["speed_resolution_mps"][0] == pytest.approx(
        2 * math.pi * 0.1 / (2048 * np.median(np.diff(t)))
    )
    (out.parent / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.81\n50,0,0,0,0,0,9.81\n"
    )
    wheel = read_native(out.parent).wheel
    assert wheel.length == t.size - 1
    np.testing.assert_allclose(wheel.t[0].numpy(), 0.5 * (t[1:] + t[:-1]), atol=1e-12)
    assert float(wheel.left_speed.mean()) == pytest.approx(0.1 * 20.0, rel=0.02)


def test_bad_logs_name_line_and_column(tmp_path, capsys) -> None:
    path = _log(tmp_path / "a.csv", np.arange(3.0), [0, 1, 2], [0, 1, 2], header="t,left,right")
    with pytest.raises(DataError, match="no column 'left_ticks'") as err:
        read_encoder_counts(path)
    assert (err.value.line, err.value.field) == (1, "left_ticks")
    path.write_text("t,left_ticks,right_ticks\n0,1,2\n0.1,x,3\n")
    with pytest.raises(DataError, match="not a number") as err:
        read_encoder_counts(path)
    assert (err.value.line, err.value.field) == (3, "left_ticks")
    path.write_text("t,left_ticks,right_ticks\n0.2,1,2\n0.1,2,3\n")
    with pytest.raises(DataError, match="time goes backwards"):
        read_encoder_counts(path)
    log = read_encoder_counts(path, sort=True)
    assert log.counts["sorted"] == 1
    with pytest.raises(ValueError, match="counts_per_rev"):
        log.wheel_speeds((0.0, 1.0), RADIUS)
    path.write_text("t,left_ticks,right_ticks\n0.2,1,2\n0.2000000000000001,1e300,2\n")
    with pytest.raises(DataError, match="not finite"):
        read_encoder_counts(path).wheel_speeds((1e-300, 1.0), RADIUS)
    path.write_text("t,left_ticks,right_ticks\n0.2,1,2\n")
    with pytest.raises(ValueError, match="at least 2"):
        read_encoder_counts(path).wheel_speeds((1.0, 1.0), RADIUS)
    args = ["encoders", str(path), "--out", str(tmp_path), "--ticks-per-rev", "1", "--radius", "1"]
    assert main(args) == 2
    assert "is a folder" in capsys.readouterr().err
