"""``vision.geometry.solve_pnp`` on synthetic 3-D/2-D matches with a known camera pose:
the pose and its covariance on a general scene, and a refusal when the points leave a
direction of the pose unconstrained (collinear points: any rotation about their line
fits)."""

from __future__ import annotations

import numpy as np

from msf_torch.vision.geometry import camera_to_opencv, opencv_to_camera, solve_pnp

CAMERA = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])


def _project(points: np.ndarray, rotation_wc: np.ndarray, centre: np.ndarray) -> np.ndarray:
    cam = (points - centre) @ rotation_wc  # R_wc^T (X - c)
    return cam[:, :2] / cam[:, 2:] * 400.0 + [320.0, 240.0]


def _pose(angle: float) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(angle), np.sin(angle)
    rotation_wc = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # a turn about y
    return rotation_wc, np.array([0.4, -0.1, 0.3])


def test_general_scene_gives_the_pose_and_a_positive_definite_covariance():
    rng = np.random.default_rng(0)
    rotation_wc, centre = _pose(0.1)
    points = rng.uniform([-5.0, -3.0, 4.0], [5.0, 3.0, 15.0], (60, 3))
    pixels = _project(points, rotation_wc, centre) + rng.normal(0.0, 0.3, (60, 2))
    result = solve_pnp(points, pixels, CAMERA, np.zeros(3), np.zeros(3))
    assert result.ok and result.inliers.all()
    rotation, position = opencv_to_camera(result.rvec, result.tvec)
    assert np.abs(rotation - rotation_wc).max() < 2e-3
    assert np.linalg.norm(position - centre) < 0.02
    assert np.linalg.eigvalsh(result.covariance)[0] > 0.0
    rvec, tvec = camera_to_opencv(rotation_wc, centre)
    error = np.concatenate((result.rvec - rvec, result.tvec - tvec))
    assert error @ np.linalg.solve(result.covariance, error) < 22.46  # chi-square 6 dof, 99.9 %


def test_collinear_points_are_refused():
    """Points on one line fit every rotation about it: the previous code returned ok with
    a covariance whose smallest eigenvalue was -3e17."""
    rotation_wc, centre = _pose(0.0)
    along = np.linspace(0.0, 1.0, 20)[:, None]
    points = np.array([0.0, 0.0, 5.0]) + along * np.array([1.0, 0.5, 2.0])
    pixels = _project(points, rotation_wc, centre)
    result = solve_pnp(points, pixels, CAMERA, np.zeros(3), np.zeros(3))
    assert not result.ok
