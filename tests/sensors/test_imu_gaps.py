"""Filled-in IMU stretches (``sensors.imu_gaps``) and how the front end bridges them.

* A stretch of a noisy simulated IMU replaced by linear interpolation in time (jittered
  timestamps) is found sample for sample; plain noise, a stretch shorter than
  ``min_samples`` and ``min_samples = 0`` flag nothing.
* The KITTI drive of the gtsam wheel: its eight filled-in stretches (1257 samples); the real
  EuRoC V1_01 IMU (6001 samples): none, even for runs of 3.
* ``build_schedule`` gives the pieces held on those samples ``imu_gap_noise_scale`` and
  flags their epochs as gaps.
* ``msf run``'s summary names the stretch (count, seconds, start) and says so on stderr.
* Pure propagation (no measurements): the extra attitude variance the stretch adds equals
  the closed form ``3 (scale - 1) sigma_g^2 T`` (isotropic gyro noise keeps its trace under
  rotation).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.schedule import build_schedule
from msf_torch.sensors.imu_gaps import (
    filled_stretches,
    interpolated_imu_samples,
    open_stretch_start,
)
from msf_torch.sim import SimConfig, simulate_run


def _noisy_imu(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.cumsum(0.01 + 1e-4 * rng.standard_normal(n))
    gyro = 0.3 * np.sin(np.linspace(0.0, 6.0, n))[:, None] + 2e-3 * rng.standard_normal((n, 3))
    accel = np.array([0.0, 0.0, 9.81]) + 0.05 * rng.standard_normal((n, 3))
    return t, gyro, accel


def _fill(t, gyro, accel, first: int, last: int):
    """Replace samples first+1 .. last-1 by the line through samples first and last."""
    gyro, accel = gyro.copy(), accel.copy()
    frac = (t[first + 1 : last] - t[first]) / (t[last] - t[first])
    for x in (gyro, accel):
        x[first + 1 : last] = x[first] + (x[last] - x[first]) * frac[:, None]
    return gyro, accel


def test_filled_stretch_is_found_sample_for_sample():
    t, gyro, accel = _noisy_imu(2000, seed=3)
    gyro, accel = _fill(t, gyro, accel, 700, 855)
    flags = interpolated_imu_samples(t, gyro, accel)
    expected = np.zeros(2000, dtype=bool)
    expected[701:855] = True
    np.testing.assert_array_equal(flags, expected)
    as_tensors = interpolated_imu_samples(
        torch.from_numpy(t), torch.from_numpy(gyro), torch.from_numpy(accel)
    )
    np.testing.assert_array_equal(as_tensors, expected)


def test_noise_short_stretches_and_switch_off_flag_nothing():
    t, gyro, accel = _noisy_imu(2000, seed=4)
    assert not interpolated_imu_samples(t, gyro, accel).any()
    short_gyro, short_accel = _fill(t, gyro, accel, 100, 110)  # 9 interior samples
    assert not interpolated_imu_samples(t, short_gyro, short_accel, min_samples=10).any()
    assert interpolated_imu_samples(t, short_gyro, short_accel, min_samples=9).sum() == 9
    long_gyro, long_accel = _fill(t, gyro, accel, 100, 400)
    assert not interpolated_imu_samples(t, long_gyro, long_accel, min_samples=0).any()
    with pytest.raises(ValueError, match="min_samples"):
        interpolated_imu_samples(t, gyro, accel, min_samples=-1)


def test_kitti_drive_has_eight_filled_stretches():
    pytest.importorskip("gtsam")
    from msf_torch.io import load_sequence

    seq = load_sequence("kitti-gtsam")
    keep = seq.imu.mask[0]
    t = seq.imu.t[0, keep].numpy()
    flags = interpolated_imu_samples(t, seq.imu.gyro[0, keep], seq.imu.accel[0, keep])
    starts, _ = filled_stretches(flags)
    assert int(flags.sum()) == 1257 and starts.size == 8
    assert np.any(np.abs(t[starts] - t[0] - 278.99) < 0.01)  # the turn at 279-280.5 s


def test_real_euroc_imu_has_none():
    pytest.importorskip("gtsam")
    from msf_torch.io.eqvio import load_eqvio

    imu = load_eqvio().imu  # EuRoC V1_01, 6001 samples at 200 Hz
    keep = imu.mask[0]
    flags = interpolated_imu_samples(imu.t[0, keep], imu.gyro[0, keep], imu.accel[0, keep], 3)
    assert int(keep.sum()) == 6001 and not flags.any()


def _run_with_filled_stretch(seed: int = 12):
    run = simulate_run(SimConfig(duration_s=8.0), seed=seed).sequence
    imu = run.imu
    n = int(imu.mask[0].sum())
    t = imu.t[0, :n].numpy()
    first, last = 300, 455
    gyro, accel = _fill(t, imu.gyro[0, :n].numpy(), imu.accel[0, :n].numpy(), first, last)
    new_gyro, new_accel = imu.gyro.clone(), imu.accel.clone()
    new_gyro[0, :n] = torch.from_numpy(gyro)
    new_accel[0, :n] = torch.from_numpy(accel)
    seq = dataclasses.replace(
        run, imu=dataclasses.replace(imu, gyro=new_gyro, accel=new_accel), wheel=None, gnss=None
    )
    return seq, t, first, last


def test_schedule_treats_the_filled_stretch_as_a_gap():
    seq, t, first, last = _run_with_filled_stretch()
    cfg = EskfConfig(nhc="off", zupt=False)
    sched = build_schedule(seq, cfg)
    real = sched.dt[0] > 0
    start = (sched.t_end[0, :, None] - sched.dt[0].flip(-1).cumsum(-1).flip(-1))[real].numpy()
    held = np.searchsorted(t, start + cfg.time_tolerance_s, side="right") - 1
    filled = (held > first) & (held < last)
    scale = sched.noise_scale[0][real].numpy()
    np.testing.assert_array_equal(scale, np.where(filled, cfg.imu_gap_noise_scale, 1.0))
    assert bool(sched.gap[0].any())
    off = build_schedule(seq, dataclasses.replace(cfg, imu_interpolated_min_samples=0))
    assert bool((off.noise_scale[0] == 1.0).all()) and not bool(off.gap[0].any())


def test_added_attitude_variance_matches_closed_form():
    seq, t, first, last = _run_with_filled_stretch()
    # the isotropic multiplier alone (the held sample's random walk off)
    base = EskfConfig(
        nhc="off",
        zupt=False,
        init_yaw_sigma_rad=0.05,
        imu_gap_gyro_rw_density=[0.0] * 3,
        imu_gap_accel_rw_density=[0.0] * 3,
    )
    with torch.no_grad():
        on = run_eskf(seq, base)
        off = run_eskf(seq, dataclasses.replace(base, imu_interpolated_min_samples=0))
    extra = float(
        torch.diagonal(on.covariance[0, -1, 6:9, 6:9]).sum()
        - torch.diagonal(off.covariance[0, -1, 6:9, 6:9]).sum()
    )
    duration = t[last] - t[first + 1]
    expected = 3.0 * (base.imu_gap_noise_scale - 1.0) * base.gyro_noise_density**2 * duration
    assert extra == pytest.approx(expected, rel=1e-6)
    assert bool(on.gap[0].any()) and not bool(off.gap[0].any())


def test_run_summary_reports_the_filled_stretch(tmp_path):
    from msf_torch.runner import RunOptions, run_sequence

    seq, t, first, last = _run_with_filled_stretch()
    cfg = EskfConfig(nhc="off", zupt=False)
    summary = run_sequence(seq, cfg, RunOptions(out_dir=tmp_path, plot=False))
    stretch = summary["imu_filled_stretches"]
    assert stretch["count"] == 1
    assert stretch["seconds"] == pytest.approx(t[last] - t[first], abs=1e-3)
    assert stretch["start_s"] == [pytest.approx(t[first] - t[0], abs=1e-3)]
    assert summary["imu_gaps"] > 0


def test_msf_run_says_so_on_stderr(tmp_path, capsys):
    from msf_torch.cli import main
    from msf_torch.io.native import write_native

    seq, _, _, _ = _run_with_filled_stretch()
    path = write_native(seq, tmp_path / "filled.npz")
    args = ["run", str(path), "--out", str(tmp_path / "out"), "--no-plot", "--progress", "off"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "msf run: 1 IMU stretch(es)" in err and "bridged as IMU gaps" in err


def test_open_stretch_start_finds_a_line_running_to_the_end():
    rng = np.random.default_rng(4)
    t = np.arange(50) * 0.01
    gyro, accel = rng.normal(size=(50, 3)), rng.normal(size=(50, 3)) + 9.8
    assert open_stretch_start(t, gyro, accel) is None  # noise: no line
    for start in (0, 20, 47):  # the line from sample `start` through the last
        g, a = gyro.copy(), accel.copy()
        frac = (t[start:] - t[start]) / (t[-1] - t[start])
        g[start:] = g[start] + (g[-1] - g[start]) * frac[:, None] * 0.5
        a[start:] = a[start] + (a[-1] - a[start]) * frac[:, None] * 0.5
        assert open_stretch_start(t, g, a) == start
        # a stretch that ended before the last sample is not open
        g[-1] += 0.3
        assert open_stretch_start(t, g, a) is None
    assert open_stretch_start(t[:2], gyro[:2], accel[:2]) is None
