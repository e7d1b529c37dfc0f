"""Measurement models: one residual ``r = h(x) - z`` per sensor, its error-state Jacobian and
noise. The ESKF front end and the LM back end both call these."""

from msf_torch.sensors.camera import reprojection_residual
from msf_torch.sensors.gnss import gnss_heading_residual, gnss_residual, gnss_velocity_residual
from msf_torch.sensors.imu import ImuNoise, Preintegrated, preintegrate, propagate_nominal, zoh_step
from msf_torch.sensors.plane import plane_residual
from msf_torch.sensors.pose import mean_rate_residual, pose_residual, relative_pose_residual
from msf_torch.sensors.vehicle import nonholonomic_residual, zero_velocity_residual
from msf_torch.sensors.wheel import (
    body_velocity_residual,
    wheel_increment_residual,
    wheel_residual,
    wheel_speed_and_yaw_rate,
)

__all__ = [
    "ImuNoise",
    "Preintegrated",
    "body_velocity_residual",
    "gnss_heading_residual",
    "gnss_residual",
    "gnss_velocity_residual",
    "mean_rate_residual",
    "nonholonomic_residual",
    "plane_residual",
    "pose_residual",
    "preintegrate",
    "propagate_nominal",
    "relative_pose_residual",
    "reprojection_residual",
    "wheel_increment_residual",
    "wheel_residual",
    "wheel_speed_and_yaw_rate",
    "zero_velocity_residual",
    "zoh_step",
]
