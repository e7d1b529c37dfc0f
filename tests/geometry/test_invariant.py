"""Right-invariant error coordinates (``geometry.invariant``) and the NEES in them.

* ``invariant_difference`` inverts ``invariant_retract`` exactly (1e-12), for errors up to
  a radian of rotation.
* ``invariant_maps`` returns a map and its inverse, and ``T`` is the derivative of the
  conventional error of the retracted state (central differences).
* ``eval.nees.navigation_errors``: a state drawn as ``Exp``-retraction of a Gaussian
  ``xi ~ N(0, P_inv)`` gives a mean invariant NEES of 15 (the chi-square mean) and the
  draws back exactly, while the conventional NEES of the same draws, with a tight lateral
  velocity and a 0.1 rad heading sigma, is far above 15 (the second-order part the
  invariant form avoids).
"""

from __future__ import annotations

import torch

from msf_torch.eval.nees import navigation_errors, nees
from msf_torch.geometry import so3
from msf_torch.geometry.invariant import invariant_difference, invariant_maps, invariant_retract
from msf_torch.types import NavState

DT = torch.float64


def _estimate(batch: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    position = 20.0 * torch.randn(batch, 3, generator=gen, dtype=DT)
    velocity = 3.0 * torch.randn(batch, 3, generator=gen, dtype=DT)
    rotation = so3.exp(torch.randn(batch, 3, generator=gen, dtype=DT))
    return position, velocity, rotation


def test_difference_inverts_retract():
    position, velocity, rotation = _estimate(64, 0)
    xi = 0.5 * torch.randn(64, 9, generator=torch.Generator().manual_seed(1), dtype=DT)
    state = invariant_retract(position, velocity, rotation, xi)
    back = invariant_difference(*state, position, velocity, rotation)
    assert torch.allclose(back, xi, atol=1e-12, rtol=0)


def test_maps_are_inverse_and_first_order_exact():
    position, velocity, rotation = _estimate(8, 2)
    to_conv, to_inv = invariant_maps(position, velocity, rotation)
    eye = torch.eye(15, dtype=DT).expand(8, 15, 15)
    assert torch.allclose(to_conv @ to_inv, eye, atol=1e-12)

    def conventional(xi: torch.Tensor) -> torch.Tensor:
        p, v, r = invariant_retract(position, velocity, rotation, xi)
        return torch.cat((p - position, v - velocity, so3.log(rotation.mT @ r)), -1)

    step = 1e-6
    numeric = torch.zeros(8, 9, 9, dtype=DT)
    for k in range(9):
        dxi = torch.zeros(8, 9, dtype=DT)
        dxi[:, k] = step
        numeric[:, :, k] = (conventional(dxi) - conventional(-dxi)) / (2 * step)
    assert torch.allclose(numeric, to_conv[:, :9, :9], atol=1e-7, rtol=1e-7)


def test_invariant_nees_is_chi_square_where_conventional_is_not():
    """4000 draws: invariant NEES mean 15 +- 0.5 (its standard error is 0.09); the
    conventional NEES of the same states is over 30 (expected about 57: the second-order
    term adds ``E[(0.75 psi^2)^2] / (2e-3)^2 = 42``)."""
    draws = 4000
    position = torch.tensor([[5.0, 2.0, 0.0]], dtype=DT).expand(draws, 3)
    velocity = torch.tensor([[1.5, 0.0, 0.0]], dtype=DT).expand(draws, 3)
    rotation = torch.eye(3, dtype=DT).expand(draws, 3, 3)
    sigmas = torch.tensor(
        [0.3, 0.3, 0.5, 2e-3, 1e-3, 1e-3, 0.01, 0.01, 0.1, 1e-3, 1e-3, 1e-3, 0.05, 0.05, 0.05],
        dtype=DT,
    )
    cov_inv = torch.diag(sigmas**2)
    gen = torch.Generator().manual_seed(3)
    xi = torch.randn(draws, 15, generator=gen, dtype=DT) * sigmas
    p, v, r = invariant_retract(position, velocity, rotation, xi)
    estimate = NavState(
        position[:, None],
        velocity[:, None],
        rotation[:, None],
        torch.zeros(draws, 1, 3, dtype=DT),
        torch.zeros(draws, 1, 3, dtype=DT),
    )
    truth = NavState(p[:, None], v[:, None], r[:, None], xi[:, None, 9:12], xi[:, None, 12:15])
    to_conv, _ = invariant_maps(position, velocity, rotation)
    cov_conv = (to_conv @ cov_inv @ to_conv.mT)[:, None]

    error, cov = navigation_errors(truth, estimate, cov_conv, "invariant")
    assert torch.allclose(error[:, 0], xi, atol=1e-12)
    assert torch.allclose(cov[:, 0], cov_inv.expand(draws, 15, 15), atol=1e-12)
    invariant_mean = float(nees(error, cov).mean())
    assert abs(invariant_mean - 15.0) < 0.5, invariant_mean

    error_c, cov_c = navigation_errors(truth, estimate, cov_conv, "conventional")
    conventional_mean = float(nees(error_c, cov_c).mean())
    assert conventional_mean > 30.0, conventional_mean
