"""Wheel calibration in the full-batch smoother (issue 6, online calibration, LM back end).

Input: the runs of ``benchmarks/calibration.py`` (``msf_torch.sim.calibration``, seeds
6000-6009 by default, 180 s each, fast field robot, 200 Hz IMU, 25 Hz wheels, 5 Hz RTK-grade
GNSS with two 30-s outages, 10 Hz VO), each with 5 % error on each wheel radius and 3 % on
the track width (random signs). The GNSS and camera time offsets are 0 by default: the back
end does not estimate time offsets (``--time-offset-s 0.02`` gives the runs of
``benchmarks/calibration.py`` exactly).

Front end: the ESKF with ``calibrate_wheels`` (``frontend.calibration``; a front end
without it takes the miscalibrated wheels for slipping ones and switches them off), one
batch over the runs. Smoothers, full batch, on the same front-end result:

* ``off``: the default smoother (wheel factors at the believed calibration, yaw row off);
* ``on``: ``calibrate_wheels`` (one ``[k_l, k_r, D]`` variable per run, prior = the
  believed values with the front end's prior sigmas, started at the front end's final
  estimate);
* ``oracle``: the default smoother after the default ESKF, both on the measurements
  corrected with the TRUE calibration (``CalibrationRun.corrected``): the floor.

No library peer calibrates wheels in a smoother, so the comparison is against no
calibration (and the oracle). Figures: ATE = position RMSE of the smoothed trajectory at
every front-end epoch against the analytic truth (no alignment), per run and median;
``1 - ATE_on / ATE_off``; per state the estimate, its marginal sigma (from the solved
information matrix) and ``z = (estimate - truth) / sigma``; smoother wall times (one
thread). Targets (the issue's, for the back end): every state within 3 sigma on every run,
ATE with calibration below ATE without on every run.

How to run
    .venv/bin/python benchmarks/calibration_smoother.py             # 10 runs (~4 min)
    .venv/bin/python benchmarks/calibration_smoother.py --runs 3    # quicker

    Per-run lines go to stderr; the last line on stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info  # noqa: E402
from msf_torch.backend.window import SmootherConfig, smooth  # noqa: E402
from msf_torch.frontend.calibration import WHEEL_STATES  # noqa: E402
from msf_torch.frontend.config import EskfConfig, config_for_sequence  # noqa: E402
from msf_torch.frontend.eskf import EskfResult, run_eskf  # noqa: E402
from msf_torch.sim.calibration import (  # noqa: E402
    CalibrationRun,
    calibration_sim_config,
    simulate_calibration_run,
)
from msf_torch.types import Trajectory, batch_sequences  # noqa: E402


def one_result(result: EskfResult, b: int) -> EskfResult:
    """Sequence ``b`` of a batched front-end result as a B = 1 result (per-epoch tensors and
    dicts of them sliced; the gate memory, not used by the smoother, dropped)."""
    batch = result.t.shape[0]

    def pick(value):
        if isinstance(value, torch.Tensor) and value.dim() >= 1 and value.shape[0] == batch:
            return value[b : b + 1]
        if isinstance(value, dict):
            return {k: pick(v) for k, v in value.items()}
        return value

    fields = {f.name: pick(getattr(result, f.name)) for f in dataclasses.fields(result)}
    fields["names"] = [result.names[b]]
    fields["gate_memory"] = None
    return EskfResult(**fields)


def position_rmse(output: Trajectory, run: CalibrationRun) -> float:
    """RMSE (m) of a B = 1 trajectory's positions against the run's analytic truth."""
    mask = output.mask[0]
    truth = run.run.path.evaluate(output.t[0][mask].numpy()).position
    error = output.position[0][mask].numpy() - truth
    return float(np.sqrt(np.mean(np.sum(error**2, -1))))


def main() -> None:
    """Run the benchmark; per-run lines to stderr and one JSON line to stdout."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=6000)
    parser.add_argument("--duration", type=float, default=180.0)
    parser.add_argument("--time-offset-s", type=float, default=0.0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = list(range(args.first_seed, args.first_seed + args.runs))

    start = time.perf_counter()
    runs = [
        simulate_calibration_run(
            s, calibration_sim_config(args.duration), time_offset_s=args.time_offset_s
        )
        for s in seeds
    ]
    base = config_for_sequence(EskfConfig(), runs[0].sequence.meta, set())
    front_cfg = base.replace(calibrate_wheels=True)
    log(f"simulated {len(runs)} runs in {time.perf_counter() - start:.1f} s")
    start = time.perf_counter()
    with torch.no_grad():
        front = run_eskf(batch_sequences([r.sequence for r in runs]), front_cfg)
        front_oracle = run_eskf(batch_sequences([r.corrected for r in runs]), base)
    log(f"front ends: {time.perf_counter() - start:.1f} s")

    smoothers = {
        "off": SmootherConfig(),
        "on": SmootherConfig(calibrate_wheels=True),
    }
    ate: dict[str, list[float]] = {"frontend": [], "off": [], "on": [], "oracle": []}
    wall: dict[str, list[float]] = {"off": [], "on": [], "oracle": []}
    estimate, sigma, truth = [], [], []
    for b, run in enumerate(runs):
        frontend = one_result(front, b)
        ate["frontend"].append(position_rmse(frontend.trajectory().select(0), run))
        with torch.no_grad():
            for name, config in smoothers.items():
                result = smooth(run.sequence, frontend, front_cfg, config, "full")
                ate[name].append(position_rmse(result.output, run))
                wall[name].append(result.wall_s)
                if name == "on":
                    estimate.append(result.calibration[0].numpy())
                    sigma.append(result.calibration_sigma[0].numpy())
            oracle = smooth(run.corrected, one_result(front_oracle, b), base, None, "full")
        ate["oracle"].append(position_rmse(oracle.output, run))
        wall["oracle"].append(oracle.wall_s)
        truth.append(run.truth.vector(WHEEL_STATES))
        z = (estimate[-1] - truth[-1]) / sigma[-1]
        log(
            f"seed {run.run.seed}: ATE front {ate['frontend'][-1]:.3f} off {ate['off'][-1]:.3f} "
            f"on {ate['on'][-1]:.3f} oracle {ate['oracle'][-1]:.3f} m; estimate "
            f"{np.round(estimate[-1], 4).tolist()} truth {np.round(truth[-1], 4).tolist()} "
            f"z {np.round(z, 2).tolist()}"
        )
    estimate_a, sigma_a, truth_a = np.stack(estimate), np.stack(sigma), np.stack(truth)
    z_all = (estimate_a - truth_a) / sigma_a
    believed = np.array([1.0, 1.0, runs[0].truth.believed_track_width_m])
    per_state = {}
    for k, name in enumerate(WHEEL_STATES):
        per_state[name] = {
            "truth": truth_a[:, k].tolist(),
            "estimate": estimate_a[:, k].tolist(),
            "sigma": sigma_a[:, k].tolist(),
            "z": z_all[:, k].tolist(),
            "abs_z_max": float(np.abs(z_all[:, k]).max()),
            "within_3_sigma": float(np.mean(np.abs(z_all[:, k]) <= 3.0)),
            "median_abs_error": float(np.median(np.abs(estimate_a[:, k] - truth_a[:, k]))),
            "median_initial_abs_error": float(np.median(np.abs(believed[k] - truth_a[:, k]))),
            "median_sigma": float(np.median(sigma_a[:, k])),
        }
    reduction = [1.0 - on / off for on, off in zip(ate["on"], ate["off"], strict=True)]
    within = all(v["within_3_sigma"] == 1.0 for v in per_state.values())
    lower = all(on < off for on, off in zip(ate["on"], ate["off"], strict=True))
    emit_json(
        {
            "benchmark": "calibration_smoother",
            "inputs": {
                "seeds": seeds,
                "duration_s": args.duration,
                "radius_error": 0.05,
                "track_error": 0.03,
                "time_offset_s": args.time_offset_s,
                "sensors": "IMU 200 Hz, wheels 25 Hz, GNSS 5 Hz 0.05 m (outages 60-90, "
                "130-160 s), VO 10 Hz",
                "frontend": "ESKF with calibrate_wheels (oracle: default ESKF on corrected "
                "measurements)",
                "threads": args.threads,
            },
            "peer": "none fits (no library calibrates wheels in a smoother): the smoother "
            "without calibration (off) and the oracle smoother on corrected measurements",
            "states": list(WHEEL_STATES),
            "calibration": per_state,
            "ate_m": ate,
            "ate_median_m": {k: statistics.median(v) for k, v in ate.items()},
            "ate_reduction_per_run": reduction,
            "ate_reduction_median": statistics.median(reduction),
            "ate_on_over_oracle_median": statistics.median(
                [on / orc for on, orc in zip(ate["on"], ate["oracle"], strict=True)]
            ),
            "smoother_wall_s_median": {k: statistics.median(v) for k, v in wall.items()},
            "wall_ratio_on_over_off_median": statistics.median(
                [on / off for on, off in zip(wall["on"], wall["off"], strict=True)]
            ),
            "acceptance": {
                "within_3_sigma_every_state_every_run": within,
                "ate_on_below_off_every_run": lower,
                "met": within and lower,
            },
            "machine": machine_info(),
        }
    )


if __name__ == "__main__":
    main()
