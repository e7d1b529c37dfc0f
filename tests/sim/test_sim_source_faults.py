"""Pose-source fault injection (``msf_torch.sim.faults``) against the clean streams.

Each fault must rewrite exactly the increments its labels name, in the way its kind says
(checked against the clean stream's increments), and leave every other increment as it
was; after a fault the stream is the clean one moved by a rigid world-frame offset.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.faults import (
    SourceFault,
    inject_faults,
    pair_labels,
    random_faults,
    simulate_fault_run,
)
from msf_torch.sim.weather import WeatherSchedule, apply_weather

DURATION_S = 40.0


@pytest.fixture(scope="module")
def wet():
    run = simulate_run(SimConfig(duration_s=DURATION_S, imu_rate_hz=100.0), seed=7)
    return apply_weather(run, WeatherSchedule.constant("sunny", DURATION_S), seed=8)


def _increments(stream) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sample times, body-frame position increments (M, 3) and relative rotations
    (M, 3, 3) between consecutive valid samples, and the valid indices."""
    valid = stream.mask[0].numpy()
    idx = np.flatnonzero(valid)
    rot = quat_to_matrix(stream.quaternion[0, idx]).numpy()
    pos = stream.position[0, idx].numpy()
    d_pos = np.einsum("mji,mj->mi", rot[:-1], np.diff(pos, axis=0))
    d_rot = rot[:-1].transpose(0, 2, 1) @ rot[1:]
    return stream.t[0].numpy(), d_pos, d_rot, idx


def test_stuck_and_slide_rewrite_only_their_increments(wet):
    faults = [
        SourceFault("lidar", "stuck", 10.0, 14.0),
        SourceFault("vo", "slide", 20.0, 26.0, axial_scale=0.25, axial_bias_mps=0.2),
    ]
    faulty = inject_faults(wet, faults, seed=1)
    for name in ("lidar", "vo"):
        t, d_pos, d_rot, idx = _increments(wet.pose_sources[name])
        _, f_pos, f_rot, f_idx = _increments(faulty.sequence.pose_sources[name])
        assert np.array_equal(idx, f_idx)
        changed = faulty.sample_labels[name][idx[1:]]
        end = t[idx[1:]]
        fault = next(f for f in faults if f.source == name)
        assert np.array_equal(changed, (end > fault.t_start) & (end <= fault.t_end))
        np.testing.assert_allclose(f_pos[~changed], d_pos[~changed], atol=1e-9)
        np.testing.assert_allclose(f_rot[~changed], d_rot[~changed], atol=1e-9)
        if fault.kind == "stuck":
            assert np.abs(f_pos[changed]).max() < 1e-12
            np.testing.assert_allclose(
                f_rot[changed], np.broadcast_to(np.eye(3), f_rot[changed].shape), atol=1e-12
            )
        else:
            state = wet.truth.path.evaluate(t[idx[:-1]])
            travel = np.einsum("mji,mj->mi", state.rotation, state.velocity * [1.0, 1.0, 0.0])
            axis = travel / np.linalg.norm(travel, axis=-1, keepdims=True)
            along, along_f = (np.einsum("mi,mi->m", axis, x) for x in (d_pos, f_pos))
            step = np.diff(t[idx])
            expected = fault.axial_scale * along + fault.axial_bias_mps * step
            np.testing.assert_allclose(along_f[changed], expected[changed], atol=1e-9)
            across = d_pos - along[:, None] * axis
            across_f = f_pos - along_f[:, None] * axis
            np.testing.assert_allclose(across_f, across, atol=1e-9)
            np.testing.assert_allclose(f_rot, d_rot, atol=1e-9)


def test_after_a_fault_the_stream_is_the_clean_one_moved_rigidly(wet):
    faulty = inject_faults(wet, [SourceFault("lidar", "blind", 10.0, 15.0)], seed=2)
    clean, bad = wet.pose_sources["lidar"], faulty.sequence.pose_sources["lidar"]
    t = clean.t[0].numpy()
    late = np.flatnonzero((t > 16.0) & clean.mask[0].numpy())
    early = np.flatnonzero((t <= 10.0) & clean.mask[0].numpy())
    assert torch.equal(bad.position[0, early], clean.position[0, early])
    rot_c, rot_b = (quat_to_matrix(s.quaternion[0, late]).numpy() for s in (clean, bad))
    offset = rot_b @ rot_c.transpose(0, 2, 1)  # constant world rotation
    np.testing.assert_allclose(offset, np.broadcast_to(offset[0], offset.shape), atol=1e-9)
    shift = bad.position[0, late].numpy() - np.einsum(
        "ij,nj->ni", offset[0], clean.position[0, late].numpy()
    )
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-9)
    assert np.linalg.norm(shift[0]) > 1.0  # the garbage moved it
    assert torch.equal(bad.covariance, clean.covariance)  # undeclared


def test_jump_labels_one_increment_of_the_given_size(wet):
    fault = SourceFault("vo", "jump", 12.34, 12.34, jump_m=2.5, jump_rad=0.05)
    faulty = inject_faults(wet, [fault], seed=3)
    t, d_pos, d_rot, idx = _increments(wet.pose_sources["vo"])
    _, f_pos, f_rot, _ = _increments(faulty.sequence.pose_sources["vo"])
    labels = faulty.sample_labels["vo"]
    assert labels.sum() == 1
    k = int(np.flatnonzero(labels[idx[1:]])[0])
    assert t[idx[k]] < 12.34 <= t[idx[k + 1]]
    jump = f_pos[k] - d_pos[k]
    np.testing.assert_allclose(np.linalg.norm(jump), 2.5, rtol=1e-9)
    assert abs(jump[2]) < 1e-12
    yaw = d_rot[k].T @ f_rot[k]
    np.testing.assert_allclose(np.arctan2(yaw[1, 0], yaw[0, 0]), 0.05, atol=1e-9)


def test_pair_labels_counts_labelled_samples_inside_each_pair():
    t = np.arange(10) * 0.1
    labels = np.zeros(10, dtype=bool)
    labels[[3, 8]] = True
    ends = np.array([0.3, 0.4, 0.6, 0.9, 0.9])
    dts = np.array([0.1, 0.1, 0.2, 0.2, 0.1])
    np.testing.assert_array_equal(
        pair_labels(t, labels, ends, dts), [True, False, False, True, False]
    )


def test_random_plans_and_fault_runs_are_seeded_and_disjoint():
    for seed in range(20):
        faults, free = random_faults(120.0, seed, slots=4)
        assert faults == random_faults(120.0, seed, slots=4)[0]
        spans = sorted([(f.t_start, f.t_end) for f in faults] + free)
        assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:], strict=False))
        assert {(f.source, f.kind) for f in faults[:2]} == {("lidar", "slide"), ("vo", "blind")}
        assert faults[2].kind in ("jump", "stuck")
    run = simulate_fault_run(3, duration_s=90.0)
    again = simulate_fault_run(3, duration_s=90.0)
    assert run.sequence.wheel is None and run.sequence.names == ["fault-3"]
    for name in ("vo", "lidar"):
        assert torch.equal(
            run.sequence.pose_sources[name].position, again.sequence.pose_sources[name].position
        )
        intervals = run.sequence.labels[f"fault:{name}"][0].numpy()
        mine = [f for f in run.faults if f.source == name]
        np.testing.assert_array_equal(intervals, [[f.t_start, f.t_end] for f in mine])


def test_bad_faults_are_rejected(wet):
    with pytest.raises(ValueError, match="kind"):
        inject_faults(wet, [SourceFault("vo", "melt", 1.0, 2.0)], seed=0)
    with pytest.raises(ValueError, match="no pose source 'gps'"):
        inject_faults(wet, [SourceFault("gps", "stuck", 1.0, 2.0)], seed=0)
    with pytest.raises(ValueError, match="t_end"):
        inject_faults(wet, [SourceFault("vo", "stuck", 3.0, 2.0)], seed=0)
