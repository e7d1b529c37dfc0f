"""``msf eval`` against a recorded sequence's ground truth or GNSS fixes, and at a lever arm:
closed forms (a trajectory against itself seen from an antenna 1.3 m away) and the TUM route
on the same poses."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.eval.metrics import evaluate_files, load_reference
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io.native import write_native
from msf_torch.io.tum import write_tum
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import GnssFixes, Trajectory

LEVER_ARM = (0.4, -0.3, 1.2)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A simulated run whose GNSS fixes are its true antenna positions (every 100th truth
    sample, lever arm :data:`LEVER_ARM`), written as a native folder; the truth as TUM."""
    folder = tmp_path_factory.mktemp("reference")
    seq = simulate_run(SimConfig(duration_s=30.0, slip_episodes=0, gnss_outages_s=()), 4).sequence
    truth = seq.ground_truth.compact()
    pick = torch.arange(0, truth.t.shape[1], 100)
    rotation = quat_to_matrix(truth.quaternion[:, pick])
    antenna = (
        truth.position[:, pick] + (rotation @ torch.tensor(LEVER_ARM).double()[:, None])[..., 0]
    )
    fixes = GnssFixes(
        t=truth.t[:, pick],
        position=antenna,
        sigma=torch.full_like(antenna, float("nan")),
        mask=torch.ones_like(truth.t[:, pick], dtype=torch.bool),
    )
    seq = dataclasses.replace(seq, gnss=fixes)
    run = write_native(seq, folder / "run")
    return seq, run, write_tum(truth, folder / "truth.tum")


def _noisy(truth: Trajectory, path, seed: int = 0):
    rng = np.random.default_rng(seed)
    drift = np.cumsum(rng.normal(size=truth.position.shape[1:]) * 0.002, 0)
    moved = dataclasses.replace(truth, position=truth.position + torch.as_tensor(drift)[None])
    return write_tum(moved, path)


def test_gnss_reference_at_the_lever_arm_is_exact(recorded, tmp_path, capsys) -> None:
    seq, run, truth_tum = recorded
    out = evaluate_files(truth_tum, run, reference_stream="gnss", lever_arm=LEVER_ARM)
    assert out["reference_kind"] == "gnss" and out["align"] == "none"
    assert out["rpe"] is None and "positions only" in out["rpe_skipped"]
    assert out["matched"] == seq.gnss.t.shape[1]
    assert out["ate"]["max"] < 1e-6  # the TUM file's digits
    # at the body origin every error is the lever arm's length; without a ground truth in
    # the sequence its GNSS fixes are the reference
    no_truth = write_native(dataclasses.replace(seq, ground_truth=None), tmp_path / "gnss_only")
    assert main(["eval", str(truth_tum), str(no_truth)]) == 0
    plain = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert plain["reference_kind"] == "gnss"
    norm = math.hypot(*LEVER_ARM)
    assert plain["ate"]["min"] == pytest.approx(norm, abs=1e-6)
    assert plain["ate"]["max"] == pytest.approx(norm, abs=1e-6)
    assert "lever_arm_m" not in plain


def test_ground_truth_reference_equals_the_tum_route(recorded, tmp_path) -> None:
    seq, run, truth_tum = recorded
    estimate = _noisy(seq.ground_truth.compact(), tmp_path / "est.tum")
    from_folder = evaluate_files(estimate, run, reference_stream="ground_truth", delta=10)
    from_tum = evaluate_files(estimate, truth_tum, delta=10)
    assert from_folder["reference_kind"] == "ground_truth" and from_tum["reference_kind"] == "tum"
    assert from_folder["ate"] == from_tum["ate"] and from_folder["rpe"] == from_tum["rpe"]
    assert from_folder["align"] == "se3" and from_folder["ate"]["rmse"] > 1e-3
    auto = evaluate_files(estimate, run, delta=10)  # the ground truth comes first
    assert auto["ate"] == from_tum["ate"]


def test_reference_errors(recorded, tmp_path, capsys) -> None:
    seq, run, truth_tum = recorded
    with pytest.raises(ValueError, match="TUM trajectory"):
        load_reference(truth_tum, "gnss")
    with pytest.raises(ValueError, match="reference stream"):
        load_reference(run, "lidar")
    bare = write_native(dataclasses.replace(seq, gnss=None, ground_truth=None), tmp_path / "bare")
    with pytest.raises(ValueError, match="no ground truth or GNSS"):
        load_reference(bare)
    with pytest.raises(ValueError, match="no ground truth"):
        load_reference(bare, "ground_truth")
    assert main(["eval", str(truth_tum), str(bare), "--reference-stream", "gnss"]) == 2
    assert "has no GNSS fixes" in capsys.readouterr().err
