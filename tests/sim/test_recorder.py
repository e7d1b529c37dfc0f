"""``sim.fill_imu_stretch``: the filled-in samples are exactly those the front end's
detector (``sensors.imu_gaps.interpolated_imu_samples``) flags, on the straight line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.sensors.imu_gaps import interpolated_imu_samples
from msf_torch.sim import SimConfig, fill_imu_stretch, simulate_run
from msf_torch.types import batch_sequences


def test_filled_samples_are_the_detected_stretch():
    seq = simulate_run(SimConfig(duration_s=10.0, slip_episodes=0), seed=2).sequence
    filled = fill_imu_stretch(seq, 3.0, 4.5)
    t = filled.imu.t[0]
    flags = interpolated_imu_samples(t, filled.imu.gyro[0], filled.imu.accel[0])
    expected = ((t > 3.0) & (t < 4.5)).numpy()
    assert np.array_equal(flags, expected) and int(flags.sum()) == 299  # 200 Hz, 1.5 s
    # midway: the mean of the two end samples; outside the stretch untouched
    a, b = int(torch.searchsorted(t, 3.0)), int(torch.searchsorted(t, 4.5))
    middle = (a + b) // 2
    mean = 0.5 * (seq.imu.gyro[0, a] + seq.imu.gyro[0, b])
    torch.testing.assert_close(filled.imu.gyro[0, middle], mean, rtol=0, atol=1e-12)
    assert torch.equal(filled.imu.accel[0, : a + 1], seq.imu.accel[0, : a + 1])
    assert filled.gnss is seq.gnss


def test_bad_input_is_refused():
    seq = simulate_run(SimConfig(duration_s=10.0, slip_episodes=0), seed=2).sequence
    with pytest.raises(ValueError, match="B = 2"):
        fill_imu_stretch(batch_sequences([seq, seq]), 3.0, 4.0)
    with pytest.raises(ValueError, match="no IMU samples to fill"):
        fill_imu_stretch(seq, 4.0, 3.0)
