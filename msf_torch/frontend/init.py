"""Initial state of the front end from the first seconds of each sequence.

Roll and pitch come from the mean accelerometer reading over ``init_window_s`` (gravity
direction), with the body's acceleration taken out where wheel speeds (or, without wheels,
GNSS velocities) cover the window (:func:`levelling_specific_force`). Yaw, in order of
preference: the first pose measurement (a heading source, sigma ``init_yaw_sigma_rad``);
with GNSS and wheels, the 2-D rotation that best aligns the wheel/gyro dead-reckoned path
with the GNSS track up to ``init_min_gnss_distance_m`` from the first fix (2-D Kabsch on
the centred tracks; the aligned dead-reckoning origin is the initial position); with GNSS
only, the course of the first GNSS displacement of that length, or the GNSS track's
segment courses less the gyro's turns (:func:`segment_course_yaw`) where that is better
known; else 0 with a heading sigma of ``init_yaw_sigma_unknown_rad`` (pi; the world frame
then starts aligned with the body). A track that never gets that far but reaches a quarter
of it is used up to its farthest fix.
A GNSS heading's sigma is that of the estimate made
(:func:`alignment_yaw_variance`: the fixes' noise over the track's spread, and the gyro
bias and white noise bending the dead-reckoned track; for a course, the two fixes' noise
across the baseline and the gyro's heading swing over it; plus the prior of an
IMU-to-vehicle rotation being calibrated, the track running along the vehicle's axis).
With GNSS velocities (``Sequence.gnss_velocity``), the course over ground of the first one
at least ``init_min_gnss_speed_mps`` fast, carried back to the first IMU sample by the
gyro's heading change (:func:`velocity_heading`), replaces the track's heading when its
modelled variance is smaller. A dual-antenna GNSS heading (``Sequence.gnss_heading``) does
the same with the first heading in the track's span (:func:`antenna_heading_yaw`), standing
still or not.
Biases and the other uncertainties come from the config; the initial covariance carries the
correlations the initialisation creates: roll and pitch with the accelerometer bias (the
tilt is read from the biased accelerometer; ``init_roll_pitch_sigma_rad`` is the part from
motion during the window), and a velocity built from a body-frame wheel speed with the
attitude (``dv = -R [v_b]x dtheta``; the velocity sigma is then body-frame). The Kabsch
yaw's error also shares the gyro bias error that bent the track (the gain of
:func:`alignment_yaw_variance`); that correlation is not put into the covariance (see
docs/frontend.md: it helps the NEES but keeps a stuck-gyro fault from being reset).
"""

from __future__ import annotations

__all__ = [
    "alignment_yaw_variance",
    "antenna_heading_yaw",
    "initial_state",
    "levelling_specific_force",
    "magnetometer_yaw",
    "segment_course_yaw",
    "velocity_heading",
]

import math
import warnings
from collections.abc import Callable

import numpy as np
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.schedule import corrected_readings, gyro_attitude, undisturbed_magnetometer
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import ERROR_STATE_DIM
from msf_torch.types import NavState, Sequence


def _valid(stream, b: int, span: tuple[float, float]):
    """The real samples of sequence ``b`` of ``stream`` whose times lie in ``span`` (s), as
    numpy arrays by field, or None when there are none (samples the filter never reaches,
    e.g. stamped by another clock, must not set the initial state)."""
    if stream is None:
        return None
    t = stream.t[b].detach().cpu().numpy()
    mask = stream.mask[b].cpu().numpy() & (t >= span[0]) & (t <= span[1])
    if not mask.any():
        return None
    return {
        k: v[b].detach().cpu().numpy()[mask] for k, v in stream.tensors().items() if k != "mask"
    }


def _imu_reader(
    seq: Sequence, b: int
) -> tuple[np.ndarray, Callable[[str, np.ndarray | slice], np.ndarray]]:
    """Valid IMU times (N,) s of sequence ``b`` and a reader ``(field, selection) -> values``
    of those samples at ``selection`` (a boolean mask or slice over the N): only the
    samples used are copied (the initialisation reads a short window of the accelerometer,
    and only the gyro's z axis)."""
    index = np.nonzero(seq.imu.mask[b].cpu().numpy())[0]

    def read(name: str, selection: np.ndarray | slice) -> np.ndarray:
        return getattr(seq.imu, name)[b].detach().cpu().numpy()[index[selection]]

    return seq.imu.t[b].detach().cpu().numpy()[index], read


def alignment_yaw_variance(
    track: np.ndarray,
    fix_sigma: np.ndarray,
    fix_t: np.ndarray,
    step_t: np.ndarray,
    step: np.ndarray,
    gyro_bias_sigma: float,
    gyro_noise_density: float,
) -> tuple[float, float]:
    """Variance of the 2-D Kabsch yaw that aligns a dead-reckoned track with GNSS fixes.

    The initialiser rotates the centred dead-reckoned (DR) points ``d_i`` onto the centred
    fixes ``g_i``: ``yaw = atan2(sum d_i x g_i, sum d_i . g_i)``. With ``g_i = R(yaw) d0_i +
    n_i`` (fix noise) and ``d_i = d0_i + e_i`` (DR error), to first order

        yaw_hat - yaw = (sum_i r_i x n_i - sum_i r_i x e_i) / S,   S = sum_i |r_i|^2,

    ``r_i`` the centred track (world frame; the centring drops out since ``sum r_i = 0``).
    Fix noise independent per axis: ``var = sum_i (r_iy^2 sx_i^2 + r_ix^2 sy_i^2) / S^2``
    (``sigma^2 / S`` when isotropic). The DR track is integrated from the gyro yaw rate, whose
    heading error ``psi(s) = db s + w(s)`` (turn-on bias error ``db``, sigma
    ``gyro_bias_sigma``; angle random walk ``w``, density ``gyro_noise_density``) bends it:
    ``e_i = sum_{t_k < t_i} psi_k J step_k`` (``J`` the 90-degree turn) and ``r x (J a) =
    r . a``, so ``sum_i r_i x e_i = sum_k psi_k H_k`` with ``H_k = (sum_{i: t_i > t_k} r_i) .
    step_k``. Hence ``var += (gyro_bias_sigma^2 (sum_k t_k H_k)^2 + q^2 sum_j dt_j
    (sum_{k > j} H_k)^2) / S^2``; the yaw error (truth minus estimate) moves with the bias
    error (truth minus estimate) by the gain ``sum_k t_k H_k / S`` per rad/s. A common
    wheel scale error scales the DR track and leaves the rotation unchanged; wheel speed
    noise (mm over a 20 m track) and the bias random walk over the fitting seconds are
    neglected.

    Args:
        track: (M, 2) centred aligned track at the fixes, world frame, m.
        fix_sigma: (M, 2) 1-sigma noise of each fix east and north, m.
        fix_t: (M,) fix times since the first IMU sample, s.
        step_t: (N,) IMU sample times since the first IMU sample up to the last fix, s.
        step: (N, 2) DR displacement over each IMU interval, world frame, m.
        gyro_bias_sigma: 1-sigma yaw gyro bias error, rad/s.
        gyro_noise_density: gyro white noise, rad/s/sqrt(Hz).

    Returns:
        The yaw variance, rad^2, and ``d(yaw error) / d(gyro bias z error)``, s.

    Example:
        >>> track = np.stack((np.linspace(-10, 10, 11), np.zeros(11)), 1)
        >>> var, gain = alignment_yaw_variance(
        ...     track, np.full((11, 2), 0.5), np.arange(11.0), np.zeros(1), np.zeros((1, 2)),
        ...     0.0, 0.0)
        >>> round(var**0.5, 4)  # 0.5 m / sqrt(sum of squared offsets, 440 m^2)
        0.0238
    """
    spread = float((track**2).sum())
    fixes = (
        track[:, 1] ** 2 * fix_sigma[:, 0] ** 2 + track[:, 0] ** 2 * fix_sigma[:, 1] ** 2
    ).sum()
    # sum of the centred fixes after each IMU sample: later[k] = sum_{i: t_i > t_k} r_i
    after = np.concatenate((np.cumsum(track[::-1], 0)[::-1], np.zeros((1, 2))))
    later = after[np.searchsorted(fix_t, step_t, side="right")]
    weight = (later * step).sum(1)  # H_k, m^2
    gain = float((step_t * weight).sum()) / spread
    dt = np.diff(step_t, append=step_t[-1])
    tail = np.cumsum(weight[::-1])[::-1] - weight  # sum_{k > j} H_k
    walk = gyro_noise_density**2 * float((dt * tail**2).sum())
    variance = (fixes + walk) / spread**2 + (gyro_bias_sigma * gain) ** 2
    return float(variance), gain


def velocity_heading(
    velocity: dict[str, np.ndarray],
    imu_t: np.ndarray,
    gyro: np.ndarray,
    tilt: np.ndarray,
    cfg: EskfConfig,
    reversing: Callable[[float], bool] | None = None,
) -> tuple[float, float] | None:
    """Heading at the first IMU sample from the course over ground of a GNSS velocity.

    The first velocity at least ``cfg.init_min_gnss_speed_mps`` fast (horizontally) within
    ``cfg.init_max_track_s`` of the first IMU sample gives the course ``atan2(v_n, v_e)``;
    the vehicle moves along its x axis (the non-holonomic assumption; backwards when
    ``reversing(t)`` says so), and the antenna's rotation share ``R (w x l)`` is solved for
    exactly on level ground.
    The gyro's heading change from the first IMU sample to that time (the world-z
    component of the rate, ``tilt`` applied) carries it back.

    Args:
        velocity: the ``GnssVelocity`` fields ``t`` (M,) s, ``velocity`` (M, 3) m/s (up may
            be NaN), ``sigma`` (M, 3) m/s (NaN: ``cfg.gnss_velocity_sigma_mps``).
        imu_t: (N,) IMU times, s; gyro: (N, 3) raw rates, rad/s.
        tilt: (3, 3) the initial roll-pitch rotation (body -> level frame).
        cfg: the filter's config (speed threshold, lever arm, gyro noise, bias prior).
        reversing: optional ``t -> bool``, the vehicle drives backwards at time ``t``.

    Returns:
        (yaw, variance) in rad and rad^2, or None when no velocity is fast enough. The
        variance: the velocity's noise across the course over the speed squared, the gyro
        bias prior and angle random walk over the carried-back seconds, and the prior of an
        IMU-to-vehicle rotation being calibrated.
    """
    horizontal = np.hypot(velocity["velocity"][:, 0], velocity["velocity"][:, 1])
    usable = (horizontal >= cfg.init_min_gnss_speed_mps) & (
        velocity["t"] <= imu_t[0] + cfg.init_max_track_s
    )
    if not usable.any():
        return None
    k = int(np.argmax(usable))
    t_v = float(velocity["t"][k])
    turned, carry_variance = _carried_back(imu_t, gyro, tilt, t_v, cfg)
    bias = np.asarray(cfg.init_gyro_bias_radps)
    at_v = int(np.searchsorted(imu_t, t_v, side="right")) - 1
    # the antenna moves with R (s e_x + w x l): in the level frame turned by the heading psi,
    # its horizontal velocity is (s + a_x, a_y) with a = tilt (w x l), so psi is the course
    # minus the angle of that vector, s + a_x = +-sqrt(|v_h|^2 - a_y^2) (- when reversing)
    horizontal_velocity = velocity["velocity"][k, :2]
    course = math.atan2(horizontal_velocity[1], horizontal_velocity[0])
    arm = tilt @ np.cross(gyro[at_v] - bias, np.asarray(cfg.gnss_lever_arm_m))
    along_sq = float(horizontal_velocity @ horizontal_velocity) - arm[1] ** 2
    if along_sq <= 0.0:
        return None
    along = math.sqrt(along_sq) * (-1.0 if reversing is not None and reversing(t_v) else 1.0)
    heading = course - math.atan2(arm[1], along)
    sigma = velocity["sigma"][k, :2]
    default = np.asarray(cfg.gnss_velocity_sigma_mps[:2], dtype=np.float64)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, default)
    across = np.array([-math.sin(course), math.cos(course)])
    variance = float(((sigma * across) ** 2).sum()) / float(
        horizontal_velocity @ horizontal_velocity
    )
    variance += carry_variance
    if cfg.calibrate_imu_body_rotation:
        variance += cfg.calibration_rotation_sigma_rad**2
    yaw = math.atan2(math.sin(heading - turned), math.cos(heading - turned))
    return yaw, variance


def antenna_heading_yaw(
    heading: dict[str, np.ndarray],
    imu_t: np.ndarray,
    gyro: np.ndarray,
    tilt: np.ndarray,
    cfg: EskfConfig,
) -> tuple[float, float] | None:
    """Heading at the first IMU sample from a dual-antenna GNSS heading.

    Of the headings within ``cfg.init_max_track_s`` of the first IMU sample, the one whose
    yaw carried back has the smallest variance (usually the first; not one a driver marks
    invalid with a huge sigma) gives the yaw that turns the tilted baseline
    ``tilt @ cfg.gnss_heading_baseline_m`` to the measured azimuth (clockwise from north),
    carried back to the first IMU sample by the gyro's heading change. It needs no motion:
    a vehicle standing still is aligned at once.

    Args:
        heading: the ``GnssHeading`` fields ``t`` (M,) s, ``heading`` (M,) rad, ``sigma``
            (M,) rad (NaN: ``cfg.gnss_heading_sigma_rad``).
        imu_t: (N,) IMU times, s; gyro: (N, 3) raw rates, rad/s.
        tilt: (3, 3) the initial roll-pitch rotation (body -> level frame).
        cfg: the filter's config (baseline, turned by the initial heading offset when that
            is calibrated; default sigma, gyro noise, bias prior).

    Returns:
        (yaw, variance) in rad (ENU, counter-clockwise from east) and rad^2, or None when
        no heading lies in that span or the tilted baseline is vertical. The variance: the
        heading's, plus the gyro bias prior and angle random walk over the carried-back
        seconds, plus the offset's prior variance when it is calibrated.
    """
    usable = heading["t"] <= imu_t[0] + cfg.init_max_track_s
    baseline = np.asarray(cfg.gnss_heading_baseline_m, dtype=np.float64)
    offset = cfg.calibration_gnss_heading_offset_rad if cfg.calibrate_gnss_heading_offset else 0.0
    turn = np.array(  # the baseline turned about body z by the offset being calibrated
        [
            [math.cos(offset), -math.sin(offset), 0.0],
            [math.sin(offset), math.cos(offset), 0.0],
            [0.0, 0.0, 1.0],
        ]
    )
    level = tilt @ turn @ baseline
    if not usable.any() or math.hypot(level[0], level[1]) < 1e-6 * np.linalg.norm(level):
        return None
    sigma = np.where(
        np.isfinite(heading["sigma"]) & (heading["sigma"] > 0),
        heading["sigma"],
        cfg.gnss_heading_sigma_rad,
    )
    total = sigma**2 + _carry_variance(heading["t"] - imu_t[0], cfg)
    k = int(np.argmin(np.where(usable, total, np.inf)))
    turned, variance = _carried_back(imu_t, gyro, tilt, float(heading["t"][k]), cfg)
    # azimuth (clockwise from north) = pi / 2 - (yaw + the level baseline's ENU angle)
    yaw = math.pi / 2 - float(heading["heading"][k]) - math.atan2(level[1], level[0]) - turned
    if cfg.calibrate_gnss_heading_offset:  # the offset's prior uncertainty enters the yaw
        variance += cfg.calibration_rotation_sigma_rad**2
    return math.atan2(math.sin(yaw), math.cos(yaw)), float(sigma[k]) ** 2 + variance


def magnetometer_yaw(
    seq: Sequence,
    b: int,
    imu_t: np.ndarray,
    gyro: np.ndarray,
    roll: float,
    pitch: float,
    cfg: EskfConfig,
) -> tuple[float, float] | None:
    """Heading at the first IMU sample from the magnetometer (tilt-compensated compass).

    The first undisturbed reading (:func:`~msf_torch.frontend.schedule.undisturbed_magnetometer`)
    within ``cfg.init_max_track_s`` of the first IMU sample is corrected (hard and soft
    iron), turned into the first IMU sample's body axes by the gyro's rotation since
    (:func:`~msf_torch.frontend.schedule.gyro_attitude`: on uneven ground roll and pitch
    change too, not only the heading), levelled with the accelerometer's roll and pitch,
    and the yaw that turns its horizontal part to the declination is the heading at the
    first sample. It needs no motion.

    Args:
        seq: the batch; b: the sequence.
        imu_t: (N,) IMU times, s; gyro: (N, 3) raw rates, rad/s.
        roll, pitch: the initial tilt, rad.
        cfg: the filter's config (declination, iron, noise, floor, gyro and tilt priors).

    Returns:
        (yaw, variance) in rad (ENU, counter-clockwise from east) and rad^2, or None when
        no undisturbed reading lies in that span or it has no horizontal part. The
        variance: the reading's noise over its horizontal magnitude, the heading floor,
        the tilt prior ``init_roll_pitch_sigma_rad`` through the field's vertical part
        (a level error moves the levelled field's azimuth by up to ``tan(dip)`` times it),
        and the gyro's over the carried-back seconds.
    """
    stream = seq.magnetometer
    t = stream.t[b].detach().cpu().numpy()
    usable = stream.mask[b].cpu().numpy() & (t > imu_t[0] - cfg.time_tolerance_s)
    usable &= t <= imu_t[0] + cfg.init_max_track_s
    index = np.flatnonzero(usable)
    times, index = undisturbed_magnetometer(
        stream, b, cfg, imu_t, gyro - np.asarray(cfg.init_gyro_bias_radps), t[index], index
    )
    if times.size == 0:
        return None
    k = int(index[0])
    # the reading in the first IMU sample's body axes: turned back by the gyro's rotation
    # (roll and pitch change over it on uneven ground, not only the heading)
    upto = np.searchsorted(imu_t, t[k], side="right") + 1
    turn = gyro_attitude(
        imu_t[:upto], gyro[:upto] - np.asarray(cfg.init_gyro_bias_radps), t[k : k + 1]
    )[0]
    corrected, sigma = corrected_readings(
        stream.field[b, k].detach().cpu().numpy(), cfg, stream.sigma[b, k].detach().cpu().numpy()
    )
    field = turn @ corrected

    def azimuth(roll_: float, pitch_: float) -> tuple[float, float]:
        level = _rpy_numpy(roll_, pitch_, 0.0) @ field
        return math.atan2(level[0], level[1]), math.hypot(level[0], level[1])

    level_azimuth, horizontal = azimuth(roll, pitch)
    if horizontal < 1e-6 * float(np.linalg.norm(field)):
        return None
    step = 1e-6
    tilt_var = sum(
        (math.remainder(azimuth(*angles)[0] - level_azimuth, 2.0 * math.pi) / step) ** 2
        for angles in ((roll + step, pitch), (roll, pitch + step))
    ) * (cfg.init_roll_pitch_sigma_rad**2)
    sigma = float(sigma)
    carry_var = float(_carry_variance(np.asarray(t[k] - imu_t[0]), cfg))
    # azimuth of the levelled field turned by yaw = level_azimuth - yaw = the declination
    yaw = level_azimuth - cfg.magnetometer_declination_rad
    variance = (sigma / horizontal) ** 2 + cfg.magnetometer_heading_floor_rad**2
    if cfg.calibrate_magnetometer_declination:  # the declination's prior enters the yaw
        variance += cfg.calibration_magnetometer_declination_sigma_rad**2
    return math.atan2(math.sin(yaw), math.cos(yaw)), variance + tilt_var + carry_var


def segment_course_yaw(
    gnss_t: np.ndarray,
    gnss_xy: np.ndarray,
    fix_sigma: np.ndarray,
    imu_t: np.ndarray,
    gyro: np.ndarray,
    tilt: np.ndarray,
    cfg: EskfConfig,
) -> tuple[float, float] | None:
    """Heading at the first IMU sample from the courses of a GNSS track's segments, with
    the gyro's turns taken out (no wheels needed; the vehicle drives forwards along its x
    axis, the non-holonomic assumption).

    The fixes are cut into consecutive segments, each ending at the first fix at least
    ``SEGMENT_SIGMAS`` times its two fixes' horizontal sigma from its start. On a turn of
    constant rate and speed a segment's chord points along the mean heading over it, so
    ``course_i - mean(turned)_i`` (``turned``: the gyro's heading change since the first
    IMU sample) estimates the initial heading; their weighted circular mean is the yaw.
    A turning, slow vehicle, whose track's overall course says nothing (a loop), is aligned
    this way within seconds.

    Args:
        gnss_t: (M,) fix times, s; gnss_xy: (M, 2) east, north, m; fix_sigma: (M, 2) m.
        imu_t: (N,) IMU times, s; gyro: (N, 3) raw rates, rad/s.
        tilt: (3, 3) the initial roll-pitch rotation (body -> level frame).
        cfg: the filter's config (bias prior, gyro noise).

    Returns:
        (yaw, variance) in rad (ENU, counter-clockwise from east) and rad^2, or None with
        fewer than three segments. Each segment's variance: its end fixes' noise across
        the chord over its length squared, plus a quarter of its gyro heading swing
        squared (speed changes inside it); the variance is that of the weighted mean
        (segments share end fixes: their independence is assumed) plus the carry-back
        variance (:func:`_carry_variance`) at the segments' weighted mean time. Segments
        more than 3 sigma off the first mean are dropped once.
    """
    dt = np.diff(imu_t, append=imu_t[-1])
    rate = ((gyro - np.asarray(cfg.init_gyro_bias_radps)) @ tilt.T)[:, 2]
    turned = np.concatenate(([0.0], np.cumsum(rate * dt)[:-1]))
    courses, variances, times = [], [], []
    start = 0
    for end in range(1, len(gnss_t)):
        chord = gnss_xy[end] - gnss_xy[start]
        length = float(np.hypot(*chord))
        reach = SEGMENT_SIGMAS * float(np.hypot(*fix_sigma[start]) + np.hypot(*fix_sigma[end]))
        if length < reach:
            continue
        inside = (imu_t >= gnss_t[start]) & (imu_t <= gnss_t[end])
        if inside.sum() < 2:
            start = end
            continue
        course = math.atan2(chord[1], chord[0])
        across = np.array([-math.sin(course), math.cos(course)])
        noise = float(((fix_sigma[[start, end]] * across) ** 2).sum()) / length**2
        swing = float(np.ptp(turned[inside]))
        courses.append(course - float(turned[inside].mean()))
        variances.append(noise + 0.25 * swing**2)
        times.append(0.5 * (gnss_t[start] + gnss_t[end]) - imu_t[0])
        start = end
    if len(courses) < 3:
        return None
    course_, weight, time_ = np.array(courses), 1.0 / np.array(variances), np.array(times)
    yaw = math.atan2((weight * np.sin(course_)).sum(), (weight * np.cos(course_)).sum())
    off = np.abs(np.remainder(course_ - yaw + math.pi, 2.0 * math.pi) - math.pi)
    keep = off <= 3.0 / np.sqrt(weight)
    if keep.sum() < 3:
        return None
    course_, weight, time_ = course_[keep], weight[keep], time_[keep]
    yaw = math.atan2((weight * np.sin(course_)).sum(), (weight * np.cos(course_)).sum())
    mean_time = float((weight * time_).sum() / weight.sum())
    return yaw, 1.0 / float(weight.sum()) + float(_carry_variance(np.asarray(mean_time), cfg))


SEGMENT_SIGMAS = 5.0
"""A track segment of :func:`segment_course_yaw` ends at the first fix this many times its
two fixes' horizontal sigmas (summed) from its start: its course is then good to about
0.3 rad from the fixes' noise."""


def _check_heading_source(
    name: str,
    source: str,
    hint: str,
    measured: tuple[float, float],
    yaw: float,
    yaw_sigma: float,
    consequence: str = "",
    sigmas: float = 5.0,
) -> bool:
    """Warn when a heading source's yaw and the one found before it (the GNSS track's or
    course's, or another source's) differ by more than ``sigmas`` sigma of the two
    together: a wrong ``gnss_heading_baseline_m`` (antennas mounted left-right, the
    receiver's heading offset) or magnetometer calibration makes the filter trust the
    heading and refuse the fixes. Returns whether they agree (``consequence`` ends the
    warning)."""
    difference = math.remainder(measured[0] - yaw, 2.0 * math.pi)
    sigma = math.sqrt(measured[1] + yaw_sigma**2)
    if abs(difference) > sigmas * sigma:
        warnings.warn(
            f"sequence '{name}': the {source} gives a yaw "
            f"{math.degrees(difference):+.1f} degrees from the GNSS track's or the heading "
            f"found before it ({abs(difference) / sigma:.0f} sigma): check {hint}"
            f"{consequence}",
            stacklevel=4,
        )
        return False
    return True


def _carried_back(
    imu_t: np.ndarray, gyro: np.ndarray, tilt: np.ndarray, t: float, cfg: EskfConfig
) -> tuple[float, float]:
    """The gyro's heading change (rad) from the first IMU sample to time ``t`` (s; the
    world-z component of the bias-corrected rate, ``tilt`` applied), and the variance
    (rad^2) carrying a heading back over it adds: the gyro bias prior times the seconds,
    squared, and the angle random walk."""
    inside = imu_t <= t
    dt = np.diff(np.append(imu_t[inside], t))
    rate = gyro[inside] - np.asarray(cfg.init_gyro_bias_radps)
    turned = float(((rate @ tilt.T)[:, 2] * dt).sum())
    return turned, float(_carry_variance(np.asarray(t - imu_t[0]), cfg))


def _carry_variance(elapsed: np.ndarray, cfg: EskfConfig) -> np.ndarray:
    """Variance (rad^2) a heading gains when carried back by the gyro over ``elapsed``
    seconds (any shape): the gyro bias prior times the seconds, squared, plus the angle
    random walk."""
    return (cfg.init_gyro_bias_sigma_radps * elapsed) ** 2 + cfg.gyro_noise_density**2 * elapsed


def _rpy_numpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix (3, 3) of roll, pitch, yaw (rad), computed on the CPU."""
    angles = torch.tensor([roll, pitch, yaw], dtype=torch.float64, device="cpu")
    return so3.rpy_matrix(angles).numpy()


def levelling_specific_force(
    imu_t: np.ndarray,
    accel: np.ndarray,
    gyro: np.ndarray,
    wheel: dict[str, np.ndarray] | None,
    cfg: EskfConfig,
    gnss_velocity: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """The specific force of gravity alone (3,) m/s^2 in the body axes at the first sample
    of a levelling window, whose direction gives the initial roll and pitch.

    Without wheel speeds over the window: the mean of the (bias-corrected) accelerometer,
    which carries the body's mean acceleration over the window as a tilt. With them (a
    robot that starts moving), each sample's specific force has the body's acceleration
    taken out, ``f - (dv_b/dt + w x v_b)`` with ``v_b = R_vb (v, 0, 0) - w x l`` the IMU's
    velocity from the mean wheel speed ``v`` (``l`` = ``wheel_lever_arm_m``, ``R_vb`` the
    IMU-to-vehicle rotation when it is calibrated), and is turned back to the first sample
    by the gyro (``frontend.schedule.gyro_attitude``) before the mean, so neither the
    window's speed changes and turns nor the terrain's pitching while it lasts tilt the
    estimate. The wheel speeds must cover the window (a first reading within a quarter
    window of its start, a last within a quarter window of its end, three at least);
    otherwise the plain mean is used.

    Without wheels, GNSS velocities that cover the window in the same way stand in for
    them where the non-holonomic constraint holds (``nhc`` not ``off``): the speed over
    ground ``|v|`` (the antenna's, taken as that of the NHC point ``nhc_lever_arm_m``,
    driving forwards) along the vehicle's x axis. A receiver at 5 Hz or more covers the
    0.5-s window; at 1 Hz the plain mean stays.

    Args:
        imu_t: (N,) times of the window's IMU samples, s.
        accel, gyro: (N, 3) raw readings, m/s^2 and rad/s (the config's initial biases are
            taken out here).
        wheel: the sequence's wheel readings (``t``, ``left_speed``, ``right_speed``, m/s) or
            None.
        cfg: the front end's config.
        gnss_velocity: the sequence's GNSS velocities (``t``, ``velocity`` (M, 3) m/s east,
            north, up; a NaN up is not measured) or None.
    """
    force = accel - np.asarray(cfg.init_accel_bias_mps2)
    quarter = 0.25 * (imu_t[-1] - imu_t[0])

    def covers(times: np.ndarray) -> bool:
        inside = (times >= imu_t[0] - quarter) & (times <= imu_t[-1] + quarter)
        return (
            bool(times[0] <= imu_t[0] + quarter and times[-1] >= imu_t[-1] - quarter)
            and int(inside.sum()) >= 3
        )

    if imu_t.size < 2:
        return force.mean(0)
    if wheel is not None and covers(wheel["t"]):
        speed_t, speeds = wheel["t"], 0.5 * (wheel["left_speed"] + wheel["right_speed"])
        lever = np.asarray(cfg.wheel_lever_arm_m, dtype=np.float64)
    elif (
        wheel is None
        and gnss_velocity is not None
        and cfg.nhc != "off"
        and covers(gnss_velocity["t"])
    ):
        speed_t = gnss_velocity["t"]
        speeds = np.linalg.norm(np.nan_to_num(gnss_velocity["velocity"]), axis=1)
        lever = np.asarray(cfg.nhc_lever_arm_m, dtype=np.float64)
    else:
        return force.mean(0)
    rate = gyro - np.asarray(cfg.init_gyro_bias_radps)
    speed = np.interp(imu_t, speed_t, speeds)
    forward = np.array([1.0, 0.0, 0.0])
    if cfg.calibrate_imu_body_rotation:
        rotvec = torch.as_tensor(cfg.calibration_imu_body_rotation_rad, dtype=torch.float64)
        forward = so3.exp(rotvec).numpy() @ forward
    body_velocity = speed[:, None] * forward - np.cross(rate, lever)
    acceleration = np.gradient(body_velocity, imu_t, axis=0) + np.cross(rate, body_velocity)
    turned = gyro_attitude(imu_t, rate, imu_t)
    return np.einsum("kij,kj->i", turned, force - acceleration) / imu_t.size


def _one(
    seq: Sequence, b: int, cfg: EskfConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    imu_t, read_imu = _imu_reader(seq, b)
    t0 = imu_t[0]
    window = imu_t <= t0 + cfg.init_window_s
    span = (t0 - cfg.time_tolerance_s, imu_t[-1] + cfg.time_tolerance_s)
    wheel = _valid(seq.wheel, b, span)
    gnss_velocity = _valid(seq.gnss_velocity, b, span)
    f = levelling_specific_force(
        imu_t[window],
        read_imu("accel", window),
        read_imu("gyro", window),
        wheel,
        cfg,
        gnss_velocity,
    )
    roll = math.atan2(f[1], f[2])
    pitch = math.atan2(-f[0], math.hypot(f[1], f[2]))
    yaw = 0.0
    yaw_sigma = cfg.init_yaw_sigma_unknown_rad  # no heading source
    position = np.zeros(3)
    velocity = np.zeros(3)
    gnss = _valid(seq.gnss, b, span)
    poses = _valid(seq.poses, b, span)
    wheel_speed = 0.0
    if wheel is not None:
        wheel_speed = 0.5 * (wheel["left_speed"][0] + wheel["right_speed"][0])
    if poses is not None:
        from msf_torch.geometry.quaternion import quat_to_matrix

        rot = quat_to_matrix(torch.as_tensor(poses["quaternion"][0])).numpy()
        position = poses["position"][0]
        body_velocity = np.array([wheel_speed, 0.0, 0.0])
        return position, rot @ body_velocity, rot, body_velocity, cfg.init_yaw_sigma_rad
    anchored = None  # the aligned dead-reckoning origin (wheels and a GNSS track)
    track_means = None  # (GNSS track, dead-reckoned track) means of the Kabsch fit
    track_yaw = True  # the yaw is the track's (not replaced by a velocity or antenna heading)
    if gnss is not None:
        g0 = gnss["position"][0]
        dist = np.linalg.norm(gnss["position"][:, :2] - g0[:2], axis=1)
        # only the opening stretch of fixes: within init_max_track_s of the first and
        # before the first outage (dead reckoning across a long gap would bend the track)
        t_fix = gnss["t"]
        spacing = np.diff(t_fix)
        gaps = np.nonzero(spacing > 3.0 * np.median(spacing))[0] if spacing.size else []
        last = min(len(t_fix) - 1, int(gaps[0]) if len(gaps) else len(t_fix) - 1)
        last = min(last, int(np.searchsorted(t_fix, t_fix[0] + cfg.init_max_track_s, "right")) - 1)
        dist = dist[: last + 1]
        far = np.nonzero(dist >= cfg.init_min_gnss_distance_m)[0]
        position = g0.copy()
        # a track that never gets that far (a robot turning on the spot, a short run) is
        # used up to its farthest fix, with the heading sigma grown in proportion
        reach = float(dist.max())
        usable = far.size or reach >= 0.25 * cfg.init_min_gnss_distance_m
        if usable:
            k = far[0] if far.size else int(np.argmax(dist))
            sig = gnss["sigma"][: k + 1, :2]
            fallback = np.asarray(cfg.gnss_sigma_m[:2], dtype=np.float64)
            fix_sigma = np.where(np.isfinite(sig) & (sig > 0), sig, fallback)
            if wheel is not None:
                # dead-reckon with wheel speed and gyro yaw rate in the initial heading frame
                speed = np.interp(
                    imu_t, wheel["t"], 0.5 * (wheel["left_speed"] + wheel["right_speed"])
                )
                dt = np.diff(imu_t, append=imu_t[-1])
                yaw_rate = read_imu("gyro", slice(None))[:, 2] - cfg.init_gyro_bias_radps[2]
                heading = np.cumsum(yaw_rate * dt) - yaw_rate * dt
                step = np.stack((speed * np.cos(heading), speed * np.sin(heading)), 1) * dt[:, None]
                path = np.vstack((np.zeros(2), np.cumsum(step, 0)[:-1]))
                dr = np.stack(
                    [np.interp(gnss["t"][: k + 1], imu_t, path[:, i]) for i in range(2)], 1
                )
                # 2-D Kabsch on centred point sets: no single fix anchors the alignment
                gg = gnss["position"][: k + 1, :2]
                gg_c = gg - gg.mean(0)
                dr_c = dr - dr.mean(0)
                cross = np.sum(dr_c[:, 0] * gg_c[:, 1] - dr_c[:, 1] * gg_c[:, 0])
                dot = np.sum(dr_c[:, 0] * gg_c[:, 0] + dr_c[:, 1] * gg_c[:, 1])
                yaw = math.atan2(cross, dot)
                c, s_ = math.cos(yaw), math.sin(yaw)
                origin = gg.mean(0) - np.array([[c, -s_], [s_, c]]) @ dr.mean(0)
                anchored = np.array([origin[0], origin[1], g0[2]])
                track_means = (gg.mean(0), dr.mean(0))
                inside = imu_t <= gnss["t"][k]
                to_world = np.array([[c, s_], [-s_, c]])  # row vectors: r @ R(yaw)^T
                model_var, _ = alignment_yaw_variance(
                    dr_c @ to_world,
                    fix_sigma,
                    gnss["t"][: k + 1] - t0,
                    imu_t[inside] - t0,
                    step[inside] @ to_world,
                    cfg.init_gyro_bias_sigma_radps,
                    cfg.gyro_noise_density,
                )
            else:
                delta = gnss["position"][k] - g0
                yaw = math.atan2(delta[1], delta[0])
                elapsed = max(gnss["t"][k] - gnss["t"][0], 1e-3)
                velocity = np.array([delta[0], delta[1], 0.0]) / elapsed
                # the course of the baseline moves with the two fixes' noise across it, and
                # differs from the initial heading by at most the gyro's heading swing over
                # the baseline's seconds (a course is a mean of the headings travelled)
                across = np.array([-math.sin(yaw), math.cos(yaw)])
                inside = imu_t <= gnss["t"][k]
                dt = np.diff(imu_t[inside], append=imu_t[inside][-1])
                yaw_rate = read_imu("gyro", inside)[:, 2] - cfg.init_gyro_bias_radps[2]
                swing = float(np.abs(np.cumsum(yaw_rate * dt)).max())
                model_var = (
                    float(((fix_sigma[[0, k]] * across) ** 2).sum())
                    / max(float(dist[k]), 1e-9) ** 2
                    + swing**2
                )
                # the segments' courses less the gyro's turns, when that is better known
                sig = gnss["sigma"][: last + 1, :2]
                segments = segment_course_yaw(
                    gnss["t"][: last + 1],
                    gnss["position"][: last + 1, :2],
                    np.where(np.isfinite(sig) & (sig > 0), sig, fallback),
                    imu_t,
                    read_imu("gyro", slice(None)),
                    _rpy_numpy(roll, pitch, 0.0),
                    cfg,
                )
                if segments is not None and segments[1] < model_var:
                    yaw, model_var = segments
            if cfg.calibrate_imu_body_rotation:
                # the track runs along the vehicle's x axis, the heading wanted is the IMU's:
                # an IMU-to-vehicle yaw still to be calibrated adds its prior uncertainty
                model_var += cfg.calibration_rotation_sigma_rad**2
            yaw_sigma = math.sqrt(model_var)
    if gnss_velocity is not None:
        tilt = _rpy_numpy(roll, pitch, 0.0)
        reversing = None
        if wheel is not None:
            mean_speed = 0.5 * (wheel["left_speed"] + wheel["right_speed"])

            def reversing(t: float) -> bool:
                return float(np.interp(t, wheel["t"], mean_speed)) < 0.0

        course = velocity_heading(
            gnss_velocity, imu_t, read_imu("gyro", slice(None)), tilt, cfg, reversing
        )
        if course is not None and course[1] < yaw_sigma**2:
            yaw, yaw_sigma = course[0], math.sqrt(course[1])
            track_yaw = False
    antenna_heading = _valid(seq.gnss_heading, b, span)
    if antenna_heading is not None:
        tilt = _rpy_numpy(roll, pitch, 0.0)
        measured = antenna_heading_yaw(
            antenna_heading, imu_t, read_imu("gyro", slice(None)), tilt, cfg
        )
        if measured is not None and yaw_sigma < cfg.init_yaw_sigma_unknown_rad:
            _check_heading_source(
                seq.names[b],
                "dual-antenna GNSS heading",
                "gnss_heading_baseline_m (the primary -> secondary antenna direction in the "
                "body frame) and the receiver's heading offset",
                measured,
                yaw,
                yaw_sigma,
            )
        if measured is not None and measured[1] < yaw_sigma**2:
            yaw, yaw_sigma = measured[0], math.sqrt(measured[1])
            track_yaw = False
    if seq.magnetometer is not None:
        measured = magnetometer_yaw(seq, b, imu_t, read_imu("gyro", slice(None)), roll, pitch, cfg)
        known = yaw_sigma < cfg.init_yaw_sigma_unknown_rad
        if measured is not None and known:
            # a compass that disagrees by over 3 sigma is not used: a run that starts beside
            # steel reads a disturbed field as steady as the earth's (a wrong calibration
            # warns the same); one that agrees is combined with the other heading
            # (independent errors: inverse-variance weights)
            if _check_heading_source(
                seq.names[b],
                "magnetometer",
                "magnetometer_declination_rad, the hard- and soft-iron calibration and the "
                "sensor's mounting, or a disturbance at the start",
                measured,
                yaw,
                yaw_sigma,
                "; the initial yaw keeps the other heading",
                sigmas=3.0,
            ):
                weight = yaw_sigma**2 / (yaw_sigma**2 + measured[1])
                yaw += weight * math.remainder(measured[0] - yaw, 2.0 * math.pi)
                yaw = math.atan2(math.sin(yaw), math.cos(yaw))
                yaw_sigma = math.sqrt(weight * measured[1])
                track_yaw = False
        elif measured is not None:
            yaw, yaw_sigma = measured[0], math.sqrt(measured[1])
            track_yaw = False
    if track_means is not None and not track_yaw:  # the dead-reckoned track turned by yaw
        c, s_ = math.cos(yaw), math.sin(yaw)
        origin = track_means[0] - np.array([[c, -s_], [s_, c]]) @ track_means[1]
        anchored = np.array([origin[0], origin[1], anchored[2]])
    rot = _rpy_numpy(roll, pitch, yaw)
    body_velocity = np.zeros(3)
    if wheel is not None:
        body_velocity = np.array([wheel_speed, 0.0, 0.0])
        velocity = rot @ body_velocity
    if gnss is not None:
        lever = rot @ np.asarray(cfg.gnss_lever_arm_m)
        if anchored is not None:  # the aligned dead-reckoning origin, i.e. the track at t0
            position = anchored - lever
        else:
            position = gnss["position"][0] - lever - velocity * (gnss["t"][0] - t0)
    return position, velocity, rot, body_velocity, yaw_sigma


def initial_state(seq: Sequence, cfg: EskfConfig) -> tuple[NavState, torch.Tensor]:
    """Initial nominal state and covariance for every sequence of the batch.

    Returns:
        NavState with (B, ...) fields and covariance (B, 15, 15).
    """
    dtype, device = seq.imu.t.dtype, seq.imu.t.device
    parts = [_one(seq, b, cfg) for b in range(seq.batch_size)]

    def stack(i):
        return torch.as_tensor(np.stack([p[i] for p in parts]), dtype=dtype, device=device)

    batch = seq.batch_size
    gyro_bias = torch.as_tensor(cfg.init_gyro_bias_radps, dtype=dtype, device=device)
    accel_bias = torch.as_tensor(cfg.init_accel_bias_mps2, dtype=dtype, device=device)
    state = NavState(
        position=stack(0),
        velocity=stack(1),
        rotation=stack(2),
        gyro_bias=gyro_bias.expand(batch, 3).clone(),
        accel_bias=accel_bias.expand(batch, 3).clone(),
    )
    rp, yaw = cfg.init_roll_pitch_sigma_rad, cfg.init_yaw_sigma_rad
    sigmas = [cfg.init_position_sigma_m] * 3 + [cfg.init_velocity_sigma_mps] * 3
    sigmas += [rp, rp, yaw] + [cfg.init_gyro_bias_sigma_radps] * 3
    sigmas += [cfg.init_accel_bias_sigma_mps2] * 3
    sig = torch.as_tensor(sigmas, dtype=dtype, device=device)
    cov = torch.diag_embed(sig**2).expand(batch, ERROR_STATE_DIM, ERROR_STATE_DIM).clone()
    yaw_sigmas = torch.as_tensor([p[4] for p in parts], dtype=dtype, device=device)
    cov[:, 8, 8] = yaw_sigmas**2
    # roll and pitch come from the mean accelerometer, which carries the accel bias: with
    # f = R^T (-g_w) + b_a, a bias error db_a tilts the estimate by
    # dtheta_x = -db_a,y / g, dtheta_y = db_a,x / g (on top of the motion part)
    tilt = torch.zeros(3, 3, dtype=dtype, device=device)
    tilt[0, 1] = -1.0 / cfg.gravity_mps2
    tilt[1, 0] = 1.0 / cfg.gravity_mps2
    bias_cov = cov[:, 12:15, 12:15]
    cov[:, 6:9, 6:9] = cov[:, 6:9, 6:9] + tilt @ bias_cov @ tilt.mT
    cov[:, 6:9, 12:15] = tilt @ bias_cov
    cov[:, 12:15, 6:9] = (tilt @ bias_cov).mT
    # a velocity built from a body-frame speed inherits the attitude uncertainty:
    # v = R v_b with R = R0 Exp(dtheta) gives dv = R0 dv_b - R0 [v_b]x dtheta
    body_velocity = stack(3)
    rotation = state.rotation
    coupling = -rotation @ so3.hat(body_velocity)  # (B, 3, 3)
    att = cov[:, 6:9, 6:9]
    vel_body = torch.diag_embed(sig[3:6] ** 2).expand(batch, 3, 3)
    cov[:, 3:6, 3:6] = rotation @ vel_body @ rotation.mT + coupling @ att @ coupling.mT
    cov[:, 3:6, 6:9] = coupling @ att
    cov[:, 6:9, 3:6] = (coupling @ att).mT
    return state, cov
