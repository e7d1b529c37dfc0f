"""Per-axis noise scales in ``sensors.imu.preintegrate``'s covariance.

Reference: the exact sample-by-sample recursion ``e_{k+1} = A_k e_k + B_k n_k``
(``backend.preintegration.recursive_covariance``, itself checked against autograd noise
Jacobians), with one variance multiplier per body axis, at rates that turn a sample by up
to about a radian (a gap's long held piece), and with padding (``dt = 0``).
"""

from __future__ import annotations

import pytest
import torch

from msf_torch.backend.preintegration import recursive_covariance
from msf_torch.sensors.imu import preintegrate

DTYPE = torch.float64


@pytest.mark.parametrize("batch", [1, 10])
def test_per_axis_covariance_equals_the_exact_recursion(batch):
    gen = torch.Generator().manual_seed(batch)
    length = 7

    def rand(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=DTYPE)

    gyro = 1.5 * rand(batch, length, 3)
    accel = 3.0 * rand(batch, length, 3) + torch.tensor([0.0, 0.0, 9.81], dtype=DTYPE)
    dt = 0.6 * torch.rand(batch, length, generator=gen, dtype=DTYPE)
    dt[0, -2:] = 0.0  # padding
    gyro_bias, accel_bias = 0.01 * rand(batch, 3), 0.1 * rand(batch, 3)
    scale = 1.0 + 100.0 * torch.rand(batch, length, 6, generator=gen, dtype=DTYPE)
    pre = preintegrate(gyro, accel, dt, gyro_bias, accel_bias, scale)
    cov_g, cov_a = recursive_covariance(
        gyro, accel, dt, gyro_bias, accel_bias, scale[..., :3], scale[..., 3:]
    )
    torch.testing.assert_close(pre.cov_unit_gyro, cov_g, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(pre.cov_unit_accel, cov_a, rtol=1e-10, atol=1e-14)
    # the increments and bias Jacobians do not depend on the noise scales
    plain = preintegrate(gyro, accel, dt, gyro_bias, accel_bias)
    for name in ("delta_rotation", "delta_velocity", "delta_position", "bias_jacobian"):
        assert torch.equal(getattr(pre, name), getattr(plain, name)), name
