"""Feature detection with an adaptive FAST threshold, KLT tracking, ORB descriptors.

:class:`AdaptiveFastDetector` spreads new features over a grid: FAST corners (non-maximum
suppressed) are detected where no tracked feature lies within ``min_distance_px``, and each
grid cell keeps its strongest ``per_cell`` minus the tracked features already in it. The
FAST threshold is the detector's state: when a detection finds fewer candidates than it
wants, the threshold is multiplied by ``lower_factor`` (not below ``threshold_min``) and the
detection repeated, up to ``max_retries`` times, so tracking survives low-texture stretches;
when it finds more than ``raise_above`` times what it wants, the threshold is multiplied by
``raise_factor`` (not above ``threshold_max``) for the next call, so it does not stay low
once the texture comes back.

:func:`track_klt` is pyramidal Lucas-Kanade, optionally checked forward-backward;
:func:`stereo_window_gaps` re-matches stereo matches with small windows beside the feature
and returns how far their disparities are from affine (a depth edge in the window);
:func:`orb_descriptors` computes upright ORB descriptors (the camera of a ground robot does
not roll) at given points, e.g. for a keyframe's bag of words.
"""

from __future__ import annotations

__all__ = [
    "DetectorConfig",
    "AdaptiveFastDetector",
    "KltConfig",
    "track_klt",
    "stereo_search",
    "stereo_window_gaps",
    "orb_descriptors",
]

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DetectorConfig:
    """Settings of :class:`AdaptiveFastDetector`.

    Attributes:
        threshold_init: first FAST threshold, DN.
        threshold_min, threshold_max: bounds of the adaptive threshold, DN.
        grid_cols, grid_rows: bucketing grid.
        per_cell: features per cell (tracked plus new).
        min_distance_px: new features keep this far from tracked ones, px.
        border_px: no features this close to the image border, px (ORB needs 16).
        lower_factor: threshold multiplier when too few candidates are found.
        raise_factor: threshold multiplier when far too many are found.
        raise_above: "far too many" = this times the number wanted.
        max_retries: detections repeated at a lowered threshold per call.
    """

    threshold_init: float = 20.0
    threshold_min: float = 4.0
    threshold_max: float = 80.0
    grid_cols: int = 8
    grid_rows: int = 6
    per_cell: int = 6
    min_distance_px: float = 12.0
    border_px: int = 16
    lower_factor: float = 0.6
    raise_factor: float = 1.25
    raise_above: float = 4.0
    max_retries: int = 3


class AdaptiveFastDetector:
    """Grid-bucketed FAST detection with an adaptive threshold (see the module docstring).

    Attributes:
        config: the settings.
        threshold: the current FAST threshold, DN.
        last_candidates: FAST corners found in free cells by the last call.
        last_retries: detections repeated at a lowered threshold by the last call.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()
        self.threshold = float(self.config.threshold_init)
        self.last_candidates = 0
        self.last_retries = 0

    def detect(self, image: np.ndarray, existing: np.ndarray | None = None) -> np.ndarray:
        """New feature positions (M, 2) float32 px, strongest first within each cell.

        Args:
            image: (H, W) uint8.
            existing: (N, 2) px of the features already tracked, or None.
        """
        cfg = self.config
        height, width = image.shape
        existing = np.zeros((0, 2), np.float32) if existing is None else existing
        cell_w, cell_h = width / cfg.grid_cols, height / cfg.grid_rows
        cells = cfg.grid_cols * cfg.grid_rows
        taken = np.bincount(self._cell(existing, cell_w, cell_h), minlength=cells)[:cells]
        room = np.maximum(cfg.per_cell - taken, 0)
        wanted = int(room.sum())
        self.last_retries = 0
        if wanted == 0:
            self.last_candidates = 0
            return np.zeros((0, 2), np.float32)
        mask = np.zeros((height, width), np.uint8)
        b = cfg.border_px
        mask[b : height - b, b : width - b] = 255
        radius = int(round(cfg.min_distance_px))
        for x, y in np.rint(existing).astype(np.int32):
            cv2.circle(mask, (int(x), int(y)), radius, 0, -1)
        while True:
            fast = cv2.FastFeatureDetector_create(int(round(self.threshold)), True)
            keypoints = fast.detect(image, mask)
            self.last_candidates = len(keypoints)
            if (
                self.last_candidates >= wanted
                or self.threshold <= cfg.threshold_min
                or self.last_retries >= cfg.max_retries
            ):
                break
            self.threshold = max(cfg.threshold_min, self.threshold * cfg.lower_factor)
            self.last_retries += 1
        if self.last_candidates > cfg.raise_above * wanted:
            self.threshold = min(cfg.threshold_max, self.threshold * cfg.raise_factor)
        if not keypoints:
            return np.zeros((0, 2), np.float32)
        points = np.array([k.pt for k in keypoints], np.float32)
        response = np.array([k.response for k in keypoints], np.float32)
        cell = self._cell(points, cell_w, cell_h)
        order = np.lexsort((-response, cell))
        sorted_cell = cell[order]
        first = np.searchsorted(sorted_cell, sorted_cell, side="left")
        rank = np.arange(len(order)) - first
        keep = order[rank < room[sorted_cell]]
        return points[keep]

    def _cell(self, points: np.ndarray, cell_w: float, cell_h: float) -> np.ndarray:
        cfg = self.config
        col = np.clip((points[:, 0] / cell_w).astype(np.int64), 0, cfg.grid_cols - 1)
        row = np.clip((points[:, 1] / cell_h).astype(np.int64), 0, cfg.grid_rows - 1)
        return row * cfg.grid_cols + col


@dataclass(frozen=True)
class KltConfig:
    """Pyramidal Lucas-Kanade settings.

    Attributes:
        window_px: search window side, px.
        levels: pyramid levels above the full image.
        iterations: iterations per level. epsilon: convergence threshold, px.
        max_forward_backward_px: a track is kept when tracking it back lands within this of
            where it started, px; None skips the backward pass (half the cost).
        max_error: a track is kept when its mean absolute patch difference after
            convergence is at most this, DN.
    """

    window_px: int = 21
    levels: int = 3
    iterations: int = 20
    epsilon: float = 0.03
    max_forward_backward_px: float | None = 0.5
    max_error: float = 30.0


def track_klt(
    previous: np.ndarray,
    current: np.ndarray,
    points: np.ndarray,
    config: KltConfig,
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track points from one pyramid to another, checked forward-backward.

    Args:
        previous, current: (H, W) uint8 images (OpenCV builds the pyramids).
        points: (N, 2) float32 px in ``previous``.
        guess: (N, 2) float32 predicted positions in ``current`` (None: no motion).
    Returns:
        tracked positions (N, 2) float32 px and a boolean (N,) mask of good tracks.
    """
    count = len(points)
    if count == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, config.iterations, config.epsilon)
    window = (config.window_px, config.window_px)
    start = points.reshape(-1, 1, 2).astype(np.float32)
    flags = 0
    initial = None
    if guess is not None:
        initial = guess.reshape(-1, 1, 2).astype(np.float32).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    forward, status, patch_error = cv2.calcOpticalFlowPyrLK(
        previous,
        current,
        start,
        initial,
        winSize=window,
        maxLevel=config.levels,
        criteria=criteria,
        flags=flags,
    )
    good = (status.reshape(-1) == 1) & (patch_error.reshape(-1) <= config.max_error)
    if config.max_forward_backward_px is not None:
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(
            current,
            previous,
            forward,
            start.copy(),
            winSize=window,
            maxLevel=config.levels,
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        error = np.linalg.norm((back - start).reshape(-1, 2), axis=-1)
        good &= (status_back.reshape(-1) == 1) & (error <= config.max_forward_backward_px)
    tracked = forward.reshape(-1, 2)
    height, width = current.shape[:2]
    good &= (tracked[:, 0] >= 0) & (tracked[:, 0] <= width - 1)
    good &= (tracked[:, 1] >= 0) & (tracked[:, 1] <= height - 1)
    return tracked, good


def stereo_search(
    left: np.ndarray,
    right: np.ndarray,
    points: np.ndarray,
    max_disparity_px: float,
    patch_px: int = 11,
    min_score: float = 0.8,
    min_margin: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Integer disparity of each point by normalised cross-correlation along its row.

    The ``patch_px`` square around each (rounded) left point is compared with every
    position on the same row of the right image from disparity 0 to ``max_disparity_px``
    (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``). A match needs a peak score of at least
    ``min_score`` that beats the best score more than 2 px away by ``min_margin``
    (repetitive texture is refused). The search has no prior depth, so it does not pull the
    disparity of far points towards a guess; :func:`track_klt` refines it to sub-pixel.

    Args:
        left, right: (H, W) uint8 rectified images.
        points: (N, 2) px in the left image.
        max_disparity_px: largest disparity searched, px.
        patch_px: odd patch side, px.
        min_score, min_margin: acceptance (see above).
    Returns:
        disparity (N,) float32 px (integer valued) and a boolean (N,) mask of matches.
    """
    half = patch_px // 2
    height, width = left.shape
    count = len(points)
    disparity = np.zeros(count, np.float32)
    good = np.zeros(count, bool)
    span = int(np.ceil(max_disparity_px))
    for i, (x, y) in enumerate(np.rint(points).astype(np.int64)):
        if not (half <= y < height - half and half <= x < width - half):
            continue
        low = max(half, x - span)
        template = left[y - half : y + half + 1, x - half : x + half + 1]
        strip = right[y - half : y + half + 1, low - half : x + half + 1]
        scores = cv2.matchTemplate(strip, template, cv2.TM_CCOEFF_NORMED)[0]
        best = int(np.argmax(scores))
        peak = float(scores[best])
        others = np.concatenate((scores[: max(best - 2, 0)], scores[best + 3 :]))
        runner_up = float(others.max()) if others.size else -1.0
        if peak >= min_score and peak - runner_up >= min_margin:
            disparity[i] = x - (low + best)
            good[i] = True
    return disparity, good


def stereo_window_gaps(
    left: np.ndarray,
    right: np.ndarray,
    points: np.ndarray,
    matched: np.ndarray,
    window_px: int = 7,
    offset_px: float = 4.0,
    iterations: int = 20,
    epsilon: float = 0.03,
) -> np.ndarray:
    """Second differences of the disparity across each stereo match's window, px.

    Each left point is re-matched in the right image (single-level Lucas-Kanade started at
    ``matched`` shifted alike) with a ``window_px`` square centred on it and on the four
    points ``offset_px`` to its left, right, above and below. Inside one surface the
    disparity is affine in the pixel (a plane), so the second differences
    ``d(x - o) + d(x + o) - 2 d(x)`` along the row and along the column are zero up to the
    match noise; a depth edge within ``offset_px`` plus half a window of the feature makes
    them as large as the disparity step. A sub-window whose match fails (no convergence,
    or its row moves by more than 1 px) gives NaN for its direction.

    Args:
        left, right: (H, W) uint8 rectified images.
        points: (N, 2) float32 px in the left image.
        matched: (N, 2) float32 px, their matches in the right image.
        window_px: side of the small windows, px.
        offset_px: distance of the side windows from the point, px.
        iterations, epsilon: Lucas-Kanade stopping rule (count, px).
    Returns:
        (N, 2) float64 px: the second differences along the row and along the column.
    """
    count = len(points)
    if count == 0:
        return np.zeros((0, 2))
    shifts = np.array(
        [[0.0, 0.0], [-offset_px, 0.0], [offset_px, 0.0], [0.0, -offset_px], [0.0, offset_px]],
        np.float32,
    )
    start = (points[None].astype(np.float32) + shifts[:, None]).reshape(-1, 1, 2)
    guess = (matched[None].astype(np.float32) + shifts[:, None]).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, epsilon)
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        left,
        right,
        start,
        guess.copy(),
        winSize=(window_px, window_px),
        maxLevel=0,
        criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    start, found = start.reshape(5, count, 2), found.reshape(5, count, 2)
    ok = (status.reshape(5, count) == 1) & (np.abs(found[..., 1] - start[..., 1]) <= 1.0)
    disparity = np.where(ok, start[..., 0] - found[..., 0], np.nan).astype(np.float64)
    centre = disparity[0]
    return np.stack(
        (disparity[1] + disparity[2] - 2 * centre, disparity[3] + disparity[4] - 2 * centre),
        -1,
    )


_ORB: dict[int, cv2.ORB] = {}


def orb_descriptors(image: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upright ORB descriptors at points (angle 0, full resolution).

    Args:
        image: (H, W) uint8. points: (N, 2) px.
    Returns:
        indices (K,) int64 of the points that got a descriptor (those far enough from the
        border) and their descriptors (K, 32) uint8.
    """
    if 0 not in _ORB:
        _ORB[0] = cv2.ORB_create(edgeThreshold=16, patchSize=31)
    keypoints = [
        cv2.KeyPoint(float(x), float(y), 31.0, 0.0, 0.0, 0, i) for i, (x, y) in enumerate(points)
    ]
    kept, descriptors = _ORB[0].compute(image, keypoints)
    if descriptors is None or not kept:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    return np.array([k.class_id for k in kept], np.int64), descriptors
