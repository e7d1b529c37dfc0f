"""IMU measurement model: exact zero-order-hold (ZOH) integration and preintegration.

Between samples the bias-corrected angular rate ``w`` and specific force ``f`` are held
constant (zero-order hold). Over an interval ``dt`` this is integrated exactly:

    R+ = R Exp(w dt)
    v+ = v + g dt   + R Gamma_1(w dt) f dt
    p+ = p + v dt + 1/2 g dt^2 + R Gamma_2(w dt) f dt^2

so motion with constant body rates is reproduced to machine precision. Preintegration
accumulates the same step in the frame of the interval's first sample, independent of the
state there (Forster et al. 2017, with the exact Gamma functions):

    dR_{k+1} = dR_k Exp(w_k dt_k)
    dv_{k+1} = dv_k + dR_k Gamma_1 f_k dt_k
    dp_{k+1} = dp_k + dv_k dt_k + dR_k Gamma_2 f_k dt_k^2

Its error ``[d dp, d dv, d dtheta]`` (order of ``conventions``) follows the linear recursion
``e_{k+1} = A_k e_k + B_k n_k``; the recursion gives the increments' covariance (split into a
unit-gyro and a unit-accel part so noise densities can be learned) and the first-order
bias Jacobians. The ESKF and the LM back end both consume :class:`Preintegrated`.

Noise: continuous white-noise densities ``sigma_g`` (rad/s/sqrt(Hz)) and ``sigma_a``
(m/s^2/sqrt(Hz)); a sample held for ``dt`` has variance ``sigma^2 / dt``.
"""

from __future__ import annotations

__all__ = [
    "ImuNoise",
    "Preintegrated",
    "zoh_step",
    "preintegrate",
    "propagate_nominal",
    "preintegration_residual",
]

from dataclasses import dataclass

import torch

from msf_torch.geometry import so3


@dataclass
class ImuNoise:
    """Continuous-time IMU noise densities, as tensors (broadcast against B).

    Attributes:
        gyro_noise_density: rad/s/sqrt(Hz) (angular random walk).
        accel_noise_density: m/s^2/sqrt(Hz) (velocity random walk).
        gyro_bias_rw_density: rad/s^2/sqrt(Hz) (gyro bias random walk).
        accel_bias_rw_density: m/s^3/sqrt(Hz) (accel bias random walk).
    """

    gyro_noise_density: torch.Tensor
    accel_noise_density: torch.Tensor
    gyro_bias_rw_density: torch.Tensor
    accel_bias_rw_density: torch.Tensor


def zoh_step(
    position: torch.Tensor,
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    accel: torch.Tensor,
    dt: torch.Tensor,
    gravity: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One exact ZOH step of the nominal state.

    Args:
        position, velocity: (..., 3) world, m and m/s.
        rotation: (..., 3, 3) body -> world.
        gyro, accel: (..., 3) bias-corrected body rate (rad/s) and specific force (m/s^2).
        dt: (...,) s.
        gravity: (3,) world gravity, m/s^2.
    Returns:
        position, velocity, rotation after ``dt``.
    """
    dtv = dt[..., None]
    phi = gyro * dtv
    rf = (rotation @ (so3.gamma1(phi) @ accel[..., None])).squeeze(-1)
    rf2 = (rotation @ (so3.gamma2(phi) @ accel[..., None])).squeeze(-1)
    new_position = position + velocity * dtv + 0.5 * gravity * dtv**2 + rf2 * dtv**2
    new_velocity = velocity + gravity * dtv + rf * dtv
    new_rotation = rotation @ so3.exp(phi)
    return new_position, new_velocity, new_rotation


@dataclass
class Preintegrated:
    """IMU increments over intervals, in the frame of each interval's first sample.

    Shapes are (..., ) = any leading dims (B, E for the filter's epochs).

    Attributes:
        delta_t: (...,) s.
        delta_rotation: (..., 3, 3).
        delta_velocity: (..., 3) m/s (gravity excluded).
        delta_position: (..., 3) m (gravity excluded).
        bias_jacobian: (..., 9, 6) d[dp, dv, dtheta] / d[b_g, b_a].
        cov_unit_gyro: (..., 9, 9) covariance of [dp, dv, dtheta] for unit gyro density.
        cov_unit_accel: (..., 9, 9) the same for unit accel density.
        gyro_bias_lin, accel_bias_lin: (..., 3) biases the increments were computed with.
    """

    delta_t: torch.Tensor
    delta_rotation: torch.Tensor
    delta_velocity: torch.Tensor
    delta_position: torch.Tensor
    bias_jacobian: torch.Tensor
    cov_unit_gyro: torch.Tensor
    cov_unit_accel: torch.Tensor
    gyro_bias_lin: torch.Tensor
    accel_bias_lin: torch.Tensor

    def covariance(self, noise: ImuNoise) -> torch.Tensor:
        """Increment covariance (..., 9, 9) for the given noise densities.

        The densities are scalars or tensors over the leading dims: shape (B,) with
        increments (B, E) applies one density per sequence.
        """

        def lead(x: torch.Tensor) -> torch.Tensor:
            x = x.reshape(*x.shape, *([1] * (self.delta_t.dim() - x.dim())))
            return x[..., None, None]

        return (
            lead(noise.gyro_noise_density) ** 2 * self.cov_unit_gyro
            + lead(noise.accel_noise_density) ** 2 * self.cov_unit_accel
        )

    def corrected(
        self, gyro_bias: torch.Tensor, accel_bias: torch.Tensor, index: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """First-order bias correction of the increments.

        Args:
            gyro_bias, accel_bias: (..., 3) new bias estimates.
            index: with increments (B, E), correct only interval ``index`` along E
                (the filter's current epoch); the result then has leading dims (B,).
        Returns:
            delta_rotation (..., 3, 3), delta_velocity (..., 3), delta_position (..., 3).
        """

        def at(x: torch.Tensor) -> torch.Tensor:
            return x if index is None else x[:, index]

        dbias = torch.cat(
            (gyro_bias - at(self.gyro_bias_lin), accel_bias - at(self.accel_bias_lin)), -1
        )
        corr = (at(self.bias_jacobian) @ dbias[..., None]).squeeze(-1)
        delta_rotation = at(self.delta_rotation) @ so3.exp(corr[..., 6:9])
        return (
            delta_rotation,
            at(self.delta_velocity) + corr[..., 3:6],
            at(self.delta_position) + corr[..., 0:3],
        )


def _outer_sum(weight: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``sum_j w_j a_j b_j^T`` over axis -2: weight (..., L), a, b (..., L, 3) -> (..., 3, 3)."""
    return (weight[..., None] * a).mT @ b


def _cross_gram(weight: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``sum_j w_j [a_j]x [b_j]x^T = sum_j w_j ((a_j . b_j) I - b_j a_j^T)``, (..., 3, 3)."""
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    dot = (weight * (a * b).sum(-1)).sum(-1)[..., None, None]
    return dot * eye - _outer_sum(weight, b, a)


def preintegrate(
    gyro: torch.Tensor,
    accel: torch.Tensor,
    dt: torch.Tensor,
    gyro_bias: torch.Tensor,
    accel_bias: torch.Tensor,
    noise_scale: torch.Tensor | None = None,
) -> Preintegrated:
    """Preintegrate IMU samples over the last axis L, vectorised over leading dims.

    Only the rotation prefix product loops over L (one 3x3 product per sample, batched
    over all leading dims); the rest is closed-form sums. Writing ``y_j`` for sample j's
    rotation error input in the interval frame, the error recursion unrolls to

        dtheta_L = R_L^T sum_j y_j
        dv_L     = sum_j h_j - [V_L - V_{j+1}]x y_j
        dp_L     = sum_j (T_L - T_{j+1}) h_j + q_j - [P_L - P_{j+1} - (T_L - T_{j+1}) V_{j+1}]x y_j

    with ``y_j = -R_{j+1} J_r(w_j dt_j) dt_j (db_g + n_g)``,
    ``h_j = -R_j Gamma_1 dt_j (db_a + n_a)``, ``q_j = -R_j Gamma_2 dt_j^2 (db_a + n_a)``
    and ``R, V, P, T`` the prefix rotation, velocity, position and time. Summing these
    per-sample maps gives the bias Jacobians, including the bias's effect on the rotation
    inside each sample (``so3.gamma_vector_jacobians``): they are exact derivatives. For
    the covariance the maps are taken at zeroth order in ``w dt`` (``J_r = Gamma_1 = I``,
    ``Gamma_2 = I/2``), which makes every term rotation-free and the covariance a handful
    of weighted sums; it is exact for non-rotating motion and within O(|w| dt) otherwise
    (1e-5 relative against the exact recursion at 1.2 rad/s and 100 Hz in the tests).
    Samples with ``dt = 0`` are exact no-ops, which is how ragged intervals are padded.

    Args:
        gyro: (..., L, 3) raw angular rate, rad/s.
        accel: (..., L, 3) raw specific force, m/s^2.
        dt: (..., L) hold time of each sample, s.
        gyro_bias, accel_bias: (..., 3) linearisation biases.
        noise_scale: optional (..., L) variance multiplier per sample (e.g. IMU gaps).
    Returns:
        :class:`Preintegrated` with leading dims (...).
    """
    omega = gyro - gyro_bias[..., None, :]
    force = accel - accel_bias[..., None, :]
    dt_col = dt[..., None]
    dt_mat = dt_col[..., None]
    phi = omega * dt_col
    coef = so3.coefficients(phi, derivatives=True)
    step_rot, gam1, gam2 = so3.exp_and_gammas(phi, coef).unbind(-3)
    d_gamma1, d_gamma2 = so3.gamma_vector_jacobians(phi, force, coef)

    steps_first = step_rot.movedim(-3, 0).contiguous()  # (L, ..., 3, 3): contiguous slices
    rotations = [so3.identity(gyro.dtype, gyro.device).expand_as(steps_first[0]).contiguous()]
    for step in steps_first:
        rotations.append(torch.matmul(rotations[-1], step))
    prefix_rot = torch.stack(rotations, -3)  # (..., L + 1, 3, 3)
    rot_start = prefix_rot[..., :-1, :, :]

    # the increments: V, P from the sample-frame steps Gamma_1 f dt, Gamma_2 f dt^2
    dt2 = dt_mat * dt_mat
    gam1_dt = gam1 * dt_mat  # R_j Gamma_1 dt = R_{j+1} J_r dt = -Y_j / (db_g + n_g) = acc_v
    gam2_dt2 = gam2 * dt2
    local_steps = torch.cat((gam1_dt @ force[..., None], gam2_dt2 @ force[..., None]), -1)
    vel_steps, pos_steps = (rot_start @ local_steps).unbind(-1)  # (..., L, 3) each
    vel_after = torch.cumsum(vel_steps, -2)  # V_{j+1}
    vel_before = vel_after - vel_steps  # V_j
    pos_after = torch.cumsum(vel_before * dt_col + pos_steps, -2)  # P_{j+1}
    time_after = torch.cumsum(dt, -1)  # T_{j+1}
    delta_t = time_after[..., -1]
    delta_velocity = vel_after[..., -1, :]
    delta_position = pos_after[..., -1, :]
    delta_rotation = prefix_rot[..., -1, :, :]

    remaining = delta_t[..., None] - time_after  # T_L - T_{j+1}
    vel_lever = delta_velocity[..., None, :] - vel_after  # D_j
    pos_lever = delta_position[..., None, :] - pos_after - remaining[..., None] * vel_after  # C_j

    # Every bias Jacobian is a sum over samples of R_j X_j (X_j 3 x 12 in the sample frame),
    # so they are one contraction over (sample, column of R_j):
    #   sum R_j Gamma_1 dt, sum R_j (rem Gamma_1 dt + Gamma_2 dt^2), and the bias turning the
    #   force inside each sample (d(Gamma_n(w dt) f)/db_g = -dG_n dt) as
    #   sum R_j dG_1 dt^2 and sum R_j (dG_2 dt^3 + rem dG_1 dt^2).
    # The lever terms sum [D_j]x acc_v_j = sum_m G_m W_m (hat(a) = sum_m a_m G_m) with
    # W_m = sum_j D_jm acc_v_j, and the same with C_j, are one contraction over samples.
    rem = remaining[..., None, None]
    in_v = d_gamma1 * dt2
    in_p = d_gamma2 * (dt2 * dt_mat) + rem * in_v
    columns = torch.cat((gam1_dt, rem * gam1_dt + gam2_dt2, in_v, in_p), -1)  # (..., L, 3, 12)
    length = dt.shape[-1]
    lead = dt.shape[:-1]
    sums = rot_start.transpose(-3, -2).reshape(*lead, 3, 3 * length) @ (
        columns.reshape(*lead, 3 * length, 12)
    )
    sum_acc_v, sum_acc_p, sum_in_v, sum_in_p = sums.split(3, -1)
    acc_v = rot_start @ gam1_dt  # (..., L, 3, 3)
    lever_w = torch.cat((vel_lever, pos_lever), -1).mT @ acc_v.flatten(-2)  # (..., 6, 9)
    generators = so3.hat(so3.identity(gyro.dtype, gyro.device))  # (3, 3, 3): G_m[a, i]
    to_hat = generators.permute(1, 0, 2).reshape(3, 9)  # [a, (m, i)]
    levers = to_hat @ lever_w.reshape(*lead, 2, 9, 3)  # sum [D_j]x acc_v_j, [C_j]x acc_v_j
    jac_theta_bg = -delta_rotation.mT @ sum_acc_v
    jac_v_bg = levers[..., 0, :, :] - sum_in_v
    jac_p_bg = levers[..., 1, :, :] - sum_in_p
    jac_v_ba = -sum_acc_v
    jac_p_ba = -sum_acc_p
    zeros = torch.zeros_like(jac_v_ba)
    jac = torch.cat(
        (
            torch.cat((jac_p_bg, jac_p_ba), -1),
            torch.cat((jac_v_bg, jac_v_ba), -1),
            torch.cat((jac_theta_bg, zeros), -1),
        ),
        -2,
    )

    scale = torch.ones_like(dt) if noise_scale is None else noise_scale
    weight = scale * dt  # discrete variance (1/dt) times dt^2 from the maps
    eye = torch.eye(3, dtype=gyro.dtype, device=gyro.device)
    w_sum = weight.sum(-1)[..., None, None]
    gg_tt = w_sum * eye
    gg_vt = -so3.hat((weight[..., None] * vel_lever).sum(-2)) @ delta_rotation
    gg_pt = -so3.hat((weight[..., None] * pos_lever).sum(-2)) @ delta_rotation
    gg_vv = _cross_gram(weight, vel_lever, vel_lever)
    gg_pv = _cross_gram(weight, pos_lever, vel_lever)
    gg_pp = _cross_gram(weight, pos_lever, pos_lever)
    cov_g = torch.cat(
        (
            torch.cat((gg_pp, gg_pv, gg_pt), -1),
            torch.cat((gg_pv.mT, gg_vv, gg_vt), -1),
            torch.cat((gg_pt.mT, gg_vt.mT, gg_tt), -1),
        ),
        -2,
    )
    lever_t = remaining + 0.5 * dt
    aa_vv = w_sum * eye
    aa_pv = (weight * lever_t).sum(-1)[..., None, None] * eye
    aa_pp = (weight * lever_t**2).sum(-1)[..., None, None] * eye
    cov_a = torch.cat(
        (
            torch.cat((aa_pp, aa_pv, zeros), -1),
            torch.cat((aa_pv, aa_vv, zeros), -1),
            torch.cat((zeros, zeros, zeros), -1),
        ),
        -2,
    )
    return Preintegrated(
        delta_t=delta_t,
        delta_rotation=delta_rotation,
        delta_velocity=delta_velocity,
        delta_position=delta_position,
        bias_jacobian=jac,
        cov_unit_gyro=cov_g,
        cov_unit_accel=cov_a,
        gyro_bias_lin=gyro_bias,
        accel_bias_lin=accel_bias,
    )


def propagate_nominal(
    position: torch.Tensor,
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    delta_t: torch.Tensor,
    delta_rotation: torch.Tensor,
    delta_velocity: torch.Tensor,
    delta_position: torch.Tensor,
    gravity: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Apply (bias-corrected) increments to the nominal state at the interval start.

    ``p_j = p_i + v_i dT + 1/2 g dT^2 + R_i dp``, ``v_j = v_i + g dT + R_i dv``,
    ``R_j = R_i dR``. Shapes as :func:`zoh_step` with ``delta_t`` (...,).
    """
    dtv = delta_t[..., None]
    new_position = (
        position
        + velocity * dtv
        + 0.5 * gravity * dtv**2
        + (rotation @ delta_position[..., None]).squeeze(-1)
    )
    new_velocity = velocity + gravity * dtv + (rotation @ delta_velocity[..., None]).squeeze(-1)
    return new_position, new_velocity, rotation @ delta_rotation


def preintegration_residual(
    state_i: torch.Tensor, state_j: torch.Tensor, pre: Preintegrated, gravity: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """IMU preintegration residual between nav states i and j, with Jacobians.

    With the increments bias-corrected to first order at ``b_i`` (:meth:`Preintegrated.corrected`)::

        r_p  = R_i^T (p_j - p_i - v_i dT - 1/2 g dT^2) - dp(b_i)
        r_v  = R_i^T (v_j - v_i - g dT) - dv(b_i)
        r_th = Log(dR(b_i)^T R_i^T R_j)
        r_bg = b_g,j - b_g,i,   r_ba = b_a,j - b_a,i

    stacked ``[r_p, r_v, r_th, r_bg, r_ba]`` (15,), the error-state order of
    :mod:`msf_torch.geometry.conventions` (Forster et al. 2017, eq. 45, reordered). The first
    nine rows are in the frame of state i, like the increments' covariance.

    Args:
        state_i, state_j: (..., 21) flat nav states ``[p, v, R (row-major 9), b_g, b_a]``.
        pre: increments with leading dims (...).
        gravity: (3,) world gravity, m/s^2.
    Returns:
        residual (..., 15), Jacobians w.r.t. the error states of i and j (..., 15, 15).
    """
    p_i, v_i, b_gi, b_ai = (
        state_i[..., 0:3],
        state_i[..., 3:6],
        state_i[..., 15:18],
        state_i[..., 18:21],
    )
    p_j, v_j, b_gj, b_aj = (
        state_j[..., 0:3],
        state_j[..., 3:6],
        state_j[..., 15:18],
        state_j[..., 18:21],
    )
    rot_i = state_i[..., 6:15].reshape(*state_i.shape[:-1], 3, 3)
    rot_j = state_j[..., 6:15].reshape(*state_j.shape[:-1], 3, 3)
    d_t = pre.delta_t[..., None]
    d_rot, d_vel, d_pos = pre.corrected(b_gi, b_ai)
    world_v = v_j - v_i - gravity * d_t
    world_p = p_j - p_i - v_i * d_t - 0.5 * gravity * d_t**2
    local_v = (rot_i.mT @ world_v[..., None]).squeeze(-1)
    local_p = (rot_i.mT @ world_p[..., None]).squeeze(-1)
    rel = rot_i.mT @ rot_j
    r_theta = so3.log(d_rot.mT @ rel)
    residual = torch.cat((local_p - d_pos, local_v - d_vel, r_theta, b_gj - b_gi, b_aj - b_ai), -1)

    lead = residual.shape[:-1]
    jr_inv = torch.linalg.inv(so3.right_jacobian(r_theta))
    bias_jac = pre.bias_jacobian.expand(*lead, 9, 6)
    gyro_bias_change = b_gi - pre.gyro_bias_lin
    theta_bias = (bias_jac[..., 6:9, 0:3] @ gyro_bias_change[..., None]).squeeze(-1)
    d_theta_d_bg = (
        -jr_inv @ so3.exp(r_theta).mT @ so3.right_jacobian(theta_bias) @ bias_jac[..., 6:9, 0:3]
    )

    jac_i = torch.zeros(*lead, 15, 15, dtype=residual.dtype, device=residual.device)
    jac_j = torch.zeros_like(jac_i)
    rot_i_t = rot_i.mT
    jac_i[..., 0:3, 0:3] = -rot_i_t
    jac_i[..., 0:3, 3:6] = -rot_i_t * d_t[..., None]
    jac_i[..., 0:3, 6:9] = so3.hat(local_p)
    jac_i[..., 0:3, 9:15] = -bias_jac[..., 0:3, :]
    jac_i[..., 3:6, 3:6] = -rot_i_t
    jac_i[..., 3:6, 6:9] = so3.hat(local_v)
    jac_i[..., 3:6, 9:15] = -bias_jac[..., 3:6, :]
    jac_i[..., 6:9, 6:9] = -jr_inv @ rel.mT
    jac_i[..., 6:9, 9:12] = d_theta_d_bg
    jac_i[..., 9:15, 9:15] = -torch.eye(6, dtype=residual.dtype, device=residual.device)
    jac_j[..., 0:3, 0:3] = rot_i_t
    jac_j[..., 3:6, 3:6] = rot_i_t
    jac_j[..., 6:9, 6:9] = jr_inv
    jac_j[..., 9:15, 9:15] = torch.eye(6, dtype=residual.dtype, device=residual.device)
    return residual, jac_i, jac_j
