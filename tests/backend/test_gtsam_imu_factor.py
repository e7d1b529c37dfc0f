"""The GTSAM-compatible IMU option against gtsam itself and against finite differences.

``preintegrate_imu_tangent`` + ``GtsamImuFactor`` must pose the problem ``gtsam.ImuFactor``
(Logmap error mode) + ``gtsam.BetweenFactorConstantBias`` poses: increments, bias
Jacobians, noise (``residualCovariance``), error and cost are compared with the gtsam wheel
on random states; the factor's analytic Jacobians with central differences on the
nav-state retraction.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from msf_torch.backend.factors import GtsamImuFactor
from msf_torch.backend.preintegration import (
    ImuIntervals,
    TangentPreintegrated,
    imu_covariance,
    preintegrate_imu_tangent,
)
from msf_torch.backend.variables import NAV_STATE, pack_nav_state
from msf_torch.geometry import so3
from msf_torch.sensors.imu import ImuNoise

gtsam = pytest.importorskip("gtsam")

DTYPE = torch.float64
F, L = 3, 60
G = 9.8
SIGMA_A, SIGMA_G, SIGMA_I = 0.01, 1.75e-4, 3e-3
SIGMA_BA, SIGMA_BG = 1.67e-4, 2.91e-6
# gtsam's tangent order [theta, p, v] -> ours [p, v, theta]
PERM = [3, 4, 5, 6, 7, 8, 0, 1, 2]


def _t(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=DTYPE)


@pytest.fixture(scope="module")
def case():
    """Three intervals of random IMU samples (one padded) and their preintegration."""
    rng = np.random.default_rng(3)
    gyro = rng.normal(size=(F, L, 3)) * 0.5 + rng.normal(size=(F, 1, 3)) * 0.3
    accel = rng.normal(size=(F, L, 3)) + np.array([0.0, 0.0, 9.81])
    dt = 0.01 * (1.0 + 0.05 * rng.standard_normal((F, L)))
    dt[1, -9:] = 0.0  # padding
    accel_bias = rng.normal(size=(F, 3)) * 0.1
    gyro_bias = rng.normal(size=(F, 3)) * 0.01
    pre = preintegrate_imu_tangent(
        ImuIntervals(_t(gyro), _t(accel), _t(dt)), _t(gyro_bias), _t(accel_bias), SIGMA_I
    )
    noise = ImuNoise(_t(SIGMA_G), _t(SIGMA_A), _t(SIGMA_BG), _t(SIGMA_BA))
    params = gtsam.PreintegrationParams.MakeSharedU(G)
    params.setAccelerometerCovariance(np.eye(3) * SIGMA_A**2)
    params.setGyroscopeCovariance(np.eye(3) * SIGMA_G**2)
    params.setIntegrationCovariance(np.eye(3) * SIGMA_I**2)
    pims = []
    for f in range(F):
        pim = gtsam.PreintegratedImuMeasurements(
            params, gtsam.imuBias.ConstantBias(accel_bias[f], gyro_bias[f])
        )
        for a, w, h in zip(accel[f], gyro[f], dt[f], strict=True):
            if h > 0:
                pim.integrateMeasurement(a, w, h)
        pims.append(pim)
    return {"pre": pre, "noise": noise, "pims": pims, "rng": rng}


def _one(pre: TangentPreintegrated, f: int) -> TangentPreintegrated:
    """Interval f of ``pre`` with leading dims (1, 1)."""
    fields = {k: v[f : f + 1][None] for k, v in vars(pre).items()}
    return TangentPreintegrated(**fields)


def _random_pair(rng: np.random.Generator, pim) -> dict[str, np.ndarray]:
    """State i at random, state j near gtsam's prediction from i (rotations up to ~1 rad)."""
    rot_i = so3.exp(_t(rng.normal(size=3))).numpy()
    p_i, v_i = rng.normal(size=3) * 50.0, rng.normal(size=3) * 10.0
    bias = pim.biasHat()
    ba_i = bias.accelerometer() + rng.normal(size=3) * 0.05
    bg_i = bias.gyroscope() + rng.normal(size=3) * 0.005
    pred = pim.predict(
        gtsam.NavState(gtsam.Rot3(rot_i), p_i, v_i), gtsam.imuBias.ConstantBias(ba_i, bg_i)
    )
    rot_j = pred.attitude().matrix() @ so3.exp(_t(rng.normal(size=3) * 0.3)).numpy()
    return {
        "rot_i": rot_i,
        "p_i": p_i,
        "v_i": v_i,
        "ba_i": ba_i,
        "bg_i": bg_i,
        "rot_j": rot_j,
        "p_j": pred.position() + rng.normal(size=3),
        "v_j": pred.velocity() + rng.normal(size=3) * 0.3,
        "ba_j": ba_i + rng.normal(size=3) * 0.01,
        "bg_j": bg_i + rng.normal(size=3) * 0.001,
    }


def _states(s: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    def nav(end: str) -> torch.Tensor:
        parts = [s[f"p_{end}"], s[f"v_{end}"], s[f"rot_{end}"], s[f"bg_{end}"], s[f"ba_{end}"]]
        return pack_nav_state(*[_t(x)[None, None] for x in parts])

    return nav("i"), nav("j")


def _factor(case, f: int) -> GtsamImuFactor:
    pre = _one(case["pre"], f)
    cov = imu_covariance(pre, case["noise"])
    gravity = _t([0.0, 0.0, -G])
    index = torch.tensor([0])
    factor = GtsamImuFactor("state", index, index + 1, pre, cov, gravity)
    factor.kinds = [NAV_STATE, NAV_STATE]
    return factor


def test_increments_and_noise_equal_gtsam(case):
    pre = case["pre"]
    for f, pim in enumerate(case["pims"]):
        zeta = pim.preintegrated()[PERM]
        np.testing.assert_allclose(pre.increment[f].numpy(), zeta, rtol=0, atol=1e-12)
        assert pre.delta_t[f].item() == pytest.approx(pim.deltaTij(), abs=1e-14)
        cov = pre.covariance(case["noise"])[f].numpy()
        ref = pim.residualCovariance()[np.ix_(PERM, PERM)]
        assert np.abs(cov - ref).max() <= 1e-9 * np.abs(ref).max()


def test_error_and_cost_equal_gtsam(case):
    rng = case["rng"]
    for f, pim in enumerate(case["pims"]):
        factor = _factor(case, f)
        for _ in range(3):
            s = _random_pair(rng, pim)
            values = gtsam.Values()
            values.insert(0, gtsam.Pose3(gtsam.Rot3(s["rot_i"]), s["p_i"]))
            values.insert(1, s["v_i"])
            values.insert(2, gtsam.Pose3(gtsam.Rot3(s["rot_j"]), s["p_j"]))
            values.insert(3, s["v_j"])
            values.insert(4, gtsam.imuBias.ConstantBias(s["ba_i"], s["bg_i"]))
            values.insert(5, gtsam.imuBias.ConstantBias(s["ba_j"], s["bg_j"]))
            imu = gtsam.ImuFactor(0, 1, 2, 3, 4, pim)
            sigmas = np.sqrt(pim.deltaTij()) * np.r_[[SIGMA_BA] * 3, [SIGMA_BG] * 3]
            walk = gtsam.BetweenFactorConstantBias(
                4, 5, gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            )
            residual = factor.residual(list(_states(s)))[0, 0].numpy()
            ref = imu.unwhitenedError(values)[PERM]
            assert np.abs(residual[0:9] - ref).max() <= 1e-9 * max(1.0, np.abs(ref).max())
            np.testing.assert_allclose(
                residual[9:15],
                np.r_[s["bg_j"] - s["bg_i"], s["ba_j"] - s["ba_i"]],
                rtol=0,
                atol=1e-15,
            )
            white = factor.sqrt_information[0, 0].numpy() @ residual
            cost = 0.5 * white @ white
            ref_cost = imu.error(values) + walk.error(values)
            assert cost == pytest.approx(ref_cost, rel=1e-9)


def test_jacobians_match_central_differences(case):
    rng = case["rng"]
    step = 1e-6
    for f, pim in enumerate(case["pims"]):
        factor = _factor(case, f)
        states = list(_states(_random_pair(rng, pim)))
        _, jacobians = factor.residual_and_jacobians(states, factor.kinds)
        for slot in range(2):
            numeric = torch.zeros(15, 15, dtype=DTYPE)
            for col in range(15):
                delta = torch.zeros(1, 1, 15, dtype=DTYPE)
                delta[..., col] = step
                plus, minus = list(states), list(states)
                plus[slot] = NAV_STATE.retract(states[slot], delta)
                minus[slot] = NAV_STATE.retract(states[slot], -delta)
                diff = factor.residual(plus) - factor.residual(minus)
                numeric[:, col] = diff[0, 0] / (2.0 * step)
            analytic = jacobians[slot][0, 0]
            scale = numeric.abs().max()
            assert (analytic - numeric).abs().max() <= 1e-7 * scale, f"slot {slot}"
