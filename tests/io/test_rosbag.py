"""ROS bags through rosbags (issue 6, acceptance 1), frames, GNSS, wheels and references.

Bags are written with rosbags' own writers: by :func:`write_rosbag` from a native sequence
(acceptance 1), and message by message in the tests below, whose expected values are hand
computed (rotations, an extended-precision ECEF route for GNSS, finite-difference
Jacobians for the pose covariance).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from bag_messages import header_msg, store_for
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.io import DataError, read_native, write_native
from msf_torch.io.rosbag import (
    UNFUSED_SIGMA,
    BagLayout,
    SensorTopic,
    read_referenced_message,
    read_rosbag,
    write_odometry_rosbag2,
    write_rosbag,
)
from msf_torch.robot import FrameTree, StaticTransform
from msf_torch.sim import default_slip_config, simulate_run
from msf_torch.types import PoseMeasurements

ORIGIN_NS = 1_700_000_000_123_456_789
GNSS_ORIGIN = (49.0125, 8.4172, 115.3)
LAYOUT = BagLayout(
    sensors=(
        SensorTopic("imu", "imu", "/imu/data"),
        SensorTopic("gps", "gnss", "/gps/fix"),
        SensorTopic(
            "wheels",
            "wheels",
            "/joint_states",
            left_joints=("wheel_l",),
            right_joints=("wheel_r",),
            wheel_radius_m=(0.1, 0.1),
        ),
        SensorTopic("vo", "pose", "/vo/odom"),
        SensorTopic("truth", "pose", "/ground_truth", role="ground_truth"),
    ),
    time_origin_ns=ORIGIN_NS,
    gnss_origin=GNSS_ORIGIN,
)


def _on_ns_grid(stream):
    """The stream with times rounded to whole nanoseconds (what a bag stamp can hold)."""
    return dataclasses.replace(stream, t=torch.round(stream.t * 1e9) / 1e9)


@pytest.fixture(scope="module")
def native(tmp_path_factory) -> Path:
    """A 12 s simulated run (IMU, wheels, GNSS, truth) plus a 10 Hz pose source, as npz."""
    seq = simulate_run(default_slip_config(duration_s=12.0, slip_episodes=0), seed=5).sequence
    truth = seq.ground_truth
    pick = torch.arange(0, truth.length, 20)
    rng = torch.Generator().manual_seed(0)
    n = pick.numel()
    sigma = torch.tensor([0.02, 0.02, 0.03, 0.004, 0.004, 0.006], dtype=torch.float64)
    noise = torch.randn(1, n, 3, generator=rng, dtype=torch.float64) * 0.02
    vo = PoseMeasurements(
        t=truth.t[:, pick],
        position=truth.position[:, pick] + noise,
        quaternion=truth.quaternion[:, pick],
        covariance=torch.diag(sigma**2).expand(1, n, 6, 6).clone(),
        mask=torch.ones(1, n, dtype=torch.bool),
    )
    seq = dataclasses.replace(
        seq,
        imu=_on_ns_grid(seq.imu),
        wheel=_on_ns_grid(seq.wheel),
        gnss=_on_ns_grid(seq.gnss),
        ground_truth=_on_ns_grid(truth),
        pose_sources={"vo": _on_ns_grid(vo)},
    )
    return write_native(seq, tmp_path_factory.mktemp("native") / "run.npz")


@pytest.fixture(scope="module")
def native_result(native: Path):
    """The ESKF front end on the native file."""
    return run_eskf(read_native(native), EskfConfig())


@pytest.mark.parametrize("version", [1, 2])
def test_bag_gives_the_native_trajectory(
    native: Path, native_result, tmp_path: Path, version: int
) -> None:
    """Acceptance 1: a rosbag1 / rosbag2 with the native file's content gives the same ESKF
    trajectory as the native file, within 1e-9 (m; quaternion components)."""
    seq = read_native(native)
    bag = tmp_path / ("run.bag" if version == 1 else "run")
    write_rosbag(
        seq, bag, LAYOUT, version=version, time_origin_ns=ORIGIN_NS, gnss_origin=GNSS_ORIGIN
    )
    back = read_rosbag(bag, LAYOUT)
    assert back.meta["format"] == f"rosbag{version}"
    assert back.meta["time_origin_ns"] == ORIGIN_NS
    assert back.meta["gnss_origin"] == list(GNSS_ORIGIN)
    # the streams themselves
    assert torch.equal(back.imu.t, seq.imu.t)
    assert torch.equal(back.imu.gyro, seq.imu.gyro) and torch.equal(back.imu.accel, seq.imu.accel)
    assert torch.equal(back.wheel.t, seq.wheel.t)
    torch.testing.assert_close(back.wheel.left_speed, seq.wheel.left_speed, rtol=1e-15, atol=0)
    assert torch.equal(back.gnss.t, seq.gnss.t)
    assert (back.gnss.position - seq.gnss.position).abs().max() < 1e-9
    torch.testing.assert_close(back.gnss.sigma, seq.gnss.sigma, rtol=1e-15, atol=0)
    vo, vo_native = back.pose_sources["vo"], seq.pose_sources["vo"]
    assert torch.equal(vo.t, vo_native.t) and torch.equal(vo.position, vo_native.position)
    torch.testing.assert_close(vo.quaternion, vo_native.quaternion, rtol=0, atol=1e-15)
    torch.testing.assert_close(vo.covariance, vo_native.covariance, rtol=1e-12, atol=1e-20)
    torch.testing.assert_close(back.ground_truth.position, seq.ground_truth.position)
    # the trajectory through the ESKF front end
    want = native_result
    got = run_eskf(back, EskfConfig())
    assert torch.equal(got.t, want.t)
    assert got.present["pose:vo"].sum() == want.present["pose:vo"].sum() > 90
    assert (got.position - want.position).abs().max() < 1e-9
    rot_error = so3.log(want.rotation.mT @ got.rotation).norm(dim=-1).max()
    assert rot_error < 1e-9


# --------------------------------------------------------------------------- hand-made bags


def _write_bag(path: Path, version: int, topics: dict[str, tuple[str, list]]) -> Path:
    """``topics``: topic -> (msgtype, [(stamp_ns, message), ...])."""
    store = store_for(version)
    writer = Writer1(path) if version == 1 else Writer2(path, version=9)
    serialize = store.serialize_ros1 if version == 1 else store.serialize_cdr
    with writer:
        for topic, (msgtype, messages) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=store)
            for stamp, msg in messages:
                writer.write(conn, stamp, serialize(msg, msgtype))
    return path


def _v3(store, v):
    return store.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose_msg(store, position, rot: np.ndarray):
    q = matrix_to_quat(torch.as_tensor(rot))[[1, 2, 3, 0]].tolist()
    return store.types["geometry_msgs/msg/Pose"](
        position=store.types["geometry_msgs/msg/Point"](
            x=float(position[0]), y=float(position[1]), z=float(position[2])
        ),
        orientation=store.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _imu_msg(store, stamp, frame, gyro, accel):
    zeros = np.zeros(9)
    return store.types["sensor_msgs/msg/Imu"](
        header=header_msg(store, stamp, frame),
        orientation=store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=_v3(store, gyro),
        angular_velocity_covariance=zeros,
        linear_acceleration=_v3(store, accel),
        linear_acceleration_covariance=zeros,
    )


def _still_imu(store, t0: int, frame: str, count: int, gravity: float) -> list:
    """``count`` Imu messages at 100 Hz from ``t0`` (ns) of a still IMU: zero rate, specific
    force ``[0, 0, gravity]``; ``(stamp, message)`` pairs for :func:`_write_bag`."""
    stamps = [t0 + k * 10_000_000 for k in range(count)]
    return [(t, _imu_msg(store, t, frame, [0, 0, 0], [0, 0, gravity])) for t in stamps]


def _fix_msg(store, stamp, frame, lat, lon, alt, status=0, cov=None):
    return store.types["sensor_msgs/msg/NavSatFix"](
        header=header_msg(store, stamp, frame),
        status=store.types["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
        latitude=lat,
        longitude=lon,
        altitude=alt,
        position_covariance=np.zeros(9) if cov is None else np.diag(cov).reshape(9),
        position_covariance_type=0 if cov is None else 2,
    )


def _rot(rpy) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", rpy).as_matrix()


def _h(rot, xyz) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, xyz
    return out


IMU_T = _h(_rot([0.0, 0.0, math.pi / 2]), [0.1, 0.2, 0.3])  # T_base_imu
GPS_T = _h(np.eye(3), [-0.3, 0.0, 1.2])  # T_base_gps
CAM_T = _h(_rot([-math.pi / 2, 0.0, -math.pi / 2]), [0.5, -0.1, 0.8])  # T_base_camera
FRAMES = FrameTree.from_transforms(
    [
        StaticTransform("base_link", "imu_link", torch.as_tensor(IMU_T)),
        StaticTransform("base_link", "gps_link", torch.as_tensor(GPS_T)),
        StaticTransform("base_link", "camera_link", torch.as_tensor(CAM_T)),
    ]
)


def _ecef_longdouble(lat, lon, alt) -> np.ndarray:
    """The textbook geodetic -> ECEF in extended precision (independent of io.geodesy)."""
    a = np.longdouble(6378137.0)
    f = np.longdouble(1) / np.longdouble("298.257223563")
    e2 = f * (2 - f)
    lat = np.longdouble(lat) * np.longdouble(np.pi) / 180
    lon = np.longdouble(lon) * np.longdouble(np.pi) / 180
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    alt = np.longdouble(alt)
    return np.array(
        [
            (n + alt) * np.cos(lat) * np.cos(lon),
            (n + alt) * np.cos(lat) * np.sin(lon),
            (n * (1 - e2) + alt) * np.sin(lat),
        ]
    )


def _enu_reference(lat, lon, alt, origin) -> np.ndarray:
    d = _ecef_longdouble(lat, lon, alt) - _ecef_longdouble(*origin)
    la = np.longdouble(origin[0]) * np.longdouble(np.pi) / 180
    lo = np.longdouble(origin[1]) * np.longdouble(np.pi) / 180
    rot = np.array(
        [
            [-np.sin(lo), np.cos(lo), 0],
            [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
            [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
        ]
    )
    return (rot @ d).astype(np.float64)


def _robot_bag(path: Path, version: int) -> tuple[Path, dict]:
    """IMU (rotated frame), GNSS, wheels (JointState), camera pose with covariance, image."""
    store = store_for(version)
    t0 = 1_600_000_000_000_000_000
    gyro, accel = np.array([0.01, -0.02, 0.3]), np.array([0.2, -0.1, 9.81])
    imu = [
        (t0 + k * 10_000_000, _imu_msg(store, t0 + k * 10_000_000, "imu_link", gyro, accel))
        for k in range(50)
    ]
    fixes = [
        (
            t0 + 5_000_000,
            _fix_msg(store, t0 + 5_000_000, "gps_link", 49.0, 8.4, 110.0, cov=[0.04, 0.09, 0.25]),
        ),
        (t0 + 105_000_000, _fix_msg(store, t0 + 105_000_000, "gps_link", 49.0001, 8.4002, 113.0)),
        (
            t0 + 205_000_000,
            _fix_msg(store, t0 + 205_000_000, "gps_link", 49.0003, 8.4005, 112.0, status=-1),
        ),
    ]
    state = store.types["sensor_msgs/msg/JointState"]
    names = ["fl", "rl", "fr", "rr", "arm"]
    wheels = []
    for k in range(5):
        stamp = t0 + k * 40_000_000
        rates = np.array([10.0, 10.2, 11.0, 11.4, 0.0]) + k
        wheels.append(
            (
                stamp,
                state(
                    header=header_msg(store, stamp, "base_link"),
                    name=names,
                    position=np.zeros(5),
                    velocity=rates,
                    effort=np.zeros(0),
                ),
            )
        )
    stamp = t0 + 300_000_000
    wheels.append(
        (
            stamp,
            state(
                header=header_msg(store, stamp, "base_link"),
                name=["arm"],
                position=np.zeros(1),
                velocity=np.ones(1),
                effort=np.zeros(0),
            ),
        )
    )
    cam_world = _h(_rot([0.3, -0.2, 1.1]), [10.0, -4.0, 2.0])
    a = np.random.default_rng(2).normal(size=(6, 6))
    ros_cov = a @ a.T * 1e-3
    with_cov = store.types["geometry_msgs/msg/PoseWithCovariance"]
    pose = store.types["geometry_msgs/msg/PoseWithCovarianceStamped"]
    poses = [
        (
            t0 + 50_000_000,
            pose(
                header=header_msg(store, t0 + 50_000_000, "map"),
                pose=with_cov(
                    pose=_pose_msg(store, cam_world[:3, 3], cam_world[:3, :3]),
                    covariance=ros_cov.reshape(36),
                ),
            ),
        )
    ]
    image = store.types["sensor_msgs/msg/Image"]
    images = [
        (
            t0 + 30_000_000 + k,
            image(
                header=header_msg(store, t0 + 20_000_000 * k, "camera_link"),
                height=1,
                width=2,
                encoding="mono8",
                is_bigendian=0,
                step=2,
                data=np.array([k, 7], dtype=np.uint8),
            ),
        )
        for k in range(3)
    ]
    _write_bag(
        path,
        version,
        {
            "/imu": ("sensor_msgs/msg/Imu", imu),
            "/fix": ("sensor_msgs/msg/NavSatFix", fixes),
            "/joint_states": ("sensor_msgs/msg/JointState", wheels),
            "/camera/pose": ("geometry_msgs/msg/PoseWithCovarianceStamped", poses),
            "/camera/image": ("sensor_msgs/msg/Image", images),
        },
    )
    truth = {"t0": t0, "gyro": gyro, "accel": accel, "cam_world": cam_world, "ros_cov": ros_cov}
    return path, truth


ROBOT_LAYOUT = BagLayout(
    sensors=(
        SensorTopic("imu", "imu", "/imu"),
        SensorTopic("gps", "gnss", "/fix", fuse=("x", "y")),
        SensorTopic(
            "wheels",
            "wheels",
            "/joint_states",
            frame="base_link",
            left_joints=("fl", "rl"),
            right_joints=("fr", "rr"),
            wheel_radius_m=(0.1, 0.11),
        ),
        SensorTopic(
            "cam",
            "pose",
            "/camera/pose",
            frame="camera_link",
            role="poses",
            fuse=("x", "y", "z", "roll", "pitch"),
        ),
        SensorTopic("camera", "image", "/camera/image"),
    ),
    frames=FRAMES,
    body_frame="base_link",
)


def _sensor_to_body(cam_world: np.ndarray) -> np.ndarray:
    """T_world_E: the estimator's body (base_link axes, origin at the IMU)."""
    base_est = _h(np.eye(3), IMU_T[:3, 3])
    return cam_world @ np.linalg.inv(CAM_T) @ base_est


@pytest.mark.parametrize("version", [1, 2])
def test_robot_bag_in_the_body_frame(tmp_path: Path, version: int) -> None:
    bag, truth = _robot_bag(tmp_path / ("robot.bag" if version == 1 else "robot"), version)
    seq = read_rosbag(bag, ROBOT_LAYOUT)
    meta = seq.meta
    assert meta["time_origin_ns"] == truth["t0"]  # the earliest stamp
    assert meta["body_frame"] == "base_link" and meta["imu_frame"] == "imu_link"
    # IMU vectors turned into the base_link axes
    rot = IMU_T[:3, :3]
    np.testing.assert_allclose(seq.imu.gyro[0, 0].numpy(), rot @ truth["gyro"], atol=1e-15)
    np.testing.assert_allclose(seq.imu.accel[0, 0].numpy(), rot @ truth["accel"], atol=1e-14)
    assert seq.imu.t[0, 1].item() == 0.01
    # GNSS: the first fix is the origin; the NO_FIX one is dropped; z is not fused
    assert meta["gnss_origin"] == [49.0, 8.4, 110.0]
    assert meta["dropped_no_fix"] == {"gps": 1}
    want = _enu_reference(49.0001, 8.4002, 113.0, (49.0, 8.4, 110.0))
    np.testing.assert_allclose(seq.gnss.position[0, 1].numpy(), want, rtol=0, atol=1e-9)
    assert seq.gnss.position[0, 0].abs().max() == 0
    np.testing.assert_allclose(seq.gnss.sigma[0, 0].numpy(), [0.2, 0.3, UNFUSED_SIGMA])
    assert torch.isnan(seq.gnss.sigma[0, 1, :2]).all() and seq.gnss.sigma[0, 1, 2] == UNFUSED_SIGMA
    # lever arms of the estimator's body frame (base axes, IMU origin)
    gps_lever = np.asarray(meta["extrinsics"]["gps"])[:3, 3]
    np.testing.assert_allclose(gps_lever, GPS_T[:3, 3] - IMU_T[:3, 3], atol=1e-15)
    wheel_lever = np.asarray(meta["extrinsics"]["wheels"])
    np.testing.assert_allclose(wheel_lever[:3, 3], -IMU_T[:3, 3], atol=1e-15)
    # wheels: mean joint rate per side times that side's radius; the "arm"-only message skipped
    assert seq.wheel.length == 5 and meta["skipped_messages"] == {"wheels": 1}
    k = torch.arange(5, dtype=torch.float64)
    torch.testing.assert_close(seq.wheel.left_speed[0], (10.1 + k) * 0.1)
    torch.testing.assert_close(seq.wheel.right_speed[0], (11.2 + k) * 0.11)
    # the camera pose as a body pose
    want_pose = _sensor_to_body(truth["cam_world"])
    np.testing.assert_allclose(seq.poses.position[0, 0].numpy(), want_pose[:3, 3], atol=1e-12)
    got_rot = quat_to_matrix(seq.poses.quaternion[0, 0]).numpy()
    np.testing.assert_allclose(got_rot, want_pose[:3, :3], atol=1e-12)
    # references
    refs = meta["references"]["camera"]
    assert refs["msgtype"] == "sensor_msgs/msg/Image" and refs["frame"] == "camera_link"
    np.testing.assert_allclose(refs["t"], [0.0, 0.02, 0.04])
    image = read_referenced_message(bag, "/camera/image", refs["bag_ns"][2])
    assert list(image.data) == [2, 7]


def test_pose_covariance_follows_the_frame_change(tmp_path: Path) -> None:
    """The body pose covariance is J C J^T with J the finite-difference Jacobian of the map
    (ROS sensor-pose error: world dp, rotation about world axes) -> (body error: world dp,
    body-frame dtheta)."""
    bag, truth = _robot_bag(tmp_path / "robot", 2)
    layout = dataclasses.replace(
        ROBOT_LAYOUT,
        sensors=tuple(
            dataclasses.replace(s, fuse=None) if s.name == "cam" else s
            for s in ROBOT_LAYOUT.sensors
        ),
    )
    seq = read_rosbag(bag, layout)
    cam_world = truth["cam_world"]
    sensor_body = np.linalg.inv(CAM_T) @ _h(np.eye(3), IMU_T[:3, 3])
    body = cam_world @ sensor_body

    def exp(phi):
        return so3.exp(torch.as_tensor(phi)).numpy()

    jac = np.zeros((6, 6))
    step = 1e-6
    for k in range(6):
        pair = []
        for sign in (1, -1):
            e = np.zeros(6)
            e[k] = sign * step
            perturbed = cam_world.copy()
            perturbed[:3, 3] += e[:3]
            perturbed[:3, :3] = exp(e[3:]) @ cam_world[:3, :3]
            moved = perturbed @ sensor_body
            d_theta = so3.log(torch.as_tensor(body[:3, :3].T @ moved[:3, :3])).numpy()
            pair.append(np.r_[moved[:3, 3] - body[:3, 3], d_theta])
        jac[:, k] = (pair[0] - pair[1]) / (2 * step)
    want = jac @ truth["ros_cov"] @ jac.T
    np.testing.assert_allclose(seq.poses.covariance[0, 0].numpy(), want, rtol=1e-7, atol=1e-12)
    # fusing only some components inflates the others (yaw here) and drops their correlations
    inflated = read_rosbag(bag, ROBOT_LAYOUT).poses.covariance[0, 0].numpy()
    assert inflated[5, 5] == UNFUSED_SIGMA**2 and not inflated[5, :5].any()
    np.testing.assert_allclose(inflated[:5, :5], want[:5, :5], rtol=1e-7, atol=1e-12)


def test_pan_camera_with_joint_states(tmp_path: Path) -> None:
    """A camera on a revolute pan joint: its poses become body poses with the joint angle
    interpolated from JointState at each pose time."""
    urdf = """<robot name="pan">
      <link name="base_link"/><link name="pan_link"/><link name="camera_link"/>
      <joint name="pan" type="continuous"><parent link="base_link"/><child link="pan_link"/>
        <origin xyz="0.3 0 0.6" rpy="0 0 0"/><axis xyz="0 0 1"/></joint>
      <joint name="cam" type="fixed"><parent link="pan_link"/><child link="camera_link"/>
        <origin xyz="0.05 0 0.1" rpy="-1.5707963267948966 0 -1.5707963267948966"/></joint>
    </robot>"""
    tree = FrameTree.from_urdf(urdf)
    store = store_for(2)
    t0 = 1_000_000_000
    imu = _still_imu(store, t0, "base_link", 40, 9.8)
    state = store.types["sensor_msgs/msg/JointState"]
    # pan angle 0.5 t (t in s after t0), published at 10 Hz
    joints = [
        (
            t0 + k * 100_000_000,
            state(
                header=header_msg(store, t0 + k * 100_000_000, "base_link"),
                name=["pan"],
                position=np.array([0.05 * k]),
                velocity=np.zeros(1),
                effort=np.zeros(0),
            ),
        )
        for k in range(5)
    ]
    body_world = [_h(_rot([0.0, 0.0, 0.1 * k]), [k, 2.0 * k, 0.0]) for k in range(3)]
    pose_times = [t0 + 50_000_000, t0 + 150_000_000, t0 + 333_000_000]
    stamped = store.types["geometry_msgs/msg/PoseStamped"]
    poses = []
    for stamp, world_body in zip(pose_times, body_world, strict=True):
        angle = 0.5 * (stamp - t0) / 1e9
        base_cam = tree.transform("base_link", "camera_link", {"pan": angle}).numpy()
        cam_world = world_body @ base_cam
        poses.append(
            (
                stamp,
                stamped(
                    header=header_msg(store, stamp, "odom"),
                    pose=_pose_msg(store, cam_world[:3, 3], cam_world[:3, :3]),
                ),
            )
        )
    bag = _write_bag(
        tmp_path / "pan",
        2,
        {
            "/imu": ("sensor_msgs/msg/Imu", imu),
            "/joint_states": ("sensor_msgs/msg/JointState", joints),
            "/camera/pose": ("geometry_msgs/msg/PoseStamped", poses),
        },
    )
    layout = BagLayout(
        sensors=(
            SensorTopic("imu", "imu", "/imu"),
            SensorTopic("joints", "joints", "/joint_states"),
            SensorTopic("cam", "pose", "/camera/pose", frame="camera_link", sigma=(0.1,) * 6),
        ),
        frames=tree,
    )
    seq = read_rosbag(bag, layout)
    source = seq.pose_sources["cam"]
    for k, world_body in enumerate(body_world):
        np.testing.assert_allclose(source.position[0, k].numpy(), world_body[:3, 3], atol=1e-12)
        got = quat_to_matrix(source.quaternion[0, k]).numpy()
        np.testing.assert_allclose(got, world_body[:3, :3], atol=1e-12)
    assert "cam" not in seq.meta["extrinsics"]  # it moves: no static extrinsic
    # without the joint values the camera frame is unknown
    no_joints = dataclasses.replace(layout, sensors=(layout.sensors[0], layout.sensors[2]))
    with pytest.raises(DataError, match="moves with joint 'pan'"):
        read_rosbag(bag, no_joints)
    # a PoseStamped carries no covariance: sigma is required
    no_sigma = dataclasses.replace(
        layout, sensors=(*layout.sensors[:2], dataclasses.replace(layout.sensors[2], sigma=None))
    )
    with pytest.raises(DataError, match="sensors.cam.sigma"):
        read_rosbag(bag, no_sigma)


def test_twist_wheels_and_time_offset(tmp_path: Path) -> None:
    store = store_for(1)
    t0 = 5_000_000_000
    imu = _still_imu(store, t0, "imu", 10, 9.8)
    twist = store.types["geometry_msgs/msg/TwistStamped"]
    tw = store.types["geometry_msgs/msg/Twist"]
    twists = [
        (
            t0 + 20_000_000,
            twist(
                header=header_msg(store, t0 + 20_000_000, "base_link"),
                twist=tw(linear=_v3(store, [1.5, 0, 0]), angular=_v3(store, [0, 0, 0.4])),
            ),
        )
    ]
    bag = _write_bag(
        tmp_path / "twist.bag",
        1,
        {
            "/imu": ("sensor_msgs/msg/Imu", imu),
            "/cmd": ("geometry_msgs/msg/TwistStamped", twists),
        },
    )
    layout = BagLayout(
        sensors=(
            SensorTopic("imu", "imu", "/imu"),
            SensorTopic("wheels", "wheels", "/cmd", time_offset_s=-0.005),
        ),
        wheel_track_m=0.5,
    )
    seq = read_rosbag(bag, layout)
    assert seq.wheel.left_speed.item() == 1.5 - 0.4 * 0.25
    assert seq.wheel.right_speed.item() == 1.5 + 0.4 * 0.25
    assert seq.wheel.t.item() == pytest.approx(0.015, abs=1e-15)
    # the time origin given explicitly
    later = read_rosbag(bag, dataclasses.replace(layout, time_origin_ns=t0 - 1_000_000_000))
    assert later.imu.t[0, 0].item() == 1.0


def test_bag_errors_name_the_sensor(tmp_path: Path) -> None:
    bag, _ = _robot_bag(tmp_path / "robot", 2)
    missing = BagLayout(
        sensors=(SensorTopic("imu", "imu", "/imu"), SensorTopic("lidar", "pose", "/lo"))
    )
    with pytest.raises(DataError, match="topic '/lo' of sensor 'lidar' is not in the bag"):
        read_rosbag(bag, missing)
    wrong = BagLayout(sensors=(SensorTopic("imu", "imu", "/fix"),))
    with pytest.raises(DataError, match="carries sensor_msgs/msg/NavSatFix"):
        read_rosbag(bag, wrong)
    unknown_frame = dataclasses.replace(
        ROBOT_LAYOUT,
        frames=FrameTree.from_transforms(
            [StaticTransform("base_link", "imu_link", torch.eye(4, dtype=torch.float64))]
        ),
    )
    with pytest.raises(DataError, match="frame 'gps_link', which the robot's frames do not define"):
        read_rosbag(bag, unknown_frame)
    # the fixes' frame (from the messages) below a parent that is not linked to base_link
    detached = dataclasses.replace(
        ROBOT_LAYOUT,
        frames=FrameTree.from_transforms(
            [
                StaticTransform("base_link", "imu_link", torch.as_tensor(IMU_T)),
                StaticTransform("mast", "gps_link", torch.as_tensor(GPS_T)),
                StaticTransform("base_link", "camera_link", torch.as_tensor(CAM_T)),
            ]
        ),
    )
    with pytest.raises(
        DataError,
        match="frame 'gps_link', which is not connected to the body frame 'base_link': its "
        "tree starts at 'mast'",
    ) as caught:
        read_rosbag(bag, detached)
    assert caught.value.field == "sensors.gps.frame" and str(caught.value).startswith(str(bag))
    with pytest.raises(DataError, match="not a ROS bag"):
        read_rosbag(tmp_path, ROBOT_LAYOUT)
    with pytest.raises(ValueError, match="exactly one imu"):
        BagLayout(sensors=(SensorTopic("gps", "gnss", "/fix"),))


def test_odometry_rosbag2_reads_back_in_evo(native: Path, tmp_path: Path) -> None:
    """The output bag read by evo's own bag reader gives the trajectory back."""
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    truth = read_native(native).ground_truth
    path = write_odometry_rosbag2(truth, tmp_path / "odom", time_origin_ns=ORIGIN_NS)
    with Reader(path) as reader:
        traj = file_interface.read_bag_trajectory(reader, "/msf/odometry")
    want_t = (ORIGIN_NS + torch.round(truth.t[0] * 1e9).to(torch.int64)).numpy() / 1e9
    np.testing.assert_allclose(traj.timestamps, want_t, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(traj.positions_xyz, truth.position[0].numpy())
    np.testing.assert_allclose(traj.orientations_quat_wxyz, truth.quaternion[0].numpy(), atol=1e-15)
    # written again over the old folder: replaced, not mixed
    shorter = dataclasses.replace(truth, mask=truth.mask.clone())
    shorter.mask[0, 10:] = False
    write_odometry_rosbag2(shorter, path)
    with Reader(path) as reader:
        assert reader.message_count == 10


def test_fix_without_altitude_is_a_horizontal_fix(tmp_path: Path) -> None:
    """NavSatFix altitude NaN means "no altitude available": east and north are kept, the
    up component is not fused, and the origin's altitude comes from the first fix with one."""
    store = store_for(2)
    t0 = 1_650_000_000_000_000_000
    imu = _still_imu(store, t0, "imu", 40, 9.8)
    nan = float("nan")
    fixes = [
        (t0, _fix_msg(store, t0, "gps", 49.0, 8.4, nan)),
        (t0 + 100_000_000, _fix_msg(store, t0 + 100_000_000, "gps", 49.0001, 8.4002, 113.0)),
        (
            t0 + 200_000_000,
            _fix_msg(store, t0 + 200_000_000, "gps", 49.0003, 8.4005, nan, cov=[0.04, 0.09, 0.0]),
        ),
    ]
    bag = _write_bag(
        tmp_path / "nan_alt",
        2,
        {"/imu": ("sensor_msgs/msg/Imu", imu), "/fix": ("sensor_msgs/msg/NavSatFix", fixes)},
    )
    layout = BagLayout(
        sensors=(SensorTopic("imu", "imu", "/imu"), SensorTopic("gps", "gnss", "/fix"))
    )
    seq = read_rosbag(bag, layout)
    assert seq.meta["gnss_origin"] == [49.0, 8.4, 113.0]
    assert seq.meta["gnss_no_altitude"] == {"gps": 2}
    assert seq.gnss.length == 3
    origin = (49.0, 8.4, 113.0)
    got = seq.gnss.position[0].numpy()
    assert not got[0].any()
    np.testing.assert_allclose(got[1], _enu_reference(49.0001, 8.4002, 113.0, origin), atol=1e-9)
    # the altitude-less fix: horizontal position on the origin's height
    np.testing.assert_allclose(got[2], _enu_reference(49.0003, 8.4005, 113.0, origin), atol=1e-9)
    sigma = seq.gnss.sigma[0].numpy()
    assert sigma[0, 2] == UNFUSED_SIGMA and sigma[2, 2] == UNFUSED_SIGMA
    np.testing.assert_allclose(sigma[2, :2], [0.2, 0.3])
    assert np.isnan(sigma[1]).all()  # covariance UNKNOWN: the estimator's default


def test_odometry_without_child_frame_needs_the_sensor_frame(tmp_path: Path) -> None:
    """An Odometry's pose is that of its child_frame_id; header.frame_id is the parent. With
    the child left empty and no ``frame`` for the sensor, the reader asks for one (it used to
    take the parent frame and fail as an unknown frame)."""
    store = store_for(2)
    t0 = 1_600_000_000_000_000_000
    imu = _still_imu(store, t0, "imu_link", 30, 9.81)
    odometry = store.types["nav_msgs/msg/Odometry"]
    with_cov = store.types["geometry_msgs/msg/PoseWithCovariance"]
    twist = store.types["geometry_msgs/msg/TwistWithCovariance"](
        twist=store.types["geometry_msgs/msg/Twist"](
            linear=_v3(store, [0, 0, 0]), angular=_v3(store, [0, 0, 0])
        ),
        covariance=np.zeros(36),
    )
    poses = [
        (
            t0 + k * 100_000_000,
            odometry(
                header=header_msg(store, t0 + k * 100_000_000, "odom"),
                child_frame_id="",
                pose=with_cov(
                    pose=_pose_msg(store, [0.1 * k, 0.0, 0.0], np.eye(3)),
                    covariance=(np.eye(6) * 1e-4).reshape(36),
                ),
                twist=twist,
            ),
        )
        for k in range(3)
    ]
    bag = _write_bag(
        tmp_path / "odom_bag",
        2,
        {"/imu": ("sensor_msgs/msg/Imu", imu), "/vo": ("nav_msgs/msg/Odometry", poses)},
    )
    layout = BagLayout(
        sensors=(SensorTopic("imu", "imu", "/imu"), SensorTopic("vo", "pose", "/vo")),
        frames=FRAMES,
        body_frame="base_link",
    )
    with pytest.raises(DataError, match="empty child_frame_id .* set sensors.vo.frame") as caught:
        read_rosbag(bag, layout)
    assert caught.value.field == "sensors.vo.frame"
    named = dataclasses.replace(
        layout,
        sensors=(
            SensorTopic("imu", "imu", "/imu"),
            SensorTopic("vo", "pose", "/vo", frame="base_link"),
        ),
    )
    seq = read_rosbag(bag, named)
    assert seq.pose_sources["vo"].t.shape[-1] == 3


@pytest.mark.parametrize("version", [1, 2])
def test_wheel_joint_positions_only(tmp_path: Path, version: int) -> None:
    """A driver publishing wheel joint positions without velocities: the speeds are the mean
    rates between messages (midpoint stamps), times each side's radius."""
    store = store_for(version)
    t0 = 1_600_000_000_000_000_000
    state = store.types["sensor_msgs/msg/JointState"]
    stamps = t0 + np.cumsum([0, 40, 45, 38, 41, 40]) * 1_000_000
    t = (stamps - t0) / 1e9
    angles = {"fl": 3.0 * t + 0.5 * t**2, "rl": 3.2 * t + 0.5 * t**2, "fr": 4.0 * t - t**2}
    angles["rr"] = angles["fr"] + 0.1
    wheels = [
        (
            int(stamp),
            state(
                header=header_msg(store, int(stamp), "base_link"),
                name=list(angles),
                position=np.array([angles[j][k] for j in angles]),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            ),
        )
        for k, stamp in enumerate(stamps)
    ]
    imu = [(int(s), _imu_msg(store, int(s), "imu_link", np.zeros(3), [0, 0, 9.81])) for s in stamps]
    bag = _write_bag(
        tmp_path / ("w.bag" if version == 1 else "w"),
        version,
        {
            "/imu": ("sensor_msgs/msg/Imu", imu),
            "/joint_states": ("sensor_msgs/msg/JointState", wheels),
        },
    )
    layout = BagLayout(
        sensors=(
            SensorTopic("imu", "imu", "/imu"),
            SensorTopic(
                "wheels",
                "wheels",
                "/joint_states",
                left_joints=("fl", "rl"),
                right_joints=("fr", "rr"),
                wheel_radius_m=(0.1, 0.11),
            ),
        ),
    )
    seq = read_rosbag(bag, layout)
    np.testing.assert_allclose(seq.wheel.t[0].numpy(), 0.5 * (t[1:] + t[:-1]), atol=1e-12)
    left = 0.5 * (angles["fl"] + angles["rl"])
    right = 0.5 * (angles["fr"] + angles["rr"])
    np.testing.assert_allclose(
        seq.wheel.left_speed[0].numpy(), 0.1 * np.diff(left) / np.diff(t), rtol=1e-12
    )
    np.testing.assert_allclose(
        seq.wheel.right_speed[0].numpy(), 0.11 * np.diff(right) / np.diff(t), rtol=1e-12
    )
    # a mean rate of a quadratic angle is its rate at the midpoint, exactly
    np.testing.assert_allclose(
        seq.wheel.left_speed[0].numpy(), 0.1 * (3.1 + seq.wheel.t[0].numpy()), rtol=1e-12
    )


def _twist_cov_msg(store, stamp, frame, linear, linear_cov):
    """A u-blox style ``fix_velocity``: ENU linear velocity, covariance diagonal
    ``linear_cov`` (3 values) on the linear rows, -1 on the first angular one."""
    cov = np.zeros((6, 6))
    cov[[0, 1, 2], [0, 1, 2]] = linear_cov
    cov[3, 3] = -1.0
    twist = store.types["geometry_msgs/msg/Twist"](
        linear=_v3(store, linear), angular=_v3(store, [0.0, 0.0, 0.0])
    )
    return store.types["geometry_msgs/msg/TwistWithCovarianceStamped"](
        header=header_msg(store, stamp, frame),
        twist=store.types["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=cov.reshape(36)
        ),
    )


@pytest.mark.parametrize("version", [1, 2])
def test_gnss_velocity_from_twist_messages(tmp_path: Path, version: int) -> None:
    """TwistWithCovarianceStamped -> Sequence.gnss_velocity: the linear part as ENU m/s,
    sigma = sqrt(covariance diagonal), NaN where the diagonal is 0 or -1; a NaN up is kept as
    "not measured", a NaN east drops the message; TwistStamped has no sigma."""
    store = store_for(version)
    t0 = 1_650_000_000_000_000_000
    step = 200_000_000
    nan = float("nan")
    rows = [
        ([1.5, -0.25, 0.125], [0.0025, 0.0025, 0.0025]),  # sAcc 5 cm/s on every axis
        ([2.0, 0.5, 0.0], [0.0, 0.0, 0.0]),  # covariance unknown
        ([0.75, 1.0, nan], [0.01, 0.04, -1.0]),  # horizontal only
        ([nan, 1.0, 0.0], [0.01, 0.01, 0.01]),  # dropped
        ([-3.0, 4.0, 0.5], [0.09, 0.16, -1.0]),
    ]
    velocity = [
        (t0 + k * step, _twist_cov_msg(store, t0 + k * step, "gps_link", v, c))
        for k, (v, c) in enumerate(rows)
    ]
    plain = store.types["geometry_msgs/msg/TwistStamped"](
        header=header_msg(store, t0, "gps_link"),
        twist=store.types["geometry_msgs/msg/Twist"](
            linear=_v3(store, [0.5, 0.25, -0.125]), angular=_v3(store, [0.0, 0.0, 1.0])
        ),
    )
    bag = _write_bag(
        tmp_path / ("vel.bag" if version == 1 else "vel"),
        version,
        {
            "/imu": ("sensor_msgs/msg/Imu", _still_imu(store, t0, "imu", 120, 9.8)),
            "/fix_velocity": ("geometry_msgs/msg/TwistWithCovarianceStamped", velocity),
            "/twist": ("geometry_msgs/msg/TwistStamped", [(t0, plain)]),
        },
    )
    imu = SensorTopic("imu", "imu", "/imu")
    layout = BagLayout(
        sensors=(imu, SensorTopic("vel", "gnss_velocity", "/fix_velocity", time_offset_s=0.01))
    )
    seq = read_rosbag(bag, layout)
    vel = seq.gnss_velocity
    assert vel.velocity.dtype == torch.float64 and vel.velocity.shape == (1, 4, 3)
    np.testing.assert_allclose(vel.t[0].numpy(), [0.01, 0.21, 0.41, 0.81], rtol=0, atol=1e-12)
    want = np.array([rows[k][0] for k in (0, 1, 2, 4)])
    np.testing.assert_array_equal(vel.velocity[0].numpy(), want)
    np.testing.assert_array_equal(
        vel.sigma[0].numpy(),
        [[0.05, 0.05, 0.05], [nan, nan, nan], [0.1, 0.2, nan], [0.3, 0.4, nan]],
    )
    assert seq.meta["dropped_nonfinite"]["gnss_velocity"] == 1
    assert seq.meta["dropped_indices"]["gnss_velocity"] == [3]
    assert seq.meta["topics"]["vel"]["frame"] == "gps_link"
    # the message covariance switched off: the estimator's default everywhere
    off = BagLayout(
        sensors=(
            imu,
            SensorTopic("vel", "gnss_velocity", "/fix_velocity", use_message_covariance=False),
        )
    )
    assert torch.isnan(read_rosbag(bag, off).gnss_velocity.sigma).all()
    # TwistStamped: no covariance, the angular part ignored
    stamped = read_rosbag(
        bag, BagLayout(sensors=(imu, SensorTopic("vel", "gnss_velocity", "/twist")))
    ).gnss_velocity
    np.testing.assert_array_equal(stamped.velocity[0].numpy(), [[0.5, 0.25, -0.125]])
    assert torch.isnan(stamped.sigma).all()


def test_gnss_velocity_round_trips_through_write_rosbag(tmp_path: Path) -> None:
    from msf_torch.types import GnssVelocity

    seq = read_native(_native_folder_with_velocity(tmp_path))
    layout = BagLayout(
        sensors=(
            SensorTopic("imu", "imu", "/imu"),
            SensorTopic("vel", "gnss_velocity", "/ublox/fix_velocity"),
        )
    )
    bag = write_rosbag(seq, tmp_path / "bag", layout, time_origin_ns=ORIGIN_NS)
    back = read_rosbag(bag, dataclasses.replace(layout, time_origin_ns=ORIGIN_NS))
    assert isinstance(back.gnss_velocity, GnssVelocity)
    assert torch.equal(back.gnss_velocity.t, seq.gnss_velocity.t)
    torch.testing.assert_close(
        back.gnss_velocity.velocity, seq.gnss_velocity.velocity, equal_nan=True
    )
    torch.testing.assert_close(back.gnss_velocity.sigma, seq.gnss_velocity.sigma, equal_nan=True)


def _native_folder_with_velocity(tmp_path: Path) -> Path:
    """A CSV folder: a still IMU at 100 Hz for 1 s and four GNSS velocities, one without
    an up component and one without sigmas."""
    folder = tmp_path / "native"
    folder.mkdir()
    imu = "".join(f"{k / 100!r},0,0,0,0,0,9.81\n" for k in range(101))
    (folder / "imu.csv").write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + imu)
    (folder / "gnss_velocity.csv").write_text(
        "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz\n"
        "0.1,1.25,-0.5,0.0625,0.05,0.05,0.1\n"
        "0.3,1.5,-0.25,nan,0.05,0.06,nan\n"
        "0.5,1.75,0.0,0.125,nan,nan,nan\n"
        "0.7,2.0,0.25,-0.125,0.02,0.03,0.04\n"
    )
    return folder


def test_gnss_velocity_and_fixes_share_one_antenna(tmp_path: Path) -> None:
    """With frames, a gnss_velocity sensor elsewhere than the gnss one is an error naming its
    frame (the estimator applies one lever arm); alone, it gives the GNSS lever arm."""
    from msf_torch.robot.config import load_robot_config

    store = store_for(2)
    t0 = 1_650_000_000_000_000_000
    bag = _write_bag(
        tmp_path / "antenna",
        2,
        {
            "/imu": ("sensor_msgs/msg/Imu", _still_imu(store, t0, "imu_link", 30, 9.8)),
            "/fix": (
                "sensor_msgs/msg/NavSatFix",
                [(t0, _fix_msg(store, t0, "gps_link", 49, 8, 1))],
            ),
            "/fix_velocity": (
                "geometry_msgs/msg/TwistWithCovarianceStamped",
                [(t0, _twist_cov_msg(store, t0, "gps_link", [1, 0, 0], [0.01] * 3))],
            ),
        },
    )
    sensors = (
        SensorTopic("imu", "imu", "/imu"),
        SensorTopic("gps", "gnss", "/fix"),
        SensorTopic("vel", "gnss_velocity", "/fix_velocity"),
    )
    layout = BagLayout(sensors=sensors, frames=FRAMES, body_frame="base_link")
    seq = read_rosbag(bag, layout)
    assert seq.meta["extrinsics"]["vel"] == seq.meta["extrinsics"]["gps"]
    elsewhere = dataclasses.replace(
        layout, sensors=(*sensors[:2], dataclasses.replace(sensors[2], frame="camera_link"))
    )
    with pytest.raises(DataError, match="one GNSS antenna") as caught:
        read_rosbag(bag, elsewhere)
    assert caught.value.field == "sensors.vel.frame"
    with pytest.raises(ValueError, match="one gnss_velocity sensor"):
        BagLayout(sensors=(*sensors, dataclasses.replace(sensors[2], name="vel2")))

    yaml_text = (
        "frames:\n  body: base_link\n  transforms:\n"
        "    - {parent: base_link, child: imu_link, xyz: [0.1, 0.2, 0.3],\n"
        "       rpy: [0, 0, 1.5707963267948966]}\n"
        "    - {parent: base_link, child: gps_link, xyz: [-0.3, 0.0, 1.2], rpy: [0, 0, 0]}\n"
        "sensors:\n"
        "  imu: {type: imu, topic: /imu, frame: imu_link}\n"
        "  vel: {type: gnss_velocity, topic: /fix_velocity, use_message_covariance: false}\n"
    )
    path = tmp_path / "robot.yaml"
    path.write_text(yaml_text)
    robot = load_robot_config(path)
    assert robot.layout.sensor("gnss_velocity").use_message_covariance is False
    alone = read_rosbag(bag, robot.layout)
    lever = robot.eskf_config(alone.meta).gnss_lever_arm_m
    np.testing.assert_allclose(lever, GPS_T[:3, 3] - IMU_T[:3, 3], rtol=0, atol=1e-12)
    path.write_text(yaml_text.replace("use_message_covariance: false", "fuse: [x, y]"))
    with pytest.raises(DataError, match="fuse"):
        load_robot_config(path)
