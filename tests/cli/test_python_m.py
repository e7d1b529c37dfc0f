"""``python -m msf_torch`` runs the ``msf`` command line."""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys


def test_python_m_msf_torch_version_and_exit_status(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(
        [sys.executable, "-m", "msf_torch", "--version"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    version = importlib.metadata.version("msf_torch")
    assert run.stdout.startswith(f"msf {version} (torch "), run.stdout
    missing = subprocess.run(
        [sys.executable, "-m", "msf_torch", "posegraph", str(tmp_path / "absent.g2o")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
        check=False,
    )
    assert missing.returncode == 2 and "absent.g2o: no such file" in missing.stderr
