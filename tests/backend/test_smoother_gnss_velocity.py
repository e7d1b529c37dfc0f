"""GNSS velocities in the smoothers (``SmootherConfig.gnss_velocity``): a factor at every
keyframe with a velocity (keyframes are forced there), the front end's residual
(``backend.factors.GnssVelocityFactor``, Jacobians in ``test_backend_factors.py``).

Reference: the simulated truth of three 60-s IMU + GNSS runs (fixes and velocities at 1 Hz,
a 15-s outage), no wheels, full smoother with and without the velocities.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from msf_torch import load_sequence_config
from msf_torch.backend import window as W
from msf_torch.eval.metrics import ate
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run


def test_velocities_lower_the_full_smoother_error():
    sim = SimConfig(
        duration_s=60.0, gnss_velocity=True, slip_episodes=0, gnss_outages_s=((30.0, 45.0),)
    )
    errors = {True: [], False: []}
    for seed in (1, 2, 3):
        run = simulate_run(sim, seed=seed)
        seq = dataclasses.replace(run.sequence, wheel=None)
        cfg = load_sequence_config(seq.meta)
        with torch.no_grad():
            front = run_eskf(seq, cfg)
            for with_velocity in (True, False):
                smoother = W.SmootherConfig(covariance=False, gnss_velocity=with_velocity)
                graph = W.build_graph(seq, front, cfg, smoother)
                # every velocity (45: 1 Hz from t = 0 but in the outage) at a keyframe
                expected = seq.gnss_velocity.length if with_velocity else 0
                assert graph.gnss_velocity_index.numel() == expected == 45 * with_velocity
                out = W.smooth(seq, front, cfg, smoother, "full")
                score = ate(out.output, seq.ground_truth, align="none", max_dt=0.02)
                errors[with_velocity].append(score["rmse"])
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    # measured: 0.172 m with, 0.225 m without
    assert rms[True] < 0.85 * rms[False], errors
