"""The whole estimator on CUDA gives the CPU's answers (skipped without a GPU).

One 20-s simulated drive holding every stream the front end fuses (IMU with a 3-s dropout,
wheels with a slip episode, GNSS fixes and velocities, visual and LiDAR odometry under a
weather schedule, the source-fault detector on) runs on the CPU and on ``MSF_TEST_DEVICE``
(default ``cuda``): the front end, the front end fed piece by piece, both smoothers, the
shipped CovNet checkpoint's noise, a gradient through the filter, ``msf run --device`` and
the Lightning smoke fit with its accelerator on the device.
The CPU results are the reference; cuSOLVER / cuBLAS round differently from LAPACK, so
positions are compared to 1e-8 m (the back end's CUDA check measured 3.4e-9 m), gate
decisions exactly.

Measured on an H200 (torch 2.11 + CUDA 13.0, 2026-11-28): 10 passed with this file and
``tests/backend/test_backend_cuda.py``; smoothed positions 2.5e-10 m (full) and
0.8-1.6e-10 m (window) from the CPU's, marginal covariances within 5.7e-6 of
``sigma_i sigma_j`` (two runs; cuSOLVER's results vary a little from run to run). The
first run found the smoothers' graph built partly on the CPU (the IMU-gap noise, gravity,
the IMU noise, index and empty tensors) and the CovNet features read with numpy from
device tensors. The smoke fit's test was added after the device time was spent; the same
command (``--trainer.accelerator=gpu``) ran its epoch on the H200.

``MSF_TEST_DEVICE=cpu pytest tests/test_cuda_pipeline.py`` runs the same checks CPU
against CPU (to check the test itself on a machine without a GPU).
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import pytest
import torch

from msf_torch.backend import window as W
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.frontend.stream import EskfStream, concat_results, time_slice
from msf_torch.io.tum import read_tum
from msf_torch.learning.inference import learned_scales, load_learned, run_piecewise
from msf_torch.runner import RunOptions, run_batch, run_sequence

DEVICE = os.environ.get("MSF_TEST_DEVICE", "cuda")
CHECKPOINT = Path(__file__).resolve().parents[1] / "checkpoints" / "covnet_weather.pt"
KEYS = ("wheel", "gnss", "gnss_velocity", "pose:vo", "pose:lidar")

pytestmark = pytest.mark.skipif(
    DEVICE == "cuda" and not torch.cuda.is_available(), reason="needs CUDA"
)


@pytest.fixture(scope="module")
def drive(every_stream_drive):
    """The drive of ``tests/conftest.py`` and its filter settings."""
    return every_stream_drive


def _largest(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest absolute difference of two same-shape tensors, ``b`` brought to ``a``'s device;
    NaN where they are NaN in different places."""
    b = b.to(a.device)
    if not torch.equal(a.isnan(), b.isnan()):
        return float("nan")
    return float((a - b).nan_to_num().abs().max())


def test_front_end(drive):
    seq, cfg = drive
    with torch.no_grad():
        cpu = run_eskf(seq, cfg)
        dev = run_eskf(seq.to(DEVICE), cfg)
    assert dev.position.device.type == DEVICE
    assert bool(dev.gap[0].any()), "the dropout is an IMU gap"
    assert torch.equal(dev.t.cpu(), cpu.t)
    for key in KEYS:
        assert torch.equal(dev.accepted[key].cpu(), cpu.accepted[key]), key
    assert _largest(cpu.position, dev.position) < 1e-8
    assert _largest(cpu.velocity, dev.velocity) < 1e-8
    assert _largest(cpu.rotation, dev.rotation) < 1e-9
    torch.testing.assert_close(dev.covariance.cpu(), cpu.covariance, rtol=1e-6, atol=1e-12)


def test_pieces_on_the_device_equal_one_run(drive):
    seq, cfg = drive
    bounds = [0.0, 4.9, 9.5, 11.35, 16.0, 20.01]
    moved = seq.to(DEVICE)
    with torch.no_grad():
        whole = run_eskf(moved, cfg)
        stream = EskfStream(cfg, initial=initial_state(moved, cfg))
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            stream.push(time_slice(moved, a, b))
        joined = concat_results(stream.results)
    real = whole.t[0, whole.mask[0]]
    index = torch.searchsorted(joined.t[0], real)
    assert torch.equal(joined.t[0, index], real)
    for key in KEYS:
        assert int(joined.accepted[key].sum()) == int(whole.accepted[key].sum()), key
    # biases estimated: 1.2e-5 m measured on the CPU (test_stream.py), the chunk boundaries
    # re-linearise the bias states
    assert _largest(whole.position[0, whole.mask[0]], joined.position[0, index]) < 1e-4


@pytest.mark.parametrize("mode", ["full", "window"])
def test_smoothers(drive, mode):
    seq, cfg = drive
    smoother = W.SmootherConfig()
    outputs = {}
    for device in ("cpu", DEVICE):
        moved = seq.to(device)
        with torch.no_grad():
            front = run_eskf(moved, cfg)
            outputs[device] = W.smooth(moved, front, cfg, smoother, mode)
    cpu, dev = outputs["cpu"], outputs[DEVICE]
    assert [r.status for r in dev.lm] == [r.status for r in cpu.lm]
    assert dev.output.position.device.type == DEVICE
    position = _largest(cpu.output.position, dev.output.position)
    # the marginal covariances invert a Hessian whose bias rows carry 1e10 and more of
    # random-walk information: near-zero cross terms differ by percents between LAPACK and
    # cuSOLVER, so each entry is compared relative to its row and column's sigmas
    sigma = cpu.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
    scale = sigma[..., :, None] * sigma[..., None, :]
    correlation = _largest(cpu.covariance / scale, dev.covariance.cpu() / scale)
    print(f"{mode}: position {position:.2e} m, covariance / (sigma_i sigma_j) {correlation:.2e}")
    assert position < 1e-7
    assert correlation < 1e-4


def test_learned_noise(drive):
    seq, cfg = drive
    learned = load_learned(CHECKPOINT)
    runs = {}
    for device in ("cpu", DEVICE):
        moved = seq.to(device)
        model = dataclasses.replace(learned, model=learned.model.to(device))
        with torch.no_grad():
            scales = learned_scales(moved, model, cfg)
            result = run_piecewise(
                moved, cfg, scales.log_scales, scales.window_length, scales.pose_source
            )
        runs[device] = scales, result
    (cpu_scales, cpu), (dev_scales, dev) = runs["cpu"], runs[DEVICE]
    assert dev_scales.log_scales.device.type == DEVICE
    assert _largest(cpu_scales.log_scales, dev_scales.log_scales) < 1e-5
    assert _largest(cpu.position, dev.position) < 1e-6


def test_gradient_through_the_filter(drive):
    """d(position error) / d(wheel speed sigma, accelerometer density) over the first 6 s
    (the training path: the noise as tensors with gradients)."""
    seq, cfg = drive
    first = time_slice(seq, 0.0, 6.0)
    truth = seq.ground_truth
    grads = {}
    for device in ("cpu", DEVICE):
        moved = first.to(device)
        params = (
            torch.tensor(cfg.wheel_speed_sigma_mps, dtype=torch.float64, device=device),
            torch.tensor(cfg.accel_noise_density, dtype=torch.float64, device=device),
        )
        for p in params:
            p.requires_grad_(True)
        base = EskfNoise.from_config(cfg, device=device)
        noise = dataclasses.replace(
            base,
            imu=dataclasses.replace(base.imu, accel_noise_density=params[1]),
            wheel_speed_sigma=params[0],
        )
        result = run_eskf(moved, cfg, noise)
        index = torch.searchsorted(truth.t[0].to(device), result.t[0].clamp(max=6.0))
        error = result.position[0] - truth.position[0].to(device)[index]
        loss = (error.square().sum(-1) * result.mask[0]).sum()
        grads[device] = torch.stack(torch.autograd.grad(loss, params))
    assert bool(torch.isfinite(grads["cpu"]).all()) and float(grads["cpu"].abs().min()) > 0
    torch.testing.assert_close(grads[DEVICE].cpu(), grads["cpu"], rtol=1e-6, atol=0)


@pytest.mark.parametrize("batch", [False, True])
def test_msf_run_device(drive, tmp_path, batch):
    """``msf run --device`` (``RunOptions.device``): the estimator runs on the device, the
    results come back to the CPU and are written as the CPU run's, for one sequence (learned
    noise, full smoother) and for a batch of two (front end batched, then each smoothed)."""
    seq, cfg = drive
    other = dataclasses.replace(seq, names=["second"])
    trajectories = {}
    for device in ("cpu", DEVICE):
        out = tmp_path / device
        options = RunOptions(out_dir=out, plot=False, smooth="full", device=device)
        if batch:
            summary = run_batch([seq, other], cfg, options)
            files = [out / name / "trajectory.tum" for name in summary["names"]]
        else:
            options = dataclasses.replace(options, learned=load_learned(CHECKPOINT))
            summary = run_sequence(seq, cfg, options)
            files = [out / "trajectory.tum"]
        assert summary["device"] == str(torch.device(device))
        trajectories[device] = [read_tum(f) for f in files]
    for cpu, dev in zip(trajectories["cpu"], trajectories[DEVICE], strict=True):
        assert torch.equal(cpu.t, dev.t)
        assert _largest(cpu.position, dev.position) < 1e-6


def test_training_fit_on_the_device(smoke_fit):
    """``training/train.py fit`` with Lightning's accelerator on the device: the smoke
    config's one epoch (training and validation) with finite losses in its event files."""
    accelerator = "gpu" if DEVICE.startswith("cuda") else DEVICE
    done, events = smoke_fit(f"--trainer.accelerator={accelerator}", "--trainer.devices=1")
    assert done.returncode == 0, done.stderr[-4000:]
    for tag in ("train/loss", "val/loss"):
        values = [e.value for e in events.Scalars(tag)]
        assert values and all(math.isfinite(v) for v in values), tag
