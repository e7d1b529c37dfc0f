"""Scan odometry: chaining and the pose source the ESKF consumes."""

from __future__ import annotations

import math

import torch

from msf_torch.geometry.se2 import between, compose
from msf_torch.lidar.odometry import ScanOdometry, pose_source, scan_odometry
from msf_torch.sim.lidar2d import LidarSpec, SegmentMap, scan_at

F64 = torch.float64


def _room() -> SegmentMap:
    segments = [
        [[0, 0], [12, 0]], [[12, 0], [12, 7]], [[12, 7], [0, 7]], [[0, 7], [0, 0]],
        [[4, 7], [4, 4.5]], [[7, 1], [8.5, 1]], [[8.5, 1], [8.5, 2.2]],
        [[8.5, 2.2], [7, 2.2]], [[7, 2.2], [7, 1]],
    ]  # fmt: skip
    return SegmentMap("room", torch.tensor(segments, dtype=F64), torch.zeros(2, 2, dtype=F64))


def test_chain_recovers_noise_free_poses():
    k = torch.arange(8, dtype=F64)
    truth = torch.stack((2.0 + 0.2 * k, 2.0 + 0.05 * k, 0.1 + 0.03 * k), -1)
    spec = LidarSpec()
    ranges, _ = scan_at(_room(), truth, spec)
    odometry = truth + torch.tensor([0.02, -0.01, 0.005], dtype=F64) * k[:, None]  # drifting
    from msf_torch.lidar.plicp import PlicpConfig

    config = PlicpConfig(epsilon_xy_m=1e-12, epsilon_theta_rad=1e-12)
    chain = scan_odometry(0.1 * k, ranges, spec.angles(), odometry, config, start=truth[0])
    assert not bool(chain.failed.any()) and not bool(chain.degenerate.any())
    torch.testing.assert_close(chain.pose, truth, rtol=0, atol=1e-6)


def test_pose_source_covariance_and_pairs():
    n = 5
    heading = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0], dtype=F64)
    relative = torch.stack(
        (torch.full((n - 1,), 0.1, dtype=F64), torch.zeros(n - 1, dtype=F64), heading.diff()), -1
    )
    pose = torch.zeros(n, 3, dtype=F64)
    for i in range(n - 1):
        pose[i + 1] = compose(pose[i], relative[i])
    cov = torch.diag(torch.tensor([4e-4, 1e-4, 1e-5], dtype=F64)).repeat(n - 1, 1, 1)
    cov[:, 0, 2] = cov[:, 2, 0] = 1e-5
    odo = ScanOdometry(
        t=0.1 * torch.arange(n, dtype=F64), pose=pose, relative=relative,
        relative_covariance=cov, iterations=torch.ones(n - 1, dtype=torch.long),
        converged=torch.ones(n - 1, dtype=torch.bool), failed=torch.zeros(n - 1, dtype=torch.bool),
        degenerate=torch.zeros(n - 1, dtype=torch.bool),
    )  # fmt: skip
    source = pose_source(odo, height_m=0.3)
    assert source.position.shape == (1, n, 3) and source.covariance.shape == (1, n, 6, 6)
    torch.testing.assert_close(source.position[0, :, 2], torch.full((n,), 0.3, dtype=F64))
    # yaw quaternion
    yaw = 2 * torch.atan2(source.quaternion[0, :, 3], source.quaternion[0, :, 0])
    torch.testing.assert_close(yaw, pose[:, 2])
    # sample k holds half of increment k-1 -> k, rotated to the world by the heading of k-1
    c, s = math.cos(float(pose[2, 2])), math.sin(float(pose[2, 2]))
    turn = torch.tensor([[c, -s], [s, c]], dtype=F64)
    expected = 0.5 * turn @ cov[2, :2, :2] @ turn.T
    torch.testing.assert_close(source.covariance[0, 3, :2, :2], expected)
    assert float(source.covariance[0, 3, 5, 5]) == 0.5e-5
    assert float(source.covariance[0, 3, 2, 2]) == 1e4  # height unobserved
    # the ESKF adds the two samples of a pair: equal increments give the increment's own
    # covariance back (world frame of the pair's first scan for position, yaw unchanged)
    pair = source.covariance[0, 2] + source.covariance[0, 3]
    c1, s1 = math.cos(float(pose[1, 2])), math.sin(float(pose[1, 2]))
    turn1 = torch.tensor([[c1, -s1], [s1, c1]], dtype=F64)
    mean = 0.5 * (turn1 @ cov[1, :2, :2] @ turn1.T + turn @ cov[2, :2, :2] @ turn.T)
    torch.testing.assert_close(pair[:2, :2], mean)
    torch.testing.assert_close(between(pose[:-1], pose[1:]), relative)
