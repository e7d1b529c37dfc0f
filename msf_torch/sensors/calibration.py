"""Measurement models with calibration parameters: wheel radii and track width, time offsets.

Wheels. An encoder reports the rim speed computed with the nominal (believed) radius ``r_0``:
``z = theta_dot r_0``. With true radius ``r = k r_0`` the rim speed is ``k z``, so the wheel
calibration parameters are the radius ratios ``k_l``, ``k_r`` (dimensionless, 1 = nominal)
and the track width ``D`` (m):

    v = (k_r z_r + k_l z_l) / 2,    omega = (k_r z_r - k_l z_l) / D

and the residual of :func:`msf_torch.sensors.wheel.wheel_residual` becomes

    r = [R^T v + [w]x l - (v, 0, 0),  (w_m,z - b_g,z) - omega]     (4,)

with ``dr/dk_l = [-z_l / 2, 0, 0, z_l / D]``, ``dr/dk_r = [-z_r / 2, 0, 0, -z_r / D]``,
``dr/dD = [0, 0, 0, omega / D]``. The last is evaluated at the gyro's yaw rate
``w_m,z - b_g,z`` (equal to ``omega`` where the residual vanishes): the encoder ``omega``
carries the encoder noise, and a Jacobian correlated with the residual's noise biases the
track width upwards by ``var(noise) / var(omega)`` (errors in variables; 7 % on the
benchmark's runs).

Time offsets. A sensor sample stamped ``t_s`` on the sensor's clock was taken at
``t_s + t_d`` on the IMU clock (``t_d`` = time offset, s). The filter fuses it at ``t_s``
and predicts it at ``t_s + t_d`` to first order with the current rates:

* GNSS: ``h = p + R l + t_d (v + R ([w]x l))``, ``dh/dt_d`` = antenna velocity (world).
* Pose-source body velocity: ``h = R^T v + [w]x l + t_d (R^T a - [w]x R^T v)`` with ``a`` the
  world acceleration (an input, from the propagation), ``dh/dt_d = d(R^T v)/dt``.
* Pose-source mean rate: the mean gyro rate over the shifted interval,
  ``w_bar + t_d (w_k - w_k-1) / dt`` with the body rate at the pair's two ends; the ESKF
  passes a low-noise estimate of ``(w_k - w_k-1) / dt`` (see ``frontend.eskf``).

Extrinsics (lever arms in the body = IMU frame, m; rotations with a right error
``M = M_hat Exp(dphi)``):

* GNSS antenna lever arm ``l``: ``dh/dl = R (I + t_d [w]x)`` (:func:`gnss_lever_arm_jacobian`).
* Pose source (camera / VO) at lever arm ``l_c`` with mounting rotation ``M`` (sensor ->
  body): its pairs measure the sensor frame's mean velocity ``M^T (R^T v + [w]x l_c)`` and
  rate ``M^T w`` (:func:`mounted_velocity_residual`, :func:`mounted_rate_residual`).
* IMU-to-vehicle rotation ``V`` (vehicle -> body): the wheels and the non-holonomic
  constraint act along the vehicle's axes, ``V^T u`` and ``(V^T w)_z``
  (:func:`vehicle_frame_wheel_residual`, :func:`vehicle_frame_nonholonomic_residual`).
* Dual-antenna heading offset ``delta`` (rad): the baseline is the configured one turned
  about the body z axis, ``b' = Rz(delta) b`` (antennas mounted a few degrees off, or the
  receiver's own heading offset); with ``u = R b'``, ``dr/ddelta = [u_n, -u_e, 0] /
  (u_e^2 + u_n^2) R (e_z x b')`` (:func:`heading_offset_residual`; on level ground -1).
  Its time offset: the azimuth moves at ``g . R (w x b')`` (``g = [u_n, -u_e, 0] /
  (u_e^2 + u_n^2)``, ``w = gyro - b_g``), so ``h = azimuth + t_d g . R (w x b')``,
  ``dh/dt_d = g . R (w x b')``, ``dh/db_g += t_d g . R [b']x``
  (:func:`shifted_heading_residual`; the shift's dependence on the attitude and on
  ``delta`` is neglected, second order: ``t_d`` times the rate times the error).

Sign convention ``r = h(x) - z``; nav Jacobians w.r.t. ``[dp, dv, dtheta, db_g, db_a]``
(``geometry.conventions``), calibration Jacobians as separate columns.
"""

from __future__ import annotations

__all__ = [
    "calibrated_wheel_residual",
    "shifted_gnss_residual",
    "shifted_body_velocity_residual",
    "shifted_mean_rate_residual",
    "gnss_lever_arm_jacobian",
    "heading_offset_residual",
    "shifted_heading_residual",
    "mounted_velocity_residual",
    "mounted_rate_residual",
    "vehicle_frame_wheel_residual",
    "vehicle_frame_nonholonomic_residual",
]

import torch

from msf_torch.geometry import so3
from msf_torch.geometry.conventions import IDX_BG, IDX_THETA, IDX_V
from msf_torch.sensors._jacobian import error_state_jacobian
from msf_torch.sensors.gnss import (
    azimuth_and_gradient,
    gnss_heading_residual,
    gnss_residual,
    gnss_velocity_residual,
)
from msf_torch.sensors.pose import mean_rate_residual
from msf_torch.sensors.wheel import body_velocity_residual, wheel_residual, wheel_speed_and_yaw_rate


def _wheel_calibration_jacobian(
    left_reading: torch.Tensor,
    right_reading: torch.Tensor,
    track_width: torch.Tensor,
    yaw_rate: torch.Tensor,
) -> torch.Tensor:
    """(..., 4, 3) Jacobian of the wheel residual ``[u - (v, 0, 0), w_z - omega]`` w.r.t.
    ``[k_l, k_r, D]``: ``v = (k_r z_r + k_l z_l) / 2``, ``omega = (k_r z_r - k_l z_l) / D``,
    with ``d omega / dD = -omega / D`` taken at the gyro's ``yaw_rate`` (rad/s), not the
    encoders' (a Jacobian correlated with the residual's noise biases D)."""
    zero = torch.zeros_like(left_reading)
    d_left = torch.stack((-0.5 * left_reading, zero, zero, left_reading / track_width), -1)
    d_right = torch.stack((-0.5 * right_reading, zero, zero, -right_reading / track_width), -1)
    d_track = torch.stack((zero, zero, zero, yaw_rate / track_width), -1)
    return torch.stack((d_left, d_right, d_track), -1)


def calibrated_wheel_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    left_reading: torch.Tensor,
    right_reading: torch.Tensor,
    radius_ratio: torch.Tensor,
    track_width: torch.Tensor,
    lever_arm: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Wheel residual with calibration parameters.

    Args:
        velocity, rotation, gyro, gyro_bias, lever_arm: as
            :func:`msf_torch.sensors.wheel.wheel_residual`.
        left_reading, right_reading: (...,) rim speeds computed with the nominal radius, m/s.
        radius_ratio: (..., 2) ``[k_l, k_r]`` true radius / nominal radius.
        track_width: (...,) ``D``, m.
    Returns:
        residual (..., 4), nav Jacobian (..., 4, 15), calibration Jacobian (..., 4, 3) w.r.t.
        ``[k_l, k_r, D]``.
    """
    left = radius_ratio[..., 0] * left_reading
    right = radius_ratio[..., 1] * right_reading
    residual, jac = wheel_residual(
        velocity, rotation, gyro, gyro_bias, left, right, track_width, lever_arm
    )
    yaw_rate = gyro[..., 2] - gyro_bias[..., 2]
    return (
        residual,
        jac,
        _wheel_calibration_jacobian(left_reading, right_reading, track_width, yaw_rate),
    )


def shifted_gnss_residual(
    position: torch.Tensor,
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    measured: torch.Tensor,
    time_offset: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """GNSS residual with the fix taken ``time_offset`` after the filter time.

    Args:
        position, velocity: (..., 3) IMU position (m) and velocity (m/s), world.
        rotation: (..., 3, 3) body -> world. gyro, gyro_bias: (..., 3) rad/s.
        lever_arm: (..., 3) antenna in the body frame, m. measured: (..., 3) fix, m.
        time_offset: (...,) ``t_d``, s.
    Returns:
        residual (..., 3) m, nav Jacobian (..., 3, 15), time-offset Jacobian (..., 3, 1) m/s.
    """
    # the fix t_d later: the antenna moved on by t_d times its velocity (and Jacobian)
    lever = lever_arm.expand_as(position)
    at_time, jac_position = gnss_residual(position, rotation, lever, measured)
    antenna_velocity, jac_velocity = gnss_velocity_residual(
        velocity, rotation, gyro, gyro_bias, lever, torch.zeros_like(velocity)
    )
    offset = time_offset[..., None]
    residual = at_time + offset * antenna_velocity
    jac = jac_position + offset[..., None] * jac_velocity
    return residual, jac, antenna_velocity[..., None]


def shifted_body_velocity_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    acceleration: torch.Tensor,
    measured: torch.Tensor,
    time_offset: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Body-frame velocity of a point at ``lever_arm``, predicted ``time_offset`` later.

    ``h = R^T v + [w]x l + t_d (R^T a - [w]x R^T v)``; ``a`` (the world acceleration) is an
    input, not a state.

    Args:
        velocity: (..., 3) world, m/s. rotation: (..., 3, 3). gyro, gyro_bias: (..., 3) rad/s.
        lever_arm: (..., 3) m. acceleration: (..., 3) world, m/s^2.
        measured: (..., 3) body-frame velocity, m/s. time_offset: (...,) s.
    Returns:
        residual (..., 3) m/s, nav Jacobian (..., 3, 15), time-offset Jacobian (..., 3, 1).
    """
    lever = lever_arm.expand_as(velocity)
    omega = gyro - gyro_bias
    v_body = (rotation.mT @ velocity[..., None]).squeeze(-1)
    a_body = (rotation.mT @ acceleration[..., None]).squeeze(-1)
    rate = a_body - torch.linalg.cross(omega, v_body)
    offset = time_offset[..., None]
    residual = v_body + torch.linalg.cross(omega, lever) + offset * rate - measured
    scale = offset[..., None]
    hat_w, hat_vb = so3.hat(omega), so3.hat(v_body)
    jac = error_state_jacobian(
        3,
        [
            (IDX_V, rotation.mT - scale * hat_w @ rotation.mT),
            (IDX_THETA, hat_vb + scale * (so3.hat(a_body) - hat_w @ hat_vb)),
            (IDX_BG, so3.hat(lever) - scale * hat_vb),
        ],
        like=velocity,
    )
    return residual, jac, rate[..., None]


def shifted_mean_rate_residual(
    mean_gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    gyro_rate_change: torch.Tensor,
    measured_rate: torch.Tensor,
    time_offset: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean-rate residual over an interval shifted by ``time_offset``.

    Args:
        mean_gyro: (..., 3) mean raw gyro over the unshifted interval, rad/s.
        gyro_bias: (..., 3) rad/s.
        gyro_rate_change: (..., 3) ``(w_k - w_k-1) / dt``, body rate at the interval's
            ends (or an estimate of it), rad/s^2.
        measured_rate: (..., 3) the source's mean body rate, rad/s.
        time_offset: (...,) s.
    Returns:
        residual (..., 3) rad/s, nav Jacobian (..., 3, 15), time-offset Jacobian (..., 3, 1).
    """
    residual, jac = mean_rate_residual(mean_gyro, gyro_bias, measured_rate)
    return residual + time_offset[..., None] * gyro_rate_change, jac, gyro_rate_change[..., None]


def gnss_lever_arm_jacobian(
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    time_offset: torch.Tensor,
) -> torch.Tensor:
    """Jacobian (..., 3, 3) of the (shifted) GNSS residual w.r.t. the antenna lever arm.

    ``h = p + R l + t_d (v + R ([w]x l))`` gives ``dh/dl = R (I + t_d [w]x)`` (``t_d = 0``:
    :func:`msf_torch.sensors.gnss.gnss_residual`).

    Args:
        rotation: (..., 3, 3) body -> world. gyro, gyro_bias: (..., 3) rad/s.
        time_offset: (...,) ``t_d``, s.
    """
    eye = so3.identity(rotation.dtype, rotation.device)
    return rotation @ (eye + time_offset[..., None, None] * so3.hat(gyro - gyro_bias))


def heading_offset_residual(
    rotation: torch.Tensor, baseline: torch.Tensor, offset: torch.Tensor, measured: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dual-antenna heading residual with the baseline turned by ``offset`` about body z.

    Args:
        rotation: (..., 3, 3) body -> world. baseline: (3,) configured primary -> secondary
            antenna, body frame. offset: (...,) ``delta``, rad. measured: (...,) azimuth
            clockwise from north, rad.

    Returns:
        residual (..., 1) rad and nav Jacobian (..., 1, 15) of
        :func:`msf_torch.sensors.gnss.gnss_heading_residual` at ``b' = Rz(delta) b``, and
        ``dr/ddelta`` (..., 1, 1).
    """
    zeros = torch.zeros_like(offset)
    turn = so3.exp(torch.stack((zeros, zeros, offset), -1))
    turned = (turn @ baseline.expand(*offset.shape, 3)[..., None])[..., 0]
    residual, jac = gnss_heading_residual(rotation, turned, measured)
    # the azimuth row of the attitude Jacobian is d(az)/du (-R [b']x); (e_z x b') = -[b']x e_z
    d_offset = jac[..., IDX_THETA][..., 2:3]
    return residual, jac, d_offset


def shifted_heading_residual(
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    baseline: torch.Tensor,
    offset: torch.Tensor,
    time_offset: torch.Tensor,
    measured: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dual-antenna heading residual with the baseline turned by ``offset`` about body z and
    the heading predicted ``time_offset`` later with the current body rate.

    Args:
        rotation: (..., 3, 3) body -> world. gyro, gyro_bias: (..., 3) rad/s. baseline: (3,)
            configured antenna baseline, body frame. offset: (...,) rad. time_offset:
            (...,) ``t_d``, s. measured: (...,) azimuth clockwise from north, rad.

    Returns:
        residual (..., 1) rad, nav Jacobian (..., 1, 15), ``dr/ddelta`` (..., 1, 1) and
        ``dr/dt_d`` (..., 1, 1).
    """
    residual, jac, d_offset = heading_offset_residual(rotation, baseline, offset, measured)
    zeros = torch.zeros_like(offset)
    turn = so3.exp(torch.stack((zeros, zeros, offset), -1))
    turned = (turn @ baseline.expand(*offset.shape, 3)[..., None])[..., 0]
    _, gradient, _ = azimuth_and_gradient((rotation @ turned[..., None])[..., 0])
    rate = torch.linalg.cross(gyro - gyro_bias, turned)  # w x b'
    azimuth_rate = (gradient * (rotation @ rate[..., None])[..., 0]).sum(-1)
    d_bias = (gradient[..., None, :] @ rotation @ so3.hat(turned))[..., 0, :]
    jac = jac.clone()
    jac[..., 0, IDX_BG] = jac[..., 0, IDX_BG] + time_offset[..., None] * d_bias
    residual = residual + (time_offset * azimuth_rate)[..., None]
    return residual, jac, d_offset, azimuth_rate[..., None, None]


def mounted_velocity_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    mount_rotation: torch.Tensor,
    acceleration: torch.Tensor,
    measured: torch.Tensor,
    time_offset: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """Sensor-frame velocity of a pose source mounted at ``(lever_arm, mount_rotation)``.

    ``h = M^T u`` with ``u`` the body-frame velocity of the sensor origin predicted
    ``time_offset`` later (:func:`shifted_body_velocity_residual`) and ``M`` the mounting
    rotation (sensor -> body, error ``M = M_hat Exp(dphi)``): ``dh/dl = M^T [w]x``,
    ``dh/dphi = [M^T u]x``.

    Args:
        velocity, rotation, gyro, gyro_bias, acceleration, time_offset: as
            :func:`shifted_body_velocity_residual`.
        lever_arm: (..., 3) sensor origin in the body frame, m.
        mount_rotation: (..., 3, 3) sensor -> body.
        measured: (..., 3) the sensor-frame velocity of its origin, m/s.
    Returns:
        residual (..., 3) m/s, nav Jacobian (..., 3, 15), time-offset Jacobian (..., 3, 1),
        lever-arm Jacobian (..., 3, 3), mount-rotation Jacobian (..., 3, 3).
    """
    predicted, jac, jac_time = shifted_body_velocity_residual(
        velocity,
        rotation,
        gyro,
        gyro_bias,
        lever_arm,
        acceleration,
        torch.zeros_like(velocity),
        time_offset,
    )
    to_sensor = mount_rotation.mT
    in_sensor = (to_sensor @ predicted[..., None]).squeeze(-1)
    return (
        in_sensor - measured,
        to_sensor @ jac,
        to_sensor @ jac_time,
        to_sensor @ so3.hat(gyro - gyro_bias),
        so3.hat(in_sensor),
    )


def mounted_rate_residual(
    mean_gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    gyro_rate_change: torch.Tensor,
    mount_rotation: torch.Tensor,
    measured_rate: torch.Tensor,
    time_offset: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """Sensor-frame mean rate of a pose source with mounting rotation ``M`` (sensor -> body).

    ``h = M^T (w_bar - b_g + t_d dw/dt)`` (:func:`shifted_mean_rate_residual` in the sensor
    frame), ``dh/dphi = [h]x`` for ``M = M_hat Exp(dphi)``.

    Args:
        mean_gyro, gyro_bias, gyro_rate_change, time_offset: as
            :func:`shifted_mean_rate_residual`.
        mount_rotation: (..., 3, 3). measured_rate: (..., 3) the source's mean rate, rad/s.
    Returns:
        residual (..., 3) rad/s, nav Jacobian (..., 3, 15), time-offset Jacobian (..., 3, 1),
        mount-rotation Jacobian (..., 3, 3).
    """
    predicted, jac, jac_time = shifted_mean_rate_residual(
        mean_gyro, gyro_bias, gyro_rate_change, torch.zeros_like(mean_gyro), time_offset
    )
    to_sensor = mount_rotation.mT
    in_sensor = (to_sensor @ predicted[..., None]).squeeze(-1)
    return in_sensor - measured_rate, to_sensor @ jac, to_sensor @ jac_time, so3.hat(in_sensor)


def vehicle_frame_wheel_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    left_reading: torch.Tensor,
    right_reading: torch.Tensor,
    radius_ratio: torch.Tensor,
    track_width: torch.Tensor,
    lever_arm: torch.Tensor,
    vehicle_rotation: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """Wheel residual in the vehicle frame, misaligned from the IMU (body) frame.

    The wheels (and the non-holonomic constraint) act along the vehicle's axes; ``V``
    (vehicle -> body, error ``V = V_hat Exp(dphi)``) rotates the body-frame axle velocity
    ``u = R^T v + [w]x l`` and rate ``w`` into them:

        r = [V^T u - (v, 0, 0),  (V^T w)_z - omega]     (4,)

    ``dr/dphi = [[V^T u]x; ([V^T w]x)_z]``; the wheel-calibration columns are those of
    :func:`calibrated_wheel_residual` with the track-width row at the vehicle yaw rate.

    Args:
        velocity, rotation, gyro, gyro_bias, lever_arm: as
            :func:`msf_torch.sensors.wheel.wheel_residual` (lever arm in the body frame).
        left_reading, right_reading, radius_ratio, track_width: as
            :func:`calibrated_wheel_residual`.
        vehicle_rotation: (..., 3, 3) vehicle -> body.
    Returns:
        residual (..., 4), nav Jacobian (..., 4, 15), wheel-calibration Jacobian (..., 4, 3)
        w.r.t. ``[k_l, k_r, D]``, vehicle-rotation Jacobian (..., 4, 3).
    """
    left = radius_ratio[..., 0] * left_reading
    right = radius_ratio[..., 1] * right_reading
    speed, turn = wheel_speed_and_yaw_rate(left, right, track_width)
    zero = torch.zeros_like(speed)
    to_vehicle = vehicle_rotation.mT
    axle, jac_axle = body_velocity_residual(
        velocity, rotation, gyro, gyro_bias, lever_arm, torch.zeros_like(velocity)
    )
    axle_vehicle = (to_vehicle @ axle[..., None]).squeeze(-1)
    rate_vehicle = (to_vehicle @ (gyro - gyro_bias)[..., None]).squeeze(-1)
    residual = torch.cat(
        (
            axle_vehicle - torch.stack((speed, zero, zero), -1),
            (rate_vehicle[..., 2] - turn)[..., None],
        ),
        -1,
    )
    jac_yaw = torch.zeros_like(jac_axle[..., :1, :])
    jac_yaw[..., 0, IDX_BG] = -to_vehicle[..., 2, :]
    jac = torch.cat((to_vehicle @ jac_axle, jac_yaw), -2)
    jac_calibration = _wheel_calibration_jacobian(
        left_reading, right_reading, track_width, rate_vehicle[..., 2]
    )
    jac_rotation = torch.cat((so3.hat(axle_vehicle), so3.hat(rate_vehicle)[..., 2:3, :]), -2)
    return residual, jac, jac_calibration, jac_rotation


def vehicle_frame_nonholonomic_residual(
    velocity: torch.Tensor,
    rotation: torch.Tensor,
    gyro: torch.Tensor,
    gyro_bias: torch.Tensor,
    lever_arm: torch.Tensor,
    vehicle_rotation: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lateral and vertical velocity (..., 2) m/s in the vehicle frame (``V^T u``, see
    :func:`vehicle_frame_wheel_residual`), nav Jacobian (..., 2, 15) and vehicle-rotation
    Jacobian (..., 2, 3).

    Args: as :func:`vehicle_frame_wheel_residual` (no readings).
    """
    point, jac = body_velocity_residual(
        velocity, rotation, gyro, gyro_bias, lever_arm, torch.zeros_like(velocity)
    )
    to_vehicle = vehicle_rotation.mT
    in_vehicle = (to_vehicle @ point[..., None]).squeeze(-1)
    return in_vehicle[..., 1:3], (to_vehicle @ jac)[..., 1:3, :], so3.hat(in_vehicle)[..., 1:3, :]
