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

   The covariance is kept in right-invariant coordinates (see ``geometry.invariant``):
   ``P_inv`` propagates with ``T_j^-1 Phi T_i`` and updates with ``H T_j``, so the
   global-yaw direction that wheels and the NHC cannot observe stays unobservable
   whatever the estimate; results report the conventional covariance ``T P_inv T^T``.
   The invariant errors are taken about the estimate's own position (the origin moves with
   it: ``_move_origin`` after each correction, folded into the transition during
   propagation), so ``T`` has no position arm and nothing depends on, or loses precision
   to, where the world origin lies.
   In these coordinates the navigation block of ``T_j^-1 Phi T_i`` depends on ``dT`` only
   (:func:`_invariant_nav_transition`, computed with the increments in chunks of epochs by
   ``_EpochIncrements``, on a worker thread for large batches without gradients); the loop
   fills in the bias columns, which use the bias Jacobians and the estimate. The nominal
   state uses the bias-corrected increments; a transition built from other increments
   would leak heading information at every epoch.

2. Update with every measurement that falls on the epoch end, stacked into one vector:
   wheel (3: body velocity; its yaw-rate row joins with ``wheel_yaw_rate_update``), NHC (2),
   zero velocity (3), GNSS (3), pose (6), then one block per pose source (6, or 3 without
   ``pose_source_rate_update``; drifting frames: 9 or 6; key ``"pose:<name>"``), each a
   residual from ``sensors``.
   Each block is chi-square gated on its own innovation; the wheel block is also scaled by
   the slip factor (``frontend.slip``) and skipped below a threshold. Joseph-form covariance
   update, then the invariant error is injected (``R <- Exp(xi_R) R``,
   ``v <- Exp(xi_R) v + xi_v``, ...).

Pose sources (VO, LiDAR odometry) drift, so they are fused as odometry: the body-frame mean
velocity ``z_v`` of a pair of consecutive samples (``frontend.schedule``) goes through the
wheels' residual (``sensors.wheel.body_velocity_residual``, lever arm 0: a source measures
the body pose) at the pair's later time ``t_k``, with covariance

    R_v = s C_v + (a dt / 2)^2 I

``C_v`` the pair's declared covariance, ``s`` the source's variance scale
(``EskfNoise.pose_source_scale``) and ``a = pose_source_accel_sigma_mps2``: under an
acceleration ``a`` the interval's mean velocity differs from the velocity at its end by
``a dt / 2``, treated as zero-mean noise of that size. With ``pose_source_rate_update`` the
mean body rate of the relative rotation is compared with the mean gyro rate over the same
interval (``sensors.pose.mean_rate_residual``; it observes the gyro bias, so the heading
stops drifting with it), covariance ``R_w = s C_w + sigma_g^2 / dt I`` (``sigma_g`` the gyro
noise density). Only relative motion enters, so the source's drift stays out, up to its
increment over ``dt``. Each sample's white noise enters two neighbouring pairs with opposite
signs, which the filter treats as independent: most of a source's position information is
lost.

With ``pose_source_fusion: drifting_frame`` the sample ending each pair is instead fused as
an absolute pose against the source's own drifting frame (``frontend.source_frames``;
residual ``sensors.pose.drifting_frame_pose_residual``, ``z_p = p + t_o``,
``R_z = R Exp(phi_o)``, covariance ``s C`` of the declared 6x6 ``C``; the rate row joins with
``pose_source_rate_update``). The error state grows by six offset states per source after
the calibration states: identity transition, a random walk in distance travelled
(``pose_source_drift*`` times ``s``), no invariant-coordinate change. At a source's first
pair and after each gap the offset is re-initialised from the estimate with the
cross-covariance of the linearised model (that sample is consumed, not fused). Consecutive
samples then carry independent white noise and the drift sits in the offsets.

With ``source_fault_detection`` the pose sources first go through the multi-model fault
detector of ``frontend.gating`` (a UKF per source, the difference of the sources'
residuals, a two-tailed Z-test with hysteresis; it sees only the sources' own pairs, so it
runs once over the schedule before the epoch loop). A source it flags has weight 0 in the
flagged epochs: its rows leave the update (its gate streak does not count them), and the
gate, ``pose_source_scale`` and learned weights act on the sources that pass. The weight
is a straight-through 0/1 gate, so gradients reach the detector's inputs.

Everything is a differentiable torch op: gradients reach the noise parameters
(:class:`EskfNoise`). The only Python loop on the hot path is over epochs.
"""

from __future__ import annotations

__all__ = ["EskfNoise", "EskfResult", "run_eskf", "SENSORS", "INCREMENT_CHUNK_SAMPLES"]

import concurrent.futures
import contextlib
import copy
import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from msf_torch.frontend.adaptive import BlockAdaptation
from msf_torch.frontend.calibration import CalibrationLayout, CalibrationMemory, observability
from msf_torch.frontend.config import MEASUREMENT_BLOCKS, EskfConfig
from msf_torch.frontend.gating import (
    FaultMemory,
    SourceFaultParams,
    chi2_threshold,
    detect_source_faults,
)
from msf_torch.frontend.guard import (
    DivergenceGuard,
    EstimationInterrupted,
    GateMemory,
    InterruptCatcher,
    sanitize_sequence,
)
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.schedule import UNMEASURED_SIGMA, PairMemory, Schedule, build_schedule
from msf_torch.frontend.slip import slip_factor
from msf_torch.frontend.source_frames import (
    FRAME_DIM,
    FrameMemory,
    SourceFrames,
    build_source_frames,
    reinitialise,
)
from msf_torch.frontend.source_frames import inject as inject_frames
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import ERROR_STATE_DIM, gravity_world
from msf_torch.geometry.invariant import invariant_maps, invariant_retract
from msf_torch.geometry.quaternion import matrix_to_quat
from msf_torch.sensors.calibration import (
    calibrated_wheel_residual,
    gnss_lever_arm_jacobian,
    mounted_rate_residual,
    mounted_velocity_residual,
    shifted_body_velocity_residual,
    shifted_gnss_residual,
    shifted_heading_residual,
    shifted_mean_rate_residual,
    vehicle_frame_nonholonomic_residual,
    vehicle_frame_wheel_residual,
)
from msf_torch.sensors.gnss import gnss_heading_residual, gnss_residual, gnss_velocity_residual
from msf_torch.sensors.imu import ImuNoise, Preintegrated, preintegrate, propagate_nominal
from msf_torch.sensors.imu_gaps import gap_walk_scale
from msf_torch.sensors.magnetometer import (
    field_dip,
    magnetometer_heading_residual,
    magnetometer_heading_variance,
)
from msf_torch.sensors.pose import (
    drifting_frame_offset,
    drifting_frame_pose_residual,
    mean_rate_residual,
    pose_residual,
)
from msf_torch.sensors.vehicle import nonholonomic_residual, zero_velocity_residual
from msf_torch.sensors.wheel import body_velocity_residual, wheel_residual
from msf_torch.types import NavState, Sequence, Trajectory

SENSORS = MEASUREMENT_BLOCKS
_DIMS = {
    "wheel": 4,
    "nhc": 2,
    "zupt": 3,
    "gnss": 3,
    "gnss_velocity": 3,
    "gnss_heading": 1,
    "magnetometer": 1,
    "pose": 6,
}
_SOURCE_PREFIX = "pose:"  # result key of a pose source: "pose:vo", "pose:lidar"


@dataclass
class EskfNoise:
    """Noise parameters as tensors, shape () or (B,), so they can be learned.

    Attributes (units in the names of the matching :class:`EskfConfig` fields):
        imu: IMU noise densities.
        wheel_speed_sigma, wheel_lateral_sigma, wheel_yaw_rate_sigma: m/s, m/s, rad/s.
        nhc_sigma, zupt_sigma: m/s.
        gnss_sigma_scale: multiplier on each fix's sigma (1 = as given).
        pose_source_scale: pose-source name -> multiplier on the declared variances of its
            velocity and rate rows, () or (B,) (missing names: 1; names not fused are
            ignored).
    """

    imu: ImuNoise
    wheel_speed_sigma: torch.Tensor
    wheel_lateral_sigma: torch.Tensor
    wheel_yaw_rate_sigma: torch.Tensor
    nhc_sigma: torch.Tensor
    zupt_sigma: torch.Tensor
    gnss_sigma_scale: torch.Tensor
    pose_source_scale: dict[str, torch.Tensor] = field(default_factory=dict)

    @classmethod
    def from_config(
        cls,
        cfg: EskfConfig,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> EskfNoise:
        """Noise tensors (scalars, in the config's units) from a config."""

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
            gnss_sigma_scale=t(cfg.gnss_sigma_scale),
            pose_source_scale={
                name: t(float(scale)) for name, scale in cfg.pose_source_variance_scale.items()
            },
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
        present, accepted: sensor -> (B, E + 1) bool (a measurement was there / was fused);
            sensors are :data:`SENSORS` and ``"pose:<name>"`` per fused pose source.
        nis: sensor -> (B, E + 1) normalised innovation squared (0 where absent).
        innovation_logdet: sensor -> (B, E + 1) ``log det S`` of its innovation covariance
            (0 where absent): with ``nis`` and the block's rows ``d``, the Gaussian
            log-likelihood of the innovation is ``-(nis + logdet + d log 2 pi) / 2``
            (differentiable w.r.t. the noise; :mod:`msf_torch.frontend.tuning`).
        gate_threshold: sensor -> the chi-square gate on its NIS (``gate_probability`` at
            the block's rows; inf where it is not gated), for every sensor with a
            measurement.
        block_rows: sensor -> its block's rows (the NIS's degrees of freedom), for every
            sensor with a measurement.
        gap: (B, E + 1) bool, an IMU gap was bridged in this epoch.
        divergence: (B, E + 1) int64, 0 or the ``frontend.guard`` codes (bit flags: 1
            non-finite, 2 not positive definite, 4 NIS blow-up) of a sequence that diverged
            in this epoch and was reset to its last good state with inflated covariance.
        dropped_samples: stream (``"imu"``, ``"wheel"``, ``"gnss"``, ``"pose"``,
            ``"pose:<name>"``) -> (B,) int64 samples skipped by the input rule of
            ``frontend.guard`` (non-finite, repeated or backwards stamps).
        fading_factor: (B, E + 1) strong-tracking factor on the predicted covariance (1 =
            none; all 1 without ``strong_tracking_sensors``).
        noise_estimate: Sage-Husa block (``adaptive_noise_sensors``) -> (B, E + 1, d, d)
            the estimated measurement covariance in force after each epoch (zeros before
            the block's first measurement).
        source_fault: ``"pose:<name>"`` -> (B, E + 1) bool, the fault detector
            (``source_fault_detection``) excludes the source after this epoch (empty when
            off).
        source_fault_z: ``"pose:<name>"`` -> (B, E + 1) the detector's deciding Z statistic
            at the source's pairs (0 elsewhere; ``frontend.gating.SourceFaultResult.z``).
        gate_memory: the gate's rejection streaks and the divergence guard's episode after
            the last completed epoch (``frontend.guard.GateMemory``), for a next chunk.
        calibration_names: names of the online-calibration states (``frontend.calibration``;
            empty when off).
        calibration: (B, E + 1, n) their estimates (units in the names; None when off).
        calibration_covariance: (B, E + 1, n, n) their covariance (None when off).
        calibration_variance_ratio: (B, E + 1, n) each state's variance over the variance
            it would have without measurements (``frontend.calibration.observability``).
        calibration_observable: state name -> (B,) bool, its ratio at the sequence's last
            epoch below ``calibration_observable_ratio``.
        source_frame: ``"pose:<name>"`` -> (B, E + 1, 6) the offset ``[t_o (m, world),
            phi_o (rad, body)]`` of the source's frame (``pose_source_fusion:
            drifting_frame``, ``frontend.source_frames``; empty otherwise).
        source_frame_covariance: ``"pose:<name>"`` -> (B, E + 1, 9, 9) joint covariance of
            the (conventional) position error and the offset error ``[dt, dphi]``.
        frame_memory: the source frames after each sequence's last real epoch, for a next
            chunk (``frontend.source_frames.FrameMemory``; None without drifting frames).
        calibration_memory: the calibration states after each sequence's last real epoch,
            for a next chunk (``frontend.calibration.CalibrationMemory``; None when off).
        pair_memory: each pose source's latest sample with the gyro integral since and its
            latest pair, after the last IMU sample, for a next chunk
            (``frontend.schedule.PairMemory``; it depends on the data only, so it covers the
            whole chunk also when interrupted; None without pose sources).
        fault_memory: the source-fault detector's state after the chunk, for a next chunk
            (``frontend.gating.FaultMemory``; data only, like ``pair_memory``; None without
            ``source_fault_detection`` or pose sources).
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
    innovation_logdet: dict[str, torch.Tensor] = field(default_factory=dict)
    gate_threshold: dict[str, float] = field(default_factory=dict)
    block_rows: dict[str, int] = field(default_factory=dict)
    gap: torch.Tensor | None = None
    divergence: torch.Tensor | None = None
    dropped_samples: dict[str, torch.Tensor] = field(default_factory=dict)
    fading_factor: torch.Tensor | None = None
    noise_estimate: dict[str, torch.Tensor] = field(default_factory=dict)
    source_fault: dict[str, torch.Tensor] = field(default_factory=dict)
    source_fault_z: dict[str, torch.Tensor] = field(default_factory=dict)
    gate_memory: GateMemory | None = None
    calibration_names: tuple[str, ...] = ()
    calibration: torch.Tensor | None = None
    calibration_covariance: torch.Tensor | None = None
    calibration_variance_ratio: torch.Tensor | None = None
    calibration_observable: dict[str, torch.Tensor] = field(default_factory=dict)
    source_frame: dict[str, torch.Tensor] = field(default_factory=dict)
    source_frame_covariance: dict[str, torch.Tensor] = field(default_factory=dict)
    frame_memory: FrameMemory | None = None
    calibration_memory: CalibrationMemory | None = None
    pair_memory: PairMemory | None = None
    fault_memory: FaultMemory | None = None

    def select(self, index: int) -> EskfResult:
        """Sequence ``index`` of the batch as a result with B = 1 (views, not copies): every
        per-sequence tensor, in the fields and in the ``*_memory`` fields, cut
        to ``[index : index + 1]``; epochs stay padded to the batch's E (see ``mask``)."""
        batch = self.position.shape[0]
        if not -batch <= index < batch:
            raise IndexError(f"EskfResult.select: index {index} out of range for B = {batch}")
        index = index % batch

        def cut(value: object) -> object:
            if isinstance(value, torch.Tensor):
                return value[index : index + 1]
            if isinstance(value, dict):
                return {key: cut(item) for key, item in value.items()}
            memories = (GateMemory, FrameMemory, CalibrationMemory, PairMemory, FaultMemory)
            if isinstance(value, memories):
                return dataclasses.replace(
                    value,
                    **{
                        spec.name: cut(getattr(value, spec.name))
                        for spec in dataclasses.fields(value)
                        if spec.name != "names"
                    },
                )
            return value

        return dataclasses.replace(
            self,
            names=[self.names[index]],
            **{
                spec.name: cut(getattr(self, spec.name))
                for spec in dataclasses.fields(self)
                if spec.name not in ("names", "calibration_names")
            },
        )

    def trajectory(self) -> Trajectory:
        """Estimated poses as a :class:`~msf_torch.types.Trajectory` (B, E + 1)."""
        return Trajectory(
            t=self.t,
            position=self.position,
            quaternion=matrix_to_quat(self.rotation),
            mask=self.mask,
        )

    def accepted_nis(self, after_s: float = 0.0) -> dict[str, tuple[float, int]]:
        """Per sensor with accepted measurements (all sequences pooled, from ``after_s``
        seconds after each one's start): their mean NIS and count. A consistent filter's
        mean NIS is the block's rows (``block_rows``)."""
        settled = self.mask & (self.t >= self.t[:, :1] + after_s)
        out = {}
        for key, nis in self.nis.items():
            accepted = self.accepted[key] & settled
            count = int(accepted.sum())
            if count:
                out[key] = (float(nis[accepted].mean()), count)
        return out

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


INCREMENT_CHUNK_SAMPLES = 65536
"""IMU pieces (B x epochs x slots) preintegrated per chunk by the filter."""

_LOOKAHEAD_CHUNKS = 3
"""Chunks the background worker may have done or queued beyond the loop's current one."""


@dataclass
class _IncrementChunk:
    """IMU increments of epochs ``start .. start + E_c - 1`` (leading dims (B, E_c)): the
    preintegration, the local process noise (:func:`_local_process_noise`) and the
    invariant navigation transition (:func:`_invariant_nav_transition`).

    ``q_rows`` is ``q_loc`` unbound along the epochs: the loop takes epoch ``k``'s as
    ``q_rows[k]``, whose backward is one stack for the chunk, where ``q_loc[:, k]``'s
    would fill a zero gradient of the whole chunk at every epoch (quadratic in E_c: it
    was three quarters of a gradient's time)."""

    start: int
    pre: Preintegrated
    q_loc: torch.Tensor
    nav_transition: torch.Tensor
    q_rows: tuple[torch.Tensor, ...] = ()

    def __post_init__(self) -> None:
        self.q_rows = self.q_loc.unbind(1)


class _EpochIncrements:
    """The epoch loop's IMU increments, computed in chunks along E as the loop reaches them
    (about ``max_samples`` IMU pieces per chunk: cache-friendly, and memory for a few
    chunks, not for the whole run).

    Without ``background`` a chunk is computed on the calling thread, with the torch thread
    count in force at construction, when :meth:`at` first asks for it. With ``background``
    a worker thread computes the chunks in order, up to :data:`_LOOKAHEAD_CHUNKS` ahead of
    the loop, while the epoch loop consumes them (:meth:`at` waits for a chunk not yet
    done): a large batch's preintegration (about 0.4 us per IMU sample) then overlaps with
    its epoch loop on a second core. The worker runs under inference mode with one
    intra-op thread; use it only when no gradients are recorded. Epochs are visited in
    order; a chunk is released once the loop has moved past it. :meth:`close` stops the
    worker (always call it, e.g. through ``contextlib.closing``).
    """

    def __init__(
        self,
        sched: Schedule,
        gyro_bias: torch.Tensor,
        accel_bias: torch.Tensor,
        noise: EskfNoise,
        gravity_mps2: float,
        background: bool = False,
        max_samples: int | None = None,
        gap_walk: torch.Tensor | None = None,
        gap_walk_max_blind_s: float = math.inf,
    ) -> None:
        """Args: sched: the batch's schedule (B, E, L). gyro_bias, accel_bias: (B, 3)
        linearisation biases. noise: the filter's noise. gravity_mps2: gravity, m/s^2.
        background: see the class docstring. max_samples: IMU pieces per chunk (default
        :data:`INCREMENT_CHUNK_SAMPLES`). gap_walk: (6,) random-walk densities of the true
        rate and specific force away from a sample held over a gap, per body axis (rad/s^2
        and m/s^3 per sqrt(Hz); :func:`_gap_walk_covariance`), or None.
        gap_walk_max_blind_s: the walk skips epochs that hold more gap than this, s."""
        batch, n_epochs, n_slots = sched.dt.shape
        max_samples = max_samples or INCREMENT_CHUNK_SAMPLES
        self.step = max(1, max_samples // max(1, batch * n_slots))
        self._starts = list(range(0, n_epochs, self.step))

        def compute(start: int) -> _IncrementChunk:
            sl = slice(start, start + self.step)
            count = sched.dt[:, sl].shape[1]
            gyro, accel = sched.held_imu(sl)  # gathered per chunk: no (B, E, L, 3)
            pre = preintegrate(
                gyro,
                accel,
                sched.dt[:, sl],
                gyro_bias[:, None, :].expand(batch, count, 3),
                accel_bias[:, None, :].expand(batch, count, 3),
                sched.noise_scale[:, sl],
            )
            if gap_walk is not None:
                pre = _gap_walk_covariance(
                    pre, gyro, accel, sched, sl, noise.imu, gap_walk, gap_walk_max_blind_s
                )
            return _IncrementChunk(
                start,
                pre,
                _local_process_noise(pre, noise),
                _invariant_nav_transition(pre.delta_t, gravity_mps2),
            )

        threads = torch.get_num_threads()

        def compute_here(start: int) -> _IncrementChunk:
            with _intra_op_threads(threads):
                return compute(start)

        def compute_in_worker(start: int) -> _IncrementChunk:
            torch.set_num_threads(1)
            with torch.inference_mode():
                return compute(start)

        self._compute = compute_in_worker if background else compute_here
        self._chunks: list[_IncrementChunk | concurrent.futures.Future | None] = [None] * len(
            self._starts
        )
        self._released = 0
        self._submitted = 0
        self._executor = None
        if background:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, "msf-increments")
            self._submit_through(_LOOKAHEAD_CHUNKS - 1)

    def _submit_through(self, last: int) -> None:
        """Queue the worker's chunks up to index ``last``."""
        for index in range(self._submitted, min(last + 1, len(self._starts))):
            self._chunks[index] = self._executor.submit(self._compute, self._starts[index])
        self._submitted = max(self._submitted, min(last + 1, len(self._starts)))

    def at(self, epoch: int) -> tuple[_IncrementChunk, int]:
        """The chunk holding ``epoch`` and the epoch's index inside it (epochs in order;
        the chunks before this one are released)."""
        index, local = divmod(epoch, self.step)
        if index < self._released:
            raise IndexError(f"_EpochIncrements: epoch {epoch} lies in a released chunk")
        for earlier in range(self._released, index):
            self._chunks[earlier] = None
        self._released = index
        if self._executor is not None:
            self._submit_through(index + _LOOKAHEAD_CHUNKS)
        chunk = self._chunks[index]
        if chunk is None:
            chunk = self._chunks[index] = self._compute(self._starts[index])
        elif isinstance(chunk, concurrent.futures.Future):
            chunk = self._chunks[index] = chunk.result()
        return chunk, local

    def close(self) -> None:
        """Stop the worker (pending chunks are cancelled); a no-op without one."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None


def _gap_walk_covariance(
    pre: Preintegrated,
    gyro: torch.Tensor,
    accel: torch.Tensor,
    sched: Schedule,
    sl: slice,
    imu: ImuNoise,
    walk: torch.Tensor,
    max_blind_s: float,
) -> Preintegrated:
    """``pre`` (B, E_c) with the covariance of every epoch that holds gap pieces redone
    per body axis: over a gap of ``T`` s the true rate and specific force leave the held
    sample as a random walk of density ``q`` (``walk`` (6,), gyro x, y, z then accel), whose
    integral over the gap has variance ``q^2 T^3 / 3``; each piece held in the gap gets
    white noise of density ``q^2 T^2 / 3`` on top of ``imu_gap_noise_scale``, so the whole
    gap carries that variance whatever epochs cut it
    (:func:`~msf_torch.sensors.imu_gaps.gap_walk_scale`, as in the smoothers). As a
    multiplier of the filter's own density ``n`` (() or (B,)): ``scale + (q / n)^2 T^2 /
    3``, through the exact per-axis covariance of :func:`~msf_torch.sensors.imu.preintegrate`.
    gyro, accel: the chunk's held samples (B, E_c, L, 3); the other epochs are left as they
    are, bit for bit.

    An epoch that holds more than ``max_blind_s`` of gap (a dropout with no update inside,
    e.g. every sensor silent) keeps the isotropic ``imu_gap_noise_scale`` only: with the
    walk, such an epoch ends with a heading sigma of half a radian and more, from which the
    linearised updates after it do not recover (they shrink the sigma while the error
    stays, the fixes are then rejected and nothing resets the filter), whereas the smaller
    covariance lets the returning fixes blow up the NIS, and the divergence guard's reset
    recovers (``frontend.guard``; docs/frontend.md, "Faulty input")."""
    length = sched.gap_length[:, sl]
    blind = (sched.dt[:, sl] * (length > 0)).sum(-1)
    rows = torch.nonzero((length.amax(-1) > 0) & (blind <= max_blind_s), as_tuple=True)
    if rows[0].numel() == 0:
        return pre
    batch = length.shape[0]
    density = torch.cat(
        [imu.gyro_noise_density.expand(batch)[:, None].expand(batch, 3)]
        + [imu.accel_noise_density.expand(batch)[:, None].expand(batch, 3)],
        -1,
    )[rows[0]]  # (G, 6)
    extra = gap_walk_scale(length[rows], walk, density[:, None])  # (G, L, 6)
    redone = preintegrate(
        gyro[rows],
        accel[rows],
        sched.dt[:, sl][rows],
        pre.gyro_bias_lin[rows],
        pre.accel_bias_lin[rows],
        sched.noise_scale[:, sl][rows][..., None] + extra,
    )
    return dataclasses.replace(
        pre,
        cov_unit_gyro=pre.cov_unit_gyro.index_put(rows, redone.cov_unit_gyro),
        cov_unit_accel=pre.cov_unit_accel.index_put(rows, redone.cov_unit_accel),
    )


def _local_process_noise(pre: Preintegrated, noise: EskfNoise) -> torch.Tensor:
    """Process noise of every epoch, IMU part in the epoch-start body frame.

    ``Q_loc = blockdiag(Sigma_Delta, sigma_bg^2 dT I, sigma_ba^2 dT I)`` (B, E, 15, 15);
    the loop maps the navigation block into invariant coordinates.
    """
    lead = pre.delta_t.shape
    dtype, device = pre.delta_t.dtype, pre.delta_t.device

    def per_seq(x: torch.Tensor) -> torch.Tensor:
        return x[:, None] if x.dim() == 1 else x

    imu = noise.imu
    nav = pre.covariance(imu)
    var_g = per_seq(imu.gyro_bias_rw_density) ** 2 * pre.delta_t
    var_a = per_seq(imu.accel_bias_rw_density) ** 2 * pre.delta_t
    bias = torch.diag_embed(torch.stack((var_g, var_g, var_g, var_a, var_a, var_a), -1))
    zeros = torch.zeros(*lead, 9, 6, dtype=dtype, device=device)
    return torch.cat((torch.cat((nav, zeros), -1), torch.cat((zeros.mT, bias), -1)), -2)


def _invariant_nav_transition(delta_t: torch.Tensor, gravity_mps2: float) -> torch.Tensor:
    """(B, E, 15, 15) invariant-error transition without its bias columns.

    With right-invariant errors the navigation block does not depend on the estimate:
    ``xi_R' = xi_R``, ``xi_v' = xi_v + dT [g]x xi_R``,
    ``xi_p' = xi_p + dT xi_v + dT^2 / 2 [g]x xi_R``; biases carry over.
    """
    dtype, device = delta_t.dtype, delta_t.device
    hat_g = so3.hat(gravity_world(gravity_mps2, dtype, device))
    eye3 = so3.identity(dtype, device)
    dt = delta_t[..., None, None]
    out = torch.eye(ERROR_STATE_DIM, dtype=dtype, device=device).repeat(*delta_t.shape, 1, 1)
    out[..., 0:3, 3:6] = dt * eye3
    out[..., 0:3, 6:9] = 0.5 * dt * dt * hat_g
    out[..., 3:6, 6:9] = dt * hat_g
    return out


def _with_mean_rate_row(
    r: torch.Tensor,
    h: torch.Tensor,
    sched: Schedule,
    epoch: int,
    col: int,
    gyro_bias: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A pose source's block ``(r, h)`` (B, m), (B, m, 15) with the mean-rate row of its
    pair at ``epoch`` appended (``sensors.pose.mean_rate_residual``): (B, m + 3),
    (B, m + 3, 15)."""
    r_w, h_w = mean_rate_residual(
        sched.source_gyro_mean[:, epoch, col], gyro_bias, sched.source_rate[:, epoch, col]
    )
    return torch.cat((r, r_w), -1), torch.cat((h, h_w), -2)


def _conventional_covariance(
    velocity: torch.Tensor, rotation: torch.Tensor, cov: torch.Tensor
) -> torch.Tensor:
    """Conventional covariance ``T P T^T`` (N, 15, 15) of invariant-coordinate covariances
    ``cov`` (N, 15, 15) about their estimates' own positions, at estimates (N, 3) m/s,
    (N, 3, 3).

    ``T`` (``geometry.invariant.invariant_maps`` with a zero position arm) differs from the
    identity only in its attitude columns (``dv = xi_v - [v]x xi_R``, ``dtheta = R^T xi_R``),
    so the product only mixes rows and columns 6:9 into 3:9. Those products have inner
    dimension 3 and run as three broadcast multiply-adds over all N at once (for many small
    matrices much faster than batched matrix products, which go matrix by matrix).
    """

    def times(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        """``left @ right`` for (N, r, 3) @ (N, 3, c)."""
        out = left[:, :, 0, None] * right[:, None, 0]
        out.addcmul_(left[:, :, 1, None], right[:, None, 1])
        return out.addcmul_(left[:, :, 2, None], right[:, None, 2])

    arm = -so3.hat(velocity)  # (N, 3, 3)
    att_rows = cov[:, 6:9]  # (N, 3, 15)
    out = cov.clone()  # T P, then (T P) T^T, in place: one (N, 15, 15) buffer
    out[:, 3:6] += times(arm, att_rows)
    out[:, 6:9] = times(rotation.mT, att_rows)
    att_cols = out[..., 6:9].clone()  # (N, 15, 3)
    out[..., 3:6] += times(att_cols, arm.mT)
    out[..., 6:9] = times(att_cols, rotation)
    return out


def _inject_invariant(state: NavState, xi: torch.Tensor) -> NavState:
    """Apply a right-invariant correction ``xi`` (B, 15), in coordinates about the estimate's
    own position (the filter's covariance origin), to the nominal state."""
    offset, velocity, rotation = invariant_retract(
        torch.zeros_like(state.position), state.velocity, state.rotation, xi
    )
    return NavState(
        position=state.position + offset,
        velocity=velocity,
        rotation=rotation,
        gyro_bias=state.gyro_bias + xi[:, 9:12],
        accel_bias=state.accel_bias + xi[:, 12:15],
    )


def _move_origin(matrix: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """``M matrix M^T`` for ``M`` = identity but ``M[0:3, 6:9] = [shift]x``: the covariance
    (B, D, D) of invariant errors about an origin moved by ``-shift`` (B, 3) m
    (``xi_p' = xi_p + [shift]x xi_R``, ``shift`` = old origin - new origin; rows and
    columns past 15 carry over)."""
    hat = so3.hat(shift)
    left = torch.cat((matrix[:, 0:3] + hat @ matrix[:, 6:9], matrix[:, 3:]), 1)  # M P
    return torch.cat((left[:, :, 0:3] + left[:, :, 6:9] @ hat.mT, left[:, :, 3:]), 2)


def _maps_at_estimate(
    position: torch.Tensor, velocity: torch.Tensor, rotation: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``geometry.invariant.invariant_maps`` for the filter's covariances, whose origin is
    the estimate's own position (the position arm vanishes): (B, 15, 15) each."""
    return invariant_maps(torch.zeros_like(position), velocity, rotation)


def _source_covariance(
    sched: Schedule,
    noise: EskfNoise,
    cfg: EskfConfig,
    per_seq: Callable[[torch.Tensor], torch.Tensor],
) -> torch.Tensor:
    """Pose-source block covariances (B, E, S, d, d): ``R_v = s C_v + (a dt / 2)^2 I``,
    (m/s)^2, and with ``pose_source_rate_update`` (d = 6) ``R_w = s C_w + sigma_g^2 / dt I``,
    (rad/s)^2, on the diagonal; ``s`` from ``noise.pose_source_scale`` (default 1)."""
    if not sched.source_names:
        return sched.source_covariance
    scale = _source_scale(sched, noise, per_seq)[:, None, :, None, None]
    eye = torch.eye(3, dtype=scale.dtype, device=scale.device)
    accel_var = (0.5 * cfg.pose_source_accel_sigma_mps2 * sched.source_dt) ** 2
    velocity = scale * sched.source_covariance + accel_var[..., None, None] * eye
    if not cfg.pose_source_rate_update:
        return velocity
    gyro_var = per_seq(noise.imu.gyro_noise_density)[:, None, None] ** 2 / sched.source_dt.where(
        sched.source_mask, 1.0
    )
    rate = scale * sched.source_rate_covariance + gyro_var[..., None, None] * eye
    zeros = torch.zeros_like(rate)
    return torch.cat((torch.cat((velocity, zeros), -1), torch.cat((zeros, rate), -1)), -2)


def _frame_covariance(
    sched: Schedule,
    frames: SourceFrames,
    noise: EskfNoise,
    cfg: EskfConfig,
    per_seq: Callable[[torch.Tensor], torch.Tensor],
) -> torch.Tensor:
    """Drifting-frame block covariances (B, E, S, d, d): the pose ``s C`` (6), and with
    ``pose_source_rate_update`` (d = 9) the rate rows ``R_w`` of :func:`_source_covariance`."""
    scale = _source_scale(sched, noise, per_seq)[:, None, :, None, None]
    pose = scale * frames.covariance
    if not cfg.pose_source_rate_update:
        return pose
    eye = torch.eye(3, dtype=scale.dtype, device=scale.device)
    gyro_var = per_seq(noise.imu.gyro_noise_density)[:, None, None] ** 2 / sched.source_dt.where(
        sched.source_mask, 1.0
    )
    rate = scale * sched.source_rate_covariance + gyro_var[..., None, None] * eye
    cross = torch.zeros(*rate.shape[:-2], 6, 3, dtype=rate.dtype, device=rate.device)
    return torch.cat((torch.cat((pose, cross), -1), torch.cat((cross.mT, rate), -1)), -2)


def _source_scale(
    sched: Schedule, noise: EskfNoise, per_seq: Callable[[torch.Tensor], torch.Tensor]
) -> torch.Tensor:
    """(B, S) variance scale of each pose source (``noise.pose_source_scale``, default 1)."""
    ones = torch.ones(sched.t_end.shape[0], dtype=sched.t_end.dtype, device=sched.t_end.device)
    return torch.stack(
        [
            per_seq(noise.pose_source_scale[n]) if n in noise.pose_source_scale else ones
            for n in sched.source_names
        ],
        -1,
    )


def _source_gyro_change(
    sched: Schedule, memory: PairMemory | None = None, tolerance_s: float = 1e-6
) -> torch.Tensor:
    """(B, E, S, 3) rate of change of the body rate over each pose-source pair, rad/s^2.

    The difference of the mean gyro rates of the pair and of the source's previous pair
    (which must end where this one starts; before a chunk's first pair, the previous
    chunk's latest, ``memory``) over their mean interval; 0 where there is no such previous
    pair. Means over a pair average the gyro noise, which a difference of single samples
    would put into the time-offset Jacobian (biasing the offset towards 0).
    """
    batch, n_epochs, n_sources = sched.source_mask.shape
    mask = sched.source_mask
    index = torch.arange(n_epochs, device=mask.device)[None, :, None].expand_as(mask)
    last = torch.where(mask, index, -1).cummax(1).values
    previous = torch.cat((torch.full_like(last[:, :1], -1), last[:, :-1]), 1)
    safe = previous.clamp_min(0)
    prev_mean = sched.source_gyro_mean.gather(1, safe[..., None].expand(-1, -1, -1, 3))
    prev_dt = sched.source_dt.gather(1, safe)
    prev_end = sched.t_end.gather(1, safe.reshape(batch, -1)).reshape(batch, n_epochs, n_sources)
    first = previous < 0
    if memory is not None:  # a chunk's first pairs follow the previous chunk's latest
        prev_mean = torch.where(
            first[..., None], memory.pair_gyro_mean.to(prev_mean)[:, None], prev_mean
        )
        prev_dt = torch.where(first, memory.pair_dt.to(prev_dt)[:, None], prev_dt)
        prev_end = torch.where(first, memory.pair_end.to(prev_end)[:, None], prev_end)
        first = first & ~torch.isfinite(prev_end)
    start = sched.t_end[:, :, None] - sched.source_dt
    adjacent = mask & ~first & ((prev_end - start).abs() <= tolerance_s)
    span = (0.5 * (sched.source_dt + prev_dt)).clamp_min(1e-9)
    change = (sched.source_gyro_mean - prev_mean) / span[..., None]
    return torch.where(adjacent[..., None], change, 0.0)


def _reinitialise_frames(
    state: NavState,
    cov: torch.Tensor,
    frame_value: torch.Tensor,
    frames: SourceFrames,
    source_cov: torch.Tensor,
    to_conv: torch.Tensor,
    frame_col: int,
    epoch: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(Re-)initialise the offsets of the sources whose pair at ``epoch`` starts a segment
    (``frontend.source_frames``): the offset that zeroes the residual at the estimate, its
    covariance rows from the linearised model. Returns the covariance (B, N, N) and the
    offsets (B, S, 6)."""
    batch, n_state = cov.shape[0], cov.shape[-1]
    for s in range(len(frames.names)):
        reset = frames.reset[:, epoch, s]
        measured_p, measured_r = frames.position[:, epoch, s], frames.rotation[:, epoch, s]
        t_o, phi_o = drifting_frame_offset(state.position, state.rotation, measured_p, measured_r)
        _, h, _ = drifting_frame_pose_residual(
            state.position, state.rotation, t_o, phi_o, measured_p, measured_r
        )
        h_body = torch.zeros(batch, FRAME_DIM, n_state, dtype=cov.dtype, device=cov.device)
        h_body[..., :ERROR_STATE_DIM] = h @ to_conv
        cov = reinitialise(
            cov, h_body, source_cov[:, epoch, s, :FRAME_DIM, :FRAME_DIM], frame_col + 6 * s, reset
        )
        fresh = torch.cat((t_o, phi_o), -1)
        frame_value = torch.where(
            (reset[:, None] & (torch.arange(len(frames.names), device=cov.device) == s))[..., None],
            fresh[:, None, :],
            frame_value,
        )
    return cov, frame_value


def _joint_at_last_epoch(
    result: EskfResult, full_cov: torch.Tensor, block: slice
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """At each sequence's last real epoch (``result.mask``): the batch rows (B,), that epoch
    (B,) and the joint covariance (B, 15 + n, 15 + n) of the conventional navigation error
    and the augmented states in columns ``block`` of the invariant-coordinate ``full_cov``
    (B, E + 1, N, N) (what a next chunk's ``run_eskf`` starts from)."""
    epochs = torch.arange(result.mask.shape[1], device=full_cov.device)
    last = torch.where(result.mask, epochs, 0).argmax(1)
    rows = torch.arange(full_cov.shape[0], device=full_cov.device)
    full = full_cov[rows, last]
    to_conv, _ = _maps_at_estimate(
        result.position[rows, last], result.velocity[rows, last], result.rotation[rows, last]
    )
    cross = to_conv @ full[:, :ERROR_STATE_DIM, block]
    covariance = torch.cat(
        (
            torch.cat((result.covariance[rows, last], cross), -1),
            torch.cat((cross.mT, full[:, block, block]), -1),
        ),
        -2,
    )
    return rows, last, covariance


def _frame_memory(
    frames: SourceFrames,
    previous: FrameMemory | None,
    sched: Schedule,
    result: EskfResult,
    full_cov: torch.Tensor,
    frame_out: torch.Tensor,
    frame_col: int,
) -> FrameMemory:
    """The source frames after each sequence's last real epoch (``result.mask``), with the
    joint conventional covariance of the navigation state and the offsets there."""
    rows, last, covariance = _joint_at_last_epoch(result, full_cov, slice(frame_col, None))
    used = sched.source_mask & result.mask[:, 1:, None]
    stamps = torch.where(used, sched.t_end[:, :, None], -math.inf).amax(1)
    if previous is not None:
        stamps = torch.maximum(stamps, previous.last_time.to(stamps))
    return FrameMemory(frames.names, frame_out[rows, last], covariance, stamps)


def _check_calibration_memory(memory: CalibrationMemory, calib: CalibrationLayout) -> None:
    if tuple(memory.names) != tuple(calib.names):
        raise ValueError(
            f"calibration_memory holds {list(memory.names)}, but this run calibrates "
            f"{list(calib.names)}"
        )


def _calibration_memory(
    calib: CalibrationLayout, result: EskfResult, full_cov: torch.Tensor, frame_col: int
) -> CalibrationMemory:
    """The calibration states after each sequence's last real epoch (``result.mask``), with
    the joint conventional covariance of the navigation state and those states there."""
    block = slice(ERROR_STATE_DIM, frame_col)
    rows, last, covariance = _joint_at_last_epoch(result, full_cov, block)
    return CalibrationMemory(calib.names, result.calibration[rows, last], covariance)


def _position_frame_covariance(
    position_cov: torch.Tensor, full_cov: torch.Tensor, block: slice
) -> torch.Tensor:
    """(B, E + 1, 9, 9) joint covariance of the conventional position error and the offset
    error in columns ``block`` of the invariant-coordinate covariance ``full_cov``
    (B, E + 1, N, N), whose origin is the estimate's position (``dp = xi_p`` there);
    ``position_cov`` (B, E + 1, 3, 3) is the conventional position block."""
    cross = full_cov[..., 0:3, block]
    frame = full_cov[..., block, block]
    return torch.cat((torch.cat((position_cov, cross), -1), torch.cat((cross.mT, frame), -1)), -2)


def _segment_matrix(dims: list[int], dtype, device) -> torch.Tensor:
    """(M, K) 0/1 matrix mapping stacked measurement rows to their block."""
    seg = torch.zeros(sum(dims), len(dims), dtype=dtype, device=device)
    offset = 0
    for k, d in enumerate(dims):
        seg[offset : offset + d, k] = 1.0
        offset += d
    return seg


@contextlib.contextmanager
def _intra_op_threads(count: int):
    """Temporarily set torch's intra-op threads. The epoch loop works on tiny matrices:
    for a few sequences thread hand-offs cost more than they save (and oversubscribed
    cores make LAPACK's spinning threads take milliseconds per call), so it runs on one
    thread unless the batch is large (16 or more sequences)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _ordinary_tensors(value: object) -> object:
    """``value`` with every inference-mode tensor in it (in dataclass fields, dicts, lists and
    tuples, recursively) replaced by an ordinary copy; everything else is kept as it is."""
    if isinstance(value, torch.Tensor):
        return value.clone() if value.is_inference() else value
    if isinstance(value, dict):
        return {key: _ordinary_tensors(item) for key, item in value.items()}
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # NamedTuple
        return type(value)(*(_ordinary_tensors(item) for item in value))
    if isinstance(value, (list, tuple)):
        return type(value)(_ordinary_tensors(item) for item in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = copy.copy(value)
        for spec in dataclasses.fields(value):
            object.__setattr__(out, spec.name, _ordinary_tensors(getattr(value, spec.name)))
        return out
    return value


_SOURCE_LISTS = (
    "adaptive_noise_sensors",
    "strong_tracking_sensors",
    "calibrate_time_offsets",
    "calibrate_pose_extrinsics",
)
"""Config lists whose ``"pose:<name>"`` entries name pose sources of the data."""


def _warn_unknown_sources(cfg: EskfConfig, source_col: dict[str, int]) -> None:
    """Warn (once per message) about ``"pose:<name>"`` entries of :data:`_SOURCE_LISTS`
    that name no pose source of the batch: they do nothing (a misspelt name, or data
    without that source)."""
    for key in _SOURCE_LISTS:
        unknown = [
            n for n in getattr(cfg, key) if n.startswith(_SOURCE_PREFIX) and n not in source_col
        ]
        if unknown:
            have = ", ".join(source_col) or "none"
            warnings.warn(
                f"{key} names {', '.join(unknown)}, which no sequence of the batch has "
                f"(its pose sources: {have}): those entries do nothing",
                stacklevel=3,
            )


def run_eskf(
    seq: Sequence,
    cfg: EskfConfig | None = None,
    noise: EskfNoise | None = None,
    progress: Callable[[int, int], None] | None = None,
    initial: tuple[NavState, torch.Tensor] | None = None,
    gate_memory: GateMemory | None = None,
    frame_memory: FrameMemory | None = None,
    calibration_memory: CalibrationMemory | None = None,
    pair_memory: PairMemory | None = None,
    fault_memory: FaultMemory | None = None,
) -> EskfResult:
    """Run the ESKF over a batch of sequences.

    Args:
        seq: B sequences (IMU required; wheel, GNSS, poses optional), float64 advised.
        cfg: settings; defaults to :class:`EskfConfig()`.
        noise: noise tensors (learnable, shape () or (B,)); defaults to
            ``EskfNoise.from_config(cfg)``.
        progress: optional callback ``(epochs_done, epochs_total)`` (progress bars).
        initial: optional initial state (B, ...) and covariance (B, 15, 15) at each
            sequence's first IMU sample; default: ``frontend.init.initial_state``.
        gate_memory: the previous chunk's ``result.gate_memory`` when a run is filtered in
            chunks (``initial`` its last state): rejection streaks, the wheel slip factor and
            the adaptive noise's / strong tracking's state carry over.
        frame_memory: the previous chunk's ``result.frame_memory`` (drifting source frames):
            the offsets and their covariance with the state carry over.
        calibration_memory: the previous chunk's ``result.calibration_memory`` (online
            calibration): the estimates and their covariance with the state carry over
            (their correlation with drifting source frames does not).
        pair_memory: the previous chunk's ``result.pair_memory`` (pose sources): each
            source's pair across the boundary is fused as in the run in one piece (its mean
            gyro rate from the previous chunk's IMU and this one's), and the time-offset
            calibration sees the pair before it. The chunks must share their boundary IMU
            sample (the previous chunk's last is this one's first).
        fault_memory: the previous chunk's ``result.fault_memory``
            (``source_fault_detection``): the detector's models, windows and exclusions
            carry over.
    Returns:
        :class:`EskfResult` with (B, E + 1) per-epoch fields.
        Samples with non-finite values or repeated / backwards stamps are skipped and
        counted (``result.dropped_samples``); a sequence whose state or covariance turns
        non-finite or not positive definite, or whose re-opened gate lets through a NIS
        blow-up, is reset to its last good state with inflated covariance and flagged
        (``result.divergence``); see ``frontend.guard``.
    Raises:
        EstimationInterrupted: Ctrl-C (SIGINT) in the epoch loop; a ``KeyboardInterrupt``
            carrying the result of the epochs completed (``frontend.guard``).

    Example:
        >>> from msf_torch.sim import SimConfig, simulate_run
        >>> run = simulate_run(SimConfig(duration_s=5.0), seed=0)
        >>> result = run_eskf(run.sequence)
        >>> result.position.shape[0]
        1
    """
    if not torch.is_grad_enabled() and not torch.is_inference_mode_enabled():
        # no gradients asked for: inference mode skips autograd's per-op bookkeeping (about
        # a quarter of the time of a B = 1 run, whose epochs are many small ops); the result
        # comes back as ordinary tensors, usable anywhere
        try:
            with torch.inference_mode():
                result = run_eskf(
                    seq,
                    cfg,
                    noise,
                    progress,
                    initial,
                    gate_memory,
                    frame_memory,
                    calibration_memory,
                    pair_memory,
                    fault_memory,
                )
        except EstimationInterrupted as stop:
            raise EstimationInterrupted(
                _ordinary_tensors(stop.result), stop.epochs_done, stop.epochs_total
            ) from None
        return _ordinary_tensors(result)
    cfg = cfg or EskfConfig()
    dtype, device = seq.imu.t.dtype, seq.imu.t.device
    noise = noise or EskfNoise.from_config(cfg, dtype, device)
    seq, dropped_samples = sanitize_sequence(seq)
    sched = build_schedule(seq, cfg, pair_memory, continuing=gate_memory is not None)
    frames = (
        build_source_frames(seq, sched, cfg, frame_memory)
        if cfg.pose_source_fusion == "drifting_frame" and sched.source_names
        else None
    )
    state, cov_conventional = initial if initial is not None else initial_state(seq, cfg)
    # kept in invariant coordinates about the estimate's own position (moved every epoch)
    _, to_inv0 = _maps_at_estimate(state.position, state.velocity, state.rotation)
    cov = to_inv0 @ cov_conventional @ to_inv0.mT
    gravity = gravity_world(cfg.gravity_mps2, dtype, device)
    batch, n_epochs = sched.t_end.shape
    present = {
        "wheel": sched.wheel_mask,
        "nhc": sched.nhc_mask,
        "zupt": sched.zupt_mask,
        "gnss": sched.gnss_mask,
        "gnss_velocity": sched.gnss_velocity_mask,
        "gnss_heading": sched.gnss_heading_mask,
        "magnetometer": sched.magnetometer_mask,
        "pose": sched.pose_mask,
    }
    source_col = {_SOURCE_PREFIX + n: s for s, n in enumerate(sched.source_names)}
    _warn_unknown_sources(cfg, source_col)
    present.update({k: sched.source_mask[..., s] for k, s in source_col.items()})
    if frames is not None:  # a sample that (re-)initialises its offset is not fused
        present.update({k: present[k] & ~frames.reset[..., s] for k, s in source_col.items()})
    sensors = SENSORS + tuple(source_col)
    active = [k for k in sensors if bool(present[k].any())]
    source_rows = (3 if frames is None else FRAME_DIM) + (3 if cfg.pose_source_rate_update else 0)
    dims = dict(_DIMS) | dict.fromkeys(source_col, source_rows)
    if not (cfg.wheel_yaw_rate_update or cfg.calibrate_wheels):
        dims["wheel"] = 3  # the yaw-rate row then only feeds the slip factor
    thresholds = {k: chi2_threshold(dims[k], cfg.gate_probability) for k in sensors}
    if not cfg.gate_pseudo_measurements:
        thresholds["nhc"] = thresholds["zupt"] = math.inf
    blocks = [dims[k] for k in active]
    n_rows = sum(blocks)
    segment = _segment_matrix(blocks, dtype, device)  # (M, K)
    block_mask = segment @ segment.mT  # (M, M) 1 inside diagonal blocks
    eye_rows = torch.eye(n_rows, dtype=dtype, device=device)
    threshold = torch.tensor(
        [thresholds[k] if math.isfinite(thresholds[k]) else 1e300 for k in active],
        dtype=dtype,
        device=device,
    )
    reopen = torch.tensor(
        [
            k in ("gnss", "gnss_velocity", "gnss_heading", "magnetometer", "pose")
            or k in source_col
            for k in active
        ],
        device=device,
    )
    velocity_col = active.index("gnss_velocity") if "gnss_velocity" in active else None
    magnetometer_col = active.index("magnetometer") if "magnetometer" in active else None
    # blocks that stay shut while another re-openable block vouches for the state: a burst
    # of Doppler outliers, of wrong dual-antenna headings or of a magnetometer near steel
    # must not be let in
    suspect_cols = [
        active.index(k) for k in ("gnss_velocity", "gnss_heading", "magnetometer") if k in active
    ]
    # a horizontal-only GNSS velocity (no up component) is gated with two degrees of freedom
    horizontal_only = sched.gnss_velocity_sigma[..., 2] >= UNMEASURED_SIGMA  # (B, E)
    two_dof = chi2_threshold(2, cfg.gate_probability)
    present_all = torch.stack([present[k] for k in active], -1) if active else None
    adaptation = BlockAdaptation(
        active,
        blocks,
        cfg.adaptive_noise_sensors,
        cfg.strong_tracking_sensors,
        batch,
        cfg.adaptive_forgetting,
        cfg.adaptive_prior_samples,
        cfg.adaptive_noise_floor,
        cfg.strong_tracking_softening,
        cfg.adaptive_clip_probability,
        cfg.strong_tracking_max_factor,
        dtype,
        device,
    )
    carried_adaptation = None if gate_memory is None else gate_memory.adaptation
    adaptation.restore(carried_adaptation)

    def per_seq(x: torch.Tensor) -> torch.Tensor:
        return x.expand(batch) if x.dim() == 0 else x

    wheel_lever = torch.as_tensor(cfg.wheel_lever_arm_m, dtype=dtype, device=device)
    nhc_lever = torch.as_tensor(cfg.nhc_lever_arm_m, dtype=dtype, device=device)
    gnss_lever = torch.as_tensor(cfg.gnss_lever_arm_m, dtype=dtype, device=device)
    wheel_var = torch.stack(
        (
            per_seq(noise.wheel_speed_sigma) ** 2,
            per_seq(noise.wheel_lateral_sigma) ** 2,
            per_seq(noise.wheel_lateral_sigma) ** 2,
            per_seq(noise.wheel_yaw_rate_sigma) ** 2,
        ),
        -1,
    )
    nhc_var = (per_seq(noise.nhc_sigma) ** 2)[:, None].expand(batch, 2)
    zupt_var = (per_seq(noise.zupt_sigma) ** 2)[:, None].expand(batch, 3)
    # per-epoch rows of the noise-dependent tables (``unbind``: a gradient's backward is
    # one stack, not a zero fill of the whole table at every epoch)
    gnss_var = ((sched.gnss_sigma * per_seq(noise.gnss_sigma_scale)[:, None, None]) ** 2).unbind(1)
    gnss_velocity_var = sched.gnss_velocity_sigma**2
    gnss_heading_var = (sched.gnss_heading_sigma**2)[..., None]  # (B, E, 1)
    heading_baseline = torch.as_tensor(cfg.gnss_heading_baseline_m, dtype=dtype, device=device)
    source_cov = (
        _source_covariance(sched, noise, cfg, per_seq)
        if frames is None
        else _frame_covariance(sched, frames, noise, cfg, per_seq)
    )
    source_cov_rows = source_cov.unbind(1)
    faults = None  # frontend.gating: multi-model source-fault detection over the pairs
    block_weight = None  # (B, E, K) 0/1 straight-through weight of each block
    if fault_memory is not None and not (cfg.source_fault_detection and source_col):
        raise ValueError("fault_memory given, but this run detects no pose-source faults")
    if cfg.source_fault_detection and source_col:
        scale = _source_scale(sched, noise, per_seq)[:, None, :, None, None]
        faults = detect_source_faults(
            sched.t_end,
            sched.source_velocity,
            sched.source_rate,
            scale * sched.source_covariance,
            scale * sched.source_rate_covariance,
            sched.source_dt,
            sched.source_mask,
            SourceFaultParams.from_config(cfg),
            memory=fault_memory,
            names=sched.source_names,
        )
        keep = torch.ones(batch, n_epochs, dtype=dtype, device=device)
        block_weight = torch.stack(
            [faults.weight[..., source_col[k]] if k in source_col else keep for k in active], -1
        )
    source_lever = torch.zeros(3, dtype=dtype, device=device)
    eye15 = torch.eye(ERROR_STATE_DIM, dtype=dtype, device=device)
    # online calibration (frontend.calibration): states appended after the 15 nav entries
    calib = CalibrationLayout.from_config(cfg, sensors, dtype, device)
    if calibration_memory is not None and calib is None:
        raise ValueError("calibration_memory given, but this run calibrates no state")
    n_calib = 0 if calib is None else calib.size
    calib_value = torch.zeros(batch, n_calib, dtype=dtype, device=device)
    eye_state = eye15
    if calib is not None:
        calib_value = calib.initial.expand(batch, n_calib).clone()
        cross = torch.zeros(batch, ERROR_STATE_DIM, n_calib, dtype=dtype, device=device)
        calib_cov = calib.prior_covariance(batch)
        if calibration_memory is not None:  # the previous chunk's estimates and covariance
            _check_calibration_memory(calibration_memory, calib)
            calib_value = calibration_memory.value.to(dtype).clone()
            carried = calibration_memory.covariance.to(dtype)
            cross = to_inv0 @ carried[:, :ERROR_STATE_DIM, ERROR_STATE_DIM:]
            calib_cov = carried[:, ERROR_STATE_DIM:, ERROR_STATE_DIM:]
        cov = torch.cat(
            (torch.cat((cov, cross), -1), torch.cat((cross.mT, calib_cov), -1)),
            -2,
        )
        gyro_change = _source_gyro_change(sched, pair_memory)
    # drifting source frames (frontend.source_frames): six offset states per source, after
    # the calibration states; their prior is replaced at each source's first pair
    n_frame = 0 if frames is None else frames.size
    frame_col = ERROR_STATE_DIM + n_calib
    frame_value = torch.zeros(batch, len(sched.source_names), FRAME_DIM, dtype=dtype, device=device)
    if frames is not None:
        frame_scale = _source_scale(sched, noise, per_seq)
        cross = torch.zeros(batch, frame_col, n_frame, dtype=dtype, device=device)
        prior = torch.eye(n_frame, dtype=dtype, device=device).expand(batch, n_frame, n_frame)
        cov = torch.cat((torch.cat((cov, cross), -1), torch.cat((cross.mT, prior), -1)), -2)
        reset_epochs = frames.reset.any(0).tolist()  # (E, S) host flags: one transfer
        if frame_memory is not None:  # the previous chunk's offsets, covariance rows
            frame_value = frame_memory.value.to(dtype).clone()
            carried = frame_memory.covariance.to(dtype)
            cross = to_inv0 @ carried[:, :ERROR_STATE_DIM, ERROR_STATE_DIM:]
            cov = cov.clone()
            cov[:, :ERROR_STATE_DIM, frame_col:] = cross
            cov[:, frame_col:, :ERROR_STATE_DIM] = cross.mT
            cov[:, frame_col:, frame_col:] = carried[:, ERROR_STATE_DIM:, ERROR_STATE_DIM:]
    n_aug = n_calib + n_frame
    if n_aug:
        eye_state = torch.eye(ERROR_STATE_DIM + n_aug, dtype=dtype, device=device)
    frame_base = eye15.expand(batch, 15, 15)
    nav_frame = torch.zeros(batch, 9, 9, dtype=dtype, device=device)
    zeros_b = torch.zeros(batch, dtype=dtype, device=device)
    false_b = torch.zeros(batch, dtype=torch.bool, device=device)

    slip = torch.ones(batch, dtype=dtype, device=device)
    last_wheel_t = sched.t_start.clone()
    if gate_memory is not None and gate_memory.slip_factor is not None:
        slip = gate_memory.slip_factor.to(dtype).clone()
        last_wheel_t = gate_memory.last_wheel_time.to(dtype).clone()
    guard = DivergenceGuard(
        state, cov, cfg, active, segment, reopen, _maps_at_estimate, gate_memory
    )  # also counts each block's gate rejections in a row (guard.streak)
    divergence_out = [torch.zeros(batch, dtype=torch.long, device=device)]
    out: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("p", "v", "R", "bg", "ba", "P", "s", "c", "f")
    }
    accepted_out: list[torch.Tensor] = []
    nis_out: list[torch.Tensor] = []
    logdet_out: list[torch.Tensor] = []

    def record(st: NavState, p_cov: torch.Tensor, slip_now: torch.Tensor) -> None:
        out["p"].append(st.position)
        out["v"].append(st.velocity)
        out["R"].append(st.rotation)
        out["bg"].append(st.gyro_bias)
        out["ba"].append(st.accel_bias)
        out["P"].append(p_cov)
        out["s"].append(slip_now)
        out["c"].append(calib_value)
        out["f"].append(frame_value)

    record(state, cov, slip)
    no_blocks = torch.zeros(batch, len(active), dtype=dtype, device=device)
    accepted_out.append(no_blocks.bool())
    nis_out.append(no_blocks)
    logdet_out.append(no_blocks)

    # which epochs have a measurement in any sequence: one host transfer, not one per epoch
    epoch_has_update = (
        [False] * n_epochs if present_all is None else present_all.any(-1).any(0).tolist()
    )
    interrupt = InterruptCatcher()
    # a large batch on the CPU without gradients preintegrates on a second thread while the
    # epochs run (each on one intra-op thread); otherwise all of it first, then the epochs
    background = (
        torch.is_inference_mode_enabled()
        and device.type == "cpu"
        and batch >= 16
        and torch.get_num_threads() >= 2
    )
    loop_threads = 1 if batch < 16 or background else torch.get_num_threads()
    walk = [*cfg.imu_gap_gyro_rw_density, *cfg.imu_gap_accel_rw_density]
    walk_on = any(walk) and bool(sched.gap.any())  # one check: runs without gaps skip it
    increments = _EpochIncrements(
        sched,
        state.gyro_bias,
        state.accel_bias,
        noise,
        cfg.gravity_mps2,
        background,
        gap_walk=torch.tensor(walk, dtype=dtype, device=device) if walk_on else None,
        gap_walk_max_blind_s=cfg.imu_gap_walk_max_blind_s,
    )
    with contextlib.closing(increments), _intra_op_threads(loop_threads), interrupt:
        for e in range(n_epochs):
            # --- propagation: nominal with bias-corrected increments -----------------------
            chunk, k = increments.at(e)
            pre, epoch_dt = chunk.pre, chunk.pre.delta_t[:, k]
            d_rot, d_vel, d_pos = pre.corrected(state.gyro_bias, state.accel_bias, index=k)
            position, velocity, rotation = propagate_nominal(
                state.position,
                state.velocity,
                state.rotation,
                epoch_dt,
                d_rot,
                d_vel,
                d_pos,
                gravity,
            )
            # invariant-coordinate transition: the navigation block depends on dT only
            # (precomputed); the bias columns are T_j^-1 [R_i J_p; R_i J_v; J_t]
            jac = pre.bias_jacobian[:, k]
            # errors are taken about the estimate's own position, so the transition maps
            # errors about p_i to errors about p_j: ``_move_origin`` by p_i - p_j folded in on
            # the left, which cancels the position arm of T_j^-1 and leaves [p_i - p_j]x in
            # the position rows' attitude columns
            hat_velocity = so3.hat(velocity)
            right = torch.cat((torch.zeros_like(rotation), hat_velocity @ rotation, rotation), -2)
            rotated = state.rotation @ torch.cat((jac[:, 0:3], jac[:, 3:6]), -1)
            transition = chunk.nav_transition[:, k].clone()
            transition[:, 0:9, 9:15] = right @ jac[:, 6:9]
            transition[:, 0:6, 9:15] += torch.cat(rotated.split(6, -1), -2)
            noise_map = nav_frame.clone()
            noise_map[:, 0:3, 0:3] = state.rotation
            noise_map[:, 3:6, 3:6] = state.rotation
            noise_map[:, :, 6:9] = right
            transition[:, 0:3, 6:9] += so3.hat(state.position - position)
            q_local = chunk.q_rows[k]
            q = q_local.clone()
            q[:, 0:9, 0:9] = noise_map @ q_local[:, 0:9, 0:9] @ noise_map.mT
            if not n_aug:
                cov = transition @ cov @ transition.mT + q
            else:  # calibration states and source frames: identity transition, random walk
                full = eye_state.repeat(batch, 1, 1)
                full[:, :ERROR_STATE_DIM, :ERROR_STATE_DIM] = transition
                q_full = torch.zeros_like(full)
                q_full[:, :ERROR_STATE_DIM, :ERROR_STATE_DIM] = q
                if calib is not None:
                    q_full[:, ERROR_STATE_DIM:frame_col, ERROR_STATE_DIM:frame_col] = (
                        calib.process_noise(epoch_dt)
                    )
                if frames is not None:  # random walk in distance travelled
                    speed = 0.5 * (state.velocity.norm(dim=-1) + velocity.norm(dim=-1))
                    q_full[:, frame_col:, frame_col:] = frames.process_noise(
                        frame_scale, speed * epoch_dt
                    )
                q = q_full
                cov = full @ cov @ full.mT + q
            if calib is not None:
                accel_world = (velocity - state.velocity) / epoch_dt[:, None].clamp_min(1e-9)
            to_conv = frame_base.clone()  # about the new origin p_j: no position arm
            to_conv[:, 3:6, 6:9] = -hat_velocity
            to_conv[:, 6:9, 6:9] = rotation.mT
            state = NavState(position, velocity, rotation, state.gyro_bias, state.accel_bias)
            if frames is not None and any(reset_epochs[e]):
                cov, frame_value = _reinitialise_frames(
                    state, cov, frame_value, frames, source_cov, to_conv, frame_col, e
                )
            guard.propagated(state, cov)

            if not epoch_has_update[e]:
                state, cov, code = guard.check(state, cov)
                divergence_out.append(code)
                accepted_out.append(no_blocks.bool())
                nis_out.append(no_blocks)
                logdet_out.append(no_blocks)
                record(state, cov, slip)
                if progress is not None:
                    progress(e + 1, n_epochs)
                continue

            # --- measurement blocks (residuals from sensors/, stacked) ---------------------
            residuals, jacobians, variances = [], [], []
            calib_jacobians = []  # (B, d, n) per block
            frame_jacobians = []  # (B, d, 6 S) per block
            full_cov = []  # (row offset, (B, d, d) covariance) of blocks with full covariances
            offset = 0
            gyro_end = sched.gyro_end[:, e]
            for name in active:
                h_calib = h_frame = None
                if name == "wheel":
                    if calib is not None and calib.imu_body_index is not None:
                        col_v = calib.imu_body_index
                        ones = torch.ones(batch, 2, dtype=dtype, device=device)
                        r, h, h_wheel, h_rot = vehicle_frame_wheel_residual(
                            state.velocity,
                            state.rotation,
                            gyro_end,
                            state.gyro_bias,
                            sched.wheel_left[:, e],
                            sched.wheel_right[:, e],
                            calib_value[:, 0:2] if calib.wheels else ones,
                            calib_value[:, 2] if calib.wheels else cfg.wheel_track_m + zeros_b,
                            wheel_lever,
                            calib.rotation_matrix(calib_value, col_v),
                        )
                        h_calib = torch.zeros(batch, 4, n_calib, dtype=dtype, device=device)
                        if calib.wheels:
                            h_calib[..., 0:3] = h_wheel
                        h_calib[..., col_v : col_v + 3] = h_rot
                    elif calib is not None and calib.wheels:
                        r, h, h_wheel = calibrated_wheel_residual(
                            state.velocity,
                            state.rotation,
                            gyro_end,
                            state.gyro_bias,
                            sched.wheel_left[:, e],
                            sched.wheel_right[:, e],
                            calib_value[:, 0:2],
                            calib_value[:, 2],
                            wheel_lever,
                        )
                        h_calib = torch.zeros(batch, 4, n_calib, dtype=dtype, device=device)
                        h_calib[..., 0:3] = h_wheel
                    else:
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
                    var = wheel_var
                    here = sched.wheel_mask[:, e]
                    if cfg.slip_detection:
                        h_inv = h @ to_conv
                        if calib is not None:
                            h_inv = torch.cat(
                                (
                                    h_inv,
                                    h_calib
                                    if h_calib is not None
                                    else h.new_zeros(batch, h.shape[-2], n_calib),
                                ),
                                -1,
                            )
                        if n_frame:
                            h_inv = torch.cat((h_inv, h.new_zeros(batch, h.shape[-2], n_frame)), -1)
                        innov = torch.diagonal(h_inv @ cov @ h_inv.mT, dim1=-2, dim2=-1) + var
                        new_slip = slip_factor(
                            r,
                            innov,
                            slip,
                            sched.t_end[:, e] - last_wheel_t,
                            cfg.slip_sensitivity,
                            cfg.slip_recovery_per_s,
                        )
                        slip = torch.where(here & torch.isfinite(new_slip), new_slip, slip)
                        var = var / slip[:, None].clamp_min(1e-3) ** 2
                    last_wheel_t = torch.where(here, sched.t_end[:, e], last_wheel_t)
                    rows_used = dims["wheel"]
                    r, h, var = r[:, :rows_used], h[:, :rows_used], var[:, :rows_used]
                    if h_calib is not None:
                        h_calib = h_calib[:, :rows_used]
                elif name == "nhc" and calib is not None and calib.imu_body_index is not None:
                    col_v = calib.imu_body_index
                    r, h, h_rot = vehicle_frame_nonholonomic_residual(
                        state.velocity,
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        nhc_lever,
                        calib.rotation_matrix(calib_value, col_v),
                    )
                    h_calib = torch.zeros(batch, 2, n_calib, dtype=dtype, device=device)
                    h_calib[..., col_v : col_v + 3] = h_rot
                    var = nhc_var
                elif name == "nhc":
                    r, h = nonholonomic_residual(
                        state.velocity, state.rotation, gyro_end, state.gyro_bias, nhc_lever
                    )
                    var = nhc_var
                elif name == "zupt":
                    r, h = zero_velocity_residual(state.velocity)
                    var = zupt_var
                elif (
                    name == "gnss"
                    and calib is not None
                    and ("gnss" in calib.time_offset_index or calib.gnss_lever_index is not None)
                ):
                    col_l = calib.gnss_lever_index
                    lever = gnss_lever if col_l is None else calib_value[:, col_l : col_l + 3]
                    h_calib = torch.zeros(batch, 3, n_calib, dtype=dtype, device=device)
                    offset_now = zeros_b
                    if "gnss" in calib.time_offset_index:
                        col_td = calib.time_offset_index["gnss"]
                        offset_now = calib_value[:, col_td]
                        r, h, h_td = shifted_gnss_residual(
                            state.position,
                            state.velocity,
                            state.rotation,
                            gyro_end,
                            state.gyro_bias,
                            lever,
                            sched.gnss_position[:, e],
                            offset_now,
                        )
                        h_calib[..., col_td : col_td + 1] = h_td
                    else:
                        r, h = gnss_residual(
                            state.position, state.rotation, lever, sched.gnss_position[:, e]
                        )
                    if col_l is not None:
                        h_calib[..., col_l : col_l + 3] = gnss_lever_arm_jacobian(
                            state.rotation, gyro_end, state.gyro_bias, offset_now
                        )
                    var = gnss_var[e]
                elif name == "gnss":
                    r, h = gnss_residual(
                        state.position, state.rotation, gnss_lever, sched.gnss_position[:, e]
                    )
                    var = gnss_var[e]
                elif name == "gnss_velocity":
                    col_l = None if calib is None else calib.gnss_lever_index
                    lever = gnss_lever if col_l is None else calib_value[:, col_l : col_l + 3]
                    r, h = gnss_velocity_residual(
                        state.velocity,
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        lever,
                        sched.gnss_velocity[:, e],
                    )
                    if col_l is not None:  # d(R (w x l)) / dl = R [w]x
                        h_calib = torch.zeros(batch, 3, n_calib, dtype=dtype, device=device)
                        h_calib[..., col_l : col_l + 3] = state.rotation @ so3.hat(
                            gyro_end - state.gyro_bias
                        )
                    var = gnss_velocity_var[:, e]
                elif name == "gnss_heading" and (
                    calib is not None
                    and (
                        calib.heading_offset_index is not None
                        or "gnss_heading" in calib.time_offset_index
                    )
                ):
                    col_o = calib.heading_offset_index
                    col_td = calib.time_offset_index.get("gnss_heading")
                    r, h, h_offset, h_td = shifted_heading_residual(
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        heading_baseline,
                        zeros_b if col_o is None else calib_value[:, col_o],
                        zeros_b if col_td is None else calib_value[:, col_td],
                        sched.gnss_heading[:, e],
                    )
                    h_calib = torch.zeros(batch, 1, n_calib, dtype=dtype, device=device)
                    if col_o is not None:
                        h_calib[..., col_o : col_o + 1] = h_offset
                    if col_td is not None:
                        h_calib[..., col_td : col_td + 1] = h_td
                    var = gnss_heading_var[:, e]
                elif name == "gnss_heading":
                    r, h = gnss_heading_residual(
                        state.rotation, heading_baseline, sched.gnss_heading[:, e]
                    )
                    var = gnss_heading_var[:, e]
                elif name == "magnetometer":
                    field_body = sched.magnetometer_field[:, e]
                    col_d = None if calib is None else calib.declination_index
                    r, h = magnetometer_heading_residual(
                        state.rotation,
                        field_body,
                        cfg.magnetometer_declination_rad
                        if col_d is None
                        else calib_value[:, col_d],
                    )
                    if col_d is not None:  # r = wrap(azimuth - D): dr/dD = -1
                        h_calib = torch.zeros(batch, 1, n_calib, dtype=dtype, device=device)
                        h_calib[..., col_d] = -1.0
                    magnetometer_dip_ok = (
                        field_dip(state.rotation, field_body) - sched.magnetometer_dip
                    ).abs() <= cfg.magnetometer_dip_tolerance_rad
                    var = magnetometer_heading_variance(
                        state.rotation,
                        field_body,
                        sched.magnetometer_sigma[:, e],
                        cfg.magnetometer_heading_floor_rad,
                    )[:, None]
                elif name == "pose":
                    r, h = pose_residual(
                        state.position,
                        state.rotation,
                        sched.pose_position[:, e],
                        sched.pose_rotation[:, e],
                    )
                    var = zeros_b[:, None].expand(batch, 6)
                    full_cov.append((offset, sched.pose_covariance[:, e]))
                elif frames is not None and name in source_col:
                    col = source_col[name]
                    value = frame_value[:, col]
                    r, h, h_f = drifting_frame_pose_residual(
                        state.position,
                        state.rotation,
                        value[:, :3],
                        value[:, 3:],
                        frames.position[:, e, col],
                        frames.rotation[:, e, col],
                    )
                    if cfg.pose_source_rate_update:
                        r, h = _with_mean_rate_row(r, h, sched, e, col, state.gyro_bias)
                        h_f = torch.cat((h_f, h_f.new_zeros(batch, 3, FRAME_DIM)), -2)
                    h_frame = torch.zeros(batch, r.shape[-1], n_frame, dtype=dtype, device=device)
                    h_frame[..., FRAME_DIM * col : FRAME_DIM * (col + 1)] = h_f
                    var = zeros_b[:, None].expand(batch, r.shape[-1])
                    full_cov.append((offset, source_cov_rows[e][:, col]))
                elif calib is not None and name in calib.pose_extrinsic_index:
                    col = source_col[name]
                    col_x = calib.pose_extrinsic_index[name]
                    col_td = calib.time_offset_index.get(name)
                    offset_now = zeros_b if col_td is None else calib_value[:, col_td]
                    mount = calib.rotation_matrix(calib_value, col_x + 3)
                    r, h, h_td, h_lever, h_mount = mounted_velocity_residual(
                        state.velocity,
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        calib_value[:, col_x : col_x + 3],
                        mount,
                        accel_world,
                        sched.source_velocity[:, e, col],
                        offset_now - 0.5 * sched.source_dt[:, e, col],
                    )
                    h_extrinsic = torch.cat((h_lever, h_mount), -1)  # (B, 3, 6)
                    if cfg.pose_source_rate_update:
                        r_w, h_w, h_td_w, h_mount_w = mounted_rate_residual(
                            sched.source_gyro_mean[:, e, col],
                            state.gyro_bias,
                            gyro_change[:, e, col],
                            mount,
                            sched.source_rate[:, e, col],
                            offset_now,
                        )
                        r, h = torch.cat((r, r_w), -1), torch.cat((h, h_w), -2)
                        h_td = torch.cat((h_td, h_td_w), -2)
                        h_extrinsic = torch.cat(
                            (h_extrinsic, torch.cat((torch.zeros_like(h_mount_w), h_mount_w), -1)),
                            -2,
                        )
                    h_calib = torch.zeros(batch, r.shape[-1], n_calib, dtype=dtype, device=device)
                    if col_td is not None:
                        h_calib[..., col_td : col_td + 1] = h_td
                    h_calib[..., col_x : col_x + 6] = h_extrinsic
                    var = zeros_b[:, None].expand(batch, r.shape[-1])
                    full_cov.append((offset, source_cov_rows[e][:, col]))
                elif calib is not None and name in calib.time_offset_index:
                    col = source_col[name]
                    col_td = calib.time_offset_index[name]
                    offset_now = calib_value[:, col_td]
                    # the pair's mean velocity is the velocity at its mid-time, dt / 2 before
                    # its end: predicted at t + t_d - dt / 2 (d/dt_d unchanged)
                    r, h, h_td = shifted_body_velocity_residual(
                        state.velocity,
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        source_lever,
                        accel_world,
                        sched.source_velocity[:, e, col],
                        offset_now - 0.5 * sched.source_dt[:, e, col],
                    )
                    if cfg.pose_source_rate_update:
                        r_w, h_w, h_td_w = shifted_mean_rate_residual(
                            sched.source_gyro_mean[:, e, col],
                            state.gyro_bias,
                            gyro_change[:, e, col],
                            sched.source_rate[:, e, col],
                            offset_now,
                        )
                        r, h = torch.cat((r, r_w), -1), torch.cat((h, h_w), -2)
                        h_td = torch.cat((h_td, h_td_w), -2)
                    h_calib = torch.zeros(batch, r.shape[-1], n_calib, dtype=dtype, device=device)
                    h_calib[..., col_td : col_td + 1] = h_td
                    var = zeros_b[:, None].expand(batch, r.shape[-1])
                    full_cov.append((offset, source_cov_rows[e][:, col]))
                else:
                    col = source_col[name]
                    r, h = body_velocity_residual(
                        state.velocity,
                        state.rotation,
                        gyro_end,
                        state.gyro_bias,
                        source_lever,
                        sched.source_velocity[:, e, col],
                    )
                    if cfg.pose_source_rate_update:
                        r, h = _with_mean_rate_row(r, h, sched, e, col, state.gyro_bias)
                    var = zeros_b[:, None].expand(batch, r.shape[-1])
                    full_cov.append((offset, source_cov_rows[e][:, col]))
                offset += r.shape[-1]
                residuals.append(r)
                jacobians.append(h)
                variances.append(var)
                if calib is not None:
                    calib_jacobians.append(
                        h_calib
                        if h_calib is not None
                        else torch.zeros(batch, r.shape[-1], n_calib, dtype=dtype, device=device)
                    )
                if n_frame:
                    frame_jacobians.append(
                        h_frame
                        if h_frame is not None
                        else torch.zeros(batch, r.shape[-1], n_frame, dtype=dtype, device=device)
                    )
            r_all = torch.cat(residuals, -1)
            h_all = torch.cat(jacobians, -2) @ to_conv  # w.r.t. the invariant error
            if calib is not None:
                h_all = torch.cat((h_all, torch.cat(calib_jacobians, -2)), -1)
            if n_frame:
                h_all = torch.cat((h_all, torch.cat(frame_jacobians, -2)), -1)
            r_cov = torch.diag_embed(torch.cat(variances, -1))
            if full_cov:
                r_cov = r_cov.clone()
                for start, block in full_cov:
                    size = block.shape[-1]
                    r_cov[:, start : start + size, start : start + size] = block
            if adaptation.enabled:  # frontend.adaptive: Sage-Husa R, strong tracking
                teaching = present_all[:, e]
                if block_weight is not None:  # an excluded source teaches the noise nothing
                    teaching = teaching & (block_weight[:, e] > 0.5)
                cov, r_cov = adaptation.step(e, cov - q, q, h_all, r_all, r_cov, teaching)
            s_all = h_all @ cov @ h_all.mT + r_cov

            # --- gating: NIS of every block at once through the block-diagonal part of S ----
            here = present_all[:, e]
            here_rows = (here.to(dtype) @ segment.mT)[..., None]
            s_blocks = s_all * block_mask + (1.0 - here_rows) * eye_rows
            chol_b, info_b = torch.linalg.cholesky_ex(s_blocks)
            white = torch.linalg.solve_triangular(chol_b, r_all[..., None], upper=False)
            nis = ((white[..., 0] ** 2) @ segment) * here
            # rows of absent blocks are the identity there: log 1 = 0
            logdet = (2.0 * torch.log(torch.diagonal(chol_b, dim1=-2, dim2=-1)) @ segment) * here
            gate = threshold
            if velocity_col is not None and bool(here[:, velocity_col].any()):
                gate = threshold.expand(batch, -1).clone()
                gate[:, velocity_col] = torch.where(
                    horizontal_only[:, e], two_dof, threshold[velocity_col]
                )
            ok = here & (nis < gate)
            reopening = here & reopen & (guard.streak >= cfg.gate_reopen_after)
            for col in suspect_cols:
                # a GNSS velocity or heading that disagrees while another re-openable block
                # (a fix, a pose) passes its gate during its streak is the suspect: its gate
                # stays shut
                calm = ok & reopen
                others_calm = calm.sum(-1) - calm[:, col].long() > 0
                suspect = guard.vouched[:, col] | others_calm
                reopening[:, col] = reopening[:, col] & ~suspect
            ok = ok | reopening
            if magnetometer_col is not None:  # a field tilted off the local dip is disturbed
                ok[:, magnetometer_col] = ok[:, magnetometer_col] & magnetometer_dip_ok
            if "wheel" in active and cfg.slip_detection:
                wheel_col = active.index("wheel")
                ok[:, wheel_col] = ok[:, wheel_col] & (slip >= cfg.slip_skip_below)
            passed = ok.to(dtype)
            if block_weight is not None:  # a source flagged as faulty weighs 0
                passed = passed * block_weight[:, e]
                ok = ok & (block_weight[:, e] > 0.5)
                here = here & (block_weight[:, e] > 0.5)

            # --- joint update over the accepted rows (Joseph form) ------------------------
            rows = passed @ segment.mT  # (B, M)
            rows_outer = rows[:, :, None] * rows[:, None, :]
            h_m = h_all * rows[..., None]
            s_m = s_all * rows_outer + torch.diag_embed(1.0 - rows)
            chol, info = torch.linalg.cholesky_ex(s_m)
            failed = (info != 0) | (info_b != 0)
            gain = torch.cholesky_solve(h_m @ cov, chol).mT  # (B, 15, M)
            dx = -(gain @ (r_all * rows)[..., None]).squeeze(-1)
            ikh = eye_state - gain @ h_m
            cov = ikh @ cov @ ikh.mT + gain @ (r_cov * rows_outer) @ gain.mT
            state = _inject_invariant(state, dx)
            cov = _move_origin(cov, -dx[:, 0:3])  # origin back on the corrected position
            calib_before, frame_before = calib_value, frame_value
            if calib is not None:
                calib_value = calib.inject(calib_value, dx[:, ERROR_STATE_DIM:frame_col])
            if n_frame:
                frame_value = inject_frames(frame_value, dx[:, frame_col:])
            cov = 0.5 * (cov + cov.mT)
            state, cov, ok, code = guard.updated(
                state, cov, ok, nis, threshold, failed, here, white[..., 0]
            )
            if calib is not None:  # a reset also takes the calibration back
                calib_value = torch.where((code != 0)[:, None], calib_before, calib_value)
            if n_frame:  # ... and the source frames
                frame_value = torch.where((code != 0)[:, None, None], frame_before, frame_value)
            divergence_out.append(code)
            accepted_out.append(ok)
            nis_out.append(nis)
            logdet_out.append(logdet)
            record(state, cov, slip)
            if progress is not None:
                progress(e + 1, n_epochs)

    done = interrupt.settle(
        list(out.values()), [accepted_out, nis_out, logdet_out, divergence_out], n_epochs
    )
    mask = torch.cat((torch.ones(batch, 1, dtype=torch.bool, device=device), sched.epoch_mask), 1)
    mask[:, done + 1 :] = False
    t = torch.cat((sched.t_start[:, None], sched.t_end), 1)
    positions = torch.stack(out["p"], 1)
    velocities = torch.stack(out["v"], 1)
    rotations = torch.stack(out["R"], 1)
    full_covariances = torch.stack(out["P"], 1)
    nav = slice(0, ERROR_STATE_DIM)
    # all B (E + 1) epochs at once, flattened to 3-D operands
    covariances = _conventional_covariance(
        velocities.flatten(0, 1),
        rotations.flatten(0, 1),
        full_covariances[..., nav, nav].flatten(0, 1),
    ).unflatten(0, (batch, n_epochs + 1))
    accepted_all = torch.stack(accepted_out, 1)  # (B, E + 1, K)
    nis_all = torch.stack(nis_out, 1)
    logdet_all = torch.stack(logdet_out, 1)
    present_out = {k: torch.cat((false_b[:, None], present[k]), 1) for k in sensors}
    accepted = {}
    nis = {}
    logdets = {}
    for k in sensors:
        if k in active:
            col = active.index(k)
            accepted[k] = accepted_all[..., col]
            nis[k] = nis_all[..., col]
            logdets[k] = logdet_all[..., col]
        else:
            accepted[k] = torch.zeros_like(present_out[k])
            nis[k] = torch.zeros(batch, n_epochs + 1, dtype=dtype, device=device)
            logdets[k] = torch.zeros_like(nis[k])
    gap = torch.cat((false_b[:, None], sched.gap), 1)
    fading, noise_estimate = adaptation.history(n_epochs)
    calib_ratio, calib_observable = None, {}
    if calib is not None:  # information gained on each state by the last epoch of each run
        calib_ratio, observable = observability(
            calib,
            torch.diagonal(
                full_covariances[..., nav.stop : frame_col, nav.stop : frame_col], dim1=-2, dim2=-1
            ),
            t - t[:, :1],
            cfg.calibration_observable_ratio,
        )
        epochs = torch.arange(n_epochs + 1, device=device)
        last = torch.where(mask, epochs, 0).argmax(1)
        rows_b = torch.arange(batch, device=device)
        calib_observable = {n: observable[rows_b, last, k] for k, n in enumerate(calib.names)}
    result = EskfResult(
        names=list(seq.names),
        t=t,
        mask=mask,
        position=positions,
        velocity=velocities,
        rotation=rotations,
        gyro_bias=torch.stack(out["bg"], 1),
        accel_bias=torch.stack(out["ba"], 1),
        covariance=covariances,
        slip_factor=torch.stack(out["s"], 1),
        present=present_out,
        accepted=accepted,
        nis=nis,
        innovation_logdet=logdets,
        gate_threshold={k: thresholds[k] for k in active},
        block_rows={k: dims[k] for k in active},
        gap=gap,
        divergence=torch.stack(divergence_out, 1),
        dropped_samples=dropped_samples,
        fading_factor=fading,
        noise_estimate=noise_estimate,
        source_fault={
            k: torch.cat((false_b[:, None], faults.flagged[..., s]), 1)
            for k, s in source_col.items()
        }
        if faults is not None
        else {},
        source_fault_z={
            k: torch.cat((zeros_b[:, None], faults.z[..., s]), 1) for k, s in source_col.items()
        }
        if faults is not None
        else {},
        calibration_names=() if calib is None else calib.names,
        calibration=None if calib is None else torch.stack(out["c"], 1),
        calibration_covariance=None
        if calib is None
        else full_covariances[..., ERROR_STATE_DIM:frame_col, ERROR_STATE_DIM:frame_col],
        calibration_variance_ratio=calib_ratio,
        calibration_observable=calib_observable,
    )
    if frames is not None:
        frame_out = torch.stack(out["f"], 1)  # (B, E + 1, S, 6)
        result.frame_memory = _frame_memory(
            frames, frame_memory, sched, result, full_covariances, frame_out, frame_col
        )
        for key, s in source_col.items():
            block = slice(frame_col + FRAME_DIM * s, frame_col + FRAME_DIM * (s + 1))
            result.source_frame[key] = frame_out[:, :, s]
            result.source_frame_covariance[key] = _position_frame_covariance(
                covariances[..., 0:3, 0:3], full_covariances, block
            )
    result.gate_memory = dataclasses.replace(
        guard.memory(),
        slip_factor=slip,
        last_wheel_time=last_wheel_t,
        adaptation=adaptation.memory(carried_adaptation)
        if adaptation.enabled or carried_adaptation
        else None,
    )
    if calib is not None:
        result.calibration_memory = _calibration_memory(calib, result, full_covariances, frame_col)
    result.pair_memory = sched.pair_memory
    result.fault_memory = None if faults is None else faults.memory
    if interrupt.caught:
        raise EstimationInterrupted(result, done, n_epochs)
    return result
