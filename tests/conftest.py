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
