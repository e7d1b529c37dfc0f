"""The front end's shortcuts against the plain computations they replace.

* ``_conventional_covariance`` (structured ``T P T^T``) equals the dense product with the
  map of ``invariant_maps`` (no position arm: the filter's covariances are about their
  estimates' positions) on random estimates and covariances (1e-12), and its
  gradients pass ``gradcheck``.
* ``sanitize_sequence``: the finite-sum shortcut still drops exactly the non-finite samples,
  keeps finite samples whose sums overflow (1e308 + 1e308 = inf) and returns the input
  tensors when every sample is usable.
* ``build_schedule``: the held IMU samples (``Schedule.held_imu``, all epochs or a range)
  are the raw samples at the pieces' start times
  (zero-order hold, independent ``searchsorted`` reference), padding slots have ``dt = 0``,
  and an IMU gap's pieces carry ``imu_gap_noise_scale``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import _conventional_covariance
from msf_torch.frontend.guard import sanitize_sequence
from msf_torch.frontend.schedule import build_schedule
from msf_torch.geometry import so3
from msf_torch.geometry.invariant import invariant_maps
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import batch_sequences


def test_structured_covariance_map_equals_dense_product():
    gen = torch.Generator().manual_seed(5)
    n = 40
    velocity = 10.0 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    rotation = so3.exp(torch.randn(n, 3, generator=gen, dtype=torch.float64))
    root = torch.randn(n, 15, 15, generator=gen, dtype=torch.float64)
    cov = root @ root.mT
    # the filter's covariances are about their estimates' positions: no position arm
    to_conv, _ = invariant_maps(torch.zeros_like(velocity), velocity, rotation)
    dense = to_conv @ cov @ to_conv.mT
    fast = _conventional_covariance(velocity, rotation, cov)
    scale = float(dense.abs().max())
    assert float((fast - dense).abs().max()) < 1e-12 * scale
    # in-place block updates keep it differentiable (gradients reach estimate and cov)
    inputs = tuple(x[:2].clone().requires_grad_() for x in (velocity, rotation, cov))
    assert torch.autograd.gradcheck(_conventional_covariance, inputs)


def test_sanitize_shortcut_drops_exactly_the_non_finite_samples():
    seq = simulate_run(SimConfig(duration_s=3.0), seed=11).sequence
    clean, dropped = sanitize_sequence(seq)
    assert clean.imu.gyro is seq.imu.gyro and int(dropped["imu"].sum()) == 0

    accel = seq.imu.accel.clone()
    accel[0, 5, 0] = accel[0, 5, 1] = accel[0, 6, 2] = 1e308  # finite; sums overflow
    gyro = seq.imu.gyro.clone()
    gyro[0, 20, 2] = float("nan")
    gyro[0, 30, 0] = float("-inf")
    dirty = dataclasses.replace(seq, imu=dataclasses.replace(seq.imu, accel=accel, gyro=gyro))
    clean, dropped = sanitize_sequence(dirty)
    assert int(dropped["imu"][0]) == 2
    kept = clean.imu.mask[0]
    assert bool(kept[5]) and bool(kept[6]) and not bool(kept[20]) and not bool(kept[30])
    assert float(clean.imu.gyro[0, 20].abs().sum()) == 0.0  # dropped values zeroed


def test_schedule_holds_the_raw_samples_and_pads_with_zero_dt():
    cfg = EskfConfig()
    runs = [simulate_run(SimConfig(duration_s=4.0 + 3.0 * k), seed=30 + k).sequence for k in (0, 1)]
    imu = runs[1].imu
    mask = imu.mask.clone()
    mask[0, 100:130] = False  # a 0.3 s IMU gap in the second run
    runs[1] = dataclasses.replace(runs[1], imu=dataclasses.replace(imu, mask=mask))
    seq = batch_sequences(runs)
    sched = build_schedule(seq, cfg)
    gyro, accel = sched.held_imu()
    first, second = sched.held_imu(slice(3, 7))
    assert torch.equal(first, gyro[:, 3:7]) and torch.equal(second, accel[:, 3:7])
    for b in range(2):
        valid = seq.imu.mask[b].numpy()
        t = seq.imu.t[b].numpy()[valid]
        real = sched.dt[b] > 0
        start = (sched.t_end[b, :, None] - sched.dt[b].flip(-1).cumsum(-1).flip(-1))[real]
        held = np.searchsorted(t, start.numpy() + cfg.time_tolerance_s, side="right") - 1
        np.testing.assert_array_equal(gyro[b][real].numpy(), seq.imu.gyro[b].numpy()[valid][held])
        np.testing.assert_array_equal(accel[b][real].numpy(), seq.imu.accel[b].numpy()[valid][held])
        spacing = np.diff(t, append=t[-1])[held]
        expected_scale = np.where(spacing > cfg.imu_gap_s, cfg.imu_gap_noise_scale, 1.0)
        np.testing.assert_array_equal(sched.noise_scale[b][real].numpy(), expected_scale)
        assert bool((sched.noise_scale[b][~real] == 1.0).all())
        assert bool(sched.gap[b].any()) == (b == 1)
        total = float(sched.dt[b].sum())
        assert abs(total - (t[-1] - t[0])) < 1e-9
