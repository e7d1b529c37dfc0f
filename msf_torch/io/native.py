"""The native msf_torch sequence format: one ``.npz`` file or a folder of CSV tables.

Both forms hold the same schema. Only the IMU is required; every other table is optional.
Times are seconds on the sequence's own clock, positions are metres in the local world frame
(ENU, z up), quaternions are Hamilton ``[w, x, y, z]`` body -> world (see
``msf_torch.geometry.conventions``) and are normalised on read.

CSV folder
----------
One table per file, comma separated, a header row naming the columns (any order, no unknown
or repeated columns), ``#`` comment lines and blank lines ignored. Numbers use Python's
``float`` grammar (``nan`` and ``inf`` are accepted and then handled by the rules below).

==================== =================================================================
file                 columns
==================== =================================================================
``imu.csv``          ``t, gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z``
                     (s, rad/s, m/s^2; accel is specific force, +g on z at rest)
``wheel.csv``        ``t, left_speed, right_speed`` (s, rim speeds in m/s)
``gnss.csv``         ``t, x, y, z`` [``, sigma_x, sigma_y, sigma_z``] (s, m, m)
``gnss_velocity.csv`` ``t, vx, vy, vz`` [``, sigma_vx, sigma_vy, sigma_vz``] (s, m/s,
                     m/s): the antenna's velocity in the world frame (east, north, up)
                     from the receiver's Doppler or its speed and course over ground;
                     ``vz`` may be ``nan`` (horizontal only, e.g. NMEA RMC / VTG): the up
                     component is then not fused
``gnss_heading.csv`` ``t, heading`` [``, sigma_heading``] (s, rad, rad): a dual-antenna
                     receiver's heading, the azimuth of the baseline from the primary to
                     the secondary antenna clockwise from true north (any value: the
                     filter wraps it; ``msf ubx`` and ``msf nmea`` write [0, 2 pi));
                     ``sigma_heading`` may be ``nan`` (the estimator's configured
                     ``gnss_heading_sigma_rad`` applies)
``magnetometer.csv`` ``t, mx, my, mz`` [``, sigma``] (s, uT, uT): three-axis magnetometer
                     readings in the body (IMU) frame as the sensor gives them, before
                     hard- and soft-iron correction (microtesla: 1 gauss = 100 uT, a ROS
                     ``sensor_msgs/MagneticField`` is in tesla = 1e6 uT); ``sigma`` is the
                     per-axis standard deviation and may be ``nan`` (the estimator's
                     configured ``magnetometer_sigma_uT`` applies)
``poses.csv``        ``t, x, y, z, qw, qx, qy, qz`` then the uncertainty, one of:
                     nothing (covariance unknown: NaN);
                     6 standard deviations ``sigma_x, sigma_y, sigma_z, sigma_roll,
                     sigma_pitch, sigma_yaw`` (m, rad; covariance = diag(sigma^2));
                     21 covariance entries ``c00, c01, ..., c05, c11, ..., c55`` (the upper
                     triangle, row-major, ``cIJ`` with I <= J; m^2, m rad, rad^2).
                     The covariance is over ``[dp (world, m), dtheta (body, rad)]``.
``poses_<name>.csv``  a named pose source, e.g. ``poses_vo.csv`` (visual odometry),
                     ``poses_lidar.csv`` (LiDAR odometry): the columns of ``poses.csv``;
                     read into ``Sequence.pose_sources[<name>]``. ``<name>`` matches
                     :data:`SOURCE_NAME_PATTERN` (letters, digits, ``_``, ``-``).
``ground_truth.csv`` ``t, x, y, z, qw, qx, qy, qz``
``labels.csv``       ``name, t_start, t_end`` (s); e.g. ``slip`` or ``weather:rain``; a
                     name may appear on many rows (one interval each); a name with no
                     interval (e.g. a weather condition that never occurs) has no row, so
                     it is absent after a CSV round trip (the npz keeps it as (0, 2))
``meta.json``        optional JSON object describing the sensors, e.g.
                     ``{"wheel_track_m": 0.5, "imu_noise": {...}}``; ``"gnss_origin":
                     [lat_deg, lon_deg, alt_m]`` (WGS-84, ellipsoidal height) is the
                     geodetic point the ENU frame of ``gnss.csv`` starts from (``msf
                     nmea`` writes it), which maps the trajectory onto the Earth
                     (``msf run --export geojson,kml``); ``"imu_rpy_deg": [roll,
                     pitch, yaw]`` is the IMU's mounting in the body frame (deg,
                     ``R_body_imu = Rz Ry Rx``): its samples are turned into body axes on
                     read (``meta["imu_rpy_deg_applied"]``) and the key is not kept, so a
                     written copy holds body-axes samples
==================== =================================================================

NPZ file
--------
Arrays keyed ``<stream>/<field>``, float64, N samples per stream:

``imu/t`` (N,), ``imu/gyro`` (N, 3), ``imu/accel`` (N, 3);
``wheel/t``, ``wheel/left_speed``, ``wheel/right_speed`` (N,);
``gnss/t`` (N,), ``gnss/position`` (N, 3), optional ``gnss/sigma`` (N, 3);
``gnss_velocity/t`` (N,), ``gnss_velocity/velocity`` (N, 3) (up may be NaN), optional
``gnss_velocity/sigma`` (N, 3);
``gnss_heading/t``, ``gnss_heading/heading`` (N,) (rad), optional ``gnss_heading/sigma`` (N,);
``magnetometer/t`` (N,), ``magnetometer/field`` (N, 3) (uT), optional ``magnetometer/sigma``
(N,) (uT);
``poses/t`` (N,), ``poses/position`` (N, 3), ``poses/quaternion`` (N, 4) ``[w,x,y,z]``,
optional ``poses/covariance`` (N, 6, 6);
``poses/<name>/t``, ``poses/<name>/position``, ``poses/<name>/quaternion``, optional
``poses/<name>/covariance``: the named pose source ``<name>`` (same shapes as ``poses``);
``ground_truth/t``, ``ground_truth/position``, ``ground_truth/quaternion``;
``labels/<name>`` (K, 2) ``[t_start, t_end]`` rows; ``meta_json`` a 0-d string holding the
same JSON object as ``meta.json``. Unknown keys are an error.

Rules on read (every format in ``msf_torch.io`` follows them)
------------------------------------------------------------
* Malformed input raises :class:`~msf_torch.io.errors.DataError` naming the file, the
  1-based line (CSV) or the sample (npz) and the column: a cell that is not a number, a
  row with the wrong number of cells, a missing or unknown column, a zero quaternion, a
  negative sigma.
* A sample with NaN or inf in its time or values is dropped, counted in
  ``meta["dropped_nonfinite"][stream]``; the first few line numbers go to
  ``meta["dropped_lines"][stream]`` (CSV) or sample indices to
  ``meta["dropped_indices"][stream]`` (npz). Uncertainties (``sigma_*``, ``c*``) may be NaN,
  meaning "not given, use the estimator's default".
* Timestamps that go backwards raise DataError naming the line, unless ``sort=True``: then
  each stream is stably sorted and ``meta["sorted"][stream]`` counts the backwards steps.
* A sample whose timestamp exactly repeats the previous one is dropped (the first is kept),
  counted in ``meta["dropped_duplicates"][stream]``.
* The rules apply to each named pose source as a stream keyed ``"poses/<name>"`` in the
  ``meta`` counts. A source stream with no samples left is kept (N = 0).
* ``meta["source"]`` is the path read, ``meta["format"]`` is ``"native-csv"`` or
  ``"native-npz"``, ``meta["sensor"]`` is the ``meta.json`` object, and its ``"imu_noise"``
  entry (if any) is also put at ``meta["imu_noise"]``, where every reader puts IMU noise;
  likewise ``"gnss_origin"`` at ``meta["gnss_origin"]`` (three finite numbers, latitude in
  [-90, 90], else a DataError naming the field), where the ROS bag reader puts it, and
  ``"time_origin_ns"`` (an integer: the UNIX time of ``t = 0`` in ns, which ``msf nmea``
  stores) at ``meta["time_origin_ns"]``, as a ROS bag's.
"""

from __future__ import annotations

__all__ = [
    "IMU_COLUMNS",
    "WHEEL_COLUMNS",
    "GNSS_COLUMNS",
    "GNSS_SIGMA_COLUMNS",
    "GNSS_VELOCITY_COLUMNS",
    "GNSS_VELOCITY_SIGMA_COLUMNS",
    "GNSS_HEADING_COLUMNS",
    "GNSS_HEADING_SIGMA_COLUMNS",
    "MAGNETOMETER_COLUMNS",
    "MAGNETOMETER_SIGMA_COLUMNS",
    "POSE_COLUMNS",
    "POSE_SIGMA_COLUMNS",
    "POSE_COVARIANCE_COLUMNS",
    "LABEL_COLUMNS",
    "TABLE_FILES",
    "SOURCE_NAME_PATTERN",
    "GEOMETRY_KEYS",
    "pose_source_file",
    "read_native",
    "stored_gnss_origin",
    "store_gnss_origin",
    "stored_time_origin",
    "store_time_origin",
    "write_stream_csv",
    "write_native",
]

import contextlib
import csv
import dataclasses
import json
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.so3 import rpy_matrix
from msf_torch.io import _tables
from msf_torch.io._tables import CleanReport, Table
from msf_torch.io.atomic import atomic_save_npz, atomic_write
from msf_torch.io.errors import DataError
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

# sensor geometry a ``meta.json`` may give (m, body axes): the GNSS antenna and wheel-axle
# lever arms and the dual-antenna baseline; the front end's config takes them from there
# unless the run's YAML sets them (frontend.config.config_for_sequence)
GEOMETRY_KEYS = ("gnss_lever_arm_m", "wheel_lever_arm_m", "gnss_heading_baseline_m")
IMU_COLUMNS = ["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
WHEEL_COLUMNS = ["t", "left_speed", "right_speed"]
GNSS_COLUMNS = ["t", "x", "y", "z"]
GNSS_SIGMA_COLUMNS = ["sigma_x", "sigma_y", "sigma_z"]
GNSS_VELOCITY_COLUMNS = ["t", "vx", "vy", "vz"]
GNSS_VELOCITY_SIGMA_COLUMNS = ["sigma_vx", "sigma_vy", "sigma_vz"]
GNSS_HEADING_COLUMNS = ["t", "heading"]
GNSS_HEADING_SIGMA_COLUMNS = ["sigma_heading"]
MAGNETOMETER_COLUMNS = ["t", "mx", "my", "mz"]
MAGNETOMETER_SIGMA_COLUMNS = ["sigma"]
POSE_COLUMNS = ["t", "x", "y", "z", "qw", "qx", "qy", "qz"]
POSE_SIGMA_COLUMNS = ["sigma_x", "sigma_y", "sigma_z", "sigma_roll", "sigma_pitch", "sigma_yaw"]
POSE_COVARIANCE_COLUMNS = [f"c{i}{j}" for i in range(6) for j in range(i, 6)]
LABEL_COLUMNS = ["name", "t_start", "t_end"]

TABLE_FILES = {
    "imu": "imu.csv",
    "wheel": "wheel.csv",
    "gnss": "gnss.csv",
    "gnss_velocity": "gnss_velocity.csv",
    "gnss_heading": "gnss_heading.csv",
    "magnetometer": "magnetometer.csv",
    "poses": "poses.csv",
    "ground_truth": "ground_truth.csv",
}
"""Stream name -> CSV file name in a native folder."""

SOURCE_NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_-]*"
"""Names allowed for a named pose source (``Sequence.pose_sources`` keys)."""

_SOURCE_NAME = re.compile(SOURCE_NAME_PATTERN)
_SOURCE_FILE = re.compile(rf"poses_({SOURCE_NAME_PATTERN})\.csv")
_SOURCE_PREFIX = "poses/"


def pose_source_file(name: str) -> str:
    """CSV file name of the named pose source ``name`` in a native folder (``poses_<name>.csv``).

    Raises:
        ValueError: ``name`` does not match :data:`SOURCE_NAME_PATTERN`.
    """
    if not isinstance(name, str) or not _SOURCE_NAME.fullmatch(name):
        raise ValueError(
            f"pose source name {name!r} cannot be stored (allowed: {SOURCE_NAME_PATTERN})"
        )
    return f"poses_{name}.csv"


def _base(stream: str) -> str:
    """Kind of a stream key: ``"poses/<name>"`` (a named pose source) -> ``"poses"``."""
    return stream.partition("/")[0]


_LABELS_FILE = "labels.csv"
_META_FILE = "meta.json"
_KNOWN_NAMES = ", ".join(
    [*TABLE_FILES.values(), "poses_<name>.csv", _LABELS_FILE, _META_FILE]
)  # for messages


def _is_native_file(name: str) -> bool:
    """Whether ``name`` is a file name a native folder holds (tables, labels, meta)."""
    known = (*TABLE_FILES.values(), _LABELS_FILE, _META_FILE)
    return name in known or _SOURCE_FILE.fullmatch(name) is not None


def _shown_files(names: list[str], limit: int = 8) -> str:
    """``a.csv, b.csv, ...`` of at most ``limit`` names, with the total when cut."""
    more = f", ... ({len(names)} files)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _native_path_problem(path: str | os.PathLike[str]) -> DataError | None:
    """The DataError for a path that is almost a native CSV sequence, else None.

    Two mistakes are recognised: a folder that holds native tables but no ``imu.csv`` (the
    one required table), and a native file (``imu.csv``, ``gnss.csv``, ...) given instead of
    the folder that holds ``imu.csv``.

    Args:
        path: a file or folder.

    Returns:
        ``"imu.csv missing in FOLDER (found: ...)"`` or ``"pass the folder FOLDER, not one of
        its files"`` as a DataError on ``path``, or None when neither applies.
    """
    p = Path(path)
    if p.is_dir():
        found = sorted(f.name for f in p.iterdir() if f.is_file() and _is_native_file(f.name))
        if found and TABLE_FILES["imu"] not in found:
            return DataError(p, f"imu.csv missing in this folder (found: {_shown_files(found)})")
    elif p.is_file() and _is_native_file(p.name) and (p.parent / TABLE_FILES["imu"]).is_file():
        return DataError(p, f"pass the folder {p.parent}, not one of its files")
    return None


_KINDS: dict[str, type] = {
    "imu": ImuSamples,
    "wheel": WheelSamples,
    "gnss": GnssFixes,
    "gnss_velocity": GnssVelocity,
    "gnss_heading": GnssHeading,
    "magnetometer": Magnetometer,
    "poses": PoseMeasurements,
    "ground_truth": Trajectory,
}

# stream -> field -> trailing shape; "optional" fields may be absent (filled with NaN).
_NPZ_FIELDS: dict[str, dict[str, tuple[int, ...]]] = {
    "imu": {"t": (), "gyro": (3,), "accel": (3,)},
    "wheel": {"t": (), "left_speed": (), "right_speed": ()},
    "gnss": {"t": (), "position": (3,), "sigma": (3,)},
    "gnss_velocity": {"t": (), "velocity": (3,), "sigma": (3,)},
    "gnss_heading": {"t": (), "heading": (), "sigma": ()},
    "magnetometer": {"t": (), "field": (3,), "sigma": ()},
    "poses": {"t": (), "position": (3,), "quaternion": (4,), "covariance": (6, 6)},
    "ground_truth": {"t": (), "position": (3,), "quaternion": (4,)},
}
_OPTIONAL = {
    ("gnss", "sigma"),
    ("gnss_velocity", "sigma"),
    ("gnss_heading", "sigma"),
    ("magnetometer", "sigma"),
    ("poses", "covariance"),
}
_NAN_OK = {
    "gnss": ("sigma",),
    "gnss_velocity": ("sigma", "velocity_up"),
    "gnss_heading": ("sigma",),
    "magnetometer": ("sigma",),
    "poses": ("covariance",),
}
_QUAT_STREAMS = ("poses", "ground_truth")


# --------------------------------------------------------------------------- reading


def read_native(path: str | os.PathLike[str], sort: bool = False) -> Sequence:
    """Read a native sequence: a ``.npz`` file or a folder of CSV tables (module docstring).

    Args:
        path: the ``.npz`` file or the folder holding ``imu.csv`` and friends.
        sort: stably sort streams whose timestamps go backwards instead of raising.

    Returns:
        a :class:`~msf_torch.types.Sequence` with B = 1: float64 tensors (1, N, ...), all-True
        masks, labels (1, K, 2), ``names == [stem of path]`` and ``meta`` as described in the
        module docstring.

    Raises:
        DataError: naming the file, line and field of bad input.
    """
    p = Path(path)
    if p.is_dir():
        return _read_folder(p, sort)
    if p.suffix.lower() == ".npz":
        if not p.exists():
            raise DataError(p, "no such file")
        return _read_npz(p, sort)
    if not p.exists():
        raise DataError(p, "no such file or folder")
    raise _native_path_problem(p) or DataError(
        p, "not a native sequence: expected a .npz file or a folder with imu.csv"
    )


def _read_folder(folder: Path, sort: bool) -> Sequence:
    raw: dict[str, dict[str, np.ndarray]] = {}
    where: dict[str, tuple[str, np.ndarray | None, str]] = {}
    for stream, fname in TABLE_FILES.items():
        file = folder / fname
        if not file.exists():
            if stream == "imu":
                found = sorted(f.name for f in folder.iterdir() if f.is_file())
                raise DataError(
                    folder,
                    "imu.csv missing in this folder (the one required table; found: "
                    f"{_shown_files(found) or 'no files'})",
                )
            continue
        table = _tables.read_table(file)
        raw[stream] = _arrays_from_table(stream, table)
        where[stream] = (str(file), table.lines, "")
    for file in sorted(folder.glob("poses_*.csv")):
        match = _SOURCE_FILE.fullmatch(file.name)
        if match is None:
            continue
        stream = _SOURCE_PREFIX + match.group(1)
        table = _tables.read_table(file)
        raw[stream] = _arrays_from_table("poses", table)
        where[stream] = (str(file), table.lines, "")
    unknown = sorted(
        f.name for f in folder.glob("*.csv") if f.is_file() and not _is_native_file(f.name)
    )
    if unknown:
        warnings.warn(
            f"{folder}: ignored CSV files with names a native folder does not use: "
            f"{_shown_files(unknown)} (recognised: {_KNOWN_NAMES})",
            stacklevel=3,
        )
    labels = _read_labels_csv(folder / _LABELS_FILE)
    sensor = _read_meta_json(folder / _META_FILE)
    return _assemble(folder, "native-csv", raw, where, labels, sensor, sort)


def _check_sigmas(table: Table, data: np.ndarray, columns: list[str], first: int) -> None:
    """DataError at the first negative sigma in data[:, first:first+len(columns)]."""
    block = data[:, first : first + len(columns)]
    bad = np.argwhere(block < 0)
    if bad.size:
        r, c = (int(x) for x in bad[0])
        raise DataError(
            table.path,
            f"a standard deviation must not be negative, got {float(block[r, c])!r}",
            line=int(table.lines[r]),
            field=columns[c],
        )


def _vector_and_sigmas(
    table: Table, columns: list[str], sigma_columns: list[str], name: str
) -> dict[str, np.ndarray]:
    """A ``t`` + 3-vector table with optional per-axis sigmas (GNSS fixes, velocities):
    ``t`` (N,), ``name`` (N, 3), ``sigma`` (N, 3) (NaN when the table has none)."""
    extra = _tables.check_columns(table, columns, [[sigma_columns]])
    d = table.floats(columns + extra)
    if extra:
        _check_sigmas(table, d, sigma_columns, 4)
        sigma = d[:, 4:7]
    else:
        sigma = np.full((d.shape[0], 3), np.nan)
    return {"t": d[:, 0], name: d[:, 1:4], "sigma": sigma}


def _arrays_from_table(stream: str, table: Table) -> dict[str, np.ndarray]:
    """Convert one CSV table of the native schema to field -> (N, ...) arrays."""
    if stream == "imu":
        _tables.check_columns(table, IMU_COLUMNS)
        d = table.floats(IMU_COLUMNS)
        return {"t": d[:, 0], "gyro": d[:, 1:4], "accel": d[:, 4:7]}
    if stream == "wheel":
        _tables.check_columns(table, WHEEL_COLUMNS)
        d = table.floats(WHEEL_COLUMNS)
        return {"t": d[:, 0], "left_speed": d[:, 1], "right_speed": d[:, 2]}
    if stream == "gnss":
        return _vector_and_sigmas(table, GNSS_COLUMNS, GNSS_SIGMA_COLUMNS, "position")
    if stream == "gnss_velocity":
        columns, sigmas = GNSS_VELOCITY_COLUMNS, GNSS_VELOCITY_SIGMA_COLUMNS
        return _vector_and_sigmas(table, columns, sigmas, "velocity")
    if stream == "gnss_heading":
        extra = _tables.check_columns(table, GNSS_HEADING_COLUMNS, [[GNSS_HEADING_SIGMA_COLUMNS]])
        d = table.floats(GNSS_HEADING_COLUMNS + extra)
        if extra:
            _check_sigmas(table, d, GNSS_HEADING_SIGMA_COLUMNS, 2)
        sigma = d[:, 2] if extra else np.full(d.shape[0], np.nan)
        return {"t": d[:, 0], "heading": d[:, 1], "sigma": sigma}
    if stream == "magnetometer":
        extra = _tables.check_columns(table, MAGNETOMETER_COLUMNS, [[MAGNETOMETER_SIGMA_COLUMNS]])
        d = table.floats(MAGNETOMETER_COLUMNS + extra)
        if extra:
            _check_sigmas(table, d, MAGNETOMETER_SIGMA_COLUMNS, 4)
        sigma = d[:, 4] if extra else np.full(d.shape[0], np.nan)
        return {"t": d[:, 0], "field": d[:, 1:4], "sigma": sigma}
    if stream == "poses":
        extra = _tables.check_columns(
            table, POSE_COLUMNS, [[POSE_SIGMA_COLUMNS, POSE_COVARIANCE_COLUMNS]]
        )
        d = table.floats(POSE_COLUMNS + extra)
        n = d.shape[0]
        if extra == POSE_SIGMA_COLUMNS:
            _check_sigmas(table, d, POSE_SIGMA_COLUMNS, 8)
            cov = np.zeros((n, 6, 6))
            idx = np.arange(6)
            cov[:, idx, idx] = d[:, 8:14] ** 2
        elif extra:
            diag = [POSE_COVARIANCE_COLUMNS.index(f"c{i}{i}") for i in range(6)]
            _check_sigmas(table, d[:, [8 + k for k in diag]], [f"c{i}{i}" for i in range(6)], 0)
            rows, cols = np.triu_indices(6)
            cov = np.zeros((n, 6, 6))
            cov[:, rows, cols] = d[:, 8:29]
            cov[:, cols, rows] = d[:, 8:29]
        else:
            cov = np.full((n, 6, 6), np.nan)
        return {"t": d[:, 0], "position": d[:, 1:4], "quaternion": d[:, 4:8], "covariance": cov}
    _tables.check_columns(table, POSE_COLUMNS)
    d = table.floats(POSE_COLUMNS)
    return {"t": d[:, 0], "position": d[:, 1:4], "quaternion": d[:, 4:8]}


def _read_labels_csv(file: Path) -> dict[str, list[tuple[float, float]]]:
    if not file.exists():
        return {}
    table = _tables.read_table(file)
    _tables.check_columns(table, LABEL_COLUMNS)
    names = table.strings("name")
    spans = table.floats(["t_start", "t_end"])
    out: dict[str, list[tuple[float, float]]] = {}
    for r, name in enumerate(names):
        line = int(table.lines[r])
        if not name:
            raise DataError(file, "empty label name", line=line, field="name")
        _check_interval(str(file), spans[r], line=line)
        out.setdefault(name, []).append((float(spans[r, 0]), float(spans[r, 1])))
    return out


def _check_interval(path: str, span: np.ndarray, *, line: int | None = None, key: str = "") -> None:
    prefix = key if line is None else ""
    if not np.isfinite(span).all():
        raise DataError(
            path,
            f"{prefix}a label interval must be finite, got {span.tolist()}",
            line=line,
            field=None if line is None else "t_start",
        )
    if span[1] < span[0]:
        raise DataError(
            path,
            f"{prefix}t_end {float(span[1])!r} is before t_start {float(span[0])!r}",
            line=line,
            field=None if line is None else "t_end",
        )


def _parse_meta_json(path: str, text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise DataError(path, f"invalid JSON: {err.msg}", line=err.lineno) from None
    except RecursionError:
        raise DataError(path, "invalid JSON: nested too deeply") from None
    except ValueError as err:  # e.g. an integer longer than Python's digit limit
        raise DataError(path, f"invalid JSON: {str(err)[:120]}") from None
    if not isinstance(value, dict):
        raise DataError(path, f"must hold a JSON object, got {type(value).__name__}")
    return value


def _three_numbers(value: Any) -> list[float] | None:
    """A JSON value as three finite floats, or None when it is not a list of three finite
    numbers (booleans, strings and integers beyond the float range are not)."""
    numbers: list[float] = []
    if isinstance(value, list) and len(value) == 3:
        for x in value:
            if isinstance(x, bool) or not isinstance(x, int | float):
                return None
            try:
                numbers.append(float(x))
            except OverflowError:  # a JSON integer beyond the float range
                return None
    if len(numbers) != 3 or not all(math.isfinite(x) for x in numbers):
        return None
    return numbers


def _gnss_origin(where: str, value: Any) -> list[float]:
    """``meta.json``'s ``gnss_origin`` checked: [lat_deg, lon_deg, alt_m], finite, latitude
    in [-90, 90]; else a DataError naming the field."""
    origin = _three_numbers(value)
    if origin is None:
        shown = repr(value)[:80]
        raise DataError(
            where, f"expected [lat_deg, lon_deg, alt_m], got {shown}", field="gnss_origin"
        )
    if abs(origin[0]) > 90.0:
        raise DataError(where, f"latitude {origin[0]!r} outside [-90, 90]", field="gnss_origin")
    return origin


def _geometry_vector(where: str, key: str, value: Any) -> list[float]:
    """A ``meta.json`` lever arm or baseline (one of :data:`GEOMETRY_KEYS`) checked: three
    finite numbers in m, body axes; else a DataError naming the field."""
    vector = _three_numbers(value)
    if vector is None:
        shown = repr(value)[:80]
        raise DataError(where, f"expected [x, y, z] in m, got {shown}", field=key)
    return vector


def _imu_mounting(where: str, value: Any) -> np.ndarray:
    """``meta.json``'s ``imu_rpy_deg`` ``[roll, pitch, yaw]`` (deg, the IMU's axes in the body
    frame) as ``R_body_imu = Rz(yaw) Ry(pitch) Rx(roll)`` (3, 3); DataError naming the field
    unless three finite numbers."""
    angles = _three_numbers(value)
    if angles is None:
        shown = repr(value)[:80]
        raise DataError(
            where, f"expected [roll, pitch, yaw] in deg, got {shown}", field="imu_rpy_deg"
        )
    return rpy_matrix(torch.tensor(np.radians(angles), dtype=torch.float64)).numpy()


def _read_meta_json(file: Path) -> dict[str, Any]:
    if not file.exists():
        return {}
    return _parse_meta_json(str(file), _tables.read_text(file))


def stored_gnss_origin(folder: str | os.PathLike[str]) -> list[float] | None:
    """The ``gnss_origin`` ``[lat_deg, lon_deg, alt_m]`` a native folder's ``meta.json``
    holds, or None (no file, or no such entry). DataError for a malformed file or entry."""
    file = Path(folder) / _META_FILE
    sensor = _read_meta_json(file)
    if "gnss_origin" not in sensor:
        return None
    return _gnss_origin(str(file), sensor["gnss_origin"])


def store_gnss_origin(
    folder: str | os.PathLike[str], origin: tuple[float, ...] | list[float]
) -> Path:
    """Set ``gnss_origin`` in a native folder's ``meta.json`` (created if absent; its other
    entries kept), atomically.

    Args:
        folder: the native folder (created if needed).
        origin: ``[lat_deg, lon_deg, alt_m]`` (WGS-84, ellipsoidal height) of the ENU frame.

    Returns:
        the ``meta.json`` path.

    Raises:
        DataError: an existing ``meta.json`` is not a JSON object. ValueError: a bad origin.
    """
    return _store_meta_entry(
        folder, "gnss_origin", _gnss_origin("origin", [float(x) for x in origin])
    )


def _time_origin(where: str, value: Any) -> int:
    """``meta.json``'s ``time_origin_ns`` checked: an integer (ns)."""
    if isinstance(value, bool) or not isinstance(value, int):
        shown = _tables.shown(json.dumps(value))
        raise DataError(where, f"expected an integer (ns), got {shown}", field="time_origin_ns")
    return value


def stored_time_origin(folder: str | os.PathLike[str]) -> int | None:
    """The ``time_origin_ns`` a native folder's ``meta.json`` holds, or None (no file, or no
    such entry). DataError for a malformed file or entry."""
    file = Path(folder) / _META_FILE
    sensor = _read_meta_json(file)
    if "time_origin_ns" not in sensor:
        return None
    return _time_origin(str(file), sensor["time_origin_ns"])


def store_time_origin(folder: str | os.PathLike[str], origin_ns: int) -> Path:
    """Set ``time_origin_ns`` (the UNIX time of the folder's ``t = 0``, ns) in a native
    folder's ``meta.json`` (created if absent; its other entries kept), atomically.

    Returns:
        the ``meta.json`` path.

    Raises:
        DataError: an existing ``meta.json`` is not a JSON object, or ``origin_ns`` is not
            an integer.
    """
    return _store_meta_entry(folder, "time_origin_ns", _time_origin("origin_ns", origin_ns))


def _store_meta_entry(folder: str | os.PathLike[str], key: str, value: Any) -> Path:
    """Set ``key`` in ``folder/meta.json`` (created if absent, other entries kept),
    atomically; the file's path."""
    file = Path(folder) / _META_FILE
    sensor = _read_meta_json(file)
    sensor[key] = value
    with atomic_write(file) as handle:
        handle.write(json.dumps(sensor, indent=2, sort_keys=True, allow_nan=True) + "\n")
    return file


def _read_npz(path: Path, sort: bool) -> Sequence:
    spath = str(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except _tables.NPZ_ERRORS as err:
        raise DataError(path, f"not a readable .npz file ({type(err).__name__}: {err})") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise DataError(path, "not a .npz archive (a single .npy array?)")
    with archive as z:
        key = None
        try:
            contents = {}
            for key in z.files:
                contents[key] = z[key]
        except _tables.NPZ_ERRORS as err:
            raise DataError(
                path, f"corrupt .npz member ({type(err).__name__}: {err})", field=key
            ) from None
    raw: dict[str, dict[str, np.ndarray]] = {}
    where: dict[str, tuple[str, np.ndarray | None, str]] = {}
    labels: dict[str, list[tuple[float, float]]] = {}
    sensor: dict[str, Any] = {}
    npz_streams = dict(_NPZ_FIELDS)
    for key in contents:
        stream, _, fname = key.partition("/")
        if key == "meta_json" or (stream == "labels" and fname):
            continue
        name, _, source_field = fname.partition("/")
        if (
            stream == "poses"
            and _SOURCE_NAME.fullmatch(name)
            and source_field in _NPZ_FIELDS["poses"]
        ):
            npz_streams[_SOURCE_PREFIX + name] = _NPZ_FIELDS["poses"]
            continue
        if stream not in _NPZ_FIELDS or fname not in _NPZ_FIELDS[stream]:
            raise DataError(
                path,
                "unknown key (expected <stream>/<field> with stream in "
                f"{', '.join(_NPZ_FIELDS)}, poses/<name>/<field>, labels/<name> or meta_json)",
                field=key,
            )
    if not any(k.startswith("imu/") for k in contents):
        raise DataError(path, "missing key: the imu stream is required", field="imu/t")
    for stream, fields in npz_streams.items():
        if not any(f"{stream}/{f}" in contents for f in fields):
            continue
        arrays: dict[str, np.ndarray] = {}
        n: int | None = None
        for fname, trailing in fields.items():
            key = f"{stream}/{fname}"
            if key not in contents:
                if (_base(stream), fname) in _OPTIONAL:
                    continue
                needed = ", ".join(
                    f"{stream}/{f}" for f in fields if (_base(stream), f) not in _OPTIONAL
                )
                raise DataError(
                    path, f"missing key (the {stream} stream needs {needed})", field=key
                )
            value = _numeric(spath, key, contents[key])
            if n is None:
                n = value.shape[0] if value.ndim else -1
            expected = (n, *trailing)
            if value.shape != expected:
                raise DataError(
                    path,
                    f"shape {tuple(value.shape)}, expected {expected} "
                    f"(N = {n} samples from {stream}/t)",
                    field=key,
                )
            arrays[fname] = value
        count = arrays["t"].shape[0]
        for fname, trailing in fields.items():
            if fname not in arrays:
                arrays[fname] = np.full((count, *trailing), np.nan)
        negative = np.argwhere(arrays["sigma"] < 0) if "sigma" in arrays else ()
        if len(negative):  # as the CSV reader refuses a negative sigma cell
            index = tuple(int(i) for i in negative[0])
            raise DataError(
                path,
                f"sample {index[0]}: a standard deviation must not be negative, got "
                f"{float(arrays['sigma'][index])!r}",
                field=f"{stream}/sigma",
            )
        raw[stream] = arrays
        where[stream] = (spath, None, f"{stream}/")
    for key, value in contents.items():
        if key.startswith("labels/") and len(key) > len("labels/"):
            spans = _numeric(spath, key, value)
            if spans.ndim != 2 or spans.shape[1] != 2:
                raise DataError(path, f"shape {tuple(spans.shape)}, expected (K, 2)", field=key)
            for k, span in enumerate(spans):
                _check_interval(spath, span, key=f"{key} row {k}: ")
            labels[key[len("labels/") :]] = [(float(a), float(b)) for a, b in spans]
    if "meta_json" in contents:
        text = contents["meta_json"]
        if text.dtype.kind != "U" or text.ndim != 0:
            raise DataError(path, "must be a 0-d string array", field="meta_json")
        sensor = _parse_meta_json(f"{spath}[meta_json]", str(text[()]))
    return _assemble(path, "native-npz", raw, where, labels, sensor, sort)


def _numeric(path: str, key: str, value: np.ndarray) -> np.ndarray:
    if value.dtype.kind not in "fiub":
        raise DataError(path, f"not a numeric array (dtype {value.dtype})", field=key)
    return value.astype(np.float64)


def _assemble(
    path: Path,
    fmt: str,
    raw: dict[str, dict[str, np.ndarray]],
    where: dict[str, tuple[str, np.ndarray | None, str]],
    labels: dict[str, list[tuple[float, float]]],
    sensor: dict[str, Any],
    sort: bool,
) -> Sequence:
    """Apply the cleaning rules to raw streams and build the Sequence (B = 1)."""
    report = CleanReport()
    streams: dict[str, Any] = {}
    sources: dict[str, PoseMeasurements] = {}
    for stream, arrays in raw.items():
        file, lines, prefix = where[stream]
        kind = _base(stream)
        if kind in _QUAT_STREAMS:
            _tables.check_quaternions(
                file,
                arrays["quaternion"],
                lines=lines,
                field_prefix=prefix,
                name="qw" if lines is not None else "quaternion",
            )
        if kind == "gnss_velocity":  # the up component may be NaN (not measured)
            arrays = dict(arrays)
            velocity = arrays.pop("velocity")
            arrays["velocity"], arrays["velocity_up"] = velocity[:, :2], velocity[:, 2]
        cleaned = _tables.clean_stream(
            report,
            stream,
            file,
            arrays,
            lines=lines,
            sort=sort,
            nan_ok=_NAN_OK.get(kind, ()),
            field_prefix=prefix,
        )
        if kind == "gnss_velocity":
            up = cleaned.pop("velocity_up")
            cleaned["velocity"] = np.concatenate((cleaned["velocity"], up[:, None]), 1)
        if kind in _QUAT_STREAMS:
            cleaned["quaternion"] = _tables.normalise_quaternions(cleaned["quaternion"])
        value = _tables.stream_from_arrays(_KINDS[kind], cleaned)
        if stream.startswith(_SOURCE_PREFIX):
            sources[stream[len(_SOURCE_PREFIX) :]] = value
        else:
            streams[stream] = value
    if streams["imu"].length == 0:
        raise DataError(where["imu"][0], "no IMU samples (after dropping non-finite rows)")
    meta: dict[str, Any] = {"source": str(path), "format": fmt, **report.to_meta()}
    where_meta = str(path / _META_FILE if fmt == "native-csv" else f"{path}[meta_json]")
    if "imu_rpy_deg" in sensor:  # the IMU's mounting: its samples turned into body axes
        sensor = dict(sensor)
        angles = sensor.pop("imu_rpy_deg")
        rotation = _imu_mounting(where_meta, angles)
        imu = streams["imu"]
        turn = torch.as_tensor(rotation, dtype=imu.gyro.dtype)
        streams["imu"] = dataclasses.replace(
            imu, gyro=imu.gyro @ turn.mT, accel=imu.accel @ turn.mT
        )
        meta["imu_rpy_deg_applied"] = [float(x) for x in angles]
    if sensor:
        meta["sensor"] = sensor
        if "imu_noise" in sensor:
            meta["imu_noise"] = sensor["imu_noise"]
        if "gnss_origin" in sensor:
            meta["gnss_origin"] = _gnss_origin(where_meta, sensor["gnss_origin"])
        if "time_origin_ns" in sensor:
            meta["time_origin_ns"] = _time_origin(where_meta, sensor["time_origin_ns"])
        for key in GEOMETRY_KEYS:
            if key in sensor:
                sensor[key] = _geometry_vector(where_meta, key, sensor[key])
    label_tensors = {
        name: torch.tensor(spans, dtype=torch.float64).reshape(1, -1, 2)
        for name, spans in labels.items()
    }
    seq = Sequence(
        names=[_tables.path_name(path)],
        labels=label_tensors,
        meta=meta,
        pose_sources=dict(sorted(sources.items())),
        **streams,
    )
    seq.check()
    return seq


# --------------------------------------------------------------------------- writing


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to(device="cpu", dtype=torch.float64).numpy()


def _stream_arrays(seq: Sequence) -> dict[str, dict[str, np.ndarray]]:
    """Stream -> field -> (N, ...) float64 arrays of the real (masked-in) samples; named pose
    sources under ``"poses/<name>"``."""
    out: dict[str, dict[str, np.ndarray]] = {}
    named = {_SOURCE_PREFIX + name: value for name, value in seq.pose_sources.items()}
    for name in seq.pose_sources:
        pose_source_file(name)
    for stream, value in {**seq.streams(), **named}.items():
        compact = value.compact()
        out[stream] = {k: _np(v[0]) for k, v in compact.tensors().items() if k != "mask"}
    return out


def _label_arrays(seq: Sequence) -> dict[str, np.ndarray]:
    out = {}
    for name, spans in seq.labels.items():
        if not name or "\n" in name:
            raise ValueError(f"label name {name!r} cannot be stored")
        value = _np(spans[0]).reshape(-1, 2)
        out[name] = value[~np.isnan(value).all(axis=1)]
    return out


def _sensor_json(seq: Sequence) -> str | None:
    sensor = dict(seq.meta.get("sensor") or {})
    for key in ("imu_noise", "gnss_origin", "time_origin_ns"):
        if key in seq.meta and key not in sensor:
            sensor[key] = seq.meta[key]
    if not sensor:
        return None
    try:
        return json.dumps(sensor, indent=2, sort_keys=True, allow_nan=True)
    except TypeError as err:
        raise ValueError(f"seq.meta['sensor'] must be JSON-serialisable: {err}") from None


def write_native(seq: Sequence, path: str | os.PathLike[str]) -> Path:
    """Write a B = 1 sequence in the native format (module docstring), atomically.

    A path ending in ``.npz`` gives one npz file; any other path is a folder (created if
    needed) that receives one CSV per stream (``poses_<name>.csv`` per named pose source)
    plus ``labels.csv`` and ``meta.json``. Each file is written through a temporary file and
    renamed into place, so a failure never leaves a truncated file. In a folder, native
    tables of streams the sequence lacks are removed (so reading back gives exactly ``seq``);
    other files are left alone.

    Only real samples (mask True) are written. Numbers are written with ``repr`` (the
    shortest string that reads back to the same float64), so a round trip is exact up to
    quaternion re-normalisation. ``meta["sensor"]`` (plus ``meta["imu_noise"]``,
    ``meta["gnss_origin"]`` and ``meta["time_origin_ns"]``) is stored as the JSON sensor
    description; the other meta entries are derived on read and not stored.

    Args:
        seq: the sequence, B = 1, any device / floating dtype.
        path: ``something.npz`` or a folder.

    Returns:
        the path written, as a ``Path``.

    Raises:
        ValueError: B != 1, a non-JSON sensor meta, a label or pose source name that cannot
            be stored.
    """
    if seq.batch_size != 1:
        raise ValueError(f"write_native writes one sequence, got B = {seq.batch_size}")
    seq.check()
    target = Path(path)
    streams = _stream_arrays(seq)
    labels = _label_arrays(seq)
    sensor = _sensor_json(seq)
    if target.suffix.lower() == ".npz":
        arrays: dict[str, np.ndarray] = {}
        for stream, fields in streams.items():
            for fname, value in fields.items():
                if (_base(stream), fname) in _OPTIONAL and np.isnan(value).all():
                    continue
                arrays[f"{stream}/{fname}"] = value
        for name, spans in labels.items():
            arrays[f"labels/{name}"] = spans
        if sensor is not None:
            arrays["meta_json"] = np.array(sensor)
        atomic_save_npz(target, **arrays)
        return target
    if target.exists() and not target.is_dir():
        raise ValueError(f"{target} is a file; give a .npz path or a folder")
    target.mkdir(parents=True, exist_ok=True)
    for stream, fname in TABLE_FILES.items():
        file = target / fname
        if stream not in streams:
            with contextlib.suppress(FileNotFoundError):
                file.unlink()
            continue
        _write_table(file, *_table_for(stream, streams[stream]))
    for stale in target.glob("poses_*.csv"):
        match = _SOURCE_FILE.fullmatch(stale.name)
        if match is not None and match.group(1) not in seq.pose_sources:
            stale.unlink()
    for name in seq.pose_sources:
        _write_table(
            target / pose_source_file(name), *_table_for("poses", streams[_SOURCE_PREFIX + name])
        )
    labels_file = target / _LABELS_FILE
    if labels:
        with atomic_write(labels_file, newline="") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(LABEL_COLUMNS)
            for name, spans in labels.items():
                for t0, t1 in spans.tolist():
                    writer.writerow([name, repr(t0), repr(t1)])
    else:
        with contextlib.suppress(FileNotFoundError):
            labels_file.unlink()
    meta_file = target / _META_FILE
    if sensor is not None:
        with atomic_write(meta_file) as handle:
            handle.write(sensor + "\n")
    else:
        with contextlib.suppress(FileNotFoundError):
            meta_file.unlink()
    return target


def _table_for(stream: str, a: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
    """Header and (N, C) matrix of one native CSV table."""
    t = a["t"][:, None]
    if stream == "imu":
        return IMU_COLUMNS, np.hstack((t, a["gyro"], a["accel"]))
    if stream == "wheel":
        return WHEEL_COLUMNS, np.hstack((t, a["left_speed"][:, None], a["right_speed"][:, None]))
    if stream == "gnss":
        if np.isnan(a["sigma"]).all():
            return GNSS_COLUMNS, np.hstack((t, a["position"]))
        return GNSS_COLUMNS + GNSS_SIGMA_COLUMNS, np.hstack((t, a["position"], a["sigma"]))
    if stream == "gnss_velocity":
        if np.isnan(a["sigma"]).all():
            return GNSS_VELOCITY_COLUMNS, np.hstack((t, a["velocity"]))
        return GNSS_VELOCITY_COLUMNS + GNSS_VELOCITY_SIGMA_COLUMNS, np.hstack(
            (t, a["velocity"], a["sigma"])
        )
    if stream == "gnss_heading":
        if np.isnan(a["sigma"]).all():
            return GNSS_HEADING_COLUMNS, np.hstack((t, a["heading"][:, None]))
        return GNSS_HEADING_COLUMNS + GNSS_HEADING_SIGMA_COLUMNS, np.hstack(
            (t, a["heading"][:, None], a["sigma"][:, None])
        )
    if stream == "magnetometer":
        if np.isnan(a["sigma"]).all():
            return MAGNETOMETER_COLUMNS, np.hstack((t, a["field"]))
        return MAGNETOMETER_COLUMNS + MAGNETOMETER_SIGMA_COLUMNS, np.hstack(
            (t, a["field"], a["sigma"][:, None])
        )
    base = np.hstack((t, a["position"], a["quaternion"]))
    if stream == "poses" and not np.isnan(a["covariance"]).all():
        rows, cols = np.triu_indices(6)
        return POSE_COLUMNS + POSE_COVARIANCE_COLUMNS, np.hstack(
            (base, a["covariance"][:, rows, cols])
        )
    return POSE_COLUMNS, base


def write_stream_csv(path: str | os.PathLike[str], name: str, stream: Any) -> Path:
    """Write one B = 1 stream as its native CSV table (``imu``, ``wheel``, ``gnss``,
    ``gnss_velocity``, ``gnss_heading``, ``magnetometer``, ``poses``, ``ground_truth``; the
    columns of :data:`TABLE_FILES`'s table), atomically.

    Only real samples (mask True) are written, numbers as shortest exact ``repr``; sigma
    and pose covariance columns only when some value is given (not NaN).

    Args:
        path: the file to write (normally ``FOLDER/<table name>``); its folder must exist.
        name: the stream's name.
        stream: the samples (``ImuSamples``, ``WheelSamples``, ...), B = 1.

    Returns:
        the path written.

    Raises:
        ValueError: B != 1, an unknown ``name``.
    """
    if name not in TABLE_FILES:
        raise ValueError(f"unknown stream {name!r}; native tables: {', '.join(TABLE_FILES)}")
    if stream.batch_size != 1:
        raise ValueError(f"write_stream_csv writes one stream, got B = {stream.batch_size}")
    arrays = {
        key: value[0].detach().to(device="cpu", dtype=torch.float64).numpy()
        for key, value in stream.compact().tensors().items()
        if key != "mask"
    }
    target = Path(path)
    _write_table(target, *_table_for(name, arrays))
    return target


def _write_table(file: Path, header: list[str], matrix: np.ndarray) -> None:
    """Write one native CSV table (header row, then ``matrix`` (N, C) rows) atomically."""
    with atomic_write(file, newline="") as handle:
        handle.write(",".join(header) + "\n")
        handle.write(_format_rows(matrix))


def _format_rows(matrix: np.ndarray) -> str:
    """Rows of floats as CSV text, each number as its shortest exact ``repr``."""
    if matrix.shape[0] == 0:
        return ""
    return "".join(",".join(map(repr, row)) + "\n" for row in matrix.tolist())
