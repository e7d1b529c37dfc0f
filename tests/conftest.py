"""Fixtures shared by the test packages."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Run a test on one torch thread, then restore the count: small batched matrices (LM
    steps, backward passes, tiny networks) are slowest when the threads oversubscribe the
    machine's cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def python_in(tmp_path):
    """``python_in(*args, timeout=120)``: this interpreter run as a subprocess in the
    test's temporary folder with one OpenMP thread; returns the ``CompletedProcess`` (text
    stdout and stderr; a non-zero exit status does not raise)."""

    def run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, *args],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
            timeout=timeout,
            check=False,
        )

    return run


@pytest.fixture(scope="module")
def every_stream_drive():
    """A 20-s simulated drive holding every stream the front end fuses (wheels with a slip
    episode, GNSS fixes, velocities and dual-antenna headings, visual and LiDAR odometry
    under a weather schedule) with the IMU samples inside 9..12 s dropped, and its settings
    (source-fault detector on)."""
    import dataclasses

    from msf_torch.frontend.config import EskfConfig, config_for_sequence
    from msf_torch.sim import SimConfig, simulate_run
    from msf_torch.sim.weather import WeatherSchedule, apply_weather

    sim = SimConfig(
        duration_s=20.0,
        gnss_velocity=True,
        gnss_heading=True,
        slip_episodes=1,
        gnss_outage_count=0,
    )
    wet = apply_weather(simulate_run(sim, seed=5), WeatherSchedule.random(20.0, seed=2), seed=3)
    seq = wet.sequence
    keep = (seq.imu.t[0] <= 9.0) | (seq.imu.t[0] >= 12.0)
    seq = dataclasses.replace(seq, imu=seq.imu.map(lambda x: x[:, keep]))
    cfg = config_for_sequence(EskfConfig(source_fault_detection=True), seq.meta, set())
    return seq, cfg


@pytest.fixture
def smoke_fit(tmp_path):
    """``smoke_fit(*args, timeout=600)``: ``training/train.py fit`` with the smoke config and
    ``args`` (``--trainer.*`` overrides) as a subprocess in the test's temporary folder (one
    OpenMP thread, logs there); returns the ``CompletedProcess`` and the run's TensorBoard
    scalars (an ``EventAccumulator``, loaded; None when the fit wrote no log)."""
    from pathlib import Path

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    root = Path(__file__).resolve().parents[1]

    def run(*args: str, timeout: float = 600):
        command = [
            sys.executable,
            str(root / "training" / "train.py"),
            "fit",
            "--config",
            str(root / "training" / "configs" / "smoke.yaml"),
            *args,
            f"--trainer.logger.init_args.save_dir={tmp_path}",
            f"--trainer.default_root_dir={tmp_path}",
        ]
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)}
        done = subprocess.run(
            command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout
        )
        versions = sorted((tmp_path / "smoke").glob("version_*"))
        if not versions:
            return done, None
        events = EventAccumulator(str(versions[-1]), size_guidance={"scalars": 0})
        events.Reload()
        return done, events

    return run
