"""3-D pose graphs (g2o / TORO): GTSAM's parse as the reference, round trips, bad input."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io import (
    GTSAM_POSE3_FILES,
    DataError,
    MissingExtraError,
    PoseGraph,
    gtsam_pose_graph_path,
    read_pose_graph,
    write_g2o,
)

SWAP = [3, 4, 5, 0, 1, 2]
"""[rot, trans] <-> [trans, rot] permutation of a 6-vector (its own inverse)."""

POSE_TAGS = ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "VERTEX3", "EDGE3")
VERTICES_ONLY = ("example_with_vertices.g2o", "edge_se3_trackxyz_example.g2o")
"""gtsam Data files with 3-D vertices and landmark records but no pose edges: GTSAM reads
their poses; we refuse them (no pose graph to solve), naming the landmark tags."""
GTSAM_REJECTS = (
    "edge_se3_trackxyz_missing_vertex.g2o",
    "edge_se3_trackxyz_nonidentity_offset.g2o",
    "edge_se3_trackxyz_zero_range.g2o",
)
"""One-vertex files whose landmark edge GTSAM rejects (they test its landmark parser); we
refuse them too: their one edge is a landmark record, so there is no pose edge."""


@pytest.fixture(scope="module")
def gtsam():
    return pytest.importorskip("gtsam")


@pytest.fixture(scope="module")
def sphere(gtsam) -> PoseGraph:
    """sphere2500.txt (TORO EDGE3, edges only), read once for the module."""
    return read_pose_graph(gtsam_pose_graph_path("sphere2500.txt"))


@pytest.fixture(scope="module")
def sphere_gtsam(gtsam):
    """GTSAM's parse of sphere2500.txt: (Pose3 Values, [BetweenFactorPose3])."""
    return _gtsam_parse(gtsam, gtsam_pose_graph_path("sphere2500.txt"))


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _write(tmp_path: Path, text: str, name: str = "graph.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _gtsam_parse(gtsam, path: Path):
    """(Pose3 Values, [BetweenFactorPose3]) from GTSAM's own 3-D reader."""
    graph, values = gtsam.readG2o(str(path), True)
    factors = [graph.at(k) for k in range(graph.size())]
    between = [f for f in factors if isinstance(f, gtsam.BetweenFactorPose3)]
    return gtsam.utilities.allPose3s(values), between


def _assert_close(a, b, tol: float = 1e-12) -> None:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    scale = max(1.0, float(np.abs(b).max(initial=0.0)))
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * scale)


# ------------------------------------------------------------------ GTSAM as the reference


def test_listed_files_are_all_3d_pose_graphs_in_the_wheel(gtsam):
    """Every gtsam Data file with a 3-D pose tag is listed, vertex-only, or known-bad."""
    folder = gtsam_pose_graph_path("sphere2500.txt").parent
    found = set()
    for path in folder.iterdir():
        if path.suffix not in (".txt", ".g2o", ".graph") or not path.is_file():
            continue
        with path.open(errors="replace") as handle:
            tags = {line.split(maxsplit=1)[0] for line in handle if line.strip()}
        if tags & set(POSE_TAGS):
            found.add(path.name)
    known_bad = {"sphere_smallnoise.graph", *GTSAM_REJECTS}
    assert found == set(GTSAM_POSE3_FILES) | set(VERTICES_ONLY) | known_bad


@pytest.mark.parametrize("name", GTSAM_REJECTS)
def test_files_of_landmark_edges_only_are_refused(gtsam, name):
    path = gtsam_pose_graph_path(name)
    with pytest.raises(DataError) as info:
        read_pose_graph(path)
    assert info.value.path == str(path) and "no pose edges" in info.value.problem
    assert re.search(r"'EDGE_SE3_TRACKXYZ' x1 \(first on line \d\)", info.value.problem)
    assert "'PARAMS_SE3OFFSET' x1" in info.value.problem
    with pytest.raises(ValueError, match="EDGE_SE3_TRACKXYZ"):
        gtsam.readG2o(str(path), True)


@pytest.mark.parametrize("name", VERTICES_ONLY)
def test_vertices_and_landmarks_without_pose_edges_are_refused(gtsam, name):
    """The audit's case: edge_se3_trackxyz_example.g2o used to read as 0 edges, "converged"."""
    path = gtsam_pose_graph_path(name)
    with pytest.raises(DataError, match=r"no pose edges .*'VERTEX_TRACKXYZ' x\d+"):
        read_pose_graph(path)
    _, values = gtsam.readG2o(str(path), True)
    assert values.size() > 0  # GTSAM returns the poses alone


def test_pose_files_with_landmark_records_warn_once(gtsam):
    path = gtsam_pose_graph_path("known_landmark_localization_3.g2o")
    with pytest.warns(UserWarning) as caught:
        graph = read_pose_graph(path)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert message.startswith(f"{path}: skipped 17 lines")
    assert "'EDGE_SE3_TRACKXYZ' x12" in message and "'VERTEX_TRACKXYZ' x4" in message
    assert graph.num_edges == 2 and graph.skipped["EDGE_SE3_TRACKXYZ"] == 12


@pytest.mark.parametrize("name", GTSAM_POSE3_FILES)
def test_matches_gtsam_parse(gtsam, name):
    path = gtsam_pose_graph_path(name)
    ours = read_pose_graph(path)
    poses, factors = _gtsam_parse(gtsam, path)

    if ours.has_vertices:
        keys = sorted(poses.keys())
        assert ours.vertex_ids.tolist() == keys
        _assert_close(ours.rotations, [poses.atPose3(k).rotation().matrix() for k in keys])
        _assert_close(ours.positions, [poses.atPose3(k).translation() for k in keys])
    else:
        assert name.startswith("sphere2500") and poses.size() == 0

    assert ours.num_edges == len(factors)
    if not factors:
        return
    assert ours.edge_ids().tolist() == [list(f.keys()) for f in factors]
    measured = [f.measured() for f in factors]
    _assert_close(ours.edge_rotations, [m.rotation().matrix() for m in measured])
    _assert_close(ours.edge_translations, [m.translation() for m in measured])
    info = np.stack([f.noiseModel().information() for f in factors])  # [rot, trans]
    _assert_close(ours.edge_information, info[:, SWAP][:, :, SWAP])


def test_offdiagonal_g2o_information_is_the_file_matrix(gtsam):
    """EDGE_SE3:QUAT: the file's [x y z qx qy qz] matrix is ours unchanged; GTSAM swaps it."""
    ours = read_pose_graph(gtsam_pose_graph_path("pose3example-offdiagonal.txt"))
    upper = [10000, 1, 1, 1, 1, 1, 10000, 2, 2, 2, 2, 10000, 3, 3, 3, 10000, 4, 4, 10000, 5, 10000]
    expected = np.zeros((6, 6))
    expected[np.triu_indices(6)] = upper
    expected = expected + np.triu(expected, 1).T
    assert ours.edge_information[0].tolist() == expected.tolist()
    _, factors = _gtsam_parse(gtsam, gtsam_pose_graph_path("pose3example-offdiagonal.txt"))
    gtsam_info = factors[0].noiseModel().information()
    _assert_close(gtsam_info[:3, :3], expected[3:, 3:])  # GTSAM's rotation block first
    _assert_close(gtsam_info[:3, 3:], expected[3:, :3])


def test_toro_edge3_information_follows_gtsam_order(sphere, sphere_gtsam):
    """EDGE3: GTSAM reads the file matrix as [rot, trans], so sphere2500's
    ``10 .. 10 .. 10 .. 100 .. 100 .. 25`` is translation 100, 100, 25 and rotation 10."""
    ours, (_, factors) = sphere, sphere_gtsam
    expected = torch.diag(torch.tensor([100.0, 100.0, 25.0, 10.0, 10.0, 10.0], dtype=torch.float64))
    assert torch.equal(ours.edge_information, expected.expand(ours.num_edges, 6, 6))
    np.testing.assert_allclose(
        factors[0].noiseModel().sigmas(), 1 / np.sqrt([10, 10, 10, 100, 100, 25]), rtol=1e-14
    )


def test_sphere2500_initial_poses_are_the_odometry_chain(gtsam, sphere, sphere_gtsam):
    ours, (_, factors) = sphere, sphere_gtsam
    assert not ours.has_vertices
    assert ours.vertex_ids.tolist() == list(range(2500))
    odometry = {tuple(f.keys()): f.measured() for f in reversed(factors)}  # first one wins
    pose = gtsam.Pose3()
    rotations, positions = [pose.rotation().matrix()], [pose.translation()]
    for k in range(2499):
        pose = pose.compose(odometry[(k, k + 1)])
        rotations.append(pose.rotation().matrix())
        positions.append(pose.translation())
    assert ours.rotations[0].tolist() == np.eye(3).tolist()
    assert ours.positions[0].tolist() == [0.0, 0.0, 0.0]
    # 2499 compositions, positions up to ~100 m: rounding differences stay below 1e-11
    _assert_close(ours.rotations, rotations, tol=1e-11)
    _assert_close(ours.positions, positions, tol=1e-11)


@pytest.mark.parametrize(
    "name", ["pose3example-offdiagonal.txt", "pose3example-grid.txt", "sphere2500.txt"]
)
def test_whitened_cost_equals_gtsam_error(gtsam, name):
    """0.5 sum r^T Lambda r with r = [rho, omega] (GTSAM's Pose3 Logmap, swapped into our
    order) and our information equals GTSAM's ``graph.error`` at perturbed poses."""
    path = gtsam_pose_graph_path(name)
    ours = read_pose_graph(path)
    graph, _ = gtsam.readG2o(str(path), True)
    rng = np.random.default_rng(7)
    values = gtsam.Values()
    poses = {}
    for row, vid in enumerate(ours.vertex_ids.tolist()):
        pose = gtsam.Pose3(gtsam.Rot3(ours.rotations[row].numpy()), ours.positions[row].numpy())
        pose = pose.retract(rng.normal(scale=0.05, size=6))
        poses[vid] = pose
        values.insert(vid, pose)
    cost = 0.0
    for e, (i, j) in enumerate(ours.edge_ids().tolist()):
        measured = gtsam.Pose3(
            gtsam.Rot3(ours.edge_rotations[e].numpy()), ours.edge_translations[e].numpy()
        )
        err = measured.inverse().compose(poses[i].inverse().compose(poses[j]))
        r = gtsam.Pose3.Logmap(err)[SWAP]
        cost += 0.5 * r @ ours.edge_information[e].numpy() @ r
    reference = graph.error(values)
    assert reference > 1.0
    assert cost == pytest.approx(reference, rel=1e-10)


def test_sphere_smallnoise_edges_without_information_are_an_error():
    pytest.importorskip("gtsam")
    path = gtsam_pose_graph_path("sphere_smallnoise.graph")
    with pytest.raises(DataError) as info:
        read_pose_graph(path)
    assert info.value.line == 2201 and info.value.field == "info[0,0]"
    assert "expected 29, got 8" in str(info.value)


def test_gtsam_reads_our_file_identically(gtsam, sphere, tmp_path):
    ours = sphere
    out = write_g2o(tmp_path / "sphere.g2o", ours)
    poses, factors = _gtsam_parse(gtsam, out)
    assert sorted(poses.keys()) == ours.vertex_ids.tolist()
    _assert_close(ours.positions, [poses.atPose3(k).translation() for k in range(2500)])
    _assert_close(ours.rotations, [poses.atPose3(k).rotation().matrix() for k in range(2500)])
    info = np.stack([f.noiseModel().information() for f in factors])
    _assert_close(ours.edge_information, info[:, SWAP][:, :, SWAP])
    _assert_close(ours.edge_translations, [f.measured().translation() for f in factors])


def test_gtsam_pose_graph_path_without_gtsam(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else real(name, *a)
    )
    with pytest.raises(MissingExtraError, match=r"msf_torch\[peers\]"):
        gtsam_pose_graph_path("sphere2500.txt")


def test_gtsam_pose_graph_path_unknown_name(gtsam):
    with pytest.raises(DataError, match="no such data file"):
        gtsam_pose_graph_path("no_such_graph.g2o")


# ------------------------------------------------------------------ format details


MIXED = """\
# a mixed file: comments, blank lines, both formats

VERTEX_SE3:QUAT 10 1.5 -2 0.25 0 0 0.6 0.8   # trailing comment
VERTEX3 3 0.1 0.2 0.3 0.4 -0.5 0.6
FOO_BAR 3
EDGE3 3 10 1 2 3 0.1 0.2 0.3 1 0 0 0 0 0 2 0 0 0 0 3 0 0 0 4 0 0 5 0 6
EDGE_SE3:QUAT 10 3 -1 0 0 0 0 0 2 11 0.1 0 0 0 0 12 0 0 0 0 13 0 0 0 14 0 0 15 0 16
"""


def test_mixed_formats_comments_and_skipped_tags(tmp_path):
    with pytest.warns(UserWarning, match=r"skipped 1 lines .*'FOO_BAR' x1 \(first on line 5\)"):
        graph = read_pose_graph(_write(tmp_path, MIXED))
    assert graph.has_vertices
    assert graph.vertex_ids.tolist() == [3, 10]
    assert graph.skipped == {"FOO_BAR": 1} and graph.fixed_ids == ()
    assert graph.edge_lines.tolist() == [6, 7]
    assert graph.edge_ids().tolist() == [[3, 10], [10, 3]]
    assert graph.edge_index.tolist() == [[0, 1], [1, 0]]
    # VERTEX3 roll pitch yaw -> Rz(yaw) Ry(pitch) Rx(roll)
    _assert_close(graph.rotations[0], _rz(0.6) @ _ry(-0.5) @ _rx(0.4), tol=1e-15)
    # quaternion [x y z w] = [0 0 0.6 0.8]: a turn about z by 2 atan2(0.6, 0.8)
    _assert_close(graph.rotations[1], _rz(2 * np.arctan2(0.6, 0.8)), tol=1e-15)
    assert graph.positions.tolist() == [[0.1, 0.2, 0.3], [1.5, -2.0, 0.25]]
    _assert_close(graph.edge_rotations[0], _rz(0.3) @ _ry(0.2) @ _rx(0.1), tol=1e-15)
    # a quaternion (0, 0, 0, 2) is normalised to the identity
    assert graph.edge_rotations[1].tolist() == np.eye(3).tolist()
    # EDGE3 file diag(1..6) is [rot, trans] (GTSAM) -> ours [trans, rot] = diag(4, 5, 6, 1, 2, 3)
    assert graph.edge_information[0].diagonal().tolist() == [4, 5, 6, 1, 2, 3]
    # EDGE_SE3:QUAT is already [x y z qx qy qz]: kept, the off-diagonal mirrored
    assert graph.edge_information[1].diagonal().tolist() == [11, 12, 13, 14, 15, 16]
    assert graph.edge_information[1, 0, 1] == graph.edge_information[1, 1, 0] == 0.1


def test_unknown_tags_can_be_errors(tmp_path):
    path = _write(tmp_path, MIXED)
    with pytest.raises(DataError) as info:
        read_pose_graph(path, unknown_tags="error")
    assert (info.value.line, info.value.field) == (5, "tag")
    assert "unknown tag 'FOO_BAR'" in str(info.value)
    with pytest.raises(ValueError, match="unknown_tags"):
        read_pose_graph(path, unknown_tags="warn")  # type: ignore[arg-type]


EDGE_INFO = " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


def test_unknown_tags_are_counted_in_one_warning(tmp_path):
    text = (
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3_PRIOR 0 0 0 0 0 0 0 1\nFOO_BAR 1 2 3\n"
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1{EDGE_INFO}\nFOO_BAR 4\nEDGE_SE3_PRIOR 1\nFOO_BAR\n"
    )
    path = _write(tmp_path, text)
    with pytest.warns(UserWarning) as caught:
        graph = read_pose_graph(path)
    assert len(caught) == 1
    assert str(caught[0].message) == (
        f"{path}: skipped 5 lines with tags this reader does not read: "
        "'EDGE_SE3_PRIOR' x2 (first on line 3), 'FOO_BAR' x3 (first on line 4) "
        "(tags read: VERTEX_SE3:QUAT, EDGE_SE3:QUAT, VERTEX3, EDGE3, FIX)"
    )
    assert graph.skipped == {"EDGE_SE3_PRIOR": 2, "FOO_BAR": 3} and graph.num_edges == 1


def test_edges_free_file_with_unknown_tags_is_a_data_error(tmp_path):
    text = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
    text += "EDGE_SE3_PRIOR 0 0 0 0 0 0 0 1\nFIX 0\nEDGE_SE3_PRIOR 1 0 0 0 0 0 0 1\n"
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as info:
        read_pose_graph(path)
    assert info.value.path == str(path) and info.value.line is None
    assert "no pose edges (EDGE_SE3:QUAT or EDGE3)" in info.value.problem
    assert "'EDGE_SE3_PRIOR' x2 (first on line 3)" in info.value.problem


def test_fix_records_name_the_held_vertices(tmp_path):
    text = "".join(f"VERTEX_SE3:QUAT {k} {k} 0 0 0 0 0 1\n" for k in (2, 5, 9))
    text += "FIX 9 # comment\nFIX 5 9\n"
    text += (
        f"EDGE_SE3:QUAT 2 5 1 0 0 0 0 0 1{EDGE_INFO}\nEDGE_SE3:QUAT 5 9 1 0 0 0 0 0 1{EDGE_INFO}\n"
    )
    graph = read_pose_graph(_write(tmp_path, text))
    assert graph.fixed_ids == (5, 9) and graph.fixed_rows().tolist() == [1, 2]
    assert graph.skipped == {}
    back = read_pose_graph(write_g2o(tmp_path / "back.g2o", graph))
    assert back.fixed_ids == (5, 9)
    with pytest.raises(ValueError, match=r"fixed_ids: \[4\] are not vertex ids"):
        PoseGraph(**{**graph.__dict__, "fixed_ids": (4, 5)}).check()


@pytest.mark.parametrize(
    ("fix", "line", "problem"),
    [
        ("FIX 7", 3, "FIX names vertex 7, which no vertex line defines"),
        ("FIX", 3, "FIX names no vertex id"),
        ("FIX 0 x", 3, "not a non-negative integer id: 'x'"),
    ],
)
def test_bad_fix_records(tmp_path, fix, line, problem):
    text = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
    text += f"{fix}\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1{EDGE_INFO}\n"
    with pytest.raises(DataError) as info:
        read_pose_graph(_write(tmp_path, text))
    assert (info.value.line, info.value.field) == (line, "id")
    assert problem in info.value.problem


def test_writer_creates_missing_folders(tmp_path):
    graph = _random_graph(4)
    out = write_g2o(tmp_path / "new" / "deeper" / "g.g2o", graph)
    assert out.is_file() and read_pose_graph(out).num_edges == graph.num_edges


def test_edge_only_file_chains_the_odometry(tmp_path):
    text = (
        f"EDGE3 5 6 1 0 0 0 0 1.5707963267948966{EDGE_INFO}\n"
        f"EDGE3 6 7 1 0 0 0 0 0{EDGE_INFO}\n"
        f"EDGE3 5 7 0 2 0 0 0 1.5707963267948966{EDGE_INFO}\n"
    )
    graph = read_pose_graph(_write(tmp_path, text, "odo.txt"))
    assert not graph.has_vertices
    assert graph.vertex_ids.tolist() == [5, 6, 7]
    _assert_close(graph.positions, [[0, 0, 0], [1, 0, 0], [1, 1, 0]], tol=1e-15)
    _assert_close(graph.rotations[2], _rz(np.pi / 2), tol=1e-15)


# ------------------------------------------------------------------ round trip


def _random_graph(seed: int, n: int = 12, e: int = 30, *, float32: bool = False) -> PoseGraph:
    g = torch.Generator().manual_seed(seed)

    def rotations(k: int) -> torch.Tensor:
        return quat_to_matrix(torch.randn(k, 4, generator=g, dtype=torch.float64))

    ids = torch.randperm(5 * n, generator=g)[:n].sort().values
    pairs = torch.stack(
        [torch.randperm(n, generator=g)[:2] for _ in range(e)]
    )  # distinct i, j per edge
    a = torch.randn(e, 6, 6, generator=g, dtype=torch.float64)
    info = a @ a.transpose(1, 2) + 0.1 * torch.eye(6, dtype=torch.float64)
    graph = PoseGraph(
        vertex_ids=ids,
        rotations=rotations(n),
        positions=torch.randn(n, 3, generator=g, dtype=torch.float64) * 100,
        edge_index=pairs,
        edge_rotations=rotations(e),
        edge_translations=torch.randn(e, 3, generator=g, dtype=torch.float64),
        edge_information=info * 1e3,
    )
    return graph.to(dtype=torch.float32) if float32 else graph


def _assert_same_graph(a: PoseGraph, b: PoseGraph, tol: float = 1e-12) -> None:
    assert a.vertex_ids.tolist() == b.vertex_ids.tolist()
    assert a.edge_index.tolist() == b.edge_index.tolist()
    for name in ("rotations", "positions", "edge_rotations", "edge_translations"):
        _assert_close(getattr(a, name), getattr(b, name), tol)
    _assert_close(a.edge_information, b.edge_information, tol)


def test_write_read_round_trip(tmp_path):
    graph = _random_graph(0)
    out = write_g2o(tmp_path / "g.g2o", graph)
    back = read_pose_graph(out)
    assert back.has_vertices and back.skipped == {}
    _assert_same_graph(back, graph)
    # positions, translations and information are written exactly
    assert back.positions.tolist() == graph.positions.tolist()
    assert back.edge_translations.tolist() == graph.edge_translations.tolist()
    assert back.edge_information.tolist() == graph.edge_information.tolist()


def test_round_trip_of_edge_only_file(sphere, tmp_path):
    back = read_pose_graph(write_g2o(tmp_path / "sphere.g2o", sphere))
    assert back.has_vertices
    _assert_same_graph(back, sphere)


def test_write_float32_graph(tmp_path):
    graph = _random_graph(1, float32=True)
    back = read_pose_graph(write_g2o(tmp_path / "g.g2o", graph))
    assert back.positions.dtype == torch.float64
    _assert_close(back.positions, graph.positions.double(), 1e-15)


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "g.g2o"
    target.write_text("old\n")
    bad = _random_graph(2)
    bad.positions[3, 1] = float("nan")
    with pytest.raises(ValueError, match=f"vertex {bad.vertex_ids[3].item()}: not finite"):
        write_g2o(target, bad)
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["g.g2o"]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda g: g.rotations[0].mul_(2.0), "vertex .*rotation is not a proper orthonormal"),
        (lambda g: g.edge_information[4, 0, 5].add_(1.0), r"edge 4 \(.*not symmetric"),
        (lambda g: setattr(g, "edge_index", g.edge_index + 100), "edge_index"),
        (lambda g: setattr(g, "positions", g.positions[:, :2]), "positions: shape"),
    ],
)
def test_write_rejects_bad_graphs(tmp_path, edit, message):
    graph = _random_graph(3)
    edit(graph)
    with pytest.raises(ValueError, match=message):
        write_g2o(tmp_path / "g.g2o", graph)
    assert not (tmp_path / "g.g2o").exists()


# ------------------------------------------------------------------ bad input


VERTEX = "VERTEX_SE3:QUAT {} 0 0 0 0 0 0 1\n"
EDGE = "EDGE_SE3:QUAT {} {} 1 0 0 0 0 0 1" + EDGE_INFO + "\n"


@pytest.mark.parametrize(
    ("text", "line", "field", "fragment"),
    [
        (VERTEX.format(0) + "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 abc\n", 2, "qw", "not a number: 'abc'"),
        (VERTEX.format(0) + "VERTEX_SE3:QUAT 1 0 0 nan 0 0 0 1\n", 2, "z", "not finite: 'nan'"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 1\n", 1, "qw", "expected 8, got 7"),
        ("VERTEX3 0 0 0 0 0 0 0 7\n", 1, None, "expected 7, got 8"),
        ("\n\n" + EDGE.format(0, 1).replace(" 0 1\n", " 0\n"), 3, "info[5,5]", "expected 30"),
        ("VERTEX_SE3:QUAT 1.5 0 0 0 0 0 0 1\n", 1, "id", "non-negative integer id: '1.5'"),
        ("VERTEX_SE3:QUAT -1 0 0 0 0 0 0 1\n", 1, "id", "non-negative integer id: '-1'"),
        ("VERTEX3 9223372036854775808 0 0 0 0 0 0\n", 1, "id", "integer id: '92233720"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", 1, "qw", "zero norm"),
        (VERTEX.format(0) + "# c\n" + VERTEX.format(0), 3, "id", "duplicate vertex id 0"),
        (VERTEX.format(0) + EDGE.format(0, 0), 2, "j", "edge from vertex 0 to itself"),
        (VERTEX.format(0) + VERTEX.format(1) + EDGE.format(0, 2), 3, "j", "vertex 2"),
        (VERTEX.format(4) + VERTEX.format(1) + EDGE.format(9, 1), 3, "i", "vertex 9"),
        (
            VERTEX.format(0) + VERTEX.format(1) + EDGE.format(0, 1).replace(EDGE_INFO, " 0" * 21),
            3,
            "information",
            "not positive definite",
        ),
        (
            EDGE.format(0, 1).replace(EDGE_INFO, " 1 2" + " 0" * 4 + " 1" + " 0" * 14),
            1,
            "information",
            "not positive definite",
        ),
        ("VERTEX_SE2 0 0 0 0\n", 1, "tag", "2-D pose-graph tag 'VERTEX_SE2'"),
        (VERTEX.format(0) + "EDGE2 0 1 1 0 0 1 0 1 1 0 0\n", 2, "tag", "2-D pose-graph tag"),
        ("# nothing here\n\nFIX 0\n", None, None, "no vertices or edges"),
        (EDGE.format(0, 1) + EDGE.format(2, 3), None, None, "there is no edge 1 -> 2"),
        (EDGE.format(0, 1) + EDGE.format(1, 3), None, None, "there is no edge 1 -> 2"),
    ],
)
def test_bad_input_names_file_line_and_field(tmp_path, text, line, field, fragment):
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as info:
        read_pose_graph(path)
    err = info.value
    message = str(err)
    assert err.path == str(path) and message.startswith(str(path))
    assert err.line == line and err.field == field
    if line is not None:
        assert f"{path}:{line}:" in message
    if field is not None:
        assert f"field '{field}'" in message
    assert fragment in message


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_pose_graph(tmp_path / "absent.g2o")


def test_a_2d_tag_after_3d_records_says_the_file_mixes_them(tmp_path):
    """Was the advice to read the file as a 2-D graph."""
    path = tmp_path / "mixed.g2o"
    path.write_text(VERTEX.format(0) + "VERTEX_SE2 1 0 0 0\n")
    with pytest.raises(DataError, match=r"mixes it with 3-D records \(the first on line 1\)"):
        read_pose_graph(path)
