"""The stereo odometry's pose covariance against a Monte Carlo with known truth.

One synthetic frame: 120 map points (ground-like points 2-8 m ahead, far points 9-14 m)
triangulated by a rectified stereo rig (400 px, 0.12 m), so each point carries the stereo
depth error of a 0.3 px disparity sigma, and seen with 0.3 px pixel noise. Each of 400 draws
perturbs the points and the pixels and solves the pose as the odometry does (plain
least-squares refinement, ``cv2.solvePnPRefineLM``, from the true pose). The spread of the
pose error (a twist about the camera centre; about its sample mean, since the estimate is
biased at second order by the points' depth errors: 0.1-0.5 sigma per axis here) is compared
with ``uncertain_point_pnp``'s covariance: mean NEES within [5.3, 6.7] (6 expected; the mean
of 400 chi-square(6) draws has a standard deviation of 0.17) and every axis' sample variance
within 0.75-1.33 times the reported one; the bias stays below one sigma. The covariance the
odometry declared before
(``sigma^2 (J^T J)^-1``, sigma from the inlier residuals, floored at 0.3 px, then its
position block x 2 and rotation block x 0.5) fails that tolerance on these draws (mean NEES
above 15).

Also: ``sum_i G_i L_i = I`` (a rigid motion of every point moves the pose by it), the twist
to body map against finite differences of ``body_pose``, and the stereo point covariance
against a Monte Carlo of ``triangulate_stereo``.
"""

from __future__ import annotations

import cv2
import numpy as np

from msf_torch.sensors.camera import CameraRig
from msf_torch.vision.geometry import (
    body_pose,
    camera_to_opencv,
    camera_twist_to_body,
    opencv_to_camera,
    rotation_log,
    skew,
    stereo_point_covariance,
    triangulate_stereo,
    uncertain_point_pnp,
)

RIG = CameraRig()
CAMERA = RIG.matrix()
PIXEL_SIGMA = 0.3
DISPARITY_SIGMA = 0.3
DRAWS = 400


def _turn(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about the camera's y


def _scene(rng: np.random.Generator):
    """True camera pose, points (M, 3) world and their stereo covariances (M, 3, 3): the
    points were triangulated by the rig 0.5 m behind the camera (their depth errors lie along
    that camera's rays, so this one sees them)."""
    rotation_a, centre_a = _turn(0.2), np.array([1.0, -0.5, 2.0])
    near = rng.uniform([-3.0, 0.3, 3.5], [3.0, 1.2, 9.0], (80, 3))
    far = rng.uniform([-6.0, -2.0, 9.0], [6.0, 1.5, 14.0], (40, 3))
    cam = np.concatenate((near, far))
    disparity = RIG.fx * RIG.baseline_m / cam[:, 2]
    cov_cam = stereo_point_covariance(
        RIG.project(cam), disparity, CAMERA, RIG.baseline_m, 0.0, DISPARITY_SIGMA
    )
    points = cam @ rotation_a.T + centre_a
    point_cov = rotation_a @ cov_cam @ rotation_a.T
    rotation_wc = _turn(0.3)
    centre = centre_a + rotation_a @ np.array([0.1, 0.0, 0.5])
    return rotation_wc, centre, points, point_cov


def _project(points, rotation_wc, centre):
    cam = (points - centre) @ rotation_wc
    return cam[:, :2] / cam[:, 2:] * RIG.fx + CAMERA[:2, 2]


def _draws(rng, rotation_wc, centre, points, point_cov):
    """Pose errors (DRAWS, 6) as twists about the centre, and each draw's residual sigma."""
    rvec0, tvec0 = camera_to_opencv(rotation_wc, centre)
    true_pixels = _project(points, rotation_wc, centre)
    values, vectors = np.linalg.eigh(point_cov)  # rank 1: the error lies along the ray
    root = vectors * np.sqrt(np.maximum(values, 0.0))[:, None, :]
    errors, sigmas = [], []
    for _ in range(DRAWS):
        moved = points + (root @ rng.standard_normal((len(points), 3, 1)))[..., 0]
        pixels = true_pixels + rng.normal(0.0, PIXEL_SIGMA, true_pixels.shape)
        rvec, tvec = cv2.solvePnPRefineLM(
            moved.reshape(-1, 1, 3),
            pixels.reshape(-1, 1, 2),
            CAMERA,
            None,
            rvec0.reshape(3, 1).copy(),
            tvec0.reshape(3, 1).copy(),
        )
        rotation, position = opencv_to_camera(rvec, tvec)
        errors.append(np.concatenate((position - centre, rotation_log(rotation @ rotation_wc.T))))
        residual = _project(moved, rotation, position) - pixels
        sigmas.append(np.sqrt((residual**2).sum() / (2 * len(points) - 6)))
    return np.array(errors), np.array(sigmas)


def _nees(errors, covariance):
    return np.einsum("ni,nij,nj->n", errors, np.linalg.inv(covariance), errors)


def test_uncertain_point_covariance_matches_a_monte_carlo():
    rng = np.random.default_rng(7)
    rotation_wc, centre, points, point_cov = _scene(rng)
    covariance, _ = uncertain_point_pnp(
        points, point_cov, rotation_wc, centre, CAMERA, PIXEL_SIGMA**2 * np.eye(2)
    )
    errors, sigmas = _draws(rng, rotation_wc, centre, points, point_cov)
    # the spread about the sample mean: the least-squares pose is biased at second order
    # by the points' depth errors (0.1-0.5 sigma per axis here), which the first-order
    # covariance does not describe
    spread = errors - errors.mean(0)
    nees = _nees(spread, np.broadcast_to(covariance, (DRAWS, 6, 6)))
    assert 5.3 < nees.mean() < 6.7, nees.mean()
    ratio = (spread**2).mean(0) / np.diag(covariance)
    assert np.all((ratio > 0.75) & (ratio < 1.33)), ratio
    assert np.all(np.abs(errors.mean(0)) < np.sqrt(np.diag(covariance))), errors.mean(0)

    # the previous declaration: sigma^2 (J^T J)^-1 (pixel noise only, sigma from the
    # residuals, at least 0.3 px), position x 2, rotation x 0.5
    pixel_only, _ = uncertain_point_pnp(
        points, np.zeros_like(point_cov), rotation_wc, centre, CAMERA, np.eye(2)
    )
    scale = np.sqrt(np.repeat([2.0, 0.5], 3))
    old = (
        np.maximum(sigmas, 0.3)[:, None, None] ** 2
        * (scale[:, None] * pixel_only * scale[None, :])[None]
    )
    assert _nees(errors, old).mean() > 15.0


def test_a_rigid_motion_of_the_points_moves_the_pose_by_it():
    rng = np.random.default_rng(3)
    rotation_wc, centre, points, point_cov = _scene(rng)
    _, gain = uncertain_point_pnp(
        points, point_cov, rotation_wc, centre, CAMERA, PIXEL_SIGMA**2 * np.eye(2)
    )
    motion = np.concatenate(
        (np.broadcast_to(np.eye(3), (len(points), 3, 3)), -skew(points - centre)), -1
    )
    assert np.allclose((gain @ motion).sum(0), np.eye(6), atol=1e-9)


def test_stereo_point_covariance_matches_a_monte_carlo():
    rng = np.random.default_rng(5)
    left = np.array([[250.0, 300.0]])
    disparity = np.array([6.0])
    cov = stereo_point_covariance(left, disparity, CAMERA, RIG.baseline_m, 0.2, 0.3)[0]
    noisy_left = left + rng.normal(0.0, 0.2, (20000, 2))
    noisy_disparity = disparity + rng.normal(0.0, 0.3, 20000)
    right = noisy_left - np.stack((noisy_disparity, np.zeros(20000)), -1)
    points = triangulate_stereo(noisy_left, right, CAMERA, RIG.baseline_m)
    sample = np.cov(points.T)
    # first order: the depth's 1/d curvature adds a few percent at d = 6 px, 5 % of sigma
    assert np.allclose(np.diag(sample), np.diag(cov), rtol=0.12)


def test_camera_twist_to_body_matches_finite_differences():
    rotation_wc = cv2.Rodrigues(np.array([0.2, -0.4, 0.3]))[0]
    centre = np.array([2.0, -1.0, 0.5])
    rotation_bc, translation_bc = RIG.body_rotation_cam(), RIG.body_translation_cam()
    position0, rotation0 = body_pose(
        *camera_to_opencv(rotation_wc, centre), rotation_bc, translation_bc
    )
    jacobian = np.zeros((6, 6))
    for k in range(6):
        outputs = []
        for sign in (1.0, -1.0):
            twist = np.zeros(6)
            twist[k] = sign * 1e-6
            rotation = cv2.Rodrigues(twist[3:])[0] @ rotation_wc
            position, body = body_pose(
                *camera_to_opencv(rotation, centre + twist[:3]), rotation_bc, translation_bc
            )
            outputs.append(np.concatenate((position, rotation_log(rotation0.T @ body))))
        jacobian[:, k] = (outputs[0] - outputs[1]) / 2e-6
    covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5]) + 1e-6
    expected = jacobian @ covariance @ jacobian.T
    mapped = camera_twist_to_body(covariance, rotation0, translation_bc)
    assert np.allclose(mapped, expected, rtol=1e-6, atol=1e-12)
    assert np.allclose(position0, centre - rotation0 @ translation_bc)
    back = camera_twist_to_body(mapped, rotation0, translation_bc, inverse=True)
    assert np.allclose(back, covariance, rtol=1e-9, atol=1e-15)  # the odometry's inverse map
