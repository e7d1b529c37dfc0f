"""Scan files and ``msf lidar-map``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from msf_torch.backend.posegraph import optimize_pose_graph
from msf_torch.cli import main
from msf_torch.io.errors import DataError
from msf_torch.io.g2o_2d import read_pose_graph_2d
from msf_torch.io.scans import read_scans, write_scans
from msf_torch.lidar.grid import read_map
from msf_torch.sim.lidar2d import corridor_map, simulate_lidar_run


def test_round_trip(tmp_path):
    run = simulate_lidar_run(corridor_map(), seed=1, duration_s=0.5)
    path = write_scans(tmp_path / "s.npz", run.t, run.angles, run.ranges, run.odometry)
    back = read_scans(path)
    assert set(back) == {"t", "angles", "ranges", "odometry"}
    assert torch.equal(back["t"], run.t) and torch.equal(back["odometry"], run.odometry)
    assert torch.equal(torch.isnan(back["ranges"]), torch.isnan(run.ranges))
    assert torch.equal(back["ranges"].nan_to_num(), run.ranges.nan_to_num())


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"t": np.array([0.0, 0.2, 0.1])}, "t"),
        ({"angles": np.array([0.0, 0.1, 0.3])}, "angles"),
        ({"ranges": np.array([[1.0, -2.0, 1.0]] * 3)}, "ranges"),
        ({"odometry": np.zeros((2, 3))}, "odometry"),
    ],
)
def test_bad_files_name_the_key(tmp_path, change, field):
    arrays = {"t": np.array([0.0, 0.1, 0.2]), "angles": np.array([0.0, 0.1, 0.2]),
              "ranges": np.ones((3, 3))}  # fmt: skip
    arrays.update(change)
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(DataError, match=field):
        read_scans(path)


def _save(path, **arrays) -> None:
    base = {"t": np.array([0.0, 0.1, 0.2]), "ranges": np.ones((3, 4))}
    np.savez(path, **{**base, **arrays})


def test_angles_in_degrees_are_refused(tmp_path):
    path = tmp_path / "deg.npz"
    _save(path, angles=np.linspace(-135.0, 135.0, 4))
    with pytest.raises(DataError) as info:
        read_scans(path)
    assert info.value.field == "angles"
    assert info.value.problem.startswith("angles look like degrees (span 270), expected radians")
    # one full turn (inclusive ends) is still radians
    _save(path, angles=np.linspace(0.0, 2 * np.pi, 4))
    assert read_scans(path)["angles"][-1] == pytest.approx(2 * np.pi)


def test_ranges_in_millimetres_are_refused(tmp_path):
    """The simulated corridor's ranges in mm are refused; in m (and with far returns up to
    the limit) they read."""
    run = simulate_lidar_run(corridor_map(), seed=1, duration_s=0.5)
    path = write_scans(tmp_path / "mm.npz", run.t, run.angles, run.ranges * 1000.0)
    with pytest.raises(DataError) as info:
        read_scans(path)
    assert info.value.field == "ranges"
    assert info.value.problem.startswith("ranges look like millimetres (median ")
    far = tmp_path / "far.npz"
    _save(far, angles=np.linspace(0.0, 1.0, 4), ranges=np.full((3, 4), 250.0))
    assert float(read_scans(far)["ranges"].max()) == 250.0


def test_non_finite_angle_is_named(tmp_path):
    path = tmp_path / "inf.npz"
    _save(path, angles=np.array([0.0, 0.1, np.inf, 0.3]))
    with pytest.raises(DataError, match="beam angle 2 is not finite"):
        read_scans(path)


def test_wrong_npz_lists_its_keys_not_its_values(tmp_path):
    """A sensor sequence .npz given as a scan file: the key names, not the meta JSON."""
    path = tmp_path / "sensor.npz"
    meta = '{"imu_noise": {"gyro_noise_density": 1e-4}, "wheel_track_m": 0.5}'
    keys = [f"imu/{k}" for k in "abcdefghij"]
    np.savez(path, **{k: np.zeros(2) for k in keys}, meta_json=np.array(meta))
    with pytest.raises(DataError) as info:
        read_scans(path)
    shown = ", ".join(keys[:8])
    assert info.value.problem == f"missing key 't' (has: {shown}, ... (11 keys))"
    np.savez(path, t=np.array([0.0, 0.1]), angles=np.array([0.0, 0.1]), meta_json=np.array(meta))
    with pytest.raises(DataError, match="missing key 'ranges' \\(has: t, angles, meta_json\\)"):
        read_scans(path)
    _save(path, angles=np.array([0.0, 0.1, 0.2, 0.3]), meta_json=np.array(meta))
    with pytest.raises(DataError) as info:
        read_scans(path)
    assert info.value.field == "meta_json" and "wheel_track_m" not in str(info.value)


def test_cli_lidar_map(tmp_path, capsys):
    out = tmp_path / "map"
    status = main(["lidar-map", "--simulate", "corridor", "--duration", "2", "--out", str(out)])
    assert status == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["scans"] == 21 and summary["initial_guess"] == "odometry"
    assert summary["failed_pairs"] == 0
    assert summary["lidar_error"]["final_m"] < 0.05
    grid = read_map(out / "map.yaml")
    assert (grid.trinary == 1).sum() == summary["occupied_cells"]
    assert (out / "lidar_odometry.tum").read_text().count("\n") == 22  # header + 21 poses
    # the chain as a 2-D pose graph: 21 scans, 20 matched pairs, consistent (zero cost)
    graph = read_pose_graph_2d(summary["files"]["graph"])
    assert (graph.num_vertices, graph.num_edges) == (21, 20)
    assert bool((torch.linalg.eigvalsh(graph.edge_information) > 0).all())
    assert optimize_pose_graph(graph).initial_cost < 1e-12
    assert main(["lidar-map", "--out", str(out)]) == 2
