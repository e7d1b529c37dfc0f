"""Wheel calibration (radius ratios, track width) as a variable of the full-batch smoother.

References: :func:`preintegrate_wheel` at scaled readings (the calibrated increment),
central finite differences on the tangent space (analytic Jacobians), the dense inverse of
the Gauss-Newton Hessian (bordered chain covariances), and the simulator's true
calibration and trajectory (a miscalibrated run).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from msf_torch.backend import factors as F
from msf_torch.backend import window as W
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.preintegration import calibrated_wheel_increment, preintegrate_wheel
from msf_torch.backend.problem import Problem
from msf_torch.backend.variables import KINDS, NAV_STATE, POSE, WHEEL_CALIBRATION
from msf_torch.cli import main
from msf_torch.frontend.calibration import WHEEL_STATES
from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.geometry import so3
from msf_torch.io.native import write_native
from msf_torch.sim.calibration import calibration_sim_config, simulate_calibration_run

DTYPE = torch.float64


def _readings(generator: torch.Generator, count: int, length: int):
    left = 3.0 + torch.rand(count, length, generator=generator, dtype=DTYPE)
    right = left + 0.6 * (torch.rand(count, length, generator=generator, dtype=DTYPE) - 0.5)
    dt = 0.04 * torch.ones(count, length, dtype=DTYPE)
    dt[0, -2:] = 0.0  # padding
    return left, right, dt


def test_calibrated_increment_is_preintegration_of_scaled_readings():
    generator = torch.Generator().manual_seed(0)
    left, right, dt = _readings(generator, 4, 12)
    calibration = torch.tensor([1.04, 0.97, 0.62], dtype=DTYPE).expand(4, 3)
    increment, jacobian = calibrated_wheel_increment(left, right, dt, calibration)
    expected, _ = preintegrate_wheel(1.04 * left, 0.97 * right, dt, 0.62, 0.05)
    torch.testing.assert_close(increment, expected, rtol=0, atol=1e-14)
    step = 1e-5  # rounding in the arcs' sums dominates below
    for k in range(3):
        shift = torch.zeros(3, dtype=DTYPE)
        shift[k] = step
        plus, _ = calibrated_wheel_increment(left, right, dt, calibration + shift)
        minus, _ = calibrated_wheel_increment(left, right, dt, calibration - shift)
        torch.testing.assert_close(
            jacobian[..., k], (plus - minus) / (2 * step), rtol=1e-7, atol=1e-8
        )


def _random_nav(generator: torch.Generator, count: int) -> torch.Tensor:
    position = 3.0 * torch.randn(1, count, 3, generator=generator, dtype=DTYPE)
    velocity = torch.randn(1, count, 3, generator=generator, dtype=DTYPE)
    rotation = so3.exp(0.3 * torch.randn(1, count, 3, generator=generator, dtype=DTYPE))
    bias = 0.01 * torch.randn(1, count, 6, generator=generator, dtype=DTYPE)
    flat = rotation.reshape(1, count, 9)
    return torch.cat((position, velocity, flat, bias), -1)


@pytest.mark.parametrize("kind", ["nav_state", "pose"])
def test_calibrated_wheel_factor_jacobians_match_finite_differences(kind):
    generator = torch.Generator().manual_seed(1)
    count = 5
    nav = _random_nav(generator, count + 1)
    values = nav if kind == "nav_state" else torch.cat((nav[..., 0:3], nav[..., 6:15]), -1)
    left, right, dt = _readings(generator, count, 8)
    covariance = torch.diag(torch.tensor([0.01, 0.02, 0.003], dtype=DTYPE)).expand(1, count, 3, 3)
    index = torch.arange(count)
    factor = F.CalibratedWheelOdometryFactor(
        "state",
        index,
        index + 1,
        "calib",
        left[None],
        right[None],
        dt[None],
        covariance,
        0.6,
        torch.tensor([-0.2, 0.05, -0.1], dtype=DTYPE),
    )
    calibration = torch.tensor([[[1.05, 0.96, 0.58]]], dtype=DTYPE)
    prior = F.VectorPriorFactor(
        "calib",
        torch.zeros(1, dtype=torch.long),
        torch.tensor([[[1.0, 1.0, 0.6]]], dtype=DTYPE),
        torch.diag(torch.tensor([0.01, 0.01, 0.0025], dtype=DTYPE))[None, None],
    )
    problem = Problem(
        {"state": (kind, values), "calib": (WHEEL_CALIBRATION, calibration)}, [factor, prior]
    )
    step = 1e-5
    for fac in problem.factors:
        slot_values = problem.gathered(fac, problem.values)
        kinds = [KINDS[problem.kinds[g].name] for g, _ in fac.slots]
        residual, jacobians = fac.residual_and_jacobians(slot_values, kinds)
        torch.testing.assert_close(residual, fac.residual(slot_values), rtol=0, atol=0)
        for slot, (value, slot_kind) in enumerate(zip(slot_values, kinds, strict=True)):
            for d in range(slot_kind.tangent_dim):
                tangent = torch.zeros(*value.shape[:-1], slot_kind.tangent_dim, dtype=DTYPE)
                tangent[..., d] = step
                moved = [list(slot_values), list(slot_values)]
                moved[0][slot] = slot_kind.retract(value, tangent)
                moved[1][slot] = slot_kind.retract(value, -tangent)
                numeric = (fac.residual(moved[0]) - fac.residual(moved[1])) / (2 * step)
                torch.testing.assert_close(jacobians[slot][..., d], numeric, rtol=1e-6, atol=1e-8)
    assert problem.kinds["state"] in (NAV_STATE, POSE)


@pytest.fixture(scope="module")
def miscalibrated():
    """A 40-s run with 5 % radius and 3 % track errors (a 12-s GNSS outage, brisk turns),
    the front end with wheel calibration, the smoother's graphs with calibration off / on."""
    sim = calibration_sim_config(
        40.0, gnss_outages_s=((20.0, 32.0),), turn_rate_peak_rad_s=1.0, turn_period_s=(6.0, 15.0)
    )
    run = simulate_calibration_run(2, sim, time_offset_s=0.0)
    seq = run.sequence
    cfg = config_for_sequence(EskfConfig(), seq.meta, set()).replace(calibrate_wheels=True)
    with torch.no_grad():
        frontend = run_eskf(seq, cfg)
    return run, seq, cfg, frontend


def _position_rmse(run, output) -> float:
    mask = output.mask[0]
    truth = run.run.path.evaluate(output.t[0][mask].numpy()).position
    error = output.position[0][mask].numpy() - truth
    return float(np.sqrt(np.mean(np.sum(error**2, -1))))


def test_smoother_recovers_calibration_and_lowers_ate(miscalibrated):
    run, seq, cfg, frontend = miscalibrated
    truth = torch.tensor(run.truth.vector(WHEEL_STATES), dtype=DTYPE)
    on = W.SmootherConfig(calibrate_wheels=True)
    with torch.no_grad():
        graph = W.build_graph(seq, frontend, cfg, on)
        # start from the wrong (believed) calibration, not the front end's estimate
        prior_mean = graph.calibration_prior[0]
        cold = dataclasses.replace(graph, calibration_initial=prior_mean.clone())
        states, state_cov, results, estimate, covariance = W.smooth_full_calibrated(cold, on)
        result_on = W.smooth(seq, frontend, cfg, on, "full")
        result_off = W.smooth(seq, frontend, cfg, W.SmootherConfig(), "full")
    assert results[0].converged.all()
    sigma = torch.diagonal(covariance[0]).sqrt()
    initial_error = (prior_mean[0, 0] - truth).abs()
    error = (estimate[0] - truth).abs()
    assert bool((error <= 3.0 * sigma).all()), (estimate, truth, sigma)
    assert bool((error < initial_error / 3.0).all()), (error, initial_error)
    assert bool((sigma < initial_error).all())  # the data resolve each error
    # the default start (front end's estimate) reaches the same optimum
    torch.testing.assert_close(result_on.calibration, estimate, rtol=0, atol=5e-4 * sigma.max())
    torch.testing.assert_close(result_on.calibration_sigma[0], sigma, rtol=1e-4, atol=0)
    assert state_cov.shape == (1, graph.size, 15, 15)
    ate_on = _position_rmse(run, result_on.output)
    ate_off = _position_rmse(run, result_off.output)
    assert ate_on < 0.5 * ate_off, (ate_on, ate_off)
    summary = result_on.summary()["calibration"]
    assert list(summary) == list(WHEEL_STATES)
    assert summary["wheel_track_m"]["sigma"] == pytest.approx(float(sigma[2]))
    assert "calibration" not in result_off.summary() and result_off.calibration is None


def test_bordered_covariance_matches_dense_inverse_and_solver_paths(miscalibrated):
    _, seq, cfg, frontend = miscalibrated
    graph = W.build_graph(seq, frontend, cfg, W.SmootherConfig(calibrate_wheels=True))
    count = 30
    problem = graph.problem(graph.initial[:, :count], 0, count)
    # the calibration border breaks the block-tridiagonal structure: no chain path
    assert problem.block_tridiagonal_size() is None
    off = W.build_graph(seq, frontend, cfg, W.SmootherConfig())
    assert off.problem(off.initial[:, :count], 0, count).block_tridiagonal_size() == 15
    with torch.no_grad():
        dense = solve(problem, LMConfig(linear_solver="dense", damping="identity"))
        sparse = solve(problem, LMConfig(linear_solver="sparse", damping="identity"))
    for name in dense.values:
        torch.testing.assert_close(dense.values[name], sparse.values[name], rtol=0, atol=1e-9)
    values = dense.values
    chain, border = W.bordered_chain_covariance(problem, values, "wheel_calibration")
    inverse = torch.linalg.inv(problem.linearize(values).hessian)
    blocks = torch.stack(
        [inverse[:, 15 * k : 15 * k + 15, 15 * k : 15 * k + 15] for k in range(count)], 1
    )
    scale = torch.diagonal(blocks, dim1=-2, dim2=-1).sqrt()
    outer = scale[..., :, None] * scale[..., None, :]
    torch.testing.assert_close(chain / outer, blocks / outer, rtol=0, atol=1e-7)
    corner = inverse[:, -3:, -3:]
    corner_scale = torch.diagonal(corner, dim1=-2, dim2=-1).sqrt()
    torch.testing.assert_close(
        border / (corner_scale[..., :, None] * corner_scale[..., None, :]),
        corner / (corner_scale[..., :, None] * corner_scale[..., None, :]),
        rtol=0,
        atol=1e-8,
    )


def test_calibration_off_keeps_the_plain_wheel_factor(miscalibrated):
    _, seq, cfg, frontend = miscalibrated
    graph = W.build_graph(seq, frontend, cfg, W.SmootherConfig())
    assert not graph.calibrated and graph.wheel_samples is None
    types = {type(f) for f in graph.factors(0, graph.size)}
    assert F.WheelOdometryFactor in types and F.CalibratedWheelOdometryFactor not in types
    assert F.VectorPriorFactor not in types
    # the yaw row stays switched off without calibration (wheel_yaw_rate_update unset)
    assert bool((graph.wheel_covariance[..., 2, 2] == 1e4).all())
    on = W.build_graph(seq, frontend, cfg, W.SmootherConfig(calibrate_wheels=True))
    assert bool((on.wheel_covariance[..., 2, 2] < 1.0).all())
    torch.testing.assert_close(on.wheel_increment[..., :2], graph.wheel_increment[..., :2])


def test_calibration_config_errors(miscalibrated, tmp_path):
    _, seq, cfg, frontend = miscalibrated
    path = tmp_path / "c.yaml"
    path.write_text("smoother:\n  calibrate_wheels: 1\n")
    with pytest.raises(ValueError, match="smoother.calibrate_wheels"):
        W.load_smoother_config(path)
    path.write_text("smoother:\n  calibrate_wheels: true\n  wheel: false\n")
    with pytest.raises(ValueError, match="smoother.calibrate_wheels"):
        W.load_smoother_config(path)
    path.write_text("robot: {name: rover}\nsmoother:\n  calibrate_wheels: true\n")
    assert W.load_smoother_config(path).calibrate_wheels  # a robot YAML's section
    on = W.SmootherConfig(calibrate_wheels=True)
    with pytest.raises(ValueError, match="full batch only"):
        W.smooth(seq, frontend, cfg, on, "window")
    uncalibrated = dataclasses.replace(
        frontend, calibration_names=(), calibration=None, calibration_covariance=None
    )
    with pytest.raises(ValueError, match="front end's 'calibrate_wheels'"):
        W.build_graph(seq, uncalibrated, cfg, on)


def test_cli_run_smooth_full_reports_calibration(tmp_path, capsys):
    sim = calibration_sim_config(15.0, turn_rate_peak_rad_s=1.0, turn_period_s=(6.0, 15.0))
    run = simulate_calibration_run(3, sim, time_offset_s=0.0)
    data = write_native(run.sequence, tmp_path / "run.npz")
    config = tmp_path / "c.yaml"
    config.write_text("calibrate_wheels: true\nsmoother:\n  calibrate_wheels: true\n")
    args = ["run", str(data), "--out", str(tmp_path / "out"), "--smooth", "full", "--no-plot"]
    assert main([*args, "--config", str(config), "--progress", "off"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    figures = summary["smoother"]["calibration"]
    truth = run.truth.vector(WHEEL_STATES)
    for name, true in zip(WHEEL_STATES, truth, strict=True):
        assert abs(figures[name]["estimate"] - true) <= 3.0 * figures[name]["sigma"]
    assert figures["wheel_radius_ratio_left"]["sigma"] < 0.01
