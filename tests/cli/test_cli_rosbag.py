"""``msf run BAG --topics ROBOT.yaml``, ``--export kitti,rosbag2`` and ``msf config check``.

A simulated run with a GNSS antenna 1 m above and behind the IMU goes into a rosbag2 whose
robot YAML places the antenna with a URDF; the bag run must give the trajectory of the
native run with the same lever arm set by hand.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.frontend.config import EskfConfig
from msf_torch.io import read_kitti_poses, read_native, write_native
from msf_torch.io.rosbag import write_rosbag
from msf_torch.io.tum import read_tum
from msf_torch.robot.config import load_robot_config
from msf_torch.sim import SimConfig, simulate_run

LEVER = (-0.25, 0.1, 0.95)
ORIGIN_NS = 1_650_000_000_000_000_000

URDF = f"""<robot name="rover">
  <link name="base_link"/><link name="gps_link"/>
  <joint name="gps_joint" type="fixed"><parent link="base_link"/><child link="gps_link"/>
    <origin xyz="{LEVER[0]} {LEVER[1]} {LEVER[2]}" rpy="0 0 0"/></joint>
</robot>
"""

ROBOT = f"""\
robot: {{name: rover}}
frames:
  urdf: rover.urdf
time: {{origin_ns: {ORIGIN_NS}}}
sensors:
  imu: {{type: imu, topic: /imu, frame: base_link}}
  gps: {{type: gnss, topic: /fix, frame: gps_link, origin: [47.37, 8.54, 410.0]}}
  wheels:
    type: wheels
    topic: /joint_states
    frame: base_link
    left_joints: left
    right_joints: right
    wheel_radius_m: 0.15
  truth: {{type: pose, topic: /truth, role: ground_truth, frame: base_link}}
"""


@pytest.fixture(scope="module")
def robot_run(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("robot")
    config = SimConfig(duration_s=12.0, slip_episodes=0, gnss_lever_arm_m=LEVER)
    seq = simulate_run(config, 4).sequence
    streams = {
        name: dataclasses.replace(s, t=torch.round(s.t * 1e9) / 1e9)
        for name, s in seq.streams().items()
    }
    seq = dataclasses.replace(seq, **streams)
    native = write_native(seq, folder / "run.npz")
    (folder / "rover.urdf").write_text(URDF)
    robot_yaml = folder / "robot.yaml"
    robot_yaml.write_text(ROBOT)
    robot = load_robot_config(robot_yaml)
    bag = write_rosbag(
        read_native(native),
        folder / "run",
        robot.layout,
        version=2,
        time_origin_ns=ORIGIN_NS,
        gnss_origin=robot.layout.gnss_origin,
    )
    # the native run's settings: the bag's (defaults) with the lever arm set by hand
    defaults = EskfConfig()
    native_cfg = folder / "native.yaml"
    keys = ("gyro_noise_density", "accel_noise_density")
    keys += ("gyro_bias_rw_density", "accel_bias_rw_density", "wheel_track_m")
    lines = [f"{k}: {getattr(defaults, k)!r}" for k in keys]
    lines.append(f"gnss_lever_arm_m: {list(LEVER)}")
    native_cfg.write_text("\n".join(lines) + "\n")
    return {"native": native, "bag": bag, "robot": robot_yaml, "native_cfg": native_cfg}


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_bag_run_equals_native_run_and_exports(robot_run, tmp_path, capsys) -> None:
    out_bag, out_native = tmp_path / "bag", tmp_path / "native"
    common = ["--no-plot", "--no-learned", "--progress", "off"]
    args = ["run", str(robot_run["bag"]), "--topics", str(robot_run["robot"])]
    assert main([*args, "--out", str(out_bag), "--export", "kitti,rosbag2", *common]) == 0
    summary = _last_json(capsys)
    assert summary["source"] == str(robot_run["bag"]) and summary["ate_rmse_m"] < 1.0
    args = ["run", str(robot_run["native"]), "--config", str(robot_run["native_cfg"])]
    assert main([*args, "--out", str(out_native), *common]) == 0
    native_summary = _last_json(capsys)
    bag_traj = read_tum(out_bag / "trajectory.tum")
    native_traj = read_tum(out_native / "trajectory.tum")
    assert torch.equal(bag_traj.t, native_traj.t)
    assert (bag_traj.position - native_traj.position).abs().max() < 1e-9
    assert (bag_traj.quaternion - native_traj.quaternion).abs().max() < 1e-9
    assert summary["measurements"] == native_summary["measurements"]
    # KITTI export: the same poses, times in their own file
    kitti = read_kitti_poses(out_bag / "trajectory.kitti", out_bag / "trajectory_times.txt")
    assert torch.equal(kitti.t, bag_traj.t)
    torch.testing.assert_close(kitti.position, bag_traj.position, rtol=0, atol=1e-12)
    torch.testing.assert_close(kitti.quaternion, bag_traj.quaternion, rtol=0, atol=1e-12)
    # rosbag2 export, read by evo: stamps on the bag's clock, poses as in the TUM file
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    with Reader(out_bag / "trajectory_rosbag2") as reader:
        odom = file_interface.read_bag_trajectory(reader, "/msf/odometry")
    np.testing.assert_allclose(odom.timestamps - ORIGIN_NS / 1e9, bag_traj.t[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(odom.positions_xyz, bag_traj.position[0].numpy(), atol=1e-12)


def test_bag_needs_its_topics(robot_run, tmp_path, capsys) -> None:
    assert main(["run", str(robot_run["bag"]), "--out", str(tmp_path), "--no-plot"]) == 2
    assert "--topics" in capsys.readouterr().err


def test_config_check(robot_run, tmp_path, capsys) -> None:
    assert main(["config", "check", str(robot_run["robot"])]) == 0
    report = _last_json(capsys)
    assert report["ok"] and report["kind"] == "robot" and report["body_frame"] == "base_link"
    assert report["extrinsics_in_body"]["gps"]["xyz"] == list(LEVER)
    assert report["derived"] == {"gnss_lever_arm_m": list(LEVER), "wheel_lever_arm_m": [0, 0, 0]}
    assert main(["config", "check", str(robot_run["native_cfg"])]) == 0
    report = _last_json(capsys)
    assert report["kind"] == "frontend" and report["estimator"] == {"gnss_lever_arm_m": list(LEVER)}
    bad = tmp_path / "bad.yaml"
    text = ROBOT.replace("wheel_radius_m: 0.15", "wheel_radius_m: fast")
    bad.write_text(text)
    (tmp_path / "rover.urdf").write_text(URDF)
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    line = next(i for i, row in enumerate(text.splitlines(), 1) if "wheel_radius_m" in row)
    assert f"{bad}:{line}: field 'sensors.wheels.wheel_radius_m': must be a number" in err


def test_config_value_errors_name_file_and_key(robot_run, tmp_path, capsys) -> None:
    """A negative sigma or a value of the wrong type: exit status 2, one line naming the
    file, the line and the key."""
    frontend = tmp_path / "frontend.yaml"
    frontend.write_text("gate_probability: 0.99\ngnss_sigma_m: [0.5, -0.5, 1.0]\n")
    assert main(["config", "check", str(frontend)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"msf config: error: {frontend}:2: field 'gnss_sigma_m': config key 'gnss_sigma_m' is a "
        "standard deviation: "
        "it must be above 0, got [0.5, -0.5, 1.0]"
    )
    args = ["run", str(robot_run["native"]), "--out", str(tmp_path / "o"), "--no-plot"]
    frontend.write_text("zupt: 'yes'\n")
    assert main([*args, "--config", str(frontend)]) == 2
    assert (
        f"{frontend}:1: field 'zupt': config key 'zupt' must be true or false, got 'yes'"
        in capsys.readouterr().err
    )
    smoother = tmp_path / "smoother.yaml"
    smoother.write_text("smoother:\n  window_size: 1\n")
    assert main(["config", "check", str(smoother)]) == 2
    assert (
        f"{smoother}:2: field 'smoother.window_size': config key 'smoother.window_size'"
        in capsys.readouterr().err
    )
    robot = tmp_path / "robot.yaml"
    (tmp_path / "rover.urdf").write_text(URDF)
    robot.write_text(ROBOT + "estimator:\n  wheel_speed_sigma_mps: -0.05\n")
    assert main(["config", "check", str(robot)]) == 2
    line = len(ROBOT.splitlines()) + 2
    assert (
        f"{robot}:{line}: field 'estimator.wheel_speed_sigma_mps': config key "
        "'wheel_speed_sigma_mps' is a standard deviation: it must be above 0, got -0.05"
    ) in capsys.readouterr().err


def test_config_check_of_a_robot_yaml_with_sensors_misspelt(tmp_path, capsys) -> None:
    """Without ``sensors`` the file used to be taken for a front-end config, and the error
    named its first robot key ('unknown config key 'robot'') instead of the typo."""
    bad = tmp_path / "robot.yaml"
    (tmp_path / "rover.urdf").write_text(URDF)
    text = ROBOT.replace("sensors:", "sensor:")
    bad.write_text(text)
    assert main(["config", "check", str(bad)]) == 2
    line = next(i for i, row in enumerate(text.splitlines(), 1) if row == "sensor:")
    assert f"{bad}:{line}: field 'sensor': unknown key" in capsys.readouterr().err


URDF_IMU = f"""<robot name="rover">
  <link name="base_link"/><link name="gps_link"/><link name="imu_link"/>
  <joint name="gps_joint" type="fixed"><parent link="base_link"/><child link="gps_link"/>
    <origin xyz="{LEVER[0]} {LEVER[1]} {LEVER[2]}" rpy="0 0 0"/></joint>
  <joint name="imu_joint" type="fixed"><parent link="base_link"/><child link="imu_link"/>
    <origin xyz="0 0 0" rpy="0 0 1.5707963267948966"/></joint>
</robot>
"""


def _odometry(folder: Path) -> dict[str, np.ndarray]:
    """Pose, covariances and twist of every message of an exported odometry bag."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(folder) as reader:
        messages = [store.deserialize_cdr(raw, conn.msgtype) for conn, _, raw in reader.messages()]

    def xyz(v) -> list[float]:
        return [v.x, v.y, v.z]

    return {
        "child_frame_id": np.array([m.child_frame_id for m in messages]),
        "position": np.array([xyz(m.pose.pose.position) for m in messages]),
        "xyzw": np.array(
            [[*xyz(m.pose.pose.orientation), m.pose.pose.orientation.w] for m in messages]
        ),
        "linear": np.array([xyz(m.twist.twist.linear) for m in messages]),
        "angular": np.array([xyz(m.twist.twist.angular) for m in messages]),
        "pose_cov": np.array([np.array(m.pose.covariance).reshape(6, 6) for m in messages]),
        "twist_cov": np.array([np.array(m.twist.covariance).reshape(6, 6) for m in messages]),
    }


def _twist_against_poses(odom: dict[str, np.ndarray], t: np.ndarray) -> tuple[float, float]:
    """Median |twist - finite difference of the exported poses| (mid-interval, the mean of
    the two ends against ``Log(R_k^T R_k+1) / dt`` and ``R_k^T dp / dt``): rad/s, m/s."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_quat(odom["xyzw"])
    dt = np.diff(t)[:, None]
    rate_fd = (rotation[:-1].inv() * rotation[1:]).as_rotvec() / dt
    velocity_fd = rotation[:-1].apply(np.diff(odom["position"], axis=0) / dt, inverse=True)
    mid_rate = 0.5 * (odom["angular"][:-1] + odom["angular"][1:])
    mid_velocity = 0.5 * (odom["linear"][:-1] + odom["linear"][1:])
    return (
        float(np.median(np.abs(mid_rate - rate_fd))),
        float(np.median(np.abs(mid_velocity - velocity_fd))),
    )


def test_rosbag2_export_is_the_imu_frame_when_the_body_frame_is_another(tmp_path, capsys):
    # the IMU turned 90 deg in yaw on base_link: the estimate is base_link's axes at the
    # IMU's origin, so the export is the IMU frame's pose (R_world_imu = R R_body_imu),
    # labelled imu_link, and tf relates it to base_link
    (tmp_path / "rover.urdf").write_text(URDF_IMU)
    robot_yaml = tmp_path / "robot.yaml"
    text = ROBOT.replace("urdf: rover.urdf", "urdf: rover.urdf\n  body: base_link")
    robot_yaml.write_text(text.replace("frame: base_link}", "frame: imu_link}", 1))
    robot = load_robot_config(robot_yaml)
    seq = simulate_run(SimConfig(duration_s=12.0, slip_episodes=0, gnss_lever_arm_m=LEVER), 4)
    bag = write_rosbag(
        seq.sequence,
        tmp_path / "run",
        robot.layout,
        version=2,
        gnss_origin=robot.layout.gnss_origin,
    )
    out = tmp_path / "out"
    args = ["run", str(bag), "--topics", str(robot_yaml), "--out", str(out), "--no-plot"]
    assert main([*args, "--export", "rosbag2", "--no-learned", "--progress", "off"]) == 0
    capsys.readouterr()
    estimate = read_tum(out / "trajectory.tum")
    odom = _odometry(out / "trajectory_rosbag2")
    assert len(odom["position"]) == estimate.length
    assert set(odom["child_frame_id"]) == {"imu_link"}
    np.testing.assert_allclose(odom["position"], estimate.position[0].numpy(), atol=1e-12)
    from scipy.spatial.transform import Rotation

    body = Rotation.from_quat(estimate.quaternion[0].numpy()[:, [1, 2, 3, 0]])
    expected = (body * Rotation.from_euler("z", 90, degrees=True)).as_matrix()
    np.testing.assert_allclose(Rotation.from_quat(odom["xyzw"]).as_matrix(), expected, atol=1e-9)
    # the rotation covariance (about the world axes in ROS) does not depend on the label
    cov = odom["pose_cov"]
    assert np.all(np.linalg.eigvalsh(cov) > -1e-12) and cov[:, 5, 5].min() > 0

    # the twist, in imu_link's axes, against the exported poses' own finite differences
    rate_gap, velocity_gap = _twist_against_poses(odom, estimate.t[0].numpy())
    linear, angular = odom["linear"], odom["angular"]
    assert np.abs(angular[:, 2]).max() > 0.2  # the run turns (imu z = base_link z)
    assert rate_gap < 0.003
    assert velocity_gap < 0.03
    assert np.abs(linear[:, 0]).max() < 0.2 < np.abs(linear[:, 1]).max()  # forward = imu -y
    twist_cov = odom["twist_cov"]
    np.testing.assert_allclose(twist_cov, twist_cov.transpose(0, 2, 1), atol=1e-15)
    assert np.all(np.linalg.eigvalsh(twist_cov) > 0)
    one_sample = EskfConfig().gyro_noise_density ** 2 * 100.0
    assert np.diagonal(twist_cov[:, 3:, 3:], axis1=1, axis2=2).min() >= one_sample


def test_smoothed_rosbag2_export_carries_covariance_and_twist(robot_run, tmp_path, capsys):
    # --smooth full: the bag holds the smoothed poses with the smoother's marginal
    # covariances (tighter than the filter's) and a twist that matches the poses' motion
    args = ["run", str(robot_run["native"]), "--config", str(robot_run["native_cfg"])]
    common = ["--no-plot", "--no-learned", "--progress", "off", "--export", "rosbag2"]
    runs = {}
    for name, extra in (("filter", []), ("smoothed", ["--smooth", "full"])):
        assert main([*args, "--out", str(tmp_path / name), *common, *extra]) == 0
        capsys.readouterr()
        runs[name] = _odometry(tmp_path / name / "trajectory_rosbag2")
    smoothed, filtered = runs["smoothed"], runs["filter"]
    estimate = read_tum(tmp_path / "smoothed" / "trajectory.tum")
    np.testing.assert_allclose(smoothed["position"], estimate.position[0].numpy(), atol=1e-12)
    for key in ("pose_cov", "twist_cov"):
        cov = smoothed[key]
        np.testing.assert_allclose(cov, cov.transpose(0, 2, 1), atol=1e-15)
        assert np.linalg.eigvalsh(cov).min() > 0
    # same epochs (the smoother's output is at the front end's epochs)
    assert smoothed["pose_cov"].shape == filtered["pose_cov"].shape
    trace = np.trace(smoothed["pose_cov"][:, :3, :3], axis1=1, axis2=2)
    filter_trace = np.trace(filtered["pose_cov"][:, :3, :3], axis1=1, axis2=2)
    assert np.median(trace / filter_trace) < 0.8
    # twist against the exported poses' finite differences (mid-interval)
    rate_gap, velocity_gap = _twist_against_poses(smoothed, estimate.t[0].numpy())
    assert np.abs(smoothed["angular"][:, 2]).max() > 0.2  # the run turns
    assert rate_gap < 0.003
    assert velocity_gap < 0.03


def test_checkpoint_filter_settings_are_compared_with_the_robot_estimator(
    robot_run, tmp_path, capsys
) -> None:
    """For a bag, the front-end values a checkpoint's training set are compared with the
    robot YAML's ``estimator:`` section (then ``--config``): a checkpoint trained with the
    defaults is warned about the robot's gyro noise; one trained with it is not."""
    from msf_torch.learning import CovNet, CovNetConfig, NoiseApplication, save_checkpoint

    robot = tmp_path / "robot.yaml"
    robot.write_text(ROBOT + "estimator:\n  gyro_noise_density: 5.0e-3\n")
    (tmp_path / "rover.urdf").write_text(URDF)
    torch.manual_seed(0)
    net = CovNet(CovNetConfig(window_length=50, channels=4, embedding=4, hidden=8))
    common = ["run", str(robot_run["bag"]), "--topics", str(robot), "--no-plot"]
    for trained, warned in (({}, True), ({"gyro_noise_density": 5.0e-3}, False)):
        checkpoint = tmp_path / f"net{len(trained)}.pt"
        save_checkpoint(checkpoint, net, NoiseApplication(filter_settings=trained))
        out = tmp_path / f"out{len(trained)}"
        assert main([*common, "--out", str(out), "--checkpoint", str(checkpoint)]) == 0
        err = capsys.readouterr().err
        expected = "gyro_noise_density: trained with 9.9e-05, this run 0.005"
        assert (expected in err) is warned, err


def test_tune_reads_a_bag_as_the_native_run(robot_run, tmp_path, capsys) -> None:
    """``msf tune BAG --topics ROBOT.yaml`` sees what ``msf tune`` of the same run written
    natively (with the bag's settings by hand) sees: the same parameters, the same
    likelihood of the same innovations to rounding (one evaluation each: the data path,
    not the optimiser, is under test)."""
    common = ["--piece-s", "12.5", "--burn-in-s", "2", "--max-evaluations", "1"]
    common += ["--progress", "off"]
    bag = ["tune", str(robot_run["bag"]), "--topics", str(robot_run["robot"]), *common]
    out = tmp_path / "tuned.yaml"
    assert main([*bag, "--out", str(out)]) == 0
    from_bag = _last_json(capsys)
    native = ["tune", str(robot_run["native"]), "--config", str(robot_run["native_cfg"]), *common]
    assert main(native) == 0
    from_native = _last_json(capsys)
    assert from_bag["pieces"] == from_native["pieces"] == 1
    assert set(from_bag["parameters"]) == {
        "gyro_noise_density",
        "accel_noise_density",
        "wheel_speed_sigma_mps",
        "wheel_lateral_sigma_mps",
        "gnss_sigma_scale",
    }
    for key in ("nll_per_measurement_initial", "nll_per_measurement_final"):
        assert from_bag[key] == pytest.approx(from_native[key], rel=1e-9)
    assert from_bag["mean_nis"].keys() == from_native["mean_nis"].keys()
    for name, values in from_bag["mean_nis"].items():
        assert values == pytest.approx(from_native["mean_nis"][name], rel=1e-9)
    assert from_bag["accepted"] == from_native["accepted"]
    assert "gnss_sigma_scale" in out.read_text()
