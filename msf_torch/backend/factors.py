"""Factor types of the back end: the residuals of :mod:`msf_torch.sensors`, noise, kernel.

Each class is one *type* of factor holding F factors as a struct of arrays: index tensors
(F,) into the variable groups, measurement tensors (B or 1, F, ...), a square-root
information matrix (B or 1, F, R, R) from a covariance (``Sigma = L L^T``, ``W = L^-1``) and
an optional :class:`~msf_torch.backend.robust.RobustKernel`. Where the sensor module gives a
Jacobian w.r.t. the 15-dim error state it is used directly (columns picked for pose
variables); the others are differentiated by forward-mode autodiff on the tangent space.

Variables may be ``nav_state`` (15-dim tangent [dp, dv, dtheta, db_g, db_a]) or ``pose``
(6-dim [dp, dtheta]) where a factor only needs the pose.
"""

from __future__ import annotations

__all__ = [
    "sqrt_information",
    "pose_of",
    "PosePriorFactor",
    "NavStatePriorFactor",
    "GnssFactor",
    "GnssVelocityFactor",
    "AzimuthFactor",
    "GnssHeadingFactor",
    "MagnetometerFactor",
    "ZeroVelocityFactor",
    "NonholonomicFactor",
    "BetweenFactor",
    "PlaneFactor",
    "ImuPreintegrationFactor",
    "GtsamImuFactor",
    "WheelOdometryFactor",
    "CalibratedWheelOdometryFactor",
    "VectorPriorFactor",
    "ReprojectionFactor",
    "MarginalPriorFactor",
]

import torch

from msf_torch.backend.preintegration import TangentPreintegrated, calibrated_wheel_increment
from msf_torch.backend.problem import Factor
from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import VariableKind, unpack_nav_state, unpack_pose
from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_P, IDX_THETA
from msf_torch.sensors.camera import reprojection_residual
from msf_torch.sensors.gnss import azimuth_residual, gnss_residual, gnss_velocity_residual
from msf_torch.sensors.imu import Preintegrated, preintegration_residual
from msf_torch.sensors.plane import plane_residual
from msf_torch.sensors.pose import pose_residual, relative_pose_residual
from msf_torch.sensors.vehicle import nonholonomic_residual, zero_velocity_residual
from msf_torch.sensors.wheel import wheel_increment_residual

_POSE_COLUMNS = [IDX_P.start + i for i in range(3)] + [IDX_THETA.start + i for i in range(3)]


def sqrt_information(covariance: torch.Tensor) -> torch.Tensor:
    """Whitening ``W = L^-1`` (..., R, R) of a covariance ``Sigma = L L^T`` (..., R, R), so
    ``|W r|^2 = r^T Sigma^-1 r``."""
    chol = torch.linalg.cholesky(covariance)
    eye = torch.eye(covariance.shape[-1], dtype=covariance.dtype, device=covariance.device)
    return torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)


def pose_of(kind: VariableKind, value: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Position (..., 3) and rotation (..., 3, 3) of ``nav_state``, ``pose`` or ``se3`` values."""
    if kind.name in ("pose", "se3"):
        return unpack_pose(value)
    position, _, rotation, _, _ = unpack_nav_state(value)
    return position, rotation


def _for_kind(jacobian: torch.Tensor, kind: VariableKind) -> torch.Tensor:
    """Error-state Jacobian (..., R, 15) restricted to the tangent of ``kind``."""
    if kind.name == "nav_state":
        return jacobian
    if kind.name == "se3":
        raise ValueError("this factor takes nav_state or pose variables, not se3")
    return jacobian[..., _POSE_COLUMNS]


class _Evaluated:
    """Factors whose residual and Jacobians come from one ``_evaluate(values, jacobians)``."""

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, R) of this type (R in the class docstring), no Jacobians."""
        return self._evaluate(values, jacobians=False)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, R) and analytic Jacobians (B, F, R, D_slot) per slot (the slots'
        kinds are ``self.kinds``; ``kinds`` is not read)."""
        return self._evaluate(values, jacobians=True)


class _Unary(Factor):
    """Factor on one variable per factor."""

    def __init__(
        self, group: str, index: torch.Tensor, covariance: torch.Tensor, kernel: RobustKernel | None
    ) -> None:
        self.slots = ((group, index.long()),)
        self.sqrt_information = sqrt_information(covariance)
        self.kernel = kernel


class PosePriorFactor(_Unary):
    """Prior on a pose from the front end: ``r = [p - p', Log(R'^T R)]`` (6,) with the front
    end's 6x6 covariance in [dp, dtheta] order (:func:`msf_torch.sensors.pose.pose_residual`).

    Args:
        group, index: variables (F,) (``nav_state`` or ``pose``).
        position: (B|1, F, 3) m. rotation: (B|1, F, 3, 3).
        covariance: (B|1, F, 6, 6) m^2 / rad^2.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("position", "rotation")

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        position: torch.Tensor,
        rotation: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.position, self.rotation = position, rotation

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 6): position error m, rotation error rad."""
        return self.residual_and_jacobians(values, None)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 6) and the Jacobian (B, F, 6, D) w.r.t. the variable's tangent
        (D = 15 for ``nav_state``, 6 for ``pose``); ``kinds`` is not read (``self.kinds``)."""
        kind = self.kinds[0]
        position, rotation = pose_of(kind, values[0])
        r, jac = pose_residual(
            position, rotation, self.position.expand_as(position), self.rotation.expand_as(rotation)
        )
        return r, [_for_kind(jac, kind)]


class NavStatePriorFactor(_Unary):
    """Prior on a whole nav state: ``r = [p - p', v - v', Log(R'^T R), b_g - b_g', b_a - b_a']``
    (15,) with a 15x15 covariance in the error-state order.

    Args:
        group, index: ``nav_state`` variables (F,).
        prior: (B|1, F, 21) nav-state values (:func:`msf_torch.backend.variables.pack_nav_state`).
        covariance: (B|1, F, 15, 15).
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("prior",)

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        prior: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.prior = prior

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 15) in the error-state order (m, m/s, rad, rad/s, m/s^2)."""
        return nav_state_local(self.prior.expand_as(values[0]), values[0])

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 15) and the Jacobian (B, F, 15, 15) w.r.t. the nav-state tangent;
        ``kinds`` is not read."""
        local = nav_state_local(self.prior.expand_as(values[0]), values[0])
        return local, [nav_state_local_jacobian(local)]


def nav_state_local(origin: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """Tangent coordinates (..., 15) of nav states ``value`` around ``origin`` (..., 21)."""
    p0, v0, r0, bg0, ba0 = unpack_nav_state(origin)
    p, v, r, bg, ba = unpack_nav_state(value)
    return torch.cat((p - p0, v - v0, so3.log(r0.mT @ r), bg - bg0, ba - ba0), -1)


def nav_state_local_jacobian(local: torch.Tensor) -> torch.Tensor:
    """Jacobian (..., 15, 15) of :func:`nav_state_local` w.r.t. the tangent step of its
    ``value``, from the coordinates ``local`` (..., 15) it returned: identity except
    ``J_r^-1(Log(R0^T R))`` on the rotation block (``Log(R0^T R) = local[..., 6:9]``)."""
    jac = torch.eye(15, dtype=local.dtype, device=local.device).repeat(*local.shape[:-1], 1, 1)
    jac[..., 6:9, 6:9] = torch.linalg.inv(so3.right_jacobian(local[..., 6:9]))
    return jac


class GnssFactor(_Unary):
    """GNSS antenna position ``r = p + R l - z`` (3,) (:mod:`msf_torch.sensors.gnss`).

    Args:
        group, index: variables (F,). measured: (B|1, F, 3) m. lever_arm: (3,) or (B|1, F, 3)
        m in the body frame. covariance: (B|1, F, 3, 3) m^2.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("measured", "lever_arm")

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        measured: torch.Tensor,
        covariance: torch.Tensor,
        lever_arm: torch.Tensor | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.measured = measured
        self.lever_arm = _lever_arm_or_zero(lever_arm, measured)
        self._no_arm = bool((self.lever_arm == 0).all())  # stays true for any subset

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 3), m."""
        return self.residual_and_jacobians(values, None)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 3) m and the Jacobian (B, F, 3, D) w.r.t. the variable's tangent
        (D = 15 or 6); ``kinds`` is not read (``self.kinds``)."""
        kind = self.kinds[0]
        position, rotation = pose_of(kind, values[0])
        arm = self.lever_arm.expand_as(position)
        r, jac = gnss_residual(position, rotation, arm, self.measured.expand_as(position))
        return r, [_for_kind(jac, kind)]

    def normal_blocks(
        self, values: list[torch.Tensor], kinds: list[VariableKind], pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, list[torch.Tensor], list[list[tuple[slice, slice, torch.Tensor]]]]:
        """Without a lever arm (zero and not learned) or robust kernel the Jacobian is I on
        the position columns and zero elsewhere, so the block is ``W^T W`` on them, no
        Jacobian formed (see :meth:`Factor.normal_blocks`); else the generic form."""
        kind = self.kinds[0]
        arm_free = self._no_arm and not self.lever_arm.requires_grad
        if not arm_free or self.kernel is not None or kind.name not in ("nav_state", "pose"):
            return super().normal_blocks(values, kinds, pairs)
        position, _ = pose_of(kind, values[0])
        white = (self.sqrt_information @ (position - self.measured)[..., None]).squeeze(-1)
        loss = 0.5 * (white * white).sum(-1)
        grad = (self.sqrt_information.mT @ white[..., None]).squeeze(-1)  # (B, F, 3)
        grad = torch.nn.functional.pad(grad, (0, kind.tangent_dim - 3))
        block = self.sqrt_information.mT @ self.sqrt_information
        block = block.expand(*white.shape[:-1], 3, 3)
        columns = slice(0, 3)
        return loss, [grad], [[(columns, columns, block)] for _ in pairs]


class ZeroVelocityFactor(_Unary):
    """Zero velocity ``r = v`` (3,) on ``nav_state`` variables.

    Args:
        group, index: ``nav_state`` variables (F,). covariance: (B|1, F, 3, 3) (m/s)^2.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ()

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 3), m/s."""
        return self.residual_and_jacobians(values, None)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 3) m/s and the Jacobian (B, F, 3, 15) w.r.t. the nav-state tangent;
        ``kinds`` is not read."""
        _, velocity, _, _, _ = unpack_nav_state(values[0])
        r, jac = zero_velocity_residual(velocity)
        return r, [jac]


class _PointVelocityFactor(_Unary):
    """The velocity of a point on the body (``lever_arm``), which moves with the raw gyro
    rate at each state's time: the shared parts of :class:`NonholonomicFactor` and
    :class:`GnssVelocityFactor`."""

    batched = ("gyro", "lever_arm")

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        gyro: torch.Tensor,
        covariance: torch.Tensor,
        lever_arm: torch.Tensor | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.gyro = gyro
        self.lever_arm = _lever_arm_or_zero(lever_arm, gyro)

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, R), m/s."""
        return self.residual_and_jacobians(values, None)[0]


class NonholonomicFactor(_PointVelocityFactor):
    """Non-holonomic constraint on ``nav_state`` variables: the lateral and vertical body
    velocity of the point at ``lever_arm``, ``r = [R^T v + [w - b_g]x l]_{y,z}`` (2,) m/s
    (:func:`msf_torch.sensors.vehicle.nonholonomic_residual`).

    Args:
        group, index: ``nav_state`` variables (F,). gyro: (B|1, F, 3) raw gyro rate at each
        state's time, rad/s. covariance: (B|1, F, 2, 2) (m/s)^2. lever_arm: (3,) m, body.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 2) m/s and the Jacobian (B, F, 2, 15) w.r.t. the nav-state tangent;
        ``kinds`` is not read."""
        _, velocity, rotation, gyro_bias, _ = unpack_nav_state(values[0])
        r, jac = nonholonomic_residual(
            velocity,
            rotation,
            self.gyro.expand_as(velocity),
            gyro_bias,
            self.lever_arm.expand_as(velocity),
        )
        return r, [jac]


class GnssVelocityFactor(_PointVelocityFactor):
    """GNSS antenna velocity ``r = v + R ([w - b_g]x l) - z`` (3,) m/s on ``nav_state``
    variables (:func:`msf_torch.sensors.gnss.gnss_velocity_residual`).

    Args:
        group, index: ``nav_state`` variables (F,). measured: (B|1, F, 3) world velocity,
        m/s. gyro: (B|1, F, 3) raw gyro rate at each state's time, rad/s. covariance:
        (B|1, F, 3, 3) (m/s)^2 (an axis the receiver did not give: a huge variance).
        lever_arm: (3,) m, body. kernel: robust kernel (:mod:`msf_torch.backend.robust`),
        or None for plain least squares.
    """

    batched = ("measured", "gyro", "lever_arm")

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        measured: torch.Tensor,
        gyro: torch.Tensor,
        covariance: torch.Tensor,
        lever_arm: torch.Tensor | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, gyro, covariance, lever_arm, kernel)
        self.measured = measured

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 3) m/s and the Jacobian (B, F, 3, 15) w.r.t. the nav-state tangent;
        ``kinds`` is not read."""
        _, velocity, rotation, gyro_bias, _ = unpack_nav_state(values[0])
        r, jac = gnss_velocity_residual(
            velocity,
            rotation,
            self.gyro.expand_as(velocity),
            gyro_bias,
            self.lever_arm.expand_as(velocity),
            self.measured.expand_as(velocity),
        )
        return r, [jac]


class AzimuthFactor(_Unary):
    """Azimuth of a body-frame vector seen in the world, ``r = wrap(azimuth(R v) - z)`` (1,)
    rad, clockwise from north (:func:`msf_torch.sensors.gnss.azimuth_residual`): the
    common model of :class:`GnssHeadingFactor` and :class:`MagnetometerFactor`.

    Args:
        group, index: variables (F,) (``nav_state`` or ``pose``). body_vector: (B|1, F, 3)
        the vector in the body frame (only its direction counts). measured: (B|1, F) the
        azimuth it should have, rad. covariance: (B|1, F, 1, 1) rad^2. kernel: robust kernel
        (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("body_vector", "measured")

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        body_vector: torch.Tensor,
        measured: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.body_vector = body_vector
        self.measured = measured

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 1), rad."""
        return self.residual_and_jacobians(values, None)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 1) rad and the Jacobian (B, F, 1, D) w.r.t. the variable's
        tangent (D = 15 or 6); ``kinds`` is not read (``self.kinds``)."""
        kind = self.kinds[0]
        _, rotation = pose_of(kind, values[0])
        lead = rotation.shape[:-2]
        r, jac = azimuth_residual(
            rotation, self.body_vector.expand(*lead, 3), self.measured.expand(lead)
        )
        return r, [_for_kind(jac, kind)]


class GnssHeadingFactor(AzimuthFactor):
    """Dual-antenna GNSS heading ``r = wrap(azimuth(R b) - z)`` (1,) rad, the azimuth of the
    baseline ``b`` (body frame) clockwise from north
    (:func:`msf_torch.sensors.gnss.gnss_heading_residual`).

    Args:
        group, index: variables (F,) (``nav_state`` or ``pose``). measured: (B|1, F)
        heading, rad. covariance: (B|1, F, 1, 1) rad^2. baseline: (3,) primary ->
        secondary antenna, body frame (only its direction counts). kernel: robust kernel
        (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        measured: torch.Tensor,
        covariance: torch.Tensor,
        baseline: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        body_vector = baseline.expand(1, index.shape[0], 3)
        super().__init__(group, index, body_vector, measured, covariance, kernel)


class MagnetometerFactor(AzimuthFactor):
    """Magnetometer heading ``r = wrap(azimuth(R f_b) - D)`` (1,) rad: the azimuth of the
    hard- and soft-iron corrected field ``f_b`` (body frame) turned into the world, clockwise
    from north, against the declination ``D``
    (:func:`msf_torch.sensors.magnetometer.magnetometer_heading_residual`, the front end's
    residual; only the heading, not the field's dip).

    Args:
        group, index: variables (F,) (``nav_state`` or ``pose``). field: (B|1, F, 3)
        corrected field ``W (m - b)``, uT (only its direction counts). declination: (B|1, F)
        magnetic north's azimuth, rad (east positive). covariance: (B|1, F, 1, 1) rad^2
        (:func:`~msf_torch.sensors.magnetometer.magnetometer_heading_variance`). kernel:
        robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        field: torch.Tensor,
        declination: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, field, declination, covariance, kernel)


class _Binary(Factor):
    """Factor between two variables i and j of one group per factor."""

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None,
    ) -> None:
        self.slots = ((group, index_i.long()), (group, index_j.long()))
        self.sqrt_information = sqrt_information(covariance)
        self.kernel = kernel


class BetweenFactor(_Evaluated, _Binary):
    """Relative pose (odometry, loop closure): ``r = Log_SE3(Z^-1 T_i^-1 T_j)`` (6,), order
    [rho, phi] (translation part first): :func:`msf_torch.sensors.pose.relative_pose_residual`,
    GTSAM's ``BetweenFactor<Pose3>`` error in our order.

    Args:
        group, index_i, index_j: variables (F,). rotation: (B|1, F, 3, 3), translation:
        (B|1, F, 3) m, the measured ``T_i^-1 T_j``. covariance: (B|1, F, 6, 6) in [rho, phi].
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("rotation", "translation")

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        rotation: torch.Tensor,
        translation: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index_i, index_j, covariance, kernel)
        self.rotation, self.translation = rotation, translation

    def _evaluate(self, values, jacobians: bool):
        kind = self.kinds[0]
        p_i, r_i = pose_of(kind, values[0])
        p_j, r_j = pose_of(kind, values[1])
        xi, jac_i, jac_j = relative_pose_residual(
            p_i, r_i, p_j, r_j, self.rotation.expand_as(r_i), self.translation.expand_as(p_i)
        )
        if not jacobians or kind.name == "se3":
            return xi, [jac_i, jac_j] if jacobians else None
        # our chart moves p by dp = R rho (world), so d/d(dp) = d/d(rho) R^T
        jac_j = torch.cat((jac_j[..., :, 0:3] @ r_j.mT, jac_j[..., :, 3:6]), -1)
        jac_i = torch.cat((jac_i[..., :, 0:3] @ r_i.mT, jac_i[..., :, 3:6]), -1)
        return xi, [_widen(jac_i, kind), _widen(jac_j, kind)]


class PlaneFactor(_Binary):
    """Planar motion of a ground vehicle between poses i and j (3,): the residual of
    :func:`msf_torch.sensors.plane.plane_residual` (no relative roll, pitch or height change
    in the ground plane of pose i).

    Args: group, index_i, index_j (F,); covariance (B|1, F, 3, 3) rad^2, rad^2, m^2;
    kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ()

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 3): x and y of ``Log(R_i^T R_j)``, rad; height of ``p_j`` in pose
        i's frame, m."""
        kind = self.kinds[0]
        return plane_residual(*pose_of(kind, values[0]), *pose_of(kind, values[1]))


class ImuPreintegrationFactor(_Binary):
    """IMU preintegration between nav states i and j (15,): the residual of
    :func:`msf_torch.sensors.imu.preintegration_residual` ([r_p, r_v, r_theta] and the bias
    random walk [r_bg, r_ba]).

    Args:
        group, index_i, index_j: ``nav_state`` variables (F,).
        preintegrated: :class:`~msf_torch.sensors.imu.Preintegrated` with leading (B|1, F).
        covariance: (B|1, F, 15, 15) (see :func:`msf_torch.backend.preintegration.imu_covariance`).
        gravity: (3,) m/s^2 world.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("preintegrated",)

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        preintegrated: Preintegrated,
        covariance: torch.Tensor,
        gravity: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index_i, index_j, covariance, kernel)
        self.preintegrated, self.gravity = preintegrated, gravity

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 15): [r_p m, r_v m/s, r_theta rad, r_bg rad/s, r_ba m/s^2]."""
        return self.residual_and_jacobians(values, None)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 15) and the Jacobians (B, F, 15, 15) w.r.t. the nav-state tangents
        of states i and j; ``kinds`` is not read."""
        r, jac_i, jac_j = preintegration_residual(
            values[0], values[1], self.preintegrated, self.gravity
        )
        return r, [jac_i, jac_j]


class GtsamImuFactor(_Evaluated, _Binary):
    """``gtsam.ImuFactor`` (Logmap error mode) plus its bias random walk, between nav states
    i and j (15,), on :func:`~msf_torch.backend.preintegration.preintegrate_imu_tangent`
    increments: the option that poses GTSAM's exact problem (the default IMU factor is
    :class:`ImuPreintegrationFactor`, exact zero-order hold with Forster's residual).

    With the increment ``z = [z_p, z_v, z_theta]`` bias-corrected additively at ``b_i``, the
    prediction ``R^ = R_i Exp(z_theta)``, ``p^ = p_i + v_i dT + 1/2 g dT^2 + R_i z_p``,
    ``v^ = v_i + g dT + R_i z_v`` is compared with state j in its own frame:
    ``phi = Log(R_j^T R^)``, ``dp = R_j^T (p^ - p_j)``, ``dv = R_j^T (v^ - v_j)`` and::

        r = [Jl(phi)^-1 dp, Jl(phi)^-1 dv, phi, b_g,j - b_g,i, b_a,j - b_a,i]

    i.e. GTSAM's ``[phi; Jl^-1 dp; Jl^-1 dv]`` (the SE_2(3) log of ``X_j^-1 X^``) in our
    order, plus ``BetweenFactorConstantBias`` rows. Analytic Jacobians w.r.t. the nav-state
    tangent ``[dp, dv, dtheta, db_g, db_a]`` (world-frame ``dp``, ``dv``; right-perturbed R).

    Args:
        group, index_i, index_j: ``nav_state`` variables (F,).
        preintegrated: :class:`~msf_torch.backend.preintegration.TangentPreintegrated` with
            leading (B|1, F).
        covariance: (B|1, F, 15, 15): ``imu_covariance(preintegrated, noise)`` gives
            GTSAM's ``residualCovariance`` and the random walk ``sigma_bw^2 dT``.
        gravity: (3,) m/s^2 world (``[0, 0, -g]`` for GTSAM's ``MakeSharedU(g)``).
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("preintegrated",)

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        preintegrated: TangentPreintegrated,
        covariance: torch.Tensor,
        gravity: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index_i, index_j, covariance, kernel)
        self.preintegrated, self.gravity = preintegrated, gravity

    def _evaluate(self, values, jacobians: bool):
        residual, rows = self._compact(values, jacobians)
        if not jacobians:
            return residual, None
        jac_i9, jac_j9 = rows[..., 0:15], rows[..., 15:24]
        lead = residual.shape[:-1]
        bias_i = torch.cat(
            (
                torch.zeros(*lead, 6, 9, dtype=residual.dtype, device=residual.device),
                -so3.identity(residual.dtype, residual.device, 6).expand(*lead, 6, 6),
            ),
            -1,
        )
        jac_i = torch.cat((jac_i9, bias_i), -2)
        jac_j = torch.cat(
            (
                torch.nn.functional.pad(jac_j9, (0, 6)),
                torch.cat((bias_i[..., :9], -bias_i[..., 9:]), -1),
            ),
            -2,
        )
        return residual, [jac_i, jac_j]

    def _compact(self, values, jacobians: bool):
        """Residual (..., 15) and, when asked, its increment rows ``[rho_p; rho_v; phi]`` as
        one (..., 9, 25) matrix: their Jacobians w.r.t. state i (15 columns) and state j's
        [dp, dv, dtheta] (9; the rest of the Jacobians: the bias rows are -I / +I on the bias
        columns), and the rows' values (last column)."""
        pre = self.preintegrated
        p_i, v_i, r_i, bg_i, ba_i = unpack_nav_state(values[0])
        p_j, v_j, r_j, bg_j, ba_j = unpack_nav_state(values[1])
        d_t = pre.delta_t[..., None]
        z = pre.corrected(bg_i, ba_i)
        z_p, z_v, z_theta = z[..., 0:3], z[..., 3:6], z[..., 6:9]
        eye = so3.identity(z.dtype, z.device)
        # the series coefficients of z_theta and of phi are each computed once, for Exp(z_theta)
        # and J_r(z_theta), for Jl(phi) and its derivatives (same values as so3.exp, ...)
        coef_z = so3.coefficients(z_theta, "012" if jacobians else "01")
        hat_z = so3.hat(z_theta)
        exp_z = eye + coef_z["c0"] * hat_z + coef_z["c1"] * coef_z["skew2"]
        pred_p = p_i + v_i * d_t + 0.5 * self.gravity * d_t**2 + (r_i @ z_p[..., None]).squeeze(-1)
        pred_v = v_i + self.gravity * d_t + (r_i @ z_v[..., None]).squeeze(-1)
        r_j_t = r_j.mT
        rel = r_j_t @ r_i  # R_j^T R_i
        d_rot = rel @ exp_z
        phi = so3.log(d_rot)
        d_pv = r_j_t @ torch.stack((pred_p - p_j, pred_v - v_j), -1)  # (..., 3, 2)
        coef = so3.coefficients(phi, "123" if jacobians else "12", derivatives=jacobians)
        jl_inv = torch.linalg.inv(eye + coef["c1"] * so3.hat(phi) + coef["c2"] * coef["skew2"])
        rho = jl_inv @ d_pv
        rho_p, rho_v = rho[..., 0], rho[..., 1]
        residual = torch.cat((rho_p, rho_v, phi, bg_j - bg_i, ba_j - ba_i), -1)
        if not jacobians:
            return residual, None

        lead = residual.shape[:-1]
        jr_inv = jl_inv.mT  # J_r(phi) = J_l(phi)^T
        bias_jac = pre.bias_jacobian.expand(*lead, 9, 6)
        # phi rows: d phi / d(theta_i, bias_i) = P (3, 9); d phi / d theta_j = S (3, 3)
        jr_z = eye - coef_z["c1"] * hat_z + coef_z["c2"] * coef_z["skew2"]  # J_r(z_theta)
        rot_bias = jr_z @ bias_jac[..., 6:9, :]
        ps = _matmul3(jr_inv, torch.cat((exp_z.mT, rot_bias, -d_rot.mT), -1))  # [P, S]
        # d(Jl(phi)^-1 x)/dphi = -Jl^-1 d(Jl(phi) y)/dphi at y = Jl^-1 x, for x = dp, dv
        turn = -jl_inv @ torch.cat(
            (
                so3.gamma_vector_jacobians(phi, rho_p, coef)[0],
                so3.gamma_vector_jacobians(phi, rho_v, coef)[0],
            ),
            -1,
        )
        turn = torch.cat((turn[..., 0:3], turn[..., 3:6]), -2)  # (..., 6, 3): p rows, v rows
        turn_ps = _matmul3(turn, ps)  # (..., 6, 12): turn [P, S]
        jl_rj = jl_inv @ r_j_t
        zero = torch.zeros_like(jl_rj)
        # state i: rows [rho_p; rho_v] = Jl^-1 [d dp; d dv] + turn P on [dtheta, db]
        own = torch.cat(
            (-so3.hat(z_p), bias_jac[..., 0:3, :], -so3.hat(z_v), bias_jac[..., 3:6, :]), -1
        )
        moved = _matmul3(jl_inv @ rel, own)  # (..., 3, 18): p columns, v columns
        rot_cols = torch.cat((moved[..., 0:9], moved[..., 9:18]), -2) + turn_ps[..., 0:9]
        translation = torch.cat(
            (torch.cat((jl_rj, jl_rj * d_t[..., None]), -1), torch.cat((zero, jl_rj), -1)), -2
        )
        # state j: [dp, dv, dtheta] columns of the same rows
        hats = so3.hat(d_pv.mT)  # (..., 2, 3, 3): [d_p]x, [d_v]x
        turned = jl_inv @ torch.cat((hats[..., 0, :, :], hats[..., 1, :, :]), -1)
        turn_j = torch.cat((turned[..., 0:3], turned[..., 3:6]), -2) + turn_ps[..., 9:12]
        translation_j = torch.cat(
            (torch.cat((-jl_rj, zero), -1), torch.cat((zero, -jl_rj), -1)), -2
        )
        rows = torch.cat(
            (
                torch.cat(
                    (translation, rot_cols, translation_j, turn_j, rho.mT.reshape(*lead, 6, 1)),
                    -1,
                ),
                torch.cat(
                    (zero, zero, ps[..., 0:9], zero, zero, ps[..., 9:12], phi[..., None]), -1
                ),
            ),
            -2,
        )
        return residual, rows

    def _split_whitening(self) -> torch.Tensor | None:
        """(B|1, F, 9, 9) whitening of the increment rows when the whitening is
        block-diagonal (9 increment rows, 6 random-walk rows with a diagonal block) and no
        robust kernel is set, else None. The check is made once (it survives :meth:`select`,
        which keeps the structure)."""
        sqrt_info = self.sqrt_information
        if not hasattr(self, "_split"):
            walk = sqrt_info[..., 9:15, 9:15]
            self._split = (
                self.kernel is None
                and bool((sqrt_info[..., 0:9, 9:15] == 0).all())
                and bool((sqrt_info[..., 9:15, 0:9] == 0).all())
                and bool(
                    (walk - torch.diag_embed(torch.diagonal(walk, dim1=-2, dim2=-1)) == 0).all()
                )
            )
        return sqrt_info[..., 0:9, 0:9] if self._split else None

    def normal_blocks(
        self, values: list[torch.Tensor], kinds: list[VariableKind], pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, list[torch.Tensor], list[list[tuple[slice, slice, torch.Tensor]]]]:
        """Gauss-Newton share from the compact Jacobian rows when the whitening is
        block-diagonal (see :meth:`Factor.normal_blocks`; the rows' Jacobians and values are
        whitened by one product); else the generic form."""
        white_nav = self._split_whitening()
        if white_nav is None or not all(k.name == "nav_state" for k in kinds):
            return super().normal_blocks(values, kinds, pairs)
        residual, rows = self._compact(values, True)
        whitened = white_nav @ rows  # (B, F, 9, 25): whitened Jacobians and residual
        a, c, white9 = whitened[..., 0:15], whitened[..., 15:24], whitened[..., 24]
        walk = torch.diagonal(self.sqrt_information[..., 9:15, 9:15], dim1=-2, dim2=-1)
        white6 = walk * residual[..., 9:15]
        loss = 0.5 * ((white9 * white9).sum(-1) + (white6 * white6).sum(-1))
        walk_grad = walk * white6
        grad = (whitened[..., 0:24].mT @ white9[..., None]).squeeze(-1)  # (B, F, 24): i, j
        grad_i = torch.cat((grad[..., 0:9], grad[..., 9:15] - walk_grad), -1)
        grad_j = torch.cat((grad[..., 15:24], walk_grad), -1)
        walk_info = walk * walk  # (B|1, F, 6) diagonal of the random-walk information
        whole, nav, bias = slice(None), slice(0, 9), slice(9, 15)
        products = {
            (0, 0): (whole, whole, lambda: a.mT @ a),
            (1, 1): (nav, nav, lambda: c.mT @ c),
            (1, 0): (nav, whole, lambda: c.mT @ a),
            (0, 1): (whole, nav, lambda: a.mT @ c),
        }
        pieces = []
        for pair in pairs:
            rows, cols, product = products[pair]
            sign = walk_info if pair[0] == pair[1] else -walk_info
            pieces.append([(rows, cols, product()), (bias, bias, sign)])
        return loss, [grad_i, grad_j], pieces


class WheelOdometryFactor(_Binary):
    """Preintegrated differential-drive odometry between poses i and j (3,): the planar
    increment ``[dx, dy, dyaw]`` in the body frame of i, against the states:
    ``r = [(R_i^T (p_j - p_i))_{x,y} - (dx, dy), wrap(yaw(R_i^T R_j) - dyaw)]``. Its noise is
    the propagated wheel-speed noise, scaled by the slip factor (see
    :func:`msf_torch.backend.preintegration.preintegrate_wheel`).

    Args: group, index_i, index_j (F,); increment (B|1, F, 3) m, m, rad; covariance
    (B|1, F, 3, 3); lever_arm (3,) axle centre in the body frame, m; kernel: robust kernel
    (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("increment", "lever_arm")

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        increment: torch.Tensor,
        covariance: torch.Tensor,
        lever_arm: torch.Tensor | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index_i, index_j, covariance, kernel)
        self.increment = increment
        self.lever_arm = _lever_arm_or_zero(lever_arm, increment)

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 3): [x m, y m, yaw rad]."""
        kind = self.kinds[0]
        return wheel_increment_residual(
            *pose_of(kind, values[0]), *pose_of(kind, values[1]), self.increment, self.lever_arm
        )[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 3) and the Jacobians (B, F, 3, D) w.r.t. the tangents of poses i
        and j (D = 15 or 6; by autodiff for ``se3`` variables)."""
        kind = self.kinds[0]
        if kind.name == "se3":
            return super().residual_and_jacobians(values, kinds)
        residual, jac_i, jac_j = wheel_increment_residual(
            *pose_of(kind, values[0]), *pose_of(kind, values[1]), self.increment, self.lever_arm
        )
        return residual, [_widen(jac_i, kind), _widen(jac_j, kind)]


class CalibratedWheelOdometryFactor(Factor):
    """Differential-drive odometry between poses i and j with the run's wheel calibration
    as a variable (3,): the residual of :class:`WheelOdometryFactor` with the increment
    recomputed from the interval's readings at the current calibration ``c = [k_l, k_r,
    D]`` (:func:`~msf_torch.backend.preintegration.calibrated_wheel_increment`), its yaw
    row multiplied by ``D``:

        r = [(R_i^T (a_j - a_i))_{x,y} - (dx, dy)(c),  D wrap(yaw(R_i^T R_j) - dyaw(c))]

    ``D dyaw = sum (k_r z_r - k_l z_l) dt`` does not depend on ``D``, so the yaw row
    predicts the encoders' wheel-speed difference from the states' yaw change: the
    encoder noise stays on the measured side. In the plain form the noisy encoder yaw
    multiplies ``1 / D`` (errors in variables), which biases ``D`` upwards by
    ``var(noise) / var(dyaw)`` (2-3 % on the calibration benchmark's runs). The noise is
    the one propagated at the nominal calibration, its yaw row and column scaled by the
    nominal track ``D_0``, so at ``D = D_0`` the whitened residual is the plain one.

    Args:
        group, index_i, index_j: ``nav_state`` or ``pose`` variables (F,).
        calibration_group: the ``wheel_calib`` group (one variable, index 0).
        left, right: (B|1, F, L) nominal-radius rim speeds, m/s. dt: (B|1, F, L) s (0 =
        padding). covariance: (B|1, F, 3, 3) of the plain increment. nominal_track: D_0, m.
        lever_arm: (3,) axle centre, body frame, m.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("left", "right", "dt", "lever_arm")

    def __init__(
        self,
        group: str,
        index_i: torch.Tensor,
        index_j: torch.Tensor,
        calibration_group: str,
        left: torch.Tensor,
        right: torch.Tensor,
        dt: torch.Tensor,
        covariance: torch.Tensor,
        nominal_track: float,
        lever_arm: torch.Tensor | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        index_i = index_i.long()
        self.slots = (
            (group, index_i),
            (group, index_j.long()),
            (calibration_group, torch.zeros_like(index_i)),
        )
        scale = torch.ones(3, dtype=covariance.dtype, device=covariance.device)
        scale[2] = float(nominal_track)
        scaled = covariance * scale[:, None] * scale
        self.sqrt_information = sqrt_information(scaled)
        self.kernel = kernel
        self.left, self.right, self.dt = left, right, dt
        self.lever_arm = _lever_arm_or_zero(lever_arm, left)

    def _evaluate(self, values, jacobians: bool):
        kind = self.kinds[0]
        if kind.name == "se3":
            raise ValueError("CalibratedWheelOdometryFactor takes nav_state or pose variables")
        calibration = values[2]
        batch = calibration.shape[0]
        increment, d_increment = calibrated_wheel_increment(
            self.left.expand(batch, *self.left.shape[1:]),
            self.right.expand(batch, *self.right.shape[1:]),
            self.dt.expand(batch, *self.dt.shape[1:]),
            calibration,
        )
        plain, jac_i, jac_j = wheel_increment_residual(
            *pose_of(kind, values[0]), *pose_of(kind, values[1]), increment, self.lever_arm
        )
        track = calibration[..., 2:3]
        ones = torch.ones_like(track)
        scale = torch.cat((ones, ones, track), -1)  # (B, F, 3): rows x, y, yaw * D
        residual = plain * scale
        if not jacobians:
            return residual, None
        jac_c = -d_increment * scale[..., None]
        jac_c[..., 2, 2] = jac_c[..., 2, 2] + plain[..., 2]  # d(D r_yaw)/dD = r_yaw + D dr/dD
        jac_i, jac_j = (_widen(jac, kind) * scale[..., None] for jac in (jac_i, jac_j))
        return residual, [jac_i, jac_j, jac_c]

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, 3): [x m, y m, D times yaw, m rad]."""
        return self._evaluate(values, jacobians=False)[0]

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, 3) and the Jacobians w.r.t. poses i and j (B, F, 3, D) and the
        calibration ``[k_l, k_r, D]`` (B, F, 3, 3); ``kinds`` is not read (``self.kinds``)."""
        return self._evaluate(values, jacobians=True)


class VectorPriorFactor(_Unary):
    """Gaussian prior on a vector-valued variable (``point``, ``wheel_calib``):
    ``r = x - mean`` (D,).

    Args:
        group, index: variables (F,). mean: (B|1, F, D). covariance: (B|1, F, D, D).
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    batched = ("mean",)

    def __init__(
        self,
        group: str,
        index: torch.Tensor,
        mean: torch.Tensor,
        covariance: torch.Tensor,
        kernel: RobustKernel | None = None,
    ) -> None:
        super().__init__(group, index, covariance, kernel)
        self.mean = mean

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, D), in the variable's units."""
        return values[0] - self.mean

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, D) and the identity Jacobian (B, F, D, D); ``kinds`` is not read."""
        residual = values[0] - self.mean
        eye = torch.eye(residual.shape[-1], dtype=residual.dtype, device=residual.device)
        return residual, [eye.expand(*residual.shape, residual.shape[-1])]


class ReprojectionFactor(_Evaluated, Factor):
    """Pinhole reprojection of landmark l in camera pose i (2,): the residual of
    :func:`msf_torch.sensors.camera.reprojection_residual` (normalized coordinates, or
    pixels when ``intrinsics=(fx, fy, cx, cy)``).

    Args:
        pose_group, pose_index: camera-carrying variables (F,) (``nav_state`` or ``pose``).
        point_group, point_index: ``point`` variables (F,).
        measured: (B|1, F, 2). covariance: (B|1, F, 2, 2) (normalized units or px^2).
        body_rotation_cam (3, 3), body_translation_cam (3,): extrinsics (camera in the body
        frame, m). intrinsics: ``(fx, fy, cx, cy)`` px, or None for normalized coordinates.
        kernel: robust kernel (:mod:`msf_torch.backend.robust`), or None for plain least squares.
    """

    def __init__(
        self,
        pose_group: str,
        pose_index: torch.Tensor,
        point_group: str,
        point_index: torch.Tensor,
        measured: torch.Tensor,
        covariance: torch.Tensor,
        body_rotation_cam: torch.Tensor,
        body_translation_cam: torch.Tensor,
        intrinsics: tuple[float, float, float, float] | None = None,
        kernel: RobustKernel | None = None,
    ) -> None:
        self.slots = ((pose_group, pose_index.long()), (point_group, point_index.long()))
        self.sqrt_information = sqrt_information(covariance)
        self.kernel = kernel
        self.measured = measured
        self.body_rotation_cam, self.body_translation_cam = body_rotation_cam, body_translation_cam
        self.intrinsics = intrinsics

    def _evaluate(self, values, jacobians: bool):
        kind = self.kinds[0]
        position, rotation = pose_of(kind, values[0])
        residual, jac, d_landmark = reprojection_residual(
            position,
            rotation,
            values[1],
            self.body_rotation_cam,
            self.body_translation_cam,
            self.measured.expand(*position.shape[:-1], 2),
            self.intrinsics,
        )
        if not jacobians:
            return residual, None
        if kind.name == "se3":  # the se3 step moves the position by R rho
            pose_jac = torch.cat((jac[..., IDX_P] @ rotation, jac[..., IDX_THETA]), -1)
        else:
            pose_jac = _for_kind(jac, kind)
        return residual, [pose_jac, d_landmark]


class MarginalPriorFactor(Factor):
    """Gaussian prior left by marginalisation: ``r = S (x [-] x0) + e`` over several
    ``nav_state`` variables (one factor per problem), where the marginal Gauss-Newton system
    ``(H_m, g_m)`` at ``x0`` was factored as ``H_m = S^T S``, ``e = S^-T g_m``.

    Args:
        slots: ``((group, index (1,)), ...)``. origin: list of (B, 1, 21) per slot.
        sqrt_hessian: ``S`` (B, 1, R, R). offset: ``e`` (B, 1, R).
    """

    def __init__(
        self,
        slots: tuple[tuple[str, torch.Tensor], ...],
        origin: list[torch.Tensor],
        sqrt_hessian: torch.Tensor,
        offset: torch.Tensor,
    ) -> None:
        self.slots = tuple((g, i.long()) for g, i in slots)
        self.origin = origin
        dim = sqrt_hessian.shape[-1]
        self.sqrt_information = torch.eye(dim, dtype=sqrt_hessian.dtype, device=sqrt_hessian.device)
        self.sqrt_hessian, self.offset = sqrt_hessian, offset
        self.kernel = None

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, 1, R), already whitened (the factor's ``sqrt_information`` is I)."""
        local = torch.cat(
            [nav_state_local(o.expand_as(v), v) for o, v in zip(self.origin, values, strict=True)],
            -1,
        )
        return (self.sqrt_hessian @ local[..., None]).squeeze(-1) + self.offset

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind] | None
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, 1, R) and the Jacobians (B, 1, R, 15) per slot; ``kinds`` is not read."""
        parts = [
            nav_state_local(o.expand_as(v), v) for o, v in zip(self.origin, values, strict=True)
        ]
        local = torch.cat(parts, -1)
        residual = (self.sqrt_hessian @ local[..., None]).squeeze(-1) + self.offset
        jacobians = []
        for k, part in enumerate(parts):
            block = self.sqrt_hessian[..., 15 * k : 15 * (k + 1)]
            jacobians.append(block @ nav_state_local_jacobian(part))
        return residual, jacobians


def _lever_arm_or_zero(lever_arm: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """The given lever arm, or a zero (3,) vector in ``like``'s dtype and device."""
    if lever_arm is None:
        return torch.zeros(3, dtype=like.dtype, device=like.device)
    return lever_arm


def _matmul3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for ``a`` (..., m, 3) and ``b`` (..., 3, n) as three broadcast products: for
    such small matrices (m n from about 18) torch's batched CPU kernel is about twice as
    slow."""
    out = a[..., :, 0:1] * b[..., 0:1, :]
    out.addcmul_(a[..., :, 1:2], b[..., 1:2, :])
    return out.addcmul_(a[..., :, 2:3], b[..., 2:3, :])


def _widen(jacobian: torch.Tensor, kind: VariableKind) -> torch.Tensor:
    """Pose Jacobian (..., R, 6) in [dp, dtheta] placed in the 15 nav-state columns when needed."""
    if kind.name == "pose":
        return jacobian
    out = torch.zeros(*jacobian.shape[:-1], 15, dtype=jacobian.dtype, device=jacobian.device)
    out[..., IDX_P] = jacobian[..., 0:3]
    out[..., IDX_THETA] = jacobian[..., 3:6]
    return out
