"""CovNet inference throughput: windows per second on the CPU (or a given device).

What it measures
    ``msf_torch.learning.CovNet`` with the default config (or ``--window``) in float32,
    untrained weights (speed does not depend on them), eval mode under
    ``torch.inference_mode()``. Input: one batch of ``--batch`` random windows (IMU (B, L, 6),
    wheel (B, L, 2) with presence flags, pose-source residual statistics (B, 3, 4), weather
    unknown), built once; only the forward pass is timed (median over ``--repeats`` after
    ``--warmup`` untimed calls, with the minimum and process CPU time alongside). On CUDA
    the device is synchronised inside the timed call. Target: >= 10,000 windows/s on the
    CPU for L = 100 (1 s at 100 Hz).

    Measured on the 2-core AMD EPYC dev box: ~95k windows/s with 2 threads on an idle
    machine, ~65k with ``--threads 1``. With 2 threads and another busy process on the two
    cores the median falls to ~7.5k (OpenMP threads wait for a descheduled peer); the load
    average is in the JSON line, and ``--threads 1`` is the robust figure on a shared box.

How to run
    .venv/bin/python benchmarks/covnet_speed.py                  # B = 4096, L = 100
    .venv/bin/python benchmarks/covnet_speed.py --threads 1

    Progress goes to stderr; the last line on stdout is one JSON object.

Options
    --batch N      windows per forward pass (default 4096)
    --window L     IMU samples per window (default 100)
    --repeats N    timed forward passes (median; default 20)
    --warmup N     untimed forward passes first (default 3)
    --threads N    torch intra-op threads (default: torch's choice)
    --device D     run on this device (default cpu)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from benchmarks._common import emit_json, log, machine_info, time_repeats  # noqa: E402
from msf_torch.learning import RESIDUAL_FEATURES, CovNet, CovNetConfig  # noqa: E402


def main() -> None:
    """Parse the options, time the forward pass, print one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--window", type=int, default=CovNetConfig.window_length)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)

    torch.manual_seed(0)
    config = CovNetConfig(window_length=args.window)
    model = CovNet(config).to(device).eval()
    batch, length = args.batch, config.window_length
    imu = torch.randn(batch, length, 6, device=device)
    imu[..., 5] += 9.81
    wheel = torch.randn(batch, length, 2, device=device)
    present = torch.rand(batch, device=device) > 0.3
    stats = torch.rand(batch, len(config.pose_sources), len(RESIDUAL_FEATURES), device=device)
    weather = torch.full((batch,), config.unknown_weather, device=device)

    def forward() -> None:
        with torch.inference_mode():
            model(imu, wheel, present, stats, weather)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    log(f"CovNet forward, B = {batch}, L = {length}, {torch.get_num_threads()} threads")
    median, timing, _ = time_repeats(forward, args.repeats, args.warmup)
    emit_json(
        {
            "benchmark": "covnet_speed",
            "windows_per_s": batch / median,
            "windows_per_s_best": batch / timing["min_s"],
            "target_windows_per_s": 10_000,
            "params": sum(p.numel() for p in model.parameters()),
            "window_length": length,
            "batch": batch,
            "dtype": "float32",
            "device": str(device),
            "threads": torch.get_num_threads(),
            "timing": timing,
            "machine": machine_info(),
        }
    )


if __name__ == "__main__":
    main()
