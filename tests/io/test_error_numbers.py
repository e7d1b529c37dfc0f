"""Numbers in error messages read as the file wrote them (``1.5``), not as numpy reprs
(``np.float64(1.5)``), so a user can search the file for them."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from msf_torch.io import DataError, read_euroc, read_kitti_poses, read_native, read_tum
from msf_torch.io.kitti_poses import write_kitti_poses
from msf_torch.io.tum import write_tum
from msf_torch.types import Trajectory

EUROC_HEADER = "#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n"


def _tum_nan(folder: Path) -> None:
    (folder / "t.tum").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n")
    read_tum(folder / "t.tum")


def _euroc_backwards(folder: Path) -> None:
    (folder / "imu0").mkdir()
    rows = "1500000000,0,0,0,9.8,0,0\n1250000000,0,0,0,9.8,0,0\n"
    (folder / "imu0" / "data.csv").write_text(EUROC_HEADER + rows)
    read_euroc(folder)


def _kitti_times(folder: Path) -> None:
    (folder / "p.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    (folder / "times.txt").write_text("0.75\n0.5\n")
    read_kitti_poses(folder / "p.txt", folder / "times.txt")


def _native_sigma(folder: Path) -> None:
    (folder / "imu.csv").write_text(
        "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,9.8\n"
    )
    (folder / "gnss.csv").write_text("t,x,y,z,sigma_x,sigma_y,sigma_z\n0,0,0,0,1,-2.5,1\n")
    read_native(folder)


def _nonfinite_trajectory() -> Trajectory:
    return Trajectory(
        t=torch.tensor([[0.25, 0.5]], dtype=torch.float64),
        position=torch.tensor([[[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]]]),
        quaternion=torch.tensor([[[1.0, 0.0, 0.0, 0.0]] * 2], dtype=torch.float64),
        mask=torch.ones(1, 2, dtype=torch.bool),
    )


@pytest.mark.parametrize(
    ("case", "numbers"),
    [
        (_tum_nan, ["nan"]),
        (_euroc_backwards, ["1.25 s comes after 1.5 s"]),
        (_kitti_times, ["time 0.5 does not increase"]),
        (_native_sigma, ["got -2.5"]),
        (lambda folder: write_tum(_nonfinite_trajectory(), folder / "x.tum"), ["t = 0.5"]),
        (lambda folder: write_kitti_poses(_nonfinite_trajectory(), folder / "x"), ["t = 0.5"]),
    ],
)
def test_error_messages_show_plain_numbers(tmp_path, case, numbers) -> None:
    with pytest.raises(ValueError) as caught:
        case(tmp_path)
    message = str(caught.value)
    assert "np." not in message, message
    for text in numbers:
        assert text in message, message
    if isinstance(caught.value, DataError):
        assert caught.value.path.startswith(str(tmp_path))
