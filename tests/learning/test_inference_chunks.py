"""Learned-noise runs in chunks (``learning.inference.run_piecewise``) behave as one run.

* The gate's rejection streaks and the guard's episode carry from chunk to chunk
  (``EskfResult.gate_memory``): on a run whose GNSS turns 8 x noisier than declared (gate
  re-opens), chunks of 1 s equal the unchained run to 1e-9; without the memory they do not.
  A block that a chunk does not measure keeps its streak through it (0.04 s chunks, GNSS
  at 5 Hz: round-off; it was forgotten, 0.32 m).
  So do the wheel slip factor (same memory) on a run with slip episodes, and the online
  calibration states (``EskfResult.calibration_memory``) on a run with miscalibrated wheels,
  a GNSS time offset and a 10 Hz VO source, whose pairs across the chunk boundaries are
  fused as in the one run (``EskfResult.pair_memory``: the pair's start and the gyro
  integral since), also in the drifting-frame mode, with the VO's time offset calibrated,
  and in a batch of two with masked VO samples and chunks without a VO sample.
  The biases are held there (zero initial sigma and random walk, also after
  ``config_for_sequence``): the preintegration is linearised at each chunk's starting bias,
  a second-order difference otherwise.
* The pose-source fault detector's models, windows and exclusions carry over
  (``EskfResult.fault_memory``): a LiDAR sliding along a corridor over 8 s is flagged at
  the same pairs in 1-s chunks as in the one run.
* An IMU sample skipped at a chunk boundary: the chunks meet at the real sample before it
  and equal the one run at its epochs.
* Diagnostics: divergence codes, skipped samples, source-fault flags and Z, fading factors
  and noise estimates come through the chunks as ``run_eskf`` reports them.
* Ctrl-C in a later chunk: ``EstimationInterrupted`` carries the epochs of every completed
  chunk (equal to the full run's first ones) and the whole run's epoch count, and
  ``run_sequence`` with a CovNet writes the partial outputs.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.gating import chi2_threshold
from msf_torch.frontend.guard import NONFINITE, EstimationInterrupted
from msf_torch.frontend.init import initial_state
from msf_torch.io.tum import read_tum
from msf_torch.learning import CovNet, CovNetConfig
from msf_torch.learning.data import simulate_labelled_run
from msf_torch.learning.inference import LearnedModel, run_piecewise
from msf_torch.runner import RunInterrupted, RunOptions, run_sequence
from msf_torch.sim import SimConfig, fill_imu_stretch, simulate_run
from msf_torch.sim.calibration import calibration_sim_config, simulate_calibration_run
from msf_torch.sim.faults import SourceFault, inject_faults
from msf_torch.sim.noise_step import gnss_noise_step
from msf_torch.sim.weather import WeatherSchedule, apply_weather
from msf_torch.types import NavState, batch_sequences

TOL = 1e-9
HELD_BIASES = EskfConfig(
    init_gyro_bias_sigma_radps=0.0,
    init_accel_bias_sigma_mps2=0.0,
    gyro_bias_rw_density=0.0,
    accel_bias_rw_density=0.0,
)


def _alternating(windows: int) -> torch.Tensor:
    """(W, 7) log scales that differ from window to window (so each window is a chunk) but
    give the same noise: exp(1e-300) == 1 in float64."""
    scales = torch.zeros(windows, 7, dtype=torch.float64)
    scales[1::2] = 1e-300
    return scales


@pytest.fixture(scope="module")
def noisy_gnss_run():
    run = simulate_run(SimConfig(duration_s=25.0, slip_episodes=0), seed=4)
    return gnss_noise_step(run.sequence, 8.0, 8.0, seed=4)


def _held(cfg: EskfConfig) -> EskfConfig:
    """``cfg`` with the biases held (``config_for_sequence`` sets their random walks from
    the sequence's metadata)."""
    return cfg.replace(
        init_gyro_bias_sigma_radps=0.0,
        init_accel_bias_sigma_mps2=0.0,
        gyro_bias_rw_density=0.0,
        accel_bias_rw_density=0.0,
    )


def _chunks(seq, cfg, length: int, carry: bool):
    """run_eskf over IMU chunks of ``length`` samples, chained by hand (B > 1: IMU samples
    unmasked); ``carry``: with every memory (gate, calibration, source pairs, faults)."""
    imu = seq.imu.compact() if seq.batch_size == 1 else seq.imu
    initial, memory, parts = initial_state(seq, cfg), {}, []
    rows = torch.arange(seq.batch_size)
    for start in range(0, imu.length - 1, length):
        chunk = dataclasses.replace(seq, imu=imu.map(lambda x, a=start: x[:, a : a + length + 1]))
        part = run_eskf(chunk, cfg, initial=initial, **memory)
        last = part.mask.sum(1) - 1
        fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
        initial = (
            NavState(*(getattr(part, f)[rows, last] for f in fields)),
            part.covariance[rows, last],
        )
        if carry:
            names = ("gate_memory", "calibration_memory", "pair_memory", "fault_memory")
            memory = {name: getattr(part, name) for name in names}
        parts.append(part)
    return parts


def test_chunks_gate_as_one_run(noisy_gnss_run):
    seq, cfg = noisy_gnss_run, HELD_BIASES
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(25), 200, None)
        forgetful = _chunks(seq, cfg, 200, carry=False)
    reopened = whole.accepted["gnss"] & (whole.nis["gnss"] > 21.0)
    assert int(reopened.sum()) >= 2  # re-opened fixes far outside the gate (measured 2)
    _assert_same_run(pieces, whole)
    assert torch.equal(pieces.accepted["gnss"], whole.accepted["gnss"])
    # without the memory every 1 s chunk starts with no rejections: the gate never re-opens
    accepted = torch.cat([p.accepted["gnss"][0, 1:] for p in forgetful])
    assert int(accepted.sum()) < int(whole.accepted["gnss"].sum())
    final = forgetful[-1].position[0, forgetful[-1].mask[0]][-1]
    assert float((final - whole.position[0, -1]).norm()) > 1e-3


def test_chunks_bridge_a_skipped_sample_at_a_boundary(noisy_gnss_run):
    accel = noisy_gnss_run.imu.accel.clone()
    accel[0, 600, 1] = torch.nan  # the sample at 3 s, where the fourth 1 s chunk starts
    seq = dataclasses.replace(
        noisy_gnss_run, imu=dataclasses.replace(noisy_gnss_run.imu, accel=accel)
    )
    with torch.no_grad():
        whole = run_eskf(seq, HELD_BIASES)
        pieces = run_piecewise(seq, HELD_BIASES, _alternating(25), 200, None)
    assert pieces.dropped_samples["imu"].tolist() == [1]
    # the chunks meet at the sample before (an epoch the one run has not); before, the 10 ms
    # between its neighbours went unfiltered (measured 0.26 m)
    here = torch.isin(pieces.t[0], whole.t[0])
    assert int((~here).sum()) == 1 and torch.equal(pieces.t[0, here], whole.t[0])
    for name in ("position", "velocity", "covariance"):
        diff = (getattr(pieces, name)[0, here] - getattr(whole, name)[0]).abs().max()
        assert float(diff) < TOL, name  # round-off (measured 1.9e-12 m)


@pytest.mark.parametrize("length", [160, 360])
def test_chunks_keep_a_filled_in_stretch_whole(noisy_gnss_run, length):
    """A 2-s filled-in stretch (8..10 s) that chunk boundaries fall into: each boundary
    moves to the stretch's end, so the stretch's variance comes from its whole length, as
    in the one run (before: 19.1 m apart with 0.8-s chunks, 21.4 m with 1.8-s ones on this run
    whose GNSS turns 8 x noisier than declared); a
    chunk wholly inside it is left to the chunk before."""
    seq = fill_imu_stretch(noisy_gnss_run, 8.0, 10.0)
    windows = (seq.imu.length - 1) // length
    with torch.no_grad():
        whole = run_eskf(seq, HELD_BIASES)
        pieces = run_piecewise(seq, HELD_BIASES, _alternating(windows), length, None)
    assert int(whole.gap[0].sum()) > 0
    _assert_same_run(pieces, whole)


def _assert_same_run(
    pieces, whole, fields=("position", "velocity", "rotation", "covariance"), tol=TOL
):
    assert torch.equal(pieces.t, whole.t)
    for field in fields:
        diff = (getattr(pieces, field) - getattr(whole, field)).abs().max()
        assert float(diff) < tol, field


def test_chunks_carry_the_slip_factor():
    run = simulate_run(SimConfig(duration_s=30.0, slip_episodes=2), seed=11)
    seq, cfg = run.sequence, config_for_sequence(HELD_BIASES, run.sequence.meta, set())
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(30), 200, None)
        forgetful = _chunks(seq, cfg, 200, carry=False)
    assert float(whole.slip_factor.min()) < 0.05  # the slips were seen (measured 0.0)
    # round-off only (measured 5.8e-9 m over 30 s of slipping wheels)
    fields = ("position", "velocity", "covariance", "slip_factor")
    _assert_same_run(pieces, whole, fields, tol=1e-7)
    # forgetting the factor skips its rate-limited recovery at every chunk start
    forgot = torch.cat([p.slip_factor[0, 1:] for p in forgetful])
    assert float((forgot - whole.slip_factor[0, 1:]).abs().max()) > 0.2  # measured 0.43


@pytest.fixture(scope="module")
def vo_calibration_run():
    """40 s with miscalibrated wheels, a GNSS time offset and a 10 Hz VO source."""
    return simulate_calibration_run(3, calibration_sim_config(40.0)).sequence


def test_chunks_carry_the_calibration(vo_calibration_run):
    seq = vo_calibration_run
    cfg = _held(
        config_for_sequence(
            EskfConfig(calibrate_wheels=True, calibrate_time_offsets=["gnss"]), seq.meta, set()
        )
    )
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(40), 200, None)
    fields = ("position", "covariance", "calibration", "calibration_covariance")
    _assert_same_run(pieces, whole, fields)  # round-off (measured 4.5e-13 m)
    sigma = torch.diagonal(whole.calibration_covariance[0, -1]).sqrt()
    prior = torch.diagonal(whole.calibration_covariance[0, 0]).sqrt()
    # the wheel radii were learned over many 1 s chunks (measured 0.0018 from 0.1)
    assert bool((sigma[:2] < 0.05 * prior[:2]).all())
    with pytest.raises(ValueError, match="calibrates no state"):
        run_eskf(seq, HELD_BIASES, calibration_memory=pieces.calibration_memory)


@pytest.mark.parametrize(
    "fusion", [{"calibrate_time_offsets": ["pose:vo"]}, {"pose_source_fusion": "drifting_frame"}]
)
def test_chunks_fuse_the_source_pairs_across_boundaries(vo_calibration_run, fusion):
    seq = vo_calibration_run
    cfg = _held(config_for_sequence(EskfConfig(**fusion), seq.meta, set()))
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(40), 200, None)
    # every pair is fused, also the 39 across the 1 s chunk boundaries (the VO runs at
    # 10 Hz from 0.08 s), with the mean gyro rate over its whole interval and, for the
    # VO's time offset, the rate change since the pair before (before: ~1 cm apart)
    assert torch.equal(pieces.present["pose:vo"], whole.present["pose:vo"])
    assert torch.equal(pieces.accepted["pose:vo"], whole.accepted["pose:vo"])
    fields = ("position", "velocity", "rotation", "covariance", "calibration")
    fields = fields if whole.calibration is not None else fields[:-1]
    _assert_same_run(pieces, whole, fields)  # round-off (measured 1.6e-13, 4.3e-14 m)
    for key, frame in whole.source_frame.items():
        assert float((pieces.source_frame[key] - frame).abs().max()) < TOL


def test_batch_chunks_fuse_the_source_pairs_across_boundaries():
    """B = 2, 0.04 s chunks (on the wheel epochs; most hold no valid VO sample: the pair's
    start, its gyro integral and the pair before it pass through), VO samples masked around
    two boundaries, the VO's time offset calibrated."""
    runs = [simulate_calibration_run(s, calibration_sim_config(6.0)).sequence for s in (3, 4)]
    vo = runs[1].pose_sources["vo"]
    mask = vo.mask.clone()
    mask[0, torch.isin(torch.round(vo.t[0] * 100), torch.tensor([302.0, 402.0]))] = False
    assert int(mask.sum()) == vo.length - 2
    runs[1] = dataclasses.replace(runs[1], pose_sources={"vo": dataclasses.replace(vo, mask=mask)})
    seq = batch_sequences(runs)
    cfg = EskfConfig(calibrate_time_offsets=["pose:vo"])
    cfg = _held(config_for_sequence(cfg, runs[0].meta, set()))
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        parts = _chunks(seq, cfg, 8, carry=True)
        with pytest.raises(ValueError, match="pair_memory"):
            memory = dataclasses.replace(parts[0].pair_memory, names=("lidar",))
            run_eskf(seq, cfg, pair_memory=memory)
    for b in range(2):  # round-off (measured 1.4e-14 m)
        _assert_same_epochs(parts, whole, b, ("position", "velocity", "covariance", "calibration"))


def test_chunks_carry_the_source_fault_detector():
    """35 s, wheels dropped, GNSS over the first 12 s; the LiDAR reports 20 % of the motion
    along a corridor over 20-28 s. 1-s chunks flag it as the run in one piece does; before
    the detector restarted in every chunk, its window and models empty, and flagged less."""
    duration = 35.0
    sim = SimConfig(duration_s=duration, imu_rate_hz=100.0, gnss_outages_s=((12.0, duration),))
    run = simulate_run(sim, seed=9)
    wet = apply_weather(run, WeatherSchedule.constant("sunny", duration), seed=9)
    fault = SourceFault("lidar", "slide", 20.0, 28.0, axial_scale=0.2)
    seq = dataclasses.replace(inject_faults(wet, [fault], seed=9).sequence, wheel=None)
    cfg = config_for_sequence(HELD_BIASES, seq.meta, set()).replace(source_fault_detection=True)
    cfg = _held(cfg)
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(35), 100, "lidar")
        forgetful = _chunks(seq, cfg, 100, carry=False)
    flagged = whole.source_fault["pose:lidar"][0]
    assert int(flagged.sum()) > 50  # the slide was caught (pairs at 10 Hz)
    for key in ("pose:lidar", "pose:vo"):
        assert torch.equal(pieces.source_fault[key][0], whole.source_fault[key][0]), key
        diff = (pieces.source_fault_z[key] - whole.source_fault_z[key]).abs().max()
        assert float(diff) < 1e-9, key
    _assert_same_run(pieces, whole, ("position", "velocity", "covariance"))
    restarted = sum(
        int(p.source_fault["pose:lidar"][0, 1:][p.mask[0, 1:]].sum()) for p in forgetful
    )
    assert restarted < int(flagged.sum())
    with pytest.raises(ValueError, match="no pose-source faults"):
        run_eskf(seq, HELD_BIASES, fault_memory=pieces.fault_memory)


def test_chunks_without_a_block_keep_its_gate_streak():
    """A GNSS whose fixes the uncalibrated run rejects in streaks (16 of 30), filtered in
    0.04 s chunks: most chunks hold no fix, and the streak (count, innovation sums,
    vouching) passes through them, so the gate re-opens where the one run's does."""
    seq = simulate_calibration_run(3, calibration_sim_config(6.0)).sequence
    cfg = _held(config_for_sequence(EskfConfig(), seq.meta, set()))
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        parts = _chunks(seq, cfg, 8, carry=True)
    real = whole.mask[0]
    gate = chi2_threshold(3, cfg.gate_probability)
    reopened = whole.accepted["gnss"][0, real] & (whole.nis["gnss"][0, real] > gate)
    assert int(reopened.sum()) >= 2  # measured 4
    assert sum(bool(p.present["gnss"].any()) for p in parts) < len(parts) / 4  # 30 of 150
    t = _chained(parts, "t", 0)
    accepted = torch.cat(
        [p.accepted["gnss"][0, p.mask[0]][min(k, 1) :] for k, p in enumerate(parts)]
    )
    assert torch.equal(accepted[torch.isin(t, whole.t[0, real])], whole.accepted["gnss"][0, real])
    # round-off (measured 2.8e-14 m); forgetting the streak: 0.32 m
    _assert_same_epochs(parts, whole, 0, ("position", "velocity", "covariance"))


def _chained(parts, name: str, b: int) -> torch.Tensor:
    """Sequence ``b``'s real epochs of hand-chained chunks (:func:`_chunks`) of a per-epoch
    field, each chunk's first (its predecessor's last) dropped."""
    return torch.cat([getattr(p, name)[b, p.mask[b]][min(k, 1) :] for k, p in enumerate(parts)])


def _assert_same_epochs(parts, whole, b: int, fields, tol=TOL) -> None:
    """The chunks equal the one run at its epochs (the chunk boundaries it has no epoch at
    left out) in ``fields``."""
    t, real = _chained(parts, "t", b), whole.mask[b]
    here = torch.isin(t, whole.t[b, real])
    assert torch.equal(t[here], whole.t[b, real])
    for name in fields:
        diff = (_chained(parts, name, b)[here] - getattr(whole, name)[b, real]).abs().max()
        assert float(diff) < tol, (b, name, float(diff))


@pytest.fixture(scope="module")
def weather_run():
    """A 6 s weather run (VO and LiDAR odometry, GNSS) with a NaN IMU sample and a
    1e200 rad/s gyro sample (finite: the propagation overflows, a divergence reset)."""
    seq = simulate_labelled_run(3, 6.0)
    gyro, accel = seq.imu.gyro.clone(), seq.imu.accel.clone()
    accel[0, 150, 1] = torch.nan
    gyro[0, 420, 2] = 1e200
    return dataclasses.replace(seq, imu=dataclasses.replace(seq.imu, gyro=gyro, accel=accel))


def test_chunked_run_reports_the_diagnostics(weather_run):
    seq = weather_run
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    faults = cfg.replace(source_fault_detection=True)
    # the adaptive blocks fail on a non-finite propagation (frontend.adaptive), so they run
    # on the sequence without the overflowing sample
    adaptive = cfg.replace(adaptive_noise_sensors=["gnss"], strong_tracking_sensors=["gnss"])
    gyro = seq.imu.gyro.clone()
    gyro[0, 420, 2] = 0.0
    finite = dataclasses.replace(seq, imu=dataclasses.replace(seq.imu, gyro=gyro))
    with torch.no_grad():
        whole = run_eskf(seq, faults)
        pieces = run_piecewise(seq, faults, _alternating(6), 100, "lidar")
        whole_adaptive = run_eskf(finite, adaptive)
        pieces_adaptive = run_piecewise(finite, adaptive, _alternating(6), 100, "lidar")
    real = whole.mask[0]
    assert torch.equal(pieces.t[0], whole.t[0, real])
    assert {k: v.tolist() for k, v in pieces.dropped_samples.items()} == {
        k: v.tolist() for k, v in whole.dropped_samples.items()
    }
    assert pieces.dropped_samples["imu"].tolist() == [1]
    reset_at = whole.t[0, real][whole.divergence[0, real] != 0]
    assert reset_at.numel() == 1 and bool((whole.divergence[0] & NONFINITE).any())
    assert torch.equal(pieces.t[0][pieces.divergence[0] != 0], reset_at)
    epochs = pieces.t.shape[1]
    checks = [(pieces, whole, "source_fault"), (pieces, whole, "source_fault_z")]
    checks.append((pieces_adaptive, whole_adaptive, "noise_estimate"))
    for got_result, want_result, name in checks:
        got, want = getattr(got_result, name), getattr(want_result, name)
        assert set(got) == set(want) and got, name
        for key, value in got.items():
            assert value.shape == (1, got_result.t.shape[1], *want[key].shape[2:]), (name, key)
    fading = pieces_adaptive.fading_factor
    assert fading.shape == pieces_adaptive.t.shape and bool((fading >= 1.0).all())
    assert bool((fading > 1.0).any()) == bool((whole_adaptive.fading_factor > 1.0).any())
    assert pieces.gap.shape == (1, epochs) and pieces.gate_memory is not None


def _stopper(after: int):
    def progress(done: int, total: int) -> None:
        if done == after:
            raise KeyboardInterrupt

    return progress


def test_interrupt_hands_on_the_completed_chunks(noisy_gnss_run):
    seq, cfg = noisy_gnss_run, HELD_BIASES
    scales = _alternating(25)
    with torch.no_grad():
        full = run_piecewise(seq, cfg, scales, 200, None)
        stop_after = 130  # in the fifth 1 s chunk (25 epochs a chunk)
        with pytest.raises(EstimationInterrupted) as info:
            run_piecewise(seq, cfg, scales, 200, None, progress=_stopper(stop_after))
    stop = info.value
    assert stop.epochs_done == stop_after
    assert stop.epochs_total == full.t.shape[1] - 1
    part = stop.result
    assert int(part.mask[0].sum()) == part.t.shape[1] == stop_after + 1
    for field in ("t", "position", "rotation", "covariance"):
        assert torch.equal(getattr(part, field)[0], getattr(full, field)[0, : stop_after + 1])


def test_learned_msf_run_writes_partial_outputs(tmp_path):
    torch.manual_seed(0)
    net = CovNet(CovNetConfig(window_length=50, channels=4, embedding=4, hidden=8)).eval()
    seq = simulate_labelled_run(3, 6.0)
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    options = RunOptions(
        out_dir=tmp_path,
        plot=False,
        progress=lambda: (_stopper(100), lambda: None),
        learned=LearnedModel(net, tmp_path / "net.pt", "0" * 64),
    )
    with pytest.raises(RunInterrupted) as info:
        run_sequence(seq, cfg, options)
    summary = info.value.summary
    assert summary["noise"] == "learned"
    assert summary["interrupted"]["stage"] == "frontend"
    assert summary["interrupted"]["epochs_done"] == 100
    assert summary["interrupted"]["epochs_total"] > 100
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert read_tum(tmp_path / "trajectory.tum").length == 101
    rows = (tmp_path / "diagnostics.csv").read_text().splitlines()
    assert len(rows) == 102 and "divergence" in rows[0].split(",")
