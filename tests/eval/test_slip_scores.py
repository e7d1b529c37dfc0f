"""``slip_scores`` against a hand count (it had no test of its own).

Epochs at t = 0, 1, ..., 19 s; labelled slip intervals A = [3, 6], B = [12, 13],
C = [16, 16.5] and a NaN row (ignored); tolerance 1 s, so the widened intervals are
[2, 7], [11, 14], [15, 17.5]. Flags at 4, 5, 7, 9, 10, 13, 19:

* positives (inside an interval): 3, 4, 5, 6, 12, 13, 16 -> 7; flagged among them: 4, 5, 13
  -> recall 3/7;
* flags inside a widened interval: 4, 5, 7, 13 -> precision 4/7; F1 = 2 (4/7)(3/7) / 1 =
  24/49;
* episodes found: A and B, not C -> 2/3;
* runs of flags: [4, 5], [7], [9, 10], [13], [19]; [9, 10] and the final [19] touch no
  widened interval -> 2 false episodes.
"""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.eval.slip import slip_scores


def test_slip_scores_by_hand():
    t = torch.arange(20, dtype=torch.float64)
    flagged = torch.zeros(20, dtype=torch.bool)
    flagged[[4, 5, 7, 9, 10, 13, 19]] = True
    intervals = torch.tensor(
        [[3.0, 6.0], [12.0, 13.0], [math.nan, math.nan], [16.0, 16.5]], dtype=torch.float64
    )
    scores = slip_scores(t, flagged, intervals, tolerance_s=1.0)
    assert scores["precision"] == pytest.approx(4 / 7, rel=1e-12)
    assert scores["recall"] == pytest.approx(3 / 7, rel=1e-12)
    assert scores["f1"] == pytest.approx(24 / 49, rel=1e-12)
    assert scores["episode_recall"] == pytest.approx(2 / 3, rel=1e-12)
    assert scores["false_episodes"] == 2
    assert scores["episodes"] == 3
