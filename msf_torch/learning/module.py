"""LightningModule: CovNet -> noise scales -> differentiable ESKF -> trajectory loss.

Per batch (:class:`~msf_torch.learning.data.RunBatch`, B runs of W windows):

1. :class:`~msf_torch.learning.covnet.CovNet` maps every window to log-variance scales
   (B, W, 7), fusion weights (B, W, S) and weather logits (B, W, C); the fusion weights are
   folded into the scales (:func:`~msf_torch.learning.covnet.apply_fusion_weights`).
2. The run is cut into chunks of ``chunk_windows`` windows. Per chunk the scales are
   averaged over the chunk's windows (``noise_granularity="chunk"``) or over the whole run
   (``"run"``), turned into an :class:`~msf_torch.frontend.eskf.EskfNoise` by
   :func:`~msf_torch.learning.covnet.scaled_noise` (the pose stream's covariances by
   :func:`~msf_torch.learning.covnet.scaled_pose_covariance` with the run's pose source),
   and :func:`~msf_torch.frontend.eskf.run_eskf` runs over the chunk's IMU samples, starting
   from the previous chunk's final state and covariance, *detached* (truncated
   backpropagation through time: gradients stay inside a chunk; the graph of the whole
   batch is kept until the one backward pass, so memory grows with the run length). A
   chunk boundary that falls inside a filled-in IMU stretch of any run of the batch moves
   past it, as :func:`~msf_torch.learning.inference.run_piecewise` does at inference, so
   that the stretch is one gap (the chunk keeps its own windows' scales).
3. Loss, averaged over the real filter epochs of all chunks (``e_p`` position error, m;
   ``e_R = Log(R_true^T R_est)``, rad; ``P_p`` the filter's 3x3 position covariance, m^2)::

       position_weight * |e_p|^2 + orientation_weight * |e_R|^2
       + nll_weight * 0.5 (e_p^T P_p^-1 e_p + log det P_p)
       + weather_weight * cross_entropy(weather logits, labelled windows)

   The Gaussian negative log-likelihood keeps the covariances consistent with the errors
   (a too-small covariance is punished by the quadratic term, a too-large one by the log
   determinant). Ground truth is interpolated at the epoch times (position linearly,
   rotation from the nearer sample).

Logged (TensorBoard through ``self.log`` / ``logger.experiment``): ``train/*`` and
``val/*`` loss terms; ``val/weather_accuracy`` (labelled windows); per sensor and weather
``sigma/<sensor>/<weather>`` from the mean log scale of the validation windows with that
label (``wheel`` and ``nhc`` in m/s, ``imu_gyro`` in rad/s/sqrt(Hz), ``imu_accel`` in
m/s^2/sqrt(Hz), ``gnss``, ``vo``, ``lidar`` as multipliers of the measurement sigma; before
fusion weights); ``fusion/<source>/<weather>`` mean fusion weights; ``val/slip_factor_mean``
and ``val/slip_flagged_fraction`` (epochs below ``EskfConfig.slip_flag_below``); a figure
``val_trajectory/<run>`` (``<run>-2``, ... for repeated names; plan view and slip factor)
for the first ``max_figures``
validation runs. At the end of ``fit`` the network is written with
:func:`~msf_torch.learning.covnet.save_checkpoint` to ``<log_dir>/covnet.pt``.
"""

from __future__ import annotations

__all__ = ["CovNetModule", "truth_at"]

import dataclasses
import statistics
from pathlib import Path
from typing import Any, Literal

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from matplotlib.figure import Figure
from torch.nn import functional as F

from msf_torch.frontend.config import (
    EskfConfig,
    config_for_sequence,
    load_config,
    read_config_keys,
)
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.learning.covnet import (
    LOG_SCALE_SENSORS,
    CovNet,
    CovNetConfig,
    CovNetOutput,
    NoiseApplication,
    apply_fusion_weights,
    save_checkpoint,
    scaled_noise,
)
from msf_torch.learning.data import RunBatch
from msf_torch.sensors.imu_gaps import outside_stretches
from msf_torch.types import ImuSamples, NavState, Sequence, Trajectory

_TERMS = ("position", "orientation", "nll", "weather_ce")


def truth_at(truth: Trajectory, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference pose at query times.

    Args:
        truth: (B, N) ground truth, time-sorted real samples first (padding after).
        t: (B, M) query times, s (clamped to each run's truth span).

    Returns:
        position (B, M, 3) m, linearly interpolated; rotation (B, M, 3, 3) body -> world of
        the nearer truth sample.
    """
    real = truth.mask.sum(-1)  # (B,)
    big = torch.finfo(truth.t.dtype).max
    times = torch.where(truth.mask, truth.t, torch.full_like(truth.t, big)).contiguous()
    hi = torch.searchsorted(times, t.contiguous())
    hi = torch.minimum(hi.clamp_min(1), (real - 1).clamp_min(1)[:, None])
    lo = hi - 1
    t_lo, t_hi = times.gather(1, lo), times.gather(1, hi)
    w = ((t - t_lo) / (t_hi - t_lo).clamp_min(1e-12)).clamp(0.0, 1.0)

    def pick(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        return x.gather(1, index[..., None].expand(*index.shape, x.shape[-1]))

    position = pick(truth.position, lo) + w[..., None] * (
        pick(truth.position, hi) - pick(truth.position, lo)
    )
    quat = pick(truth.quaternion, torch.where(w < 0.5, lo, hi))
    return position, quat_to_matrix(quat)


def _final(result: EskfResult) -> tuple[NavState, torch.Tensor]:
    """Detached state (B, ...) and conventional covariance (B, 15, 15) at the last real
    epoch of each run."""
    last = result.mask.sum(-1) - 1
    rows = torch.arange(last.shape[0], device=last.device)

    def at(x: torch.Tensor) -> torch.Tensor:
        return x[rows, last].detach()

    state = NavState(
        at(result.position),
        at(result.velocity),
        at(result.rotation),
        at(result.gyro_bias),
        at(result.accel_bias),
    )
    return state, at(result.covariance)


def _chunk_samples(
    imu: ImuSamples, windows: int, chunk_windows: int, length: int, min_samples: int
) -> list[tuple[int, int, int, int]]:
    """The filter chunks of a batch: windows ``[w0, w1)`` and IMU samples
    ``[first, last]`` (the end sample included; the next chunk starts there).

    Chunks of ``chunk_windows`` windows of ``length`` samples; a boundary that falls inside
    a filled-in IMU stretch of any run (:func:`~msf_torch.sensors.imu_gaps.outside_stretches`,
    stretches of at least ``min_samples`` samples) moves to that stretch's end, to the
    largest end over the runs and again until no run has a stretch across it (the runs
    share the samples' indices), so that each stretch is one gap as in the run in one piece
    (:func:`~msf_torch.learning.inference.run_piecewise` moves its boundaries alike). A chunk
    left with no samples (wholly inside a stretch) is dropped: the chunk before runs to the
    stretch's end with its own windows' scales.

    Args:
        imu: (B, N) the batch's IMU samples, N = ``windows * length + 1``.
        windows: W, CovNet windows per run.
        chunk_windows: windows per chunk.
        length: IMU samples per window.
        min_samples: ``EskfConfig.imu_interpolated_min_samples``.

    Returns:
        ``(w0, w1, first, last)`` per chunk, in order; the first starts at sample 0, the last
        ends at sample ``windows * length``.
    """
    moved = np.stack(
        [
            outside_stretches(imu.t[b], imu.gyro[b], imu.accel[b], imu.mask[b], min_samples)
            for b in range(imu.t.shape[0])
        ]
    )

    def boundary(sample: int) -> int:
        while (after := int(moved[:, sample].max())) != sample:
            sample = after
        return sample

    cuts = list(range(0, windows, chunk_windows))
    starts = [0] + [boundary(w * length) for w in cuts[1:]]
    ends = starts[1:] + [windows * length]
    return [  # a chunk wholly inside a stretch is empty: the chunk before ends past it
        (w0, min(w0 + chunk_windows, windows), first, last)
        for w0, first, last in zip(cuts, starts, ends, strict=True)
        if last > first
    ]


class CovNetModule(L.LightningModule):
    """Trains a :class:`~msf_torch.learning.covnet.CovNet` through the ESKF (module
    docstring).

    Args:
        covnet: network config (default :class:`CovNetConfig`); its ``window_length``
            must equal the data module's.
        eskf_config: YAML file of :class:`~msf_torch.frontend.config.EskfConfig` keys
            (default settings when None); the first run's metadata fills the keys the
            file leaves out (:func:`~msf_torch.frontend.config.config_for_sequence`).
        chunk_windows: windows per truncated-backpropagation chunk.
        noise_granularity: ``"chunk"`` (scales averaged per chunk) or ``"run"``.
        use_weather_labels: condition the network on the weather labels where known
            (otherwise it uses its own weather head, as at inference).
        position_weight: weight of the squared position error, 1/m^2.
        orientation_weight: weight of the squared orientation error, 1/rad^2.
        nll_weight: weight of the position negative log-likelihood.
        weather_weight: weight of the weather cross-entropy.
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        max_figures: validation trajectory figures per validation epoch.
    """

    def __init__(
        self,
        covnet: CovNetConfig | None = None,
        eskf_config: str | None = None,
        chunk_windows: int = 5,
        noise_granularity: Literal["chunk", "run"] = "chunk",
        use_weather_labels: bool = False,
        position_weight: float = 1.0,
        orientation_weight: float = 100.0,
        nll_weight: float = 0.1,
        weather_weight: float = 0.1,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        max_figures: int = 4,
    ) -> None:
        super().__init__()
        if chunk_windows < 1:
            raise ValueError(f"CovNetModule: chunk_windows must be >= 1, got {chunk_windows}")
        if noise_granularity not in ("chunk", "run"):
            raise ValueError(
                f"CovNetModule: noise_granularity must be 'chunk' or 'run', "
                f"got {noise_granularity!r}"
            )
        self.save_hyperparameters()
        self.net = CovNet(covnet or CovNetConfig())
        self.eskf_base = load_config(eskf_config)
        self.eskf_explicit: set[str] = set()
        if eskf_config is not None:
            # the filter's own keys (a config file may also hold a ``smoother:`` section)
            fields = {spec.name for spec in dataclasses.fields(EskfConfig)}
            self.eskf_explicit = set(read_config_keys(eskf_config)) & fields
        self.chunk_windows = chunk_windows
        self.noise_granularity = noise_granularity
        self.use_weather_labels = use_weather_labels
        self.weights = {
            "position": position_weight,
            "orientation": orientation_weight,
            "nll": nll_weight,
            "weather_ce": weather_weight,
        }
        self.lr = lr
        self.weight_decay = weight_decay
        self.max_figures = max_figures
        self._val_stats: dict[str, torch.Tensor] = {}
        self._figures_done = 0
        self._figure_tags: set[str] = set()
        self._val_cfg = self.eskf_base
        self._imu_rates_hz: list[float] = []

    # ------------------------------------------------------------------------------------
    def forward(self, batch: RunBatch) -> tuple[CovNetOutput, torch.Tensor]:
        """Per-window network outputs.

        Returns:
            the network's output per window (``log_scales`` (B, W, 7), ``fusion_weights``
            (B, W, S), ``weather_logits`` (B, W, C)) and the effective log scales
            (B, W, 7) with the fusion weights folded in.
        """
        b, w = batch.imu.shape[:2]
        weather = batch.weather.flatten() if self.use_weather_labels else None
        out = self.net(
            batch.imu.flatten(0, 1),
            batch.wheel.flatten(0, 1),
            batch.wheel_present.flatten(0, 1),
            batch.residual_stats.flatten(0, 1),
            weather,
        )
        effective = apply_fusion_weights(
            out.log_scales, out.fusion_weights, self.net.config.pose_sources
        )
        per_window = CovNetOutput(
            *(
                x.unflatten(0, (b, w))
                for x in (out.log_scales, out.fusion_weights, out.weather_logits)
            )
        )
        return per_window, effective.unflatten(0, (b, w))

    def eskf_config(self, seq: Sequence) -> EskfConfig:
        """The filter settings for a batch (config file + the first run's metadata)."""
        meta = seq.meta.get("per_sequence", [seq.meta])[0]
        return config_for_sequence(self.eskf_base, meta, self.eskf_explicit)

    def _scaled_sequence(
        self, seq: Sequence, log_scales: torch.Tensor, pose_source: list[str | None]
    ) -> Sequence:
        """``seq`` with pose covariances times ``exp(log_scale)`` of each run's source."""
        if seq.poses is None:
            return seq
        columns = torch.tensor(
            [LOG_SCALE_SENSORS.index(s or "vo") for s in pose_source], device=log_scales.device
        )
        factor = torch.exp(log_scales.gather(1, columns[:, None])[:, 0])
        factor = factor.to(seq.poses.covariance)[:, None, None, None]
        poses = dataclasses.replace(seq.poses, covariance=seq.poses.covariance * factor)
        return dataclasses.replace(seq, poses=poses)

    def start_state(self, batch: RunBatch, cfg: EskfConfig) -> tuple[NavState, torch.Tensor]:
        """State (B, ...) and conventional covariance (B, 15, 15) at each run's first IMU
        sample; here :func:`~msf_torch.frontend.init.initial_state` (a subclass may start
        from known states)."""
        return initial_state(batch.sequence, cfg)

    def scored_epochs(self, batch: RunBatch, result: EskfResult) -> torch.Tensor:
        """(B, E + 1) bool: the epochs of one chunk's result that enter the loss; here every
        real epoch but the chunk's first (it belongs to the previous chunk)."""
        mask = result.mask.clone()
        mask[:, 0] = False
        return mask

    def run_chunks(
        self, batch: RunBatch, log_scales: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], list[EskfResult]]:
        """Run the filter chunk by chunk and sum the trajectory loss terms.

        Args:
            batch: B runs of W windows.
            log_scales: (B, W, 7) effective log-variance scales.

        Returns:
            sums of ``position`` (m^2), ``orientation`` (rad^2), ``nll`` over the real
            epochs, and their ``count``; the per-chunk :class:`EskfResult` list.

        Raises:
            ValueError: a run has no ground truth.
        """
        seq = batch.sequence
        if seq.ground_truth is None or bool((seq.ground_truth.counts() < 2).any()):
            raise ValueError(f"training needs ground truth in every run: {seq.names}")
        cfg = self.eskf_config(seq)
        base = EskfNoise.from_config(cfg, seq.imu.t.dtype, seq.imu.t.device)
        length = self.net.config.window_length
        windows = batch.windows
        state, cov = self.start_state(batch, cfg)
        totals = {k: seq.imu.t.new_zeros(()) for k in ("position", "orientation", "nll")}
        totals["count"] = seq.imu.t.new_zeros(())
        results = []
        min_samples = cfg.imu_interpolated_min_samples
        for w0, w1, first, last in _chunk_samples(
            seq.imu, windows, self.chunk_windows, length, min_samples
        ):
            scales = log_scales[:, w0:w1] if self.noise_granularity == "chunk" else log_scales
            scales = scales.mean(1).to(seq.imu.t.dtype)
            chunk = dataclasses.replace(
                self._scaled_sequence(seq, scales, batch.pose_source),
                imu=seq.imu.map(lambda x, a=first, b=last: x[:, a : b + 1]),
            )
            result = run_eskf(chunk, cfg, scaled_noise(base, scales), initial=(state, cov))
            state, cov = _final(result)
            position, rotation = truth_at(seq.ground_truth, result.t)
            mask = self.scored_epochs(batch, result)
            err_p = result.position - position
            err_r = so3.log(rotation.mT @ result.rotation)
            p_cov = result.covariance[..., 0:3, 0:3]
            chol, _ = torch.linalg.cholesky_ex(p_cov)
            white = torch.linalg.solve_triangular(chol, err_p[..., None], upper=False)[..., 0]
            log_det = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
            nll = 0.5 * ((white**2).sum(-1) + log_det)
            m = mask.to(err_p.dtype)
            totals["position"] = totals["position"] + ((err_p**2).sum(-1) * m).sum()
            totals["orientation"] = totals["orientation"] + ((err_r**2).sum(-1) * m).sum()
            totals["nll"] = totals["nll"] + torch.where(mask, nll, 0.0).sum()
            totals["count"] = totals["count"] + m.sum()
            results.append(result)
        return totals, results

    def _losses(self, batch: RunBatch) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Loss terms (means) and the intermediate outputs for logging."""
        out, log_scales = self(batch)
        logits = out.weather_logits
        totals, results = self.run_chunks(batch, log_scales)
        count = totals["count"].clamp_min(1.0)
        terms = {k: (totals[k] / count).float() for k in ("position", "orientation", "nll")}
        unknown = self.net.config.unknown_weather
        labelled = batch.weather != unknown
        if bool(labelled.any()):
            terms["weather_ce"] = F.cross_entropy(logits[labelled], batch.weather[labelled])
        else:
            terms["weather_ce"] = logits.new_zeros(())
        terms["loss"] = sum(self.weights[k] * terms[k] for k in _TERMS)
        extra = {"out": out, "labelled": labelled, "results": results}
        return terms, extra

    def _log_terms(self, prefix: str, terms: dict[str, torch.Tensor], batch_size: int) -> None:
        for key, value in terms.items():
            self.log(
                f"{prefix}/{key}",
                value.detach(),
                batch_size=batch_size,
                prog_bar=key == "loss",
                sync_dist=prefix != "train",
            )

    def training_step(self, batch: RunBatch, batch_idx: int) -> torch.Tensor:
        """One batch: forward, filter, loss (logged as ``train/*``)."""
        terms, extra = self._losses(batch)
        batch_size = batch.imu.shape[0]
        rates = batch.sequence.imu.median_rate_hz()
        self._imu_rates_hz.extend(rates[rates.isfinite()].tolist())
        self._log_terms("train", terms, batch_size)
        slip = torch.cat([r.slip_factor[r.mask] for r in extra["results"]])
        self.log("train/slip_factor_mean", slip.mean().float(), batch_size=batch_size)
        return terms["loss"]

    # ------------------------------------------------------------------------------------
    def on_validation_epoch_start(self) -> None:
        """Reset the per-weather accumulators and the figure count."""
        classes = len(self.net.config.weather_classes) + 1
        sources = len(self.net.config.pose_sources)
        self._val_stats = {
            "log_scales": torch.zeros(classes, len(LOG_SCALE_SENSORS), device=self.device),
            "fusion": torch.zeros(classes, sources, device=self.device),
            "count": torch.zeros(classes, device=self.device),
            "correct": torch.zeros((), device=self.device),
            "labelled": torch.zeros((), device=self.device),
            "slip_sum": torch.zeros((), device=self.device),
            "slip_flagged": torch.zeros((), device=self.device),
            "epochs": torch.zeros((), device=self.device),
        }
        self._figures_done = 0
        self._figure_tags = set()

    def validation_step(self, batch: RunBatch, batch_idx: int) -> None:
        """Loss terms (``val/*``), per-weather statistics and trajectory figures."""
        terms, extra = self._losses(batch)
        self._log_terms("val", terms, batch.imu.shape[0])
        stats = self._val_stats
        weather = batch.weather.flatten()
        out = extra["out"]
        stats["log_scales"].index_add_(0, weather, out.log_scales.flatten(0, 1).float())
        stats["fusion"].index_add_(0, weather, out.fusion_weights.flatten(0, 1).float())
        stats["count"].index_add_(0, weather, torch.ones_like(weather, dtype=torch.float32))
        labelled = extra["labelled"]
        predicted = out.weather_logits.argmax(-1)
        stats["correct"] += (predicted == batch.weather)[labelled].sum()
        stats["labelled"] += labelled.sum()
        self._val_cfg = self.eskf_config(batch.sequence)
        flag = self._val_cfg.slip_flag_below
        for result in extra["results"]:
            slip = result.slip_factor[result.mask].float()
            stats["slip_sum"] += slip.sum()
            stats["slip_flagged"] += (slip < flag).sum()
            stats["epochs"] += slip.numel()
        if (
            not self.trainer.sanity_checking
            and self.trainer.is_global_zero
            and isinstance(self.logger, TensorBoardLogger)
        ):
            self._add_figures(batch, extra["results"])

    def _add_figures(self, batch: RunBatch, results: list[EskfResult]) -> None:
        """Plan view (truth and estimate) and slip factor per run, up to ``max_figures``."""
        truth = batch.sequence.ground_truth
        position = torch.cat([r.position for r in results], 1).detach().cpu()
        slip = torch.cat([r.slip_factor for r in results], 1).detach().cpu()
        times = torch.cat([r.t for r in results], 1).detach().cpu()
        mask = torch.cat([r.mask for r in results], 1).cpu()
        for b, name in enumerate(batch.sequence.names):
            if self._figures_done >= self.max_figures:
                return
            fig = Figure(figsize=(8, 4))
            ax_xy, ax_slip = fig.subplots(1, 2)
            real = truth.mask[b].cpu()
            ref = truth.position[b].cpu()[real]
            est = position[b][mask[b]]
            ax_xy.plot(ref[:, 0], ref[:, 1], "k-", label="truth")
            ax_xy.plot(est[:, 0], est[:, 1], "r-", label="ESKF + CovNet")
            ax_xy.set(xlabel="x [m]", ylabel="y [m]", title=name, aspect="equal")
            ax_xy.legend(loc="best")
            ax_slip.plot(times[b][mask[b]], slip[b][mask[b]])
            ax_slip.set(xlabel="t [s]", ylabel="slip factor", ylim=(0.0, 1.05))
            fig.tight_layout()
            tag, repeat = f"val_trajectory/{name}", 1
            while tag in self._figure_tags:  # two validation runs of one name (dayA/run.npz,
                repeat += 1  # dayB/run.npz): one figure each
                tag = f"val_trajectory/{name}-{repeat}"
            self._figure_tags.add(tag)
            self.logger.experiment.add_figure(tag, fig, global_step=self.global_step)
            self._figures_done += 1

    def _log_reduced(self, name: str, value: float) -> None:
        """Log a value already reduced over ranks (rank 0 writes it)."""
        self.log(name, value, rank_zero_only=True)

    def on_validation_epoch_end(self) -> None:
        """Reduce the per-weather statistics over ranks; log sigmas, fusion weights, slip."""
        reduce = self.trainer.strategy.reduce
        stats = {k: reduce(v, reduce_op="sum") for k, v in self._val_stats.items()}
        if self.trainer.sanity_checking:
            return
        cfg = self.net.config
        names = (*cfg.weather_classes, "unknown")
        base = EskfNoise.from_config(self._val_cfg)
        for k, weather in enumerate(names):
            count = float(stats["count"][k])
            if count == 0:
                continue
            mean = (stats["log_scales"][k] / count).double()
            noise = scaled_noise(base, mean)
            sigmas = {
                "wheel": noise.wheel_speed_sigma,
                "nhc": noise.nhc_sigma,
                "gnss": noise.gnss_sigma_scale,
                "imu_gyro": noise.imu.gyro_noise_density,
                "imu_accel": noise.imu.accel_noise_density,
            }
            for sensor in ("vo", "lidar"):
                sigmas[sensor] = torch.exp(0.5 * mean[LOG_SCALE_SENSORS.index(sensor)])
            for sensor, value in sigmas.items():
                self._log_reduced(f"sigma/{sensor}/{weather}", float(value))
            for s, source in enumerate(cfg.pose_sources):
                value = float(stats["fusion"][k, s] / count)
                self._log_reduced(f"fusion/{source}/{weather}", value)
        if float(stats["labelled"]) > 0:
            accuracy = float(stats["correct"] / stats["labelled"])
            self._log_reduced("val/weather_accuracy", accuracy)
        epochs = max(float(stats["epochs"]), 1.0)
        self._log_reduced("val/slip_factor_mean", float(stats["slip_sum"]) / epochs)
        flagged = float(stats["slip_flagged"]) / epochs
        self._log_reduced("val/slip_flagged_fraction", flagged)

    # ------------------------------------------------------------------------------------
    def test_step(self, batch: RunBatch, batch_idx: int) -> None:
        """Loss terms on the test split (``test/*``)."""
        terms, _ = self._losses(batch)
        self._log_terms("test", terms, batch.imu.shape[0])

    def configure_optimizers(self) -> torch.optim.Optimizer:
        """Adam over the network's parameters."""
        return torch.optim.Adam(self.net.parameters(), lr=self.lr, weight_decay=self.weight_decay)

    def noise_application(self) -> NoiseApplication:
        """How this module applied the network's scales in training (stored in
        ``covnet.pt``): its chunking, the median IMU rate of the training runs seen and the
        filter settings its ``eskf_config`` set."""
        rates = self._imu_rates_hz
        return NoiseApplication(
            imu_rate_hz=round(statistics.median(rates), 6) if rates else None,
            chunk_windows=self.chunk_windows,
            noise_granularity=self.noise_granularity,
            filter_settings={k: getattr(self.eskf_base, k) for k in sorted(self.eskf_explicit)},
        )

    def on_fit_end(self) -> None:
        """Write the trained network and :meth:`noise_application` to
        ``<log_dir>/covnet.pt`` (global rank 0)."""
        log_dir = self.trainer.log_dir
        if self.trainer.is_global_zero and log_dir is not None:
            Path(log_dir).mkdir(parents=True, exist_ok=True)
            save_checkpoint(Path(log_dir) / "covnet.pt", self.net, self.noise_application())
