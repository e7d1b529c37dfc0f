"""GNSS velocity fusion through a GNSS outage: our ESKF vs GTSAM's ISAM2, on simulated runs.

What it measures
    N simulated wheeled runs (``msf_torch.sim.simulate_run``, seeds ``seed0 .. seed0+N-1``,
    default 10 runs of 90 s): IMU at 200 Hz (ADIS16470 noise), GNSS fixes at 1 Hz (sigma
    0.5 / 0.5 / 1.0 m east / north / up) and GNSS velocities at the same times (sigma
    0.05 / 0.05 / 0.1 m/s, ``SimConfig(gnss_velocity=True)``), zero antenna lever arm. One
    GNSS outage of ``--outage-s`` (default 20 s) starts at random after ``--outage-after-s``
    (default 40 s, ``gnss_outage_margin_s``); the simulator emits neither fixes nor
    velocities inside it. Every estimator gets IMU + GNSS, with and without the velocities:

    * ours: ``run_eskf`` with ``load_sequence_config(seq.meta)`` (the simulator's IMU noise
      densities and GNSS sigmas; each velocity with its own sigma), under
      ``torch.no_grad()``, without wheels. With no wheels the config's ``nhc: auto`` turns
      the non-holonomic constraint (zero lateral / vertical body velocity) on, which the
      peer does not have, so two extra columns show ours without it (``nhc: off``, same
      information as the peer; its epochs then come every ``max_epoch_s`` = 0.5 s where
      no fix does, as the constraint's at 2 Hz) and one shows ours with the wheels
      (velocities on);
    * peer: ``benchmarks/peers/gtsam_kitti.py`` ``run_gtsam_kitti`` (CombinedImuFactor +
      GPSFactor under ISAM2, one state per 1-Hz GNSS time, the outage's times included
      with no fix), with the velocities as ``PriorFactorVector(V(i), v, sigma)`` at every
      state with a fix (exact: the lever arm is zero). It gets the same IMU noise as ours
      (continuous-time densities as GTSAM's covariances, integration sigma 0), gravity
      9.80665 m/s^2 (the simulator's), the simulator's GNSS and velocity sigmas, and
      initial bias sigmas equal to the simulator's turn-on spread (0.049 m/s^2,
      3.5e-3 rad/s; ours starts from 0.05 and 3.5e-3). What it gets differently: the
      example's initial rotation prior has zero precision and its initial value is only
      the yaw of the first velocity (without velocities: of the first GNSS displacement),
      because the peer has no accelerometer levelling and no track-based heading search as
      ours does; and it makes its first ISAM2 update after the example's 20-interval
      (20 s) warm-up, so its states in the first 20 s are a small batch solution that
      sees up to 20 s into their future (ours is causal throughout). The main peer figure
      is its causal "filter" estimate (newest state right after each update); its final
      (smoothed) ISAM2 estimate is compared with our full smoother over the same data
      (``msf_torch.backend.window.smooth``, mode ``full``, default settings, after our
      front end; ``smoothed`` under the ``ours`` and ``ours_no_velocity`` columns).

    Scoring, the same for all (``msf_torch.eval.outage.interpolate_positions`` at the
    1-Hz GNSS times, ours and the truth interpolated there): ``rmse_m`` position RMSE
    against the simulated truth over the whole run, ``rmse_after_warmup_m`` over the
    times after the peer's warm-up, ``outage_max_error_m`` and ``outage_rmse_m`` over the
    GNSS times inside the outage. Medians over the runs; wall time of each call (median
    over runs), ratio ours / peer. No target: no issue sets one.

How to run
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gnss_velocity.py           # ~1 min
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gnss_velocity.py --seeds 2 \\
        --duration-s 45 --outage-after-s 22 --outage-s 10                   # smoke run

    Per-run lines go to stderr; the last line on stdout is one JSON object.

Options
    --seeds N           number of simulated runs (default 10)
    --seed0 S           first seed (default 100)
    --duration-s T      run length, s (default 90)
    --outage-s D        outage length, s (default 20)
    --outage-after-s A  earliest outage start, s (default 40; must leave the peer's 20-s
                        warm-up first)
    --repeats N         timed repeats of every call (median; default 1)
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info, time_repeats  # noqa: E402
from benchmarks.peers.gtsam_kitti import run_gtsam_kitti  # noqa: E402
from msf_torch.backend.window import SmootherConfig, smooth  # noqa: E402
from msf_torch.eval.outage import interpolate_positions  # noqa: E402
from msf_torch.frontend.config import load_sequence_config  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.geometry.conventions import STANDARD_GRAVITY  # noqa: E402
from msf_torch.sim import SimConfig, simulate_run  # noqa: E402
from msf_torch.types import Sequence  # noqa: E402

PEER_WARMUP_INTERVALS = 20
"""GNSS intervals before the peer's first ISAM2 update (the GTSAM example's)."""

NO_NHC: dict[str, Any] = {"nhc": "off"}
"""Config overrides for ours without the non-holonomic constraint (the peer has none)."""

OURS: dict[str, dict[str, Any]] = {
    "ours": {"velocity": True, "wheels": False, "config": {}},
    "ours_no_velocity": {"velocity": False, "wheels": False, "config": {}},
    "ours_no_nhc": {"velocity": True, "wheels": False, "config": NO_NHC},
    "ours_no_nhc_no_velocity": {"velocity": False, "wheels": False, "config": NO_NHC},
    "ours_wheels": {"velocity": True, "wheels": True, "config": {}},
}
"""Our columns: GNSS velocities used, wheels used, config overrides."""

SMOOTHED = ("ours", "ours_no_velocity")
"""Our columns also smoothed afterwards (full batch, ``msf run --smooth full``)."""

PEERS: dict[str, bool] = {"peer": True, "peer_no_velocity": False}
"""Peer columns: GNSS velocities used."""

METRICS = ("rmse_m", "rmse_after_warmup_m", "outage_max_error_m", "outage_rmse_m")


def peer_inputs(seq: Sequence, outage: tuple[float, float]) -> dict[str, Any]:
    """Keyword inputs of ``run_gtsam_kitti`` from a simulated B = 1 Sequence.

    The state times are the simulator's whole 1-Hz GNSS grid (``k / gnss_rate_hz``); the
    times inside the outage get NaN fixes, velocities and headings (unused by the peer: no
    truth can leak in), and they must be exactly the missing ones.

    Returns:
        dict with ``imu_t`` (N,), ``imu_acc`` / ``imu_gyro`` (N, 3), ``gps_t`` (M,),
        ``gps_xyz`` (M, 3) m, ``gps_velocity`` (M, 3) m/s and ``gps_velocity_sigma``
        (M, 3) (both None when the sequence has no velocities), ``gps_sigma`` (3,) m,
        ``meta`` (GTSAM noise keys from ``meta["sensor"]["imu_noise"]``), ``gravity`` and
        ``init_bias_sigmas``; when the sequence has dual-antenna headings also
        ``gps_heading`` (M,) rad, ``gps_heading_sigma`` (M,) rad and ``heading_baseline``
        (3,) (the simulator's ``gnss_heading_baseline_m``).
    """
    sim = seq.meta["sim"]
    sensor = seq.meta["sensor"]
    if any(float(x) != 0.0 for x in sensor["gnss_lever_arm_m"]):
        raise ValueError("the peer's velocity prior needs a zero GNSS lever arm")
    noise = sensor["imu_noise"]
    rate = float(sim["gnss_rate_hz"])
    n_grid = int(np.floor(float(sim["duration_s"]) * rate + 1e-9)) + 1
    grid = np.arange(n_grid) / rate
    fix_t = seq.gnss.t[0, seq.gnss.mask[0]].numpy()
    index = np.rint(fix_t * rate).astype(int)
    if not np.allclose(grid[index], fix_t, rtol=0.0, atol=1e-9):
        raise ValueError("GNSS fixes off the simulator's 1/gnss_rate_hz grid")
    missing = np.setdiff1d(np.arange(n_grid), index)
    inside = np.nonzero((grid >= outage[0]) & (grid <= outage[1]))[0]
    if not np.array_equal(missing, inside):
        raise ValueError("the missing GNSS times are not the outage's")
    xyz = np.full((n_grid, 3), np.nan)
    xyz[index] = seq.gnss.position[0, seq.gnss.mask[0]].numpy()
    vel = vel_sigma = None
    gv = seq.gnss_velocity
    if gv is not None:
        vel = np.full((n_grid, 3), np.nan)
        vel_sigma = np.full((n_grid, 3), np.nan)
        vel_index = np.rint(gv.t[0, gv.mask[0]].numpy() * rate).astype(int)
        vel[vel_index] = gv.velocity[0, gv.mask[0]].numpy()
        vel_sigma[vel_index] = gv.sigma[0, gv.mask[0]].numpy()
    heading: dict[str, Any] = {}
    gh = seq.gnss_heading
    if gh is not None:
        head_t = gh.t[0, gh.mask[0]].numpy()
        head_index = np.rint(head_t * rate).astype(int)
        if not np.allclose(grid[head_index], head_t, rtol=0.0, atol=1e-9):
            raise ValueError("GNSS headings off the simulator's 1/gnss_rate_hz grid")
        heading["gps_heading"] = np.full(n_grid, np.nan)
        heading["gps_heading_sigma"] = np.full(n_grid, np.nan)
        heading["gps_heading"][head_index] = gh.heading[0, gh.mask[0]].numpy()
        heading["gps_heading_sigma"][head_index] = gh.sigma[0, gh.mask[0]].numpy()
        heading["heading_baseline"] = np.asarray(sim["gnss_heading_baseline_m"], dtype=float)
    imu_m = seq.imu.mask[0]
    return {
        "imu_t": seq.imu.t[0, imu_m].numpy(),
        "imu_acc": seq.imu.accel[0, imu_m].numpy(),
        "imu_gyro": seq.imu.gyro[0, imu_m].numpy(),
        "gps_t": grid,
        "gps_xyz": xyz,
        "gps_velocity": vel,
        "gps_velocity_sigma": vel_sigma,
        "gps_sigma": np.asarray(sensor["gnss_sigma_m"], dtype=float),
        "meta": {
            "accel_noise_sigma": noise["accel_noise_density"],
            "gyro_noise_sigma": noise["gyro_noise_density"],
            "integration_sigma": 0.0,
            "accel_bias_rw_sigma": noise["accel_bias_rw_density"],
            "gyro_bias_rw_sigma": noise["gyro_bias_rw_density"],
            "body_p_sensor": [0.0] * 6,
            "average_delta_t": 1.0 / float(sim["imu_rate_hz"]),
        },
        "gravity": STANDARD_GRAVITY,
        "init_bias_sigmas": (noise["accel_bias_sigma0"], noise["gyro_bias_sigma0"]),
        **heading,
    }


def score(
    position: torch.Tensor, truth: torch.Tensor, grid: np.ndarray, outage: tuple[float, float]
) -> dict[str, float]:
    """Errors of positions (M, 3) m at the GNSS grid times (M,) s against the truth (M, 3)."""
    err = (position - truth).norm(dim=-1).numpy()
    inside = (grid >= outage[0]) & (grid <= outage[1])
    after = grid > grid[PEER_WARMUP_INTERVALS]

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(e**2)))

    return {
        "rmse_m": rms(err),
        "rmse_after_warmup_m": rms(err[after]),
        "outage_max_error_m": float(err[inside].max()),
        "outage_rmse_m": rms(err[inside]),
    }


def run_seed(seed: int, sim_cfg: SimConfig, repeats: int) -> dict[str, Any]:
    """All columns on one simulated run: ``{column: metrics + wall_s}`` plus the outage."""
    run = simulate_run(sim_cfg, seed=seed)
    seq = run.sequence
    labels = seq.labels["gnss_outage"][0]
    if labels.shape[0] != 1:
        raise RuntimeError(f"seed {seed}: {labels.shape[0]} outages, expected 1")
    outage = (float(labels[0, 0]), float(labels[0, 1]))
    arrays = peer_inputs(seq, outage)
    grid = arrays["gps_t"]
    grid_t = torch.as_tensor(grid)
    truth = interpolate_positions(seq.ground_truth, grid_t)
    row: dict[str, Any] = {"seed": seed, "outage_s": list(outage)}
    for name, spec in OURS.items():
        variant = dataclasses.replace(
            seq,
            gnss_velocity=seq.gnss_velocity if spec["velocity"] else None,
            wheel=seq.wheel if spec["wheels"] else None,
        )
        cfg = load_sequence_config(seq.meta, **spec["config"])

        def ours(variant: Sequence = variant, cfg: Any = cfg) -> Any:
            with torch.no_grad():
                return run_eskf(variant, cfg)

        wall, _, result = time_repeats(ours, repeats)
        position = interpolate_positions(result.trajectory(), grid_t)
        row[name] = {**score(position, truth, grid, outage), "wall_s": wall}
        if name in SMOOTHED:  # our full smoother over that front end (beside the peer's)

            def smoothed(variant: Sequence = variant, cfg: Any = cfg, result: Any = result) -> Any:
                with torch.no_grad():
                    return smooth(variant, result, cfg, SmootherConfig(covariance=False), "full")

            wall_s, _, out = time_repeats(smoothed, repeats)
            position = interpolate_positions(out.output, grid_t)
            row[name]["smoothed"] = {**score(position, truth, grid, outage), "wall_s": wall_s}
    for name, use_velocity in PEERS.items():
        kwargs = dict(arrays)
        if not use_velocity:
            kwargs["gps_velocity"] = kwargs["gps_velocity_sigma"] = None

        def peer(kwargs: dict[str, Any] = kwargs) -> dict[str, Any]:
            return run_gtsam_kitti(
                **kwargs,
                first_gps_index=0,
                warmup_intervals=PEER_WARMUP_INTERVALS,
                init_from_gps=True,
            )

        wall, _, res = time_repeats(peer, repeats)
        if not np.array_equal(res["t"], grid):
            raise RuntimeError(f"seed {seed}: the peer's states are not at the GNSS grid")
        filt = torch.as_tensor(res["filter_position"])
        smoothed = torch.as_tensor(res["smoothed_position"])
        row[name] = {
            **score(filt, truth, grid, outage),
            "wall_s": wall,
            "smoothed": score(smoothed, truth, grid, outage),
        }
    return row


def medians(
    rows: list[dict[str, Any]], column: str, metrics: tuple[str, ...] = METRICS
) -> dict[str, float]:
    """Median over runs of each of ``metrics`` (and wall time) of one column."""
    out = {k: statistics.median(r[column][k] for r in rows) for k in (*metrics, "wall_s")}
    if "smoothed" in rows[0][column]:
        keys = [k for k in (*metrics, "wall_s") if k in rows[0][column]["smoothed"]]
        out["smoothed"] = {
            k: statistics.median(r[column]["smoothed"][k] for r in rows) for k in keys
        }
    return out


def outage_parser(description: str) -> argparse.ArgumentParser:
    """The options of the simulated-outage benchmarks (this one, ``gnss_heading.py``):
    seeds, run length, outage length and earliest start, timed repeats."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--seeds", type=int, default=10, help="number of simulated runs")
    parser.add_argument("--seed0", type=int, default=100, help="first seed")
    parser.add_argument("--duration-s", type=float, default=90.0, help="run length, s")
    parser.add_argument("--outage-s", type=float, default=20.0, help="outage length, s")
    parser.add_argument("--outage-after-s", type=float, default=40.0, help="earliest start")
    parser.add_argument("--repeats", type=int, default=1, help="timed repeats of each call")
    return parser


def outage_runs(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    streams: dict[str, bool],
    run_one: Callable[[int, SimConfig, int], dict[str, Any]],
    line: Callable[[dict[str, Any]], str],
) -> tuple[SimConfig, list[dict[str, Any]], dict[str, Any]]:
    """Check the options, simulate and score every seed (``run_one(seed, sim_cfg,
    repeats)``, one stderr line each: ``line(metrics)`` per column), and return the
    simulator's config, the rows and the machine (read before the runs' own load)."""
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    sim_cfg = SimConfig(
        duration_s=args.duration_s,
        gnss_outage_count=1,
        gnss_outage_duration_s=(args.outage_s, args.outage_s),
        gnss_outage_margin_s=args.outage_after_s,
        **streams,
    )
    if args.outage_after_s <= PEER_WARMUP_INTERVALS / sim_cfg.gnss_rate_hz:
        parser.error("--outage-after-s must leave the peer's warm-up (20 GNSS intervals) first")
    machine = machine_info()  # before our own load shows in the load average
    rows = []
    for seed in range(args.seed0, args.seed0 + args.seeds):
        row = run_one(seed, sim_cfg, args.repeats)
        rows.append(row)
        columns = [name for name in row if name not in ("seed", "outage_s")]
        log(
            f"seed {seed} outage {row['outage_s'][0]:.1f}-{row['outage_s'][1]:.1f} s | "
            + " | ".join(
                f"{name} {line(row[name])} ({row[name]['wall_s']:.2f} s)" for name in columns
            )
        )
    return sim_cfg, rows, machine


def outage_inputs(
    args: argparse.Namespace, sim_cfg: SimConfig, rows: list[dict[str, Any]]
) -> dict[str, Any]:
    """The JSON line's ``inputs`` shared by the simulated-outage benchmarks."""
    return {
        "simulator": "msf_torch.sim.simulate_run (wheeled, ADIS16470 IMU at 200 Hz)",
        "seeds": [r["seed"] for r in rows],
        "duration_s": args.duration_s,
        "gnss_rate_hz": sim_cfg.gnss_rate_hz,
        "gnss_sigma_m": [sim_cfg.gnss_sigma_horizontal_m] * 2 + [sim_cfg.gnss_sigma_vertical_m],
        "outage_s": args.outage_s,
        "outage_after_s": args.outage_after_s,
        "outages": [r["outage_s"] for r in rows],
        "ours_config": "load_sequence_config(seq.meta) (defaults + the simulator's noise)",
        "peer_warmup_intervals": PEER_WARMUP_INTERVALS,
        "repeats": args.repeats,
        "statistic": "median over runs",
    }


def main(argv: list[str] | None = None) -> int:
    parser = outage_parser(__doc__.split("\n\n")[0])
    args = parser.parse_args(argv)
    sim_cfg, rows, machine = outage_runs(
        parser,
        args,
        {"gnss_velocity": True},
        run_seed,
        lambda m: f"max {m['outage_max_error_m']:.2f} m rmse {m['rmse_m']:.2f} m",
    )
    columns = {name: medians(rows, name) for name in (*OURS, *PEERS)}
    om, pm = columns["ours"], columns["peer"]
    on, pn = columns["ours_no_velocity"], columns["peer_no_velocity"]
    record = {
        "benchmark": "gnss_velocity",
        "inputs": {
            **outage_inputs(args, sim_cfg, rows),
            "gnss_velocity_sigma_mps": list(sim_cfg.gnss_velocity_sigma_mps),
            "ours_columns": OURS,
            "peer": "GTSAM CombinedImuFactor + GPSFactor (+ PriorFactorVector velocities), "
            "ISAM2 (benchmarks/peers/gtsam_kitti.py)",
        },
        "ours": om,
        "peer": pm,
        "columns": columns,
        "ratio": {
            "outage_max_ours_over_peer": om["outage_max_error_m"] / pm["outage_max_error_m"],
            "rmse_ours_over_peer": om["rmse_m"] / pm["rmse_m"],
            "outage_max_ours_no_nhc_over_peer": columns["ours_no_nhc"]["outage_max_error_m"]
            / pm["outage_max_error_m"],
            "wall_ours_over_peer": om["wall_s"] / pm["wall_s"],
            "outage_max_velocity_over_none_ours": om["outage_max_error_m"]
            / on["outage_max_error_m"],
            "outage_max_velocity_over_none_peer": pm["outage_max_error_m"]
            / pn["outage_max_error_m"],
            "smoothed_outage_max_ours_over_peer": om["smoothed"]["outage_max_error_m"]
            / pm["smoothed"]["outage_max_error_m"],
            "smoothed_rmse_ours_over_peer": om["smoothed"]["rmse_m"] / pm["smoothed"]["rmse_m"],
        },
        "accuracy": {name: {k: columns[name][k] for k in METRICS} for name in (*OURS, *PEERS)},
        "runs": rows,
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
