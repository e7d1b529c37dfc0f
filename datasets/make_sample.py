"""Generate the bundled sample sequence ``datasets/sample_slip.npz`` (or a native CSV folder).

The sample is a simulated wheeled-robot run (:func:`msf_torch.sim.simulate_run` with
:func:`msf_torch.sim.sample_slip_config`, seed 7): 120 s, ADIS16470-grade IMU at 200 Hz,
wheel encoders at 25 Hz, GNSS at 1 Hz, three labelled slip episodes (one each of ``spin``,
``skid``, ``lock``) and one 30 s GNSS outage that contains a slip episode.

The native writer stores the streams, ``labels.csv`` (``slip`` and ``gnss_outage``) and the
sensor description (``meta.json``). This script adds ``sim.json``: the simulator config,
the seed, the slip episodes in detail and the hidden truth the native tables do not hold
(wheel scale errors, initial IMU biases), so the sample can be reproduced and audited.

Usage::

    python datasets/make_sample.py                 # datasets/sample_slip.npz (+ .sim.json)
    python datasets/make_sample.py --out /tmp/x    # a folder of CSVs elsewhere
"""

from __future__ import annotations

__all__ = ["SAMPLE_SEED", "make_sample", "main"]

import argparse
import json
from pathlib import Path

from msf_torch.io.atomic import atomic_write
from msf_torch.io.native import write_native
from msf_torch.sim import sample_slip_config, simulate_run

SAMPLE_SEED = 7
"""Seed of the bundled sample."""

DEFAULT_OUT = Path(__file__).resolve().parent / "sample_slip.npz"


def make_sample(out: str | Path = DEFAULT_OUT, seed: int = SAMPLE_SEED) -> Path:
    """Simulate the sample run and write it in the native format plus its provenance.

    Args:
        out: ``FILE.npz`` (provenance beside it as ``FILE.sim.json``) or a folder of CSVs
            (provenance inside as ``sim.json``).
        seed: simulator seed (7 for the bundled sample).

    Returns:
        the path written.
    """
    run = simulate_run(sample_slip_config(), seed=seed)
    folder = write_native(run.sequence, out)
    truth = run.truth
    provenance = {
        "generator": "datasets/make_sample.py (msf_torch.sim.simulate_run)",
        "seed": seed,
        "config": run.config.to_dict(),
        "slip_episodes": run.sequence.meta["slip_episodes"],
        "truth": {
            "wheel_scale_error": run.sequence.meta["truth"]["wheel_scale_error"],
            "gyro_bias_initial_rad_s": truth.gyro_bias[0, 0].tolist(),
            "accel_bias_initial_m_s2": truth.accel_bias[0, 0].tolist(),
            "gyro_bias_final_rad_s": truth.gyro_bias[0, -1].tolist(),
            "accel_bias_final_m_s2": truth.accel_bias[0, -1].tolist(),
        },
    }
    target = folder.with_suffix(".sim.json") if folder.suffix == ".npz" else folder / "sim.json"
    with atomic_write(target) as handle:
        handle.write(json.dumps(provenance, indent=2, sort_keys=True) + "\n")
    return folder


def main(argv: list[str] | None = None) -> int:
    """Command-line entry: ``python datasets/make_sample.py [--out DIR] [--seed N]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="FILE.npz or a folder of CSVs"
    )
    parser.add_argument("--seed", type=int, default=SAMPLE_SEED, help="simulator seed")
    args = parser.parse_args(argv)
    folder = make_sample(args.out, args.seed)
    print(f"wrote {folder}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
