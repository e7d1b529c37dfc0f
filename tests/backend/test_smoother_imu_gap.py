"""The smoothers over an IMU dropout: the gap's unknown motion in the preintegration.

References: the closed form ``q^2 T^3 / 3`` of a random walk's integral for the gap
variance, the simulator's ground truth for a 10-s dropout with wheels and GNSS running (the
per-axis covariance against autograd noise Jacobians: ``test_backend_preintegration.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.backend import window as W
from msf_torch.backend.preintegration import cut_imu, recursive_covariance
from msf_torch.eval.metrics import ate
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.schedule import gap_lengths
from msf_torch.sim import SimConfig, simulate_run

DTYPE = torch.float64


@pytest.mark.parametrize("keyframes", [[0.0, 20.0], [0.0, 4.0, 6.5, 7.0, 11.0, 20.0]])
def test_gap_heading_variance_is_the_random_walk_integral(keyframes):
    # a still IMU at 100 Hz with a 10-s dropout from 5 s; however keyframes cut the gap,
    # the yaw variances of the intervals add up to the gap's q^2 T^3 / 3 (plus the held
    # sample's scaled white noise and the measured samples' noise)
    t = torch.arange(0, 2001, dtype=DTYPE) * 0.01
    t = t[(t <= 5.0) | (t >= 15.0)]
    gyro = torch.zeros(t.numel(), 3, dtype=DTYPE)
    accel = torch.tensor([0.0, 0.0, 9.8], dtype=DTYPE).expand(t.numel(), 3)
    spacing = torch.cat((t[1:] - t[:-1], t.new_zeros(1)))
    cfg = EskfConfig()
    smoother = W.SmootherConfig()
    still = np.zeros(t.numel(), dtype=bool)  # no filled-in stretch
    length = torch.as_tensor(gap_lengths(t.numpy(), spacing.numpy(), still, cfg.imu_gap_s))
    assert float(length.max()) == pytest.approx(10.0) and int((length > 0).sum()) == 1
    scales = W._gap_noise_scales(length, cfg, smoother)
    knots = torch.tensor(keyframes, dtype=DTYPE)
    cut = cut_imu(t, gyro, accel, knots)
    scale = cut_imu(t, scales[:, :3], scales[:, 3:], knots)
    zero = torch.zeros(knots.numel() - 1, 3, dtype=DTYPE)
    cov_g, _ = recursive_covariance(
        cut.gyro, cut.accel, cut.dt, zero, zero, scale.gyro, scale.accel
    )
    yaw = cfg.gyro_noise_density**2 * cov_g[:, 8, 8].sum()
    walk = smoother.imu_gap_gyro_rw_density[2]
    expect = walk**2 * 10.0**3 / 3.0 + cfg.gyro_noise_density**2 * (
        cfg.imu_gap_noise_scale * 10.0 + 10.0
    )
    assert float(yaw) == pytest.approx(expect, rel=1e-9)


def test_gap_densities_are_validated():
    with pytest.raises(ValueError, match="smoother.imu_gap_gyro_rw_density"):
        W.SmootherConfig(imu_gap_gyro_rw_density=[0.1, 0.1]).validate()
    with pytest.raises(ValueError, match="smoother.imu_gap_accel_rw_density"):
        W.SmootherConfig(imu_gap_accel_rw_density=[0.1, -0.1, 0.1]).validate()


def test_ten_second_imu_dropout_with_wheels_and_gnss_running():
    # a 60-s simulated drive; no IMU sample from 25 s to 35 s, wheels and GNSS go on. The
    # held sample's variance only x100 (before the gap's random walk): keyframe trajectory
    # ATE 7.3 m full batch, 3.9 m sliding window (front end 4.5 m); now 0.31 and 0.35 m
    run = simulate_run(SimConfig(duration_s=60.0), seed=3)
    imu = run.sequence.imu
    keep = (imu.t[0] <= 25.0) | (imu.t[0] >= 35.0)
    seq = dataclasses.replace(run.sequence, imu=imu.map(lambda x: x[:, keep]))
    cfg = config_for_sequence(load_config(), seq.meta, set())
    with torch.no_grad():
        frontend = run_eskf(seq, cfg)
        for mode in ("full", "window"):
            result = W.smooth(seq, frontend, cfg, W.SmootherConfig(covariance=False), mode)
            rmse = ate(result.output, seq.ground_truth, align="none", max_dt=0.02)["rmse"]
            assert rmse < 1.0, (mode, rmse)
