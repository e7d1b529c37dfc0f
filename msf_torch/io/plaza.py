"""The Plaza range-beacon runs that the gtsam wheel ships: a wheeled robot's odometry, radio
ranges to four fixed beacons and RTK-GPS ground truth (Carnegie Mellon's "emergency
response" range data; Djugash, Singh, Kantor and Zhang, "Range-only SLAM for robots
operating cooperatively with sensor networks", ICRA 2006).

Files (in ``gtsam/Data``; ``NAME`` is ``Plaza1`` or ``Plaza2``)
    * ``NAME_DR.txt``: one odometry step per line: time (s), distance travelled (m), heading
      change (rad) since the previous line.
    * ``NAME_TD.txt``: one range per line: time (s), sender (the robot's antenna), receiver
      (the beacon's id), range (m).
    * ``NAME_.mat`` (MATLAB): ``GT`` ground truth, one row per pose: time (s), x, y (m),
      heading (rad), the first row the start pose and one row at every odometry time;
      ``TL`` the beacons: id, x, y (m).

    Plaza1: 1932 s, 1861 m, 9657 steps at 5 Hz, 3529 ranges. Plaza2: 409 s, 1354 m, 4090
    steps at 10 Hz, 1816 ranges.

What the files do not say (measured on them; ``RangeRun.meta``)
    * Plaza2's ground-truth heading points backwards: the course of its ground-truth
      positions differs from it by a median 3.08 rad (Plaza1: -0.016 rad). The loader
      turns a run's truth headings by pi when that median exceeds pi/2, so
      ``truth[:, 2]`` is the direction of travel in both (``meta["truth_heading_turned"]``).
    * Plaza1's truth heading is the odometry's own (their difference over any stretch is
      0 to 1e-15 rad): only its positions are independent ground truth
      (``meta["truth_heading_is_odometry"]``).
    * Plaza1's range log has two blocks out of time order (the loader sorts the ranges by
      time; ``meta["ranges_reordered"]`` counts the moved lines).
    * The ranges read long: the median of range minus the true distance is +2.85 m on
      Plaza1 and +2.80 m on Plaza2 (spread 1.2 / 1.8 m, 1.4826 MAD): a constant bias of the
      radio ranging, not modelled here (the benchmark calibrates it on the other run).
"""

from __future__ import annotations

__all__ = ["PLAZA_RUNS", "load_plaza"]

import math
from typing import Any

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.io.kitti_gtsam import gtsam_data_path
from msf_torch.io.ranges import RangeRun

PLAZA_RUNS = ("Plaza1", "Plaza2")


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * angle))


def _matrix(path, mat: dict[str, Any], name: str, columns: int) -> np.ndarray:
    value = mat.get(name)
    if not isinstance(value, np.ndarray) or value.ndim != 2 or value.shape[1] != columns:
        shape = getattr(value, "shape", None)
        raise DataError(path, f"variable {name!r}: expected an (n, {columns}) matrix, got {shape}")
    value = value.astype(np.float64)
    if not np.isfinite(value).all():
        raise DataError(path, f"variable {name!r}: not finite")
    return value


def load_plaza(name: str = "Plaza2") -> RangeRun:
    """Read one Plaza run from the installed gtsam's data folder.

    Args:
        name: ``"Plaza1"`` or ``"Plaza2"``.

    Returns:
        a :class:`~msf_torch.io.ranges.RangeRun`: poses at the start and every odometry
        time (``pose_t``, the truth's times), each odometry step as the relative pose
        ``[distance, 0, heading change]`` (move, then turn), anchors = the beacons sorted by
        id, ``truth`` (M + 1, 3) with its heading along the direction of travel, wrapped.

    Raises:
        ValueError: an unknown run name.
        MissingExtraError: gtsam is not installed (``pip install 'msf_torch[peers]'``).
        DataError: a missing or malformed file (naming file, line and field), ranges to a
            beacon the run does not list, or truth rows that do not match the odometry.
    """
    if name not in PLAZA_RUNS:
        raise ValueError(f"unknown Plaza run {name!r}; known: {', '.join(PLAZA_RUNS)}")
    from scipy.io import loadmat

    dr_path = gtsam_data_path(f"{name}_DR.txt")
    td_path = gtsam_data_path(f"{name}_TD.txt")
    mat_path = gtsam_data_path(f"{name}_.mat")
    dr_names = ["time", "distance", "heading_change"]
    dr = _tables.read_table(dr_path, delimiter=None, header="none", names=dr_names)
    odometry = dr.floats(dr_names)
    td_names = ["time", "sender", "receiver", "range"]
    td = _tables.read_table(td_path, delimiter=None, header="none", names=td_names)
    ranges = td.floats(td_names)
    for table, values in ((dr, odometry), (td, ranges)):
        if not np.isfinite(values).all():
            row = int(np.argwhere(~np.isfinite(values))[0, 0])
            raise DataError(table.path, "not finite", line=int(table.lines[row]))
    back = np.flatnonzero(np.diff(odometry[:, 0]) <= 0)
    if back.size:
        raise DataError(
            dr.path, "time does not increase", line=int(dr.lines[back[0] + 1]), field="time"
        )
    # Plaza1's range log holds two blocks out of time order: sorted (stable) by time
    order = np.argsort(ranges[:, 0], kind="stable")
    reordered = int((order != np.arange(order.size)).sum())
    ranges, range_lines = ranges[order], td.lines[order]
    try:
        mat = loadmat(mat_path)
    except (ValueError, TypeError, OSError) as err:
        raise DataError(mat_path, f"not a readable MATLAB file ({err})") from None
    truth = _matrix(mat_path, mat, "GT", 4)
    beacons = _matrix(mat_path, mat, "TL", 3)
    if truth.shape[0] != odometry.shape[0] + 1 or not np.allclose(
        truth[1:, 0], odometry[:, 0], atol=1e-6
    ):
        raise DataError(
            mat_path,
            f"GT must hold the start pose and one row per odometry step ({odometry.shape[0] + 1} "
            f"rows at the {dr_path.name} times), got {truth.shape[0]} rows",
        )
    beacon_ids = beacons[:, 0].astype(np.int64)
    unknown = ~np.isin(ranges[:, 2].astype(np.int64), beacon_ids)
    if unknown.any():
        row = int(np.flatnonzero(unknown)[0])
        raise DataError(
            td_path,
            f"range to beacon {ranges[row, 2]:g}, which TL does not list ({beacon_ids.tolist()})",
            line=int(range_lines[row]),
            field="receiver",
        )
    step = np.diff(truth[:, 1:3], axis=0)
    moving = np.linalg.norm(step, axis=1) > 0.05
    course_offset = float(
        np.median(_wrap(np.arctan2(step[moving, 1], step[moving, 0]) - truth[1:, 3][moving]))
    )
    turned = abs(course_offset) > math.pi / 2
    truth[:, 3] = _wrap(truth[:, 3] + (math.pi if turned else 0.0))
    truth_turn = _wrap(np.diff(truth[:, 3]))
    meta = {
        "source": str(dr_path.parent),
        "truth_course_offset_rad": course_offset,
        "truth_heading_turned": turned,
        "ranges_reordered": reordered,
        "truth_heading_is_odometry": bool(np.abs(_wrap(truth_turn - odometry[:, 2])).max() < 1e-9),
    }

    def f64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    by_id = np.argsort(beacon_ids)
    steps = np.stack((odometry[:, 1], np.zeros(odometry.shape[0]), odometry[:, 2]), -1)
    return RangeRun(
        name=name,
        pose_t=f64(truth[:, 0]),
        odometry=f64(steps),
        range_t=f64(ranges[:, 0]),
        range_anchor=torch.as_tensor(ranges[:, 2].astype(np.int64)),
        ranges=f64(ranges[:, 3]),
        anchor_ids=torch.as_tensor(beacon_ids[by_id]),
        anchors=f64(beacons[by_id, 1:3]),
        truth=f64(truth[:, 1:4]),
        meta=meta,
    )
