"""Dual-antenna GNSS headings in the smoothers (``SmootherConfig.gnss_heading``): a factor at
every keyframe with a heading (keyframes are forced there), the front end's residual
(``backend.factors.GnssHeadingFactor``, Jacobians in ``test_backend_factors.py``).

Reference: the simulated truth of 60-s IMU + GNSS runs (fixes and headings at 1 Hz, a 15-s
outage), no wheels, full smoother with and without the heading factors (the front end
fuses the headings in both).
"""

from __future__ import annotations

import dataclasses

import torch

from msf_torch import load_sequence_config
from msf_torch.backend import window as W
from msf_torch.eval.metrics import ate
from msf_torch.frontend.eskf import run_eskf
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.learning.module import truth_at
from msf_torch.sim import SimConfig, simulate_run


def test_headings_pin_the_smoothed_yaw():
    sim = SimConfig(
        duration_s=60.0, gnss_heading=True, slip_episodes=0, gnss_outages_s=((30.0, 45.0),)
    )
    for seed in (1, 3):
        run = simulate_run(sim, seed=seed)
        seq = dataclasses.replace(run.sequence, wheel=None)
        cfg = load_sequence_config(seq.meta)
        yaw, rmse = {}, {}
        with torch.no_grad():
            front = run_eskf(seq, cfg)
            for with_heading in (True, False):
                smoother = W.SmootherConfig(covariance=False, gnss_heading=with_heading)
                graph = W.build_graph(seq, front, cfg, smoother)
                # every heading (45: 1 Hz from t = 0 but in the outage) at a keyframe
                assert graph.gnss_heading_index.numel() == 45 * with_heading
                out = W.smooth(seq, front, cfg, smoother, "full")
                _, truth_rotation = truth_at(seq.ground_truth, out.output.t)
                rotation = quat_to_matrix(out.output.quaternion)
                yaw[with_heading] = float(
                    so3.log(truth_rotation.mT @ rotation)[..., 2].abs().median()
                )
                rmse[with_heading] = ate(out.output, seq.ground_truth, align="none", max_dt=0.02)[
                    "rmse"
                ]
        # measured: median yaw error 0.0009 / 0.0006 rad with, 0.0058 / 0.0124 without;
        # ATE 0.212 / 0.201 m with, 0.238 / 0.210 m without
        assert yaw[True] < 0.3 * yaw[False], (seed, yaw)
        assert rmse[True] <= rmse[False], (seed, rmse)


def test_a_nonfinite_measurement_is_left_out_as_in_the_front_end():
    """A NaN heading or fix is dropped by the front end's input rule
    (``frontend.guard.sanitize_sequence``); the smoothers read the same cleaned streams. They
    read the raw ones: a NaN cost, LM running to its limit without converging, no error."""
    seq = simulate_run(
        SimConfig(duration_s=20.0, gnss_heading=True, gnss_outage_count=0), seed=5
    ).sequence
    heading = seq.gnss_heading.heading.clone()
    heading[0, 7] = float("nan")
    position = seq.gnss.position.clone()
    position[0, 9, 0] = float("nan")
    bad = dataclasses.replace(
        seq,
        gnss_heading=dataclasses.replace(seq.gnss_heading, heading=heading),
        gnss=dataclasses.replace(seq.gnss, position=position),
    )
    cfg = load_sequence_config(bad.meta)
    with torch.no_grad():
        front = run_eskf(bad, cfg)
        out = W.smooth(bad, front, cfg, W.SmootherConfig(covariance=False), "full")
        graph = W.build_graph(bad, front, cfg, W.SmootherConfig(covariance=False))
    assert graph.gnss_heading_index.numel() == seq.gnss_heading.length - 1
    assert all(r.status == ["converged"] for r in out.lm)
    assert bool(torch.isfinite(out.output.position).all()) and float(out.cost) < 1e3
