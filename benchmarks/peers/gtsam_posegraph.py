"""GTSAM peer for pose graphs: ``BetweenFactor<Pose3>`` factors solved by GTSAM's
``LevenbergMarquardtOptimizer``.

The factors are built from a :class:`~msf_torch.io.g2o.PoseGraph` (so a prefix of a graph can
be solved too): measured ``Pose3(R_ij, t_ij)`` and ``noiseModel.Gaussian.Information(M)``
with ``M`` the edge information permuted from the PoseGraph's ``[dp, dtheta]`` order into
GTSAM's ``[rot, trans]`` order. ``gtsam_factors`` on a whole file gives the same
``error()`` as ``gtsam.readG2o(path, True)`` (the benchmark records the check). The first
vertex is held by ``NonlinearEqualityPose3`` (zero error while held, so the reported cost
is the between factors' alone).
"""

from __future__ import annotations

__all__ = ["gtsam_factors", "run_gtsam_lm", "count_linear_solves"]

import os
import tempfile
import time
from typing import Any

import numpy as np

from msf_torch.io.g2o import PoseGraph

SWAP = [3, 4, 5, 0, 1, 2]
"""[dp, dtheta] <-> GTSAM's [rot, trans] order of a 6-vector (its own inverse)."""


def gtsam_factors(graph: PoseGraph) -> tuple[Any, Any]:
    """GTSAM ``(NonlinearFactorGraph, Values)`` of the graph's edges and vertex poses."""
    import gtsam

    factors = gtsam.NonlinearFactorGraph()
    ids = graph.vertex_ids.tolist()
    info = graph.edge_information.cpu().numpy()[:, SWAP][:, :, SWAP]
    rot = graph.edge_rotations.cpu().numpy()
    trans = graph.edge_translations.cpu().numpy()
    for k, (a, b) in enumerate(graph.edge_index.tolist()):
        noise = gtsam.noiseModel.Gaussian.Information(info[k])
        measured = gtsam.Pose3(gtsam.Rot3(rot[k]), trans[k])
        factors.add(gtsam.BetweenFactorPose3(ids[a], ids[b], measured, noise))
    values = gtsam.Values()
    rotations, positions = graph.rotations.cpu().numpy(), graph.positions.cpu().numpy()
    for k, vid in enumerate(ids):
        values.insert(vid, gtsam.Pose3(gtsam.Rot3(rotations[k]), positions[k]))
    return factors, values


def _params(relative_tolerance: float, absolute_tolerance: float, max_iterations: int) -> Any:
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(absolute_tolerance)
    params.setMaxIterations(max_iterations)
    return params


def _held(factors: Any, initial: Any, first_id: int) -> Any:
    import gtsam

    held = gtsam.NonlinearFactorGraph(factors)
    held.add(gtsam.NonlinearEqualityPose3(first_id, initial.atPose3(first_id)))
    return held


def run_gtsam_lm(
    factors: Any,
    initial: Any,
    first_id: int,
    relative_tolerance: float = 1e-5,
    absolute_tolerance: float = 1e-5,
    max_iterations: int = 100,
) -> dict[str, Any]:
    """Solve with GTSAM's LM; every other ``LevenbergMarquardtParams`` field at its default
    (lambda 1e-5, factor 10, identity damping, multifrontal Cholesky, COLAMD ordering).

    Args:
        factors, initial: from :func:`gtsam_factors` (or ``gtsam.readG2o``).
        first_id: the vertex held fixed.
        relative_tolerance, absolute_tolerance: GTSAM's ``relativeErrorTol`` and
            ``absoluteErrorTol`` (on the cost decrease of an iteration).
        max_iterations: GTSAM's ``maxIterations`` (outer iterations).

    Returns:
        ``initial_cost``, ``final_cost`` (``0.5 * sum |W r|^2``), ``iterations`` (outer),
        ``wall_s`` (optimizer construction + ``optimize()``), ``positions`` (N, 3) m and
        ``rotations`` (N, 3, 3) numpy arrays in vertex order of ``initial.keys()``.
    """
    held = _held(factors, initial, first_id)
    params = _params(relative_tolerance, absolute_tolerance, max_iterations)
    start = time.perf_counter()
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(held, initial, params)
    result = optimizer.optimize()
    wall = time.perf_counter() - start
    keys = sorted(initial.keys())
    return {
        "initial_cost": factors.error(initial),
        "final_cost": factors.error(result),
        "iterations": optimizer.iterations(),
        "wall_s": wall,
        "positions": np.stack([result.atPose3(k).translation() for k in keys]),
        "rotations": np.stack([result.atPose3(k).rotation().matrix() for k in keys]),
    }


def count_linear_solves(
    factors: Any,
    initial: Any,
    first_id: int,
    relative_tolerance: float = 1e-5,
    absolute_tolerance: float = 1e-5,
    max_iterations: int = 100,
) -> int:
    """Linear solves (lambda tries, accepted or not) of the same run as :func:`run_gtsam_lm`,
    counted from GTSAM's ``TRYLAMBDA`` log (C++ stdout captured through a temporary file;
    not timed)."""
    import gtsam

    held = _held(factors, initial, first_id)
    params = _params(relative_tolerance, absolute_tolerance, max_iterations)
    params.setVerbosityLM("TRYLAMBDA")
    with tempfile.TemporaryFile(mode="w+b") as sink:
        saved = os.dup(1)
        try:
            os.dup2(sink.fileno(), 1)
            gtsam.LevenbergMarquardtOptimizer(held, initial, params).optimize()
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        sink.seek(0)
        text = sink.read().decode(errors="replace")
    return text.count("trying lambda")
