"""The KITTI IMU + GPS drive shipped in the gtsam wheel."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from msf_torch.io import DataError, MissingExtraError, gtsam_data_path, load_sequence
from msf_torch.io.kitti_gtsam import load_kitti_gtsam


@pytest.fixture(scope="module")
def kitti():
    pytest.importorskip("gtsam")
    return load_sequence("kitti-gtsam")


def test_counts_and_times(kitti):
    assert kitti.names == ["kitti-gtsam"]
    assert kitti.imu.t.shape == (1, 46968)  # 46969 lines minus the header
    assert kitti.gnss.t.shape == (1, 470)
    assert kitti.imu.t[0, 0].item() == 46534.47837579
    assert kitti.gnss.t[0, 0].item() == pytest.approx(46534.47837579, abs=1e-9)
    assert (kitti.imu.t.diff() > 0).all()
    assert np.isnan(kitti.gnss.sigma.numpy()).all()
    assert kitti.meta["dropped_nonfinite"] == {"imu": 0, "gnss": 0}
    # first row: accel then omega in the file; gyro/accel in memory
    assert kitti.imu.accel[0, 0].tolist() == [1.7114864219577, 0.1717911743144, 9.80533438749]
    assert kitti.imu.gyro[0, 0, 2].item() == -0.0063569265706488


def test_noise_meta_equals_metadata_file(kitti):
    text = gtsam_data_path("KittiEquivBiasedImu_metadata.txt").read_text().split("\n")
    values = dict(zip(text[0].split(), map(float, text[1].split()), strict=True))
    noise = kitti.meta["imu_noise"]
    assert noise["accel_noise_sigma"] == values["AccelerometerSigma"] == 0.01
    assert noise["gyro_noise_sigma"] == values["GyroscopeSigma"]
    assert noise["integration_sigma"] == values["IntegrationSigma"]
    assert noise["accel_bias_rw_sigma"] == values["AccelerometerBiasSigma"]
    assert noise["gyro_bias_rw_sigma"] == values["GyroscopeBiasSigma"] == 2.91e-6
    assert noise["average_dt"] == values["AverageDeltaT"]
    assert noise["body_p_sensor"] == [0.0] * 6


def test_gtsam_data_path(kitti):
    assert gtsam_data_path("sphere2500.txt").is_file()
    with pytest.raises(DataError, match="no such data file"):
        gtsam_data_path("no_such_file.txt")


def test_missing_gtsam_names_the_extra(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else real(name, *a)
    )
    with pytest.raises(MissingExtraError, match=r"pip install 'msf_torch\[peers\]'") as info:
        load_kitti_gtsam()
    assert info.value.name == "gtsam"
