"""A large batch without gradients preintegrates on a worker thread while the epoch loop
runs (``frontend.eskf._EpochIncrements``): the same numbers as computing every chunk first,
the worker really runs, and it is stopped when the loop ends early."""

from __future__ import annotations

import threading

import pytest
import torch

from msf_torch.frontend import eskf
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import batch_sequences

WORKER = "msf-increments"


def _workers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith(WORKER)]


@pytest.fixture
def batch16():
    runs = [simulate_run(SimConfig(duration_s=6.0), seed=s).sequence for s in range(16)]
    return batch_sequences(runs)


@pytest.fixture
def threads():
    previous = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(previous)


def test_background_chunks_equal_serial_chunks(batch16, threads, monkeypatch):
    monkeypatch.setattr(eskf, "INCREMENT_CHUNK_SAMPLES", 2000)  # many chunks per run
    seen = []

    def watch(done: int, total: int) -> None:
        seen.append(len(_workers()))

    threads(1)  # one thread: every chunk first, on the calling thread
    with torch.no_grad():
        serial = run_eskf(batch16, progress=watch)
    assert max(seen) == 0
    seen.clear()
    threads(2)  # two threads and B >= 16: the worker
    with torch.no_grad():
        background = run_eskf(batch16, progress=watch)
    assert max(seen) == 1
    steps = background.position.shape[1]
    assert steps > 20
    # the worker runs one intra-op thread, as the serial run: bit-identical
    for name in ("position", "velocity", "rotation", "gyro_bias", "accel_bias", "covariance"):
        torch.testing.assert_close(
            getattr(background, name), getattr(serial, name), rtol=0, atol=0, msg=name
        )


def test_no_worker_with_gradients_or_small_batches(batch16, threads):
    threads(2)
    seen = []

    def watch(done: int, total: int) -> None:
        seen.append(len(_workers()))

    run_eskf(batch16, progress=watch)  # autograd on: every chunk first
    small = batch_sequences(
        [simulate_run(SimConfig(duration_s=6.0), seed=s).sequence for s in range(4)]
    )
    with torch.no_grad():
        run_eskf(small, progress=watch)  # B < 16: every chunk first
    assert len(seen) > 40
    assert max(seen) == 0


def test_worker_stops_when_the_loop_ends_early(batch16, threads, monkeypatch):
    monkeypatch.setattr(eskf, "INCREMENT_CHUNK_SAMPLES", 500)
    threads(2)

    def stop(done: int, total: int) -> None:
        if done == 3:
            raise RuntimeError("stop here")

    with torch.no_grad(), pytest.raises(RuntimeError, match="stop here"):
        run_eskf(batch16, progress=stop)
    assert _workers() == []  # shut down and joined


def test_consumed_chunks_are_released(batch16):
    from msf_torch.frontend.config import EskfConfig
    from msf_torch.frontend.eskf import EskfNoise, _EpochIncrements
    from msf_torch.frontend.schedule import build_schedule

    cfg = EskfConfig()
    sched = build_schedule(batch16, cfg)
    zeros = torch.zeros(16, 3, dtype=torch.float64)
    noise = EskfNoise.from_config(cfg, torch.float64, "cpu")
    increments = _EpochIncrements(sched, zeros, zeros, noise, cfg.gravity_mps2, max_samples=500)
    step = increments.step
    assert sched.t_end.shape[1] > 3 * step
    assert all(chunk is None for chunk in increments._chunks)  # computed when reached
    first, local = increments.at(1)
    assert local == 1 and first.start == 0 and first.pre.delta_t.shape[1] == step
    third, local = increments.at(2 * step + 1)
    assert third.start == 2 * step and local == 1
    assert increments._chunks[0] is None and increments._chunks[1] is None  # released
    assert increments.at(2 * step)[0] is third
    assert increments._chunks[3] is None  # not reached yet
    with pytest.raises(IndexError, match="released chunk"):
        increments.at(step)
    increments.close()


def test_worker_stays_a_few_chunks_ahead(batch16):
    from msf_torch.frontend.config import EskfConfig
    from msf_torch.frontend.eskf import _LOOKAHEAD_CHUNKS, EskfNoise, _EpochIncrements
    from msf_torch.frontend.schedule import build_schedule

    cfg = EskfConfig()
    sched = build_schedule(batch16, cfg)
    zeros = torch.zeros(16, 3, dtype=torch.float64)
    noise = EskfNoise.from_config(cfg, torch.float64, "cpu")
    with torch.inference_mode():
        increments = _EpochIncrements(sched, zeros, zeros, noise, 9.81, True, max_samples=300)
        try:
            chunks = len(increments._chunks)
            assert chunks > _LOOKAHEAD_CHUNKS + 3
            assert sum(c is not None for c in increments._chunks) == _LOOKAHEAD_CHUNKS
            increments.at(increments.step)  # chunk 1: queued through 1 + lookahead
            queued = [c is not None for c in increments._chunks]
            assert queued == [False] + [True] * (1 + _LOOKAHEAD_CHUNKS) + [False] * (
                chunks - 2 - _LOOKAHEAD_CHUNKS
            )
        finally:
            increments.close()
