"""CovNet: a small network that sets the filter's noise from a window of sensor data.

Inputs, per window of ``L`` IMU samples (default ``L = 100`` at 100 Hz, i.e. 1 s):

* ``imu`` (B, L, 6): ``[gyro (rad/s), accel (m/s^2)]`` in the body frame, divided inside by
  ``CovNetConfig.gyro_scale_radps`` and ``accel_scale_mps2``.
* ``wheel`` (B, L, 2): ``[left, right]`` rim speeds, m/s, resampled onto the IMU times,
  divided inside by ``wheel_scale_mps``; with ``wheel_present`` (B,) or (B, L) bool. Where
  the wheels are absent the speeds are zeroed inside, so any placeholder value will do.
* ``residual_stats`` (B, S, K): per pose source (``CovNetConfig.pose_sources``, default
  ``("gnss", "vo", "lidar")``) the K = 4 features of :data:`RESIDUAL_FEATURES`, measured over
  the window by a reference pass of the filter with the configured (unlearned) noise
  (:func:`msf_torch.learning.features.run_features`):

  0. ``nis_per_dof``: mean normalised innovation squared of the source's measurements
     divided by the measurement dimension (about 1 for a consistent filter);
  1. ``nis_max_per_dof``: the largest of them in the window;
  2. ``rejected_fraction``: fraction of the source's measurements the gate rejected, [0, 1];
  3. ``dropout_fraction``: fraction of the source's expected epochs without a measurement,
     [0, 1] (1 = the source is absent; the other three are 0 then).

* ``weather`` (B,) int64, optional: an index into ``CovNetConfig.weather_classes`` or
  ``CovNetConfig.unknown_weather`` (= the number of classes) when unknown. ``None`` means
  unknown for the whole batch.

Outliers cannot blow up the activations: the normalised signals are clipped to
``+-CovNetConfig.input_clip`` and the residual features pass through ``asinh`` (the identity
near 0, logarithmic beyond), so the outputs stay finite and bounded for any finite input.

Architecture (29,389 parameters with the default config; 32,493 with
``residual_pooling="per_source"``): a 1-D convolution encoder over the 9 signal channels
(IMU, wheel, wheel presence; a patch convolution with kernel = stride = ``patch``, then two
stride-2 convolutions) with mean and max pooling over time -> signal embedding (E); a
per-source MLP on the residual features plus a learned source embedding, pooled over the S
sources -> residual embedding (E); a weather head on both embeddings -> weather
logits (W); a weather embedding, the label's when known and the softmax of the weather
logits mixed over the class embeddings when unknown; a trunk MLP on the three embeddings ->
the log-scale head and, with each source's embedding, the fusion-weight head.

Outputs (:class:`CovNetOutput`):

* ``log_scales`` (B, 7): natural-log *variance* scales for :data:`LOG_SCALE_SENSORS`
  ``[wheel, nhc, gnss, vo, lidar, imu_gyro, imu_accel]``, each bounded by a scaled tanh,
  ``b * tanh(raw / b)`` with ``b = CovNetConfig.log_scale_bounds[i]`` (default 3: variance
  scale in ``[e^-3, e^3]``, sigma scale in ``[e^-1.5, e^1.5]``).
* ``fusion_weights`` (B, S): per-source trust in (0, 1), a sigmoid per source (not a softmax:
  several sources may be good at once, or none), of a logit bounded to
  ``+-fusion_logit_bound`` (default 6: weights in [0.0025, 0.9975]). A weight ``w`` divides
  the source's variance (:func:`apply_fusion_weights`).
* ``weather_logits`` (B, W): always produced, so a caller can train the head on labelled
  windows and report its accuracy.

Mapping onto the filter: :func:`scaled_noise` scales an
:class:`~msf_torch.frontend.eskf.EskfNoise` (wheel, NHC, GNSS, gyro and accelerometer noise;
sigmas by ``exp(log_scale / 2)``), :func:`scaled_pose_covariance` scales a VO or LiDAR pose
stream's covariances. The frontend never imports this module (ARCHITECTURE.md, contract 3).

Throughput: ``benchmarks/covnet_speed.py`` (one JSON line).
"""

from __future__ import annotations

__all__ = [
    "LOG_SCALE_SENSORS",
    "RESIDUAL_FEATURES",
    "CovNetConfig",
    "CovNetOutput",
    "CovNet",
    "scaled_noise",
    "scaled_pose_covariance",
    "apply_fusion_weights",
    "IMU_RATE_TOLERANCE",
    "NoiseApplication",
    "save_checkpoint",
    "load_checkpoint",
    "read_checkpoint",
]

import dataclasses
import math
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from msf_torch.frontend.eskf import EskfNoise
from msf_torch.sensors.imu import ImuNoise

LOG_SCALE_SENSORS = ("wheel", "nhc", "gnss", "vo", "lidar", "imu_gyro", "imu_accel")
RESIDUAL_FEATURES = (
    "nis_per_dof",
    "nis_max_per_dof",
    "rejected_fraction",
    "dropout_fraction",
)
_CHECKPOINT_FORMAT = "msf_torch.covnet/1"
_SIGNAL_CHANNELS = 9  # gyro (3), accel (3), wheel speeds (2), wheel presence (1)


def _require_known_keys(cls: type, values: dict[str, Any]) -> None:
    """Raise ``ValueError`` naming the keys of ``values`` that are not fields of ``cls``."""
    unknown = set(values) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys {sorted(unknown)}")


@dataclass
class CovNetConfig:
    """CovNet sizes, bounds and input scales (plain types, stored in checkpoints).

    Attributes:
        window_length: L, IMU samples per window (100 = 1 s at 100 Hz).
        channels: C, channels of each convolution layer.
        embedding: E, size of the signal, residual, source and weather embeddings.
        hidden: H, width of the trunk and head MLPs.
        patch: samples per patch of the first convolution (kernel = stride = patch).
        pose_sources: names of the S pose sources, each one of :data:`LOG_SCALE_SENSORS`.
        weather_classes: names of the W weather classes (default: the simulator's
            conditions); index W means unknown.
        log_scale_bounds: bound b of each of the 7 log-variance scales (natural log).
        fusion_logit_bound: bound of the fusion-weight logits.
        gyro_scale_radps, accel_scale_mps2, wheel_scale_mps: input divisors, rad/s, m/s^2,
            m/s.
        input_clip: the normalised signals are clipped to +-input_clip (8 rad/s, 78 m/s^2
            and 40 m/s with the default scales).
        residual_pooling: ``"mean"`` (default; the shipped checkpoints' and a config
            without the key) averages the S source embeddings; the MLP is shared and the
            source embedding is added after it, so the average is the same whichever
            source's residuals are large: the trunk and the weather head cannot tell a bad
            VO (night) from a bad LiDAR (fog). ``"per_source"`` concatenates them and
            projects to E. On the weather recipe (2026-11-28, 10 held-out runs) per-source
            pooling infers the weather in 75.5 % of windows (mean pooling 43.5 %), ATE
            0.563 m against 0.559 m, but position NEES inside the 95 % bounds in 87.1 % of
            epochs (mean pooling 94.5 %).
    """

    window_length: int = 100
    channels: int = 32
    embedding: int = 32
    hidden: int = 64
    patch: int = 4
    pose_sources: tuple[str, ...] = ("gnss", "vo", "lidar")
    weather_classes: tuple[str, ...] = ("sunny", "rain", "fog", "night", "snow")
    log_scale_bounds: tuple[float, ...] = (3.0,) * len(LOG_SCALE_SENSORS)
    fusion_logit_bound: float = 6.0
    gyro_scale_radps: float = 1.0
    accel_scale_mps2: float = 9.80665
    wheel_scale_mps: float = 5.0
    input_clip: float = 8.0
    residual_pooling: str = "mean"

    @property
    def unknown_weather(self) -> int:
        """The weather index that means unknown (= the number of classes)."""
        return len(self.weather_classes)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        for key in ("window_length", "channels", "embedding", "hidden", "patch"):
            value = getattr(self, key)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"CovNetConfig.{key} must be a positive int, got {value!r}")
        if self.window_length < self.patch:
            raise ValueError("CovNetConfig.window_length must be at least one patch")
        if not self.pose_sources or any(s not in LOG_SCALE_SENSORS for s in self.pose_sources):
            raise ValueError(
                f"CovNetConfig.pose_sources must be names from {LOG_SCALE_SENSORS}, "
                f"got {self.pose_sources!r}"
            )
        if len(set(self.pose_sources)) != len(self.pose_sources):
            raise ValueError(f"CovNetConfig.pose_sources has duplicates: {self.pose_sources!r}")
        if len(self.weather_classes) < 2:
            raise ValueError("CovNetConfig.weather_classes needs at least 2 classes")
        if self.residual_pooling not in ("per_source", "mean"):
            raise ValueError(
                "CovNetConfig.residual_pooling must be 'per_source' or 'mean', "
                f"got {self.residual_pooling!r}"
            )
        if len(self.log_scale_bounds) != len(LOG_SCALE_SENSORS):
            raise ValueError(
                f"CovNetConfig.log_scale_bounds needs {len(LOG_SCALE_SENSORS)} entries "
                f"{LOG_SCALE_SENSORS}, got {len(self.log_scale_bounds)}"
            )
        bounds = (*self.log_scale_bounds, self.fusion_logit_bound)
        bounds += (self.gyro_scale_radps, self.accel_scale_mps2, self.wheel_scale_mps)
        bounds += (self.input_clip,)
        if not all(math.isfinite(b) and b > 0 for b in bounds):
            raise ValueError("CovNetConfig bounds and input scales must be positive and finite")

    def to_dict(self) -> dict[str, Any]:
        """Plain Python types (tuples as lists), loadable with ``torch.load(weights_only=True)``."""
        return {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> CovNetConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``; a dict without
        ``residual_pooling`` (written before the key existed) means the default ``"mean"``."""
        _require_known_keys(cls, values)
        config = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
        config.validate()
        return config


@dataclass
class CovNetOutput:
    """What :class:`CovNet` returns.

    Attributes:
        log_scales: (B, 7) natural-log variance scales for :data:`LOG_SCALE_SENSORS`.
        fusion_weights: (B, S) per-pose-source weights in (0, 1).
        weather_logits: (B, W) unnormalised class scores of the weather head.
    """

    log_scales: torch.Tensor
    fusion_weights: torch.Tensor
    weather_logits: torch.Tensor


def _bounded(raw: torch.Tensor, bound: torch.Tensor | float) -> torch.Tensor:
    """Scaled tanh ``b * tanh(raw / b)``: slope 1 at 0, values in (-b, b)."""
    return bound * torch.tanh(raw / bound)


class CovNet(nn.Module):
    """Window of IMU / wheel signals + pose residual statistics -> noise scales and weights.

    See the module docstring for the inputs, the architecture and the outputs. Works in the
    dtype and on the device of its parameters (float32 by default).

    Args:
        config: sizes, pose sources and weather classes (:class:`CovNetConfig`; its defaults
            when None). Validated here.
    """

    def __init__(self, config: CovNetConfig | None = None) -> None:
        super().__init__()
        config = config or CovNetConfig()
        config.validate()
        self.config = config
        c, e, h = config.channels, config.embedding, config.hidden
        n_sources, n_weather = len(config.pose_sources), len(config.weather_classes)
        self.encoder = nn.Sequential(
            nn.Conv1d(_SIGNAL_CHANNELS, c, config.patch, stride=config.patch),
            nn.ReLU(),
            nn.Conv1d(c, c, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv1d(c, c, 3, stride=2, padding=1),
            nn.ReLU(),
        )
        self.signal_proj = nn.Linear(2 * c, e)
        self.source_mlp = nn.Sequential(
            nn.Linear(len(RESIDUAL_FEATURES), e), nn.GELU(), nn.Linear(e, e)
        )
        self.source_embedding = nn.Parameter(0.1 * torch.randn(n_sources, e))
        if config.residual_pooling == "per_source":
            self.residual_proj = nn.Linear(n_sources * e, e)
        self.weather_head = nn.Sequential(nn.Linear(2 * e, h), nn.GELU(), nn.Linear(h, n_weather))
        self.weather_embedding = nn.Parameter(0.1 * torch.randn(n_weather, e))
        self.trunk = nn.Sequential(nn.Linear(3 * e, h), nn.GELU(), nn.Linear(h, h), nn.GELU())
        self.log_scale_head = nn.Linear(h, len(LOG_SCALE_SENSORS))
        self.fusion_head = nn.Sequential(nn.Linear(h + e, e), nn.GELU(), nn.Linear(e, 1))
        with torch.no_grad():  # start near the base noise (log scale ~ 0)
            self.log_scale_head.weight.mul_(0.1)
            self.log_scale_head.bias.zero_()
        self.register_buffer(
            "log_scale_bounds", torch.tensor(config.log_scale_bounds), persistent=False
        )
        scales = [config.gyro_scale_radps] * 3 + [config.accel_scale_mps2] * 3
        scales += [config.wheel_scale_mps] * 2
        self.register_buffer("input_scales", torch.tensor(scales)[:, None], persistent=False)

    def forward(
        self,
        imu: torch.Tensor,
        wheel: torch.Tensor,
        wheel_present: torch.Tensor,
        residual_stats: torch.Tensor,
        weather: torch.Tensor | None = None,
    ) -> CovNetOutput:
        """Noise scales, fusion weights and weather logits for a batch of windows.

        Args:
            imu: (B, L, 6) ``[gyro rad/s, accel m/s^2]``.
            wheel: (B, L, 2) left / right rim speed, m/s (ignored where absent).
            wheel_present: (B,) or (B, L) bool, wheel data present.
            residual_stats: (B, S, 4) pose-source features, :data:`RESIDUAL_FEATURES`.
            weather: (B,) int64 class index or ``config.unknown_weather``; None = unknown.

        Returns:
            :class:`CovNetOutput` with (B, 7), (B, S) and (B, W) tensors.

        Raises:
            ValueError: an input's shape disagrees with the config.
        """
        cfg = self.config
        batch, length = imu.shape[0], cfg.window_length
        n_sources = len(cfg.pose_sources)
        expected = {
            "imu": (imu, (batch, length, 6)),
            "wheel": (wheel, (batch, length, 2)),
            "residual_stats": (residual_stats, (batch, n_sources, len(RESIDUAL_FEATURES))),
        }
        for name, (value, shape) in expected.items():
            if tuple(value.shape) != shape:
                raise ValueError(f"CovNet input {name} must be {shape}, got {tuple(value.shape)}")
        if tuple(wheel_present.shape) not in ((batch,), (batch, length)):
            raise ValueError(
                f"CovNet input wheel_present must be ({batch},) or ({batch}, {length}), "
                f"got {tuple(wheel_present.shape)}"
            )
        if wheel_present.dim() == 1:
            wheel_present = wheel_present[:, None].expand(batch, length)
        dtype = self.source_embedding.dtype
        present = wheel_present.to(dtype)[:, None]  # (B, 1, L)
        signals = torch.cat([imu.to(dtype).mT, wheel.to(dtype).mT * present], 1)
        signals = (signals / self.input_scales.to(dtype)).clamp(-cfg.input_clip, cfg.input_clip)
        features = self.encoder(torch.cat([signals, present], 1))  # (B, C, L')
        signal = self.signal_proj(torch.cat([features.mean(-1), features.amax(-1)], -1))
        per_source = self.source_mlp(torch.asinh(residual_stats.to(dtype)))
        per_source = per_source + self.source_embedding  # (B, S, E)
        if cfg.residual_pooling == "per_source":
            residual = self.residual_proj(per_source.flatten(1))
        else:
            residual = per_source.mean(1)

        weather_logits = self.weather_head(torch.cat([signal, residual], -1))
        mix = torch.softmax(weather_logits, -1)
        if weather is not None:
            if tuple(weather.shape) != (batch,):
                raise ValueError(f"CovNet input weather must be ({batch},), got {weather.shape}")
            if bool(((weather < 0) | (weather > cfg.unknown_weather)).any()):
                raise ValueError(
                    f"CovNet input weather must lie in [0, {cfg.unknown_weather}] "
                    f"({cfg.unknown_weather} = unknown)"
                )
            known = weather != cfg.unknown_weather
            one_hot = nn.functional.one_hot(
                torch.where(known, weather, 0), len(cfg.weather_classes)
            ).to(dtype)
            mix = torch.where(known[:, None], one_hot, mix)
        weather_cond = mix @ self.weather_embedding

        hidden = self.trunk(torch.cat([signal, residual, weather_cond], -1))
        log_scales = _bounded(self.log_scale_head(hidden), self.log_scale_bounds.to(dtype))
        fusion_in = torch.cat([hidden[:, None].expand(-1, n_sources, -1), per_source], -1)
        fusion_logit = _bounded(self.fusion_head(fusion_in)[..., 0], cfg.fusion_logit_bound)
        return CovNetOutput(log_scales, torch.sigmoid(fusion_logit), weather_logits)


def _column(log_scales: torch.Tensor, sensor: str, like: torch.Tensor) -> torch.Tensor:
    """The (B,) or () log scale of ``sensor`` in ``like``'s dtype and device (keeps grad)."""
    return log_scales[..., LOG_SCALE_SENSORS.index(sensor)].to(like)


def scaled_noise(base: EskfNoise, log_scales: torch.Tensor) -> EskfNoise:
    """Scale the filter's noise by the network's log-variance scales.

    Every variance becomes ``base_variance * exp(log_scale)``, i.e. every sigma or noise
    density is multiplied by ``exp(log_scale / 2)``: ``wheel`` scales the wheel speed,
    lateral and yaw-rate sigmas, ``nhc`` the NHC sigma, ``gnss`` the GNSS sigma scale,
    ``imu_gyro`` / ``imu_accel`` the gyro / accelerometer white-noise densities. Bias random
    walks and the zero-velocity sigma are kept; ``vo`` and ``lidar`` apply to pose streams
    (:func:`scaled_pose_covariance`) and multiply the variance scales of the ESKF's pose
    sources of those names (``EskfNoise.pose_source_scale``, fused as odometry), so a fusion
    weight folded in by :func:`apply_fusion_weights` reaches the odometry rows too.

    Args:
        base: noise tensors of shape () or (B,) (``EskfNoise.from_config``).
        log_scales: (B, 7) or (7,) :data:`LOG_SCALE_SENSORS` log-variance scales.

    Returns:
        A new :class:`EskfNoise` in ``base``'s dtype, shape (B,) (or () for (7,) scales),
        differentiable w.r.t. ``log_scales``.
    """

    def scale(value: torch.Tensor, sensor: str) -> torch.Tensor:
        return value * torch.exp(0.5 * _column(log_scales, sensor, value))

    return dataclasses.replace(
        base,
        imu=ImuNoise(
            scale(base.imu.gyro_noise_density, "imu_gyro"),
            scale(base.imu.accel_noise_density, "imu_accel"),
            base.imu.gyro_bias_rw_density,
            base.imu.accel_bias_rw_density,
        ),
        wheel_speed_sigma=scale(base.wheel_speed_sigma, "wheel"),
        wheel_lateral_sigma=scale(base.wheel_lateral_sigma, "wheel"),
        wheel_yaw_rate_sigma=scale(base.wheel_yaw_rate_sigma, "wheel"),
        nhc_sigma=scale(base.nhc_sigma, "nhc"),
        gnss_sigma_scale=scale(base.gnss_sigma_scale, "gnss"),
        pose_source_scale=base.pose_source_scale
        | {
            source: base.pose_source_scale.get(source, 1.0)
            * torch.exp(_column(log_scales, source, base.gnss_sigma_scale))
            for source in ("vo", "lidar")
        },
    )


def scaled_pose_covariance(
    covariance: torch.Tensor, log_scales: torch.Tensor, source: str
) -> torch.Tensor:
    """A pose stream's covariances times ``exp(log_scale)`` of its source.

    Args:
        covariance: (B, N, 6, 6) ``PoseMeasurements.covariance``, m^2 and rad^2.
        log_scales: (B, 7) :data:`LOG_SCALE_SENSORS` log-variance scales.
        source: ``"vo"`` or ``"lidar"`` (any name of :data:`LOG_SCALE_SENSORS` works).

    Returns:
        (B, N, 6, 6) in ``covariance``'s dtype, differentiable w.r.t. ``log_scales``.
    """
    return covariance * torch.exp(_column(log_scales, source, covariance))[:, None, None, None]


def apply_fusion_weights(
    log_scales: torch.Tensor, fusion_weights: torch.Tensor, pose_sources: tuple[str, ...]
) -> torch.Tensor:
    """Fold per-source fusion weights into the log-variance scales.

    A weight ``w`` divides the source's variance: the source's log scale becomes
    ``log_scale - log(w)``; sensors that are not pose sources keep theirs.

    Args:
        log_scales: (B, 7) :data:`LOG_SCALE_SENSORS` log-variance scales.
        fusion_weights: (B, S) in (0, 1].
        pose_sources: the S source names (``CovNetConfig.pose_sources``).

    Returns:
        (B, 7) effective log-variance scales, for :func:`scaled_noise` and
        :func:`scaled_pose_covariance`.
    """
    columns = torch.tensor(
        [LOG_SCALE_SENSORS.index(s) for s in pose_sources], device=log_scales.device
    )
    penalty = torch.zeros_like(log_scales).index_add(
        -1, columns, -torch.log(fusion_weights.to(log_scales))
    )
    return log_scales + penalty


IMU_RATE_TOLERANCE = 0.05
"""Largest relative difference between IMU rates one network's windows may mix (training
runs among themselves, a run at inference against the training runs)."""


@dataclass(frozen=True)
class NoiseApplication:
    """How training applied a network's scales; inference applies them the same way.

    Stored in the checkpoint beside the weights (plain types). A checkpoint written before
    this record existed loads with the defaults below (those of
    ``training/configs/default.yaml``) and no IMU rate.

    Attributes:
        imu_rate_hz: median IMU rate of the training runs, Hz; a window of
            ``CovNetConfig.window_length`` samples spans ``window_length / imu_rate_hz`` s.
            None: not recorded.
        chunk_windows: windows per noise chunk (the truncated-backpropagation chunk).
        noise_granularity: ``"chunk"``: scales averaged per chunk; ``"run"``: per run.
        innovation_features: the network saw the innovation statistics of a reference filter
            pass with the run's configured noise (False: those features were zero).
        gnss_outages_only: the scales applied only in chunks holding no GNSS fix, the
            configured noise elsewhere (``msf_torch.learning.kitti.gate_outage_chunks``).
        filter_settings: the front-end settings the training's ``eskf_config`` YAML set
            (key -> value, plain types; ``{}``: none, the defaults), which the learned
            scales multiply; None: not recorded (checkpoints before 2026-11-28).
    """

    imu_rate_hz: float | None = None
    chunk_windows: int = 10
    noise_granularity: str = "chunk"
    innovation_features: bool = True
    gnss_outages_only: bool = False
    filter_settings: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.chunk_windows < 1:
            raise ValueError(
                f"NoiseApplication.chunk_windows must be >= 1, got {self.chunk_windows}"
            )
        if self.noise_granularity not in ("chunk", "run"):
            raise ValueError(
                "NoiseApplication.noise_granularity must be 'chunk' or 'run', "
                f"got {self.noise_granularity!r}"
            )
        if self.imu_rate_hz is not None and not (
            math.isfinite(self.imu_rate_hz) and self.imu_rate_hz > 0
        ):
            raise ValueError(
                f"NoiseApplication.imu_rate_hz must be a positive rate, got {self.imu_rate_hz!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain Python types, loadable with ``torch.load(weights_only=True)``."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> NoiseApplication:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        _require_known_keys(cls, values)
        return cls(**values)


def save_checkpoint(
    path: str | Path, model: CovNet, application: NoiseApplication | None = None
) -> None:
    """Write the config and the application record (plain types) and the weights, loadable
    with ``weights_only=True``. ``application`` None stores the defaults of
    :class:`NoiseApplication`."""
    torch.save(
        {
            "format": _CHECKPOINT_FORMAT,
            "config": model.config.to_dict(),
            "application": (application or NoiseApplication()).to_dict(),
            "state_dict": model.state_dict(),
        },
        path,
    )


def read_checkpoint(path: str | Path) -> tuple[CovNet, NoiseApplication]:
    """A :class:`CovNet` from :func:`save_checkpoint`'s file (CPU, eval mode) and how its
    training applied it.

    Uses ``torch.load(weights_only=True)``, so the file cannot run code; move the model
    with ``.to(device)``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a CovNet checkpoint (the message names it; a file that
            ``torch.load`` cannot read at all says it is not an msf_torch checkpoint, without
            torch's own text).
    """
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except (
        pickle.UnpicklingError,
        RuntimeError,
        EOFError,
        KeyError,
        ValueError,
        TypeError,
        AttributeError,
        IndexError,
        UnicodeDecodeError,
        zipfile.BadZipFile,
    ) as err:
        raise ValueError(
            f"{path}: not an msf_torch checkpoint (torch.load cannot read it: "
            f"{type(err).__name__}; checkpoints are written by save_checkpoint)"
        ) from err
    if not isinstance(payload, dict) or payload.get("format") != _CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a CovNet checkpoint (format {_CHECKPOINT_FORMAT})")
    try:
        model = CovNet(CovNetConfig.from_dict(payload["config"]))
        application = NoiseApplication.from_dict(payload.get("application", {}))
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err
    model.load_state_dict(payload["state_dict"])
    return model.eval(), application


def load_checkpoint(path: str | Path) -> CovNet:
    """The :class:`CovNet` of :func:`read_checkpoint` (CPU, eval mode), without the
    application record.

    Raises:
        ValueError: the file is not a CovNet checkpoint (the message names it).
    """
    return read_checkpoint(path)[0]
