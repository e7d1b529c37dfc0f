"""``run_eskf`` without gradients runs under ``torch.inference_mode`` (about a quarter less
time at B = 1) and hands back ordinary tensors: the same numbers as a run with autograd on,
usable afterwards in autograd and in place, and the geometry's cached constants stay
ordinary tensors when inference mode first builds them."""

from __future__ import annotations

import dataclasses

import torch

from msf_torch.frontend.eskf import run_eskf
from msf_torch.geometry import quaternion, so3
from msf_torch.sim import SimConfig, simulate_run


def _tensors(value, path="result"):
    """Every tensor in a result, with its path (dataclass fields, dicts, lists, tuples)."""
    if isinstance(value, torch.Tensor):
        yield path, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _tensors(item, f"{path}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from _tensors(item, f"{path}[{i}]")
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        for spec in dataclasses.fields(value):
            yield from _tensors(getattr(value, spec.name), f"{path}.{spec.name}")


def test_no_grad_run_equals_autograd_run_and_returns_ordinary_tensors():
    seq = simulate_run(SimConfig(duration_s=20.0, slip_episodes=1), seed=4).sequence
    with torch.no_grad():
        fast = run_eskf(seq)
    reference = run_eskf(seq)  # autograd on (nothing requires grad): no inference mode
    fast_tensors, reference_tensors = list(_tensors(fast)), list(_tensors(reference))
    assert [p for p, _ in fast_tensors] == [p for p, _ in reference_tensors]
    assert len(fast_tensors) > 20
    for (path, got), (_, want) in zip(fast_tensors, reference_tensors, strict=True):
        assert not got.is_inference(), path
        torch.testing.assert_close(got, want, rtol=0, atol=0, equal_nan=True, msg=path)
    # ordinary tensors: in-place edits and autograd work on them
    fast.position[:, 0] += 1.0
    gain = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    (gain * fast.covariance).sum().backward()
    assert float(gain.grad) == float(fast.covariance.sum())


def test_cached_constants_built_in_inference_mode_serve_autograd():
    for cached in (so3.identity, so3._hat_generators, quaternion._product_table):
        cached.cache_clear()
    with torch.inference_mode():  # the first calls build the caches
        so3.exp(torch.zeros(3, dtype=torch.float64))
        quaternion.quat_multiply(
            torch.tensor([1.0, 0, 0, 0], dtype=torch.float64),
            torch.tensor([1.0, 0, 0, 0], dtype=torch.float64),
        )
    phi = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64, requires_grad=True)
    so3.exp(phi).sum().backward()  # hat's generators and the identity are saved for backward
    step = 1e-6
    numeric = torch.stack(
        [
            (so3.exp(phi.detach() + step * e).sum() - so3.exp(phi.detach() - step * e).sum())
            / (2 * step)
            for e in torch.eye(3, dtype=torch.float64)
        ]
    )
    torch.testing.assert_close(phi.grad, numeric, rtol=1e-7, atol=1e-9)
    q = torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64, requires_grad=True)
    quaternion.quat_multiply(q, q).sum().backward()
    # q (x) q for q = [w, v] is [w^2 - |v|^2, 2 w v]: its sum is w^2 - |v|^2 + 2 w sum(v)
    w, v = q.detach()[0], q.detach()[1:]
    expected = torch.cat(((2 * w + 2 * v.sum())[None], -2 * v + 2 * w))
    torch.testing.assert_close(q.grad, expected, rtol=1e-12, atol=1e-12)
