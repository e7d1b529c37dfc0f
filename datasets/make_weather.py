"""Generate weather-labelled simulated runs: train / val / test splits, or the bundled sample.

Each run is :func:`msf_torch.sim.simulate_run` (wheeled robot, ADIS16470 IMU at 200 Hz, wheel
encoders at 25 Hz, GNSS at 1 Hz) degraded by :func:`msf_torch.sim.apply_weather` under a
weather schedule that changes within the run, with LiDAR-degenerate corridors and urban
(GNSS multipath and outage) intervals, and slip episodes drawn from the schedule's ground
friction (:func:`msf_torch.sim.weather_slip_config`). Both pose sources are stored as named
streams (``pose_sources["vo"]``, ``["lidar"]``; ``poses`` is left empty); VO frames dropped for
too few tracked features are absent from the file.

Splits
------
* Every seed in the dataset is distinct (drawn without repetition from ``--seed``): per run a
  sim seed (sensor noise, slip placement, GNSS), a weather seed (:func:`apply_weather`), a
  schedule seed (segment lengths, condition intensities, environment) and a slip seed
  (:func:`weather_slip_config`). Seeds never repeat across runs or splits.
* Maps are disjoint too: each split drives its own map seeds (``path_seed`` of
  :func:`simulate_run`: route and terrain), ``--runs-per-map`` runs per map, so a map seen
  in training never appears in validation or test.
* Conditions are balanced per split: the segments of a split (lengths ``10 + Exp(20)`` s) take
  their conditions in turn from shuffled rounds of all five, never one condition twice in a
  row within a run, so every condition appears in every split (given >= 5 segments).
* Intensities vary per run (log-uniform): night 2-20 lux, fog visibility 20-200 m, snowfall
  visibility 300-1500 m, rain 2-25 mm/h; friction stays at the presets
  (:data:`msf_torch.sim.DEFAULT_CONDITIONS`). Dim nights and dense fog drop VO frames.
* Environment per run: 0-2 corridors of 8-20 s and 0-2 urban intervals of 15-40 s.

Output (``--out``, default ``datasets/weather/``, git-ignored): ``<split>/<name>.npz`` in the
native format (:mod:`msf_torch.io.native`; the sensor JSON holds the weather models and
schedule under ``"weather"``) and ``manifest.json``: the command, the master seed, per split
its map seeds and runs (file, seeds, duration, schedule, condition intensities, environment,
slip count) and a summary of seconds per condition per split. Defaults (48 / 12 / 12 runs of
60-120 s, ~1.5 h of driving, ~200 MB) suit a CPU training run under 20 minutes.

Usage::

    python datasets/make_weather.py                        # datasets/weather/ (about 1 min)
    python datasets/make_weather.py --train 8 --val 2 --test 2 --out /tmp/w
    python datasets/make_weather.py --check --out /tmp/w   # per-condition time per split
    python datasets/make_weather.py --sample               # datasets/sample_weather.npz
"""

from __future__ import annotations

__all__ = [
    "SPLITS",
    "SAMPLE_SEED",
    "RunPlan",
    "plan_splits",
    "simulate_plan",
    "sample_plan",
    "generate",
    "make_sample",
    "summarise",
    "check",
    "main",
]

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msf_torch.io.atomic import atomic_write
from msf_torch.io.native import read_native, write_native
from msf_torch.sim import (
    CONDITIONS,
    DEFAULT_CONDITIONS,
    Environment,
    SimConfig,
    WeatherCondition,
    WeatherRun,
    WeatherSchedule,
    apply_weather,
    simulate_run,
    weather_slip_config,
)
from msf_torch.types import Sequence

SPLITS: tuple[str, ...] = ("train", "val", "test")
"""Split names, in generation order."""

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "weather"
SAMPLE_OUT = HERE / "sample_weather.npz"
SAMPLE_SEED = 17
"""Master seed of the bundled sample."""

MEAN_SEGMENT_S = 30.0
MIN_SEGMENT_S = 10.0
INTENSITY_RANGES: dict[str, tuple[str, float, float]] = {
    "night": ("illuminance_lux", 2.0, 20.0),
    "fog": ("visibility_m", 20.0, 200.0),
    "snow": ("visibility_m", 300.0, 1500.0),
    "rain": ("rain_rate_mm_h", 2.0, 25.0),
}
"""Condition -> (WeatherCondition field, low, high), drawn log-uniformly per run."""
CORRIDOR_S = (8.0, 20.0)
URBAN_S = (15.0, 40.0)
ENV_EDGE_S = 5.0


@dataclass(frozen=True)
class RunPlan:
    """Everything that fixes one run (JSON-friendly via :meth:`to_dict`).

    Attributes:
        name: sequence name and file stem.
        split: ``"train"``, ``"val"``, ``"test"`` or ``"sample"``.
        duration_s: run length, s.
        map_seed: ``path_seed`` of :func:`simulate_run` (route and terrain).
        sim_seed: :func:`simulate_run` seed (sensor noise, slip placement, GNSS).
        weather_seed: :func:`apply_weather` seed.
        schedule_seed: seed of the segment lengths, intensities and environment.
        slip_seed: :func:`weather_slip_config` seed.
        boundaries_s: segment boundaries, s (first 0, last ``duration_s``).
        conditions: one condition per segment.
        intensities: condition -> field -> value overriding the preset (see
            :data:`INTENSITY_RANGES`).
        corridors_s: ``((t0, t1), ...)`` s.
        urban_s: ``((t0, t1), ...)`` s.
    """

    name: str
    split: str
    duration_s: float
    map_seed: int
    sim_seed: int
    weather_seed: int
    schedule_seed: int
    slip_seed: int
    boundaries_s: tuple[float, ...]
    conditions: tuple[str, ...]
    intensities: dict[str, dict[str, float]]
    corridors_s: tuple[tuple[float, float], ...]
    urban_s: tuple[tuple[float, float], ...]

    def schedule(self) -> WeatherSchedule:
        """The weather schedule."""
        return WeatherSchedule.from_boundaries(list(self.boundaries_s), list(self.conditions))

    def weather_conditions(self) -> dict[str, WeatherCondition]:
        """The presets with this run's intensities."""
        out = dict(DEFAULT_CONDITIONS)
        for name, fields in self.intensities.items():
            out[name] = dataclasses.replace(out[name], **fields)
        return out

    def environment(self) -> Environment:
        """Corridors and urban intervals."""
        return Environment(corridors_s=self.corridors_s, urban_s=self.urban_s)

    def condition_seconds(self) -> dict[str, float]:
        """Seconds per condition (every one of :data:`CONDITIONS`, 0 where absent)."""
        out = dict.fromkeys(CONDITIONS, 0.0)
        for seg in self.schedule().segments:
            out[seg.condition] = out.get(seg.condition, 0.0) + seg.t_end - seg.t_start
        return out

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (tuples as lists) for the manifest."""
        return json.loads(json.dumps(dataclasses.asdict(self)))


def _unique_seeds(rng: np.random.Generator, count: int) -> list[int]:
    """``count`` distinct seeds in [0, 2^31)."""
    seen: dict[int, None] = {}
    while len(seen) < count:
        for value in rng.integers(0, 2**31, count - len(seen)).tolist():
            seen.setdefault(int(value), None)
    return list(seen)


def _place(
    count: int, length_s: tuple[float, float], duration_s: float, rng: np.random.Generator
) -> tuple[tuple[float, float], ...]:
    """Up to ``count`` disjoint intervals of ``U(length_s)`` s in ``[5, duration - 5]`` s, 2 s
    apart, random slack (fewer when they do not fit)."""
    lengths = rng.uniform(*length_s, count)
    room = duration_s - 2 * ENV_EDGE_S
    while len(lengths) and lengths.sum() + 2.0 * (len(lengths) - 1) > room:
        lengths = lengths[:-1]
    slack = room - lengths.sum() - 2.0 * max(len(lengths) - 1, 0)
    spare = rng.dirichlet(np.ones(len(lengths) + 1)) * slack
    out, t = [], ENV_EDGE_S
    for k, length in enumerate(lengths):
        t += spare[k]
        out.append((round(float(t), 3), round(float(t + length), 3)))
        t += length + 2.0
    return tuple(out)


def _condition_order(rng: np.random.Generator, count: int) -> list[str]:
    """Conditions for ``count`` segments: shuffled rounds of all five, no immediate repeat."""
    order: list[str] = []
    while len(order) < count:
        block = list(rng.permutation(CONDITIONS))
        if order and block[0] == order[-1]:
            block[0], block[-1] = block[-1], block[0]
        order.extend(str(c) for c in block)
    return order[:count]


def plan_splits(
    runs: dict[str, int],
    seed: int = 0,
    duration_s: tuple[float, float] = (60.0, 120.0),
    runs_per_map: int = 4,
) -> dict[str, dict[str, Any]]:
    """Plan the runs of every split (no simulation).

    Args:
        runs: split -> number of runs (``>= 1`` each).
        seed: master seed; every run and map seed is drawn from it without repetition.
        duration_s: run length range, s (whole seconds, uniform; low >= 30).
        runs_per_map: runs that share one map within a split.

    Returns:
        split -> ``{"maps": [map seeds], "runs": [RunPlan, ...]}``.
    """
    low, high = duration_s
    if not 30.0 <= low <= high:
        raise ValueError(f"plan_splits: need 30 <= low <= high s, got {duration_s}")
    if runs_per_map < 1 or any(n < 1 for n in runs.values()):
        raise ValueError(f"plan_splits: need >= 1 run per split and per map, got {runs}")
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed))))
    maps = {split: math.ceil(n / runs_per_map) for split, n in runs.items()}
    pool = iter(_unique_seeds(rng, sum(maps.values()) + 4 * sum(runs.values())))
    out: dict[str, dict[str, Any]] = {}
    for split, count in runs.items():
        map_seeds = [next(pool) for _ in range(maps[split])]
        drafts = []
        for k in range(count):
            sim, weather, sched, slip = (next(pool) for _ in range(4))
            local = np.random.Generator(np.random.PCG64(np.random.SeedSequence(sched).spawn(1)[0]))
            duration = float(round(local.uniform(low, high)))
            bounds = [
                s.t_start for s in WeatherSchedule.random(duration, sched, ("x",)).segments
            ] + [duration]
            intensities = {
                name: {field: round(float(math.exp(local.uniform(math.log(a), math.log(b)))), 3)}
                for name, (field, a, b) in INTENSITY_RANGES.items()
            }
            corridors = _place(int(local.integers(0, 3)), CORRIDOR_S, duration, local)
            urban = _place(int(local.integers(0, 3)), URBAN_S, duration, local)
            drafts.append(
                (k, duration, sim, weather, sched, slip, bounds, intensities, corridors, urban)
            )
        order = _condition_order(rng, sum(len(d[6]) - 1 for d in drafts))
        plans = []
        for k, duration, sim, weather, sched, slip, bounds, intens, corr, urb in drafts:
            taken, order = order[: len(bounds) - 1], order[len(bounds) - 1 :]
            plans.append(
                RunPlan(
                    name=f"weather_{split}_{k:03d}",
                    split=split,
                    duration_s=duration,
                    map_seed=map_seeds[k // runs_per_map],
                    sim_seed=sim,
                    weather_seed=weather,
                    schedule_seed=sched,
                    slip_seed=slip,
                    boundaries_s=tuple(round(float(b), 3) for b in bounds),
                    conditions=tuple(taken),
                    intensities=intens,
                    corridors_s=corr,
                    urban_s=urb,
                )
            )
        out[split] = {"maps": map_seeds, "runs": plans}
    return out


def sample_plan(seed: int = SAMPLE_SEED) -> RunPlan:
    """The bundled sample: 50 s, all five conditions for 10 s each (sunny, rain, fog, night,
    snow), a dim night (6 lux) and dense fog (28 m) that drop VO frames, one corridor
    (12-20 s) and one urban interval (25-45 s)."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed))))
    map_seed, sim, weather, sched, slip = _unique_seeds(rng, 5)
    return RunPlan(
        name="sample_weather",
        split="sample",
        duration_s=50.0,
        map_seed=map_seed,
        sim_seed=sim,
        weather_seed=weather,
        schedule_seed=sched,
        slip_seed=slip,
        boundaries_s=(0.0, 10.0, 20.0, 30.0, 40.0, 50.0),
        conditions=CONDITIONS,
        intensities={
            "night": {"illuminance_lux": 6.0},
            "fog": {"visibility_m": 28.0},
            "snow": {"visibility_m": 600.0},
            "rain": {"rain_rate_mm_h": 10.0},
        },
        corridors_s=((12.0, 20.0),),
        urban_s=((25.0, 45.0),),
    )


def simulate_plan(plan: RunPlan) -> WeatherRun:
    """Simulate one planned run; ``sequence.poses`` is None, both sources in
    ``sequence.pose_sources``, ``meta["sensor"]["weather"]`` the weather record."""
    schedule = plan.schedule()
    conditions = plan.weather_conditions()
    config = weather_slip_config(
        SimConfig(duration_s=plan.duration_s), schedule, plan.slip_seed, conditions=conditions
    )
    run = simulate_run(config, plan.sim_seed, path_seed=plan.map_seed)
    wet = apply_weather(
        run,
        schedule,
        plan.weather_seed,
        environment=plan.environment(),
        conditions=conditions,
        pose_source=None,
    )
    meta = dict(wet.sequence.meta)
    meta["sensor"] = {**meta["sensor"], "weather": meta["weather"], "run_plan": plan.to_dict()}
    wet.sequence = dataclasses.replace(wet.sequence, names=[plan.name], meta=meta)
    return wet


def _seconds(spans: np.ndarray) -> float:
    """Total length of (K, 2) intervals, s."""
    return float((spans[:, 1] - spans[:, 0]).sum()) if spans.size else 0.0


def _run_stats(seq: Sequence) -> dict[str, dict[str, float]]:
    """Per condition: seconds, VO frames expected on the camera grid, and present."""
    rate = seq.meta["sensor"]["weather"]["camera"]["rate_hz"]
    t_end = float(seq.imu.t[0, -1])
    grid = np.arange(math.floor(t_end * rate + 1e-9) + 1) / rate
    vo = seq.pose_sources["vo"].compact().t[0].numpy() if "vo" in seq.pose_sources else []
    out = {}
    for name in CONDITIONS:
        label = seq.labels.get(f"weather:{name}")
        spans = label[0].numpy() if label is not None else np.zeros((0, 2))
        spans = spans[~np.isnan(spans).any(axis=1)]
        expected = present = 0
        for start, end in spans:
            expected += int(((grid >= start) & (grid < end)).sum())
            present += int(((vo >= start - 1e-9) & (vo < end - 1e-9)).sum())
        out[name] = {"seconds": _seconds(spans), "vo_expected": expected, "vo_present": present}
    for env in ("env:corridor", "env:urban"):
        label = seq.labels.get(env)
        spans = label[0].numpy() if label is not None else np.zeros((0, 2))
        out[env] = {"seconds": _seconds(spans[~np.isnan(spans).any(axis=1)])}
    return out


def summarise(stats: dict[str, list[dict[str, dict[str, float]]]]) -> dict[str, Any]:
    """Per split: seconds per condition and environment, VO dropout % (None where a
    condition has no time), total seconds, runs."""
    out: dict[str, Any] = {}
    for split, runs in stats.items():
        row: dict[str, Any] = {"runs": len(runs)}
        for key in (*CONDITIONS, "env:corridor", "env:urban"):
            row[f"{key}_s"] = round(sum(r[key]["seconds"] for r in runs), 1)
        for name in CONDITIONS:
            expected = sum(r[name]["vo_expected"] for r in runs)
            present = sum(r[name]["vo_present"] for r in runs)
            row[f"{name}_vo_dropout_pct"] = (
                round(100.0 * (1 - present / expected), 2) if expected else None
            )
        row["total_s"] = round(sum(row[f"{c}_s"] for c in CONDITIONS), 1)
        out[split] = row
    return out


def _table(summary: dict[str, Any]) -> str:
    """Plain-text table of :func:`summarise`'s seconds and VO dropouts per split."""
    keys = [*CONDITIONS, "env:corridor", "env:urban"]
    lines = [f"{'split':<6}{'runs':>5}" + "".join(f"{k.removeprefix('env:'):>10}" for k in keys)]
    for split, row in summary.items():
        cells = "".join(f"{row[f'{k}_s']:>9.0f}s" for k in keys)
        lines.append(f"{split:<6}{row['runs']:>5}{cells}")
        drops = "".join(
            f"{'-':>10}" if row[key] is None else f"{row[key]:>9.1f}%"
            for key in (f"{c}_vo_dropout_pct" for c in CONDITIONS)
        )
        lines.append(f"{'  VO dropped':<11}{drops}")
    return "\n".join(lines)


def _missing(summary: dict[str, Any]) -> list[str]:
    """``"split: condition"`` for every condition with no time in a split."""
    return [f"{s}: {c}" for s, row in summary.items() for c in CONDITIONS if row[f"{c}_s"] <= 0]


def generate(
    out: str | Path = DEFAULT_OUT,
    runs: dict[str, int] | None = None,
    seed: int = 0,
    duration_s: tuple[float, float] = (60.0, 120.0),
    runs_per_map: int = 4,
    progress: bool = True,
    argv: list[str] | None = None,
) -> dict[str, Any]:
    """Simulate and write the splits plus ``manifest.json``; returns the manifest.

    Args:
        out: output folder (created).
        runs: split -> run count (default 48 / 12 / 12).
        seed: master seed.
        duration_s: run length range, s.
        runs_per_map: runs per map within a split.
        progress: show a tqdm bar on stderr.
        argv: the command line, recorded in the manifest.
    """
    from tqdm import tqdm

    runs = runs or {"train": 48, "val": 12, "test": 12}
    folder = Path(out)
    splits = plan_splits(runs, seed, duration_s, runs_per_map)
    plans = [p for split in splits.values() for p in split["runs"]]
    stats: dict[str, list[dict[str, dict[str, float]]]] = {s: [] for s in splits}
    entries: dict[str, list[dict[str, Any]]] = {s: [] for s in splits}
    for plan in tqdm(plans, desc="weather runs", unit="run", disable=not progress, file=sys.stderr):
        wet = simulate_plan(plan)
        (folder / plan.split).mkdir(parents=True, exist_ok=True)
        path = write_native(wet.sequence, folder / plan.split / f"{plan.name}.npz")
        stats[plan.split].append(_run_stats(wet.sequence))
        entries[plan.split].append(
            {
                "file": str(path.relative_to(folder)),
                **plan.to_dict(),
                "condition_seconds": plan.condition_seconds(),
                "slip_episodes": len(wet.truth.slip_episodes),
            }
        )
    manifest = {
        "generator": "datasets/make_weather.py",
        "command": argv,
        "seed": int(seed),
        "duration_s": list(duration_s),
        "runs_per_map": runs_per_map,
        "splits": {s: {"maps": splits[s]["maps"], "runs": entries[s]} for s in splits},
        "summary": summarise(stats),
    }
    with atomic_write(folder / "manifest.json") as handle:
        handle.write(json.dumps(manifest, indent=2) + "\n")
    return manifest


def check(out: str | Path = DEFAULT_OUT) -> tuple[dict[str, Any], list[str]]:
    """Re-read a generated dataset: the summary from the files' labels and VO streams, and
    problems (missing files, a condition absent from a split, shared seeds or maps)."""
    folder = Path(out)
    manifest = json.loads((folder / "manifest.json").read_text())
    problems: list[str] = []
    stats: dict[str, list[dict[str, dict[str, float]]]] = {}
    owner: dict[tuple[str, int], str] = {}
    for split, block in manifest["splits"].items():
        stats[split] = []
        for seed in block["maps"]:
            if owner.setdefault(("map", seed), split) != split:
                problems.append(f"map seed {seed} in {owner[('map', seed)]} and {split}")
        for entry in block["runs"]:
            for kind in ("sim_seed", "weather_seed", "schedule_seed", "slip_seed"):
                key = (kind, entry[kind])
                if owner.setdefault(key, entry["name"]) != entry["name"]:
                    problems.append(f"{kind} {entry[kind]} in {owner[key]} and {entry['name']}")
            path = folder / entry["file"]
            if not path.exists():
                problems.append(f"missing {path}")
                continue
            stats[split].append(_run_stats(read_native(path)))
    summary = summarise(stats)
    problems += [f"no time in {m}" for m in _missing(summary)]
    return summary, problems


def make_sample(out: str | Path = SAMPLE_OUT, seed: int = SAMPLE_SEED) -> Path:
    """Write the sample run (:func:`sample_plan`) natively plus ``<stem>.sim.json`` (plan, config,
    slip episodes, hidden truth: pose-source drift at the end, wheel scale errors)."""
    plan = sample_plan(seed)
    wet = simulate_plan(plan)
    path = write_native(wet.sequence, out)
    provenance = {
        "generator": "datasets/make_weather.py --sample (msf_torch.sim.apply_weather)",
        "seed": seed,
        "plan": plan.to_dict(),
        "config": wet.truth.config.to_dict(),
        "slip_episodes": wet.sequence.meta["slip_episodes"],
        "summary": summarise({"sample": [_run_stats(wet.sequence)]})["sample"],
        "truth": {
            "wheel_scale_error": wet.sequence.meta["truth"]["wheel_scale_error"],
            **{
                f"{name}_final_drift": truth.drift[-1].tolist()
                for name, truth in wet.source_truth.items()
            },
        },
    }
    target = path.with_suffix(".sim.json") if path.suffix == ".npz" else path / "sim.json"
    with atomic_write(target) as handle:
        handle.write(json.dumps(provenance, indent=2, sort_keys=True) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    """Command line (module docstring); returns the exit status (1 when ``--check`` fails)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (or .npz)")
    parser.add_argument("--train", type=int, default=48, help="training runs")
    parser.add_argument("--val", type=int, default=12, help="validation runs")
    parser.add_argument("--test", type=int, default=12, help="test runs")
    parser.add_argument("--seed", type=int, default=0, help="master seed")
    parser.add_argument("--min-duration", type=float, default=60.0, help="s")
    parser.add_argument("--max-duration", type=float, default=120.0, help="s")
    parser.add_argument("--runs-per-map", type=int, default=4)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--check", action="store_true", help="summarise an existing dataset")
    parser.add_argument("--sample", action="store_true", help="write the bundled sample")
    args = parser.parse_args(argv)
    if args.sample:
        print(f"wrote {make_sample(args.out or SAMPLE_OUT)}")
        return 0
    out = args.out or DEFAULT_OUT
    if args.check:
        summary, problems = check(out)
    else:
        manifest = generate(
            out,
            {"train": args.train, "val": args.val, "test": args.test},
            args.seed,
            (args.min_duration, args.max_duration),
            args.runs_per_map,
            progress=not args.no_progress,
            argv=sys.argv if argv is None else ["make_weather.py", *argv],
        )
        summary, problems = (
            manifest["summary"],
            [f"no time in {m}" for m in _missing(manifest["summary"])],
        )
        print(f"wrote {out}")
    print(_table(summary))
    for problem in problems:
        print(f"problem: {problem}")
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
