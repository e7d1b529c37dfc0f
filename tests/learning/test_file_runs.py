"""Training on the user's own recorded runs: RunDataModule file lists, their checks, and the
trained checkpoint applied with ``msf run --checkpoint``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from msf_torch.cli import main as msf_main
from msf_torch.frontend.config import config_for_sequence, load_config
from msf_torch.io import DataError
from msf_torch.io.native import write_native
from msf_torch.learning import CovNetConfig, load_checkpoint
from msf_torch.learning.data import RunDataModule, simulate_labelled_run
from msf_torch.learning.features import run_features
from msf_torch.learning.module import CovNetModule

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "training" / "configs" / "smoke.yaml"
WEATHER = ("sunny", "rain", "fog", "night", "snow")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[str, Path]:
    """Three 4-s labelled runs written as native .npz files (the user's recordings)."""
    folder = tmp_path_factory.mktemp("recorded")
    paths = {}
    for name, seed in (("field_a", 11), ("field_b", 12), ("field_c", 13)):
        paths[name] = write_native(simulate_labelled_run(seed, 4.0), folder / f"{name}.npz")
    return paths


def _module(train: list[Path], val: list[Path]) -> RunDataModule:
    return RunDataModule(train_files=[str(p) for p in train], val_files=[str(p) for p in val])


def test_file_lists_load_the_files_not_simulated_runs(recorded) -> None:
    data = _module([recorded["field_a"], recorded["field_b"]], [recorded["field_c"]])
    data.setup("fit")
    assert data.split_seeds("train") == [] and data.split_seeds("val") == []
    assert [s.names[0] for s, _ in data.runs["train"]] == ["field_a", "field_b"]
    assert [s.names[0] for s, _ in data.runs["val"]] == ["field_c"]
    # the weather labels come from the file: same windows as the in-memory run
    reference = run_features(simulate_labelled_run(13, 4.0), 100, ("gnss", "vo", "lidar"), WEATHER)
    assert torch.equal(data.runs["val"][0][1].weather, reference.weather)
    assert bool((reference.weather < len(WEATHER)).any())


def test_run_without_ground_truth_is_named_with_its_field(recorded, tmp_path) -> None:
    seq = dataclasses.replace(simulate_labelled_run(11, 4.0), ground_truth=None)
    bare = write_native(seq, tmp_path / "no_truth.npz")
    data = _module([recorded["field_a"], bare], [recorded["field_c"]])
    with pytest.raises(DataError, match="no ground truth") as err:
        data.setup("fit")
    assert err.value.path == str(bare) and err.value.field == "ground_truth"


def test_ground_truth_that_stops_early_is_an_error(tmp_path) -> None:
    seq = simulate_labelled_run(11, 4.0)
    # truth for the first 2 s of a 4 s run: 2 s short, windows are 1 s (100 samples, 100 Hz)
    half = seq.ground_truth.map(lambda x: x[:, :201])
    part = write_native(dataclasses.replace(seq, ground_truth=half), tmp_path / "part.npz")
    with pytest.raises(DataError, match=r"ground truth spans 0\.000-2\.000 s") as err:
        _module([part], [part]).setup("fit")
    assert err.value.path == str(part) and err.value.field == "ground_truth"
    # one IMU sample short of the end is within one window: accepted
    most = seq.ground_truth.map(lambda x: x[:, :-1])
    fine = write_native(dataclasses.replace(seq, ground_truth=most), tmp_path / "most.npz")
    _module([fine], [fine]).setup("fit")


def test_run_shorter_than_one_window_is_named(recorded, tmp_path) -> None:
    seq = simulate_labelled_run(11, 4.0)
    short = dataclasses.replace(seq, imu=seq.imu.map(lambda x: x[:, :100]))
    path = write_native(short, tmp_path / "short.npz")
    with pytest.raises(DataError, match="100 IMU samples") as err:
        _module([path], [recorded["field_c"]]).setup("fit")
    assert err.value.path == str(path) and err.value.field == "imu"


def test_runs_at_different_imu_rates_are_refused(recorded, tmp_path) -> None:
    fast = write_native(simulate_labelled_run(14, 4.0, imu_rate_hz=200.0), tmp_path / "f.npz")
    with pytest.raises(DataError, match=r"IMU at 200 Hz, but .*field_a\.npz runs at 100 Hz") as err:
        _module([recorded["field_a"], fast], [recorded["field_c"]]).setup("fit")
    assert err.value.path == str(fast) and err.value.field == "imu"
    # 200 Hz files validated on simulated runs at the default 100 Hz: name the setting
    data = RunDataModule(train_files=[str(fast)], val_runs=1, duration_s=4.0)
    with pytest.raises(ValueError, match=r"simulated val run 0: IMU at 100 Hz.*data\.imu_rate_hz"):
        data.setup("fit")
    # within 5 %: one network's windows span nearly the same time
    near = write_native(simulate_labelled_run(15, 4.0, imu_rate_hz=104.0), tmp_path / "n.npz")
    _module([recorded["field_a"], near], [recorded["field_c"]]).setup("fit")


def test_missing_file_is_named(recorded, tmp_path) -> None:
    missing = tmp_path / "nowhere.npz"
    with pytest.raises(DataError, match="no such file") as err:
        _module([missing], [recorded["field_c"]]).setup("fit")
    assert err.value.path == str(missing)


def test_fit_on_files_then_msf_run_with_the_checkpoint(
    recorded, tmp_path, train_script, capsys
) -> None:
    train_script.main(
        [
            "fit",
            "--config",
            str(SMOKE),
            f"--data.train_files=[{recorded['field_a']}, {recorded['field_b']}]",
            f"--data.val_files=[{recorded['field_c']}]",
            f"--trainer.logger.init_args.save_dir={tmp_path}",
            f"--trainer.default_root_dir={tmp_path}",
        ]
    )
    (log_dir,) = sorted((tmp_path / "smoke").iterdir())
    events = EventAccumulator(str(log_dir), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    assert {"train/loss", "val/loss", "val/weather_accuracy"} <= set(events.Tags()["scalars"])
    assert events.Tags()["images"] == ["val_trajectory/field_c"]  # validated on the file
    checkpoint = log_dir / "covnet.pt"
    plain = torch.load(checkpoint, weights_only=True)
    assert set(plain) == {"format", "config", "application", "state_dict"}
    # the training runs' IMU rate: simulate_labelled_run's 100 Hz, read back from the files
    stamps = [np.load(recorded[name])["imu/t"] for name in ("field_a", "field_b")]
    rate = 1.0 / float(np.median(np.concatenate([np.diff(t) for t in stamps])))
    assert plain["application"]["imu_rate_hz"] == pytest.approx(rate, rel=1e-9)
    assert rate == pytest.approx(100.0, rel=1e-9)
    assert load_checkpoint(checkpoint).config.window_length == 100
    code = msf_main(
        [
            "run",
            str(recorded["field_c"]),
            "--checkpoint",
            str(checkpoint),
            "--out",
            str(tmp_path / "out"),
            "--no-plot",
            "--progress",
            "off",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["noise"] == "learned"
    assert summary["learned"]["checkpoint"] == str(checkpoint)
    assert summary["learned"]["windows"] == 4  # (401 - 1) // 100


def test_window_length_differing_from_the_model_is_named_before_loading(tmp_path) -> None:
    data = RunDataModule(train_files=[str(tmp_path / "unread.npz")], window_length=100)
    module = CovNetModule(CovNetConfig(window_length=50, pose_sources=("gnss",)))
    trainer = L.Trainer(
        accelerator="cpu",
        max_epochs=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    message = (
        r"data.window_length = 100 but model.covnet.window_length = 50; "
        r"data.pose_sources = \['gnss', 'vo', 'lidar'\] but model.covnet.pose_sources = \['gnss'\]"
    )
    with pytest.raises(ValueError, match=message):  # not the DataError of the unread file
        trainer.fit(module, datamodule=data)


def test_reference_pass_keeps_the_keys_the_eskf_yaml_sets(recorded, tmp_path) -> None:
    # the run's metadata gives the IMU noise (gyro 9.9e-5); the YAML sets 50x that, which
    # msf run --config and the module's filter keep, so the features' reference pass must too
    config = tmp_path / "robot.yaml"
    config.write_text("gyro_noise_density: 5.0e-3\n")
    data = RunDataModule(
        train_files=[str(recorded["field_a"])],
        val_files=[str(recorded["field_a"])],
        eskf_config=str(config),
    )
    data.setup("fit")
    seq = data.runs["train"][0][0]
    base = load_config(str(config))
    kept = config_for_sequence(base, seq.meta, {"gyro_noise_density"})
    overridden = config_for_sequence(base, seq.meta, set())
    assert kept.gyro_noise_density == 5.0e-3 != overridden.gyro_noise_density
    sources, stats = ("gnss", "vo", "lidar"), data.runs["train"][0][1].residual_stats
    want = run_features(seq, 100, sources, WEATHER, cfg=kept).residual_stats
    other = run_features(seq, 100, sources, WEATHER, cfg=overridden).residual_stats
    assert not torch.equal(want, other)
    assert torch.equal(stats, want)


def test_eskf_config_differing_from_the_model_is_named(tmp_path) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text("gyro_noise_density: 5.0e-3\n")
    data = RunDataModule(train_files=[str(tmp_path / "unread.npz")])  # default settings
    module = CovNetModule(eskf_config=str(config))
    trainer = L.Trainer(accelerator="cpu", max_epochs=1, logger=False, enable_progress_bar=False)
    with pytest.raises(ValueError, match="data.eskf_config and model.eskf_config") as err:
        trainer.fit(module, datamodule=data)
    assert f"data.eskf_config unset, model.eskf_config = {config}" in str(err.value)
    assert "they differ in gyro_noise_density:" in str(err.value)
    same = RunDataModule(train_files=[str(tmp_path / "unread.npz")], eskf_config=str(config))
    with pytest.raises(DataError, match="unread.npz"):  # the check passes; the file is next
        trainer.fit(module, datamodule=same)


def test_train_script_names_bad_data_in_one_line(tmp_path, python_in) -> None:
    """``training/train.py`` on a file that does not exist: exit status 2 and one error line
    naming it, not Lightning's traceback (the same DataError ``msf run`` reports)."""
    root = Path(__file__).resolve().parents[2]
    missing = tmp_path / "missing.npz"
    run = python_in(
        str(root / "training" / "train.py"),
        "fit",
        "--config",
        str(root / "training" / "configs" / "smoke.yaml"),
        f"--data.train_files=[{missing}]",
        "--trainer.logger=false",
        timeout=300,
    )
    assert run.returncode == 2, run.stderr[-2000:]
    errors = [line for line in run.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith(f"train.py: error: {missing}: no such file")
    assert "Traceback" not in run.stderr


def test_unknown_weather_label_is_warned(tmp_path) -> None:
    """A weather label the network has no class for (a typo, ``weather:Rain``) would
    silently count as unknown weather: loading the run warns, naming it."""
    seq = simulate_labelled_run(11, 4.0)
    name = next(k for k in seq.labels if k.startswith("weather:"))
    labels = {("weather:Rain" if k == name else k): v for k, v in seq.labels.items()}
    path = write_native(dataclasses.replace(seq, labels=labels), tmp_path / "typo.npz")
    data = _module([path], [path])
    with pytest.warns(UserWarning, match=r"typo.npz: weather labels Rain are not among"):
        data.setup("fit")
