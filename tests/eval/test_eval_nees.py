"""NEES of exact Gaussian samples and the chi-square interval."""

from __future__ import annotations

import pytest
import torch
from scipy import stats

from msf_torch.eval.nees import average_nees, chi2_interval, fraction_inside, nees

DT = torch.float64


def _gaussian(gen, runs, n, dim):
    """Random SPD covariances (runs, n, D, D) and exact samples e = L z from them."""
    a = torch.randn(runs, n, dim, dim, generator=gen, dtype=DT)
    cov = a @ a.transpose(-1, -2) + 0.1 * torch.eye(dim, dtype=DT)
    chol = torch.linalg.cholesky(cov)
    z = torch.randn(runs, n, dim, 1, generator=gen, dtype=DT)
    return (chol @ z)[..., 0], cov


@pytest.mark.parametrize("dim", [3, 6])
def test_nees_of_exact_samples_averages_to_dim(dim):
    gen = torch.Generator().manual_seed(dim)
    err, cov = _gaussian(gen, 4, 1000, dim)
    values = nees(err, cov)
    assert values.shape == (4, 1000)
    # mean of 4000 chi2(D) draws: std = sqrt(2 D / 4000); allow 5 sigma.
    assert abs(float(values.mean()) - dim) < 5.0 * (2.0 * dim / 4000) ** 0.5
    explicit = (err[..., None, :] @ torch.linalg.inv(cov) @ err[..., None])[..., 0, 0]
    torch.testing.assert_close(values, explicit, atol=1e-9, rtol=1e-9)
    frac = fraction_inside(values, dim, n_runs=1, prob=0.95)
    assert frac.shape == (4,)
    assert abs(float(frac.mean()) - 0.95) < 0.02


def test_average_over_runs_is_consistent():
    gen = torch.Generator().manual_seed(1)
    runs, dim = 25, 3
    err, cov = _gaussian(gen, runs, 400, dim)
    anees = average_nees(nees(err, cov))
    assert anees.shape == (400,)
    assert abs(float(fraction_inside(anees, dim, n_runs=runs, prob=0.95)) - 0.95) < 0.04
    # An overconfident filter (covariance too small by 2x) fails the test clearly.
    over = average_nees(nees(err, 0.5 * cov))
    assert float(fraction_inside(over, dim, n_runs=runs)) < 0.2


def test_mask_skips_padding_and_bad_covariance_raises():
    gen = torch.Generator().manual_seed(2)
    err, cov = _gaussian(gen, 2, 10, 3)
    mask = torch.ones(2, 10, dtype=torch.bool)
    mask[1, 6:] = False
    cov[1, 6:] = 0.0  # padding: not factorisable, must not be touched
    values = nees(err, cov, mask)
    assert bool((values[1, 6:] == 0).all()) and bool((values[mask] > 0).all())
    cov[0, 3] = -torch.eye(3, dtype=DT)
    with pytest.raises(ValueError, match=r"b=0, n=3"):
        nees(err, cov, mask)
    with pytest.raises(ValueError, match="covariance"):
        nees(err, cov[..., :2, :2])
    # average_nees with a mask averages only real runs.
    vals = torch.tensor([[1.0, 2.0], [3.0, 100.0]], dtype=DT)
    m = torch.tensor([[True, True], [True, False]])
    torch.testing.assert_close(average_nees(vals, m), torch.tensor([2.0, 2.0], dtype=DT))


@pytest.mark.parametrize(("dof", "runs", "prob"), [(1, 1, 0.95), (3, 50, 0.95), (15, 10, 0.99)])
def test_chi2_interval_matches_scipy(dof, runs, prob):
    low, high = chi2_interval(dof, runs, prob)
    k = dof * runs
    assert low == pytest.approx(stats.chi2.ppf((1 - prob) / 2, k) / runs, rel=1e-14)
    assert high == pytest.approx(stats.chi2.ppf((1 + prob) / 2, k) / runs, rel=1e-14)
    mass = stats.chi2.cdf(high * runs, k) - stats.chi2.cdf(low * runs, k)
    assert mass == pytest.approx(prob, abs=1e-12)
    with pytest.raises(ValueError):
        chi2_interval(dof, runs, 1.5)
