"""``python -m msf_torch`` runs the ``msf`` command line."""

from __future__ import annotations

import importlib.metadata


def test_python_m_msf_torch_version_and_exit_status(tmp_path, python_in):
    run = python_in("-m", "msf_torch", "--version")
    assert run.returncode == 0, run.stderr
    version = importlib.metadata.version("msf_torch")
    assert run.stdout.startswith(f"msf {version} (torch "), run.stdout
    missing = python_in("-m", "msf_torch", "posegraph", str(tmp_path / "absent.g2o"))
    assert missing.returncode == 2 and "absent.g2o: no such file" in missing.stderr
