"""Magnetometers from ROS bags: ``sensor_msgs/MagneticField`` (tesla, the sensor's axes,
3x3 covariance in T^2) -> ``Sequence.magnetometer`` (microtesla, body axes, per-axis sigma).

Expected values are written out here from the message fields: 1 T = 1e6 uT, sigma =
1e6 sqrt(mean of the covariance diagonal), and a mount rotation applied by hand.
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

from msf_torch.io import DataError
from msf_torch.io.rosbag import BagLayout, SensorTopic, read_rosbag, write_rosbag
from msf_torch.robot.frames import FrameTree, StaticTransform
from msf_torch.types import ImuSamples, Magnetometer, Sequence

T0 = 1_650_000_000_000_000_000
IMU = SensorTopic("imu", "imu", "/imu")
MAG = SensorTopic("mag", "magnetometer", "/imu/mag")


def _imu_msg(store, stamp: int, frame: str):
    vector = store.types["geometry_msgs/msg/Vector3"]
    return store.types["sensor_msgs/msg/Imu"](
        header=header_msg(store, stamp, frame),
        orientation=store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=vector(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector(x=0.0, y=0.0, z=9.8),
        linear_acceleration_covariance=np.zeros(9),
    )


def _mag_msg(store, stamp: int, frame: str, tesla, covariance):
    x, y, z = (float(c) for c in tesla)
    return store.types["sensor_msgs/msg/MagneticField"](
        header=header_msg(store, stamp, frame),
        magnetic_field=store.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
        magnetic_field_covariance=np.asarray(covariance, dtype=np.float64).reshape(9),
    )


def _write_bag(path: Path, version: int, magnetometer: list, frame: str = "mag_link") -> Path:
    """A bag with 50 still IMU samples at 100 Hz and ``magnetometer``: [(stamp_ns,
    tesla (3,), covariance (9,)), ...] on ``/imu/mag``."""
    store = store_for(version)
    writer = Writer1(path) if version == 1 else Writer2(path, version=9)
    serialize = store.serialize_ros1 if version == 1 else store.serialize_cdr
    with writer:
        conn = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        for k in range(50):
            stamp = T0 + k * 10_000_000
            writer.write(
                conn, stamp, serialize(_imu_msg(store, stamp, "imu"), "sensor_msgs/msg/Imu")
            )
        msgtype = "sensor_msgs/msg/MagneticField"
        conn = writer.add_connection("/imu/mag", msgtype, typestore=store)
        for stamp, tesla, cov in magnetometer:
            writer.write(conn, stamp, serialize(_mag_msg(store, stamp, frame, tesla, cov), msgtype))
    return path


@pytest.mark.parametrize("version", [1, 2])
def test_fields_and_sigmas_from_magnetic_field(tmp_path: Path, version: int) -> None:
    """Tesla -> uT; sigma = 1e6 sqrt(mean of the diagonal) when all three entries are
    positive and finite, NaN when the covariance is all zero ("unknown" in ROS) or not
    usable (a zero or -1 entry, NaN); a non-finite field is dropped and counted;
    use_message_covariance: false gives NaN throughout."""
    step = 50_000_000
    fields = [
        [2.1e-5, -3.4e-6, -4.25e-5],
        [1.9e-5, 4.0e-6, -4.3e-5],
        [0.0, 2.2e-5, -4.1e-5],
        [-1.5e-5, -1.5e-5, -4.0e-5],
        [2.0e-5, float("nan"), -4.2e-5],
        [1.0e-5, 1.0e-5, -4.4e-5],
    ]
    diagonals = [
        [1e-14, 8e-14, 1.8e-13],  # uT^2 0.01, 0.08, 0.18: sigma sqrt(0.09) = 0.3 uT
        [0.0, 0.0, 0.0],  # unknown
        [1e-14, 0.0, 1e-14],  # one axis missing: not usable
        [-1.0, 0.0, 0.0],  # "not provided" in the Imu style: not usable
        [1e-14, 1e-14, 1e-14],  # the NaN field: dropped
        [4e-14, 4e-14, 4e-14],  # 0.2 uT
    ]
    rows = [
        (T0 + k * step, f, np.diag(d).reshape(9))
        for k, (f, d) in enumerate(zip(fields, diagonals, strict=True))
    ]
    rows[0] = (rows[0][0], rows[0][1], rows[0][2] + 1e-15 * (1 - np.eye(3)).reshape(9))
    bag = _write_bag(tmp_path / ("m.bag" if version == 1 else "m"), version, rows)
    layout = BagLayout(sensors=(IMU, dataclasses.replace(MAG, time_offset_s=0.01)))
    seq = read_rosbag(bag, layout)
    mag = seq.magnetometer
    assert isinstance(mag, Magnetometer) and mag.field.dtype == torch.float64
    np.testing.assert_allclose(mag.t[0].numpy(), [0.01, 0.06, 0.11, 0.16, 0.26], atol=1e-12)
    want = 1e6 * np.array([fields[k] for k in (0, 1, 2, 3, 5)])
    np.testing.assert_allclose(mag.field[0].numpy(), want, rtol=1e-14, atol=0)
    nan = float("nan")
    np.testing.assert_allclose(mag.sigma[0].numpy(), [0.3, nan, nan, nan, 0.2], rtol=1e-12)
    assert seq.meta["dropped_nonfinite"]["magnetometer"] == 1
    assert seq.meta["topics"]["mag"] == {
        "topic": "/imu/mag",
        "msgtype": "sensor_msgs/msg/MagneticField",
        "messages": 6,
        "frame": "mag_link",
    }
    assert seq.meta["extrinsics"]["mag"] == np.eye(4).tolist()
    off = BagLayout(sensors=(IMU, dataclasses.replace(MAG, use_message_covariance=False)))
    assert torch.isnan(read_rosbag(bag, off).magnetometer.sigma).all()


# the magnetometer upside down and turned a quarter turn: URDF rpy [pi, 0, pi/2] gives
# R = Rz(pi/2) Rx(pi) = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]: sensor [a, b, c] -> body [b, a, -c]
MOUNT = StaticTransform.from_xyz_rpy(
    "base_link", "mag_link", [0.3, -0.1, 0.2], [math.pi, 0.0, 0.5 * math.pi]
)
IMU_AT = StaticTransform.from_xyz_rpy("base_link", "imu_link", [0.1, 0.0, 0.05], [0.0, 0.0, 0.0])


def test_mounted_magnetometer_reads_in_the_body_axes(tmp_path: Path) -> None:
    """A sensor frame rotated against the body: the field comes out as R_body_sensor times
    the reading (closed form above); the lever arm plays no part."""
    rows = [(T0 + 20_000_000, [1e-5, 2e-5, -4e-5], np.zeros(9))]
    bag = _write_bag(tmp_path / "mounted", 2, rows)
    layout = BagLayout(
        sensors=(dataclasses.replace(IMU, frame="imu_link"), MAG),
        frames=FrameTree.from_transforms([IMU_AT, MOUNT]),
        body_frame="base_link",
    )
    seq = read_rosbag(bag, layout)
    np.testing.assert_allclose(seq.magnetometer.field[0].numpy(), [[20.0, 10.0, 40.0]], rtol=1e-14)
    rotation = np.array(seq.meta["extrinsics"]["mag"])[:3, :3]
    np.testing.assert_allclose(rotation, [[0, 1, 0], [1, 0, 0], [0, 0, -1]], atol=1e-15)


@pytest.mark.parametrize("version", [1, 2])
def test_round_trip_through_a_mounted_sensor(tmp_path: Path, version: int) -> None:
    """write_rosbag turns body-frame fields back into the sensor's axes in tesla with a
    diag(sigma^2) covariance (all zero for a NaN sigma); read back: the same times, fields
    (1e-12 relative) and sigmas, NaN kept."""
    gen = torch.Generator().manual_seed(5)
    n_imu, n_mag = 200, 40
    t_imu = torch.arange(n_imu, dtype=torch.float64)[None] * 0.01
    imu = ImuSamples(
        t=t_imu,
        gyro=0.01 * torch.randn(1, n_imu, 3, generator=gen, dtype=torch.float64),
        accel=torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64).expand(1, n_imu, 3).clone(),
        mask=torch.ones(1, n_imu, dtype=torch.bool),
    )
    sigma = 0.1 + torch.rand(1, n_mag, generator=gen, dtype=torch.float64)
    sigma[0, 7] = float("nan")
    mag = Magnetometer(
        t=torch.round((0.003 + 0.05 * torch.arange(n_mag, dtype=torch.float64)) * 1e9)[None] / 1e9,
        field=50.0 * torch.randn(1, n_mag, 3, generator=gen, dtype=torch.float64),
        sigma=sigma,
        mask=torch.ones(1, n_mag, dtype=torch.bool),
    )
    seq = Sequence(names=["run"], imu=imu, magnetometer=mag)
    layout = BagLayout(
        sensors=(
            dataclasses.replace(IMU, frame="imu_link"),
            dataclasses.replace(MAG, frame="mag_link"),
        ),
        frames=FrameTree.from_transforms([IMU_AT, MOUNT]),
        body_frame="base_link",
        time_origin_ns=T0,
    )
    bag = write_rosbag(
        seq,
        tmp_path / ("r.bag" if version == 1 else "r"),
        layout,
        version=version,
        time_origin_ns=T0,
    )
    back = read_rosbag(bag, layout).magnetometer
    assert torch.equal(back.t, mag.t)
    torch.testing.assert_close(back.field, mag.field, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(back.sigma, sigma, rtol=1e-12, atol=0, equal_nan=True)
    assert bool(torch.isnan(back.sigma[0, 7]))


def test_magnetometer_sensor_rules(tmp_path: Path) -> None:
    """One magnetometer sensor at most; its topic must carry MagneticField; a sensor frame
    that moves with a joint is refused (a static extrinsic is needed)."""
    with pytest.raises(ValueError, match="one magnetometer sensor"):
        BagLayout(sensors=(IMU, MAG, dataclasses.replace(MAG, name="second")))
    bag = _write_bag(tmp_path / "m", 2, [(T0, [1e-5, 0.0, -4e-5], np.zeros(9))])
    on_imu = SensorTopic("mag", "magnetometer", "/imu")
    with pytest.raises(
        DataError, match="a magnetometer sensor reads sensor_msgs/msg/MagneticField"
    ) as err:
        read_rosbag(bag, BagLayout(sensors=(IMU, on_imu)))
    assert err.value.field == "sensors.mag.topic"
    urdf = tmp_path / "pan.urdf"
    urdf.write_text(
        """<robot name="pan">
  <link name="imu"/><link name="mag_link"/>
  <joint name="pan" type="continuous"><parent link="imu"/><child link="mag_link"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 0 1"/></joint>
</robot>
"""
    )
    moving = BagLayout(
        sensors=(dataclasses.replace(IMU, frame="imu"), MAG), frames=FrameTree.from_urdf(urdf)
    )
    with pytest.raises(DataError, match="moves with joint 'pan': its frame must be static") as err:
        read_rosbag(bag, moving)
    assert err.value.field == "sensors.mag.frame"
