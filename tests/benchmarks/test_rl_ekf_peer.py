"""The robot_localization EKF peer (``benchmarks/peers/rl_ekf.py``) and its benchmark
(``benchmarks/robot_localization.py``): the predict Jacobian against finite differences,
a noise-free straight drive tracked from the node's default zero start, a yaw-only
heading input (``imu1``) pulling a wrong yaw to truth (also across +-pi), and the
benchmark's smoke run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks import robot_localization
from benchmarks.peers.rl_ekf import STATE_SIZE, run_rl_ekf, transfer_jacobian, transfer_matrix


@pytest.mark.parametrize("seed", range(5))
def test_predict_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(seed)
    state = rng.normal(size=STATE_SIZE)
    state[3:6] = rng.uniform(-1.2, 1.2, 3)  # roll, pitch, yaw away from the pitch singularity
    dt = rng.uniform(0.005, 0.5)
    step = 1e-6
    numeric = np.zeros((STATE_SIZE, STATE_SIZE))
    for i in range(STATE_SIZE):
        e = np.zeros(STATE_SIZE)
        e[i] = step
        plus = transfer_matrix(state + e, dt) @ (state + e)
        minus = transfer_matrix(state - e, dt) @ (state - e)
        numeric[:, i] = (plus - minus) / (2.0 * step)
    np.testing.assert_allclose(transfer_jacobian(state, dt), numeric, rtol=0.0, atol=1e-8)


def _straight_drive(speed: float, heading: float, g: float, **options):
    """1.5 m/s along ``heading``, level, exact IMU / wheels / GNSS, through ``run_rl_ekf``."""
    track = 0.5
    imu_t = np.arange(0.0, 40.0 + 1e-9, 0.01)
    wheel_t = np.arange(0.04, 40.0 + 1e-9, 0.04)
    gnss_t = np.arange(0.0, 40.0 + 1e-9, 1.0)
    direction = np.array([math.cos(heading), math.sin(heading), 0.0])
    return run_rl_ekf(
        imu_t=imu_t,
        imu_gyro=np.zeros((imu_t.size, 3)),
        imu_accel=np.tile([0.0, 0.0, g], (imu_t.size, 1)),
        gyro_variance=np.full(3, 1e-6),
        accel_variance=np.full(3, 1e-4),
        wheel_t=wheel_t,
        wheel_left=np.full(wheel_t.size, speed),
        wheel_right=np.full(wheel_t.size, speed),
        wheel_track_m=track,
        wheel_twist_variance=np.full(4, 1e-4),
        gnss_t=gnss_t,
        gnss_xyz=gnss_t[:, None] * speed * direction,
        gnss_sigma=np.full(3, 0.05),
        gravity=g,
        **options,
    ), direction


def test_straight_drive_tracked_from_default_start():
    """From the node's zero start (heading 0) the filter must find the 0.6-rad heading of a
    straight drive and track the position."""
    speed, heading, g = 1.5, 0.6, 9.80665
    out, direction = _straight_drive(speed, heading, g)
    truth = out["t"][:, None] * speed * direction
    err = np.linalg.norm(out["position"] - truth, axis=1)
    late = out["t"] >= 20.0
    assert np.all(np.isfinite(out["position"]))
    assert err[late].max() < 0.05, err[late].max()
    assert abs(out["rpy"][-1, 2] - heading) < 1e-3
    assert out["rejected"] == 0


def test_ahrs_orientation_is_fused_first():
    """An AHRS's roll, pitch, yaw (``imu_rpy``) enter as ``imu0`` orientation: with the true
    heading given at every IMU sample the filter's yaw holds it from the first stamp."""
    speed, heading, g = 1.5, 0.6, 9.80665
    n = 4001
    rpy = np.tile([0.0, 0.0, heading], (n, 1))
    out, _ = _straight_drive(speed, heading, g, imu_rpy=rpy, rpy_variance=np.full(3, 1e-6))
    assert np.abs(out["rpy"][:, 2] - heading).max() < 1e-3
    with pytest.raises(ValueError, match="imu_rpy"):
        _straight_drive(speed, heading, g, imu_rpy=rpy[:-1], rpy_variance=np.full(3, 1e-6))


def test_smoke_run_json_line(capsys, one_torch_thread):
    argv = ["--seeds", "2", "--tune-seeds", "1", "--q-scales", "1", "--q-attitude-scales", "1"]
    argv += ["--duration-s", "24", "--outage-after-s", "10", "--outage-s", "6", "--slip", "1"]
    assert robot_localization.main(argv) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["benchmark"] == "robot_localization"
    for key in ("inputs", "ours", "peer", "columns", "ratio", "wins_ours", "accuracy", "runs"):
        assert key in record
    assert record["inputs"]["seeds"] == [300, 301]
    best = record["inputs"]["tuning"]["best"]
    assert (
        best["scale"] == best["attitude_scale"] == 1.0
        and len(record["inputs"]["tuning"]["grid"]) == 2
    )
    assert set(record["columns"]) == {
        "ours",
        *robot_localization.PEERS,
        *robot_localization.HEADING_COLUMNS,
    }
    assert set(record["wins_ours_heading"]["peer_heading"]) == set(robot_localization.METRICS)
    assert record["ratio"]["rmse_ours_heading_over_peer_heading"] > 0.0
    for name, figures in record["accuracy"].items():
        for metric in robot_localization.METRICS:
            assert math.isfinite(figures[metric]) and figures[metric] > 0.0, (name, metric)
    assert "wall_s_numpy" in record["peer"] and "wall_ours_over_peer" not in record["ratio"]
    for row in record["runs"]:
        start, end = row["outage_s"]
        assert 10.0 <= start and end - start == pytest.approx(6.0)


def _turning_drive(yaw0: float, yaw_rate: float, start_yaw: float, **options):
    """1.5 m/s with a constant yaw rate (rad/s) from yaw ``yaw0``, level, exact IMU (the
    centripetal acceleration included) / wheels / GNSS, the peer started at the true
    position and speed with yaw ``start_yaw``; returns the output and the true yaw at its
    stamps."""
    speed, track, g = 1.5, 0.5, 9.80665
    imu_t = np.arange(0.0, 30.0 + 1e-9, 0.01)
    wheel_t = np.arange(0.04, 30.0 + 1e-9, 0.04)
    gnss_t = np.arange(0.0, 30.0 + 1e-9, 1.0)
    radius = speed / yaw_rate
    yaw = yaw0 + yaw_rate * gnss_t
    east = radius * (np.sin(yaw) - math.sin(yaw0))
    north = -radius * (np.cos(yaw) - math.cos(yaw0))
    gnss_xyz = np.stack((east, north, np.zeros_like(yaw)), -1)
    start = np.zeros(STATE_SIZE)
    start[5], start[6], start[11] = start_yaw, speed, yaw_rate
    out = run_rl_ekf(
        imu_t=imu_t,
        imu_gyro=np.tile([0.0, 0.0, yaw_rate], (imu_t.size, 1)),
        imu_accel=np.tile([0.0, speed * yaw_rate, g], (imu_t.size, 1)),
        gyro_variance=np.full(3, 1e-6),
        accel_variance=np.full(3, 1e-4),
        wheel_t=wheel_t,
        wheel_left=np.full(wheel_t.size, speed - 0.5 * track * yaw_rate),
        wheel_right=np.full(wheel_t.size, speed + 0.5 * track * yaw_rate),
        wheel_track_m=track,
        wheel_twist_variance=np.full(4, 1e-4),
        gnss_t=gnss_t,
        gnss_xyz=gnss_xyz,
        gnss_sigma=np.full(3, 0.5),
        gravity=g,
        initial_state=start,
        **options,
    )
    return out, yaw0 + yaw_rate * out["t"]


def _yaw_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Wrapped estimate - truth, rad."""
    return (estimate - truth + math.pi) % (2.0 * math.pi) - math.pi


def test_yaw_only_heading_pulls_a_wrong_yaw_to_truth():
    """A dual-antenna heading fused as a yaw-only input (``imu1``), at its own stamps off the
    IMU's grid: the peer started 0.5 rad off in yaw on a turning drive has the true yaw
    after the first heading; without the headings the error is still there."""
    yaw0, rate = 0.6, 0.05
    heading_t = np.arange(0.505, 30.0, 1.0)
    headings = {
        "heading_t": heading_t,
        "heading_yaw": yaw0 + rate * heading_t,
        "heading_variance": np.full(heading_t.size, 0.005**2),
    }
    out, truth = _turning_drive(yaw0, rate, yaw0 + 0.5, **headings)
    without, truth_without = _turning_drive(yaw0, rate, yaw0 + 0.5)
    assert set(np.round(heading_t, 6)) <= set(np.round(out["t"], 6))
    after = out["t"] >= heading_t[0]
    assert np.abs(_yaw_error(out["rpy"][after, 2], truth[after])).max() < 0.01
    early = (without["t"] >= heading_t[0]) & (without["t"] < 2.0)
    assert np.abs(_yaw_error(without["rpy"][early, 2], truth_without[early])).min() > 0.3
    assert out["rejected"] == 0
    with pytest.raises(ValueError, match="heading_t, heading_yaw and heading_variance"):
        _turning_drive(yaw0, rate, yaw0, **{**headings, "heading_variance": None})
    with pytest.raises(ValueError, match=r"must be \(H,\)"):
        _turning_drive(yaw0, rate, yaw0, **{**headings, "heading_yaw": headings["heading_yaw"][1:]})


def test_yaw_only_heading_across_pi_pulls_the_short_way():
    """Driving through yaw = pi (the headings given unwrapped, beyond pi after 2 s), the peer
    started 0.3 rad past the truth across the +-pi cut moves the short way: its wrapped
    error never grows past the start's and shrinks to the truth. With heading variances
    near the state's, an unwrapped innovation of ~2 pi - 0.3 swings the yaw ~3 rad the
    wrong way (checked: max error 3.1 rad with the yaw innovation unwrapped)."""
    yaw0, rate = math.pi - 0.2, 0.1
    heading_t = np.arange(1.0, 30.0, 1.0)
    true_heading = yaw0 + rate * heading_t  # beyond pi after 2 s: another branch
    out, truth = _turning_drive(
        yaw0,
        rate,
        yaw0 + 0.3 - 2.0 * math.pi,
        heading_t=heading_t,
        heading_yaw=true_heading,
        heading_variance=np.full(heading_t.size, 0.06),
    )
    error = np.abs(_yaw_error(out["rpy"][:, 2], truth))
    assert error.max() < 0.31, error.max()
    assert error[out["t"] >= 20.0].max() < 0.02, error[out["t"] >= 20.0].max()
    assert np.all(np.abs(out["rpy"][:, 2]) <= math.pi)
