"""A run fed to ``frontend.stream.EskfStream`` piece by piece equals the run filtered in one
piece (``run_eskf``): at every epoch of the one run, to round-off with the biases held, to
second order otherwise (the preintegration is linearised at each piece's starting bias).

The run: 20 s, wheels with a slip episode, GNSS fixes and velocities, VO and LiDAR under
a random weather schedule, the source-fault detector on. Pieces end at uneven times, one
0.05 s long; measurements may come with the piece before the IMU reaches them (held back),
or late (skipped, counted, warned).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.stream import EskfStream, concat_results, time_slice
from msf_torch.sim import SimConfig, fill_imu_stretch, simulate_run
from msf_torch.sim.weather import WeatherSchedule, apply_weather

BOUNDS = [0.0, 2.37, 4.9, 7.1, 11.3, 11.35, 16.0, 20.01]
HELD = {
    "init_gyro_bias_sigma_radps": 0.0,
    "init_accel_bias_sigma_mps2": 0.0,
    "gyro_bias_rw_density": 0.0,
    "accel_bias_rw_density": 0.0,
}


@pytest.fixture(scope="module")
def run():
    sim = SimConfig(duration_s=20.0, gnss_velocity=True, slip_episodes=1, gnss_outage_count=0)
    wet = apply_weather(simulate_run(sim, seed=5), WeatherSchedule.random(20.0, seed=2), seed=3)
    seq = wet.sequence
    cfg = config_for_sequence(EskfConfig(source_fault_detection=True), seq.meta, set())
    return seq, cfg


def _streamed(seq, cfg, pieces):
    stream = EskfStream(cfg, initial=initial_state(seq, cfg))
    for piece in pieces:
        stream.push(piece)
    return stream, concat_results(stream.results)


def _largest_difference(joined, whole) -> dict[str, float]:
    """At the one run's epochs (each also an epoch of the pieces)."""
    real = whole.t[0, whole.mask[0]]
    index = torch.searchsorted(joined.t[0], real)
    assert torch.equal(joined.t[0, index], real)
    return {
        name: float(
            (getattr(joined, name)[0, index] - getattr(whole, name)[0, whole.mask[0]]).abs().max()
        )
        for name in ("position", "velocity", "covariance")
    }


@pytest.mark.parametrize("held", [True, False])
def test_pieces_equal_the_run_in_one_piece(run, held):
    seq, cfg = run
    cfg = cfg.replace(**HELD) if held else cfg
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = [time_slice(seq, a, b) for a, b in zip(BOUNDS[:-1], BOUNDS[1:], strict=True)]
        stream, joined = _streamed(seq, cfg, pieces)
    assert {"pose:vo", "pose:lidar", "gnss_velocity"} <= set(joined.present)
    for key in ("wheel", "gnss", "gnss_velocity", "pose:vo", "pose:lidar"):
        assert int(joined.accepted[key].sum()) == int(whole.accepted[key].sum()), key
    difference = _largest_difference(joined, whole)
    # measured: 7e-13 m held; 1.2e-5 m with the biases estimated
    tolerance = 1e-9 if held else 1e-4
    assert max(difference.values()) < tolerance, difference
    assert stream.late_samples == {}
    assert joined.gate_memory is not None and joined.fault_memory is not None


@pytest.mark.parametrize(
    "adaptive",
    [
        {"adaptive_noise_sensors": ["gnss", "gnss_velocity"]},
        {"strong_tracking_sensors": ["gnss"]},
    ],
)
def test_the_adaptive_noise_carries_over(run, adaptive):
    """The adaptive noise's and strong tracking's state goes on from piece to piece
    (``GateMemory.adaptation``), across a piece without GNSS (11.3-11.35 s) too. It restarted
    in every piece: 0.25 m (adaptive GNSS) and 0.75 m (strong tracking) from the one run;
    now 1.5e-6 and 4e-7 m (the pieces' extra epochs remain)."""
    seq, cfg = run
    cfg = cfg.replace(**HELD, **adaptive)
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = [time_slice(seq, a, b) for a, b in zip(BOUNDS[:-1], BOUNDS[1:], strict=True)]
        _, joined = _streamed(seq, cfg, pieces)
    assert joined.gate_memory.adaptation is not None
    assert _largest_difference(joined, whole)["position"] < 1e-4


def test_measurements_ahead_of_the_imu_wait_for_the_next_piece(run):
    """Each piece's measurements run 0.3 s past its IMU (a receiver ahead of the IMU
    driver): they are fused when the IMU gets there, as in the one run."""
    seq, cfg = run
    cfg = cfg.replace(**HELD)
    imu_only = dataclasses.replace
    pieces = []
    for a, b in zip(BOUNDS[:-1], BOUNDS[1:], strict=True):
        measured = time_slice(seq, a + 0.3 if a > 0 else 0.0, b + 0.3)
        pieces.append(imu_only(measured, imu=time_slice(seq, a, b).imu))
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        _, joined = _streamed(seq, cfg, pieces)
    assert max(_largest_difference(joined, whole).values()) < 1e-9


def test_late_samples_are_skipped_counted_and_warned(run):
    seq, cfg = run
    cfg = cfg.replace(**HELD)
    first, second = time_slice(seq, 0.0, 5.0), time_slice(seq, 5.0, 9.0)
    late = dataclasses.replace(
        second,
        gnss=time_slice(seq, 4.0, 9.0).gnss,  # the fix at 4 s, after the IMU passed it
        imu=time_slice(seq, 4.99, 9.0).imu,  # and two IMU samples already filtered
    )
    with torch.no_grad():
        stream = EskfStream(cfg, initial=initial_state(seq, cfg))
        stream.push(first)
        with pytest.warns(UserWarning, match="gnss sample"):
            got = stream.push(late)
        reference = EskfStream(cfg, initial=initial_state(seq, cfg))
        reference.push(first)
        want = reference.push(second)
    assert stream.late_samples == {"imu": 2, "gnss": 1}
    assert torch.equal(got.position, want.position)


def test_the_first_piece_sets_the_initial_state_and_tiny_pieces_wait(run):
    seq, cfg = run
    with torch.no_grad():
        stream = EskfStream(cfg)
        assert stream.push(time_slice(seq, 0.0, 0.004)) is None  # one IMU sample: kept
        first = stream.push(time_slice(seq, 0.004, 8.0))
        # measurements alone (the fix at 8 s before its IMU packet): they wait
        early = time_slice(seq, 8.0, 8.5)
        assert bool(early.gnss.t[0] == 8.0) and early.imu.length > 1
        assert (
            stream.push(dataclasses.replace(early, imu=early.imu.map(lambda x: x[:, :0]))) is None
        )
        rest = time_slice(seq, 8.5, 12.0)
        second = stream.push(dataclasses.replace(rest, imu=time_slice(seq, 8.0, 12.0).imu))
    assert float(first.t[0, 0]) == 0.0
    # the heading from the first GNSS velocity fast enough (frontend.init), not pi
    assert float(first.covariance[0, 0, 8, 8].sqrt()) < 0.1
    assert float(second.t[0, 0]) == float(first.t[0, -1])
    # the fix at 8 s was fused, in the second piece, with those at 9, 10, 11 s
    assert second.t[0, second.present["gnss"][0]].tolist() == [8.0, 9.0, 10.0, 11.0]
    assert int(second.dropped_samples["gnss"].sum()) == 0


@pytest.mark.parametrize("cut", [8.02, 9.0, 9.98])
def test_a_boundary_inside_a_filled_in_stretch(run, cut):
    """A 2-s filled-in stretch (8..10 s) cut by a piece boundary: the tail from its first
    sample waits for the next piece, so the stretch is modelled as one, as in the run in
    one piece (before: 0.19-1.28 m apart, each part's variance from its own length)."""
    seq, cfg = run
    seq, cfg = fill_imu_stretch(seq, 8.0, 10.0), cfg.replace(**HELD)
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        stream, joined = _streamed(seq, cfg, [time_slice(seq, 0, cut), time_slice(seq, cut, 21)])
        held = stream.results[0]
    assert float(held.t[0, held.mask[0]][-1]) == pytest.approx(8.0)  # the stretch's start
    assert int(whole.gap[0].sum()) == int(joined.gap[0].sum()) > 0
    assert max(_largest_difference(joined, whole).values()) < 1e-9


def test_pieces_inside_a_stretch_wait_and_max_hold_s_bounds_the_wait(run):
    seq, cfg = run
    seq, cfg = fill_imu_stretch(seq, 8.0, 10.0), cfg.replace(**HELD)
    pieces = [time_slice(seq, a, b) for a, b in ((0, 8.5), (8.5, 9.5), (9.5, 21))]
    with torch.no_grad():
        stream = EskfStream(cfg, initial=initial_state(seq, cfg))
        first, middle = stream.push(pieces[0]), stream.push(pieces[1])
        assert middle is None  # every new sample continues the stretch
        stream.push(pieces[2])
        short = EskfStream(cfg, initial=initial_state(seq, cfg), max_hold_s=0.1)
        cut_short = short.push(pieces[0])
    assert float(first.t[0, first.mask[0]][-1]) == pytest.approx(8.0)
    assert float(cut_short.t[0, cut_short.mask[0]][-1]) == pytest.approx(8.495)
    assert [float(r.t[0, 0]) for r in stream.results] == pytest.approx([0.0, 8.0])


def test_finish_filters_a_stretch_that_reaches_the_end(run):
    """A run that ends inside a filled-in stretch (from 18 s to its last sample): the last
    piece holds the stretch back; ``finish`` filters it, and the pieces equal the run in
    one piece (which models the stretch up to its end too)."""
    seq, cfg = run
    last = float(seq.imu.t[0, seq.imu.mask[0]][-1])
    seq, cfg = fill_imu_stretch(seq, 18.0, last), cfg.replace(**HELD)
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        stream = EskfStream(cfg, initial=initial_state(seq, cfg))
        stream.push(time_slice(seq, 0, 10))
        held = stream.push(time_slice(seq, 10, 21))
        tail = stream.finish()
        assert stream.finish() is None
    assert float(held.t[0, held.mask[0]][-1]) == pytest.approx(18.0)
    assert float(tail.t[0, tail.mask[0]][-1]) == pytest.approx(last)
    joined = concat_results(stream.results)
    assert int(whole.gap[0].sum()) == int(joined.gap[0].sum()) > 0
    assert max(_largest_difference(joined, whole).values()) < 1e-9
