"""Robot description: sensor frames (URDF via pytorch-kinematics, or static transforms) and
the robot config YAML (:func:`load_robot_config` -> :class:`RobotConfig`, whose ``layout``
:func:`msf_torch.io.read_rosbag` reads a bag with).

``RobotConfig`` and ``load_robot_config`` are loaded on first use: :mod:`msf_torch.robot.config`
imports :mod:`msf_torch.io`, which imports this package for its frames.
"""

from __future__ import annotations

__all__ = [
    "FrameTree",
    "RobotConfig",
    "StaticTransform",
    "inverse_transform",
    "load_robot_config",
    "rpy_matrix",
]

from typing import Any

from msf_torch.robot.frames import FrameTree, StaticTransform, inverse_transform, rpy_matrix

_FROM_CONFIG = ("RobotConfig", "load_robot_config")


def __getattr__(name: str) -> Any:
    """``RobotConfig`` and ``load_robot_config`` from :mod:`msf_torch.robot.config`."""
    if name in _FROM_CONFIG:
        from msf_torch.robot import config

        return getattr(config, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
