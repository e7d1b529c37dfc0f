"""Helpers shared by the benchmark scripts: output, repeat timing, memory, machine info.

Conventions of every benchmark in this folder:

* progress and per-case lines go to stderr (:func:`log`);
* the last line on stdout is ONE JSON object (:func:`emit_json`) with the inputs, our
  figures, the peer's figures, their ratio and the accuracy of both;
* timings are medians over repeats (:func:`time_repeats`), ratios are taken against the
  peer measured in the same process;
* peak memory is the resident set size high-water mark (``VmHWM``), reset before each
  measured part where Linux allows it (:class:`PeakRss`), else the process-wide
  ``ru_maxrss`` (then marked ``"resettable": false``); run it in a fresh process when
  parts must not see each other's freed-but-kept heap.

KITTI helpers (:func:`kitti_config`, :func:`peer_arrays`, :func:`trajectory_from`) give
every script the same configuration of ours and the same numpy inputs for the peers.

Not a benchmark itself; imported as ``benchmarks._common`` (the scripts put the repository
root on ``sys.path``).
"""

from __future__ import annotations

__all__ = [
    "REPO_ROOT",
    "log",
    "emit_json",
    "time_repeats",
    "PeakRss",
    "rss_mb",
    "machine_info",
    "rounded",
    "kitti_config",
    "peer_arrays",
    "trajectory_from",
]

import json
import math
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parent.parent


def log(*parts: Any) -> None:
    """Print a progress line to stderr (stdout is kept for the final JSON line)."""
    print(*parts, file=sys.stderr, flush=True)


def rounded(value: Any, digits: int = 6) -> Any:
    """Round floats (recursively in dicts/lists) for a compact JSON line; NaN/inf -> None."""
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            return None
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v, digits) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:  # numpy / torch scalar
        return rounded(value.item(), digits)
    return value


def emit_json(record: dict[str, Any], digits: int = 6) -> None:
    """Print ``record`` as one JSON line on stdout (the benchmark's last line), floats to
    ``digits`` significant digits."""
    sys.stdout.write(json.dumps(rounded(record, digits), separators=(",", ":")) + "\n")
    sys.stdout.flush()


def time_repeats(
    fn: Callable[[], Any], repeats: int, warmup: int = 0, label: str | None = None
) -> tuple[float, dict[str, Any], Any]:
    """Call ``fn`` ``warmup`` + ``repeats`` times.

    Returns:
        (median wall s, timing dict, last result). The timing dict has ``median_s``,
        ``min_s``, ``repeats_s`` (wall), ``cpu_median_s`` and ``cpu_repeats_s`` (process CPU
        time over all threads: when other work shares the machine, wall time grows while CPU
        time stays put, so the two together show contention).
    """
    result = None
    for _ in range(warmup):
        result = fn()
    walls: list[float] = []
    cpus: list[float] = []
    n = max(1, repeats)
    for i in range(n):
        cpu0 = time.process_time()
        start = time.perf_counter()
        result = fn()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu0)
        if label is not None:
            log(f"  {label}: repeat {i + 1}/{n} wall {walls[-1]:.3f} s, cpu {cpus[-1]:.3f} s")
    median = statistics.median(walls)
    timing = {
        "median_s": median,
        "min_s": min(walls),
        "repeats_s": walls,
        "cpu_median_s": statistics.median(cpus),
        "cpu_repeats_s": cpus,
    }
    return median, timing, result


def _status_kb(key: str) -> float | None:
    try:
        with open("/proc/self/status", encoding="ascii") as handle:
            for line in handle:
                if line.startswith(key + ":"):
                    return float(line.split()[1])
    except OSError:
        return None
    return None


def rss_mb() -> float | None:
    """Current resident set size of this process, MiB (None where /proc is missing)."""
    kb = _status_kb("VmRSS")
    return None if kb is None else kb / 1024.0


class PeakRss:
    """Peak resident memory over a ``with`` block.

    On Linux the kernel's high-water mark is reset on entry (``/proc/self/clear_refs``
    ``5``) and read on exit, so the figure belongs to the block (it includes whatever the
    process already held: see ``rss_before_mb``). Elsewhere ``ru_maxrss`` is used, which is
    the process-wide peak so far (``resettable`` False).
    """

    def __init__(self) -> None:
        self.resettable = False
        self.rss_before_mb: float | None = None
        self.peak_mb: float | None = None

    def __enter__(self) -> PeakRss:
        self.rss_before_mb = rss_mb()
        try:
            with open("/proc/self/clear_refs", "w", encoding="ascii") as handle:
                handle.write("5")
            self.resettable = _status_kb("VmHWM") is not None
        except OSError:
            self.resettable = False
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.resettable:
            kb = _status_kb("VmHWM")
            self.peak_mb = None if kb is None else kb / 1024.0
        else:
            maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            scale = 1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0  # bytes vs KiB
            self.peak_mb = maxrss / scale

    def as_dict(self) -> dict[str, Any]:
        """``{"peak_rss_mb", "rss_before_mb", "peak_minus_before_mb", "resettable"}``."""
        delta = None
        if self.peak_mb is not None and self.rss_before_mb is not None:
            delta = self.peak_mb - self.rss_before_mb
        return {
            "peak_rss_mb": self.peak_mb,
            "rss_before_mb": self.rss_before_mb,
            "peak_minus_before_mb": delta,
            "resettable": self.resettable,
        }


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU model and count, thread settings and library versions, for the JSON line."""
    info: dict[str, Any] = {
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    try:
        info["affinity_cpus"] = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        pass
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
        info["cuda"] = torch.cuda.is_available()
    except ImportError:
        pass
    try:
        import numpy

        info["numpy"] = numpy.__version__
    except ImportError:
        pass
    from importlib import metadata

    for name in ("gtsam", "filterpy"):
        try:
            info[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            info[name] = None
    try:
        info["load_average_1_5_15"] = list(os.getloadavg())  # other work on the machine
    except OSError:
        pass
    info["when_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return info


# --- KITTI (gtsam data) helpers ----------------------------------------------------------


def kitti_config(seq: Any) -> tuple[Any, list[str]]:
    """Our config for the KITTI drive and the keys its YAML sets explicitly.

    ``load_config(packaged_config("kitti-gtsam"))`` then ``config_for_sequence`` with the
    YAML's keys as explicit, so the dataset's IMU noise fills the keys the YAML leaves out.
    """
    import yaml

    from msf_torch.frontend.config import config_for_sequence, load_config, packaged_config

    path = packaged_config("kitti-gtsam")
    if path is None:
        raise FileNotFoundError("msf_torch/configs/kitti-gtsam.yaml is missing")
    with open(path, encoding="utf-8") as handle:
        explicit = set((yaml.safe_load(handle) or {}).keys())
    return config_for_sequence(load_config(path), seq.meta, explicit), sorted(explicit)


def peer_arrays(seq: Any) -> dict[str, Any]:
    """Keyword inputs of ``run_gtsam_kitti`` taken from the same B = 1 Sequence ours gets.

    The metadata is the Sequence's ``meta["imu_noise"]`` (the same file's values) with
    ``average_delta_t`` added under the peer's key name.
    """
    meta = dict(seq.meta["imu_noise"])
    meta.setdefault("average_delta_t", meta.get("average_dt"))
    imu_m = seq.imu.mask[0].numpy()
    gps_m = seq.gnss.mask[0].numpy()
    return {
        "imu_t": seq.imu.t[0].numpy()[imu_m],
        "imu_acc": seq.imu.accel[0].numpy()[imu_m],
        "imu_gyro": seq.imu.gyro[0].numpy()[imu_m],
        "gps_t": seq.gnss.t[0].numpy()[gps_m],
        "gps_xyz": seq.gnss.position[0].numpy()[gps_m],
        "meta": meta,
    }


def trajectory_from(t: Any, position: Any) -> Any:
    """A B = 1 ``Trajectory`` (identity quaternions) from numpy times (K,) and positions."""
    import numpy as np
    import torch

    from msf_torch.types import Trajectory

    n = len(t)
    quat = torch.zeros(1, n, 4, dtype=torch.float64)
    quat[..., 0] = 1.0
    return Trajectory(
        t=torch.as_tensor(np.asarray(t, dtype=float))[None],
        position=torch.as_tensor(np.asarray(position, dtype=float))[None],
        quaternion=quat,
        mask=torch.ones(1, n, dtype=torch.bool),
    )
