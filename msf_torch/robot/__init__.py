"""Robot description: sensor frames (URDF via pytorch-kinematics, or static transforms)."""

from __future__ import annotations

__all__ = ["FrameTree", "StaticTransform", "inverse_transform", "rpy_matrix"]

from msf_torch.robot.frames import FrameTree, StaticTransform, inverse_transform, rpy_matrix
