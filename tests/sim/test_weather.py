"""Weather schedule, degradation models and degraded streams against closed forms and
Monte Carlo statistics (tolerances from the sample sizes)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.sensors.pose import pose_residual
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.weather import (
    CONDITIONS,
    DEFAULT_CONDITIONS,
    CameraModel,
    Environment,
    GnssModel,
    LidarModel,
    WeatherSchedule,
    WeatherSegment,
    WheelModel,
    apply_weather,
    draw_outages,
    extinction_coefficient,
    rain_extinction,
    weather_slip_config,
)


@pytest.fixture(scope="module")
def run():
    return simulate_run(SimConfig(duration_s=60.0), seed=11)


def _schedule() -> WeatherSchedule:
    return WeatherSchedule.from_boundaries(
        [0.0, 15.0, 30.0, 45.0, 60.0], ["fog", "night", "sunny", "snow"]
    )


# schedule -------------------------------------------------------------------------------------


def test_random_schedule_covers_the_run_without_overlap_and_is_seeded():
    for seed in range(30):
        duration = 50.0 + 7.0 * seed
        schedule = WeatherSchedule.random(duration, seed, mean_segment_s=20.0, min_segment_s=5.0)
        assert schedule == WeatherSchedule.random(
            duration, seed, mean_segment_s=20.0, min_segment_s=5.0
        )
        labels = schedule.labels()
        assert {f"weather:{c}" for c in CONDITIONS} <= labels.keys()
        rows = torch.cat([v[0] for v in labels.values()], 0).numpy()
        rows = rows[np.argsort(rows[:, 0])]
        assert rows[0, 0] == 0.0 and rows[-1, 1] == duration
        np.testing.assert_array_equal(rows[1:, 0], rows[:-1, 1])  # touching, no gap/overlap
        assert np.all(rows[:, 1] - rows[:, 0] >= 5.0 - 1e-12)
        names = [s.condition for s in schedule.segments]
        assert all(a != b for a, b in zip(names, names[1:], strict=False))
        for value in labels.values():
            assert value.dim() == 3 and value.shape[0] == 1 and value.shape[2] == 2
    assert WeatherSchedule.random(100.0, 1) != WeatherSchedule.random(100.0, 2)


def test_schedule_index_and_validation():
    schedule = _schedule()
    idx = schedule.index_at(np.array([0.0, 14.999, 15.0, 44.0, 60.0]))
    np.testing.assert_array_equal(idx, [0, 0, 1, 2, 3])
    for second in (12.0, 8.0):  # a gap, an overlap
        with pytest.raises(ValueError, match="gap or overlap"):
            WeatherSchedule(
                (WeatherSegment(0.0, 10.0, "rain"), WeatherSegment(second, 20.0, "fog"))
            )
    with pytest.raises(ValueError, match="start at 0"):
        WeatherSchedule.from_boundaries([1.0, 10.0], ["rain"])


# closed forms ---------------------------------------------------------------------------------


def test_extinction_koschmieder_kim_and_carbonneau_rain():
    vis = np.array([100.0, 700.0, 3000.0, 10000.0, 60000.0])
    np.testing.assert_allclose(extinction_coefficient(vis), 3.912023005428146 / vis, rtol=1e-15)
    q = np.array([0.0, 0.7 - 0.5, 0.16 * 3.0 + 0.34, 1.3, 1.6])  # Kim et al. 2001, V in km
    expected = 3.912023005428146 / vis * (905.0 / 550.0) ** (-q)
    np.testing.assert_allclose(extinction_coefficient(vis, 905.0), expected, rtol=1e-14)
    rate = np.array([1.0, 8.0, 25.0])
    # back to dB/km: 10 log10(exp(alpha * 1000 m))
    db_per_km = 10.0 * np.log10(np.exp(rain_extinction(rate) * 1000.0))
    np.testing.assert_allclose(db_per_km, 1.076 * rate**0.67, rtol=1e-13)
    both = extinction_coefficient(5000.0, 905.0, 8.0)
    np.testing.assert_allclose(both, extinction_coefficient(5000.0, 905.0) + rain_extinction(8.0))


def test_vo_features_and_sigma_follow_visibility_and_illuminance():
    cam = CameraModel()
    base = DEFAULT_CONDITIONS["sunny"]

    def by_hand(visibility: float, lux: float) -> float:
        signal = min(5000.0, 50.0 * lux)
        contrast = 0.1 * math.exp(-3.912023005428146 / visibility * 10.0)
        return 500.0 * math.exp(-5.0 * math.sqrt(signal + 9.0) / (contrast * signal))

    counts = {}
    for vis, lux in [(30.0, 2e4), (80.0, 2e4), (500.0, 2e4), (2e4, 2e4), (2e4, 10.0), (2e4, 1.0)]:
        cond = dataclasses.replace(base, visibility_m=vis, illuminance_lux=lux)
        counts[vis, lux] = cam.expected_features(cond)
        assert counts[vis, lux] == pytest.approx(by_hand(vis, lux), rel=1e-12)
    clear, fog = counts[2e4, 2e4], counts[30.0, 2e4]
    assert fog < counts[80.0, 2e4] < counts[500.0, 2e4] < clear
    sig_clear, sig_fog = cam.sigmas(np.array([clear, fog]))[0]
    assert sig_fog / sig_clear == pytest.approx(math.sqrt(clear / fog), rel=1e-12)
    assert sig_clear == pytest.approx(0.5 / math.sqrt(clear), rel=1e-12)


def test_lidar_range_loss_matches_the_attenuation_formula():
    lidar = LidarModel()
    ranges = []
    for alpha in [1e-5, 1e-3, 1e-2, 0.05, 0.3]:
        r_max = lidar.max_range(alpha)
        # received power of the reference target at R_max equals the clear-air threshold
        assert math.exp(-2.0 * alpha * r_max) / r_max**2 == pytest.approx(1.0 / 100.0**2, rel=1e-12)
        ranges.append(r_max)
        assert lidar.spurious_probability(alpha) == pytest.approx(1.0 - math.exp(-2.0 * alpha))
    assert np.all(np.diff(ranges) < 0) and ranges[0] == pytest.approx(100.0, rel=1e-3)
    assert lidar.max_range(0.0) == 100.0
    fog = DEFAULT_CONDITIONS["fog"]
    alpha = 3.912023005428146 / 80.0  # V < 500 m: q = 0, wavelength-independent
    r_max = lidar.max_range(alpha)
    expected = 400.0 * (1.0 - math.exp(-r_max / 20.0)) * math.exp(-2.0 * alpha)
    assert lidar.expected_points(fog) == pytest.approx(expected, rel=1e-12)


def test_corridor_covariance_largest_axis_is_the_corridor():
    lidar = LidarModel()
    rng = np.random.default_rng(0)
    axis = rng.normal(size=(50, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    points = rng.uniform(100.0, 400.0, 50)
    corridor = np.arange(50) % 2 == 0
    cov = lidar.position_covariance(points, axis, corridor)
    values, vectors = np.linalg.eigh(cov)
    base = 0.2**2 / points
    f = 0.02
    np.testing.assert_allclose(values[corridor, 2], base[corridor] / f, rtol=1e-12)
    across = base[corridor] * 2 / (1 - f)
    np.testing.assert_allclose(values[corridor, :2], np.stack((across, across), -1), rtol=1e-12)
    # inverse of the information H = n / sigma^2 (f a a^T + (1 - f) / 2 (I - a a^T))
    outer = axis[:, :, None] * axis[:, None, :]
    frac = np.where(corridor, f, 1.0 / 3.0)[:, None, None]
    info = (frac * outer + (1 - frac) / 2 * (np.eye(3) - outer)) / base[:, None, None]
    np.testing.assert_allclose(cov @ info, np.broadcast_to(np.eye(3), cov.shape), atol=1e-12)
    alignment = np.abs((vectors[corridor, :, 2] * axis[corridor]).sum(-1))
    np.testing.assert_allclose(alignment, 1.0, atol=1e-12)
    np.testing.assert_allclose(
        cov[~corridor] / base[~corridor, None, None],
        np.broadcast_to(3.0 * np.eye(3), cov[~corridor].shape),
        atol=1e-12,
    )


# emitted streams ----------------------------------------------------------------------------


def _residuals(run, stream, t: np.ndarray) -> np.ndarray:
    state = run.path.evaluate(t)
    residual, _ = pose_residual(
        torch.from_numpy(state.position),
        torch.from_numpy(state.rotation),
        stream.position[0],
        quat_to_matrix(stream.quaternion[0]),
    )
    return residual.numpy()


@pytest.mark.parametrize("unreported", [False, True])
def test_emitted_noise_matches_declared_covariance(run, unreported):
    env = Environment(corridors_s=((20.0, 40.0),))
    for source in ("vo", "lidar"):
        white, nees = [], []
        for seed in range(4):
            out = apply_weather(
                run, _schedule(), seed, environment=env, unreported_error=unreported
            )
            stream, truth = out.pose_sources[source], out.source_truth[source]
            if not unreported:
                np.testing.assert_array_equal(truth.error_scale, 1.0)
                np.testing.assert_array_equal(truth.clutter, 0.0)
            keep = stream.mask[0].numpy()
            noise = (_residuals(run, stream, truth.t) - truth.drift)[keep]
            np.testing.assert_allclose(noise, truth.noise[keep], atol=1e-9)
            # emitted = error_scale^2 x declared (the weather error the source cannot see)
            cov = stream.covariance[0].numpy()[keep] * truth.error_scale[keep, None, None] ** 2
            chol = np.linalg.cholesky(cov)
            w = np.linalg.solve(chol, noise[..., None])[..., 0]
            white.append(w)
            nees.append((w**2).sum(-1))
        w, e = np.concatenate(white), np.concatenate(nees)
        n = len(e)
        assert n > 1500
        # NEES ~ chi2(6): mean 6, variance 12
        assert abs(e.mean() - 6.0) < 4.0 * math.sqrt(12.0 / n), (source, e.mean())
        sample = w.T @ w / n  # whitened covariance ~ I: diag var 2/n, off-diag var 1/n
        assert np.all(np.abs(sample - np.eye(6)) < 4.5 * math.sqrt(2.0 / n)), source


def test_declared_covariances_follow_the_models(run):
    env = Environment(corridors_s=((20.0, 40.0),))
    out = apply_weather(run, _schedule(), 3, environment=env)
    vo, vo_truth = out.pose_sources["vo"], out.source_truth["vo"]
    keep = vo.mask[0].numpy()
    expected = 0.5**2 / vo_truth.count[keep]
    cov = vo.covariance[0].numpy()[keep]
    np.testing.assert_allclose(cov[:, :3, :3], expected[:, None, None] * np.eye(3), rtol=1e-12)
    lidar, li_truth = out.pose_sources["lidar"], out.source_truth["lidar"]
    inside = li_truth.corridor & lidar.mask[0].numpy()
    assert (
        inside.sum() > 150
        and not li_truth.corridor[(li_truth.t < 19.9) | (li_truth.t > 40.1)].any()
    )
    velocity = run.path.evaluate(li_truth.t[inside]).velocity[:, :2]
    heading = velocity / np.linalg.norm(velocity, axis=-1, keepdims=True)
    _, vectors = np.linalg.eigh(lidar.covariance[0].numpy()[inside, :3, :3])
    np.testing.assert_allclose(np.abs((vectors[:, :2, 2] * heading).sum(-1)), 1.0, atol=1e-9)


def test_drift_is_a_random_walk_in_distance(run):
    out = apply_weather(run, _schedule(), 5, unreported_error=True)
    for source, model in (("vo", CameraModel()), ("lidar", LidarModel())):
        truth = out.source_truth[source]
        state = run.path.evaluate(truth.t)
        ds = np.linalg.norm(np.diff(state.position, axis=0), axis=-1)
        step = np.diff(truth.drift, axis=0) / (np.sqrt(ds) * truth.error_scale[1:])[:, None]
        body_p = np.einsum("nji,nj->ni", state.rotation[1:], step[:, :3])
        z = np.concatenate(
            (
                body_p / model.drift_position_m_per_sqrt_m,
                step[:, 3:] / model.drift_rotation_rad_per_sqrt_m,
            ),
            0,
        ).reshape(-1)
        np.testing.assert_array_equal(truth.drift[0], 0.0)
        assert abs((z**2).mean() - 1.0) < 4.0 * math.sqrt(2.0 / z.size)
        assert abs(z.mean()) < 4.0 / math.sqrt(z.size)


def test_vo_error_scale_from_contrast_and_motion_blur():
    camera = CameraModel()
    a = camera.detection_cnr

    def inverse_cnr_squared(mean: float) -> float:  # E[1/(a + X)^2], X ~ Exp(mean), by quadrature
        return integrate.quad(lambda x: math.exp(-x / mean) / mean / (a + x) ** 2, 0, np.inf)[0]

    for mean in (0.005, 0.05, 0.7, 2.0, 7.0, 40.0):
        closed_form = camera.inverse_cnr_squared(mean)
        assert closed_form == pytest.approx(inverse_cnr_squared(mean), rel=1e-7)
    sunny, night = DEFAULT_CONDITIONS["sunny"], DEFAULT_CONDITIONS["night"]
    # clear daylight at rest is the calibration: k = 1; sunny (V = 20 km) barely above
    clear = dataclasses.replace(sunny, visibility_m=1e9)
    assert camera.error_scale(clear, np.zeros(1), np.zeros(1))[0] == pytest.approx(1.0, rel=1e-9)
    assert camera.error_scale(sunny, np.zeros(1), np.zeros(1))[0] == pytest.approx(1.0, rel=1e-3)
    # night: full exposure t_max, blur b = f (|w| + v / d) t_max px, box variance b^2 / 12
    speed, rate = np.array([0.0, 1.5, 1.5]), np.array([0.0, 0.0, 0.2])
    contrast = camera.inverse_cnr_squared(camera.mean_cnr(night)) / camera.inverse_cnr_squared(
        camera.mean_cnr(clear)
    )
    blur = 450.0 * (rate + speed / 10.0) * 0.03
    expected = np.sqrt(contrast + blur**2 / 12.0 / 0.3**2)
    np.testing.assert_allclose(camera.error_scale(night, speed, rate), expected, rtol=1e-12)
    assert camera.error_scale(night, speed, rate)[2] > 3.0  # several-fold at night in a turn


def test_lidar_clutter_error_scale_matches_least_squares_monte_carlo():
    lidar = LidarModel()
    fog = DEFAULT_CONDITIONS["fog"]
    alpha = lidar.extinction(fog)
    p_c = lidar.clutter_probability(alpha)
    assert p_c == pytest.approx(math.exp(-2.0 * alpha) * (1.0 - math.exp(-8.0 * alpha)), rel=1e-12)
    assert lidar.clutter_probability(0.0) == 0.0
    # equal-weight least squares of an offset from n_s surface points (sigma 0.2 m) and n_c
    # clutter points (sigma 1 m) vs the reported sigma_pt^2 / (n_s + n_c)
    rng = np.random.default_rng(0)
    n_s, n_c, trials = 260, 110, 20000
    residuals = np.concatenate(
        (rng.normal(0, 0.2, (trials, n_s)), rng.normal(0, 1.0, (trials, n_c))), 1
    )
    ratio = residuals.mean(1).var() / (0.2**2 / (n_s + n_c))
    k = float(lidar.error_scale(np.array([n_s]), np.array([n_c]))[0])
    assert abs(ratio - k**2) < 4.0 * k**2 * math.sqrt(2.0 / trials)
    assert lidar.error_scale(np.array([300.0]), np.array([0.0]))[0] == 1.0


def test_weather_error_scale_reaches_the_streams(run):
    schedule = WeatherSchedule.from_boundaries([0.0, 30.0, 60.0], ["night", "fog"])
    out = apply_weather(run, schedule, 1, unreported_error=True)
    vo, lidar = out.source_truth["vo"], out.source_truth["lidar"]
    assert np.median(vo.error_scale[vo.condition == 0]) > 2.0  # night: blur
    assert np.median(vo.error_scale[vo.condition == 1]) < 1.5
    assert np.median(lidar.error_scale[lidar.condition == 1]) > 2.0  # fog: clutter
    assert np.median(lidar.error_scale[lidar.condition == 0]) < 1.1
    fog = lidar.condition == 1
    p_c = LidarModel().clutter_probability(LidarModel().extinction(DEFAULT_CONDITIONS["fog"]))
    assert abs(lidar.clutter[fog].mean() - 400 * p_c) < 4.0 * math.sqrt(400 * p_c / fog.sum())


def test_dropouts_only_below_the_tracking_threshold(run):
    dim = {
        **DEFAULT_CONDITIONS,
        "night": dataclasses.replace(DEFAULT_CONDITIONS["night"], illuminance_lux=6.5),
        "fog": dataclasses.replace(DEFAULT_CONDITIONS["fog"], visibility_m=11.0),
    }
    schedule = WeatherSchedule.from_boundaries([0.0, 30.0, 60.0], ["night", "fog"])
    out = apply_weather(run, schedule, 2, conditions=dim)
    for source, threshold in (("vo", 30), ("lidar", 60)):
        stream, truth = out.pose_sources[source], out.source_truth[source]
        mask = stream.mask[0].numpy()
        np.testing.assert_array_equal(mask, truth.count >= threshold)
        assert 0 < mask.sum() < mask.size
        assert torch.all(stream.covariance[0][~stream.mask[0]] == 0.0)
    # VO dropout rate in the dim night: P(Poisson(n) < 30) within binomial tolerance
    truth = out.source_truth["vo"]
    night = truth.condition == 0
    p = stats.poisson.cdf(29, truth.expected_count[night][0])
    rate = (truth.count[night] < 30).mean()
    assert abs(rate - p) < 4.0 * math.sqrt(p * (1 - p) / night.sum())


def test_gnss_urban_multipath_is_student_t():
    run = simulate_run(SimConfig(duration_s=60.0, gnss_rate_hz=100.0), seed=4)
    model = GnssModel(urban_outage_rate_per_min=0.0)
    env = Environment(urban_s=((10.0, 60.0),))
    out = apply_weather(run, WeatherSchedule.constant("rain", 60.0), 1, environment=env, gnss=model)
    fixes, old = out.sequence.gnss, run.sequence.gnss
    t = fixes.t[0].numpy()
    urban = t >= 10.0
    state = run.path.evaluate(t)
    scale = np.array([1.5, 1.5, 3.0])
    z = ((fixes.position[0].numpy() - state.position) / scale)[urban].reshape(-1)
    tail = 2.0 * stats.t.sf(stats.t.ppf(0.975, 3), 3)  # 5 %
    p_hat = (np.abs(z) > stats.t.ppf(0.975, 3)).mean()
    assert abs(p_hat - tail) < 4.0 * math.sqrt(tail * (1 - tail) / z.size)
    # heavy tail: P(|t_3| > 5) matches; a Gaussian of the same variance (3) lies far outside
    tail5 = 2.0 * stats.t.sf(5.0, 3)
    gauss5 = 2.0 * stats.norm.sf(5.0 / math.sqrt(3.0))
    p_hat5 = (np.abs(z) > 5.0).mean()
    tol5 = 4.0 * math.sqrt(tail5 * (1 - tail5) / z.size)
    assert abs(p_hat5 - tail5) < tol5 and abs(p_hat5 - gauss5) > tol5
    np.testing.assert_allclose(
        fixes.sigma[0].numpy()[urban], np.broadcast_to(scale * math.sqrt(3.0), (urban.sum(), 3))
    )
    torch.testing.assert_close(fixes.position[:, ~urban], old.position[:, : (~urban).sum()])


def test_urban_outages_are_poisson_and_remove_fixes(run):
    rng = np.random.default_rng(7)
    counts = [len(draw_outages(((0.0, 600.0),), 0.5, 1e-3, rng)) for _ in range(400)]
    assert abs(np.mean(counts) - 5.0) < 4.0 * math.sqrt(5.0 / 400)
    model = GnssModel(urban_outage_rate_per_min=6.0, urban_outage_mean_s=3.0)
    out = apply_weather(
        run,
        WeatherSchedule.constant("sunny", 60.0),
        0,
        environment=Environment(urban_s=((5.0, 55.0),)),
        gnss=model,
    )
    outages = out.sequence.labels["gnss_outage"][0].numpy()
    assert len(outages) > 0
    t = out.sequence.gnss.t[0].numpy()
    for start, end in outages:
        assert not np.any((t >= start) & (t <= end))
        assert 5.0 <= start and end <= 55.0


def test_urban_outages_take_the_receivers_velocities_and_headings():
    """A receiver that loses its fixes in an urban outage loses its Doppler velocities and
    dual-antenna headings too; outside the outages they are the run's own samples."""
    run = simulate_run(SimConfig(duration_s=60.0, gnss_velocity=True, gnss_heading=True), seed=9)
    model = GnssModel(urban_outage_rate_per_min=6.0, urban_outage_mean_s=3.0)
    out = apply_weather(
        run,
        WeatherSchedule.constant("sunny", 60.0),
        0,
        environment=Environment(urban_s=((5.0, 55.0),)),
        gnss=model,
    )
    fixes = out.sequence.gnss.t[0]
    for name in ("gnss_velocity", "gnss_heading"):
        stream, before = getattr(out.sequence, name), getattr(run.sequence, name)
        torch.testing.assert_close(stream.t, fixes[None])  # the fixes' epochs, no others
        kept = torch.isin(before.t[0], fixes)
        for key, value in stream.tensors().items():
            torch.testing.assert_close(value, getattr(before, key)[:, kept])
    assert fixes.numel() < run.sequence.gnss.length


def test_wheel_slip_rate_and_ratio_distribution():
    wheel = WheelModel()
    for mu in (0.2, 0.5, 0.8):
        assert wheel.slip_rate_per_min(mu) == pytest.approx(2.0 * math.exp(-mu / 0.15))
        rng = np.random.default_rng(1)
        excess = rng.exponential(0.15, 20000)
        ratio = excess / (excess + mu)
        for p in (0.1, 0.5, 0.9):
            q = wheel.slip_ratio_quantile(mu, p)
            assert 1.0 - math.exp(-mu * q / ((1.0 - q) * 0.15)) == pytest.approx(p, rel=1e-12)
            assert abs((ratio <= q).mean() - p) < 4.0 * math.sqrt(p * (1 - p) / ratio.size)
    config = SimConfig(duration_s=600.0)
    schedule = WeatherSchedule.from_boundaries([0.0, 300.0, 600.0], ["snow", "rain"])
    lam = (2.0 * math.exp(-0.2 / 0.15) + 2.0 * math.exp(-0.5 / 0.15)) * 5.0
    counts = [weather_slip_config(config, schedule, s).slip_episodes for s in range(300)]
    assert abs(np.mean(counts) - lam) < 4.0 * math.sqrt(lam / 300)
    slip = weather_slip_config(config, schedule, 0)
    rates = np.array([2.0 * math.exp(-0.2 / 0.15), 2.0 * math.exp(-0.5 / 0.15)])
    mu_eff = (rates * [0.2, 0.5]).sum() / rates.sum()
    band = [-0.15 * math.log(1 - p) for p in (0.1, 0.9)]
    np.testing.assert_allclose(slip.slip_ratio, [y / (y + mu_eff) for y in band], rtol=1e-12)
    short = SimConfig(duration_s=60.0, slip_duration_s=(2.0, 3.0))
    busy = WheelModel(traction_event_rate_per_min=20.0)
    snowy = weather_slip_config(short, WeatherSchedule.constant("snow", 60.0), 3, wheel=busy)
    assert snowy.slip_episodes > 0
    episodes = simulate_run(snowy, 0).slip_episodes
    assert len(episodes) == snowy.slip_episodes
    spin_skid = [ep.ratio for ep in episodes if ep.kind != "lock"]
    assert all(snowy.slip_ratio[0] <= r <= snowy.slip_ratio[1] for r in spin_skid)


def test_deterministic_with_seed_and_sequence_contract(run):
    env = Environment(corridors_s=((5.0, 15.0),), urban_s=((20.0, 50.0),))
    a = apply_weather(run, _schedule(), 9, environment=env)
    b = apply_weather(run, _schedule(), 9, environment=env)
    c = apply_weather(run, _schedule(), 10, environment=env)
    for key in ("vo", "lidar"):
        for name, value in a.pose_sources[key].tensors().items():
            assert torch.equal(value, b.pose_sources[key].tensors()[name]), (key, name)
        assert not torch.equal(a.pose_sources[key].position, c.pose_sources[key].position)
    assert torch.equal(a.sequence.gnss.position, b.sequence.gnss.position)
    assert a.sequence.meta == b.sequence.meta
    seq = a.sequence
    seq.check()
    assert seq.poses is None  # both sources are fused as odometry from pose_sources
    assert seq.imu is run.sequence.imu and run.sequence.poses is None
    assert {"slip", "gnss_outage", "env:corridor", "env:urban"} <= seq.labels.keys()
    assert torch.equal(
        seq.labels["weather:night"], torch.tensor([[[15.0, 30.0]]], dtype=torch.float64)
    )
    assert apply_weather(run, _schedule(), 9, pose_source="vo").sequence.poses.t.shape == (1, 601)
    lidar = apply_weather(run, _schedule(), 9, pose_source="lidar").sequence
    assert lidar.poses is lidar.pose_sources["lidar"]
    with pytest.raises(ValueError, match="schedule covers"):
        apply_weather(run, WeatherSchedule.constant("rain", 30.0), 0)
    with pytest.raises(ValueError, match="urban_dof"):
        GnssModel(urban_dof=2.0)
    with pytest.raises(ValueError, match="no WeatherCondition"):
        apply_weather(run, WeatherSchedule.constant("hail", 60.0), 0)
