"""Magnetometer heading in the front end: the residual against the simulator's truth, the
disturbance tests against its labelled anomalies, the initial yaw, the fused run against
the same run without the magnetometer, batches and pieces."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state, magnetometer_yaw
from msf_torch.frontend.schedule import (
    disturbed_field,
    gyro_attitude,
    median_dip,
    rotation_inconsistent,
    undisturbed_magnetometer,
)
from msf_torch.frontend.stream import EskfStream, concat_results, time_slice
from msf_torch.geometry import so3
from msf_torch.sensors.magnetometer import (
    corrected_field,
    field_dip,
    magnetometer_heading_residual,
    magnetometer_heading_variance,
)
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import batch_sequences

DTYPE = torch.float64
DECLINATION = 0.2
HARD = (12.0, -7.0, 4.0)
DISTORTION = (1.05, 0.02, 0.0, 0.02, 0.96, 0.01, 0.0, 0.01, 1.0)


def _sim(seed: int, **overrides) -> object:
    config = SimConfig(
        duration_s=overrides.pop("duration_s", 60.0),
        magnetometer=True,
        magnetometer_declination_rad=DECLINATION,
        magnetometer_hard_iron_uT=HARD,
        magnetometer_distortion=DISTORTION,
        **overrides,
    )
    return simulate_run(config, seed)


def _config(run, **overrides) -> EskfConfig:
    base = config_for_sequence(EskfConfig(), run.sequence.meta, set())
    soft = np.linalg.inv(np.reshape(DISTORTION, (3, 3))).reshape(-1).tolist()
    return dataclasses.replace(
        base,
        magnetometer_declination_rad=DECLINATION,
        magnetometer_hard_iron_uT=list(HARD),
        magnetometer_soft_iron=soft,
        **overrides,
    )


def test_corrected_residual_is_zero_at_the_truth():
    """Noise-free readings, corrected with the inverse distortion, point at the declination
    and the simulated dip at every sample (closed form of the sim's field model)."""
    run = _sim(3, duration_s=20.0, magnetometer_sigma_uT=1e-9)
    seq, truth = run.sequence, run.truth
    cfg = _config(run)
    index = torch.searchsorted(truth.t[0], seq.magnetometer.t[0])
    rotation = truth.rotation[0, index]
    soft = torch.tensor(cfg.magnetometer_soft_iron, dtype=DTYPE).reshape(3, 3)
    field = corrected_field(seq.magnetometer.field[0], torch.tensor(HARD, dtype=DTYPE), soft)
    residual, _ = magnetometer_heading_residual(rotation, field, DECLINATION)
    assert float(residual.abs().max()) < 1e-8
    dip = field_dip(rotation, field)
    assert float((dip - SimConfig().magnetometer_inclination_rad).abs().max()) < 1e-8
    torch.testing.assert_close(
        field.norm(dim=-1), torch.full_like(dip, SimConfig().magnetometer_field_uT)
    )


def test_variance_closed_form():
    """sigma^2 / H^2 + floor^2 with H the field's horizontal magnitude in the world."""
    rotation = so3.exp(torch.tensor([[0.1, -0.2, 1.0]], dtype=DTYPE))
    field = torch.tensor([[20.0, 5.0, -40.0]], dtype=DTYPE)
    world = rotation[0] @ field[0]
    expected = 0.5**2 / float(world[0] ** 2 + world[1] ** 2) + 0.03**2
    got = magnetometer_heading_variance(rotation, field, 0.5, 0.03)
    assert float(got) == pytest.approx(expected, rel=1e-12)


def test_magnitude_test_by_hand():
    """Readings 10 % off the local magnitude are disturbed, 5 % off are not; the median
    of the run is the reference when the config gives none."""
    cfg = EskfConfig(magnetometer_field_tolerance=0.08)
    direction = np.array([0.6, 0.0, -0.8])
    field = np.outer([50.0, 50.0, 50.0, 52.5, 45.0, 50.0], direction)
    np.testing.assert_array_equal(
        disturbed_field(field, cfg), [False, False, False, False, True, False]
    )
    cfg = dataclasses.replace(cfg, magnetometer_field_uT=45.0)
    np.testing.assert_array_equal(
        disturbed_field(field, cfg), [True, True, True, True, False, True]
    )


def test_zero_and_nan_readings_are_disturbed():
    """A sensor that reads zeros (no hard iron configured, the local field from the run's
    median) or a NaN reading under the mask gives no direction: disturbed, so that the
    initial yaw and the filter go on without it; one NaN does not spoil the median."""
    field = np.array([[30.0, 0.0, -40.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 2.0], [0.0, 30, -40]])
    cfg = EskfConfig()
    np.testing.assert_array_equal(disturbed_field(field, cfg), [False, True, True, False])
    np.testing.assert_array_equal(disturbed_field(np.zeros((3, 3)), cfg), [True] * 3)
    run = _sim(11, duration_s=15.0)
    stream = run.sequence.magnetometer
    seq = dataclasses.replace(
        run.sequence,
        gnss=None,
        wheel=None,
        magnetometer=dataclasses.replace(stream, field=torch.zeros_like(stream.field)),
    )
    cfg = dataclasses.replace(_config(run), magnetometer_hard_iron_uT=[0.0, 0.0, 0.0])
    _, cov = initial_state(seq, cfg)
    assert math.sqrt(float(cov[0, 8, 8])) == cfg.init_yaw_sigma_unknown_rad
    result = run_eskf(seq, cfg)
    assert int(result.accepted["magnetometer"].sum()) == 0
    assert bool(torch.isfinite(result.position).all())


def test_disturbance_detection_against_the_labels():
    """On runs past simulated anomalies the gyro-consistency and magnitude tests catch
    >= 90 % of the readings labelled disturbed; on clean runs they flag <= 1 % beyond the
    first second (which cannot be judged)."""
    caught, labelled, false, clean = 0, 0, 0, 0
    for seed in (100, 101, 103):
        for anomalies in (0, 6):
            run = _sim(seed, duration_s=90.0, magnetometer_anomaly_count=anomalies)
            seq = run.sequence
            cfg = _config(run)
            t = seq.magnetometer.t[0].numpy()
            field = seq.magnetometer.field[0].numpy()
            sigma = seq.magnetometer.sigma[0].numpy()
            attitude = gyro_attitude(seq.imu.t[0].numpy(), seq.imu.gyro[0].numpy(), t)
            flagged = rotation_inconsistent(t, field, sigma, attitude, cfg) | disturbed_field(
                field, cfg
            )
            inside = np.zeros(t.size, dtype=bool)
            for start, end in seq.labels.get("magnetic_anomaly", torch.zeros(1, 0, 2))[0]:
                inside |= (t >= float(start)) & (t <= float(end))
            caught += int((flagged & inside).sum())
            labelled += int(inside.sum())
            if anomalies == 0:
                judged = t >= t[0] + 0.5 * cfg.magnetometer_consistency_s / 6
                false += int(flagged[judged].sum())
                clean += int(judged.sum())
    assert labelled > 1000
    assert caught >= 0.9 * labelled, (caught, labelled)
    assert false <= 0.01 * clean, (false, clean)


def test_gyro_consistency_on_rough_terrain_and_fast_turns():
    """A clean run turning at up to 1 rad/s over 8-degree terrain of 10-30 m wavelength at
    3 m/s: the body turns about changing axes, and the gyro-consistency test (through
    ``undisturbed_magnetometer``) keeps >= 99 % of the judged readings (the rotation-vector
    difference of the gyro's integral flagged a third of them)."""
    run = _sim(
        5,
        duration_s=60.0,
        terrain_slope_deg=8.0,
        terrain_wavelength_m=(10.0, 30.0),
        mean_speed_mps=3.0,
        turn_rate_peak_rad_s=1.0,
    )
    seq = run.sequence
    cfg = _config(run, magnetometer_field_uT=SimConfig().magnetometer_field_uT)
    imu_t = seq.imu.t[0].numpy()
    t = seq.magnetometer.t[0].numpy()
    kept, _ = undisturbed_magnetometer(
        seq.magnetometer, 0, cfg, imu_t, seq.imu.gyro[0].numpy(), t, np.arange(t.size)
    )
    judged = int((t >= t[0] + cfg.magnetometer_consistency_s / 6).sum())
    assert kept.size >= 0.99 * judged, (kept.size, judged)
    # the relative rotation is the truth's (gyro noise and bias over 1 s aside)
    truth = run.truth
    rows = torch.searchsorted(truth.t[0], torch.from_numpy(t[[200, 250]])).numpy()
    rotation = truth.rotation[0, rows].numpy()
    attitude = gyro_attitude(imu_t, seq.imu.gyro[0].numpy(), t[[200, 250]])
    error = so3.log(
        torch.from_numpy((attitude[0].T @ attitude[1]) @ (rotation[0].T @ rotation[1]).T)
    )
    assert float(error.norm()) < 0.02


def test_median_dip_is_the_inclination():
    run = _sim(5, duration_s=30.0)
    seq = run.sequence
    index = torch.searchsorted(seq.imu.t[0], seq.magnetometer.t[0])
    dip = median_dip(
        seq.magnetometer.field[0].numpy(), seq.imu.accel[0, index].numpy(), _config(run)
    )
    assert dip == pytest.approx(SimConfig().magnetometer_inclination_rad, abs=0.02)


def test_initial_yaw_from_the_magnetometer_alone():
    """Without GNSS and wheels the compass sets the yaw: errors within 3 sigma, and a
    sigma far below the unknown-heading prior."""
    z = []
    for seed in range(8):
        run = _sim(200 + seed, duration_s=15.0)
        seq = dataclasses.replace(run.sequence, gnss=None, wheel=None)
        cfg = _config(run)
        state, cov = initial_state(seq, cfg)
        error = float(so3.log(run.truth.rotation[0, 0].mT @ state.rotation[0])[2])
        z.append(error / math.sqrt(float(cov[0, 8, 8])))
        assert math.sqrt(float(cov[0, 8, 8])) < 0.1
    assert max(abs(x) for x in z) < 3.0, z


def test_initial_yaw_carried_back_over_uneven_ground():
    """Rough terrain at 3 m/s, turning up to 1 rad/s, no reading before 5 s (a start beside
    steel): the compass yaw carried back to the first sample (given its true tilt) stays
    within 3 sigma on 8 seeds (the heading-only carry-back levelled the late reading with
    the first sample's tilt: errors to 0.7 rad, 9 sigma)."""
    z = []
    for seed in range(300, 308):
        run = _sim(
            seed,
            duration_s=12.0,
            terrain_slope_deg=8.0,
            terrain_wavelength_m=(10.0, 30.0),
            mean_speed_mps=3.0,
            turn_rate_peak_rad_s=1.0,
        )
        stream = run.sequence.magnetometer
        seq = dataclasses.replace(
            run.sequence,
            magnetometer=dataclasses.replace(stream, mask=stream.mask & (stream.t >= 5.0)),
        )
        first = run.truth.rotation[0, 0].numpy()
        roll = math.atan2(first[2, 1], first[2, 2])
        pitch = -math.asin(first[2, 0])
        measured = magnetometer_yaw(
            seq, 0, seq.imu.t[0].numpy(), seq.imu.gyro[0].numpy(), roll, pitch, _config(run)
        )
        assert measured is not None
        error = math.remainder(measured[0] - math.atan2(first[1, 0], first[0, 0]), math.tau)
        z.append(error / math.sqrt(measured[1]))
    assert max(abs(x) for x in z) < 3.0, z


def test_wrong_declination_warns_at_initialisation():
    run = _sim(7, duration_s=40.0)
    cfg = dataclasses.replace(_config(run), magnetometer_declination_rad=DECLINATION + 1.0)
    with pytest.warns(UserWarning, match="magnetometer gives a yaw"):
        initial_state(run.sequence, cfg)


def _yaw_and_outage(run, result) -> tuple[float, float]:
    truth = run.truth
    index = torch.searchsorted(truth.t[0], result.t[0]).clamp(max=truth.t.shape[1] - 1)
    yaw = so3.log(truth.rotation[0, index].mT @ result.rotation[0])[:, 2]
    error = (result.position[0] - truth.position[0, index]).norm(dim=-1)
    outage = (result.t[0] > 30.0) & (result.t[0] < 50.0)
    return float(yaw.pow(2).mean().sqrt()), float(error[outage].max())


def test_magnetometer_holds_the_heading_through_an_outage():
    """IMU + GNSS (no wheels) with a 20-s outage, 6 seeds: the magnetometer lowers the yaw
    RMS on every seed (by 4-6x) and the median of the largest outage errors (the outage's
    drift also comes from velocity and accelerometer bias: 2 of 6 seeds drift more), and
    the heading stays consistent."""
    outages_with, outages_without = [], []
    for seed in range(100, 106):
        run = _sim(seed, duration_s=70.0, gnss_outages_s=((30.0, 50.0),))
        seq = dataclasses.replace(run.sequence, wheel=None)
        cfg = _config(run)
        with_mag = run_eskf(seq, cfg)
        without = run_eskf(dataclasses.replace(seq, magnetometer=None), cfg)
        yaw_with, outage_with = _yaw_and_outage(run, with_mag)
        yaw_without, outage_without = _yaw_and_outage(run, without)
        outages_with.append(outage_with)
        outages_without.append(outage_without)
        assert yaw_with < 0.5 * yaw_without, (seed, yaw_with, yaw_without)
        accepted = with_mag.accepted["magnetometer"].sum()
        assert int(accepted) >= 0.95 * int(with_mag.present["magnetometer"].sum())
        truth = run.truth
        index = torch.searchsorted(truth.t[0], with_mag.t[0]).clamp(max=truth.t.shape[1] - 1)
        yaw_error = so3.log(truth.rotation[0, index].mT @ with_mag.rotation[0])[:, 2]
        z = yaw_error / with_mag.covariance[0, :, 8, 8].sqrt()
        assert float((z.abs() < 1.96).double().mean()) >= 0.9
    assert np.median(outages_with) < 0.75 * np.median(outages_without)


def test_batch_equals_single_runs():
    runs = [_sim(11, duration_s=20.0), _sim(12, duration_s=14.0, magnetometer_rate_hz=25.0)]
    cfg = _config(runs[0])
    singles = [run_eskf(r.sequence, cfg) for r in runs]
    batch = run_eskf(batch_sequences([r.sequence for r in runs]), cfg)
    for b, single in enumerate(singles):
        n = single.t.shape[1]
        torch.testing.assert_close(batch.position[b, :n], single.position[0], rtol=0, atol=1e-9)
        torch.testing.assert_close(batch.rotation[b, :n], single.rotation[0], rtol=0, atol=1e-9)


def test_pieces_equal_one_run_with_fixed_references():
    """With the local field given and the gyro-consistency test off, a run filtered in
    pieces fuses the same readings as in one piece (rate bins on the absolute clock)."""
    run = _sim(13, duration_s=24.0)
    cfg = _config(
        run,
        magnetometer_field_uT=SimConfig().magnetometer_field_uT,
        magnetometer_inclination_rad=SimConfig().magnetometer_inclination_rad,
        magnetometer_consistency_s=0.0,
    )
    whole = run_eskf(run.sequence, cfg)
    stream = EskfStream(cfg, initial=initial_state(run.sequence, cfg))
    for start, end in ((0.0, 8.0), (8.0, 16.0), (16.0, 24.01)):
        stream.push(time_slice(run.sequence, start, end))
    joined = concat_results(stream.results)
    real = whole.t[0, whole.mask[0]]
    index = torch.searchsorted(joined.t[0], real)
    assert torch.equal(joined.t[0, index], real)
    # the bias estimates differ by round-off between the pieces' epochs (tests/frontend/
    # test_stream.py: 1.2e-5 m with the biases estimated)
    torch.testing.assert_close(
        joined.position[0, index], whole.position[0, whole.mask[0]], rtol=0, atol=1e-4
    )
    assert int(joined.accepted["magnetometer"].sum()) == int(whole.accepted["magnetometer"].sum())


def test_declination_calibrated_online():
    """The config's declination 0.2 rad off (the sim's is 0.2): uncalibrated the heading is
    pulled off (yaw RMS > 0.1 rad on most seeds); calibrated from 0 with a 0.3-rad prior the
    estimate ends within 3 sigma of 0.2 and the yaw RMS below 0.03 rad."""
    for seed in (100, 103):
        run = _sim(seed, duration_s=70.0, gnss_outages_s=((40.0, 55.0),))
        wrong = dataclasses.replace(_config(run), magnetometer_declination_rad=0.0)
        calibrated = dataclasses.replace(wrong, calibrate_magnetometer_declination=True)
        off = run_eskf(run.sequence, wrong)
        result = run_eskf(run.sequence, calibrated)
        column = result.calibration_names.index("declination_rad:magnetometer")
        estimate = float(result.calibration[0, -1, column])
        sigma = float(result.calibration_covariance[0, -1, column, column]) ** 0.5
        assert abs(estimate - DECLINATION) < 3.0 * sigma, (seed, estimate, sigma)
        assert sigma < 0.01
        assert _yaw_and_outage(run, result)[0] < 0.03
        assert _yaw_and_outage(run, off)[0] > 0.1


def test_initial_yaw_combines_an_agreeing_compass_and_drops_a_disagreeing_one():
    """With the GNSS track's heading known, a compass within 3 sigma is combined with it
    (the variance below both), one 0.6 rad off is not used (the track's yaw and variance,
    with a warning)."""
    run = _sim(7, duration_s=40.0)
    cfg = _config(run)
    _, cov_track = initial_state(dataclasses.replace(run.sequence, magnetometer=None), cfg)
    compass = dataclasses.replace(run.sequence, gnss=None, wheel=None)
    _, cov_compass = initial_state(compass, cfg)
    state, cov = initial_state(run.sequence, cfg)
    assert float(cov[0, 8, 8]) < min(float(cov_track[0, 8, 8]), float(cov_compass[0, 8, 8]))
    error = float(so3.log(run.truth.rotation[0, 0].mT @ state.rotation[0])[2])
    assert abs(error) < 3.0 * math.sqrt(float(cov[0, 8, 8]))
    wrong = dataclasses.replace(cfg, magnetometer_declination_rad=DECLINATION + 0.6)
    track_state, _ = initial_state(dataclasses.replace(run.sequence, magnetometer=None), wrong)
    with pytest.warns(UserWarning, match="the initial yaw keeps the other heading"):
        state, cov = initial_state(run.sequence, wrong)
    torch.testing.assert_close(state.rotation, track_state.rotation, rtol=0, atol=1e-12)
    assert float(cov[0, 8, 8]) == pytest.approx(float(cov_track[0, 8, 8]), rel=1e-12)


def test_short_pieces_of_a_live_stream_fuse_the_magnetometer():
    """A run pushed to ``EskfStream`` in 0.4-s pieces (shorter than the gyro test's
    shortest lag, 0.5 s): the pieces after the first pass the readings the test cannot
    judge on to the gate, so they fuse what the run in one piece fuses (before, none: every
    reading of a piece was unjudged and left out)."""
    run = _sim(14, duration_s=12.0)
    cfg = _config(
        run,
        magnetometer_field_uT=SimConfig().magnetometer_field_uT,
        magnetometer_inclination_rad=SimConfig().magnetometer_inclination_rad,
    )
    whole = run_eskf(run.sequence, cfg)
    stream = EskfStream(cfg, initial=initial_state(run.sequence, cfg))
    bounds = np.arange(0.0, 12.01, 0.4)
    for start, end in zip(bounds[:-1], bounds[1:], strict=True):
        stream.push(time_slice(run.sequence, float(start), float(end) + (end > 11.9) * 0.01))
    joined = concat_results(stream.results)
    fused_whole = int(whole.accepted["magnetometer"].sum())
    fused_pieces = int(joined.accepted["magnetometer"].sum())
    assert fused_whole >= 20
    # the first piece's readings are unjudged (the run's start) and left out, as in one piece
    assert fused_whole - 1 <= fused_pieces <= fused_whole + 1, (fused_pieces, fused_whole)
    real = whole.t[0, whole.mask[0]]
    index = torch.searchsorted(joined.t[0], real)
    assert torch.equal(joined.t[0, index], real)
    difference = (joined.position[0, index] - whole.position[0, whole.mask[0]]).norm(dim=-1)
    assert float(difference.max()) < 0.01
