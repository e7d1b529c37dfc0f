"""``msf run`` with a CovNet checkpoint: ``--checkpoint``, ``--no-learned``, bad files."""

from __future__ import annotations

import hashlib
import json

import pytest
import torch

from msf_torch.cli import main
from msf_torch.eval.outage import split_gnss_outage
from msf_torch.frontend.config import config_for_sequence, load_config
from msf_torch.frontend.eskf import EskfNoise, run_eskf
from msf_torch.io import load_sequence
from msf_torch.io.native import write_native
from msf_torch.io.tum import write_tum
from msf_torch.learning import (
    LOG_SCALE_SENSORS,
    CovNet,
    CovNetConfig,
    NoiseApplication,
    apply_fusion_weights,
    read_checkpoint,
    save_checkpoint,
    scaled_noise,
)
from msf_torch.learning.data import simulate_labelled_run
from msf_torch.learning.features import pose_source_of
from msf_torch.learning.inference import run_piecewise

SCALES = (0.8, -0.6, 1.2, 0.3, -0.9, 0.5, -0.4)
"""Pre-bound log scales the test network outputs for every window."""


@pytest.fixture(scope="module")
def weather_run(tmp_path_factory):
    """A 6 s labelled weather run with VO and LiDAR odometry sources, as a native file."""
    folder = tmp_path_factory.mktemp("learned")
    return write_native(simulate_labelled_run(3, 6.0), folder / "run.npz")


@pytest.fixture(scope="module")
def constant_checkpoint(tmp_path_factory):
    """A small random-init CovNet whose heads are set to constant outputs (SCALES)."""
    torch.manual_seed(0)
    net = CovNet(CovNetConfig(window_length=50, channels=4, embedding=4, hidden=8))
    with torch.no_grad():
        net.log_scale_head.weight.zero_()
        net.log_scale_head.bias.copy_(torch.tensor(SCALES))
        net.fusion_head[-1].weight.zero_()
        net.fusion_head[-1].bias.fill_(2.0)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, net)
    return path, net


def _constant_scales(net: CovNet) -> torch.Tensor:
    """(7,) the effective log scales of the constant network: bounded heads, fusion weights
    folded in."""
    bound = torch.tensor(net.config.log_scale_bounds)
    raw = bound * torch.tanh(torch.tensor(SCALES) / bound)
    weight = torch.sigmoid(6.0 * torch.tanh(torch.tensor(2.0) / 6.0))
    return apply_fusion_weights(
        raw[None], weight.expand(1, len(net.config.pose_sources)), net.config.pose_sources
    )[0].double()


def _run(args, capsys):
    code = main(["run", *map(str, args), "--no-plot", "--progress", "off"])
    captured = capsys.readouterr()
    return code, captured


def _cfg(seq):
    return config_for_sequence(load_config(None), seq.meta, set())


def test_checkpoint_sets_noise_as_the_scales_say(
    weather_run, constant_checkpoint, tmp_path, capsys
):
    path, net = constant_checkpoint
    code, captured = _run([weather_run, "--out", tmp_path, "--checkpoint", path], capsys)
    assert code == 0, captured.err
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["noise"] == "learned"
    learned = summary["learned"]
    assert learned["checkpoint"] == str(path)
    assert learned["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert learned["weather_from_labels"] is True
    assert set(learned["inferred_weather"]) == set(net.config.weather_classes)
    expected = _constant_scales(net)
    for sensor, value in zip(LOG_SCALE_SENSORS, expected, strict=True):
        assert learned["mean_log_scales"][sensor] == pytest.approx(float(value), abs=1e-4)

    # the same filter, run directly with the scaled noise (VO and LiDAR odometry included)
    seq = load_sequence(weather_run)
    assert seq.poses is None and set(seq.pose_sources) == {"vo", "lidar"}
    cfg = _cfg(seq)
    base = EskfNoise.from_config(cfg)
    with torch.no_grad():
        direct = run_eskf(seq, cfg, scaled_noise(base, expected))
    write_tum(direct.trajectory().select(0).compact(), tmp_path / "direct.tum")
    assert (tmp_path / "trajectory.tum").read_text() == (tmp_path / "direct.tum").read_text()


@pytest.mark.parametrize("trained_hz", [200.0, 104.0, 50.0, 40.0])
def test_checkpoint_trained_at_another_imu_rate(
    weather_run, constant_checkpoint, tmp_path, capsys, trained_hz
):
    """The run's IMU is at 100 Hz: a 104 Hz network takes it as it is (within 5 %), a
    50 Hz one its pairs averaged (windows of twice the samples); 200 Hz (slower than the
    network) and 40 Hz (not a whole multiple) are refused."""
    _, net = constant_checkpoint
    path = tmp_path / "rate.pt"
    save_checkpoint(path, net, NoiseApplication(imu_rate_hz=trained_hz))
    code, captured = _run([weather_run, "--out", tmp_path / "o", "--checkpoint", path], capsys)
    if trained_hz in (104.0, 50.0):  # within IMU_RATE_TOLERANCE (5 %) of 100 Hz / 2 x 50 Hz
        assert code == 0, captured.err
        learned = json.loads(captured.out.strip().splitlines()[-1])["learned"]
        assert learned["trained_imu_rate_hz"] == trained_hz
        factor = 2 if trained_hz == 50.0 else 1
        assert learned["imu_decimation"] == factor
        assert learned["window_length"] == factor * net.config.window_length
        return
    assert code == 2
    length = net.config.window_length
    spans = f"{length / trained_hz:.3g} s there, {length / 100.0:.3g} s here"
    for part in ("'run'", "100 Hz", f"{trained_hz:.6g} Hz", spans, "--no-learned"):
        assert part in captured.err, part
    assert not (tmp_path / "o" / "trajectory.tum").exists()


def test_outage_only_checkpoint_keeps_the_configured_noise_where_fixes_are(
    weather_run, constant_checkpoint, tmp_path, capsys
):
    _, net = constant_checkpoint
    path = tmp_path / "outage.pt"
    record = NoiseApplication(imu_rate_hz=100.0, chunk_windows=2, gnss_outages_only=True)
    save_checkpoint(path, net, record)
    out = tmp_path / "o"
    code, captured = _run(
        [weather_run, "--out", out, "--checkpoint", path, "--gnss-outage", "1.5:3.5"], capsys
    )
    assert code == 0, captured.err
    learned = json.loads(captured.out.strip().splitlines()[-1])["learned"]
    assert learned["gnss_outages_only"] is True and learned["chunk_windows"] == 2

    # by hand: chunks of 2 windows x 50 samples (1 s at 100 Hz, end sample included); a
    # chunk holding a fix keeps the configured noise (log scale 0)
    seq, _ = split_gnss_outage(load_sequence(weather_run), 1.5, 3.5)
    imu_t = seq.imu.t[0].tolist()
    fixes = seq.gnss.t[0, seq.gnss.mask[0]].tolist()
    scales = torch.zeros(12, 7, dtype=torch.float64)
    free_chunks = 0
    for chunk in range(6):
        start, end = imu_t[100 * chunk], imu_t[100 * chunk + 100]
        if not any(start <= f <= end for f in fixes):
            scales[2 * chunk : 2 * chunk + 2] = _constant_scales(net)
            free_chunks += 1
    assert free_chunks == 1  # the only whole second without a fix: [2, 3] s
    with torch.no_grad():
        direct = run_piecewise(seq, _cfg(seq), scales, 50, pose_source_of(seq))
    write_tum(direct.trajectory().select(0).compact(), tmp_path / "direct.tum")
    assert (out / "trajectory.tum").read_text() == (tmp_path / "direct.tum").read_text()


def test_no_learned_is_the_plain_filter(weather_run, tmp_path, capsys):
    code, captured = _run([weather_run, "--out", tmp_path, "--no-learned"], capsys)
    assert code == 0, captured.err
    assert json.loads(captured.out.strip().splitlines()[-1])["noise"] == "config"
    seq = load_sequence(weather_run)
    with torch.no_grad():
        plain = run_eskf(seq, _cfg(seq))
    write_tum(plain.trajectory().select(0).compact(), tmp_path / "plain.tum")
    assert (tmp_path / "trajectory.tum").read_bytes() == (tmp_path / "plain.tum").read_bytes()


def test_piecewise_chunks_cover_the_run(weather_run):
    seq = load_sequence(weather_run)
    cfg = _cfg(seq)
    scales = torch.zeros(6, 7, dtype=torch.float64)
    scales[3:, LOG_SCALE_SENSORS.index("gnss")] = 2.0
    with torch.no_grad():
        plain = run_eskf(seq, cfg)
        pieces = run_piecewise(seq, cfg, scales, 100, "lidar")
    assert torch.equal(pieces.t, plain.t[:, plain.mask[0]])
    same = pieces.t[0] <= float(seq.imu.t[0, 300])
    assert torch.equal(pieces.position[0, same], plain.position[0, same])
    assert not torch.equal(pieces.covariance[0, ~same], plain.covariance[0, ~same])


@pytest.mark.parametrize("kind", ["missing", "garbage", "not_covnet"])
def test_bad_checkpoint_names_the_file(weather_run, tmp_path, capsys, kind):
    path = tmp_path / f"{kind}.pt"
    if kind == "garbage":
        path.write_bytes(b"not a torch file")
    elif kind == "not_covnet":
        torch.save({"weights": torch.zeros(3)}, path)
    code, captured = _run([weather_run, "--out", tmp_path / "o", "--checkpoint", path], capsys)
    assert code == 2
    assert str(path) in captured.err and "checkpoint" in captured.err


def test_filter_settings_of_the_training_are_checked(
    weather_run, constant_checkpoint, tmp_path, capsys
):
    """The checkpoint records the front-end values its training's eskf_config set; a run
    whose --config sets others (or none) is warned, naming each key, since the learned
    scales multiply those values; the same settings pass quietly."""
    _, net = constant_checkpoint
    path = tmp_path / "robot.pt"
    trained = {"gyro_noise_density": 5.0e-3, "nhc": "on"}
    save_checkpoint(path, net, NoiseApplication(imu_rate_hz=100.0, filter_settings=trained))
    assert read_checkpoint(path)[1].filter_settings == trained
    run = [weather_run, "--out", tmp_path / "o", "--checkpoint", path]
    code, captured = _run(run, capsys)
    assert code == 0, captured.err
    warning = next(line for line in captured.err.splitlines() if "other filter settings" in line)
    assert "gyro_noise_density: trained with 0.005, this run 9.9e-05" in warning
    assert "nhc: trained with 'on', this run 'auto'" in warning
    same = tmp_path / "robot.yaml"
    same.write_text("gyro_noise_density: 5.0e-3\nnhc: on\n")
    code, captured = _run([*run, "--config", same], capsys)
    assert code == 0 and "other filter settings" not in captured.err
