"""SO(3) geometry on plain tensors and the project's one error-state convention."""

from msf_torch.geometry import conventions, quaternion, se3, so3

__all__ = ["conventions", "quaternion", "se3", "so3"]
