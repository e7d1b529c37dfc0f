"""The back end on CUDA gives the CPU's answers (skipped without a GPU).

cuSOLVER and LAPACK round differently; on this ring graph the solutions agree to about
3e-9 m (measured on an H100), so the cross-device tolerance is 1e-8.
"""

from __future__ import annotations

import pytest
import torch

from msf_torch.backend import factors as F
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.problem import Problem

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _on(problem: Problem, device: str) -> Problem:
    factor = problem.factors[0]
    moved = F.BetweenFactor(
        "pose",
        factor.slots[0][1].to(device),
        factor.slots[1][1].to(device),
        factor.rotation.to(device),
        factor.translation.to(device),
        torch.linalg.inv(factor.sqrt_information.mT @ factor.sqrt_information).to(device),
    )
    values = {"pose": ("se3", problem.values["pose"].to(device))}
    return Problem(values, [moved], {k: v.to(device) for k, v in problem.fixed.items()})


@pytest.mark.parametrize("linear_solver", ["dense", "sparse"])
def test_cuda_solve_equals_cpu(linear_solver):
    from test_backend_lm import _pose_graph

    problem = _pose_graph(batch=8, count=30, seed=9)
    config = LMConfig(
        linear_solver=linear_solver,
        sparse_backend="cholespy",
        relative_tolerance=0.0,
        step_tolerance=1e-12,
    )
    cpu = solve(problem, config)
    gpu = solve(_on(problem, "cuda"), config)
    torch.testing.assert_close(gpu.values["pose"].cpu(), cpu.values["pose"], rtol=0, atol=1e-8)
    torch.testing.assert_close(gpu.cost.cpu(), cpu.cost, rtol=1e-10, atol=0)
