"""Visual-inertial bundle adjustment over keyframes: IMU preintegration + reprojection.

The problem (one full batch over every keyframe of a run, or any window of them) has
``nav_state`` variables ``"state"`` (K keyframes: position, velocity, attitude, gyro and
accel bias) and ``point`` variables ``"landmark"`` (L world points, the last group so that
LM can eliminate them by the Schur complement, ``LMConfig(eliminate="landmark")``). Its
factors are

* :class:`~msf_torch.backend.factors.ReprojectionFactor` per kept observation, normalized
  image coordinates ``[x/z, y/z]`` with an isotropic sigma (dimensionless) under a robust
  kernel;
* :class:`~msf_torch.backend.factors.ImuPreintegrationFactor` between consecutive
  keyframes (increments of :func:`~msf_torch.backend.preintegration.preintegrate_imu`, the
  exact recursive covariance and the bias random walk of
  :func:`~msf_torch.backend.preintegration.imu_covariance`);
* a :class:`~msf_torch.backend.factors.NavStatePriorFactor` on the first keyframe that fixes
  the gauge (position and yaw; gravity makes roll and pitch observable, so they are left
  free) and gives the biases a weak prior (:func:`first_state_prior`).

:func:`solve_vio` runs the whole pipeline on a :class:`VioData` (IMU stream, frame times,
feature tracks, extrinsics, noise):

1. tracks: landmark ids are split where a track jumps or skips a frame
   (:func:`split_tracks`; a replayed tracker may give a lost feature's id to a new one);
   each piece is a landmark of its own;
2. keyframes: every ``keyframe_stride``-th camera frame (:func:`select_keyframes`);
   observations in other frames are not used;
3. first state: gravity-aligned attitude (no turn about the vertical beyond the tilt,
   :func:`gravity_aligned_rotation`) from the mean specific force over the
   opening ``rest_duration`` seconds, zero position and velocity, the mean gyro rate there
   as the gyro bias guess, zero accel bias: the platform is assumed near rest at the start
   (EuRoC's MAV sits on the floor for ~4 s);
4. growing window: keyframes are added ``growth`` at a time, predicted by IMU
   preintegration from the last estimate; landmarks seen in two processed keyframes are
   triangulated linearly (:func:`triangulate`) or, with less than ``min_parallax_deg`` of
   parallax, put at ``fallback_depth`` along their latest bearing and re-triangulated once
   they have parallax; then LM refines the last ``window`` keyframes (older ones held
   fixed) and the landmarks they see (with all their observations);
5. final batch: the increments are re-preintegrated at the estimated biases, landmarks with
   fewer than ``min_observations`` keyframe observations or still without parallax are
   dropped, and LM (Schur complement over the landmarks) solves all keyframes and
   landmarks together under the robust kernel; once, observations beyond
   ``outlier_sigma`` are removed (with landmarks left with too few observations), and
   landmarks that end up behind a camera that sees them are dropped, each time followed by
   a new solve. Every drop is counted in :attr:`VioResult.counts`.
"""

from __future__ import annotations

__all__ = [
    "VioData",
    "VioConfig",
    "VioResult",
    "select_keyframes",
    "split_tracks",
    "gravity_aligned_rotation",
    "camera_poses",
    "triangulate",
    "first_state_prior",
    "keyframe_imu_factor_inputs",
    "build_vio_problem",
    "solve_vio",
]

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from msf_torch.backend.factors import (
    ImuPreintegrationFactor,
    NavStatePriorFactor,
    ReprojectionFactor,
)
from msf_torch.backend.lm import LMConfig, LMResult, solve
from msf_torch.backend.preintegration import (
    ImuIntervals,
    cut_imu,
    imu_covariance,
    preintegrate_imu,
)
from msf_torch.backend.problem import Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import pack_nav_state, unpack_nav_state
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import gravity_world
from msf_torch.sensors.imu import ImuNoise, Preintegrated, propagate_nominal

if TYPE_CHECKING:
    from msf_torch.io.eqvio import EqvioRun

HUBER_2DOF_95 = math.sqrt(5.991464547107979)
"""Default Huber scale, in sigmas: the 95 % quantile of the norm of a 2-D standard normal
(``sqrt(chi2_2(0.95))`` = 2.448), so 5 % of Gaussian inlier observations are downweighted."""


@dataclass
class VioData:
    """One visual-inertial recording, float64 on one device.

    Attributes:
        imu_t: (T,) IMU sample times, s, increasing.
        gyro: (T, 3) angular rate, rad/s, IMU (body) frame.
        accel: (T, 3) specific force, m/s^2, body frame.
        frame_times: (F,) camera frame times, s, increasing, inside the IMU span.
        obs_frame: (M,) int64 frame index of each feature observation.
        obs_landmark: (M,) int64 landmark index 0..L-1 of each observation.
        obs_uv: (M, 2) normalized image coordinates ``[x/z, y/z]`` in the camera frame.
        body_rotation_cam: (3, 3) camera -> body rotation, ``v_b = R_bc v_c``.
        body_translation_cam: (3,) camera centre in the body frame, m.
        feature_sigma: per-axis standard deviation of ``obs_uv`` (dimensionless).
        imu_noise: continuous-time IMU noise densities.
        gravity: (3,) world gravity, m/s^2 (``[0, 0, -g]``).
    """

    imu_t: torch.Tensor
    gyro: torch.Tensor
    accel: torch.Tensor
    frame_times: torch.Tensor
    obs_frame: torch.Tensor
    obs_landmark: torch.Tensor
    obs_uv: torch.Tensor
    body_rotation_cam: torch.Tensor
    body_translation_cam: torch.Tensor
    feature_sigma: float
    imu_noise: ImuNoise
    gravity: torch.Tensor = field(default_factory=gravity_world)

    @classmethod
    def from_eqvio(cls, run: EqvioRun) -> VioData:
        """The IMU, tracks, extrinsics (``T_imu_cam``) and noise of an
        :class:`~msf_torch.io.eqvio.EqvioRun`; the noise densities are the square roots of
        the file's EqF input variances, the feature sigma its normalized-units one.

        Raises:
            ValueError: the run lacks extrinsics, the feature sigma or the IMU noise.
        """
        needed = ("gyro_noise_sigma", "accel_noise_sigma", "gyro_bias_rw_sigma")
        missing = [k for k in (*needed, "accel_bias_rw_sigma") if k not in run.imu_noise]
        if run.R_imu_cam is None or run.feature_sigma_normalized is None or missing:
            raise ValueError(
                f"{run.source}: VIO needs T_imu_cam, the normalized feature noise and the "
                f"four IMU noise values; missing IMU noise keys: {missing}"
            )
        noise = ImuNoise(
            *(
                torch.tensor(run.imu_noise[k], dtype=torch.float64)
                for k in (*needed, "accel_bias_rw_sigma")
            )
        )
        return cls(
            imu_t=run.imu.t[0],
            gyro=run.imu.gyro[0],
            accel=run.imu.accel[0],
            frame_times=run.frame_times,
            obs_frame=run.obs_frame,
            obs_landmark=run.obs_landmark,
            obs_uv=run.obs_normalized,
            body_rotation_cam=run.R_imu_cam,
            body_translation_cam=run.t_imu_cam,
            feature_sigma=run.feature_sigma_normalized,
            imu_noise=noise,
        )


@dataclass
class VioConfig:
    """Settings of :func:`solve_vio`.

    Attributes:
        keyframe_stride: every k-th camera frame is a keyframe.
        min_observations: keyframe observations a landmark needs in the final batch.
        min_parallax_deg: below this triangulation angle (deg) a landmark is not
            triangulated but put at ``fallback_depth`` (and dropped from the final batch).
        fallback_depth: m along the optical axis for landmarks without parallax.
        min_depth: m; a landmark closer than this to (or behind) a camera that sees it is
            dropped from the final batch.
        rest_duration: s at the start assumed near rest (attitude and gyro bias guess).
        max_track_jump: normalized units; feature tracks are split where an id jumps by
            more than this beyond the gyro-predicted rotation (:func:`split_tracks`), or
            None to take the input ids as they are.
        kernel: robust kernel of the reprojection factors (scale in sigmas), or None.
        outlier_sigma: after the first final solve, observations whose whitened
            reprojection error ``|r| / sigma`` exceeds this are removed (once; a Gaussian
            2-D error does so with probability ``exp(-s^2 / 2)``, 3.7e-6 at 5) and the
            batch is solved again; None keeps every observation.
        growth: keyframes added per growing step.
        window: keyframes left free while growing (older ones are held fixed).
        growth_lm: LM settings while growing.
        final_lm: LM settings of the final batch.
        prior_position_sigma: m, gauge prior on the first position.
        prior_yaw_sigma: rad, gauge prior on the first yaw.
        prior_gyro_bias_sigma: rad/s, weak prior on the first gyro bias.
        prior_accel_bias_sigma: m/s^2, weak prior on the first accel bias (zero mean).
    """

    keyframe_stride: int = 4
    min_observations: int = 3
    min_parallax_deg: float = 1.0
    fallback_depth: float = 5.0
    min_depth: float = 0.1
    rest_duration: float = 1.0
    max_track_jump: float | None = 0.05
    outlier_sigma: float | None = 5.0
    kernel: RobustKernel | None = field(
        default_factory=lambda: RobustKernel("huber", HUBER_2DOF_95)
    )
    growth: int = 5
    window: int = 15
    growth_lm: LMConfig = field(
        default_factory=lambda: LMConfig(
            max_iterations=10, relative_tolerance=1e-6, eliminate="landmark"
        )
    )
    final_lm: LMConfig = field(
        default_factory=lambda: LMConfig(max_iterations=100, eliminate="landmark")
    )
    prior_position_sigma: float = 1e-3
    prior_yaw_sigma: float = 1e-3
    prior_gyro_bias_sigma: float = 0.1
    prior_accel_bias_sigma: float = 0.5


@dataclass
class VioResult:
    """Outcome of :func:`solve_vio`.

    Attributes:
        keyframe_frames: (K,) frame index of each keyframe.
        keyframe_times: (K,) s.
        states: (K, 21) final nav states (:func:`~msf_torch.backend.variables.pack_nav_state`).
        landmarks: (L', 3) world points of the landmarks kept, m.
        landmark_index: (L',) their track ids (see ``tracks``).
        tracks: (M,) track id of every input observation: the input landmark ids split
            by :func:`split_tracks` (the ids themselves with ``max_track_jump=None``).
        obs_keyframe: (M',) keyframe of each observation kept in the final batch.
        obs_landmark: (M',) index into ``landmarks`` of each kept observation.
        obs_index: (M',) index of each kept observation in the input arrays.
        residual: (M', 2) final reprojection residual (prediction - measurement), normalized.
        robust_weight: (M',) final IRLS weight of each observation (1 = not downweighted).
        rejected_index: (R,) input index of each observation removed by the outlier gate
            whose landmark was kept.
        rejected_residual: (R, 2) their residual at the final estimate, normalized.
        lm: the last final-batch solve's :class:`~msf_torch.backend.lm.LMResult` (B = 1).
        problem: that solve's :class:`~msf_torch.backend.problem.Problem` (its ``values``
            are the solve's initial values: the previous solve's result after the first).
        counts: what was kept and dropped (observations outside keyframes, landmarks with
            too few observations, without parallax, behind a camera, ...).
        growth_iterations: LM iterations summed over the growing stage.
        solve_costs: (initial, final) cost of each final-batch solve, in order (each on its
            own observation set).
        timings: wall seconds of the ``"growing"`` stage and the ``"final"`` batch
            (building and solving, every re-solve included).
    """

    keyframe_frames: torch.Tensor
    keyframe_times: torch.Tensor
    states: torch.Tensor
    landmarks: torch.Tensor
    landmark_index: torch.Tensor
    tracks: torch.Tensor
    obs_keyframe: torch.Tensor
    obs_landmark: torch.Tensor
    obs_index: torch.Tensor
    residual: torch.Tensor
    robust_weight: torch.Tensor
    rejected_index: torch.Tensor
    rejected_residual: torch.Tensor
    lm: LMResult
    problem: Problem
    counts: dict[str, int]
    growth_iterations: int
    solve_costs: list[tuple[float, float]]
    timings: dict[str, float]


def select_keyframes(
    num_frames: int, stride: int, device: torch.device | str | None = None
) -> torch.Tensor:
    """Every ``stride``-th frame index, starting with 0: (ceil(F / stride),) int64."""
    if stride < 1:
        raise ValueError(f"keyframe stride must be >= 1, got {stride}")
    return torch.arange(0, num_frames, stride, device=device)


def split_tracks(
    data: VioData, gyro_bias: torch.Tensor, max_jump: float
) -> tuple[torch.Tensor, int, int]:
    """Split feature tracks where the same landmark id stops following one point.

    A replayed tracker may hand a lost feature's id to a new feature. Between consecutive
    frames f, f + 1 the camera rotation ``R_c`` from the gyro (bias ``gyro_bias``) predicts
    where a tracked point goes if it is far away, ``[u, v, 1] ~ R_c^T [u_f, v_f, 1]``; what is
    left is the translational flow (a few 1e-3 for the EuRoC MAV at 20 Hz). A track is cut
    where that remainder exceeds ``max_jump`` (normalized units) and where its id skips a
    frame (a lost landmark is new when it comes back).

    Args:
        data: the recording. gyro_bias: (3,) rad/s used to derotate.
        max_jump: normalized units.
    Returns:
        track id (M,) int64 of each observation (0..L'-1, ordered by original id, then
        time), the number of cuts at jumps and the number at gaps.
    """
    frames = data.frame_times.shape[0]
    device = data.obs_frame.device
    intervals = cut_imu(data.imu_t, data.gyro, data.accel, data.frame_times)
    zero = torch.zeros_like(gyro_bias)
    count = frames - 1
    pre = preintegrate_imu(
        intervals, gyro_bias.expand(count, 3), zero.expand(count, 3), covariance="closed_form"
    )
    cam_rotation = data.body_rotation_cam.mT @ pre.delta_rotation @ data.body_rotation_cam
    order = torch.argsort(data.obs_landmark * frames + data.obs_frame)
    frame, landmark, uv = data.obs_frame[order], data.obs_landmark[order], data.obs_uv[order]
    same = landmark[1:] == landmark[:-1]
    consecutive = same & (frame[1:] == frame[:-1] + 1)
    bearing = torch.cat((uv[:-1], torch.ones_like(uv[:-1, :1])), -1)
    moved = (cam_rotation[frame[:-1].clamp_max(count - 1)].mT @ bearing[..., None]).squeeze(-1)
    predicted = moved[:, 0:2] / moved[:, 2:3]
    jump = consecutive & ((uv[1:] - predicted).norm(dim=-1) > max_jump)
    gap = same & ~consecutive
    start = torch.cat((torch.ones(1, dtype=torch.bool, device=device), ~same | jump | gap))
    track_sorted = torch.cumsum(start.long(), 0) - 1
    track = torch.empty_like(track_sorted)
    track[order] = track_sorted
    return track, int(jump.sum()), int(gap.sum())


def gravity_aligned_rotation(specific_force: torch.Tensor) -> torch.Tensor:
    """Body -> world rotation (..., 3, 3) under which a body at rest measuring
    ``specific_force`` (..., 3) m/s^2 is level (``conventions``: at rest
    ``f = R^T [0, 0, g]``): the smallest rotation taking the measured up direction onto world
    ``+z``, so no turn about the vertical is added (a half turn about body x when the
    measured up is exactly ``-z``).

    Raises:
        ValueError: a specific force is not finite or is zero (no up direction).
    """
    norm = specific_force.norm(dim=-1, keepdim=True)
    if not bool((torch.isfinite(specific_force).all(-1) & (norm[..., 0] > 0)).all()):
        raise ValueError(
            "gravity_aligned_rotation: every specific force must be finite and non-zero "
            "(an average over no IMU samples, or a NaN sample, has no up direction)"
        )
    up = specific_force / norm
    z = torch.zeros_like(up)
    z[..., 2] = 1.0
    axis = torch.linalg.cross(up, z)
    sin = axis.norm(dim=-1, keepdim=True)
    cos = (up * z).sum(-1, keepdim=True)
    tilted = sin > 1e-12
    safe = torch.where(tilted, sin, torch.ones_like(sin))
    half_turn = torch.zeros_like(up)
    half_turn[..., 0] = math.pi
    upright = torch.where(cos > 0, torch.zeros_like(up), half_turn)
    rotvec = torch.where(tilted, axis / safe * torch.atan2(sin, cos), upright)
    return so3.exp(rotvec)


def camera_poses(
    states: torch.Tensor, body_rotation_cam: torch.Tensor, body_translation_cam: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera centres (..., 3) m and camera -> world rotations (..., 3, 3) of nav states
    (..., 21) carrying the camera at ``(R_bc, t_bc)``."""
    position, _, rotation, _, _ = unpack_nav_state(states)
    centre = position + (rotation @ body_translation_cam[..., None]).squeeze(-1)
    return centre, rotation @ body_rotation_cam


def triangulate(
    centres: torch.Tensor,
    rotations: torch.Tensor,
    obs_camera: torch.Tensor,
    obs_landmark: torch.Tensor,
    obs_uv: torch.Tensor,
    num_landmarks: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linear (midpoint) triangulation of every landmark from normalized observations.

    Each observation gives the ray ``c_k + s d_k`` with ``d_k = R_k [u, v, 1] / |.|``; the
    point minimises the sum of squared distances to its rays,
    ``(sum_k (I - d_k d_k^T)) X = sum_k (I - d_k d_k^T) c_k``.

    Args:
        centres: (C, 3) camera centres, m. rotations: (C, 3, 3) camera -> world.
        obs_camera, obs_landmark: (M,) int64. obs_uv: (M, 2) normalized coordinates.
        num_landmarks: L.
    Returns:
        points (L, 3) m (zero for landmarks without two observations), parallax (L,) rad
        (twice the largest angle between a ray and the mean ray; 0 for a single ray) and
        the smallest depth along the optical axis over the landmark's observations (L,) m
        (+inf without observations).
    """
    dtype, device = centres.dtype, centres.device
    bearing = torch.cat((obs_uv, torch.ones_like(obs_uv[:, :1])), -1)
    ray = (rotations[obs_camera] @ bearing[..., None]).squeeze(-1)
    ray = ray / ray.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=dtype, device=device)
    proj = eye - ray[:, :, None] * ray[:, None, :]
    normal = torch.zeros(num_landmarks, 3, 3, dtype=dtype, device=device)
    normal = normal.index_add(0, obs_landmark, proj)
    rhs = torch.zeros(num_landmarks, 3, dtype=dtype, device=device)
    rhs = rhs.index_add(0, obs_landmark, (proj @ centres[obs_camera][..., None]).squeeze(-1))
    count = torch.bincount(obs_landmark, minlength=num_landmarks)
    solvable = count >= 2
    normal = torch.where(solvable[:, None, None], normal, eye)
    points = torch.linalg.solve(normal, rhs[..., None]).squeeze(-1)
    points = torch.where(solvable[:, None], points, torch.zeros_like(points))

    mean_ray = torch.zeros(num_landmarks, 3, dtype=dtype, device=device)
    mean_ray = mean_ray.index_add(0, obs_landmark, ray)
    mean_ray = mean_ray / mean_ray.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    cosine = (ray * mean_ray[obs_landmark]).sum(-1).clamp(-1.0, 1.0)
    parallax = torch.zeros(num_landmarks, dtype=dtype, device=device)
    parallax = parallax.scatter_reduce(0, obs_landmark, 2.0 * torch.acos(cosine), "amax")
    local = rotations[obs_camera].mT @ (points[obs_landmark] - centres[obs_camera])[..., None]
    depth = torch.full((num_landmarks,), math.inf, dtype=dtype, device=device)
    depth = depth.scatter_reduce(0, obs_landmark, local[:, 2, 0], "amin")
    return points, parallax, depth


def first_state_prior(state: torch.Tensor, config: VioConfig) -> torch.Tensor:
    """Covariance (15, 15) of the prior on the first nav state ``state`` (21,).

    Gauge: position (``prior_position_sigma``) and yaw about world z
    (``prior_yaw_sigma``); roll, pitch and velocity get a flat 1e2 (rad, m/s) sigma, so
    gravity and the data determine them; the biases get ``prior_gyro_bias_sigma`` and
    ``prior_accel_bias_sigma``. The attitude error is body-side (``R = R_0 Exp(dtheta)``),
    so yaw is the component along ``a = R_0^T e_z``:
    ``Sigma_theta = s_yaw^2 a a^T + 1e4 (I - a a^T)``.
    """
    dtype, device = state.dtype, state.device
    _, _, rotation, _, _ = unpack_nav_state(state)
    eye = torch.eye(3, dtype=dtype, device=device)
    axis = rotation[2]  # R^T e_z
    outer = axis[:, None] * axis[None, :]
    cov = torch.zeros(15, 15, dtype=dtype, device=device)
    cov[0:3, 0:3] = config.prior_position_sigma**2 * eye
    cov[3:6, 3:6] = 1e4 * eye
    cov[6:9, 6:9] = config.prior_yaw_sigma**2 * outer + 1e4 * (eye - outer)
    cov[9:12, 9:12] = config.prior_gyro_bias_sigma**2 * eye
    cov[12:15, 12:15] = config.prior_accel_bias_sigma**2 * eye
    return cov


def keyframe_imu_factor_inputs(
    intervals: ImuIntervals, states: torch.Tensor, noise: ImuNoise, covariance: str = "recursive"
) -> tuple[Preintegrated, torch.Tensor]:
    """Increments and 15x15 covariances of K - 1 keyframe intervals, each preintegrated at
    the biases of its first state.

    Args:
        intervals: raw samples cut at the K keyframes (leading dim K - 1).
        states: (K, 21) nav states (only the biases of the first K - 1 are read).
        noise: IMU noise densities.
        covariance: ``"recursive"`` (exact) or ``"closed_form"`` (zeroth order in ``w dt``,
            vectorised; the growing stage uses it), see
            :func:`~msf_torch.backend.preintegration.preintegrate_imu`.
    Returns:
        :class:`~msf_torch.sensors.imu.Preintegrated` with leading (K - 1,) and covariance
        (K - 1, 15, 15).
    """
    _, _, _, gyro_bias, accel_bias = unpack_nav_state(states[:-1])
    pre = preintegrate_imu(intervals, gyro_bias, accel_bias, covariance)
    return pre, imu_covariance(pre, noise)


def _interval_slice(intervals: ImuIntervals, start: int, stop: int) -> ImuIntervals:
    return ImuIntervals(
        intervals.gyro[start:stop], intervals.accel[start:stop], intervals.dt[start:stop]
    )


def build_vio_problem(
    states: torch.Tensor,
    points: torch.Tensor,
    obs_keyframe: torch.Tensor,
    obs_landmark: torch.Tensor,
    obs_uv: torch.Tensor,
    preintegrated: Preintegrated,
    imu_cov: torch.Tensor,
    body_rotation_cam: torch.Tensor,
    body_translation_cam: torch.Tensor,
    feature_sigma: float,
    gravity: torch.Tensor,
    prior_state: torch.Tensor,
    prior_covariance: torch.Tensor,
    kernel: RobustKernel | None = None,
    fixed_states: torch.Tensor | None = None,
) -> Problem:
    """The visual-inertial least-squares problem over K keyframes and L landmarks, B copies.

    Factors, in this order: the prior on state 0, K - 1 IMU preintegration factors
    (k -> k + 1), M reprojection factors. Groups: ``"state"`` then ``"landmark"`` (last,
    for ``LMConfig(eliminate="landmark")``).

    Args:
        states: (B, K, 21) initial nav states. points: (B, L, 3) initial landmarks, m.
        obs_keyframe, obs_landmark: (M,) int64 indices. obs_uv: (B|1, M, 2) normalized.
        preintegrated: increments with leading (K - 1,) or (B|1, K - 1).
        imu_cov: (B|1, K - 1, 15, 15) or (K - 1, 15, 15).
        body_rotation_cam (3, 3), body_translation_cam (3,) m: camera on the body.
        feature_sigma: per-axis sigma of ``obs_uv``.
        gravity: (3,) m/s^2.
        prior_state: (B|1, 21) or (21,) prior mean of state 0.
        prior_covariance: (B|1, 15, 15) or (15, 15).
        kernel: robust kernel of the reprojection factors.
        fixed_states: (K,) bool, states held constant.
    Returns:
        :class:`~msf_torch.backend.problem.Problem`.
    """
    dtype, device = states.dtype, states.device
    num = states.shape[1]
    if imu_cov.dim() == 3:
        preintegrated = _lead(preintegrated)
        imu_cov = imu_cov[None]
    count = obs_keyframe.shape[0]
    eye2 = torch.eye(2, dtype=dtype, device=device)
    feature_cov = (feature_sigma**2 * eye2).expand(1, count, 2, 2)
    index = torch.arange(num, device=device)
    factors = [
        NavStatePriorFactor(
            "state",
            index[:1],
            prior_state.reshape(-1, 1, 21),
            prior_covariance.reshape(-1, 1, 15, 15),
        ),
        ImuPreintegrationFactor("state", index[:-1], index[1:], preintegrated, imu_cov, gravity),
        ReprojectionFactor(
            "state",
            obs_keyframe,
            "landmark",
            obs_landmark,
            obs_uv if obs_uv.dim() == 3 else obs_uv[None],
            feature_cov,
            body_rotation_cam,
            body_translation_cam,
            kernel=kernel,
        ),
    ]
    fixed = {} if fixed_states is None else {"state": fixed_states}
    return Problem(
        variables={"state": ("nav_state", states), "landmark": ("point", points)},
        factors=factors,
        fixed=fixed,
    )


def _lead(pre: Preintegrated) -> Preintegrated:
    """Add a leading batch dim of 1 to every field."""
    return Preintegrated(**{f.name: getattr(pre, f.name)[None] for f in dataclasses.fields(pre)})


def _propagate(
    state: torch.Tensor, pre: Preintegrated, gravity: torch.Tensor
) -> list[torch.Tensor]:
    """Nav states (21,) after each of the intervals of ``pre`` (leading (n,)), chained from
    ``state`` with its biases held."""
    position, velocity, rotation, gyro_bias, accel_bias = unpack_nav_state(state)
    out = []
    for k in range(pre.delta_t.shape[0]):
        position, velocity, rotation = propagate_nominal(
            position,
            velocity,
            rotation,
            pre.delta_t[k],
            pre.delta_rotation[k],
            pre.delta_velocity[k],
            pre.delta_position[k],
            gravity,
        )
        out.append(pack_nav_state(position, velocity, rotation, gyro_bias, accel_bias))
    return out


def solve_vio(data: VioData, config: VioConfig | None = None) -> VioResult:
    """Keyframe visual-inertial bundle adjustment of a whole recording (see the module
    docstring for the steps).

    Args:
        data: the recording. config: :class:`VioConfig`.
    Returns:
        :class:`VioResult`; ``counts`` says what was kept and dropped.
    Raises:
        ValueError: fewer than two keyframes, or no landmark survives.
    """
    config = config or VioConfig()
    dtype, device = data.imu_t.dtype, data.imu_t.device
    gravity = data.gravity.to(dtype=dtype, device=device)
    keyframe_frames = select_keyframes(data.frame_times.shape[0], config.keyframe_stride, device)
    num_kf = keyframe_frames.shape[0]
    if num_kf < 2:
        raise ValueError(f"need at least two keyframes, got {num_kf}")
    kf_times = data.frame_times[keyframe_frames]
    rest = data.imu_t <= data.imu_t[0] + config.rest_duration
    zero = torch.zeros(3, dtype=dtype, device=device)
    rest_gyro = data.gyro[rest].mean(0)
    first = pack_nav_state(
        zero, zero, gravity_aligned_rotation(data.accel[rest].mean(0)), rest_gyro, zero
    )
    counts = {
        "frames": int(data.frame_times.shape[0]),
        "keyframes": num_kf,
        "observations_input": int(data.obs_frame.shape[0]),
        "landmark_ids_input": int(torch.unique(data.obs_landmark).numel()),
    }
    if config.max_track_jump is None:
        tracks = data.obs_landmark
    else:
        tracks, jumps, gaps = split_tracks(data, rest_gyro, config.max_track_jump)
        counts["track_cuts_at_jumps"] = jumps
        counts["track_cuts_at_gaps"] = gaps
    num_lm = int(tracks.max()) + 1
    counts["tracks"] = int(torch.unique(tracks).numel())
    frame_to_kf = torch.full_like(data.frame_times, -1, dtype=torch.long)
    frame_to_kf[keyframe_frames] = torch.arange(num_kf, device=device)
    obs_kf_all = frame_to_kf[data.obs_frame]
    in_kf = torch.nonzero(obs_kf_all >= 0).squeeze(-1)
    obs_kf, obs_lm, obs_uv = obs_kf_all[in_kf], tracks[in_kf], data.obs_uv[in_kf]
    counts["observations_outside_keyframes"] = int(data.obs_frame.shape[0] - in_kf.numel())
    intervals = cut_imu(data.imu_t, data.gyro, data.accel, kf_times)
    prior_cov = first_state_prior(first, config)
    states = first[None].repeat(num_kf, 1)
    points = torch.zeros(num_lm, 3, dtype=dtype, device=device)
    active = torch.zeros(num_lm, dtype=torch.bool, device=device)
    no_parallax = torch.zeros_like(active)
    min_parallax = math.radians(config.min_parallax_deg)
    growth_iterations = 0

    def seed_landmarks(done: int) -> None:
        """Triangulate new landmarks and those still without parallax, from states < done."""
        use = obs_kf < done
        centres, rotations = camera_poses(
            states[:done], data.body_rotation_cam, data.body_translation_cam
        )
        tri, parallax, depth = triangulate(
            centres, rotations, obs_kf[use], obs_lm[use], obs_uv[use], num_lm
        )
        seen = torch.bincount(obs_lm[use], minlength=num_lm) >= 2
        good = seen & (parallax >= min_parallax) & (depth > config.min_depth)
        update = good & (~active | no_parallax)
        points[update] = tri[update]
        no_parallax[update] = False
        fresh = seen & ~active & ~good
        if bool(fresh.any()):
            # latest observation of each fresh landmark, at the fallback depth
            rows = torch.nonzero(use).squeeze(-1)
            latest = torch.full((num_lm,), -1, dtype=torch.long, device=device)
            latest = latest.scatter_reduce(0, obs_lm[rows], rows, "amax")
            pick = latest[fresh]
            bearing = torch.cat((obs_uv[pick], torch.ones_like(obs_uv[pick, :1])), -1)
            centre, rotation = centres[obs_kf[pick]], rotations[obs_kf[pick]]
            points[fresh] = centre + config.fallback_depth * (
                rotation @ bearing[..., None]
            ).squeeze(-1)
            no_parallax[fresh] = True
        active[seen] = True

    start = time.perf_counter()
    done = 1
    while done < num_kf:
        stop = min(done + config.growth, num_kf)
        last = states[done - 1]
        pre_new, _ = keyframe_imu_factor_inputs(
            _interval_slice(intervals, done - 1, stop - 1),
            last[None].expand(stop - done + 1, 21),
            data.imu_noise,
            "closed_form",
        )
        states[done:stop] = torch.stack(_propagate(last, pre_new, gravity))
        done = stop
        seed_landmarks(done)
        first_free = max(done - config.window, 0)
        in_window = (obs_kf >= first_free) & (obs_kf < done)
        seen = torch.zeros_like(active)
        seen[obs_lm[in_window]] = True
        seen &= active
        use_obs = (obs_kf < done) & seen[obs_lm]
        lm_ids = torch.nonzero(seen).squeeze(-1)
        compact = torch.full((num_lm,), -1, dtype=torch.long, device=device)
        compact[lm_ids] = torch.arange(lm_ids.numel(), device=device)
        pre, cov = keyframe_imu_factor_inputs(
            _interval_slice(intervals, 0, done - 1), states[:done], data.imu_noise, "closed_form"
        )
        fixed = torch.arange(done, device=device) < first_free
        problem = build_vio_problem(
            states[None, :done],
            points[None, lm_ids],
            obs_kf[use_obs],
            compact[obs_lm[use_obs]],
            obs_uv[use_obs],
            pre,
            cov,
            data.body_rotation_cam,
            data.body_translation_cam,
            data.feature_sigma,
            gravity,
            first,
            prior_cov,
            kernel=config.kernel,
            fixed_states=fixed,
        )
        result = solve(problem, config.growth_lm)
        growth_iterations += int(result.iterations[0])
        states[:done] = result.values["state"][0]
        points[lm_ids] = result.values["landmark"][0]

    timings = {"growing": time.perf_counter() - start}
    start = time.perf_counter()
    seed_landmarks(num_kf)
    per_landmark = torch.bincount(obs_lm, minlength=num_lm)
    present = torch.bincount(tracks, minlength=num_lm) > 0
    few = present & (per_landmark < config.min_observations)
    flat = present & ~few & no_parallax
    keep_lm = present & ~few & ~flat
    counts["landmarks_too_few_keyframe_observations"] = int(few.sum())
    counts["landmarks_without_parallax"] = int(flat.sum())
    pre, cov = keyframe_imu_factor_inputs(intervals, states, data.imu_noise)

    def batch(use: torch.Tensor, lm_ids: torch.Tensor, init: torch.Tensor) -> Problem:
        compact = torch.full((num_lm,), -1, dtype=torch.long, device=device)
        compact[lm_ids] = torch.arange(lm_ids.numel(), device=device)
        return build_vio_problem(
            init[None],
            points[None, lm_ids],
            obs_kf[use],
            compact[obs_lm[use]],
            obs_uv[use],
            pre,
            cov,
            data.body_rotation_cam,
            data.body_translation_cam,
            data.feature_sigma,
            gravity,
            first,
            prior_cov,
            kernel=config.kernel,
        )

    def reprojection(problem: Problem, values: dict[str, torch.Tensor]) -> torch.Tensor:
        factor = problem.factors[2]
        return factor.residual(problem.gathered(factor, values))[0]

    keep_obs = torch.ones_like(obs_kf, dtype=torch.bool)
    gated = config.outlier_sigma is None
    counts["observations_rejected_outliers"] = 0
    counts["landmarks_too_few_after_outliers"] = 0
    counts["landmarks_behind_camera"] = 0
    counts["final_solves"] = 0
    solve_costs: list[tuple[float, float]] = []
    while True:
        lm_ids = torch.nonzero(keep_lm).squeeze(-1)
        if lm_ids.numel() == 0:
            raise ValueError("no landmark has enough keyframe observations and parallax")
        use = torch.nonzero(keep_obs & keep_lm[obs_lm]).squeeze(-1)
        problem = batch(use, lm_ids, states)
        result = solve(problem, config.final_lm)
        counts["final_solves"] += 1
        solve_costs.append((float(result.initial_cost[0]), float(result.cost[0])))
        final_states = result.values["state"][0]
        final_points = result.values["landmark"][0]
        states = final_states
        points[lm_ids] = final_points
        centres, rotations = camera_poses(
            final_states, data.body_rotation_cam, data.body_translation_cam
        )
        local = rotations[obs_kf[use]].mT @ (points[obs_lm[use]] - centres[obs_kf[use]])[..., None]
        too_close = torch.zeros(num_lm, dtype=torch.bool, device=device)
        too_close[obs_lm[use][local[:, 2, 0] <= config.min_depth]] = True
        keep_lm &= ~too_close
        counts["landmarks_behind_camera"] += int(too_close.sum())
        changed = bool(too_close.any())
        if not gated:
            gated = True
            whitened = reprojection(problem, result.values).norm(dim=-1) / data.feature_sigma
            outliers = use[whitened > config.outlier_sigma]
            keep_obs[outliers] = False
            remaining = torch.bincount(obs_lm[keep_obs], minlength=num_lm)
            thin = keep_lm & (remaining < config.min_observations)
            keep_lm &= ~thin
            counts["observations_rejected_outliers"] = int(outliers.numel())
            counts["landmarks_too_few_after_outliers"] = int(thin.sum())
            changed = changed or outliers.numel() > 0
        if not changed:
            break
    timings["final"] = time.perf_counter() - start
    counts["landmarks_kept"] = int(lm_ids.numel())
    counts["observations_kept"] = int(use.numel())
    counts["observations_of_dropped_landmarks"] = int((keep_obs & ~keep_lm[obs_lm]).sum())

    residual = reprojection(problem, result.values)
    squared = (residual**2).sum(-1) / data.feature_sigma**2
    weight = torch.ones_like(squared) if config.kernel is None else config.kernel.weight(squared)
    rejected = torch.nonzero(~keep_obs & keep_lm[obs_lm]).squeeze(-1)
    rejected_residual = reprojection(batch(rejected, lm_ids, final_states), result.values)
    compact = torch.full((num_lm,), -1, dtype=torch.long, device=device)
    compact[lm_ids] = torch.arange(lm_ids.numel(), device=device)
    return VioResult(
        keyframe_frames=keyframe_frames,
        keyframe_times=kf_times,
        states=final_states,
        landmarks=final_points,
        landmark_index=lm_ids,
        tracks=tracks,
        obs_keyframe=obs_kf[use],
        obs_landmark=compact[obs_lm[use]],
        obs_index=in_kf[use],
        residual=residual,
        robust_weight=weight,
        rejected_index=in_kf[rejected],
        rejected_residual=rejected_residual,
        lm=result,
        problem=problem,
        counts=counts,
        growth_iterations=growth_iterations,
        solve_costs=solve_costs,
        timings=timings,
    )
