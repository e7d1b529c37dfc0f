"""Closed forms of two adaptive-noise pieces that had no direct test.

``inflate_along_measurements`` against its closed form and the properties its docstring
states: with ``A = P H^T`` and ``M = H P H^T`` the result is ``P + (lambda - 1) A M^-1 A^T``;
``H = I`` gives full fading ``lambda P``; in the measurement space it equals full fading
(``H P' H^T = lambda M``, ``P' H^T = lambda A``); states uncorrelated with the measurement
keep their covariance; masked rows count as absent.

``BlockAdaptation``'s Sage-Husa floor is ``noise_floor`` times the nominal R's *smallest*
eigenvalue: a first sample ``nu nu^T - H P^- H^T`` that is negative definite (zero
innovation) with no prior weight is projected to exactly ``floor * I``.

``BlockAdaptation``'s strong tracking on a first sample (``V = nu nu^T``):
``lambda = tr(V - H Q H^T - R) / tr(H Phi P Phi^T H^T)`` (the process noise is left out of
the denominator), and ``P^- = lambda Phi P Phi^T + Q`` for ``H = I``. By hand with
``Phi P Phi^T = I``, ``Q = I / 2``, ``R = I / 10``, ``nu = (2, 1)``: ``lambda = 3.8 / 2``.
"""

from __future__ import annotations

import torch

from msf_torch.frontend.adaptive import BlockAdaptation, inflate_along_measurements

DTYPE = torch.float64


def _spd(gen: torch.Generator, *shape: int) -> torch.Tensor:
    a = torch.randn(*shape, shape[-1], generator=gen, dtype=DTYPE)
    return a @ a.mT + 0.5 * torch.eye(shape[-1], dtype=DTYPE)


def test_identity_measurement_is_full_fading():
    gen = torch.Generator().manual_seed(21)
    propagated = _spd(gen, 3, 4)
    factor = torch.tensor([1.0, 1.7, 3.2], dtype=DTYPE)
    eye = torch.eye(4, dtype=DTYPE).expand(3, 4, 4)
    out = inflate_along_measurements(propagated, eye, factor)
    torch.testing.assert_close(out, factor[:, None, None] * propagated, rtol=1e-12, atol=1e-12)


def test_partial_measurement_matches_closed_form_and_keeps_unseen_states():
    gen = torch.Generator().manual_seed(22)
    seen = _spd(gen, 2, 3)
    unseen = _spd(gen, 2, 2)
    propagated = torch.zeros(2, 5, 5, dtype=DTYPE)
    propagated[:, :3, :3] = seen
    propagated[:, 3:, 3:] = unseen
    jacobian = torch.zeros(2, 2, 5, dtype=DTYPE)
    jacobian[:, :, :3] = torch.randn(2, 2, 3, generator=gen, dtype=DTYPE)
    factor = torch.tensor([2.5, 1.3], dtype=DTYPE)
    out = inflate_along_measurements(propagated, jacobian, factor)
    cross = propagated @ jacobian.mT
    m = jacobian @ cross
    expected = propagated + (factor - 1.0)[:, None, None] * (
        cross @ torch.linalg.solve(m, cross.mT)
    )
    torch.testing.assert_close(out, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(jacobian @ out @ jacobian.mT, factor[:, None, None] * m)
    torch.testing.assert_close(out @ jacobian.mT, factor[:, None, None] * cross)
    torch.testing.assert_close(out[:, 3:, 3:], unseen, rtol=0, atol=0)


def test_masked_rows_are_left_out():
    gen = torch.Generator().manual_seed(23)
    propagated = _spd(gen, 1, 6)
    jacobian = torch.randn(1, 4, 6, generator=gen, dtype=DTYPE)
    factor = torch.tensor([1.8], dtype=DTYPE)
    rows = torch.tensor([[True, False, True, False]])
    out = inflate_along_measurements(propagated, jacobian, factor, rows)
    kept = inflate_along_measurements(propagated, jacobian[:, [0, 2]], factor)
    torch.testing.assert_close(out, kept, rtol=1e-10, atol=1e-12)


def test_rows_measuring_the_same_direction_inflate_as_one_block():
    """Two strong-tracking blocks seeing the same direction (two pose sources' rate rows, GNSS
    and a pose position) make M singular; the inflation is that of the block alone (it was
    dropped: ``propagated`` came back unchanged while the fading factor said lambda > 1)."""
    gen = torch.Generator().manual_seed(24)
    propagated = _spd(gen, 1, 6)
    block = torch.randn(1, 3, 6, generator=gen, dtype=DTYPE)
    factor = torch.tensor([3.0], dtype=DTYPE)
    alone = inflate_along_measurements(propagated, block, factor)
    for twice in (torch.cat((block, block), 1), torch.cat((block, -2.0 * block[:, :2]), 1)):
        out = inflate_along_measurements(propagated, twice, factor)
        torch.testing.assert_close(out, alone, rtol=1e-8, atol=1e-10)
    rows = torch.tensor([[True, True, True, True, False, True]])
    masked = torch.cat((block, block), 1)
    out = inflate_along_measurements(propagated, masked, factor, rows)
    torch.testing.assert_close(out, alone, rtol=1e-8, atol=1e-10)


def test_sage_husa_floor_is_a_fraction_of_the_smallest_nominal_eigenvalue():
    adaptation = BlockAdaptation(
        ["gnss"], [2], ["gnss"], [], batch=1, forgetting=0.9, prior_samples=0.0, noise_floor=0.1
    )
    nominal = torch.diag(torch.tensor([1.0, 100.0], dtype=DTYPE))[None]
    eye = torch.eye(2, dtype=DTYPE)[None]
    predicted, r_cov = adaptation.step(
        0,
        0.5 * eye,
        torch.zeros(1, 2, 2, dtype=DTYPE),
        eye,
        torch.zeros(1, 2, dtype=DTYPE),
        nominal,
        torch.ones(1, 1, dtype=torch.bool),
    )
    torch.testing.assert_close(r_cov, 0.1 * eye, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(predicted, 0.5 * eye, rtol=0, atol=0)


def test_strong_tracking_factor_by_hand():
    adaptation = BlockAdaptation(["gnss"], [2], [], ["gnss"], batch=1, forgetting=0.9)
    eye = torch.eye(2, dtype=DTYPE)[None]
    predicted, r_cov = adaptation.step(
        0,
        eye,
        0.5 * eye,
        eye,
        torch.tensor([[2.0, 1.0]], dtype=DTYPE),
        0.1 * eye,
        torch.ones(1, 1, dtype=torch.bool),
    )
    torch.testing.assert_close(predicted, (1.9 + 0.5) * eye, rtol=1e-12, atol=0)
    torch.testing.assert_close(r_cov, 0.1 * eye, rtol=0, atol=0)
    fading, _ = adaptation.history(1)
    torch.testing.assert_close(fading, torch.tensor([[1.0, 1.9]], dtype=DTYPE))
