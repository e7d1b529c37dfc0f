"""load_sequence dispatch, DataError / MissingExtraError, atomic writes."""

from __future__ import annotations

import os
import pickle

import pytest

from msf_torch.io import (
    FORMATS,
    DataError,
    MissingExtraError,
    atomic_save_npz,
    atomic_write,
    load_sequence,
    write_native,
    write_tum,
)


def test_auto_detect_native(tmp_path, sequence):
    npz = write_native(sequence, tmp_path / "a.npz")
    folder = write_native(sequence, tmp_path / "a")
    assert load_sequence(npz).meta["format"] == "native-npz"
    assert load_sequence(folder).meta["format"] == "native-csv"
    assert load_sequence(str(folder), fmt="native").imu.length == sequence.imu.length
    assert load_sequence(folder, fmt="csv").imu.length == sequence.imu.length
    with pytest.raises(DataError, match="format 'npz' needs a file ending in .npz"):
        load_sequence(folder, fmt="npz")


def test_tum_is_a_trajectory_not_a_sequence(tmp_path, sequence):
    path = write_tum(sequence.ground_truth, tmp_path / "est.txt")
    with pytest.raises(DataError, match="read_tum.*msf eval"):
        load_sequence(path)
    with pytest.raises(DataError, match="trajectory"):
        load_sequence(path, fmt="tum")


def test_unrecognised_inputs(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="accepted: 'kitti-gtsam'.*npz.*imu.csv.*mav0"):
        load_sequence(tmp_path / "empty")
    with pytest.raises(DataError, match="no such file or folder"):
        load_sequence(tmp_path / "missing.npz")
    with pytest.raises(ValueError, match="accepted: " + ", ".join(FORMATS)):
        load_sequence(tmp_path, fmt="rosbag")


def test_data_error_message_and_pickle():
    assert str(DataError("a.csv", "bad", line=3, field="x")) == "a.csv:3: field 'x': bad"
    assert str(DataError("a.csv", "bad", line=3)) == "a.csv:3: bad"
    assert str(DataError("a.npz", "bad", field="imu/t")) == "a.npz: field 'imu/t': bad"
    assert str(DataError("a.csv", "bad")) == "a.csv: bad"
    err = pickle.loads(pickle.dumps(DataError("a.csv", "bad", line=3, field="x")))
    assert (err.path, err.line, err.field, str(err)) == ("a.csv", 3, "x", "a.csv:3: field 'x': bad")
    assert isinstance(err, ValueError)
    missing = MissingExtraError("gtsam", "peers", "the KITTI data")
    assert "pip install 'msf_torch[peers]'" in str(missing) and isinstance(missing, ImportError)
    assert str(pickle.loads(pickle.dumps(missing))) == str(missing)


def test_atomic_write_keeps_old_file_on_error(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as handle:
            handle.write("partial")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]
    with atomic_write(target) as handle:
        handle.write("new")
    assert target.read_text() == "new"
    assert os.listdir(tmp_path) == ["out.txt"]
    with pytest.raises(ValueError, match="modes"):
        with atomic_write(target, "a"):
            pass


def test_atomic_save_npz(tmp_path):
    import numpy as np

    atomic_save_npz(tmp_path / "x.npz", **{"a/b": np.arange(3.0)})
    with np.load(tmp_path / "x.npz") as z:
        assert z["a/b"].tolist() == [0.0, 1.0, 2.0]


def test_atomic_write_creates_missing_folders(tmp_path):
    target = tmp_path / "a" / "b" / "out.txt"
    with atomic_write(target) as handle:
        handle.write("new")
    assert target.read_text() == "new"
    assert os.listdir(target.parent) == ["out.txt"]


def test_atomic_write_error_names_the_target_not_the_temporary_file(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    target = tmp_path / "file" / "out.g2o"
    with pytest.raises(OSError) as info:
        with atomic_write(target):
            pass
    assert str(target) in str(info.value) and ".tmp" not in str(info.value)
    assert os.listdir(tmp_path) == ["file"]
