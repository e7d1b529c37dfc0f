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
* the odometry's increment covariance (:class:`~msf_torch.vision.StereoVisualOdometry`):
  :func:`stereo_point_covariance` (a stereo point's covariance from its pixel and disparity
  noise), :func:`uncertain_point_pnp` (the PnP pose covariance and the pose's sensitivity to
  each map point when the points are uncertain too), :func:`residual_change` (the change of
  the reprojection residuals between frames, from which the tracking noise is estimated) and
  :func:`camera_twist_to_body` (camera-centred twist covariance to the body pose's
  ``[dp (world), dtheta (body)]``, the layout of :class:`~msf_torch.types.PoseMeasurements`).

Twists ``[dt, dtheta]`` (6,) perturb a camera pose by a rigid motion of the world about a
point ``o``: ``c <- c + dt + dtheta x (c - o)``, ``R_wc <- Exp(dtheta) R_wc``; the covariances
of the increment model are over twists about the current camera centre (``o = c``, so
``dt`` is the centre's own displacement).
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
    "rotation_log",
    "skew",
    "stereo_point_covariance",
    "uncertain_point_pnp",
    "residual_change",
    "camera_twist_to_body",
]

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from msf_torch.geometry import so3
from msf_torch.sensors.camera import reprojection_residual


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
    """Rotation vector (..., 3) rad of rotation matrices (..., 3, 3): numpy face of
    :func:`msf_torch.geometry.so3.log` (accurate at the identity and up to a half turn;
    ``cv2.Rodrigues`` returns 0 below 1e-5 rad)."""
    return so3.log(torch.as_tensor(np.asarray(rotation, np.float64))).numpy()


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (..., 3, 3) of vectors (..., 3): ``[v]x w = v x w``;
    numpy face of :func:`msf_torch.geometry.so3.hat`."""
    return so3.hat(torch.as_tensor(np.asarray(vectors, np.float64))).numpy()


def stereo_point_covariance(
    left: np.ndarray,
    disparity: np.ndarray,
    camera_matrix: np.ndarray,
    baseline_m: float,
    pixel_sigma_px: float,
    disparity_sigma_px: float,
) -> np.ndarray:
    """Camera-frame covariance (N, 3, 3), m^2, of rectified stereo points
    (:func:`triangulate_stereo`) from independent noise on the left pixel ``(u, v)`` and on
    the disparity ``d``: ``J diag(s_p^2, s_p^2, s_d^2) J^T`` with ``J = d(x, y, z)/d(u, v, d)``,
    ``z = fx b / d``, ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``.

    Args:
        left: (N, 2) left pixels, px. disparity: (N,) ``u_l - u_r`` > 0, px.
        camera_matrix: (3, 3). baseline_m: b, m.
        pixel_sigma_px: sigma of u and of v, px. disparity_sigma_px: sigma of d, px.
    """
    fx, fy = camera_matrix[0, 0], camera_matrix[1, 1]
    cx, cy = camera_matrix[0, 2], camera_matrix[1, 2]
    u, v = left[:, 0].astype(np.float64), left[:, 1].astype(np.float64)
    d = np.asarray(disparity, np.float64)
    z = fx * baseline_m / d
    jac = np.zeros((len(d), 3, 3))
    jac[:, 0, 0] = z / fx
    jac[:, 0, 2] = -(u - cx) * z / (fx * d)
    jac[:, 1, 1] = z / fy
    jac[:, 1, 2] = -(v - cy) * z / (fy * d)
    jac[:, 2, 2] = -z / d
    noise = np.array([pixel_sigma_px**2, pixel_sigma_px**2, disparity_sigma_px**2])
    return (jac * noise[None, None, :]) @ jac.transpose(0, 2, 1)


def uncertain_point_pnp(
    points_world: np.ndarray,
    point_covariance: np.ndarray,
    rotation_wc: np.ndarray,
    centre: np.ndarray,
    camera_matrix: np.ndarray,
    pixel_covariance: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of a least-squares PnP camera pose whose map points are uncertain too, and
    the pose's sensitivity to each point (first order, at the solution).

    Pixel ``i`` is ``u_i = pi(R_wc^T (X_i - c)) + n_i`` with ``n_i ~ N(0, N_i)`` and the
    point ``X_i`` off by ``dX_i ~ N(0, S_i)``, independent. With ``P_i = du_i/dX_i`` (2, 3),
    ``L_i = [I, -[X_i - c]x]`` (the point's motion under a twist ``xi`` about ``c``) and
    ``J_i = du_i/dxi = -P_i L_i``, the pose that minimises the plain sum of squared
    reprojection errors (as ``cv2.solvePnPRefineLM`` does: every pixel weighs alike, however
    uncertain its point) moves by ``A sum_i J_i^T (n_i - P_i dX_i)``, ``A = (sum_i J_i^T
    J_i)^-1``, so (the sandwich form)

        C = A (sum_i J_i^T (N_i + P_i S_i P_i^T) J_i) A,    G_i = A L_i^T P_i^T P_i

    (the pose's twist moves by ``G_i dX_i``; ``sum_i G_i L_i = I``: moving every point by the
    same rigid motion moves the pose by it). A far point's depth error, small in its own
    pixel, still counts fully in the estimate; the maximum-likelihood covariance
    ``(sum_i J_i^T (N_i + P_i S_i P_i^T)^-1 J_i)^-1`` would understate it.

    Args:
        points_world: (M, 3) m. point_covariance: (M, 3, 3) m^2, world frame.
        rotation_wc: (3, 3) camera -> world. centre: (3,) camera centre, m.
        camera_matrix: (3, 3).
        pixel_covariance: (M, 2, 2) or (2, 2) pixel noise ``N_i``, px^2.
    Returns:
        ``C`` (6, 6) over the twist ``[dt (m), dtheta (rad)]`` about ``centre`` (world axes),
        and ``G`` (M, 6, 3).
    """
    points = np.asarray(points_world, np.float64)
    rel = points - centre
    count = len(points)
    # du/dX (M, 2, 3): the landmark Jacobian of the reprojection residual (sensors.camera),
    # the camera itself as the "body" (no mount offset)
    intrinsics = (
        float(camera_matrix[0, 0]),
        float(camera_matrix[1, 1]),
        float(camera_matrix[0, 2]),
        float(camera_matrix[1, 2]),
    )
    _, _, d_landmark = reprojection_residual(
        torch.as_tensor(np.asarray(centre, np.float64)).expand(count, 3),
        torch.as_tensor(np.asarray(rotation_wc, np.float64)).expand(count, 3, 3),
        torch.as_tensor(points),
        torch.eye(3, dtype=torch.float64),
        torch.zeros(3, dtype=torch.float64),
        torch.zeros(count, 2, dtype=torch.float64),
        intrinsics,
    )
    p = d_landmark.numpy()
    motion = np.concatenate((np.broadcast_to(np.eye(3), (count, 3, 3)), -skew(rel)), -1)
    jac = -p @ motion  # (M, 2, 6)
    inverse = np.linalg.inv(np.einsum("mai,maj->ij", jac, jac))
    noise = pixel_covariance + p @ point_covariance @ p.transpose(0, 2, 1)
    covariance = inverse @ np.einsum("mai,mab,mbj->ij", jac, noise, jac) @ inverse
    gain = inverse @ motion.transpose(0, 2, 1) @ p.transpose(0, 2, 1) @ p
    return covariance, gain


def residual_change(
    points_world: np.ndarray,
    pixels: np.ndarray,
    previous_pixels: np.ndarray,
    pose: tuple[np.ndarray, np.ndarray],
    previous_pose: tuple[np.ndarray, np.ndarray],
    camera_matrix: np.ndarray,
) -> np.ndarray:
    """Change (M, 2), px, of the reprojection residuals of the same map points between two
    frames: ``dr_i = (pi_k(X_i) - u_i,k) - (pi_k-1(X_i) - u_i,k-1)``.

    A map point's own error (and a track's accumulated drift) sits in both residuals and
    mostly cancels; what is left is the tracking error between the two frames, less the part
    the pose absorbs (6 of the ``2 M`` coordinates: ``E sum_i dr_i dr_i^T`` is
    ``(2 M - 6) / (2 M)`` of the tracking error's for noise alike on every track).

    Args:
        points_world: (M, 3) m. pixels, previous_pixels: (M, 2) px in frames k and k - 1.
        pose, previous_pose: ``(rvec, tvec)`` (3,) each of frames k and k - 1.
        camera_matrix: (3, 3).
    """
    obj = np.ascontiguousarray(points_world, np.float64).reshape(-1, 1, 3)
    now, _ = cv2.projectPoints(obj, pose[0], pose[1], camera_matrix, None)
    before, _ = cv2.projectPoints(obj, previous_pose[0], previous_pose[1], camera_matrix, None)
    return (now.reshape(-1, 2) - pixels) - (before.reshape(-1, 2) - previous_pixels)


def camera_twist_to_body(
    covariance: np.ndarray,
    rotation_wb: np.ndarray,
    body_translation_cam: np.ndarray,
    inverse: bool = False,
) -> np.ndarray:
    """Covariance (6, 6) over the body pose's ``[dp (world), dtheta (body)]`` of a covariance
    (6, 6) over the camera's twist ``[dt, dtheta]`` about its centre (world axes), for a
    camera at ``t_bc`` in the body: ``p_b = c - R_wb t_bc`` gives
    ``dp = dt + [R_wb t_bc]x dtheta``, and ``dtheta_body = R_wb^T dtheta``. With
    ``inverse`` the opposite map (body covariance to the camera's twist)."""
    jac = np.zeros((6, 6))
    jac[:3, :3] = np.eye(3)
    jac[:3, 3:] = skew(rotation_wb @ body_translation_cam)
    jac[3:, 3:] = rotation_wb.T
    if inverse:
        jac = np.linalg.inv(jac)
    return jac @ covariance @ jac.T
