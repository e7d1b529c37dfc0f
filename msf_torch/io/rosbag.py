"""ROS bags (rosbag1 ``.bag`` files and rosbag2 folders) through the pure-Python ``rosbags``.

:func:`read_rosbag` turns the topics named by a :class:`BagLayout` into a
:class:`~msf_torch.types.Sequence` (B = 1, float64) in the estimator's frames;
:func:`write_rosbag` writes a sequence back as messages (the inverse, used by the tests
and to hand native sequences to ROS tools); :func:`write_odometry_rosbag2` writes an
estimated trajectory as ``nav_msgs/Odometry`` for RViz and evo.

Sensors and messages
--------------------
============ ===================================================== ==========================
kind         message types                                         becomes
============ ===================================================== ==========================
``imu``      ``sensor_msgs/Imu``                                   ``Sequence.imu``
``gnss``     ``sensor_msgs/NavSatFix``                             ``Sequence.gnss`` (ENU)
``gnss_velocity`` ``geometry_msgs/TwistWithCovarianceStamped``,    ``Sequence.gnss_velocity``
             ``TwistStamped`` (the antenna's velocity, ENU)        (ENU)
``gnss_heading`` ``sensor_msgs/Imu`` (orientation only: a dual-      ``Sequence.gnss_heading``
             antenna receiver's baseline heading)
``magnetometer`` ``sensor_msgs/MagneticField``                     ``Sequence.magnetometer``
                                                                   (body axes, uT)
``wheels``   ``sensor_msgs/JointState`` (wheel joint velocities    ``Sequence.wheel``
             or positions),
             ``geometry_msgs/TwistStamped``,
             ``TwistWithCovarianceStamped``, ``nav_msgs/Odometry``
             (forward speed and yaw rate of the axle centre)
``pose``     ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,  a pose source (``role:
             ``PoseWithCovarianceStamped``                         pose_source``), ``poses``
                                                                   or ``ground_truth``
``joints``   ``sensor_msgs/JointState`` (joint positions)          joint values of the frames
``image``    ``sensor_msgs/Image``, ``CompressedImage``            references in ``meta``
``laser_scan`` ``sensor_msgs/LaserScan``                           references in ``meta``
============ ===================================================== ==========================

Times
    A message's time is its ``header.stamp`` (or, with ``stamp: bag``, the time the bag
    recorded it) plus the sensor's ``time_offset_s``, in seconds after the time origin:
    ``t = (stamp_ns - origin_ns) / 1e9 + offset``. The origin is ``time_origin_ns`` when
    given, else the earliest stamp of all read topics; it is kept in
    ``meta["time_origin_ns"]`` (integer ns) so that outputs can be stamped back.
Frames
    The estimator's body frame has the axes of ``body_frame`` (default: the IMU's frame)
    and its origin at the IMU (``geometry.conventions``: the body frame is the IMU frame;
    with the default body frame the two are the same). Gyro and accelerometer vectors are
    rotated into the body axes; poses of a sensor frame ``s`` become body poses
    ``T_world_body = T_world_s T_s_body``, their covariance carried along (below); GNSS and
    wheel frames give the lever arms in ``meta["extrinsics"]`` (``T_body_s`` 4x4 per sensor).
    Sensor frames come from ``frames`` (a :class:`~msf_torch.robot.frames.FrameTree`);
    without one, every sensor is taken to sit at the body origin with the body axes. A
    frame that moves with a joint (a pan-tilt camera) is allowed for pose sensors: the
    joint values come from the ``joints`` topic (linearly interpolated to each pose time,
    held at the ends) or from ``joint_values``.
GNSS
    ``NavSatFix`` latitude, longitude and ellipsoidal altitude go to local ENU metres
    about ``gnss_origin`` (:mod:`msf_torch.io.geodesy`); without one the first kept fix is
    the origin. ``meta["gnss_origin"]`` holds ``[lat_deg, lon_deg, alt_m]``. Fixes with
    ``status.status`` below ``min_fix_status`` (default 0, STATUS_FIX) are dropped and
    counted in ``meta["dropped_no_fix"]``. The sigma per axis is the square root of the
    diagonal of ``position_covariance`` (ENU, m^2) unless its type is UNKNOWN or the sensor
    says ``use_message_covariance: false``: then NaN, i.e. the estimator's ``gnss_sigma_m``.
    A fix whose altitude is NaN (the message's "no altitude available") is kept as a
    horizontal fix: its altitude is taken as the origin's and its up component is not
    fused (sigma :data:`UNFUSED_SIGMA`); such fixes are counted in
    ``meta["gnss_no_altitude"]``. The origin's altitude is that of the earliest kept fix
    with one (0 if none has).
GNSS velocity
    The twist's linear part is the antenna's velocity east, north, up in m/s (u-blox
    ``ublox_gps`` ``fix_velocity``: ``velE, velN, -velD`` of NAV-PVT, covariance diagonal
    ``sAcc^2``, angular part -1; Septentrio ``septentrio_gnss_driver`` twist topics are ENU
    only with ``use_ros_axis_orientation: true``, NED otherwise). The angular part is
    ignored. The sigma per axis is the square root of the covariance diagonal (rows 0-2 of
    the 6x6, m^2/s^2); a diagonal entry of 0 or -1 (unknown, or "not provided"), a
    ``TwistStamped``, or ``use_message_covariance: false`` gives NaN: the estimator's
    ``gnss_velocity_sigma_mps``. A NaN up component (a horizontal-only velocity) is kept
    as "not measured" (``GnssVelocity``); a NaN or inf east / north drops the message.
    The velocity is that of the antenna the fixes come from: the estimator applies the GNSS
    lever arm to both, so with ``frames`` the two sensors must sit in the same place
    (DataError otherwise); a ``gnss_velocity`` sensor without a ``gnss`` one gives the lever
    arm itself.
GNSS heading
    A dual-antenna (moving-baseline) receiver's heading as ROS drivers publish it: a
    ``sensor_msgs/Imu`` with only the orientation filled, the yaw in ENU (counter-clockwise
    from east, REP-103) of the baseline from the primary to the secondary antenna. u-blox's
    ``ublox_gps`` (``navheading``, from NAV-RELPOSNED; KumarRobotics/ublox,
    ``ublox_gps/src/hp_pos_rec_product.cpp``, ``HpPosRecProduct::callbackNavRelPosNed``)
    sets ``yaw = pi/2 - relPosHeading`` with roll = pitch = 0 and puts ``accHeading^2``
    (rad^2) in ``orientation_covariance[8]`` when the heading is flagged valid, 1000
    otherwise (1000 also on the roll and pitch entries); it stamps the message with the
    ROS clock when it arrives, not with the receiver's time. The reader inverts that:
    ``heading = pi/2 - yaw`` wrapped to [0, 2 pi), clockwise from true north
    (``GnssHeading``), where ``yaw = atan2(R[1, 0], R[0, 0])`` is the azimuth of the
    quaternion's x axis from east (so a tilted quaternion gives the heading of its x axis
    projected on the level plane). The sigma is the square root of the yaw variance
    ``orientation_covariance[8]`` (rad^2) when it is > 0 and ``use_message_covariance``
    (default true); otherwise NaN, i.e. the estimator's ``gnss_heading_sigma_rad``. A
    message with ``orientation_covariance[0] == -1`` (ROS: "no orientation estimate") is
    skipped and counted in ``meta["skipped_messages"]``. The message's frame places the
    primary antenna only (``meta["extrinsics"]``); its axes are not applied to the
    heading. Which body direction the baseline has is ``gnss_heading_baseline_m`` (a robot
    YAML derives it from the two antenna frames).
Magnetometer
    ``magnetic_field`` (tesla, in the sensor frame's axes) becomes microtesla (x 1e6)
    turned into the body axes, ``f_body = R_body_sensor f_sensor`` (a free vector: no lever
    arm; ``meta["extrinsics"]`` keeps ``T_body_sensor``). The sensor frame must not move
    with a joint. The readings are not corrected: hard and soft iron are the estimator's
    (``magnetometer_hard_iron_uT``, ``magnetometer_soft_iron``, body frame; a robot YAML
    turns sensor-frame values into the body frame). The sigma per axis (uT) is ``1e6
    sqrt(trace(C) / 3)`` of the ``magnetic_field_covariance`` ``C`` (3x3 row-major, T^2;
    its trace does not change with the rotation) when all three diagonal entries are
    positive and finite and ``use_message_covariance`` (default true); otherwise NaN (ROS:
    an all-zero covariance is "unknown"), i.e. the estimator's ``magnetometer_sigma_uT``.
Pose covariance
    ROS orders a pose covariance ``[x, y, z, rot x, rot y, rot z]`` with both blocks about
    the parent (world) axes; msf_torch's is ``[dp (world), dtheta (body)]``
    (``PoseMeasurements``), so the rotation rows are turned by ``R^T``. Moving from frame
    ``s`` to the body applies ``J = [[I, -R_ws [p_sb]x], [0, R_sb^T]]`` on both sides. A
    message without covariance (``PoseStamped``), or a sensor with ``sigma`` given
    (``[x, y, z, roll, pitch, yaw]`` in m and rad, in the sensor's own ``[dp (world),
    dtheta (sensor)]``), uses ``diag(sigma^2)``.
Fused components
    robot_localization style switches: ``fuse`` lists the components a sensor
    contributes; a component left out keeps its place in the measurement but gets a
    standard deviation of :data:`UNFUSED_SIGMA` (its Kalman gain is ~1e-12 of a fused
    one's), with its correlations zeroed. GNSS components are ``x, y, z`` (east, north,
    up); absolute poses (``role: poses``) ``x, y, z, roll, pitch, yaw`` (the rotations
    about the body axes).
Wheels
    From ``JointState``: the rim speed of a side is the mean joint velocity (rad/s) of its
    joints times its radius; messages lacking those joints' velocities are skipped and
    counted in ``meta["skipped_messages"]``. A driver that publishes positions only (no
    message carries the velocities) gives wheel angles instead: the speed is then the mean
    rate between consecutive messages, times the radius, stamped at their midpoint
    (:func:`msf_torch.io.encoders.wheel_speeds_from_angles`). From a twist (``v_x``,
    ``w_z`` of the axle centre): ``v_left = v_x - w_z D / 2``, ``v_right = v_x + w_z D / 2``
    with the track ``D = wheel_track_m``.
References
    Image and LaserScan topics are not read into streams: ``meta["references"][name]``
    lists their times ``t`` and ``stamp_ns`` (header) and ``bag_ns`` (recording time, the
    key :func:`read_referenced_message` looks a message up by).

The io rules of :mod:`msf_torch.io.native` apply to every stream (non-finite samples
dropped and counted, backwards time an error unless ``sort``, repeated stamps dropped),
with 0-based message indices in ``meta["dropped_indices"]``.
"""

from __future__ import annotations

__all__ = [
    "SENSOR_KINDS",
    "MESSAGE_TYPES",
    "UNFUSED_SIGMA",
    "SensorTopic",
    "BagLayout",
    "is_rosbag",
    "read_rosbag",
    "read_referenced_message",
    "write_rosbag",
    "write_odometry_rosbag2",
]

import contextlib
import math
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import (
    matrix_to_quat,
    quat_to_matrix,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)
from msf_torch.io import _tables
from msf_torch.io.encoders import wheel_speeds_from_angles
from msf_torch.io.errors import DataError
from msf_torch.io.geodesy import enu_to_geodetic, geodetic_to_enu
from msf_torch.robot.frames import FrameTree, inverse_transform
from msf_torch.types import (
    GnssFixes,
    GnssHeading,
    GnssVelocity,
    ImuSamples,
    Magnetometer,
    PoseMeasurements,
    Sequence,
    Trajectory,
    WheelSamples,
)

SENSOR_KINDS = (
    "imu",
    "gnss",
    "gnss_velocity",
    "gnss_heading",
    "magnetometer",
    "wheels",
    "pose",
    "joints",
    "image",
    "laser_scan",
)
"""Sensor kinds a topic can be mapped to."""

MESSAGE_TYPES: dict[str, tuple[str, ...]] = {
    "imu": ("sensor_msgs/msg/Imu",),
    "gnss": ("sensor_msgs/msg/NavSatFix",),
    "gnss_velocity": (
        "geometry_msgs/msg/TwistWithCovarianceStamped",
        "geometry_msgs/msg/TwistStamped",
    ),
    "gnss_heading": ("sensor_msgs/msg/Imu",),
    "magnetometer": ("sensor_msgs/msg/MagneticField",),
    "wheels": (
        "sensor_msgs/msg/JointState",
        "geometry_msgs/msg/TwistStamped",
        "geometry_msgs/msg/TwistWithCovarianceStamped",
        "nav_msgs/msg/Odometry",
    ),
    "pose": (
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/msg/PoseStamped",
    ),
    "joints": ("sensor_msgs/msg/JointState",),
    "image": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "laser_scan": ("sensor_msgs/msg/LaserScan",),
}
"""Accepted message types per sensor kind (rosbags' names, ``pkg/msg/Type``)."""

UNFUSED_SIGMA = 1.0e6
"""Standard deviation (m or rad) given to a measurement component that ``fuse`` leaves out."""

POSE_ROLES = ("pose_source", "poses", "ground_truth")
GNSS_COMPONENTS = ("x", "y", "z")
POSE_COMPONENTS = ("x", "y", "z", "roll", "pitch", "yaw")
WHEEL_COMPONENTS = ("speed", "yaw_rate")


@dataclass(frozen=True)
class SensorTopic:
    """One bag topic and how it becomes a stream (module docstring for the rules).

    Attributes:
        name: the sensor's name (its key in the robot YAML), used in messages and ``meta``.
        kind: one of :data:`SENSOR_KINDS`.
        topic: the bag topic, e.g. ``"/imu/data"``.
        frame: the sensor's frame; None: the message's ``header.frame_id`` (an Odometry's
            ``child_frame_id``; the body frame for ``PoseStamped`` / ``PoseWithCovariance``).
        stamp: ``"header"`` or ``"bag"`` (the recording time).
        time_offset_s: added to every time of this sensor, s.
        use_message_covariance: GNSS, GNSS velocity, GNSS heading, magnetometer, pose: take
            the message's covariance.
        min_fix_status: GNSS: lowest ``NavSatStatus.status`` kept (-1 keeps all).
        fuse: fused components (None: all); see the module docstring.
        left_joints, right_joints: wheels from JointState: the joints of each side.
        wheel_radius_m: wheels from JointState: (left, right) radius, m.
        role: pose: ``"pose_source"``, ``"poses"`` or ``"ground_truth"``.
        source_name: pose source name (default: ``name``).
        sigma: pose: 6 standard deviations replacing the message covariance (m, rad).
    """

    name: str
    kind: str
    topic: str
    frame: str | None = None
    stamp: str = "header"
    time_offset_s: float = 0.0
    use_message_covariance: bool = True
    min_fix_status: int = 0
    fuse: tuple[str, ...] | None = None
    left_joints: tuple[str, ...] = ()
    right_joints: tuple[str, ...] = ()
    wheel_radius_m: tuple[float, float] | None = None
    role: str = "pose_source"
    source_name: str | None = None
    sigma: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        """Check the fields that do not depend on the bag (ValueError naming the sensor)."""
        where = f"sensor '{self.name}'"
        if self.kind not in SENSOR_KINDS:
            raise ValueError(f"{where}: kind must be one of {SENSOR_KINDS}, got {self.kind!r}")
        if self.stamp not in ("header", "bag"):
            raise ValueError(f"{where}: stamp must be 'header' or 'bag', got {self.stamp!r}")
        if self.kind == "pose" and self.role not in POSE_ROLES:
            raise ValueError(f"{where}: role must be one of {POSE_ROLES}, got {self.role!r}")
        if self.sigma is not None and (
            len(self.sigma) != 6 or not all(np.isfinite(s) and s > 0 for s in self.sigma)
        ):
            raise ValueError(f"{where}: sigma must be 6 positive numbers, got {self.sigma!r}")


@dataclass
class BagLayout:
    """Which topics to read and how (the ``sensors`` and ``frames`` of a robot YAML).

    Attributes:
        sensors: the topics to read; at most one each of gnss, gnss_velocity, gnss_heading,
            magnetometer and wheels, one pose sensor with role ``poses`` and one with
            ``ground_truth``; exactly one imu.
        frames: the robot's frames, or None (every sensor at the body origin and axes).
        body_frame: the estimator's body axes (origin at the IMU); None: the IMU's frame.
        joint_values: fixed values (rad or m) of movable joints, by name.
        time_origin_ns: the time origin, ns; None: the earliest stamp read.
        gnss_origin: ``(lat_deg, lon_deg, alt_m)`` of the ENU origin; None: the first fix.
        wheel_track_m: track width for wheel speeds from twist messages, m.
    """

    sensors: tuple[SensorTopic, ...]
    frames: FrameTree | None = None
    body_frame: str | None = None
    joint_values: Mapping[str, float] = field(default_factory=dict)
    time_origin_ns: int | None = None
    gnss_origin: tuple[float, float, float] | None = None
    wheel_track_m: float | None = None

    def __post_init__(self) -> None:
        """Check the sensor set (ValueError naming the sensors)."""
        kinds = [s.kind for s in self.sensors]
        if kinds.count("imu") != 1:
            raise ValueError(f"a bag layout needs exactly one imu sensor, got {kinds.count('imu')}")
        for single in ("gnss", "gnss_velocity", "gnss_heading", "magnetometer", "wheels", "joints"):
            names = [s.name for s in self.sensors if s.kind == single]
            if len(names) > 1:
                raise ValueError(f"the estimator takes one {single} sensor, got {names}")
        for role in ("poses", "ground_truth"):
            names = [s.name for s in self.sensors if s.kind == "pose" and s.role == role]
            if len(names) > 1:
                raise ValueError(f"one pose sensor may have role {role}, got {names}")
        sources = [
            s.source_name or s.name
            for s in self.sensors
            if s.kind == "pose" and s.role == "pose_source"
        ]
        if len(set(sources)) != len(sources):
            raise ValueError(f"pose source names repeat: {sources}")
        names = [s.name for s in self.sensors]
        if len(set(names)) != len(names):
            raise ValueError(f"sensor names repeat: {names}")

    def sensor(self, kind: str) -> SensorTopic | None:
        """The (single) sensor of ``kind``, or None."""
        return next((s for s in self.sensors if s.kind == kind), None)


# --------------------------------------------------------------------------- small helpers


def is_rosbag(path: str | os.PathLike[str]) -> str | None:
    """``"rosbag1"`` for a ``.bag`` file, ``"rosbag2"`` for a folder with ``metadata.yaml``,
    else None."""
    p = Path(path)
    if p.is_file() and p.suffix == ".bag":
        return "rosbag1"
    if p.is_dir() and (p / "metadata.yaml").is_file():
        return "rosbag2"
    return None


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _vec(v) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def _quat_xyzw(q) -> list[float]:
    return [float(q.x), float(q.y), float(q.z), float(q.w)]


def _hamilton(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of ``[w, x, y, z]`` quaternions (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def _ros_to_native_covariance(cov: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """ROS pose covariance (..., 6, 6) (rotation about world axes) -> ``[dp, dtheta body]``."""
    jac = torch.zeros_like(cov)
    jac[..., :3, :3] = torch.eye(3, dtype=cov.dtype, device=cov.device)
    jac[..., 3:, 3:] = rot.mT
    return jac @ cov @ jac.mT


def _native_to_ros_covariance(cov: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`_ros_to_native_covariance`."""
    jac = torch.zeros_like(cov)
    jac[..., :3, :3] = torch.eye(3, dtype=cov.dtype, device=cov.device)
    jac[..., 3:, 3:] = rot
    return jac @ cov @ jac.mT


def _move_pose_covariance(
    cov: torch.Tensor, rot_world_from: torch.Tensor, from_to: torch.Tensor
) -> torch.Tensor:
    """Covariance (..., 6, 6) ``[dp, dtheta]`` of ``T_world_from`` -> of ``T_world_from @
    from_to`` (``from_to`` (..., 4, 4), ``rot_world_from`` (..., 3, 3))."""
    lever = from_to[..., :3, 3]
    jac = torch.zeros(*cov.shape[:-2], 6, 6, dtype=cov.dtype, device=cov.device)
    jac[..., :3, :3] = torch.eye(3, dtype=cov.dtype, device=cov.device)
    jac[..., :3, 3:] = -rot_world_from @ so3.hat(lever)
    jac[..., 3:, 3:] = from_to[..., :3, :3].mT
    return jac @ cov @ jac.mT


def _inflate(cov: torch.Tensor, unfused: list[int]) -> torch.Tensor:
    """Covariance (..., D, D) with rows/columns ``unfused`` replaced by UNFUSED_SIGMA^2 I."""
    if not unfused:
        return cov
    keep = torch.ones(cov.shape[-1], dtype=torch.bool, device=cov.device)
    keep[unfused] = False
    outer = keep[:, None] & keep[None, :]
    diag = torch.zeros(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    diag[unfused] = UNFUSED_SIGMA**2
    return torch.where(outer, cov, torch.diag(diag).to(cov))


# --------------------------------------------------------------------------- reading


@dataclass
class _Raw:
    """Messages of one sensor, as arrays in message order."""

    spec: SensorTopic
    msgtype: str
    header_ns: np.ndarray  # (N,) int64
    bag_ns: np.ndarray  # (N,) int64
    frame_id: str
    child_frame_id: str
    fields: dict[str, np.ndarray]
    skipped: int = 0


def _extract(
    spec: SensorTopic, msgtype: str, messages: list
) -> tuple[dict[str, np.ndarray], list[int]]:
    """Field arrays of deserialised messages; returns the arrays and the kept indices."""
    keep = list(range(len(messages)))
    if spec.kind == "imu":
        gyro = [_vec(m.angular_velocity) for m in messages]
        accel = [_vec(m.linear_acceleration) for m in messages]
        return {
            "gyro": np.array(gyro).reshape(-1, 3),
            "accel": np.array(accel).reshape(-1, 3),
        }, keep
    if spec.kind == "gnss":
        return {
            "lat": np.array([m.latitude for m in messages], dtype=np.float64),
            "lon": np.array([m.longitude for m in messages], dtype=np.float64),
            "alt": np.array([m.altitude for m in messages], dtype=np.float64),
            "status": np.array([m.status.status for m in messages], dtype=np.int64),
            "cov": np.array([m.position_covariance for m in messages]).reshape(-1, 9),
            "cov_type": np.array([m.position_covariance_type for m in messages], dtype=np.int64),
        }, keep
    if spec.kind == "gnss_velocity":
        if msgtype == "geometry_msgs/msg/TwistStamped":
            linear = [_vec(m.twist.linear) for m in messages]
            cov = np.full((len(messages), 3), np.nan)
        else:
            linear = [_vec(m.twist.twist.linear) for m in messages]
            cov = np.array([m.twist.covariance for m in messages]).reshape(-1, 36)[:, [0, 7, 14]]
        return {"velocity": np.array(linear).reshape(-1, 3), "cov": cov}, keep
    if spec.kind == "gnss_heading":
        cov = np.array([m.orientation_covariance for m in messages]).reshape(-1, 9)
        keep = [i for i in keep if cov[i, 0] != -1.0]  # ROS: no orientation estimate
        quat = [_quat_xyzw(messages[i].orientation) for i in keep]
        return {
            "quaternion_xyzw": np.array(quat, dtype=np.float64).reshape(-1, 4),
            "yaw_variance": cov[keep, 8],
        }, keep
    if spec.kind == "magnetometer":
        cov = np.array([m.magnetic_field_covariance for m in messages]).reshape(-1, 9)
        return {
            "field_tesla": np.array([_vec(m.magnetic_field) for m in messages]).reshape(-1, 3),
            "cov_diagonal": cov[:, [0, 4, 8]],
        }, keep
    if spec.kind == "pose":
        pose_of = {
            "nav_msgs/msg/Odometry": lambda m: m.pose.pose,
            "geometry_msgs/msg/PoseWithCovarianceStamped": lambda m: m.pose.pose,
            "geometry_msgs/msg/PoseStamped": lambda m: m.pose,
        }[msgtype]
        poses = [pose_of(m) for m in messages]
        if msgtype == "geometry_msgs/msg/PoseStamped":
            cov = np.full((len(messages), 36), np.nan)
        else:
            cov = np.array([m.pose.covariance for m in messages]).reshape(-1, 36)
        return {
            "position": np.array([_vec(p.position) for p in poses]).reshape(-1, 3),
            "quaternion_xyzw": np.array([_quat_xyzw(p.orientation) for p in poses]).reshape(-1, 4),
            "cov": cov,
        }, keep
    if spec.kind == "wheels":
        if msgtype == "sensor_msgs/msg/JointState":
            return _joint_wheels(messages, spec)
        twist_of = {
            "geometry_msgs/msg/TwistStamped": lambda m: m.twist,
            "geometry_msgs/msg/TwistWithCovarianceStamped": lambda m: m.twist.twist,
            "nav_msgs/msg/Odometry": lambda m: m.twist.twist,
        }[msgtype]
        twists = [twist_of(m) for m in messages]
        return {
            "forward": np.array([float(t.linear.x) for t in twists]),
            "yaw_rate": np.array([float(t.angular.z) for t in twists]),
        }, keep
    if spec.kind == "joints":
        return {"joint_states": np.array(messages, dtype=object)}, keep
    return {}, keep


def _read_raw(path: Path, layout: BagLayout) -> tuple[str, dict[str, _Raw]]:
    from rosbags.highlevel import AnyReader
    from rosbags.highlevel.anyreader import AnyReaderError

    kind = is_rosbag(path)
    if kind is None:
        if not path.exists():
            raise DataError(path, "no such file or folder")
        raise DataError(
            path,
            "not a ROS bag: expected a rosbag1 .bag file or a rosbag2 folder with metadata.yaml",
        )
    raw: dict[str, _Raw] = {}
    try:
        with AnyReader([path]) as reader:
            by_topic: dict[str, list] = {}
            for conn in reader.connections:
                by_topic.setdefault(conn.topic, []).append(conn)
            for spec in layout.sensors:
                conns = by_topic.get(spec.topic)
                if not conns:
                    raise DataError(
                        path,
                        f"topic '{spec.topic}' of sensor '{spec.name}' is not in the bag "
                        f"(topics: {', '.join(sorted(by_topic)) or 'none'})",
                        field=f"sensors.{spec.name}.topic",
                    )
                msgtype = conns[0].msgtype
                if msgtype not in MESSAGE_TYPES[spec.kind]:
                    raise DataError(
                        path,
                        f"topic '{spec.topic}' carries {msgtype}; a {spec.kind} sensor reads "
                        f"{', '.join(MESSAGE_TYPES[spec.kind])}",
                        field=f"sensors.{spec.name}.topic",
                    )
                messages, bag_ns = [], []
                for conn, timestamp, data in reader.messages(connections=conns):
                    messages.append(reader.deserialize(data, conn.msgtype))
                    bag_ns.append(timestamp)
                fields, keep = _extract(spec, msgtype, messages)
                kept = [messages[i] for i in keep]
                header_ns = np.array([_stamp_ns(m.header) for m in kept], dtype=np.int64)
                frame_id = str(kept[0].header.frame_id) if kept else ""
                child = str(getattr(kept[0], "child_frame_id", "")) if kept else ""
                raw[spec.name] = _Raw(
                    spec,
                    msgtype,
                    header_ns,
                    np.array(bag_ns, dtype=np.int64)[keep],
                    frame_id,
                    child,
                    fields,
                    skipped=len(messages) - len(keep),
                )
    except AnyReaderError as err:
        raise DataError(path, f"cannot read the bag ({err})") from None
    return kind, raw


def _times(raw: _Raw, origin_ns: int) -> np.ndarray:
    stamps = raw.header_ns if raw.spec.stamp == "header" else raw.bag_ns
    return (stamps - origin_ns) / 1e9 + raw.spec.time_offset_s


def _first_stamp(raw: _Raw) -> int | None:
    stamps = raw.header_ns if raw.spec.stamp == "header" else raw.bag_ns
    return int(stamps.min()) if stamps.size else None


class _Frames:
    """Sensor extrinsics ``T_body_sensor`` in the estimator's body frame (IMU origin)."""

    def __init__(self, layout: BagLayout, raw: dict[str, _Raw], path: Path) -> None:
        self.layout = layout
        self.tree = layout.frames
        self.path = path
        imu = raw[layout.sensor("imu").name]
        self.imu_frame = self.sensor_frame(imu)
        self.body_frame = layout.body_frame or self.imu_frame
        self.joint_series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if self.tree is None:
            self.body_imu = torch.eye(4, dtype=torch.float64)
            return
        for name in (self.body_frame, self.imu_frame):
            self._check_frame(name, layout.sensor("imu").name)
        moving = self.tree.joints_between(self.body_frame, self.imu_frame)
        if moving:
            raise DataError(
                path,
                f"the IMU frame '{self.imu_frame}' moves with joint(s) {moving} relative to "
                f"the body frame '{self.body_frame}'",
                field="frames.body",
            )
        self.body_imu = self.tree.transform(self.body_frame, self.imu_frame)

    def _check_frame(self, frame: str, sensor: str) -> None:
        if frame not in self.tree.frames:
            raise DataError(
                self.path,
                f"sensor '{sensor}' is in frame '{frame}', which the robot's frames do not "
                f"define (known: {', '.join(self.tree.frames)})",
                field=f"sensors.{sensor}.frame",
            )
        body = self.body_frame
        if self.tree.root(frame) != self.tree.root(body):
            raise DataError(
                self.path,
                f"sensor '{sensor}' is in frame '{frame}', which is not connected to the body "
                f"frame '{body}': its tree starts at '{self.tree.root(frame)}', the body's at "
                f"'{self.tree.root(body)}' (check the parents in frames.transforms)",
                field=f"sensors.{sensor}.frame",
            )

    def sensor_frame(self, raw: _Raw) -> str:
        if raw.spec.frame:
            return raw.spec.frame
        if raw.msgtype == "nav_msgs/msg/Odometry" and raw.child_frame_id:
            return raw.child_frame_id
        if raw.msgtype.startswith("geometry_msgs/msg/Pose"):
            return self.layout.body_frame or ""
        return raw.frame_id

    def body_from(self, raw: _Raw, t: np.ndarray | None = None) -> torch.Tensor:
        """``T_body_sensor``: (4, 4), or (N, 4, 4) at times ``t`` when joints move it."""
        if self.tree is None:
            return torch.eye(4, dtype=torch.float64)
        if raw.msgtype == "nav_msgs/msg/Odometry" and not (raw.spec.frame or raw.child_frame_id):
            raise DataError(
                self.path,
                f"the nav_msgs/Odometry messages on '{raw.spec.topic}' have an empty "
                "child_frame_id (the frame whose pose they give; header.frame_id is the parent "
                f"frame): set sensors.{raw.spec.name}.frame",
                field=f"sensors.{raw.spec.name}.frame",
            )
        frame = self.sensor_frame(raw) or self.body_frame
        self._check_frame(frame, raw.spec.name)
        moving = self.tree.joints_between(self.body_frame, frame)
        values: dict[str, Any] = {}
        for joint in moving:
            if joint in self.layout.joint_values:
                values[joint] = float(self.layout.joint_values[joint])
            elif joint in self.joint_series and t is not None:
                times, series = self.joint_series[joint]
                values[joint] = torch.as_tensor(np.interp(t, times, series))
            else:
                why = (
                    "its frame must be static for this sensor kind"
                    if t is None
                    else "give the joint's value (frames.joints.values) or a joints topic"
                )
                raise DataError(
                    self.path,
                    f"sensor '{raw.spec.name}' (frame '{frame}') moves with joint '{joint}': {why}",
                    field=f"sensors.{raw.spec.name}.frame",
                )
        body_sensor = self.tree.transform(self.body_frame, frame, values or None)
        # the estimator's body frame: body axes, origin at the IMU
        shift = torch.eye(4, dtype=torch.float64)
        shift[:3, 3] = -self.body_imu[:3, 3]
        return shift @ body_sensor


def _joint_series(raw: _Raw, origin_ns: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per joint: (times, positions) from JointState messages, time-sorted."""
    t = _times(raw, origin_ns)
    per_joint: dict[str, list[tuple[float, float]]] = {}
    for time, message in zip(t.tolist(), raw.fields["joint_states"], strict=True):
        positions = np.asarray(message.position, dtype=np.float64)
        for k, name in enumerate(message.name):
            if k < positions.shape[0] and np.isfinite(positions[k]):
                per_joint.setdefault(str(name), []).append((time, float(positions[k])))
    out = {}
    for name, pairs in per_joint.items():
        arr = np.array(sorted(pairs))
        out[name] = (arr[:, 0], arr[:, 1])
    return out


def read_rosbag(path: str | os.PathLike[str], layout: BagLayout, sort: bool = False) -> Sequence:
    """Read a rosbag1 file or rosbag2 folder into a sequence (B = 1, float64).

    Args:
        path: a ``.bag`` file (rosbag1) or a rosbag2 folder (``metadata.yaml`` inside).
        layout: which topics to read and the robot's frames (:class:`BagLayout`).
        sort: stably sort streams whose times go backwards instead of raising.

    Returns:
        a :class:`~msf_torch.types.Sequence`: ``imu`` and, when mapped, ``wheel``, ``gnss``,
        ``gnss_velocity``, ``gnss_heading``, ``magnetometer``, ``poses``, ``ground_truth``
        and named ``pose_sources``, in the body frame (module docstring); ``names == [bag stem]``;
        ``meta`` with ``source``, ``format`` (``"rosbag1"`` / ``"rosbag2"``),
        ``time_origin_ns``, ``body_frame``, ``imu_frame``, ``body_imu_rotation`` (3x3, the
        IMU's axes in the body frame), ``topics``, ``extrinsics``, ``gnss_origin``,
        ``references`` and the cleaning counts.

    Raises:
        DataError: naming the bag and the sensor key (a missing topic, a wrong message
            type, an unknown frame, a moving frame without joint values, ...).
    """
    bag = Path(path)
    kind, raw = _read_raw(bag, layout)
    imu_raw = raw[layout.sensor("imu").name]
    if imu_raw.header_ns.size == 0:
        raise DataError(bag, f"topic '{imu_raw.spec.topic}' has no messages", field="imu")
    if layout.time_origin_ns is not None:
        origin_ns = int(layout.time_origin_ns)
    else:
        firsts = [s for s in (_first_stamp(r) for r in raw.values()) if s is not None]
        origin_ns = min(firsts)
    frames = _Frames(layout, raw, bag)
    joints = layout.sensor("joints")
    if joints is not None:
        frames.joint_series = _joint_series(raw[joints.name], origin_ns)
    report = _tables.CleanReport()
    streams: dict[str, Any] = {}
    sources: dict[str, PoseMeasurements] = {}
    meta: dict[str, Any] = {
        "source": str(bag),
        "format": kind,
        "time_origin_ns": origin_ns,
        "body_frame": frames.body_frame,
        "imu_frame": frames.imu_frame,
        "body_imu_rotation": frames.body_imu[:3, :3].tolist(),
        "topics": {},
        "extrinsics": {},
    }
    skipped = {name: r.skipped for name, r in raw.items() if r.skipped}
    if skipped:
        meta["skipped_messages"] = skipped

    def clean(stream: str, arrays: dict[str, np.ndarray], nan_ok=()) -> dict[str, np.ndarray]:
        return _tables.clean_stream(
            report, stream, str(bag), arrays, sort=sort, nan_ok=nan_ok, field_prefix=""
        )

    for name, r in raw.items():
        spec = r.spec
        meta["topics"][name] = {
            "topic": spec.topic,
            "msgtype": r.msgtype,
            "messages": int(r.header_ns.size + r.skipped),
            "frame": frames.sensor_frame(r),
        }
        t = _times(r, origin_ns)
        if spec.kind == "imu":
            rot = frames.body_imu[:3, :3].numpy()
            arrays = clean(
                "imu",
                {"t": t, "gyro": r.fields["gyro"] @ rot.T, "accel": r.fields["accel"] @ rot.T},
            )
            streams["imu"] = _tables.stream_from_arrays(ImuSamples, arrays)
        elif spec.kind == "gnss":
            streams["gnss"], origin = _gnss_stream(r, t, layout, clean, meta)
            meta["gnss_origin"] = list(origin)
            meta["extrinsics"][name] = frames.body_from(r).tolist()
        elif spec.kind == "gnss_velocity":
            streams["gnss_velocity"] = _gnss_velocity_stream(r, t, clean)
            meta["extrinsics"][name] = frames.body_from(r).tolist()
        elif spec.kind == "gnss_heading":
            streams["gnss_heading"] = _gnss_heading_stream(r, t, clean, bag)
            meta["extrinsics"][name] = frames.body_from(r).tolist()
        elif spec.kind == "magnetometer":
            body_sensor = frames.body_from(r)
            streams["magnetometer"] = _magnetometer_stream(r, t, body_sensor[:3, :3], clean)
            meta["extrinsics"][name] = body_sensor.tolist()
        elif spec.kind == "wheels":
            streams["wheel"] = _wheel_stream(r, t, layout, clean, bag)
            meta["extrinsics"][name] = frames.body_from(r).tolist()
        elif spec.kind == "pose":
            stream_name = {
                "pose_source": f"poses/{spec.source_name or spec.name}",
                "poses": "poses",
                "ground_truth": "ground_truth",
            }[spec.role]
            value, static = _pose_stream(r, t, frames, clean, stream_name, bag)
            if static is not None:
                meta["extrinsics"][name] = static.tolist()
            if spec.role == "pose_source":
                sources[spec.source_name or spec.name] = value
            else:
                streams[spec.role] = value
        elif spec.kind in ("image", "laser_scan"):
            meta.setdefault("references", {})[name] = {
                "topic": spec.topic,
                "msgtype": r.msgtype,
                "frame": frames.sensor_frame(r),
                "t": t.tolist(),
                "stamp_ns": r.header_ns.tolist(),
                "bag_ns": r.bag_ns.tolist(),
            }
    meta.update(report.to_meta())
    _check_one_antenna(layout, meta, bag)
    if streams["imu"].length == 0:
        raise DataError(bag, "no IMU samples (after dropping non-finite ones)", field="imu")
    seq = Sequence(
        names=[_tables.path_name(bag)],
        meta=meta,
        pose_sources=dict(sorted(sources.items())),
        **streams,
    )
    seq.check()
    return seq


def _gnss_stream(r: _Raw, t: np.ndarray, layout: BagLayout, clean, meta) -> tuple:
    spec = r.spec
    f = r.fields
    fix = f["status"] >= spec.min_fix_status
    dropped = int((~fix).sum())
    if dropped:
        meta.setdefault("dropped_no_fix", {})[spec.name] = dropped
    horizontal = fix & np.isfinite(f["lat"]) & np.isfinite(f["lon"])
    no_altitude = horizontal & np.isnan(f["alt"])
    if no_altitude.any():
        meta.setdefault("gnss_no_altitude", {})[spec.name] = int(no_altitude.sum())
    if layout.gnss_origin is not None:
        origin = tuple(float(x) for x in layout.gnss_origin)
    elif horizontal.any():
        first = int(np.flatnonzero(horizontal)[np.argmin(t[horizontal])])
        vertical = horizontal & np.isfinite(f["alt"])
        alt0 = (
            float(f["alt"][np.flatnonzero(vertical)[np.argmin(t[vertical])]])
            if vertical.any()
            else 0.0
        )
        origin = (float(f["lat"][first]), float(f["lon"][first]), alt0)
    else:
        origin = (0.0, 0.0, 0.0)
    alt = np.where(no_altitude, origin[2], f["alt"])
    position = geodetic_to_enu(f["lat"][fix], f["lon"][fix], alt[fix], origin)
    diag = f["cov"][fix][:, [0, 4, 8]]
    known = (f["cov_type"][fix] != 0)[:, None] & (diag > 0)
    use = spec.use_message_covariance
    sigma = np.where(known & use, np.sqrt(np.where(known, diag, 1.0)), np.nan)
    fused = GNSS_COMPONENTS if spec.fuse is None else spec.fuse
    for axis, component in enumerate(GNSS_COMPONENTS):
        if component not in fused:
            sigma[:, axis] = UNFUSED_SIGMA
    sigma[no_altitude[fix], 2] = UNFUSED_SIGMA
    arrays = clean("gnss", {"t": t[fix], "position": position, "sigma": sigma}, nan_ok=("sigma",))
    return _tables.stream_from_arrays(GnssFixes, arrays), origin


def _gnss_velocity_stream(r: _Raw, t: np.ndarray, clean) -> GnssVelocity:
    """The antenna's ENU velocity (N, 3) m/s with per-axis sigmas (module docstring)."""
    cov = r.fields["cov"]
    known = np.isfinite(cov) & (cov > 0)
    use = r.spec.use_message_covariance
    sigma = np.where(known & use, np.sqrt(np.where(known, cov, 1.0)), np.nan)
    velocity = r.fields["velocity"]
    arrays = clean(
        "gnss_velocity",
        {"t": t, "velocity": velocity[:, :2], "velocity_up": velocity[:, 2], "sigma": sigma},
        nan_ok=("sigma", "velocity_up"),
    )
    up = arrays.pop("velocity_up")
    arrays["velocity"] = np.concatenate((arrays["velocity"], up[:, None]), axis=1)
    return _tables.stream_from_arrays(GnssVelocity, arrays)


def _gnss_heading_stream(r: _Raw, t: np.ndarray, clean, bag: Path) -> GnssHeading:
    """Baseline headings (N,) clockwise from north in [0, 2 pi), rad, and sigmas (N,) rad
    from ``sensor_msgs/Imu`` orientations (module docstring)."""
    spec = r.spec
    quat_xyzw = r.fields["quaternion_xyzw"]
    _tables.check_quaternions(
        str(bag), quat_xyzw, field_prefix=f"{spec.topic}:", name="orientation"
    )
    finite = np.isfinite(quat_xyzw).all(axis=1)
    unit_xyzw = _tables.normalise_quaternions(np.where(finite[:, None], quat_xyzw, [0, 0, 0, 1.0]))
    rot = quat_to_matrix(xyzw_to_wxyz(torch.as_tensor(unit_xyzw))).numpy()
    yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])  # the x axis' ENU azimuth from east
    heading = np.where(finite, np.mod(0.5 * np.pi - yaw, 2.0 * np.pi), np.nan)
    heading = np.where(heading >= 2.0 * np.pi, 0.0, heading)  # mod rounded up to 2 pi
    variance = r.fields["yaw_variance"]
    known = np.isfinite(variance) & (variance > 0)
    use = spec.use_message_covariance
    sigma = np.where(known & use, np.sqrt(np.where(known, variance, 1.0)), np.nan)
    arrays = clean("gnss_heading", {"t": t, "heading": heading, "sigma": sigma}, nan_ok=("sigma",))
    return _tables.stream_from_arrays(GnssHeading, arrays)


def _magnetometer_stream(r: _Raw, t: np.ndarray, rotation: torch.Tensor, clean) -> Magnetometer:
    """Body-frame fields (N, 3) uT and per-axis sigmas (N,) uT from ``MagneticField``
    messages (module docstring); ``rotation`` (3, 3) is ``R_body_sensor``."""
    field = 1e6 * r.fields["field_tesla"] @ rotation.numpy().T
    diagonal = r.fields["cov_diagonal"]
    known = (np.isfinite(diagonal) & (diagonal > 0)).all(axis=1)
    use = known & r.spec.use_message_covariance
    mean = np.where(known[:, None], diagonal, 1.0).mean(axis=1)
    sigma = np.where(use, 1e6 * np.sqrt(mean), np.nan)
    arrays = clean("magnetometer", {"t": t, "field": field, "sigma": sigma}, nan_ok=("sigma",))
    return _tables.stream_from_arrays(Magnetometer, arrays)


def _check_one_antenna(layout: BagLayout, meta: dict[str, Any], bag: Path) -> None:
    """DataError when the gnss and gnss_velocity sensors sit more than 1 mm apart (the
    estimator applies one GNSS lever arm to fixes and velocities)."""
    fixes, velocity = layout.sensor("gnss"), layout.sensor("gnss_velocity")
    if fixes is None or velocity is None or layout.frames is None:
        return
    arms = [np.array(meta["extrinsics"][s.name])[:3, 3] for s in (fixes, velocity)]
    if np.abs(arms[0] - arms[1]).max() > 1e-3:
        raise DataError(
            bag,
            f"sensor '{velocity.name}' sits at {arms[1].tolist()} m in the body frame, sensor "
            f"'{fixes.name}' at {arms[0].tolist()} m: the estimator takes one GNSS antenna "
            "(one lever arm) for fixes and velocities",
            field=f"sensors.{velocity.name}.frame",
        )


def _side_means(messages: list, spec: SensorTopic, field: str) -> tuple[list, list, list]:
    """Per message holding every wheel joint in ``field`` (``"velocity"`` or ``"position"``):
    the mean over each side's joints, and the message's index."""
    wanted = spec.left_joints + spec.right_joints
    left, right, keep = [], [], []
    for i, m in enumerate(messages):
        names = list(m.name)
        values = np.asarray(getattr(m, field), dtype=np.float64)
        if values.shape[0] != len(names) or not all(j in names for j in wanted):
            continue
        left.append(np.mean([values[names.index(j)] for j in spec.left_joints]))
        right.append(np.mean([values[names.index(j)] for j in spec.right_joints]))
        keep.append(i)
    return left, right, keep


def _joint_wheels(messages: list, spec: SensorTopic) -> tuple[dict[str, np.ndarray], list[int]]:
    """Wheel rates from JointState: the joint velocities when messages carry them; from a
    driver that publishes positions only, the wheel angles (differentiated later)."""
    left, right, keep = _side_means(messages, spec, "velocity")
    if not keep:
        left, right, keep = _side_means(messages, spec, "position")
        if keep:
            return {"left_angle": np.array(left), "right_angle": np.array(right)}, keep
    return {"left_rate": np.array(left), "right_rate": np.array(right)}, keep


def _wheel_stream(r: _Raw, t: np.ndarray, layout: BagLayout, clean, bag: Path) -> WheelSamples:
    spec = r.spec
    if r.msgtype == "sensor_msgs/msg/JointState":
        if not spec.left_joints or not spec.right_joints or spec.wheel_radius_m is None:
            raise DataError(
                bag,
                "wheels from JointState need left_joints, right_joints and wheel_radius_m",
                field=f"sensors.{spec.name}",
            )
        if "left_angle" in r.fields:  # positions only: mean rates between messages
            angles = clean(
                "wheel", {"t": t, "left": r.fields["left_angle"], "right": r.fields["right_angle"]}
            )
            if angles["t"].size < 2:
                raise DataError(
                    bag,
                    f"{angles['t'].size} JointState message(s) with wheel positions and no "
                    "velocities: wheel speeds need at least 2",
                    field=f"sensors.{spec.name}",
                )
            return wheel_speeds_from_angles(
                angles["t"], angles["left"], angles["right"], spec.wheel_radius_m
            )
        left = r.fields["left_rate"] * spec.wheel_radius_m[0]
        right = r.fields["right_rate"] * spec.wheel_radius_m[1]
    else:
        if layout.wheel_track_m is None:
            raise DataError(
                bag,
                "wheels from a twist need the track width (estimator.wheel_track_m)",
                field=f"sensors.{spec.name}",
            )
        half = 0.5 * layout.wheel_track_m
        left = r.fields["forward"] - r.fields["yaw_rate"] * half
        right = r.fields["forward"] + r.fields["yaw_rate"] * half
    arrays = clean("wheel", {"t": t, "left_speed": left, "right_speed": right})
    return _tables.stream_from_arrays(WheelSamples, arrays)


def _pose_stream(r: _Raw, t: np.ndarray, frames: _Frames, clean, stream: str, bag: Path):
    """The pose stream of one sensor in the body frame, and its static extrinsic (or None)."""
    spec = r.spec
    f = r.fields
    quat_xyzw = f["quaternion_xyzw"]
    _tables.check_quaternions(
        str(bag), quat_xyzw, field_prefix=f"{spec.topic}:", name="orientation"
    )
    finite = np.isfinite(quat_xyzw).all(axis=1) & np.isfinite(f["position"]).all(axis=1)
    finite &= np.isfinite(t)
    unit_xyzw = _tables.normalise_quaternions(np.where(finite[:, None], quat_xyzw, [0, 0, 0, 1.0]))
    quat = xyzw_to_wxyz(torch.as_tensor(unit_xyzw))
    position = torch.as_tensor(np.where(finite[:, None], f["position"], 0.0))
    rot = quat_to_matrix(quat)
    body_sensor = frames.body_from(r, t)
    static = body_sensor if body_sensor.dim() == 2 else None
    sensor_body = inverse_transform(body_sensor)
    body_position = position + (rot @ sensor_body[..., :3, 3:])[..., 0]
    body_quat = _hamilton(quat, matrix_to_quat(sensor_body[..., :3, :3]))
    body_quat = torch.where(body_quat[..., :1] < 0, -body_quat, body_quat)
    arrays: dict[str, np.ndarray] = {
        "t": t,
        "position": np.where(finite[:, None], body_position.numpy(), np.nan),
        "quaternion": np.where(finite[:, None], body_quat.numpy(), np.nan),
    }
    if spec.role != "ground_truth":
        if spec.sigma is not None or not spec.use_message_covariance:
            if spec.sigma is None:
                raise DataError(
                    bag,
                    "use_message_covariance is off: give sigma (6 values, m and rad)",
                    field=f"sensors.{spec.name}.sigma",
                )
            sensor_cov = torch.diag(torch.tensor(spec.sigma, dtype=torch.float64) ** 2)
            sensor_cov = sensor_cov.expand(t.shape[0], 6, 6)
        else:
            ros = torch.as_tensor(f["cov"]).reshape(-1, 6, 6)
            valid = torch.isfinite(ros).all(-1).all(-1) & (
                torch.diagonal(ros, dim1=-2, dim2=-1) > 0
            ).all(-1)
            bad = np.flatnonzero(~valid.numpy() & finite)
            if bad.size:
                i = int(bad[0])
                has = (
                    "has no covariance"
                    if r.msgtype.endswith("PoseStamped")
                    else ("has a covariance without a positive diagonal")
                )
                raise DataError(
                    bag,
                    f"message {i} of '{spec.topic}' {has}; give sigma (6 values, m and rad) "
                    "for this sensor",
                    field=f"sensors.{spec.name}.sigma",
                )
            sensor_cov = _ros_to_native_covariance(torch.where(valid[:, None, None], ros, 0.0), rot)
        cov = _move_pose_covariance(sensor_cov, rot, sensor_body)
        if spec.role == "poses" and spec.fuse is not None:
            cov = _inflate(cov, [k for k, c in enumerate(POSE_COMPONENTS) if c not in spec.fuse])
        arrays["covariance"] = np.where(finite[:, None, None], cov.numpy(), np.nan)
    cleaned = clean(stream, arrays)
    kind = Trajectory if spec.role == "ground_truth" else PoseMeasurements
    return _tables.stream_from_arrays(kind, cleaned), static


def read_referenced_message(path: str | os.PathLike[str], topic: str, bag_ns: int) -> Any:
    """The deserialised message of ``topic`` recorded at ``bag_ns`` (from ``meta["references"]``).

    Raises:
        DataError: no such message.
    """
    from rosbags.highlevel import AnyReader

    bag = Path(path)
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, timestamp, data in reader.messages(conns, start=bag_ns, stop=bag_ns + 1):
            if timestamp == bag_ns:
                return reader.deserialize(data, conn.msgtype)
    raise DataError(bag, f"no message of '{topic}' recorded at {bag_ns} ns")


# --------------------------------------------------------------------------- writing


class _Messages:
    """Builds messages of one typestore (ROS 1 or ROS 2 flavour of the common types)."""

    def __init__(self, typestore) -> None:
        self.store = typestore
        self.types = typestore.types
        self.header_has_seq = "seq" in self.types["std_msgs/msg/Header"].__dataclass_fields__
        self.seq = 0

    def header(self, stamp_ns: int, frame_id: str):
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        stamp = self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        header = self.types["std_msgs/msg/Header"]
        self.seq += 1
        if self.header_has_seq:
            return header(seq=self.seq, stamp=stamp, frame_id=frame_id)
        return header(stamp=stamp, frame_id=frame_id)

    def vector(self, v) -> Any:
        return self.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v) -> Any:
        return self.types["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q_xyzw) -> Any:
        x, y, z, w = (float(c) for c in q_xyzw)
        return self.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def pose(self, position, q_xyzw) -> Any:
        return self.types["geometry_msgs/msg/Pose"](
            position=self.point(position), orientation=self.quaternion(q_xyzw)
        )

    def twist(self, linear, angular) -> Any:
        return self.types["geometry_msgs/msg/Twist"](
            linear=self.vector(linear), angular=self.vector(angular)
        )


def _stamps(t: np.ndarray, origin_ns: int, offset_s: float) -> np.ndarray:
    return origin_ns + np.round((t - offset_s) * 1e9).astype(np.int64)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to(device="cpu", dtype=torch.float64).numpy()


def _messages_for(
    spec: SensorTopic,
    seq: Sequence,
    layout: BagLayout,
    m: _Messages,
    origin_ns: int,
    body_from: dict[str, torch.Tensor],
    gnss_origin,
) -> list[tuple[int, Any]]:
    """(stamp_ns, message) pairs of one sensor from a B = 1 sequence."""
    frame = spec.frame or ""
    out: list[tuple[int, Any]] = []
    if spec.kind == "imu":
        s = seq.imu.compact()
        rot = _np(body_from[spec.name][:3, :3])
        gyro, accel = _np(s.gyro[0]) @ rot, _np(s.accel[0]) @ rot
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        imu = m.types["sensor_msgs/msg/Imu"]
        unknown = np.zeros(9)
        unknown[0] = -1.0
        for k, stamp in enumerate(stamps.tolist()):
            out.append(
                (
                    stamp,
                    imu(
                        header=m.header(stamp, frame),
                        orientation=m.quaternion([0.0, 0.0, 0.0, 1.0]),
                        orientation_covariance=unknown.copy(),
                        angular_velocity=m.vector(gyro[k]),
                        angular_velocity_covariance=np.zeros(9),
                        linear_acceleration=m.vector(accel[k]),
                        linear_acceleration_covariance=np.zeros(9),
                    ),
                )
            )
    elif spec.kind == "gnss":
        if seq.gnss is None:
            return out
        s = seq.gnss.compact()
        lat, lon, alt = enu_to_geodetic(_np(s.position[0]), gnss_origin)
        sigma = _np(s.sigma[0])
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        fix = m.types["sensor_msgs/msg/NavSatFix"]
        status = m.types["sensor_msgs/msg/NavSatStatus"]
        for k, stamp in enumerate(stamps.tolist()):
            known = bool(np.isfinite(sigma[k]).all())
            cov = np.diag(sigma[k] ** 2).reshape(9) if known else np.zeros(9)
            out.append(
                (
                    stamp,
                    fix(
                        header=m.header(stamp, frame),
                        status=status(status=0, service=1),
                        latitude=float(lat[k]),
                        longitude=float(lon[k]),
                        altitude=float(alt[k]),
                        position_covariance=cov,
                        position_covariance_type=2 if known else 0,
                    ),
                )
            )
    elif spec.kind == "gnss_velocity":
        if seq.gnss_velocity is None:
            return out
        s = seq.gnss_velocity.compact()
        velocity, sigma = _np(s.velocity[0]), _np(s.sigma[0])
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        stamped = m.types["geometry_msgs/msg/TwistWithCovarianceStamped"]
        twist_cov = m.types["geometry_msgs/msg/TwistWithCovariance"]
        for k, stamp in enumerate(stamps.tolist()):
            cov = np.zeros((6, 6))
            cov[[0, 1, 2], [0, 1, 2]] = np.where(np.isfinite(sigma[k]), sigma[k] ** 2, 0.0)
            cov[3, 3] = -1.0  # the angular part is not measured
            twist = m.twist(velocity[k], [0.0] * 3)
            out.append(
                (
                    stamp,
                    stamped(
                        header=m.header(stamp, frame),
                        twist=twist_cov(twist=twist, covariance=cov.reshape(36)),
                    ),
                )
            )
    elif spec.kind == "gnss_heading":
        if seq.gnss_heading is None:
            return out
        s = seq.gnss_heading.compact()
        half_yaw = 0.5 * (0.5 * np.pi - _np(s.heading[0]))  # ENU yaw = pi/2 - heading
        sigma = _np(s.sigma[0])
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        imu = m.types["sensor_msgs/msg/Imu"]
        not_given = np.zeros(9)
        not_given[0] = -1.0
        for k, stamp in enumerate(stamps.tolist()):
            cov = np.zeros(9)
            cov[[0, 4]] = 1000.0  # roll and pitch not measured (as ublox_gps writes)
            cov[8] = sigma[k] ** 2 if np.isfinite(sigma[k]) else 0.0
            quat = [0.0, 0.0, math.sin(half_yaw[k]), math.cos(half_yaw[k])]
            out.append(
                (
                    stamp,
                    imu(
                        header=m.header(stamp, frame),
                        orientation=m.quaternion(quat),
                        orientation_covariance=cov,
                        angular_velocity=m.vector([0.0] * 3),
                        angular_velocity_covariance=not_given.copy(),
                        linear_acceleration=m.vector([0.0] * 3),
                        linear_acceleration_covariance=not_given.copy(),
                    ),
                )
            )
    elif spec.kind == "magnetometer":
        if seq.magnetometer is None:
            return out
        s = seq.magnetometer.compact()
        rot = _np(body_from[spec.name][:3, :3])
        tesla = 1e-6 * _np(s.field[0]) @ rot  # body -> sensor axes
        sigma = _np(s.sigma[0])
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        magnetic = m.types["sensor_msgs/msg/MagneticField"]
        for k, stamp in enumerate(stamps.tolist()):
            variance = (1e-6 * sigma[k]) ** 2 if np.isfinite(sigma[k]) else 0.0
            out.append(
                (
                    stamp,
                    magnetic(
                        header=m.header(stamp, frame),
                        magnetic_field=m.vector(tesla[k]),
                        magnetic_field_covariance=np.diag([variance] * 3).reshape(9),
                    ),
                )
            )
    elif spec.kind == "wheels":
        if seq.wheel is None:
            return out
        s = seq.wheel.compact()
        left, right = _np(s.left_speed[0]), _np(s.right_speed[0])
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        joints = spec.left_joints + spec.right_joints
        state = m.types["sensor_msgs/msg/JointState"]
        twist = m.types["geometry_msgs/msg/TwistStamped"]
        for k, stamp in enumerate(stamps.tolist()):
            if joints:
                rates = [left[k] / spec.wheel_radius_m[0]] * len(spec.left_joints) + [
                    right[k] / spec.wheel_radius_m[1]
                ] * len(spec.right_joints)
                out.append(
                    (
                        stamp,
                        state(
                            header=m.header(stamp, frame),
                            name=list(joints),
                            position=np.zeros(len(joints)),
                            velocity=np.array(rates, dtype=np.float64),
                            effort=np.zeros(0),
                        ),
                    )
                )
            else:
                forward = 0.5 * (left[k] + right[k])
                yaw_rate = (right[k] - left[k]) / layout.wheel_track_m
                out.append(
                    (
                        stamp,
                        twist(
                            header=m.header(stamp, frame),
                            twist=m.twist([forward, 0.0, 0.0], [0.0, 0.0, yaw_rate]),
                        ),
                    )
                )
    elif spec.kind == "pose":
        stream = {
            "pose_source": seq.pose_sources.get(spec.source_name or spec.name),
            "poses": seq.poses,
            "ground_truth": seq.ground_truth,
        }[spec.role]
        if stream is None:
            return out
        s = stream.compact()
        quat = s.quaternion[0]
        rot = quat_to_matrix(quat)
        body_sensor = body_from[spec.name]
        sensor_position = s.position[0] + (rot @ body_sensor[:3, 3:])[..., 0]
        sensor_quat = _hamilton(quat, matrix_to_quat(body_sensor[:3, :3]))
        sensor_rot = quat_to_matrix(sensor_quat)
        cov = None
        if spec.role != "ground_truth":
            cov = _move_pose_covariance(s.covariance[0], rot, body_sensor)
            cov = _native_to_ros_covariance(cov, sensor_rot)
        position, xyzw = _np(sensor_position), _np(wxyz_to_xyzw(sensor_quat))
        stamps = _stamps(_np(s.t[0]), origin_ns, spec.time_offset_s)
        odom = m.types["nav_msgs/msg/Odometry"]
        with_cov = m.types["geometry_msgs/msg/PoseWithCovariance"]
        twist_cov = m.types["geometry_msgs/msg/TwistWithCovariance"]
        for k, stamp in enumerate(stamps.tolist()):
            covariance = np.zeros(36) if cov is None else _np(cov[k]).reshape(36)
            out.append(
                (
                    stamp,
                    odom(
                        header=m.header(stamp, "world"),
                        child_frame_id=frame,
                        pose=with_cov(pose=m.pose(position[k], xyzw[k]), covariance=covariance),
                        twist=twist_cov(
                            twist=m.twist([0.0] * 3, [0.0] * 3), covariance=np.zeros(36)
                        ),
                    ),
                )
            )
    return out


_WRITE_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "gnss": "sensor_msgs/msg/NavSatFix",
    "gnss_velocity": "geometry_msgs/msg/TwistWithCovarianceStamped",
    "gnss_heading": "sensor_msgs/msg/Imu",
    "magnetometer": "sensor_msgs/msg/MagneticField",
    "pose": "nav_msgs/msg/Odometry",
}


def write_rosbag(
    seq: Sequence,
    path: str | os.PathLike[str],
    layout: BagLayout,
    *,
    version: int = 2,
    time_origin_ns: int = 0,
    gnss_origin: tuple[float, float, float] | None = None,
) -> Path:
    """Write a B = 1 sequence as a ROS bag with the topics of ``layout`` (the inverse of
    :func:`read_rosbag`).

    Each sensor of ``layout`` becomes its topic: imu -> ``Imu``; gnss -> ``NavSatFix``
    about ``gnss_origin`` (diagonal covariance from the sigmas, UNKNOWN when NaN);
    gnss_velocity -> ``TwistWithCovarianceStamped`` (the ENU velocity, NaN up kept; the
    linear covariance diagonal from the sigmas, 0 where NaN; angular -1); gnss_heading
    -> ``Imu`` with only the orientation (yaw ``pi/2 - heading`` about the vertical, the yaw
    variance ``sigma^2`` in ``orientation_covariance[8]``, 0 where NaN, roll and pitch 1000;
    the rates and accelerations -1, "not provided"); magnetometer -> ``MagneticField`` in
    tesla in the sensor's axes (covariance ``diag(sigma^2)``, T^2, all zero where NaN:
    "unknown"); wheels
    -> ``JointState`` velocities (rim speed / radius per joint) when the sensor names
    joints, else ``TwistStamped``; pose (each role) -> ``Odometry`` of the sensor frame
    with the covariance in ROS order. Data are turned from the body frame into each
    sensor's frame with the layout's static frames (``frame`` must then be set for every
    sensor). Header stamps are ``time_origin_ns + round((t - time_offset_s) * 1e9)``; the
    recording time equals the header stamp. Sensors of kind joints / image / laser_scan
    write nothing.

    Args:
        seq: the sequence, B = 1.
        path: a new ``.bag`` file (version 1) or a new rosbag2 folder (version 2).
        layout: the topics and frames.
        version: 1 (rosbag1, ROS 1 Noetic types) or 2 (rosbag2 sqlite3, ROS 2 Humble
            types).
        time_origin_ns: added to the sequence's times, ns.
        gnss_origin: ``(lat_deg, lon_deg, alt_m)``; needed when a gnss sensor is written.

    Returns:
        the path written.

    Raises:
        ValueError: B != 1, an existing path, a missing ``gnss_origin``, a sensor frame
            that moves with a joint.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    if seq.batch_size != 1:
        raise ValueError(f"write_rosbag writes one sequence, got B = {seq.batch_size}")
    target = Path(path)
    if target.exists():
        raise ValueError(f"{target} exists; a bag is written to a new path")
    if version not in (1, 2):
        raise ValueError(f"version must be 1 or 2, got {version!r}")
    if layout.sensor("gnss") is not None and seq.gnss is not None and gnss_origin is None:
        raise ValueError("writing a gnss sensor needs gnss_origin = (lat_deg, lon_deg, alt_m)")
    store = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    m = _Messages(store)
    body_from = _static_extrinsics(layout)
    messages: list[tuple[int, int, str, Any]] = []
    for order, spec in enumerate(layout.sensors):
        if spec.kind in ("joints", "image", "laser_scan"):
            continue
        for stamp, msg in _messages_for(
            spec, seq, layout, m, time_origin_ns, body_from, gnss_origin
        ):
            messages.append((stamp, order, spec.topic, msg))
    messages.sort(key=lambda x: (x[0], x[1]))
    serialize = store.serialize_ros1 if version == 1 else store.serialize_cdr
    writer = Writer1(target) if version == 1 else Writer2(target, version=9)
    with writer:
        connections = {}
        for spec in layout.sensors:
            if spec.kind in ("joints", "image", "laser_scan") or spec.topic in connections:
                continue
            msgtype = _WRITE_TYPES.get(spec.kind)
            if spec.kind == "wheels":
                msgtype = (
                    "sensor_msgs/msg/JointState"
                    if spec.left_joints
                    else "geometry_msgs/msg/TwistStamped"
                )
            connections[spec.topic] = (
                writer.add_connection(spec.topic, msgtype, typestore=store),
                msgtype,
            )
        for stamp, _, topic, msg in messages:
            conn, msgtype = connections[topic]
            writer.write(conn, stamp, serialize(msg, msgtype))
    return target


def _static_extrinsics(layout: BagLayout) -> dict[str, torch.Tensor]:
    """``T_body_sensor`` (4, 4) per sensor from the layout's frames (identity without)."""
    out = {}
    eye = torch.eye(4, dtype=torch.float64)
    if layout.frames is None:
        return {s.name: eye for s in layout.sensors}
    imu = layout.sensor("imu")
    if imu.frame is None:
        raise ValueError("writing with frames needs the imu sensor's frame")
    body = layout.body_frame or imu.frame
    body_imu = layout.frames.transform(body, imu.frame, layout.joint_values or None)
    shift = eye.clone()
    shift[:3, 3] = -body_imu[:3, 3]
    for spec in layout.sensors:
        if spec.kind in ("joints", "image", "laser_scan"):
            continue
        if spec.frame is None:
            raise ValueError(f"writing with frames needs the frame of sensor '{spec.name}'")
        values = {
            j: layout.joint_values[j]
            for j in layout.frames.joints_between(body, spec.frame)
            if j in layout.joint_values
        }
        transform = layout.frames.transform(body, spec.frame, values or None)
        out[spec.name] = body_imu if spec.kind == "imu" else shift @ transform
    return out


def write_odometry_rosbag2(
    trajectory: Trajectory,
    path: str | os.PathLike[str],
    *,
    topic: str = "/msf/odometry",
    frame_id: str = "enu",
    child_frame_id: str = "base_link",
    time_origin_ns: int = 0,
    covariance: torch.Tensor | None = None,
    velocity: torch.Tensor | None = None,
    angular_velocity: torch.Tensor | None = None,
    twist_covariance: torch.Tensor | None = None,
) -> Path:
    """Write a B = 1 trajectory as ``nav_msgs/Odometry`` in a new rosbag2 folder (sqlite3).

    The folder is written next to ``path`` under a temporary name and renamed into place
    (an existing folder at ``path`` is replaced only once the new one is complete).

    Args:
        trajectory: the poses, B = 1: ``t`` (1, N) s, ``position`` (1, N, 3) m,
            ``quaternion`` (1, N, 4) ``[w, x, y, z]``.
        path: the rosbag2 folder.
        topic, frame_id, child_frame_id: the topic and the message frames.
        time_origin_ns: stamps are ``time_origin_ns + round(t * 1e9)``.
        covariance: optional (1, N, 6, 6) over ``[dp (world), dtheta (body)]``, written in
            ROS order (rotation about the world axes); zeros when None.
        velocity: optional (1, N, 3) world velocity, m/s, written as the twist's linear
            part in the child frame's axes (``R^T v``); zeros when None.
        angular_velocity: optional (1, N, 3) angular rate in the child frame's axes, rad/s,
            the twist's angular part; zeros when None.
        twist_covariance: optional (1, N, 6, 6) over ``[linear, angular]`` in the child
            frame's axes (ROS order); zeros when None.

    Returns:
        the folder written.
    """
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    if trajectory.batch_size != 1:
        raise ValueError(
            f"write_odometry_rosbag2 writes one trajectory, got B = {trajectory.batch_size}"
        )
    keep = trajectory.mask[0]
    t = _np(trajectory.t[0, keep])
    position = _np(trajectory.position[0, keep])
    quat = trajectory.quaternion[0, keep].detach().to(torch.float64)
    rot = quat_to_matrix(quat)
    xyzw = _np(wxyz_to_xyzw(quat))
    cov = None
    if covariance is not None:
        cov = _np(_native_to_ros_covariance(covariance[0, keep].to(torch.float64), rot))
    body_velocity = angular = twist_cov_rows = None
    if velocity is not None:
        body_velocity = _np((rot.mT @ velocity[0, keep].to(torch.float64)[..., None])[..., 0])
    if angular_velocity is not None:
        angular = _np(angular_velocity[0, keep].to(torch.float64))
    if twist_covariance is not None:
        twist_cov_rows = _np(twist_covariance[0, keep].to(torch.float64)).reshape(-1, 36)
    store = get_typestore(Stores.ROS2_HUMBLE)
    m = _Messages(store)
    odom = store.types["nav_msgs/msg/Odometry"]
    with_cov = store.types["geometry_msgs/msg/PoseWithCovariance"]
    twist_cov = store.types["geometry_msgs/msg/TwistWithCovariance"]
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    staged = scratch / "bag"
    try:
        with Writer(staged, version=9) as writer:
            conn = writer.add_connection(topic, "nav_msgs/msg/Odometry", typestore=store)
            stamps = _stamps(t, time_origin_ns, 0.0)
            for k, stamp in enumerate(stamps.tolist()):
                linear = [0.0] * 3 if body_velocity is None else body_velocity[k]
                rate = [0.0] * 3 if angular is None else angular[k]
                spread = np.zeros(36) if twist_cov_rows is None else twist_cov_rows[k].copy()
                msg = odom(
                    header=m.header(stamp, frame_id),
                    child_frame_id=child_frame_id,
                    pose=with_cov(
                        pose=m.pose(position[k], xyzw[k]),
                        covariance=np.zeros(36) if cov is None else cov[k].reshape(36).copy(),
                    ),
                    twist=twist_cov(twist=m.twist(linear, rate), covariance=spread),
                )
                writer.write(conn, stamp, store.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
        if target.exists():
            os.replace(target, scratch / "replaced")
        os.replace(staged, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(scratch)
    return target
