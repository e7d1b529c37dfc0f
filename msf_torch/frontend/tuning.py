"""Noise tuning from recorded runs without ground truth: maximum likelihood of the
front end's own innovations.

For a linear-Gaussian system the likelihood of all the measurements factors into that of
the filter's innovations (the prediction-error decomposition):

    -log p(z_1 .. z_N | theta) = 1/2 sum_k (nu_k^T S_k^-1 nu_k + log det S_k + d_k log 2 pi)

with ``nu_k`` the innovation of measurement ``k`` and ``S_k = H P H^T + R`` its covariance,
both functions of the noise ``theta`` through the filter. The ESKF reports both terms per
block (``EskfResult.nis``, ``EskfResult.innovation_logdet``) and is differentiable w.r.t.
its noise tensors (:class:`~msf_torch.frontend.eskf.EskfNoise`), so the noise that makes a
robot's recorded measurements most likely is found by L-BFGS on the gradient of that sum
(the linearised filter makes it an approximation, exact for a linear system). Every
measurement counts, accepted by the gate or not, through a robust form of the likelihood
(an NIS far beyond the gate counts as the gate's value: :func:`innovation_nll`), so the
sum is smooth in the noise and compares like with like while the gate's decisions change;
readings the slip detector or the source-fault detector left out do not count.

Parameters are log multipliers ``theta`` of the start config's sigmas (``sigma = sigma_0
exp(theta)``; a pose source's variance scale by ``exp(2 theta)``), bounded to
``|theta| <= bound`` (``bound tanh(phi / bound)``, a factor 100 by default) and held
near 0 by a Gaussian prior of ``prior_sigma`` (a factor 10): a parameter the data cannot
see stays near its start instead of wandering. Runs are cut into pieces of ``piece_s``
seconds filtered as one batch, each from its own initial state: the sequential length,
and so the time and memory of a gradient, is that of one piece. The first ``burn_in_s``
seconds of each piece do not count: an initial state guessed from a moment of data (a
robot already moving and no wheels: velocity 0) would otherwise be explained by large
noise.

What the innovations can tell apart: a sensor's sigma against the process noise that
predicts it, the gyro against the accelerometer. The bias random walks against the white
noises over minutes of data they cannot (the gyro's white noise and its walk trade off),
so they are tuned only when asked for (:data:`TUNABLE`, ``parameters``). The wheels'
lateral sigma is tuned by default although a run without sideslip (every simulated one)
drives it to the bound and leaves the filter over-confident (held-out NEES share 0.95 ->
0.57 in ``benchmarks/noise_tuning.py`` from the configured start): left at a start 5x too
large instead, the other parameters made up for it and the held-out ATE got worse than the
start's (1.02 -> 1.61 m), where tuning it too gives 0.36 m.
"""

from __future__ import annotations

__all__ = ["TUNABLE", "TuningResult", "counted_blocks", "innovation_nll", "tune_noise"]

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, EskfResult, ImuNoise, run_eskf
from msf_torch.frontend.stream import time_slice
from msf_torch.types import Sequence, batch_sequences

# tunable config keys (a sigma or density each; gnss_sigma_scale multiplies every fix's
# sigma) -> (the measurement block it needs, None for the IMU's; whether it is tuned by
# default when that block is there); pose sources are "pose:<name>", the key
# pose_source_variance_scale[<name>], tuned by default
TUNABLE: dict[str, tuple[str | None, bool]] = {
    "gyro_noise_density": (None, True),
    "accel_noise_density": (None, True),
    "gyro_bias_rw_density": (None, False),
    "accel_bias_rw_density": (None, False),
    "wheel_speed_sigma_mps": ("wheel", True),
    "wheel_lateral_sigma_mps": ("wheel", True),
    "wheel_yaw_rate_sigma_radps": ("wheel", False),
    "nhc_sigma_mps": ("nhc", True),
    "gnss_sigma_scale": ("gnss", True),
}


@dataclass
class TuningResult:
    """What :func:`tune_noise` found.

    Attributes:
        config: the start config with the tuned values.
        parameters: name -> ``{"initial", "tuned", "ratio"}``: config values (a pose
            source's variance scale for ``"pose:<name>"``) and tuned / initial.
        at_bound: parameters that ended within 1 % of the bound (the data pull them
            further: a sensor the data describe better with a much larger or smaller
            sigma, or one they cannot see).
        nll_initial, nll_final: robust negative log-likelihood per measurement
            (:func:`innovation_nll`, without the ``d log 2 pi`` constant; lower is better),
            with the start and the tuned noise.
        mean_nis: block -> ``(initial, final)`` mean NIS of its accepted measurements
            (consistent noise: the block's rows, e.g. 3 for a GNSS fix).
        accepted: block -> ``(initial, final)`` accepted measurements.
        evaluations: filter runs with gradient (L-BFGS function evaluations).
        converged: L-BFGS stopped on its tolerance (the objective changed by less than
            1e-3 between iterations, or the gradient vanished) before ``max_evaluations``;
            False: it was still improving when stopped, so more evaluations may move the
            values further (on the KITTI drive, 25 of the 144 it took left a set worse than
            the start config in GNSS outages).
        history: the objective (per measurement, prior included) at each.
        pieces: how many pieces the runs were cut into; piece_s their length, s;
            burn_in_s the seconds at the start of each that did not count.
    """

    config: EskfConfig
    parameters: dict[str, dict[str, float]]
    at_bound: list[str]
    nll_initial: float
    nll_final: float
    mean_nis: dict[str, tuple[float, float]]
    accepted: dict[str, tuple[int, int]]
    evaluations: int
    converged: bool
    history: list[float] = field(default_factory=list)
    pieces: int = 0
    piece_s: float = 0.0
    burn_in_s: float = 0.0


def counted_blocks(
    result: EskfResult, burn_in_s: float = 0.0, slip_skip_below: float = 0.0
) -> dict[str, torch.Tensor]:
    """Per measurement block, the (B, E + 1) epochs whose measurement counts in
    :func:`innovation_nll`: every one that was there, gated or not, except in the first
    ``burn_in_s`` seconds of each sequence, wheel readings where the slip factor was below
    ``slip_skip_below`` and pose samples of a source flagged as faulty (not the noise's
    doing). :func:`tune_noise` takes them from the start run and keeps them: the sum then
    holds the same terms at every noise it tries (the slip factor moves with the noise)."""
    settled = result.mask & (result.t >= result.t[:, :1] + burn_in_s)
    counted = {}
    for name, present in result.present.items():
        keep = present & settled
        if name == "wheel":
            keep = keep & (result.slip_factor >= slip_skip_below)
        if name in result.source_fault:
            keep = keep & ~result.source_fault[name]
        counted[name] = keep
    return counted


def innovation_nll(
    result: EskfResult, counted: dict[str, torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust negative log-likelihood ``1/2 sum (rho(nis) + log det S)`` () of the
    ``counted`` measurement blocks of a filter run (:func:`counted_blocks`; all sequences
    and blocks; the ``d log 2 pi`` constant left out), and the number of blocks it sums
    () (float).

    ``rho(x) = -2 log(exp(-x / 2) + exp(-g / 2))`` (less its value at 0) is the NIS itself
    well below the block's gate ``g`` and ``g`` well above it: a Gaussian contaminated by
    outliers that look like an NIS of ``g``, smooth in the noise (a gate's yes / no is
    not)."""
    total = result.position.new_zeros(())
    count = result.position.new_zeros(())
    for name, nis in result.nis.items():
        gate = result.gate_threshold.get(name, math.inf)
        rho = nis
        if math.isfinite(gate):
            cap = torch.full_like(nis, -0.5 * gate)
            rho = -2.0 * (torch.logaddexp(-0.5 * nis, cap) - math.log1p(math.exp(-0.5 * gate)))
        weight = counted[name].to(nis.dtype)
        total = total + 0.5 * (weight * (rho + result.innovation_logdet[name])).sum()
        count = count + weight.sum()
    return total, count


def _pieces(sequences: list[Sequence], piece_s: float) -> list[Sequence]:
    """Every run cut into pieces of ``piece_s`` seconds (a last piece shorter than half
    of that joins the one before), each with IMU samples."""
    pieces = []
    for seq in sequences:
        for b in range(seq.batch_size):
            one = seq.select(b)
            times = one.imu.t[0][one.imu.mask[0]]
            if times.numel() < 2:
                continue
            start, end = float(times[0]), float(times[-1])
            count = max(1, int(math.floor((end - start) / piece_s + 0.5)))
            edges = [start + k * piece_s for k in range(count)] + [math.nextafter(end, math.inf)]
            for a, z in zip(edges[:-1], edges[1:], strict=True):
                piece = time_slice(one, a, z)
                if piece.imu.length >= 2:
                    pieces.append(piece)
    return pieces


def _present(result: EskfResult) -> set[str]:
    """The measurement blocks of a filter run with at least one measurement."""
    return {name for name, flags in result.present.items() if bool((flags & result.mask).any())}


def _default_parameters(result: EskfResult) -> list[str]:
    """The IMU's white noises and each present sensor's sigma (:data:`TUNABLE`)."""
    present = _present(result)
    names = [
        key
        for key, (block, default) in TUNABLE.items()
        if default and (block is None or block in present)
    ]
    return names + sorted(name for name in present if name.startswith("pose:"))


def _check_parameters(names: list[str], result: EskfResult) -> None:
    """``ValueError`` naming a parameter that is not tunable or whose sensor the runs lack."""
    present = _present(result)
    for name in names:
        if name.startswith("pose:"):
            if name not in present:
                fused = sorted(k for k in present if k.startswith("pose:"))
                raise ValueError(
                    f"tune: {name!r} is not a pose source the filter fuses here "
                    f"(fused: {', '.join(fused) or 'none'})"
                )
        elif name not in TUNABLE:
            raise ValueError(
                f"tune: {name!r} is not a tunable parameter; choose from "
                f"{', '.join(TUNABLE)} or pose:<name>"
            )
        elif TUNABLE[name][0] is not None and TUNABLE[name][0] not in present:
            raise ValueError(
                f"tune: {name!r} needs {TUNABLE[name][0]} measurements, which the filter "
                "has none of in these runs"
            )
    if len(set(names)) != len(names):
        raise ValueError(f"tune: a parameter is given twice in {names}")


def _noise(base: EskfNoise, names: list[str], theta: torch.Tensor) -> EskfNoise:
    """``base`` with each named sigma times ``exp(theta_i)`` (a pose source's variance
    scale times ``exp(2 theta_i)``)."""
    factor = {name: torch.exp(theta[i]) for i, name in enumerate(names)}

    def scaled(value: torch.Tensor, name: str) -> torch.Tensor:
        return value * factor[name] if name in factor else value

    imu = ImuNoise(
        scaled(base.imu.gyro_noise_density, "gyro_noise_density"),
        scaled(base.imu.accel_noise_density, "accel_noise_density"),
        scaled(base.imu.gyro_bias_rw_density, "gyro_bias_rw_density"),
        scaled(base.imu.accel_bias_rw_density, "accel_bias_rw_density"),
    )
    pose = dict(base.pose_source_scale)
    for name, value in factor.items():
        if name.startswith("pose:"):
            source = name[len("pose:") :]
            pose[source] = pose.get(source, 1.0) * value**2
    return dataclasses.replace(
        base,
        imu=imu,
        wheel_speed_sigma=scaled(base.wheel_speed_sigma, "wheel_speed_sigma_mps"),
        wheel_lateral_sigma=scaled(base.wheel_lateral_sigma, "wheel_lateral_sigma_mps"),
        wheel_yaw_rate_sigma=scaled(base.wheel_yaw_rate_sigma, "wheel_yaw_rate_sigma_radps"),
        nhc_sigma=scaled(base.nhc_sigma, "nhc_sigma_mps"),
        gnss_sigma_scale=scaled(base.gnss_sigma_scale, "gnss_sigma_scale"),
        pose_source_scale=pose,
    )


def _tuned_config(cfg: EskfConfig, names: list[str], theta: list[float]) -> EskfConfig:
    """``cfg`` with each parameter's value multiplied as :func:`_noise` does."""
    changes: dict[str, Any] = {}
    pose = dict(cfg.pose_source_variance_scale)
    for name, value in zip(names, theta, strict=True):
        if name.startswith("pose:"):
            source = name[len("pose:") :]
            pose[source] = pose.get(source, 1.0) * math.exp(2.0 * value)
        else:
            changes[name] = getattr(cfg, name) * math.exp(value)
    if pose != cfg.pose_source_variance_scale:
        changes["pose_source_variance_scale"] = pose
    return cfg.replace(**changes)


def _value(cfg: EskfConfig, name: str) -> float:
    """A parameter's config value (a pose source's variance scale)."""
    if name.startswith("pose:"):
        return float(cfg.pose_source_variance_scale.get(name[len("pose:") :], 1.0))
    return float(getattr(cfg, name))


def tune_noise(
    sequences: list[Sequence],
    cfg: EskfConfig,
    parameters: list[str] | None = None,
    *,
    piece_s: float = 30.0,
    burn_in_s: float = 5.0,
    max_evaluations: int = 100,
    prior_sigma: float = math.log(10.0),
    bound: float = math.log(100.0),
    progress: Callable[[int, int], None] | None = None,
) -> TuningResult:
    """Fit the front end's noise to recorded runs by maximising the likelihood of its
    innovations (no ground truth needed; see the module docstring).

    Args:
        sequences: the runs (any B each; one config fits them all).
        cfg: the start config (its noise values are the starting point and the prior's
            centre; every other key is kept).
        parameters: :data:`TUNABLE` keys and ``"pose:<name>"``; None: the IMU's white
            noises and the sigma of every sensor the filter accepted measurements from.
        piece_s: length of the pieces the runs are cut into, s.
        burn_in_s: the measurements of each piece's first seconds do not count (its
            start is an initialisation, whose guess of e.g. the velocity of a robot
            already moving would otherwise be blamed on the noise), s.
        max_evaluations: most filter runs with gradient (each about 3-4 times a run
            without). The parameters' curvatures differ by orders of magnitude (a sigma
            every measurement sees against a bias walk), so L-BFGS can need a hundred and
            more; ``converged`` says whether it stopped on its own tolerance.
        prior_sigma: sigma of the Gaussian prior on each log multiplier.
        bound: largest |log multiplier|.
        progress: called ``(evaluations done, max_evaluations)`` after each.

    Returns:
        :class:`TuningResult`.

    Raises:
        ValueError: no piece with IMU samples, a parameter that is not tunable or whose
            sensor the runs lack, or no accepted measurement at all.
    """
    if not piece_s > 0 or not max_evaluations >= 1 or not prior_sigma > 0 or not bound > 0:
        raise ValueError(
            "tune: piece_s, max_evaluations, prior_sigma and bound must be positive, got "
            f"{piece_s!r}, {max_evaluations!r}, {prior_sigma!r}, {bound!r}"
        )
    if not 0.0 <= burn_in_s < piece_s:
        raise ValueError(f"tune: burn_in_s must lie in [0, piece_s), got {burn_in_s!r}")
    pieces = _pieces(sequences, piece_s)
    if not pieces:
        raise ValueError("tune: no run has IMU samples")
    batch = batch_sequences(pieces)
    dtype, device = batch.imu.t.dtype, batch.imu.t.device
    with torch.no_grad():
        start = run_eskf(batch, cfg)
    names = _default_parameters(start) if parameters is None else list(parameters)
    _check_parameters(names, start)
    counted = counted_blocks(start, burn_in_s, cfg.slip_skip_below)
    total, count = innovation_nll(start, counted)
    if float(count) == 0:
        raise ValueError("tune: the filter accepted no measurement in these runs")
    base = EskfNoise.from_config(cfg, dtype, device)
    phi = torch.zeros(len(names), dtype=dtype, device=device, requires_grad=True)
    optimizer = torch.optim.LBFGS(
        [phi],
        lr=1.0,
        max_iter=max_evaluations,
        max_eval=max_evaluations,
        tolerance_grad=1e-4,
        tolerance_change=1e-3,
        history_size=10,
        line_search_fn="strong_wolfe",
    )
    history: list[float] = []
    best: dict[str, Any] = {"loss": math.inf, "theta": torch.zeros_like(phi)}

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        theta = bound * torch.tanh(phi / bound)
        result = run_eskf(batch, cfg, noise=_noise(base, names, theta))
        nll, blocks = innovation_nll(result, counted)
        prior = 0.5 * ((theta / prior_sigma) ** 2).sum()
        loss = nll + prior  # summed: L-BFGS's first step is then one unit of log scale
        if not torch.isfinite(loss):  # a diverged filter: a wall for the line search
            history.append(math.inf)
            if progress is not None:
                progress(len(history), max_evaluations)
            return torch.full_like(loss, 1e20).detach()
        loss.backward()
        history.append(float(loss.detach()) / max(float(blocks), 1.0))
        if float(loss.detach()) < best["loss"]:  # the same terms at every evaluation
            best.update(loss=float(loss.detach()), theta=theta.detach().clone())
        if progress is not None:
            progress(len(history), max_evaluations)
        return loss

    if names:
        optimizer.step(closure)
    theta = best["theta"].tolist()
    tuned = _tuned_config(cfg, names, theta)
    with torch.no_grad():
        final = run_eskf(batch, tuned)
    final_total, final_count = innovation_nll(final, counted)
    before, after = start.accepted_nis(burn_in_s), final.accepted_nis(burn_in_s)
    blocks = sorted(set(before) | set(after))
    return TuningResult(
        config=tuned,
        parameters={
            name: {
                "initial": _value(cfg, name),
                "tuned": _value(tuned, name),
                "ratio": _value(tuned, name) / _value(cfg, name),
            }
            for name in names
        },
        at_bound=[n for n, v in zip(names, theta, strict=True) if abs(v) >= 0.99 * bound],
        nll_initial=float(total) / float(count),
        nll_final=float(final_total) / max(float(final_count), 1.0),
        mean_nis={
            k: (before.get(k, (math.nan, 0))[0], after.get(k, (math.nan, 0))[0]) for k in blocks
        },
        accepted={
            k: (before.get(k, (math.nan, 0))[1], after.get(k, (math.nan, 0))[1]) for k in blocks
        },
        evaluations=len(history),
        converged=len(history) < max_evaluations,
        history=history,
        pieces=len(pieces),
        piece_s=float(piece_s),
        burn_in_s=float(burn_in_s),
    )
