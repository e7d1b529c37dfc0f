"""Every back-end factor's Jacobian against central finite differences on its own tangent.

For each factor type, random variables and measurements are drawn, the analytic (or
autodiff) Jacobian of the residual w.r.t. each slot's tangent step is compared with
``(r(x [+] h e_k) - r(x [+] -h e_k)) / 2h``, the retraction being the variable kind's own.
"""

from __future__ import annotations

import pytest
import torch

from msf_torch.backend import factors as F
from msf_torch.backend.preintegration import ImuIntervals, imu_covariance, preintegrate_imu
from msf_torch.backend.problem import Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import (
    POINT,
    pack_nav_state,
    pack_pose,
    unpack_nav_state,
    unpack_pose,
)
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.imu import ImuNoise

DTYPE = torch.float64
B, N = 2, 6


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _nav_states(gen: torch.Generator, count: int = N) -> torch.Tensor:
    def rand(*shape, scale=1.0):
        return scale * torch.randn(*shape, generator=gen, dtype=DTYPE)

    return pack_nav_state(
        rand(B, count, 3, scale=5.0),
        rand(B, count, 3, scale=2.0),
        so3.exp(rand(B, count, 3, scale=1.5)),
        rand(B, count, 3, scale=0.01),
        rand(B, count, 3, scale=0.1),
    )


def _poses(gen: torch.Generator, count: int = N) -> torch.Tensor:
    position = 5.0 * torch.randn(B, count, 3, generator=gen, dtype=DTYPE)
    rotation = so3.exp(1.5 * torch.randn(B, count, 3, generator=gen, dtype=DTYPE))
    return pack_pose(position, rotation)


def _spd(gen: torch.Generator, count: int, dim: int) -> torch.Tensor:
    a = torch.randn(1, count, dim, dim, generator=gen, dtype=DTYPE)
    return a @ a.mT + dim * torch.eye(dim, dtype=DTYPE)


def _check_jacobians(problem: Problem, factor, tol: float = 1e-6) -> None:
    values = problem.gathered(factor, problem.values)
    kinds = factor.kinds
    residual, jacobians = factor.residual_and_jacobians(values, kinds)
    torch.testing.assert_close(residual, factor.residual(values), rtol=0, atol=1e-12)
    step = 1e-6
    for slot, kind in enumerate(kinds):
        assert jacobians[slot].shape == (*residual.shape, kind.tangent_dim)
        for dim in range(kind.tangent_dim):
            moved = []
            for sign in (1.0, -1.0):
                shifted = []
                for k, (value, other) in enumerate(zip(values, kinds, strict=True)):
                    delta = torch.zeros(*value.shape[:-1], other.tangent_dim, dtype=DTYPE)
                    if k == slot:
                        delta[..., dim] = sign * step
                    shifted.append(other.retract(value, delta))
                moved.append(factor.residual(shifted))
            numeric = (moved[0] - moved[1]) / (2 * step)
            scale = 1.0 + numeric.abs().max()
            error = (numeric - jacobians[slot][..., dim]).abs().max() / scale
            assert error < tol, (type(factor).__name__, slot, dim, float(error))


@pytest.mark.parametrize("kind", ["nav_state", "pose", "se3"])
def test_between_factor_jacobians(kind):
    gen = _gen(1)
    values = _nav_states(gen) if kind == "nav_state" else _poses(gen)
    index_i, index_j = torch.tensor([0, 1, 2, 4]), torch.tensor([1, 3, 5, 0])
    rotation = so3.exp(torch.randn(1, 4, 3, generator=gen, dtype=DTYPE))
    translation = torch.randn(1, 4, 3, generator=gen, dtype=DTYPE)
    factor = F.BetweenFactor("x", index_i, index_j, rotation, translation, _spd(gen, 4, 6))
    problem = Problem({"x": (kind, values)}, [factor])
    _check_jacobians(problem, factor)


@pytest.mark.parametrize("kind", ["nav_state", "pose"])
def test_unary_pose_factor_jacobians(kind):
    gen = _gen(2)
    values = _nav_states(gen) if kind == "nav_state" else _poses(gen)
    index = torch.tensor([0, 2, 5])
    prior = F.PosePriorFactor(
        "x",
        index,
        torch.randn(1, 3, 3, generator=gen, dtype=DTYPE),
        so3.exp(torch.randn(1, 3, 3, generator=gen, dtype=DTYPE)),
        _spd(gen, 3, 6),
    )
    gnss = F.GnssFactor(
        "x",
        index,
        torch.randn(1, 3, 3, generator=gen, dtype=DTYPE),
        _spd(gen, 3, 3),
        lever_arm=torch.tensor([0.5, -0.2, 1.1], dtype=DTYPE),
    )
    plane = F.PlaneFactor("x", torch.tensor([0, 1]), torch.tensor([1, 2]), _spd(gen, 2, 3), None)
    wheel = F.WheelOdometryFactor(
        "x",
        torch.tensor([0, 3]),
        torch.tensor([1, 4]),
        torch.randn(1, 2, 3, generator=gen, dtype=DTYPE),
        _spd(gen, 2, 3),
        lever_arm=torch.tensor([-0.3, 0.0, -0.2], dtype=DTYPE),
    )
    # headings within ~0.3 rad of each variable's baseline azimuth (off the residual's wrap)
    baseline = torch.tensor([0.4, 0.9, -0.3], dtype=DTYPE)
    if kind == "nav_state":
        rotation = unpack_nav_state(values[:, index])[2]
    else:
        rotation = unpack_pose(values[:, index])[1]
    world = (rotation @ baseline[:, None])[..., 0]
    measured = torch.atan2(world[..., 0], world[..., 1])
    heading = F.GnssHeadingFactor(
        "x",
        index,
        measured + 0.3 * torch.randn(B, 3, generator=gen, dtype=DTYPE),
        torch.full((1, 3, 1, 1), 0.01**2, dtype=DTYPE),
        baseline,
    )
    problem = Problem({"x": (kind, values)}, [prior, gnss, plane, wheel, heading])
    for factor in problem.factors:
        _check_jacobians(problem, factor)


def test_nav_state_factor_jacobians():
    gen = _gen(3)
    values = _nav_states(gen)
    prior = F.NavStatePriorFactor("x", torch.tensor([1]), _nav_states(gen, 1)[:1], _spd(gen, 1, 15))
    zero = F.ZeroVelocityFactor("x", torch.tensor([2, 3]), _spd(gen, 2, 3), None)
    origin = [_nav_states(gen, 1), _nav_states(gen, 1)]
    sqrt_h = torch.randn(B, 1, 30, 30, generator=gen, dtype=DTYPE)
    marginal = F.MarginalPriorFactor(
        (("x", torch.tensor([4])), ("x", torch.tensor([5]))),
        origin,
        sqrt_h,
        torch.randn(B, 1, 30, generator=gen, dtype=DTYPE),
    )
    nhc = F.NonholonomicFactor(
        "x",
        torch.tensor([0, 5]),
        torch.randn(1, 2, 3, generator=gen, dtype=DTYPE),
        _spd(gen, 2, 2),
        lever_arm=torch.tensor([-0.8, 0.1, -0.3], dtype=DTYPE),
    )
    gnss_velocity = F.GnssVelocityFactor(
        "x",
        torch.tensor([1, 3, 5]),
        torch.randn(B, 3, 3, generator=gen, dtype=DTYPE),
        torch.randn(1, 3, 3, generator=gen, dtype=DTYPE),
        _spd(gen, 3, 3),
        lever_arm=torch.tensor([0.9, -0.2, 1.1], dtype=DTYPE),
    )
    factors = [prior, zero, marginal, nhc, gnss_velocity]
    problem = Problem({"x": ("nav_state", values)}, factors)
    for factor in problem.factors:
        _check_jacobians(problem, factor)


def test_imu_preintegration_factor_jacobians():
    gen = _gen(4)
    count = 3
    samples = 40
    gyro = 0.6 * torch.randn(B, count, samples, 3, generator=gen, dtype=DTYPE)
    accel = torch.randn(B, count, samples, 3, generator=gen, dtype=DTYPE) + torch.tensor(
        [0.0, 0.0, 9.8], dtype=DTYPE
    )
    dt = torch.full((B, count, samples), 0.01, dtype=DTYPE)
    lin_bg = 0.01 * torch.randn(B, count, 3, generator=gen, dtype=DTYPE)
    lin_ba = 0.1 * torch.randn(B, count, 3, generator=gen, dtype=DTYPE)
    pre = preintegrate_imu(ImuIntervals(gyro, accel, dt), lin_bg, lin_ba)
    noise = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (2e-3, 2e-2, 1e-4, 1e-3)))
    cov = imu_covariance(pre, noise)
    values = _nav_states(gen, count + 1)
    index = torch.arange(count)
    factor = F.ImuPreintegrationFactor("x", index, index + 1, pre, cov, gravity_world())
    problem = Problem({"x": ("nav_state", values)}, [factor])
    _check_jacobians(problem, factor)


@pytest.mark.parametrize("intrinsics", [None, (450.0, 455.0, 320.0, 240.0)])
def test_reprojection_factor_jacobians(intrinsics):
    gen = _gen(5)
    poses = _nav_states(gen, 3)
    rotation_cam = so3.exp(torch.tensor([-1.2, 0.1, -1.5], dtype=DTYPE))
    translation_cam = torch.tensor([0.1, -0.05, 0.02], dtype=DTYPE)
    # landmarks 4-9 m in front of each observing camera
    pose_index = torch.tensor([0, 0, 1, 2, 2])
    p, _, r, _, _ = (x[:, pose_index] for x in unpack_nav_state(poses))
    in_cam = torch.tensor(
        [[0.3, -0.2, 5.0], [-1.0, 0.5, 7.0], [0.2, 0.1, 4.0], [1.5, -0.5, 9.0], [0.0, 0.0, 6.0]],
        dtype=DTYPE,
    )
    body = (rotation_cam @ in_cam[..., None]).squeeze(-1) + translation_cam
    world = p + (r @ body[..., None]).squeeze(-1)
    factor = F.ReprojectionFactor(
        "state",
        pose_index,
        "landmark",
        torch.arange(5),
        torch.randn(1, 5, 2, generator=gen, dtype=DTYPE) * 0.01,
        _spd(gen, 5, 2),
        rotation_cam,
        translation_cam,
        intrinsics=intrinsics,
        kernel=RobustKernel("huber", 1.345),
    )
    problem = Problem({"state": ("nav_state", poses), "landmark": (POINT, world)}, [factor])
    _check_jacobians(problem, factor)
