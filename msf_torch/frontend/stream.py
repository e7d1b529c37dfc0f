"""Filter a run piece by piece as its data arrives (a live robot, or a log too long to hold).

:class:`EskfStream` takes consecutive pieces of one run (``Sequence``, B = 1, each holding the
samples recorded since the previous piece) and filters each from where the previous one
stopped, handing on everything :func:`~msf_torch.frontend.eskf.run_eskf` carries between
chunks: the state and covariance at the last IMU sample, the gate's streaks and the wheel
slip factor, drifting source frames, online calibration, pose-source pairs and the
source-fault detector (``EskfResult.*_memory``). The pieces together equal the run filtered
in one piece to round-off, wherever the boundaries fall on the IMU samples, except that the
pseudo-measurements (NHC, ZUPT) and the epoch-wise adaptive noise also act at each piece's
last IMU sample (an extra epoch there). The adaptive noise's state carries over
(``GateMemory.adaptation``; before 2026-11-29 it restarted in every piece: 0.23 m apart
with adaptive GNSS noise).

What the stream does with the samples:

* The previous piece's last IMU sample is put in front of the next piece's IMU (the chunks
  of ``run_eskf`` share it); IMU samples at or before it are late and skipped. So is each
  pose source's latest sample up to there: the pair it starts with the next sample is
  fused in the next piece.
* A measurement (wheel, GNSS fix or velocity, pose, pose source) stamped after a piece's
  last IMU sample (beyond ``time_tolerance_s``) is held back and fused with the next piece,
  where the IMU reaches it: a fix that arrives before the IMU sample after it is not lost.
* A piece that ends on IMU samples lying on a straight line (a filled-in stretch of the
  recording, :func:`~msf_torch.sensors.imu_gaps.interpolated_imu_samples`, whose length
  sets its variance) is filtered up to the real sample the line starts from; the rest
  waits for the next piece, up to ``max_hold_s`` of it (:meth:`EskfStream.finish` filters
  what is held when the run ends). A boundary inside a 2-s stretch had moved the estimate
  by up to 1.3 m from the run in one piece.
* A measurement stamped at or before the previous piece's last IMU sample, in a later
  piece, is late: skipped and counted (``late_samples``), with one warning per stream.
* The first piece sets the initial state from its own data (:func:`initial_state`: the
  heading from the GNSS track or course, which needs its first seconds) unless
  ``initial`` is given.

:func:`concat_results` joins the pieces' results into one (the stream's ``results`` when it
keeps them), :func:`last_state` is the state a next piece starts from.

Example:
    >>> from msf_torch.sim import SimConfig, simulate_run
    >>> from msf_torch.frontend.stream import EskfStream, time_slice
    >>> run = simulate_run(SimConfig(duration_s=20.0, slip_episodes=0), seed=1)
    >>> stream = EskfStream()
    >>> parts = [stream.push(time_slice(run.sequence, a, a + 5.0)) for a in (0.0, 5.0, 10.0)]
    >>> [round(float(p.t[0, -1]), 3) for p in parts]
    [4.995, 9.995, 14.995]
"""

from __future__ import annotations

__all__ = ["EskfStream", "concat_results", "last_state", "time_slice"]

import dataclasses
import warnings
from typing import Any

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.sensors.imu_gaps import open_stretch_start
from msf_torch.types import NavState, Sequence

_MEMORIES = ("gate_memory", "frame_memory", "calibration_memory", "pair_memory", "fault_memory")


def last_state(result: EskfResult) -> tuple[NavState, torch.Tensor]:
    """State (B = 1) and conventional covariance (1, 15, 15) at the last real epoch."""
    last = int(result.mask[0].sum()) - 1

    def at(x: torch.Tensor) -> torch.Tensor:
        return x[:, last]

    fields = (result.position, result.velocity, result.rotation)
    state = NavState(*(at(x) for x in fields), at(result.gyro_bias), at(result.accel_bias))
    return state, at(result.covariance)


def _per_epoch(values: list[torch.Tensor | None], results: list[EskfResult], keeps) -> torch.Tensor:
    """One (B, E + 1, ...) tensor from the chunks' per-epoch ``values`` (a chunk's None or
    missing entry: zeros like the others')."""
    like = next(v for v in values if v is not None)
    parts = []
    for value, result, keep in zip(values, results, keeps, strict=True):
        if value is None:
            value = like.new_zeros(like.shape[0], result.mask.shape[1], *like.shape[2:])
        parts.append(value[:, keep])
    return torch.cat(parts, 1)


def concat_results(
    results: list[EskfResult], dropped_samples: dict[str, torch.Tensor] | None = None
) -> EskfResult:
    """One result from consecutive chunks' results (B = 1): real epochs only, each later
    chunk's start epoch (its predecessor's last) dropped.

    Every per-epoch field (a tensor (B, E + 1, ...) or a dict of them: states, covariance,
    per-sensor flags and NIS, divergence codes, gaps, fading factors, noise estimates,
    source-fault flags and Z, any later one) is concatenated, a dict's keys united (zeros
    where a chunk lacks one); ``dropped_samples`` is the given one (the whole run's), else
    the chunks' summed; other fields (names, the ``*_memory`` fields, per-run flags) are the
    last chunk's.
    """
    keeps = []
    for k, r in enumerate(results):
        keep = r.mask[0].clone()
        keep[0] = keep[0] and k == 0
        keeps.append(keep)

    def is_per_epoch(value: object, result: EskfResult) -> bool:
        return (
            isinstance(value, torch.Tensor)
            and value.dim() >= 2
            and value.shape[1] == result.mask.shape[1]
        )

    if dropped_samples is None:
        dropped_samples = {}
        for result in results:
            for key, count in result.dropped_samples.items():
                dropped_samples[key] = dropped_samples.get(key, 0) + count
    fields: dict[str, Any] = {}
    for name in (f.name for f in dataclasses.fields(EskfResult)):
        values = [getattr(r, name) for r in results]
        if name == "dropped_samples":
            fields[name] = dropped_samples
        elif any(is_per_epoch(v, r) for v, r in zip(values, results, strict=True)):
            fields[name] = _per_epoch(values, results, keeps)
        elif isinstance(values[0], dict) and any(
            is_per_epoch(x, results[0]) for x in values[0].values()
        ):
            keys = list(dict.fromkeys(key for value in values for key in value))
            fields[name] = {
                key: _per_epoch([value.get(key) for value in values], results, keeps)
                for key in keys
            }
        else:
            fields[name] = values[-1]
    return EskfResult(**fields)


def time_slice(seq: Sequence, start_s: float, end_s: float) -> Sequence:
    """The samples of every stream of ``seq`` (B = 1) with ``start_s <= t < end_s`` (s, the
    sequence's clock), masked-out samples dropped: a piece of the run as a recorder would
    hand it on. Labels and meta are kept whole."""
    if seq.batch_size != 1:
        raise ValueError(f"time_slice takes one sequence (B = 1), got B = {seq.batch_size}")

    def cut(stream):
        stream = stream.compact()
        keep = (stream.t[0] >= start_s) & (stream.t[0] < end_s)
        return stream.map(lambda x: x[:, keep])

    streams = {name: cut(stream) for name, stream in seq.streams().items()}
    sources = {name: cut(stream) for name, stream in seq.pose_sources.items()}
    return dataclasses.replace(seq, pose_sources=sources, **streams)


class EskfStream:
    """The ESKF over one run fed piece by piece (module docstring).

    Args:
        cfg: front-end settings (default :class:`EskfConfig()`).
        noise: noise tensors (default ``EskfNoise.from_config(cfg)``).
        initial: optional initial state (B = 1) and covariance (1, 15, 15) at the first
            piece's first IMU sample; default: from the first piece's data.
        keep_results: keep every piece's result in :attr:`results` (for
            :func:`concat_results`); off for a long-running stream.
        max_hold_s: longest tail of IMU samples held back as a possibly unfinished
            filled-in stretch, s; a longer one is filtered as it is (the stretch is then
            modelled as two).

    Attributes:
        results: the pieces' results (``keep_results``).
        late_samples: stream key (``"imu"``, ``"gnss"``, ``"pose:<name>"``, ...) -> samples
            skipped because they arrived after the IMU had passed their time.
    """

    def __init__(
        self,
        cfg: EskfConfig | None = None,
        noise: EskfNoise | None = None,
        initial: tuple[NavState, torch.Tensor] | None = None,
        keep_results: bool = True,
        max_hold_s: float = 10.0,
    ) -> None:
        self.cfg = cfg or EskfConfig()
        self.max_hold_s = max_hold_s
        self.noise = noise
        self.keep_results = keep_results
        self.results: list[EskfResult] = []
        self.late_samples: dict[str, int] = {}
        self._initial = initial
        self._memories: dict[str, Any] = {}
        # the last IMU sample and each pose source's latest sample up to it
        self._boundary: Sequence | None = None
        self._pending: Sequence | None = None  # measurements after the last IMU sample
        self._finishing = False  # finish(): filter to the last IMU sample, hold nothing

    def push(self, piece: Sequence) -> EskfResult | None:
        """Filter the next piece of the run.

        Args:
            piece: B = 1, the samples recorded since the previous piece (any streams; the
                IMU's must be later than the previous piece's last IMU sample).

        Returns:
            the piece's :class:`EskfResult` (epoch 0: the state at the previous piece's last
            IMU sample, or the initial state), or None when the piece adds no IMU sample to
            filter up to (its samples wait for the next piece; also when all its new IMU
            samples may continue a filled-in stretch).

        Raises:
            ValueError: B != 1; a first piece with fewer than two IMU samples.
        """
        if piece.batch_size != 1:
            raise ValueError(f"EskfStream takes one run (B = 1), got B = {piece.batch_size}")
        tol = self.cfg.time_tolerance_s
        piece = _joined(self._pending, piece) if self._pending is not None else piece
        if self._boundary is not None:
            piece = self._drop_late(piece, float(self._boundary.imu.t[0, 0]), tol)
        new_samples = int(piece.imu.mask.sum())
        if new_samples < (2 if self._boundary is None else 1):
            # nothing to filter up to: the samples wait for more IMU
            self._pending = piece
            return None
        unjoined = piece
        if self._boundary is not None:
            piece = _joined(self._boundary, piece)
        imu = piece.imu.compact()
        last = self._last_to_filter(imu)
        if last < 1:
            self._pending = unjoined  # all new IMU samples may lie in an open stretch: wait
            return None
        t_last = float(imu.t[0, last])
        held = imu.map(lambda x: x[:, last + 1 :])
        self._pending = _after(piece, t_last + tol, held)
        filtered = dataclasses.replace(piece, imu=imu.map(lambda x: x[:, : last + 1]))
        result = run_eskf(
            filtered,
            self.cfg,
            self.noise,
            initial=self._initial,
            **self._memories,
        )
        self._initial = last_state(result)
        self._memories = {name: getattr(result, name) for name in _MEMORIES}
        self._boundary = _boundary(filtered, last, t_last + tol)
        if self.keep_results:
            self.results.append(result)
        return result

    def finish(self) -> EskfResult | None:
        """The run has ended: filter the IMU samples still held back as a possibly
        unfinished filled-in stretch (a stretch that reaches the end of the run is modelled
        up to there, as in the run in one piece).

        Returns:
            the result over the held samples, or None when none were held (measurements
            stamped after the last IMU sample stay unfused: no IMU reaches them).
        """
        if self._pending is None or self._pending.imu.length == 0:
            return None
        piece, self._pending = self._pending, None
        self._finishing = True
        try:
            return self.push(piece)
        finally:
            self._finishing = False

    def _last_to_filter(self, imu) -> int:
        """Index of the last IMU sample of the (compacted) piece to filter now: the last,
        unless the piece ends inside what may be a filled-in stretch
        (:func:`~msf_torch.sensors.imu_gaps.open_stretch_start`) no longer than
        ``max_hold_s``: then the real sample the stretch starts from, the rest held back
        until the stretch's end is known (its variance grows with its whole length)."""
        last = imu.length - 1
        if self.cfg.imu_interpolated_min_samples == 0 or self._finishing:
            return last
        start = open_stretch_start(imu.t[0], imu.gyro[0], imu.accel[0])
        if start is None or float(imu.t[0, last] - imu.t[0, start]) > self.max_hold_s:
            return last
        return start

    def _drop_late(self, piece: Sequence, t_boundary: float, tol: float) -> Sequence:
        """``piece`` without the samples stamped at or before the last IMU sample filtered
        (IMU: at or before it; measurements: within ``tol`` after it too, where the previous
        piece fused them), counted in :attr:`late_samples` and warned about once each."""
        streams = {"imu": piece.imu}
        streams |= {k: v for k, v in piece.streams().items() if k not in ("imu", "ground_truth")}
        streams |= {f"pose:{k}": v for k, v in piece.pose_sources.items()}
        kept: dict[str, Any] = {}
        for key, stream in streams.items():
            stream = stream.compact()
            limit = t_boundary if key == "imu" else t_boundary + tol
            late = stream.t[0] <= limit
            count = int(late.sum())
            if count:
                if key not in self.late_samples:
                    warnings.warn(
                        f"EskfStream: {count} {key} sample(s) stamped at or before "
                        f"{t_boundary:.6f} s, where the filter already is: skipped",
                        stacklevel=3,
                    )
                self.late_samples[key] = self.late_samples.get(key, 0) + count
            kept[key] = stream.map(lambda x, k=~late: x[:, k])
        sources = {k[5:]: v for k, v in kept.items() if k.startswith("pose:")}
        others = {k: v for k, v in kept.items() if not k.startswith("pose:")}
        return dataclasses.replace(piece, pose_sources=sources, **others)


def _boundary(seq: Sequence, index: int, t: float) -> Sequence:
    """A piece holding IMU sample ``index`` of ``seq``'s compacted IMU and each pose
    source's latest sample stamped at or before ``t`` (s)."""
    imu = seq.imu.compact()
    sources = {}
    for name, stream in seq.pose_sources.items():
        stream = stream.compact()
        latest = int((stream.t[0] <= t).sum()) - 1
        if latest >= 0:
            sources[name] = stream.map(lambda x, k=latest: x[:, k : k + 1])
    return Sequence(
        names=list(seq.names),
        imu=imu.map(lambda x: x[:, index : index + 1]),
        meta=seq.meta,
        pose_sources=sources,
    )


def _after(seq: Sequence, t: float, imu=None) -> Sequence | None:
    """The measurements of ``seq`` stamped after ``t`` (no ground truth) with ``imu`` (held
    IMU samples; default none), or None when there are none of either."""
    streams = {k: v.compact() for k, v in seq.streams().items() if k not in ("imu", "ground_truth")}
    sources = {k: v.compact() for k, v in seq.pose_sources.items()}
    later = {k: v.map(lambda x, s=v: x[:, s.t[0] > t]) for k, v in streams.items()}
    later_sources = {k: v.map(lambda x, s=v: x[:, s.t[0] > t]) for k, v in sources.items()}
    imu = seq.imu.map(lambda x: x[:, :0]) if imu is None else imu
    if not any(v.length for v in (*later.values(), *later_sources.values(), imu)):
        return None
    return Sequence(
        names=list(seq.names),
        imu=imu,
        meta=seq.meta,
        pose_sources=later_sources,
        **later,
    )


def _joined(first: Sequence, second: Sequence) -> Sequence:
    """``first``'s samples followed by ``second``'s, stream by stream (B = 1, compacted);
    labels, meta and ground truth from ``second``."""
    streams: dict[str, Any] = {}
    for name in ("imu", "wheel", "gnss", "gnss_velocity", "gnss_heading", "magnetometer", "poses"):
        a, b = getattr(first, name), getattr(second, name)
        streams[name] = _cat(a, b)
    names = dict.fromkeys([*first.pose_sources, *second.pose_sources])
    sources = {n: _cat(first.pose_sources.get(n), second.pose_sources.get(n)) for n in names}
    return dataclasses.replace(second, pose_sources=sources, **streams)


def _cat(a, b):
    """Two B = 1 streams of one kind, ``a``'s samples first (either may be None)."""
    if a is None or b is None:
        return b if a is None else a.compact()
    a, b = a.compact(), b.compact()
    return type(a)(**{k: torch.cat((v, getattr(b, k)), 1) for k, v in a.tensors().items()})
