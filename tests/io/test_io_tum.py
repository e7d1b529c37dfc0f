"""TUM trajectories: exact round trip, evo reads our files identically, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.io import DataError, read_tum, write_tum


def test_round_trip_exact(tmp_path, sequence):
    traj = sequence.ground_truth
    path = write_tum(traj, tmp_path / "traj.tum")
    back = read_tum(path)
    assert back.t.dtype == torch.float64 and back.mask.all()
    assert torch.equal(back.t, traj.t)
    assert torch.equal(back.position, traj.position)
    torch.testing.assert_close(back.quaternion, traj.quaternion, atol=1e-15, rtol=0)
    first = path.read_text().splitlines()[:2]
    assert first[0] == "# t x y z qx qy qz qw"
    assert "e" not in first[1].split()[0]  # time in positional notation


def test_evo_reads_our_file_to_the_same_numbers(tmp_path, sequence):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    traj = sequence.ground_truth
    path = write_tum(traj, tmp_path / "traj.txt")
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    ours = read_tum(path)
    np.testing.assert_array_equal(evo_traj.timestamps, ours.t[0].numpy())
    np.testing.assert_array_equal(evo_traj.positions_xyz, ours.position[0].numpy())
    np.testing.assert_allclose(
        evo_traj.orientations_quat_wxyz, ours.quaternion[0].numpy(), atol=1e-15, rtol=0
    )
    np.testing.assert_array_equal(evo_traj.timestamps, traj.t[0].numpy())


def test_comments_blank_lines_and_normalisation(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("# header\n\n1.0 1 2 3 0 0 0 2\n# mid comment\n2.0 1 2 3 0 0 0 1\n")
    traj = read_tum(path)
    assert traj.t.tolist() == [[1.0, 2.0]]
    assert traj.quaternion[0, 0].tolist() == [1.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    ("body", "pattern"),
    [
        ("1 1 2 3 0 0 0 1\n2 1 2 x 0 0 0 1\n", r"t.txt:2: field 'z': not a number: 'x'"),
        ("1 1 2 3 0 0 0 1\n2 1 2 3 0 0 1\n", r"t.txt:2: expected 8 columns"),
        ("1 1 2 3 0 0 0 1\n2 1 nan 3 0 0 0 1\n", r"t.txt:2: field 'y': non-finite"),
        ("2 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n", r"t.txt:2: field 't': time goes backwards"),
        ("1 1 2 3 0 0 0 0\n", r"t.txt:1: field 'qw': quaternion"),
        ("# only a comment\n", r"no poses"),
    ],
)
def test_errors_name_line_and_field(tmp_path, body, pattern):
    path = tmp_path / "t.txt"
    path.write_text(body)
    with pytest.raises(DataError, match=pattern):
        read_tum(path)


def test_sort_and_duplicates(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("2 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n1 5 5 5 0 0 0 1\n")
    traj = read_tum(path, sort=True)
    assert traj.t.tolist() == [[1.0, 2.0]]
    assert traj.position[0, 0].tolist() == [1.0, 2.0, 3.0]


def test_write_rejects_nonfinite_and_batches(tmp_path, sequence):
    traj = sequence.ground_truth
    bad = traj.map(lambda x: x.clone())
    bad.position[0, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="pose 2"):
        write_tum(bad, tmp_path / "bad.tum")
    assert not (tmp_path / "bad.tum").exists()
    assert list(tmp_path.iterdir()) == []  # no temporary file left behind
    two = traj.map(lambda x: torch.cat((x, x)))
    with pytest.raises(ValueError, match="B = 2"):
        write_tum(two, tmp_path / "two.tum")
