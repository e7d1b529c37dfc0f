"""Readers and writers: native .npz/.csv sequences, TUM trajectories, EuRoC ASL folders,
KITTI raw drives' OXTS GPS/IMU (:func:`read_kitti_raw`), the KITTI drive shipped with gtsam
and gtsam's EuRoC EqVIO replay file (:func:`load_eqvio`, IMU + feature tracks; not a
:class:`~msf_torch.types.Sequence`).

:func:`load_sequence` is the one entry point for sequences; it dispatches on ``fmt`` or
detects the format. Every reader returns a B = 1 :class:`~msf_torch.types.Sequence` in
float64 and follows the same rules for bad input (see :mod:`msf_torch.io.native`):
malformed data raises :class:`DataError` naming file, line and field; non-finite samples are
dropped and counted in ``meta``; backwards time raises unless ``sort=True``; repeated
timestamps keep the first sample.

ROS bags (rosbag1 and rosbag2, :mod:`msf_torch.io.rosbag`) are read by :func:`read_rosbag`
with a :class:`BagLayout` (topics -> sensors, frames); trajectories are also written as
KITTI pose files (:func:`write_kitti_poses`) and ``nav_msgs/Odometry`` rosbag2 folders
(:func:`write_odometry_rosbag2`).

3-D pose graphs (g2o ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``, TORO ``VERTEX3`` / ``EDGE3``) are
read by :func:`read_pose_graph` into a :class:`PoseGraph` and written by :func:`write_g2o`
(:mod:`msf_torch.io.g2o`; information matrices in ``[dp, dtheta]`` order, costs equal to
GTSAM's). 2-D (planar) pose graphs (g2o ``VERTEX_SE2`` / ``EDGE_SE2``, TORO ``VERTEX2`` /
``EDGE2``) are read by :func:`read_pose_graph_2d` into a :class:`PoseGraph2D` and written by
:func:`write_g2o_2d` (:mod:`msf_torch.io.g2o_2d`); :func:`is_pose_graph_2d` tells the two apart.
The 2-D reader also reads landmark SLAM files (``ODOMETRY``, ``VERTEX_XY``, ``BR``,
``LANDMARK``: GTSAM's ``victoria_park.txt``) into the graph's landmarks and sightings.
Odometry + anchor-range runs (UWB, radio beacons) are read from CSV files by
:func:`read_range_run` and from the gtsam wheel's Plaza runs by :func:`load_plaza` into a
:class:`RangeRun`. NMEA 0183 GNSS logs (GGA fixes with GST sigmas, RMC/ZDA dates, RMC / VTG
speed and course, HDT / THS dual-antenna headings) are read by :func:`read_nmea` into an
:class:`NmeaLog`, u-blox UBX logs (NAV-PVT, NAV-RELPOSNED moving-baseline headings) by
:func:`read_ubx` into a :class:`UbxLog`; their fixes go to local ENU metres and a native
``gnss.csv`` (:func:`write_gnss_csv`; ``msf nmea``, ``msf ubx``) with the velocities in
``gnss_velocity.csv`` and the headings in ``gnss_heading.csv``, whose folder keeps the ENU
origin in ``meta.json``; with it,
trajectories go on the map as GeoJSON, KML and GPX (:func:`write_geojson`, :func:`write_kml`,
:func:`write_gpx`; ``msf run --export geojson,kml,gpx``).
"""

from __future__ import annotations

__all__ = [
    "FORMATS",
    "GTSAM_LANDMARK2_FILES",
    "GTSAM_POSE2_FILES",
    "GTSAM_POSE3_FILES",
    "PoseGraph",
    "PoseGraph2D",
    "RangeRun",
    "BagLayout",
    "SensorTopic",
    "DataError",
    "EqvioRun",
    "MissingExtraError",
    "NmeaLog",
    "UbxLog",
    "atomic_write",
    "atomic_save_npz",
    "detect_format",
    "gtsam_data_path",
    "gtsam_pose_graph_path",
    "is_pose_graph_2d",
    "is_rosbag",
    "load_eqvio",
    "load_kitti_gtsam",
    "load_plaza",
    "load_sequence",
    "read_euroc",
    "read_kitti_poses",
    "read_kitti_raw",
    "read_rosbag",
    "read_native",
    "read_nmea",
    "read_ubx",
    "read_range_run",
    "read_pose_graph",
    "read_pose_graph_2d",
    "read_tum",
    "write_g2o",
    "write_g2o_2d",
    "write_geojson",
    "write_gpx",
    "write_kml",
    "write_kitti_poses",
    "write_odometry_rosbag2",
    "write_rosbag",
    "write_anchors",
    "write_gnss_csv",
    "write_native",
    "write_tum",
]

import os
from pathlib import Path

from msf_torch.io.atomic import atomic_save_npz, atomic_write
from msf_torch.io.eqvio import EqvioRun, load_eqvio
from msf_torch.io.errors import DataError, MissingExtraError
from msf_torch.io.euroc import find_euroc_root, read_euroc
from msf_torch.io.g2o import (
    GTSAM_POSE3_FILES,
    PoseGraph,
    gtsam_pose_graph_path,
    read_pose_graph,
    write_g2o,
)
from msf_torch.io.g2o_2d import (
    GTSAM_LANDMARK2_FILES,
    GTSAM_POSE2_FILES,
    PoseGraph2D,
    is_pose_graph_2d,
    read_pose_graph_2d,
    write_g2o_2d,
)
from msf_torch.io.geo_export import write_geojson, write_gpx, write_kml
from msf_torch.io.kitti_gtsam import KITTI_GTSAM_NAME, gtsam_data_path, load_kitti_gtsam
from msf_torch.io.kitti_poses import read_kitti_poses, write_kitti_poses
from msf_torch.io.kitti_raw import find_kitti_raw_root, read_kitti_raw
from msf_torch.io.native import _native_path_problem, read_native, write_native
from msf_torch.io.nmea import NmeaLog, read_nmea, write_gnss_csv
from msf_torch.io.plaza import load_plaza
from msf_torch.io.ranges import RangeRun, read_range_run, write_anchors
from msf_torch.io.rosbag import (
    BagLayout,
    SensorTopic,
    is_rosbag,
    read_rosbag,
    write_odometry_rosbag2,
    write_rosbag,
)
from msf_torch.io.tum import read_tum, write_tum
from msf_torch.io.ubx import UbxLog, read_ubx
from msf_torch.types import Sequence

FORMATS = ("native", "npz", "csv", "euroc", "kitti-raw", "tum", "kitti-gtsam")
"""Accepted values of ``load_sequence(fmt=...)``."""

_TRAJECTORY_SUFFIXES = (".tum", ".txt")
_ACCEPTED = (
    "'kitti-gtsam' (the KITTI drive shipped with gtsam), a native .npz file, a native "
    "folder with imu.csv, a EuRoC ASL folder with mav0/ or imu0/, or a KITTI raw drive "
    "folder with oxts/"
)


def _tum_is_not_a_sequence(path: Path) -> DataError:
    return DataError(
        path,
        "a TUM file holds a trajectory, not a sensor sequence: read it with "
        "msf_torch.io.read_tum, or score it with `msf eval`",
    )


def detect_format(source: str | os.PathLike[str]) -> str:
    """Guess the format of ``source``; one of ``"kitti-gtsam"``, ``"npz"``, ``"csv"``,
    ``"euroc"``, ``"kitti-raw"``, ``"tum"``.

    Rules, in order: the name ``"kitti-gtsam"`` (when no such file exists); a file ending in
    ``.npz``; a folder holding ``imu.csv``; a folder holding ``mav0/`` or ``imu0/``; a KITTI
    raw drive (a folder holding ``oxts/timestamps.txt`` and ``oxts/data/``, or that ``oxts``
    folder); a ``.tum``/``.txt`` file (a trajectory).

    Raises:
        DataError: the path does not exist or matches no format (the message lists them);
            a folder of native tables without ``imu.csv`` (``"imu.csv missing in FOLDER
            (found: ...)"``) and a native table given instead of its folder (``"pass the
            folder FOLDER, not one of its files"``) are named as such.
    """
    path = Path(source)
    if str(source) == KITTI_GTSAM_NAME and not path.exists():
        return "kitti-gtsam"
    if not path.exists():
        raise DataError(path, f"no such file or folder (accepted: {_ACCEPTED})")
    if path.is_file() and path.suffix.lower() == ".npz":
        return "npz"
    if path.is_dir():
        if (path / "imu.csv").is_file():
            return "csv"
        if find_euroc_root(path) is not None:
            return "euroc"
        if find_kitti_raw_root(path) is not None:
            return "kitti-raw"
    if path.is_file() and path.suffix.lower() in _TRAJECTORY_SUFFIXES:
        return "tum"
    near_native = _native_path_problem(path)
    if near_native is not None:
        raise near_native
    if is_rosbag(path) is not None:
        raise DataError(
            path,
            "a ROS bag needs its topic mapping: msf run BAG --topics ROBOT.yaml "
            "(or msf_torch.io.read_rosbag with a BagLayout)",
        )
    raise DataError(path, f"unrecognised sequence format; accepted: {_ACCEPTED}")


def load_sequence(
    source: str | os.PathLike[str], fmt: str | None = None, sort: bool = False
) -> Sequence:
    """Load a recorded sequence (B = 1) from a file, folder or named dataset.

    Args:
        source: a path, or ``"kitti-gtsam"`` for the KITTI IMU + GPS drive shipped with gtsam.
        fmt: one of :data:`FORMATS` (``"native"`` = ``.npz`` or CSV folder, ``"npz"``,
            ``"csv"``, ``"euroc"``, ``"kitti-raw"``, ``"tum"``, ``"kitti-gtsam"``), or None
            to detect it
            (:func:`detect_format`).
        sort: stably sort streams whose timestamps go backwards instead of raising.

    Returns:
        a :class:`~msf_torch.types.Sequence` with B = 1, float64, all-True masks.

    Raises:
        ValueError: an unknown ``fmt`` (the message lists the accepted ones).
        DataError: bad or unrecognised input; for a TUM file, an explanation that it is a
            trajectory (use :func:`read_tum` or ``msf eval``).
        MissingExtraError: ``"kitti-gtsam"`` without gtsam installed.
    """
    if fmt is not None and fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; accepted: {', '.join(FORMATS)}")
    if fmt is None:
        fmt = detect_format(source)
    path = Path(source)
    if fmt == "kitti-gtsam":
        return load_kitti_gtsam(sort=sort)
    if fmt == "tum":
        raise _tum_is_not_a_sequence(path)
    if fmt == "euroc":
        return read_euroc(path, sort=sort)
    if fmt == "kitti-raw":
        return read_kitti_raw(path, sort=sort)
    if fmt == "npz" and (path.is_dir() or path.suffix.lower() != ".npz"):
        raise DataError(path, "format 'npz' needs a file ending in .npz")
    if fmt == "csv" and path.exists() and not path.is_dir():
        raise _native_path_problem(path) or DataError(
            path, "format 'csv' needs a folder holding imu.csv"
        )
    return read_native(path, sort=sort)
