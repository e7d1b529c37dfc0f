"""Online extrinsic calibration (frontend.calibration, sensors.calibration): GNSS lever arm,
pose-source lever arm and mounting rotation, IMU-to-vehicle rotation. Jacobians against
central differences, rotation injection and the observability ratio in closed form, the
off switches bit-identical, held states = the plain filter, and on a simulated run with
known wrong extrinsics the excited states converge within 3 sigma and are flagged
observable while the unexcited ones (the camera's vertical lever arm, the IMU roll about
the direction of travel on level ground) are flagged unobservable."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from error_state_checks import DTYPE, boxplus, central_differences, random_state

from msf_torch.frontend.calibration import CalibrationLayout, observability
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.geometry import so3
from msf_torch.sensors.calibration import (
    calibrated_wheel_residual,
    gnss_lever_arm_jacobian,
    mounted_rate_residual,
    mounted_velocity_residual,
    shifted_body_velocity_residual,
    shifted_gnss_residual,
    shifted_mean_rate_residual,
    vehicle_frame_nonholonomic_residual,
    vehicle_frame_wheel_residual,
)
from msf_torch.sensors.vehicle import nonholonomic_residual
from msf_torch.sensors.wheel import wheel_residual
from msf_torch.sim.calibration import calibration_sim_config, simulate_calibration_run

EXTRINSIC_ERRORS = {
    "gnss_lever_arm_error_m": 0.2,
    "camera_lever_arm_error_m": 0.15,
    "camera_rotation_error_rad": 0.03,
    "imu_body_rotation_error_rad": 0.03,
    "camera_drift_side": "chained",
}


def _close(analytic: torch.Tensor, numeric: torch.Tensor) -> None:
    torch.testing.assert_close(analytic, numeric, atol=1e-7, rtol=1e-7)


def test_gnss_lever_arm_jacobian_matches_finite_differences():
    gen = torch.Generator().manual_seed(3)
    state = random_state(gen)
    batch = state["position"].shape[0]
    gyro = 0.4 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    lever = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    measured = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    for offset in (0.0, 0.03):
        t_d = torch.full((batch,), offset, dtype=DTYPE)

        def gnss(arm, t_d=t_d):
            return shifted_gnss_residual(
                state["position"],
                state["velocity"],
                state["rotation"],
                gyro,
                state["gyro_bias"],
                arm,
                measured,
                t_d,
            )[0]

        analytic = gnss_lever_arm_jacobian(state["rotation"], gyro, state["gyro_bias"], t_d)
        _close(analytic, central_differences(lambda d, f=gnss: f(lever + d), 3, batch))


def test_mounted_pose_source_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(4)
    state = random_state(gen)
    batch = state["position"].shape[0]
    gyro = 0.4 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    accel = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    lever = 0.3 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    mount_vector = 0.5 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    measured = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    offset = torch.full((batch,), -0.04, dtype=DTYPE)

    def velocity(s, arm, phi, td):
        return mounted_velocity_residual(
            s["velocity"],
            s["rotation"],
            gyro,
            s["gyro_bias"],
            arm,
            so3.exp(mount_vector) @ so3.exp(phi),
            accel,
            measured,
            td,
        )

    zero3 = torch.zeros(batch, 3, dtype=DTYPE)
    _, h_nav, h_td, h_lever, h_mount = velocity(state, lever, zero3, offset)
    _close(
        h_nav,
        central_differences(
            lambda dx: velocity(boxplus(state, dx), lever, zero3, offset)[0], 15, batch
        ),
    )
    _close(
        h_td,
        central_differences(lambda d: velocity(state, lever, zero3, offset + d[:, 0])[0], 1, batch),
    )
    _close(
        h_lever,
        central_differences(lambda d: velocity(state, lever + d, zero3, offset)[0], 3, batch),
    )
    _close(h_mount, central_differences(lambda d: velocity(state, lever, d, offset)[0], 3, batch))
    # identity mount: the body-frame model of sensors.calibration, unrotated
    plain = shifted_body_velocity_residual(
        state["velocity"],
        state["rotation"],
        gyro,
        state["gyro_bias"],
        lever,
        accel,
        measured,
        offset,
    )
    identity = mounted_velocity_residual(
        state["velocity"],
        state["rotation"],
        gyro,
        state["gyro_bias"],
        lever,
        so3.exp(zero3),
        accel,
        measured,
        offset,
    )
    for a, b in zip(plain, identity[:3], strict=True):
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)

    mean = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    change = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    rate_measured = torch.randn(batch, 3, generator=gen, dtype=DTYPE)

    def rate(s, phi, td):
        return mounted_rate_residual(
            mean, s["gyro_bias"], change, so3.exp(mount_vector) @ so3.exp(phi), rate_measured, td
        )

    _, h_nav, h_td, h_mount = rate(state, zero3, offset)
    _close(
        h_nav, central_differences(lambda dx: rate(boxplus(state, dx), zero3, offset)[0], 15, batch)
    )
    _close(h_td, central_differences(lambda d: rate(state, zero3, offset + d[:, 0])[0], 1, batch))
    _close(h_mount, central_differences(lambda d: rate(state, d, offset)[0], 3, batch))
    unrotated = shifted_mean_rate_residual(mean, state["gyro_bias"], change, rate_measured, offset)
    identity = mounted_rate_residual(
        mean, state["gyro_bias"], change, so3.exp(zero3), rate_measured, offset
    )
    for a, b in zip(unrotated, identity[:3], strict=True):
        torch.testing.assert_close(a, b, atol=1e-14, rtol=0)


def test_vehicle_frame_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(5)
    state = random_state(gen)
    batch = state["position"].shape[0]
    gyro = 0.4 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    left = 3.0 + torch.randn(batch, generator=gen, dtype=DTYPE)
    right = 3.0 + torch.randn(batch, generator=gen, dtype=DTYPE)
    lever = torch.tensor([0.1, -0.05, 0.2], dtype=DTYPE)
    vehicle = so3.exp(0.3 * torch.randn(batch, 3, generator=gen, dtype=DTYPE))
    ratio = torch.tensor([1.04, 0.97], dtype=DTYPE).expand(batch, 2)
    track = torch.full((batch,), 0.61, dtype=DTYPE)
    # the track-width column is taken at the gyro's (vehicle-frame) yaw rate: exact where it
    # equals the encoders' yaw rate
    turn = (ratio[:, 1] * right - ratio[:, 0] * left) / track
    rate_vehicle = (vehicle.mT @ (gyro - state["gyro_bias"])[..., None]).squeeze(-1)
    gyro = gyro + (vehicle[..., :, 2] * (turn - rate_vehicle[:, 2])[:, None])

    def wheel(s, calib, phi):
        return vehicle_frame_wheel_residual(
            s["velocity"],
            s["rotation"],
            gyro,
            s["gyro_bias"],
            left,
            right,
            calib[:, 0:2],
            calib[:, 2],
            lever,
            vehicle @ so3.exp(phi),
        )

    calib = torch.cat((ratio, track[:, None]), -1)
    zero3 = torch.zeros(batch, 3, dtype=DTYPE)
    _, h_nav, h_wheel, h_rot = wheel(state, calib, zero3)
    _close(
        h_nav, central_differences(lambda dx: wheel(boxplus(state, dx), calib, zero3)[0], 15, batch)
    )
    _close(h_wheel, central_differences(lambda d: wheel(state, calib + d, zero3)[0], 3, batch))
    _close(h_rot, central_differences(lambda d: wheel(state, calib, d)[0], 3, batch))
    # identity rotation: the body-frame wheel model
    plain = calibrated_wheel_residual(
        state["velocity"],
        state["rotation"],
        gyro,
        state["gyro_bias"],
        left,
        right,
        ratio,
        track,
        lever,
    )
    aligned = vehicle_frame_wheel_residual(
        state["velocity"],
        state["rotation"],
        gyro,
        state["gyro_bias"],
        left,
        right,
        ratio,
        track,
        lever,
        so3.exp(zero3),
    )
    for a, b in zip(plain, aligned[:3], strict=True):
        torch.testing.assert_close(a, b, atol=1e-13, rtol=0)
    unit = torch.ones(batch, 2, dtype=DTYPE)
    r_plain, h_plain = wheel_residual(
        state["velocity"], state["rotation"], gyro, state["gyro_bias"], left, right, 0.61, lever
    )
    r_unit = vehicle_frame_wheel_residual(
        state["velocity"],
        state["rotation"],
        gyro,
        state["gyro_bias"],
        left,
        right,
        unit,
        track,
        lever,
        so3.exp(zero3),
    )
    torch.testing.assert_close(r_unit[0], r_plain, atol=1e-13, rtol=0)
    torch.testing.assert_close(r_unit[1], h_plain, atol=1e-13, rtol=0)

    def nhc(s, phi):
        return vehicle_frame_nonholonomic_residual(
            s["velocity"], s["rotation"], gyro, s["gyro_bias"], lever, vehicle @ so3.exp(phi)
        )

    _, h_nav, h_rot = nhc(state, zero3)
    _close(h_nav, central_differences(lambda dx: nhc(boxplus(state, dx), zero3)[0], 15, batch))
    _close(h_rot, central_differences(lambda d: nhc(state, d)[0], 3, batch))
    r_plain, h_plain = nonholonomic_residual(
        state["velocity"], state["rotation"], gyro, state["gyro_bias"], lever
    )
    r_aligned, h_aligned, _ = vehicle_frame_nonholonomic_residual(
        state["velocity"], state["rotation"], gyro, state["gyro_bias"], lever, so3.exp(zero3)
    )
    torch.testing.assert_close(r_aligned, r_plain, atol=1e-13, rtol=0)
    torch.testing.assert_close(h_aligned, h_plain, atol=1e-13, rtol=0)


def test_layout_rotation_injection_and_observability_ratio():
    cfg = EskfConfig(
        calibrate_gnss_lever_arm=True,
        gnss_lever_arm_m=[0.1, 0.2, 0.3],
        calibrate_pose_extrinsics=["pose:vo"],
        calibration_pose_lever_arm_m={"pose:vo": [0.5, 0.0, 0.2]},
        calibrate_imu_body_rotation=True,
        calibration_lever_arm_sigma_m=0.4,
        calibration_rotation_rw_density=1e-3,
    )
    layout = CalibrationLayout.from_config(cfg, ("wheel", "gnss", "pose:vo"))
    assert layout.names[:3] == ("lever_arm_m:gnss:x", "lever_arm_m:gnss:y", "lever_arm_m:gnss:z")
    assert layout.gnss_lever_index == 0
    assert layout.pose_extrinsic_index == {"pose:vo": 3}
    assert layout.imu_body_index == 9 and layout.rotation_index == (6, 9)
    torch.testing.assert_close(
        layout.initial[:6], torch.tensor([0.1, 0.2, 0.3, 0.5, 0.0, 0.2], dtype=DTYPE)
    )
    # rotations compose on the right, the rest adds
    gen = torch.Generator().manual_seed(6)
    values = torch.randn(2, 12, generator=gen, dtype=DTYPE)
    correction = 0.1 * torch.randn(2, 12, generator=gen, dtype=DTYPE)
    injected = layout.inject(values, correction)
    torch.testing.assert_close(injected[:, :6], values[:, :6] + correction[:, :6])
    for col in (6, 9):
        block = slice(col, col + 3)
        torch.testing.assert_close(
            so3.exp(injected[:, block]), so3.exp(values[:, block]) @ so3.exp(correction[:, block])
        )
    # observability: the variance over sigma_0^2 + q^2 t
    elapsed = torch.tensor([[0.0, 100.0]], dtype=DTYPE)
    unobserved = layout.prior_sigma**2 + layout.rw_density**2 * elapsed[..., None]
    variance = unobserved * torch.linspace(0.05, 1.0, 12, dtype=DTYPE)
    ratio, observable = observability(layout, variance, elapsed, 0.25)
    torch.testing.assert_close(ratio, torch.linspace(0.05, 1.0, 12, dtype=DTYPE).expand(1, 2, 12))
    assert observable.tolist() == (ratio < 0.25).tolist()
    assert CalibrationLayout.from_config(cfg, ("wheel",)).names[0] == "rotation_rad:imu_body:x"
    for bad, key in (
        ({"calibrate_pose_extrinsics": ["vo"]}, "calibrate_pose_extrinsics"),
        ({"calibration_pose_lever_arm_m": {"pose:vo": [0.0, 0.0]}}, "calibration_pose_lever_arm_m"),
        ({"calibration_imu_body_rotation_rad": [0.0]}, "calibration_imu_body_rotation_rad"),
        ({"calibration_rotation_sigma_rad": -1.0}, "calibration_rotation_sigma_rad"),
        ({"calibration_observable_ratio": 1.5}, "calibration_observable_ratio"),
    ):
        with pytest.raises(ValueError, match=key):
            load_config(None, **bad)


@pytest.fixture(scope="module")
def short_run():
    """One 15-s run with wrong extrinsics, and its base config."""
    run = simulate_calibration_run(11, calibration_sim_config(15.0), **EXTRINSIC_ERRORS)
    return run, config_for_sequence(EskfConfig(), run.sequence.meta, set())


def test_off_switches_bit_identical_and_held_states_match_plain_filter(short_run):
    run, cfg = short_run
    plain = run_eskf(run.sequence, cfg)
    with pytest.warns(UserWarning, match="calibrate_pose_extrinsics names pose:absent"):
        off = run_eskf(
            run.sequence,
            cfg.replace(
                calibration_lever_arm_sigma_m=0.9,
                calibration_rotation_sigma_rad=0.2,
                calibration_observable_ratio=0.5,
                calibrate_pose_extrinsics=["pose:absent"],
            ),
        )
    assert off.calibration is None and off.calibration_observable == {}
    for name in ("position", "velocity", "rotation", "gyro_bias", "accel_bias", "covariance"):
        assert torch.equal(getattr(plain, name), getattr(off, name)), name
    # GNSS lever arm and IMU-to-vehicle rotation held at the believed values (sigma ~0, no
    # random walk): the plain filter up to round-off, and flagged unobservable (ratio ~1)
    held = run_eskf(
        run.sequence,
        cfg.replace(
            calibrate_gnss_lever_arm=True,
            calibrate_imu_body_rotation=True,
            calibration_lever_arm_sigma_m=1e-12,
            calibration_rotation_sigma_rad=1e-12,
            calibration_lever_arm_rw_density=0.0,
            calibration_rotation_rw_density=0.0,
        ),
    )
    torch.testing.assert_close(held.position, plain.position, atol=1e-7, rtol=0)
    torch.testing.assert_close(held.covariance, plain.covariance, atol=1e-9, rtol=1e-6)
    assert float(held.calibration.abs().max()) < 1e-9
    assert not any(bool(v.any()) for v in held.calibration_observable.values())


def test_extrinsics_converge_and_unexcited_states_are_flagged():
    """A 60-s planar run with 0.2 m GNSS lever-arm, 0.15 m camera lever-arm, 0.03 rad
    camera-mount and 0.03 rad IMU-to-vehicle errors per axis (random signs) plus the wheel /
    time-offset errors of the benchmark."""
    run = simulate_calibration_run(0, calibration_sim_config(60.0), **EXTRINSIC_ERRORS)
    cfg = config_for_sequence(EskfConfig(), run.sequence.meta, set())
    off = run_eskf(run.sequence, cfg)
    on = run_eskf(
        run.sequence,
        cfg.replace(
            calibrate_wheels=True,
            calibrate_time_offsets=["gnss", "pose:vo"],
            calibrate_gnss_lever_arm=True,
            calibrate_pose_extrinsics=["pose:vo"],
            calibrate_imu_body_rotation=True,
        ),
    )
    names = on.calibration_names
    estimate = on.calibration[0, -1].numpy()
    sigma = np.sqrt(np.diagonal(on.calibration_covariance[0, -1].numpy()))
    truth = run.truth.vector(names)
    initial = on.calibration[0, 0].numpy()
    observable = {n: bool(v[0]) for n, v in on.calibration_observable.items()}
    assert np.all(np.abs(estimate - truth) <= 3.0 * sigma), dict(
        zip(names, (estimate - truth) / sigma, strict=True)
    )
    # no rate about x or y on level ground: the camera's vertical lever arm ([w]x l has no
    # l_z term for w along z) and the IMU roll about the direction of travel (the vehicle
    # velocity lies along it) stay at their prior
    unexcited = ("lever_arm_m:pose:vo:z", "rotation_rad:imu_body:x")
    for name in unexcited:
        assert not observable[name], name
        assert on.calibration_variance_ratio[0, -1, names.index(name)] > 0.5
    excited = [
        "lever_arm_m:gnss:x",
        "lever_arm_m:gnss:y",
        "rotation_rad:pose:vo:x",
        "rotation_rad:pose:vo:y",
        "rotation_rad:pose:vo:z",
        "rotation_rad:imu_body:y",
        "rotation_rad:imu_body:z",
    ]
    for name in excited:
        k = names.index(name)
        assert observable[name], name
        # resolved: the initial error is at least 3 final sigmas
        assert abs(initial[k] - truth[k]) >= 3.0 * sigma[k], name

    def ate(result):
        mask = result.mask[0]
        position = run.run.path.evaluate(result.t[0][mask].numpy()).position
        return np.sqrt(np.mean(np.sum((result.position[0][mask].numpy() - position) ** 2, -1)))

    assert ate(on) < 0.8 * ate(off)


@pytest.mark.parametrize("turning", [False, True])
def test_gnss_lever_arm_needs_turns(turning):
    """On a straight 40-s run (constant heading) the horizontal lever arm only shifts the
    track, like the initial position: flagged unobservable, left near its prior. With turns
    it rotates against the track and is resolved (0.2 m errors per axis)."""
    config = calibration_sim_config(
        40.0,
        turn_rate_peak_rad_s=0.3 if turning else 0.0,
        mean_turn_rate_rad_s=0.02 if turning else 0.0,
    )
    run = simulate_calibration_run(
        3, config, radius_error=0.0, track_error=0.0, time_offset_s=0.0, gnss_lever_arm_error_m=0.2
    )
    cfg = config_for_sequence(EskfConfig(), run.sequence.meta, set())
    result = run_eskf(run.sequence, cfg.replace(calibrate_gnss_lever_arm=True))
    names = result.calibration_names
    estimate = result.calibration[0, -1].numpy()
    sigma = np.sqrt(np.diagonal(result.calibration_covariance[0, -1].numpy()))
    assert np.all(np.abs(estimate - run.truth.vector(names)) <= 3.0 * sigma)
    for name in ("lever_arm_m:gnss:x", "lever_arm_m:gnss:y"):
        assert bool(result.calibration_observable[name][0]) is turning, name
        assert bool(sigma[names.index(name)] < 0.05) is turning, name


def test_run_outputs_report_calibration_and_observability(short_run, tmp_path):
    """``msf run``'s summary.json and diagnostics.csv carry the estimates, sigmas and
    observability flags of the result."""
    import csv
    import json

    from msf_torch.runner import RunOptions, run_sequence

    run, cfg = short_run
    cfg = cfg.replace(calibrate_gnss_lever_arm=True, calibrate_imu_body_rotation=True)
    summary = run_sequence(run.sequence, cfg, RunOptions(out_dir=tmp_path, plot=False))
    written = json.loads((tmp_path / "summary.json").read_text())
    result = run_eskf(run.sequence, cfg)
    names = result.calibration_names
    assert list(written["calibration_observable"]) == list(names)
    for k, name in enumerate(names):
        assert written["calibration"][name] == pytest.approx(float(result.calibration[0, -1, k]))
        sigma = float(result.calibration_covariance[0, -1, k, k]) ** 0.5
        assert written["calibration_sigma"][name] == pytest.approx(sigma)
        assert written["calibration_observable"][name] is bool(
            result.calibration_observable[name][0]
        )
    assert summary["calibration_observable"] == written["calibration_observable"]
    with open(tmp_path / "diagnostics.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert float(rows[-1]["lever_arm_m:gnss:x"]) == pytest.approx(
        float(result.calibration[0, -1, 0]), rel=1e-8
    )
    assert float(rows[-1]["rotation_rad:imu_body:z_sigma"]) == pytest.approx(
        float(result.calibration_covariance[0, -1, 5, 5]) ** 0.5, rel=1e-8
    )


def test_robot_yaml_extrinsic_switches(tmp_path):
    from msf_torch.io.errors import DataError
    from msf_torch.robot.config import load_robot_config

    text = """\
sensors:
  imu: {type: imu, topic: /imu, calibrate_rotation: true}
  odom: {type: wheels, topic: /odom}
  gps: {type: gnss, topic: /fix, calibrate_lever_arm: true}
  cam: {type: pose, topic: /vo, source_name: vo, calibrate_extrinsics: true}
"""
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    robot = load_robot_config(path)
    assert robot.calibrate_extrinsics == ("imu", "gnss", "pose:vo")
    cfg = robot.eskf_config({"extrinsics": {}})
    assert cfg.calibrate_gnss_lever_arm and cfg.calibrate_imu_body_rotation
    assert cfg.calibrate_pose_extrinsics == ["pose:vo"]
    assert cfg.calibrate_wheels is False and cfg.calibrate_time_offsets == []
    both = tmp_path / "both.yaml"
    both.write_text(text + "estimator: {calibrate_gnss_lever_arm: false}\n")
    with pytest.raises(DataError, match="calibrate_gnss_lever_arm"):
        load_robot_config(both).eskf_config({"extrinsics": {}})
    poses = tmp_path / "poses.yaml"
    poses.write_text(text.replace("source_name: vo,", "role: poses,"))
    with pytest.raises(DataError, match="sensors.cam.calibrate_extrinsics"):
        load_robot_config(poses)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("calibrate_rotation: true", "calibrate_rotation: 1.5"))
    with pytest.raises(DataError, match="sensors.imu.calibrate_rotation"):
        load_robot_config(bad)
