"""Magnetometer hard- and soft-iron calibration from readings taken in many orientations.

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

Coverage
--------
``coverage = 3 lambda_min(Cov(u))`` with ``u`` the corrected readings' unit directions
``W (m - b) / |W (m - b)|``: 1 for directions spread evenly over the sphere (or along the
six axes), 0 when they lie on one cone or plane (a robot that only yaws sees one circle of
directions), 0.25 for one hemisphere. It is the sphere fit's information on the hard iron:
the worst-determined direction of ``b`` has the standard deviation of ``coverage * N``
evenly spread readings, ``sigma sqrt(3 / (coverage N))``.

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
    "ELLIPSOID_MIN_COVERAGE",
    "ELLIPSOID_MIN_SHAPE_COVERAGE",
    "PLANAR_THICKNESS_RATIO",
    "MagnetometerCalibration",
    "direction_coverage",
    "fit_magnetometer",
    "shape_coverage",
]

import warnings
from dataclasses import dataclass

import numpy as np

ELLIPSOID_MIN_COVERAGE = 0.1
"""Least :func:`direction_coverage` (of the sphere fit) for the ellipsoid model."""

ELLIPSOID_MIN_SHAPE_COVERAGE = 1e-3
"""Least :func:`shape_coverage` of the fitted ellipsoid (its 9 parameters determined)."""

PLANAR_THICKNESS_RATIO = 2.0
"""Readings whose standard deviation along their thinnest axis is at most this many times
the sphere fit's radial residual RMS (their noise) are planar: their extent off the plane
is noise."""

_MIN_SAMPLES = {"ellipsoid": 10, "sphere": 4}
_NEWTON_STEPS = 50


@dataclass(frozen=True)
class MagnetometerCalibration:
    """A fitted magnetometer calibration: ``f_b = soft_iron @ (m - hard_iron)``.

    Attributes:
        hard_iron: (3,) offset ``b``, uT.
        soft_iron: (3, 3) symmetric positive definite ``W`` (``det W = 1``; identity for
            the sphere model).
        field_uT: the radius of the corrected readings (the local field magnitude, uT).
        residual_rms_uT: RMS of ``|W (m - b)| - field_uT`` over the readings, uT.
        coverage: :func:`direction_coverage` of the corrected readings, in [0, 1].
        samples: number of readings fitted.
        model: ``"ellipsoid"`` or ``"sphere"``.
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


def _planar_centre(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hard iron (3,) of raw readings m (N, 3) close to one plane, and the plane's unit
    normal (3,): the circle fitted in the plane, its component along the normal set to zero
    (module docstring)."""
    mean = m.mean(0)
    axes = np.linalg.eigh(np.cov((m - mean).T))[1]
    normal, plane = axes[:, 0], axes[:, 1:]
    xy = (m - mean) @ plane
    scale = np.sqrt((xy * xy).sum(1).mean())
    design = np.column_stack((2.0 * xy / scale, np.ones(m.shape[0])))
    solution = np.linalg.lstsq(design, (xy * xy).sum(1) / scale**2, rcond=None)[0]
    centre = mean + plane @ (scale * solution[:2])
    return centre - (normal @ centre) * normal, normal


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


def _checked_readings(field: np.ndarray, model: str) -> np.ndarray:
    """Readings as (N, 3) float64; ValueError for a bad shape, too few or non-finite rows."""
    if model not in _MIN_SAMPLES:
        raise ValueError(f"model must be 'ellipsoid' or 'sphere', got {model!r}")
    m = np.asarray(field, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"magnetometer readings must be (N, 3), got shape {m.shape}")
    need = _MIN_SAMPLES[model]
    if m.shape[0] < need:
        raise ValueError(f"the {model} model needs at least {need} readings, got {m.shape[0]}")
    bad = np.flatnonzero(~np.isfinite(m).all(axis=1))
    if bad.size:
        raise ValueError(
            f"reading {int(bad[0])} is not finite: {m[bad[0]].tolist()} ({bad.size} such rows)"
        )
    return m


def fit_magnetometer(field: np.ndarray, *, model: str = "ellipsoid") -> MagnetometerCalibration:
    """Fit hard iron (and soft iron) to magnetometer readings (module docstring).

    Args:
        field: (N, 3) raw readings in the sensor's (body) frame, uT, taken with the sensor
            turned through as many orientations as possible.
        model: ``"ellipsoid"`` (hard and soft iron; N >= 10) or ``"sphere"`` (hard iron
            only; N >= 4).

    Returns:
        the calibration; ``calibration.correct(field)`` has norms ``field_uT`` (up to the
        noise, ``residual_rms_uT``).

    Raises:
        ValueError: a bad shape, too few readings, a non-finite reading, all readings equal;
            for the ellipsoid, readings that span too little of the sphere of directions or
            leave its shape undetermined (tilt the sensor, or use ``model="sphere"``), or a
            best quadric that is not an ellipsoid.

    Warns:
        UserWarning: the sphere model on readings close to one plane (the hard iron along
            its normal is set to 0).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> u = rng.normal(size=(200, 3))
        >>> m = 48.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [10.0, -5.0, 3.0]
        >>> cal = fit_magnetometer(m)
        >>> np.round(cal.hard_iron, 6).tolist(), round(cal.field_uT, 6)
        ([10.0, -5.0, 3.0], 48.0)
    """
    m = _checked_readings(field, model)
    mean = m.mean(0)
    scale = float(np.sqrt(((m - mean) ** 2).sum(1).mean()))
    if scale == 0.0:
        raise ValueError(f"all {m.shape[0]} readings are equal: the sensor was not turned")
    x = (m - mean) / scale
    sphere_centre = _sphere_centre(x)
    spread = direction_coverage(x - sphere_centre)
    distance = np.linalg.norm(x - sphere_centre, axis=1)
    thickness = np.sqrt(max(np.linalg.eigvalsh(np.cov(x.T))[0], 0.0))
    planar = thickness <= max(PLANAR_THICKNESS_RATIO * distance.std(), 1e-9)
    soft_iron, radius = np.eye(3), None
    if model == "ellipsoid":
        if planar or spread < ELLIPSOID_MIN_COVERAGE:
            why = "in one plane up to their noise" if planar else f"< {ELLIPSOID_MIN_COVERAGE}"
            raise ValueError(
                "the readings span too little of the sphere of directions for the ellipsoid "
                f"model (coverage {spread:.3g}, {why}; a robot that only yaws sees one "
                "circle): tilt the sensor through many more orientations, or fit the hard "
                'iron only with model="sphere"'
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
    elif planar:
        in_plane, normal = _planar_centre(m)
        centre = (in_plane - mean) / scale
        warnings.warn(
            f"magnetometer readings lie close to one plane (coverage {spread:.3g}; a robot "
            "that only yaws): the hard iron along the plane's normal "
            f"{np.round(normal, 3).tolist()} is unobservable and set to 0 (only the offset "
            "in the plane is fitted); tilt the sensor to calibrate it",
            stacklevel=2,
        )
    else:
        centre = _refine_sphere(x, sphere_centre)
    hard_iron = mean + scale * centre
    corrected = (m - hard_iron) @ soft_iron.T
    norms = np.linalg.norm(corrected, axis=1)
    radius = float(norms.mean()) if radius is None else float(radius)
    return MagnetometerCalibration(
        hard_iron=hard_iron,
        soft_iron=soft_iron,
        field_uT=radius,
        residual_rms_uT=float(np.sqrt(np.mean((norms - radius) ** 2))),
        coverage=direction_coverage(corrected),
        samples=int(m.shape[0]),
        model=model,
    )
