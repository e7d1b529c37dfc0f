"""Training: the CLI's smoke fit and its TensorBoard tags, DDP on two CPU processes, the
loss going down on a fixed problem, the data module's seeds, windows and labels."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from msf_torch.frontend.config import config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.learning import (
    LOG_SCALE_SENSORS,
    CovNetConfig,
    NoiseApplication,
    read_checkpoint,
)
from msf_torch.learning.data import (
    SPLIT_SEED_STRIDE,
    RunDataModule,
    collate_runs,
    run_features,
    simulate_labelled_run,
    simulate_labelled_weather_run,
)
from msf_torch.learning.module import CovNetModule, truth_at
from msf_torch.types import Trajectory

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "training" / "configs" / "smoke.yaml"
TRAIN = ROOT / "training" / "train.py"
WEATHER = ("sunny", "rain", "fog", "night", "snow")


def _events(log_dir: Path) -> EventAccumulator:
    """All scalars and images of a TensorBoard log folder."""
    accumulator = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0})
    accumulator.Reload()
    return accumulator


def _version_dir(save_dir: Path, name: str) -> Path:
    (version,) = sorted((save_dir / name).iterdir())
    return version


def test_smoke_fit_through_cli_logs_expected_tags(tmp_path: Path, train_script) -> None:
    train_script.main(
        [
            "fit",
            "--config",
            str(SMOKE),
            f"--trainer.logger.init_args.save_dir={tmp_path}",
            f"--trainer.default_root_dir={tmp_path}",
        ]
    )
    log_dir = _version_dir(tmp_path, "smoke")
    events = _events(log_dir)
    scalars = set(events.Tags()["scalars"])
    expected = {
        f"{split}/{term}"
        for split in ("train", "val")
        for term in ("loss", "position", "orientation", "nll", "weather_ce")
    }
    expected |= {"train/slip_factor_mean", "val/slip_factor_mean", "val/slip_flagged_fraction"}
    assert expected <= scalars, expected - scalars
    seen = {tag.split("/")[2] for tag in scalars if tag.startswith("sigma/")}
    assert seen and seen <= {*WEATHER, "unknown"}
    for weather in seen:
        for sensor in LOG_SCALE_SENSORS:
            assert f"sigma/{sensor}/{weather}" in scalars
        for source in ("gnss", "vo", "lidar"):
            assert f"fusion/{source}/{weather}" in scalars
    for tag in scalars:
        values = [e.value for e in events.Scalars(tag)]
        assert values and all(math.isfinite(v) for v in values), tag
    # base sigmas times a bounded scale: e^-1.5 .. e^1.5 of the config's 0.05 m/s
    for weather in seen:
        (wheel,) = [e.value for e in events.Scalars(f"sigma/wheel/{weather}")]
        assert 0.05 * math.exp(-1.5) <= wheel <= 0.05 * math.exp(1.5)
    images = events.Tags()["images"]
    assert len(images) == 1 and images[0].startswith("val_trajectory/sim-")
    model, application = read_checkpoint(log_dir / "covnet.pt")
    assert model.config.window_length == 100
    # how training applied the scales: smoke.yaml's chunking, the simulated 100 Hz IMU,
    # no eskf_config (the defaults: no filter setting recorded as set)
    assert application == NoiseApplication(
        imu_rate_hz=100.0, chunk_windows=4, noise_granularity="chunk", filter_settings={}
    )


def test_ddp_two_cpu_processes_one_step(smoke_fit) -> None:
    done, events = smoke_fit(
        "--trainer.strategy=ddp",
        "--trainer.devices=2",
        "--trainer.accelerator=cpu",
        "--trainer.max_steps=1",
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    assert "Starting with 2 processes" in done.stderr + done.stdout
    (loss,) = [e.value for e in events.Scalars("train/loss")]
    assert math.isfinite(loss)
    assert math.isfinite(events.Scalars("val/loss")[0].value)


@pytest.fixture(scope="module")
def tiny_batch():
    """One fixed 6 s run as a batch (windows of 100 IMU samples at 100 Hz)."""
    seq = simulate_labelled_run(7, 6.0)
    features = run_features(seq, 100, ("gnss", "vo", "lidar"), WEATHER)
    return collate_runs([(seq, features)], window_length=100)


def test_loss_decreases_on_a_fixed_problem(tiny_batch) -> None:
    torch.manual_seed(0)
    module = CovNetModule(CovNetConfig(), chunk_windows=3)
    optimizer = torch.optim.Adam(module.parameters(), lr=1e-2)
    losses = []
    for _ in range(6):
        terms, _ = module._losses(tiny_batch)
        optimizer.zero_grad()
        terms["loss"].backward()
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
        optimizer.step()
        losses.append(float(terms["loss"].detach()))
    assert losses[-1] < losses[0] - 0.05, losses  # seeds 0-2 drop by 0.13-0.17


def test_chunks_cover_the_run_and_detach_between_them(tiny_batch) -> None:
    module = CovNetModule(CovNetConfig(), chunk_windows=2)
    log_scales = torch.zeros(1, tiny_batch.windows, 7, requires_grad=True)
    totals, results = module.run_chunks(tiny_batch, log_scales)
    assert len(results) == math.ceil(tiny_batch.windows / 2)
    t_imu = tiny_batch.sequence.imu.t[0]
    assert float(results[0].t[0, 0]) == float(t_imu[0])
    assert float(results[-1].t[0, -1]) == float(t_imu[-1])
    for before, after in zip(results, results[1:], strict=False):
        assert float(before.t[0, -1]) == float(after.t[0, 0])
        assert torch.equal(before.position[0, -1].detach(), after.position[0, 0])
    # the last chunk's loss reaches only the last chunk's scales
    (grad,) = torch.autograd.grad(
        (results[-1].position[..., :2] ** 2).sum(), log_scales, allow_unused=True
    )
    last_start = 2 * (len(results) - 1)
    assert grad is not None and bool((grad[0, :last_start] == 0).all())
    assert bool((grad[0, last_start:] != 0).any())
    assert float(totals["count"]) == sum(int(r.mask[:, 1:].sum()) for r in results)


def test_data_module_splits_are_disjoint_and_windows_labelled() -> None:
    dm = RunDataModule(train_runs=2, val_runs=1, test_runs=1, duration_s=6.0, batch_size=2)
    seeds = {split: dm.split_seeds(split) for split in ("train", "val", "test")}
    assert seeds == {"train": [0, 1], "val": [SPLIT_SEED_STRIDE], "test": [2 * SPLIT_SEED_STRIDE]}
    dm.setup("fit")
    assert set(dm.runs) == {"train", "val"}
    (batch,) = list(dm.train_dataloader())
    assert batch.imu.shape == (2, 6, 100, 6)  # 601 samples at 100 Hz: 6 windows + end
    assert batch.sequence.imu.t.shape == (2, 601)
    assert batch.wheel.shape == (2, 6, 100, 2) and bool(batch.wheel_present[:, 1:].all())
    assert batch.residual_stats.shape == (2, 6, 3, 4)
    nis_mean, nis_max, rejected = batch.residual_stats[..., :3].unbind(-1)
    assert bool((nis_mean > 0).any()) and bool((nis_max >= nis_mean).all())
    assert bool(((rejected >= 0) & (rejected <= 1)).all())
    dropout = batch.residual_stats[..., 3]
    assert bool(((dropout >= 0) & (dropout <= 1)).all())
    assert bool((dropout[:, :, 0] < 1).all())  # GNSS at 1 Hz: counted over 2 s spans
    assert batch.weather.shape == (2, 6) and bool((batch.weather < len(WEATHER)).all())
    names = batch.sequence.names
    for b in range(2):
        centre = 0.5 + torch.arange(6, dtype=torch.float64)
        label = batch.sequence.labels[f"weather:{WEATHER[int(batch.weather[b, 0])]}"][b]
        inside = (label[:, 0] <= centre[0]) & (centre[0] <= label[:, 1])
        assert bool(inside.any()), names[b]


def test_innovation_features_summarise_the_reference_filter(tiny_batch) -> None:
    seq = tiny_batch.sequence
    cfg = config_for_sequence(load_config(None), seq.meta, set())
    features = run_features(seq, 100, ("gnss", "vo", "lidar"), WEATHER, cfg)
    result = run_eskf(seq, cfg)
    for s, key, dof in ((0, "gnss", 3), (2, "pose:lidar", 6)):
        for w in range(6):  # window w covers [w, w + 1) s
            inside = result.present[key][0] & (result.t[0] >= w) & (result.t[0] < w + 1)
            nis = result.nis[key][0][inside] / dof
            rejected = (~result.accepted[key][0][inside]).double()
            expected = [nis.mean(), nis.max(), rejected.mean()] if inside.any() else [0, 0, 0]
            got = features.residual_stats[w, s, :3].double()
            assert torch.allclose(got, torch.tensor(expected).double(), rtol=1e-6), (key, w)
    assert int(result.present["pose:lidar"][0].sum()) > 40  # 10 Hz source, present


def test_dropout_fraction_of_absent_and_thinned_sources(tiny_batch) -> None:
    seq = tiny_batch.sequence
    gnss_only = dataclasses.replace(seq, poses=None, pose_sources={})
    features = run_features(gnss_only, 100, ("gnss", "vo", "lidar"), WEATHER)
    assert bool((features.residual_stats[:, 1:, 3] == 1).all())  # no VO, no LiDAR
    lidar = seq.pose_sources["lidar"]
    kept = lidar.t[0] < 3.0  # LiDAR (10 Hz) lost after 3 s
    thinned = dataclasses.replace(
        seq, poses=None, pose_sources={"lidar": lidar.map(lambda x: x[:, kept])}
    )
    column = run_features(thinned, 100, ("gnss", "vo", "lidar"), WEATHER).residual_stats[:, 2, 3]
    assert column[:2].tolist() == [0.0, 0.0]  # windows [0, 1) s and [1, 2) s
    assert column[4:].tolist() == [1.0, 1.0]


def test_truth_at_interpolates_position_and_picks_nearer_rotation() -> None:
    t = torch.tensor([[0.0, 1.0, 2.0, 0.0]], dtype=torch.float64)
    position = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [0, 0, 0]]], dtype=torch.float64)
    half = math.sqrt(0.5)
    quat = torch.tensor(
        [[[1.0, 0, 0, 0], [half, 0, 0, half], [0, 0, 0, 1], [1, 0, 0, 0]]], dtype=torch.float64
    )
    mask = torch.tensor([[True, True, True, False]])
    truth = Trajectory(t=t, position=position, quaternion=quat, mask=mask)
    pos, rot = truth_at(truth, torch.tensor([[0.25, 1.5, 1.75, 5.0]], dtype=torch.float64))
    assert torch.allclose(pos[0, :, 0], torch.tensor([0.25, 2.0, 2.5, 3.0], dtype=torch.float64))
    yaw = torch.atan2(rot[0, :, 1, 0], rot[0, :, 0, 0])
    expected = torch.tensor([0.0, math.pi, math.pi, math.pi], dtype=torch.float64)
    assert torch.allclose(yaw.abs(), expected, atol=1e-12)


def test_labelled_runs_carry_the_unreported_weather_error():
    """Training runs emit the weather error the sources do not report (error scale k >= 1,
    sim.weather); switched off, the same draws give streams whose error the declared
    covariances describe. The declared covariances are the same either way."""
    on = simulate_labelled_run(3, 12.0)
    off = simulate_labelled_run(3, 12.0, unreported_error=False)
    assert on.meta["weather"]["unreported_error"] is True
    assert "unreported_error" not in off.meta["weather"]
    truth = on.ground_truth
    stride = round(float(on.pose_sources["vo"].t[0, 1] - on.pose_sources["vo"].t[0, 0]) * 100)
    rms = {}
    for name, seq in (("on", on), ("off", off)):
        vo = seq.pose_sources["vo"]
        true_position = truth.position[:, ::stride][:, : vo.t.shape[1]]
        torch.testing.assert_close(truth.t[:, ::stride][:, : vo.t.shape[1]], vo.t)
        err = (vo.position - true_position)[vo.mask]
        rms[name] = float(err.pow(2).sum(-1).mean().sqrt())
    torch.testing.assert_close(
        on.pose_sources["vo"].covariance, off.pose_sources["vo"].covariance, rtol=0.0, atol=0.0
    )
    assert rms["on"] > 1.05 * rms["off"], rms


def test_labelled_weather_run_is_the_labelled_run_with_its_source_truth():
    """The oracle's entry point gives the same streams as simulate_labelled_run, and its
    per-sample error scale k is the ratio of the emitted white noise to the declared
    covariance: whitening the noise by k L (L L^T = covariance) leaves unit variance."""
    wet = simulate_labelled_weather_run(3, 12.0)
    seq = simulate_labelled_run(3, 12.0)
    assert wet.sequence.names == seq.names == ["sim-3"]
    for name in ("vo", "lidar"):
        a, b = wet.sequence.pose_sources[name], seq.pose_sources[name]
        torch.testing.assert_close(a.position, b.position, rtol=0.0, atol=0.0)
        torch.testing.assert_close(a.covariance, b.covariance, rtol=0.0, atol=0.0)
        truth = wet.source_truth[name]
        assert truth.error_scale.shape == (a.t.shape[1],)
        keep = a.mask[0].numpy()
        chol = torch.linalg.cholesky(a.covariance[0, keep])
        noise = torch.from_numpy(truth.noise[keep])[..., None]
        k = torch.from_numpy(truth.error_scale[keep])[:, None]
        white = torch.linalg.solve_triangular(chol, noise, upper=False)[..., 0] / k
        assert abs(float(white.var()) - 1.0) < 0.1, float(white.var())
    assert float(wet.source_truth["lidar"].error_scale.max()) > 2.0  # fog: k matters above


def test_validation_figures_of_runs_with_one_name_get_their_own_tags(tiny_batch) -> None:
    """Two validation runs named alike (``dayA/run.npz``, ``dayB/run.npz``) used to share
    one TensorBoard tag, the second figure hiding the first."""
    from types import SimpleNamespace

    from msf_torch.types import batch_sequences

    tags: list[str] = []
    experiment = SimpleNamespace(add_figure=lambda tag, fig, global_step: tags.append(tag))
    module = CovNetModule(max_figures=4)
    module._trainer = SimpleNamespace(
        logger=SimpleNamespace(experiment=experiment), global_step=0, loggers=[]
    )
    twice = dataclasses.replace(
        tiny_batch,
        sequence=batch_sequences([tiny_batch.sequence, tiny_batch.sequence]),
    )
    with torch.no_grad():
        result = run_eskf(twice.sequence, module.eskf_base)
    module._add_figures(twice, [result])
    name = tiny_batch.sequence.names[0]
    assert tags == [f"val_trajectory/{name}", f"val_trajectory/{name}-2"]


def test_filter_settings_of_a_config_with_a_smoother_section() -> None:
    """The KITTI config holds a ``smoother:`` section beside the filter's keys: the
    checkpoint's recorded filter settings are the filter's keys only (the section made
    ``noise_application`` raise at the end of a KITTI fit)."""
    path = Path(__file__).resolve().parents[2] / "msf_torch" / "configs" / "kitti-gtsam.yaml"
    module = CovNetModule(eskf_config=str(path))
    settings = module.noise_application().filter_settings
    assert "smoother" not in settings and settings["imu_gap_noise_scale"] == 10000.0
