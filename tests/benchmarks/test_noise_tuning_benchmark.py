"""``benchmarks/noise_tuning.py``: a tiny run's JSON line (keys, finite figures, counts);
the labelled search's batched candidates score as separate filter runs do; the mis-set and
true-noise configs."""

from __future__ import annotations

import json
import math

import pytest
import torch

from benchmarks import noise_tuning
from msf_torch.frontend.config import load_sequence_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.types import batch_sequences

TINY = [
    "--train", "1", "--test", "2", "--duration-s", "20", "--outage-s", "4", "--slips", "1",
    "--starts", "mis_set", "--max-evaluations", "1", "--piece-s", "10", "--burn-in-s", "2",
    "--grid-points", "1", "--sweeps", "1",
]  # fmt: skip


def test_tiny_run_json_line(capsys, one_torch_thread):
    assert noise_tuning.main(TINY) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["benchmark"] == "noise_tuning"
    for key in ("inputs", "ours", "peer", "ratio", "starts", "machine", "wall_s_total"):
        assert key in record
    assert record["inputs"]["train_seeds"] == [7000]
    assert record["inputs"]["test_seeds"] == [7001, 7002]
    block = record["starts"]["mis_set"]
    assert set(block["columns"]) == set(noise_tuning.COLUMNS)
    for column, row in block["columns"].items():
        for metric in (*noise_tuning.METRICS, "anees_share", "anees_median"):
            assert math.isfinite(row[metric]) and row[metric] >= 0.0, (column, metric)
        assert len(block["per_run"][column]["ate_rmse_m"]) == 2
    assert set(block["wins"]) == {"ours_vs_start", "ours_vs_labelled", "ours_vs_true_noise"}
    for counts in block["wins"].values():
        assert all(0 <= n <= 2 for n in counts.values())
    names = list(block["ours"]["parameters"])
    assert names == list(block["labelled"]["multipliers"])
    # one sweep of a 3-point grid: the start, then two new values per parameter
    assert block["labelled"]["filter_runs"] == 1 + 2 * len(names)
    assert block["labelled"]["batched_calls"] == 1 + len(names)
    for name, ratio in block["labelled"]["multipliers"].items():
        assert any(math.isclose(ratio, 3.0**k, rel_tol=1e-5) for k in (-1, 0, 1)), name
    assert record["ratio"]["tuning_wall_ours_over_labelled"] == pytest.approx(
        block["ours"]["wall_s"] / block["labelled"]["wall_s"], rel=1e-5
    )
    # the mis-set config's true values: gyro /10, accel x5, GNSS scale x1 / 0.3
    truth = block["true_over_start"]
    assert truth["gyro_noise_density"] == pytest.approx(0.1)
    assert truth["accel_noise_density"] == pytest.approx(5.0)
    assert truth["gnss_sigma_scale"] == pytest.approx(1.0 / 0.3, rel=1e-5)
    assert truth["wheel_speed_sigma_mps"] == pytest.approx(1.0)


def test_batched_candidates_match_separate_runs(one_torch_thread):
    runs = noise_tuning.simulate([11, 12], duration_s=15.0, outage_s=3.0, slips=0)
    cfg = load_sequence_config(runs[0].sequence.meta)
    configs = [
        cfg,
        noise_tuning.scaled(cfg, ["gyro_noise_density", "gnss_sigma_scale"], (1.1, -0.7)),
    ]
    batched = noise_tuning.candidates_ate(configs, runs)
    batch = batch_sequences([r.sequence for r in runs])
    for config, value in zip(configs, batched, strict=True):
        with torch.no_grad():
            alone = noise_tuning.position_rmse(run_eskf(batch, config), runs)
        assert value == pytest.approx(sum(alone) / len(alone), rel=1e-9, abs=1e-12)
    assert batched[0] != pytest.approx(batched[1], rel=1e-6)  # the noise did differ


def test_mis_set_and_true_noise_configs():
    runs = noise_tuning.simulate([13], duration_s=10.0, outage_s=2.0, slips=0)
    meta = runs[0].sequence.meta
    cfg = load_sequence_config(meta)
    wrong = noise_tuning.mis_set(cfg, 10.0, 0.2, 5.0, 0.3)
    assert wrong.gyro_noise_density == pytest.approx(10.0 * cfg.gyro_noise_density)
    assert wrong.accel_noise_density == pytest.approx(0.2 * cfg.accel_noise_density)
    assert wrong.wheel_lateral_sigma_mps == pytest.approx(5.0 * cfg.wheel_lateral_sigma_mps)
    assert wrong.gnss_sigma_scale == 0.3
    back = noise_tuning.true_noise(wrong, meta)
    assert back.gyro_noise_density == meta["sensor"]["imu_noise"]["gyro_noise_density"]
    assert back.gnss_sigma_scale == 1.0
    assert back.wheel_speed_sigma_mps == wrong.wheel_speed_sigma_mps  # no true wheel sigma
    assert noise_tuning.true_noise(cfg, meta) == cfg
