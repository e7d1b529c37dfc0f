"""Adaptive noise (frontend/adaptive.py) against closed forms and hand-computed recursions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.frontend.adaptive import (
    clipped_outer,
    fading_factor,
    forgetting_weight,
    project_positive_definite,
    sage_husa_update,
    update_innovation_covariance,
)

DTYPE = torch.float64


def _random_spd(gen: torch.Generator, batch: int, size: int, scale: float = 1.0) -> torch.Tensor:
    a = torch.randn(batch, size, size, generator=gen, dtype=DTYPE)
    return scale * (a @ a.mT + size * torch.eye(size, dtype=DTYPE))


@pytest.mark.parametrize("prior_count", [0.0, 7.0])
def test_forgetting_recursion_is_the_weighted_mean(prior_count):
    """Mixing with d_k reproduces sum_j b^(n-1-j) X_j / sum_j b^(n-1-j), prior worth k0."""
    b = 0.97
    rng = np.random.default_rng(0)
    prior = rng.normal(size=(4, 2, 2))
    samples = rng.normal(size=(25, 4, 2, 2))
    estimate = torch.as_tensor(prior)
    for k in range(len(samples)):
        d = forgetting_weight(torch.full((4,), float(k), dtype=DTYPE), b, prior_count)
        estimate = (1 - d[:, None, None]) * estimate + d[:, None, None] * torch.as_tensor(
            samples[k]
        )
    n = len(samples)
    ages = np.arange(n - 1, -1, -1)  # sample j has age n - 1 - j
    prior_weight = sum(b ** (n + i) for i in range(int(prior_count)))  # k0 copies, older
    weights = b**ages
    expected = (prior_weight * prior + np.einsum("j,jbxy->bxy", weights, samples)) / (
        prior_weight + weights.sum()
    )
    np.testing.assert_allclose(estimate.numpy(), expected, rtol=1e-12, atol=1e-12)


def test_forgetting_weight_values_and_checks():
    d = forgetting_weight(torch.tensor([0.0, 1.0, 1e6], dtype=DTYPE), 0.95)
    np.testing.assert_allclose(d.numpy(), [1.0, 0.05 / (1 - 0.95**2), 0.05], rtol=1e-12)
    with pytest.raises(ValueError, match="forgetting"):
        forgetting_weight(torch.zeros(1), 1.0)
    with pytest.raises(ValueError, match="prior_count"):
        forgetting_weight(torch.zeros(1), 0.9, -1.0)


def test_innovation_covariance_closed_form():
    b = 0.96
    gen = torch.Generator().manual_seed(1)
    nus = torch.randn(30, 3, 2, generator=gen, dtype=DTYPE)
    v = torch.zeros(3, 2, 2, dtype=DTYPE)
    for k in range(30):
        v = update_innovation_covariance(v, nus[k], torch.full((3,), float(k), dtype=DTYPE), b)
    weights = b ** torch.arange(29, -1, -1, dtype=DTYPE)
    outer = nus[:, :, :, None] * nus[:, :, None, :]
    expected = (weights[:, None, None, None] * outer).sum(0) / weights.sum()
    torch.testing.assert_close(v, expected, rtol=1e-12, atol=1e-12)


def test_clipped_outer_caps_the_nis():
    gen = torch.Generator().manual_seed(2)
    s = _random_spd(gen, 5, 3)
    nu = 10.0 * torch.randn(5, 3, generator=gen, dtype=DTYPE)
    nu[0] *= 1e-3  # below the clip: untouched
    out = clipped_outer(nu, s, max_nis=9.0)
    nis_raw = (nu[:, None, :] @ torch.linalg.solve(s, nu[..., None]))[:, 0, 0]
    # s nu nu^T has "NIS" tr(S^-1 s nu nu^T) = s NIS
    nis_out = torch.einsum("bij,bji->b", torch.linalg.inv(s), out)
    expected = torch.minimum(nis_raw, torch.tensor(9.0, dtype=DTYPE))
    torch.testing.assert_close(nis_out, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out[0], nu[0, :, None] * nu[0, None, :])
    with pytest.raises(ValueError, match="innovation_cov"):
        clipped_outer(nu, None, 9.0)


def test_fading_factor_hand_computed():
    v = torch.tensor([[4.0, 1.0], [1.0, 6.0]], dtype=DTYPE)
    m = torch.tensor([[1.0, 0.2], [0.2, 1.0]], dtype=DTYPE)
    r = torch.tensor([[0.5, 0.0], [0.0, 0.5]], dtype=DTYPE)
    hqh = torch.tensor([[0.25, 0.0], [0.0, 0.25]], dtype=DTYPE)
    # N = V - HQH^T - beta R: trace 10 - 0.5 - 2 * 1.0 = 7.5; tr M = 2
    lam = fading_factor(v, m, r, hqh, softening=2.0)
    assert float(lam) == pytest.approx(3.75, rel=1e-14)
    # a consistent filter (V = M + HQH^T + R) keeps lambda at 1
    assert float(fading_factor(m + hqh + r, m, r, hqh)) == pytest.approx(1.0, rel=1e-14)
    # batched; tr M = 0 -> 1
    batch = fading_factor(
        torch.stack((v, v)), torch.stack((m, torch.zeros_like(m))), torch.stack((r, r))
    )
    np.testing.assert_allclose(batch.numpy(), [(10.0 - 1.0) / 2.0, 1.0], rtol=1e-14)


def test_projection_is_the_nearest_matrix_above_the_floor():
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(6, 3, 3, generator=gen, dtype=DTYPE)
    a = a + a.mT
    a[0] = _random_spd(gen, 1, 3)[0]  # already above the floor: unchanged
    floor = torch.tensor(0.3, dtype=DTYPE)
    out = project_positive_definite(a, floor)
    torch.testing.assert_close(out[0], a[0], rtol=0, atol=0)
    for k in range(1, 6):
        values, vectors = np.linalg.eigh(a[k].numpy())
        expected = vectors @ np.diag(np.maximum(values, 0.3)) @ vectors.T
        np.testing.assert_allclose(out[k].numpy(), expected, atol=1e-12)
    assert float(torch.linalg.eigvalsh(out).min()) >= 0.3 - 1e-12
    # per-element floors broadcast
    floors = torch.linspace(0.1, 0.6, 6, dtype=DTYPE)
    per = project_positive_definite(a, floors)
    assert bool((torch.linalg.eigvalsh(per).min(-1).values >= floors - 1e-12).all())


def test_sage_husa_recursion_without_projection():
    """While the estimate stays above the floor, R_n is the closed-form weighted mean."""
    b, k0 = 0.95, 4.0
    gen = torch.Generator().manual_seed(4)
    prior = _random_spd(gen, 2, 2, 0.5)
    hph = 0.01 * _random_spd(gen, 2, 2)
    nus = 3.0 * torch.randn(20, 2, 2, generator=gen, dtype=DTYPE)
    r = prior.clone()
    for k in range(20):
        r = sage_husa_update(
            r, nus[k], hph, torch.full((2,), float(k), dtype=DTYPE), b, torch.tensor(1e-6), k0
        )
    n = 20
    samples = nus[:, :, :, None] * nus[:, :, None, :] - hph
    weights = b ** torch.arange(n - 1, -1, -1, dtype=DTYPE)
    prior_weight = sum(b ** (n + i) for i in range(int(k0)))
    expected = (prior_weight * prior + (weights[:, None, None, None] * samples).sum(0)) / (
        prior_weight + weights.sum()
    )
    assert float(torch.linalg.eigvalsh(expected).min()) > 1e-6  # projection never acted
    torch.testing.assert_close(r, expected, rtol=1e-12, atol=1e-12)


def test_sage_husa_stays_positive_definite_and_projects():
    """nu = 0 with a large H P H^T drives the raw recursion negative: the floor holds."""
    prior = torch.eye(2, dtype=DTYPE)[None]
    hph = 10.0 * torch.eye(2, dtype=DTYPE)[None]
    out = sage_husa_update(
        prior, torch.zeros(1, 2, dtype=DTYPE), hph, torch.zeros(1), 0.9, torch.tensor(0.05)
    )
    # raw: (1 - 1) * I + 1 * (0 - 10 I) = -10 I -> projected to 0.05 I
    torch.testing.assert_close(out, 0.05 * torch.eye(2, dtype=DTYPE)[None])


def test_sage_husa_converges_to_the_true_noise():
    """Scalar random walk observed directly; nominal R = 1, true R = 4: R_hat -> 4 (+-10%)."""
    rng = np.random.default_rng(5)
    q_true, r_true = 0.01, 4.0
    x_true, x, p, r_hat = 0.0, 0.0, 1.0, torch.ones(1, 1, 1, dtype=DTYPE)
    estimates = []
    for k in range(3000):
        x_true += rng.normal(0.0, np.sqrt(q_true))
        z = x_true + rng.normal(0.0, np.sqrt(r_true))
        p_pred = p + q_true
        nu = torch.tensor([[z - x]], dtype=DTYPE)
        r_hat = sage_husa_update(
            r_hat,
            nu,
            torch.tensor([[[p_pred]]], dtype=DTYPE),
            torch.tensor([float(k)]),
            0.99,
            torch.tensor(1e-3),
            prior_count=20.0,
        )
        gain = p_pred / (p_pred + float(r_hat))
        x += gain * float(nu)
        p = (1 - gain) * p_pred
        estimates.append(float(r_hat))
    assert np.mean(estimates[1000:]) == pytest.approx(r_true, rel=0.1)


def test_strong_tracking_recovers_from_a_jump_faster():
    """Constant-level model with tiny Q; the level jumps by 10 sigma. The fading factor
    (b = 0.95) pulls the estimate to the new level several times faster than the plain KF."""
    rng = np.random.default_rng(6)
    r, q = 1.0, 1e-6
    z = rng.normal(0.0, 1.0, 400)
    z[200:] += 10.0
    errors = {}
    for strong in (False, True):
        x, p, v = 0.0, 1.0, torch.zeros(1, 1, dtype=DTYPE)
        err = []
        for k in range(400):
            p_phi = p  # Phi = 1
            nu = torch.tensor([z[k] - x], dtype=DTYPE)
            v = update_innovation_covariance(v, nu, torch.tensor(float(k)), 0.95)
            lam = 1.0
            if strong:
                lam = float(
                    fading_factor(
                        v, torch.tensor([[p_phi]]), torch.tensor([[r]]), torch.tensor([[q]])
                    )
                )
            p_pred = lam * p_phi + q
            gain = p_pred / (p_pred + r)
            x += gain * float(nu)
            p = (1 - gain) * p_pred
            err.append(abs(x - (10.0 if k >= 200 else 0.0)))
        errors[strong] = np.array(err)
    assert errors[True][215:235].mean() < 0.3 * errors[False][215:235].mean()
    assert errors[True][:200].mean() < 0.6  # before the jump it still averages


def test_gradients_through_both_branches():
    gen = torch.Generator().manual_seed(7)
    prior = _random_spd(gen, 2, 2, 0.2).requires_grad_()
    nu = torch.randn(2, 2, generator=gen, dtype=DTYPE, requires_grad=True)
    hph = torch.stack((0.01 * torch.eye(2, dtype=DTYPE), 50.0 * torch.eye(2, dtype=DTYPE)))

    def fn(prior_, nu_):
        return sage_husa_update(prior_, nu_, hph, torch.ones(2), 0.95, torch.tensor(0.05), 3.0)

    out = fn(prior, nu)
    assert float(torch.linalg.eigvalsh(out[1].detach()).min()) == pytest.approx(0.05)  # projected
    assert torch.autograd.gradcheck(fn, (prior, nu), eps=1e-7, atol=1e-6)
    # repeated eigenvalues (s I) on the non-projected branch: finite gradient
    eye_prior = (2.0 * torch.eye(2, dtype=DTYPE))[None].requires_grad_()
    r = sage_husa_update(
        eye_prior,
        torch.zeros(1, 2, dtype=DTYPE),
        0.01 * torch.eye(2, dtype=DTYPE)[None],
        torch.ones(1, dtype=DTYPE),
        0.95,
        torch.tensor(0.05),
    )
    r.sum().backward()
    # no projection there: d sum(R) / d prior = 1 - d_1, with d_1 = (1 - b) / (1 - b^2)
    expected = (1.0 - 0.05 / (1.0 - 0.95**2)) * torch.ones(1, 2, 2, dtype=DTYPE)
    torch.testing.assert_close(eye_prior.grad, expected, rtol=1e-14, atol=0)
