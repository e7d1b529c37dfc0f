"""Per-frame image-quality statistics (the covariance network's weather input).

For an 8-bit grayscale image ``I`` (values in DN, 0-255):

* ``brightness`` = ``mean(I) / 255``;
* ``contrast`` = RMS contrast ``std(I) / 255``;
* ``laplacian_var`` = variance of the 4-neighbour Laplacian
  ``L = I(x-1, y) + I(x+1, y) + I(x, y-1) + I(x, y+1) - 4 I(x, y)`` over the interior
  pixels (one-pixel border left out), DN^2: a focus / blur / texture measure that fog, rain
  and low texture lower;
* ``dark_channel`` = the dark-channel fog estimate (He, Sun and Tang): the dark channel is
  the minimum of ``I`` over a ``patch`` x ``patch`` window around each pixel; the airlight
  ``A`` is the mean intensity of the brightest 0.1 % of the dark channel; the estimate is
  ``mean(dark) / A``, which is ``1 - mean(t)`` for the transmission ``t = 1 - dark / A`` of
  the scattering model ``I = J t + A (1 - t)`` with a dark haze-free ``J``. It rises with
  the extinction coefficient.

Reference: K. He, J. Sun, X. Tang, "Single image haze removal using dark channel prior",
CVPR 2009.
"""

from __future__ import annotations

__all__ = ["QUALITY_NAMES", "image_quality"]

import cv2
import numpy as np

QUALITY_NAMES: tuple[str, ...] = ("contrast", "laplacian_var", "dark_channel", "brightness")
"""Order of the statistics in :func:`image_quality`'s output."""


def image_quality(image: np.ndarray, patch: int = 15) -> np.ndarray:
    """Image-quality statistics of one frame, in :data:`QUALITY_NAMES` order.

    Args:
        image: (H, W) uint8 grayscale image (H, W >= 3).
        patch: dark-channel window side, px (odd).
    Returns:
        (4,) float64: contrast (0-1), Laplacian variance (DN^2), dark-channel fog estimate
        (0-1), brightness (0-1).
    Raises:
        ValueError: not a 2-D uint8 image of at least 3 x 3 pixels, or an even ``patch``.
    """
    if image.ndim != 2 or image.dtype != np.uint8 or min(image.shape) < 3:
        raise ValueError(
            f"image_quality: needs a 2-D uint8 image of at least 3 x 3 px, got "
            f"{image.dtype} {tuple(image.shape)}"
        )
    if patch < 1 or patch % 2 == 0:
        raise ValueError(f"image_quality: patch must be a positive odd size, got {patch}")
    values = image.astype(np.float32)
    mean, std = cv2.meanStdDev(values)
    laplacian = cv2.Laplacian(values, cv2.CV_32F, ksize=1)[1:-1, 1:-1]
    _, lap_std = cv2.meanStdDev(laplacian)
    dark = cv2.erode(
        image, np.ones((patch, patch), np.uint8), borderType=cv2.BORDER_REPLICATE
    ).reshape(-1)
    histogram = np.bincount(dark, minlength=256).astype(np.float64)
    levels = np.arange(256.0)
    top = max(1, dark.size // 1000)
    # mean of the ``top`` brightest dark-channel values, from the histogram
    above = np.cumsum(histogram[::-1])[::-1] - histogram  # count strictly brighter
    take = np.clip(top - above, 0.0, histogram)
    airlight = float(take @ levels) / top
    fog = float(histogram @ levels) / dark.size / airlight if airlight > 0 else 0.0
    return np.array(
        [
            float(std[0, 0]) / 255.0,
            float(lap_std[0, 0]) ** 2,
            fog,
            float(mean[0, 0]) / 255.0,
        ]
    )
