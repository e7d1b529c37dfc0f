"""Batched Levenberg-Marquardt: batch equals single solves, linear solvers agree, robust
kernels equal GTSAM's M-estimators, and gradients through the solve equal finite
differences."""

from __future__ import annotations

import pytest
import torch

from msf_torch.backend import factors as F
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.robust import KERNELS, RobustKernel
from msf_torch.backend.variables import POINT, pack_pose, unpack_pose
from msf_torch.geometry import so3

DTYPE = torch.float64


def _pose_graph(batch: int, count: int, seed: int, kind: str = "se3", sigma_scale=None):
    """Ring of poses with odometry and two loop closures, B different noise draws."""
    gen = torch.Generator().manual_seed(seed)
    angle = torch.linspace(0, 2 * torch.pi, count + 1, dtype=DTYPE)[:-1]
    position = torch.stack(
        (5 * torch.cos(angle), 5 * torch.sin(angle), 0.3 * torch.sin(3 * angle)), -1
    )
    rotation = so3.exp(
        torch.stack((0.1 * torch.sin(angle), 0.05 * torch.cos(angle), angle + torch.pi / 2), -1)
    )
    index_i = torch.cat((torch.arange(count - 1), torch.tensor([0, 2])))
    index_j = torch.cat((torch.arange(1, count), torch.tensor([count - 1, count // 2])))
    edges = index_i.numel()
    rel_r = rotation[index_i].mT @ rotation[index_j]
    rel_t = (rotation[index_i].mT @ (position[index_j] - position[index_i])[..., None]).squeeze(-1)
    noisy_r = rel_r @ so3.exp(0.02 * torch.randn(batch, edges, 3, generator=gen, dtype=DTYPE))
    noisy_t = rel_t + 0.05 * torch.randn(batch, edges, 3, generator=gen, dtype=DTYPE)
    sigmas = torch.tensor([0.05] * 3 + [0.02] * 3, dtype=DTYPE)
    if sigma_scale is not None:
        sigmas = sigmas * sigma_scale
    cov = torch.diag_embed(sigmas**2).expand(batch, edges, 6, 6)
    factor = F.BetweenFactor("pose", index_i, index_j, noisy_r, noisy_t, cov)
    init_r = rotation @ so3.exp(0.1 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE))
    init_p = position + 0.3 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE)
    init_r[:, 0], init_p[:, 0] = rotation[0], position[0]
    fixed = {"pose": torch.arange(count) == 0}
    return Problem({"pose": (kind, pack_pose(init_p, init_r))}, [factor], fixed)


def _single(problem: Problem, b: int) -> Problem:
    factor = problem.factors[0]
    single = F.BetweenFactor(
        "pose",
        factor.slots[0][1],
        factor.slots[1][1],
        factor.rotation[b : b + 1],
        factor.translation[b : b + 1],
        torch.linalg.inv(
            factor.sqrt_information[b : b + 1].mT @ factor.sqrt_information[b : b + 1]
        ),
    )
    kind = problem.kinds["pose"]
    return Problem({"pose": (kind, problem.values["pose"][b : b + 1])}, [single], problem.fixed)


@pytest.mark.parametrize("linear_solver", ["dense", "sparse"])
def test_batch_equals_single_solves(linear_solver):
    problem = _pose_graph(batch=4, count=12, seed=1)
    # converge on the step (the cost-decrease rule leaves ~1e-8 m of slack in x)
    config = LMConfig(linear_solver=linear_solver, relative_tolerance=0.0, step_tolerance=1e-12)
    batched = solve(problem, config)
    assert all(s == "converged" for s in batched.status)
    for b in range(4):
        alone = solve(_single(problem, b), config)
        torch.testing.assert_close(
            batched.values["pose"][b], alone.values["pose"][0], rtol=0, atol=1e-9
        )
        torch.testing.assert_close(batched.cost[b], alone.cost[0], rtol=1e-12, atol=0)
        if linear_solver == "dense":  # the sparse stack orders round-off differently
            assert int(batched.iterations[b]) == int(alone.iterations[0])


def test_dense_and_sparse_agree_and_reach_a_stationary_point():
    problem = _pose_graph(batch=2, count=10, seed=2, kind="pose")
    dense = solve(problem, LMConfig(linear_solver="dense", relative_tolerance=1e-14))
    sparse = solve(problem, LMConfig(linear_solver="sparse", relative_tolerance=1e-14))
    torch.testing.assert_close(dense.values["pose"], sparse.values["pose"], rtol=0, atol=1e-8)
    lin = problem.linearize(dense.values)
    assert lin.gradient.abs().max() < 1e-5
    assert (dense.cost < dense.initial_cost).all()
    assert len(dense.log) == int(dense.iterations.max())


def test_linear_problem_matches_closed_form_least_squares():
    """Points observed by GNSS-like unary factors with full covariances: the optimum is the
    information-weighted mean, in one Gauss-Newton step."""
    gen = torch.Generator().manual_seed(3)
    batch, points, obs = 3, 4, 5
    measured = torch.randn(batch, points * obs, 3, generator=gen, dtype=DTYPE)
    a = torch.randn(batch, points * obs, 3, 3, generator=gen, dtype=DTYPE)
    cov = a @ a.mT + 0.5 * torch.eye(3, dtype=DTYPE)
    index = torch.arange(points).repeat_interleave(obs)

    class PointObservation(F._Unary):
        def residual(self, values):
            return values[0] - measured

    factor = PointObservation("point", index, cov, None)
    problem = Problem({"point": (POINT, torch.zeros(batch, points, 3, dtype=DTYPE))}, [factor])
    result = solve(problem, LMConfig(linear_solver="dense", relative_tolerance=1e-15))
    info = torch.linalg.inv(cov).reshape(batch, points, obs, 3, 3)
    weighted = (info @ measured.reshape(batch, points, obs, 3, 1)).sum(2)
    expect = torch.linalg.solve(info.sum(2), weighted).squeeze(-1)
    torch.testing.assert_close(result.values["point"], expect, rtol=0, atol=1e-10)


def test_schur_complement_equals_plain_dense_solve():
    """Camera poses and landmarks: eliminating the landmarks gives the same steps."""
    gen = torch.Generator().manual_seed(4)
    poses, landmarks = 4, 30
    position = torch.stack(
        (
            torch.arange(poses, dtype=DTYPE),
            torch.zeros(poses, dtype=DTYPE),
            torch.zeros(poses, dtype=DTYPE),
        ),
        -1,
    )
    rotation = so3.exp(0.05 * torch.randn(poses, 3, generator=gen, dtype=DTYPE))
    points = torch.randn(landmarks, 3, generator=gen, dtype=DTYPE) + torch.tensor(
        [1.5, 0.0, 6.0], dtype=DTYPE
    )
    pose_index = torch.arange(poses).repeat(landmarks)
    point_index = torch.arange(landmarks).repeat_interleave(poses)
    body = (
        rotation[pose_index].mT @ (points[point_index] - position[pose_index])[..., None]
    ).squeeze(-1)
    uv = body[:, :2] / body[:, 2:3] + 0.002 * torch.randn(
        pose_index.numel(), 2, generator=gen, dtype=DTYPE
    )
    eye = torch.eye(3, dtype=DTYPE)
    reprojection = F.ReprojectionFactor(
        "pose",
        pose_index,
        "landmark",
        point_index,
        uv[None],
        (0.002**2 * torch.eye(2, dtype=DTYPE)).expand(1, uv.shape[0], 2, 2),
        eye,
        torch.zeros(3, dtype=DTYPE),
        kernel=RobustKernel("cauchy", 2.0),
    )
    prior = F.PosePriorFactor(
        "pose",
        torch.tensor([0, 1]),
        position[None, :2],
        rotation[None, :2],
        (1e-6 * torch.eye(6, dtype=DTYPE)).expand(1, 2, 6, 6),
    )
    init_pose = pack_pose(
        position + 0.05 * torch.randn(poses, 3, generator=gen, dtype=DTYPE), rotation
    )[None]
    init_points = (points + 0.2 * torch.randn(landmarks, 3, generator=gen, dtype=DTYPE))[None]
    problem = Problem(
        {"pose": ("pose", init_pose), "landmark": (POINT, init_points)}, [reprojection, prior]
    )
    plain = solve(problem, LMConfig(linear_solver="dense", relative_tolerance=1e-14))
    schur = solve(
        problem, LMConfig(linear_solver="dense", eliminate="landmark", relative_tolerance=1e-14)
    )
    for name in ("pose", "landmark"):
        torch.testing.assert_close(schur.values[name], plain.values[name], rtol=0, atol=1e-9)
    torch.testing.assert_close(schur.cost, plain.cost, rtol=1e-10, atol=0)
    recovered, _ = unpack_pose(schur.values["pose"][0])
    assert (recovered - position).norm(dim=-1).max() < 0.1


@pytest.mark.parametrize("name", KERNELS)
def test_robust_kernels_equal_gtsam_m_estimators(name):
    gtsam = pytest.importorskip("gtsam")
    scale = 1.7
    classes = {
        "huber": gtsam.noiseModel.mEstimator.Huber,
        "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
        "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
        "tukey": gtsam.noiseModel.mEstimator.Tukey,
    }
    peer = classes[name].Create(scale)
    kernel = RobustKernel(name, scale)
    errors = torch.tensor([0.0, 0.3, 1.0, 1.69, 1.71, 2.5, 10.0], dtype=DTYPE)
    ours_loss = kernel.loss(errors**2)
    ours_weight = kernel.weight(errors**2)
    for e, loss, weight in zip(
        errors.tolist(), ours_loss.tolist(), ours_weight.tolist(), strict=True
    ):
        assert loss == pytest.approx(peer.loss(e), rel=1e-12, abs=1e-15)
        assert weight == pytest.approx(peer.weight(e), rel=1e-12, abs=1e-15)
    # IRLS weight is rho'(e) / e
    e = errors[1:].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(kernel.loss(e**2).sum(), e)
    torch.testing.assert_close(grad / e.detach(), ours_weight[1:], rtol=1e-12, atol=1e-15)


def test_gradient_through_the_solve_equals_finite_differences():
    """d(sum of optimised positions)/d(odometry sigma scale), unrolled through LM."""
    config = LMConfig(linear_solver="dense", relative_tolerance=1e-15, gradient_steps=10)

    def objective(scale: torch.Tensor) -> torch.Tensor:
        problem = _pose_graph(batch=1, count=8, seed=5, kind="pose", sigma_scale=scale)
        result = solve(problem, config)
        position, _ = unpack_pose(result.values["pose"])
        weights = torch.linspace(-1.0, 2.0, position.numel(), dtype=DTYPE).reshape(position.shape)
        return (weights * position).sum()

    base = torch.tensor([1.0, 1.0, 1.0, 2.0, 2.0, 2.0], dtype=DTYPE)
    scale = base.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(objective(scale), scale)
    step = 1e-5
    for k in (0, 3, 5):
        up, down = base.clone(), base.clone()
        up[k] += step
        down[k] -= step
        numeric = (objective(up) - objective(down)) / (2 * step)
        assert float(grad[k]) == pytest.approx(float(numeric), rel=1e-4, abs=1e-8)
    assert grad.abs().max() > 1e-4


def test_sparse_backends_agree():
    pytest.importorskip("pypardiso")
    problem = _pose_graph(batch=3, count=15, seed=6)
    results = [
        solve(
            problem, LMConfig(linear_solver="sparse", sparse_backend=name, relative_tolerance=1e-14)
        )
        for name in ("pardiso", "cholespy")
    ]
    torch.testing.assert_close(
        results[0].values["pose"], results[1].values["pose"], rtol=0, atol=1e-8
    )
    torch.testing.assert_close(results[0].cost, results[1].cost, rtol=1e-10, atol=0)


def test_block_tridiagonal_solve_equals_dense_cholesky():
    """A chain of nav states (priors, GNSS, between factors only on neighbours) is detected
    as block-tridiagonal; its block Cholesky step equals the full dense Cholesky step."""
    from msf_torch.backend.lm import _solve_block_tridiagonal
    from msf_torch.backend.variables import pack_nav_state

    gen = torch.Generator().manual_seed(8)
    batch, count = 3, 6
    values = pack_nav_state(
        torch.randn(batch, count, 3, generator=gen, dtype=DTYPE),
        torch.randn(batch, count, 3, generator=gen, dtype=DTYPE),
        so3.exp(torch.randn(batch, count, 3, generator=gen, dtype=DTYPE)),
        0.01 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE),
        0.1 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE),
    )
    index = torch.arange(count - 1)
    between = F.BetweenFactor(
        "x",
        index,
        index + 1,
        so3.exp(torch.randn(1, count - 1, 3, generator=gen, dtype=DTYPE)),
        torch.randn(1, count - 1, 3, generator=gen, dtype=DTYPE),
        torch.eye(6, dtype=DTYPE).expand(1, count - 1, 6, 6),
    )
    prior = F.NavStatePriorFactor(
        "x", torch.arange(count), values[:1], torch.eye(15, dtype=DTYPE).expand(1, count, 15, 15)
    )
    problem = Problem({"x": ("nav_state", values)}, [between, prior])
    assert problem.block_tridiagonal_size() == 15
    lin = problem.linearize(problem.values)
    step, ok = _solve_block_tridiagonal(lin.hessian, -lin.gradient, 15)
    expect = torch.linalg.solve(lin.hessian, -lin.gradient[..., None]).squeeze(-1)
    assert bool(ok.all())
    torch.testing.assert_close(step, expect, rtol=1e-9, atol=1e-10)
    loop = Problem(
        {"x": ("nav_state", values)},
        [
            F.BetweenFactor(
                "x",
                torch.tensor([0]),
                torch.tensor([count - 1]),
                between.rotation[:, :1],
                between.translation[:, :1],
                torch.eye(6, dtype=DTYPE).expand(1, 1, 6, 6),
            ),
            prior,
        ],
    )
    assert loop.block_tridiagonal_size() is None


class _StiffPairFactor(Factor):
    """``r = W (x - c)`` on one point, ``W = [[s, s, 0], [1, -1, 0], [0, 0, 1]]``: the sum
    of the first two coordinates is known to 1/s, their difference to 1. With s = 1e10
    the Gauss-Newton matrix ``W^T W`` rounds to a singular one in float64, so Cholesky
    fails at a small damping."""

    def __init__(self, target: torch.Tensor, stiffness: float) -> None:
        self.slots = (("x", torch.zeros(1, dtype=torch.long)),)
        self.sqrt_information = torch.eye(3, dtype=DTYPE)
        self.kernel = None
        self.target = target
        self.weight = torch.tensor(
            [[stiffness, stiffness, 0.0], [1.0, -1.0, 0.0], [0.0, 0.0, 1.0]], dtype=DTYPE
        )

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """(B, 1, 3)."""
        return (values[0] - self.target) @ self.weight.mT

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residual (B, 1, 3) and the constant Jacobian ``W`` (B, 1, 3, 3)."""
        return self.residual(values), [self.weight.expand(values[0].shape[0], 1, 3, 3)]


def test_failed_linear_solve_is_not_convergence():
    """The minimum is ``x = c`` at cost 0 (closed form). A failed Cholesky yields no step;
    the solver used to take that zero step for convergence and return the start as
    'converged'. It must raise the damping and go on: either reach the minimum or say
    that it did not."""
    target = torch.tensor([[[0.3, -0.2, 0.5]]], dtype=DTYPE)
    start = torch.tensor([[[1.0, 2.0, -1.0]]], dtype=DTYPE)
    problem = Problem({"x": ("point", start)}, [_StiffPairFactor(target, 1e10)])
    config = LMConfig(damping="identity", initial_damping=1e-9, max_iterations=30)
    result = solve(problem, config)
    assert float(result.initial_cost[0]) > 1e19
    assert not bool(result.log[0]["accepted"][0])  # the first solve fails
    if result.status[0] == "converged":
        assert float(result.cost[0]) < 1e-12
    else:
        assert float(result.cost[0]) < 1e-6 * float(result.initial_cost[0])
