"""No tensor of the estimator is made on torch's default device.

The CUDA check (``test_cuda_pipeline.py``) runs only where a GPU is; its first run found
factory calls without ``device=`` in the smoothers and the CovNet features, which put CPU
tensors into CUDA work. This is its CPU stand-in for CI: the inputs are made on the CPU,
then the pipeline runs with torch's default device set to ``meta`` (tensors without data).
A tensor made without naming a device becomes a meta tensor, which either stops the run
(mixing it with CPU data, or reading it with numpy) or leaks into the results. Every
result must equal the normal run's bit for bit and lie on the CPU.

The drive (``every_stream_drive`` in ``tests/conftest.py``) holds every stream the front
end fuses and an IMU dropout; the front end, the front end fed piece by piece, both
smoothers and the shipped CovNet checkpoint's noise are checked.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

from msf_torch.backend import window as W
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.stream import EskfStream, concat_results, time_slice
from msf_torch.learning.inference import learned_scales, load_learned, run_piecewise
from msf_torch.runner import RunOptions, run_batch, run_sequence

CHECKPOINT = Path(__file__).resolve().parents[1] / "checkpoints" / "covnet_weather.pt"


def _twice(run: Callable[[], Any]) -> tuple[Any, Any]:
    """``run()`` as it is, then with the default device ``meta``."""
    with torch.no_grad():
        normal = run()
        with torch.device("meta"):
            guarded = run()
    return normal, guarded


def _same(normal: torch.Tensor, guarded: torch.Tensor) -> None:
    assert guarded.device.type == "cpu"
    assert torch.equal(normal.isnan(), guarded.isnan())
    assert torch.equal(normal.nan_to_num(), guarded.nan_to_num())


def test_front_end_and_pieces(every_stream_drive):
    seq, cfg = every_stream_drive

    def pieces():
        stream = EskfStream(cfg, initial=initial_state(seq, cfg))
        for a, b in ((0.0, 4.9), (4.9, 11.35), (11.35, 20.01)):
            stream.push(time_slice(seq, a, b))
        return concat_results(stream.results)

    for run in (lambda: run_eskf(seq, cfg), pieces):
        normal, guarded = _twice(run)
        for field in ("position", "velocity", "rotation", "covariance"):
            _same(getattr(normal, field), getattr(guarded, field))


@pytest.mark.parametrize("mode", ["full", "window"])
def test_smoothers(every_stream_drive, mode):
    seq, cfg = every_stream_drive
    with torch.no_grad():
        front = run_eskf(seq, cfg)
    normal, guarded = _twice(lambda: W.smooth(seq, front, cfg, W.SmootherConfig(), mode))
    _same(normal.output.position, guarded.output.position)
    _same(normal.covariance, guarded.covariance)


def test_learned_noise(every_stream_drive):
    seq, cfg = every_stream_drive
    learned = load_learned(CHECKPOINT)

    def run():
        scales = learned_scales(seq, learned, cfg)
        result = run_piecewise(
            seq, cfg, scales.log_scales, scales.window_length, scales.pose_source
        )
        return scales, result

    (normal_scales, normal), (guarded_scales, guarded) = _twice(run)
    _same(normal_scales.log_scales, guarded_scales.log_scales)
    _same(normal.position, guarded.position)


@pytest.mark.parametrize(("batch", "smooth"), [(False, None), (False, "full"), (True, "full")])
def test_msf_run_writes_the_same_files(every_stream_drive, tmp_path, batch, smooth):
    """``runner.run_sequence`` and ``run_batch`` (``msf run`` with one or two sequences):
    the estimator's copy of the runs and its results come back to the CPU
    (``types.move_to``) to be scored and written."""
    seq, cfg = every_stream_drive
    written = {}
    for guarded in (False, True):
        out = tmp_path / ("meta" if guarded else "normal")
        options = RunOptions(out_dir=out, plot=False, smooth=smooth)
        with torch.device("meta") if guarded else contextlib.nullcontext():
            if batch:
                other = dataclasses.replace(seq, names=["second"])
                summary = run_batch([seq, other], cfg, options)
                files = [out / name / "trajectory.tum" for name in summary["names"]]
            else:
                summary = run_sequence(seq, cfg, options)
                files = [out / "trajectory.tum"]
        for timing in ("wall_s", "realtime_factor", "frontend_wall_s", "imu_samples_per_s"):
            summary.pop(timing, None)
        for entry in (summary.get("smoother", {}), *summary.get("runs", [])):
            entry.pop("wall_s", None)
        summary.pop("smoother_wall_s", None)
        summary.pop("out", None)
        written[guarded] = summary, [f.read_text() for f in files]
    assert written[True] == written[False]
    assert written[True][0]["device"] == "cpu"


def test_pose_graph_and_visual_inertial_window():
    """``optimize_pose_graph`` on a GTSAM example graph and ``solve_vio`` on a simulated
    visual-inertial run (the window BA with landmarks and the Schur complement)."""
    from msf_torch.backend.lm import LMConfig
    from msf_torch.backend.posegraph import optimize_pose_graph
    from msf_torch.backend.vio import VioConfig, solve_vio
    from msf_torch.io import gtsam_pose_graph_path, read_pose_graph
    from tests.backend.test_vio_window import _simulate

    graph = read_pose_graph(str(gtsam_pose_graph_path("pose3Localizationexample.txt")))
    normal, guarded = _twice(lambda: optimize_pose_graph(graph))
    assert guarded.final_cost == normal.final_cost
    _same(normal.graph.rotations, guarded.graph.rotations)
    _same(normal.graph.positions, guarded.graph.positions)
    data, _, _ = _simulate()
    growth = LMConfig(max_iterations=5, relative_tolerance=1e-6, eliminate="landmark")
    config = VioConfig(keyframe_stride=1, rest_duration=0.4, window=10, growth_lm=growth)
    normal, guarded = _twice(lambda: solve_vio(data, config))
    _same(normal.residual, guarded.residual)


def test_training_step():
    """One loss and backward pass of ``CovNetModule`` (the differentiable filter in chunks,
    the NLL term, the weather head)."""
    from msf_torch.learning import CovNetConfig
    from msf_torch.learning.data import collate_runs, run_features, simulate_labelled_run
    from msf_torch.learning.module import CovNetModule

    seq = simulate_labelled_run(7, 6.0)
    weather = ("sunny", "rain", "fog", "night", "snow")
    batch = collate_runs([(seq, run_features(seq, 100, ("gnss", "vo", "lidar"), weather))], 100)
    torch.manual_seed(0)
    module = CovNetModule(CovNetConfig(), chunk_windows=3)

    def step() -> tuple[torch.Tensor, list[torch.Tensor]]:
        module.zero_grad()
        with torch.enable_grad():
            loss = module._losses(batch)[0]["loss"]
            loss.backward()
        return loss.detach(), [p.grad.clone() for p in module.parameters() if p.grad is not None]

    (normal_loss, normal_grads), (guarded_loss, guarded_grads) = _twice(step)
    _same(normal_loss, guarded_loss)
    assert len(normal_grads) == len(guarded_grads) > 0
    for a, b in zip(normal_grads, guarded_grads, strict=True):
        _same(a, b)
