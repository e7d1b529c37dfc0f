"""What ``msf run`` tells a user about its outputs and input (``runner`` + ``cli._notes``):

* ``--out`` naming an existing file: exit status 2 and one line, no traceback;
* files of an earlier run that this run does not rewrite are listed (``stale_outputs``);
* a GNSS outage labelled in the data is scored against the ground truth
  (``labelled_gnss_outages``), checked against the truth's own path length and the
  estimate's error computed here from the written TUM file;
* a run without GNSS or pose measurements says it is dead reckoning
  (``absolute_aiding``), and slip detection is not reported enabled without wheels.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.io.native import write_native
from msf_torch.io.tum import read_tum
from msf_torch.sim import SimConfig, simulate_run


@pytest.fixture(scope="module")
def outage_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("outputs")
    config = SimConfig(duration_s=40.0, slip_episodes=0, gnss_outages_s=((15.0, 30.0),))
    run = simulate_run(config, 5)
    return run, write_native(run.sequence, folder / "run.npz")


def _summary(capsys) -> tuple[dict, str]:
    captured = capsys.readouterr()
    return json.loads(captured.out.strip().splitlines()[-1]), captured.err


def test_out_naming_a_file_is_refused(outage_run, tmp_path, capsys) -> None:
    _, path = outage_run
    target = tmp_path / "afile"
    target.write_text("")
    assert main(["run", str(path), "--out", str(target), "--no-plot"]) == 2
    err = capsys.readouterr().err
    assert err == f"msf run: error: output folder {target} is an existing file; give a folder\n"


def test_stale_outputs_and_labelled_outage(outage_run, tmp_path, capsys) -> None:
    run, path = outage_run
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--export", "kitti"]) == 0
    first, _ = _summary(capsys)
    assert "stale_outputs" not in first and first["absolute_aiding"] is True
    assert main(["run", str(path), "--out", str(out), "--no-plot"]) == 0
    second, err = _summary(capsys)
    assert second["stale_outputs"] == ["trajectory.kitti", "trajectory_times.txt", "overview.png"]
    assert "trajectory.kitti, trajectory_times.txt, overview.png" in err
    (outage,) = second["labelled_gnss_outages"]
    t0 = float(run.sequence.start_time[0])
    assert (outage["start_s"], outage["end_s"]) == (pytest.approx(15.0), pytest.approx(30.0))
    truth = run.sequence.ground_truth
    inside = (truth.t[0] >= t0 + 15.0) & (truth.t[0] <= t0 + 30.0) & truth.mask[0]
    t_ref, p_ref = truth.t[0, inside].numpy(), truth.position[0, inside].numpy()
    assert outage["outage_distance_m"] == pytest.approx(
        np.linalg.norm(np.diff(p_ref, axis=0), axis=1).sum(), rel=1e-3
    )
    estimate = read_tum(out / "trajectory.tum")
    t_est, p_est = estimate.t[0].numpy(), estimate.position[0].numpy()
    interpolated = np.stack([np.interp(t_ref, t_est, p_est[:, k]) for k in range(3)], -1)
    error = np.linalg.norm(interpolated - p_ref, axis=1)
    assert outage["outage_rmse_m"] == pytest.approx(np.sqrt(np.mean(error**2)), rel=1e-3)
    assert outage["outage_max_error_m"] == pytest.approx(error.max(), rel=1e-3)


def test_dead_reckoning_is_said(outage_run, tmp_path, capsys) -> None:
    run, _ = outage_run
    bare = dataclasses.replace(run.sequence, gnss=None, wheel=None)
    path = write_native(bare, tmp_path / "imu_only.npz")
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--no-plot"]) == 0
    summary, err = _summary(capsys)
    assert summary["absolute_aiding"] is False and summary["slip_detection_enabled"] is False
    assert "no GNSS or pose measurements were fused: dead reckoning" in err


def test_reader_warnings_are_one_line(tmp_path, capsys) -> None:
    """A reader's warning (here: a g2o tag it does not read) reaches the user as one
    ``msf COMMAND: warning:`` line, not Python's two-line warning with a source location."""
    info = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"  # upper triangle of I (6 x 6)
    graph = tmp_path / "graph.g2o"
    graph.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
        "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info}\n"
        "FOO_BAR 1 2 3\n"
    )
    assert main(["posegraph", str(graph)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("msf posegraph: warning: ")
    assert "'FOO_BAR' x1 (first on line 4)" in err[0]


def test_a_stream_on_another_clock_is_named_and_ignored(outage_run, tmp_path, capsys) -> None:
    """GNSS stamped in UNIX seconds beside IMU seconds since boot: a warning names the
    stream and both spans, and the run is the dead-reckoning run (the initial state too)."""
    run, _ = outage_run
    gnss = run.sequence.gnss
    shifted = dataclasses.replace(gnss, t=gnss.t + 1.7e9)
    off = write_native(dataclasses.replace(run.sequence, gnss=shifted), tmp_path / "off.npz")
    none = write_native(dataclasses.replace(run.sequence, gnss=None), tmp_path / "none.npz")
    assert main(["run", str(off), "--out", str(tmp_path / "off"), "--no-plot"]) == 0
    err = capsys.readouterr().err
    assert "none of the" in err and "gnss samples" in err and "another clock" in err
    assert main(["run", str(none), "--out", str(tmp_path / "none"), "--no-plot"]) == 0
    capsys.readouterr()
    a = read_tum(tmp_path / "off" / "trajectory.tum")
    b = read_tum(tmp_path / "none" / "trajectory.tum")
    assert torch.equal(a.position, b.position)
