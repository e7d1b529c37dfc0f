"""Wheel slip factor.

Before each wheel update the wheel's speed and yaw rate are compared with the filter's
prediction (IMU-propagated velocity, bias-corrected gyro yaw rate). With ``d`` the wheel
residual rows 0 (speed) and 3 (yaw rate) and ``s_i`` their innovation variances,

    q = d_v^2 / s_v + d_w^2 / s_w,      f_raw = exp(-q / (2 k^2))

(k = ``slip_sensitivity``). The factor drops at once and recovers at most at
``slip_recovery_per_s`` per second: ``f = min(f_raw, f_prev + rate * dt)``. The wheel
noise sigma is divided by ``f`` and updates are skipped below ``slip_skip_below``. 1 means
no slip.
"""

from __future__ import annotations

__all__ = ["slip_factor"]

import torch


def slip_factor(
    wheel_residual: torch.Tensor,
    innovation_var: torch.Tensor,
    previous: torch.Tensor,
    elapsed_s: torch.Tensor,
    sensitivity: float,
    recovery_per_s: float,
) -> torch.Tensor:
    """Slip factor (B,) in [0, 1].

    Args:
        wheel_residual: (B, 4) wheel residual ``h - z`` (speed, lateral, vertical, yaw rate).
        innovation_var: (B, 4) diagonal of the innovation covariance of those rows.
        previous: (B,) factor at the previous wheel epoch.
        elapsed_s: (B,) time since that epoch, s.
        sensitivity: k, in normalised units.
        recovery_per_s: maximum rise of the factor per second.
    """
    q = (
        wheel_residual[:, 0] ** 2 / innovation_var[:, 0]
        + wheel_residual[:, 3] ** 2 / (innovation_var[:, 3])
    )
    raw = torch.exp(-q / (2.0 * sensitivity**2))
    return torch.minimum(raw, (previous + recovery_per_s * elapsed_s).clamp(max=1.0))
