"""One YAML per robot: sensors and their topics, frames, estimator noise and gating.

The file is validated when it is loaded; an error is a
:class:`~msf_torch.io.errors.DataError` that names the file, the line and the key path
(``robot.yaml:14: field 'sensors.gps.origin': ...``). ``msf config check FILE`` runs the
same validation. ``docs/ros-and-robots.md`` lists every key with its default.

Top-level keys
--------------
``robot``
    ``name`` (string, optional).
``frames`` (optional; without it every sensor sits at the body origin with the body axes)
    ``urdf`` (path, relative to the YAML file), ``body`` (the estimator's body axes;
    default: the IMU's frame), ``transforms`` (a list of static transforms ``{parent,
    child, xyz, rpy}`` or ``{parent, child, xyz, quaternion_xyzw}``: the fallback when
    there is no URDF, or frames the URDF lacks), ``joints`` (``topic``: a JointState topic
    giving the movable joints' positions; ``values``: fixed joint values by name).
``time``
    ``origin_ns``: ``first`` (default: the earliest stamp read) or an integer in ns.
``sensors`` (required; a mapping name -> sensor)
    Every sensor: ``type`` (imu | gnss | gnss_velocity | gnss_heading | magnetometer |
    wheels | pose | joints | image | laser_scan),
    ``topic``, ``enabled`` (default true), ``frame`` (default: from the messages),
    ``stamp`` (header | bag), ``time_offset_s`` (0). Per type (see
    :mod:`msf_torch.io.rosbag` for what they do): gnss ``origin`` (first | [lat_deg,
    lon_deg, alt_m]), ``use_message_covariance`` (true), ``min_fix_status`` (0), ``fuse``
    (subset of [x, y, z]); gnss_velocity ``use_message_covariance`` (true); gnss_heading
    (a dual-antenna heading as ``sensor_msgs/Imu``; its frame is the primary antenna's)
    ``use_message_covariance`` (true), ``baseline`` (``{secondary_frame: FRAME}``: the
    secondary antenna's frame; needs ``frames``); magnetometer
    (``sensor_msgs/MagneticField``) ``use_message_covariance`` (true), ``declination_deg``,
    ``hard_iron_uT`` (3 numbers), ``soft_iron`` (9 numbers, row-major 3x3 ``W``; its
    determinant must be positive), ``sigma_uT``; wheels
    ``left_joints``, ``right_joints``, ``wheel_radius_m``
    (a number or [left, right]) for JointState, ``fuse`` (subset of [speed, yaw_rate],
    default [speed]); pose ``role`` (pose_source | poses | ground_truth),
    ``source_name``, ``sigma`` (6 numbers), ``use_message_covariance``, ``fuse`` (subset
    of [x, y, z, roll, pitch, yaw]; role poses only). Online calibration switches
    (``frontend.calibration``, default false): wheels ``calibrate`` (radius ratios and track
    width; the yaw-rate row is then fused), gnss ``calibrate_time_offset``, pose
    ``calibrate_time_offset`` (role pose_source; the estimate starts at 0 on top of the
    sensor's ``time_offset_s``); extrinsics: gnss ``calibrate_lever_arm`` (starts at the
    lever arm from the frames or ``estimator``), pose ``calibrate_extrinsics`` (role
    pose_source: lever arm and mounting rotation on top of the frames' transform, start at
    0), imu ``calibrate_rotation`` (the IMU's rotation against the vehicle axes of the wheel
    and non-holonomic models), gnss_heading ``calibrate_offset`` (the antenna baseline's
    turn about body z) and ``calibrate_time_offset`` (its latency), magnetometer
    ``calibrate_declination`` (the azimuth of magnetic north, starting at
    ``declination_deg``).
``estimator``
    Front-end settings: any key of :class:`~msf_torch.frontend.config.EskfConfig`
    (noise densities, sigmas, gating, initialisation, slip detection, ...).
``smoother``
    The back end's section, as in a front-end config (``msf run --smooth``);
    ``calibrate_wheels: true`` there makes the wheel radii and track width variables of the
    full-batch smoother (with the wheels' ``calibrate`` on as well).

Derived estimator settings
--------------------------
With ``frames``, :meth:`RobotConfig.eskf_config` sets ``gnss_lever_arm_m`` and
``wheel_lever_arm_m`` from the extrinsics the bag reader computed, and
``wheel_track_m`` from the URDF (the distance, along the body y axis, between the left and
right wheel joints' frames) unless ``estimator`` gives it. A gnss_heading sensor with
``baseline`` sets ``gnss_heading_baseline_m``: the secondary antenna frame's position minus
the primary's (the sensor's frame), in the body axes, m; without ``baseline``,
``estimator.gnss_heading_baseline_m`` applies. A magnetometer's ``declination_deg`` sets
``magnetometer_declination_rad`` (in rad), ``sigma_uT`` ``magnetometer_sigma_uT``, and its
``hard_iron_uT`` ``b`` and ``soft_iron`` ``W``, given in the sensor's own axes (as a fit on
the sensor's readings gives them), set ``magnetometer_hard_iron_uT = R b`` and
``magnetometer_soft_iron = R W R^T`` with ``R = R_body_sensor`` (the frame's rotation in the
body axes; identity without ``frames``): the reader turns the readings ``m`` into the body
axes, and ``R W R^T (R m - R b) = R W (m - b)``, the corrected field turned likewise.
Setting a derived key in ``estimator`` as well is an error that names both. The wheels'
``fuse`` sets ``wheel_yaw_rate_update``; the calibration switches set ``calibrate_wheels``,
``calibrate_time_offsets``, ``calibrate_gnss_lever_arm``, ``calibrate_pose_extrinsics``,
``calibrate_imu_body_rotation``, ``calibrate_gnss_heading_offset`` and
``calibrate_magnetometer_declination``.
"""

from __future__ import annotations

__all__ = ["RobotConfig", "load_robot_config", "is_robot_config", "ROBOT_KEYS"]

import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml

from msf_torch.backend.window import SmootherConfig
from msf_torch.frontend.config import EskfConfig
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.io.errors import DataError
from msf_torch.io.rosbag import (
    GNSS_COMPONENTS,
    POSE_COMPONENTS,
    POSE_ROLES,
    SENSOR_KINDS,
    WHEEL_COMPONENTS,
    BagLayout,
    SensorTopic,
)
from msf_torch.io.yaml_files import ConfigLoader, YamlDocument, named_key, read_yaml
from msf_torch.robot.frames import FrameTree, StaticTransform

ROBOT_KEYS = ("robot", "frames", "time", "sensors", "estimator", "smoother")
"""Top-level keys of a robot YAML."""

_COMMON = ("type", "topic", "enabled", "frame", "stamp", "time_offset_s")
_PER_KIND = {
    "imu": ("calibrate_rotation",),
    "gnss": (
        "origin",
        "use_message_covariance",
        "min_fix_status",
        "fuse",
        "calibrate_time_offset",
        "calibrate_lever_arm",
    ),
    "gnss_velocity": ("use_message_covariance",),
    "gnss_heading": (
        "use_message_covariance",
        "baseline",
        "calibrate_offset",
        "calibrate_time_offset",
    ),
    "magnetometer": (
        "use_message_covariance",
        "declination_deg",
        "hard_iron_uT",
        "soft_iron",
        "sigma_uT",
        "calibrate_declination",
    ),
    "wheels": ("left_joints", "right_joints", "wheel_radius_m", "fuse", "calibrate"),
    "pose": (
        "role",
        "source_name",
        "sigma",
        "use_message_covariance",
        "fuse",
        "calibrate_time_offset",
        "calibrate_extrinsics",
    ),
    "joints": (),
    "image": (),
    "laser_scan": (),
}

_MAGNETOMETER_KEYS = {
    "declination_deg": "magnetometer_declination_rad",
    "hard_iron_uT": "magnetometer_hard_iron_uT",
    "soft_iron": "magnetometer_soft_iron",
    "sigma_uT": "magnetometer_sigma_uT",
}
"""A magnetometer's options and the EskfConfig keys they set (module docstring)."""


class _Checker:
    """Typed access to the loaded YAML with errors naming file, line and key path."""

    def __init__(self, path: str, lines: dict[tuple, int]) -> None:
        self.path = path
        self.lines = lines

    def fail(self, keys: tuple, problem: str) -> DataError:
        line = YamlDocument(Path(self.path), None, self.lines).line_of(*keys)
        name = ".".join(str(k) if not isinstance(k, int) else f"[{k}]" for k in keys)
        return DataError(self.path, problem, line=line, field=name.replace(".[", "["))

    def mapping(self, value: Any, keys: tuple, allowed: tuple[str, ...]) -> dict[str, Any]:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.fail(keys, f"must be a mapping, got {type(value).__name__}")
        for key in value:
            if key not in allowed:
                raise self.fail((*keys, key), f"unknown key (allowed here: {', '.join(allowed)})")
        return value

    def string(self, value: Any, keys: tuple) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(keys, f"must be a non-empty string, got {value!r}")
        return value

    def boolean(self, value: Any, keys: tuple) -> bool:
        if not isinstance(value, bool):
            raise self.fail(keys, f"must be true or false, got {value!r}")
        return value

    def number(self, value: Any, keys: tuple, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(keys, f"must be a number, got {value!r}")
        if not math.isfinite(value) or (positive and value <= 0):
            raise self.fail(keys, f"must be a {'positive ' if positive else ''}finite number")
        return float(value)

    def numbers(self, value: Any, keys: tuple, count: int, positive: bool = False) -> list[float]:
        if not isinstance(value, list) or len(value) != count:
            raise self.fail(keys, f"must be a list of {count} numbers, got {value!r}")
        return [self.number(v, (*keys, i), positive) for i, v in enumerate(value)]

    def strings(self, value: Any, keys: tuple) -> tuple[str, ...]:
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, list) or not items:
            raise self.fail(keys, f"must be a name or a non-empty list of names, got {value!r}")
        return tuple(self.string(v, (*keys, i)) for i, v in enumerate(items))

    def subset(self, value: Any, keys: tuple, allowed: tuple[str, ...]) -> tuple[str, ...]:
        if not isinstance(value, list) or not value:
            raise self.fail(keys, f"must be a non-empty list from {list(allowed)}, got {value!r}")
        for i, item in enumerate(value):
            if item not in allowed:
                raise self.fail((*keys, i), f"unknown component {item!r} (allowed: {allowed})")
        if len(set(value)) != len(value):
            raise self.fail(keys, f"repeats a component: {value!r}")
        return tuple(value)


@dataclass
class RobotConfig:
    """A validated robot YAML (module docstring).

    Attributes:
        path: the file it came from, or None.
        name: ``robot.name`` (default: the file's stem).
        layout: the bag topics, frames and time / GNSS origins for
            :func:`~msf_torch.io.rosbag.read_rosbag`.
        estimator: the ``estimator`` section (EskfConfig keys), validated.
        wheel_fuse: the wheels' ``fuse`` list, or None when not given.
        disabled: names of sensors with ``enabled: false``.
        calibrate: sensors with an online-calibration switch on: ``"wheels"``, ``"gnss"``,
            ``"pose:<source name>"``.
        calibrate_extrinsics: sensors with an extrinsic-calibration switch on: ``"imu"``,
            ``"gnss"``, ``"pose:<source name>"``.
        heading_secondary_frame: the gnss_heading sensor's ``baseline.secondary_frame``
            (the secondary antenna's frame), or None.
        magnetometer: the magnetometer's options given (keys of ``_MAGNETOMETER_KEYS``) as
            written: ``declination_deg`` deg, ``hard_iron_uT`` (3) uT and ``soft_iron`` (9)
            in the sensor's axes, ``sigma_uT`` uT.
    """

    path: Path | None
    name: str
    layout: BagLayout
    estimator: dict[str, Any] = field(default_factory=dict)
    wheel_fuse: tuple[str, ...] | None = None
    disabled: tuple[str, ...] = ()
    calibrate: tuple[str, ...] = ()
    calibrate_extrinsics: tuple[str, ...] = ()
    heading_secondary_frame: str | None = None
    magnetometer: dict[str, Any] = field(default_factory=dict)
    _lines: dict[tuple, int] = field(default_factory=dict, repr=False)

    @property
    def frames(self) -> FrameTree | None:
        """The robot's frames, or None."""
        return self.layout.frames

    def _fail(self, keys: tuple, problem: str) -> DataError:
        return _Checker(str(self.path or "robot config"), self._lines).fail(keys, problem)

    def _wheel_track_from_urdf(self) -> float | None:
        """Track width from the URDF wheel joints' frames (body y distance), or None."""
        wheels = self.layout.sensor("wheels")
        tree = self.layout.frames
        if wheels is None or tree is None or not wheels.left_joints:
            return None
        frames = {}
        for joint in wheels.left_joints + wheels.right_joints:
            frame = tree.joint_frame(joint)
            if frame is None:
                return None
            frames[joint] = frame
        imu = self.layout.sensor("imu")
        body = self.layout.body_frame or imu.frame
        if body is None:
            return None

        def mean_y(joints: tuple[str, ...]) -> float:
            values = {j: 0.0 for j in tree.joint_names if j in joints}
            ys = [float(tree.transform(body, frames[j], values or None)[1, 3]) for j in joints]
            return sum(ys) / len(ys)

        return abs(mean_y(wheels.left_joints) - mean_y(wheels.right_joints))

    def _from_imu(self, frame: str) -> torch.Tensor:
        """Position (3,) of ``frame`` from the IMU in the body axes, m (the frame's joints
        at ``frames.joints.values``)."""
        tree = self.layout.frames
        imu = self.layout.sensor("imu")
        body = self.layout.body_frame or imu.frame
        values = {
            j: self.layout.joint_values[j]
            for j in tree.joints_between(body, frame)
            if j in self.layout.joint_values
        }
        position = tree.transform(body, frame, values or None)[:3, 3]
        return position - tree.transform(body, imu.frame)[:3, 3]

    def _heading_baseline(self, primary: torch.Tensor) -> list[float]:
        """``gnss_heading_baseline_m`` (3,) m: the secondary antenna frame's position minus
        the primary's (``primary`` (3,) m: the heading sensor's, from the IMU in the body
        axes), in the body axes.

        Raises:
            DataError: the baseline has no horizontal part (it would give no heading).
        """
        heading = self.layout.sensor("gnss_heading")
        baseline = self._from_imu(self.heading_secondary_frame) - primary
        if float(torch.linalg.vector_norm(baseline[:2])) < 1e-3:
            raise self._fail(
                ("sensors", heading.name, "baseline", "secondary_frame"),
                f"the antennas' baseline {baseline.tolist()} m (body frame) has no horizontal "
                "part (x, y under 1 mm): it gives no heading",
            )
        return baseline.tolist()

    def _magnetometer_settings(
        self, values: Mapping[str, Any], extrinsics: Mapping[str, Any]
    ) -> dict[str, Any]:
        """EskfConfig keys from the magnetometer's options (module docstring). The hard and
        soft iron are turned into the body axes with the sensor's rotation, known without
        ``frames`` (identity) or from ``extrinsics`` (``T_body_sensor`` 4x4 by sensor name);
        otherwise they are left out (a check of the file without a bag).

        Raises:
            DataError: a key also set in ``estimator`` (``values``).
        """
        sensor = self.layout.sensor("magnetometer")
        out: dict[str, Any] = {}
        if sensor is None:
            return out
        rotation = None
        if self.layout.frames is None:
            rotation = torch.eye(3, dtype=torch.float64)
        elif sensor.name in extrinsics:
            rotation = torch.tensor(extrinsics[sensor.name], dtype=torch.float64)[:3, :3]
        for option, value in self.magnetometer.items():
            key = _MAGNETOMETER_KEYS[option]
            if key in values:
                raise self._fail(
                    ("estimator", key),
                    f"is also given by sensors.{sensor.name}.{option}; set it in one place",
                )
            if option == "declination_deg":
                out[key] = math.radians(value)
            elif option == "sigma_uT":
                out[key] = value
            elif rotation is not None and option == "hard_iron_uT":
                out[key] = (rotation @ torch.tensor(value, dtype=torch.float64)).tolist()
            elif rotation is not None:
                soft = torch.tensor(value, dtype=torch.float64).reshape(3, 3)
                out[key] = (rotation @ soft @ rotation.mT).reshape(9).tolist()
        return out

    def eskf_config(
        self, meta: Mapping[str, Any] | None = None, overrides: Mapping[str, Any] | None = None
    ) -> EskfConfig:
        """The front end's settings: ``estimator`` + derived geometry + ``overrides``.

        Args:
            meta: ``Sequence.meta`` from :func:`~msf_torch.io.rosbag.read_rosbag` (its
                ``extrinsics`` give the lever arms); None: no derived lever arms.
            overrides: EskfConfig keys that win over everything (command-line switches).

        Raises:
            DataError: a derived key also set in ``estimator``, a wheel frame rotated
                against the body, or a setting EskfConfig rejects (naming the key).
        """
        values = dict(self.estimator)
        derived: dict[str, Any] = {}
        extrinsics = (meta or {}).get("extrinsics", {})
        # the antenna of the fixes, else of the velocities (the reader checks they agree)
        antenna = self.layout.sensor("gnss") or self.layout.sensor("gnss_velocity")
        if self.layout.frames is not None:
            if antenna is not None and antenna.name in extrinsics:
                derived["gnss_lever_arm_m"] = [row[3] for row in extrinsics[antenna.name][:3]]
            wheels = self.layout.sensor("wheels")
            if wheels is not None and wheels.name in extrinsics:
                matrix = torch.tensor(extrinsics[wheels.name], dtype=torch.float64)
                turn = (matrix[:3, :3] - torch.eye(3, dtype=torch.float64)).abs().max()
                if float(turn) > 1e-9:
                    raise self._fail(
                        ("sensors", wheels.name, "frame"),
                        "the wheel frame is rotated against the body axes; the wheel model "
                        "measures speed along the body x axis (choose frames.body so that "
                        "the two agree)",
                    )
                derived["wheel_lever_arm_m"] = matrix[:3, 3].tolist()
            track = self._wheel_track_from_urdf()
            if track is not None and "wheel_track_m" not in values:
                derived["wheel_track_m"] = track
        heading = self.layout.sensor("gnss_heading")
        if heading is not None and self.heading_secondary_frame is not None:
            if "gnss_heading_baseline_m" in values:
                raise self._fail(
                    ("estimator", "gnss_heading_baseline_m"),
                    f"is also given by sensors.{heading.name}.baseline.secondary_frame (the "
                    "antenna frames); set it in one place",
                )
            if heading.name in extrinsics:
                primary = [row[3] for row in extrinsics[heading.name][:3]]
                derived["gnss_heading_baseline_m"] = self._heading_baseline(
                    torch.tensor(primary, dtype=torch.float64)
                )
        derived.update(self._magnetometer_settings(values, extrinsics))
        if self.layout.frames is not None:
            for key, sensor in (
                ("gnss_lever_arm_m", antenna),
                ("wheel_lever_arm_m", self.layout.sensor("wheels")),
            ):
                if key in values and sensor is not None:
                    raise self._fail(
                        ("estimator", key),
                        f"is also given by the robot's frames (sensor '{sensor.name}'); set it "
                        "in one place",
                    )
        if self.wheel_fuse is not None:
            if "wheel_yaw_rate_update" in values:
                raise self._fail(
                    ("estimator", "wheel_yaw_rate_update"),
                    "is also set by the wheels' fuse list; set it in one place",
                )
            derived["wheel_yaw_rate_update"] = "yaw_rate" in self.wheel_fuse
        if self.calibrate:
            for key in ("calibrate_wheels", "calibrate_time_offsets"):
                if key in values:
                    raise self._fail(
                        ("estimator", key),
                        "is also set by the sensors' calibrate switches; set it in one place",
                    )
            derived["calibrate_wheels"] = "wheels" in self.calibrate
            derived["calibrate_time_offsets"] = [k for k in self.calibrate if k != "wheels"]
        if self.calibrate_extrinsics:
            extrinsic_keys = (
                "calibrate_gnss_lever_arm",
                "calibrate_pose_extrinsics",
                "calibrate_imu_body_rotation",
                "calibrate_gnss_heading_offset",
                "calibrate_magnetometer_declination",
            )
            for key in extrinsic_keys:
                if key in values:
                    raise self._fail(
                        ("estimator", key),
                        "is also set by the sensors' calibrate switches; set it in one place",
                    )
            chosen = self.calibrate_extrinsics
            derived["calibrate_gnss_lever_arm"] = "gnss" in chosen
            derived["calibrate_pose_extrinsics"] = [k for k in chosen if k.startswith("pose:")]
            derived["calibrate_imu_body_rotation"] = "imu" in chosen
            derived["calibrate_gnss_heading_offset"] = "gnss_heading" in chosen
            derived["calibrate_magnetometer_declination"] = "magnetometer" in chosen
        values.update(derived)
        values.update(overrides or {})
        return _eskf_config(values, self._fail)

    def summary(self) -> dict[str, Any]:
        """A JSON-ready description (what ``msf config check`` prints).

        With ``frames``: ``extrinsics_in_body`` gives each sensor frame that the YAML names
        and no joint moves as its pose in ``frames.body`` (``xyz`` m from the body frame's
        origin, ``quaternion_wxyz``); ``derived`` gives the estimator settings the frames
        set: ``gnss_lever_arm_m`` and ``wheel_lever_arm_m`` (from the IMU, the estimator's
        body origin, in the body axes), ``gnss_heading_baseline_m`` (the two antenna
        frames), the magnetometer's keys its options set (hard and soft iron in the body
        axes; for a magnetometer whose frame the YAML names), ``wheel_track_m`` (URDF) and
        ``wheel_yaw_rate_update`` (the wheels' ``fuse``) where they differ from the defaults.
        """
        layout = self.layout
        out: dict[str, Any] = {
            "file": None if self.path is None else str(self.path),
            "name": self.name,
            "sensors": {
                s.name: {"type": s.kind, "topic": s.topic}
                | ({"role": s.role} if s.kind == "pose" else {})
                for s in layout.sensors
            },
            "disabled": list(self.disabled),
            "time_origin_ns": "first" if layout.time_origin_ns is None else layout.time_origin_ns,
            "gnss_origin": "first" if layout.gnss_origin is None else list(layout.gnss_origin),
            "estimator": dict(self.estimator),
        }
        if layout.frames is not None:
            tree = layout.frames
            imu = layout.sensor("imu")
            body = layout.body_frame or imu.frame
            out["frames"] = tree.frames
            out["joints"] = tree.joint_names
            out["body_frame"] = body
            origin = None
            if not tree.joints_between(body, imu.frame):
                origin = tree.transform(body, imu.frame)[:3, 3]
            extrinsics = {}
            from_imu = {}
            for sensor in layout.sensors:
                if sensor.frame is None or tree.joints_between(body, sensor.frame):
                    continue
                matrix = tree.transform(body, sensor.frame)
                extrinsics[sensor.name] = {
                    "xyz": matrix[:3, 3].tolist(),
                    "quaternion_wxyz": matrix_to_quat(matrix[:3, :3]).tolist(),
                }
                if origin is not None:
                    shifted = matrix.clone()
                    shifted[:3, 3] -= origin
                    from_imu[sensor.name] = shifted.tolist()
            out["extrinsics_in_body"] = extrinsics
            derived = self.eskf_config({"extrinsics": from_imu})
            # the antenna: the gnss sensor, else a gnss_velocity sensor alone
            antenna = layout.sensor("gnss") or layout.sensor("gnss_velocity")
            heading = layout.sensor("gnss_heading") if self.heading_secondary_frame else None
            placed = {
                "gnss_lever_arm_m": antenna,
                "wheel_lever_arm_m": layout.sensor("wheels"),
                "gnss_heading_baseline_m": heading,
            } | {
                _MAGNETOMETER_KEYS[option]: layout.sensor("magnetometer")
                for option in self.magnetometer
            }
            out["derived"] = {
                key: getattr(derived, key)
                for key, sensor in placed.items()
                if sensor is not None and sensor.name in from_imu
            } | {
                key: getattr(derived, key)
                for key in ("wheel_track_m", "wheel_yaw_rate_update")
                if getattr(derived, key) != getattr(EskfConfig(**self.estimator), key)
            }
        return out


def _eskf_config(values: dict[str, Any], fail) -> EskfConfig:
    known = {f.name for f in dataclasses.fields(EskfConfig)}
    for key in values:
        if key not in known:
            raise fail(("estimator", key), "unknown estimator key (see EskfConfig)")
    try:
        config = EskfConfig(**values)
        config.validate()
    except (TypeError, ValueError) as err:
        bad = named_key(err, values)
        raise fail(("estimator",) if bad is None else ("estimator", bad), str(err)) from None
    return config


def _smoother_config(check: _Checker, section: Any) -> None:
    """Validate the ``smoother`` section (SmootherConfig keys), naming key path and line."""
    values = check.mapping(
        section, ("smoother",), tuple(f.name for f in dataclasses.fields(SmootherConfig))
    )
    try:
        SmootherConfig(**values).validate()
    except (TypeError, ValueError) as err:
        bad = named_key(err, values, "smoother.")
        raise check.fail(("smoother",) if bad is None else ("smoother", bad), str(err)) from None


def is_robot_config(path: str | os.PathLike[str]) -> bool:
    """Whether a YAML file is meant as a robot config: a top-level mapping with ``sensors``
    or with a key that only a robot config has (``robot``, ``frames``, ``time``,
    ``estimator``), so that a misspelt ``sensors`` is reported as such."""
    try:
        with open(path, encoding="utf-8") as handle:
            loaded = yaml.load(handle, Loader=ConfigLoader)  # noqa: S506 (a safe loader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    robot_only = ("sensors", "robot", "frames", "time", "estimator")
    return isinstance(loaded, dict) and any(key in loaded for key in robot_only)


def load_robot_config(path: str | os.PathLike[str]) -> RobotConfig:
    """Read and validate a robot YAML (module docstring).

    Raises:
        DataError: naming the file, line and key path of the first problem (a missing
            or unknown key, a wrong type, an unreadable URDF, an unknown frame, ...).
    """
    file = Path(path)
    document = read_yaml(file, "robot config")
    loaded = document.data
    check = _Checker(str(file), document.lines)
    top = check.mapping(loaded, (), ROBOT_KEYS)
    if "sensors" not in top:
        raise check.fail(("sensors",), "missing: a robot config maps sensors to topics")
    robot = check.mapping(top.get("robot"), ("robot",), ("name",))
    name = check.string(robot["name"], ("robot", "name")) if "name" in robot else file.stem
    frames_section = check.mapping(
        top.get("frames"), ("frames",), ("urdf", "body", "transforms", "joints")
    )
    tree = _frames(check, frames_section, file.parent)
    body = None
    if "body" in frames_section:
        body = check.string(frames_section["body"], ("frames", "body"))
    joints = check.mapping(frames_section.get("joints"), ("frames", "joints"), ("topic", "values"))
    joint_values: dict[str, float] = {}
    values = joints.get("values") or {}
    if not isinstance(values, dict):
        raise check.fail(("frames", "joints", "values"), "must map joint names to values")
    for joint, value in values.items():
        if tree is None or joint not in tree.joint_names:
            raise check.fail(
                ("frames", "joints", "values", joint),
                "not a movable joint of the URDF"
                + ("" if tree is None else f" (movable: {tree.joint_names})"),
            )
        joint_values[joint] = check.number(value, ("frames", "joints", "values", joint))
    time = check.mapping(top.get("time"), ("time",), ("origin_ns",))
    origin_ns = None
    if time.get("origin_ns", "first") != "first":
        value = time["origin_ns"]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise check.fail(
                ("time", "origin_ns"), f"must be 'first' or an integer >= 0 (ns), got {value!r}"
            )
        origin_ns = value
    estimator = check.mapping(
        top.get("estimator"), ("estimator",), tuple(f.name for f in dataclasses.fields(EskfConfig))
    )
    _eskf_config(dict(estimator), check.fail)
    _smoother_config(check, top.get("smoother"))
    sensors_section = top["sensors"]
    if not isinstance(sensors_section, dict) or not sensors_section:
        raise check.fail(("sensors",), "must be a non-empty mapping of sensor names to sensors")
    sensors: list[SensorTopic] = []
    disabled: list[str] = []
    gnss_origin = None
    wheel_fuse = None
    calibrate: list[str] = []
    calibrate_extrinsics: list[str] = []
    secondary_frame = None
    magnetometer: dict[str, Any] = {}
    for sensor_name, body_value in sensors_section.items():
        keys = ("sensors", str(sensor_name))
        if not isinstance(body_value, dict):
            raise check.fail(keys, "must be a mapping with at least type and topic")
        kind = body_value.get("type")
        if kind not in SENSOR_KINDS:
            raise check.fail(
                (*keys, "type"), f"must be one of {', '.join(SENSOR_KINDS)}, got {kind!r}"
            )
        spec = check.mapping(body_value, keys, _COMMON + _PER_KIND[kind])
        if "topic" not in spec:
            raise check.fail((*keys, "topic"), "missing")
        if not check.boolean(spec.get("enabled", True), (*keys, "enabled")):
            disabled.append(str(sensor_name))
            continue
        fields: dict[str, Any] = {
            "name": str(sensor_name),
            "kind": kind,
            "topic": check.string(spec["topic"], (*keys, "topic")),
        }
        if "frame" in spec:
            fields["frame"] = check.string(spec["frame"], (*keys, "frame"))
            if tree is not None and fields["frame"] not in tree.frames:
                raise check.fail(
                    (*keys, "frame"),
                    f"unknown frame {fields['frame']!r} (known: {', '.join(tree.frames)})",
                )
        if "stamp" in spec:
            if spec["stamp"] not in ("header", "bag"):
                raise check.fail((*keys, "stamp"), f"must be header or bag, got {spec['stamp']!r}")
            fields["stamp"] = spec["stamp"]
        if "time_offset_s" in spec:
            fields["time_offset_s"] = check.number(spec["time_offset_s"], (*keys, "time_offset_s"))
        if "use_message_covariance" in spec:
            fields["use_message_covariance"] = check.boolean(
                spec["use_message_covariance"], (*keys, "use_message_covariance")
            )
        if kind == "gnss":
            origin = spec.get("origin", "first")
            if origin != "first":
                gnss_origin = tuple(check.numbers(origin, (*keys, "origin"), 3))
                if abs(gnss_origin[0]) > 90:
                    raise check.fail((*keys, "origin"), "latitude must lie in [-90, 90] deg")
            if "min_fix_status" in spec:
                status = spec["min_fix_status"]
                if isinstance(status, bool) or status not in (-1, 0, 1, 2):
                    raise check.fail(
                        (*keys, "min_fix_status"), f"must be -1, 0, 1 or 2, got {status!r}"
                    )
                fields["min_fix_status"] = status
            if "fuse" in spec:
                fields["fuse"] = check.subset(spec["fuse"], (*keys, "fuse"), GNSS_COMPONENTS)
            if check.boolean(
                spec.get("calibrate_time_offset", False), (*keys, "calibrate_time_offset")
            ):
                calibrate.append("gnss")
            if check.boolean(
                spec.get("calibrate_lever_arm", False), (*keys, "calibrate_lever_arm")
            ):
                calibrate_extrinsics.append("gnss")
        elif kind == "wheels":
            if "left_joints" in spec or "right_joints" in spec or "wheel_radius_m" in spec:
                for side in ("left_joints", "right_joints", "wheel_radius_m"):
                    if side not in spec:
                        raise check.fail(
                            (*keys, side),
                            "missing (wheels from JointState need left_joints, right_joints "
                            "and wheel_radius_m)",
                        )
                fields["left_joints"] = check.strings(spec["left_joints"], (*keys, "left_joints"))
                fields["right_joints"] = check.strings(
                    spec["right_joints"], (*keys, "right_joints")
                )
                radius = spec["wheel_radius_m"]
                if isinstance(radius, list):
                    fields["wheel_radius_m"] = tuple(
                        check.numbers(radius, (*keys, "wheel_radius_m"), 2, positive=True)
                    )
                else:
                    r = check.number(radius, (*keys, "wheel_radius_m"), positive=True)
                    fields["wheel_radius_m"] = (r, r)
            if "fuse" in spec:
                fuse = check.subset(spec["fuse"], (*keys, "fuse"), WHEEL_COMPONENTS)
                if "speed" not in fuse:
                    raise check.fail((*keys, "fuse"), "the wheels always fuse speed")
                wheel_fuse = fuse
            if check.boolean(spec.get("calibrate", False), (*keys, "calibrate")):
                calibrate.append("wheels")
        elif kind == "pose":
            role = spec.get("role", "pose_source")
            if role not in POSE_ROLES:
                raise check.fail(
                    (*keys, "role"), f"must be one of {', '.join(POSE_ROLES)}, got {role!r}"
                )
            fields["role"] = role
            if "source_name" in spec:
                if role != "pose_source":
                    raise check.fail((*keys, "source_name"), "only a pose_source has a source name")
                fields["source_name"] = check.string(spec["source_name"], (*keys, "source_name"))
            if "sigma" in spec:
                fields["sigma"] = tuple(
                    check.numbers(spec["sigma"], (*keys, "sigma"), 6, positive=True)
                )
            if "fuse" in spec:
                if role != "poses":
                    raise check.fail(
                        (*keys, "fuse"),
                        "applies to role poses; a pose source is fused as velocity and rate "
                        "(estimator.pose_source_rate_update)",
                    )
                fields["fuse"] = check.subset(spec["fuse"], (*keys, "fuse"), POSE_COMPONENTS)
            if check.boolean(
                spec.get("calibrate_time_offset", False), (*keys, "calibrate_time_offset")
            ):
                if role != "pose_source":
                    raise check.fail(
                        (*keys, "calibrate_time_offset"),
                        "applies to role pose_source (the only pose role the filter fuses "
                        "with a time offset)",
                    )
                calibrate.append("pose:" + fields.get("source_name", str(sensor_name)))
            if check.boolean(
                spec.get("calibrate_extrinsics", False), (*keys, "calibrate_extrinsics")
            ):
                if role != "pose_source":
                    raise check.fail(
                        (*keys, "calibrate_extrinsics"),
                        "applies to role pose_source (the filter fuses its relative motion)",
                    )
                calibrate_extrinsics.append("pose:" + fields.get("source_name", str(sensor_name)))
        elif kind == "imu":
            if check.boolean(spec.get("calibrate_rotation", False), (*keys, "calibrate_rotation")):
                calibrate_extrinsics.append("imu")
        elif kind == "magnetometer":
            magnetometer = _magnetometer_options(check, spec, keys)
            if check.boolean(
                spec.get("calibrate_declination", False), (*keys, "calibrate_declination")
            ):
                calibrate_extrinsics.append("magnetometer")
        elif kind == "gnss_heading":
            if "baseline" in spec:
                secondary_frame = _secondary_frame(
                    check, spec["baseline"], (*keys, "baseline"), tree
                )
            if check.boolean(spec.get("calibrate_offset", False), (*keys, "calibrate_offset")):
                calibrate_extrinsics.append("gnss_heading")
            if check.boolean(
                spec.get("calibrate_time_offset", False), (*keys, "calibrate_time_offset")
            ):
                calibrate.append("gnss_heading")
        try:
            sensors.append(SensorTopic(**fields))
        except ValueError as err:
            raise check.fail(keys, str(err)) from None
    if "topic" in joints:
        sensors.append(
            SensorTopic(
                "joints", "joints", check.string(joints["topic"], ("frames", "joints", "topic"))
            )
        )
    try:
        layout = BagLayout(
            sensors=tuple(sensors),
            frames=tree,
            body_frame=body,
            joint_values=joint_values,
            time_origin_ns=origin_ns,
            gnss_origin=gnss_origin,
            wheel_track_m=estimator.get("wheel_track_m", EskfConfig.wheel_track_m),
        )
    except ValueError as err:
        raise check.fail(("sensors",), str(err)) from None
    imu = layout.sensor("imu")
    if tree is not None:
        if body is not None and body not in tree.frames:
            raise check.fail(
                ("frames", "body"), f"unknown frame {body!r} (known: {', '.join(tree.frames)})"
            )
        if imu.frame is None:
            raise check.fail(
                ("sensors", imu.name, "frame"),
                "missing: with frames, the imu sensor names its frame",
            )
        reference = body or imu.frame
        placed = [(s.frame, ("sensors", s.name, "frame")) for s in layout.sensors if s.frame]
        heading = layout.sensor("gnss_heading")
        if secondary_frame is not None and heading is not None:
            placed.append(
                (secondary_frame, ("sensors", heading.name, "baseline", "secondary_frame"))
            )
            moving = [
                j for j in tree.joints_between(reference, secondary_frame) if j not in joint_values
            ]
            if moving:
                raise check.fail(
                    placed[-1][1],
                    f"frame {secondary_frame!r} moves with joint(s) {moving}: give their values "
                    "(frames.joints.values); an antenna baseline is static",
                )
        for frame, where in placed:
            if tree.root(frame) != tree.root(reference):
                raise check.fail(
                    where,
                    f"frame {frame!r} is not connected to the body frame {reference!r}: "
                    f"its tree starts at {tree.root(frame)!r}, the body's at "
                    f"{tree.root(reference)!r} (check the parents in frames.transforms)",
                )
    config = RobotConfig(
        path=file,
        name=name,
        layout=layout,
        estimator=dict(estimator),
        wheel_fuse=wheel_fuse,
        disabled=tuple(disabled),
        calibrate=tuple(calibrate),
        calibrate_extrinsics=tuple(calibrate_extrinsics),
        heading_secondary_frame=secondary_frame,
        magnetometer=magnetometer,
        _lines=check.lines,
    )
    if tree is not None:
        config.eskf_config(None)
        heading = layout.sensor("gnss_heading")
        if secondary_frame is not None and heading.frame is not None:
            # the baseline now when the primary antenna's frame is named and static
            reference = body or imu.frame
            frames = (heading.frame, imu.frame)
            joints = [j for f in frames for j in tree.joints_between(reference, f)]
            if all(j in joint_values for j in joints):
                config._heading_baseline(config._from_imu(heading.frame))
    return config


def _magnetometer_options(check: _Checker, spec: dict[str, Any], keys: tuple) -> dict[str, Any]:
    """A magnetometer sensor's options given (keys of ``_MAGNETOMETER_KEYS``), checked:
    ``declination_deg`` in [-180, 180], ``hard_iron_uT`` 3 numbers, ``soft_iron`` 9 numbers
    (row-major) with a positive determinant, ``sigma_uT`` above 0."""
    out: dict[str, Any] = {}
    if "declination_deg" in spec:
        declination = check.number(spec["declination_deg"], (*keys, "declination_deg"))
        if abs(declination) > 180.0:
            raise check.fail(
                (*keys, "declination_deg"), f"must lie in [-180, 180] deg, got {declination}"
            )
        out["declination_deg"] = declination
    if "hard_iron_uT" in spec:
        out["hard_iron_uT"] = check.numbers(spec["hard_iron_uT"], (*keys, "hard_iron_uT"), 3)
    if "soft_iron" in spec:
        soft = check.numbers(spec["soft_iron"], (*keys, "soft_iron"), 9)
        det = float(torch.linalg.det(torch.tensor(soft, dtype=torch.float64).reshape(3, 3)))
        if not det > 0:
            raise check.fail(
                (*keys, "soft_iron"),
                f"the 3x3 matrix (row-major) has determinant {det:.6g}; a soft-iron correction "
                "has a positive one (a mirror or a singular matrix would corrupt the heading)",
            )
        out["soft_iron"] = soft
    if "sigma_uT" in spec:
        out["sigma_uT"] = check.number(spec["sigma_uT"], (*keys, "sigma_uT"), positive=True)
    return out


def _secondary_frame(check: _Checker, value: Any, keys: tuple, tree: FrameTree | None) -> str:
    """The ``secondary_frame`` of a gnss_heading sensor's ``baseline`` mapping (a frame
    of ``tree``, which must exist)."""
    baseline = check.mapping(value, keys, ("secondary_frame",))
    if "secondary_frame" not in baseline:
        raise check.fail((*keys, "secondary_frame"), "missing: the secondary antenna's frame")
    frame = check.string(baseline["secondary_frame"], (*keys, "secondary_frame"))
    if tree is None:
        raise check.fail(
            (*keys, "secondary_frame"),
            "needs the robot's frames (frames.urdf or frames.transforms); without them set "
            "estimator.gnss_heading_baseline_m",
        )
    if frame not in tree.frames:
        raise check.fail(
            (*keys, "secondary_frame"),
            f"unknown frame {frame!r} (known: {', '.join(tree.frames)})",
        )
    return frame


def _frames(check: _Checker, section: dict[str, Any], folder: Path) -> FrameTree | None:
    """The FrameTree of a ``frames`` section (URDF and / or static transforms), or None."""
    transforms: list[StaticTransform] = []
    items = section.get("transforms") or []
    if not isinstance(items, list):
        raise check.fail(("frames", "transforms"), "must be a list of transforms")
    for i, item in enumerate(items):
        keys = ("frames", "transforms", i)
        spec = check.mapping(item, keys, ("parent", "child", "xyz", "rpy", "quaternion_xyzw"))
        for key in ("parent", "child", "xyz"):
            if key not in spec:
                raise check.fail((*keys, key), "missing")
        if ("rpy" in spec) == ("quaternion_xyzw" in spec):
            raise check.fail(keys, "give exactly one of rpy and quaternion_xyzw")
        parent = check.string(spec["parent"], (*keys, "parent"))
        child = check.string(spec["child"], (*keys, "child"))
        xyz = check.numbers(spec["xyz"], (*keys, "xyz"), 3)
        if "rpy" in spec:
            rpy = check.numbers(spec["rpy"], (*keys, "rpy"), 3)
            for k, angle in enumerate(rpy):
                if abs(angle) > 2 * math.pi:
                    raise check.fail(
                        (*keys, "rpy", k),
                        f"{angle} rad is more than a full turn: rpy is in radians (as in a "
                        f"URDF), not degrees ({angle} deg = {math.radians(angle)!r} rad)",
                    )
            transforms.append(StaticTransform.from_xyz_rpy(parent, child, xyz, rpy))
        else:
            quat = check.numbers(spec["quaternion_xyzw"], (*keys, "quaternion_xyzw"), 4)
            norm = math.hypot(*quat)
            if abs(norm - 1.0) > 1e-3:
                raise check.fail(
                    (*keys, "quaternion_xyzw"),
                    f"must be a unit quaternion [x, y, z, w] (ROS order), its norm is {norm:.6g}",
                )
            transforms.append(StaticTransform.from_xyz_quaternion(parent, child, xyz, quat))
    try:
        if "urdf" in section:
            urdf = Path(check.string(section["urdf"], ("frames", "urdf")))
            if not urdf.is_absolute():
                urdf = folder / urdf
            return FrameTree.from_urdf(urdf, transforms)
        if transforms:
            return FrameTree.from_transforms(transforms)
    except ValueError as err:
        key = ("frames", "urdf") if "urdf" in section else ("frames", "transforms")
        raise check.fail(key, str(err)) from None
    return None
