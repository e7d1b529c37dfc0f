"""Quaternion product, conjugate, Exp and Log against the SO(3) matrix functions."""

from __future__ import annotations

import math

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import (
    quat_conjugate,
    quat_exp,
    quat_log,
    quat_multiply,
    quat_to_matrix,
)

DTYPE = torch.float64


def test_against_matrices():
    gen = torch.Generator().manual_seed(0)
    phi = torch.randn(200, 3, generator=gen, dtype=DTYPE)
    psi = torch.randn(200, 3, generator=gen, dtype=DTYPE)
    a, b = quat_exp(phi), quat_exp(psi)
    torch.testing.assert_close(quat_to_matrix(a), so3.exp(phi), atol=1e-14, rtol=0)
    torch.testing.assert_close(
        quat_to_matrix(quat_multiply(a, b)), so3.exp(phi) @ so3.exp(psi), atol=1e-14, rtol=0
    )
    torch.testing.assert_close(
        quat_to_matrix(quat_conjugate(a)), so3.exp(phi).mT, atol=1e-14, rtol=0
    )
    torch.testing.assert_close(quat_log(a), so3.log(so3.exp(phi)), atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_log(-a), quat_log(a), atol=1e-14, rtol=0)


def test_near_identity_and_half_turn():
    small = torch.tensor([[1e-12, -2e-12, 3e-13], [0.0, 0.0, 0.0]], dtype=DTYPE)
    torch.testing.assert_close(quat_log(quat_exp(small)), small, atol=1e-24, rtol=0)
    half = torch.tensor([[math.pi, 0.0, 0.0]], dtype=DTYPE)
    torch.testing.assert_close(quat_log(quat_exp(half)).abs(), half, atol=1e-12, rtol=0)


def test_gradients_are_finite_at_the_identity():
    phi = torch.zeros(3, dtype=DTYPE, requires_grad=True)
    quat_log(quat_exp(phi)).sum().backward()
    torch.testing.assert_close(phi.grad, torch.ones(3, dtype=DTYPE))  # d Log(Exp)/dphi = I
    jac = torch.autograd.functional.jacobian(quat_exp, torch.zeros(3, dtype=DTYPE))
    expected = torch.cat((torch.zeros(1, 3, dtype=DTYPE), 0.5 * torch.eye(3, dtype=DTYPE)))
    torch.testing.assert_close(jac, expected)  # dq/dphi = [0; I / 2] at the identity
    assert torch.autograd.gradcheck(
        lambda x: quat_log(quat_exp(x)), (1e-3 * torch.randn(4, 3, dtype=DTYPE)).requires_grad_()
    )


def test_log_runs_under_vmap_of_jacrev():
    """``so3.log`` (through ``matrix_to_quat``) has no data-dependent Python control flow, so
    per-sample Jacobians by ``vmap(jacrev)`` (Theseus's autodiff) match the batched ones."""
    gen = torch.Generator().manual_seed(1)
    rot = so3.exp(torch.randn(6, 3, generator=gen, dtype=DTYPE))
    per_sample = torch.func.vmap(torch.func.jacrev(so3.log))(rot)  # (6, 3, 3, 3)
    batched = torch.autograd.functional.jacobian(lambda r: so3.log(r).sum(0), rot)
    torch.testing.assert_close(per_sample, batched.permute(1, 0, 2, 3), atol=1e-14, rtol=0)
