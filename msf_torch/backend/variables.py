"""Variable kinds of the back end: how values are stored and how a tangent step is applied.

Every kind stores a value as a flat vector (..., S) and moves on its tangent space (..., D)
with the project's one convention (:mod:`msf_torch.geometry.conventions`): vectors add,
rotations are perturbed on the right, ``R = R_hat Exp(dtheta)``.

============ ======================================= ========================================
kind         storage (S)                             tangent (D)
============ ======================================= ========================================
nav_state    [p(3), v(3), R(9, row-major), b_g, b_a] 15: [dp, dv, dtheta, db_g, db_a]
pose         [p(3), R(9, row-major)]                 6: [dp, dtheta]
se3          [p(3), R(9, row-major)]                 6: [rho, phi], ``T <- T exp(xi)``
point        [x, y, z]                               3
wheel_calib  [k_l, k_r, D]                           3
============ ======================================= ========================================

``se3`` is the Lie-group chart of pose graphs (GTSAM's ``Pose3`` retraction): the step is
body-frame, ``R <- R Exp(phi)``, ``p <- p + R Gamma_1(phi) rho``. Relative-pose residuals
are nearly linear in it, so pose-graph LM needs fewer iterations than with ``pose``.

``wheel_calib`` holds a run's wheel calibration (:mod:`msf_torch.frontend.calibration`):
the radius ratios true / nominal of the left and right wheels and the track width (m);
steps add.

A ``nav_state`` tangent is the ESKF's error state, so the residual Jacobians in
:mod:`msf_torch.sensors` apply to it column for column.
"""

from __future__ import annotations

__all__ = [
    "VariableKind",
    "NAV_STATE",
    "POSE",
    "POINT",
    "SE3",
    "WHEEL_CALIBRATION",
    "KINDS",
    "pack_nav_state",
    "unpack_nav_state",
    "pack_pose",
    "unpack_pose",
]

from dataclasses import dataclass

import torch

from msf_torch.geometry import so3


@dataclass(frozen=True)
class VariableKind:
    """A kind of variable: name, storage size ``S`` and tangent size ``D``."""

    name: str
    storage_dim: int
    tangent_dim: int

    def retract(self, value: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """Apply a tangent step (..., D) to values (..., S); returns (..., S)."""
        if self.name in ("point", "wheel_calib"):
            return value + step
        if self.name == "pose":
            position, rotation = unpack_pose(value)
            return pack_pose(position + step[..., 0:3], rotation @ so3.exp(step[..., 3:6]))
        if self.name == "se3":
            position, rotation = unpack_pose(value)
            phi = step[..., 3:6]
            local = (so3.gamma1(phi) @ step[..., 0:3, None]).squeeze(-1)
            moved = position + (rotation @ local[..., None]).squeeze(-1)
            return pack_pose(moved, rotation @ so3.exp(phi))
        position, velocity, rotation, gyro_bias, accel_bias = unpack_nav_state(value)
        return pack_nav_state(
            position + step[..., 0:3],
            velocity + step[..., 3:6],
            rotation @ so3.exp(step[..., 6:9]),
            gyro_bias + step[..., 9:12],
            accel_bias + step[..., 12:15],
        )


NAV_STATE = VariableKind("nav_state", 21, 15)
POSE = VariableKind("pose", 12, 6)
POINT = VariableKind("point", 3, 3)
SE3 = VariableKind("se3", 12, 6)
WHEEL_CALIBRATION = VariableKind("wheel_calib", 3, 3)
KINDS = {kind.name: kind for kind in (NAV_STATE, POSE, POINT, SE3, WHEEL_CALIBRATION)}


def pack_nav_state(
    position: torch.Tensor,
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro_bias: torch.Tensor,
    accel_bias: torch.Tensor,
) -> torch.Tensor:
    """Flat nav-state values (..., 21) from p, v (..., 3) m, m/s; R (..., 3, 3) body->world;
    b_g (..., 3) rad/s; b_a (..., 3) m/s^2."""
    flat_rotation = rotation.reshape(*rotation.shape[:-2], 9)
    return torch.cat((position, velocity, flat_rotation, gyro_bias, accel_bias), -1)


def unpack_nav_state(
    value: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse of :func:`pack_nav_state`: (..., 21) -> p, v, R (..., 3, 3), b_g, b_a."""
    rotation = value[..., 6:15].reshape(*value.shape[:-1], 3, 3)
    return value[..., 0:3], value[..., 3:6], rotation, value[..., 15:18], value[..., 18:21]


def pack_pose(position: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Flat pose values (..., 12) from p (..., 3) m and R (..., 3, 3) body->world."""
    return torch.cat((position, rotation.reshape(*rotation.shape[:-2], 9)), -1)


def unpack_pose(value: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`pack_pose`: (..., 12) -> p (..., 3), R (..., 3, 3)."""
    return value[..., 0:3], value[..., 3:12].reshape(*value.shape[:-1], 3, 3)
