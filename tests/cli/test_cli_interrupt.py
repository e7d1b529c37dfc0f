"""Ctrl-C (SIGINT) during ``msf run`` leaves valid partial outputs and says where it stopped.

Three levels: ``run_eskf`` hands on the completed epochs (equal to the full run's first
ones); ``run_sequence`` writes them as a readable TUM file, diagnostics and a summary; and a
real ``msf run`` subprocess sent SIGINT exits with status 130, prints the stop point on
stderr and the summary on stdout.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.guard import EstimationInterrupted
from msf_torch.io.native import write_native
from msf_torch.io.tum import read_tum
from msf_torch.runner import RunInterrupted, RunOptions, run_sequence
from msf_torch.sim import SimConfig, simulate_run

STOP_AFTER = 37


@pytest.fixture(scope="module")
def run_seq():
    return simulate_run(SimConfig(duration_s=8.0, slip_episodes=0, gnss_outage_count=0), 4).sequence


def _stopper(after: int):
    """A progress callback that presses Ctrl-C once ``after`` epochs are done."""

    def progress(done: int, total: int) -> None:
        if done == after:
            raise KeyboardInterrupt

    return progress


def test_run_eskf_hands_on_the_completed_epochs(run_seq):
    full = run_eskf(run_seq, EskfConfig())
    with pytest.raises(EstimationInterrupted) as info:
        run_eskf(run_seq, EskfConfig(), progress=_stopper(STOP_AFTER))
    stop = info.value
    assert isinstance(stop, KeyboardInterrupt)
    assert stop.epochs_done == STOP_AFTER and stop.epochs_total == full.t.shape[1] - 1
    part = stop.result
    n = STOP_AFTER + 1
    assert part.t.shape == full.t.shape
    assert bool(part.mask[0, :n].all()) and not bool(part.mask[0, n:].any())
    for field in ("t", "position", "rotation", "covariance", "slip_factor"):
        torch.testing.assert_close(getattr(part, field)[0, :n], getattr(full, field)[0, :n])
    for key in full.accepted:
        assert torch.equal(part.accepted[key][0, :n], full.accepted[key][0, :n])
        assert not bool(part.accepted[key][0, n:].any())
    assert part.trajectory().select(0).compact().length == n


def test_run_sequence_writes_partial_outputs(run_seq, tmp_path):
    full = run_eskf(run_seq, EskfConfig())

    def progress():
        return _stopper(STOP_AFTER), lambda: None

    options = RunOptions(out_dir=tmp_path, plot=False, progress=progress)
    with pytest.raises(RunInterrupted) as info:
        run_sequence(run_seq, EskfConfig(), options)
    summary = info.value.summary
    stop = summary["interrupted"]
    assert stop["stage"] == "frontend" and stop["epochs_done"] == STOP_AFTER
    assert stop["t_s"] == pytest.approx(float(full.t[0, STOP_AFTER]), abs=1e-6)
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    traj = read_tum(tmp_path / "trajectory.tum")
    assert traj.length == STOP_AFTER + 1 == summary["epochs"]
    np.testing.assert_allclose(
        traj.position[0].numpy(), full.position[0, : STOP_AFTER + 1].numpy(), rtol=0, atol=1e-12
    )
    rows = (tmp_path / "diagnostics.csv").read_text().splitlines()
    assert len(rows) == STOP_AFTER + 2 and "divergence" in rows[0].split(",")
    assert not list(tmp_path.glob(".*.tmp"))


def test_sigint_to_msf_run_leaves_a_valid_partial_trajectory(tmp_path):
    config = SimConfig(duration_s=60.0, imu_rate_hz=100.0, slip_episodes=0, gnss_outage_count=0)
    seq = simulate_run(config, 5)
    path = write_native(seq.sequence, tmp_path / "long.npz")
    out = tmp_path / "out"
    command = [sys.executable, "-m", "msf_torch.cli", "run", str(path), "--out", str(out)]
    command += ["--no-plot", "--progress", "on", "--no-learned"]
    # a shell's background job (`cmd &`, a CI runner's) starts with SIGINT ignored, which the
    # child would inherit and Python then never raises KeyboardInterrupt: give it the default
    proc = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    os.set_blocking(proc.stderr.fileno(), False)
    seen = b""
    deadline = time.monotonic() + 180.0
    # SIGINT once the progress bar shows the epoch loop running
    while not re.search(rb"\| *[1-9][0-9]*/[0-9]+ \[", seen) and time.monotonic() < deadline:
        assert proc.poll() is None, seen.decode(errors="replace")
        seen += proc.stderr.read() or b""
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    os.set_blocking(proc.stderr.fileno(), True)
    stdout, stderr = proc.communicate(timeout=120)
    stderr = (seen + stderr).decode(errors="replace")
    assert proc.returncode == 130, stderr[-2000:]
    match = re.search(
        r"interrupted in the frontend at t = ([0-9.]+) s .*epoch (\d+) of (\d+)", stderr
    )
    assert match, stderr[-2000:]
    summary = json.loads(stdout.decode().strip().splitlines()[-1])
    stop = summary["interrupted"]
    assert 0 < stop["epochs_done"] == int(match.group(2)) < stop["epochs_total"] == 1500
    assert json.loads((out / "summary.json").read_text()) == summary
    traj = read_tum(out / "trajectory.tum")
    assert traj.length == stop["epochs_done"] + 1
    assert float(traj.t[0, -1]) == pytest.approx(stop["t_s"], abs=1e-6)
    assert float(match.group(1)) == pytest.approx(stop["t_s"], abs=1e-3)
    assert bool(torch.isfinite(traj.position).all())
    assert sorted(p.name for p in out.iterdir()) == [
        "diagnostics.csv",
        "summary.json",
        "trajectory.tum",
    ]
