"""Two-view and map-based pose geometry for the visual front end (OpenCV, numpy float64).

Camera poses are ``(R_wc, c)``: camera -> world rotation and camera centre in the world. A
world point ``X`` is at ``R_wc^T (X - c)`` in the camera. OpenCV's ``(rvec, tvec)`` is the
world -> camera transform ``x_c = Exp(rvec) X + tvec``.

* :func:`solve_pnp` -- PnP RANSAC against map points, refined by Levenberg-Marquardt on the
  inliers, with the Gauss-Newton covariance ``sigma^2 (J^T J)^-1`` of ``(rvec, tvec)``
  (``sigma`` from the inlier residuals, not below a floor);
* :func:`relative_pose_essential` -- the essential matrix by RANSAC (five-point) and the
  cheirality check of ``cv2.recoverPose``: relative rotation and translation direction;
* :func:`triangulate_stereo` -- rectified stereo: depth ``z = fx b / d`` from the disparity
  ``d``;
* :func:`body_pose_covariance` -- maps a covariance of ``(rvec, tvec)`` to the body pose's
  ``[dp (world), dtheta (body)]`` (the layout of
  :class:`~msf_torch.types.PoseMeasurements`) by a central-difference Jacobian.
"""

from __future__ import annotations

__all__ = [
    "PnpResult",
    "camera_to_opencv",
    "opencv_to_camera",
    "solve_pnp",
    "relative_pose_essential",
    "triangulate_stereo",
    "body_pose",
    "body_pose_covariance",
    "rotation_log",
]

import math
from dataclasses import dataclass

import cv2
import numpy as np


def camera_to_opencv(rotation_wc: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rvec, tvec)`` (3,) each of the camera pose ``(R_wc, c)``."""
    rotation_cw = rotation_wc.T
    rvec, _ = cv2.Rodrigues(rotation_cw)
    return rvec.reshape(3), -rotation_cw @ centre


def opencv_to_camera(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose ``(R_wc (3, 3), c (3,))`` of OpenCV's ``(rvec, tvec)``."""
    rotation_cw, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    rotation_wc = rotation_cw.T
    return rotation_wc, -rotation_wc @ np.asarray(tvec, np.float64).reshape(3)


@dataclass
class PnpResult:
    """Outcome of :func:`solve_pnp`.

    Attributes:
        ok: a pose was found with enough inliers.
        rvec, tvec: (3,) world -> camera.
        inliers: (N,) bool over the input points.
        covariance: (6, 6) of ``(rvec, tvec)``.
        sigma_px: reprojection sigma used, px.
        rms_px: RMS inlier reprojection error, px.
    """

    ok: bool
    rvec: np.ndarray
    tvec: np.ndarray
    inliers: np.ndarray
    covariance: np.ndarray
    sigma_px: float
    rms_px: float


def solve_pnp(
    points_world: np.ndarray,
    pixels: np.ndarray,
    camera_matrix: np.ndarray,
    rvec_guess: np.ndarray,
    tvec_guess: np.ndarray,
    reprojection_px: float = 2.0,
    iterations: int = 100,
    min_inliers: int = 12,
    sigma_floor_px: float = 0.3,
) -> PnpResult:
    """Camera pose from 3D-2D matches: RANSAC, then LM on the inliers, then covariance.

    Args:
        points_world: (N, 3) m. pixels: (N, 2) px. camera_matrix: (3, 3).
        rvec_guess, tvec_guess: (3,) predicted pose (RANSAC starts its refinement there).
        reprojection_px: RANSAC inlier threshold, px.
        iterations: RANSAC iterations.
        min_inliers: fewer inliers fail.
        sigma_floor_px: least reprojection sigma for the covariance, px.
    Returns:
        :class:`PnpResult` (``ok`` False with the guess when it fails: too few inliers, or
        the inliers leave a direction of the pose unconstrained, the Gauss-Newton
        information's eigenvalue ratio below 1e-12, e.g. collinear points).
    """
    count = len(points_world)
    fail = PnpResult(
        False, rvec_guess.copy(), tvec_guess.copy(), np.zeros(count, bool), np.eye(6), 0.0, 0.0
    )
    if count < max(min_inliers, 6):
        return fail
    obj = np.ascontiguousarray(points_world, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    rvec = rvec_guess.reshape(3, 1).astype(np.float64).copy()
    tvec = tvec_guess.reshape(3, 1).astype(np.float64).copy()
    ok, rvec, tvec, index = cv2.solvePnPRansac(
        obj,
        img,
        camera_matrix,
        None,
        rvec,
        tvec,
        useExtrinsicGuess=True,
        iterationsCount=iterations,
        reprojectionError=reprojection_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or index is None or len(index) < min_inliers:
        return fail
    inliers = np.zeros(count, bool)
    inliers[index.reshape(-1)] = True
    rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], camera_matrix, None, rvec, tvec)
    projected, jacobian = cv2.projectPoints(obj, rvec, tvec, camera_matrix, None)
    error = np.linalg.norm((projected - img).reshape(-1, 2), axis=-1)
    inliers = error <= reprojection_px
    if inliers.sum() < min_inliers:
        return fail
    residual = (projected - img).reshape(-1, 2)[inliers]
    dof = max(2 * int(inliers.sum()) - 6, 1)
    rms = float(np.sqrt((residual**2).sum() / inliers.sum()))
    sigma = max(float(np.sqrt((residual**2).sum() / dof)), sigma_floor_px)
    rows = np.repeat(inliers, 2)
    jac = jacobian[rows, :6]
    information = jac.T @ jac
    eigen = np.linalg.eigvalsh(information)
    if not eigen[0] > 1e-12 * eigen[-1]:
        return fail  # a direction the points leave free (collinear: rotation about the line)
    covariance = sigma**2 * np.linalg.inv(information)
    return PnpResult(True, rvec.reshape(3), tvec.reshape(3), inliers, covariance, sigma, rms)


def relative_pose_essential(
    points_a: np.ndarray,
    points_b: np.ndarray,
    camera_matrix: np.ndarray,
    threshold_px: float = 1.0,
    min_inliers: int = 12,
) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
    """Relative pose of camera b w.r.t. camera a from matched pixels (five-point RANSAC).

    ``x_b = R x_a + t`` for camera-frame points, ``|t| = 1`` (the scale is unobservable).

    Args:
        points_a, points_b: (N, 2) px in images a and b.
        camera_matrix: (3, 3).
        threshold_px: RANSAC epipolar threshold, px.
        min_inliers: fewer inliers (after the cheirality check) fail.
    Returns:
        (ok, R (3, 3), t (3,), inliers (N,) bool).
    """
    count = len(points_a)
    eye, zero = np.eye(3), np.zeros(3)
    if count < max(min_inliers, 5):
        return False, eye, zero, np.zeros(count, bool)
    a = np.ascontiguousarray(points_a, np.float64)
    b = np.ascontiguousarray(points_b, np.float64)
    essential, mask = cv2.findEssentialMat(
        a, b, camera_matrix, method=cv2.RANSAC, prob=0.999, threshold=threshold_px
    )
    if essential is None or essential.shape != (3, 3):
        return False, eye, zero, np.zeros(count, bool)
    good, rotation, translation, mask = cv2.recoverPose(essential, a, b, camera_matrix, mask=mask)
    inliers = mask.reshape(-1) > 0
    if good < min_inliers:
        return False, eye, zero, inliers
    return True, rotation, translation.reshape(3), inliers


def triangulate_stereo(
    left: np.ndarray,
    right: np.ndarray,
    camera_matrix: np.ndarray,
    baseline_m: float,
) -> np.ndarray:
    """Camera-frame points (N, 3) m of rectified stereo matches.

    ``z = fx b / (u_l - u_r)``, ``x = (u_l - cx) z / fx``, ``y = (v_l - cy) z / fy``.

    Args:
        left, right: (N, 2) px in the left and right images (same rows).
        camera_matrix: (3, 3) of both cameras.
        baseline_m: b, m.
    Raises:
        ValueError: a disparity is not positive (a point at infinity or behind the rig;
            names the first such row).
    """
    fx, fy = camera_matrix[0, 0], camera_matrix[1, 1]
    cx, cy = camera_matrix[0, 2], camera_matrix[1, 2]
    disparity = left[:, 0].astype(np.float64) - right[:, 0]
    if not np.all(disparity > 0):
        row = int(np.argmin(disparity > 0))
        raise ValueError(
            f"triangulate_stereo: disparity u_left - u_right must be > 0 px, row {row} has "
            f"{float(disparity[row])!r}"
        )
    z = fx * baseline_m / disparity
    return np.stack(((left[:, 0] - cx) * z / fx, (left[:, 1] - cy) * z / fy, z), -1)


def body_pose(
    rvec: np.ndarray,
    tvec: np.ndarray,
    body_rotation_cam: np.ndarray,
    body_translation_cam: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Body position (3,) and body -> world rotation (3, 3) of a camera pose ``(rvec, tvec)``
    for a camera mounted at ``(R_bc, t_bc)``."""
    rotation_wc, centre = opencv_to_camera(rvec, tvec)
    rotation_wb = rotation_wc @ body_rotation_cam.T
    return centre - rotation_wb @ body_translation_cam, rotation_wb


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) rad of a rotation matrix (3, 3), accurate near the identity
    (``cv2.Rodrigues`` returns 0 below 1e-5 rad); angles up to just below pi."""
    skew = 0.5 * (rotation - rotation.T)
    axis = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    sin = float(np.linalg.norm(axis))
    cos = 0.5 * (float(np.trace(rotation)) - 1.0)
    angle = math.atan2(sin, cos)
    return axis if sin < 1e-12 else axis * (angle / sin)


def body_pose_covariance(
    rvec: np.ndarray,
    tvec: np.ndarray,
    covariance: np.ndarray,
    body_rotation_cam: np.ndarray,
    body_translation_cam: np.ndarray,
    step: float = 1e-6,
) -> np.ndarray:
    """Covariance (6, 6) over the body pose's ``[dp (world), dtheta (body)]`` of a
    covariance (6, 6) over ``(rvec, tvec)``, through the central-difference Jacobian of
    ``(rvec, tvec) -> (p_wb, Log(R_wb0^T R_wb))``."""
    position0, rotation0 = body_pose(rvec, tvec, body_rotation_cam, body_translation_cam)
    jacobian = np.zeros((6, 6))
    params = np.concatenate((rvec, tvec)).astype(np.float64)
    for i in range(6):
        outputs = []
        for sign in (1.0, -1.0):
            moved = params.copy()
            moved[i] += sign * step
            position, rotation = body_pose(
                moved[:3], moved[3:], body_rotation_cam, body_translation_cam
            )
            outputs.append(
                np.concatenate((position - position0, rotation_log(rotation0.T @ rotation)))
            )
        jacobian[:, i] = (outputs[0] - outputs[1]) / (2.0 * step)
    return jacobian @ covariance @ jacobian.T
