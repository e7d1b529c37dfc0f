"""Pose-graph optimisation: a 3-D :class:`~msf_torch.io.g2o.PoseGraph` (or a planar
:class:`~msf_torch.io.g2o_2d.PoseGraph2D`, :mod:`msf_torch.backend.posegraph2d`) solved by
the batched LM of :mod:`msf_torch.backend.lm` with GTSAM's cost.

The graph becomes one :class:`~msf_torch.backend.problem.Problem` (B = 1) with one ``se3``
variable group (the poses, moved by ``T <- T exp([rho, phi])``, GTSAM's ``Pose3``
retraction) and one :class:`~msf_torch.backend.factors.BetweenFactor` type over the edges,
error ``Log_SE3(Z_ij^-1 T_i^-1 T_j)`` in [rho, phi] order with covariance
``edge_information^-1``. The cost is

    0.5 * sum_ij rho(|W_ij r_ij|^2)      (rho(s) = s without a robust kernel)

i.e. exactly GTSAM's ``NonlinearFactorGraph.error`` of ``BetweenFactor<Pose3>`` factors with
``noiseModel::Gaussian.Information(M)`` (robust: ``noiseModel::Robust`` around it). The
gauge is fixed by holding chosen vertices constant, where GTSAM would add a prior: by default
those the file's ``FIX`` records name (``PoseGraph.fixed_ids``, as g2o does), else the first
vertex.

``dof=4`` solves the same cost over x, y, z and yaw only, holding every vertex's roll and
pitch (visual-inertial runs, where gravity makes them observable):
:mod:`msf_torch.backend.posegraph4dof`.

Solver defaults (:func:`pose_graph_config`) follow GTSAM's ``LevenbergMarquardtParams``:
identity damping (``lambda I``) starting at ``lambda = 1e-5``, relative cost-decrease
tolerance 1e-5, at most 100 iterations; the normal equations are factored by MKL
PARDISO when ``pypardiso`` is installed (extra ``[fast]``), else by CHOLMOD through
cholespy (:mod:`msf_torch.backend.lm`). Two differences: for 3-D graphs the damping is
updated by Nielsen's rule (GTSAM, and ours for 2-D graphs: divide / multiply by 10; see
:func:`pose_graph_config`), and ``iterations`` counts every linear solve,
including rejected steps (GTSAM counts outer iterations, each of which may retry with more
damping).

Example::

    from msf_torch.io import gtsam_pose_graph_path, read_pose_graph
    graph = read_pose_graph(gtsam_pose_graph_path("pose3example.txt"))
    result = optimize_pose_graph(graph)
    result.final_cost, result.graph.positions  # GTSAM-convention cost; (N, 3) m
"""

from __future__ import annotations

__all__ = [
    "PoseGraphResult",
    "incremental_start",
    "optimize_pose_graph",
    "pose_graph_config",
    "pose_graph_problem",
]

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from msf_torch.backend.factors import BetweenFactor
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.posegraph2d import LANDMARK_GROUP, held_vertices, pose_graph_2d_problem
from msf_torch.backend.posegraph4dof import YAW_POSITION, YawBetweenFactor
from msf_torch.backend.problem import Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import pack_pose, unpack_pose
from msf_torch.geometry.se2 import between, compose, inverse, transform_points
from msf_torch.io.g2o import PoseGraph
from msf_torch.io.g2o_2d import PoseGraph2D

_GROUP = "pose"


@dataclass
class PoseGraphResult:
    """Outcome of :func:`optimize_pose_graph`.

    Attributes:
        graph: the optimised graph: the input's edges with the solved vertex poses
            (``rotations`` (N, 3, 3), ``positions`` (N, 3) m; for a 2-D graph ``positions``
            (N, 2) m, ``headings`` (N,) rad), same device and dtype.
        initial_cost, final_cost: GTSAM-convention cost ``0.5 * sum rho(|W r|^2)`` before and
            after (with the robust loss when a kernel was given).
        iterations: linear solves run (accepted and rejected steps).
        seconds: wall time of building the problem and solving it, s.
        status: ``"converged"``, ``"stalled"`` (no decrease found up to the largest damping)
            or ``"max_iterations"``.
        log: one dict per iteration: ``cost`` (after it), ``step_norm`` (tangent step,
            mixed m / rad), ``damping`` (lambda used), ``accepted`` (bool).
        start: ``"file"`` (LM from the graph's own poses) or ``"incremental"`` (from
            :func:`incremental_start`'s estimate; ``log`` then covers the final LM only).
        start_cost: cost at the start the final LM began from (``initial_cost`` for
            ``"file"``).
    """

    graph: PoseGraph | PoseGraph2D
    initial_cost: float
    final_cost: float
    iterations: int
    seconds: float
    status: str
    log: list[dict[str, float | bool]] = field(default_factory=list)
    start: str = "file"
    start_cost: float | None = None

    @property
    def converged(self) -> bool:
        """True when a tolerance was met."""
        return self.status == "converged"


def pose_graph_config(
    max_iterations: int = 100,
    relative_tolerance: float = 1e-5,
    absolute_tolerance: float = 0.0,
    step_tolerance: float = 1e-12,
    initial_damping: float = 1e-5,
    planar: bool = False,
) -> LMConfig:
    """The LM settings for pose graphs: sparse solver, identity damping; Nielsen's damping
    update for 3-D graphs, GTSAM's (divide / multiply by 10) for planar ones.

    Defaults are GTSAM's ``LevenbergMarquardtParams`` defaults where the meaning agrees. The
    update rule is the faster one on each kind's benchmark graph: on sphere2500 (3-D)
    Nielsen's rule reaches rel 1e-12 in 96 linear solves where GTSAM's takes 200; on w10000
    (2-D) GTSAM's rule reaches the minimum (144.86738) in the 8 solves after which Nielsen's
    stops at 144.87139 at rel 1e-5, and rel 1e-12 in 10 solves instead of 15.

    Args:
        max_iterations: most linear solves.
        relative_tolerance: converged when an accepted step lowers the cost by at most this
            fraction of it (GTSAM's ``relativeErrorTol``).
        absolute_tolerance: converged when the cost falls to this (GTSAM's ``errorTol``).
        step_tolerance: converged when the step is at most this times the norm of the stacked
            variable values.
        initial_damping: lambda of the first iteration (GTSAM's ``lambdaInitial``).
        planar: settings for a 2-D graph (GTSAM's damping update).

    Returns:
        an :class:`~msf_torch.backend.lm.LMConfig`.
    """
    return LMConfig(
        max_iterations=max_iterations,
        initial_damping=initial_damping,
        damping="identity",
        relative_tolerance=relative_tolerance,
        absolute_tolerance=absolute_tolerance,
        step_tolerance=step_tolerance,
        linear_solver="sparse",
        damping_update="multiplicative" if planar else "nielsen",
    )


def pose_graph_problem(
    graph: PoseGraph,
    robust: RobustKernel | None = None,
    fixed: Sequence[int] | torch.Tensor | None = None,
    dof: int = 6,
) -> Problem:
    """The B = 1 least-squares problem of a pose graph.

    Args:
        graph: N vertices, E edges (any device; float64 recommended).
        robust: kernel applied to every edge, or None.
        fixed: row indices (not file ids) of the vertices held constant; None holds the
            rows of ``graph.fixed_ids`` (the file's ``FIX`` records), else the first vertex.
        dof: 6 (full poses) or 4 (x, y, z, yaw; roll and pitch held).

    Returns:
        a :class:`~msf_torch.backend.problem.Problem` with group ``"pose"`` (``se3``, or
        ``yaw_position`` for ``dof=4``; values (1, N, 12)) and one
        :class:`~msf_torch.backend.factors.BetweenFactor` type (E,).

    Raises:
        ValueError: a malformed graph, a fixed index outside ``[0, N)`` or ``dof`` not 4 or 6.
    """
    if dof not in (4, 6):
        raise ValueError(f"pose graph dof must be 4 or 6, got {dof}")
    graph.check()
    dtype = graph.positions.dtype
    held = held_vertices(graph, fixed)
    covariance = torch.linalg.inv(graph.edge_information.to(dtype))
    factor = (BetweenFactor if dof == 6 else YawBetweenFactor)(
        _GROUP,
        graph.edge_index[:, 0],
        graph.edge_index[:, 1],
        graph.edge_rotations.to(dtype)[None],
        graph.edge_translations.to(dtype)[None],
        covariance[None],
        kernel=robust,
    )
    values = pack_pose(graph.positions, graph.rotations)[None]
    kind = "se3" if dof == 6 else YAW_POSITION
    return Problem({_GROUP: (kind, values)}, [factor], fixed={_GROUP: held})


def _subgraph_2d(
    graph: PoseGraph2D,
    count: int,
    poses: torch.Tensor,
    landmarks: torch.Tensor,
    entered: torch.Tensor,
) -> PoseGraph2D:
    """The first ``count`` vertices of a planar graph with the edges among them, their
    sightings and the landmarks ``entered`` (L,) bool, at ``poses`` (count, 3) and
    ``landmarks`` (L, 2); without FIX ids (the caller names the held rows)."""
    keep_edge = (graph.edge_index < count).all(-1)
    keep_seen = graph.observation_index[:, 0] < count
    rows = torch.nonzero(entered).squeeze(-1)
    renumber = torch.full_like(entered, -1, dtype=torch.int64)
    renumber[rows] = torch.arange(rows.numel(), device=rows.device)
    seen = graph.observation_index[keep_seen]
    return dataclasses.replace(
        graph,
        vertex_ids=graph.vertex_ids[:count],
        positions=poses[:, 0:2].clone(),
        headings=poses[:, 2].clone(),
        edge_index=graph.edge_index[keep_edge],
        edge_translations=graph.edge_translations[keep_edge],
        edge_headings=graph.edge_headings[keep_edge],
        edge_information=graph.edge_information[keep_edge],
        edge_lines=None,
        fixed_ids=(),
        landmark_ids=graph.landmark_ids[rows],
        landmark_positions=landmarks[rows].clone(),
        observation_index=torch.stack((seen[:, 0], renumber[seen[:, 1]]), -1),
        observation_bearings=graph.observation_bearings[keep_seen],
        observation_ranges=graph.observation_ranges[keep_seen],
        observation_sigmas=graph.observation_sigmas[keep_seen],
        observation_lines=None,
    )


def incremental_start(
    graph: PoseGraph2D,
    chunk: int = 200,
    robust: RobustKernel | None = None,
    max_solves: int = 10,
    relative_tolerance: float = 1e-3,
    progress: Callable[[int, int], None] | None = None,
    fixed: Sequence[int] | torch.Tensor | None = None,
) -> tuple[PoseGraph2D, int]:
    """A start for a planar graph whose own start (odometry chained from the first pose) is
    too far from the optimum for LM to find it: the graph grown ``chunk`` vertices at a time
    in id order (time order for a run), each prefix solved by a short LM warm-started from
    the previous one, as an incremental smoother would.

    New vertices keep their pose relative to the last solved vertex as the graph's own
    start has it (for an odometry chain: the odometry); a landmark enters with the vertex
    of its first sighting and keeps its position relative to it (for a landmark placed by
    that sighting: the measured bearing and range). The held vertices (``fixed``, as in
    :func:`optimize_pose_graph`: default the file's ``FIX`` vertices, else the first) enter
    at their own poses and stay there; a prefix without one holds its first vertex. Edges
    enter once both ends have. On
    ``victoria_park.txt`` LM from the file's start stops at cost 105,099 (GTSAM's LM too:
    a local minimum whose repeated passes do not overlap), LM from this start at 2,339.2,
    the minimum GTSAM's ISAM2 followed by LM reaches.

    Args:
        graph: the planar graph (its poses and landmarks are the start to grow from).
        chunk: vertices added per step; smaller is slower and more robust (on
            victoria_park.txt 100, 200 and 1000 reach 2,339.2, 500 a minimum at 2,869.9).
        robust: kernel on every edge and sighting of the prefix solves, or None.
        max_solves, relative_tolerance: the short LM per prefix (GTSAM's damping rule).
        progress: called with (vertices placed, N) after each step, or None.
        fixed: row indices of the held vertices, or None (the file's ``FIX``, else row 0).

    Returns:
        a copy of ``graph`` with the grown poses and landmarks (landmarks never sighted
        keep theirs), and the number of linear solves spent.

    Raises:
        ValueError: ``chunk`` or ``max_solves`` below 1, or a fixed row outside ``[0, N)``.
    """
    if chunk < 1 or max_solves < 1:
        raise ValueError(f"chunk and max_solves must be >= 1, got {chunk} and {max_solves}")
    graph.check()
    n = graph.num_vertices
    held = held_vertices(graph, fixed)
    start = torch.cat((graph.positions, graph.headings[:, None]), -1)
    poses = start.clone()
    landmarks = graph.landmark_positions.clone()
    sightings = graph.observation_index
    first = torch.full((graph.num_landmarks,), n, dtype=torch.int64, device=start.device)
    first.scatter_reduce_(0, sightings[:, 1], sightings[:, 0], reduce="amin")
    sighted = first < n
    anchor = start[first.clamp(max=max(n - 1, 0))]
    local = transform_points(inverse(anchor), landmarks[:, None, :])[:, 0]
    config = pose_graph_config(
        max_iterations=max_solves, relative_tolerance=relative_tolerance, planar=True
    )
    solves, done = 0, 0
    while done < n:
        upto = min(n, done + chunk)
        if done:
            relative = between(start[done - 1].expand(upto - done, 3), start[done:upto])
            carried = compose(poses[done - 1].expand(upto - done, 3), relative)
            poses[done:upto] = torch.where(held[done:upto, None], start[done:upto], carried)
        new = sighted & (first >= done) & (first < upto)
        landmarks[new] = transform_points(poses[first[new]], local[new][:, None, :])[:, 0]
        prefix = _subgraph_2d(graph, upto, poses[:upto], landmarks, sighted & (first < upto))
        rows = torch.nonzero(held[:upto]).squeeze(-1)
        result = optimize_pose_graph(
            prefix, robust=robust, config=config, fixed=rows if rows.numel() else (0,)
        )
        solves += result.iterations
        poses[:upto, 0:2] = result.graph.positions
        poses[:upto, 2] = result.graph.headings
        landmarks[sighted & (first < upto)] = result.graph.landmark_positions
        done = upto
        if progress is not None:
            progress(done, n)
    grown = dataclasses.replace(
        graph,
        positions=poses[:, 0:2].clone(),
        headings=poses[:, 2].clone(),
        landmark_positions=landmarks,
    )
    return grown, solves


def optimize_pose_graph(
    graph: PoseGraph | PoseGraph2D,
    robust: RobustKernel | None = None,
    config: LMConfig | None = None,
    fixed: Sequence[int] | torch.Tensor | None = None,
    dof: int = 6,
    start: str = "file",
    chunk: int = 200,
    progress: Callable[[int, int], None] | None = None,
) -> PoseGraphResult:
    """Optimise the vertex poses of a pose graph by Levenberg-Marquardt (GTSAM's cost).

    Args:
        graph: N vertices (the initial estimate), E edges; any device (CUDA works with the
            sparse solver). A :class:`~msf_torch.io.g2o_2d.PoseGraph2D` is solved over
            planar poses (:mod:`msf_torch.backend.posegraph2d`).
        robust: kernel on every edge (e.g. ``RobustKernel("cauchy", 1.0)``), or None.
        config: LM settings; default :func:`pose_graph_config` (``planar=True`` for a
            2-D graph).
        fixed: row indices of the vertices held constant (gauge); default (None) the
            vertices the file's ``FIX`` records name (``graph.fixed_ids``), else the first.
        dof: 6 (full poses) or 4 (x, y, z and yaw move; every vertex keeps its roll and
            pitch: visual-inertial graphs).
        start: ``"file"`` (default: LM from the graph's own poses, GTSAM's start) or, for a
            2-D graph, ``"incremental"``: LM from :func:`incremental_start` (grown ``chunk``
            vertices at a time; ``progress`` as there), for runs with long loops whose
            chained start LM cannot recover from.

    Returns:
        :class:`PoseGraphResult`; the input graph is not modified.

    Raises:
        ValueError: a malformed graph, bad ``fixed`` indices, ``dof`` not 4 or 6,
            ``dof=4`` for a 2-D graph, or an unknown ``start`` (``"incremental"`` for a
            3-D graph).
    """
    planar = isinstance(graph, PoseGraph2D)
    config = config or pose_graph_config(planar=planar)
    began = time.perf_counter()
    if planar and dof != 6:
        raise ValueError(f"a 2-D pose graph has 3-dof poses; dof={dof} is for 3-D graphs")
    if start not in ("file", "incremental") or (start == "incremental" and not planar):
        raise ValueError(
            f"start must be 'file', or 'incremental' for a 2-D graph; got {start!r} for a "
            f"{'2' if planar else '3'}-D graph"
        )
    file_cost = None
    if start == "incremental":
        with torch.no_grad():
            problem = pose_graph_2d_problem(graph, robust, fixed, _GROUP)
            file_cost = float(problem.cost(problem.values)[0])
            grown, _ = incremental_start(graph, chunk, robust, progress=progress, fixed=fixed)
        problem = pose_graph_2d_problem(grown, robust, fixed, _GROUP)
    elif planar:
        problem = pose_graph_2d_problem(graph, robust, fixed, _GROUP)
    else:
        problem = pose_graph_problem(graph, robust, fixed, dof)
    with torch.no_grad():
        result = solve(problem, config)
    solved_values = result.values[_GROUP][0]
    if planar:
        landmarks = result.values.get(LANDMARK_GROUP)
        solved = dataclasses.replace(
            graph,
            positions=solved_values[:, 0:2].clone(),
            headings=solved_values[:, 2].clone(),
            landmark_positions=graph.landmark_positions
            if landmarks is None
            else landmarks[0].clone(),
        )
    else:
        position, rotation = unpack_pose(solved_values)
        solved = dataclasses.replace(graph, rotations=rotation.clone(), positions=position.clone())
    start_cost = float(result.initial_cost[0])
    initial_cost = start_cost if file_cost is None else file_cost
    final_cost = float(result.cost[0])
    seconds = time.perf_counter() - began
    log = [
        {
            "cost": float(entry["cost"][0]),
            "step_norm": float(entry["step_norm"][0]),
            "damping": float(entry["damping"][0]),
            "accepted": bool(entry["accepted"][0]),
        }
        for entry in result.log
    ]
    return PoseGraphResult(
        graph=solved,
        initial_cost=initial_cost,
        final_cost=final_cost,
        iterations=int(result.iterations[0]),
        seconds=seconds,
        status=result.status[0],
        log=log,
        start=start,
        start_cost=start_cost,
    )
