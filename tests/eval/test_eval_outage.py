"""GNSS outage split and drift metrics against closed forms and the bundled sample."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks._common import trajectory_from
from msf_torch.eval.outage import outage_metrics, split_gnss_outage
from msf_torch.io import load_sequence
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import GnssFixes, Trajectory

SAMPLE = Path(__file__).resolve().parents[2] / "datasets" / "sample_slip.npz"


def _line(speed: float, duration: float, rate: float = 100.0) -> Trajectory:
    """Straight-line estimate p(t) = (speed t, 0, 0), identity attitude, B = 1."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    return trajectory_from(t, np.stack([speed * t, 0.0 * t, 0.0 * t], axis=-1))


def _fixes(t: torch.Tensor, position: torch.Tensor) -> GnssFixes:
    n = t.numel()
    sigma = torch.full((1, n, 3), float("nan"), dtype=torch.float64)
    return GnssFixes(t[None], position[None], sigma, torch.ones(1, n, dtype=torch.bool))


def test_outage_metrics_closed_form():
    speed, step = 2.0, 0.1
    estimate = _line(speed, 12.0)
    k = torch.arange(11, dtype=torch.float64)
    t_fix = k + 0.005  # between estimate samples: exercises the linear interpolation
    truth = torch.stack([speed * t_fix, step * k, torch.zeros_like(k)], dim=-1)
    metrics = outage_metrics(estimate, _fixes(t_fix, truth))
    errors = step * k
    distance = 10 * math.hypot(speed, step)
    assert metrics["outage_fixes"] == 11
    assert metrics["outage_max_error_m"] == pytest.approx(1.0, abs=1e-12)
    assert metrics["outage_rmse_m"] == pytest.approx(float(errors.pow(2).mean().sqrt()), abs=1e-12)
    assert metrics["outage_distance_m"] == pytest.approx(distance, rel=1e-12)
    assert metrics["outage_drift_pct"] == pytest.approx(100.0 / distance, rel=1e-12)
    assert metrics["outage_duration_s"] == pytest.approx(10.0, abs=1e-12)


def test_outage_metrics_rejects_empty_fixes():
    empty = _fixes(torch.zeros(0, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="no withheld GNSS fix"):
        outage_metrics(_line(1.0, 5.0), empty)


def test_split_gnss_outage_partitions_the_fixes():
    seq = load_sequence(SAMPLE)
    t0 = seq.start_time[0]
    rel = seq.gnss.t[0, seq.gnss.mask[0]] - t0
    start, end = float(rel[-20]), float(rel[-11])  # ten fixes, the window's ends on fixes
    kept, withheld = split_gnss_outage(seq, start, end)
    rel_withheld = withheld.t[0] - t0
    rel_kept = kept.gnss.t[0, kept.gnss.mask[0]] - t0
    assert int(withheld.mask.sum()) == 10
    assert bool(((rel_withheld >= start) & (rel_withheld <= end)).all())
    assert not bool(((rel_kept >= start) & (rel_kept <= end)).any())
    assert int(withheld.mask.sum()) + int(kept.gnss.mask.sum()) == int(seq.gnss.mask.sum())
    assert kept.gnss_velocity is None


def test_split_gnss_outage_withholds_the_velocities_and_headings_too():
    seq = simulate_run(
        SimConfig(duration_s=30.0, gnss_velocity=True, gnss_heading=True), seed=4
    ).sequence
    kept, withheld = split_gnss_outage(seq, 10.0, 19.5)
    for name in ("gnss_velocity", "gnss_heading"):
        rel = getattr(kept, name).t[0] - seq.start_time[0]
        assert not bool(((rel >= 10.0) & (rel <= 19.5)).any())
        assert getattr(kept, name).length == getattr(seq, name).length - 10 == 21
    assert int(withheld.mask.sum()) == 10


def test_split_gnss_outage_needs_two_fixes():
    seq = load_sequence(SAMPLE)
    rel = seq.gnss.t[0, seq.gnss.mask[0]] - seq.start_time[0]
    first_gap = float(rel[1] - rel[0])
    one_fix = (float(rel[0]) - 0.25 * first_gap, float(rel[0]) + 0.25 * first_gap)
    with pytest.raises(ValueError, match="holds 1 GNSS fix"):
        split_gnss_outage(seq, *one_fix)
    with pytest.raises(ValueError, match="end > start"):
        split_gnss_outage(seq, 30.0, 20.0)
