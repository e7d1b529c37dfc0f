"""Visual front end on OpenCV: stereo odometry (features, KLT, PnP / essential matrix,
keyframes, map points), image-quality statistics, tracks for the back end."""

from msf_torch.vision.features import AdaptiveFastDetector, DetectorConfig, KltConfig
from msf_torch.vision.odometry import (
    STATUSES,
    Keyframe,
    StereoVisualOdometry,
    VoConfig,
    VoFrame,
    VoResult,
)
from msf_torch.vision.quality import QUALITY_NAMES, image_quality

__all__ = [
    "STATUSES",
    "QUALITY_NAMES",
    "AdaptiveFastDetector",
    "DetectorConfig",
    "KltConfig",
    "Keyframe",
    "StereoVisualOdometry",
    "VoConfig",
    "VoFrame",
    "VoResult",
    "image_quality",
]
