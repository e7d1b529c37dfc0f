"""The KITTI smoother cross-validation's training windows never touch the held-out window.

``benchmarks/kitti_smoother_cv.py`` picks the smoother's IMU noise on 60-s GNSS outages and
scores the main (middle-30 %) outage once with the pick; these checks compare its window
list with a brute-force construction on a synthetic 1-Hz fix clock with jitter.
"""

from __future__ import annotations

import numpy as np

from benchmarks.kitti_outage import EPS_S
from benchmarks.kitti_smoother_cv import (
    FRONTEND_GAPS,
    FRONTEND_GRID,
    FRONTEND_GYRO_NOISE,
    GRID,
    candidates,
    training_windows,
)


def _fix_times(count: int = 470, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 1000.0 + np.arange(count) + rng.uniform(-0.002, 0.002, count)


def test_training_windows_match_brute_force_and_avoid_the_held_out_fixes():
    times = _fix_times()
    held_out = (int(0.35 * times.size), int(0.35 * times.size) + round(0.3 * times.size))
    windows = training_windows(times, held_out)
    expected = []
    for i0 in range(5, times.size, 30):
        last = max(i for i in range(times.size) if times[i] <= times[i0] + 60.0 + EPS_S)
        i1 = last + 1
        if i1 >= times.size:
            break
        if not set(range(i0, i1)) & set(range(*held_out)):
            expected.append((i0, i1))
    assert [(w["i0"], w["i1"]) for w in windows] == expected
    assert len(windows) == 8
    for w in windows:
        span = times[w["i1"] - 1] - times[w["i0"]]
        assert 59.0 - 0.01 < span <= 60.0 + EPS_S  # 60 or 61 fixes, by the jitter
        assert w["i1"] <= held_out[0] or w["i0"] >= held_out[1]


def test_candidates_cover_the_grid_once_with_the_dataset_values_first():
    rows = candidates(GRID)
    sizes = [len(v) for v in GRID.values()]
    assert len(rows) == int(np.prod(sizes))
    assert len({tuple(sorted(r.items())) for r in rows}) == len(rows)
    assert rows[0] == {k: v[0] for k, v in GRID.items()}
    assert rows[0]["accel_bias_rw_density"] == 1.67e-4  # the metadata file's value


def test_frontend_grid_pairs_every_gyro_density_with_every_gap_handling():
    pairs = {
        (
            row["gyro_noise_density"],
            row.get("imu_gap_noise_scale"),
            row["imu_interpolated_min_samples"],
        )
        for row in FRONTEND_GRID
    }
    expected = {
        (gyro, gaps.get("imu_gap_noise_scale"), gaps["imu_interpolated_min_samples"])
        for gyro in FRONTEND_GYRO_NOISE
        for gaps in FRONTEND_GAPS
    }
    assert len(FRONTEND_GRID) == len(FRONTEND_GYRO_NOISE) * len(FRONTEND_GAPS) == 16
    assert pairs == expected
    assert 1.75e-4 in FRONTEND_GYRO_NOISE  # the metadata file's gyro white noise
    assert {1e2, 1e3, 1e4, None} == {gaps.get("imu_gap_noise_scale") for gaps in FRONTEND_GAPS}
