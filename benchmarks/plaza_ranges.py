"""Real wheeled-robot data with range beacons (Plaza): our planar smoother vs GTSAM's LM on
the same graph, and both against RTK ground truth and dead reckoning.

What it measures
    Input: a Plaza run of the ``gtsam`` wheel (:func:`msf_torch.io.plaza.load_plaza`; default
    test run ``Plaza2``: 409 s, 1354 m, 4090 odometry steps at 10 Hz, 1816 radio ranges to
    four beacons at known positions). The settings come from the OTHER run (``Plaza1``,
    ``--calibrate``), never from the test run:

    * range bias = median of (range - true distance) and range sigma = 1.4826 MAD of it,
      over the calibration run's ranges (true distances from its RTK positions);
    * odometry noise (:class:`~msf_torch.backend.range2d.OdometryNoise`, variance per metre
      travelled): over consecutive 100-step stretches of the calibration run, the forward
      error of the chained odometry against the truth gives ``forward`` (and ``lateral``,
      set equal), and the sideways error, read as a heading random walk
      (``var_y = heading L^3 / 3`` over a stretch of ``L`` m), gives ``heading``.
      (Plaza1's truth heading is its odometry's, so heading itself cannot be compared.)

    The graph (ours and GTSAM's, built from the same numbers): poses at the start and every
    odometry time; one ``BetweenFactor<Pose2>`` per step measuring ``Pose2(distance, 0,
    turn)``; one ``RangeFactor2D`` per range (bias removed) to its beacon, attached to the
    first pose at or after the range's time, under the robust kernel ``--kernel`` (scale in
    sigmas); a ``PriorFactorPose2`` on pose 0 at the true start (0.1 m, 0.05 rad: the robot
    starts from a known spot); beacons held at their surveyed positions (GTSAM:
    ``NonlinearEqualityPoint2``). Initial values: dead reckoning from the start.

    * ours: :func:`msf_torch.backend.range2d.odometry_range_problem` solved by
      :func:`msf_torch.backend.lm.solve` (sparse, identity damping from 1e-5, GTSAM's
      divide / multiply by 10 update);
    * GTSAM (the ratio's peer): ``LevenbergMarquardtOptimizer`` with the same tolerances
      (relative ``--tolerance``, absolute 0).

    Accuracy: position RMSE and max error against the RTK truth at every pose (same frame: no
    alignment), for ours, GTSAM and dead reckoning; agreement of the two solvers (final
    costs, largest position difference).

    Second case, ``slam`` (GTSAM's RangeISAMExample_plaza2 problem, solved in batch): the
    beacons are unknown, free variables; each starts from
    :func:`~msf_torch.backend.range2d.multilaterate` of its ranges in the first
    ``--slam-window`` seconds at the dead-reckoned poses. The map's frame is then only the
    prior on pose 0, so a start-heading error turns the whole solution about the start:
    reported raw and after the best rigid 2-D alignment to the truth (``aligned_error``,
    ``alignment_rotation_deg``), with the beacons' errors both ways. (On Plaza2 the
    localisation case itself puts pose 0's heading 5.6 degrees from the truth's, under the
    0.05 rad prior: the truth's start heading disagrees with the beacons by about that much.)

    Time (both cases): medians of ``--repeats`` solves after one warm-up each, ours and
    GTSAM alternating (graph building apart); ``ratio`` = ours / GTSAM wall time. No issue
    names a target; the figures are reported as measured. Both cases attach each range to
    the first pose at or after its time (GTSAM's graph; the calibration measures the bias
    and sigma the same way).

    Third case, ``odometry_rate`` (ours only): where a range counts. The odometry (10 Hz)
    is thinned to every ``n``-th pose (``--rates``; ``RangeRun.thinned``: composed steps,
    truth and ranges kept),
    calibration and test alike, and :func:`~msf_torch.backend.range_smoother.smooth_ranges`
    (beacons known, start at the truth's first pose, 0.1 m / 0.05 rad) runs with
    ``range_timing="next_pose"`` (GTSAM's graph) and ``"interpolate"`` (the range at the
    position interpolated between the poses around its time, the library's default):
    position RMSE and max error against RTK for each.

How to run
    .venv/bin/python benchmarks/plaza_ranges.py                       # Plaza2, ~30 s
    .venv/bin/python benchmarks/plaza_ranges.py --test Plaza1 --calibrate Plaza2
    .venv/bin/python benchmarks/plaza_ranges.py --plot plaza2.png     # truth, DR, ours, beacons

    Progress goes to stderr; the last line on stdout is one JSON object.

Options
    --test RUN         the run solved (default Plaza2)
    --calibrate RUN    the run the settings come from (default: the other one)
    --kernel K[:S]     robust kernel on the ranges: cauchy (default, 2.3849 sigmas), huber
                       (1.345), tukey (4.6851), none
    --tolerance T      relative cost decrease that stops both solvers (default 1e-10)
    --repeats N        timed repeats (median; default 3)
    --slam-window S    seconds of ranges that place the SLAM case's beacons (default 60)
    --threads N        torch intra-op threads (default: torch's default)
    --plot PNG         write a figure of the test run
    --rates N [N ...]  odometry thinning factors of the odometry_rate case (default 1 5 10 20)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info, time_repeats  # noqa: E402
from msf_torch.backend.lm import LMConfig, solve  # noqa: E402
from msf_torch.backend.range2d import (  # noqa: E402
    OdometryNoise,
    multilaterate,
    odometry_range_problem,
)
from msf_torch.backend.range_smoother import (  # noqa: E402
    RangeSmootherSettings,
    calibrate_from_truth,
    smooth_ranges,
)
from msf_torch.backend.robust import RobustKernel  # noqa: E402
from msf_torch.eval.plots import range_run_figure  # noqa: E402
from msf_torch.geometry.se2 import (  # noqa: E402
    align_points,
    transform_points,
)
from msf_torch.io.plaza import PLAZA_RUNS, load_plaza  # noqa: E402
from msf_torch.io.ranges import RangeRun  # noqa: E402

DEFAULT_SCALES = {"cauchy": 2.3849, "huber": 1.345, "tukey": 4.6851}
START_SIGMA = (0.1, 0.1, 0.05)


def parse_kernel(text: str) -> RobustKernel | None:
    """``name[:scale]`` -> kernel (scale in sigmas), ``none`` -> None."""
    name, _, scale = text.partition(":")
    if name == "none":
        return None
    if name not in DEFAULT_SCALES:
        raise SystemExit(f"--kernel: unknown kernel {name!r} (cauchy, huber, tukey, none)")
    return RobustKernel(name, float(scale) if scale else DEFAULT_SCALES[name])


def _errors(positions: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    distance = np.linalg.norm(positions - truth, axis=1)
    return {
        "rmse_m": float(np.sqrt(np.mean(distance**2))),
        "max_m": float(distance.max()),
        "final_m": float(distance[-1]),
    }


def initial_beacons(run: RangeRun, ranges: torch.Tensor, window_s: float) -> torch.Tensor:
    """(L, 2) beacon guesses for range-only SLAM: each beacon multilaterated from its
    (bias-removed) ranges of the first ``window_s`` seconds, taken at the dead-reckoned
    poses."""
    dead_reckoning = run.odometry_poses()[run.range_pose_index(), 0:2]
    rows = run.range_anchor_rows()
    early = run.range_t <= run.range_t[0] + window_s
    return torch.stack(
        [
            multilaterate(dead_reckoning[early & (rows == j)], ranges[early & (rows == j)])
            for j in range(run.anchors.shape[0])
        ]
    )


def gtsam_graph(
    run: RangeRun,
    noise: OdometryNoise,
    bias: float,
    sigma: float,
    kernel: RobustKernel | None,
    first_covariance: np.ndarray,
    initial_poses: np.ndarray,
    initial_beacons: np.ndarray | None = None,
) -> tuple[Any, Any]:
    """The same graph for GTSAM: (NonlinearFactorGraph, initial Values). Beacons are held
    at their surveyed positions, or free from ``initial_beacons`` (L, 2) when given."""
    import gtsam

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()

    def pose_key(i: int) -> int:
        return gtsam.symbol("x", i)

    def beacon_key(j: int) -> int:
        return gtsam.symbol("l", j)

    for i, pose in enumerate(initial_poses):
        values.insert(pose_key(i), gtsam.Pose2(*pose))
    known = initial_beacons is None
    for j, beacon in enumerate(run.anchors.numpy() if known else initial_beacons):
        values.insert(beacon_key(j), beacon.copy())
        if known:
            graph.add(gtsam.NonlinearEqualityPoint2(beacon_key(j), beacon.copy()))
    start = gtsam.Pose2(*run.truth[0].numpy())
    graph.add(
        gtsam.PriorFactorPose2(
            pose_key(0), start, gtsam.noiseModel.Gaussian.Covariance(first_covariance)
        )
    )
    covariances = noise.covariance(run.odometry[:, 0:2].norm(dim=-1)).numpy()
    for i, (dx, dy, turn) in enumerate(run.odometry.numpy()):
        graph.add(
            gtsam.BetweenFactorPose2(
                pose_key(i),
                pose_key(i + 1),
                gtsam.Pose2(dx, dy, turn),
                gtsam.noiseModel.Gaussian.Covariance(covariances[i]),
            )
        )
    gaussian = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    if kernel is None:
        range_noise = gaussian
    else:
        estimator = {
            "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
            "huber": gtsam.noiseModel.mEstimator.Huber,
            "tukey": gtsam.noiseModel.mEstimator.Tukey,
        }[kernel.name].Create(kernel.scale)
        range_noise = gtsam.noiseModel.Robust.Create(estimator, gaussian)
    pose_index = run.range_pose_index().tolist()
    beacon_rows = run.range_anchor_rows().tolist()
    for i, j, z in zip(pose_index, beacon_rows, (run.ranges - bias).tolist(), strict=True):
        graph.add(gtsam.RangeFactor2D(pose_key(i), beacon_key(j), z, range_noise))
    return graph, values


@dataclass
class Setting:
    """What both solvers share: the run, its calibration and the LM settings."""

    run: RangeRun
    noise: OdometryNoise
    bias: float
    sigma: float
    kernel: RobustKernel | None
    first_covariance: torch.Tensor
    tolerance: float
    repeats: int


def solve_case(setting: Setting, beacons: torch.Tensor | None) -> dict[str, Any]:
    """Ours and GTSAM on one graph (beacons known, or free from the guesses ``beacons``
    (L, 2)): timings, costs, errors against the truth, agreement of the two."""
    import gtsam

    run = setting.run
    ranges = run.ranges - setting.bias
    known = beacons is None
    build_start = time.perf_counter()
    problem = odometry_range_problem(
        run.odometry,
        run.range_pose_index(),
        run.range_anchor_rows(),
        ranges,
        run.anchors if known else beacons,
        run.truth[0],
        setting.first_covariance,
        odometry_noise=setting.noise,
        range_sigma_m=setting.sigma,
        range_kernel=setting.kernel,
        beacons_known=known,
    )
    build_s = time.perf_counter() - build_start
    config = LMConfig(
        max_iterations=200,
        damping="identity",
        linear_solver="sparse",
        damping_update="multiplicative",
        relative_tolerance=setting.tolerance,
        absolute_tolerance=0.0,
    )

    def ours():
        with torch.no_grad():
            return solve(problem, config)

    graph, values = gtsam_graph(
        run,
        setting.noise,
        setting.bias,
        setting.sigma,
        setting.kernel,
        setting.first_covariance.numpy(),
        problem.values["pose"][0].numpy(),
        None if known else beacons.numpy(),
    )
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(setting.tolerance)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(200)

    def peer():
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        return optimizer, optimizer.optimize()

    ours(), peer()  # warm-up (MKL / PARDISO start, first calls)
    ours_walls, peer_walls, ours_result, peer_result = [], [], None, None
    for k in range(max(1, setting.repeats)):
        wall, _, ours_result = time_repeats(ours, 1)
        ours_walls.append(wall)
        wall, _, peer_result = time_repeats(peer, 1)
        peer_walls.append(wall)
        log(f"  repeat {k + 1}: ours {ours_walls[-1]:.3f} s, GTSAM {peer_walls[-1]:.3f} s")
    ours_poses = ours_result.values["pose"][0].numpy()
    optimizer, solved = peer_result
    count = ours_poses.shape[0]
    peer_positions = np.array(
        [solved.atPose2(gtsam.symbol("x", i)).translation() for i in range(count)]
    )
    ours_cost, peer_cost = float(ours_result.cost[0]), float(graph.error(solved))
    ours_wall, peer_wall = float(np.median(ours_walls)), float(np.median(peer_walls))
    truth = run.truth[:, 0:2].numpy()
    case = {
        "ours": {
            "wall_s": ours_wall,
            "repeats_s": ours_walls,
            "build_s": build_s,
            "initial_cost": float(ours_result.initial_cost[0]),
            "final_cost": ours_cost,
            "iterations": int(ours_result.iterations[0]),
            "status": ours_result.status[0],
            "error": _errors(ours_poses[:, 0:2], truth),
        },
        "gtsam": {
            "wall_s": peer_wall,
            "repeats_s": peer_walls,
            "initial_cost": float(graph.error(values)),
            "final_cost": peer_cost,
            "iterations": int(optimizer.iterations()),
            "error": _errors(peer_positions, truth),
        },
        "ratio": ours_wall / peer_wall,
        "accuracy": {
            "initial_cost_rel_diff": abs(float(ours_result.initial_cost[0]) - graph.error(values))
            / graph.error(values),
            "final_cost_rel_diff": abs(ours_cost - peer_cost) / peer_cost,
            "max_position_diff_m": float(np.abs(ours_poses[:, 0:2] - peer_positions).max()),
        },
        "poses": ours_poses,
    }
    if not known:
        solved_beacons = ours_result.values["beacon"][0]
        motion = align_points(torch.as_tensor(ours_poses[:, 0:2]), run.truth[:, 0:2])
        aligned = transform_points(motion, torch.as_tensor(ours_poses[:, 0:2])).numpy()
        case["ours"]["aligned_error"] = _errors(aligned, truth)
        case["ours"]["alignment_rotation_deg"] = math.degrees(float(motion[2]))
        surveyed = run.anchors.numpy()
        moved = transform_points(motion, solved_beacons).numpy()
        case["beacons"] = {
            "initial_error_m": np.linalg.norm(beacons.numpy() - surveyed, axis=1).tolist(),
            "error_m": np.linalg.norm(solved_beacons.numpy() - surveyed, axis=1).tolist(),
            "aligned_error_m": np.linalg.norm(moved - surveyed, axis=1).tolist(),
        }
    return case


def odometry_rate(run: RangeRun, calibration_run: RangeRun, rates: list[int]) -> list[dict]:
    """The ``odometry_rate`` case (module docstring): per thinning factor and range timing,
    the calibration and the position error against the truth."""
    rows = []
    for every in rates:
        test, calibration = run.thinned(every), calibration_run.thinned(every)
        row: dict[str, Any] = {
            "every": every,
            "odometry_hz": float(1.0 / torch.diff(test.pose_t).median()),
        }
        for timing in ("next_pose", "interpolate"):
            settings = calibrate_from_truth(
                calibration,
                RangeSmootherSettings(range_timing=timing),
                stretch_steps=max(5, 100 // every),
            )
            settings = dataclasses.replace(settings, start=test.truth[0], start_sigma=START_SIGMA)
            result = smooth_ranges(test, settings)
            row[timing] = {
                "range_bias_m": settings.range_bias_m,
                "range_sigma_m": settings.range_sigma_m,
                **result.truth_error,
            }
        log(
            f"odometry every {every} ({row['odometry_hz']:.2f} Hz): RMSE next pose "
            f"{row['next_pose']['rmse_m']:.3f} m, interpolated {row['interpolate']['rmse_m']:.3f} m"
        )
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (options in the module docstring); returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--test", choices=PLAZA_RUNS, default="Plaza2")
    parser.add_argument("--calibrate", choices=PLAZA_RUNS, default=None)
    parser.add_argument("--kernel", default="cauchy")
    parser.add_argument("--tolerance", type=float, default=1e-10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--slam-window", type=float, default=60.0)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--rates", type=int, nargs="+", default=[1, 5, 10, 20])
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    calibration_name = args.calibrate or next(r for r in PLAZA_RUNS if r != args.test)
    if calibration_name == args.test:
        raise SystemExit("--calibrate must name the other run (settings never come from the test)")
    kernel = parse_kernel(args.kernel)
    run, calibration_run = load_plaza(args.test), load_plaza(calibration_name)
    calibrated = calibrate_from_truth(
        calibration_run, RangeSmootherSettings(range_timing="next_pose")
    )
    settings = {
        "range_bias_m": calibrated.range_bias_m,
        "range_sigma_m": calibrated.range_sigma_m,
        "odometry_forward_m2_per_m": calibrated.odometry_noise.forward,
        "odometry_lateral_m2_per_m": calibrated.odometry_noise.lateral,
        "odometry_heading_rad2_per_m": calibrated.odometry_noise.heading,
    }
    log(f"calibration on {calibration_name}: {settings}")
    setting = Setting(
        run=run,
        noise=calibrated.odometry_noise,
        bias=calibrated.range_bias_m,
        sigma=calibrated.range_sigma_m,
        kernel=kernel,
        first_covariance=torch.diag(torch.tensor(START_SIGMA, dtype=torch.float64) ** 2),
        tolerance=args.tolerance,
        repeats=args.repeats,
    )
    log("localisation (beacons at their surveyed positions)")
    localisation = solve_case(setting, None)
    log(f"range-only SLAM (beacons from the first {args.slam_window:g} s)")
    guesses = initial_beacons(run, run.ranges - setting.bias, args.slam_window)
    slam = solve_case(setting, guesses)
    dead_reckoning = run.odometry_poses()
    poses = localisation.pop("poses")
    slam.pop("poses")
    record = {
        "benchmark": "plaza_ranges",
        "inputs": {
            "test_run": args.test,
            "calibration_run": calibration_name,
            "odometry_steps": int(run.odometry.shape[0]),
            "ranges": int(run.ranges.shape[0]),
            "beacons": int(run.anchors.shape[0]),
            "distance_m": float(run.odometry[:, 0:2].norm(dim=-1).sum()),
            "kernel": None if kernel is None else [kernel.name, kernel.scale],
            "start_sigma": list(START_SIGMA),
            "tolerance": args.tolerance,
            "repeats": args.repeats,
            "slam_window_s": args.slam_window,
            "calibration": settings,
            "meta": run.meta,
        },
        **localisation,
        "dead_reckoning": {
            "error": _errors(dead_reckoning[:, 0:2].numpy(), run.truth[:, 0:2].numpy())
        },
        "slam": slam,
        "odometry_rate": odometry_rate(run, calibration_run, args.rates),
        "machine": machine_info(),
    }
    if args.plot is not None:
        record["plot"] = str(range_run_figure(args.plot, run, torch.as_tensor(poses), run.anchors))
    emit_json(record, digits=12)
    return 0


if __name__ == "__main__":
    sys.exit(main())
