"""Scan odometry: PLICP between consecutive scans, chained, and handed to the ESKF as a named
pose source.

:func:`scan_odometry` matches scan ``k + 1`` to scan ``k`` for every ``k`` (batched in
chunks), each from the wheel-odometry increment ``odometry_k^-1 (+) odometry_k+1`` when
wheel odometry is given (identity otherwise), and chains the increments from ``start``. A pair
whose match failed (too few correspondences) keeps its initial guess with covariance
``diag(failed_sigma)^2``.

:func:`pose_source` turns the chain into :class:`~msf_torch.types.PoseMeasurements` for
``Sequence.pose_sources`` (e.g. under ``"lidar"``). The ESKF fuses a pose source as odometry:
for consecutive samples it adds their declared position covariances (world) and their
rotation covariances (body). Sample ``k`` therefore declares half of the covariance of the
increment that ends at it (the first sample half of the first increment's), rotated to the
world by the heading of the scan the increment starts from; a pair's sum is then the mean
of two neighbouring increments' covariances. A 2D scanner says nothing about height, roll
and pitch: those get ``unobserved_sigma`` (m and rad).

Example:
    >>> from msf_torch.lidar.odometry import pose_source, scan_odometry
    >>> from msf_torch.sim.lidar2d import corridor_map, simulate_lidar_run
    >>> run = simulate_lidar_run(corridor_map(), seed=0, duration_s=3.0)
    >>> odo = scan_odometry(run.t, run.ranges, run.angles, run.odometry, start=run.truth[0])
    >>> pose_source(odo).position.shape
    torch.Size([1, 31, 3])
"""

from __future__ import annotations

__all__ = ["ScanOdometry", "scan_odometry", "pose_source"]

from dataclasses import dataclass

import torch

from msf_torch.geometry.se2 import between, compose
from msf_torch.lidar.plicp import PlicpConfig, plicp, scan_points
from msf_torch.types import PoseMeasurements


@dataclass
class ScanOdometry:
    """Chained scan-to-scan PLICP.

    Attributes:
        t: (N,) scan times, s.
        pose: (N, 3) ``[x, y, yaw]`` of each scan, chained from ``start``, m and rad.
        relative: (N - 1, 3) pose of scan ``k + 1`` in scan ``k``'s frame.
        relative_covariance: (N - 1, 3, 3) its covariance (m^2, m rad, rad^2).
        iterations: (N - 1,) PLICP iterations.
        converged: (N - 1,) bool.
        failed: (N - 1,) bool (initial guess kept).
        degenerate: (N - 1,) bool (some direction unobserved; the guess kept there).
    """

    t: torch.Tensor
    pose: torch.Tensor
    relative: torch.Tensor
    relative_covariance: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    failed: torch.Tensor
    degenerate: torch.Tensor


def scan_odometry(
    t: torch.Tensor,
    ranges: torch.Tensor,
    angles: torch.Tensor,
    odometry: torch.Tensor | None = None,
    config: PlicpConfig | None = None,
    start: torch.Tensor | None = None,
    chunk: int = 64,
    failed_sigma: tuple[float, float, float] = (1.0, 1.0, 0.5),
) -> ScanOdometry:
    """PLICP between consecutive scans, chained (see the module docstring).

    Args:
        t: (N,) scan times, s.
        ranges: (N, K) ranges, m (NaN, inf or <= 0 = no return).
        angles: (K,) beam angles, rad.
        odometry: (N, 3) wheel-odometry poses at the scan times (initial guesses), or None
            for identity guesses.
        config: PLICP settings.
        start: (3,) pose of the first scan (default zeros).
        chunk: scan pairs per PLICP batch.
        failed_sigma: 1-sigma ``(x m, y m, yaw rad)`` of a failed pair's guess.
    """
    n = ranges.shape[0]
    if n < 2 or t.shape != (n,):
        raise ValueError(
            f"scan_odometry: need N >= 2 scans with times (N,), got ranges "
            f"{tuple(ranges.shape)} and t {tuple(t.shape)}"
        )
    if odometry is not None and odometry.shape != (n, 3):
        raise ValueError(f"scan_odometry: odometry must be ({n}, 3), got {tuple(odometry.shape)}")
    points, valid = scan_points(ranges, angles)
    if odometry is None:
        guess = torch.zeros(n - 1, 3, dtype=ranges.dtype, device=ranges.device)
    else:
        guess = between(odometry[:-1], odometry[1:])
    parts = []
    for index in torch.arange(n - 1, device=ranges.device).split(chunk):
        parts.append(
            plicp(
                points[index],
                valid[index],
                points[index + 1],
                valid[index + 1],
                guess[index],
                config,
            )
        )
    relative = torch.cat([p.pose for p in parts])
    covariance = torch.cat([p.covariance for p in parts])
    failed = torch.cat([p.failed for p in parts])
    sigma = torch.tensor(failed_sigma, dtype=ranges.dtype, device=ranges.device)
    relative = torch.where(failed[:, None], guess, relative)
    covariance = torch.where(failed[:, None, None], torch.diag(sigma**2), covariance)
    pose = torch.zeros(n, 3, dtype=ranges.dtype, device=ranges.device)
    pose[0] = start if start is not None else 0.0
    for k in range(n - 1):  # the chain is sequential by nature
        pose[k + 1] = compose(pose[k], relative[k])
    return ScanOdometry(
        t=t,
        pose=pose,
        relative=relative,
        relative_covariance=covariance,
        iterations=torch.cat([p.iterations for p in parts]),
        converged=torch.cat([p.converged for p in parts]),
        failed=failed,
        degenerate=torch.cat([p.degenerate for p in parts]),
    )


def pose_source(
    odometry: ScanOdometry, height_m: float = 0.0, unobserved_sigma: float = 100.0
) -> PoseMeasurements:
    """A B = 1 pose source from chained scan odometry (see the module docstring).

    Args:
        odometry: the chain.
        height_m: the constant z of the poses, m.
        unobserved_sigma: 1-sigma of z (m), roll and pitch (rad).

    Returns:
        PoseMeasurements (1, N, ...): positions ``[x, y, height_m]``, yaw quaternions,
        covariances over ``[dp (world), dtheta (body)]``.
    """
    pose = odometry.pose
    n = pose.shape[0]
    f64 = dict(dtype=pose.dtype, device=pose.device)
    half = 0.5 * odometry.relative_covariance  # (N - 1, 3, 3)
    per_sample = torch.cat((half[:1], half))  # sample k <- increment ending at k
    heading = torch.cat((pose[:1, 2], pose[:-1, 2]))  # frame each increment is expressed in
    c, s = torch.cos(heading), torch.sin(heading)
    turn = torch.zeros(n, 3, 3, **f64)
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1] = c, -s, s, c
    turn[:, 2, 2] = 1.0  # yaw is the same in both frames
    planar = turn @ per_sample @ turn.mT  # [x, y (world), yaw]
    cov = torch.diag(torch.full((6,), unobserved_sigma**2, **f64)).repeat(n, 1, 1)
    rows = torch.tensor([0, 1, 5], device=pose.device)  # dp_x, dp_y, dtheta_z
    cov[:, rows[:, None], rows[None, :]] = planar
    position = torch.stack((pose[:, 0], pose[:, 1], torch.full_like(pose[:, 0], height_m)), -1)
    zero = torch.zeros_like(pose[:, 2])
    quaternion = torch.stack(
        (torch.cos(0.5 * pose[:, 2]), zero, zero, torch.sin(0.5 * pose[:, 2])), -1
    )
    return PoseMeasurements(
        t=odometry.t[None],
        position=position[None],
        quaternion=quaternion[None],
        covariance=cov[None],
        mask=torch.ones(1, n, dtype=torch.bool, device=pose.device),
    )
