"""Unit checks on loaded sequences (``msf_torch.io.units``): the bundled runs and the real
KITTI drive pass; the usual unit mistakes made on the bundled sample (times in ns,
accelerometer in g, gyro in deg/s on a slowly turning robot) are each caught with the
likely fix, and ``msf run`` refuses them with exit status 2."""

from __future__ import annotations

import dataclasses
import math

import pytest

from msf_torch.cli import main
from msf_torch.io import load_sequence, write_native
from msf_torch.io.errors import DataError
from msf_torch.io.units import check_units, unit_problems

SAMPLE = "datasets/sample_slip.npz"


@pytest.fixture(scope="module")
def sample():
    return load_sequence(SAMPLE)


def _imu(seq, **fields):
    return dataclasses.replace(seq, imu=dataclasses.replace(seq.imu, **fields))


@pytest.mark.parametrize("name", [SAMPLE, "datasets/sample_weather.npz"])
def test_bundled_runs_pass(name) -> None:
    assert unit_problems(load_sequence(name)) == []


def test_kitti_drive_passes() -> None:
    pytest.importorskip("gtsam")
    assert unit_problems(load_sequence("kitti-gtsam")) == []


def test_times_in_nanoseconds(sample) -> None:
    (problem,) = unit_problems(_imu(sample, t=sample.imu.t * 1e9))
    assert "nanoseconds? divide by 1e9" in problem


def test_accelerometer_in_g(sample) -> None:
    (problem,) = unit_problems(_imu(sample, accel=sample.imu.accel / 9.80665))
    assert "median |a| is 1 " in problem and "multiply by 9.80665" in problem


def test_gyro_in_degrees_per_second_on_a_slow_robot(sample) -> None:
    degrees = _imu(sample, gyro=sample.imu.gyro * 180.0 / math.pi)
    rate = degrees.imu.gyro[0, degrees.imu.mask[0]].norm(dim=-1).max()
    assert rate < 20.0  # the plain rate check cannot see it: the wheels must
    (problem,) = unit_problems(degrees)
    assert "deg/s (x 57)" in problem
    with pytest.raises(DataError, match="run.npz"):
        check_units(degrees, "run.npz")


def test_msf_run_refuses_them(sample, tmp_path, capsys) -> None:
    path = tmp_path / "ns.npz"
    write_native(_imu(sample, t=sample.imu.t * 1e9), path)
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"msf run: error: {path}: IMU samples are a median")


def test_magnetometer_in_gauss_tesla_or_nanotesla_is_caught() -> None:
    """A simulated magnetometer in uT passes (with 40 uT of hard iron too); the same
    readings in gauss, tesla or nanotesla are each caught with the factor to apply."""
    from msf_torch.sim import SimConfig, simulate_run

    run = simulate_run(SimConfig(duration_s=10.0, magnetometer=True), 2)
    seq = run.sequence

    def scaled(factor, offset=0.0):
        mag = dataclasses.replace(seq.magnetometer, field=seq.magnetometer.field * factor + offset)
        return dataclasses.replace(seq, magnetometer=mag)

    assert unit_problems(seq) == []
    assert unit_problems(scaled(1.0, 40.0)) == []
    for factor, hint in ((0.01, "gauss"), (1e-6, "tesla"), (1e3, "nanotesla")):
        problems = unit_problems(scaled(factor))
        assert len(problems) == 1 and "magnetometer" in problems[0] and hint in problems[0]
