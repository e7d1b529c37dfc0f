"""The Levenberg-Marquardt iteration itself (gain ratio, Nielsen's damping update, growth on
rejection, acceptance) against a plain-Python re-derivation on a problem small enough to
solve by hand: three decoupled scalar residuals ``atan(x_i) - c_i`` on one point, so the
damped Gauss-Newton system is diagonal and every quantity has a closed form."""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.variables import VariableKind

DTYPE = torch.float64
# (start x_i, target c_i, initial damping): the first case overshoots twice from the flat
# part of atan (rejections, then a gain ratio of 0.11); the second accepts ratios of
# 0.12, 0.33 and 0.76, where Nielsen's cubic differs from any other polynomial.
CASES = [
    ((1.5, -1.0, 0.5), (0.3, -1.1, 0.9), 1e-2),
    ((1.3, 0.2, -0.1), (0.0, 0.0, 0.0), 1e-3),
]
ITERATIONS = 5  # past these the cost is near round-off and the ratio is noise


class _AtanFactor(Factor):
    """``r_i = atan(x_i) - c_i`` on one point variable, unit information."""

    def __init__(self, target: torch.Tensor) -> None:
        self.slots = (("x", torch.zeros(1, dtype=torch.long)),)
        self.sqrt_information = torch.eye(3, dtype=DTYPE)
        self.kernel = None
        self.target = target

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """(B, 1, 3)."""
        return torch.atan(values[0]) - self.target

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind]
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residual (B, 1, 3) and its diagonal Jacobian (B, 1, 3, 3)."""
        return self.residual(values), [torch.diag_embed(1.0 / (1.0 + values[0] ** 2))]


def _reference(
    start: tuple[float, ...], target: tuple[float, ...], config: LMConfig
) -> list[tuple[float, float, bool]]:
    """(damping used, cost after, accepted) per iteration, by hand: Marquardt scaling
    ``D = max(diag H, min_diagonal)``, step ``-g / (H + lambda D)``, gain ratio
    ``rho = (cost - cost_new) / (-g.s - s.H.s / 2)``, and on acceptance Nielsen's
    ``lambda *= max(1/3, 1 - (2 rho - 1)^3)`` (growth reset to 2), else ``lambda *= growth``,
    ``growth *= 2``."""
    x = list(start)
    damping, growth = config.initial_damping, 2.0

    def cost_of(point: list[float]) -> float:
        return 0.5 * sum((math.atan(v) - c) ** 2 for v, c in zip(point, target, strict=True))

    out = []
    for _ in range(config.max_iterations):
        jac = [1.0 / (1.0 + v * v) for v in x]
        res = [math.atan(v) - c for v, c in zip(x, target, strict=True)]
        hess = [j * j for j in jac]
        grad = [j * r for j, r in zip(jac, res, strict=True)]
        step = [
            -g / (h + damping * max(h, config.min_diagonal))
            for g, h in zip(grad, hess, strict=True)
        ]
        predicted = sum(-g * s - 0.5 * h * s * s for g, h, s in zip(grad, hess, step, strict=True))
        candidate = [v + s for v, s in zip(x, step, strict=True)]
        cost, new_cost = cost_of(x), cost_of(candidate)
        accepted = cost - new_cost > 0
        out.append((damping, new_cost if accepted else cost, accepted))
        if accepted:
            rho = (cost - new_cost) / predicted
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            growth = 2.0
            x = candidate
        else:
            damping *= growth
            growth *= 2.0
    return out


@pytest.mark.parametrize(("start", "target", "initial_damping"), CASES)
def test_damping_and_acceptance_follow_nielsen_by_hand(start, target, initial_damping):
    config = LMConfig(
        max_iterations=ITERATIONS,
        initial_damping=initial_damping,
        relative_tolerance=0.0,
        absolute_tolerance=0.0,
        step_tolerance=0.0,
        linear_solver="dense",
    )
    problem = Problem(
        {"x": ("point", torch.tensor([[start]], dtype=DTYPE))},
        [_AtanFactor(torch.tensor(target, dtype=DTYPE))],
    )
    result = solve(problem, config)
    want = _reference(start, target, config)
    assert len(result.log) == ITERATIONS
    for k, (entry, (damping, cost, accepted)) in enumerate(zip(result.log, want, strict=True)):
        assert bool(entry["accepted"][0]) == accepted, k
        assert float(entry["damping"][0]) == pytest.approx(damping, rel=1e-9), k
        assert float(entry["cost"][0]) == pytest.approx(cost, rel=1e-9), k
