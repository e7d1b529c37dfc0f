"""``python -m msf_torch`` runs the ``msf`` command line."""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys


def _python_m(folder, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "msf_torch", *args],
        capture_output=True,
        text=True,
        cwd=folder,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=120,
        check=False,
    )


def test_python_m_msf_torch_version_and_exit_status(tmp_path):
    run = _python_m(tmp_path, "--version")
    assert run.returncode == 0, run.stderr
    version = importlib.metadata.version("msf_torch")
    assert run.stdout.startswith(f"msf {version} (torch "), run.stdout
    missing = _python_m(tmp_path, "posegraph", str(tmp_path / "absent.g2o"))
    assert missing.returncode == 2 and "absent.g2o: no such file" in missing.stderr
