"""Stream helpers in ``msf_torch.types`` against hand-made time stamps."""

from __future__ import annotations

import math

import torch

from msf_torch.types import ImuSamples


def _imu(t: torch.Tensor, mask: torch.Tensor) -> ImuSamples:
    zeros = torch.zeros(*t.shape, 3, dtype=torch.float64)
    return ImuSamples(t=t, gyro=zeros, accel=zeros.clone(), mask=mask)


def test_median_rate_is_one_over_the_median_interval_of_real_samples() -> None:
    # sequence 0: 200 Hz with one late sample (a 7 ms interval, then 3 ms) and padding;
    # sequence 1: 50 Hz, shorter, with a masked sample in the middle (its two intervals
    # are not real ones) and padding stamped 0
    fast = torch.arange(12, dtype=torch.float64) * 0.005
    fast[5] += 0.002
    slow = torch.zeros(12, dtype=torch.float64)
    slow[:6] = torch.arange(6, dtype=torch.float64) * 0.02
    slow[3] = 9.0
    mask = torch.ones(2, 12, dtype=torch.bool)
    mask[0, 10:] = False
    mask[1, 6:] = False
    mask[1, 3] = False
    rate = _imu(torch.stack([fast, slow]), mask).median_rate_hz()
    torch.testing.assert_close(rate, torch.tensor([200.0, 50.0], dtype=torch.float64))


def test_median_rate_of_too_short_streams_is_nan() -> None:
    one = _imu(torch.zeros(2, 1, dtype=torch.float64), torch.ones(2, 1, dtype=torch.bool))
    assert all(math.isnan(r) for r in one.median_rate_hz().tolist())
    padded = _imu(
        torch.tensor([[0.0, 0.01, 0.02], [0.0, 0.0, 0.0]], dtype=torch.float64),
        torch.tensor([[True, True, True], [True, False, False]]),
    )
    rate = padded.median_rate_hz()
    assert math.isclose(rate[0].item(), 100.0, rel_tol=1e-12)
    assert math.isnan(rate[1].item())


def test_move_to_reaches_every_tensor_and_keeps_the_rest() -> None:
    from collections import namedtuple
    from dataclasses import dataclass, field

    from msf_torch.types import move_to

    Pair = namedtuple("Pair", "left right")

    @dataclass
    class Inner:
        value: torch.Tensor
        name: str = "inner"

    @dataclass
    class Outer:
        inner: Inner
        by_key: dict
        items: list
        pair: Pair
        count: int = 3
        derived: torch.Tensor = field(init=False)

        def __post_init__(self) -> None:
            self.derived = self.inner.value * 2

    outer = Outer(
        Inner(torch.ones(2)),
        {"a": torch.zeros(1), "b": None},
        [torch.arange(3), (torch.ones(1), "x")],
        Pair(torch.ones(1), 7),
    )
    moved = move_to(outer, "meta")
    tensors = [
        moved.inner.value,
        moved.derived,
        moved.by_key["a"],
        moved.items[0],
        moved.items[1][0],
        moved.pair.left,
    ]
    assert all(t.device.type == "meta" for t in tensors)
    assert isinstance(moved.pair, Pair) and moved.pair.right == 7
    assert moved.by_key["b"] is None and moved.items[1][1] == "x" and moved.count == 3
    assert moved.inner.name == "inner" and isinstance(moved.items[1], tuple)
    assert outer.inner.value.device.type == "cpu"  # the original is left as it was
