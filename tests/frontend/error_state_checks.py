"""Shared helpers for tests of error-state measurement models: a random batch of
navigation states, the conventions' perturbation and central differences; a filter run's
navigation errors against a simulated truth; a level, non-turning IMU + GNSS sequence (the
linear-Gaussian reduction of the filter)."""

from __future__ import annotations

import numpy as np
import torch

from msf_torch.geometry import so3
from msf_torch.types import GnssFixes, ImuSamples, Sequence

DTYPE = torch.float64
EPS = 1e-6


def random_state(gen: torch.Generator, batch: int = 4) -> dict[str, torch.Tensor]:
    """A batch of navigation states: position (B, 3) m, velocity (B, 3) m/s, rotation
    (B, 3, 3), gyro bias (B, 3) rad/s, accel bias (B, 3) m/s^2."""

    def randn(*shape, scale=1.0):
        return scale * torch.randn(batch, *shape, generator=gen, dtype=DTYPE)

    return {
        "position": randn(3, scale=20.0),
        "velocity": randn(3, scale=3.0),
        "rotation": so3.exp(randn(3, scale=1.5)),
        "gyro_bias": randn(3, scale=0.01),
        "accel_bias": randn(3, scale=0.05),
    }


def boxplus(state: dict[str, torch.Tensor], dx: torch.Tensor) -> dict[str, torch.Tensor]:
    """Conventions' perturbation by dx (B, 15): p + dp, v + dv, R Exp(dtheta), b + db."""
    return {
        "position": state["position"] + dx[:, 0:3],
        "velocity": state["velocity"] + dx[:, 3:6],
        "rotation": state["rotation"] @ so3.exp(dx[:, 6:9]),
        "gyro_bias": state["gyro_bias"] + dx[:, 9:12],
        "accel_bias": state["accel_bias"] + dx[:, 12:15],
    }


def central_differences(fn, size: int, batch: int) -> torch.Tensor:
    """(B, rows, size) central differences of fn(dx (B, size)) -> (B, rows), step EPS."""
    cols = []
    for k in range(size):
        step = torch.zeros(batch, size, dtype=DTYPE)
        step[:, k] = EPS
        cols.append((fn(step) - fn(-step)) / (2 * EPS))
    return torch.stack(cols, -1)


CHI2_95_9DOF = 16.919  # scipy.stats.chi2.ppf(0.95, 9)


def navigation_errors(result, runs, b: int):
    """Times (E,) s, ``[dp, dv, dtheta]`` errors (E, 9) of sequence ``b`` of an
    ``EskfResult`` against ``runs[b].truth`` (a simulated run), and the filter's (E, 9, 9)
    covariance, at the real epochs (every one an IMU sample of the truth)."""
    keep = result.mask[b]
    t = result.t[b, keep]
    truth = runs[b].truth
    j = torch.searchsorted(truth.t[0], t).clamp(max=truth.t.shape[1] - 1)
    assert float((truth.t[0, j] - t).abs().max()) < 1e-9
    error = torch.cat(
        (
            result.position[b, keep] - truth.position[0, j],
            result.velocity[b, keep] - truth.velocity[0, j],
            so3.log(truth.rotation[0, j].mT @ result.rotation[b, keep]),
        ),
        -1,
    )
    return t, error, result.covariance[b, keep][:, :9, :9]


def nees_inside_fraction(result, runs, after_s: float = 5.0) -> float:
    """Fraction of the epochs after ``after_s`` (s) of every sequence of ``result`` whose
    position, velocity and attitude NEES lies below the 95 % chi-square bound (9 dof)."""
    inside = []
    for b in range(len(runs)):
        t, error, cov = navigation_errors(result, runs, b)
        nees = (error[:, None, :] @ torch.linalg.solve(cov, error[..., None]))[:, 0, 0]
        inside.append((nees[t > after_s] < CHI2_95_9DOF).double())
    return float(torch.cat(inside).mean())


def level_sequence(
    name: str,
    t: np.ndarray,
    specific_force: np.ndarray,
    fix_index: np.ndarray,
    fixes: np.ndarray,
    sigma: np.ndarray,
) -> Sequence:
    """A B = 1 sequence of a level body that does not turn (the gyro reads 0): IMU at times
    ``t`` (N,) s with ``specific_force`` (N, 3) m/s^2, and GNSS ``fixes`` (M, 3) m with
    their ``sigma`` (M, 3) m at the IMU samples ``fix_index`` (M,)."""
    n = t.size
    seq = Sequence(
        names=[name],
        imu=ImuSamples(
            t=torch.as_tensor(t)[None],
            gyro=torch.zeros(1, n, 3, dtype=DTYPE),
            accel=torch.as_tensor(specific_force)[None],
            mask=torch.ones(1, n, dtype=torch.bool),
        ),
        gnss=GnssFixes(
            t=torch.as_tensor(t[fix_index])[None],
            position=torch.as_tensor(fixes)[None],
            sigma=torch.as_tensor(sigma)[None],
            mask=torch.ones(1, fix_index.size, dtype=torch.bool),
        ),
    )
    seq.check()
    return seq
