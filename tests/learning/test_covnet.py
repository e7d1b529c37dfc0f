"""CovNet: shapes, bounds, gradients, size, speed, checkpoints, weather head, noise mapping.

References are independent of the code under test: bounds and sizes from the config's
numbers, scaled noise from Python-float arithmetic on the config values
(``variance = sigma^2 * exp(log_scale)``), checkpoints against the model that was saved.
"""

from __future__ import annotations

import ast
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.learning import (
    LOG_SCALE_SENSORS,
    CovNet,
    CovNetConfig,
    NoiseApplication,
    apply_fusion_weights,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    scaled_noise,
    scaled_pose_covariance,
)
from msf_torch.sim.wheeled import SimConfig, simulate_run

CFG = CovNetConfig()


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _inputs(batch: int, seed: int = 0, scale: float = 1.0, config: CovNetConfig = CFG):
    """Random inputs (imu, wheel, wheel_present, residual_stats, weather) of one batch."""
    gen = torch.Generator().manual_seed(seed)
    length, n_sources = config.window_length, len(config.pose_sources)
    imu = scale * torch.randn(batch, length, 6, generator=gen)
    imu[..., 5] += 9.81
    wheel = scale * torch.randn(batch, length, 2, generator=gen)
    present = torch.rand(batch, generator=gen) > 0.3
    stats = scale * torch.rand(batch, n_sources, 4, generator=gen)
    weather = torch.randint(0, config.unknown_weather + 1, (batch,), generator=gen)
    return imu, wheel, present, stats, weather


def _check_bounds(out, config: CovNetConfig, batch: int) -> None:
    n_sources, n_weather = len(config.pose_sources), len(config.weather_classes)
    assert out.log_scales.shape == (batch, len(LOG_SCALE_SENSORS))
    assert out.fusion_weights.shape == (batch, n_sources)
    assert out.weather_logits.shape == (batch, n_weather)
    for tensor in (out.log_scales, out.fusion_weights, out.weather_logits):
        assert bool(torch.isfinite(tensor).all())
    bounds = torch.tensor(config.log_scale_bounds)
    assert bool((out.log_scales.abs() <= bounds).all())
    low = 1.0 / (1.0 + math.exp(config.fusion_logit_bound)) - 1e-6  # float32 rounding
    assert bool((out.fusion_weights >= low).all() and (out.fusion_weights <= 1 - low).all())


@pytest.mark.parametrize("scale", [1.0, 1e6, 1e30])
def test_shapes_and_bounds_even_for_extreme_inputs(scale):
    config = CovNetConfig(log_scale_bounds=(3.0, 2.0, 1.0, 0.5, 0.25, 3.0, 1.5))
    torch.manual_seed(0)
    model = CovNet(config)
    with torch.no_grad():  # large weights saturate the heads
        for p in model.parameters():
            p.mul_(20.0)
    for sign in (1.0, -1.0):
        inputs = _inputs(64, seed=1, scale=sign * scale, config=config)
        _check_bounds(model(*inputs), config, 64)
    out = model(*_inputs(64, seed=1, scale=scale, config=config))
    # saturated: at least one output reaches its bound to float32 precision
    assert bool(((out.log_scales.abs() - torch.tensor(config.log_scale_bounds)).abs() < 1e-4).any())
    # wheel_present as (B, L) and weather None work too
    imu, wheel, _, stats, _ = _inputs(8, seed=2, config=config)
    present = torch.rand(8, config.window_length) > 0.5
    _check_bounds(model(imu, wheel, present, stats), config, 8)


def test_bad_shapes_raise_naming_the_input():
    model = CovNet()
    imu, wheel, present, stats, weather = _inputs(4)
    with pytest.raises(ValueError, match="imu"):
        model(imu[:, :50], wheel, present, stats)
    with pytest.raises(ValueError, match="residual_stats"):
        model(imu, wheel, present, stats[:, :2])
    with pytest.raises(ValueError, match="wheel_present"):
        model(imu, wheel, present[:2], stats)
    with pytest.raises(ValueError, match="weather"):
        model(imu, wheel, present, stats, weather + CFG.unknown_weather + 1)
    with pytest.raises(ValueError, match="pose_sources"):
        CovNetConfig(pose_sources=("gnss", "radar")).validate()


def test_gradient_reaches_every_parameter():
    torch.manual_seed(0)
    model = CovNet()
    imu, wheel, present, stats, weather = _inputs(32, seed=3)
    n_classes = len(CFG.weather_classes)
    weather[:n_classes] = torch.arange(n_classes)
    weather[n_classes : 2 * n_classes] = CFG.unknown_weather
    out = model(imu, wheel, present, stats, weather)
    loss = (out.log_scales**2).sum() + out.fusion_weights.sum() + out.weather_logits.square().sum()
    loss.backward()
    for name, param in model.named_parameters():
        assert param.grad is not None, name
        assert bool(torch.isfinite(param.grad).all()), name
        assert float(param.grad.abs().max()) > 0.0, name


def test_parameter_count_under_100k():
    count = sum(p.numel() for p in CovNet().parameters())
    assert count < 100_000, count


def test_cpu_throughput_at_least_10k_windows_per_second():
    """B = 4096 windows of L = 100 (1 s at 100 Hz), float32, best of 5, on one thread.

    One thread is a lower bound for any thread count and cannot be oversubscribed: with 2
    threads on 2 cores and another busy process, OpenMP's waiting threads cut throughput
    about 8x (60k -> 7.5k windows/s measured), 1 thread keeps ~60k.
    """
    torch.manual_seed(0)
    model = CovNet().eval()
    inputs = _inputs(4096, seed=4)
    best = math.inf
    with torch.inference_mode():
        model(*inputs)
        for _ in range(5):
            start = time.perf_counter()
            model(*inputs)
            best = min(best, time.perf_counter() - start)
    assert 4096 / best >= 10_000, f"{4096 / best:.0f} windows/s"


def test_checkpoint_round_trip_with_weights_only(tmp_path):
    config = CovNetConfig(
        window_length=40,
        channels=16,
        pose_sources=("gnss", "lidar"),
        weather_classes=("dry", "wet", "ice"),
        log_scale_bounds=(2.0, 2.0, 1.0, 1.0, 1.0, 0.5, 0.5),
    )
    torch.manual_seed(0)
    model = CovNet(config).eval()
    path = tmp_path / "covnet.pt"
    save_checkpoint(path, model)
    payload = torch.load(path, weights_only=True)
    assert payload["config"]["pose_sources"] == ["gnss", "lidar"]
    loaded = load_checkpoint(path)
    assert loaded.config == config
    assert not loaded.training
    inputs = _inputs(16, seed=5, config=config)
    with torch.no_grad():
        a, b = model(*inputs), loaded(*inputs)
    for field in dataclasses.fields(a):
        assert torch.equal(getattr(a, field.name), getattr(b, field.name)), field.name
    torch.save({"state_dict": model.state_dict()}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt"):
        load_checkpoint(tmp_path / "other.pt")


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("text.pt", b"hello, not a checkpoint\n"),
        ("empty.pt", b""),
        ("graph.g2o", b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"),
        ("scans.npz", None),  # a zip archive that is not torch's
    ],
)
def test_a_file_that_is_no_checkpoint_gets_a_clean_error(tmp_path, name, content):
    path = tmp_path / name
    if content is None:
        np.savez(path, a=np.zeros(3))
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not an msf_torch checkpoint (torch.load cannot read it")
    assert "Could this error message be improved" not in message and "\n" not in message


def test_residual_embedding_knows_which_source_is_bad():
    """Swap the VO and LiDAR residual statistics of a window (VO bad and LiDAR good, or
    the reverse: night against fog). With ``per_source`` pooling the log scales and the
    weather logits change; with the old ``mean`` pooling (the shared MLP runs before the
    source embedding is added) they cannot: the mean is the same for both orders."""
    imu, wheel, present, stats, _ = _inputs(8, seed=3)
    stats[:, 1] = torch.tensor([9.0, 30.0, 0.4, 0.2])  # vo: large NIS, many rejections
    stats[:, 2] = torch.tensor([1.0, 3.0, 0.0, 0.0])  # lidar: nominal
    swapped = stats[:, [0, 2, 1]]
    for pooling, differs in (("per_source", True), ("mean", False)):
        torch.manual_seed(0)
        model = CovNet(CovNetConfig(residual_pooling=pooling)).eval()
        with torch.no_grad():
            a = model(imu, wheel, present, stats)
            b = model(imu, wheel, present, swapped)
        gap = max(
            float((a.log_scales - b.log_scales).abs().max()),
            float((a.weather_logits - b.weather_logits).abs().max()),
        )
        assert (gap > 1e-4) == differs, (pooling, gap)


def test_checkpoints_without_the_pooling_key_load_as_mean_pooling():
    config = CovNetConfig(residual_pooling="mean").to_dict()
    del config["residual_pooling"]
    assert CovNetConfig.from_dict(config).residual_pooling == "mean"
    assert CovNetConfig().residual_pooling == "mean"
    with pytest.raises(ValueError, match="residual_pooling"):
        CovNetConfig(residual_pooling="max").validate()


def test_checkpoint_keeps_how_training_applied_the_scales(tmp_path):
    torch.manual_seed(0)
    model = CovNet(CovNetConfig()).eval()
    record = NoiseApplication(
        imu_rate_hz=200.0,
        chunk_windows=3,
        noise_granularity="run",
        innovation_features=False,
        gnss_outages_only=True,
        filter_settings={"gyro_noise_density": 5e-3, "gnss_sigma_m": [0.5, 0.5, 1.0]},
    )
    save_checkpoint(tmp_path / "a.pt", model, record)
    assert torch.load(tmp_path / "a.pt", weights_only=True)["application"] == {
        "imu_rate_hz": 200.0,
        "chunk_windows": 3,
        "noise_granularity": "run",
        "innovation_features": False,
        "gnss_outages_only": True,
        "filter_settings": {"gyro_noise_density": 5e-3, "gnss_sigma_m": [0.5, 0.5, 1.0]},
    }
    loaded, application = read_checkpoint(tmp_path / "a.pt")
    assert application == record and loaded.config == model.config

    # a file from before the record: training/configs/default.yaml's chunking, no rate
    payload = torch.load(tmp_path / "a.pt", weights_only=True)
    del payload["application"]
    torch.save(payload, tmp_path / "old.pt")
    _, application = read_checkpoint(tmp_path / "old.pt")
    assert application == NoiseApplication(None, 10, "chunk", True, False)

    payload["application"] = {"chunk_windows": 0}
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=r"bad\.pt.*chunk_windows must be >= 1"):
        read_checkpoint(tmp_path / "bad.pt")
    payload["application"] = {"imu_rate": 100.0}
    torch.save(payload, tmp_path / "typo.pt")
    with pytest.raises(ValueError, match=r"typo\.pt.*unknown NoiseApplication keys \['imu_rate'\]"):
        read_checkpoint(tmp_path / "typo.pt")


def test_weather_head_learns_a_separable_problem():
    """Class k has a gyro-x offset of 0.3 k rad/s; labels are withheld from the input."""
    torch.manual_seed(0)
    model = CovNet()
    n_classes = len(CFG.weather_classes)

    def batch(seed: int):
        imu, wheel, present, stats, _ = _inputs(256, seed=seed, scale=0.05)
        label = torch.arange(256) % n_classes
        imu[..., 0] += 0.3 * label[:, None]
        unknown = torch.full((256,), CFG.unknown_weather)
        return (imu, wheel, present, stats, unknown), label

    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    inputs, label = batch(10)
    for _ in range(40):
        loss = torch.nn.functional.cross_entropy(model(*inputs).weather_logits, label)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    test_inputs, test_label = batch(11)
    with torch.no_grad():
        accuracy = (model(*test_inputs).weather_logits.argmax(-1) == test_label).float().mean()
    assert float(accuracy) >= 0.95, float(accuracy)


def _sigmas(noise: EskfNoise) -> dict[str, torch.Tensor]:
    return {
        "gyro": noise.imu.gyro_noise_density,
        "accel": noise.imu.accel_noise_density,
        "gyro_bias": noise.imu.gyro_bias_rw_density,
        "accel_bias": noise.imu.accel_bias_rw_density,
        "wheel_speed": noise.wheel_speed_sigma,
        "wheel_lateral": noise.wheel_lateral_sigma,
        "wheel_yaw_rate": noise.wheel_yaw_rate_sigma,
        "nhc": noise.nhc_sigma,
        "zupt": noise.zupt_sigma,
        "gnss": noise.gnss_sigma_scale,
    }


def test_scaled_noise_is_base_variance_times_exp_log_scale():
    cfg = EskfConfig()
    log_scales = torch.tensor(
        [[0.5, -1.0, 2.0, 0.1, 0.2, -2.5, 1.25], [0.0, 3.0, -3.0, 0.0, 0.0, 0.75, -0.5]],
        dtype=torch.float64,
        requires_grad=True,
    )
    scaled = _sigmas(scaled_noise(EskfNoise.from_config(cfg), log_scales))
    column = {
        "gyro": 5,
        "accel": 6,
        "wheel_speed": 0,
        "wheel_lateral": 0,
        "wheel_yaw_rate": 0,
        "nhc": 1,
        "gnss": 2,
    }
    base = {
        "gyro": cfg.gyro_noise_density,
        "accel": cfg.accel_noise_density,
        "gyro_bias": cfg.gyro_bias_rw_density,
        "accel_bias": cfg.accel_bias_rw_density,
        "wheel_speed": cfg.wheel_speed_sigma_mps,
        "wheel_lateral": cfg.wheel_lateral_sigma_mps,
        "wheel_yaw_rate": cfg.wheel_yaw_rate_sigma_radps,
        "nhc": cfg.nhc_sigma_mps,
        "zupt": cfg.zupt_sigma_mps,
        "gnss": 1.0,
    }
    rows = log_scales.detach().tolist()
    for name, value in scaled.items():
        assert value.dtype == torch.float64, name
        if name in column:
            expected = [base[name] ** 2 * math.exp(row[column[name]]) for row in rows]
            torch.testing.assert_close(
                value.detach() ** 2, torch.tensor(expected, dtype=torch.float64), rtol=1e-14, atol=0
            )
        else:  # bias random walks and zero velocity are kept
            assert float(value) == base[name], name
    # d sigma / d log_scale = sigma / 2
    grad = torch.autograd.grad(scaled["nhc"].sum(), log_scales)[0]
    expected_grad = torch.zeros(2, 7, dtype=torch.float64)
    expected_grad[:, 1] = 0.5 * scaled["nhc"].detach()
    torch.testing.assert_close(grad, expected_grad, rtol=1e-14, atol=0)


def test_pose_covariance_and_fusion_weights():
    log_scales = torch.tensor([[0.0, 0.0, 0.5, 1.0, -1.0, 0.0, 0.0]], dtype=torch.float64)
    cov = torch.eye(6, dtype=torch.float64).expand(1, 3, 6, 6) * 0.01
    vo = scaled_pose_covariance(cov, log_scales, "vo")
    torch.testing.assert_close(vo, cov * math.exp(1.0), rtol=1e-15, atol=0)
    lidar = scaled_pose_covariance(cov, log_scales, "lidar")
    torch.testing.assert_close(lidar, cov * math.exp(-1.0), rtol=1e-15, atol=0)
    weights = torch.tensor([[0.5, 0.25, 1.0]], dtype=torch.float64)
    effective = apply_fusion_weights(log_scales, weights, ("gnss", "vo", "lidar"))
    expected = [0.0, 0.0, 0.5 + math.log(2.0), 1.0 + math.log(4.0), -1.0, 0.0, 0.0]
    torch.testing.assert_close(effective, torch.tensor([expected], dtype=torch.float64))


def test_gradient_reaches_the_network_through_the_filter():
    """A 2 s simulated run: trajectory loss -> run_eskf -> scaled_noise -> CovNet; the
    gradient w.r.t. each log-scale output (the head's bias) equals central differences."""
    run = simulate_run(SimConfig(duration_s=2.0), seed=90)
    cfg = EskfConfig(gate_probability=1.0, slip_detection=False)
    torch.manual_seed(0)
    model = CovNet().double()  # float64 for the finite difference
    inputs = _inputs(1, seed=6)[:4]

    def loss_of() -> torch.Tensor:
        out = model(*inputs)
        noise = scaled_noise(EskfNoise.from_config(cfg), out.log_scales)
        res = run_eskf(run.sequence, cfg, noise)
        idx = torch.round(res.t[0] * run.config.imu_rate_hz).long()
        return ((res.position[0] - run.truth.position[0, idx]) ** 2).sum()

    loss_of().backward()
    assert float(model.log_scale_head.weight.grad.abs().max()) > 0
    # per log-scale output: central differences through the head's bias
    bias = model.log_scale_head.bias
    grad = bias.grad.clone()
    numeric = torch.zeros_like(grad)
    step = 1e-5
    with torch.no_grad():
        for k in range(grad.numel()):
            bias[k] += step
            up = loss_of()
            bias[k] -= 2.0 * step
            down = loss_of()
            bias[k] += step
            numeric[k] = (up - down) / (2.0 * step)
    torch.testing.assert_close(grad, numeric, rtol=1e-5, atol=1e-7 * float(grad.abs().max()))


def test_frontend_does_not_import_learning():
    frontend = Path(__file__).resolve().parents[2] / "msf_torch" / "frontend"
    for path in frontend.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            assert not any(n.startswith("msf_torch.learning") for n in names), path


def test_decimate_imu_means_whole_groups() -> None:
    """``learning.inference.decimate_imu``: each sample the mean of ``factor`` real samples
    (numpy reshape as the reference), stamped at the group's first; a masked sample is left
    out before grouping (as the filter's windows count samples); the incomplete last group
    is dropped."""
    from msf_torch.learning.inference import decimate_imu
    from msf_torch.sim import SimConfig, simulate_run

    seq = simulate_run(SimConfig(duration_s=2.0, slip_episodes=0), 1).sequence
    imu = seq.imu
    mask = imu.mask.clone()
    mask[0, 7] = False
    decimated = decimate_imu(dataclasses.replace(seq, imu=dataclasses.replace(imu, mask=mask)), 3)
    kept = np.delete(np.arange(imu.t.shape[1]), 7)
    count = kept.size // 3
    groups = kept[: 3 * count].reshape(count, 3)
    expected = imu.gyro[0].numpy()[groups].mean(1)
    np.testing.assert_allclose(decimated.imu.gyro[0].numpy(), expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(decimated.imu.t[0].numpy(), imu.t[0].numpy()[groups[:, 0]])
    assert decimate_imu(seq, 1) is seq
