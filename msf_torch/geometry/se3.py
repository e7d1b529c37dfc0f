"""SE(3) logarithm used by relative-pose (between) residuals.

A pose is ``(R, t)`` (body -> world rotation and position). ``Log(R, t) = [rho, phi]`` with
``phi = Log(R)`` and ``rho = V(phi)^-1 t``, ``V = Gamma_1`` the SO(3) left Jacobian; this is
the chart GTSAM's ``Pose3.Logmap`` uses (order here: translation part first, as in
:mod:`msf_torch.geometry.conventions`).
"""

from __future__ import annotations

__all__ = ["log", "relative", "compose", "adjoint", "right_jacobian", "right_jacobian_inverse"]

import torch

from msf_torch.geometry import so3


def log(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """``[rho, phi]`` (..., 6) of poses R (..., 3, 3), t (..., 3)."""
    phi = so3.log(rotation)
    rho = torch.linalg.solve(so3.gamma1(phi), translation[..., None]).squeeze(-1)
    return torch.cat((rho, phi), -1)


def relative(
    rotation_a: torch.Tensor,
    position_a: torch.Tensor,
    rotation_b: torch.Tensor,
    position_b: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``T_a^-1 T_b``: rotation (..., 3, 3) and translation (..., 3)."""
    rotation = rotation_a.mT @ rotation_b
    translation = (rotation_a.mT @ (position_b - position_a)[..., None]).squeeze(-1)
    return rotation, translation


def compose(
    rotation_a: torch.Tensor,
    position_a: torch.Tensor,
    rotation_b: torch.Tensor,
    position_b: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``T_a T_b``: rotation (..., 3, 3) and translation (..., 3)."""
    return rotation_a @ rotation_b, position_a + (rotation_a @ position_b[..., None]).squeeze(-1)


def adjoint(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Adjoint (..., 6, 6) of poses in [rho, phi] order: ``[[R, [t]x R], [0, R]]``, so that
    ``T exp(xi) = exp(Ad_T xi) T``."""
    top = torch.cat((rotation, so3.hat(translation) @ rotation), -1)
    bottom = torch.cat((torch.zeros_like(rotation), rotation), -1)
    return torch.cat((top, bottom), -2)


def _ad(xi: torch.Tensor) -> torch.Tensor:
    """Lie-algebra adjoint ``ad(xi)`` (..., 6, 6) in [rho, phi] order."""
    rho_hat, phi_hat = so3.hat(xi[..., 0:3]), so3.hat(xi[..., 3:6])
    top = torch.cat((phi_hat, rho_hat), -1)
    bottom = torch.cat((torch.zeros_like(phi_hat), phi_hat), -1)
    return torch.cat((top, bottom), -2)


def _q_matrix(rho: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Barfoot's ``Q(rho, phi)`` (..., 3, 3), the off-diagonal block of the SE(3) left
    Jacobian (State Estimation for Robotics, eq. 7.86b), with Taylor series below 1e-2 rad."""
    theta2 = (phi * phi).sum(-1)[..., None, None]
    small = theta2 < 1e-4
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    sin, cos = torch.sin(theta), torch.cos(theta)
    a = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (theta - sin) / (safe2 * theta))
    b = torch.where(
        small, 1 / 24 - theta2 / 720 + theta2**2 / 40320, (safe2 + 2 * cos - 2) / (2 * safe2**2)
    )
    c = torch.where(
        small,
        1 / 120 - theta2 / 2520 + theta2**2 / 120960,
        (2 * theta - 3 * sin + theta * cos) / (2 * safe2**2 * theta),
    )
    r, p = so3.hat(rho), so3.hat(phi)
    pr, rp = p @ r, r @ p
    prp = pr @ p
    return 0.5 * r + a * (pr + rp + prp) + b * (p @ pr + rp @ p - 3 * prp) + c * (prp @ p + p @ prp)


def right_jacobian_inverse(xi: torch.Tensor) -> torch.Tensor:
    """Inverse SE(3) right Jacobian (..., 6, 6) in [rho, phi] order, closed form:
    ``J_r(xi) = [[J_r(phi), Q(-rho, -phi)], [0, J_r(phi)]]``, so
    ``J_r^-1 = [[J_r^-1, -J_r^-1 Q J_r^-1], [0, J_r^-1]]``."""
    rho, phi = xi[..., 0:3], xi[..., 3:6]
    jr_inv = torch.linalg.inv(so3.right_jacobian(phi))
    q = _q_matrix(-rho, -phi)
    top = torch.cat((jr_inv, -jr_inv @ q @ jr_inv), -1)
    bottom = torch.cat((torch.zeros_like(jr_inv), jr_inv), -1)
    return torch.cat((top, bottom), -2)


def right_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """SE(3) right Jacobian ``J_r(xi) = sum_n (-ad xi)^n / (n+1)!`` (..., 6, 6), so that
    ``exp(xi + d) ~ exp(xi) exp(J_r d)``.

    Computed as the top-right block of ``expm([[-ad xi, I], [0, 0]])`` (exact for every
    angle; a reference for :func:`right_jacobian_inverse`)."""
    ad = -_ad(xi)
    eye = torch.eye(6, dtype=xi.dtype, device=xi.device).expand_as(ad)
    zeros = torch.zeros_like(ad)
    block = torch.cat((torch.cat((ad, eye), -1), torch.cat((zeros, zeros), -1)), -2)
    return torch.linalg.matrix_exp(block)[..., 0:6, 6:12]
