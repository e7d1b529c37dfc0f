"""The simulator's sensors, labels, presets and determinism."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from msf_torch.sim import (
    SLIP_TYPES,
    ImuNoiseSpec,
    SimConfig,
    default_slip_config,
    gnss_denied_slip_config,
    sample_slip_config,
    simulate_run,
)

IDEAL_WHEELS = {
    "encoder_ticks_per_rev": None,
    "wheel_speed_noise_mps": 0.0,
    "wheel_scale_sigma": 0.0,
}


def _tensors(run) -> dict[str, torch.Tensor]:
    out = {}
    for name, stream in run.sequence.streams().items():
        for key, value in stream.tensors().items():
            out[f"{name}.{key}"] = value
    for key, value in run.sequence.labels.items():
        out[f"labels.{key}"] = value
    for f in dataclasses.fields(run.truth):
        out[f"truth.{f.name}"] = getattr(run.truth, f.name)
    return out


def _inside(t: np.ndarray, intervals: np.ndarray) -> np.ndarray:
    hit = np.zeros(t.shape, dtype=bool)
    for start, end in intervals:
        hit |= (t >= start) & (t <= end)
    return hit


def test_same_seed_bit_identical_different_seed_differs():
    config = default_slip_config(
        duration_s=40.0, slip_episodes=2, gnss_outage_count=1, gnss_outage_duration_s=(5.0, 10.0)
    )
    a, b, c = simulate_run(config, 5), simulate_run(config, 5), simulate_run(config, 6)
    ta, tb, tc = _tensors(a), _tensors(b), _tensors(c)
    assert ta.keys() == tb.keys()
    for key in ta:
        assert torch.equal(ta[key], tb[key]), key
    assert a.sequence.meta == b.sequence.meta
    assert not torch.equal(ta["imu.gyro"], tc["imu.gyro"])
    assert not torch.equal(ta["truth.position"], tc["truth.position"])
    assert not torch.equal(ta["labels.slip"], tc["labels.slip"])


def test_streams_are_independent_of_other_settings():
    base = default_slip_config(duration_s=40.0, slip_episodes=2)
    quiet = dataclasses.replace(base, imu_noise=ImuNoiseSpec.zero(), gnss_sigma_vertical_m=0.1)
    a, b = simulate_run(base, 9), simulate_run(quiet, 9)
    assert torch.equal(a.truth.position, b.truth.position)
    assert torch.equal(a.sequence.labels["slip"], b.sequence.labels["slip"])
    assert torch.equal(a.sequence.wheel.left_speed, b.sequence.wheel.left_speed)


def test_shapes_dtypes_and_meta():
    run = simulate_run(
        sample_slip_config(duration_s=60.0, slip_episodes=3, slip_margin_s=(5.0, 5.0)), 2
    )
    seq = run.sequence
    seq.check()
    n = int(60.0 * 200) + 1
    assert seq.imu.gyro.shape == (1, n, 3) and seq.imu.gyro.dtype == torch.float64
    assert seq.wheel.t.shape == (1, 60 * 25)
    assert run.truth.rotation.shape == (1, n, 3, 3)
    assert run.truth.slip_mask_imu.shape == (1, n) and run.truth.slip_mask_imu.dtype == torch.bool
    assert seq.labels["slip"].shape == (1, 3, 2)
    assert seq.labels["gnss_outage"].shape[::2] == (1, 2)
    sensor = seq.meta["sensor"]
    assert sensor["imu_model"] == "ADIS16470"
    assert sorted(sensor["slip_types"]) == sorted(SLIP_TYPES)
    assert sensor["gnss_sigma_m"] == [0.5, 0.5, 1.0]
    assert seq.meta["sim"]["seed"] == 2
    json.dumps(seq.meta)  # plain values only
    assert (
        SimConfig.from_dict({k: v for k, v in seq.meta["sim"].items() if k != "seed"}) == run.config
    )
    # monotonic time stamps
    for stream in seq.streams().values():
        assert bool((stream.t[0, 1:] > stream.t[0, :-1]).all())


def test_ideal_wheels_reproduce_forward_speed_and_yaw_rate():
    config = SimConfig(duration_s=30.0, **IDEAL_WHEELS)
    run = simulate_run(config, 4)
    wheel = run.sequence.wheel
    left, right = wheel.left_speed[0].numpy(), wheel.right_speed[0].numpy()
    state = run.path.evaluate(wheel.t[0].numpy())
    np.testing.assert_allclose(0.5 * (left + right), state.speed, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        (right - left) / config.wheel_track_m, state.angular_velocity[:, 2], rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(left, run.wheel_truth.left_speed[0].numpy())


def test_encoder_quantisation_and_scale_error():
    config = SimConfig(duration_s=30.0, wheel_speed_noise_mps=0.0, wheel_scale_sigma=0.01)
    run = simulate_run(config, 4)
    wheel = run.sequence.wheel
    dt = 1.0 / config.wheel_rate_hz
    tick = 2 * math.pi * config.wheel_radius_m / config.encoder_ticks_per_rev
    scale = 1.0 + run.truth.wheel_scale_error[0].numpy()
    measured = torch.stack((wheel.left_speed[0], wheel.right_speed[0]), -1).numpy()
    # readings are whole ticks per interval
    counts = measured * dt / tick
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    # they follow the scaled true speed at mid-interval within one tick per interval
    mid = run.path.evaluate(wheel.t[0].numpy() - 0.5 * dt)
    half = 0.5 * config.wheel_track_m * mid.angular_velocity[:, 2]
    expected = np.stack((mid.speed - half, mid.speed + half), -1) * scale
    assert np.abs(measured - expected).max() < tick / dt + 1e-3
    # and no tick is lost: the cumulative distance is within one tick of the truth
    fine_t = np.linspace(0.0, wheel.t[0, -1].item(), 30001)
    fine = run.path.evaluate(fine_t)
    half = 0.5 * config.wheel_track_m * fine.angular_velocity[:, 2]
    rim = np.stack((fine.speed - half, fine.speed + half), -1) * scale
    travelled = (0.5 * (rim[1:] + rim[:-1]) * np.diff(fine_t)[:, None]).sum(0)  # trapezoid
    assert np.all(np.abs(measured.sum(0) * dt - travelled) <= tick + 1e-6)


def test_slip_labels_cover_departures():
    config = default_slip_config(duration_s=120.0, slip_episodes=6, **IDEAL_WHEELS)
    run = simulate_run(config, 21)
    seq = run.sequence
    labels = seq.labels["slip"][0].numpy()
    assert labels.shape == (6, 2)
    assert np.all(np.diff(labels[:, 0]) > 0)
    assert np.all(labels[1:, 0] - labels[:-1, 1] >= config.slip_min_gap_s - 1e-9)
    durations = labels[:, 1] - labels[:, 0]
    assert np.all((durations >= 2.0) & (durations <= 6.0))
    t = seq.wheel.t[0].numpy()
    true = np.stack((run.wheel_truth.left_speed[0], run.wheel_truth.right_speed[0]), -1)
    meas = np.stack((seq.wheel.left_speed[0], seq.wheel.right_speed[0]), -1)
    departs = np.abs(meas - true) > 1e-9
    inside = _inside(t, labels)
    assert not departs[~inside].any()
    kinds = seq.meta["sensor"]["slip_types"]
    assert set(kinds) == set(SLIP_TYPES)
    for k, (start, end) in enumerate(labels):
        core = (t > start + config.slip_ramp_s) & (t < end - config.slip_ramp_s)
        ratio = meas[core] / true[core]
        episode = seq.meta["slip_episodes"][k]
        assert episode["kind"] == kinds[k]
        if kinds[k] == "spin":
            assert np.all(ratio > 1.0 + config.slip_ratio[0] - 1e-9)
        elif kinds[k] == "lock":
            assert np.all(ratio < 1.0 - config.lock_ratio[0] + 1e-9)
        else:
            moved = np.abs(ratio - 1.0) > config.slip_ratio[0] - 1e-9
            side = 0 if episode["wheel"] == "left" else 1
            assert moved[:, side].all() and not moved[:, 1 - side].any()
    # the IMU-rate slip mask is the label intervals
    mask = run.truth.slip_mask_imu[0].numpy()
    np.testing.assert_array_equal(mask, _inside(run.truth.t[0].numpy(), labels))


def test_gnss_outages_lever_arm_and_noise():
    lever = (0.3, -0.2, 1.1)
    config = SimConfig(
        duration_s=100.0,
        gnss_rate_hz=5.0,
        gnss_sigma_horizontal_m=0.0,
        gnss_sigma_vertical_m=0.0,
        gnss_lever_arm_m=lever,
        gnss_outages_s=((20.0, 35.0), (60.0, 61.5)),
    )
    run = simulate_run(config, 8)
    gnss = run.sequence.gnss
    t = gnss.t[0].numpy()
    outages = run.sequence.labels["gnss_outage"][0].numpy()
    np.testing.assert_array_equal(outages, [[20.0, 35.0], [60.0, 61.5]])
    assert not _inside(t, outages).any()
    assert len(t) == 501 - 76 - 8
    state = run.path.evaluate(t)
    expected = state.position + state.rotation @ np.asarray(lever)
    np.testing.assert_allclose(gnss.position[0].numpy(), expected, atol=1e-12)

    noisy = simulate_run(SimConfig(duration_s=600.0, gnss_rate_hz=10.0, imu_rate_hz=10.0), 8)
    error = (
        noisy.sequence.gnss.position[0].numpy()
        - noisy.path.evaluate(noisy.sequence.gnss.t[0].numpy()).position
    )
    np.testing.assert_allclose(error.std(0), [0.5, 0.5, 1.0], rtol=0.05)
    np.testing.assert_array_equal(noisy.sequence.gnss.sigma[0, 0].numpy(), [0.5, 0.5, 1.0])


def test_imu_noise_statistics_match_densities():
    config = SimConfig(duration_s=120.0)
    run = simulate_run(config, 13)
    spec = config.imu_noise
    dt = 1.0 / config.imu_rate_hz
    sig_g, sig_a = spec.white_sigmas(dt)
    step_g, step_a = spec.bias_step_sigmas(dt)
    tr = run.truth
    white_g = (run.sequence.imu.gyro - tr.angular_velocity - tr.gyro_bias)[0].numpy()
    white_a = (run.sequence.imu.accel - tr.specific_force - tr.accel_bias)[0].numpy()
    np.testing.assert_allclose(white_g.std(0), sig_g, rtol=0.03)
    np.testing.assert_allclose(white_a.std(0), sig_a, rtol=0.03)
    assert np.abs(white_g.mean(0)).max() < 4 * sig_g / math.sqrt(len(white_g))
    np.testing.assert_allclose(np.diff(tr.gyro_bias[0].numpy(), axis=0).std(0), step_g, rtol=0.03)
    np.testing.assert_allclose(np.diff(tr.accel_bias[0].numpy(), axis=0).std(0), step_a, rtol=0.03)
    # white noise is white: lag-1 autocorrelation near zero
    lag1 = (white_g[1:] * white_g[:-1]).mean(0) / white_g.var(0)
    assert np.abs(lag1).max() < 0.03


def test_turn_on_bias_spread():
    spec = ImuNoiseSpec.adis16470()
    config = SimConfig(duration_s=0.05, gnss_rate_hz=100.0)
    runs = [simulate_run(config, s).truth for s in range(300)]
    bg = np.stack([truth.gyro_bias[0, 0].numpy() for truth in runs])
    ba = np.stack([truth.accel_bias[0, 0].numpy() for truth in runs])
    np.testing.assert_allclose(bg.std(), spec.gyro_bias_sigma0, rtol=0.1)
    np.testing.assert_allclose(ba.std(), spec.accel_bias_sigma0, rtol=0.1)


def test_adis16470_numbers():
    spec = ImuNoiseSpec.adis16470()
    assert spec.gyro_noise_density == pytest.approx(0.34 * math.pi / 180 / 60)
    assert spec.accel_noise_density == pytest.approx(0.037 / 60)
    assert spec.gyro_bias_rw_density == pytest.approx(8 * math.pi / 180 / 3600 / 10)
    assert spec.accel_bias_rw_density == pytest.approx(13e-6 * 9.80665 / 10)
    # a random walk of this density drifts by the in-run stability over tau = 100 s
    assert spec.gyro_bias_rw_density * math.sqrt(100) == pytest.approx(8 * math.pi / 180 / 3600)


def test_sample_config_outage_contains_a_slip_episode():
    run = simulate_run(sample_slip_config(), 7)
    labels = run.sequence.labels
    outage = labels["gnss_outage"][0].numpy()
    slips = labels["slip"][0].numpy()
    assert outage.shape == (1, 2)
    assert outage[0, 1] - outage[0, 0] == pytest.approx(30.0)
    assert any(outage[0, 0] <= s0 and s1 <= outage[0, 1] for s0, s1 in slips)
    assert sorted(run.sequence.meta["sensor"]["slip_types"]) == sorted(SLIP_TYPES)


def test_gnss_denied_preset():
    config = gnss_denied_slip_config(duration_s=120.0, gnss_available_s=25.0, slip_episodes=4)
    run = simulate_run(config, 1)
    t = run.sequence.gnss.t[0].numpy()
    assert t.max() < 25.0 and len(t) == 25
    assert run.sequence.labels["slip"][0, 0, 0].item() >= 30.0
    periodic = gnss_denied_slip_config(duration_s=120.0, reacquire_period_s=40.0)
    t = simulate_run(periodic, 1).sequence.gnss.t[0].numpy()
    assert ((t > 25.0) & (t < 60.0)).sum() == 0 and ((t > 60.0) & (t < 65.0)).sum() == 4


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"duration_s": 0.0}, "duration_s"),
        ({"slip_ratio": (0.8, 0.3)}, "slip_ratio"),
        ({"slip_types": ("drift",)}, "slip_types"),
        ({"speed_variation": 0.9}, "0.3"),
        ({"slip_episodes": 30}, "do not fit"),
        ({"gnss_outage_count": 2, "gnss_outage_over_slip": True}, "gnss_outage_over_slip"),
        ({"gnss_outages_s": ((5.0, 1.0),)}, r"gnss_outages_s\[0\]"),
    ],
)
def test_bad_config_raises(overrides, match):
    with pytest.raises(ValueError, match=match):
        simulate_run(SimConfig(**{"duration_s": 60.0, **overrides}), 0)


def test_bad_seed_raises():
    with pytest.raises(ValueError, match="seed"):
        simulate_run(SimConfig(duration_s=1.0), -1)
