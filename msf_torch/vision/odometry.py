"""Stereo visual odometry on OpenCV: features, KLT, PnP / essential matrix, keyframes, map.

Per frame (left image; the right one only at keyframes):

1. image-quality statistics (:func:`~msf_torch.vision.quality.image_quality`);
2. KLT tracking of the current features from the previous frame (an optional
   forward-backward check, off by default: PnP RANSAC rejects bad tracks); features with a
   map point start from the pixel that the constant-velocity pose prediction gives them;
3. pose: PnP RANSAC of the tracked features that have map points, refined on the inliers
   (:func:`~msf_torch.vision.geometry.solve_pnp`); outliers are dropped. With too few
   inliers, the essential matrix between the previous and the current frame
   (:func:`~msf_torch.vision.geometry.relative_pose_essential`) gives the rotation and the
   direction of travel, the length of the step being the previous one's (status
   ``"essential"``, translation covariance ``(essential_step_sigma * step + 0.01 m)^2`` per
   axis: the floor keeps a near-zero step from claiming a near-zero sigma).
   When both fail the pose is the constant-velocity prediction and the frame is ``"lost"``
   (no pose measurement); the map is rebuilt at the next keyframe, counted as a reset when
   no map point is left;
4. keyframe when any holds: ``keyframe_interval_s`` since the last one, translation beyond
   ``keyframe_translation_m`` or rotation beyond ``keyframe_rotation_deg`` since it, fewer
   than ``keyframe_min_tracked`` features with map points or fewer than
   ``keyframe_track_ratio`` of those the last keyframe had;
5. at a keyframe: new FAST features in the free grid cells (adaptive threshold,
   :class:`~msf_torch.vision.features.AdaptiveFastDetector`); every feature without a map
   point is found in the right image by a row search
   (:func:`~msf_torch.vision.features.stereo_search`, no depth prior) refined by KLT (rows
   must agree within ``stereo_max_row_px``, forward-backward checked) and triangulated
   (:func:`~msf_torch.vision.geometry.triangulate_stereo`) when its depth lies in
   ``[min_depth_m, max_depth_m]``: a new map point in the odometry frame; features that
   fail are dropped. With ``stereo_edge_max_px`` a far match whose window straddles a
   depth edge is refused too (its sub-window disparities are not affine,
   :func:`~msf_torch.vision.features.stereo_window_gaps`). With ``refine_map_points`` the
   features that have map points are matched too (KLT from their predicted disparity) and
   each new point is fused with the old one by inverse-variance weights of the depth sigmas
   ``z^2 sigma_d / (fx b)`` (closer views count more; a point more than 3 combined sigmas
   off is ignored). Upright ORB descriptors of the keyframe's features are kept (for place
   recognition).

The odometry frame is the body frame at the first frame. Each frame's body pose comes with a
covariance over ``[dp (world), dtheta (body)]``, made for the ESKF, which fuses the poses as
odometry increments (a named pose source, :meth:`VoResult.pose_source`) with the pair
covariance ``C_k + C_k-1``: ``C_k`` is half the covariance ``Sigma_k`` of frame k's pose
relative to frame k - 1's (the increment), so the pair gets about ``Sigma_k``. First order,
over twists (``vision.geometry``):

* each frame's pose error is its own error plus the errors its map points inherited from
  the frames they were triangulated at (their *anchors*):
  ``e_k = d_k + sum_a W_a e_a``, ``W_a = sum_{i from a} w_i,a G_i L_i`` (``G_i`` the pose's
  sensitivity to point ``i``, ``L_i`` the point's motion under a twist, ``w_i,a`` anchor
  ``a``'s share in the point after the inverse-variance fusion of ``refine_map_points``;
  ``sum_a W_a = I``). The joint covariance of the frames that points still carry is kept
  (a window, twists about the origin), and ``Sigma_k = P_k,k + P_k-1,k-1 - P_k,k-1 -
  P_k-1,k`` (anchors are forgotten below ``anchor_weight_min`` of a point);
* ``d_k``: the least-squares PnP pose's covariance with uncertain points
  (:func:`~msf_torch.vision.geometry.uncertain_point_pnp`, the sandwich form: the refinement
  weighs every pixel alike). Pixel noise: each inlier's own tracking error, estimated from
  the change of its reprojection residual since the previous frame
  (:func:`~msf_torch.vision.geometry.residual_change`; a map point's own error cancels
  there) as ``dr_i dr_i^T 2 M / (2 M - 6)`` (heteroscedasticity-consistent, White 1980;
  ``2 M / (2 M - 6)`` for the coordinates the pose absorbs) plus ``sigma_floor_px^2 I``.
  Point noise: the stereo depth error of the keyframe's disparity sigma (the RMS gap between
  the re-matched map points' disparities and their predictions, less the points' own share,
  not below ``stereo_disparity_sigma_px``) along the triangulating camera's ray
  (:func:`~msf_torch.vision.geometry.stereo_point_covariance`; the left pixel defines the
  point, its later error is the tracking noise), carried through the fusion as
  ``S = a^2 S_old + (1 - a)^2 S_new``.

The pose estimates do not depend on it. Left out: a systematic error (the odometry's scale
and turn rate are off by a few tenths of a percent on the rendered runs: stereo matches whose
window straddles a depth edge read the disparity high, docs/visual.md), the least-squares
pose's second-order bias from the points' depth errors, a track error common to all tracks
(the pose absorbs it, so the residuals cannot show it), and the correlation of consecutive
increments, which the ESKF treats as independent.
The feature tracks (every PnP inlier, every frame, normalized coordinates) feed the back
end's reprojection factors (:mod:`msf_torch.vision.tracks`).
"""

from __future__ import annotations

__all__ = [
    "VoConfig",
    "VoFrame",
    "Keyframe",
    "VoResult",
    "StereoVisualOdometry",
    "STATUSES",
    "stereo_match",
]

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sensors.camera import CameraRig
from msf_torch.types import PoseMeasurements
from msf_torch.vision.features import (
    AdaptiveFastDetector,
    DetectorConfig,
    KltConfig,
    orb_descriptors,
    stereo_search,
    stereo_window_gaps,
    track_klt,
)
from msf_torch.vision.geometry import (
    body_pose,
    camera_to_opencv,
    camera_twist_to_body,
    opencv_to_camera,
    relative_pose_essential,
    residual_change,
    skew,
    solve_pnp,
    stereo_point_covariance,
    triangulate_stereo,
    uncertain_point_pnp,
)
from msf_torch.vision.quality import QUALITY_NAMES, image_quality

STATUSES: tuple[str, ...] = ("init", "pnp", "essential", "lost")
"""Per-frame pose status: first frame, PnP against the map, essential-matrix fallback, lost."""


@dataclass(frozen=True)
class VoConfig:
    """Settings of :class:`StereoVisualOdometry`.

    Attributes:
        detector: FAST detector and its adaptive threshold.
        klt: temporal tracking (an 11 px window: on the ground, which a forward camera sees
            at a grazing angle, larger windows average over more perspective distortion;
            the translation-only model then errs by 0.31 px at 21 px against 0.24 px at 11 px
            over a 0.15 m step, noise-free renders).
        stereo_klt: left -> right sub-pixel refinement of the disparity (an 11 px window:
            unbiased inside a surface; larger windows read the slanted ground's disparity
            low, -0.14..-0.22 % at 21 px and -0.35..-0.58 % at 31 px on seeds 11-13).
        stereo_patch_px: patch of the row search for new features
            (:func:`~msf_torch.vision.features.stereo_search`), px.
        stereo_max_row_px: rectified rows must agree within this, px.
        stereo_disparity_sigma_px: disparity sigma, px, for the depth sigma
            ``z^2 sigma_d / (fx b)`` that weighs stereo depths, and the least one for the map
            points' covariance (a keyframe's re-matches can show a larger one).
        stereo_edge_max_px: the depth-edge check of stereo matches (None: off): a match
            below ``stereo_edge_max_disparity_px`` is refused when the second difference of
            its sub-window disparities along the row or the column
            (:func:`~msf_torch.vision.features.stereo_window_gaps`) exceeds this, px, or a
            sub-window does not match on its row; new features are kept, the least
            edge-like first, while the map would hold fewer than ``keyframe_min_tracked``
            points. Matches whose window straddles a depth edge read the disparity high
            (+12..+17 % where the truth is below 3 px, +0.7 % above, seeds 11-13;
            docs/visual.md). Off by default: at 0.3 px (tuned on seeds 11-13) it refuses
            23-26 % of the matches and shrinks the 900-frame turn error on all six 90 s
            runs (seeds 11-13 and 21-23), but the fused ATE of the held-out runs 21 / 22 /
            23 goes from 0.193 / 0.161 / 0.191 m to 0.260 / 0.198 / 0.110 m, and the
            keyframes it adds (1.2-1.7x as many) cost 3-4 ms CPU per frame on average.
        stereo_edge_window_px: side of the check's sub-windows, px.
        stereo_edge_offset_px: distance of its side windows from the feature, px.
        stereo_edge_max_disparity_px: only matches below this disparity are checked, px
            (4 px: beyond 12 m; nearer edge matches err by under 1 %, and on the slanted
            ground the translation-only sub-windows give second differences of their own).
        refine_map_points: at keyframes, stereo-match the features that have map points too
            and fuse each new point with the old one (inverse-variance weights of the depth
            sigmas; a new point more than 3 combined sigmas away is ignored).
        min_depth_m, max_depth_m: new map points must lie in this depth range, m.
        pnp_reprojection_px: PnP RANSAC inlier threshold, px.
        pnp_iterations: PnP RANSAC iterations.
        min_pnp_inliers: fewer inliers fall back to the essential matrix.
        essential_threshold_px: essential-matrix RANSAC threshold, px.
        essential_step_sigma: relative sigma of the step length in the fallback (plus
            0.01 m).
        essential_rotation_sigma_rad: rotation sigma per axis in the fallback, rad.
        sigma_floor_px: pixel sigma added to each track's frame-to-frame noise estimate in
            the covariance, px (module docstring).
        anchor_weight_min: a fused map point forgets anchors whose share falls below this
            (the rest are renormalised).
        keyframe_interval_s, keyframe_translation_m, keyframe_rotation_deg,
        keyframe_min_tracked, keyframe_track_ratio: keyframe rules (module docstring).
        descriptors: compute ORB descriptors at keyframes.
        record_tracks: keep every PnP inlier observation for the back end.
    """

    detector: DetectorConfig = field(default_factory=DetectorConfig)
    klt: KltConfig = field(
        default_factory=lambda: KltConfig(window_px=11, max_forward_backward_px=None)
    )
    stereo_klt: KltConfig = field(default_factory=lambda: KltConfig(window_px=11, levels=1))
    stereo_patch_px: int = 11
    stereo_max_row_px: float = 1.0
    stereo_disparity_sigma_px: float = 0.3
    stereo_edge_max_px: float | None = None
    stereo_edge_window_px: int = 7
    stereo_edge_offset_px: float = 4.0
    stereo_edge_max_disparity_px: float = 4.0
    refine_map_points: bool = True
    min_depth_m: float = 0.5
    max_depth_m: float = 30.0
    pnp_reprojection_px: float = 2.0
    pnp_iterations: int = 100
    min_pnp_inliers: int = 10
    essential_threshold_px: float = 1.0
    essential_step_sigma: float = 0.5
    essential_rotation_sigma_rad: float = 0.01
    sigma_floor_px: float = 0.05
    anchor_weight_min: float = 0.01
    keyframe_interval_s: float = 1.0
    keyframe_translation_m: float = 1.0
    keyframe_rotation_deg: float = 15.0
    keyframe_min_tracked: int = 120
    keyframe_track_ratio: float = 0.6
    descriptors: bool = True
    record_tracks: bool = True


@dataclass
class VoFrame:
    """One frame's output.

    Attributes:
        t: time, s.
        status: one of :data:`STATUSES`.
        position: (3,) body position in the odometry frame, m.
        rotation: (3, 3) body -> odometry frame.
        covariance: (6, 6) over ``[dp (odometry frame), dtheta (body)]``, m^2 and rad^2:
            half the covariance of the pose relative to the previous frame's (module
            docstring); NaN on the first frame and on lost frames.
        pixel_sigma: RMS per coordinate of the tracks' frame-to-frame pixel noise used in
            the covariance, px (NaN without PnP).
        tracked: features tracked into this frame.
        map_tracked: of those, with map points.
        inliers: PnP (or essential-matrix) inliers.
        new_points: map points created at this frame (keyframes).
        keyframe: this frame is a keyframe.
        threshold: FAST threshold after this frame's detection, DN.
        quality: (4,) image-quality statistics (:data:`~msf_torch.vision.quality.QUALITY_NAMES`).
        wall_s: processing time of this frame (wall clock), s.
        cpu_s: CPU time of the processing thread for this frame, s (unaffected by other
            work sharing the machine).
    """

    t: float
    status: str
    position: np.ndarray
    rotation: np.ndarray
    covariance: np.ndarray
    pixel_sigma: float
    tracked: int
    map_tracked: int
    inliers: int
    new_points: int
    keyframe: bool
    threshold: float
    quality: np.ndarray
    wall_s: float
    cpu_s: float


@dataclass
class Keyframe:
    """A keyframe: pose, features, map links and descriptors (for place recognition).

    Attributes:
        frame: frame index. t: time, s.
        position: (3,) body, odometry frame, m. rotation: (3, 3) body -> odometry frame.
        pixels: (K, 2) feature positions, px. feature_ids: (K,) track ids.
        landmark: (K,) bool, the feature has a map point (its id is the landmark id).
        descriptor_index: (D,) rows of ``pixels`` with a descriptor.
        descriptors: (D, 32) uint8 upright ORB.
    """

    frame: int
    t: float
    position: np.ndarray
    rotation: np.ndarray
    pixels: np.ndarray
    feature_ids: np.ndarray
    landmark: np.ndarray
    descriptor_index: np.ndarray
    descriptors: np.ndarray


@dataclass
class VoResult:
    """A whole run of the visual odometry, numpy arrays over the F frames.

    Attributes:
        t: (F,) s.
        status: (F,) int index into :data:`STATUSES`.
        position: (F, 3) m. rotation: (F, 3, 3).
        covariance: (F, 6, 6), half the increment covariance (:class:`VoFrame`; first and
            lost frames take the first measured one).
        pixel_sigma: (F,) the tracks' frame-to-frame pixel noise, RMS per coordinate, px
            (NaN without PnP).
        tracked, map_tracked, inliers, new_points: (F,) int counts.
        keyframe: (F,) bool. threshold: (F,) FAST threshold, DN.
        quality: (F, 4) image-quality statistics.
        wall_s: (F,) per-frame processing time (wall clock), s.
        cpu_s: (F,) per-frame CPU time of the processing thread, s.
        keyframes: the keyframes.
        landmarks: (L, 3) map points, odometry frame, m (row = landmark index).
        landmark_ids: (L,) their track ids.
        obs_frame, obs_landmark: (M,) int64 frame and landmark index of each PnP inlier.
        obs_pixel: (M, 2) px.
        stereo_frame, stereo_landmark: (S,) int64 frame and landmark index of each
            right-image observation: the stereo match that created the landmark, and
            with ``refine_map_points`` each later keyframe's match that agrees with it.
        stereo_pixel: (S, 2) px in the right image.
        resets: times the map had to be rebuilt from nothing.
        rig: the camera rig.
    """

    t: np.ndarray
    status: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    covariance: np.ndarray
    pixel_sigma: np.ndarray
    tracked: np.ndarray
    map_tracked: np.ndarray
    inliers: np.ndarray
    new_points: np.ndarray
    keyframe: np.ndarray
    threshold: np.ndarray
    quality: np.ndarray
    wall_s: np.ndarray
    cpu_s: np.ndarray
    keyframes: list[Keyframe]
    landmarks: np.ndarray
    landmark_ids: np.ndarray
    obs_frame: np.ndarray
    obs_landmark: np.ndarray
    obs_pixel: np.ndarray
    stereo_frame: np.ndarray
    stereo_landmark: np.ndarray
    stereo_pixel: np.ndarray
    resets: int
    rig: CameraRig

    @property
    def valid(self) -> np.ndarray:
        """(F,) bool: frames with a pose measurement (status init, pnp or essential)."""
        return self.status != STATUSES.index("lost")

    def counts(self) -> dict[str, int]:
        """Frames per status, keyframes, map points, observations and resets."""
        out = {name: int((self.status == k).sum()) for k, name in enumerate(STATUSES)}
        out.update(
            frames=len(self.t),
            keyframes=int(self.keyframe.sum()),
            landmarks=len(self.landmarks),
            observations=len(self.obs_frame),
            resets=self.resets,
        )
        return out

    def pose_source(self, dtype: torch.dtype = torch.float64) -> PoseMeasurements:
        """The body poses as a B = 1 :class:`~msf_torch.types.PoseMeasurements` (``mask``
        False on lost frames), for ``Sequence.pose_sources["vo"]``."""
        rotation = torch.as_tensor(self.rotation, dtype=dtype)
        return PoseMeasurements(
            t=torch.as_tensor(self.t, dtype=dtype)[None],
            position=torch.as_tensor(self.position, dtype=dtype)[None],
            quaternion=matrix_to_quat(rotation)[None],
            covariance=torch.as_tensor(self.covariance, dtype=dtype)[None],
            mask=torch.as_tensor(self.valid)[None],
        )

    def quality_tensor(self, dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
        """Image-quality statistics as ``{"t": (1, F), name: (1, F)}`` tensors."""
        out = {"t": torch.as_tensor(self.t, dtype=dtype)[None]}
        for k, name in enumerate(QUALITY_NAMES):
            out[name] = torch.as_tensor(self.quality[:, k], dtype=dtype)[None]
        return out


def _stack_observations(
    records: list[tuple[int, np.ndarray, np.ndarray]], lookup: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame (M,), landmark index (M,) and pixel (M, 2) arrays of per-frame records
    ``(frame, track ids, pixels)``; ``lookup`` maps track ids to landmark indices."""
    if not records:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    frame = np.concatenate([np.full(len(ids), k, np.int64) for k, ids, _ in records])
    landmark = lookup[np.concatenate([ids for _, ids, _ in records])]
    pixel = np.concatenate([px for _, _, px in records], 0).astype(np.float64)
    return frame, landmark, pixel


def _twist_to_origin(centre: np.ndarray) -> np.ndarray:
    """(6, 6) map of a twist about ``centre`` to the same rigid motion as a twist about the
    origin: ``dt_o = dt_c + [c]x dtheta``."""
    out = np.eye(6)
    out[:3, 3:] = skew(centre)
    return out


def stereo_match(
    left: np.ndarray,
    right: np.ndarray,
    points: np.ndarray,
    config: VoConfig,
    focal_baseline_px: float,
    disparity_guess: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The odometry's left -> right stereo match of features in a rectified pair.

    Features without a guess are first searched along their row
    (:func:`~msf_torch.vision.features.stereo_search`), then all are refined by KLT
    (``config.stereo_klt``); a match is good when the search found it, KLT converged, it
    stays within ``config.stereo_max_row_px`` of its row and its depth lies within
    ``[config.min_depth_m, config.max_depth_m]``.

    Args:
        left, right: (H, W) uint8 rectified images.
        points: (N, 2) float32 left pixels.
        config: the odometry's settings.
        focal_baseline_px: ``fx * baseline``, px m.
        disparity_guess: (N,) px, NaN where there is none (None: none at all).
    Returns:
        matched (N, 2) right pixels, disparity (N,) px (left x - right x), good (N,) bool.
    """
    count = len(points)
    guess = np.full(count, np.nan) if disparity_guess is None else disparity_guess.copy()
    searched = np.ones(count, bool)
    missing = np.isnan(guess)
    if missing.any():
        guess[missing], searched[missing] = stereo_search(
            left,
            right,
            points[missing],
            focal_baseline_px / config.min_depth_m,
            config.stereo_patch_px,
        )
    start = points - np.stack((guess, np.zeros(count)), -1).astype(np.float32)
    matched, good = track_klt(left, right, points, config.stereo_klt, start)
    disparity = points[:, 0] - matched[:, 0]
    good &= searched & (np.abs(matched[:, 1] - points[:, 1]) <= config.stereo_max_row_px)
    good &= (disparity >= focal_baseline_px / config.max_depth_m) & (
        disparity <= focal_baseline_px / config.min_depth_m
    )
    return matched, disparity, good


class StereoVisualOdometry:
    """Stereo visual odometry (see the module docstring). Feed frames in time order with
    :meth:`process`, or a whole sequence with :meth:`run`.

    Args:
        rig: the stereo rig (intrinsics, baseline, mount).
        config: settings.
    """

    def __init__(self, rig: CameraRig, config: VoConfig | None = None) -> None:
        self.rig = rig
        self.config = config or VoConfig()
        self.camera_matrix = rig.matrix()
        self.body_rotation_cam = rig.body_rotation_cam()
        self.body_translation_cam = rig.body_translation_cam()
        self.detector = AdaptiveFastDetector(self.config.detector)
        self._reset_state()

    def _reset_state(self) -> None:
        self.frames: list[VoFrame] = []
        self.keyframes: list[Keyframe] = []
        self._previous: np.ndarray | None = None
        self._points = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._xyz = np.zeros((0, 3))
        self._has_map = np.zeros(0, bool)
        self._next_id = 0
        self._map_xyz = np.full((0, 3), np.nan)  # by feature id; NaN: no map point
        self._map_weight = np.zeros(0)
        self._map_cov = np.zeros((0, 3, 3))  # by feature id: stereo error, world, m^2
        # by feature id: (anchor frames, shares) of the fused point
        self._anchors: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # frames whose pose errors points still carry (the last frame always), and the joint
        # covariance (W, W, 6, 6) of their pose errors as twists about the origin
        self._window = np.zeros(0, np.int64)
        self._joint = np.zeros((0, 0, 6, 6))
        self._obs: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._stereo: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._poses: list[tuple[np.ndarray, np.ndarray]] = []  # (rvec, tvec) per frame
        self._last_kf_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._last_kf_t = -math.inf
        self._last_kf_map = 0
        self.resets = 0

    # ---------------------------------------------------------------------------------------

    def _predict(self) -> tuple[np.ndarray, np.ndarray]:
        """Constant-velocity prediction of the camera pose ``(rvec, tvec)``."""
        rvec1, tvec1 = self._poses[-1]
        if len(self._poses) < 2:
            return rvec1.copy(), tvec1.copy()
        rvec0, tvec0 = self._poses[-2]
        rot1, _ = cv2.Rodrigues(rvec1.reshape(3, 1))
        rot0, _ = cv2.Rodrigues(rvec0.reshape(3, 1))
        # world -> camera transforms T1, T0; delta = T1 T0^-1; prediction = delta T1
        delta_rot = rot1 @ rot0.T
        delta_t = tvec1 - delta_rot @ tvec0
        rot2 = delta_rot @ rot1
        rvec2, _ = cv2.Rodrigues(rot2)
        return rvec2.reshape(3), delta_rot @ tvec1 + delta_t

    def _project(self, rvec: np.ndarray, tvec: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        rot, _ = cv2.Rodrigues(rvec.reshape(3, 1))
        cam = xyz @ rot.T + tvec
        z = np.maximum(cam[:, 2], 1e-6)
        k = self.camera_matrix
        return np.stack(
            (k[0, 0] * cam[:, 0] / z + k[0, 2], k[1, 1] * cam[:, 1] / z + k[1, 2]), -1
        ).astype(np.float32)

    def _keep(self, keep: np.ndarray) -> None:
        self._points = self._points[keep]
        self._ids = self._ids[keep]
        self._xyz = self._xyz[keep]
        self._has_map = self._has_map[keep]

    def _stereo_update(
        self, left: np.ndarray, right: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
    ) -> int:
        """Stereo-match the current features: make map points of those without one; with
        ``refine_map_points``, fuse the new depth into those with one. Returns the number
        of new map points."""
        cfg = self.config
        rows = np.arange(len(self._points)) if cfg.refine_map_points else None
        if rows is None:
            rows = np.nonzero(~self._has_map)[0]
        if rows.size == 0:
            return 0
        points = self._points[rows]
        fb = self.rig.fx * self.rig.baseline_m
        mapped = self._has_map[rows]
        disparity_guess = np.zeros(len(rows))
        if mapped.any():
            rot, _ = cv2.Rodrigues(rvec.reshape(3, 1))
            depth = (self._xyz[rows[mapped]] @ rot.T + tvec)[:, 2]
            disparity_guess[mapped] = fb / np.clip(depth, cfg.min_depth_m, cfg.max_depth_m)
        disparity_guess[~mapped] = np.nan
        matched, disp, good = stereo_match(left, right, points, cfg, fb, disparity_guess)
        if cfg.stereo_edge_max_px is not None:
            good &= ~self._edge_matches(left, right, points, matched, good, mapped, disp)
        disp = np.where(good, disp, 1.0)
        cam = triangulate_stereo(
            points,
            points - np.stack((disp, np.zeros_like(disp)), -1),
            self.camera_matrix,
            self.rig.baseline_m,
        )
        rotation_wc, centre = opencv_to_camera(rvec, tvec)
        world = cam @ rotation_wc.T + centre
        sigma_d = self._disparity_sigma(rows, good & mapped, disp, rotation_wc, centre)
        cov_cam = stereo_point_covariance(
            points, disp, self.camera_matrix, self.rig.baseline_m, 0.0, sigma_d
        )
        cov_world = rotation_wc @ cov_cam @ rotation_wc.T
        # depth sigma of a disparity sigma: z^2 sigma_d / (fx b)
        depth_sigma = cam[:, 2] ** 2 * cfg.stereo_disparity_sigma_px / fb
        weight = 1.0 / np.maximum(depth_sigma, 1e-9) ** 2
        frame_index = len(self.frames)
        fresh = good & ~mapped
        new_rows = rows[fresh]
        self._xyz[new_rows] = world[fresh]
        self._has_map[new_rows] = True
        ids = self._ids[new_rows]
        self._map_xyz[ids] = world[fresh]
        self._map_weight[ids] = weight[fresh]
        self._map_cov[ids] = cov_world[fresh]
        for i in ids.tolist():
            self._anchors[i] = (np.array([frame_index]), np.ones(1))
        if len(new_rows):
            self._stereo.append((len(self.frames), ids.copy(), matched[fresh].copy()))
        again = good & mapped
        if again.any():
            old_rows = rows[again]
            old_ids = self._ids[old_rows]
            old, old_weight = self._map_xyz[old_ids], self._map_weight[old_ids]
            new, new_weight = world[again], weight[again]
            gap = np.linalg.norm(new - old, axis=-1)
            combined_sigma = np.sqrt(1.0 / old_weight + 1.0 / new_weight)
            agree = gap <= 3.0 * combined_sigma
            total = old_weight + new_weight
            fused = (old * old_weight[:, None] + new * new_weight[:, None]) / total[:, None]
            fused_ids, fused_rows = old_ids[agree], old_rows[agree]
            share = (old_weight / total)[agree]  # the old point's share a in the fused one
            self._map_cov[fused_ids] = (
                share[:, None, None] ** 2 * self._map_cov[fused_ids]
                + (1.0 - share[:, None, None]) ** 2 * cov_world[again][agree]
            )
            for i, a in zip(fused_ids.tolist(), share.tolist(), strict=True):
                frames, shares = self._anchors[i]
                frames = np.append(frames, frame_index)
                shares = np.append(a * shares, 1.0 - a)
                kept = shares >= cfg.anchor_weight_min
                self._anchors[i] = (frames[kept], shares[kept] / shares[kept].sum())
            if agree.any():
                self._stereo.append(
                    (len(self.frames), fused_ids.copy(), matched[again][agree].copy())
                )
            self._map_xyz[fused_ids] = fused[agree]
            self._map_weight[fused_ids] = total[agree]
            self._xyz[fused_rows] = fused[agree]
        # features that cannot be triangulated now are dropped (they would block grid cells)
        drop = np.zeros(len(self._points), bool)
        drop[rows[~good & ~mapped]] = True
        self._keep(~drop)
        return int(fresh.sum())

    def _edge_matches(
        self,
        left: np.ndarray,
        right: np.ndarray,
        points: np.ndarray,
        matched: np.ndarray,
        good: np.ndarray,
        mapped: np.ndarray,
        disparity: np.ndarray,
    ) -> np.ndarray:
        """(N,) bool over the stereo matches ``good``: those below
        ``stereo_edge_max_disparity_px`` whose window straddles a depth edge (a sub-window
        disparity second difference beyond ``stereo_edge_max_px``, or a sub-window that
        does not match on its row; :func:`~msf_torch.vision.features.stereo_window_gaps`).
        New features among them are kept, the least edge-like first, while the map would
        otherwise hold fewer than ``keyframe_min_tracked`` points."""
        cfg = self.config
        out = np.zeros(len(points), bool)
        rows = np.nonzero(good & (disparity < cfg.stereo_edge_max_disparity_px))[0]
        if rows.size == 0:
            return out
        gaps = stereo_window_gaps(
            left,
            right,
            points[rows],
            matched[rows],
            cfg.stereo_edge_window_px,
            cfg.stereo_edge_offset_px,
        )
        score = np.nan_to_num(np.abs(gaps), nan=np.inf).max(-1)
        edge = score > cfg.stereo_edge_max_px
        new_edge = edge & ~mapped[rows]
        lacking = cfg.keyframe_min_tracked - int(self._has_map.sum() + (good & ~mapped).sum())
        lacking += int(new_edge.sum())
        if lacking > 0:
            order = np.nonzero(new_edge)[0]
            edge[order[np.argsort(score[order], kind="stable")][:lacking]] = False
        out[rows[edge]] = True
        return out

    def _disparity_sigma(
        self,
        rows: np.ndarray,
        again: np.ndarray,
        disparity: np.ndarray,
        rotation_wc: np.ndarray,
        centre: np.ndarray,
    ) -> float:
        """Disparity sigma, px, for this keyframe's stereo points' covariance: the larger of
        ``stereo_disparity_sigma_px`` and the RMS gap between the disparities of the
        re-matched map points (``again``, (R,) over ``rows``) and those their map points
        predict, less the map points' own share (their depth variance along the optical
        axis, ``(fx b / z^2)^2 a^T S a``), when at least ``min_pnp_inliers`` points were
        re-matched. Bad weather and low texture widen the gaps."""
        cfg = self.config
        sigma = cfg.stereo_disparity_sigma_px
        if int(again.sum()) < cfg.min_pnp_inliers:
            return sigma
        ids = self._ids[rows[again]]
        axis = rotation_wc[:, 2]
        depth = (self._xyz[rows[again]] - centre) @ axis
        fb = self.rig.fx * self.rig.baseline_m
        gap = disparity[again] - fb / depth
        old_var = (fb / depth**2) ** 2 * np.einsum("i,nij,j->n", axis, self._map_cov[ids], axis)
        excess = float(np.mean(gap**2 - old_var))
        return max(sigma, math.sqrt(max(excess, 0.0)))

    def _is_keyframe(self, t: float, rvec: np.ndarray, tvec: np.ndarray, map_count: int) -> bool:
        cfg = self.config
        if self._last_kf_pose is None:
            return True
        if t - self._last_kf_t >= cfg.keyframe_interval_s:
            return True
        if map_count < cfg.keyframe_min_tracked:
            return True
        if map_count < cfg.keyframe_track_ratio * self._last_kf_map:
            return True
        rot_kf, centre_kf = opencv_to_camera(*self._last_kf_pose)
        rot, centre = opencv_to_camera(rvec, tvec)
        if np.linalg.norm(centre - centre_kf) >= cfg.keyframe_translation_m:
            return True
        turn, _ = cv2.Rodrigues(rot_kf.T @ rot)
        return math.degrees(float(np.linalg.norm(turn))) >= cfg.keyframe_rotation_deg

    # ---------------------------------------------------------------------------------------

    def process(self, t: float, left: np.ndarray, right: np.ndarray) -> VoFrame:
        """Process one stereo frame (times increasing).

        Args:
            t: time, s.
            left, right: (H, W) uint8 rectified images of the rig's size.
        Returns:
            the frame's :class:`VoFrame` (also appended to ``frames``).
        Raises:
            ValueError: an image has the wrong size or type.
        """
        for name, image in (("left", left), ("right", right)):
            if image.shape != (self.rig.height, self.rig.width) or image.dtype != np.uint8:
                raise ValueError(
                    f"StereoVisualOdometry: {name} image must be uint8 "
                    f"({self.rig.height}, {self.rig.width}), got {image.dtype} {image.shape}"
                )
        start = time.perf_counter()
        cpu_start = time.thread_time()
        cfg = self.config
        index = len(self.frames)
        quality = image_quality(left)
        tracked_count = 0
        inliers = 0
        pixel_sigma = math.nan
        if self._previous is None:
            status = "init"
            rvec, tvec = camera_to_opencv(self.body_rotation_cam, self.body_translation_cam)
            self._window = np.array([index])
            self._joint = np.zeros((1, 1, 6, 6))
        else:
            rvec_pred, tvec_pred = self._predict()
            guess = self._points.copy()
            if self._has_map.any():
                guess[self._has_map] = self._project(rvec_pred, tvec_pred, self._xyz[self._has_map])
            previous_points = self._points.copy()
            tracked, good = track_klt(self._previous, left, self._points, cfg.klt, guess)
            self._points = tracked
            self._keep(good)
            previous_points = previous_points[good]
            tracked_count = int(good.sum())
            has_map = self._has_map
            pnp = solve_pnp(
                self._xyz[has_map],
                self._points[has_map],
                self.camera_matrix,
                rvec_pred,
                tvec_pred,
                cfg.pnp_reprojection_px,
                cfg.pnp_iterations,
                cfg.min_pnp_inliers,
            )
            if pnp.ok:
                status = "pnp"
                rvec, tvec = pnp.rvec, pnp.tvec
                keep = np.ones(len(self._points), bool)
                keep[np.nonzero(has_map)[0][~pnp.inliers]] = False
                self._keep(keep)
                previous_points = previous_points[keep]
                inliers = int(pnp.inliers.sum())
                # before the keyframe's stereo update changes the map
                increment, pixel_sigma = self._pnp_increment(index, rvec, tvec, previous_points)
            else:
                status, rvec, tvec, inliers = self._fallback(previous_points, rvec_pred, tvec_pred)
        map_count = int(self._has_map.sum())
        new_points = 0
        keyframe = self._is_keyframe(t, rvec, tvec, map_count)
        if keyframe:
            new = self.detector.detect(left, self._points)
            if len(new):
                ids = np.arange(self._next_id, self._next_id + len(new))
                self._next_id += len(new)
                if self._next_id > len(self._map_weight):
                    grow = max(self._next_id, 2 * len(self._map_weight))
                    self._map_xyz = np.concatenate(
                        (self._map_xyz, np.full((grow - len(self._map_xyz), 3), np.nan)), 0
                    )
                    self._map_weight = np.concatenate(
                        (self._map_weight, np.zeros(grow - len(self._map_weight)))
                    )
                    self._map_cov = np.concatenate(
                        (self._map_cov, np.zeros((grow - len(self._map_cov), 3, 3))), 0
                    )
                self._points = np.concatenate((self._points, new), 0)
                self._ids = np.concatenate((self._ids, ids))
                self._xyz = np.concatenate((self._xyz, np.zeros((len(new), 3))), 0)
                self._has_map = np.concatenate((self._has_map, np.zeros(len(new), bool)))
            had_map = map_count
            new_points = self._stereo_update(left, right, rvec, tvec)
            map_count = int(self._has_map.sum())
            if had_map == 0 and index > 0 and map_count > 0 and status == "lost":
                self.resets += 1
            self._last_kf_pose = (rvec.copy(), tvec.copy())
            self._last_kf_t = t
            self._last_kf_map = map_count
        if cfg.record_tracks and status in ("init", "pnp"):
            rows = self._has_map
            self._obs.append((index, self._ids[rows].copy(), self._points[rows].copy()))
        position, rotation = body_pose(
            rvec, tvec, self.body_rotation_cam, self.body_translation_cam
        )
        covariance = np.full((6, 6), np.nan)
        if status == "pnp":
            covariance = 0.5 * camera_twist_to_body(increment, rotation, self.body_translation_cam)
        elif status in ("essential", "lost"):
            # the fallback's step covariance stands for the increment (the anchors' history)
            step_covariance = self._essential_covariance(position)
            increment = camera_twist_to_body(
                step_covariance, rotation, self.body_translation_cam, inverse=True
            )
            self._step_increment(index, opencv_to_camera(rvec, tvec)[1], increment)
            if status == "essential":
                covariance = step_covariance
        self._prune_window(index)
        if keyframe:
            self._store_keyframe(index, t, left, position, rotation)
        self._poses.append((rvec.copy(), tvec.copy()))
        self._previous = left
        frame = VoFrame(
            t=float(t),
            status=status,
            position=position,
            rotation=rotation,
            covariance=covariance,
            pixel_sigma=pixel_sigma,
            tracked=tracked_count,
            map_tracked=map_count,
            inliers=inliers,
            new_points=new_points,
            keyframe=keyframe,
            threshold=self.detector.threshold,
            quality=quality,
            wall_s=time.perf_counter() - start,
            cpu_s=time.thread_time() - cpu_start,
        )
        self.frames.append(frame)
        return frame

    def _fallback(
        self, previous_points: np.ndarray, rvec_pred: np.ndarray, tvec_pred: np.ndarray
    ) -> tuple[str, np.ndarray, np.ndarray, int]:
        """Essential-matrix pose when PnP fails (step length from the previous step), else
        the prediction (lost)."""
        cfg = self.config
        ok, rot_ab, t_ab, inlier = relative_pose_essential(
            previous_points,
            self._points,
            self.camera_matrix,
            cfg.essential_threshold_px,
            cfg.min_pnp_inliers,
        )
        if not ok:
            return "lost", rvec_pred, tvec_pred, 0
        rvec_prev, tvec_prev = self._poses[-1]
        rot_prev, _ = cv2.Rodrigues(rvec_prev.reshape(3, 1))
        if len(self._poses) >= 2:
            _, c1 = opencv_to_camera(*self._poses[-1])
            _, c0 = opencv_to_camera(*self._poses[-2])
            step = float(np.linalg.norm(c1 - c0))
        else:
            step = 0.0
        # x_b = R x_a + t (camera frames); world -> b = (R, step t) composed with world -> a
        rot = rot_ab @ rot_prev
        tvec = rot_ab @ tvec_prev + step * t_ab
        rvec, _ = cv2.Rodrigues(rot)
        return "essential", rvec.reshape(3), tvec, int(inlier.sum())

    def _pnp_increment(
        self, index: int, rvec: np.ndarray, tvec: np.ndarray, previous_points: np.ndarray
    ) -> tuple[np.ndarray, float]:
        """Covariance (6, 6) of frame ``index``'s PnP pose relative to the previous frame's,
        over the camera's twist about its centre, and the pixel sigma used (module
        docstring); appends the frame to the window of anchor frames. The features with map
        points are the PnP inliers; ``previous_points`` (rows aligned with the features) are
        their pixels in the previous frame."""
        cfg = self.config
        rows = self._has_map
        xyz, ids = self._xyz[rows], self._ids[rows]
        change = residual_change(
            xyz,
            self._points[rows].astype(np.float64),
            previous_points[rows].astype(np.float64),
            (rvec, tvec),
            self._poses[-1],
            self.camera_matrix,
        )
        # tracking noise: each track's own residual change (heteroscedasticity-consistent),
        # scaled up for the 6 coordinates the pose absorbs, plus the floor
        count = len(ids)
        outer = change[:, :, None] * change[:, None, :] * (2 * count / (2 * count - 6))
        pixel_cov = outer + cfg.sigma_floor_px**2 * np.eye(2)
        sigma = math.sqrt(0.5 * float(np.trace(pixel_cov.mean(0))))
        rotation_wc, centre = opencv_to_camera(rvec, tvec)
        own, gain = uncertain_point_pnp(
            xyz, self._map_cov[ids], rotation_wc, centre, self.camera_matrix, pixel_cov
        )
        # e_k = (own error) + sum_a W_a e_a over the anchors a, twists about the origin
        anchor_lists = [self._anchors[i] for i in ids.tolist()]
        point = np.repeat(np.arange(len(ids)), [len(f) for f, _ in anchor_lists])
        frames = np.concatenate([f for f, _ in anchor_lists])
        shares = np.concatenate([w for _, w in anchor_lists])
        anchors, which = np.unique(frames, return_inverse=True)
        eye = np.broadcast_to(np.eye(3), (len(ids), 3, 3))
        motion = np.concatenate((eye, -skew(xyz)), -1)  # a point's motion under a twist
        per_anchor = np.zeros((len(anchors), 6, 6))
        np.add.at(per_anchor, which, shares[:, None, None] * (gain @ motion)[point])
        to_origin = _twist_to_origin(centre)
        loading = to_origin @ per_anchor
        slot = np.searchsorted(self._window, anchors)
        cross = np.einsum("aij,awjk->wik", loading, self._joint[slot])  # Cov(e_k, e_w)
        total = to_origin @ own @ to_origin.T + np.einsum("bij,bkj->ik", cross[slot], loading)
        self._append_window(index, cross, total)
        last = len(self._window) - 2  # the previous frame
        increment = total + self._joint[last, last] - cross[last] - cross[last].T
        back = np.linalg.inv(to_origin)
        return back @ increment @ back.T, sigma

    def _step_increment(self, index: int, centre: np.ndarray, increment: np.ndarray) -> None:
        """Append a frame whose pose is the previous one's plus a step of covariance
        ``increment`` (6, 6, twist about the camera ``centre``) to the window."""
        to_origin = _twist_to_origin(centre)
        cross = self._joint[-1].copy()
        total = self._joint[-1, -1] + to_origin @ increment @ to_origin.T
        self._append_window(index, cross, total)

    def _append_window(self, index: int, cross: np.ndarray, total: np.ndarray) -> None:
        count = len(self._window)
        joint = np.zeros((count + 1, count + 1, 6, 6))
        joint[:count, :count] = self._joint
        joint[count, :count] = cross
        joint[:count, count] = cross.transpose(0, 2, 1)
        joint[count, count] = total
        self._window = np.append(self._window, index)
        self._joint = joint

    def _prune_window(self, index: int) -> None:
        """Keep the frames that some map point still carries, and frame ``index``."""
        ids = self._ids[self._has_map].tolist()
        referenced = np.unique(np.concatenate([[index]] + [self._anchors[i][0] for i in ids]))
        keep = np.isin(self._window, referenced)
        if not keep.all():
            self._window = self._window[keep]
            self._joint = self._joint[keep][:, keep]

    def _essential_covariance(self, position: np.ndarray) -> np.ndarray:
        cfg = self.config
        previous = self.frames[-1].position if self.frames else position
        step = float(np.linalg.norm(position - previous))
        out = np.zeros((6, 6))
        out[:3, :3] = np.eye(3) * (cfg.essential_step_sigma * step + 0.01) ** 2
        out[3:, 3:] = np.eye(3) * cfg.essential_rotation_sigma_rad**2
        return out

    def _store_keyframe(
        self, index: int, t: float, left: np.ndarray, position: np.ndarray, rotation: np.ndarray
    ) -> None:
        if self.config.descriptors:
            rows, descriptors = orb_descriptors(left, self._points)
        else:
            rows, descriptors = np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        self.keyframes.append(
            Keyframe(
                frame=index,
                t=float(t),
                position=position.copy(),
                rotation=rotation.copy(),
                pixels=self._points.copy(),
                feature_ids=self._ids.copy(),
                landmark=self._has_map.copy(),
                descriptor_index=rows,
                descriptors=descriptors,
            )
        )

    # ---------------------------------------------------------------------------------------

    def result(self) -> VoResult:
        """Everything processed so far as a :class:`VoResult`."""
        frames = self.frames
        covariance = np.stack([f.covariance for f in frames]) if frames else np.zeros((0, 6, 6))
        # the first frame has no covariance of its own: it takes the first measured one
        measured = [k for k, f in enumerate(frames) if not np.isnan(f.covariance).any()]
        if measured:
            covariance[np.isnan(covariance).any((1, 2))] = covariance[measured[0]]
        landmark_ids = np.nonzero(np.isfinite(self._map_xyz[: self._next_id, 0]))[0]
        landmarks = self._map_xyz[landmark_ids].copy()
        lookup = np.full(self._next_id, -1, np.int64)
        lookup[landmark_ids] = np.arange(len(landmark_ids))
        obs_frame, obs_landmark, obs_pixel = _stack_observations(self._obs, lookup)
        stereo_frame, stereo_landmark, stereo_pixel = _stack_observations(self._stereo, lookup)
        return VoResult(
            t=np.array([f.t for f in frames]),
            status=np.array([STATUSES.index(f.status) for f in frames], np.int64),
            position=np.stack([f.position for f in frames]) if frames else np.zeros((0, 3)),
            rotation=np.stack([f.rotation for f in frames]) if frames else np.zeros((0, 3, 3)),
            covariance=covariance,
            pixel_sigma=np.array([f.pixel_sigma for f in frames]),
            tracked=np.array([f.tracked for f in frames], np.int64),
            map_tracked=np.array([f.map_tracked for f in frames], np.int64),
            inliers=np.array([f.inliers for f in frames], np.int64),
            new_points=np.array([f.new_points for f in frames], np.int64),
            keyframe=np.array([f.keyframe for f in frames], bool),
            threshold=np.array([f.threshold for f in frames]),
            quality=np.stack([f.quality for f in frames]) if frames else np.zeros((0, 4)),
            wall_s=np.array([f.wall_s for f in frames]),
            cpu_s=np.array([f.cpu_s for f in frames]),
            keyframes=list(self.keyframes),
            landmarks=landmarks,
            landmark_ids=landmark_ids,
            obs_frame=obs_frame,
            obs_landmark=obs_landmark,
            obs_pixel=obs_pixel,
            stereo_frame=stereo_frame,
            stereo_landmark=stereo_landmark,
            stereo_pixel=stereo_pixel,
            resets=self.resets,
            rig=self.rig,
        )

    def run(self, frames: Iterable) -> VoResult:
        """Process ``(t, left, right)`` triples (or objects with ``t``, ``left``, ``right``
        attributes, e.g. :class:`~msf_torch.sim.render.StereoFrame`) and return the result."""
        for item in frames:
            if isinstance(item, tuple):
                t, left, right = item
            else:
                t, left, right = item.t, item.left, item.right
            self.process(t, left, right)
        return self.result()
