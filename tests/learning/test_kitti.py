"""CovNet on the KITTI drive (msf_torch.learning.kitti): GNSS-free windows and the chunk gate
against brute force, outage segments cut from the drive with their splits and causal start
states, one training step whose gradient reaches the network only through GNSS-free
chunks, and the LightningCLI config."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.frontend.eskf import run_eskf
from msf_torch.learning import LOG_SCALE_SENSORS, CovNet, CovNetConfig
from msf_torch.learning.kitti import (
    KittiBatch,
    KittiCovNetModule,
    KittiDataModule,
    collate_segments,
    drive_scales,
    gate_outage_chunks,
    gnss_free_windows,
    kitti_eskf_config,
    outage_segment,
    reference_states,
    segment_features,
    segment_starts,
)
from msf_torch.sim import SimConfig, simulate_run

ROOT = Path(__file__).resolve().parents[2]
KITTI_YAML = ROOT / "training" / "configs" / "kitti.yaml"
ESKF_YAML = ROOT / "msf_torch" / "configs" / "kitti-gtsam.yaml"
CHECKPOINTS = ROOT / "checkpoints"
WINDOW = 100


@pytest.fixture(scope="module")
def drive():
    pytest.importorskip("gtsam")
    from msf_torch.io import load_sequence

    return load_sequence("kitti-gtsam")


def test_gnss_free_windows_match_brute_force() -> None:
    seq = simulate_run(SimConfig(duration_s=12.0), seed=3).sequence
    t = seq.imu.t[0].numpy()
    fixes = seq.gnss.t[0, seq.gnss.mask[0]].numpy()
    keep = (fixes < t[250]) | (fixes > t[730])  # an outage over windows 3..6
    seq = dataclasses.replace(seq, gnss=seq.gnss.map(lambda x: x[:, torch.from_numpy(keep)]))
    free = gnss_free_windows(seq, WINDOW).numpy()
    windows = (t.size - 1) // WINDOW
    expected = [
        not np.any((fixes[keep] >= t[w * WINDOW]) & (fixes[keep] <= t[(w + 1) * WINDOW]))
        for w in range(windows)
    ]
    assert free.tolist() == expected
    assert free[3:7].all() and not free[:2].any()


def test_gate_keeps_only_fully_gnss_free_chunks() -> None:
    scales = torch.randn(2, 7, 7, dtype=torch.float64)
    free = torch.tensor([[1, 1, 1, 0, 1, 1, 1], [0, 1, 1, 1, 1, 1, 0]], dtype=torch.bool)
    gated = gate_outage_chunks(scales, free, chunk_windows=3)
    # chunks of 3 windows: [0, 3), [3, 6), [6, 7)
    keep = torch.tensor([[1, 1, 1, 0, 0, 0, 1], [0, 0, 0, 1, 1, 1, 0]], dtype=torch.bool)
    torch.testing.assert_close(gated, torch.where(keep[..., None], scales, 0.0))


def test_outage_segments_splits_and_causal_start_states(drive) -> None:
    cfg = kitti_eskf_config(drive, ESKF_YAML)
    fixes = drive.gnss.t[0].numpy()
    n_fix = fixes.size
    ranges = {"train": (0, int(0.45 * n_fix)), "test": (int(0.6 * n_fix), n_fix)}
    segments = {
        split: segment_starts(drive, WINDOW, 0.0, 20.0, 60.0, 10.0, fix_range)
        for split, fix_range in ranges.items()
    }
    assert segments["train"] and segments["test"]
    start, warmup, total = segments["test"][0]
    assert warmup == 0 and total == 2000 and start % WINDOW == 0
    segment = outage_segment(drive, start, warmup, total)
    t = drive.imu.t[0]
    inside = (fixes >= float(t[start])) & (fixes <= float(t[start + total]))
    assert segment.gnss is None  # every fix of the outage is withheld ...
    np.testing.assert_array_equal(segment.ground_truth.t[0].numpy(), fixes[inside])
    first = int(np.argmax(inside))
    assert first >= ranges["test"][0]  # ... and they all lie in the test part
    for s, _, total_train in segments["train"]:
        last = np.nonzero(fixes <= float(t[s + total_train]))[0][-1]
        assert last < ranges["train"][1]
    torch.testing.assert_close(segment.imu.gyro[0], drive.imu.gyro[0, start : start + total + 1])

    # the start state only sees fixes before it: withholding every later fix changes nothing
    before = dataclasses.replace(
        drive,
        gnss=drive.gnss.map(lambda x: x[:, torch.from_numpy(fixes <= float(t[start]))]),
    )
    ((state, cov),) = reference_states(drive, cfg, [start])
    ((state_b, cov_b),) = reference_states(before, cfg, [start])
    torch.testing.assert_close(state.position, state_b.position, rtol=0, atol=0)
    torch.testing.assert_close(cov, cov_b, rtol=0, atol=0)
    # and it is the fixed filter's: one pass over the drive up to that sample
    with torch.no_grad():
        single = run_eskf(
            dataclasses.replace(drive, imu=drive.imu.map(lambda x: x[:, : start + 1])), cfg
        )
    last = int(single.mask[0].sum()) - 1
    assert float((single.position[0, last] - state.position[0]).norm()) < 1e-6


def test_one_training_step_gradient_reaches_net_only_through_outage(drive) -> None:
    torch.manual_seed(0)
    cfg = kitti_eskf_config(drive, ESKF_YAML)
    net_cfg = CovNetConfig(pose_sources=("gnss",))
    starts = [1000, 2500]
    states = reference_states(drive, cfg, starts)
    items = []
    for start, state in zip(starts, states, strict=True):
        segment = outage_segment(drive, start, 500, 1500)  # 5 s with GNSS, 10 s without
        features = segment_features(segment, WINDOW, net_cfg.pose_sources, net_cfg.weather_classes)
        items.append((segment, features, state))
    batch = collate_segments(items, WINDOW)
    assert isinstance(batch, KittiBatch) and batch.imu.shape[:2] == (2, 15)
    assert batch.gnss_free[:, :5].logical_not().any(-1).all() and batch.gnss_free[:, 6:].all()
    module = KittiCovNetModule(covnet=net_cfg, eskf_config=str(ESKF_YAML), chunk_windows=5)
    _, effective = module(batch)
    torch.testing.assert_close(effective[:, :5], torch.zeros_like(effective[:, :5]))

    # scales through the gate into the filter: no gradient reaches the GNSS chunk's scales
    raw = (0.3 * torch.randn(2, 15, 7, dtype=torch.float64)).requires_grad_()
    _, results = module.run_chunks(batch, gate_outage_chunks(raw, batch.gnss_free, 5))
    mean_relative, drift = module._drift(batch, results)
    assert torch.isfinite(mean_relative) and bool((drift > 0).all())
    mean_relative.backward()
    used = [LOG_SCALE_SENSORS.index(s) for s in ("nhc", "imu_gyro", "imu_accel")]
    assert float(raw.grad[:, :5].abs().max()) == 0.0
    assert bool((raw.grad[:, 5:, used].abs().sum((1, 2)) > 0).all())

    # one full training step: finite loss terms, the network's head gets a gradient
    terms, _ = module._losses(batch)
    assert all(bool(torch.isfinite(v)) for v in terms.values())
    terms["loss"].backward()
    head = module.net.log_scale_head.weight.grad
    assert head is not None and bool(torch.isfinite(head).all()) and float(head.abs().sum()) > 0


def test_drive_scales_are_chunk_means_in_outage_only(drive) -> None:
    torch.manual_seed(1)
    net = CovNet(CovNetConfig(pose_sources=("gnss",))).eval()
    part = dataclasses.replace(drive, imu=drive.imu.map(lambda x: x[:, :3001]))
    keep = (drive.gnss.t[0] < float(drive.imu.t[0, 1000])) | (
        drive.gnss.t[0] > float(drive.imu.t[0, 2500])
    )
    part = dataclasses.replace(part, gnss=drive.gnss.map(lambda x: x[:, keep]))
    scales = drive_scales(part, net, chunk_windows=5)
    features = segment_features(part, WINDOW, ("gnss",), net.config.weather_classes)
    with torch.no_grad():
        raw = net(features.imu, features.wheel, features.wheel_present, features.residual_stats)
    raw = raw.log_scales.double() - torch.log(raw.fusion_weights.double()).sum(-1, keepdim=True) * (
        torch.arange(7) == LOG_SCALE_SENSORS.index("gnss")
    )
    free = gnss_free_windows(part, WINDOW)
    assert free[10:25].all() and not free[:10].any()
    for c in range(6):
        block = slice(5 * c, 5 * c + 5)
        expected = raw[block].mean(0) if bool(free[block].all()) else torch.zeros(7)
        torch.testing.assert_close(scales[block], expected.expand(5, 7).double())


def test_shipped_kitti_network_is_applied_as_trained(drive) -> None:
    from msf_torch.learning.inference import learned_scales, load_learned

    learned = load_learned(CHECKPOINTS / "covnet_kitti.pt")
    application = learned.application
    assert (application.chunk_windows, application.noise_granularity) == (5, "chunk")
    assert application.gnss_outages_only and not application.innovation_features
    # the median of the training segments' IMU rates (the whole drive's: 100.0225 Hz)
    assert application.imu_rate_hz == pytest.approx(100.0352, abs=1e-4)
    part = dataclasses.replace(drive, imu=drive.imu.map(lambda x: x[:, :6001]))
    keep = (drive.gnss.t[0] < float(drive.imu.t[0, 1000])) | (
        drive.gnss.t[0] > float(drive.imu.t[0, 4000])
    )
    part = dataclasses.replace(part, gnss=drive.gnss.map(lambda x: x[:, keep]))
    scales = learned_scales(part, learned, cfg=None)
    assert scales.gnss_outages_only and scales.chunk_windows == 5
    torch.testing.assert_close(
        scales.log_scales, drive_scales(part, learned.model, 5), rtol=0.0, atol=0.0
    )
    assert bool((scales.log_scales[10:30] != 0).all()) and not bool(scales.log_scales[:10].any())


def test_kitti_yaml_builds_through_the_training_cli(train_script) -> None:
    cli = train_script.main(["--config", str(KITTI_YAML)], run=False)
    assert isinstance(cli.model, KittiCovNetModule) and isinstance(cli.datamodule, KittiDataModule)
    assert cli.model.weights["orientation"] == 0.0 and cli.model.chunk_windows == 5
    assert cli.datamodule.fix_ranges(470) == {
        "train": (0, 211),
        "val": (211, 282),
        "test": (282, 470),
    }


@pytest.mark.slow
def test_kitti_fit_through_cli_writes_a_loadable_network(
    drive, tmp_path: Path, train_script
) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from msf_torch.learning import read_checkpoint

    train_script.main(
        [
            "fit",
            "--config",
            str(KITTI_YAML),
            "--trainer.max_epochs=2",
            "--trainer.limit_train_batches=0.2",  # 1 of the 5 batches (an int 1 reads as 1.0)
            "--trainer.enable_progress_bar=false",
            f"--trainer.logger.init_args.save_dir={tmp_path}",
            f"--trainer.default_root_dir={tmp_path}",
        ]
    )
    (version,) = sorted((tmp_path / "kitti").iterdir())
    net, application = read_checkpoint(version / "covnet.pt")
    assert net.config.pose_sources == ("gnss",)
    assert application.gnss_outages_only and not application.innovation_features
    assert application.chunk_windows == 5
    assert application.imu_rate_hz == pytest.approx(100.0, abs=0.1)
    events = EventAccumulator(str(version), size_guidance={"scalars": 0})
    events.Reload()
    drift = [e.value for e in events.Scalars("val/drift_pct")]
    best = events.Scalars("val/best_drift_pct")[-1].value
    assert len(drift) == 2 and best == pytest.approx(min(drift), rel=1e-6)
