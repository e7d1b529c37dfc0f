"""Values (not only Jacobians) of the planar residuals, against closed forms.

The factor tests check these residuals' Jacobians by differencing the residual itself, so a
residual that measures the wrong quantity passes them. Here:

* ``plane_residual``: pose j is pose i moved by ``R_i [dx, dy, h]`` and turned by
  ``Exp(phi)`` in i's frame, so the residual is exactly ``[phi_x, phi_y, h]``.
* ``wheel_increment_residual``: the yaw row is wrapped into ``(-pi, pi]``: a relative yaw of
  ``-3.1`` rad against an increment of ``3.0`` rad is ``2 pi - 6.1`` rad, not ``-6.1``.
"""

from __future__ import annotations

import math

import torch

from msf_torch.geometry import so3
from msf_torch.sensors.plane import plane_residual
from msf_torch.sensors.wheel import wheel_increment_residual

DTYPE = torch.float64


def test_plane_residual_is_relative_roll_pitch_and_height_in_frame_i():
    rotation_i = so3.exp(torch.tensor([[0.3, -0.2, 1.0], [-0.1, 0.4, -2.5]], dtype=DTYPE))
    position_i = torch.tensor([[1.0, -2.0, 0.5], [-4.0, 3.0, 2.0]], dtype=DTYPE)
    local = torch.tensor([[1.5, 2.0, 0.25], [-0.7, 0.3, -0.4]], dtype=DTYPE)  # [dx, dy, h]
    phi = torch.tensor([[0.05, -0.02, 0.7], [-0.03, 0.04, -1.2]], dtype=DTYPE)
    position_j = position_i + (rotation_i @ local[..., None]).squeeze(-1)
    rotation_j = rotation_i @ so3.exp(phi)
    residual = plane_residual(position_i, rotation_i, position_j, rotation_j)
    expected = torch.stack((phi[:, 0], phi[:, 1], local[:, 2]), -1)
    torch.testing.assert_close(residual, expected, rtol=0, atol=1e-12)


def test_wheel_increment_yaw_residual_is_wrapped():
    yaw_i, turn = 0.4, -3.1
    rotation_i = so3.exp(torch.tensor([[0.0, 0.0, yaw_i]], dtype=DTYPE))
    rotation_j = so3.exp(torch.tensor([[0.0, 0.0, yaw_i + turn]], dtype=DTYPE))
    position_i = torch.tensor([[2.0, 1.0, 0.0]], dtype=DTYPE)
    local = torch.tensor([[0.8, -0.3, 0.0]], dtype=DTYPE)
    position_j = position_i + (rotation_i @ local[..., None]).squeeze(-1)
    increment = torch.tensor([[0.8, -0.3, 3.0]], dtype=DTYPE)
    residual, _, _ = wheel_increment_residual(
        position_i, rotation_i, position_j, rotation_j, increment, torch.zeros(3, dtype=DTYPE)
    )
    expected = torch.tensor([[0.0, 0.0, turn - 3.0 + 2.0 * math.pi]], dtype=DTYPE)
    torch.testing.assert_close(residual, expected, rtol=0, atol=1e-12)
