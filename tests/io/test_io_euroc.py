"""EuRoC ASL folders, written synthetically."""

from __future__ import annotations

import pytest
import torch

from msf_torch.io import DataError, load_sequence, read_euroc

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
    "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
    "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]\n"
)
SENSOR_YAML = """%YAML:1.0
sensor_type: imu
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
accelerometer_noise_density: 2.0000e-3
accelerometer_random_walk: 3.0000e-3
"""


def make_asl(root, with_mav0=True, with_gt=True):
    base = root / "MH_01" / ("mav0" if with_mav0 else "")
    (base / "imu0").mkdir(parents=True)
    t0 = 1403636579758555392
    rows = [f"{t0 + i * 5_000_000},{0.1 * i},-0.02,0.03,9.0,0.1,{-0.2 * i}\n" for i in range(10)]
    (base / "imu0" / "data.csv").write_text(IMU_HEADER + "".join(rows))
    (base / "imu0" / "sensor.yaml").write_text(SENSOR_YAML)
    if with_gt:
        (base / "state_groundtruth_estimate0").mkdir()
        gt = [
            f"{t0 + i * 5_000_000},{i},{2 * i},0.5,0.0,0.0,0.0,2.0,0,0,0,0,0,0,0,0,0\n"
            for i in range(4)
        ]
        (base / "state_groundtruth_estimate0" / "data.csv").write_text(GT_HEADER + "".join(gt))
    return root / "MH_01"


def test_read_asl_folder(tmp_path):
    folder = make_asl(tmp_path)
    seq = read_euroc(folder)
    assert seq.names == ["MH_01"]
    assert seq.imu.t.shape == (1, 10) and seq.imu.t.dtype == torch.float64
    assert seq.imu.t[0, 0].item() == 1403636579.758555392
    torch.testing.assert_close(
        seq.imu.t.diff(), torch.full((1, 9), 0.005, dtype=torch.float64), atol=1e-6, rtol=0
    )
    assert seq.imu.gyro[0, 3].tolist() == pytest.approx([0.3, -0.02, 0.03])
    assert seq.imu.accel[0, 3].tolist() == pytest.approx([9.0, 0.1, -0.6])
    gt = seq.ground_truth
    assert gt.t.shape == (1, 4)
    assert gt.position[0, 2].tolist() == [2.0, 4.0, 0.5]
    assert gt.quaternion[0, 0].tolist() == [0.0, 0.0, 0.0, 1.0]  # normalised
    assert seq.meta["format"] == "euroc"
    assert seq.meta["imu_noise"]["gyro_noise_density"] == 1.6968e-04
    assert seq.meta["imu_noise"]["accel_bias_rw_density"] == 3.0e-3
    assert seq.meta["imu_noise"]["rate_hz"] == 200.0
    assert len(seq.meta["imu_noise"]["T_body_sensor"]) == 16
    assert load_sequence(folder).imu.length == 10
    assert load_sequence(folder / "mav0", fmt="euroc").names == ["MH_01"]


def test_read_imu0_without_mav0_or_gt(tmp_path):
    folder = make_asl(tmp_path, with_mav0=False, with_gt=False)
    seq = load_sequence(folder)
    assert seq.ground_truth is None and seq.imu.length == 10


def test_errors(tmp_path):
    folder = make_asl(tmp_path)
    data = folder / "mav0" / "imu0" / "data.csv"
    data.write_text(IMU_HEADER + "1403636579758555392,0,0,0,0,0,9\n1403636579.76,0,0,0,0,0,9\n")
    with pytest.raises(DataError, match=r"data.csv:3: field 'timestamp': not an integer"):
        read_euroc(folder)
    data.write_text("#timestamp [ns],w_RS_S_x\n1,0\n")
    with pytest.raises(DataError, match="field 'w_RS_S_y': missing column"):
        read_euroc(folder)
    with pytest.raises(DataError, match="not a EuRoC ASL folder"):
        read_euroc(tmp_path)


def test_aerial_platform_turns_the_nonholonomic_constraint_off(tmp_path):
    """EuRoC is a MAV: its sequences say so, and the front end's ``nhc: auto`` (on for any
    run without wheels) becomes off unless the user's config sets it."""
    from msf_torch.frontend.config import load_sequence_config

    seq = read_euroc(make_asl(tmp_path))
    assert seq.meta["platform"] == "aerial"
    assert load_sequence_config(seq.meta).nhc == "off"
    config = tmp_path / "c.yaml"
    config.write_text("nhc: on\n")
    assert load_sequence_config(seq.meta, config).nhc == "on"
