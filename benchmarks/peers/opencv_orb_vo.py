"""OpenCV's textbook ORB stereo visual odometry (speed and accuracy peer).

The tracking front end that ORB-SLAM2 popularised, written with OpenCV's own primitives:
per frame

1. ORB (``cv2.ORB_create(nfeatures)``: FAST corners over an 8-level pyramid, scale 1.2,
   Harris ranking, oriented rBRIEF descriptors) in the left and in the right image;
2. stereo: brute-force Hamming matching left -> right with cross-check, kept when the rows
   agree within ``max_row_px`` and the disparity gives a depth in ``[min_depth_m,
   max_depth_m]``: 3D points in the left camera;
3. motion: brute-force Hamming matching of the previous frame's stereo points to the current
   left descriptors with cross-check; PnP RANSAC (``cv2.solvePnPRansac``, 2 px) gives the
   current camera pose relative to the previous one, chained into the trajectory. With
   fewer than ``min_inliers`` inliers the previous frame's motion is repeated (counted as a
   failure).

No map, no keyframes, no local bundle adjustment (ORB-SLAM2 adds those on other threads),
so it is a frame-to-frame odometry; its cost per frame is dominated by the two ORB
extractions, as in ORB-SLAM2's tracking thread.
"""

from __future__ import annotations

__all__ = ["OrbStereoVo"]

import time

import cv2
import numpy as np


class OrbStereoVo:
    """ORB stereo odometry (module docstring).

    Args:
        camera_matrix: (3, 3) of both rectified cameras.
        baseline_m: stereo baseline, m.
        body_rotation_cam, body_translation_cam: the left camera on the body.
        features: ORB features per image.
    """

    def __init__(
        self,
        camera_matrix: np.ndarray,
        baseline_m: float,
        body_rotation_cam: np.ndarray,
        body_translation_cam: np.ndarray,
        features: int = 1000,
        max_row_px: float = 2.0,
        min_depth_m: float = 0.5,
        max_depth_m: float = 30.0,
        min_inliers: int = 15,
    ) -> None:
        self.k = camera_matrix
        self.baseline = baseline_m
        self.body_rotation_cam = body_rotation_cam
        self.body_translation_cam = body_translation_cam
        self.orb = cv2.ORB_create(nfeatures=features, scaleFactor=1.2, nlevels=8)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.max_row_px = max_row_px
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        self.min_inliers = min_inliers
        self._previous: tuple[np.ndarray, np.ndarray] | None = None  # descriptors, points
        self._cam_from_body = np.eye(4)
        self._cam_from_body[:3, :3] = body_rotation_cam.T
        self._cam_from_body[:3, 3] = -body_rotation_cam.T @ body_translation_cam
        self._world_from_cam = np.linalg.inv(self._cam_from_body)  # body at the origin
        self._motion = np.eye(4)
        self.times: list[float] = []
        self.positions: list[np.ndarray] = []
        self.rotations: list[np.ndarray] = []
        self.wall_s: list[float] = []
        self.cpu_s: list[float] = []
        self.failures = 0

    def _extract(
        self, left: np.ndarray, right: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Left keypoints (N, 2) px and descriptors (N, 32), and the stereo subset: its
        descriptors (S, 32) and camera-frame points (S, 3)."""
        kl, dl = self.orb.detectAndCompute(left, None)
        kr, dr = self.orb.detectAndCompute(right, None)
        none = (np.zeros((0, 32), np.uint8), np.zeros((0, 3)))
        if dl is None:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8), *none
        left_px = np.array([k.pt for k in kl])
        if dr is None:
            return left_px, dl, *none
        matches = self.matcher.match(dl, dr)
        if not matches:
            return left_px, dl, *none
        il = np.array([m.queryIdx for m in matches])
        ir = np.array([m.trainIdx for m in matches])
        pl = left_px[il]
        pr = np.array([kr[i].pt for i in ir])
        fx, fy, cx, cy = self.k[0, 0], self.k[1, 1], self.k[0, 2], self.k[1, 2]
        disparity = pl[:, 0] - pr[:, 0]
        good = (np.abs(pl[:, 1] - pr[:, 1]) <= self.max_row_px) & (disparity > 0)
        depth = fx * self.baseline / np.where(good, disparity, 1.0)
        good &= (depth >= self.min_depth_m) & (depth <= self.max_depth_m)
        z = depth[good]
        points = np.stack(((pl[good, 0] - cx) * z / fx, (pl[good, 1] - cy) * z / fy, z), -1)
        return left_px, dl, dl[il[good]], points

    def _step(self, left_px: np.ndarray, left_desc: np.ndarray) -> np.ndarray | None:
        """Current camera <- previous camera (4, 4) by PnP on the previous stereo points."""
        previous_desc, previous_points = self._previous
        if not len(previous_desc) or not len(left_desc):
            return None
        matches = self.matcher.match(previous_desc, left_desc)
        if len(matches) < self.min_inliers:
            return None
        obj = previous_points[[m.queryIdx for m in matches]]
        img = left_px[[m.trainIdx for m in matches]]
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, self.k, None, reprojectionError=2.0, iterationsCount=100
        )
        if not ok or inliers is None or len(inliers) < self.min_inliers:
            return None
        step = np.eye(4)
        step[:3, :3], _ = cv2.Rodrigues(rvec)
        step[:3, 3] = tvec.reshape(3)
        return step

    def process(self, t: float, left: np.ndarray, right: np.ndarray) -> None:
        """Process one rectified stereo pair (times increasing)."""
        start, cpu_start = time.perf_counter(), time.thread_time()
        left_px, left_desc, stereo_desc, stereo_points = self._extract(left, right)
        if self._previous is not None:
            step = self._step(left_px, left_desc)
            if step is None:
                self.failures += 1
                step = self._motion
            self._motion = step
            self._world_from_cam = self._world_from_cam @ np.linalg.inv(step)
        self._previous = (stereo_desc, stereo_points)
        world_from_body = self._world_from_cam @ self._cam_from_body
        self.times.append(float(t))
        self.positions.append(world_from_body[:3, 3].copy())
        self.rotations.append(world_from_body[:3, :3].copy())
        self.wall_s.append(time.perf_counter() - start)
        self.cpu_s.append(time.thread_time() - cpu_start)
