"""``msf_torch.robot`` exports the robot config loader that docs/ros-and-robots.md uses."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import msf_torch.robot
from msf_torch.robot import config

DOC = Path(__file__).resolve().parents[2] / "docs" / "ros-and-robots.md"


def test_load_robot_config_is_exported():
    from msf_torch.robot import RobotConfig, load_robot_config

    assert load_robot_config is config.load_robot_config and RobotConfig is config.RobotConfig
    assert {"load_robot_config", "RobotConfig"} <= set(msf_torch.robot.__all__)
    with pytest.raises(AttributeError, match="no attribute 'load_config'"):
        msf_torch.robot.load_config  # noqa: B018


def test_importing_robot_first_in_a_fresh_interpreter(python_in):
    """robot.config imports msf_torch.io, which imports msf_torch.robot: no import cycle."""
    code = "from msf_torch.robot import load_robot_config; print(load_robot_config.__module__)"
    run = python_in("-c", code)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "msf_torch.robot.config"


def test_the_docs_python_imports_resolve():
    block = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert block is not None
    imports = [line for line in block.group(1).splitlines() if line.startswith("from ")]
    assert "from msf_torch.robot import load_robot_config" in imports
    for line in imports:
        exec(line, {})  # noqa: S102 - the doc's own import lines
