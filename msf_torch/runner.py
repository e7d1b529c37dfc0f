"""Run the front end on one recorded sequence (:func:`run_sequence`), or on several in one
batch (:func:`run_batch`: each sequence's outputs in ``out_dir/<name>/``, plus ``runs.csv``
and the batch's ``summary.json``), and write the outputs.

Used by ``msf run``. Outputs in ``out_dir`` (each written atomically: temp file + rename):

- ``trajectory.tum``: estimated poses at every filter epoch (TUM: t x y z qx qy qz qw);
  with ``smooth`` set, the smoothed trajectory instead (``msf_torch.backend.window``: at
  every filter epoch by default, or at the keyframes with the smoother's
  ``output: keyframes``).
- ``diagnostics.csv``: per epoch: time, error-state covariance diagonal (15 variances in
  the order of ``geometry.conventions``), slip factor, IMU-gap flag, ``divergence`` (0, or
  the ``frontend.guard`` code of a divergence reset: 1 non-finite, 2 not positive definite,
  4 NIS blow-up, added), and per sensor (each pose source as ``pose:<name>``) whether a
  measurement was present, whether it was accepted, and its NIS; with
  ``source_fault_detection``, per pose source ``pose:<name>_fault`` (1 = excluded as
  faulty, ``frontend.gating``) and ``pose:<name>_fault_z`` (the detector's deciding Z at
  the source's pairs); with online
  calibration (``frontend.calibration``), per state its estimate ``<state>`` and 1-sigma
  ``<state>_sigma``.
- ``summary.json``: the run summary (also printed as the last line by the CLI). With
  ``smooth`` set, ``ate_*`` and ``outage_*`` score the smoothed trajectory, the front end's
  own figures keep a ``frontend_`` prefix, and ``smoother`` holds the smoother's figures.
  With online calibration: ``calibration`` / ``calibration_sigma`` (final estimates and
  1-sigma per state), ``calibration_variance_ratio`` and ``calibration_observable``
  (``frontend.calibration.observability``).
- ``overview.png``: trajectory against the reference, position error, slip factor.
- in ``summary.json`` besides: ``absolute_aiding`` (whether any GNSS or pose measurement
  was fused), ``labelled_gnss_outages`` (a real outage labelled in the data,
  ``labels["gnss_outage"]``, scored like a withheld one but against the ground truth:
  ``eval.outage.labelled_outage_metrics``; with ``smooth`` also ``frontend_`` figures) and
  ``stale_outputs`` (files of the names above that an earlier run left in ``out_dir`` and
  this one did not rewrite).
- with ``exports`` (``msf run --export kitti,rosbag2``): ``trajectory.kitti`` and
  ``trajectory_times.txt`` (KITTI pose format, :mod:`msf_torch.io.kitti_poses`) and
  ``trajectory_rosbag2/`` (``nav_msgs/Odometry`` on ``/msf/odometry``, frame ``enu``,
  child frame the sequence's body frame, or, for a bag whose robot YAML names a body
  frame other than the IMU's, the IMU's frame with the IMU's orientation: the estimate is
  the body axes at the IMU's origin, i.e. exactly the IMU frame's pose, and tf relates
  that to the body frame; stamped with the bag's time origin when the sequence came from
  a bag; the pose covariance and the twist in the child frame's axes with its covariance:
  velocity ``R^T v`` and the bias-corrected gyro rate interpolated at the epoch, see
  ``_body_twist``; for a smoothed trajectory from the smoother's marginal covariances,
  velocities and gyro biases, :func:`msf_torch.backend.window.interpolate_imu`; both
  covariances all zeros, the twist still written, when the smoother's ``covariance`` is
  off).
- with ``exports`` ``geojson`` / ``kml`` / ``gpx``: ``trajectory.geojson``,
  ``trajectory.kml`` and ``trajectory.gpx``, the estimate, the ground truth (when the
  sequence has one) and the GNSS fixes (fused and withheld) in WGS-84 longitude / latitude
  (:mod:`msf_torch.io.geo_export`), from the sequence's ENU origin ``meta["gnss_origin"]``;
  a sequence without one is refused before the run starts. The GPX points carry UTC times
  when the sequence has an absolute time origin (``geo_export.time_origin_ns``: a bag's,
  a KITTI raw drive's, ``time_origin_ns`` in a native folder's ``meta.json``).

Ctrl-C (SIGINT) during the front end or the smoother writes ``trajectory.tum`` (the epochs
completed), ``diagnostics.csv`` and ``summary.json`` (with an ``interrupted`` entry saying
where it stopped) and raises :class:`RunInterrupted`, with learned noise too
(``learning.inference.run_piecewise`` hands on the epochs of the chunks it finished).

With ``RunOptions.learned`` set, the filter's noise comes from a trained CovNet, per chunk
of windows, applied as the checkpoint's training did (``learning.inference.learned_scales``;
an IMU at a whole multiple of the training rate is averaged down to it for the network,
any other rate is refused); ``summary.json`` then has ``"noise":
"learned"`` and a ``learned`` entry (checkpoint path and sha256, mean log-variance scales,
inferred weather), else ``"noise": "config"``.
"""

from __future__ import annotations

__all__ = [
    "RunOptions",
    "RunInterrupted",
    "run_sequence",
    "run_batch",
    "write_diagnostics",
    "DEFAULT_SAMPLE",
    "BATCH_TABLE_COLUMNS",
]

import copy
import csv
import dataclasses
import json
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from msf_torch.backend.window import OutputMotion, SmootherConfig, smooth
from msf_torch.eval.metrics import ate
from msf_torch.eval.outage import labelled_outage_metrics, outage_metrics, split_gnss_outage
from msf_torch.eval.slip import slip_scores
from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import SENSORS, EskfResult, run_eskf
from msf_torch.frontend.guard import DIVERGENCE_CODES, EstimationInterrupted
from msf_torch.frontend.schedule import undisturbed_magnetometer
from msf_torch.io.atomic import atomic_write
from msf_torch.io.tum import write_tum
from msf_torch.sensors.imu_gaps import filled_stretches, interpolated_imu_samples
from msf_torch.types import GnssFixes, Sequence, Trajectory, batch_sequences, move_to

if TYPE_CHECKING:
    from msf_torch.learning.inference import LearnedModel

DEFAULT_SAMPLE = Path(__file__).resolve().parent.parent / "datasets" / "sample_slip.npz"
"""The bundled sample sequence (simulated wheeled robot with slip episodes)."""

_STATE_NAMES = [
    "px",
    "py",
    "pz",
    "vx",
    "vy",
    "vz",
    "thx",
    "thy",
    "thz",
    "bgx",
    "bgy",
    "bgz",
    "bax",
    "bay",
    "baz",
]


@dataclass
class RunOptions:
    """What ``msf run`` does beyond the filter settings.

    Attributes:
        out_dir: output folder.
        gnss_outage_s: optional (start, end) in s from the first IMU sample; fixes inside
            are withheld from the estimator and used as the reference.
        plot: write ``overview.png``.
        progress: factory ``() -> (callback(done, total), close())`` for a progress bar, or
            None.
        smooth: ``"full"`` or ``"window"`` to smooth after the front end, or None.
        smoother: the smoother's settings (default :class:`SmootherConfig()`).
        learned: a trained CovNet that sets the filter's noise, or None (the config's).
        exports: extra trajectory formats, any of ``"kitti"``, ``"rosbag2"``, ``"geojson"``,
            ``"kml"``, ``"gpx"`` (the last three need ``seq.meta["gnss_origin"]``).
        device: where the estimator runs (``"cpu"``, ``"cuda"``, ``"cuda:1"``); the results
            come back to the CPU to be scored and written.
    """

    out_dir: Path
    gnss_outage_s: tuple[float, float] | None = None
    plot: bool = True
    progress: Callable[[], tuple[Callable[[int, int], None], Callable[[], None]]] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    smooth: str | None = None
    smoother: SmootherConfig | None = None
    learned: LearnedModel | None = None
    exports: tuple[str, ...] = ()
    device: str = "cpu"


def write_diagnostics(result: EskfResult, path: Path, index: int = 0) -> None:
    """Write the per-epoch diagnostics table of sequence ``index`` as CSV.

    Columns: ``t``; the 15 error-state variances; ``slip_factor``, ``imu_gap``,
    ``divergence``; per sensor present / accepted / NIS (``wheel`` ... ``pose``, then each
    pose source ``pose:<name>`` with a pair in this sequence); ``fading_factor`` (strong
    tracking, 1 where nothing was adapted); per Sage-Husa block ``<block>_noise_sigma<i>``,
    the square roots of the estimated R's diagonal (units of the block's rows, 0 before its
    first measurement); per pose source the fault flag and Z; the online-calibration states
    and their sigmas.
    """
    keep = result.mask[index]
    t = result.t[index, keep].numpy()
    var = torch.diagonal(result.covariance[index, keep], dim1=-2, dim2=-1).numpy()
    cols = [
        t[:, None],
        var,
        result.slip_factor[index, keep].numpy()[:, None],
        result.gap[index, keep].numpy()[:, None].astype(float),
    ]
    header = ["t"] + [f"var_{n}" for n in _STATE_NAMES] + ["slip_factor", "imu_gap"]
    cols.append(_divergence(result)[index, keep].numpy()[:, None].astype(float))
    header.append("divergence")
    sources = [
        n for n in result.present if n not in SENSORS and bool(result.present[n][index].any())
    ]
    for name in [*SENSORS, *sources]:  # pose sources: those with a pair in this sequence
        cols.append(result.present[name][index, keep].numpy()[:, None].astype(float))
        cols.append(result.accepted[name][index, keep].numpy()[:, None].astype(float))
        cols.append(result.nis[name][index, keep].numpy()[:, None])
        header += [f"{name}_present", f"{name}_accepted", f"{name}_nis"]
    cols.append(result.fading_factor[index, keep].numpy()[:, None])  # 1: nothing adapted
    header.append("fading_factor")
    for name, estimate in result.noise_estimate.items():  # Sage-Husa R_hat per block
        sigma = torch.diagonal(estimate[index, keep], dim1=-2, dim2=-1).clamp_min(0.0).sqrt()
        cols.append(sigma.numpy())
        header += [f"{name}_noise_sigma{i}" for i in range(sigma.shape[-1])]
    for name, flags in result.source_fault.items():  # frontend.gating, source_fault_detection
        cols.append(flags[index, keep].numpy()[:, None].astype(float))
        cols.append(result.source_fault_z[name][index, keep].numpy()[:, None])
        header += [f"{name}_fault", f"{name}_fault_z"]
    if result.calibration is not None:  # frontend.calibration: estimate and sigma per state
        sigma = torch.diagonal(result.calibration_covariance[index, keep], dim1=-2, dim2=-1)
        cols += [result.calibration[index, keep].numpy(), sigma.sqrt().numpy()]
        header += list(result.calibration_names)
        header += [f"{name}_sigma" for name in result.calibration_names]
    table = np.hstack(cols)
    with atomic_write(path) as handle:
        handle.write(",".join(header) + "\n")
        np.savetxt(handle, table, delimiter=",", fmt="%.10g")


OUTPUT_NAMES = (
    "trajectory.tum",
    "trajectory.kitti",
    "trajectory_times.txt",
    "trajectory_rosbag2",
    "trajectory.geojson",
    "trajectory.kml",
    "trajectory.gpx",
    "diagnostics.csv",
    "overview.png",
    "summary.json",
)
"""The files and folders a run writes to its output folder (module docstring)."""

GEO_EXPORTS = ("geojson", "kml", "gpx")
"""Exports that put the trajectory on the Earth: they need the sequence's geodetic origin."""


def _output_folder(path: str | Path) -> Path:
    """The output folder, created with its parents; a path that is a file is refused."""
    out_dir = Path(path)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"output folder {out_dir} is an existing file; give a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir


def _written(options: RunOptions) -> set[str]:
    """The names of :data:`OUTPUT_NAMES` a completed run with ``options`` writes."""
    names = {"trajectory.tum", "diagnostics.csv", "summary.json"}
    if options.plot:
        names.add("overview.png")
    if "kitti" in options.exports:
        names |= {"trajectory.kitti", "trajectory_times.txt"}
    if "rosbag2" in options.exports:
        names.add("trajectory_rosbag2")
    names |= {f"trajectory.{fmt}" for fmt in GEO_EXPORTS if fmt in options.exports}
    return names


def _warn_streams_off_the_imu_clock(seq: Sequence, name: str) -> None:
    """Warn about each stream of a B = 1 sequence none of whose samples lies within the IMU's
    time span: the filter never reaches them (typically times of another clock, e.g. UNIX
    GNSS times beside IMU times since boot)."""
    imu_t = seq.imu.t[0, seq.imu.mask[0]]
    start, end = float(imu_t[0]), float(imu_t[-1])
    others = {**seq.streams(), **{f"pose:{k}": v for k, v in seq.pose_sources.items()}}
    for key, stream in others.items():
        if key == "imu":
            continue
        t = stream.t[0, stream.mask[0]]
        if t.numel() and not bool(((t >= start) & (t <= end)).any()):
            warnings.warn(
                f"sequence {name}: none of the {t.numel()} {key} samples "
                f"({float(t[0]):.3f} .. {float(t[-1]):.3f} s) lies within the IMU's "
                f"{start:.3f} .. {end:.3f} s, so the estimator ignores them: another clock? "
                "(shift the times onto the IMU's; msf nmea --t0 does that for GNSS logs)",
                stacklevel=3,
            )


def _check_geo_exports(seqs: list[Sequence], names: list[str], exports: tuple[str, ...]) -> None:
    """Refuse, before any work, a map export for a sequence without ``meta["gnss_origin"]``."""
    wanted = [fmt for fmt in GEO_EXPORTS if fmt in exports]
    if not wanted:
        return
    for seq, name in zip(seqs, names, strict=True):
        if seq.meta.get("gnss_origin") is None:
            raise ValueError(
                f"--export {','.join(wanted)}: sequence {name} has no geodetic origin for its "
                'ENU frame; a native folder keeps it in meta.json as "gnss_origin": '
                "[lat_deg, lon_deg, alt_m] (msf nmea writes it), a ROS bag's GNSS sets it"
            )


def _duration(seq: Sequence) -> float:
    t = seq.imu.t[0, seq.imu.mask[0]]
    return float(t[-1] - t[0])


def run_sequence(seq: Sequence, cfg: EskfConfig, options: RunOptions) -> dict[str, Any]:
    """Run the front end on one sequence (B = 1), write the outputs, return the summary.

    Args:
        seq: the loaded sequence.
        cfg: front-end settings.
        options: outputs and experiment switches.
    Returns:
        The summary dict (also written to ``summary.json``).
    """
    _check_geo_exports([seq], seq.names[:1], options.exports)
    _warn_streams_off_the_imu_clock(seq, seq.names[0])
    out_dir = _output_folder(options.out_dir)
    withheld = None
    if options.gnss_outage_s is not None:
        seq, withheld = split_gnss_outage(seq, *options.gnss_outage_s)
    callback, close = (None, None)
    if options.progress is not None:
        callback, close = options.progress()
    start = time.perf_counter()
    learned = None
    device = torch.device(options.device)
    work = seq.to(device)  # the estimator's copy; seq stays on the CPU for scoring and writing
    with torch.no_grad():
        if options.learned is None:
            try:
                result = run_eskf(work, cfg, progress=callback)
            except EstimationInterrupted as stop:
                if close is not None:
                    close()
                wall = time.perf_counter() - start
                _write_interrupted(seq, stop.result, out_dir, "frontend", stop.epochs_total, wall)
        else:
            from msf_torch.learning.inference import learned_scales, run_piecewise, scales_summary

            network = options.learned.model  # a copy on the device: the caller's stays put
            if next(network.parameters()).device != device:
                network = copy.deepcopy(network).to(device)
            model = dataclasses.replace(options.learned, model=network)
            scales = learned_scales(work, model, cfg)
            try:
                result = run_piecewise(
                    work, cfg, scales.log_scales, scales.window_length, scales.pose_source, callback
                )
            except EstimationInterrupted as stop:
                if close is not None:
                    close()
                wall = time.perf_counter() - start
                total = stop.epochs_total
                _write_interrupted(seq, stop.result, out_dir, "frontend", total, wall, "learned")
            learned = scales_summary(move_to(scales, "cpu"), options.learned)
    frontend_wall = time.perf_counter() - start
    if close is not None:
        close()
    smoothed = None
    if options.smooth is not None:
        callback, close = options.progress() if options.progress is not None else (None, None)
        with torch.no_grad():
            try:
                smoothed = smooth(work, result, cfg, options.smoother, options.smooth, callback)
            except KeyboardInterrupt:
                if close is not None:
                    close()
                wall = time.perf_counter() - start
                total = int(result.mask[0].sum()) - 1
                _write_interrupted(seq, result, out_dir, "smoother", total, wall)
        if close is not None:
            close()
    result, smoothed = move_to((result, smoothed), "cpu")
    trajectory = result.trajectory()
    wall = time.perf_counter() - start
    summary = _header(seq, result, wall)
    summary["device"] = str(device)
    summary["noise"] = "config" if learned is None else "learned"
    if learned is not None:
        summary["learned"] = learned
    if smoothed is not None:
        summary["frontend_wall_s"] = round(frontend_wall, 4)
        summary["smoother"] = _smoother_summary(smoothed)
    return _score_and_write(
        seq, result, trajectory, smoothed, cfg, options, out_dir, summary, withheld
    )


def _smoother_summary(smoothed: Any) -> dict[str, Any]:
    """A :class:`~msf_torch.backend.window.SmootherResult`'s figures for ``summary.json``
    (floats to 4 decimals)."""
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in smoothed.summary().items()}


BATCH_TABLE_COLUMNS = (
    "sequence",
    "source",
    "duration_s",
    "imu_samples",
    "epochs",
    "ate_rmse_m",
    "ate_max_m",
    "frontend_ate_rmse_m",
    "outage_rmse_m",
    "outage_distance_m",
    "outage_drift_pct",
    "imu_gaps",
    "slip_flagged_epochs",
    "slip_f1",
)
"""Columns of ``runs.csv`` written by :func:`run_batch` (empty where a run lacks one; with
``--smooth`` the ATE and outage columns score the smoothed trajectory and
``frontend_ate_rmse_m`` the front end's)."""


def run_batch(seqs: list[Sequence], cfg: EskfConfig, options: RunOptions) -> dict[str, Any]:
    """Run the front end on B sequences in one batched ``run_eskf`` call and write each
    sequence's outputs (as :func:`run_sequence`) to ``options.out_dir / <name>``.

    All sequences share ``cfg``; ``options.gnss_outage_s`` applies to each (seconds from its
    own first sample). With ``options.smooth`` each sequence is smoothed on its own after the
    batched front end (keyframe counts differ between sequences), as :func:`run_sequence`
    does; learned noise runs one sequence at a time (:func:`run_sequence`) and is refused
    here. ``out_dir`` also receives ``runs.csv`` (one row per sequence,
    :data:`BATCH_TABLE_COLUMNS`) and ``summary.json`` (the batch's summary). Ctrl-C stops the
    batch without partial outputs (nothing is written before every sequence is done).

    Args:
        seqs: B >= 1 loaded sequences (B = 1 each); folder names are their names, made
            unique with ``-2``, ``-3``, ... where two agree.
        cfg: front-end settings for all of them.
        options: outputs (``learned`` must be unset).
    Returns:
        The batch summary: ``sequences``, ``names``, ``out``, total ``duration_s`` and
        ``imu_samples``, ``wall_s`` (the one batched front-end run), ``realtime_factor``
        (total duration / wall), ``imu_samples_per_s``, ``device`` (where the estimator
        ran), with smoothing ``smoother_wall_s`` (all sequences' smoothers), and ``runs``
        (per sequence, the ``runs.csv`` row).
    """
    if not seqs:
        raise ValueError("run_batch: no sequences")
    if options.learned is not None:
        raise ValueError(
            "learned noise runs one sequence at a time (give one SEQUENCE, or --no-learned)"
        )
    names = _unique_names([seq.names[0] for seq in seqs])
    _check_geo_exports(seqs, names, options.exports)
    for seq, name in zip(seqs, names, strict=True):
        _warn_streams_off_the_imu_clock(seq, name)
    out_dir = _output_folder(options.out_dir)
    withheld: list[GnssFixes | None] = [None] * len(seqs)
    if options.gnss_outage_s is not None:
        split = []
        for seq, name in zip(seqs, names, strict=True):
            try:
                split.append(split_gnss_outage(seq, *options.gnss_outage_s))
            except ValueError as err:
                raise ValueError(f"sequence {name}: {err}") from None
        seqs, withheld = [s for s, _ in split], [w for _, w in split]
    callback, close = options.progress() if options.progress is not None else (None, None)
    device = torch.device(options.device)
    batch = batch_sequences(seqs).to(device)
    start = time.perf_counter()
    try:
        with torch.no_grad():
            result = run_eskf(batch, cfg, progress=callback)
    finally:
        if close is not None:
            close()
    wall = time.perf_counter() - start
    own = [result.select(index) for index in range(len(seqs))]
    smoothed: list[Any] = [None] * len(seqs)
    smoother_start = time.perf_counter()
    if options.smooth is not None:
        for index, seq in enumerate(seqs):
            callback, close = options.progress() if options.progress is not None else (None, None)
            try:
                with torch.no_grad():
                    smoothed[index] = smooth(
                        seq.to(device), own[index], cfg, options.smoother, options.smooth, callback
                    )
            finally:
                if close is not None:
                    close()
    smoother_wall = time.perf_counter() - smoother_start
    own, smoothed = move_to((own, smoothed), "cpu")
    rows = []
    for index, (seq, name) in enumerate(zip(seqs, names, strict=True)):
        (out_dir / name).mkdir(parents=True, exist_ok=True)
        summary = _header(seq, own[index], wall)
        summary["device"] = str(device)
        summary["noise"] = "config"
        summary["batch"] = {"size": len(seqs), "index": index}
        if smoothed[index] is not None:
            summary["frontend_wall_s"] = round(wall, 4)
            summary["smoother"] = _smoother_summary(smoothed[index])
        summary = _score_and_write(
            seq,
            own[index],
            own[index].trajectory(),
            smoothed[index],
            cfg,
            options,
            out_dir / name,
            summary,
            withheld[index],
        )
        row = {key: summary.get(key) for key in BATCH_TABLE_COLUMNS}
        row["slip_f1"] = summary.get("slip_detection", {}).get("f1")
        rows.append(row)
    duration = sum(row["duration_s"] for row in rows)
    samples = sum(row["imu_samples"] for row in rows)
    out = {
        "sequences": len(seqs),
        "names": names,
        "out": str(out_dir),
        "duration_s": round(duration, 3),
        "imu_samples": samples,
        "wall_s": round(wall, 4),
        "realtime_factor": round(duration / wall, 1) if wall > 0 else math.inf,
        "imu_samples_per_s": round(samples / wall) if wall > 0 else math.inf,
        "device": str(device),
    }
    if options.smooth is not None:
        out["smoother_wall_s"] = round(smoother_wall, 4)
    out["runs"] = rows
    with atomic_write(out_dir / "runs.csv", newline="") as handle:
        table = csv.DictWriter(handle, BATCH_TABLE_COLUMNS)
        table.writeheader()
        table.writerows(rows)
    with atomic_write(out_dir / "summary.json") as handle:
        json.dump(out, handle, indent=2)
        handle.write("\n")
    return out


def _unique_names(names: list[str]) -> list[str]:
    """Folder-safe, unique names: path separators replaced, repeats suffixed ``-2``, ..."""
    out, seen = [], {}
    for name in names:
        base = name.replace("/", "_").replace("\\", "_") or "sequence"
        count = seen.get(base, 0) + 1
        seen[base] = count
        out.append(base if count == 1 else f"{base}-{count}")
    return out


def _header(seq: Sequence, result: EskfResult, wall: float) -> dict[str, Any]:
    """The summary's first entries for one sequence (B = 1) and its result."""
    duration = _duration(seq)
    return {
        "sequence": seq.names[0],
        "source": str(seq.meta.get("source", "")),
        "duration_s": round(duration, 3),
        "imu_samples": int(seq.imu.mask[0].sum()),
        "epochs": int(result.mask[0].sum()),
        "wall_s": round(wall, 4),
        "realtime_factor": round(duration / wall, 1) if wall > 0 else math.inf,
    }


def _magnetometer_summary(
    seq: Sequence, cfg: EskfConfig, counts: dict[str, Any] | None
) -> dict[str, int]:
    """``magnetometer_readings`` of sequence 0 (B = 1) and how many of them the front end
    leaves out as disturbed (``frontend.schedule.undisturbed_magnetometer``: magnitude
    and gyro consistency; the dip test acts in the filter and counts as rejected); empty
    without a magnetometer. Warns when over half of at least 20 readings are disturbed, or
    the filter rejects over half of at least 10 it is given (``counts``: the block's
    present / accepted counts): a wrong reference (field magnitude, inclination,
    declination) or calibration leaves a magnetometer out without another sign."""
    stream = seq.magnetometer
    if stream is None or not bool(stream.mask[0].any()):
        return {}
    keep = seq.imu.mask[0]
    imu_t = seq.imu.t[0, keep].detach().cpu().numpy()
    gyro = seq.imu.gyro[0, keep].detach().cpu().numpy() - np.asarray(cfg.init_gyro_bias_radps)
    index = np.flatnonzero(stream.mask[0].cpu().numpy())
    times = stream.t[0].detach().cpu().numpy()[index]
    kept, _ = undisturbed_magnetometer(stream, 0, cfg, imu_t, gyro, times, index)
    disturbed = int(index.size - kept.size)
    if index.size >= 20 and disturbed > 0.5 * index.size:
        warnings.warn(
            f"{seq.names[0]}: {disturbed} of {index.size} magnetometer readings are left out as "
            "disturbed (magnitude or turn against the gyro): check magnetometer_field_uT (the "
            "value msf magcal fits, not the world model's total field; 0 = the run's median), "
            "the hard and soft iron and the units (uT)",
            stacklevel=2,
        )
    if counts is not None and counts["present"][0] >= 10:
        present, accepted = counts["present"][0], counts["accepted"][0]
        if accepted < 0.5 * present:
            warnings.warn(
                f"{seq.names[0]}: the filter accepted {accepted} of {present} magnetometer "
                "headings: check magnetometer_declination_rad, magnetometer_inclination_rad "
                "(0 = the run's median dip) and the calibration",
                stacklevel=2,
            )
    return {"magnetometer_readings": int(index.size), "magnetometer_disturbed": disturbed}


def _innovation_summary(seq: Sequence, result: EskfResult) -> dict[str, dict[str, float]]:
    """Per measurement block of sequence 0 (B = 1) with accepted measurements: their mean
    NIS, the block's rows (what a consistent filter's mean NIS is) and the ratio. Warns for
    a block of at least 10 whose ratio is above 3: innovations that large against the
    modelled spread mean a noise set too small for the run (an over-confident filter),
    which ``msf tune`` fits (docs/tuning.md)."""
    out = {}
    for name, (mean, count) in result.accepted_nis().items():
        rows = result.block_rows[name]
        out[name] = {"mean_nis": round(mean, 3), "rows": rows, "ratio": round(mean / rows, 3)}
        if count >= 10 and mean > 3.0 * rows:
            warnings.warn(
                f"{seq.names[0]}: the {name} innovations are {mean / rows:.1f}x the spread the "
                f"filter models (mean NIS {mean:.3g} for {rows} rows over {count} accepted): "
                "its noise looks too small for this run; msf tune fits the noise to the run "
                "(docs/tuning.md)",
                stacklevel=2,
            )
    return out


def _score_and_write(
    seq: Sequence,
    result: EskfResult,
    trajectory: Trajectory,
    smoothed: Any,
    cfg: EskfConfig,
    options: RunOptions,
    out_dir: Path,
    summary: dict[str, Any],
    withheld: GnssFixes | None,
) -> dict[str, Any]:
    """Add the counts and scores of one sequence (B = 1) to ``summary`` and write its
    outputs to ``out_dir``; returns the summary."""
    estimate = _single(trajectory) if smoothed is None else smoothed.output
    counts = result.counts()
    summary["measurements"] = {
        k: {n: v[0] for n, v in c.items()} for k, c in counts.items() if c["present"][0] > 0
    }
    summary["innovations"] = _innovation_summary(seq, result)
    dropped = seq.meta.get("dropped_nonfinite")
    if dropped:
        summary["dropped_nonfinite"] = dropped
    summary["imu_gaps"] = int((result.gap[0] & result.mask[0]).sum())
    summary["imu_filled_stretches"] = _filled_summary(seq, cfg)
    summary.update(_fault_summary(result))
    summary.update(_calibration_summary(result))
    summary.update(_magnetometer_summary(seq, cfg, counts.get("magnetometer")))
    scored = [("", estimate)] + ([] if smoothed is None else [("frontend_", _single(trajectory))])
    if seq.ground_truth is not None and bool(seq.ground_truth.mask.any()):
        for prefix, traj in scored:
            stats = ate(traj, seq.ground_truth, align="none", max_dt=0.02)
            summary[f"{prefix}ate_rmse_m"] = round(float(stats["rmse"]), 4)
            summary[f"{prefix}ate_max_m"] = round(float(stats["max"]), 4)
    if withheld is not None:
        summary["gnss_outage_s"] = list(options.gnss_outage_s)
        for prefix, traj in scored:
            metrics = outage_metrics(traj, withheld)
            summary.update(
                {
                    f"{prefix}{k}": round(v, 4) if isinstance(v, float) else v
                    for k, v in metrics.items()
                }
            )
    labelled = _labelled_outages(seq, scored)
    if labelled:
        summary["labelled_gnss_outages"] = labelled
    aiding = [k for k in counts if k in ("gnss", "pose") or k.startswith("pose:")]
    summary["absolute_aiding"] = any(counts[k]["present"][0] > 0 for k in aiding)
    if result.present["wheel"].any():
        wheel_epochs = result.present["wheel"][0] & result.mask[0]
        factor = result.slip_factor[0, wheel_epochs]
        flagged = factor < cfg.slip_flag_below
        summary["slip_flagged_epochs"] = int(flagged.sum())
        summary["slip_factor_min"] = round(float(factor.min()), 4)
        if "slip" in seq.labels and cfg.slip_detection:
            scores = slip_scores(result.t[0, wheel_epochs], flagged, seq.labels["slip"][0])
            summary["slip_detection"] = {
                k: round(v, 4) if isinstance(v, float) else v for k, v in scores.items()
            }
    summary["slip_detection_enabled"] = bool(cfg.slip_detection) and bool(
        result.present["wheel"].any()
    )
    write_tum(estimate, out_dir / "trajectory.tum")
    if smoothed is not None:
        motion = smoothed.output_motion
    else:
        keep = result.mask[0]
        motion = OutputMotion(
            result.velocity[:1, keep], result.gyro_bias[:1, keep], result.covariance[:1, keep]
        )
    _export(options.exports, out_dir, seq, estimate, motion, cfg, withheld)
    write_diagnostics(result, out_dir / "diagnostics.csv")
    if options.plot:
        _plot(out_dir / "overview.png", seq, estimate, result, withheld, options, summary)
    stale = [n for n in OUTPUT_NAMES if n not in _written(options) and (out_dir / n).exists()]
    if stale:
        summary["stale_outputs"] = stale
    with atomic_write(out_dir / "summary.json") as handle:
        json.dump(summary, handle, indent=2)
        handle.write("\n")
    return summary


def _labelled_outages(seq: Sequence, scored: list[tuple[str, Trajectory]]) -> list[dict]:
    """Each labelled GNSS outage (``labels["gnss_outage"]``, B = 1) scored against the
    ground truth: start / end in s from the first IMU sample, then per scored trajectory
    its ``eval.outage.labelled_outage_metrics`` (keys prefixed as in ``scored``). Outages
    with under 2 truth samples, or no ground truth, give nothing."""
    intervals = seq.labels.get("gnss_outage")
    truth = seq.ground_truth
    if intervals is None or truth is None or not bool(truth.mask.any()):
        return []
    origin = float(seq.start_time[0])
    out = []
    for start, end in intervals[0].tolist():
        if not (math.isfinite(start) and math.isfinite(end)):
            continue
        entry: dict[str, Any] = {
            "start_s": round(start - origin, 3),
            "end_s": round(end - origin, 3),
        }
        try:
            for prefix, traj in scored:
                metrics = labelled_outage_metrics(traj, truth, start, end)
                entry.update(
                    {
                        f"{prefix}{k}": round(v, 4) if isinstance(v, float) else v
                        for k, v in metrics.items()
                    }
                )
        except ValueError:
            continue
        out.append(entry)
    return out


def _export(
    formats: tuple[str, ...],
    out_dir: Path,
    seq: Sequence,
    estimate: Trajectory,
    motion: OutputMotion,
    cfg: EskfConfig,
    withheld: GnssFixes | None = None,
) -> None:
    """Write ``estimate`` in the extra formats (see the module docstring); ``motion`` at
    its epochs gives the rosbag2 twist and covariances; the map exports show ``withheld``
    GNSS fixes beside the fused ones."""
    if any(fmt in formats for fmt in GEO_EXPORTS):
        from msf_torch.io.geo_export import time_origin_ns, write_geojson, write_gpx, write_kml

        tracks = {"estimate": estimate}
        truth = seq.ground_truth
        if truth is not None and bool(truth.mask.any()):
            tracks["ground truth"] = truth
        fixes = {"GNSS fixes": seq.gnss, "withheld GNSS fixes": withheld}
        fixes = {k: v for k, v in fixes.items() if v is not None}
        origin = seq.meta["gnss_origin"]
        if "geojson" in formats:
            write_geojson(out_dir / "trajectory.geojson", origin, tracks, fixes)
        if "kml" in formats:
            write_kml(out_dir / "trajectory.kml", origin, tracks, fixes, name=seq.names[0])
        if "gpx" in formats:
            write_gpx(
                out_dir / "trajectory.gpx",
                origin,
                tracks,
                fixes,
                time_origin=time_origin_ns(seq.meta),
                name=seq.names[0],
            )
    if "kitti" in formats:
        from msf_torch.io.kitti_poses import write_kitti_poses

        write_kitti_poses(estimate, out_dir / "trajectory.kitti", out_dir / "trajectory_times.txt")
    if "rosbag2" in formats:
        from msf_torch.io.rosbag import write_odometry_rosbag2

        covariance = None
        if motion.covariance is not None:
            rows = torch.tensor([0, 1, 2, 6, 7, 8])
            covariance = motion.covariance[..., rows[:, None], rows]
        twist, twist_covariance = _body_twist(seq, estimate, motion, cfg.gyro_noise_density)
        velocity, angular = motion.velocity, twist[..., 3:]
        child = str(seq.meta.get("body_frame") or "base_link")
        imu_frame = seq.meta.get("imu_frame")
        if imu_frame and imu_frame != child:
            # the estimate is the body axes at the IMU's origin: written as the IMU frame's
            # own pose (R_world_imu = R_world_body R_body_imu), which tf relates to the body
            body_imu = seq.meta["body_imu_rotation"]
            estimate, covariance = _as_imu_frame(estimate, covariance, body_imu)
            to_imu = torch.as_tensor(body_imu, dtype=angular.dtype).mT
            angular = angular @ to_imu.mT
            if twist_covariance is not None:
                both = torch.block_diag(to_imu, to_imu)
                twist_covariance = both @ twist_covariance @ both.mT
            child = str(imu_frame)
        write_odometry_rosbag2(
            estimate,
            out_dir / "trajectory_rosbag2",
            child_frame_id=child,
            time_origin_ns=int(seq.meta.get("time_origin_ns", 0)),
            covariance=covariance,
            velocity=velocity,
            angular_velocity=angular,
            twist_covariance=twist_covariance,
        )


def _body_twist(
    seq: Sequence, estimate: Trajectory, motion: OutputMotion, gyro_noise_density: float
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Body-axes twist at the epochs of a B = 1 estimate, and its covariance.

    ``v_b = R^T v`` (m/s); ``w_b = w(t) - b_g`` (rad/s), ``w(t)`` the gyro interpolated
    linearly between the IMU samples around the epoch time (the nearest end sample outside
    them). With the error state ``[dp, dv, dtheta, db_g, db_a]`` (``R = R_hat Exp(dtheta)``,
    ``b = b_hat + db``), ``dv_b = R^T dv + [v_b]x dtheta`` and ``dw_b = -db_g - n_g``, so the
    covariance is ``J P J^T`` plus one gyro sample's white noise
    ``gyro_noise_density^2 x IMU rate`` on the rate block.

    Args:
        seq: the sequence the estimate was made from (B = 1).
        estimate: (1, N) poses (every epoch real).
        motion: velocity, gyro bias and covariance at those epochs.
        gyro_noise_density: rad/s/sqrt(Hz).

    Returns:
        twist (1, N, 6) ``[v_b, w_b]`` and covariance (1, N, 6, 6), or None when
        ``motion`` has no covariance.
    """
    from msf_torch.geometry.quaternion import quat_to_matrix
    from msf_torch.geometry.so3 import hat

    rotation = quat_to_matrix(estimate.quaternion[:1])
    linear = (rotation.mT @ motion.velocity[..., None])[..., 0]
    imu = seq.imu.compact()
    times = estimate.t[0].cpu().numpy()
    stamps = imu.t[0].cpu().numpy()
    gyro = imu.gyro[0].cpu().numpy()
    sampled = np.stack([np.interp(times, stamps, gyro[:, axis]) for axis in range(3)], -1)
    rate = torch.as_tensor(sampled, dtype=linear.dtype, device=linear.device)[None]
    angular = rate - motion.gyro_bias
    if motion.covariance is None:
        return torch.cat([linear, angular], -1), None
    epochs = linear.shape[1]
    jacobian = torch.zeros(1, epochs, 6, 15, dtype=linear.dtype, device=linear.device)
    jacobian[..., :3, 3:6] = rotation.mT
    jacobian[..., :3, 6:9] = hat(linear)
    jacobian[..., 3:, 9:12] = -torch.eye(3, dtype=linear.dtype, device=linear.device)
    covariance = jacobian @ motion.covariance @ jacobian.mT
    sample_variance = gyro_noise_density**2 * float(imu.median_rate_hz()[0])
    covariance[..., 3:, 3:] += sample_variance * torch.eye(3, dtype=linear.dtype)
    return torch.cat([linear, angular], -1), covariance


def _as_imu_frame(
    estimate: Trajectory, covariance: torch.Tensor | None, body_imu_rotation: Any
) -> tuple[Trajectory, torch.Tensor | None]:
    """The estimate (body axes, origin at the IMU) as the IMU frame's pose.

    Orientation ``R_world_imu = R_world_body R_body_imu``; the position is the IMU's
    already; the covariance (1, N, 6, 6) over ``[dp (world), dtheta (body)]`` gets its
    attitude rows and columns in IMU axes (``dtheta_imu = R_body_imu^T dtheta_body``). The
    world velocity is the IMU origin's already.
    """
    from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix

    body_imu = torch.as_tensor(body_imu_rotation, dtype=estimate.quaternion.dtype)
    rotation = quat_to_matrix(estimate.quaternion) @ body_imu
    moved = dataclasses.replace(estimate, quaternion=matrix_to_quat(rotation))
    if covariance is None:
        return moved, None
    to_imu = torch.eye(6, dtype=covariance.dtype)
    to_imu[3:, 3:] = body_imu.to(covariance.dtype).mT
    return moved, to_imu @ covariance @ to_imu.mT


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) stopped :func:`run_sequence`; partial outputs were written first.

    ``trajectory.tum`` holds the front end's poses up to the last completed epoch (the whole
    front-end trajectory when the smoother was interrupted), ``diagnostics.csv`` the same
    epochs, ``summary.json`` the summary below.

    Attributes:
        summary: the run summary with an ``"interrupted"`` entry: ``stage`` (``"frontend"``
            or ``"smoother"``), ``epochs_done`` and ``epochs_total`` (front-end epochs),
            ``t_s`` (time of the last completed epoch, s, the sequence's clock) and
            ``t_from_start_s`` (the same from the first IMU sample).
    """

    def __init__(self, summary: dict[str, Any]) -> None:
        stop = summary["interrupted"]
        super().__init__(
            f"interrupted in the {stop['stage']} at t = {stop['t_s']:.6f} s "
            f"(epoch {stop['epochs_done']} of {stop['epochs_total']})"
        )
        self.summary = summary


def _divergence(result: EskfResult) -> torch.Tensor:
    """(B, E + 1) divergence codes; zeros for a result assembled without them (the learned
    path's chunk concatenation)."""
    if result.divergence is None:
        return torch.zeros(result.mask.shape, dtype=torch.long)
    return result.divergence


def _filled_summary(seq: Sequence, cfg: EskfConfig) -> dict[str, Any]:
    """Stretches of the IMU log filled in by linear interpolation (``sensors.imu_gaps``),
    which the front end bridged as gaps: ``{"count", "seconds", "start_s"}`` (start times
    from the first IMU sample; ``count`` 0 when the check is off)."""
    keep = seq.imu.mask[0]
    t = seq.imu.t[0, keep]
    flags = interpolated_imu_samples(
        t, seq.imu.gyro[0, keep], seq.imu.accel[0, keep], cfg.imu_interpolated_min_samples
    )
    first, end = filled_stretches(flags)
    times = t.detach().cpu().numpy()
    return {
        "count": int(first.size),
        "seconds": round(float((times[end] - times[first - 1]).sum()), 3),
        "start_s": [round(float(times[k - 1] - times[0]), 3) for k in first],
    }


def _calibration_summary(result: EskfResult) -> dict[str, Any]:
    """Summary entries of online calibration (sequence 0): final estimate, 1-sigma, variance
    ratio and observability flag per state; empty when off."""
    if result.calibration is None:
        return {}
    last = int(torch.nonzero(result.mask[0])[-1])
    names = result.calibration_names
    sigma = torch.diagonal(result.calibration_covariance[0, last]).sqrt()
    ratio = result.calibration_variance_ratio[0, last]
    return {
        "calibration": {n: float(result.calibration[0, last, k]) for k, n in enumerate(names)},
        "calibration_sigma": {n: float(sigma[k]) for k, n in enumerate(names)},
        "calibration_variance_ratio": {n: round(float(ratio[k]), 6) for k, n in enumerate(names)},
        "calibration_observable": {n: bool(result.calibration_observable[n][0]) for n in names},
    }


def _fault_summary(result: EskfResult) -> dict[str, Any]:
    """Summary entries of the fault guards (sequence 0): divergence resets (count, first
    times, per code) and samples the filter skipped; empty when there were none."""
    out: dict[str, Any] = {}
    keep = result.mask[0]
    codes = _divergence(result)[0, keep]
    diverged = codes != 0
    if bool(diverged.any()):
        out["divergence_resets"] = int(diverged.sum())
        out["divergence_first_t_s"] = [round(float(x), 6) for x in result.t[0, keep][diverged][:5]]
        out["divergence_causes"] = {
            name: int(((codes & bit) != 0).sum())
            for bit, name in DIVERGENCE_CODES.items()
            if bool(((codes & bit) != 0).any())
        }
    skipped = {k: int(v[0]) for k, v in result.dropped_samples.items() if int(v[0])}
    if skipped:
        out["estimator_skipped_samples"] = skipped
    return out


def _write_interrupted(
    seq: Sequence,
    result: EskfResult,
    out_dir: Path,
    stage: str,
    epochs_total: int,
    wall: float,
    noise: str = "config",
) -> None:
    """Write the partial outputs of an interrupted run (``noise``: the summary's ``"config"``
    or ``"learned"``), then raise :class:`RunInterrupted`."""
    result = move_to(result, "cpu")
    done = int(result.mask[0].sum()) - 1
    t_stop = float(result.t[0, done])
    summary: dict[str, Any] = {
        "sequence": seq.names[0],
        "source": str(seq.meta.get("source", "")),
        "duration_s": round(_duration(seq), 3),
        "imu_samples": int(seq.imu.mask[0].sum()),
        "epochs": done + 1,
        "wall_s": round(wall, 4),
        "noise": noise,
        "interrupted": {
            "stage": stage,
            "epochs_done": done,
            "epochs_total": epochs_total,
            "t_s": round(t_stop, 6),
            "t_from_start_s": round(t_stop - float(result.t[0, 0]), 6),
        },
        **_fault_summary(result),
    }
    write_tum(_single(result.trajectory()), out_dir / "trajectory.tum")
    write_diagnostics(result, out_dir / "diagnostics.csv")
    with atomic_write(out_dir / "summary.json") as handle:
        json.dump(summary, handle, indent=2)
        handle.write("\n")
    raise RunInterrupted(summary)


def _single(traj: Trajectory) -> Trajectory:
    return traj.select(0).compact()


def _plot(path, seq, trajectory, result, withheld, options, summary) -> None:
    from msf_torch.eval.outage import interpolate_positions
    from msf_torch.eval.plots import overview_figure
    from msf_torch.types import Trajectory as Traj

    est = _single(trajectory)
    reference = None
    reference_label = "ground truth"
    if seq.ground_truth is not None:
        reference = seq.ground_truth
    elif seq.gnss is not None or withheld is not None:
        streams = [s for s in (seq.gnss, withheld) if s is not None]
        reference_label = "GNSS fixes"
        t = torch.cat([s.t[0, s.mask[0]] for s in streams])
        p = torch.cat([s.position[0, s.mask[0]] for s in streams])
        order = torch.argsort(t)
        quat = torch.zeros(t.numel(), 4, dtype=t.dtype)
        quat[:, 0] = 1.0
        reference = Traj(
            t=t[order][None],
            position=p[order][None],
            quaternion=quat[None],
            mask=torch.ones(1, t.numel(), dtype=torch.bool),
        )
    error_t = error = None
    if reference is not None:
        # errors at the reference's own times, the estimate interpolated (no alignment:
        # the estimator's world frame is the reference's)
        ref_t = reference.t[0, reference.mask[0]]
        inside = (ref_t >= est.t[0, 0]) & (ref_t <= est.t[0, -1])
        error_t = ref_t[inside]
        error = (
            interpolate_positions(est, error_t) - reference.position[0, reference.mask[0]][inside]
        ).norm(dim=-1)
    wheel = result.present["wheel"][0] & result.mask[0]
    slip_t = result.t[0, wheel] if wheel.any() else None
    slip = result.slip_factor[0, wheel] if wheel.any() else None
    outage = None
    if options.gnss_outage_s is not None:
        t0 = float(seq.start_time[0])
        outage = (t0 + options.gnss_outage_s[0], t0 + options.gnss_outage_s[1])
    overview_figure(
        path,
        est,
        reference,
        error_t=error_t,
        error=error,
        slip_t=slip_t,
        slip=slip,
        outage=outage,
        title=f"{summary['sequence']} ({summary.get('noise', 'config')} noise)",
        reference_label=reference_label,
    )
