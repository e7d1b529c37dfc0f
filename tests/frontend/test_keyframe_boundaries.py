"""Keyframe thresholds are inclusive: the next keyframe is the first epoch with
``t_j - t_i >= max_interval_s`` or a path ``>= max_distance_m`` (the docstring's rule and
example). The other keyframe tests use thresholds between epochs (0.99 s, 0.59 m), where
``>=`` and ``>`` select the same epochs; here the thresholds fall exactly on epochs (binary
times and steps, so the sums are exact).
"""

from __future__ import annotations

import math

import torch

from msf_torch.frontend.keyframes import KeyframeConfig, select_keyframes

DTYPE = torch.float64


def test_docstring_example_keeps_every_second_epoch():
    t = torch.arange(5.0, dtype=DTYPE)[None]
    pos = torch.zeros(1, 5, 3, dtype=DTYPE)
    rot = torch.eye(3, dtype=DTYPE).expand(1, 5, 3, 3)
    mask = torch.ones(1, 5, dtype=torch.bool)
    keyframes = select_keyframes(t, pos, rot, mask, KeyframeConfig(max_interval_s=2.0))
    assert keyframes.index.tolist() == [[0, 2, 4]]


def test_time_and_distance_thresholds_met_exactly_select_that_epoch():
    count = 41
    t = torch.arange(count, dtype=DTYPE)[None] * 0.125
    eye = torch.eye(3, dtype=DTYPE).expand(1, count, 3, 3)
    mask = torch.ones(1, count, dtype=torch.bool)
    still = torch.zeros(1, count, 3, dtype=DTYPE)
    by_time = select_keyframes(t, still, eye, mask, KeyframeConfig(1.0, math.inf, math.inf))
    assert by_time.index[0].tolist() == list(range(0, count, 8))
    moving = torch.zeros(1, count, 3, dtype=DTYPE)
    moving[..., 1] = t  # 0.125 m per epoch
    by_path = select_keyframes(t, moving, eye, mask, KeyframeConfig(math.inf, 0.5, math.inf))
    assert by_path.index[0].tolist() == list(range(0, count, 4))
