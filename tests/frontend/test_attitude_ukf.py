"""Attitude UKF (frontend/attitude_ukf.py) against filterpy, a linear KF and simulated truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from msf_torch.frontend.attitude_ukf import (
    AttitudeUkfConfig,
    merwe_weights,
    roll_pitch,
    run_attitude_ukf,
    sigma_points,
    ukf_predict,
    ukf_update,
)
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_exp, quat_log

DTYPE = torch.float64
G = 9.80665


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_weights_and_sigma_points_match_filterpy():
    alpha, beta, kappa = 0.5, 2.0, 0.3
    ref = MerweScaledSigmaPoints(6, alpha=alpha, beta=beta, kappa=kappa)
    wm, wc, spread = merwe_weights(6, alpha, beta, kappa)
    np.testing.assert_allclose(wm.numpy(), ref.Wm, rtol=1e-14)
    np.testing.assert_allclose(wc.numpy(), ref.Wc, rtol=1e-14)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + np.eye(6)
    ours = sigma_points(torch.as_tensor(cov)[None], spread)[0].numpy()
    np.testing.assert_allclose(ours, ref.sigma_points(np.zeros(6), cov), atol=1e-12)


def test_linear_case_equals_filterpy_kalman_filter():
    """Rotation about z only, x/y variances 1e-20: the UKF is a linear KF on (theta_z,
    omega_z) with F = [[1, dt], [0, 1]] and H = I (attitude fix and gyro); filterpy's
    KalmanFilter gives the same means and covariances (1e-9)."""
    dt, steps = 0.01, 60
    rng = np.random.default_rng(1)
    tiny = 1e-20
    p0 = np.array([[0.04, 0.01], [0.01, 0.09]])
    q_diag = np.array([1e-5, 4e-3])
    r_diag = np.array([2.5e-3, 1e-3])
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.x = np.array([0.2, 0.5])
    kf.P = p0.copy()
    kf.F = np.array([[1.0, dt], [0.0, 1.0]])
    kf.H = np.eye(2)
    kf.Q = np.diag(q_diag)
    kf.R = np.diag(r_diag)

    def embed(block2: np.ndarray, other: float) -> torch.Tensor:
        full = np.eye(6) * other
        idx = [2, 5]
        full[np.ix_(idx, idx)] = block2
        return torch.as_tensor(full)[None]

    quat = quat_exp(torch.tensor([[0.0, 0.0, 0.2]], dtype=DTYPE))
    rate = torch.tensor([[0.0, 0.0, 0.5]], dtype=DTYPE)
    cov = embed(p0, tiny)
    process = embed(np.diag(q_diag), tiny)
    r_cov = torch.diag(torch.tensor([1.0, 1.0, r_diag[0], 1.0, 1.0, r_diag[1], 1.0, 1.0, 1.0]))
    weights = merwe_weights(6, 0.5, 2.0, 0.0)
    present = torch.tensor([[True, True, False]])
    dt_t = torch.tensor([dt], dtype=DTYPE)
    for _ in range(steps):
        kf.predict()
        quat, rate, cov = ukf_predict(quat, rate, cov, process, dt_t, weights)
        z = np.array([kf.x[0], kf.x[1]]) + rng.normal(0.0, np.sqrt(r_diag) * 3)
        kf.update(z)
        fix = quat_exp(torch.tensor([[0.0, 0.0, z[0]]], dtype=DTYPE))
        measurement = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, z[1], 0.0, 0.0, 0.0]], dtype=DTYPE)
        quat, rate, cov = ukf_update(
            quat, rate, cov, measurement, fix, r_cov[None], present, weights, G
        )
        theta = quat_log(quat)[0]
        assert float(theta[2]) == pytest.approx(kf.x[0], abs=1e-9)
        assert float(rate[0, 2]) == pytest.approx(kf.x[1], abs=1e-9)
        assert float(theta[:2].abs().max()) < 1e-9
        ours = cov[0][[2, 5]][:, [2, 5]].numpy()
        np.testing.assert_allclose(ours, kf.P, atol=1e-12, rtol=1e-9)


def test_accelerometer_update_equals_filterpy_ukf():
    """Roll only (the other axes' variances 1e-20): the error-state chart is additive, so the
    UKF with the gyro and the accelerometer as a gravity sensor, ``h = [omega, g (0, sin r,
    cos r)]``, a nonlinear model, is filterpy's UnscentedKalmanFilter on ``[theta, omega]``
    with the same sigma points (1e-12)."""
    dt, tiny = 0.01, 1e-20
    rng = np.random.default_rng(3)

    def fx(x: np.ndarray, step: float) -> np.ndarray:
        return x + np.concatenate((x[3:] * step, np.zeros(3)))

    def hx(x: np.ndarray) -> np.ndarray:
        return np.concatenate((x[3:], G * np.array([0.0, np.sin(x[0]), np.cos(x[0])])))

    ukf = UnscentedKalmanFilter(6, 6, dt, hx, fx, MerweScaledSigmaPoints(6, 0.5, 2.0, 0.0))
    p0 = np.diag([0.05**2, tiny, tiny, 0.2**2, tiny, tiny])
    p0[0, 3] = p0[3, 0] = 0.003
    ukf.x, ukf.P = np.array([0.4, 0.0, 0.0, 0.5, 0.0, 0.0]), p0.copy()
    ukf.Q = np.diag([1e-6, tiny, tiny, 1e-2, tiny, tiny])
    ukf.R = np.diag([1e-4] * 3 + [0.05, 0.02, 0.2])  # anisotropic: Wc_0 then matters
    weights = merwe_weights(6, 0.5, 2.0, 0.0)
    quat = quat_exp(torch.tensor([[0.4, 0.0, 0.0]], dtype=DTYPE))
    rate = torch.tensor([[0.5, 0.0, 0.0]], dtype=DTYPE)
    cov, process = torch.as_tensor(p0)[None], torch.as_tensor(ukf.Q)[None]
    r_cov = torch.diag(torch.as_tensor(np.concatenate((np.ones(3), np.diag(ukf.R)))))[None]
    present = torch.tensor([[False, True, True]])
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=DTYPE)
    truth = np.array([0.4, 0.0, 0.0, 0.9, 0.0, 0.0])
    for _ in range(100):
        truth = fx(truth, dt)
        ukf.predict()
        quat, rate, cov = ukf_predict(
            quat, rate, cov, process, torch.tensor([dt], dtype=DTYPE), weights
        )
        z = hx(truth) + rng.normal(size=6) * np.sqrt(np.diag(ukf.R))
        ukf.update(z)
        measurement = torch.as_tensor(np.concatenate((np.zeros(3), z)))[None]
        quat, rate, cov = ukf_update(
            quat, rate, cov, measurement, identity, r_cov, present, weights, G
        )
        ours = torch.cat((quat_log(quat)[0], rate[0])).numpy()
        np.testing.assert_allclose(ours, ukf.x, rtol=0, atol=1e-12)
        idx = np.ix_([0, 3], [0, 3])
        np.testing.assert_allclose(cov[0].numpy()[idx], ukf.P[idx], rtol=0, atol=1e-12)


def _static_imu(batch: int, n_samples: int, dt: float, seed: int, gyro_d: float, accel_d: float):
    gen = torch.Generator().manual_seed(seed)
    tilt = 0.15 * (2 * torch.rand(batch, 3, generator=gen, dtype=DTYPE) - 1)
    rot = so3.exp(tilt)  # (B, 3, 3)
    force = (rot.mT @ torch.tensor([0.0, 0.0, G], dtype=DTYPE)[:, None])[..., 0]
    gyro = gyro_d / math.sqrt(dt) * torch.randn(batch, n_samples, 3, generator=gen, dtype=DTYPE)
    accel = force[:, None] + accel_d / math.sqrt(dt) * torch.randn(
        batch, n_samples, 3, generator=gen, dtype=DTYPE
    )
    return rot, gyro, accel


def test_batched_over_runs_and_imus_equals_single_filters():
    dt = 0.01
    rot, gyro, accel = _static_imu(4, 150, dt, 2, 1e-4, 1e-3)
    gyro, accel = gyro.view(2, 2, 150, 3), accel.view(2, 2, 150, 3)
    density = torch.tensor([1e-4, 2e-4], dtype=DTYPE)  # per IMU of the pair
    cfg = AttitudeUkfConfig(density, torch.tensor([1e-3, 1.5e-3], dtype=DTYPE))
    both = run_attitude_ukf(gyro, accel, dt, cfg)
    for b in range(2):
        for n in range(2):
            single_cfg = AttitudeUkfConfig(float(density[n]), float(cfg.accel_noise_density[n]))
            one = run_attitude_ukf(gyro[b, n], accel[b, n], dt, single_cfg)
            torch.testing.assert_close(both.quaternion[b, n], one.quaternion, atol=1e-10, rtol=0)
            torch.testing.assert_close(both.covariance[b, n], one.covariance, atol=1e-12, rtol=0)
            torch.testing.assert_close(
                both.noise_estimate["accel"][b, n], one.noise_estimate["accel"], atol=1e-12, rtol=0
            )


def test_static_tilt_is_recovered():
    dt = 0.01
    rot, gyro, accel = _static_imu(3, 400, dt, 3, 7e-5, 1e-3)
    est = run_attitude_ukf(gyro, accel, dt, AttitudeUkfConfig(7e-5, 1e-3))
    err = (roll_pitch(est.rotation[:, 100:]) - roll_pitch(rot)[:, None]) * 180 / math.pi
    assert float(err.pow(2).mean().sqrt()) < 0.02  # deg
    # the world-frame tilt covariance is not overconfident (noise only: consistent filter)
    world = est.rotation @ est.covariance[..., :3, :3] @ est.rotation.mT
    sigma = world.diagonal(dim1=-2, dim2=-1)[..., :2].sqrt()[:, 100:] * 180 / math.pi
    assert float((err.abs() / sigma).pow(2).mean()) < 3.0


def test_sage_husa_accel_noise_helps_during_vibration():
    """Static IMU; 3 s of strong vibration (accel noise sigma 1.5 m/s^2): R_a rises to the
    vibration level within the burst and the tilt error over the burst is lower than the
    fixed-noise filter's (16% with the defaults: R_a needs about 1 s, b = 0.99 at 100 Hz
    and a prior worth 50 samples, so the first second is not protected)."""
    dt = 0.01
    rot, gyro, accel = _static_imu(4, 800, dt, 4, 7e-5, 1e-3)
    gen = torch.Generator().manual_seed(5)
    burst = slice(300, 600)
    accel = accel.clone()
    accel[:, burst] += 1.5 * torch.randn(4, 300, 3, generator=gen, dtype=DTYPE)
    fixed = AttitudeUkfConfig(7e-5, 1e-3, adaptive_noise_blocks=(), strong_tracking_blocks=())
    adaptive = AttitudeUkfConfig(7e-5, 1e-3, strong_tracking_blocks=())
    errors = {}
    for name, cfg in (("fixed", fixed), ("adaptive", adaptive)):
        est = run_attitude_ukf(gyro, accel, dt, cfg)
        err = roll_pitch(est.rotation[:, burst]) - roll_pitch(rot)[:, None]
        errors[name] = float(err.pow(2).mean().sqrt())
        if name == "adaptive":
            sigma = est.noise_estimate["accel"][:, 550].diagonal(dim1=-2, dim2=-1).sqrt()
            assert float(sigma.mean()) > 0.75  # tracks the 1.5 m/s^2 burst
    assert errors["adaptive"] < 0.9 * errors["fixed"], errors


def test_strong_tracking_follows_a_rate_step():
    """A stiff rate model (angular acceleration density 0.01) and a 1 rad/s step about x:
    with strong tracking on the gyro block the rate error 0.05-0.5 s after the step is
    several times smaller."""
    dt, n = 0.01, 300
    omega = torch.zeros(n, 3, dtype=DTYPE)
    omega[150:, 0] = 1.0
    gen = torch.Generator().manual_seed(6)
    gyro = omega + 1e-3 / math.sqrt(dt) * torch.randn(2, n, 3, generator=gen, dtype=DTYPE)
    rot = [torch.eye(3, dtype=DTYPE)]
    for k in range(1, n):
        rot.append(rot[-1] @ so3.exp(omega[k] * dt))
    rot = torch.stack(rot)
    accel = (rot.mT @ torch.tensor([0.0, 0.0, G], dtype=DTYPE)[:, None])[..., 0].expand(2, n, 3)
    base = dict(angular_accel_density=0.01, adaptive_noise_blocks=())
    errors = {}
    for name, blocks in (("plain", ()), ("strong", ("rate",))):
        cfg = AttitudeUkfConfig(1e-3, 1e-3, strong_tracking_blocks=blocks, **base)
        est = run_attitude_ukf(gyro, accel, dt, cfg)
        errors[name] = float((est.angular_rate[:, 155:200] - omega[155:200]).norm(dim=-1).mean())
        if name == "strong":
            assert float(est.fading_factor[:, 150:160].max()) > 1.0
            assert float(est.fading_factor[:, 20:140].max()) < 1.5
    assert errors["strong"] < 0.3 * errors["plain"], errors


def test_quaternion_fixes_make_yaw_observable():
    dt, n = 0.01, 300
    yaw = 0.8
    rot = so3.exp(torch.tensor([0.05, -0.03, yaw], dtype=DTYPE))
    gen = torch.Generator().manual_seed(7)
    gyro = 1e-4 / math.sqrt(dt) * torch.randn(1, n, 3, generator=gen, dtype=DTYPE)
    accel = (rot.mT @ torch.tensor([0.0, 0.0, G], dtype=DTYPE))[None, None].expand(1, n, 3)
    fixes = matrix_to_quat(rot @ so3.exp(0.01 * torch.randn(n, 3, generator=gen, dtype=DTYPE)))
    mask = torch.zeros(1, n, dtype=torch.bool)
    mask[:, ::10] = True
    cfg = AttitudeUkfConfig(1e-4, 1e-3, init_yaw_sigma_rad=1.0)
    with_fix = run_attitude_ukf(gyro, accel, dt, cfg, fixes[None], mask)
    without = run_attitude_ukf(gyro, accel, dt, cfg)
    err_fix = so3.log(rot.mT @ with_fix.rotation[0, -1]).norm()
    err_without = so3.log(rot.mT @ without.rotation[0, -1]).norm()
    assert float(err_fix) < 0.01
    assert float(err_without) > 0.5  # yaw stays at its initial 0


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"gyro_noise_density": 0.0}, "gyro_noise_density"),
        ({"adaptive_noise_blocks": ("mag",)}, "adaptive_noise_blocks"),
        ({"init_samples": 0}, "init_samples"),
        ({"init_yaw_sigma_rad": -1.0}, "init_yaw_sigma_rad"),
        # below 1 the fading factor was silently 1 (strong tracking off)
        ({"max_factor": 0.5}, "max_factor"),
        ({"softening": -1.0}, "softening"),
        ({"noise_floor": 0.0}, "noise_floor"),
        ({"clip_probability": 0.0}, "clip_probability"),
        ({"forgetting": 1.0}, "forgetting"),
        ({"prior_samples": -0.5}, "prior_samples"),
    ],
)
def test_config_validation(changes, match):
    values = {"gyro_noise_density": 1e-4, "accel_noise_density": 1e-3} | changes
    with pytest.raises(ValueError, match=match):
        AttitudeUkfConfig(**values).validate()


def test_no_samples_is_a_clear_error():
    """T = 0 used to fail inside torch (a reshape of 0 elements)."""
    empty = torch.zeros(2, 0, 3, dtype=DTYPE)
    with pytest.raises(ValueError, match="no samples"):
        run_attitude_ukf(empty, empty, 0.01, AttitudeUkfConfig(1e-4, 1e-3))


@pytest.mark.parametrize(
    ("field", "index", "match"),
    [("gyro", (1, 20, 0), r"gyro\[1, 20\]"), ("accel", (0, 7, 2), r"accel\[0, 7\]")],
)
def test_a_non_finite_sample_is_named(field, index, match):
    """A NaN sample of one filter used to stop the whole batch later with 'covariance lost
    positive definiteness', naming neither the filter nor the sample."""
    data = {
        "gyro": torch.zeros(2, 50, 3, dtype=DTYPE),
        "accel": torch.tensor([0.0, 0.0, G], dtype=DTYPE).repeat(2, 50, 1),
    }
    data[field][index] = math.nan
    with pytest.raises(ValueError, match=match):
        run_attitude_ukf(data["gyro"], data["accel"], 0.01, AttitudeUkfConfig(1e-4, 1e-3))
    dt = torch.full((2, 50), 0.01, dtype=DTYPE)
    dt[0, 3] = -0.01
    with pytest.raises(ValueError, match=r"dt\[0, 3\] is not >= 0"):
        run_attitude_ukf(
            torch.zeros(2, 50, 3, dtype=DTYPE),
            data["accel"].nan_to_num(),
            dt,
            AttitudeUkfConfig(1e-4, 1e-3),
        )
