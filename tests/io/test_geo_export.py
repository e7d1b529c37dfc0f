"""Map exports (GeoJSON, KML) against the textbook ECEF route in extended precision; the
geodetic origin a native folder keeps in ``meta.json``; ``msf nmea`` storing it and ``msf run
--export geojson,kml`` using it; the IMU mounting ``meta.json`` may give."""

from __future__ import annotations

import dataclasses
import datetime
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.geometry import so3
from msf_torch.io.errors import DataError
from msf_torch.io.geo_export import time_origin_ns, write_geojson, write_gpx, write_kml
from msf_torch.io.native import (
    read_native,
    store_gnss_origin,
    store_time_origin,
    stored_gnss_origin,
    stored_time_origin,
    write_native,
)
from msf_torch.io.tum import read_tum
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.types import GnssFixes, Trajectory

KML = "{http://www.opengis.net/kml/2.2}"
ORIGINS = [(49.0125, 8.4172, 115.3), (-33.8688, 151.2093, 58.0), (78.2232, 15.6267, 10.0)]


def _enu(lon_lat_h: np.ndarray, origin, reference) -> np.ndarray:
    """ENU (N, 3) of ``[lon, lat, h]`` rows by the textbook route (``enu_reference``)."""
    return reference(lon_lat_h[:, 1], lon_lat_h[:, 0], lon_lat_h[:, 2], origin)


def _track(seed: int, n: int = 300) -> tuple[Trajectory, np.ndarray]:
    """A B = 1 trajectory of n poses over ~20 km, the last 10 padding; its real positions."""
    rng = np.random.default_rng(seed)
    enu = np.cumsum(rng.normal(size=(n, 3)) * [80.0, 80.0, 0.5], 0)
    enu[:, :2] += np.linspace(0.0, 15000.0, n)[:, None]  # heading north-east
    mask = np.ones(n, dtype=bool)
    mask[-10:] = False
    quat = torch.zeros(1, n, 4, dtype=torch.float64)
    quat[..., 0] = 1.0
    traj = Trajectory(
        t=torch.arange(n, dtype=torch.float64)[None] * 0.1,
        position=torch.as_tensor(enu)[None],
        quaternion=quat,
        mask=torch.as_tensor(mask)[None],
    )
    return traj, enu[mask]


def _fixes(enu: np.ndarray) -> GnssFixes:
    n = enu.shape[0]
    return GnssFixes(
        t=torch.arange(n, dtype=torch.float64)[None],
        position=torch.as_tensor(enu)[None],
        sigma=torch.full((1, n, 3), float("nan"), dtype=torch.float64),
        mask=torch.ones(1, n, dtype=torch.bool),
    )


@pytest.mark.parametrize("origin", ORIGINS)
def test_geojson_points_are_the_enu_positions_on_the_earth(tmp_path, origin, enu_reference) -> None:
    traj, enu = _track(3)
    fix_enu = enu[::25] + 1.5
    path = write_geojson(
        tmp_path / "t.geojson", origin, {"estimate": traj}, {"gnss": _fixes(fix_enu)}
    )
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["properties"]["enu_origin"] == dict(
        zip(("lat_deg", "lon_deg", "height_m"), origin, strict=True)
    )
    line, points = doc["features"]
    assert line["geometry"]["type"] == "LineString" and points["geometry"]["type"] == "MultiPoint"
    assert line["properties"] == {
        "name": "estimate",
        "kind": "track",
        "points": enu.shape[0],
        "t_start_s": 0.0,
        "t_end_s": pytest.approx(0.1 * (enu.shape[0] - 1)),
    }
    coords = np.array(line["geometry"]["coordinates"])
    assert np.abs(coords[:, 1] - origin[0]).max() > 0.1  # kilometres, not a neighbourhood
    # 9 decimals of a degree and 4 of a metre: within 0.1 mm
    assert np.abs(_enu(coords, origin, enu_reference) - enu).max() < 1e-4
    fixes = np.array(points["geometry"]["coordinates"])
    assert np.abs(_enu(fixes, origin, enu_reference) - fix_enu).max() < 1e-4


def test_kml_holds_the_same_coordinates_clamped_to_the_ground(tmp_path, enu_reference) -> None:
    origin = ORIGINS[1]
    traj, enu = _track(4)
    truth, _ = _track(5, 40)
    fixes = _fixes(enu[::30])
    tracks = {"estimate": traj, "ground truth": truth}
    geo = json.loads(
        write_geojson(tmp_path / "t.geojson", origin, tracks, {"GNSS": fixes}).read_text()
    )
    root = ET.parse(write_kml(tmp_path / "t.kml", origin, tracks, {"GNSS": fixes}, name="run 1"))
    document = root.getroot().find(f"{KML}Document")
    assert document.findtext(f"{KML}name") == "run 1"
    marks = document.findall(f"{KML}Placemark")
    assert [m.findtext(f"{KML}name") for m in marks] == ["estimate", "ground truth", "GNSS"]
    for mark, feature in zip(marks[:2], geo["features"][:2], strict=True):
        line = mark.find(f"{KML}LineString")
        assert line.findtext(f"{KML}altitudeMode") == "clampToGround"
        text = line.findtext(f"{KML}coordinates").split()
        coords = np.array([[float(x) for x in item.split(",")] for item in text])
        np.testing.assert_allclose(coords, feature["geometry"]["coordinates"], atol=1e-9)
    points = marks[2].findall(f"{KML}MultiGeometry/{KML}Point/{KML}coordinates")
    coords = np.array([[float(x) for x in p.text.split(",")] for p in points])
    assert np.abs(_enu(coords, origin, enu_reference) - enu[::30]).max() < 1e-4
    styles = {s.get("id"): s for s in document.findall(f"{KML}Style")}
    colours = [styles[m.findtext(f"{KML}styleUrl")[1:]].findtext(f".//{KML}color") for m in marks]
    assert colours[0] != colours[1] and colours[2] is None


def test_short_tracks_are_left_out_and_batches_refused(tmp_path) -> None:
    traj, _ = _track(6, 12)  # two real poses: kept
    lone, _ = _track(7, 11)  # one real pose: no line
    doc = json.loads(
        write_geojson(tmp_path / "t.geojson", ORIGINS[0], {"a": traj, "b": lone}).read_text()
    )
    assert [f["properties"]["name"] for f in doc["features"]] == ["a"]
    two = Trajectory(
        *(torch.cat((x, x)) for x in (traj.t, traj.position, traj.quaternion, traj.mask))
    )
    with pytest.raises(ValueError, match="B = 2"):
        write_geojson(tmp_path / "t.geojson", ORIGINS[0], {"a": two})


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    run = simulate_run(SimConfig(duration_s=20.0, slip_episodes=0), 9)
    return run.sequence


@pytest.mark.parametrize(
    ("value", "match"),
    [
        ([49.0, 8.4], "expected"),
        ([49.0, "8.4", 1.0], "expected"),
        ([49.0, 8.4, True], "expected"),
        ([49.0, 8.4, 10**400], "expected"),
        ({"lat": 49.0}, "expected"),
        ([91.0, 8.4, 0.0], "latitude"),
    ],
)
def test_malformed_gnss_origin_names_the_field(tmp_path, short_run, value, match) -> None:
    folder = tmp_path / "run"
    write_native(short_run, folder)
    (folder / "meta.json").write_text(json.dumps({"gnss_origin": value}))
    with pytest.raises(DataError, match=match) as err:
        read_native(folder)
    assert err.value.field == "gnss_origin"
    with pytest.raises(DataError):
        stored_gnss_origin(folder)


def test_gnss_origin_is_kept_by_the_native_format(tmp_path, short_run) -> None:
    folder = tmp_path / "run"
    write_native(short_run, folder)
    assert stored_gnss_origin(folder) is None
    (folder / "meta.json").write_text(json.dumps({"wheel_track_m": 0.5}))
    store_gnss_origin(folder, (49.0, 8.4, 110))
    assert json.loads((folder / "meta.json").read_text()) == {
        "gnss_origin": [49.0, 8.4, 110.0],
        "wheel_track_m": 0.5,
    }
    seq = read_native(folder)
    assert seq.meta["gnss_origin"] == [49.0, 8.4, 110.0]
    for target in (tmp_path / "copy.npz", tmp_path / "copy"):
        assert read_native(write_native(seq, target)).meta["gnss_origin"] == [49.0, 8.4, 110.0]


def test_run_exports_the_estimate_and_fixes_on_the_map(
    tmp_path, short_run, capsys, enu_reference
) -> None:
    folder = tmp_path / "run"
    write_native(short_run, folder)
    args = ["run", str(folder), "--no-plot", "--no-learned", "--export", "geojson,kml"]
    assert main([*args, "--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "has no geodetic origin" in err and "gnss_origin" in err
    assert not (tmp_path / "none").exists()

    origin = (-33.8688, 151.2093, 58.0)
    store_gnss_origin(folder, origin)
    out = tmp_path / "out"
    assert main([*args, "--out", str(out), "--gnss-outage", "5:10"]) == 0
    capsys.readouterr()
    doc = json.loads((out / "trajectory.geojson").read_text())
    names = [f["properties"]["name"] for f in doc["features"]]
    assert names == ["estimate", "ground truth", "GNSS fixes", "withheld GNSS fixes"]
    estimate = read_tum(out / "trajectory.tum")
    coords = np.array(doc["features"][0]["geometry"]["coordinates"])
    assert coords.shape[0] == estimate.t.shape[1]
    assert np.abs(_enu(coords, origin, enu_reference) - estimate.position[0].numpy()).max() < 1e-4
    withheld = np.array(doc["features"][3]["geometry"]["coordinates"])
    t = short_run.gnss.t[0].numpy() - float(short_run.start_time[0])
    assert withheld.shape[0] == int(((t >= 5.0) & (t <= 10.0)).sum())
    kml = ET.parse(out / "trajectory.kml").getroot()
    assert len(kml.findall(f"{KML}Document/{KML}Placemark")) == 4


def test_imu_mounting_turns_the_samples_into_body_axes(tmp_path, short_run) -> None:
    """``imu_rpy_deg`` in meta.json: an IMU mounted upside down and turned 90 degrees reads
    back in body axes (the run's own samples), and a second write keeps them so."""
    mounting = (180.0, 0.0, 90.0)
    turn = so3.rpy_matrix(torch.tensor(np.radians(mounting)))  # R_body_imu
    imu = short_run.imu
    raw = dataclasses.replace(imu, gyro=imu.gyro @ turn, accel=imu.accel @ turn)
    folder = write_native(dataclasses.replace(short_run, imu=raw), tmp_path / "raw")
    (folder / "meta.json").write_text(json.dumps({"imu_rpy_deg": list(mounting)}))
    seq = read_native(folder)
    torch.testing.assert_close(seq.imu.gyro, imu.gyro, rtol=0, atol=1e-15)
    torch.testing.assert_close(seq.imu.accel, imu.accel, rtol=0, atol=1e-14)
    assert seq.meta["imu_rpy_deg_applied"] == list(mounting)
    again = read_native(write_native(seq, tmp_path / "again"))
    torch.testing.assert_close(again.imu.accel, imu.accel, rtol=0, atol=1e-14)
    (folder / "meta.json").write_text(json.dumps({"imu_rpy_deg": [0, 90]}))
    with pytest.raises(DataError, match="roll, pitch, yaw") as err:
        read_native(folder)
    assert err.value.field == "imu_rpy_deg"


GPX = "{http://www.topografix.com/GPX/1/1}"
# the GPX 1.1 schema's xsd:sequence of the elements msf_torch writes (gpx.xsd, 2004)
GPX_ORDER = {
    "gpx": ["metadata", "wpt", "rte", "trk", "extensions"],
    "metadata": ["name", "desc", "author", "copyright", "link", "time", "keywords", "bounds"],
    "trk": ["name", "cmt", "desc", "src", "link", "number", "type", "extensions", "trkseg"],
    "trkseg": ["trkpt", "extensions"],
    "trkpt": ["ele", "time", "magvar", "geoidheight", "name", "cmt", "desc", "src", "link"],
}


def _check_gpx_1_1(element: ET.Element) -> None:
    """Every element's children in its GPX 1.1 sequence order, point attributes in range."""
    tag = element.tag.removeprefix(GPX)
    assert element.tag.startswith(GPX), element.tag
    if tag == "trkpt":
        lat, lon = float(element.get("lat")), float(element.get("lon"))
        assert -90.0 <= lat <= 90.0 and -180.0 <= lon < 180.0
    if tag == "bounds":
        assert set(element.keys()) == {"minlat", "minlon", "maxlat", "maxlon"}
    order = GPX_ORDER.get(tag, [])
    ranks = [order.index(child.tag.removeprefix(GPX)) for child in element if order]
    assert ranks == sorted(ranks), (tag, [child.tag for child in element])
    for child in element:
        _check_gpx_1_1(child)


@pytest.mark.parametrize("origin", ORIGINS)
def test_gpx_points_are_the_geojson_points(tmp_path, origin) -> None:
    """lat / lon of every trkpt equal geo_export's GeoJSON to 1e-9 deg, ele its height; one
    trk per track and per set of fixes, in GPX 1.1 element order; no times without an
    absolute time origin."""
    traj, enu = _track(8)
    truth, _ = _track(9, 50)
    tracks, fixes = {"estimate": traj, "ground truth": truth}, {"GNSS fixes": _fixes(enu[::20])}
    geo = json.loads(write_geojson(tmp_path / "t.geojson", origin, tracks, fixes).read_text())
    root = ET.parse(write_gpx(tmp_path / "t.gpx", origin, tracks, fixes, name="run 2")).getroot()
    assert root.tag == f"{GPX}gpx" and root.get("version") == "1.1" and root.get("creator")
    _check_gpx_1_1(root)
    assert root.findtext(f"{GPX}metadata/{GPX}name") == "run 2"
    assert "WGS-84 ellipsoid" in root.findtext(f"{GPX}metadata/{GPX}desc")
    trks = root.findall(f"{GPX}trk")
    assert [t.findtext(f"{GPX}name") for t in trks] == ["estimate", "ground truth", "GNSS fixes"]
    assert [t.findtext(f"{GPX}type") for t in trks] == ["track", "track", "fixes"]
    every = []
    for trk, feature in zip(trks, geo["features"], strict=True):
        points = trk.findall(f"{GPX}trkseg/{GPX}trkpt")
        got = np.array([[float(p.get("lon")), float(p.get("lat"))] for p in points])
        want = np.array(feature["geometry"]["coordinates"])
        np.testing.assert_allclose(got, want[:, :2], rtol=0, atol=1e-9)
        height = np.array([float(p.findtext(f"{GPX}ele")) for p in points])
        np.testing.assert_allclose(height, want[:, 2], rtol=0, atol=1e-4)
        assert all(p.find(f"{GPX}time") is None for p in points)
        every.append(got)
    every = np.concatenate(every)
    bounds = root.find(f"{GPX}metadata/{GPX}bounds")
    assert float(bounds.get("minlat")) == pytest.approx(every[:, 1].min(), abs=1e-9)
    assert float(bounds.get("maxlon")) == pytest.approx(every[:, 0].max(), abs=1e-9)


def test_gpx_times_are_utc_from_the_time_origin(tmp_path) -> None:
    """<time> = time origin + t in ISO 8601 UTC (to the microsecond), ele before time; an
    origin whose times fall before the GPS epoch (simulated time) writes none."""
    traj, _ = _track(10, 40)
    traj = dataclasses.replace(traj, t=traj.t * 2.5 + 0.1234565)
    origin_ns = 1_634_601_580_123_456_789  # 2021-10-18 23:59:40.123456789 UTC
    root = ET.parse(
        write_gpx(tmp_path / "t.gpx", ORIGINS[0], {"estimate": traj}, time_origin=origin_ns)
    ).getroot()
    _check_gpx_1_1(root)
    points = root.findall(f"{GPX}trk/{GPX}trkseg/{GPX}trkpt")
    assert [child.tag for child in points[0]] == [f"{GPX}ele", f"{GPX}time"]
    text = [p.findtext(f"{GPX}time") for p in points]
    assert text[0] == "2021-10-18T23:59:40.246913Z"  # .123456789 + .1234565 s
    assert all(x.endswith("Z") for x in text)
    stamps = np.array([datetime.datetime.fromisoformat(x).timestamp() for x in text])
    want = origin_ns / 1e9 + traj.t[0, traj.mask[0]].numpy()
    np.testing.assert_allclose(stamps, want, rtol=0, atol=2e-6)
    # a bag recorded with simulated time: its origin is no UTC time
    sim = write_gpx(tmp_path / "sim.gpx", ORIGINS[0], {"estimate": traj}, time_origin=10**9)
    assert ET.parse(sim).getroot().find(f".//{GPX}time") is None


def test_gpx_longitude_stays_below_180_across_the_antimeridian(tmp_path) -> None:
    origin = (-16.5, 179.99995, 5.0)  # Fiji: the track runs east over 180 deg
    n = 20
    enu = np.zeros((n, 3))
    enu[:, 0] = np.linspace(0.0, 20.0, n)
    traj = Trajectory(
        t=torch.arange(n, dtype=torch.float64)[None],
        position=torch.as_tensor(enu)[None],
        quaternion=torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(1, n, 4),
        mask=torch.ones(1, n, dtype=torch.bool),
    )
    root = ET.parse(write_gpx(tmp_path / "t.gpx", origin, {"estimate": traj})).getroot()
    _check_gpx_1_1(root)
    lon = np.array([float(p.get("lon")) for p in root.iter(f"{GPX}trkpt")])
    assert (lon[:5] > 179.9).all() and (lon[-5:] < -179.9).all()


def test_time_origin_of_a_sequence() -> None:
    assert time_origin_ns({"time_origin_ns": 5}) == 5  # a ROS bag, a KITTI raw drive
    assert time_origin_ns({"sensor": {"wheel_track_m": 0.5}}) is None
    assert time_origin_ns({}) is None
    for bad in (1.5, "5", True):
        with pytest.raises(ValueError, match="integer number of ns"):
            time_origin_ns({"time_origin_ns": bad})


def test_time_origin_is_kept_by_the_native_format(tmp_path, short_run) -> None:
    """meta.json's time_origin_ns reaches meta["time_origin_ns"] (as a bag's) and survives a
    write; a value that is not an integer names the field."""
    folder = tmp_path / "run"
    write_native(short_run, folder)
    assert stored_time_origin(folder) is None
    store_time_origin(folder, 1_634_601_580_250_000_000)
    seq = read_native(folder)
    assert seq.meta["time_origin_ns"] == 1_634_601_580_250_000_000
    assert stored_time_origin(folder) == 1_634_601_580_250_000_000
    for target in (tmp_path / "copy.npz", tmp_path / "copy"):
        back = read_native(write_native(seq, target))
        assert back.meta["time_origin_ns"] == 1_634_601_580_250_000_000
    for bad in (1.5e18, "1634601580", True, None):
        (folder / "meta.json").write_text(json.dumps({"time_origin_ns": bad}))
        with pytest.raises(DataError) as err:
            read_native(folder)
        assert err.value.field == "time_origin_ns"


def test_run_exports_gpx_with_utc_times(tmp_path, short_run, capsys) -> None:
    """msf run --export gpx: trajectory.gpx holds the estimate (lat / lon as the GeoJSON's),
    the ground truth and the fixes, with UTC times from meta.json's time_origin_ns."""
    folder = tmp_path / "run"
    write_native(short_run, folder)
    store_gnss_origin(folder, ORIGINS[0])
    store_time_origin(folder, 1_634_601_580_000_000_000)
    out = tmp_path / "out"
    args = ["run", str(folder), "--no-plot", "--no-learned", "--out", str(out)]
    assert main([*args, "--export", "gpx,geojson"]) == 0
    capsys.readouterr()
    root = ET.parse(out / "trajectory.gpx").getroot()
    _check_gpx_1_1(root)
    names = [trk.findtext(f"{GPX}name") for trk in root.findall(f"{GPX}trk")]
    assert names == ["estimate", "ground truth", "GNSS fixes"]
    doc = json.loads((out / "trajectory.geojson").read_text())
    points = root.findall(f"{GPX}trk/{GPX}trkseg/{GPX}trkpt")[
        : len(doc["features"][0]["geometry"]["coordinates"])
    ]
    got = np.array([[float(p.get("lon")), float(p.get("lat"))] for p in points])
    want = np.array(doc["features"][0]["geometry"]["coordinates"])[:, :2]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    estimate = read_tum(out / "trajectory.tum")
    stamp = datetime.datetime.fromisoformat(points[0].findtext(f"{GPX}time")).timestamp()
    assert stamp == pytest.approx(1_634_601_580 + float(estimate.t[0, 0]), abs=1e-6)
