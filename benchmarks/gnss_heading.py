"""Dual-antenna GNSS heading through a GNSS outage: our ESKF and smoother vs GTSAM's ISAM2,
on simulated runs.

What it measures
    N simulated wheeled runs (``msf_torch.sim.simulate_run``, seeds ``seed0 .. seed0+N-1``,
    default 10 runs of 90 s): IMU at 200 Hz (ADIS16470 noise), GNSS fixes at 1 Hz (sigma
    0.5 / 0.5 / 1.0 m east / north / up), zero antenna lever arm, and dual-antenna
    (moving-baseline) headings at the fix times (``SimConfig(gnss_heading=True)``: the
    azimuth of the body's x axis clockwise from north, sigma 0.005 rad). One GNSS outage
    of ``--outage-s`` (default 20 s) starts at random after ``--outage-after-s`` (default
    40 s); the simulator emits neither fixes nor headings inside it. Each run is simulated
    twice, with and without headings, and the two must carry identical IMU samples, fixes,
    truth and labels (the heading noise has its own random stream; checked, else the run
    stops): the columns without headings get the second one.

    GNSS velocities are off by default (``--velocity`` gives them to every column): on
    this simulator the antenna's velocity (zero lever arm, no side slip) gives the course,
    so with it the yaw is pinned whenever the vehicle moves and the heading's own share
    hardly shows; ``benchmarks/gnss_velocity.py`` measures the velocities.

    Every estimator gets IMU + GNSS, with and without the headings:

    * ours: ``run_eskf`` with ``load_sequence_config(seq.meta)`` (the simulator's IMU noise
      and GNSS sigmas; each heading with its own sigma; ``gnss_heading_baseline_m`` set to
      the simulator's), under ``torch.no_grad()``, without wheels. With no wheels the
      config's ``nhc: auto`` turns the non-holonomic constraint on (zero lateral and
      vertical body velocity: a course, like a velocity's), which the peer does not have,
      so two extra columns show ours with ``nhc: off`` (the peer's information). The
      ``ours`` and ``ours_no_heading`` front ends are also smoothed afterwards
      (``msf_torch.backend.window.smooth``, mode ``full``, default settings: headings in
      when the sequence has them; ``smoothed`` under those columns);
    * peer: ``benchmarks/peers/gtsam_kitti.py`` ``run_gtsam_kitti`` (CombinedImuFactor +
      GPSFactor under ISAM2, one state per 1-Hz GNSS time, the outage's included with no
      fix) with the headings as a ``gtsam.CustomFactor`` on each pose with one (the same
      wrapped azimuth residual of the same baseline, Gaussian, the heading's sigma), set up
      as in ``benchmarks/gnss_velocity.py`` (same IMU noise, gravity, GNSS sigmas, initial
      bias sigmas, 20-s warm-up before its first ISAM2 update, so its first 20 s are a
      small batch solution that sees up to 20 s ahead). Its initial rotation value is level
      with the yaw of the first heading (without headings: of the first GNSS displacement,
      or of the first velocity with ``--velocity``); its rotation prior has zero precision.
      Its causal estimate (newest state right after each update) is the main peer figure;
      its final ISAM2 estimate (``smoothed``) is compared with our full smoother.

    Scoring, the same for all, at the 1-Hz GNSS grid times (ours interpolated there:
    positions linearly, yaw linearly after unwrapping; the peer's states are at those
    times): position ``rmse_m``, ``rmse_after_warmup_m`` (after the peer's warm-up),
    ``outage_max_error_m`` and ``outage_rmse_m`` (as ``benchmarks/gnss_velocity.py``),
    and yaw error against the simulator's truth (yaw = ``atan2(R[1, 0], R[0, 0])``, the
    body x axis's direction counter-clockwise from east; error wrapped to (-180, 180]
    deg): ``yaw_rmse_deg`` over the run, ``yaw_rmse_after_warmup_deg`` and
    ``outage_yaw_max_deg``. Medians over the runs; wall time of each call (median over
    runs), ratios ours / peer. No target: no issue sets one. Without headings (and
    velocities) both initial yaws come from a GNSS track at walking speed (about 1.5 m/s,
    0.5-m fixes) and can be tens of degrees off; on some runs neither estimator recovers
    within the run (the per-run lines show it), so those columns' medians say little more
    than that.

How to run
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gnss_heading.py           # ~30 s
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gnss_heading.py --seeds 2 \\
        --duration-s 45 --outage-after-s 22 --outage-s 10                  # smoke run

    Per-run lines go to stderr; the last line on stdout is one JSON object.

Options
    --seeds N           number of simulated runs (default 10)
    --seed0 S           first seed (default 100)
    --duration-s T      run length, s (default 90)
    --outage-s D        outage length, s (default 20)
    --outage-after-s A  earliest outage start, s (default 40; must leave the peer's 20-s
                        warm-up first)
    --velocity          GNSS velocities too, for every column (default off)
    --repeats N         timed repeats of every call (median; default 1)
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks._common import emit_json, time_repeats  # noqa: E402
from benchmarks.gnss_velocity import (  # noqa: E402
    METRICS,
    NO_NHC,
    PEER_WARMUP_INTERVALS,
    medians,
    outage_inputs,
    outage_parser,
    outage_runs,
    peer_inputs,
    score,
)
from benchmarks.peers.gtsam_kitti import run_gtsam_kitti  # noqa: E402
from msf_torch.backend.window import SmootherConfig, smooth  # noqa: E402
from msf_torch.eval.outage import interpolate_positions  # noqa: E402
from msf_torch.frontend.config import load_sequence_config  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.geometry.quaternion import quat_to_matrix  # noqa: E402
from msf_torch.sim import SimConfig, SimulatedRun, simulate_run  # noqa: E402
from msf_torch.types import Sequence, Trajectory  # noqa: E402

OURS: dict[str, dict[str, Any]] = {
    "ours": {"heading": True, "config": {}},
    "ours_no_heading": {"heading": False, "config": {}},
    "ours_no_nhc": {"heading": True, "config": NO_NHC},
    "ours_no_nhc_no_heading": {"heading": False, "config": NO_NHC},
}
"""Our columns: dual-antenna headings used, config overrides."""

SMOOTHED = ("ours", "ours_no_heading")
"""Our columns also smoothed afterwards (full batch, ``msf run --smooth full``)."""

PEERS: dict[str, bool] = {"peer": True, "peer_no_heading": False}
"""Peer columns: dual-antenna headings used."""

YAW_METRICS = ("yaw_rmse_deg", "yaw_rmse_after_warmup_deg", "outage_yaw_max_deg")
ALL_METRICS = (*METRICS, *YAW_METRICS)


def yaw_of(rotation: np.ndarray) -> np.ndarray:
    """Yaw (..., ) rad of body -> world rotations (..., 3, 3): the ZYX Euler yaw
    ``atan2(R[1, 0], R[0, 0])``, counter-clockwise from east."""
    return np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0])


def yaw_at(estimate: Trajectory, times: np.ndarray) -> np.ndarray:
    """Yaw (M,) rad of a B = 1 trajectory at ``times`` (M,) s: linear between its samples
    after unwrapping (the first / last value outside its span)."""
    keep = estimate.mask[0]
    yaw = np.unwrap(yaw_of(quat_to_matrix(estimate.quaternion[0, keep]).numpy()))
    return np.interp(times, estimate.t[0, keep].numpy(), yaw)


def truth_yaw(run: SimulatedRun, times: np.ndarray) -> np.ndarray:
    """The simulator's true yaw (M,) rad at ``times`` (M,) s, which must be IMU sample
    times (the GNSS grid is)."""
    t = run.truth.t[0].numpy()
    index = np.clip(np.searchsorted(t, times - 1e-9), 0, len(t) - 1)
    if not np.allclose(t[index], times, rtol=0.0, atol=1e-9):
        raise ValueError("the scoring times are not IMU sample times of the simulated truth")
    return yaw_of(run.truth.rotation[0, index].numpy())


def yaw_score(
    yaw: np.ndarray, truth: np.ndarray, grid: np.ndarray, outage: tuple[float, float]
) -> dict[str, float]:
    """Yaw errors, deg, of yaws (M,) rad at the grid times (M,) s against the truth (M,)."""
    err = np.degrees(np.angle(np.exp(1j * (yaw - truth))))
    inside = (grid >= outage[0]) & (grid <= outage[1])
    after = grid > grid[PEER_WARMUP_INTERVALS]
    return {
        "yaw_rmse_deg": float(np.sqrt(np.mean(err**2))),
        "yaw_rmse_after_warmup_deg": float(np.sqrt(np.mean(err[after] ** 2))),
        "outage_yaw_max_deg": float(np.abs(err[inside]).max()),
    }


def check_same_run(with_heading: Sequence, without: Sequence) -> None:
    """Raise ``RuntimeError`` unless two simulations of one seed, with and without
    headings, carry identical IMU, wheel, GNSS (fixes and velocities), truth and labels."""
    for name in ("imu", "wheel", "gnss", "gnss_velocity", "ground_truth"):
        a, b = getattr(with_heading, name), getattr(without, name)
        if (a is None) != (b is None):
            raise RuntimeError(f"stream {name} present in only one of the two simulations")
        if a is None:
            continue
        for field in dataclasses.fields(a):
            if not torch.equal(getattr(a, field.name), getattr(b, field.name)):
                raise RuntimeError(f"{name}.{field.name} differs with headings on and off")
    labels, other = with_heading.labels, without.labels
    if labels.keys() != other.keys() or not all(
        labels[k].shape == other[k].shape
        and torch.allclose(labels[k], other[k], rtol=0.0, atol=0.0, equal_nan=True)
        for k in labels
    ):
        raise RuntimeError("labels differ with headings on and off")
    if with_heading.gnss_heading is None or without.gnss_heading is not None:
        raise RuntimeError("the heading stream is not where it belongs")


def run_seed(seed: int, sim_cfg: SimConfig, repeats: int) -> dict[str, Any]:
    """All columns on one simulated run: ``{column: metrics + wall_s}`` plus the outage."""
    run = simulate_run(sim_cfg, seed=seed)
    seq = run.sequence
    seq_off = simulate_run(dataclasses.replace(sim_cfg, gnss_heading=False), seed=seed).sequence
    check_same_run(seq, seq_off)
    labels = seq.labels["gnss_outage"][0]
    if labels.shape[0] != 1:
        raise RuntimeError(f"seed {seed}: {labels.shape[0]} outages, expected 1")
    outage = (float(labels[0, 0]), float(labels[0, 1]))
    arrays = {True: peer_inputs(seq, outage), False: peer_inputs(seq_off, outage)}
    grid = arrays[True]["gps_t"]
    grid_t = torch.as_tensor(grid)
    truth = interpolate_positions(seq.ground_truth, grid_t)
    yaw_true = truth_yaw(run, grid)
    baseline = list(sim_cfg.gnss_heading_baseline_m)

    def scored(estimate: Trajectory) -> dict[str, float]:
        position = interpolate_positions(estimate, grid_t)
        return {
            **score(position, truth, grid, outage),
            **yaw_score(yaw_at(estimate, grid), yaw_true, grid, outage),
        }

    row: dict[str, Any] = {"seed": seed, "outage_s": list(outage)}
    for name, spec in OURS.items():
        variant = seq if spec["heading"] else seq_off
        variant = dataclasses.replace(variant, wheel=None)
        cfg = load_sequence_config(seq.meta, gnss_heading_baseline_m=baseline, **spec["config"])

        def ours(variant: Sequence = variant, cfg: Any = cfg) -> Any:
            with torch.no_grad():
                return run_eskf(variant, cfg)

        wall, _, result = time_repeats(ours, repeats)
        row[name] = {**scored(result.trajectory()), "wall_s": wall}
        if name in SMOOTHED:  # our full smoother over that front end (beside the peer's)

            def smoothed(variant: Sequence = variant, cfg: Any = cfg, result: Any = result) -> Any:
                with torch.no_grad():
                    return smooth(variant, result, cfg, SmootherConfig(covariance=False), "full")

            wall_s, _, out = time_repeats(smoothed, repeats)
            row[name]["smoothed"] = {**scored(out.output), "wall_s": wall_s}
    for name, use_heading in PEERS.items():

        def peer(kwargs: dict[str, Any] = arrays[use_heading]) -> dict[str, Any]:
            return run_gtsam_kitti(
                **kwargs,
                first_gps_index=0,
                warmup_intervals=PEER_WARMUP_INTERVALS,
                init_from_gps=True,
            )

        wall, _, res = time_repeats(peer, repeats)
        if not np.array_equal(res["t"], grid):
            raise RuntimeError(f"seed {seed}: the peer's states are not at the GNSS grid")
        if use_heading and not res["heading_used"].any():
            raise RuntimeError(f"seed {seed}: the peer used no heading")
        figures = {}
        for key in ("filter", "smoothed"):
            position = torch.as_tensor(res[f"{key}_position"])
            yaw = yaw_of(res[f"{key}_rotation"])
            figures[key] = {
                **score(position, truth, grid, outage),
                **yaw_score(yaw, yaw_true, grid, outage),
            }
        row[name] = {**figures["filter"], "wall_s": wall, "smoothed": figures["smoothed"]}
    return row


def main(argv: list[str] | None = None) -> int:
    parser = outage_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--velocity", action="store_true", help="GNSS velocities too")
    args = parser.parse_args(argv)
    sim_cfg, rows, machine = outage_runs(
        parser,
        args,
        {"gnss_heading": True, "gnss_velocity": args.velocity},
        run_seed,
        lambda m: f"yaw {m['yaw_rmse_deg']:.3f} deg max {m['outage_max_error_m']:.2f} m",
    )

    columns = {name: medians(rows, name, ALL_METRICS) for name in (*OURS, *PEERS)}
    om, pm = columns["ours"], columns["peer"]
    on, pn = columns["ours_no_heading"], columns["peer_no_heading"]
    record = {
        "benchmark": "gnss_heading",
        "inputs": {
            **outage_inputs(args, sim_cfg, rows),
            "gnss_heading_sigma_rad": sim_cfg.gnss_heading_sigma_rad,
            "gnss_heading_baseline_m": list(sim_cfg.gnss_heading_baseline_m),
            "gnss_velocity": args.velocity,
            "ours_columns": OURS,
            "peer": "GTSAM CombinedImuFactor + GPSFactor + CustomFactor headings, ISAM2 "
            "(benchmarks/peers/gtsam_kitti.py)",
        },
        "ours": om,
        "peer": pm,
        "columns": columns,
        "ratio": {
            "yaw_rmse_ours_over_peer": om["yaw_rmse_deg"] / pm["yaw_rmse_deg"],
            "yaw_rmse_after_warmup_ours_over_peer": om["yaw_rmse_after_warmup_deg"]
            / pm["yaw_rmse_after_warmup_deg"],
            "yaw_rmse_ours_no_nhc_over_peer": columns["ours_no_nhc"]["yaw_rmse_deg"]
            / pm["yaw_rmse_deg"],
            "outage_max_ours_over_peer": om["outage_max_error_m"] / pm["outage_max_error_m"],
            "rmse_ours_over_peer": om["rmse_m"] / pm["rmse_m"],
            "yaw_rmse_heading_over_none_ours": om["yaw_rmse_deg"] / on["yaw_rmse_deg"],
            "yaw_rmse_heading_over_none_peer": pm["yaw_rmse_deg"] / pn["yaw_rmse_deg"],
            "smoothed_yaw_rmse_ours_over_peer": om["smoothed"]["yaw_rmse_deg"]
            / pm["smoothed"]["yaw_rmse_deg"],
            "smoothed_outage_max_ours_over_peer": om["smoothed"]["outage_max_error_m"]
            / pm["smoothed"]["outage_max_error_m"],
            "smoothed_rmse_ours_over_peer": om["smoothed"]["rmse_m"] / pm["smoothed"]["rmse_m"],
            "wall_ours_over_peer": om["wall_s"] / pm["wall_s"],
            "wall_ours_smoothed_over_peer": (om["wall_s"] + om["smoothed"]["wall_s"])
            / pm["wall_s"],
        },
        "accuracy": {name: {k: columns[name][k] for k in ALL_METRICS} for name in (*OURS, *PEERS)},
        "runs": rows,
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
