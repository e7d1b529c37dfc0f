"""Learned-noise runs in chunks (``learning.inference.run_piecewise``) behave as one run.

* The gate's rejection streaks and the guard's episode carry from chunk to chunk
  (``EskfResult.gate_memory``): on a run whose GNSS turns 8 x noisier than declared (gate
  re-opens), chunks of 1 s equal the unchained run to 1e-9; without the memory they do not.
  So do the wheel slip factor (same memory) on a run with slip episodes, and the online
  calibration states (``EskfResult.calibration_memory``) on a run with miscalibrated wheels
  and a GNSS time offset.
  The biases are held there (zero initial sigma and random walk): the preintegration is
  linearised at each chunk's starting bias, a second-order difference otherwise.
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
from msf_torch.frontend.guard import NONFINITE, EstimationInterrupted
from msf_torch.frontend.init import initial_state
from msf_torch.io.tum import read_tum
from msf_torch.learning import CovNet, CovNetConfig
from msf_torch.learning.data import simulate_labelled_run
from msf_torch.learning.inference import LearnedModel, run_piecewise
from msf_torch.runner import RunInterrupted, RunOptions, run_sequence
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.calibration import calibration_sim_config, simulate_calibration_run
from msf_torch.sim.noise_step import gnss_noise_step
from msf_torch.types import NavState

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


def _chunks(seq, cfg, length: int, carry: bool):
    """run_eskf over IMU chunks of ``length`` samples, chained by hand."""
    imu = seq.imu.compact()
    initial, memory, parts = initial_state(seq, cfg), None, []
    for start in range(0, imu.length - 1, length):
        chunk = dataclasses.replace(seq, imu=imu.map(lambda x, a=start: x[:, a : a + length + 1]))
        part = run_eskf(chunk, cfg, initial=initial, gate_memory=memory if carry else None)
        last = int(part.mask[0].sum()) - 1
        fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
        initial = (
            NavState(*(getattr(part, f)[:, last] for f in fields)),
            part.covariance[:, last],
        )
        memory = part.gate_memory
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


def test_chunks_carry_the_calibration():
    run = simulate_calibration_run(3, calibration_sim_config(40.0))
    # without its VO: a pose source's pair across a chunk boundary is not fused
    seq = dataclasses.replace(run.sequence, pose_sources={})
    cfg = config_for_sequence(
        dataclasses.replace(HELD_BIASES, calibrate_wheels=True, calibrate_time_offsets=["gnss"]),
        seq.meta,
        set(),
    )
    with torch.no_grad():
        whole = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, _alternating(40), 200, None)
    fields = ("position", "covariance", "calibration", "calibration_covariance")
    _assert_same_run(pieces, whole, fields, tol=1e-6)  # round-off (measured 5e-8 m)
    sigma = torch.diagonal(whole.calibration_covariance[0, -1]).sqrt()
    prior = torch.diagonal(whole.calibration_covariance[0, 0]).sqrt()
    # the wheel radii were learned over many 1 s chunks (measured 0.0018 from 0.1)
    assert bool((sigma[:2] < 0.05 * prior[:2]).all())
    with pytest.raises(ValueError, match="calibrates no state"):
        run_eskf(seq, HELD_BIASES, calibration_memory=pieces.calibration_memory)


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
