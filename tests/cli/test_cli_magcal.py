"""``msf magcal``: a native folder of magnetometer readings with known hard and soft iron;
the fitted keys written as a front-end config; the errors a user meets."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from msf_torch.cli import main
from msf_torch.frontend.config import load_config
from msf_torch.io.native import write_native
from msf_torch.sim import SimConfig, simulate_run

WORLD_FIELD = 48.0 * np.array([0.0, np.cos(np.radians(60.0)), -np.sin(np.radians(60.0))])
HARD_IRON = np.array([21.5, -13.25, 8.0])
SOFT_IRON = np.array([[1.08, 0.04, -0.02], [0.04, 0.95, 0.03], [-0.02, 0.03, 1.0]])


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


def _folder(path, rotations: Rotation):
    """A native folder: two IMU rows and magnetometer.csv (uT) of the field seen in
    ``rotations`` through SOFT_IRON^-1 plus HARD_IRON, noiseless."""
    path.mkdir()
    (path / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.81\n0.01,0,0,0,0,0,9.81\n"
    )
    body = rotations.inv().apply(WORLD_FIELD)
    readings = body @ np.linalg.inv(SOFT_IRON).T + HARD_IRON
    rows = [",".join(map(repr, (0.05 * k, *map(float, m)))) for k, m in enumerate(readings)]
    (path / "magnetometer.csv").write_text("t,mx,my,mz\n" + "\n".join(rows) + "\n")
    return path


def test_magcal_fits_and_writes_config_keys(tmp_path, capsys):
    folder = _folder(tmp_path / "turned", Rotation.random(120, random_state=5))
    out = tmp_path / "mag.yaml"
    assert main(["magcal", str(folder), "--out", str(out)]) == 0
    summary = _last_json(capsys.readouterr().out)
    scale = np.cbrt(np.linalg.det(SOFT_IRON))  # the fit's W has det 1
    assert np.abs(np.array(summary["hard_iron_uT"]) - HARD_IRON).max() < 1e-9
    assert np.abs(np.array(summary["soft_iron"]) - (SOFT_IRON / scale).ravel()).max() < 1e-9
    assert summary["field_uT"] == pytest.approx(48.0 / scale, abs=1e-9)
    assert summary["residual_rms_uT"] < 1e-9 and summary["corrected_norm_std_uT"] < 1e-9
    assert summary["raw_norm_std_uT"] > 1.0
    assert summary["samples"] == 120 and summary["model"] == "ellipsoid"
    assert summary["model_reason"].startswith("auto: the readings are not planar (")
    assert 0.7 < summary["coverage"] <= 1.0
    assert summary["config_file"] == str(out)
    cfg = load_config(out)  # the file is a valid --config
    assert cfg.magnetometer_hard_iron_uT == summary["hard_iron_uT"]
    assert cfg.magnetometer_soft_iron == summary["soft_iron"]
    assert cfg.magnetometer_field_uT == summary["field_uT"]


def test_magcal_on_a_robot_that_only_yaws(tmp_path, capsys):
    """Default ``--model auto``: planar readings get the ellipse (exact headings); the
    ellipsoid, asked for, points at ``--model ellipse``; the sphere warns."""
    yaw = np.linspace(0.0, 2 * np.pi, 90, endpoint=False)
    rotations = Rotation.from_euler("z", yaw[:, None])
    folder = _folder(tmp_path / "yawing", rotations)
    out = tmp_path / "mag.yaml"
    assert main(["magcal", str(folder), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    summary = _last_json(captured.out)
    assert summary["model"] == "ellipse"
    assert summary["model_reason"].startswith("auto: the readings lie in one plane (")
    assert summary["hard_iron_uT"][2] == 0.0 and summary["residual_rms_uT"] < 1e-9
    assert summary["coverage"] == pytest.approx(1.0, abs=1e-9)  # 90 even headings
    cfg = load_config(out)
    assert cfg.magnetometer_soft_iron == summary["soft_iron"]
    assert "(auto: the readings lie in one plane" in out.read_text().splitlines()[0]
    # the corrected field's azimuth is the true heading (SOFT_IRON couples x / y to z)
    raw = np.loadtxt(folder / "magnetometer.csv", delimiter=",", skiprows=1)[:, 1:]
    soft = np.reshape(summary["soft_iron"], (3, 3))
    world = rotations.apply((raw - summary["hard_iron_uT"]) @ soft.T)
    assert np.abs(np.arctan2(world[:, 0], world[:, 1])).max() < 1e-9  # WORLD_FIELD: north
    assert main(["magcal", str(folder), "--model", "ellipsoid"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("msf magcal: error: the readings span too little of the sphere")
    assert err.rstrip().endswith("in the plane with --model ellipse")
    assert main(["magcal", str(folder), "--model", "sphere"]) == 0
    captured = capsys.readouterr()
    assert captured.err.startswith("msf magcal: warning: magnetometer readings lie close to one")
    summary = _last_json(captured.out)
    assert summary["model"] == "sphere" and summary["soft_iron"] == np.eye(3).ravel().tolist()
    assert summary["model_reason"] == "--model sphere" and summary["coverage"] < 1e-3


def test_magcal_auto_on_readings_neither_planar_nor_covering(tmp_path, capsys):
    """Yawing with roll and pitch within +-10 deg, noiseless: not planar, so auto tries the
    ellipsoid, which refuses; the error says why auto chose it and what to do."""
    rng = np.random.default_rng(8)
    tilt = np.radians(10.0)
    angles = np.column_stack(
        (
            rng.uniform(0, 2 * np.pi, 200),
            rng.uniform(-tilt, tilt, 200),
            rng.uniform(-tilt, tilt, 200),
        )
    )
    folder = _folder(tmp_path / "tilting", Rotation.from_euler("ZYX", angles))
    assert main(["magcal", str(folder)]) == 2
    err = capsys.readouterr().err
    assert (
        "for a robot that only yaws (one circle of directions) fit the hard and soft iron in "
        in err
    )
    assert "--model ellipse (tilts ignored), or the hard iron only with --model sphere" in err
    assert re.search(
        r"\(auto: the readings are not planar \([\d.]+ uT thick off their plane, > 2 x their "
        r"noise [\d.]+ uT\), so the ellipsoid was tried\)$",
        err.rstrip(),
    )
    assert main(["magcal", str(folder), "--model", "ellipse"]) == 0
    captured = capsys.readouterr()
    assert "uT thick off their plane, more than 2 x their noise" in captured.err
    assert _last_json(captured.out)["model"] == "ellipse"


def test_magcal_warns_on_readings_not_in_microtesla(tmp_path, capsys):
    folder = _folder(tmp_path / "gauss", Rotation.random(60, random_state=7))
    table = np.loadtxt(folder / "magnetometer.csv", delimiter=",", skiprows=1)
    table[:, 1:] /= 100.0  # written in gauss
    np.savetxt(folder / "magnetometer.csv", table, delimiter=",", header="t,mx,my,mz", comments="")
    assert main(["magcal", str(folder)]) == 0
    captured = capsys.readouterr()
    assert captured.err.startswith("msf magcal: warning: the fitted field 0.4764 uT")
    assert "1 gauss = 100 uT" in captured.err
    assert _last_json(captured.out)["field_uT"] == pytest.approx(
        0.48 / np.cbrt(np.linalg.det(SOFT_IRON))
    )


def test_magcal_without_readings(tmp_path, capsys):
    folder = _folder(tmp_path / "none", Rotation.random(20, random_state=6))
    (folder / "magnetometer.csv").unlink()
    out = tmp_path / "never.yaml"
    assert main(["magcal", str(folder), "--out", str(out)]) == 2
    assert "no magnetometer readings" in capsys.readouterr().err
    assert not out.exists()


def test_magcal_level_on_circles_over_uneven_ground(tmp_path, capsys):
    """A simulated 60-s drive of slow circles (0.25 rad/s) on 2.5-deg terrain with IMU,
    wheels and GNSS, hard iron [12, -7, 4] uT and soft iron: the ellipse (auto) takes the
    tilts' leak of the vertical field for a shifted centre (0.83 uT off in the plane);
    ``--level`` levels the readings with the front end's roll and pitch (0.20 uT)."""
    hard = np.array([12.0, -7.0, 4.0])
    config = SimConfig(
        duration_s=60.0,
        magnetometer=True,
        magnetometer_hard_iron_uT=tuple(hard),
        magnetometer_distortion=(1.05, 0.02, 0.0, 0.02, 0.96, 0.01, 0.0, 0.01, 1.0),
        mean_turn_rate_rad_s=0.25,
        turn_rate_peak_rad_s=0.05,
        terrain_slope_deg=2.5,
    )
    folder = write_native(simulate_run(config, 200).sequence, tmp_path / "circles")
    assert main(["magcal", str(folder)]) == 0
    ellipse = _last_json(capsys.readouterr().out)
    assert ellipse["model"] == "ellipse"
    assert np.linalg.norm(np.array(ellipse["hard_iron_uT"][:2]) - hard[:2]) > 0.5
    out = tmp_path / "mag.yaml"
    assert main(["magcal", str(folder), "--level", "--out", str(out)]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["model"] == "levelled"
    assert summary["model_reason"] == (
        "--level: 3001 readings levelled with the roll and pitch of the front end run "
        "without the magnetometer"
    )
    assert np.linalg.norm(np.array(summary["hard_iron_uT"][:2]) - hard[:2]) < 0.3
    assert summary["hard_iron_uT"][2] == 0.0  # b_z: not fitted (the ellipse's convention)
    assert load_config(out).magnetometer_hard_iron_uT == summary["hard_iron_uT"]
    assert "(--level: 3001 readings levelled" in out.read_text().splitlines()[0]
    assert main(["magcal", str(folder), "--level", "--model", "ellipse"]) == 2
    assert "--level fits its own model: leave out --model" in capsys.readouterr().err
    imu_only = _folder(tmp_path / "imu_only", Rotation.random(20, random_state=6))
    assert main(["magcal", str(imu_only), "--level"]) == 2
    assert "--level needs the front end's roll and pitch: IMU with GNSS and / or wheel" in (
        capsys.readouterr().err
    )
