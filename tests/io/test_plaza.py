"""The Plaza range-beacon runs shipped in the gtsam wheel: what the loader reads and the facts
it records, the Plaza2 smoothing problem against GTSAM on the same graph, and malformed
copies of the files."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch

from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.range2d import OdometryNoise, odometry_range_problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.io import DataError, gtsam_data_path
from msf_torch.io import plaza as plaza_module
from msf_torch.io.plaza import load_plaza
from msf_torch.io.ranges import RangeRun

DT = torch.float64
# the range bias and spread measured on Plaza1 (median and 1.4826 MAD of range minus the
# true distance), used on Plaza2 as the benchmark does
RANGE_BIAS_M = 2.8494908035277575
RANGE_SIGMA_M = 1.2094651576857784
FIRST_COVARIANCE = torch.diag(torch.tensor([0.1**2, 0.1**2, 0.05**2], dtype=DT))


@pytest.fixture(scope="module")
def gtsam():
    return pytest.importorskip("gtsam")


@pytest.fixture(scope="module")
def runs(gtsam):
    return {name: load_plaza(name) for name in ("Plaza1", "Plaza2")}


def _anchor_rows(run) -> torch.Tensor:
    """(K,) row of ``run.anchors`` each range is to, by a lookup table."""
    rows = {int(i): k for k, i in enumerate(run.anchor_ids)}
    return torch.tensor([rows[int(i)] for i in run.range_anchor])


@pytest.mark.parametrize(
    ("name", "steps", "count", "ids"),
    [("Plaza1", 9657, 3529, [0, 1, 6, 5]), ("Plaza2", 4090, 1816, [1, 6, 0, 5])],
)
def test_shapes_and_times(runs, name, steps, count, ids):
    """``ids``: the beacons in the file's order (TL); the run holds them sorted by id."""
    run = runs[name]
    assert run.name == name
    assert run.odometry.shape == (steps, 3)
    assert run.range_t.shape == run.range_anchor.shape == run.ranges.shape == (count,)
    assert run.pose_t.shape == (steps + 1,) and run.truth.shape == (steps + 1, 3)
    assert run.anchor_ids.tolist() == sorted(ids) and run.anchors.shape == (4, 2)
    assert run.range_anchor.dtype == run.anchor_ids.dtype == torch.int64
    assert all(t.dtype == DT for t in (run.odometry, run.ranges, run.truth, run.anchors))
    # the poses: the start pose, then one at each odometry time (the DR file's first column)
    odometry_t = np.loadtxt(gtsam_data_path(f"{name}_DR.txt"))[:, 0]
    assert run.pose_t[0] < odometry_t[0]
    np.testing.assert_allclose(run.pose_t[1:].numpy(), odometry_t, rtol=0, atol=1e-6)
    assert (run.pose_t.diff() > 0).all()
    assert (run.range_t.diff() >= 0).all()  # Plaza1 has ranges at equal times
    assert set(run.range_anchor.tolist()) == set(ids)


@pytest.mark.parametrize("name", ["Plaza1", "Plaza2"])
def test_anchors_sorted_with_their_positions_and_rows(runs, name):
    """Each anchor keeps its own position from TL after the sort; ``range_anchor_rows``
    equals a lookup by id."""
    from scipy.io import loadmat

    run = runs[name]
    beacons = loadmat(gtsam_data_path(f"{name}_.mat"))["TL"]
    for anchor, position in zip(run.anchor_ids.tolist(), run.anchors, strict=True):
        (row,) = np.flatnonzero(beacons[:, 0] == anchor)
        np.testing.assert_array_equal(position.numpy(), beacons[row, 1:3])
    rows = run.range_anchor_rows()
    assert rows.dtype == torch.int64
    assert torch.equal(rows, _anchor_rows(run))
    assert torch.equal(run.anchor_ids[rows], run.range_anchor)


@pytest.mark.parametrize("name", ["Plaza1", "Plaza2"])
def test_odometry_steps_move_then_turn(runs, name):
    """Each DR line ``distance, heading change`` is the relative pose ``[distance, 0,
    heading change]``."""
    run = runs[name]
    lines = np.loadtxt(gtsam_data_path(f"{name}_DR.txt"))
    np.testing.assert_array_equal(run.odometry[:, 0].numpy(), lines[:, 1])
    assert (run.odometry[:, 1] == 0).all()
    np.testing.assert_array_equal(run.odometry[:, 2].numpy(), lines[:, 2])


def test_meta_facts(runs):
    plaza1, plaza2 = runs["Plaza1"].meta, runs["Plaza2"].meta
    assert plaza2["truth_heading_turned"] and not plaza1["truth_heading_turned"]
    assert plaza2["truth_course_offset_rad"] == pytest.approx(3.08, abs=0.01)
    assert plaza1["truth_course_offset_rad"] == pytest.approx(-0.016, abs=0.001)
    assert plaza1["truth_heading_is_odometry"] and not plaza2["truth_heading_is_odometry"]
    assert plaza1["ranges_reordered"] > 0 and plaza2["ranges_reordered"] == 0


@pytest.mark.parametrize("name", ["Plaza1", "Plaza2"])
def test_truth_heading_is_the_direction_of_travel(runs, name):
    """After the loader's turn, the course of the truth positions and the truth heading
    agree (median within 0.05 rad) on both runs."""
    truth = runs[name].truth
    step = truth[1:, 0:2] - truth[:-1, 0:2]
    moving = step.norm(dim=-1) > 0.05
    course = torch.atan2(step[moving, 1], step[moving, 0])
    difference = torch.remainder(course - truth[1:, 2][moving] + math.pi, 2 * math.pi) - math.pi
    assert difference.median().abs() < 0.05


@pytest.mark.parametrize("name", ["Plaza1", "Plaza2"])
def test_dead_reckoning_starts_on_the_truth(runs, name):
    run = runs[name]
    poses = run.odometry_poses()
    assert poses.shape == run.truth.shape
    torch.testing.assert_close(poses[0], run.truth[0], rtol=0, atol=0)
    assert (poses[:51, 0:2] - run.truth[:51, 0:2]).norm(dim=-1).max() < 0.25
    # an explicit start moves the whole chain with it
    start = run.truth[0] + torch.tensor([1.0, -2.0, 0.0], dtype=DT)
    moved = run.odometry_poses(start)
    shift = torch.tensor([1.0, -2.0], dtype=DT).expand(len(poses), 2)
    torch.testing.assert_close(moved[:, 0:2] - poses[:, 0:2], shift, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["Plaza1", "Plaza2"])
def test_range_pose_index_is_the_first_pose_at_or_after_the_range(runs, name):
    run = runs[name]
    index = run.range_pose_index()
    assert index.shape == run.range_t.shape and index.dtype == torch.int64
    truth_t, range_t = run.pose_t.numpy(), run.range_t.numpy()
    for k, i in enumerate(index.tolist()):
        before = truth_t[i - 1] < range_t[k] if i > 0 else True
        assert before and (truth_t[i] >= range_t[k] or i == len(truth_t) - 1), k


def _toy_run() -> RangeRun:
    """Three steps of 1 m: turn left, turn left, straight; ranges at and between the
    pose times (0, 1, 2, 3 s), one after the last."""
    odometry = torch.tensor(
        [[1.0, 0.0, math.pi / 2], [1.0, 0.0, math.pi / 2], [1.0, 0.0, 0.0]], dtype=DT
    )
    return RangeRun(
        name="toy",
        pose_t=torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=DT),
        odometry=odometry,
        range_t=torch.tensor([0.0, 0.5, 1.0, 2.9, 3.0, 5.0], dtype=DT),
        range_anchor=torch.zeros(6, dtype=torch.int64),
        ranges=torch.ones(6, dtype=DT),
        anchor_ids=torch.zeros(1, dtype=torch.int64),
        anchors=torch.zeros(1, 2, dtype=DT),
        truth=torch.zeros(4, 3, dtype=DT),
    )


def test_toy_run_dead_reckoning_moves_then_turns():
    poses = _toy_run().odometry_poses()
    expected = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2], [1.0, 1.0, math.pi], [0.0, 1.0, math.pi]],
        dtype=DT,
    )
    torch.testing.assert_close(poses, expected, rtol=0, atol=1e-12)


def test_toy_run_range_pose_index_at_equal_times():
    """A range at a pose's time goes to that pose; one after the last pose to the last."""
    assert _toy_run().range_pose_index().tolist() == [0, 1, 1, 3, 3, 3]


@pytest.mark.parametrize(("name", "bias"), [("Plaza1", 2.85), ("Plaza2", 2.80)])
def test_ranges_read_long_by_the_documented_bias(runs, name, bias):
    """Median of range minus the true distance from the assigned pose: +2.85 / +2.80 m."""
    run = runs[name]
    distance = (run.anchors[_anchor_rows(run)] - run.truth[run.range_pose_index(), 0:2]).norm(
        dim=-1
    )
    assert (run.ranges - distance).median().item() == pytest.approx(bias, abs=0.01)


def test_plaza2_solve_equals_gtsam_on_the_same_graph(runs, gtsam):
    """Known beacons, the Plaza1 bias removed, Cauchy at 2.3849 sigmas: initial and final
    costs equal GTSAM's LM on the same factors; 0.42 m RMSE where dead reckoning is 32 m."""
    run = runs["Plaza2"]
    beacon_rows, range_pose = _anchor_rows(run), run.range_pose_index()
    ranges = run.ranges - RANGE_BIAS_M
    noise = OdometryNoise()
    kernel = RobustKernel("cauchy", 2.3849)
    first = run.truth[0]
    problem = odometry_range_problem(
        run.odometry,
        range_pose,
        beacon_rows,
        ranges,
        run.anchors,
        first,
        FIRST_COVARIANCE,
        odometry_noise=noise,
        range_sigma_m=RANGE_SIGMA_M,
        range_kernel=kernel,
    )
    config = LMConfig(
        max_iterations=100,
        damping="identity",
        linear_solver="sparse",
        damping_update="multiplicative",
        relative_tolerance=1e-12,
        absolute_tolerance=0.0,
    )
    with torch.no_grad():
        result = solve(problem, config)
    assert result.status == ["converged"]

    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()

    def pose_key(i: int) -> int:
        return gtsam.symbol("x", i)

    def beacon_key(j: int) -> int:
        return gtsam.symbol("l", j)

    for i, pose in enumerate(problem.values["pose"][0].tolist()):
        initial.insert(pose_key(i), gtsam.Pose2(*pose))
    for j, beacon in enumerate(run.anchors.numpy()):
        initial.insert(beacon_key(j), beacon.copy())
        graph.add(gtsam.NonlinearEqualityPoint2(beacon_key(j), beacon.copy()))
    graph.add(
        gtsam.PriorFactorPose2(
            pose_key(0),
            gtsam.Pose2(*first.tolist()),
            gtsam.noiseModel.Gaussian.Covariance(FIRST_COVARIANCE.numpy()),
        )
    )
    covariances = noise.covariance(run.odometry[:, 0]).numpy()
    for i, (distance, sideways, turn) in enumerate(run.odometry.tolist()):
        graph.add(
            gtsam.BetweenFactorPose2(
                pose_key(i),
                pose_key(i + 1),
                gtsam.Pose2(distance, sideways, turn),
                gtsam.noiseModel.Gaussian.Covariance(covariances[i]),
            )
        )
    range_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(kernel.scale),
        gtsam.noiseModel.Isotropic.Sigma(1, RANGE_SIGMA_M),
    )
    for i, j, z in zip(range_pose.tolist(), beacon_rows.tolist(), ranges.tolist(), strict=True):
        graph.add(gtsam.RangeFactor2D(pose_key(i), beacon_key(j), z, range_noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(100)
    estimate = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()

    assert result.initial_cost.item() == pytest.approx(graph.error(initial), rel=1e-9)
    assert result.cost.item() == pytest.approx(graph.error(estimate), rel=1e-9)
    positions = result.values["pose"][0, :, 0:2]
    reference = np.array(
        [
            [estimate.atPose2(pose_key(i)).x(), estimate.atPose2(pose_key(i)).y()]
            for i in range(len(positions))
        ]
    )
    np.testing.assert_allclose(positions.numpy(), reference, rtol=0, atol=1e-5)
    rmse = (positions - run.truth[:, 0:2]).norm(dim=-1).pow(2).mean().sqrt()
    dead_reckoning = run.odometry_poses()[:, 0:2] - run.truth[:, 0:2]
    assert rmse < 0.6 and dead_reckoning.norm(dim=-1).pow(2).mean().sqrt() > 25.0


def test_unknown_run_name():
    with pytest.raises(ValueError, match="unknown Plaza run 'Plaza3'; known: Plaza1, Plaza2"):
        load_plaza("Plaza3")


@pytest.fixture
def plaza2_copy(gtsam, tmp_path, monkeypatch):
    """A copy of Plaza2's three files in ``tmp_path``, which the loader then reads."""
    for suffix in ("_DR.txt", "_TD.txt", "_.mat"):
        shutil.copy(gtsam_data_path(f"Plaza2{suffix}"), tmp_path)
    monkeypatch.setattr(plaza_module, "gtsam_data_path", lambda name: tmp_path / name)
    return tmp_path


def _edit_lines(path, edit) -> None:
    lines = path.read_text().splitlines()
    edit(lines)
    path.write_text("\n".join(lines) + "\n")


def test_copy_loads_like_the_original(runs, plaza2_copy):
    run = load_plaza("Plaza2")
    assert torch.equal(run.truth, runs["Plaza2"].truth)
    assert torch.equal(run.ranges, runs["Plaza2"].ranges)
    assert run.meta["source"] == str(plaza2_copy)


def test_out_of_order_ranges_are_sorted(runs, plaza2_copy):
    """Two range lines swapped: the loader puts them back and counts both."""
    _edit_lines(plaza2_copy / "Plaza2_TD.txt", lambda lines: lines.insert(100, lines.pop(101)))
    run = load_plaza("Plaza2")
    assert run.meta["ranges_reordered"] == 2
    original = runs["Plaza2"]
    for name in ("range_t", "range_anchor", "ranges"):
        assert torch.equal(getattr(run, name), getattr(original, name)), name


def test_range_to_an_unlisted_beacon_names_its_line(plaza2_copy):
    """The error names the file's line even after the ranges were sorted (the last line
    moved to the top)."""

    def edit(lines: list[str]) -> None:
        fields = lines[9].split()
        lines[9] = "  ".join(fields[:2] + ["9"] + fields[3:])
        lines.insert(0, lines.pop())

    _edit_lines(plaza2_copy / "Plaza2_TD.txt", edit)
    with pytest.raises(DataError, match="range to beacon 9, which TL does not list") as info:
        load_plaza("Plaza2")
    assert info.value.line == 11 and info.value.field == "receiver"


def test_odometry_time_going_back_names_its_line(plaza2_copy):
    def edit(lines: list[str]) -> None:
        fields = lines[41].split()
        lines[41] = "  ".join([lines[39].split()[0]] + fields[1:])

    _edit_lines(plaza2_copy / "Plaza2_DR.txt", edit)
    with pytest.raises(DataError, match="time does not increase") as info:
        load_plaza("Plaza2")
    assert info.value.line == 42 and info.value.field == "time"


@pytest.mark.parametrize("name", ["Plaza2_DR.txt", "Plaza2_TD.txt"])
def test_non_finite_value_names_its_line(plaza2_copy, name):
    def edit(lines: list[str]) -> None:
        fields = lines[6].split()
        lines[6] = "  ".join(fields[:1] + ["inf"] + fields[2:])

    _edit_lines(plaza2_copy / name, edit)
    with pytest.raises(DataError, match="not finite") as info:
        load_plaza("Plaza2")
    assert info.value.line == 7 and info.value.path.endswith(name)


def test_malformed_mat_variables(plaza2_copy):
    from scipy.io import loadmat, savemat

    path = plaza2_copy / "Plaza2_.mat"
    mat = loadmat(path)
    savemat(path, {"GT": mat["GT"][:-1], "TL": mat["TL"]})
    with pytest.raises(DataError, match=r"GT must hold the start pose .* got 4090 rows"):
        load_plaza("Plaza2")
    savemat(path, {"GT": mat["GT"], "TL": mat["TL"][:, :2]})
    with pytest.raises(DataError, match=r"variable 'TL': expected an \(n, 3\) matrix"):
        load_plaza("Plaza2")
    savemat(path, {"TL": mat["TL"]})
    with pytest.raises(DataError, match="variable 'GT': expected an"):
        load_plaza("Plaza2")
    path.write_bytes(b"not a MATLAB file at all" * 20)
    with pytest.raises(DataError, match="not a readable MATLAB file"):
        load_plaza("Plaza2")
