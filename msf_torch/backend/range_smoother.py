"""Smooth a whole odometry + anchor-range run (:class:`~msf_torch.io.ranges.RangeRun`): the
start pose found when it is not given, then the run solved at once by LM
(:func:`~msf_torch.backend.range2d.odometry_range_problem`); what ``msf ranges`` runs.

Start pose. With the anchors known, the map frame is theirs and the odometry's start pose in
it is unknown: it is searched over ``start_headings`` headings; for each, the odometry of the
first ``start_window_m`` metres travelled is turned by it and the start position
multilaterated from those ranges (:func:`~msf_torch.backend.range2d.multilaterate` on anchor
minus odometry offset); the heading whose fit leaves the smallest Cauchy loss
``sum log(1 + (r / sigma)^2)`` of the range residuals wins, and the solve then holds it only
loosely (``start_sigma`` defaults to 10 m, 1 rad when searched). A window in metres, not
seconds: a robot that turns on the spot first tells nothing about its heading (on Plaza2 the
first 20 s gave a heading 2.2 rad off; the first 30 m give it to 0.1 rad).
Solving for the anchors too (range-only SLAM), the given anchor positions are first guesses
in the map frame and the start is searched against them in the same way, then refined by a
solve with the guesses held, whose start pose the map solve begins from (from the grid
start alone the map ended rotated: 1.59 m RMSE on a simulated run where this gives 0.12 m,
0.82 m on Plaza2 where it gives 0.45 m); without guesses
(``anchors_known_positions=False``) the map frame is the start pose (the origin unless
given), held tightly, and the anchors start from multilateration at the dead-reckoned poses.
"""

from __future__ import annotations

__all__ = [
    "RangeSmootherSettings",
    "RangeSmootherResult",
    "calibrate_from_truth",
    "estimate_start",
    "smooth_ranges",
]

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import torch

from msf_torch.backend.lm import solve
from msf_torch.backend.posegraph import pose_graph_config
from msf_torch.backend.range2d import OdometryNoise, multilaterate, odometry_range_problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.geometry.se2 import align_points, between, chain, rotation, transform_points
from msf_torch.io.ranges import RangeRun


@dataclass
class RangeSmootherSettings:
    """Settings of :func:`smooth_ranges`.

    Attributes:
        range_sigma_m: sigma of one range, m. range_bias_m: subtracted from every range, m.
        kernel: robust kernel on the ranges (scale in sigmas), or None.
        odometry_noise: per-step odometry covariance model.
        solve_anchors: solve for the anchors (range-only SLAM) instead of holding them.
        start: (3,) start pose ``[x, y, heading]`` in the map frame, or None (searched
            against the anchors' positions, or the origin when there are none).
        start_sigma: (m, m, rad) 1-sigma of the prior on the start; None: 0.1 m, 0.05 rad
            for a given start or a solved map, 10 m, 1 rad for a searched start.
        start_window_m: metres travelled whose ranges find the start (and unknown
            anchors).
        start_headings: headings tried when searching the start.
        relative_tolerance, max_iterations: LM stopping rule.
        range_timing: ``"interpolate"`` (default): a range counts at the position
            interpolated between the odometry poses around its time
            (:class:`~msf_torch.backend.range2d.Se2InterpolatedRangeFactor`);
            ``"next_pose"``: at the first pose at or after it (GTSAM's graph, what
            ``benchmarks/plaza_ranges.py`` compares with GTSAM). :func:`calibrate_from_truth`
            measures the range bias and sigma the same way.
    """

    range_sigma_m: float = 0.3
    range_bias_m: float = 0.0
    kernel: RobustKernel | None = field(default_factory=lambda: RobustKernel("cauchy", 2.3849))
    odometry_noise: OdometryNoise = field(default_factory=OdometryNoise)
    solve_anchors: bool = False
    start: torch.Tensor | None = None
    start_sigma: tuple[float, float, float] | None = None
    start_window_m: float = 30.0
    start_headings: int = 72
    relative_tolerance: float = 1e-10
    max_iterations: int = 200
    range_timing: str = "interpolate"


@dataclass
class RangeSmootherResult:
    """Outcome of :func:`smooth_ranges`.

    Attributes:
        poses: (M + 1, 3) ``[x, y, heading]`` at ``run.pose_t`` in the map frame.
        anchors: (L, 2) m (solved, or the run's when held).
        start: (3,) the start pose the solve began from. start_searched: whether it was.
        initial_cost, final_cost: GTSAM-convention cost. iterations: linear solves.
        status: the LM status. seconds: wall time.
        truth_error: position RMSE / max / final (m) against ``run.truth`` (``aligned``:
            after the best rigid motion, when the map frame is the odometry's start), or
            None.
    """

    poses: torch.Tensor
    anchors: torch.Tensor
    start: torch.Tensor
    start_searched: bool
    initial_cost: float
    final_cost: float
    iterations: int
    status: str
    seconds: float
    truth_error: dict[str, float] | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures (no per-pose arrays)."""
        return {
            "start": self.start.tolist(),
            "start_searched": self.start_searched,
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "iterations": self.iterations,
            "status": self.status,
            "seconds": self.seconds,
            "truth_error": self.truth_error,
        }


def calibrate_from_truth(
    run: RangeRun, settings: RangeSmootherSettings | None = None, stretch_steps: int = 100
) -> RangeSmootherSettings:
    """Range bias and sigma and the odometry noise measured on a run with ground truth
    (use another run than the one you then solve).

    * range bias = median of (range - true distance to the anchor), sigma = 1.4826 MAD;
    * odometry: over consecutive stretches of ``stretch_steps`` steps, the chained odometry
      against the truth's relative pose, in the truth's frame at the stretch start: the
      forward error's spread^2 per metre gives ``forward`` (and ``lateral``, set equal),
      the sideways error read as a heading random walk (``var_y = heading L^3 / 3`` over
      ``L`` m) gives ``heading``. Needs truth headings and one whole stretch; without them
      the odometry noise is left as ``settings`` has it, with a warning.

    Args:
        run: a run with ``truth``. settings: the settings to update (default ones).
        stretch_steps: odometry steps per stretch.

    Returns:
        a copy of ``settings`` with ``range_bias_m``, ``range_sigma_m`` and, when measured,
        ``odometry_noise`` replaced.

    Raises:
        ValueError: the run has no truth.
    """
    if run.truth is None:
        raise ValueError(f"run {run.name!r} has no truth to calibrate against")
    settings = settings or RangeSmootherSettings()
    truth = run.truth
    true_distance = run.anchors[run.range_anchor_rows()] - _range_positions(run, truth, settings)
    errors = run.ranges - true_distance.norm(dim=-1)
    bias = float(errors.median())
    sigma = float(1.4826 * (errors - bias).abs().median())
    out = dataclasses.replace(settings, range_bias_m=bias, range_sigma_m=sigma)
    steps = run.odometry.shape[0]
    starts = list(range(0, steps - stretch_steps, stretch_steps))
    if not starts or bool(torch.isnan(truth[:, 2]).any()):
        reason = "no truth headings" if starts else f"fewer than {stretch_steps + 1} poses"
        warnings.warn(
            f"calibrate_from_truth: odometry noise not measured on {run.name!r} ({reason}); "
            "the range bias and sigma are, the odometry noise is kept",
            stacklevel=2,
        )
        return out
    forward, sideways, lengths = [], [], []
    for start in starts:
        chained = chain(run.odometry.new_zeros(3), run.odometry[start : start + stretch_steps])[-1]
        reference = between(truth[start], truth[start + stretch_steps])
        forward.append(float(chained[0] - reference[0]))
        sideways.append(float(chained[1] - reference[1]))
        lengths.append(float(run.odometry[start : start + stretch_steps, 0:2].norm(dim=-1).sum()))

    def spread(values: list[float]) -> float:
        v = torch.tensor(values, dtype=torch.float64)
        return float(1.4826 * (v - v.median()).abs().median())

    length = sum(lengths) / len(lengths)
    forward_per_m = spread(forward) ** 2 / length
    noise = dataclasses.replace(
        settings.odometry_noise,
        forward=forward_per_m,
        lateral=forward_per_m,
        heading=3.0 * spread(sideways) ** 2 / length**3,
    )
    return dataclasses.replace(out, odometry_noise=noise)


def _interpolated(settings: RangeSmootherSettings) -> bool:
    """Whether ranges count at interpolated positions; a ValueError for an unknown timing."""
    if settings.range_timing not in ("interpolate", "next_pose"):
        raise ValueError(
            f"range_timing must be 'interpolate' or 'next_pose', got {settings.range_timing!r}"
        )
    return settings.range_timing == "interpolate"


def _range_positions(
    run: RangeRun, poses: torch.Tensor, settings: RangeSmootherSettings
) -> torch.Tensor:
    """(K, 2) positions of ``poses`` (M + 1, >= 2) where the ranges count (settings'
    ``range_timing``)."""
    if _interpolated(settings):
        return run.range_positions(poses)
    return poses[run.range_pose_index(), 0:2]


def _early(run: RangeRun, window_m: float) -> torch.Tensor:
    """(K,) bool: the ranges taken within the first ``window_m`` metres travelled."""
    travelled = torch.cumsum(run.odometry[:, 0:2].norm(dim=-1), 0)
    travelled = torch.cat((travelled.new_zeros(1), travelled))
    return travelled[run.range_pose_index()] <= window_m


def estimate_start(
    run: RangeRun,
    ranges: torch.Tensor,
    range_sigma_m: float,
    window_m: float = 30.0,
    headings: int = 72,
) -> torch.Tensor:
    """Start pose (3,) of the odometry in the anchors' frame (module docstring).

    Args:
        run: the run (anchors known). ranges: (K,) bias-removed ranges, m.
        range_sigma_m: scale of the Cauchy loss, m. window_m: metres travelled whose ranges
            are used. headings: headings tried over the full turn.

    Raises:
        ValueError: fewer than three ranges in the window, or all of them to anchors at one
            position (the run could be turned about it: the heading is not observable).
    """
    early = _early(run, window_m)
    if int(early.sum()) < 3:
        raise ValueError(
            f"finding the start needs 3 or more ranges in the first {window_m:g} m travelled, "
            f"got {int(early.sum())}; give the start pose"
        )
    ranged = run.range_anchor_rows()[early].unique()
    if torch.unique(run.anchors[ranged], dim=0).shape[0] < 2:
        x, y = run.anchors[ranged[0]].tolist()
        raise ValueError(
            f"finding the start needs ranges to anchors at 2 or more positions in the first "
            f"{window_m:g} m travelled, got ranges to anchor(s) "
            f"{run.anchor_ids[ranged].tolist()} at ({x:g}, {y:g}) only; give the start pose"
        )
    offsets = run.odometry_poses(run.odometry.new_zeros(3))[run.range_pose_index()[early]]
    anchors = run.anchors[run.range_anchor_rows()[early]]
    angle = (
        torch.remainder(
            torch.arange(headings, dtype=offsets.dtype) * (2 * math.pi / headings) + math.pi,
            2 * math.pi,
        )
        - math.pi
    )
    turned = offsets[None, :, 0:2] @ rotation(angle).mT  # (H, K', 2): the odometry turned
    positions = multilaterate(anchors[None] - turned, ranges[early])  # (H, 2), one solve
    residual = (anchors[None] - turned - positions[:, None]).norm(dim=-1) - ranges[early]
    cost = torch.log1p((residual / range_sigma_m) ** 2).sum(-1)
    best = int(cost.argmin())
    return torch.cat((positions[best], angle[best : best + 1]))


_MIN_SPREAD_M = 1.0
"""Sideways spread (m, the smaller principal axis) the poses of an anchor's first ranges
must have before they place it: from a straight stretch the anchor's mirror image across it
fits as well, and a robust kernel then keeps the wrong one (its ranges all taken for
outliers)."""


def _initial_anchors(run: RangeRun, start: torch.Tensor, ranges: torch.Tensor, window_m: float):
    """Anchors multilaterated at the dead-reckoned poses from their ranges of the first
    ``window_m`` metres, or of as much longer as it takes for those poses to spread
    :data:`_MIN_SPREAD_M` sideways (all of the anchor's ranges at most)."""
    early = _early(run, window_m)
    dead_reckoning = run.odometry_poses(start)[run.range_pose_index(), 0:2]
    rows = run.range_anchor_rows()
    guesses = []
    for j in range(run.anchors.shape[0]):
        mine = torch.nonzero(rows == j).squeeze(-1)
        if mine.numel() < 3:
            raise ValueError(f"anchor {int(run.anchor_ids[j])} has fewer than 3 ranges")
        count = max(3, int(early[mine].sum()))
        while count < mine.numel():
            spread = torch.linalg.eigvalsh(torch.cov(dead_reckoning[mine[:count]].T))[0]
            if float(spread) >= _MIN_SPREAD_M**2:
                break
            count = min(mine.numel(), 2 * count)
        chosen = mine[:count]
        guesses.append(multilaterate(dead_reckoning[chosen], ranges[chosen]))
    return torch.stack(guesses)


def smooth_ranges(
    run: RangeRun,
    settings: RangeSmootherSettings | None = None,
    anchors_known_positions: bool | None = None,
) -> RangeSmootherResult:
    """Solve a whole run (module docstring).

    Args:
        run: odometry, ranges, anchors (:func:`~msf_torch.io.ranges.read_range_run`).
        settings: :class:`RangeSmootherSettings`.
        anchors_known_positions: with ``settings.solve_anchors``, whether ``run.anchors``
            holds usable first guesses (else they are multilaterated); None: whether they
            are all finite (:func:`~msf_torch.io.ranges.read_range_run` gives NaN without
            an anchors file).

    Returns:
        :class:`RangeSmootherResult`.

    Raises:
        ValueError: too few ranges to find the start or an anchor; a given start heading
            beyond a full turn (degrees by mistake); anchors without positions to hold
            (``solve_anchors`` off).
    """
    settings = settings or RangeSmootherSettings()
    if anchors_known_positions is None:
        anchors_known_positions = bool(torch.isfinite(run.anchors).all())
    if not settings.solve_anchors and not bool(torch.isfinite(run.anchors).all()):
        raise ValueError(
            "the anchors' positions are unknown (no anchors file, or NaN): give them, or solve "
            "for them (solve_anchors, msf ranges --solve-anchors)"
        )
    begin = time.perf_counter()
    ranges = run.ranges - settings.range_bias_m
    guessed = not settings.solve_anchors or anchors_known_positions
    searched = settings.start is None and guessed
    if settings.start is not None:
        start = settings.start.to(torch.float64)
        heading = float(start[-1]) if start.shape == (3,) else 0.0
        if abs(heading) > 2 * math.pi:
            raise ValueError(
                f"start heading {heading:g} rad is more than a full turn; headings are in "
                f"radians ({heading:g} degrees would be {math.radians(heading):.4f} rad)"
            )
    elif searched:
        start = estimate_start(
            run, ranges, settings.range_sigma_m, settings.start_window_m, settings.start_headings
        )
    else:
        start = run.odometry.new_zeros(3)
    sigma = settings.start_sigma or ((10.0, 10.0, 1.0) if searched else (0.1, 0.1, 0.05))
    anchors = run.anchors
    if settings.solve_anchors and not anchors_known_positions:
        anchors = _initial_anchors(run, start, ranges, settings.start_window_m)
    if settings.solve_anchors and searched:
        # the searched start is on a 5-degree grid and the map's frame hangs on its loose
        # prior: solve with the guesses held first and start the map from that start
        held = smooth_ranges(
            run, dataclasses.replace(settings, solve_anchors=False), anchors_known_positions
        )
        start = held.poses[0]
    problem = odometry_range_problem(
        run.odometry,
        run.range_pose_index(),
        run.range_anchor_rows(),
        ranges,
        anchors,
        start,
        torch.diag(torch.tensor(sigma, dtype=torch.float64) ** 2),
        odometry_noise=settings.odometry_noise,
        range_sigma_m=settings.range_sigma_m,
        range_kernel=settings.kernel,
        beacons_known=not settings.solve_anchors,
        initial_poses=run.odometry_poses(start),
        range_fraction=run.range_pose_fraction() if _interpolated(settings) else None,
    )
    config = pose_graph_config(
        planar=True,
        relative_tolerance=settings.relative_tolerance,
        max_iterations=settings.max_iterations,
    )
    with torch.no_grad():
        result = solve(problem, config)
    poses = result.values["pose"][0]
    truth_error = None
    if run.truth is not None:
        positions = poses[:, 0:2]
        own_frame = settings.start is None and not anchors_known_positions
        if own_frame:  # the map frame is the odometry's start: compare up to a rigid motion
            positions = transform_points(align_points(positions, run.truth[:, 0:2]), positions)
        distance = (positions - run.truth[:, 0:2]).norm(dim=-1)
        truth_error = {
            "rmse_m": float(distance.pow(2).mean().sqrt()),
            "max_m": float(distance.max()),
            "final_m": float(distance[-1]),
            "aligned": own_frame,
        }
    return RangeSmootherResult(
        poses=poses,
        anchors=result.values["beacon"][0],
        start=start,
        start_searched=searched,
        initial_cost=float(result.initial_cost[0]),
        final_cost=float(result.cost[0]),
        iterations=int(result.iterations[0]),
        status=result.status[0],
        seconds=time.perf_counter() - begin,
        truth_error=truth_error,
    )
