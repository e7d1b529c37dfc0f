"""A simulated run survives the native CSV writer and reader (as datasets/make_sample.py uses)."""

from __future__ import annotations

import pytest
import torch

from msf_torch.sim import ImuNoiseSpec, sample_slip_config, simulate_run

native = pytest.importorskip("msf_torch.io.native")


def test_simulated_run_native_roundtrip(tmp_path):
    config = sample_slip_config(
        duration_s=40.0,
        slip_episodes=2,
        slip_margin_s=(5.0, 5.0),
        gnss_outage_duration_s=(10.0, 10.0),
    )
    run = simulate_run(config, 7)
    folder = native.write_native(run.sequence, tmp_path / "run")
    back = native.read_native(folder)
    for name, stream in run.sequence.streams().items():
        other = getattr(back, name)
        for key, value in stream.tensors().items():
            torch.testing.assert_close(getattr(other, key), value, rtol=0, atol=1e-15)
    for key, value in run.sequence.labels.items():
        assert torch.equal(back.labels[key], value)
    sensor = back.meta["sensor"]
    assert sensor["slip_types"] == run.sequence.meta["sensor"]["slip_types"]
    assert ImuNoiseSpec(**back.meta["imu_noise"]) == config.imu_noise
