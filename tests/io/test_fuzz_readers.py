"""Malformed input never crashes a reader: the only exception is DataError naming the input.

Property-based (hypothesis, a few dozen inputs per reader, derandomised so CI is
reproducible; ``benchmarks/fuzz.py`` runs 10,000+): every reader of ``msf_torch.io`` gets a
valid input of its format with 1-3 mutations (``benchmarks/_fuzz_inputs.py``) and must
either return a result that keeps the io promises or raise a DataError whose path is inside
the input and whose line number the file has. Then one regression test per crash the
fuzzer found, each with the exact message expected.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings

from benchmarks._fuzz_inputs import ACCEPTED, READERS, FuzzCase, case_strategy, classify
from msf_torch.io import DataError, load_eqvio, read_euroc, read_native, read_pose_graph, read_tum
from msf_torch.io._tables import CleanReport, clean_stream, normalise_quaternions
from msf_torch.io.kitti_gtsam import load_kitti_gtsam


@pytest.mark.parametrize("reader", sorted(READERS))
def test_malformed_input_gives_data_error_or_valid_result(reader):
    seen: dict[str, int] = {}

    @settings(
        max_examples=25,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(case_strategy(reader))
    def check(case: FuzzCase) -> None:
        with tempfile.TemporaryDirectory(prefix="msf-fuzz-") as tmp:
            outcome, detail = classify(case, Path(tmp))
        seen[outcome] = seen.get(outcome, 0) + 1
        assert outcome in ACCEPTED, f"{outcome}: {detail} <- {case.mutations}"

    check()
    # the generator reaches both sides: readable inputs and rejected ones
    assert seen.get("data_error", 0) > 0


def test_oracle_catches_a_crash_and_a_silent_nan(tmp_path, monkeypatch):
    """The oracle is not vacuous: a reader that crashes, or lets a NaN through, is caught."""
    import benchmarks._fuzz_inputs as fuzz

    case = FuzzCase("tum", {"t.tum": b"0 0 0 0 0 0 0 1\n"}, "t.tum", False, [])
    assert classify(case, tmp_path / "plain") == ("ok", "")
    bad_line = FuzzCase("tum", {"t.tum": b"0 0 0 0 0 0 0 1\n1 x\n"}, "t.tum", False, [])
    outcome, detail = classify(bad_line, tmp_path / "short")
    assert outcome == "data_error" and ":2:" in detail

    def crashing(path, sort):
        raise IndexError("boom")

    def nan_trajectory(path, sort):
        traj = read_tum(path)
        traj.position[0, 0, 0] = float("nan")
        return traj

    for read, outcome in ((crashing, "crash"), (nan_trajectory, "bad_output")):
        spec = fuzz.READERS["tum"]
        monkeypatch.setitem(
            fuzz.READERS, "tum", fuzz.Reader(spec.name, spec.build, read, spec.check)
        )
        folder = tmp_path / outcome
        folder.mkdir()
        assert classify(case, folder)[0] == outcome


def _write(path: Path, text: str | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


IMU_HEADER = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n"
IMU_ROWS = "0.0,0,0,0,0,0,9.8\n0.01,0,0,0,0,0,9.8\n"


def _error(call, *args, **kwargs) -> DataError:
    with pytest.raises(DataError) as info:
        call(*args, **kwargs)
    return info.value


def test_csv_cell_over_the_field_limit_names_its_line(tmp_path):
    _write(tmp_path / "imu.csv", IMU_HEADER + IMU_ROWS + '"' + "1" * 200_000 + '",0,0,0,0,0,9.8\n')
    err = _error(read_native, tmp_path)
    assert err.line == 4 and "malformed CSV" in err.problem and "field limit" in err.problem


def test_empty_optional_stream_is_read_as_zero_samples(tmp_path):
    _write(tmp_path / "imu.csv", IMU_HEADER + IMU_ROWS)
    _write(tmp_path / "gnss.csv", "t,x,y,z\n")
    seq = read_native(tmp_path)
    assert seq.gnss.length == 0 and seq.gnss.sigma.shape == (1, 0, 3)
    report = CleanReport()
    out = clean_stream(report, "s", "f", {"t": np.zeros(0), "x": np.zeros((0, 6, 6))})
    assert out["x"].shape == (0, 6, 6) and report.dropped_nonfinite["s"] == 0


def test_line_numbers_count_cr_and_crlf_but_not_form_feed(tmp_path):
    text = IMU_HEADER + "0.0,0,0,0,0,0,9.8\r0.01,0,0,\x0c0,0,0,9.8\r\n0.02,0,x,0,0,0,9.8\n"
    _write(tmp_path / "imu.csv", text)
    err = _error(read_native, tmp_path)
    assert (err.line, err.field, err.problem) == (4, "gyro_y", "not a number: 'x'")


def test_non_utf8_byte_names_its_line(tmp_path):
    _write(tmp_path / "imu.csv", (IMU_HEADER + IMU_ROWS).encode() + b"0.02,0,\xff,0,0,0,9.8\n")
    err = _error(read_native, tmp_path)
    assert err.line == 4 and "not a UTF-8 text file" in err.problem and "0xff" in err.problem
    graph = _write(tmp_path / "g.g2o", b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n\x93\n")
    assert _error(read_pose_graph, graph).line == 2


@pytest.mark.parametrize(
    ("meta", "problem"),
    [
        ("[" * 100_000 + "]" * 100_000, "invalid JSON: nested too deeply"),
        ('{"a": ' + "1" * 5000 + "}", "invalid JSON: Exceeds the limit"),
    ],
)
def test_meta_json_that_python_cannot_decode(tmp_path, meta, problem):
    _write(tmp_path / "imu.csv", IMU_HEADER + IMU_ROWS)
    _write(tmp_path / "meta.json", meta)
    assert _error(read_native, tmp_path).problem.startswith(problem)
    arrays = {"imu/t": np.array([0.0, 0.01]), "imu/gyro": np.zeros((2, 3))}
    arrays |= {"imu/accel": np.zeros((2, 3)), "meta_json": np.array(meta)}
    np.savez(tmp_path / "run.npz", **arrays)
    assert _error(read_native, tmp_path / "run.npz").problem.startswith(problem)


@pytest.mark.parametrize("cut", [10, 200, -30])
def test_truncated_npz_is_a_data_error(tmp_path, cut):
    arrays = {"imu/t": np.arange(50) * 0.01, "imu/gyro": np.zeros((50, 3))}
    np.savez(tmp_path / "full.npz", **arrays, **{"imu/accel": np.zeros((50, 3))})
    data = (tmp_path / "full.npz").read_bytes()
    _write(tmp_path / "cut.npz", data[:cut])
    err = _error(read_native, tmp_path / "cut.npz")
    assert "npz" in err.problem and err.path == str(tmp_path / "cut.npz")


def test_euroc_yaml_not_utf8_or_not_numbers(tmp_path):
    imu = "#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n"
    imu += "1000,0,0,0,0,0,9.8\n2000,0,0,0,0,0,9.8\n"
    _write(tmp_path / "mav0" / "imu0" / "data.csv", imu)
    yaml_path = tmp_path / "mav0" / "imu0" / "sensor.yaml"
    _write(yaml_path, b"%YAML:1.0\nrate_hz: 200\n\x93\n")
    err = _error(read_euroc, tmp_path)
    assert err.line == 3 and "not a UTF-8" in err.problem
    _write(
        yaml_path, "%YAML:1.0\nT_BS:\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, a, 0, 1]\n"
    )
    err = _error(read_euroc, tmp_path)
    assert (err.field, err.problem) == ("T_BS.data[13]", "not a number: 'a'")
    _write(yaml_path, "%YAML:1.0\ngyroscope_noise_density: .nan\n")
    assert _error(read_euroc, tmp_path).field == "gyroscope_noise_density"
    _write(yaml_path, "%YAML:1.0\nrate_hz: 200\nbad: [\n")
    assert _error(read_euroc, tmp_path).line == 4  # the directive line still counts


def test_pose_graph_ids_too_long_and_chained_overflow(tmp_path):
    long_id = _write(tmp_path / "a.g2o", "VERTEX_SE3:QUAT " + "9" * 5000 + " 0 0 0 0 0 0 1\n")
    err = _error(read_pose_graph, long_id)
    assert (err.line, err.field) == (1, "id") and "5000 characters" in err.problem
    info = " ".join(["10 0 0 0 0 0", "10 0 0 0 0", "10 0 0 0", "100 0 0", "100 0", "25"])
    edges = "".join(f"EDGE3 {i} {i + 1} 1e308 0 0 0 0 0 {info}\n" for i in range(2))
    err = _error(read_pose_graph, _write(tmp_path / "b.graph", edges))
    assert (err.line, err.field) == (2, "x") and "overflows" in err.problem


def test_huge_quaternions_normalise_to_unit(tmp_path):
    q = np.array([[1e300, 1e300, 0.0, 0.0], [1e-200, 0.0, 1e-200, 0.0], [0.6, 0.8, 0.0, 0.0]])
    unit = normalise_quaternions(q)
    np.testing.assert_allclose(unit, [[0.5**0.5, 0.5**0.5, 0, 0], [0.5**0.5, 0, 0.5**0.5, 0], q[2]])
    tum = _write(tmp_path / "t.tum", "0 1 2 3 1e300 0 0 1e300\n")
    np.testing.assert_allclose(read_tum(tum).quaternion[0, 0].numpy(), [0.5**0.5, 0.5**0.5, 0, 0])
    graph = _write(tmp_path / "g.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 1e308 1e308\n")
    rot = read_pose_graph(graph).rotations[0]
    torch.testing.assert_close(rot @ rot.T, torch.eye(3, dtype=torch.float64))


def test_kitti_reader_takes_a_folder(tmp_path):
    _write(
        tmp_path / "KittiEquivBiasedImu.txt",
        "Time dt accelX accelY accelZ omegaX omegaY omegaZ\n"
        "10 10 0 0 9.8 0 0 0\n10.01 0.01 0 0 9.8 0 0 0\n",
    )
    _write(tmp_path / "KittiGps_converted.txt", "Time,X,Y,Z\n10,1,2,3\n")
    meta = "BodyPtx BodyPty BodyPtz BodyPrx BodyPry BodyPrz AccelerometerSigma GyroscopeSigma "
    meta += "IntegrationSigma AccelerometerBiasSigma GyroscopeBiasSigma AverageDeltaT\n"
    _write(
        tmp_path / "KittiEquivBiasedImu_metadata.txt",
        meta + "0 0 0 0 0 0 0.01 2e-4 0 2e-4 3e-6 0.01\n",
    )
    seq = load_kitti_gtsam(data_dir=tmp_path)
    assert seq.imu.length == 2 and seq.gnss.length == 1
    assert seq.meta["imu_noise"]["gyro_noise_sigma"] == 2e-4
    assert seq.meta["source"] == str(tmp_path)
    (tmp_path / "KittiGps_converted.txt").unlink()
    err = _error(load_kitti_gtsam, data_dir=tmp_path)
    assert err.path.endswith("KittiGps_converted.txt") and err.problem == "no such file"


def test_eqvio_meta_json_like_keys_do_not_crash(tmp_path):
    header = (
        "row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,"
        "bgx,bgy,bgz,bax,bay,baz,u_norm,v_norm,key,value\n"
    )
    rows = "meta" + "," * 20 + "T_ci_qw,1e308\n"
    for key in ("T_ci_tx", "T_ci_ty", "T_ci_tz", "T_ci_qy", "T_ci_qz"):
        rows += "meta" + "," * 20 + f"{key},0\n"
    rows += "meta" + "," * 20 + "T_ci_qx,1e308\n"
    rows += "imu,1.0,0,1,,,0,0,0,0,0,9.8,0,0,0,0,0,0,,,,\n"
    run = load_eqvio(_write(tmp_path / "e.csv", header + rows))
    torch.testing.assert_close(run.R_imu_cam @ run.R_imu_cam.T, torch.eye(3, dtype=torch.float64))
    assert json.dumps(run.meta)


def _scan_arrays(n: int = 3, k: int = 5) -> dict[str, np.ndarray]:
    return {
        "t": np.arange(n, dtype=np.float64) * 0.1,
        "angles": np.linspace(-1.0, 1.0, k),
        "ranges": np.full((n, k), 2.0),
        "odometry": np.zeros((n, 3)),
    }


@pytest.mark.parametrize("cut", [0, 10, 120])
def test_truncated_scan_file_is_a_data_error(tmp_path, cut):
    """Fuzzer finds: a cut .npz raised EOFError (empty member) or BadZipFile."""
    from msf_torch.io.scans import read_scans

    path = tmp_path / "scans.npz"
    np.savez(path, **_scan_arrays())
    path.write_bytes(path.read_bytes()[:cut])
    with pytest.raises(DataError, match="cannot read as .npz"):
        read_scans(path)


def test_scan_file_single_nan_time_and_nan_odometry(tmp_path):
    """Fuzzer finds: one scan with a NaN time crashed the error's own argmax; NaN odometry
    passed through to PLICP's initial guesses."""
    from msf_torch.io.scans import read_scans

    path = tmp_path / "scans.npz"
    arrays = _scan_arrays(n=1)
    arrays["t"][0] = np.nan
    np.savez(path, **arrays)
    with pytest.raises(DataError, match=r"finite and increasing \(scan 0\)"):
        read_scans(path)
    arrays = _scan_arrays()
    arrays["odometry"][2, 1] = np.inf
    np.savez(path, **arrays)
    with pytest.raises(DataError, match="non-finite pose at scan 2") as info:
        read_scans(path)
    assert info.value.field == "odometry"


def test_kitti_poses_single_infinite_time_is_a_data_error(tmp_path):
    """Fuzzer finds (seed 1): a lone time over the float range (400 nines) was read as inf."""
    from msf_torch.io.kitti_poses import read_kitti_poses

    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "times.txt").write_text("9" * 400 + "\n")
    with pytest.raises(DataError, match="non-finite value") as info:
        read_kitti_poses(tmp_path / "poses.txt", tmp_path / "times.txt")
    assert info.value.line == 1 and info.value.field == "t"


def test_kitti_poses_block_that_is_not_a_rotation_names_its_line(tmp_path):
    """Fuzzer finds (seed 2): a 1e308 token in the 3x3 block gave a non-unit quaternion."""
    from msf_torch.io.kitti_poses import read_kitti_poses

    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1e308 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match="pose 1: the 3x3 block is not a rotation") as info:
        read_kitti_poses(path)
    assert info.value.line == 2
    path.write_text("-1 0 0 0 0 1 0 0 0 0 1 0\n")  # a reflection: orthonormal, det -1
    with pytest.raises(DataError, match="det = -1"):
        read_kitti_poses(path)


def test_scan_angles_beyond_the_float_range_are_a_data_error(tmp_path):
    """Fuzzer finds (seed 2): huge beam angles made the spacing check compare NaN."""
    from msf_torch.io.scans import read_scans

    path = tmp_path / "scans.npz"
    arrays = _scan_arrays()
    arrays["angles"][1:] = [1e308, 1.5e308, 1.7e308, 1.79e308]
    arrays["angles"][0] = -1.7e308
    np.savez(path, **arrays)
    with pytest.raises(DataError, match="evenly spaced"):
        read_scans(path)
