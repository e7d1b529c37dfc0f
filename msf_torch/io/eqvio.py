"""The EuRoC IMU + feature-track replay file that the ``gtsam`` wheel ships for EqVIO.

``gtsam/Data/eqvio_processed_30s.csv`` holds the first 30 s of EuRoC MAV ``V1_01_easy``
(Vicon room 1) as GTSAM's ``EqVIOFilterExample`` replays it: the 200 Hz IMU stream and the
20 Hz cam0 feature tracks in normalized image coordinates, plus the filter's settings. It is
read here through the installed package (nothing is copied into this repository).

File layout (one CSV, header line then one event per row)::

    row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,
    bgx,bgy,bgz,bax,bay,baz,u_norm,v_norm,key,value

``row_type`` is one of

* ``meta``: only ``key`` and ``value`` are filled; 52 rows in the shipped file (see below).
* ``imu``: ``t_abs`` (absolute time, s; EuRoC's Unix-epoch clock), ``t_rel`` (``t_abs``
  minus the ``t0_abs`` meta value, s), ``seq``, ``gx gy gz`` (gyro, rad/s), ``ax ay az``
  (specific force, m/s^2), ``bgx bgy bgz`` and ``bax bay baz``; 6001 rows, 0 s to 30 s.
  GTSAM's reader (``gtsam_unstable/navigation/EqVIOCsv.cpp``) loads the ``b*`` columns
  into ``IMUInput.gyrBiasVel`` / ``accBiasVel``: they are bias *velocities* (the rate of
  change of the bias, an input of the EqF), not bias values. All are 0 in the shipped file.
* ``vision_feature``: one feature observation: ``t_abs``, ``t_rel``, ``seq``,
  ``frame_idx``, ``landmark_id``, ``u_norm``, ``v_norm`` (normalized, i.e. undistorted
  ``x/z``, ``y/z`` in the camera frame, dimensionless); 13316 rows over 601 frames
  (``frame_idx`` 0..600) and 307 landmarks (ids 1..307), 12 to 38 per frame.

``seq`` is one global event counter: every IMU row has its own, every feature row of one
frame shares the frame's. The rows are sorted by time; at equal times ``seq`` gives the event
order (frame 0 is ``seq`` 0, the first IMU sample ``seq`` 1, both at ``t_rel`` 0).

The meta keys that matter (values of the shipped file):

* camera-to-IMU extrinsics ``T_ci_tx, T_ci_ty, T_ci_tz`` (m) and ``T_ci_qw, T_ci_qx,
  T_ci_qy, T_ci_qz`` (Hamilton, scalar first): translation ``[-0.02164, -0.06468,
  0.00981]``, a rotation of about +90 degrees about z. Despite the name, this is
  ``T_imu_cam`` (it maps camera-frame points into the IMU frame, i.e. the camera's pose in
  the IMU frame): the translation and the rotation equal, to 5e-13, EuRoC's published
  ``cam0/sensor.yaml`` ``T_BS`` (``T_body_sensor``, body = IMU), and GTSAM's example feeds
  them unchanged to ``State.cameraOffset``. ``tests/io/test_io_eqvio.py`` checks this
  against ``T_BS`` and, independently, against the data (gyro rates rotated into the camera
  frame match the rotation fitted to the feature flow).
* feature noise ``eqf.measurement_noise_variance_norm`` = 1.7756e-5 (normalized units^2,
  sigma 0.004214) and ``eqf.measurement_noise_variance_px`` = 3.7241 px^2 (sigma 1.930 px);
  the first is the second divided by ``camera_fx * camera_fy``. GTSAM's example uses the
  normalized one (``R = variance * I``).
* cam0 intrinsics ``camera_fx, camera_fy, camera_cx, camera_cy`` = 458.654, 457.296,
  367.215, 248.375 px (EuRoC's; no distortion coefficients: the features are undistorted).
* IMU noise ``eqf.input_var_gyr``, ``eqf.input_var_acc``, ``eqf.input_var_gyr_bias_walk``,
  ``eqf.input_var_acc_bias_walk`` = 5.912e-8, 1.547e-4, 1.788e-8, 1.991e-5: the diagonal of
  the EqF's continuous-time input noise (GTSAM's ``EqVIOFilterParams.inputNoise``). The file
  states no units; they read as continuous-time densities squared ((rad/s)^2/Hz,
  (m/s^2)^2/Hz, (rad/s^2)^2/Hz, (m/s^3)^2/Hz) tuned above EuRoC's ADIS16448 datasheet
  (whose squared densities are 2.9e-8, 4.0e-6, 3.8e-10, 9.0e-6).
* ``t0_abs`` = 1403715273.2621431 s (the first IMU time), ``duration_sec`` = 30, the other
  ``eqf.*`` filter settings (initial and process variances, outlier thresholds, ...) and
  bookkeeping (``format_version`` 1, ``measurement_space`` normalized, ``source_mode`` asl,
  ``dataset_path``).

The file has no ground truth (EuRoC's ``state_groundtruth_estimate0`` is not included), so
:class:`EqvioRun` has no ground-truth field. The gtsam extra is needed for the default path:
``pip install 'msf_torch[peers]'``.
"""

from __future__ import annotations

__all__ = ["EQVIO_FILE", "EqvioRun", "load_eqvio"]

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.io.kitti_gtsam import gtsam_data_path
from msf_torch.types import ImuSamples

EQVIO_FILE = "eqvio_processed_30s.csv"
"""Name of the file in the gtsam wheel's ``Data`` folder."""

_REQUIRED = [
    "row_type",
    "t_abs",
    "seq",
    "frame_idx",
    "landmark_id",
    "gx",
    "gy",
    "gz",
    "ax",
    "ay",
    "az",
    "bgx",
    "bgy",
    "bgz",
    "bax",
    "bay",
    "baz",
    "u_norm",
    "v_norm",
    "key",
    "value",
]
_OPTIONAL = [[["t_rel"]]]
_GYRO = ["gx", "gy", "gz"]
_ACCEL = ["ax", "ay", "az"]
_BIAS_VEL = ["bgx", "bgy", "bgz", "bax", "bay", "baz"]
_EXTRINSIC_KEYS = ["T_ci_tx", "T_ci_ty", "T_ci_tz", "T_ci_qw", "T_ci_qx", "T_ci_qy", "T_ci_qz"]
_INTRINSIC_KEYS = ["camera_fx", "camera_fy", "camera_cx", "camera_cy"]
_IMU_NOISE_KEYS = {
    "gyro_noise_sigma": "eqf.input_var_gyr",
    "accel_noise_sigma": "eqf.input_var_acc",
    "gyro_bias_rw_sigma": "eqf.input_var_gyr_bias_walk",
    "accel_bias_rw_sigma": "eqf.input_var_acc_bias_walk",
}
_FRAME_TIME_TOL = 1e-9
"""Feature rows of one frame must agree on ``t_abs`` to this many seconds (as GTSAM's)."""


@dataclass
class EqvioRun:
    """IMU samples, feature tracks and sensor settings of one EqVIO replay file.

    Times are float64 seconds relative to the first IMU sample (``t0_abs``); all float
    tensors are float64 and all index tensors int64, on the CPU (see :meth:`to`).

    Attributes:
        imu: the IMU stream, B = 1: ``t`` (1, N) s (0 at the first sample), ``gyro``
            (1, N, 3) rad/s, ``accel`` (1, N, 3) m/s^2 (specific force: at rest it reads
            +g along the IMU's up axis, here mostly +x), ``mask`` (1, N) all True. IMU frame
            = EuRoC's body frame.
        imu_seq: (N,) int64 the file's global event counter of each IMU sample.
        gyro_bias_velocity: (1, N, 3) rad/s^2, the ``bgx bgy bgz`` columns (rate of change
            of the gyro bias, an EqF input), or None when the columns are empty on every
            IMU row. All zero in the shipped file.
        accel_bias_velocity: (1, N, 3) m/s^3, the ``bax bay baz`` columns, or None.
        t0_abs: absolute time of the first IMU sample, s (EuRoC: Unix epoch). Add it to
            any relative time to get the file's ``t_abs``.
        frame_times: (F,) camera frame times, s, strictly increasing, same origin as
            ``imu.t``.
        frame_idx: (F,) int64 the file's ``frame_idx`` of each frame (0..600 here).
        frame_seq: (F,) int64 the file's ``seq`` of each frame (orders a frame against IMU
            samples with the same time).
        obs_frame: (M,) int64 index into ``frame_times`` of each feature observation.
        obs_landmark: (M,) int64 dense landmark index 0..L-1 of each observation
            (``landmark_ids[obs_landmark]`` is the file's id).
        landmark_ids: (L,) int64 the file's ``landmark_id`` values, ascending.
        obs_normalized: (M, 2) normalized image coordinates ``[u, v] = [x/z, y/z]`` in the
            camera frame (undistorted), dimensionless. Observations are grouped by frame in
            frame order, file order within a frame; a (frame, landmark) pair occurs once.
        R_imu_cam: (3, 3) rotation camera -> IMU (``v_imu = R_imu_cam @ v_cam``), from the
            ``T_ci_q*`` meta keys; None when the file has no extrinsics.
        t_imu_cam: (3,) position of the camera centre in the IMU frame, m (``T_ci_t*``), so
            ``p_imu = R_imu_cam @ p_cam + t_imu_cam``; None when absent. Evidence for the
            direction: these equal EuRoC's published cam0 ``T_BS`` (``T_body_sensor``) to
            5e-13, and the IMU's gyro rates rotated by ``R_imu_cam^T`` match the camera
            rotation fitted to the feature flow (see the module docstring and the tests).
        feature_sigma_normalized: per-axis standard deviation of ``obs_normalized``,
            dimensionless (sqrt of ``eqf.measurement_noise_variance_norm``), or None.
        feature_sigma_px: per-axis standard deviation in pixels (sqrt of
            ``eqf.measurement_noise_variance_px``), or None.
        intrinsics: (4,) ``[fx, fy, cx, cy]`` px of the camera that gave the features, or
            None when not all four ``camera_*`` keys are present.
        imu_noise: continuous-time IMU noise under the keys :func:`load_kitti_gtsam` uses,
            each the sqrt of the file's EqF input variance: ``gyro_noise_sigma``
            (rad/s/sqrt(Hz), from ``eqf.input_var_gyr``), ``accel_noise_sigma``
            (m/s^2/sqrt(Hz), ``eqf.input_var_acc``), ``gyro_bias_rw_sigma``
            (rad/s^2/sqrt(Hz), ``eqf.input_var_gyr_bias_walk``), ``accel_bias_rw_sigma``
            (m/s^3/sqrt(Hz), ``eqf.input_var_acc_bias_walk``); only the keys the file gives.
            The file states no units (see the module docstring).
        eqf_params: every numeric ``eqf.*`` meta value as a float (the EqF's tuning, as
            written; ``eqf.coordinate_choice`` = ``InvDepth`` is text and stays in ``meta``).
        meta: every meta row, ``key -> value`` as written (strings).
        source: the file that was read.
        cleaning: what the io cleaning rules did (``msf_torch.io._tables.CleanReport``):
            ``dropped_nonfinite`` / ``dropped_duplicates`` / ``sorted`` per stream
            (``"imu"``, ``"features"``), and ``dropped_lines`` when rows were dropped.
    """

    imu: ImuSamples
    imu_seq: torch.Tensor
    gyro_bias_velocity: torch.Tensor | None
    accel_bias_velocity: torch.Tensor | None
    t0_abs: float
    frame_times: torch.Tensor
    frame_idx: torch.Tensor
    frame_seq: torch.Tensor
    obs_frame: torch.Tensor
    obs_landmark: torch.Tensor
    landmark_ids: torch.Tensor
    obs_normalized: torch.Tensor
    R_imu_cam: torch.Tensor | None
    t_imu_cam: torch.Tensor | None
    feature_sigma_normalized: float | None
    feature_sigma_px: float | None
    intrinsics: torch.Tensor | None
    imu_noise: dict[str, float] = field(default_factory=dict)
    eqf_params: dict[str, float] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)
    source: str = ""
    cleaning: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        """F."""
        return int(self.frame_times.shape[0])

    @property
    def num_landmarks(self) -> int:
        """L."""
        return int(self.landmark_ids.shape[0])

    @property
    def num_observations(self) -> int:
        """M."""
        return int(self.obs_frame.shape[0])

    @property
    def duration(self) -> float:
        """Last IMU time minus the first, s."""
        t = self.imu.t[0]
        return float(t[-1] - t[0]) if t.numel() else 0.0

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> EqvioRun:
        """A copy on ``device``; floating tensors also cast to ``dtype`` when given."""

        def move(x: Any) -> Any:
            if not isinstance(x, torch.Tensor):
                return x
            if dtype is not None and x.is_floating_point():
                return x.to(device=device, dtype=dtype)
            return x.to(device=device)

        changes = {f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)}
        changes["imu"] = self.imu.to(device, dtype)
        return dataclasses.replace(self, **changes)


def _subtable(table: _tables.Table, keep: list[int]) -> _tables.Table:
    return _tables.Table(
        path=table.path,
        header=table.header,
        header_line=table.header_line,
        rows=[table.rows[i] for i in keep],
        lines=table.lines[keep],
    )


def _read_meta(table: _tables.Table) -> tuple[dict[str, str], dict[str, int]]:
    """Meta rows -> (key -> value, key -> 1-based line). A key given twice is a DataError."""
    k_col, v_col = table.index("key"), table.index("value")
    meta: dict[str, str] = {}
    lines: dict[str, int] = {}
    for row, line in zip(table.rows, table.lines.tolist(), strict=True):
        key = row[k_col]
        if not key:
            raise DataError(table.path, "a meta row needs a key", line=line, field="key")
        if key in meta:
            raise DataError(
                table.path,
                f"meta key {key!r} given twice (first on line {lines[key]})",
                line=line,
                field="key",
            )
        meta[key] = row[v_col]
        lines[key] = line
    return meta, lines


def _meta_float(path: str, meta: dict[str, str], lines: dict[str, int], key: str) -> float | None:
    """The finite float value of meta ``key``; None when absent; DataError when malformed."""
    if key not in meta:
        return None
    return _parse_meta(path, meta[key], lines[key], key)


def _parse_meta(path: str, text: str, line: int, key: str) -> float:
    try:
        value = float(text)
    except ValueError:
        problem = "empty value" if text == "" else f"not a number: {text!r}"
        raise DataError(path, f"meta {key!r}: {problem}", line=line, field="value") from None
    if not math.isfinite(value):
        raise DataError(path, f"meta {key!r}: not finite: {text!r}", line=line, field="value")
    return value


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _meta_group(
    path: str, meta: dict[str, str], lines: dict[str, int], keys: list[str]
) -> list[float] | None:
    """All of ``keys`` as floats, or None when none is present (a partial set is an error)."""
    present = [k for k in keys if k in meta]
    if not present:
        return None
    missing = [k for k in keys if k not in meta]
    if missing:
        raise DataError(
            path,
            f"meta keys {', '.join(keys)} come together; {', '.join(missing)} missing",
            line=lines[present[0]],
            field="key",
        )
    return [_parse_meta(path, meta[k], lines[k], k) for k in keys]


def _nonneg_sqrt(path: str, lines: dict[str, int], key: str, value: float | None) -> float | None:
    if value is None:
        return None
    if value < 0:
        raise DataError(
            path, f"meta {key!r}: negative variance {value!r}", line=lines[key], field="value"
        )
    return math.sqrt(value)


def _extrinsics(
    path: str, meta: dict[str, str], lines: dict[str, int]
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    values = _meta_group(path, meta, lines, _EXTRINSIC_KEYS)
    if values is None:
        return None, None
    quat = np.asarray(values[3:], dtype=np.float64)
    _tables.check_quaternions(path, quat[None], lines=np.array([lines["T_ci_qw"]]), name="value")
    unit = _tables.normalise_quaternions(quat[None])[0]
    rot = quat_to_matrix(torch.as_tensor(unit, dtype=torch.float64))
    return rot, torch.tensor(values[:3], dtype=torch.float64)


def _read_imu(
    table: _tables.Table, report: _tables.CleanReport
) -> tuple[dict[str, np.ndarray], bool]:
    """IMU rows -> cleaned arrays ``t`` (absolute s), ``gyro``, ``accel``, ``seq`` and, when
    the bias-velocity cells are filled, ``bias_vel`` (N, 6)."""
    if len(table) == 0:
        raise DataError(table.path, "no IMU rows (row_type 'imu')")
    bias_cols = [table.index(c) for c in _BIAS_VEL]
    has_bias = any(row[i] != "" for row in table.rows for i in bias_cols)
    values = table.floats(["t_abs", *_GYRO, *_ACCEL])
    seq = table.ints("seq")
    arrays = {
        "t": values[:, 0],
        "gyro": values[:, 1:4],
        "accel": values[:, 4:7],
        "seq": seq.astype(np.float64),
    }
    if has_bias:
        arrays["bias_vel"] = table.floats(_BIAS_VEL)
    cleaned = _tables.clean_stream(
        report, "imu", table.path, arrays, lines=table.lines, time_name="t_abs"
    )
    return cleaned, has_bias


def _read_features(
    table: _tables.Table, report: _tables.CleanReport, t0: float
) -> dict[str, np.ndarray]:
    """Feature rows -> frames (by ``seq``) and flat observations; see :class:`EqvioRun`."""
    values = table.floats(["t_abs", "u_norm", "v_norm"])
    seq = table.ints("seq")
    frame = table.ints("frame_idx")
    landmark = table.ints("landmark_id")
    lines = table.lines
    good = np.isfinite(values).all(axis=1)
    dropped = np.flatnonzero(~good)
    report.dropped_nonfinite["features"] = int(dropped.size)
    report.dropped_duplicates["features"] = 0
    report.sorted["features"] = 0
    if dropped.size:
        report.dropped_lines["features"] = [
            int(x) for x in lines[dropped[: _tables.MAX_REPORTED_LINES]]
        ]
        values, seq, frame, landmark, lines = (
            a[good] for a in (values, seq, frame, landmark, lines)
        )
    # Frames are the distinct seq values, in seq order (GTSAM's event order).
    frame_seq, first, obs_frame = np.unique(seq, return_index=True, return_inverse=True)
    frame_t = values[first, 0]
    frame_id = frame[first]
    bad_id = np.flatnonzero(frame != frame_id[obs_frame])
    if bad_id.size:
        i = int(bad_id[0])
        raise DataError(
            table.path,
            f"frame_idx {int(frame[i])} differs from {int(frame_id[obs_frame[i]])} on line "
            f"{int(lines[first[obs_frame[i]]])}, the first row of seq {int(seq[i])}",
            line=int(lines[i]),
            field="frame_idx",
        )
    bad_t = np.flatnonzero(np.abs(values[:, 0] - frame_t[obs_frame]) > _FRAME_TIME_TOL)
    if bad_t.size:
        i = int(bad_t[0])
        raise DataError(
            table.path,
            f"t_abs {float(values[i, 0])!r} differs from {float(frame_t[obs_frame[i]])!r} on line "
            f"{int(lines[first[obs_frame[i]]])}, the first row of frame seq {int(seq[i])}",
            line=int(lines[i]),
            field="t_abs",
        )
    _, first_id = np.unique(frame_id, return_index=True)
    if first_id.size != frame_id.size:
        dup = np.setdiff1d(np.arange(frame_id.size), first_id)[0]
        other = int(np.flatnonzero(frame_id == frame_id[dup])[0])
        raise DataError(
            table.path,
            f"frame_idx {int(frame_id[dup])} is used by seq {int(frame_seq[other])} "
            f"(line {int(lines[first[other]])}) and seq {int(frame_seq[dup])}",
            line=int(lines[first[dup]]),
            field="frame_idx",
        )
    back = np.flatnonzero(np.diff(frame_t) <= 0) + 1
    if back.size:
        k = int(back[0])
        raise DataError(
            table.path,
            f"frame times must increase with seq: frame seq {int(frame_seq[k])} at "
            f"{float(frame_t[k])!r} s does not come after seq {int(frame_seq[k - 1])} at "
            f"{float(frame_t[k - 1])!r} s (line {int(lines[first[k - 1]])})",
            line=int(lines[first[k]]),
            field="t_abs",
        )
    landmark_ids, obs_landmark = np.unique(landmark, return_inverse=True)
    pair = obs_frame.astype(np.int64) * landmark_ids.size + obs_landmark
    _, first_pair = np.unique(pair, return_index=True)
    if first_pair.size != pair.size:
        dup = int(np.setdiff1d(np.arange(pair.size), first_pair)[0])
        other = int(np.flatnonzero(pair == pair[dup])[0])
        raise DataError(
            table.path,
            f"landmark {int(landmark[dup])} is observed twice in frame {int(frame[dup])} "
            f"(first on line {int(lines[other])})",
            line=int(lines[dup]),
            field="landmark_id",
        )
    order = np.argsort(obs_frame, kind="stable")
    return {
        "frame_times": frame_t - t0,
        "frame_idx": frame_id,
        "frame_seq": frame_seq,
        "obs_frame": obs_frame[order],
        "obs_landmark": obs_landmark[order],
        "landmark_ids": landmark_ids,
        "obs_normalized": values[order, 1:3],
    }


def load_eqvio(path: str | os.PathLike[str] | None = None) -> EqvioRun:
    """Load an EqVIO replay CSV (by default the EuRoC V1_01_easy file shipped with gtsam).

    Args:
        path: the CSV file, or None for ``eqvio_processed_30s.csv`` in the installed gtsam
            wheel's ``Data`` folder.

    Returns:
        an :class:`EqvioRun`. For the shipped file: N = 6001 IMU samples at 200 Hz over
        30 s, F = 601 frames at 20 Hz, M = 13316 observations of L = 307 landmarks.

    Rules (those of :mod:`msf_torch.io`): IMU rows and feature rows with a NaN or inf are
    dropped and counted in ``cleaning``; IMU times must not go backwards (a repeated time
    keeps the first sample); frame times must increase with ``seq``; all feature rows of one
    ``seq`` must agree on ``frame_idx`` and ``t_abs``.

    Raises:
        MissingExtraError: ``path`` is None and gtsam is not installed
            (``pip install 'msf_torch[peers]'``).
        DataError: a missing file, a missing, repeated or unknown column, a row with the
            wrong number of cells, an unknown ``row_type``, a cell that is not a number
            (or integer for ``seq``, ``frame_idx``, ``landmark_id``), a malformed or
            repeated meta value, inconsistent frames, a landmark seen twice in one frame,
            backwards time, or no IMU rows; the message names the file, the 1-based line and
            the field.
    """
    file = gtsam_data_path(EQVIO_FILE) if path is None else Path(path)
    table = _tables.read_table(file)
    _tables.check_columns(table, _REQUIRED, _OPTIONAL)
    kinds: dict[str, list[int]] = {"meta": [], "imu": [], "vision_feature": []}
    type_col = table.index("row_type")
    for i, row in enumerate(table.rows):
        bucket = kinds.get(row[type_col])
        if bucket is None:
            raise DataError(
                table.path,
                f"unknown row_type {row[type_col]!r} (expected: {', '.join(kinds)})",
                line=int(table.lines[i]),
                field="row_type",
            )
        bucket.append(i)

    meta, meta_lines = _read_meta(_subtable(table, kinds["meta"]))
    report = _tables.CleanReport()
    imu, has_bias = _read_imu(_subtable(table, kinds["imu"]), report)
    if imu["t"].shape[0] == 0:
        raise DataError(table.path, "no finite IMU rows (row_type 'imu')")
    t0 = float(imu["t"][0])
    feats = _read_features(_subtable(table, kinds["vision_feature"]), report, t0)

    src = table.path
    rot, trans = _extrinsics(src, meta, meta_lines)
    intr = _meta_group(src, meta, meta_lines, _INTRINSIC_KEYS)
    var_norm_key = "eqf.measurement_noise_variance_norm"
    var_px_key = "eqf.measurement_noise_variance_px"
    sigma_norm = _nonneg_sqrt(
        src, meta_lines, var_norm_key, _meta_float(src, meta, meta_lines, var_norm_key)
    )
    sigma_px = _nonneg_sqrt(
        src, meta_lines, var_px_key, _meta_float(src, meta, meta_lines, var_px_key)
    )
    imu_noise: dict[str, float] = {}
    for name, key in _IMU_NOISE_KEYS.items():
        sigma = _nonneg_sqrt(src, meta_lines, key, _meta_float(src, meta, meta_lines, key))
        if sigma is not None:
            imu_noise[name] = sigma
    eqf_params = {
        key: float(value)
        for key, value in meta.items()
        if key.startswith("eqf.") and _is_number(value)
    }

    def f64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    def i64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.int64)

    n = imu["t"].shape[0]
    imu_samples = ImuSamples(
        t=f64(imu["t"] - t0)[None],
        gyro=f64(imu["gyro"])[None],
        accel=f64(imu["accel"])[None],
        mask=torch.ones((1, n), dtype=torch.bool),
    )
    bias_vel = f64(imu["bias_vel"])[None] if has_bias else None
    return EqvioRun(
        imu=imu_samples,
        imu_seq=i64(imu["seq"].astype(np.int64)),
        gyro_bias_velocity=None if bias_vel is None else bias_vel[..., :3].contiguous(),
        accel_bias_velocity=None if bias_vel is None else bias_vel[..., 3:].contiguous(),
        t0_abs=t0,
        frame_times=f64(feats["frame_times"]),
        frame_idx=i64(feats["frame_idx"]),
        frame_seq=i64(feats["frame_seq"]),
        obs_frame=i64(feats["obs_frame"]),
        obs_landmark=i64(feats["obs_landmark"]),
        landmark_ids=i64(feats["landmark_ids"]),
        obs_normalized=f64(feats["obs_normalized"]),
        R_imu_cam=rot,
        t_imu_cam=trans,
        feature_sigma_normalized=sigma_norm,
        feature_sigma_px=sigma_px,
        intrinsics=None if intr is None else torch.tensor(intr, dtype=torch.float64),
        imu_noise=imu_noise,
        eqf_params=eqf_params,
        meta=meta,
        source=src,
        cleaning=report.to_meta(),
    )
