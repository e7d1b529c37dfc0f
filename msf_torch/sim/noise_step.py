"""A sudden change of measurement noise: GNSS fixes that get noisier at a known time.

The receiver does not notice (urban canyon, multipath, a degraded antenna): from
``t_change_s`` on each fix carries ``k`` times its original noise while its declared
``sigma`` stays as it was. The simulator's fixes already hold ``N(0, sigma^2)`` per axis, so
independent ``N(0, (k^2 - 1) sigma^2)`` is added to reach ``k sigma``.

Example:
    >>> from msf_torch.sim import SimConfig, simulate_run
    >>> run = simulate_run(SimConfig(duration_s=20.0), seed=3)
    >>> noisy = gnss_noise_step(run.sequence, t_change_s=10.0, sigma_scale=6.0, seed=3)
    >>> bool((noisy.gnss.sigma == run.sequence.gnss.sigma).all())
    True
"""

from __future__ import annotations

__all__ = ["gnss_noise_step"]

import dataclasses
import math

import torch

from msf_torch.types import Sequence


def gnss_noise_step(
    sequence: Sequence, t_change_s: float, sigma_scale: float, seed: int
) -> Sequence:
    """The sequence with every GNSS fix at ``t >= t_change_s`` carrying ``sigma_scale`` times
    its declared per-axis noise; the declared ``sigma`` is left unchanged.

    Args:
        sequence: B sequences with GNSS fixes whose noise is the declared sigma.
        t_change_s: time of the change, s.
        sigma_scale: k >= 1, noise multiplier after the change.
        seed: seed of the added noise (a ``torch.Generator`` on the CPU).
    Returns:
        A new :class:`~msf_torch.types.Sequence` (other streams shared, not copied); its
        ``meta["noise_step"]`` records the change.
    Raises:
        ValueError: no GNSS, ``sigma_scale < 1``, or a declared sigma that is not finite.
    """
    gnss = sequence.gnss
    if gnss is None:
        raise ValueError("gnss_noise_step: the sequence has no GNSS fixes")
    if not (math.isfinite(sigma_scale) and sigma_scale >= 1.0):
        raise ValueError(f"gnss_noise_step: sigma_scale must be >= 1, got {sigma_scale!r}")
    after = (gnss.t >= t_change_s) & gnss.mask
    if not bool(torch.isfinite(gnss.sigma[after]).all()):
        raise ValueError("gnss_noise_step: fixes after the change need a finite declared sigma")
    generator = torch.Generator().manual_seed(int(seed))
    unit = torch.randn(gnss.position.shape, generator=generator, dtype=gnss.position.dtype)
    extra = unit.to(gnss.position.device) * gnss.sigma.nan_to_num(0.0)
    extra = extra * math.sqrt(sigma_scale**2 - 1.0) * after[..., None]
    noisy = dataclasses.replace(gnss, position=gnss.position + extra)
    meta = dict(sequence.meta)
    meta["noise_step"] = {"sensor": "gnss", "t_change_s": t_change_s, "sigma_scale": sigma_scale}
    return dataclasses.replace(sequence, gnss=noisy, meta=meta)
