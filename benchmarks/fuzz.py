"""Property-based fuzzing of the msf_torch.io readers (all but rosbags) with malformed inputs.

What it measures
    For each reader of :data:`benchmarks._fuzz_inputs.READERS` (native ``.npz``, native CSV
    folder, TUM, EuRoC ASL, the KITTI files gtsam ships, 3-D g2o and TORO, 2-D g2o and TORO,
    2-D graphs with landmarks (ODOMETRY, LANDMARK, BR, VERTEX_XY), the EqVIO replay CSV,
    KITTI odometry poses with their times file, 2D LiDAR scan .npz, the odometry +
    anchor-range CSV files, NMEA 0183 GNSS logs),
    hypothesis generates ``--examples`` malformed inputs (a valid input of the format with 1-3
    mutations: truncated lines, wrong field counts, non-numeric tokens, NaN/inf, huge numbers,
    empty files, binary junk, bad headers, backwards or repeated stamps, missing files, ...;
    see ``benchmarks/_fuzz_inputs.py``). Each input is written to a fresh folder and read; the
    outcome is sorted by :func:`benchmarks._fuzz_inputs.classify` into ``ok`` (the result
    keeps the io promises: finite values, increasing stamps, unit quaternions, ...),
    ``data_error`` (the library's DataError naming a file inside the input and a line that
    file has), ``bad_output``, ``bad_error`` or ``crash``. Every outcome is recorded; nothing
    stops the run, so the counts cover all inputs.

    Peer: none. No other library promises typed errors for these formats; the figure that
    matters is an absolute one (zero crashes), so ``peer`` is null in the JSON line.

    Target (issue 5, acceptance 4): at least 10,000 inputs in all and zero crashes; also
    reported: zero ``bad_output`` and zero ``bad_error``.

How to run
    .venv/bin/python benchmarks/fuzz.py                    # 15 readers x 1300 = 19,500 inputs
    .venv/bin/python benchmarks/fuzz.py --examples 200 --seed 3

    Progress and one line per reader go to stderr; crashes and other failures are listed (the
    first few per reader, with their mutations) under ``failures`` in the JSON line, which
    is the last line on stdout.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402
from hypothesis import HealthCheck, Phase, given, seed, settings  # noqa: E402

from benchmarks._common import emit_json, log, machine_info  # noqa: E402
from benchmarks._fuzz_inputs import (  # noqa: E402
    ACCEPTED,
    OUTCOMES,
    READERS,
    FuzzCase,
    case_strategy,
    classify,
)

MIN_TOTAL = 10_000
MAX_LISTED = 5


def fuzz_reader(name: str, examples: int, run_seed: int) -> dict[str, Any]:
    """Run ``examples`` generated inputs through one reader; counts, failures and wall time."""
    counts: collections.Counter[str] = collections.Counter()
    mutations: collections.Counter[str] = collections.Counter()
    failures: list[dict[str, Any]] = []
    signatures: collections.Counter[str] = collections.Counter()

    @seed(run_seed)
    @settings(
        max_examples=examples,
        database=None,
        deadline=None,
        phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(case_strategy(name))
    def run(case: FuzzCase) -> None:
        with tempfile.TemporaryDirectory(prefix="msf-fuzz-") as tmp:
            outcome, detail = classify(case, Path(tmp))
        counts[outcome] += 1
        for m in case.mutations:
            mutations[m.split(":")[0]] += 1
        if outcome not in ACCEPTED:
            signature = f"{outcome}: {detail.split(':')[0]}"
            signatures[signature] += 1
            if signatures[signature] == 1 and len(failures) < MAX_LISTED:
                failures.append({"outcome": outcome, "detail": detail, "mutations": case.mutations})

    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run()
    wall = time.perf_counter() - start
    total = sum(counts.values())
    return {
        "inputs": total,
        **{k: counts.get(k, 0) for k in OUTCOMES},
        "wall_s": wall,
        "inputs_per_s": total / wall if wall > 0 else None,
        "mutations": dict(sorted(mutations.items())),
        "failure_kinds": dict(signatures),
        "failures": failures,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=1300, help="inputs per reader")
    parser.add_argument("--seed", type=int, default=0, help="hypothesis seed")
    parser.add_argument(
        "--readers", nargs="*", default=list(READERS), choices=list(READERS), help="subset"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    per_reader: dict[str, Any] = {}
    for name in args.readers:
        log(f"{name}: {args.examples} inputs ...")
        stats = fuzz_reader(name, args.examples, args.seed)
        per_reader[name] = stats
        log(
            f"  {name}: {stats['inputs']} inputs, ok {stats['ok']}, data_error "
            f"{stats['data_error']}, crash {stats['crash']}, bad_output {stats['bad_output']}, "
            f"bad_error {stats['bad_error']} ({stats['wall_s']:.1f} s)"
        )
        for failure in stats["failures"]:
            log(f"    {failure['outcome']}: {failure['detail']}  <- {failure['mutations']}")
    totals = {k: sum(s[k] for s in per_reader.values()) for k in ("inputs", *OUTCOMES)}
    emit_json(
        {
            "benchmark": "fuzz",
            "inputs": {
                "readers": args.readers,
                "examples_per_reader": args.examples,
                "seed": args.seed,
            },
            "ours": {
                "totals": totals,
                "per_reader": {
                    k: {
                        key: v[key]
                        for key in ("inputs", *OUTCOMES, "wall_s", "inputs_per_s", "failure_kinds")
                    }
                    for k, v in per_reader.items()
                },
                "mutations": {k: v["mutations"] for k, v in per_reader.items()},
            },
            "peer": None,
            "ratio": None,
            "failures": {k: v["failures"] for k, v in per_reader.items() if v["failures"]},
            "targets": {
                "inputs_at_least_10000": totals["inputs"] >= MIN_TOTAL,
                "zero_crashes": totals["crash"] == 0,
                "zero_bad_output": totals["bad_output"] == 0,
                "zero_bad_error": totals["bad_error"] == 0,
            },
            "machine": machine_info(),
        }
    )


if __name__ == "__main__":
    main()
