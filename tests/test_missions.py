"""Missions and exports: every file is read back with the reference library
(pymavlink, gpxpy; the KML with the standard library's XML parser, simplekml only writes), and
the antimeridian split is checked against a brute-force reference."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from lrm_cvx import Region
from lrm_cvx.cli import main
from lrm_cvx.errors import PlanningError
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import place_sensors, plan_greedy
from lrm_cvx.planning.missions import (
    DEFAULT_ALTITUDE,
    route_points,
    split_antimeridian,
    to_qgc_plan,
    wrap_lon,
)

pytest.importorskip("pymavlink")
pytest.importorskip("gpxpy")
pytest.importorskip("simplekml")

LAT = np.arange(-6.0, 7.0, 2.0)
LON = np.arange(170.0, 193.0, 2.0)  # 170E .. 168W: the grid crosses the antimeridian


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    da = xr.DataArray(rng.normal(size=(12, LAT.size, LON.size)).astype(np.float32),
                      dims=("time", "lat", "lon"),
                      coords={"time": pd.date_range("2000", periods=12, freq="MS"),
                              "lat": LAT, "lon": LON})
    model = GLRM(3, random_state=0, progress=False).fit(da)
    plan = plan_greedy(model.Y_, model.region_, (0.0, 176.0), 14.0, progress=False)
    fleet = plan_greedy(model.Y_, model.region_, [(0.0, 176.0), (4.0, 186.0)], 8.0,
                        progress=False)
    return model, plan, fleet


# ------------------------------------------------------------------------ the antimeridian
def _unwrapped(lon):
    """Brute force: the polyline in unwrapped longitudes, each leg the short way round."""
    lon = np.asarray(lon, float)
    unwrapped = [lon[0]]
    for a, b in zip(lon[:-1], lon[1:], strict=True):
        d = (b - a + 180.0) % 360.0 - 180.0
        unwrapped.append(unwrapped[-1] + d)
    return np.asarray(unwrapped)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.floats(-400, 400), st.floats(-80, 80)), min_size=1, max_size=12))
@example([(1.202523279395976, 0.0), (334.0, 0.0), (180.0, 0.0)])  # ends on the line, up to
def test_split_antimeridian_against_brute_force(points):  # the unwrapping's rounding
    lon = np.array([p[0] for p in points])
    lat = np.array([p[1] for p in points])
    # a leg of exactly 180 degrees has no shorter way round: either direction is right
    assume(np.all(np.abs(np.abs(wrap_lon(np.diff(lon))) - 180.0) > 1e-6))
    pieces = split_antimeridian(lon, lat)
    flat = [p for piece in pieces for p in piece]
    assert all(-180.0 <= x <= 180.0 for x, _ in flat)
    for piece in pieces:  # no leg inside a piece jumps across the map
        xs = np.array([x for x, _ in piece])
        assert np.all(np.abs(np.diff(xs)) <= 180.0 + 1e-9)
    # the original points, wrapped, in order; only crossing points (at +-180) are added
    wrapped = np.column_stack([wrap_lon(lon), lat])
    kept = [p for p in flat if abs(abs(p[0]) - 180.0) > 1e-9]
    expect = [list(p) for p in wrapped if abs(abs(p[0]) - 180.0) > 1e-9]
    assert (np.allclose(kept, expect) if expect else not kept)
    # one cut per change of side of the brute-force unwrapped polyline, a point on the
    # antimeridian being on its neighbour's side (the previous point's; the first: the next's)
    unwrapped = np.round(_unwrapped(lon), 9)  # a point on the antimeridian up to rounding
    side = np.floor((unwrapped + 180.0) / 360.0)
    on = np.mod(unwrapped + 180.0, 360.0) == 0
    for i in [*range(1, side.size), 0]:
        if on[i] and side.size > 1:
            neighbour = side[i - 1] if i else side[1]
            side[i] = neighbour if neighbour in (side[i] - 1, side[i]) else side[i]
    n_cross = int(np.count_nonzero(np.diff(side)))
    assert len(pieces) == 1 + n_cross
    for piece in pieces:  # each piece on its side: only its ends may lie on the meridian
        assert len(piece) >= 2 or len(pieces) == 1
        inner = np.array([x for x, _ in piece])
        off = inner[np.abs(inner) < 180.0]
        assert np.all(off >= 0) or np.all(off <= 0) or np.all(np.abs(np.diff(off)) <= 180.0)
    for a, b in zip(pieces[:-1], pieces[1:], strict=True):  # cut exactly on the meridian
        assert abs(a[-1][0]) == 180.0 and b[0][0] == -a[-1][0] and b[0][1] == a[-1][1]


@pytest.mark.parametrize("lon, lat, expect", [
    # through a point on the meridian: one cut there, no zero-length piece
    ([170.0, 180.0, 190.0], [0.0, 1, 2],
     [[[170.0, 0.0], [180.0, 1.0]], [[-180.0, 1.0], [-170.0, 2.0]]]),
    # touching the meridian and turning back: not cut, the touch point on the line's side
    ([170.0, 180.0, 170.0], [0.0, 1, 2], [[[170.0, 0.0], [180.0, 1.0], [170.0, 2.0]]]),
    ([-170.0, 180.0, -160.0], [0.0, 1, 2], [[[-170.0, 0.0], [-180.0, 1.0], [-160.0, 2.0]]]),
    # starting or ending on it: on the side the line goes to or comes from
    ([180.0, 170.0], [0.0, 1], [[[180.0, 0.0], [170.0, 1.0]]]),
    ([180.0, 190.0], [0.0, 1], [[[-180.0, 0.0], [-170.0, 1.0]]]),
    ([170.0, 180.0], [0.0, 1], [[[170.0, 0.0], [180.0, 1.0]]]),
])
def test_split_at_a_point_on_the_antimeridian(lon, lat, expect):
    assert split_antimeridian(lon, lat) == expect


def test_split_crossing_latitude_is_interpolated():
    pieces = split_antimeridian([170.0, 190.0], [0.0, 10.0])
    assert pieces == [[[170.0, 0.0], [180.0, 5.0]], [[-180.0, 5.0], [-170.0, 10.0]]]
    pieces = split_antimeridian([-175.0, 175.0], [4.0, 0.0])  # westward
    assert pieces == [[[-175.0, 4.0], [-180.0, 2.0]], [[180.0, 2.0], [175.0, 0.0]]]


@pytest.mark.parametrize("which", ["plan", "fleet", (0.0, 180.0), (0.0, 182.0)])
def test_geojson_wraps_longitudes_and_splits_the_route(setup, which):
    model, plan, fleet = setup
    plan = {"plan": plan, "fleet": fleet}.get(which) if isinstance(which, str) else \
        plan_greedy(model.Y_, model.region_, which, 8.0, progress=False)
    doc = plan.to_geojson()
    for r in range(plan.n_robots):
        route = doc["features"][r]["geometry"]
        sel = plan.route_robot == r
        lons = np.asarray(plan.lon[sel])  # continuous on this grid: east of 180 is across
        crosses = bool(np.any(lons > 180) and np.any(lons < 180))
        assert route["type"] == ("MultiLineString" if crosses else "LineString")
        if not crosses:  # touching the meridian is no crossing: the route as flown
            np.testing.assert_array_equal(route["coordinates"], np.column_stack(
                [np.where(lons == 180, 180 if np.all(lons <= 180) else -180, wrap_lon(lons)),
                 plan.lat[sel]]))
            continue
        pieces = route["coordinates"]
        for piece in pieces:  # each piece on one side, its cut ends exactly on the meridian
            xs = np.array([x for x, _ in piece])
            assert len(piece) >= 2 and (np.all(xs >= 0) or np.all(xs <= 0))
        for a, b in zip(pieces[:-1], pieces[1:], strict=True):
            assert abs(a[-1][0]) == 180 and b[0] == [-a[-1][0], a[-1][1]]
    points = [f["geometry"]["coordinates"] for f in doc["features"][plan.n_robots:]]
    assert all(-180 <= x < 180 for x, _ in points)
    json.dumps(doc)


# ------------------------------------------------------------------------ mission files
def test_qgc_plan_passes_the_ground_station_checks(setup, tmp_path):
    _, plan, _ = setup
    path = plan.to_mission(tmp_path / "route.plan")
    doc = json.loads(path.read_text())
    assert doc["fileType"] == "Plan" and doc["version"] == 1
    mission = doc["mission"]
    assert mission["version"] == 2
    items = mission["items"]
    pts = route_points(plan)
    assert len(items) == pts["lat"].size and all(i["command"] == 16 for i in items)
    assert [i["doJumpId"] for i in items] == list(range(1, len(items) + 1))
    np.testing.assert_allclose([i["params"][4] for i in items], pts["lat"])
    np.testing.assert_allclose([i["params"][5] for i in items], pts["lon"])
    assert all(i["params"][6] == DEFAULT_ALTITUDE and i["frame"] == 3 for i in items)
    home = mission["plannedHomePosition"]
    assert home[:2] == [pts["lat"][0], pts["lon"][0]] and len(home) == 3
    assert all(-180 <= i["params"][5] < 180 for i in items)
    # a speed: a DO_CHANGE_SPEED first
    items = to_qgc_plan(plan, altitude=80, speed=12.5)["mission"]["items"]
    assert items[0]["command"] == 178 and items[0]["params"][1] == 12.5
    assert items[1]["params"][6] == 80


def test_mavlink_waypoints_read_back_with_pymavlink(setup, tmp_path):
    from pymavlink import mavwp

    _, _, fleet = setup
    path = fleet.to_mission(tmp_path / "robot1.waypoints", robot=1, altitude=30)
    assert path.read_text().startswith("QGC WPL 110")
    loader = mavwp.MAVWPLoader()
    n = loader.load(str(path))
    pts = route_points(fleet, 1)
    assert n == pts["lat"].size + 1  # home, then the route
    items = [loader.wp(i) for i in range(n)]
    assert items[0].frame == 0 and items[0].current == 1
    np.testing.assert_allclose([w.x for w in items[1:]], pts["lat"], atol=1e-6)
    np.testing.assert_allclose([w.y for w in items[1:]], pts["lon"], atol=1e-6)
    assert all(w.command == 16 and w.z == 30 and w.frame == 3 for w in items[1:])


def test_gpx_reads_back_with_gpxpy(setup, tmp_path):
    import gpxpy

    _, _, fleet = setup
    path = fleet.to_mission(tmp_path / "fleet.gpx")
    gpx = gpxpy.parse(path.read_text())
    assert len(gpx.routes) == fleet.n_robots
    for r, route in enumerate(gpx.routes):
        pts = route_points(fleet, r)
        np.testing.assert_allclose([p.latitude for p in route.points], pts["lat"])
        np.testing.assert_allclose([p.longitude for p in route.points], pts["lon"])
    n_stops = sum(int(route_points(fleet, r)["stop"].sum()) for r in range(fleet.n_robots))
    assert len(gpx.waypoints) == n_stops and n_stops >= len(fleet.cells) - 2


def test_kml_lines_and_placemarks(setup, tmp_path):
    _, plan, _ = setup
    path = plan.to_mission(tmp_path / "route.kml", altitude=20)
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    root = ET.parse(path).getroot()
    lines = root.findall(".//k:LineString/k:coordinates", ns)
    coords = [tuple(map(float, c.split(","))) for line in lines for c in line.text.split()]
    pieces = split_antimeridian(route_points(plan)["lon"], route_points(plan)["lat"])
    assert len(lines) == len(pieces)
    np.testing.assert_allclose([c[:2] for c in coords], [p for piece in pieces for p in piece])
    assert all(c[2] == 20 for c in coords)
    placemarks = root.findall(".//k:Point", ns)
    assert len(placemarks) == int(route_points(plan)["stop"].sum())


def test_static_placement_has_its_own_columns(setup, tmp_path):
    model, _, _ = setup
    plan = place_sensors(model.Y_, model.region_, 6, progress=False)
    df = plan.to_dataframe()
    assert list(df.columns) == ["sensor", "cell", "lat", "lon", "gain"]
    assert df["sensor"].tolist() == list(range(6)) and df["cell"].tolist() == plan.stops.tolist()
    n_forced = 6 - plan.history["gain"].size  # the forced initial cells have no gain
    assert n_forced >= 0 and df["gain"].iloc[:n_forced].isna().all()
    np.testing.assert_allclose(df["gain"].iloc[n_forced:], plan.history["gain"])
    assert (df["lon"] >= -180).all() and (df["lon"] < 180).all()
    region: Region = model.region_
    np.testing.assert_allclose(df["lat"], region.cell_lat[plan.stops])
    pts = [f for f in plan.to_geojson()["features"]]
    assert [f["properties"]["sensor"] for f in pts] == list(range(6))
    with pytest.raises(PlanningError, match="static placement has no route"):
        plan.to_mission(tmp_path / "s.plan")


@pytest.mark.parametrize("kwargs, needle", [
    ({"altitude": -5}, "altitude"), ({"altitude": "50"}, "altitude"),
    ({"robot": 3}, "robot must be in"), ({"speed": 0}, "speed"),
])
def test_bad_mission_arguments(setup, tmp_path, kwargs, needle):
    _, _, fleet = setup
    with pytest.raises(PlanningError, match=needle):
        fleet.to_mission(tmp_path / "x.plan", **kwargs)
    with pytest.raises(PlanningError, match="must end in"):
        fleet.to_mission(tmp_path / "x.txt")
    assert list(tmp_path.iterdir()) == []


def test_cli_writes_a_mission_and_states_the_default_altitude(setup, tmp_path, capsys):
    model, _, _ = setup
    model.save(tmp_path / "m.nc")
    code = main(["-q", "plan", str(tmp_path / "m.nc"), "--start", "0,176", "--budget", "10",
                 "-o", str(tmp_path / "r.plan")])
    out = capsys.readouterr().out
    assert code == 0 and "50 m above home (the default" in out
    assert json.loads((tmp_path / "r.plan").read_text())["mission"]["items"]
    code = main(["-q", "place", str(tmp_path / "m.nc"), "--sensors", "3", "--criterion",
                 "fisher", "-o", str(tmp_path / "s.plan")])
    assert code == 2 and "-o must end in .csv" in capsys.readouterr().err
