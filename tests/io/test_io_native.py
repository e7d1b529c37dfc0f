"""Native .npz / CSV-folder format: round trips and the bad-input rules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch import load_sequence_config, run_eskf
from msf_torch.eval.metrics import ate
from msf_torch.io import DataError, load_sequence, read_native, write_native
from msf_torch.io.native import (
    IMU_COLUMNS,
    MAGNETOMETER_COLUMNS,
    POSE_COLUMNS,
    POSE_SIGMA_COLUMNS,
    write_stream_csv,
)
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import Magnetometer

IMU_HEADER = ",".join(IMU_COLUMNS) + "\n"


def _imu_rows(times, start=0.0) -> str:
    return "".join(f"{t},0.1,0.2,0.3,0.0,0.0,9.81\n" for t in times)


def _write(folder, name, text):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(text)
    return folder / name


def assert_sequences_close(a, b, tol=1e-12):
    assert a.names == b.names
    assert set(a.streams()) == set(b.streams())
    for key, stream in a.streams().items():
        other = getattr(b, key)
        for fname, value in stream.tensors().items():
            got = getattr(other, fname)
            assert got.shape == value.shape, (key, fname)
            if value.dtype == torch.bool:
                assert torch.equal(got, value), (key, fname)
            else:
                assert got.dtype == torch.float64
                torch.testing.assert_close(got, value, atol=tol, rtol=0, equal_nan=True)
    assert set(a.labels) == set(b.labels)
    for name, spans in a.labels.items():
        torch.testing.assert_close(b.labels[name], spans, atol=tol, rtol=0)


@pytest.mark.parametrize("target", ["run.npz", "run"])
def test_round_trip(tmp_path, sequence, target):
    path = write_native(sequence, tmp_path / target)
    back = read_native(path)
    assert back.names == ["run"]
    back.names = sequence.names
    assert_sequences_close(sequence, back)
    assert back.meta["sensor"] == sequence.meta["sensor"]
    assert back.meta["imu_noise"] == {"gyro_noise_density": 1.7e-4}
    assert back.meta["source"] == str(path)
    assert back.meta["dropped_nonfinite"] == {k: 0 for k in sequence.streams()}
    assert back.meta["dropped_duplicates"] == {k: 0 for k in sequence.streams()}
    # writing again onto the same target replaces it
    write_native(back, path)
    again = read_native(path)
    again.names = back.names
    assert_sequences_close(back, again)


def test_round_trip_imu_only_and_masked_samples(tmp_path, sequence):
    seq = dataclasses.replace(
        sequence, wheel=None, gnss=None, poses=None, ground_truth=None, labels={}, meta={}
    )
    seq.imu.mask[0, 3] = False
    for target in ("only.npz", "only"):
        back = read_native(write_native(seq, tmp_path / target))
        assert back.wheel is None and back.gnss is None and back.labels == {}
        assert "sensor" not in back.meta
        torch.testing.assert_close(back.imu.t, seq.imu.compact().t, atol=1e-12, rtol=0)


def test_folder_rewrite_removes_stale_tables(tmp_path, sequence):
    folder = tmp_path / "seq"
    write_native(sequence, folder)
    (folder / "notes.txt").write_text("kept")
    write_native(dataclasses.replace(sequence, wheel=None, labels={}, meta={}), folder)
    assert not (folder / "wheel.csv").exists()
    assert not (folder / "labels.csv").exists()
    assert not (folder / "meta.json").exists()
    assert (folder / "notes.txt").read_text() == "kept"
    assert read_native(folder).wheel is None


def test_write_rejects_batches(tmp_path, sequence, sequence_factory):
    from msf_torch.types import batch_sequences

    with pytest.raises(ValueError, match="B = 2"):
        write_native(batch_sequences([sequence, sequence_factory(1)]), tmp_path / "x.npz")


def test_nonfinite_rows_are_dropped_and_counted(tmp_path):
    folder = tmp_path / "nan"
    _write(
        folder,
        "imu.csv",
        IMU_HEADER
        + "0.0,0.1,0.2,0.3,0,0,9.81\n"
        + "0.01,nan,0.2,0.3,0,0,9.81\n"
        + "0.02,0.1,0.2,0.3,0,0,9.81\n"
        + "0.03,0.1,0.2,0.3,inf,0,9.81\n"
        + "nan,0.1,0.2,0.3,0,0,9.81\n"
        + "0.05,0.1,0.2,0.3,0,0,9.81\n",
    )
    _write(
        folder,
        "gnss.csv",
        "t,x,y,z,sigma_x,sigma_y,sigma_z\n0,1,2,3,nan,nan,nan\n1,1,2,3,inf,1,1\n",
    )
    seq = read_native(folder)
    assert seq.imu.t.tolist() == [[0.0, 0.02, 0.05]]
    assert seq.meta["dropped_nonfinite"] == {"imu": 3, "gnss": 1}
    assert seq.meta["dropped_lines"] == {"imu": [3, 5, 6], "gnss": [3]}
    # NaN sigma means "not given" and is kept
    assert seq.gnss.length == 1 and torch.isnan(seq.gnss.sigma).all()


def test_nonfinite_npz_samples_dropped_by_index(tmp_path, sequence):
    sequence.imu.gyro[0, 4, 1] = float("nan")
    back = read_native(write_native(sequence, tmp_path / "n.npz"))
    assert back.imu.length == sequence.imu.length - 1
    assert back.meta["dropped_nonfinite"]["imu"] == 1
    assert back.meta["dropped_indices"] == {"imu": [4]}


def test_backwards_time_names_file_and_line(tmp_path):
    folder = tmp_path / "back"
    _write(folder, "imu.csv", "# a comment line\n" + IMU_HEADER + _imu_rows([0.0, 0.2, 0.1, 0.3]))
    with pytest.raises(DataError) as info:
        read_native(folder)
    err = info.value
    assert err.path.endswith("imu.csv") and err.line == 5 and err.field == "t"
    assert "imu.csv:5: field 't': time goes backwards" in str(err)
    assert "sort=True" in str(err)
    seq = read_native(folder, sort=True)
    assert seq.imu.t.tolist() == [[0.0, 0.1, 0.2, 0.3]]
    assert seq.meta["sorted"] == {"imu": 1}
    assert load_sequence(folder, sort=True).imu.length == 4


def test_backwards_time_in_npz_names_key_and_sample(tmp_path, sequence):
    sequence.wheel.t[0, 7] = 0.0
    path = write_native(sequence, tmp_path / "b.npz")
    with pytest.raises(DataError, match=r"field 'wheel/t': sample 7: time goes backwards"):
        read_native(path)
    assert read_native(path, sort=True).wheel.t[0, 0] == 0.0


def test_duplicate_timestamps_keep_first(tmp_path):
    folder = tmp_path / "dup"
    _write(
        folder,
        "imu.csv",
        IMU_HEADER + "0.0,1,1,1,0,0,9\n0.1,2,2,2,0,0,9\n0.1,3,3,3,0,0,9\n0.2,4,4,4,0,0,9\n",
    )
    seq = read_native(folder)
    assert seq.imu.t.tolist() == [[0.0, 0.1, 0.2]]
    assert seq.imu.gyro[0, :, 0].tolist() == [1.0, 2.0, 4.0]
    assert seq.meta["dropped_duplicates"] == {"imu": 1}


def test_non_numeric_cell_names_file_line_field(tmp_path):
    folder = tmp_path / "bad"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0]) + "0.1,0.1,abc,0.3,0,0,9.81\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    err = info.value
    assert (err.line, err.field) == (3, "gyro_y")
    assert str(err) == f"{folder / 'imu.csv'}:3: field 'gyro_y': not a number: 'abc'"


def test_empty_cell_and_wrong_column_count(tmp_path):
    folder = tmp_path / "cols"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0]) + "0.1,0.1,0.2,0.3,0,0\n")
    with pytest.raises(DataError, match=r"imu.csv:3: expected 7 columns .* got 6"):
        read_native(folder)
    _write(folder, "imu.csv", IMU_HEADER + "0.1,0.1,,0.3,0,0,9.81\n")
    with pytest.raises(DataError, match="field 'gyro_y': empty cell"):
        read_native(folder)


def test_missing_and_unknown_columns(tmp_path):
    folder = tmp_path / "hdr"
    _write(folder, "imu.csv", "t,gyro_x,gyro_y,accel_x,accel_y,accel_z\n0,0,0,0,0,9.8\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (1, "gyro_z")
    assert "missing column" in str(info.value)
    _write(folder, "imu.csv", IMU_HEADER.strip() + ",temp\n0,0,0,0,0,0,9.8,20\n")
    with pytest.raises(DataError, match="field 'temp': unknown column"):
        read_native(folder)
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0]))
    _write(folder, "gnss.csv", "t,x,y,z,sigma_x\n0,1,2,3,1\n")
    with pytest.raises(DataError, match="field 'sigma_y': missing column"):
        read_native(folder)


def test_missing_imu_table(tmp_path):
    folder = tmp_path / "noimu"
    _write(folder, "wheel.csv", "t,left_speed,right_speed\n0,1,1\n")
    _write(folder, "gnss.csv", "t,x,y,z\n0,1,2,3\n")
    _write(folder, "notes.txt", "x")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert info.value.problem == (
        "imu.csv missing in this folder (the one required table; found: gnss.csv, notes.txt, "
        "wheel.csv)"
    )
    with pytest.raises(DataError) as info:
        load_sequence(folder)  # detected: native tables, no imu.csv (not "unrecognised")
    assert info.value.problem == "imu.csv missing in this folder (found: gnss.csv, wheel.csv)"


@pytest.mark.parametrize("name", ["imu.csv", "gnss.csv", "meta.json", "poses_vo.csv"])
def test_a_file_of_a_native_folder_asks_for_the_folder(tmp_path, name):
    folder = tmp_path / "run"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.01]))
    file = _write(folder, name, "t,x,y,z\n") if name != "imu.csv" else folder / name
    for read in (load_sequence, read_native):
        with pytest.raises(DataError) as info:
            read(file)
        assert info.value.path == str(file)
        assert info.value.problem == f"pass the folder {folder}, not one of its files"
    with pytest.raises(DataError, match="pass the folder"):
        load_sequence(file, fmt="csv")


def test_unknown_csv_files_warn_once_and_are_ignored(tmp_path):
    folder = tmp_path / "run"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.01]))
    _write(folder, "gps.csv", "t,x,y,z\n0,1,2,3\n")
    _write(folder, "poses_a b.csv", "t\n")  # not a valid pose source name
    _write(folder, "sim.json", "{}")  # not a CSV: no warning
    with pytest.warns(UserWarning) as caught:
        seq = read_native(folder)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert message.startswith(
        f"{folder}: ignored CSV files with names a native folder does not use: gps.csv, "
        "poses_a b.csv (recognised: imu.csv, wheel.csv, gnss.csv, gnss_velocity.csv, "
        "gnss_heading.csv, magnetometer.csv, poses.csv, ground_truth.csv, poses_<name>.csv, "
        "labels.csv, meta.json)"
    )
    assert seq.gnss is None and seq.imu.length == 2


def test_pose_uncertainty_forms_and_quaternion_normalisation(tmp_path):
    folder = tmp_path / "poses"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0]))
    header = ",".join(POSE_COLUMNS + POSE_SIGMA_COLUMNS)
    _write(folder, "poses.csv", header + "\n0,1,2,3,2,0,0,0,0.1,0.2,0.3,0.01,0.02,0.03\n")
    seq = read_native(folder)
    assert seq.poses.quaternion.tolist() == [[[1.0, 0.0, 0.0, 0.0]]]
    expected = torch.diag(torch.tensor([0.1, 0.2, 0.3, 0.01, 0.02, 0.03]) ** 2)
    torch.testing.assert_close(seq.poses.covariance[0, 0], expected.double())
    # no uncertainty columns -> NaN covariance
    _write(folder, "poses.csv", ",".join(POSE_COLUMNS) + "\n0,1,2,3,1,0,0,0\n")
    assert torch.isnan(read_native(folder).poses.covariance).all()
    # both forms at once is an error
    _write(folder, "poses.csv", header + ",c00\n0,1,2,3,1,0,0,0,1,1,1,1,1,1,1\n")
    with pytest.raises(DataError, match="one set of optional columns"):
        read_native(folder)
    # a zero quaternion is an error, a negative sigma too
    _write(folder, "poses.csv", ",".join(POSE_COLUMNS) + "\n0,1,2,3,0,0,0,0\n")
    with pytest.raises(DataError, match=r"poses.csv:2: field 'qw': quaternion"):
        read_native(folder)
    _write(folder, "poses.csv", header + "\n0,1,2,3,1,0,0,0,0.1,-0.2,0.3,0.01,0.02,0.03\n")
    with pytest.raises(DataError, match="field 'sigma_y': a standard deviation"):
        read_native(folder)


def test_labels_and_meta_json_errors(tmp_path):
    folder = tmp_path / "lab"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0]))
    _write(folder, "labels.csv", "name,t_start,t_end\nslip,1,2\nslip,3,4\nweather:rain,0,9\n")
    seq = read_native(folder)
    assert seq.labels["slip"].tolist() == [[[1.0, 2.0], [3.0, 4.0]]]
    assert seq.labels["weather:rain"].shape == (1, 1, 2)
    _write(folder, "labels.csv", "name,t_start,t_end\nslip,2,1\n")
    with pytest.raises(DataError, match="labels.csv:2: field 't_end'"):
        read_native(folder)
    (folder / "labels.csv").unlink()
    _write(folder, "meta.json", '{\n  "wheel_track_m": 0.5,\n  oops\n}\n')
    with pytest.raises(DataError, match=r"meta.json:3: invalid JSON"):
        read_native(folder)


def test_npz_schema_errors(tmp_path):
    path = tmp_path / "s.npz"
    np.savez(
        path, **{"imu/t": np.zeros(3), "imu/gyro": np.zeros((3, 2)), "imu/accel": np.zeros((3, 3))}
    )
    with pytest.raises(DataError, match=r"field 'imu/gyro': shape \(3, 2\), expected \(3, 3\)"):
        read_native(path)
    np.savez(path, **{"imu/t": np.zeros(3), "imu/accel": np.zeros((3, 3))})
    with pytest.raises(DataError, match="field 'imu/gyro': missing key"):
        read_native(path)
    np.savez(
        path,
        **{
            "imu/t": np.arange(3.0),
            "imu/gyro": np.zeros((3, 3)),
            "imu/accel": np.zeros((3, 3)),
            "imu/temperature": np.zeros(3),
        },
    )
    with pytest.raises(DataError, match="field 'imu/temperature': unknown key"):
        read_native(path)
    path.write_bytes(b"not a zip")
    with pytest.raises(DataError, match="not a readable .npz"):
        read_native(path)
    # a negative sigma is refused naming key and sample, as the CSV reader names the cell
    imu = {"imu/t": np.arange(3.0), "imu/gyro": np.zeros((3, 3)), "imu/accel": np.zeros((3, 3))}
    for stream, values in (
        ("gnss", {"gnss/position": np.zeros((3, 3)), "gnss/sigma": np.full((3, 3), 0.5)}),
        ("gnss_heading", {"gnss_heading/heading": np.zeros(3), "gnss_heading/sigma": np.ones(3)}),
        ("magnetometer", {"magnetometer/field": np.ones((3, 3)), "magnetometer/sigma": np.ones(3)}),
    ):
        values[f"{stream}/sigma"][1] = np.nan  # "not given": fine
        np.savez(path, **imu, **{f"{stream}/t": np.arange(3.0)}, **values)
        assert read_native(path) is not None
        values[f"{stream}/sigma"][2] = -0.1
        np.savez(path, **imu, **{f"{stream}/t": np.arange(3.0)}, **values)
        with pytest.raises(DataError, match=rf"field '{stream}/sigma': sample 2: .* negative"):
            read_native(path)


def test_gnss_velocity_table_round_trips_with_an_unmeasured_up_component(tmp_path):
    folder = tmp_path / "run"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.5, 1.0, 1.5, 2.0]))
    rows = [
        "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz",
        "0.5,1.25,-0.5,0.125,0.05,0.05,0.1",
        "1.0,1.5,-0.25,nan,nan,nan,nan",  # RMC-style: horizontal only, default sigma
        "1.5,nan,0.0,0.0,0.1,0.1,0.1",  # no east component: not a measurement
        "2.0,1.75,0.0,inf,0.1,0.1,0.1",  # inf is never "not given"
    ]
    _write(folder, "gnss_velocity.csv", "\n".join(rows) + "\n")
    seq = read_native(folder)
    vel = seq.gnss_velocity
    assert seq.meta["dropped_nonfinite"]["gnss_velocity"] == 2
    assert seq.meta["dropped_lines"]["gnss_velocity"] == [4, 5]
    assert vel.t.tolist() == [[0.5, 1.0]]
    assert vel.velocity[0, 0].tolist() == [1.25, -0.5, 0.125]
    assert vel.velocity[0, 1, :2].tolist() == [1.5, -0.25] and bool(vel.velocity[0, 1, 2].isnan())
    assert vel.sigma[0, 0].tolist() == [0.05, 0.05, 0.1] and bool(vel.sigma[0, 1].isnan().all())
    for target in (tmp_path / "copy", tmp_path / "copy.npz"):
        back = read_native(write_native(seq, target)).gnss_velocity
        for name in ("t", "velocity", "sigma"):
            assert torch.equal(
                getattr(back, name).nan_to_num(7.0), getattr(vel, name).nan_to_num(7.0)
            )
    _write(
        folder,
        "gnss_velocity.csv",
        "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz\n0.5,1,2,3,0.1,-0.1,0.1\n",
    )
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (2, "sigma_vy")


def test_gnss_heading_table_round_trips_with_default_sigmas(tmp_path):
    """gnss_heading.csv: any angle kept as given (the filter wraps it), a NaN sigma means the
    configured default, a NaN heading or an inf sigma drops the row, a negative sigma names
    its line; CSV, npz and write_stream_csv give back the same stream."""
    folder = tmp_path / "run"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.5, 1.0, 1.5, 2.0]))
    rows = [
        "heading,t,sigma_heading",  # any column order
        "0.25,0.5,0.01",
        "7.5,1.0,nan",  # beyond 2 pi, no sigma: kept as it is
        "nan,1.5,0.01",  # no heading: not a measurement
        "-0.5,2.0,inf",  # inf is never "not given"
        "-0.5,2.0,0.02",  # the same time again: a duplicate
    ]
    _write(folder, "gnss_heading.csv", "\n".join(rows) + "\n")
    seq = read_native(folder)
    heading = seq.gnss_heading
    assert seq.meta["dropped_nonfinite"]["gnss_heading"] == 2
    assert seq.meta["dropped_lines"]["gnss_heading"] == [4, 5]
    assert seq.meta["dropped_duplicates"]["gnss_heading"] == 0
    assert heading.t.tolist() == [[0.5, 1.0, 2.0]] and heading.heading.shape == (1, 3)
    assert heading.heading.tolist() == [[0.25, 7.5, -0.5]]
    assert heading.sigma[0, 0] == 0.01 and bool(heading.sigma[0, 1].isnan())
    for target in (tmp_path / "copy", tmp_path / "copy.npz"):
        back = read_native(write_native(seq, target)).gnss_heading
        for name in ("t", "heading", "sigma", "mask"):
            assert torch.equal(
                getattr(back, name).nan_to_num(7.0), getattr(heading, name).nan_to_num(7.0)
            )
    assert (tmp_path / "copy" / "gnss_heading.csv").read_text().splitlines()[0] == (
        "t,heading,sigma_heading"
    )
    no_sigma = dataclasses.replace(heading, sigma=torch.full_like(heading.sigma, float("nan")))
    table = write_stream_csv(tmp_path / "copy" / "gnss_heading.csv", "gnss_heading", no_sigma)
    assert table.read_text() == "t,heading\n0.5,0.25\n1.0,7.5\n2.0,-0.5\n"
    assert bool(read_native(tmp_path / "copy").gnss_heading.sigma.isnan().all())
    npz = dict(np.load(tmp_path / "copy.npz"))
    assert npz["gnss_heading/heading"].shape == (3,) and npz["gnss_heading/sigma"].shape == (3,)
    del npz["gnss_heading/sigma"]  # optional
    np.savez(tmp_path / "bare.npz", **npz)
    assert bool(read_native(tmp_path / "bare.npz").gnss_heading.sigma.isnan().all())
    npz["gnss_heading/heading"] = np.zeros((3, 1))
    np.savez(tmp_path / "bad.npz", **npz)
    with pytest.raises(DataError) as info:
        read_native(tmp_path / "bad.npz")
    assert info.value.field == "gnss_heading/heading" and "expected (3,)" in info.value.problem
    _write(folder, "gnss_heading.csv", "t,heading,sigma_heading\n0.5,1.0,0.1\n1.0,1.0,-0.1\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (3, "sigma_heading")
    _write(folder, "gnss_heading.csv", "t,heading,sigma\n0.5,1.0,0.1\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (1, "sigma")


def test_magnetometer_table_round_trips_with_default_sigmas(tmp_path):
    """magnetometer.csv (uT, body frame): a NaN sigma means the configured default, a NaN
    field component or an inf sigma drops the row, a negative sigma names its line; CSV,
    npz and write_stream_csv give back the same stream."""
    folder = tmp_path / "run"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.5, 1.0, 1.5, 2.0]))
    rows = [
        "mz,t,mx,sigma,my",  # any column order
        "-41.5,0.5,22.25,0.4,3.125",
        "-40.0,1.0,-12.5,nan,20.0",  # no sigma: the configured default
        "-40.0,1.5,nan,0.4,20.0",  # no x component: not a measurement
        "-39.5,2.0,1.0,inf,2.0",  # inf is never "not given"
        "-39.0,2.5,1.5,0.3,2.5",
    ]
    _write(folder, "magnetometer.csv", "\n".join(rows) + "\n")
    seq = read_native(folder)
    mag = seq.magnetometer
    assert isinstance(mag, Magnetometer)
    assert seq.meta["dropped_nonfinite"]["magnetometer"] == 2
    assert seq.meta["dropped_lines"]["magnetometer"] == [4, 5]
    assert mag.t.tolist() == [[0.5, 1.0, 2.5]] and mag.sigma.shape == (1, 3)
    assert mag.field[0].tolist() == [[22.25, 3.125, -41.5], [-12.5, 20.0, -40.0], [1.5, 2.5, -39.0]]
    assert mag.sigma[0, 0] == 0.4 and bool(mag.sigma[0, 1].isnan())
    for target in (tmp_path / "copy", tmp_path / "copy.npz"):
        back = read_native(write_native(seq, target)).magnetometer
        for name in ("t", "field", "sigma", "mask"):
            assert torch.equal(
                getattr(back, name).nan_to_num(7.0), getattr(mag, name).nan_to_num(7.0)
            )
    assert (tmp_path / "copy" / "magnetometer.csv").read_text().splitlines()[
        0
    ] == "t,mx,my,mz,sigma"
    no_sigma = dataclasses.replace(mag, sigma=torch.full_like(mag.sigma, float("nan")))
    table = write_stream_csv(tmp_path / "copy" / "magnetometer.csv", "magnetometer", no_sigma)
    assert table.read_text().splitlines() == [
        ",".join(MAGNETOMETER_COLUMNS),
        "0.5,22.25,3.125,-41.5",
        "1.0,-12.5,20.0,-40.0",
        "2.5,1.5,2.5,-39.0",
    ]
    assert bool(read_native(tmp_path / "copy").magnetometer.sigma.isnan().all())
    npz = dict(np.load(tmp_path / "copy.npz"))
    assert npz["magnetometer/field"].shape == (3, 3) and npz["magnetometer/sigma"].shape == (3,)
    del npz["magnetometer/sigma"]  # optional
    np.savez(tmp_path / "bare.npz", **npz)
    assert bool(read_native(tmp_path / "bare.npz").magnetometer.sigma.isnan().all())
    npz["magnetometer/field"] = np.zeros(3)
    np.savez(tmp_path / "bad.npz", **npz)
    with pytest.raises(DataError) as info:
        read_native(tmp_path / "bad.npz")
    assert info.value.field == "magnetometer/field" and "expected (3, 3)" in info.value.problem
    _write(folder, "magnetometer.csv", "t,mx,my,mz,sigma\n0.5,1,2,3,0.1\n1.0,1,2,3,-0.1\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (3, "sigma")
    assert info.value.path == str(folder / "magnetometer.csv")
    _write(folder, "magnetometer.csv", "t,mx,my,mz,sigma_x\n0.5,1.0,2.0,3.0,0.1\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert (info.value.line, info.value.field) == (1, "sigma_x")
    _write(folder, "magnetometer.csv", "t,mx,my,mz\n0.5,1.0,2.0\n")
    with pytest.raises(DataError) as info:
        read_native(folder)
    assert info.value.line == 2


@pytest.mark.parametrize("target", ["run.npz", "run"])
def test_round_trip_with_a_magnetometer(tmp_path, sequence, target):
    rng = np.random.default_rng(3)
    n = 7
    sigma = rng.uniform(0.1, 1.0, n)
    sigma[2] = np.nan
    mag = Magnetometer(
        t=torch.as_tensor(100.0 + np.arange(n) / 9.0).unsqueeze(0),
        field=torch.as_tensor(rng.normal(size=(n, 3)) * 30.0).unsqueeze(0),
        sigma=torch.as_tensor(sigma).unsqueeze(0),
        mask=torch.ones((1, n), dtype=torch.bool),
    )
    seq = dataclasses.replace(sequence, magnetometer=mag)
    back = read_native(write_native(seq, tmp_path / target))
    back.names = seq.names
    assert_sequences_close(seq, back)  # quaternions re-normalised: 1e-16 off
    for name in ("t", "field", "sigma", "mask"):  # the magnetometer exactly
        got, want = getattr(back.magnetometer, name), getattr(mag, name)
        assert torch.equal(got.nan_to_num(7.0), want.nan_to_num(7.0))
    assert back.meta["dropped_nonfinite"]["magnetometer"] == 0
    # a later write without the stream removes its table from the folder
    write_native(sequence, tmp_path / target)
    assert read_native(tmp_path / target).magnetometer is None


def test_meta_json_lever_arms_and_baseline_set_the_config_unless_the_yaml_does(tmp_path):
    folder = tmp_path / "geometry"
    _write(folder, "imu.csv", IMU_HEADER + _imu_rows([0.0, 0.01]))
    _write(
        folder,
        "meta.json",
        '{"gnss_lever_arm_m": [0.4, -0.1, 1.2], "wheel_lever_arm_m": [-0.3, 0, -0.2],'
        ' "gnss_heading_baseline_m": [0, 1.5, 0], "wheel_track_m": 0.6}',
    )
    seq = read_native(folder)
    cfg = load_sequence_config(seq.meta)
    assert cfg.gnss_lever_arm_m == [0.4, -0.1, 1.2]
    assert cfg.wheel_lever_arm_m == [-0.3, 0.0, -0.2]
    assert cfg.gnss_heading_baseline_m == [0.0, 1.5, 0.0]
    yaml = tmp_path / "robot.yaml"
    yaml.write_text("gnss_lever_arm_m: [0.0, 0.0, 0.5]\n")
    cfg = load_sequence_config(seq.meta, yaml)
    assert cfg.gnss_lever_arm_m == [0.0, 0.0, 0.5]  # the YAML's
    assert cfg.wheel_lever_arm_m == [-0.3, 0.0, -0.2]  # the folder's
    _write(folder, "meta.json", '{"wheel_lever_arm_m": [0.1, "x", 0]}')
    with pytest.raises(DataError, match=r"meta.json: field 'wheel_lever_arm_m'"):
        read_native(folder)


def test_a_simulated_antenna_lever_arm_reaches_the_filter(tmp_path):
    """The simulator records its antenna's lever arm in ``meta["sensor"]``: ``msf run`` on
    a written run (read back from disk) puts the estimate at the IMU, not at the antenna."""
    sim = SimConfig(duration_s=40.0, gnss_lever_arm_m=(0.6, 0.3, 1.5))
    write_native(simulate_run(sim, 3).sequence, tmp_path / "run.npz")
    seq = load_sequence(tmp_path / "run.npz")
    cfg = load_sequence_config(seq.meta)
    assert cfg.gnss_lever_arm_m == [0.6, 0.3, 1.5]
    with torch.inference_mode():
        read = ate(run_eskf(seq, cfg).trajectory(), seq.ground_truth, align="none")["rmse"]
        none = run_eskf(seq, cfg.replace(gnss_lever_arm_m=[0.0, 0.0, 0.0])).trajectory()
    # 0.34 m (0.32 m for the same seed simulated without a lever arm) against 1.66 m
    assert read < 0.6 and ate(none, seq.ground_truth, align="none")["rmse"] > 1.2
