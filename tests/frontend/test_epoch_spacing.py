"""Epochs come at least every ``max_epoch_s`` where no measurement ends one: an IMU + GNSS
run with the NHC off has trajectory samples, and propagation steps, through a GNSS outage,
with the uncertainty growing there (before, its only epochs were the fixes, and the output
crossed a 15-s outage on a chord between them)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from msf_torch import load_sequence_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run


def test_epochs_fill_an_outage_without_pseudo_measurements():
    outage = (15.0, 30.0)
    sim = SimConfig(duration_s=40.0, slip_episodes=0, gnss_outages_s=(outage,))
    run = simulate_run(sim, seed=8)
    seq = dataclasses.replace(run.sequence, wheel=None)
    cfg = load_sequence_config(seq.meta).replace(nhc="off")
    with torch.no_grad():
        filled = run_eskf(seq, cfg)
        sparse = run_eskf(seq, cfg.replace(max_epoch_s=1e9))
    real = filled.mask[0]
    t = filled.t[0, real].numpy()
    assert np.diff(t).max() <= 0.5 + 1e-9
    inside = (t > outage[0] + 0.5) & (t < outage[1] - 0.5)
    assert inside.sum() >= 25  # every 0.5 s, no update there
    assert not bool(filled.present["gnss"][0, real][torch.from_numpy(inside)].any())
    sparse_t = sparse.t[0, sparse.mask[0]].numpy()
    assert not ((sparse_t > outage[0] + 1.0) & (sparse_t < outage[1] - 1.0)).any()
    # the position sigma grows through the outage (IMU alone)
    sigma = torch.diagonal(filled.covariance[0, real, :3, :3], dim1=-2, dim2=-1).sum(-1).sqrt()
    inside_sigma = sigma[torch.from_numpy(inside)].numpy()
    assert bool((np.diff(inside_sigma) > 0).all()) and inside_sigma[-1] > 3 * inside_sigma[0]
