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

from msf_torch.sensors.magnetometer import corrected_field, magnetometer_heading_residual
from msf_torch.sensors.magnetometer_calibration import (
    circle_coverage,
    direction_coverage,
    fit_magnetometer,
    fit_magnetometer_levelled,
    planarity,
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
    """One circle of directions: the ellipsoid is refused (pointing to the ellipse), the
    sphere warns and fits the horizontal hard iron, the vertical one set to 0."""
    rng = np.random.default_rng(11)
    hard = np.array([12.0, -25.0, 18.0])
    for noise in (0.0, 0.3):
        m = _readings(_yawing(400, 11), hard, np.eye(3), noise, rng)
        assert direction_coverage(m - hard) < 1e-3
        with pytest.raises(ValueError, match=r"span too little .* with model=\"ellipse\"$"):
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


HORIZONTAL = FIELD_UT * np.cos(INCLINATION)
VERTICAL = WORLD_FIELD[2]
# a yawing robot's soft iron: W^-1 with 4 % in the plane and 3 % coupling x / y to z
COUPLED = np.linalg.inv([[1.04, 0.02, 0.03], [0.02, 0.97, -0.03], [0.03, -0.03, 1.02]])


def _heading_errors(cal, rotations: Rotation, hard: np.ndarray, soft: np.ndarray) -> np.ndarray:
    """(N,) heading residuals, rad, of the noise-free readings in ``rotations`` corrected by
    ``cal``: the front end's ``wrap(azimuth(R W (m - b)) - D)`` at the true attitude (D = 0:
    WORLD_FIELD points north), zero for an exact calibration."""
    clean = _readings(rotations, hard, soft, 0.0, np.random.default_rng(0))
    rotation = torch.from_numpy(rotations.as_matrix())
    residual, _ = magnetometer_heading_residual(rotation, torch.from_numpy(cal.correct(clean)), 0.0)
    return residual[..., 0].numpy()


@pytest.mark.parametrize("seed", [20, 21, 22])
def test_noiseless_ellipse_recovers_the_in_plane_iron(seed):
    """A level robot yawing all round, soft iron only in the plane: the in-plane hard iron
    and the det-1 in-plane soft iron exactly, ``b_z = 0``, ``W_zz = 1``, exact headings."""
    rng = np.random.default_rng(seed)
    hard = np.append(rng.uniform(-30.0, 30.0, 2), rng.uniform(-10.0, 10.0))
    soft = np.eye(3)
    soft[:2, :2] = _soft_iron(rng)[:2, :2]
    rotations = _yawing(300, seed)
    m = _readings(rotations, hard, soft, 0.0, rng)
    cal = fit_magnetometer(m, model="ellipse")
    in_plane = soft[:2, :2] / np.sqrt(np.linalg.det(soft[:2, :2]))
    assert np.abs(cal.hard_iron - [hard[0], hard[1], 0.0]).max() < 1e-9
    assert np.abs(cal.soft_iron[:2, :2] - in_plane).max() < 1e-9
    assert np.abs(cal.soft_iron - np.eye(3))[2].max() < 1e-12
    assert np.abs(cal.soft_iron - cal.soft_iron.T).max() < 1e-15
    # corrected: the horizontal field scaled by 1 / sqrt(det W_xy), and the vertical plus b_z
    horizontal = HORIZONTAL / np.sqrt(np.linalg.det(soft[:2, :2]))
    assert abs(cal.field_uT - np.hypot(horizontal, VERTICAL + hard[2])) < 1e-9
    assert cal.residual_rms_uT < 1e-9 and cal.samples == 300 and cal.model == "ellipse"
    assert 0.7 < cal.coverage <= 1.0  # 300 random headings
    assert np.abs(_heading_errors(cal, rotations, hard, soft)).max() < 1e-9


def test_noiseless_ellipse_with_coupling_gives_exact_headings():
    """Soft iron coupling x / y to z tilts the readings' plane: ``W`` maps the truth's
    horizontal columns ``W_true^-1 e_x, e_y`` onto the body's x, y axes (scaled), and the
    corrected readings are the true corrected field (scaled) in x and y: exact headings.
    Only z differs (``b_z`` and the vertical scale are unobservable). The sphere leaves
    0.06 rad, a plane-normal embedding (``W`` the identity along the plane's normal, the
    hard iron along it 0) 0.03 rad."""
    hard = np.array([12.0, -25.0, 18.0])
    rotations = _yawing(400, 23)
    m = _readings(rotations, hard, COUPLED, 0.0, np.random.default_rng(0))
    cal = fit_magnetometer(m, model="ellipse")
    assert np.abs(_heading_errors(cal, rotations, hard, COUPLED)).max() < 1e-9
    columns = cal.soft_iron @ np.linalg.inv(COUPLED)[:, :2]
    scale = np.sqrt(np.linalg.det(columns[:2]))
    assert np.abs(columns / scale - np.eye(3)[:, :2]).max() < 1e-9
    truth = (m - hard) @ COUPLED.T
    assert np.abs(cal.correct(m)[:, :2] - scale * truth[:, :2]).max() < 1e-9
    assert abs(cal.hard_iron[2]) < 1e-12 and abs(cal.soft_iron[2, 2] - 1.0) < 1e-12
    assert abs(np.linalg.det(cal.soft_iron) - 1.0) < 1e-12
    with pytest.warns(UserWarning, match="close to one plane"):
        sphere = fit_magnetometer(m, model="sphere")
    assert np.abs(_heading_errors(sphere, rotations, hard, COUPLED)).max() > 0.05
    centre = m.mean(0)  # the readings' centre, the identity along their plane's normal
    normal = np.linalg.eigh(np.cov(m.T))[1][:, 0]
    projector = np.eye(3) - np.outer(normal, normal)
    along_normal = type(cal)(
        hard_iron=centre - (normal @ centre) * normal,
        soft_iron=projector @ cal.soft_iron @ projector + np.outer(normal, normal),
        field_uT=cal.field_uT,
        residual_rms_uT=0.0,
        coverage=cal.coverage,
        samples=cal.samples,
        model="ellipse",
    )
    assert np.abs(_heading_errors(along_normal, rotations, hard, COUPLED)).max() > 0.02


def _ellipse_heading_rms(seed: int, tilt_deg: float, soft: np.ndarray, hard: np.ndarray):
    """RMS over 500 readings (0.3 uT) of the heading error after the ellipse fit, and its
    derived value ``2 sigma_eff / (H sqrt(N))``: the in-plane centre (2 numbers, each
    ``sigma_eff sqrt(2 / N)``, heading ``|delta b| / H`` over the turn) and the det-1 shape
    (2 numbers, ``sigma_eff sqrt(2 / N) / H``, heading the same) each add ``2 sigma_eff^2 /
    (N H^2)`` to its mean square; roll and pitch uniform in +-T move the horizontal
    components by the vertical field times the tilt, in-plane noise of ``V T / sqrt(3)``:
    ``sigma_eff^2 = sigma^2 + V^2 T^2 / 3``."""
    sigma, n, tilt = 0.3, 500, np.radians(tilt_deg)
    rng = np.random.default_rng(seed)
    rotations = _yawing(n, seed, tilt_deg)
    cal = fit_magnetometer(_readings(rotations, hard, soft, sigma, rng), model="ellipse")
    errors = _heading_errors(cal, rotations, hard, soft)
    effective = np.sqrt(sigma**2 + (VERTICAL * tilt) ** 2 / 3)
    return np.sqrt(np.mean(errors**2)), 2 * effective / (HORIZONTAL * np.sqrt(n))


@pytest.mark.parametrize("seed", [24, 25, 26, 27])
def test_noisy_ellipse_within_the_derived_bound(seed):
    """Level and yawing, the coupled soft iron; and roll / pitch within +-1 deg (planar up
    to the noise), no coupling and ``b_z = 0`` (so no vertical offset leaks into the heading
    under the tilt): heading RMS below 3 times the derived value (its square is about
    chi-square with 4 degrees of freedom / 4: 3 times is past 1e-6 of the tail)."""
    rms, derived = _ellipse_heading_rms(seed, 0.0, COUPLED, np.array([12.0, -25.0, 18.0]))
    assert rms < 3 * derived, (rms, derived)
    level = np.diag([1 / 1.04, 1 / 0.97, 1.0])
    rms, derived = _ellipse_heading_rms(seed, 1.0, level, np.array([12.0, -25.0, 0.0]))
    assert rms < 3 * derived, (rms, derived)


def test_ellipse_noise_matches_the_derived_value():
    """Over 40 draws the heading errors' mean square is the derived one, level and at +-1
    deg: the algebraic fit is efficient on one full turn (the tilt acts as in-plane noise)."""
    hard = np.array([12.0, -25.0, 0.0])
    level = np.diag([1 / 1.04, 1 / 0.97, 1.0])
    for tilt, soft in ((0.0, COUPLED), (1.0, level)):
        rms, derived = zip(
            *(_ellipse_heading_rms(seed, tilt, soft, hard) for seed in range(40)), strict=True
        )
        ratio = np.sqrt(np.mean(np.square(rms))) / derived[0]  # 160 chi-square terms: +-11 %
        assert 0.8 < ratio < 1.25, (tilt, ratio)


def test_ellipse_refusals_and_warning():
    """Readings that do not go round, that cover the sphere, whose plane is tilted far from
    the body's xy plane (not soft iron), too few; tilts beyond the noise warn."""
    hard = np.array([12.0, -25.0, 18.0])
    half = Rotation.from_euler("z", np.linspace(0.0, np.pi, 100)[:, None])
    with pytest.raises(ValueError, match=r"do not go round the circle \(coverage 0.00"):
        fit_magnetometer(
            _readings(half, hard, COUPLED, 0.0, np.random.default_rng(0)), model="ellipse"
        )
    m, _, _ = _case(28, 200, 0.0)
    with pytest.raises(ValueError, match=r'cover the sphere .* with model="ellipsoid"'):
        fit_magnetometer(m, model="ellipse")
    m = _readings(
        _yawing(200, 28) * Rotation.from_euler("x", 0.3),
        hard,
        np.eye(3),
        0.0,
        np.random.default_rng(0),
    )
    with pytest.raises(ValueError, match=r"tilted 17.\d deg from the body's xy plane"):
        fit_magnetometer(m, model="ellipse")
    with pytest.raises(ValueError, match="the ellipse model needs at least 8 readings, got 7"):
        fit_magnetometer(m[:7], model="ellipse")
    rng = np.random.default_rng(29)
    m = _readings(_yawing(500, 29, tilt_deg=8.0), hard, COUPLED, 0.3, rng)
    assert not planarity(m)[0]
    with pytest.warns(UserWarning, match="uT thick off their plane, more than 2 x their noise"):
        assert fit_magnetometer(m, model="ellipse").model == "ellipse"


def test_circle_coverage_values():
    """1 for even angles, about 0.5 for 7/8 of a turn, 0.16 for 3/4, 0.005 for a half."""
    for turn, expected, tolerance in ((1.0, 1.0, 1e-3), (0.875, 0.497, 0.01), (0.75, 0.160, 0.01)):
        angle = np.linspace(0.0, 2 * np.pi * turn, 4000, endpoint=turn < 1)
        vectors = np.column_stack((np.cos(angle), np.sin(angle)))
        assert circle_coverage(3.0 * vectors) == pytest.approx(expected, abs=tolerance)
    angle = np.linspace(0.0, np.pi, 4000)
    assert circle_coverage(np.column_stack((np.cos(angle), np.sin(angle)))) < 0.006
    assert circle_coverage(np.zeros((5, 2))) == 0.0


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
        fit_magnetometer(m, model="circle")
    with pytest.raises(ValueError, match="all 20 readings are equal"):
        fit_magnetometer(np.ones((20, 3)))
    # points on a hyperboloid of one sheet x^2 + y^2 - z^2 = 1: a quadric, not an ellipsoid
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    h = np.repeat([-1.0, -0.3, 0.4, 1.2], 10)
    r = np.sqrt(1 + h**2)
    hyperboloid = 30.0 * np.column_stack((r * np.cos(t * 3.1), r * np.sin(t * 3.1), h))
    with pytest.raises(ValueError, match="not an ellipsoid"):
        fit_magnetometer(hyperboloid)


def _circling(n: int, seed: int, mean_roll_deg: float) -> np.ndarray:
    """(n, 3) ZYX angles (yaw, pitch, roll) of a robot driving 2.5 circles over bumps: roll
    ``mean_roll_deg`` (leaning into a bowl) +-1.5 deg and pitch +-2 deg, each at its own
    frequency, so the tilts vary within a turn."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)
    yaw = 5 * np.pi * s + 0.3 * np.sin(9 * s)
    roll = np.radians(mean_roll_deg) + np.radians(1.5) * np.sin(20.7 * s + rng.uniform(0, 6))
    pitch = np.radians(2.0) * np.sin(25.8 * s + rng.uniform(0, 6))
    return np.column_stack((yaw, pitch, roll))


def test_noiseless_levelled_fit_recovers_the_iron():
    """With varying tilts known, noiseless: ``vertical=True`` recovers everything up to the
    overall scale (b with b_z, W with det W_xy^-1 = 1, the field scaled alike); the default
    (b_z and the vertical scale held at the ellipse's b_z = 0, det W = 1) recovers iron that
    keeps that convention. Attitudes (N, 3, 3) with any yaw give the same."""
    angles = _circling(400, 40, 2.0)
    rotations = Rotation.from_euler("ZYX", angles)
    hard = np.array([12.0, -25.0, 18.0])
    m = _readings(rotations, hard, COUPLED, 0.0, np.random.default_rng(0))
    cal = fit_magnetometer_levelled(m, angles[:, [2, 1]], vertical=True)
    distortion = np.linalg.inv(COUPLED)
    scale = np.sqrt(np.linalg.det(distortion[:2, :2]))
    assert np.abs(cal.hard_iron - hard).max() < 1e-9
    assert np.abs(cal.soft_iron - COUPLED * scale).max() < 1e-9
    assert abs(cal.field_uT - FIELD_UT * scale) < 1e-9
    assert cal.residual_rms_uT < 1e-9 and cal.model == "levelled" and cal.samples == 400
    assert 0.7 < cal.coverage < 0.9  # 2.5 turns: the extra half weighs one side
    again = fit_magnetometer_levelled(m, rotations.as_matrix(), vertical=True)
    assert np.abs(again.hard_iron - hard).max() < 1e-9
    # the ellipse's convention: det S = 1 with det S_xy = 1, b_z = 0
    top, column = distortion[:2, :2] / scale, distortion[:2, 2]
    convention = np.block(
        [[top, column[:, None]], [np.append(column, 1 + column @ np.linalg.solve(top, column))]]
    )
    in_plane = np.array([12.0, -25.0, 0.0])
    m = _readings(rotations, in_plane, np.linalg.inv(convention), 0.0, np.random.default_rng(0))
    cal = fit_magnetometer_levelled(m, angles[:, [2, 1]])
    assert np.abs(cal.hard_iron - in_plane).max() < 1e-9
    assert np.abs(cal.soft_iron - np.linalg.inv(convention)).max() < 1e-9
    assert abs(cal.field_uT - FIELD_UT) < 1e-9 and cal.residual_rms_uT < 1e-9
    ellipse = fit_magnetometer(m, model="ellipse")
    assert np.abs(ellipse.hard_iron - in_plane).max() > 1.0  # 2 deg of lean: V * 0.035


def test_levelled_fit_on_circles_over_bumps():
    """0.3 uT noise, 500 readings, a 2-deg lean (mean roll) with +-1.5 / 2 deg bumps, b_z =
    4 uT: the ellipse's centre is off by the vertical field times the lean (> 0.5 uT in the
    plane), while the readings still look planar; the levelled fit is within 0.3 uT (the
    unfitted b_z times the lean, 0.14 uT, and the noise, sigma sqrt(2 / N) = 0.02 uT per
    axis; 0.20 uT at most over 40 draws). ``vertical=True`` also fits b_z, weakly: 1.4 uT
    RMS over 40 draws with these bumps (bound 4.5 uT), 0.14 uT at most in the plane."""
    hard = np.array([12.0, -25.0, 4.0])
    for seed in range(41, 44):
        angles = _circling(500, seed, 2.0)
        rng = np.random.default_rng(seed)
        m = _readings(Rotation.from_euler("ZYX", angles), hard, COUPLED, 0.3, rng)
        assert planarity(m)[0]  # no trace of the tilts: the ellipse fits without a warning
        ellipse = fit_magnetometer(m, model="ellipse")
        levelled = fit_magnetometer_levelled(m, angles[:, [2, 1]])
        vertical = fit_magnetometer_levelled(m, angles[:, [2, 1]], vertical=True)
        assert np.linalg.norm(ellipse.hard_iron[:2] - hard[:2]) > 0.5
        assert np.linalg.norm(levelled.hard_iron[:2] - hard[:2]) < 0.3
        assert levelled.hard_iron[2] == 0.0
        assert np.linalg.norm(vertical.hard_iron[:2] - hard[:2]) < 0.2
        assert abs(vertical.hard_iron[2] - hard[2]) < 4.5
        assert 0.2 < levelled.residual_rms_uT < 0.3  # sigma sqrt(2 / 3): 2 of 3 axes fitted


def test_levelled_fit_refusals():
    angles = _circling(100, 45, 0.0)
    m = _readings(
        Rotation.from_euler("ZYX", angles), np.zeros(3), np.eye(3), 0.0, np.random.default_rng(0)
    )
    with pytest.raises(ValueError, match=r"tilt must be \(N, 2\) roll and pitch or \(N, 3, 3\)"):
        fit_magnetometer_levelled(m, angles[:50, [2, 1]])
    bad = angles[:, [2, 1]].copy()
    bad[3, 0] = np.inf
    with pytest.raises(ValueError, match="must be finite"):
        fit_magnetometer_levelled(m, bad)
    with pytest.raises(ValueError, match="the levelled fit needs at least 10 readings, got 9"):
        fit_magnetometer_levelled(m[:9], angles[:9, [2, 1]])
