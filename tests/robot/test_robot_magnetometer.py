"""A magnetometer in a robot YAML: ``type: magnetometer`` reads ``sensor_msgs/MagneticField``
into the body axes with the URDF mount's rotation, and its options reach EskfConfig
(``declination_deg`` in rad, ``sigma_uT``, the sensor-frame hard and soft iron turned into
the body axes); errors name file, line and key.

The mount (URDF rpy [pi, 0, pi/2]) is R = Rz(pi/2) Rx(pi) = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]
(sensor [a, b, c] -> body [b, a, -c]); expected values below are written out from it.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io import DataError
from msf_torch.io.rosbag import BagLayout, read_rosbag, write_rosbag
from msf_torch.io.tum import read_tum
from msf_torch.robot.config import load_robot_config
from msf_torch.sensors.magnetometer import corrected_field
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import ImuSamples, Magnetometer, Sequence

ORIGIN_NS = 1_650_000_000_000_000_000
HARD_IRON = [12.0, -7.5, 30.0]  # uT, the sensor's axes
SOFT_IRON = [1.1, 0.05, -0.03, 0.02, 0.95, 0.04, 0.01, -0.02, 1.03]  # row-major, sensor axes
MOUNT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

URDF = """<robot name="rover">
  <link name="base_link"/><link name="mag_link"/>
  <joint name="mag_joint" type="fixed"><parent link="base_link"/><child link="mag_link"/>
    <origin xyz="0.2 -0.1 0.4" rpy="3.141592653589793 0 1.5707963267948966"/></joint>
</robot>
"""

ROBOT = f"""\
frames: {{urdf: rover.urdf}}
time: {{origin_ns: {ORIGIN_NS}}}
sensors:
  imu: {{type: imu, topic: /imu, frame: base_link}}
  mag:
    type: magnetometer
    topic: /imu/mag
    frame: mag_link
    declination_deg: 3.5
    hard_iron_uT: {HARD_IRON}
    soft_iron: {SOFT_IRON}
    sigma_uT: 0.4
"""


def _line_of(text: str, fragment: str) -> int:
    return next(i for i, row in enumerate(text.splitlines(), 1) if fragment in row)


def _readings(count: int = 30) -> Sequence:
    """A still IMU and ``count`` raw readings (uT, NaN sigma): the magnetometer's own
    axes when written without frames."""
    gen = torch.Generator().manual_seed(3)
    t = torch.arange(100, dtype=torch.float64)[None] * 0.01
    imu = ImuSamples(
        t=t,
        gyro=torch.zeros(1, 100, 3, dtype=torch.float64),
        accel=torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64).expand(1, 100, 3).clone(),
        mask=torch.ones(1, 100, dtype=torch.bool),
    )
    mag = Magnetometer(
        t=t[:, :count] * 3.0,
        field=40.0 * torch.randn(1, count, 3, generator=gen, dtype=torch.float64),
        sigma=torch.full((1, count), float("nan"), dtype=torch.float64),
        mask=torch.ones(1, count, dtype=torch.bool),
    )
    return Sequence(names=["run"], imu=imu, magnetometer=mag)


def test_mounted_magnetometer_options_reach_the_config(tmp_path: Path) -> None:
    """Readings m (sensor axes) come out as R m; EskfConfig gets the declination in rad,
    sigma_uT, hard iron R b = [b_y, b_x, -b_z] and soft iron R W R^T, so that the
    estimator's correction of the body-frame readings is the sensor-frame correction
    turned into the body: W_b (R m - b_b) = R W (m - b)."""
    (tmp_path / "rover.urdf").write_text(URDF)
    path = tmp_path / "robot.yaml"
    path.write_text(ROBOT)
    robot = load_robot_config(path)
    raw = _readings()
    plain = BagLayout(sensors=robot.layout.sensors)  # no frames: the readings as they are
    bag = write_rosbag(raw, tmp_path / "run", plain, time_origin_ns=ORIGIN_NS)
    seq = read_rosbag(bag, robot.layout)
    m = raw.magnetometer.field[0].numpy()
    body = seq.magnetometer.field[0].numpy()
    np.testing.assert_allclose(body, np.stack((m[:, 1], m[:, 0], -m[:, 2]), 1), rtol=1e-12)
    assert torch.isnan(seq.magnetometer.sigma).all()
    cfg = robot.eskf_config(seq.meta)
    assert cfg.magnetometer_declination_rad == pytest.approx(math.radians(3.5), abs=1e-15)
    assert cfg.magnetometer_sigma_uT == 0.4
    np.testing.assert_allclose(cfg.magnetometer_hard_iron_uT, [-7.5, 12.0, -30.0], atol=1e-12)
    w = np.array(SOFT_IRON).reshape(3, 3)
    np.testing.assert_allclose(
        np.array(cfg.magnetometer_soft_iron).reshape(3, 3), MOUNT @ w @ MOUNT.T, atol=1e-12
    )
    estimator = corrected_field(
        seq.magnetometer.field[0],
        torch.tensor(cfg.magnetometer_hard_iron_uT, dtype=torch.float64),
        torch.tensor(cfg.magnetometer_soft_iron, dtype=torch.float64).reshape(3, 3),
    ).numpy()
    in_sensor = (m - np.array(HARD_IRON)) @ w.T  # W (m - b), the sensor's axes
    np.testing.assert_allclose(estimator, in_sensor @ MOUNT.T, rtol=1e-12, atol=1e-10)
    derived = robot.summary()["derived"]
    np.testing.assert_allclose(
        derived["magnetometer_hard_iron_uT"], [-7.5, 12.0, -30.0], atol=1e-12
    )
    assert derived["magnetometer_declination_rad"] == pytest.approx(math.radians(3.5))


def test_without_frames_the_options_pass_as_written(tmp_path: Path) -> None:
    """No frames: the sensor's axes are the body's; an option left out keeps the
    estimator's value; use_message_covariance reaches the sensor."""
    text = (
        "sensors:\n"
        "  imu: {type: imu, topic: /imu}\n"
        "  mag: {type: magnetometer, topic: /mag, hard_iron_uT: [1, 2, 3],\n"
        "        use_message_covariance: false}\n"
        "estimator: {magnetometer_declination_rad: -0.1}\n"
    )
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    robot = load_robot_config(path)
    assert robot.layout.sensor("magnetometer").use_message_covariance is False
    cfg = robot.eskf_config({})
    assert cfg.magnetometer_hard_iron_uT == [1.0, 2.0, 3.0]
    assert cfg.magnetometer_declination_rad == -0.1
    assert cfg.magnetometer_soft_iron == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    assert cfg.calibrate_magnetometer_declination is False


def test_calibrate_declination_switch(tmp_path: Path) -> None:
    """calibrate_declination: true sets calibrate_magnetometer_declination; setting that
    key in estimator as well is an error naming both places."""
    text = (
        "sensors:\n"
        "  imu: {type: imu, topic: /imu}\n"
        "  mag: {type: magnetometer, topic: /mag, declination_deg: 10,\n"
        "        calibrate_declination: true}\n"
    )
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    cfg = load_robot_config(path).eskf_config({})
    assert cfg.calibrate_magnetometer_declination is True
    assert cfg.magnetometer_declination_rad == pytest.approx(math.radians(10.0))
    path.write_text(text + "estimator: {calibrate_magnetometer_declination: true}\n")
    with pytest.raises(Exception, match="calibrate_magnetometer_declination"):
        load_robot_config(path).eskf_config({})


@pytest.mark.parametrize(
    ("old", "new", "key", "line_of", "message"),
    [
        (
            "declination_deg: 3.5",
            "declination_deg: 190",
            "sensors.mag.declination_deg",
            "declination_deg",
            "must lie in [-180, 180] deg",
        ),
        (
            f"hard_iron_uT: {HARD_IRON}",
            "hard_iron_uT: [1, 2]",
            "sensors.mag.hard_iron_uT",
            "hard_iron_uT",
            "must be a list of 3 numbers",
        ),
        (
            f"soft_iron: {SOFT_IRON}",
            "soft_iron: [1, 0, 0, 0, 1, 0, 0, 0, -1]",
            "sensors.mag.soft_iron",
            "soft_iron",
            "has determinant -1",
        ),
        (
            f"soft_iron: {SOFT_IRON}",
            "soft_iron: [1, 0, 0, 0, 1, 0]",
            "sensors.mag.soft_iron",
            "soft_iron",
            "must be a list of 9 numbers",
        ),
        (
            "sigma_uT: 0.4",
            "sigma_uT: 0",
            "sensors.mag.sigma_uT",
            "sigma_uT",
            "must be a positive finite number",
        ),
        (
            "sigma_uT: 0.4",
            "fuse: [x]",
            "sensors.mag.fuse",
            "fuse",
            "unknown key",
        ),
        # set in two places
        (
            "time: {",
            "estimator: {magnetometer_hard_iron_uT: [0, 0, 0]}\ntime: {",
            "estimator.magnetometer_hard_iron_uT",
            "magnetometer_hard_iron_uT",
            "is also given by sensors.mag.hard_iron_uT",
        ),
    ],
)
def test_errors_name_the_key_and_line(
    tmp_path: Path, old: str, new: str, key: str, line_of: str, message: str
) -> None:
    assert old in ROBOT
    text = ROBOT.replace(old, new, 1)
    (tmp_path / "rover.urdf").write_text(URDF)
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(DataError) as caught:
        load_robot_config(path)
    err = caught.value
    assert err.field == key, str(err)
    assert message in err.problem, str(err)
    assert err.line == _line_of(text, line_of), str(err)


def _yaw_errors(tum: Path, truth) -> torch.Tensor:
    """|yaw error| (E,) rad of a TUM trajectory against the simulated truth."""
    estimate = read_tum(tum)
    t = estimate.t[0]
    j = torch.searchsorted(truth.t[0], t - 1e-6).clamp(max=truth.t.shape[1] - 1)
    assert float((truth.t[0, j] - t).abs().max()) < 1e-5
    rotation = quat_to_matrix(estimate.quaternion[0])
    return so3.log(truth.rotation[0, j].mT @ rotation)[:, 2].abs()


def test_msf_run_fuses_a_mounted_magnetometer(tmp_path: Path, capsys) -> None:
    """A 30 s simulated drive (hard iron b and soft iron S in the body frame, declination
    0.2 rad) written as a rosbag2 with the magnetometer mounted as in URDF: the YAML gives
    the calibration in the sensor's axes (b_s = R^T b, W_s = R^T S^-1 R) and
    ``msf run BAG --topics ROBOT.yaml`` fuses every reading, yaw error 0.0014 rad median
    (measured; 0.013 with the magnetometer disabled). The body-frame values given as if
    they were the sensor's diverge (measured: yaw 0.92 rad median, three resets)."""
    hard = np.array([10.0, -20.0, 15.0])
    distortion = np.array([[1.08, 0.04, 0.0], [0.04, 0.93, 0.03], [0.0, 0.03, 1.02]])
    config = SimConfig(
        duration_s=30.0,
        magnetometer=True,
        magnetometer_declination_rad=0.2,
        magnetometer_hard_iron_uT=tuple(hard),
        magnetometer_distortion=tuple(distortion.reshape(9)),
    )
    run = simulate_run(config, 11)
    seq = run.sequence
    seq = dataclasses.replace(
        seq,
        **{
            name: dataclasses.replace(s, t=torch.round(s.t * 1e9) / 1e9)
            for name, s in seq.streams().items()
        },
    )
    (tmp_path / "rover.urdf").write_text(URDF)
    soft = np.linalg.inv(distortion)

    def robot(name: str, hard_iron: np.ndarray, soft_iron: np.ndarray, extra: str = "") -> Path:
        text = (
            f"frames: {{urdf: rover.urdf}}\n"
            f"time: {{origin_ns: {ORIGIN_NS}}}\n"
            "sensors:\n"
            "  imu: {type: imu, topic: /imu, frame: base_link}\n"
            "  gps: {type: gnss, topic: /fix, frame: base_link, origin: [47.37, 8.54, 410.0]}\n"
            "  wheels: {type: wheels, topic: /joint_states, frame: base_link, left_joints: left,\n"
            "           right_joints: right, wheel_radius_m: 0.15}\n"
            f"  mag: {{type: magnetometer, topic: /mag, frame: mag_link,{extra}\n"
            f"        declination_deg: {math.degrees(0.2)},\n"
            f"        hard_iron_uT: {hard_iron.tolist()},\n"
            f"        soft_iron: {soft_iron.reshape(9).tolist()}}}\n"
        )
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        return path

    robots = {
        "sensor": robot("sensor", MOUNT.T @ hard, MOUNT.T @ soft @ MOUNT),
        "body": robot("body", hard, soft),
        "off": robot("off", MOUNT.T @ hard, MOUNT.T @ soft @ MOUNT, " enabled: false,"),
    }
    layout = load_robot_config(robots["sensor"]).layout
    bag = write_rosbag(
        seq, tmp_path / "run", layout, time_origin_ns=ORIGIN_NS, gnss_origin=layout.gnss_origin
    )
    runs = {}
    errors = {}
    for name, path in robots.items():
        out = tmp_path / name
        args = ["run", str(bag), "--topics", str(path), "--out", str(out)]
        assert main([*args, "--no-plot", "--no-learned", "--progress", "off"]) == 0
        captured = capsys.readouterr()
        summary = json.loads(captured.out.strip().splitlines()[-1])
        runs[name] = (summary, _yaw_errors(out / "trajectory.tum", run.truth))
        errors[name] = captured.err
    summary, yaw = runs["sensor"]
    counts = summary["measurements"]["magnetometer"]
    # estimator.magnetometer_rate_hz 2: one in 25 of the 50-Hz readings over 30 s (the
    # first second's readings cannot yet be judged against the gyro)
    assert counts["present"] == counts["accepted"] > 50, counts
    assert float(yaw.median()) < 0.008, yaw
    assert "magnetometer" not in runs["off"][0]["measurements"]
    assert float(runs["off"][1].median()) > 2.0 * float(yaw.median())
    # the body-frame values given as the sensor's: the compass disagrees with the GNSS
    # track, so the initial yaw keeps the track's (a warning), and the wrongly corrected
    # field's magnitude swings, so most readings are left out as disturbed (a warning): the
    # run is as good as without the magnetometer, not 0.9 rad off as before the initial
    # heading check (14c7d45)
    body = runs["body"][0]
    assert body["magnetometer_disturbed"] > 0.5 * body["magnetometer_readings"], body
    assert "the initial yaw keeps the other heading" in errors["body"]
    assert "magnetometer readings are left out as disturbed" in errors["body"]
    assert float(runs["body"][1].median()) < 1.5 * float(runs["off"][1].median())


def test_magcal_reads_a_bag_in_the_body_axes(tmp_path: Path, capsys) -> None:
    """``msf magcal BAG --topics ROBOT.yaml``: readings of a sensor turned every way,
    written in the mounted sensor's axes with a hard iron ``b`` there, come back in the body
    axes, so the fitted hard iron is ``R b`` (the front end's body-frame key) and the
    soft iron the identity."""
    (tmp_path / "rover.urdf").write_text(URDF)
    path = tmp_path / "robot.yaml"
    path.write_text(ROBOT)
    robot = load_robot_config(path)
    gen = torch.Generator().manual_seed(5)
    count = 400
    attitudes = so3.exp(2.0 * torch.randn(count, 3, generator=gen, dtype=torch.float64))
    earth = torch.tensor([20.0, 5.0, -42.0], dtype=torch.float64)
    sensor = (attitudes.mT @ earth) + torch.tensor(HARD_IRON, dtype=torch.float64)
    raw = _readings()
    mag = Magnetometer(
        t=torch.arange(count, dtype=torch.float64)[None] * 0.002,
        field=(sensor @ torch.as_tensor(MOUNT).T)[None],  # what the reader gives: R m
        sigma=torch.full((1, count), float("nan"), dtype=torch.float64),
        mask=torch.ones(1, count, dtype=torch.bool),
    )
    raw = dataclasses.replace(raw, magnetometer=mag)
    bag = write_rosbag(raw, tmp_path / "run", robot.layout, time_origin_ns=ORIGIN_NS)
    assert main(["magcal", str(bag), "--topics", str(path), "--out", str(tmp_path / "m.yaml")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    np.testing.assert_allclose(summary["hard_iron_uT"], MOUNT @ np.array(HARD_IRON), atol=1e-6)
    np.testing.assert_allclose(summary["soft_iron"], np.eye(3).reshape(-1), atol=1e-6)
    assert summary["field_uT"] == pytest.approx(float(earth.norm()), rel=1e-9)
