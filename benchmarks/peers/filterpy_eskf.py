"""A per-IMU-sample error-state EKF on ``filterpy.kalman.KalmanFilter`` (numpy peer).

The straightforward way to write our front end's model: one Python step per IMU sample,
``filterpy``'s ``predict`` / ``update`` for the 15-dim error state, numpy for the rest.
It is a speed peer for ``benchmarks/frontend_speed.py``; it also returns its trajectory so
its accuracy can be scored the same way as ours.

Model (as ``msf_torch.frontend.eskf``; conventions of ``msf_torch.geometry.conventions``):

* nominal state ``p, v, R, b_g, b_a``; error ``dx = [dp, dv, dtheta, db_g, db_a]`` with
  ``R = R_hat Exp(dtheta)`` and world gravity ``[0, 0, -g]``;
* time line (the rule of ``msf_torch.frontend.schedule``): update times are the GNSS fixes
  after the first IMU sample and the last sample; with the NHC on, every update time
  carries an NHC pseudo-measurement and evenly spaced update times are inserted wherever
  consecutive ones (from the first sample on) are over ``1 / nhc_rate_hz`` s apart. The
  IMU sample times are merged with the update times; each piece holds the latest IMU
  sample at or before its start (zero-order hold), so updates happen at their own time;
* per piece of length ``dt`` with ``w = gyro - b_g``, ``f = accel - b_a``
  (Euler integration of the nominal state, first-order error dynamics):

      a = R f + g,  p <- p + v dt + a dt^2 / 2,  v <- v + a dt,  R <- R Exp(w dt)
      F = I + [[0, I dt, -R[f]x dt^2/2, 0, -R dt^2/2],
               [0, 0,    -R[f]x dt,     0, -R dt    ],
               [0, 0,  Exp(w dt)^T - I, -I dt, 0    ],  0, 0]
      Q = diag(0, sa^2 dt, sg^2 dt, sbg^2 dt, sba^2 dt)   (x gap_scale for IMU gaps)

  then ``kf.F = F; kf.Q = Q; kf.predict()`` (``filterpy``: ``P <- F P F^T + Q``);
* GNSS update: ``H = [I 0 0 0 0]``, ``R = diag(sigma^2)``, measurement ``z - p_hat`` of
  ``dp``; chi-square gated at ``gate_probability`` with the same re-open rule as ours
  (a fix passes after ``gate_reopen_after`` consecutive rejections);
* NHC update (every epoch, so at least ``nhc_rate_hz``): lateral and vertical body
  velocity ``[R^T v + [w]x l]_{y,z} = 0``, ``H`` rows ``[0, R^T, [v_b]x, [l]x, 0]_{y,z}``
  (``msf_torch.sensors.vehicle``), ``R = nhc_sigma^2 I``, not gated;
* after the updates of an epoch: error injection (``p += dp``, ``v += dv``,
  ``R <- R Exp(dtheta)``, ``b += db``), covariance reset ``G P G^T`` with
  ``G = I - [dtheta]x / 2`` on the rotation block, and ``kf.x = 0``.

Differences from ours: Euler instead of exact zero-order-hold integration of each sample
and no position part in ``Q`` (both O(dt^2) per sample at 100 Hz); sequential instead of
stacked GNSS/NHC updates in the same epoch (equal for a linear update; gating of both uses
the prior here too since GNSS goes first and NHC is not gated).

Usage::

    from benchmarks.peers.filterpy_eskf import inputs_from_sequence, run_filterpy_eskf
    out = run_filterpy_eskf(**inputs_from_sequence(seq, cfg), t_stop=None)
"""

from __future__ import annotations

__all__ = ["run_filterpy_eskf", "inputs_from_sequence"]

import math
import time
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2


def _hat(x: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def _exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, (3,) -> (3, 3)."""
    theta2 = float(phi @ phi)
    skew = _hat(phi)
    if theta2 < 1e-12:
        a = 1.0 - theta2 / 6.0
        b = 0.5 - theta2 / 24.0
    else:
        theta = math.sqrt(theta2)
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta2
    return np.eye(3) + a * skew + b * (skew @ skew)


def _merge(times: np.ndarray, tol: float) -> np.ndarray:
    if times.size == 0:
        return times
    times = np.sort(times)
    return times[np.concatenate(([True], np.diff(times) > tol))]


def _fill_gaps(times: np.ndarray, max_step: float) -> np.ndarray:
    """Insert evenly spaced times wherever consecutive ``times`` are over ``max_step`` apart."""
    out = [times[:1]]
    for a, b in zip(times[:-1], times[1:], strict=True):
        pieces = max(int(np.ceil((b - a) / max_step - 1e-9)), 1)
        out.append(a + (b - a) / pieces * np.arange(1, pieces + 1))
    return np.concatenate(out)


def inputs_from_sequence(seq: Any, cfg: Any) -> dict[str, Any]:
    """Arguments of :func:`run_filterpy_eskf` from a B = 1 ``Sequence`` and ``EskfConfig``.

    The initial state and covariance come from ``msf_torch.frontend.init.initial_state``
    (the same as our filter's); GNSS sigmas missing in the data take ``cfg.gnss_sigma_m``.
    """
    from msf_torch.frontend.init import initial_state

    if seq.batch_size != 1:
        raise ValueError("the filterpy peer runs one sequence (B = 1)")
    state, cov = initial_state(seq, cfg)
    imu_mask = seq.imu.mask[0].numpy()
    out: dict[str, Any] = {
        "imu_t": seq.imu.t[0].numpy()[imu_mask],
        "imu_gyro": seq.imu.gyro[0].numpy()[imu_mask],
        "imu_acc": seq.imu.accel[0].numpy()[imu_mask],
        "gnss_t": np.zeros(0),
        "gnss_pos": np.zeros((0, 3)),
        "gnss_sigma": np.zeros((0, 3)),
    }
    if seq.gnss is not None:
        gm = seq.gnss.mask[0].numpy()
        sigma = seq.gnss.sigma[0].numpy()[gm]
        default = np.broadcast_to(np.asarray(cfg.gnss_sigma_m, dtype=float), sigma.shape)
        out["gnss_t"] = seq.gnss.t[0].numpy()[gm]
        out["gnss_pos"] = seq.gnss.position[0].numpy()[gm]
        out["gnss_sigma"] = np.where(np.isfinite(sigma), sigma, default)
    out["init"] = {
        "position": state.position[0].numpy().copy(),
        "velocity": state.velocity[0].numpy().copy(),
        "rotation": state.rotation[0].numpy().copy(),
        "gyro_bias": state.gyro_bias[0].numpy().copy(),
        "accel_bias": state.accel_bias[0].numpy().copy(),
        "covariance": cov[0].numpy().copy(),
    }
    use_nhc = cfg.nhc == "on" or (cfg.nhc == "auto" and seq.wheel is None)
    out["params"] = {
        "gyro_noise_density": cfg.gyro_noise_density,
        "accel_noise_density": cfg.accel_noise_density,
        "gyro_bias_rw_density": cfg.gyro_bias_rw_density,
        "accel_bias_rw_density": cfg.accel_bias_rw_density,
        "gravity_mps2": cfg.gravity_mps2,
        "nhc": use_nhc,
        "nhc_rate_hz": cfg.nhc_rate_hz,
        "nhc_sigma_mps": cfg.nhc_sigma_mps,
        "nhc_lever_arm_m": list(cfg.nhc_lever_arm_m),
        "imu_gap_s": cfg.imu_gap_s,
        "imu_gap_noise_scale": cfg.imu_gap_noise_scale,
        "gate_probability": cfg.gate_probability,
        "gate_reopen_after": cfg.gate_reopen_after,
        "time_tolerance_s": cfg.time_tolerance_s,
    }
    return out


def run_filterpy_eskf(
    imu_t: np.ndarray,
    imu_gyro: np.ndarray,
    imu_acc: np.ndarray,
    gnss_t: np.ndarray,
    gnss_pos: np.ndarray,
    gnss_sigma: np.ndarray,
    init: dict[str, np.ndarray],
    params: dict[str, Any],
    t_stop: float | None = None,
) -> dict[str, Any]:
    """Run the per-sample filterpy ESKF.

    Args:
        imu_t (N,), imu_gyro (N, 3) rad/s, imu_acc (N, 3) m/s^2: IMU samples.
        gnss_t (M,), gnss_pos (M, 3) m, gnss_sigma (M, 3) m: GNSS fixes.
        init: ``position``, ``velocity``, ``rotation``, ``gyro_bias``, ``accel_bias``,
            ``covariance`` (15, 15) at ``imu_t[0]``.
        params: noise densities and settings (keys as written by
            :func:`inputs_from_sequence`).
        t_stop: stop at this many seconds after the first IMU sample (a prefix); None = all.

    Returns:
        dict with ``t`` (K,) times after each piece, ``position`` (K, 3), ``wall_s`` (time
        line building + filtering), ``imu_samples`` (IMU samples consumed), ``pieces``,
        ``gnss_updates``, ``gnss_rejected``, ``nhc_updates``, ``duration_s``.
    """
    start = time.perf_counter()
    tol = float(params["time_tolerance_s"])
    imu_t = np.asarray(imu_t, dtype=float)
    t0 = float(imu_t[0])
    t_last = float(imu_t[-1])
    if t_stop is not None:
        t_last = min(t_last, t0 + float(t_stop))
    n_used = int(np.searchsorted(imu_t, t_last + tol, side="right"))
    imu_t = imu_t[:n_used]
    gyro_all = np.asarray(imu_gyro, dtype=float)[:n_used]
    acc_all = np.asarray(imu_acc, dtype=float)[:n_used]

    # --- time line (the same rule as msf_torch.frontend.schedule) ---------------------
    gnss_t = np.asarray(gnss_t, dtype=float)
    keep = (gnss_t > t0 + tol) & (gnss_t <= t_last + tol)
    g_t, g_pos, g_sig = gnss_t[keep], np.asarray(gnss_pos)[keep], np.asarray(gnss_sigma)[keep]
    updates = _merge(np.concatenate((g_t, [t_last])), tol)
    if params["nhc"]:  # NHC at every epoch; epochs added where updates are too far apart
        updates = _fill_gaps(np.concatenate(([t0], updates)), 1.0 / float(params["nhc_rate_hz"]))
        updates = updates[1:]
    bounds = _merge(np.concatenate((imu_t, updates)), tol)
    piece_start = bounds[:-1]
    piece_dt = np.diff(bounds)
    sample = np.searchsorted(imu_t, piece_start + tol, side="right") - 1
    spacing = np.diff(imu_t, append=imu_t[-1])
    gap = spacing[sample] > float(params["imu_gap_s"])
    piece_end = bounds[1:]
    # which update (if any) ends each piece
    upd_idx = np.searchsorted(updates, piece_end - tol, side="left")
    upd_idx = np.clip(upd_idx, 0, updates.size - 1)
    ends_update = np.abs(updates[upd_idx] - piece_end) <= tol
    gnss_at = np.full(updates.size, -1, dtype=np.int64)
    if g_t.size:
        j = np.clip(np.searchsorted(g_t, updates), 0, g_t.size - 1)
        jl = np.clip(j - 1, 0, g_t.size - 1)
        best = np.where(np.abs(g_t[jl] - updates) <= np.abs(g_t[j] - updates), jl, j)
        gnss_at = np.where(np.abs(g_t[best] - updates) <= tol, best, -1)
    nhc_at = np.full(updates.size, bool(params["nhc"]))

    # --- filter ----------------------------------------------------------------------
    sg2 = float(params["gyro_noise_density"]) ** 2
    sa2 = float(params["accel_noise_density"]) ** 2
    sbg2 = float(params["gyro_bias_rw_density"]) ** 2
    sba2 = float(params["accel_bias_rw_density"]) ** 2
    gap_scale = float(params["imu_gap_noise_scale"])
    gravity = np.array([0.0, 0.0, -float(params["gravity_mps2"])])
    nhc_var = float(params["nhc_sigma_mps"]) ** 2
    lever = np.asarray(params["nhc_lever_arm_m"], dtype=float)
    lever_hat = _hat(lever)
    gate = (
        math.inf
        if float(params["gate_probability"]) >= 1.0
        else float(chi2.ppf(float(params["gate_probability"]), 3))
    )
    reopen = int(params["gate_reopen_after"])

    p = np.array(init["position"], dtype=float)
    v = np.array(init["velocity"], dtype=float)
    rot = np.array(init["rotation"], dtype=float)
    bg = np.array(init["gyro_bias"], dtype=float)
    ba = np.array(init["accel_bias"], dtype=float)

    kf = KalmanFilter(dim_x=15, dim_z=3)
    kf.x = np.zeros((15, 1))
    kf.P = np.array(init["covariance"], dtype=float)
    eye3 = np.eye(3)
    h_gnss = np.zeros((3, 15))
    h_gnss[:, 0:3] = eye3
    q_white = np.array([0.0] * 3 + [sa2] * 3 + [sg2] * 3 + [0.0] * 6)
    q_bias = np.array([0.0] * 9 + [sbg2] * 3 + [sba2] * 3)
    diag = np.arange(15)
    F = np.eye(15)
    Q = np.zeros((15, 15))

    n_pieces = piece_start.size
    out_t = piece_end.copy()
    out_p = np.empty((n_pieces, 3))
    n_gnss = n_gnss_rej = n_nhc = 0
    streak = 0
    for k in range(n_pieces):
        s = sample[k]
        dt = piece_dt[k]
        w = gyro_all[s] - bg
        f = acc_all[s] - ba
        step_rot = _exp(w * dt)
        rf_hat = rot @ _hat(f)
        # error-state transition at the piece start
        F[0:3, 3:6] = eye3 * dt
        F[0:3, 6:9] = -0.5 * dt * dt * rf_hat
        F[0:3, 12:15] = -0.5 * dt * dt * rot
        F[3:6, 6:9] = -dt * rf_hat
        F[3:6, 12:15] = -dt * rot
        F[6:9, 6:9] = step_rot.T
        F[6:9, 9:12] = -dt * eye3
        Q[diag, diag] = (q_white * (gap_scale if gap[k] else 1.0) + q_bias) * dt
        # nominal state
        acc_w = rot @ f + gravity
        p = p + v * dt + 0.5 * acc_w * dt * dt
        v = v + acc_w * dt
        rot = rot @ step_rot
        kf.F = F
        kf.Q = Q
        kf.predict()

        if ends_update[k]:
            u = upd_idx[k]
            updated = False
            g = gnss_at[u]
            if g >= 0:
                z = (g_pos[g] - p)[:, None]  # measurement of dp (r = p - z, y = -r)
                r_mat = np.diag(g_sig[g] ** 2)
                y = z - kf.x[0:3]
                s_mat = kf.P[0:3, 0:3] + r_mat
                nis = float((y.T @ np.linalg.solve(s_mat, y))[0, 0])
                if nis < gate or streak >= reopen:
                    kf.update(z, R=r_mat, H=h_gnss)
                    streak = 0
                    n_gnss += 1
                    updated = True
                else:
                    streak += 1
                    n_gnss_rej += 1
            if nhc_at[u]:
                w_end = gyro_all[s] - bg
                v_body = rot.T @ v
                resid = v_body + np.cross(w_end, lever)
                h_nhc = np.zeros((2, 15))
                h_nhc[:, 3:6] = rot.T[1:3]
                h_nhc[:, 6:9] = _hat(v_body)[1:3]
                h_nhc[:, 9:12] = lever_hat[1:3]
                kf.update(-resid[1:3, None], R=np.eye(2) * nhc_var, H=h_nhc)
                n_nhc += 1
                updated = True
            if updated:
                dx = kf.x[:, 0]
                p = p + dx[0:3]
                v = v + dx[3:6]
                rot = rot @ _exp(dx[6:9])
                bg = bg + dx[9:12]
                ba = ba + dx[12:15]
                reset = np.eye(15)
                reset[6:9, 6:9] = eye3 - 0.5 * _hat(dx[6:9])
                kf.P = reset @ kf.P @ reset.T
                kf.P = 0.5 * (kf.P + kf.P.T)
                kf.x = np.zeros((15, 1))
        out_p[k] = p

    wall_s = time.perf_counter() - start
    return {
        "t": out_t,
        "position": out_p,
        "wall_s": wall_s,
        "imu_samples": int(n_used),
        "pieces": int(n_pieces),
        "gnss_updates": n_gnss,
        "gnss_rejected": n_gnss_rej,
        "nhc_updates": n_nhc,
        "duration_s": float(t_last - t0),
    }
