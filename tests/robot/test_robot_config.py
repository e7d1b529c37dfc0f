"""Robot YAML: validation with errors naming file, line and key; derived estimator settings."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from msf_torch.io import DataError
from msf_torch.robot.config import is_robot_config, load_robot_config

URDF = """<robot name="rover">
  <link name="base_link"/><link name="imu_link"/><link name="gps_link"/>
  <link name="left_wheel"/><link name="right_wheel"/><link name="pan_link"/>
  <link name="camera_link"/>
  <joint name="imu_joint" type="fixed"><parent link="base_link"/><child link="imu_link"/>
    <origin xyz="0.1 0.0 0.2" rpy="0 0 0"/></joint>
  <joint name="gps_joint" type="fixed"><parent link="base_link"/><child link="gps_link"/>
    <origin xyz="-0.3 0.05 1.0" rpy="0 0 0"/></joint>
  <joint name="wheel_l" type="continuous"><parent link="base_link"/><child link="left_wheel"/>
    <origin xyz="0 0.31 0" rpy="-1.5707963267948966 0 0"/><axis xyz="0 0 1"/></joint>
  <joint name="wheel_r" type="continuous"><parent link="base_link"/><child link="right_wheel"/>
    <origin xyz="0 -0.29 0" rpy="-1.5707963267948966 0 0"/><axis xyz="0 0 1"/></joint>
  <joint name="pan" type="revolute"><parent link="base_link"/><child link="pan_link"/>
    <origin xyz="0.4 0 0.6"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="cam" type="fixed"><parent link="pan_link"/><child link="camera_link"/></joint>
</robot>
"""

ROBOT = """\
robot:
  name: rover
frames:
  urdf: rover.urdf
  body: base_link
  transforms:
    - {parent: gps_link, child: antenna, xyz: [0, 0, 0.1], rpy: [0, 0, 0]}
  joints:
    topic: /joint_states
    values: {pan: 0.25}
time:
  origin_ns: first
sensors:
  imu:
    type: imu
    topic: /imu/data
    frame: imu_link
  gps:
    type: gnss
    topic: /gps/fix
    frame: antenna
    origin: [49.0, 8.4, 110.0]
    fuse: [x, y]
  wheels:
    type: wheels
    topic: /wheel_states
    frame: base_link
    left_joints: wheel_l
    right_joints: [wheel_r]
    wheel_radius_m: [0.15, 0.151]
    fuse: [speed, yaw_rate]
  vo:
    type: pose
    topic: /vo
    frame: camera_link
    sigma: [0.1, 0.1, 0.1, 0.01, 0.01, 0.01]
  camera:
    type: image
    topic: /camera/image_raw
    enabled: false
estimator:
  gnss_sigma_m: [0.8, 0.8, 1.5]
  gate_probability: 0.999
smoother:
  keyframe_distance_m: 5.0
"""


def _write(folder: Path, text: str, urdf: bool = True) -> Path:
    if urdf:
        (folder / "rover.urdf").write_text(URDF)
    path = folder / "robot.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def test_full_robot_config(tmp_path: Path) -> None:
    robot = load_robot_config(_write(tmp_path, ROBOT))
    assert robot.name == "rover" and robot.disabled == ("camera",)
    layout = robot.layout
    assert [s.name for s in layout.sensors] == ["imu", "gps", "wheels", "vo", "joints"]
    gps = layout.sensor("gnss")
    assert gps.fuse == ("x", "y") and layout.gnss_origin == (49.0, 8.4, 110.0)
    wheels = layout.sensor("wheels")
    assert wheels.left_joints == ("wheel_l",) and wheels.wheel_radius_m == (0.15, 0.151)
    assert layout.time_origin_ns is None and layout.body_frame == "base_link"
    assert layout.joint_values == {"pan": 0.25}
    assert is_robot_config(tmp_path / "robot.yaml")
    # derived settings: the URDF wheel joints are 0.31 + 0.29 m apart; lever arms come from
    # the extrinsics the reader computed (here written by hand: base axes, IMU origin)
    meta = {
        "extrinsics": {
            "gps": [[1, 0, 0, -0.4], [0, 1, 0, 0.05], [0, 0, 1, 0.9], [0, 0, 0, 1]],
            "wheels": [[1, 0, 0, -0.1], [0, 1, 0, 0], [0, 0, 1, -0.2], [0, 0, 0, 1]],
        }
    }
    cfg = robot.eskf_config(meta, {"slip_detection": False})
    assert math.isclose(cfg.wheel_track_m, 0.6, abs_tol=1e-15)
    assert cfg.gnss_lever_arm_m == [-0.4, 0.05, 0.9]
    assert cfg.wheel_lever_arm_m == [-0.1, 0.0, -0.2]
    assert cfg.wheel_yaw_rate_update is True and cfg.slip_detection is False
    assert cfg.gnss_sigma_m == [0.8, 0.8, 1.5] and cfg.gate_probability == 0.999
    summary = robot.summary()
    np.testing.assert_allclose(summary["extrinsics_in_body"]["gps"]["xyz"], [-0.3, 0.05, 1.1])
    derived = summary["derived"]
    assert derived.pop("wheel_track_m") == cfg.wheel_track_m and derived.pop(
        "wheel_yaw_rate_update"
    )
    # the lever arms the run will use, from the YAML alone: from the IMU (0.1, 0, 0.2) in
    # base_link to the antenna (-0.3, 0.05, 1.0 + 0.1) and to base_link's origin (wheels)
    assert derived.keys() == {"gnss_lever_arm_m", "wheel_lever_arm_m"}
    np.testing.assert_allclose(derived["gnss_lever_arm_m"], [-0.4, 0.05, 0.9], atol=1e-15)
    np.testing.assert_allclose(derived["wheel_lever_arm_m"], [-0.1, 0.0, -0.2], atol=1e-15)
    assert "vo" not in summary["extrinsics_in_body"]  # it moves with the pan joint


def test_a_velocity_antenna_alone_gives_the_gnss_lever_arm(tmp_path: Path) -> None:
    """A receiver whose velocity topic is fused without its fixes: the antenna's lever arm
    still comes from the URDF, in the run's config and in ``msf config check``'s summary."""
    text = ROBOT.replace(
        "    type: gnss\n    topic: /gps/fix\n    frame: antenna\n"
        "    origin: [49.0, 8.4, 110.0]\n    fuse: [x, y]\n",
        "    type: gnss_velocity\n    topic: /gps/fix_velocity\n    frame: antenna\n",
    )
    assert "gnss_velocity" in text
    robot = load_robot_config(_write(tmp_path, text))
    derived = robot.summary()["derived"]
    np.testing.assert_allclose(derived["gnss_lever_arm_m"], [-0.4, 0.05, 0.9], atol=1e-15)


def test_minimal_topic_map(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        """\
        sensors:
          imu: {type: imu, topic: /imu}
          odom: {type: wheels, topic: /odom}
        """,
        urdf=False,
    )
    robot = load_robot_config(path)
    assert robot.frames is None and robot.name == "robot"
    cfg = robot.eskf_config({"extrinsics": {}})
    assert cfg.wheel_lever_arm_m == [0.0, 0.0, 0.0] and cfg.wheel_yaw_rate_update is False


def _line_of(text: str, needle: str) -> int:
    lines = textwrap.dedent(text).splitlines()
    return next(i for i, line in enumerate(lines, 1) if needle in line)


@pytest.mark.parametrize(
    ("old", "new", "key", "line_of", "message"),
    [
        ("robot:\n", "robots:\n", "robots", "robots:", "unknown key"),
        (
            "    fuse: [x, y]\n",
            "    fuse: [x, q]\n",
            "sensors.gps.fuse[1]",
            "fuse: [x, q]",
            "unknown component",
        ),
        (
            "    origin: [49.0, 8.4, 110.0]\n",
            "    origin: [95.0, 8.4, 110.0]\n",
            "sensors.gps.origin",
            "origin:",
            "latitude",
        ),
        (
            "    origin: [49.0, 8.4, 110.0]\n",
            "    origin: [49.0, 8.4]\n",
            "sensors.gps.origin",
            "origin:",
            "list of 3 numbers",
        ),
        (
            "    type: image\n",
            "    type: camera\n",
            "sensors.camera.type",
            "type: camera",
            "must be one of",
        ),
        (
            "    wheel_radius_m: [0.15, 0.151]\n",
            "    wheel_radius_m: -0.1\n",
            "sensors.wheels.wheel_radius_m",
            "wheel_radius_m",
            "positive",
        ),
        (
            "    right_joints: [wheel_r]\n",
            "",
            "sensors.wheels.right_joints",
            "  wheels:",
            "missing",
        ),
        (
            "    frame: camera_link\n",
            "    frame: camera\n",
            "sensors.vo.frame",
            "frame: camera",
            "unknown frame 'camera'",
        ),
        (
            "    sigma: [0.1, 0.1, 0.1, 0.01, 0.01, 0.01]\n",
            "    sigma: [0.1, 0.1, 0.1, 0.01, 0.01, 0]\n",
            "sensors.vo.sigma[5]",
            "sigma:",
            "positive",
        ),
        (
            "    sigma: [0.1, 0.1, 0.1, 0.01, 0.01, 0.01]\n",
            "    fuse: [x]\n",
            "sensors.vo.fuse",
            "fuse: [x]",
            "role poses",
        ),
        (
            "  gate_probability: 0.999\n",
            "  gate_probability: 1.5\n",
            "estimator.gate_probability",
            "gate_probability",
            "(0, 1]",
        ),
        (
            "  gate_probability: 0.999\n",
            "  gate_prob: 0.9\n",
            "estimator.gate_prob",
            "gate_prob",
            "unknown key",
        ),
        (
            "  gate_probability: 0.999\n",
            "  gnss_lever_arm_m: [0, 0, 1]\n",
            "estimator.gnss_lever_arm_m",
            "gnss_lever_arm_m",
            "set it in one place",
        ),
        (
            "  gate_probability: 0.999\n",
            "  wheel_yaw_rate_update: true\n",
            "estimator.wheel_yaw_rate_update",
            "wheel_yaw_rate_update",
            "set it in one place",
        ),
        (
            "    values: {pan: 0.25}\n",
            "    values: {tilt: 0.25}\n",
            "frames.joints.values.tilt",
            "values:",
            "not a movable joint",
        ),
        (
            "  body: base_link\n",
            "  body: chassis\n",
            "frames.body",
            "body: chassis",
            "unknown frame",
        ),
        (
            "xyz: [0, 0, 0.1], rpy: [0, 0, 0]}",
            "xyz: [0, 0, 0.1]}",
            "frames.transforms[0]",
            "antenna",
            "exactly one of rpy",
        ),
        (
            "  urdf: rover.urdf\n",
            "  urdf: missing.urdf\n",
            "frames.urdf",
            "urdf:",
            "cannot read the URDF",
        ),
        ("  origin_ns: first\n", "  origin_ns: soon\n", "time.origin_ns", "origin_ns", "integer"),
        ("    topic: /imu/data\n", "", "sensors.imu.topic", "  imu:", "missing"),
        ("    type: imu\n", "    type: gnss\n", "sensors", "sensors:", "exactly one imu"),
        (
            "  vo:\n",
            "  vo:\n    stamp_offset: 1\n",
            "sensors.vo.stamp_offset",
            "stamp_offset",
            "unknown key",
        ),
        # estimator values of the wrong type or sign
        (
            "  gnss_sigma_m: [0.8, 0.8, 1.5]\n",
            "  gnss_sigma_m: [-0.8, 0.8, 1.5]\n",
            "estimator.gnss_sigma_m",
            "gnss_sigma_m",
            "must be above 0",
        ),
        (
            "  gnss_sigma_m: [0.8, 0.8, 1.5]\n",
            "  gnss_sigma_m: [0.8, a, 1.5]\n",
            "estimator.gnss_sigma_m",
            "gnss_sigma_m",
            "list of finite numbers",
        ),
        (
            "  gnss_sigma_m: [0.8, 0.8, 1.5]\n",
            "  gnss_sigma_m: [.nan, 0.8, 1.5]\n",
            "estimator.gnss_sigma_m",
            "gnss_sigma_m",
            "list of finite numbers",
        ),
        (
            "  gate_probability: 0.999\n",
            "  gate_probability: high\n",
            "estimator.gate_probability",
            "gate_probability",
            "must be a finite number",
        ),
        (
            "  gate_probability: 0.999\n",
            "  slip_detection: 3\n",
            "estimator.slip_detection",
            "slip_detection",
            "true or false",
        ),
        (
            "  gate_probability: 0.999\n",
            "  gyro_bias_rw_density: -1.0e-6\n",
            "estimator.gyro_bias_rw_density",
            "gyro_bias_rw_density",
            "must not be negative",
        ),
        (
            "  gate_probability: 0.999\n",
            "  init_yaw_sigma_rad: 0\n",
            "estimator.init_yaw_sigma_rad",
            "init_yaw_sigma_rad",
            "must be above 0",
        ),
        # a sensor given twice: YAML would silently keep the second only
        (
            "estimator:\n",
            "  imu: {type: imu, topic: /imu2}\nestimator:\n",
            "sensors.imu",
            "topic: /imu2",
            "given twice (also on line 14)",
        ),
        # a static transform below a misspelt parent: the antenna hangs in a tree of its own
        (
            "{parent: gps_link, child: antenna",
            "{parent: gps_lnk, child: antenna",
            "sensors.gps.frame",
            "frame: antenna",
            "its tree starts at 'gps_lnk', the body's at 'base_link'",
        ),
        (
            "xyz: [0, 0, 0.1], rpy: [0, 0, 0]}",
            "xyz: [0, 0, 0.1], quaternion_xyzw: [0, 0, 1, 1]}",
            "frames.transforms[0].quaternion_xyzw",
            "antenna",
            "unit quaternion [x, y, z, w] (ROS order), its norm is 1.41421",
        ),
        (
            "xyz: [0, 0, 0.1], rpy: [0, 0, 0]}",
            "xyz: [0, 0, 0.1], rpy: [0, 0, 90]}",
            "frames.transforms[0].rpy[2]",
            "antenna",
            "in radians",
        ),
        (
            "  keyframe_distance_m: 5.0\n",
            "  keyframe_distance_m: -5.0\n",
            "smoother.keyframe_distance_m",
            "keyframe_distance_m",
            "must be a positive number",
        ),
        (
            "  keyframe_distance_m: 5.0\n",
            "  keyframe_distnce_m: 5.0\n",
            "smoother.keyframe_distnce_m",
            "keyframe_distnce_m",
            "unknown key",
        ),
    ],
)
def test_errors_name_the_key_and_line(
    tmp_path: Path, old: str, new: str, key: str, line_of: str, message: str
) -> None:
    assert old in ROBOT
    text = ROBOT.replace(old, new, 1)
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as caught:
        load_robot_config(path)
    err = caught.value
    assert err.field == key, str(err)
    assert message in err.problem, str(err)
    assert err.line == _line_of(text, line_of), str(err)
    assert str(err).startswith(f"{path}:{err.line}: field '{key}'")


def test_wheel_frame_must_share_the_body_axes(tmp_path: Path) -> None:
    robot = load_robot_config(_write(tmp_path, ROBOT))
    turned = [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(DataError, match="rotated against the body axes") as caught:
        robot.eskf_config({"extrinsics": {"wheels": turned}})
    assert caught.value.field == "sensors.wheels.frame"


def test_not_yaml_and_not_a_mapping(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("sensors: [unclosed\n")
    with pytest.raises(DataError, match="not valid YAML"):
        load_robot_config(path)
    path.write_text("- just\n- a list\n")
    with pytest.raises(DataError, match="must be a mapping"):
        load_robot_config(path)
    assert not is_robot_config(path)
