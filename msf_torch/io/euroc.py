"""EuRoC MAV (ASL folder layout) IMU and ground truth.

Layout: ``<folder>/mav0/imu0/data.csv`` or ``<folder>/imu0/data.csv`` with header
``#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z``
and, optionally, ``state_groundtruth_estimate0/data.csv`` beside ``imu0`` with
``#timestamp,p_RS_R_x [m],p_RS_R_y,p_RS_R_z,q_RS_w [],q_RS_x,q_RS_y,q_RS_z,...`` (velocity
and bias columns follow and are ignored). Column names are matched without their
``[unit]`` suffix. Timestamps are integer nanoseconds, converted exactly to float64 seconds.
``imu0/sensor.yaml``, when present, gives the IMU noise densities.
"""

from __future__ import annotations

__all__ = ["EUROC_IMU_COLUMNS", "EUROC_GT_COLUMNS", "find_euroc_root", "read_euroc"]

import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.types import ImuSamples, Sequence, Trajectory

EUROC_IMU_COLUMNS = [
    "timestamp",
    "w_RS_S_x",
    "w_RS_S_y",
    "w_RS_S_z",
    "a_RS_S_x",
    "a_RS_S_y",
    "a_RS_S_z",
]
EUROC_GT_COLUMNS = [
    "timestamp",
    "p_RS_R_x",
    "p_RS_R_y",
    "p_RS_R_z",
    "q_RS_w",
    "q_RS_x",
    "q_RS_y",
    "q_RS_z",
]

_UNIT = re.compile(r"\s*\[[^\]]*\]\s*$")

_YAML_NOISE = {
    "gyroscope_noise_density": "gyro_noise_density",
    "gyroscope_random_walk": "gyro_bias_rw_density",
    "accelerometer_noise_density": "accel_noise_density",
    "accelerometer_random_walk": "accel_bias_rw_density",
    "rate_hz": "rate_hz",
}


def find_euroc_root(folder: str | os.PathLike[str]) -> Path | None:
    """The folder holding ``imu0/`` (``folder/mav0`` or ``folder`` itself), or None."""
    base = Path(folder)
    for root in (base / "mav0", base):
        if (root / "imu0").is_dir():
            return root
    return None


def _ns_to_seconds(ns: np.ndarray) -> np.ndarray:
    """int64 ns (N,) -> float64 s (N,), splitting whole seconds to keep precision."""
    whole, frac = np.divmod(ns, 1_000_000_000)
    return whole.astype(np.float64) + frac.astype(np.float64) * 1e-9


def _read(path: Path, required: list[str]) -> tuple[_tables.Table, np.ndarray, np.ndarray]:
    """Read an ASL csv; return the table, t (N,) s and the float columns after time."""
    table = _tables.read_table(path, header="hash")
    assert table.header is not None
    table.header = [_UNIT.sub("", name) for name in table.header]
    missing = [c for c in required if c not in table.header]
    if missing:
        raise DataError(
            path,
            f"missing column (the header has: {', '.join(table.header)})",
            line=table.header_line,
            field=missing[0],
        )
    t = _ns_to_seconds(table.ints("timestamp"))
    return table, t, table.floats(required[1:])


def _read_sensor_yaml(path: Path) -> dict[str, Any]:
    """IMU noise densities from ``imu0/sensor.yaml`` (EuRoC's ``%YAML:1.0`` files).

    Directive lines (``%...``) are blanked, not removed, so YAML's line numbers stay the
    file's. A noise value or ``T_BS`` entry that is not a finite number is a DataError.
    """
    lines = _tables.split_lines(_tables.read_text(path))
    text = "\n".join("" if line.startswith("%") else line for line in lines)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        raise DataError(path, f"invalid YAML: {err}", line=line) from None
    except RecursionError:
        raise DataError(path, "invalid YAML: nested too deeply") from None
    if not isinstance(doc, dict):
        return {}
    noise: dict[str, Any] = {}
    for key, name in _YAML_NOISE.items():
        value = doc.get(key)
        if isinstance(value, int | float) and not isinstance(value, bool):
            noise[name] = _finite_yaml_number(path, value, key)
    body = doc.get("T_BS")
    if isinstance(body, dict) and isinstance(body.get("data"), list) and len(body["data"]) == 16:
        noise["T_body_sensor"] = [
            _finite_yaml_number(path, x, f"T_BS.data[{k}]") for k, x in enumerate(body["data"])
        ]
    return noise


def _finite_yaml_number(path: Path, value: Any, key: str) -> float:
    """``value`` as a finite float; DataError naming ``key`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DataError(path, f"not a number: {value!r}", field=key)
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise DataError(path, f"not finite: {value!r}", field=key)
    return number


def read_euroc(folder: str | os.PathLike[str], sort: bool = False) -> Sequence:
    """Read a EuRoC ASL folder's IMU and (optional) ground truth into a Sequence (B = 1).

    Args:
        folder: the sequence folder (holding ``mav0/``) or the ``mav0`` folder itself.
        sort: stably sort streams whose timestamps go backwards instead of raising.

    Returns:
        a :class:`~msf_torch.types.Sequence` with ``imu`` (``t`` (1, N) s, ``gyro`` from
        ``w_RS_S`` rad/s, ``accel`` from ``a_RS_S`` m/s^2), ``ground_truth`` when
        ``state_groundtruth_estimate0/data.csv`` exists (position m, quaternion
        ``[w, x, y, z]`` body -> world, normalised), ``names == [folder name]``, and meta:
        the cleaning counts (see ``msf_torch.io.native``), ``source``, ``format ==
        "euroc"`` and, if ``imu0/sensor.yaml`` exists, ``imu_noise`` with keys
        ``gyro_noise_density`` (rad/s/sqrt(Hz)), ``gyro_bias_rw_density``
        (rad/s^2/sqrt(Hz)), ``accel_noise_density`` (m/s^2/sqrt(Hz)),
        ``accel_bias_rw_density`` (m/s^3/sqrt(Hz)), ``rate_hz`` and ``T_body_sensor``
        (16 numbers, row-major 4x4).

    Raises:
        DataError: no ``imu0/data.csv``, or malformed files (file, line and column named).
    """
    base = Path(folder)
    root = find_euroc_root(base)
    if root is None:
        raise DataError(base, "not a EuRoC ASL folder: no mav0/imu0/ or imu0/ inside")
    report = _tables.CleanReport()
    imu_path = root / "imu0" / "data.csv"
    table, t, d = _read(imu_path, EUROC_IMU_COLUMNS)
    imu = _tables.clean_stream(
        report,
        "imu",
        str(imu_path),
        {"t": t, "gyro": d[:, 0:3], "accel": d[:, 3:6]},
        lines=table.lines,
        sort=sort,
        time_name="timestamp",
    )
    if imu["t"].shape[0] == 0:
        raise DataError(imu_path, "no IMU samples (after dropping non-finite rows)")
    ground_truth = None
    gt_path = root / "state_groundtruth_estimate0" / "data.csv"
    if gt_path.exists():
        gt_table, gt_t, g = _read(gt_path, EUROC_GT_COLUMNS)
        _tables.check_quaternions(str(gt_path), g[:, 3:7], lines=gt_table.lines, name="q_RS_w")
        gt = _tables.clean_stream(
            report,
            "ground_truth",
            str(gt_path),
            {"t": gt_t, "position": g[:, 0:3], "quaternion": g[:, 3:7]},
            lines=gt_table.lines,
            sort=sort,
            time_name="timestamp",
        )
        gt["quaternion"] = _tables.normalise_quaternions(gt["quaternion"])
        ground_truth = _tables.stream_from_arrays(Trajectory, gt)
    meta: dict[str, Any] = {
        "source": str(base),
        "format": "euroc",
        "platform": "aerial",  # a MAV: no non-holonomic constraint (config_for_sequence)
        **report.to_meta(),
    }
    yaml_path = root / "imu0" / "sensor.yaml"
    if yaml_path.exists():
        noise = _read_sensor_yaml(yaml_path)
        if noise:
            meta["imu_noise"] = noise
    name = base.resolve().name
    if name == "mav0":
        name = base.resolve().parent.name
    seq = Sequence(
        names=[name],
        imu=_tables.stream_from_arrays(ImuSamples, imu),
        ground_truth=ground_truth,
        meta=meta,
    )
    seq.check()
    return seq
