"""URDF sensor frames through pytorch-kinematics (issue 6, acceptance 2).

A two-sensor robot: an IMU on a fixed joint and a camera on a revolute pan joint (plus a GNSS
antenna). References are hand-written rotation matrices (``Rz Ry Rx`` for URDF rpy, the
Rodrigues matrix about the joint axis), composed in numpy; gradients are checked against
central finite differences and the closed-form derivative of a rotation about an axis.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from msf_torch.robot import FrameTree, StaticTransform

IMU_XYZ, IMU_RPY = [0.12, -0.03, 0.31], [0.02, -0.04, math.pi / 2]
PAN_XYZ, PAN_RPY = [0.45, 0.01, 0.52], [0.0, 0.0, 0.1]
PAN_AXIS = [0.0, 0.6, 0.8]  # tilted pan axis: not a coordinate axis
CAM_XYZ, CAM_RPY = [0.05, 0.0, 0.07], [-math.pi / 2, 0.0, -math.pi / 2]
GPS_XYZ = [-0.2, 0.0, 1.1]

URDF = f"""<?xml version="1.0"?>
<robot name="two_sensor_robot">
  <link name="base_link"/>
  <link name="imu_link"/>
  <link name="pan_link"/>
  <link name="camera_link"/>
  <link name="gps_link"/>
  <joint name="imu_joint" type="fixed">
    <parent link="base_link"/><child link="imu_link"/>
    <origin xyz="{" ".join(map(repr, IMU_XYZ))}" rpy="{" ".join(map(repr, IMU_RPY))}"/>
  </joint>
  <joint name="pan_joint" type="revolute">
    <parent link="base_link"/><child link="pan_link"/>
    <origin xyz="{" ".join(map(repr, PAN_XYZ))}" rpy="{" ".join(map(repr, PAN_RPY))}"/>
    <axis xyz="{" ".join(map(repr, PAN_AXIS))}"/>
    <limit lower="-3.1" upper="3.1" effort="1" velocity="1"/>
  </joint>
  <joint name="camera_joint" type="fixed">
    <parent link="pan_link"/><child link="camera_link"/>
    <origin xyz="{" ".join(map(repr, CAM_XYZ))}" rpy="{" ".join(map(repr, CAM_RPY))}"/>
  </joint>
  <joint name="gps_joint" type="fixed">
    <parent link="base_link"/><child link="gps_link"/>
    <origin xyz="{" ".join(map(repr, GPS_XYZ))}"/>
  </joint>
</robot>
"""


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _hat(v) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _about(axis, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about the unit ``axis``."""
    k = _hat(np.asarray(axis) / np.linalg.norm(axis))
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _h(rot: np.ndarray, xyz) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = xyz
    return out


def _origin(xyz, rpy) -> np.ndarray:
    return _h(_rz(rpy[2]) @ _ry(rpy[1]) @ _rx(rpy[0]), xyz)


def _base_camera(q: float) -> np.ndarray:
    return (
        _origin(PAN_XYZ, PAN_RPY) @ _h(_about(PAN_AXIS, q), [0, 0, 0]) @ _origin(CAM_XYZ, CAM_RPY)
    )


def _imu_camera(q: float) -> np.ndarray:
    return np.linalg.inv(_origin(IMU_XYZ, IMU_RPY)) @ _base_camera(q)


@pytest.fixture(scope="module")
def tree() -> FrameTree:
    return FrameTree.from_urdf(URDF)


def test_frames_and_joints(tree: FrameTree) -> None:
    assert set(tree.frames) == {"base_link", "imu_link", "pan_link", "camera_link", "gps_link"}
    assert tree.joint_names == ["pan_joint"]
    assert tree.joints_between("imu_link", "camera_link") == ["pan_joint"]
    assert tree.joints_between("imu_link", "gps_link") == []
    assert tree.joints_between("pan_link", "camera_link") == []
    assert tree.joint_frame("pan_joint") == "pan_link"


def test_urdf_extrinsics_equal_hand_computed(tree: FrameTree) -> None:
    """Acceptance 2: every transform within 1e-12 of the hand-composed matrices."""
    angles = [-2.5, -0.3, 0.0, 0.7, 3.0]
    got = tree.transform(
        "imu_link", "camera_link", {"pan_joint": torch.tensor(angles, dtype=torch.float64)}
    )
    assert got.shape == (5, 4, 4) and got.dtype == torch.float64
    want = np.stack([_imu_camera(q) for q in angles])
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    # the static sensors need no joint value
    imu_gps = tree.transform("imu_link", "gps_link")
    want_gps = np.linalg.inv(_origin(IMU_XYZ, IMU_RPY)) @ _h(np.eye(3), GPS_XYZ)
    np.testing.assert_allclose(imu_gps.numpy(), want_gps, rtol=0, atol=1e-12)
    # and the reverse direction is the inverse
    cam_imu = tree.transform("camera_link", "imu_link", {"pan_joint": 0.7})
    np.testing.assert_allclose(cam_imu.numpy(), np.linalg.inv(_imu_camera(0.7)), atol=1e-12)
    # a joint-value tensor in joint_names order gives the same
    by_tensor = tree.transform(
        "imu_link", "camera_link", torch.tensor([[0.7]], dtype=torch.float64)
    )
    np.testing.assert_allclose(by_tensor[0].numpy(), _imu_camera(0.7), rtol=0, atol=1e-12)


def test_gradients_reach_joint_values(tree: FrameTree) -> None:
    """Acceptance 2: d T_imu_camera / d q against central finite differences and the
    closed form ``T_imu_pan0 (R'(q)) T_pan_cam`` with ``R'(q) = R(q) [axis]x``."""
    q0 = 0.4
    q = torch.tensor(q0, dtype=torch.float64, requires_grad=True)
    transform = tree.transform("imu_link", "camera_link", {"pan_joint": q})
    jac = torch.stack(
        [torch.autograd.grad(transform.reshape(-1)[k], q, retain_graph=True)[0] for k in range(16)]
    ).reshape(4, 4)
    step = 1e-6
    fd = (_imu_camera(q0 + step) - _imu_camera(q0 - step)) / (2 * step)
    np.testing.assert_allclose(jac.numpy(), fd, rtol=0, atol=1e-9)
    axis = np.asarray(PAN_AXIS) / np.linalg.norm(PAN_AXIS)
    d_joint = np.zeros((4, 4))
    d_joint[:3, :3] = _about(axis, q0) @ _hat(axis)
    closed = (
        np.linalg.inv(_origin(IMU_XYZ, IMU_RPY))
        @ _origin(PAN_XYZ, PAN_RPY)
        @ d_joint
        @ _origin(CAM_XYZ, CAM_RPY)
    )
    np.testing.assert_allclose(jac.numpy(), closed, rtol=0, atol=1e-12)
    # batched values: a scalar loss's gradient per joint value, against the same closed form
    qs = torch.tensor([-1.0, 0.4, 2.0], dtype=torch.float64, requires_grad=True)
    loss = tree.transform("imu_link", "camera_link", {"pan_joint": qs})[:, :3, 3].sum()
    (grad,) = torch.autograd.grad(loss, qs)
    for value, g in zip(qs.tolist(), grad.tolist(), strict=True):
        d_joint[:3, :3] = _about(axis, value) @ _hat(axis)
        full = (
            np.linalg.inv(_origin(IMU_XYZ, IMU_RPY))
            @ _origin(PAN_XYZ, PAN_RPY)
            @ d_joint
            @ _origin(CAM_XYZ, CAM_RPY)
        )
        assert abs(g - full[:3, 3].sum()) < 1e-12
    assert torch.autograd.gradcheck(
        lambda v: tree.transform("imu_link", "camera_link", {"pan_joint": v}),
        (torch.tensor([0.3, -1.2], dtype=torch.float64, requires_grad=True),),
    )


def test_static_transforms_match_the_urdf(tree: FrameTree) -> None:
    """The YAML fallback (static transforms) gives the URDF's fixed transforms."""
    yaml_tree = FrameTree.from_transforms(
        [
            StaticTransform.from_xyz_rpy("base_link", "imu_link", IMU_XYZ, IMU_RPY),
            StaticTransform.from_xyz_rpy("base_link", "gps_link", GPS_XYZ, [0, 0, 0]),
        ]
    )
    np.testing.assert_allclose(
        yaml_tree.transform("imu_link", "gps_link").numpy(),
        tree.transform("imu_link", "gps_link").numpy(),
        rtol=0,
        atol=1e-15,
    )
    # a quaternion (ROS order x, y, z, w) for a quarter turn about z
    quarter = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    q_tree = FrameTree.from_transforms(
        [StaticTransform.from_xyz_quaternion("a", "b", [1.0, 2.0, 3.0], quarter)]
    )
    np.testing.assert_allclose(
        q_tree.transform("a", "b").numpy(), _h(_rz(math.pi / 2), [1, 2, 3]), rtol=0, atol=1e-15
    )
    # static frames below a URDF link, several levels deep
    mixed = FrameTree.from_urdf(
        URDF,
        [
            StaticTransform.from_xyz_rpy("lidar_mount", "lidar", [0, 0, 0.1], [0, 0, 0.2]),
            StaticTransform.from_xyz_rpy("pan_link", "lidar_mount", [0.3, 0, 0], [0, 0, 0]),
        ],
    )
    want = (
        np.linalg.inv(_origin(IMU_XYZ, IMU_RPY))
        @ _origin(PAN_XYZ, PAN_RPY)
        @ _h(_about(PAN_AXIS, 0.5), [0, 0, 0])
        @ _h(np.eye(3), [0.3, 0, 0])
        @ _origin([0, 0, 0.1], [0, 0, 0.2])
    )
    got = mixed.transform("imu_link", "lidar", {"pan_joint": 0.5})
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    assert mixed.joints_between("base_link", "lidar") == ["pan_joint"]


def test_frame_errors(tree: FrameTree) -> None:
    with pytest.raises(ValueError, match="unknown frame 'nope'"):
        tree.transform("imu_link", "nope")
    with pytest.raises(ValueError, match="no value for joint.*pan_joint"):
        tree.transform("imu_link", "camera_link")
    with pytest.raises(ValueError, match="unknown joint"):
        tree.transform("imu_link", "camera_link", {"pan_joint": 0.0, "tilt": 1.0})
    with pytest.raises(ValueError, match="defined twice"):
        FrameTree.from_urdf(
            URDF, [StaticTransform.from_xyz_rpy("base_link", "imu_link", [0] * 3, [0] * 3)]
        )
    with pytest.raises(ValueError, match="cycle"):
        FrameTree.from_transforms(
            [
                StaticTransform.from_xyz_rpy("a", "b", [0] * 3, [0] * 3),
                StaticTransform.from_xyz_rpy("b", "a", [0] * 3, [0] * 3),
            ]
        )
    separate = FrameTree.from_transforms(
        [
            StaticTransform.from_xyz_rpy("a", "b", [0] * 3, [0] * 3),
            StaticTransform.from_xyz_rpy("c", "d", [0] * 3, [0] * 3),
        ]
    )
    with pytest.raises(ValueError, match="not connected"):
        separate.transform("b", "d")
    assert [separate.root(f) for f in "abcd"] == ["a", "a", "c", "c"]
    below_urdf = FrameTree.from_urdf(
        URDF, [StaticTransform.from_xyz_rpy("camera_link", "lens", [0] * 3, [0] * 3)]
    )
    assert {below_urdf.root(f) for f in below_urdf.frames} == {"base_link"}
    floating = URDF.replace('type="revolute"', 'type="floating"')
    with pytest.raises(ValueError, match="type 'floating'"):
        FrameTree.from_urdf(floating)
    with pytest.raises(ValueError, match="cannot read the URDF"):
        FrameTree.from_urdf("/nonexistent/robot.urdf")
