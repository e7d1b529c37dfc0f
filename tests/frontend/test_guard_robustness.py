"""The divergence guard neither runs away nor mistakes a noisy sensor for a diverged state.

* A GNSS noise step (fixes 10 x noisier than declared, a healthy state): the gate's
  re-opened fixes have NIS far above 10 x the gate, yet their streaks share no offset, so
  there is no reset and the run equals the filter with the NIS test off (the pre-guard
  behaviour), to 1e-9.
* The streak test (:func:`streak_offset`) against Monte Carlo: its false-alarm rate is
  ``1 - probability`` whatever the noise scale (the Beta law), and a common offset is found.
* Inflation (:class:`DivergenceGuard`, closed form): a reset scales each conventional sigma by
  ``sqrt(inflation)`` up to ``divergence_max_sigma_factor`` x its initial sigma,
  correlations kept; a second reset in the same episode does not inflate; repeated
  episodes stay at the cap instead of compounding x100 each.
* Fault runs with a blinded VO fused without source-fault detection (seeds 5 and 7; before,
  with both sources the position sigma ran away to 1e6 m and 4e88 m, with VO alone to 1e106
  m and NaN): with both sources the LiDAR vouches for the state, no reset; with VO alone
  resets, every output finite and bounded.
* A stream with zero samples (GNSS, wheels, poses, a pose source) is a run without it.
"""

from __future__ import annotations

import dataclasses

import torch
from scipy.stats import beta

from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.gating import chi2_threshold
from msf_torch.frontend.guard import (
    NOT_POSITIVE_DEFINITE,
    DivergenceGuard,
    reset_sigma_cap,
    streak_offset,
)
from msf_torch.geometry import so3
from msf_torch.geometry.invariant import invariant_maps
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.faults import simulate_fault_run
from msf_torch.sim.noise_step import gnss_noise_step
from msf_torch.types import NavState, PoseMeasurements, batch_sequences

TOL = 1e-9


def test_noisy_gnss_is_not_taken_for_divergence():
    run = simulate_run(SimConfig(duration_s=40.0), seed=0)
    seq = gnss_noise_step(run.sequence, 10.0, 10.0, seed=0)
    cfg = EskfConfig()
    with torch.no_grad():
        guarded = run_eskf(seq, cfg)
        nis_test_off = run_eskf(seq, cfg.replace(divergence_nis_scale=1e12))
    limit = cfg.divergence_nis_scale * chi2_threshold(3, cfg.gate_probability)
    blowups = guarded.accepted["gnss"] & (guarded.nis["gnss"] > limit)
    assert int(blowups.sum()) >= 2  # re-opened fixes that the old guard reset on
    assert not bool(guarded.divergence.any())
    for field in ("position", "velocity", "rotation", "covariance"):
        diff = (getattr(guarded, field) - getattr(nis_test_off, field)).abs().max()
        assert float(diff) < TOL, field


def _streaks(generator, count, n, d, scale, offset):
    """(B, 1) candidates, (B, d) sums, (B, 1) NIS sums and counts of ``count`` streaks of n
    whitened innovations ``offset + scale N(0, I)``."""
    w = offset + scale * torch.randn(count, n, d, generator=generator, dtype=torch.float64)
    ones = torch.ones(count, 1, dtype=torch.float64)
    return (
        torch.ones(count, 1, dtype=torch.bool),
        w.sum(1),
        w.square().sum((1, 2))[:, None],
        n * ones,
    )


def test_streak_test_rate_is_its_level_whatever_the_noise_scale():
    generator = torch.Generator().manual_seed(0)
    count = 40000
    for d, n in ((3, 4), (6, 4), (3, 7)):
        segment = torch.ones(d, 1, dtype=torch.float64)
        for scale in (1.0, 6.0, 100.0):
            args = _streaks(generator, count, n, d, scale, 0.0)
            for probability in (0.5, 0.9, 0.999):
                rate = float(streak_offset(*args, segment, probability).double().mean())
                sd = (probability * (1 - probability) / count) ** 0.5
                assert abs(rate - (1 - probability)) < 5 * sd + 1e-4, (d, n, scale, rate)
        # the quantile is Beta(d/2, (n-1)d/2)'s: scipy's survival function at it is 0.001
        cut = beta.ppf(0.999, d / 2, (n - 1) * d / 2)
        assert abs(beta.sf(cut, d / 2, (n - 1) * d / 2) - 1e-3) < 1e-9
        # a common offset 8 sigma long (NIS about 64 + d per sample) is found
        direction = torch.nn.functional.normalize(torch.ones(d, dtype=torch.float64), dim=0)
        args = _streaks(generator, 2000, n, d, 1.0, 8.0 * direction)
        assert float(streak_offset(*args, segment).double().mean()) > 0.99


def _guard_setup(cfg: EskfConfig):
    """One sequence away from the origin, a correlated covariance; a GNSS-like block."""
    generator = torch.Generator().manual_seed(3)
    rotation = so3.exp(torch.tensor([[0.2, -0.1, 1.3]], dtype=torch.float64))
    state = NavState(
        torch.tensor([[40.0, -25.0, 2.0]], dtype=torch.float64),
        torch.tensor([[3.0, 1.0, 0.0]], dtype=torch.float64),
        rotation,
        torch.zeros(1, 3, dtype=torch.float64),
        torch.zeros(1, 3, dtype=torch.float64),
    )
    root = 0.1 * torch.randn(1, 15, 15, generator=generator, dtype=torch.float64)
    conventional = (
        root @ root.mT
        + torch.diag_embed(
            torch.tensor([[0.25] * 3 + [0.01] * 3 + [1e-4] * 3 + [1e-6] * 3 + [1e-4] * 3])
        ).double()
    )
    _, to_inv = invariant_maps(state.position, state.velocity, state.rotation)
    cov = to_inv @ conventional @ to_inv.mT
    guard = DivergenceGuard(
        state,
        cov,
        cfg,
        ["gnss"],
        torch.ones(3, 1, dtype=torch.float64),
        torch.tensor([True]),
        invariant_maps,
    )
    return state, cov, guard


def _conventional(state: NavState, cov: torch.Tensor) -> torch.Tensor:
    to_conv, _ = invariant_maps(state.position, state.velocity, state.rotation)
    return to_conv @ cov @ to_conv.mT


def _step(guard, state, cov, fail: bool, calm: bool = False):
    """One epoch: propagated (unchanged), then an update that fails to factorise or, with
    ``calm``, a GNSS fix accepted inside its gate."""
    guard.propagated(state, cov)
    accepted = torch.tensor([[calm]])
    nis = torch.tensor([[1.0 if calm else 0.0]], dtype=torch.float64)
    gate = torch.tensor([16.3], dtype=torch.float64)
    return guard.updated(
        state,
        cov,
        accepted,
        nis,
        gate,
        torch.tensor([fail]),
        torch.tensor([[calm]]),
        torch.zeros(1, 3, dtype=torch.float64),
    )


def test_inflation_is_capped_and_once_per_episode():
    cfg = EskfConfig()
    state, cov, guard = _guard_setup(cfg)
    before = _conventional(state, cov)[0]
    var = before.diagonal()
    cap = reset_sigma_cap(cfg) ** 2
    # first reset: each conventional variance x100, but not past the cap; correlations kept
    _, inflated, accepted, code = _step(guard, state, cov, fail=True)
    assert int(code[0]) == NOT_POSITIVE_DEFINITE and not bool(accepted.any())
    after = _conventional(state, inflated)[0]
    expected = torch.minimum(100.0 * var, torch.maximum(var, cap))
    torch.testing.assert_close(after.diagonal(), expected, rtol=1e-9, atol=0.0)
    assert bool((after.diagonal() < 100.0 * var).any())  # some state hit its cap
    corr_before = before / (var[:, None] * var[None, :]).sqrt()
    corr_after = after / (after.diagonal()[:, None] * after.diagonal()[None, :]).sqrt()
    torch.testing.assert_close(corr_after, corr_before, rtol=0.0, atol=1e-9)
    # a second reset in the same episode: back to the (propagated) state, no new inflation
    _, again, _, code = _step(guard, state, inflated, fail=True)
    assert int(code[0]) == NOT_POSITIVE_DEFINITE
    assert torch.equal(again, inflated)
    # episodes closed by a calm fix, then reset again, ten times: the variance stays at the
    # cap (the old guard multiplied it by 100 every time: 1e20 x after ten)
    current = again
    for _ in range(10):
        _, current, _, code = _step(guard, state, current, fail=False, calm=True)
        assert int(code[0]) == 0
        _, current, _, code = _step(guard, state, current, fail=True)
    final = _conventional(state, current)[0].diagonal()
    torch.testing.assert_close(final, torch.maximum(var, cap), rtol=1e-6, atol=0.0)


def test_blinded_vo_without_detection_stays_bounded():
    runs = [simulate_fault_run(seed) for seed in (5, 7)]
    batch = batch_sequences([r.sequence for r in runs])
    cfg = config_for_sequence(EskfConfig(), runs[0].sequence.meta, set())
    cap = float(reset_sigma_cap(cfg)[0])
    with torch.no_grad():
        both = run_eskf(batch, cfg)
        vo_only = run_eskf(batch, cfg.replace(pose_sources=["vo"]))
    # with both sources the LiDAR, passing its gate, vouches for the state: no reset at all
    assert not bool(both.divergence.any())
    # VO alone: nothing tells a consistently wrong VO from a wrong state, so it resets
    assert bool(vo_only.divergence.any(-1).all())
    # unaligned errors (the heading drifts once GNSS ends at 15 s): 24 / 13 m with both
    # sources, 140 / 12 m with VO alone (the old guard: 1e106 m and NaN)
    for result, bound in ((both, 50.0), (vo_only, 200.0)):
        for field in ("position", "velocity", "rotation", "covariance"):
            assert bool(torch.isfinite(getattr(result, field)).all()), field
        sigma = result.covariance[..., 0:3, 0:3].diagonal(dim1=-2, dim2=-1).sqrt()
        # the cap bounds every inflation; after one, propagation alone adds to it
        assert float(sigma[result.mask].max()) < 3.0 * cap
        for b, run in enumerate(runs):
            keep = result.mask[b]
            truth = run.truth.path.evaluate(result.t[b, keep].numpy())
            error = (result.position[b, keep] - torch.from_numpy(truth.position)).norm(dim=-1)
            assert float(error.max()) < bound, b


def test_streams_without_samples_are_runs_without_them():
    seq = simulate_run(SimConfig(duration_s=6.0), seed=3).sequence
    truth = seq.ground_truth
    at = torch.arange(0, truth.length, 50)
    poses = PoseMeasurements(
        t=truth.t[:, at],
        position=truth.position[:, at],
        quaternion=truth.quaternion[:, at],
        covariance=0.01 * torch.eye(6, dtype=torch.float64).expand(1, at.numel(), 6, 6),
        mask=torch.ones(1, at.numel(), dtype=torch.bool),
    )
    seq = dataclasses.replace(seq, poses=poses, pose_sources={"vo": poses})

    def empty(stream):
        return stream.map(lambda x: x[:, :0])

    cases = {
        "gnss": ({"gnss": empty(seq.gnss)}, {"gnss": None}),
        "wheel": ({"wheel": empty(seq.wheel)}, {"wheel": None}),
        "pose": ({"poses": empty(poses)}, {"poses": None}),
        "source": ({"pose_sources": {"vo": empty(poses)}}, {"pose_sources": {}}),
    }
    for name, (without_samples, without_stream) in cases.items():
        with torch.no_grad():
            got = run_eskf(dataclasses.replace(seq, **without_samples))
            want = run_eskf(dataclasses.replace(seq, **without_stream))
        assert torch.equal(got.t, want.t), name
        for field in ("position", "rotation", "covariance"):
            assert torch.equal(getattr(got, field), getattr(want, field)), (name, field)
