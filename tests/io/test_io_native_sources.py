"""Native format: named pose sources (``poses/<name>/...``, ``poses_<name>.csv``) and weather
labels round-trip; the single ``poses`` stream keeps its behaviour."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.io import DataError, read_native, write_native
from msf_torch.io.native import pose_source_file
from msf_torch.sim import (
    DEFAULT_CONDITIONS,
    Environment,
    SimConfig,
    WeatherSchedule,
    apply_weather,
    simulate_run,
)
from msf_torch.types import PoseMeasurements, batch_sequences


def _source(seed: int, n: int, covariance: bool = True) -> PoseMeasurements:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    a = rng.normal(size=(n, 6, 6))
    cov = a @ np.swapaxes(a, 1, 2) * 1e-3 if covariance else np.full((n, 6, 6), np.nan)
    return PoseMeasurements(
        t=torch.from_numpy(100.0 + np.arange(n) / 10.0)[None],
        position=torch.from_numpy(rng.normal(size=(n, 3)))[None],
        quaternion=torch.from_numpy(q)[None],
        covariance=torch.from_numpy(cov)[None],
        mask=torch.ones((1, n), dtype=torch.bool),
    )


def _assert_streams_equal(a: PoseMeasurements, b: PoseMeasurements, tol: float = 1e-12) -> None:
    for name, value in a.tensors().items():
        got = getattr(b, name)
        assert got.shape == value.shape, name
        if value.dtype == torch.bool:
            assert torch.equal(got, value), name
        else:
            torch.testing.assert_close(got, value, atol=tol, rtol=0, equal_nan=True)


@pytest.fixture
def with_sources(sequence):
    return dataclasses.replace(
        sequence, pose_sources={"vo": _source(1, 7), "lidar": _source(2, 4, covariance=False)}
    )


@pytest.mark.parametrize("target", ["run.npz", "run"])
def test_named_sources_round_trip(tmp_path, with_sources, target):
    path = write_native(with_sources, tmp_path / target)
    back = read_native(path)
    assert list(back.pose_sources) == ["lidar", "vo"]
    for name, stream in with_sources.pose_sources.items():
        _assert_streams_equal(stream, back.pose_sources[name])
    _assert_streams_equal(with_sources.poses, back.poses)  # the single stream is untouched
    assert back.meta["dropped_nonfinite"]["poses/vo"] == 0
    if target.endswith(".npz"):
        with np.load(path) as z:
            assert {"poses/vo/t", "poses/vo/covariance", "poses/lidar/t", "poses/t"} <= set(z)
            assert "poses/lidar/covariance" not in z  # all-NaN optional field omitted
    else:
        assert (path / "poses_vo.csv").exists() and (path / "poses_lidar.csv").exists()
        header = (path / "poses_lidar.csv").read_text().splitlines()[0]
        assert header == "t,x,y,z,qw,qx,qy,qz"


def test_without_sources_nothing_changes(tmp_path, sequence):
    for target in ("plain.npz", "plain"):
        back = read_native(write_native(sequence, tmp_path / target))
        assert back.pose_sources == {}
        assert "poses/vo" not in back.meta["dropped_nonfinite"]
    with np.load(tmp_path / "plain.npz") as z:
        assert not [k for k in z if k.count("/") > 1]


def test_folder_rewrite_removes_stale_sources(tmp_path, with_sources):
    folder = tmp_path / "seq"
    write_native(with_sources, folder)
    (folder / "poses_notes.txt").write_text("kept")
    write_native(dataclasses.replace(with_sources, pose_sources={"vo": _source(3, 2)}), folder)
    assert not (folder / "poses_lidar.csv").exists()
    assert (folder / "poses_notes.txt").exists()
    assert list(read_native(folder).pose_sources) == ["vo"]


def test_bad_source_names_and_keys(tmp_path, with_sources):
    bad = dataclasses.replace(with_sources, pose_sources={"a/b": _source(1, 3)})
    with pytest.raises(ValueError, match="pose source name"):
        write_native(bad, tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="pose source name"):
        pose_source_file("")
    path = write_native(with_sources, tmp_path / "ok.npz")
    with np.load(path) as z:
        arrays = dict(z)
    arrays["poses/vo/speed"] = arrays["poses/vo/t"]
    np.savez(tmp_path / "extra.npz", **arrays)
    with pytest.raises(DataError, match="poses/vo/speed"):
        read_native(tmp_path / "extra.npz")
    del arrays["poses/vo/speed"], arrays["poses/vo/quaternion"]
    np.savez(tmp_path / "short.npz", **arrays)
    with pytest.raises(DataError, match="poses/vo/quaternion"):
        read_native(tmp_path / "short.npz")


def test_source_cleaning_rules_apply(tmp_path, with_sources):
    folder = write_native(with_sources, tmp_path / "seq")
    lines = (folder / "poses_vo.csv").read_text().splitlines()
    lines[2] = "nan," + lines[2].split(",", 1)[1]
    (folder / "poses_vo.csv").write_text("\n".join(lines) + "\n")
    back = read_native(folder)
    assert back.pose_sources["vo"].length == 6
    assert back.meta["dropped_nonfinite"]["poses/vo"] == 1
    assert back.meta["dropped_lines"]["poses/vo"] == [3]


def test_sequence_methods_carry_sources(with_sources, sequence):
    moved = with_sources.to(dtype=torch.float32)
    assert moved.pose_sources["vo"].position.dtype == torch.float32
    batch = batch_sequences([with_sources, sequence])
    assert batch.pose_sources["vo"].position.shape == (2, 7, 3)
    assert batch.pose_sources["vo"].counts().tolist() == [7, 0]
    batch.check()
    picked = batch.select(0)
    assert picked.pose_sources["lidar"].counts().tolist() == [4]
    broken = dataclasses.replace(with_sources, pose_sources={"vo": batch.pose_sources["vo"]})
    with pytest.raises(ValueError, match="pose_sources\\['vo'\\]"):
        broken.check()


@pytest.mark.parametrize("target", ["wet.npz", "wet"])
def test_weather_run_round_trip(tmp_path, target):
    run = simulate_run(SimConfig(duration_s=30.0), seed=3)
    schedule = WeatherSchedule.from_boundaries([0.0, 10.0, 20.0, 30.0], ["sunny", "fog", "night"])
    env = Environment(corridors_s=((5.0, 12.0),), urban_s=((15.0, 25.0),))
    dark = {
        **DEFAULT_CONDITIONS,
        "night": dataclasses.replace(DEFAULT_CONDITIONS["night"], illuminance_lux=3.0),
    }
    wet = apply_weather(run, schedule, 4, environment=env, conditions=dark, pose_source=None)
    back = read_native(write_native(wet.sequence, tmp_path / target))
    assert back.poses is None and sorted(back.pose_sources) == ["lidar", "vo"]
    for name, stream in wet.pose_sources.items():
        _assert_streams_equal(stream.compact(), back.pose_sources[name], tol=1e-15)
    assert back.pose_sources["vo"].length < wet.pose_sources["vo"].length  # dark-night dropouts
    for name, spans in wet.sequence.labels.items():
        if target == "wet" and spans.shape[1] == 0:
            assert name not in back.labels  # a CSV row per interval: empty labels vanish
            continue
        assert torch.equal(back.labels[name], spans), name
    assert {"weather:sunny", "weather:fog", "weather:night", "env:corridor", "env:urban"} <= set(
        back.labels
    )
