"""Drifting source frames: pose sources fused as absolute poses (``drifting_frame`` mode).

With ``EskfConfig.pose_source_fusion = "drifting_frame"`` every fused pose source ``s`` gets
six error states after the navigation (and calibration) ones: the offset of its frame,
``[t_o (m, world), phi_o (rad, body)]``, with the measurement model of
``sensors.pose.drifting_frame_pose_residual``: ``z_p = p + t_o``, ``R_z = R Exp(phi_o)``
(additive translation error, right rotation error ``Exp(phi_o) = Exp(phi_hat) Exp(dphi)``).
This is the error model of the simulator's odometry (``msf_torch.sim.weather``: a world-frame
position drift and a body-frame rotation drift, both random walks in distance travelled).
A rigid SE(3) frame offset would tie a rotation offset to the distance from the source's
origin, which that model does not have.

* Process: a random walk in distance travelled ``ds = |v| dT``:
  ``Q = s diag(q_p^2 ds I_3, q_theta^2 ds I_3)`` per epoch, ``q_p, q_theta`` the source's
  drift densities (``pose_source_drift*``, m/sqrt(m), rad/sqrt(m)) and ``s`` its variance
  scale (``EskfNoise.pose_source_scale``: drift accumulates the frame-to-frame errors, so it
  grows with the same weather factor as the white noise).
* Measurements: each sample that ends a pair of the schedule (``frontend.schedule``)
  is fused as an absolute pose, covariance ``s C`` (``C`` the declared 6x6 covariance).
  Consecutive samples then carry independent white noise, and the drift sits in the
  offset state, instead of each sample's noise entering two differenced pairs.
* (Re-)initialisation: at a source's first pair, and at every pair that does not start
  where the source's previous pair ended (a gap longer than ``pose_source_max_gap_s``: a VO
  reset), the offset is set from the measurement and the current estimate, ``t_o = z_p -
  p``, ``phi_o = Log(R^T R_z)`` (:func:`~msf_torch.sensors.pose.drifting_frame_offset`),
  and its covariance rows from the linearised model: with the residual ``r = H_x dx + dq -
  n`` (its offset Jacobian is I at ``r = 0``), ``dq = -H_x dx + n``, so
  ``P_qq = H_x P H_x^T + s C`` and ``P_qx = -H_x P``. The sample itself is consumed by the
  initialisation (not fused): no information is counted twice, and the old offset is
  forgotten.
* Chunks: a run filtered chunk by chunk (``learning.inference.run_piecewise``) hands each
  chunk's offsets, their joint covariance with the navigation state and each source's last
  sample time to the next (:class:`FrameMemory`, ``EskfResult.frame_memory``); a chunk's
  first pair then continues the offset when it starts at most ``pose_source_max_gap_s``
  after that time. With ``run_eskf(..., pair_memory=...)`` that first pair is the one across
  the chunk boundary, as in the run in one piece; without, that pair is not formed.
"""

from __future__ import annotations

__all__ = [
    "FRAME_DIM",
    "FrameMemory",
    "SourceFrames",
    "build_source_frames",
    "inject",
    "reinitialise",
]

from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.schedule import Schedule
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.types import Sequence

FRAME_DIM = 6  # [t_o (3), phi_o (3)] per source


@dataclass
class SourceFrames:
    """Absolute source poses at the schedule's pair ends, and the offsets' process noise.

    Attributes:
        names: the S fused sources (``Schedule.source_names`` order).
        position: (B, E, S, 3) measured position ``z_p``, m (0 where absent).
        rotation: (B, E, S, 3, 3) measured rotation ``R_z`` (I where absent).
        covariance: (B, E, S, 6, 6) declared covariance ``C`` (I where absent).
        reset: (B, E, S) bool, the offset is (re-)initialised from this sample.
        drift_variance: (S, 6) offset variance per metre travelled ``[q_p^2] * 3 +
            [q_theta^2] * 3``.
    """

    names: tuple[str, ...]
    position: torch.Tensor
    rotation: torch.Tensor
    covariance: torch.Tensor
    reset: torch.Tensor
    drift_variance: torch.Tensor

    @property
    def size(self) -> int:
        """6 S, the number of offset error states."""
        return FRAME_DIM * len(self.names)

    def process_noise(self, scale: torch.Tensor, distance: torch.Tensor) -> torch.Tensor:
        """(B, 6 S, 6 S) diagonal random-walk covariance over an epoch.

        Args:
            scale: (B, S) each source's variance scale.
            distance: (B,) distance travelled in the epoch, m.
        """
        var = scale[:, :, None] * self.drift_variance * distance[:, None, None]
        return torch.diag_embed(var.flatten(1))


@dataclass
class FrameMemory:
    """The source frames at the last epoch of a chunk, for the next chunk's ``run_eskf``.

    Attributes:
        names: the S sources, in the order of the other fields.
        value: (B, S, 6) offsets ``[t_o (m), phi_o (rad)]``.
        covariance: (B, 15 + 6 S, 15 + 6 S) joint covariance of the conventional navigation
            error and the offset errors (calibration states left out).
        last_time: (B, S) stamp of each source's last used sample, s (-inf: none yet).
    """

    names: tuple[str, ...]
    value: torch.Tensor
    covariance: torch.Tensor
    last_time: torch.Tensor


def _drift_variance(cfg: EskfConfig, names: tuple[str, ...], dtype, device) -> torch.Tensor:
    """(S, 6) variance per metre of each source's offset (``pose_source_drift*``)."""
    rows = []
    for name in names:
        q_p, q_r = cfg.pose_source_drift.get(
            name,
            [
                cfg.pose_source_drift_position_m_per_sqrt_m,
                cfg.pose_source_drift_rotation_rad_per_sqrt_m,
            ],
        )
        rows.append([q_p**2] * 3 + [q_r**2] * 3)
    return torch.tensor(rows, dtype=dtype, device=device).reshape(len(names), FRAME_DIM)


def _pair_end_samples(seq: Sequence, sched: Schedule, tol: float) -> np.ndarray:
    """(B, E, S) index of the sample of each source that ends a pair at each epoch (0 where
    none): the valid sample stamped at the epoch end (preprocessing, one pass per sequence
    and source)."""
    mask = sched.source_mask.cpu().numpy()
    t_end = sched.t_end.detach().cpu().numpy()
    out = np.zeros(mask.shape, dtype=np.int64)
    for s, name in enumerate(sched.source_names):
        stream = seq.pose_sources[name]
        stamps = stream.t.detach().cpu().numpy()
        valid = stream.mask.cpu().numpy()
        for b in range(mask.shape[0]):
            epochs = np.nonzero(mask[b, :, s])[0]
            if epochs.size == 0:
                continue
            index = np.nonzero(valid[b])[0]
            times = stamps[b, index]
            pos = np.clip(np.searchsorted(times, t_end[b, epochs] - tol), 0, times.size - 1)
            if np.any(np.abs(times[pos] - t_end[b, epochs]) > tol):
                raise ValueError(f"pose source '{name}': a pair end has no sample at its time")
            out[b, epochs, s] = index[pos]
    return out


def _resets(
    sched: Schedule, tol: float, max_gap: float, last_time: torch.Tensor | None
) -> torch.Tensor:
    """(B, E, S) bool: a pair that does not start where the source's previous pair ended
    (its first pair, or the first after a gap); a chunk's first pair continues when it
    starts at most ``max_gap`` after ``last_time`` (B, S) of the previous chunk."""
    batch, n_epochs, n_sources = sched.source_mask.shape
    mask = sched.source_mask
    index = torch.arange(n_epochs, device=mask.device)[None, :, None].expand_as(mask)
    last = torch.where(mask, index, -1).cummax(1).values
    previous = torch.cat((torch.full_like(last[:, :1], -1), last[:, :-1]), 1)
    prev_end = sched.t_end.gather(1, previous.clamp_min(0).reshape(batch, -1)).reshape(
        batch, n_epochs, n_sources
    )
    start = sched.t_end[:, :, None] - sched.source_dt
    adjacent = (previous >= 0) & ((prev_end - start).abs() <= tol)
    if last_time is not None:
        carried = (start - last_time[:, None, :]) <= max_gap + tol
        adjacent = adjacent | ((previous < 0) & carried)
    return mask & ~adjacent


def build_source_frames(
    seq: Sequence, sched: Schedule, cfg: EskfConfig, memory: FrameMemory | None = None
) -> SourceFrames:
    """The absolute poses of the pair ends of ``sched`` (from the sanitised ``seq``), their
    resets and the sources' drift densities; see the module docstring. ``memory``: the
    previous chunk's frames (its sources must be ``sched.source_names``)."""
    if memory is not None and memory.names != sched.source_names:
        raise ValueError(
            f"frame_memory holds sources {memory.names}, the run fuses {sched.source_names}"
        )
    dtype, device = sched.t_end.dtype, sched.t_end.device
    tol = cfg.time_tolerance_s
    names = sched.source_names
    end = torch.as_tensor(_pair_end_samples(seq, sched, tol), device=device)
    rows = torch.arange(end.shape[0], device=device)[:, None]
    mask = sched.source_mask
    positions, rotations, covariances = [], [], []
    unit = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device)
    eye = torch.eye(6, dtype=dtype, device=device)
    for s, name in enumerate(names):
        stream = seq.pose_sources[name]
        here = mask[..., s]
        positions.append(torch.where(here[..., None], stream.position[rows, end[..., s]], 0.0))
        quat = torch.where(here[..., None], stream.quaternion[rows, end[..., s]], unit)
        rotations.append(quat_to_matrix(quat))
        covariances.append(
            torch.where(here[..., None, None], stream.covariance[rows, end[..., s]], eye)
        )
    batch, n_epochs = sched.t_end.shape

    def stack(parts: list[torch.Tensor], *shape: int) -> torch.Tensor:
        if parts:
            return torch.stack(parts, 2)
        return torch.zeros(batch, n_epochs, 0, *shape, dtype=dtype, device=device)

    return SourceFrames(
        names=names,
        position=stack(positions, 3),
        rotation=stack(rotations, 3, 3),
        covariance=stack(covariances, 6, 6),
        reset=_resets(
            sched, tol, cfg.pose_source_max_gap_s, None if memory is None else memory.last_time
        ),
        drift_variance=_drift_variance(cfg, names, dtype, device),
    )


def reinitialise(
    cov: torch.Tensor,
    body_jacobian: torch.Tensor,
    measurement_covariance: torch.Tensor,
    column: int,
    reset: torch.Tensor,
) -> torch.Tensor:
    """Covariance (B, N, N) with the offset block at ``column`` re-initialised where
    ``reset`` (B,): ``P_qq = H_x P H_x^T + R``, ``P_qx = -H_x P`` (module docstring).

    Args:
        cov: (B, N, N) the filter's covariance.
        body_jacobian: (B, 6, N) ``H_x``, the residual's Jacobian w.r.t. every state but
            this offset (its own columns zero), at the initialised offset.
        measurement_covariance: (B, 6, 6) ``R = s C`` of the sample.
        column: first of the offset's six columns.
        reset: (B,) bool.
    """
    rows = -body_jacobian @ cov
    block = slice(column, column + FRAME_DIM)
    fresh = cov.clone()
    fresh[:, block, :] = rows
    fresh[:, :, block] = rows.mT
    fresh[:, block, block] = body_jacobian @ cov @ body_jacobian.mT + measurement_covariance
    return torch.where(reset[:, None, None], fresh, cov)


def inject(values: torch.Tensor, correction: torch.Tensor) -> torch.Tensor:
    """Offsets (B, S, 6) after a correction (B, 6 S): translation added, rotation
    ``Log(Exp(phi) Exp(dphi))``."""
    step = correction.reshape(values.shape)
    rotation = so3.log(so3.exp(values[..., 3:]) @ so3.exp(step[..., 3:]))
    return torch.cat((values[..., :3] + step[..., :3], rotation), -1)
