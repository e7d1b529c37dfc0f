"""Filled-in IMU stretches: samples a recorder synthesised by linear interpolation.

Some logs bridge dropped IMU packets by writing samples interpolated linearly between the
last real sample before the dropout and the first one after it, with evenly spaced
timestamps, so the timestamps show no gap. The KITTI drive shipped by the gtsam wheel has
eight such stretches of 1.5-1.6 s (155-165 samples each), six of them in turns: over the
turn at 279-280.5 s the gyro's integral falls 13 degrees short of the GNSS track's change of
course, because the real yaw rate peaked between the two end samples. A real sensor's
noise makes six channels collinear to rounding for many samples in a row practically
impossible, so such a run is a reliable signature.

:func:`interpolated_imu_samples` finds the interior samples of every run of at least
``min_samples`` consecutive samples that lie, in all six channels, on the straight line
through their neighbours (to ``rtol`` relative to the channel's magnitude). The front end
and the smoothers treat those samples as an IMU gap (``EskfConfig.imu_gap_noise_scale``):
the interpolated values are still the best guess of the motion, but their noise is the
vehicle's unknown motion, not the sensor's. A run filtered in chunks (learned noise, at
inference and in training) moves a chunk boundary that falls inside a stretch to the
stretch's end (:func:`outside_stretches`), so that each stretch stays one gap.
"""

from __future__ import annotations

__all__ = [
    "filled_stretches",
    "gap_walk_scale",
    "interpolated_imu_samples",
    "open_stretch_start",
    "outside_stretches",
]

import numpy as np
import torch


def _imu_arrays(
    t: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    accel: torch.Tensor | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) and the six channels (N, 6), gyro then accelerometer, as float64 numpy."""

    def host(x: torch.Tensor | np.ndarray) -> np.ndarray:
        return np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, np.float64)

    return host(t), np.concatenate((host(gyro), host(accel)), axis=1)


def _line_fractions(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per interior sample k + 1: the span (N - 2,) s between its neighbours and where it
    lies on it (0..1; 0 where the span is not positive)."""
    span = times[2:] - times[:-2]
    return span, (times[1:-1] - times[:-2]) / np.where(span > 0, span, np.inf)


def _on_line(
    before: np.ndarray, here: np.ndarray, after: np.ndarray, frac: np.ndarray, rtol: float
) -> np.ndarray:
    """(M,) whether every channel of ``here`` (M, C) lies within ``rtol * max(1, |value|)``
    of the line from ``before`` to ``after`` at fraction ``frac`` (M,)."""
    off_line = np.abs(here - before - (after - before) * frac[:, None])
    return np.all(off_line <= rtol * np.maximum(1.0, np.abs(here)), axis=1)


def interpolated_imu_samples(
    t: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    accel: torch.Tensor | np.ndarray,
    min_samples: int = 10,
    rtol: float = 1e-6,
) -> np.ndarray:
    """(N,) bool: the samples of one IMU stream that were filled in by linear interpolation.

    Args:
        t: (N,) sample times, s, increasing.
        gyro: (N, 3) angular rate, rad/s.
        accel: (N, 3) specific force, m/s^2.
        min_samples: shortest run of collinear interior samples that counts (0 disables).
        rtol: a sample is collinear when every channel's distance from the line through its
            two neighbours is at most ``rtol * max(1, |value|)`` (rounding of the file's
            text, not sensor noise).

    Returns:
        (N,) numpy bool; the first and last samples of a stretch (the real samples it joins)
        are not marked.
    """
    if min_samples < 0:
        raise ValueError(f"min_samples must be >= 0, got {min_samples}")
    times, values = _imu_arrays(t, gyro, accel)
    n = times.shape[0]
    out = np.zeros(n, dtype=bool)
    if min_samples == 0 or n < 3:
        return out
    span, frac = _line_fractions(times)

    def runs(flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start and end (exclusive) of the runs of True in ``flags`` that are long enough."""
        starts, ends = filled_stretches(flags)
        long = ends - starts >= min_samples
        return starts[long], ends[long]

    # candidates from one channel with the loosest tolerance of the stream (a superset)
    gyro_z = values[:, 2]
    line = gyro_z[:-2] + (gyro_z[2:] - gyro_z[:-2]) * frac
    loose = rtol * max(1.0, float(np.abs(gyro_z).max()))
    starts, ends = runs((np.abs(gyro_z[1:-1] - line) <= loose) & (span > 0))
    if starts.size == 0:
        return out
    # every channel of every candidate sample, at its own tolerance
    rows = np.concatenate([np.arange(a, b) for a, b in zip(starts, ends, strict=True)])
    confirmed = np.zeros(n - 2, dtype=bool)
    confirmed[rows] = _on_line(values[rows], values[rows + 1], values[rows + 2], frac[rows], rtol)
    for a, b in zip(*runs(confirmed), strict=True):
        out[a + 1 : b + 1] = True  # index k of the interior arrays is sample k + 1
    return out


def open_stretch_start(
    t: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    accel: torch.Tensor | np.ndarray,
    rtol: float = 1e-6,
) -> int | None:
    """Where a filled-in stretch that may go on past the stream's end begins.

    The samples before the last that lie on the line through their neighbours, every
    channel within ``rtol * max(1, |value|)`` (the test of :func:`interpolated_imu_samples`),
    and reach the last-but-one sample: the stream may stop inside a stretch whose length is
    not known yet (a piece of a recording).

    Args:
        t: (N,) sample times, s, increasing.
        gyro: (N, 3) angular rate, rad/s.
        accel: (N, 3) specific force, m/s^2.
        rtol: as :func:`interpolated_imu_samples`.

    Returns:
        the index of the real sample the trailing run of collinear samples starts from (the
        samples after it may be filled in), or None when the last-but-one sample is not
        collinear (or N < 3).
    """
    times, values = _imu_arrays(t, gyro, accel)
    if times.shape[0] < 3:
        return None
    span, frac = _line_fractions(times)
    collinear = _on_line(values[:-2], values[1:-1], values[2:], frac, rtol) & (span > 0)
    if not collinear[-1]:
        return None
    off = np.flatnonzero(~collinear)
    return int(off[-1] + 1) if off.size else 0  # collinear[k] is sample k + 1


def filled_stretches(flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Runs of True in a (N,) bool array, e.g. :func:`interpolated_imu_samples`' flags.

    Returns:
        (K,) first index and (K,) end index (exclusive) of each run; for filled-in IMU
        samples, ``first - 1`` and ``end`` are the real samples the stretch joins.
    """
    edges = np.diff(np.asarray(flags).astype(np.int8), prepend=np.int8(0), append=np.int8(0))
    return np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]


def outside_stretches(
    t: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    accel: torch.Tensor | np.ndarray,
    mask: torch.Tensor | np.ndarray,
    min_samples: int = 10,
) -> np.ndarray:
    """Where a chunk boundary at each sample of one IMU stream moves to, so that no chunk
    boundary cuts a filled-in stretch (the filter then models each stretch as one gap, as in
    the run in one piece).

    Args:
        t: (N,) sample times, s (masked samples in place).
        gyro: (N, 3) angular rate, rad/s.
        accel: (N, 3) specific force, m/s^2.
        mask: (N,) bool, real samples; the stretches are found among these
            (:func:`interpolated_imu_samples`).
        min_samples: as :func:`interpolated_imu_samples`.

    Returns:
        (N,) int64 sample index: the sample itself, or for a sample inside a filled-in
        stretch (from its first filled-in sample up to the real sample that ends it,
        exclusive) that ending real sample. A stretch's ending sample maps to itself.
    """
    real = np.flatnonzero(
        np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor) else mask)
    )
    times, values = _imu_arrays(t, gyro, accel)
    filled = interpolated_imu_samples(times[real], values[real, :3], values[real, 3:], min_samples)
    moved = np.arange(times.shape[0])
    for first, end in zip(*filled_stretches(filled), strict=True):
        moved[real[first] : real[end]] = real[end]
    return moved


def gap_walk_scale(length: torch.Tensor, walk: torch.Tensor, density: torch.Tensor) -> torch.Tensor:
    """Extra white-noise variance of an IMU sample held over a gap, as a multiplier of the
    sensor's own noise variance: ``(q / n)^2 T^2 / 3`` per channel.

    Over a gap of ``T`` s the true rate and specific force leave the held sample as a
    random walk of density ``q``; its integral over the gap has variance ``q^2 T^3 / 3``.
    White noise of density ``q^2 T^2 / 3`` on each piece held in the gap gives the gap that
    variance whatever epochs or keyframes cut it. The front end and the smoothers add this
    to ``imu_gap_noise_scale``.

    Args:
        length: (...,) the gap each sample is held over, s (0: a measured sample).
        walk: (6,) ``q``: gyro x, y, z (rad/s^2/sqrt(Hz)) then accelerometer (m/s^3/sqrt(Hz)).
        density: (..., 6) or (6,) ``n``, the sensors' white-noise densities, broadcast
            against ``length[..., None]``.

    Returns:
        (..., 6) multipliers (0 where ``length`` is 0).
    """
    return (walk / density) ** 2 * length[..., None] ** 2 / 3.0
