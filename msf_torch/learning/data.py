"""LightningDataModule over labelled runs: simulated on the fly or loaded from files.

Each split (train / val / test) holds runs from its list of files (any format
:func:`msf_torch.io.load_sequence` reads, e.g. native ``.npz``) or, when the list is empty,
``<split>_runs`` runs simulated with :func:`msf_torch.sim.simulate_run` under a random
:class:`~msf_torch.sim.WeatherSchedule` (:func:`~msf_torch.sim.weather_slip_config`,
:func:`~msf_torch.sim.apply_weather`). Simulated runs of split ``k`` (train 0, val 1,
test 2) use the seeds ``seed + k * SPLIT_SEED_STRIDE + i``, so the splits are disjoint by
construction and every rank of a distributed job builds the same runs.

A batch (:class:`RunBatch`) holds B runs (:func:`msf_torch.types.batch_sequences`) cropped
to a common length of ``W * L + 1`` IMU samples (W windows of L = ``window_length``
samples, plus the end sample), and the per-window CovNet inputs
(:class:`msf_torch.learning.covnet.CovNet`):

* ``imu`` (B, W, L, 6): ``[gyro rad/s, accel m/s^2]``, window ``w`` = IMU samples
  ``[w L, (w + 1) L)``;
* ``wheel`` (B, W, L, 2): left / right rim speeds held (zero-order) at the IMU times, m/s;
  ``wheel_present`` (B, W, L) bool: a wheel sample lies within ``wheel_hold_s`` before;
* ``residual_stats`` (B, W, S, 4): per pose source of ``CovNetConfig.pose_sources``
  (``"gnss"`` is ``Sequence.gnss``, other names ``Sequence.pose_sources[name]`` or the
  ``poses`` stream of that source): the mean and largest NIS per degree of freedom and the
  gate-rejected fraction of the source's measurements in a reference pass of the filter with
  the configured noise, and the ``dropout_fraction`` (the fraction of the source's expected
  samples missing in the window, widened to two sample intervals for slow streams, from its
  median sample interval over the run; 1 for a source the run lacks)
  (:func:`~msf_torch.learning.features.run_features`);
* ``weather`` (B, W) int64: the index in ``CovNetConfig.weather_classes`` of the
  ``"weather:<c>"`` label interval holding the window's centre, or the unknown index.
"""

from __future__ import annotations

__all__ = [
    "SPLITS",
    "SPLIT_SEED_STRIDE",
    "RunBatch",
    "RunFeatures",
    "run_features",
    "simulate_labelled_run",
    "simulate_labelled_weather_run",
    "collate_runs",
    "RunDataModule",
]

import dataclasses
import functools
import warnings
from dataclasses import dataclass
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from msf_torch.frontend.config import config_for_sequence, load_config, read_config_keys
from msf_torch.io import DataError, load_sequence
from msf_torch.learning.covnet import IMU_RATE_TOLERANCE
from msf_torch.learning.features import RunFeatures, pose_source_of, run_features
from msf_torch.sim import (
    SimConfig,
    WeatherRun,
    WeatherSchedule,
    apply_weather,
    simulate_run,
    weather_slip_config,
)
from msf_torch.types import Sequence, batch_sequences

SPLITS = ("train", "val", "test")
SPLIT_SEED_STRIDE = 1_000_000
"""Seed offset between splits; a split may hold at most this many simulated runs."""


@dataclass
class RunBatch:
    """B runs and their per-window CovNet inputs.

    Attributes:
        sequence: B runs, IMU cropped to ``W * L + 1`` samples each (float64).
        imu: (B, W, L, 6); wheel (B, W, L, 2); wheel_present (B, W, L) bool;
            residual_stats (B, W, S, 4); weather (B, W) int64 (see :class:`RunFeatures`).
        pose_source: per run, the source of ``sequence.poses`` (``"vo"``, ``"lidar"``) or
            None.
    """

    sequence: Sequence
    imu: torch.Tensor
    wheel: torch.Tensor
    wheel_present: torch.Tensor
    residual_stats: torch.Tensor
    weather: torch.Tensor
    pose_source: list[str | None]

    @property
    def windows(self) -> int:
        """W, windows per run."""
        return self.imu.shape[1]

    def to(self, device: Any = None, **_: Any) -> RunBatch:
        """Move every tensor to ``device`` (Lightning calls this; extra options ignored)."""
        moved = {
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor)
        }
        return dataclasses.replace(self, sequence=self.sequence.to(device), **moved)


def simulate_labelled_weather_run(
    seed: int,
    duration_s: float,
    imu_rate_hz: float = 100.0,
    pose_source: str | None = None,
    mean_segment_s: float = 15.0,
    min_segment_s: float = 5.0,
    gnss_outage_count: int = 0,
    gnss_outage_duration_s: tuple[float, float] = (10.0, 20.0),
    unreported_error: bool = True,
) -> WeatherRun:
    """The :class:`~msf_torch.sim.weather.WeatherRun` behind :func:`simulate_labelled_run`
    (same seed, same draws): the run plus what its pose sources did (per-sample
    ``error_scale``, drift and white noise: :class:`~msf_torch.sim.weather.PoseSourceTruth`),
    for oracle baselines. ``sequence.names`` is ``["sim-<seed>"]``.

    Args:
        seed: non-negative int; the schedule, slip, path and weather draws use seeds
            derived from it (``numpy.random.SeedSequence(seed)``).
        duration_s: run length, s.
        imu_rate_hz: IMU and ground-truth rate, Hz.
        pose_source: ``"vo"``, ``"lidar"`` or None (see :func:`~msf_torch.sim.apply_weather`).
        mean_segment_s, min_segment_s: weather segment lengths, s
            (:meth:`~msf_torch.sim.WeatherSchedule.random`).
        gnss_outage_count, gnss_outage_duration_s: random GNSS outages
            (:class:`~msf_torch.sim.SimConfig`).
        unreported_error: the VO / LiDAR weather error their covariances do not report
            (:func:`~msf_torch.sim.apply_weather`; on for learning: it is what the
            network can learn beyond the declared covariances).
    """
    s_schedule, s_slip, s_run, s_weather = (
        int(x) for x in np.random.SeedSequence(int(seed)).generate_state(4)
    )
    schedule = WeatherSchedule.random(
        duration_s, s_schedule, mean_segment_s=mean_segment_s, min_segment_s=min_segment_s
    )
    base = SimConfig(
        duration_s=duration_s,
        imu_rate_hz=imu_rate_hz,
        gnss_outage_count=gnss_outage_count,
        gnss_outage_duration_s=gnss_outage_duration_s,
    )
    run = simulate_run(weather_slip_config(base, schedule, s_slip), s_run)
    wet = apply_weather(
        run, schedule, s_weather, pose_source=pose_source, unreported_error=unreported_error
    )
    return dataclasses.replace(
        wet, sequence=dataclasses.replace(wet.sequence, names=[f"sim-{seed}"])
    )


def simulate_labelled_run(
    seed: int,
    duration_s: float,
    imu_rate_hz: float = 100.0,
    pose_source: str | None = None,
    mean_segment_s: float = 15.0,
    min_segment_s: float = 5.0,
    gnss_outage_count: int = 0,
    gnss_outage_duration_s: tuple[float, float] = (10.0, 20.0),
    unreported_error: bool = True,
) -> Sequence:
    """One simulated run (B = 1) with a random weather schedule, weather-driven slip
    episodes and degraded GNSS / pose streams; labels ``"weather:<c>"``, ``"slip"``, ...
    (the arguments as in :func:`simulate_labelled_weather_run`)."""
    return simulate_labelled_weather_run(
        seed,
        duration_s,
        imu_rate_hz,
        pose_source,
        mean_segment_s,
        min_segment_s,
        gnss_outage_count,
        gnss_outage_duration_s,
        unreported_error,
    ).sequence


def _crop_imu(seq: Sequence, samples: int) -> Sequence:
    """A B = 1 sequence with only its first ``samples`` real IMU samples."""
    return dataclasses.replace(seq, imu=seq.imu.compact().map(lambda x: x[:, :samples]))


def collate_runs(items: list[tuple[Sequence, RunFeatures]], window_length: int) -> RunBatch:
    """Stack runs into a :class:`RunBatch`, cropping all to the shortest run's windows."""
    windows = min(f.imu.shape[0] for _, f in items)
    sequence = batch_sequences([_crop_imu(s, windows * window_length + 1) for s, _ in items])
    return RunBatch(
        sequence=sequence,
        imu=torch.stack([f.imu[:windows] for _, f in items]),
        wheel=torch.stack([f.wheel[:windows] for _, f in items]),
        wheel_present=torch.stack([f.wheel_present[:windows] for _, f in items]),
        residual_stats=torch.stack([f.residual_stats[:windows] for _, f in items]),
        weather=torch.stack([f.weather[:windows] for _, f in items]),
        pose_source=[pose_source_of(s) for s, _ in items],
    )


class RunDataModule(L.LightningDataModule):
    """Train / val / test runs (files or simulated) as :class:`RunBatch` batches.

    Args:
        train_files, val_files, test_files: runs to load per split (any format
            :func:`~msf_torch.io.load_sequence` reads); each needs ground truth covering its
            IMU span to within one window and more than ``window_length`` IMU samples
            (``setup`` raises :class:`~msf_torch.io.DataError` naming the file otherwise),
            and all runs of all splits one IMU rate (within ``IMU_RATE_TOLERANCE``);
            ``weather:<c>`` labels are optional (unlabelled windows add no weather loss).
            An empty list means simulated runs for that split.
        train_runs, val_runs, test_runs: simulated runs per split (< ``SPLIT_SEED_STRIDE``).
        duration_s: simulated run length, s.
        imu_rate_hz: simulated IMU rate, Hz.
        pose_source: simulated stream also put in ``Sequence.poses`` as absolute poses
            (``"vo"``, ``"lidar"``; default None: both sources are fused as odometry from
            ``Sequence.pose_sources``).
        gnss_outage_count, gnss_outage_duration_s: random GNSS outages per simulated run
            (:func:`simulate_labelled_run`).
        eskf_config: YAML of filter settings for the reference pass that gives the
            innovation features (as the module's ``eskf_config``; None = defaults); a run's
            metadata fills the keys the file leaves out, as in ``msf run --config``.
        seed: base seed of the simulated runs.
        batch_size: runs per batch.
        window_length: L, IMU samples per CovNet window (``CovNetConfig.window_length``).
        pose_sources, weather_classes: as in :class:`~msf_torch.learning.CovNetConfig`.
        num_workers: DataLoader workers (runs are built in ``setup``, so 0 is fine).
    """

    def __init__(
        self,
        train_files: list[str] | None = None,
        val_files: list[str] | None = None,
        test_files: list[str] | None = None,
        train_runs: int = 8,
        val_runs: int = 2,
        test_runs: int = 2,
        duration_s: float = 30.0,
        imu_rate_hz: float = 100.0,
        pose_source: str | None = None,
        gnss_outage_count: int = 0,
        gnss_outage_duration_s: tuple[float, float] = (10.0, 20.0),
        eskf_config: str | None = None,
        seed: int = 0,
        batch_size: int = 2,
        window_length: int = 100,
        pose_sources: tuple[str, ...] = ("gnss", "vo", "lidar"),
        weather_classes: tuple[str, ...] = ("sunny", "rain", "fog", "night", "snow"),
        num_workers: int = 0,
    ) -> None:
        super().__init__()
        files = {"train": train_files, "val": val_files, "test": test_files}
        counts = {"train": train_runs, "val": val_runs, "test": test_runs}
        for split in SPLITS:
            if not 0 <= counts[split] < SPLIT_SEED_STRIDE:
                raise ValueError(
                    f"RunDataModule: {split}_runs must lie in [0, {SPLIT_SEED_STRIDE}), "
                    f"got {counts[split]}"
                )
        if batch_size < 1:
            raise ValueError(f"RunDataModule: batch_size must be >= 1, got {batch_size}")
        self.files = {k: list(v or []) for k, v in files.items()}
        self.counts = counts
        self.duration_s = duration_s
        self.imu_rate_hz = imu_rate_hz
        self.pose_source = pose_source
        self.gnss_outage_count = gnss_outage_count
        self.gnss_outage_duration_s = tuple(gnss_outage_duration_s)
        self.eskf_base = load_config(eskf_config)
        self.eskf_config_path = eskf_config
        self.eskf_explicit: set[str] = set()
        if eskf_config is not None:
            self.eskf_explicit = set(read_config_keys(eskf_config))
        self.seed = seed
        self.batch_size = batch_size
        self.window_length = window_length
        self.pose_sources = tuple(pose_sources)
        self.weather_classes = tuple(weather_classes)
        self.num_workers = num_workers
        self.runs: dict[str, list[tuple[Sequence, RunFeatures]]] = {}

    def split_seeds(self, split: str) -> list[int]:
        """Simulator seeds of a split (empty when the split reads files)."""
        if self.files[split]:
            return []
        offset = self.seed + SPLITS.index(split) * SPLIT_SEED_STRIDE
        return [offset + i for i in range(self.counts[split])]

    def _load(self, path: str) -> Sequence:
        """One run of a file list, checked for what training needs.

        Raises:
            DataError: naming the file: it has no ground truth (field ``ground_truth``), the
                ground truth does not cover the IMU span (start or end more than one window
                away), or the run has no more than ``window_length`` IMU samples (field
                ``imu``).
        """
        seq = load_sequence(path)
        imu_t = seq.imu.compact().t[0]
        if imu_t.numel() <= self.window_length:
            raise DataError(
                path,
                f"{imu_t.numel()} IMU samples, training needs more than window_length = "
                f"{self.window_length} (one window)",
                field="imu",
            )
        truth = seq.ground_truth
        if truth is None or int(truth.counts()[0]) < 2:
            raise DataError(
                path,
                "no ground truth (at least 2 samples): training scores the filter against it "
                "(native .npz keys ground_truth/t, ground_truth/position, "
                "ground_truth/quaternion; native folder ground_truth.csv)",
                field="ground_truth",
            )
        truth_t = truth.compact().t[0]
        window_s = float(imu_t[self.window_length] - imu_t[0])
        start_gap, end_gap = float(truth_t[0] - imu_t[0]), float(imu_t[-1] - truth_t[-1])
        if max(start_gap, end_gap) > window_s:
            raise DataError(
                path,
                f"ground truth spans {float(truth_t[0]):.3f}-{float(truth_t[-1]):.3f} s, the "
                f"IMU {float(imu_t[0]):.3f}-{float(imu_t[-1]):.3f} s: more than one window "
                f"({window_s:.3f} s) of the run would be scored against a held pose "
                "(crop the run to the ground truth's span)",
                field="ground_truth",
            )
        unknown = sorted(
            name.split(":", 1)[1]
            for name in seq.labels
            if name.startswith("weather:") and name.split(":", 1)[1] not in self.weather_classes
        )
        if unknown:
            warnings.warn(
                f"{path}: weather labels {', '.join(unknown)} are not among the network's "
                f"weather_classes ({', '.join(self.weather_classes)}): their windows count as "
                "unknown weather (no weather loss); rename them or set weather_classes",
                stacklevel=2,
            )
        return seq

    def _build(self, split: str) -> list[tuple[Sequence, RunFeatures]]:
        if self.files[split]:
            sequences = [self._load(path) for path in self.files[split]]
        else:
            sequences = [
                simulate_labelled_run(
                    s,
                    self.duration_s,
                    self.imu_rate_hz,
                    self.pose_source,
                    gnss_outage_count=self.gnss_outage_count,
                    gnss_outage_duration_s=self.gnss_outage_duration_s,
                )
                for s in self.split_seeds(split)
            ]
        return [
            (
                seq,
                run_features(
                    seq,
                    self.window_length,
                    self.pose_sources,
                    self.weather_classes,
                    cfg=config_for_sequence(self.eskf_base, seq.meta, self.eskf_explicit),
                ),
            )
            for seq in sequences
        ]

    def check_model(self) -> None:
        """Compare the window length, pose sources and weather classes with the trainer's
        model's ``CovNetConfig``, and the filter settings of ``eskf_config`` with the
        model's (a model without a ``net`` CovNet, or no trainer: nothing to compare).

        Raises:
            ValueError: naming the ``data.*`` and ``model.*`` keys that differ.
        """
        model = getattr(self.trainer, "lightning_module", None)
        config = getattr(getattr(model, "net", None), "config", None)
        if config is None:
            return
        differ = [
            f"data.{key} = {ours} but model.covnet.{key} = {theirs}"
            for key, ours, theirs in (
                ("window_length", self.window_length, config.window_length),
                ("pose_sources", list(self.pose_sources), list(config.pose_sources)),
                ("weather_classes", list(self.weather_classes), list(config.weather_classes)),
            )
            if ours != theirs
        ]
        theirs = (getattr(model, "eskf_base", None), getattr(model, "eskf_explicit", None))
        if theirs[0] is not None and theirs != (self.eskf_base, self.eskf_explicit):
            keys = sorted(
                set(theirs[0].differing_keys(self.eskf_base)) | (theirs[1] ^ self.eskf_explicit)
            )
            files = (self.eskf_config_path, model.hparams.get("eskf_config"))
            named = [
                f"{side}.eskf_config {'unset' if path is None else '= ' + str(path)}"
                for side, path in zip(("data", "model"), files, strict=True)
            ]
            differ.append(
                "data.eskf_config and model.eskf_config give different filter settings "
                f"({', '.join(named)}; they differ in {', '.join(keys)}: the reference pass "
                "that feeds the network and the filter it trains through; msf run uses one "
                "--config for both)"
            )
        if differ:
            raise ValueError(
                "RunDataModule: " + "; ".join(differ) + " (set both to the same value)"
            )

    def setup(self, stage: str | None = None) -> None:
        """Build (once) the runs of the splits that ``stage`` needs, after
        :meth:`check_model`."""
        self.check_model()
        needed = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",)}
        for split in needed.get(stage or "", SPLITS):
            if split not in self.runs:
                self.runs[split] = self._build(split)
        self._check_imu_rates()

    def _check_imu_rates(self) -> None:
        """All built runs share one IMU rate (within ``IMU_RATE_TOLERANCE``): a window of
        ``window_length`` samples must span the same time in every run the network sees.

        Raises:
            DataError: a file's rate differs from the first file's (naming both).
            ValueError: simulated runs (``imu_rate_hz``) and files differ in rate.
        """
        first: tuple[str, float, bool] | None = None
        for split in SPLITS:
            files = self.files[split]
            for index, (seq, _) in enumerate(self.runs.get(split, [])):
                name = files[index] if files else f"simulated {split} run {index}"
                rate = float(seq.imu.median_rate_hz()[0])
                if first is None:
                    first = (name, rate, not files)
                if abs(rate / first[1] - 1.0) <= IMU_RATE_TOLERANCE:
                    continue
                message = (
                    f"IMU at {rate:.6g} Hz, but {first[0]} runs at {first[1]:.6g} Hz: one "
                    f"network's windows of {self.window_length} samples must span the same "
                    "time in every run (resample the runs to one rate"
                )
                if first[2] or not files:
                    raise ValueError(
                        f"RunDataModule: {name}: {message}, or set data.imu_rate_hz to the "
                        "files' rate for the simulated splits)"
                    )
                raise DataError(name, message + ")", field="imu")

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        return DataLoader(
            self.runs[split],
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            collate_fn=functools.partial(collate_runs, window_length=self.window_length),
        )

    def train_dataloader(self) -> DataLoader:
        """Shuffled training batches."""
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        """Validation batches, in order."""
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        """Test batches, in order."""
        return self._loader("test", shuffle=False)
