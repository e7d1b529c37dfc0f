"""GTSAM peer for the keyframe visual-inertial bundle adjustment (``benchmarks/eqvio.py``).

The same problem as :func:`msf_torch.backend.vio.build_vio_problem`, posed in GTSAM's own
factors and solved by GTSAM's Levenberg-Marquardt from the same initial values:

* per keyframe k: ``X(k)`` (``Pose3``: body -> world), ``V(k)`` (world velocity), ``B(k)``
  (``imuBias.ConstantBias``); per landmark l: ``L(l)`` (``Point3``);
* ``ImuFactor(X_i, V_i, X_j, V_j, B_i)`` on ``PreintegratedImuMeasurements`` with
  ``MakeSharedU(g)``, accelerometer / gyroscope covariances ``sigma^2 I`` (continuous
  densities squared), zero integration covariance, each raw sample integrated with the
  hold time our ``cut_imu`` gives it, linearised at the initial bias of ``B_i``;
* ``BetweenFactorConstantBias(B_i, B_j)`` with sigmas ``sigma_bw sqrt(dT)`` (ours has these
  rows inside its IMU factor);
* ``GenericProjectionFactorCal3_S2`` with ``Cal3_S2(1, 1, 0, 0, 0)`` (normalized
  coordinates), ``body_P_sensor = T_imu_cam`` and the noise model
  ``Robust(Huber(k), Isotropic(2, sigma))`` (GTSAM applies ``rho`` to the whitened norm,
  as ours does);
* priors on ``X(0)`` (Gaussian 6x6 in GTSAM's ``[rotation, translation]`` body-frame
  tangent order, the blocks of ours), ``V(0)`` and ``B(0)`` (GTSAM's ``[accel, gyro]``
  order).

Differences that remain: GTSAM's ``ImuFactor`` residual (its NavState Lie-group error
and its midpoint-free preintegration covariance) is not our exact zero-order-hold
residual, and GTSAM's LM has its own damping and stopping rules; the optimum of the two
costs therefore differs slightly, which is why the benchmark evaluates each solution on
both costs.
"""

from __future__ import annotations

import time
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X


def run_gtsam_vio(
    states: np.ndarray,
    points: np.ndarray,
    obs_keyframe: np.ndarray,
    obs_landmark: np.ndarray,
    obs_uv: np.ndarray,
    imu_gyro: np.ndarray,
    imu_accel: np.ndarray,
    imu_dt: np.ndarray,
    body_rotation_cam: np.ndarray,
    body_translation_cam: np.ndarray,
    feature_sigma: float,
    huber_scale: float | None,
    noise: dict[str, float],
    gravity: float,
    prior_covariance: np.ndarray,
    max_iterations: int = 100,
) -> dict[str, Any]:
    """Build and solve the GTSAM problem.

    Args:
        states: (K, 21) initial nav states ``[p, v, R (row-major), b_g, b_a]``.
        points: (L, 3) initial landmarks, m.
        obs_keyframe, obs_landmark: (M,) int. obs_uv: (M, 2) normalized coordinates.
        imu_gyro, imu_accel: (K - 1, S, 3) raw samples per interval; imu_dt: (K - 1, S) s
            (0 = padding).
        body_rotation_cam (3, 3), body_translation_cam (3,): ``T_imu_cam``.
        feature_sigma: per-axis sigma of ``obs_uv``. huber_scale: Huber ``k`` in sigmas or
            None for plain least squares.
        noise: ``gyro_noise_sigma``, ``accel_noise_sigma``, ``gyro_bias_rw_sigma``,
            ``accel_bias_rw_sigma`` (continuous densities).
        gravity: m/s^2 (world z up).
        prior_covariance: (15, 15) prior on state 0 in our ``[dp, dv, dtheta, db_g, db_a]``
            order; its blocks are reordered to GTSAM's.
        max_iterations: LM limit.
    Returns:
        ``{"states": (K, 21), "points": (L, 3), "iterations", "initial_error",
        "final_error", "build_s", "solve_s", "graph"}``; errors are GTSAM's
        ``0.5 sum rho``; ``graph`` is the factor graph (for :func:`gtsam_error_at`).
    """
    start = time.perf_counter()
    num_kf = states.shape[0]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(num_kf):
        rot = gtsam.Rot3(states[k, 6:15].reshape(3, 3))
        values.insert(X(k), gtsam.Pose3(rot, states[k, 0:3]))
        values.insert(V(k), states[k, 3:6].copy())
        values.insert(B(k), gtsam.imuBias.ConstantBias(states[k, 18:21], states[k, 15:18]))
    for l_index in range(points.shape[0]):
        values.insert(L(l_index), points[l_index].copy())

    pose_cov = np.zeros((6, 6))
    pose_cov[0:3, 0:3] = prior_covariance[6:9, 6:9]
    pose_cov[3:6, 3:6] = prior_covariance[0:3, 0:3]
    graph.add(
        gtsam.PriorFactorPose3(
            X(0), values.atPose3(X(0)), gtsam.noiseModel.Gaussian.Covariance(pose_cov)
        )
    )
    graph.add(
        gtsam.PriorFactorVector(
            V(0),
            states[0, 3:6].copy(),
            gtsam.noiseModel.Gaussian.Covariance(prior_covariance[3:6, 3:6]),
        )
    )
    bias_cov = np.zeros((6, 6))
    bias_cov[0:3, 0:3] = prior_covariance[12:15, 12:15]
    bias_cov[3:6, 3:6] = prior_covariance[9:12, 9:12]
    graph.add(
        gtsam.PriorFactorConstantBias(
            B(0), values.atConstantBias(B(0)), gtsam.noiseModel.Gaussian.Covariance(bias_cov)
        )
    )

    params = gtsam.PreintegrationParams.MakeSharedU(gravity)
    eye = np.eye(3)
    params.setAccelerometerCovariance(noise["accel_noise_sigma"] ** 2 * eye)
    params.setGyroscopeCovariance(noise["gyro_noise_sigma"] ** 2 * eye)
    params.setIntegrationCovariance(np.zeros((3, 3)))
    for k in range(num_kf - 1):
        pim = gtsam.PreintegratedImuMeasurements(params, values.atConstantBias(B(k)))
        for gyro, accel, dt in zip(imu_gyro[k], imu_accel[k], imu_dt[k], strict=True):
            if dt > 0:
                pim.integrateMeasurement(accel, gyro, float(dt))
        graph.add(gtsam.ImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), pim))
        span = float(imu_dt[k].sum())
        sigmas = np.concatenate(
            (
                np.full(3, noise["accel_bias_rw_sigma"] * np.sqrt(span)),
                np.full(3, noise["gyro_bias_rw_sigma"] * np.sqrt(span)),
            )
        )
        graph.add(
            gtsam.BetweenFactorConstantBias(
                B(k),
                B(k + 1),
                gtsam.imuBias.ConstantBias(),
                gtsam.noiseModel.Diagonal.Sigmas(sigmas),
            )
        )

    calibration = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    body_p_cam = gtsam.Pose3(gtsam.Rot3(body_rotation_cam), body_translation_cam)
    pixel_noise = gtsam.noiseModel.Isotropic.Sigma(2, feature_sigma)
    if huber_scale is not None:
        pixel_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(huber_scale), pixel_noise
        )
    for kf, lm, uv in zip(obs_keyframe, obs_landmark, obs_uv, strict=True):
        graph.add(
            gtsam.GenericProjectionFactorCal3_S2(
                uv.copy(), pixel_noise, X(int(kf)), L(int(lm)), calibration, body_p_cam
            )
        )
    build_s = time.perf_counter() - start

    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(max_iterations)
    lm_params.setRelativeErrorTol(1e-10)
    lm_params.setAbsoluteErrorTol(1e-12)
    initial_error = graph.error(values)
    start = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, lm_params)
    result = optimizer.optimize()
    solve_s = time.perf_counter() - start

    out_states = np.zeros_like(states)
    for k in range(num_kf):
        pose = result.atPose3(X(k))
        bias = result.atConstantBias(B(k))
        out_states[k, 0:3] = pose.translation()
        out_states[k, 3:6] = result.atVector(V(k))
        out_states[k, 6:15] = pose.rotation().matrix().reshape(9)
        out_states[k, 15:18] = bias.gyroscope()
        out_states[k, 18:21] = bias.accelerometer()
    out_points = np.stack([result.atPoint3(L(i)) for i in range(points.shape[0])])
    return {
        "states": out_states,
        "points": out_points,
        "iterations": int(optimizer.iterations()),
        "initial_error": float(initial_error),
        "final_error": float(graph.error(result)),
        "build_s": build_s,
        "solve_s": solve_s,
        "graph": graph,
    }


def gtsam_error_at(
    graph: gtsam.NonlinearFactorGraph, states: np.ndarray, points: np.ndarray
) -> float:
    """GTSAM's error (``0.5 sum rho``) of ``graph`` at nav states (K, 21) and points (L, 3)."""
    values = gtsam.Values()
    for k in range(states.shape[0]):
        rot = gtsam.Rot3(states[k, 6:15].reshape(3, 3))
        values.insert(X(k), gtsam.Pose3(rot, states[k, 0:3]))
        values.insert(V(k), states[k, 3:6].copy())
        values.insert(B(k), gtsam.imuBias.ConstantBias(states[k, 18:21], states[k, 15:18]))
    for l_index in range(points.shape[0]):
        values.insert(L(l_index), points[l_index].copy())
    return float(graph.error(values))
