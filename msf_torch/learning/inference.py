"""Run the filter with a trained CovNet's noise (``msf run``, ``benchmarks/learned.py``).

The network sees the sequence window by window (:func:`~msf_torch.learning.features.run_features`,
``CovNetConfig.window_length`` IMU samples each), as in training. Its log-variance scales
(fusion weights folded in, :func:`~msf_torch.learning.covnet.apply_fusion_weights`) are
averaged per chunk of ``chunk_windows`` windows (``granularity="chunk"``) or over the whole
run (``"run"``), exactly as :class:`~msf_torch.learning.module.CovNetModule` does with its
``noise_granularity``. :func:`run_piecewise` then runs the ESKF chunk by chunk, each chunk
with its own :func:`~msf_torch.learning.covnet.scaled_noise` and pose-stream covariance
scale, starting from the previous chunk's last state and covariance (the training's chunking,
without the gradient truncation that only matters for training).

The checkpoint does not store the training's chunking: :data:`DEFAULT_CHUNK_WINDOWS` matches
``training/configs/default.yaml`` (``chunk_windows: 10``, ``noise_granularity: chunk``).
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_CHECKPOINT",
    "DEFAULT_CHUNK_WINDOWS",
    "LearnedModel",
    "WindowScales",
    "load_learned",
    "window_scales",
    "run_piecewise",
    "scales_summary",
]

import dataclasses
import hashlib
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.learning.covnet import (
    LOG_SCALE_SENSORS,
    CovNet,
    apply_fusion_weights,
    load_checkpoint,
    scaled_noise,
    scaled_pose_covariance,
)
from msf_torch.learning.features import pose_source_of, run_features
from msf_torch.types import NavState, Sequence

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parent.parent.parent / "checkpoints" / "covnet_default.pt"
)
"""The shipped network (``msf run`` uses it when the file exists)."""

DEFAULT_CHUNK_WINDOWS = 10
"""Windows per noise chunk, as in ``training/configs/default.yaml``."""


@dataclass
class LearnedModel:
    """A loaded CovNet and where it came from.

    Attributes:
        model: the network, eval mode, CPU.
        path: the checkpoint file.
        sha256: hex digest of the file's bytes.
    """

    model: CovNet
    path: Path
    sha256: str


@dataclass
class WindowScales:
    """Per-window noise of one run (B = 1).

    Attributes:
        log_scales: (W, 7) effective log-variance scales (:data:`LOG_SCALE_SENSORS`), already
            averaged per chunk or per run, float64.
        window_length: L, IMU samples per window.
        pose_source: the source of ``Sequence.poses`` whose log scale its covariances take.
        chunk_windows: windows per chunk the scales were averaged over (W for ``"run"``).
        labels: (W,) weather label index per window (``CovNetConfig.unknown_weather`` where
            unlabelled).
        from_labels: the network was conditioned on the labels (where present).
        inferred: (W,) argmax of the weather head.
    """

    log_scales: torch.Tensor
    window_length: int
    pose_source: str | None
    chunk_windows: int
    labels: torch.Tensor
    from_labels: bool
    inferred: torch.Tensor


def load_learned(path: str | Path) -> LearnedModel:
    """Load a CovNet checkpoint (``torch.load(weights_only=True)``) and hash it.

    Raises:
        FileNotFoundError: the file does not exist (the message names it).
        ValueError: the file is not a readable CovNet checkpoint (the message names it).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"CovNet checkpoint {path}: no such file")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    try:
        model = load_checkpoint(path)
    except (RuntimeError, pickle.UnpicklingError, EOFError, KeyError, TypeError) as err:
        raise ValueError(f"CovNet checkpoint {path}: cannot be read ({err})") from err
    return LearnedModel(model, path, digest)


def window_scales(
    seq: Sequence,
    model: CovNet,
    cfg: EskfConfig | None,
    chunk_windows: int = DEFAULT_CHUNK_WINDOWS,
    granularity: Literal["chunk", "run"] = "chunk",
    use_labels: bool = True,
) -> WindowScales:
    """The network's noise per window of a B = 1 sequence.

    Args:
        seq: one run (B = 1).
        model: the CovNet.
        cfg: filter settings of the reference pass whose innovations feed the network
            (:func:`~msf_torch.learning.features.run_features`; the base noise the learned
            scales multiply); None leaves the innovation features zero.
        chunk_windows: windows per chunk (``granularity="chunk"``).
        granularity: ``"chunk"``: scales averaged over each chunk; ``"run"``: over the run.
        use_labels: condition on the ``weather:<c>`` labels where present (otherwise, and
            where a window has no label, on the network's own weather head).

    Raises:
        ValueError: the run is shorter than one window, or ``chunk_windows < 1``.
    """
    if chunk_windows < 1:
        raise ValueError(f"chunk_windows must be >= 1, got {chunk_windows}")
    net = model.config
    features = run_features(seq, net.window_length, net.pose_sources, net.weather_classes, cfg)
    labels = features.weather
    weather = labels if use_labels else torch.full_like(labels, net.unknown_weather)
    with torch.no_grad():
        out = model(
            features.imu, features.wheel, features.wheel_present, features.residual_stats, weather
        )
        scales = apply_fusion_weights(out.log_scales, out.fusion_weights, net.pose_sources)
    scales = scales.double()
    windows = scales.shape[0]
    step = chunk_windows if granularity == "chunk" else windows
    for w0 in range(0, windows, step):
        scales[w0 : w0 + step] = scales[w0 : w0 + step].mean(0)
    return WindowScales(
        log_scales=scales,
        window_length=net.window_length,
        pose_source=_pose_source(seq),
        chunk_windows=step,
        labels=labels,
        from_labels=use_labels and bool((labels != net.unknown_weather).any()),
        inferred=out.weather_logits.argmax(-1),
    )


def _pose_source(seq: Sequence) -> str | None:
    """The source of a B = 1 sequence's ``poses`` stream: the simulator's metadata, else the
    named stream of ``Sequence.pose_sources`` it equals (files keep no metadata), else
    :func:`~msf_torch.learning.features.run_features`' default."""
    if seq.poses is not None and "weather" not in seq.meta:
        for name, stream in seq.pose_sources.items():
            if stream.t.shape == seq.poses.t.shape and bool(
                torch.equal(stream.t, seq.poses.t)
                and torch.equal(stream.position, seq.poses.position)
            ):
                return name
    return pose_source_of(seq)


def _last(result: EskfResult) -> tuple[NavState, torch.Tensor]:
    """State and conventional covariance at the last real epoch (B = 1)."""
    last = int(result.mask[0].sum()) - 1

    def at(x: torch.Tensor) -> torch.Tensor:
        return x[:, last]

    state = NavState(
        at(result.position),
        at(result.velocity),
        at(result.rotation),
        at(result.gyro_bias),
        at(result.accel_bias),
    )
    return state, at(result.covariance)


def _concat(results: list[EskfResult]) -> EskfResult:
    """One result from consecutive chunks' results (B = 1): real epochs only, each later
    chunk's start epoch (its predecessor's last) dropped."""
    keeps = []
    for k, r in enumerate(results):
        keep = r.mask[0].clone()
        keep[0] = keep[0] and k == 0
        keeps.append(keep)

    def cat(get: Callable[[EskfResult], torch.Tensor]) -> torch.Tensor:
        return torch.cat([get(r)[:, keep] for r, keep in zip(results, keeps, strict=True)], 1)

    first = results[0]
    per_sensor = {
        name: {key: cat(lambda r, n=name, k=key: getattr(r, n)[k]) for key in first.present}
        for name in ("present", "accepted", "nis")
    }
    return EskfResult(
        names=first.names,
        t=cat(lambda r: r.t),
        mask=cat(lambda r: r.mask),
        position=cat(lambda r: r.position),
        velocity=cat(lambda r: r.velocity),
        rotation=cat(lambda r: r.rotation),
        gyro_bias=cat(lambda r: r.gyro_bias),
        accel_bias=cat(lambda r: r.accel_bias),
        covariance=cat(lambda r: r.covariance),
        slip_factor=cat(lambda r: r.slip_factor),
        gap=None if first.gap is None else cat(lambda r: r.gap),
        **per_sensor,
    )


def run_piecewise(
    seq: Sequence,
    cfg: EskfConfig,
    log_scales: torch.Tensor,
    window_length: int,
    pose_source: str | None,
    progress: Callable[[int, int], None] | None = None,
) -> EskfResult:
    """The ESKF over a B = 1 sequence with piecewise-constant noise per window.

    Consecutive windows with equal scales form one chunk; the filter runs chunk by chunk
    over the chunk's IMU samples (the last chunk to the end of the IMU stream), each
    chunk with ``scaled_noise`` of its scales and ``seq.poses`` covariances times
    ``exp(log_scale)`` of ``pose_source`` (``"vo"`` when None), starting from the previous
    chunk's last state and covariance.

    Args:
        seq: one run (B = 1).
        cfg: front-end settings (the base noise).
        log_scales: (W, 7) :data:`LOG_SCALE_SENSORS` log-variance scales per window.
        window_length: L, IMU samples per window.
        pose_source: column of the pose stream's scale.
        progress: optional callback ``(epochs_done, epochs_total)`` over all chunks.

    Returns:
        :class:`EskfResult` over the whole run (B = 1), real epochs only.
    """
    imu = seq.imu.compact()
    base = EskfNoise.from_config(cfg, imu.t.dtype, imu.t.device)
    windows = log_scales.shape[0]
    change = [0] + [
        w for w in range(1, windows) if not torch.equal(log_scales[w], log_scales[w - 1])
    ]
    bounds = list(zip(change, change[1:] + [None], strict=True))
    results: list[EskfResult] = []
    done = 0
    initial = initial_state(seq, cfg)  # from the whole run, as run_eskf(seq) starts
    pose_column = LOG_SCALE_SENSORS.index(pose_source or "vo")
    for w0, w1 in bounds:
        scales = log_scales[w0].to(imu.t)
        end = None if w1 is None else w1 * window_length + 1
        chunk = dataclasses.replace(
            seq, imu=imu.map(lambda x, a=w0 * window_length, b=end: x[:, a:b])
        )
        if seq.poses is not None:
            covariance = scaled_pose_covariance(
                seq.poses.covariance, scales[None], LOG_SCALE_SENSORS[pose_column]
            )
            chunk = dataclasses.replace(
                chunk, poses=dataclasses.replace(seq.poses, covariance=covariance)
            )
        callback = None
        if progress is not None:

            def callback(d: int, t: int, offset: int = done) -> None:
                progress(offset + d, offset + t)

        result = run_eskf(
            chunk, cfg, scaled_noise(base, scales), progress=callback, initial=initial
        )
        done += int(result.mask[0].sum())
        initial = _last(result)
        results.append(result)
    return _concat(results)


def scales_summary(scales: WindowScales, learned: LearnedModel) -> dict[str, Any]:
    """The ``learned`` entry of ``summary.json``: checkpoint, mean scales, weather."""
    cfg = learned.model.config
    names = cfg.weather_classes
    mean = scales.log_scales.mean(0)
    inferred = torch.bincount(scales.inferred, minlength=len(names)) / scales.inferred.numel()
    entry: dict[str, Any] = {
        "checkpoint": str(learned.path),
        "sha256": learned.sha256,
        "windows": int(scales.log_scales.shape[0]),
        "window_length": scales.window_length,
        "chunk_windows": scales.chunk_windows,
        "mean_log_scales": {
            s: round(float(v), 4) for s, v in zip(LOG_SCALE_SENSORS, mean, strict=True)
        },
        "pose_source": scales.pose_source,
        "weather_from_labels": scales.from_labels,
        "inferred_weather": {n: round(float(f), 4) for n, f in zip(names, inferred, strict=True)},
    }
    labelled = scales.labels != cfg.unknown_weather
    if bool(labelled.any()):
        hits = (scales.inferred == scales.labels)[labelled].float().mean()
        entry["weather_accuracy"] = round(float(hits), 4)
    return entry
