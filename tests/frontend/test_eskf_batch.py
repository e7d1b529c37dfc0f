"""A batch of sequences equals each sequence run alone (acceptance, 1e-9).

Three simulated runs of different durations and sensor sets: wheel + GNSS at 1 Hz; wheel
only (no GNSS); GNSS at 2 Hz without wheels (so NHC and ZUPT pseudo-measurements are
scheduled). Default configuration, gating and slip factor on, so every branch sees padding.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import SENSORS, run_eskf
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import batch_sequences

TOL = 1e-9


@pytest.fixture(scope="module")
def sequences():
    a = simulate_run(SimConfig(duration_s=8.0), seed=70).sequence
    b = simulate_run(SimConfig(duration_s=12.0), seed=71).sequence
    b = dataclasses.replace(b, gnss=None)
    c = simulate_run(SimConfig(duration_s=10.0, gnss_rate_hz=2.0), seed=72).sequence
    c = dataclasses.replace(c, wheel=None)
    return [a, b, c]


def _max_diffs(single, batch, b: int) -> dict[str, float]:
    n = single.t.shape[1]
    out = {}
    for name in ("position", "velocity", "rotation", "gyro_bias", "accel_bias", "covariance"):
        one = getattr(single, name)[0]
        many = getattr(batch, name)[b, :n]
        out[name] = float((one - many).abs().max())
    out["t"] = float((single.t[0] - batch.t[b, :n]).abs().max())
    return out


@pytest.mark.parametrize("cfg", [EskfConfig(), EskfConfig(gate_probability=1.0, nhc="on")])
def test_batched_equals_single(sequences, cfg):
    batch_res = run_eskf(batch_sequences(sequences), cfg)
    assert batch_res.position.shape[0] == 3
    for b, seq in enumerate(sequences):
        single = run_eskf(seq, cfg)
        n = single.t.shape[1]
        # real epochs line up, the rest of the batch row is padding
        assert bool(batch_res.mask[b, :n].all()) and not bool(batch_res.mask[b, n:].any())
        diffs = _max_diffs(single, batch_res, b)
        assert all(v < TOL for v in diffs.values()), (seq.names[0], diffs)
        for key in SENSORS:
            if key in single.present:
                assert torch.equal(single.present[key][0], batch_res.present[key][b, :n]), key
                assert torch.equal(single.accepted[key][0], batch_res.accepted[key][b, :n]), key
        torch.testing.assert_close(
            single.slip_factor[0], batch_res.slip_factor[b, :n], rtol=0, atol=TOL
        )
        assert torch.isfinite(single.covariance).all()
    # the runs exercise what they should
    assert bool(batch_res.present["gnss"][1].any()) is False
    assert bool(batch_res.present["wheel"][2].any()) is False
    if cfg.nhc == "auto":
        assert bool(batch_res.present["nhc"][2].any())
        assert not bool(batch_res.present["nhc"][0].any())


def test_batch_order_does_not_matter(sequences):
    cfg = EskfConfig()
    forward = run_eskf(batch_sequences(sequences), cfg)
    backward = run_eskf(batch_sequences(sequences[::-1]), cfg)
    for b in range(3):
        n = int(forward.mask[b].sum())
        torch.testing.assert_close(
            forward.position[b, :n], backward.position[2 - b, :n], rtol=0, atol=TOL
        )
        torch.testing.assert_close(
            forward.covariance[b, :n], backward.covariance[2 - b, :n], rtol=0, atol=TOL
        )
