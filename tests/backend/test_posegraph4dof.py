"""4-DoF (x, y, z, yaw) pose graphs: Jacobians against finite differences and autodiff, the
optimum against scipy's least squares on the same cost, and a drifted visual-inertial loop
that the loop edges close while roll and pitch stay put."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from msf_torch.backend.posegraph import optimize_pose_graph, pose_graph_config, pose_graph_problem
from msf_torch.backend.posegraph4dof import YAW_POSITION, YawBetweenFactor
from msf_torch.backend.problem import Factor
from msf_torch.backend.variables import pack_pose
from msf_torch.geometry import so3
from msf_torch.io import PoseGraph

DT = torch.float64


def _random_poses(count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    position = torch.randn(count, 3, generator=generator, dtype=DT) * 3.0
    rotation = so3.exp(torch.randn(count, 3, generator=generator, dtype=DT))
    return position, rotation


def _factor(rotation_ij, translation_ij, count: int) -> YawBetweenFactor:
    covariance = torch.diag(torch.tensor([0.04, 0.09, 0.01, 0.002, 0.003, 0.001], dtype=DT))
    factor = YawBetweenFactor(
        "pose",
        torch.arange(count),
        torch.arange(count),
        rotation_ij[None],
        translation_ij[None],
        covariance.expand(1, count, 6, 6),
    )
    factor.kinds = [YAW_POSITION, YAW_POSITION]
    return factor


@pytest.mark.parametrize("half_turn", [False, True])
def test_jacobians_match_finite_differences_and_autodiff(half_turn: bool):
    generator = torch.Generator().manual_seed(4)
    count = 10
    p_i, r_i = _random_poses(count, generator)
    p_j, r_j = _random_poses(count, generator)
    if half_turn:  # relative rotation of pi about z, the yaw axis
        r_j = r_i @ so3.exp(torch.tensor([0.0, 0.0, torch.pi - 1e-9], dtype=DT)).expand_as(r_i)
    z_r = so3.exp(0.1 * torch.randn(count, 3, generator=generator, dtype=DT)) @ (r_i.mT @ r_j)
    z_t = torch.randn(count, 3, generator=generator, dtype=DT)
    factor = _factor(z_r, z_t, count)
    values = [pack_pose(p_i, r_i)[None], pack_pose(p_j, r_j)[None]]
    residual, jacobians = factor.residual_and_jacobians(values, factor.kinds)
    assert residual.shape == (1, count, 6) and jacobians[0].shape == (1, count, 6, 4)
    step = 1e-6
    for slot in range(2):
        numeric = torch.zeros(1, count, 6, 4, dtype=DT)
        for k in range(4):
            delta = torch.zeros(1, count, 4, dtype=DT)
            delta[..., k] = step
            plus, minus = list(values), list(values)
            plus[slot] = YAW_POSITION.retract(values[slot], delta)
            minus[slot] = YAW_POSITION.retract(values[slot], -delta)
            numeric[..., k] = (factor.residual(plus) - factor.residual(minus)) / (2 * step)
        torch.testing.assert_close(jacobians[slot], numeric, atol=1e-6, rtol=1e-6)
    # forward-mode autodiff through the generic Factor route
    _, autodiff = Factor.residual_and_jacobians(factor, values, factor.kinds)
    for ours, reference in zip(jacobians, autodiff, strict=True):
        torch.testing.assert_close(ours, reference, atol=1e-9, rtol=1e-9)


def _ring(count: int, seed: int, yaw_drift: float, position_noise: float):
    """Truth on a circle with small roll/pitch, odometry edges with yaw drift and noise, a
    drifted initial estimate that keeps the true roll and pitch, and three loop edges."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    position = np.stack((10 * np.cos(angle), 10 * np.sin(angle), 0.3 * np.sin(3 * angle)), -1)
    roll = 0.05 * np.sin(2 * angle)
    pitch = 0.04 * np.cos(5 * angle)
    yaw = angle + np.pi / 2
    rotation = Rotation.from_euler("ZYX", np.stack((yaw, pitch, roll), -1)).as_matrix()
    edges = [(k, k + 1) for k in range(count - 1)] + [
        (count - 1, 0),
        (count - 2, 0),
        (count - 1, 1),
    ]
    rel_r, rel_t = [], []
    for i, j in edges:
        rel_r.append(rotation[i].T @ rotation[j])
        rel_t.append(rotation[i].T @ (position[j] - position[i]))
    # drifted estimate: chain the odometry with a yaw error per step and a position error
    est_p, est_yaw = [position[0]], [yaw[0]]
    for k in range(count - 1):
        true_step_world = position[k + 1] - position[k]
        drift = Rotation.from_euler("z", yaw_drift * (k + 1)).as_matrix()
        est_p.append(est_p[-1] + drift @ true_step_world + position_noise * rng.standard_normal(3))
        est_yaw.append(yaw[k + 1] + yaw_drift * (k + 1))
    est_rot = Rotation.from_euler("ZYX", np.stack((est_yaw, pitch, roll), -1)).as_matrix()
    information = np.diag([100.0, 100.0, 100.0, 400.0, 400.0, 400.0])
    graph = PoseGraph(
        vertex_ids=torch.arange(count),
        rotations=torch.as_tensor(est_rot, dtype=DT),
        positions=torch.as_tensor(np.array(est_p), dtype=DT),
        edge_index=torch.as_tensor(edges),
        edge_rotations=torch.as_tensor(np.array(rel_r), dtype=DT),
        edge_translations=torch.as_tensor(np.array(rel_t), dtype=DT),
        edge_information=torch.as_tensor(information, dtype=DT).expand(len(edges), 6, 6).clone(),
    )
    return graph, position, rotation


def test_gradient_matches_finite_differences_of_the_cost():
    graph, _, _ = _ring(12, seed=1, yaw_drift=0.01, position_noise=0.05)
    problem = pose_graph_problem(graph, dof=4)
    values = problem.values
    lin = problem.linearize(values)
    step = 1e-6
    numeric = torch.zeros(problem.dim, dtype=DT)
    for k in range(problem.dim):
        delta = torch.zeros(1, problem.dim, dtype=DT)
        delta[0, k] = step
        plus = problem.cost(problem.retract(values, delta))
        minus = problem.cost(problem.retract(values, -delta))
        numeric[k] = ((plus - minus) / (2 * step))[0]
    torch.testing.assert_close(lin.gradient[0], numeric, atol=1e-5, rtol=1e-6)


def _se3_log(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[rho, phi] of a pose (numpy, independent of msf_torch)."""
    phi = Rotation.from_matrix(rotation).as_rotvec()
    angle = np.linalg.norm(phi)
    skew = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if angle < 1e-4:
        coeff = 1.0 / 12.0
    else:
        coeff = (1 - angle * np.sin(angle) / (2 * (1 - np.cos(angle)))) / angle**2
    v_inv = np.eye(3) - 0.5 * skew + coeff * skew @ skew
    return np.concatenate((v_inv @ translation, phi))


def test_optimum_matches_scipy_least_squares_and_closes_the_loop():
    count = 16
    graph, true_p, true_r = _ring(count, seed=2, yaw_drift=0.01, position_noise=0.03)
    result = optimize_pose_graph(graph, dof=4, config=pose_graph_config(relative_tolerance=1e-14))
    assert result.status == "converged"
    est_r0 = graph.rotations.numpy()
    euler0 = Rotation.from_matrix(est_r0).as_euler("ZYX")
    info_sqrt = np.linalg.cholesky(graph.edge_information[0].numpy()).T
    edges = graph.edge_index.numpy()
    z_r, z_t = graph.edge_rotations.numpy(), graph.edge_translations.numpy()

    def poses(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        full = np.concatenate(
            (np.concatenate((graph.positions[0].numpy(), [euler0[0, 0]])), params)
        )
        full = full.reshape(count, 4)
        rot = Rotation.from_euler(
            "ZYX", np.stack((full[:, 3], euler0[:, 1], euler0[:, 2]), -1)
        ).as_matrix()
        return full[:, :3], rot

    def residuals(params: np.ndarray) -> np.ndarray:
        p, r = poses(params)
        out = []
        for (i, j), zr, zt in zip(edges, z_r, z_t, strict=True):
            rel_r, rel_t = r[i].T @ r[j], r[i].T @ (p[j] - p[i])
            out.append(info_sqrt @ _se3_log(zr.T @ rel_r, zr.T @ (rel_t - zt)))
        return np.concatenate(out)

    start = np.concatenate((graph.positions.numpy()[1:], euler0[1:, :1]), -1).reshape(-1)
    reference = least_squares(residuals, start, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    ref_p, ref_r = poses(reference.x)
    np.testing.assert_allclose(result.graph.positions.numpy(), ref_p, atol=1e-6)
    np.testing.assert_allclose(result.graph.rotations.numpy(), ref_r, atol=1e-7)
    assert result.final_cost == pytest.approx(0.5 * float(reference.fun @ reference.fun), rel=1e-6)
    # roll and pitch untouched; the loop is closed: position error falls from metres to cm
    euler = Rotation.from_matrix(result.graph.rotations.numpy()).as_euler("ZYX")
    np.testing.assert_allclose(euler[:, 1:], euler0[:, 1:], atol=1e-12)
    before = np.linalg.norm(graph.positions.numpy() - true_p, axis=1)
    after = np.linalg.norm(result.graph.positions.numpy() - true_p, axis=1)
    assert before.max() > 1.0 and after.max() < 0.15 * before.max(), (before.max(), after.max())
    true_yaw = Rotation.from_matrix(true_r).as_euler("ZYX")[:, 0]
    yaw_error = np.angle(np.exp(1j * (euler[:, 0] - true_yaw)))
    assert np.abs(yaw_error).max() < 0.02


def test_dof_must_be_four_or_six():
    graph, _, _ = _ring(5, seed=0, yaw_drift=0.0, position_noise=0.0)
    with pytest.raises(ValueError, match="dof"):
        optimize_pose_graph(graph, dof=3)
