"""SO(3) on plain tensors ``(..., 3)`` / ``(..., 3, 3)``: hat, Exp, Log and the series
functions ``Gamma_1`` (left Jacobian) and ``Gamma_2`` used by exact zero-order-hold IMU
integration.

Singular branches use the double-``where`` form with Taylor series, so values and gradients
are finite at the identity and at a half turn.

Reference: T. Barfoot, *State Estimation for Robotics*, sec. 7.1 (Gamma functions in
eq. 7.86 are Barfoot's ``J`` and ``N``); Forster et al., "On-Manifold Preintegration", 2017.
"""

from __future__ import annotations

__all__ = [
    "identity",
    "hat",
    "vee",
    "exp",
    "log",
    "gamma1",
    "gamma2",
    "right_jacobian",
    "gamma_vector_jacobians",
    "exp_and_gammas",
    "coefficients",
    "series_coefficients",
    "series",
    "project",
    "rpy_matrix",
]

import functools

import torch

_SMALL_ANGLE = 2e-2  # Taylor branches below: truncation error < 2e-16 up to here


@functools.lru_cache(maxsize=16)
@torch.inference_mode(False)  # cached: an ordinary tensor, never an inference one
def _hat_generators(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(3, 9) matrix G with ``hat(phi).reshape(9) = phi @ G``."""
    gen = torch.zeros(3, 3, 3, dtype=dtype, device=device)
    gen[0, 2, 1], gen[0, 1, 2] = 1.0, -1.0
    gen[1, 0, 2], gen[1, 2, 0] = 1.0, -1.0
    gen[2, 1, 0], gen[2, 0, 1] = 1.0, -1.0
    return gen.reshape(3, 9)


@functools.lru_cache(maxsize=16)
@torch.inference_mode(False)  # cached: an ordinary tensor, never an inference one
def identity(dtype: torch.dtype, device: torch.device, size: int = 3) -> torch.Tensor:
    """A cached identity matrix (size, size); read-only by convention (never modify it)."""
    return torch.eye(size, dtype=dtype, device=device)


def hat(phi: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[phi]x`` so that ``hat(a) @ b == cross(a, b)``.

    Shape: (..., 3) -> (..., 3, 3). One product with a constant generator tensor.
    """
    return (phi @ _hat_generators(phi.dtype, phi.device)).unflatten(-1, (3, 3))


def vee(skew: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`: (..., 3, 3) -> (..., 3)."""
    return torch.stack((skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]), -1)


def _angle_terms(phi: torch.Tensor):
    """theta^2 and a safe theta for the series coefficients; (..., 3) -> (..., 1, 1)."""
    theta2 = (phi * phi).sum(-1)[..., None, None]
    small = theta2 < _SMALL_ANGLE**2
    safe_theta2 = torch.where(small, torch.ones_like(theta2), theta2)
    return theta2, small, safe_theta2, torch.sqrt(safe_theta2)


# Each series coefficient as its Taylor series ``a0 + a1 t^2 + a2 t^4`` (below the
# small-angle switch; the table holds (a0, a1, a2)) and in closed form (t = theta,
# t2 = theta^2, s = sin t, c = cos t): one table for ``_coefficients`` and
# ``series_coefficients``.
_TAYLOR = {
    "c0": (1.0, -1.0 / 6.0, 1.0 / 120.0),
    "c1": (0.5, -1.0 / 24.0, 1.0 / 720.0),
    "c2": (1.0 / 6.0, -1.0 / 120.0, 1.0 / 5040.0),
    "c3": (1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0),
    "e1": (-1.0 / 12.0, 1.0 / 180.0, -1.0 / 6720.0),
    "e2": (-1.0 / 60.0, 1.0 / 1260.0, -1.0 / 60480.0),
    "e3": (-1.0 / 360.0, 1.0 / 10080.0, -1.0 / 604800.0),
}
_CLOSED = {
    "c0": lambda t2, t, s, c: s / t,
    "c1": lambda t2, t, s, c: (1.0 - c) / t2,
    "c2": lambda t2, t, s, c: (t - s) / (t2 * t),
    "c3": lambda t2, t, s, c: (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2),
    "e1": lambda t2, t, s, c: s / (t2 * t) - 2.0 * (1.0 - c) / (t2 * t2),
    "e2": lambda t2, t, s, c: (1.0 - c) / (t2 * t2) - 3.0 * (t - s) / (t2 * t2 * t),
    "e3": lambda t2, t, s, c: (t - s) / (t2 * t2 * t) - 2.0 * (t2 + 2.0 * c - 2.0) / (t2 * t2 * t2),
}
SERIES_NAMES = ("c0", "c1", "c2", "c3", "e1", "e2", "e3")


def _coefficients(
    phi: torch.Tensor, which: str = "0123", derivatives: bool = False
) -> dict[str, torch.Tensor]:
    """Series coefficients of the SO(3) functions, each (..., 1, 1).

    ``c0 = sin t / t``, ``c1 = (1 - cos t) / t^2``, ``c2 = (t - sin t) / t^3``,
    ``c3 = (t^2 + 2 cos t - 2) / (2 t^4)`` (Taylor series below the small-angle switch; only
    the digits in ``which`` are computed), with ``theta2`` and
    ``skew2 = [phi]x^2 = phi phi^T - t^2 I``. With ``derivatives``, also
    ``e_n = (dc_n / dt) / t`` for n = 1, 2, 3.
    """
    theta2, small, t2, t = _angle_terms(phi)
    sin_t, cos_t = torch.sin(t), torch.cos(t)
    th4 = theta2 * theta2
    out = {
        "theta2": theta2,
        "skew2": phi[..., :, None] * phi[..., None, :] - theta2 * identity(phi.dtype, phi.device),
    }
    names = [f"c{d}" for d in which] + (["e1", "e2", "e3"] if derivatives else [])
    for name in names:
        a0, a1, a2 = _TAYLOR[name]
        taylor = a0 + a1 * theta2 + a2 * th4
        out[name] = torch.where(small, taylor, _CLOSED[name](t2, t, sin_t, cos_t))
    return out


def series_coefficients(theta2: torch.Tensor) -> torch.Tensor:
    """All seven series coefficients ``(c0, c1, c2, c3, e1, e2, e3)`` of :func:`coefficients`
    from ``theta^2`` of any shape: (...) -> (7, ...), the same values up to rounding.

    For large batches of small rotations (IMU samples): the Taylor series is evaluated
    everywhere (one matrix product with the table of series coefficients) and the closed
    form only at angles above the small-angle switch (one host check whether there are
    any), instead of both everywhere.
    """
    table = torch.tensor(
        [_TAYLOR[name] for name in SERIES_NAMES], dtype=theta2.dtype, device=theta2.device
    )
    powers = torch.stack((torch.ones_like(theta2), theta2, theta2 * theta2))
    out = (table @ powers.reshape(3, -1)).reshape(len(SERIES_NAMES), *theta2.shape)
    large = theta2 >= _SMALL_ANGLE**2
    if not bool(large.any()):
        return out
    t2 = theta2[large]
    t = torch.sqrt(t2)
    sin_t, cos_t = torch.sin(t), torch.cos(t)
    closed = torch.stack([_CLOSED[name](t2, t, sin_t, cos_t) for name in SERIES_NAMES])
    return out.masked_scatter(large.expand_as(out), closed)


def coefficients(
    phi: torch.Tensor, which: str = "0123", derivatives: bool = False
) -> dict[str, torch.Tensor]:
    """Public form of the shared series coefficients (see ``_coefficients``), for callers
    that need several SO(3) functions of the same large batch of rotation vectors."""
    return _coefficients(phi, which, derivatives)


def exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``Exp(phi) = I + c0 [phi]x + c1 [phi]x^2`` (Rodrigues).

    Args:
        phi: rotation vector (..., 3), rad.
    Returns:
        (..., 3, 3) rotation matrices.
    """
    c = _coefficients(phi, "01")
    return identity(phi.dtype, phi.device) + c["c0"] * hat(phi) + c["c1"] * c["skew2"]


def gamma1(phi: torch.Tensor) -> torch.Tensor:
    """``Gamma_1(phi) = sum_n [phi]x^n / (n+1)!``, the SO(3) left Jacobian.

    ``integral_0^1 Exp(s phi) ds = Gamma_1(phi)``. Shape (..., 3) -> (..., 3, 3).
    """
    c = _coefficients(phi, "12")
    return identity(phi.dtype, phi.device) + c["c1"] * hat(phi) + c["c2"] * c["skew2"]


def gamma2(phi: torch.Tensor) -> torch.Tensor:
    """``Gamma_2(phi) = sum_n [phi]x^n / (n+2)!``.

    ``integral_0^1 integral_0^s Exp(u phi) du ds = Gamma_2(phi)``. Shape (..., 3) -> (..., 3, 3).
    """
    c = _coefficients(phi, "23")
    return 0.5 * identity(phi.dtype, phi.device) + c["c2"] * hat(phi) + c["c3"] * c["skew2"]


def series(phi: torch.Tensor) -> dict[str, torch.Tensor]:
    """``Exp``, ``Gamma_1``, ``Gamma_2`` and ``J_r`` of one rotation vector, sharing work.

    Shape (..., 3) -> dict of (..., 3, 3) under keys ``exp``, ``gamma1``, ``gamma2``,
    ``right_jacobian``; also ``coef`` (..., 4) = ``(c0, c1, c2, c3)`` =
    (sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3, (t^2 + 2 cos t - 2) / 2t^4).
    """
    c = _coefficients(phi)
    skew, skew2 = hat(phi), c["skew2"]
    eye = identity(phi.dtype, phi.device)
    return {
        "exp": eye + c["c0"] * skew + c["c1"] * skew2,
        "gamma1": eye + c["c1"] * skew + c["c2"] * skew2,
        "gamma2": 0.5 * eye + c["c2"] * skew + c["c3"] * skew2,
        "right_jacobian": eye - c["c1"] * skew + c["c2"] * skew2,
        "coef": torch.cat((c["c0"], c["c1"], c["c2"], c["c3"]), -1)[..., 0, :],
    }


def exp_and_gammas(
    phi: torch.Tensor, coefficients: dict[str, torch.Tensor] | None = None
) -> torch.Tensor:
    """``Exp(phi)``, ``Gamma_1(phi)``, ``Gamma_2(phi)`` stacked: (..., 3) -> (..., 3, 3, 3).

    All three are ``a I + b [phi]x + c [phi]x^2``; computing them together shares every
    intermediate (large batches of IMU samples). ``coefficients``: optional
    ``coefficients(phi)`` computed already.
    """
    c = coefficients if coefficients is not None else _coefficients(phi)
    eye = identity(phi.dtype, phi.device)
    skew, skew2 = hat(phi), c["skew2"]
    # (..., 1, 1) x (..., 3, 3) products: a 5-D broadcast over the three is slower on CPU
    return torch.stack(
        (
            eye + c["c0"] * skew + c["c1"] * skew2,
            eye + c["c1"] * skew + c["c2"] * skew2,
            0.5 * eye + c["c2"] * skew + c["c3"] * skew2,
        ),
        -3,
    )


def gamma_vector_jacobians(
    phi: torch.Tensor, vec: torch.Tensor, coefficients: dict[str, torch.Tensor] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact derivatives ``d(Gamma_1(phi) x)/dphi`` and ``d(Gamma_2(phi) x)/dphi``.

    With ``Gamma_n(phi) x = a_n x + c_n phi x x + d_n phi x (phi x x)`` and
    ``d[phi x (phi x x)]/dphi = (phi . x) I + phi x^T - 2 x phi^T``, the derivative is
    ``-c_n [x]x + c_n' (phi x x) phi^T + d_n (...) + d_n' (phi x (phi x x)) phi^T`` where
    ``c' = (dc/dtheta) / theta`` (Taylor series below the small-angle switch).

    Args:
        phi: (..., 3) rotation vector, rad. vec: (..., 3).
        coefficients: optional ``coefficients(phi, derivatives=True)`` computed already.
    Returns:
        two (..., 3, 3) Jacobians.
    """
    c = coefficients if coefficients is not None else _coefficients(phi, "123", True)
    cross1 = torch.linalg.cross(phi, vec)
    cross2 = torch.linalg.cross(phi, cross1)
    dot = (phi * vec).sum(-1)[..., None, None]
    double = (
        dot * identity(phi.dtype, phi.device)
        + phi[..., :, None] * vec[..., None, :]
        - 2.0 * vec[..., :, None] * phi[..., None, :]
    )
    hat_vec = hat(vec)
    outer1 = cross1[..., :, None] * phi[..., None, :]
    outer2 = cross2[..., :, None] * phi[..., None, :]
    d_gamma1 = -c["c1"] * hat_vec + c["e1"] * outer1 + c["c2"] * double + c["e2"] * outer2
    d_gamma2 = -c["c2"] * hat_vec + c["e2"] * outer1 + c["c3"] * double + c["e3"] * outer2
    return d_gamma1, d_gamma2


def right_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """SO(3) right Jacobian ``J_r(phi) = Gamma_1(-phi)``: ``Exp(phi + d) ~ Exp(phi) Exp(J_r d)``.

    Shape (..., 3) -> (..., 3, 3).
    """
    return gamma1(-phi)


def log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``Log(R)`` (..., 3, 3) -> (..., 3), angle in [0, pi].

    Goes through the quaternion (:func:`msf_torch.geometry.quaternion.matrix_to_quat`,
    whose square roots are gradient-safe) and ``2 atan2(|v|, w)``, which is accurate at the
    identity and at a half turn.
    """
    from msf_torch.geometry.quaternion import matrix_to_quat

    quat = matrix_to_quat(rot)
    w, vec = quat[..., :1], quat[..., 1:]
    norm2 = (vec * vec).sum(-1, keepdim=True)
    small = norm2 < 1e-16
    safe_norm = torch.sqrt(torch.where(small, torch.ones_like(norm2), norm2))
    safe_w = torch.where(small, w, torch.ones_like(w))
    scale = torch.where(
        small,
        2.0 / safe_w * (1.0 - norm2 / (3.0 * safe_w * safe_w)),
        2.0 * torch.atan2(safe_norm, w) / safe_norm,
    )
    return scale * vec


def project(mat: torch.Tensor) -> torch.Tensor:
    """Nearest rotation matrix (SVD, determinant fixed to +1). Shape (..., 3, 3)."""
    u, _, vh = torch.linalg.svd(mat)
    det = torch.linalg.det(u @ vh)
    ones = torch.ones_like(det)
    fix = torch.diag_embed(torch.stack((ones, ones, det), -1))
    return u @ fix @ vh


def rpy_matrix(rpy: torch.Tensor) -> torch.Tensor:
    """Fixed-axis roll-pitch-yaw (..., 3) rad -> rotation ``Rz(yaw) Ry(pitch) Rx(roll)``
    (..., 3, 3): URDF's ``rpy``, the ZYX Euler angles of KITTI's OXTS and of most IMU
    mounting specs."""
    roll, pitch, yaw = rpy.unbind(-1)
    cr, sr = torch.cos(roll), torch.sin(roll)
    cp, sp = torch.cos(pitch), torch.sin(pitch)
    cy, sy = torch.cos(yaw), torch.sin(yaw)
    rows = (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )
    return torch.stack([torch.stack(row, -1) for row in rows], -2)
