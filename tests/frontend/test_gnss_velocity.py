"""GNSS velocity in the front end on simulated runs (``SimConfig(gnss_velocity=True)``):
the heading it gives (initial and filtered), the consistency of the filter with it, and the
antenna lever arm.

The linear-case equality with filterpy is in ``test_eskf_filterpy.py``; the residual's
Jacobian in ``tests/sensors/test_sensor_jacobians.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from error_state_checks import navigation_errors, nees_inside_fraction

from msf_torch import batch_sequences, load_sequence_config
from msf_torch.eval.metrics import ate
from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state, velocity_heading
from msf_torch.geometry import so3
from msf_torch.sim import SimConfig, simulate_run

SEEDS = range(200, 208)


@pytest.fixture(scope="module")
def runs():
    return [simulate_run(SimConfig(duration_s=40.0, gnss_velocity=True), seed=s) for s in SEEDS]


def _run(runs, with_velocity: bool, cfg=None):
    seqs = [
        r.sequence if with_velocity else dataclasses.replace(r.sequence, gnss_velocity=None)
        for r in runs
    ]
    cfg = cfg or load_sequence_config(runs[0].sequence.meta)
    with torch.no_grad():
        return run_eskf(batch_sequences(seqs), cfg)


def test_velocities_pin_the_heading_and_the_filter_stays_consistent(runs):
    plain, aided = _run(runs, False), _run(runs, True)
    assert int(aided.accepted["gnss_velocity"].sum()) >= 0.95 * sum(
        r.sequence.gnss_velocity.length for r in runs
    )
    for when in (10.0, 20.0):
        yaw = {}
        for name, result in (("plain", plain), ("aided", aided)):
            values = []
            for b in range(len(runs)):
                t, error, _ = navigation_errors(result, runs, b)
                values.append(abs(float(error[int(torch.searchsorted(t, when)), 8])))
            yaw[name] = float(np.median(values))
        # the velocity's direction is the course: half the heading error or less
        assert yaw["aided"] < 0.6 * yaw["plain"], (when, yaw)
    # position, velocity and attitude NEES inside the 95 % bounds at >= 90 % of the epochs
    # after the first 5 s (alignment)
    assert nees_inside_fraction(aided, runs, after_s=5.0) >= 0.9


def test_the_antenna_lever_arm_enters_through_the_body_rate():
    """Antenna 1 m above and 1 m ahead of the IMU on a turning robot: with the lever arm
    configured the velocity innovations are consistent (mean NIS ~ 3 rows), without it the
    rotation's share ``R (w x l)`` (~0.1-0.3 m/s in turns, sigma 0.05) is missed (the GNSS
    position residual then misses ``R l`` too)."""
    lever = (1.0, 0.3, 1.0)
    run = simulate_run(
        SimConfig(duration_s=60.0, gnss_velocity=True, gnss_lever_arm_m=lever), seed=21
    )
    cfg = load_sequence_config(run.sequence.meta)
    nis = {}
    arms = {"right": list(lever), "zero": [0.0] * 3, "flipped": [-x for x in lever]}
    for name, arm in arms.items():
        with torch.no_grad():
            result = run_eskf(run.sequence, cfg.replace(gnss_lever_arm_m=arm))
        here = result.present["gnss_velocity"][0] & (result.t[0] > 10.0)
        nis[name] = float(result.nis["gnss_velocity"][0, here].mean())
    assert 1.5 < nis["right"] < 5.0, nis
    # the sign: the opposite arm is twice as wrong as none
    assert nis["flipped"] > 2.0 * nis["zero"] > 5.0 * nis["right"], nis


def _turning_drive(yaw0: float, rate: float, speed: float, lever: np.ndarray, backwards=False):
    """A level drive turning at a constant rate: IMU at 100 Hz, the antenna's exact velocity
    ``v + R (w x l)`` at 1 Hz from t = 1 s."""
    imu_t = np.arange(0.0, 5.0, 0.01)
    gyro = np.tile([0.0, 0.0, rate], (imu_t.size, 1))
    t_v = np.arange(1.0, 5.0, 1.0)
    yaw = yaw0 + rate * t_v
    direction = -1.0 if backwards else 1.0
    forward = np.stack((np.cos(yaw), np.sin(yaw), 0.0 * yaw), -1)
    left = np.stack((-np.sin(yaw), np.cos(yaw), 0.0 * yaw), -1)
    arm = np.cross([0.0, 0.0, rate], lever)  # body frame
    velocity = direction * speed * forward + arm[0] * forward + arm[1] * left
    velocity[:, 2] = np.nan
    sigma = np.full((t_v.size, 3), 0.1)
    return {"t": t_v, "velocity": velocity, "sigma": sigma}, imu_t, gyro


@pytest.mark.parametrize("backwards", [False, True])
def test_velocity_heading_is_the_course_carried_back_by_the_gyro(backwards):
    lever = np.array([1.2, -0.4, 0.9])
    cfg = EskfConfig(gnss_lever_arm_m=list(lever), init_min_gnss_speed_mps=1.0)
    velocity, imu_t, gyro = _turning_drive(0.7, 0.25, 2.0, lever, backwards)
    yaw, variance = velocity_heading(
        velocity, imu_t, gyro, np.eye(3), cfg, (lambda t: True) if backwards else None
    )
    # course at t = 1 s, minus the 0.25 rad the gyro turned since t = 0
    assert yaw == pytest.approx(0.7, abs=1e-12)
    # (0.1 / |v_h|)^2 across the course + bias prior and angle random walk over 1 s
    across = 0.1**2 / float((velocity["velocity"][0, :2] ** 2).sum())
    expected = across + cfg.init_gyro_bias_sigma_radps**2 + cfg.gyro_noise_density**2
    assert variance == pytest.approx(expected, rel=1e-12)
    slow = dict(velocity, velocity=0.2 * velocity["velocity"])
    assert velocity_heading(slow, imu_t, gyro, np.eye(3), cfg) is None


def test_velocities_give_the_initial_heading_without_wheels(runs):
    cfg = load_sequence_config(runs[0].sequence.meta)
    ratios, errors, errors_track = [], [], []
    for run in runs:
        for with_velocity, out in ((True, errors), (False, errors_track)):
            seq = dataclasses.replace(run.sequence, wheel=None)
            if not with_velocity:
                seq = dataclasses.replace(seq, gnss_velocity=None)
            state, cov = initial_state(seq, cfg)
            yaw_error = float(so3.log(run.truth.rotation[0, 0].mT @ state.rotation[0])[2])
            out.append(abs(yaw_error))
            if with_velocity:
                ratios.append(yaw_error / float(cov[0, 8, 8].sqrt()))
    # the first course over ground against the track's segment courses less the gyro's
    # turns (measured: 0.023 vs 0.035 rad; the track's first 20 m, before
    # frontend.init.segment_course_yaw, 0.20 rad)
    assert np.median(errors) < 0.05 and np.median(errors) < np.median(errors_track)
    assert max(abs(r) for r in ratios) < 3.0


def test_the_initial_position_follows_the_velocity_heading():
    """With wheels, the initial position is the dead-reckoned track's origin fitted to the
    GNSS track; where the course over ground gives the heading, the track is turned by
    that heading before the fit (20 runs of 30 s: RMS horizontal error 0.31 m; 0.52 m when
    the first fix was taken instead)."""
    errors = []
    for seed in range(300, 320):
        run = simulate_run(SimConfig(duration_s=30.0, gnss_velocity=True), seed=seed)
        state, _ = initial_state(run.sequence, load_sequence_config(run.sequence.meta))
        errors.append(float((state.position[0, :2] - run.truth.position[0, 0, :2]).norm()))
    assert float(np.sqrt(np.mean(np.square(errors)))) < 0.4


def test_velocities_without_fixes(runs):
    """A receiver that logs only its Doppler velocity (no fixes): the heading still comes
    from the course (this crashed the initialisation once), the position stays where it
    starts, unobserved."""
    run = runs[0]
    seq = dataclasses.replace(run.sequence, gnss=None)
    cfg = load_sequence_config(seq.meta)
    state, cov = initial_state(seq, cfg)
    yaw_error = float(so3.log(run.truth.rotation[0, 0].mT @ state.rotation[0])[2])
    assert abs(yaw_error) < 3.0 * float(cov[0, 8, 8].sqrt()) < 0.2
    with torch.no_grad():
        result = run_eskf(seq, cfg)
    assert int(result.accepted["gnss_velocity"].sum()) >= 0.95 * seq.gnss_velocity.length


def test_a_burst_of_velocity_outliers_is_not_let_in(runs):
    """Five Doppler velocities 20 m/s off in a row, with the fixes of the same epochs passing
    their gate: the velocity gate does not re-open after its three rejections (the fixes
    vouch for the state; the velocity is the suspect). It did, and the run went 9.7 m off."""
    run = runs[0]
    velocity = run.sequence.gnss_velocity
    values = velocity.velocity.clone()
    values[0, 10:15, 0] += 20.0
    seq = dataclasses.replace(
        run.sequence, gnss_velocity=dataclasses.replace(velocity, velocity=values)
    )
    cfg = load_sequence_config(seq.meta)
    with torch.no_grad():
        clean, burst = run_eskf(run.sequence, cfg), run_eskf(seq, cfg)
    times = velocity.t[0, 10:15]
    at = torch.isin(burst.t[0], times)
    assert int(burst.present["gnss_velocity"][0, at].sum()) == 5
    assert not bool(burst.accepted["gnss_velocity"][0, at].any())
    errors = [
        ate(r.trajectory(), run.sequence.ground_truth, align="none", max_dt=0.02)["rmse"]
        for r in (clean, burst)
    ]
    assert errors[1] < errors[0] + 0.05, errors
