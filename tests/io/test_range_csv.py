"""Odometry + anchor-range runs from CSV files (:func:`read_range_run`): the odometry steps
against their closed form, ranges sorted and dropped outside the odometry's span, the
truth interpolated, every DataError rule naming file, line and column, and the anchors
file written and read back."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.io import DataError
from msf_torch.io.ranges import read_range_run, write_anchors

DT = torch.float64
# poses at 0, 1, 2.5, 4 s; the last step turns across the half turn
POSES = [
    (0.0, 0.0, 0.0, 0.3),
    (1.0, 1.2, 0.5, 1.4),
    (2.5, 0.7, 2.1, 3.0),
    (4.0, -0.9, 2.6, -2.9),
]
ODOMETRY = "# wheel odometry, columns out of order\nheading,t,y,x\n" + "".join(
    f"{h!r},{t!r},{y!r},{x!r}\n" for t, x, y, h in POSES
)
# out of time order; the ones at -0.5 s and 4.5 s lie outside the odometry's 0..4 s
RANGES = """t,anchor,range
1.5,7,3.25
0.0,2,4.0

-0.5,4,9.0
2.5,4,2.5
4.5,2,1.0
4.0,7,5.5
"""
ANCHORS = "anchor,x,y\n7,3.5,-1.25\n2,-4.0,2.0\n4,0.5,6.0\n"
TRUTH = "t,x,y\n-1.0,10.0,20.0\n2.0,13.0,14.0\n5.0,13.0,20.0\n"


def _files(tmp_path: Path, **texts: str) -> dict[str, Path]:
    """The run's files in ``tmp_path``: the defaults above, with ``texts`` replacing some."""
    contents = {"odometry": ODOMETRY, "ranges": RANGES, "anchors": ANCHORS, **texts}
    paths = {}
    for name, text in contents.items():
        paths[name] = tmp_path / f"{name}.csv"
        paths[name].write_text(text)
    return paths


def _read(tmp_path: Path, **texts: str):
    paths = _files(tmp_path, **texts)
    return read_range_run(paths["odometry"], paths["ranges"], paths["anchors"], paths.get("truth"))


def test_odometry_steps_are_the_relative_poses(tmp_path):
    """Step k: the position change rotated into pose k's heading, and the heading change
    wrapped (the last one crosses the half turn: -2.9 - 3.0 + 2 pi)."""
    run = _read(tmp_path)
    assert run.name == "odometry"
    poses = np.array(POSES)
    torch.testing.assert_close(run.pose_t, torch.tensor(poses[:, 0], dtype=DT), rtol=0, atol=0)
    assert run.odometry.shape == (3, 3) and run.odometry.dtype == DT
    for k in range(3):
        (_, x0, y0, h0), (_, x1, y1, h1) = POSES[k], POSES[k + 1]
        c, s = math.cos(h0), math.sin(h0)
        expected = [
            c * (x1 - x0) + s * (y1 - y0),
            -s * (x1 - x0) + c * (y1 - y0),
            math.remainder(h1 - h0, 2 * math.pi),
        ]
        torch.testing.assert_close(
            run.odometry[k], torch.tensor(expected, dtype=DT), rtol=0, atol=1e-12
        )
    assert run.odometry[2, 2].item() == pytest.approx(-5.9 + 2 * math.pi, abs=1e-12)
    # chained from the first pose, the steps give the file's poses back
    chained = run.odometry_poses(torch.tensor(poses[0, 1:], dtype=DT))
    torch.testing.assert_close(chained, torch.tensor(poses[:, 1:], dtype=DT), rtol=0, atol=1e-12)
    # without truth, dead reckoning starts at the origin
    assert torch.equal(run.odometry_poses()[0], torch.zeros(3, dtype=DT))


def test_ranges_sorted_dropped_and_counted(tmp_path):
    run = _read(tmp_path)
    # sorted: 0.0, 1.5, 2.5, 4.0 kept; -0.5 and 4.5 dropped
    assert run.range_t.tolist() == [0.0, 1.5, 2.5, 4.0]
    assert run.range_anchor.tolist() == [2, 7, 4, 7]
    assert run.ranges.tolist() == [4.0, 3.25, 2.5, 5.5]
    assert run.range_anchor.dtype == torch.int64 and run.ranges.dtype == DT
    # of the six lines (1.5, 0.0, -0.5, 2.5, 4.5, 4.0 s) sorting moves four: 0.0 s and
    # 2.5 s keep their places
    assert run.meta["ranges_reordered"] == 4
    assert run.meta["ranges_outside"] == 2
    assert run.meta["files"] == {
        "odometry": str(tmp_path / "odometry.csv"),
        "ranges": str(tmp_path / "ranges.csv"),
        "anchors": str(tmp_path / "anchors.csv"),
    }
    # ranges at pose times go to that pose, others to the next one
    assert run.range_pose_index().tolist() == [0, 2, 2, 3]


def test_sorted_ranges_inside_the_span_are_counted_as_such(tmp_path):
    run = _read(tmp_path, ranges="t,anchor,range\n0.0,2,1.0\n4.0,4,2.0\n")
    assert run.meta["ranges_reordered"] == 0 and run.meta["ranges_outside"] == 0
    assert run.range_t.tolist() == [0.0, 4.0]


def test_anchors_without_ranges_are_listed(tmp_path):
    """Anchor 4 is never ranged and anchor 7 only after the odometry ends (4.5 s): both
    listed, sorted by id; every anchor of the default files is ranged."""
    run = _read(tmp_path, ranges="t,anchor,range\n4.5,7,2.0\n0.0,2,1.0\n")
    assert run.meta["anchors_without_ranges"] == [4, 7]
    assert _read(tmp_path).meta["anchors_without_ranges"] == []


def test_anchors_sorted_by_id_with_their_positions(tmp_path):
    run = _read(tmp_path)
    assert run.anchor_ids.tolist() == [2, 4, 7] and run.anchor_ids.dtype == torch.int64
    expected = torch.tensor([[-4.0, 2.0], [0.5, 6.0], [3.5, -1.25]], dtype=DT)
    assert torch.equal(run.anchors, expected)
    assert run.range_anchor_rows().tolist() == [0, 2, 1, 2]


def test_truth_interpolated_to_the_pose_times(tmp_path):
    """Linear in time between the truth rows; heading NaN (the file has none); dead
    reckoning then starts at the origin."""
    run = _read(tmp_path, truth=TRUTH)
    expected_xy = torch.tensor([[11.0, 18.0], [12.0, 16.0], [13.0, 15.0], [13.0, 18.0]], dtype=DT)
    assert run.truth.shape == (4, 3)
    torch.testing.assert_close(run.truth[:, 0:2], expected_xy, rtol=0, atol=1e-12)
    assert torch.isnan(run.truth[:, 2]).all()
    assert run.meta["files"]["truth"] == str(tmp_path / "truth.csv")
    assert torch.equal(run.odometry_poses()[0], torch.zeros(3, dtype=DT))


def test_a_slower_truth_may_end_one_of_its_periods_early(tmp_path):
    """A 5 Hz RTK log ends up to 0.2 s before 10 Hz odometry: kept (was refused), the last
    pose takes the truth's last position."""
    truth = "t,x,y\n0,0,0\n1,1,0\n2,2,0\n3,3,0\n3.5,3.5,0\n"  # median period 1 s
    run = _read(tmp_path, truth=truth)
    assert run.truth[-1, 0:2].tolist() == [3.5, 0.0]  # odometry ends at 4.0 s


def _error(tmp_path: Path, **texts: str) -> DataError:
    with pytest.raises(DataError) as info:
        _read(tmp_path, **texts)
    return info.value


BAD = [
    # (file, its text, message, line, column)
    ("odometry", "t,x,y\n0,0,0\n1,1,0\n", "missing column", 1, "heading"),
    ("odometry", "t,x,y,heading,z\n0,0,0,0,1\n1,1,0,0,1\n", "unknown column", 1, "z"),
    ("odometry", "t,x,y,heading\n0,0,0,0\n1,abc,0,0\n", "not a number: 'abc'", 3, "x"),
    ("odometry", "t,x,y,heading\n0,0,0,0\n1,1,0,nan\n", "not finite", 3, "heading"),
    ("odometry", "t,x,y,heading\n0,0,0,0\n# c\n1,1,0,0\n1,2,0,0\n", "must increase", 5, "t"),
    ("odometry", "t,x,y,heading\n0,0,0,0\n", "need at least 2 odometry rows, got 1", None, None),
    ("ranges", "t,anchor\n0,2\n", "missing column", 1, "range"),
    ("ranges", "t,anchor,range\n0,2,1\n1,2,inf\n", "not finite", 3, "range"),
    ("ranges", "t,anchor,range\n0,2,1\n1,2,-0.5\n", "negative range -0.5", 3, "range"),
    ("ranges", "t,anchor,range\n0,2,1\n\n1,2.5,1\n", "not a non-negative whole", 4, "anchor"),
    ("ranges", "t,anchor,range\n0,-2,1\n", "not a non-negative whole number: -2.0", 2, "anchor"),
    (
        "ranges",
        "t,anchor,range\n2,2,1\n1,3,1\n",
        r"range to anchor 3, which anchors\.csv",
        3,
        "anchor",
    ),
    ("anchors", "anchor,x\n2,0\n", "missing column", 1, "y"),
    (
        "anchors",
        "anchor,x,y\n2,0,0\n4,0,0\n7,0,0\n4,1,1\n",
        "anchor 4 is listed twice",
        5,
        "anchor",
    ),
    ("anchors", "anchor,x,y\n2,0,0\n4.5,0,0\n7,0,0\n", "not a non-negative whole", 3, "anchor"),
    ("anchors", "anchor,x,y\n2,0,0\n4,0,0\n7,0,x\n", "not a number", 4, "y"),
    ("truth", "t,x,y\n-1,0,0\n", "need 2 or more rows with increasing times", None, None),
    ("truth", "t,x,y\n-1,0,0\n3,0,0\n3,1,1\n9,0,0\n", "increasing times", None, None),
    (  # starts more than one of its periods (0.1 s) after the odometry
        "truth",
        "t,x,y\n0.5,0,0\n0.6,0,0\n0.7,0,0\n9,0,0\n",
        r"covers 0\.500\.\.9\.000 s, not the odometry's 0\.000\.\.4\.000",
        None,
        None,
    ),
    ("truth", "t,x,y\n0,0,0\n0.1,0,0\n0.2,0,0\n3.5,0,0\n", "not the odometry's", None, None),
    ("truth", "t,x\n0,0\n4,0\n", "missing column", 1, "y"),
]


@pytest.mark.parametrize(
    ("name", "text", "message", "line", "column"),
    BAD,
    ids=[f"{case[0]}-{k}-{case[2].split()[0]}" for k, case in enumerate(BAD)],
)
def test_data_errors_name_file_line_and_column(tmp_path, name, text, message, line, column):
    error = _error(tmp_path, **{"truth": TRUTH, name: text})
    assert Path(error.path) == tmp_path / f"{name}.csv"
    assert error.line == line and error.field == column
    assert re.search(message, error.problem), (message, error.problem)


def test_missing_file_is_a_data_error(tmp_path):
    paths = _files(tmp_path)
    with pytest.raises(DataError, match="no such file") as info:
        read_range_run(paths["odometry"], tmp_path / "none.csv", paths["anchors"])
    assert info.value.path == str(tmp_path / "none.csv")


def test_write_anchors_round_trip(tmp_path):
    """Ids and positions written and read back bit for bit (sorted by id on reading);
    parent folders are created."""
    generator = torch.Generator().manual_seed(0)
    ids = torch.tensor([9, 0, 3, 12], dtype=torch.int64)
    positions = torch.randn(4, 2, generator=generator, dtype=DT) * 30.0
    target = tmp_path / "out" / "solved" / "anchors.csv"
    assert write_anchors(target, ids, positions) == target
    assert target.read_text().splitlines()[0] == "anchor,x,y"
    paths = _files(tmp_path, ranges="t,anchor,range\n1.0,3,2.0\n")
    run = read_range_run(paths["odometry"], paths["ranges"], target)
    order = torch.argsort(ids)
    assert torch.equal(run.anchor_ids, ids[order])
    assert torch.equal(run.anchors, positions[order])


@pytest.mark.parametrize(
    ("name", "text", "line", "column"),
    [
        # finite coordinates whose step overflows: x jumps by -2e308, y by -2e308, and a
        # finite jump of (1.7e308, 1.7e308) seen from a heading of 45 degrees
        ("odometry", "t,x,y,heading\n0,0,0,0\n1,1e308,0,0\n2,-1e308,0,0\n", 4, "x"),
        ("odometry", "t,x,y,heading\n0,0,1e308,0\n1,0,-1e308,0\n2,0,0,0\n", 3, "y"),
        ("odometry", f"t,x,y,heading\n0,0,0,{math.pi / 4!r}\n1,1.7e308,1.7e308,0\n", 3, "x"),
        # interpolating between y = 1e308 and y = -1e308 overflows (pose at 2.5 s)
        ("truth", "t,x,y\n-1,0,0\n2,0,1e308\n5,0,-1e308\n", 4, "y"),
    ],
)
def test_steps_and_truth_that_overflow_are_data_errors(tmp_path, name, text, line, column):
    """Finite but huge coordinates gave inf odometry steps or truth positions (found by hand
    while adding this reader to the fuzzer: its mutations rarely put two huge values of
    opposite sign on neighbouring rows)."""
    error = _error(tmp_path, **{"truth": TRUTH, name: text})
    assert Path(error.path) == tmp_path / f"{name}.csv"
    assert (error.line, error.field) == (line, column) and "overflows" in error.problem


def test_ranges_inside_an_odometry_gap_are_dropped_and_counted(tmp_path):
    """Odometry every 0.1 s with a 3-s gap: a range in the middle of the gap (over two
    periods from both poses) is dropped, ranges near its edges and elsewhere are kept."""
    times = [0.1 * k for k in range(11)] + [4.0 + 0.1 * k for k in range(11)]
    odometry = "t,x,y,heading\n" + "".join(f"{t!r},{t!r},0,0\n" for t in times)
    ranges = "t,anchor,range\n0.55,2,4.0\n1.05,2,4.0\n2.5,7,3.0\n3.95,4,5.0\n4.35,4,5.0\n"
    run = _read(tmp_path, odometry=odometry, ranges=ranges)
    assert run.meta["ranges_in_gaps"] == 1
    assert run.range_t.tolist() == [0.55, 1.05, 3.95, 4.35]


def test_ranges_in_millimetres_are_refused(tmp_path):
    """A scene a few metres across ranged in thousands: a DataError naming the file."""
    ranges = "t,anchor,range\n0.0,2,4000.0\n1.5,7,3250.0\n2.5,4,2500.0\n"
    err = _error(tmp_path, ranges=ranges)
    assert "ranges in mm or cm" in str(err) and err.path.endswith("ranges.csv")
