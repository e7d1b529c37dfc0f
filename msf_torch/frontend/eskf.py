"""Batched error-state Kalman filter (ESKF) front end.

State and error state follow ``geometry.conventions``: nominal ``(p, v, R, b_g, b_a)``,
error ``dx = [dp, dv, dtheta, db_g, db_a]`` with ``R = R_hat Exp(dtheta)``.

Per epoch (see ``frontend.schedule``) and for all B sequences at once:

1. Propagate with the epoch's preintegrated IMU increments, bias-corrected to first order
   (``sensors.imu``):  ``x_j = f(x_i, Delta)``, ``P_j = Phi P_i Phi^T + G Sigma_Delta G^T +
   Q_bias``, with

       Phi = [[I, dT I, -R [dp]x, R J_p^g, R J_p^a],
              [0, I,    -R [dv]x, R J_v^g, R J_v^a],
              [0, 0,     dR^T,    J_t^g,   0     ],
              [0, 0,     0,       I,       0     ],
              [0, 0,     0,       0,       I     ]].

2. Update with every measurement that falls on the epoch end, stacked into one vector:
   wheel (4: body velocity + yaw rate), NHC (2), zero velocity (3), GNSS (3), pose (6),
   each a residual from ``sensors``. Each block is chi-square gated on its own innovation;
   the wheel block is also scaled by the slip factor (``frontend.slip``) and skipped below
   a threshold. Joseph-form covariance update, then error injection and the reset
   Jacobian ``I - 1/2 [dtheta]x``.

Everything is a differentiable torch op: gradients reach the noise parameters
(:class:`EskfNoise`). The only Python loop on the hot path is over epochs.
"""

from __future__ import annotations

__all__ = ["EskfNoise", "EskfResult", "run_eskf", "SENSORS"]

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.gating import chi2_threshold
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.schedule import Schedule, build_schedule
from msf_torch.frontend.slip import slip_factor
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import ERROR_STATE_DIM, gravity_world
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sensors.gnss import gnss_residual
from msf_torch.sensors.imu import ImuNoise, Preintegrated, preintegrate, propagate_nominal
from msf_torch.sensors.pose import pose_residual
from msf_torch.sensors.vehicle import nonholonomic_residual, zero_velocity_residual
from msf_torch.sensors.wheel import wheel_residual
from msf_torch.types import NavState, Sequence, Trajectory

SENSORS = ("wheel", "nhc", "zupt", "gnss", "pose")
_DIMS = {"wheel": 4, "nhc": 2, "zupt": 3, "gnss": 3, "pose": 6}


@dataclass
class EskfNoise:
    """Noise parameters as tensors, shape () or (B,), so they can be learned.

    Attributes (units in the names of the matching :class:`EskfConfig` fields):
        imu: IMU noise densities.
        wheel_speed_sigma, wheel_lateral_sigma, wheel_yaw_rate_sigma: m/s, m/s, rad/s.
        nhc_sigma, zupt_sigma: m/s.
        gnss_sigma_scale: multiplier on each fix's sigma (1 = as given).
    """

    imu: ImuNoise
    wheel_speed_sigma: torch.Tensor
    wheel_lateral_sigma: torch.Tensor
    wheel_yaw_rate_sigma: torch.Tensor
    nhc_sigma: torch.Tensor
    zupt_sigma: torch.Tensor
    gnss_sigma_scale: torch.Tensor

    @classmethod
    def from_config(cls, cfg: EskfConfig, dtype=torch.float64, device=None) -> EskfNoise:
        """Noise tensors (scalars) from a config."""

        def t(x: float) -> torch.Tensor:
            return torch.tensor(x, dtype=dtype, device=device)

        return cls(
            imu=ImuNoise(
                t(cfg.gyro_noise_density),
                t(cfg.accel_noise_density),
                t(cfg.gyro_bias_rw_density),
                t(cfg.accel_bias_rw_density),
            ),
            wheel_speed_sigma=t(cfg.wheel_speed_sigma_mps),
            wheel_lateral_sigma=t(cfg.wheel_lateral_sigma_mps),
            wheel_yaw_rate_sigma=t(cfg.wheel_yaw_rate_sigma_radps),
            nhc_sigma=t(cfg.nhc_sigma_mps),
            zupt_sigma=t(cfg.zupt_sigma_mps),
            gnss_sigma_scale=t(1.0),
        )


@dataclass
class EskfResult:
    """Per-epoch output of :func:`run_eskf`; index 0 is the initial state at ``t_start``.

    Attributes:
        names: sequence names (B).
        t: (B, E + 1) s.
        mask: (B, E + 1) bool, real epochs.
        position, velocity: (B, E + 1, 3) world, m and m/s.
        rotation: (B, E + 1, 3, 3) body -> world.
        gyro_bias, accel_bias: (B, E + 1, 3).
        covariance: (B, E + 1, 15, 15) error-state covariance.
        slip_factor: (B, E + 1) in [0, 1], held between wheel epochs.
        present, accepted: sensor -> (B, E + 1) bool (a measurement was there / was fused).
        nis: sensor -> (B, E + 1) normalised innovation squared (0 where absent).
        gap: (B, E + 1) bool, an IMU gap was bridged in this epoch.
        wheel_epoch: (B, E + 1) bool, a wheel reading arrived (slip factor evaluated).
    """

    names: list[str]
    t: torch.Tensor
    mask: torch.Tensor
    position: torch.Tensor
    velocity: torch.Tensor
    rotation: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor
    covariance: torch.Tensor
    slip_factor: torch.Tensor
    present: dict[str, torch.Tensor] = field(default_factory=dict)
    accepted: dict[str, torch.Tensor] = field(default_factory=dict)
    nis: dict[str, torch.Tensor] = field(default_factory=dict)
    gap: torch.Tensor | None = None
    wheel_epoch: torch.Tensor | None = None

    def trajectory(self) -> Trajectory:
        """Estimated poses as a :class:`~msf_torch.types.Trajectory` (B, E + 1)."""
        return Trajectory(
            t=self.t,
            position=self.position,
            quaternion=matrix_to_quat(self.rotation),
            mask=self.mask,
        )

    def counts(self) -> dict[str, dict[str, list[int]]]:
        """Per sensor: present / accepted / rejected counts per sequence."""
        out = {}
        for key in self.present:
            present = (self.present[key] & self.mask).sum(-1)
            accepted = (self.accepted[key] & self.mask).sum(-1)
            out[key] = {
                "present": present.tolist(),
                "accepted": accepted.tolist(),
                "rejected": (present - accepted).tolist(),
            }
        return out


def _preintegrate_chunked(
    sched: Schedule, bias_g: torch.Tensor, bias_a: torch.Tensor, max_samples: int = 65536
) -> Preintegrated:
    """Preintegrate all epochs in chunks along E (bounded memory, cache-friendly)."""
    batch, n_epochs, n_slots = sched.dt.shape
    step = max(1, max_samples // max(1, batch * n_slots))
    parts = []
    for start in range(0, n_epochs, step):
        sl = slice(start, start + step)
        count = sched.dt[:, sl].shape[1]
        parts.append(
            preintegrate(
                sched.gyro[:, sl],
                sched.accel[:, sl],
                sched.dt[:, sl],
                bias_g[:, None, :].expand(batch, count, 3),
                bias_a[:, None, :].expand(batch, count, 3),
                sched.noise_scale[:, sl],
            )
        )
    if len(parts) == 1:
        return parts[0]
    names = Preintegrated.__dataclass_fields__.keys()
    return Preintegrated(**{k: torch.cat([getattr(p, k) for p in parts], 1) for k in names})


def _transition(rotation, d_rot, d_vel, d_pos, delta_t, jac):
    """Phi (B, 15, 15) of one epoch; see the module docstring."""
    batch = rotation.shape[0]
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand(batch, 3, 3)
    zero = torch.zeros_like(eye)
    jac_p = rotation @ jac[:, 0:3]  # bias Jacobians of dp, dv rotated into the world
    jac_v = rotation @ jac[:, 3:6]
    rows = (
        torch.cat((eye, delta_t[:, None, None] * eye, -rotation @ so3.hat(d_pos), jac_p), -1),
        torch.cat((zero, eye, -rotation @ so3.hat(d_vel), jac_v), -1),
        torch.cat((zero, zero, d_rot.mT, jac[:, 6:9, 0:3], zero), -1),
    )
    top = torch.cat(rows, -2)
    bottom = torch.eye(ERROR_STATE_DIM, dtype=rotation.dtype, device=rotation.device)[9:]
    return torch.cat((top, bottom.expand(batch, 6, ERROR_STATE_DIM)), -2)


def _process_noise(rotation, pre_cov, delta_t, noise: EskfNoise):
    """G Sigma_Delta G^T + bias random walk, (B, 15, 15)."""
    batch = rotation.shape[0]
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand(batch, 3, 3)
    zero = torch.zeros_like(eye)
    g = torch.cat(
        (
            torch.cat((rotation, zero, zero), -1),
            torch.cat((zero, rotation, zero), -1),
            torch.cat((zero, zero, eye), -1),
        ),
        -2,
    )
    q_nav = g @ pre_cov @ g.mT
    var_g = (noise.imu.gyro_bias_rw_density**2).expand(batch) * delta_t
    var_a = (noise.imu.accel_bias_rw_density**2).expand(batch) * delta_t
    q_bias = torch.diag_embed(
        torch.cat((var_g[:, None].expand(batch, 3), var_a[:, None].expand(batch, 3)), -1)
    )
    zeros = torch.zeros(batch, 9, 6, dtype=rotation.dtype, device=rotation.device)
    return torch.cat((torch.cat((q_nav, zeros), -1), torch.cat((zeros.mT, q_bias), -1)), -2)


def _inject(state: NavState, dx: torch.Tensor) -> NavState:
    return NavState(
        position=state.position + dx[:, 0:3],
        velocity=state.velocity + dx[:, 3:6],
        rotation=state.rotation @ so3.exp(dx[:, 6:9]),
        gyro_bias=state.gyro_bias + dx[:, 9:12],
        accel_bias=state.accel_bias + dx[:, 12:15],
    )


def _reset_jacobian(dtheta: torch.Tensor) -> torch.Tensor:
    batch = dtheta.shape[0]
    g = torch.eye(ERROR_STATE_DIM, dtype=dtheta.dtype, device=dtheta.device).repeat(batch, 1, 1)
    block = torch.eye(3, dtype=dtheta.dtype, device=dtheta.device) - 0.5 * so3.hat(dtheta)
    top = torch.cat((g[:, 6:9, 0:6], block, g[:, 6:9, 9:15]), -1)
    return torch.cat((g[:, 0:6], top, g[:, 9:15]), -2)


def run_eskf(
    seq: Sequence,
    cfg: EskfConfig | None = None,
    noise: EskfNoise | None = None,
    progress: Callable[[int], None] | None = None,
) -> EskfResult:
    """Run the ESKF over a batch of sequences.

    Args:
        seq: B sequences (IMU required; wheel, GNSS, poses optional), float64 advised.
        cfg: settings; defaults to :class:`EskfConfig()`.
        noise: noise tensors (learnable); defaults to ``EskfNoise.from_config(cfg)``.
        progress: optional callback called with the number of epochs done (progress bars).
    Returns:
        :class:`EskfResult` with (B, E + 1) per-epoch fields.

    Example:
        >>> from msf_torch.sim import SimConfig, simulate_run
        >>> run = simulate_run(SimConfig(duration_s=5.0), seed=0)
        >>> result = run_eskf(run.sequence)
        >>> result.position.shape[0]
        1
    """
    cfg = cfg or EskfConfig()
    dtype, device = seq.imu.t.dtype, seq.imu.t.device
    noise = noise or EskfNoise.from_config(cfg, dtype, device)
    sched = build_schedule(seq, cfg)
    state, cov = initial_state(seq, cfg)
    pre = _preintegrate_chunked(sched, state.gyro_bias, state.accel_bias)
    pre_cov = pre.covariance(
        ImuNoise(
            *(
                x[..., None] if x.dim() == 1 else x
                for x in (
                    noise.imu.gyro_noise_density,
                    noise.imu.accel_noise_density,
                    noise.imu.gyro_bias_rw_density,
                    noise.imu.accel_bias_rw_density,
                )
            )
        )
    )
    gravity = gravity_world(cfg.gravity_mps2, dtype, device)
    batch, n_epochs = sched.t_end.shape
    present = {
        "wheel": sched.wheel_mask,
        "nhc": sched.nhc_mask,
        "zupt": sched.zupt_mask,
        "gnss": sched.gnss_mask,
        "pose": sched.pose_mask,
    }
    active = [k for k in SENSORS if bool(present[k].any())]
    dims = dict(_DIMS)
    if not cfg.wheel_yaw_rate_update:
        dims["wheel"] = 3  # the yaw-rate row then only feeds the slip factor
    thresholds = {k: chi2_threshold(dims[k], cfg.gate_probability) for k in SENSORS}
    if not cfg.gate_pseudo_measurements:
        thresholds["nhc"] = thresholds["zupt"] = math.inf
    wheel_lever = torch.as_tensor(cfg.wheel_lever_arm_m, dtype=dtype, device=device)
    nhc_lever = torch.as_tensor(cfg.nhc_lever_arm_m, dtype=dtype, device=device)
    gnss_lever = torch.as_tensor(cfg.gnss_lever_arm_m, dtype=dtype, device=device)
    ones = torch.ones(batch, dtype=dtype, device=device)

    def per_seq(x: torch.Tensor) -> torch.Tensor:
        return x.expand(batch) if x.dim() == 0 else x

    slip = ones.clone()
    streak = {k: torch.zeros(batch, dtype=torch.long, device=device) for k in ("gnss", "pose")}
    last_wheel_t = sched.t_start.clone()
    out = {k: [] for k in ("p", "v", "R", "bg", "ba", "P", "slip")}
    acc_out = {k: [] for k in SENSORS}
    nis_out = {k: [] for k in SENSORS}

    def record(st: NavState, p_cov, slip_now):
        out["p"].append(st.position)
        out["v"].append(st.velocity)
        out["R"].append(st.rotation)
        out["bg"].append(st.gyro_bias)
        out["ba"].append(st.accel_bias)
        out["P"].append(p_cov)
        out["slip"].append(slip_now)

    zeros_b = torch.zeros(batch, dtype=dtype, device=device)
    false_b = torch.zeros(batch, dtype=torch.bool, device=device)
    record(state, cov, slip)
    for k in SENSORS:
        acc_out[k].append(false_b)
        nis_out[k].append(zeros_b)

    for e in range(n_epochs):
        # --- propagation -------------------------------------------------------------
        jac = pre.bias_jacobian[:, e]
        dbias = torch.cat(
            (
                state.gyro_bias - pre.gyro_bias_lin[:, e],
                state.accel_bias - pre.accel_bias_lin[:, e],
            ),
            -1,
        )
        corr = (jac @ dbias[..., None]).squeeze(-1)
        d_rot = pre.delta_rotation[:, e] @ so3.exp(corr[:, 6:9])
        d_vel = pre.delta_velocity[:, e] + corr[:, 3:6]
        d_pos = pre.delta_position[:, e] + corr[:, 0:3]
        delta_t = pre.delta_t[:, e]
        phi = _transition(state.rotation, d_rot, d_vel, d_pos, delta_t, jac)
        q = _process_noise(state.rotation, pre_cov[:, e], delta_t, noise)
        position, velocity, rotation = propagate_nominal(
            state.position, state.velocity, state.rotation, delta_t, d_rot, d_vel, d_pos, gravity
        )
        state = NavState(position, velocity, rotation, state.gyro_bias, state.accel_bias)
        cov = phi @ cov @ phi.mT + q

        # --- measurement blocks ------------------------------------------------------
        residuals, jacobians, noises, masks, names = [], [], [], [], []
        gyro_end = sched.gyro_end[:, e]
        if "wheel" in active:
            r, h = wheel_residual(
                state.velocity,
                state.rotation,
                gyro_end,
                state.gyro_bias,
                sched.wheel_left[:, e],
                sched.wheel_right[:, e],
                cfg.wheel_track_m,
                wheel_lever,
            )
            var = torch.stack(
                (
                    per_seq(noise.wheel_speed_sigma) ** 2,
                    per_seq(noise.wheel_lateral_sigma) ** 2,
                    per_seq(noise.wheel_lateral_sigma) ** 2,
                    per_seq(noise.wheel_yaw_rate_sigma) ** 2,
                ),
                -1,
            )
            here = sched.wheel_mask[:, e]
            if cfg.slip_detection:
                innov = torch.diagonal(h @ cov @ h.mT, dim1=-2, dim2=-1) + var
                new_slip = slip_factor(
                    r,
                    innov,
                    slip,
                    sched.t_end[:, e] - last_wheel_t,
                    cfg.slip_sensitivity,
                    cfg.slip_recovery_per_s,
                )
                slip = torch.where(here, new_slip, slip)
                var = var / slip[:, None].clamp_min(1e-3) ** 2
                here = here & (slip >= cfg.slip_skip_below)
            last_wheel_t = torch.where(sched.wheel_mask[:, e], sched.t_end[:, e], last_wheel_t)
            rows_used = dims["wheel"]
            r, h, var = r[:, :rows_used], h[:, :rows_used], var[:, :rows_used]
            residuals.append(r)
            jacobians.append(h)
            noises.append(var)
            masks.append(here)
            names.append("wheel")
        if "nhc" in active:
            r, h = nonholonomic_residual(
                state.velocity, state.rotation, gyro_end, state.gyro_bias, nhc_lever
            )
            residuals.append(r)
            jacobians.append(h)
            noises.append((per_seq(noise.nhc_sigma) ** 2)[:, None].expand(batch, 2))
            masks.append(sched.nhc_mask[:, e])
            names.append("nhc")
        if "zupt" in active:
            r, h = zero_velocity_residual(state.velocity)
            residuals.append(r)
            jacobians.append(h)
            noises.append((per_seq(noise.zupt_sigma) ** 2)[:, None].expand(batch, 3))
            masks.append(sched.zupt_mask[:, e])
            names.append("zupt")
        if "gnss" in active:
            r, h = gnss_residual(
                state.position, state.rotation, gnss_lever, sched.gnss_position[:, e]
            )
            sig = sched.gnss_sigma[:, e] * per_seq(noise.gnss_sigma_scale)[:, None]
            residuals.append(r)
            jacobians.append(h)
            noises.append(sig**2)
            masks.append(sched.gnss_mask[:, e])
            names.append("gnss")
        pose_block = None
        if "pose" in active:
            r, h = pose_residual(
                state.position, state.rotation, sched.pose_position[:, e], sched.pose_rotation[:, e]
            )
            residuals.append(r)
            jacobians.append(h)
            noises.append(torch.zeros(batch, 6, dtype=dtype, device=device))
            pose_block = sched.pose_covariance[:, e]
            masks.append(sched.pose_mask[:, e])
            names.append("pose")

        candidate = torch.stack(masks, -1) if masks else None
        if candidate is None or not bool(candidate.any()):
            for k in SENSORS:
                acc_out[k].append(false_b)
                nis_out[k].append(zeros_b)
            record(state, cov, slip)
            if progress is not None:
                progress(e + 1)
            continue
        r_all = torch.cat(residuals, -1)
        h_all = torch.cat(jacobians, -2)
        r_cov = torch.diag_embed(torch.cat(noises, -1))
        if pose_block is not None:
            r_cov = r_cov.clone()
            r_cov[:, -6:, -6:] = pose_block
        s_all = h_all @ cov @ h_all.mT + r_cov
        row_masks, offset = [], 0
        accepted_now = {}
        nis_now = {}
        for name, m in zip(names, masks, strict=True):
            d = dims[name]
            blk = slice(offset, offset + d)
            s_blk = s_all[:, blk, blk]
            s_safe = torch.where(m[:, None, None], s_blk, torch.eye(d, dtype=dtype, device=device))
            chol = torch.linalg.cholesky(s_safe)
            white = torch.linalg.solve_triangular(chol, r_all[:, blk, None], upper=False)
            nis = torch.where(m, (white**2).sum((-2, -1)), zeros_b)
            ok = m & (nis < thresholds[name]) if math.isfinite(thresholds[name]) else m
            if name in streak:
                # an absolute sensor rejected again and again means the state has drifted
                # away, not that every fix is bad: let it back in rather than diverge
                ok = ok | (m & (streak[name] >= cfg.gate_reopen_after))
                streak[name] = torch.where(m, torch.where(ok, 0, streak[name] + 1), streak[name])
            accepted_now[name] = ok
            nis_now[name] = nis
            row_masks.append(ok[:, None].expand(batch, d))
            offset += d
        rows = torch.cat(row_masks, -1).to(dtype)
        h_m = h_all * rows[..., None]
        r_m = r_all * rows
        s_m = s_all * (rows[:, :, None] * rows[:, None, :]) + torch.diag_embed(1.0 - rows)
        chol = torch.linalg.cholesky(s_m)
        gain = torch.cholesky_solve(h_m @ cov, chol).mT  # (B, 15, M)
        dx = -(gain @ r_m[..., None]).squeeze(-1)
        ikh = torch.eye(ERROR_STATE_DIM, dtype=dtype, device=device) - gain @ h_m
        r_cov_m = r_cov * (rows[:, :, None] * rows[:, None, :])
        cov = ikh @ cov @ ikh.mT + gain @ r_cov_m @ gain.mT
        state = _inject(state, dx)
        reset = _reset_jacobian(dx[:, 6:9])
        cov = reset @ cov @ reset.mT
        cov = 0.5 * (cov + cov.mT)
        for k in SENSORS:
            acc_out[k].append(accepted_now.get(k, false_b))
            nis_out[k].append(nis_now.get(k, zeros_b))
        record(state, cov, slip)
        if progress is not None:
            progress(e + 1)

    mask = torch.cat((torch.ones(batch, 1, dtype=torch.bool, device=device), sched.epoch_mask), 1)
    t = torch.cat((sched.t_start[:, None], sched.t_end), 1)
    present_out = {k: torch.cat((false_b[:, None], present[k]), 1) for k in SENSORS}
    gap = torch.cat((false_b[:, None], sched.gap), 1)
    return EskfResult(
        names=list(seq.names),
        t=t,
        mask=mask,
        position=torch.stack(out["p"], 1),
        velocity=torch.stack(out["v"], 1),
        rotation=torch.stack(out["R"], 1),
        gyro_bias=torch.stack(out["bg"], 1),
        accel_bias=torch.stack(out["ba"], 1),
        covariance=torch.stack(out["P"], 1),
        slip_factor=torch.stack(out["slip"], 1),
        present=present_out,
        accepted={k: torch.stack(v, 1) for k, v in acc_out.items()},
        nis={k: torch.stack(v, 1) for k, v in nis_out.items()},
        gap=gap,
        wheel_epoch=present_out["wheel"],
    )
