"""Multi-model source-fault detection (``frontend.gating``) and its use in the ESKF.

References: scipy's normal distribution (two-tailed Z-test), filterpy's linear Kalman filter
(the UKF on a linear model), a fine quadrature of a constant twist (the increment model),
the analytic sigmoid derivative and finite differences (straight-through gradients), and
the simulator's fault labels (a run with an injected LiDAR fault). Seeds here: 0-9; the
benchmark (``benchmarks/faults.py``) uses 1000+, and the defaults were chosen on 100-179.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy import special, stats

from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.gating import (
    MerweSigmaPoints,
    SourceFaultParams,
    detect_source_faults,
    source_increment_model,
    straight_through_gate,
    two_tailed_p_value,
    ukf_predict,
    ukf_update,
    window_z_scores,
    z_threshold,
)
from msf_torch.frontend.schedule import build_schedule
from msf_torch.geometry import so3
from msf_torch.runner import write_diagnostics
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.faults import SourceFault, inject_faults, pair_labels
from msf_torch.sim.weather import WeatherSchedule, apply_weather

DTYPE = torch.float64


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --- Z-test ----------------------------------------------------------------------------------


def test_two_tailed_p_value_and_threshold_match_scipy():
    z = torch.linspace(-7.0, 7.0, 141, dtype=DTYPE)
    expected = 2.0 * stats.norm.sf(np.abs(z.numpy()))
    np.testing.assert_allclose(two_tailed_p_value(z).numpy(), expected, rtol=1e-12)
    for alpha in (0.3, 0.05, 1e-3, 1e-6):
        threshold = z_threshold(alpha)
        assert threshold == pytest.approx(math.sqrt(2.0) * special.erfcinv(alpha), rel=1e-12)
        assert float(two_tailed_p_value(torch.tensor(threshold, dtype=DTYPE))) == pytest.approx(
            alpha, rel=1e-9
        )
    with pytest.raises(ValueError, match="alpha"):
        z_threshold(1.5)


def test_window_z_scores_are_standardised_sums_and_standard_normal_under_no_fault():
    gen = torch.Generator().manual_seed(0)
    variances = torch.rand(2000, 10, 3, generator=gen, dtype=DTYPE) * 4.0 + 0.1
    residuals = torch.randn(2000, 10, 3, generator=gen, dtype=DTYPE) * variances.sqrt()
    variances[:, 7:] = 0.0  # empty slots (a window not yet full)
    residuals[:, 7:] = 0.0
    z = window_z_scores(residuals, variances)
    k = 4
    hand = residuals[:, : k + 1].sum(1) / variances[:, : k + 1].sum(1).sqrt()
    torch.testing.assert_close(z[:, k], hand, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(z[:, 9], z[:, 6])  # empty slots add nothing
    for k in (0, 3, 6):  # each Z_k is N(0, 1): Kolmogorov-Smirnov against scipy's normal
        assert stats.kstest(z[:, k].flatten().numpy(), "norm").pvalue > 0.01
    assert torch.equal(
        window_z_scores(torch.zeros(2, 3, 1), torch.zeros(2, 3, 1)), torch.zeros(2, 3, 1)
    )


# --- UKF -------------------------------------------------------------------------------------


def test_ukf_equals_the_kalman_filter_on_a_linear_model():
    """The unscented transform is exact for linear maps: the UKF is the KF (filterpy)."""
    gen = torch.Generator().manual_seed(1)
    batch, n, m = 3, 4, 2
    transition = torch.eye(n, dtype=DTYPE) + 0.1 * torch.randn(
        batch, n, n, generator=gen, dtype=DTYPE
    )
    observation = torch.randn(batch, m, n, generator=gen, dtype=DTYPE)
    root_q = 0.3 * torch.randn(batch, n, n, generator=gen, dtype=DTYPE)
    root_r = 0.5 * torch.randn(batch, m, m, generator=gen, dtype=DTYPE)
    q = root_q @ root_q.mT + 1e-3 * torch.eye(n, dtype=DTYPE)
    r = root_r @ root_r.mT + 1e-2 * torch.eye(m, dtype=DTYPE)
    mean = torch.randn(batch, n, generator=gen, dtype=DTYPE)
    cov = torch.eye(n, dtype=DTYPE).repeat(batch, 1, 1) * 2.0
    refs = []
    for b in range(batch):
        kf = KalmanFilter(dim_x=n, dim_z=m)
        kf.x, kf.P = mean[b].numpy().copy(), cov[b].numpy().copy()
        kf.F, kf.H = transition[b].numpy(), observation[b].numpy()
        kf.Q, kf.R = q[b].numpy(), r[b].numpy()
        refs.append(kf)
    sigma = MerweSigmaPoints(alpha=0.5, beta=2.0, kappa=1.0)
    for _ in range(15):
        z = torch.randn(batch, m, generator=gen, dtype=DTYPE)
        mean, cov = ukf_predict(mean, cov, lambda x: x @ transition.mT, q, sigma)
        upd = ukf_update(mean, cov, z, lambda x: x @ observation.mT, r, sigma)
        for b, kf in enumerate(refs):
            kf.predict()
            innovation = z[b].numpy() - kf.H @ kf.x
            kf.update(z[b].numpy())
            np.testing.assert_allclose(upd.innovation[b].numpy(), innovation, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(upd.innovation_cov[b].numpy(), kf.S, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(upd.mean[b].numpy(), kf.x, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(upd.cov[b].numpy(), kf.P, rtol=1e-9, atol=1e-10)
        mean, cov = upd.mean, upd.cov


def test_ukf_equals_filterpy_ukf_on_the_increment_model():
    """On the detector's own nonlinear model (random walk, ``h`` = the mid-frame increment
    of a fast turn) the batched UKF follows filterpy's UnscentedKalmanFilter with the same
    scaled sigma points; a nonlinear ``h`` also tests the centre point's covariance weight."""
    gen = torch.Generator().manual_seed(7)
    dt = torch.tensor([[0.5]], dtype=DTYPE)
    sigma = MerweSigmaPoints(alpha=0.5, beta=2.0, kappa=1.0)

    def observe(points: torch.Tensor) -> torch.Tensor:
        return source_increment_model(points, dt.expand(*points.shape[:-2], 1))

    def hx(x: np.ndarray) -> np.ndarray:
        return observe(torch.as_tensor(x)[None, None])[0, 0].numpy()

    ref = UnscentedKalmanFilter(
        6, 6, 0.1, hx, lambda x, _: x, MerweScaledSigmaPoints(6, alpha=0.5, beta=2.0, kappa=1.0)
    )
    ref.x = np.array([2.0, 0.3, 0.0, 0.2, -0.4, 1.5])
    ref.P = np.diag([0.5, 0.5, 0.2, 0.3, 0.3, 0.6])
    ref.Q = 0.01 * np.eye(6)
    ref.R = np.diag([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    mean, cov = torch.as_tensor(ref.x)[None], torch.as_tensor(ref.P)[None]
    for _ in range(10):
        z = torch.as_tensor(hx(ref.x)) + 0.2 * torch.randn(6, generator=gen, dtype=DTYPE)
        mean, cov = ukf_predict(mean, cov, lambda x: x, torch.as_tensor(ref.Q)[None], sigma)
        upd = ukf_update(mean, cov, z[None], observe, torch.as_tensor(ref.R)[None], sigma)
        ref.predict()
        ref.update(z.numpy())
        np.testing.assert_allclose(upd.innovation[0].numpy(), ref.y, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(upd.innovation_cov[0].numpy(), ref.S, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(upd.mean[0].numpy(), ref.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(upd.cov[0].numpy(), ref.P, rtol=1e-9, atol=1e-12)
        mean, cov = upd.mean, upd.cov


def test_increment_model_is_the_mid_frame_chord_of_a_constant_twist():
    gen = torch.Generator().manual_seed(2)
    velocity = torch.randn(6, 3, generator=gen, dtype=DTYPE)
    rate = (
        torch.randn(6, 3, generator=gen, dtype=DTYPE)
        * torch.tensor([3.0, 1.0, 0.3, 1e-2, 1e-4, 0.0], dtype=DTYPE)[:, None]
    )
    dt = torch.full((6, 1), 0.25, dtype=DTYPE)
    model = source_increment_model(torch.cat((velocity, rate), -1)[:, None], dt)[:, 0]
    steps = 4000  # midpoint rule for the chord of p(s) = int_0^s Exp(w u) v du
    u = (torch.arange(steps, dtype=DTYPE) + 0.5) / steps * 0.25
    turns = so3.exp(rate[:, None] * u[None, :, None])  # (6, steps, 3, 3)
    chord = (turns @ velocity[:, None, :, None])[..., 0].mean(1)  # Delta p / dt, start frame
    mid = so3.exp(0.5 * rate * dt)
    expected = (mid.mT @ chord[..., None])[..., 0]
    torch.testing.assert_close(model[:, :3], expected, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(model[:, 3:], rate)


# --- straight-through gate ------------------------------------------------------------------


def test_straight_through_gate_is_hard_forward_and_sigmoid_backward():
    margin = torch.linspace(-3.0, 3.0, 13, dtype=DTYPE, requires_grad=True)
    hard = (margin > 0.4).to(DTYPE)  # any 0/1 decision
    out = straight_through_gate(hard, margin, 0.7)
    assert torch.equal(out.detach(), hard)
    (grad,) = torch.autograd.grad(out.sum(), margin)
    soft = torch.sigmoid(margin.detach() / 0.7)
    torch.testing.assert_close(grad, soft * (1.0 - soft) / 0.7, rtol=1e-12, atol=1e-14)


# --- the detector on synthetic sources ------------------------------------------------------


def _synthetic(freeze: tuple[int, int] | None, seed: int = 3, epochs: int = 120):
    """Two sources at 10 Hz seeing the same manoeuvring motion (speed steps 1 -> 2.5 -> 1 m/s
    and a 0.5 rad/s turn) with independent white noise; the second optionally frozen
    (zero motion) over the epoch range ``freeze``."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.arange(1, epochs + 1, dtype=DTYPE)[None] * 0.1
    speed = torch.ones(epochs, dtype=DTYPE)
    speed[40:60] = 2.5
    rate_z = torch.zeros(epochs, dtype=DTYPE)
    rate_z[70:90] = 0.5
    velocity = torch.zeros(1, epochs, 2, 3, dtype=DTYPE)
    velocity[..., 0] = speed[None, :, None]
    rate = torch.zeros(1, epochs, 2, 3, dtype=DTYPE)
    rate[..., 2] = rate_z[None, :, None]
    sigma_v, sigma_w = 0.1, 0.01
    velocity = velocity + sigma_v * torch.randn(velocity.shape, generator=gen, dtype=DTYPE)
    rate = rate + sigma_w * torch.randn(rate.shape, generator=gen, dtype=DTYPE)
    if freeze is not None:
        velocity[:, freeze[0] : freeze[1], 1] = 0.0
        rate[:, freeze[0] : freeze[1], 1] = 0.0
    eye = torch.eye(3, dtype=DTYPE).expand(1, epochs, 2, 3, 3)
    dt = torch.full((1, epochs, 2), 0.1, dtype=DTYPE)
    mask = torch.ones(1, epochs, 2, dtype=torch.bool)
    return t, velocity, rate, sigma_v**2 * eye, sigma_w**2 * eye, dt, mask


def test_a_frozen_source_is_excluded_and_a_shared_manoeuvre_is_not_a_fault():
    calm = detect_source_faults(*_synthetic(None))
    assert not bool(calm.flagged.any())  # speed steps and the turn move both sources
    out = detect_source_faults(*_synthetic((95, 110)))
    flagged = out.flagged[0, :, 1]
    assert not bool(flagged[:95].any()) and not bool(out.flagged[0, :, 0].any())
    assert bool(flagged[97:110].all())  # within two samples of the onset, to the end
    assert not bool(flagged[113:].any())  # released within three samples of the end
    assert torch.equal(out.weight, (~out.flagged).to(DTYPE))
    # one source alone has no peer to disagree with
    t, vel, rate, cov_v, cov_w, dt, mask = _synthetic((95, 110))
    alone = detect_source_faults(
        t,
        vel[:, :, 1:],
        rate[:, :, 1:],
        cov_v[:, :, 1:],
        cov_w[:, :, 1:],
        dt[:, :, 1:],
        mask[:, :, 1:],
    )
    assert not bool(alone.flagged.any())


def test_batch_equals_each_sequence_alone():
    one = _synthetic((30, 50), seed=4)
    two = _synthetic((80, 100), seed=5)
    two = (two[0],) + tuple(x.clone() for x in two[1:])
    two[-1][:, 60:70, 0] = False  # a gap in the first source of the second run
    both = detect_source_faults(*(torch.cat((a, b), 0) for a, b in zip(one, two, strict=True)))
    for b, single in enumerate((detect_source_faults(*one), detect_source_faults(*two))):
        assert torch.equal(both.flagged[b], single.flagged[0])
        torch.testing.assert_close(both.z[b], single.z[0], rtol=1e-12, atol=1e-12)
    assert bool(both.flagged[0, 32:50, 1].all()) and bool(both.flagged[1, 82:100, 1].all())


def test_batch_member_without_pairs_at_an_epoch_is_not_moved_by_the_others():
    """Three sources, the second frozen; the first run has no pair at all at every other
    epoch of its fault while the second run has pairs at every epoch. The excluded model is
    re-synchronised only at its own run's epochs: its Z scores equal those of the run alone
    (a sync at the other run's epochs used to change them by up to 0.7)."""

    def three(freeze, seed):
        x, y = _synthetic(freeze, seed=seed), _synthetic(None, seed=seed + 100)
        pairs = zip(x, y, strict=True)
        return [u if u.dim() == 2 else torch.cat((u, v[:, :, :1]), 2) for u, v in pairs]

    gappy = three((30, 60), 4)
    gappy[-1] = gappy[-1].clone()
    gappy[-1][:, 33:58:2] = False
    both = detect_source_faults(
        *(torch.cat((a, b), 0) for a, b in zip(gappy, three(None, 5), strict=True))
    )
    alone = detect_source_faults(*gappy)
    assert bool(alone.flagged[0, 32:60, 1].all())
    assert torch.equal(both.flagged[0], alone.flagged[0])
    torch.testing.assert_close(both.z[0], alone.z[0], rtol=1e-12, atol=1e-12)


def test_weight_gradient_is_the_surrogate_gradient():
    """d(sum of weights)/d(noise scale) by autograd equals central finite differences of the
    surrogate sum(sigmoid((z_gate - z) / tau)), decisions held (they do not flip)."""
    t, vel, rate, cov_v, cov_w, dt, mask = _synthetic((60, 80), seed=6)
    params = SourceFaultParams()

    def run(scale: torch.Tensor):
        return detect_source_faults(t, vel, rate, scale * cov_v, scale * cov_w, dt, mask, params)

    scale = torch.tensor(1.3, dtype=DTYPE, requires_grad=True)
    out = run(scale)
    (grad,) = torch.autograd.grad(out.weight.sum(), scale)

    def surrogate(s: float) -> tuple[float, torch.Tensor]:
        res = run(torch.tensor(s, dtype=DTYPE))
        before = torch.cat((torch.zeros_like(res.flagged[:, :1]), res.flagged[:, :-1]), 1)
        gate = torch.where(before, params.z_exit, params.z_enter)
        return float(torch.sigmoid((gate - res.z) / params.softness).sum()), res.flagged

    h = 1e-6
    up, flags_up = surrogate(1.3 + h)
    down, flags_down = surrogate(1.3 - h)
    assert torch.equal(flags_up, out.flagged) and torch.equal(flags_down, out.flagged)
    assert float(grad) != 0.0
    assert float(grad) == pytest.approx((up - down) / (2 * h), rel=1e-5, abs=1e-8)


# --- in the ESKF ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lidar_fault_run():
    """45 s, sunny, wheels dropped, GNSS over the first 15 s; the LiDAR slides along a
    corridor (it reports 20 % of the axial motion) over 25-33 s."""
    duration = 45.0
    sim = SimConfig(duration_s=duration, imu_rate_hz=100.0, gnss_outages_s=((15.0, duration),))
    run = simulate_run(sim, seed=9)
    wet = apply_weather(run, WeatherSchedule.constant("sunny", duration), seed=9)
    fault = SourceFault("lidar", "slide", 25.0, 33.0, axial_scale=0.2)
    faulty = inject_faults(wet, [fault], seed=9)
    seq = dataclasses.replace(faulty.sequence, wheel=None)
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    return faulty, seq, cfg


def test_eskf_excludes_a_faulty_lidar_during_its_fault_and_not_outside(lidar_fault_run, tmp_path):
    faulty, seq, cfg = lidar_fault_run
    with torch.no_grad():
        on = run_eskf(seq, cfg.replace(source_fault_detection=True))
        off = run_eskf(seq, cfg)
    sched = build_schedule(seq, cfg)
    col = sched.source_names.index("lidar")
    present = sched.source_mask[0, :, col].numpy()
    stream = faulty.sequence.pose_sources["lidar"]
    faulty_pair = present & pair_labels(
        stream.t[0].numpy(),
        faulty.sample_labels["lidar"],
        sched.t_end[0].numpy(),
        sched.source_dt[0, :, col].numpy(),
    )
    healthy_pair = present & ~faulty_pair
    flagged = on.source_fault["pose:lidar"][0, 1:].numpy()
    accepted = on.accepted["pose:lidar"][0, 1:].numpy()
    assert faulty_pair.sum() == 80
    assert (flagged & faulty_pair).sum() >= 0.95 * faulty_pair.sum()
    assert not (accepted & flagged).any()  # flagged rows never reach the update
    assert (accepted & faulty_pair).sum() <= 0.05 * faulty_pair.sum()
    assert (flagged & healthy_pair).sum() <= 0.02 * healthy_pair.sum()
    vo_present = sched.source_mask[0, :, sched.source_names.index("vo")].numpy()
    assert on.source_fault["pose:vo"][0, 1:].numpy()[vo_present].mean() <= 0.02
    assert (
        off.accepted["pose:lidar"][0, 1:].numpy() & faulty_pair
    ).sum() > 0.25 * faulty_pair.sum()
    assert on.source_fault_z["pose:lidar"][0, 1:].numpy()[faulty_pair].max() > 3.5
    # the flags reach msf run's diagnostics.csv
    write_diagnostics(on, tmp_path / "diagnostics.csv")
    table = np.genfromtxt(tmp_path / "diagnostics.csv", delimiter=",", names=True, deletechars="")
    np.testing.assert_array_equal(table["pose:lidar_fault"], on.source_fault["pose:lidar"][0])
    # and the fused trajectory is better for it (truth from the simulator)
    errors = []
    for result in (on, off):
        keep = result.mask[0] & (result.t[0] > 25.0)
        truth = faulty.truth.path.evaluate(result.t[0, keep].numpy())
        errors.append(
            float((result.position[0, keep] - torch.from_numpy(truth.position)).norm(dim=-1).max())
        )
    assert errors[0] < 0.5 * errors[1]


def test_an_excluded_source_does_not_adapt_the_noise(lidar_fault_run):
    # Sage-Husa and strong tracking on the LiDAR block: while the detector excludes the
    # sliding LiDAR, its noise estimate holds (it grew from 0.31 to 1.38 m/s when the
    # excluded rows still fed the adaptation) and they raise no fading factor
    _, seq, cfg = lidar_fault_run
    adaptive = cfg.replace(
        source_fault_detection=True,
        adaptive_noise_sensors=["pose:lidar"],
        strong_tracking_sensors=["pose:lidar"],
    )
    with torch.no_grad():
        result = run_eskf(seq, adaptive)
    flagged = result.source_fault["pose:lidar"][0]
    estimate = result.noise_estimate["pose:lidar"][0]
    assert int(flagged.sum()) > 50
    held = 0
    for e in torch.nonzero(flagged[1:]).flatten().tolist():
        epoch = e + 1
        if bool(flagged[epoch - 1]):  # excluded after epoch - 1: epoch adapts nothing
            assert torch.equal(estimate[epoch], estimate[epoch - 1]), epoch
            assert float(result.fading_factor[0, epoch]) == 1.0, epoch
            held += 1
    assert held > 50
    # outside the exclusion the LiDAR does adapt its noise
    free = ~flagged[1:] & ~flagged[:-1]
    changed = (estimate[1:] != estimate[:-1]).flatten(-2).any(-1)
    assert bool((changed & free).any())


def test_detection_off_or_with_one_source_changes_nothing(lidar_fault_run):
    _, seq, cfg = lidar_fault_run
    short = dataclasses.replace(seq, imu=seq.imu.map(lambda x: x[:, :1000]))  # 10 s
    with torch.no_grad():
        for names in (["lidar"], ["vo"]):
            single = cfg.replace(pose_sources=names)
            off = run_eskf(short, single)
            on = run_eskf(short, single.replace(source_fault_detection=True))
            assert torch.equal(on.position, off.position)
            assert torch.equal(on.covariance, off.covariance)
            assert not on.source_fault[f"pose:{names[0]}"].any()
            assert off.source_fault == {}


def test_config_keys_are_validated():
    assert load_config(None, source_fault_detection=True).source_fault_window == 10
    with pytest.raises(ValueError, match="source_fault_window"):
        load_config(None, source_fault_window=0)
    with pytest.raises(ValueError, match="source_fault_accel_sigma_mps2"):
        load_config(None, source_fault_accel_sigma_mps2=0.0)
    with pytest.raises(ValueError, match="z_exit"):
        load_config(None, source_fault_z_exit=5.0)
    with pytest.raises(ValueError, match="source_fault_speed_factor"):
        load_config(None, source_fault_speed_factor=math.nan)
