"""Geodetic <-> local ENU against an extended-precision textbook route (np.longdouble)."""

from __future__ import annotations

import numpy as np
import pytest

from msf_torch.io.geodesy import enu_to_geodetic, geodetic_to_ecef, geodetic_to_enu

ORIGINS = [
    (49.0125, 8.4172, 115.3),
    (-33.8688, 151.2093, 58.0),
    (78.2232, 15.6267, 10.0),  # high latitude
    (-17.7, 179.99, 0.0),  # at the antimeridian: points on both sides
]


@pytest.mark.skipif(np.finfo(np.longdouble).eps > 1e-18, reason="needs extended precision")
@pytest.mark.parametrize("origin", ORIGINS)
def test_enu_matches_extended_precision(origin, enu_reference) -> None:
    rng = np.random.default_rng(1)
    lat = origin[0] + rng.uniform(-0.05, 0.05, 200)
    lon = origin[1] + rng.uniform(-0.05, 0.05, 200)
    alt = origin[2] + rng.uniform(-50, 50, 200)
    want = enu_reference(lat, lon, alt, origin)
    lon = np.where(lon >= 180.0, lon - 360.0, lon)  # points past 180 deg come as -179.x
    got = geodetic_to_enu(lat, lon, alt, origin)
    assert np.abs(got - want).max() < 1e-9
    assert np.abs(want).max() > 1000  # kilometres away, not a trivial neighbourhood


@pytest.mark.parametrize("origin", ORIGINS)
def test_enu_round_trip(origin) -> None:
    rng = np.random.default_rng(2)
    enu = rng.normal(size=(500, 3)) * [3000.0, 3000.0, 30.0]
    lat, lon, alt = enu_to_geodetic(enu, origin)
    assert np.all((lon >= -180) & (lon < 180))
    back = geodetic_to_enu(lat, lon, alt, origin)
    # limited by how finely float64 degrees resolve a position: half a unit in the last
    # place of the latitude and of the longitude, in metres (2.6e-9 m at 151 deg E, 34 deg S)
    metres_per_degree = np.pi / 180 * 6.4e6
    resolution = (
        0.5
        * metres_per_degree
        * (np.spacing(abs(lat)) + np.spacing(np.abs(lon)) * np.cos(np.radians(lat)))
    )
    assert np.all(np.abs(back - enu)[:, :2].max(axis=1) <= resolution + 1e-12)
    assert np.abs(back - enu)[:, 2].max() < 1e-9
    # the origin maps to zero exactly
    assert not geodetic_to_enu(*[np.array(x) for x in origin], origin).any()


def test_ecef_and_origin_checks() -> None:
    # on the equator at the prime meridian: x = a + h
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 10.0), [6378147.0, 0.0, 0.0])
    # at the north pole: z = b + h, b = a (1 - f)
    z = geodetic_to_ecef(90.0, 0.0, 0.0)[2]
    assert z == pytest.approx(6378137.0 * (1 - 1 / 298.257223563), abs=1e-8)
    with pytest.raises(ValueError, match="latitude"):
        geodetic_to_enu(0.0, 0.0, 0.0, (91.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="lat_deg, lon_deg, alt_m"):
        geodetic_to_enu(0.0, 0.0, 0.0, (1.0, 2.0))
