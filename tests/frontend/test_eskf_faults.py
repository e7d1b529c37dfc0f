"""Faulty input to the ESKF: skipped by rule, or detected as divergence and reset.

One simulated wheeled-robot run (40 s, IMU 200 Hz, wheels 25 Hz, GNSS 1 Hz, no slip) is
copied with one fault each and all copies go through ``run_eskf`` as ONE batch, so every
check also shows that a sequence's fault and reset stay in its own row. References are
independent: the same run with the offending samples removed, a single-sequence run, and
the simulated truth.

Faults: NaN/inf samples; duplicated and out-of-order stamps; a 3 s IMU gap and an 8 s gap
of every sensor; GNSS missing for the whole run; a 1 km GNSS jump (one fix, and eight); a
stuck gyro axis (z held for 12 s); a gyro sample of 1e200 rad/s (finite, so it passes the
input rule and blows up the propagation); a pose with an indefinite covariance.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfResult, run_eskf
from msf_torch.frontend.guard import NIS_BLOWUP, NONFINITE, NOT_POSITIVE_DEFINITE
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import PoseMeasurements, Sequence, Trajectory, batch_sequences

TOL = 1e-9
CFG = EskfConfig()


def _remove(stream, index: list[int]):
    """The stream without the samples ``index`` (B = 1)."""
    keep = torch.ones(stream.length, dtype=torch.bool)
    keep[index] = False
    return stream.map(lambda x: x[:, keep])


def _insert(stream, at: int, source: int):
    """The stream with a copy of sample ``source`` inserted before ``at`` (B = 1)."""
    order = list(range(stream.length))
    order.insert(at, source)
    return stream.map(lambda x: x[:, order])


def _cut(stream, t0: float, t1: float):
    """The stream without the samples strictly inside (t0, t1) s."""
    inside = (stream.t[0] > t0) & (stream.t[0] < t1)
    return _remove(stream, torch.nonzero(inside).flatten().tolist())


def _first_after(stream, t: float) -> int:
    return int(torch.nonzero(stream.t[0] >= t)[0])


def _scenarios(seq: Sequence) -> dict[str, Sequence]:
    imu, wheel, gnss = seq.imu, seq.wheel, seq.gnss
    out = {"clean": seq}

    # NaN / inf in times and values; the reference has those samples removed
    bad_imu = [_first_after(imu, t) for t in (2.0, 2.01, 7.5, 11.1, 15.0, 15.01, 25.0)]
    gyro, accel, t = imu.gyro.clone(), imu.accel.clone(), imu.t.clone()
    gyro[0, bad_imu[:3], 1] = torch.nan
    accel[0, bad_imu[3:5], 2] = torch.inf
    gyro[0, bad_imu[5], 0] = -torch.inf
    t[0, bad_imu[6]] = torch.nan
    left = wheel.left_speed.clone()
    left[0, [30, 31]] = torch.nan
    fixes = gnss.position.clone()
    fixes[0, 12, 0] = torch.nan
    out["nonfinite"] = dataclasses.replace(
        seq,
        imu=dataclasses.replace(imu, gyro=gyro, accel=accel, t=t),
        wheel=dataclasses.replace(wheel, left_speed=left),
        gnss=dataclasses.replace(gnss, position=fixes),
    )
    out["nonfinite_ref"] = dataclasses.replace(
        seq, imu=_remove(imu, bad_imu), wheel=_remove(wheel, [30, 31]), gnss=_remove(gnss, [12])
    )

    # repeated stamps (a copy right after the original) and out-of-order ones (a sample
    # moved after its successor: the successor is kept, the moved one is late and dropped)
    i, j = _first_after(imu, 5.0), _first_after(imu, 15.0)
    dup_imu = _insert(_insert(imu, i + 1, i), j + 1, j)  # samples i and j repeated
    swapped = list(range(dup_imu.length))
    k = _first_after(imu, 10.0) + 1  # its index after the first insertion
    swapped[k - 1], swapped[k] = k, k - 1
    dup_imu = dup_imu.map(lambda x: x[:, swapped])
    late_gnss = _insert(gnss, 16, 9)  # fix 9 again after fix 15: backwards in time
    out["stamps"] = dataclasses.replace(
        seq, imu=dup_imu, wheel=_insert(wheel, 101, 100), gnss=late_gnss
    )
    out["stamps_ref"] = dataclasses.replace(seq, imu=_remove(imu, [k - 2]))

    # a gap of the IMU alone, 3 s (every sensor: see _all_sensor_gap)
    out["imu_gap"] = dataclasses.replace(seq, imu=_cut(imu, 12.0, 15.0))

    # GNSS missing for the whole run: the stream exists, no sample is real
    out["no_gnss"] = dataclasses.replace(
        seq, gnss=dataclasses.replace(gnss, mask=torch.zeros_like(gnss.mask))
    )

    # a 1 km GNSS jump: one fix, then eight in a row
    k = _first_after(gnss, 20.0)
    one, eight = gnss.position.clone(), gnss.position.clone()
    one[0, k, 0] += 1000.0
    eight[0, k : k + 8, 0] += 1000.0
    out["jump_one"] = dataclasses.replace(seq, gnss=dataclasses.replace(gnss, position=one))
    out["jump_one_ref"] = dataclasses.replace(seq, gnss=_remove(gnss, [k]))
    out["jump_eight"] = dataclasses.replace(seq, gnss=dataclasses.replace(gnss, position=eight))

    # the gyro's z axis stuck at its 6 s reading until 16 s
    stuck = imu.gyro.clone()
    held = (imu.t[0] >= 6.0) & (imu.t[0] < 16.0)
    stuck[0, held, 2] = stuck[0, _first_after(imu, 6.0), 2]
    out["stuck_gyro"] = dataclasses.replace(seq, imu=dataclasses.replace(imu, gyro=stuck))

    # a finite but absurd gyro sample: the propagation overflows
    huge = imu.gyro.clone()
    huge[0, _first_after(imu, 15.0), 1] = 1e200
    out["huge_gyro"] = dataclasses.replace(seq, imu=dataclasses.replace(imu, gyro=huge))

    # absolute poses (truth, 0.1 m / 0.01 rad) at 1 Hz, one with an indefinite covariance
    truth = seq.ground_truth
    at = torch.arange(200, truth.length, 200)
    cov = torch.diag(torch.tensor([0.01] * 3 + [1e-4] * 3, dtype=torch.float64))
    cov = cov.expand(1, at.numel(), 6, 6).clone()
    cov[0, 10] = -100.0 * torch.eye(6, dtype=torch.float64)
    poses = PoseMeasurements(
        t=truth.t[:, at],
        position=truth.position[:, at],
        quaternion=truth.quaternion[:, at],
        covariance=cov,
        mask=torch.ones(1, at.numel(), dtype=torch.bool),
    )
    out["bad_pose_cov"] = dataclasses.replace(seq, poses=poses)
    return out


def _all_sensor_gap(seq: Sequence) -> Sequence:
    """Every sensor silent from 10 s to 20 s."""
    return dataclasses.replace(
        seq,
        imu=_cut(seq.imu, 10.0, 20.0),
        wheel=_cut(seq.wheel, 10.0, 20.0),
        gnss=_cut(seq.gnss, 10.0, 20.0),
    )


class Faults(NamedTuple):
    """The module fixture: the base run, every scenario, its truth, the batch's result."""

    seq: Sequence
    scenarios: dict[str, Sequence]
    truth: dict[str, Trajectory]
    names: list[str]
    result: EskfResult

    def row(self, name: str) -> int:
        return self.names.index(name)

    def errors(self, name: str, result: EskfResult | None = None, b: int | None = None):
        """Epoch times and position errors (m) of scenario ``name`` against its truth."""
        result = self.result if result is None else result
        b = self.row(name) if b is None else b
        keep = result.mask[b]
        t = result.t[b, keep].numpy()
        p = result.position[b, keep].numpy()
        truth = self.truth[name]
        ref_t, ref_p = truth.t[0].numpy(), truth.position[0].numpy()
        ref = np.stack([np.interp(t, ref_t, ref_p[:, i]) for i in range(3)], 1)
        return t, np.linalg.norm(p - ref, axis=1)

    def codes(self, name: str) -> np.ndarray:
        b = self.row(name)
        return self.result.divergence[b, self.result.mask[b]].numpy()

    def same(self, a: str, b: str, tol: float = TOL) -> None:
        """Scenarios ``a`` and ``b`` gave the same estimates (real epochs)."""
        ia, ib = self.row(a), self.row(b)
        na, nb = int(self.result.mask[ia].sum()), int(self.result.mask[ib].sum())
        assert na == nb, (a, b, na, nb)
        for field in ("t", "position", "velocity", "rotation", "gyro_bias", "covariance"):
            x = getattr(self.result, field)[ia, :na]
            y = getattr(self.result, field)[ib, :nb]
            assert float((x - y).abs().max()) < tol, (a, b, field)


@pytest.fixture(scope="module")
def faults() -> Faults:
    """All scenarios in one batch. The all-sensor gap is cut from a second run (seed 12):
    its gap falls on a stretch where dead reckoning drifts tens of metres."""
    config = SimConfig(
        duration_s=40.0, imu_rate_hz=100.0, wheel_rate_hz=10.0, slip_episodes=0, gnss_outage_count=0
    )
    seq = simulate_run(config, seed=11).sequence
    other = simulate_run(config, seed=12).sequence
    scenarios = _scenarios(seq)
    scenarios["all_gap"] = _all_sensor_gap(other)
    truth = {name: seq.ground_truth for name in scenarios} | {"all_gap": other.ground_truth}
    names = list(scenarios)
    batch = batch_sequences([dataclasses.replace(s, names=[n]) for n, s in scenarios.items()])
    with torch.no_grad():
        result = run_eskf(batch, CFG)
    return Faults(seq, scenarios, truth, names, result)


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2)))


def test_every_output_is_finite(faults):
    result = faults.result
    for field in ("position", "velocity", "rotation", "gyro_bias", "accel_bias", "covariance"):
        finite = torch.isfinite(getattr(result, field).flatten(2)).all(-1) | ~result.mask
        bad = [n for n, ok in zip(faults.names, finite.all(-1), strict=True) if not ok]
        assert not bad, (field, bad)


def test_clean_row_equals_its_single_run(faults):
    single = run_eskf(faults.seq, CFG)
    b = faults.row("clean")
    n = single.t.shape[1]
    assert int(faults.result.mask[b].sum()) == n
    for field in ("position", "rotation", "covariance"):
        diff = (getattr(single, field)[0] - getattr(faults.result, field)[b, :n]).abs().max()
        assert float(diff) < TOL, field
    # the faults and resets of the other rows flagged nothing here
    assert not bool(faults.result.divergence[b].any())


def test_nonfinite_samples_are_skipped_like_missing_ones(faults):
    b = faults.row("nonfinite")
    dropped = {k: int(v[b]) for k, v in faults.result.dropped_samples.items()}
    assert dropped == {"imu": 7, "wheel": 2, "gnss": 1, "pose": 0}
    faults.same("nonfinite", "nonfinite_ref")
    assert not faults.codes("nonfinite").any()


def test_repeated_and_backwards_stamps_are_skipped(faults):
    b = faults.row("stamps")
    dropped = {k: int(v[b]) for k, v in faults.result.dropped_samples.items()}
    # 2 repeated + 1 overtaken IMU samples, 1 repeated wheel sample, 1 late GNSS fix
    assert dropped == {"imu": 3, "wheel": 1, "gnss": 1, "pose": 0}
    faults.same("stamps", "stamps_ref")


def test_imu_gap_is_bridged(faults):
    b = faults.row("imu_gap")
    gap_t = faults.result.t[b, faults.result.gap[b]]
    assert gap_t.numel() > 0 and float(gap_t.min()) > 12.0 and float(gap_t.max()) <= 15.1
    _, clean = faults.errors("clean")
    _, err = faults.errors("imu_gap")
    assert _rmse(err) < 1.5 * _rmse(clean)
    assert not faults.codes("imu_gap").any()


def _reset_and_recovery(faults: Faults, name: str) -> tuple[float, float, float]:
    """(time of the first reset, error then, largest error from 1 s after it on), s, m, m."""
    t, err = faults.errors(name)
    codes = faults.codes(name)
    reset = np.flatnonzero(codes != 0)
    assert reset.size >= 1 and (codes[reset] == NIS_BLOWUP).all(), (name, codes[reset])
    first = reset[0]
    return t[first], err[first], err[t >= t[first] + 1.0].max()


def test_all_sensor_gap_diverges_is_reset_and_recovers(faults):
    b = faults.row("all_gap")
    keep = faults.result.mask[b]
    t = faults.result.t[b, keep].numpy()
    assert not ((t > 10.0) & (t < 20.0)).any() and bool(faults.result.gap[b, keep][t == 20.0])
    # 10 s of blind propagation: the fixes after the gap disagree by far more than the
    # covariance admits; the NIS of the re-opened fix blows up: reset, inflated, and the
    # next fix pulls the estimate back
    when, before, after = _reset_and_recovery(faults, "all_gap")
    assert 20.0 < when < 26.0 and before > 10.0 and after < 2.0


def test_stuck_gyro_axis_is_detected_and_reset(faults):
    when, before, after = _reset_and_recovery(faults, "stuck_gyro")
    # the held z rate left a heading (and gyro-bias) error that outlives the fault
    assert when > 16.0 and before > 5.0 and after < 2.0


@pytest.mark.slow
def test_without_the_reset_both_stay_diverged(faults):
    """Reference: the same two runs with the NIS test off (scale 1e12) keep metres of error
    to the end, the re-opened fixes pulling them part of the way every few seconds."""
    pair = ["stuck_gyro", "all_gap"]
    batch = batch_sequences([dataclasses.replace(faults.scenarios[n], names=[n]) for n in pair])
    with torch.no_grad():
        off = run_eskf(batch, CFG.replace(divergence_nis_scale=1e12))
    for b, name in enumerate(pair):
        assert not bool(off.divergence[b].any())
        t_off, err_off = faults.errors(name, off, b)
        t_on, err_on = faults.errors(name)
        assert err_off[t_off > 36.5].min() > 2.0 * err_on[t_on > 36.5].max(), name


def test_missing_sensor_equals_a_run_without_the_stream(faults):
    b = faults.row("no_gnss")
    assert not bool(faults.result.present["gnss"][b].any())
    single = run_eskf(dataclasses.replace(faults.seq, gnss=None), CFG)
    n = single.t.shape[1]
    assert int(faults.result.mask[b].sum()) == n
    assert float((single.position[0] - faults.result.position[b, :n]).abs().max()) < TOL
    assert not faults.codes("no_gnss").any()


def test_one_gnss_fix_off_by_a_kilometre_is_rejected(faults):
    b = faults.row("jump_one")
    k = int(torch.nonzero(faults.result.t[b] >= 20.0)[0])
    assert bool(faults.result.present["gnss"][b, k])
    assert not bool(faults.result.accepted["gnss"][b, k])
    assert float(faults.result.nis["gnss"][b, k]) > 1e5
    # rejected = as if the fix were not there (up to the joint update's round-off)
    faults.same("jump_one", "jump_one_ref", tol=1e-6)
    assert not faults.codes("jump_one").any()


def test_eight_jumped_fixes_trip_the_guard_and_are_not_followed(faults):
    b = faults.row("jump_eight")
    keep = faults.result.mask[b]
    t, err = faults.errors("jump_eight")
    gnss = faults.result.present["gnss"][b, keep].numpy()
    accepted = faults.result.accepted["gnss"][b, keep].numpy()
    jumped = gnss & (t >= 20.0) & (t < 27.5)
    assert jumped.sum() == 8 and not accepted[jumped].any()
    # the 4th and 8th jumped fixes pass the re-opened gate: NIS blow-ups, each update
    # discarded (reset to the propagated state, covariance inflated)
    codes = faults.codes("jump_eight")
    np.testing.assert_array_equal(t[codes != 0], [23.0, 27.0])
    assert (codes[codes != 0] == NIS_BLOWUP).all()
    _, clean = faults.errors("clean")
    assert err.max() < 2.0 and _rmse(err) < 1.5 * _rmse(clean)


def test_overflowing_propagation_is_reset_to_the_last_good_state(faults):
    t, err = faults.errors("huge_gyro")
    codes = faults.codes("huge_gyro")
    assert (codes != 0).sum() == 1 and codes[codes != 0][0] & NONFINITE
    assert 15.0 <= t[codes != 0][0] <= 15.1 + 1e-9  # the epoch holding the 1e200 sample
    _, clean = faults.errors("clean")
    assert _rmse(err) < _rmse(clean) + 0.2


def test_indefinite_measurement_covariance_is_flagged_not_fused(faults):
    b = faults.row("bad_pose_cov")
    keep = faults.result.mask[b]
    codes = faults.codes("bad_pose_cov")
    t = faults.result.t[b, keep].numpy()
    pose = faults.result.present["pose"][b, keep].numpy()
    accepted = faults.result.accepted["pose"][b, keep].numpy()
    flagged = codes != 0
    np.testing.assert_array_equal(t[flagged], [22.0])  # the 11th pose, covariance -100 I
    assert (codes[flagged] & NOT_POSITIVE_DEFINITE).all() and pose[flagged].all()
    assert not accepted[flagged].any() and accepted.sum() == pose.sum() - 1
