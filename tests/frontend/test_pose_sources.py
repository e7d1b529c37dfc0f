"""Pose sources (VO, LiDAR odometry) fused as odometry by the ESKF.

Runs: simulated 90 s drives (seeds 1-3) degraded by :func:`~msf_torch.sim.weather.apply_weather`
(random weather schedules; VO and LiDAR with drift), wheels dropped, GNSS only over the first
15 s (enough for the initial heading), and dropouts added to the sources' masks (a random
fifth of the VO frames, a 5 s LiDAR block), so pairs across gaps are skipped.

* IMU + NHC alone drifts; with the sources the Umeyama-aligned (SE(3)) ATE falls to below
  0.6 of it on every run and below 0.35 of it on average (measured: 0.17, 0.56, 0.23).
* Consistency: the average NIS of the source blocks (6 rows: velocity and rate) over all
  present pairs lies within 10 % of 6 (the Monte-Carlo standard error of the mean over
  ~10^4 correlated pairs is ~1 %; consecutive pairs share a sample, and the velocity noise
  is treated as white).
* In both fusion modes (velocity, drifting_frame): a batch equals each sequence alone
  (1e-9; with drifting frames, the offsets and their covariance too), and the gradient
  w.r.t. a source's variance scale matches central finite differences; with
  no sources (absent, or ``pose_sources: []``) the results are bit-for-bit those of the
  sequence without ``pose_sources``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.eval.metrics import ate
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import SENSORS, EskfNoise, run_eskf
from msf_torch.frontend.schedule import build_schedule
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.weather import WeatherSchedule, apply_weather
from msf_torch.types import PoseMeasurements, Sequence, batch_sequences

SEEDS = (1, 2, 3)
DURATION_S = 90.0
GNSS_UNTIL_S = 15.0


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _thin(source: PoseMeasurements, keep: np.ndarray) -> PoseMeasurements:
    return dataclasses.replace(source, mask=source.mask & torch.from_numpy(keep)[None])


def odometry_run(
    seed: int, duration_s: float = DURATION_S, gnss_until_s: float = GNSS_UNTIL_S
) -> Sequence:
    """Weather run without wheels, GNSS withheld after ``gnss_until_s``, sources thinned."""
    outages = ((gnss_until_s, duration_s),) if gnss_until_s < duration_s else None
    sim = SimConfig(duration_s=duration_s, gnss_outages_s=outages)
    run = simulate_run(sim, seed=seed)
    schedule = WeatherSchedule.random(duration_s, seed=seed + 10)
    wet = apply_weather(run, schedule, seed=seed + 20, pose_source=None)
    rng = np.random.default_rng(seed)
    vo, lidar = wet.pose_sources["vo"], wet.pose_sources["lidar"]
    t_lidar = lidar.t[0].numpy()
    sources = {
        "vo": _thin(vo, rng.random(vo.t.shape[1]) > 0.2),
        "lidar": _thin(lidar, ~((t_lidar > 40.0) & (t_lidar < 45.0))),
    }
    return dataclasses.replace(wet.sequence, wheel=None, pose_sources=sources)


@pytest.fixture(scope="module")
def runs() -> tuple[Sequence, EskfConfig]:
    singles = [odometry_run(s) for s in SEEDS]
    cfg = config_for_sequence(EskfConfig(), singles[0].meta, set())
    return batch_sequences(singles), cfg


@pytest.fixture(scope="module")
def results(runs):
    seq, cfg = runs
    return run_eskf(seq, cfg), run_eskf(seq, cfg.replace(pose_sources=[]))


def test_odometry_sources_cut_ate(runs, results):
    seq, _ = runs
    fused, alone = results
    ratios, with_sources, without = [], [], []
    for b in range(seq.batch_size):
        truth = seq.ground_truth.select(b)
        a_fused = ate(fused.trajectory().select(b), truth)["rmse"]
        a_alone = ate(alone.trajectory().select(b), truth)["rmse"]
        with_sources.append(a_fused)
        without.append(a_alone)
        ratios.append(a_fused / a_alone)
    assert max(ratios) < 0.6, (with_sources, without)
    assert sum(with_sources) < 0.35 * sum(without), (with_sources, without)
    assert set(fused.present) == set(SENSORS) | {"pose:vo", "pose:lidar"}
    counts = fused.counts()
    for key in ("pose:vo", "pose:lidar"):
        assert min(counts[key]["present"]) > 600
        assert min(counts[key]["accepted"]) >= 0.99 * min(counts[key]["present"])


def test_source_nis_matches_dimension(results):
    fused, _ = results
    for key in ("pose:vo", "pose:lidar"):
        here = fused.present[key] & fused.mask
        mean = float(fused.nis[key][here].mean())
        assert abs(mean / 6.0 - 1.0) < 0.1, (key, mean)


def test_schedule_pairs_skip_gaps(runs):
    seq, cfg = runs
    sched = build_schedule(seq, cfg)
    assert sched.source_names == ("lidar", "vo")
    dt = sched.source_dt[sched.source_mask]
    assert float(dt.min()) > 0.0 and float(dt.max()) <= cfg.pose_source_max_gap_s
    # the LiDAR block (40 s, 45 s) yields no pair ending inside it, VO pairs span dropouts
    t_lidar = sched.t_end[sched.source_mask[..., 0]]
    assert not bool(((t_lidar > 40.05) & (t_lidar < 45.0)).any())
    assert float(sched.source_dt[..., 1][sched.source_mask[..., 1]].max()) > 0.15


@pytest.mark.parametrize("fusion", ["velocity", "drifting_frame"])
def test_batch_equals_single_runs(fusion):
    singles = [odometry_run(s, 6.0 + s, gnss_until_s=20.0) for s in (4, 5)]
    singles[1] = dataclasses.replace(singles[1], pose_sources={"vo": singles[1].pose_sources["vo"]})
    cfg = config_for_sequence(EskfConfig(pose_source_fusion=fusion), singles[0].meta, set())
    batch = run_eskf(batch_sequences(singles), cfg)
    for b, single_seq in enumerate(singles):
        one = run_eskf(single_seq, cfg)
        n = one.t.shape[1]
        for name in ("position", "velocity", "rotation", "gyro_bias", "covariance"):
            diff = (getattr(one, name)[0] - getattr(batch, name)[b, :n]).abs().max()
            assert float(diff) < 1e-9, (b, name, float(diff))
        for key in one.present:
            assert torch.equal(one.present[key][0], batch.present[key][b, :n])
            assert torch.equal(one.accepted[key][0], batch.accepted[key][b, :n])
            assert float((one.nis[key][0] - batch.nis[key][b, :n]).abs().max()) < 1e-9
        for key in one.source_frame:  # drifting_frame only: offsets and their covariance
            diff = (one.source_frame[key][0] - batch.source_frame[key][b, :n]).abs().max()
            assert float(diff) < 1e-9, (b, key, float(diff))
            diff = (
                one.source_frame_covariance[key][0] - batch.source_frame_covariance[key][b, :n]
            ).abs()
            assert float(diff.max()) < 1e-9, (b, key)


@pytest.mark.parametrize("fusion", ["velocity", "drifting_frame"])
def test_gradient_wrt_source_scale_matches_finite_differences(fusion):
    seq = odometry_run(6, duration_s=5.0)
    # no gating: a decision flipping between the finite-difference runs would be a jump
    cfg = config_for_sequence(
        EskfConfig(gate_probability=1.0, pose_source_fusion=fusion), seq.meta, set()
    )
    truth = seq.ground_truth

    def loss(scale_vo: torch.Tensor) -> torch.Tensor:
        noise = EskfNoise.from_config(cfg)
        noise.pose_source_scale = {"vo": scale_vo, "lidar": torch.tensor(0.7, dtype=torch.float64)}
        result = run_eskf(seq, cfg, noise)
        return ((result.position[0, -1] - truth.position[0, -1]) ** 2).sum() + (
            result.velocity[0] ** 2
        ).mean()

    scale = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(scale), scale)
    eps = 1e-5
    with torch.no_grad():
        numeric = (loss(scale + eps) - loss(scale - eps)) / (2 * eps)
    assert torch.isfinite(grad)
    assert abs(float(grad)) > 1e-8
    assert float((grad - numeric).abs()) <= 1e-5 * max(1.0, float(numeric.abs()))


def test_no_sources_is_bit_for_bit_unchanged():
    seq = odometry_run(7, duration_s=20.0)
    bare = dataclasses.replace(seq, pose_sources={})
    cfg = config_for_sequence(EskfConfig(), seq.meta, set())
    reference = run_eskf(bare, cfg)
    off = run_eskf(seq, cfg.replace(pose_sources=[]))
    assert set(reference.present) == set(SENSORS) == set(off.present)
    for name in ("t", "position", "velocity", "rotation", "gyro_bias", "covariance"):
        assert torch.equal(getattr(reference, name), getattr(off, name)), name
    for key in SENSORS:
        assert torch.equal(reference.nis[key], off.nis[key])


def test_config_keys_are_validated(runs):
    seq, cfg = runs
    with pytest.raises(ValueError, match="'pose_sources'"):
        load_config(pose_sources="all")
    with pytest.raises(ValueError, match="'pose_sources'"):
        load_config(pose_sources=["vo", "vo"])
    with pytest.raises(ValueError, match="'pose_source_accel_sigma_mps2'"):
        load_config(pose_source_accel_sigma_mps2=-1.0)
    with pytest.raises(ValueError, match="'pose_source_max_gap_s'"):
        load_config(pose_source_max_gap_s=0.0)
    with pytest.raises(ValueError, match="'pose_sources' names \\['radar'\\]"):
        build_schedule(seq, cfg.replace(pose_sources=["radar"]))


def test_covnet_scales_map_onto_pose_sources():
    from msf_torch.learning.covnet import LOG_SCALE_SENSORS, scaled_noise

    base = EskfNoise.from_config(EskfConfig())
    log_scales = torch.linspace(-0.5, 0.5, len(LOG_SCALE_SENSORS), dtype=torch.float64)
    log_scales = log_scales[None].repeat(2, 1).requires_grad_(True)
    scale = scaled_noise(base, log_scales).pose_source_scale
    for name in ("vo", "lidar"):
        expected = torch.exp(log_scales[:, LOG_SCALE_SENSORS.index(name)])
        assert torch.allclose(scale[name], expected, rtol=1e-15, atol=0.0)
    (grad,) = torch.autograd.grad(scale["vo"].sum(), log_scales)
    assert float(grad[:, LOG_SCALE_SENSORS.index("vo")].min()) > 0.0


def test_noise_free_source_measures_mid_interval_motion():
    """A noise-free source on the simulator's continuous path: the pair's velocity and rate
    equal the true body velocity and rate at mid-interval up to O(dt^2) (reference: the
    path's analytic derivatives), and the mean gyro equals the IMU rate (bias + noise)."""
    run = simulate_run(SimConfig(duration_s=20.0), seed=8)
    t = np.arange(1, 200) / 10.0
    truth = run.path.evaluate(t)
    source = PoseMeasurements(
        t=torch.from_numpy(t)[None],
        position=torch.from_numpy(truth.position)[None],
        quaternion=matrix_to_quat(torch.from_numpy(truth.rotation))[None],
        covariance=torch.eye(6, dtype=torch.float64).expand(1, t.size, 6, 6) * 1e-6,
        mask=torch.ones(1, t.size, dtype=torch.bool),
    )
    seq = dataclasses.replace(run.sequence, pose_sources={"exact": source})
    sched = build_schedule(seq, EskfConfig())
    here = sched.source_mask[0, :, 0]
    t_end = sched.t_end[0, here].numpy()
    mid = run.path.evaluate(t_end - 0.05)
    v_body = np.einsum("nji,nj->ni", mid.rotation, mid.velocity)
    assert here.sum() == t.size - 1
    assert np.abs(sched.source_velocity[0, here, 0].numpy() - v_body).max() < 2e-3
    assert np.abs(sched.source_rate[0, here, 0].numpy() - mid.angular_velocity).max() < 2e-3
    assert torch.allclose(sched.source_dt[0, here, 0], torch.tensor(0.1, dtype=torch.float64))
    # declared covariance: (C_k + C_k-1) / dt^2 (isotropic, so rotation-invariant)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(sched.source_covariance[0, here, 0], 2e-4 * eye, rtol=1e-9)
    gyro_err = sched.source_gyro_mean[0, here, 0].numpy() - mid.angular_velocity
    assert np.abs(gyro_err).max() < 0.02  # turn-on gyro bias (3.5e-3 rad/s 1-sigma) + noise
