"""The EuRoC V1_01_easy EqVIO replay file shipped in the gtsam wheel, and malformed copies."""

from __future__ import annotations

import csv
import importlib.util
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.io import DataError, EqvioRun, MissingExtraError, gtsam_data_path, load_eqvio
from msf_torch.io.eqvio import EQVIO_FILE

# EuRoC MAV dataset, mav0/cam0/sensor.yaml: T_BS (body = IMU, sensor = cam0), published
# independently of the gtsam file.
EUROC_T_BODY_CAM0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    ]
)


@pytest.fixture(scope="module")
def run() -> EqvioRun:
    pytest.importorskip("gtsam")
    return load_eqvio()


@pytest.fixture(scope="module")
def raw_rows() -> list[dict[str, str]]:
    pytest.importorskip("gtsam")
    with open(gtsam_data_path(EQVIO_FILE), newline="") as handle:
        return list(csv.DictReader(handle))


def test_counts_match_plain_csv(run, raw_rows):
    kinds = Counter(r["row_type"] for r in raw_rows)
    assert kinds == {"meta": 52, "imu": 6001, "vision_feature": 13316}
    feats = [r for r in raw_rows if r["row_type"] == "vision_feature"]
    assert run.imu.t.shape == (1, kinds["imu"])
    assert run.imu.mask.all()
    assert run.imu_seq.shape == (kinds["imu"],)
    assert run.num_observations == kinds["vision_feature"]
    assert run.num_frames == len({r["frame_idx"] for r in feats}) == 601
    assert run.num_landmarks == len({r["landmark_id"] for r in feats}) == 307
    assert run.meta == {r["key"]: r["value"] for r in raw_rows if r["row_type"] == "meta"}
    assert len(run.meta) == 52
    # per-frame counts and the flat index tensors agree with the file
    per_frame = Counter(int(r["frame_idx"]) for r in feats)
    counts = torch.bincount(run.obs_frame, minlength=run.num_frames)
    assert counts.tolist() == [per_frame[int(i)] for i in run.frame_idx]
    first = feats[0]
    assert run.landmark_ids[run.obs_landmark[0]].item() == int(first["landmark_id"])
    assert run.obs_normalized[0].tolist() == [float(first["u_norm"]), float(first["v_norm"])]
    assert run.obs_landmark.max().item() == run.num_landmarks - 1
    assert (run.landmark_ids.diff() > 0).all()


def test_dtypes_and_shapes(run):
    assert run.imu.t.dtype == run.imu.gyro.dtype == run.obs_normalized.dtype == torch.float64
    for name in ("obs_frame", "obs_landmark", "landmark_ids", "frame_idx", "frame_seq"):
        assert getattr(run, name).dtype == torch.int64, name
    assert run.imu.gyro.shape == run.imu.accel.shape == (1, 6001, 3)
    assert run.obs_normalized.shape == (13316, 2)
    assert run.gyro_bias_velocity.shape == run.accel_bias_velocity.shape == (1, 6001, 3)
    assert (run.gyro_bias_velocity == 0).all() and (run.accel_bias_velocity == 0).all()
    assert run.cleaning["dropped_nonfinite"] == {"imu": 0, "features": 0}
    assert run.cleaning["dropped_duplicates"] == {"imu": 0, "features": 0}


def test_times(run, raw_rows):
    t = run.imu.t[0]
    assert t[0].item() == 0.0
    assert (t.diff() > 0).all()
    assert (run.frame_times.diff() > 0).all()
    assert run.duration == pytest.approx(30.0, abs=1e-6)
    assert run.duration == pytest.approx(float(run.meta["duration_sec"]), abs=1e-6)
    assert run.t0_abs == float(run.meta["t0_abs"])
    # relative times equal the file's t_rel column
    t_rel = [float(r["t_rel"]) for r in raw_rows if r["row_type"] == "imu"]
    assert np.allclose(t.numpy(), t_rel, atol=1e-6)
    # EuRoC: IMU at 200 Hz, cam0 at 20 Hz
    assert 1.0 / t.diff().median().item() == pytest.approx(200.0, rel=1e-3)
    assert 1.0 / run.frame_times.diff().median().item() == pytest.approx(20.0, rel=1e-3)
    assert run.frame_times[0].item() == 0.0
    assert run.frame_times[-1].item() == pytest.approx(30.0, abs=1e-6)
    assert run.frame_idx.tolist() == list(range(601))


def test_gravity_at_rest(run):
    # the MAV sits on the floor for the first seconds; EuRoC's IMU x axis points up
    mean = run.imu.accel[0, :400].mean(0)
    assert mean.norm().item() == pytest.approx(9.81, abs=0.15)
    assert mean.abs().argmax().item() == 0 and mean[0] > 0


def test_noise_and_intrinsics(run):
    fx, fy, cx, cy = run.intrinsics.tolist()
    assert (fx, fy, cx, cy) == (458.654, 457.29599999999999, 367.21499999999997, 248.375)
    var_px = float(run.meta["eqf.measurement_noise_variance_px"])
    var_norm = float(run.meta["eqf.measurement_noise_variance_norm"])
    assert run.feature_sigma_px == pytest.approx(math.sqrt(var_px))
    assert run.feature_sigma_normalized == pytest.approx(math.sqrt(var_norm))
    assert run.feature_sigma_normalized == pytest.approx(0.0042137, rel=1e-4)
    # the normalized variance is the pixel one over fx * fy
    assert var_norm == pytest.approx(var_px / (fx * fy), rel=1e-5)
    assert run.imu_noise["gyro_noise_sigma"] == pytest.approx(
        math.sqrt(float(run.meta["eqf.input_var_gyr"]))
    )
    assert set(run.imu_noise) == {
        "gyro_noise_sigma",
        "accel_noise_sigma",
        "gyro_bias_rw_sigma",
        "accel_bias_rw_sigma",
    }
    assert run.eqf_params["eqf.input_var_acc"] == float(run.meta["eqf.input_var_acc"])
    assert "eqf.coordinate_choice" not in run.eqf_params  # text, kept in meta only
    # normalized coordinates of a 752 x 480 image: |u| < cx / fx + margin
    assert run.obs_normalized.abs().max().item() < 1.5


def test_extrinsics_orthonormal_and_equal_to_euroc_t_bs(run):
    rot, trans = run.R_imu_cam, run.t_imu_cam
    assert rot.shape == (3, 3) and trans.shape == (3,)
    assert torch.allclose(rot.T @ rot, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.linalg.det(rot).item() == pytest.approx(1.0, abs=1e-12)
    assert np.abs(rot.numpy() - EUROC_T_BODY_CAM0[:, :3]).max() < 1e-9
    assert np.abs(trans.numpy() - EUROC_T_BODY_CAM0[:, 3]).max() < 1e-9


def _angle_deg(rot: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))


def test_extrinsic_direction_from_the_data(run):
    """Independent of any published calibration: the camera's angular rate fitted to the
    feature flow of consecutive frames, rotated by ``R_imu_cam``, matches the gyro.

    For a camera turning at ``w`` (camera frame), a static point's normalized coordinates
    move at ``du = w_x u v - w_y (1 + u^2) + w_z v`` and ``dv = w_x (1 + v^2) - w_y u v -
    w_z u`` (translation ignored, outlier tracks trimmed). The rotation that best maps the
    fitted rates onto the gyro rates (Kabsch) is within a few degrees of ``R_imu_cam`` and
    about a half turn from its transpose (the other direction).
    """
    t, gyro = run.imu.t[0].numpy(), run.imu.gyro[0].numpy()
    ft = run.frame_times.numpy()
    grid = np.full((run.num_frames, run.num_landmarks, 2), np.nan)
    grid[run.obs_frame.numpy(), run.obs_landmark.numpy()] = run.obs_normalized.numpy()

    def fit(p: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = p[:, 0], p[:, 1]
        a = np.stack([np.c_[u * v, -(1 + u * u), v], np.c_[1 + v * v, -u * v, -u]], 1)
        w = np.linalg.lstsq(a.reshape(-1, 3), flow.reshape(-1), rcond=None)[0]
        return w, np.linalg.norm(a @ w - flow, axis=1)

    cam_rates, imu_rates = [], []
    for k in range(run.num_frames - 1):
        a, b = grid[k], grid[k + 1]
        ok = np.isfinite(a[:, 0]) & np.isfinite(b[:, 0])
        if ok.sum() < 8:
            continue
        p, flow = (a[ok] + b[ok]) / 2, (b[ok] - a[ok]) / (ft[k + 1] - ft[k])
        w, err = fit(p, flow)
        keep = err <= 3 * np.median(err)
        if keep.sum() >= 6:
            w, _ = fit(p[keep], flow[keep])
        cam_rates.append(w)
        imu_rates.append(gyro[(t >= ft[k]) & (t <= ft[k + 1])].mean(0))
    wc, wi = np.array(cam_rates), np.array(imu_rates)
    assert len(wc) > 500
    u, _, vt = np.linalg.svd(wc.T @ wi)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    fitted = vt.T @ d @ u.T  # wi ~ fitted @ wc
    rot = run.R_imu_cam.numpy()
    assert _angle_deg(fitted.T @ rot) < 15.0
    assert _angle_deg(fitted.T @ rot.T) > 150.0
    err_right = np.median(np.linalg.norm(wi - wc @ rot.T, axis=1))
    err_wrong = np.median(np.linalg.norm(wi - wc @ rot, axis=1))
    assert err_right < 0.5 * err_wrong


def test_to(run):
    moved = run.to("cpu", torch.float32)
    assert moved.obs_normalized.dtype == torch.float32
    assert moved.imu.gyro.dtype == torch.float32
    assert moved.obs_frame.dtype == torch.int64
    assert run.obs_normalized.dtype == torch.float64


def test_missing_gtsam_names_the_extra(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else real(name, *a)
    )
    with pytest.raises(MissingExtraError, match=r"pip install 'msf_torch\[peers\]'") as info:
        load_eqvio()
    assert info.value.name == "gtsam"


# --- small hand-written files -----------------------------------------------------------

HEADER = (
    "row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,"
    "bgx,bgy,bgz,bax,bay,baz,u_norm,v_norm,key,value"
)


def _meta(key: str, value: str) -> str:
    return "meta" + "," * 19 + f",{key},{value}"


def _imu(t: float, seq: int, gx: str = "0.1") -> str:
    return f"imu,{t},{t - 100.0},{seq},,,{gx},0.2,0.3,9.8,0.1,0.2,0,0,0,0,0,0,,,,"


def _feat(t: float, seq: int, frame: int, lm: int, u: str = "0.1", v: str = "-0.2") -> str:
    return f"vision_feature,{t},{t - 100.0},{seq},{frame},{lm}" + "," * 12 + f",{u},{v},,"


def _lines() -> list[str]:
    return [
        HEADER,  # line 1
        _meta("T_ci_tx", "0.1"),  # 2
        _meta("T_ci_ty", "0.2"),  # 3
        _meta("T_ci_tz", "0.3"),  # 4
        _meta("T_ci_qw", "1"),  # 5
        _meta("T_ci_qx", "0"),  # 6
        _meta("T_ci_qy", "0"),  # 7
        _meta("T_ci_qz", "0"),  # 8
        _meta("eqf.measurement_noise_variance_norm", "4e-6"),  # 9
        _feat(100.0, 0, 0, 7),  # 10
        _feat(100.0, 0, 0, 3),  # 11
        _imu(100.0, 1),  # 12
        _imu(100.005, 2),  # 13
        _feat(100.01, 3, 1, 7, "0.15"),  # 14
        _imu(100.01, 4),  # 15
    ]


def _write(tmp_path: Path, lines: list[str]) -> Path:
    path = tmp_path / "eqvio.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_small_file(tmp_path):
    run = load_eqvio(_write(tmp_path, _lines()))
    assert run.imu.t[0].tolist() == pytest.approx([0.0, 0.005, 0.01])
    assert run.t0_abs == 100.0
    assert run.imu_seq.tolist() == [1, 2, 4]
    assert run.frame_times.tolist() == pytest.approx([0.0, 0.01])
    assert run.frame_seq.tolist() == [0, 3]
    assert run.landmark_ids.tolist() == [3, 7]
    assert run.obs_frame.tolist() == [0, 0, 1]
    assert run.obs_landmark.tolist() == [1, 0, 1]
    assert run.obs_normalized[:, 0].tolist() == [0.1, 0.1, 0.15]
    assert torch.equal(run.R_imu_cam, torch.eye(3, dtype=torch.float64))
    assert run.t_imu_cam.tolist() == [0.1, 0.2, 0.3]
    assert run.feature_sigma_normalized == pytest.approx(2e-3)
    assert run.feature_sigma_px is None and run.intrinsics is None and run.imu_noise == {}


def test_no_extrinsics_and_empty_bias_columns(tmp_path):
    lines = [ln for ln in _lines() if "T_ci_" not in ln]
    lines = [
        ln.replace(",0,0,0,0,0,0,,,,", ",,,,,,,,,,") if ln.startswith("imu") else ln for ln in lines
    ]
    run = load_eqvio(_write(tmp_path, lines))
    assert run.R_imu_cam is None and run.t_imu_cam is None
    assert run.gyro_bias_velocity is None and run.accel_bias_velocity is None


def test_nonfinite_rows_are_dropped_and_counted(tmp_path):
    lines = _lines()
    lines[12] = _imu(100.005, 2, gx="nan")  # line 13
    lines[10] = _feat(100.0, 0, 0, 3, u="inf")  # line 11
    run = load_eqvio(_write(tmp_path, lines))
    assert run.imu.t.shape == (1, 2)
    assert run.num_observations == 2 and run.landmark_ids.tolist() == [7]
    assert run.cleaning["dropped_nonfinite"] == {"imu": 1, "features": 1}
    assert run.cleaning["dropped_lines"] == {"imu": [13], "features": [11]}


@pytest.mark.parametrize(
    ("line", "replacement", "field", "message"),
    [
        (13, _imu(100.005, 2, gx="abc"), "gx", "not a number: 'abc'"),
        (13, _imu(100.005, 2, gx=""), "gx", "empty cell"),
        (12, "pose" + _imu(100.0, 1)[3:], "row_type", "unknown row_type 'pose'"),
        (11, _feat(100.0, 0, 0, 3).replace(",0,0,3,", ",0,0.5,3,"), "frame_idx", "integer"),
        (11, _feat(100.0, 0, 1, 3), "frame_idx", "differs"),
        (11, _feat(100.002, 0, 0, 3), "t_abs", "differs"),
        (11, _feat(100.0, 0, 0, 7), "landmark_id", "observed twice"),
        (14, _feat(100.01, 3, 0, 7), "frame_idx", "is used by seq 0"),
        (14, _feat(99.0, 3, 1, 7), "t_abs", "must increase"),
        (13, _imu(99.0, 2), "t_abs", "time goes backwards"),
        (5, _meta("T_ci_qw", "one"), "value", "meta 'T_ci_qw': not a number"),
        (9, _meta("eqf.measurement_noise_variance_norm", "-1"), "value", "negative"),
        (9, _meta("T_ci_tx", "0.5"), "key", r"given twice \(first on line 2\)"),
    ],
)
def test_malformed_rows_name_line_and_field(tmp_path, line, replacement, field, message):
    lines = _lines()
    lines[line - 1] = replacement
    path = _write(tmp_path, lines)
    with pytest.raises(DataError, match=message) as info:
        load_eqvio(path)
    assert info.value.line == line
    assert info.value.field == field
    assert info.value.path == str(path)
    assert f"{path}:{line}: field '{field}'" in str(info.value)


def test_zero_quaternion_and_partial_extrinsics(tmp_path):
    lines = _lines()
    for i in range(4, 8):
        lines[i] = lines[i].rsplit(",", 1)[0] + ",0"
    with pytest.raises(DataError, match="zero norm") as info:
        load_eqvio(_write(tmp_path, lines))
    assert info.value.line == 5
    lines = [ln for ln in _lines() if "T_ci_qz" not in ln]
    with pytest.raises(DataError, match="T_ci_qz missing"):
        load_eqvio(_write(tmp_path, lines))


def test_structural_errors(tmp_path):
    lines = _lines()
    lines[11] = lines[11] + ",extra"
    with pytest.raises(DataError, match="expected 22 columns") as info:
        load_eqvio(_write(tmp_path, lines))
    assert info.value.line == 12
    lines = _lines()
    lines[0] = HEADER.replace("u_norm", "u")
    with pytest.raises(DataError, match="u_norm|unknown column") as info:
        load_eqvio(_write(tmp_path, lines))
    assert info.value.line == 1
    with pytest.raises(DataError, match="no IMU rows"):
        load_eqvio(_write(tmp_path, [ln for ln in _lines() if not ln.startswith("imu")]))
    with pytest.raises(DataError, match="no such file"):
        load_eqvio(tmp_path / "missing.csv")
