"""Shared builders for the io tests."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.types import (
    GnssFixes,
    ImuSamples,
    PoseMeasurements,
    Sequence,
    Trajectory,
    WheelSamples,
)


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64).unsqueeze(0)


def _mask(n: int) -> torch.Tensor:
    return torch.ones((1, n), dtype=torch.bool)


def _unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q


def make_sequence(seed: int = 0, n_imu: int = 50) -> Sequence:
    """A B = 1 sequence with every stream, labels and sensor meta (irrational-ish numbers)."""
    rng = np.random.default_rng(seed)
    t_imu = 100.0 + np.cumsum(rng.uniform(0.004, 0.006, n_imu))
    imu = ImuSamples(
        t=_t(t_imu),
        gyro=_t(rng.normal(size=(n_imu, 3))),
        accel=_t(rng.normal(size=(n_imu, 3)) + [0, 0, 9.81]),
        mask=_mask(n_imu),
    )
    n_w = 20
    wheel = WheelSamples(
        t=_t(100.0 + np.arange(n_w) / 7.0),
        left_speed=_t(rng.normal(size=n_w)),
        right_speed=_t(rng.normal(size=n_w)),
        mask=_mask(n_w),
    )
    n_g = 5
    gnss = GnssFixes(
        t=_t(100.0 + np.arange(n_g) / 3.0),
        position=_t(rng.normal(size=(n_g, 3)) * 100),
        sigma=_t(rng.uniform(0.1, 2.0, size=(n_g, 3))),
        mask=_mask(n_g),
    )
    n_p = 6
    a = rng.normal(size=(n_p, 6, 6))
    cov = a @ np.swapaxes(a, 1, 2) * 1e-3
    poses = PoseMeasurements(
        t=_t(100.0 + np.arange(n_p) / 11.0),
        position=_t(rng.normal(size=(n_p, 3))),
        quaternion=_t(_unit_quats(rng, n_p)),
        covariance=_t(cov),
        mask=_mask(n_p),
    )
    n_gt = 30
    gt = Trajectory(
        t=_t(100.0 + np.arange(n_gt) / 13.0),
        position=_t(rng.normal(size=(n_gt, 3))),
        quaternion=_t(_unit_quats(rng, n_gt)),
        mask=_mask(n_gt),
    )
    labels = {
        "slip": torch.tensor([[[100.01, 100.05], [100.1, 100.2]]], dtype=torch.float64),
        "weather:rain": torch.tensor([[[100.0, 100.3]]], dtype=torch.float64),
    }
    meta = {"sensor": {"wheel_track_m": 0.5, "imu_noise": {"gyro_noise_density": 1.7e-4}}}
    return Sequence(
        names=["synthetic"],
        imu=imu,
        wheel=wheel,
        gnss=gnss,
        poses=poses,
        ground_truth=gt,
        labels=labels,
        meta=meta,
    )


@pytest.fixture
def sequence() -> Sequence:
    """A synthetic B = 1 sequence with every stream (seed 0)."""
    return make_sequence()


@pytest.fixture
def sequence_factory():
    """``make_sequence(seed=0, n_imu=50)`` for tests that need several sequences."""
    return make_sequence


def enu_longdouble(lat, lon, alt, origin) -> np.ndarray:
    """ECEF difference rotated into ENU, all in extended precision (80-bit on x86)."""
    ld = np.longdouble
    a, f = ld(6378137.0), ld(1) / ld("298.257223563")
    e2 = f * (2 - f)
    deg = ld(np.pi) / 180

    def ecef(la, lo, h):
        la, lo, h = (
            np.asarray(la, dtype=ld) * deg,
            np.asarray(lo, dtype=ld) * deg,
            np.asarray(h, dtype=ld),
        )
        n = a / np.sqrt(1 - e2 * np.sin(la) ** 2)
        return np.stack(
            (
                (n + h) * np.cos(la) * np.cos(lo),
                (n + h) * np.cos(la) * np.sin(lo),
                (n * (1 - e2) + h) * np.sin(la),
            ),
            -1,
        )

    d = ecef(lat, lon, alt) - ecef(*origin)
    la, lo = ld(origin[0]) * deg, ld(origin[1]) * deg
    rot = np.array(
        [
            [-np.sin(lo), np.cos(lo), ld(0)],
            [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
            [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
        ]
    )
    return (d @ rot.T).astype(np.float64)


@pytest.fixture
def enu_reference():
    """:func:`enu_longdouble`: the textbook ENU of geodetic points, in extended precision."""
    return enu_longdouble
