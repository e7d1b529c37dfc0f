"""CovNet on the real KITTI drive (gtsam wheel): GNSS-outage segments as training runs.

The drive (:func:`msf_torch.io.kitti_gtsam.load_kitti_gtsam`, 471 s, IMU at 100 Hz, GNSS
fixes at 1 Hz, no wheels) has no ground truth besides its GNSS fixes, so the fixes are the
reference: a segment withholds the fixes of its last ``outage_s`` seconds from the filter
and scores the filter's positions against them (the orientation term is off), in the
spirit of AI-IMU (Brossard et al., 2020), where the network learns the noise of the
non-holonomic constraint and the IMU so that dead reckoning drifts less.

Splits, by GNSS fix index (M fixes, ``i = int(fraction * M)``):

* train: segments whose withheld fixes lie in ``[0, val_start_fraction M)``;
* val: withheld fixes in ``[val_start_fraction M, test_start_fraction M)``;
* test: withheld fixes in ``[test_start_fraction M, M)`` (the last 40 % by default; the
  benchmark ``benchmarks/learned_kitti.py`` scores 60-s outages there on the whole drive).

Where the learned noise applies: only in GNSS outages. A filter chunk (``chunk_windows``
CovNet windows) with no GNSS fix in its time span takes the network's NHC, IMU and GNSS
log-variance scales; every other chunk keeps the configured noise
(:func:`gate_outage_chunks`). With truncated backpropagation and the loss only inside
outages, the noise of GNSS-aided chunks would get no gradient of its own, so the network is
not let loose there: while GNSS is present the filter is exactly the fixed-noise one, and
what is learned is the dead-reckoning noise of the outage (AI-IMU's setting: IMU + NHC).

A segment therefore starts at the outage (``warmup_s = 0``, the default; a positive
``warmup_s`` keeps that many seconds of GNSS before it, with the configured noise) from the
state and covariance of a reference pass of the filter with the configured noise over the
drive with all fixes before the segment (:func:`reference_states`; causal, so no withheld
fix reaches the start state), which is the state the fixed filter has at that point of the
drive. Segments start every ``stride_s`` seconds. The CovNet inputs are the IMU windows and
the GNSS dropout fraction (:func:`segment_features`; no innovation features: they need a
reference pass per outage); at test time the same features come from the whole drive with
the stretch withheld (:func:`drive_scales`).
"""

from __future__ import annotations

__all__ = [
    "KittiBatch",
    "KittiCovNetModule",
    "KittiDataModule",
    "collate_segments",
    "drive_scales",
    "gate_outage_chunks",
    "gnss_free_windows",
    "kitti_eskf_config",
    "outage_segment",
    "reference_states",
    "segment_features",
    "segment_starts",
]

import copy
import dataclasses
import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch.utils.data import DataLoader

from msf_torch.frontend.config import (
    EskfConfig,
    load_sequence_config,
    packaged_config,
)
from msf_torch.frontend.eskf import EskfResult, run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.io.kitti_gtsam import load_kitti_gtsam
from msf_torch.learning.covnet import (
    CovNet,
    CovNetConfig,
    CovNetOutput,
    NoiseApplication,
    apply_fusion_weights,
    save_checkpoint,
)
from msf_torch.learning.data import SPLITS, RunBatch, RunDataModule, collate_runs
from msf_torch.learning.features import RunFeatures, run_features
from msf_torch.learning.module import CovNetModule, truth_at
from msf_torch.types import NavState, Sequence, Trajectory


def kitti_eskf_config(seq: Sequence, path: str | Path | None = None) -> EskfConfig:
    """Filter settings for the drive: a YAML file (default the packaged
    ``msf_torch/configs/kitti-gtsam.yaml``) with the dataset's IMU noise filling the keys the
    file leaves out (:func:`~msf_torch.frontend.config.config_for_sequence`), as ``msf run``
    and ``benchmarks/kitti_outage.py`` build it."""
    path = path if path is not None else packaged_config("kitti-gtsam")
    if path is None:
        raise FileNotFoundError("msf_torch/configs/kitti-gtsam.yaml is missing")
    return load_sequence_config(seq.meta, path)


def _state_at(result: EskfResult, index: torch.Tensor | int) -> tuple[NavState, torch.Tensor]:
    """State and covariance of epoch ``index`` of a B = 1 result, detached."""

    def at(x: torch.Tensor) -> torch.Tensor:
        return x[:, index].detach()

    state = NavState(
        at(result.position),
        at(result.velocity),
        at(result.rotation),
        at(result.gyro_bias),
        at(result.accel_bias),
    )
    return state, at(result.covariance)


def reference_states(
    seq: Sequence, cfg: EskfConfig, sample_indices: list[int]
) -> list[tuple[NavState, torch.Tensor]]:
    """The fixed-noise filter's state and covariance at given IMU samples of a B = 1 drive.

    The filter runs from the drive's start (its usual initialisation) piece by piece, each
    piece ending at the next requested sample and starting from the previous piece's last
    state; a piece sees the GNSS fixes of its own time span only, so a state depends on the
    fixes up to its sample (causal).

    Args:
        seq: the drive (B = 1).
        cfg: filter settings (fixed noise).
        sample_indices: increasing IMU sample indices (>= 0).

    Returns:
        one ``(NavState (1, ...), covariance (1, 15, 15))`` per index.
    """
    imu = seq.imu.compact()
    if any(b <= a for a, b in zip(sample_indices, sample_indices[1:], strict=False)):
        raise ValueError("reference_states: sample_indices must increase")
    out = []
    current = initial_state(seq, cfg)
    done = 0
    with torch.no_grad():
        for index in sample_indices:
            if index > done:
                piece = dataclasses.replace(
                    seq, imu=imu.map(lambda x, a=done, b=index: x[:, a : b + 1])
                )
                result = run_eskf(piece, cfg, initial=current)
                current = _state_at(result, int(result.mask[0].sum()) - 1)
                done = index
            out.append(current)
    return out


def segment_starts(
    seq: Sequence,
    window_length: int,
    warmup_s: float,
    outage_s: float,
    stride_s: float,
    first_start_s: float,
    withheld_range: tuple[int, int],
) -> list[tuple[int, int, int]]:
    """Segments of a B = 1 drive whose withheld fixes lie in a fix-index range.

    All lengths are rounded to whole windows of ``window_length`` IMU samples (the drive's
    median sample interval gives the samples per second).

    Returns:
        ``(start, warmup, total)`` IMU sample counts per segment: the segment covers samples
        ``[start, start + total]``, GNSS is withheld from sample ``start + warmup`` on.
    """
    imu = seq.imu.compact()
    t = imu.t[0]
    dt = float(torch.median(t[1:] - t[:-1]))

    def windows(seconds: float) -> int:
        return max(1, round(seconds / (dt * window_length)))

    warmup = round(warmup_s / (dt * window_length)) * window_length
    total = warmup + windows(outage_s) * window_length
    stride = windows(stride_s) * window_length
    first = math.ceil(first_start_s / (dt * window_length) - 1e-6) * window_length
    gnss = seq.gnss.compact()
    fixes = gnss.t[0]
    lo, hi = withheld_range
    out = []
    for start in range(first, t.numel() - total, stride):
        t_out, t_end = float(t[start + warmup]), float(t[start + total])
        withheld = torch.nonzero((fixes >= t_out) & (fixes <= t_end))[:, 0]
        if withheld.numel() >= 2 and int(withheld[0]) >= lo and int(withheld[-1]) < hi:
            out.append((start, warmup, total))
    return out


def outage_segment(seq: Sequence, start: int, warmup: int, total: int) -> Sequence:
    """IMU samples ``[start, start + total]`` of a B = 1 drive, GNSS fixes up to sample
    ``start + warmup`` (exclusive) kept, the later ones as ``ground_truth`` (identity
    orientations: position reference only; ``gnss`` is None when no fix is kept). Named
    ``"<drive>@<t>s"`` (t in s from the drive's first IMU sample)."""
    imu = seq.imu.compact()
    gnss = seq.gnss.compact()
    part = imu.map(lambda x: x[:, start : start + total + 1])
    t_start, t_out = float(part.t[0, 0]), float(part.t[0, warmup])
    t_end = float(part.t[0, -1])
    fixes = gnss.t[0]
    kept = (fixes >= t_start) & (fixes < t_out)
    withheld = (fixes >= t_out) & (fixes <= t_end)
    ref = gnss.map(lambda x: x[:, withheld])
    quaternion = torch.zeros(*ref.position.shape[:2], 4, dtype=ref.position.dtype)
    quaternion[..., 0] = 1.0
    truth = Trajectory(t=ref.t, position=ref.position, quaternion=quaternion, mask=ref.mask)
    offset = t_start - float(imu.t[0, 0])
    return dataclasses.replace(
        seq,
        names=[f"{seq.names[0]}@{offset:.0f}s"],
        imu=part,
        gnss=gnss.map(lambda x: x[:, kept]) if bool(kept.any()) else None,
        ground_truth=truth,
        labels={},
        meta=dict(seq.meta),
    )


def segment_features(
    seq: Sequence,
    window_length: int,
    pose_sources: tuple[str, ...],
    weather_classes: tuple[str, ...],
) -> RunFeatures:
    """CovNet inputs of a B = 1 sequence as the KITTI network sees them: IMU windows and the
    GNSS dropout fraction, no innovation features (``run_features`` with ``cfg=None``).

    Args:
        seq: a segment or the whole drive (B = 1).
        window_length, pose_sources, weather_classes: the ``CovNetConfig`` fields.
    """
    return run_features(seq, window_length, pose_sources, weather_classes)


def gnss_free_windows(seq: Sequence, window_length: int) -> torch.Tensor:
    """(W,) bool: CovNet window ``w`` of a B = 1 sequence (IMU samples ``[w L, (w + 1) L]``,
    end sample included) holds no GNSS fix; W as in ``run_features``."""
    t = seq.imu.compact().t[0]
    windows = (t.numel() - 1) // window_length
    starts = t[0 : windows * window_length : window_length].contiguous()
    ends = t[window_length : windows * window_length + 1 : window_length].contiguous()
    if seq.gnss is None or not bool(seq.gnss.mask.any()):
        return torch.ones(windows, dtype=torch.bool, device=t.device)
    fixes = seq.gnss.compact().t[0].contiguous()
    count = torch.searchsorted(fixes, ends, right=True) - torch.searchsorted(fixes, starts)
    return count == 0


def gate_outage_chunks(
    log_scales: torch.Tensor, gnss_free: torch.Tensor, chunk_windows: int
) -> torch.Tensor:
    """Keep the log scales only in chunks without GNSS, zero (configured noise) elsewhere.

    Args:
        log_scales: (B, W, 7) per-window log-variance scales.
        gnss_free: (B, W) bool, :func:`gnss_free_windows` per run.
        chunk_windows: K, windows per filter chunk, counted from window 0.

    Returns:
        (B, W, 7): a chunk's scales where all of its windows are GNSS-free, else 0
        (differentiable w.r.t. ``log_scales``).
    """
    batch, windows = gnss_free.shape
    chunks = -(-windows // chunk_windows)
    padded = torch.ones(batch, chunks * chunk_windows, dtype=torch.bool, device=gnss_free.device)
    padded[:, :windows] = gnss_free
    free = padded.view(batch, chunks, chunk_windows).all(-1)
    free = free.repeat_interleave(chunk_windows, 1)[:, :windows]
    return torch.where(free[..., None], log_scales, torch.zeros_like(log_scales))


def drive_scales(seq: Sequence, model: CovNet, chunk_windows: int) -> torch.Tensor:
    """Per-window log-variance scales (W, 7) of a B = 1 sequence as the KITTI filter uses
    them: the network's scales (fusion weights folded in) averaged per chunk of
    ``chunk_windows`` windows from the first IMU sample, kept in GNSS-free chunks and 0
    elsewhere (:func:`gate_outage_chunks`), float64: the input of
    :func:`msf_torch.learning.inference.run_piecewise`.
    """
    net = model.config
    features = segment_features(seq, net.window_length, net.pose_sources, net.weather_classes)
    with torch.no_grad():
        out = model(features.imu, features.wheel, features.wheel_present, features.residual_stats)
        scales = apply_fusion_weights(out.log_scales, out.fusion_weights, net.pose_sources)
    scales = scales.double()
    for w0 in range(0, scales.shape[0], chunk_windows):
        scales[w0 : w0 + chunk_windows] = scales[w0 : w0 + chunk_windows].mean(0)
    free = gnss_free_windows(seq, net.window_length)
    return gate_outage_chunks(scales[None], free[None], chunk_windows)[0]


@dataclass
class KittiBatch(RunBatch):
    """A :class:`RunBatch` of outage segments and where their filters start.

    Attributes:
        start_position, start_velocity: (B, 3) m, m/s; start_rotation (B, 3, 3);
            start_gyro_bias, start_accel_bias (B, 3): the reference state at each segment's
            first IMU sample.
        start_covariance: (B, 15, 15) its covariance.
        outage_distance: (B,) path length of the withheld fixes, m.
        gnss_free: (B, W) bool, windows without a GNSS fix (:func:`gnss_free_windows`).
    """

    start_position: torch.Tensor | None = None
    start_velocity: torch.Tensor | None = None
    start_rotation: torch.Tensor | None = None
    start_gyro_bias: torch.Tensor | None = None
    start_accel_bias: torch.Tensor | None = None
    start_covariance: torch.Tensor | None = None
    outage_distance: torch.Tensor | None = None
    gnss_free: torch.Tensor | None = None

    def start(self) -> tuple[NavState, torch.Tensor]:
        """The start state (B, ...) and covariance (B, 15, 15)."""
        state = NavState(
            self.start_position,
            self.start_velocity,
            self.start_rotation,
            self.start_gyro_bias,
            self.start_accel_bias,
        )
        return state, self.start_covariance


_START_FIELDS = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")


def collate_segments(
    items: list[tuple[Sequence, RunFeatures, tuple[NavState, torch.Tensor]]],
    window_length: int,
) -> KittiBatch:
    """Stack segments (sequence, features, start state) into a :class:`KittiBatch`."""
    base = collate_runs([(s, f) for s, f, _ in items], window_length)
    starts = [state for _, _, state in items]
    fields = {
        f"start_{name}": torch.cat([getattr(s, name) for s, _ in starts]) for name in _START_FIELDS
    }
    truth = base.sequence.ground_truth
    step = (truth.position[:, 1:] - truth.position[:, :-1]).norm(dim=-1)
    both = truth.mask[:, 1:] & truth.mask[:, :-1]
    return KittiBatch(
        **{f.name: getattr(base, f.name) for f in dataclasses.fields(RunBatch)},
        **fields,
        start_covariance=torch.cat([cov for _, cov in starts]),
        outage_distance=torch.where(both, step, 0.0).sum(-1),
        gnss_free=torch.stack(
            [gnss_free_windows(s, window_length)[: base.windows] for s, _, _ in items]
        ),
    )


class KittiDataModule(RunDataModule):
    """Outage segments of the KITTI drive as :class:`KittiBatch` batches (module docstring).

    Args:
        eskf_config: YAML of filter settings for the reference pass (default the packaged
            ``kitti-gtsam.yaml``); the module's ``eskf_config`` should be the same file.
        data_dir: folder with the drive's three files (None: the installed gtsam's).
        warmup_s: seconds of GNSS before a segment's outage (configured noise there).
        outage_s: seconds of withheld GNSS (the loss reference).
        stride_s: seconds between segment starts.
        first_start_s: earliest segment start, s from the drive's first IMU sample.
        val_start_fraction, test_start_fraction: split boundaries as fractions of the
            fixes (module docstring).
        batch_size: segments per batch.
        window_length, pose_sources, weather_classes: as in
            :class:`~msf_torch.learning.CovNetConfig`.
        num_workers: DataLoader workers.
    """

    def __init__(
        self,
        eskf_config: str | None = None,
        data_dir: str | None = None,
        warmup_s: float = 0.0,
        outage_s: float = 40.0,
        stride_s: float = 5.0,
        first_start_s: float = 10.0,
        val_start_fraction: float = 0.45,
        test_start_fraction: float = 0.6,
        batch_size: int = 8,
        window_length: int = 100,
        pose_sources: tuple[str, ...] = ("gnss",),
        weather_classes: tuple[str, ...] = ("sunny", "rain", "fog", "night", "snow"),
        num_workers: int = 0,
    ) -> None:
        super().__init__(
            train_runs=0,
            val_runs=0,
            test_runs=0,
            batch_size=batch_size,
            window_length=window_length,
            pose_sources=pose_sources,
            weather_classes=weather_classes,
            num_workers=num_workers,
        )
        if not 0.0 < val_start_fraction < test_start_fraction < 1.0:
            raise ValueError(
                "KittiDataModule: need 0 < val_start_fraction < test_start_fraction < 1, got "
                f"{val_start_fraction}, {test_start_fraction}"
            )
        if min(outage_s, stride_s) <= 0.0 or warmup_s < 0.0:
            raise ValueError("KittiDataModule: outage_s and stride_s must be > 0 and warmup_s >= 0")
        self.eskf_path = eskf_config
        self.data_dir = data_dir
        self.warmup_s = warmup_s
        self.outage_s = outage_s
        self.stride_s = stride_s
        self.first_start_s = first_start_s
        self.fractions = (val_start_fraction, test_start_fraction)
        self.segments: dict[str, list[tuple[int, int, int]]] = {}

    def fix_ranges(self, n_fixes: int) -> dict[str, tuple[int, int]]:
        """Withheld-fix index range ``[lo, hi)`` of each split."""
        val, test = (int(f * n_fixes) for f in self.fractions)
        return {"train": (0, val), "val": (val, test), "test": (test, n_fixes)}

    def setup(self, stage: str | None = None) -> None:
        """Load the drive, cut the segments of every split and their start states (once)."""
        if self.runs:
            return
        drive = load_kitti_gtsam(data_dir=self.data_dir)
        cfg = kitti_eskf_config(drive, self.eskf_path)
        ranges = self.fix_ranges(int(drive.gnss.mask.sum()))
        for split in SPLITS:
            self.segments[split] = segment_starts(
                drive,
                self.window_length,
                self.warmup_s,
                self.outage_s,
                self.stride_s,
                self.first_start_s,
                ranges[split],
            )
        starts = sorted({s for split in SPLITS for s, _, _ in self.segments[split]})
        states = dict(zip(starts, reference_states(drive, cfg, starts), strict=True))
        for split in SPLITS:
            items = []
            for start, warmup, total in self.segments[split]:
                segment = outage_segment(drive, start, warmup, total)
                features = segment_features(
                    segment, self.window_length, self.pose_sources, self.weather_classes
                )
                items.append((segment, features, states[start]))
            self.runs[split] = items

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        return DataLoader(
            self.runs[split],
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            collate_fn=functools.partial(collate_segments, window_length=self.window_length),
        )


class KittiCovNetModule(CovNetModule):
    """:class:`~msf_torch.learning.module.CovNetModule` on :class:`KittiBatch` outage segments.

    The filter starts from each segment's reference state; the network's noise applies in
    GNSS-free chunks only (module docstring); only the epochs between the first and last
    withheld fix are scored. A drift term joins the parent's loss terms:
    ``drift_l1``, the mean over the scored epochs of the position error divided by the
    segment's withheld path length, in percent (``drift_weight`` times it is added to the
    loss; unlike the squared error it does not let the few segments with tens of metres of
    error decide alone). Logged besides the parent's terms: ``train/drift_pct`` and
    ``val/drift_pct``, per segment the largest scored error over the withheld path length in
    percent, averaged over the segments (epoch-based; the benchmark scores at the fix
    times). At the end of ``fit`` the network of the epoch with the lowest ``val/drift_pct``
    is written to ``<log_dir>/covnet.pt`` (``val/best_drift_pct`` logs that value).

    Args:
        drift_weight: weight of ``drift_l1`` (1/percent).
        covnet, eskf_config, chunk_windows, noise_granularity, use_weather_labels,
        position_weight, orientation_weight, nll_weight, weather_weight, lr, weight_decay,
        max_figures: as :class:`CovNetModule` (``orientation_weight`` should be 0: the
            reference has no orientation).
    """

    def __init__(
        self,
        covnet: CovNetConfig | None = None,
        eskf_config: str | None = None,
        chunk_windows: int = 5,
        noise_granularity: Literal["chunk", "run"] = "chunk",
        use_weather_labels: bool = False,
        position_weight: float = 0.0,
        orientation_weight: float = 0.0,
        nll_weight: float = 0.1,
        weather_weight: float = 0.0,
        drift_weight: float = 1.0,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        max_figures: int = 2,
    ) -> None:
        super().__init__(
            covnet=covnet,
            eskf_config=eskf_config,
            chunk_windows=chunk_windows,
            noise_granularity=noise_granularity,
            use_weather_labels=use_weather_labels,
            position_weight=position_weight,
            orientation_weight=orientation_weight,
            nll_weight=nll_weight,
            weather_weight=weather_weight,
            lr=lr,
            weight_decay=weight_decay,
            max_figures=max_figures,
        )
        self.drift_weight = drift_weight
        self._best_drift = math.inf
        self._best_state: dict[str, torch.Tensor] | None = None
        self._val_drift: list[torch.Tensor] = []

    def forward(self, batch: RunBatch) -> tuple[CovNetOutput, torch.Tensor]:
        """The parent's per-window outputs; the effective scales gated to GNSS-free chunks
        (:func:`gate_outage_chunks`) for a :class:`KittiBatch`."""
        out, effective = super().forward(batch)
        if isinstance(batch, KittiBatch):
            effective = gate_outage_chunks(effective, batch.gnss_free, self.chunk_windows)
        return out, effective

    def start_state(self, batch: RunBatch, cfg: EskfConfig) -> tuple[NavState, torch.Tensor]:
        """The segments' reference states (:class:`KittiBatch`)."""
        if not isinstance(batch, KittiBatch):
            return super().start_state(batch, cfg)
        state, cov = batch.start()
        dtype = batch.sequence.imu.t.dtype
        return NavState(*(x.to(dtype) for x in dataclasses.astuple(state))), cov.to(dtype)

    def scored_epochs(self, batch: RunBatch, result: EskfResult) -> torch.Tensor:
        """Real epochs (but a chunk's first) between the first and last withheld fix."""
        mask = super().scored_epochs(batch, result)
        truth = batch.sequence.ground_truth
        last = torch.where(truth.mask, truth.t, torch.full_like(truth.t, -math.inf)).amax(-1)
        first = torch.where(truth.mask, truth.t, torch.full_like(truth.t, math.inf)).amin(-1)
        return mask & (result.t >= first[:, None]) & (result.t <= last[:, None])

    def _drift(
        self, batch: RunBatch, results: list[EskfResult]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Relative position error: the mean (scalar, with gradient) over all scored epochs
        and the largest per segment (B,), detached; both error / withheld path, percent."""
        distance = batch.sequence.imu.t.new_ones(batch.imu.shape[0])
        if isinstance(batch, KittiBatch):
            distance = batch.outage_distance.to(distance).clamp_min(1e-9)
        worst = torch.zeros_like(distance)
        total = distance.new_zeros(())
        count = distance.new_zeros(())
        for result in results:
            position, _ = truth_at(batch.sequence.ground_truth, result.t)
            scored = self.scored_epochs(batch, result)
            relative = 100.0 * (result.position - position).norm(dim=-1) / distance[:, None]
            relative = torch.where(scored, relative, 0.0)
            total = total + relative.sum()
            count = count + scored.sum()
            worst = torch.maximum(worst, relative.detach().amax(-1))
        return total / count.clamp_min(1.0), worst

    def _losses(self, batch: RunBatch) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """The parent's terms plus ``drift_l1`` (in the loss) and ``drift_pct`` (logged);
        during validation the per-segment drifts are kept for the epoch's mean."""
        terms, extra = super()._losses(batch)
        mean_relative, drift = self._drift(batch, extra["results"])
        terms["drift_l1"] = mean_relative.float()
        terms["loss"] = terms["loss"] + self.drift_weight * terms["drift_l1"]
        terms["drift_pct"] = drift.mean().float()
        if self._trainer is not None and self.trainer.validating:
            self._val_drift.append(drift)
        return terms, extra

    def on_validation_epoch_start(self) -> None:
        """Also reset the per-segment drifts."""
        super().on_validation_epoch_start()
        self._val_drift = []

    def on_validation_epoch_end(self) -> None:
        """The parent's logs; then the mean segment drift over all validation batches and the
        best network so far."""
        super().on_validation_epoch_end()
        if self.trainer.sanity_checking or not self._val_drift:
            return
        drift = torch.cat(self._val_drift)
        total = self.trainer.strategy.reduce(drift.sum(), reduce_op="sum")
        count = self.trainer.strategy.reduce(drift.new_tensor(drift.numel()), reduce_op="sum")
        mean = float(total / count)
        if mean < self._best_drift:
            self._best_drift = mean
            self._best_state = copy.deepcopy(self.net.state_dict())
        self._log_reduced("val/best_drift_pct", self._best_drift)

    def noise_application(self) -> NoiseApplication:
        """The parent's record, with the KITTI network's inputs (no innovation features)
        and its scales applied in GNSS-free chunks only."""
        return dataclasses.replace(
            super().noise_application(), innovation_features=False, gnss_outages_only=True
        )

    def on_fit_end(self) -> None:
        """Write the network of the best validation epoch and :meth:`noise_application` to
        ``<log_dir>/covnet.pt``."""
        if self._best_state is not None:
            self.net.load_state_dict(self._best_state)
        log_dir = self.trainer.log_dir
        if self.trainer.is_global_zero and log_dir is not None:
            Path(log_dir).mkdir(parents=True, exist_ok=True)
            save_checkpoint(Path(log_dir) / "covnet.pt", self.net, self.noise_application())
