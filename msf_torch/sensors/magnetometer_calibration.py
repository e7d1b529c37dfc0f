"""Magnetometer hard- and soft-iron calibration from readings taken in many orientations
(or, for a robot that only yaws, in every heading on level ground).

A magnetometer on a vehicle reads ``m = W^-1 f + b`` (body frame, uT): the local earth
field ``f`` (magnitude ``F``, the same in every orientation) distorted by the soft iron
``W^-1`` (steel that bends the field) and offset by the hard iron ``b`` (magnetised parts,
currents). The readings of a sensor turned through many orientations therefore lie on an
ellipsoid ``|W (m - b)| = F``; the correction ``f_b = W (m - b)``
(:func:`msf_torch.sensors.magnetometer.corrected_field`, config keys
``magnetometer_hard_iron_uT`` and ``magnetometer_soft_iron``) maps them onto the sphere of
radius ``F``.

Models
------
``"ellipsoid"`` (hard and soft iron, 9 parameters): an algebraic least-squares fit of the
general quadric ``x^T M x + 2 v^T x + d = 0`` (the right singular vector of the smallest
singular value of the design matrix, on readings centred and scaled to unit RMS radius),
its centre ``b = -M^-1 v`` and shape ``A = M / (b^T M b - d)``, ``|L (m - b)| = 1`` with ``L``
the symmetric positive definite square root of ``A``. ``W`` is ``L`` scaled to
``det W = 1``: it keeps the volume, so ``F`` is the geometric mean of the ellipsoid's
semi-axes and ``W`` is the identity when there is no soft iron. A quadric fit with
mixed-sign ``M`` (a hyperboloid) or an imaginary ellipsoid is refused.

``"sphere"`` (hard iron only, ``W = I``): the linear least-squares sphere
``|m|^2 = 2 b . m + k``, refined by Gauss-Newton on the radial residual ``|m - b| - F``
(the linear fit alone is far from efficient on a narrow band of directions: 6 uT off
where the refined fit is 0.6 uT with T = 3 deg below); ``F`` is the mean distance of the
readings from ``b``.

``"ellipse"`` (hard and soft iron in the plane, for a robot that only yaws about its body z
axis on level ground): the readings ``m = c + [T; t^T] u`` lie on an ellipse in 3-D
(``u = (cos, sin)`` of the heading, ``c = V W^-1 e_z + b``, ``[T; t^T]`` the first two
columns of ``S = W^-1`` times the horizontal field ``H``). Their plane is the covariance's
smallest eigenvector's (``~ e_z``; tilted by the soft iron's xz / yz coupling ``t``), and
an algebraic conic fit of the in-plane coordinates (the right singular vector of the
smallest singular value, on coordinates scaled to unit RMS radius; a conic that is not a
real ellipse is refused) gives ``c`` and ``G = [T; t^T] [T; t^T]^T``. A symmetric ``S``
makes ``T`` symmetric, so ``T = sqrt(G_xy)`` and ``t = T^-1 G_xy,z``: the data fix ``S``'s
first two columns up to scale, all but ``S_zz``. ``T`` is normalised to ``det T = 1`` (the
horizontal area kept: the corrected horizontal radius is the geometric mean of the
ellipse's semi-axes, ``W_xy`` the identity without soft iron); ``S_zz = 1 + t^T T^-1 t``
gives ``det S = det W = 1`` and ``W_zz = 1``. The hard iron is ``b = c - k S e_z`` with
``k = c_z / S_zz`` (``b_z = 0``). Then a level reading corrects to exactly
``(rho cos, rho sin, k)``: the heading is exact, whatever the coupling (the in-plane hard
iron is the ellipse's centre less ``k t``, about ``V |t|``). Unobservable: ``b_z`` and the
vertical field's scale (``k`` stands for them); tilted, the error of ``k`` against the true
vertical leaks into the heading by up to ``|dk| sin(tilt) / H``. Identity along the plane's
normal with the hard iron along it 0 instead leaves ``|V| |t| / H`` (0.03 rad for 3 %
coupling, see the tests). The readings' plane must be within ``ELLIPSE_MAX_TILT_RAD`` of
the body's xy plane; readings that cover the sphere (coverage ``>= ELLIPSOID_MIN_COVERAGE``)
are refused (fit the ellipsoid); readings that are not planar (below) are fitted by their
projection onto the plane, with a warning. Tilts that vary with the heading (circles
driven over uneven ground) shift the fitted centre by about ``V`` times the tilt's first
harmonic, invisibly (the readings still lie on an ellipse): drive the circles on level
ground (in simulation, 2.5 deg terrain of 30-100 m wavelength under 6-m circles: 0.9-2 uT
off; level: 0.03-0.07 uT), or level the readings:

Levelled (:func:`fit_magnetometer_levelled`, for circles on uneven ground, with roll and
pitch known at each reading, e.g. from the front end run without the magnetometer): the
ellipse's parameters (``b``, ``T`` with ``det T = 1``, ``t``) plus the horizontal and
vertical field ``H``, ``V``, fitted by nonlinear least squares so that the corrected
readings turned level, ``g = L W (m - b)``, have ``|g_xy| = H`` and ``g_z = V``; the
residual is ``g`` less its nearest such point, taken back through ``S L^T`` into reading
units. It removes the ellipse's tilt error (the vertical field times the tilt) and leaves
the unfitted ``b_z`` times the tilt (in simulation, 2.5 deg terrain: 0.12-0.27 uT with the
front end's roll and pitch, 0.05-0.14 uT with the true ones). With tilts that vary within a
turn, ``b_z`` and the vertical scale ``s33`` become observable too (``vertical=True``: the
tilts leak ``b_z`` into the horizontal and ``H`` into ``S e_z``), but weakly: a steady
slope under a circle leaves them free (its tilt turns with the heading, like the field),
+-2 deg bumps determine ``b_z`` to 1.4 uT, and on the simulator's terrain with the front
end's tilts the fit wanders 3-21 uT off; so by default ``b_z`` stays 0 and ``s33`` the
ellipse's ``1 + t^T T^-1 t``. Unobservable with any tilts: the overall scale and a rotation
of the magnetometer against the IMU (``S`` symmetric, as the other models).

Coverage
--------
``coverage = 3 lambda_min(Cov(u))`` with ``u`` the corrected readings' unit directions
``W (m - b) / |W (m - b)|``: 1 for directions spread evenly over the sphere (or along the
six axes), 0 when they lie on one cone or plane (a robot that only yaws sees one circle of
directions), 0.25 for one hemisphere. It is the sphere fit's information on the hard iron:
the worst-determined direction of ``b`` has the standard deviation of ``coverage * N``
evenly spread readings, ``sigma sqrt(3 / (coverage N))``.

For the ellipse model the coverage is :func:`circle_coverage` of the corrected readings'
horizontal part: the smallest eigenvalue of the radial residual's information on the
in-plane offset, radius and det-1 shape, over that of headings spread evenly: 1 for one or
more even turns, 0.16 for 3/4 of a turn, 0.005 for half a turn. The fit needs
``ELLIPSE_MIN_COVERAGE`` (0.1, about 260 deg), measured before the fit about the plane's
circle fit. With noise ``sigma`` per axis on ``N`` readings spread evenly, the in-plane
centre (``sigma sqrt(2 / N)`` per axis) and the det-1 shape (``sigma sqrt(2 / N) / H``
per number) give a heading error of RMS ``2 sigma / (H sqrt(N))`` over the turn (0.0011
rad with 0.3 uT, H = 24 uT, N = 500; measured 0.98 of it over 40 draws); roll and pitch
uniform in +-T act as in-plane noise ``V T / sqrt(3)``.

The ellipsoid needs ``coverage >= ELLIPSOID_MIN_COVERAGE`` (checked with the sphere fit's
centre before the quadric fit) and readings that determine its 9 parameters
(``shape_coverage >= ELLIPSOID_MIN_SHAPE_COVERAGE``: the smallest eigenvalue of the
radial residual's information in corrected units over that of evenly spread directions,
``2 / 15``, so that the worst-determined combination has the relative standard deviation
``sigma / (F sqrt(2 / 15 shape_coverage N))``; readings on two parallel circles leave the
ellipsoid's stretch along their axis free: 0). Otherwise a ``ValueError`` says to tilt the
sensor through more orientations or to fit ``model="sphere"``. The algebraic fit is not
refined: a radial Gauss-Newton refinement lowered the cost but moved the hard iron further
from the truth on partial coverage (median 0.29 -> 0.91 uT with T = 45 deg below).

Figures (simulated: 48 uT, inclination 60 deg, 500 readings, 0.3 uT noise per axis, the
sensor turned through every heading with roll and pitch uniform in +-T, soft iron 15 %
off for the ellipsoid, none for the sphere; median norm of the hard-iron error over 30
draws, the sphere's Cramer-Rao RMS ``sigma sqrt(tr(Cov(u)^-1) / N)`` in brackets):

======= ======== ============================== =====================================
T (deg) coverage ellipsoid                      sphere
======= ======== ============================== =====================================
90      0.46     0.08 uT                        0.05 uT (0.05)
45      0.15     0.34 uT (shape coverage 0.005) 0.06 uT (0.07)
30      0.07     refused (would be 1.3 uT)      0.07 uT (0.10)
10      0.008    refused                        0.22 uT (0.27)
5       0.002    refused                        0.44 uT (0.54)
3       0.0007   refused                        0.67 uT (0.89)
0, 1    < 1e-4   refused                        planar (below): x / y 0.03 uT, z = 0
======= ======== ============================== =====================================

Readings are planar when their standard deviation along their thinnest axis is at most
``PLANAR_THICKNESS_RATIO`` (2) times the sphere fit's radial residual RMS: their extent off
the plane is their noise (with 0.3 uT noise a level robot and one tilting +-1 deg are
planar, +-3 deg is not; with 1 uT +-5 deg is planar, +-10 deg not). The ellipsoid refuses
them. The sphere fit on planar readings (a ground robot that only yaws) warns: the hard
iron along the plane's normal ``n`` is unobservable. The offset in the plane is fitted (a
circle fit in the plane) and the component along ``n`` is set to 0, ``b = c - (n . c) n``
with ``c`` the circle's centre (for a level sensor, ``b_z = 0``: the sensor's own vertical
zero). ``F`` is then the corrected magnitude ``|m - b|``, which includes the unfitted
vertical offset, so the filter's field-magnitude check (``magnetometer_field_uT``) stays
consistent with the correction it applies. On a level robot the heading uses only the
horizontal part, which the fit corrects.

Reference: the hard / soft iron model and the ellipsoid fit as in NXP application note
AN4246, "Calibrating an eCompass in the presence of hard- and soft-iron interference"; Q. Li
and J. G. Griffiths, "Least squares ellipsoid specific fitting" (2004) constrain the fit to
ellipsoids instead of checking the result, as here.
"""

from __future__ import annotations

__all__ = [
    "ELLIPSE_MAX_TILT_RAD",
    "ELLIPSE_MIN_COVERAGE",
    "ELLIPSOID_MIN_COVERAGE",
    "ELLIPSOID_MIN_SHAPE_COVERAGE",
    "PLANAR_THICKNESS_RATIO",
    "MagnetometerCalibration",
    "circle_coverage",
    "direction_coverage",
    "fit_magnetometer",
    "fit_magnetometer_levelled",
    "planarity",
    "shape_coverage",
]

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

ELLIPSOID_MIN_COVERAGE = 0.1
"""Least :func:`direction_coverage` (of the sphere fit) for the ellipsoid model."""

ELLIPSOID_MIN_SHAPE_COVERAGE = 1e-3
"""Least :func:`shape_coverage` of the fitted ellipsoid (its 9 parameters determined)."""

PLANAR_THICKNESS_RATIO = 2.0
"""Readings whose standard deviation along their thinnest axis is at most this many times
the sphere fit's radial residual RMS (their noise) are planar: their extent off the plane
is noise."""

ELLIPSE_MIN_COVERAGE = 0.1
"""Least :func:`circle_coverage` of the ellipse model (about 260 deg of one turn)."""

ELLIPSE_MAX_TILT_RAD = 0.2
"""Largest angle between the readings' plane and the body's xy plane for the ellipse model;
soft iron tilts it by its xz / yz coupling (a few hundredths of a radian)."""

_MIN_SAMPLES = {"ellipsoid": 10, "ellipse": 8, "sphere": 4}
_NEWTON_STEPS = 50


@dataclass(frozen=True)
class MagnetometerCalibration:
    """A fitted magnetometer calibration: ``f_b = soft_iron @ (m - hard_iron)``.

    Attributes:
        hard_iron: (3,) offset ``b``, uT.
        soft_iron: (3, 3) symmetric positive definite ``W`` (``det W = 1``; identity for
            the sphere model; ``W_zz = 1`` for the ellipse).
        field_uT: the radius of the corrected readings (the local field magnitude, uT).
        residual_rms_uT: RMS of ``|W (m - b)| - field_uT`` over the readings, uT.
        coverage: :func:`direction_coverage` of the corrected readings (ellipse:
            :func:`circle_coverage` of their horizontal part), in [0, 1].
        samples: number of readings fitted.
        model: ``"ellipsoid"``, ``"ellipse"`` or ``"sphere"``.
    """

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field_uT: float
    residual_rms_uT: float
    coverage: float
    samples: int
    model: str

    def correct(self, field: np.ndarray) -> np.ndarray:
        """Corrected readings ``W (m - b)`` (..., 3) uT of raw readings ``field`` (..., 3)."""
        return (np.asarray(field, dtype=np.float64) - self.hard_iron) @ self.soft_iron.T


def direction_coverage(vectors: np.ndarray) -> float:
    """How evenly the directions of ``vectors`` (N, 3) cover the sphere: ``3 lambda_min`` of
    the covariance of the unit vectors, in [0, 1] (module docstring). Zero vectors are
    skipped; fewer than 2 directions give 0."""
    norms = np.linalg.norm(vectors, axis=1)
    units = vectors[norms > 0] / norms[norms > 0, None]
    if units.shape[0] < 2:
        return 0.0
    centred = units - units.mean(0)
    smallest = np.linalg.eigvalsh(centred.T @ centred / units.shape[0])[0]
    return float(np.clip(3.0 * smallest, 0.0, 1.0))


def _shape_rows(units: np.ndarray) -> np.ndarray:
    """(N, 9) radial-residual Jacobian rows in corrected units at unit directions ``u``: the
    offset ``u`` and the symmetric distortion ``u_k u_l`` (twice off the diagonal)."""
    x, y, z = units.T
    return np.column_stack((x, y, z, x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z))


def shape_coverage(vectors: np.ndarray) -> float:
    """How well directions ``vectors`` (N, 3) (corrected readings) determine the 9
    ellipsoid parameters: the smallest eigenvalue of the radial residual's information
    (:func:`_shape_rows`, per reading) over that of evenly spread directions (2 / 15);
    about 1 for readings spread over the sphere, 0 for readings on a few circles."""
    units = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    rows = _shape_rows(units)
    return float(np.linalg.eigvalsh(rows.T @ rows / rows.shape[0])[0] * 7.5)


def circle_coverage(vectors: np.ndarray) -> float:
    """How well in-plane vectors (N, 2) (the corrected readings' horizontal part) go round the
    circle for the ellipse model: the smallest eigenvalue of the mean outer product of
    ``(sqrt2 cos a, sqrt2 sin a, 1, sqrt2 cos 2a, sqrt2 sin 2a)`` at their angles ``a`` (the
    radial residual's information on the in-plane offset, radius and det-1 shape over that
    of angles spread evenly), in [0, 1]: 1 for one or more even turns, 0.5 for 7/8 of a turn,
    0.16 for 3/4, 0.005 for half a turn. Zero vectors are skipped."""
    angle = np.arctan2(vectors[:, 1], vectors[:, 0])[np.linalg.norm(vectors, axis=1) > 0]
    if angle.size == 0:
        return 0.0
    root2 = np.sqrt(2.0)
    rows = np.column_stack(
        (
            root2 * np.cos(angle),
            root2 * np.sin(angle),
            np.ones_like(angle),
            root2 * np.cos(2 * angle),
            root2 * np.sin(2 * angle),
        )
    )
    return float(np.clip(np.linalg.eigvalsh(rows.T @ rows / angle.size)[0], 0.0, 1.0))


def _sphere_centre(x: np.ndarray) -> np.ndarray:
    """Centre (3,) of the linear least-squares sphere ``|x|^2 = 2 c . x + k`` through x."""
    design = np.column_stack((2.0 * x, np.ones(x.shape[0])))
    solution = np.linalg.lstsq(design, (x * x).sum(1), rcond=None)[0]
    return solution[:3]


def _refine_sphere(x: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Gauss-Newton on the radial residual ``|x_i - c| - R`` over c (3) and R from the
    linear fit's centre (N, 3) -> (3,): the linear fit is far from efficient on a narrow band
    of directions. A step that does not lower the cost is halved (at most 30 times)."""

    def radial(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = x - c
        r = np.linalg.norm(d, axis=1)
        return r - r.mean(), d / r[:, None]

    residual, units = radial(centre)
    for _ in range(_NEWTON_STEPS):
        jacobian = np.column_stack((-units, -np.ones(x.shape[0])))
        step = np.linalg.lstsq(jacobian, -residual, rcond=None)[0][:3]
        for _ in range(30):
            new_residual, new_units = radial(centre + step)
            if new_residual @ new_residual <= residual @ residual:
                break
            step = step / 2
        else:
            break
        centre, residual, units = centre + step, new_residual, new_units
        if np.abs(step).max() <= 1e-14 * (1.0 + np.abs(centre).max()):
            break
    return centre


def _plane(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The readings' best plane: mean (3,), unit normal (3,) (the covariance's smallest
    eigenvector), in-plane axes (3, 2), the readings' in-plane coordinates (N, 2) over their
    RMS radius ``scale`` and that scale (uT)."""
    mean = m.mean(0)
    axes = np.linalg.eigh(np.cov((m - mean).T))[1]
    xy = (m - mean) @ axes[:, 1:]
    scale = float(np.sqrt((xy * xy).sum(1).mean()))
    return mean, axes[:, 0], axes[:, 1:], xy / scale, scale


def _circle_centre(xy: np.ndarray) -> np.ndarray:
    """Centre (2,) of the linear least-squares circle ``|x|^2 = 2 c . x + k`` through xy (N, 2)."""
    design = np.column_stack((2.0 * xy, np.ones(xy.shape[0])))
    return np.linalg.lstsq(design, (xy * xy).sum(1), rcond=None)[0][:2]


def _planar_centre(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hard iron (3,) of raw readings m (N, 3) close to one plane, and the plane's unit
    normal (3,): the circle fitted in the plane, its component along the normal set to zero
    (module docstring)."""
    mean, normal, plane, xy, scale = _plane(m)
    centre = mean + plane @ (scale * _circle_centre(xy))
    return centre - (normal @ centre) * normal, normal


def _conic_ellipse(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic ellipse through in-plane points xy (N, 2): centre (2,) and symmetric
    positive definite A (2, 2) with ``(x - c)^T A (x - c) = 1``; ValueError when the best
    conic is not a real ellipse."""
    a, b = xy.T
    design = np.column_stack((a * a, b * b, 2 * a * b, 2 * a, 2 * b, np.ones_like(a)))
    p = np.linalg.svd(design, full_matrices=False)[2][-1]
    quad = np.array([[p[0], p[2]], [p[2], p[1]]])
    eig = np.linalg.eigvalsh(quad)
    if eig[0] * eig[-1] <= 0 or min(abs(eig[0]), abs(eig[-1])) <= 1e-12 * max(abs(eig)):
        raise ValueError(
            "the best-fitting conic in the readings' plane is not an ellipse (its quadratic "
            f"part is not definite: eigenvalues {np.array2string(eig / max(abs(eig)), precision=3)}"
            "); the readings are not one sensor's field turned about one axis, or too noisy"
        )
    centre = -np.linalg.solve(quad, p[3:5])
    shape = quad / (centre @ quad @ centre - p[5])
    if np.linalg.eigvalsh(shape)[0] <= 0:
        raise ValueError("the best-fitting conic is an imaginary ellipse (no real points)")
    return centre, shape


def _ellipse_calibration(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Hard iron (3,), soft iron W (3, 3) and the plane's tilt from the body's xy plane (rad)
    of raw readings m (N, 3) of a sensor yawed about its body z axis (module docstring: the
    ellipse ``c + [T; t^T] u`` in 3-D, ``W = S^-1`` with ``S = [[T, t], [t^T, s33]]``).
    ValueError when the readings do not go round (:func:`circle_coverage` of their angles
    about the plane's circle fit) or their best conic is not an ellipse."""
    mean, normal, plane, xy, scale = _plane(m)
    going_round = circle_coverage(xy - _circle_centre(xy))
    if going_round < ELLIPSE_MIN_COVERAGE:
        raise ValueError(
            f"the readings do not go round the circle (coverage {going_round:.3g} < "
            f"{ELLIPSE_MIN_COVERAGE}, e.g. less than about 260 deg of one turn): drive at "
            "least one full, slow turn"
        )
    centre2, shape2 = _conic_ellipse(xy)
    centre = mean + scale * plane @ centre2
    spread = scale**2 * plane @ np.linalg.inv(shape2) @ plane.T  # [T; t^T] [T; t^T]^T
    values, vectors = np.linalg.eigh(spread[:2, :2])
    top = (vectors * np.sqrt(values)) @ vectors.T  # T, symmetric positive definite
    radius = np.sqrt(np.linalg.det(top))
    coupling = np.linalg.solve(top, spread[:2, 2]) / radius  # t (det T = 1)
    top = top / radius
    column = np.append(coupling, 1.0 + coupling @ np.linalg.solve(top, coupling))  # S e_z
    soft_iron = np.linalg.inv(np.block([[top, column[:2, None]], [column[None, :]]]))
    hard_iron = centre - (centre[2] / column[2]) * column  # the unobservable b_z set to 0
    tilt = float(np.arccos(min(abs(normal[2]), 1.0)))
    return hard_iron, (soft_iron + soft_iron.T) / 2, tilt


def _quadric_ellipsoid(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic ellipsoid through x (N, 3): centre (3,) and symmetric L (3, 3) with
    ``|L (x - c)| = 1``; ValueError when the best quadric is not a real ellipsoid."""
    a, b, c = x.T
    design = np.column_stack(
        (a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c, 2 * a, 2 * b, 2 * c, np.ones_like(a))
    )
    p = np.linalg.svd(design, full_matrices=False)[2][-1]
    quad = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    eig = np.linalg.eigvalsh(quad)
    if eig[0] * eig[-1] <= 0 or min(abs(eig[0]), abs(eig[-1])) <= 1e-12 * max(abs(eig)):
        raise ValueError(
            "the best-fitting quadric is not an ellipsoid (its quadratic part is not definite: "
            f"eigenvalues {np.array2string(eig / max(abs(eig)), precision=3)}); the readings "
            "are not one sensor's field turned through many orientations, or too noisy"
        )
    centre = -np.linalg.solve(quad, p[6:9])
    level = centre @ quad @ centre - p[9]
    shape = quad / level
    values, vectors = np.linalg.eigh(shape)
    if values[0] <= 0:
        raise ValueError("the best-fitting quadric is an imaginary ellipsoid (no real points)")
    return centre, (vectors * np.sqrt(values)) @ vectors.T


def _checked_readings(field: np.ndarray, need: int, what: str) -> np.ndarray:
    """Readings as (N, 3) float64; ValueError for a bad shape, fewer than ``need`` rows (for
    ``what``) or non-finite rows."""
    m = np.asarray(field, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"magnetometer readings must be (N, 3), got shape {m.shape}")
    if m.shape[0] < need:
        raise ValueError(f"{what} needs at least {need} readings, got {m.shape[0]}")
    bad = np.flatnonzero(~np.isfinite(m).all(axis=1))
    if bad.size:
        raise ValueError(
            f"reading {int(bad[0])} is not finite: {m[bad[0]].tolist()} ({bad.size} such rows)"
        )
    return m


def _planarity(x: np.ndarray, centre: np.ndarray) -> tuple[bool, float, float]:
    """(planar, thickness, noise) of readings x (N, 3) around the sphere centre (3,), in x's
    units: the standard deviation along their thinnest axis against
    ``PLANAR_THICKNESS_RATIO`` times the radial residual's standard deviation."""
    thickness = float(np.sqrt(max(np.linalg.eigvalsh(np.cov(x.T))[0], 0.0)))
    noise = float(np.linalg.norm(x - centre, axis=1).std())
    return thickness <= max(PLANAR_THICKNESS_RATIO * noise, 1e-9), thickness, noise


def planarity(field: np.ndarray) -> tuple[bool, float, float]:
    """Whether readings (N, 3) uT (N >= 4) lie in one plane up to their noise (module
    docstring), their thickness (standard deviation along their thinnest axis, uT) and
    noise (the sphere fit's radial residual standard deviation, uT)."""
    m = _checked_readings(field, 4, "the planarity test")
    scale = float(np.sqrt(((m - m.mean(0)) ** 2).sum(1).mean()))
    if scale == 0.0:
        return True, 0.0, 0.0
    x = (m - m.mean(0)) / scale
    planar, thickness, noise = _planarity(x, _sphere_centre(x))
    return planar, thickness * scale, noise * scale


def fit_magnetometer(field: np.ndarray, *, model: str = "ellipsoid") -> MagnetometerCalibration:
    """Fit hard iron (and soft iron) to magnetometer readings (module docstring).

    Args:
        field: (N, 3) raw readings in the sensor's (body) frame, uT, taken with the sensor
            turned through as many orientations as possible (``"ellipse"``: yawed about
            body z through at least one full turn).
        model: ``"ellipsoid"`` (hard and soft iron; N >= 10), ``"ellipse"`` (hard and soft
            iron in the plane of a sensor that only yaws, ``b_z = 0``; N >= 8) or
            ``"sphere"`` (hard iron only; N >= 4).

    Returns:
        the calibration; ``calibration.correct(field)`` has norms ``field_uT`` (up to the
        noise, ``residual_rms_uT``).

    Raises:
        ValueError: a bad shape, too few readings, a non-finite reading, all readings equal;
            for the ellipsoid, readings that span too little of the sphere of directions or
            leave its shape undetermined (tilt the sensor, or use ``model="ellipse"`` or
            ``"sphere"``), or a best quadric that is not an ellipsoid; for the ellipse,
            readings that cover the sphere (fit the ellipsoid), do not go round, lie in a
            plane tilted more than ``ELLIPSE_MAX_TILT_RAD`` from the body's xy plane, or a
            best conic that is not an ellipse.

    Warns:
        UserWarning: the sphere model on readings close to one plane (the hard iron along
            its normal is set to 0); the ellipse model on readings that are not planar
            (tilts: their projection onto the plane is fitted).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> u = rng.normal(size=(200, 3))
        >>> m = 48.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [10.0, -5.0, 3.0]
        >>> cal = fit_magnetometer(m)
        >>> np.round(cal.hard_iron, 6).tolist(), round(cal.field_uT, 6)
        ([10.0, -5.0, 3.0], 48.0)
    """
    if model not in _MIN_SAMPLES:
        raise ValueError(f"model must be 'ellipsoid', 'ellipse' or 'sphere', got {model!r}")
    m = _checked_readings(field, _MIN_SAMPLES[model], f"the {model} model")
    mean = m.mean(0)
    scale = float(np.sqrt(((m - mean) ** 2).sum(1).mean()))
    if scale == 0.0:
        raise ValueError(f"all {m.shape[0]} readings are equal: the sensor was not turned")
    x = (m - mean) / scale
    sphere_centre = _sphere_centre(x)
    spread = direction_coverage(x - sphere_centre)
    planar, thickness, noise = _planarity(x, sphere_centre)
    soft_iron, radius = np.eye(3), None
    if model == "ellipsoid":
        if planar or spread < ELLIPSOID_MIN_COVERAGE:
            why = "in one plane up to their noise" if planar else f"< {ELLIPSOID_MIN_COVERAGE}"
            raise ValueError(
                "the readings span too little of the sphere of directions for the ellipsoid "
                f"model (coverage {spread:.3g}, {why}): tilt the sensor through many more "
                "orientations; for a robot that only yaws (one circle of directions) fit the "
                'hard and soft iron in the plane with model="ellipse"'
                + ("" if planar else ' (tilts ignored), or the hard iron only with model="sphere"')
            )
        centre, shape = _quadric_ellipsoid(x)
        radius = scale / np.cbrt(np.linalg.det(shape))  # det W = 1
        soft_iron = (shape + shape.T) * (radius / (2 * scale))
        determined = shape_coverage((x - centre) @ shape.T)
        if determined < ELLIPSOID_MIN_SHAPE_COVERAGE:
            raise ValueError(
                f"the readings leave the ellipsoid's shape undetermined (shape coverage "
                f"{determined:.3g} < {ELLIPSOID_MIN_SHAPE_COVERAGE}: e.g. readings on a few "
                "circles): tilt the sensor through many more orientations, or fit the hard "
                'iron only with model="sphere"'
            )
        hard_iron = mean + scale * centre
    elif model == "ellipse":
        if spread >= ELLIPSOID_MIN_COVERAGE:
            raise ValueError(
                f"the readings cover the sphere of directions (coverage {spread:.3g} >= "
                f"{ELLIPSOID_MIN_COVERAGE}), not one circle: fit the hard and soft iron in 3-D "
                'with model="ellipsoid"'
            )
        hard_iron, soft_iron, tilt = _ellipse_calibration(m)
        if tilt > ELLIPSE_MAX_TILT_RAD:
            raise ValueError(
                f"the readings' plane is tilted {np.degrees(tilt):.3g} deg from the body's xy "
                f"plane (> {np.degrees(ELLIPSE_MAX_TILT_RAD):.3g}; soft iron tilts it by a few "
                "deg): the ellipse model needs readings in the body axes of a robot yawing "
                "about its body z axis on level ground"
            )
        if not planar:
            warnings.warn(
                f"magnetometer readings are {thickness * scale:.3g} uT thick off their plane, "
                f"more than {PLANAR_THICKNESS_RATIO:g} x their noise ({noise * scale:.3g} uT): "
                "the sensor tilted while yawing; the ellipse is fitted to their projection "
                "onto the plane",
                stacklevel=2,
            )
    elif planar:
        hard_iron, normal = _planar_centre(m)
        warnings.warn(
            f"magnetometer readings lie close to one plane (coverage {spread:.3g}; a robot "
            "that only yaws): the hard iron along the plane's normal "
            f"{np.round(normal, 3).tolist()} is unobservable and set to 0 (only the offset "
            'in the plane is fitted; model="ellipse" also fits the soft iron in the plane); '
            "tilt the sensor to calibrate it",
            stacklevel=2,
        )
    else:
        hard_iron = mean + scale * _refine_sphere(x, sphere_centre)
    corrected = (m - hard_iron) @ soft_iron.T
    norms = np.linalg.norm(corrected, axis=1)
    radius = float(norms.mean()) if radius is None else float(radius)
    coverage = (
        circle_coverage(corrected[:, :2]) if model == "ellipse" else direction_coverage(corrected)
    )
    return MagnetometerCalibration(
        hard_iron=hard_iron,
        soft_iron=soft_iron,
        field_uT=radius,
        residual_rms_uT=float(np.sqrt(np.mean((norms - radius) ** 2))),
        coverage=coverage,
        samples=int(m.shape[0]),
        model=model,
    )


def _tilt_matrices(tilt: np.ndarray, n: int) -> np.ndarray:
    """(N, 3, 3) body -> level rotations of ``tilt``: (N, 2) roll and pitch, rad (``R_y(pitch)
    R_x(roll)``, the ZYX Euler angles), or (N, 3, 3) attitudes (body -> world; the yaw does
    not matter). ValueError for another shape or non-finite values."""
    a = np.asarray(tilt, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError("the roll / pitch (or attitudes) must be finite")
    if a.shape == (n, 3, 3):
        return a
    if a.shape != (n, 2):
        raise ValueError(
            f"tilt must be (N, 2) roll and pitch or (N, 3, 3) attitudes for the {n} readings, "
            f"got shape {a.shape}"
        )
    cr, sr, cp, sp = np.cos(a[:, 0]), np.sin(a[:, 0]), np.cos(a[:, 1]), np.sin(a[:, 1])
    zero = np.zeros(n)
    return np.stack(
        (
            np.stack((cp, sp * sr, sp * cr), 1),
            np.stack((zero, cr, -sr), 1),
            np.stack((-sp, cp * sr, cp * cr), 1),
        ),
        1,
    )


def _levelled_distortion(p: np.ndarray, vertical: bool) -> np.ndarray:
    """Distortion ``S = [[T, t], [t^T, s33]]`` (3, 3) of the levelled fit's parameters
    ``p[3:8]``: ``T = expm([[a, c], [c, -a]])`` (symmetric, det 1), ``t``, and ``s33 =
    p[7]`` when ``vertical``, else the ellipse's ``1 + t^T T^-1 t`` (``det S = 1``)."""
    a, c = p[3], p[4]
    r = float(np.hypot(a, c))
    top = np.cosh(r) * np.eye(2) + (np.sinh(r) / r if r > 0 else 1.0) * np.array([[a, c], [c, -a]])
    coupling = p[5:7]
    s33 = p[7] if vertical else 1.0 + coupling @ np.linalg.solve(top, coupling)
    return np.block([[top, coupling[:, None]], [np.append(coupling, s33)[None, :]]])


def _levelled_residual(
    p: np.ndarray, m: np.ndarray, level: np.ndarray, vertical: bool
) -> np.ndarray:
    """(3N,) levelled residuals of parameters p (10,) = (b, a, c, t, s33, H, V), uT of the
    readings: the corrected readings ``g = L S^-1 (m - b)`` turned level, less their nearest
    point ``(H g_xy / |g_xy|, V)``, taken back through ``S L^T`` (so that a larger vertical
    scale cannot shrink the noise it is weighed by); ``vertical``: p[7] is ``s33``, else the
    ellipse's convention (:func:`_levelled_distortion`)."""
    distortion = _levelled_distortion(p, vertical)
    g = np.einsum("nij,nj->ni", level, np.linalg.solve(distortion, (m - p[:3]).T).T)
    horizontal = np.hypot(g[:, 0], g[:, 1])
    miss = np.column_stack(
        (g[:, :2] * (1.0 - p[8] / np.maximum(horizontal, 1e-12))[:, None], g[:, 2] - p[9])
    )
    return (np.einsum("nji,nj->ni", level, miss) @ distortion.T).reshape(-1)


def fit_magnetometer_levelled(
    field: np.ndarray,
    tilt: np.ndarray,
    *,
    vertical: bool = False,
    initial: MagnetometerCalibration | None = None,
) -> MagnetometerCalibration:
    """Hard and soft iron of a robot yawing on uneven ground, its readings levelled with
    known roll and pitch (e.g. the front end's, run without the magnetometer).

    The corrected readings ``f_i = W (m_i - b)`` turned level, ``g_i = L_i f_i`` (``L_i``
    the body -> level rotation of roll and pitch), must have one horizontal magnitude ``H``
    and one vertical component ``V``: a nonlinear least squares
    (``scipy.optimize.least_squares``) over ``b`` (3), ``S = W^-1 = [[T, t], [t^T, s33]]``
    (``T`` symmetric with ``det T = 1``, as the ellipse model), ``H`` and ``V``, from the
    ellipse fit (or ``initial``). The tilts explain what the ellipse absorbs into a shifted
    centre (the vertical field times the tilt). ``b_z`` and ``s33`` are fitted only with
    ``vertical``: tilts that vary within a turn make them observable, weakly (module
    docstring); else ``b_z`` is the start's (the ellipse's 0) and ``s33 = 1 + t^T T^-1 t``
    (``det W = 1``, the ellipse's convention). Never observable: the overall scale
    (``det T = 1`` fixes it) and a rotation of the magnetometer against the IMU.

    Args:
        field: (N, 3) raw readings in the body frame, uT, N >= 10.
        tilt: (N, 2) roll and pitch, rad (ZYX Euler angles), or (N, 3, 3) body -> world
            attitudes, at the readings.
        vertical: also fit ``b_z`` and the vertical scale ``s33``.
        initial: the start (default: ``fit_magnetometer(field, model="ellipse")``, its
            warning on readings that are not planar silenced).

    Returns:
        the calibration, ``model="levelled"``: ``hard_iron``, ``soft_iron = S^-1``,
        ``field_uT = hypot(H, V)``, ``residual_rms_uT`` of the levelled residuals (3 per
        reading, in reading units; the tangential one is 0), ``coverage``
        :func:`circle_coverage` of the levelled horizontal part.

    Raises:
        ValueError: bad shapes, too few or non-finite readings, or the ellipse start's
            refusals (readings that do not go round).
    """
    m = _checked_readings(field, 10, "the levelled fit")
    level = _tilt_matrices(tilt, m.shape[0])
    if initial is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            initial = fit_magnetometer(m, model="ellipse")
    distortion = np.linalg.inv(initial.soft_iron)
    distortion = distortion / np.sqrt(np.linalg.det(distortion[:2, :2]))
    values, vectors = np.linalg.eigh((distortion[:2, :2] + distortion[:2, :2].T) / 2)
    log_top = (vectors * np.log(values)) @ vectors.T
    g = np.einsum("nij,nj->ni", level, (m - initial.hard_iron) @ np.linalg.inv(distortion).T)
    start = np.concatenate(
        (
            initial.hard_iron,
            [log_top[0, 0], log_top[0, 1]],
            distortion[:2, 2],
            [distortion[2, 2], np.hypot(g[:, 0], g[:, 1]).mean(), g[:, 2].mean()],
        )
    )
    free = np.ones(10, dtype=bool)
    free[[2, 7]] = vertical  # else b_z the start's (the ellipse's 0), s33 the convention

    def residual(x: np.ndarray) -> np.ndarray:
        p = start.copy()
        p[free] = x
        return _levelled_residual(p, m, level, vertical)

    solution = start.copy()
    solution[free] = least_squares(
        residual,
        start[free],
        method="trf",
        x_scale="jac",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=200,
    ).x
    soft_iron = np.linalg.inv(_levelled_distortion(solution, vertical))
    soft_iron = (soft_iron + soft_iron.T) / 2
    residual = _levelled_residual(solution, m, level, vertical)
    g = np.einsum("nij,nj->ni", level, (m - solution[:3]) @ soft_iron.T)
    return MagnetometerCalibration(
        hard_iron=solution[:3].copy(),
        soft_iron=soft_iron,
        field_uT=float(np.hypot(solution[8], solution[9])),
        residual_rms_uT=float(np.sqrt(np.mean(residual**2))),
        coverage=circle_coverage(g[:, :2]),
        samples=int(m.shape[0]),
        model="levelled",
    )
