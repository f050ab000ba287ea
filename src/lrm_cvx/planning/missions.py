"""A plan as files that robots, ground stations and GIS tools load.

GeoJSON, QGroundControl ``.plan``, MAVLink waypoint text, GPX 1.1 and KML; every route point is
exported and ``stop`` marks where the robot samples. Formats, the antimeridian and
:data:`DEFAULT_ALTITUDE` are described in docs/planning.md.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import atomic_output, check_positive
from ..errors import PlanningError

__all__ = ["DEFAULT_ALTITUDE", "MISSION_SUFFIXES", "wrap_lon", "split_antimeridian",
           "route_points", "plan_geojson", "to_qgc_plan", "to_mavlink_wpl", "to_gpx", "to_kml",
           "write_mission", "sensors_dataframe"]

DEFAULT_ALTITUDE = 50.0
"""Metres above the home position (MAVLink ``MAV_FRAME_GLOBAL_RELATIVE_ALT``) when a mission
export is given no altitude."""

MISSION_SUFFIXES = {".plan": "qgc", ".waypoints": "wpl", ".gpx": "gpx", ".kml": "kml"}
"""File suffix -> mission format of :func:`write_mission`."""

_NAV_WAYPOINT = 16
_DO_CHANGE_SPEED = 178
_FRAME_GLOBAL = 0
_FRAME_RELATIVE_ALT = 3


def wrap_lon(lon: Any) -> np.ndarray:
    """Longitudes in [-180, 180) (RFC 7946), from any convention (0..360, -180..180, ...)."""
    return (np.asarray(lon, dtype=np.float64) + 180.0) % 360.0 - 180.0


def split_antimeridian(lon: Any, lat: Any) -> list[list[list[float]]]:
    """A polyline as pieces of ``[lon, lat]`` points in [-180, 180], cut where it crosses the
    antimeridian, as RFC 7946 section 3.1.9 asks of a GeoJSON line that crosses it.

    Each leg goes the shorter way round (as a robot flies it). Where a leg crosses, the
    crossing latitude is interpolated linearly in (lon, lat) and the cut lies exactly on the
    meridian: the piece ends at ``[180, lat]`` (or ``[-180, lat]`` going west) and the next one
    starts at the same point on the other side, ``[-180, lat]`` (``[180, lat]``). Every other
    point of a piece lies strictly on that piece's side. A point exactly on the antimeridian is
    written on the side the line comes from (points the line starts with: the side it goes
    to), so no piece is a lone point or a line along the meridian, and a line that touches the
    meridian and turns back is not cut.
    """
    lon, lat = wrap_lon(lon), np.asarray(lat, dtype=np.float64)
    if lon.size == 0:
        return []
    pieces = [[[float(lon[0]), float(lat[0])]]]
    for i in range(1, lon.size):  # a loop over route points, never over the region's cells
        x, y = pieces[-1][-1]
        d = lon[i] - x
        b = float(lon[i] - 360.0 * np.sign(d)) if abs(d) > 180.0 else float(lon[i])
        if -180.0 <= b <= 180.0:  # on this side (or on the meridian, written on this side)
            pieces[-1].append([b, float(lat[i])])
            continue
        edge = 180.0 if b > 180.0 else -180.0
        if all(px == edge for px, _ in pieces[-1]):  # it starts on the meridian: that side
            for point in pieces[-1]:
                point[0] = -edge
            pieces[-1].append([b - 2.0 * edge, float(lat[i])])
            continue
        crossing = float(y + (edge - x) / (b - x) * (lat[i] - y))
        if x != edge:
            pieces[-1].append([edge, crossing])
        pieces.append([[-edge, crossing], [b - 2.0 * edge, float(lat[i])]])
    return pieces


def route_points(plan: Any, robot: int = 0) -> dict[str, np.ndarray]:
    """Robot ``robot``'s route in flying order: ``lat``, ``lon`` (wrapped), ``cell``, ``stop``
    (True where it samples a stop of the plan), consecutive repeats dropped."""
    if plan.path.get("kind") == "static":
        raise PlanningError("a static placement has no route; export it as CSV or GeoJSON "
                            "(sensor positions)")
    if not 0 <= int(robot) < plan.n_robots:
        raise PlanningError(f"robot must be in [0, {plan.n_robots - 1}], got {robot!r}")
    sel = np.flatnonzero(plan.route_robot == int(robot))
    if sel.size:
        keep = np.r_[True, plan.route[sel][1:] != plan.route[sel][:-1]]
        sel = sel[keep]
    stops = plan.stops[plan.stop_robot == int(robot)]
    cells = plan.route[sel]
    return {"lat": np.asarray(plan.lat[sel], dtype=np.float64), "lon": wrap_lon(plan.lon[sel]),
            "cell": cells, "stop": plan.waypoint[sel] & np.isin(cells, stops)}


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _path_json(plan: Any) -> dict[str, Any]:
    return {k: v for k, v in plan.path.items()}


def plan_geojson(plan: Any) -> dict[str, Any]:
    """The GeoJSON FeatureCollection of :meth:`Plan.to_geojson` (see there), longitudes wrapped
    to [-180, 180) and routes split at the antimeridian."""
    lon, lat = wrap_lon(plan.lon), np.asarray(plan.lat, dtype=np.float64)
    coords = [[float(lo), float(la)] for lo, la in zip(lon, lat, strict=True)]
    order = plan._order()
    static = plan.path.get("kind") == "static"
    budgets = plan.path.get("budgets") or [plan.budget]
    starts = set(int(s) for s in (plan.path.get("starts") or [plan.start]))
    features: list[dict[str, Any]] = []
    for r in range(0 if static else plan.n_robots):  # (fixed sensors: Points only)
        sel = np.flatnonzero(plan.route_robot == r)
        pieces = split_antimeridian(lon[sel], lat[sel])
        geometry = ({"type": "LineString", "coordinates": pieces[0] if pieces else []}
                    if len(pieces) <= 1 else {"type": "MultiLineString", "coordinates": pieces})
        features.append({
            "type": "Feature", "geometry": geometry,
            "properties": {"kind": "route", "robot": r,
                           "cost": float(plan.robot_costs[r]) if plan.robot_costs.size > r
                           else plan.cost,
                           "budget": float(budgets[r]) if len(budgets) > r else None},
        })
    sel_of: dict[tuple[int, int], int] = {}
    for i, (c, r) in enumerate(zip(plan.stops.tolist(), plan.stop_robot.tolist(), strict=True)):
        sel_of.setdefault((int(r), int(c)), i)
    first: dict[tuple[int, int], int] = {}
    for i, (c, r) in enumerate(zip(plan.route.tolist(), plan.route_robot.tolist(), strict=True)):
        if (r, c) in sel_of and bool(plan.waypoint[i]):
            first.setdefault((r, c), i)
    gains = _gains(plan) if static else {}
    for (_, c), i in first.items():
        props: dict[str, Any] = {"kind": "cell", "cell": c}
        if static:
            props |= {"kind": "sensor", "sensor": int(order[i]), "gain": gains.get(c)}
        else:
            props |= {"robot": int(plan.route_robot[i]), "order": int(order[i]),
                      "selection": sel_of.get((int(plan.route_robot[i]), c)),
                      "start": c in starts and int(order[i]) == 0}
        features.append({"type": "Feature",
                         "geometry": {"type": "Point", "coordinates": coords[i]},
                         "properties": props})
    return {
        "type": "FeatureCollection",
        "features": features,
        "properties": {
            "method": plan.method, "criterion": plan.criterion,
            "cost_function": plan.cost_function, "cost": _num(plan.cost),
            "budget": _num(plan.budget), "information": _num(plan.information),
            "ridge": plan.ridge, "start": plan.start, "n_cells": len(plan),
            "n_robots": plan.n_robots, "path": _path_json(plan),
        },
    }


def _gains(plan: Any) -> dict[int, float]:
    """Each placed sensor's greedy gain (from the plan's history), by cell."""
    hist = getattr(plan, "history", None) or {}
    cells, gain = hist.get("cell"), hist.get("gain")
    if cells is None or gain is None or len(cells) != len(gain):
        return {}
    return {int(c): float(g) for c, g in zip(np.asarray(cells), np.asarray(gain), strict=True)}


def sensors_dataframe(plan: Any) -> Any:
    """A static placement as one row per sensor: ``sensor`` (placement order), ``cell``,
    ``lat``, ``lon`` (wrapped to [-180, 180)), ``gain`` (the criterion's gain when it was placed;
    NaN when the plan has no history, e.g. after an exchange)."""
    import pandas as pd

    gains = _gains(plan)
    cells = np.asarray(plan.stops, dtype=np.int64)
    index = {int(c): i for i, c in enumerate(plan.route.tolist())}
    rows = [index[int(c)] for c in cells]
    return pd.DataFrame({
        "sensor": np.arange(cells.size, dtype=np.int64),
        "cell": cells,
        "lat": np.asarray(plan.lat[rows], dtype=np.float64),
        "lon": wrap_lon(plan.lon[rows]),
        "gain": np.array([gains.get(int(c), np.nan) for c in cells], dtype=np.float64),
    })


def _altitude(altitude: float | None) -> float:
    if altitude is None:
        return DEFAULT_ALTITUDE
    return check_positive(altitude, "altitude", error=PlanningError, numbers_only=True)


def _speed_mps(plan: Any, speed: float | None) -> float | None:
    """Cruise speed in m/s: ``speed`` (m/s) if given, else the path model's (km/h) if any."""
    if speed is not None:
        return check_positive(speed, "speed", strict=True, error=PlanningError,
                              numbers_only=True)
    kmh = plan.path.get("speed")
    return None if kmh is None else float(kmh) / 3.6


def to_qgc_plan(plan: Any, *, robot: int = 0, altitude: float | None = None,
                speed: float | None = None, home_altitude: float = 0.0,
                hold: float = 0.0) -> dict[str, Any]:
    """QGroundControl mission (``.plan`` JSON, mission version 2) of robot ``robot``'s route.

    Items: a ``DO_CHANGE_SPEED`` (178) when a speed is known (``speed`` m/s, else the path
    model's km/h), then one ``NAV_WAYPOINT`` (16) per route point at ``altitude`` m above home
    (frame 3; default :data:`DEFAULT_ALTITUDE`), ``hold`` seconds at each sampling stop. The
    route's first point (the start) is the ``plannedHomePosition`` at ``home_altitude`` m AMSL.
    """
    pts = route_points(plan, robot)
    alt = _altitude(altitude)
    mps = _speed_mps(plan, speed)
    hold = check_positive(hold, "hold", error=PlanningError, numbers_only=True)
    items: list[dict[str, Any]] = []

    def add(command: int, params: list[Any]) -> None:
        items.append({"type": "SimpleItem", "autoContinue": True, "command": command,
                      "doJumpId": len(items) + 1, "frame": _FRAME_RELATIVE_ALT
                      if command == _NAV_WAYPOINT else 2, "params": params,
                      **({"AMSLAltAboveTerrain": None, "Altitude": alt, "AltitudeMode": 1}
                         if command == _NAV_WAYPOINT else {})})

    if mps is not None:
        add(_DO_CHANGE_SPEED, [1, mps, -1, 0, 0, 0, 0])  # ground speed, throttle unchanged
    for la, lo, stop in zip(pts["lat"], pts["lon"], pts["stop"], strict=True):
        add(_NAV_WAYPOINT, [hold if stop else 0, 0, 0, None, float(la), float(lo), alt])
    home = [float(pts["lat"][0]), float(pts["lon"][0]), float(home_altitude)] if \
        pts["lat"].size else [0.0, 0.0, float(home_altitude)]
    return {
        "fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {"version": 2, "firmwareType": 0, "vehicleType": 0,
                    "cruiseSpeed": mps if mps is not None else 15,
                    "hoverSpeed": mps if mps is not None else 5,
                    "globalPlanAltitudeMode": 1,
                    "plannedHomePosition": home, "items": items},
    }


def _mavlink_items(plan: Any, robot: int, altitude: float | None, hold: float) -> list[Any]:
    from pymavlink import mavutil

    pts = route_points(plan, robot)
    alt = _altitude(altitude)
    hold = check_positive(hold, "hold", error=PlanningError, numbers_only=True)
    msg = mavutil.mavlink.MAVLink_mission_item_message
    if not pts["lat"].size:
        raise PlanningError("the plan's route is empty: nothing to export")
    # item 0 is the home position (absolute frame), as ground stations write it
    items = [msg(0, 0, 0, _FRAME_GLOBAL, _NAV_WAYPOINT, 1, 1, 0, 0, 0, 0,
                 float(pts["lat"][0]), float(pts["lon"][0]), 0.0)]
    for la, lo, stop in zip(pts["lat"], pts["lon"], pts["stop"], strict=True):
        items.append(msg(0, 0, len(items), _FRAME_RELATIVE_ALT, _NAV_WAYPOINT, 0, 1,
                         hold if stop else 0.0, 0, 0, 0, float(la), float(lo), alt))
    return items


def to_mavlink_wpl(plan: Any, path: str | os.PathLike, *, robot: int = 0,
                   altitude: float | None = None, hold: float = 0.0) -> Path:
    """Write robot ``robot``'s route as a MAVLink waypoint file (``QGC WPL 110``) with
    pymavlink's ``MAVWPLoader``: item 0 the home position (the start), then a ``NAV_WAYPOINT``
    per route point at ``altitude`` m above home. Atomic; returns the path."""
    from pymavlink import mavwp

    loader = mavwp.MAVWPLoader()
    for item in _mavlink_items(plan, robot, altitude, hold):
        loader.add(item)
    path = Path(path)
    with atomic_output(path) as tmp:
        loader.save(str(tmp))
    return path


def to_gpx(plan: Any, *, altitude: float | None = None) -> str:
    """GPX 1.1 text (gpxpy): one route per robot (every route point, ``rtept``), one waypoint
    per sampling stop (``wpt``, named ``robot R stop I``), elevations ``altitude`` m when
    given (GPX has no relative altitude: none by default)."""
    import gpxpy.gpx

    gpx = gpxpy.gpx.GPX()
    gpx.creator = "lrm-cvx"
    ele = None if altitude is None else _altitude(altitude)
    for r in range(plan.n_robots):
        pts = route_points(plan, r)
        route = gpxpy.gpx.GPXRoute(name=f"robot {r}")
        for i, (la, lo, stop) in enumerate(zip(pts["lat"], pts["lon"], pts["stop"],
                                               strict=True)):
            route.points.append(gpxpy.gpx.GPXRoutePoint(float(la), float(lo), elevation=ele,
                                                        name=f"{i}"))
            if stop:
                gpx.waypoints.append(gpxpy.gpx.GPXWaypoint(
                    float(la), float(lo), elevation=ele, name=f"robot {r} stop {i}",
                    comment=f"cell {int(pts['cell'][i])}"))
        gpx.routes.append(route)
    return gpx.to_xml(version="1.1")


def to_kml(plan: Any, *, altitude: float | None = None) -> str:
    """KML text (simplekml): a line per robot (a ``MultiGeometry`` of lines where the route
    crosses the antimeridian) and a placemark per sampling stop; ``altitude`` m above ground
    when given (``relativeToGround``), else clamped to the ground."""
    import simplekml

    kml = simplekml.Kml(name="lrm-cvx plan")
    alt = None if altitude is None else _altitude(altitude)
    mode = simplekml.AltitudeMode.relativetoground if alt is not None else \
        simplekml.AltitudeMode.clamptoground
    for r in range(plan.n_robots):
        pts = route_points(plan, r)
        pieces = split_antimeridian(pts["lon"], pts["lat"])
        z = 0.0 if alt is None else alt
        multi = kml.newmultigeometry(name=f"robot {r}")
        for piece in pieces:
            line = multi.newlinestring(coords=[(x, y, z) for x, y in piece])
            line.altitudemode = mode
        for i, (la, lo, stop) in enumerate(zip(pts["lat"], pts["lon"], pts["stop"],
                                               strict=True)):
            if stop:
                p = kml.newpoint(name=f"robot {r} stop {i}", coords=[(float(lo), float(la), z)])
                p.description = f"cell {int(pts['cell'][i])}"
                p.altitudemode = mode
    return kml.kml()


def write_mission(plan: Any, path: str | os.PathLike, *, robot: int = 0,
                  altitude: float | None = None, speed: float | None = None,
                  hold: float = 0.0) -> Path:
    """Write ``plan`` in the mission format of ``path``'s suffix (:data:`MISSION_SUFFIXES`:
    ``.plan`` QGroundControl, ``.waypoints`` MAVLink ``QGC WPL 110``, ``.gpx``, ``.kml``),
    atomically. ``robot`` picks a fleet's robot for the one-vehicle formats (QGC, MAVLink);
    GPX and KML hold every robot. Returns the path."""
    path = Path(path)
    kind = MISSION_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise PlanningError(f"mission file {path.name!r} must end in "
                            f"{', '.join(MISSION_SUFFIXES)}")
    if kind == "wpl":
        return to_mavlink_wpl(plan, path, robot=robot, altitude=altitude, hold=hold)
    if kind == "qgc":
        text = json.dumps(to_qgc_plan(plan, robot=robot, altitude=altitude, speed=speed,
                                      hold=hold), indent=2)
    elif kind == "gpx":
        text = to_gpx(plan, altitude=altitude)
    else:
        text = to_kml(plan, altitude=altitude)
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
