"""WGS-84 geodetic coordinates <-> a local East-North-Up (ENU) frame.

``sensor_msgs/NavSatFix`` reports latitude and longitude in degrees and the altitude in
metres above the WGS-84 ellipsoid. msf_torch's world frame is a local ENU frame (z up, see
``geometry.conventions``) whose origin is a geodetic point ``(lat0, lon0, alt0)``: a fix
maps to the exact ENU coordinates of its Earth-centred (ECEF) position relative to the
origin's, rotated into the origin's tangent frame,

    [e, n, u] = R0^T (ecef(lat, lon, alt) - ecef(lat0, lon0, alt0)),
    R0 = [east, north, up] unit vectors at the origin (columns, in ECEF).

No flat-Earth approximation is made. The ECEF difference is formed from differences of
the geodetic coordinates (half-angle forms of ``cos a - cos b`` and ``sin a - sin b``,
and of the prime-vertical radius), never as a difference of two ~6.4e6 m numbers, so the
result is as precise as the float64 latitude and longitude themselves. :func:`enu_to_geodetic`
inverts it by Newton steps on the same function; a round trip is then exact up to the
rounding of the degrees to float64 (half a unit in the last place: ~2e-10 m at 8 deg E,
~1.3e-9 m east at 151 deg E, 34 deg S).

Example:
    >>> import numpy as np
    >>> origin = (49.0, 8.4, 110.0)
    >>> enu = geodetic_to_enu(np.array([49.001]), np.array([8.4]), np.array([110.0]), origin)
    >>> round(float(enu[0, 1]), 3)  # 0.001 deg north at 49 deg latitude, m
    111.212
"""

from __future__ import annotations

__all__ = [
    "WGS84_A",
    "WGS84_F",
    "geodetic_to_ecef",
    "geodetic_to_enu",
    "enu_to_geodetic",
]

from collections.abc import Sequence

import numpy as np

WGS84_A = 6378137.0
"""WGS-84 semi-major axis, m."""
WGS84_F = 1.0 / 298.257223563
"""WGS-84 flattening."""
_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    """Earth-centred, Earth-fixed coordinates (..., 3) in m of geodetic points (...,).

    The textbook form ``((N + h) cos(lat) cos(lon), (N + h) cos(lat) sin(lon),
    (N (1 - e^2) + h) sin(lat))`` with ``N = a / sqrt(1 - e^2 sin(lat)^2)``.
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    alt = np.asarray(alt_m, dtype=np.float64)
    prime = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack(
        (
            (prime + alt) * np.cos(lat) * np.cos(lon),
            (prime + alt) * np.cos(lat) * np.sin(lon),
            (prime * (1.0 - _E2) + alt) * np.sin(lat),
        ),
        -1,
    )


def _origin(origin: Sequence[float]) -> tuple[float, float, float]:
    values = tuple(float(x) for x in origin)
    if len(values) != 3 or not all(np.isfinite(values)):
        raise ValueError(f"a geodetic origin is [lat_deg, lon_deg, alt_m], got {origin!r}")
    if abs(values[0]) > 90.0:
        raise ValueError(f"origin latitude must lie in [-90, 90] deg, got {values[0]!r}")
    return values


def _enu_rotation(lat: np.ndarray | float, lon: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) columns = east, north, up unit vectors (ECEF) at (lat, lon) (...,) in rad."""
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    east = np.stack((-sl, cl, np.zeros_like(sl)), -1)
    north = np.stack((-sp * cl, -sp * sl, cp), -1)
    up = np.stack((cp * cl, cp * sl, sp), -1)
    return np.stack((east, north, up), -1)


def _wrap_degrees(angle: np.ndarray) -> np.ndarray:
    """Angles (...,) in deg wrapped into [-180, 180); values already inside are unchanged.

    Within one turn outside the range the wrap is one exact subtraction or addition of 360
    (Sterbenz), so no bits are lost; only angles further out go through ``%``.
    """
    near = np.where(angle >= 180.0, angle - 360.0, np.where(angle < -180.0, angle + 360.0, angle))
    far = (near < -180.0) | (near >= 180.0)
    return np.where(far, (angle + 180.0) % 360.0 - 180.0, near)


def _ecef_difference(
    dlat_deg: np.ndarray,
    dlon_deg: np.ndarray,
    dalt: np.ndarray,
    origin: tuple[float, float, float],
) -> np.ndarray:
    """``ecef(origin + d) - ecef(origin)`` (..., 3) from coordinate differences, m."""
    lat0, lon0 = np.radians(origin[0]), np.radians(origin[1])
    alt0 = origin[2]
    dlat, dlon = np.radians(dlat_deg), np.radians(dlon_deg)
    lat, lon = lat0 + dlat, lon0 + dlon
    half_lat, half_lon = np.sin(0.5 * dlat), np.sin(0.5 * dlon)
    mid_lat, mid_lon = lat0 + 0.5 * dlat, lon0 + 0.5 * dlon
    dcos_lat = -2.0 * np.sin(mid_lat) * half_lat
    dsin_lat = 2.0 * np.cos(mid_lat) * half_lat
    dcos_lon = -2.0 * np.sin(mid_lon) * half_lon
    dsin_lon = 2.0 * np.cos(mid_lon) * half_lon
    s, s0 = np.sin(lat), np.sin(lat0)
    u, u0 = 1.0 - _E2 * s * s, 1.0 - _E2 * s0 * s0
    root, root0 = np.sqrt(u), np.sqrt(u0)
    # N - N0 = a (1/sqrt(u) - 1/sqrt(u0)) = a (u0 - u) / (sqrt(u) sqrt(u0) (sqrt(u) + sqrt(u0)))
    dprime = WGS84_A * _E2 * dsin_lat * (s + s0) / (root * root0 * (root + root0))
    prime0 = WGS84_A / root0
    radial0 = (prime0 + alt0) * np.cos(lat0)
    dradial = (dprime + dalt) * np.cos(lat) + (prime0 + alt0) * dcos_lat
    dx = dradial * np.cos(lon) + radial0 * dcos_lon
    dy = dradial * np.sin(lon) + radial0 * dsin_lon
    dz = (dprime * (1.0 - _E2) + dalt) * s + (prime0 * (1.0 - _E2) + alt0) * dsin_lat
    return np.stack((dx, dy, dz), -1)


def geodetic_to_enu(
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    origin: Sequence[float],
) -> np.ndarray:
    """ENU coordinates (..., 3) in m of geodetic points (...,) relative to ``origin``.

    Args:
        lat_deg, lon_deg: (...,) latitude and longitude, degrees (WGS-84).
        alt_m: (...,) height above the WGS-84 ellipsoid, m.
        origin: ``[lat0_deg, lon0_deg, alt0_m]``, the ENU origin.

    Returns:
        (..., 3) ``[east, north, up]`` in m.
    """
    lat0, lon0, alt0 = _origin(origin)
    dlat = np.asarray(lat_deg, dtype=np.float64) - lat0
    lon = np.asarray(lon_deg, dtype=np.float64)
    # across the antimeridian, move the longitude by a turn first: that sum is exact, and
    # so is the difference of two nearby longitudes that follows
    raw = lon - lon0
    lon = np.where(raw > 180.0, lon - 360.0, np.where(raw < -180.0, lon + 360.0, lon))
    dlon = lon - lon0
    dalt = np.asarray(alt_m, dtype=np.float64) - alt0
    diff = _ecef_difference(dlat, dlon, dalt, (lat0, lon0, alt0))
    return diff @ _enu_rotation(np.radians(lat0), np.radians(lon0))


def enu_to_geodetic(
    enu: np.ndarray, origin: Sequence[float], iterations: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`geodetic_to_enu`: ENU (..., 3) in m -> (lat_deg, lon_deg, alt_m).

    Newton's method on the coordinate differences from the origin, with the exact
    Jacobian of the ECEF position (columns ``(M + h) north``, ``(N + h) cos(lat) east``,
    ``up`` per radian and metre). Six steps reach float64 precision within tens of km.

    Args:
        enu: (..., 3) ``[east, north, up]``, m.
        origin: ``[lat0_deg, lon0_deg, alt0_m]``.
        iterations: Newton steps.

    Returns:
        latitude (...,) deg, longitude (...,) deg in [-180, 180), altitude (...,) m.
    """
    lat0, lon0, alt0 = _origin(origin)
    target = np.asarray(enu, dtype=np.float64)
    rot0 = _enu_rotation(np.radians(lat0), np.radians(lon0))
    shape = target.shape[:-1]
    delta = np.zeros((*shape, 3))  # dlat_deg, dlon_deg, dalt
    for _ in range(iterations):
        lat = np.radians(lat0 + delta[..., 0])
        lon = np.radians(lon0 + delta[..., 1])
        current = _ecef_difference(delta[..., 0], delta[..., 1], delta[..., 2], (lat0, lon0, alt0))
        residual = target - current @ rot0
        s = np.sin(lat)
        w = np.sqrt(1.0 - _E2 * s * s)
        prime = WGS84_A / w
        meridian = WGS84_A * (1.0 - _E2) / w**3
        h = alt0 + delta[..., 2]
        local = _enu_rotation(lat, lon)  # (..., 3, 3) east, north, up columns
        scale = np.stack(
            (
                np.radians(1.0) * (meridian + h),
                np.radians(1.0) * (prime + h) * np.cos(lat),
                np.ones_like(h),
            ),
            -1,
        )
        columns = np.stack((local[..., :, 1], local[..., :, 0], local[..., :, 2]), -1)
        jac = rot0.T @ (columns * scale[..., None, :])
        delta = delta + np.linalg.solve(jac, residual[..., None])[..., 0]
    return lat0 + delta[..., 0], _wrap_degrees(lon0 + delta[..., 1]), alt0 + delta[..., 2]
