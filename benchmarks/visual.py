"""Visual front end on rendered runs: fused accuracy, low-texture survival, time per frame.

What it measures
    Rendered stereo runs (``msf_torch.sim.render``): a wheeled robot drives loops (mean
    heading rate ``v / 15 m``, so it comes back past its start) among textured boxes on a
    textured floor, 640 x 480 grayscale at 10 Hz, GNSS-denied, with two wheel-slip episodes,
    a weather schedule that visits sunny, fog, rain, night and snow (blended over 4 s at each
    change; rotated per run) and one 12 s low-texture stretch (contrast x 0.12 within 8 m of
    the path driven then), starting at 45 % of the run. Each frame is rendered once and fed,
    in the same process and the same loop, to

    * ours: :class:`msf_torch.vision.StereoVisualOdometry` (adaptive FAST, KLT, PnP RANSAC
      against stereo map points, essential-matrix fallback, keyframes, ORB descriptors at
      keyframes, image-quality statistics every frame);
    * the ablation: the same with the FAST threshold fixed at 20 (no adaptation);
    * the peer: OpenCV's ORB stereo odometry (``benchmarks/peers/opencv_orb_vo.py``: ORB
      with 1000 features in both images, brute-force Hamming matching, PnP RANSAC), the
      tracking front end of ORB-SLAM2 in OpenCV primitives.

    Then the ESKF (``msf_torch.frontend.eskf.run_eskf``, the simulator's sensor settings via
    ``config_for_sequence``) runs IMU + wheels, and IMU + wheels + our odometry as the named
    pose source ``"vo"`` (fused as odometry increments with the declared covariances).

    Reported per run and over all: Umeyama-aligned (SE(3)) ATE RMSE of IMU + wheels, of the
    fused estimate, of our odometry alone and of the peer's; their ratio (acceptance 2: the
    fused ATE at most 0.5 x IMU + wheels on every run); in the low-texture stretches the
    frames per status (pnp / essential fallback / lost), resets, the fewest map points
    tracked and the lowest FAST threshold, for ours and for the fixed threshold (acceptance
    2: no lost frame and no reset); the time per frame of ours and of the peer, median and
    90th percentile, as wall time and as CPU time of the processing thread (one thread,
    ``cv2.setNumThreads(1)``; CPU time is what the work costs when other jobs share the
    machine, wall time what it took here), beside the anchor paper's ORB-SLAM2 variants'
    41-62 ms per frame (acceptance 4: median at most 30 ms); the NIS of the fused pose
    source (6 rows: 6 expected when the declared covariance is right); the NEES of our
    odometry's increments against the truth (``increment_nees``: over 1 and 100 frames, in
    the earlier frame's body axes, with the covariance the ESKF gives the pairs, ``C_k +
    C_k-1`` summed over the pairs; translation and rotation, 3 expected each, and per axis
    x forward, y left, z up, 1 expected); per weather condition
    the median image-quality statistics and map points tracked; render time per stereo frame.

    Low-texture stress case (seed 21, 30 s loop): from 10 to 22 s the robot crosses an open
    hall, no box within 25 m and the floor at 0.12 contrast (``low_texture_open``); ours
    against the fixed threshold (frames per status, resets) and the ESKF with ours.

    Timing (``timed``, the figures the acceptance uses): ``--timing-frames`` frames of run
    21 from 40 s on (rain, night, the low-texture stretch) are rendered first, then ours
    and the peer process them in turn,
    ``--repeats`` passes each; medians of the per-pass medians, wall and CPU. The per-run
    timings above are taken between renders and are given for reference.

How to run
    .venv/bin/python benchmarks/visual.py              # 3 runs x 90 s (~10 min on 2 cores)
    .venv/bin/python benchmarks/visual.py --quick      # 1 run x 40 s

    Per-run lines go to stderr; the last line on stdout is one JSON object.

Options
    --runs N           runs (seeds 21, 22, ...; default 3; seeds 11-13 tuned the odometry)
    --first-seed N     seed of the first run (default 21; 11 for the tuning runs)
    --duration S       run length, s (default 90)
    --quick            one 40 s run
    --no-peer          skip the ORB peer
    --target-ratio X   fused / IMU + wheels ATE target (default 0.5)
    --target-ms X      time per frame target, ms (default 30)
    --timing-frames N  pre-rendered frames for the timing passes (default 200)
    --repeats N        timing passes of ours and of the peer (default 3)
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info  # noqa: E402
from benchmarks.peers.opencv_orb_vo import OrbStereoVo  # noqa: E402
from msf_torch.eval.metrics import ate  # noqa: E402
from msf_torch.frontend.config import EskfConfig, config_for_sequence  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.geometry.quaternion import matrix_to_quat  # noqa: E402
from msf_torch.sim import simulate_run  # noqa: E402
from msf_torch.sim.render import RunRenderer, SceneConfig, loop_sim_config  # noqa: E402
from msf_torch.sim.weather import WeatherSchedule  # noqa: E402
from msf_torch.types import Trajectory  # noqa: E402
from msf_torch.vision import (  # noqa: E402
    QUALITY_NAMES,
    STATUSES,
    DetectorConfig,
    StereoVisualOdometry,
    VoConfig,
)
from msf_torch.vision.geometry import rotation_log  # noqa: E402

CONDITIONS = ["sunny", "fog", "rain", "night", "snow"]
FIRST_SEED = 21  # seeds 11-13 were used to choose the odometry's KLT window (and to measure)
STRESS_INTERVAL = (10.0, 22.0)
ANCHOR_MS = (41.0, 62.0)


def trajectory(t: np.ndarray, position: np.ndarray, rotation: np.ndarray, mask=None) -> Trajectory:
    """B = 1 trajectory from numpy arrays (F,), (F, 3), (F, 3, 3)."""
    rot = torch.as_tensor(rotation, dtype=torch.float64)
    keep = np.ones(len(t), bool) if mask is None else mask
    return Trajectory(
        t=torch.as_tensor(t, dtype=torch.float64)[None],
        position=torch.as_tensor(position, dtype=torch.float64)[None],
        quaternion=matrix_to_quat(rot)[None],
        mask=torch.as_tensor(keep)[None],
    )


def make_renderer(seed: int, duration: float, index: int) -> tuple[Any, RunRenderer, tuple]:
    """The run, its renderer and the low-texture interval."""
    sim = loop_sim_config(
        duration_s=duration, slip_episodes=2, gnss_outages_s=((0.0, duration + 1.0),)
    )
    run = simulate_run(sim, seed=seed)
    order = CONDITIONS[index % 5 :] + CONDITIONS[: index % 5]
    bounds = list(np.linspace(0.0, duration, len(order) + 1))
    schedule = WeatherSchedule.from_boundaries(bounds, order)
    low = (0.45 * duration, 0.45 * duration + 12.0)
    renderer = RunRenderer.for_run(
        run, SceneConfig(low_texture_s=(low,)), seed=seed, schedule=schedule
    )
    return run, renderer, low


def increment_nees(
    result, truth_position: np.ndarray, truth_rotation: np.ndarray, lag: int
) -> dict[str, Any]:
    """NEES of the odometry's increments over ``lag`` consecutive valid frames against the
    truth (F, 3) m and (F, 3, 3) at the frame times, as the ESKF sees them: the increment in
    the earlier frame's body axes, ``R_a^T (p_b - p_a)`` and ``Log(R_a^T R_b)``, with the
    covariances of the pairs in between (``C_k + C_k-1``, the rotation blocks moved into the
    earlier frame's axes) summed. Increments across a lost frame are skipped. Returns the
    mean 3-DoF NEES of translation and rotation (3 expected) and per axis the mean
    ``e_i^2 / C_ii`` (1 expected)."""
    position = (truth_position - truth_position[0]) @ truth_rotation[0]
    rotation = truth_rotation[0].T @ truth_rotation
    valid = np.nonzero(result.valid)[0]
    cov = result.covariance
    errors_t, errors_r, covs_t, covs_r = [], [], [], []
    for i in range(lag, len(valid)):
        a, b = valid[i - lag], valid[i]
        if b - a != lag:
            continue
        rot_a = result.rotation[a]
        errors_t.append(
            rot_a.T @ (result.position[b] - result.position[a])
            - rotation[a].T @ (position[b] - position[a])
        )
        turn = rot_a.T @ result.rotation[b]
        errors_r.append(rotation_log((rotation[a].T @ rotation[b]).T @ turn))
        pairs = np.arange(a + 1, b + 1)
        covs_t.append(rot_a.T @ (cov[pairs, :3, :3] + cov[pairs - 1, :3, :3]).sum(0) @ rot_a)
        moved = rot_a.T @ result.rotation[np.concatenate((pairs, pairs - 1))]
        blocks = np.concatenate((cov[pairs, 3:, 3:], cov[pairs - 1, 3:, 3:]))
        covs_r.append((moved @ blocks @ moved.transpose(0, 2, 1)).sum(0))
    out: dict[str, Any] = {"lag_frames": lag, "increments": len(errors_t)}
    for name, errors, covs in (("translation", errors_t, covs_t), ("rotation", errors_r, covs_r)):
        e, c = np.array(errors), np.array(covs)
        out[f"nees_{name}"] = float(np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e).mean())
        out[f"nees_{name}_per_axis"] = (e**2 / np.diagonal(c, 0, 1, 2)).mean(0).tolist()
    return out


def low_texture_summary(result, inside: np.ndarray) -> dict[str, Any]:
    status = result.status[inside]
    return {
        "frames": int(inside.sum()),
        **{name: int((status == k).sum()) for k, name in enumerate(STATUSES) if k > 0},
        "resets": int(result.resets),
        "min_map_tracked": int(result.map_tracked[inside].min()),
        "median_map_tracked": float(np.median(result.map_tracked[inside])),
        "min_fast_threshold": float(result.threshold[inside].min()),
    }


def one_run(seed: int, duration: float, index: int, with_peer: bool) -> dict[str, Any]:
    run, renderer, low = make_renderer(seed, duration, index)
    rig = renderer.rig
    ours = StereoVisualOdometry(rig)
    fixed_detector = DetectorConfig(threshold_min=20.0, threshold_max=20.0)
    fixed = StereoVisualOdometry(rig, VoConfig(detector=fixed_detector, descriptors=False))
    peer = OrbStereoVo(
        rig.matrix(), rig.baseline_m, rig.body_rotation_cam(), rig.body_translation_cam()
    )
    render_s = []
    for k in range(len(renderer)):
        start = time.perf_counter()
        frame = renderer.frame(k)
        render_s.append(time.perf_counter() - start)
        ours.process(frame.t, frame.left, frame.right)
        fixed.process(frame.t, frame.left, frame.right)
        if with_peer:
            peer.process(frame.t, frame.left, frame.right)
    res, res_fixed = ours.result(), fixed.result()

    seq = dataclasses.replace(run.sequence, gnss=None)  # GNSS-denied
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    with torch.no_grad():
        alone = run_eskf(seq, cfg)
        fused = run_eskf(dataclasses.replace(seq, pose_sources={"vo": res.pose_source()}), cfg)
    truth = seq.ground_truth
    ate_alone = ate(alone.trajectory(), truth)["rmse"]
    ate_fused = ate(fused.trajectory(), truth)["rmse"]
    ate_vo = ate(trajectory(res.t, res.position, res.rotation, res.valid), truth)["rmse"]
    here = fused.present["pose:vo"] & fused.mask
    nis = float(fused.nis["pose:vo"][here].mean())
    accepted = fused.counts()["pose:vo"]
    truth_p, truth_r = renderer.body_poses()
    nees = [increment_nees(res, truth_p, truth_r, lag) for lag in (1, 100)]

    inside = (res.t >= low[0]) & (res.t <= low[1])
    weather = np.array([w.name for w in renderer._weather])
    per_condition = {}
    for name in CONDITIONS:
        sel = weather == name
        per_condition[name] = {
            **{q: float(np.median(res.quality[sel, i])) for i, q in enumerate(QUALITY_NAMES)},
            "median_map_tracked": float(np.median(res.map_tracked[sel])),
            "median_fast_threshold": float(np.median(res.threshold[sel])),
        }
    row: dict[str, Any] = {
        "seed": seed,
        "frames": len(res.t),
        "path_length_m": float(
            np.linalg.norm(np.diff(truth.position[0].numpy(), axis=0), axis=1).sum()
        ),
        "low_texture_s": list(low),
        "weather_order": [s.condition for s in renderer.schedule.segments],
        "ate_imu_wheel_m": ate_alone,
        "ate_fused_m": ate_fused,
        "ate_ratio": ate_fused / ate_alone,
        "ate_vo_m": ate_vo,
        "vo_counts": res.counts(),
        "vo_nis_mean": nis,
        "vo_increment_nees": nees,
        "vo_pairs_present": accepted["present"][0],
        "vo_pairs_accepted": accepted["accepted"][0],
        "low_texture": low_texture_summary(res, inside),
        "low_texture_fixed_threshold": low_texture_summary(res_fixed, inside),
        "per_condition": per_condition,
        "ours_cpu_s": res.cpu_s.tolist(),
        "ours_wall_s": res.wall_s.tolist(),
        "ours_keyframe": res.keyframe.tolist(),
        "render_s": render_s,
    }
    if with_peer:
        row["ate_peer_m"] = ate(
            trajectory(np.array(peer.times), np.array(peer.positions), np.array(peer.rotations)),
            truth,
        )["rmse"]
        row["peer_failures"] = peer.failures
        row["peer_cpu_s"] = peer.cpu_s
        row["peer_wall_s"] = peer.wall_s
    log(
        f"seed {seed}: ATE imu+wheel {ate_alone:.3f} m, fused {ate_fused:.3f} m "
        f"(ratio {ate_fused / ate_alone:.3f}), VO {ate_vo:.3f} m"
        + (f", peer {row['ate_peer_m']:.3f} m" if with_peer else "")
        + f"; low texture {row['low_texture']}; fixed threshold "
        f"{row['low_texture_fixed_threshold']}; ours {np.median(res.cpu_s) * 1e3:.1f} ms cpu "
        f"/ {np.median(res.wall_s) * 1e3:.1f} ms wall per frame"
    )
    for n in nees:
        log(
            f"seed {seed}: VO increment NEES over {n['lag_frames']} frames: translation "
            f"{n['nees_translation']:.2f} (x, y, z "
            + ", ".join(f"{v:.2f}" for v in n["nees_translation_per_axis"])
            + f"), rotation {n['nees_rotation']:.2f} (roll, pitch, yaw "
            + ", ".join(f"{v:.2f}" for v in n["nees_rotation_per_axis"])
            + f"); fused NIS {nis:.2f}"
        )
    return row


def stress_run(seed: int) -> dict[str, Any]:
    """The open-hall stress case: a 30 s loop whose 10-22 s stretch has no boxes within
    25 m and a floor at 0.12 contrast; adaptive against fixed threshold, and the ESKF."""
    run = simulate_run(loop_sim_config(duration_s=30.0), seed=seed)
    scene = SceneConfig(
        low_texture_s=(STRESS_INTERVAL,), low_texture_radius_m=25.0, low_texture_open=True
    )
    renderer = RunRenderer.for_run(run, scene, seed=seed)
    adaptive = StereoVisualOdometry(renderer.rig)
    fixed_detector = DetectorConfig(threshold_min=20.0, threshold_max=20.0)
    fixed = StereoVisualOdometry(renderer.rig, VoConfig(detector=fixed_detector))
    for frame in renderer:
        adaptive.process(frame.t, frame.left, frame.right)
        fixed.process(frame.t, frame.left, frame.right)
    res, res_fixed = adaptive.result(), fixed.result()
    inside = (res.t >= STRESS_INTERVAL[0]) & (res.t <= STRESS_INTERVAL[1])
    seq = dataclasses.replace(run.sequence, gnss=None)
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    with torch.no_grad():
        alone = run_eskf(seq, cfg)
        fused = run_eskf(dataclasses.replace(seq, pose_sources={"vo": res.pose_source()}), cfg)
    truth = seq.ground_truth
    out = {
        "seed": seed,
        "interval_s": list(STRESS_INTERVAL),
        "adaptive": low_texture_summary(res, inside),
        "fixed_threshold": low_texture_summary(res_fixed, inside),
        "ate_imu_wheel_m": ate(alone.trajectory(), truth)["rmse"],
        "ate_fused_m": ate(fused.trajectory(), truth)["rmse"],
        "ate_vo_m": ate(trajectory(res.t, res.position, res.rotation, res.valid), truth)["rmse"],
    }
    log(f"open-hall stress: {out}")
    return out


def timed_passes(
    seed: int, duration: float, frames: int, repeats: int, with_peer: bool
) -> dict[str, Any]:
    """Per-frame time of ours and of the peer on the same pre-rendered frames (``frames``
    consecutive frames of run ``seed`` from 40 s on: rain, night and the low-texture
    stretch), ``repeats`` passes each, alternating; the medians of the per-pass medians."""
    _, renderer, _ = make_renderer(seed, duration, 0)
    first = min(int(40.0 * renderer.rate_hz), max(len(renderer) - frames, 0))
    stereo = [renderer.frame(k) for k in range(first, min(first + frames, len(renderer)))]
    passes: dict[str, list[dict[str, float]]] = {"ours": [], "peer": []}
    rig = renderer.rig
    for _ in range(repeats):
        ours = StereoVisualOdometry(rig)
        for f in stereo:
            ours.process(f.t, f.left, f.right)
        res = ours.result()
        passes["ours"].append(
            {
                "wall_ms": float(np.median(res.wall_s)) * 1e3,
                "cpu_ms": float(np.median(res.cpu_s)) * 1e3,
            }
        )
        if with_peer:
            peer = OrbStereoVo(
                rig.matrix(), rig.baseline_m, rig.body_rotation_cam(), rig.body_translation_cam()
            )
            for f in stereo:
                peer.process(f.t, f.left, f.right)
            passes["peer"].append(
                {
                    "wall_ms": float(np.median(peer.wall_s)) * 1e3,
                    "cpu_ms": float(np.median(peer.cpu_s)) * 1e3,
                }
            )
    out: dict[str, Any] = {"frames": len(stereo), "repeats": repeats}
    for who, values in passes.items():
        if values:
            out[who] = {
                "wall_median_ms": float(np.median([v["wall_ms"] for v in values])),
                "cpu_median_ms": float(np.median([v["cpu_ms"] for v in values])),
                "per_pass": values,
            }
    log(f"timing on {len(stereo)} pre-rendered frames: {out}")
    return out


def timing(values: list[float]) -> dict[str, float]:
    ms = np.asarray(values) * 1e3
    return {
        "median_ms": float(np.median(ms)),
        "p90_ms": float(np.percentile(ms, 90)),
        "mean_ms": float(ms.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=FIRST_SEED)
    parser.add_argument("--duration", type=float, default=90.0)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--target-ratio", type=float, default=0.5)
    parser.add_argument("--target-ms", type=float, default=30.0)
    parser.add_argument("--timing-frames", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    runs, duration = (1, 40.0) if args.quick else (args.runs, args.duration)
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    with_peer = not args.no_peer
    rows = [one_run(args.first_seed + i, duration, i, with_peer) for i in range(runs)]
    stress = stress_run(FIRST_SEED)
    timed = timed_passes(FIRST_SEED, duration, args.timing_frames, args.repeats, with_peer)

    def gather(key: str) -> list[float]:
        return [x for r in rows for x in r[key]]

    keyframe = np.array(gather("ours_keyframe"))
    ours_cpu, ours_wall = np.array(gather("ours_cpu_s")), np.array(gather("ours_wall_s"))
    ours = {
        "cpu": timing(ours_cpu.tolist()),
        "wall": timing(ours_wall.tolist()),
        "keyframe_cpu": timing(ours_cpu[keyframe].tolist()),
        "other_frames_cpu": timing(ours_cpu[~keyframe].tolist()),
        "ate_vo_m": [r["ate_vo_m"] for r in rows],
        "ate_fused_m": [r["ate_fused_m"] for r in rows],
        "vo_nis_mean": [r["vo_nis_mean"] for r in rows],
        "vo_increment_nees": [r["vo_increment_nees"] for r in rows],
    }
    peer: dict[str, Any] = {"name": "OpenCV ORB stereo VO (ORB x2, BF Hamming, PnP RANSAC)"}
    ratio: dict[str, Any] = {"ate_fused_over_imu_wheel": [r["ate_ratio"] for r in rows]}
    if with_peer:
        peer.update(
            cpu=timing(gather("peer_cpu_s")),
            wall=timing(gather("peer_wall_s")),
            ate_vo_m=[r["ate_peer_m"] for r in rows],
            failures=[r["peer_failures"] for r in rows],
        )
        ratio["time_ours_over_peer_cpu"] = ours["cpu"]["median_ms"] / peer["cpu"]["median_ms"]
        ratio["time_ours_over_peer_wall"] = ours["wall"]["median_ms"] / peer["wall"]["median_ms"]
        ratio["ate_vo_ours_over_peer"] = [r["ate_vo_m"] / r["ate_peer_m"] for r in rows]
    low_ok = all(r["low_texture"]["lost"] == 0 and r["low_texture"]["resets"] == 0 for r in rows)
    low_ok &= stress["adaptive"]["lost"] == 0 and stress["adaptive"]["resets"] == 0
    targets = {
        "ate_ratio_target": args.target_ratio,
        "ate_ratio_worst": max(r["ate_ratio"] for r in rows),
        "ate_ratio_met": all(r["ate_ratio"] <= args.target_ratio for r in rows),
        "low_texture_no_loss_no_reset_met": low_ok,
        "frame_ms_target": args.target_ms,
        "frame_ms_cpu_met": timed["ours"]["cpu_median_ms"] <= args.target_ms,
        "frame_ms_wall_met": timed["ours"]["wall_median_ms"] <= args.target_ms,
    }
    if with_peer:
        ratio["timed_ours_over_peer_wall"] = (
            timed["ours"]["wall_median_ms"] / timed["peer"]["wall_median_ms"]
        )
        ratio["timed_ours_over_peer_cpu"] = (
            timed["ours"]["cpu_median_ms"] / timed["peer"]["cpu_median_ms"]
        )
    for r in rows:
        for key in ("ours_cpu_s", "ours_wall_s", "ours_keyframe", "peer_cpu_s", "peer_wall_s"):
            r.pop(key, None)
        r["render_ms_median"] = float(np.median(r.pop("render_s")) * 1e3)
    emit_json(
        {
            "benchmark": "visual",
            "inputs": {
                "runs": runs,
                "duration_s": duration,
                "rate_hz": 10.0,
                "image": [640, 480],
                "stereo_baseline_m": 0.12,
                "conditions": CONDITIONS,
                "gnss": "none",
                "slip_episodes": 2,
            },
            "ours": ours,
            "peer": peer,
            "anchor_orb_slam2_ms_per_frame": list(ANCHOR_MS),
            "ratio": ratio,
            "accuracy": {
                "ate_imu_wheel_m": [r["ate_imu_wheel_m"] for r in rows],
                "ate_fused_m": [r["ate_fused_m"] for r in rows],
                "ate_vo_m": [r["ate_vo_m"] for r in rows],
                **({"ate_peer_vo_m": [r["ate_peer_m"] for r in rows]} if with_peer else {}),
            },
            "timed": timed,
            "low_texture_stress": stress,
            "targets": targets,
            "per_run": rows,
            "machine": machine_info(),
        }
    )


if __name__ == "__main__":
    main()
