"""The ESKF is differentiable w.r.t. its noise parameters (acceptance).

``torch.autograd.gradcheck`` of a trajectory loss (squared position error against the
ground truth at every epoch) of a 3 s simulated run with wheel + GNSS, w.r.t. the wheel
speed sigma and the accelerometer noise density. Gating and the slip factor are off so the
loss is smooth. A second sequence starts at a yaw of a half turn, with pose measurements,
to check that gradients stay finite there.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix, yaw_matrix
from msf_torch.sensors.imu import ImuNoise
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import PoseMeasurements

DTYPE = torch.float64
CFG = EskfConfig(gate_probability=1.0, slip_detection=False)


def _truth_at(run, times: torch.Tensor):
    """Truth position and rotation at epoch times (which are IMU sample times)."""
    rate = run.config.imu_rate_hz
    idx = torch.round(times * rate).long()
    assert float((run.truth.t[0, idx] - times).abs().max()) < 1e-9
    return run.truth.position[0, idx], run.truth.rotation[0, idx]


def _noise(wheel_speed_sigma: torch.Tensor, accel_density: torch.Tensor) -> EskfNoise:
    base = EskfNoise.from_config(CFG)
    imu = dataclasses.replace(base.imu, accel_noise_density=accel_density)
    return dataclasses.replace(base, imu=imu, wheel_speed_sigma=wheel_speed_sigma)


def test_gradcheck_trajectory_loss_wrt_noise_parameters():
    run = simulate_run(SimConfig(duration_s=3.0), seed=80)
    seq = run.sequence

    def loss(wheel_speed_sigma, accel_density):
        res = run_eskf(seq, CFG, _noise(wheel_speed_sigma, accel_density))
        pos_true, _ = _truth_at(run, res.t[0])
        return ((res.position[0] - pos_true) ** 2).sum()

    params = (
        torch.tensor(CFG.wheel_speed_sigma_mps, dtype=DTYPE, requires_grad=True),
        torch.tensor(CFG.accel_noise_density, dtype=DTYPE, requires_grad=True),
    )
    value = loss(*params)
    grads = torch.autograd.grad(value, params)
    assert all(torch.isfinite(g) and float(g) != 0.0 for g in grads), grads
    assert torch.autograd.gradcheck(loss, params, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_gradients_finite_from_a_half_turn_yaw():
    """Rotate the world so the run starts at yaw pi exactly about z; a pose at t0 fixes the
    initial attitude and poses every second are fused (pose residual ~ Log near identity)."""
    run = simulate_run(SimConfig(duration_s=3.0), seed=81)
    seq = run.sequence
    rot0 = run.truth.rotation[0, 0]
    yaw0 = math.atan2(float(rot0[1, 0]), float(rot0[0, 0]))
    turn = yaw_matrix(torch.tensor(math.pi - yaw0, dtype=DTYPE))

    def rotate(x):
        return (turn @ x[..., None])[..., 0]

    gnss = dataclasses.replace(seq.gnss, position=rotate(seq.gnss.position))
    truth_pos = rotate(run.truth.position[0])
    truth_rot = turn @ run.truth.rotation[0]
    pose_idx = torch.arange(0, truth_rot.shape[0], int(run.config.imu_rate_hz))
    n_pose = pose_idx.numel()
    cov = torch.diag(torch.tensor([0.1] * 3 + [0.02] * 3, dtype=DTYPE) ** 2)
    poses = PoseMeasurements(
        t=run.truth.t[:, pose_idx],
        position=truth_pos[pose_idx][None],
        quaternion=matrix_to_quat(truth_rot[pose_idx])[None],
        covariance=cov.expand(1, n_pose, 6, 6).clone(),
        mask=torch.ones(1, n_pose, dtype=torch.bool),
    )
    seq = dataclasses.replace(seq, gnss=gnss, poses=poses, ground_truth=None)
    start = quat_to_matrix(poses.quaternion[0, 0])
    assert abs(abs(math.atan2(float(start[1, 0]), float(start[0, 0]))) - math.pi) < 1e-12

    wheel_sigma = torch.tensor(0.05, dtype=DTYPE, requires_grad=True)
    accel_density = torch.tensor(CFG.accel_noise_density, dtype=DTYPE, requires_grad=True)
    res = run_eskf(seq, CFG, _noise(wheel_sigma, accel_density))
    assert bool(res.accepted["pose"].any())
    idx = torch.round(res.t[0] * run.config.imu_rate_hz).long()
    pos_err = res.position[0] - truth_pos[idx]
    rot_err = so3.log(truth_rot[idx].mT @ res.rotation[0])
    loss = (pos_err**2).sum() + (rot_err**2).sum()
    grads = torch.autograd.grad(loss, (wheel_sigma, accel_density))
    assert all(bool(torch.isfinite(g)) for g in grads), (
        f"non-finite gradient from a half-turn start: {grads}"
    )
    assert float(loss.detach()) < 10.0  # sane estimate
    # the initial attitude is the pose's, a half turn about z
    assert float(so3.log(start.mT @ res.rotation[0, 0].detach()).norm()) < 1e-12


def test_noise_as_batch_tensors_gives_per_sequence_gradients():
    """Noise fields of shape (B,) learn per sequence: d loss_b / d sigma_c = 0 for b != c."""
    from msf_torch.types import batch_sequences

    runs = [simulate_run(SimConfig(duration_s=2.0), seed=s) for s in (82, 83)]
    seq = batch_sequences([r.sequence for r in runs])
    sigma = torch.tensor([0.05, 0.08], dtype=DTYPE, requires_grad=True)
    base = EskfNoise.from_config(CFG)
    noise = dataclasses.replace(
        base,
        wheel_speed_sigma=sigma,
        imu=ImuNoise(
            base.imu.gyro_noise_density,
            base.imu.accel_noise_density,
            base.imu.gyro_bias_rw_density,
            base.imu.accel_bias_rw_density,
        ),
    )
    res = run_eskf(seq, CFG, noise)
    losses = []
    for b, run in enumerate(runs):
        n = int(res.mask[b].sum())
        pos_true, _ = _truth_at(run, res.t[b, :n])
        losses.append(((res.position[b, :n] - pos_true) ** 2).sum())
    jac = torch.stack([torch.autograd.grad(v, sigma, retain_graph=True)[0] for v in losses])
    assert torch.isfinite(jac).all()
    assert float(jac[0, 1]) == 0.0 and float(jac[1, 0]) == 0.0
    assert float(jac[0, 0]) != 0.0 and float(jac[1, 1]) != 0.0
