"""Sensors that see more than a point: footprints and towed sensors.

A sensor turns a sampling stop into **one** observation, a weighted average ``a^T d`` of the
values ``d`` of the cells it covers (``a >= 0`` over those cells, summing to 1):

* ``"point"`` (default, the paper's): the stop's own cell, ``a = e_stop``;
* ``"square"`` / ``"disc"``: every valid cell whose centre lies in the square (side ``width_km``,
  north-south / east-west on the local tangent plane of the stop) or the disc (diameter
  ``width_km``, great-circle) centred on the stop's cell centre, equal weights; the stop's own
  cell is always covered. ``width_km = size_km + 2 altitude_km tan(fov_deg / 2)`` (a camera at
  altitude ``altitude_km`` with full field of view ``fov_deg`` sees that much more);
* ``"leg-average"`` (a towed sensor): the observation at a stop is the mean of the distinct
  cells the leg arriving there passes (both ends included; the start's is its own cell).

Under the low-rank model ``d_j = y_j^T x + e_j`` an averaged observation is
``a^T d = (Y a)^T x + a^T e``: one row ``Y a`` (``k``) with noise variance
``sum_j a_j^2 sigma_j^2`` (independent cell errors; two observations have independent errors
even when their footprints overlap, as repeated point measurements do), and with the GP
residual ``r`` its residual covariance with another observation ``b`` is ``a^T K b``. Every
criterion (:func:`lrm_cvx.information.make_row_oracle`), the fold-in
(:meth:`lrm_cvx.belief.posterior.LatentPosterior.update_rows`) and the monitoring filter
(:meth:`lrm_cvx.belief.filter.LatentFilter.assimilate_rows`) read these rows: a sparse
``(n, L)`` matrix (:func:`footprint_matrix`, :func:`leg_matrix`, :func:`observation_rows`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sps
from scipy.spatial import cKDTree

from .._validation import check_positive
from ..belief.averaged import ERRORS
from ..errors import PlanningError
from ..oracles import whitened_rows
from ..region import EARTH_RADIUS_KM, Region
from ..registry import Registry

__all__ = ["Sensor", "SENSOR_REGISTRY", "SENSOR_KINDS", "POINT", "footprint_matrix",
           "footprint_factors", "leg_matrix", "observation_rows", "observe", "observed_cells",
           "plan_observations"]

SENSOR_REGISTRY = Registry("sensor", PlanningError)
"""Sensor kinds (entries: whether the kind has a footprint size)."""
SENSOR_REGISTRY.register("point", False, description="the stop's own cell (the paper)")
SENSOR_REGISTRY.register("square", True, description="mean of the cells in a square of side "
                         "width_km centred on the stop", aliases=("box",))
SENSOR_REGISTRY.register("disc", True, description="mean of the cells within a disc of diameter "
                         "width_km centred on the stop", aliases=("disk", "circle"))
SENSOR_REGISTRY.register("leg-average", False, description="a towed sensor: mean of the cells "
                         "the leg arriving at each stop passes", aliases=("leg", "towed",
                                                                           "leg_average"))
SENSOR_KINDS: tuple[str, ...] = SENSOR_REGISTRY.choices()
"""Canonical sensor kinds."""

_TOL_KM = 1e-9  # a cell centre exactly on the footprint's edge is covered


@dataclass(frozen=True)
class Sensor:
    """What one sampling stop observes (see the module docstring); validated.

    ``kind``: ``"point"``, ``"square"``, ``"disc"`` or ``"leg-average"`` (aliases accepted);
    ``size_km`` (>= 0): the footprint's width at altitude 0 (square side, disc diameter);
    ``altitude_km`` (>= 0) and ``fov_deg`` (full field of view, in (0, 180)): the width grows
    by ``2 altitude_km tan(fov_deg / 2)``. A square or disc needs a width > 0. ``errors``: how
    the cell errors inside one observation relate, ``"independent"`` (the model's assumption:
    an ``n``-cell average has ``1 / n`` of the noise variance) or ``"shared"`` (the average
    keeps the cells' noise: a conservative rule when the model's residuals are spatially
    correlated and no GP residual was fitted); not for a point.

    >>> Sensor("disc", size_km=5).width_km
    5.0
    >>> round(Sensor("square", altitude_km=0.1, fov_deg=90).width_km, 6)
    0.2
    """

    kind: str = "point"
    size_km: float = 0.0
    altitude_km: float = 0.0
    fov_deg: float | None = None
    errors: str = "independent"

    def __post_init__(self) -> None:
        kind = SENSOR_REGISTRY.canonical(self.kind, "sensor")
        size = check_positive(self.size_km, "size_km (km)", error=PlanningError,
                              numbers_only=True)
        alt = check_positive(self.altitude_km, "altitude_km (km)", error=PlanningError,
                             numbers_only=True)
        fov = self.fov_deg
        if fov is not None:
            fov = check_positive(fov, "fov_deg (degrees)", error=PlanningError,
                                 numbers_only=True)
            if not 0 < fov < 180:
                raise PlanningError(f"fov_deg must be in (0, 180) degrees, got {self.fov_deg!r}")
        if alt > 0 and fov is None:
            raise PlanningError("altitude_km needs fov_deg (the field of view that makes the "
                                "footprint grow with altitude)")
        if self.errors not in ERRORS:
            raise PlanningError(f"errors must be one of {list(ERRORS)}, got {self.errors!r}")
        if kind == "point" and self.errors != "independent":
            raise PlanningError("errors applies to footprints and leg-average, not a point")
        sized = SENSOR_REGISTRY.get(kind)
        if not sized and (size > 0 or alt > 0 or fov is not None):
            raise PlanningError(f"sensor {kind!r} has no footprint: size_km, altitude_km and "
                                "fov_deg apply to 'square' and 'disc'")
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "size_km", size)
        object.__setattr__(self, "altitude_km", alt)
        object.__setattr__(self, "fov_deg", fov)
        if sized and not self.width_km > 0:
            raise PlanningError(f"a {kind} sensor needs a footprint width > 0: give size_km "
                                "(km) or altitude_km with fov_deg")

    # ------------------------------------------------------------------ reading
    @property
    def width_km(self) -> float:
        """The footprint's width in km (0 for point and leg-average)."""
        grow = (2.0 * self.altitude_km * math.tan(math.radians(self.fov_deg) / 2.0)
                if self.fov_deg is not None else 0.0)
        return float(self.size_km + grow)

    @property
    def is_point(self) -> bool:
        return self.kind == "point"

    @property
    def has_footprint(self) -> bool:
        """A square or disc (each stop's observation is fixed by the stop alone)."""
        return self.kind in ("square", "disc")

    @property
    def is_leg(self) -> bool:
        return self.kind == "leg-average"

    def describe(self) -> str:
        """``"point"``, ``"disc 5 km"``, ``"leg-average"``..."""
        text = f"{self.kind} {self.width_km:g} km" if self.has_footprint else self.kind
        return text + (", shared errors" if self.errors == "shared" else "")

    def spec(self) -> str:
        """The text :meth:`parse` reads back into this sensor (files, the CLI)."""
        text = self.kind
        if self.has_footprint:
            text += f":{self.size_km!r}km"
            if self.fov_deg is not None:
                text += f",altitude={self.altitude_km!r}km,fov={self.fov_deg!r}"
        return text + (",errors=shared" if self.errors == "shared" else "")

    # ------------------------------------------------------------------ construction
    @classmethod
    def of(cls, value: Any) -> Sensor:
        """``value`` as a Sensor: None (point), a Sensor, a mapping of its fields, or a string
        (:meth:`parse`)."""
        if value is None:
            return POINT
        if isinstance(value, Sensor):
            return value
        if isinstance(value, str):
            return cls.parse(value)
        if isinstance(value, dict):
            try:
                return cls(**value)
            except TypeError as err:
                raise PlanningError(f"sensor: {err}") from None
        raise PlanningError(f"sensor must be a Sensor, a string such as 'disc:5km' or None, "
                            f"got {type(value).__name__}")

    @classmethod
    def parse(cls, text: str) -> Sensor:
        """``"point"``, ``"leg-average"``, ``"disc:5km"``, ``"square:2"`` (km), optionally
        ``",altitude=0.1km,fov=60"`` (altitude in km, full field of view in degrees) and
        ``",errors=shared"``."""
        parts = [p.strip() for p in str(text).split(",")]
        head = parts[0].split(":", 1)
        fields: dict[str, Any] = {"kind": head[0].strip()}
        if len(head) == 2:
            fields["size_km"] = _number(head[1], "km", text)
        for part in parts[1:]:
            key, _, val = part.partition("=")
            key = key.strip().lower()
            if key in ("altitude", "alt", "altitude_km"):
                fields["altitude_km"] = _number(val, "km", text)
            elif key in ("fov", "fov_deg"):
                fields["fov_deg"] = _number(val, "deg", text)
            elif key == "errors":
                fields["errors"] = val.strip().lower()
            else:
                raise PlanningError(f"sensor {text!r}: unknown option {key!r} (use "
                                    "KIND[:SIZEkm][,altitude=KM,fov=DEG][,errors=shared])")
        return cls(**fields)


POINT = Sensor()
"""The paper's point sensor."""


def _number(text: str, unit: str, whole: str) -> float:
    """``"5km"`` / ``"5"`` -> 5.0 (the check of the value is the Sensor's)."""
    m = re.fullmatch(rf"\s*([-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?)\s*(?:{unit})?\s*", str(text))
    if m is None:
        raise PlanningError(f"sensor {whole!r}: {text!r} is not a number of {unit}")
    try:
        return float(m.group(1))
    except ValueError:
        raise PlanningError(f"sensor {whole!r}: {text!r} is not a number of {unit}") from None


# ------------------------------------------------------------------------------ footprints
def _xyz(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Points on the sphere of radius ``EARTH_RADIUS_KM`` (chord = straight-line km)."""
    la, lo = np.radians(lat), np.radians(lon)
    c = np.cos(la)
    return EARTH_RADIUS_KM * np.column_stack([c * np.cos(lo), c * np.sin(lo), np.sin(la)])


def footprint_matrix(region: Region, sensor: Any, cells: Any = None, *, lat: Any = None,
                     lon: Any = None) -> sps.csr_matrix:
    """The averaging rows of footprints: ``(n, L)`` CSR float64, row ``i`` the equal weights
    (summing to 1) of the valid cells ``sensor`` covers when centred on ``cells[i]`` (cell
    indices; default every cell) or on the points ``lat[i], lon[i]`` (degrees).

    A point sensor gives one-hot rows (a point at ``lat, lon`` covers its nearest cell); a
    leg-average sensor has no footprint (:func:`leg_matrix`). Vectorised: one KD-tree query of
    the cells' 3-D positions, then the exact square / disc test. PlanningError for a
    footprint (given by ``lat, lon``) that covers no valid cell.
    """
    sensor = Sensor.of(sensor)
    if sensor.is_leg:
        raise PlanningError("a leg-average sensor has no footprint: its rows come from the "
                            "route (leg_matrix / observation_rows)")
    L = region.n_cells
    clat, clon = np.asarray(region.cell_lat, float), np.asarray(region.cell_lon, float)
    if lat is not None or lon is not None:
        if cells is not None:
            raise PlanningError("give cells or lat/lon, not both")
        plat = np.atleast_1d(np.asarray(lat, dtype=np.float64))
        plon = np.atleast_1d(np.asarray(lon, dtype=np.float64))
        if plat.shape != plon.shape or plat.ndim != 1 or not np.all(np.isfinite(plat)) \
                or not np.all(np.isfinite(plon)):
            raise PlanningError("lat and lon must be finite 1-D arrays of the same length")
        own = None
    else:
        own = (np.arange(L, dtype=np.int64) if cells is None
               else np.atleast_1d(np.asarray(region.check_cells(cells, "cells"), np.int64)))
        plat, plon = clat[own], clon[own]
    n = plat.size
    if sensor.is_point:
        if own is None:
            own = np.asarray(cKDTree(_xyz(clat, clon)).query(_xyz(plat, plon))[1], np.int64)
        return sps.csr_matrix((np.ones(n), (np.arange(n), own)), shape=(n, L))
    half = 0.5 * sensor.width_km
    radius = half if sensor.kind == "disc" else half * math.sqrt(2.0)
    chord = 2.0 * EARTH_RADIUS_KM * math.sin(min(radius / (2.0 * EARTH_RADIUS_KM), math.pi / 2))
    pairs = cKDTree(_xyz(plat, plon)).sparse_distance_matrix(
        cKDTree(_xyz(clat, clon)), chord * (1 + 1e-12) + _TOL_KM, output_type="ndarray")
    i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    if sensor.kind == "disc":
        d = 2.0 * EARTH_RADIUS_KM * np.arcsin(np.clip(pairs["v"] / (2 * EARTH_RADIUS_KM), 0, 1))
        keep = d <= half + _TOL_KM
    else:  # the local tangent plane of the centre: north-south and east-west km
        dy = EARTH_RADIUS_KM * np.radians(clat[j] - plat[i])
        dlon = (clon[j] - plon[i] + 180.0) % 360.0 - 180.0
        dx = EARTH_RADIUS_KM * np.cos(np.radians(plat[i])) * np.radians(dlon)
        keep = (np.abs(dx) <= half + _TOL_KM) & (np.abs(dy) <= half + _TOL_KM)
    i, j = i[keep], j[keep]
    if own is not None:  # the stop's own cell is always covered
        i, j = np.concatenate([i, np.arange(n)]), np.concatenate([j, own])
    A = sps.csr_matrix((np.ones(i.size), (i, j)), shape=(n, L))
    A.data[:] = 1.0  # a pair listed twice counts once
    count = np.diff(A.indptr)
    if np.any(count == 0):
        bad = int(np.flatnonzero(count == 0)[0])
        raise PlanningError(f"the {sensor.describe()} footprint at (lat {plat[bad]:g}, lon "
                            f"{plon[bad]:g}) covers no valid cell of the region")
    A.data /= np.repeat(count, count).astype(np.float64)
    return A


def footprint_factors(Y: Any, region: Region, sensor: Any, noise_var: Any = None,
                      cells: Any = None) -> np.ndarray:
    """The whitened footprint rows ``(k, n)`` of ``cells`` (default every cell, ``n = L``):
    column ``i`` is ``Y a_c / sqrt(v_c)`` for ``c = cells[i]``, ``a_c`` the footprint of
    ``sensor`` centred on cell ``c`` (:func:`footprint_matrix`) and ``v_c`` its noise variance
    from cell errors ``noise_var`` (default 1) and the sensor's ``errors``
    (:func:`~lrm_cvx.oracles.whitened_rows`). A footprint plan's Fisher information is ``log
    det(ridge I + sum_{stops} u u^T)`` of these columns: what the point certificate bounds for
    ``Y``'s (planning/certificate.py, which asks only for the cells a plan may visit: the
    footprint matrix holds ``n x footprint`` entries: 18 million for every cell of the
    paper's 2M-cell grid under a disc three cells wide, 1.1 million for a budget of 200)."""
    sensor = Sensor.of(sensor)
    if not sensor.has_footprint:
        raise PlanningError(f"footprint_factors needs a square or disc sensor, got "
                            f"{sensor.describe()!r}")
    return whitened_rows(Y, footprint_matrix(region, sensor, cells), noise_var, sensor.errors)


def leg_matrix(route: Any, waypoint: Any, route_robot: Any, n_cells: int) -> sps.csr_matrix:
    """The rows of a towed sensor: one per sampling stop (``waypoint`` entries of ``route``, in
    route order), the equal weights of the distinct cells of the leg arriving there (the
    previous stop, the cells passed, the stop); a robot's first stop (its start) is its own
    cell. ``route``, ``waypoint``, ``route_robot``: ``(r,)`` per route entry (robots'
    routes contiguous, each starting at a stop, as :class:`~lrm_cvx.planning.plan.Plan`
    holds them). Returns ``(n_stops, n_cells)`` CSR."""
    route = np.asarray(route, dtype=np.int64).ravel()
    way = np.asarray(waypoint, dtype=bool).ravel()
    rob = np.asarray(route_robot, dtype=np.int64).ravel()
    if not (route.shape == way.shape == rob.shape):
        raise PlanningError("route, waypoint and route_robot must have the same length")
    if route.size == 0:
        return sps.csr_matrix((0, n_cells))
    first = np.r_[True, rob[1:] != rob[:-1]]
    if not np.all(way[first]):
        raise PlanningError("every robot's route must start at a sampling stop")
    count = np.cumsum(way)  # stops at or before each entry
    leg = np.where(way, count - 1, count)  # a pass-through cell: the leg of the next stop
    r = route.size
    nxt = np.minimum.accumulate(np.where(way, np.arange(r), r)[::-1])[::-1]  # next stop
    own = (nxt < r) & (rob[np.minimum(nxt, r - 1)] == rob)  # ... of the same robot
    after = np.r_[nxt[1:], r]  # the next stop strictly after each entry
    starts_next = way & (after < r) & (rob[np.minimum(after, r - 1)] == rob)  # a stop also
    # starts the next leg of its robot
    rows = np.concatenate([leg, count[starts_next]])
    cols = np.concatenate([route, route[starts_next]])
    n = int(count[-1])
    ok = np.concatenate([own, np.ones(int(starts_next.sum()), bool)])  # cells after a
    # robot's last stop belong to no leg
    A = sps.csr_matrix((np.ones(int(ok.sum())), (rows[ok], cols[ok])), shape=(n, n_cells))
    A.data[:] = 1.0
    cnt = np.diff(A.indptr)
    A.data /= np.repeat(cnt, cnt).astype(np.float64)
    return A


def observation_rows(plan: Any) -> sps.csr_matrix:
    """The rows a plan's sensor observes (``(n, L)`` CSR, each summing to 1): point sensors
    one-hot rows of ``plan.cells``, footprints one row per cell of ``plan.cells`` (its stops,
    and with ``sense_along`` the cells passed), a towed sensor one per stop
    (:func:`leg_matrix` of the plan's route)."""
    region = plan._region
    if region is None:
        raise PlanningError("the plan has no region (build it with Plan.build)")
    sensor = plan.sensor
    if sensor.is_leg:
        return leg_matrix(plan.route, plan.waypoint, plan.route_robot, region.n_cells)
    cells = np.asarray(plan.cells, dtype=np.int64)
    return footprint_matrix(region, sensor, cells)


def observe(truth: Any, rows: Any) -> tuple[sps.csr_matrix, np.ndarray]:
    """What the sensor reads of the field ``truth`` (``(L,)``, NaN where not observable):
    ``(rows, values)`` with each row re-weighted over its observable cells (weights still
    summing to 1) and ``values = rows @ truth``; a row none of whose cells is observable
    reads NaN (the fold-in drops it)."""
    t = np.asarray(truth, dtype=np.float64).ravel()
    A = sps.csr_matrix(rows, dtype=np.float64)
    if A.shape[1] != t.size:
        raise PlanningError(f"truth has {t.size} cells, the rows {A.shape[1]}")
    ok = np.isfinite(t)
    A = A.multiply(ok[None, :]).tocsr() if not ok.all() else A.copy()
    A.eliminate_zeros()
    s = np.asarray(A.sum(axis=1)).ravel()
    cnt = np.diff(A.indptr)
    A.data /= np.repeat(np.where(s > 0, s, 1.0), cnt)
    values = A @ np.where(ok, t, 0.0)
    values[s <= 0] = np.nan
    return A, values


def observed_cells(rows: Any) -> np.ndarray:
    """The distinct cells the rows touch (sorted int64): what the sensor saw."""
    A = sps.csr_matrix(rows)
    return np.unique(A.indices[A.data != 0]).astype(np.int64)


def plan_observations(plan: Any, truth: Any) -> tuple[sps.csr_matrix, np.ndarray]:
    """What ``plan``'s sensor reads of the snapshot ``truth`` (``(L,)``, the region's cells,
    NaN where not observable): ``(rows, values)``, one averaged value per observation
    (:func:`observation_rows` re-weighted by :func:`observe`). A campaign assimilates them
    with ``state.assimilate_rows(rows, values, time, errors=plan.sensor.errors)``;
    ``observed_cells(rows)`` are the cells seen."""
    return observe(truth, observation_rows(plan))
