"""Feature tracks of the visual odometry for the back end's reprojection factors.

The back end's visual-inertial bundle adjustment takes observations in normalized image
coordinates ``[x/z, y/z]``
(:class:`~msf_torch.backend.factors.ReprojectionFactor`, landmarks eliminated by the Schur
complement). Two ways in:

* :func:`vio_data` converts a :class:`~msf_torch.vision.odometry.VoResult` (every PnP
  inlier of every frame, landmark ids that never repeat) and the run's IMU stream into a
  :class:`~msf_torch.backend.vio.VioData` for :func:`~msf_torch.backend.vio.solve_vio`
  (which initialises from a platform at rest);
* :func:`bundle_adjust` starts the same problem
  (:func:`~msf_torch.backend.vio.build_vio_problem`: first-state prior, IMU preintegration
  between keyframes, robust reprojection factors), plus one right-camera reprojection factor
  per landmark (the stereo match that created it: it fixes the scale, which monocular
  observations and a nearly unaccelerated IMU leave open), from the odometry itself: the
  odometry's
  keyframe poses and stereo map points, turned into a gravity-aligned world by the mean
  specific force over ``init_window_s`` from the first keyframe inside the IMU span (roll
  and pitch stay free in the solve), velocities by central differences of the odometry
  positions, zero biases; then one batched LM solve with the landmarks eliminated.

Which frames become states (``frames``): the odometry's keyframes (default: cheapest), or
every valid frame (``"all"``: every PnP inlier observation enters). On 4-s rendered runs
(10 Hz stereo, seeds 1-7, 2026-11-28, with the odometry's right-image re-matches at
keyframes) the aligned position RMS was, keyframes only 1.8-6.9 mm (median 4.9; below the
frame-to-frame odometry's 3.7-10.0 mm in 5 of 7 runs), every frame 1.4-4.9 mm (median 3.6;
below the odometry in all 7) at about 6x the time (1.6 s against 0.26 s for 41 frames).
What limits it: the left-camera tracks drift (KLT frame to frame), see docs/visual.md.
"""

from __future__ import annotations

__all__ = ["normalized_coordinates", "vio_data", "VisualInertialBa", "bundle_adjust"]

from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.backend.factors import ReprojectionFactor
from msf_torch.backend.lm import LMConfig, LMResult, solve
from msf_torch.backend.preintegration import cut_imu
from msf_torch.backend.problem import Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import pack_nav_state
from msf_torch.backend.vio import (
    HUBER_2DOF_95,
    VioConfig,
    VioData,
    build_vio_problem,
    first_state_prior,
    gravity_aligned_rotation,
    keyframe_imu_factor_inputs,
)
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.camera import CameraRig
from msf_torch.sensors.imu import ImuNoise
from msf_torch.types import ImuSamples
from msf_torch.vision.odometry import VoResult


def normalized_coordinates(pixels: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Normalized image coordinates (N, 2) ``((u - cx) / fx, (v - cy) / fy)`` of pixels
    (N, 2)."""
    return np.stack(((pixels[:, 0] - rig.cx) / rig.fx, (pixels[:, 1] - rig.cy) / rig.fy), -1)


def vio_data(
    result: VoResult,
    imu: ImuSamples,
    imu_noise: ImuNoise,
    pixel_sigma: float = 0.5,
    dtype: torch.dtype = torch.float64,
) -> VioData:
    """The back end's input from a visual-odometry result and the IMU stream.

    Frames outside the IMU span are left out (with their observations); frame indices are
    renumbered over the kept frames.

    Args:
        result: the odometry run (``record_tracks`` on).
        imu: B = 1 IMU samples on the same clock.
        imu_noise: IMU noise densities.
        pixel_sigma: feature sigma, px (converted with ``fx``).
        dtype: float dtype of the tensors.
    Returns:
        :class:`~msf_torch.backend.vio.VioData` with the left camera's extrinsics.
    Raises:
        ValueError: B is not 1 or no observation is left.
    """
    if imu.batch_size != 1:
        raise ValueError(f"vio_data: needs B = 1 IMU samples, got B = {imu.batch_size}")
    keep = imu.mask[0]
    imu_t = imu.t[0][keep].to(dtype)
    t0, t1 = float(imu_t[0]), float(imu_t[-1])
    inside = (result.t >= t0) & (result.t <= t1)
    renumber = np.cumsum(inside) - 1
    obs = inside[result.obs_frame]
    if not obs.any():
        raise ValueError("vio_data: no feature observation inside the IMU span")
    rig = result.rig
    uv = normalized_coordinates(result.obs_pixel[obs], rig)
    return VioData(
        imu_t=imu_t,
        gyro=imu.gyro[0][keep].to(dtype),
        accel=imu.accel[0][keep].to(dtype),
        frame_times=torch.as_tensor(result.t[inside], dtype=dtype),
        obs_frame=torch.as_tensor(renumber[result.obs_frame[obs]], dtype=torch.int64),
        obs_landmark=torch.as_tensor(result.obs_landmark[obs], dtype=torch.int64),
        obs_uv=torch.as_tensor(uv, dtype=dtype),
        body_rotation_cam=torch.as_tensor(rig.body_rotation_cam(), dtype=dtype),
        body_translation_cam=torch.as_tensor(rig.body_translation_cam(), dtype=dtype),
        feature_sigma=pixel_sigma / rig.fx,
        imu_noise=imu_noise,
    )


@dataclass
class VisualInertialBa:
    """Outcome of :func:`bundle_adjust`.

    Attributes:
        keyframe_frames: (K,) frame index of each state (the keyframes, or every valid
            frame with ``frames="all"``).
        keyframe_times: (K,) s.
        initial_states: (K, 21) nav states the solve started from (gravity-aligned world).
        states: (K, 21) solved nav states.
        landmarks: (L, 3) solved map points, world, m.
        landmark_index: (L,) their rows in the odometry's ``landmarks``.
        observations: M left-camera reprojection factors.
        stereo_observations: S right-camera reprojection factors.
        lm: the :class:`~msf_torch.backend.lm.LMResult` (B = 1).
    """

    keyframe_frames: np.ndarray
    keyframe_times: torch.Tensor
    initial_states: torch.Tensor
    states: torch.Tensor
    landmarks: torch.Tensor
    landmark_index: np.ndarray
    observations: int
    stereo_observations: int
    lm: LMResult


def bundle_adjust(
    result: VoResult,
    imu: ImuSamples,
    imu_noise: ImuNoise,
    pixel_sigma: float = 0.5,
    min_observations: int = 3,
    init_window_s: float = 0.5,
    lm: LMConfig | None = None,
    prior: VioConfig | None = None,
    kernel: RobustKernel | None = None,
    frames: str = "keyframes",
) -> VisualInertialBa:
    """Visual-inertial bundle adjustment over the odometry's keyframes or every valid
    frame (module docstring).

    Args:
        result: the odometry run (``record_tracks`` on).
        imu: B = 1 IMU samples on the same clock.
        imu_noise: IMU noise densities.
        pixel_sigma: feature sigma, px.
        min_observations: keyframe observations a landmark needs.
        init_window_s: accelerometer averaging for the initial roll and pitch, from the
            first keyframe inside the IMU span, s.
        lm: LM settings (default: 30 iterations, landmarks eliminated).
        prior: first-state prior sigmas (:func:`~msf_torch.backend.vio.first_state_prior`).
        kernel: robust kernel of the reprojection factors (default Huber at 2.45 sigma).
        frames: ``"keyframes"`` (the odometry's) or ``"all"`` (every valid frame) as states.
    Returns:
        :class:`VisualInertialBa`.
    Raises:
        ValueError: B is not 1, ``frames`` is neither choice, fewer than two keyframes lie
            in the IMU span, no IMU sample lies in the gravity window, or no landmark has
            enough observations.
    """
    if imu.batch_size != 1:
        raise ValueError(f"bundle_adjust: needs B = 1 IMU samples, got B = {imu.batch_size}")
    if frames not in ("keyframes", "all"):
        raise ValueError(f"bundle_adjust: frames must be 'keyframes' or 'all', got {frames!r}")
    dtype = torch.float64
    lm = lm or LMConfig(max_iterations=30, eliminate="landmark")
    prior = prior or VioConfig()
    kernel = kernel or RobustKernel("huber", HUBER_2DOF_95)
    keep = imu.mask[0]
    imu_t = imu.t[0][keep].to(dtype)
    gyro, accel = imu.gyro[0][keep].to(dtype), imu.accel[0][keep].to(dtype)
    t0, t1 = float(imu_t[0]), float(imu_t[-1])
    chosen = result.keyframe if frames == "keyframes" else np.ones_like(result.keyframe)
    states_at = np.nonzero(chosen & result.valid & (result.t >= t0) & (result.t <= t1))[0]
    if len(states_at) < 2:
        kind = "keyframes" if frames == "keyframes" else "valid frames"
        raise ValueError(f"bundle_adjust: {len(states_at)} {kind} in the IMU span, need 2")
    # gravity in the body at the first keyframe inside the IMU span, carried to the
    # odometry frame by that keyframe's attitude (the IMU may start after the odometry)
    first = states_at[0]
    start = result.t[first]
    rest = (imu_t >= start) & (imu_t <= start + init_window_s)
    if not bool(rest.any()):
        raise ValueError(
            f"bundle_adjust: no IMU sample in [{start:.3f}, {start + init_window_s:.3f}] s "
            f"(init_window_s after the first keyframe in the IMU span)"
        )
    level = gravity_aligned_rotation(accel[rest].mean(0)).numpy()
    to_world = level @ result.rotation[first].T
    position = result.position @ to_world.T
    velocity = np.gradient(position, result.t, axis=0)
    rotation = to_world @ result.rotation
    zero = torch.zeros(len(states_at), 3, dtype=dtype)
    states = pack_nav_state(
        torch.as_tensor(position[states_at]),
        torch.as_tensor(velocity[states_at]),
        torch.as_tensor(rotation[states_at]),
        zero,
        zero,
    )
    to_keyframe = np.full(len(result.t), -1, np.int64)
    to_keyframe[states_at] = np.arange(len(states_at))
    obs_kf = to_keyframe[result.obs_frame]
    in_kf = obs_kf >= 0
    seen = np.bincount(result.obs_landmark[in_kf], minlength=len(result.landmarks))
    good_landmark = seen >= min_observations
    use = in_kf & good_landmark[result.obs_landmark]
    landmark_index = np.nonzero(good_landmark)[0]
    if landmark_index.size == 0:
        raise ValueError("bundle_adjust: no landmark has enough keyframe observations")
    compact = np.full(len(result.landmarks), -1, np.int64)
    compact[landmark_index] = np.arange(landmark_index.size)
    points = torch.as_tensor(result.landmarks[landmark_index] @ to_world.T)
    times = torch.as_tensor(result.t[states_at], dtype=dtype)
    intervals = cut_imu(imu_t, gyro, accel, times)
    pre, cov = keyframe_imu_factor_inputs(intervals, states, imu_noise)
    rig = result.rig
    sigma = pixel_sigma / rig.fx
    base = build_vio_problem(
        states[None],
        points[None],
        torch.as_tensor(obs_kf[use]),
        torch.as_tensor(compact[result.obs_landmark[use]]),
        torch.as_tensor(normalized_coordinates(result.obs_pixel[use], rig)),
        pre,
        cov,
        torch.as_tensor(rig.body_rotation_cam(), dtype=dtype),
        torch.as_tensor(rig.body_translation_cam(), dtype=dtype),
        sigma,
        gravity_world(dtype=dtype),
        states[0],
        first_state_prior(states[0], prior),
        kernel=kernel,
    )
    stereo_kf = to_keyframe[result.stereo_frame]
    stereo_use = (stereo_kf >= 0) & good_landmark[result.stereo_landmark]
    count = int(stereo_use.sum())
    right = ReprojectionFactor(
        "state",
        torch.as_tensor(stereo_kf[stereo_use]),
        "landmark",
        torch.as_tensor(compact[result.stereo_landmark[stereo_use]]),
        torch.as_tensor(normalized_coordinates(result.stereo_pixel[stereo_use], rig))[None],
        (sigma**2 * torch.eye(2, dtype=dtype)).expand(1, count, 2, 2),
        torch.as_tensor(rig.body_rotation_cam(), dtype=dtype),
        torch.as_tensor(rig.body_translation_cam(right=True), dtype=dtype),
        kernel=kernel,
    )
    problem = Problem(variables=base.variables, factors=[*base.factors, right], fixed=base.fixed)
    solved = solve(problem, lm)
    return VisualInertialBa(
        keyframe_frames=states_at,
        keyframe_times=times,
        initial_states=states,
        states=solved.values["state"][0],
        landmarks=solved.values["landmark"][0],
        landmark_index=landmark_index,
        observations=int(use.sum()),
        stereo_observations=count,
        lm=solved,
    )
