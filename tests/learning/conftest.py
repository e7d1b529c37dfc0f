"""Shared fixtures of the learning tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

TRAIN_SCRIPT = Path(__file__).resolve().parents[2] / "training" / "train.py"


@pytest.fixture
def train_script(monkeypatch) -> ModuleType:
    """``training/train.py`` loaded as a module (its ``main(args, run=...)`` is the
    LightningCLI entry point); ``sys.argv`` is set to the script alone, since the CLI reads
    only the ``args`` it is given."""
    monkeypatch.setattr(sys, "argv", [str(TRAIN_SCRIPT)])
    spec = importlib.util.spec_from_file_location("train_script", TRAIN_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
