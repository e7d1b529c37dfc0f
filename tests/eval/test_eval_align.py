"""Umeyama alignment and timestamp association, against known transforms and evo."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from evo.core import geometry as evo_geometry
from evo.core import sync
from evo.core.trajectory import PoseTrajectory3D

from msf_torch.eval.align import apply_similarity, associate, umeyama
from msf_torch.geometry import so3
from msf_torch.types import Trajectory

DT = torch.float64


def _random_similarity(gen: torch.Generator, batch: int):
    rot = so3.exp(torch.randn(batch, 3, generator=gen, dtype=DT) * 1.5)
    trans = torch.randn(batch, 3, generator=gen, dtype=DT) * 10.0
    scale = 0.2 + 3.0 * torch.rand(batch, generator=gen, dtype=DT)
    return rot, trans, scale


@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_known_transform(batch, with_scale):
    gen = torch.Generator().manual_seed(7 + batch)
    rot, trans, scale = _random_similarity(gen, batch)
    if not with_scale:
        scale = torch.ones_like(scale)
    src = torch.randn(batch, 40, 3, generator=gen, dtype=DT) * 4.0
    dst = apply_similarity(src, rot, trans, scale)
    r_hat, t_hat, s_hat = umeyama(src, dst, with_scale=with_scale)
    torch.testing.assert_close(r_hat, rot, atol=1e-10, rtol=0)
    torch.testing.assert_close(t_hat, trans, atol=1e-10, rtol=0)
    torch.testing.assert_close(s_hat, scale, atol=1e-10, rtol=0)


def test_umeyama_batched_equals_looped_and_ignores_padding():
    gen = torch.Generator().manual_seed(3)
    batch, n = 4, 30
    rot, trans, scale = _random_similarity(gen, batch)
    src = torch.randn(batch, n, 3, generator=gen, dtype=DT)
    dst = apply_similarity(src, rot, trans, scale) + 0.05 * torch.randn(
        batch, n, 3, generator=gen, dtype=DT
    )
    lengths = [30, 12, 25, 5]
    mask = torch.arange(n)[None] < torch.tensor(lengths)[:, None]
    # Garbage in the padding must not matter.
    src = torch.where(mask[..., None], src, torch.full_like(src, 1e6))
    dst = torch.where(mask[..., None], dst, torch.full_like(dst, -3e5))
    r_b, t_b, s_b = umeyama(src, dst, mask, with_scale=True)
    for b, k in enumerate(lengths):
        r_1, t_1, s_1 = umeyama(src[b : b + 1, :k], dst[b : b + 1, :k], with_scale=True)
        torch.testing.assert_close(r_b[b], r_1[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(t_b[b], t_1[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(s_b[b], s_1[0], atol=1e-12, rtol=0)
        # And evo's reference implementation on the same noisy points.
        r_e, t_e, s_e = evo_geometry.umeyama_alignment(
            src[b, :k].numpy().T, dst[b, :k].numpy().T, True
        )
        np.testing.assert_allclose(r_b[b].numpy(), r_e, atol=1e-10)
        np.testing.assert_allclose(t_b[b].numpy(), t_e, atol=1e-10)
        assert abs(float(s_b[b]) - s_e) < 1e-10


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_reflection_case_gives_rotation(with_scale):
    """A scaled, noisy mirror image: the best proper rotation, with the sign fix of the
    smallest singular value in the scale ``tr(D S) / sigma_x^2`` too, equal to evo's."""
    gen = torch.Generator().manual_seed(11)
    src = torch.randn(1, 20, 3, generator=gen, dtype=DT) * torch.tensor([3.0, 2.0, 1.0], dtype=DT)
    mirror = torch.tensor([1.0, 1.0, -1.0], dtype=DT)
    dst = 1.7 * src * mirror + 0.05 * torch.randn(1, 20, 3, generator=gen, dtype=DT)
    rot, trans, scale = umeyama(src, dst, with_scale=with_scale)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(1, dtype=DT))
    torch.testing.assert_close(rot[0] @ rot[0].T, torch.eye(3, dtype=DT))
    r_e, t_e, s_e = evo_geometry.umeyama_alignment(src[0].numpy().T, dst[0].numpy().T, with_scale)
    np.testing.assert_allclose(rot[0].numpy(), r_e, rtol=0, atol=1e-10)
    np.testing.assert_allclose(trans[0].numpy(), t_e, rtol=0, atol=1e-10)
    assert float(scale[0]) == pytest.approx(s_e, rel=1e-12)


def test_umeyama_degenerate_raises_or_falls_back():
    src = torch.zeros(2, 5, 3, dtype=DT)
    src[0, :, 0] = torch.arange(5.0, dtype=DT)  # collinear: rank 1 < 2
    src[1] = torch.randn(5, 3, generator=torch.Generator().manual_seed(0), dtype=DT)
    dst = src + 1.0
    with pytest.raises(ValueError, match=r"problems \[0\]"):
        umeyama(src, dst)
    rot, trans, scale = umeyama(src, dst, strict=False, with_scale=True)
    torch.testing.assert_close(rot[0], torch.eye(3, dtype=DT))
    torch.testing.assert_close(trans[0], torch.ones(3, dtype=DT))
    assert float(scale[0]) == 1.0


def _traj(t: np.ndarray) -> Trajectory:
    n = t.size
    tt = torch.from_numpy(np.asarray(t, dtype=np.float64))[None]
    quat = torch.zeros(1, n, 4, dtype=DT)
    quat[..., 0] = 1.0
    return Trajectory(
        t=tt,
        position=torch.zeros(1, n, 3, dtype=DT),
        quaternion=quat,
        mask=torch.ones(1, n, dtype=torch.bool),
    )


def _evo_pairs(t_est: np.ndarray, t_ref: np.ndarray, max_dt: float):
    """Index pairs that evo's associate_trajectories(ref, est) keeps, found via x positions."""

    def traj(t):
        xyz = np.zeros((t.size, 3))
        xyz[:, 0] = np.arange(t.size)
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (t.size, 1))
        return PoseTrajectory3D(xyz, quat, t)

    ref_s, est_s = sync.associate_trajectories(traj(t_ref), traj(t_est), max_diff=max_dt)
    return est_s.positions_xyz[:, 0].astype(int), ref_s.positions_xyz[:, 0].astype(int)


@pytest.mark.parametrize("seed", range(6))
def test_associate_matches_evo(seed):
    rng = np.random.default_rng(seed)
    n_ref, n_est = (50, 80) if seed % 2 else (80, 50)
    t_ref = np.sort(rng.uniform(0, 10, n_ref))
    t_est = np.sort(rng.uniform(-0.5, 10.5, n_est))
    if seed == 4:
        n_est = n_ref = 60
        t_ref = np.sort(rng.uniform(0, 10, n_ref))
        t_est = np.sort(rng.uniform(0, 10, n_est))
    est_idx, ref_idx = associate(_traj(t_est), _traj(t_ref), max_dt=0.1)
    evo_est, evo_ref = _evo_pairs(t_est, t_ref, 0.1)
    np.testing.assert_array_equal(est_idx.numpy(), evo_est)
    np.testing.assert_array_equal(ref_idx.numpy(), evo_ref)


def test_associate_tie_takes_earlier_and_honours_mask():
    t_ref = np.array([0.0, 0.25, 0.5, 0.75])
    t_est = np.array([0.125, 0.625])
    est_idx, ref_idx = associate(_traj(t_est), _traj(t_ref), max_dt=0.125)
    assert est_idx.tolist() == [0, 1] and ref_idx.tolist() == [0, 2]
    evo_est, evo_ref = _evo_pairs(t_est, t_ref, 0.125)
    assert evo_est.tolist() == [0, 1] and evo_ref.tolist() == [0, 2]
    # Masked samples are invisible; indices refer to the padded N axis.
    ref = _traj(np.array([0.0, 0.25, 0.5, 0.75, 99.0]))
    ref.mask[0, 0] = False
    ref.mask[0, 4] = False
    est_idx, ref_idx = associate(_traj(t_est), ref, max_dt=0.125)
    assert est_idx.tolist() == [0, 1] and ref_idx.tolist() == [1, 2]


def test_associate_errors():
    with pytest.raises(ValueError, match="no matching timestamps"):
        associate(_traj(np.array([0.0, 1.0])), _traj(np.array([5.0, 6.0])))
    with pytest.raises(ValueError, match="not sorted"):
        associate(_traj(np.array([0.0, 2.0, 1.0])), _traj(np.array([0.0, 1.0])))
    two = _traj(np.array([0.0, 1.0]))
    batch = two.map(lambda x: torch.cat((x, x), 0))
    with pytest.raises(ValueError, match="B = 1"):
        associate(batch, two)
