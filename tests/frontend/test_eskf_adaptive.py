"""Adaptive noise in the ESKF (Sage-Husa R, strong tracking) on simulated runs with truth.

Seeds 41-44 and 61-63 are used here only; ``benchmarks/adaptive_noise.py`` measures the
acceptance figure on seeds 5000+.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.noise_step import gnss_noise_step
from msf_torch.types import batch_sequences

DTYPE = torch.float64


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _position_rmse(result, runs, t_from: float = -1.0) -> torch.Tensor:
    """(B,) position RMSE against the simulator's truth at epochs with t >= t_from."""
    out = []
    for b, run in enumerate(runs):
        keep = result.mask[b] & (result.t[b] >= t_from)
        t_truth = run.truth.t[0]
        idx = torch.searchsorted(t_truth, result.t[b, keep] - 1e-9).clamp(max=t_truth.numel() - 1)
        err = (result.position[b, keep] - run.truth.position[0, idx]).norm(dim=-1)
        out.append(err.pow(2).mean().sqrt())
    return torch.stack(out)


@pytest.fixture(scope="module")
def noise_step_runs():
    runs = [simulate_run(SimConfig(duration_s=60.0), seed=s) for s in (41, 42)]
    seqs = [gnss_noise_step(r.sequence, 20.0, 6.0, seed=r.seed) for r in runs]
    base = config_for_sequence(load_config(), runs[0].sequence.meta, set())
    return runs, batch_sequences(seqs), base


def test_sage_husa_lowers_rmse_after_a_noise_step(noise_step_runs):
    """GNSS noise x6 at t = 20 s (declared sigma unchanged): the Sage-Husa filter's position
    RMSE is >= 30% below the fixed-noise filter's, and R_hat finds the new sigmas."""
    runs, batch, base = noise_step_runs
    with torch.no_grad():
        fixed = run_eskf(batch, base)
        adaptive = run_eskf(batch, base.replace(adaptive_noise_sensors=["gnss"]))
    rmse_fixed = _position_rmse(fixed, runs)
    rmse_adaptive = _position_rmse(adaptive, runs)
    reduction = 1.0 - float(rmse_adaptive.mean() / rmse_fixed.mean())
    assert reduction >= 0.30, (rmse_fixed.tolist(), rmse_adaptive.tolist())
    assert bool((rmse_adaptive < rmse_fixed).all())
    sigma_end = adaptive.noise_estimate["gnss"][:, -1].diagonal(dim1=-2, dim2=-1).sqrt()
    expected = torch.tensor([3.0, 3.0, 6.0], dtype=DTYPE)
    torch.testing.assert_close(sigma_end, expected.expand(2, 3), rtol=0.3, atol=0.0)
    # before the change R_hat stays near the declared sigmas
    t_before = (adaptive.t[0] > 15.0) & (adaptive.t[0] < 20.0)
    sigma_before = adaptive.noise_estimate["gnss"][0, t_before].diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(sigma_before[:, :2].max()) < 0.9
    assert bool((adaptive.fading_factor == 1.0).all())


def test_diagnostics_table_carries_the_adaptation(noise_step_runs, tmp_path):
    """msf run's diagnostics.csv: the fading factor and Sage-Husa's sigmas per epoch, of the
    sequence asked for."""
    import numpy as np

    from msf_torch.runner import write_diagnostics

    _, batch, base = noise_step_runs
    cfg = base.replace(adaptive_noise_sensors=["gnss"], strong_tracking_sensors=["gnss"])
    with torch.no_grad():
        result = run_eskf(batch, cfg)
    write_diagnostics(result, tmp_path / "d.csv", index=1)
    table = np.genfromtxt(tmp_path / "d.csv", delimiter=",", names=True, deletechars="")
    keep = result.mask[1]
    np.testing.assert_allclose(table["fading_factor"], result.fading_factor[1, keep], rtol=1e-9)
    assert table["fading_factor"].max() > 1.0
    estimate = result.noise_estimate["gnss"][1, keep]
    for i in range(3):
        np.testing.assert_allclose(
            table[f"gnss_noise_sigma{i}"], estimate[:, i, i].sqrt(), rtol=1e-9, atol=1e-12
        )
    write_diagnostics(run_eskf(batch.select(0), base), tmp_path / "plain.csv")
    plain = np.genfromtxt(tmp_path / "plain.csv", delimiter=",", names=True, deletechars="")
    assert (plain["fading_factor"] == 1.0).all()
    assert not any("noise_sigma" in name for name in plain.dtype.names)


def test_strong_tracking_recovers_from_a_wrong_initial_position():
    """Start 18 m off with a 0.2 m sigma (model mismatch): over 10-30 s the faded filter's
    error is less than half the plain one's, which the gate and its confidence hold back."""
    runs = [simulate_run(SimConfig(duration_s=30.0), seed=s) for s in (61, 62)]
    batch = batch_sequences([r.sequence for r in runs])
    base = config_for_sequence(load_config(), runs[0].sequence.meta, set())
    state, cov = initial_state(batch, base)
    state = dataclasses.replace(
        state, position=state.position + torch.tensor([15.0, -10.0, 0.0], dtype=DTYPE)
    )
    cov = cov.clone()
    cov[:, 0:3, 0:3] = 0.04 * torch.eye(3, dtype=DTYPE)
    with torch.no_grad():
        plain = run_eskf(batch, base, initial=(state, cov))
        faded = run_eskf(
            batch, base.replace(strong_tracking_sensors=["gnss"]), initial=(state, cov)
        )
    err_plain = _position_rmse(plain, runs, 10.0)
    err_faded = _position_rmse(faded, runs, 10.0)
    assert float(err_faded.mean()) < 0.5 * float(err_plain.mean()), (
        err_plain.tolist(),
        err_faded.tolist(),
    )
    assert float(faded.fading_factor.max()) > 1.0
    assert float(faded.fading_factor.max()) <= base.strong_tracking_max_factor


def test_batch_equals_single_with_adaptation():
    runs = [simulate_run(SimConfig(duration_s=d), seed=s) for d, s in ((8.0, 43), (6.0, 44))]
    seqs = [gnss_noise_step(r.sequence, 4.0, 5.0, seed=r.seed) for r in runs]
    cfg = config_for_sequence(load_config(), runs[0].sequence.meta, set()).replace(
        adaptive_noise_sensors=["gnss"], strong_tracking_sensors=["gnss", "wheel"]
    )
    with torch.no_grad():
        batched = run_eskf(batch_sequences(seqs), cfg)
        for b, seq in enumerate(seqs):
            single = run_eskf(seq, cfg)
            n = single.t.shape[1]
            for name in ("position", "rotation", "covariance", "fading_factor"):
                diff = (getattr(single, name)[0] - getattr(batched, name)[b, :n]).abs().max()
                assert float(diff) < 1e-9, name
            diff = single.noise_estimate["gnss"][0] - batched.noise_estimate["gnss"][b, :n]
            assert float(diff.abs().max()) < 1e-9


def test_off_or_absent_blocks_change_nothing():
    run = simulate_run(SimConfig(duration_s=6.0), seed=43)
    cfg = config_for_sequence(load_config(), run.sequence.meta, set())
    with torch.no_grad():
        off = run_eskf(run.sequence, cfg)
        with pytest.warns(UserWarning, match=r"adaptive_noise_sensors names pose:vo, which no"):
            absent = run_eskf(
                run.sequence,
                cfg.replace(adaptive_noise_sensors=["pose:vo"], strong_tracking_sensors=["pose"]),
            )
    assert off.noise_estimate == {}
    assert bool((off.fading_factor == 1.0).all())
    assert torch.equal(off.position, absent.position)
    assert torch.equal(off.covariance, absent.covariance)


def test_a_misspelt_pose_source_is_warned_about(recwarn):
    from msf_torch.learning.data import simulate_labelled_run

    run = simulate_labelled_run(3, 4.0)  # pose sources vo and lidar
    cfg = config_for_sequence(load_config(), run.meta, set())
    with torch.no_grad():
        run_eskf(run, cfg.replace(strong_tracking_sensors=["pose:lidar", "gnss"]))
        assert not [w for w in recwarn if "names" in str(w.message)]
        with pytest.warns(UserWarning) as caught:
            run_eskf(run, cfg.replace(strong_tracking_sensors=["pose:lidr"]))
    (message,) = [str(w.message) for w in caught if "names" in str(w.message)]
    assert message == (
        "strong_tracking_sensors names pose:lidr, which no sequence of the batch has "
        "(its pose sources: pose:lidar, pose:vo): those entries do nothing"
    )


def test_gradient_through_the_adaptive_filter_matches_finite_differences():
    run = simulate_run(SimConfig(duration_s=3.0, gnss_rate_hz=5.0), seed=44)
    seq = gnss_noise_step(run.sequence, 1.0, 4.0, seed=44)
    cfg = config_for_sequence(load_config(), run.sequence.meta, set()).replace(
        adaptive_noise_sensors=["gnss"], strong_tracking_sensors=["gnss"]
    )

    def loss(scale: torch.Tensor) -> torch.Tensor:
        noise = EskfNoise.from_config(cfg)
        noise.gnss_sigma_scale = scale
        result = run_eskf(seq, cfg, noise)
        return result.position[0, -1].sum() + result.covariance[0, -1].diagonal().sum()

    scale = torch.tensor(1.3, dtype=DTYPE, requires_grad=True)
    value = loss(scale)
    (grad,) = torch.autograd.grad(value, scale)
    step = 1e-6
    with torch.no_grad():
        numeric = (loss(scale + step) - loss(scale - step)) / (2 * step)
    assert torch.isfinite(grad)
    assert float(grad) == pytest.approx(float(numeric), rel=1e-4, abs=1e-8)
    assert abs(float(grad)) > 1e-8


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("adaptive_noise_sensors", ["wheel"], "adaptive_noise_sensors"),
        ("adaptive_noise_sensors", "gnss", "adaptive_noise_sensors"),
        ("strong_tracking_sensors", ["radar"], "strong_tracking_sensors"),
        ("adaptive_forgetting", 1.0, "adaptive_forgetting"),
        ("adaptive_noise_floor", 0.0, "adaptive_noise_floor"),
        ("strong_tracking_max_factor", 0.5, "strong_tracking_max_factor"),
        ("adaptive_clip_probability", 0.0, "adaptive_clip_probability"),
        ("adaptive_prior_samples", -1.0, "adaptive_prior_samples"),
    ],
)
def test_config_validation(key, value, match):
    with pytest.raises(ValueError, match=match):
        EskfConfig(**{key: value}).validate()
    EskfConfig(adaptive_noise_sensors=["gnss", "pose:lidar"]).validate()


def test_gnss_noise_step_statistics():
    run = simulate_run(SimConfig(duration_s=400.0, gnss_rate_hz=5.0), seed=45)
    seq = run.sequence
    noisy = gnss_noise_step(seq, 100.0, 4.0, seed=1)
    extra = noisy.gnss.position - seq.gnss.position
    after = seq.gnss.t[0] >= 100.0
    assert float(extra[0, ~after].abs().max()) == 0.0
    sigma = seq.gnss.sigma[0, after]
    ratio_std = (extra[0, after] / sigma).std(0)  # sqrt(k^2 - 1) = 3.873
    torch.testing.assert_close(
        ratio_std, torch.full((3,), 15.0**0.5, dtype=DTYPE), rtol=0.07, atol=0.0
    )
    assert torch.equal(noisy.gnss.sigma, seq.gnss.sigma)
    assert noisy.meta["noise_step"]["sigma_scale"] == 4.0
    with pytest.raises(ValueError, match="sigma_scale"):
        gnss_noise_step(seq, 1.0, 0.5, seed=0)
    with pytest.raises(ValueError, match="no GNSS"):
        gnss_noise_step(dataclasses.replace(seq, gnss=None), 1.0, 2.0, seed=0)
