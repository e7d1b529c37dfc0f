"""Strong-tracking adaptive UKF attitude filter for one or several IMUs, batched.

State: attitude, a unit quaternion ``q = [w, x, y, z]`` (Hamilton, body -> world), and body
angular rate ``omega`` (rad/s). Error state (6,) ``[dtheta, domega]`` with
``q = q_hat (x) Exp(dtheta)`` (the body-side perturbation of ``geometry.conventions``,
``R = R_hat Exp(dtheta)``) and ``omega = omega_hat + domega``; covariance ``P`` (6, 6).

Process (one IMU interval ``dt``): ``q' = q (x) Exp(omega dt)``, ``omega' = omega``; noise
``Q = blockdiag(sigma_att^2 dt I, sigma_alpha^2 dt I)`` (attitude random walk: unmodelled
gyro drift; rate random walk: angular acceleration).

Measurements (any subset per sample, stacked, ``present`` masks):

* ``quaternion`` (3 rows): an attitude fix ``q_z``, in the chart at the fix,
  ``h(x) = Log(q_z^-1 (x) q)`` (= ``Log(R_z^T R)``) against ``0``, covariance
  ``sigma_q^2 I``;
* ``rate`` (3): the gyro, ``h(x) = omega``, ``R_w = sigma_g^2 / dt I`` (white noise of
  density ``sigma_g``);
* ``accel`` (3): the accelerometer as a gravity sensor, ``h(x) = R^T [0, 0, g]`` (the
  specific force at rest; linear acceleration is noise), ``R_a = (sigma_a^2 / dt +
  sigma_d^2) I`` with ``sigma_d`` an allowance for linear acceleration.

Unscented transform: Merwe scaled sigma points (:func:`merwe_weights`, the weights of
filterpy's ``MerweScaledSigmaPoints``) in the error state; the attitude mean of the
propagated points is the weighted Karcher mean (two fixed-point iterations
``q <- q (x) Exp(sum W_i Log(q^-1 (x) q_i))``, enough for sigma points a few degrees
apart). Sigma points are redrawn from ``P^-`` for the update.

Adaptation (``frontend.adaptive.BlockAdaptation``, per sample, after the prediction):
Sage-Husa estimation of the accelerometer block's R (the linear acceleration of a moving
body is a time-varying measurement noise) and a strong-tracking fading factor from the
gyro block's innovations (a sudden angular acceleration is a process-model mismatch), with
the statistically linearised ``H = P_xz^T (P^-)^-1``; the faded ``P^-`` is applied along the
measured directions and the sigma points are redrawn from it.

Everything runs on leading dims ``(...)``, e.g. ``(B, N)`` for B runs of N IMUs, flattened
into one batch; the only Python loop is over samples.

Reference: Merwe & Wan, "Sigma-point Kalman filters for probabilistic inference in
dynamic state-space models", 2004; Crassidis & Markley, "Unscented filtering for spacecraft
attitude estimation", 2003 (error-state sigma points on the attitude).

Example:
    >>> import torch
    >>> gyro = torch.zeros(2, 400, 3, dtype=torch.float64)
    >>> accel = torch.tensor([0.0, 0.0, 9.80665], dtype=torch.float64).expand(2, 400, 3)
    >>> cfg = AttitudeUkfConfig(gyro_noise_density=1e-4, accel_noise_density=1e-3)
    >>> est = run_attitude_ukf(gyro, accel, 0.005, cfg)
    >>> est.quaternion.shape
    torch.Size([2, 400, 4])
"""

from __future__ import annotations

__all__ = [
    "BLOCKS",
    "AttitudeUkfConfig",
    "AttitudeEstimate",
    "merwe_weights",
    "sigma_points",
    "ukf_predict",
    "ukf_update",
    "initial_attitude",
    "run_attitude_ukf",
    "roll_pitch",
]

import math
from dataclasses import dataclass, field

import torch

from msf_torch.frontend.adaptive import BlockAdaptation
from msf_torch.geometry.conventions import STANDARD_GRAVITY
from msf_torch.geometry.quaternion import quat_conjugate as _qconj
from msf_torch.geometry.quaternion import quat_exp as _qexp
from msf_torch.geometry.quaternion import quat_log as _qlog
from msf_torch.geometry.quaternion import quat_multiply as _qmul
from msf_torch.geometry.quaternion import quat_to_matrix

BLOCKS = ("quaternion", "rate", "accel")
"""Measurement blocks, in stacking order (3 rows each)."""

_STATE_DIM = 6


def _gravity_in_body(q: torch.Tensor, gravity_mps2: float) -> torch.Tensor:
    """``R(q)^T [0, 0, g]`` (..., 3): g times the third row of R."""
    w, x, y, z = q.unbind(-1)
    row = torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1)
    return gravity_mps2 * row


@dataclass
class AttitudeUkfConfig:
    """Settings of :func:`run_attitude_ukf` (SI units, named in the fields).

    Attributes:
        gyro_noise_density: rad/s/sqrt(Hz) (datasheet rate noise spectral density); a
            float, or a tensor broadcastable to the filters' leading dims (e.g. (N,): one
            value per IMU type).
        accel_noise_density: m/s^2/sqrt(Hz), float or tensor as above.
        accel_disturbance_sigma_mps2: allowance for linear acceleration in the nominal R_a.
        quaternion_sigma_rad: per-axis sigma of an attitude fix.
        angular_accel_density: rad/s^2/sqrt(Hz), process noise of the rate.
        attitude_noise_density: rad/sqrt(s), process noise of the attitude. The state has no
            gyro bias, so this random walk must absorb the unmodelled gyro offset: it sets
            the time constant over which the accelerometer pulls the tilt back
            (``tau ~ sqrt(R_a dt) / (g sigma)``), trading offset drift (short tau wanted)
            against linear acceleration leaking in (long tau wanted). 3e-4 was the best of
            1e-4 / 3e-4 / 1e-3 / 3e-3 on simulated ICM-20602/20689 pairs with 0.05 deg/s
            residual offsets, static and moving (tuning seeds 9000-9005, not the benchmark's).
        gravity_mps2: g.
        alpha, beta, kappa: Merwe sigma-point parameters.
        adaptive_noise_blocks: blocks whose R is estimated (Sage-Husa).
        strong_tracking_blocks: blocks whose innovations drive the fading factor.
        forgetting: b of the exponential fading (per sample).
        prior_samples: what the nominal R is worth, in samples.
        noise_floor: R_hat eigenvalues >= this x the nominal R's smallest.
        softening: beta of the fading factor.
        max_factor: cap on the fading factor.
        clip_probability: chi-square quantile that clips one innovation's influence.
        init_samples: accelerometer samples averaged for the initial roll and pitch.
        init_attitude_sigma_rad: initial roll/pitch sigma.
        init_yaw_sigma_rad: initial yaw sigma (yaw starts at 0). The yaw is unobservable
            without attitude fixes; its prior must keep the sigma points, ``sqrt(n +
            lambda)`` sigmas out, well inside the chart (angles < pi), or the unscented
            means wrap around.
        init_rate_sigma_radps: initial rate sigma (the rate starts at the first gyro sample).
    """

    gyro_noise_density: float | torch.Tensor
    accel_noise_density: float | torch.Tensor
    accel_disturbance_sigma_mps2: float = 0.1
    quaternion_sigma_rad: float = 0.01
    angular_accel_density: float = 1.0
    attitude_noise_density: float = 3e-4
    gravity_mps2: float = STANDARD_GRAVITY
    alpha: float = 0.5
    beta: float = 2.0
    kappa: float = 0.0
    adaptive_noise_blocks: tuple[str, ...] = ("accel",)
    strong_tracking_blocks: tuple[str, ...] = ("rate",)
    forgetting: float = 0.99
    prior_samples: float = 50.0
    noise_floor: float = 0.1
    softening: float = 1.0
    max_factor: float = 10.0
    clip_probability: float = 0.9999
    init_samples: int = 50
    init_attitude_sigma_rad: float = 0.05
    init_yaw_sigma_rad: float = 0.3
    init_rate_sigma_radps: float = 0.05

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        for name in ("gyro_noise_density", "accel_noise_density"):
            value = torch.as_tensor(getattr(self, name))
            if not bool((torch.isfinite(value) & (value > 0)).all()):
                raise ValueError(f"AttitudeUkfConfig.{name} must be > 0, got {value!r}")
        for name in (
            "quaternion_sigma_rad",
            "angular_accel_density",
            "gravity_mps2",
            "alpha",
            "init_attitude_sigma_rad",
            "init_yaw_sigma_rad",
            "init_rate_sigma_radps",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"AttitudeUkfConfig.{name} must be > 0, got {value!r}")
        for name in ("accel_disturbance_sigma_mps2", "attitude_noise_density"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"AttitudeUkfConfig.{name} must be >= 0")
        for name in ("adaptive_noise_blocks", "strong_tracking_blocks"):
            unknown = [b for b in getattr(self, name) if b not in BLOCKS]
            if unknown:
                raise ValueError(f"AttitudeUkfConfig.{name}: unknown blocks {unknown}")
        if self.init_samples < 1:
            raise ValueError("AttitudeUkfConfig.init_samples must be >= 1")
        for name, ok, rule in (
            ("forgetting", 0.0 < self.forgetting < 1.0, "lie in (0, 1)"),
            ("clip_probability", 0.0 < self.clip_probability <= 1.0, "lie in (0, 1]"),
            ("noise_floor", self.noise_floor > 0, "be > 0"),
            ("softening", self.softening > 0, "be > 0"),
            ("prior_samples", self.prior_samples >= 0, "be >= 0"),
            ("max_factor", self.max_factor >= 1.0, "be >= 1"),
        ):
            if not ok:
                value = getattr(self, name)
                raise ValueError(f"AttitudeUkfConfig.{name} must {rule}, got {value!r}")


@dataclass
class AttitudeEstimate:
    """Per-sample posteriors of :func:`run_attitude_ukf` (leading dims ``(...)``, T samples).

    Attributes:
        quaternion: (..., T, 4) ``[w, x, y, z]``, body -> world, w >= 0.
        rotation: (..., T, 3, 3).
        angular_rate: (..., T, 3) body, rad/s.
        covariance: (..., T, 6, 6) over ``[dtheta, domega]`` (rad^2, rad^2/s, (rad/s)^2).
        fading_factor: (..., T) strong-tracking factor (1 = none).
        noise_estimate: adaptive block -> (..., T, 3, 3) its estimated R.
    """

    quaternion: torch.Tensor
    rotation: torch.Tensor
    angular_rate: torch.Tensor
    covariance: torch.Tensor
    fading_factor: torch.Tensor
    noise_estimate: dict[str, torch.Tensor] = field(default_factory=dict)


def merwe_weights(
    n: int,
    alpha: float,
    beta: float,
    kappa: float,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Merwe scaled sigma-point weights.

    ``lambda = alpha^2 (n + kappa) - n``; ``Wm_0 = lambda / (n + lambda)``,
    ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``, ``W_i = 1 / (2 (n + lambda))`` for i = 1..2n.

    Returns:
        Wm (2n+1,), Wc (2n+1,) and the spread ``sqrt(n + lambda)``.
    """
    lam = alpha**2 * (n + kappa) - n
    if n + lam <= 0:
        raise ValueError(f"merwe_weights: n + lambda must be > 0, got {n + lam}")
    rest = torch.full((2 * n,), 0.5 / (n + lam), dtype=dtype, device=device)
    first = torch.tensor([lam / (n + lam)], dtype=dtype, device=device)
    wm = torch.cat((first, rest))
    wc = torch.cat((first + (1.0 - alpha**2 + beta), rest))
    return wm, wc, math.sqrt(n + lam)


def sigma_points(covariance: torch.Tensor, spread: float) -> torch.Tensor:
    """Error-state sigma points ``[0, +s L_i, -s L_i]`` (..., 2n+1, n), ``L L^T = P``.

    Raises:
        FloatingPointError: ``P`` is not positive definite.
    """
    chol, info = torch.linalg.cholesky_ex(0.5 * (covariance + covariance.mT))
    if bool((info != 0).any()):
        raise FloatingPointError("attitude UKF: covariance lost positive definiteness")
    cols = spread * chol.mT  # rows are the scaled columns of L
    zero = torch.zeros_like(cols[..., :1, :])
    return torch.cat((zero, cols, -cols), -2)


def _attitude_mean(quats: torch.Tensor, weights: torch.Tensor, iterations: int = 2):
    """Weighted Karcher mean of (..., S, 4) with weights (S,) summing to 1; returns the
    mean (..., 4) and the deviations ``Log(q_mean^-1 (x) q_i)`` (..., S, 3)."""
    mean = quats[..., 0, :]
    for _ in range(iterations):
        dev = _qlog(_qmul(_qconj(mean)[..., None, :], quats))
        mean = _qmul(mean, _qexp((weights[:, None] * dev).sum(-2)))
    return mean, _qlog(_qmul(_qconj(mean)[..., None, :], quats))


def ukf_predict(
    quat: torch.Tensor,
    rate: torch.Tensor,
    covariance: torch.Tensor,
    process: torch.Tensor,
    dt: torch.Tensor,
    weights: tuple[torch.Tensor, torch.Tensor, float],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unscented prediction over one interval.

    Args:
        quat: (L, 4), rate: (L, 3), covariance: (L, 6, 6) at the start.
        process: (L, 6, 6) Q of the interval.
        dt: (L,) s.
        weights: :func:`merwe_weights` output.
    Returns:
        predicted quaternion (L, 4), rate (L, 3), covariance ``P^-`` (L, 6, 6).
    """
    wm, wc, spread = weights
    chi = sigma_points(covariance, spread)  # (L, S, 6)
    rate_i = rate[:, None] + chi[..., 3:]
    turn = _qmul(_qexp(chi[..., :3]), _qexp(rate_i * dt[:, None, None]))
    quat_i = _qmul(quat[:, None], turn)
    quat_mean, dev_rot = _attitude_mean(quat_i, wm)
    rate_mean = (wm[:, None] * rate_i).sum(-2)
    dev = torch.cat((dev_rot, rate_i - rate_mean[:, None]), -1)
    cov = (wc[:, None, None] * dev[..., :, None] * dev[..., None, :]).sum(-3) + process
    return quat_mean, rate_mean, 0.5 * (cov + cov.mT)


def _measure(
    quat: torch.Tensor,
    rate: torch.Tensor,
    chi: torch.Tensor,
    fix: torch.Tensor,
    gravity_mps2: float,
) -> torch.Tensor:
    """Stacked predictions (L, S, 9) of the sigma points ``chi`` (L, S, 6)."""
    quat_i = _qmul(quat[:, None], _qexp(chi[..., :3]))
    quat_rows = _qlog(_qmul(_qconj(fix)[:, None], quat_i))
    rate_rows = rate[:, None] + chi[..., 3:]
    accel_rows = _gravity_in_body(quat_i, gravity_mps2)
    return torch.cat((quat_rows, rate_rows, accel_rows), -1)


def _moments(predicted: torch.Tensor, chi: torch.Tensor, wm: torch.Tensor, wc: torch.Tensor):
    mean = (wm[:, None] * predicted).sum(-2)
    dev = predicted - mean[:, None]
    p_yy = (wc[:, None, None] * dev[..., :, None] * dev[..., None, :]).sum(-3)
    p_xy = (wc[:, None, None] * chi[..., :, None] * dev[..., None, :]).sum(-3)
    return mean, p_yy, p_xy


def ukf_update(
    quat: torch.Tensor,
    rate: torch.Tensor,
    covariance: torch.Tensor,
    measurement: torch.Tensor,
    fix: torch.Tensor,
    measurement_cov: torch.Tensor,
    present: torch.Tensor,
    weights: tuple[torch.Tensor, torch.Tensor, float],
    gravity_mps2: float,
    process: torch.Tensor | None = None,
    adaptation: BlockAdaptation | None = None,
    step: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unscented update with the stacked ``[quaternion, rate, accel]`` measurement.

    Args:
        quat, rate, covariance: the prediction (L, 4), (L, 3), ``P^-`` (L, 6, 6).
        measurement: (L, 9) ``[0, 0, 0, gyro, accel]`` (the quaternion rows are 0 in the
            chart at ``fix``).
        fix: (L, 4) attitude fix (any unit quaternion where absent).
        measurement_cov: (L, 9, 9) nominal R.
        present: (L, 3) bool per block of :data:`BLOCKS`.
        weights: :func:`merwe_weights` output.
        gravity_mps2: g.
        process: (L, 6, 6) the Q inside ``P^-``, for the fading factor.
        adaptation: optional Sage-Husa / strong-tracking state (adapted in place).
        step: sample index, for the adaptation's history.
    Returns:
        posterior quaternion, rate, covariance.
    """
    wm, wc, spread = weights
    dtype = covariance.dtype
    rows = present.repeat_interleave(3, -1)  # (L, 9)
    chi = sigma_points(covariance, spread)
    predicted = _measure(quat, rate, chi, fix, gravity_mps2)
    mean, p_yy, p_xy = _moments(predicted, chi, wm, wc)
    innovation = (measurement - mean) * rows
    r_cov = measurement_cov
    if adaptation is not None and adaptation.enabled:
        # statistical linearisation H = P_xy^T P^-1 (exact for a linear h)
        jacobian = torch.linalg.solve(covariance, p_xy).mT
        q = torch.zeros_like(covariance) if process is None else process
        faded, r_cov = adaptation.step(
            step, covariance - q, q, jacobian, innovation, measurement_cov, present
        )
        if adaptation.tracking_blocks:
            covariance = faded
            chi = sigma_points(covariance, spread)
            predicted = _measure(quat, rate, chi, fix, gravity_mps2)
            mean, p_yy, p_xy = _moments(predicted, chi, wm, wc)
            innovation = (measurement - mean) * rows
    weight = rows.to(dtype)
    outer = weight[:, :, None] * weight[:, None, :]
    s = (p_yy + r_cov) * outer + torch.diag_embed(1.0 - weight)
    p_xy = p_xy * weight[:, None, :]
    chol = torch.linalg.cholesky(s)
    gain = torch.cholesky_solve(p_xy.mT, chol).mT  # (L, 6, 9)
    correction = (gain @ innovation[..., None])[..., 0]
    cov = covariance - gain @ s @ gain.mT
    quat = _qmul(quat, _qexp(correction[:, :3]))
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return quat, rate + correction[:, 3:], 0.5 * (cov + cov.mT)


def initial_attitude(accel: torch.Tensor) -> torch.Tensor:
    """Roll and pitch from a mean specific force (..., 3) at rest, yaw 0 -> quaternion (..., 4).

    ``roll = atan2(f_y, f_z)``, ``pitch = atan2(-f_x, sqrt(f_y^2 + f_z^2))``,
    ``q = q_y(pitch) (x) q_x(roll)`` so that ``R^T [0, 0, g] ~ f``.
    """
    roll = torch.atan2(accel[..., 1], accel[..., 2])
    pitch = torch.atan2(-accel[..., 0], accel[..., 1:].norm(dim=-1))
    zero = torch.zeros_like(roll)
    return _qmul(
        _qexp(torch.stack((zero, pitch, zero), -1)), _qexp(torch.stack((roll, zero, zero), -1))
    )


def roll_pitch(rotation: torch.Tensor) -> torch.Tensor:
    """Roll and pitch (ZYX Euler angles) of body -> world rotations (..., 3, 3) -> (..., 2) rad.

    ``roll = atan2(R_21, R_22)``, ``pitch = -asin(R_20)``; both ignore the yaw.
    """
    roll = torch.atan2(rotation[..., 2, 1], rotation[..., 2, 2])
    pitch = -torch.asin(rotation[..., 2, 0].clamp(-1.0, 1.0))
    return torch.stack((roll, pitch), -1)


def run_attitude_ukf(
    gyro: torch.Tensor,
    accel: torch.Tensor,
    dt: float | torch.Tensor,
    cfg: AttitudeUkfConfig,
    quaternion: torch.Tensor | None = None,
    quaternion_mask: torch.Tensor | None = None,
    initial: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> AttitudeEstimate:
    """Run the attitude UKF over IMU samples.

    Sample k: predict over ``dt_k`` (not at k = 0), then update with the gyro and the
    accelerometer of sample k and the attitude fix when ``quaternion_mask[..., k]``.

    Args:
        gyro: (..., T, 3) rad/s.
        accel: (..., T, 3) m/s^2 (specific force).
        dt: sample interval, s: a float or (..., T) (entry k is the interval before k).
        cfg: settings.
        quaternion: optional (..., T, 4) attitude fixes ``[w, x, y, z]``.
        quaternion_mask: (..., T) bool, fixes present (default: all, when given).
        initial: optional (quaternion (..., 4), rate (..., 3), covariance (..., 6, 6));
            default from the first ``init_samples`` samples (:func:`initial_attitude`).
    Returns:
        :class:`AttitudeEstimate`.
    Raises:
        ValueError: a bad setting, bad shapes, no samples, or a non-finite gyro / accel
            sample or a negative ``dt`` (naming the first one).
    """
    cfg.validate()
    if gyro.shape != accel.shape or gyro.dim() < 2 or gyro.shape[-1] != 3:
        raise ValueError(
            f"gyro {tuple(gyro.shape)} and accel {tuple(accel.shape)} must be (..., T, 3)"
        )
    if gyro.shape[-2] == 0:
        raise ValueError(f"gyro and accel {tuple(gyro.shape)} hold no samples (T = 0)")
    lead, n_samples = gyro.shape[:-2], gyro.shape[-2]
    dtype, device = gyro.dtype, gyro.device
    gyro_f, accel_f = gyro.reshape(-1, n_samples, 3), accel.reshape(-1, n_samples, 3)
    count = gyro_f.shape[0]
    dt_f = torch.as_tensor(dt, dtype=dtype, device=device).expand(*lead, n_samples)
    dt_f = dt_f.reshape(count, n_samples)
    for name, bad, what in (
        ("gyro", ~torch.isfinite(gyro).all(-1), "not finite"),
        ("accel", ~torch.isfinite(accel).all(-1), "not finite"),
        ("dt", ~(torch.isfinite(dt_f) & (dt_f >= 0)).reshape(*lead, n_samples), "not >= 0"),
    ):
        if bool(bad.any()):  # one bad sample would stop every filter of the batch later
            where = [int(i) for i in bad.nonzero()[0]]
            raise ValueError(f"run_attitude_ukf: {name}{where} is {what}")
    if quaternion is not None:
        fixes = quaternion.reshape(count, n_samples, 4)
        fixes = fixes / fixes.norm(dim=-1, keepdim=True)
        mask = (
            torch.ones(count, n_samples, dtype=torch.bool, device=device)
            if quaternion_mask is None
            else quaternion_mask.reshape(count, n_samples)
        )
    else:
        fixes, mask = None, torch.zeros(count, n_samples, dtype=torch.bool, device=device)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device)
    if initial is None:
        init = min(cfg.init_samples, n_samples)
        quat = initial_attitude(accel_f[:, :init].mean(1))
        rate = gyro_f[:, 0]
        variances = torch.tensor(
            [cfg.init_attitude_sigma_rad**2] * 2
            + [cfg.init_yaw_sigma_rad**2]
            + [cfg.init_rate_sigma_radps**2] * 3,
            dtype=dtype,
            device=device,
        )
        cov = torch.diag(variances).expand(count, 6, 6)
    else:
        quat = initial[0].reshape(count, 4)
        rate = initial[1].reshape(count, 3)
        cov = initial[2].reshape(count, 6, 6)

    def per_filter(value: float | torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(value, dtype=dtype, device=device).expand(lead).reshape(count)

    gyro_density, accel_density = (
        per_filter(cfg.gyro_noise_density),
        per_filter(cfg.accel_noise_density),
    )
    weights = merwe_weights(_STATE_DIM, cfg.alpha, cfg.beta, cfg.kappa, dtype, device)
    adaptation = BlockAdaptation(
        BLOCKS,
        [3, 3, 3],
        cfg.adaptive_noise_blocks,
        cfg.strong_tracking_blocks,
        count,
        cfg.forgetting,
        cfg.prior_samples,
        cfg.noise_floor,
        cfg.softening,
        cfg.clip_probability,
        cfg.max_factor,
        dtype,
        device,
    )
    zeros3 = torch.zeros(count, 3, dtype=dtype, device=device)
    quat_var = cfg.quaternion_sigma_rad**2
    accel_base = cfg.accel_disturbance_sigma_mps2**2
    out_q, out_w, out_p = [], [], []
    for k in range(n_samples):
        step_dt = dt_f[:, k]
        q_att = cfg.attitude_noise_density**2 * step_dt
        q_rate = cfg.angular_accel_density**2 * step_dt
        process = torch.diag_embed(
            torch.cat((q_att[:, None].expand(count, 3), q_rate[:, None].expand(count, 3)), -1)
        )
        if k > 0:
            quat, rate, cov = ukf_predict(quat, rate, cov, process, step_dt, weights)
        safe_dt = step_dt.clamp_min(1e-9) if k > 0 else dt_f[:, min(1, n_samples - 1)]
        var_rate = gyro_density**2 / safe_dt
        var_accel = accel_density**2 / safe_dt + accel_base
        r_diag = torch.cat(
            (
                torch.full((count, 3), quat_var, dtype=dtype, device=device),
                var_rate[:, None].expand(count, 3),
                var_accel[:, None].expand(count, 3),
            ),
            -1,
        )
        present = torch.stack(
            (mask[:, k], torch.ones_like(mask[:, k]), torch.ones_like(mask[:, k])), -1
        )
        fix = fixes[:, k] if fixes is not None else identity.expand(count, 4)
        measurement = torch.cat((zeros3, gyro_f[:, k], accel_f[:, k]), -1)
        quat, rate, cov = ukf_update(
            quat,
            rate,
            cov,
            measurement,
            fix,
            torch.diag_embed(r_diag),
            present,
            weights,
            cfg.gravity_mps2,
            process if k > 0 else None,
            adaptation,
            k,
        )
        out_q.append(quat)
        out_w.append(rate)
        out_p.append(cov)
    quats = torch.stack(out_q, 1)
    quats = torch.where(quats[..., :1] < 0, -quats, quats)
    fading, noise = adaptation.history(n_samples)
    shape = (*lead, n_samples)
    return AttitudeEstimate(
        quaternion=quats.reshape(*shape, 4),
        rotation=quat_to_matrix(quats).reshape(*shape, 3, 3),
        angular_rate=torch.stack(out_w, 1).reshape(*shape, 3),
        covariance=torch.stack(out_p, 1).reshape(*shape, 6, 6),
        fading_factor=fading[:, 1:].reshape(shape),
        noise_estimate={k: v[:, 1:].reshape(*shape, 3, 3) for k, v in noise.items()},
    )
