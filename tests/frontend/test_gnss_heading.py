"""Dual-antenna GNSS heading in the front end on simulated runs
(``SimConfig(gnss_heading=True)``): the yaw it pins (initial and filtered), the filter's
consistency with it, the wrap at north, the gate, the initial yaw from a heading
(closed form), a batch with different heading counts against single runs, and
``EskfStream`` pieces against the run in one piece.

The residual's Jacobian is checked in ``tests/sensors/test_sensor_jacobians.py``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from error_state_checks import navigation_errors, nees_inside_fraction

from msf_torch import batch_sequences, load_sequence_config
from msf_torch.frontend.config import EskfConfig, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import antenna_heading_yaw, initial_state
from msf_torch.frontend.stream import EskfStream, concat_results, time_slice
from msf_torch.geometry import so3
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import GnssHeading

SEEDS = range(210, 216)


@pytest.fixture(scope="module")
def runs():
    return [simulate_run(SimConfig(duration_s=40.0, gnss_heading=True), seed=s) for s in SEEDS]


def _run(seqs, cfg=None):
    cfg = cfg or load_sequence_config(seqs[0].meta)
    with torch.no_grad():
        return run_eskf(batch_sequences(seqs), cfg)


def test_heading_pins_the_yaw_and_the_filter_stays_consistent(runs):
    plain = _run([dataclasses.replace(r.sequence, gnss_heading=None) for r in runs])
    aided = _run([r.sequence for r in runs])
    total = sum(r.sequence.gnss_heading.length for r in runs)
    assert int(aided.accepted["gnss_heading"].sum()) >= 0.95 * total
    yaw = {}
    for name, result in (("plain", plain), ("aided", aided)):
        values = []
        for b in range(len(runs)):
            _, error, _ = navigation_errors(result, runs, b)
            values.append(float(error[:, 8].abs().median()))
        yaw[name] = float(np.median(values))
    # a 0.005-rad heading every second against the GNSS track's and the NHC's yaw
    assert yaw["aided"] < 0.006 and yaw["aided"] < 0.3 * yaw["plain"], yaw
    assert nees_inside_fraction(aided, runs, after_s=5.0) >= 0.9
    nis = aided.nis["gnss_heading"][aided.accepted["gnss_heading"]]
    assert 0.6 < float(nis.mean()) < 1.6  # one row: mean NIS 1


def test_headings_a_turn_apart_give_the_same_estimate(runs):
    """``h`` and ``h + 2 pi`` are one direction: adding whole turns to the headings (and
    crossing north) changes nothing; without the wrap the residuals would be ~6.3 rad."""
    seq = runs[0].sequence
    heading = seq.gnss_heading
    turns = torch.tensor([-2.0, 1.0, 0.0, 3.0], dtype=heading.heading.dtype)
    shifted = (
        heading.heading
        + 2 * math.pi * turns.repeat(heading.length // 4 + 1)[None, : heading.length]
    )
    moved = dataclasses.replace(seq, gnss_heading=dataclasses.replace(heading, heading=shifted))
    first, second = _run([seq]), _run([moved])
    torch.testing.assert_close(second.position, first.position, rtol=0, atol=1e-9)
    torch.testing.assert_close(second.rotation, first.rotation, rtol=0, atol=1e-9)


def test_a_wrong_heading_is_gated_and_the_baseline_direction_counts(runs):
    seq = runs[1].sequence
    heading = seq.gnss_heading
    values = heading.heading.clone()
    values[0, 20] += 0.5  # 29 degrees off, 100 sigma
    bad = dataclasses.replace(seq, gnss_heading=dataclasses.replace(heading, heading=values))
    result = _run([bad])
    at = torch.isclose(result.t[0], heading.t[0, 20])
    assert bool(result.present["gnss_heading"][0, at].all())
    assert not bool(result.accepted["gnss_heading"][0, at].any())
    # the same headings read as from antennas mounted left-right (baseline +y) put the yaw
    # 90 degrees off the GNSS track's: the initialisation says so
    cfg = load_sequence_config(seq.meta).replace(gnss_heading_baseline_m=[0.0, 1.0, 0.0])
    with pytest.warns(UserWarning, match=r"-(8[5-9]|9[0-5])\.\d degrees from the GNSS track's"):
        initial_state(seq, cfg)


def _level_drive(yaw0: float, rate: float, roll: float):
    """A vehicle rolled by ``roll`` turning about its own z at ``rate`` from yaw ``yaw0``:
    IMU at 100 Hz, the exact headings of a baseline (0.3, 0.9, 0.2) m from t = 2 s."""
    imu_t = np.arange(0.0, 5.0, 0.01)
    gyro = np.tile([0.0, 0.0, rate], (imu_t.size, 1))
    baseline = np.array([0.3, 0.9, 0.2])
    t_h = np.arange(2.0, 5.0, 0.5)
    tilt = so3.exp(torch.tensor([roll, 0.0, 0.0], dtype=torch.float64)).numpy()
    headings = []
    for t in t_h:
        yaw = so3.exp(torch.tensor([0.0, 0.0, yaw0], dtype=torch.float64)).numpy()
        spin = so3.exp(torch.tensor([0.0, 0.0, rate * t], dtype=torch.float64)).numpy()
        world = yaw @ tilt @ spin @ baseline
        headings.append(math.atan2(world[0], world[1]) % (2 * math.pi))
    heading = {"t": t_h, "heading": np.array(headings), "sigma": np.full(t_h.size, np.nan)}
    return heading, imu_t, gyro, tilt, baseline


def test_initial_yaw_is_the_heading_carried_back_by_the_gyro():
    """Closed form: the yaw that turns the tilted baseline to the first heading, minus the
    gyro's turn since the first IMU sample (no motion needed), and its variance: the
    heading's (config default for a NaN sigma) plus the bias prior and angle random walk
    over the 2 s carried back."""
    heading, imu_t, gyro, tilt, baseline = _level_drive(2.8, 0.0, 0.0)
    cfg = EskfConfig(gnss_heading_baseline_m=list(baseline))
    yaw, variance = antenna_heading_yaw(heading, imu_t, gyro, tilt, cfg)
    assert yaw == pytest.approx(2.8, abs=1e-12)
    expected = (
        cfg.gnss_heading_sigma_rad**2
        + (cfg.init_gyro_bias_sigma_radps * 2.0) ** 2
        + cfg.gyro_noise_density**2 * 2.0
    )
    assert variance == pytest.approx(expected, rel=1e-12)
    # a turning vehicle: the heading at 2 s is 0.6 rad later than the start
    heading, imu_t, gyro, tilt, baseline = _level_drive(-1.1, 0.3, 0.0)
    yaw, _ = antenna_heading_yaw(heading, imu_t, gyro, tilt, cfg)
    assert yaw == pytest.approx(-1.1, abs=1e-9)
    # a first heading a driver marks invalid (sigma 31.6 rad, the ublox ROS driver's
    # variance 1000) is passed over for the next valid one
    heading, imu_t, gyro, tilt, baseline = _level_drive(0.4, 0.3, 0.0)
    heading["sigma"][0] = math.sqrt(1000.0)
    heading["heading"][0] += 1.0
    yaw, variance = antenna_heading_yaw(heading, imu_t, gyro, tilt, cfg)
    assert yaw == pytest.approx(0.4, abs=1e-9) and variance < 1e-3
    # on a level vehicle, a baseline pointing straight up has no heading
    up = EskfConfig(gnss_heading_baseline_m=[0.0, 0.0, 1.0])
    assert antenna_heading_yaw(heading, imu_t, gyro, np.eye(3), up) is None
    # ... and a config saying so is refused when it is loaded
    with pytest.raises(ValueError, match="gnss_heading_baseline_m.*horizontal part"):
        load_config(gnss_heading_baseline_m=[0.0, 0.0, 1.0])


def test_heading_gives_the_initial_yaw_before_any_motion(runs):
    """Without wheels and with the first fixes withheld, the track gives no heading for
    seconds; the first dual-antenna heading sets the yaw to within its sigma."""
    errors, ratios = [], []
    for run in runs:
        seq = dataclasses.replace(run.sequence, wheel=None)
        cfg = load_sequence_config(seq.meta)
        state, cov = initial_state(seq, cfg)
        yaw_error = float(so3.log(run.truth.rotation[0, 0].mT @ state.rotation[0])[2])
        errors.append(abs(yaw_error))
        ratios.append(yaw_error / float(cov[0, 8, 8].sqrt()))
        assert float(cov[0, 8, 8].sqrt()) < 0.02
    assert max(errors) < 0.03 and max(abs(r) for r in ratios) < 3.0


def test_guard_drops_nonfinite_headings_and_fills_missing_sigmas(runs):
    seq = runs[2].sequence
    heading = seq.gnss_heading
    values, sigma = heading.heading.clone(), heading.sigma.clone()
    values[0, 5] = float("nan")
    sigma[0, 6:] = float("nan")  # default 0.01 rad
    broken = dataclasses.replace(
        seq, gnss_heading=GnssHeading(heading.t, values, sigma, heading.mask)
    )
    result = _run([broken])
    assert int(result.dropped_samples["gnss_heading"][0]) == 1
    # the heading at t = 0 sets the initial yaw; the filter's epochs start after it
    assert int(result.present["gnss_heading"].sum()) == heading.length - 2
    assert torch.isfinite(result.position).all()


@pytest.fixture(scope="module")
def mixed_batch():
    """Three runs with different heading counts: wheels and 1-Hz headings with three of
    them removed; no wheels and 2-Hz headings; no headings at all."""
    a = simulate_run(SimConfig(duration_s=8.0, gnss_heading=True), seed=70).sequence
    kept = torch.ones(a.gnss_heading.length, dtype=torch.bool)
    kept[2:5] = False
    a = dataclasses.replace(a, gnss_heading=a.gnss_heading.map(lambda x: x[:, kept]))
    b = simulate_run(SimConfig(duration_s=12.0, gnss_heading=True, gnss_rate_hz=2.0), seed=71)
    b = dataclasses.replace(b.sequence, wheel=None)
    c = simulate_run(SimConfig(duration_s=10.0), seed=72).sequence
    return [a, b, c]


@pytest.mark.parametrize(
    "cfg",
    [
        EskfConfig(),
        EskfConfig(calibrate_gnss_heading_offset=True, adaptive_noise_sensors=["gnss_heading"]),
    ],
)
def test_a_batch_with_different_heading_counts_equals_single_runs(mixed_batch, cfg):
    """B = 3 (padding in the heading block of two runs) equals each run alone to 1e-9,
    the heading block's presence and gate decisions included."""
    with torch.no_grad():
        batch = run_eskf(batch_sequences(mixed_batch), cfg)
        singles = [run_eskf(seq, cfg) for seq in mixed_batch]
    counts = [int(batch.present["gnss_heading"][b].sum()) for b in range(3)]
    assert counts[0] > 0 and counts[1] > counts[0] and counts[2] == 0
    for b, single in enumerate(singles):
        n = single.t.shape[1]
        for name in ("position", "velocity", "rotation", "gyro_bias", "covariance"):
            difference = (getattr(single, name)[0] - getattr(batch, name)[b, :n]).abs().max()
            assert float(difference) < 1e-9, (b, name, float(difference))
        if counts[b]:
            for table in ("present", "accepted"):
                one = getattr(single, table)["gnss_heading"][0]
                assert torch.equal(one, getattr(batch, table)["gnss_heading"][b, :n]), table


HELD = {  # biases held: the pieces then equal the one run to round-off (test_stream.py)
    "init_gyro_bias_sigma_radps": 0.0,
    "init_accel_bias_sigma_mps2": 0.0,
    "gyro_bias_rw_density": 0.0,
    "accel_bias_rw_density": 0.0,
}


@pytest.mark.parametrize("ahead_s", [0.0, 0.3])
def test_pieces_fuse_each_heading_once_as_the_run_in_one_piece(ahead_s):
    """``EskfStream`` pieces ending on heading times (7 s, 11 s) and between them, the
    headings (and other measurements) handed over with the piece or ``ahead_s`` before
    the IMU reaches them: every heading after the first IMU sample is fused exactly once,
    the gate decides as in one run, and the states agree to 1e-9."""
    sim = SimConfig(duration_s=20.0, gnss_heading=True, gnss_velocity=True, gnss_outage_count=0)
    seq = simulate_run(sim, seed=5).sequence
    cfg = load_sequence_config(seq.meta).replace(**HELD)
    bounds = [0.0, 2.37, 7.0, 7.004, 11.0, 16.5, 20.01]
    pieces = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        measured = time_slice(seq, a + ahead_s if a > 0 else 0.0, b + ahead_s)
        pieces.append(dataclasses.replace(measured, imu=time_slice(seq, a, b).imu))
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        stream = EskfStream(cfg, initial=initial_state(seq, cfg))
        for piece in pieces:
            stream.push(piece)
        joined = concat_results(stream.results)
    assert stream.late_samples == {}
    fused = joined.t[0, joined.present["gnss_heading"][0]]
    later = seq.gnss_heading.t[0][seq.gnss_heading.t[0] > 0.0]
    assert fused.tolist() == later.tolist()  # each once, none lost at a boundary
    assert int(joined.accepted["gnss_heading"].sum()) == int(whole.accepted["gnss_heading"].sum())
    real = whole.t[0, whole.mask[0]]
    index = torch.searchsorted(joined.t[0], real)
    assert torch.equal(joined.t[0, index], real)
    for name in ("position", "rotation", "covariance"):
        difference = getattr(joined, name)[0, index] - getattr(whole, name)[0, whole.mask[0]]
        assert float(difference.abs().max()) < 1e-9, (name, float(difference.abs().max()))


def test_a_burst_of_wrong_headings_beside_passing_fixes_stays_out():
    """Five headings 0.5 rad off in a row (a wrong moving-baseline solution) while the fixes
    pass their gate: the gate stays shut through the streak (as for GNSS velocities), so
    the yaw stays where the clean run has it. Measured before the rule: the fourth was let
    in by the re-opening, yaw error 0.14 rad (clean 0.005), position error 1.46 m (0.74)."""
    run = simulate_run(SimConfig(duration_s=40.0, gnss_heading=True, gnss_outage_count=0), seed=210)
    seq = run.sequence
    heading = seq.gnss_heading
    values = heading.heading.clone()
    values[0, 20:25] += 0.5
    bad = dataclasses.replace(seq, gnss_heading=dataclasses.replace(heading, heading=values))
    cfg = load_sequence_config(seq.meta)
    with torch.no_grad():
        clean, result = run_eskf(seq, cfg), run_eskf(bad, cfg)
    at = (result.t[0] >= 19.5) & (result.t[0] <= 24.5) & result.present["gnss_heading"][0]
    assert int(at.sum()) == 5 and not bool(result.accepted["gnss_heading"][0, at].any())
    truth = run.truth.rotation[0, torch.searchsorted(run.truth.t[0], result.t[0])]
    yaw = so3.log(truth.mT @ result.rotation[0])[:, 2].abs().max()
    yaw_clean = so3.log(truth.mT @ clean.rotation[0])[:, 2].abs().max()
    assert float(yaw) < 1.5 * float(yaw_clean) + 1e-3, (float(yaw), float(yaw_clean))
