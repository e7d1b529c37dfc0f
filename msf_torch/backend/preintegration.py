"""IMU and wheel preintegration between keyframes, for the back end's factors.

IMU: :func:`preintegrate_imu` cuts raw samples at keyframe times and calls
:func:`msf_torch.sensors.imu.preintegrate` (the same exact zero-order-hold step the ESKF
propagates with) for the increments and their exact bias Jacobians. The increments'
covariance is then propagated sample by sample,

    Omega_{k+1} = A_k Omega_k A_k^T + B_k (Sigma_n / dt_k) B_k^T,

with ``A_k``, ``B_k`` the exact Jacobians of the ZOH step w.r.t. the increment error
``[dp, dv, dtheta]`` and the white noise (including the noise's effect inside the sample
through ``d Gamma_n / d phi``); ``sensors.imu.preintegrate`` itself carries a closed form at
zeroth order in ``w dt`` used by the filter, which this recursion replaces. The bias random
walk adds ``sigma_bw^2 dT`` to the bias rows of the 15x15 factor covariance.

GTSAM-compatible IMU option: :func:`preintegrate_imu_tangent` reproduces the gtsam 4.3
wheel's tangent-space preintegration (Euler steps, additive bias correction, its
``residualCovariance``) for :class:`~msf_torch.backend.factors.GtsamImuFactor`, so a
problem can be posed exactly as GTSAM poses it (solver comparisons); the ZOH path above
stays the default.

Wheels: :func:`preintegrate_wheel` integrates differential-drive rim speeds into a planar
increment ``[dx, dy, dyaw]`` in the frame of keyframe i with exact arcs per sample, and
propagates the rim-speed noise to its 3x3 covariance; the slip factor ``f`` in (0, 1] from
the front end divides that sample's noise sigma (``f = 1``: no slip).
"""

from __future__ import annotations

__all__ = [
    "ImuIntervals",
    "cut_imu",
    "preintegrate_imu",
    "recursive_covariance",
    "imu_covariance",
    "preintegrate_wheel",
    "calibrated_wheel_increment",
    "TangentPreintegrated",
    "preintegrate_imu_tangent",
]

from dataclasses import dataclass, replace

import torch

from msf_torch.geometry import so3
from msf_torch.sensors.imu import ImuNoise, Preintegrated, preintegrate
from msf_torch.sensors.wheel import wheel_speed_and_yaw_rate


@dataclass
class ImuIntervals:
    """Raw IMU samples cut into K - 1 keyframe intervals, padded with ``dt = 0``.

    Attributes:
        gyro, accel: (..., K - 1, L, 3) rad/s, m/s^2.
        dt: (..., K - 1, L) hold time of each (piece of a) sample, s.
    """

    gyro: torch.Tensor
    accel: torch.Tensor
    dt: torch.Tensor


def cut_imu(
    times: torch.Tensor, gyro: torch.Tensor, accel: torch.Tensor, keyframe_times: torch.Tensor
) -> ImuIntervals:
    """Cut one IMU stream at keyframe times (zero-order hold: sample k holds from ``t_k`` to
    ``t_{k+1}``; a sample that straddles a keyframe time is split there).

    Args:
        times: (T,) s, increasing. gyro, accel: (T, 3).
        keyframe_times: (K,) s, increasing, inside ``[times[0], times[-1]]``.
    Returns:
        :class:`ImuIntervals` with leading dim K - 1.
    """
    if keyframe_times[0] < times[0] or keyframe_times[-1] > times[-1]:
        raise ValueError("keyframe times must lie inside the IMU time span")
    knots, order = torch.sort(torch.cat((times, keyframe_times)), stable=True)
    device = times.device
    source = torch.cat(
        (
            torch.arange(times.numel(), device=device),
            torch.full((keyframe_times.numel(),), -1, device=device),
        )
    )[order]
    # sample index held on each piece [knots[m], knots[m+1]): the last real sample at or before
    sample = torch.cummax(torch.where(source >= 0, source, torch.full_like(source, -1)), 0).values
    piece_dt = knots[1:] - knots[:-1]
    piece_sample = sample[:-1]
    piece_start = knots[:-1]
    interval = torch.searchsorted(keyframe_times, piece_start, right=True) - 1
    valid = (interval >= 0) & (interval < keyframe_times.numel() - 1) & (piece_dt > 0)
    interval, piece_sample, piece_dt = interval[valid], piece_sample[valid], piece_dt[valid]
    count = keyframe_times.numel() - 1
    lengths = torch.bincount(interval, minlength=count)
    width = int(lengths.max()) if lengths.numel() else 0
    first = torch.cumsum(lengths, 0) - lengths
    slot = torch.arange(interval.numel(), device=device) - first[interval]
    out_dt = torch.zeros(count, width, dtype=times.dtype, device=device)
    out_gyro = torch.zeros(count, width, 3, dtype=gyro.dtype, device=device)
    out_accel = torch.zeros(count, width, 3, dtype=accel.dtype, device=device)
    out_dt[interval, slot] = piece_dt
    out_gyro[interval, slot] = gyro[piece_sample]
    out_accel[interval, slot] = accel[piece_sample]
    return ImuIntervals(out_gyro, out_accel, out_dt)


def recursive_covariance(
    gyro: torch.Tensor,
    accel: torch.Tensor,
    dt: torch.Tensor,
    gyro_bias: torch.Tensor,
    accel_bias: torch.Tensor,
    noise_scale: torch.Tensor | None = None,
    accel_noise_scale: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact sample-by-sample covariance of ``[dp, dv, dtheta]`` for unit noise densities.

    Args: as :func:`msf_torch.sensors.imu.preintegrate`, except that ``noise_scale`` may also
        be (..., L, 3): one variance multiplier per sensor axis (body frame); and
        ``accel_noise_scale`` ((..., L) or (..., L, 3)), when given, multiplies the
        accelerometer's variance instead of ``noise_scale`` (which then scales the gyro's
        only).
    Returns:
        (cov_unit_gyro, cov_unit_accel), each (..., 9, 9).
    """
    omega = gyro - gyro_bias[..., None, :]
    force = accel - accel_bias[..., None, :]
    phi = omega * dt[..., None]
    coef = so3.coefficients(phi, derivatives=True)
    step_rot, gam1, gam2 = so3.exp_and_gammas(phi, coef).unbind(-3)
    d_gamma1, d_gamma2 = so3.gamma_vector_jacobians(phi, force, coef)
    jr = so3.right_jacobian(phi)

    def per_axis(scale: torch.Tensor | None) -> torch.Tensor:
        if scale is None:
            return torch.ones_like(dt)[..., None].expand(*dt.shape, 3)
        return scale[..., None].expand(*dt.shape, 3) if scale.dim() == dt.dim() else scale

    scale_g = per_axis(noise_scale)
    scale_a = scale_g if accel_noise_scale is None else per_axis(accel_noise_scale)
    lead = dt.shape[:-1]
    eye = torch.eye(3, dtype=dt.dtype, device=dt.device)
    cov_g = torch.zeros(*lead, 9, 9, dtype=dt.dtype, device=dt.device)
    cov_a = torch.zeros_like(cov_g)
    rot = eye.expand(*lead, 3, 3)
    for k in range(dt.shape[-1]):
        h = dt[..., k, None, None]
        g1f = (gam1[..., k, :, :] @ force[..., k, :, None]).squeeze(-1)
        g2f = (gam2[..., k, :, :] @ force[..., k, :, None]).squeeze(-1)
        a = torch.zeros(*lead, 9, 9, dtype=dt.dtype, device=dt.device)
        a[..., 0:3, 0:3] = eye
        a[..., 0:3, 3:6] = h * eye
        a[..., 0:3, 6:9] = -rot @ so3.hat(g2f) * h * h
        a[..., 3:6, 3:6] = eye
        a[..., 3:6, 6:9] = -rot @ so3.hat(g1f) * h
        a[..., 6:9, 6:9] = step_rot[..., k, :, :].mT
        b_g = torch.cat(
            (
                rot @ d_gamma2[..., k, :, :] * h**3,
                rot @ d_gamma1[..., k, :, :] * h**2,
                jr[..., k, :, :] * h,
            ),
            -2,
        )
        b_a = torch.cat(
            (rot @ gam2[..., k, :, :] * h**2, rot @ gam1[..., k, :, :] * h, torch.zeros_like(rot)),
            -2,
        )
        # discrete white-noise variance scale / dt per axis (0 on padding)
        held = dt[..., k, None].clamp_min(torch.finfo(dt.dtype).tiny)
        valid = dt[..., k, None, None] > 0
        var_g = torch.where(valid, (scale_g[..., k, :] / held)[..., None, :], 0.0)
        var_a = torch.where(valid, (scale_a[..., k, :] / held)[..., None, :], 0.0)
        cov_g = a @ cov_g @ a.mT + (b_g * var_g) @ b_g.mT
        cov_a = a @ cov_a @ a.mT + (b_a * var_a) @ b_a.mT
        rot = rot @ step_rot[..., k, :, :]
    return cov_g, cov_a


def preintegrate_imu(
    intervals: ImuIntervals,
    gyro_bias: torch.Tensor,
    accel_bias: torch.Tensor,
    covariance: str = "recursive",
    noise_scale: torch.Tensor | None = None,
    accel_noise_scale: torch.Tensor | None = None,
) -> Preintegrated:
    """Increments of every interval (leading dims of ``intervals``), linearised at the
    given biases (..., 3); ``covariance="recursive"`` (exact, default) or ``"closed_form"``
    (the filter's zeroth-order form); ``noise_scale`` (..., L) multiplies each piece's
    noise variance (IMU gaps), as in :func:`msf_torch.sensors.imu.preintegrate`. With the
    recursive covariance, ``noise_scale`` may be (..., L, 3) (one multiplier per sensor
    axis) and ``accel_noise_scale`` ((..., L) or (..., L, 3)) multiplies the
    accelerometer's variance instead (``noise_scale`` then scales the gyro's only)."""
    if covariance == "closed_form":
        if accel_noise_scale is not None or (
            noise_scale is not None and noise_scale.dim() != intervals.dt.dim()
        ):
            raise ValueError(
                "closed_form covariance takes one noise_scale (..., L) for both sensors"
            )
        return preintegrate(
            intervals.gyro, intervals.accel, intervals.dt, gyro_bias, accel_bias, noise_scale
        )
    if covariance != "recursive":
        raise ValueError(f"covariance must be 'recursive' or 'closed_form', got {covariance!r}")
    pre = preintegrate(intervals.gyro, intervals.accel, intervals.dt, gyro_bias, accel_bias)
    cov_g, cov_a = recursive_covariance(
        intervals.gyro,
        intervals.accel,
        intervals.dt,
        gyro_bias,
        accel_bias,
        noise_scale,
        accel_noise_scale,
    )
    return replace(pre, cov_unit_gyro=cov_g, cov_unit_accel=cov_a)


def imu_covariance(pre: Preintegrated | TangentPreintegrated, noise: ImuNoise) -> torch.Tensor:
    """15x15 covariance (..., 15, 15) of the preintegration residual ``[r_p, r_v, r_theta,
    r_bg, r_ba]``: the increments' covariance and the bias random walk over ``dT``."""
    nav = pre.covariance(noise)
    lead = nav.shape[:-2]
    eye = torch.eye(3, dtype=nav.dtype, device=nav.device)
    d_t = pre.delta_t[..., None, None]

    def density(x: torch.Tensor) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=nav.dtype, device=nav.device)
        return x.reshape(*x.shape, *([1] * (pre.delta_t.dim() - x.dim())))[..., None, None]

    out = torch.zeros(*lead, 15, 15, dtype=nav.dtype, device=nav.device)
    out[..., 0:9, 0:9] = nav
    out[..., 9:12, 9:12] = density(noise.gyro_bias_rw_density) ** 2 * d_t * eye
    out[..., 12:15, 12:15] = density(noise.accel_bias_rw_density) ** 2 * d_t * eye
    return out


def _wheel_arcs(
    speed: torch.Tensor, yaw_rate: torch.Tensor, dt: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Planar increment of exact arcs and its sensitivities to each sample's speed and yaw
    rate.

    Args:
        speed: (..., L) forward speed, m/s. yaw_rate: (..., L) rad/s. dt: (..., L) s.
    Returns:
        increment (..., 3) ``[dx, dy, dyaw]`` in the frame of the start, and the Jacobians
        (..., 3, L) of the increment w.r.t. each sample's speed and yaw rate.
    """
    turn = yaw_rate * dt
    small = turn.abs() < 1e-6
    safe = torch.where(small, torch.ones_like(turn), turn)
    sin_ratio = torch.where(small, 1.0 - turn**2 / 6.0, torch.sin(safe) / safe)
    cos_ratio = torch.where(small, turn / 2.0, (1.0 - torch.cos(safe)) / safe)
    yaw_before = torch.cumsum(turn, -1) - turn
    step_x = speed * dt * sin_ratio
    step_y = speed * dt * cos_ratio
    c, s = torch.cos(yaw_before), torch.sin(yaw_before)
    dx = c * step_x - s * step_y
    dy = s * step_x + c * step_y
    increment = torch.stack((dx.sum(-1), dy.sum(-1), turn.sum(-1)), -1)

    # exact first-order sensitivities of the increment to each sample's speed v_k and yaw
    # rate w_k: through that sample's arc, and (for w_k) through the turn of all later arcs
    sin_d = torch.where(small, -turn / 3.0, (safe * torch.cos(safe) - torch.sin(safe)) / safe**2)
    cos_d = torch.where(
        small, 0.5 - turn**2 / 8.0, (safe * torch.sin(safe) - 1.0 + torch.cos(safe)) / safe**2
    )
    total_x, total_y = increment[..., 0], increment[..., 1]
    later_x = total_x[..., None] - torch.cumsum(dx, -1)
    later_y = total_y[..., None] - torch.cumsum(dy, -1)
    arc_v = (dt * sin_ratio, dt * cos_ratio)
    arc_w = (speed * dt * dt * sin_d, speed * dt * dt * cos_d)
    jac_v = torch.stack(
        (c * arc_v[0] - s * arc_v[1], s * arc_v[0] + c * arc_v[1], torch.zeros_like(dt)), -2
    )
    jac_w = torch.stack(
        (
            c * arc_w[0] - s * arc_w[1] - later_y * dt,
            s * arc_w[0] + c * arc_w[1] + later_x * dt,
            dt,
        ),
        -2,
    )  # (..., 3, L)
    return increment, jac_v, jac_w


def _rim_speed_jacobians(
    jac_speed: torch.Tensor, jac_yaw_rate: torch.Tensor, track_width: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Chain rule from ``(v, w)`` to the rim speeds: (..., 3, L) Jacobians of the increment
    w.r.t. each sample's left and right rim speed, with ``v = (v_r + v_l) / 2`` and
    ``w = (v_r - v_l) / D``."""
    return (
        0.5 * jac_speed - jac_yaw_rate / track_width,
        0.5 * jac_speed + jac_yaw_rate / track_width,
    )


def preintegrate_wheel(
    left_speed: torch.Tensor,
    right_speed: torch.Tensor,
    dt: torch.Tensor,
    track_width: float | torch.Tensor,
    speed_sigma: float | torch.Tensor,
    slip: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Planar differential-drive increment and covariance over intervals.

    Each sample holds forward speed ``v = (v_r + v_l)/2`` and yaw rate ``w = (v_r - v_l)/D``
    for ``dt`` (an exact arc); the increment is ``[dx, dy, dyaw]`` in the frame of the
    interval's start. Rim-speed noise: each speed has standard deviation ``speed_sigma /
    f`` (m/s) over the sample, ``f`` the slip factor.

    Args:
        left_speed, right_speed: (..., L) rim speeds, m/s. dt: (..., L) s (0 = padding).
        track_width: D, m. speed_sigma: m/s. slip: (..., L) slip factor in (0, 1] or None.
    Returns:
        increment (..., 3) [m, m, rad] and covariance (..., 3, 3).
    """
    speed, yaw_rate = wheel_speed_and_yaw_rate(left_speed, right_speed, track_width)
    increment, jac_v, jac_w = _wheel_arcs(speed, yaw_rate, dt)
    sigma = torch.as_tensor(speed_sigma, dtype=dt.dtype, device=dt.device)
    if slip is not None:
        sigma = sigma / slip.clamp_min(1e-3)
    var = sigma**2 * torch.ones_like(dt)
    jac_left, jac_right = _rim_speed_jacobians(jac_v, jac_w, track_width)
    cov = torch.zeros(*dt.shape[:-1], 3, 3, dtype=dt.dtype, device=dt.device)
    for jac in (jac_left, jac_right):
        cov = cov + (jac * var[..., None, :]) @ jac.mT
    return increment, cov


def calibrated_wheel_increment(
    left_reading: torch.Tensor,
    right_reading: torch.Tensor,
    dt: torch.Tensor,
    calibration: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differential-drive increment with wheel calibration, and its Jacobian.

    The readings are rim speeds at the nominal radii; with radius ratios (true / nominal)
    ``k_l``, ``k_r`` and track width ``D`` each sample holds ``v = (k_r z_r + k_l z_l) / 2``
    and ``w = (k_r z_r - k_l z_l) / D`` for ``dt`` (exact arcs, as
    :func:`preintegrate_wheel`).

    Args:
        left_reading, right_reading: (..., L) nominal-radius rim speeds, m/s.
        dt: (..., L) s (0 = padding).
        calibration: (..., 3) ``[k_l, k_r, D]`` (dimensionless, dimensionless, m).
    Returns:
        increment (..., 3) ``[dx, dy, dyaw]`` (m, m, rad) in the frame of the interval's
        start, and its Jacobian (..., 3, 3) w.r.t. ``[k_l, k_r, D]``.
    """
    ratio_left = calibration[..., 0:1]
    ratio_right = calibration[..., 1:2]
    track = calibration[..., 2:3]
    speed, yaw_rate = wheel_speed_and_yaw_rate(
        ratio_left * left_reading, ratio_right * right_reading, track
    )
    increment, jac_v, jac_w = _wheel_arcs(speed, yaw_rate, dt)
    # w.r.t. each sample's left / right rim speed
    d_left, d_right = _rim_speed_jacobians(jac_v, jac_w, track[..., None])
    jacobian = torch.stack(
        (
            (d_left * left_reading[..., None, :]).sum(-1),
            (d_right * right_reading[..., None, :]).sum(-1),
            -(jac_w * (yaw_rate / track)[..., None, :]).sum(-1),
        ),
        -1,
    )
    return increment, jacobian


@dataclass
class TangentPreintegrated:
    """IMU increments from GTSAM's tangent-space preintegration (see
    :func:`preintegrate_imu_tangent`), in our ``[p, v, theta]`` order.

    Shapes are (..., ) = the leading dims of the intervals (B, K - 1 for windows).

    Attributes:
        delta_t: (...,) s.
        increment: (..., 9) ``[dp, dv, theta]`` at the linearisation biases: position (m)
            and velocity (m/s) increments in the frame of the interval's start, gravity
            excluded, and the rotation increment as a rotation vector, ``dR = Exp(theta)``.
        bias_jacobian: (..., 9, 6) d increment / d[b_g, b_a]; the bias correction is
            additive in all nine rows, the theta rows included (GTSAM's convention).
        cov_unit_gyro, cov_unit_accel: (..., 9, 9) covariance of the factor's error
            ``[r_p, r_v, r_theta]`` (GTSAM's ``residualCovariance``, reordered) for unit gyro
            and accelerometer noise densities.
        cov_integration: (..., 9, 9) the same for the integration noise (already scaled).
        gyro_bias_lin, accel_bias_lin: (..., 3) biases the increments were computed with.
    """

    delta_t: torch.Tensor
    increment: torch.Tensor
    bias_jacobian: torch.Tensor
    cov_unit_gyro: torch.Tensor
    cov_unit_accel: torch.Tensor
    cov_integration: torch.Tensor
    gyro_bias_lin: torch.Tensor
    accel_bias_lin: torch.Tensor

    def covariance(self, noise: ImuNoise) -> torch.Tensor:
        """Error covariance (..., 9, 9) for the noise densities of ``noise`` (scalars or
        tensors over the leading dims, as :meth:`Preintegrated.covariance`)."""

        def lead(x: torch.Tensor) -> torch.Tensor:
            x = torch.as_tensor(x, dtype=self.delta_t.dtype, device=self.delta_t.device)
            x = x.reshape(*x.shape, *([1] * (self.delta_t.dim() - x.dim())))
            return x[..., None, None]

        return (
            lead(noise.gyro_noise_density) ** 2 * self.cov_unit_gyro
            + lead(noise.accel_noise_density) ** 2 * self.cov_unit_accel
            + self.cov_integration
        )

    def corrected(self, gyro_bias: torch.Tensor, accel_bias: torch.Tensor) -> torch.Tensor:
        """First-order bias-corrected increment (..., 9) for biases (..., 3)."""
        dbias = torch.cat((gyro_bias - self.gyro_bias_lin, accel_bias - self.accel_bias_lin), -1)
        return self.increment + (self.bias_jacobian @ dbias[..., None]).squeeze(-1)


def _d_right_jacobian(phi: torch.Tensor, vec: torch.Tensor) -> torch.Tensor:
    """``d(J_r(phi) vec) / dphi`` (..., 3, 3); ``J_r(phi) = Gamma_1(-phi)``."""
    return -so3.gamma_vector_jacobians(-phi, vec)[0]


def preintegrate_imu_tangent(
    intervals: ImuIntervals,
    gyro_bias: torch.Tensor,
    accel_bias: torch.Tensor,
    integration_sigma: float | torch.Tensor = 0.0,
) -> TangentPreintegrated:
    """GTSAM's tangent-space IMU preintegration, to pose the exact problem GTSAM solves.

    This is an option beside :func:`preintegrate_imu` (exact zero-order hold), not a
    replacement: it reproduces ``gtsam.PreintegratedImuMeasurements`` of the gtsam 4.3
    wheel (``TangentPreintegration``) so that :class:`~msf_torch.backend.factors.GtsamImuFactor`
    has the error and noise of ``gtsam.ImuFactor`` to round-off, and benchmarks compare
    solvers on identical problems. Per sample ``(w_m, a_m, h)``, with ``w = w_m - b_g``,
    ``a = a_m - b_a``, ``R = Exp(theta)``:

        p     += v h + 1/2 R a h^2
        v     += R a h                     (Euler, attitude at the sample's start)
        theta += J_r(theta)^-1 w h         (Euler step in the tangent space)

    The covariance ``P`` of ``[p, v, theta]`` and the bias Jacobians follow the linearised
    step ``P <- A P A^T + B (S_a / h) B^T + C (S_g / h) C^T``, ``P_pp += S_i h``,
    ``H <- A H - [C, B]`` with ``S = sigma^2 I`` the continuous covariances. The stored
    covariance is GTSAM's ``residualCovariance`` ``J P J^T``, ``J = diag(R^T, R^T,
    J_r(theta))`` at the end of the interval, i.e. that of the error
    ``[Jl(phi)^-1 dp, Jl(phi)^-1 dv, phi]`` of the factor. The bias correction is additive
    in the tangent space (theta included), as in GTSAM.

    Each sample is paired with the time it covers, as ``integrateMeasurement(acc, gyro, h)``
    takes it; GTSAM's KITTI example gives the sample at ``t_s`` the span ``t_s - t_{s-1}``.
    Samples with ``dt = 0`` are no-ops (padding).

    Args:
        intervals: samples (..., L, 3) and spans (..., L) s, see :class:`ImuIntervals`.
        gyro_bias, accel_bias: (..., 3) linearisation biases, rad/s and m/s^2.
        integration_sigma: GTSAM's integration noise sigma (m/s^2/sqrt(Hz)), on the
            position rows.
    Returns:
        :class:`TangentPreintegrated` with leading dims (...).
    """
    dt = intervals.dt
    omega = intervals.gyro - gyro_bias[..., None, :]
    force = intervals.accel - accel_bias[..., None, :]
    lead = dt.shape[:-1]
    dtype, device = dt.dtype, dt.device
    eye = so3.identity(dtype, device)
    theta = torch.zeros(*lead, 3, dtype=dtype, device=device)
    position = torch.zeros_like(theta)
    velocity = torch.zeros_like(theta)
    cov = torch.zeros(*lead, 3, 9, 9, dtype=dtype, device=device)  # unit gyro, accel; integration
    jac = torch.zeros(*lead, 9, 6, dtype=dtype, device=device)  # columns [b_g, b_a]
    integration = torch.as_tensor(integration_sigma, dtype=dtype, device=device) ** 2
    for k in range(dt.shape[-1]):
        h = dt[..., k, None, None]
        inv_h = torch.where(h > 0, h, torch.ones_like(h)).reciprocal() * (h > 0)
        rot = so3.exp(theta)
        jr = so3.right_jacobian(theta)
        jr_inv = torch.linalg.inv(jr)
        w_tan = (jr_inv @ omega[..., k, :, None]).squeeze(-1)
        rot_a = (rot @ force[..., k, :, None]).squeeze(-1)
        turn = -rot @ so3.hat(force[..., k, :]) @ jr
        a = torch.eye(9, dtype=dtype, device=device).repeat(*lead, 1, 1)
        a[..., 0:3, 3:6] = eye * h
        a[..., 0:3, 6:9] = turn * (0.5 * h * h)
        a[..., 3:6, 6:9] = turn * h
        a[..., 6:9, 6:9] = eye - jr_inv @ _d_right_jacobian(theta, w_tan) * h
        noise_g = torch.cat((torch.zeros_like(rot), torch.zeros_like(rot), jr_inv * h), -2)
        noise_a = torch.cat((rot * (0.5 * h * h), rot * h, torch.zeros_like(rot)), -2)
        a_cov = a[..., None, :, :]
        cov = a_cov @ cov @ a_cov.mT
        cov[..., 0, :, :] += noise_g @ noise_g.mT * inv_h
        cov[..., 1, :, :] += noise_a @ noise_a.mT * inv_h
        cov[..., 2, 0:3, 0:3] += eye * h
        jac = a @ jac - torch.cat((noise_g, noise_a), -1)
        position = position + velocity * h[..., 0] + 0.5 * rot_a * (h[..., 0] * h[..., 0])
        velocity = velocity + rot_a * h[..., 0]
        theta = theta + w_tan * h[..., 0]
    rot_t = so3.exp(theta).mT
    frame = torch.zeros(*lead, 9, 9, dtype=dtype, device=device)
    frame[..., 0:3, 0:3] = rot_t
    frame[..., 3:6, 3:6] = rot_t
    frame[..., 6:9, 6:9] = so3.right_jacobian(theta)
    frame = frame[..., None, :, :]
    cov = frame @ cov @ frame.mT
    return TangentPreintegrated(
        delta_t=dt.sum(-1),
        increment=torch.cat((position, velocity, theta), -1),
        bias_jacobian=jac,
        cov_unit_gyro=cov[..., 0, :, :],
        cov_unit_accel=cov[..., 1, :, :],
        cov_integration=cov[..., 2, :, :] * integration,
        gyro_bias_lin=gyro_bias,
        accel_bias_lin=accel_bias,
    )
