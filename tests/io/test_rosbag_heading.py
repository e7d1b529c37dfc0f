"""Dual-antenna GNSS heading from ROS bags: ``sensor_msgs/Imu`` orientations as the
ublox_gps driver's ``navheading`` publishes them (ENU yaw = pi/2 - heading, the heading
accuracy squared in ``orientation_covariance[8]``) -> ``Sequence.gnss_heading``.

Expected headings are computed here independently of the reader: the azimuth, clockwise
from north, of the quaternion's x axis (scipy's rotation), and the ublox_gps formula run
forwards.
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
from scipy.spatial.transform import Rotation

from msf_torch.io import DataError
from msf_torch.io.rosbag import BagLayout, SensorTopic, read_rosbag, write_rosbag
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import GnssHeading

ORIGIN_NS = 1_700_000_000_000_000_000
T0 = 1_650_000_000_000_000_000
IMU = SensorTopic("imu", "imu", "/imu")
HEADING = SensorTopic("heading", "gnss_heading", "/ublox/navheading")


def _wrapped(a: torch.Tensor) -> torch.Tensor:
    """Angles (rad) wrapped to [-pi, pi)."""
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


def _imu_msg(store, stamp: int, frame: str, xyzw, orientation_cov, accel=(0.0, 0.0, 0.0)):
    vector = store.types["geometry_msgs/msg/Vector3"]
    x, y, z, w = (float(c) for c in xyzw)
    return store.types["sensor_msgs/msg/Imu"](
        header=header_msg(store, stamp, frame),
        orientation=store.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        orientation_covariance=np.asarray(orientation_cov, dtype=np.float64),
        angular_velocity=vector(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.r_[-1.0, np.zeros(8)],
        linear_acceleration=vector(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
        linear_acceleration_covariance=np.r_[-1.0, np.zeros(8)],
    )


def _write_bag(path: Path, version: int, topics: dict[str, list]) -> Path:
    """``topics``: topic -> [(stamp_ns, sensor_msgs/Imu message), ...]."""
    store = store_for(version)
    writer = Writer1(path) if version == 1 else Writer2(path, version=9)
    serialize = store.serialize_ros1 if version == 1 else store.serialize_cdr
    with writer:
        for topic, messages in topics.items():
            conn = writer.add_connection(topic, "sensor_msgs/msg/Imu", typestore=store)
            for stamp, msg in messages:
                writer.write(conn, stamp, serialize(msg, "sensor_msgs/msg/Imu"))
    return path


def _still_imu(store, count: int) -> list:
    stamps = [T0 + k * 10_000_000 for k in range(count)]
    unknown = np.r_[-1.0, np.zeros(8)]
    return [(t, _imu_msg(store, t, "imu", [0, 0, 0, 1], unknown, (0, 0, 9.8))) for t in stamps]


def _ublox_navheading(rel_pos_heading_1e5deg: int, acc_heading_1e5deg: int, valid: bool):
    """The orientation (xyzw) and covariance ublox_gps publishes for one NAV-RELPOSNED."""
    yaw = math.pi / 2 - rel_pos_heading_1e5deg * 1e-5 / 180.0 * math.pi
    cov = np.zeros(9)
    cov[[0, 4, 8]] = 1000.0
    if valid:
        cov[8] = (acc_heading_1e5deg * 1e-5 / 180.0 * math.pi) ** 2
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)], cov


@pytest.mark.parametrize("version", [1, 2])
def test_headings_from_imu_orientations(tmp_path: Path, version: int) -> None:
    """Heading = the azimuth of the quaternion's x axis clockwise from north (a tilted one
    too), sigma = sqrt(orientation_covariance[8]) when > 0, else NaN; a message with
    orientation_covariance[0] == -1 is skipped and counted."""
    store = store_for(version)
    step = 125_000_000
    tilted = Rotation.from_euler("ZYX", [-2.9, 0.3, -0.2])  # yaw, pitch, roll
    cov_small = np.r_[1e3, 0, 0, 0, 1e3, 0, 0, 0, 4e-4]
    rows = [
        _ublox_navheading(35_000_000, 250_000, True),  # 350 deg, 2.5 deg accuracy
        _ublox_navheading(1_234_567, 0, False),  # not valid: variance 1000
        ([0.0, 0.0, 0.0, 1.0], np.r_[-1.0, np.zeros(8)]),  # no orientation: skipped
        (2.0 * tilted.as_quat(), cov_small),  # not unit, tilted
        ([0.0, 0.0, 0.0, 1.0], np.zeros(9)),  # yaw 0 (east), variance unknown
        ([0.0, 0.0, float("nan"), 1.0], cov_small),  # non-finite: dropped
    ]
    messages = [
        (T0 + k * step, _imu_msg(store, T0 + k * step, "gps_link", q, c))
        for k, (q, c) in enumerate(rows)
    ]
    bag = _write_bag(
        tmp_path / ("h.bag" if version == 1 else "h"),
        version,
        {"/imu": _still_imu(store, 100), "/ublox/navheading": messages},
    )
    layout = BagLayout(sensors=(IMU, dataclasses.replace(HEADING, time_offset_s=0.02)))
    seq = read_rosbag(bag, layout)
    heading = seq.gnss_heading
    assert isinstance(heading, GnssHeading) and heading.heading.dtype == torch.float64
    np.testing.assert_allclose(heading.t[0].numpy(), [0.02, 0.145, 0.395, 0.52], rtol=0, atol=1e-12)
    x_axis = tilted.apply([1.0, 0.0, 0.0])
    want = torch.tensor(
        [
            math.radians(350.0),
            math.radians(12.34567),
            math.atan2(x_axis[0], x_axis[1]) % (2 * math.pi),
            math.pi / 2,
        ],
        dtype=torch.float64,
    )
    assert float(_wrapped(heading.heading[0] - want).abs().max()) < 1e-9
    assert bool(((heading.heading >= 0) & (heading.heading < 2 * math.pi)).all())
    np.testing.assert_allclose(
        heading.sigma[0].numpy(),
        [math.radians(2.5), math.sqrt(1000.0), 0.02, float("nan")],
        rtol=1e-12,
    )
    assert seq.meta["skipped_messages"] == {"heading": 1}
    assert seq.meta["dropped_nonfinite"]["gnss_heading"] == 1
    assert seq.meta["topics"]["heading"] == {
        "topic": "/ublox/navheading",
        "msgtype": "sensor_msgs/msg/Imu",
        "messages": 6,
        "frame": "gps_link",
    }
    off = BagLayout(sensors=(IMU, dataclasses.replace(HEADING, use_message_covariance=False)))
    assert torch.isnan(read_rosbag(bag, off).gnss_heading.sigma).all()


@pytest.mark.parametrize("version", [1, 2])
def test_simulated_headings_round_trip(tmp_path: Path, version: int) -> None:
    """A simulated drive's headings written by write_rosbag as sensor_msgs/Imu and read
    back: the same times, headings (to 1e-9 rad, wrap-aware) and sigmas; a NaN sigma
    (the config default) stays NaN."""
    seq = simulate_run(SimConfig(duration_s=20.0, gnss_heading=True), seed=31).sequence
    streams = {
        name: dataclasses.replace(s, t=torch.round(s.t * 1e9) / 1e9)
        for name, s in seq.streams().items()
    }
    sigma = streams["gnss_heading"].sigma.clone()
    sigma[0, 3] = float("nan")
    streams["gnss_heading"] = dataclasses.replace(streams["gnss_heading"], sigma=sigma)
    seq = dataclasses.replace(seq, **streams)
    assert seq.gnss_heading.length > 10
    layout = BagLayout(sensors=(IMU, HEADING), time_origin_ns=ORIGIN_NS)
    bag = write_rosbag(
        seq,
        tmp_path / ("run.bag" if version == 1 else "run"),
        layout,
        version=version,
        time_origin_ns=ORIGIN_NS,
    )
    back = read_rosbag(bag, layout).gnss_heading
    assert torch.equal(back.t, seq.gnss_heading.t)
    assert float(_wrapped(back.heading - seq.gnss_heading.heading).abs().max()) < 1e-9
    torch.testing.assert_close(back.sigma, sigma, rtol=1e-15, atol=0, equal_nan=True)
    assert bool(torch.isnan(back.sigma[0, 3]))


def test_heading_sensor_rules(tmp_path: Path) -> None:
    """One gnss_heading sensor at most; the topic must carry sensor_msgs/Imu; a zero
    quaternion is an error naming the topic."""
    with pytest.raises(ValueError, match="one gnss_heading sensor"):
        BagLayout(sensors=(IMU, HEADING, dataclasses.replace(HEADING, name="second")))
    store = store_for(2)
    bag = _write_bag(
        tmp_path / "zero",
        2,
        {
            "/imu": _still_imu(store, 20),
            "/ublox/navheading": [(T0, _imu_msg(store, T0, "gps", [0, 0, 0, 0], np.zeros(9)))],
        },
    )
    with pytest.raises(DataError, match="zero norm") as caught:
        read_rosbag(bag, BagLayout(sensors=(IMU, HEADING)))
    assert "/ublox/navheading" in str(caught.value)
    heading_on_fixes = SensorTopic("heading", "gnss_heading", "/fix")
    fix = store.types["sensor_msgs/msg/NavSatFix"](
        header=header_msg(store, T0, "gps"),
        status=store.types["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
        latitude=47.0,
        longitude=8.0,
        altitude=400.0,
        position_covariance=np.zeros(9),
        position_covariance_type=0,
    )
    other = tmp_path / "fix"
    with Writer2(other, version=9) as writer:
        conn = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        for stamp, msg in _still_imu(store, 5):
            writer.write(conn, stamp, store.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
        conn = writer.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=store)
        writer.write(conn, T0, store.serialize_cdr(fix, "sensor_msgs/msg/NavSatFix"))
    with pytest.raises(DataError, match="a gnss_heading sensor reads sensor_msgs/msg/Imu") as err:
        read_rosbag(other, BagLayout(sensors=(IMU, heading_on_fixes)))
    assert err.value.field == "sensors.heading.topic"
