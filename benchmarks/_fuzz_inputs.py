"""Malformed inputs for every reader in ``msf_torch.io`` (hypothesis strategies) and the oracle
that judges what a reader did with them.

Used by ``benchmarks/fuzz.py`` (10,000+ inputs) and ``tests/io/test_fuzz_readers.py`` (a few
dozen per reader in CI). Not a benchmark itself; imported as ``benchmarks._fuzz_inputs``.

A *case* is a valid input of one format (random sizes and numbers from a drawn seed) with 1 to
3 mutations applied, written into a fresh folder as ``files`` (relative path -> bytes, or None
for a folder). Mutations of text files: a truncated line or file, a dropped, extra or replaced
field (the replacement drawn from :data:`JUNK_TOKENS`: non-numbers, NaN/inf, huge and tiny
numbers, odd Unicode digits, quotes, NUL, ...), swapped, repeated or deleted lines (backwards
or repeated stamps, lost headers), a line of binary junk, flipped bytes, an empty file, a file
of random bytes, blank and comment lines, another delimiter, a non-UTF-8 byte, a NUL byte, a
very long cell, CR line ends. Binary ``.npz`` inputs are mutated as arrays (missing, unknown,
mistyped or misshapen keys, NaN/inf/huge values, backwards time, zero quaternions, bad labels
and meta JSON) and as bytes (truncated, flipped, junk). Folder inputs also lose files or get
a folder where a file should be.

:func:`classify` runs a reader on a case and returns one of

* ``"ok"``: the reader returned and its result keeps the io promises (finite values where
  promised, strictly increasing times, unit quaternions, orthonormal rotations, positive
  definite information matrices);
* ``"data_error"``: a :class:`~msf_torch.io.errors.DataError` (or ``MissingExtraError``)
  whose path is the input or inside it, with a line number (when given) that the file has;
* ``"bad_output"``: the reader returned a result that breaks a promise (e.g. a NaN passed);
* ``"bad_error"``: a DataError that points outside the input or at a line the file lacks;
* ``"crash"``: any other exception.

Only the first two are acceptable.
"""

from __future__ import annotations

__all__ = [
    "JUNK_TOKENS",
    "READERS",
    "OUTCOMES",
    "ACCEPTED",
    "FuzzCase",
    "Reader",
    "case_strategy",
    "classify",
    "write_case",
]

import datetime
import io
import json
import math
import os
import re
import struct
import traceback
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hypothesis import strategies as st

from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io import (
    DataError,
    MissingExtraError,
    PoseGraph,
    PoseGraph2D,
    load_eqvio,
    load_kitti_gtsam,
    read_euroc,
    read_native,
    read_pose_graph,
    read_pose_graph_2d,
    read_tum,
)
from msf_torch.io.encoders import read_encoder_counts
from msf_torch.io.eqvio import EqvioRun
from msf_torch.io.kitti_poses import read_kitti_poses
from msf_torch.io.kitti_raw import OXTS_FIELDS, read_kitti_raw
from msf_torch.io.nmea import DEFAULT_QUALITIES, NmeaLog, read_nmea
from msf_torch.io.ranges import RangeRun, read_range_run
from msf_torch.io.scans import read_scans
from msf_torch.io.ubx import UbxLog, read_ubx
from msf_torch.types import Sequence, Trajectory, WheelSamples

OUTCOMES = ("ok", "data_error", "bad_output", "bad_error", "crash")
ACCEPTED = ("ok", "data_error")

JUNK_TOKENS = (
    "",
    " ",
    "abc",
    "nan",
    "NaN",
    "-nan",
    "inf",
    "-inf",
    "+Infinity",
    "1e400",
    "-1e400",
    "1e-400",
    "1e308",
    "-1.7976931348623157e308",
    "4.9e-324",
    "9" * 400,
    "-" + "9" * 30,
    "18446744073709551616",
    "-9223372036854775809",
    "9223372036854775807",
    "-0",
    "0x1A",
    "1_000",
    "\u0661\u0662",  # Arabic-Indic digits: Python's float() reads them, numpy does not
    "\uff11",  # fullwidth 1
    "1,5",
    "1.2.3",
    "--1",
    "e5",
    ".",
    "+",
    '"',
    '"1"',
    '"a,b"',
    "\x00",
    "\t",
    "\x0c",
    "\u2028",
    "None",
    "true",
    "\u221e",
    "1e5\x00",
    "#",
)
"""Replacement tokens: not numbers, non-finite, out-of-range, odd grammar and odd bytes."""

_FILE_JUNK = (
    b"",
    b"\x00" * 16,
    b"\xff\xfe\x00\x00",
    b"PK\x03\x04",
    b"\x93NUMPY\x01\x00",
    b"\xef\xbb\xbf",
    b"#",
    b"\n\n\n",
    b"\r",
    b'"',
)


@dataclass
class FuzzCase:
    """One generated input.

    Attributes:
        reader: key of :data:`READERS`.
        files: relative path -> bytes (a file) or None (a folder), written by
            :func:`write_case`.
        entry: the relative path handed to the reader (``""``: the case folder itself).
        sort: the reader's ``sort`` flag (readers that have one).
        mutations: names of the mutations applied, in order (for reports).
    """

    reader: str
    files: dict[str, bytes | None]
    entry: str
    sort: bool
    mutations: list[str]


@dataclass(frozen=True)
class Reader:
    """A reader under test: how to build its valid input, call it and check its result."""

    name: str
    build: Callable[[np.random.Generator], tuple[dict[str, Any], str]]
    read: Callable[[Path, bool], Any]
    check: Callable[[Any], str | None]
    binary: bool = False


# ----------------------------------------------------------------------------- valid inputs


def _num(x: float) -> str:
    return repr(float(x))


def _csv(header: list[str] | None, rows: np.ndarray | list[list[str]], sep: str = ",") -> str:
    lines = [] if header is None else [sep.join(header)]
    for row in rows:
        lines.append(sep.join(c if isinstance(c, str) else _num(c) for c in row))
    return "\n".join(lines) + "\n"


def _times(rng: np.random.Generator, n: int, t0: float = 100.0, step: float = 0.01) -> np.ndarray:
    return t0 + np.cumsum(rng.uniform(0.5, 1.5, n) * step)


def _quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _native_arrays(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A valid native sequence as npz arrays (every stream, a named source, labels, meta)."""
    n_imu = int(rng.integers(2, 30))
    out: dict[str, np.ndarray] = {
        "imu/t": _times(rng, n_imu),
        "imu/gyro": rng.normal(size=(n_imu, 3)),
        "imu/accel": rng.normal(size=(n_imu, 3)) + [0.0, 0.0, 9.81],
    }
    n_w = int(rng.integers(0, 8))
    out |= {
        "wheel/t": _times(rng, n_w, step=0.05),
        "wheel/left_speed": rng.normal(size=n_w),
        "wheel/right_speed": rng.normal(size=n_w),
    }
    n_g = int(rng.integers(0, 5))
    out |= {
        "gnss/t": _times(rng, n_g, step=0.1),
        "gnss/position": rng.normal(size=(n_g, 3)) * 100.0,
        "gnss/sigma": rng.uniform(0.1, 2.0, (n_g, 3)),
    }
    n_v = int(rng.integers(0, 5))
    velocity = rng.normal(size=(n_v, 3)) * 5.0
    velocity[rng.random(n_v) < 0.5, 2] = np.nan  # RMC-style: no vertical speed
    out |= {
        "gnss_velocity/t": _times(rng, n_v, step=0.1),
        "gnss_velocity/velocity": velocity,
        "gnss_velocity/sigma": rng.uniform(0.02, 0.5, (n_v, 3)),
    }
    n_h = int(rng.integers(0, 5))
    heading_sigma = rng.uniform(0.001, 0.1, n_h)
    heading_sigma[rng.random(n_h) < 0.3] = np.nan  # not given: the configured default
    out |= {
        "gnss_heading/t": _times(rng, n_h, step=0.1),
        "gnss_heading/heading": rng.uniform(-10.0, 10.0, n_h),  # any angle: the filter wraps
        "gnss_heading/sigma": heading_sigma,
    }
    n_m = int(rng.integers(0, 6))
    field_sigma = rng.uniform(0.1, 2.0, n_m)
    field_sigma[rng.random(n_m) < 0.3] = np.nan  # not given: the configured default
    out |= {
        "magnetometer/t": _times(rng, n_m, step=0.05),
        "magnetometer/field": rng.normal(size=(n_m, 3)) * 40.0,  # uT, before calibration
        "magnetometer/sigma": field_sigma,
    }
    for prefix in ("poses", "poses/vo"):
        n_p = int(rng.integers(0, 5))
        a = rng.normal(size=(n_p, 6, 6))
        out |= {
            f"{prefix}/t": _times(rng, n_p, step=0.1),
            f"{prefix}/position": rng.normal(size=(n_p, 3)),
            f"{prefix}/quaternion": _quats(rng, n_p),
            f"{prefix}/covariance": a @ np.swapaxes(a, 1, 2) * 1e-3,
        }
    n_gt = int(rng.integers(0, 6))
    out |= {
        "ground_truth/t": _times(rng, n_gt, step=0.05),
        "ground_truth/position": rng.normal(size=(n_gt, 3)),
        "ground_truth/quaternion": _quats(rng, n_gt),
        "labels/slip": np.array([[100.0, 100.1], [100.2, 100.3]]),
        "meta_json": np.array(json.dumps({"wheel_track_m": 0.5, "imu_noise": {"rate_hz": 100}})),
    }
    return out


def _native_folder(rng: np.random.Generator) -> dict[str, str]:
    """The same schema as CSV tables (pose sigmas or covariance entries drawn at random)."""
    a = _native_arrays(rng)
    files = {
        "imu.csv": _csv(
            ["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"],
            np.column_stack((a["imu/t"], a["imu/gyro"], a["imu/accel"])),
        ),
        "wheel.csv": _csv(
            ["t", "left_speed", "right_speed"],
            np.column_stack((a["wheel/t"], a["wheel/left_speed"], a["wheel/right_speed"])),
        ),
        "gnss.csv": _csv(
            ["t", "x", "y", "z", "sigma_x", "sigma_y", "sigma_z"],
            np.column_stack((a["gnss/t"], a["gnss/position"], a["gnss/sigma"])),
        ),
        "gnss_velocity.csv": _csv(
            ["t", "vx", "vy", "vz", "sigma_vx", "sigma_vy", "sigma_vz"],
            np.column_stack(
                (a["gnss_velocity/t"], a["gnss_velocity/velocity"], a["gnss_velocity/sigma"])
            ),
        ),
        "gnss_heading.csv": _csv(
            ["t", "heading", "sigma_heading"],
            np.column_stack(
                (a["gnss_heading/t"], a["gnss_heading/heading"], a["gnss_heading/sigma"])
            ),
        ),
        "magnetometer.csv": _csv(
            ["t", "mx", "my", "mz", "sigma"],
            np.column_stack(
                (a["magnetometer/t"], a["magnetometer/field"], a["magnetometer/sigma"])
            ),
        ),
        "ground_truth.csv": _csv(
            ["t", "x", "y", "z", "qw", "qx", "qy", "qz"],
            np.column_stack(
                (a["ground_truth/t"], a["ground_truth/position"], a["ground_truth/quaternion"])
            ),
        ),
        "labels.csv": "name,t_start,t_end\nslip,100.0,100.1\nweather:rain,100.0,100.3\n",
        "meta.json": json.dumps({"wheel_track_m": 0.5}) + "\n",
    }
    for prefix, name in (("poses", "poses.csv"), ("poses/vo", "poses_vo.csv")):
        base = np.column_stack(
            (a[f"{prefix}/t"], a[f"{prefix}/position"], a[f"{prefix}/quaternion"])
        )
        header = ["t", "x", "y", "z", "qw", "qx", "qy", "qz"]
        if rng.random() < 0.5:
            header += ["sigma_x", "sigma_y", "sigma_z", "sigma_roll", "sigma_pitch", "sigma_yaw"]
            base = np.column_stack((base, rng.uniform(0.01, 0.1, (base.shape[0], 6))))
        else:
            rows, cols = np.triu_indices(6)
            header += [f"c{i}{j}" for i, j in zip(rows, cols, strict=True)]
            base = np.column_stack((base, a[f"{prefix}/covariance"][:, rows, cols]))
        files[name] = _csv(header, base)
    return files


def _build_npz(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    return {"run.npz": _native_arrays(rng)}, "run.npz"


def _build_native_csv(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    return dict(_native_folder(rng)), ""


def _build_tum(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 25))
    q = _quats(rng, n)
    rows = np.column_stack((_times(rng, n), rng.normal(size=(n, 3)), q[:, 1:], q[:, :1]))
    text = "# t x y z qx qy qz qw\n" + _csv(None, rows, sep=" ")
    return {"traj.tum": text}, "traj.tum"


def _build_kitti_poses(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 25))
    matrices = quat_to_matrix(torch.as_tensor(_quats(rng, n))).numpy()
    rows = np.concatenate((matrices, rng.normal(size=(n, 3, 1)) * 10), -1).reshape(n, 12)
    times = _times(rng, n, t0=0.0, step=0.1)[:, None]
    return {"poses.txt": _csv(None, rows, sep=" "), "times.txt": _csv(None, times)}, ""


def _build_scans(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n, k = int(rng.integers(1, 12)), int(rng.integers(2, 40))
    ranges = rng.uniform(0.1, 30.0, (n, k))
    ranges[rng.random((n, k)) < 0.1] = np.nan
    arrays = {
        "t": _times(rng, n, t0=0.0, step=0.1),
        "angles": np.linspace(-np.pi / 2, np.pi / 2, k),
        "ranges": ranges,
        "odometry": rng.normal(size=(n, 3)),
        "truth": rng.normal(size=(n, 3)),
    }
    if rng.random() < 0.3:
        del arrays["odometry"], arrays["truth"]
    return {"scans.npz": arrays}, "scans.npz"


def _build_euroc(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 25))
    ns = 1_403_715_273_000_000_000 + np.cumsum(rng.integers(4_000_000, 6_000_000, n))
    imu_rows = [
        [str(int(t)), *map(_num, row)]
        for t, row in zip(ns, rng.normal(size=(n, 6)).tolist(), strict=True)
    ]
    imu = _csv(
        [
            "#timestamp [ns]",
            "w_RS_S_x [rad s^-1]",
            "w_RS_S_y [rad s^-1]",
            "w_RS_S_z [rad s^-1]",
            "a_RS_S_x [m s^-2]",
            "a_RS_S_y [m s^-2]",
            "a_RS_S_z [m s^-2]",
        ],
        imu_rows,
    )
    m = int(rng.integers(0, 10))
    gt_ns = ns[0] + np.cumsum(rng.integers(4_000_000, 6_000_000, m))
    gt_vals = np.column_stack((rng.normal(size=(m, 3)), _quats(rng, m), rng.normal(size=(m, 9))))
    gt = _csv(
        ["#timestamp", "p_RS_R_x [m]", "p_RS_R_y [m]", "p_RS_R_z [m]", "q_RS_w []", "q_RS_x []"]
        + ["q_RS_y []", "q_RS_z []", "v_RS_R_x [m s^-1]", "v_RS_R_y", "v_RS_R_z"]
        + ["b_w_RS_S_x", "b_w_RS_S_y", "b_w_RS_S_z", "b_a_RS_S_x", "b_a_RS_S_y", "b_a_RS_S_z"],
        [[str(int(t)), *map(_num, row)] for t, row in zip(gt_ns, gt_vals.tolist(), strict=True)],
    )
    data = ", ".join(_num(x) for x in np.eye(4).ravel())
    yaml_text = (
        "%YAML:1.0\nsensor_type: imu\nrate_hz: 200\n"
        f"gyroscope_noise_density: {_num(rng.uniform(1e-4, 1e-3))}\n"
        "gyroscope_random_walk: 1.9393e-05\naccelerometer_noise_density: 2.0e-3\n"
        "accelerometer_random_walk: 3.0e-3\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
    )
    return {
        "mav0": None,
        "mav0/imu0": None,
        "mav0/imu0/data.csv": imu,
        "mav0/imu0/sensor.yaml": yaml_text,
        "mav0/state_groundtruth_estimate0": None,
        "mav0/state_groundtruth_estimate0/data.csv": gt,
    }, ""


def _build_kitti_raw(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 15))
    ns = 1_317_386_400_000_000_000 + np.cumsum(rng.integers(9_000_000, 11_000_000, n))
    files: dict[str, Any] = {"oxts": None, "oxts/data": None}
    stamps = []
    for k, stamp in enumerate(ns.tolist()):
        when = datetime.datetime.fromtimestamp(stamp // 1_000_000_000, datetime.UTC)
        stamps.append(f"{when:%Y-%m-%d %H:%M:%S}.{stamp % 1_000_000_000:09d}")
        values = rng.normal(size=len(OXTS_FIELDS))
        values[:3] = [49.0 + 1e-4 * values[0], 8.4 + 1e-4 * values[1], 110.0 + values[2]]
        files[f"oxts/data/{k:010d}.txt"] = " ".join(_num(x) for x in values) + "\n"
    files["oxts/timestamps.txt"] = "\n".join(stamps) + "\n"
    return files, ""


def _build_kitti(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 25))
    t = _times(rng, n, t0=46534.0)
    dt = np.diff(t, prepend=t[0])
    imu = _csv(
        ["Time", "dt", "accelX", "accelY", "accelZ", "omegaX", "omegaY", "omegaZ"],
        np.column_stack((t, dt, rng.normal(size=(n, 6)))),
        sep=" ",
    )
    m = int(rng.integers(0, 6))
    gps = _csv(
        ["Time", "X", "Y", "Z"],
        np.column_stack((_times(rng, m, t0=46534.0, step=0.1), rng.normal(size=(m, 3)) * 10)),
    )
    metadata = (
        "BodyPtx BodyPty BodyPtz BodyPrx BodyPry BodyPrz AccelerometerSigma GyroscopeSigma "
        "IntegrationSigma AccelerometerBiasSigma GyroscopeBiasSigma AverageDeltaT\n"
        "0 0 0 0 0 0 0.01 0.000175 0 0.000167 2.91e-006 0.0100395199348279\n"
    )
    return {
        "KittiEquivBiasedImu.txt": imu,
        "KittiGps_converted.txt": gps,
        "KittiEquivBiasedImu_metadata.txt": metadata,
    }, ""


def _info_upper(rng: np.random.Generator) -> list[float]:
    a = rng.normal(size=(6, 6))
    info = a @ a.T + 6.0 * np.eye(6)
    return info[np.triu_indices(6)].tolist()


def _build_graph(rng: np.random.Generator, toro: bool) -> tuple[dict[str, Any], str]:
    n = int(rng.integers(1, 8))
    lines = ["# a pose graph"]
    with_vertices = n == 1 or rng.random() < 0.8
    for i in range(n if with_vertices else 0):
        p = rng.normal(size=3).tolist()
        if toro:
            lines.append(" ".join(["VERTEX3", str(i), *map(_num, p + rng.normal(size=3).tolist())]))
        else:
            q = _quats(rng, 1)[0]
            pose = p + [q[1], q[2], q[3], q[0]]
            lines.append(" ".join(["VERTEX_SE3:QUAT", str(i), *map(_num, pose)]))
    edges = [(i, i + 1) for i in range(n - 1)] + [(0, n - 1)] * (n > 2)
    for i, j in edges:
        p = rng.normal(size=3).tolist()
        if toro:
            pose = p + rng.normal(size=3).tolist()
            tag = "EDGE3"
        else:
            q = _quats(rng, 1)[0]
            pose = p + [q[1], q[2], q[3], q[0]]
            tag = "EDGE_SE3:QUAT"
        lines.append(" ".join([tag, str(i), str(j), *map(_num, pose + _info_upper(rng))]))
    if rng.random() < 0.3:
        lines.append("FIX 0")
    name = "graph.graph" if toro else "graph.g2o"
    return {name: "\n".join(lines) + "\n"}, name


def _build_graph_2d(rng: np.random.Generator, toro: bool) -> tuple[dict[str, Any], str]:
    """A planar pose graph like the gtsam wheel's: g2o (``noisyToyGraph.txt``: VERTEX_SE2,
    EDGE_SE2 with the information in g2o order, LANDMARK2 lines as in
    ``victoriaPark_reduced_1k.g2o``) or TORO (``w100.graph``: VERTEX2, EDGE2 in TORO order,
    EQUIV lines); one in five has no vertices (``cityTrees_reduced_1k.g2o``)."""
    n = int(rng.integers(1, 8))
    vertex_tag, edge_tag = ("VERTEX2", "EDGE2") if toro else ("VERTEX_SE2", "EDGE_SE2")
    lines = ["# a 2-D pose graph"]
    with_vertices = n == 1 or rng.random() < 0.8
    for i in range(n if with_vertices else 0):
        pose = [*rng.normal(size=2), rng.uniform(-math.pi, math.pi)]
        lines.append(" ".join([vertex_tag, str(i), *map(_num, pose)]))
    edges = [(i, i + 1) for i in range(n - 1)] + [(0, n - 1)] * (n > 2)
    cells = ([0, 0, 1, 2, 0, 1], [0, 1, 1, 2, 2, 2]) if toro else np.triu_indices(3)
    for i, j in edges:
        pose = [*rng.normal(size=2), rng.uniform(-math.pi, math.pi)]
        a = rng.normal(size=(3, 3))
        info = (a @ a.T + 3.0 * np.eye(3))[cells].tolist()
        lines.append(" ".join([edge_tag, str(i), str(j), *map(_num, pose + info)]))
    if n > 1 and rng.random() < 0.3:
        extra = "EQUIV 1 0" if toro else "LANDMARK2 0 1 1.5 -0.5 1.581139 0 1.581139"
        lines.insert(int(rng.integers(1, len(lines) + 1)), extra)
    if rng.random() < 0.3:
        lines.append("FIX 0")
    name = "graph.graph" if toro else "graph.g2o"
    return {name: "\n".join(lines) + "\n"}, name


def _build_landmark_2d(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """A planar graph with landmarks like the gtsam wheel's ``victoria_park.txt`` (ODOMETRY
    with covariances, LANDMARK sightings as x, y and variances, no vertices) or
    ``example.graph`` (vertices, BR sightings); VERTEX_XY lines place some landmarks."""
    n = int(rng.integers(2, 8))
    lines = ["# a 2-D graph with landmarks"]
    if rng.random() < 0.5:
        for i in range(n):
            pose = [*rng.normal(size=2), rng.uniform(-math.pi, math.pi)]
            lines.append(" ".join(["VERTEX_SE2", str(i), *map(_num, pose)]))
    for i in range(n - 1):
        pose = [*rng.normal(size=2), rng.uniform(-math.pi, math.pi)]
        a = rng.normal(size=(3, 3)) * 0.1
        cov = (a @ a.T + 0.01 * np.eye(3))[np.triu_indices(3)].tolist()
        lines.append(" ".join(["ODOMETRY", str(i), str(i + 1), *map(_num, pose + cov)]))
    landmarks = int(rng.integers(1, 4))
    for _ in range(int(rng.integers(1, 7))):
        i, lid = str(int(rng.integers(0, n))), str(int(rng.integers(0, landmarks)))
        if rng.random() < 0.5:
            var = float(rng.uniform(0.01, 1.0))
            var_yy = var if rng.random() < 0.8 else var * 2  # unequal: sigmas 1, with a warning
            values = [*rng.normal(size=2) * 5, var, 0.0, var_yy]
            lines.append(" ".join(["LANDMARK", i, lid, *map(_num, values)]))
        else:
            values = [rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 10), 0.05, 0.1]
            lines.append(" ".join(["BR", i, lid, *map(_num, values)]))
    for lid in range(landmarks):
        if rng.random() < 0.3:
            lines.append(" ".join(["VERTEX_XY", str(lid), *map(_num, rng.normal(size=2) * 5)]))
    return {"graph.txt": "\n".join(lines) + "\n"}, "graph.txt"


_EQVIO_HEADER = (
    "row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,"
    "bgx,bgy,bgz,bax,bay,baz,u_norm,v_norm,key,value"
).split(",")


def _build_eqvio(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    width = len(_EQVIO_HEADER)

    def row(**cells: str) -> list[str]:
        out = [""] * width
        for key, value in cells.items():
            out[_EQVIO_HEADER.index(key)] = value
        return out

    rows = [row(row_type="meta", key="format_version", value="1")]
    extr = {"T_ci_tx": -0.02, "T_ci_ty": -0.06, "T_ci_tz": 0.01}
    q = _quats(rng, 1)[0]
    extr |= {"T_ci_qw": q[0], "T_ci_qx": q[1], "T_ci_qy": q[2], "T_ci_qz": q[3]}
    extr |= {"camera_fx": 458.6, "camera_fy": 457.3, "camera_cx": 367.2, "camera_cy": 248.4}
    extr |= {"eqf.measurement_noise_variance_norm": 1.7756e-5, "eqf.input_var_gyr": 5.9e-8}
    for key, value in extr.items():
        rows.append(row(row_type="meta", key=key, value=_num(value)))
    t0 = 1403715273.2621431
    n_imu, n_frames = int(rng.integers(1, 15)), int(rng.integers(0, 4))
    t_imu = t0 + 0.005 * np.arange(n_imu)
    t_frame = t0 + 0.05 * np.arange(n_frames)
    events = [(t, 1, k) for k, t in enumerate(t_imu)] + [(t, 0, f) for f, t in enumerate(t_frame)]
    seq = 0
    for t, kind, k in sorted(events):
        if kind == 1:
            vals = rng.normal(size=6).tolist()
            rows.append(
                row(
                    row_type="imu",
                    t_abs=_num(t),
                    t_rel=_num(t - t0),
                    seq=str(seq),
                    **dict(zip(("gx", "gy", "gz", "ax", "ay", "az"), map(_num, vals), strict=True)),
                    **dict.fromkeys(("bgx", "bgy", "bgz", "bax", "bay", "baz"), "0"),
                )
            )
        else:
            for landmark in rng.choice(40, size=int(rng.integers(1, 5)), replace=False):
                uv = rng.normal(size=2).tolist()
                rows.append(
                    row(
                        row_type="vision_feature",
                        t_abs=_num(t),
                        t_rel=_num(t - t0),
                        seq=str(seq),
                        frame_idx=str(k),
                        landmark_id=str(int(landmark) + 1),
                        u_norm=_num(uv[0]),
                        v_norm=_num(uv[1]),
                    )
                )
        seq += 1
    return {"eqvio.csv": _csv(_EQVIO_HEADER, rows)}, "eqvio.csv"


def _build_range_csv(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """An odometry + anchor-range run (``read_range_run``'s CSV files: odometry and ranges,
    anchors in four cases of five, truth in half): columns in a drawn order, ranges partly
    out of time order and partly outside the odometry's span, anchors listed in any order,
    some never ranged."""
    n = int(rng.integers(2, 20))
    t = _times(rng, n, t0=0.0, step=0.1)
    odo = np.column_stack((t, np.cumsum(rng.normal(size=(n, 2)), 0), rng.uniform(-3, 3, n)))
    columns = ["t", "x", "y", "heading"]
    order = rng.permutation(4)
    files = {"odometry.csv": _csv([columns[k] for k in order], odo[:, order])}
    ids = rng.choice(50, size=int(rng.integers(1, 6)), replace=False)
    anchors = [[str(int(i)), *map(_num, rng.normal(size=2) * 10)] for i in ids]
    if rng.random() < 0.8:  # else positions unknown: no anchors file
        files["anchors.csv"] = _csv(["anchor", "x", "y"], anchors)
    k = int(rng.integers(0, 25))
    range_t = np.sort(rng.uniform(t[0] - 0.05, t[-1] + 0.05, k))
    range_t[rng.random(k) < 0.2] = t[rng.integers(0, n)]  # some at a pose time, out of order
    ranges = [[_num(s), str(int(rng.choice(ids))), _num(rng.uniform(0.0, 30.0))] for s in range_t]
    files["ranges.csv"] = _csv(["t", "anchor", "range"], ranges)
    if rng.random() < 0.5:
        m = int(rng.integers(2, 12))
        ref_t = np.linspace(t[0] - 0.05, t[-1] + 0.05, m)
        files["truth.csv"] = _csv(
            ["t", "x", "y"], np.column_stack((ref_t, rng.normal(size=(m, 2)) * 10))
        )
    return files, ""


def _build_encoders(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """Running 16-bit encoder counts (``read_encoder_counts``), an extra column in a drawn
    place."""
    n = int(rng.integers(1, 30))
    t = _times(rng, n, t0=0.0, step=0.02)
    counts = np.cumsum(rng.integers(-50, 400, size=(n, 2)), 0) % 65536
    rows = [[_num(a), str(int(b)), str(int(c)), "3.7"] for a, (b, c) in zip(t, counts, strict=True)]
    order = rng.permutation(4)
    header = ["t", "left_ticks", "right_ticks", "battery"]
    table = _csv([header[k] for k in order], [[row[k] for k in order] for row in rows])
    return {"ticks.csv": table}, "ticks.csv"


def _read_encoders(path: Path, sort: bool) -> WheelSamples:
    """``read_encoder_counts`` (16-bit rollover) and the speeds of a 1024-count, 0.1 m wheel;
    fewer than 2 readings is the documented ValueError, passed on as a DataError."""
    log = read_encoder_counts(path, rollover=65536, sort=sort)
    if log.t.size < 2:
        raise DataError(path, "fewer than 2 readings")
    return log.wheel_speeds((1024.0, 1024.0), (0.1, 0.1))


def _check_wheel(wheel: WheelSamples) -> str | None:
    return _check_stream("wheel", wheel)


def _read_range_csv(folder: Path) -> RangeRun:
    """``read_range_run`` on a case folder; the anchors and truth files are passed when the
    case has them."""
    anchors, truth = folder / "anchors.csv", folder / "truth.csv"
    return read_range_run(
        folder / "odometry.csv",
        folder / "ranges.csv",
        anchors if anchors.exists() else None,
        truth if truth.exists() else None,
    )


_NMEA_NOISE = (
    "GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00",
    "GLGSV,1,1,02,65,35,101,41,72,12,330,",
    "GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A",
    "GPVTG,,T,,M,0.012,N,0.022,K,A",
    "GPVTG,,,,,,,,,N",
    "GNGSA,A,3,04,05,,09,12,,,24,,,,,2.5,1.3,2.1",
    "PUBX,00,081350.00,4717.113210,N,00833.915187,E,546.589,G3,2.1,2.0,0.007,77.52,0.007,,0.92,1.19,0.77,9,0,0",
)


def _nmea_line(body: str, checksum: bool) -> str:
    """``$body[*hh]`` (the XOR of the body's bytes as two upper-case hex digits)."""
    if not checksum:
        return f"${body}"
    value = 0
    for byte in body.encode("ascii"):
        value ^= byte
    return f"${body}*{value:02X}"


def _build_nmea(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """An NMEA 0183 log like a u-blox or NovAtel serial capture: GGA fixes at 1 or 5 Hz
    anywhere on the globe, GSTs for some, RMC or ZDA dates (or none), RMC speeds and courses
    (stationary, invalid, dead reckoning, before NMEA 2.3), VTGs, HDT / THS headings (empty,
    360, every THS mode), GSV/GSA/PUBX noise,
    no-fix GGAs, a second talker's GGA of the same epoch, checksums on all, none or some
    lines, receive stamps before a comma or a space (or none), a midnight rollover in one
    log of three."""
    n = int(rng.integers(1, 16))
    step = int(rng.choice((100, 20)))  # centiseconds
    day = 18000 + int(rng.integers(0, 2000))  # days since 1970
    if rng.random() < 1 / 3:
        tod0 = 8_640_000 - step * int(rng.integers(1, n + 1))  # crosses 00:00 UTC
    else:
        tod0 = 100 * int(rng.integers(0, 86400 - 4 * n)) + int(rng.choice((0, 50)))
    unix_cs = [day * 8_640_000 + tod0 + step * k for k in range(n)]
    talker = str(rng.choice(("GP", "GN", "GL")))
    date_kind = str(rng.choice(("RMC", "ZDA", "none"), p=(0.5, 0.3, 0.2)))
    checksum_kind = str(rng.choice(("all", "none", "some")))
    stamp_sep = str(rng.choice(("", ",", " ")))
    lat0, lon0 = rng.uniform(-89.0, 89.0), rng.uniform(-179.0, 179.0)
    lines: list[tuple[float, str]] = []  # (receive time, sentence body)
    for k, cs in enumerate(unix_cs):
        t = cs / 100
        clock = datetime.datetime.fromtimestamp(cs // 100, datetime.timezone.utc)
        hms = f"{clock:%H%M%S}.{cs % 100:02d}"
        lat, lon = lat0 + 1e-5 * k, lon0 + 1e-5 * k
        lat_text = f"{int(abs(lat)):02d}{abs(lat) % 1 * 60:010.7f},{'NS'[lat < 0]}"
        lon_text = f"{int(abs(lon)):03d}{abs(lon) % 1 * 60:010.7f},{'EW'[lon < 0]}"
        if rng.random() < 0.15:
            lines.append((t, f"{talker}GGA,{hms},,,,,0,00,99.99,,,,,,"))
            continue
        quality = int(rng.choice((1, 2, 4, 5, 6), p=(0.3, 0.2, 0.3, 0.15, 0.05)))
        separation = "" if rng.random() < 0.1 else f"{rng.uniform(-100, 80):.1f}"
        gga = (
            f"{talker}GGA,{hms},{lat_text},{lon_text},{quality},{int(rng.integers(4, 30)):02d},"
            f"{rng.uniform(0.5, 3):.1f},{rng.uniform(-50, 3000):.3f},M,{separation},M,,"
        )
        lines.append((t, gga))
        if rng.random() < 0.1:  # the same epoch from a second talker: a duplicate time
            lines.append((t, "GP" + gga[2:]))
        if rng.random() < 0.6:
            sigmas = ",".join(f"{s:.3f}" for s in rng.uniform(0.005, 3.0, 3))
            lines.append((t, f"{talker}GST,{hms},1.2,0.9,0.5,34.5,{sigmas}"))
        if date_kind == "RMC" and rng.random() < 0.5:
            motion = str(rng.choice(("A,0.02,31.66", "A,0.0,", "A,0.004,", "V,,", "A,12.5,359.9")))
            mode = str(rng.choice(("D", "A", "E", "N", "")))
            lines.append(
                (
                    t,
                    f"{talker}RMC,{hms},{motion[:1]},{lat_text},{lon_text},{motion[2:]},"
                    f"{clock:%d%m%y},,,{mode}",
                )
            )
        elif date_kind == "ZDA" and rng.random() < 0.5:
            lines.append((t, f"{talker}ZDA,{hms},{clock:%d,%m,%Y},00,00"))
        if rng.random() < 0.4:  # a dual-antenna heading of this epoch
            degrees = str(rng.choice((f"{rng.uniform(0, 360):.3f}", "", "360.0", "0")))
            if rng.random() < 0.5:
                lines.append((t, f"{talker}HDT,{degrees},T"))
            else:
                lines.append((t, f"{talker}THS,{degrees},{rng.choice(list('AAAEMSV'))}"))
        if rng.random() < 0.5:
            lines.append((t, str(rng.choice(_NMEA_NOISE))))
    text = []
    for i, (t, body) in enumerate(lines):
        checksum = checksum_kind == "all" or (checksum_kind == "some" and rng.random() < 0.5)
        sentence = _nmea_line(body, checksum)
        stamp = f"{t + 0.05 + 1e-3 * i:.3f}"
        text.append(sentence if not stamp_sep else f"{stamp}{stamp_sep}{sentence}")
    return {"log.nmea": "\n".join(text) + "\n"}, "log.nmea"


def _ubx_frame(cls: int, ident: int, payload: bytes) -> bytes:
    """One UBX frame: sync, class, id, length, payload, Fletcher checksum."""
    body = bytes((cls, ident)) + len(payload).to_bytes(2, "little") + payload
    a = b = 0
    for byte in body:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    return b"\xb5\x62" + body + bytes((a, b))


def _build_ubx(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """A u-blox UBX log: NAV-PVT frames at 1-10 Hz anywhere on the globe (fix types 0-5,
    valid flags mostly set, RTK carrier states, 92- or 84-byte payloads), NAV-STATUS and
    RXM-RAWX-like frames between, NMEA text now and then, a leap-second :60 in some;
    NAV-RELPOSNED after most (version 1 with random flags, version 0, an iTOW of no
    NAV-PVT)."""
    n = int(rng.integers(1, 12))
    start = 1_500_000_000 + int(rng.integers(0, 300_000_000))
    step_ns = int(rng.choice((100_000_000, 200_000_000, 1_000_000_000)))
    chunks = []
    for k in range(n):
        stamp_ns = start * 1_000_000_000 + k * step_ns
        whole, nano = divmod(stamp_ns, 1_000_000_000)
        if nano > 500_000_000:  # the receiver rounds to the nearest second, nano negative
            whole, nano = whole + 1, nano - 1_000_000_000
        year, month, day, hour, minute, second = datetime.datetime.fromtimestamp(
            whole, datetime.timezone.utc
        ).timetuple()[:6]
        fix = int(rng.choice((3, 3, 3, 4, 2, 0, 1, 5)))
        flags = (1 if rng.random() < 0.9 else 0) | (int(rng.integers(0, 3)) << 6)
        valid = 0x07 if rng.random() < 0.9 else int(rng.integers(0, 8))
        lat = int(rng.integers(-900_000_000, 900_000_001))
        lon = int(rng.integers(-1_800_000_000, 1_800_000_000))
        fields = (
            int(rng.integers(0, 604_800_000)), year, month, day, hour, minute, second, valid,
            int(rng.integers(0, 1000)), nano, fix, flags, 0, int(rng.integers(0, 40)), lon, lat,
            int(rng.integers(-400_000, 9_000_000)), 0, int(rng.integers(5, 50_000)),
            int(rng.integers(5, 80_000)), *[int(v) for v in rng.integers(-40_000, 40_000, 3)],
            int(rng.integers(0, 40_000)), int(rng.integers(0, 36_000_000)),
            int(rng.integers(5, 5_000)), int(rng.integers(0, 18_000_000)), 150,
        )  # fmt: skip
        payload = struct.pack("<IHBBBBBBIiBBBBiiiiIIiiiiiIIH", *fields)
        payload += bytes(6) if rng.random() < 0.2 else bytes(14)
        chunks.append(_ubx_frame(0x01, 0x07, payload))
        if rng.random() < 0.7:
            itow = fields[0] if rng.random() < 0.9 else int(rng.integers(0, 604_800_000))
            flags = int(rng.choice((0x127, 0x12F, 0x13F, 0x107, 0x027, 0))) | (
                int(rng.integers(0, 3)) << 3
            )
            relposned = struct.pack(
                "<BBHIiiiii4xbbbbIIIII4xI",
                1, 0, 0, itow, *[int(v) for v in rng.integers(-300, 300, 4)],
                int(rng.integers(-18_000_000, 36_000_000)), 0, 0, 0, 0,
                *[int(v) for v in rng.integers(0, 500, 4)],
                int(rng.choice((0, int(rng.integers(1, 2_000_000))))), flags,
            )  # fmt: skip
            if rng.random() < 0.15:  # the M8P layout: no heading
                relposned = bytes((0, 0, 0, 0)) + relposned[4:20] + bytes(20)
            chunks.append(_ubx_frame(0x01, 0x3C, relposned))
        if rng.random() < 0.3:
            chunks.append(_ubx_frame(0x01, 0x03, bytes(int(v) for v in rng.integers(0, 256, 16))))
        if rng.random() < 0.2:
            chunks.append(b"$GNGGA,,,,,,0,00,99.99,,,,,,*56\r\n")
    return {"log.ubx": b"".join(chunks)}, "log.ubx"


def _read_ubx(path: Path) -> UbxLog:
    """``read_ubx`` on a case file; a warning that is not a UserWarning is a crash."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = read_ubx(path)
    for w in caught:
        if not issubclass(w.category, UserWarning):
            raise AssertionError(f"{w.category.__name__}: {w.message}")
    return log


def _check_ubx(log: UbxLog) -> str | None:
    n = len(log)
    columns = ("latitude_deg", "longitude_deg", "height_m", "fix_type", "satellites", "carrier")
    if any(getattr(log, c).shape != (n,) for c in (*columns, "offsets")):
        return "a column is not (N,)"
    if any(getattr(log, c).shape != (n, 3) for c in ("sigma_enu", "velocity_enu")):
        return "sigma_enu or velocity_enu not (N, 3)"
    if not (np.isfinite(log.t).all() and (np.diff(log.t) > 0).all()):
        return "t not finite and strictly increasing"
    if not (np.abs(log.latitude_deg) <= 90).all() or not (np.abs(log.longitude_deg) <= 180).all():
        return "a latitude outside [-90, 90] or a longitude outside [-180, 180]"
    arrays = (log.height_m, log.sigma_enu, log.velocity_enu, log.velocity_sigma)
    if not all(np.isfinite(a).all() for a in arrays):
        return "a height, sigma or velocity that is not finite"
    if (log.sigma_enu < 0).any() or (log.velocity_sigma < 0).any():
        return "a negative sigma"
    if any(v < 0 for v in log.counts.values()) or log.counts["kept"] != n:
        return "a negative count or counts['kept'] != N"
    problem = _check_headings(log.counts, log.heading_t, log.heading_rad, log.heading_offsets)
    if problem:
        return problem
    sigma = log.heading_sigma_rad[~np.isnan(log.heading_sigma_rad)]
    if log.heading_sigma_rad.shape != log.heading_t.shape or not (sigma > 0).all():
        return "heading_sigma_rad not (H,) positive or NaN"
    if not np.isfinite(sigma).all():
        return "an infinite heading sigma"
    if n:
        gnss, _ = log.to_gnss()
        if not _finite(gnss.position) or gnss.t.shape != (1, n):
            return "to_gnss gave a non-finite ENU position"
    return None


def _read_nmea(path: Path) -> NmeaLog:
    """``read_nmea`` on a case file; a warning that is not a UserWarning is a crash, and so
    is a DataError that names a field but no line."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            log = read_nmea(path)
        except DataError as err:
            if err.field is not None and err.line is None:
                raise AssertionError(f"DataError names field {err.field!r} but no line") from err
            raise
    for w in caught:
        if not issubclass(w.category, UserWarning):
            raise AssertionError(f"{w.category.__name__}: {w.message}")
    return log


# ----------------------------------------------------------------------------- result checks


def _read_kitti_raw(folder: Path, sort: bool) -> Sequence:
    """``read_kitti_raw`` with its warnings (a synced-rate drive, extra data files) kept
    quiet: they are not failures."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_kitti_raw(folder, sort=sort)


def _finite(x: torch.Tensor, allow_nan: bool = False) -> bool:
    x = x.detach()
    return bool((~torch.isinf(x)).all()) if allow_nan else bool(torch.isfinite(x).all())


def _increasing(t: torch.Tensor) -> bool:
    return bool((t[1:] > t[:-1]).all())


def _unit(q: torch.Tensor) -> bool:
    return bool(((q.norm(dim=-1) - 1.0).abs() < 1e-9).all())


def _orthonormal(rot: torch.Tensor) -> bool:
    if rot.numel() == 0:
        return True
    eye = torch.eye(3, dtype=rot.dtype)
    close = ((rot.mT @ rot - eye).abs().amax((-2, -1)) < 1e-6).all()
    return bool(close and (torch.linalg.det(rot) > 0).all())


def _check_stream(name: str, stream: Any) -> str | None:
    mask = stream.mask[0]
    t = stream.t[0, mask]
    if not _finite(t) or not _increasing(t):
        return f"{name}.t not finite and strictly increasing"
    for key, value in stream.tensors().items():
        if key in ("mask", "t"):
            continue
        nan_ok = key in ("sigma", "covariance")
        values = value[0, mask]
        if name == "gnss_velocity" and key == "velocity":  # the up axis may be not given
            if not (_finite(values[:, :2]) and _finite(values[:, 2:], allow_nan=True)):
                return f"{name}.{key} holds a non-finite east / north or an inf up value"
        elif not _finite(values, allow_nan=nan_ok):
            return f"{name}.{key} holds a non-finite value"
        if key == "quaternion" and not _unit(value[0, mask]):
            return f"{name}.quaternion not unit"
    return None


def _check_sequence(seq: Sequence) -> str | None:
    seq.check()
    if seq.batch_size != 1:
        return f"B = {seq.batch_size}"
    if int(seq.imu.mask.sum()) == 0:
        return "no IMU samples"
    named = {f"pose_sources[{k}]": v for k, v in seq.pose_sources.items()}
    for name, stream in {**seq.streams(), **named}.items():
        problem = _check_stream(name, stream)
        if problem:
            return problem
    for name, spans in seq.labels.items():
        if not _finite(spans) or bool((spans[..., 1] < spans[..., 0]).any()):
            return f"label {name!r} interval not finite or reversed"
    return None


def _check_trajectory(traj: Trajectory) -> str | None:
    return _check_stream("trajectory", traj)


def _check_scans(scans: dict[str, torch.Tensor]) -> str | None:
    t, angles, ranges = scans["t"], scans["angles"], scans["ranges"]
    if not (_finite(t) and _increasing(t)):
        return "t not finite and strictly increasing"
    if not (_finite(angles) and _increasing(angles)):
        return "angles not finite and strictly increasing"
    if ranges.shape != (t.numel(), angles.numel()):
        return "ranges not (N, K)"
    if bool((ranges.isinf() | (ranges < 0)).any()):
        return "ranges hold inf or a negative value"
    for key in ("odometry", "truth"):
        if key in scans and not _finite(scans[key]):
            return f"{key} holds a non-finite value"
    return None


def _check_graph(graph: PoseGraph) -> str | None:
    graph.check()
    for name in ("rotations", "positions", "edge_rotations", "edge_translations"):
        if not _finite(getattr(graph, name)):
            return f"{name} holds a non-finite value"
    if not (_orthonormal(graph.rotations) and _orthonormal(graph.edge_rotations)):
        return "a rotation is not orthonormal"
    info = graph.edge_information
    if info.numel() and (
        not _finite(info) or bool(torch.linalg.cholesky_ex(info).info.ne(0).any())
    ):
        return "an information matrix is not finite positive definite"
    return None


def _check_graph_2d(graph: PoseGraph2D) -> str | None:
    graph.check()
    for name in ("positions", "headings", "edge_translations", "edge_headings"):
        if not _finite(getattr(graph, name)):
            return f"{name} holds a non-finite value"
    info = graph.edge_information
    if info.numel() and (
        not _finite(info)
        or not torch.equal(info, info.mT)
        or bool(torch.linalg.cholesky_ex(info).info.ne(0).any())
    ):
        return "an information matrix is not finite symmetric positive definite"
    if not _finite(graph.landmark_positions):
        return "landmark_positions holds a non-finite value"
    bearings, ranges = graph.observation_bearings, graph.observation_ranges
    if not (_finite(bearings) and bool((bearings.abs() <= math.pi).all())):
        return "a sighting's bearing is not finite in [-pi, pi]"
    if not (_finite(ranges) and bool((ranges > 0).all())):
        return "a sighting's range is not finite and positive"
    sigmas = graph.observation_sigmas
    if not (_finite(sigmas) and bool((sigmas > 0).all()) and _finite(sigmas**-2)):
        return "a sighting's sigma is not finite and positive with finite information"
    return None


def _check_eqvio(run: EqvioRun) -> str | None:
    problem = _check_stream("imu", run.imu)
    if problem:
        return problem
    if not (_finite(run.frame_times) and _increasing(run.frame_times)):
        return "frame_times not finite and strictly increasing"
    if not _finite(run.obs_normalized):
        return "obs_normalized holds a non-finite value"
    if run.R_imu_cam is not None and not (
        _finite(run.R_imu_cam) and _orthonormal(run.R_imu_cam[None])
    ):
        return "R_imu_cam not a finite rotation"
    for name in ("t_imu_cam", "intrinsics"):
        value = getattr(run, name)
        if value is not None and not _finite(value):
            return f"{name} holds a non-finite value"
    if not all(math.isfinite(v) for v in run.imu_noise.values()):
        return "imu_noise holds a non-finite value"
    return None


def _check_range_run(run: RangeRun) -> str | None:
    m, k = run.odometry.shape[0], run.ranges.shape[0]
    if run.pose_t.shape != (m + 1,) or not (_finite(run.pose_t) and _increasing(run.pose_t)):
        return "pose_t not (M + 1,) finite and strictly increasing"
    for name in ("odometry", "ranges"):
        if not _finite(getattr(run, name)):
            return f"{name} holds a non-finite value"
    if run.meta["files"]["anchors"] is None:  # no anchors file: positions unknown (NaN)
        if not bool(run.anchors.isnan().all()):
            return "anchors without a file hold a position"
    elif not _finite(run.anchors):
        return "anchors holds a non-finite value"
    if run.range_t.shape != (k,) or run.range_anchor.shape != (k,):
        return "range_t or range_anchor not (K,)"
    range_t = run.range_t
    if not _finite(range_t) or bool((range_t[1:] < range_t[:-1]).any()):
        return "range_t not finite and non-decreasing"
    if k and (range_t[0] < run.pose_t[0] or range_t[-1] > run.pose_t[-1]):
        return "a range outside the odometry's span"
    if bool((run.ranges < 0).any()):
        return "a negative range"
    ids = run.anchor_ids
    if not _increasing(ids) or run.anchors.shape != (ids.shape[0], 2):
        return "anchor_ids not strictly increasing or anchors not (L, 2)"
    if k and not bool(torch.isin(run.range_anchor, ids).all()):
        return "a range to an unlisted anchor"
    if run.truth is not None and not (run.truth.shape == (m + 1, 3) and _finite(run.truth[:, :2])):
        return "truth not (M + 1, 3) with finite x, y"
    return None


def _check_headings(
    counts: dict[str, int], t: np.ndarray, heading: np.ndarray, where: np.ndarray
) -> str | None:
    """The NMEA / UBX promises on headings: H = counts["heading_kept"] of each, times finite
    and increasing, angles in [0, 2 pi), and the stream they give."""
    h = counts["heading_kept"]
    if t.shape != (h,) or heading.shape != (h,) or where.shape != (h,):
        return "heading_t, heading_rad or their lines / offsets not (H,) = counts['heading_kept']"
    if not (np.isfinite(t).all() and (np.diff(t) > 0).all()):
        return "heading_t not finite and strictly increasing"
    if not ((heading >= 0) & (heading < 2 * np.pi)).all():
        return "a heading outside [0, 2 pi)"
    return None


def _check_nmea(log: NmeaLog) -> str | None:
    n = len(log)
    columns = ("t", "latitude_deg", "longitude_deg", "altitude_m", "quality", "satellites")
    if any(getattr(log, c).shape != (n,) for c in (*columns, "hdop", "lines")):
        return "a column is not (N,)"
    if log.sigma_enu.shape != (n, 3):
        return "sigma_enu not (N, 3)"
    if not (np.isfinite(log.t).all() and (np.diff(log.t) > 0).all()):
        return "t not finite and strictly increasing"
    if not (np.abs(log.latitude_deg) <= 90).all() or not (np.abs(log.longitude_deg) <= 180).all():
        return "a latitude outside [-90, 90] or a longitude outside [-180, 180]"
    if not np.isfinite(log.altitude_m).all():
        return "altitude_m holds a non-finite value"
    if not np.isin(log.quality, DEFAULT_QUALITIES).all():
        return "a quality code that is not kept"
    if not (log.satellites >= -1).all():
        return "satellites below -1"
    hdop, sigma = log.hdop[~np.isnan(log.hdop)], log.sigma_enu[~np.isnan(log.sigma_enu)]
    if not (np.isfinite(hdop).all() and (hdop >= 0).all()):
        return "hdop not finite non-negative or NaN"
    if not (np.isfinite(sigma).all() and (sigma > 0).all()):  # a GST 0 reads as NaN
        return "sigma_enu not finite positive or NaN"
    if not (log.lines >= 1).all() or not (np.diff(log.lines) > 0).all():
        return "lines not positive and increasing"
    if any(v < 0 for v in log.counts.values()) or log.counts["kept"] != n:
        return "a negative count or counts['kept'] != N"
    m = log.counts["velocity_kept"]
    if log.velocity_t.shape != (m,) or log.velocity_lines.shape != (m,):
        return "velocity_t or velocity_lines not (M,) with M = counts['velocity_kept']"
    if log.velocity_enu.shape != (m, 3) or not np.isnan(log.velocity_enu[:, 2]).all():
        return "velocity_enu not (M, 3) with the up component NaN"
    if not np.isfinite(log.velocity_enu[:, :2]).all():
        return "a velocity east / north that is not finite"
    if not (np.isfinite(log.velocity_t).all() and (np.diff(log.velocity_t) > 0).all()):
        return "velocity_t not finite and strictly increasing"
    problem = _check_headings(log.counts, log.heading_t, log.heading_rad, log.heading_lines)
    if problem:
        return problem
    if n:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            gnss, _ = log.to_gnss()
        if caught:
            return f"to_gnss warned: {caught[0].message}"
        if not _finite(gnss.position) or gnss.t.shape != (1, n):
            return "to_gnss gave a non-finite ENU position"
    return None


READERS: dict[str, Reader] = {
    r.name: r
    for r in (
        Reader(
            "native_npz", _build_npz, lambda p, s: read_native(p, sort=s), _check_sequence, True
        ),
        Reader(
            "native_csv", _build_native_csv, lambda p, s: read_native(p, sort=s), _check_sequence
        ),
        Reader("tum", _build_tum, lambda p, s: read_tum(p, sort=s), _check_trajectory),
        Reader("euroc", _build_euroc, lambda p, s: read_euroc(p, sort=s), _check_sequence),
        Reader(
            "kitti_gtsam",
            _build_kitti,
            lambda p, s: load_kitti_gtsam(sort=s, data_dir=p),
            _check_sequence,
        ),
        Reader(
            "g2o",
            lambda rng: _build_graph(rng, toro=False),
            lambda p, s: read_pose_graph(p),
            _check_graph,
        ),
        Reader(
            "toro",
            lambda rng: _build_graph(rng, toro=True),
            lambda p, s: read_pose_graph(p),
            _check_graph,
        ),
        Reader(
            "g2o_2d",
            lambda rng: _build_graph_2d(rng, toro=False),
            lambda p, s: read_pose_graph_2d(p),
            _check_graph_2d,
        ),
        Reader(
            "toro_2d",
            lambda rng: _build_graph_2d(rng, toro=True),
            lambda p, s: read_pose_graph_2d(p),
            _check_graph_2d,
        ),
        Reader(
            "landmark_2d", _build_landmark_2d, lambda p, s: read_pose_graph_2d(p), _check_graph_2d
        ),
        Reader("eqvio", _build_eqvio, lambda p, s: load_eqvio(p), _check_eqvio),
        Reader(
            "kitti_poses",
            _build_kitti_poses,
            lambda p, s: read_kitti_poses(p / "poses.txt", p / "times.txt"),
            _check_trajectory,
        ),
        Reader("scans", _build_scans, lambda p, s: read_scans(p), _check_scans, True),
        Reader("range_csv", _build_range_csv, lambda p, s: _read_range_csv(p), _check_range_run),
        Reader("nmea", _build_nmea, lambda p, s: _read_nmea(p), _check_nmea),
        Reader("kitti_raw", _build_kitti_raw, lambda p, s: _read_kitti_raw(p, s), _check_sequence),
        Reader("encoders", _build_encoders, _read_encoders, _check_wheel),
        Reader("ubx", _build_ubx, lambda p, s: _read_ubx(p), _check_ubx),
    )
}
"""Reader name -> :class:`Reader`: native ``.npz`` and CSV folder, TUM, EuRoC ASL, the KITTI
files gtsam ships (``data_dir``), g2o and TORO pose graphs (3-D and 2-D), 2-D graphs with
landmarks (``landmark_2d``: ODOMETRY, LANDMARK, BR, VERTEX_XY), the EqVIO replay CSV, KITTI
odometry poses + times, 2D LiDAR scans (``.npz``), odometry + anchor-range CSV files
(``range_csv``), NMEA 0183 GNSS logs (``nmea``), KITTI raw OXTS drives (``kitti_raw``),
encoder counts (``encoders``), u-blox UBX logs (``ubx``, mutated byte by byte). Not
here: rosbags (binary containers written by ``rosbags``; their reader is tested on bags
written by its own writers)."""


# ----------------------------------------------------------------------------- mutations

_TEXT_MUTATIONS = (
    "truncate_line",
    "truncate_file",
    "drop_field",
    "extra_field",
    "replace_token",
    "replace_token",
    "replace_token",
    "swap_lines",
    "duplicate_line",
    "delete_line",
    "binary_line",
    "flip_bytes",
    "empty_file",
    "junk_file",
    "blank_comment",
    "swap_delimiter",
    "non_utf8",
    "nul_byte",
    "long_cell",
    "cr_line_ends",
)
_FOLDER_MUTATIONS = ("remove_file", "file_to_folder", "stray_file")
_ARRAY_MUTATIONS = (
    "drop_key",
    "unknown_key",
    "retype",
    "reshape",
    "poison_value",
    "poison_value",
    "reverse_time",
    "zero_quaternion",
    "bad_label",
    "bad_meta_json",
)
_BYTE_MUTATIONS = ("truncate_bytes", "flip_bytes", "junk_file", "empty_file")


def _split(line: str, sep: str | None) -> list[str]:
    return line.split() if sep is None else line.split(sep)


def _join(tokens: list[str], sep: str | None) -> str:
    return (" " if sep is None else sep).join(tokens)


def _separator(path: str, text: str) -> str | None:
    """Field separator of a generated text file (None: runs of whitespace)."""
    if path.endswith((".tum", ".g2o", ".graph")) or "Imu" in path:
        return None
    return "," if path.endswith(".csv") or "," in text else None


@st.composite
def _junk_token(draw) -> str:
    if draw(st.booleans()):
        return draw(st.sampled_from(JUNK_TOKENS))
    return draw(st.text(max_size=12))


@st.composite
def _mutate_text(draw, path: str, data: bytes) -> tuple[bytes, str]:
    """One mutation of a text file; returns the new bytes and the mutation's name."""
    kind = draw(st.sampled_from(_TEXT_MUTATIONS))
    text = data.decode("utf-8", errors="surrogateescape")
    sep = _separator(path, text)
    lines = text.split("\n")
    k = draw(st.integers(0, max(0, len(lines) - 1)))
    line = lines[k] if lines else ""
    if kind == "truncate_line":
        lines[k] = line[: draw(st.integers(0, max(0, len(line) - 1)))]
    elif kind == "truncate_file":
        return data[: draw(st.integers(0, max(0, len(data) - 1)))], kind
    elif kind in ("drop_field", "extra_field", "replace_token", "long_cell"):
        tokens = _split(line, sep)
        i = draw(st.integers(0, len(tokens)))
        if kind == "drop_field" and tokens:
            del tokens[min(i, len(tokens) - 1)]
        elif kind == "extra_field":
            tokens.insert(i, draw(_junk_token()))
        elif kind == "replace_token" and tokens:
            tokens[min(i, len(tokens) - 1)] = draw(_junk_token())
        elif kind == "long_cell" and tokens:
            tokens[min(i, len(tokens) - 1)] = "1" * draw(st.sampled_from((1000, 200_000)))
        lines[k] = _join(tokens, sep)
    elif kind == "swap_lines":
        j = draw(st.integers(0, max(0, len(lines) - 1)))
        lines[k], lines[j] = lines[j], lines[k]
    elif kind == "duplicate_line":
        lines.insert(k, line)
    elif kind == "delete_line" and lines:
        del lines[k]
    elif kind == "binary_line":
        junk = draw(st.binary(min_size=1, max_size=40))
        lines.insert(k, junk.decode("utf-8", errors="surrogateescape"))
    elif kind == "flip_bytes":
        raw = bytearray(data)
        for _ in range(draw(st.integers(1, 4))):
            if raw:
                raw[draw(st.integers(0, len(raw) - 1))] = draw(st.integers(0, 255))
        return bytes(raw), kind
    elif kind == "empty_file":
        return draw(st.sampled_from((b"", b"\n", b"   \n\n", b"# only a comment\n"))), kind
    elif kind == "junk_file":
        return draw(st.sampled_from(_FILE_JUNK)) + draw(st.binary(max_size=200)), kind
    elif kind == "blank_comment":
        lines.insert(k, draw(st.sampled_from(("", "   ", "# comment", "#", "\t"))))
    elif kind == "swap_delimiter":
        lines[k] = _join(_split(line, sep), draw(st.sampled_from((";", "\t", ", ", "  ", "|"))))
    elif kind == "non_utf8":
        pos = draw(st.integers(0, len(line)))
        lines[k] = line[:pos] + "\udcff" + line[pos:]
    elif kind == "nul_byte":
        pos = draw(st.integers(0, len(line)))
        lines[k] = line[:pos] + "\x00" + line[pos:]
    elif kind == "cr_line_ends":
        return "\n".join(lines).replace("\n", draw(st.sampled_from(("\r\n", "\r")))).encode(
            "utf-8", errors="surrogateescape"
        ), kind
    return "\n".join(lines).encode("utf-8", errors="surrogateescape"), kind


@st.composite
def _mutate_arrays(draw, arrays: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], str]:
    """One mutation of an npz's arrays."""
    kind = draw(st.sampled_from(_ARRAY_MUTATIONS))
    out = dict(arrays)
    keys = sorted(out)
    key = draw(st.sampled_from(keys)) if keys else "imu/t"
    value = out.get(key, np.zeros(3))
    if kind == "drop_key":
        out.pop(key, None)
    elif kind == "unknown_key":
        name = draw(st.sampled_from(("imu/temperature", "odometry/t", "poses/vo/extra", "x", "")))
        out[name] = np.zeros(3)
    elif kind == "retype":
        target = draw(st.sampled_from(("str", "object", "complex", "bool", "int", "float16")))
        numeric = value.dtype.kind in "fiub"
        if target == "str":
            out[key] = value.astype(str)
        elif target == "object":
            out[key] = np.array([None, "a", 1.0], dtype=object)
        elif target == "complex" and numeric:
            out[key] = value.astype(complex)
        elif target == "bool" and numeric:
            out[key] = value.astype(bool)
        elif target == "int" and numeric:
            out[key] = np.nan_to_num(value).astype(np.int64)
        elif target == "float16" and numeric:
            out[key] = value.astype(np.float16)
    elif kind == "reshape":
        how = draw(st.sampled_from(("scalar", "flat", "extra_dim", "transpose", "short")))
        if how == "scalar":
            out[key] = np.array(1.0)
        elif how == "flat":
            out[key] = np.ravel(value)
        elif how == "extra_dim":
            out[key] = value[..., None]
        elif how == "transpose":
            out[key] = np.transpose(value)
        else:
            out[key] = value[:-1] if value.ndim else value
    elif kind == "poison_value" and value.dtype.kind == "f" and value.size:
        value = value.copy()
        flat = value.reshape(-1)
        flat[draw(st.integers(0, flat.size - 1))] = draw(
            st.sampled_from((np.nan, np.inf, -np.inf, 1e308, -1e308, 5e-324, 0.0, -1.0))
        )
        out[key] = value
    elif kind == "reverse_time":
        times = [k for k in keys if k.endswith("/t") and out[k].size > 1]
        if times:
            name = draw(st.sampled_from(times))
            out[name] = out[name][::-1].copy()
    elif kind == "zero_quaternion":
        quats = [k for k in keys if k.endswith("quaternion") and out[k].size]
        if quats:
            name = draw(st.sampled_from(quats))
            q = out[name].copy()
            q[draw(st.integers(0, q.shape[0] - 1))] = 0.0
            out[name] = q
    elif kind == "bad_label":
        out["labels/" + draw(st.sampled_from(("slip", "x", "")))] = draw(
            st.sampled_from(
                (
                    np.array([[1.0, 0.0]]),
                    np.array([[np.nan, 1.0]]),
                    np.zeros((2, 3)),
                    np.zeros(2),
                    np.array(["a", "b"]),
                )
            )
        )
    elif kind == "bad_meta_json":
        out["meta_json"] = draw(
            st.sampled_from(
                (
                    np.array("{not json"),
                    np.array("[1, 2]"),
                    np.array("[" * 100_000 + "]" * 100_000),
                    np.array(["{}", "{}"]),
                    np.array(b"{}"),
                    np.array(7),
                    np.array('{"a": NaN}'),
                    np.array("\udcff"),
                )
            )
        )
    return out, kind


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for key, value in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=True)
            archive.writestr(key + ".npy", member.getvalue())
    return buffer.getvalue()


@st.composite
def _mutate_bytes(draw, data: bytes) -> tuple[bytes, str]:
    kind = draw(st.sampled_from(_BYTE_MUTATIONS))
    if kind == "truncate_bytes":
        return data[: draw(st.integers(0, max(0, len(data) - 1)))], kind
    if kind == "flip_bytes":
        raw = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            if raw:
                raw[draw(st.integers(0, len(raw) - 1))] = draw(st.integers(0, 255))
        return bytes(raw), kind
    if kind == "junk_file":
        return draw(st.sampled_from(_FILE_JUNK)) + draw(st.binary(max_size=300)), kind
    return b"", kind


@st.composite
def case_strategy(draw, reader: str) -> FuzzCase:
    """A malformed input for ``reader`` (a key of :data:`READERS`): a valid input built from
    a drawn seed, then 1-3 mutations (see the module docstring)."""
    spec = READERS[reader]
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    content, entry = spec.build(rng)
    sort = draw(st.booleans())
    mutations: list[str] = []
    n_mutations = draw(st.integers(1, 3))
    if isinstance(content.get(entry), bytes):  # a binary log (UBX): byte-level mutations
        data = content[entry]
        for _ in range(n_mutations):
            data, name = draw(_mutate_bytes(data))
            mutations.append(name)
        return FuzzCase(reader, {entry: data}, entry, sort, mutations)
    if spec.binary:
        arrays = content[entry]
        byte_level = draw(st.integers(0, 3)) == 0
        for _ in range(n_mutations if not byte_level else 0):
            arrays, name = draw(_mutate_arrays(arrays))
            mutations.append(name)
        data = _npz_bytes(arrays)
        if byte_level:
            data, name = draw(_mutate_bytes(data))
            mutations.append(name)
        return FuzzCase(reader, {entry: data}, entry, sort, mutations)
    files: dict[str, bytes | None] = {
        k: None if v is None else v.encode("utf-8") for k, v in content.items()
    }
    for _ in range(n_mutations):
        names = sorted(k for k, v in files.items() if v is not None)
        if not names:
            break
        target = draw(st.sampled_from(names))
        if entry == "" and draw(st.integers(0, 5)) == 0:
            kind = draw(st.sampled_from(_FOLDER_MUTATIONS))
            if kind == "remove_file":
                del files[target]
            elif kind == "file_to_folder":
                files[target] = None
            else:
                files[draw(st.sampled_from(("notes.txt", "poses_.csv", "poses_a b.csv")))] = (
                    b"junk\n"
                )
            mutations.append(f"{kind}:{target}")
            continue
        files[target], name = draw(_mutate_text(target, files[target] or b""))
        mutations.append(f"{name}:{target}")
    return FuzzCase(reader, files, entry, sort, mutations)


# ----------------------------------------------------------------------------- running


def write_case(case: FuzzCase, root: Path) -> Path:
    """Write ``case.files`` under the empty folder ``root``; return the path to read."""
    for rel, data in sorted(case.files.items(), key=lambda kv: kv[0].count("/")):
        target = root / rel
        if data is None:
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
    return root / case.entry if case.entry else root


def _line_count(path: Path) -> int:
    """Most lines any common convention finds in ``path`` (0 when it is no readable file)."""
    try:
        data = path.read_bytes()
    except OSError:
        return 0
    text = data.decode("utf-8", errors="replace")
    universal = len(re.split(r"\r\n|\r|\n", text))
    return max(universal, len(text.splitlines()), text.count("\n") + 1)


def _judge_error(err: DataError, root: Path) -> str | None:
    """Why a DataError does not locate its problem inside the input (None: it does)."""
    where = os.path.abspath(err.path)
    base = os.path.abspath(root)
    if not (where == base or where.startswith(base + os.sep) or where.startswith(base + "[")):
        return f"error names {err.path!r}, outside the input"
    if err.line is not None:
        file = Path(re.sub(r"\[[^\]]*\]$", "", where))
        count = _line_count(file)
        if not 1 <= err.line <= count:
            return f"error names line {err.line}; the file has {count}"
    if not err.problem:
        return "error without a problem statement"
    return None


def classify(case: FuzzCase, root: Path) -> tuple[str, str]:
    """Write ``case`` under the empty folder ``root``, run its reader, judge the outcome.

    Returns:
        (outcome, detail): ``outcome`` one of :data:`OUTCOMES`; ``detail`` the error message,
        the broken promise or the crash's exception type, message and innermost frame.
    """
    spec = READERS[case.reader]
    path = write_case(case, root)
    try:
        result = spec.read(path, case.sort)
    except (DataError, MissingExtraError) as err:
        if isinstance(err, MissingExtraError):
            return "data_error", str(err)
        problem = _judge_error(err, root)
        return ("bad_error", f"{problem}: {err}") if problem else ("data_error", str(err))
    except Exception as err:  # noqa: BLE001 - the oracle's job is to catch everything
        frame = traceback.extract_tb(err.__traceback__)[-1]
        where = f"{Path(frame.filename).name}:{frame.lineno}"
        return "crash", f"{type(err).__name__} at {where}: {str(err)[:200]}"
    try:
        problem = spec.check(result)
    except Exception as err:  # noqa: BLE001 - a result that cannot be checked is bad output
        problem = f"result check raised {type(err).__name__}: {str(err)[:200]}"
    return ("bad_output", problem) if problem else ("ok", "")
