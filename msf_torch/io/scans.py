"""2D LiDAR scan files (``.npz``): ranges per beam, beam angles, optional odometry and truth.

Keys (float64):

* ``t`` (N,): scan times, s, strictly increasing;
* ``angles`` (K,): beam angles in the sensor frame, rad, finite, evenly spaced and
  increasing (0 = sensor x axis, counter-clockwise), spanning at most one turn
  (``angles[-1] - angles[0] <= 2 pi`` + :data:`ANGLE_SPAN_TOLERANCE`; a wider span is
  taken for degrees and refused);
* ``ranges`` (N, K): ranges, m; NaN (or inf) where a beam returned nothing (the scan
  matcher and the grid also read 0 as no return); a median return above
  :data:`MAX_MEDIAN_RANGE_M` is taken for millimetres and refused;
* ``odometry`` (N, 3), optional: wheel-odometry pose ``[x, y, yaw]`` at each scan (m, rad),
  used as PLICP's initial guesses; finite;
* ``truth`` (N, 3), optional: true pose at each scan, for evaluation; finite.

Example:
    >>> from msf_torch.io.scans import read_scans, write_scans
    >>> from msf_torch.sim.lidar2d import corridor_map, simulate_lidar_run
    >>> run = simulate_lidar_run(corridor_map(), seed=0, duration_s=1.0)
    >>> path = write_scans("/tmp/scans_doctest.npz", run.t, run.angles, run.ranges,
    ...                    odometry=run.odometry, truth=run.truth)
    >>> read_scans(path)["ranges"].shape
    torch.Size([11, 541])
"""

from __future__ import annotations

__all__ = ["ANGLE_SPAN_TOLERANCE", "MAX_MEDIAN_RANGE_M", "read_scans", "write_scans"]

import os
from pathlib import Path

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_save_npz
from msf_torch.io.errors import DataError

ANGLE_SPAN_TOLERANCE = 1e-3
"""rad: how far past one full turn (2 pi) the beam angles of a scan file may span."""

MAX_MEDIAN_RANGE_M = 300.0
"""m: the largest median return a scan file may have (2D LiDARs reach 30-100 m; ranges in
millimetres read a thousand times their metres)."""

_REQUIRED = ("t", "angles", "ranges")
_SHOWN_KEYS = 8


def write_scans(
    path: str | os.PathLike[str],
    t: torch.Tensor,
    angles: torch.Tensor,
    ranges: torch.Tensor,
    odometry: torch.Tensor | None = None,
    truth: torch.Tensor | None = None,
) -> Path:
    """Write a scan file (see the module docstring); returns its path."""
    arrays = {
        "t": t.detach().cpu().numpy(),
        "angles": angles.detach().cpu().numpy(),
        "ranges": ranges.detach().cpu().numpy(),
    }
    if odometry is not None:
        arrays["odometry"] = odometry.detach().cpu().numpy()
    if truth is not None:
        arrays["truth"] = truth.detach().cpu().numpy()
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_save_npz(target, **arrays)
    return target


def read_scans(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Read and check a scan file; returns float64 tensors by key (``ranges`` with NaN where
    there is no return).

    Raises:
        DataError: naming the file and key when a key is missing (the message lists the
            file's keys, e.g. for a sensor ``.npz`` given by mistake), a value is not
            numeric, or a shape or value is bad; beam angles that span more than one turn
            are refused as degrees.
    """
    source = Path(path)
    try:
        with np.load(source) as data:
            raw = {key: np.asarray(data[key]) for key in data.files}
    except _tables.NPZ_ERRORS as err:
        raise DataError(source, f"cannot read as .npz: {err}") from err
    for key in _REQUIRED:
        if key not in raw:
            names = ", ".join(
                k if len(k) <= 30 else k[:27] + "..." for k in list(raw)[:_SHOWN_KEYS]
            )
            more = f", ... ({len(raw)} keys)" if len(raw) > _SHOWN_KEYS else ""
            raise DataError(
                source, f"missing key '{key}' (has: {names or 'no keys'}{more})", field=key
            )
    arrays = {}
    for key, value in raw.items():
        if value.dtype.kind not in "biuf":
            raise DataError(source, f"not numeric (dtype {value.dtype})", field=key)
        arrays[key] = value.astype(np.float64)
    t, angles, ranges = arrays["t"], arrays["angles"], arrays["ranges"]
    if t.ndim != 1 or angles.ndim != 1 or ranges.shape != (t.shape[0], angles.shape[0]):
        raise DataError(
            source,
            f"expected t (N,), angles (K,), ranges (N, K); got {t.shape}, {angles.shape}, "
            f"{ranges.shape}",
            field="ranges",
        )
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        with np.errstate(invalid="ignore"):
            wrong = ~np.isfinite(t) | np.concatenate(([False], np.diff(t) <= 0))
        bad = int(np.argmax(wrong))
        raise DataError(source, f"times must be finite and increasing (scan {bad})", field="t")
    if not np.all(np.isfinite(angles)):
        beam = int(np.argmax(~np.isfinite(angles)))
        raise DataError(source, f"beam angle {beam} is not finite", field="angles")
    step = np.diff(angles)
    if (
        len(angles) < 2
        or not np.all(np.isfinite(step))
        or not np.all(step > 0)
        or np.ptp(step) > 1e-6 * abs(step.mean())
    ):
        raise DataError(source, "beam angles must be evenly spaced and increasing", field="angles")
    span = float(angles[-1] - angles[0])
    if span > 2 * np.pi + ANGLE_SPAN_TOLERANCE:
        raise DataError(
            source,
            f"angles look like degrees (span {span:.6g}), expected radians (a span of at most "
            "2 pi)",
            field="angles",
        )
    with np.errstate(invalid="ignore"):
        negative = np.isfinite(ranges) & (ranges < 0)
    if negative.any():
        scan, beam = np.argwhere(negative)[0]
        raise DataError(source, f"negative range at scan {scan}, beam {beam}", field="ranges")
    returned = ranges[np.isfinite(ranges) & (ranges > 0)]
    if returned.size and float(np.median(returned)) > MAX_MEDIAN_RANGE_M:
        raise DataError(
            source,
            f"ranges look like millimetres (median {float(np.median(returned)):.6g}), expected "
            f"metres (a 2D LiDAR's median return is under {MAX_MEDIAN_RANGE_M:g} m)",
            field="ranges",
        )
    arrays["ranges"] = np.where(np.isfinite(ranges), ranges, np.nan)
    for key in ("odometry", "truth"):
        if key in arrays and arrays[key].shape != (t.shape[0], 3):
            raise DataError(
                source, f"expected ({t.shape[0]}, 3), got {arrays[key].shape}", field=key
            )
        if key in arrays and not np.all(np.isfinite(arrays[key])):
            scan = int(np.argwhere(~np.isfinite(arrays[key]))[0, 0])
            raise DataError(source, f"non-finite pose at scan {scan}", field=key)
    return {key: torch.as_tensor(value) for key, value in arrays.items()}
