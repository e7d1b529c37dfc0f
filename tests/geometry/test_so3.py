"""SO(3) on plain tensors: Exp/Log, hat/vee, Gamma functions, right Jacobian, gradients.

Independent routes: scipy's matrix exponential (``expm``), Van Loan block exponentials for
the Gamma functions, Simpson quadrature of ``Exp(s phi)``, central finite differences.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.linalg import expm

from msf_torch.geometry import quaternion, so3

DTYPE = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _random_axis(n: int, gen: torch.Generator) -> torch.Tensor:
    axis = torch.randn(n, 3, generator=gen, dtype=DTYPE)
    return axis / axis.norm(dim=-1, keepdim=True)


def _test_angles() -> torch.Tensor:
    """Angles from 0 through the Taylor switch (1e-4) to a hair below a half turn."""
    return torch.tensor(
        [
            0.0,
            1e-12,
            1e-8,
            1e-6,
            9.9e-5,
            1e-4,
            1.01e-4,
            1e-3,
            0.1,
            1.0,
            2.0,
            3.0,
            math.pi - 1e-3,
            math.pi - 1e-6,
            math.pi - 1e-9,
        ],
        dtype=DTYPE,
    )


def _phis(seed: int = 0) -> torch.Tensor:
    """(K, 3) rotation vectors at every test angle, random axes."""
    angles = _test_angles()
    return angles[:, None] * _random_axis(angles.numel(), _gen(seed))


def _expm_np(phi: torch.Tensor) -> np.ndarray:
    return np.stack([expm(so3.hat(p).numpy()) for p in phi])


# --------------------------------------------------------------------------------------------
# hat / vee
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [1, 10])
def test_hat_is_cross_product_and_vee_inverts_it(batch):
    gen = _gen(1)
    a = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    b = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    skew = so3.hat(a)
    assert skew.shape == (batch, 3, 3)
    torch.testing.assert_close(
        (skew @ b[..., None])[..., 0], torch.linalg.cross(a, b), rtol=0, atol=1e-15
    )
    torch.testing.assert_close(skew.mT, -skew, rtol=0, atol=0)
    torch.testing.assert_close(so3.vee(skew), a, rtol=0, atol=0)
    # leading dims broadcast
    assert so3.hat(a.reshape(batch, 1, 3)).shape == (batch, 1, 3, 3)


# --------------------------------------------------------------------------------------------
# Exp / Log
# --------------------------------------------------------------------------------------------


def test_exp_matches_matrix_exponential():
    phi = _phis(2)
    rot = so3.exp(phi)
    np.testing.assert_allclose(rot.numpy(), _expm_np(phi), rtol=0, atol=1e-14)
    eye = torch.eye(3, dtype=DTYPE).expand_as(rot)
    torch.testing.assert_close(rot @ rot.mT, eye, rtol=0, atol=1e-15)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(len(phi), dtype=DTYPE))


def test_log_inverts_exp_from_zero_to_near_half_turn():
    phi = _phis(3)
    back = so3.log(so3.exp(phi))
    err = (back - phi).norm(dim=-1)
    # near pi the rotation vector is ill conditioned: d(phi) ~ eps / (pi - theta)
    angle = phi.norm(dim=-1)
    bound = 1e-14 + 1e-15 / (math.pi - angle).clamp_min(1e-9)
    assert bool((err <= bound * 100).all()), err.tolist()
    assert err[angle < 3.0].max() < 2e-15


def test_log_at_exact_half_turn_returns_a_half_turn():
    axis = _random_axis(10, _gen(4))
    rot = so3.exp(math.pi * axis)
    back = so3.log(rot)
    np.testing.assert_allclose(back.norm(dim=-1).numpy(), math.pi, rtol=0, atol=1e-7)
    # +axis or -axis: both are the same half turn
    align = (back / back.norm(dim=-1, keepdim=True) * axis).sum(-1).abs()
    np.testing.assert_allclose(align.numpy(), 1.0, atol=1e-12)
    torch.testing.assert_close(so3.exp(back), rot, rtol=0, atol=1e-12)


@pytest.mark.parametrize("batch", [1, 10])
def test_exp_of_log_of_random_rotations(batch):
    gen = _gen(5)
    axis = _random_axis(batch, gen)
    angle = math.pi * torch.rand(batch, generator=gen, dtype=DTYPE)
    rot = so3.exp(angle[:, None] * axis)
    torch.testing.assert_close(so3.exp(so3.log(rot)), rot, rtol=0, atol=1e-14)
    assert bool((so3.log(rot).norm(dim=-1) <= math.pi + 1e-12).all())


def test_exp_is_group_homomorphism_along_an_axis():
    axis = _random_axis(10, _gen(6))
    a = torch.linspace(-2.0, 2.0, 10, dtype=DTYPE)[:, None]
    b = torch.linspace(1.0, -0.5, 10, dtype=DTYPE)[:, None]
    torch.testing.assert_close(
        so3.exp(a * axis) @ so3.exp(b * axis), so3.exp((a + b) * axis), rtol=0, atol=1e-14
    )


# --------------------------------------------------------------------------------------------
# Gamma functions
# --------------------------------------------------------------------------------------------


def _power_series(phi: torch.Tensor, shift: int, terms: int = 40) -> torch.Tensor:
    """``sum_n [phi]x^n / (n + shift)!`` summed term by term (test-local, differentiable):
    shift 0 is Exp, 1 is Gamma_1, 2 is Gamma_2. Accurate to ~1e-15 for |phi| <= pi."""
    skew = so3.hat(phi)
    term = torch.eye(3, dtype=phi.dtype).expand_as(skew) / math.factorial(shift)
    total = term
    for n in range(1, terms):
        term = term @ skew / (n + shift)
        total = total + term
    return total


_REFERENCE = {
    "exp": lambda p: _power_series(p, 0),
    "gamma1": lambda p: _power_series(p, 1),
    "gamma2": lambda p: _power_series(p, 2),
    "right_jacobian": lambda p: _power_series(-p, 1),
}


def _simpson_weights(n: int) -> np.ndarray:
    """Composite Simpson weights on n (odd) equally spaced points of [0, 1]."""
    w = np.ones(n)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    return w / (3.0 * (n - 1))


@pytest.mark.parametrize("angle", [0.0, 1e-6, 9.9e-5, 1e-2, 0.3, 1.5, 3.0, math.pi - 1e-6])
def test_gamma_functions_equal_integrals_of_exp(angle):
    """Gamma_1 = int_0^1 Exp(s phi) ds; Gamma_2 = int_0^1 int_0^s Exp(u phi) du ds
    = int_0^1 (1 - u) Exp(u phi) du. Simpson, 2001 points (quadrature error ~1e-14)."""
    phi = angle * _random_axis(1, _gen(7))[0]
    n = 2001
    s = torch.linspace(0.0, 1.0, n, dtype=DTYPE)
    w = torch.as_tensor(_simpson_weights(n), dtype=DTYPE)
    rots = torch.as_tensor(_expm_np(s[:, None] * phi), dtype=DTYPE)
    int1 = (w[:, None, None] * rots).sum(0)
    int2 = (w[:, None, None] * (1.0 - s)[:, None, None] * rots).sum(0)
    torch.testing.assert_close(so3.gamma1(phi), int1, rtol=0, atol=1e-12)
    torch.testing.assert_close(so3.gamma2(phi), int2, rtol=0, atol=1e-12)


def test_gamma_functions_equal_van_loan_block_exponentials():
    """expm([[W, I], [0, 0]]) has Gamma_1 top right; the 3-block chain has Gamma_2."""
    phi = _phis(8)
    g1 = so3.gamma1(phi).numpy()
    g2 = so3.gamma2(phi).numpy()
    eye, zero = np.eye(3), np.zeros((3, 3))
    for k, p in enumerate(phi):
        w = so3.hat(p).numpy()
        two = expm(np.block([[w, eye], [zero, zero]]))
        three = expm(np.block([[w, eye, zero], [zero, zero, eye], [zero, zero, zero]]))
        np.testing.assert_allclose(g1[k], two[:3, 3:], rtol=0, atol=1e-12)
        np.testing.assert_allclose(g2[k], three[:3, 6:], rtol=0, atol=1e-12)


_ANGLES = [0.0, 1e-9, 1e-5, 9.9e-5, 1.0001e-4, 2e-4, 5e-4, 1e-3, 1e-2, 0.5, 2.0, 3.0, math.pi]


@pytest.mark.parametrize(("name", "angle"), [(n, a) for n in _REFERENCE for a in _ANGLES])
def test_series_functions_and_gradients_equal_power_series(name, angle):
    """Values to 1e-12 and autograd Jacobians to 1e-8 against the term-by-term power series,
    across the Taylor switch; no NaN at 0 or pi."""
    fn = getattr(so3, name)
    phi = angle * _random_axis(1, _gen(13))[0]
    torch.testing.assert_close(fn(phi), _REFERENCE[name](phi), rtol=0, atol=1e-12)
    jac = _jac(fn, phi)
    assert torch.isfinite(jac).all(), f"{name} gradient not finite at |phi| = {angle}"
    ref = _jac(_REFERENCE[name], phi)
    torch.testing.assert_close(jac, ref, rtol=0, atol=1e-8)


def test_series_equals_the_individual_functions():
    phi = torch.cat((_phis(9), _phis(10), _phis(11)))
    out = so3.series(phi.reshape(3, -1, 3))
    ref = {
        "exp": so3.exp(phi),
        "gamma1": so3.gamma1(phi),
        "gamma2": so3.gamma2(phi),
        "right_jacobian": so3.right_jacobian(phi),
    }
    for key, value in ref.items():
        got = out[key].reshape(-1, 3, 3)
        torch.testing.assert_close(got, value, rtol=0, atol=2e-15, msg=key)
    assert out["coef"].shape == (3, phi.shape[0] // 3, 4)
    torch.testing.assert_close(so3.right_jacobian(phi), so3.gamma1(-phi), rtol=0, atol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-5, 0.5, 2.0, 3.0, math.pi - 1e-3])
def test_right_jacobian_against_finite_differences(angle):
    """Exp(phi + d) = Exp(phi) Exp(J_r d) to first order: column i of J_r is
    (Log(Exp(phi)^T Exp(phi + h e_i)) - Log(Exp(phi)^T Exp(phi - h e_i))) / 2h."""
    phi = angle * _random_axis(1, _gen(11))[0]
    h = 1e-6
    base = so3.exp(phi).mT
    cols = []
    for i in range(3):
        e = torch.zeros(3, dtype=DTYPE)
        e[i] = h
        plus = so3.log(base @ so3.exp(phi + e))
        minus = so3.log(base @ so3.exp(phi - e))
        cols.append((plus - minus) / (2 * h))
    numeric = torch.stack(cols, -1)
    torch.testing.assert_close(so3.right_jacobian(phi), numeric, rtol=0, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.5, 2.0, 3.0])
def test_gamma_vector_jacobians_equal_central_differences(angle):
    """d(Gamma_n(phi) x)/dphi of gamma_vector_jacobians, column by column against central
    differences of gamma1 / gamma2 (below and above the small-angle switch)."""
    gen = _gen(23)
    phi = angle * _random_axis(4, gen)
    vec = torch.randn(4, 3, generator=gen, dtype=DTYPE)
    d_gamma1, d_gamma2 = so3.gamma_vector_jacobians(phi, vec)
    h = 1e-6
    for analytic, gamma in ((d_gamma1, so3.gamma1), (d_gamma2, so3.gamma2)):
        cols = []
        for i in range(3):
            e = torch.zeros(3, dtype=DTYPE)
            e[i] = h
            plus = (gamma(phi + e) @ vec[..., None])[..., 0]
            minus = (gamma(phi - e) @ vec[..., None])[..., 0]
            cols.append((plus - minus) / (2 * h))
        torch.testing.assert_close(analytic, torch.stack(cols, -1), rtol=0, atol=1e-8)


def test_project_returns_the_nearest_rotation():
    gen = _gen(12)
    rot = so3.exp(_random_axis(10, gen) * 2.0)
    noisy = rot + 1e-3 * torch.randn(10, 3, 3, generator=gen, dtype=DTYPE)
    fixed = so3.project(noisy)
    eye = torch.eye(3, dtype=DTYPE).expand_as(fixed)
    torch.testing.assert_close(fixed @ fixed.mT, eye, rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.linalg.det(fixed), torch.ones(10, dtype=DTYPE))
    assert (fixed - rot).abs().max() < 3e-3
    torch.testing.assert_close(so3.project(rot), rot, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Gradients at the identity and at a half turn
# --------------------------------------------------------------------------------------------


def _jac(fn, x: torch.Tensor) -> torch.Tensor:
    return torch.autograd.functional.jacobian(fn, x)


def test_exp_gradient_at_identity_is_hat_basis():
    """d Exp(phi) / d phi_i at 0 is hat(e_i), with no NaN from the singular branch."""
    jac = _jac(so3.exp, torch.zeros(3, dtype=DTYPE))  # (3, 3, 3)
    assert torch.isfinite(jac).all()
    for i in range(3):
        e = torch.zeros(3, dtype=DTYPE)
        e[i] = 1.0
        torch.testing.assert_close(jac[..., i], so3.hat(e), rtol=0, atol=1e-15)


@pytest.mark.parametrize("angle", [1e-6, 1.0, math.pi - 1e-3, math.pi - 1e-6])
def test_log_gradient_is_inverse_right_jacobian(angle):
    """d Log(R0 Exp(d)) / d d at d = 0 is J_r^-1(Log R0) (generic axis)."""
    phi0 = angle * _random_axis(1, _gen(14))[0]
    rot0 = so3.exp(phi0)
    jac = _jac(lambda d: so3.log(rot0 @ so3.exp(d)), torch.zeros(3, dtype=DTYPE))
    assert torch.isfinite(jac).all()
    expected = torch.linalg.inv(so3.right_jacobian(phi0))
    tol = 1e-10 if angle < 3.0 else 1e-6
    torch.testing.assert_close(jac, expected, rtol=tol, atol=tol)


def _log_input_gradient(rot: torch.Tensor) -> torch.Tensor:
    x = rot.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(so3.log(x).sum(), x)
    return grad


_LOG_POINTS = {
    "identity": torch.zeros(3, dtype=DTYPE),
    "yaw_0.3": torch.tensor([0.0, 0.0, 0.3], dtype=DTYPE),
    "roll_1": torch.tensor([1.0, 0.0, 0.0], dtype=DTYPE),
    "half_turn_z": torch.tensor([0.0, 0.0, math.pi], dtype=DTYPE),
    "half_turn_generic": math.pi * torch.tensor([0.48, -0.6, 0.64], dtype=DTYPE),
    "tiny_generic": 1e-7 * torch.tensor([0.48, -0.6, 0.64], dtype=DTYPE),
}


@pytest.mark.parametrize("point", list(_LOG_POINTS))
def test_log_gradient_finite_at_identity_axis_rotations_and_half_turns(point):
    """Habit 8: no NaN gradient at the identity or a half turn. pytorch_kinematics'
    ``matrix_to_quaternion`` takes sqrt(clamp(x, 0)) of all four candidates; an exact 0
    (identity, any rotation about a coordinate axis) gives 0 * inf = NaN in backward."""
    rot = so3.exp(_LOG_POINTS[point])
    grad = _log_input_gradient(rot)
    jac = _jac(lambda d: so3.log(rot @ so3.exp(d)), torch.zeros(3, dtype=DTYPE))
    assert torch.isfinite(grad).all() and torch.isfinite(jac).all(), (
        f"so3.log backward gives NaN at {point}: dLog/dR = {grad.tolist()}, "
        f"dLog(R Exp(d))/dd = {jac.tolist()}"
    )
    if point in ("identity", "yaw_0.3", "roll_1", "tiny_generic"):
        expected = torch.linalg.inv(so3.right_jacobian(_LOG_POINTS[point]))
        torch.testing.assert_close(jac, expected, rtol=0, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Quaternions
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [1, 10])
def test_quaternion_round_trip_and_orders(batch):
    gen = _gen(16)
    phi = _random_axis(batch, gen) * math.pi * torch.rand(batch, 1, generator=gen, dtype=DTYPE)
    rot = so3.exp(phi)
    quat = quaternion.matrix_to_quat(rot)
    assert bool((quat[:, 0] >= 0).all())
    torch.testing.assert_close(quat.norm(dim=-1), torch.ones(batch, dtype=DTYPE))
    # Hamilton scalar-first: q = [cos(t/2), sin(t/2) axis]
    angle = phi.norm(dim=-1, keepdim=True)
    expected = torch.cat((torch.cos(angle / 2), torch.sin(angle / 2) * phi / angle), -1)
    torch.testing.assert_close(quat, expected, rtol=0, atol=1e-14)
    torch.testing.assert_close(quaternion.quat_to_matrix(quat), rot, rtol=0, atol=1e-14)
    # not-quite-unit input is normalised
    torch.testing.assert_close(quaternion.quat_to_matrix(1.01 * quat), rot, rtol=0, atol=1e-14)
    xyzw = quaternion.wxyz_to_xyzw(quat)
    torch.testing.assert_close(xyzw[:, 3], quat[:, 0], rtol=0, atol=0)
    torch.testing.assert_close(quaternion.xyzw_to_wxyz(xyzw), quat, rtol=0, atol=0)


def test_yaw_matrix_is_exp_about_z():
    yaw = torch.linspace(-math.pi, math.pi, 10, dtype=DTYPE)
    phi = torch.stack((torch.zeros_like(yaw), torch.zeros_like(yaw), yaw), -1)
    torch.testing.assert_close(quaternion.yaw_matrix(yaw), so3.exp(phi), rtol=0, atol=1e-15)


def test_log_gradient_finite_for_nearly_equal_rotations():
    """Log(R_a^T R_b) with R_b = R_a Exp(1e-7 n): the product's diagonal combinations round
    to <= 0, and a NaN gradient here would poison any rotation-error loss."""
    gen = _gen(17)
    rot_a = so3.exp(2.0 * torch.randn(500, 3, generator=gen, dtype=DTYPE))
    rot_b = rot_a @ so3.exp(1e-7 * torch.randn(500, 3, generator=gen, dtype=DTYPE))
    x = (rot_a.mT @ rot_b).requires_grad_(True)
    (grad,) = torch.autograd.grad((so3.log(x) ** 2).sum(), x)
    bad = (~torch.isfinite(grad)).flatten(1).any(-1)
    assert not bool(bad.any()), f"{int(bad.sum())} of 500 log gradients are NaN"


def test_series_coefficients_equal_coefficients_and_closed_forms():
    """Batched coefficients from theta^2 (Taylor everywhere, closed form above the switch)
    equal ``coefficients`` on both sides of the switch; at theta >= 0.5 they equal numpy's
    closed forms of c_n and central differences (dc_n / dt) / t of them for e_n."""
    phi = torch.cat((_phis(21), _phis(22), 1e-2 * _phis(23))).reshape(3, -1, 3)
    coef = so3.coefficients(phi, "0123", derivatives=True)
    batched = so3.series_coefficients((phi * phi).sum(-1))
    assert batched.shape == (7, *phi.shape[:-1])
    for k, name in enumerate(so3.SERIES_NAMES):
        torch.testing.assert_close(batched[k], coef[name][..., 0, 0], rtol=1e-15, atol=1e-18)

    def closed(t: np.ndarray) -> list[np.ndarray]:
        s, c = np.sin(t), np.cos(t)
        return [s / t, (1 - c) / t**2, (t - s) / t**3, (t**2 + 2 * c - 2) / (2 * t**4)]

    t = np.linspace(0.5, 3.0, 30)  # closed forms free of cancellation here
    h = 1e-5
    slopes = [(a - b) / (2 * h) / t for a, b in zip(closed(t + h), closed(t - h), strict=True)]
    got = so3.series_coefficients(torch.as_tensor(t * t)).numpy()
    np.testing.assert_allclose(got[:4], np.stack(closed(t)), rtol=1e-13)
    np.testing.assert_allclose(got[4:], np.stack(slopes[1:]), rtol=1e-6)


def test_rpy_matrix_equals_pytorch_kinematics_zyx() -> None:
    """``rpy_matrix`` (URDF / OXTS / mounting roll-pitch-yaw) against pytorch_kinematics'
    intrinsic ZYX Euler angles ``[yaw, pitch, roll]``, batched."""
    from pytorch_kinematics.transforms import euler_angles_to_matrix

    gen = torch.Generator().manual_seed(7)
    rpy = (torch.rand(50, 3, generator=gen, dtype=torch.float64) - 0.5) * 6.0
    expected = euler_angles_to_matrix(rpy.flip(-1), "ZYX")
    torch.testing.assert_close(so3.rpy_matrix(rpy), expected, rtol=0, atol=1e-14)
    quarter = so3.rpy_matrix(torch.tensor([0.0, 0.0, torch.pi / 2], dtype=torch.float64))
    torch.testing.assert_close(
        quarter @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
    )
