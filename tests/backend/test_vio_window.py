"""Keyframe visual-inertial BA (``msf_torch.backend.vio``) on a simulated run with known truth.

The truth is the exact zero-order-hold integration (``sensors.imu.zoh_step``) of smooth
body rates and specific forces sampled at 200 Hz, after 0.5 s at rest; the IMU reads them
plus biases and white noise of the stated densities; a camera on the body (the
EuRoC-like extrinsics: optical axis along body x) sees 30 landmarks on a wall 4-6 m ahead
at 10 Hz with normalized-coordinate noise sigma = 1e-3; the biases follow a random walk of
the stated densities. Checks:

* from a perturbed truth, the batch (no kernel) converges to within the noise: the
  normalized estimation error squared ``e^T H e`` over all states and landmarks is below
  the chi-square 99.9 % bound and above the 0.1 % one (H the Gauss-Newton information at
  the estimate), and every component is within 4.5 marginal sigmas;
* one LM step with the landmarks eliminated by the Schur complement equals the plain
  dense step to 1e-9;
* the whole pipeline (``solve_vio``: rest initialisation, growing window, final batch under
  the Huber kernel) recovers the trajectory to centimetres and the biases, with a
  reprojection RMS at the noise level.
"""

from __future__ import annotations

import math

import pytest
import torch
from scipy.stats import chi2

from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.preintegration import cut_imu
from msf_torch.backend.variables import pack_nav_state, unpack_nav_state
from msf_torch.backend.vio import (
    VioConfig,
    VioData,
    build_vio_problem,
    camera_poses,
    first_state_prior,
    gravity_aligned_rotation,
    keyframe_imu_factor_inputs,
    solve_vio,
)
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.imu import ImuNoise, zoh_step

DTYPE = torch.float64
IMU_DT = 0.005
DURATION = 2.0
REST = 0.5
FRAME_EVERY = 20  # IMU samples per camera frame (10 Hz)
SIGMA_UV = 1e-3
NOISE = ImuNoise(*(torch.tensor(x, dtype=DTYPE) for x in (2e-4, 2e-3, 1e-5, 1e-4)))
GYRO_BIAS = torch.tensor([0.004, -0.006, 0.008], dtype=DTYPE)
ACCEL_BIAS = torch.tensor([0.03, -0.02, 0.04], dtype=DTYPE)
R_BODY_CAM = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=DTYPE)
T_BODY_CAM = torch.tensor([0.05, -0.02, 0.01], dtype=DTYPE)


def _simulate(seed: int = 0):
    """Truth (states at every IMU sample, landmarks) and noisy measurements."""
    gen = torch.Generator().manual_seed(seed)
    gravity = gravity_world()
    count = round(DURATION / IMU_DT) + 1
    t = torch.arange(count, dtype=DTYPE) * IMU_DT
    ramp = torch.clamp((t - REST) / 0.5, 0.0, 1.0)
    ramp = 0.5 - 0.5 * torch.cos(math.pi * ramp)
    omega = ramp[:, None] * torch.stack(
        (0.3 * torch.sin(2.0 * t), 0.4 * torch.sin(1.3 * t + 0.5), 0.5 * torch.sin(1.7 * t)), -1
    )
    accel_world = ramp[:, None] * torch.stack(
        (0.8 * torch.sin(2.5 * t), 1.0 * torch.sin(1.9 * t), 0.4 * torch.sin(3.1 * t)), -1
    )
    rotation = gravity_aligned_rotation(torch.tensor([0.3, -0.2, 9.7], dtype=DTYPE))
    position = torch.zeros(3, dtype=DTYPE)
    velocity = torch.zeros(3, dtype=DTYPE)
    positions, velocities, rotations, forces = [], [], [], []
    for k in range(count):
        positions.append(position)
        velocities.append(velocity)
        rotations.append(rotation)
        force = rotation.mT @ (accel_world[k] - gravity)
        forces.append(force)
        position, velocity, rotation = zoh_step(
            position,
            velocity,
            rotation,
            omega[k],
            force,
            torch.tensor(IMU_DT, dtype=DTYPE),
            gravity,
        )
    positions, velocities = torch.stack(positions), torch.stack(velocities)
    rotations, forces = torch.stack(rotations), torch.stack(forces)
    # biases: a random walk of the stated densities from GYRO_BIAS, ACCEL_BIAS
    walk = torch.randn(count, 6, generator=gen, dtype=DTYPE) * math.sqrt(IMU_DT)
    walk[0] = 0.0
    gyro_bias = GYRO_BIAS + NOISE.gyro_bias_rw_density * torch.cumsum(walk[:, 0:3], 0)
    accel_bias = ACCEL_BIAS + NOISE.accel_bias_rw_density * torch.cumsum(walk[:, 3:6], 0)
    white = torch.randn(count, 6, generator=gen, dtype=DTYPE) / math.sqrt(IMU_DT)
    gyro = omega + gyro_bias + NOISE.gyro_noise_density * white[:, 0:3]
    accel = forces + accel_bias + NOISE.accel_noise_density * white[:, 3:6]
    states = pack_nav_state(positions, velocities, rotations, gyro_bias, accel_bias)
    frames = torch.arange(0, count, FRAME_EVERY)
    landmarks = torch.stack(
        (
            4.0 + 2.0 * torch.rand(30, generator=gen, dtype=DTYPE),
            -2.0 + 4.0 * torch.rand(30, generator=gen, dtype=DTYPE),
            -1.5 + 3.0 * torch.rand(30, generator=gen, dtype=DTYPE),
        ),
        -1,
    )
    centre, cam_rot = camera_poses(states[frames], R_BODY_CAM, T_BODY_CAM)
    local = (cam_rot.mT[:, None] @ (landmarks[None] - centre[:, None])[..., None]).squeeze(-1)
    assert bool((local[..., 2] > 1.0).all())
    uv = local[..., 0:2] / local[..., 2:3]
    uv = uv + SIGMA_UV * torch.randn(uv.shape, generator=gen, dtype=DTYPE)
    obs_frame = torch.arange(frames.numel())[:, None].expand(-1, 30).reshape(-1)
    obs_landmark = torch.arange(30)[None].expand(frames.numel(), -1).reshape(-1)
    data = VioData(
        imu_t=t,
        gyro=gyro,
        accel=accel,
        frame_times=t[frames],
        obs_frame=obs_frame,
        obs_landmark=obs_landmark,
        obs_uv=uv.reshape(-1, 2),
        body_rotation_cam=R_BODY_CAM,
        body_translation_cam=T_BODY_CAM,
        feature_sigma=SIGMA_UV,
        imu_noise=NOISE,
    )
    return data, states[frames], landmarks


@pytest.fixture(scope="module")
def simulated():
    return _simulate()


def _local(origin: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """Tangent (..., 15) taking nav states ``origin`` to ``value`` (both (..., 21))."""
    p0, v0, r0, bg0, ba0 = unpack_nav_state(origin)
    p, v, r, bg, ba = unpack_nav_state(value)
    return torch.cat((p - p0, v - v0, so3.log(r0.mT @ r), bg - bg0, ba - ba0), -1)


def _batch_problem(data: VioData, truth_states: torch.Tensor, truth_points: torch.Tensor):
    """The batch over every frame from a perturbed truth, prior centred on the truth."""
    gen = torch.Generator().manual_seed(7)
    num = truth_states.shape[0]
    position, velocity, rotation, _, _ = unpack_nav_state(truth_states)
    zero = torch.zeros(num, 3, dtype=DTYPE)
    init = pack_nav_state(
        position + 0.02 * torch.randn(num, 3, generator=gen, dtype=DTYPE),
        velocity + 0.02 * torch.randn(num, 3, generator=gen, dtype=DTYPE),
        rotation @ so3.exp(0.01 * torch.randn(num, 3, generator=gen, dtype=DTYPE)),
        zero,
        zero,
    )
    points = truth_points + 0.05 * torch.randn(truth_points.shape, generator=gen, dtype=DTYPE)
    intervals = cut_imu(data.imu_t, data.gyro, data.accel, data.frame_times)
    pre, cov = keyframe_imu_factor_inputs(intervals, init, data.imu_noise)
    return build_vio_problem(
        init[None],
        points[None],
        data.obs_frame,
        data.obs_landmark,
        data.obs_uv,
        pre,
        cov,
        R_BODY_CAM,
        T_BODY_CAM,
        SIGMA_UV,
        gravity_world(),
        truth_states[0],
        first_state_prior(truth_states[0], VioConfig()),
    )


@pytest.fixture(scope="module")
def batch(simulated):
    return _batch_problem(*simulated)


def test_batch_recovers_truth_within_noise(simulated, batch):
    _, truth_states, truth_points = simulated
    problem = batch
    result = solve(problem, LMConfig(max_iterations=30, eliminate="landmark"))
    assert result.status == ["converged"]
    states = result.values["state"][0]
    points = result.values["landmark"][0]
    error = torch.cat(
        (_local(states, truth_states).reshape(-1), (truth_points - points).reshape(-1))
    )
    hessian = problem.linearize(result.values).hessian[0]
    nees = float(error @ hessian @ error)
    dim = error.numel()
    assert nees < chi2.ppf(0.999, dim), (nees, dim)
    assert nees > chi2.ppf(0.001, dim), (nees, dim)
    # every component within 4.5 marginal sigmas (480 components: a false alarm < 0.5 %)
    sigma = torch.sqrt(torch.diagonal(torch.linalg.inv(hessian)))
    assert float((error / sigma).abs().max()) < 4.5


def test_schur_step_equals_dense_step(batch):
    problem = batch
    schur = solve(problem, LMConfig(max_iterations=1, eliminate="landmark"))
    dense = solve(problem, LMConfig(max_iterations=1, linear_solver="dense"))
    assert bool(schur.log[0]["accepted"][0]) and bool(dense.log[0]["accepted"][0])
    for group in ("state", "landmark"):
        torch.testing.assert_close(schur.values[group], dense.values[group], rtol=0.0, atol=1e-9)
    torch.testing.assert_close(schur.cost, dense.cost, rtol=1e-9, atol=0.0)


def test_pipeline_recovers_trajectory(simulated):
    data, truth_states, _ = simulated
    growth_lm = LMConfig(max_iterations=5, relative_tolerance=1e-6, eliminate="landmark")
    config = VioConfig(keyframe_stride=1, rest_duration=0.4, window=10, growth_lm=growth_lm)
    result = solve_vio(data, config)
    assert result.lm.status == ["converged"]
    assert result.counts["landmarks_kept"] == 30
    assert result.counts["track_cuts_at_jumps"] == 0
    assert result.counts["observations_kept"] == data.obs_frame.numel()
    rms = math.sqrt(float((result.residual**2).mean()))
    assert 0.7 * SIGMA_UV < rms < 1.3 * SIGMA_UV
    position_error = (result.states[:, 0:3] - truth_states[:, 0:3]).norm(dim=-1)
    assert float(position_error.max()) < 0.03
    gyro_bias_error = (result.states[:, 15:18] - truth_states[:, 15:18]).norm(dim=-1)
    assert float(gyro_bias_error.max()) < 2e-3


def test_gravity_alignment_levels_the_measured_up_and_refuses_no_up() -> None:
    # against scipy: the rotation takes the measured up onto +z with no turn about it
    from scipy.spatial.transform import Rotation

    force = torch.tensor([[0.3, -0.2, 9.7], [0.0, 0.0, -9.8], [4.0, 3.0, 0.0]], dtype=DTYPE)
    rotation = gravity_aligned_rotation(force)
    up = (rotation @ (force / force.norm(dim=-1, keepdim=True))[..., None])[..., 0]
    torch.testing.assert_close(up, torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=DTYPE))
    expected, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], force[2:].numpy())
    torch.testing.assert_close(rotation[2], torch.from_numpy(expected.as_matrix()))
    for bad in ([float("nan"), 0.0, 9.8], [0.0, 0.0, 0.0]):
        with pytest.raises(ValueError, match="finite and non-zero"):
            gravity_aligned_rotation(torch.tensor(bad, dtype=DTYPE))
