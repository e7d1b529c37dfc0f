"""PyPose peer for pose graphs: ``pypose.optim.LevenbergMarquardt`` in the style of PyPose's
pose-graph example (``examples/module/pgo/pgo.py``).

* nodes are one ``pp.Parameter`` of ``pp.SE3`` LieTensors (``[t, q_xyzw]``); the first pose
  is a buffer (held fixed), as in PyPose's sparse pose-graph docstring example;
* the module returns the whitened Between errors ``W (Z^-1 T_i^-1 T_j).Log()`` (E, 6), with
  ``W`` the upper Cholesky factor of the edge information (``W^T W = M``) in PyPose's
  ``se3`` order ``[rho, phi]``, which is the PoseGraph's ``[dp, dtheta]`` order. Whitening
  inside the module gives the same cost as LM's ``weight=`` argument, which would build a
  dense block-diagonal (6E, 6E) weight matrix (7 GB for sphere2500);
* PyPose 0.9.5's ``sparse=True`` path needs the optional ``bae`` backend (CUDA), so the
  dense path runs: dense Jacobian (``modjac``, reverse mode, vectorised), dense ``J^T J``
  and ``solver.Cholesky``. Its LM damps by ``A_ii (1 + damping)`` (Marquardt scaling);
  strategy ``TrustRegion(radius=1e4)`` as in PyPose's example;
* PyPose's loss is ``sum |W r|^2``; costs here are halved into GTSAM's convention.

Stopping: the outer loop (one ``optimizer.step`` = one accepted step, or up to 16
rejected tries) stops when a step lowers the cost by at most ``relative_tolerance`` times
the cost, GTSAM's rule, or after ``max_iterations`` steps.
"""

from __future__ import annotations

__all__ = ["run_pypose_lm", "dense_sizes", "step_lm"]

import time
from typing import Any

import torch

from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.io.g2o import PoseGraph


def dense_sizes(graph: PoseGraph) -> dict[str, float]:
    """Bytes of PyPose's dense float64 Jacobian (6E, 7(N-1)) and ``J^T J`` for a graph
    (its SE3 LieTensor parameters have 7 storage columns each, one of them zero)."""
    rows = 6 * graph.num_edges
    cols = 7 * (graph.num_vertices - 1)
    return {
        "jacobian_rows": rows,
        "jacobian_cols": cols,
        "jacobian_gb": rows * cols * 8 / 1e9,
        "normal_matrix_gb": cols * cols * 8 / 1e9,
        "jtj_gflop": 2.0 * rows * cols * cols / 1e9,
    }


def _lie(rotation: torch.Tensor, translation: torch.Tensor) -> Any:
    import pypose as pp

    q = matrix_to_quat(rotation)  # [w, x, y, z]
    return pp.SE3(torch.cat((translation, q[..., 1:], q[..., :1]), -1))


def step_lm(
    optimizer: Any, inputs: Any, initial: float, relative_tolerance: float, max_iterations: int
) -> list[float]:
    """Costs (GTSAM's convention, half PyPose's loss) after each ``optimizer.step(inputs)``
    of a PyPose LM, from ``initial``, until a step lowers the cost by at most
    ``relative_tolerance`` times the cost (GTSAM's rule) or ``max_iterations`` steps."""
    costs: list[float] = []
    last = initial
    for _ in range(max_iterations):
        cost = 0.5 * float(optimizer.step(input=inputs))
        costs.append(cost)
        done = last - cost <= relative_tolerance * last
        last = cost
        if done:
            break
    return costs


def run_pypose_lm(
    graph: PoseGraph, relative_tolerance: float = 1e-5, max_iterations: int = 100
) -> dict[str, Any]:
    """Solve a pose graph (vertex 0 fixed) with PyPose's dense LM.

    Returns:
        ``initial_cost``, ``final_cost`` (GTSAM convention), ``iterations`` (optimizer
        steps), ``costs`` (after each step), ``wall_s`` (module and optimizer construction
        plus the steps), ``positions`` (N, 3) m and ``rotations`` (N, 3, 3) tensors.
    """
    import pypose as pp
    from torch import nn

    start = time.perf_counter()
    nodes = _lie(graph.rotations, graph.positions)
    measured = _lie(graph.edge_rotations, graph.edge_translations)
    sqrt_info = torch.linalg.cholesky(graph.edge_information).mT
    edges = graph.edge_index

    class PoseGraphModule(nn.Module):
        """Whitened Between errors of all edges (E, 6)."""

        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("root", nodes[:1].clone())
            self.nodes = pp.Parameter(nodes[1:].clone())

        def forward(self, index: torch.Tensor, relative: Any) -> torch.Tensor:
            poses = torch.cat((self.root, self.nodes), 0)
            error = (relative.Inv() @ poses[index[:, 0]].Inv() @ poses[index[:, 1]]).Log()
            return (sqrt_info @ error.tensor()[..., None]).squeeze(-1)

    module = PoseGraphModule()
    optimizer = pp.optim.LM(
        module,
        solver=pp.optim.solver.Cholesky(),
        strategy=pp.optim.strategy.TrustRegion(radius=1e4),
        min=1e-6,
    )
    with torch.no_grad():
        initial = 0.5 * float(module(edges, measured).square().sum())
    costs = step_lm(optimizer, (edges, measured), initial, relative_tolerance, max_iterations)
    last = costs[-1] if costs else initial
    wall = time.perf_counter() - start
    with torch.no_grad():
        poses = torch.cat((module.root, module.nodes), 0).tensor()
    rotations = quat_to_matrix(torch.cat((poses[:, 6:7], poses[:, 3:6]), -1))
    return {
        "initial_cost": initial,
        "final_cost": last,
        "iterations": len(costs),
        "costs": costs,
        "wall_s": wall,
        "positions": poses[:, :3].clone(),
        "rotations": rotations,
    }
