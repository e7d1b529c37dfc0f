"""``EskfResult.select``: one sequence of a batched result, as a result with B = 1."""

from __future__ import annotations

import pytest
import torch

from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import batch_sequences


def test_select_equals_the_sequence_run_alone():
    runs = [simulate_run(SimConfig(duration_s=d), seed=s).sequence for s, d in ((1, 8.0), (2, 6.0))]
    with torch.no_grad():
        batch = run_eskf(batch_sequences(runs))
        alone = run_eskf(runs[1])
    own = batch.select(1)
    assert own.names == alone.names
    epochs = int(alone.mask[0].sum())
    assert int(own.mask[0].sum()) == epochs and own.position.shape[0] == 1
    for name in ("t", "position", "velocity", "covariance", "slip_factor"):
        got, want = getattr(own, name)[:, :epochs], getattr(alone, name)[:, :epochs]
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9, msg=name)
    assert own.present.keys() == alone.present.keys()
    for key in alone.present:
        assert torch.equal(own.accepted[key][:, :epochs], alone.accepted[key][:, :epochs]), key
    assert own.counts() == alone.counts()
    memory = own.gate_memory
    assert memory is not None and memory.episode.shape == (1,)
    assert all(v.shape[0] == 1 for v in memory.streak.values())
    assert batch.select(-1).names == batch.select(1).names
    with pytest.raises(IndexError, match="out of range for B = 2"):
        batch.select(2)
