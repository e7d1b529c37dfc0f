"""Front-end speed on the real KITTI drive: our ESKF vs GTSAM's ISAM2 and a filterpy ESKF.

What it measures
    Input: the KITTI IMU + GPS drive that the ``gtsam`` wheel ships (471 s, 46,968 IMU
    samples at ~100 Hz, 470 GPS fixes at 1 Hz), full GNSS, loaded once as a ``Sequence``.

    * ours, single: wall time from the loaded ``Sequence`` to a finished trajectory,
      ``run_eskf(seq, cfg).trajectory()`` under ``torch.no_grad()`` with torch's default
      thread count; config ``msf_torch/configs/kitti-gtsam.yaml`` plus the dataset's IMU
      noise. Realtime factor = drive duration / wall; IMU samples per second.
    * ours, batched: B = 32 copies of the drive in one ``batch_sequences`` batch. Copy 0 is
      the drive itself; copies 1..31 get their own GNSS noise realisation (N(0, sigma^2)
      per axis, seeded) and a time shift of all streams, so they are 32 distinct full-length
      sequences. Aggregate IMU samples per second vs the single run (target: >= 10x).
      Copy 0 of the batch is checked against the single run (``batch_copy0_max_diff_m``).
      With two or more torch threads a batch of 16 or more preintegrates its IMU on a
      worker thread while its epoch loop runs (``run_eskf``); the single run has too little
      to preintegrate for that and runs on one thread. ``OMP_NUM_THREADS=1`` runs both on
      one thread.
    * peer 1 (the ratio's peer): GTSAM CombinedImuFactor + GPSFactor under ISAM2
      (``benchmarks/peers/gtsam_kitti.py``) on the same arrays; wall time of the call
      (graph building, ISAM2 updates, estimate extraction). Target: ours below GTSAM's.
    * peer 2: a per-IMU-sample ESKF of the same model on ``filterpy.kalman.KalmanFilter``
      (``benchmarks/peers/filterpy_eskf.py``), timed from the same ``Sequence`` (its initial
      state comes from ours), over the whole drive or a prefix (``--filterpy-prefix-s``).

    * ``--device cuda``: ours (B = 1, the batch and ``--extra-batch``) runs on the GPU: the
      loaded sequences are moved there before timing, and every timed call ends with
      ``torch.cuda.synchronize()``. The peers stay on the CPU, so ``ratio`` then compares our
      GPU run with GTSAM on the CPU. ``cuda_peak_allocated_mb``: the GPU memory high-water
      mark of each of our runs (``torch.cuda.max_memory_allocated``).
    * ``--extra-batch N``: one more batched run of ours with N copies (e.g. 256), reported
      as ``ours.extra_batched`` with its speedup over the single run; not judged.

    Timings are medians over ``--repeats`` (after ``--warmup`` untimed runs of each of our
    parts, B = 1 and batched alike: a process's first batched run pays for first-touch page
    faults of its memory, about 0.2 s more on the CPU at B = 32, and for CUDA's first calls
    on the GPU), with the minimum and the process CPU time alongside (wall time grows when
    other work shares the machine; CPU time much less). Peak resident memory: each part
    runs once more in a fresh spawned process that has loaded the drive and built the
    part's input; VmHWM is reset before the run and read after it (``peak_rss_mb``,
    ``rss_before_mb`` and ``peak_minus_before_mb`` = what the run adds). Accuracy:
    position RMSE against the GPS fixes (which every estimator also fuses, so this is a
    consistency figure, not ground truth), on the fixes from GTSAM's first causal state on;
    GTSAM's smoothed RMSE for reference.

    ``ratio`` = ours_wall / gtsam_wall (below 1 means ours is faster).

How to run
    .venv/bin/python benchmarks/frontend_speed.py             # ~1-3 min on a 2-core CPU
    .venv/bin/python benchmarks/frontend_speed.py --quick     # 1 repeat, B = 8
    .venv/bin/python benchmarks/frontend_speed.py --device cuda --extra-batch 256

    Progress goes to stderr; the last line on stdout is one JSON object.

Options
    --repeats N            timed repeats of each part (median; default 3)
    --warmup N             untimed runs of ours before timing (default 1)
    --batch N              batch size of the batched run (default 32)
    --batch-repeats N      timed repeats of the batched run (default: --repeats)
    --gnss-noise-m S       GNSS noise sigma added to copies 1..B-1, m (default 0.2)
    --time-shift-s S       time shift of copy k is k * S, s (default 1e-3)
    --filterpy-prefix-s S  run the filterpy peer on the first S seconds only (0 = all; default)
    --extra-batch N        also time ours with N copies (0 = no; default), not judged
    --device cpu|cuda      where ours runs (default cpu); peers always on the CPU
    --quick                1 repeat, no warm-up, B = 8 (the 10x target is still judged)
    --no-memory            skip the four memory-measurement processes
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import multiprocessing
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import (  # noqa: E402
    PeakRss,
    emit_json,
    kitti_config,
    log,
    machine_info,
    peer_arrays,
    time_repeats,
    trajectory_from,
)
from benchmarks.peers.filterpy_eskf import inputs_from_sequence, run_filterpy_eskf  # noqa: E402
from benchmarks.peers.gtsam_kitti import run_gtsam_kitti  # noqa: E402
from msf_torch.eval.outage import outage_metrics  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.io import load_sequence  # noqa: E402
from msf_torch.types import GnssFixes, Sequence, batch_sequences  # noqa: E402


def variant(seq: Sequence, k: int, noise_m: float, shift_s: float) -> Sequence:
    """Copy ``k`` of the drive: GNSS noise realisation ``k`` and all times shifted by k*shift."""
    if k == 0:
        return seq
    gen = torch.Generator().manual_seed(1000 + k)
    shift = k * shift_s
    gnss = seq.gnss
    noise = noise_m * torch.randn(gnss.position.shape, generator=gen, dtype=gnss.position.dtype)
    gnss = dataclasses.replace(gnss, t=gnss.t + shift, position=gnss.position + noise)
    imu = dataclasses.replace(seq.imu, t=seq.imu.t + shift)
    return dataclasses.replace(seq, imu=imu, gnss=gnss, names=[f"{seq.names[0]}#{k}"])


def rmse_at(traj, fixes: GnssFixes) -> float:
    """Position RMSE of a trajectory against fixes (interpolated at the fix times)."""
    return float(outage_metrics(traj, fixes)["outage_rmse_m"])


def synchronized(fn: Callable[[], Any], device: torch.device) -> Callable[[], Any]:
    """``fn`` followed by ``torch.cuda.synchronize`` on a CUDA device (so a timing covers
    the queued GPU work); ``fn`` itself on the CPU."""
    if device.type != "cuda":
        return fn

    def run():
        out = fn()
        torch.cuda.synchronize(device)
        return out

    return run


def part_callable(
    name: str, seq: Sequence, cfg: Any, opts: dict[str, Any]
) -> tuple[Callable[[], Any], dict[str, Any]]:
    """The zero-argument callable that one timed part runs, and facts about its input.

    ``name``: ``ours`` (B = 1), ``ours_batch`` (B = ``opts["batch"]`` varied copies),
    ``ours_extra`` (B = ``opts["extra_batch"]``), ``gtsam`` or ``filterpy``. Ours runs on
    ``opts["device"]`` (the input is moved there first, outside the callable; on CUDA the
    callable ends with a synchronize). Timing and memory measurement run exactly these
    callables.
    """
    device = torch.device(opts.get("device", "cpu"))
    if name == "ours":
        seq_dev = seq.to(device)

        def ours():
            with torch.no_grad():
                result = run_eskf(seq_dev, cfg)
                return result, result.trajectory()

        return synchronized(ours, device), {"imu_samples": int(seq.imu.mask.sum())}
    if name in ("ours_batch", "ours_extra"):
        start = time.perf_counter()
        size = opts["batch"] if name == "ours_batch" else opts["extra_batch"]
        copies = [variant(seq, k, opts["gnss_noise_m"], opts["time_shift_s"]) for k in range(size)]
        batch = batch_sequences(copies).to(device)
        info = {"imu_samples": int(batch.imu.mask.sum()), "build_s": time.perf_counter() - start}

        def ours_batch():
            with torch.no_grad():
                result = run_eskf(batch, cfg)
                return result, result.trajectory()

        return synchronized(ours_batch, device), info
    if name == "gtsam":
        arrays = peer_arrays(seq)
        return (lambda: run_gtsam_kitti(**arrays)), {}
    if name == "filterpy":
        prefix = opts["prefix"]
        return (lambda: run_filterpy_eskf(**inputs_from_sequence(seq, cfg), t_stop=prefix)), {}
    raise ValueError(f"unknown part {name!r}")


def _memory_child(name: str, opts: dict[str, Any], conn: Any) -> None:
    """Child process: load the drive, build the part's input, run it once under PeakRss."""
    try:
        seq = load_sequence("kitti-gtsam")
        cfg, _ = kitti_config(seq)
        fn, _ = part_callable(name, seq, cfg, opts)
        gc.collect()
        cuda = name.startswith("ours") and torch.device(opts["device"]).type == "cuda"
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        with PeakRss() as mem:
            fn()
        gpu = {"cuda_peak_allocated_mb": torch.cuda.max_memory_allocated() / 2**20} if cuda else {}
        conn.send({**mem.as_dict(), **gpu, "process": "fresh"})
    except Exception as exc:  # report, do not hang the parent
        conn.send({"error": f"{type(exc).__name__}: {exc}"})
    finally:
        conn.close()


def measure_memory(name: str, opts: dict[str, Any]) -> dict[str, Any]:
    """Peak RSS of one run of a part, in a fresh (spawned) process with the input loaded.

    ``rss_before_mb`` is the process with Python, torch, the drive and the part's input
    loaded; ``peak_minus_before_mb`` is what the run itself adds at its peak.
    """
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_memory_child, args=(name, opts, child))
    proc.start()
    child.close()
    try:
        result = parent.recv()
    except EOFError:
        result = {"error": "the memory process ended without a result"}
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--batch-repeats", type=int, default=None, help="default: --repeats")
    parser.add_argument("--gnss-noise-m", type=float, default=0.2)
    parser.add_argument("--time-shift-s", type=float, default=1e-3)
    parser.add_argument("--filterpy-prefix-s", type=float, default=0.0)
    parser.add_argument("--extra-batch", type=int, default=0, help="also time this B (0: no)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="where ours runs")
    parser.add_argument("--quick", action="store_true", help="1 repeat, no warm-up, B = 8")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory processes")
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats, args.warmup, args.batch = 1, 0, min(args.batch, 8)
    batch_repeats = args.batch_repeats if args.batch_repeats is not None else args.repeats
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA device")
    # a batched run's first call pays for first-touch page faults of its memory (CPU) or
    # CUDA's first calls (GPU), which a warm-up takes out as it does for B = 1
    batch_warmup = args.warmup
    machine = machine_info()  # before our own load shows in the load average

    seq = load_sequence("kitti-gtsam")
    cfg, explicit = kitti_config(seq)
    n_imu = int(seq.imu.mask.sum())
    n_fix = int(seq.gnss.mask.sum())
    duration = float(seq.imu.t[0, -1] - seq.imu.t[0, 0])
    log(
        f"kitti-gtsam: {n_imu} IMU samples, {n_fix} fixes, {duration:.1f} s; "
        f"torch threads {torch.get_num_threads()}; ours on {device}"
    )

    opts = {
        "batch": args.batch,
        "gnss_noise_m": args.gnss_noise_m,
        "time_shift_s": args.time_shift_s,
        "prefix": args.filterpy_prefix_s if args.filterpy_prefix_s > 0 else None,
        "extra_batch": args.extra_batch,
        "device": args.device,
    }
    prefix = opts["prefix"]

    # --- ours, single sequence ------------------------------------------------------------
    ours_single, _ = part_callable("ours", seq, cfg, opts)
    ours_wall, ours_times, (ours_res, ours_traj) = time_repeats(
        ours_single, args.repeats, args.warmup, label="ours B=1"
    )
    log(f"ours B=1: {ours_wall:.3f} s median, {n_imu / ours_wall:.0f} samples/s")

    # --- ours, batched ----------------------------------------------------------------------
    ours_batch, batch_info = part_callable("ours_batch", seq, cfg, opts)
    n_batch_imu = batch_info["imu_samples"]
    batch_wall, batch_times, (batch_res, _) = time_repeats(
        ours_batch, batch_repeats, batch_warmup, label=f"ours B={args.batch}"
    )
    copy0_diff = float(
        (batch_res.position[0, : ours_res.position.shape[1]] - ours_res.position[0]).abs().max()
    )
    del batch_res, ours_batch
    log(f"ours B={args.batch}: {batch_wall:.3f} s median, {n_batch_imu / batch_wall:.0f} samples/s")

    extra = None
    if args.extra_batch > 0:
        ours_extra, extra_info = part_callable("ours_extra", seq, cfg, opts)
        extra_wall, extra_times, (extra_res, _) = time_repeats(
            ours_extra, batch_repeats, batch_warmup, label=f"ours B={args.extra_batch}"
        )
        extra_diff = float(
            (extra_res.position[0, : ours_res.position.shape[1]] - ours_res.position[0]).abs().max()
        )
        del extra_res, ours_extra
        extra_sps = extra_info["imu_samples"] / extra_wall
        extra = {
            "batch": args.extra_batch,
            "wall_s": extra_wall,
            "timing": extra_times,
            "imu_samples": extra_info["imu_samples"],
            "imu_samples_per_s": extra_sps,
            "aggregate_realtime_factor": args.extra_batch * duration / extra_wall,
            "speedup_vs_single": extra_sps / (n_imu / ours_wall),
            "batch_build_s": extra_info["build_s"],
            "batch_copy0_max_diff_m": extra_diff,
        }
        log(f"ours B={args.extra_batch}: {extra_wall:.3f} s median, {extra_sps:.0f} samples/s")

    # --- GTSAM peer -------------------------------------------------------------------------
    gtsam_run, _ = part_callable("gtsam", seq, cfg, opts)
    gtsam_wall, gtsam_times, gtsam_res = time_repeats(gtsam_run, args.repeats, label="gtsam")
    log(f"gtsam: {gtsam_wall:.3f} s median (its own wall_s {gtsam_res['wall_s']:.3f} s)")

    # --- filterpy peer ------------------------------------------------------------------------
    filterpy_run, _ = part_callable("filterpy", seq, cfg, opts)
    fp_wall, fp_times, fp_res = time_repeats(filterpy_run, args.repeats, label="filterpy")
    fp_samples = fp_res["imu_samples"]
    log(f"filterpy: {fp_wall:.3f} s median over {fp_samples} samples")

    # --- peak memory, each part once in a fresh process ----------------------------------------
    memory: dict[str, Any] = {}
    if not args.no_memory:
        parts = ("ours", "ours_batch") + (("ours_extra",) if extra else ()) + ("gtsam", "filterpy")
        for name in parts:
            memory[name] = measure_memory(name, opts)
            log(f"memory {name}: {memory[name]}")

    # --- accuracy (RMSE vs GPS) on the fixes where GTSAM's estimate is causal ------------------
    first = gtsam_res["first_gps_index"]
    causal_idx = np.nonzero(gtsam_res["causal"])[0] + first
    scored = seq.gnss.map(lambda x: x[:, torch.as_tensor(causal_idx)])
    ours_traj = ours_traj.to("cpu")
    fp_traj = trajectory_from(fp_res["t"], fp_res["position"])
    fp_scored = scored
    if prefix is not None:
        inside = scored.t[0] <= fp_res["t"][-1]
        fp_scored = scored.map(lambda x: x[:, inside])
    acc = {
        "scored_fixes": int(causal_idx.size),
        "ours_rmse_vs_gps_m": rmse_at(ours_traj, scored),
        "gtsam_filter_rmse_vs_gps_m": rmse_at(
            trajectory_from(gtsam_res["t"], gtsam_res["filter_position"]), scored
        ),
        "gtsam_smoothed_rmse_vs_gps_m": rmse_at(
            trajectory_from(gtsam_res["t"], gtsam_res["smoothed_position"]), scored
        ),
        "filterpy_rmse_vs_gps_m": rmse_at(fp_traj, fp_scored) if fp_scored.mask.any() else None,
        "filterpy_scored_fixes": int(fp_scored.mask.sum()),
        "ours_gnss_accepted": int(ours_res.accepted["gnss"].sum()),
        "ours_gnss_rejected": int((ours_res.present["gnss"] & ~ours_res.accepted["gnss"]).sum()),
        "filterpy_gnss_accepted": fp_res["gnss_updates"],
        "filterpy_gnss_rejected": fp_res["gnss_rejected"],
    }

    single_sps = n_imu / ours_wall
    batch_sps = n_batch_imu / batch_wall
    speedup = batch_sps / single_sps
    ratio = ours_wall / gtsam_wall
    record = {
        "benchmark": "frontend_speed",
        "inputs": {
            "dataset": "kitti-gtsam (gtsam/Data: KittiEquivBiasedImu + KittiGps_converted)",
            "imu_samples": n_imu,
            "gps_fixes": n_fix,
            "duration_s": duration,
            "gnss": "full (no outage)",
            "ours_config": "msf_torch/configs/kitti-gtsam.yaml + dataset IMU noise",
            "ours_config_explicit_keys": explicit,
            "repeats": args.repeats,
            "warmup": args.warmup,
            "batch": args.batch,
            "batch_repeats": batch_repeats,
            "batch_warmup": batch_warmup,
            "batch_variation": {
                "gnss_noise_sigma_m": args.gnss_noise_m,
                "time_shift_per_copy_s": args.time_shift_s,
            },
            "filterpy_prefix_s": prefix,
            "torch_threads": torch.get_num_threads(),
            "grad": "torch.no_grad()",
            "ours_device": str(device),
            "ours_device_name": (
                torch.cuda.get_device_name(device) if device.type == "cuda" else None
            ),
            "peers_device": "cpu",
            "extra_batch": args.extra_batch,
        },
        "ours": {
            "wall_s": ours_wall,
            "timing": ours_times,
            "realtime_factor": duration / ours_wall,
            "imu_samples_per_s": single_sps,
            "memory": memory.get("ours"),
            "batched": {
                "batch": args.batch,
                "wall_s": batch_wall,
                "timing": batch_times,
                "imu_samples": n_batch_imu,
                "imu_samples_per_s": batch_sps,
                "aggregate_realtime_factor": args.batch * duration / batch_wall,
                "speedup_vs_single": speedup,
                "batch_build_s": batch_info["build_s"],
                "batch_copy0_max_diff_m": copy0_diff,
                "memory": memory.get("ours_batch"),
            },
            "extra_batched": None
            if extra is None
            else {**extra, "memory": memory.get("ours_extra")},
        },
        "peer": {
            "name": "GTSAM CombinedImuFactor + GPSFactor, ISAM2 (benchmarks/peers/gtsam_kitti.py)",
            "wall_s": gtsam_wall,
            "timing": gtsam_times,
            "wall_s_internal_last": gtsam_res["wall_s"],
            "realtime_factor": duration / gtsam_wall,
            "imu_samples_per_s": n_imu / gtsam_wall,
            "memory": memory.get("gtsam"),
        },
        "peer_filterpy": {
            "name": "per-sample ESKF on filterpy.kalman.KalmanFilter "
            "(benchmarks/peers/filterpy_eskf.py)",
            "wall_s": fp_wall,
            "timing": fp_times,
            "imu_samples": fp_samples,
            "duration_s": fp_res["duration_s"],
            "imu_samples_per_s": fp_samples / fp_wall,
            "realtime_factor": fp_res["duration_s"] / fp_wall,
            "memory": memory.get("filterpy"),
        },
        "ratio": ratio,
        "ratios": {
            "ours_wall_over_gtsam_wall": ratio,
            "ours_cpu_over_gtsam_cpu": ours_times["cpu_median_s"] / gtsam_times["cpu_median_s"],
            "ours_min_wall_over_gtsam_min_wall": ours_times["min_s"] / gtsam_times["min_s"],
            "ours_samples_per_s_over_filterpy": single_sps / (fp_samples / fp_wall),
            "batch_speedup_vs_single": speedup,
        },
        "accuracy": acc,
        "targets": {
            "ours_below_gtsam": {"target": "ours_wall_s < gtsam_wall_s", "met": ratio < 1.0},
            "batch_speedup": {
                "target": f"aggregate samples/s at B={args.batch} >= 10x single",
                "value": speedup,
                "met": speedup >= 10.0,
            },
        },
        "target_met": bool(ratio < 1.0 and speedup >= 10.0),
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
