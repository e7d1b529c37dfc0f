"""Outage metrics on a path that turns, with fixes a quarter of the way between estimate
samples (the closed-form test drives straight, with fixes half-way, where a reversed
interpolation weight and the chord instead of the path length give the same numbers).

Estimate: ``p(t) = (t, 0, 0)`` at 1 Hz, so at a fix time ``k + 1/4`` it is ``(k + 1/4, 0,
0)``. Fixes: ``(1, 0, 0), (2, 0, 0), (2, 1, 0), (2, 2, 0)`` at ``1.25 .. 4.25`` s: errors
``1/4, 1/4, |(5/4, -1)|, |(9/4, -2)|``, distance travelled 3 m (the chord is sqrt(5) m).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks._common import trajectory_from
from msf_torch.eval.outage import outage_metrics
from msf_torch.types import GnssFixes


def test_outage_metrics_on_a_turning_path_by_hand():
    t = np.arange(0.0, 10.5, 1.0)
    estimate = trajectory_from(t, np.stack([t, 0.0 * t, 0.0 * t], axis=-1))
    t_fix = torch.tensor([1.25, 2.25, 3.25, 4.25], dtype=torch.float64)
    fixes = torch.tensor(
        [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 2.0, 0.0]], dtype=torch.float64
    )
    sigma = torch.full((1, 4, 3), float("nan"), dtype=torch.float64)
    withheld = GnssFixes(t_fix[None], fixes[None], sigma, torch.ones(1, 4, dtype=torch.bool))
    metrics = outage_metrics(estimate, withheld)
    errors = np.array([0.25, 0.25, math.hypot(1.25, 1.0), math.hypot(2.25, 2.0)])
    assert metrics["outage_distance_m"] == pytest.approx(3.0, rel=1e-12)
    assert metrics["outage_max_error_m"] == pytest.approx(errors.max(), rel=1e-12)
    assert metrics["outage_rmse_m"] == pytest.approx(math.sqrt((errors**2).mean()), rel=1e-12)
    assert metrics["outage_drift_pct"] == pytest.approx(100.0 * errors.max() / 3.0, rel=1e-12)
    assert metrics["outage_duration_s"] == pytest.approx(3.0, abs=1e-12)
