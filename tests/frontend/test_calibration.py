"""Online calibration (frontend.calibration, sensors.calibration): Jacobians against finite
differences, the off switch leaves results bit-identical, a held calibration state matches
the plain filter, and on a short miscalibrated simulated run the wheel radii, track width
and GNSS time offset converge to the truth within their reported 3 sigma with a lower ATE
than without calibration."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from error_state_checks import DTYPE, boxplus, central_differences, random_state

from msf_torch.frontend.calibration import CalibrationLayout
from msf_torch.frontend.config import EskfConfig, config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sensors.calibration import (
    calibrated_wheel_residual,
    shifted_body_velocity_residual,
    shifted_gnss_residual,
    shifted_mean_rate_residual,
)
from msf_torch.sim.calibration import calibration_sim_config, simulate_calibration_run
from msf_torch.types import batch_sequences


def test_wheel_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(1)
    state = random_state(gen)
    batch = state["position"].shape[0]
    gyro = 0.4 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    left = 3.0 + torch.randn(batch, generator=gen, dtype=DTYPE)
    right = 3.0 + torch.randn(batch, generator=gen, dtype=DTYPE)
    calib = torch.stack((1.04 + 0.0 * left, 0.97 + 0.0 * left, 0.61 + 0.0 * left), -1)
    # the track-width column is evaluated at the gyro yaw rate: exact where it equals the
    # encoders' yaw rate, so make them agree
    gyro[:, 2] = state["gyro_bias"][:, 2] + (calib[:, 1] * right - calib[:, 0] * left) / calib[:, 2]
    lever = torch.tensor([0.1, -0.05, 0.2], dtype=DTYPE)

    def residual(s, c):
        return calibrated_wheel_residual(
            s["velocity"],
            s["rotation"],
            gyro,
            s["gyro_bias"],
            left,
            right,
            c[:, 0:2],
            c[:, 2],
            lever,
        )

    _, h_nav, h_cal = residual(state, calib)
    num_nav = central_differences(lambda dx: residual(boxplus(state, dx), calib)[0], 15, batch)
    num_cal = central_differences(lambda dc: residual(state, calib + dc)[0], 3, batch)
    torch.testing.assert_close(h_nav, num_nav, atol=1e-7, rtol=1e-7)
    torch.testing.assert_close(h_cal, num_cal, atol=1e-7, rtol=1e-7)


def test_time_offset_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(2)
    state = random_state(gen)
    batch = state["position"].shape[0]
    gyro = 0.4 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    lever = torch.tensor([0.3, -0.2, 0.5], dtype=DTYPE)
    measured = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    accel = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    offset = torch.full((batch,), 0.03, dtype=DTYPE)

    def gnss(s, td):
        return shifted_gnss_residual(
            s["position"], s["velocity"], s["rotation"], gyro, s["gyro_bias"], lever, measured, td
        )

    def body(s, td):
        return shifted_body_velocity_residual(
            s["velocity"], s["rotation"], gyro, s["gyro_bias"], lever, accel, measured, td
        )

    for model in (gnss, body):
        _, h_nav, h_td = model(state, offset)
        num_nav = central_differences(
            lambda dx, m=model: m(boxplus(state, dx), offset)[0], 15, batch
        )
        num_td = central_differences(lambda d, m=model: m(state, offset + d[:, 0])[0], 1, batch)
        torch.testing.assert_close(h_nav, num_nav, atol=1e-7, rtol=1e-7)
        torch.testing.assert_close(h_td, num_td, atol=1e-7, rtol=1e-7)
    # with t_d = 0 the GNSS model is the plain one: antenna position p + R l
    r0, _, h0 = gnss(state, torch.zeros(batch, dtype=DTYPE))
    arm = (state["rotation"] @ lever[:, None]).squeeze(-1)
    torch.testing.assert_close(r0, state["position"] + arm - measured)
    omega = gyro - state["gyro_bias"]
    rate = state["velocity"] + (
        state["rotation"] @ torch.linalg.cross(omega, lever.expand_as(omega))[..., None]
    ).squeeze(-1)
    torch.testing.assert_close(h0[..., 0], rate)

    change = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    mean = torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    rate_meas = torch.randn(batch, 3, generator=gen, dtype=DTYPE)

    def mean_rate(s, td):
        return shifted_mean_rate_residual(mean, s["gyro_bias"], change, rate_meas, td)

    _, h_nav, h_td = mean_rate(state, offset)
    num_nav = central_differences(lambda dx: mean_rate(boxplus(state, dx), offset)[0], 15, batch)
    num_td = central_differences(lambda d: mean_rate(state, offset + d[:, 0])[0], 1, batch)
    torch.testing.assert_close(h_nav, num_nav, atol=1e-7, rtol=1e-7)
    torch.testing.assert_close(h_td, num_td, atol=1e-7, rtol=1e-7)


def test_shifted_mean_rate_matches_integral_of_a_ramp():
    """A linearly rising rate: the mean over the interval shifted by t_d is exactly
    ``w_bar + t_d (w_k - w_k-1) / dt``."""
    slope = torch.tensor([[0.2, -0.1, 0.5]], dtype=DTYPE)
    start, dt, offset = 1.0, 0.1, 0.02
    rate = lambda t: slope * t  # noqa: E731
    mean = rate(start + dt / 2)
    shifted_mean = rate(start + offset + dt / 2)
    residual, _, _ = shifted_mean_rate_residual(
        mean,
        torch.zeros(1, 3, dtype=DTYPE),
        (rate(start + dt) - rate(start)) / dt,
        shifted_mean,
        torch.tensor([offset], dtype=DTYPE),
    )
    torch.testing.assert_close(residual, torch.zeros(1, 3, dtype=DTYPE), atol=1e-15, rtol=0)


def _runs(duration_s: float, seeds: tuple[int, ...]):
    """Miscalibrated runs batched, their truths, and the matching base config."""
    runs = [simulate_calibration_run(s, calibration_sim_config(duration_s)) for s in seeds]
    seq = batch_sequences([r.sequence for r in runs])
    cfg = config_for_sequence(EskfConfig(), runs[0].sequence.meta, set())
    return runs, seq, cfg


@pytest.fixture(scope="module")
def short_run():
    """One 15-s miscalibrated run."""
    return _runs(15.0, (11,))


def _ate(result, runs) -> np.ndarray:
    out = []
    for b, run in enumerate(runs):
        mask = result.mask[b]
        truth = run.run.path.evaluate(result.t[b][mask].numpy()).position
        out.append(np.sqrt(np.mean(np.sum((result.position[b][mask].numpy() - truth) ** 2, -1))))
    return np.array(out)


def test_off_switches_leave_results_bit_identical(short_run):
    _, seq1, cfg = short_run
    plain = run_eskf(seq1, cfg)
    # calibration keys changed but every switch off (a time offset for a sensor the run
    # lacks is skipped): the same code path, bit for bit
    off = cfg.replace(
        calibration_wheel_radius_sigma=0.3,
        calibration_time_offset_sigma_s=0.2,
        calibrate_time_offsets=["pose:absent"],
    )
    with pytest.warns(UserWarning, match="calibrate_time_offsets names pose:absent"):
        other = run_eskf(seq1, off)
    assert other.calibration is None and other.calibration_names == ()
    for name in ("position", "velocity", "rotation", "gyro_bias", "accel_bias", "covariance"):
        assert torch.equal(getattr(plain, name), getattr(other, name)), name


def test_held_time_offset_state_matches_plain_filter(short_run):
    """A GNSS time-offset state held at 0 (prior sigma ~0, no random walk) changes nothing
    but round-off: the augmentation's propagation, update and injection are consistent."""
    _, seq1, cfg = short_run
    plain = run_eskf(seq1, cfg)
    held = run_eskf(
        seq1,
        cfg.replace(
            calibrate_time_offsets=["gnss"],
            calibration_time_offset_sigma_s=1e-12,
            calibration_time_offset_rw_density=0.0,
        ),
    )
    assert held.calibration_names == ("time_offset_s:gnss",)
    torch.testing.assert_close(held.position, plain.position, atol=1e-7, rtol=0)
    torch.testing.assert_close(held.covariance, plain.covariance, atol=1e-9, rtol=1e-6)
    assert float(held.calibration.abs().max()) < 1e-9


def test_calibration_converges_within_3_sigma_and_lowers_ate():
    """Two 60-s runs (5 % radius, 3 % track, 20 ms GNSS offset, random signs)."""
    runs, seq, cfg = _runs(60.0, (11, 12))
    off = run_eskf(seq, cfg)
    on = run_eskf(seq, cfg.replace(calibrate_wheels=True, calibrate_time_offsets=["gnss"]))
    names = on.calibration_names
    assert names == (
        "wheel_radius_ratio_left",
        "wheel_radius_ratio_right",
        "wheel_track_m",
        "time_offset_s:gnss",
    )
    estimate = on.calibration[:, -1].numpy()
    sigma = np.sqrt(np.diagonal(on.calibration_covariance[:, -1].numpy(), 0, -2, -1))
    truth = np.stack([r.truth.vector(names) for r in runs])
    initial = on.calibration[:, 0].numpy()
    assert np.all(np.abs(estimate - truth) <= 3.0 * sigma)
    # converged, not just left at a wide prior (0.1, 0.05 m, 50 ms): the final sigma
    # resolves the radius and time-offset errors (5 %, 20 ms) at least 3 times over; the
    # track width, weakly excited by these turns, has at least a third of its prior sigma
    resolved = [0, 1, 3]
    assert np.all(np.abs(initial - truth)[:, resolved] >= 3.0 * sigma[:, resolved])
    assert np.all(sigma[:, 2] <= 0.05 / 3.0)
    assert np.all(_ate(on, runs) < _ate(off, runs))


def test_layout_and_config_validation():
    cfg = EskfConfig(calibrate_wheels=True, calibrate_time_offsets=["gnss", "pose:vo"])
    layout = CalibrationLayout.from_config(cfg, ("wheel", "gnss", "pose:vo"))
    assert layout.names[2] == "wheel_track_m"
    assert layout.time_offset_index == {"gnss": 3, "pose:vo": 4}
    torch.testing.assert_close(
        layout.initial, torch.tensor([1.0, 1.0, 0.55, 0.0, 0.0], dtype=DTYPE)
    )
    assert CalibrationLayout.from_config(EskfConfig(), ("wheel", "gnss")) is None
    for bad, key in (
        ({"calibrate_time_offsets": ["wheel"]}, "calibrate_time_offsets"),
        ({"calibration_wheel_radius_ratio": [1.0]}, "calibration_wheel_radius_ratio"),
        ({"calibration_time_offset_sigma_s": 0.0}, "calibration_time_offset_sigma_s"),
        ({"calibration_time_offset_s": {"gnss": 0.01}}, "calibration_time_offset_s"),
    ):
        with pytest.raises(ValueError, match=key):
            load_config(None, **bad)


def test_robot_yaml_calibration_switches(tmp_path):
    from msf_torch.io.errors import DataError
    from msf_torch.robot.config import load_robot_config

    text = """\
sensors:
  imu: {type: imu, topic: /imu}
  odom: {type: wheels, topic: /odom, calibrate: true}
  gps: {type: gnss, topic: /fix, calibrate_time_offset: true}
  cam: {type: pose, topic: /vo, source_name: vo, calibrate_time_offset: true}
"""
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    robot = load_robot_config(path)
    assert robot.calibrate == ("wheels", "gnss", "pose:vo")
    cfg = robot.eskf_config({"extrinsics": {}})
    assert cfg.calibrate_wheels is True
    assert cfg.calibrate_time_offsets == ["gnss", "pose:vo"]
    plain = tmp_path / "plain.yaml"
    plain.write_text(
        text.replace(", calibrate: true", "").replace(", calibrate_time_offset: true", "")
    )
    off = load_robot_config(plain).eskf_config({"extrinsics": {}})
    assert off.calibrate_wheels is False and off.calibrate_time_offsets == []
    both = tmp_path / "both.yaml"
    both.write_text(text + "estimator: {calibrate_wheels: true}\n")
    with pytest.raises(DataError, match="calibrate_wheels"):
        load_robot_config(both).eskf_config({"extrinsics": {}})
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("calibrate: true", "calibrate: maybe"))
    with pytest.raises(DataError, match="sensors.odom.calibrate"):
        load_robot_config(bad)
