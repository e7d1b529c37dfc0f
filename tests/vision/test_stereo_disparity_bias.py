"""The keyframe stereo match against the rendered true disparity, on the ground.

New features are matched as ``StereoVisualOdometry`` matches them (``stereo_match``: the row
search with ``stereo_patch_px``, then KLT with ``stereo_klt``) on the 41 frames of the shared
4 s drive;
the truth is the renderer's range at the left pixel. On features whose 21 x 21 px
neighbourhood lies on one surface (the true disparity is affine there: second differences
below 0.05 px) and whose disparity changes down the column (the ground, seen at a grazing
angle), the median relative disparity error must stay within 0.07 %. The 11 px window gives
-0.035 % (2528 features; bootstrap sigma of the median 0.02 %); larger ones read the ground's
disparity low, i.e. its depth high: 15 px -0.054 %, 21 px -0.104 %, 31 px -0.214 % (bootstrap
sigma 0.035 / 0.045 % for 21 / 31 px), so the test fails for a 21 or 31 px window. On the
90 s benchmark runs (seeds 11-13) the same class reads -0.02..-0.05 % at 11 px, -0.14..-0.22 %
at 21 px and -0.35..-0.58 % at 31 px (docs/visual.md).
"""

from __future__ import annotations

import numpy as np

from msf_torch.vision import VoConfig
from msf_torch.vision.features import AdaptiveFastDetector
from msf_torch.vision.odometry import stereo_match

PLANE_RADIUS_PX = 10
SLANT_PX_PER_ROW = 0.02


def _slanted_plane(disparity: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Features whose neighbourhood within PLANE_RADIUS_PX lies on one plane (disparity
    affine in the pixel) and whose disparity changes down the column."""
    height, width = disparity.shape
    r = PLANE_RADIUS_PX
    x = np.clip(np.rint(points[:, 0]).astype(np.int64), r, width - 1 - r)
    y = np.clip(np.rint(points[:, 1]).astype(np.int64), r, height - 1 - r)
    centre = disparity[y, x]
    second = sum(
        np.abs(disparity[y + dy, x + dx] + disparity[y - dy, x - dx] - 2.0 * centre)
        for dx, dy in ((r, 0), (0, r), (r, r), (r, -r))
    )
    slope = (disparity[y + r, x] - disparity[y - r, x]) / (2 * r)
    return (centre > 0.0) & (second < 0.05) & (np.abs(slope) > SLANT_PX_PER_ROW)


def test_stereo_match_is_unbiased_on_the_ground(rendered):
    _, renderer, frames = rendered
    cfg = VoConfig()
    rig = renderer.rig
    fb = rig.fx * rig.baseline_m
    measured, true = [], []
    for frame in frames:
        truth = renderer.true_disparity(frame.position, frame.rotation)
        points = AdaptiveFastDetector(cfg.detector).detect(frame.left)
        matched, _, good = stereo_match(frame.left, frame.right, points, cfg, fb)
        good &= _slanted_plane(truth, points)
        # the truth is affine around these points: bilinear interpolation is exact
        x, y = points[good, 0], points[good, 1]
        x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx_, fy_ = x - x0, y - y0
        at = (
            truth[y0, x0] * (1 - fx_) * (1 - fy_)
            + truth[y0, x0 + 1] * fx_ * (1 - fy_)
            + truth[y0 + 1, x0] * (1 - fx_) * fy_
            + truth[y0 + 1, x0 + 1] * fx_ * fy_
        )
        measured.append(points[good, 0] - matched[good, 0])
        true.append(at)
    measured, true = np.concatenate(measured), np.concatenate(true)
    assert len(measured) > 2000
    relative = np.median(measured / true - 1.0)
    assert abs(relative) < 7e-4, f"median relative disparity error {relative:+.3%}"
