"""Per-window CovNet inputs of a run (no Lightning import: ``msf run`` uses it).

:func:`run_features` cuts a B = 1 sequence into W windows of L IMU samples and gives the
:class:`~msf_torch.learning.covnet.CovNet` inputs of each (see
:mod:`msf_torch.learning.data` for the fields); :mod:`msf_torch.learning.data` batches them
for training, :mod:`msf_torch.learning.inference` feeds them to a trained network.
"""

from __future__ import annotations

__all__ = ["RunFeatures", "run_features", "reference_filter", "pose_source_of"]

from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfResult, run_eskf
from msf_torch.learning.covnet import RESIDUAL_FEATURES
from msf_torch.types import Sequence

_DROPOUT = RESIDUAL_FEATURES.index("dropout_fraction")
_INNOVATION = [RESIDUAL_FEATURES.index(k) for k in ("nis_per_dof", "nis_max_per_dof")]
_REJECTED = RESIDUAL_FEATURES.index("rejected_fraction")
_NIS_CLIP = 1.0e4  # NIS / dof beyond this (a 1 km jump) carries no more information


@dataclass
class RunFeatures:
    """CovNet inputs of one run (B dropped), W windows of L IMU samples.

    Attributes:
        imu: (W, L, 6) gyro rad/s, accel m/s^2.
        wheel: (W, L, 2) rim speeds, m/s.
        wheel_present: (W, L) bool.
        residual_stats: (W, S, 4) :data:`~msf_torch.learning.covnet.RESIDUAL_FEATURES`.
        weather: (W,) int64 weather class index (``len(weather_classes)`` = unknown).
    """

    imu: torch.Tensor
    wheel: torch.Tensor
    wheel_present: torch.Tensor
    residual_stats: torch.Tensor
    weather: torch.Tensor


def pose_source_of(seq: Sequence) -> str | None:
    """The source name of a B = 1 sequence's pose stream (simulator meta), or None."""
    if seq.poses is None or not bool(seq.poses.mask.any()):
        return None
    return seq.meta.get("weather", {}).get("pose_source") or "vo"


def _dropout(t_stream: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Fraction (W,) of a stream's expected samples missing around windows ``[start, end)`` s.

    The count is taken over the window widened (about its centre) to at least two of the
    stream's median sample intervals, so that a slow stream (GNSS at 1 Hz in 0.5 s windows)
    does not read as alternately present and absent.
    """
    if t_stream.size < 2:
        return np.ones(starts.shape)
    interval = max(float(np.median(np.diff(t_stream))), 1e-9)
    centre, half = 0.5 * (starts + ends), np.maximum(0.5 * (ends - starts), interval)
    lo, hi = centre - half, centre + half
    count = np.searchsorted(t_stream, hi, side="left") - np.searchsorted(t_stream, lo, side="left")
    return np.clip(1.0 - count / (2.0 * half / interval), 0.0, 1.0)


def _innovation_stats(
    result: EskfResult, cfg: EskfConfig, name: str, starts: np.ndarray, ends: np.ndarray
) -> np.ndarray:
    """(W, 3) ``[nis_per_dof, nis_max_per_dof, rejected_fraction]`` of one source over the
    windows ``[start, end)`` s from a B = 1 filter result (zeros where it has no measurement)."""
    key = name if name == "gnss" else f"pose:{name}"
    out = np.zeros((starts.size, 3))
    if key not in result.present:
        return out
    dof = 3 if name == "gnss" or not cfg.pose_source_rate_update else 6
    present = result.present[key][0].numpy()
    t = result.t[0].numpy()[present]
    nis = np.minimum(result.nis[key][0].numpy()[present] / dof, _NIS_CLIP)
    rejected = ~result.accepted[key][0].numpy()[present]
    lo, hi = np.searchsorted(t, starts, "left"), np.searchsorted(t, ends, "left")
    for w in np.nonzero(hi > lo)[0]:
        part = slice(lo[w], hi[w])
        out[w] = nis[part].mean(), nis[part].max(), rejected[part].mean()
    return out


def reference_filter(seq: Sequence, cfg: EskfConfig) -> EskfResult:
    """The filter over a B = 1 sequence with the configured noise, no gradient: the pass
    whose innovations :func:`run_features` summarises."""
    with torch.no_grad():
        return run_eskf(seq, cfg)


def run_features(
    seq: Sequence,
    window_length: int,
    pose_sources: tuple[str, ...],
    weather_classes: tuple[str, ...],
    cfg: EskfConfig | None = None,
    wheel_hold_s: float = 0.2,
) -> RunFeatures:
    """Per-window CovNet inputs of a B = 1 sequence (see the module docstring).

    Args:
        seq: one run (B = 1) with at least ``window_length + 1`` IMU samples.
        window_length: L, IMU samples per window.
        pose_sources: the S sources of ``CovNetConfig.pose_sources``.
        weather_classes: ``CovNetConfig.weather_classes``.
        cfg: filter settings of the reference pass (:func:`reference_filter`) that gives the
            innovation features; None leaves them zero (only the dropout fraction is set).
        wheel_hold_s: a wheel reading counts as present for this long after its stamp, s.

    Returns:
        :class:`RunFeatures` with W = ``(N_imu - 1) // L`` windows, float32 signals, on the
        CPU whatever ``seq``'s device (the windowing and statistics run in numpy, the
        reference pass on the CPU copy).

    Raises:
        ValueError: the run is too short for one window (the message names it).
    """
    seq = seq.to("cpu")
    imu = seq.imu.compact()
    t = imu.t[0].numpy()
    windows = (t.size - 1) // window_length
    if windows < 1:
        raise ValueError(
            f"run '{seq.names[0]}': {t.size} IMU samples, need > {window_length} for one window"
        )
    used = windows * window_length
    t_used = t[:used]
    signals = torch.cat((imu.gyro[0, :used], imu.accel[0, :used]), -1).float()
    wheel = torch.zeros(used, 2, device="cpu")
    present = torch.zeros(used, dtype=torch.bool, device="cpu")
    if seq.wheel is not None and bool(seq.wheel.mask.any()):
        wh = seq.wheel.compact()
        t_w = wh.t[0].numpy()
        last = np.searchsorted(t_w, t_used, side="right") - 1
        valid = last >= 0
        held = np.clip(last, 0, None)
        speeds = torch.stack((wh.left_speed[0], wh.right_speed[0]), -1).float()
        wheel = speeds[torch.from_numpy(held)] * torch.from_numpy(valid)[:, None]
        present = torch.from_numpy(valid & (t_used - t_w[held] <= wheel_hold_s))
    starts, ends = t[0:used:window_length], t[window_length : used + 1 : window_length]
    stats = torch.zeros(windows, len(pose_sources), len(RESIDUAL_FEATURES), device="cpu")
    streams = {"gnss": seq.gnss, **seq.pose_sources}
    source = pose_source_of(seq)
    if source is not None:
        streams.setdefault(source, seq.poses)
    reference = None if cfg is None else reference_filter(seq, cfg)
    for s, name in enumerate(pose_sources):
        stream = streams.get(name)
        if stream is None or not bool(stream.mask.any()):
            stats[:, s, _DROPOUT] = 1.0
            continue
        t_s = stream.compact().t[0].numpy()
        stats[:, s, _DROPOUT] = torch.from_numpy(_dropout(t_s, starts, ends)).float()
        if reference is not None:
            innovation = _innovation_stats(reference, cfg, name, starts, ends)
            stats[:, s, _INNOVATION] = torch.from_numpy(innovation[:, :2]).float()
            stats[:, s, _REJECTED] = torch.from_numpy(innovation[:, 2]).float()
    centres = 0.5 * (starts + ends)
    weather = np.full(windows, len(weather_classes), dtype=np.int64)
    for k, name in enumerate(weather_classes):
        intervals = seq.labels.get(f"weather:{name}")
        if intervals is None:
            continue
        for lo, hi in intervals[0].numpy():
            if np.isfinite(lo):
                weather[(centres >= lo) & (centres <= hi)] = k
    shape = (windows, window_length)
    return RunFeatures(
        imu=signals.reshape(*shape, 6),
        wheel=wheel.reshape(*shape, 2),
        wheel_present=present.reshape(shape),
        residual_stats=stats,
        weather=torch.from_numpy(weather),
    )
