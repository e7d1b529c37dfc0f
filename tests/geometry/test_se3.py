"""SE(3) log and right Jacobian: against GTSAM's Pose3.Logmap, the matrix-exponential form
and finite differences of exp/log."""

from __future__ import annotations

import pytest
import torch

from msf_torch.geometry import se3, so3

DTYPE = torch.float64


def _within_pi(xi: torch.Tensor) -> torch.Tensor:
    """Scale rotation parts down to angles below 3 rad (log returns angles in [0, pi])."""
    angle = xi[..., 3:6].norm(dim=-1, keepdim=True)
    return torch.cat((xi[..., 0:3], xi[..., 3:6] * torch.clamp(3.0 / angle, max=1.0)), -1)


def _exp(xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    phi = xi[..., 3:6]
    return so3.exp(phi), (so3.gamma1(phi) @ xi[..., 0:3, None]).squeeze(-1)


@pytest.mark.parametrize("scale", [1e-5, 3e-3, 0.5, 2.0])
def test_log_inverts_exp(scale):
    xi = _within_pi(
        scale * torch.randn(40, 6, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    )
    torch.testing.assert_close(se3.log(*_exp(xi)), xi, rtol=0, atol=1e-12)


def test_log_equals_gtsam_pose3_logmap():
    gtsam = pytest.importorskip("gtsam")
    gen = torch.Generator().manual_seed(2)
    for _ in range(5):
        rot = so3.exp(torch.randn(3, generator=gen, dtype=DTYPE))
        t = torch.randn(3, generator=gen, dtype=DTYPE)
        peer = gtsam.Pose3.Logmap(gtsam.Pose3(gtsam.Rot3(rot.numpy()), t.numpy()))
        ours = se3.log(rot, t)
        torch.testing.assert_close(ours[3:6], torch.as_tensor(peer[0:3]), rtol=0, atol=1e-12)
        torch.testing.assert_close(ours[0:3], torch.as_tensor(peer[3:6]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-6, 4e-3, 0.3, 2.5])
def test_right_jacobian_inverse(scale):
    xi = _within_pi(
        scale * torch.randn(30, 6, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    )
    inverse = se3.right_jacobian_inverse(xi)
    torch.testing.assert_close(
        inverse @ se3.right_jacobian(xi),
        torch.eye(6, dtype=DTYPE).expand(30, 6, 6),
        rtol=0,
        atol=1e-10,
    )
    # d Log(exp(xi) exp(d)) / dd = J_r^-1(xi), by central differences
    rot, t = _exp(xi)
    step = 1e-6
    for k in range(6):
        d = torch.zeros(6, dtype=DTYPE)
        d[k] = step
        up = se3.log(*se3.compose(rot, t, *_exp(d)))
        down = se3.log(*se3.compose(rot, t, *_exp(-d)))
        torch.testing.assert_close((up - down) / (2 * step), inverse[..., k], rtol=0, atol=2e-7)
