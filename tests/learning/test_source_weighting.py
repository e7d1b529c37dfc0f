"""benchmarks/source_weighting.py helpers: keyframe pairs and the oracle's covariances."""

from __future__ import annotations

import dataclasses

import torch

from benchmarks.source_weighting import in_outage, keyframes, with_error_scale
from msf_torch.frontend.config import config_for_sequence, load_config
from msf_torch.frontend.schedule import build_schedule
from msf_torch.learning.data import simulate_labelled_weather_run


def test_keyframes_pair_samples_stride_apart_and_scale_by_k_squared():
    """With stride 5 every fused pair spans 0.5 s (the sources run at 10 Hz) and no two
    pairs share a sample; the oracle multiplies each sample's covariance by k^2."""
    wet = simulate_labelled_weather_run(
        3, 24.0, gnss_outage_count=1, gnss_outage_duration_s=(5.0, 6.0)
    )
    seq = keyframes(wet.sequence, 5)
    cfg = dataclasses.replace(
        config_for_sequence(load_config(None), seq.meta, set()), pose_source_max_gap_s=0.75
    )
    sched = build_schedule(seq, cfg)
    dt = sched.source_dt[sched.source_mask]
    assert dt.numel() > 0
    torch.testing.assert_close(dt, torch.full_like(dt, 0.5), rtol=0.0, atol=1e-9)
    for name, stream in seq.pose_sources.items():
        kept = stream.t[stream.mask]
        steps = torch.round(kept * 10.0).long()
        assert bool((steps % 5 == 0).all()), name
    k = {n: torch.from_numpy(wet.source_truth[n].error_scale) for n in ("vo", "lidar")}
    scaled = with_error_scale(seq, k)
    lidar = seq.pose_sources["lidar"]
    ratio = scaled.pose_sources["lidar"].covariance[0, :, 0, 0] / lidar.covariance[0, :, 0, 0]
    keep = lidar.covariance[0, :, 0, 0] > 0
    torch.testing.assert_close(ratio[keep], (k["lidar"] ** 2)[keep])
    outage = in_outage(seq, seq.gnss.t)
    assert not bool(outage.any())  # fixes lie outside the outages by construction
    grid = torch.arange(0.0, 24.0, 0.01, dtype=torch.float64)[None]
    assert 4.9 <= float(in_outage(seq, grid).sum()) * 0.01 <= 6.5  # the drawn 5-6 s outage
