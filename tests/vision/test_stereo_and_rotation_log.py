"""Two numpy helpers of ``vision.geometry`` against independent forms.

* ``triangulate_stereo`` with ``fx != fy`` (the rendered runs use square pixels, where
  the two focal lengths are interchangeable): points projected into a rectified pair by
  hand come back exactly; a zero or negative disparity is refused.
* ``rotation_log`` against scipy's ``Rotation.as_rotvec`` from 1e-7 rad to just below pi
  (its callers gate loop closures on its angle).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from msf_torch.vision.geometry import rotation_log, triangulate_stereo


def test_triangulate_stereo_recovers_points_with_unequal_focal_lengths():
    fx, fy, cx, cy, baseline = 720.0, 650.0, 610.0, 180.0, 0.54
    camera = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    points = np.array([[1.5, -0.8, 6.0], [-2.0, 0.4, 12.0], [0.3, 1.1, 3.5]])
    x, y, z = points.T
    left = np.stack((fx * x / z + cx, fy * y / z + cy), -1)
    right = np.stack((fx * (x - baseline) / z + cx, fy * y / z + cy), -1)
    np.testing.assert_allclose(
        triangulate_stereo(left, right, camera, baseline), points, rtol=1e-12, atol=1e-12
    )


def test_triangulate_stereo_refuses_non_positive_disparity():
    """Zero disparity (a point at infinity) or a negative one (behind the rig): a ValueError
    naming the row (the previous code returned inf and a negative depth silently)."""
    camera = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    left = np.array([[330.0, 200.0], [300.0, 210.0], [310.0, 220.0]])
    for row, shift in ((1, 0.0), (2, -2.5)):
        right = left - [8.0, 0.0]
        right[row, 0] = left[row, 0] - shift
        with pytest.raises(ValueError, match=f"row {row} has {shift}"):
            triangulate_stereo(left, right, camera, 0.12)


def test_rotation_log_matches_scipy():
    rng = np.random.default_rng(4)
    axes = rng.standard_normal((6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([1e-7, 1e-3, 0.4, 1.5, 2.5, 3.1])
    for axis, angle in zip(axes, angles, strict=True):
        rotvec = angle * axis
        matrix = Rotation.from_rotvec(rotvec).as_matrix()
        np.testing.assert_allclose(rotation_log(matrix), rotvec, rtol=1e-9, atol=1e-15)
