"""How much can VO / LiDAR source weighting move the ATE? Oracle bounds on held-out runs.

Issue 4, acceptance 2 asks for learned source weighting better than equal weights in every
held-out run. This script measures, on the held-out runs of ``benchmarks/learned.py`` (the
recipe of ``training/configs/default.yaml``, test seeds ``2 * SPLIT_SEED_STRIDE + i``), what
any weighting of the two odometry sources can do with the front end as configured, every
other noise at the configured value (so only the weighting changes):

* ``equal``: both sources at their declared covariances;
* ``vo_only``, ``lidar_only``, ``no_sources``: one source, or none, fused;
* ``oracle_error_scale``: each sample's covariance times ``k^2``, the simulator's own
  unreported weather error (``PoseSourceTruth.error_scale``: night blur for VO, fog clutter
  for LiDAR), i.e. the covariances a perfect weather model would give;
* ``oracle_best_constant``: the best of a grid of constant log-variance scales
  ``(vo, lidar)`` in ``--levels`` x ``--levels``, chosen per run on that run's own truth (an
  upper bound on any constant weighting; not a method);
* ``learned``: the checkpoint's VO / LiDAR log scales with its fusion weights folded in, per
  10-window chunk, weather from the labels (:mod:`msf_torch.learning.inference`).

``--stride n`` keeps every n-th sample of each source (keyframes ``n / 10 Hz`` apart), so
consecutive pairs share no sample (their differenced white noise is then independent, as the
filter assumes) and the baseline is n times longer; ``pose_source_max_gap_s`` grows to match.

``--fusion`` picks how the sources enter the filter (``EskfConfig.pose_source_fusion``):
``velocity`` (odometry rows, the default) or ``drifting_frame`` (absolute poses against a
drifting per-source frame, ``frontend.source_frames``), with the simulator's drift densities
(``CameraModel`` / ``LidarModel`` ``drift_*_per_sqrt_m``) as the sources' datasheet drift.

ATE: position RMSE against the simulator's truth over the filter epochs (no alignment),
per run; ``ate_outage_m`` / ``ate_gnss_m`` split ``equal``'s error into epochs inside and
outside GNSS outages (``gnss_outage`` labels), where relative sources can and cannot help.

    python benchmarks/source_weighting.py [--test-runs 10] [--stride 1]
        [--levels -3 -1.5 0 1.5 3] [--checkpoint checkpoints/covnet_weather.pt]
        [--fusion velocity|drifting_frame]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import time
from pathlib import Path

import torch

from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.learning.covnet import LOG_SCALE_SENSORS, scaled_noise
from msf_torch.learning.data import SPLIT_SEED_STRIDE, simulate_labelled_weather_run
from msf_torch.learning.inference import learned_scales, load_learned, run_piecewise
from msf_torch.sim.weather import CameraModel, LidarModel
from msf_torch.types import Sequence

try:
    from benchmarks._common import emit_json, log
    from benchmarks.learned import SOURCES, WEATHER_CHECKPOINT, WINDOW, epoch_errors, recipe
except ImportError:  # run as a script from benchmarks/
    from _common import emit_json, log
    from learned import SOURCES, WEATHER_CHECKPOINT, WINDOW, epoch_errors, recipe


def source_scales(vo: float, lidar: float) -> torch.Tensor:
    """(7,) log-variance scales: ``vo`` and ``lidar`` in their columns, 0 elsewhere."""
    scales = torch.zeros(len(LOG_SCALE_SENSORS), dtype=torch.float64)
    scales[LOG_SCALE_SENSORS.index("vo")] = vo
    scales[LOG_SCALE_SENSORS.index("lidar")] = lidar
    return scales


def keyframes(seq: Sequence, stride: int) -> Sequence:
    """``seq`` with every pose source's samples other than each ``stride``-th masked out."""
    if stride == 1:
        return seq
    sources = {}
    for name, stream in seq.pose_sources.items():
        keep = torch.zeros_like(stream.mask)
        keep[:, ::stride] = True
        sources[name] = dataclasses.replace(stream, mask=stream.mask & keep)
    return dataclasses.replace(seq, pose_sources=sources)


def with_error_scale(seq: Sequence, error_scale: dict[str, torch.Tensor]) -> Sequence:
    """``seq`` with each source's (B = 1, N) covariances times its per-sample ``k^2`` (N,)."""
    sources = {
        name: dataclasses.replace(
            stream, covariance=stream.covariance * (error_scale[name] ** 2)[None, :, None, None]
        )
        for name, stream in seq.pose_sources.items()
    }
    return dataclasses.replace(seq, pose_sources=sources)


def ate(result: EskfResult, seq: Sequence, where: torch.Tensor | None = None) -> float:
    """Position RMSE (m) over the real epochs (but the start), optionally only ``where``
    (B, E + 1) bool."""
    err, mask = epoch_errors(result, seq)
    if where is not None:
        mask = mask & where
    return float((err**2).sum(-1)[mask].mean().sqrt())


def in_outage(seq: Sequence, t: torch.Tensor) -> torch.Tensor:
    """(B, E + 1) bool: the epoch time lies in a ``gnss_outage`` label interval (B = 1)."""
    out = torch.zeros_like(t, dtype=torch.bool)
    for lo, hi in seq.labels["gnss_outage"][0].tolist():
        out |= (t >= lo) & (t <= hi)
    return out


def source_drift() -> dict[str, list[float]]:
    """The simulator's drift densities per source, [m/sqrt(m), rad/sqrt(m)]."""
    return {
        name: [model.drift_position_m_per_sqrt_m, model.drift_rotation_rad_per_sqrt_m]
        for name, model in (("vo", CameraModel()), ("lidar", LidarModel()))
    }


def main() -> None:
    """Score every weighting per held-out run; table on stderr, one JSON line on stdout."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=WEATHER_CHECKPOINT)
    parser.add_argument("--test-runs", type=int, default=10)
    parser.add_argument("--stride", type=int, default=1, help="keyframe stride (samples)")
    parser.add_argument("--levels", type=float, nargs="+", default=[-3.0, -1.5, 0.0, 1.5, 3.0])
    parser.add_argument(
        "--fusion",
        choices=("velocity", "drifting_frame"),
        default="velocity",
        help=("pose_source_fusion"),
    )
    args = parser.parse_args()
    if args.stride < 1:
        parser.error("--stride must be >= 1")
    start = time.perf_counter()
    learned = load_learned(args.checkpoint)
    settings = recipe()
    seeds = [2 * SPLIT_SEED_STRIDE + i for i in range(args.test_runs)]
    methods = (
        "equal",
        "vo_only",
        "lidar_only",
        "no_sources",
        "oracle_error_scale",
        "oracle_best_constant",
        "learned",
    )
    per_run: dict[str, list[float]] = {m: [] for m in methods}
    split: dict[str, list[float]] = {"ate_outage_m": [], "ate_gnss_m": []}
    best_levels: list[list[float]] = []
    with torch.no_grad():
        for n, seed in enumerate(seeds):
            wet = simulate_labelled_weather_run(seed, **settings)
            run = wet.sequence
            seq = keyframes(run, args.stride)
            cfg: EskfConfig = config_for_sequence(load_config(None), run.meta, set())
            gap = max(cfg.pose_source_max_gap_s, 1.5 * args.stride / 10.0)
            cfg = dataclasses.replace(
                cfg,
                pose_source_max_gap_s=gap,
                pose_source_fusion=args.fusion,
                pose_source_drift=source_drift(),
            )
            base = EskfNoise.from_config(cfg)

            def fixed(vo: float, lidar: float, base: EskfNoise = base) -> EskfNoise:
                return scaled_noise(base, source_scales(vo, lidar))

            equal = run_eskf(seq, cfg, fixed(0.0, 0.0))
            outage = in_outage(seq, equal.t)
            split["ate_outage_m"].append(round(ate(equal, seq, outage), 4))
            split["ate_gnss_m"].append(round(ate(equal, seq, ~outage), 4))
            scores = {
                "equal": ate(equal, seq),
                **{
                    f"{name}_only": ate(
                        run_eskf(
                            seq, dataclasses.replace(cfg, pose_sources=[name]), fixed(0.0, 0.0)
                        ),
                        seq,
                    )
                    for name in SOURCES
                },
                "no_sources": ate(
                    run_eskf(seq, dataclasses.replace(cfg, pose_sources=[]), fixed(0.0, 0.0)),
                    seq,
                ),
            }
            k = {name: torch.from_numpy(wet.source_truth[name].error_scale) for name in SOURCES}
            scores["oracle_error_scale"] = ate(
                run_eskf(with_error_scale(seq, k), cfg, fixed(0.0, 0.0)), seq
            )
            grid = {
                (vo, li): ate(run_eskf(seq, cfg, fixed(vo, li)), seq)
                for vo, li in itertools.product(args.levels, args.levels)
            }
            best = min(grid, key=grid.__getitem__)
            scores["oracle_best_constant"] = grid[best]
            best_levels.append(list(best))
            scales = learned_scales(run, learned, cfg).log_scales
            only_sources = torch.zeros_like(scales)
            for name in SOURCES:
                column = LOG_SCALE_SENSORS.index(name)
                only_sources[:, column] = scales[:, column]
            scores["learned"] = ate(run_piecewise(seq, cfg, only_sources, WINDOW, None), seq)
            for name in methods:
                per_run[name].append(round(scores[name], 4))
            weather = sorted({s.condition for s in wet.schedule.segments})
            log(
                f"run {n} {weather}: "
                + ", ".join(f"{m} {per_run[m][-1]:.4f}" for m in methods)
                + f", best constant {best}"
            )

    def wins(name: str) -> int:
        return sum(a < b for a, b in zip(per_run[name], per_run["equal"], strict=True))

    single = [min(a, b) for a, b in zip(per_run["vo_only"], per_run["lidar_only"], strict=True)]
    record = {
        "benchmark": "source_weighting",
        "checkpoint": str(learned.path),
        "sha256": learned.sha256,
        "test_seeds": seeds,
        "stride": args.stride,
        "fusion": args.fusion,
        "source_drift": source_drift() if args.fusion == "drifting_frame" else None,
        "levels": args.levels,
        "ate_per_run_m": per_run,
        "equal_error_split": split,
        "best_constant_levels": best_levels,
        "runs_better_than_equal": {m: wins(m) for m in methods if m != "equal"},
        "runs_better_than_best_single": {
            m: sum(a < b for a, b in zip(per_run[m], single, strict=True)) for m in methods
        },
        "spread_over_methods_m": [
            round(max(v) - min(v), 4)
            for v in zip(*(per_run[m] for m in methods if m != "no_sources"), strict=True)
        ],
        "any_weighting_beats_equal_in_every_run": wins("oracle_best_constant") == len(seeds),
        "wall_s": round(time.perf_counter() - start, 1),
    }
    emit_json(record)


if __name__ == "__main__":
    main()
