"""Cut a batch of sequences into filter epochs: IMU samples between update times.

An *epoch* ends at an update time (a wheel, GNSS fix, GNSS velocity or pose measurement, the
later sample of a pose-source pair, or the last IMU sample; in a stretch without any, every
``max_epoch_s``, or every ``1 / nhc_rate_hz`` where the NHC or the IMU's ZUPT detector acts
at each epoch). The IMU timeline is split at every update time; each piece is held at the
value of the latest IMU sample at or before its start (zero-order hold), so a measurement
that falls between two IMU samples is fused at its own time with no interpolation error.
The result is a set of dense, padded ``(B, E, L)`` tensors: the filter then loops over E
only, and everything inside an epoch is vectorised (``sensors.imu.preintegrate``). Padding
has ``dt = 0``, an exact no-op.

Pose sources (``Sequence.pose_sources``, chosen by ``EskfConfig.pose_sources``) drift, so
they enter as odometry. Consecutive valid samples ``k - 1``, ``k`` of a source,
``0 < dt = t_k - t_k-1 <= pose_source_max_gap_s``, give the body-frame mean velocity over the
interval, fused at ``t_k``:

    z_v = R_m^T (p_k - p_k-1) / dt,    R_m = R_k-1 Exp(Log(R_k-1^T R_k) / 2),
    C_v = R_m^T (C_p,k + C_p,k-1) R_m / dt^2

with ``C_p`` the samples' declared (world-frame) position covariances. The chord of a
constant-rate turn points along the mid-interval heading, so ``R_m`` (not ``R_k-1``) removes
the first-order turn error; a constant drift of the source's frame cancels in the
difference. The filter adds the mean-versus-end-velocity term (``frontend.eskf``). The
relative rotation gives the mean body rate ``z_w = Log(dR) / dt``, ``dR = R_k-1^T R_k``, with
covariance ``(dR^T C_r,k-1 dR + C_r,k) / dt^2`` (``C_r`` the declared rotation blocks), to
compare with the mean raw gyro rate ``w_bar`` over the same interval (exact integral of the
zero-order-held samples). Pairs that start before the first IMU sample are not used, except
in a run filtered in chunks: a chunk hands each source's latest sample and the gyro integral
from it to the chunk's last IMU sample on to the next (:class:`PairMemory`,
``EskfResult.pair_memory``), whose schedule then forms the pair across the boundary with
``w_bar`` = (carried integral + integral from its first IMU sample to the pair end) / ``dt``,
as the run in one piece does.

Building the schedule is preprocessing with numpy (one pass per sequence, vectorised over
its samples); the hot path never loops over B.
"""

from __future__ import annotations

__all__ = [
    "UNMEASURED_SIGMA",
    "PairMemory",
    "Schedule",
    "bin_starts",
    "build_schedule",
    "corrected_magnetometer",
    "corrected_readings",
    "disturbed_field",
    "median_dip",
    "rotation_inconsistent",
    "undisturbed_magnetometer",
    "gap_lengths",
    "gyro_attitude",
    "source_names",
]

import math
from dataclasses import dataclass

import numpy as np
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.gating import chi2_threshold
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.sensors.imu_gaps import filled_stretches, interpolated_imu_samples
from msf_torch.sensors.magnetometer import corrected_field
from msf_torch.types import Magnetometer, PoseMeasurements, Sequence

UNMEASURED_SIGMA = 1e6
"""Sigma (m/s) of a GNSS velocity axis the receiver did not give (NaN up component): its row
stays in the update with a gain of order 1e-12 of the state's variance, i.e. unused."""

_MEASURED = (
    "wheel",
    "gnss",
    "gnss_velocity",
    "gnss_heading",
    "magnetometer",
    "pose",
)  # streams matched to epoch ends


@dataclass
class PairMemory:
    """What the pose-source pairs of a chunk hand on to the next chunk's schedule
    (``build_schedule(..., pair_memory=...)``, ``run_eskf(..., pair_memory=...)``), so that
    the pair across the boundary is fused and the time-offset calibration sees its
    predecessor, as in the run in one piece. It depends on the data only (not on the
    filter): it describes the whole chunk.

    Attributes:
        names: the S sources (``Schedule.source_names`` order).
        start_time: (B, S) stamp of each source's latest valid sample at or before the
            chunk's last IMU sample (the start of the next pair), s (-inf: none).
        gyro_integral: (B, S, 3) integral of the zero-order-held raw gyro from
            ``start_time`` to the chunk's last IMU sample, rad (0 where none).
        pair_end: (B, S) end time of each source's latest pair so far, s (-inf: none).
        pair_gyro_mean: (B, S, 3) that pair's mean raw gyro rate ``w_bar``, rad/s.
        pair_dt: (B, S) its interval, s (0 where none).
    """

    names: tuple[str, ...]
    start_time: torch.Tensor
    gyro_integral: torch.Tensor
    pair_end: torch.Tensor
    pair_gyro_mean: torch.Tensor
    pair_dt: torch.Tensor


@dataclass
class Schedule:
    """Padded per-epoch tensors for a batch (B sequences, E epochs, L samples per epoch).

    Attributes:
        t_start: (B,) filter start time (first IMU sample), s.
        t_end: (B, E) epoch end times, s.
        epoch_mask: (B, E) bool, real epochs.
        sample_index: (B, E, L) index of each piece's held IMU sample into ``imu_gyro`` /
            ``imu_accel`` (padding: the sequence's first sample); :meth:`held_imu` gathers
            the (B, E, L, 3) ZOH values of a range of epochs.
        imu_gyro, imu_accel: (B N, 3) the batch's raw IMU samples, flattened (views).
        dt: (B, E, L) piece durations, s (0 = padding).
        noise_scale: (B, E, L) IMU variance multipliers (gaps).
        gap_length: (B, E, L) length of the IMU gap a piece is held over (or the filled-in
            stretch it lies in, see :func:`gap_lengths`), s; 0 outside gaps.
        gap: (B, E) bool, the epoch contains an IMU gap.
        gyro_end: (B, E, 3) raw gyro held at the epoch end (for lever-arm terms).
        wheel_left, wheel_right: (B, E) rim speeds, m/s; wheel_mask (B, E).
        gnss_position: (B, E, 3) m; gnss_sigma (B, E, 3) m (config default filled in);
            gnss_mask (B, E).
        gnss_velocity: (B, E, 3) antenna velocity east, north, up, m/s (0 where an axis is
            not measured); gnss_velocity_sigma (B, E, 3) m/s (config default filled in;
            :data:`UNMEASURED_SIGMA` on an axis the receiver did not give); gnss_velocity_mask
            (B, E).
        gnss_heading: (B, E) dual-antenna baseline azimuth clockwise from north, rad (0
            where absent); gnss_heading_sigma (B, E) rad (config default filled in);
            gnss_heading_mask (B, E).
        magnetometer_field: (B, E, 3) hard- and soft-iron corrected field in the body
            frame, uT (0 where absent); magnetometer_sigma (B, E) its per-axis noise, uT
            (the config's default, carried through the soft-iron matrix, filled in);
            magnetometer_mask (B, E). Fused readings: at most ``magnetometer_rate_hz`` per
            second (the undisturbed readings that open a ``1 / rate`` bin of the clock,
            :func:`bin_starts`),
            none whose corrected magnitude departs from the local field's by more than
            ``magnetometer_field_tolerance`` (:func:`disturbed_field`).
        magnetometer_dip: (B,) the local field's inclination (dip below the horizon), rad:
            ``magnetometer_inclination_rad``, or where that is 0 the run's median angle
            between the corrected field and the accelerometer (:func:`median_dip`).
        pose_position (B, E, 3), pose_rotation (B, E, 3, 3), pose_covariance (B, E, 6, 6),
            pose_mask (B, E).
        source_names: the S fused pose sources, in this order along the S axes below.
        source_velocity: (B, E, S, 3) body-frame mean velocity ``z_v``, m/s (0 where absent).
        source_covariance: (B, E, S, 3, 3) declared part ``C_v``, m^2/s^2 (I where absent).
        source_rate: (B, E, S, 3) mean body rate ``z_w``, rad/s (0 where absent).
        source_rate_covariance: (B, E, S, 3, 3) its declared covariance, rad^2/s^2 (I where
            absent).
        source_gyro_mean: (B, E, S, 3) mean raw gyro rate ``w_bar`` over the pair, rad/s.
        source_dt: (B, E, S) pair interval ``dt``, s (0 where absent).
        source_mask: (B, E, S) bool, a pair of the source ends at the epoch.
        nhc_mask, zupt_mask: (B, E) bool pseudo-measurements. With the NHC on, every epoch
            carries it, and epochs are added where updates are further apart than
            ``1 / nhc_rate_hz``.
        imu_index_end: (B, E) index of the IMU sample held at each epoch end.
        pair_memory: the sources' pairs after the last IMU sample, for a next chunk (None
            without pose sources).
    """

    t_start: torch.Tensor
    t_end: torch.Tensor
    epoch_mask: torch.Tensor
    sample_index: torch.Tensor
    imu_gyro: torch.Tensor
    imu_accel: torch.Tensor
    dt: torch.Tensor
    noise_scale: torch.Tensor
    gap_length: torch.Tensor
    gap: torch.Tensor
    gyro_end: torch.Tensor
    wheel_left: torch.Tensor
    wheel_right: torch.Tensor
    wheel_mask: torch.Tensor
    gnss_position: torch.Tensor
    gnss_sigma: torch.Tensor
    gnss_mask: torch.Tensor
    gnss_velocity: torch.Tensor
    gnss_velocity_sigma: torch.Tensor
    gnss_velocity_mask: torch.Tensor
    gnss_heading: torch.Tensor
    gnss_heading_sigma: torch.Tensor
    gnss_heading_mask: torch.Tensor
    magnetometer_field: torch.Tensor
    magnetometer_sigma: torch.Tensor
    magnetometer_mask: torch.Tensor
    magnetometer_dip: torch.Tensor
    pose_position: torch.Tensor
    pose_rotation: torch.Tensor
    pose_covariance: torch.Tensor
    pose_mask: torch.Tensor
    nhc_mask: torch.Tensor
    zupt_mask: torch.Tensor
    imu_index_end: torch.Tensor
    source_names: tuple[str, ...]
    source_velocity: torch.Tensor
    source_covariance: torch.Tensor
    source_rate: torch.Tensor
    source_rate_covariance: torch.Tensor
    source_gyro_mean: torch.Tensor
    source_dt: torch.Tensor
    source_mask: torch.Tensor
    pair_memory: PairMemory | None = None

    @property
    def num_epochs(self) -> int:
        """E."""
        return self.t_end.shape[1]

    def held_imu(self, epochs: slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor]:
        """ZOH gyro (rad/s) and accelerometer (m/s^2) values (B, e, L, 3) of the pieces of
        ``epochs``, gathered on demand: a consumer that works through the epochs in chunks
        never holds all (B, E, L, 3) of them (at B = 32 on the KITTI drive, 37 MB each)."""
        index = self.sample_index[:, epochs]
        flat = index.reshape(-1)
        shape = (*index.shape, 3)
        return (
            self.imu_gyro.index_select(0, flat).reshape(shape),
            self.imu_accel.index_select(0, flat).reshape(shape),
        )


def _merge_times(times: np.ndarray, tol: float) -> np.ndarray:
    """Sorted unique times, merging values closer than ``tol`` (first kept)."""
    if times.size == 0:
        return times
    times = np.sort(times, kind="stable")  # timsort: linear on a few concatenated sorted runs
    keep = np.concatenate(([True], np.diff(times) > tol))
    return times[keep]


def gap_lengths(t: np.ndarray, spacing: np.ndarray, filled: np.ndarray, gap_s: float) -> np.ndarray:
    """Per IMU sample, the length (s) of the gap it is held over or filled in, 0 for a
    measured sample. ``t``, ``spacing`` (time to the next sample, s) and ``filled``
    (:func:`~msf_torch.sensors.imu_gaps.interpolated_imu_samples`) are (T,); a spacing
    above ``gap_s`` is a gap. A filled-in stretch's length runs from the real sample before
    it to the one after it."""
    length = np.where(spacing > gap_s, spacing, 0.0)
    for first, end in zip(*filled_stretches(filled), strict=True):
        stretch = t[min(end, t.size - 1)] - t[max(first - 1, 0)]
        length[first:end] = np.maximum(length[first:end], stretch)
    return length


def _fill_gaps(times: np.ndarray, max_step: float) -> np.ndarray:
    """Insert evenly spaced times wherever consecutive ``times`` are over ``max_step`` apart."""
    gaps = np.diff(times)
    pieces = np.maximum(np.ceil(gaps / max_step - 1e-9).astype(np.int64), 1)
    starts = np.repeat(times[:-1], pieces)
    frac = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces) + 1
    filled = starts + np.repeat(gaps / pieces, pieces) * frac
    return np.concatenate((times[:1], filled))


def disturbed_field(
    field: np.ndarray, cfg: EskfConfig, reference: np.ndarray | None = None
) -> np.ndarray:
    """Readings whose hard- and soft-iron corrected magnitude departs from the local field's
    by more than ``cfg.magnetometer_field_tolerance`` (relative): near steel, motors or
    currents the field is not the earth's, and its direction says nothing of the heading.

    Args:
        field: (N, 3) raw readings, uT.
        cfg: the hard and soft iron, the local field magnitude ``magnetometer_field_uT``
            (0: the median corrected magnitude of ``reference``) and the tolerance.
        reference: (M, 3) raw readings the median is taken over (default ``field``).

    Returns:
        (N,) bool, True where disturbed; also where the corrected field is zero (a sensor
        that reads zeros gives no direction) or not finite.
    """
    norm = np.linalg.norm(corrected_readings(field, cfg)[0], axis=-1)
    local = cfg.magnetometer_field_uT
    if local == 0.0:
        ref = norm
        if reference is not None:
            ref = np.linalg.norm(corrected_readings(reference, cfg)[0], axis=-1)
        ref = ref[np.isfinite(ref)]
        local = float(np.median(ref)) if ref.size else 0.0
    within = np.abs(norm - local) <= cfg.magnetometer_field_tolerance * local
    return ~(within & (norm > 0.0))


def median_dip(field: np.ndarray, accel: np.ndarray, cfg: EskfConfig) -> float:
    """The local field's inclination from a run: the median over readings of the field's
    angle below the plane normal to the accelerometer (the accelerometer reads ``+g`` up
    at rest; its motion part averages out of the median on a ground vehicle).

    Args:
        field: (M, 3) raw readings, uT; accel: (M, 3) the accelerometer at their times,
            m/s^2.
        cfg: the hard and soft iron.

    Returns:
        The dip, rad (positive: the field points below the horizon).
    """
    corrected = corrected_readings(field, cfg)[0]
    cosine = (corrected * accel).sum(-1) / (
        np.linalg.norm(corrected, axis=-1) * np.linalg.norm(accel, axis=-1)
    ).clip(1e-300)
    return float(np.median(-np.arcsin(np.clip(cosine, -1.0, 1.0))))


def undisturbed_magnetometer(
    stream: Magnetometer,
    b: int,
    cfg: EskfConfig,
    imu_t: np.ndarray,
    gyro: np.ndarray,
    times: np.ndarray,
    index: np.ndarray,
    refuse_unjudged: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """The undisturbed magnetometer readings of sequence ``b`` among ``times`` (s) /
    ``index`` (into the stream): in magnitude (:func:`disturbed_field`, the median over
    all the sequence's readings) and turning with the gyro (:func:`rotation_inconsistent`;
    ``refuse_unjudged``: also leave out the readings it cannot judge).

    Args:
        stream: the ``Magnetometer`` stream (B, N).
        b: the sequence.
        cfg: the filter's config.
        imu_t: (N_imu,) IMU times, s; gyro: (N_imu, 3) bias-corrected rates, rad/s.
        times: (M,) candidate reading times, s (sorted); index: (M,) their indices.

    Returns:
        (times, index) of the readings kept.
    """
    if times.size == 0:
        return times, index
    valid = _np(stream.mask[b])
    field = _np(stream.field[b])
    keep = ~disturbed_field(field[index], cfg, field[valid])
    times, index = times[keep], index[keep]
    if cfg.magnetometer_consistency_s > 0 and times.size:
        sigma = _np(stream.sigma[b])[index]
        upto = np.searchsorted(imu_t, times[-1], side="right") + 1  # the samples needed
        keep = ~rotation_inconsistent(
            times,
            field[index],
            sigma,
            gyro_attitude(imu_t[:upto], gyro[:upto], times),
            cfg,
            refuse_unjudged,
        )
        times, index = times[keep], index[keep]
    return times, index


def bin_starts(times: np.ndarray, stream_times: np.ndarray, cfg: EskfConfig) -> np.ndarray:
    """The readings that open a ``1 / magnetometer_rate_hz`` bin of the clock: those less
    than one reading interval (the stream's median, times 0.999 against round-off) after the
    bin's start. The rule needs no neighbouring reading, so a run filtered in pieces or
    chunks, whatever their bounds, fuses the same readings as in one piece; a bin whose
    opening reading was left out as disturbed fuses none.

    Args:
        times: (M,) candidate reading times, s; stream_times: (N,) all the stream's reading
            times, s (their median interval; with fewer than two, every candidate opens a
            bin).
        cfg: ``magnetometer_rate_hz``.

    Returns:
        (M,) bool.
    """
    rate = cfg.magnetometer_rate_hz
    if stream_times.size < 2:
        return np.ones(times.shape, dtype=bool)
    interval = float(np.median(np.diff(np.sort(stream_times))))
    phase = times * rate - np.floor(times * rate)
    return phase < 0.999 * interval * rate


CONSISTENCY_LAGS = (1.0 / 6.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
"""Lags of :func:`rotation_inconsistent`, as fractions of ``magnetometer_consistency_s``."""


def rotation_inconsistent(
    times: np.ndarray,
    field: np.ndarray,
    sigma: np.ndarray,
    attitude: np.ndarray,
    cfg: EskfConfig,
    refuse_unjudged: bool = True,
) -> np.ndarray:
    """Readings whose change from earlier readings is not the body's turn: the earth's field
    is fixed in the world, so between readings ``j`` and ``k`` the body-frame field turns
    by the gyro's rotation, ``f_k = (G_j^T G_k)^T f_j`` (``G`` from :func:`gyro_attitude`); a
    local disturbance (driving past steel, a motor switching on) changes it otherwise, and no
    attitude is needed to see it.

    Each reading is compared with the latest reading at least ``lag`` earlier, for each lag
    of :data:`CONSISTENCY_LAGS` times ``magnetometer_consistency_s`` (a disturbance's
    plateau is still compared with a reading from before it); it is inconsistent when, for
    any lag, ``|f_k - G_k^T G_j f_j|`` exceeds the gate's chi-square (3 dof,
    ``gate_probability``) bound on the two readings' noise plus the gyro bias prior's
    turn over the interval (``init_gyro_bias_sigma_radps`` times the interval times
    ``|f_j|``). The relative rotation is the product of the held samples' exponentials, not
    the difference of the gyro's integral as a rotation vector: that is exact only for turns
    about one body axis, and a vehicle turning at 1 rad/s over 8-degree terrain then has a
    third of its clean readings flagged. A reading with no reading at least the shortest
    lag before it in the sequence cannot be judged and counts as inconsistent with
    ``refuse_unjudged`` (the run's first readings: a run that starts beside steel would
    otherwise set its heading from the disturbance; a chunk or piece that continues a run
    passes them on, :func:`build_schedule`'s ``continuing``).

    Args:
        times: (M,) s; field: (M, 3) raw readings, uT (corrected here with the config's
            hard and soft iron); sigma: (M,) per-axis noise, uT.
        attitude: (M, 3, 3) the body's rotation at each reading relative to the run's
            start from the gyro alone (:func:`gyro_attitude`).
        cfg: hard and soft iron, ``magnetometer_consistency_s``, the gate probability and
            the gyro bias prior.

    Returns:
        (M,) bool, True where inconsistent (or not judged, with ``refuse_unjudged``).
    """
    corrected, sigma = corrected_readings(field, cfg, sigma)
    bound = math.sqrt(chi2_threshold(3, cfg.gate_probability))
    bias = float(np.linalg.norm(cfg.init_gyro_bias_sigma_radps))
    inconsistent = np.zeros(times.size, dtype=bool)
    judged_once = np.zeros(times.size, dtype=bool)
    for fraction in CONSISTENCY_LAGS:
        j = np.searchsorted(times, times - fraction * cfg.magnetometer_consistency_s, "right") - 1
        judged = j >= 0
        judged_once |= judged
        k = np.flatnonzero(judged)
        j = j[judged]
        turned = np.einsum("nim,nm,nik->nk", attitude[j], corrected[j], attitude[k])
        change = np.linalg.norm(corrected[k] - turned, axis=-1)
        noise = bound * np.hypot(sigma[k], sigma[j])
        drift = bias * (times[k] - times[j]) * np.linalg.norm(corrected[j], axis=-1)
        inconsistent[k] |= change > noise + drift
    return inconsistent | (~judged_once if refuse_unjudged else False)


def gyro_attitude(imu_t: np.ndarray, gyro: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The body's rotation (P, 3, 3) at each time ``t`` (P,) s relative to the first IMU
    sample, from the zero-order-held gyro alone: ``G(t) = Exp(w_0 dt_0) ... Exp(w_i (t - t_i))``
    (``G_j^T G_k`` turns body vectors at ``t_k`` into the body frame at ``t_j``).

    Args:
        imu_t: (N,) IMU times, s; gyro: (N, 3) rates, rad/s (bias taken out by the caller).
        t: (P,) times, s (clipped to the first sample before ``imu_t[0]``).
    """
    step = so3.exp(torch.from_numpy(gyro[:-1] * np.diff(imu_t)[:, None])).numpy()
    product = np.concatenate((np.eye(3)[None], step))
    span = 1
    while span < product.shape[0]:  # inclusive prefix products, log2(N) passes
        product[span:] = product[:-span] @ product[span:]
        span *= 2
    i = np.clip(np.searchsorted(imu_t, t, side="right") - 1, 0, imu_t.size - 1)
    rest = so3.exp(torch.from_numpy(gyro[i] * np.maximum(t - imu_t[i], 0.0)[:, None])).numpy()
    return product[i] @ rest


def corrected_readings(
    field: np.ndarray, cfg: EskfConfig, sigma: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`corrected_magnetometer` of numpy readings (..., 3) uT and their sigmas (...,)
    uT (None: the config's default): the corrected field and its per-axis sigma."""
    raw = torch.from_numpy(np.asarray(field, dtype=np.float64))
    noise = torch.full(raw.shape[:-1], torch.nan, dtype=raw.dtype)
    if sigma is not None:
        noise = torch.from_numpy(np.asarray(sigma, dtype=np.float64))
    corrected, noise = corrected_magnetometer(raw, noise, cfg)
    return corrected.numpy(), noise.numpy()


def corrected_magnetometer(
    raw: torch.Tensor, sigma: torch.Tensor, cfg: EskfConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """The config's hard- and soft-iron correction ``W (m - b)``
    (:func:`msf_torch.sensors.magnetometer.corrected_field`) of raw readings (..., 3) uT,
    and their per-axis sigma (...,) uT: the reading's (the config's default where NaN or not
    above 0) times ``sqrt(trace(W W^T) / 3)``."""
    hard = torch.as_tensor(cfg.magnetometer_hard_iron_uT, dtype=raw.dtype, device=raw.device)
    soft = torch.as_tensor(cfg.magnetometer_soft_iron, dtype=raw.dtype, device=raw.device)
    soft = soft.reshape(3, 3)
    sigma = torch.where(
        torch.isfinite(sigma) & (sigma > 0), sigma, cfg.magnetometer_sigma_uT
    ) * torch.sqrt((soft**2).sum() / 3)
    return corrected_field(raw, hard, soft), sigma


def _match(times: np.ndarray, targets: np.ndarray, tol: float) -> np.ndarray:
    """Index into ``times`` of each target within ``tol``, else -1. ``times`` sorted."""
    if times.size == 0:
        return np.full(targets.shape, -1, dtype=np.int64)
    idx = (
        np.clip(np.searchsorted(times, targets), 1, times.size - 1)
        if times.size > 1
        else (np.zeros(targets.shape, dtype=np.int64))
    )
    best = idx.copy()
    if times.size > 1:
        left = idx - 1
        closer_left = np.abs(times[left] - targets) <= np.abs(times[idx] - targets)
        best = np.where(closer_left, left, idx)
    ok = np.abs(times[best] - targets) <= tol
    return np.where(ok, best, -1)


def _stationary_imu(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, targets: np.ndarray, cfg: EskfConfig
) -> np.ndarray:
    """IMU stationarity test over the window ending at each target time (vectorised)."""
    acc_norm = np.linalg.norm(accel, axis=1)
    gyro_norm = np.linalg.norm(gyro, axis=1)
    c1 = np.concatenate(([0.0], np.cumsum(acc_norm)))
    c2 = np.concatenate(([0.0], np.cumsum(acc_norm**2)))
    cg = np.concatenate(([0.0], np.cumsum(gyro_norm)))
    hi = np.searchsorted(t, targets, side="right")
    lo = np.searchsorted(t, targets - cfg.zupt_window_s, side="left")
    count = np.maximum(hi - lo, 1)
    mean = (c1[hi] - c1[lo]) / count
    var = np.maximum((c2[hi] - c2[lo]) / count - mean**2, 0.0)
    gyro_mean = (cg[hi] - cg[lo]) / count
    enough = (hi - lo) >= 5
    return enough & (np.sqrt(var) < cfg.zupt_accel_std_mps2) & (gyro_mean < cfg.zupt_gyro_radps)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy()


def source_names(seq: Sequence, cfg: EskfConfig) -> tuple[str, ...]:
    """The pose sources to fuse: all of ``seq.pose_sources`` (sorted) for ``"auto"``, else
    ``cfg.pose_sources`` in its order.

    Raises:
        ValueError: a configured name is not a source of the sequence (names the key).
    """
    if cfg.pose_sources == "auto":
        return tuple(sorted(seq.pose_sources))
    missing = [n for n in cfg.pose_sources if n not in seq.pose_sources]
    if missing:
        raise ValueError(
            f"config key 'pose_sources' names {missing}, not in the sequence's pose sources "
            f"{sorted(seq.pose_sources)}"
        )
    return tuple(cfg.pose_sources)


def _source_pairs(
    stream: PoseMeasurements,
    b: int,
    t0: float,
    t_last: float,
    cfg: EskfConfig,
    carried_start: float = -np.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive valid sample pairs of a pose source in sequence ``b`` inside
    ``[t0, t_last]``, and the pair that starts at ``carried_start`` (s, a previous chunk's
    :attr:`PairMemory.start_time`) and ends there: end times (P,) s, start times (P,) s and
    the sample indices of the pair ends and starts (P,)."""
    tol = cfg.time_tolerance_s
    valid = np.nonzero(_np(stream.mask[b]))[0]
    t = _np(stream.t[b])[valid]
    gap = np.diff(t)
    ok = (gap > tol) & (gap <= cfg.pose_source_max_gap_s) & (t[1:] <= t_last + tol)
    ok &= (t[:-1] >= t0 - tol) | (np.abs(t[:-1] - carried_start) <= tol)
    return t[1:][ok], t[:-1][ok], valid[1:][ok], valid[:-1][ok]


def _pair_memory_row(
    stream: PoseMeasurements,
    b: int,
    t0: float,
    t_last: float,
    tol: float,
    imu_t: np.ndarray,
    gyro: np.ndarray,
    pairs: tuple[np.ndarray, ...],
    gyro_mean: np.ndarray,
    carried: tuple[np.ndarray, ...] | None,
) -> tuple[np.ndarray, ...]:
    """One source's :class:`PairMemory` entries for sequence ``b`` after ``t_last``:
    ``(start_time, gyro_integral (3,), pair_end, pair_gyro_mean (3,), pair_dt)``.

    Args:
        imu_t, gyro: (N,) s and (N, 3) rad/s, the sequence's IMU samples in use.
        pairs: the chunk's pairs (:func:`_source_pairs`), gyro_mean (P, 3) their ``w_bar``.
        carried: the previous chunk's entries (same order), or None.
    """
    stamps = _np(stream.t[b])[_np(stream.mask[b])]
    latest = np.searchsorted(stamps, t_last + tol, side="right") - 1
    start, integral = -np.inf, np.zeros(3)
    if latest >= 0 and stamps[latest] >= t0 - tol:  # a sample of this chunk
        start = stamps[latest]
        ends = _gyro_integral(imu_t, gyro, np.array([start, t_last]))
        integral = ends[1] - ends[0]
    elif latest >= 0 and carried is not None and abs(stamps[latest] - carried[0]) <= tol:
        # still an earlier chunk's sample: its integral runs on over this chunk
        start = carried[0]
        integral = carried[1] + _gyro_integral(imu_t, gyro, np.array([t_last]))[0]
    if pairs[0].size:
        last = (pairs[0][-1], gyro_mean[-1], pairs[0][-1] - pairs[1][-1])
    elif carried is not None:
        last = carried[2:]
    else:
        last = (-np.inf, np.zeros(3), 0.0)
    return (start, integral, *last)


def _gyro_integral(imu_t: np.ndarray, gyro: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Integral (P, 3) rad of the zero-order-held gyro from ``imu_t[0]`` to each ``t`` (P,)."""
    cum = np.concatenate((np.zeros((1, 3)), np.cumsum(gyro[:-1] * np.diff(imu_t)[:, None], 0)))
    i = np.clip(np.searchsorted(imu_t, t, side="right") - 1, 0, imu_t.size - 1)
    return cum[i] + gyro[i] * (t - imu_t[i])[:, None]


def _source_velocities(
    stream: PoseMeasurements,
    rows: torch.Tensor,
    end: torch.Tensor,
    start: torch.Tensor,
    mask: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """Mean body velocity (B, E, 3) and rate (B, E, 3), their declared covariances
    (B, E, 3, 3) each, and ``dt`` (B, E) of the pairs ``(start, end)`` (sample indices,
    (B, E)) where ``mask`` (B, E)."""
    if stream.length == 0:  # no samples, so no pairs: one zero sample keeps the indexing valid
        stream = stream.map(
            lambda x: torch.zeros(x.shape[0], 1, *x.shape[2:], dtype=x.dtype, device=x.device)
        )
    f64 = dict(dtype=stream.position.dtype, device=stream.position.device)
    unit = torch.tensor([1.0, 0.0, 0.0, 0.0], **f64)
    m3 = mask[..., None]
    rot_end = quat_to_matrix(
        torch.where(m3.expand(*mask.shape, 4), stream.quaternion[rows, end], unit)
    )
    rot_start = quat_to_matrix(
        torch.where(m3.expand(*mask.shape, 4), stream.quaternion[rows, start], unit)
    )
    turn = rot_start.mT @ rot_end
    angle = so3.log(turn)
    rot_mid = rot_start @ so3.exp(0.5 * angle)
    dt = torch.where(mask, stream.t[rows, end] - stream.t[rows, start], 1.0)
    step = torch.where(m3, stream.position[rows, end] - stream.position[rows, start], 0.0)
    velocity = (rot_mid.mT @ step[..., None]).squeeze(-1) / dt[..., None]
    pos_cov = (stream.covariance[rows, end] + stream.covariance[rows, start])[..., :3, :3]
    cov = rot_mid.mT @ pos_cov @ rot_mid / (dt * dt)[..., None, None]
    rate_cov = turn.mT @ stream.covariance[rows, start][..., 3:, 3:] @ turn
    rate_cov = (rate_cov + stream.covariance[rows, end][..., 3:, 3:]) / (dt * dt)[..., None, None]
    eye = torch.eye(3, **f64)
    keep = mask[..., None, None]
    return (
        velocity,
        torch.where(keep, cov, eye),
        angle / dt[..., None],
        torch.where(keep, rate_cov, eye),
        torch.where(mask, dt, 0.0),
    )


def build_schedule(
    seq: Sequence,
    cfg: EskfConfig,
    pair_memory: PairMemory | None = None,
    continuing: bool = False,
) -> Schedule:
    """Build the padded epoch schedule of a batch.

    Args:
        seq: batch of B sequences (masks mark real samples).
        cfg: front-end configuration (tolerances, NHC rate, gap threshold, ZUPT tests).
        pair_memory: the previous chunk's ``Schedule.pair_memory`` when a run is filtered in
            chunks (each chunk's first IMU sample the previous chunk's last): each source's
            pair across the boundary is formed (module docstring).
        continuing: the batch continues a run filtered in chunks or pieces (``run_eskf``
            with a ``gate_memory``): magnetometer readings the gyro test cannot judge (no
            reading early enough in this chunk) go on to the dip test and the gate instead
            of being left out, since the state no longer rests on them (a live stream of
            short pieces would otherwise never fuse one).
    Returns:
        :class:`Schedule` on the IMU tensors' device and dtype.

    Raises:
        ValueError: fewer than two IMU samples in a sequence; a configured pose source the
            sequence lacks; ``pair_memory`` of other sources.
    """
    tol = cfg.time_tolerance_s
    dtype, device = seq.imu.t.dtype, seq.imu.t.device
    names = source_names(seq, cfg)
    carried_all = None  # the memory's (B, S, ...) numpy arrays
    if pair_memory is not None:
        if tuple(pair_memory.names) != names:
            raise ValueError(
                f"pair_memory holds sources {list(pair_memory.names)}, the run fuses {list(names)}"
            )
        carried_all = [
            _np(x)
            for x in (
                pair_memory.start_time,
                pair_memory.gyro_integral,
                pair_memory.pair_end,
                pair_memory.pair_gyro_mean,
                pair_memory.pair_dt,
            )
        ]
    per_seq = []
    for b in range(seq.batch_size):
        imu_mask = _np(seq.imu.mask[b])
        imu_t = _np(seq.imu.t[b])[imu_mask]
        if imu_t.size < 2:
            raise ValueError(f"sequence '{seq.names[b]}' has {imu_t.size} IMU samples; need >= 2")
        imu_sel = np.nonzero(imu_mask)[0]
        t0, t_last = imu_t[0], imu_t[-1]

        def stream_times(stream, b=b, t0=t0, t_last=t_last):
            if stream is None:
                return np.zeros(0), np.zeros(0, dtype=np.int64)
            m = _np(stream.mask[b])
            t = _np(stream.t[b])
            keep = m & (t > t0 + tol) & (t <= t_last + tol)
            return t[keep], np.nonzero(keep)[0]

        wheel_t, wheel_src = stream_times(seq.wheel)
        gnss_t, gnss_src = stream_times(seq.gnss)
        gvel_t, gvel_src = stream_times(seq.gnss_velocity)
        head_t, head_src = stream_times(seq.gnss_heading)
        # undisturbed readings that open a 1 / magnetometer_rate_hz bin of the clock
        mag_t, mag_src = undisturbed_magnetometer(
            seq.magnetometer,
            b,
            cfg,
            imu_t,
            _np(seq.imu.gyro[b])[imu_sel] - np.asarray(cfg.init_gyro_bias_radps),
            *stream_times(seq.magnetometer),
            refuse_unjudged=not continuing,
        )
        if mag_t.size:
            at_bin_start = bin_starts(
                mag_t, _np(seq.magnetometer.t[b])[_np(seq.magnetometer.mask[b])], cfg
            )
            mag_t, mag_src = mag_t[at_bin_start], mag_src[at_bin_start]
        mag_dip = cfg.magnetometer_inclination_rad
        if mag_t.size and mag_dip == 0.0:
            mag_dip = median_dip(
                _np(seq.magnetometer.field[b])[mag_src],
                _np(seq.imu.accel[b])[imu_sel][np.searchsorted(imu_t, mag_t + tol) - 1],
                cfg,
            )
        pose_t, pose_src = stream_times(seq.poses)
        carried = [
            None if carried_all is None else tuple(x[b, s] for x in carried_all)
            for s in range(len(names))
        ]
        pairs = [
            _source_pairs(seq.pose_sources[n], b, t0, t_last, cfg, -np.inf if c is None else c[0])
            for n, c in zip(names, carried, strict=True)
        ]
        # the gyro and accelerometer values (N, 3) are read only where a step needs them
        gyro = _np(seq.imu.gyro[b])[imu_sel] if pairs or cfg.zupt else None
        accel = _np(seq.imu.accel[b])[imu_sel] if cfg.zupt else None
        use_nhc = cfg.nhc == "on" or (cfg.nhc == "auto" and wheel_t.size == 0)
        updates = _merge_times(
            np.concatenate(
                (wheel_t, gnss_t, gvel_t, head_t, mag_t, pose_t, *[p[0] for p in pairs], [t_last])
            ),
            tol,
        )
        # epochs at least every 1 / nhc_rate_hz where the pseudo-measurements act at each,
        # else every max_epoch_s (an output sample and a propagation step, no update)
        if use_nhc or (cfg.zupt_imu_detector and wheel_t.size == 0):
            updates = _fill_gaps(np.concatenate(([t0], updates)), 1.0 / cfg.nhc_rate_hz)[1:]
        else:  # not inside an IMU dropout: that stays one epoch, flagged as a gap
            filled = _fill_gaps(np.concatenate(([t0], updates)), cfg.max_epoch_s)[1:]
            dropout = np.flatnonzero(np.diff(imu_t) > cfg.imu_gap_s)
            held = np.searchsorted(imu_t, filled, side="right") - 1
            inside = np.isin(held, dropout) & ~np.isin(filled, updates)
            updates = filled[~inside]
        bounds = _merge_times(np.concatenate((imu_t, updates)), tol)
        piece_start = bounds[:-1]
        piece_dt = np.diff(bounds)
        sample = np.searchsorted(imu_t, piece_start + tol, side="right") - 1
        epoch = np.searchsorted(updates, piece_start + tol, side="right")
        first = np.searchsorted(epoch, np.arange(updates.size), side="left")
        slot = np.arange(piece_start.size) - first[epoch]
        spacing = np.diff(imu_t, append=imu_t[-1])
        # the samples in use are usually one block (padding at the end): read them as views
        block = imu_sel[-1] - imu_sel[0] + 1 == imu_sel.size
        rows = slice(imu_sel[0], imu_sel[-1] + 1) if block else imu_sel
        filled = interpolated_imu_samples(
            imu_t,
            _np(seq.imu.gyro[b])[rows],
            _np(seq.imu.accel[b])[rows],
            cfg.imu_interpolated_min_samples,
        )
        gap_piece = (spacing[sample] > cfg.imu_gap_s) | filled[sample]
        gap_length = gap_lengths(imu_t, spacing, filled, cfg.imu_gap_s)[sample]
        end_sample = np.searchsorted(imu_t, updates + tol, side="right") - 1
        end_sample = np.clip(end_sample, 0, imu_t.size - 1)
        # measurements at each epoch end
        wheel_idx = _match(wheel_t, updates, tol)
        gnss_idx = _match(gnss_t, updates, tol)
        gvel_idx = _match(gvel_t, updates, tol)
        head_idx = _match(head_t, updates, tol)
        mag_idx = _match(mag_t, updates, tol)
        pose_idx = _match(pose_t, updates, tol)
        source_idx, memory_rows = [], []
        for n, p, c in zip(names, pairs, carried, strict=True):
            at_start = _gyro_integral(imu_t, gyro, p[1])
            if c is not None:  # the pair across the boundary: minus the carried integral
                at_start[p[1] < t0 - tol] = -c[1]
            gyro_mean = (_gyro_integral(imu_t, gyro, p[0]) - at_start) / (p[0] - p[1])[:, None]
            source_idx.append((_match(p[0], updates, tol), p[2], p[3], gyro_mean))
            memory_rows.append(
                _pair_memory_row(
                    seq.pose_sources[n], b, t0, t_last, tol, imu_t, gyro, p, gyro_mean, c
                )
            )
        pseudo = np.ones(updates.size, dtype=bool)  # pseudo-measurements at every epoch
        zupt = np.zeros(updates.size, dtype=bool)
        if cfg.zupt:
            still_imu = _stationary_imu(imu_t, gyro, accel, updates, cfg)
            if wheel_t.size:
                wl = _np(seq.wheel.left_speed[b])[wheel_src]
                wr = _np(seq.wheel.right_speed[b])[wheel_src]
                still_wheel = np.zeros(updates.size, dtype=bool)
                has = wheel_idx >= 0
                still_wheel[has] = (np.abs(wl[wheel_idx[has]]) < cfg.zupt_wheel_speed_mps) & (
                    np.abs(wr[wheel_idx[has]]) < cfg.zupt_wheel_speed_mps
                )
                zupt = still_wheel & (
                    np.linalg.norm(gyro[end_sample], axis=1) < cfg.zupt_gyro_radps
                )
            elif cfg.zupt_imu_detector:
                zupt = pseudo & still_imu
        per_seq.append(
            dict(
                t0=t0,
                updates=updates,
                epoch=epoch,
                slot=slot,
                sample=sample,
                piece_dt=piece_dt,
                gap_piece=gap_piece,
                gap_length=gap_length,
                end_sample=end_sample,
                imu_sel=imu_sel,
                wheel=(wheel_idx, wheel_src),
                gnss=(gnss_idx, gnss_src),
                gnss_velocity=(gvel_idx, gvel_src),
                gnss_heading=(head_idx, head_src),
                magnetometer=(mag_idx, mag_src),
                magnetometer_dip=mag_dip,
                pose=(pose_idx, pose_src),
                nhc=pseudo & use_nhc,
                zupt=zupt,
                sources=source_idx,
                memory=memory_rows,
            )
        )

    batch = seq.batch_size
    n_epochs = max(p["updates"].size for p in per_seq)
    n_slots = max(int(p["slot"].max()) + 1 for p in per_seq)
    f64 = dict(dtype=dtype, device=device)

    def zeros(*shape, dt=dtype):
        return torch.zeros(*shape, dtype=dt, device=device)

    # the padded (B, E[, L]) arrays are filled in numpy (fancy-index writes of a sequence's
    # pieces cost microseconds there, far less than torch's multi-index puts) and moved to
    # the device once
    t_end = np.zeros((batch, n_epochs))
    epoch_mask = np.zeros((batch, n_epochs), dtype=bool)
    dt = np.zeros((batch, n_epochs, n_slots))
    noise_scale = np.ones((batch, n_epochs, n_slots))
    gap_length = np.zeros((batch, n_epochs, n_slots))
    gap = np.zeros((batch, n_epochs), dtype=bool)
    # index into the flattened (B N) IMU samples, padding at each sequence's first sample
    sample_index = np.empty((batch, n_epochs, n_slots), dtype=np.int64)
    end_index = np.zeros((batch, n_epochs), dtype=np.int64)
    masks = {k: np.zeros((batch, n_epochs), dtype=bool) for k in (*_MEASURED, "nhc", "zupt")}
    src = {k: np.zeros((batch, n_epochs), dtype=np.int64) for k in _MEASURED}
    n_src = len(names)
    source_mask = np.zeros((batch, n_epochs, n_src), dtype=bool)
    source_end = np.zeros((batch, n_epochs, n_src), dtype=np.int64)
    source_start = np.zeros((batch, n_epochs, n_src), dtype=np.int64)
    source_gyro_mean = np.zeros((batch, n_epochs, n_src, 3))
    t_start = np.array([p["t0"] for p in per_seq], dtype=np.float64)
    for b, p in enumerate(per_seq):
        n_e = p["updates"].size
        t_end[b, :n_e] = p["updates"]
        t_end[b, n_e:] = p["updates"][-1]
        epoch_mask[b, :n_e] = True
        piece = p["epoch"] * n_slots + p["slot"]  # index into the sequence's (E L) slots
        dt[b].reshape(-1)[piece] = p["piece_dt"]
        noise_scale[b].reshape(-1)[piece[p["gap_piece"]]] = cfg.imu_gap_noise_scale
        gap_length[b].reshape(-1)[piece] = p["gap_length"]
        gap[b, p["epoch"][p["gap_piece"]]] = True
        sample_index[b] = b * seq.imu.length
        sample_index[b].reshape(-1)[piece] += p["imu_sel"][p["sample"]]
        end_index[b, :n_e] = p["imu_sel"][p["end_sample"]]
        for key in _MEASURED:
            idx, source = p[key]
            has = idx >= 0
            masks[key][b, :n_e] = has
            src[key][b, :n_e][has] = source[idx[has]]
        masks["nhc"][b, :n_e] = p["nhc"]
        masks["zupt"][b, :n_e] = p["zupt"]
        for s, (idx, end, start, gyro_mean) in enumerate(p["sources"]):
            has = np.nonzero(idx >= 0)[0]
            source_mask[b, has, s] = True
            source_end[b, has, s] = end[idx[has]]
            source_start[b, has, s] = start[idx[has]]
            source_gyro_mean[b, has, s] = gyro_mean[idx[has]]

    def tensor(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, device=device, dtype=dtype if x.dtype == np.float64 else None)

    t_start, t_end, dt, noise_scale, gap_length, source_gyro_mean = map(
        tensor, (t_start, t_end, dt, noise_scale, gap_length, source_gyro_mean)
    )
    epoch_mask, gap, end_index, source_mask = map(tensor, (epoch_mask, gap, end_index, source_mask))
    source_end, source_start, sample_index = map(tensor, (source_end, source_start, sample_index))
    masks = {k: tensor(v) for k, v in masks.items()}
    src = {k: tensor(v) for k, v in src.items()}
    pair_memory_out = None
    if names:  # PairMemory's fields, (B, S[, 3]) each
        columns = [
            np.array([[p["memory"][s][k] for s in range(n_src)] for p in per_seq], np.float64)
            for k in range(5)
        ]
        pair_memory_out = PairMemory(names, *map(tensor, columns))

    rows = torch.arange(batch, device=device)[:, None]
    gyro_end = seq.imu.gyro[rows, end_index]

    def take(stream, name, key, shape):
        if stream is None or stream.length == 0:  # no samples: as without the stream
            return zeros(batch, n_epochs, *shape)
        return getattr(stream, name)[rows, src[key]]

    wheel_left = take(seq.wheel, "left_speed", "wheel", ())
    wheel_right = take(seq.wheel, "right_speed", "wheel", ())
    gnss_position = take(seq.gnss, "position", "gnss", (3,))
    gnss_sigma = take(seq.gnss, "sigma", "gnss", (3,))
    default_sigma = torch.as_tensor(cfg.gnss_sigma_m, **f64)
    gnss_sigma = torch.where(
        torch.isfinite(gnss_sigma) & (gnss_sigma > 0), gnss_sigma, default_sigma
    )
    gnss_velocity = take(seq.gnss_velocity, "velocity", "gnss_velocity", (3,))
    gnss_velocity_sigma = take(seq.gnss_velocity, "sigma", "gnss_velocity", (3,))
    default_sigma = torch.as_tensor(cfg.gnss_velocity_sigma_mps, **f64)
    gnss_velocity_sigma = torch.where(
        torch.isfinite(gnss_velocity_sigma) & (gnss_velocity_sigma > 0),
        gnss_velocity_sigma,
        default_sigma,
    )
    unmeasured = torch.isnan(gnss_velocity)  # the up axis of a horizontal-only receiver
    gnss_velocity = torch.where(unmeasured, 0.0, gnss_velocity)
    gnss_velocity_sigma = torch.where(unmeasured, UNMEASURED_SIGMA, gnss_velocity_sigma)
    gnss_heading = take(seq.gnss_heading, "heading", "gnss_heading", ())
    gnss_heading_sigma = take(seq.gnss_heading, "sigma", "gnss_heading", ())
    gnss_heading_sigma = torch.where(
        torch.isfinite(gnss_heading_sigma) & (gnss_heading_sigma > 0),
        gnss_heading_sigma,
        cfg.gnss_heading_sigma_rad,
    )
    magnetometer_field, magnetometer_sigma = corrected_magnetometer(
        take(seq.magnetometer, "field", "magnetometer", (3,)),
        take(seq.magnetometer, "sigma", "magnetometer", ()),
        cfg,
    )
    pose_position = take(seq.poses, "position", "pose", (3,))
    if seq.poses is None or seq.poses.length == 0:
        pose_rotation = torch.eye(3, **f64).expand(batch, n_epochs, 3, 3).clone()
        pose_covariance = torch.eye(6, **f64).expand(batch, n_epochs, 6, 6).clone()
    else:
        pose_quat = seq.poses.quaternion[rows, src["pose"]]
        pose_quat = torch.where(
            masks["pose"][..., None], pose_quat, torch.tensor([1.0, 0, 0, 0], **f64)
        )
        pose_rotation = quat_to_matrix(pose_quat)
        pose_covariance = torch.where(
            masks["pose"][..., None, None],
            seq.poses.covariance[rows, src["pose"]],
            torch.eye(6, **f64),
        )
    parts = [
        _source_velocities(
            seq.pose_sources[n], rows, source_end[..., s], source_start[..., s], source_mask[..., s]
        )
        for s, n in enumerate(names)
    ]
    if parts:
        stacked = [torch.stack(x, 2) for x in zip(*parts, strict=True)]
    else:
        stacked = [zeros(batch, n_epochs, 0, *shape) for shape in ((3,), (3, 3)) * 2 + ((),)]
    source_velocity, source_covariance, source_rate, source_rate_cov, source_dt = stacked
    return Schedule(
        t_start=t_start,
        t_end=t_end,
        epoch_mask=epoch_mask,
        sample_index=sample_index,
        imu_gyro=seq.imu.gyro.reshape(-1, 3),
        imu_accel=seq.imu.accel.reshape(-1, 3),
        dt=dt,
        noise_scale=noise_scale,
        gap_length=gap_length,
        gap=gap,
        gyro_end=gyro_end,
        wheel_left=wheel_left,
        wheel_right=wheel_right,
        wheel_mask=masks["wheel"],
        gnss_position=gnss_position,
        gnss_sigma=gnss_sigma,
        gnss_mask=masks["gnss"],
        gnss_velocity=gnss_velocity,
        gnss_velocity_sigma=gnss_velocity_sigma,
        gnss_velocity_mask=masks["gnss_velocity"],
        gnss_heading=gnss_heading,
        gnss_heading_sigma=gnss_heading_sigma,
        gnss_heading_mask=masks["gnss_heading"],
        magnetometer_field=magnetometer_field,
        magnetometer_sigma=magnetometer_sigma,
        magnetometer_mask=masks["magnetometer"],
        magnetometer_dip=torch.as_tensor([p["magnetometer_dip"] for p in per_seq], **f64),
        pose_position=pose_position,
        pose_rotation=pose_rotation,
        pose_covariance=pose_covariance,
        pose_mask=masks["pose"],
        nhc_mask=masks["nhc"],
        zupt_mask=masks["zupt"],
        imu_index_end=end_index,
        source_names=names,
        source_velocity=source_velocity,
        source_covariance=source_covariance,
        source_rate=source_rate,
        source_rate_covariance=source_rate_cov,
        source_gyro_mean=source_gyro_mean,
        source_dt=source_dt,
        source_mask=source_mask,
        pair_memory=pair_memory_out,
    )
