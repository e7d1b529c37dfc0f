"""KITTI raw drives: the OXTS RT3003 GPS/IMU unit of ``<date>_drive_<nnnn>_{sync,extract}``.

Layout (the KITTI raw devkit's ``readme.txt``)::

    <drive>/oxts/timestamps.txt      one line per sample: ``YYYY-MM-DD HH:MM:SS.fffffffff``
    <drive>/oxts/data/0000000000.txt one file per sample, line k of timestamps.txt <-> file k

Each data file holds one line of 30 space-separated numbers (:data:`OXTS_FIELDS`): ``lat``,
``lon`` (deg), ``alt`` (m), ``roll`` (rad, positive left side up), ``pitch`` (rad, positive
front down), ``yaw`` (rad, 0 = east, counter-clockwise), velocities ``vn ve vf vl vu``
(m/s), accelerations ``ax ay az`` (vehicle axes: x front, y left, z top; specific force,
so about +9.81 on ``az`` when level) and ``af al au`` (forward, leftward, upward), angular
rates ``wx wy wz`` (vehicle axes) and ``wf wl wu``, ``pos_accuracy`` (m, north/east),
``vel_accuracy`` (m/s), ``navstat``, ``numsats``, ``posmode``, ``velmode``, ``orimode``.
The ``extract`` drives sample it at about 100 Hz, the ``sync`` drives at the 10 Hz of the
cameras (too slow to propagate an IMU well: a warning says so).

What the reader makes of it (a B = 1 :class:`~msf_torch.types.Sequence`):

* ``imu``: every sample, ``gyro = [wx, wy, wz]`` rad/s, ``accel = [ax, ay, az]`` m/s^2. The
  body frame is the OXTS unit's (x forward, y left, z up), the msf convention.
* ``ground_truth``: every sample's pose, position ``[e, n, u]`` m in the ENU frame about
  ``meta["gnss_origin"]`` (exact, :mod:`msf_torch.io.geodesy`), rotation
  ``Rz(yaw) Ry(pitch) Rx(roll)`` (body -> ENU, the devkit's ``convertOxtsToPose``). It is
  the unit's RTK-aided INS solution, what KITTI itself calls ground truth.
* ``gnss``: the same positions taken at ``gnss_rate_hz`` (the first sample of each
  ``1 / gnss_rate_hz`` interval; default 1 Hz, as GTSAM's KITTI example), with sigmas
  ``[pos_accuracy, pos_accuracy, NaN]`` (NaN: the configured ``gnss_sigma_m`` applies
  upward). They are the INS's positions, not raw receiver fixes: smoother and more
  correlated in time than a receiver's.
* times: seconds from the first sample; ``meta["time_origin_ns"]`` holds that first stamp
  as integer nanoseconds since 1970 (the stamps are read as UTC). ``meta["gnss_origin"]``
  is ``[lat, lon, alt]`` of the first sample with a position (``alt`` taken as the
  ellipsoidal height: the devkit does not say which it is, and a height offset barely moves
  the ENU axes), so ``msf run --export geojson,kml`` puts the run on the map.
  ``meta["oxts_posmode"]`` counts the samples of each GPS position mode.

Malformed input raises :class:`~msf_torch.io.errors.DataError` naming the file, line and
field: a timestamp that is not ``YYYY-MM-DD HH:MM:SS[.f]``, a data file that is missing or
does not hold 30 numbers, fewer data files than timestamps. The usual rules of
:mod:`msf_torch.io.native` follow (non-finite samples dropped and counted, backwards time an
error unless ``sort``, repeated stamps dropped).

Example:
    >>> seq = read_kitti_raw("2011_09_30_drive_0028_extract")  # doctest: +SKIP
    >>> seq.imu.t.shape  # about 100 Hz  # doctest: +SKIP
"""

from __future__ import annotations

__all__ = ["OXTS_FIELDS", "find_kitti_raw_root", "read_kitti_raw"]

import calendar
import math
import os
import re
import warnings
from collections import Counter
from collections.abc import Sequence as SequenceABC
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.geometry.so3 import rpy_matrix
from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.io.geodesy import geodetic_to_enu
from msf_torch.types import GnssFixes, ImuSamples, Sequence, Trajectory

OXTS_FIELDS = (
    "lat",
    "lon",
    "alt",
    "roll",
    "pitch",
    "yaw",
    "vn",
    "ve",
    "vf",
    "vl",
    "vu",
    "ax",
    "ay",
    "az",
    "af",
    "al",
    "au",
    "wx",
    "wy",
    "wz",
    "wf",
    "wl",
    "wu",
    "pos_accuracy",
    "vel_accuracy",
    "navstat",
    "numsats",
    "posmode",
    "velmode",
    "orimode",
)
"""The 30 values of an OXTS data file, in order."""

_COLUMN = {name: k for k, name in enumerate(OXTS_FIELDS)}
_STAMP = re.compile(r"(\d{4})-(\d{2})-(\d{2}) (\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?")
_SLOW_IMU_S = 0.05
"""A median sample spacing above this (s) is a synced (10 Hz) drive: warned."""


def find_kitti_raw_root(path: str | os.PathLike[str]) -> Path | None:
    """The ``oxts`` folder of a KITTI raw drive given the drive folder or ``oxts`` itself
    (a folder holding ``timestamps.txt`` and ``data/``), or None."""
    folder = Path(path)
    for candidate in (folder / "oxts", folder):
        if (candidate / "timestamps.txt").is_file() and (candidate / "data").is_dir():
            return candidate
    return None


def _stamp_ns(path: Path, line: int, text: str) -> int:
    """Nanoseconds since 1970 (UTC) of one ``timestamps.txt`` line."""
    match = _STAMP.fullmatch(text.strip())
    if match is None:
        raise DataError(
            path,
            f"expected YYYY-MM-DD HH:MM:SS.fffffffff, got {_tables.shown(text.strip())}",
            line=line,
            field="timestamp",
        )
    year, month, day, hour, minute, second = (int(x) for x in match.groups()[:6])
    fraction = match.group(7) or "0"
    if not (1 <= month <= 12 and 1 <= day <= 31 and hour < 24 and minute < 60 and second < 61):
        shown = _tables.shown(text.strip())
        raise DataError(path, f"not a date and time: {shown}", line=line, field="timestamp")
    seconds = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
    return seconds * 1_000_000_000 + int(fraction.ljust(9, "0"))


def _read_stamps(path: Path) -> list[int]:
    lines = _tables.split_lines(_tables.read_text(path))
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise DataError(path, "no timestamps")
    return [_stamp_ns(path, k + 1, text) for k, text in enumerate(lines)]


def _read_sample(path: Path) -> np.ndarray:
    """The 30 values of one data file (30,)."""
    lines = [x for x in _tables.split_lines(_tables.read_text(path)) if x.strip()]
    if len(lines) != 1:
        raise DataError(path, f"expected one line of {len(OXTS_FIELDS)} numbers, got {len(lines)}")
    cells = lines[0].split()
    if len(cells) != len(OXTS_FIELDS):
        raise DataError(path, f"expected {len(OXTS_FIELDS)} numbers, got {len(cells)}", line=1)
    values = np.empty(len(OXTS_FIELDS))
    for k, cell in enumerate(cells):
        try:
            values[k] = float(cell)
        except ValueError:
            raise DataError(
                path, f"not a number: {_tables.shown(cell)}", line=1, field=OXTS_FIELDS[k]
            ) from None
    return values


def _fix_rows(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the first sample of each ``1 / rate_hz`` interval of ``t`` (s)."""
    bins = np.floor(t * rate_hz + 1e-9)
    return np.flatnonzero(np.concatenate(([True], bins[1:] != bins[:-1])))


def read_kitti_raw(
    path: str | os.PathLike[str],
    sort: bool = False,
    gnss_rate_hz: float = 1.0,
    origin: SequenceABC[float] | None = None,
) -> Sequence:
    """Read a KITTI raw drive's OXTS GPS/IMU data (module docstring) as a Sequence (B = 1).

    Args:
        path: the drive folder (``..._extract`` or ``..._sync``) or its ``oxts`` folder.
        sort: stably sort samples whose stamps go backwards instead of raising.
        gnss_rate_hz: rate of the GNSS fixes taken from the OXTS positions, Hz (> 0).
        origin: ``[lat_deg, lon_deg, alt_m]`` of the ENU frame; None: the first sample
            with a position.

    Returns:
        the sequence (float64): ``imu`` (1, N), ``gnss`` (1, M), ``ground_truth`` (1, N),
        ``meta`` with ``gnss_origin``, ``time_origin_ns``, ``oxts_posmode`` and the
        cleaning counts, ``format`` ``"kitti-raw"``.

    Raises:
        DataError: malformed or missing files (module docstring). ValueError: a bad
            ``gnss_rate_hz`` or ``origin``.
    """
    if not (math.isfinite(gnss_rate_hz) and gnss_rate_hz > 0):
        raise ValueError(f"gnss_rate_hz must be a positive number, got {gnss_rate_hz!r}")
    oxts = find_kitti_raw_root(path)
    if oxts is None:
        raise DataError(path, "not a KITTI raw drive: no oxts/timestamps.txt and oxts/data/")
    stamps_path = oxts / "timestamps.txt"
    stamps = _read_stamps(stamps_path)
    data = oxts / "data"
    rows = np.stack([_read_sample(data / f"{k:010d}.txt") for k in range(len(stamps))])
    extra = data / f"{len(stamps):010d}.txt"
    if extra.exists():
        warnings.warn(
            f"{data}: more data files than the {len(stamps)} timestamps; the rest are ignored",
            stacklevel=2,
        )
    t = (np.asarray(stamps, dtype=np.int64) - stamps[0]) / 1e9
    col = {name: rows[:, k] for name, k in _COLUMN.items()}
    finite = np.isfinite(rows[:, :3]).all(axis=1) & (np.abs(col["lat"]) <= 90.0)
    if origin is None:
        if not finite.any():
            raise DataError(data, "no sample with a finite latitude, longitude and altitude")
        origin = rows[np.argmax(finite), :3]
    used = tuple(float(x) for x in origin)
    enu = np.full((rows.shape[0], 3), np.nan)
    enu[finite] = geodetic_to_enu(col["lat"][finite], col["lon"][finite], col["alt"][finite], used)
    attitude = np.isfinite(rows[:, 3:6]).all(axis=1)
    quat = np.full((rows.shape[0], 4), np.nan)
    if attitude.any():
        angles = np.stack([col[k][attitude] for k in ("roll", "pitch", "yaw")], -1)
        quat[attitude] = matrix_to_quat(rpy_matrix(torch.as_tensor(angles))).numpy()
    report = _tables.CleanReport()
    where = str(stamps_path)
    imu = _tables.clean_stream(
        report,
        "imu",
        where,
        {
            "t": t,
            "gyro": np.stack((col["wx"], col["wy"], col["wz"]), -1),
            "accel": np.stack((col["ax"], col["ay"], col["az"]), -1),
        },
        sort=sort,
        field_prefix="oxts/",
    )
    if imu["t"].shape[0] < 2:
        raise DataError(where, "fewer than 2 usable IMU samples")
    truth = _tables.clean_stream(
        report,
        "ground_truth",
        where,
        {"t": t, "position": enu, "quaternion": quat},
        sort=sort,
        field_prefix="oxts/",
    )
    accuracy = np.where(col["pos_accuracy"] > 0, col["pos_accuracy"], np.nan)
    sigma = np.stack((accuracy, accuracy, np.full_like(accuracy, np.nan)), -1)
    fixes = _tables.clean_stream(
        report,
        "gnss",
        where,
        {"t": t, "position": enu, "sigma": sigma},
        sort=sort,
        nan_ok=("sigma",),
        field_prefix="oxts/",
    )
    if fixes["t"].size:
        keep = _fix_rows(fixes["t"], gnss_rate_hz)
        fixes = {k: v[keep] for k, v in fixes.items()}
    spacing = float(np.median(np.diff(imu["t"])))
    if spacing > _SLOW_IMU_S:
        warnings.warn(
            f"{oxts}: OXTS samples {spacing:.3f} s apart (a synced drive?): the IMU is "
            "propagated at that rate; the unsynced 'extract' drive has it at 100 Hz",
            stacklevel=2,
        )
    posmode = Counter(int(x) for x in col["posmode"][np.isfinite(col["posmode"])])
    meta: dict[str, Any] = {
        "source": str(oxts.parent if oxts.name == "oxts" else oxts),
        "format": "kitti-raw",
        "gnss_origin": list(used),
        "time_origin_ns": int(stamps[0]),
        "gnss_rate_hz": float(gnss_rate_hz),
        "oxts_posmode": {str(k): v for k, v in sorted(posmode.items())},
        **report.to_meta(),
    }
    truth["quaternion"] = _tables.normalise_quaternions(truth["quaternion"])
    seq = Sequence(
        names=[_tables.path_name(oxts.parent if oxts.name == "oxts" else oxts)],
        imu=_tables.stream_from_arrays(ImuSamples, imu),
        gnss=_tables.stream_from_arrays(GnssFixes, fixes),
        ground_truth=_tables.stream_from_arrays(Trajectory, truth),
        meta=meta,
    )
    seq.check()
    return seq
