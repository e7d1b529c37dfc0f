"""The real KITTI IMU + GPS drive that the ``gtsam`` wheel ships under ``gtsam/Data/``.

GTSAM's ``IMUKittiExampleGPS`` example uses three files, read here through the installed
package (nothing is copied into this repository):

* ``KittiEquivBiasedImu.txt``: header ``Time dt accelX accelY accelZ omegaX omegaY omegaZ``,
  space separated; s, s, m/s^2, rad/s. The first row's ``dt`` equals its time (a quirk of
  the file); only ``Time`` is kept, the estimator computes its own steps.
* ``KittiEquivBiasedImu_metadata.txt``: one header line and one value line: ``BodyPtx
  BodyPty BodyPtz BodyPrx BodyPry BodyPrz AccelerometerSigma GyroscopeSigma
  IntegrationSigma AccelerometerBiasSigma GyroscopeBiasSigma AverageDeltaT``.
* ``KittiGps_converted.txt``: CSV ``Time,X,Y,Z``, GPS fixes in a local metric frame (m).

The sequence is named ``"kitti-gtsam"``; times stay as given (absolute seconds, about
46534 s to 47006 s). The gtsam extra is needed: ``pip install 'msf_torch[peers]'``.
"""

from __future__ import annotations

__all__ = [
    "KITTI_GTSAM_NAME",
    "KITTI_IMU_FILE",
    "KITTI_IMU_METADATA_FILE",
    "KITTI_GPS_FILE",
    "gtsam_data_dir",
    "gtsam_data_path",
    "load_kitti_gtsam",
]

import importlib.resources
import importlib.util
import os
from pathlib import Path
from typing import Any

import numpy as np

from msf_torch.io import _tables
from msf_torch.io.errors import DataError, MissingExtraError
from msf_torch.types import GnssFixes, ImuSamples, Sequence

KITTI_GTSAM_NAME = "kitti-gtsam"
KITTI_IMU_FILE = "KittiEquivBiasedImu.txt"
KITTI_IMU_METADATA_FILE = "KittiEquivBiasedImu_metadata.txt"
KITTI_GPS_FILE = "KittiGps_converted.txt"

_IMU_COLUMNS = ["Time", "dt", "accelX", "accelY", "accelZ", "omegaX", "omegaY", "omegaZ"]
_GPS_COLUMNS = ["Time", "X", "Y", "Z"]
_METADATA_COLUMNS = {
    "AccelerometerSigma": "accel_noise_sigma",
    "GyroscopeSigma": "gyro_noise_sigma",
    "IntegrationSigma": "integration_sigma",
    "AccelerometerBiasSigma": "accel_bias_rw_sigma",
    "GyroscopeBiasSigma": "gyro_bias_rw_sigma",
    "AverageDeltaT": "average_dt",
}
_BODY_P_SENSOR = ["BodyPtx", "BodyPty", "BodyPtz", "BodyPrx", "BodyPry", "BodyPrz"]


def gtsam_data_dir() -> Path:
    """The ``Data`` folder of the installed ``gtsam`` wheel.

    Found with ``importlib.resources.files("gtsam") / "Data"``; if that is not a real
    folder (e.g. a zipped install), the package's ``submodule_search_locations`` are tried.

    Raises:
        MissingExtraError: gtsam is not installed (names the ``peers`` extra).
        DataError: gtsam is installed but ships no ``Data`` folder.
    """
    spec = importlib.util.find_spec("gtsam")
    if spec is None:
        raise MissingExtraError("gtsam", "peers", "the data files shipped with gtsam")
    candidates: list[Path] = []
    try:
        resource = importlib.resources.files("gtsam") / "Data"
        candidates.append(Path(str(resource)))
    except (ImportError, TypeError, ValueError):
        pass
    for location in spec.submodule_search_locations or []:
        candidates.append(Path(location) / "Data")
    for folder in candidates:
        if folder.is_dir():
            return folder
    where = ", ".join(str(c) for c in candidates) or "(no package folder)"
    raise DataError(
        where, "the installed gtsam has no Data folder (a gtsam >= 4.2 wheel ships one)"
    )


def gtsam_data_path(name: str) -> Path:
    """Path of one data file shipped with gtsam, e.g. ``gtsam_data_path("sphere2500.txt")``.

    Args:
        name: a file name (or relative path) inside ``gtsam/Data``.

    Returns:
        the absolute path of an existing file.

    Raises:
        MissingExtraError: gtsam is not installed.
        DataError: no such file in the installed gtsam's Data folder.
    """
    folder = gtsam_data_dir()
    path = folder / name
    if not path.is_file():
        raise DataError(path, f"no such data file in the installed gtsam ({folder})")
    return path


def _read_metadata(path: Path) -> dict[str, Any]:
    table = _tables.read_table(path, delimiter=None)
    _tables.check_columns(table, _BODY_P_SENSOR + list(_METADATA_COLUMNS))
    if len(table) != 1:
        raise DataError(path, f"expected one line of values, got {len(table)}")
    values = table.floats(table.header or [])[0]
    named = dict(zip(table.header or [], values.tolist(), strict=True))
    noise: dict[str, Any] = {key: named[col] for col, key in _METADATA_COLUMNS.items()}
    noise["body_p_sensor"] = [named[c] for c in _BODY_P_SENSOR]
    return noise


def load_kitti_gtsam(
    sort: bool = False, data_dir: str | os.PathLike[str] | None = None
) -> Sequence:
    """Load the KITTI IMU + GPS drive shipped with gtsam as a Sequence (B = 1).

    Args:
        sort: passed to the cleaning rules (the shipped files are already time-sorted).
        data_dir: a folder holding the three files in the layout described in the module
            docstring (e.g. an edited copy), or None for the installed gtsam's ``Data``
            folder. ``meta["source"]`` is this folder.

    Returns:
        a :class:`~msf_torch.types.Sequence` named ``"kitti-gtsam"`` with

        * ``imu``: 46968 samples, ``t`` (1, N) absolute s, ``gyro`` (1, N, 3) rad/s from
          ``omegaX..Z``, ``accel`` (1, N, 3) m/s^2 from ``accelX..Z``;
        * ``gnss``: 470 fixes, ``position`` (1, M, 3) m in the file's local frame,
          ``sigma`` NaN (the file gives none; the estimator's default applies);
        * ``meta["imu_noise"]``: the metadata file's values under unit-named keys, as
          GTSAM's example uses them: ``accel_noise_sigma`` (m/s^2, continuous-time,
          i.e. m/s^2/sqrt(Hz)), ``gyro_noise_sigma`` (rad/s/sqrt(Hz)), ``integration_sigma``,
          ``accel_bias_rw_sigma`` (m/s^3/sqrt(Hz)), ``gyro_bias_rw_sigma``
          (rad/s^2/sqrt(Hz)), ``average_dt`` (s) and ``body_p_sensor``
          ``[tx, ty, tz, rx, ry, rz]`` (m, rad);
        * the usual cleaning counts, ``meta["source"]`` (the Data folder) and
          ``meta["format"] == "kitti-gtsam"``.

    Raises:
        MissingExtraError: ``data_dir`` is None and gtsam is not installed
            (``pip install 'msf_torch[peers]'``).
        DataError: a missing or malformed data file.
    """
    if data_dir is None:
        imu_path = gtsam_data_path(KITTI_IMU_FILE)
        gps_path = gtsam_data_path(KITTI_GPS_FILE)
        metadata_path = gtsam_data_path(KITTI_IMU_METADATA_FILE)
    else:
        folder = Path(data_dir)
        imu_path, gps_path, metadata_path = (
            folder / name for name in (KITTI_IMU_FILE, KITTI_GPS_FILE, KITTI_IMU_METADATA_FILE)
        )
    noise = _read_metadata(metadata_path)

    imu_table = _tables.read_table(imu_path, delimiter=None)
    _tables.check_columns(imu_table, _IMU_COLUMNS)
    d = imu_table.floats(["Time", "omegaX", "omegaY", "omegaZ", "accelX", "accelY", "accelZ"])
    report = _tables.CleanReport()
    imu = _tables.clean_stream(
        report,
        "imu",
        str(imu_path),
        {"t": d[:, 0], "gyro": d[:, 1:4], "accel": d[:, 4:7]},
        lines=imu_table.lines,
        sort=sort,
        time_name="Time",
    )

    gps_table = _tables.read_table(gps_path)
    _tables.check_columns(gps_table, _GPS_COLUMNS)
    g = gps_table.floats(_GPS_COLUMNS)
    gps = _tables.clean_stream(
        report,
        "gnss",
        str(gps_path),
        {"t": g[:, 0], "position": g[:, 1:4], "sigma": np.full((g.shape[0], 3), np.nan)},
        lines=gps_table.lines,
        sort=sort,
        nan_ok=("sigma",),
        time_name="Time",
    )
    if imu["t"].shape[0] == 0:
        raise DataError(imu_path, "no IMU samples")

    meta: dict[str, Any] = {
        "source": str(imu_path.parent),
        "format": KITTI_GTSAM_NAME,
        "imu_noise": noise,
        **report.to_meta(),
    }
    seq = Sequence(
        names=[KITTI_GTSAM_NAME],
        imu=_tables.stream_from_arrays(ImuSamples, imu),
        gnss=_tables.stream_from_arrays(GnssFixes, gps),
        meta=meta,
    )
    seq.check()
    return seq
