"""Learned covariances and source weights vs tuned fixed covariances, held-out weather runs.

Runs: the recipe of ``training/configs/default.yaml`` (its ``data`` section:
:func:`~msf_torch.learning.data.simulate_labelled_run`, 40 s, 100 Hz IMU, wheels, GNSS with
one random 15-25 s outage besides the urban ones, VO and LiDAR odometry fused as named pose
sources with the weather error their covariances do not report (night blur for VO, fog
clutter for LiDAR: ``msf_torch.sim.weather``), weather changing within runs). Tuning uses
the first ``--train-runs`` of the training seeds (``0, 1, ...``, the runs the network was
trained on); scoring uses the test split's seeds (``2 * SPLIT_SEED_STRIDE + i``), which
neither training nor tuning ever sees.

Methods, each scored by ATE (position RMSE against the simulator's truth at the filter
epochs, no alignment: GNSS fixes the frame), pooled over the test runs' epochs:

* ``learned``: the checkpoint's CovNet (its inputs include the innovation statistics of a
  reference pass with the config's noise), weather from the labels, noise per 10-window
  chunk (:mod:`msf_torch.learning.inference`, as ``msf run``); ``learned_unlabelled`` the
  same with the labels withheld (the network infers the weather).
* ``fixed_best``: the best single fixed covariance set on the tuning runs, from a grid of
  log-variance scales (natural log) of the GNSS, wheel, NHC, IMU (gyro and accelerometer
  together), VO and LiDAR noise: a two-level factorial ``{-LEVEL, +LEVEL}^6`` plus the
  centre (the config's noise), 65 sets with the default ``--level 1.5``.
* ``fixed_per_weather``: per weather condition the set of the same grid with the lowest
  position error over the tuning runs' epochs labelled with that condition; applied on the
  test runs per weather segment (1 s windows, from the labels).
* ``config``: the config's noise (the grid's centre).

Source weighting (acceptance 2), per held-out run, with the network's noise for every
sensor but the two odometry sources: ``learned`` (its VO / LiDAR scales and fusion weights)
against ``equal_weights`` (both sources at their declared covariances, equal weight) and
against each source alone (``vo_only``, ``lidar_only``: the other source not fused).

Also: NEES of the position with the learned covariances, fraction of epochs inside the
two-sided 95 % chi-square bounds (3 dof); weather-head accuracy with labels withheld.

Also the reduction against ``config`` (the noise ``msf run`` uses without a network) and
the runs where learned beats it: the grid's best set is an argmin over near-ties on few
tuning runs and can generalise worse than the config noise, so a target met against
``fixed_best`` alone does not show that the network earns its place.

Targets (issue 4): ATE(learned) at least 30 % below the better of ``fixed_best`` and
``config`` (``ate_target_met`` is judged so; ``ate_target_as_worded_met`` judges the issue's
wording, ``fixed_best`` alone) and 15 % below ``fixed_per_weather``; learned
weighting better than equal weights in every held-out run and better than the best single
source in >= 90 % of them; NEES fraction >= 90 %.

    python benchmarks/learned.py [--checkpoint checkpoints/covnet_weather.pt]
        [--train-runs 8] [--test-runs 10] [--level 1.5]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import time
from pathlib import Path

import torch
import yaml

from msf_torch.eval.nees import fraction_inside, nees
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.learning.covnet import LOG_SCALE_SENSORS, scaled_noise
from msf_torch.learning.data import SPLIT_SEED_STRIDE, simulate_labelled_run
from msf_torch.learning.features import run_features
from msf_torch.learning.inference import (
    learned_scales,
    load_learned,
    run_piecewise,
)
from msf_torch.learning.module import truth_at
from msf_torch.types import Sequence, batch_sequences

try:
    from benchmarks._common import emit_json, log
except ImportError:  # run as a script from benchmarks/
    from _common import emit_json, log

GRID_AXES = {
    "gnss": ("gnss",),
    "wheel": ("wheel",),
    "nhc": ("nhc",),
    "imu": ("imu_gyro", "imu_accel"),
    "vo": ("vo",),
    "lidar": ("lidar",),
}
"""Grid axis -> the :data:`LOG_SCALE_SENSORS` columns it sets."""

TRAINING_CONFIG = Path(__file__).resolve().parent.parent / "training" / "configs" / "default.yaml"
WEATHER_CHECKPOINT = Path(__file__).resolve().parent.parent / "checkpoints" / "covnet_weather.pt"
"""The network trained by ``default.yaml`` (see ``checkpoints/README.md``)."""
WINDOW = 100
SOURCES = ("vo", "lidar")


def recipe() -> dict:
    """The simulated-run settings of the training config's ``data`` section."""
    with open(TRAINING_CONFIG, encoding="utf-8") as handle:
        data = yaml.safe_load(handle)["data"]
    return {
        "duration_s": float(data["duration_s"]),
        "imu_rate_hz": float(data["imu_rate_hz"]),
        "pose_source": data.get("pose_source"),
        "gnss_outage_count": int(data.get("gnss_outage_count", 0)),
        "gnss_outage_duration_s": tuple(data.get("gnss_outage_duration_s", (10.0, 20.0))),
    }


def grid(level: float) -> list[torch.Tensor]:
    """The centre and the two-level factorial, as (7,) log-scale vectors."""
    points = [torch.zeros(len(LOG_SCALE_SENSORS), dtype=torch.float64)]
    for signs in itertools.product((-level, level), repeat=len(GRID_AXES)):
        point = torch.zeros(len(LOG_SCALE_SENSORS), dtype=torch.float64)
        for value, columns in zip(signs, GRID_AXES.values(), strict=True):
            for column in columns:
                point[LOG_SCALE_SENSORS.index(column)] = value
        points.append(point)
    return points


def epoch_errors(result: EskfResult, seq: Sequence) -> tuple[torch.Tensor, torch.Tensor]:
    """Position errors (B, E + 1, 3) at the epochs and the mask of real epochs but the
    start."""
    position, _ = truth_at(seq.ground_truth, result.t)
    mask = result.mask.clone()
    mask[:, 0] = False
    return result.position - position, mask


def epoch_weather(seq: Sequence, t: torch.Tensor, classes: tuple[str, ...]) -> torch.Tensor:
    """(B, N) weather class index of each time (``len(classes)`` = unlabelled)."""
    out = torch.full(t.shape, len(classes), dtype=torch.long)
    for k, name in enumerate(classes):
        intervals = seq.labels.get(f"weather:{name}")
        if intervals is None:
            continue
        for b in range(t.shape[0]):
            for lo, hi in intervals[b].tolist():
                out[b][(t[b] >= lo) & (t[b] <= hi)] = k
    return out


def fixed_batch(seq: Sequence, cfg: EskfConfig, scales: torch.Tensor) -> EskfResult:
    """The filter over a batch with one (7,) set of log scales for every run."""
    return run_eskf(seq, cfg, scaled_noise(EskfNoise.from_config(cfg), scales))


def with_sources(scales: torch.Tensor, value: float | None) -> torch.Tensor:
    """(W, 7) scales with the VO and LiDAR columns set to ``value`` (unchanged for None)."""
    out = scales.clone()
    if value is not None:
        for name in SOURCES:
            out[:, LOG_SCALE_SENSORS.index(name)] = value
    return out


def rmse(sq_sum: float, count: float) -> float:
    """Root of a mean of squares."""
    return (sq_sum / max(count, 1.0)) ** 0.5


def weighting(per_run: dict[str, list[float]]) -> dict:
    """Acceptance 2 from per-run ATEs: learned vs equal weights and vs the best single source."""
    learned = per_run["learned"]
    single = [min(v, li) for v, li in zip(per_run["vo_only"], per_run["lidar_only"], strict=True)]
    runs = max(len(learned), 1)
    beats_equal = sum(a < b for a, b in zip(learned, per_run["equal_weights"], strict=True))
    beats_single = sum(a < b for a, b in zip(learned, single, strict=True))
    return {
        "runs": len(learned),
        "better_than_equal_weights": beats_equal,
        "better_than_best_single_source": beats_single,
        "fraction_better_than_best_single": round(beats_single / runs, 4),
        "target_equal": "all runs",
        "target_single": 0.90,
        "met": beats_equal == len(learned) and beats_single / runs >= 0.90,
    }


def main() -> None:
    """Tune, score, print the table on stderr and one JSON line on stdout."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=WEATHER_CHECKPOINT)
    parser.add_argument("--train-runs", type=int, default=8, help="tuning runs (train seeds)")
    parser.add_argument("--test-runs", type=int, default=10, help="held-out runs (test seeds)")
    parser.add_argument("--level", type=float, default=1.5, help="grid log-scale level")
    args = parser.parse_args()
    start = time.perf_counter()
    learned = load_learned(args.checkpoint)
    classes = learned.model.config.weather_classes
    n_classes = len(classes)

    settings = recipe()
    train = [simulate_labelled_run(s, **settings) for s in range(args.train_runs)]
    test_seeds = [2 * SPLIT_SEED_STRIDE + i for i in range(args.test_runs)]
    test = [simulate_labelled_run(s, **settings) for s in test_seeds]
    train_seq = batch_sequences(train)
    cfg = config_for_sequence(load_config(None), train[0].meta, set())

    # --- tuning: every grid point on all tuning runs, errors pooled overall and per weather
    points = grid(args.level)
    overall = torch.zeros(len(points))
    per_weather = torch.zeros(len(points), n_classes)
    counts = torch.zeros(n_classes)
    with torch.no_grad():
        for i, point in enumerate(points):
            result = fixed_batch(train_seq, cfg, point)
            err, mask = epoch_errors(result, train_seq)
            sq = (err**2).sum(-1)
            weather = epoch_weather(train_seq, result.t, classes)
            overall[i] = rmse(float(sq[mask].sum()), float(mask.sum()))
            for k in range(n_classes):
                here = mask & (weather == k)
                per_weather[i, k] = rmse(float(sq[here].sum()), float(here.sum()))
                counts[k] = float(here.sum())
            log(f"grid {i + 1}/{len(points)}: ATE {overall[i]:.3f} m")
    best = int(overall.argmin())
    best_per = [
        int(per_weather[:, k].argmin()) if counts[k] > 0 else best for k in range(n_classes)
    ]
    tuned_s = time.perf_counter() - start

    # --- held-out scoring
    methods = (
        "learned",
        "learned_unlabelled",
        "fixed_best",
        "fixed_per_weather",
        "config",
        "equal_weights",
        "vo_only",
        "lidar_only",
    )
    sums = dict.fromkeys(methods, 0.0)
    total = 0.0
    inside = hits = labelled = 0.0
    per_run: dict[str, list[float]] = {m: [] for m in methods}
    with torch.no_grad():
        for n, seq in enumerate(test):
            cfg_run = config_for_sequence(load_config(None), seq.meta, set())
            scales = learned_scales(seq, learned, cfg_run)
            blind = learned_scales(seq, learned, cfg_run, use_labels=False)
            labels = run_features(seq, WINDOW, ("gnss",), classes).weather
            choice = [best_per[k] if k < n_classes else best for k in labels.tolist()]
            per_segment = torch.stack([points[c] for c in choice])
            declared = with_sources(scales.log_scales, 0.0)

            def piecewise(
                log_scales: torch.Tensor, run_cfg: EskfConfig = cfg_run, run: Sequence = seq
            ) -> EskfResult:
                return run_piecewise(run, run_cfg, log_scales, WINDOW, None)

            results = {
                "learned": piecewise(scales.log_scales),
                "learned_unlabelled": piecewise(blind.log_scales),
                "fixed_best": fixed_batch(seq, cfg_run, points[best]),
                "fixed_per_weather": piecewise(per_segment),
                "config": run_eskf(seq, cfg_run),
                "equal_weights": piecewise(declared),
                **{
                    f"{name}_only": piecewise(
                        declared, dataclasses.replace(cfg_run, pose_sources=[name])
                    )
                    for name in SOURCES
                },
            }
            for name, result in results.items():
                err, mask = epoch_errors(result, seq)
                sq = float((err**2).sum(-1)[mask].sum())
                sums[name] += sq
                per_run[name].append(round(rmse(sq, float(mask.sum())), 4))
                if name == "learned":
                    total += float(mask.sum())
                    values = nees(err, result.covariance[..., 0:3, 0:3], mask)
                    inside += float(fraction_inside(values, 3, mask=mask)) * float(mask.sum())
            known = blind.labels != n_classes
            hits += float((blind.inferred == blind.labels)[known].sum())
            labelled += float(known.sum())
            log(
                f"test run {n + 1}/{len(test)}: "
                + ", ".join(f"{m} {per_run[m][-1]:.3f}" for m in methods)
            )
    ate = {m: round(rmse(sums[m], total), 4) for m in methods}
    for m in methods:
        log(f"{m:20s} ATE {ate[m]:.3f} m  per run {per_run[m]}")
    record = {
        "benchmark": "learned",
        "checkpoint": str(learned.path),
        "sha256": learned.sha256,
        "train_seeds": list(range(args.train_runs)),
        "test_seeds": test_seeds,
        "recipe": {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()},
        "grid": {
            "axes": {k: list(v) for k, v in GRID_AXES.items()},
            "levels": [-args.level, 0.0, args.level],
            "points": len(points),
            "best": {
                k: float(points[best][LOG_SCALE_SENSORS.index(v[0])]) for k, v in GRID_AXES.items()
            },
            "best_per_weather": {
                c: {
                    k: float(points[best_per[i]][LOG_SCALE_SENSORS.index(v[0])])
                    for k, v in GRID_AXES.items()
                }
                for i, c in enumerate(classes)
            },
            "tuning_ate_m": round(float(overall[best]), 4),
        },
        "ate_m": ate,
        "ate_per_run_m": per_run,
        "reduction_vs_fixed_best": round(1.0 - ate["learned"] / ate["fixed_best"], 4),
        "reduction_vs_fixed_per_weather": round(1.0 - ate["learned"] / ate["fixed_per_weather"], 4),
        "reduction_vs_config": round(1.0 - ate["learned"] / ate["config"], 4),
        "runs_learned_better_than_config": sum(
            a < b for a, b in zip(per_run["learned"], per_run["config"], strict=True)
        ),
        "target_vs_fixed_best": 0.30,
        "target_vs_fixed_per_weather": 0.15,
        # judged against the stronger of the two fixed sets a user could pick without the
        # test runs (the grid's choice on the tuning runs and the configured noise, itself a
        # grid point): a grid choice that generalises badly must not make the target easy
        "ate_target_met": 1.0 - ate["learned"] / min(ate["fixed_best"], ate["config"]) >= 0.30
        and 1.0 - ate["learned"] / ate["fixed_per_weather"] >= 0.15,
        # the wording alone (the grid's choice and the per-weather sets), for the record
        "ate_target_as_worded_met": 1.0 - ate["learned"] / ate["fixed_best"] >= 0.30
        and 1.0 - ate["learned"] / ate["fixed_per_weather"] >= 0.15,
        "nees_fraction_inside_95": round(inside / max(total, 1.0), 4),
        "nees_target": 0.90,
        "nees_target_met": inside / max(total, 1.0) >= 0.90,
        "weather_accuracy_unlabelled": round(hits / max(labelled, 1.0), 4),
        "source_weighting": weighting(per_run),
        "tuning_s": round(tuned_s, 1),
        "wall_s": round(time.perf_counter() - start, 1),
    }
    emit_json(record)


if __name__ == "__main__":
    main()
