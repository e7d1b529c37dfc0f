"""Tensor dataclasses with a leading batch dimension B.

Every stream is padded to a common length N across the batch and carries a boolean
``mask`` (B, N): True where a sample is real. Padding is never read as data. Times are
seconds (float64) on the sequence's own clock; streams of one sequence share that clock.

Use :func:`batch_sequences` to stack single sequences (B = 1 each) into one batch, and
``Sequence.select`` to take one back out.
"""

from __future__ import annotations

__all__ = [
    "ImuSamples",
    "WheelSamples",
    "GnssFixes",
    "GnssVelocity",
    "GnssHeading",
    "Magnetometer",
    "PoseMeasurements",
    "Trajectory",
    "NavState",
    "Sequence",
    "batch_sequences",
    "move_to",
]

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import torch

StreamT = TypeVar("StreamT")
T = TypeVar("T")


class _Stream:
    """Shared behaviour of the time-stamped stream dataclasses (fields ``t`` and ``mask``)."""

    t: torch.Tensor
    mask: torch.Tensor

    @property
    def batch_size(self) -> int:
        """B, the number of sequences."""
        return self.t.shape[0]

    @property
    def length(self) -> int:
        """N, the padded number of samples."""
        return self.t.shape[1]

    def counts(self) -> torch.Tensor:
        """Real samples per sequence, (B,) int64."""
        return self.mask.sum(-1)

    def median_rate_hz(self) -> torch.Tensor:
        """(B,) one over the median interval between consecutive real samples, Hz (NaN for
        a sequence with fewer than two)."""
        if self.length < 2:
            return torch.full((self.batch_size,), torch.nan, dtype=self.t.dtype)
        both = self.mask[:, 1:] & self.mask[:, :-1]
        interval = torch.where(both, self.t.diff(dim=1), torch.nan)
        return 1.0 / torch.nanmedian(interval, dim=1).values

    def tensors(self) -> dict[str, torch.Tensor]:
        """The fields as a name -> tensor dict."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def map(self: StreamT, fn: Callable[[torch.Tensor], torch.Tensor]) -> StreamT:
        """A copy with ``fn`` applied to every tensor field (shapes as ``fn`` returns them)."""
        return type(self)(**{k: fn(v) for k, v in self.tensors().items()})

    def to(
        self: StreamT, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> StreamT:
        """Move to a device; floating fields also to ``dtype`` when given."""

        def move(x: torch.Tensor) -> torch.Tensor:
            if dtype is not None and x.is_floating_point():
                return x.to(device=device, dtype=dtype)
            return x.to(device=device)

        return self.map(move)

    def select(self: StreamT, index: int | slice | torch.Tensor) -> StreamT:
        """Sub-batch along B (an int keeps a batch dimension of 1)."""
        if isinstance(index, int):
            index = slice(index, index + 1)
        return self.map(lambda x: x[index])

    def compact(self: StreamT) -> StreamT:
        """For B = 1: drop masked samples, so ``mask`` is all True."""
        if self.batch_size != 1:
            raise ValueError(f"compact() needs B = 1, got B = {self.batch_size}")
        keep = self.mask[0]
        return self.map(lambda x: x[:, keep])

    def check(self, name: str) -> None:
        """Raise ``ValueError`` naming the field if shapes disagree with ``t`` (B, N)."""
        if self.t.dim() != 2:
            raise ValueError(f"{name}.t must be (B, N), got {tuple(self.t.shape)}")
        for key, value in self.tensors().items():
            if value.shape[:2] != self.t.shape:
                raise ValueError(
                    f"{name}.{key} has shape {tuple(value.shape)}; its leading dims must "
                    f"equal t's {tuple(self.t.shape)}"
                )


@dataclass
class ImuSamples(_Stream):
    """IMU samples in the body frame.

    Attributes:
        t: (B, N) sample times, s.
        gyro: (B, N, 3) angular rate, rad/s.
        accel: (B, N, 3) specific force, m/s^2 (a level IMU at rest reads +g on z).
        mask: (B, N) bool.
    """

    t: torch.Tensor
    gyro: torch.Tensor
    accel: torch.Tensor
    mask: torch.Tensor


@dataclass
class WheelSamples(_Stream):
    """Differential-drive wheel encoder readings, as rim speeds.

    Attributes:
        t: (B, N) s.
        left_speed: (B, N) left wheel rim speed (radius x angular rate), m/s.
        right_speed: (B, N) right wheel rim speed, m/s.
        mask: (B, N) bool.
    """

    t: torch.Tensor
    left_speed: torch.Tensor
    right_speed: torch.Tensor
    mask: torch.Tensor


@dataclass
class GnssFixes(_Stream):
    """GNSS antenna positions in the local world frame (ENU, m).

    Attributes:
        t: (B, N) s.
        position: (B, N, 3) m.
        sigma: (B, N, 3) per-axis standard deviation, m; NaN where the file gave none
            (the estimator's configured default applies).
        mask: (B, N) bool.
    """

    t: torch.Tensor
    position: torch.Tensor
    sigma: torch.Tensor
    mask: torch.Tensor


@dataclass
class GnssVelocity(_Stream):
    """GNSS velocity of the antenna in the local world frame (ENU, m/s): a receiver's
    Doppler velocity, or speed and course over ground.

    Attributes:
        t: (B, N) s.
        velocity: (B, N, 3) east, north, up, m/s; the up component is NaN where the
            receiver gave none (NMEA RMC / VTG: horizontal only), and is then not fused.
        sigma: (B, N, 3) per-axis standard deviation, m/s; NaN where the file gave none
            (the estimator's configured default applies).
        mask: (B, N) bool.
    """

    t: torch.Tensor
    velocity: torch.Tensor
    sigma: torch.Tensor
    mask: torch.Tensor


@dataclass
class GnssHeading(_Stream):
    """Heading of a dual-antenna (moving-baseline) GNSS receiver: the azimuth of the
    baseline from the primary to the secondary antenna, as receivers report it (u-blox
    NAV-RELPOSNED ``relPosHeading``, NMEA ``HDT`` / ``THS``, Septentrio ``AttEuler``).

    Attributes:
        t: (B, N) s.
        heading: (B, N) clockwise from north (true north, the local frame's +y), rad.
        sigma: (B, N) standard deviation, rad; NaN where the file gave none (the
            estimator's configured default applies).
        mask: (B, N) bool.
    """

    t: torch.Tensor
    heading: torch.Tensor
    sigma: torch.Tensor
    mask: torch.Tensor


@dataclass
class Magnetometer(_Stream):
    """Three-axis magnetometer readings in the body (IMU) frame, as the sensor gives them
    (before hard- and soft-iron correction, which ``EskfConfig`` applies).

    Attributes:
        t: (B, N) s.
        field: (B, N, 3) magnetic flux density, microtesla (uT; 1 gauss = 100 uT, ROS
            ``sensor_msgs/MagneticField`` carries tesla = 1e6 uT).
        sigma: (B, N) per-axis standard deviation, uT; NaN where the file gave none (the
            estimator's configured default applies).
        mask: (B, N) bool.
    """

    t: torch.Tensor
    field: torch.Tensor
    sigma: torch.Tensor
    mask: torch.Tensor


@dataclass
class PoseMeasurements(_Stream):
    """Pose measurements of the body in the world frame (visual / LiDAR odometry, priors).

    Attributes:
        t: (B, N) s.
        position: (B, N, 3) m.
        quaternion: (B, N, 4) ``[w, x, y, z]``.
        covariance: (B, N, 6, 6) over ``[dp (world), dtheta (body)]``, m^2 and rad^2.
        mask: (B, N) bool.
    """

    t: torch.Tensor
    position: torch.Tensor
    quaternion: torch.Tensor
    covariance: torch.Tensor
    mask: torch.Tensor


@dataclass
class Trajectory(_Stream):
    """Timed poses of the body in the world frame (estimates or ground truth).

    Attributes:
        t: (B, N) s.
        position: (B, N, 3) m.
        quaternion: (B, N, 4) ``[w, x, y, z]``.
        mask: (B, N) bool.
    """

    t: torch.Tensor
    position: torch.Tensor
    quaternion: torch.Tensor
    mask: torch.Tensor


@dataclass
class NavState:
    """Nominal navigation state (see ``geometry.conventions``), batch-first.

    Attributes:
        position: (B, 3) world, m.
        velocity: (B, 3) world, m/s.
        rotation: (B, 3, 3) body -> world.
        gyro_bias: (B, 3) rad/s.
        accel_bias: (B, 3) m/s^2.
    """

    position: torch.Tensor
    velocity: torch.Tensor
    rotation: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor


@dataclass
class Sequence:
    """A batch of recorded (or simulated) runs: streams, ground truth, labels.

    Attributes:
        names: one name per sequence (length B).
        imu: IMU samples (required).
        wheel, gnss, gnss_velocity, gnss_heading, magnetometer, poses: optional
            measurement streams.
        ground_truth: optional reference trajectory.
        labels: name -> (B, K, 2) intervals ``[t_start, t_end]`` in s, NaN-padded; e.g.
            ``"slip"`` or ``"weather:rain"``.
        meta: per-batch metadata (sensor noise from a dataset's files, counts of dropped
            samples, source paths). Plain Python values.
        pose_sources: named pose streams besides ``poses``, e.g. ``"vo"`` (visual odometry)
            and ``"lidar"`` (LiDAR odometry), each (B, N_name, ...) like ``poses``; empty when
            a sequence has none.
    """

    names: list[str]
    imu: ImuSamples
    wheel: WheelSamples | None = None
    gnss: GnssFixes | None = None
    gnss_velocity: GnssVelocity | None = None
    gnss_heading: GnssHeading | None = None
    magnetometer: Magnetometer | None = None
    poses: PoseMeasurements | None = None
    ground_truth: Trajectory | None = None
    labels: dict[str, torch.Tensor] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    pose_sources: dict[str, PoseMeasurements] = field(default_factory=dict)

    _STREAMS = (
        "imu",
        "wheel",
        "gnss",
        "gnss_velocity",
        "gnss_heading",
        "magnetometer",
        "poses",
        "ground_truth",
    )

    @property
    def batch_size(self) -> int:
        """B."""
        return self.imu.batch_size

    def streams(self) -> dict[str, _Stream]:
        """The streams that are present, by field name (``pose_sources`` not included)."""
        out = {}
        for key in self._STREAMS:
            value = getattr(self, key)
            if value is not None:
                out[key] = value
        return out

    def check(self) -> None:
        """Validate shapes of all streams and labels; raise ``ValueError`` naming the field."""
        batch = self.batch_size
        if len(self.names) != batch:
            raise ValueError(f"names has {len(self.names)} entries, B = {batch}")
        for key, stream in self.streams().items():
            stream.check(key)
            if stream.batch_size != batch:
                raise ValueError(f"{key} has B = {stream.batch_size}, imu has B = {batch}")
        for name, source in self.pose_sources.items():
            key = f"pose_sources[{name!r}]"
            if not isinstance(source, PoseMeasurements):
                raise ValueError(f"{key} must be PoseMeasurements, got {type(source).__name__}")
            source.check(key)
            if source.batch_size != batch:
                raise ValueError(f"{key} has B = {source.batch_size}, imu has B = {batch}")
        for key, value in self.labels.items():
            if value.dim() != 3 or value.shape[0] != batch or value.shape[2] != 2:
                raise ValueError(f"labels[{key!r}] must be (B, K, 2), got {tuple(value.shape)}")

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Sequence:
        """Move every stream (pose sources and labels too) to ``device`` / ``dtype``."""
        moved = {k: s.to(device, dtype) for k, s in self.streams().items()}
        labels = {k: v.to(device=device) for k, v in self.labels.items()}
        sources = {k: s.to(device, dtype) for k, s in self.pose_sources.items()}
        return dataclasses.replace(self, labels=labels, pose_sources=sources, **moved)

    def select(self, index: int) -> Sequence:
        """Sequence ``index`` of the batch, as a batch of one."""
        picked = {k: s.select(index) for k, s in self.streams().items()}
        labels = {k: v[index : index + 1] for k, v in self.labels.items()}
        sources = {k: s.select(index) for k, s in self.pose_sources.items()}
        return dataclasses.replace(
            self,
            names=[self.names[index]],
            labels=labels,
            meta=dict(self.meta),
            pose_sources=sources,
            **picked,
        )

    @property
    def start_time(self) -> torch.Tensor:
        """(B,) the first real IMU time per sequence, s."""
        big = torch.finfo(self.imu.t.dtype).max
        return torch.where(self.imu.mask, self.imu.t, torch.full_like(self.imu.t, big)).amin(-1)


def _pad_cat(tensors: list[torch.Tensor], fill: float | bool) -> torch.Tensor:
    """Concatenate (1, N_i, ...) tensors along B, padding N to the longest with ``fill``."""
    longest = max(x.shape[1] for x in tensors)
    padded = []
    for x in tensors:
        pad_shape = (x.shape[0], longest - x.shape[1], *x.shape[2:])
        padded.append(
            torch.cat((x, torch.full(pad_shape, fill, dtype=x.dtype, device=x.device)), 1)
        )
    return torch.cat(padded, 0)


def _batch_streams(streams: list, kind: type) -> Any:
    fields = [f.name for f in dataclasses.fields(kind)]
    out = {}
    for name in fields:
        values = [getattr(s, name) for s in streams]
        fill: float | bool = False if name == "mask" else 0.0
        out[name] = _pad_cat(values, fill)
    return kind(**out)


def _empty_like_stream(kind: type, template) -> Any:
    """A stream of ``kind`` with B = 1 and N = 0, dtype/device from ``template``."""
    shapes = {
        "t": (),
        "mask": (),
        "gyro": (3,),
        "accel": (3,),
        "left_speed": (),
        "right_speed": (),
        "position": (3,),
        "velocity": (3,),
        "sigma": (3,),
        "quaternion": (4,),
        "covariance": (6, 6),
        "heading": (),
        "field": (3,),
    }
    if kind in (GnssHeading, Magnetometer):
        shapes["sigma"] = ()
    out = {}
    for f in dataclasses.fields(kind):
        dtype = torch.bool if f.name == "mask" else template.dtype
        out[f.name] = torch.zeros((1, 0, *shapes[f.name]), dtype=dtype, device=template.device)
    return kind(**out)


def batch_sequences(sequences: list[Sequence]) -> Sequence:
    """Stack sequences along B, padding every stream to its longest length with masks.

    A stream present in some sequences and absent in others is kept, with zero real samples
    for those that lack it; so is a named pose source (``pose_sources``, union of the names).
    Labels are padded with NaN intervals. ``meta`` becomes
    ``{"per_sequence": [meta_0, meta_1, ...]}`` merged over the inputs' keys.
    """
    if not sequences:
        raise ValueError("batch_sequences needs at least one sequence")
    singles = [s.select(i) for s in sequences for i in range(s.batch_size)]
    template = singles[0].imu.t
    kinds = {
        "imu": ImuSamples,
        "wheel": WheelSamples,
        "gnss": GnssFixes,
        "gnss_velocity": GnssVelocity,
        "gnss_heading": GnssHeading,
        "magnetometer": Magnetometer,
        "poses": PoseMeasurements,
        "ground_truth": Trajectory,
    }
    streams: dict[str, Any] = {}
    for key, kind in kinds.items():
        present = [getattr(s, key) for s in singles]
        if all(p is None for p in present):
            streams[key] = None
            continue
        filled = [p if p is not None else _empty_like_stream(kind, template) for p in present]
        streams[key] = _batch_streams(filled, kind)
    source_names = sorted({k for s in singles for k in s.pose_sources})
    pose_sources = {
        name: _batch_streams(
            [
                s.pose_sources[name]
                if name in s.pose_sources
                else _empty_like_stream(PoseMeasurements, template)
                for s in singles
            ],
            PoseMeasurements,
        )
        for name in source_names
    }
    label_keys = sorted({k for s in singles for k in s.labels})
    labels = {}
    for key in label_keys:
        parts = [s.labels.get(key, torch.zeros((1, 0, 2), dtype=template.dtype)) for s in singles]
        labels[key] = _pad_cat(parts, float("nan"))
    meta: dict[str, Any] = {"per_sequence": [s.meta for s in singles]}
    return Sequence(
        names=[n for s in singles for n in s.names],
        labels=labels,
        meta=meta,
        pose_sources=pose_sources,
        **streams,
    )


def move_to(obj: T, device: torch.device | str) -> T:
    """``obj`` with every tensor in it on ``device``: a tensor, or dataclasses, dicts, lists,
    tuples and named tuples holding tensors, recursively (rebuilt; other values kept as
    they are). For results such as ``EskfResult`` or ``SmootherResult`` made on a GPU and
    written from the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        moved = {
            f.name: move_to(getattr(obj, f.name), device) for f in dataclasses.fields(obj) if f.init
        }
        return dataclasses.replace(obj, **moved)
    if isinstance(obj, dict):
        return type(obj)((key, move_to(value, device)) for key, value in obj.items())
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(move_to(value, device) for value in obj))
    if isinstance(obj, list | tuple):
        return type(obj)(move_to(value, device) for value in obj)
    return obj
