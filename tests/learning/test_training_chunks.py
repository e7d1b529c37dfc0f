"""Training chunks (``CovNetModule.run_chunks``) keep filled-in IMU stretches whole.

* Runs without a filled-in stretch (the simulated weather runs): the chunks are the
  window-aligned ones, bit for bit (reference: ``run_eskf`` chained by hand).
* A stretch across a chunk boundary: the boundary moves to the stretch's end, as in
  ``learning.inference.run_piecewise``, and the training filter equals it to 1e-9; a chunk
  wholly inside the stretch is left to the chunk before. Before, the boundary cut the
  stretch into two shorter gaps (measured 2.7 and 3.7 cm from run_piecewise at their
  common epochs on these 8-s runs).
* A batch shares its chunk boundaries: a boundary moves past the stretches of every run.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.learning import CovNetConfig
from msf_torch.learning.covnet import scaled_noise
from msf_torch.learning.data import collate_runs, run_features, simulate_labelled_run
from msf_torch.learning.inference import run_piecewise
from msf_torch.learning.module import CovNetModule
from msf_torch.sensors.imu_gaps import interpolated_imu_samples
from msf_torch.sim import SimConfig, fill_imu_stretch, simulate_run
from msf_torch.types import NavState

WEATHER = ("sunny", "rain", "fog", "night", "snow")
LENGTH = 100  # IMU samples per window (CovNetConfig's default), 1 s at 100 Hz


def _batch(runs, sources=("gnss", "vo", "lidar")):
    features = [run_features(seq, LENGTH, sources, WEATHER) for seq in runs]
    return collate_runs(list(zip(runs, features, strict=True)), window_length=LENGTH)


def _chained(results) -> dict[str, torch.Tensor]:
    """Run 0's real epochs of consecutive chunk results, each later chunk's first (its
    predecessor's last) dropped."""
    out = {}
    for name in ("t", "position", "velocity", "rotation", "covariance"):
        parts = [getattr(r, name)[0, r.mask[0]][min(k, 1) :] for k, r in enumerate(results)]
        out[name] = torch.cat(parts)
    return out


def test_runs_without_stretches_keep_window_aligned_chunks() -> None:
    """Two weather runs, 7 windows in chunks of 2 (the last of 1), per-window scales."""
    runs = [simulate_labelled_run(seed, 7.0) for seed in (5, 6)]
    batch = _batch(runs)
    imu = batch.sequence.imu
    for b in range(2):
        assert not interpolated_imu_samples(imu.t[b], imu.gyro[b], imu.accel[b]).any()
    module = CovNetModule(CovNetConfig(), chunk_windows=2)
    log_scales = 0.3 * torch.randn(2, batch.windows, 7, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        totals, results = module.run_chunks(batch, log_scales)
        seq = batch.sequence
        cfg = module.eskf_config(seq)
        base = EskfNoise.from_config(cfg, imu.t.dtype)
        state = module.start_state(batch, cfg)
        reference = []
        for w0 in range(0, batch.windows, 2):
            a, b = w0 * LENGTH, min(w0 + 2, batch.windows) * LENGTH
            chunk = dataclasses.replace(seq, imu=imu.map(lambda x, a=a, b=b: x[:, a : b + 1]))
            noise = scaled_noise(base, log_scales[:, w0 : w0 + 2].mean(1).double())
            part = run_eskf(chunk, cfg, noise, initial=state)
            fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
            last = part.mask.sum(1) - 1
            rows = torch.arange(2)
            state = (
                NavState(*(getattr(part, f)[rows, last] for f in fields)),
                part.covariance[rows, last],
            )
            reference.append(part)
    assert len(results) == len(reference) == 4
    for got, want in zip(results, reference, strict=True):
        for name in ("t", "mask", "position", "rotation", "covariance"):
            assert torch.equal(getattr(got, name), getattr(want, name)), name
    assert float(totals["count"]) == sum(int(r.mask[:, 1:].sum()) for r in reference)


@pytest.mark.parametrize(
    ("chunk_windows", "stretch_s"),
    [(2, (3.5, 4.8)), (1, (3.5, 5.2))],  # across the boundary at 4 s; over the chunk 4-5 s
)
def test_stretch_across_a_boundary_is_one_gap_as_at_inference(chunk_windows, stretch_s):
    """IMU + NHC + GNSS, as the KITTI drive (no wheels: training chunks start with no wheel
    slip factor, run_piecewise carries it; 0.3 mm apart after this stretch with wheels)."""
    run = simulate_run(SimConfig(duration_s=8.0, imu_rate_hz=100.0), seed=4).sequence
    seq = fill_imu_stretch(dataclasses.replace(run, wheel=None), *stretch_s)
    batch = _batch([seq], ("gnss",))
    module = CovNetModule(CovNetConfig(pose_sources=("gnss",)), chunk_windows=chunk_windows)
    cfg = module.eskf_config(batch.sequence)
    # chunk-wise alternating scales of equal noise (exp(1e-300) == 1): run_piecewise cuts
    # its chunks at the training's windows
    alternating = torch.zeros(batch.windows, 7, dtype=torch.float64)
    alternating[(torch.arange(batch.windows) // chunk_windows) % 2 == 1] = 1e-300
    with torch.no_grad():
        _, results = module.run_chunks(batch, torch.zeros(1, batch.windows, 7))
        pieces = run_piecewise(batch.sequence, cfg, alternating, LENGTH, None)
    assert int(pieces.gap[0].sum()) > 0
    t_end = float(batch.sequence.imu.t[0, round(stretch_s[1] * 100)])
    assert t_end in [float(r.t[0, 0]) for r in results]  # a chunk starts at the stretch end
    assert len(results) == -(-batch.windows // chunk_windows) - (chunk_windows == 1)
    training = _chained(results)
    assert torch.equal(training["t"], pieces.t[0])
    for name in ("position", "velocity", "rotation", "covariance"):
        diff = (training[name] - getattr(pieces, name)[0]).abs().max()
        assert float(diff) < 1e-9, (name, float(diff))


def test_batch_boundary_moves_past_the_stretches_of_every_run():
    """Boundary at 2 s (chunks of 2 windows); run 0 filled over 1.5-2.5 s, run 1 over
    2.3-3.2 s: 2 s moves to 2.5 s (run 0's end), which lies in run 1's stretch, so on to
    3.2 s."""
    runs = [simulate_labelled_run(seed, 6.0) for seed in (5, 6)]
    runs = [fill_imu_stretch(runs[0], 1.5, 2.5), fill_imu_stretch(runs[1], 2.3, 3.2)]
    batch = _batch(runs)
    module = CovNetModule(CovNetConfig(), chunk_windows=2)
    with torch.no_grad():
        _, results = module.run_chunks(batch, torch.zeros(2, batch.windows, 7))
    imu_t = batch.sequence.imu.t
    end = 320  # the sample at 3.2 s
    assert len(results) == 3
    assert torch.equal(results[0].t[:, -1], imu_t[:, end])
    assert torch.equal(results[1].t[:, 0], imu_t[:, end])
    assert torch.equal(results[1].t[:, -1], imu_t[:, 4 * LENGTH])  # the next one stays
    assert bool(results[0].gap.any(1).all())  # both stretches filtered in the first chunk
    assert not bool(results[1].gap.any())
