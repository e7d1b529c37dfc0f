"""Real visual-inertial data: keyframe bundle adjustment of EuRoC V1_01 (gtsam's EqVIO file).

What it measures
    ``eqvio_processed_30s.csv`` from the ``gtsam`` wheel (the first 30 s of EuRoC MAV
    ``V1_01_easy``: 200 Hz IMU, 20 Hz cam0 feature tracks in normalized coordinates, 601
    frames, 307 landmark ids) is loaded with :func:`msf_torch.io.eqvio.load_eqvio` and solved
    by :func:`msf_torch.backend.vio.solve_vio`: every ``--stride``-th frame is a keyframe; a
    growing window (last 15 keyframes free) initialises states and landmarks; then ONE
    full batch over all keyframes and landmarks, with reprojection factors (normalized
    coordinates, the file's ``eqf.measurement_noise_variance_norm`` as variance, Huber
    kernel at 2.448 sigma), IMU preintegration factors (the file's ``eqf.input_var_*`` as
    squared noise densities) and a gauge prior on the first state, is solved by LM with the
    landmarks eliminated by the Schur complement. The landmark ids of the file are reused
    by its tracker for new features; tracks are split where an id jumps by more than 0.05
    (normalized) beyond the gyro-predicted rotation (counted in ``inputs.counts``).

    Reported: the final reprojection RMS over ALL observations kept in the final batch
    (per axis, ``sqrt(sum |r|^2 / (2 M))``, normalized units and pixels with the file's fx,
    fy); the batch is solved once under the kernel, observations beyond 5 sigma are removed
    (counted) and it is solved again; the RMS with those put back at the final estimate and
    over the observations the kernel leaves at full weight are reported too; the file's sigma;
    their ratio (target ``<= 1.5``); the fraction of observations the kernel downweights;
    costs, iterations, wall times. The file has no ground truth, so no trajectory error.

    Peer (skipped with ``--no-peer``): GTSAM ``ImuFactor`` + ``BetweenFactorConstantBias`` +
    ``GenericProjectionFactorCal3_S2`` (Huber) on the same observations, solved by GTSAM's
    LM from the initial values of our last final-batch solve
    (``benchmarks/peers/gtsam_vio.py``); each optimum is evaluated on both costs.

How to run
    .venv/bin/python benchmarks/eqvio.py                      # ~1.5 min on 2 cores
    .venv/bin/python benchmarks/eqvio.py --tum /tmp/eqvio.tum --no-peer

    The keyframe trajectory (time s, position m, quaternion wxyz) is printed to stdout as a
    table, then the one JSON line; progress goes to stderr.

Options
    --stride K       keyframe stride in frames (default 4: 5 Hz)
    --tum PATH       also write the keyframe trajectory as a TUM file
    --no-peer        skip GTSAM
    --repeats N      timed repeats of our pipeline (median; default 1)
    --target X       RMS / sigma target (default 1.5)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info, time_repeats  # noqa: E402
from msf_torch.backend.preintegration import cut_imu  # noqa: E402
from msf_torch.backend.vio import (  # noqa: E402
    VioConfig,
    VioData,
    VioResult,
    first_state_prior,
    solve_vio,
)
from msf_torch.geometry.quaternion import matrix_to_quat  # noqa: E402
from msf_torch.io.eqvio import load_eqvio  # noqa: E402
from msf_torch.io.tum import write_tum  # noqa: E402
from msf_torch.types import Trajectory  # noqa: E402


def reprojection_stats(
    residual: torch.Tensor, weight: torch.Tensor, sigma: float, fx: float, fy: float
) -> dict[str, Any]:
    """Per-axis RMS of residuals (M, 2) (normalized, and px with fx, fy), all and at full
    kernel weight, and the fraction downweighted (weight < 1)."""
    px = residual * torch.tensor([fx, fy], dtype=residual.dtype)
    full = weight >= 1.0
    rms = math.sqrt(float((residual**2).mean()))
    return {
        "rms_normalized": rms,
        "rms_px": math.sqrt(float((px**2).mean())),
        "rms_over_sigma": rms / sigma,
        "rms_normalized_full_weight_only": math.sqrt(float((residual[full] ** 2).mean())),
        "observations_full_weight": int(full.sum()),
        "downweighted_fraction": float((~full).double().mean()),
        "max_whitened_norm": float((residual.norm(dim=-1) / sigma).max()),
        "p99_whitened_norm": float(torch.quantile(residual.norm(dim=-1) / sigma, 0.99)),
    }


def trajectory_of(res: VioResult, t0_abs: float) -> Trajectory:
    """B = 1 keyframe trajectory, times in the file's absolute clock."""
    position = res.states[:, 0:3]
    quat = matrix_to_quat(res.states[:, 6:15].reshape(-1, 3, 3))
    num = position.shape[0]
    return Trajectory(
        t=(res.keyframe_times + t0_abs)[None],
        position=position[None],
        quaternion=quat[None],
        mask=torch.ones(1, num, dtype=torch.bool),
    )


def print_trajectory(res: VioResult) -> None:
    """Keyframe table on stdout: t (s from the first IMU sample), p (m), q (wxyz)."""
    quat = matrix_to_quat(res.states[:, 6:15].reshape(-1, 3, 3))
    print(
        "# keyframe trajectory (world: z up, origin and heading of the first keyframe; body = IMU)"
    )
    print(f"# {'t_s':>7} {'x_m':>8} {'y_m':>8} {'z_m':>8} {'qw':>8} {'qx':>8} {'qy':>8} {'qz':>8}")
    rows = zip(res.keyframe_times.tolist(), res.states[:, 0:3].tolist(), quat.tolist(), strict=True)
    for t, p, q in rows:
        cells = " ".join(f"{x:8.4f}" for x in (*p, *q))
        print(f"  {t:7.2f} {cells}")


def run_peer(
    data: VioData, res: VioResult, config: VioConfig, sigma: float, fx: float, fy: float
) -> dict[str, Any]:
    """GTSAM on the final batch of ``res``, from the same initial values."""
    from benchmarks.peers.gtsam_vio import gtsam_error_at, run_gtsam_vio

    problem = res.problem
    init_states = problem.values["state"][0]
    init_points = problem.values["landmark"][0]
    intervals = cut_imu(data.imu_t, data.gyro, data.accel, res.keyframe_times)
    prior_cov = first_state_prior(problem.factors[0].prior.reshape(21), config)
    noise = {
        "gyro_noise_sigma": float(data.imu_noise.gyro_noise_density),
        "accel_noise_sigma": float(data.imu_noise.accel_noise_density),
        "gyro_bias_rw_sigma": float(data.imu_noise.gyro_bias_rw_density),
        "accel_bias_rw_sigma": float(data.imu_noise.accel_bias_rw_density),
    }
    out = run_gtsam_vio(
        init_states.numpy(),
        init_points.numpy(),
        res.obs_keyframe.numpy(),
        res.obs_landmark.numpy(),
        data.obs_uv[res.obs_index].numpy(),
        intervals.gyro.numpy(),
        intervals.accel.numpy(),
        intervals.dt.numpy(),
        data.body_rotation_cam.numpy(),
        data.body_translation_cam.numpy(),
        sigma,
        None if config.kernel is None else config.kernel.scale,
        noise,
        float(-data.gravity[2]),
        prior_cov.numpy(),
        max_iterations=config.final_lm.max_iterations,
    )
    peer_values = {
        "state": torch.as_tensor(out["states"])[None],
        "landmark": torch.as_tensor(out["points"])[None],
    }
    reproj = problem.factors[2]
    residual = reproj.residual(problem.gathered(reproj, peer_values))[0]
    squared = (residual**2).sum(-1) / sigma**2
    weight = (
        config.kernel.weight(squared) if config.kernel is not None else torch.ones_like(squared)
    )
    position_diff = (peer_values["state"][0, :, 0:3] - res.states[:, 0:3]).norm(dim=-1)
    return {
        "what": "GTSAM ImuFactor + BetweenFactorConstantBias + GenericProjectionFactorCal3_S2 "
        "(Huber), LevenbergMarquardtOptimizer, same observations, from the initial values "
        "of our last final-batch solve",
        "iterations": out["iterations"],
        "build_s": out["build_s"],
        "solve_s": out["solve_s"],
        "gtsam_error_initial": out["initial_error"],
        "gtsam_error_final": out["final_error"],
        "gtsam_error_at_ours": gtsam_error_at(
            out["graph"], res.states.numpy(), res.landmarks.numpy()
        ),
        "our_cost_at_peer": float(problem.cost(peer_values)[0]),
        "reprojection": reprojection_stats(residual, weight, sigma, fx, fy),
        "position_difference_to_ours_m": {
            "max": float(position_diff.max()),
            "rms": math.sqrt(float((position_diff**2).mean())),
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stride", type=int, default=4, help="keyframe stride (frames)")
    parser.add_argument("--tum", type=Path, default=None, help="write the trajectory here")
    parser.add_argument("--no-peer", action="store_true", help="skip GTSAM")
    parser.add_argument("--repeats", type=int, default=1, help="timed repeats of ours")
    parser.add_argument("--target", type=float, default=1.5, help="RMS / sigma target")
    args = parser.parse_args(argv)
    machine = machine_info()

    start = time.perf_counter()
    run = load_eqvio()
    load_s = time.perf_counter() - start
    data = VioData.from_eqvio(run)
    config = VioConfig(keyframe_stride=args.stride)
    sigma = data.feature_sigma
    fx, fy = (float(x) for x in run.intrinsics[:2])
    log(f"loaded {run.source}: {run.num_frames} frames, {run.num_observations} observations")
    with torch.no_grad():
        wall, timing, res = time_repeats(
            lambda: solve_vio(data, config), args.repeats, label="ours"
        )
    stats = reprojection_stats(res.residual, res.robust_weight, sigma, fx, fy)
    every = torch.cat((res.residual, res.rejected_residual))
    rms_every = math.sqrt(float((every**2).mean()))
    stats["rms_normalized_including_rejected"] = rms_every
    stats["rms_over_sigma_including_rejected"] = rms_every / sigma
    log(
        f"ours: {res.counts['keyframes']} keyframes, {res.counts['landmarks_kept']} landmarks, "
        f"{res.counts['observations_kept']} observations; RMS {stats['rms_px']:.3f} px "
        f"= {stats['rms_over_sigma']:.3f} sigma; {wall:.1f} s"
    )
    print_trajectory(res)
    if args.tum is not None:
        write_tum(trajectory_of(res, run.t0_abs), args.tum)
        log(f"wrote {args.tum}")

    peer: dict[str, Any] | None = None
    peer_note = "skipped (--no-peer)"
    if not args.no_peer:
        try:
            with torch.no_grad():
                peer = run_peer(data, res, config, sigma, fx, fy)
            peer_note = "ok"
            log(
                f"gtsam: {peer['iterations']} iterations, {peer['solve_s']:.2f} s; RMS "
                f"{peer['reprojection']['rms_px']:.3f} px; max position difference to ours "
                f"{peer['position_difference_to_ours_m']['max']:.4f} m"
            )
        except ImportError as exc:
            peer_note = f"gtsam not importable: {exc}"

    lm = res.lm
    states = res.states
    path = float((states[1:, 0:3] - states[:-1, 0:3]).norm(dim=-1).sum())
    record = {
        "benchmark": "eqvio_vio_ba",
        "inputs": {
            "dataset": "gtsam/Data/eqvio_processed_30s.csv (EuRoC V1_01_easy, first 30 s)",
            "imu_samples": int(data.imu_t.shape[0]),
            "duration_s": run.duration,
            "keyframe_stride": args.stride,
            "keyframes": res.counts["keyframes"],
            "landmarks": res.counts["landmarks_kept"],
            "observations": res.counts["observations_kept"],
            "counts": res.counts,
            "solve": "one full batch over all keyframes and landmarks (initialised by a "
            "growing window, last 15 keyframes free), LM with the landmarks eliminated "
            "by the Schur complement",
            "rms_over": "all observations kept in the final batch, i.e. after one outlier "
            "gate at 5 sigma (counts.observations_rejected_outliers); *_including_rejected "
            "adds the gated ones back at the final estimate; observations of landmarks "
            "dropped before the batch are counted in inputs.counts",
            "repeats": args.repeats,
        },
        "ours": {
            **stats,
            "robust_kernel": {"name": config.kernel.name, "scale_sigma": config.kernel.scale},
            "iterations_last_final_solve": int(lm.iterations[0]),
            "final_solves": res.counts["final_solves"],
            "iterations_growing": res.growth_iterations,
            "status": lm.status[0],
            "initial_cost": res.solve_costs[0][0],
            "final_cost": res.solve_costs[-1][1],
            "costs_per_final_solve": res.solve_costs,
            "wall_s": wall,
            "growing_s": res.timings["growing"],
            "final_batch_s": res.timings["final"],
            "load_s": load_s,
            "timing": timing,
            "gyro_bias_final_rad_s": states[-1, 15:18].tolist(),
            "accel_bias_final_m_s2": states[-1, 18:21].tolist(),
            "path_length_m": path,
        },
        "noise": {
            "sigma_normalized": sigma,
            "sigma_px": run.feature_sigma_px,
            "source": "meta eqf.measurement_noise_variance_norm / _px",
        },
        "peer": peer,
        "peer_note": peer_note,
        "target": {"what": "ours rms_over_sigma <= max_ratio", "max_ratio": args.target},
        "target_met": stats["rms_over_sigma"] <= args.target,
        "trajectory_printed": True,
        "tum_file": None if args.tum is None else str(args.tum),
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
