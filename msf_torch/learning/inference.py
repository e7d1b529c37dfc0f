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

:func:`learned_scales` applies a checkpoint as its training did
(:class:`~msf_torch.learning.covnet.NoiseApplication`, stored in the checkpoint): the chunking,
whether the network saw innovation features, whether the scales apply only where GNSS is
out; a sequence whose IMU runs at a whole multiple of the training runs' rate is shown to the
network averaged down to it (:func:`decimate_imu`), any other rate is refused (a window of
``window_length`` samples would span another time, and each sample's noise differs).
Checkpoints written before that record existed load with
``training/configs/default.yaml``'s chunking (:data:`DEFAULT_CHUNK_WINDOWS`) and no rate.
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_CHECKPOINT",
    "DEFAULT_CHUNK_WINDOWS",
    "IMU_RATE_TOLERANCE",
    "LearnedModel",
    "WindowScales",
    "load_learned",
    "decimate_imu",
    "filter_settings_mismatch",
    "imu_decimation",
    "learned_scales",
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
from msf_torch.frontend.guard import EstimationInterrupted, sanitize_sequence
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.schedule import build_schedule
from msf_torch.frontend.stream import concat_results, last_state
from msf_torch.learning.covnet import (
    IMU_RATE_TOLERANCE,
    LOG_SCALE_SENSORS,
    CovNet,
    NoiseApplication,
    apply_fusion_weights,
    read_checkpoint,
    scaled_noise,
    scaled_pose_covariance,
)
from msf_torch.learning.features import RunFeatures, pose_source_of, run_features
from msf_torch.sensors.imu_gaps import outside_stretches
from msf_torch.types import ImuSamples, Sequence

DEFAULT_CHECKPOINT = (
    Path(__file__).resolve().parent.parent.parent / "checkpoints" / "covnet_default.pt"
)
"""The shipped network (``msf run`` uses it when the file exists)."""

DEFAULT_CHUNK_WINDOWS = NoiseApplication().chunk_windows
"""Windows per noise chunk, as in ``training/configs/default.yaml``."""


@dataclass
class LearnedModel:
    """A loaded CovNet and where it came from.

    Attributes:
        model: the network, eval mode, CPU.
        path: the checkpoint file.
        sha256: hex digest of the file's bytes.
        application: how its training applied the scales (the checkpoint's record).
    """

    model: CovNet
    path: Path
    sha256: str
    application: NoiseApplication = dataclasses.field(default_factory=NoiseApplication)


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
        gnss_outages_only: the scales were zeroed (configured noise) in chunks holding a
            GNSS fix.
        imu_decimation: the sequence's IMU samples per network sample
            (:func:`imu_decimation`); ``window_length`` counts the sequence's own samples.
    """

    log_scales: torch.Tensor
    window_length: int
    pose_source: str | None
    chunk_windows: int
    labels: torch.Tensor
    from_labels: bool
    inferred: torch.Tensor
    gnss_outages_only: bool = False
    imu_decimation: int = 1


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
        model, application = read_checkpoint(path)
    except (RuntimeError, pickle.UnpicklingError, EOFError, KeyError, TypeError) as err:
        raise ValueError(f"CovNet checkpoint {path}: cannot be read ({err})") from err
    return LearnedModel(model, path, digest, application)


def imu_decimation(seq: Sequence, learned: LearnedModel) -> int:
    """How many of a B = 1 sequence's IMU samples make one sample at the rate the
    checkpoint was trained on: 1 when the rates agree within :data:`IMU_RATE_TOLERANCE`
    (relative), ``k`` when the sequence's rate is ``k >= 2`` times the training rate within
    it (a 200 or 400 Hz IMU for a 100 Hz network). The network then sees the means of
    ``k`` consecutive samples (:func:`decimate_imu`): the noise the scales multiply is a
    density, the same at either rate, and the mean of ``k`` samples has the per-sample
    noise of the slower sensor. A checkpoint that recorded no rate gives 1.

    Raises:
        ValueError: any other rate (slower than the training rate, or not a whole multiple
            of it); the message names the sequence, both rates and the window spans.
    """
    rate = float(seq.imu.median_rate_hz()[0])
    trained = learned.application.imu_rate_hz
    if trained is None:
        return 1
    ratio = max(1, round(rate / trained))
    if abs(rate / (ratio * trained) - 1.0) <= IMU_RATE_TOLERANCE:
        return ratio
    length = learned.model.config.window_length
    raise ValueError(
        f"sequence '{seq.names[0]}': its IMU runs at {rate:.6g} Hz, but CovNet checkpoint "
        f"{learned.path} was trained on {trained:.6g} Hz (windows of {length} samples: "
        f"{length / trained:.3g} s there, {length / rate:.3g} s here, and each sample's noise "
        f"differs; a whole multiple of {trained:.6g} Hz would be averaged down to it). "
        f"Resample the IMU to {trained:.6g} Hz, train a network on your rate, or run without "
        "learned noise (msf run --no-learned)."
    )


def filter_settings_mismatch(learned: LearnedModel, settings: dict[str, Any]) -> list[str]:
    """The front-end keys whose value differs between the checkpoint's training
    (``NoiseApplication.filter_settings``) and a run's config YAML ``settings`` (key ->
    value as the file sets them); a key only one side sets is compared with
    :class:`~msf_torch.frontend.config.EskfConfig`'s default on the other. Empty when they
    agree or the checkpoint recorded none.

    Returns:
        ``"key: trained with A, this run B"`` per differing key, sorted by key.
    """
    trained = learned.application.filter_settings
    if trained is None:
        return []
    default = EskfConfig()
    out = []
    for key in sorted(set(trained) | (set(settings) - {"smoother"})):
        ours = trained.get(key, getattr(default, key, None))
        theirs = settings.get(key, getattr(default, key, None))
        if ours != theirs:
            out.append(f"{key}: trained with {ours!r}, this run {theirs!r}")
    return out


def decimate_imu(seq: Sequence, factor: int) -> Sequence:
    """A B = 1 sequence whose IMU samples are the means of ``factor`` consecutive real
    samples of ``seq`` (``ImuSamples.compact``: masked samples are left out first, as the
    windows of :func:`run_piecewise` count them), stamped at the first of each group; a
    last incomplete group is dropped; the other streams unchanged. ``factor = 1`` returns
    ``seq``.

    Args:
        seq: one run (B = 1); IMU (1, N) samples, rad/s and m/s^2.
        factor: samples per group (>= 1).
    Returns:
        the sequence with (1, N // factor) IMU samples.
    """
    if factor == 1:
        return seq
    imu = seq.imu.compact()
    count = (imu.t.shape[1] // factor) * factor

    def groups(x: torch.Tensor) -> torch.Tensor:
        return x[:, :count].unflatten(1, (count // factor, factor))

    decimated = ImuSamples(
        t=groups(imu.t)[:, :, 0],
        gyro=groups(imu.gyro).mean(2),
        accel=groups(imu.accel).mean(2),
        mask=groups(imu.mask).all(2),
    )
    return dataclasses.replace(seq, imu=decimated)


def learned_scales(
    seq: Sequence, learned: LearnedModel, cfg: EskfConfig | None, use_labels: bool = True
) -> WindowScales:
    """The network's noise per window of a B = 1 sequence, applied as its training did.

    :func:`imu_decimation` first (the network sees a faster IMU averaged down to its
    training rate; a window then spans ``factor`` times its length in the sequence's own
    samples); then :func:`window_scales` with the checkpoint's chunking,
    with the innovation features of a reference pass under ``cfg`` only where the network
    was trained with them; with ``gnss_outages_only`` the scales of chunks that hold a GNSS
    fix are zeroed (``msf_torch.learning.kitti.gate_outage_chunks``).

    Args:
        seq: one run (B = 1).
        learned: the checkpoint.
        cfg: the run's filter settings.
        use_labels: as :func:`window_scales`.

    Raises:
        ValueError: the IMU rate is neither the training runs' nor a whole multiple of it,
            or the run is shorter than one window.
    """
    application = learned.application
    factor = imu_decimation(seq, learned)
    scales = window_scales(
        decimate_imu(seq, factor),
        learned.model,
        cfg if application.innovation_features else None,
        chunk_windows=application.chunk_windows,
        granularity=application.noise_granularity,
        use_labels=use_labels,
    )
    scales = dataclasses.replace(
        scales, window_length=scales.window_length * factor, imu_decimation=factor
    )
    if not application.gnss_outages_only:
        return scales
    from msf_torch.learning.kitti import gate_outage_chunks, gnss_free_windows

    free = gnss_free_windows(seq, scales.window_length)
    gated = gate_outage_chunks(scales.log_scales[None], free[None], scales.chunk_windows)[0]
    return dataclasses.replace(scales, log_scales=gated, gnss_outages_only=True)


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
    on_model = next(model.parameters()).device
    features = RunFeatures(**{k: v.to(on_model) for k, v in vars(features).items()})
    weather = weather.to(on_model)
    with torch.no_grad():
        out = model(
            features.imu, features.wheel, features.wheel_present, features.residual_stats, weather
        )
        scales = apply_fusion_weights(out.log_scales, out.fusion_weights, net.pose_sources)
    scales = scales.to(device=seq.imu.t.device, dtype=torch.float64)
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
        inferred=out.weather_logits.argmax(-1).cpu(),
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
    over the chunk's IMU samples (the last chunk to the end of the IMU stream; each chunk
    from the previous chunk's last real sample, also where the boundary's was skipped), each
    chunk with ``scaled_noise`` of its scales and ``seq.poses`` covariances times
    ``exp(log_scale)`` of ``pose_source`` (``"vo"`` when None), starting from the previous
    chunk's last state and covariance and carrying the gate's rejection streaks, the
    divergence guard's episode and the wheel slip factor (``EskfResult.gate_memory``), so
    the chunks gate as one run, the drifting source frames (``EskfResult.frame_memory``),
    the online-calibration states (``EskfResult.calibration_memory``) and each pose source's
    latest sample with the gyro integral since (``EskfResult.pair_memory``), so the pair
    that straddles a chunk boundary is fused as in the run in one piece, and the
    source-fault detector's models, windows and exclusions (``EskfResult.fault_memory``).
    The input rule of ``frontend.guard`` is applied to the whole run once (skipped samples
    counted in ``dropped_samples`` as by ``run_eskf``). A chunk boundary inside a filled-in
    IMU stretch moves to the stretch's end, so the stretch is one gap as in the one run
    (the windows it crosses into take the earlier chunk's scales there).

    Args:
        seq: one run (B = 1).
        cfg: front-end settings (the base noise).
        log_scales: (W, 7) :data:`LOG_SCALE_SENSORS` log-variance scales per window.
        window_length: L, IMU samples per window.
        pose_source: column of the pose stream's scale.
        progress: optional callback ``(epochs_done, epochs_total)`` over all chunks.

    Returns:
        :class:`EskfResult` over the whole run (B = 1), real epochs only, with every
        diagnostic of ``run_eskf`` (divergence codes, dropped samples, source faults, ...).

    Raises:
        EstimationInterrupted: Ctrl-C in a chunk; it carries the epochs completed over all
            chunks (the result as above, up to the last completed epoch) and the epochs of
            the whole run.
    """
    seq, dropped_samples = sanitize_sequence(dataclasses.replace(seq, imu=seq.imu.compact()))
    imu = seq.imu  # skipped samples stay in place (masked): the windows keep their samples
    base = EskfNoise.from_config(cfg, imu.t.dtype, imu.t.device)
    windows = log_scales.shape[0]
    change = [0] + [
        w for w in range(1, windows) if not torch.equal(log_scales[w], log_scales[w - 1])
    ]
    bounds = list(zip(change, change[1:] + [None], strict=True))
    results: list[EskfResult] = []
    done = 0
    initial = initial_state(seq, cfg)  # from the whole run, as run_eskf(seq) starts
    memory = None  # the gate's rejection streaks and the guard's episode, chunk to chunk
    frames = None  # drifting source frames (pose_source_fusion: drifting_frame), the same
    calibration = None  # online calibration states, the same
    pairs = None  # pose sources' latest samples and latest pairs, the same
    faults = None  # the source-fault detector's models and windows (source_fault_detection)
    pose_column = LOG_SCALE_SENSORS.index(pose_source or "vo")
    # (N,) index of the last real IMU sample at or before each sample: a chunk starts at the
    # previous chunk's last real sample, also where the sample at the boundary was skipped
    samples = torch.arange(imu.length, device=imu.t.device)
    last_real = torch.where(imu.mask[0], samples, 0).cummax(0).values
    # a boundary inside a filled-in IMU stretch moves to the stretch's end (the real sample
    # after it), so that the stretch is modelled as one, as in the run in one piece
    outside = outside_stretches(
        imu.t[0], imu.gyro[0], imu.accel[0], imu.mask[0], cfg.imu_interpolated_min_samples
    ).tolist()

    def sample_range(w0: int, w1: int | None) -> tuple[int, int | None]:
        """First and end (exclusive; None: to the end) IMU sample of windows [w0, w1)."""
        start = outside[int(last_real[w0 * window_length])]
        return start, None if w1 is None else outside[w1 * window_length] + 1

    # a chunk wholly inside a stretch is left to the chunk before, which runs to its end
    def enough(w0: int, w1: int | None) -> bool:
        start, end = sample_range(w0, w1)
        return end is None or end - start >= 2

    bounds = [(a, b) for a, b in bounds if enough(a, b)]

    def chunk_of(w0: int, w1: int | None) -> Sequence:
        """The run over windows [w0, w1) with those windows' pose covariances."""
        start, end = sample_range(w0, w1)
        chunk = dataclasses.replace(seq, imu=imu.map(lambda x, a=start, b=end: x[:, a:b]))
        if seq.poses is not None:
            covariance = scaled_pose_covariance(
                seq.poses.covariance,
                log_scales[w0].to(imu.t)[None],
                LOG_SCALE_SENSORS[pose_column],
            )
            chunk = dataclasses.replace(
                chunk, poses=dataclasses.replace(seq.poses, covariance=covariance)
            )
        return chunk

    for index, (w0, w1) in enumerate(bounds):
        callback = None
        if progress is not None:

            def callback(d: int, t: int, offset: int = done) -> None:
                progress(offset + d, offset + t)

        noise = scaled_noise(base, log_scales[w0].to(imu.t))
        try:
            result = run_eskf(
                chunk_of(w0, w1),
                cfg,
                noise,
                callback,
                initial=initial,
                gate_memory=memory,
                frame_memory=frames,
                calibration_memory=calibration,
                pair_memory=pairs,
                fault_memory=faults,
            )
        except EstimationInterrupted as stop:
            results.append(stop.result)
            later, pairs = 0, stop.result.pair_memory
            for a, b in bounds[index + 1 :]:
                sched = build_schedule(chunk_of(a, b), cfg, pairs, continuing=True)
                later, pairs = later + sched.num_epochs, sched.pair_memory
            raise EstimationInterrupted(
                concat_results(results, dropped_samples),
                done + stop.epochs_done,
                done + stop.epochs_total + later,
            ) from None
        done += int(result.mask[0].sum()) - 1
        initial, memory, frames = last_state(result), result.gate_memory, result.frame_memory
        calibration, pairs = result.calibration_memory, result.pair_memory
        faults = result.fault_memory
        results.append(result)
    return concat_results(results, dropped_samples)


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
        "trained_imu_rate_hz": learned.application.imu_rate_hz,
        "imu_decimation": scales.imu_decimation,
        "gnss_outages_only": scales.gnss_outages_only,
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
