"""Innovation gating: chi-square tests of single blocks, multi-model source-fault detection.

**Chi-square.** A measurement block with residual ``r`` and innovation covariance
``S = H P H^T + R`` passes when its normalised innovation squared ``NIS = r^T S^-1 r`` lies
below the chi-square quantile of its dimension at the configured probability.

**Multi-model source-fault detection** (:func:`detect_source_faults`). A chi-square gate
sees one epoch against the filter's own prediction; it lets through a source that is wrong
by less than its gate every epoch (a LiDAR matcher sliding along a corridor, a blinded
camera drifting, a frozen driver), and the filter's gate re-opening fuses it anyway. Here
each pose source ``s`` gets its own model of the motion it reports, and the sources are
compared with each other:

1. *Per-source UKF.* State ``x = [v, w]``: body-frame velocity (m/s) and body rate (rad/s),
   constant over a pair interval, random walk between samples
   (``Q = diag(sigma_a^2 I, sigma_alpha^2 I) dt``). A pair of consecutive samples over
   ``dt`` (``frontend.schedule``) reports the mid-interval-frame mean velocity and the mean
   rate, which for constant ``v`` and ``w`` are (:func:`source_increment_model`)

       h(x) = [Exp(-phi / 2) Gamma_1(phi) v,  w],   phi = w dt,

   a nonlinear map (``Gamma_1`` the SO(3) left Jacobian), hence an unscented filter
   (:func:`ukf_update`, scaled sigma points of van der Merwe). The measurement noise is the
   pair's declared covariance (times the source's variance scale). Each source's
   innovation ``nu_s`` becomes a pose-increment residual in metres,
   ``e_s = [nu_v dt, L nu_w dt]`` (``L`` a lever that turns a heading error into metres),
   kept over a window of the last ``n`` samples. The models are deliberately stiff
   (``sigma_a = 0.1 m/s^2/sqrt(Hz)`` by default): a model that follows its source quickly
   absorbs a lasting fault before the test below has seen enough of it; the manoeuvres a
   stiff model misses are common to all sources and cancel in step 2.
2. *Residual difference.* A manoeuvre the constant-velocity models did not expect moves all
   sources' residuals together; a faulty source moves alone. Over the window, the
   difference of source ``s``'s summed residual and the other healthy sources' mean residual
   (as a mean velocity, rescaled to ``s``'s window duration ``W_s``),

       D_s = sum_window e_s - W_s mean_o (sum_window e_o / W_o),

   is compared with a threshold that scales with speed, ``T = c v / f + T_0`` (``v`` the
   healthy models' speed, ``f = 1 / dt`` the source's rate: ``c = 1`` is one sample's
   travel). Sources at the same rate and times give ``D_s = sum (e_s - mean_o e_o)``.
3. *Two-tailed Z-test.* ``|D_s| > T`` triggers a test of the window of ``s``: per component
   ``i`` and over the newest ``k = 1..n`` samples, ``Z_k,i = sum e_i / sqrt(sum var_i)``
   (:func:`window_z_scores`; ``var`` from the UKF's innovation covariances; the shortest
   ``k`` catches a gross fault at once, the longest a small lasting one), two-tailed
   ``p = erfc(|Z| / sqrt 2)`` (:func:`two_tailed_p_value`). A source whose ``max |Z|``
   exceeds ``z_enter`` gets weight 0 (at most one new source per step, and never the last
   healthy one). While excluded, its model is re-synchronised at every step to the
   information-weighted consensus of the healthy models (so its own faulty samples cannot
   drag its prediction along and hide a lasting fault), and it is tested at every sample,
   trigger or not: it recovers once the Z over its last ``exit_samples`` samples is below
   ``z_exit`` in every component (hysteresis: ``z_exit < z_enter``), and its window then
   restarts empty (the faulty residuals are no evidence any more).

A constant-velocity model makes the white position noise of a differenced source (the
pairs share samples) look white with twice the variance, so a window sum of residuals
telescopes to less noise than ``sum var`` states: the test is conservative for healthy
sources. A source with no healthy fresh reference (the other sources absent or excluded)
cannot enter exclusion; an excluded source whose reference disappears is released once its
residuals against the extrapolated consensus (whose covariance grows) look calm.

**Gradients.** UKF, residuals and Z are differentiable torch ops. The 0/1 weight is a
*straight-through* gate (:func:`straight_through_gate`): the forward value is exactly 0
or 1 (the filter drops the source's rows), the backward pass uses the derivative of the
surrogate ``sigmoid((z_thr - Z) / tau)`` (``Z`` the deciding statistic; ``z_thr = z_enter``,
or ``z_exit`` for an excluded source). Everything is batched over B sequences and S
sources; the only loop is over the epochs that carry a source pair.

References:
    R. van der Merwe, "Sigma-point Kalman filters for probabilistic inference in dynamic
    state-space models", PhD thesis, OGI, 2004 (scaled sigma points).
    P. Maybeck, *Stochastic Models, Estimation and Control*, vol. 2, ch. 10 (multiple-model
    adaptive estimation), 1982.
    Y. Bengio, N. Leonard, A. Courville, "Estimating or propagating gradients through
    stochastic neurons for conditional computation", arXiv:1308.3432, 2013
    (straight-through estimator).
"""

from __future__ import annotations

__all__ = [
    "chi2_threshold",
    "two_tailed_p_value",
    "z_threshold",
    "MerweSigmaPoints",
    "unscented_transform",
    "ukf_predict",
    "ukf_update",
    "UkfUpdate",
    "source_increment_model",
    "window_z_scores",
    "straight_through_gate",
    "SourceFaultParams",
    "SourceFaultResult",
    "FaultMemory",
    "detect_source_faults",
]

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from scipy.stats import chi2, norm

from msf_torch.frontend.config import EskfConfig


def chi2_threshold(dof: int, probability: float) -> float:
    """Chi-square quantile for ``dof`` at ``probability`` (inf when probability is 1)."""
    if probability >= 1.0:
        return math.inf
    return float(chi2.ppf(probability, dof))


def two_tailed_p_value(z: torch.Tensor) -> torch.Tensor:
    """Two-tailed p-value ``P(|N(0, 1)| >= |z|) = erfc(|z| / sqrt 2)`` (...,) of Z scores."""
    return torch.special.erfc(z.abs() / math.sqrt(2.0))


def z_threshold(alpha: float) -> float:
    """``|z|`` at which a two-tailed Z-test rejects at level ``alpha`` (``Phi^-1(1 - a/2)``)."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"z_threshold: alpha must lie in (0, 1), got {alpha!r}")
    return float(norm.isf(alpha / 2.0))


# --------------------------------------------------------------------------------------------
# Unscented Kalman filter (batched over leading dims)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MerweSigmaPoints:
    """Scaled sigma points (van der Merwe): ``2n + 1`` points ``x``, ``x +- sqrt(n + l) L_k``
    with ``L L^T = P``, ``l = alpha^2 (n + kappa) - n``.

    Weights: ``Wm_0 = l / (n + l)``, ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``,
    ``Wm_k = Wc_k = 1 / (2 (n + l))``. The same ordering as ``filterpy``'s
    ``MerweScaledSigmaPoints`` (centre, then the ``+`` points, then the ``-`` points).
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def weights(
        self, n: int, dtype: torch.dtype, device: torch.device | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and covariance weights, (2n + 1,) each."""
        lam = self.alpha**2 * (n + self.kappa) - n
        wm = torch.full((2 * n + 1,), 0.5 / (n + lam), dtype=dtype, device=device)
        wc = wm.clone()
        wm[0] = lam / (n + lam)
        wc[0] = lam / (n + lam) + 1.0 - self.alpha**2 + self.beta
        return wm, wc

    def points(self, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """Sigma points (..., 2n + 1, n) of mean (..., n) and covariance (..., n, n)."""
        n = mean.shape[-1]
        lam = self.alpha**2 * (n + self.kappa) - n
        spread = torch.linalg.cholesky((n + lam) * cov).mT  # rows: columns of L
        centre = mean[..., None, :]
        return torch.cat((centre, centre + spread, centre - spread), -2)


def unscented_transform(
    points: torch.Tensor,
    wm: torch.Tensor,
    wc: torch.Tensor,
    noise_cov: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted mean (..., m), covariance (..., m, m) (plus ``noise_cov``) and deviations
    (..., N, m) of transformed sigma points (..., N, m)."""
    mean = (wm[:, None] * points).sum(-2)
    dev = points - mean[..., None, :]
    cov = (dev * wc[:, None]).mT @ dev
    if noise_cov is not None:
        cov = cov + noise_cov
    return mean, cov, dev


def ukf_predict(
    mean: torch.Tensor,
    cov: torch.Tensor,
    transition: Callable[[torch.Tensor], torch.Tensor],
    process_cov: torch.Tensor,
    sigma: MerweSigmaPoints,
) -> tuple[torch.Tensor, torch.Tensor]:
    """UKF prediction: ``x^- = sum Wm f(X)``, ``P^- = sum Wc (f(X) - x^-)(.)^T + Q``.

    Args:
        mean, cov: (..., n), (..., n, n).
        transition: maps sigma points (..., 2n + 1, n) to (..., 2n + 1, n).
        process_cov: Q (..., n, n).
    """
    wm, wc = sigma.weights(mean.shape[-1], mean.dtype, mean.device)
    moved = transition(sigma.points(mean, cov))
    new_mean, new_cov, _ = unscented_transform(moved, wm, wc, process_cov)
    return new_mean, 0.5 * (new_cov + new_cov.mT)


@dataclass
class UkfUpdate:
    """Result of :func:`ukf_update`: posterior mean (..., n) and covariance (..., n, n),
    innovation ``z - z_hat`` (..., m) and its covariance ``S`` (..., m, m)."""

    mean: torch.Tensor
    cov: torch.Tensor
    innovation: torch.Tensor
    innovation_cov: torch.Tensor


def ukf_update(
    mean: torch.Tensor,
    cov: torch.Tensor,
    measurement: torch.Tensor,
    observe: Callable[[torch.Tensor], torch.Tensor],
    noise_cov: torch.Tensor,
    sigma: MerweSigmaPoints,
) -> UkfUpdate:
    """UKF update with sigma points drawn from the predicted ``(mean, cov)``.

    ``z_hat = sum Wm h(X)``, ``S = sum Wc (h(X) - z_hat)(.)^T + R``,
    ``C = sum Wc (X - x)(h(X) - z_hat)^T``, ``K = C S^-1``, ``x+ = x + K (z - z_hat)``,
    ``P+ = P - K S K^T``.

    Args:
        mean, cov: predicted state (..., n), (..., n, n).
        measurement: z (..., m).
        observe: maps sigma points (..., 2n + 1, n) to (..., 2n + 1, m).
        noise_cov: R (..., m, m).
    """
    wm, wc = sigma.weights(mean.shape[-1], mean.dtype, mean.device)
    return _ukf_update(mean, cov, measurement, observe, noise_cov, sigma, wm, wc)


def _ukf_update(
    mean: torch.Tensor,
    cov: torch.Tensor,
    measurement: torch.Tensor,
    observe: Callable[[torch.Tensor], torch.Tensor],
    noise_cov: torch.Tensor,
    sigma: MerweSigmaPoints,
    wm: torch.Tensor,
    wc: torch.Tensor,
) -> UkfUpdate:
    """:func:`ukf_update` with precomputed weights."""
    points = sigma.points(mean, cov)
    predicted, innovation_cov, dev_z = unscented_transform(observe(points), wm, wc, noise_cov)
    innovation_cov = 0.5 * (innovation_cov + innovation_cov.mT)
    cross = ((points - mean[..., None, :]) * wc[:, None]).mT @ dev_z  # (..., n, m)
    gain = torch.linalg.solve(innovation_cov, cross.mT).mT
    innovation = measurement - predicted
    new_mean = mean + (gain @ innovation[..., None])[..., 0]
    new_cov = cov - gain @ innovation_cov @ gain.mT
    return UkfUpdate(new_mean, 0.5 * (new_cov + new_cov.mT), innovation, innovation_cov)


def source_increment_model(points: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
    """Mean body velocity and rate a pose source reports over ``dt`` for constant ``v, w``.

    ``z = [Exp(-phi / 2) Gamma_1(phi) v, w]``, ``phi = w dt``: the chord of the interval in the
    mid-interval frame (``frontend.schedule``) divided by ``dt``, and the mean rate. The
    matrix is symmetric: the part of ``v`` along the rotation axis passes unchanged, the part
    across it shrinks to the chord ``2 sin(theta / 2) / theta`` of its arc, so
    ``Exp(-phi / 2) Gamma_1(phi) = I + k [phi]x^2`` with ``k = (1 - 2 sin(theta/2) / theta) /
    theta^2`` (series ``1/24 - theta^2 / 1920 + theta^4 / 322560`` near 0).

    Args:
        points: states ``[v (m/s), w (rad/s)]`` (..., N, 6).
        dt: pair intervals (..., 1) s, broadcast over N.
    Returns:
        (..., N, 6) ``[z_v (m/s), z_w (rad/s)]``.
    """
    velocity, rate = points[..., :3], points[..., 3:]
    phi = rate * dt[..., None]
    theta2 = (phi * phi).sum(-1, keepdim=True)
    small = theta2 < 1e-4
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    safe = torch.sqrt(safe2)
    series = 1.0 / 24.0 - theta2 / 1920.0 + theta2 * theta2 / 322560.0
    k = torch.where(small, series, (1.0 - 2.0 * torch.sin(0.5 * safe) / safe) / safe2)
    bent = torch.linalg.cross(phi, torch.linalg.cross(phi, velocity, dim=-1), dim=-1)
    return torch.cat((velocity + k * bent, rate), -1)


def window_z_scores(residuals: torch.Tensor, variances: torch.Tensor) -> torch.Tensor:
    """Z scores of the newest ``k = 1..n`` samples of a residual window, per component.

    ``Z_k,i = sum_(j < k) e_j,i / sqrt(sum_(j < k) var_j,i)`` over the window ordered newest
    first; under "no fault" (zero-mean independent residuals of those variances) each is
    N(0, 1), and ``|Z| > z`` rejects at the two-tailed level ``erfc(z / sqrt 2)``
    (:func:`two_tailed_p_value`). Empty slots (variance 0) contribute nothing; a ``k``
    with no filled slot gives 0.

    Args:
        residuals: (..., n, d) newest first.
        variances: (..., n, d) their variances (0 = empty slot).
    Returns:
        (..., n, d) ``Z_k,i``.
    """
    res_k, var_k = residuals.cumsum(-2), variances.cumsum(-2)
    filled = var_k > 0
    z = res_k / torch.sqrt(torch.where(filled, var_k, 1.0))
    return torch.where(filled, z, 0.0)


def straight_through_gate(
    hard: torch.Tensor, margin: torch.Tensor, softness: float
) -> torch.Tensor:
    """0/1 forward, ``d sigmoid(margin / softness)`` backward (straight-through estimator).

    Args:
        hard: (...,) the decision as 0/1 floats (no gradient needed).
        margin: (...,) signed margin of the decision (positive = keep).
        softness: temperature ``tau`` of the surrogate sigmoid (margin units).
    Returns:
        (...,) equal to ``hard`` in value, with the surrogate's gradient.
    """
    soft = torch.sigmoid(margin / softness)
    return hard.detach() + (soft - soft.detach())  # exactly ``hard``: the bracket is 0


# --------------------------------------------------------------------------------------------
# Source-fault detection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SourceFaultParams:
    """Settings of :func:`detect_source_faults` (the ``source_fault_*`` keys of
    ``EskfConfig``).

    Attributes:
        window: n, samples in each source's residual window.
        speed_factor: c in the trigger ``T = c v / f + T_0``.
        min_threshold_m: ``T_0``, m (standing still).
        z_enter: ``max |Z|`` (newest 1..n samples, every component) above which a
            triggered source is excluded.
        z_exit: ``max |Z|`` over the last ``exit_samples`` samples below which an excluded
            source is re-admitted.
        exit_samples: samples in the re-admission test.
        accel_sigma_mps2: ``sigma_a``, random-walk density of the models' velocity, m/s^2.
        angular_accel_sigma_radps2: ``sigma_alpha``, of the models' rate, rad/s^2.
        rotation_lever_m: ``L``, m per rad of a heading residual.
        max_age_s: a source's residuals older than this are no reference for the others, s.
        softness: ``tau`` of the straight-through surrogate, Z units.
        initial_velocity_sigma_mps, initial_rate_sigma_radps: prior of each model.
    """

    window: int = 10
    speed_factor: float = 1.0
    min_threshold_m: float = 0.05
    z_enter: float = 3.0
    z_exit: float = 1.5
    exit_samples: int = 3
    accel_sigma_mps2: float = 0.1
    angular_accel_sigma_radps2: float = 0.1
    rotation_lever_m: float = 1.0
    max_age_s: float = 0.5
    softness: float = 0.5
    initial_velocity_sigma_mps: float = 10.0
    initial_rate_sigma_radps: float = 1.0

    @classmethod
    def from_config(cls, cfg: EskfConfig) -> SourceFaultParams:
        """The ``source_fault_*`` keys of a front-end config (``max_age_s`` from
        ``pose_source_max_gap_s``)."""
        return cls(
            window=cfg.source_fault_window,
            speed_factor=cfg.source_fault_speed_factor,
            min_threshold_m=cfg.source_fault_min_threshold_m,
            z_enter=cfg.source_fault_z_enter,
            z_exit=cfg.source_fault_z_exit,
            exit_samples=cfg.source_fault_exit_samples,
            accel_sigma_mps2=cfg.source_fault_accel_sigma_mps2,
            angular_accel_sigma_radps2=cfg.source_fault_angular_accel_sigma_radps2,
            rotation_lever_m=cfg.source_fault_rotation_lever_m,
            max_age_s=cfg.pose_source_max_gap_s,
        )


@dataclass
class SourceFaultResult:
    """Per-epoch output of :func:`detect_source_faults` (B sequences, E epochs, S sources).

    Attributes:
        flagged: (B, E, S) bool, the source is excluded after this epoch (held between its
            samples).
        weight: (B, E, S) fusion weight, exactly ``1 - flagged`` in value, with the
            straight-through surrogate gradient (:func:`straight_through_gate`).
        z: (B, E, S) the statistic that decided, at the source's samples (0 elsewhere): the
            window's ``max |Z|`` for a healthy source, the last ``exit_samples``' for an
            excluded one.
        difference_m: (B, E, S) ``|D_s|``, m, at its samples (0 elsewhere).
        threshold_m: (B, E, S) the trigger ``T``, m, at its samples (0 elsewhere).
        triggered: (B, E, S) bool, ``|D_s| > T`` at this sample.
    """

    flagged: torch.Tensor
    weight: torch.Tensor
    z: torch.Tensor
    difference_m: torch.Tensor
    threshold_m: torch.Tensor
    triggered: torch.Tensor
    memory: FaultMemory | None = None


@dataclass
class FaultMemory:
    """The fault detector's state after a chunk's last epoch, for the next chunk of a run
    filtered in pieces (``detect_source_faults(..., memory=...)``, ``run_eskf(...,
    fault_memory=...)``), so that the chunks detect as the run in one piece. It depends on
    the pose-source data only (not on the filter).

    Attributes:
        names: the S sources, in the schedule's order.
        mean: (B, S, 6) each source's model state ``[v, w]`` (m/s, rad/s).
        cov: (B, S, 6, 6) its covariance.
        t_state: (B, S) time of that state, s.
        t_last: (B, S) time of the source's latest residual in its window, s (-inf: none).
        seen: (B, S) bool, the source has had a sample.
        flagged: (B, S) bool, the source is excluded.
        window: (B, S, n, 13) the latest ``n`` residual entries, newest first.
    """

    names: tuple[str, ...]
    mean: torch.Tensor
    cov: torch.Tensor
    t_state: torch.Tensor
    t_last: torch.Tensor
    seen: torch.Tensor
    flagged: torch.Tensor
    window: torch.Tensor


def _hold(
    values: list[torch.Tensor],
    steps: list[int],
    n_epochs: int,
    fill: float,
    initial: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, E, S) from per-processed-epoch values (B, S) at epochs ``steps`` (sorted): each
    epoch takes the value of the last processed epoch at or before it (before the first:
    ``initial`` (B, S), a previous chunk's, else ``fill``)."""
    stacked = torch.stack(values, 1)
    where = torch.as_tensor(steps, device=stacked.device)
    index = torch.searchsorted(where, torch.arange(n_epochs, device=stacked.device), right=True)
    held = stacked[:, (index - 1).clamp_min(0)]
    before = (index == 0)[None, :, None]
    first = torch.full_like(held, fill) if initial is None else initial[:, None].expand_as(held)
    return torch.where(before, first, held)


def _scatter(values: list[torch.Tensor], steps: list[int], n_epochs: int) -> torch.Tensor:
    """(B, E, S) with per-processed-epoch values (B, S) at ``steps`` and zeros elsewhere."""
    stacked = torch.stack(values, 1)
    out = torch.zeros(
        stacked.shape[0], n_epochs, *stacked.shape[2:], dtype=stacked.dtype, device=stacked.device
    )
    out[:, steps] = stacked
    return out


def detect_source_faults(
    t: torch.Tensor,
    velocity: torch.Tensor,
    rate: torch.Tensor,
    velocity_cov: torch.Tensor,
    rate_cov: torch.Tensor,
    dt: torch.Tensor,
    mask: torch.Tensor,
    params: SourceFaultParams | None = None,
    sigma: MerweSigmaPoints | None = None,
    memory: FaultMemory | None = None,
    names: tuple[str, ...] = (),
) -> SourceFaultResult:
    """Multi-model fault detection over the pose-source pairs of a schedule.

    Args:
        t: (B, E) epoch times, s.
        velocity: (B, E, S, 3) each source's mean body velocity ``z_v`` over its pair, m/s.
        rate: (B, E, S, 3) mean body rate ``z_w``, rad/s.
        velocity_cov, rate_cov: (B, E, S, 3, 3) their covariances, (m/s)^2 and (rad/s)^2.
        dt: (B, E, S) pair intervals, s.
        mask: (B, E, S) bool, a pair of the source ends at the epoch.
        params: settings (default :class:`SourceFaultParams()`).
        sigma: sigma-point scaling (default ``alpha = 1, beta = 2, kappa = 0``).
        memory: the previous chunk's ``result.memory`` (a run in pieces): the detector
            goes on from its state instead of starting afresh.
        names: the S sources' names (recorded in the returned memory; checked against
            ``memory.names``).
    Returns:
        :class:`SourceFaultResult`, (B, E, S) fields, and the state after the last epoch
        (``memory``).

    Example:
        >>> import torch
        >>> B, E, S = 1, 40, 2
        >>> t = torch.arange(1, E + 1, dtype=torch.float64)[None] * 0.1
        >>> vel = torch.zeros(B, E, S, 3, dtype=torch.float64)
        >>> vel[..., 0] = 1.0
        >>> vel[:, 20:30, 1, 0] = 0.0  # the second source freezes for 1 s
        >>> cov = 1e-3 * torch.eye(3, dtype=torch.float64).expand(B, E, S, 3, 3)
        >>> out = detect_source_faults(t, vel, torch.zeros_like(vel), cov, cov,
        ...     torch.full((B, E, S), 0.1, dtype=torch.float64),
        ...     torch.ones(B, E, S, dtype=torch.bool))
        >>> out.flagged[0, 18:36, 1].int().tolist()
        [0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0]
        >>> bool(out.flagged[0, :, 0].any())
        False
    """
    params = params or SourceFaultParams()
    sigma = sigma or MerweSigmaPoints()
    batch, _, n_src = mask.shape
    n_epochs = t.shape[1]
    dtype, device = velocity.dtype, velocity.device
    if memory is not None and tuple(memory.names) != tuple(names):
        raise ValueError(
            f"fault memory holds sources {list(memory.names)}, this run has {list(names)}"
        )
    steps = [e for e in range(n_epochs) if bool(mask[:, e].any())]
    if not steps:
        zeros = torch.zeros(batch, n_epochs, n_src, dtype=dtype, device=device)
        held = zeros.bool() if memory is None else memory.flagged[:, None].expand_as(zeros)
        return SourceFaultResult(
            held,
            (~held).to(dtype),
            zeros,
            zeros,
            zeros,
            zeros.bool(),
            memory,
        )
    eye6 = torch.eye(6, dtype=dtype, device=device)
    q_rate = torch.tensor(
        [params.accel_sigma_mps2**2] * 3 + [params.angular_accel_sigma_radps2**2] * 3,
        dtype=dtype,
        device=device,
    )
    prior = torch.tensor(
        [params.initial_velocity_sigma_mps**2] * 3 + [params.initial_rate_sigma_radps**2] * 3,
        dtype=dtype,
        device=device,
    )
    lever = torch.tensor([1.0] * 3 + [params.rotation_lever_m] * 3, dtype=dtype, device=device)
    wm, wc = sigma.weights(6, dtype, device)

    # inputs at the processed epochs only: (B, P, S, ...)
    here_all = mask[:, steps]
    t_all = t[:, steps]
    dt_all = dt[:, steps].where(here_all, torch.ones_like(dt[:, steps]))
    z_all = torch.cat((velocity[:, steps], rate[:, steps]), -1) * here_all[..., None]
    zero3 = torch.zeros_like(velocity_cov[:, steps])
    noise_all = torch.cat(
        (
            torch.cat((velocity_cov[:, steps], zero3), -1),
            torch.cat((zero3, rate_cov[:, steps]), -1),
        ),
        -2,
    )
    noise_all = torch.where(here_all[..., None, None], noise_all, eye6)
    scale_all = lever * dt_all[..., None]  # m per (m/s), m per (rad/s)

    if memory is None:
        mean = torch.zeros(batch, n_src, 6, dtype=dtype, device=device)
        cov = torch.diag_embed(prior).expand(batch, n_src, 6, 6)
        t_state = torch.zeros(batch, n_src, dtype=dtype, device=device)
        t_last = torch.full((batch, n_src), -math.inf, dtype=dtype, device=device)
        seen = torch.zeros(batch, n_src, dtype=torch.bool, device=device)
        flagged = torch.zeros(batch, n_src, dtype=torch.bool, device=device)
        window = torch.zeros(batch, n_src, params.window, 13, dtype=dtype, device=device)
    else:
        if memory.window.shape[2] != params.window:
            raise ValueError(
                f"fault memory holds windows of {memory.window.shape[2]} samples, this run "
                f"uses {params.window}"
            )
        mean, cov, t_state, t_last = memory.mean, memory.cov, memory.t_state, memory.t_last
        seen, flagged, window = memory.seen, memory.flagged, memory.window
    not_self = (~torch.eye(n_src, dtype=torch.bool, device=device)).to(dtype)  # (S, S)
    exit_index = min(params.exit_samples, params.window) - 1
    rec: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("flagged", "weight", "z", "diff", "thr", "trig")
    }
    for p in range(len(steps)):
        here = here_all[:, p]
        now = t_all[:, p, None]
        pair_dt = dt_all[:, p]
        # --- predict (random walk: the unscented transform of the identity is exact) -------
        elapsed = torch.where(here & seen, now - t_state, 0.0).clamp_min(0.0)
        cov_pred = cov + torch.diag_embed(q_rate * elapsed[..., None])
        # --- innovation of every source's own model ------------------------------------
        upd = _ukf_update(
            mean,
            cov_pred,
            z_all[:, p],
            lambda pts, step=pair_dt: source_increment_model(pts, step[..., None]),
            noise_all[:, p],
            sigma,
            wm,
            wc,
        )
        scale = scale_all[:, p]
        entry = torch.cat(
            (
                upd.innovation * scale,  # pose-increment residual, m
                torch.diagonal(upd.innovation_cov, dim1=-2, dim2=-1) * scale**2,
                pair_dt[..., None],
            ),
            -1,
        )
        push = here & seen
        window = torch.where(
            push[..., None, None], torch.cat((entry[:, :, None], window[:, :, :-1]), 2), window
        )  # newest first
        t_last = torch.where(push, now, t_last)
        # --- two-tailed Z over the last k = 1..n samples --------------------------------
        sums = window.cumsum(2)  # (B, S, n, 13): sums over the newest k + 1 samples
        z_k = window_z_scores(window[..., :6], window[..., 6:12]).abs().amax(-1)  # (B, S, n)
        z_scan = z_k.amax(-1)
        z_recent = z_k[..., exit_index]
        # --- residual difference against the healthy, fresh other sources ----------------
        res_sum, duration = sums[:, :, -1, :6], sums[:, :, -1, 12]
        fresh = seen & ~flagged & (now - t_last <= params.max_age_s) & (duration > 0)
        mean_vel = res_sum / torch.where(duration > 0, duration, 1.0)[..., None]
        weight_o = not_self * fresh[:, None, :].to(dtype)  # (B, S, S'): s <- o
        count = weight_o.sum(-1)
        ref_vel = (weight_o @ mean_vel) / count.clamp_min(1.0)[..., None]
        difference = (res_sum - duration[..., None] * ref_vel).norm(dim=-1)
        healthy = (seen & ~flagged).to(dtype)
        speed = (mean[..., :3].norm(dim=-1) * healthy).sum(-1) / healthy.sum(-1).clamp_min(1.0)
        threshold = params.speed_factor * speed[:, None] * pair_dt + params.min_threshold_m
        triggered = push & (count > 0) & (difference > threshold)
        # --- exclusion with hysteresis ---------------------------------------------------
        leaving = flagged & push & (z_recent < params.z_exit)
        candidate = triggered & ~flagged & (z_scan > params.z_enter)
        score = torch.where(candidate, z_scan.detach(), -1.0)
        best = torch.zeros_like(candidate).scatter(1, score.argmax(-1, keepdim=True), True)
        entering = candidate & best
        entering = entering & ((seen | here) & ~flagged & ~entering).any(-1, keepdim=True)
        new_flagged = (flagged & ~leaving) | entering
        # a recovered source starts a fresh window (its faulty residuals are no evidence now)
        window = torch.where(leaving[..., None, None], 0.0, window)
        z_stat = torch.where(flagged, z_recent, z_scan)
        z_gate = torch.where(flagged, params.z_exit, params.z_enter)
        weight = straight_through_gate((~new_flagged).to(dtype), z_gate - z_stat, params.softness)
        # --- models: healthy sources take their update; excluded ones follow the consensus
        take = here & ~new_flagged
        mean = torch.where(take[..., None], upd.mean, mean)
        cov = torch.where(
            take[..., None, None], upd.cov, torch.where(here[..., None, None], cov_pred, cov)
        )
        t_state = torch.where(here, now, t_state)
        seen = seen | here
        good = seen & ~new_flagged
        # only a sequence with a sample at this epoch: another sequence's epochs must not move
        # it (two syncs of one model with two healthy ones differ from one sync later)
        sync = new_flagged & good.any(-1, keepdim=True) & here.any(-1, keepdim=True)
        if bool(sync.any()):
            lag = (now - t_state).clamp_min(0.0)
            cov_now = cov + torch.diag_embed(q_rate * lag[..., None])
            info = torch.linalg.inv(torch.where(good[..., None, None], cov_now, eye6))
            info = info * good[..., None, None].to(dtype)
            info_sum = info.sum(1) + (~good.any(-1)).to(dtype)[:, None, None] * eye6
            consensus_cov = torch.linalg.inv(info_sum)
            consensus = (consensus_cov @ (info @ mean[..., None]).sum(1))[..., 0]
            mean = torch.where(sync[..., None], consensus[:, None], mean)
            cov = torch.where(sync[..., None, None], consensus_cov[:, None], cov)
            t_state = torch.where(sync, now, t_state)
        flagged = new_flagged
        rec["flagged"].append(flagged)
        rec["weight"].append(weight)
        rec["z"].append(torch.where(push, z_stat, 0.0))
        rec["diff"].append(torch.where(push, difference, 0.0))
        rec["thr"].append(torch.where(push, threshold, 0.0))
        rec["trig"].append(triggered)

    flagged_before = None if memory is None else memory.flagged  # the previous chunk's
    weight_before = None if memory is None else (~memory.flagged).to(dtype)
    return SourceFaultResult(
        flagged=_hold(rec["flagged"], steps, n_epochs, False, flagged_before),
        weight=_hold(rec["weight"], steps, n_epochs, 1.0, weight_before),
        z=_scatter(rec["z"], steps, n_epochs),
        difference_m=_scatter(rec["diff"], steps, n_epochs),
        threshold_m=_scatter(rec["thr"], steps, n_epochs),
        triggered=_scatter(rec["trig"], steps, n_epochs),
        memory=FaultMemory(tuple(names), mean, cov, t_state, t_last, seen, flagged, window),
    )
