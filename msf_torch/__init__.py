"""msf_torch: learning-augmented multi-sensor state estimation for wheeled robots."""

__version__ = "0.1.0"

__all__ = ["__version__"]
