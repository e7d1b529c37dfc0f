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
    episode, GNSS fixes and velocities, visual and LiDAR odometry under a weather schedule)
    with the IMU samples inside 9..12 s dropped, and its settings (source-fault detector on)."""
    import dataclasses

    from msf_torch.frontend.config import EskfConfig, config_for_sequence
    from msf_torch.sim import SimConfig, simulate_run
    from msf_torch.sim.weather import WeatherSchedule, apply_weather

    sim = SimConfig(duration_s=20.0, gnss_velocity=True, slip_episodes=1, gnss_outage_count=0)
    wet = apply_weather(simulate_run(sim, seed=5), WeatherSchedule.random(20.0, seed=2), seed=3)
    seq = wet.sequence
    keep = (seq.imu.t[0] <= 9.0) | (seq.imu.t[0] >= 12.0)
    seq = dataclasses.replace(seq, imu=seq.imu.map(lambda x: x[:, keep]))
    cfg = config_for_sequence(EskfConfig(source_fault_detection=True), seq.meta, set())
    return seq, cfg
