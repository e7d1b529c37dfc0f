"""2-D pose graphs (g2o VERTEX_SE2 / EDGE_SE2, TORO VERTEX2 / EDGE2, ODOMETRY, and the
landmark records VERTEX_XY / BR / LANDMARK): bad input, format details, landmark placement,
round trips and GTSAM's ``load2D`` initial values. The solver is tested in
``tests/backend/test_posegraph2d.py``."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.backend.posegraph2d import pose_graph_2d_problem
from msf_torch.io import (
    GTSAM_LANDMARK2_FILES,
    DataError,
    PoseGraph2D,
    gtsam_pose_graph_path,
    is_pose_graph_2d,
    read_pose_graph_2d,
    write_g2o_2d,
)

G2O_INFO = " 1 0 0 1 0 1"
"""Identity information as EDGE_SE2 writes it (upper triangle, row by row)."""
TORO_INFO = " 1 0 1 1 0 0"
"""Identity information in TORO's order (I_xx I_xy I_yy I_tt I_xt I_yt)."""

VERTEX = "VERTEX_SE2 {} 0 0 0\n"
EDGE = "EDGE_SE2 {} {} 1 0 0" + G2O_INFO + "\n"
VERTEX2 = "VERTEX2 {} 0 0 0\n"
EDGE2 = "EDGE2 {} {} 1 0 0" + TORO_INFO + "\n"
TWO = VERTEX.format(0) + VERTEX.format(1)
COV = " 0.01 0 0 0.01 0 0.0025"
"""A diagonal ODOMETRY covariance (m^2, m^2, rad^2): information diag(100, 100, 400)."""

PLACED_BY_SIGHTINGS = (
    "VERTEX2 0 1 2 0.5\n"
    "VERTEX2 1 3 1 -0.5\n"
    f"EDGE2 0 1 1 0 0{TORO_INFO}\n"
    "BR 1 4 0.3 2 0.1 0.1\n"  # landmark 4: its first sighting places it
    "BR 0 4 0.3 2 0.1 0.1\n"
    "BR 0 6 0.3 2 0.1 0.1\n"
    "VERTEX_XY 6 -1 -2\n"  # landmark 6: VERTEX_XY wins, even after a sighting
    "BR 1 8 -2 1.5 0.1 0.1\n"
    "BR 0 8 1 2 0.1 0.1\n"
    "VERTEX_XY 2 5 5\n"  # landmark 2: never seen
)
"""Vertices and landmarks placed from VERTEX_XY lines and first sightings."""
SIGHTING_BEFORE_EDGE = (
    f"ODOMETRY 0 1 1 0 0.5{COV}\n"
    "BR 2 5 0.25 3 0.1 0.2\n"  # vertex 2 not placed yet: it goes to the origin
    f"ODOMETRY 1 2 1 0 0.5{COV}\n"  # and stays there
    "BR 1 5 -0.5 2 0.1 0.2\n"
    "LANDMARK 2 7 1 2 0.2 0 0.2\n"
)
"""An edge-only file where a sighting comes before the edge that would place its vertex."""


def _write(tmp_path: Path, text: str, name: str = "graph.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("text", "line", "field", "fragment"),
    [
        ("VERTEX_SE2 0 0 0\n", 1, "theta", "expected 4, got 3"),
        ("VERTEX2 0 0 0 0 7\n", 1, None, "expected 4, got 5"),
        (TWO + "\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", 4, "info[2,2]", "expected 11, got 10"),
        (TWO + "EDGE2 0 1 1 0 0 1 0 1 1\n", 3, "inf_fr", "expected 11, got 9"),
        ("VERTEX_SE2 0 0 abc 0\n", 1, "y", "not a number: 'abc'"),
        ("VERTEX2 0 0 0 inf\n", 1, "theta", "not finite: 'inf'"),
        (TWO + "EDGE_SE2 0 1 1 0 0 1 0 nan 1 0 1\n", 3, "info[0,2]", "not finite: 'nan'"),
        (TWO + "EDGE2 0 1 1 0 0 1 0 1 1e400 0 0\n", 3, "inf_rr", "not finite: '1e400'"),
        ("VERTEX_SE2 -1 0 0 0\n", 1, "id", "non-negative integer id: '-1'"),
        ("VERTEX_SE2 1.5 0 0 0\n", 1, "id", "non-negative integer id: '1.5'"),
        (VERTEX.format(0) + "EDGE_SE2 0 x 1 0 0" + G2O_INFO + "\n", 2, "j", "integer id: 'x'"),
        (VERTEX.format(0) + "# c\n" + VERTEX2.format(0), 3, "id", "duplicate vertex id 0"),
        (TWO + EDGE.format(1, 1), 3, "j", "edge from vertex 1 to itself"),
        # TORO's identity written as EDGE_SE2: [[1, 0, 1], [0, 1, 0], [1, 0, 0]], indefinite
        (TWO + "EDGE_SE2 0 1 1 0 0" + TORO_INFO + "\n", 3, "information", "not positive def"),
        (TWO + "EDGE2 0 1 1 0 0 1 0 1 0 0 0\n", 3, "information", "not positive definite"),
        (TWO + EDGE.format(0, 2), 3, "j", "vertex 2, which no vertex line defines"),
        (TWO + EDGE.format(0, 1) + EDGE.format(7, 1), 4, "i", "vertex 7, which no vertex"),
        (TWO + "FIX 5\n" + EDGE.format(0, 1), 3, "id", "FIX names vertex 5, which no vertex"),
        (EDGE.format(0, 1) + "FIX 1 2\n", 2, "id", "FIX names vertex 2, which no edge names"),
        (TWO + "FIX\n" + EDGE.format(0, 1), 3, "id", "FIX names no vertex id"),
        (VERTEX.format(0) + "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n", 2, "tag", "3-D pose-graph tag"),
        ("EDGE3 0 1" + " 0" * 27 + "\n", 1, "tag", "read 3-D graphs with msf_torch"),
        (
            "# 2-D\n" + TWO + "EDGE3 0 1" + " 0" * 27 + "\n",
            4,
            "tag",
            "2-D records (the first on line 2)",
        ),
        (EDGE.format(0, 1) + "VERTEX3 0" + " 0" * 6 + "\n", 2, "tag", "keep one kind per file"),
        (TWO + "EQUIV 0 1\nLANDMARK2 0 1 1 1 1 0 1\n", None, None, "no 2-D pose edges"),
        ("# only a comment\n\n", None, None, "no vertices or edges"),
        ("", None, None, "no vertices or edges"),
        ("".join(f"EDGE2 {i} {i + 1} 1e308 0 0{TORO_INFO}\n" for i in range(2)), 2, "x", "overf"),
        # landmark records
        (TWO + "VERTEX_XY 0 1\n", 3, "y", "expected 3, got 2"),
        (TWO + "BR 0 1 0.5 2 0.1\n", 3, "range_sigma", "expected 6, got 5"),
        (TWO + "LANDMARK 0 1 1 1 0.1 0 0.1 9\n", 3, None, "expected 7, got 8"),
        (TWO + "ODOMETRY 0 1 1 0 0 1 0 0 1 0\n", 3, "cov[2,2]", "expected 11, got 10"),
        (TWO + "VERTEX_XY 0 abc 1\n", 3, "x", "not a number: 'abc'"),
        (TWO + "BR 0 1 nan 2 0.1 0.1\n", 3, "bearing", "not finite: 'nan'"),
        (TWO + "LANDMARK 0 1 1 inf 0.1 0 0.1\n", 3, "y", "not finite: 'inf'"),
        (TWO + "BR 0 -1 0.5 2 0.1 0.1\n", 3, "l", "non-negative integer id: '-1'"),
        (TWO + "LANDMARK 0 1 0 -0 0.1 0 0.1\n", 3, "x", "has no bearing and range"),
        (TWO + "LANDMARK 0 1 1.5e308 1.5e308 1 0 1\n", 3, "x", "overflowing distance"),
        (TWO + "BR 0 1 0.5 0 0.1 0.1\n", 3, "range", "range must be positive, got 0.0"),
        (TWO + "BR 0 1 0.5 -2 0.1 0.1\n", 3, "range", "range must be positive, got -2.0"),
        (TWO + "BR 0 1 0.5 2 0 0.1\n", 3, "bearing_sigma", "standard deviation 0.0 this"),
        (TWO + "BR 0 1 0.5 2 0.1 -0.1\n", 3, "range_sigma", "standard deviation -0.1 this"),
        (TWO + "BR 0 1 0.5 2 1e-200 0.1\n", 3, "bearing_sigma", "1/sigma^2 is not finite"),
        (TWO + "LANDMARK 0 1 1 1 0 0 0\n", 3, "cov[0,0]", "standard deviation 0.0 this"),
        (TWO + "LANDMARK 0 1 1 1 -0.5 0 -0.5\n", 3, "cov[0,0]", "is not positive"),
        (
            TWO + "VERTEX_XY 3 0 0\n# c\nVERTEX_XY 3 1 1\n",
            5,
            "id",
            "duplicate landmark id 3 (first defined on line 3)",
        ),
        (TWO + EDGE.format(0, 1) + "BR 5 1 0.5 2 0.1 0.1\n", 4, "i", "vertex 5, which no vertex"),
        (
            VERTEX.format(0) + VERTEX.format(2) + "LANDMARK 1 4 1 1 0.1 0 0.1\n",
            3,
            "i",
            "sighting names vertex 1, which no vertex line defines",
        ),
        (TWO + "ODOMETRY 0 1 1 0 0 1 0 0 1 0 -1\n", 3, "covariance", "covariance matrix is not"),
        (TWO + "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1e-320\n", 3, "covariance", "singular to invert"),
    ],
)
def test_bad_input_names_file_line_and_field(tmp_path, text, line, field, fragment):
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as info:
        read_pose_graph_2d(path)
    err = info.value
    message = str(err)
    assert err.path == str(path) and message.startswith(str(path))
    assert (err.line, err.field) == (line, field)
    if line is not None:
        assert f"{path}:{line}:" in message
    if field is not None:
        assert f"field '{field}'" in message
    assert fragment in message


def test_positive_definite_means_cholesky_succeeds(tmp_path):
    """Probing the fuzz oracle's check finds: the smallest eigenvalue (``eigvalsh``) of an
    exactly singular information was a rounding error above 0, so it was read (and its
    Cholesky fails); that of diag(1e308, 1e-308, 1) was 0, so it was refused."""
    singular = TWO + "EDGE_SE2 0 1 1 0 0 1e-16 0 0 1 -3 9\n"  # [[1, -3], [-3, 9]] block
    with pytest.raises(DataError, match="not positive definite") as info:
        read_pose_graph_2d(_write(tmp_path, singular))
    assert (info.value.line, info.value.field) == (3, "information")
    graph = read_pose_graph_2d(_write(tmp_path, TWO + "EDGE2 0 1 1 0 0 1e308 0 1e-308 1 0 0\n"))
    assert graph.edge_information[0].diagonal().tolist() == [1e308, 1e-308, 1.0]
    assert int(torch.linalg.cholesky_ex(graph.edge_information).info) == 0


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_pose_graph_2d(tmp_path / "absent.g2o")
    with pytest.raises(DataError, match="no such file"):
        is_pose_graph_2d(tmp_path / "absent.g2o")


def test_skipped_tags_are_counted_in_one_warning(tmp_path):
    text = TWO + "EQUIV 1 0\nLANDMARK2 0 1 1 1 1 0 1\n" + EDGE.format(0, 1) + "EQUIV 0 1\n"
    path = _write(tmp_path, text)
    with pytest.warns(UserWarning) as caught:
        graph = read_pose_graph_2d(path)
    assert len(caught) == 1
    assert str(caught[0].message) == (
        f"{path}: skipped 3 lines with tags this reader does not read: "
        "'EQUIV' x2 (first on line 3), 'LANDMARK2' x1 (first on line 4) "
        "(tags read: VERTEX_SE2, EDGE_SE2, VERTEX2, EDGE2, ODOMETRY, VERTEX_XY, LANDMARK, BR, FIX)"
    )
    assert graph.skipped == {"EQUIV": 2, "LANDMARK2": 1} and graph.num_edges == 1
    assert graph.edge_lines.tolist() == [5]
    with pytest.raises(DataError) as info:
        read_pose_graph_2d(path, unknown_tags="error")
    assert (info.value.line, info.value.field) == (3, "tag")
    assert "unknown tag 'EQUIV'" in info.value.problem
    with pytest.raises(ValueError, match="unknown_tags"):
        read_pose_graph_2d(path, unknown_tags="warn")  # type: ignore[arg-type]


# ------------------------------------------------------------------ format details


def test_toro_and_g2o_information_orders_give_the_same_matrix(tmp_path):
    """One edge, one full information matrix: EDGE_SE2 gives its upper triangle row by row,
    EDGE2 in TORO's order (xx xy yy tt xt yt); both read to the same [x, y, theta] matrix."""
    info = np.array([[4.0, 0.5, -0.25], [0.5, 3.0, 0.125], [-0.25, 0.125, 2.0]])
    g2o = info[np.triu_indices(3)]
    toro = info[[0, 0, 1, 2, 0, 1], [0, 1, 1, 2, 2, 2]]
    pose = "0.5 -0.25 0.75"
    g2o_graph = read_pose_graph_2d(
        _write(tmp_path, f"EDGE_SE2 3 8 {pose} " + " ".join(map(repr, g2o.tolist())) + "\n")
    )
    toro_graph = read_pose_graph_2d(
        _write(tmp_path, f"EDGE2 3 8 {pose} " + " ".join(map(repr, toro.tolist())) + "\n", "t")
    )
    for graph in (g2o_graph, toro_graph):
        assert graph.edge_information.tolist() == [info.tolist()]
        assert graph.edge_translations.tolist() == [[0.5, -0.25]]
        assert graph.edge_headings.tolist() == [0.75]
        assert graph.vertex_ids.tolist() == [3, 8] and not graph.has_vertices


def test_mixed_tags_comments_and_vertex_order(tmp_path):
    text = (
        "# both formats in one file\n"
        "VERTEX2 7 1.5 -2 0.25   # trailing comment\n"
        "VERTEX_SE2 2 0.1 0.2 -3.5\n"
        "\n"
        f"EDGE_SE2 7 2 1 2 3{G2O_INFO}\n"
        f"EDGE2 2 7 -1 0 0.5{TORO_INFO}\n"
        "FIX 7 2\nFIX 7\n"
    )
    graph = read_pose_graph_2d(_write(tmp_path, text))
    assert graph.has_vertices and graph.skipped == {}
    assert graph.vertex_ids.tolist() == [2, 7]
    assert graph.positions.tolist() == [[0.1, 0.2], [1.5, -2.0]]
    assert graph.headings.tolist() == [-3.5, 0.25]  # vertex headings are kept as written
    assert graph.edge_index.tolist() == [[1, 0], [0, 1]]
    assert graph.edge_lines.tolist() == [5, 6]
    assert graph.edge_headings.tolist() == [3.0, 0.5]
    assert graph.edge_information.tolist() == [np.eye(3).tolist()] * 2
    assert graph.fixed_ids == (2, 7) and graph.fixed_rows().tolist() == [0, 1]


def test_edge_only_file_chains_from_the_first_vertex(tmp_path):
    half = np.pi / 2
    text = (
        f"EDGE2 5 6 1 0 {half!r}{TORO_INFO}\n"
        f"EDGE2 6 7 1 0 {half!r}{TORO_INFO}\n"
        f"EDGE2 5 7 9 9 0{TORO_INFO}\n"  # both placed: no effect on the initial poses
        f"EDGE2 9 8 2 0 3{TORO_INFO}\n"  # a second component: 9 at the origin, 8 from it
    )
    graph = read_pose_graph_2d(_write(tmp_path, text, "odo.graph"))
    assert not graph.has_vertices
    assert graph.vertex_ids.tolist() == [5, 6, 7, 8, 9]
    np.testing.assert_allclose(
        graph.positions.numpy(), [[0, 0], [1, 0], [1, 1], [2, 0], [0, 0]], atol=1e-15
    )
    np.testing.assert_allclose(graph.headings.numpy(), [0, half, np.pi, 3, 0], atol=1e-15)


def test_landmark_lines_read_as_gtsam_load2d_reads_them(tmp_path):
    """LANDMARK x y: bearing atan2(y, x), range |(x, y)|; equal variances (within 1e-4) give
    sigmas sqrt(v / 10) rad and sqrt(v) m, unequal ones 1 and 1 with one warning."""
    text = (
        TWO
        + EDGE.format(0, 1)
        + "LANDMARK 0 3 3 4 0.4 0 0.4\n"
        + "LANDMARK 1 3 0 -2 0.4 0 0.5\n"  # unequal: sigmas 1, 1
        + "LANDMARK 0 9 1 0 0.4 0.3 0.40005\n"  # equal within 1e-4
        + "LANDMARK 1 9 -1 0 1 0 2\n"
    )
    path = _write(tmp_path, text)
    with pytest.warns(UserWarning) as caught:
        graph = read_pose_graph_2d(path)
    assert [str(w.message) for w in caught] == [
        f"{path}: 2 LANDMARK lines (first on line 5) give unequal x and y variances; read "
        "with bearing and range sigma 1, as GTSAM's load2D reads them"
    ]
    assert graph.landmark_ids.tolist() == [3, 9]
    assert graph.observation_index.tolist() == [[0, 0], [1, 0], [0, 1], [1, 1]]
    assert graph.observation_lines.tolist() == [4, 5, 6, 7]
    assert graph.observation_bearings.tolist() == [math.atan2(4, 3), -math.pi / 2, 0.0, math.pi]
    assert graph.observation_ranges.tolist() == [5.0, 2.0, 1.0, 1.0]
    equal = [math.sqrt(0.4 / 10.0), math.sqrt(0.4)]
    assert graph.observation_sigmas.tolist() == [equal, [1.0, 1.0], equal, [1.0, 1.0]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # equal variances only: no warning
        read_pose_graph_2d(_write(tmp_path, TWO + "LANDMARK 0 3 3 4 0.4 0 0.4\n", "eq.g2o"))


def test_landmarks_are_placed_by_vertex_xy_else_their_first_sighting(tmp_path):
    graph = read_pose_graph_2d(_write(tmp_path, PLACED_BY_SIGHTINGS, "lm.graph"))
    assert graph.landmark_ids.tolist() == [2, 4, 6, 8]
    assert graph.observation_index.tolist() == [[1, 1], [0, 1], [0, 2], [1, 3], [0, 3]]
    assert graph.observation_lines.tolist() == [4, 5, 6, 8, 9]

    def seen(x: float, y: float, heading: float, bearing: float, distance: float) -> list[float]:
        angle = heading + bearing
        return [x + distance * math.cos(angle), y + distance * math.sin(angle)]

    expected = [[5.0, 5.0], seen(3, 1, -0.5, 0.3, 2), [-1.0, -2.0], seen(3, 1, -0.5, -2, 1.5)]
    np.testing.assert_allclose(graph.landmark_positions.numpy(), expected, rtol=0, atol=1e-15)


def test_edge_only_sighting_before_the_placing_edge_puts_its_vertex_at_the_origin(tmp_path):
    """load2D's rule: a sighting's vertex not yet placed goes to the origin, and a later edge
    into it does not move it."""
    graph = read_pose_graph_2d(_write(tmp_path, SIGHTING_BEFORE_EDGE, "odo.txt"))
    assert not graph.has_vertices and graph.vertex_ids.tolist() == [0, 1, 2]
    assert graph.positions.tolist() == [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]
    assert graph.headings.tolist() == [0.0, 0.5, 0.0]
    assert graph.landmark_ids.tolist() == [5, 7]
    np.testing.assert_allclose(
        graph.landmark_positions.numpy(),
        [[3 * math.cos(0.25), 3 * math.sin(0.25)], [1.0, 2.0]],
        rtol=0,
        atol=1e-15,
    )
    # ODOMETRY gives the covariance: stored as its inverse
    np.testing.assert_allclose(
        graph.edge_information.numpy(), [np.diag([100.0, 100.0, 400.0])] * 2, rtol=1e-13
    )


# ------------------------------------------------------------------ round trip


def _random_graph(seed: int, n: int = 10, e: int = 25) -> PoseGraph2D:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(e, 3, 3, generator=g, dtype=torch.float64)
    info = a @ a.mT + 0.1 * torch.eye(3, dtype=torch.float64)
    ids = torch.randperm(5 * n, generator=g)[:n].sort().values
    return PoseGraph2D(
        vertex_ids=ids,
        positions=torch.randn(n, 2, generator=g, dtype=torch.float64) * 100,
        headings=(torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2 * torch.pi,
        edge_index=torch.stack([torch.randperm(n, generator=g)[:2] for _ in range(e)]),
        edge_translations=torch.randn(e, 2, generator=g, dtype=torch.float64),
        edge_headings=torch.randn(e, generator=g, dtype=torch.float64),
        edge_information=info * 1e3,
        fixed_ids=(int(ids[0]), int(ids[3])),
    )


def _assert_same_graph(a: PoseGraph2D, b: PoseGraph2D) -> None:
    for name in (
        "vertex_ids",
        "positions",
        "headings",
        "edge_index",
        "edge_translations",
        "edge_headings",
        "edge_information",
        "landmark_ids",
        "landmark_positions",
        "observation_index",
        "observation_bearings",
        "observation_ranges",
        "observation_sigmas",
    ):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.fixed_ids == b.fixed_ids


def test_write_read_round_trip_is_exact(tmp_path):
    graph = _random_graph(0)
    out = write_g2o_2d(tmp_path / "new" / "g.g2o", graph)
    back = read_pose_graph_2d(out)
    assert back.has_vertices and back.skipped == {} and back.source == str(out)
    _assert_same_graph(back, graph)
    assert back.fixed_ids == graph.fixed_ids and len(back.fixed_ids) == 2
    assert write_g2o_2d(tmp_path / "again.g2o", back).read_text() == out.read_text()


def _with_landmarks(graph: PoseGraph2D, seed: int, m: int = 6, o: int = 20) -> PoseGraph2D:
    """``graph`` with m landmarks (one never seen) and o sightings of the others."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(graph.num_vertices, (o,), generator=g)
    return dataclasses.replace(
        graph,
        landmark_ids=torch.randperm(4 * m, generator=g)[:m].sort().values,
        landmark_positions=torch.randn(m, 2, generator=g, dtype=torch.float64) * 50,
        observation_index=torch.stack((rows, torch.randint(m - 1, (o,), generator=g)), 1),
        observation_bearings=(torch.rand(o, generator=g, dtype=torch.float64) - 0.5) * 6.28,
        observation_ranges=torch.rand(o, generator=g, dtype=torch.float64) * 30 + 1e-3,
        observation_sigmas=torch.rand(o, 2, generator=g, dtype=torch.float64) + 1e-3,
    )


def test_round_trip_with_landmarks_is_exact(tmp_path):
    graph = _with_landmarks(_random_graph(1), seed=1)
    out = write_g2o_2d(tmp_path / "lm.g2o", graph)
    text = out.read_text()
    assert text.count("VERTEX_XY ") == 6 and text.count("BR ") == 20
    back = read_pose_graph_2d(out)
    _assert_same_graph(back, graph)
    assert back.observation_lines.tolist() == list(range(44, 64))  # after 10 + 2 + 25 + 6
    assert write_g2o_2d(tmp_path / "again.g2o", back).read_bytes() == out.read_bytes()


@pytest.mark.parametrize("text", [SIGHTING_BEFORE_EDGE, PLACED_BY_SIGHTINGS])
def test_round_trip_of_landmark_records(tmp_path, text):
    """ODOMETRY, LANDMARK and TORO lines come back as EDGE_SE2 and BR lines: the same graph,
    and the same file when written again."""
    graph = read_pose_graph_2d(_write(tmp_path, text, "in.txt"))
    out = write_g2o_2d(tmp_path / "first.g2o", graph)
    back = read_pose_graph_2d(out)
    assert back.has_vertices
    _assert_same_graph(back, graph)
    assert write_g2o_2d(tmp_path / "second.g2o", back).read_bytes() == out.read_bytes()


def test_round_trip_of_an_edge_only_file(tmp_path):
    text = "".join(f"EDGE2 {k} {k + 1} 0.3 0.1 0.7{TORO_INFO}\n" for k in range(6))
    text += f"EDGE_SE2 0 6 0.1 0.2 0.3{G2O_INFO}\nFIX 0\n"
    graph = read_pose_graph_2d(_write(tmp_path, text, "odo.graph"))
    assert not graph.has_vertices
    back = read_pose_graph_2d(write_g2o_2d(tmp_path / "odo.g2o", graph))
    assert back.has_vertices and back.fixed_ids == (0,)
    _assert_same_graph(back, graph)


def test_is_pose_graph_2d(tmp_path):
    assert is_pose_graph_2d(_write(tmp_path, "# c\nFIX 0\n" + EDGE.format(0, 1), "a.g2o"))
    assert is_pose_graph_2d(_write(tmp_path, "EQUIV 1 0\n" + VERTEX2.format(0), "b.graph"))
    three = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n" + VERTEX.format(1)  # the first pose tag decides
    assert not is_pose_graph_2d(_write(tmp_path, three, "c.g2o"))
    assert not is_pose_graph_2d(_write(tmp_path, "EDGE3 0 1" + " 0" * 27 + "\n", "d.graph"))
    assert not is_pose_graph_2d(_write(tmp_path, "# no tags\nFIX 0\nEQUIV 1 0\n", "e.g2o"))
    assert not is_pose_graph_2d(_write(tmp_path, "", "f.g2o"))


# ------------------------------------------------------------------ GTSAM as the reference


def test_edge_only_initial_poses_equal_gtsam_load2d():
    """victoriaPark_reduced_1k.g2o has EDGE_SE2 and LANDMARK2 lines, no vertices: our chained
    initial poses are GTSAM's ``load2D`` initial Values."""
    gtsam = pytest.importorskip("gtsam")
    path = gtsam_pose_graph_path("victoriaPark_reduced_1k.g2o")
    with pytest.warns(UserWarning, match="'LANDMARK2' x606"):
        graph = read_pose_graph_2d(path)
    assert not graph.has_vertices and graph.num_edges == 999
    _, initial = gtsam.load2D(str(path), noiseFormat=gtsam.NoiseFormat.NoiseFormatG2O)
    poses = gtsam.utilities.allPose2s(initial)
    keys = sorted(poses.keys())
    assert keys == graph.vertex_ids.tolist()
    expected = np.array([[poses.atPose2(k).x(), poses.atPose2(k).y()] for k in keys])
    headings = np.array([poses.atPose2(k).theta() for k in keys])
    # 999 compositions over ~90 m: rounding differences stay below 1e-11 m and rad
    np.testing.assert_allclose(graph.positions.numpy(), expected, rtol=0, atol=1e-11)
    np.testing.assert_allclose(graph.headings.numpy(), headings, rtol=0, atol=1e-11)


def _gtsam_initial(gtsam, graph: PoseGraph2D, initial) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM's initial Values as our arrays: poses (N, 3) by vertex id, landmarks (L, 2) by
    ``L(id)``; also checks that Values holds nothing else."""
    poses = gtsam.utilities.allPose2s(initial)
    assert sorted(poses.keys()) == graph.vertex_ids.tolist()
    assert initial.size() == graph.num_vertices + graph.num_landmarks
    pose = [poses.atPose2(k) for k in graph.vertex_ids.tolist()]
    points = [initial.atPoint2(gtsam.symbol("l", k)) for k in graph.landmark_ids.tolist()]
    return (
        np.array([[p.x(), p.y(), p.theta()] for p in pose]),
        np.array(points, dtype=np.float64).reshape(-1, 2),
    )


def _assert_same_initial(graph: PoseGraph2D, poses: np.ndarray, points: np.ndarray, atol: float):
    np.testing.assert_allclose(graph.positions.numpy(), poses[:, 0:2], rtol=0, atol=atol)
    turn = np.angle(np.exp(1j * (graph.headings.numpy() - poses[:, 2])))
    assert np.abs(turn).max(initial=0.0) <= atol
    np.testing.assert_allclose(graph.landmark_positions.numpy(), points, rtol=0, atol=atol)


@pytest.mark.parametrize("name", GTSAM_LANDMARK2_FILES)
def test_landmark_files_equal_gtsam_load2d(name):
    """example.graph (VERTEX2, EDGE2, BR) and victoria_park.txt (ODOMETRY, LANDMARK, no
    vertices): the same poses, landmark initial values, factor count and initial cost as
    GTSAM's ``load2D`` with its default noise format."""
    gtsam = pytest.importorskip("gtsam")
    path = gtsam_pose_graph_path(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # both files are read without skipping or warning
        graph = read_pose_graph_2d(path)
    factors, initial = gtsam.load2D(str(path))
    assert graph.num_landmarks > 0 and graph.num_observations > 0
    assert factors.size() == graph.num_edges + graph.num_observations
    poses, points = _gtsam_initial(gtsam, graph, initial)
    _assert_same_initial(graph, poses, points, atol=1e-9)
    problem = pose_graph_2d_problem(graph)
    ours = float(problem.cost(problem.values)[0])
    assert ours == pytest.approx(factors.error(initial), rel=1e-12)


@pytest.mark.parametrize("text", [SIGHTING_BEFORE_EDGE, PLACED_BY_SIGHTINGS])
def test_landmark_placement_equals_gtsam_load2d(tmp_path, text):
    gtsam = pytest.importorskip("gtsam")
    path = _write(tmp_path, text, "small.txt")
    graph = read_pose_graph_2d(path)
    factors, initial = gtsam.load2D(str(path))
    assert factors.size() == graph.num_edges + graph.num_observations
    _assert_same_initial(graph, *_gtsam_initial(gtsam, graph, initial), atol=1e-15)
    problem = pose_graph_2d_problem(graph)
    assert float(problem.cost(problem.values)[0]) == pytest.approx(
        factors.error(initial), rel=1e-12
    )
