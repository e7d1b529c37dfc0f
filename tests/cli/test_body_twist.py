"""The twist ``msf run --export rosbag2`` writes (``runner._body_twist``): the body-axes
velocity and bias-corrected gyro rate at the front end's epochs, and their covariance
against a Monte-Carlo draw of the error state under the conventions'
(``v = v_hat + dv``, ``R = R_hat Exp(dtheta)``, ``b = b_hat + db``)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from msf_torch.backend.window import OutputMotion
from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.runner import _body_twist
from msf_torch.sim import SimConfig, simulate_run

DENSITY = 2e-3
"""Gyro white noise for the rate block, rad/s/sqrt(Hz)."""


def test_twist_and_its_covariance_follow_the_error_state() -> None:
    seq = simulate_run(SimConfig(duration_s=6.0, slip_episodes=0), seed=2).sequence
    with torch.no_grad():
        result = run_eskf(seq, EskfConfig())
    keep = result.mask[0]
    motion = OutputMotion(
        result.velocity[:1, keep], result.gyro_bias[:1, keep], result.covariance[:1, keep]
    )
    twist, covariance = _body_twist(seq, result.trajectory().select(0).compact(), motion, DENSITY)
    epochs = int(keep.sum())
    assert twist.shape == (1, epochs, 6) and covariance.shape == (1, epochs, 6, 6)

    rotation = result.rotation[0, keep].numpy()
    velocity = result.velocity[0, keep].numpy()
    gyro_bias = result.gyro_bias[0, keep].numpy()
    t = result.t[0, keep].numpy()
    imu_t = seq.imu.t[0].numpy()
    gyro = seq.imu.gyro[0].numpy()
    for k in (5, epochs // 2, epochs - 2):
        np.testing.assert_allclose(twist[0, k, :3].numpy(), rotation[k].T @ velocity[k], atol=1e-12)
        # the gyro between the two samples around t_k, weighted by distance
        j = int(np.searchsorted(imu_t, t[k], side="right"))
        w = (t[k] - imu_t[j - 1]) / (imu_t[j] - imu_t[j - 1])
        rate = (1 - w) * gyro[j - 1] + w * gyro[j]
        np.testing.assert_allclose(twist[0, k, 3:].numpy(), rate - gyro_bias[k], atol=1e-12)

    # first order: errors drawn from (1e-3)^2 P, their twist covariance scaled back
    rng = np.random.default_rng(0)
    shrink = 1e-3
    sample_variance = DENSITY**2 * 200.0  # the simulated IMU runs at 200 Hz
    for k in (epochs // 3, epochs - 2):
        p = result.covariance[0, keep][k].numpy()
        dx = rng.multivariate_normal(np.zeros(15), shrink**2 * p, size=40_000)
        true_rotation = Rotation.from_matrix(rotation[k]) * Rotation.from_rotvec(dx[:, 6:9])
        true_linear = true_rotation.apply(velocity[k] + dx[:, 3:6], inverse=True)
        true_rate = twist[0, k, 3:].numpy() + gyro_bias[k] - (gyro_bias[k] + dx[:, 9:12])
        error = np.concatenate([true_linear, true_rate], 1) - twist[0, k].numpy()
        reference = np.cov(error.T) / shrink**2
        reference[3:, 3:] += sample_variance * np.eye(3)
        got = covariance[0, k].numpy()
        scale = np.sqrt(np.outer(np.diag(reference), np.diag(reference)))
        np.testing.assert_allclose(got / scale, reference / scale, atol=0.03)
