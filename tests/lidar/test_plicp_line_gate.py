"""``fit_lines``' rms gate against a closed form: points on a straight wall at 1 cm spacing
with perpendicular offsets alternating ``+d, -d``. A full window of 21 neighbours
(``line_window = 10``) has ``sum j (-1)^j = 0`` about its centre, so the fitted direction
is the wall's and the fit's rms distance is the population deviation of the offsets,
``d sqrt(1 - 1/21^2)``. The gate keeps a line when that rms is at most ``line_max_rms_m``
(0.03 m): an rms of 0.0295 m passes (the sample deviation, 1.025 times larger, would not),
0.05 m does not (its variance, 0.0025 m^2, would pass a gate applied to the variance).
"""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.lidar.plicp import PlicpConfig, fit_lines


@pytest.mark.parametrize(("rms", "kept"), [(0.0295, True), (0.05, False)])
def test_line_rms_gate_by_hand(rms, kept):
    count = 61
    d = rms / math.sqrt(1.0 - 1.0 / 21**2)
    index = torch.arange(count, dtype=torch.float64)
    offset = d * (1.0 - 2.0 * (index % 2))
    points = torch.stack((2.0 + 0.01 * index, 1.0 + offset), -1)[None]
    valid = torch.ones(1, count, dtype=torch.bool)
    lines = fit_lines(points, valid, PlicpConfig())
    middle = slice(10, count - 10)  # full windows
    assert bool((lines.valid[0, middle] == kept).all())
    if kept:
        normal = lines.normal[0, middle]
        torch.testing.assert_close(normal[:, 0], torch.zeros(count - 20, dtype=torch.float64))
        torch.testing.assert_close(normal[:, 1].abs(), torch.ones(count - 20, dtype=torch.float64))
