"""Unit checks on a loaded sequence: catch the usual unit mistakes before they become a
diverging filter (``msf run`` applies :func:`check_units` to every input).

The estimator wants time in seconds, angular rate in rad/s and specific force in m/s^2
including gravity. Each check tests a property any recording of a wheeled robot or a car
has, whatever it does, with wide margins:

* IMU time step: the median step lies in [1e-5, 0.5] s (an IMU samples at 2 Hz to 100 kHz;
  times in nanoseconds or milliseconds give steps of 1e7 or 10 "s");
* accelerometer: the median ``|a|`` over the run lies within 0.5-2 g (gravity dominates the
  specific force of a ground vehicle; data in g reads about 1, data with gravity removed
  about 0);
* gyro: the 99th percentile of ``|w|`` is below 20 rad/s (1146 deg/s; a turning vehicle
  stays under a few rad/s, while deg/s read as rad/s gives tens);
* gyro against wheels (when the run has wheel speeds and turns): the yaw rate (the gyro
  along the mean accelerometer direction, the body's up) over the wheels' differential
  speed ``v_r - v_l`` (median ratio over the turning 1-s bins) is ``1 / track``, 0.3-5
  1/m for tracks of 0.2-3 m; above 20 1/m (a 5 cm track) the gyro reads in deg/s (57x) or
  the wheel speeds are not in m/s. This catches deg/s on slowly turning robots, where the
  first gyro check cannot.
* magnetometer (when the run has one): the median raw ``|m|`` lies within 5-1000 uT (the
  earth's field is 25-65 uT, and hard iron near motors can add a few hundred; gauss reads
  about 0.5, tesla about 5e-5, nanotesla about 5e4). Milligauss (250-650) passes: it is
  10x the microtesla it should be, which the magnitude check of the front end does not
  mind (it compares with the run's own median) but a configured
  ``magnetometer_field_uT`` or hard iron does.

A recording that fails a check is not usable as it is: the message says which stream, what
was measured and the likely fix.
"""

from __future__ import annotations

__all__ = ["UNIT_LIMITS", "unit_problems", "check_units"]

import torch

from msf_torch.io.errors import DataError
from msf_torch.types import Sequence

STANDARD_GRAVITY = 9.80665
"""m/s^2."""

UNIT_LIMITS = {
    "imu_step_s": (1e-5, 0.5),
    "accel_median_g": (0.5, 2.0),
    "gyro_p99_radps": 20.0,
    "yaw_per_wheel_difference_per_m": 20.0,
    "magnetometer_median_uT": (5.0, 1000.0),
}
"""The ranges :func:`unit_problems` accepts (module docstring)."""


def unit_problems(seq: Sequence) -> list[str]:
    """Unit problems of each sequence's IMU stream (empty: plausible).

    Args:
        seq: B sequences; only real (masked) IMU samples count.
    Returns:
        one message per problem, naming the quantity and the likely fix (and the sequence,
        when B > 1).
    """
    problems: list[str] = []
    low_step, high_step = UNIT_LIMITS["imu_step_s"]
    low_g, high_g = UNIT_LIMITS["accel_median_g"]
    rates_hz = seq.imu.median_rate_hz()
    for b, name in enumerate(seq.names):
        prefix = f"{name}: " if seq.batch_size > 1 else ""
        keep = seq.imu.mask[b]
        if int(keep.sum()) < 3:
            continue
        t = seq.imu.t[b, keep]
        step = 1.0 / float(rates_hz[b])
        if not low_step <= step <= high_step:
            hint = (
                "nanoseconds? divide by 1e9; milliseconds? divide by 1e3"
                if step > high_step
                else "times must be in seconds"
            )
            span = float(t[-1] - t[0])
            problems.append(
                f"{prefix}IMU samples are a median {step:.4g} s apart (span {span:.4g} s); the "
                f"estimator needs times in seconds ({hint})"
            )
        accel = float(seq.imu.accel[b, keep].norm(dim=-1).median())
        if not low_g * STANDARD_GRAVITY <= accel <= high_g * STANDARD_GRAVITY:
            problems.append(
                f"{prefix}the accelerometer's median |a| is {accel:.4g} where gravity alone gives "
                f"{STANDARD_GRAVITY:.2f}; the estimator needs specific force in m/s^2 with "
                "gravity (in g? multiply by 9.80665; gravity removed by the driver? use its raw "
                "acceleration)"
            )
        speeds = seq.imu.gyro[b, keep].norm(dim=-1)
        rate = float(speeds.kthvalue(max(1, int(0.99 * speeds.numel()))).values)
        if rate > UNIT_LIMITS["gyro_p99_radps"]:
            problems.append(
                f"{prefix}the gyro's 99th percentile |w| is {rate:.4g} rad/s "
                f"({rate * 180 / torch.pi:.4g} deg/s); the estimator needs rad/s (in deg/s? "
                "multiply by pi/180)"
            )
        else:
            slope = _yaw_per_wheel_difference(seq, b)
            if slope is not None and abs(slope) > UNIT_LIMITS["yaw_per_wheel_difference_per_m"]:
                problems.append(
                    f"{prefix}the gyro's yaw rate is {abs(slope):.3g} x the wheels' speed "
                    "difference (1 / track: 0.3-5 for a track of 0.2-3 m); the gyro in deg/s "
                    "(x 57)? multiply it by pi/180; else the wheel speeds are not in m/s"
                )
        field = _magnetometer_median(seq, b)
        low_field, high_field = UNIT_LIMITS["magnetometer_median_uT"]
        if field is not None and not low_field <= field <= high_field:
            problems.append(
                f"{prefix}the magnetometer's median |m| is {field:.4g} where the earth's field "
                "is 25-65 uT; the estimator needs microtesla (in gauss? multiply by 100; in "
                "tesla, as ROS sensor_msgs/MagneticField? by 1e6; in nanotesla? divide by 1000)"
            )
    return problems


def _magnetometer_median(seq: Sequence, b: int) -> float | None:
    """Median raw magnitude of sequence ``b``'s magnetometer readings, or None without at
    least 3."""
    stream = seq.magnetometer
    if stream is None or int(stream.mask[b].sum()) < 3:
        return None
    return float(stream.field[b, stream.mask[b]].norm(dim=-1).median())


def _yaw_per_wheel_difference(seq: Sequence, b: int) -> float | None:
    """Median ratio (1/m) of the gyro's yaw rate to the wheels' ``v_r - v_l`` of sequence
    ``b`` over the 1-s bins that turn (binned difference above 0.05 m/s; the median keeps
    wheel-slip bins from swaying it); None without wheels, or with under 10 bins or
    under 5 turning ones."""
    wheel = seq.wheel
    if wheel is None or int(wheel.mask[b].sum()) < 2:
        return None
    keep = wheel.mask[b]
    t_wheel = wheel.t[b, keep]
    imu = seq.imu.mask[b]
    up = seq.imu.accel[b, imu].mean(0)
    yaw = seq.imu.gyro[b, imu] @ (up / up.norm().clamp_min(1e-12))
    t_imu = seq.imu.t[b, imu]
    edges = torch.arange(float(t_wheel[0]), float(t_wheel[-1]), 1.0, dtype=t_wheel.dtype)
    if edges.numel() < 11:
        return None

    def binned(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        bins = torch.bucketize(t, edges, right=True) - 1
        inside = (bins >= 0) & (bins < edges.numel() - 1)
        total = torch.zeros(edges.numel() - 1, dtype=x.dtype).index_add_(0, bins[inside], x[inside])
        count = torch.zeros_like(total).index_add_(0, bins[inside], torch.ones_like(x[inside]))
        return total / count.clamp_min(1.0)

    difference = binned(t_wheel, wheel.right_speed[b, keep] - wheel.left_speed[b, keep])
    rate = binned(t_imu, yaw)
    turning = difference.abs() > 0.05
    if int(turning.sum()) < 5:
        return None
    return float((rate[turning] / difference[turning]).median())


def check_units(seq: Sequence, source: str | None = None) -> None:
    """Raise when :func:`unit_problems` finds any.

    Args:
        seq: the loaded sequence(s).
        source: the file or folder they came from, for the message (default: the
            sequence's ``meta["source"]``).
    Raises:
        DataError: naming ``source`` and every problem found.
    """
    problems = unit_problems(seq)
    if problems:
        where = source if source is not None else str(seq.meta.get("source", seq.names[0]))
        raise DataError(where, "; ".join(problems))
