"""Two factor properties the per-kind Jacobian checks did not reach.

* :class:`ReprojectionFactor` on ``se3`` poses (``T <- T exp([rho, phi])``, the chart of
  pose graphs): its analytic Jacobian against central finite differences on that chart.
* :class:`CalibratedWheelOdometryFactor` at the nominal track ``D = D_0``: its whitened
  residual is the plain wheel factor's, i.e. ``|W r|^2 = r^T Sigma^-1 r`` with the plain
  residual and covariance (a full 3x3 covariance, so row-only or column-only scaling of the
  yaw row shows).
"""

from __future__ import annotations

import torch

from msf_torch.backend import factors as F
from msf_torch.backend.preintegration import preintegrate_wheel
from msf_torch.backend.problem import Problem
from msf_torch.backend.variables import (
    POINT,
    SE3,
    WHEEL_CALIBRATION,
    pack_pose,
    unpack_pose,
)
from msf_torch.geometry import so3

DTYPE = torch.float64


def test_reprojection_jacobian_on_se3_poses_matches_finite_differences():
    gen = torch.Generator().manual_seed(11)
    count = 3
    position = 5.0 * torch.randn(2, count, 3, generator=gen, dtype=DTYPE)
    rotation = so3.exp(1.5 * torch.randn(2, count, 3, generator=gen, dtype=DTYPE))
    poses = pack_pose(position, rotation)
    rotation_cam = so3.exp(torch.tensor([-1.2, 0.1, -1.5], dtype=DTYPE))
    translation_cam = torch.tensor([0.1, -0.05, 0.02], dtype=DTYPE)
    pose_index = torch.tensor([0, 0, 1, 2, 2])
    p, r = unpack_pose(poses[:, pose_index])
    in_cam = torch.tensor(
        [
            [0.3, -0.2, 5.0],
            [-1.0, 0.5, 7.0],
            [0.2, 0.1, 4.0],
            [1.5, -0.5, 9.0],
            [0.0, 0.0, 6.0],
        ],
        dtype=DTYPE,
    )
    body = (rotation_cam @ in_cam[..., None]).squeeze(-1) + translation_cam
    world = p + (r @ body[..., None]).squeeze(-1)
    covariance = 1e-4 * torch.eye(2, dtype=DTYPE).expand(1, 5, 2, 2)
    factor = F.ReprojectionFactor(
        "pose",
        pose_index,
        "landmark",
        torch.arange(5),
        0.01 * torch.randn(1, 5, 2, generator=gen, dtype=DTYPE),
        covariance,
        rotation_cam,
        translation_cam,
        intrinsics=(450.0, 455.0, 320.0, 240.0),
    )
    problem = Problem({"pose": (SE3, poses), "landmark": (POINT, world)}, [factor])
    values = problem.gathered(factor, problem.values)
    kinds = factor.kinds
    assert kinds[0] is SE3
    _, jacobians = factor.residual_and_jacobians(values, kinds)
    step = 1e-6
    for slot, kind in enumerate(kinds):
        for dim in range(kind.tangent_dim):
            moved = []
            for sign in (1.0, -1.0):
                delta = torch.zeros(*values[slot].shape[:-1], kind.tangent_dim, dtype=DTYPE)
                delta[..., dim] = sign * step
                shifted = list(values)
                shifted[slot] = kind.retract(values[slot], delta)
                moved.append(factor.residual(shifted))
            numeric = (moved[0] - moved[1]) / (2 * step)
            torch.testing.assert_close(jacobians[slot][..., dim], numeric, rtol=1e-6, atol=1e-4)


def test_calibrated_wheel_factor_whitens_like_the_plain_factor_at_the_nominal_track():
    gen = torch.Generator().manual_seed(12)
    count, length, track = 4, 10, 0.55
    left = 3.0 + torch.rand(count, length, generator=gen, dtype=DTYPE)
    right = left + 0.6 * (torch.rand(count, length, generator=gen, dtype=DTYPE) - 0.5)
    dt = 0.04 * torch.ones(count, length, dtype=DTYPE)
    increment, _ = preintegrate_wheel(left, right, dt, track, 0.05)
    a = torch.randn(count, 3, 3, generator=gen, dtype=DTYPE)
    covariance = (0.01 * (a @ a.mT) + 0.001 * torch.eye(3, dtype=DTYPE))[None]
    position = 3.0 * torch.randn(1, count + 1, 3, generator=gen, dtype=DTYPE)
    rotation = so3.exp(0.3 * torch.randn(1, count + 1, 3, generator=gen, dtype=DTYPE))
    poses = pack_pose(position, rotation)
    arm = torch.tensor([-0.2, 0.05, -0.1], dtype=DTYPE)
    index = torch.arange(count)
    calibrated = F.CalibratedWheelOdometryFactor(
        "pose",
        index,
        index + 1,
        "calib",
        left[None],
        right[None],
        dt[None],
        covariance,
        track,
        arm,
    )
    plain = F.WheelOdometryFactor("pose", index, index + 1, increment[None], covariance, arm)
    calibration = torch.tensor([[[1.0, 1.0, track]]], dtype=DTYPE)
    problem = Problem(
        {"pose": ("pose", poses), "calib": (WHEEL_CALIBRATION, calibration)},
        [calibrated, plain],
    )
    (white_cal, _, loss_cal), (white_plain, _, loss_plain) = problem.whitened(
        problem.values, jacobians=False
    )
    residual = plain.residual(problem.gathered(plain, problem.values))
    expected = 0.5 * (residual[..., None, :] @ torch.linalg.solve(covariance, residual[..., None]))
    torch.testing.assert_close(loss_plain, expected[..., 0, 0], rtol=1e-10, atol=0)
    torch.testing.assert_close(loss_cal, expected[..., 0, 0], rtol=1e-10, atol=0)
    torch.testing.assert_close(white_cal, white_plain, rtol=1e-9, atol=1e-12)
