"""IMU model: exact ZOH integration, preintegration, bias Jacobians and covariance.

Routes compared: the closed form for constant body rate and specific force, an RK4
integration of the continuous kinematics, ``zoh_step`` looped, ``preintegrate`` +
``propagate_nominal``, finite differences of re-preintegration, Monte Carlo, and a plain
per-sample 9x9 covariance recursion written here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.imu import ImuNoise, preintegrate, propagate_nominal, zoh_step

DTYPE = torch.float64
GRAVITY = gravity_world()


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _random_state(batch: int, gen: torch.Generator):
    p0 = 10.0 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    v0 = 2.0 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    r0 = so3.exp(2.0 * torch.randn(batch, 3, generator=gen, dtype=DTYPE))
    return p0, v0, r0


def _closed_form(p0, v0, r0, w, f, total):
    """R0 Exp(wT), v0 + gT + R0 T Gamma1(wT) f, p0 + v0 T + g T^2/2 + R0 T^2 Gamma2(wT) f."""
    phi = w * total
    rf1 = (r0 @ so3.gamma1(phi) @ f[..., None])[..., 0]
    rf2 = (r0 @ so3.gamma2(phi) @ f[..., None])[..., 0]
    rot = r0 @ so3.exp(phi)
    vel = v0 + GRAVITY * total + total * rf1
    pos = p0 + v0 * total + 0.5 * GRAVITY * total**2 + total**2 * rf2
    return pos, vel, rot


def _rk4(p0, v0, r0, w, f, total, steps):
    """RK4 of R' = R [w]x, v' = R f + g, p' = v (numpy, one state)."""
    g = GRAVITY.numpy()
    wx = so3.hat(torch.as_tensor(w)).numpy()

    def deriv(state):
        p, v, r = state
        return v, r @ f + g, r @ wx

    state = (p0.copy(), v0.copy(), r0.copy())
    h = total / steps
    for _ in range(steps):
        k1 = deriv(state)
        k2 = deriv(tuple(s + 0.5 * h * k for s, k in zip(state, k1, strict=True)))
        k3 = deriv(tuple(s + 0.5 * h * k for s, k in zip(state, k2, strict=True)))
        k4 = deriv(tuple(s + h * k for s, k in zip(state, k3, strict=True)))
        state = tuple(
            s + h / 6.0 * (a + 2 * b + 2 * c + d)
            for s, a, b, c, d in zip(state, k1, k2, k3, k4, strict=True)
        )
    return state


# --------------------------------------------------------------------------------------------
# Closed form (acceptance: 1e-9)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [1, 10])
def test_constant_rate_and_force_match_closed_form(batch):
    """Constant body rate w and specific force f for T = 2 s at 100 Hz, with biases:
    preintegrate + propagate_nominal and zoh_step looped both equal the closed form."""
    gen = _gen(20)
    w = 0.8 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    f = torch.tensor([0.5, -0.3, 9.81], dtype=DTYPE) + torch.randn(
        batch, 3, generator=gen, dtype=DTYPE
    )
    bg = 0.01 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    ba = 0.1 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    p0, v0, r0 = _random_state(batch, gen)
    n, total = 200, 2.0
    dt = torch.full((batch, n), total / n, dtype=DTYPE)
    gyro = (w + bg)[:, None, :].expand(batch, n, 3)
    accel = (f + ba)[:, None, :].expand(batch, n, 3)

    pos_ref, vel_ref, rot_ref = _closed_form(p0, v0, r0, w, f, torch.tensor(total, dtype=DTYPE))

    pre = preintegrate(gyro, accel, dt, bg, ba)
    torch.testing.assert_close(pre.delta_t, torch.full((batch,), total, dtype=DTYPE))
    pos, vel, rot = propagate_nominal(
        p0,
        v0,
        r0,
        pre.delta_t,
        pre.delta_rotation,
        pre.delta_velocity,
        pre.delta_position,
        GRAVITY,
    )
    torch.testing.assert_close(pos, pos_ref, rtol=0, atol=1e-9)
    torch.testing.assert_close(vel, vel_ref, rtol=0, atol=1e-9)
    torch.testing.assert_close(rot, rot_ref, rtol=0, atol=1e-9)

    pos, vel, rot = p0, v0, r0
    for k in range(n):
        pos, vel, rot = zoh_step(pos, vel, rot, w, f, dt[:, k], GRAVITY)
    torch.testing.assert_close(pos, pos_ref, rtol=0, atol=1e-9)
    torch.testing.assert_close(vel, vel_ref, rtol=0, atol=1e-9)
    torch.testing.assert_close(rot, rot_ref, rtol=0, atol=1e-9)


def test_closed_form_matches_rk4_of_continuous_kinematics():
    """Independent check of the closed form (and so of the Gamma functions it uses):
    RK4 with h = 1e-4 s (local error ~h^5) of the continuous kinematics for T = 2 s."""
    gen = _gen(21)
    w = torch.tensor([0.3, -0.7, 1.1], dtype=DTYPE)
    f = torch.tensor([0.4, 0.2, 9.7], dtype=DTYPE)
    p0, v0, r0 = (x[0] for x in _random_state(1, gen))
    total = 2.0
    pos, vel, rot = _closed_form(p0, v0, r0, w, f, torch.tensor(total, dtype=DTYPE))
    p_rk, v_rk, r_rk = _rk4(p0.numpy(), v0.numpy(), r0.numpy(), w.numpy(), f.numpy(), total, 20000)
    np.testing.assert_allclose(rot.numpy(), r_rk, rtol=0, atol=1e-11)
    np.testing.assert_allclose(vel.numpy(), v_rk, rtol=0, atol=1e-10)
    np.testing.assert_allclose(pos.numpy(), p_rk, rtol=0, atol=1e-9)
    # and the sampled route on the same case
    n = 400
    pre = preintegrate(
        w.expand(n, 3),
        f.expand(n, 3),
        torch.full((n,), total / n, dtype=DTYPE),
        torch.zeros(3, dtype=DTYPE),
        torch.zeros(3, dtype=DTYPE),
    )
    pos2, vel2, rot2 = propagate_nominal(
        p0,
        v0,
        r0,
        pre.delta_t,
        pre.delta_rotation,
        pre.delta_velocity,
        pre.delta_position,
        GRAVITY,
    )
    np.testing.assert_allclose(pos2.numpy(), p_rk, rtol=0, atol=1e-9)
    np.testing.assert_allclose(vel2.numpy(), v_rk, rtol=0, atol=1e-10)
    np.testing.assert_allclose(rot2.numpy(), r_rk, rtol=0, atol=1e-11)


def test_ragged_padding_is_an_exact_no_op():
    gen = _gen(22)
    gyro = torch.randn(2, 30, 3, generator=gen, dtype=DTYPE)
    accel = torch.randn(2, 30, 3, generator=gen, dtype=DTYPE) + torch.tensor([0, 0, 9.8])
    dt = torch.full((2, 30), 0.01, dtype=DTYPE)
    dt[1, 20:] = 0.0
    zero = torch.zeros(2, 3, dtype=DTYPE)
    full = preintegrate(gyro, accel, dt, zero, zero)
    short = preintegrate(gyro[1:, :20], accel[1:, :20], dt[1:, :20], zero[1:], zero[1:])
    for name in ("delta_rotation", "delta_velocity", "delta_position", "bias_jacobian"):
        torch.testing.assert_close(
            getattr(full, name)[1:], getattr(short, name), rtol=0, atol=1e-15
        )
    for name in ("cov_unit_gyro", "cov_unit_accel"):
        torch.testing.assert_close(
            getattr(full, name)[1:], getattr(short, name), rtol=0, atol=1e-15
        )


# --------------------------------------------------------------------------------------------
# Bias Jacobians and first-order correction
# --------------------------------------------------------------------------------------------


def _interval(seed: int, batch: int = 1, n: int = 50, rate: float = 1.2):
    """A rotating, accelerating interval of n samples at 100 Hz (rates ~rate rad/s)."""
    gen = _gen(seed)
    t = torch.arange(n, dtype=DTYPE) * 0.01
    phase = torch.rand(batch, 1, 3, generator=gen, dtype=DTYPE) * 6.0
    gyro = rate * torch.sin(3.0 * t[None, :, None] + phase)
    accel = torch.tensor([0.0, 0.0, 9.8], dtype=DTYPE) + 2.0 * torch.cos(
        2.0 * t[None, :, None] + phase
    )
    dt = 0.01 + 0.002 * torch.rand(batch, n, generator=gen, dtype=DTYPE)
    bg = 0.01 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    ba = 0.05 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    return gyro, accel, dt, bg, ba


def _increment_error(pre_a, rot_b, vel_b, pos_b):
    """[dp, dv, dtheta] of increments b relative to a, dtheta = Log(dR_a^T dR_b)."""
    return torch.cat(
        (
            pos_b - pre_a.delta_position,
            vel_b - pre_a.delta_velocity,
            so3.log(pre_a.delta_rotation.mT @ rot_b),
        ),
        -1,
    )


_WITHIN_SAMPLE = (
    "preintegrate's gyro-bias Jacobian of dp, dv leaves out the within-sample term "
    "d(Gamma_1(w dt) f)/d(w) (relative error ~1/L for L samples: 13% at L = 8, 2% at L = 50); "
    "add sum_j R_j [f_j]x dt_j^2 / 2 to J_v^g and sum_j R_j [f_j]x (dt_j^3 / 6 + "
    "(T_L - T_j+1) dt_j^2 / 2) to J_p^g (zeroth order in w dt), or the exact derivative"
)


def _numeric_bias_jacobian(gyro, accel, dt, bg, ba, pre, h=1e-6):
    batch = bg.shape[0]
    cols = []
    for i in range(6):
        e = torch.zeros(batch, 6, dtype=DTYPE)
        e[:, i] = h
        plus = preintegrate(gyro, accel, dt, bg + e[:, :3], ba + e[:, 3:])
        minus = preintegrate(gyro, accel, dt, bg - e[:, :3], ba - e[:, 3:])
        d_plus = _increment_error(
            pre, plus.delta_rotation, plus.delta_velocity, plus.delta_position
        )
        d_minus = _increment_error(
            pre, minus.delta_rotation, minus.delta_velocity, minus.delta_position
        )
        cols.append((d_plus - d_minus) / (2 * h))
    return torch.stack(cols, -1)  # (B, 9, 6)


@pytest.mark.parametrize("batch", [1, 10])
def test_accel_bias_and_rotation_jacobians_match_central_differences(batch):
    gyro, accel, dt, bg, ba = _interval(23, batch)
    pre = preintegrate(gyro, accel, dt, bg, ba)
    numeric = _numeric_bias_jacobian(gyro, accel, dt, bg, ba, pre)
    assert pre.bias_jacobian.shape == (batch, 9, 6)
    scale = float(numeric.abs().max())
    # every row for the accel bias, and the rotation rows for the gyro bias
    torch.testing.assert_close(
        pre.bias_jacobian[:, :, 3:], numeric[:, :, 3:], rtol=0, atol=1e-6 * scale
    )
    torch.testing.assert_close(
        pre.bias_jacobian[:, 6:, :3], numeric[:, 6:, :3], rtol=0, atol=1e-6 * scale
    )
    torch.testing.assert_close(pre.bias_jacobian[:, 6:, 3:], torch.zeros(batch, 3, 3, dtype=DTYPE))


@pytest.mark.parametrize("samples", [8, 50])
def test_gyro_bias_jacobian_of_position_and_velocity_matches_central_differences(samples):
    """Rows dp, dv, columns b_g; relative 1e-6 of the block's largest entry."""
    gyro, accel, dt, bg, ba = _interval(23, 10, n=samples)
    pre = preintegrate(gyro, accel, dt, bg, ba)
    numeric = _numeric_bias_jacobian(gyro, accel, dt, bg, ba, pre)[:, :6, :3]
    got = pre.bias_jacobian[:, :6, :3]
    rel = float((got - numeric).abs().max() / numeric.abs().max())
    assert rel < 1e-6, f"{_WITHIN_SAMPLE}; measured max relative error {rel:.3e}"


@pytest.mark.parametrize("which", ["accel", "gyro"])
def test_bias_correction_error_is_second_order(which):
    """corrected(b + db) vs re-integration at b + db. The increments are linear in the accel
    bias, so that correction is exact; for the gyro bias the error shrinks 4x when db halves."""
    gyro, accel, dt, bg, ba = _interval(24, 1, n=100)
    pre = preintegrate(gyro, accel, dt, bg, ba)
    direction = torch.tensor([[0.02, -0.01, 0.015, 0.2, -0.1, 0.15]], dtype=DTYPE)
    if which == "accel":
        direction[:, :3] = 0.0
    else:
        direction[:, 3:] = 0.0
    errors = []
    for k in range(4):
        db = direction / 2**k
        rot, vel, pos = pre.corrected(bg + db[:, :3], ba + db[:, 3:])
        exact = preintegrate(gyro, accel, dt, bg + db[:, :3], ba + db[:, 3:])
        err = torch.cat(
            (
                pos - exact.delta_position,
                vel - exact.delta_velocity,
                so3.log(exact.delta_rotation.mT @ rot),
            ),
            -1,
        )
        errors.append(float(err.norm()))
    ratios = [errors[k] / errors[k + 1] for k in range(3)]
    message = f"errors {errors}, ratios {ratios}"
    if which == "accel":
        assert max(errors) < 1e-12, message
    else:
        assert all(3.5 < r < 4.5 for r in ratios), f"{_WITHIN_SAMPLE}; {message}"
    # unchanged bias: exactly the stored increments
    rot, vel, pos = pre.corrected(bg, ba)
    torch.testing.assert_close(rot, pre.delta_rotation, rtol=0, atol=0)
    torch.testing.assert_close(vel, pre.delta_velocity, rtol=0, atol=0)


# --------------------------------------------------------------------------------------------
# Covariance
# --------------------------------------------------------------------------------------------


def test_one_sample_accel_covariance_is_held_white_noise():
    """A sample held for dt with variance sigma^2/dt: Cov[dp, dv] = [[dt^3/4, dt^2/2],
    [dt^2/2, dt]] per axis (the convention test_eskf_filterpy.py builds its Q from)."""
    dt = 0.005
    pre = preintegrate(
        torch.zeros(1, 3, dtype=DTYPE),
        torch.tensor([[0.0, 0.0, 9.8]], dtype=DTYPE),
        torch.tensor([dt], dtype=DTYPE),
        torch.zeros(3, dtype=DTYPE),
        torch.zeros(3, dtype=DTYPE),
    )
    eye = torch.eye(3, dtype=DTYPE)
    expected = torch.zeros(9, 9, dtype=DTYPE)
    expected[:3, :3] = dt**3 / 4 * eye
    expected[:3, 3:6] = expected[3:6, :3] = dt**2 / 2 * eye
    expected[3:6, 3:6] = dt * eye
    torch.testing.assert_close(pre.cov_unit_accel, expected, rtol=1e-14, atol=0)
    assert float(pre.cov_unit_gyro[6:, 6:].diagonal().sub(dt).abs().max()) < 1e-18


def _reference_covariance(gyro, accel, dt, bg, ba, sigma_g, sigma_a):
    """Per-sample recursion of [dp, dv, dtheta] (right perturbation of dR), exact ZOH maps:

    A_k = [[I, dt I, -dR_k [G2 f]x dt^2], [0, I, -dR_k [G1 f]x dt], [0, 0, Exp(w dt)^T]],
    gyro noise  -> dtheta:  J_r(w dt) dt,     accel noise -> dv: dR_k G1 dt, dp: dR_k G2 dt^2,
    sample variances sigma^2 / dt. (The within-sample effect of gyro noise on dv, dp,
    O(dt / T) relative, is left out, as in the implementation.)"""
    eye = torch.eye(3, dtype=DTYPE)
    zero = torch.zeros(3, 3, dtype=DTYPE)
    cov = torch.zeros(9, 9, dtype=DTYPE)
    rot = torch.eye(3, dtype=DTYPE)
    for k in range(dt.shape[0]):
        h = float(dt[k])
        w = gyro[k] - bg
        f = accel[k] - ba
        phi = w * h
        g1, g2 = so3.gamma1(phi), so3.gamma2(phi)
        a = torch.cat(
            (
                torch.cat((eye, h * eye, -rot @ so3.hat(g2 @ f) * h * h), 1),
                torch.cat((zero, eye, -rot @ so3.hat(g1 @ f) * h), 1),
                torch.cat((zero, zero, so3.exp(phi).mT), 1),
            ),
            0,
        )
        b_g = torch.cat((zero, zero, so3.right_jacobian(phi) * h), 0)
        b_a = torch.cat((rot @ g2 * h * h, rot @ g1 * h, zero), 0)
        q = sigma_g**2 / h * b_g @ b_g.mT + sigma_a**2 / h * b_a @ b_a.mT
        cov = a @ cov @ a.mT + q
        rot = rot @ so3.exp(phi)
    return cov


def _block_errors(cov, ref):
    """Relative Frobenius error of each 3x3 block pair (p, v, theta), (3, 3)."""
    out = torch.zeros(3, 3, dtype=DTYPE)
    for i in range(3):
        for j in range(3):
            blk = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
            scale = math.sqrt(float(ref[blk[0], blk[0]].trace() * ref[blk[1], blk[1]].trace()))
            out[i, j] = (cov[blk] - ref[blk]).norm() / scale
    return out


@pytest.mark.parametrize(("rate", "tol"), [(0.0, 1e-12), (1.2, 1e-3)])
def test_covariance_matches_per_sample_recursion(rate, tol):
    """Exact at zero rotation rate. At ~1 rad/s, 100 Hz the implementation's zeroth-order
    noise maps differ by O(|w| dt) per map, but the first-order parts are skew and cancel in
    B B^T, so the covariance agrees to O((|w| dt)^2): measured 1.3e-5, asserted 1e-3
    (block-wise relative Frobenius error; the brief allowed 2%)."""
    gyro, accel, dt, bg, ba = _interval(25, 1, n=100, rate=rate)
    if rate == 0.0:
        bg = torch.zeros_like(bg)
    sigma_g, sigma_a = 2e-3, 3e-2
    pre = preintegrate(gyro, accel, dt, bg, ba)
    noise = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (sigma_g, sigma_a, 0.0, 0.0)))
    cov = pre.covariance(noise)[0]
    ref = _reference_covariance(gyro[0], accel[0], dt[0], bg[0], ba[0], sigma_g, sigma_a)
    err = _block_errors(cov, ref)
    assert float(err.max()) < tol, err
    torch.testing.assert_close(cov, cov.mT, rtol=0, atol=1e-18)


def _monte_carlo(gyro, accel, dt, bg, ba, sigma_g, sigma_a, samples, seed):
    gen = _gen(seed)
    n = dt.shape[-1]
    std_g = sigma_g / dt.sqrt()
    std_a = sigma_a / dt.sqrt()
    noisy_g = gyro + std_g[..., None] * torch.randn(samples, n, 3, generator=gen, dtype=DTYPE)
    noisy_a = accel + std_a[..., None] * torch.randn(samples, n, 3, generator=gen, dtype=DTYPE)
    clean = preintegrate(gyro, accel, dt, bg, ba)
    noisy = preintegrate(
        noisy_g, noisy_a, dt.expand(samples, n), bg.expand(samples, 3), ba.expand(samples, 3)
    )
    err = torch.cat(
        (
            noisy.delta_position - clean.delta_position,
            noisy.delta_velocity - clean.delta_velocity,
            so3.log(clean.delta_rotation.mT @ noisy.delta_rotation),
        ),
        -1,
    )
    return clean, err


def test_covariance_matches_monte_carlo_without_rotation():
    """Whitened sample covariance L^-1 S L^-T of 4000 samples is I within sampling error
    (entries ~N(0, 1/N) off the diagonal, N(1, 2/N) on it; 5 sigma allowed)."""
    samples = 4000
    gyro, accel, dt, bg, ba = _interval(26, 1, n=50, rate=0.0)
    bg = torch.zeros_like(bg)
    sigma_g, sigma_a = 1e-3, 2e-2
    clean, err = _monte_carlo(gyro, accel, dt, bg, ba, sigma_g, sigma_a, samples, seed=27)
    noise = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (sigma_g, sigma_a, 0.0, 0.0)))
    cov = clean.covariance(noise)[0]
    chol = torch.linalg.cholesky(cov)
    white = torch.linalg.solve_triangular(chol, err.mT, upper=False)  # (9, N)
    sample_cov = white @ white.mT / samples
    dev = sample_cov - torch.eye(9, dtype=DTYPE)
    assert float(dev.abs().max()) < 5.0 * math.sqrt(2.0 / samples), sample_cov.diagonal()
    # mean error ~0 (first order): |mean| < 5 / sqrt(N) in whitened units
    assert float(white.mean(1).abs().max()) < 5.0 / math.sqrt(samples)


def test_covariance_matches_monte_carlo_while_rotating():
    """At ~1.2 rad/s the diagonal agrees with 4000 samples to 10%."""
    samples = 4000
    gyro, accel, dt, bg, ba = _interval(28, 1, n=50, rate=1.2)
    sigma_g, sigma_a = 1e-3, 2e-2
    clean, err = _monte_carlo(gyro, accel, dt, bg, ba, sigma_g, sigma_a, samples, seed=29)
    noise = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (sigma_g, sigma_a, 0.0, 0.0)))
    cov = clean.covariance(noise)[0]
    sample_cov = err.mT @ err / samples
    ratio = sample_cov.diagonal() / cov.diagonal()
    assert float((ratio - 1.0).abs().max()) < 0.10, ratio
