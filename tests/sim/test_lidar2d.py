"""2D LiDAR simulator: ray casting against a per-beam reference, the range-noise and dropout
model, routes and wheel odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from msf_torch.sim.lidar2d import (
    LidarSpec,
    corridor_map,
    follow_route,
    raycast,
    scan_at,
    simulate_lidar_run,
    warehouse_map,
    wheel_odometry,
)

F64 = torch.float64


def _reference_ranges(segments, pose, angles, max_range):
    """One beam, one segment at a time (plain Python)."""
    out = []
    for angle in angles.tolist():
        heading = pose[2] + angle
        d = (math.cos(heading), math.sin(heading))
        best = math.inf
        for (ax, ay), (bx, by) in segments.tolist():
            ex, ey = bx - ax, by - ay
            denom = d[0] * ey - d[1] * ex
            if abs(denom) < 1e-12:
                continue
            ox, oy = ax - pose[0], ay - pose[1]
            t = (ox * ey - oy * ex) / denom
            u = (ox * d[1] - oy * d[0]) / denom
            if t > 1e-9 and 0 <= u <= 1:
                best = min(best, t)
        out.append(best if best <= max_range else math.nan)
    return np.array(out)


def test_raycast_matches_per_beam_reference():
    wh = warehouse_map()
    spec = LidarSpec(resolution_deg=2.0)
    poses = torch.tensor([[3.0, 1.5, 0.2], [20.0, 5.7, 3.0], [37.0, 12.0, -1.4]], dtype=F64)
    ranges, cosine = raycast(wh.segments, poses, spec.angles(), spec.max_range_m)
    for k in range(3):
        expected = _reference_ranges(wh.segments, poses[k].tolist(), spec.angles(), 25.0)
        np.testing.assert_array_equal(np.isnan(ranges[k].numpy()), np.isnan(expected))
        np.testing.assert_allclose(ranges[k].numpy(), expected, rtol=0, atol=1e-12)
    assert bool((torch.isnan(cosine) == torch.isnan(ranges)).all())


def test_range_and_incidence_facing_a_wall():
    corridor = corridor_map(width_m=4.0)
    spec = LidarSpec(resolution_deg=5.0)
    pose = torch.tensor([[60.0, 0.0, math.pi / 2]], dtype=F64)  # facing the y = +2 wall
    ranges, cosine = raycast(corridor.segments, pose, spec.angles(), 25.0)
    angles = spec.angles()
    front = angles.abs() < math.radians(80)
    torch.testing.assert_close(ranges[0, front], 2.0 / torch.cos(angles[front]))
    torch.testing.assert_close(cosine[0, front], torch.cos(angles[front]))


def test_noise_and_dropout_statistics():
    corridor = corridor_map(width_m=4.0)
    spec = LidarSpec(range_sigma_m=0.02, range_sigma_rel=0.01, dropout_probability=0.1,
                     max_incidence_deg=90.0)  # fmt: skip
    poses = torch.tensor([[60.0, 0.0, math.pi / 2]], dtype=F64).expand(400, 3)
    measured, true = scan_at(corridor, poses, spec, np.random.default_rng(5))
    beam = spec.beams // 2  # straight at the wall, r = 2 m
    values = measured[:, beam]
    kept = torch.isfinite(values)
    assert float(kept.double().mean()) == pytest.approx(0.9, abs=0.04)
    error = values[kept] - true[0, beam]
    assert float(error.mean()) == pytest.approx(0.0, abs=0.01)  # 4.7 standard errors
    assert float(error.std()) == pytest.approx(0.02 + 0.01 * 2.0, rel=0.1)
    # beams beyond the corridor's ends and range: no return
    along = torch.tensor([[60.0, 0.0, 0.0]], dtype=F64)
    ahead, _ = scan_at(corridor, along, LidarSpec())
    assert math.isnan(float(ahead[0, LidarSpec().beams // 2]))


def test_incidence_limit_drops_grazing_beams():
    corridor = corridor_map()
    spec = LidarSpec(max_incidence_deg=60.0)
    pose = torch.tensor([[60.0, 0.0, 0.0]], dtype=F64)
    measured, true = scan_at(corridor, pose, spec)
    _, cosine = raycast(corridor.segments, pose, spec.angles(), spec.max_range_m)
    expect = torch.isfinite(true) & (cosine >= math.cos(math.radians(60)))
    assert bool((torch.isfinite(measured) == expect).all())
    assert int(expect.sum()) < int(torch.isfinite(true).sum())


def test_route_following_and_ideal_odometry():
    wh = warehouse_map()
    trajectory = follow_route(wh.route[:4], speed_mps=1.0, rate_hz=50.0)
    # stays in the aisles: never inside a rack row's depth band
    y = trajectory.pose[:, 1]
    for row in range(5):
        y0 = 3.0 + row * 4.2
        inside_band = (y > y0) & (y < y0 + 1.2)
        x = trajectory.pose[:, 0]
        assert not bool((inside_band & (x > 6.0) & (x < 34.0)).any())
    assert float(trajectory.speed.max()) <= 1.0 + 1e-12
    # perfect wheels reproduce the truth (both integrate the same exact arcs)
    ideal, _ = wheel_odometry(
        trajectory, np.random.default_rng(0), scale_sigma=0.0, track_scale_sigma=0.0,
        speed_noise_mps=0.0,
    )  # fmt: skip
    torch.testing.assert_close(ideal, trajectory.pose, rtol=0, atol=1e-9)


def test_simulated_run_shapes_and_truth():
    run = simulate_lidar_run(corridor_map(), seed=3, duration_s=4.0)
    assert run.ranges.shape == (41, 541) and run.truth.shape == (41, 3)
    torch.testing.assert_close(run.t[1:] - run.t[:-1], torch.full((40,), 0.1, dtype=F64))
    assert float(run.truth[:, 1].abs().max()) < 1.2  # inside the corridor
    torch.testing.assert_close(run.odometry[0], run.truth[0])


def test_spec_validation_names_the_field():
    with pytest.raises(ValueError, match="dropout_probability"):
        LidarSpec(dropout_probability=1.0).validate()
    with pytest.raises(ValueError, match="max_incidence_deg"):
        LidarSpec(max_incidence_deg=0.0).validate()
