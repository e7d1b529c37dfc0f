"""Pose-graph optimisation against GTSAM's LevenbergMarquardtOptimizer: the same cost at the
start and the optimum, the same poses, robust kernels that downweight an outlier edge."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msf_torch.backend.posegraph import optimize_pose_graph, pose_graph_config
from msf_torch.backend.robust import RobustKernel
from msf_torch.geometry import so3
from msf_torch.io import PoseGraph, gtsam_pose_graph_path, read_pose_graph

SWAP = [3, 4, 5, 0, 1, 2]
"""[dp, dtheta] <-> GTSAM's [rot, trans] order of a 6-vector (its own inverse)."""
FILES = (
    "pose3example.txt",
    "pose3example-grid.txt",
    "pose3example-offdiagonal.txt",
    "pose3example-offdiagonal-rewritten.txt",
)
TIGHT = pose_graph_config(relative_tolerance=1e-12, max_iterations=200)


@pytest.fixture(scope="module")
def gtsam():
    return pytest.importorskip("gtsam")


def _gtsam_lm(gtsam, factors, initial, first_id: int):
    """GTSAM LM to a tight tolerance with the first pose held by NonlinearEquality."""
    held = gtsam.NonlinearFactorGraph(factors)
    held.add(gtsam.NonlinearEqualityPose3(first_id, initial.atPose3(first_id)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(200)
    return gtsam.LevenbergMarquardtOptimizer(held, initial, params).optimize()


def _gtsam_graph(gtsam, graph: PoseGraph, kernel: RobustKernel | None):
    """GTSAM factors and initial values built from a PoseGraph (information in its order)."""
    factors = gtsam.NonlinearFactorGraph()
    ids = graph.vertex_ids.tolist()
    for k, (a, b) in enumerate(graph.edge_index.tolist()):
        info = graph.edge_information[k].numpy()[SWAP][:, SWAP]
        noise = gtsam.noiseModel.Gaussian.Information(info)
        if kernel is not None:
            estimator = {
                "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
                "huber": gtsam.noiseModel.mEstimator.Huber,
            }
            noise = gtsam.noiseModel.Robust.Create(
                estimator[kernel.name].Create(kernel.scale), noise
            )
        measured = gtsam.Pose3(
            gtsam.Rot3(graph.edge_rotations[k].numpy()), graph.edge_translations[k].numpy()
        )
        factors.add(gtsam.BetweenFactorPose3(ids[a], ids[b], measured, noise))
    initial = gtsam.Values()
    for k, vid in enumerate(ids):
        pose = gtsam.Pose3(gtsam.Rot3(graph.rotations[k].numpy()), graph.positions[k].numpy())
        initial.insert(vid, pose)
    return factors, initial


def _poses(values, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    rotations = np.stack([values.atPose3(i).rotation().matrix() for i in ids])
    positions = np.stack([values.atPose3(i).translation() for i in ids])
    return rotations, positions


def _perturbed(graph: PoseGraph, seed: int) -> PoseGraph:
    """The graph with every vertex but the first moved (0.1 rad, 0.2 m rms per axis): the
    offdiagonal example files start at their optimum (cost 0)."""
    gen = torch.Generator().manual_seed(seed)
    n = graph.num_vertices
    turn = 0.1 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    shift = 0.2 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    turn[0], shift[0] = 0.0, 0.0
    return dataclasses.replace(
        graph, rotations=graph.rotations @ so3.exp(turn), positions=graph.positions + shift
    )


@pytest.mark.parametrize("name", FILES)
def test_cost_and_poses_equal_gtsam_lm(gtsam, name):
    path = str(gtsam_pose_graph_path(name))
    graph = _perturbed(read_pose_graph(path), seed=len(name))
    factors, _ = gtsam.readG2o(path, True)  # GTSAM's own parse of the file's edges
    ids = graph.vertex_ids.tolist()
    initial = gtsam.Values()
    for k, vid in enumerate(ids):
        pose = gtsam.Pose3(gtsam.Rot3(graph.rotations[k].numpy()), graph.positions[k].numpy())
        initial.insert(vid, pose)
    solved = _gtsam_lm(gtsam, factors, initial, ids[0])

    result = optimize_pose_graph(graph, config=TIGHT)

    assert result.status == "converged"
    assert result.initial_cost == pytest.approx(factors.error(initial), rel=1e-10)
    assert result.final_cost == pytest.approx(factors.error(solved), rel=1e-6)
    rotations, positions = _poses(solved, ids)
    scale = max(1.0, float(np.abs(positions).max()))
    np.testing.assert_allclose(result.graph.positions.numpy(), positions, atol=1e-5 * scale)
    angle = so3.log(torch.as_tensor(rotations).mT @ result.graph.rotations).norm(dim=-1)
    assert float(angle.max()) < 1e-5
    assert torch.equal(result.graph.positions[0], graph.positions[0])  # the gauge vertex
    assert torch.equal(result.graph.edge_information, graph.edge_information)


def test_log_and_result_fields(gtsam):
    graph = read_pose_graph(gtsam_pose_graph_path("pose3example-grid.txt"))
    before = graph.positions.clone()
    result = optimize_pose_graph(graph)
    assert torch.equal(graph.positions, before)  # the input is not modified
    assert result.converged and result.iterations == len(result.log) > 0
    accepted = [entry["cost"] for entry in result.log if entry["accepted"]]
    assert accepted[-1] == result.final_cost < result.initial_cost
    assert all(b <= a for a, b in zip(accepted, accepted[1:], strict=False))
    assert result.seconds > 0


def test_other_fixed_vertex_and_bad_index(gtsam):
    graph = read_pose_graph(gtsam_pose_graph_path("pose3example.txt"))
    last = graph.num_vertices - 1
    result = optimize_pose_graph(graph, config=TIGHT, fixed=[last])
    assert torch.equal(result.graph.positions[last], graph.positions[last])
    assert torch.equal(result.graph.rotations[last], graph.rotations[last])
    reference = optimize_pose_graph(graph, config=TIGHT)
    assert result.final_cost == pytest.approx(reference.final_cost, rel=1e-8)  # gauge only
    with pytest.raises(ValueError, match="fixed vertex"):
        optimize_pose_graph(graph, fixed=[graph.num_vertices])


def test_fix_record_holds_its_vertex_instead_of_the_first(gtsam, tmp_path):
    """g2o's ``FIX id``: that vertex is the gauge (unchanged by the solve), the others move,
    and the result is the one of ``fixed=[its row]``."""
    source = gtsam_pose_graph_path("pose3example.txt")
    plain = read_pose_graph(source)
    last = plain.num_vertices - 1
    path = tmp_path / "fixed.g2o"
    path.write_text(source.read_text().rstrip() + f"\nFIX {int(plain.vertex_ids[last])}\n")
    graph = read_pose_graph(path)
    assert graph.fixed_ids == (int(plain.vertex_ids[last]),)
    result = optimize_pose_graph(graph, config=TIGHT)
    assert torch.equal(result.graph.positions[last], graph.positions[last])
    assert torch.equal(result.graph.rotations[last], graph.rotations[last])
    moved = (result.graph.positions - graph.positions).norm(dim=1)
    assert bool((moved[:last] > 1e-4).all())  # the first vertex is not held any more
    explicit = optimize_pose_graph(plain, config=TIGHT, fixed=[last])
    torch.testing.assert_close(result.graph.positions, explicit.graph.positions, rtol=0, atol=0)


def _with_outlier(graph: PoseGraph) -> PoseGraph:
    """The graph plus one wrong loop closure first -> last vertex (0.7 m, 0.3 rad off)."""
    i, j = 0, graph.num_vertices - 1
    wrong_t = torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64)
    wrong_r = so3.exp(torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64))
    return dataclasses.replace(
        graph,
        edge_index=torch.cat((graph.edge_index, torch.tensor([[i, j]]))),
        edge_rotations=torch.cat((graph.edge_rotations, wrong_r)),
        edge_translations=torch.cat((graph.edge_translations, wrong_t)),
        edge_information=torch.cat((graph.edge_information, graph.edge_information[:1])),
        edge_lines=None,
    )


@pytest.mark.parametrize(
    ("kernel", "limit_m"),
    [(None, None), (RobustKernel("cauchy", 1.0), 0.02), (RobustKernel("huber", 1.0), 0.15)],
)
def test_outlier_edge_is_downweighted(gtsam, kernel, limit_m):
    graph = read_pose_graph(gtsam_pose_graph_path("pose3example-grid.txt"))
    spoiled = _with_outlier(graph)
    clean = optimize_pose_graph(graph, robust=kernel, config=TIGHT)
    result = optimize_pose_graph(spoiled, robust=kernel, config=TIGHT)
    moved = float((result.graph.positions - clean.graph.positions).norm(dim=-1).max())
    if kernel is None:
        assert moved > 1.0  # least squares follows the outlier (the graph spans ~3.5 m)
    else:
        assert moved < limit_m

    factors, initial = _gtsam_graph(gtsam, spoiled, kernel)
    solved = _gtsam_lm(gtsam, factors, initial, int(spoiled.vertex_ids[0]))
    assert result.initial_cost == pytest.approx(factors.error(initial), rel=1e-10)
    assert result.final_cost == pytest.approx(factors.error(solved), rel=1e-6)
    _, positions = _poses(solved, spoiled.vertex_ids.tolist())
    np.testing.assert_allclose(result.graph.positions.numpy(), positions, atol=1e-4)


@pytest.mark.parametrize("solver", ["sparse", "dense"])
def test_vertex_without_edges_stays_and_the_rest_solves_as_gtsam(gtsam, tmp_path, solver):
    """A vertex no edge names (e.g. one tied to the graph only by skipped landmark edges)
    has no entry in the Hessian; GTSAM's LM leaves it where it is and solves the rest."""
    pose = "0 0 0 1"
    info = " ".join(["1 0 0 0 0 0", "1 0 0 0 0", "1 0 0 0", "1 0 0", "1 0", "1"])
    path = tmp_path / "island.g2o"
    path.write_text(
        f"VERTEX_SE3:QUAT 0 0 0 0 {pose}\nVERTEX_SE3:QUAT 1 1.3 0.2 0 {pose}\n"
        f"VERTEX_SE3:QUAT 2 2.1 -0.4 0.1 {pose}\nVERTEX_SE3:QUAT 7 5 5 5 {pose}\n"
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0.1 0.995 {info}\n"
        f"EDGE_SE3:QUAT 1 2 1 0 0 0 0 -0.1 0.995 {info}\n"
        f"EDGE_SE3:QUAT 0 2 2.2 0 0 0 0 0 1 {info}\n"
    )
    graph = read_pose_graph(path)
    config = dataclasses.replace(TIGHT, linear_solver=solver)
    result = optimize_pose_graph(graph, config=config)
    factors, initial = gtsam.readG2o(str(path), True)
    solved = _gtsam_lm(gtsam, factors, initial, 0)
    assert result.status == "converged" and result.initial_cost > 0.1
    assert result.final_cost == pytest.approx(factors.error(solved), rel=1e-6)
    _, positions = _poses(solved, [0, 1, 2, 7])
    np.testing.assert_allclose(result.graph.positions.numpy(), positions, atol=1e-6)
    assert result.graph.positions[3].tolist() == [5.0, 5.0, 5.0]


def test_graph_of_one_vertex(gtsam, tmp_path):
    """Nothing to solve (its one vertex is the gauge): converged as it stands, and the g2o
    written back reads in GTSAM as one pose and no factors."""
    from msf_torch.cli import main

    path = tmp_path / "one.g2o"
    path.write_text("VERTEX_SE3:QUAT 4 1 2 3 0 0 0 1\n")
    out = tmp_path / "out.g2o"
    assert main(["posegraph", str(path), "--out", str(out)]) == 0
    result = optimize_pose_graph(read_pose_graph(path))
    assert (result.status, result.final_cost, result.iterations) == ("converged", 0.0, 0)
    factors, values = gtsam.readG2o(str(out), True)
    assert (factors.size(), values.size()) == (0, 1)
    assert values.atPose3(4).translation().tolist() == [1.0, 2.0, 3.0]
