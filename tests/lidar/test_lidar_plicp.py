"""PLICP: exact recovery on noise-free scans, the closed-form step against least squares and
finite differences, trimming, degeneracy handling and batching."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from msf_torch.geometry.se2 import between, transform_points
from msf_torch.lidar.odometry import scan_odometry
from msf_torch.lidar.plicp import (
    PlicpConfig,
    correspondences,
    fit_lines,
    plicp,
    point_to_line_gradient_covariance,
    point_to_line_hessian,
    point_to_line_step,
    scan_points,
)
from msf_torch.sim.lidar2d import LidarSpec, SegmentMap, corridor_map, scan_at, warehouse_map

F64 = torch.float64


def _room() -> SegmentMap:
    """A 12 x 7 m room with an inner wall and a box: no unobservable direction."""
    segments = [
        [[0, 0], [12, 0]], [[12, 0], [12, 7]], [[12, 7], [0, 7]], [[0, 7], [0, 0]],
        [[4, 7], [4, 4.5]], [[7, 1], [8.5, 1]], [[8.5, 1], [8.5, 2.2]],
        [[8.5, 2.2], [7, 2.2]], [[7, 2.2], [7, 1]],
    ]  # fmt: skip
    route = torch.tensor([[1.0, 1.0], [11.0, 6.0]], dtype=F64)
    return SegmentMap("room", torch.tensor(segments, dtype=F64), route)


def _pairs(segment_map: SegmentMap, poses: torch.Tensor, rng=None):
    spec = LidarSpec()
    ranges, _ = scan_at(segment_map, poses, spec, rng)
    points, valid = scan_points(ranges, spec.angles())
    truth = between(poses[0::2], poses[1::2])
    return points[0::2], valid[0::2], points[1::2], valid[1::2], truth


def _cost(pose, points, anchor, normal, weight):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    moved = points @ np.array([[c, s], [-s, c]]) + pose[:2]
    return ((moved - anchor) * normal).sum(-1) * np.sqrt(weight)


def test_recovers_known_rigid_transform_noise_free():
    poses = torch.tensor(
        [
            [2.0, 2.0, 0.3], [2.25, 2.1, 0.38],
            [9.5, 5.0, -2.0], [9.3, 4.85, -2.1],
            [5.5, 3.0, 1.2], [5.6, 3.3, 1.05],
        ],
        dtype=F64,
    )  # fmt: skip
    ref_p, ref_v, cur_p, cur_v, truth = _pairs(_room(), poses)
    config = PlicpConfig(epsilon_xy_m=1e-12, epsilon_theta_rad=1e-12)
    offset = torch.tensor([0.08, -0.06, 0.03], dtype=F64)
    for guess in (torch.zeros_like(truth), truth + offset):
        result = plicp(ref_p, ref_v, cur_p, cur_v, guess, config)
        assert bool(result.converged.all()) and not bool(result.degenerate.any())
        error = (result.pose - truth).abs().max()
        assert error < 1e-6, f"max error {error:.3g}"
        assert float(result.residual_rms.max()) < 1e-6


def test_batch_equals_one_by_one():
    poses = torch.tensor(
        [[2.0, 2.0, 0.3], [2.2, 2.1, 0.36], [9.5, 5.0, -2.0], [9.3, 4.9, -2.05]], dtype=F64
    )
    ref_p, ref_v, cur_p, cur_v, truth = _pairs(_room(), poses, np.random.default_rng(0))
    guess = torch.zeros_like(truth)
    batched = plicp(ref_p, ref_v, cur_p, cur_v, guess)
    for k in range(truth.shape[0]):
        single = plicp(ref_p[k : k + 1], ref_v[k : k + 1], cur_p[k : k + 1], cur_v[k : k + 1],
                       guess[k : k + 1])  # fmt: skip
        torch.testing.assert_close(single.pose[0], batched.pose[k], rtol=0, atol=1e-12)
        assert int(single.iterations[0]) == int(batched.iterations[k])
        torch.testing.assert_close(single.covariance[0], batched.covariance[k], rtol=1e-9,
                                   atol=1e-15)  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_closed_form_step_is_the_least_squares_minimum(seed):
    rng = np.random.default_rng(seed)
    batch, n = 3, 40
    points = rng.uniform(-5, 5, (batch, n, 2))
    angle = rng.uniform(-math.pi, math.pi, (batch, n))
    normal = np.stack((np.cos(angle), np.sin(angle)), -1)
    true_pose = np.c_[rng.normal(0, 0.5, (batch, 2)), rng.uniform(-math.pi, math.pi, batch)]
    anchor = np.empty_like(points)
    for b in range(batch):
        c, s = np.cos(true_pose[b, 2]), np.sin(true_pose[b, 2])
        moved = points[b] @ np.array([[c, s], [-s, c]]) + true_pose[b, :2]
        # anchors off the lines' foot points along the line, plus noise across it
        along = np.stack((-normal[b, :, 1], normal[b, :, 0]), -1)
        anchor[b] = (
            moved + rng.normal(0, 0.3, (n, 1)) * along + rng.normal(0, 0.05, (n, 1)) * (normal[b])
        )
    weight = (rng.uniform(size=(batch, n)) > 0.2).astype(float)
    solved = point_to_line_step(
        torch.tensor(points), torch.tensor(anchor), torch.tensor(normal), torch.tensor(weight),
        torch.zeros(batch, 2, dtype=F64), prior_weight=0.0,
    ).numpy()  # fmt: skip
    for b in range(batch):
        args = (points[b], anchor[b], normal[b], weight[b])
        best = None
        for theta0 in np.linspace(-math.pi, math.pi, 12, endpoint=False):
            fit = least_squares(_cost, np.array([0.0, 0.0, theta0]), args=args, xtol=1e-15,
                                ftol=1e-15, gtol=1e-15)  # fmt: skip
            if best is None or fit.cost < best.cost:
                best = fit
        ours = 0.5 * float((_cost(solved[b], *args) ** 2).sum())
        assert ours <= best.cost * (1 + 1e-10) + 1e-14
        delta = solved[b] - best.x
        delta[2] = math.remainder(delta[2], 2 * math.pi)
        assert np.abs(delta).max() < 1e-7
        # the gradient of the cost vanishes at our solution (central differences)
        h = 1e-6
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = h
            up = (_cost(solved[b] + step, *args) ** 2).sum()
            down = (_cost(solved[b] - step, *args) ** 2).sum()
            assert abs(up - down) / (2 * h) < 1e-6 * max(1.0, (up + down))


def test_hessian_matches_finite_difference_jacobian():
    rng = np.random.default_rng(4)
    points = torch.tensor(rng.uniform(-4, 4, (2, 25, 2)))
    angle = torch.tensor(rng.uniform(-3, 3, (2, 25)))
    normal = torch.stack((torch.cos(angle), torch.sin(angle)), -1)
    anchor = torch.tensor(rng.normal(0, 1, (2, 25, 2)))
    weight = torch.tensor(rng.uniform(0, 1, (2, 25)))
    pose = torch.tensor([[0.3, -0.2, 0.7], [1.0, 0.5, -2.5]], dtype=F64)
    hessian = point_to_line_hessian(pose, points, normal, weight)
    for b in range(2):
        args = (points[b].numpy(), anchor[b].numpy(), normal[b].numpy(), np.ones(25))
        jac = np.zeros((25, 3))
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = 1e-6
            jac[:, axis] = (
                _cost(pose[b].numpy() + step, *args) - _cost(pose[b].numpy() - step, *args)
            ) / 2e-6
        expected = jac.T @ (weight[b].numpy()[:, None] * jac)
        np.testing.assert_allclose(hessian[b].numpy(), expected, rtol=1e-7, atol=1e-8)


def test_trimming_keeps_the_best_fraction():
    poses = torch.tensor([[2.0, 2.0, 0.3], [2.25, 2.1, 0.38]], dtype=F64)
    ref_p, ref_v, cur_p, cur_v, _ = _pairs(_room(), poses, np.random.default_rng(1))
    config = PlicpConfig()
    lines = fit_lines(ref_p, ref_v, config)
    corr = correspondences(torch.zeros(1, 3, dtype=F64), cur_p, cur_v, lines, config)
    matched = int(corr.matched.sum())
    assert int(corr.count[0]) == math.ceil(0.8 * matched)
    kept = corr.residual[corr.keep].abs()
    # recompute the residuals of the dropped matches: none is smaller than a kept one
    moved = cur_p[0]
    anchor = lines.anchor[0]
    dist = torch.cdist(moved, torch.where(lines.valid[0, :, None], anchor, 1e6))
    nearest = dist.argmin(-1)
    residual = ((moved - anchor[nearest]) * lines.normal[0, nearest]).sum(-1).abs()
    dropped = corr.matched[0] & ~corr.keep[0]
    assert float(residual[dropped].min()) >= float(kept.max()) - 1e-12
    assert float(dist.min(-1).values[corr.matched[0]].max()) <= 0.5


def test_corridor_keeps_the_guess_along_the_axis():
    corridor = corridor_map()
    poses = torch.tensor([[50.0, 0.1, 0.02], [50.15, 0.12, 0.03]], dtype=F64)
    ref_p, ref_v, cur_p, cur_v, truth = _pairs(corridor, poses)
    config = PlicpConfig(epsilon_xy_m=1e-12, epsilon_theta_rad=1e-12)
    guess = truth + torch.tensor([0.04, 0.03, 0.01], dtype=F64)
    from_guess = plicp(ref_p, ref_v, cur_p, cur_v, guess, config)
    from_identity = plicp(ref_p, ref_v, cur_p, cur_v, torch.zeros_like(truth), config)
    assert bool(from_guess.degenerate.all()) and bool(from_identity.degenerate.all())
    # across the corridor and in rotation the scans fix the pose ...
    error = from_guess.pose - truth
    assert float(error[0, 2].abs()) < 1e-9
    # ... along it (the pose frame's axis rotated by the guess) the guess stays
    axis = torch.tensor([math.cos(poses[0, 2]), -math.sin(poses[0, 2])], dtype=F64)
    across = torch.stack((-axis[1], axis[0]))
    assert float((error[0, :2] @ across).abs()) < 1e-9
    assert abs(float(error[0, :2] @ axis) - float((guess - truth)[0, :2] @ axis)) < 1e-9
    # from identity it converges wrong by the motion along the axis
    wrong = from_identity.pose[0, :2] - truth[0, :2]
    assert abs(float(wrong @ axis) + float(truth[0, :2] @ axis)) < 1e-9
    # the reported sigma along the axis is the unobserved one
    variance = float(axis @ from_guess.covariance[0, :2, :2] @ axis)
    assert variance == pytest.approx(config.unobserved_sigma_m**2, rel=1e-6)


def test_covariance_is_the_sandwich():
    """Not degenerate: ``C = H^-1 G H^-1`` at the final kept matches."""
    poses = torch.tensor([[2.0, 2.0, 0.3], [2.2, 2.1, 0.36]], dtype=F64)
    ref_p, ref_v, cur_p, cur_v, _ = _pairs(_room(), poses, np.random.default_rng(3))
    config = PlicpConfig()
    result = plicp(ref_p, ref_v, cur_p, cur_v, torch.zeros(1, 3, dtype=F64), config)
    assert not bool(result.degenerate.any())
    lines = fit_lines(ref_p, ref_v, config)
    corr = correspondences(result.pose, cur_p, cur_v, lines, config)
    hessian = point_to_line_hessian(result.pose, cur_p, corr.normal, corr.keep.to(F64))
    gradient = point_to_line_gradient_covariance(result.pose, ref_p, lines, cur_p, corr, config)
    inverse = torch.linalg.inv(hessian[0])
    expected = inverse @ gradient[0] @ inverse
    torch.testing.assert_close(result.covariance[0], expected, rtol=1e-8, atol=1e-16)


@pytest.mark.parametrize(
    "segment_map, poses",
    [
        (_room(), [[2.0, 2.0, 0.3], [2.2, 2.1, 0.36]]),
        (warehouse_map(), [[19.2, 1.48, 0.0], [19.32, 1.484, 0.002]]),
    ],
)
def test_gradient_covariance_matches_autograd(segment_map, poses):
    """``G = M Sigma_z M^T`` with the analytic ``M`` (line fit perturbation included) equals
    the one with ``M = d g / d z`` by autograd through ``scan_points`` and ``fit_lines``
    (matches, kept set and line members fixed), on noise-free scans at the true pose, where
    the dropped second-order term (``e_i d J_i / d z``) vanishes."""
    spec = LidarSpec()
    poses = torch.tensor(poses, dtype=F64)
    ranges, _ = scan_at(segment_map, poses, spec)
    angles = spec.angles()
    config = PlicpConfig()
    truth = between(poses[:1], poses[1:])
    points, valid = scan_points(ranges, angles)
    lines = fit_lines(points[:1], valid[:1], config)
    corr = correspondences(truth, points[1:], valid[1:], lines, config)
    assert int(corr.count[0]) > 200
    analytic = point_to_line_gradient_covariance(truth, points[:1], lines, points[1:], corr,
                                                 config)  # fmt: skip
    z = torch.nan_to_num(ranges).requires_grad_(True)  # NaN -> 0, still no return
    pose = truth.clone().requires_grad_(True)
    points_z, _ = scan_points(z, angles)
    lines_z = fit_lines(points_z[:1], valid[:1], config)
    anchor = lines_z.anchor[0, corr.index[0]]
    normal = lines_z.normal[0, corr.index[0]]
    error = ((transform_points(pose, points_z[1:])[0] - anchor) * normal).sum(-1)
    cost = 0.5 * (corr.keep[0].to(F64) * error**2).sum()
    gradient = torch.autograd.grad(cost, pose, create_graph=True)[0][0]  # (3,)
    jac = torch.stack(
        [torch.autograd.grad(gradient[c], z, retain_graph=True)[0].flatten() for c in range(3)]
    )  # (3, 2K)
    sigma = config.range_sigma_m + config.range_sigma_rel * z.detach().flatten()
    expected = (jac * sigma**2) @ jac.T
    torch.testing.assert_close(analytic[0], expected, rtol=1e-9, atol=1e-18)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="initial"):
        plicp(torch.zeros(1, 5, 2), torch.ones(1, 5, dtype=torch.bool), torch.zeros(1, 5, 2),
              torch.ones(1, 5, dtype=torch.bool), torch.zeros(1, 2))  # fmt: skip
    with pytest.raises(ValueError, match="keep_fraction"):
        PlicpConfig(keep_fraction=0.0).validate()
    # points and validity of different lengths, ranges and angles of different beam
    # counts: the message names both shapes (the previous code failed inside a broadcast)
    with pytest.raises(ValueError, match=r"current_valid \(B, n\), got \(2, 6, 2\) and \(2, 5\)"):
        plicp(torch.zeros(2, 5, 2), torch.ones(2, 5, dtype=torch.bool), torch.zeros(2, 6, 2),
              torch.ones(2, 5, dtype=torch.bool), torch.zeros(2, 3))  # fmt: skip
    with pytest.raises(ValueError, match=r"got ranges \(3, 10\) and angles \(9,\)"):
        scan_points(torch.ones(3, 10), torch.linspace(0.0, 1.0, 9))
    with pytest.raises(ValueError, match=r"got ranges \(3, 10\) and angles \(9,\)"):
        scan_odometry(torch.arange(3.0), torch.ones(3, 10), torch.linspace(0.0, 1.0, 9))


def test_zero_ranges_are_no_return():
    """A beam that reports 0 m (a common encoding of "no return") adds no point: with a
    sector of 100 zero ranges in both scans the pose is exact, as with NaN there (the
    previous code put those beams at the sensor, where they formed a line that both scans
    matched: 0.15 m off here, reported converged)."""
    spec = LidarSpec()
    poses = torch.tensor([[3.0, 10.0, 1.5], [3.3, 10.2, 1.6]], dtype=F64)
    ranges, _ = scan_at(warehouse_map(), poses, spec)
    ranges[:, 100:200] = 0.0
    points, valid = scan_points(ranges, spec.angles())
    assert not bool(valid[:, 100:200].any())
    config = PlicpConfig(epsilon_xy_m=1e-12, epsilon_theta_rad=1e-12)
    guess = torch.zeros(1, 3, dtype=F64)
    result = plicp(points[:1], valid[:1], points[1:], valid[1:], guess, config)
    error = (result.pose - between(poses[:1], poses[1:])).abs().max()
    assert error < 1e-6, f"max error {error:.3g}"
