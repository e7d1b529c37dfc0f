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
  ``divergence_nis_scale`` times its gate (code :data:`NIS_BLOWUP`). Gating rejects such a
  block unless it was re-opened after ``gate_reopen_after`` rejections in a row; its NIS then
  says that the covariance claims far more certainty than the data allow. (NEES, the same
  test on the estimation error, needs the truth, which a running filter lacks; the NIS is its
  observable counterpart.)

A diverged sequence is reset to its last good state, the latest one that passed the checks
(the propagated state of the same epoch when that was healthy: the update is discarded),
with the covariance multiplied by ``divergence_inflation``; its update counts as not
accepted. The codes add up (bit flags) and are reported per epoch
(``EskfResult.divergence``, the ``divergence`` column of ``diagnostics.csv``). Sequences
that do not diverge are untouched (``torch.where`` picks their own values), so a batch never
mixes sequences and a run without faults is bit for bit the run without the guard.

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
]

import dataclasses
import math

import torch

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
_NAN_OK = {"gnss": ("sigma",)}  # fields where a non-finite value means "use the default"


def _usable(stream, nan_ok: tuple[str, ...]) -> torch.Tensor:
    """(B, N) bool: masked-in samples with finite time and values, later than every earlier
    one of the same stream."""
    good = stream.mask & torch.isfinite(stream.t)
    for name, value in stream.tensors().items():
        if name in ("t", "mask") or name in nan_ok:
            continue
        flat = value.reshape(*value.shape[:2], math.prod(value.shape[2:]))
        good = good & torch.isfinite(flat).all(-1)
    neg_inf = torch.tensor(-torch.inf, dtype=stream.t.dtype, device=stream.t.device)
    latest = torch.where(good, stream.t, neg_inf).cummax(dim=1).values
    earlier = torch.cat((torch.full_like(latest[:, :1], -torch.inf), latest[:, :-1]), 1)
    return good & (stream.t > earlier)


def _drop(stream, usable: torch.Tensor):
    """The stream with ``mask = usable`` and the values of the other samples set to 0."""

    def clean(name: str, value: torch.Tensor) -> torch.Tensor:
        if name == "mask":
            return usable
        keep = usable.reshape(*usable.shape, *([1] * (value.dim() - 2)))
        return torch.where(keep, value, torch.zeros((), dtype=value.dtype, device=value.device))

    return type(stream)(**{k: clean(k, v) for k, v in stream.tensors().items()})


def sanitize_sequence(seq: Sequence) -> tuple[Sequence, dict[str, torch.Tensor]]:
    """Mask out the samples the filter must not use (module docstring: the input rule).

    Args:
        seq: B sequences; the IMU, wheel, GNSS, pose and pose-source streams are checked
            (ground truth is left alone: the filter does not read it).

    Returns:
        (the cleaned sequence, stream -> (B,) int64 number of samples dropped). Streams are
        keyed as in ``EskfResult.present`` (``"imu"``, ``"wheel"``, ``"gnss"``, ``"pose"``,
        ``"pose:<name>"``). When nothing is dropped the input's tensors come back unchanged
        in value.
    """
    streams = {"imu": seq.imu, "wheel": seq.wheel, "gnss": seq.gnss, "pose": seq.poses}
    streams |= {f"pose:{name}": s for name, s in seq.pose_sources.items()}
    cleaned: dict[str, object] = {}
    dropped: dict[str, torch.Tensor] = {}
    for key, stream in streams.items():
        if stream is None:
            continue
        usable = _usable(stream, _NAN_OK.get(key, ()))
        dropped[key] = (stream.mask & ~usable).sum(-1)
        cleaned[key] = _drop(stream, usable)
    sources = {name: cleaned[f"pose:{name}"] for name in seq.pose_sources}
    out = dataclasses.replace(
        seq,
        imu=cleaned["imu"],
        wheel=cleaned.get("wheel"),
        gnss=cleaned.get("gnss"),
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


class DivergenceGuard:
    """Per-sequence divergence detection and reset for the ESKF epoch loop (module docstring).

    Per epoch: :meth:`propagated` remembers the propagated state (no computation); then
    :meth:`updated` checks the updated state, or :meth:`check` the propagated one in an
    epoch without measurements. The checks are batched; only when some sequence fails does
    the reset run (a ``torch.where`` over the batch), so an epoch where all pass costs a
    few reductions and one small batched Cholesky factorisation.

    Args:
        state: the initial state (B, ...), the first "last good" state.
        cov: (B, 15, 15) its covariance (any fixed coordinates: the guard only scales it).
        inflation: covariance multiplier on a reset (>= 1).
        nis_scale: an accepted gated block diverges above ``nis_scale`` x its gate.

    Attributes:
        good_state, good_cov: the last good state and covariance of every sequence.
        fresh: (B,) bool, the last good state is a reset that no healthy check has followed
            yet; resetting again to it does not inflate its covariance again.
    """

    def __init__(
        self, state: NavState, cov: torch.Tensor, inflation: float, nis_scale: float
    ) -> None:
        self.good_state, self.good_cov = state, cov
        self.prior_state, self.prior_cov = state, cov
        self.inflation = inflation
        self.nis_scale = nis_scale
        self.fresh = torch.zeros(cov.shape[0], dtype=torch.bool, device=cov.device)
        self._none = self.fresh
        self._healthy = torch.zeros(cov.shape[0], dtype=torch.long, device=cov.device)
        self._eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
        self._gate: torch.Tensor | None = None
        self._limit: torch.Tensor | None = None

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

    def _reset(
        self, code: torch.Tensor, state: NavState, cov: torch.Tensor
    ) -> tuple[NavState, torch.Tensor]:
        """Sequences with ``code != 0`` go back to their last good state (this epoch's
        propagated one when that is finite) with inflated covariance; the others keep theirs.
        Either becomes the new last good state."""
        prior_ok = _finite(self.prior_state, self.prior_cov)
        good_state = _pick(prior_ok, self.prior_state, self.good_state)
        good_cov = torch.where(prior_ok[:, None, None], self.prior_cov, self.good_cov)
        fresh = self.fresh & ~prior_ok
        bad = code != 0
        scale = torch.where(fresh, 1.0, self.inflation).to(cov.dtype)
        state = _pick(bad, good_state, state)
        cov = torch.where(bad[:, None, None], good_cov * scale[:, None, None], cov)
        self.good_state, self.good_cov, self.fresh = state, cov, bad
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
            self.good_state, self.good_cov, self.fresh = state, cov, self._none
            return state, cov, self._healthy
        code = torch.where(finite, 0, NONFINITE)
        state, cov = self._reset(code, state, cov)
        return state, cov, code

    def updated(
        self,
        state: NavState,
        cov: torch.Tensor,
        accepted: torch.Tensor,
        nis: torch.Tensor,
        gate: torch.Tensor,
        factorisation_failed: torch.Tensor,
    ) -> tuple[NavState, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Check the updated state; reset the sequences that diverged.

        Args:
            state, cov: the updated state and covariance.
            accepted: (B, K) bool, blocks fused in the update.
            nis: (B, K) their normalised innovation squared.
            gate: (K,) chi-square gate of each block (huge for ungated blocks: never a
                blow-up).
            factorisation_failed: (B,) bool, the innovation covariance's Cholesky failed.

        Returns:
            (state, cov, accepted with the diverged sequences' blocks set False, code (B,)).
        """
        finite = _finite(state, cov)
        info = torch.linalg.cholesky_ex(cov).info
        if gate is not self._gate:
            self._gate, self._limit = gate, self.nis_scale * gate
        blowup = (accepted & (nis > self._limit)).any(-1)
        if bool((finite & (info == 0) & ~(factorisation_failed | blowup)).all()):
            self.good_state, self.good_cov, self.fresh = state, cov, self._none
            return state, cov, accepted, self._healthy
        not_psd = finite & self._not_psd(torch.where(finite[:, None, None], cov, self._eye), info)
        code = torch.where(finite, 0, NONFINITE)
        code = code | torch.where(not_psd | factorisation_failed, NOT_POSITIVE_DEFINITE, 0)
        code = code | torch.where(blowup, NIS_BLOWUP, 0)
        state, cov = self._reset(code, state, cov)
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
