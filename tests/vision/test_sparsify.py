"""Map sparsification: the programme's terms against hand computation, and the greedy, the
LP relaxation and the MILP against brute force over every subset of tiny instances."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from msf_torch.vision.sparsify import (
    SparsifyConfig,
    sparsification_problem,
    sparsify_exact,
    sparsify_greedy,
    sparsify_relaxation,
    vo_sparsification_problem,
)


def test_terms_match_hand_computation():
    # keyframe 0 sees points 0, 1, 2; keyframe 1 sees points 1, 2
    points = [np.array([0, 1, 2]), np.array([1, 2])]
    pixels = [np.array([[0.0, 0.0], [10.0, 0.0], [200.0, 0.0]]), np.array([[5.0, 5.0], [5.0, 9.0]])]
    config = SparsifyConfig(
        min_points=2, neighbourhood_px=10.0, pair_weight=2.0, track_discount=0.5
    )
    problem = sparsification_problem(points, pixels, 3, config)
    np.testing.assert_array_equal(problem.coverage.toarray(), [[1, 1, 1], [0, 1, 1]])
    np.testing.assert_array_equal(problem.required, [2, 2])
    np.testing.assert_allclose(problem.linear, [1 - 0.5 * 1 / 2, 0.5, 0.5])
    q01 = 2.0 * math.exp(-100.0 / 200.0)
    q12 = 2.0 * math.exp(-16.0 / 200.0)  # 190 px apart in keyframe 0: beyond the cutoff
    expected = np.array([[0.0, q01, 0.0], [q01, 0.0, q12], [0.0, q12, 0.0]])
    np.testing.assert_allclose(problem.quadratic.toarray(), expected)
    keep = np.array([True, True, True])
    assert problem.cost(keep) == pytest.approx(q01 + q12 + 0.75 + 0.5 + 0.5)
    assert problem.feasible(keep) and not problem.feasible(np.array([True, True, False]))


def _random_instance(seed: int, points: int = 14, keyframes: int = 5, b: int = 3):
    rng = np.random.default_rng(seed)
    seen, pixels = [], []
    for _ in range(keyframes):
        chosen = np.sort(
            rng.choice(points, int(rng.integers(b + 1, points // 2 + 3)), replace=False)
        )
        seen.append(chosen)
        pixels.append(rng.uniform(0, 120, (len(chosen), 2)))
    config = SparsifyConfig(min_points=b, neighbourhood_px=25.0, pair_weight=0.8)
    return sparsification_problem(seen, pixels, points, config)


def _brute_force(problem) -> float:
    n = problem.num_points
    best = math.inf
    for bits in itertools.product((False, True), repeat=n):
        keep = np.array(bits)
        if problem.feasible(keep):
            best = min(best, problem.cost(keep))
    return best


@pytest.mark.parametrize("seed", range(6))
def test_solvers_against_brute_force(seed: int):
    problem = _random_instance(seed)
    optimum = _brute_force(problem)
    exact = sparsify_exact(problem, time_limit_s=20.0)
    assert problem.feasible(exact.keep)
    assert exact.cost == pytest.approx(optimum, abs=1e-6)
    # cost / optimum, measured over seeds 0-39: greedy mean 1.05, worst 1.22; relaxation
    # mean 1.06, worst 1.45 (seeds 0-5: worst 1.14 and 1.31)
    greedy, relaxation = sparsify_greedy(problem), sparsify_relaxation(problem)
    for result, worst in ((greedy, 1.25), (relaxation, 1.5)):
        assert problem.feasible(result.keep)
        assert result.cost >= optimum - 1e-9
        assert result.cost <= worst * optimum, (result.method, result.cost, optimum)
    assert relaxation.lower_bound <= optimum + 1e-9


def test_drop_pass_leaves_no_removable_point():
    problem = _random_instance(11, points=40, keyframes=8, b=4)
    result = sparsify_greedy(problem)
    counts = problem.coverage @ result.keep.astype(float)
    for point in np.nonzero(result.keep)[0]:
        frames = problem.coverage[:, point].toarray().reshape(-1) > 0
        assert np.any(counts[frames] - 1 < problem.required[frames])


def test_keyframes_with_fewer_points_than_b_keep_all():
    points = [np.array([0, 1]), np.array([1, 2, 3, 4])]
    pixels = [np.zeros((2, 2)), np.array([[0, 0], [50, 0], [100, 0], [150, 0]], float)]
    problem = sparsification_problem(points, pixels, 5, SparsifyConfig(min_points=3))
    result = sparsify_greedy(problem)
    assert result.keep[[0, 1]].all() and result.keep.sum() == 4


def test_empty_maps_give_empty_selections():
    """A map without points (a run that never triangulated) or without keyframes: every
    solver keeps nothing at cost 0 (the previous code failed in numpy reductions and
    concatenations with messages that named neither)."""
    no_points = sparsification_problem([np.zeros(0, np.int64)], [np.zeros((0, 2))], 0)
    no_keyframes = sparsification_problem([], [], 5)
    assert no_keyframes.coverage.shape == (0, 5) and no_keyframes.linear.tolist() == [1.0] * 5
    for problem in (no_points, no_keyframes):
        for solver in (sparsify_greedy, sparsify_relaxation, sparsify_exact):
            result = solver(problem)
            assert result.keep.shape == (problem.num_points,) and not result.keep.any()
            assert result.cost == 0.0


def test_odometry_map_programme_and_greedy_cover(odometry):
    """The programme over a rendered run's map: A's rows are the keyframes' features that
    have map points (looked up by track id one at a time), and the greedy's selection meets
    every keyframe's budget with fewer points than the map."""
    problem = vo_sparsification_problem(odometry, SparsifyConfig(min_points=20))
    ids = odometry.landmark_ids.tolist()
    for k, keyframe in enumerate(odometry.keyframes):
        expected = sorted(ids.index(i) for i in keyframe.feature_ids[keyframe.landmark])
        np.testing.assert_array_equal(problem.coverage[k].indices, expected)
    result = sparsify_greedy(problem)
    assert problem.feasible(result.keep)
    assert 20 <= result.keep.sum() < problem.num_points
    assert result.cost < problem.cost(np.ones(problem.num_points, bool))
