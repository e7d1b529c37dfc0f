"""Fusion of N IMU posteriors (frontend/imu_fusion.py) against closed forms; PSO on a quadratic."""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.frontend.imu_fusion import (
    disagreement_moments,
    error_compensation_fusion,
    information_fusion,
    particle_swarm_minimize,
    weighted_fusion,
)
from msf_torch.geometry.quaternion import quat_exp, quat_log

DTYPE = torch.float64


def _z_rotations(angles: torch.Tensor) -> torch.Tensor:
    """(..., N) angles about z -> (..., N, 4) quaternions (commuting: the chart is exact)."""
    zeros = torch.zeros_like(angles)
    return quat_exp(torch.stack((zeros, zeros, angles), -1))


def _block_cov(att_var: torch.Tensor, rate_var: torch.Tensor) -> torch.Tensor:
    """(..., N) z-attitude and z-rate variances -> (..., N, 6, 6), other axes variance 1."""
    diag = torch.ones(*att_var.shape, 6, dtype=DTYPE)
    diag[..., 2] = att_var
    diag[..., 5] = rate_var
    return torch.diag_embed(diag)


def test_information_fusion_closed_form_three_imus():
    angles = torch.tensor([[0.10, 0.13, 0.07], [-0.4, -0.38, -0.45]], dtype=DTYPE)
    att_var = torch.tensor([[1.0, 2.0, 4.0], [0.5, 0.5, 3.0]], dtype=DTYPE) * 1e-4
    rates = torch.zeros(2, 3, 3, dtype=DTYPE)
    rates[..., 2] = torch.tensor([[1.0, 1.2, 0.9], [0.0, 0.1, -0.2]], dtype=DTYPE)
    rate_var = torch.tensor([[1.0, 1.0, 2.0], [3.0, 1.0, 1.0]], dtype=DTYPE) * 1e-3
    fused = information_fusion(_z_rotations(angles), rates, _block_cov(att_var, rate_var))
    info = 1.0 / att_var
    expected = (info * angles).sum(-1) / info.sum(-1)
    torch.testing.assert_close(quat_log(fused.quaternion)[:, 2], expected, atol=1e-12, rtol=0)
    rate_info = 1.0 / rate_var
    expected_rate = (rate_info * rates[..., 2]).sum(-1) / rate_info.sum(-1)
    torch.testing.assert_close(fused.rate[:, 2], expected_rate, atol=1e-12, rtol=0)
    torch.testing.assert_close(fused.covariance[:, 2, 2], 1.0 / info.sum(-1), atol=1e-15, rtol=0)


def test_information_fusion_with_full_covariances_is_the_linear_formula():
    """Small angles, correlated 6x6 covariances: the first-order chart formula holds to
    second order in the angles."""
    gen = torch.Generator().manual_seed(0)
    x = 1e-3 * torch.randn(2, 6, generator=gen, dtype=DTYPE)
    a = torch.randn(2, 6, 6, generator=gen, dtype=DTYPE)
    cov = a @ a.mT + 6 * torch.eye(6, dtype=DTYPE)
    fused = information_fusion(quat_exp(x[:, :3]), x[:, 3:], cov)
    info = torch.linalg.inv(cov)
    expected = torch.linalg.solve(info.sum(0), (info @ x[..., None]).sum(0))[:, 0]
    # second-order chart terms ~ |x|^2 = 1e-6; a wrong weighting would miss by ~1e-3
    torch.testing.assert_close(quat_log(fused.quaternion), expected[:3], atol=1e-6, rtol=0)
    torch.testing.assert_close(fused.rate, expected[3:], atol=1e-6, rtol=0)


def test_information_fusion_halves_the_variance_of_two_equal_independent_imus():
    """Monte Carlo: two independent estimates with equal variance fuse to half of it, so
    the RMSE falls by 1 - 1/sqrt(2) = 29.3% and no more (the bound quoted for the bench)."""
    gen = torch.Generator().manual_seed(1)
    sigma = 0.01
    errors = sigma * torch.randn(20000, 2, generator=gen, dtype=DTYPE)
    cov = _block_cov(torch.full((20000, 2), sigma**2, dtype=DTYPE), torch.ones(20000, 2))
    fused = information_fusion(_z_rotations(errors), torch.zeros(20000, 2, 3, dtype=DTYPE), cov)
    rmse_single = float(errors[:, 0].pow(2).mean().sqrt())
    rmse_fused = float(quat_log(fused.quaternion)[:, 2].pow(2).mean().sqrt())
    assert 1 - rmse_fused / rmse_single == pytest.approx(1 - 1 / math.sqrt(2), abs=0.015)


def test_error_compensation_is_bar_shalom_campo_for_two():
    """Per axis, N = 2: x = x1 + (P1 - P12) / (P1 + P2 - 2 P12) (x2 - x1), P12 from C."""
    angles = torch.tensor([[0.20, 0.26]], dtype=DTYPE)
    p1, p2 = 4e-4, 9e-4
    disagreement_z = torch.tensor(6e-4, dtype=DTYPE)  # C = P1 + P2 - 2 P12 -> P12 = 3.5e-4
    cov = _block_cov(torch.tensor([[p1, p2]], dtype=DTYPE), torch.ones(1, 2, dtype=DTYPE))
    c = torch.zeros(1, 2, 2, 6, dtype=DTYPE)
    c[:, 0, 1] = c[:, 1, 0] = 2.0  # other axes: independent (C = P1 + P2)
    c[:, 0, 1, 2] = c[:, 1, 0, 2] = disagreement_z
    fused = error_compensation_fusion(
        _z_rotations(angles), torch.zeros(1, 2, 3, dtype=DTYPE), cov, c
    )
    p12 = 0.5 * (p1 + p2 - 6e-4)
    gain = (p1 - p12) / (p1 + p2 - 2 * p12)
    expected = 0.20 + gain * (0.26 - 0.20)
    assert float(quat_log(fused.quaternion)[0, 2]) == pytest.approx(expected, abs=1e-12)
    blue_var = (p1 * p2 - p12**2) / (p1 + p2 - 2 * p12)
    assert float(fused.covariance[0, 2, 2]) == pytest.approx(blue_var, rel=1e-10)
    # independent axes (C = P1 + P2): inverse-variance weights (here 1/2 each)
    assert float(fused.covariance[0, 0, 0]) == pytest.approx(0.5, rel=1e-12)


def test_error_compensation_never_extrapolates():
    """P1 << P2 with a strong positive correlation would put the BLUE beyond x1 (weight on
    x2 negative); the weights are clipped to the hull."""
    angles = torch.tensor([[0.0, 0.1]], dtype=DTYPE)
    cov = _block_cov(torch.tensor([[1e-4, 1e-2]], dtype=DTYPE), torch.ones(1, 2, dtype=DTYPE))
    c = torch.full((1, 2, 2, 6), 2.0, dtype=DTYPE)
    c[:, :, :, 2] = 1e-2 * 0.9  # C small against P2: P12 ~ sqrt(P1 P2) * 0.99 (bounded)
    fused = error_compensation_fusion(
        _z_rotations(angles), torch.zeros(1, 2, 3, dtype=DTYPE), cov, c
    )
    assert float(quat_log(fused.quaternion)[0, 2]) == pytest.approx(0.0, abs=1e-12)
    # the fused attitude is x1 on that axis: its variance is P1 (the clipped BLUE's
    # 1 / (1^T Sigma^-1 1) = 2.45e-6 would be 40 times too confident)
    assert float(fused.covariance[0, 2, 2]) == pytest.approx(1e-4, rel=1e-10)


def test_weighted_fusion_per_axis():
    x = 1e-4 * torch.tensor([[1.0, -2.0, 3.0], [3.0, 2.0, -1.0]], dtype=DTYPE)
    rates = torch.tensor([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]], dtype=DTYPE)
    weights = torch.tensor([[1.0, 1.0, 3.0], [1.0, 3.0, 1.0]], dtype=DTYPE)
    fused = weighted_fusion(quat_exp(x), rates, weights)
    norm = weights / weights.sum(0)
    torch.testing.assert_close(fused.rate, (norm * rates).sum(0), atol=1e-14, rtol=0)
    # per-axis weights are linear up to second-order (BCH) terms ~ |x|^2 = 1e-8
    torch.testing.assert_close(quat_log(fused.quaternion), (norm * x).sum(0), atol=1e-7, rtol=0)
    angles = torch.tensor([0.2, 0.4], dtype=DTYPE)
    equal = weighted_fusion(_z_rotations(angles), rates, torch.ones(2, 3, dtype=DTYPE))
    assert float(quat_log(equal.quaternion)[2]) == pytest.approx(0.3, abs=1e-12)


def test_disagreement_moments_closed_form():
    b = 0.9
    gen = torch.Generator().manual_seed(2)
    angles = 0.1 * torch.randn(1, 2, 25, generator=gen, dtype=DTYPE)
    rates = torch.randn(1, 2, 25, 3, generator=gen, dtype=DTYPE)
    moments = disagreement_moments(_z_rotations(angles), rates, b)
    diff = angles[0, 1] - angles[0, 0]
    t = 24
    weights = b ** torch.arange(t, -1, -1, dtype=DTYPE)
    expected = (weights * diff[: t + 1] ** 2).sum() / weights.sum()
    assert float(moments[0, 0, 1, t, 2]) == pytest.approx(float(expected), rel=1e-12)
    rate_diff = rates[0, 1, :, 0] - rates[0, 0, :, 0]
    expected_rate = (weights * rate_diff[: t + 1] ** 2).sum() / weights.sum()
    assert float(moments[0, 1, 0, t, 3]) == pytest.approx(float(expected_rate), rel=1e-12)
    assert float(moments[0, 0, 0].abs().max()) == 0.0


def test_particle_swarm_finds_the_minimum_of_a_quadratic():
    center = torch.tensor([0.3, -1.2, 2.5, 0.0], dtype=DTYPE)
    scale = torch.tensor([1.0, 4.0, 0.5, 2.0], dtype=DTYPE)

    def objective(x: torch.Tensor) -> torch.Tensor:
        return ((x - center) ** 2 * scale).sum(-1) + 7.0

    result = particle_swarm_minimize(
        objective,
        torch.full((4,), -3.0, dtype=DTYPE),
        torch.full((4,), 3.0, dtype=DTYPE),
        particles=40,
        iterations=150,
        generator=torch.Generator().manual_seed(3),
    )
    torch.testing.assert_close(result.position, center, atol=2e-3, rtol=0)
    assert result.value == pytest.approx(7.0, abs=1e-5)
    assert bool((result.history[1:] <= result.history[:-1]).all())
    with pytest.raises(ValueError, match="lower < upper"):
        particle_swarm_minimize(objective, torch.ones(4), torch.zeros(4))


def test_fusion_input_checks():
    with pytest.raises(ValueError, match="N >= 2"):
        information_fusion(torch.ones(1, 4), torch.ones(1, 3), torch.eye(6)[None])
    with pytest.raises(ValueError, match="expected"):
        weighted_fusion(torch.ones(2, 3), torch.ones(2, 3), torch.ones(2, 3))


def test_edge_cases_of_fusion_and_moments() -> None:
    quats = _z_rotations(torch.tensor([[0.1, 0.3]], dtype=DTYPE))
    rates = torch.zeros(1, 2, 3, dtype=DTYPE)
    cov = _block_cov(torch.tensor([[1.0, 1.0]], dtype=DTYPE), torch.ones(1, 2, dtype=DTYPE))
    with pytest.raises(ValueError, match="passes must be >= 1, got 0"):
        information_fusion(quats, rates, cov, passes=0)
    # no samples yet: no moments, of the right shape
    empty = disagreement_moments(
        torch.zeros(2, 3, 0, 4, dtype=DTYPE), torch.zeros(2, 3, 0, 3, dtype=DTYPE), 0.9
    )
    assert empty.shape == (2, 3, 3, 0, 6)
