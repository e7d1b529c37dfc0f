"""Pose-source faults for simulated runs, with ground-truth labels per sample.

A pose source (``Sequence.pose_sources``: VO, LiDAR odometry) is fused as odometry, so what
matters is its *increments*: the relative pose ``dT_i = T_(i-1)^-1 T_i`` between consecutive
valid samples (body frame of the earlier one). A fault rewrites the increments that end
inside its interval, and the stream is re-integrated from the first one changed:
``T'_i = T'_(i-1) dT'_i``. Increments outside the faults are untouched, so the stream after a
fault is the clean stream moved by a rigid world-frame offset (odometry does not know it was
wrong). The declared covariances are kept: the faults are undeclared, which is what makes
them dangerous.

Kinds (:data:`FAULT_KINDS`), each with its fields of :class:`SourceFault`:

* ``"slide"``: a LiDAR matcher sliding along a corridor (undeclared degeneracy). With ``a``
  the direction of travel in the body frame (from the truth), the axial part of each
  increment is scaled and biased: ``dp' = dp + (s - 1)(a . dp) a + b dt a``
  (``axial_scale`` s: 0 = the matcher sees no motion along the corridor; ``axial_bias_mps``
  b).
* ``"blind"``: a camera blinded (glare, fog, a covered lens) whose VO tracks noise: the
  increments are replaced by garbage unrelated to the motion, a constant random velocity of
  magnitude ``garbage_speed_mps`` (random direction in the body's horizontal plane) and
  a constant random yaw rate up to ``garbage_rate_radps``, plus white jitter
  ``jitter_m`` / ``jitter_rad`` per increment (a large drift).
* ``"jump"``: the first increment at or after ``t_start`` gains a horizontal offset of
  ``jump_m`` (random direction) and a heading offset ``jump_rad`` (a relocalisation
  glitch); ``t_end == t_start``.
* ``"stuck"``: the driver repeats the last pose: increments inside the interval are the
  identity; after it the stream continues from the frozen pose.

Labels: ``FaultRun.sample_labels[source][i]`` is True when the increment that ends at
sample ``i`` was rewritten; :func:`pair_labels` maps them onto pairs of the filter's schedule
(a pair is faulty when any increment inside it is). ``Sequence.labels["fault:<source>"]``
holds the fault intervals (s).

Example:
    >>> from msf_torch.sim import SimConfig, simulate_run
    >>> from msf_torch.sim.weather import WeatherSchedule, apply_weather
    >>> run = simulate_run(SimConfig(duration_s=30.0, imu_rate_hz=100.0), seed=1)
    >>> wet = apply_weather(run, WeatherSchedule.constant("sunny", 30.0), seed=2)
    >>> fault = SourceFault("lidar", "stuck", 10.0, 14.0)
    >>> faulty = inject_faults(wet, [fault], seed=3)
    >>> int(faulty.sample_labels["lidar"].sum())
    40
"""

from __future__ import annotations

__all__ = [
    "FAULT_KINDS",
    "SourceFault",
    "FaultRun",
    "inject_faults",
    "random_faults",
    "pair_labels",
    "simulate_fault_run",
]

import dataclasses
import math
from collections.abc import Sequence as Seq
from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.sim.weather import Environment, WeatherRun, WeatherSchedule, apply_weather
from msf_torch.sim.wheeled import SimConfig, SimulatedRun, simulate_run
from msf_torch.types import PoseMeasurements, Sequence

FAULT_KINDS: tuple[str, ...] = ("slide", "blind", "jump", "stuck")
"""Kinds of :class:`SourceFault`."""


@dataclass(frozen=True)
class SourceFault:
    """One injected fault of a pose source (see the module docstring for each kind).

    Attributes:
        source: pose-source name (``"vo"``, ``"lidar"``).
        kind: one of :data:`FAULT_KINDS`.
        t_start, t_end: the interval, s; increments ending in ``(t_start, t_end]`` are
            rewritten (``"jump"``: the first one ending at or after ``t_start``).
        axial_scale, axial_bias_mps: ``"slide"``: share of the axial motion reported and
            an axial velocity bias, m/s.
        garbage_speed_mps, garbage_rate_radps: ``"blind"``: speed of the garbage motion, m/s,
            and the bound of its yaw rate, rad/s.
        jitter_m, jitter_rad: ``"blind"``: white noise per increment, m and rad (per axis).
        jump_m, jump_rad: ``"jump"``: horizontal offset, m, and heading offset, rad.
    """

    source: str
    kind: str
    t_start: float
    t_end: float
    axial_scale: float = 0.0
    axial_bias_mps: float = 0.0
    garbage_speed_mps: float = 2.0
    garbage_rate_radps: float = 0.2
    jitter_m: float = 0.05
    jitter_rad: float = 0.01
    jump_m: float = 2.0
    jump_rad: float = 0.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when the fault is malformed."""
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"SourceFault.kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        if not (math.isfinite(self.t_start) and math.isfinite(self.t_end)):
            raise ValueError("SourceFault.t_start and t_end must be finite")
        if self.kind == "jump" and self.t_end != self.t_start:
            raise ValueError("SourceFault: a jump has t_end == t_start")
        if self.kind != "jump" and not self.t_end > self.t_start:
            raise ValueError(f"SourceFault.t_end must exceed t_start, got {self.t_end!r}")
        for name in ("garbage_speed_mps", "garbage_rate_radps", "jitter_m", "jitter_rad"):
            if getattr(self, name) < 0:
                raise ValueError(f"SourceFault.{name} must be >= 0")

    def to_dict(self) -> dict[str, object]:
        """Plain dict of the fields."""
        return dataclasses.asdict(self)


@dataclass
class FaultRun:
    """A simulated weather run with injected pose-source faults.

    Attributes:
        sequence: the weather run's sequence with the faulty streams in ``pose_sources``
            (B = 1) and ``labels["fault:<source>"]`` (1, K, 2) fault intervals, s.
        faults: the injected faults.
        sample_labels: source -> (N,) bool numpy, the increment ending at sample i was
            rewritten (False for dropped samples).
        truth: the clean simulated run (ground truth).
    """

    sequence: Sequence
    faults: tuple[SourceFault, ...]
    sample_labels: dict[str, np.ndarray]
    truth: SimulatedRun


def _rotation_z(angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations about z by ``angle`` (...,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*np.shape(angle), 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    return out


def _rotation_exp(phi: np.ndarray) -> np.ndarray:
    return so3.exp(torch.from_numpy(np.ascontiguousarray(phi))).numpy()


def _inject_stream(
    stream: PoseMeasurements,
    faults: list[SourceFault],
    path_rotation: np.ndarray,
    path_velocity: np.ndarray,
    rng: np.random.Generator,
) -> tuple[PoseMeasurements, np.ndarray]:
    """Faulty copy of a B = 1 stream and its per-sample labels (N,)."""
    t = stream.t[0].numpy()
    valid = stream.mask[0].numpy().astype(bool)
    labels = np.zeros(t.shape, dtype=bool)
    idx = np.flatnonzero(valid)
    if idx.size < 2:
        return stream, labels
    position = stream.position[0].numpy()[idx]
    rotation = quat_to_matrix(stream.quaternion[0, idx]).numpy()
    t_v = t[idx]
    step = np.diff(t_v)
    d_rot = rotation[:-1].transpose(0, 2, 1) @ rotation[1:]  # (M, 3, 3), M = valid - 1
    d_pos = np.einsum("mji,mj->mi", rotation[:-1], np.diff(position, axis=0))
    changed = np.zeros(step.shape, dtype=bool)
    end = t_v[1:]
    for fault in faults:
        inside = (end > fault.t_start) & (end <= fault.t_end)
        if fault.kind == "slide":
            travel = np.einsum(
                "mji,mj->mi", path_rotation[idx[:-1]], path_velocity[idx[:-1]] * [1.0, 1.0, 0.0]
            )
            axis = travel / np.maximum(np.linalg.norm(travel, axis=-1, keepdims=True), 1e-9)
            along = np.einsum("mi,mi->m", axis, d_pos)
            rewritten = (
                d_pos
                + ((fault.axial_scale - 1.0) * along + fault.axial_bias_mps * step)[:, None] * axis
            )
            d_pos = np.where(inside[:, None], rewritten, d_pos)
        elif fault.kind == "blind":
            heading = rng.uniform(-math.pi, math.pi)
            velocity = fault.garbage_speed_mps * np.array([math.cos(heading), math.sin(heading), 0])
            yaw_rate = rng.uniform(-fault.garbage_rate_radps, fault.garbage_rate_radps)
            jitter_p = rng.normal(0.0, fault.jitter_m, d_pos.shape)
            jitter_r = rng.normal(0.0, fault.jitter_rad, d_pos.shape)
            garbage_rot = _rotation_exp(jitter_r + np.array([0.0, 0.0, yaw_rate]) * step[:, None])
            d_pos = np.where(inside[:, None], velocity * step[:, None] + jitter_p, d_pos)
            d_rot = np.where(inside[:, None, None], garbage_rot, d_rot)
        elif fault.kind == "jump":
            after = np.flatnonzero(end >= fault.t_start)
            inside = np.zeros_like(inside)
            if after.size:
                inside[after[0]] = True
                direction = rng.uniform(-math.pi, math.pi)
                offset = fault.jump_m * np.array([math.cos(direction), math.sin(direction), 0.0])
                d_pos = d_pos + inside[:, None] * offset
                d_rot = np.where(
                    inside[:, None, None], d_rot @ _rotation_z(np.array(fault.jump_rad)), d_rot
                )
        else:  # stuck
            d_pos = np.where(inside[:, None], 0.0, d_pos)
            d_rot = np.where(inside[:, None, None], np.eye(3), d_rot)
        changed |= inside
    labels[idx[1:]] = changed
    if not changed.any():
        return stream, labels
    first = int(np.flatnonzero(changed)[0])
    new_rot, new_pos = rotation.copy(), position.copy()
    for m in range(first, len(step)):
        new_pos[m + 1] = new_pos[m] + new_rot[m] @ d_pos[m]
        new_rot[m + 1] = so3.project(torch.from_numpy(new_rot[m] @ d_rot[m])).numpy()
    out_pos = stream.position.clone()
    out_quat = stream.quaternion.clone()
    out_pos[0, idx] = torch.from_numpy(new_pos)
    out_quat[0, idx] = matrix_to_quat(torch.from_numpy(new_rot))
    return dataclasses.replace(stream, position=out_pos, quaternion=out_quat), labels


def inject_faults(run: WeatherRun, faults: Seq[SourceFault], seed: int) -> FaultRun:
    """Rewrite the pose sources of a weather run with ``faults``.

    Args:
        run: from :func:`~msf_torch.sim.weather.apply_weather` (B = 1).
        faults: the faults; each names a source of ``run.pose_sources``.
        seed: non-negative int for the random parts (garbage, jump directions).
    Returns:
        :class:`FaultRun`.
    Raises:
        ValueError: a fault is malformed or names an unknown source, or the seed is negative.
    """
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"inject_faults: seed must be a non-negative int, got {seed!r}")
    for fault in faults:
        fault.validate()
        if fault.source not in run.pose_sources:
            raise ValueError(
                f"inject_faults: no pose source {fault.source!r} "
                f"(sources: {sorted(run.pose_sources)})"
            )
    names = sorted(run.pose_sources)
    rngs = dict(
        zip(
            names,
            (
                np.random.Generator(np.random.PCG64(s))
                for s in np.random.SeedSequence(seed).spawn(len(names))
            ),
            strict=True,
        )
    )
    sources = dict(run.sequence.pose_sources)
    sample_labels: dict[str, np.ndarray] = {}
    labels = dict(run.sequence.labels)
    for name in names:
        mine = [f for f in faults if f.source == name]
        stream = sources[name]
        state = run.truth.path.evaluate(stream.t[0].numpy())
        sources[name], sample_labels[name] = _inject_stream(
            stream, mine, state.rotation, state.velocity, rngs[name]
        )
        intervals = np.array([[f.t_start, f.t_end] for f in mine], np.float64).reshape(-1, 2)
        labels[f"fault:{name}"] = torch.from_numpy(intervals)[None]
    meta = dict(run.sequence.meta)
    meta["faults"] = {"seed": int(seed), "faults": [f.to_dict() for f in faults]}
    sequence = dataclasses.replace(run.sequence, pose_sources=sources, labels=labels, meta=meta)
    sequence.check()
    return FaultRun(sequence, tuple(faults), sample_labels, run.truth)


def random_faults(
    duration_s: float,
    seed: int,
    kinds: Seq[tuple[str, str]] = (("lidar", "slide"), ("vo", "blind"), ("*", "jump|stuck")),
    start_s: float = 20.0,
    end_margin_s: float = 5.0,
    slots: int | None = None,
) -> tuple[tuple[SourceFault, ...], list[tuple[float, float]]]:
    """Draw a fault plan: one fault per ``(source, kind)`` entry, in non-overlapping slots.

    ``"*"`` picks a source (``"vo"``/``"lidar"``) and ``"a|b"`` a kind at random. The span
    ``[start_s, duration_s - end_margin_s]`` is cut into ``slots`` (default: one per fault)
    equal slots, faults go to random slots in random order, each at a random time inside its
    slot. Durations (s): slide 5-15, blind 4-10, stuck 2-6. Magnitudes: slide scale 0-0.5
    with axial bias -0.3..0.3 m/s; blind garbage speed 1-3 m/s, yaw rate up to 0.3 rad/s;
    jump 1-3 m and -0.1..0.1 rad.

    Returns:
        The faults, and the slots left free as ``(t0, t1)`` intervals, s.
    """
    rng = np.random.default_rng(seed)
    count = len(kinds) if slots is None else slots
    if count < len(kinds):
        raise ValueError(f"random_faults: {len(kinds)} faults need >= as many slots, got {count}")
    width = (duration_s - end_margin_s - start_s) / count
    order = rng.permutation(count)
    faults = []
    for n, (source, kind) in enumerate(kinds):
        source = str(rng.choice(["vo", "lidar"])) if source == "*" else source
        kind = str(rng.choice(kind.split("|")))
        length = {"slide": (5.0, 15.0), "blind": (4.0, 10.0), "stuck": (2.0, 6.0)}.get(
            kind, (0.0, 0.0)
        )
        span = float(rng.uniform(*length))
        if span > width - 1.0:
            raise ValueError(
                f"random_faults: a {span:.1f} s fault does not fit a {width:.1f} s slot"
            )
        slot = start_s + order[n] * width
        t0 = slot + float(rng.uniform(0.5, width - span - 0.5))
        faults.append(
            SourceFault(
                source,
                kind,
                t0,
                t0 + span,
                axial_scale=float(rng.uniform(0.0, 0.5)),
                axial_bias_mps=float(rng.uniform(-0.3, 0.3)),
                garbage_speed_mps=float(rng.uniform(1.0, 3.0)),
                garbage_rate_radps=0.3,
                jump_m=float(rng.uniform(1.0, 3.0)),
                jump_rad=float(rng.uniform(-0.1, 0.1)),
            )
        )
    free = [(start_s + k * width, start_s + (k + 1) * width) for k in sorted(order[len(kinds) :])]
    return tuple(faults), free


def pair_labels(
    sample_t: np.ndarray, sample_labels: np.ndarray, pair_end: np.ndarray, pair_dt: np.ndarray
) -> np.ndarray:
    """Whether each pair ``(t_end - dt, t_end]`` contains a rewritten increment.

    Args:
        sample_t: (N,) sorted sample times, s.
        sample_labels: (N,) bool, from :attr:`FaultRun.sample_labels`.
        pair_end, pair_dt: (...,) pair end times and intervals, s.
    Returns:
        (...,) bool.
    """
    tol = 1e-6
    counts = np.concatenate(([0], np.cumsum(sample_labels)))
    upper = np.searchsorted(sample_t, pair_end + tol, side="right")
    lower = np.searchsorted(sample_t, pair_end - pair_dt + tol, side="right")
    return counts[upper] - counts[lower] > 0


def simulate_fault_run(
    seed: int,
    duration_s: float = 120.0,
    imu_rate_hz: float = 100.0,
    gnss_until_s: float = 15.0,
    wheels: bool = False,
) -> FaultRun:
    """A simulated run whose pose sources carry the faults of :func:`random_faults`.

    The wheeled-robot simulator (:func:`~msf_torch.sim.simulate_run`), a random weather
    schedule and VO / LiDAR streams (:func:`~msf_torch.sim.weather.apply_weather`) with a
    declared LiDAR corridor (an honest degeneracy, for false alarms) in the slot the faults
    leave free; one LiDAR slide, one VO blind and one jump or stuck fault on a random
    source, all after ``gnss_until_s`` (GNSS fixes the initial heading, then is withheld so
    that the pose sources carry the position). Seeds of the parts derive from ``seed``
    (``numpy.random.SeedSequence``).

    Args:
        seed: non-negative int.
        duration_s: run length, s (>= 90 s: four slots of 16 s after ``gnss_until_s + 5``).
        imu_rate_hz: IMU and truth rate, Hz.
        gnss_until_s: GNSS fixes only before this time, s.
        wheels: keep the wheel encoders (default: dropped, the filter uses the NHC).
    Returns:
        :class:`FaultRun` (B = 1), named ``fault-<seed>``.
    """
    s_run, s_schedule, s_faults, s_weather, s_inject = (
        int(x) for x in np.random.SeedSequence(int(seed)).generate_state(5)
    )
    outages = ((gnss_until_s, duration_s),) if gnss_until_s < duration_s else None
    sim = SimConfig(duration_s=duration_s, imu_rate_hz=imu_rate_hz, gnss_outages_s=outages)
    run = simulate_run(sim, seed=s_run)
    schedule = WeatherSchedule.random(duration_s, seed=s_schedule)
    faults, free = random_faults(duration_s, s_faults, start_s=gnss_until_s + 5.0, slots=4)
    wet = apply_weather(
        run, schedule, seed=s_weather, environment=Environment(corridors_s=(free[0],))
    )
    faulty = inject_faults(wet, faults, s_inject)
    sequence = dataclasses.replace(
        faulty.sequence, names=[f"fault-{seed}"], wheel=faulty.sequence.wheel if wheels else None
    )
    return dataclasses.replace(faulty, sequence=sequence)
