"""Map exports (GeoJSON, KML) against the textbook ECEF route in extended precision; the
geodetic origin a native folder keeps in ``meta.json``; ``msf nmea`` storing it and ``msf run
--export geojson,kml`` using it; the IMU mounting ``meta.json`` may give."""

from __future__ import annotations

import dataclasses
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from msf_torch.cli import main
from msf_torch.geometry import so3
from msf_torch.io.errors import DataError
from msf_torch.io.geo_export import write_geojson, write_kml
from msf_torch.io.native import read_native, store_gnss_origin, stored_gnss_origin, write_native
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
