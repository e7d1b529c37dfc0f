"""Magnetometer hard / soft iron fit: exact recovery, noise at the derived bound, refusals.

Truth: a 48 uT field at 60 deg inclination (ENU: north and down), hard iron within +-30 uT,
a symmetric positive definite soft iron ``W`` up to 15 % off the identity, readings
``m = W^-1 R^T f + b + n``.

Tolerances from the radial residual's Fisher information for directions spread evenly over
the sphere (``E[u u^T] = I / 3``, ``E[u_k^4] = 1 / 5``, ``E[u_k^2 u_l^2] = 1 / 15``) and
per-axis noise sigma on N readings: hard iron ``sigma sqrt(3 / N)`` per axis; ``W`` (det 1)
diagonal ``sqrt(5) sigma / (F sqrt(N))``, off-diagonal ``sqrt(15 / 4) sigma / (F sqrt(N))``;
field ``sigma / sqrt(N)``. The checks allow 6 standard deviations (the soft iron changes
them by up to 15 %); ``test_noise_matches_the_derived_bound`` checks the derivation itself
over 40 draws.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from msf_torch.sensors.magnetometer import corrected_field
from msf_torch.sensors.magnetometer_calibration import (
    direction_coverage,
    fit_magnetometer,
    shape_coverage,
)

FIELD_UT = 48.0
INCLINATION = np.radians(60.0)
WORLD_FIELD = FIELD_UT * np.array([0.0, np.cos(INCLINATION), -np.sin(INCLINATION)])


def _soft_iron(rng: np.random.Generator) -> np.ndarray:
    """Symmetric positive definite W with eigenvalues within 15 % of 1."""
    a = rng.normal(size=(3, 3))
    e = (a + a.T) / 2
    return np.eye(3) + 0.15 * e / np.abs(np.linalg.eigvalsh(e)).max()


def _readings(rotations: Rotation, hard: np.ndarray, soft: np.ndarray, noise: float, rng):
    body = rotations.inv().apply(WORLD_FIELD)
    return body @ np.linalg.inv(soft).T + hard + noise * rng.normal(size=body.shape)


def _case(seed: int, n: int, noise: float, soft: bool = True):
    rng = np.random.default_rng(seed)
    hard = rng.uniform(-30.0, 30.0, 3)
    w = _soft_iron(rng) if soft else np.eye(3)
    rotations = Rotation.random(n, random_state=seed)
    return _readings(rotations, hard, w, noise, rng), hard, w


def _yawing(n: int, seed: int, tilt_deg: float = 0.0) -> Rotation:
    """A robot turning through every heading with roll and pitch uniform in +-tilt."""
    rng = np.random.default_rng(seed)
    tilt = np.radians(tilt_deg)
    angles = np.column_stack(
        (rng.uniform(0, 2 * np.pi, n), rng.uniform(-tilt, tilt, n), rng.uniform(-tilt, tilt, n))
    )
    return Rotation.from_euler("ZYX", angles)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noiseless_ellipsoid_recovers_hard_and_soft_iron(seed):
    m, hard, w = _case(seed, 200, 0.0)
    cal = fit_magnetometer(m)
    scale = np.cbrt(np.linalg.det(w))  # W is fitted with det 1: W_true / scale
    assert np.abs(cal.hard_iron - hard).max() < 1e-9
    assert np.abs(cal.soft_iron - w / scale).max() < 1e-9
    assert np.allclose(cal.soft_iron, cal.soft_iron.T, rtol=0, atol=1e-15)
    assert abs(cal.field_uT - FIELD_UT / scale) < 1e-9
    assert cal.residual_rms_uT < 1e-9 and cal.samples == 200 and cal.model == "ellipsoid"
    assert cal.coverage > 0.75  # 200 random directions: 3 lambda_min about 1 - 0.1
    norms = np.linalg.norm(cal.correct(m), axis=1)
    assert np.abs(norms - cal.field_uT).max() < 1e-9
    # the contract's correction is the same W (m - b)
    torch_corrected = corrected_field(
        torch.from_numpy(m), torch.from_numpy(cal.hard_iron), torch.from_numpy(cal.soft_iron)
    )
    np.testing.assert_allclose(torch_corrected.numpy(), cal.correct(m), rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", [4, 5, 6, 7, 8])
def test_noisy_ellipsoid_within_the_derived_tolerance(seed):
    sigma, n = 0.3, 500
    m, hard, w = _case(seed, n, sigma)
    cal = fit_magnetometer(m)
    scale = np.cbrt(np.linalg.det(w))
    assert np.abs(cal.hard_iron - hard).max() < 6 * sigma * np.sqrt(3 / n)
    error = np.abs(cal.soft_iron - w / scale)
    assert error.max() < 6 * np.sqrt(5) * sigma / (FIELD_UT * np.sqrt(n))
    assert abs(cal.field_uT - FIELD_UT / scale) < 6 * sigma / np.sqrt(n)
    # the corrected norms scatter by the radial noise: sigma |W^T u|, RMS over directions
    radial = sigma * np.sqrt(np.trace(cal.soft_iron @ cal.soft_iron.T) / 3)
    assert 0.88 * radial < cal.residual_rms_uT < 1.12 * radial
    raw_spread = np.linalg.norm(m, axis=1).std()
    corrected_spread = np.linalg.norm(cal.correct(m), axis=1).std()
    assert raw_spread > 5.0 and corrected_spread < 1.12 * radial


def test_noise_matches_the_derived_bound():
    """Over 40 draws the fit's errors have the derived standard deviations (within the
    sampling spread of 40 draws): the algebraic fit is efficient at full coverage."""
    sigma, n = 0.3, 500
    hard_errors, diagonal_errors = [], []
    for seed in range(100, 140):
        m, hard, w = _case(seed, n, sigma)
        cal = fit_magnetometer(m)
        hard_errors.append(cal.hard_iron - hard)
        diagonal_errors.append(np.diag(cal.soft_iron - w / np.cbrt(np.linalg.det(w))))
    hard_std = np.sqrt(np.mean(np.square(hard_errors)))
    diagonal_std = np.sqrt(np.mean(np.square(diagonal_errors)))
    # 120 numbers each: the RMS is within ~13 % of the true std at 2 sigma
    assert 0.8 < hard_std / (sigma * np.sqrt(3 / n)) < 1.25
    assert 0.8 < diagonal_std / (np.sqrt(5) * sigma / (FIELD_UT * np.sqrt(n))) < 1.25


def test_sphere_model_on_hard_iron_only_readings():
    m, hard, _ = _case(9, 100, 0.0, soft=False)
    cal = fit_magnetometer(m, model="sphere")
    assert np.abs(cal.hard_iron - hard).max() < 1e-9
    assert np.array_equal(cal.soft_iron, np.eye(3)) and cal.model == "sphere"
    assert abs(cal.field_uT - FIELD_UT) < 1e-9 and cal.residual_rms_uT < 1e-9
    sigma, n = 0.3, 500
    m, hard, _ = _case(10, n, sigma, soft=False)
    cal = fit_magnetometer(m, model="sphere")
    assert np.abs(cal.hard_iron - hard).max() < 6 * sigma * np.sqrt(3 / n)
    assert abs(cal.field_uT - FIELD_UT) < 6 * sigma / np.sqrt(n)
    assert 0.88 * sigma < cal.residual_rms_uT < 1.12 * sigma
    assert fit_magnetometer(m[:4], model="sphere").samples == 4


def test_sphere_on_a_narrow_band_reaches_the_derived_bound():
    """Yawing with roll and pitch within +-5 deg: the hard iron along the yaw axis is weakly
    observed; the refined sphere's errors match the Fisher information (the linear fit
    alone is about 4.5 times worse here). Per draw the error along each eigenvector of the
    directions' covariance C is divided by its predicted std ``sigma / sqrt(N lambda)``."""
    sigma, n, hard = 0.3, 500, np.array([12.0, -25.0, 18.0])
    normalised = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        rotations = _yawing(n, 200 + seed, tilt_deg=5.0)
        directions = rotations.inv().apply(WORLD_FIELD) / FIELD_UT
        m = _readings(rotations, hard, np.eye(3), sigma, rng)
        cal = fit_magnetometer(m, model="sphere")
        values, vectors = np.linalg.eigh(np.cov(directions.T, bias=True))
        normalised.append(((cal.hard_iron - hard) @ vectors) / (sigma / np.sqrt(n * values)))
    rms = np.sqrt(np.mean(np.square(normalised), axis=0))  # 20 draws: within ~30 % of 1
    assert np.all((rms > 0.6) & (rms < 1.45)), rms


def test_a_robot_that_only_yaws():
    """One circle of directions: the ellipsoid is refused (pointing to the sphere), the
    sphere warns and fits the horizontal hard iron, the vertical one set to 0."""
    rng = np.random.default_rng(11)
    hard = np.array([12.0, -25.0, 18.0])
    for noise in (0.0, 0.3):
        m = _readings(_yawing(400, 11), hard, np.eye(3), noise, rng)
        assert direction_coverage(m - hard) < 1e-3
        with pytest.raises(ValueError, match=r"span too little .* model=\"sphere\""):
            fit_magnetometer(m)
        with pytest.warns(UserWarning, match="close to one plane .* unobservable and set to 0"):
            cal = fit_magnetometer(m, model="sphere")
        tolerance = 1e-9 if noise == 0 else 6 * noise * np.sqrt(2 / 400)
        assert np.abs(cal.hard_iron - [12.0, -25.0, 0.0]).max() < tolerance
        # the corrected magnitude includes the vertical offset left in
        vertical = hard[2] + WORLD_FIELD[2]
        expected = np.hypot(FIELD_UT * np.cos(INCLINATION), vertical)
        assert abs(cal.field_uT - expected) < max(tolerance, 1e-9)
        assert cal.coverage < 1e-3


def test_readings_on_two_circles_leave_the_shape_undetermined():
    """The sensor spun about its z axis upright and lying on its side: two coaxial circles
    of directions (coverage well above the planar limit), but an ellipsoid stretched along
    their axis fits them too."""
    spin = np.random.default_rng(12).uniform(0, 2 * np.pi, 400)
    tilt = np.repeat([0.0, np.pi / 2], 200)
    rotations = Rotation.from_euler("YZ", np.column_stack((tilt, spin)))  # R = Ry Rz
    m = _readings(rotations, np.array([5.0, 6.0, 7.0]), np.eye(3), 0.0, np.random.default_rng(0))
    assert direction_coverage(m - [5.0, 6.0, 7.0]) > 0.1
    assert shape_coverage(m - [5.0, 6.0, 7.0]) < 1e-9
    with pytest.raises(ValueError, match="shape undetermined"):
        fit_magnetometer(m)
    rotations = Rotation.concatenate([rotations, Rotation.random(30, random_state=12)])
    m = _readings(rotations, np.array([5.0, 6.0, 7.0]), np.eye(3), 0.0, np.random.default_rng(0))
    assert np.abs(fit_magnetometer(m).hard_iron - [5.0, 6.0, 7.0]).max() < 1e-9


def test_coverage_values():
    """1 for even directions or the six axes, 0.25 for one hemisphere, 0 for one cone."""
    axes = np.vstack((np.eye(3), -np.eye(3)))
    assert direction_coverage(axes) == pytest.approx(1.0)
    u = np.random.default_rng(13).normal(size=(200_000, 3))
    assert direction_coverage(u) == pytest.approx(1.0, abs=0.01)
    assert direction_coverage(u * np.sign(u[:, 2:])) == pytest.approx(0.25, abs=0.01)
    assert shape_coverage(u) == pytest.approx(1.0, abs=0.02)
    cone = np.column_stack((np.cos(np.arange(50.0)), np.sin(np.arange(50.0)), np.ones(50)))
    assert direction_coverage(cone) < 1e-12


def test_bad_input_is_refused():
    m, _, _ = _case(14, 20, 0.0)
    with pytest.raises(ValueError, match="at least 10 readings, got 9"):
        fit_magnetometer(m[:9])
    with pytest.raises(ValueError, match="at least 4 readings, got 3"):
        fit_magnetometer(m[:3], model="sphere")
    bad = m.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match="reading 5 is not finite"):
        fit_magnetometer(bad)
    with pytest.raises(ValueError, match=r"must be \(N, 3\)"):
        fit_magnetometer(m[:, :2])
    with pytest.raises(ValueError, match="model must be"):
        fit_magnetometer(m, model="ellipse")
    with pytest.raises(ValueError, match="all 20 readings are equal"):
        fit_magnetometer(np.ones((20, 3)))
    # points on a hyperboloid of one sheet x^2 + y^2 - z^2 = 1: a quadric, not an ellipsoid
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    h = np.repeat([-1.0, -0.3, 0.4, 1.2], 10)
    r = np.sqrt(1 + h**2)
    hyperboloid = 30.0 * np.column_stack((r * np.cos(t * 3.1), r * np.sin(t * 3.1), h))
    with pytest.raises(ValueError, match="not an ellipsoid"):
        fit_magnetometer(hyperboloid)
