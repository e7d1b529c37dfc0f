"""Fault guards of the ESKF front end: unusable samples are skipped by rule, and a diverging
sequence is detected and reset.

Input rule (:func:`sanitize_sequence`, applied by ``run_eskf`` before anything else). A
sample of the IMU, wheel, GNSS, pose or named pose-source stream is used only if

1. its time and every value are finite (a GNSS ``sigma`` may be NaN or inf: the configured
   default then applies, as before), and
2. its time is later than every earlier usable sample's of the same stream (a repeated or
   backwards stamp is dropped; the first of a repeat is kept).

Dropped samples get ``mask = False`` and zero values, so nothing of them reaches the filter,
even through padding; their count per stream and sequence is reported
(``EskfResult.dropped_samples``). Samples that pass are untouched, bit for bit.

Divergence (:class:`DivergenceGuard`, one check after propagation and one after the update of
every epoch, for all B sequences at once). A sequence diverges when

* its state or covariance holds a NaN or inf (code :data:`NONFINITE`),
* its covariance is not positive semi-definite, or the innovation covariance of its update
  not positive definite (a Cholesky factorisation fails; code
  :data:`NOT_POSITIVE_DEFINITE`), or
* an accepted, gated block has a normalised innovation squared above
  ``divergence_nis_scale`` times its gate, and the streak it ends shares an offset (code
  :data:`NIS_BLOWUP`). Gating rejects such a block unless it was re-opened after
  ``gate_reopen_after`` rejections in a row. A huge NIS alone does not tell a wrong state
  from a sensor noisier than declared (a GNSS in an urban canyon: every few fixes pass the
  re-opened gate with NIS far above the limit while the state is fine). What does: a wrong
  state offsets every innovation of the streak the same way, a mis-specified noise does
  not. :func:`streak_offset` tests the streak's whitened innovations for a common offset
  with a statistic whose law without one does not depend on the noise scale (Beta; level
  0.001). Nor is it a blow-up when another re-openable block passed its own gate during the
  streak: that sensor vouches for the state, the streak's sensor is the suspect (a blinded
  camera beside a healthy LiDAR). (NEES, the same test on the estimation error, needs the
  truth, which a running filter lacks; the NIS is its observable counterpart.)

A diverged sequence is reset to its last good state, the latest one that passed the checks
(the propagated state of the same epoch when that was healthy: the update is discarded);
its update counts as not accepted. The covariance is inflated once per divergence episode
(from the reset until a re-openable block passes its gate again; a further reset in it
returns to the last good state as it is): in conventional coordinates every sigma grows by
``sqrt(divergence_inflation)``, but none past ``divergence_max_sigma_factor`` times its
configured initial sigma (:func:`reset_sigma_cap`; a sigma already above stays), and
correlations are kept. So resets cannot compound (the filter once multiplied the covariance
by 100 at each of many resets and ran away to sigmas of 1e33 m). The codes add up (bit
flags) and are reported per epoch (``EskfResult.divergence``, the ``divergence`` column of
``diagnostics.csv``). Sequences that do not diverge are untouched (``torch.where`` picks
their own values), so a batch never mixes sequences and a run without faults is bit for bit
the run without the guard.

The gate's memory (each block's rejections in a row, its streak's innovation sums, whether
another block vouched during it, the open episode) lives in the guard and is handed from
one ``run_eskf`` call to the next as :class:`GateMemory` (``EskfResult.gate_memory``), so a
run filtered in chunks gates as one run. A block that a chunk does not measure keeps its
streak through it (another block passing its gate there vouches for it, as in one run).

Interruption (:class:`InterruptCatcher`, :class:`EstimationInterrupted`). Ctrl-C (SIGINT)
during the epoch loop ends the loop, not the results: ``run_eskf`` raises
:class:`EstimationInterrupted`, a ``KeyboardInterrupt`` that carries the result of the
epochs completed (later epochs masked out), so a caller can write a valid partial output.
"""

from __future__ import annotations

__all__ = [
    "EstimationInterrupted",
    "InterruptCatcher",
    "NONFINITE",
    "NOT_POSITIVE_DEFINITE",
    "NIS_BLOWUP",
    "DIVERGENCE_CODES",
    "sanitize_sequence",
    "DivergenceGuard",
    "GateMemory",
    "reset_sigma_cap",
    "streak_offset",
    "OFFSET_PROBABILITY",
]

import dataclasses
import itertools
import math
from collections.abc import Callable

import torch
from scipy.special import betaincinv

from msf_torch.frontend.config import EskfConfig
from msf_torch.types import NavState, Sequence

NONFINITE = 1
"""Divergence code: a NaN or inf in the state or covariance."""
NOT_POSITIVE_DEFINITE = 2
"""Divergence code: the covariance or the innovation covariance is not positive definite."""
NIS_BLOWUP = 4
"""Divergence code: an accepted gated block's NIS exceeded ``divergence_nis_scale`` x gate."""
DIVERGENCE_CODES = {
    NONFINITE: "nonfinite",
    NOT_POSITIVE_DEFINITE: "not_positive_definite",
    NIS_BLOWUP: "nis_blowup",
}
"""Code bit -> name, as written in the run summary."""

_PSD_JITTER = 1e-9  # relative diagonal load of the semi-definiteness test
# fields where a non-finite value means "use the default" (sigmas)
_NAN_OK = {
    "gnss": ("sigma",),
    "gnss_velocity": ("sigma",),
    "gnss_heading": ("sigma",),
    "magnetometer": ("sigma",),
}
# field -> leading entries that must be finite; the rest may be NaN ("not measured": a GNSS
# velocity's up component), not inf
_NAN_OK_TAIL = {"gnss_velocity": {"velocity": 2}}


def _usable(
    stream, nan_ok: tuple[str, ...], nan_ok_tail: dict[str, int] | None = None
) -> torch.Tensor:
    """(B, N) bool: masked-in samples with finite time and values, later than every earlier
    one of the same stream. Fields in ``nan_ok`` may hold NaN; a field in ``nan_ok_tail``
    must be finite in its first ``n`` trailing entries and may be NaN in the rest."""
    nan_ok_tail = nan_ok_tail or {}
    good = stream.mask & torch.isfinite(stream.t)
    for name, value in stream.tensors().items():
        # a finite sum means every value is finite (one NaN or inf makes it NaN or inf):
        # the per-sample test (slow over (B, N, 3)) only runs where the sum is not
        if name in ("t", "mask") or name in nan_ok or bool(torch.isfinite(value.sum())):
            continue
        flat = value.reshape(*value.shape[:2], math.prod(value.shape[2:]))
        if name in nan_ok_tail:
            head = nan_ok_tail[name]
            good = good & torch.isfinite(flat[..., :head]).all(-1)
            good = good & ~torch.isinf(flat[..., head:]).any(-1)
        else:
            good = good & torch.isfinite(flat).all(-1)
    neg_inf = torch.tensor(-torch.inf, dtype=stream.t.dtype, device=stream.t.device)
    latest = torch.where(good, stream.t, neg_inf).cummax(dim=1).values
    earlier = torch.cat((torch.full_like(latest[:, :1], -torch.inf), latest[:, :-1]), 1)
    return good & (stream.t > earlier)


def _drop(stream, usable: torch.Tensor):
    """The stream with ``mask = usable`` and the values of the other samples set to 0 (the
    stream itself when every sample is usable)."""
    if bool(usable.all()):
        return stream

    def clean(name: str, value: torch.Tensor) -> torch.Tensor:
        if name == "mask":
            return usable
        keep = usable.reshape(*usable.shape, *([1] * (value.dim() - 2)))
        return torch.where(keep, value, torch.zeros((), dtype=value.dtype, device=value.device))

    return type(stream)(**{k: clean(k, v) for k, v in stream.tensors().items()})


def sanitize_sequence(seq: Sequence) -> tuple[Sequence, dict[str, torch.Tensor]]:
    """Mask out the samples the filter must not use (module docstring: the input rule).

    Args:
        seq: B sequences; the IMU, wheel, GNSS, GNSS velocity and heading, magnetometer,
            pose and pose-source streams
            are checked (ground truth is left alone: the filter does not read it).

    Returns:
        (the cleaned sequence, stream -> (B,) int64 number of samples dropped). Streams are
        keyed as in ``EskfResult.present`` (``"imu"``, ``"wheel"``, ``"gnss"``,
        ``"gnss_velocity"``, ``"gnss_heading"``, ``"magnetometer"``, ``"pose"``,
        ``"pose:<name>"``). When
        nothing is dropped the input's tensors come back unchanged in value.
    """
    streams = {
        "imu": seq.imu,
        "wheel": seq.wheel,
        "gnss": seq.gnss,
        "gnss_velocity": seq.gnss_velocity,
        "gnss_heading": seq.gnss_heading,
        "magnetometer": seq.magnetometer,
        "pose": seq.poses,
    }
    streams |= {f"pose:{name}": s for name, s in seq.pose_sources.items()}
    cleaned: dict[str, object] = {}
    dropped: dict[str, torch.Tensor] = {}
    for key, stream in streams.items():
        if stream is None:
            continue
        usable = _usable(stream, _NAN_OK.get(key, ()), _NAN_OK_TAIL.get(key))
        dropped[key] = (stream.mask & ~usable).sum(-1)
        cleaned[key] = _drop(stream, usable)
    sources = {name: cleaned[f"pose:{name}"] for name in seq.pose_sources}
    out = dataclasses.replace(
        seq,
        imu=cleaned["imu"],
        wheel=cleaned.get("wheel"),
        gnss=cleaned.get("gnss"),
        gnss_velocity=cleaned.get("gnss_velocity"),
        gnss_heading=cleaned.get("gnss_heading"),
        magnetometer=cleaned.get("magnetometer"),
        poses=cleaned.get("pose"),
        pose_sources=sources,
    )
    return out, dropped


_FIELDS = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")


def _finite(state: NavState, cov: torch.Tensor) -> torch.Tensor:
    """(B,) bool: no NaN or inf in the state and covariance (a sum overflowing past 1e308
    counts as inf: such values are no estimate either)."""
    parts = (cov.flatten(1), state.rotation.flatten(1))
    parts += tuple(getattr(state, f) for f in ("position", "velocity", "gyro_bias", "accel_bias"))
    return torch.isfinite(torch.cat(parts, -1).sum(-1))


def _pick(bad: torch.Tensor, a: NavState, b: NavState) -> NavState:
    """Per sequence: ``a`` where ``bad`` (B,), else ``b``."""

    def where(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return torch.where(bad.reshape(-1, *([1] * (x.dim() - 1))), x, y)

    return NavState(*(where(getattr(a, f), getattr(b, f)) for f in _FIELDS))


OFFSET_PROBABILITY = 0.999
"""Default of :func:`streak_offset`: a streak of zero-mean innovations, whatever their scale,
passes for an offset with probability 0.001."""


@dataclasses.dataclass
class GateMemory:
    """What the chi-square gate, the divergence guard and the wheel slip detector remember
    between ``run_eskf`` calls (``EskfResult.gate_memory`` in, ``run_eskf(...,
    gate_memory=...)`` out), so that a run filtered in chunks gates, resets and distrusts
    slipping wheels as the same run in one piece.

    Attributes:
        streak: block key (``EskfResult.accepted``'s) -> (B,) its rejections in a row.
        residual_sum: block key -> (B, d) sum of the whitened innovations of that streak.
        nis_sum: block key -> (B,) sum of their NIS.
        vouched: block key -> (B,) bool, another reopenable block passed its gate during
            that streak (the state agrees with it: the streak is that sensor's fault).
        episode: (B,) bool, a divergence episode is open (its one inflation is spent).
        slip_factor: (B,) the wheel slip factor at the last epoch (``frontend.slip``; it
            recovers at most ``slip_recovery_per_s`` from there), or None (1: no slip).
        last_wheel_time: (B,) s, the last wheel epoch's time (the start of the recovery), or
            None.
        adaptation: the adaptive noise's and strong tracking's state
            (``frontend.adaptive.BlockAdaptation.memory``), or None (nothing adapted yet).
    """

    streak: dict[str, torch.Tensor]
    residual_sum: dict[str, torch.Tensor]
    nis_sum: dict[str, torch.Tensor]
    vouched: dict[str, torch.Tensor]
    episode: torch.Tensor
    slip_factor: torch.Tensor | None = None
    last_wheel_time: torch.Tensor | None = None
    adaptation: dict[str, dict[str, torch.Tensor]] | None = None


def reset_sigma_cap(
    cfg: EskfConfig, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """(15,) sigma that a reset's inflation may raise each error state to:
    ``divergence_max_sigma_factor`` times its configured initial sigma (position m, velocity
    m/s, attitude rad (the larger of the roll/pitch and yaw sigmas, every axis, at most pi),
    gyro bias rad/s, accel bias m/s^2)."""
    factor = cfg.divergence_max_sigma_factor
    attitude = min(factor * max(cfg.init_roll_pitch_sigma_rad, cfg.init_yaw_sigma_rad), math.pi)
    sigmas = (
        factor * cfg.init_position_sigma_m,
        factor * cfg.init_velocity_sigma_mps,
        attitude,
        factor * cfg.init_gyro_bias_sigma_radps,
        factor * cfg.init_accel_bias_sigma_mps2,
    )
    return torch.tensor(sigmas, dtype=dtype, device=device).repeat_interleave(3)


def streak_offset(
    candidate: torch.Tensor,
    residual_sum: torch.Tensor,
    nis_sum: torch.Tensor,
    count: torch.Tensor,
    segment: torch.Tensor,
    probability: float = OFFSET_PROBABILITY,
) -> torch.Tensor:
    """(B,) bool: some ``candidate`` block's streak of innovations shares an offset.

    A streak is the n = ``count`` latest innovations of a block (its rejections in a row and
    the current one), whitened by their innovation covariances: ``w_1 ... w_n`` (d each).
    Without an offset (the state consistent, the noise zero-mean of ANY scale, so a
    mis-specified sigma passes) ``F = |sum w|^2 / (n sum |w|^2)`` is Beta(d / 2,
    (n - 1) d / 2)-distributed; an offset common to the streak (a wrong state) drives it to
    1. True where F exceeds that distribution's ``probability`` quantile (n >= 2; one
    sample carries no such evidence).

    Args:
        candidate: (B, K) bool, blocks to test.
        residual_sum: (B, M) sum of the streak's whitened innovations, rows of all blocks.
        nis_sum: (B, K) sum of their NIS ``|w|^2``.
        count: (B, K) n, as float.
        segment: (M, K) 0/1 map from rows to blocks.
        probability: the test's level is ``1 - probability``.
    """
    if not bool(candidate.any()):
        return candidate.any(-1)
    share = ((residual_sum**2) @ segment) / (count * nis_sum).clamp_min(
        torch.finfo(nis_sum.dtype).tiny
    )
    dims = segment.sum(0).round().expand_as(count)
    limit = torch.full_like(share, math.inf)
    pairs = torch.stack((dims[candidate], count[candidate].round()), -1).long()
    for d, n in {tuple(p) for p in pairs.tolist() if p[1] >= 2}:
        quantile = float(betaincinv(d / 2, (n - 1) * d / 2, probability))
        limit = torch.where((dims == d) & (count.round() == n), quantile, limit)
    return (candidate & (share > limit)).any(-1)


class DivergenceGuard:
    """Per-sequence divergence detection and reset for the ESKF epoch loop (module docstring),
    and the gate's memory of rejections in a row.

    Per epoch: :meth:`propagated` remembers the propagated state (no computation); then
    :meth:`updated` checks the updated state, or :meth:`check` the propagated one in an
    epoch without measurements. The checks are batched; only when some sequence fails does
    the reset run (a ``torch.where`` over the batch), so an epoch where all pass costs a
    few reductions and one small batched Cholesky factorisation.

    Args:
        state: the initial state (B, ...), the first "last good" state.
        cov: (B, D, D) its covariance in the filter's (invariant) coordinates.
        cfg: ``divergence_inflation``, ``divergence_nis_scale`` and the initial sigmas of
            :func:`reset_sigma_cap`.
        blocks: the update's block keys, K.
        segment: (M, K) 0/1 map from stacked measurement rows to blocks.
        reopenable: (K,) bool, blocks whose gate re-opens after a streak of rejections.
        maps: ``(position, velocity, rotation) -> (T, T^-1)`` between the filter's
            coordinates and the conventional error state, (B, D, D) each.
        memory: the previous chunk's :class:`GateMemory` (None: nothing rejected yet).

    Attributes:
        good_state, good_cov: the last good state and covariance of every sequence.
        streak: (B, K) rejections in a row of each reopenable block (the gate re-opens it
            after ``gate_reopen_after``; 0 for the others).
        vouched: (B, K) bool, another reopenable block passed its gate during the block's
            current streak (its blow-up is then no divergence).
        episode: (B,) bool, a divergence episode is open: a reset happened and no reopenable
            block has passed its gate since; a further reset does not inflate again.
    """

    def __init__(
        self,
        state: NavState,
        cov: torch.Tensor,
        cfg: EskfConfig,
        blocks: list[str],
        segment: torch.Tensor,
        reopenable: torch.Tensor,
        maps: Callable[
            [torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]
        ],
        memory: GateMemory | None = None,
    ) -> None:
        batch, dim = cov.shape[0], cov.shape[-1]
        dtype, device = cov.dtype, cov.device
        self.good_state, self.good_cov = state, cov
        self.prior_state, self.prior_cov = state, cov
        self.inflation = cfg.divergence_inflation
        self.nis_scale = cfg.divergence_nis_scale
        cap = reset_sigma_cap(cfg, dtype, device) ** 2
        self._cap_var = torch.cat(
            (cap, torch.full((dim - cap.numel(),), math.inf, dtype=dtype, device=device))
        )
        self.blocks, self.segment, self.reopenable, self.maps = blocks, segment, reopenable, maps
        self._dims = segment.sum(0).to(torch.long).tolist()
        self._offsets = [0, *itertools.accumulate(self._dims)]
        self.streak = torch.zeros(batch, len(blocks), dtype=dtype, device=device)
        self.residual_sum = torch.zeros(batch, segment.shape[0], dtype=dtype, device=device)
        self.nis_sum = torch.zeros(batch, len(blocks), dtype=dtype, device=device)
        self.vouched = torch.zeros(batch, len(blocks), dtype=torch.bool, device=device)
        self.episode = torch.zeros(batch, dtype=torch.bool, device=device)
        # (B,) a re-openable block passed its gate in some epoch (vouches for the streaks of
        # the previous chunk's blocks that this one lacks)
        self._calm_seen = torch.zeros(batch, dtype=torch.bool, device=device)
        self._carried: GateMemory | None = None
        if memory is not None:
            self._load(memory)
        self._open = bool((self.streak > 0).any())  # some streak runs (else sums are 0)
        self._healthy = torch.zeros(batch, dtype=torch.long, device=device)
        self._none = torch.zeros(batch, dtype=torch.bool, device=device)
        self._eye = torch.eye(dim, dtype=dtype, device=device)
        self._gate: torch.Tensor | None = None
        self._limit: torch.Tensor | None = None

    def _load(self, memory: GateMemory) -> None:
        """Take over a previous chunk's memory (blocks it did not have start afresh; its
        blocks this chunk lacks pass through, :meth:`memory`)."""
        self.episode = memory.episode.to(self.episode.device)
        self._carried = memory
        for k, key in enumerate(self.blocks):
            rows = slice(self._offsets[k], self._offsets[k + 1])
            if key in memory.streak and memory.residual_sum[key].shape[-1] == self._dims[k]:
                self.streak[:, k] = memory.streak[key]
                self.vouched[:, k] = memory.vouched[key]
                self.nis_sum[:, k] = memory.nis_sum[key]
                self.residual_sum[:, rows] = memory.residual_sum[key]

    def memory(self) -> GateMemory:
        """The gate's and the guard's memory now, for the next chunk's ``run_eskf``: this
        chunk's blocks, and the previous memory's blocks this chunk did not measure (their
        streaks unchanged, vouched for where another block passed its gate)."""
        rows = [slice(a, b) for a, b in itertools.pairwise(self._offsets)]
        out = GateMemory(
            streak={key: self.streak[:, k] for k, key in enumerate(self.blocks)},
            residual_sum={key: self.residual_sum[:, rows[k]] for k, key in enumerate(self.blocks)},
            nis_sum={key: self.nis_sum[:, k] for k, key in enumerate(self.blocks)},
            vouched={key: self.vouched[:, k] for k, key in enumerate(self.blocks)},
            episode=self.episode,
        )
        carried = self._carried
        lacking = [] if carried is None else [k for k in carried.streak if k not in self.blocks]
        for key in lacking:
            out.streak[key] = carried.streak[key]
            out.residual_sum[key] = carried.residual_sum[key]
            out.nis_sum[key] = carried.nis_sum[key]
            streak_open = carried.streak[key] > 0
            out.vouched[key] = carried.vouched[key] | (self._calm_seen & streak_open)
        return out

    def propagated(self, state: NavState, cov: torch.Tensor) -> None:
        """Remember the propagated state of this epoch (the reset target of its update)."""
        self.prior_state, self.prior_cov = state, cov

    def _not_psd(self, cov: torch.Tensor, info: torch.Tensor) -> torch.Tensor:
        """(B,) bool, ``cov`` is not positive semi-definite: the Cholesky factorisation of
        ``cov + 1e-9 max(diag cov) I`` fails. ``info`` is that of ``cov`` itself: where it
        succeeded no second factorisation is needed (exactly known states, zero variances,
        pass; round-off stays far below the jitter)."""
        largest = torch.diagonal(cov, dim1=-2, dim2=-1).abs().amax(-1)
        jitter = _PSD_JITTER * largest + torch.finfo(cov.dtype).tiny
        loaded = torch.linalg.cholesky_ex(cov + jitter[:, None, None] * self._eye).info
        return (info != 0) & (loaded != 0)

    def _inflate(self, state: NavState, cov: torch.Tensor) -> torch.Tensor:
        """``cov`` (B, D, D) inflated for a reset to ``state``: in conventional coordinates
        ``P' = S P S`` with ``S = diag(s)``, ``s_i^2 = min(inflation, max(1, cap_i^2 / P_ii))``:
        every sigma grows by ``sqrt(inflation)`` but not past :func:`reset_sigma_cap` (a sigma
        already above it stays). ``S P S`` is a congruence: positive semi-definite stays so."""
        nav_conv, nav_inv = self.maps(state.position, state.velocity, state.rotation)
        to_conv, to_inv = self._eye.repeat(cov.shape[0], 1, 1), self._eye.repeat(cov.shape[0], 1, 1)
        nav = slice(0, nav_conv.shape[-1])  # states after the navigation ones map to themselves
        to_conv[:, nav, nav], to_inv[:, nav, nav] = nav_conv, nav_inv
        conv = to_conv @ cov @ to_conv.mT
        var = torch.diagonal(conv, dim1=-2, dim2=-1)
        target = torch.minimum(self.inflation * var, torch.maximum(var, self._cap_var))
        scale = torch.where(var > 0, (target / var.where(var > 0, 1.0)).sqrt(), 1.0)
        conv = scale[:, :, None] * conv * scale[:, None, :]
        return to_inv @ conv @ to_inv.mT

    def _reset(
        self, code: torch.Tensor, state: NavState, cov: torch.Tensor
    ) -> tuple[NavState, torch.Tensor]:
        """Sequences with ``code != 0`` go back to their last good state (this epoch's
        propagated one when that is finite), the covariance inflated once per episode; the
        others keep theirs. Either becomes the new last good state."""
        prior_ok = _finite(self.prior_state, self.prior_cov)
        good_state = _pick(prior_ok, self.prior_state, self.good_state)
        good_cov = torch.where(prior_ok[:, None, None], self.prior_cov, self.good_cov)
        bad = code != 0
        inflate = bad & ~self.episode
        if bool(inflate.any()):
            good_cov = torch.where(
                inflate[:, None, None], self._inflate(good_state, good_cov), good_cov
            )
        state = _pick(bad, good_state, state)
        cov = torch.where(bad[:, None, None], good_cov, cov)
        self.good_state, self.good_cov = state, cov
        return state, cov

    def check(
        self, state: NavState, cov: torch.Tensor
    ) -> tuple[NavState, torch.Tensor, torch.Tensor]:
        """Check a propagated state in an epoch without update (finiteness only: propagation
        keeps a covariance positive semi-definite).

        Returns:
            (state, cov, code (B,)): unhealthy sequences reset (see the module docstring).
        """
        finite = _finite(state, cov)
        if bool(finite.all()):
            self.good_state, self.good_cov = state, cov
            return state, cov, self._healthy
        code = torch.where(finite, 0, NONFINITE)
        state, cov = self._reset(code, state, cov)
        self.episode = self.episode | ~finite
        return state, cov, code

    def _streaks(
        self,
        accepted: torch.Tensor,
        nis: torch.Tensor,
        gate: torch.Tensor,
        present: torch.Tensor,
        white: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Update the re-openable blocks' streaks (count, sums, vouching) with this epoch
        (arguments as :meth:`updated`'s). Returns (B,) NIS blow-up (a re-opened block whose
        streak shares an offset and that nothing vouched for) and (B,) calm (a re-openable
        block passed its gate: the end of a divergence episode)."""
        present = present & self.reopenable  # other blocks never re-open: no streak kept
        calm_blocks = present & accepted & (nis < gate)
        if not self._open and torch.equal(calm_blocks, present):
            return self._none, calm_blocks.any(-1)  # no streak open, none starts
        present_rows = (present.to(white.dtype) @ self.segment.mT) > 0.5
        residual_sum = self.residual_sum + torch.where(present_rows, white, 0.0)
        nis_sum = self.nis_sum + torch.where(present, nis, 0.0)
        count = self.streak + present.to(self.streak.dtype)
        calm_count = calm_blocks.sum(-1, keepdim=True)
        vouched = self.vouched | (calm_count - calm_blocks.long() > 0)
        candidate = present & accepted & (nis > self._limit) & ~vouched
        blowup = streak_offset(candidate, residual_sum, nis_sum, count, self.segment)
        rejected = present & ~accepted
        rejected_rows = (rejected.to(white.dtype) @ self.segment.mT) > 0.5
        self.streak = torch.where(present, torch.where(accepted, 0.0, count), self.streak)
        self.vouched = vouched & (self.streak > 0)
        self.residual_sum = torch.where(
            rejected_rows, residual_sum, torch.where(present_rows, 0.0, self.residual_sum)
        )
        self.nis_sum = torch.where(rejected, nis_sum, torch.where(present, 0.0, self.nis_sum))
        self._open = bool((self.streak > 0).any())
        return blowup, calm_count[:, 0] > 0

    def updated(
        self,
        state: NavState,
        cov: torch.Tensor,
        accepted: torch.Tensor,
        nis: torch.Tensor,
        gate: torch.Tensor,
        factorisation_failed: torch.Tensor,
        present: torch.Tensor,
        white: torch.Tensor,
    ) -> tuple[NavState, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Check the updated state; reset the sequences that diverged; count the gate's
        rejections in a row.

        Args:
            state, cov: the updated state and covariance.
            accepted: (B, K) bool, blocks fused in the update (gate passed or re-opened).
            nis: (B, K) their normalised innovation squared.
            gate: (K,) chi-square gate of each block (huge for ungated blocks: never a
                blow-up).
            factorisation_failed: (B,) bool, the innovation covariance's Cholesky failed.
            present: (B, K) bool, blocks measured in this epoch (and not excluded).
            white: (B, M) whitened innovations, ``L_k^-1 r_k`` per block (``S_k = L_k L_k^T``).

        Returns:
            (state, cov, accepted with the diverged sequences' blocks set False, code (B,)).
        """
        finite = _finite(state, cov)
        info = torch.linalg.cholesky_ex(cov).info
        if gate is not self._gate:
            self._gate, self._limit = gate, self.nis_scale * gate
        blowup, calm = self._streaks(accepted, nis, gate, present, white)
        self._calm_seen = self._calm_seen | calm
        if bool((finite & (info == 0) & ~(factorisation_failed | blowup)).all()):
            self.good_state, self.good_cov = state, cov
            self.episode = self.episode & ~calm
            return state, cov, accepted, self._healthy
        not_psd = finite & self._not_psd(torch.where(finite[:, None, None], cov, self._eye), info)
        code = torch.where(finite, 0, NONFINITE)
        code = code | torch.where(not_psd | factorisation_failed, NOT_POSITIVE_DEFINITE, 0)
        code = code | torch.where(blowup, NIS_BLOWUP, 0)
        state, cov = self._reset(code, state, cov)
        self.episode = torch.where(code != 0, True, self.episode & ~calm)
        return state, cov, accepted & (code == 0)[:, None], code


class EstimationInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) stopped ``run_eskf`` in its epoch loop; the epochs done come with it.

    A ``KeyboardInterrupt``, so a caller that does not look for it still stops.

    Attributes:
        result: the ``EskfResult`` of the full shape (B, E + 1); epochs after the last
            completed one are masked out (``mask`` False, state held, nothing accepted).
        epochs_done: completed epochs (0 when the first was interrupted).
        epochs_total: E, the epochs scheduled.
    """

    def __init__(self, result: object, epochs_done: int, epochs_total: int) -> None:
        super().__init__(f"interrupted after {epochs_done} of {epochs_total} epochs")
        self.result = result
        self.epochs_done = epochs_done
        self.epochs_total = epochs_total


class InterruptCatcher:
    """Context manager around the ESKF epoch loop: a ``KeyboardInterrupt`` inside ends the
    loop instead of the run, and :meth:`settle` then cuts the per-epoch records back to the
    last completed epoch and pads them to the full length.

    Attributes:
        caught: an interrupt ended the loop.
    """

    def __init__(self) -> None:
        self.caught = False

    def __enter__(self) -> InterruptCatcher:
        return self

    def __exit__(self, kind, value, traceback) -> bool:
        self.caught = kind is not None and issubclass(kind, KeyboardInterrupt)
        return self.caught

    def settle(
        self,
        held: list[list[torch.Tensor]],
        zeroed: list[list[torch.Tensor]],
        epochs_total: int,
    ) -> int:
        """Make every per-epoch list ``epochs_total + 1`` long; return the completed epochs.

        Args:
            held: lists whose missing epochs repeat the last completed epoch's entry (state,
                covariance, slip factor).
            zeroed: lists whose missing epochs repeat entry 0, the initial all-zero entry
                (accepted, NIS, divergence codes).
            epochs_total: E.
        """
        lists = held + zeroed
        done = min(len(x) for x in lists) - 1
        for values in held:
            del values[done + 1 :]
            values.extend([values[-1]] * (epochs_total - done))
        for values in zeroed:
            del values[done + 1 :]
            values.extend([values[0]] * (epochs_total - done))
        return done
