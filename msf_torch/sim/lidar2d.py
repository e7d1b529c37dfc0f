"""2D LiDAR scans ray-cast in line-segment maps (corridors, warehouses) along planar routes.

Maps are sets of wall segments, ``(S, 2, 2)`` endpoints in m (:class:`SegmentMap`):

* :func:`corridor_map`: two long parallel featureless walls closed by end walls. Away from
  the ends (farther than the sensor's maximum range) a scan sees two parallel lines, so scan
  matching cannot observe the motion along the corridor axis (degenerate).
* :func:`warehouse_map`: a rectangular hall with rows of racks (bays with gaps between
  them), aisles between the rows, cross aisles at both ends, and pillars.

Each map carries a route (waypoints). :func:`follow_route` drives a unicycle along it with a
pure-pursuit steering law (look-ahead ``L_d``, curvature ``kappa = 2 sin(alpha) / L_d`` with
``alpha`` the bearing of the look-ahead point), slows down in turns
(``v = v_nom / (1 + c |kappa|)``), limits the yaw rate, and integrates each step exactly on an
arc (constant speed and yaw rate over ``dt``). That integrated state is the ground truth.

Sensors:

* **Wheel odometry** (:func:`wheel_odometry`), differential drive with track ``D``: true
  rim speeds ``v_l,r = v -/+ omega D / 2`` read as ``v_l,r (1 + e_l,r) + n`` (per-wheel scale
  error ``e ~ N(0, s_e^2)`` drawn once per run, white noise ``n ~ N(0, s_n^2)``), turned back
  into ``v = (v_r + v_l) / 2``, ``omega = (v_r - v_l) / D_nominal`` while the effective
  track is ``D (1 + e_D)`` (tyre scrub), and integrated on arcs like the truth.
* **LiDAR** (:class:`LidarSpec`, :func:`raycast`): beams at ``angle_k = -fov/2 + k res``
  (sensor frame = body frame, x forward), each the first wall hit along the ray. A scan is
  taken at one instant (no motion distortion). Measured range
  ``r = r_true + N(0, (sigma_0 + sigma_rel r_true)^2)``. A beam returns nothing (NaN) when
  no wall lies within ``max_range``, when it meets the wall at an incidence angle beyond
  ``max_incidence`` (too little light comes back at grazing incidence), when it drops out at
  random (probability ``p_drop``, independent per beam), or when the measured range falls
  below ``min_range``. Defaults follow a SICK TiM571-class indoor scanner: 270 deg field of
  view, 0.5 deg resolution (541 beams), 25 m range, 1 cm + 0.1 % noise.

Example:
    >>> from msf_torch.sim.lidar2d import corridor_map, simulate_lidar_run
    >>> run = simulate_lidar_run(corridor_map(), seed=0, duration_s=5.0)
    >>> run.ranges.shape
    torch.Size([51, 541])
"""

from __future__ import annotations

__all__ = [
    "LidarSpec",
    "SegmentMap",
    "PlanarTrajectory",
    "LidarRun",
    "corridor_map",
    "warehouse_map",
    "raycast",
    "follow_route",
    "wheel_odometry",
    "scan_at",
    "simulate_lidar_run",
]

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from msf_torch.geometry.se2 import wrap_angle

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class LidarSpec:
    """A 2D scanning range finder.

    Attributes:
        fov_deg: field of view, deg, centred on the body x axis.
        resolution_deg: angle between beams, deg.
        max_range_m: farthest return, m.
        min_range_m: nearest return, m.
        range_sigma_m: ``sigma_0``, range noise at zero range, m.
        range_sigma_rel: ``sigma_rel``, range noise growth per metre of range (m/m).
        dropout_probability: ``p_drop``, chance that a beam returns nothing.
        max_incidence_deg: beams meeting a wall beyond this angle from its normal return
            nothing, deg.
        scan_rate_hz: scans per second, Hz.
    """

    fov_deg: float = 270.0
    resolution_deg: float = 0.5
    max_range_m: float = 25.0
    min_range_m: float = 0.05
    range_sigma_m: float = 0.01
    range_sigma_rel: float = 0.001
    dropout_probability: float = 0.01
    max_incidence_deg: float = 85.0
    scan_rate_hz: float = 10.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        for name in ("fov_deg", "resolution_deg", "max_range_m", "scan_rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LidarSpec.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("min_range_m", "range_sigma_m", "range_sigma_rel"):
            if getattr(self, name) < 0:
                raise ValueError(f"LidarSpec.{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0 <= self.dropout_probability < 1:
            raise ValueError(
                f"LidarSpec.dropout_probability must be in [0, 1), got {self.dropout_probability}"
            )
        if not 0 < self.max_incidence_deg <= 90:
            raise ValueError(
                f"LidarSpec.max_incidence_deg must be in (0, 90], got {self.max_incidence_deg}"
            )
        if self.fov_deg > 360:
            raise ValueError(f"LidarSpec.fov_deg must be <= 360, got {self.fov_deg}")

    @property
    def beams(self) -> int:
        """Number of beams per scan."""
        return int(math.floor(self.fov_deg / self.resolution_deg + 1e-9)) + 1

    def angles(self, dtype: torch.dtype = torch.float64, device: Any = None) -> torch.Tensor:
        """Beam angles (K,), rad, from ``-fov / 2`` counter-clockwise."""
        k = torch.arange(self.beams, dtype=dtype, device=device)
        return (-0.5 * self.fov_deg + k * self.resolution_deg) * _DEG


@dataclass
class SegmentMap:
    """Walls as line segments plus a route for the robot.

    Attributes:
        name: ``"corridor"``, ``"warehouse"``, ...
        segments: (S, 2, 2) segment endpoints ``[[x0, y0], [x1, y1]]``, m.
        route: (W, 2) waypoints the robot drives through, m.
        meta: map parameters.
    """

    name: str
    segments: torch.Tensor
    route: torch.Tensor
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class PlanarTrajectory:
    """Planar motion sampled at a fixed rate.

    Attributes:
        t: (T,) s.
        pose: (T, 3) ``[x, y, yaw]`` in the map frame, m and rad.
        speed: (T,) forward speed over the step that starts at ``t``, m/s.
        yaw_rate: (T,) yaw rate over that step, rad/s.
    """

    t: torch.Tensor
    pose: torch.Tensor
    speed: torch.Tensor
    yaw_rate: torch.Tensor


@dataclass
class LidarRun:
    """A simulated run: scans, their true poses and the wheel-odometry poses.

    Attributes:
        t: (N,) scan times, s.
        truth: (N, 3) true ``[x, y, yaw]`` of the body at each scan, map frame.
        odometry: (N, 3) wheel-odometry pose at each scan (starts at the truth), map frame.
        angles: (K,) beam angles, rad.
        ranges: (N, K) measured ranges, m; NaN where the beam returned nothing.
        true_ranges: (N, K) noise-free ranges to the first wall, m; NaN beyond max range.
        spec: the LiDAR.
        map: the map.
        meta: seeds and odometry error draws.
    """

    t: torch.Tensor
    truth: torch.Tensor
    odometry: torch.Tensor
    angles: torch.Tensor
    ranges: torch.Tensor
    true_ranges: torch.Tensor
    spec: LidarSpec
    map: SegmentMap
    meta: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Maps
# --------------------------------------------------------------------------------------------


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[list[float]]]:
    return [
        [[x0, y0], [x1, y0]],
        [[x1, y0], [x1, y1]],
        [[x1, y1], [x0, y1]],
        [[x0, y1], [x0, y0]],
    ]


def corridor_map(length_m: float = 120.0, width_m: float = 2.4) -> SegmentMap:
    """A straight corridor along x from 0 to ``length_m``, walls at ``y = +-width_m / 2``.

    The route runs down the middle from 4 m after the start to 4 m before the end.
    """
    if not (length_m > 10.0 and width_m > 0.5):
        raise ValueError(
            f"corridor_map: need length_m > 10 and width_m > 0.5, got {length_m}, {width_m}"
        )
    half = 0.5 * width_m
    segments = torch.tensor(_box(0.0, -half, length_m, half), dtype=torch.float64)
    xs = np.arange(4.0, length_m - 4.0 + 1e-9, 2.0)
    route = torch.tensor(np.stack((xs, np.zeros_like(xs)), -1), dtype=torch.float64)
    return SegmentMap("corridor", segments, route, {"length_m": length_m, "width_m": width_m})


def warehouse_map(
    hall_m: tuple[float, float] = (40.0, 24.0),
    rack_rows: int = 5,
    rack_depth_m: float = 1.2,
    aisle_width_m: float = 3.0,
    cross_aisle_m: float = 6.0,
    bay_length_m: float = 2.7,
    bay_gap_m: float = 0.3,
    pillar_m: float = 0.4,
    upright_m: float = 0.1,
    max_recess_m: float = 0.3,
    seed: int = 0,
) -> SegmentMap:
    """A hall ``hall_m = (X, Y)`` with ``rack_rows`` rows of racks along x.

    Rows start ``aisle_width_m`` above the floor's lower wall and repeat every
    ``rack_depth_m + aisle_width_m``; each row runs from ``cross_aisle_m`` to
    ``X - cross_aisle_m`` as bays of ``bay_length_m`` separated by ``bay_gap_m``. Each bay
    has square uprights of side ``upright_m`` at its four corners, and its load (pallets)
    stands back from each aisle face by ``U(0, max_recess_m)`` drawn per bay and face
    (``seed``), so the aisle walls are stepped, not flat. Square pillars of side
    ``pillar_m`` stand in the cross aisles, 1 m from the end walls, in line with each row.
    The route snakes through every aisle (a serpentine), turning in the cross aisles.
    """
    size_x, size_y = hall_m
    pitch = rack_depth_m + aisle_width_m
    if aisle_width_m + rack_rows * pitch > size_y + 1e-9:
        raise ValueError(
            f"warehouse_map: {rack_rows} rows need {aisle_width_m + rack_rows * pitch}"
            f" m, the hall is {size_y} m deep"
        )
    if size_x <= 2 * cross_aisle_m + bay_length_m:
        raise ValueError("warehouse_map: the hall is too short for the cross aisles and one bay")
    if not 0 <= max_recess_m < 0.5 * rack_depth_m or not 0 < upright_m < 0.5 * bay_length_m:
        raise ValueError(
            "warehouse_map: need 0 <= max_recess_m < rack_depth_m / 2 and "
            "0 < upright_m < bay_length_m / 2"
        )
    rng = np.random.default_rng(seed)
    segments = _box(0.0, 0.0, size_x, size_y)
    x_start, x_end = cross_aisle_m, size_x - cross_aisle_m
    for row in range(rack_rows):
        y0 = aisle_width_m + row * pitch
        y1 = y0 + rack_depth_m
        x = x_start
        while x + 0.5 * bay_length_m < x_end:
            x1 = min(x + bay_length_m, x_end)
            low, high = rng.uniform(0.0, max_recess_m, 2)
            segments += _box(x + upright_m, y0 + low, x1 - upright_m, y1 - high)
            for xc in (x, x1 - upright_m):
                for yc in (y0, y1 - upright_m):
                    segments += _box(xc, yc, xc + upright_m, yc + upright_m)
            x = x1 + bay_gap_m
    aisle_centres = [0.5 * aisle_width_m + k * pitch for k in range(rack_rows + 1)]
    half = 0.5 * pillar_m
    for row in range(rack_rows):
        yc = aisle_width_m + row * pitch + 0.5 * rack_depth_m
        for xc in (1.0, size_x - 1.0):
            segments += _box(xc - half, yc - half, xc + half, yc + half)
    turn_left, turn_right = 0.5 * cross_aisle_m, size_x - 0.5 * cross_aisle_m
    route: list[tuple[float, float]] = []
    for k, yc in enumerate(aisle_centres):
        ends = (turn_left, turn_right) if k % 2 == 0 else (turn_right, turn_left)
        route += [(ends[0], yc), (ends[1], yc)]
    meta = {
        "hall_m": list(hall_m),
        "rack_rows": rack_rows,
        "rack_depth_m": rack_depth_m,
        "aisle_width_m": aisle_width_m,
        "cross_aisle_m": cross_aisle_m,
        "bay_length_m": bay_length_m,
        "bay_gap_m": bay_gap_m,
        "pillar_m": pillar_m,
        "upright_m": upright_m,
        "max_recess_m": max_recess_m,
        "seed": seed,
    }
    return SegmentMap(
        "warehouse",
        torch.tensor(segments, dtype=torch.float64),
        torch.tensor(route, dtype=torch.float64),
        meta,
    )


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def raycast(
    segments: torch.Tensor,
    poses: torch.Tensor,
    angles: torch.Tensor,
    max_range_m: float,
    chunk: int = 256,
) -> tuple[torch.Tensor, torch.Tensor]:
    """First wall hit along every beam of every pose.

    A beam from origin ``o`` in direction ``d`` meets segment ``a + u (b - a)``,
    ``u in [0, 1]``, at range ``t = ((a - o) x e) / (d x e)`` with ``e = b - a`` and
    ``u = ((a - o) x d) / (d x e)`` (2D cross products); the smallest ``t > 0`` wins.
    Only the beams inside the angle a segment subtends from ``o`` (plus one beam each side)
    are tested: the (pose, segment, beam) candidates are enumerated flat, so the work grows
    with the beams each segment covers, not with beams x segments.

    Args:
        segments: (S, 2, 2) wall endpoints, m; the beam angles must be evenly spaced.
        poses: (B, 3) sensor poses ``[x, y, yaw]``, m and rad.
        angles: (K,) evenly spaced increasing beam angles in the sensor frame, rad.
        max_range_m: hits beyond this range are dropped, m.
        chunk: poses per vectorised block.

    Returns:
        ranges (B, K) to the first hit, m (NaN when none within ``max_range_m``), and the
        cosine of the incidence angle (B, K) (1 for a beam along the wall normal; NaN
        where no hit).
    """
    if segments.ndim != 3 or segments.shape[1:] != (2, 2):
        raise ValueError(f"raycast: segments must be (S, 2, 2), got {tuple(segments.shape)}")
    if poses.ndim != 2 or poses.shape[-1] != 3:
        raise ValueError(f"raycast: poses must be (B, 3), got {tuple(poses.shape)}")
    n_beams = angles.shape[0]
    angle0 = float(angles[0])
    res = float(angles[1] - angles[0]) if n_beams > 1 else 1.0
    start_pt = segments[:, 0]
    edge = segments[:, 1] - segments[:, 0]  # (S, 2)
    unit_edge = edge / edge.norm(dim=-1, keepdim=True)
    ranges_out, cos_out = [], []
    for block in poses.split(chunk):
        b = block.shape[0]
        rel_a = segments[None, :, 0] - block[:, None, :2]  # (b, S, 2)
        rel_b = segments[None, :, 1] - block[:, None, :2]
        bear_a = wrap_angle(torch.atan2(rel_a[..., 1], rel_a[..., 0]) - block[:, None, 2])
        bear_b = wrap_angle(torch.atan2(rel_b[..., 1], rel_b[..., 0]) - block[:, None, 2])
        span = wrap_angle(bear_b - bear_a)
        low = torch.where(span >= 0, bear_a, bear_b)
        high = low + span.abs()
        # two copies of the interval: as is, and shifted by -2 pi (it may wrap past +pi)
        low2 = torch.stack((low, low - 2 * math.pi), -1)  # (b, S, 2)
        high2 = torch.stack((high, high - 2 * math.pi), -1)
        k_lo = torch.ceil((low2 - angle0) / res).long() - 1
        k_hi = torch.floor((high2 - angle0) / res).long() + 1
        k_lo = k_lo.clamp(min=0)
        k_hi = k_hi.clamp(max=n_beams - 1)
        count = (k_hi - k_lo + 1).clamp(min=0).reshape(-1)
        total = int(count.sum())
        flat_pose = torch.arange(b, device=block.device)[:, None, None].expand(-1, *k_lo.shape[1:])
        flat_seg = torch.arange(k_lo.shape[1], device=block.device)[None, :, None].expand(b, -1, 2)
        owner = torch.repeat_interleave(torch.arange(count.numel(), device=block.device), count)
        first = torch.cumsum(count, 0) - count
        beam = k_lo.reshape(-1)[owner] + torch.arange(total, device=block.device) - first[owner]
        pose_i = flat_pose.reshape(-1)[owner]
        seg_i = flat_seg.reshape(-1)[owner]
        heading = block[pose_i, 2] + angles[beam]
        d = torch.stack((torch.cos(heading), torch.sin(heading)), -1)  # (P, 2)
        e = edge[seg_i]
        offset = start_pt[seg_i] - block[pose_i, :2]
        denom = _cross(d, e)
        parallel = denom.abs() < 1e-12
        safe = torch.where(parallel, 1.0, denom)
        t = _cross(offset, e) / safe
        u = _cross(offset, d) / safe
        hit = (~parallel) & (t > 1e-9) & (u >= 0.0) & (u <= 1.0)
        t = torch.where(hit, t, math.inf)
        target = pose_i * n_beams + beam
        best = torch.full((b * n_beams,), math.inf, dtype=block.dtype, device=block.device)
        best = best.scatter_reduce(0, target, t, reduce="amin")
        winner = hit & (t == best[target])
        cosine = torch.full_like(best, math.nan)
        cosine[target[winner]] = _cross(d[winner], unit_edge[seg_i[winner]]).abs()
        best = best.reshape(b, n_beams)
        cosine = cosine.reshape(b, n_beams)
        found = best <= max_range_m
        ranges_out.append(torch.where(found, best, math.nan))
        cos_out.append(torch.where(found, cosine, math.nan))
    return torch.cat(ranges_out), torch.cat(cos_out)


# --------------------------------------------------------------------------------------------
# Trajectories and odometry
# --------------------------------------------------------------------------------------------


def _arc_step(pose: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray, dt: float) -> np.ndarray:
    """Exact unicycle step (..., 3) for constant ``speed`` and ``yaw_rate`` over ``dt``."""
    dtheta = yaw_rate * dt
    small = np.abs(dtheta) < 1e-9
    safe = np.where(small, 1.0, dtheta)
    # chord factors sin(dth)/dth and (1 - cos(dth))/dth, Taylor near zero
    f_sin = np.where(small, 1.0 - dtheta**2 / 6.0, np.sin(safe) / safe)
    f_cos = np.where(small, 0.5 * dtheta, (1.0 - np.cos(safe)) / safe)
    dx_body = speed * dt * f_sin
    dy_body = speed * dt * f_cos
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    out = np.empty_like(pose)
    out[..., 0] = pose[..., 0] + c * dx_body - s * dy_body
    out[..., 1] = pose[..., 1] + s * dx_body + c * dy_body
    out[..., 2] = pose[..., 2] + dtheta
    return out


def follow_route(
    route: torch.Tensor,
    speed_mps: float = 1.2,
    rate_hz: float = 100.0,
    lookahead_m: float = 1.0,
    max_yaw_rate_rad_s: float = 1.0,
    turn_slowdown_m: float = 1.0,
    duration_s: float | None = None,
) -> PlanarTrajectory:
    """Drive a unicycle along the polyline ``route`` (W, 2) by pure pursuit.

    The robot starts on the first waypoint facing the second. Each step finds the point
    ``lookahead_m`` further along the polyline than the robot's projection onto it, steers
    with ``kappa = 2 sin(alpha) / lookahead_m``, drives at
    ``v = speed_mps / (1 + turn_slowdown_m |kappa|)`` with the yaw rate clipped to
    ``max_yaw_rate_rad_s``, and integrates the step exactly (:func:`_arc_step`). It stops
    within ``lookahead_m / 2`` of the last waypoint or at ``duration_s``.

    Returns:
        The trajectory at ``rate_hz``; ``yaw`` is continuous (not wrapped).
    """
    pts = route.detach().cpu().numpy().astype(np.float64)
    if pts.ndim != 2 or pts.shape[0] < 2 or pts.shape[1] != 2:
        raise ValueError(f"follow_route: route must be (W >= 2, 2), got {tuple(route.shape)}")
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    if np.any(seg_len <= 0):
        raise ValueError("follow_route: repeated waypoints")
    cum = np.concatenate(([0.0], np.cumsum(seg_len)))
    total = cum[-1]

    def point_at(s: float) -> np.ndarray:
        s = min(max(s, 0.0), total)
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        return pts[k] + seg[k] * (s - cum[k]) / seg_len[k]

    def project(p: np.ndarray, s_hint: float) -> float:
        # nearest point on the polyline among segments near the previous arc length
        best_s, best_d = s_hint, math.inf
        for k in range(len(seg)):
            if cum[k + 1] < s_hint - 2.0 * lookahead_m or cum[k] > s_hint + 4.0 * lookahead_m:
                continue
            u = float(np.clip(np.dot(p - pts[k], seg[k]) / seg_len[k] ** 2, 0.0, 1.0))
            d = float(np.linalg.norm(pts[k] + u * seg[k] - p))
            if d < best_d:
                best_d, best_s = d, cum[k] + u * seg_len[k]
        return max(best_s, s_hint)

    dt = 1.0 / rate_hz
    pose = np.array([pts[0, 0], pts[0, 1], math.atan2(seg[0, 1], seg[0, 0])])
    s_along = 0.0
    poses, speeds, rates = [], [], []
    max_steps = int(math.ceil((duration_s if duration_s is not None else 1e9) * rate_hz))
    step = 0
    while step <= max_steps:
        s_along = project(pose[:2], s_along)
        if s_along >= total - 0.5 * lookahead_m:
            break
        target = point_at(s_along + lookahead_m)
        alpha = math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2]
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        kappa = 2.0 * math.sin(alpha) / lookahead_m
        v = speed_mps / (1.0 + turn_slowdown_m * abs(kappa))
        w = float(np.clip(v * kappa, -max_yaw_rate_rad_s, max_yaw_rate_rad_s))
        poses.append(pose.copy())
        speeds.append(v)
        rates.append(w)
        pose = _arc_step(pose, np.float64(v), np.float64(w), dt)
        step += 1
    n = len(poses)
    f64 = dict(dtype=torch.float64)
    return PlanarTrajectory(
        t=torch.arange(n, **f64) * dt,
        pose=torch.tensor(np.array(poses), **f64),
        speed=torch.tensor(speeds, **f64),
        yaw_rate=torch.tensor(rates, **f64),
    )


def wheel_odometry(
    trajectory: PlanarTrajectory,
    rng: np.random.Generator,
    track_m: float = 0.5,
    scale_sigma: float = 0.005,
    track_scale_sigma: float = 0.02,
    speed_noise_mps: float = 0.01,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Dead-reckoned poses (T, 3) from simulated wheel readings (see the module docstring).

    Args:
        trajectory: the truth; its step speeds and yaw rates are read by the wheels.
        rng: the random source (scale errors, then white noise).
        track_m: nominal track ``D``, m.
        scale_sigma: ``s_e``, 1-sigma per-wheel scale error.
        track_scale_sigma: 1-sigma relative error ``e_D`` of the effective track.
        speed_noise_mps: ``s_n``, white noise per wheel reading, m/s.

    Returns:
        Odometry poses (T, 3) starting at the true first pose, and the drawn errors.
    """
    scale_left, scale_right = rng.normal(0.0, scale_sigma, 2)
    track_error = float(rng.normal(0.0, track_scale_sigma))
    speed = trajectory.speed.numpy()
    yaw_rate = trajectory.yaw_rate.numpy()
    true_track = track_m * (1.0 + track_error)
    left = (speed - 0.5 * yaw_rate * true_track) * (1.0 + scale_left)
    right = (speed + 0.5 * yaw_rate * true_track) * (1.0 + scale_right)
    left = left + rng.normal(0.0, speed_noise_mps, left.shape)
    right = right + rng.normal(0.0, speed_noise_mps, right.shape)
    v = 0.5 * (left + right)
    w = (right - left) / track_m
    t = trajectory.t.numpy()
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    out = np.empty((len(t), 3))
    out[0] = trajectory.pose[0].numpy()
    for k in range(1, len(t)):
        out[k] = _arc_step(out[k - 1], v[k - 1], w[k - 1], dt)
    errors = {
        "scale_left": float(scale_left),
        "scale_right": float(scale_right),
        "track_error": track_error,
    }
    return torch.tensor(out, dtype=torch.float64), errors


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


def scan_at(
    segment_map: SegmentMap,
    poses: torch.Tensor,
    spec: LidarSpec,
    rng: np.random.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Scans (B, K) from poses (B, 3): measured ranges (NaN = no return) and true ranges.

    With ``rng`` None the scan is noise-free and nothing drops out at random (the range and
    incidence limits still apply).
    """
    spec.validate()
    angles = spec.angles(poses.dtype, poses.device)
    true_ranges, cosine = raycast(segment_map.segments.to(poses), poses, angles, spec.max_range_m)
    measured = true_ranges.clone()
    valid = torch.isfinite(true_ranges) & (cosine >= math.cos(spec.max_incidence_deg * _DEG))
    if rng is not None:
        sigma = spec.range_sigma_m + spec.range_sigma_rel * torch.nan_to_num(true_ranges)
        noise = torch.as_tensor(rng.standard_normal(tuple(true_ranges.shape))).to(poses)
        measured = measured + sigma * noise
        drop = torch.as_tensor(rng.random(tuple(true_ranges.shape))).to(poses.device)
        valid = valid & (drop >= spec.dropout_probability)
    valid = valid & (measured >= spec.min_range_m)
    return torch.where(valid, measured, math.nan), true_ranges


def simulate_lidar_run(
    segment_map: SegmentMap,
    seed: int,
    spec: LidarSpec | None = None,
    speed_mps: float = 1.2,
    duration_s: float | None = None,
    route_jitter_m: float = 0.25,
    odometry_rate_hz: float = 100.0,
) -> LidarRun:
    """Drive ``segment_map``'s route and record scans and wheel odometry.

    The route's interior waypoints are shifted sideways by ``N(0, route_jitter_m^2)`` (per
    axis, seeded) so runs differ; then :func:`follow_route` at ``odometry_rate_hz`` gives the
    truth, :func:`wheel_odometry` the odometry, and scans are taken every
    ``1 / spec.scan_rate_hz`` s (:func:`scan_at`).

    Args:
        segment_map: walls and route.
        seed: random seed (route jitter, odometry errors, range noise and dropouts).
        spec: the LiDAR (default :class:`LidarSpec`).
        speed_mps: nominal forward speed, m/s.
        duration_s: stop after this long (default: the end of the route).
        route_jitter_m: sideways waypoint jitter, m.
        odometry_rate_hz: truth and wheel-reading rate, Hz (a multiple of the scan rate).
    """
    spec = spec or LidarSpec()
    spec.validate()
    ratio = odometry_rate_hz / spec.scan_rate_hz
    if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
        raise ValueError("simulate_lidar_run: odometry_rate_hz must be a multiple of scan_rate_hz")
    stride = int(round(ratio))
    rng = np.random.default_rng(seed)
    route = segment_map.route.clone()
    if len(route) > 2 and route_jitter_m > 0:
        route[1:-1] += torch.as_tensor(rng.normal(0.0, route_jitter_m, (len(route) - 2, 2)))
    trajectory = follow_route(route, speed_mps, odometry_rate_hz, duration_s=duration_s)
    odometry, errors = wheel_odometry(trajectory, rng)
    index = torch.arange(0, len(trajectory.t), stride)
    truth = trajectory.pose[index]
    ranges, true_ranges = scan_at(segment_map, truth, spec, rng)
    truth = torch.cat((truth[:, :2], wrap_angle(truth[:, 2:])), -1)
    odo = odometry[index]
    odo = torch.cat((odo[:, :2], wrap_angle(odo[:, 2:])), -1)
    return LidarRun(
        t=trajectory.t[index],
        truth=truth,
        odometry=odo,
        angles=spec.angles(),
        ranges=ranges,
        true_ranges=true_ranges,
        spec=spec,
        map=segment_map,
        meta={"seed": seed, "speed_mps": speed_mps, "odometry_errors": errors},
    )
