"""Trajectories on the map: GeoJSON (RFC 7946), KML 2.2 and GPX 1.1 in WGS-84 longitude /
latitude.

msf_torch estimates in a local East-North-Up frame whose origin is a geodetic point
``(lat0_deg, lon0_deg, alt0_m)`` (:mod:`msf_torch.io.geodesy`). Given that origin -- a ROS
bag's GNSS sets it (``meta["gnss_origin"]``), a native folder keeps it in ``meta.json``
(``msf nmea`` writes it) -- these writers put ENU tracks back on the Earth, exactly (no
flat-Earth step: :func:`~msf_torch.io.geodesy.enu_to_geodetic`), for QGIS, geojson.io,
Google Earth or any web map:

* :func:`write_geojson`: a ``FeatureCollection`` with one ``LineString`` feature per track
  (the estimate; the ground truth when there is one) and one ``MultiPoint`` feature per set
  of GNSS fixes (those fused; those withheld). Positions are ``[longitude, latitude,
  height]``: degrees with 9 decimals (0.1 mm) and metres above the WGS-84 ellipsoid with 4
  (RFC 7946's third coordinate).
  Each feature's ``properties`` hold ``name``, ``kind`` (``"track"`` or ``"fixes"``),
  ``points``, ``t_start_s`` and ``t_end_s`` (the sequence's time axis); the collection's
  ``properties`` the ENU origin.
* :func:`write_kml`: a ``Document`` with one styled ``LineString`` ``Placemark`` per track
  and one ``MultiGeometry`` of ``Point`` s per set of fixes, ``altitudeMode`` ``clampToGround``:
  KML heights are above mean sea level, ours above the ellipsoid (they differ by the geoid
  undulation, tens of metres), and a ground vehicle is on the ground anyway. The
  coordinates still carry the ellipsoidal heights.
* :func:`write_gpx`: a GPX 1.1 file with one ``<trk>`` per track and per set of fixes,
  ``<ele>`` the ellipsoidal height (said in the file), ``<time>`` in UTC when the sequence
  has an absolute time origin (:func:`time_origin_ns`).

Positions are the body origin's (the IMU's), GNSS fixes the antenna's. Only real samples
(mask True) are written; a track with fewer than two is left out. Writes are atomic.

Example:
    >>> origin = (49.0, 8.4, 110.0)
    >>> write_geojson("out/run.geojson", origin, {"estimate": traj})  # doctest: +SKIP
"""

from __future__ import annotations

__all__ = [
    "GPS_EPOCH_UNIX_NS",
    "geodetic_points",
    "time_origin_ns",
    "write_geojson",
    "write_gpx",
    "write_kml",
]

import datetime
import json
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.io.atomic import atomic_write
from msf_torch.io.geodesy import enu_to_geodetic

_KML_NS = "http://www.opengis.net/kml/2.2"
_GPX_NS = "http://www.topografix.com/GPX/1/1"
_TRACK_COLOURS = ("ff0000ff", "ff00c800", "ffff0000", "ff00a5ff")
"""KML line colours (aabbggrr), one per track in order: red, green, blue, orange."""
_FIX_ICON = "https://maps.google.com/mapfiles/kml/shapes/placemark_circle.png"


def geodetic_points(
    times: torch.Tensor, positions: torch.Tensor, mask: torch.Tensor, origin: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """The real samples of one B = 1 stream as geodetic points.

    Args:
        times: (1, N) s. positions: (1, N, 3) ENU m. mask: (1, N) bool.
        origin: ``[lat0_deg, lon0_deg, alt0_m]`` of the ENU frame.

    Returns:
        times (M,) s and ``[lon_deg, lat_deg, height_m]`` (M, 3) of the M real samples.

    Raises:
        ValueError: B != 1 or a bad origin.
    """
    if positions.shape[0] != 1:
        raise ValueError(f"one sequence at a time (B = 1), got B = {positions.shape[0]}")
    keep = mask[0].cpu().numpy().astype(bool)
    enu = positions[0].detach().cpu().numpy().astype(np.float64)[keep]
    lat, lon, height = enu_to_geodetic(enu, origin)
    return times[0].detach().cpu().numpy().astype(np.float64)[keep], np.stack(
        (lon, lat, height), -1
    )


def _streams(
    origin: Sequence[float], tracks: Mapping[str, Any], fixes: Mapping[str, Any] | None
) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """``(name, kind, times, lon-lat-height)`` per written stream: tracks with >= 2 real
    samples, then the non-empty sets of fixes."""
    out = []
    for kind, streams, least in (("track", tracks, 2), ("fixes", fixes or {}, 1)):
        for name, stream in streams.items():
            t, points = geodetic_points(stream.t, stream.position, stream.mask, origin)
            if len(t) >= least:
                out.append((str(name), kind, t, points))
    return out


def _position(point: np.ndarray) -> list[float]:
    return [round(float(point[0]), 9), round(float(point[1]), 9), round(float(point[2]), 4)]


def write_geojson(
    path: str | os.PathLike[str],
    origin: Sequence[float],
    tracks: Mapping[str, Any],
    fixes: Mapping[str, Any] | None = None,
) -> Path:
    """Write tracks (and GNSS fixes) as an RFC 7946 GeoJSON ``FeatureCollection``.

    Args:
        path: file to write (``.geojson``).
        origin: ``[lat0_deg, lon0_deg, alt0_m]`` of the ENU frame the positions are in.
        tracks: name -> B = 1 :class:`~msf_torch.types.Trajectory` (or any stream with
            ``t``, ``position``, ``mask``); each becomes a ``LineString`` feature.
        fixes: name -> B = 1 :class:`~msf_torch.types.GnssFixes`; each a ``MultiPoint``
            feature.

    Returns:
        ``path`` as a ``Path``.
    """
    features = []
    for name, kind, t, points in _streams(origin, tracks, fixes):
        geometry = "LineString" if kind == "track" else "MultiPoint"
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": geometry, "coordinates": [_position(p) for p in points]},
                "properties": {
                    "name": name,
                    "kind": kind,
                    "points": len(t),
                    "t_start_s": float(t[0]),
                    "t_end_s": float(t[-1]),
                },
            }
        )
    lat0, lon0, alt0 = (float(x) for x in origin)
    collection = {
        "type": "FeatureCollection",
        "properties": {"enu_origin": {"lat_deg": lat0, "lon_deg": lon0, "height_m": alt0}},
        "features": features,
    }
    target = Path(path)
    with atomic_write(target) as handle:
        json.dump(collection, handle, separators=(",", ":"))
        handle.write("\n")
    return target


def _sub(parent: ET.Element, tag: str, text: str | None = None) -> ET.Element:
    element = ET.SubElement(parent, f"{{{_KML_NS}}}{tag}")
    if text is not None:
        element.text = text
    return element


def _kml_coordinates(points: np.ndarray) -> str:
    return " ".join(f"{p[0]:.9f},{p[1]:.9f},{p[2]:.4f}" for p in points)


def write_kml(
    path: str | os.PathLike[str],
    origin: Sequence[float],
    tracks: Mapping[str, Any],
    fixes: Mapping[str, Any] | None = None,
    name: str = "msf_torch",
) -> Path:
    """Write tracks (and GNSS fixes) as a KML 2.2 document (Google Earth, QGIS).

    Args:
        path: file to write (``.kml``).
        origin: ``[lat0_deg, lon0_deg, alt0_m]`` of the ENU frame the positions are in.
        tracks: name -> B = 1 trajectory; each a ``LineString`` placemark, clamped to the
            ground, coloured red, green, blue, orange in order.
        fixes: name -> B = 1 GNSS fixes; each a placemark of points.
        name: the document's name.

    Returns:
        ``path`` as a ``Path``.
    """
    ET.register_namespace("", _KML_NS)
    root = ET.Element(f"{{{_KML_NS}}}kml")
    document = _sub(root, "Document")
    _sub(document, "name", name)
    lat0, lon0, alt0 = (float(x) for x in origin)
    _sub(
        document,
        "description",
        f"ENU origin {lat0!r} deg, {lon0!r} deg, {alt0!r} m (WGS-84 ellipsoid)",
    )
    track_count = 0
    for index, (stream_name, kind, t, points) in enumerate(_streams(origin, tracks, fixes)):
        style_id = f"style{index}"
        style = _sub(document, "Style")
        style.set("id", style_id)
        if kind == "track":
            line = _sub(style, "LineStyle")
            _sub(line, "color", _TRACK_COLOURS[track_count % len(_TRACK_COLOURS)])
            _sub(line, "width", "3")
            track_count += 1
        else:
            icon_style = _sub(style, "IconStyle")
            _sub(icon_style, "scale", "0.5")
            _sub(_sub(icon_style, "Icon"), "href", _FIX_ICON)
        placemark = _sub(document, "Placemark")
        _sub(placemark, "name", stream_name)
        _sub(placemark, "description", f"{len(t)} points, t = {t[0]:.3f} .. {t[-1]:.3f} s")
        _sub(placemark, "styleUrl", f"#{style_id}")
        if kind == "track":
            geometry = _sub(placemark, "LineString")
            _sub(geometry, "tessellate", "1")
            _sub(geometry, "altitudeMode", "clampToGround")
            _sub(geometry, "coordinates", _kml_coordinates(points))
        else:
            group = _sub(placemark, "MultiGeometry")
            for point in points:
                shape = _sub(group, "Point")
                _sub(shape, "altitudeMode", "clampToGround")
                _sub(shape, "coordinates", _kml_coordinates(point[None]))
    ET.indent(root, space=" ")
    target = Path(path)
    with atomic_write(target, "wb") as handle:
        ET.ElementTree(root).write(handle, encoding="UTF-8", xml_declaration=True)
    return target


GPS_EPOCH_UNIX_NS = 315_964_800_000_000_000
"""1980-01-06T00:00:00Z, the start of GPS time, in UNIX ns: :func:`write_gpx` writes no
``<time>`` when a time would fall before it (a clock that is not UTC: a bag recorded with
simulated time, times since boot)."""


def time_origin_ns(meta: Mapping[str, Any]) -> int | None:
    """The UNIX time (ns) of a sequence's ``t = 0``, when the sequence says.

    ``meta["time_origin_ns"]``: a ROS bag's header stamps' origin, a KITTI raw drive's first
    stamp, a native folder's ``meta.json`` entry (which ``msf nmea`` writes: the ``--t0``
    it moved the fixes by); None when there is none.

    Raises:
        ValueError: a value that is not an integer number of ns.
    """
    value = meta.get("time_origin_ns")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"time_origin_ns must be an integer number of ns, got {value!r}")
    return int(value)


def _gpx_time(origin_ns: int, t: float) -> str:
    """ISO 8601 UTC of ``origin_ns + t`` to the microsecond, e.g. ``2021-10-18T23:59:40.5Z``."""
    micro = (origin_ns + round(t * 1e9) + 500) // 1000  # to the nearest microsecond
    seconds, fraction = divmod(micro, 1_000_000)
    stamp = datetime.datetime.fromtimestamp(seconds, datetime.timezone.utc)
    text = f"{stamp:%Y-%m-%dT%H:%M:%S}"
    if fraction:
        text += f".{fraction:06d}".rstrip("0")
    return text + "Z"


def _gpx(parent: ET.Element, tag: str, text: str | None = None) -> ET.Element:
    element = ET.SubElement(parent, f"{{{_GPX_NS}}}{tag}")
    if text is not None:
        element.text = text
    return element


def write_gpx(
    path: str | os.PathLike[str],
    origin: Sequence[float],
    tracks: Mapping[str, Any],
    fixes: Mapping[str, Any] | None = None,
    *,
    time_origin: int | None = None,
    name: str = "msf_torch",
) -> Path:
    """Write tracks and GNSS fixes as a GPX 1.1 file (Garmin, Strava, OsmAnd, JOSM, QGIS).

    One ``<trk>`` per stream, in the order given: the tracks (``<type>track</type>``: the
    estimate, the ground truth), then each set of fixes (``<type>fixes</type>``; a
    receiver's log is a track of fixes too). Each ``<trkpt lat lon>`` holds ``<ele>`` and,
    with an absolute time origin, ``<time>``. Latitude and longitude are the exact
    :func:`~msf_torch.io.geodesy.enu_to_geodetic` of the ENU positions, as
    :func:`write_geojson` writes them (9 decimals, 0.1 mm; longitude in [-180, 180) as
    GPX requires). ``<ele>`` is the height above the WGS-84 ellipsoid (4 decimals), not
    above mean sea level as GPX readers assume: they differ by the geoid undulation (tens
    of metres; e.g. an NMEA GGA's geoid separation); the file's ``<metadata><desc>`` says
    so. ``<time>`` is ISO 8601 UTC, ``time_origin + t`` to the microsecond, written only
    when ``time_origin`` is given and every time is after :data:`GPS_EPOCH_UNIX_NS`.
    ``<metadata>`` also holds ``<name>`` and the ``<bounds>`` of all points.

    Args:
        path: file to write (``.gpx``).
        origin: ``[lat0_deg, lon0_deg, alt0_m]`` of the ENU frame the positions are in.
        tracks: name -> B = 1 trajectory (``t``, ``position``, ``mask``).
        fixes: name -> B = 1 GNSS fixes.
        time_origin: UNIX time of ``t = 0``, ns (:func:`time_origin_ns`); None: no times.
        name: the file's ``<metadata><name>``.

    Returns:
        ``path`` as a ``Path``.
    """
    streams = _streams(origin, tracks, fixes)
    utc_origin = time_origin
    if time_origin is not None and any(
        time_origin + round(float(t.min()) * 1e9) < GPS_EPOCH_UNIX_NS for _, _, t, _ in streams
    ):
        utc_origin = None  # not a UTC clock
    ET.register_namespace("", _GPX_NS)
    root = ET.Element(f"{{{_GPX_NS}}}gpx", {"version": "1.1", "creator": "msf_torch"})
    metadata = _gpx(root, "metadata")
    _gpx(metadata, "name", name)
    lat0, lon0, alt0 = (float(x) for x in origin)
    _gpx(
        metadata,
        "desc",
        f"ENU origin {lat0!r} deg, {lon0!r} deg, {alt0!r} m. ele: height above the WGS-84 "
        "ellipsoid, not mean sea level (the geoid undulation is not applied).",
    )
    if streams:
        every = np.concatenate([points for _, _, _, points in streams])
        low, high = every.min(axis=0), every.max(axis=0)
        bounds = _gpx(metadata, "bounds")
        bounds.attrib.update(
            {
                "minlat": f"{low[1]:.9f}",
                "minlon": f"{_gpx_longitude(low[0]):.9f}",
                "maxlat": f"{high[1]:.9f}",
                "maxlon": f"{_gpx_longitude(high[0]):.9f}",
            }
        )
    for stream_name, kind, t, points in streams:
        track = _gpx(root, "trk")
        _gpx(track, "name", stream_name)
        _gpx(track, "desc", f"{len(t)} points, t = {t[0]:.3f} .. {t[-1]:.3f} s")
        _gpx(track, "type", kind)
        segment = _gpx(track, "trkseg")
        for time, point in zip(t.tolist(), points, strict=True):
            lon, lat, height = _position(point)
            trkpt = _gpx(segment, "trkpt")
            trkpt.attrib.update({"lat": f"{lat:.9f}", "lon": f"{_gpx_longitude(lon):.9f}"})
            _gpx(trkpt, "ele", f"{height:.4f}")
            if utc_origin is not None:
                _gpx(trkpt, "time", _gpx_time(utc_origin, time))
    ET.indent(root, space=" ")
    target = Path(path)
    with atomic_write(target, "wb") as handle:
        ET.ElementTree(root).write(handle, encoding="UTF-8", xml_declaration=True)
    return target


def _gpx_longitude(lon: float) -> float:
    """Longitude in GPX's [-180, 180) (180 is written as -180)."""
    return -180.0 if lon >= 180.0 else lon
