"""Learning: the covariance network and the helpers that feed its outputs to the filter.

Imports point one way (ARCHITECTURE.md, contract 3): this package may import the frontend,
the frontend never imports it.
"""

from msf_torch.learning.covnet import (
    LOG_SCALE_SENSORS,
    RESIDUAL_FEATURES,
    CovNet,
    CovNetConfig,
    CovNetOutput,
    NoiseApplication,
    apply_fusion_weights,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    scaled_noise,
    scaled_pose_covariance,
)

__all__ = [
    "LOG_SCALE_SENSORS",
    "RESIDUAL_FEATURES",
    "CovNet",
    "CovNetConfig",
    "CovNetOutput",
    "NoiseApplication",
    "apply_fusion_weights",
    "load_checkpoint",
    "read_checkpoint",
    "save_checkpoint",
    "scaled_noise",
    "scaled_pose_covariance",
]
