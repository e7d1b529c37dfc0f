"""PLICP's reported covariance against a Monte Carlo of the simulator: one scan pair, many
draws of the range noise (``N(0, (1 cm + 0.1 % r)^2)``, both scans) and of the dropouts.

The reference is the spread of the estimates around the true relative pose, not the
covariance formula. Tolerances: the mean NEES ``e^T C^-1 e`` over the draws (each with its
own reported ``C``) within [2, 4.5] (3 expected), and each axis' sample variance within
0.5-2 times the mean reported variance. ``sigma^2 H^-1`` (the previous covariance: one
scan's noise, sigma from the trimmed residuals) gives a mean NEES of 22-25 on these pairs
(x variance 14 times the reported one) and is checked to fail the same tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.geometry.se2 import between, wrap_angle
from msf_torch.lidar.plicp import (
    PlicpConfig,
    correspondences,
    fit_lines,
    plicp,
    point_to_line_hessian,
    scan_points,
)
from msf_torch.sim.lidar2d import LidarSpec, corridor_map, scan_at, warehouse_map

F64 = torch.float64
DRAWS = 150
CHUNK = 50


def _nees(error: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """(D,) ``e^T C^-1 e`` of errors (D, 3) and covariances (D, 3, 3)."""
    return (error[:, None] @ torch.linalg.solve(covariance, error[..., None]))[:, 0, 0]


@pytest.mark.parametrize(
    "segment_map, poses",
    [
        # along a warehouse aisle (racks, pallet faces, the far aisle end)
        (warehouse_map(), [[19.2, 1.48, 0.0], [19.32, 1.484, 0.002]]),
        # 10 m before a corridor's end wall (the axis seen only through it)
        (corridor_map(), [[110.0, 0.0, 0.05], [110.11, 0.01, 0.06]]),
    ],
)
def test_covariance_matches_monte_carlo(segment_map, poses):
    spec = LidarSpec()
    pair = torch.tensor(poses, dtype=F64)
    ranges, _ = scan_at(segment_map, pair.repeat(DRAWS, 1), spec, np.random.default_rng(5))
    points, valid = scan_points(ranges, spec.angles())
    ref_p, ref_v, cur_p, cur_v = points[0::2], valid[0::2], points[1::2], valid[1::2]
    truth = between(pair[:1], pair[1:]).expand(DRAWS, -1)
    guess = truth + torch.tensor([0.004, -0.002, 0.003], dtype=F64)  # wheel-odometry-like
    config = PlicpConfig()
    pose, covariance, old = [], [], []
    for rows in torch.arange(DRAWS).split(CHUNK):
        result = plicp(ref_p[rows], ref_v[rows], cur_p[rows], cur_v[rows], guess[rows], config)
        assert not bool(result.degenerate.any() | result.failed.any())
        pose.append(result.pose)
        covariance.append(result.covariance)
        # sigma^2 H^-1 at the same final matches
        lines = fit_lines(ref_p[rows], ref_v[rows], config)
        corr = correspondences(result.pose, cur_p[rows], cur_v[rows], lines, config)
        hessian = point_to_line_hessian(result.pose, cur_p[rows], corr.normal, corr.keep.to(F64))
        variance = (corr.residual**2).sum(-1) / (corr.count - 3)
        old.append(variance[:, None, None] * torch.linalg.inv(hessian))
    pose, covariance, old = torch.cat(pose), torch.cat(covariance), torch.cat(old)
    error = torch.cat((pose[:, :2] - truth[:, :2], wrap_angle(pose[:, 2:] - truth[:, 2:])), -1)
    nees = float(_nees(error, covariance).mean())
    assert 2.0 <= nees <= 4.5, f"mean NEES {nees:.2f}"
    ratio = torch.cov(error.T).diagonal() / covariance.mean(0).diagonal()
    assert bool(((ratio > 0.5) & (ratio < 2.0)).all()), f"sample / reported variance {ratio}"
    # the tolerance rejects the previous, one-scan covariance
    old_nees = float(_nees(error, old).mean())
    assert old_nees > 4.5, f"sigma^2 H^-1: mean NEES {old_nees:.2f}"
