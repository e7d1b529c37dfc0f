"""``msf posegraph`` end to end: GTSAM's LM on the same file as the reference."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msf_torch.cli import main
from msf_torch.io import gtsam_pose_graph_path, read_pose_graph, read_pose_graph_2d


@pytest.fixture(scope="module")
def gtsam():
    return pytest.importorskip("gtsam")


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_posegraph_matches_gtsam_and_writes_g2o(gtsam, tmp_path, capsys):
    path = str(gtsam_pose_graph_path("pose3example.txt"))
    out = tmp_path / "solved.g2o"
    args = ["posegraph", path, "--out", str(out), "--tolerance", "1e-12", "--max-iterations", "200"]
    assert main(args) == 0
    summary = _last_json(capsys)

    factors, initial = gtsam.readG2o(path, True)
    first = int(read_pose_graph(path).vertex_ids[0])
    factors.add(gtsam.NonlinearEqualityPose3(first, initial.atPose3(first)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    solved = gtsam.LevenbergMarquardtOptimizer(factors, initial, params).optimize()

    assert (summary["poses"], summary["edges"]) == (5, 6)
    assert summary["status"] == "converged" and summary["iterations"] > 0
    assert summary["initial_cost"] == pytest.approx(factors.error(initial), rel=1e-10)
    assert summary["final_cost"] == pytest.approx(factors.error(solved), rel=1e-6)
    assert summary["seconds"] > 0 and summary["out"] == str(out)
    written = read_pose_graph(out)
    positions = np.stack([solved.atPose3(int(i)).translation() for i in written.vertex_ids])
    np.testing.assert_allclose(written.positions.numpy(), positions, atol=1e-6)


def test_posegraph_named_file_and_robust_kernel(gtsam, capsys):
    assert main(["posegraph", "pose3example-grid.txt", "--robust", "cauchy:1.5"]) == 0
    summary = _last_json(capsys)
    assert summary["robust"] == ["cauchy", 1.5]
    assert summary["final_cost"] < summary["initial_cost"]
    assert "out" not in summary


def test_posegraph_plot(gtsam, tmp_path, capsys):
    figure = tmp_path / "figs" / "grid.png"
    assert main(["posegraph", "pose3example-grid.txt", "--plot", str(figure)]) == 0
    summary = _last_json(capsys)
    assert summary["plot"] == str(figure)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 20_000
    assert sorted(p.name for p in figure.parent.iterdir()) == ["grid.png"]


def test_posegraph_bad_input(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["posegraph", "graph.g2o", "--robust", "l1"])
    assert exit_info.value.code == 2
    assert "unknown kernel 'l1'" in capsys.readouterr().err
    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1\n")
    assert main(["posegraph", str(bad)]) == 2
    assert "bad.g2o" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--max-iterations", "0", "expected an integer >= 1, got '0'"),
        ("--max-iterations", "-3", "expected an integer >= 1, got '-3'"),
        ("--tolerance", "-1", "expected a finite number >= 0, got '-1'"),
        ("--tolerance", "nan", "expected a finite number >= 0, got 'nan'"),
    ],
)
def test_posegraph_bad_solver_options_are_errors(capsys, option, value, message):
    """Were accepted: 0 or -3 iterations reported 'max_iterations' with the input unsolved,
    a negative or NaN tolerance ran to the iteration limit."""
    with pytest.raises(SystemExit) as exit_info:
        main(["posegraph", "pose3example.txt", option, value])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}: {message}" in err


def test_posegraph_2d_file_solves_as_gtsam_and_writes_g2o_and_a_top_view(gtsam, tmp_path, capsys):
    """A planar graph (TORO EDGE2 with TORO's information order) is told from a 3-D one; the
    optimum is GTSAM's, the written g2o reads back, the figure has the top view and costs."""
    out, figure = tmp_path / "w100.g2o", tmp_path / "w100.png"
    args = ["posegraph", "w100", "--out", str(out), "--plot", str(figure), "--tolerance", "1e-12"]
    assert main(args) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert "msf posegraph: warning:" in captured.err and "'EQUIV' x40" in captured.err

    path = str(gtsam_pose_graph_path("w100.graph"))
    factors, initial = gtsam.load2D(path, noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    factors.add(gtsam.NonlinearEqualityPose2(0, initial.atPose2(0)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    solved = gtsam.LevenbergMarquardtOptimizer(factors, initial, params).optimize()

    assert summary["dimension"] == 2 and (summary["poses"], summary["edges"]) == (100, 300)
    assert summary["initial_cost"] == pytest.approx(factors.error(initial), rel=1e-12)
    assert summary["final_cost"] == pytest.approx(factors.error(solved), rel=1e-9)
    written = read_pose_graph_2d(out)
    positions = np.stack([[solved.atPose2(i).x(), solved.atPose2(i).y()] for i in range(100)])
    np.testing.assert_allclose(written.positions.numpy(), positions, atol=1e-6)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 20_000


def test_posegraph_landmark_file_solves_as_gtsam_and_writes_its_landmarks(gtsam, tmp_path, capsys):
    """GTSAM's example.graph (TORO poses and edges, BR bearing-range sightings of 24
    landmarks): the JSON counts them, the optimum and its landmarks are GTSAM's LM's, the
    written g2o (VERTEX_XY and BR lines) reads back with the solved landmarks and is read by
    GTSAM's load2D as the same problem, and the figure draws them."""
    out, figure = tmp_path / "example.g2o", tmp_path / "example.png"
    args = ["posegraph", "example", "--out", str(out), "--plot", str(figure)]
    assert main([*args, "--tolerance", "1e-12"]) == 0
    summary = _last_json(capsys)
    path = str(gtsam_pose_graph_path("example.graph"))
    factors, initial = gtsam.load2D(path)
    held = gtsam.NonlinearFactorGraph(factors)
    held.add(gtsam.NonlinearEqualityPose2(0, initial.atPose2(0)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    solved = gtsam.LevenbergMarquardtOptimizer(held, initial, params).optimize()

    assert (summary["poses"], summary["edges"]) == (95, 94)
    assert (summary["landmarks"], summary["sightings"]) == (24, 422)
    assert summary["initial_cost"] == pytest.approx(factors.error(initial), rel=1e-12)
    assert summary["final_cost"] == pytest.approx(factors.error(solved), rel=1e-9)
    written = read_pose_graph_2d(out)
    ids = written.landmark_ids.tolist()
    expected = np.stack([solved.atPoint2(gtsam.symbol("l", i)) for i in ids])
    np.testing.assert_allclose(written.landmark_positions.numpy(), expected, atol=1e-6)
    again, values = gtsam.load2D(str(out))
    assert again.size() == factors.size() and values.size() == initial.size()
    assert again.error(values) == pytest.approx(summary["final_cost"], rel=1e-9)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 20_000


@pytest.mark.parametrize(
    "text", ["", "# only a comment\n", "vertex_se2 0 0 0 0\nedge_se2 0 1 1 0 0 1 0 0 1 0 1\n"]
)
def test_posegraph_file_without_pose_tags_names_both_kinds(tmp_path, capsys, text):
    """Was the 3-D reader's message, listing only the 3-D tags."""
    path = tmp_path / "graph.g2o"
    path.write_text(text)
    assert main(["posegraph", str(path)]) == 2
    err = capsys.readouterr().err
    assert "neither 2-D" in err and "VERTEX_SE2" in err and "VERTEX_SE3:QUAT" in err


def test_posegraph_output_paths_that_are_folders_are_refused_before_solving(tmp_path, capsys):
    """Was an IsADirectoryError traceback after the solve."""
    folder = tmp_path / "out.g2o"
    folder.mkdir()
    for option in ("--out", "--plot"):
        assert main(["posegraph", "w100", option, str(folder)]) == 2
        err = capsys.readouterr().err
        assert f"{option} {folder} is a folder" in err


def test_posegraph_overflowing_values_are_an_error_not_infinity(tmp_path, capsys):
    """Was a PARDISO traceback (2-D) or 'initial_cost': Infinity with exit 0 (3-D)."""
    planar = tmp_path / "planar.g2o"
    planar.write_text(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1e200 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
    )
    spatial = tmp_path / "spatial.g2o"
    spatial.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 0 1 1e300 0 0 0 0 0 1 "
        + " ".join(["1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"])
        + "\n"
    )
    for path in (planar, spatial):
        assert main(["posegraph", str(path)]) == 2
        captured = capsys.readouterr()
        assert "is not finite" in captured.err and captured.out == ""


def test_posegraph_incremental_start(gtsam, capsys):
    """--start incremental on a 2-D landmark file reports the file's cost, the grown start's
    and the same optimum as LM from the file (example.graph has one); a 3-D file refuses it."""
    assert main(["posegraph", "example", "--tolerance", "1e-12"]) == 0
    plain = _last_json(capsys)
    args = ["posegraph", "example", "--tolerance", "1e-12", "--start", "incremental"]
    assert main([*args, "--chunk", "40"]) == 0
    grown = _last_json(capsys)
    assert (grown["start"], grown["chunk"]) == ("incremental", 40)
    assert grown["initial_cost"] == pytest.approx(plain["initial_cost"], rel=1e-12)
    assert grown["final_cost"] <= grown["start_cost"] < grown["initial_cost"]
    assert grown["final_cost"] == pytest.approx(plain["final_cost"], rel=1e-9)
    assert "start" not in plain
    assert main(["posegraph", "sphere2500", "--start", "incremental"]) == 2
    assert "--start incremental is for 2-D graphs" in capsys.readouterr().err
