"""PyPose peer for nav-state windows: ``pypose.optim.LM`` on one problem at a time.

The window a PyPose user would write as an ``nn.Module``:

* parameters: the K keyframe poses as one ``pp.Parameter`` of ``pp.SE3`` LieTensors
  (``[p, q_xyzw]``; PyPose retracts them with its own SE3 retraction) and the velocities
  and biases as one ``nn.Parameter`` (K, 9) ``[v, b_g, b_a]`` (m/s, rad/s, m/s^2);
* ``forward`` packs them into our nav-state layout
  (:func:`~msf_torch.backend.variables.pack_nav_state`) and returns the Problem's whitened
  residuals ``W r`` of every factor, flattened: PyPose's loss ``sum |W r|^2`` is twice the
  Problem's cost (costs here are halved into GTSAM's convention);
* ``pp.optim.LM`` with its Cholesky solver and its default damping strategy: dense Jacobian
  by reverse-mode autodiff over the module (``modjac``), ``J^T J`` damped as PyPose does.

What is compared is PyPose's machinery (autodiff linearisation, dense normal equations,
its LM loop) on the same cost, not the problem. PyPose has no batch-of-problems LM (one
module is one least-squares problem; stacking B windows into one module would make a dense
Jacobian of B R rows by B n columns), so the windows are solved one by one, like GTSAM.

Stopping: the outer loop (one ``optimizer.step``, which retries rejected steps inside)
stops when a step lowers the cost by at most ``relative_tolerance`` times the cost (GTSAM's
rule, as :mod:`benchmarks.peers.pypose_posegraph`), or after ``max_iterations`` steps.
"""

from __future__ import annotations

__all__ = ["window_module", "solve_pypose_window"]

import time
from typing import Any

import torch

from benchmarks.peers.pypose_posegraph import step_lm
from msf_torch.backend.problem import Problem
from msf_torch.backend.variables import pack_nav_state, unpack_nav_state
from msf_torch.geometry.quaternion import matrix_to_quat


def window_module(problem: Problem) -> Any:
    """The window as a PyPose user writes it: an ``nn.Module`` whose ``forward()`` returns
    the whitened residuals (R,) of every factor of ``problem`` (B = 1, one free ``nav_state``
    group), with parameters ``pose`` (a ``pp.Parameter`` of K ``pp.SE3``) and ``rest``
    (K, 9) ``[v, b_g, b_a]`` at the problem's values; ``states()`` gives them as (1, K, 21)
    nav states."""
    import pypose as pp
    from torch import nn

    if problem.batch_size != 1 or len(problem.values) != 1 or problem.fixed:
        raise ValueError("the PyPose peer solves one problem with one free variable group")
    ((group, values),) = problem.values.items()
    if problem.kinds[group].name != "nav_state":
        raise ValueError(f"the PyPose peer maps nav_state variables, not {group!r}")
    position, velocity, rotation, gyro_bias, accel_bias = unpack_nav_state(values[0])
    quaternion = matrix_to_quat(rotation)  # [w, x, y, z]

    class Window(nn.Module):
        """Whitened residuals (R,) of every factor of the window."""

        def __init__(self) -> None:
            super().__init__()
            lie = torch.cat((position, quaternion[:, 1:], quaternion[:, :1]), -1)
            self.pose = pp.Parameter(pp.SE3(lie))
            self.rest = nn.Parameter(torch.cat((velocity, gyro_bias, accel_bias), -1))

        def states(self) -> torch.Tensor:
            """(1, K, 21) nav states from the parameters."""
            # through PyPose's group action, whose Jacobians are on the Lie algebra it
            # retracts with (reading the storage would give Jacobians by the quaternion's
            # components, which its update does not follow): origin and axes of each pose
            count = self.pose.shape[0]
            unit = torch.eye(3, dtype=self.rest.dtype, device=self.rest.device)
            points = torch.cat((torch.zeros_like(unit[:1]), unit))[None].expand(count, 4, 3)
            moved = self.pose[:, None].Act(points)  # (K, 4, 3)
            translation = moved[:, 0]
            rotation = (moved[:, 1:] - translation[:, None]).mT
            rest = self.rest
            states = pack_nav_state(translation, rest[:, 0:3], rotation, rest[:, 3:6], rest[:, 6:9])
            return states[None]

        def forward(self, _: Any = None) -> torch.Tensor:
            parts = problem.whitened({group: self.states()}, jacobians=False)
            return torch.cat([white.reshape(-1) for white, _, _ in parts])

    return Window()


def solve_pypose_window(
    problem: Problem, relative_tolerance: float, max_iterations: int
) -> dict[str, Any]:
    """Solve one window (a Problem with B = 1 and one free ``nav_state`` group) by PyPose's LM.

    Returns:
        ``values`` (1, K, 21) nav states in our layout, ``initial_cost`` and ``final_cost``
        (GTSAM convention, 0.5 sum of whitened squares), ``iterations`` (optimizer steps)
        and ``wall_s`` (module and optimizer construction plus the steps).
    """
    import pypose as pp

    start = time.perf_counter()
    module = window_module(problem)
    optimizer = pp.optim.LM(module, solver=pp.optim.solver.Cholesky())
    with torch.no_grad():
        initial = 0.5 * float(module().square().sum())
    costs = step_lm(optimizer, None, initial, relative_tolerance, max_iterations)
    wall = time.perf_counter() - start
    with torch.no_grad():
        solved = module.states().detach()
    return {
        "values": solved,
        "initial_cost": initial,
        "final_cost": costs[-1] if costs else initial,
        "iterations": len(costs),
        "wall_s": wall,
    }
