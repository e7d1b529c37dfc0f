"""``benchmarks/magnetometer.py``: a one-seed short run's JSON line (keys, finite figures);
the GTSAM peer's ``MagPoseFactorPose3`` zero at the truth for corrected noise-free readings
(our field convention is GTSAM's) and its 2-Hz graph; the compass yaw fed to
robot_localization; the clean / disturbed same-run check. Skips without the ``gtsam``
wheel."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

gtsam = pytest.importorskip("gtsam")

from benchmarks import magnetometer  # noqa: E402
from benchmarks.gnss_heading import ALL_METRICS, truth_yaw, yaw_of  # noqa: E402
from benchmarks.gnss_velocity import peer_inputs  # noqa: E402
from benchmarks.peers.gtsam_kitti import run_gtsam_kitti  # noqa: E402
from msf_torch.frontend.config import load_sequence_config  # noqa: E402
from msf_torch.sim import SimConfig, simulate_run  # noqa: E402

SHORT = ["--duration-s", "45", "--outage-after-s", "22", "--outage-s", "10"]


def _sim(sigma_uT: float = 0.3, **overrides) -> SimConfig:
    return SimConfig(
        duration_s=overrides.pop("duration_s", 30.0),
        magnetometer=True,
        magnetometer_sigma_uT=sigma_uT,
        magnetometer_declination_rad=magnetometer.DECLINATION_RAD,
        magnetometer_hard_iron_uT=magnetometer.HARD_IRON_UT,
        magnetometer_distortion=magnetometer.DISTORTION,
        **overrides,
    )


def test_smoke_run_json_line(capsys, one_torch_thread):
    assert magnetometer.main(["--seeds", "1", *SHORT]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["benchmark"] == "magnetometer"
    for key in ("inputs", "ours", "peer", "columns", "ratio", "wins", "accuracy", "runs"):
        assert key in record
    names = [
        *magnetometer.OURS,
        *magnetometer.PEERS,
        *(f"disturbed_{n}" for n in ("ours", "ours_no_nhc", "ours_wheels", "peer", "rl_peer")),
    ]
    assert set(record["columns"]) == set(names) == set(record["accuracy"])
    for name in names:
        for key in (*ALL_METRICS, "wall_s"):
            value = record["columns"][name][key]
            assert math.isfinite(value) and value > 0.0, (name, key)
    for name, value in record["ratio"].items():
        assert math.isfinite(value) and value > 0.0, name
    assert record["ratio"]["wall_ours_over_peer"] == pytest.approx(
        record["ours"]["wall_s"] / record["peer"]["wall_s"], rel=1e-5
    )
    assert set(record["wins"]) == {f"{a}_vs_{b}" for a, b in magnetometer.PAIRS}
    assert record["inputs"]["anomalies_disturbed"] == 4
    (row,) = record["runs"]
    # the magnetometer holds both estimators' yaw within 2 deg RMS on the clean run
    for name in ("ours", "ours_wheels", "peer", "rl_peer"):
        assert row[name]["yaw_rmse_deg"] < 2.0, name


def test_peer_mag_factor_zero_at_truth_and_level_initial_yaw():
    sim = _sim(sigma_uT=1e-9)
    run = simulate_run(sim, seed=3)
    seq = run.sequence
    cfg = load_sequence_config(seq.meta, **magnetometer.magnetometer_config(sim))
    t, field, sigma = magnetometer.fused_readings(seq, cfg)
    assert np.allclose(np.diff(t), 1.0 / cfg.magnetometer_rate_hz) and np.all(sigma == 1e-9)
    world = np.asarray(seq.meta["magnetometer"]["earth_field_world_uT"])
    truth_t = run.truth.t[0].numpy()
    rotation = run.truth.rotation[0, np.searchsorted(truth_t, t - 1e-9)].numpy()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    for r, f in zip(rotation, field, strict=True):
        scale = float(np.linalg.norm(world))
        factor = gtsam.MagPoseFactorPose3(0, f, scale, world / scale, np.zeros(3), noise)
        values = gtsam.Values()
        values.insert(0, gtsam.Pose3(gtsam.Rot3(r), np.zeros(3)))
        assert np.abs(factor.unwhitenedError(values)).max() < 1e-6
    # the peer's 2-Hz inputs: readings at every state, fixes on every other; its graph over
    # them (one batch) holds the yaw within 1 deg of the truth at every state
    outage_free = peer_inputs(seq, (math.inf, math.inf))
    kwargs, k = magnetometer.gtsam_mag_inputs(outage_free, seq, cfg)
    assert k == 2 and np.isfinite(kwargs["mag_field"]).all()
    assert np.isfinite(kwargs["gps_xyz"][::2]).all() and np.isnan(kwargs["gps_xyz"][1::2]).all()
    out = run_gtsam_kitti(**kwargs, first_gps_index=0, warmup_intervals=10**6, init_from_gps=True)
    assert out["mag_used"].all() and out["n_updates"] == 1
    err = np.angle(np.exp(1j * (yaw_of(out["filter_rotation"]) - truth_yaw(run, out["t"]))))
    assert np.degrees(np.abs(err).max()) < 1.0


def test_compass_yaw_tracks_the_truth():
    sim = _sim()
    run = simulate_run(sim, seed=4)
    seq = run.sequence
    cfg = load_sequence_config(seq.meta, **magnetometer.magnetometer_config(sim))
    compass = magnetometer.compass_yaw(seq, cfg)
    err = np.angle(np.exp(1j * (compass["heading_yaw"] - truth_yaw(run, compass["heading_t"]))))
    # the accelerometer's levelling errs while the robot accelerates: about 1-3 deg here
    assert np.degrees(np.median(np.abs(err))) < 3.0
    # variance sigma^2 / H^2 + floor^2: H = 48 cos(1.05) uT at level
    horizontal = sim.magnetometer_field_uT * math.cos(sim.magnetometer_inclination_rad)
    expected = (0.3 / horizontal) ** 2 + cfg.magnetometer_heading_floor_rad**2
    assert np.median(compass["heading_variance"]) == pytest.approx(expected, rel=0.05)


def test_same_but_magnetometer_check():
    sim = _sim(duration_s=20.0)
    clean = simulate_run(sim, seed=5).sequence
    disturbed = simulate_run(
        dataclasses.replace(sim, magnetometer_anomaly_count=4), seed=5
    ).sequence
    magnetometer.check_same_but_magnetometer(clean, disturbed)  # the simulator keeps them
    assert not torch.equal(clean.magnetometer.field, disturbed.magnetometer.field)
    moved = dataclasses.replace(
        disturbed, imu=disturbed.imu.map(lambda x: x + 1e-12 if x.is_floating_point() else x)
    )
    with pytest.raises(RuntimeError, match="imu"):
        magnetometer.check_same_but_magnetometer(clean, moved)
