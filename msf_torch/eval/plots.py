"""Figures: the overview of one run (top-down trajectory, position error, wheel slip factor),
a pose graph before and after optimisation, and a smoothed odometry + anchor-range run.

Drawn with matplotlib's object API on an Agg canvas (no pyplot state, no display needed) and
written atomically: a temporary file in the target directory, then ``os.replace``, so a reader
never sees a half-written PNG and a failed save leaves no stray file.
"""

from __future__ import annotations

__all__ = ["overview_figure", "pose_graph_figure", "range_run_figure"]

import os
import tempfile
from collections.abc import Sequence as SequenceABC
from pathlib import Path
from typing import Any

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from msf_torch.types import Trajectory

_EST_COLOR = "tab:blue"
_REF_COLOR = "0.3"
_OUTAGE_COLOR = "tab:red"
_DPI = 120


def _as_numpy(x: Any) -> np.ndarray:
    """1-D float64 numpy copy of a tensor or array-like."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().to(torch.float64).numpy()
    arr = np.asarray(x, dtype=np.float64).reshape(-1)
    return arr


def _xy(traj: Trajectory, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Real times (K,) and positions (K, 3) of a B = 1 trajectory, numpy float64."""
    if traj.batch_size != 1:
        raise ValueError(f"{name} must have B = 1, got B = {traj.batch_size}; use select(i)")
    keep = traj.mask[0].detach().cpu().numpy()
    t = traj.t[0].detach().cpu().to(torch.float64).numpy()[keep]
    p = traj.position[0].detach().cpu().to(torch.float64).numpy()[keep]
    return t, p


def _no_data(ax, text: str) -> None:
    ax.text(
        0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4", fontsize=11
    )
    ax.set_xticks([])
    ax.set_yticks([])


def overview_figure(
    path: str | os.PathLike,
    estimate: Trajectory,
    reference: Trajectory | None = None,
    error_t: torch.Tensor | np.ndarray | None = None,
    error: torch.Tensor | np.ndarray | None = None,
    slip_t: torch.Tensor | np.ndarray | None = None,
    slip: torch.Tensor | np.ndarray | None = None,
    outage: SequenceABC[float] | None = None,
    title: str = "",
    slip_panel: bool = True,
    reference_label: str = "reference",
) -> Path:
    """Write a three-panel PNG overview of one run.

    Panels: (left) top-down x-y trajectory, estimate against reference, equal axes, with the
    estimate's part inside ``outage`` drawn in red; (top right) position error over time with
    the outage shaded; (bottom right) wheel slip factor over time, or "no wheel data"
    (``slip_panel=False``: no such panel, the error panel takes the right column).

    All times are seconds on the estimate's clock and are drawn relative to the estimate's
    first real time.

    Args:
        path: output ``.png`` path (parent directories are created).
        estimate: estimated trajectory, B = 1 (``mask`` honoured), m.
        reference: reference trajectory, B = 1, or None. Drawn as given (not aligned); pass
            an aligned estimate if frames differ.
        error_t: (K,) times of ``error``, s.
        error: (K,) position error, m. When None and ``reference`` is given, it is computed
            with :func:`msf_torch.eval.metrics.position_errors` (SE(3) alignment).
        slip_t: (L,) times of ``slip``, s.
        slip: (L,) wheel slip factor, dimensionless; None hides the curve.
        outage: ``(t0, t1)`` s, a sensor outage to highlight, or None.
        title: figure title.
        slip_panel: draw the wheel-slip panel (a figure of a run without wheels, as
            ``msf eval`` draws, leaves it out).
        reference_label: what the reference is, for the legends (``"GNSS fixes"`` when the
            run has no ground truth and is scored against its own fixes).

    Returns:
        The written path.

    Raises:
        ValueError: B is not 1, or a time/value pair has different lengths.
    """
    path = Path(path)
    t_est, p_est = _xy(estimate, "estimate")
    t_origin = float(t_est[0]) if t_est.size else 0.0
    p_ref = None
    if reference is not None:
        _, p_ref = _xy(reference, "reference")
        if error is None:
            from msf_torch.eval.metrics import position_errors

            et, ee = position_errors(estimate, reference, align="se3")
            error_t, error = et, ee
    pairs = {}
    for name, times, values in (("error", error_t, error), ("slip", slip_t, slip)):
        if values is None:
            pairs[name] = None
            continue
        if times is None:
            raise ValueError(f"{name} is given without {name}_t")
        tt, vv = _as_numpy(times), _as_numpy(values)
        if tt.shape != vv.shape:
            raise ValueError(f"{name}_t has {tt.size} samples but {name} has {vv.size}")
        pairs[name] = (tt - t_origin, vv)
    span = None
    if outage is not None:
        t0, t1 = (float(v) for v in outage)
        span = (t0 - t_origin, t1 - t_origin)

    fig = Figure(figsize=(13.0, 6.5), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2, width_ratios=(1.15, 1.0))
    ax_xy = fig.add_subplot(grid[:, 0])
    ax_err = fig.add_subplot(grid[0, 1] if slip_panel else grid[:, 1])
    both = pairs["error"] is not None and pairs["slip"] is not None
    ax_slip = fig.add_subplot(grid[1, 1], sharex=ax_err if both else None) if slip_panel else None

    # Top-down trajectory.
    if p_ref is not None:
        ax_xy.plot(
            p_ref[:, 0],
            p_ref[:, 1],
            color=_REF_COLOR,
            ls="--",
            lw=1.3,
            label=reference_label,
            zorder=3,
        )
    ax_xy.plot(p_est[:, 0], p_est[:, 1], color=_EST_COLOR, lw=1.5, label="estimate")
    if p_est.shape[0]:
        ax_xy.plot(*p_est[0, :2], "o", color="tab:green", ms=6, label="start", zorder=5)
        ax_xy.plot(*p_est[-1, :2], "s", color="black", ms=5, label="end", zorder=5)
    if span is not None:
        inside = (t_est - t_origin >= span[0]) & (t_est - t_origin <= span[1])
        seg = np.where(inside[:, None], p_est[:, :2], np.nan)
        ax_xy.plot(
            seg[:, 0],
            seg[:, 1],
            color=_OUTAGE_COLOR,
            lw=3.0,
            alpha=0.85,
            label="estimate during outage",
        )
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_xlabel("x [m]")
    ax_xy.set_ylabel("y [m]")
    ax_xy.set_title("trajectory (top-down)")
    ax_xy.grid(True, alpha=0.35)
    ax_xy.legend(loc="best", fontsize=9)

    # Position error.
    if pairs["error"] is not None:
        tt, vv = pairs["error"]
        rmse = float(np.sqrt(np.mean(vv**2))) if vv.size else float("nan")
        against = "" if reference_label == "reference" else f" vs {reference_label}"
        ax_err.plot(
            tt, vv, color=_EST_COLOR, lw=1.2, label=f"position error{against} (RMSE {rmse:.3f} m)"
        )
        if span is not None:
            ax_err.axvspan(*span, color=_OUTAGE_COLOR, alpha=0.12, label="outage")
        ax_err.set_ylabel("position error [m]")
        ax_err.set_ylim(bottom=0.0)
        ax_err.grid(True, alpha=0.35)
        ax_err.legend(loc="upper left", fontsize=9)
    else:
        _no_data(ax_err, "no reference")
    ax_err.set_title("position error")

    # Slip factor.
    if ax_slip is None:
        if pairs["error"] is not None:
            ax_err.set_xlabel("time since start [s]")
    elif pairs["slip"] is not None:
        tt, vv = pairs["slip"]
        ax_slip.plot(tt, vv, color="tab:purple", lw=1.2, label="slip factor")
        if span is not None:
            ax_slip.axvspan(*span, color=_OUTAGE_COLOR, alpha=0.12, label="outage")
        ax_slip.set_ylabel("slip factor [-]")
        ax_slip.set_xlabel("time since start [s]")
        ax_slip.grid(True, alpha=0.35)
        ax_slip.legend(loc="upper left", fontsize=9)
    else:
        _no_data(ax_slip, "no wheel data")
        if pairs["error"] is not None:
            ax_err.set_xlabel("time since start [s]")
    if ax_slip is not None:
        ax_slip.set_title("wheel slip")
    if title:
        fig.suptitle(title)

    return _save_png(fig, path)


def _save_png(fig: Figure, path: Path) -> Path:
    """Write ``fig`` to ``path`` atomically (temporary file in the directory, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            fig.savefig(handle, format="png", dpi=_DPI)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; give the PNG ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def pose_graph_figure(
    path: str | os.PathLike[str],
    initial_positions: Any,
    optimised_positions: Any,
    edge_index: Any,
    log: SequenceABC[dict[str, Any]],
    initial_cost: float,
    title: str | None = None,
    landmarks: tuple[Any, Any] | None = None,
) -> Path:
    """Write a PNG of a pose graph before and after optimisation.

    Panels: top view (x-y) and side view (x-z; only the top view for a 2-D graph) of the
    vertex positions, initial in grey and optimised in blue, with the edges between
    non-consecutive vertices (loop closures) drawn faintly on the optimised poses; and the
    cost per iteration (log scale, rejected steps marked), starting from ``initial_cost``.

    Args:
        path: the PNG file (parent folders are created; written atomically).
        initial_positions, optimised_positions: (N, 3) m, vertex positions ((N, 2) for a
            2-D graph).
        edge_index: (E, 2) vertex rows of each edge.
        log: one dict per iteration with ``cost`` and ``accepted``
            (:class:`~msf_torch.backend.posegraph.PoseGraphResult`'s ``log``).
        initial_cost: cost before the first iteration.
        title: figure title.
        landmarks: a 2-D graph's landmark positions (L, 2) m, initial and optimised, drawn
            on the top view (initial as grey dots, optimised as orange crosses), or None.

    Returns:
        the path written.

    Raises:
        ValueError: the position arrays are not (N, 3) or (N, 2) of one N, ``edge_index``
            is not (E, 2) rows into them, or ``landmarks`` are not two (L, 2) arrays for a
            2-D graph.
    """
    path = Path(path)
    before = np.asarray(torch.as_tensor(initial_positions).detach().cpu(), dtype=np.float64)
    after = np.asarray(torch.as_tensor(optimised_positions).detach().cpu(), dtype=np.float64)
    marks = None
    if landmarks is not None:
        marks = [
            np.asarray(torch.as_tensor(m).detach().cpu(), dtype=np.float64).reshape(-1, 2)
            for m in landmarks
        ]
        if before.ndim != 2 or before.shape[-1] != 2 or marks[0].shape != marks[1].shape:
            raise ValueError(
                "landmarks are drawn for 2-D graphs only, as two (L, 2) arrays; got "
                f"{marks[0].shape} and {marks[1].shape} for positions {before.shape}"
            )
    edges = np.asarray(torch.as_tensor(edge_index).detach().cpu(), dtype=np.int64)
    if before.ndim != 2 or before.shape[1] not in (2, 3) or before.shape != after.shape:
        raise ValueError(
            f"positions must be (N, 3) or (N, 2) of one N, got {before.shape} and {after.shape}"
        )
    if (
        edges.ndim != 2
        or edges.shape[1] != 2
        or (edges.size and not (edges.min() >= 0 and edges.max() < before.shape[0]))
    ):
        raise ValueError(f"edge_index must be (E, 2) rows of the {before.shape[0]} vertices")
    loops = edges[np.abs(edges[:, 0] - edges[:, 1]) > 1]

    from matplotlib.collections import LineCollection

    views = (((0, 1), "top view"), ((0, 2), "side view"))[: before.shape[1] - 1]
    fig = Figure(figsize=(5.0 * len(views) + 4.5, 5.2), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(views) + 1, width_ratios=(1.0,) * len(views) + (0.9,))
    for ax, ((u, v), name) in zip(axes[:-1], views, strict=True):
        if loops.size:
            segments = after[loops][:, :, [u, v]]
            ax.add_collection(
                LineCollection(segments, colors="tab:orange", linewidths=0.4, alpha=0.35)
            )
        ax.plot(before[:, u], before[:, v], color="0.6", lw=0.8, label="initial")
        ax.plot(after[:, u], after[:, v], color=_EST_COLOR, lw=1.0, label="optimised")
        if loops.size:
            ax.plot([], [], color="tab:orange", lw=0.8, label=f"loop edges ({len(loops)})")
        if marks is not None and marks[0].size:
            ax.plot(*marks[0].T, ".", color="0.55", ms=3, label="landmarks, initial")
            ax.plot(*marks[1].T, "x", color="tab:red", ms=4, label=f"landmarks ({len(marks[1])})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[u] + " [m]")
        ax.set_ylabel("xyz"[v] + " [m]")
        ax.set_title(f"{name} ({before.shape[0]} poses, {edges.shape[0]} edges)")
        ax.grid(True, alpha=0.35)
        ax.legend(loc="best", fontsize=8)
    ax_cost = axes[-1]
    costs = np.array([initial_cost] + [float(entry["cost"]) for entry in log])
    accepted = np.array([True] + [bool(entry["accepted"]) for entry in log])
    steps = np.arange(costs.size)
    kept = np.minimum.accumulate(np.where(accepted, costs, np.inf))
    ax_cost.plot(steps, kept, color=_EST_COLOR, marker="o", ms=4, lw=1.2, label="cost")
    if not accepted.all():
        ax_cost.plot(
            steps[~accepted], costs[~accepted], "x", color="tab:red", ms=7, label="rejected step"
        )
    if (costs > 0).all():
        ax_cost.set_yscale("log")
    ax_cost.set_xlabel("iteration")
    ax_cost.set_ylabel("cost 0.5 sum |W r|^2")
    ax_cost.set_title(f"cost {costs[0]:.4g} -> {kept[-1]:.4g}")
    ax_cost.grid(True, alpha=0.35, which="both")
    ax_cost.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save_png(fig, path)


def range_run_figure(
    path: str | os.PathLike[str],
    run: Any,
    poses: Any,
    anchors: Any,
    dead_reckoning: Any | None = None,
) -> Path:
    """Write a PNG of a smoothed odometry + anchor-range run.

    Panels: top view of the estimate (blue), the dead-reckoned odometry from the same start
    (grey), the truth when the run has one (black), the anchors as the run gives them (red
    triangles) and as solved when they moved (orange crosses); and, with a truth, the
    position error over time (estimate and odometry, log scale).

    Args:
        path: the PNG file (parent folders are created; written atomically).
        run: a :class:`~msf_torch.io.ranges.RangeRun`.
        poses: (M + 1, 3) ``[x, y, heading]`` estimate at ``run.pose_t``.
        anchors: (L, 2) m, the anchors after the solve.
        dead_reckoning: (M + 1, 3) odometry chained from the estimate's start (default:
            computed from ``run``).

    Returns:
        the path written.
    """

    def table(x: Any) -> np.ndarray:
        return np.asarray(torch.as_tensor(x).detach().cpu().to(torch.float64))

    estimate = table(poses)
    if dead_reckoning is None:
        dead_reckoning = run.odometry_poses(torch.as_tensor(estimate[0]))
    odometry = table(dead_reckoning)
    given, solved = table(run.anchors), table(anchors)
    truth = None if run.truth is None else table(run.truth)
    panels = 1 if truth is None else 2
    fig = Figure(figsize=(6.5 * panels + 0.5, 5.5), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(1, panels))
    top = axes[0]
    if truth is not None:
        top.plot(truth[:, 0], truth[:, 1], color="k", lw=1.2, label="truth")
    top.plot(odometry[:, 0], odometry[:, 1], color="0.6", lw=0.8, label="odometry")
    top.plot(estimate[:, 0], estimate[:, 1], color=_EST_COLOR, lw=0.9, label="estimate")
    top.plot(given[:, 0], given[:, 1], "^", color="tab:red", ms=9, label="anchors")
    if np.abs(solved - given).max() > 1e-9:
        top.plot(solved[:, 0], solved[:, 1], "x", color="tab:orange", ms=9, label="solved")
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title(f"{run.name}: {run.ranges.shape[0]} ranges, {given.shape[0]} anchors")
    top.grid(True, alpha=0.35)
    top.legend(loc="best", fontsize=8)
    if truth is not None:
        errors = axes[1]
        t = table(run.pose_t) - float(run.pose_t[0])
        for positions, name, color in (
            (odometry, "odometry", "0.6"),
            (estimate, "estimate", _EST_COLOR),
        ):
            distance = np.linalg.norm(positions[:, 0:2] - truth[:, 0:2], axis=1)
            rmse = float(np.sqrt(np.mean(distance**2)))
            errors.plot(t, distance, color=color, label=f"{name} (RMSE {rmse:.2f} m)")
        errors.set_yscale("log")
        errors.set_xlabel("time [s]")
        errors.set_ylabel("position error [m]")
        errors.grid(True, alpha=0.35, which="both")
        errors.legend(loc="best", fontsize=8)
    return _save_png(fig, Path(path))
