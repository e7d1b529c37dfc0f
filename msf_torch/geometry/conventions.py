"""The one error-state convention of msf_torch, written once and imported everywhere.

Frames
    ``world`` is a local, gravity-aligned East-North-Up frame (z up). ``body`` is the IMU
    frame (x forward, y left, z up for a vehicle). A rotation ``R`` (..., 3, 3) maps body
    vectors to world vectors: ``x_world = R @ x_body``.

Quaternions
    Hamilton, scalar first: ``q = [w, x, y, z]`` (pytorch_kinematics order). TUM files use
    ``[x, y, z, w]`` and are converted on read and write.

Gravity
    ``GRAVITY_WORLD = [0, 0, -g]``. The accelerometer measures specific force
    ``f = R^T (a - g_world)``, so a level IMU at rest reads ``[0, 0, +g]``.

Nominal state and error state
    Nominal: position ``p`` (world, m), velocity ``v`` (world, m/s), rotation ``R``,
    gyro bias ``b_g`` (rad/s), accel bias ``b_a`` (m/s^2).
    Error state ``dx = [dp, dv, dtheta, db_g, db_a]`` (15,) with
    ``p = p_hat + dp``, ``v = v_hat + dv``, ``R = R_hat @ Exp(dtheta)`` (right, body-side
    perturbation), ``b = b_hat + db``.

Residuals
    ``r = h(x) - z`` (prediction minus measurement). Jacobians are ``dr/d(dx)`` at dx = 0.
    A rotation residual is ``Log(R_z^T R)``.
"""

from __future__ import annotations

__all__ = [
    "STANDARD_GRAVITY",
    "ERROR_STATE_DIM",
    "IDX_P",
    "IDX_V",
    "IDX_THETA",
    "IDX_BG",
    "IDX_BA",
    "gravity_world",
]

import torch

STANDARD_GRAVITY = 9.80665
"""Standard gravity in m/s^2."""

ERROR_STATE_DIM = 15
IDX_P = slice(0, 3)
IDX_V = slice(3, 6)
IDX_THETA = slice(6, 9)
IDX_BG = slice(9, 12)
IDX_BA = slice(12, 15)


def gravity_world(
    magnitude: float = STANDARD_GRAVITY,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Gravity vector in the world frame, ``[0, 0, -magnitude]`` (3,) in m/s^2."""
    return torch.tensor([0.0, 0.0, -magnitude], dtype=dtype, device=device)
