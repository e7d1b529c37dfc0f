"""The overview figure writes a real PNG atomically."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.eval import plots
from msf_torch.eval.plots import overview_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _trajectories(tmp_path, tum_pair, read_local):
    est_path, ref_path = tum_pair(0)
    return read_local(est_path), read_local(ref_path)


def test_overview_full(tmp_path, tum_pair, read_local):
    est, ref = _trajectories(tmp_path, tum_pair, read_local)
    t0 = float(est.t[0, 0])
    slip_t = torch.linspace(t0, t0 + 30.0, 200, dtype=torch.float64)
    slip = 0.1 * torch.sin(slip_t - t0).abs()
    out_dir = tmp_path / "figs" / "run"
    path = overview_figure(
        out_dir / "overview.png",
        est,
        ref,
        slip_t=slip_t,
        slip=slip,
        outage=(t0 + 5.0, t0 + 12.0),
        title="synthetic run",
    )
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert path.stat().st_size > 10_000
    assert sorted(p.name for p in out_dir.iterdir()) == ["overview.png"]


def test_overview_without_reference_or_wheel(tmp_path, tum_pair, read_local):
    est, _ = _trajectories(tmp_path, tum_pair, read_local)
    err_t = est.t[0].numpy()
    path = overview_figure(tmp_path / "a.png", est, None, error_t=err_t, error=np.ones_like(err_t))
    assert path.read_bytes()[:8] == PNG_MAGIC
    path = overview_figure(tmp_path / "b.png", est)
    assert path.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".tum") == ["a.png", "b.png"]
    with pytest.raises(ValueError, match="samples"):
        overview_figure(tmp_path / "c.png", est, error_t=err_t, error=np.ones(3))


def test_failed_save_keeps_old_file_and_leaves_no_temp(tmp_path, tum_pair, read_local, monkeypatch):
    est, ref = _trajectories(tmp_path, tum_pair, read_local)
    target = tmp_path / "out" / "overview.png"
    target.parent.mkdir()
    target.write_bytes(b"old")

    def boom(self, *args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(plots.Figure, "savefig", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        overview_figure(target, est, ref)
    assert target.read_bytes() == b"old"
    assert [p.name for p in target.parent.iterdir()] == ["overview.png"]


def test_pose_graph_figure_and_its_input_checks(tmp_path):
    from msf_torch.eval.plots import pose_graph_figure

    angle = torch.linspace(0.0, 6.0, 60, dtype=torch.float64)
    after = torch.stack([10 * angle.cos(), 10 * angle.sin(), 0.1 * angle], -1)
    before = after + 0.3 * angle[:, None]
    chain = torch.stack([torch.arange(59), torch.arange(1, 60)], -1)
    edges = torch.cat([chain, torch.tensor([[0, 50], [5, 55]])])
    log = [
        {"cost": 10.0, "accepted": True},
        {"cost": 10.0, "accepted": False},
        {"cost": 0.5, "accepted": True},
    ]
    path = pose_graph_figure(tmp_path / "g.png", before, after, edges, log, 1e3, title="ring")
    assert path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 20_000
    planar = pose_graph_figure(tmp_path / "p.png", before[:, :2], after[:, :2], edges, log, 1e3)
    assert planar.read_bytes()[:8] == PNG_MAGIC  # a 2-D graph: top view and costs
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 2\) of one N"):
        pose_graph_figure(tmp_path / "h.png", before[:10], after, edges, log, 1e3)
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 2\) of one N"):
        pose_graph_figure(tmp_path / "h.png", before[:, :2], after, edges, log, 1e3)
    with pytest.raises(ValueError, match="rows of the 60 vertices"):
        pose_graph_figure(tmp_path / "h.png", before, after, edges + 10, log, 1e3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.png", "p.png"]
