"""The chain fast path of the LM solver on IMU + GNSS + prior windows (keyframe chains).

Block-tridiagonal problems are assembled straight into their diagonal and sub-diagonal
blocks (``Problem.linearize_chain``), the GTSAM-compatible IMU factor contributes its blocks
from its nonzero Jacobian rows, and finished problems are dropped from the batch
(``LMConfig.compact_below``). Each is checked against the general path: the dense Hessian,
the generic per-factor products, the solve without the chain layout or dropping, single
solves, and central differences for the gradient through the solve.
"""

from __future__ import annotations

import torch

from msf_torch.backend.factors import GnssFactor, GtsamImuFactor, NavStatePriorFactor
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.preintegration import (
    ImuIntervals,
    imu_covariance,
    preintegrate_imu_tangent,
)
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.variables import pack_nav_state
from msf_torch.geometry import so3
from msf_torch.sensors.imu import ImuNoise

DTYPE = torch.float64
GRAVITY = torch.tensor([0.0, 0.0, -9.8], dtype=DTYPE)


def _windows(batch: int = 6, count: int = 5, seed: int = 0) -> dict[str, torch.Tensor]:
    """Raw data of ``batch`` windows of ``count`` keyframes 1 s apart: IMU intervals (50
    samples each), initial states scattered more in later windows (so the windows need
    different numbers of iterations), GNSS fixes."""
    gen = torch.Generator().manual_seed(seed)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=DTYPE)

    samples = 50
    gyro = 0.2 * randn(batch, count - 1, 1, 3) + 0.02 * randn(batch, count - 1, samples, 3)
    accel = torch.tensor([0.3, 0.0, 9.8], dtype=DTYPE) + 0.2 * randn(batch, count - 1, samples, 3)
    dt = torch.full((batch, count - 1, samples), 1.0 / samples, dtype=DTYPE)
    spread = torch.linspace(0.05, 1.5, batch, dtype=DTYPE)[:, None, None]
    truth_p = torch.cumsum(torch.full((batch, count, 3), 1.0, dtype=DTYPE), 1)
    return {
        "gyro": gyro,
        "accel": accel,
        "dt": dt,
        "p": truth_p + spread * randn(batch, count, 3),
        "v": torch.ones(batch, count, 3, dtype=DTYPE) + spread * randn(batch, count, 3),
        "R": so3.exp(0.2 * spread * randn(batch, count, 3)),
        "bg": 1e-3 * randn(batch, count, 3),
        "ba": 1e-2 * randn(batch, count, 3),
        "gnss": truth_p + 0.1 * randn(batch, count, 3),
    }


def _problem(data: dict[str, torch.Tensor]) -> Problem:
    """One Problem over the windows of ``data`` (leading dim B): GtsamImuFactor between
    neighbours, GNSS at every keyframe, a nav-state prior on the first."""
    batch, count = data["p"].shape[:2]
    pre = preintegrate_imu_tangent(
        ImuIntervals(data["gyro"], data["accel"], data["dt"]),
        torch.zeros(batch, count - 1, 3, dtype=DTYPE),
        torch.zeros(batch, count - 1, 3, dtype=DTYPE),
        1e-3,
    )
    noise = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (1e-3, 1e-2, 1e-4, 1e-3)))
    values = pack_nav_state(data["p"], data["v"], data["R"], data["bg"], data["ba"])
    keyframes = torch.arange(count)
    sigmas = torch.tensor([1.0] * 6 + [0.1] * 3 + [1e-3] * 3 + [0.1] * 3, dtype=DTYPE)
    factors: list[Factor] = [
        NavStatePriorFactor("x", keyframes[:1], values[:, :1], torch.diag(sigmas**2)[None, None]),
        GnssFactor("x", keyframes, data["gnss"], 0.05 * torch.eye(3, dtype=DTYPE)[None, None]),
        GtsamImuFactor(
            "x", keyframes[:-1], keyframes[1:], pre, imu_covariance(pre, noise), GRAVITY
        ),
    ]
    return Problem({"x": ("nav_state", values)}, factors)


def _subset(data: dict[str, torch.Tensor], index: list[int]) -> dict[str, torch.Tensor]:
    return {k: v[index] for k, v in data.items()}


CONFIG = LMConfig(
    max_iterations=100, relative_tolerance=1e-12, absolute_tolerance=0.0, damping="identity"
)


def _general() -> LMConfig:
    """The general dense path: no chain layout, no dropping of finished problems."""
    return LMConfig(**{**vars(CONFIG), "chain": False, "compact_below": 0.0})


def test_chain_blocks_equal_the_dense_hessian():
    problem = _problem(_windows())
    dense = problem.linearize(problem.values)
    chain = problem.linearize_chain(problem.values)
    batch, count, d = problem.batch_size, 5, 15
    grid = dense.hessian.reshape(batch, count, d, count, d)
    scale = dense.hessian.abs().amax()
    for k in range(count):
        torch.testing.assert_close(
            chain.diagonal[:, k], grid[:, k, :, k], rtol=0, atol=1e-12 * scale
        )
    for k in range(count - 1):
        torch.testing.assert_close(
            chain.lower[:, k], grid[:, k + 1, :, k], rtol=0, atol=1e-12 * scale
        )
    torch.testing.assert_close(chain.gradient, dense.gradient, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(chain.cost, dense.cost, rtol=1e-13, atol=0)


def test_imu_normal_blocks_equal_the_generic_products():
    problem = _problem(_windows())
    factor = problem.factors[2]
    values = problem.gathered(factor, problem.values)
    pairs = [(0, 0), (1, 1), (1, 0), (0, 1)]
    loss, grads, pieces = factor.normal_blocks(values, factor.kinds, pairs)
    ref_loss, ref_grads, ref_pieces = Factor.normal_blocks(factor, values, factor.kinds, pairs)
    assert factor._split_whitening() is not None  # the structured path was taken
    torch.testing.assert_close(loss, ref_loss, rtol=1e-12, atol=0)
    for got, ref in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-10 * ref.abs().amax())

    def whole(parts: list) -> torch.Tensor:
        out = torch.zeros(*loss.shape, 15, 15, dtype=DTYPE)
        for rows, cols, block in parts:
            out[..., rows, cols] += torch.diag_embed(block) if block.dim() == 3 else block
        return out

    for got, ref in zip(pieces, ref_pieces, strict=True):
        expect = whole(ref)
        torch.testing.assert_close(whole(got), expect, rtol=0, atol=1e-11 * expect.abs().amax())


def test_chain_path_with_dropping_equals_the_general_path():
    data = _windows()
    fast = solve(_problem(data), CONFIG)
    general = solve(_problem(data), _general())
    # the windows need different numbers of iterations, so problems were dropped on the way
    assert len(set(fast.iterations.tolist())) > 1
    assert fast.converged.all()
    torch.testing.assert_close(fast.iterations, general.iterations)
    torch.testing.assert_close(fast.values["x"], general.values["x"], rtol=0, atol=1e-9)
    torch.testing.assert_close(fast.cost, general.cost, rtol=1e-12, atol=0)
    assert len(fast.log) == len(general.log)
    for a, b in zip(fast.log, general.log, strict=True):
        torch.testing.assert_close(a["accepted"], b["accepted"])
        torch.testing.assert_close(a["cost"], b["cost"], rtol=1e-10, atol=0)


def test_batch_equals_single_solves():
    data = _windows()
    batch = solve(_problem(data), CONFIG)
    for b in range(data["p"].shape[0]):
        single = solve(_problem(_subset(data, [b])), CONFIG)
        torch.testing.assert_close(single.values["x"][0], batch.values["x"][b], rtol=0, atol=1e-9)
        assert int(single.iterations[0]) == int(batch.iterations[b])


def test_select_equals_the_problem_built_from_the_subset():
    data = _windows()
    problem = _problem(data)
    index = [4, 1, 2]
    picked = problem.select(torch.tensor(index))
    built = _problem(_subset(data, index))
    assert picked.batch_size == 3 and picked.selectable
    torch.testing.assert_close(picked.cost(picked.values), built.cost(built.values))
    torch.testing.assert_close(picked.cost(picked.values), problem.cost(problem.values)[index])
    lin_picked = picked.linearize_chain(picked.values)
    lin_built = built.linearize_chain(built.values)
    torch.testing.assert_close(lin_picked.diagonal, lin_built.diagonal)
    torch.testing.assert_close(lin_picked.lower, lin_built.lower)


def test_gradient_through_the_chain_solve_equals_finite_differences():
    """d(final position sum) / d(one GNSS fix) through the unrolled solve (with problems
    dropped on the way) against central differences of the whole solve."""
    data = _windows(batch=3, count=4, seed=1)
    config = LMConfig(**{**vars(CONFIG), "gradient_steps": 10})

    def objective(fix: torch.Tensor) -> torch.Tensor:
        moved = dict(data)
        gnss = data["gnss"].clone()
        gnss[2, 1] = fix
        moved["gnss"] = gnss
        result = solve(_problem(moved), config)
        return result.values["x"][2, :, 0:3].sum()

    fix = data["gnss"][2, 1].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(objective(fix), fix)
    step = 1e-5
    numeric = torch.zeros(3, dtype=DTYPE)
    with torch.no_grad():
        for axis in range(3):
            delta = torch.zeros(3, dtype=DTYPE)
            delta[axis] = step
            numeric[axis] = (objective(fix + delta) - objective(fix - delta)) / (2 * step)
    torch.testing.assert_close(grad, numeric, rtol=1e-4, atol=1e-6)
