"""Planar odometry + beacon-range smoothing: the range and prior factors against finite
differences, autodiff and GTSAM; a simulated loop among four beacons solved back to its
truth (beacons held or solved, an outlier range under Cauchy and plain least squares);
the problem builder's checks, the odometry noise model and the beacon guess from ranges."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.posegraph2d import SE2, Se2BetweenFactor
from msf_torch.backend.problem import Factor
from msf_torch.backend.range2d import (
    POINT2,
    OdometryNoise,
    Se2InterpolatedRangeFactor,
    Se2PriorFactor,
    Se2RangeFactor,
    multilaterate,
    odometry_range_problem,
)
from msf_torch.backend.robust import RobustKernel

DT = torch.float64
CONFIG = LMConfig(
    max_iterations=100,
    damping="identity",
    linear_solver="sparse",
    damping_update="multiplicative",
    relative_tolerance=1e-12,
    absolute_tolerance=0.0,
)


@pytest.fixture(scope="module")
def gtsam():
    return pytest.importorskip("gtsam")


def _poses(count: int, generator: torch.Generator, spread: float = 3.0) -> torch.Tensor:
    xy = torch.randn(count, 2, generator=generator, dtype=DT) * spread
    heading = (torch.rand(count, generator=generator, dtype=DT) * 2 - 1) * math.pi
    return torch.cat((xy, heading[:, None]), -1)


def _range_factor(count: int, generator: torch.Generator, kernel=None):
    """A range factor on ``count`` random (pose, beacon) pairs, its values and its ranges."""
    poses = _poses(count, generator)
    beacons = torch.randn(count, 2, generator=generator, dtype=DT) * 5.0
    ranges = (beacons - poses[:, 0:2]).norm(dim=-1) + torch.randn(
        count, generator=generator, dtype=DT
    )
    factor = Se2RangeFactor(
        "pose",
        torch.arange(count),
        "beacon",
        torch.arange(count),
        ranges[None],
        torch.full((1, count, 1, 1), 0.3**2, dtype=DT),
        kernel=kernel,
    )
    factor.kinds = [SE2, POINT2]
    return factor, [poses[None], beacons[None]], ranges


def _check_jacobians(factor, values: list[torch.Tensor]) -> None:
    """Analytic Jacobians against central differences through each slot's ``retract`` and
    against the generic autodiff route."""
    residual, jacobians = factor.residual_and_jacobians(values, factor.kinds)
    step = 1e-6
    for slot, kind in enumerate(factor.kinds):
        numeric = torch.zeros_like(jacobians[slot])
        for k in range(kind.tangent_dim):
            delta = torch.zeros(*values[slot].shape[:-1], kind.tangent_dim, dtype=DT)
            delta[..., k] = step
            plus, minus = list(values), list(values)
            plus[slot] = kind.retract(values[slot], delta)
            minus[slot] = kind.retract(values[slot], -delta)
            numeric[..., k] = (factor.residual(plus) - factor.residual(minus)) / (2 * step)
        torch.testing.assert_close(jacobians[slot], numeric, atol=2e-7, rtol=1e-6)
    reference_residual, autodiff = Factor.residual_and_jacobians(factor, values, factor.kinds)
    torch.testing.assert_close(residual, reference_residual, atol=0, rtol=0)
    for ours, reference in zip(jacobians, autodiff, strict=True):
        torch.testing.assert_close(ours, reference, atol=1e-12, rtol=1e-12)


def test_range_jacobians_match_finite_differences_and_autodiff():
    factor, values, _ = _range_factor(16, torch.Generator().manual_seed(0))
    residual, jacobians = factor.residual_and_jacobians(values, factor.kinds)
    assert residual.shape == (1, 16, 1)
    assert jacobians[0].shape == (1, 16, 1, 3) and jacobians[1].shape == (1, 16, 1, 2)
    # a range does not depend on the heading
    assert (jacobians[0][..., 2] == 0).all()
    _check_jacobians(factor, values)


def _interpolated_factor(count: int, generator: torch.Generator, fraction: torch.Tensor):
    """An interpolated range factor between random pose pairs and beacons, and its values."""
    before, after = _poses(count, generator), _poses(count, generator)
    beacons = torch.randn(count, 2, generator=generator, dtype=DT) * 5.0
    ranges = 3.0 + torch.rand(count, generator=generator, dtype=DT)
    factor = Se2InterpolatedRangeFactor(
        "pose",
        torch.arange(count),
        torch.arange(count, 2 * count),
        fraction[None],
        "beacon",
        torch.arange(count),
        ranges[None],
        torch.full((1, count, 1, 1), 0.3**2, dtype=DT),
    )
    factor.kinds = [SE2, SE2, POINT2]
    return factor, [before[None], after[None], beacons[None]], ranges


def test_interpolated_range_jacobians_and_its_ends():
    """Jacobians against central differences and autodiff; a fraction of 1 (0) is the plain
    range factor on the later (earlier) pose; 1/2 ranges from the midpoint."""
    generator = torch.Generator().manual_seed(3)
    fraction = torch.rand(16, generator=generator, dtype=DT)
    factor, values, _ = _interpolated_factor(16, generator, fraction)
    _check_jacobians(factor, values)
    before, after, beacons = (v[0] for v in values)
    for ends, pose in ((1.0, after), (0.0, before)):
        factor.fraction = torch.full((1, 16), ends, dtype=DT)
        plain = Se2RangeFactor(
            "pose",
            torch.arange(16),
            "beacon",
            torch.arange(16),
            factor.ranges,
            torch.full((1, 16, 1, 1), 0.3**2, dtype=DT),
        )
        torch.testing.assert_close(
            factor.residual(values), plain.residual([pose[None], beacons[None]]), rtol=0, atol=0
        )
    factor.fraction = torch.full((1, 16), 0.5, dtype=DT)
    midpoint = 0.5 * (before[:, 0:2] + after[:, 0:2])
    expected = (beacons - midpoint).norm(dim=-1) - factor.ranges[0]
    torch.testing.assert_close(factor.residual(values)[0, :, 0], expected, rtol=0, atol=1e-14)


def test_prior_jacobian_matches_finite_differences_and_autodiff():
    generator = torch.Generator().manual_seed(1)
    poses = _poses(12, generator)
    priors = _poses(12, generator)
    priors[:4] = poses[:4] + 1e-7  # small errors: the logarithm's Taylor branch
    priors[-1, 2] = poses[-1, 2] - (math.pi - 1e-3)  # an error near the half turn
    covariance = torch.diag(torch.tensor([0.04, 0.09, 0.01], dtype=DT)).expand(1, 12, 3, 3)
    factor = Se2PriorFactor("pose", torch.arange(12), priors[None], covariance)
    factor.kinds = [SE2]
    _check_jacobians(factor, [poses[None]])


def test_range_residual_equals_gtsam_range_factor(gtsam):
    factor, values, ranges = _range_factor(15, torch.Generator().manual_seed(2))
    residual = factor.residual(values)[0, :, 0]
    poses, beacons = values[0][0], values[1][0]
    unit = gtsam.noiseModel.Unit.Create(1)
    for k in range(15):
        graph_values = gtsam.Values()
        graph_values.insert(0, gtsam.Pose2(*poses[k].tolist()))
        graph_values.insert(1, beacons[k].numpy().copy())
        reference = gtsam.RangeFactor2D(0, 1, float(ranges[k]), unit)
        np.testing.assert_allclose(
            residual[k].item(), reference.unwhitenedError(graph_values)[0], rtol=0, atol=1e-12
        )


def test_prior_residual_equals_gtsam_prior_factor(gtsam):
    generator = torch.Generator().manual_seed(3)
    poses, priors = _poses(15, generator), _poses(15, generator)
    factor = Se2PriorFactor(
        "pose", torch.arange(15), priors[None], torch.eye(3, dtype=DT).expand(1, 15, 3, 3)
    )
    residual = factor.residual([poses[None]])[0]
    unit = gtsam.noiseModel.Unit.Create(3)
    for k in range(15):
        graph_values = gtsam.Values()
        graph_values.insert(0, gtsam.Pose2(*poses[k].tolist()))
        reference = gtsam.PriorFactorPose2(0, gtsam.Pose2(*priors[k].tolist()), unit)
        np.testing.assert_allclose(
            residual[k].numpy(), reference.unwhitenedError(graph_values), rtol=0, atol=1e-12
        )


STEPS = 120
BEACONS = torch.tensor([[-12.0, -10.0], [14.0, -9.0], [13.0, 15.0], [-11.0, 13.0]], dtype=DT)
START = (2.0, -1.0, 0.3)
FIRST_COVARIANCE = torch.diag(torch.tensor([0.1**2, 0.1**2, 0.05**2], dtype=DT))


def _dead_reckoning(start: tuple[float, float, float], odometry: torch.Tensor) -> torch.Tensor:
    """(M + 1, 3) poses, composed one step at a time: each step ``[dx, dy, dheading]`` is
    the next pose in the current pose's frame."""
    pose = list(start)
    out = [list(pose)]
    for dx, dy, turn in odometry.tolist():
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = [
            pose[0] + c * dx - s * dy,
            pose[1] + s * dx + c * dy,
            math.remainder(pose[2] + turn, 2 * math.pi),
        ]
        out.append(pose)
    return torch.tensor(out, dtype=DT)


@pytest.fixture(scope="module")
def loop():
    """A robot driving one loop (~60 m) among four beacons: exact odometry (M, 3) with a
    small sideways part (a skidding robot), the true poses (M + 1, 3), a range from every
    second pose to the beacons in turn (exact), and an initial estimate from odometry with
    5 % scale and 4 mrad/step heading drift (4.6 m off at worst)."""
    k = torch.arange(STEPS, dtype=DT)
    odometry = torch.stack(
        (
            0.5 + 0.1 * torch.sin(k / 7),
            0.03 * torch.cos(k / 3),
            2 * math.pi / STEPS + 0.01 * torch.cos(k / 5),
        ),
        -1,
    )
    truth = _dead_reckoning(START, odometry)
    range_pose = torch.arange(0, STEPS + 1, 2)
    range_beacon = (range_pose // 2) % 4
    ranges = (BEACONS[range_beacon] - truth[range_pose, 0:2]).norm(dim=-1)
    drift = odometry * torch.tensor([1.05, 1.05, 1.0], dtype=DT)
    drift[:, 2] += 0.004
    drifted = _dead_reckoning(START, drift)
    assert (drifted[:, 0:2] - truth[:, 0:2]).norm(dim=-1).max() > 4.0
    return odometry, truth, range_pose, range_beacon, ranges, drifted


def test_default_initial_estimate_chains_the_odometry(loop):
    odometry, truth, range_pose, range_beacon, ranges, _ = loop
    problem = odometry_range_problem(
        odometry, range_pose, range_beacon, ranges, BEACONS, truth[0], FIRST_COVARIANCE
    )
    torch.testing.assert_close(problem.values["pose"][0], truth, rtol=0, atol=1e-12)
    torch.testing.assert_close(problem.values["beacon"][0], BEACONS, rtol=0, atol=0)


def test_odometry_factor_measures_the_relative_pose_weighted_by_its_length():
    """Each step is the between factor's measurement as given (sideways part included); its
    covariance depends on the step's length, not on which way it points."""
    d = 0.8
    odometry = torch.tensor(
        [[d, 0.0, 0.0], [0.0, d, 0.1], [0.6 * d, -0.8 * d, -0.2], [0.0, 0.0, 0.3]], dtype=DT
    )
    empty = torch.zeros(0, dtype=torch.long)
    problem = odometry_range_problem(
        odometry,
        empty,
        empty,
        torch.zeros(0, dtype=DT),
        BEACONS,
        torch.zeros(3, dtype=DT),
        FIRST_COVARIANCE,
    )
    (between,) = [f for f in problem.factors if isinstance(f, Se2BetweenFactor)]
    torch.testing.assert_close(between.translation[0], odometry[:, 0:2], rtol=0, atol=0)
    torch.testing.assert_close(between.heading[0], odometry[:, 2], rtol=0, atol=0)
    information = between.sqrt_information[0]
    torch.testing.assert_close(information[1], information[0], rtol=1e-14, atol=0)
    torch.testing.assert_close(information[2], information[0], rtol=1e-14, atol=0)
    assert not torch.allclose(information[3], information[0])


def test_simulated_loop_recovers_the_truth_with_known_beacons(loop):
    odometry, truth, range_pose, range_beacon, ranges, drifted = loop
    problem = odometry_range_problem(
        odometry,
        range_pose,
        range_beacon,
        ranges,
        BEACONS,
        truth[0],
        FIRST_COVARIANCE,
        range_sigma_m=0.1,
        initial_poses=drifted,
    )
    assert problem.values["pose"].shape == (1, STEPS + 1, 3)
    with torch.no_grad():
        result = solve(problem, CONFIG)
    assert result.status == ["converged"]
    assert result.initial_cost.item() > 1e3 and result.cost.item() < 1e-16
    poses = result.values["pose"][0]
    assert (poses[:, 0:2] - truth[:, 0:2]).abs().max() < 1e-8
    torch.testing.assert_close(poses[:, 2], truth[:, 2], rtol=0, atol=1e-8)
    # held beacons stay where they were given
    torch.testing.assert_close(result.values["beacon"][0], BEACONS, rtol=0, atol=0)


def test_simulated_loop_recovers_unknown_beacons(loop):
    odometry, truth, range_pose, range_beacon, ranges, drifted = loop
    generator = torch.Generator().manual_seed(4)
    offset = torch.nn.functional.normalize(torch.randn(4, 2, generator=generator, dtype=DT), dim=1)
    guess = BEACONS + 0.5 * offset
    problem = odometry_range_problem(
        odometry,
        range_pose,
        range_beacon,
        ranges,
        guess,
        truth[0],
        FIRST_COVARIANCE,
        range_sigma_m=0.1,
        beacons_known=False,
        initial_poses=drifted,
    )
    with torch.no_grad():
        result = solve(problem, CONFIG)
    assert result.status == ["converged"]
    torch.testing.assert_close(result.values["beacon"][0], BEACONS, rtol=0, atol=1e-8)
    assert (result.values["pose"][0, :, 0:2] - truth[:, 0:2]).abs().max() < 1e-8


def test_outlier_range_is_down_weighted_by_cauchy_only(loop):
    """One range 20 m long: Cauchy (2.3849 sigmas) keeps every position within 5 mm, plain
    least squares pulls the robot metres away."""
    odometry, truth, range_pose, range_beacon, ranges, drifted = loop
    wrong = ranges.clone()
    wrong[15] += 20.0
    errors = {}
    for name, kernel in (("cauchy", RobustKernel("cauchy", 2.3849)), ("plain", None)):
        problem = odometry_range_problem(
            odometry,
            range_pose,
            range_beacon,
            wrong,
            BEACONS,
            truth[0],
            FIRST_COVARIANCE,
            range_sigma_m=0.1,
            range_kernel=kernel,
            initial_poses=drifted,
        )
        with torch.no_grad():
            result = solve(problem, CONFIG)
        assert result.status == ["converged"]
        errors[name] = (result.values["pose"][0, :, 0:2] - truth[:, 0:2]).norm(dim=-1).max()
    assert errors["cauchy"] < 5e-3
    assert errors["plain"] > 1.0


def test_problem_checks_shapes_and_indices(loop):
    odometry, truth, range_pose, range_beacon, ranges, _ = loop
    args = dict(
        odometry=odometry,
        range_pose=range_pose,
        range_beacon=range_beacon,
        ranges=ranges,
        beacons=BEACONS,
        first_pose=truth[0],
        first_pose_covariance=FIRST_COVARIANCE,
    )
    cases = [
        (
            {"odometry": odometry[:, :1]},
            r"odometry must be \(M, 3\) relative poses \[dx, dy, dheading\], got \(120, 1\)",
        ),
        ({"odometry": odometry[:, :2]}, r"odometry must be \(M, 3\) .*got \(120, 2\)"),
        ({"odometry": odometry[None]}, r"odometry must be \(M, 3\) .*got \(1, 120, 3\)"),
        ({"range_pose": range_pose[:-1]}, r"range_pose must be \(61,\) like ranges"),
        ({"range_beacon": range_beacon[None]}, r"range_beacon must be \(61,\) like ranges"),
        ({"range_pose": range_pose - 1}, "range_pose must index the 121 poses"),
        ({"range_pose": range_pose + 1}, "range_pose must index the 121 poses"),
        ({"range_beacon": range_beacon - 1}, "range_beacon must index the 4 beacons"),
        ({"range_beacon": range_beacon + 1}, "range_beacon must index the 4 beacons"),
        ({"ranges": ranges[:, None]}, r"ranges must be \(K,\), got \(61, 1\)"),
        ({"range_pose": range_pose.to(DT)}, "range_pose must hold integer indices"),
        ({"beacons": BEACONS.T.contiguous()}, r"beacons must be \(L, 2\), got \(2, 4\)"),
        ({"first_pose": truth[0, :2]}, r"first_pose must be \(3,\), got \(2,\)"),
        (
            {"first_pose_covariance": FIRST_COVARIANCE.diagonal().sqrt()},
            r"first_pose_covariance must be \(3, 3\), got \(3,\)",
        ),
        (
            {"first_pose_covariance": -FIRST_COVARIANCE},
            r"first_pose_covariance must be a positive definite",
        ),
        ({"initial_poses": truth[:-1]}, r"initial_poses must be \(121, 3\), got \(120, 3\)"),
        ({"range_sigma_m": 0.0}, "range_sigma_m must be a positive number"),
        ({"range_sigma_m": -1.0}, "range_sigma_m must be a positive number"),
    ]
    for name, index in (("ranges", (5,)), ("odometry", (3, 0)), ("beacons", (1, 1))):
        bad = args[name].clone()
        bad[index] = math.nan
        message = rf"{name}\[{', '.join(map(str, index))}\] is not finite \(nan\)"
        cases.append(({name: bad}, message))
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            odometry_range_problem(**{**args, **change})
    # the last pose is a valid index; no ranges at all is a valid problem
    odometry_range_problem(**{**args, "range_pose": torch.full_like(range_pose, STEPS)})
    empty = torch.zeros(0, dtype=torch.long)
    problem = odometry_range_problem(
        **{**args, "range_pose": empty, "range_beacon": empty, "ranges": torch.zeros(0, dtype=DT)}
    )
    assert problem.values["pose"].shape == (1, STEPS + 1, 3)


def test_odometry_noise_covariance_closed_form():
    noise = OdometryNoise(forward=2e-3, lateral=5e-4, heading=1e-4, floor_m=0.01, floor_rad=0.002)
    distance = torch.tensor([0.0, 0.5, -2.0, 10.0], dtype=DT)
    covariance = noise.covariance(distance)
    assert covariance.shape == (4, 3, 3)
    d = distance.abs()
    expected = torch.zeros(4, 3, 3, dtype=DT)
    expected[:, 0, 0] = 2e-3 * d + 0.01**2
    expected[:, 1, 1] = 5e-4 * d + 0.01**2
    expected[:, 2, 2] = 1e-4 * d + 0.002**2
    torch.testing.assert_close(covariance, expected, rtol=1e-15, atol=0)
    # defaults: a 1 m step has sigmas sqrt(6e-4 + 1e-6) m and sqrt(5e-5 + 1e-6) rad
    default = OdometryNoise().covariance(torch.ones(1, dtype=DT))[0].diagonal()
    torch.testing.assert_close(
        default, torch.tensor([6.01e-4, 6.01e-4, 5.1e-5], dtype=DT), rtol=1e-12, atol=0
    )


def test_multilaterate_recovers_a_beacon_from_exact_ranges(loop):
    """From a stretch of the loop (curved), exact ranges give the beacon back; from a
    straight path, the beacon or its mirror image across the path."""
    _, truth, *_ = loop
    positions = truth[10:40, 0:2]
    for beacon in BEACONS:
        ranges = (beacon - positions).norm(dim=-1)
        torch.testing.assert_close(multilaterate(positions, ranges), beacon, rtol=0, atol=1e-9)
    line = torch.stack((torch.linspace(0.0, 10.0, 6, dtype=DT), torch.zeros(6, dtype=DT)), -1)
    beacon = torch.tensor([3.0, 7.0], dtype=DT)
    found = multilaterate(line, (beacon - line).norm(dim=-1))
    torch.testing.assert_close(found.abs(), beacon, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"need N >= 3 .* got \(2, 2\) and \(2,\)"):
        multilaterate(positions[:2], torch.ones(2, dtype=DT))
    with pytest.raises(ValueError, match=r"got \(30, 2\) and \(29,\)"):
        multilaterate(positions, torch.ones(29, dtype=DT))
    ranges = torch.ones(30, dtype=DT)
    ranges[4] = math.inf
    with pytest.raises(ValueError, match=r"ranges\[4\] is not finite"):
        multilaterate(positions, ranges)


def test_multilaterate_over_a_batch_equals_one_problem_at_a_time():
    generator = torch.Generator().manual_seed(11)
    positions = torch.randn(5, 12, 2, generator=generator, dtype=DT) * 4.0
    beacons = torch.randn(5, 2, generator=generator, dtype=DT) * 6.0
    ranges = (beacons[0] - positions[0]).norm(dim=-1)  # one set of ranges, five position sets
    batched = multilaterate(positions, ranges)
    assert batched.shape == (5, 2)
    for k in range(5):
        torch.testing.assert_close(
            batched[k], multilaterate(positions[k], ranges), rtol=0, atol=1e-12
        )
    torch.testing.assert_close(batched[0], beacons[0], rtol=0, atol=1e-8)
