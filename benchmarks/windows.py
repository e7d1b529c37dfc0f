"""256 KITTI windows: our batched LM (one call, B = 256) vs GTSAM's LM (one window at a time)
and Theseus's batched LM.

What it measures
    The KITTI IMU + GPS drive that the ``gtsam`` wheel ships (GPS fixes at 1 Hz, 100 IMU
    samples between consecutive fixes). Keyframes sit at the GPS fixes from fix 1 on (fix 0
    is followed by a 1.9 s IMU gap; GTSAM's example skips it too). A window is 10
    consecutive keyframes; 256 windows start at evenly spaced fixes over the drive
    (overlapping). Each window is one nonlinear least-squares problem:

    * IMU between consecutive keyframes: ``gtsam.ImuFactor`` (Logmap error, TANGENT
      preintegration at zero bias, ``MakeSharedU(9.8)``, the metadata's accelerometer /
      gyroscope / integration sigmas) + ``BetweenFactorConstantBias`` with sigmas
      ``sigma_bw sqrt(dT)``. Ours: ``preintegrate_imu_tangent`` + ``GtsamImuFactor``,
      the option that poses GTSAM's exact problem (error, noise, bias correction);
    * GNSS at every keyframe: ``GPSFactor`` (no lever arm), information ``1 / 0.07`` per
      axis, as GTSAM's KITTI example; ours ``GnssFactor``;
    * priors on the first keyframe: position, rotation (``PoseTranslationPrior3D`` +
      ``PoseRotationPrior3D``), velocity and bias, centred on the initial values; ours one
      ``NavStatePriorFactor`` with the same diagonal covariance (the same squared error).

    Initial values (the same for both) are our ESKF's estimates at the keyframe times
    (``run_eskf`` with ``configs/kitti-gtsam.yaml``). The costs of the two problems are
    compared at the initial values (``initial_cost_rel_diff``: identical problems) and after
    the solves (``final_cost_rel_diff`` per window, max and median; target 1e-6).

    * ours: ``msf_torch.backend.lm.solve`` on one Problem with B = 256 (``nav_state``
      variables, 10 per problem). The windows are keyframe chains, so the solver takes its
      chain path: normal equations assembled straight into (B, 10, 15, 15) diagonal and
      (B, 9, 15, 15) sub-diagonal blocks, batched block Cholesky, windows that have
      converged dropped from the batch (``--path general``: the dense (B, 150, 150)
      assembly with every window carried to the end, for comparison);
    * peer: ``gtsam.LevenbergMarquardtOptimizer`` on each window's graph in turn (Pose3,
      velocity and bias keys), timed over the 256 ``optimize`` calls (optimizer
      construction included);
    * second peer, Theseus (when ``import theseus`` works; ``--no-theseus`` skips it): the
      same Problem as one ``th.Objective`` with batch 256
      (``benchmarks/peers/theseus_windows.py``: per keyframe a ``th.SE3`` pose and a
      ``th.Vector(9)`` ``[v, b_g, b_a]``; one ``th.AutoDiffCostFunction`` per factor whose
      error is our factor's whitened residual, so the cost is identical), solved by
      ``th.LevenbergMarquardt`` (``CholeskyDenseSolver``, adaptive ``lambda I`` damping
      from our initial damping, cost functions vectorised) through ``th.TheseusLayer``
      under ``torch.no_grad``, timed like ours. Its final cost is our ``Problem.cost`` at
      its final values (``theseus.final_cost_rel_diff`` vs GTSAM's). Theseus stops a
      window at a relative cost change below ``--rtol``, and a rejected step (cost
      unchanged) counts as such a change. It is not in the ``[peers]`` extra (its declared
      dependency scikit-sparse has no wheel and needs SuiteSparse headers; the dense
      solver does not use it); install it with::

          .venv/bin/pip install --no-build-isolation --no-deps theseus-ai==0.2.3 \\
              torchlie==0.1.0 torchkin==0.1.1 urdf_parser_py==0.0.4 semantic-version==2.10.0

      Without it a note goes to stderr and the JSON's ``theseus`` block is
      ``{"skipped": "theseus-ai not installed: <that command>"}``.

    All stop at a relative cost decrease below ``--rtol`` (default 1e-12) or after 100
    iterations; ours damps with ``lambda I`` like GTSAM's default (``--damping``). Only the
    solves are timed (medians over ``--repeats``, ours, GTSAM and Theseus alternating);
    problem construction (preintegration, factors, graphs, objective) is reported apart.
    * third peer, PyPose (when ``import pypose`` works; ``--pypose-windows 0`` skips it):
      ``pypose.optim.LM`` on one window at a time (``benchmarks/peers/pypose_windows.py``:
      an ``nn.Module`` of a ``pp.SE3`` pose parameter and a (K, 9) ``[v, b_g, b_a]``
      parameter whose forward returns our factors' whitened residuals, so the cost is
      identical; dense autodiff Jacobian, its Cholesky solver and default damping), the same
      stopping rule as GTSAM's. PyPose has no batch-of-problems LM, so it solves the windows
      one by one, once (no repeats: about 0.6 s per window, 2.6 min for all 256), after the
      timed solves; ``--pypose-windows N`` takes N of them, evenly spaced. Its throughput is
      those windows over their summed wall time (module and optimizer construction
      included, as for GTSAM); its final costs are compared with GTSAM's and ours.

    Throughput is windows per second; target: ours >= 20x GTSAM's (``ratio_vs_theseus``,
    ``ratio_vs_pypose``: ours over Theseus's and PyPose's, no target). For information the
    same windows are also solved with our default IMU factor (exact zero-order hold, Forster
    residual): ``zoh_final_cost_rel_diff`` shows how far that (different) discretisation
    moves the optimum.

How to run
    .venv/bin/python benchmarks/windows.py                 # 256 windows, 5 repeats
    .venv/bin/python benchmarks/windows.py --repeats 3 --threads 1

    Progress lines go to stderr; the last line on stdout is one JSON object.

Options
    --windows N        number of windows (default 256)
    --size K           keyframes per window (default 10)
    --repeats N        timed repeats of the solves (median; default 5)
    --rtol X           relative cost-decrease tolerance of both (default 1e-12)
    --linear-solver S  ours: "dense" (default) or "sparse"
    --damping D        ours: "identity" (default, GTSAM's lambda I) or "marquardt"
    --path P           ours: "chain" (default, see above) or "general" (dense assembly,
                       no dropping of converged windows)
    --threads N        torch intra-op threads (default: torch's choice)
    --device D         ours (and Theseus) on this device (default cpu)
    --no-theseus       skip the Theseus peer
    --pypose-windows N PyPose peer on N of the windows, evenly spaced (default: all; 0 skips;
                       needs ``pip install pypose``, in the ``[peers]`` extra)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import gtsam  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from gtsam.symbol_shorthand import B, V, X  # noqa: E402

from benchmarks._common import (  # noqa: E402
    emit_json,
    kitti_config,
    log,
    machine_info,
    time_repeats,
)
from benchmarks.peers.pypose_windows import solve_pypose_window  # noqa: E402
from benchmarks.peers.theseus_windows import (  # noqa: E402
    INSTALL,
    build_theseus,
    import_theseus,
    solve_theseus,
)
from msf_torch.backend.factors import (  # noqa: E402
    GnssFactor,
    GtsamImuFactor,
    ImuPreintegrationFactor,
    NavStatePriorFactor,
)
from msf_torch.backend.lm import LMConfig, LMResult, solve  # noqa: E402
from msf_torch.backend.preintegration import (  # noqa: E402
    ImuIntervals,
    TangentPreintegrated,
    imu_covariance,
    preintegrate_imu,
    preintegrate_imu_tangent,
)
from msf_torch.backend.problem import Factor, Problem  # noqa: E402
from msf_torch.backend.variables import pack_nav_state, unpack_nav_state  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.geometry import so3  # noqa: E402
from msf_torch.io import load_sequence  # noqa: E402
from msf_torch.sensors.imu import ImuNoise, Preintegrated  # noqa: E402
from msf_torch.types import Sequence  # noqa: E402

GRAVITY = 9.8
"""Gravity magnitude of GTSAM's KITTI example (``MakeSharedU(9.8)``), m/s^2."""
GPS_VARIANCE = 0.07
"""Per-axis GPS variance of GTSAM's KITTI example (information 1 / 0.07), m^2."""
FIRST_FIX = 1
"""First keyframe fix (fix 0 is followed by a 1.9 s IMU gap)."""
PRIOR_POSITION_SIGMA = 1.0
PRIOR_ROTATION_SIGMA = 0.1
PRIOR_VELOCITY_SIGMA = 1.0
PRIOR_ACCEL_BIAS_SIGMA = 0.1
PRIOR_GYRO_BIAS_SIGMA = 5e-5
"""First-keyframe prior sigmas: m, rad, m/s, m/s^2 and rad/s (bias: GTSAM's example)."""
MAX_ITERATIONS = 100


def gps_intervals(
    imu_t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, gps_t: np.ndarray
) -> dict[str, np.ndarray]:
    """IMU samples between consecutive GPS fixes, paired as GTSAM's KITTI example pairs them.

    Interval k (k = 1 .. M - 1) holds the samples with ``gps_t[k-1] < t_s <= gps_t[k]``,
    each with span ``dt = t_s - t_{s-1}``, padded with ``dt = 0``.

    Returns:
        ``acc``, ``gyro`` (M - 1, L, 3) m/s^2, rad/s and ``dt`` (M - 1, L) s; row k - 1 is
        interval k.
    """
    first = np.searchsorted(imu_t, gps_t[:-1], side="right")
    last = np.searchsorted(imu_t, gps_t[1:], side="right")
    if np.any(first < 1):
        raise ValueError("a GPS interval starts before the second IMU sample")
    width = int((last - first).max())
    count = gps_t.size - 1
    out = {
        "acc": np.zeros((count, width, 3)),
        "gyro": np.zeros((count, width, 3)),
        "dt": np.zeros((count, width)),
    }
    for k in range(count):
        sel = np.arange(first[k], last[k])
        out["acc"][k, : sel.size] = acc[sel]
        out["gyro"][k, : sel.size] = gyro[sel]
        out["dt"][k, : sel.size] = imu_t[sel] - imu_t[sel - 1]
    return out


def eskf_states(seq: Sequence, gps_t: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
    """Our ESKF's estimates at the GPS times: p, v (M, 3), R (M, 3, 3), b_g, b_a (M, 3)."""
    cfg, _ = kitti_config(seq)
    start = time.perf_counter()
    with torch.no_grad():
        res = run_eskf(seq, cfg)
    wall = time.perf_counter() - start
    t = res.t[0].numpy()
    idx = np.searchsorted(t, gps_t)
    if np.any(idx >= t.size) or np.abs(t[np.minimum(idx, t.size - 1)] - gps_t).max() > 1e-9:
        raise RuntimeError("the ESKF has no epoch at some GPS time")
    rot = so3.project(res.rotation[0, idx])
    states = {
        "p": res.position[0, idx].numpy(),
        "v": res.velocity[0, idx].numpy(),
        "R": rot.numpy(),
        "bg": res.gyro_bias[0, idx].numpy(),
        "ba": res.accel_bias[0, idx].numpy(),
    }
    return states, wall


def _noise(meta: dict[str, Any], device: torch.device) -> ImuNoise:
    """The metadata's IMU noise densities as tensors on ``device``."""

    def t(key: str) -> torch.Tensor:
        return torch.tensor(float(meta[key]), dtype=torch.float64, device=device)

    return ImuNoise(
        t("gyro_noise_sigma"),
        t("accel_noise_sigma"),
        t("gyro_bias_rw_sigma"),
        t("accel_bias_rw_sigma"),
    )


def _prior_covariance(device: torch.device) -> torch.Tensor:
    """(1, 1, 15, 15) diagonal covariance of the first-keyframe prior, error-state order."""
    sigmas = [PRIOR_POSITION_SIGMA] * 3 + [PRIOR_VELOCITY_SIGMA] * 3 + [PRIOR_ROTATION_SIGMA] * 3
    sigmas += [PRIOR_GYRO_BIAS_SIGMA] * 3 + [PRIOR_ACCEL_BIAS_SIGMA] * 3
    return torch.diag(torch.tensor(sigmas, dtype=torch.float64, device=device) ** 2)[None, None]


def _gather(pre: Any, index: torch.Tensor, device: torch.device) -> Any:
    """Intervals ``index`` (W, K - 1) of per-interval increments (leading dim M - 1), on
    ``device``."""
    return type(pre)(**{k: v[index].to(device) for k, v in vars(pre).items()})


def build_ours(
    states: dict[str, np.ndarray],
    gps_xyz: np.ndarray,
    starts: np.ndarray,
    size: int,
    pre: TangentPreintegrated | Preintegrated,
    noise: ImuNoise,
    device: torch.device,
) -> Problem:
    """One Problem with B = len(starts): keyframes ``start .. start + size - 1`` each.

    ``pre`` holds every GPS interval (row k - 1 = interval k); a ``TangentPreintegrated``
    gives ``GtsamImuFactor`` (GTSAM's problem), a ``Preintegrated`` our default
    ``ImuPreintegrationFactor``.
    """
    fix = torch.as_tensor(starts)[:, None] + torch.arange(size)  # (W, K) fix indices
    dtype = torch.float64

    def at(array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(array, dtype=dtype)[fix].to(device)

    values = pack_nav_state(
        at(states["p"]), at(states["v"]), at(states["R"]), at(states["bg"]), at(states["ba"])
    )
    window = _gather(pre, fix[:, 1:] - 1, device)
    cov = imu_covariance(window, noise)
    gravity = torch.tensor([0.0, 0.0, -GRAVITY], dtype=dtype, device=device)
    keyframes = torch.arange(size, device=device)
    gps_cov = GPS_VARIANCE * torch.eye(3, dtype=dtype, device=device)
    imu_type = GtsamImuFactor if isinstance(pre, TangentPreintegrated) else ImuPreintegrationFactor
    factors: list[Factor] = [
        NavStatePriorFactor("state", keyframes[:1], values[:, :1], _prior_covariance(device)),
        GnssFactor("state", keyframes, at(gps_xyz), gps_cov.expand(1, size, 3, 3)),
        imu_type("state", keyframes[:-1], keyframes[1:], window, cov, gravity),
    ]
    return Problem({"state": ("nav_state", values)}, factors)


def gtsam_pims(intervals: dict[str, np.ndarray], meta: dict[str, Any]) -> list[Any]:
    """One ``PreintegratedImuMeasurements`` per GPS interval (index k - 1 = interval k)."""
    params = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    eye = np.eye(3)
    params.setAccelerometerCovariance(eye * float(meta["accel_noise_sigma"]) ** 2)
    params.setGyroscopeCovariance(eye * float(meta["gyro_noise_sigma"]) ** 2)
    params.setIntegrationCovariance(eye * float(meta["integration_sigma"]) ** 2)
    pims = []
    for acc, gyro, dt in zip(intervals["acc"], intervals["gyro"], intervals["dt"], strict=True):
        pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
        for a, w, h in zip(acc, gyro, dt, strict=True):
            if h > 0:
                pim.integrateMeasurement(a, w, h)
        pims.append(pim)
    return pims


def build_gtsam(
    states: dict[str, np.ndarray],
    gps_xyz: np.ndarray,
    start: int,
    size: int,
    pims: list[Any],
    meta: dict[str, Any],
) -> tuple[Any, Any]:
    """Graph and initial values of the window with keyframes ``start .. start + size - 1``."""
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    diag = gtsam.noiseModel.Diagonal
    gps_noise = diag.Precisions(np.full(3, 1.0 / GPS_VARIANCE))
    for i in range(size):
        k = start + i
        pose = gtsam.Pose3(gtsam.Rot3(states["R"][k]), states["p"][k])
        bias = gtsam.imuBias.ConstantBias(states["ba"][k], states["bg"][k])
        init.insert(X(i), pose)
        init.insert(V(i), states["v"][k])
        init.insert(B(i), bias)
        graph.add(gtsam.GPSFactor(X(i), gps_xyz[k], gps_noise))
        if i == 0:
            graph.add(
                gtsam.PoseTranslationPrior3D(
                    X(0), pose, diag.Sigmas(np.full(3, PRIOR_POSITION_SIGMA))
                )
            )
            graph.add(
                gtsam.PoseRotationPrior3D(X(0), pose, diag.Sigmas(np.full(3, PRIOR_ROTATION_SIGMA)))
            )
            graph.add(
                gtsam.PriorFactorVector(
                    V(0), states["v"][k], diag.Sigmas(np.full(3, PRIOR_VELOCITY_SIGMA))
                )
            )
            sigmas = np.r_[[PRIOR_ACCEL_BIAS_SIGMA] * 3, [PRIOR_GYRO_BIAS_SIGMA] * 3]
            graph.add(gtsam.PriorFactorConstantBias(B(0), bias, diag.Sigmas(sigmas)))
            continue
        pim = pims[k - 1]
        graph.add(gtsam.ImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), pim))
        walk = (
            np.sqrt(pim.deltaTij())
            * np.r_[
                [float(meta["accel_bias_rw_sigma"])] * 3, [float(meta["gyro_bias_rw_sigma"])] * 3
            ]
        )
        graph.add(
            gtsam.BetweenFactorConstantBias(
                B(i - 1), B(i), gtsam.imuBias.ConstantBias(), diag.Sigmas(walk)
            )
        )
    return graph, init


def solve_gtsam(problems: list[tuple[Any, Any]], rtol: float) -> list[tuple[Any, int]]:
    """``LevenbergMarquardtOptimizer.optimize`` on each (graph, initial values) in turn."""
    out = []
    for graph, init in problems:
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(rtol)
        params.setAbsoluteErrorTol(0.0)
        params.setMaxIterations(MAX_ITERATIONS)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, init, params)
        out.append((optimizer.optimize(), optimizer.iterations()))
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / np.abs(b)


def _stats(x: np.ndarray) -> dict[str, float]:
    return {"max": float(np.max(x)), "median": float(np.median(x))}


def _pypose(
    problem: Problem,
    args: argparse.Namespace,
    ours_cost: np.ndarray,
    peer_cost: np.ndarray,
    throughput_ours: float,
) -> tuple[dict[str, Any], float | None]:
    """The PyPose peer on ``args.pypose_windows`` evenly spaced windows, one at a time.

    Returns:
        the record's ``pypose`` block and ours' throughput over PyPose's (None if skipped).
    """
    if args.pypose_windows is not None and args.pypose_windows <= 0:
        return {"skipped": "--pypose-windows 0"}, None
    try:
        import pypose
    except ImportError:
        log("PyPose peer skipped: pypose not installed (pip install pypose)")
        return {"skipped": "pypose not installed: pip install pypose"}, None
    count = args.windows if args.pypose_windows is None else min(args.pypose_windows, args.windows)
    chosen = np.unique(np.linspace(0, args.windows - 1, count).round().astype(int))
    runs = []
    for n, w in enumerate(chosen.tolist()):
        single = problem.select(torch.tensor([w], device=problem.device))
        with torch.no_grad():
            initial = float(single.cost(single.values))
        run = solve_pypose_window(single, args.rtol, MAX_ITERATIONS)
        run["initial_cost_ours"] = initial
        runs.append(run)
        if (n + 1) % max(1, chosen.size // 8) == 0:
            log(
                f"pypose window {n + 1}/{chosen.size} (#{w}): {run['wall_s']:.2f} s, "
                f"{run['iterations']} steps, cost {run['final_cost']:.6g}"
            )
    wall = sum(run["wall_s"] for run in runs)
    final = np.array([run["final_cost"] for run in runs])
    iterations = np.array([run["iterations"] for run in runs])
    initial_pp = np.array([run["initial_cost"] for run in runs])
    initial_ours = np.array([run["initial_cost_ours"] for run in runs])
    per_s = chosen.size / wall
    block = {
        "what": (
            f"pypose {pypose.__version__} optim.LM (solver.Cholesky, default damping "
            "strategy, dense autodiff Jacobian), one window at a time, once (no repeats)"
        ),
        "windows": int(chosen.size),
        "window_indices": chosen.tolist() if chosen.size < args.windows else "all",
        "solve_s": wall,
        "windows_per_s": per_s,
        "iterations": _stats(iterations),
        "hit_max_iterations": int((iterations >= MAX_ITERATIONS).sum()),
        "initial_cost_rel_diff_vs_ours": _stats(_rel(initial_pp, initial_ours)),
        "final_cost_rel_diff": _stats(_rel(final, peer_cost[chosen])),
        "final_cost_rel_diff_vs_ours": _stats(_rel(final, ours_cost[chosen])),
        "final_cost": _stats(final),
    }
    log(
        f"pypose {wall:.1f} s for {chosen.size} windows ({per_s:.2f} windows/s) | ours / "
        f"pypose {throughput_ours / per_s:.0f} | final cost rel diff vs gtsam max "
        f"{block['final_cost_rel_diff']['max']:.2e}"
    )
    return block, throughput_ours / per_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", type=int, default=256)
    parser.add_argument("--size", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rtol", type=float, default=1e-12)
    parser.add_argument("--linear-solver", default="dense", choices=("dense", "sparse"))
    parser.add_argument("--damping", default="identity", choices=("identity", "marquardt"))
    parser.add_argument("--path", default="chain", choices=("chain", "general"))
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-theseus", action="store_true", help="skip the Theseus peer")
    parser.add_argument(
        "--pypose-windows",
        type=int,
        default=None,
        help="PyPose peer on this many windows, evenly spaced (default: all; 0: skip)",
    )
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    machine = machine_info()
    device = torch.device(args.device)

    seq = load_sequence("kitti-gtsam")
    meta = seq.meta["imu_noise"]
    imu_t = seq.imu.t[0].numpy()
    gps_t = seq.gnss.t[0].numpy()
    gps_xyz = seq.gnss.position[0].numpy()
    n_fix = gps_t.size
    starts = np.unique(np.linspace(FIRST_FIX, n_fix - args.size, args.windows).round().astype(int))
    if starts.size != args.windows:
        raise ValueError(f"only {starts.size} distinct windows of {args.size} fit the drive")
    states, eskf_s = eskf_states(seq, gps_t)
    intervals = gps_intervals(imu_t, seq.imu.accel[0].numpy(), seq.imu.gyro[0].numpy(), gps_t)
    log(
        f"kitti-gtsam: {n_fix} fixes, {args.windows} windows of {args.size} keyframes "
        f"(starts {starts[0]}..{starts[-1]}), ESKF init {eskf_s:.1f} s"
    )

    # --- ours: problem construction --------------------------------------------------
    noise = _noise(meta, device)
    ivals = ImuIntervals(*(torch.as_tensor(intervals[k]) for k in ("gyro", "acc", "dt")))
    zeros = torch.zeros(n_fix - 1, 3, dtype=torch.float64)
    t0 = time.perf_counter()
    pre = preintegrate_imu_tangent(ivals, zeros, zeros, float(meta["integration_sigma"]))
    t1 = time.perf_counter()
    problem = build_ours(states, gps_xyz, starts, args.size, pre, noise, device)
    t2 = time.perf_counter()
    ours_build = {"preintegration_all_intervals_s": t1 - t0, "problem_s": t2 - t1}
    config = LMConfig(
        max_iterations=MAX_ITERATIONS,
        relative_tolerance=args.rtol,
        absolute_tolerance=0.0,
        damping=args.damping,
        linear_solver=args.linear_solver,
        chain=args.path == "chain",
        compact_below=LMConfig.compact_below if args.path == "chain" else 0.0,
    )

    # --- GTSAM: graph construction -----------------------------------------------------
    t0 = time.perf_counter()
    pims = gtsam_pims(intervals, meta)
    t1 = time.perf_counter()
    graphs = [build_gtsam(states, gps_xyz, int(s), args.size, pims, meta) for s in starts]
    t2 = time.perf_counter()
    peer_build = {"preintegration_all_intervals_s": t1 - t0, "graphs_s": t2 - t1}

    # --- Theseus: objective construction (second peer) ---------------------------------
    theseus = None
    theseus_block: dict[str, Any] = {"skipped": "--no-theseus"}
    if not args.no_theseus:
        try:
            th_version = import_theseus().__version__
        except ImportError:
            theseus_block = {"skipped": f"theseus-ai not installed: {INSTALL}"}
            log(f"Theseus peer skipped: theseus-ai not installed ({INSTALL})")
        else:
            t0 = time.perf_counter()
            theseus = build_theseus(problem, args.rtol, MAX_ITERATIONS, LMConfig.initial_damping)
            theseus_build_s = time.perf_counter() - t0
            with torch.no_grad():  # Theseus's own cost at the initial values: same problem?
                th_initial = theseus.layer.objective.error_metric(theseus.initial).cpu().numpy()

    # --- identical problems: costs at the initial values ----------------------------------
    with torch.no_grad():
        ours_initial = problem.cost(problem.values).cpu().numpy()
    peer_initial = np.array([graph.error(init) for graph, init in graphs])

    # --- timed solves, alternating so both see the same machine load ------------------------
    def ours() -> LMResult:
        with torch.no_grad():
            result = solve(problem, config)
        if device.type == "cuda":
            torch.cuda.synchronize()
        return result

    def theseus_solve() -> tuple[torch.Tensor, Any]:
        out = solve_theseus(theseus)
        if device.type == "cuda":
            torch.cuda.synchronize()
        return out

    ours()  # warm-up (lazy library loading)
    if theseus is not None:
        theseus_solve()
    ours_walls, peer_walls, ours_cpus, peer_cpus = [], [], [], []
    th_walls: list[float] = []
    th_cpus: list[float] = []
    for r in range(args.repeats):
        wall, ours_t, result = time_repeats(ours, 1)
        ours_walls.append(wall)
        ours_cpus.append(ours_t["cpu_median_s"])
        wall, peer_t, peer = time_repeats(lambda: solve_gtsam(graphs, args.rtol), 1)
        peer_walls.append(wall)
        peer_cpus.append(peer_t["cpu_median_s"])
        line = f"repeat {r + 1}/{args.repeats}: ours {ours_walls[-1]:.3f} s, gtsam {wall:.3f} s"
        if theseus is not None:
            wall, th_t, (th_values, th_info) = time_repeats(theseus_solve, 1)
            th_walls.append(wall)
            th_cpus.append(th_t["cpu_median_s"])
            line += f", theseus {wall:.3f} s"
        log(line)
    ours_s, peer_s = statistics.median(ours_walls), statistics.median(peer_walls)

    # --- accuracy ------------------------------------------------------------------------
    ours_cost = result.cost.cpu().numpy()
    peer_cost = np.array(
        [graph.error(res) for (graph, _), (res, _) in zip(graphs, peer, strict=True)]
    )
    p_ours, _, r_ours, _, _ = unpack_nav_state(result.values["state"].cpu())
    pos_diff, rot_diff = [], []
    for w, (res, _) in enumerate(peer):
        for i in range(args.size):
            pose = res.atPose3(X(i))
            pos_diff.append(np.linalg.norm(p_ours[w, i].numpy() - pose.translation()))
            rel = torch.as_tensor(pose.rotation().matrix()).mT @ r_ours[w, i]
            rot_diff.append(float(so3.log(rel).norm()))
    ours_iters = result.iterations.cpu().numpy()
    peer_iters = np.array([it for _, it in peer])
    statuses = {s: result.status.count(s) for s in sorted(set(result.status))}

    # --- informational: our default ZOH factor on the same windows --------------------------
    zoh_pre = preintegrate_imu(ivals, zeros, zeros)
    zoh_problem = build_ours(states, gps_xyz, starts, args.size, zoh_pre, noise, device)
    with torch.no_grad():
        zoh = solve(zoh_problem, config)
    zoh_cost = zoh.cost.cpu().numpy()

    final_rel = _rel(ours_cost, peer_cost)
    throughput_ours = args.windows / ours_s
    throughput_peer = args.windows / peer_s
    ratio = throughput_ours / throughput_peer

    # --- PyPose (third peer): a few windows one at a time, once -----------------------------
    pypose_block, ratio_pypose = _pypose(problem, args, ours_cost, peer_cost, throughput_ours)
    ratio_theseus = None
    if theseus is not None:
        th_s = statistics.median(th_walls)
        with torch.no_grad():
            th_cost = problem.cost({"state": th_values}).cpu().numpy()
        th_iters = th_info.converged_iter.cpu().numpy()
        th_status = [s.name for s in th_info.status]
        ratio_theseus = throughput_ours * th_s / args.windows
        theseus_block = {
            "what": (
                f"theseus {th_version} LevenbergMarquardt (CholeskyDenseSolver, adaptive "
                "damping, vectorised AutoDiffCostFunctions) via TheseusLayer, one call with "
                "B = windows"
            ),
            "cost_functions": theseus.cost_functions,
            "solve_s": th_s,
            "solve_repeats_s": th_walls,
            "solve_cpu_repeats_s": th_cpus,
            "windows_per_s": args.windows / th_s,
            "iterations": _stats(th_iters[th_iters >= 0]) if (th_iters >= 0).any() else None,
            "status": {s: th_status.count(s) for s in sorted(set(th_status))},
            "build_s": {"objective_s": theseus_build_s},
            "initial_cost_rel_diff_vs_ours": _stats(_rel(th_initial, ours_initial)),
            "final_cost_rel_diff": _stats(_rel(th_cost, peer_cost)),
            "final_cost_rel_diff_vs_ours": _stats(_rel(th_cost, ours_cost)),
            "final_cost": _stats(th_cost),
        }
    cost_ok = bool(final_rel.max() <= 1e-6)
    speed_ok = bool(ratio >= 20.0)
    log(
        f"ours {ours_s * 1e3:.1f} ms ({throughput_ours:.0f} windows/s, {int(ours_iters.max())} "
        f"iterations) | gtsam {peer_s * 1e3:.1f} ms ({throughput_peer:.0f} windows/s) | "
        f"ratio {ratio:.2f} | final cost rel diff max {final_rel.max():.2e}"
    )
    if theseus is not None:
        log(
            f"theseus {th_s * 1e3:.1f} ms ({args.windows / th_s:.0f} windows/s, "
            f"{int(th_iters.max())} iterations) | ours / theseus {ratio_theseus:.2f} | final "
            f"cost rel diff vs gtsam max {theseus_block['final_cost_rel_diff']['max']:.2e}"
        )
    record = {
        "benchmark": "windows",
        "inputs": {
            "dataset": "kitti-gtsam (gtsam/Data: KittiEquivBiasedImu + KittiGps_converted)",
            "windows": args.windows,
            "keyframes_per_window": args.size,
            "keyframes": "GPS fixes (1 Hz), from fix 1",
            "window_start_fixes": [int(starts[0]), int(starts[-1])],
            "unknowns_per_window": problem.dim,
            "factors": "ImuFactor (Logmap) + bias random walk + GPS + first-keyframe priors",
            "initial_values": "our ESKF (configs/kitti-gtsam.yaml) at the keyframe times",
            "imu_noise": {k: meta[k] for k in sorted(meta) if k != "body_p_sensor"},
            "gravity_mps2": GRAVITY,
            "gps_variance_m2": GPS_VARIANCE,
            "prior_sigmas": {
                "position_m": PRIOR_POSITION_SIGMA,
                "rotation_rad": PRIOR_ROTATION_SIGMA,
                "velocity_mps": PRIOR_VELOCITY_SIGMA,
                "accel_bias": PRIOR_ACCEL_BIAS_SIGMA,
                "gyro_bias": PRIOR_GYRO_BIAS_SIGMA,
            },
            "relative_tolerance": args.rtol,
            "max_iterations": MAX_ITERATIONS,
            "repeats": args.repeats,
            "linear_solver": args.linear_solver,
            "damping": args.damping,
            "path": args.path,
            "device": str(device),
            "torch_threads": torch.get_num_threads(),
        },
        "ours": {
            "what": "msf_torch.backend.lm.solve, one call with B = windows",
            "solve_s": ours_s,
            "solve_repeats_s": ours_walls,
            "solve_cpu_repeats_s": ours_cpus,
            "windows_per_s": throughput_ours,
            "iterations": {"batch": int(ours_iters.max()), **_stats(ours_iters)},
            "status": statuses,
            "build_s": ours_build,
        },
        "peer": {
            "what": "gtsam.LevenbergMarquardtOptimizer, one window at a time",
            "solve_s": peer_s,
            "solve_repeats_s": peer_walls,
            "solve_cpu_repeats_s": peer_cpus,
            "windows_per_s": throughput_peer,
            "iterations": {"sum": int(peer_iters.sum()), **_stats(peer_iters)},
            "build_s": peer_build,
        },
        "ratio": {
            "throughput_ours_over_peer": ratio,
            "cpu_time_peer_over_ours": statistics.median(peer_cpus) / statistics.median(ours_cpus),
        },
        "accuracy": {
            "initial_cost_rel_diff": _stats(_rel(ours_initial, peer_initial)),
            "final_cost_rel_diff": _stats(final_rel),
            "final_cost_ours": _stats(ours_cost),
            "final_cost_peer": _stats(peer_cost),
            "initial_cost": _stats(peer_initial),
            "position_diff_m": _stats(np.array(pos_diff)),
            "rotation_diff_rad": _stats(np.array(rot_diff)),
            "zoh_final_cost_rel_diff": _stats(_rel(zoh_cost, peer_cost)),
            "zoh_iterations": int(zoh.iterations.max()),
        },
        "target": {"final_cost_rel_diff_max": 1e-6, "throughput_ratio_min": 20.0},
        "target_met": {"final_cost": cost_ok, "throughput": speed_ok},
        "theseus": theseus_block,
        "ratio_vs_theseus": ratio_theseus,
        "pypose": pypose_block,
        "ratio_vs_pypose": ratio_pypose,
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
