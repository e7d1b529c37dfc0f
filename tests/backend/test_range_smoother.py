"""Whole-run range smoothing (:mod:`msf_torch.backend.range_smoother`): ``se2.chain``
against sequential composition; range bias and sigma calibrated on a simulated run with
known values and on Plaza1; the start pose found from odometry in its own frame and known
anchors; a simulated run smoothed with the start searched, given, and with the anchors
solved; Plaza2 smoothed with Plaza1's calibration."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from msf_torch.backend.range2d import OdometryNoise
from msf_torch.backend.range_smoother import (
    RangeSmootherSettings,
    calibrate_from_truth,
    estimate_start,
    smooth_ranges,
)
from msf_torch.geometry.se2 import chain, compose
from msf_torch.io.ranges import RangeRun

DT = torch.float64
STEPS = 400
RANGE_BIAS_M = 1.5
RANGE_SIGMA_M = 0.2
ANCHORS = torch.tensor([[-20.0, -15.0], [25.0, -18.0], [22.0, 24.0], [-18.0, 21.0]], dtype=DT)
ANCHOR_IDS = torch.tensor([3, 5, 8, 11])
# on the 72-heading search grid (21 * 5 degrees)
START_ON_GRID = (5.0, -3.0, 2 * math.pi * 21 / 72)


def _simulate(start: tuple[float, float, float], seed: int = 0) -> RangeRun:
    """Two loops (~200 m) at 2 Hz among four anchors: odometry with noise (1 cm, 1 cm,
    3 mrad per step) in its own frame, a range to every anchor at every pose time with
    bias ``RANGE_BIAS_M`` and Gaussian noise ``RANGE_SIGMA_M``; truth with headings."""
    generator = torch.Generator().manual_seed(seed)
    k = torch.arange(STEPS, dtype=DT)
    steps = torch.stack(
        (
            0.5 + 0.1 * torch.sin(k / 9),
            torch.zeros_like(k),
            2 * math.pi / 200 + 0.02 * torch.cos(k / 11),
        ),
        -1,
    )
    truth = chain(torch.tensor(start, dtype=DT), steps)
    noise = torch.randn(STEPS, 3, generator=generator, dtype=DT)
    odometry = steps + noise * torch.tensor([0.01, 0.01, 0.003], dtype=DT)
    pose = torch.arange(STEPS + 1).repeat_interleave(4)
    rows = torch.arange(4).repeat(STEPS + 1)
    distance = (ANCHORS[rows] - truth[pose, 0:2]).norm(dim=-1)
    ranges = (
        distance
        + RANGE_BIAS_M
        + RANGE_SIGMA_M * torch.randn(pose.shape[0], generator=generator, dtype=DT)
    )
    pose_t = torch.arange(STEPS + 1, dtype=DT) * 0.5
    return RangeRun(
        name="simulated",
        pose_t=pose_t,
        odometry=odometry,
        range_t=pose_t[pose],
        range_anchor=ANCHOR_IDS[rows],
        ranges=ranges,
        anchor_ids=ANCHOR_IDS,
        anchors=ANCHORS.clone(),
        truth=truth,
    )


@pytest.fixture(scope="module")
def run() -> RangeRun:
    return _simulate(START_ON_GRID)


@pytest.fixture(scope="module")
def settings() -> RangeSmootherSettings:
    return RangeSmootherSettings(range_sigma_m=RANGE_SIGMA_M, range_bias_m=RANGE_BIAS_M)


def _position_rmse(poses: torch.Tensor, truth: torch.Tensor) -> float:
    return float((poses[:, 0:2] - truth[:, 0:2]).norm(dim=-1).pow(2).mean().sqrt())


def test_chain_equals_sequential_composition():
    generator = torch.Generator().manual_seed(0)
    steps = torch.randn(300, 3, generator=generator, dtype=DT) * torch.tensor([2.0, 1.0, 1.5])
    start = torch.tensor([3.0, -4.0, 3.0], dtype=DT)
    poses = chain(start, steps)
    assert poses.shape == (301, 3)
    pose = start
    torch.testing.assert_close(poses[0], start, rtol=0, atol=0)
    for k in range(300):
        pose = compose(pose, steps[k])
        # headings wrapped the same way; positions to 1e-12 m
        torch.testing.assert_close(poses[k + 1], pose, rtol=0, atol=1e-12)
    assert poses[:, 2].abs().max() <= math.pi
    assert chain(start, steps[:0]).shape == (1, 3)


def test_calibrate_recovers_the_simulated_bias_and_sigma(run):
    """Median and 1.4826 MAD of 1604 ranges: within 0.03 m (about 4 standard errors)."""
    calibrated = calibrate_from_truth(run)
    assert calibrated.range_bias_m == pytest.approx(RANGE_BIAS_M, abs=0.03)
    assert calibrated.range_sigma_m == pytest.approx(RANGE_SIGMA_M, abs=0.03)
    # with truth headings the odometry noise is measured too (positive, not the default)
    noise = calibrated.odometry_noise
    assert noise != OdometryNoise() and noise.forward == noise.lateral > 0 and noise.heading > 0
    # other settings are kept
    base = RangeSmootherSettings(max_iterations=7, solve_anchors=True)
    assert calibrate_from_truth(run, base).max_iterations == 7
    assert calibrate_from_truth(run, base).solve_anchors


def test_calibrate_without_truth_headings_keeps_the_odometry_noise(run):
    truth = run.truth.clone()
    truth[:, 2] = math.nan
    noise = OdometryNoise(forward=1e-3, lateral=2e-3, heading=3e-4)
    with pytest.warns(UserWarning, match="odometry noise not measured.*no truth headings"):
        calibrated = calibrate_from_truth(
            dataclasses.replace(run, truth=truth), RangeSmootherSettings(odometry_noise=noise)
        )
    assert calibrated.odometry_noise == noise
    assert calibrated.range_bias_m == pytest.approx(RANGE_BIAS_M, abs=0.03)


def test_calibrate_needs_truth(run):
    with pytest.raises(ValueError, match="run 'simulated' has no truth"):
        calibrate_from_truth(dataclasses.replace(run, truth=None))


@pytest.mark.parametrize(
    ("start", "heading_tol", "position_tol"),
    [(START_ON_GRID, 1e-12, 0.3), ((-4.0, 6.0, -2.5), 2 * math.pi / 72, 0.5)],
    ids=["on-grid", "between-grid-headings"],
)
def test_estimate_start_finds_the_simulated_start(start, heading_tol, position_tol):
    """The odometry starts at its own origin; the start in the anchors' frame is found: a
    heading on the 5-degree search grid exactly, another within one grid step; the position
    within a few decimetres (over 30 m of noisy odometry)."""
    run = _simulate(start, seed=1)
    found = estimate_start(run, run.ranges - RANGE_BIAS_M, RANGE_SIGMA_M)
    assert found.shape == (3,) and found.dtype == DT
    heading_error = math.remainder(found[2].item() - start[2], 2 * math.pi)
    assert abs(heading_error) < heading_tol
    assert (found[0:2] - torch.tensor(start[0:2], dtype=DT)).norm() < position_tol


def test_estimate_start_needs_three_ranges(run):
    few = dataclasses.replace(
        run, range_t=run.range_t[:2], range_anchor=run.range_anchor[:2], ranges=run.ranges[:2]
    )
    with pytest.raises(ValueError, match="needs 3 or more ranges .* got 2; give the start"):
        estimate_start(few, few.ranges, RANGE_SIGMA_M)


@pytest.mark.parametrize("positions", ["one anchor", "coincident guesses"])
def test_estimate_start_needs_two_anchor_positions(run, positions):
    """Ranges to one anchor (or to anchors all guessed at one place) fit the run turned
    about it at any heading: refused, not a heading picked at random."""
    if positions == "one anchor":
        kept = run.range_anchor == ANCHOR_IDS[1]
        case = dataclasses.replace(
            run,
            range_t=run.range_t[kept],
            range_anchor=run.range_anchor[kept],
            ranges=run.ranges[kept],
        )
        named = r"anchor\(s\) \[5\] at \(25, -18\) only; give the start pose"
    else:
        case = dataclasses.replace(run, anchors=torch.zeros_like(ANCHORS))
        named = r"anchor\(s\) \[3, 5, 8, 11\] at \(0, 0\) only; give the start pose"
    with pytest.raises(ValueError, match="needs ranges to anchors at 2 or more positions"):
        estimate_start(case, case.ranges, RANGE_SIGMA_M)
    with pytest.raises(ValueError, match=named):
        smooth_ranges(case, RangeSmootherSettings())


def test_start_heading_in_degrees_is_refused(run, settings):
    """40 (degrees meant) is refused naming its radians; a heading just past the half turn
    (3.5 rad, not wrapped) is taken as given."""
    start = torch.tensor([5.0, -3.0, 40.0], dtype=DT)
    with pytest.raises(ValueError, match=r"start heading 40 rad .* would be 0\.6981 rad"):
        smooth_ranges(run, dataclasses.replace(settings, start=start))
    start[2] = 3.5
    result = smooth_ranges(run, dataclasses.replace(settings, start=start, max_iterations=1))
    assert torch.equal(result.start, start)


def test_smooth_with_the_start_searched_and_given(run, settings):
    """Both within 0.1 m RMSE of the truth where dead reckoning from the true start is
    0.4 m off; a given start is used as it is."""
    dead_reckoning = _position_rmse(run.odometry_poses(), run.truth)
    assert dead_reckoning > 0.4
    searched = smooth_ranges(run, settings)
    given = smooth_ranges(run, dataclasses.replace(settings, start=run.truth[0]))
    assert searched.start_searched and not given.start_searched
    assert torch.equal(given.start, run.truth[0])
    assert (searched.start[0:2] - run.truth[0, 0:2]).norm() < 0.15
    for result in (searched, given):
        assert result.status == "converged"
        assert result.final_cost < result.initial_cost
        assert result.poses.shape == (STEPS + 1, 3)
        assert torch.equal(result.anchors, ANCHORS)
        rmse = _position_rmse(result.poses, run.truth)
        assert rmse < 0.1
        assert result.truth_error["rmse_m"] == pytest.approx(rmse, rel=1e-12)
        assert set(result.summary()) >= {"start", "final_cost", "status", "truth_error"}


def test_smooth_solving_the_anchors(run, settings):
    """Range-only SLAM, from anchors multilaterated (positions unknown, NaN; map frame =
    the start pose) or from guesses 0.5 m off (start searched against them): the same
    solution up to a rigid motion -- equal costs, every pose-to-anchor distance within
    0.05 m RMS of the truth's, anchor spacings within 3 cm; the cost at most the held
    anchors' one."""
    slam = dataclasses.replace(settings, solve_anchors=True)
    generator = torch.Generator().manual_seed(5)
    offset = torch.nn.functional.normalize(torch.randn(4, 2, generator=generator, dtype=DT), dim=1)
    guessed = dataclasses.replace(run, anchors=ANCHORS + 0.5 * offset)
    unknown = dataclasses.replace(run, anchors=torch.full_like(ANCHORS, math.nan))
    from_scratch = smooth_ranges(unknown, slam, anchors_known_positions=False)
    from_guesses = smooth_ranges(guessed, slam)
    assert not from_scratch.start_searched and torch.equal(
        from_scratch.start, torch.zeros(3, dtype=DT)
    )
    assert from_guesses.start_searched
    held = smooth_ranges(run, dataclasses.replace(settings, start=run.truth[0]))
    true_spans = (run.truth[:, None, 0:2] - ANCHORS[None]).norm(dim=-1)
    true_spacing = (ANCHORS[:, None] - ANCHORS[None]).norm(dim=-1)
    for result in (from_scratch, from_guesses):
        assert result.status == "converged"
        assert result.final_cost == pytest.approx(from_scratch.final_cost, rel=1e-6)
        assert result.final_cost <= held.final_cost
        spans = (result.poses[:, None, 0:2] - result.anchors[None]).norm(dim=-1)
        assert (spans - true_spans).pow(2).mean().sqrt() < 0.05
        spacing = (result.anchors[:, None] - result.anchors[None]).norm(dim=-1)
        assert (spacing - true_spacing).abs().max() < 0.03
    # the map frame of the scratch solve is the start pose
    assert from_scratch.poses[0].abs().max() < 0.05
    # from guesses the map starts where the held solve put the start (not on the search's
    # 5-degree grid): the poses stay near the truth in the guesses' frame
    assert _position_rmse(from_guesses.poses, run.truth) < 0.3


@pytest.fixture(scope="module")
def plaza():
    pytest.importorskip("gtsam")
    from msf_torch.io.plaza import load_plaza

    return load_plaza("Plaza1"), load_plaza("Plaza2")


def test_plaza1_calibration_reads_the_documented_bias(plaza):
    """At the next pose (GTSAM's graph) and at the interpolated position (the default)."""
    calibrated = calibrate_from_truth(plaza[0], RangeSmootherSettings(range_timing="next_pose"))
    assert calibrated.range_bias_m == pytest.approx(2.849, abs=0.001)
    assert calibrated.range_sigma_m == pytest.approx(1.209, abs=0.001)
    calibrated = calibrate_from_truth(plaza[0])
    assert calibrated.range_bias_m == pytest.approx(2.839, abs=0.001)
    assert calibrated.range_sigma_m == pytest.approx(1.217, abs=0.001)


def test_interpolated_ranges_keep_accuracy_when_the_odometry_is_slow(plaza):
    """Plaza2 (3.6 m/s) with its 10 Hz odometry thinned to 1 Hz, settings from Plaza1 thinned
    alike: a range attached to the next pose is up to 3.6 m off where it was taken (RMSE
    1.52 m against RTK, measured), interpolated between the poses around it 0.45 m, as
    with the full-rate odometry (0.41-0.44 m)."""
    errors = {}
    for timing in ("next_pose", "interpolate"):
        calibration, test = (run.thinned(10) for run in plaza)
        settings = calibrate_from_truth(
            calibration, RangeSmootherSettings(range_timing=timing), stretch_steps=10
        )
        settings = dataclasses.replace(settings, start=test.truth[0], start_sigma=(0.1, 0.1, 0.05))
        errors[timing] = smooth_ranges(test, settings).truth_error["rmse_m"]
    assert errors["interpolate"] < 0.5 < 1.2 < errors["next_pose"]


def test_range_pose_fraction_and_positions():
    """Ranges at, between and outside the pose times: the fraction of the way from the pose
    before to the one it is attached to, and the interpolated positions."""
    run = RangeRun(
        name="t",
        pose_t=torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64),
        odometry=torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], dtype=torch.float64),
        range_t=torch.tensor([-0.5, 0.0, 0.25, 1.0, 2.5, 3.5], dtype=torch.float64),
        range_anchor=torch.zeros(6, dtype=torch.int64),
        ranges=torch.ones(6, dtype=torch.float64),
        anchor_ids=torch.zeros(1, dtype=torch.int64),
        anchors=torch.zeros(1, 2, dtype=torch.float64),
    )
    assert run.range_pose_index().tolist() == [0, 0, 1, 1, 2, 2]
    assert run.range_pose_fraction().tolist() == [1.0, 1.0, 0.25, 1.0, 0.75, 1.0]
    poses = run.odometry_poses(torch.zeros(3, dtype=torch.float64))
    assert run.range_positions(poses)[:, 0].tolist() == [0.0, 0.0, 0.25, 1.0, 2.5, 3.0]
    with pytest.raises(ValueError, match="range_timing"):
        smooth_ranges(run, RangeSmootherSettings(range_timing="nearest", start=poses[0]))


def test_plaza2_with_plaza1_calibration(plaza):
    """Settings calibrated on Plaza1, Plaza2 smoothed from its true start: under 0.6 m
    RMSE where dead reckoning is over 25 m off."""
    plaza1, plaza2 = plaza
    settings = dataclasses.replace(calibrate_from_truth(plaza1), start=plaza2.truth[0])
    result = smooth_ranges(plaza2, settings)
    assert result.status == "converged"
    assert result.truth_error["rmse_m"] < 0.6
    assert _position_rmse(plaza2.odometry_poses(), plaza2.truth) > 25.0


def test_holding_anchors_without_positions_is_refused(run, settings):
    unknown = dataclasses.replace(run, anchors=torch.full_like(ANCHORS, math.nan))
    with pytest.raises(ValueError, match="positions are unknown"):
        smooth_ranges(unknown, settings)


def test_thinned_run_keeps_the_poses_it_keeps():
    """Composed steps give the original dead-reckoned poses at the kept times; ranges after
    the last kept pose leave; ``every`` below 1 is refused."""
    generator = torch.Generator().manual_seed(2)
    odometry = torch.cat(
        (torch.rand(10, 2, generator=generator, dtype=torch.float64), torch.randn(10, 1).double()),
        -1,
    )
    run = RangeRun(
        name="t",
        pose_t=torch.arange(11, dtype=torch.float64),
        odometry=odometry,
        range_t=torch.tensor([0.5, 6.5, 9.5], dtype=torch.float64),
        range_anchor=torch.zeros(3, dtype=torch.int64),
        ranges=torch.ones(3, dtype=torch.float64),
        anchor_ids=torch.zeros(1, dtype=torch.int64),
        anchors=torch.zeros(1, 2, dtype=torch.float64),
        truth=torch.randn(11, 3, generator=generator, dtype=torch.float64),
    )
    thin = run.thinned(3)  # poses 0, 3, 6, 9
    zero = torch.zeros(3, dtype=torch.float64)
    torch.testing.assert_close(
        thin.odometry_poses(zero), run.odometry_poses(zero)[::3], rtol=0, atol=1e-12
    )
    assert thin.pose_t.tolist() == [0.0, 3.0, 6.0, 9.0] and thin.range_t.tolist() == [0.5, 6.5]
    torch.testing.assert_close(thin.truth, run.truth[::3])
    with pytest.raises(ValueError, match="every"):
        run.thinned(0)
