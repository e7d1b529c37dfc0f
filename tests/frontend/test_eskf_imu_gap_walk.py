"""The front end over an IMU dropout: the held sample's error as a random walk per body axis
(``EskfConfig.imu_gap_gyro_rw_density``, ``imu_gap_accel_rw_density``).

References: the simulator's ground truth for a 10-s IMU dropout with wheels and GNSS running
(front-end ATE 4.5 m with the isotropic x100 alone, 0.39 m with the walk); the same filter
with the walk off, bit for bit, where no epoch holds a gap or every gap is blind.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from msf_torch.eval.metrics import ate
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run

NO_WALK = {"imu_gap_gyro_rw_density": [0.0] * 3, "imu_gap_accel_rw_density": [0.0] * 3}


def _dropout(seq, t0: float, t1: float):
    """``seq`` without the IMU samples strictly inside (t0, t1) s."""
    t = seq.imu.t[0]
    keep = (t <= t0) | (t >= t1)
    return dataclasses.replace(seq, imu=seq.imu.map(lambda x: x[:, keep]))


@pytest.fixture(scope="module")
def drive():
    """A 60-s simulated drive (seed 3) and its config."""
    seq = simulate_run(SimConfig(duration_s=60.0), seed=3).sequence
    return seq, config_for_sequence(load_config(), seq.meta, set())


def test_ten_second_imu_dropout_with_wheels_and_gnss_running(drive):
    seq, cfg = drive
    gap = _dropout(seq, 25.0, 35.0)
    with torch.no_grad():
        walk = run_eskf(gap, cfg)
        iso = run_eskf(gap, cfg.replace(**NO_WALK))
    rmse = {
        name: ate(r.trajectory(), seq.ground_truth, align="none", max_dt=0.02)["rmse"]
        for name, r in (("walk", walk), ("iso", iso))
    }
    # x100 alone: 4.5 m and two guard resets (the slip factors reject the wheels after the
    # gap); with the walk 0.39 m and none
    assert rmse["walk"] < 1.0 and rmse["iso"] > 3.0, rmse
    assert not bool(walk.divergence.any())


def test_runs_without_gaps_and_blind_gaps_are_unchanged(drive):
    seq, cfg = drive
    # every sensor silent for 8 s: one blind epoch, which keeps the isotropic model
    blind = dataclasses.replace(
        _dropout(seq, 20.0, 28.0),
        wheel=seq.wheel.map(lambda x: x[:, (seq.wheel.t[0] <= 20.0) | (seq.wheel.t[0] >= 28.0)]),
        gnss=seq.gnss.map(lambda x: x[:, (seq.gnss.t[0] <= 20.0) | (seq.gnss.t[0] >= 28.0)]),
    )
    for s in (seq, blind):
        with torch.no_grad():
            on, off = run_eskf(s, cfg), run_eskf(s, cfg.replace(**NO_WALK))
        for field in ("position", "rotation", "covariance"):
            assert torch.equal(getattr(on, field), getattr(off, field)), field
    assert bool(on.gap[0].any())


@pytest.mark.parametrize(
    "change",
    [
        {"imu_gap_gyro_rw_density": [0.1, 0.1]},
        {"imu_gap_accel_rw_density": [0.1, -0.1, 0.1]},
        {"imu_gap_walk_max_blind_s": 0.0},
    ],
)
def test_walk_keys_are_validated(change):
    key = next(iter(change))
    with pytest.raises(ValueError, match=key):
        EskfConfig(**change).validate()
