"""Keyframe selection, the full-batch and sliding-window smoothers, and ``msf run --smooth``.

References: a plain per-epoch loop for keyframe selection, ground truth of the simulator,
the dense inverse of the full Gauss-Newton Hessian for the chain covariances, the full batch
for marginalisation, forward-mode autodiff for the analytic factor Jacobians.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from msf_torch.backend import factors as F
from msf_torch.backend import window as W
from msf_torch.backend.lm import LMConfig, solve
from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.variables import pack_nav_state, pack_pose
from msf_torch.cli import main
from msf_torch.eval.metrics import ate
from msf_torch.frontend.config import config_for_sequence, load_config
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.keyframes import KeyframeConfig, select_keyframes
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import quat_to_matrix
from msf_torch.io.native import write_native
from msf_torch.io.tum import read_tum
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import ImuSamples, Sequence

DTYPE = torch.float64


@pytest.fixture(scope="module")
def sim_run():
    """A 30-s simulated wheeled-robot run, its front-end result and keyframe graph."""
    run = simulate_run(SimConfig(duration_s=30.0), seed=4)
    seq = run.sequence
    cfg = config_for_sequence(load_config(), seq.meta, set())
    with torch.no_grad():
        frontend = run_eskf(seq, cfg)
    graph = W.build_graph(seq, frontend, cfg, W.SmootherConfig())
    return run, seq, cfg, frontend, graph


@pytest.fixture(scope="module")
def full_solution(sim_run):
    *_, graph = sim_run
    with torch.no_grad():
        return W.smooth_full(graph, W.SmootherConfig())


# --- keyframes ---------------------------------------------------------------------------


def _naive_keyframes(t, position, rotation, forced, config):
    """Per-epoch loop over the selection rule (the reference)."""
    out, last, path = [0], 0, 0.0
    for k in range(1, t.numel()):
        path += float((position[k] - position[k - 1]).norm())
        turned = float(so3.log(rotation[last].mT @ rotation[k]).norm())
        if (
            k == t.numel() - 1
            or bool(forced[k])
            or float(t[k] - t[last]) >= config.max_interval_s
            or path >= config.max_distance_m
            or turned >= config.max_rotation_rad
        ):
            out.append(k)
            last, path = k, 0.0
    return out


def test_keyframe_thresholds_each_trigger():
    count = 97  # 12 s at 8 Hz (exact binary times)
    t = torch.arange(count, dtype=DTYPE)[None] * 0.125
    still = torch.zeros(1, count, 3, dtype=DTYPE)
    eye = torch.eye(3, dtype=DTYPE).expand(1, count, 3, 3)
    mask = torch.ones(1, count, dtype=torch.bool)
    by_time = select_keyframes(t, still, eye, mask, KeyframeConfig(0.99, math.inf, math.inf))
    assert by_time.index[0].tolist() == list(range(0, count, 8))
    moving = torch.zeros(1, count, 3, dtype=DTYPE)
    moving[..., 0] = t * 1.2  # 0.15 m per epoch
    by_distance = select_keyframes(t, moving, eye, mask, KeyframeConfig(math.inf, 0.59, math.inf))
    assert by_distance.index[0].tolist() == list(range(0, count, 4))
    yaw = torch.zeros(1, count, 3, dtype=DTYPE)
    yaw[..., 2] = t * 0.4  # 0.05 rad per epoch
    by_turn = select_keyframes(
        t, still, so3.exp(yaw), mask, KeyframeConfig(math.inf, math.inf, 0.29)
    )
    assert by_turn.index[0].tolist() == list(range(0, count, 6))  # 96 = 16 * 6 is the last
    forced = torch.zeros(1, count, dtype=torch.bool)
    forced[0, [3, 4, 57]] = True
    with_forced = select_keyframes(t, still, eye, mask, KeyframeConfig(0.99), force=forced)
    expected = [0, 3, 4, 12, 20, 28, 36, 44, 52, 57, 65, 73, 81, 89, 96]
    assert with_forced.index[0].tolist() == expected
    assert torch.equal(with_forced.t[0], t[0, expected])


def test_keyframes_match_a_per_epoch_loop_and_pad_batches():
    gen = torch.Generator().manual_seed(3)
    batch, count = 3, 400
    t = torch.cumsum(0.02 + 0.2 * torch.rand(batch, count, generator=gen, dtype=DTYPE), 1)
    position = torch.cumsum(0.3 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE), 1)
    turns = 0.05 * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE)
    rotation = so3.exp(torch.cumsum(turns, 1))
    mask = torch.ones(batch, count, dtype=torch.bool)
    mask[1, 300:] = False  # a shorter sequence
    forced = torch.rand(batch, count, generator=gen) < 0.02
    config = KeyframeConfig(max_interval_s=2.0, max_distance_m=3.0, max_rotation_rad=0.3)
    keyframes = select_keyframes(t, position, rotation, mask, config, forced)
    lengths = []
    for b in range(batch):
        n = int(mask[b].sum())
        expected = _naive_keyframes(
            t[b, :n], position[b, :n], rotation[b, :n], forced[b, :n], config
        )
        assert keyframes.index[b, keyframes.mask[b]].tolist() == expected
        lengths.append(len(expected))
    assert keyframes.counts().tolist() == lengths
    assert keyframes.index.shape[1] == max(lengths)
    assert torch.equal(keyframes.t, torch.gather(t, 1, keyframes.index))


def test_keyframe_config_rejects_bad_thresholds():
    with pytest.raises(ValueError, match="max_distance_m"):
        KeyframeConfig(max_distance_m=0.0).validate()


# --- factors -----------------------------------------------------------------------------


def _random_nav(batch, count, gen):
    def rand(scale):
        return scale * torch.randn(batch, count, 3, generator=gen, dtype=DTYPE)

    return pack_nav_state(rand(3.0), rand(1.0), so3.exp(rand(1.0)), rand(0.01), rand(0.1))


@pytest.mark.parametrize("kind", ["nav_state", "pose"])
def test_analytic_jacobians_match_autodiff(kind):
    gen = torch.Generator().manual_seed(1)
    batch, count = 2, 5
    i, j = torch.arange(count - 1), torch.arange(1, count)
    eye3 = torch.eye(3, dtype=DTYPE).expand(1, count - 1, 3, 3)
    arm = torch.tensor([0.3, -0.1, 0.2], dtype=DTYPE)
    wheel = F.WheelOdometryFactor(
        "x", i, j, torch.randn(1, count - 1, 3, generator=gen, dtype=DTYPE), eye3, arm
    )
    factors: list[Factor] = [wheel]
    if kind == "nav_state":
        values = _random_nav(batch, count, gen)
        index = torch.arange(count)
        factors += [
            F.NavStatePriorFactor(
                "x",
                index,
                _random_nav(1, count, gen),
                torch.eye(15, dtype=DTYPE).expand(1, 5, 15, 15),
            ),
            F.NonholonomicFactor(
                "x",
                index,
                torch.randn(1, count, 3, generator=gen, dtype=DTYPE),
                torch.eye(2, dtype=DTYPE).expand(1, count, 2, 2),
                arm,
            ),
            F.MarginalPriorFactor(
                (("x", torch.tensor([1])), ("x", torch.tensor([3]))),
                [_random_nav(1, 1, gen), _random_nav(1, 1, gen)],
                torch.randn(batch, 1, 30, 30, generator=gen, dtype=DTYPE),
                torch.randn(batch, 1, 30, generator=gen, dtype=DTYPE),
            ),
        ]
    else:
        rot = so3.exp(torch.randn(batch, count, 3, generator=gen, dtype=DTYPE))
        values = pack_pose(torch.randn(batch, count, 3, generator=gen, dtype=DTYPE), rot)
    problem = Problem({"x": (kind, values)}, factors)
    for factor in factors:
        slot_values = problem.gathered(factor, {"x": values})
        residual, jacobians = factor.residual_and_jacobians(slot_values, factor.kinds)
        reference, expected = Factor.residual_and_jacobians(factor, slot_values, factor.kinds)
        torch.testing.assert_close(residual, reference, atol=1e-12, rtol=0)
        for got, want in zip(jacobians, expected, strict=True):
            torch.testing.assert_close(got, want, atol=1e-10, rtol=0)


# --- full batch --------------------------------------------------------------------------


def _interpolated(seq, frontend, graph, states):
    """The smoothed trajectory at the front end's epochs (``interpolate_imu``)."""
    real = torch.nonzero(frontend.mask[0]).squeeze(-1)
    where = torch.searchsorted(real, graph.epoch)
    return W.interpolate_imu(seq, frontend.t[0, real], where, states, None, graph.gravity)[0]


def test_full_smoother_beats_front_end_and_is_near_truth(sim_run, full_solution):
    run, seq, _, frontend, graph = sim_run
    states, covariance, results = full_solution
    assert results[0].converged.all()
    truth = seq.ground_truth
    front = ate(frontend.trajectory().select(0).compact(), truth, align="none", max_dt=0.02)
    output = _interpolated(seq, frontend, graph, states)
    smoothed = ate(output, truth, align="none", max_dt=0.02)
    assert smoothed["rmse"] < 0.75 * front["rmse"]
    assert smoothed["rmse"] < 0.3
    # 3-sigma consistency of the keyframe positions against the truth
    at = torch.searchsorted(run.truth.t[0], graph.t - 1e-9)
    error = states[0, :, 0:3] - run.truth.position[0, at]
    normalized = error / torch.diagonal(covariance[0, :, 0:3, 0:3], dim1=-2, dim2=-1).sqrt()
    assert float((normalized.abs() < 3.0).double().mean()) > 0.9


def test_chain_covariance_matches_dense_inverse(sim_run, full_solution):
    *_, graph = sim_run
    states, covariance, _ = full_solution
    count = 25
    problem = graph.problem(states[:, :count], 0, count)
    values = {"state": states[:, :count]}
    chain = W.chain_covariance(problem, values)
    # reference: the dense inverse of the equilibrated Hessian (unit diagonal; the raw one's
    # condition number is ~1e12: bias rows of 1e10 beside position rows of ~1)
    hessian = problem.linearize(values).hessian
    root = torch.diagonal(hessian, dim1=-2, dim2=-1).rsqrt()
    scaled = root[..., :, None] * hessian * root[..., None, :]
    dense = root[..., :, None] * torch.cholesky_inverse(torch.linalg.cholesky(scaled))
    dense = dense * root[..., None, :]
    blocks = torch.stack(
        [dense[:, 15 * k : 15 * k + 15, 15 * k : 15 * k + 15] for k in range(count)], 1
    )
    scale = torch.diagonal(blocks, dim1=-2, dim2=-1).sqrt()
    outer = scale[..., :, None] * scale[..., None, :]
    # as correlations, to what the conditioning allows: 10 eps cond (a few 1e-6 here; a
    # wrong recursion is off by O(1))
    tolerance = 10.0 * torch.finfo(hessian.dtype).eps * float(torch.linalg.cond(scaled).max())
    assert tolerance < 1e-4
    torch.testing.assert_close(chain / outer, blocks / outer, rtol=0, atol=tolerance)
    assert covariance.shape == (1, graph.size, 15, 15)


# --- sliding window ----------------------------------------------------------------------


def test_marginalisation_is_exact_to_first_order(sim_run, full_solution):
    """Marginalise the first keyframes at a point off the optimum and solve what is left:
    the remaining keyframes land on the full batch's solution up to the Gauss-Newton
    model's error, which is proportional to the offset (residual times residual curvature,
    dropped by Gauss-Newton) and vanishes at the optimum."""
    *_, graph = sim_run
    states, _, _ = full_solution
    cut = 8
    config = LMConfig(damping="identity", initial_damping=1e-9, relative_tolerance=1e-14)
    gaps = []
    for offset in (0.0, 1e-2, 1e-3):
        gen = torch.Generator().manual_seed(0)
        point = states.clone()
        noise = torch.randn(point[..., 0:6].shape, generator=gen, dtype=DTYPE)
        point[..., 0:6] += offset * noise
        marginal = None
        for k in range(cut):
            marginal = W._marginalize(graph, point, k, k + 1, marginal, 1e-12)
        factors = graph.factors(cut, graph.size) + [marginal]
        problem = Problem({"state": ("nav_state", point[:, cut:])}, factors)
        rest = solve(problem, config).values["state"]
        gaps.append(float((rest[..., 0:6] - states[:, cut:, 0:6]).abs().max()))
    assert gaps[0] < 1e-6
    assert gaps[2] < 1e-4
    assert gaps[2] < 0.2 * gaps[1]


def test_window_covering_the_run_is_the_full_batch(sim_run, full_solution):
    *_, graph = sim_run
    states, covariance, _ = full_solution
    config = W.SmootherConfig(window_size=graph.size + 5)
    window_states, window_covariance, results = W.smooth_window(graph, config)
    assert len(results) == 1
    torch.testing.assert_close(window_states[..., 0:6], states[..., 0:6], atol=1e-6, rtol=0)
    scale = torch.diagonal(covariance, dim1=-2, dim2=-1).sqrt()
    outer = scale[..., :, None] * scale[..., None, :]
    torch.testing.assert_close(window_covariance / outer, covariance / outer, rtol=0, atol=1e-6)


def test_sliding_window_ends_close_to_the_full_batch(sim_run, full_solution):
    run, seq, _, frontend, graph = sim_run
    states, _, _ = full_solution
    emitted = []
    window_states, _, results = W.smooth_window(
        graph, W.SmootherConfig(window_size=20), lambda done, total: emitted.append(done)
    )
    assert len(results) == graph.size - 19 and emitted[-1] == graph.size
    assert all(bool(r.converged.all()) for r in results)
    last_gap = float((window_states[0, -1, 0:3] - states[0, -1, 0:3]).norm())
    assert last_gap < 0.5  # GNSS sigma 0.5 m horizontal, 1 m vertical
    output = _interpolated(seq, frontend, graph, window_states)
    front = ate(
        frontend.trajectory().select(0).compact(), seq.ground_truth, align="none", max_dt=0.02
    )
    assert ate(output, seq.ground_truth, align="none", max_dt=0.02)["rmse"] < front["rmse"]


# --- output at the front-end epochs ------------------------------------------------------


def _circle(t, rate=0.5, speed=2.0):
    """Closed-form turn at constant yaw rate and forward speed: p (T, 3), v, R (T, 3, 3)."""
    yaw = rate * t
    zero = torch.zeros_like(t)
    position = torch.stack((speed / rate * yaw.sin(), speed / rate * (1 - yaw.cos()), zero), -1)
    velocity = torch.stack((speed * yaw.cos(), speed * yaw.sin(), zero), -1)
    rotation = so3.exp(torch.stack((zero, zero, yaw), -1))
    return position, velocity, rotation


def _turn_sequence(rate: float = 0.5, speed: float = 2.0, g: float = 9.80665) -> Sequence:
    """1 s of a 200-Hz IMU on the exact turn of :func:`_circle` (constant body rate and
    specific force: zero-order hold integrates it exactly)."""
    imu_t = torch.arange(0, 201, dtype=DTYPE) / 200.0
    gyro = torch.tensor([0.0, 0.0, rate], dtype=DTYPE).expand(201, 3)
    accel = torch.tensor([0.0, rate * speed, g], dtype=DTYPE).expand(201, 3)  # R^T (a - g)
    imu = ImuSamples(imu_t[None], gyro[None], accel[None], torch.ones(1, 201, dtype=torch.bool))
    return Sequence(names=["turn"], imu=imu)


def test_output_between_keyframes_follows_the_imu():
    """Keyframes at epochs 0, 15, 25 of an exact turn (closed form). With the true states
    the output is the truth at every epoch; with keyframe 1 moved by ``d`` (and its
    velocity by ``u``) the output between keyframes 0 and 1 is the truth plus ``w d``
    (``w`` the time fraction: the mismatch spread linearly), and between 1 and 2 the truth
    plus ``d + u (t - t_1)`` carried by the IMU minus ``w`` times that at keyframe 2; the
    bias and covariance are the keyframes' blended by ``w``."""
    g = 9.80665
    seq = _turn_sequence(g=g)
    gravity = torch.tensor([0.0, 0.0, -g], dtype=DTYPE)
    t = torch.arange(0, 26, dtype=DTYPE) / 25.0
    position, velocity, rotation = _circle(t)
    index = torch.tensor([0, 15, 25])
    zeros = torch.zeros(3, 3, dtype=DTYPE)
    states = pack_nav_state(position[index], velocity[index], rotation[index], zeros, zeros)
    output, motion = W.interpolate_imu(seq, t, index, states[None], None, gravity)
    torch.testing.assert_close(output.position[0], position, rtol=0, atol=1e-9)
    torch.testing.assert_close(
        so3.log(quat_to_matrix(output.quaternion[0]).mT @ rotation),
        torch.zeros(26, 3, dtype=DTYPE),
        rtol=0,
        atol=1e-9,
    )
    torch.testing.assert_close(motion.velocity[0], velocity, rtol=0, atol=1e-9)
    assert motion.covariance is None

    shift = torch.tensor([0.3, -0.2, 0.1], dtype=DTYPE)
    kick = torch.tensor([0.05, 0.02, 0.0], dtype=DTYPE)
    moved = states.clone()
    moved[1, 0:3] += shift
    moved[1, 3:6] += kick
    gen = torch.Generator().manual_seed(3)
    moved[:, 15:18] = 1e-3 * torch.randn(3, 3, generator=gen, dtype=DTYPE)
    factor = torch.randn(3, 15, 15, generator=gen, dtype=DTYPE)
    keyframe_cov = factor @ factor.mT + 0.1 * torch.eye(15, dtype=DTYPE)
    # the biases change the carried motion: give keyframes 0 and 1 zero gyro bias again
    moved[:2, 15:18] = 0.0
    output, motion = W.interpolate_imu(seq, t, index, moved[None], keyframe_cov[None], gravity)
    w_first = (t[:16] / t[15])[:, None]
    torch.testing.assert_close(
        output.position[0, :16], position[:16] + w_first * shift, rtol=0, atol=1e-9
    )
    span = t[15:] - t[15]
    w_second = (span / span[-1])[:, None]
    carried = shift + kick * span[:, None]
    expected = position[15:] + carried - w_second * carried[-1]
    torch.testing.assert_close(output.position[0, 15:], expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(output.position[0, index], moved[:, 0:3], rtol=0, atol=0)
    # epoch 20 lies half-way from keyframe 1 to 2
    torch.testing.assert_close(motion.gyro_bias[0, 20], 0.5 * moved[2, 15:18], rtol=0, atol=1e-15)
    torch.testing.assert_close(
        motion.covariance[0, 20], 0.5 * (keyframe_cov[1] + keyframe_cov[2]), rtol=1e-12, atol=0
    )
    torch.testing.assert_close(motion.covariance[0, index], keyframe_cov, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("times", "index"),
    [
        ([0.0, 0.2, 0.5, 1.0], [0, 3]),  # two keyframes only; the last at the IMU's last sample
        ([0.0, 0.005, 0.01, 0.5, 0.5025, 1.0], [0, 1, 2, 3, 4, 5]),  # 1 and 1/2 IMU periods apart
    ],
)
def test_output_at_the_edges_is_exact_and_bad_keyframe_positions_raise(times, index):
    """The closed-form turn at unusual epochs is the truth to rounding; keyframes that are not
    the first and last output times (epochs outside them would take another interval's
    state) or a state count that is not K raise ``ValueError``."""
    g = 9.80665
    seq = _turn_sequence(g=g)
    gravity = torch.tensor([0.0, 0.0, -g], dtype=DTYPE)
    t = torch.tensor(times, dtype=DTYPE)
    position, velocity, rotation = _circle(t)
    index = torch.tensor(index)
    zeros = torch.zeros(index.numel(), 3, dtype=DTYPE)
    states = pack_nav_state(position[index], velocity[index], rotation[index], zeros, zeros)
    output, motion = W.interpolate_imu(seq, t, index, states[None], None, gravity)
    torch.testing.assert_close(output.position[0], position, rtol=0, atol=1e-12)
    torch.testing.assert_close(motion.velocity[0], velocity, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="first keyframe to the last"):
        W.interpolate_imu(seq, t, index[:1], states[None, :1], None, gravity)
    with pytest.raises(ValueError, match="first keyframe to the last"):
        W.interpolate_imu(seq, t, index[:-1], states[None, :-1], None, gravity)
    with pytest.raises(ValueError, match="keyframe states for"):
        W.interpolate_imu(seq, t, index, states[None, :-1], None, gravity)


def test_smoothed_output_moves_like_the_truth_into_jumped_keyframes(sim_run):
    """End to end: the front end jumps 1.2 m at its first fix (its initial covariance is
    wide); epoch to epoch the smoothed output steps as the simulator's truth does."""
    run, seq, cfg, frontend, _ = sim_run
    output = W.smooth(seq, frontend, cfg, W.SmootherConfig(covariance=False)).output
    at = torch.searchsorted(run.truth.t[0], output.t[0] - 1e-9)
    truth = run.truth.position[0, at].diff(dim=0)
    jumps = frontend.position[0, frontend.mask[0]].diff(dim=0) - truth
    assert float(jumps.norm(dim=-1).max()) > 1.0
    step = output.position[0].diff(dim=0) - truth
    assert float(step.norm(dim=-1).max()) < 0.02


def test_fix_one_imu_period_after_the_start_is_smoothed(sim_run):
    """Every fix moved 5 ms later (one period of the 200-Hz IMU): the first keyframe
    interval is one sample long, which left the Gauss-Newton matrix singular in float64
    (LM reported convergence at the front end's states, cost 1e18). The smoother must
    converge and score as on the unshifted run. The reference is the same data: fixes 5 ms
    apart (7 mm at the robot's speed) and without the last fix, which the shift moves past
    the IMU's end (one fix of 31 moves this run's ATE by about 30 %)."""
    run, seq, cfg, _, _ = sim_run

    def smoothed_ate(gnss):
        data = dataclasses.replace(seq, gnss=gnss)
        with torch.no_grad():
            result = W.smooth(data, run_eskf(data, cfg), cfg, W.SmootherConfig(covariance=False))
        return result, ate(result.output, seq.ground_truth, align="none", max_dt=0.02)["rmse"]

    result, shifted = smoothed_ate(dataclasses.replace(seq.gnss, t=seq.gnss.t + 0.005))
    assert float(result.t[0, 1] - result.t[0, 0]) == pytest.approx(0.005)
    assert result.lm[0].status == ["converged"]
    assert result.cost < 1e-9 * result.initial_cost
    mask = seq.gnss.mask.clone()
    mask[0, int(torch.nonzero(mask[0])[-1])] = False
    _, reference = smoothed_ate(dataclasses.replace(seq.gnss, mask=mask))
    assert shifted < 1.1 * reference


# --- config and command line -------------------------------------------------------------


def test_smoother_config_errors_name_the_key(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("smoother:\n  window_size: 1\n")
    with pytest.raises(ValueError, match="smoother.window_size"):
        W.load_smoother_config(path)
    path.write_text("smoother:\n  keyframe_spacing: 1\n")
    with pytest.raises(ValueError, match="smoother.keyframe_spacing"):
        W.load_smoother_config(path)
    path.write_text("smoother:\n  noise:\n    gravity_mps2: 9.8\n")
    with pytest.raises(ValueError, match="smoother.noise.gravity_mps2"):
        W.load_smoother_config(path)
    path.write_text("gnss_sigma_m: [1.0, 1.0, 1.0]\nsmoother:\n  noise:\n    nhc_sigma_mps: 0.2\n")
    assert load_config(path).gnss_sigma_m == [1.0, 1.0, 1.0]
    assert W.load_smoother_config(path).noise == {"nhc_sigma_mps": 0.2}


@pytest.fixture(scope="module")
def short_file(tmp_path_factory):
    run = simulate_run(SimConfig(duration_s=20.0), seed=5)
    return write_native(run.sequence, tmp_path_factory.mktemp("smooth") / "run.npz")


def _summary(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_cli_run_smooth_full(short_file, tmp_path, capsys):
    out = tmp_path / "full"
    args = ["run", str(short_file), "--out", str(out), "--smooth", "full", "--no-plot"]
    assert main([*args, "--progress", "off", "--gnss-outage", "8:14"]) == 0
    summary = _summary(capsys)
    figures = summary["smoother"]
    assert figures["mode"] == "full" and figures["converged"]
    assert figures["iterations"] >= 1 and figures["cost"] < figures["initial_cost"]
    assert summary["frontend_wall_s"] <= summary["wall_s"]
    for key in ("ate_rmse_m", "frontend_ate_rmse_m", "outage_rmse_m", "frontend_outage_rmse_m"):
        assert key in summary
    assert summary["outage_rmse_m"] < summary["frontend_outage_rmse_m"]
    assert read_tum(out / "trajectory.tum").length == summary["epochs"]


def test_cli_run_smooth_window_and_config_errors(short_file, tmp_path, capsys):
    config = tmp_path / "c.yaml"
    config.write_text("smoother:\n  window_size: 8\n  output: keyframes\n")
    out = tmp_path / "window"
    args = ["run", str(short_file), "--out", str(out), "--smooth", "window", "--no-plot"]
    assert main([*args, "--config", str(config), "--progress", "off"]) == 0
    summary = _summary(capsys)
    assert summary["smoother"]["mode"] == "window"
    assert summary["smoother"]["output_poses"] == summary["smoother"]["keyframes"]
    config.write_text("smoother:\n  gnss_kernel: l1\n")
    assert main([*args, "--config", str(config), "--progress", "off"]) == 2
    assert "smoother.gnss_kernel" in capsys.readouterr().err


def test_noise_replacement_reaches_the_factors(sim_run):
    _, seq, cfg, frontend, _ = sim_run
    # fixes without their own sigma take the (replaced) configured one
    unknown = dataclasses.replace(seq.gnss, sigma=torch.full_like(seq.gnss.sigma, math.nan))
    seq = dataclasses.replace(seq, gnss=unknown)
    smoother = W.SmootherConfig(noise={"gnss_sigma_m": [0.25, 0.25, 0.5]})
    other = W.build_graph(seq, frontend, cfg, smoother)
    expected = torch.tensor([0.25, 0.25, 0.5], dtype=DTYPE) ** 2
    torch.testing.assert_close(
        torch.diagonal(other.gnss_covariance, dim1=-2, dim2=-1),
        expected.expand_as(other.gnss_position),
    )
    assert dataclasses.asdict(W.SmootherConfig())["noise"] == {}


def test_zero_gnss_sigma_reads_as_not_given(sim_run):
    """A fix whose sigma is 0 (or negative) has none, as the front end reads it: the graph
    takes the configured sigma (0 made its whitening a Cholesky of a singular matrix)."""
    _, seq, cfg, frontend, _ = sim_run
    sigma = seq.gnss.sigma.clone()
    sigma[:, ::2] = 0.0
    sigma[:, 1::4] = -1.0
    odd = W.build_graph(
        dataclasses.replace(seq, gnss=dataclasses.replace(seq.gnss, sigma=sigma)),
        frontend,
        cfg,
        W.SmootherConfig(),
    )
    unknown = dataclasses.replace(seq.gnss, sigma=torch.full_like(sigma, math.nan))
    plain = W.build_graph(dataclasses.replace(seq, gnss=unknown), frontend, cfg, W.SmootherConfig())
    given = (sigma > 0)[:, : odd.gnss_covariance.shape[1]]
    variance = torch.diagonal(odd.gnss_covariance, dim1=-2, dim2=-1)
    expected = torch.diagonal(plain.gnss_covariance, dim1=-2, dim2=-1)
    torch.testing.assert_close(variance[~given], expected[~given])
    assert bool((variance > 0).all())
