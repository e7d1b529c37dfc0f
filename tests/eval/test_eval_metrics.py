"""ATE / RPE against evo 1.38 on the same TUM files, and the batched statistics."""

from __future__ import annotations

import copy
import importlib.util

import numpy as np
import pytest
import torch
from evo.core import metrics as evo_metrics
from evo.core import sync
from evo.core.units import Unit
from evo.tools import file_interface

from msf_torch.eval.metrics import (
    ate,
    error_statistics,
    evaluate_files,
    position_errors,
    rpe,
    translation_errors,
)

STATS = ("rmse", "mean", "median", "std", "min", "max")
TOL = 1e-9
MAX_DT = 0.01


def _evo_synced(est_path, ref_path, align):
    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=MAX_DT)
    if align != "none":
        est.align(ref, correct_scale=align == "sim3")
    return ref, est


def _evo_stats(metric):
    return {k: float(metric.get_statistic(getattr(evo_metrics.StatisticsType, k))) for k in STATS}


def _assert_stats(ours, theirs):
    for key in STATS:
        assert ours[key] == pytest.approx(theirs[key], abs=TOL, rel=TOL), key


@pytest.mark.parametrize("align", ["se3", "sim3", "none"])
@pytest.mark.parametrize("seed", [0, 1])
def test_ate_matches_evo(tum_pair, read_local, align, seed):
    est_path, ref_path = tum_pair(seed)
    ref, est = _evo_synced(est_path, ref_path, align)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ours = ate(read_local(est_path), read_local(ref_path), align=align, max_dt=MAX_DT)
    _assert_stats(ours, _evo_stats(ape))
    assert ours["matched"] == est.num_poses
    if align == "sim3":
        assert ours["scale"] == pytest.approx(1.0 / 0.8, rel=0.05)
    else:
        assert ours["scale"] == 1.0


@pytest.mark.parametrize(
    ("align", "delta", "unit"),
    [
        ("se3", 1, "frames"),
        ("sim3", 1, "frames"),
        ("none", 1, "frames"),
        ("se3", 7, "frames"),
        ("sim3", 2.0, "m"),
        ("se3", 0.5, "m"),
        ("none", 3.0, "m"),
    ],
)
def test_rpe_matches_evo(tum_pair, read_local, align, delta, unit):
    est_path, ref_path = tum_pair(3)
    ref, est = _evo_synced(est_path, ref_path, align)
    evo_unit = Unit.frames if unit == "frames" else Unit.meters
    trans = evo_metrics.RPE(
        evo_metrics.PoseRelation.translation_part, delta, evo_unit, all_pairs=False
    )
    trans.process_data((ref, est))
    rot = evo_metrics.RPE(
        evo_metrics.PoseRelation.rotation_angle_deg, delta, evo_unit, all_pairs=False
    )
    rot.process_data((ref, est))
    ours = rpe(
        read_local(est_path),
        read_local(ref_path),
        delta=delta,
        delta_unit=unit,
        align=align,
        max_dt=MAX_DT,
    )
    _assert_stats(ours, _evo_stats(trans))
    _assert_stats(ours["rotation_deg"], _evo_stats(rot))
    assert ours["pairs"] == len(trans.error)
    assert ours["matched"] == est.num_poses


def test_rpe_seconds_and_rigid_invariance(tum_pair, read_local):
    est_path, ref_path = tum_pair(5)
    est, ref = read_local(est_path), read_local(ref_path)
    by_time = rpe(est, ref, delta=1.0, delta_unit="s")
    assert by_time["pairs"] > 10
    # Rigid alignment leaves RPE unchanged.
    a = rpe(est, ref, delta=3, align="se3")
    b = rpe(est, ref, delta=3, align="none")
    for key in STATS:
        assert a[key] == pytest.approx(b[key], abs=1e-12)
    with pytest.raises(ValueError, match="integer"):
        rpe(est, ref, delta=1.5, delta_unit="frames")
    with pytest.raises(ValueError, match="no pose pairs"):
        rpe(est, ref, delta=10_000, delta_unit="frames")
    with pytest.raises(ValueError, match="align"):
        ate(est, ref, align="sim2")


def test_position_errors_agree_with_ate(tum_pair, read_local):
    est_path, ref_path = tum_pair(2)
    est, ref = read_local(est_path), read_local(ref_path)
    t, err = position_errors(est, ref, align="sim3")
    stats = ate(est, ref, align="sim3")
    assert t.shape == err.shape == (stats["matched"],)
    assert bool((t[1:] >= t[:-1]).all())
    assert float(err.square().mean().sqrt()) == pytest.approx(stats["rmse"], abs=1e-12)


def test_error_statistics_masked_match_numpy():
    gen = torch.Generator().manual_seed(0)
    err = torch.rand(3, 9, generator=gen, dtype=torch.float64)
    lengths = [9, 4, 1]
    mask = torch.arange(9)[None] < torch.tensor(lengths)[:, None]
    stats = error_statistics(torch.where(mask, err, torch.full_like(err, 7.0)), mask)
    for b, k in enumerate(lengths):
        x = err[b, :k].numpy()
        expected = {
            "rmse": np.sqrt(np.mean(x**2)),
            "mean": np.mean(x),
            "median": np.median(x),
            "std": np.std(x),
            "min": np.min(x),
            "max": np.max(x),
        }
        for key, value in expected.items():
            assert float(stats[key][b]) == pytest.approx(value, abs=1e-14), (b, key)
        assert int(stats["count"][b]) == k
    empty = error_statistics(err[:1], torch.zeros(1, 9, dtype=torch.bool))
    assert torch.isnan(empty["rmse"]).all() and int(empty["count"][0]) == 0


def test_translation_errors_batched_equals_single(tum_pair, read_local):
    # Two synchronised sequences of different length in one padded batch.
    seqs = []
    for seed in (0, 1):
        est_path, ref_path = tum_pair(seed)
        ref_s, est_s = _evo_synced(est_path, ref_path, "none")
        seqs.append((torch.from_numpy(est_s.positions_xyz), torch.from_numpy(ref_s.positions_xyz)))
    n = max(s[0].shape[0] for s in seqs)
    est_b = torch.zeros(2, n, 3, dtype=torch.float64)
    ref_b = torch.zeros(2, n, 3, dtype=torch.float64)
    mask = torch.zeros(2, n, dtype=torch.bool)
    for b, (e, r) in enumerate(seqs):
        est_b[b, : e.shape[0]], ref_b[b, : r.shape[0]], mask[b, : e.shape[0]] = e, r, True
    err = translation_errors(est_b, ref_b, mask, align="sim3")
    stats = error_statistics(err, mask)
    for b, (e, r) in enumerate(seqs):
        single = translation_errors(e[None], r[None], align="sim3")
        torch.testing.assert_close(err[b, : e.shape[0]], single[0], atol=1e-12, rtol=0)
        assert float(stats["rmse"][b]) == pytest.approx(float(single.square().mean().sqrt()))
    assert bool((err[~mask] == 0).all())


@pytest.mark.skipif(
    importlib.util.find_spec("msf_torch.io.tum") is None, reason="msf_torch.io.tum not written yet"
)
@pytest.mark.parametrize("align", ["se3", "sim3", "none"])
def test_evaluate_files_matches_evo(tum_pair, align):
    est_path, ref_path = tum_pair(4)
    out = evaluate_files(est_path, ref_path, align=align, max_dt=MAX_DT)
    ref, est = _evo_synced(est_path, ref_path, align)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((copy.deepcopy(ref), copy.deepcopy(est)))
    rpe_metric = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, 1, Unit.frames)
    rpe_metric.process_data((ref, est))
    _assert_stats(out["ate"], _evo_stats(ape))
    _assert_stats(out["rpe"], _evo_stats(rpe_metric))
    assert out["matched"] == est.num_poses
    assert out["align"] == align


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_aligned_estimate_and_the_eval_plot(tmp_path, align, run_factory, read_local):
    # the reference moved by a known similarity: aligning the moved copy gives it back
    from scipy.spatial.transform import Rotation

    from msf_torch.eval.metrics import aligned_estimate

    def write_tum(path, t, xyz, quat_xyzw):
        np.savetxt(path, np.column_stack((t, xyz, quat_xyzw)), fmt="%.17g")
        return path

    run = run_factory(3)
    rotation = Rotation.from_rotvec([0.3, -0.2, 1.1])
    scale = 1.7 if align == "sim3" else 1.0
    xyz = scale * rotation.apply(run["ref_xyz"]) + np.array([5.0, -2.0, 0.5])
    quat = (rotation * Rotation.from_quat(run["ref_q"])).as_quat()
    est_path = write_tum(tmp_path / "est.tum", run["ref_t"], xyz, quat)
    ref_path = write_tum(tmp_path / "ref.tum", run["ref_t"], run["ref_xyz"], run["ref_q"])
    est, ref = read_local(est_path), read_local(ref_path)
    back = aligned_estimate(est, ref, align=align)
    torch.testing.assert_close(back.position, ref.position, atol=1e-9, rtol=0)
    relative = Rotation.from_quat(back.quaternion[0].numpy()[:, [1, 2, 3, 0]]).inv() * (
        Rotation.from_quat(run["ref_q"])
    )
    assert relative.magnitude().max() < 1e-9
    unmoved = aligned_estimate(est, ref, align="none")
    torch.testing.assert_close(unmoved.position, est.position, atol=0, rtol=0)
    out = evaluate_files(est_path, ref_path, align=align, plot=tmp_path / "eval.png")
    assert out["plot"] == str(tmp_path / "eval.png") and out["ate"]["rmse"] < 1e-9
    assert (tmp_path / "eval.png").read_bytes()[:4] == b"\x89PNG"
