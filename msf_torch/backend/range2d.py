"""Planar odometry + range-beacon smoothing: wheel odometry between SE(2) poses, ranges from
the robot to beacons at known (or unknown) positions, a prior on the first pose; the whole
run solved at once by :func:`~msf_torch.backend.lm.solve` (UWB anchors, radio tags).

Variables: ``pose`` (:data:`~msf_torch.backend.posegraph2d.SE2`, (1, M + 1, 3)) and
``beacon`` (:data:`POINT2`, (1, L, 2) m; held fixed when the positions are known).
Factors, each GTSAM's counterpart so that costs agree with it:

* odometry (:class:`~msf_torch.backend.posegraph2d.Se2BetweenFactor`): step k measures
  the relative pose ``Z_k = Pose2(dx_k, dy_k, dheading_k)`` between poses k and k + 1
  (``BetweenFactor<Pose2>``), covariance per step from :class:`OdometryNoise`;
* range (:class:`Se2RangeFactor`, ``RangeFactor2D``): ``r = |b - p| - z`` (m) between a
  pose and a beacon, sigma ``range_sigma_m`` under a robust kernel (outlier ranges are
  common: multipath, a missed first path);
* prior (:class:`Se2PriorFactor`, ``PriorFactorPose2``): ``r = Log(P^-1 T_0)`` on the first
  pose.

Jacobians of the range: the pose moves by ``T Exp(xi)``, so to first order
``p <- p + R(theta) rho``, and with ``u = (b - p) / |b - p|``:
``dr/dxi = [-u^T R(theta), 0]``, ``dr/db = u^T``.
"""

from __future__ import annotations

__all__ = [
    "POINT2",
    "OdometryNoise",
    "Point2Kind",
    "Se2InterpolatedRangeFactor",
    "Se2PriorFactor",
    "Se2RangeFactor",
    "multilaterate",
    "odometry_range_problem",
]

import math
from dataclasses import dataclass

import torch

from msf_torch.backend.factors import _Evaluated, _Unary, sqrt_information
from msf_torch.backend.posegraph2d import (
    POINT2,
    SE2,
    Point2Kind,
    Se2BetweenFactor,
    se2_between_residual,
)
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.robust import RobustKernel
from msf_torch.geometry.se2 import chain


def _range_error(
    position: torch.Tensor, beacon: torch.Tensor, ranges: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Range residual ``|b - p| - z`` (..., 1) m of positions and beacons (..., 2) against
    ``ranges`` (broadcast to (...)), and the unit direction ``u = (b - p) / |b - p|`` (..., 2)."""
    offset = beacon - position
    distance = offset.norm(dim=-1)
    residual = (distance - ranges.expand_as(distance))[..., None]
    unit = offset / distance.clamp_min(torch.finfo(offset.dtype).tiny)[..., None]
    return residual, unit


def _range_pose_row(unit: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """``dr/dxi = [-u^T R(theta), 0]`` (..., 1, 3): a range's Jacobian w.r.t. the tangent
    step of the :data:`SE2` pose (..., 3) whose position it is measured from."""
    c, s = torch.cos(pose[..., 2]), torch.sin(pose[..., 2])
    along = -(unit[..., 0] * c + unit[..., 1] * s)  # -u^T R(theta) e_x
    across = -(-unit[..., 0] * s + unit[..., 1] * c)  # -u^T R(theta) e_y
    return torch.stack((along, across, torch.zeros_like(along)), -1)[..., None, :]


class Se2RangeFactor(_Evaluated, Factor):
    """Range from an :data:`~msf_torch.backend.posegraph2d.SE2` pose's origin to a
    :data:`POINT2` beacon: ``r = |b - p| - z`` (m) (GTSAM's ``RangeFactor2D``).

    Args:
        pose_group, pose_index: the poses (F,). beacon_group, beacon_index: the beacons (F,).
        ranges: (B|1, F) measured ranges, m. variance: (B|1, F, 1, 1) m^2.
        kernel: robust kernel, or None for plain least squares.
    """

    batched = ("ranges",)

    def __init__(
        self,
        pose_group: str,
        pose_index: torch.Tensor,
        beacon_group: str,
        beacon_index: torch.Tensor,
        ranges: torch.Tensor,
        variance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        self.slots = ((pose_group, pose_index.long()), (beacon_group, beacon_index.long()))
        self.sqrt_information = sqrt_information(variance)
        self.kernel = kernel
        self.ranges = ranges

    def _evaluate(self, values, jacobians: bool):
        pose, beacon = values
        residual, unit = _range_error(pose[..., 0:2], beacon, self.ranges)
        if not jacobians:
            return residual, None
        return residual, [_range_pose_row(unit, pose), unit[..., None, :]]


class Se2InterpolatedRangeFactor(_Evaluated, Factor):
    """Range from the position between two :data:`~msf_torch.backend.posegraph2d.SE2`
    poses at the range's time to a :data:`POINT2` beacon: with ``a`` the fraction of the
    way from pose i to pose j, ``p = (1 - a) p_i + a p_j`` and ``r = |b - p| - z`` (m). A
    range taken between two odometry poses then counts where the robot was (at 3.6 m/s and
    10 Hz odometry, attaching it to the next pose moves it by 0.18 m on average). ``a = 1``
    is :class:`Se2RangeFactor` on pose j.

    Jacobians: with ``u = (b - p) / |b - p|``, ``dr/dxi_i = (1 - a) [-u^T R(theta_i), 0]``,
    ``dr/dxi_j = a [-u^T R(theta_j), 0]``, ``dr/db = u^T``.

    Args:
        pose_group, before, after: the poses i and j around each range (F,).
        fraction: (B|1, F) ``a`` in [0, 1]. beacon_group, beacon_index: the beacons (F,).
        ranges: (B|1, F) m. variance: (B|1, F, 1, 1) m^2. kernel: robust kernel, or None.
    """

    batched = ("fraction", "ranges")

    def __init__(
        self,
        pose_group: str,
        before: torch.Tensor,
        after: torch.Tensor,
        fraction: torch.Tensor,
        beacon_group: str,
        beacon_index: torch.Tensor,
        ranges: torch.Tensor,
        variance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        self.slots = (
            (pose_group, before.long()),
            (pose_group, after.long()),
            (beacon_group, beacon_index.long()),
        )
        self.sqrt_information = sqrt_information(variance)
        self.kernel = kernel
        self.fraction, self.ranges = fraction, ranges

    def _evaluate(self, values, jacobians: bool):
        pose_i, pose_j, beacon = values
        fraction = self.fraction.expand(pose_i.shape[:-1])[..., None]
        position = (1.0 - fraction) * pose_i[..., 0:2] + fraction * pose_j[..., 0:2]
        residual, unit = _range_error(position, beacon, self.ranges)
        if not jacobians:
            return residual, None
        weight = fraction[..., None]
        return residual, [
            (1.0 - weight) * _range_pose_row(unit, pose_i),
            weight * _range_pose_row(unit, pose_j),
            unit[..., None, :],
        ]


class Se2PriorFactor(_Evaluated, _Unary):
    """Prior on an :data:`~msf_torch.backend.posegraph2d.SE2` pose: ``r = Log(P^-1 T)``
    (3,) (GTSAM's ``PriorFactorPose2``).

    Args:
        group, index: the poses (F,). prior: (B|1, F, 3) ``[x, y, theta]``.
        covariance: (B|1, F, 3, 3). kernel: robust kernel, or None.
    """

    batched = ("prior",)

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        prior: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.prior = prior

    def _evaluate(self, values, jacobians: bool):
        pose = values[0]
        prior = self.prior.expand_as(pose)
        residual, _, jac = se2_between_residual(
            torch.zeros_like(pose), pose, prior[..., 0:2], prior[..., 2], jacobians
        )
        return residual, [jac] if jacobians else None


@dataclass(frozen=True)
class OdometryNoise:
    """Covariance of one odometry step, growing with the distance it covers: ``diag(
    forward * d + floor_m^2, lateral * d + floor_m^2, heading * d + floor_rad^2)`` for a step
    of ``d`` m (a random walk per metre travelled).

    Attributes:
        forward, lateral: m^2 per m travelled. heading: rad^2 per m travelled.
        floor_m, floor_rad: the sigma of a step that does not move, m and rad.
    """

    forward: float = 6e-4
    lateral: float = 6e-4
    heading: float = 5e-5
    floor_m: float = 1e-3
    floor_rad: float = 1e-3

    def covariance(self, distance: torch.Tensor) -> torch.Tensor:
        """(M, 3, 3) covariances of steps of ``distance`` (M,) m."""
        d = distance.abs()
        diagonal = torch.stack(
            (
                self.forward * d + self.floor_m**2,
                self.lateral * d + self.floor_m**2,
                self.heading * d + self.floor_rad**2,
            ),
            -1,
        )
        return torch.diag_embed(diagonal)


def odometry_range_problem(
    odometry: torch.Tensor,
    range_pose: torch.Tensor,
    range_beacon: torch.Tensor,
    ranges: torch.Tensor,
    beacons: torch.Tensor,
    first_pose: torch.Tensor,
    first_pose_covariance: torch.Tensor,
    odometry_noise: OdometryNoise | None = None,
    range_sigma_m: float = 1.0,
    range_kernel: RobustKernel | None = None,
    beacons_known: bool = True,
    initial_poses: torch.Tensor | None = None,
    range_fraction: torch.Tensor | None = None,
) -> Problem:
    """The B = 1 smoothing problem of a planar run with odometry and beacon ranges.

    Args:
        odometry: (M, 3) ``[dx, dy, dheading]`` (m, m, rad) of each step: pose k + 1 in
            pose k's frame (a unicycle's step of ``d`` m then a turn: ``[d, 0, turn]``).
        range_pose: (K,) int64 pose (0..M) each range was taken at.
        range_beacon: (K,) int64 row of ``beacons`` each range is to.
        ranges: (K,) m (any known bias already removed).
        beacons: (L, 2) m, beacon positions (the initial guess when not known).
        first_pose: (3,) prior mean of pose 0 ``[x, y, theta]``.
        first_pose_covariance: (3, 3).
        odometry_noise: per-step covariance model (default :class:`OdometryNoise`).
        range_sigma_m: sigma of a range, m.
        range_kernel: robust kernel on the ranges (scale in sigmas), or None.
        beacons_known: hold the beacons fixed (localisation) or solve for them too.
        initial_poses: (M + 1, 3) initial estimate; default the odometry chained from
            ``first_pose``.
        range_fraction: (K,) where each range lies between pose ``range_pose - 1`` (0) and
            ``range_pose`` (1) (:meth:`~msf_torch.io.ranges.RangeRun.range_pose_fraction`):
            the range counts at the interpolated position
            (:class:`Se2InterpolatedRangeFactor`); None: at pose ``range_pose``
            (:class:`Se2RangeFactor`, GTSAM's ``RangeFactor2D`` graph).

    Returns:
        a :class:`~msf_torch.backend.problem.Problem` with groups ``pose`` and ``beacon``.

    Raises:
        ValueError: inconsistent shapes, indices that are not integers or out of range, a
            value that is not finite, a first-pose covariance that is not positive definite
            or a range sigma that is not positive (each named).
    """
    dtype, device = odometry.dtype, odometry.device
    steps = odometry.shape[0]
    if odometry.ndim != 2 or odometry.shape[1] != 3:
        raise ValueError(
            f"odometry must be (M, 3) relative poses [dx, dy, dheading], got "
            f"{tuple(odometry.shape)}"
        )
    if ranges.ndim != 1:
        raise ValueError(f"ranges must be (K,), got {tuple(ranges.shape)}")
    k = ranges.shape[0]
    for name, tensor in (("range_pose", range_pose), ("range_beacon", range_beacon)):
        if tensor.shape != (k,):
            raise ValueError(f"{name} must be ({k},) like ranges, got {tuple(tensor.shape)}")
        if tensor.is_floating_point() or tensor.is_complex() or tensor.dtype == torch.bool:
            raise ValueError(f"{name} must hold integer indices, got {tensor.dtype}")
    shapes = {  # name -> (tensor, wanted shape, its description)
        "beacons": (beacons, (beacons.shape[0], 2), "(L, 2)"),
        "first_pose": (first_pose, (3,), "(3,)"),
        "first_pose_covariance": (first_pose_covariance, (3, 3), "(3, 3)"),
    }
    if initial_poses is not None:
        shapes["initial_poses"] = (initial_poses, (steps + 1, 3), f"({steps + 1}, 3)")
    for name, (tensor, shape, shown) in shapes.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must be {shown}, got {tuple(tensor.shape)}")
    inputs = {"odometry": odometry, "ranges": ranges, **{n: t[0] for n, t in shapes.items()}}
    for name, tensor in inputs.items():
        bad = torch.nonzero(~torch.isfinite(tensor))
        if bad.numel():
            where = ", ".join(str(int(i)) for i in bad[0])
            raise ValueError(f"{name}[{where}] is not finite ({float(tensor[tuple(bad[0])])})")
    ranges, first_pose, first_pose_covariance = (
        x.to(dtype=dtype, device=device) for x in (ranges, first_pose, first_pose_covariance)
    )
    if int(torch.linalg.cholesky_ex(first_pose_covariance).info):
        raise ValueError(
            "first_pose_covariance must be a positive definite (3, 3) covariance "
            f"(m^2, rad^2; not sigmas), got {first_pose_covariance.tolist()}"
        )
    if not math.isfinite(range_sigma_m) or range_sigma_m <= 0:
        raise ValueError(f"range_sigma_m must be a positive number of metres, got {range_sigma_m}")
    if k and (int(range_pose.min()) < 0 or int(range_pose.max()) > steps):
        raise ValueError(f"range_pose must index the {steps + 1} poses")
    if k and (int(range_beacon.min()) < 0 or int(range_beacon.max()) >= beacons.shape[0]):
        raise ValueError(f"range_beacon must index the {beacons.shape[0]} beacons")
    if range_fraction is not None and (
        range_fraction.shape != (k,)
        or not bool(((range_fraction >= 0) & (range_fraction <= 1)).all())
    ):
        raise ValueError(f"range_fraction must be ({k},) values in [0, 1]")
    noise = odometry_noise or OdometryNoise()
    if initial_poses is None:
        initial_poses = chain(first_pose, odometry)
    initial_poses = initial_poses.to(dtype=dtype, device=device)
    index = torch.arange(steps, device=device)
    variance = torch.full((1, k, 1, 1), range_sigma_m**2, dtype=dtype, device=device)
    if range_fraction is None:
        range_factor: Factor = Se2RangeFactor(
            "pose", range_pose, "beacon", range_beacon, ranges[None], variance, range_kernel
        )
    else:
        range_factor = Se2InterpolatedRangeFactor(
            "pose",
            (range_pose - 1).clamp(min=0),
            range_pose,
            range_fraction.to(dtype=dtype, device=device)[None],
            "beacon",
            range_beacon,
            ranges[None],
            variance,
            range_kernel,
        )
    factors = [
        Se2BetweenFactor(
            "pose",
            index,
            index + 1,
            odometry[None, :, 0:2],
            odometry[None, :, 2],
            noise.covariance(odometry[:, 0:2].norm(dim=-1))[None],
        ),
        range_factor,
        Se2PriorFactor(
            "pose",
            torch.zeros(1, dtype=torch.long, device=device),
            first_pose[None, None],
            first_pose_covariance[None, None],
        ),
    ]
    fixed = {}
    if beacons_known:
        fixed["beacon"] = torch.ones(beacons.shape[0], dtype=torch.bool, device=device)
    return Problem(
        {
            "pose": (SE2, initial_poses[None]),
            "beacon": (POINT2, beacons.to(dtype=dtype, device=device)[None]),
        },
        factors,
        fixed=fixed,
    )


def multilaterate(
    positions: torch.Tensor, ranges: torch.Tensor, iterations: int = 50
) -> torch.Tensor:
    """Least-squares position (..., 2) of a beacon from ranges (N,) m taken at known
    positions (..., N, 2) m (leading dimensions: independent problems, e.g. one per trial
    heading): Gauss-Newton on ``sum (|b - p_n| - r_n)^2`` from nine starts around the
    positions (their centroid and eight points one spread away), the lowest cost kept (a
    range-only fix has a mirror image across a straight path: the starts find both).

    Raises:
        ValueError: fewer than three ranges, mismatched shapes or a value that is not finite.
    """
    if positions.ndim < 2 or positions.shape[-2] < 3 or ranges.shape != positions.shape[-2:-1]:
        raise ValueError(
            f"multilaterate: need N >= 3 positions (..., N, 2) and ranges (N,), got "
            f"{tuple(positions.shape)} and {tuple(ranges.shape)}"
        )
    for name, tensor in (("positions", positions), ("ranges", ranges)):
        bad = torch.nonzero(~torch.isfinite(tensor))
        if bad.numel():
            where = ", ".join(str(int(i)) for i in bad[0])
            raise ValueError(f"multilaterate: {name}[{where}] is not finite")
    centre = positions.mean(-2)  # (..., 2)
    spread = (positions - centre[..., None, :]).norm(dim=-1).mean(-1) + ranges.mean()
    angles = torch.arange(8, dtype=positions.dtype, device=positions.device) * (torch.pi / 4)
    ring = torch.stack((torch.cos(angles), torch.sin(angles)), -1)  # (8, 2)
    beacon = torch.cat(  # (..., 9, 2) starts, solved together
        (centre[..., None, :], centre[..., None, :] + spread[..., None, None] * ring), -2
    )
    eye = 1e-9 * torch.eye(2, dtype=positions.dtype, device=positions.device)
    for _ in range(iterations):
        offset = beacon[..., :, None, :] - positions[..., None, :, :]  # (..., 9, N, 2)
        distance = offset.norm(dim=-1).clamp_min(1e-9)
        jac = offset / distance[..., None]
        residual = distance - ranges
        normal = jac.mT @ jac + eye
        beacon = beacon - torch.linalg.solve(normal, (jac.mT @ residual[..., None]))[..., 0]
    offset = beacon[..., :, None, :] - positions[..., None, :, :]
    cost = (offset.norm(dim=-1) - ranges).pow(2).sum(-1)  # (..., 9)
    best = cost.argmin(-1)[..., None, None].expand(*cost.shape[:-1], 1, 2)
    return beacon.gather(-2, best)[..., 0, :]
