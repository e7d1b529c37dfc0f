"""Recorder artefacts on a simulated run: IMU stretches filled in by interpolation.

Some loggers (the KITTI drive's among them) fill a stretch of missed IMU samples with the
straight line between the samples around it; the front end finds such stretches
(:func:`msf_torch.sensors.imu_gaps.interpolated_imu_samples`) and treats them as gaps.
"""

from __future__ import annotations

__all__ = ["fill_imu_stretch"]

import dataclasses

import torch

from msf_torch.types import Sequence


def fill_imu_stretch(seq: Sequence, start_s: float, end_s: float) -> Sequence:
    """``seq`` (B = 1) with its IMU samples strictly between the samples at ``start_s`` and
    ``end_s`` (s; the first samples at or after those times) replaced by the straight line
    between those two, gyro and accelerometer alike. Other streams are kept."""
    if seq.batch_size != 1:
        raise ValueError(f"fill_imu_stretch takes one sequence (B = 1), got B = {seq.batch_size}")
    t = seq.imu.t[0]
    first, last = (
        int(torch.searchsorted(t, torch.tensor(x, dtype=t.dtype, device=t.device)))
        for x in (start_s, end_s)
    )
    if not 0 <= first < last < t.numel():
        raise ValueError(f"no IMU samples to fill between {start_s} and {end_s} s")
    frac = ((t[first : last + 1] - t[first]) / (t[last] - t[first]))[:, None]

    def fill(x: torch.Tensor) -> torch.Tensor:
        x = x.clone()
        x[0, first : last + 1] = x[0, first] + (x[0, last] - x[0, first]) * frac
        return x

    imu = dataclasses.replace(seq.imu, gyro=fill(seq.imu.gyro), accel=fill(seq.imu.accel))
    return dataclasses.replace(seq, imu=imu)
