"""ESKF against filterpy's linear KalmanFilter on a linear-Gaussian problem (acceptance, 1e-9).

The gyro reads exactly 0, the attitude is level and known (zero attitude and bias variance,
zero gyro noise and bias random walks), so the error-state filter reduces to a linear KF on
``[p, v]`` with the world acceleration ``R0 f + g`` as control input. filterpy steps once per
IMU sample (ZOH: ``F = [[I, dt I], [0, I]]``, ``B = [[dt^2/2 I], [dt I]]``, a sample's accel
noise ``sigma_a^2 / dt`` held for ``dt``: ``Q = sigma_a^2 [[dt^3/4, dt^2/2], [dt^2/2, dt]]``
per axis, the convention ``tests/sensors/test_imu_preintegration.py`` checks) and updates at
the GNSS fixes, and (second test) at GNSS velocities too (``H = [0, I]``; an up component the
receiver did not give drops its row).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from error_state_checks import level_sequence
from filterpy.kalman import KalmanFilter

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.types import GnssVelocity

DTYPE = torch.float64
G = 9.80665
ACCEL_DENSITY = 0.02


def _config() -> EskfConfig:
    return EskfConfig(
        gyro_noise_density=0.0,
        accel_noise_density=ACCEL_DENSITY,
        gyro_bias_rw_density=0.0,
        accel_bias_rw_density=0.0,
        gravity_mps2=G,
        init_position_sigma_m=1.5,
        init_velocity_sigma_mps=0.4,
        init_roll_pitch_sigma_rad=0.0,
        init_yaw_sigma_rad=0.0,
        init_yaw_sigma_unknown_rad=0.0,  # the heading is known: level and yaw 0
        init_gyro_bias_sigma_radps=0.0,
        init_accel_bias_sigma_mps2=0.0,
        init_min_gnss_distance_m=1e9,  # yaw 0, velocity 0, position = first fix
        nhc="off",
        zupt=False,
        gate_probability=1.0,
        slip_detection=False,
        # the synthetic IMU is exactly constant, which is what a recorder's linear fill
        # looks like (sensors.imu_gaps): the linear model here has no such stretches
        imu_interpolated_min_samples=0,
    )


def _problem(seed: int, duration: float = 6.0, imu_rate: float = 100.0, gnss_every: int = 20):
    """IMU with jittered sample times; GNSS fixes on every ``gnss_every``-th IMU sample."""
    rng = np.random.default_rng(seed)
    n = int(duration * imu_rate) + 1
    dt = 1.0 / imu_rate * (1.0 + 0.2 * rng.uniform(-1, 1, n - 1))
    t = np.concatenate(([0.0], np.cumsum(dt)))
    accel_world = np.zeros((n, 3))
    moving = t > 0.6  # level and still over the 0.5 s roll/pitch window
    accel_world[moving] = np.cumsum(0.1 * rng.normal(size=(moving.sum(), 3)), 0)
    accel_world[:, 2] *= 0.2
    f = accel_world + np.array([0.0, 0.0, G])  # R0 = I: f = a - g_world
    # a reference path (any values do; they only enter as measurements)
    vel = np.concatenate((np.zeros((1, 3)), np.cumsum(accel_world[:-1] * dt[:, None], 0)))
    pos = np.concatenate((np.zeros((1, 3)), np.cumsum(vel[:-1] * dt[:, None], 0)))
    pos += np.array([3.0, -2.0, 1.0])
    g_idx = np.arange(0, n, gnss_every)
    sigma = rng.uniform(0.3, 1.2, (g_idx.size, 3))
    fixes = pos[g_idx] + sigma * rng.normal(size=(g_idx.size, 3))
    seq = level_sequence(f"linear{seed}", t, f, g_idx, fixes, sigma)
    return seq, t, f, g_idx, fixes, sigma


def _filterpy_run(t, f, g_idx, fixes, sigma, x0, p0, velocities=None, log_likelihood=None):
    """Step filterpy per IMU sample; return {imu index: (x (6,), P (6, 6))} at the fixes.

    ``velocities``: optional (indices, values (M, 3) with NaN up where not given, sigmas):
    GNSS velocity updates after the fix at the same sample. ``log_likelihood``: a dict that
    gets filterpy's innovation log-likelihood of each fix, by IMU index."""
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x = x0.reshape(6, 1).copy()
    kf.P = p0.copy()
    kf.H = np.hstack((np.eye(3), np.zeros((3, 3))))
    gravity = np.array([0.0, 0.0, -G])
    fix_at = {int(k): i for i, k in enumerate(g_idx)}
    vel_at = {} if velocities is None else {int(k): i for i, k in enumerate(velocities[0])}
    eye = np.eye(3)
    out = {}
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        kf.F = np.block([[eye, dt * eye], [0 * eye, eye]])
        kf.B = np.vstack((0.5 * dt**2 * eye, dt * eye))
        kf.Q = ACCEL_DENSITY**2 * np.block(
            [[dt**3 / 4 * eye, dt**2 / 2 * eye], [dt**2 / 2 * eye, dt * eye]]
        )
        u = (f[k] + gravity).reshape(3, 1)  # world acceleration R0 f + g, R0 = I
        kf.predict(u=u)
        if k + 1 in fix_at:
            i = fix_at[k + 1]
            kf.update(fixes[i].reshape(3, 1), R=np.diag(sigma[i] ** 2))
            out[k + 1] = (kf.x[:, 0].copy(), kf.P.copy())
            if log_likelihood is not None:
                log_likelihood[k + 1] = float(kf.log_likelihood)
        if k + 1 in vel_at:
            i = vel_at[k + 1]
            value, vel_sigma = velocities[1][i], velocities[2][i]
            rows = np.flatnonzero(~np.isnan(value))
            h = np.hstack((np.zeros((3, 3)), eye))[rows]
            kf.update(value[rows].reshape(-1, 1), R=np.diag(vel_sigma[rows] ** 2), H=h)
            out[k + 1] = (kf.x[:, 0].copy(), kf.P.copy())
    out["last"] = (kf.x[:, 0].copy(), kf.P.copy())
    return out


@pytest.mark.parametrize("seed", [60, 61])
def test_eskf_equals_filterpy_on_linear_problem(seed):
    seq, t, f, g_idx, fixes, sigma = _problem(seed)
    cfg = _config()
    state0, cov0 = initial_state(seq, cfg)
    # the initial state the reduction assumes
    torch.testing.assert_close(state0.rotation[0], torch.eye(3, dtype=DTYPE), rtol=0, atol=0)
    torch.testing.assert_close(state0.velocity[0], torch.zeros(3, dtype=DTYPE), rtol=0, atol=0)
    torch.testing.assert_close(state0.position[0], torch.as_tensor(fixes[0]), rtol=0, atol=0)
    x0 = torch.cat((state0.position[0], state0.velocity[0])).numpy()
    p0 = cov0[0, :6, :6].numpy()
    assert np.all(cov0[0, 6:, :].numpy() == 0) and np.all(cov0[0, :, 6:].numpy() == 0)

    ref = _filterpy_run(t, f, g_idx, fixes, sigma, x0, p0)
    res = run_eskf(seq, cfg)

    times = res.t[0].numpy()
    imu_index = {float(t[k]): k for k in g_idx[1:]}
    compared = 0
    max_diff = {"p": 0.0, "v": 0.0, "P": 0.0}
    for e in range(1, times.size):
        if not bool(res.present["gnss"][0, e]):
            continue
        k = imu_index[float(times[e])]
        x_ref, p_ref = ref[k]
        assert bool(res.accepted["gnss"][0, e])
        diff_p = np.abs(res.position[0, e].numpy() - x_ref[:3]).max()
        diff_v = np.abs(res.velocity[0, e].numpy() - x_ref[3:]).max()
        diff_cov = np.abs(res.covariance[0, e, :6, :6].numpy() - p_ref).max()
        max_diff["p"] = max(max_diff["p"], diff_p)
        max_diff["v"] = max(max_diff["v"], diff_v)
        max_diff["P"] = max(max_diff["P"], diff_cov)
        compared += 1
    assert compared == g_idx.size - 1  # every fix after the first (t0) is an update
    assert max_diff["p"] < 1e-9 and max_diff["v"] < 1e-9 and max_diff["P"] < 1e-9, max_diff

    # the last epoch (last IMU sample) too
    x_ref, p_ref = ref["last"]
    np.testing.assert_allclose(res.position[0, -1].numpy(), x_ref[:3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.velocity[0, -1].numpy(), x_ref[3:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.covariance[0, -1, :6, :6].numpy(), p_ref, rtol=0, atol=1e-9)

    # attitude and biases untouched, their covariance blocks exactly zero
    assert torch.equal(res.rotation[0], torch.eye(3, dtype=DTYPE).expand_as(res.rotation[0]))
    assert float(res.gyro_bias.abs().max()) == 0.0 and float(res.accel_bias.abs().max()) == 0.0
    assert float(res.covariance[0, :, 6:, :].abs().max()) == 0.0
    assert float(res.covariance[0, :, :, 6:].abs().max()) == 0.0


def test_innovation_log_likelihood_equals_filterpy():
    """``nis`` and ``innovation_logdet`` give each fix's Gaussian innovation log-likelihood
    ``-(nis + log det S + 3 log 2 pi) / 2``: filterpy's ``log_likelihood`` after the same
    update (scipy's multivariate normal of the innovation under ``S``)."""
    seq, t, f, g_idx, fixes, sigma = _problem(64)
    cfg = _config()
    state0, cov0 = initial_state(seq, cfg)
    x0 = torch.cat((state0.position[0], state0.velocity[0])).numpy()
    reference: dict[int, float] = {}
    _filterpy_run(t, f, g_idx, fixes, sigma, x0, cov0[0, :6, :6].numpy(), None, reference)
    res = run_eskf(seq, cfg)
    times = res.t[0].numpy()
    imu_index = {float(t[k]): k for k in g_idx[1:]}
    fused = np.flatnonzero(res.present["gnss"][0].numpy())
    ours = -0.5 * (
        res.nis["gnss"][0, fused].numpy()
        + res.innovation_logdet["gnss"][0, fused].numpy()
        + 3.0 * np.log(2.0 * np.pi)
    )
    theirs = [reference[imu_index[float(times[e])]] for e in fused]
    assert fused.size == g_idx.size - 1
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9)
    absent = ~res.present["gnss"][0]
    assert float(res.innovation_logdet["gnss"][0, absent].abs().max()) == 0.0


@pytest.mark.parametrize("seed", [62, 63])
def test_gnss_velocity_updates_equal_filterpy_on_linear_problem(seed):
    """GNSS velocities every 10th IMU sample (half of them on a fix's sample, fused with it
    in one stacked update; every third horizontal only) against filterpy's sequential
    updates: the same linear KF, so the same estimate and covariance to rounding."""
    seq, t, f, g_idx, fixes, sigma = _problem(seed)
    rng = np.random.default_rng(seed + 100)
    v_idx = np.arange(10, t.size, 10)
    values = rng.normal(0.0, 0.5, (v_idx.size, 3))
    values[::3, 2] = np.nan
    vel_sigma = rng.uniform(0.05, 0.3, (v_idx.size, 3))
    seq.gnss_velocity = GnssVelocity(
        t=torch.as_tensor(t[v_idx])[None],
        velocity=torch.as_tensor(values)[None],
        sigma=torch.as_tensor(vel_sigma)[None],
        mask=torch.ones(1, v_idx.size, dtype=torch.bool),
    )
    seq.check()
    cfg = _config()
    state0, cov0 = initial_state(seq, cfg)
    x0 = torch.cat((state0.position[0], state0.velocity[0])).numpy()
    ref = _filterpy_run(
        t, f, g_idx, fixes, sigma, x0, cov0[0, :6, :6].numpy(), (v_idx, values, vel_sigma)
    )
    res = run_eskf(seq, cfg)
    times = res.t[0].numpy()
    compared = 0
    for e in range(1, times.size):
        if not bool(res.present["gnss_velocity"][0, e]):
            continue
        assert bool(res.accepted["gnss_velocity"][0, e])
        x_ref, p_ref = ref[int(np.flatnonzero(t == times[e])[0])]
        np.testing.assert_allclose(res.position[0, e].numpy(), x_ref[:3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.velocity[0, e].numpy(), x_ref[3:], rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.covariance[0, e, :6, :6].numpy(), p_ref, rtol=0, atol=1e-9)
        compared += 1
    assert compared == v_idx.size
    # the velocities moved the estimate: without them it differs by far more than 1e-9
    plain = run_eskf(_problem(seed)[0], cfg)
    assert float((plain.velocity[0, -1] - res.velocity[0, -1]).abs().max()) > 1e-3


def _predicted_at(t, f, g_idx, fixes, sigma, x0, p0, stop):
    """filterpy's state and covariance at IMU sample ``stop``, predicted, before any update
    there (the fixes before it fused)."""
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x, kf.P = x0.reshape(6, 1).copy(), p0.copy()
    kf.H = np.hstack((np.eye(3), np.zeros((3, 3))))
    fix_at = {int(k): i for i, k in enumerate(g_idx)}
    eye = np.eye(3)
    for k in range(stop):
        dt = t[k + 1] - t[k]
        kf.F = np.block([[eye, dt * eye], [0 * eye, eye]])
        kf.B = np.vstack((0.5 * dt**2 * eye, dt * eye))
        kf.Q = ACCEL_DENSITY**2 * np.block(
            [[dt**3 / 4 * eye, dt**2 / 2 * eye], [dt**2 / 2 * eye, dt * eye]]
        )
        kf.predict(u=(f[k] + np.array([0.0, 0.0, -G])).reshape(3, 1))
        if k + 1 in fix_at and k + 1 < stop:
            i = fix_at[k + 1]
            kf.update(fixes[i].reshape(3, 1), R=np.diag(sigma[i] ** 2))
    return kf.x[:, 0], kf.P


@pytest.mark.parametrize("up_given", [False, True])
def test_a_horizontal_only_velocity_is_gated_with_two_degrees_of_freedom(up_given):
    """A velocity whose horizontal innovation has NIS 20: above the 2-dof gate (18.42 at
    0.9999), below the 3-dof one (21.11). Without an up component it is rejected; with one
    that agrees with the prediction (NIS + 0) it passes."""
    seq, t, f, g_idx, fixes, sigma = _problem(64)
    cfg = _config().replace(gate_probability=0.9999)
    state0, cov0 = initial_state(seq, cfg)
    x0 = torch.cat((state0.position[0], state0.velocity[0])).numpy()
    k, sigma_v = 35, np.array([0.1, 0.1, 0.1])
    x, p = _predicted_at(t, f, g_idx, fixes, sigma, x0, cov0[0, :6, :6].numpy(), k)
    s = p[3:5, 3:5] + np.diag(sigma_v[:2] ** 2)
    direction = np.array([1.0, 0.0])
    offset = direction * np.sqrt(20.0 / (direction @ np.linalg.solve(s, direction)))
    value = np.append(x[3:5] + offset, x[5] if up_given else np.nan)
    seq.gnss_velocity = GnssVelocity(
        t=torch.tensor([[t[k]]]),
        velocity=torch.as_tensor(value)[None, None],
        sigma=torch.as_tensor(sigma_v)[None, None],
        mask=torch.ones(1, 1, dtype=torch.bool),
    )
    result = run_eskf(seq, cfg)
    at = result.present["gnss_velocity"][0]
    assert int(at.sum()) == 1
    assert float(result.nis["gnss_velocity"][0, at]) == pytest.approx(20.0, rel=1e-6)
    assert bool(result.accepted["gnss_velocity"][0, at]) == up_given
