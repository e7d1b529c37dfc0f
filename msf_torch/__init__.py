"""msf_torch: learning-augmented multi-sensor state estimation for wheeled robots.

The names most users call::

    from msf_torch import load_sequence, load_sequence_config, run_eskf

    seq = load_sequence("datasets/sample_slip.npz")          # or "kitti-gtsam", a folder
    cfg = load_sequence_config(seq.meta)                      # or (seq.meta, "robot.yaml")
    result = run_eskf(seq, cfg)                                # batched ESKF, (B, E + 1, ...)
"""

from msf_torch.frontend.config import (
    EskfConfig,
    config_for_sequence,
    load_config,
    load_sequence_config,
    read_config_keys,
)
from msf_torch.frontend.eskf import EskfNoise, EskfResult, run_eskf
from msf_torch.io import load_sequence
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import Sequence, Trajectory, batch_sequences

__version__ = "0.1.0"

__all__ = [
    "EskfConfig",
    "EskfNoise",
    "EskfResult",
    "Sequence",
    "SimConfig",
    "Trajectory",
    "__version__",
    "batch_sequences",
    "config_for_sequence",
    "load_config",
    "load_sequence_config",
    "read_config_keys",
    "load_sequence",
    "run_eskf",
    "simulate_run",
]
