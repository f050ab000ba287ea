"""The path model: how a robot travels, what a route costs, exact incremental costs.

One :class:`PathModel` per robot (:func:`make_path_model`) answers the geometric questions of the
planners, the baselines, :class:`~lrm_cvx.planning.plan.Plan` and the certificate: the metric,
stop costs, straight lines or a travel graph, open paths, closed tours or routes to an ``end``.
The route-cost algorithms live in :mod:`lrm_cvx.planning.routecost`; docs/planning.md describes
the path options and why distances are exact.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np

from ..errors import PlanningError
from ..region import EARTH_RADIUS_KM, Region
from .request import METRICS, PATH_FIELDS, Fleet, PathOptions, check_amount, check_metric
from .routecost import (
    COST_REGISTRY,
    InsertionCost,
    MatrixRouteCost,
    NearestNeighborCost,
    nearest_neighbor_order,
)

__all__ = [
    "METRICS",
    "PathModel",
    "IncrementalCost",
    "make_path_model",
    "path_model",
    "travel_distance",
    "startable_cells",
    "TravelGeometry",
    "check_metric",
    "check_amount",
    "traversable_mask",
    "grid_wraps",
]


ELLIPSE_GRAPH = True
"""Routes to an ``end``: the travel graph holds only the cells ``x`` with ``d(start, x) +
d(x, end) <= travel budget`` (straight-line lower bounds), not the disk of radius travel around
the start. False uses the disk."""

_QUANTUM = 2.0 ** -20  # graph edge lengths are multiples of this (budget unit): exact sums
_TOL = 1e-9  # budget tolerance (as the greedy's)
_CODES = {"grid": 0, "km": 1, "h": 2}


# --------------------------------------------------------------------------- distances
@numba.njit(cache=True, nogil=True)
def _dist_pairs(code, ar, ac, br, bc, latr, lonr, coslat, speed):  # pragma: no cover
    """Straight-line distance of each pair (a_i, b_i) given by grid rows/cols, budget unit.

    ``code`` 0: Euclidean grid units; 1: haversine km; 2: haversine km / speed (hours).
    Symmetric by construction (absolute differences, commutative products).
    """
    n = ar.shape[0]
    out = np.empty(n, dtype=np.float64)
    for i in range(n):
        r1 = ar[i]
        r2 = br[i]
        if code == 0:
            dr = r1 - r2
            dc = ac[i] - bc[i]
            out[i] = math.sqrt(float(dr * dr + dc * dc))
        else:
            dphi = abs(latr[r2] - latr[r1])
            dlam = abs(lonr[bc[i]] - lonr[ac[i]])
            s1 = math.sin(0.5 * dphi)
            s2 = math.sin(0.5 * dlam)
            h = s1 * s1 + (coslat[r1] * coslat[r2]) * (s2 * s2)
            if h > 1.0:
                h = 1.0
            d = 2.0 * 6371.0088 * math.asin(math.sqrt(h))
            if code == 2:
                d = d / speed
            out[i] = d
    return out


class TravelGeometry:
    """Straight-line distances (budget unit) between cells or grid positions of ``region``
    under ``metric`` / ``speed`` (already checked, :func:`check_metric`): the per-region arrays
    of :func:`_dist_pairs` (radians, cosines), built once per model."""

    def __init__(self, region: Region, metric: str, speed: float | None) -> None:
        self.region = region
        self.code = _CODES["h" if speed is not None else metric]
        self.speed = float(speed) if speed is not None else 1.0
        self.latr = np.radians(np.asarray(region.lat.values, dtype=np.float64))
        self.lonr = np.radians(np.asarray(region.lon.values, dtype=np.float64))
        self.coslat = np.cos(self.latr)
        gi = region.grid_index
        self.rows = np.ascontiguousarray(gi[:, 0])
        self.cols = np.ascontiguousarray(gi[:, 1])
        if self.code and not region._sphere:
            raise PlanningError("metric='km' needs a grid in degrees (lat in [-90, 90])")

    def pairs(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Distances of the cell pairs ``(a_i, b_i)`` (equal-length int arrays)."""
        a = np.ascontiguousarray(a, dtype=np.int64)
        b = np.ascontiguousarray(b, dtype=np.int64)
        return _dist_pairs(self.code, self.rows[a], self.cols[a], self.rows[b], self.cols[b],
                           self.latr, self.lonr, self.coslat, self.speed)

    def position_pairs(self, ar: np.ndarray, ac: np.ndarray, br: np.ndarray,
                       bc: np.ndarray) -> np.ndarray:
        """Distances between grid positions ``(ar_i, ac_i)`` and ``(br_i, bc_i)`` (rows and
        columns inside the grid, valid cells or not; equal-length int arrays)."""
        return _dist_pairs(self.code, np.ascontiguousarray(ar, dtype=np.int64),
                           np.ascontiguousarray(ac, dtype=np.int64),
                           np.ascontiguousarray(br, dtype=np.int64),
                           np.ascontiguousarray(bc, dtype=np.int64),
                           self.latr, self.lonr, self.coslat, self.speed)

    def row(self, a: int, b: np.ndarray) -> np.ndarray:
        """Distances from cell ``a`` to every cell of ``b``."""
        b = np.asarray(b, dtype=np.int64)
        return self.pairs(np.full(b.size, int(a), dtype=np.int64), b)

    def matrix(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=np.int64)
        b = np.asarray(b, dtype=np.int64)
        return self.pairs(np.repeat(a, b.size), np.tile(b, a.size)).reshape(a.size, b.size)


def travel_distance(region: Region, a: Any, b: Any, metric: str = "grid",
                    speed: float | None = None) -> np.ndarray:
    """Straight-line travel distance between cells ``a`` and ``b`` (broadcast), budget unit.

    ``metric="grid"``: Euclidean distance between grid positions (grid units, the paper);
    ``"km"``: great-circle distance between cell centres (haversine, ``EARTH_RADIUS_KM``,
    longitude wraps); with ``speed`` (km/h, only with ``"km"``): hours ``km / speed``.
    Returns a float64 array of the broadcast shape (a 0-d array for two scalars).
    """
    metric, speed, _ = check_metric(metric, speed)
    a = region.check_cells(a, "a")
    b = region.check_cells(b, "b")
    try:
        a, b = np.broadcast_arrays(a, b)
    except ValueError as exc:
        raise PlanningError(f"a and b must broadcast: {exc}") from None
    geo = TravelGeometry(region, metric, speed)
    return geo.pairs(a.ravel(), b.ravel()).reshape(a.shape)


def _ceil_quantum(w: np.ndarray) -> np.ndarray:
    return np.ceil(w / _QUANTUM) * _QUANTUM


def grid_wraps(region: Region) -> bool:
    """True when the grid is in degrees and its columns span the full 360 degrees (the first
    and last columns are then neighbours in a travel graph)."""
    lon = np.asarray(region.lon.values, dtype=np.float64)
    if not region._sphere or lon.size < 3:
        return False
    step = np.diff(lon)
    if not np.allclose(step, step[0], rtol=1e-6, atol=0):
        return False
    return bool(abs(abs(step[0]) * lon.size - 360.0) <= 1e-6 * abs(step[0]) * lon.size)


# --------------------------------------------------------------------------- travel graph
_DIRS = ((0, 1), (1, -1), (1, 0), (1, 1))  # half of the 8 neighbours; edges are symmetric


class _Graph:
    """Travel graph over the enterable cells within straight-line ``radius`` of the start.

    ``cells`` (sorted region cell indices) are the nodes; CSR edges to 8-neighbours (wrapping
    columns on a full-circle grid) weighted by the metric distance between centres, rounded up
    to :data:`_QUANTUM`. Dijkstra rows (distance, predecessor) are cached per source cell.
    """

    def __init__(self, model: PathModel, radius: float, limit: float,
                 ellipse: float | None = None) -> None:
        from scipy.sparse import csr_matrix

        region = model.region
        self.radius = float(radius)
        self.limit = float(limit)
        lb = model._lower_bound_from_start(self.radius)
        near = model._enter & (lb <= self.radius + model.tol)
        if ellipse is not None:  # a route to an end: only where start -> x -> end fits
            reach = float(ellipse) * (1 + 1e-9) + model.tol
            near &= lb + model._lower_bound_from(model.end, reach) <= reach
            near[model.end] = True
        near[model.start] = True
        self.cells = np.flatnonzero(near).astype(np.int64)
        ny, nx = region.shape
        lookup = np.full(ny * nx, -1, dtype=np.int64)
        gi = region.grid_index[self.cells]
        lookup[gi[:, 0] * nx + gi[:, 1]] = np.arange(self.cells.size)
        src, dst, wt = [], [], []
        wrap = model._wrap
        for dr, dc in _DIRS:
            r = gi[:, 0] + dr
            c = gi[:, 1] + dc
            if wrap:
                c = np.mod(c, nx)
            ok = (r >= 0) & (r < ny) & (c >= 0) & (c < nx)
            (i,) = np.nonzero(ok)
            j = lookup[r[ok] * nx + c[ok]]
            keep = j >= 0
            i, j = i[keep], j[keep]
            if model.metric == "grid":
                w = np.full(i.size, math.sqrt(2.0) if dr and dc else 1.0)
            else:
                w = model._geo.pairs(self.cells[i], self.cells[j])
            src += [i, j]
            dst += [j, i]
            wt += [w, w]
        w = _ceil_quantum(np.concatenate(wt)) if wt else np.zeros(0)
        n = self.cells.size
        self.csr = csr_matrix((w, (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def local(self, cells: np.ndarray) -> np.ndarray:
        """Node index of each region cell, -1 where it is not a node."""
        cells = np.asarray(cells, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.cells, cells), max(self.cells.size - 1, 0))
        return np.where(self.cells[pos] == cells, pos, -1)

    def run(self, cell: int) -> tuple[np.ndarray, np.ndarray]:
        """(distance (n,), predecessor (n,)) from ``cell`` over the nodes, cached."""
        cell = int(cell)
        hit = self._cache.get(cell)
        if hit is None:
            (loc,) = self.local(np.array([cell]))
            if loc < 0:
                n = self.cells.size
                hit = (np.full(n, np.inf), np.full(n, -9999, dtype=np.int32))
            else:
                hit = _dijkstra(self.csr.indptr, self.csr.indices, self.csr.data, int(loc),
                                self.limit)
            self._cache[cell] = hit
        return hit

    def to(self, cell: int, targets: np.ndarray) -> np.ndarray:
        """Graph distances from ``cell`` to region cells ``targets`` (inf: not reachable)."""
        d = self.run(cell)[0]
        loc = self.local(targets)
        return np.where(loc >= 0, d[np.maximum(loc, 0)], np.inf)


@numba.njit(cache=True, nogil=True)
def _dijkstra(indptr, indices, data, src, limit):  # pragma: no cover - compiled
    """Shortest distances and predecessors from node ``src`` (indexed binary heap with
    decrease-key); nodes farther than ``limit`` stay ``inf`` (predecessor -9999). Edge lengths
    are multiples of a power of two, so every distance is an exact sum: any correct Dijkstra
    gives the same distances bit for bit."""
    n = indptr.shape[0] - 1
    dist = np.full(n, np.inf)
    pred = np.full(n, -9999, dtype=np.int32)
    pos = np.full(n, -1, dtype=np.int32)  # heap position, -1 never seen, -2 settled
    heap = np.empty(n, dtype=np.int32)
    key = np.empty(n, dtype=np.float64)  # key[i] == dist[heap[i]] (no indirection)
    dist[src] = 0.0
    heap[0] = src
    key[0] = 0.0
    pos[src] = 0
    size = 1
    while size > 0:
        u = heap[0]
        du = key[0]
        pos[u] = -2
        size -= 1
        if size > 0:
            _sift(heap, key, pos, 0, size, heap[size], key[size])
        for e in range(indptr[u], indptr[u + 1]):
            w = indices[e]
            if pos[w] == -2:
                continue
            nd = du + data[e]
            if nd < dist[w] and nd <= limit:
                dist[w] = nd
                pred[w] = u
                i = pos[w]
                if i < 0:
                    i = size
                    size += 1
                _sift(heap, key, pos, i, size, w, nd)
    return dist, pred


@numba.njit(cache=True, nogil=True, inline="always")
def _sift(heap, key, pos, i, size, node, d):  # pragma: no cover - compiled
    """Put ``node`` (key ``d``) at heap position ``i`` of the first ``size`` and restore the
    order: up while the parent's key is larger, then down while a child's key is smaller."""
    while i > 0 and key[(i - 1) >> 1] > d:
        par = (i - 1) >> 1
        heap[i] = heap[par]
        key[i] = key[par]
        pos[heap[i]] = i
        i = par
    while 2 * i + 1 < size:
        c = 2 * i + 1
        if c + 1 < size and key[c + 1] < key[c]:
            c += 1
        if key[c] >= d:
            break
        heap[i] = heap[c]
        key[i] = key[c]
        pos[heap[i]] = i
        i = c
    heap[i] = node
    key[i] = d
    pos[node] = i


@numba.njit(cache=True, nogil=True)
def _walk(pred, src, dst):  # pragma: no cover - compiled
    """Nodes of the shortest path src -> dst (inclusive) from a Dijkstra predecessor row."""
    n = 1
    v = dst
    while v != src:
        v = pred[v]
        if v < 0:
            return np.empty(0, dtype=np.int64)
        n += 1
    out = np.empty(n, dtype=np.int64)
    v = dst
    for k in range(n - 1, -1, -1):
        out[k] = v
        if k:
            v = pred[v]
    return out


# --------------------------------------------------------------------------- costers
class IncrementalCost(MatrixRouteCost):
    """Exact ``route_cost(P + x) - route_cost(P)`` for every candidate of a pool under
    ``model``: :class:`~lrm_cvx.planning.routecost.MatrixRouteCost` fed with the model's
    travel distances (a stop's straight-line row, or its Dijkstra row on the travel graph)."""

    def __init__(self, model: PathModel, cells0: Any, pool: Any) -> None:
        self.model = model
        cells0 = model._check_stops(cells0, "cells0", order_free=True)
        pool = np.ascontiguousarray(np.asarray(pool, dtype=np.int64).ravel())
        if pool.size and (pool.min() < 0 or pool.max() >= model.region.n_cells):
            raise PlanningError(f"pool must hold cell indices in [0, {model.region.n_cells})")
        ploc = model._graph.local(pool) if model._graph is not None else None

        def to_pool(cell: int) -> np.ndarray:
            if model._graph is None:
                return model._geo.row(cell, pool)
            d = model._graph.run(cell)[0]
            return np.where(ploc >= 0, d[np.maximum(ploc, 0)], np.inf)

        def between(cell: int, cells: np.ndarray) -> np.ndarray:
            if model._graph is None:
                return model._geo.row(cell, cells)
            return model._graph.to(cell, cells)

        super().__init__(cells0, pool, to_pool, between, nn=model.cost == "nearest-neighbor",
                         closed=model.closed, end=model.end, stop_cost=model.stop_cost,
                         sum_route=model._sum_route, reachable=model._enter[pool])


# --------------------------------------------------------------------------- the model
def traversable_mask(region: Region, traversable: Any) -> tuple[str, np.ndarray]:
    """``(kind, enterable)`` for ``traversable`` None / ``"valid"`` / a boolean ``(lat, lon)``
    grid: kind ``"none"``, ``"valid"`` or ``"mask"``, enterable the ``(L,)`` bool per cell
    (all True but for a mask). PlanningError for another string, a shape, dtype or coordinate
    that does not match the region's grid."""
    L = region.n_cells
    if traversable is None:
        return "none", np.ones(L, dtype=bool)
    if isinstance(traversable, str):
        if traversable.lower() == "valid":
            return "valid", np.ones(L, dtype=bool)
        raise PlanningError(
            f"traversable must be None, 'valid' or a boolean (lat, lon) mask, got {traversable!r}")
    values = getattr(traversable, "values", traversable)
    arr = np.asarray(values)
    if arr.shape != region.shape:
        raise PlanningError(
            f"traversable mask has shape {arr.shape}, expected the region's grid (lat, lon) = "
            f"{region.shape}")
    if arr.dtype != bool:
        raise PlanningError(f"traversable mask must be boolean (True = may enter), got dtype "
                            f"{arr.dtype}")
    if hasattr(traversable, "dims") and hasattr(traversable, "coords"):
        pairs = zip(traversable.dims, (region.lat, region.lon), strict=True)
        for k, (dim, coord) in enumerate(pairs):
            if dim in traversable.coords:
                mine = np.asarray(coord.values, dtype=np.float64)
                theirs = np.asarray(traversable[dim].values, dtype=np.float64)
                if not np.allclose(mine, theirs, rtol=0, atol=1e-6):
                    raise PlanningError(
                        f"traversable mask's {'lat' if k == 0 else 'lon'} coordinate "
                        f"({dim}) differs from the region's grid")
    gi = region.grid_index
    return "mask", arr[gi[:, 0], gi[:, 1]].astype(bool)


@dataclass(eq=False)
class PathModel:
    """How one robot travels and what its routes cost (built by :func:`make_path_model`).

    Units: ``unit`` is ``"grid units"``, ``"km"`` or ``"h"``; ``budget`` and ``stop_cost`` are
    in it. ``traversable`` is ``"none"`` (straight lines between stops, the paper), ``"valid"``
    or ``"mask"`` (shortest paths over the 8-connected enterable cells). ``cost`` is the route
    ordering heuristic (``"nearest-neighbor"`` or ``"insertion"``).
    """

    region: Region
    start: int
    budget: float
    unit: str
    metric: str
    speed: float | None
    stop_cost: float
    closed: bool
    end: int | None
    traversable: str
    cost: str
    _enter: np.ndarray = field(repr=False)
    _geo: TravelGeometry = field(repr=False)
    _wrap: bool = field(repr=False, default=False)
    _graph: _Graph | None = field(repr=False, default=None)

    # ---------------------------------------------------------------- basics
    @property
    def tol(self) -> float:
        """Budget tolerance: ``1e-9`` (grid units), ``1e-9 * max(1, budget)`` otherwise."""
        return _TOL if self.metric == "grid" else _TOL * max(1.0, self.budget)

    @property
    def is_default(self) -> bool:
        """True for the paper's model: grid units, straight lines, open path, no stop cost."""
        return (self.metric == "grid" and self.traversable == "none" and not self.closed
                and self.end is None and self.stop_cost == 0.0)

    @property
    def n_fixed_stops(self) -> int:
        """Stops every route has: the start, and the end when given."""
        return 1 + (self.end is not None)

    @property
    def travel_budget(self) -> float:
        """The budget left for travel after the fixed stops' stop costs."""
        return self.budget - self.stop_cost * self.n_fixed_stops

    def enterable(self) -> np.ndarray:
        """``(L,)`` bool: cells the robot may enter (all True when ``traversable="none"``)."""
        return self._enter.copy()

    def _sum_route(self, legs: np.ndarray, n_stops: int) -> float:
        """Route cost from its legs: one float summation order for every caller."""
        sc = self.stop_cost
        total = sc
        for k, leg in enumerate(legs):
            total = total + float(leg)
            if k + 1 < n_stops:
                total = total + sc
        return float(total)

    def _lower_bound_from_start(self, radius: float = np.inf) -> np.ndarray:
        """``(L,)`` straight-line distance from the start that no travel path beats
        (grid units wrap on a full-circle grid, matching the graph's wrapped edges); only
        cells whose latitude (row) alone keeps them within ``radius`` are computed, the
        others are ``inf`` (great-circle distance >= R |dlat|)."""
        return self._lower_bound_from(self.start, radius)

    def _lower_bound_from(self, cell: int, radius: float = np.inf) -> np.ndarray:
        """:meth:`_lower_bound_from_start` from ``cell`` instead of the start."""
        gi = self.region.grid_index
        r0 = gi[cell, 0]
        if self.metric == "grid":
            band = np.abs(np.arange(self.region.shape[0]) - r0) <= radius
        else:
            lat = self._geo.latr
            gap = EARTH_RADIUS_KM * np.abs(lat - lat[r0]) / self._geo.speed
            band = gap <= radius * (1 + 1e-9) + self.tol
        rows = np.flatnonzero(band)
        lo, hi = np.searchsorted(gi[:, 0], [rows.min(), rows.max() + 1])
        out = np.full(self.region.n_cells, np.inf)
        cells = np.arange(lo, hi)
        if self.metric == "grid":
            dr = (gi[cells, 0] - r0).astype(np.float64)
            dc = np.abs(gi[cells, 1] - gi[cell, 1]).astype(np.float64)
            if self._wrap:
                dc = np.minimum(dc, self.region.shape[1] - dc)
            out[cells] = np.sqrt(dr * dr + dc * dc)
        else:
            out[cells] = self._geo.row(cell, cells)
        return out

    # ---------------------------------------------------------------- distances
    def distances(self, a: int, cells: Any = None) -> np.ndarray:
        """Travel distance from cell ``a`` (budget unit; ``inf`` where not reachable within
        the model's reach): ``(L,)``, or ``(len(cells),)`` for the given cells."""
        a = int(self.region.check_cells(a, "a"))
        targets = (np.arange(self.region.n_cells) if cells is None
                   else self.region.check_cells(np.atleast_1d(cells), "cells").ravel())
        if self._graph is None:
            d = self._geo.row(a, targets)
            return np.where(self._enter[targets] | (targets == a), d, np.inf)
        return self._graph.to(a, targets)

    def _pair_matrix(self, cells: np.ndarray) -> np.ndarray:
        if self._graph is None:
            return self._geo.matrix(cells, cells)
        return np.stack([self._graph.to(int(c), cells) for c in cells])

    def chart_distance(self, a: Any, b: Any) -> np.ndarray:
        """Euclidean grid-unit distance between grid positions (broadcast), with columns
        taken modulo the full circle on a grid that wraps: the chart of
        :meth:`grid_budget_bound`."""
        gi = self.region.grid_index
        a = self.region.check_cells(a, "a")
        b = self.region.check_cells(b, "b")
        dr = (gi[a, 0] - gi[b, 0]).astype(np.float64)
        dc = np.abs(gi[a, 1] - gi[b, 1]).astype(np.float64)
        if self._wrap:
            dc = np.minimum(dc, self.region.shape[1] - dc)
        return np.sqrt(dr * dr + dc * dc)

    # ---------------------------------------------------------------- routes
    def _check_stops(self, stops: Any, name: str = "stops", order_free: bool = False
                     ) -> np.ndarray:
        arr = np.atleast_1d(np.asarray(stops))
        if arr.ndim != 1 or arr.size == 0:
            raise PlanningError(f"{name} must be a non-empty 1-D sequence of cells")
        arr = self.region.check_cells(arr, name)
        if int(arr[0]) != self.start:
            raise PlanningError(f"{name} must start with the start cell {self.start}, "
                                f"got {int(arr[0])}")
        if np.unique(arr).size != arr.size:
            raise PlanningError(f"{name} must not repeat a cell")
        if not self._enter[arr].all():
            bad = int(arr[~self._enter[arr]][0])
            raise PlanningError(f"{name}: cell {bad} may not be entered (traversable)")
        return arr.astype(np.int64)

    def _with_end(self, stops: np.ndarray) -> np.ndarray:
        if self.end is not None and int(stops[-1]) != self.end:
            if np.any(stops == self.end):
                raise PlanningError(f"the end cell {self.end} must be the last stop")
            stops = np.append(stops, self.end)
        return stops

    def _legs(self, stops: np.ndarray) -> np.ndarray:
        seq = np.append(stops, stops[0]) if self.closed else stops
        if self._graph is None:
            return self._geo.pairs(seq[:-1], seq[1:])
        return np.array([self._graph.to(int(a), np.array([b]))[0]
                         for a, b in itertools.pairwise(seq)], dtype=np.float64)

    def route_cost(self, stops: Any) -> float:
        """Exact cost of visiting ``stops`` in the given order (start first): travel, the way
        back (closed) or to ``end`` (appended when not last), and ``stop_cost`` per stop."""
        stops = self._with_end(self._check_stops(stops))
        return self._sum_route(self._legs(stops), stops.size)

    def order(self, stops: Any) -> np.ndarray:
        """The nearest-neighbour visiting order of the set ``stops`` (start first; the end,
        when given, last), by this model's distance, ties to the lowest cell index."""
        stops = self._check_stops(stops, order_free=True)
        if self.end is not None:
            stops = stops[stops != self.end]
        pos = nearest_neighbor_order(self._pair_matrix(stops), stops)
        out = stops[pos]
        return np.append(out, self.end) if self.end is not None else out

    def expand(self, route_stops: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The whole travel through the ordered stops.

        Returns ``(cells (r,), cumulative_cost (r,), waypoint (r,) bool)``: with a travel
        graph the pass-through cells are included (``waypoint=False``) and consecutive cells are
        8-neighbours; a closed tour ends with the start again (``waypoint=True``, no second
        stop cost); ``cumulative_cost[0] == stop_cost`` and ``cumulative_cost[-1] ==
        route_cost(route_stops)``.
        """
        stops = self._with_end(self._check_stops(route_stops))
        seq = np.append(stops, stops[0]) if self.closed else stops
        legs = self._legs(stops)
        sc = self.stop_cost
        cells = [np.array([stops[0]])]
        cum = [np.array([sc])]
        way = [np.array([True])]
        total = sc
        for k in range(seq.size - 1):
            a, b = int(seq[k]), int(seq[k + 1])
            stop = k + 1 < stops.size
            if self._graph is not None and np.isfinite(legs[k]):
                d, pred = self._graph.run(a)
                la, lb = self._graph.local(np.array([a, b]))
                path = _walk(pred, int(la), int(lb))
                mid = path[1:-1]
                cells.append(self._graph.cells[mid])
                cum.append(total + d[mid])
                way.append(np.zeros(mid.size, dtype=bool))
            total = total + float(legs[k])
            if stop:
                total = total + sc
            cells.append(np.array([b]))
            cum.append(np.array([total]))
            way.append(np.array([True]))
        return (np.concatenate(cells).astype(np.int64), np.concatenate(cum).astype(np.float64),
                np.concatenate(way))

    # ---------------------------------------------------------------- candidates
    def candidates(self) -> np.ndarray:
        """``(n,)`` sorted cells (start and end excluded) that are a stop of some feasible
        route: reachable, and ``d(start, x) + d(x, back) + stop costs <= budget`` (+ tol)
        where back is the start (closed), the end, or nothing (open)."""
        L = self.region.n_cells
        d0 = self.distances(self.start)
        need = d0.copy()
        if self.closed:
            need = d0 + d0
        elif self.end is not None:
            need = d0 + self.distances(self.end)
        n_stops = self.n_fixed_stops + 1
        ok = self._enter & np.isfinite(need) & (need + self.stop_cost * n_stops
                                                <= self.budget + self.tol)
        ok[self.start] = False
        if self.end is not None:
            ok[self.end] = False
        return np.flatnonzero(ok[:L]).astype(np.int64)

    def initial_cells(self, k: int) -> np.ndarray:
        """The start and its ``k - 1`` nearest enterable cells by this model's distance (ties
        to the lowest index), start first; with ``end``: ``[start, end, ...]`` (k >= 2 cells).
        With a travel graph the graph grows when fewer than ``k - 1`` cells are within reach."""
        k = int(k)
        if k < 1:
            raise PlanningError(f"k must be >= 1, got {k}")
        fixed = [self.start] + ([self.end] if self.end is not None else [])
        n_more = max(k - len(fixed), 0)
        while True:
            d = self.distances(self.start)
            d[self.start] = np.inf
            if self.end is not None:
                d[self.end] = np.inf
            ok = np.flatnonzero(np.isfinite(d) & self._enter)
            if ok.size >= n_more or self._graph is None or self._graph_is_whole():
                break
            self._grow_graph()
        if ok.size < n_more:
            raise PlanningError(f"the start can reach only {ok.size + len(fixed)} cells, fewer "
                                f"than k = {k}")
        key = np.lexsort((ok, d[ok]))
        more = ok[key[:n_more]]
        return np.concatenate([fixed, more]).astype(np.int64)

    def _graph_is_whole(self) -> bool:
        return self._graph is not None and not np.isfinite(self._graph.radius)

    def _grow_graph(self) -> None:
        g = self._graph
        r = g.radius * 2 if g.radius > 0 else float(self._unit_step())
        if r > self._lower_bound_from_start()[self._enter].max():
            r = np.inf
        # the forced initial cells may lie beyond the budget: their legs are then unlimited
        # within the grown graph (every node of it is connected to the start inside it)
        self._graph = _Graph(self, r, np.inf)

    def _unit_step(self) -> float:
        """About two grid steps in the budget's unit (the first growth of a graph)."""
        if self.metric == "grid":
            return 2.0
        lat = np.abs(np.diff(self.region.lat.values)).max() if self.region.shape[0] > 1 else 1.0
        lon = np.abs(np.diff(self.region.lon.values)).max() if self.region.shape[1] > 1 else 1.0
        km = 2.0 * EARTH_RADIUS_KM * float(np.radians(max(lat, lon)))
        return km / (self.speed or 1.0)

    def coster(self, cells0: Any, pool: Any) -> Any:
        """Exact incremental costs ``route_cost(P + x) - route_cost(P)`` over ``pool``, from
        the initial stops ``cells0`` (start first): an :class:`IncrementalCost` (or, for the
        paper's default model, routecost's exact classes on grid coordinates, same interface)."""
        if self.is_default:
            cls = NearestNeighborCost if self.cost == "nearest-neighbor" else InsertionCost
            cells0 = self._check_stops(cells0, "cells0", order_free=True)
            return cls(self.region.grid_index, cells0, pool)
        return IncrementalCost(self, cells0, pool)

    # ---------------------------------------------------------------- certificate
    def grid_budget_bound(self) -> float:
        """Upper bound (grid units, :meth:`chart_distance`) on the length of the straight
        polyline through any feasible route's stops in travel order (closed: back to start).

        Why valid: a feasible route travels at most ``D = budget - stop_cost * n_fixed_stops``
        (each route has the start, and the end when given, as stops). Grid metric: each leg is
        a straight chart segment, or a graph path of chart steps 1 / sqrt 2 (rounded up), so
        the stops' polyline is at most D (triangle inequality). km (hours: ``D * speed`` km):
        along any curve on the sphere ``ds^2 = R^2 (dphi^2 + cos^2 phi dlambda^2) >=
        k(phi)^2 (dr^2 + dc^2)`` with ``k(phi) = R min(dlat, cos(phi) dlon)`` (smallest grid
        spacings, radians), so a leg of km length ``l`` spans at most ``l / k`` chart units when
        ``k`` is the minimum over the latitudes it visits. Every point of a feasible route is
        within ``D`` km of the start along the route (``D / 2`` for a closed tour), so its
        latitude is within ``D / R`` (``D / 2R``) radians of the start's: ``phi_max = |phi_start|
        + that`` bounds them all (``inf`` when the band reaches a pole).
        """
        D = self.travel_budget
        if D <= 0:
            return 0.0
        if self.metric == "grid":
            return float(D)
        if self.speed is not None:
            D = D * self.speed
        lat = np.radians(np.asarray(self.region.lat.values, dtype=np.float64))
        lon = np.radians(np.asarray(self.region.lon.values, dtype=np.float64))
        dlat = float(np.abs(np.diff(lat)).min()) if lat.size > 1 else np.inf
        dlon = float(np.abs(np.diff(lon)).min()) if lon.size > 1 else np.inf
        reach = D / 2 if self.closed else D
        phi = abs(float(lat[self.region.grid_index[self.start, 0]])) + reach / EARTH_RADIUS_KM
        if phi >= np.pi / 2:
            return float(np.inf)
        k = EARTH_RADIUS_KM * min(dlat, math.cos(phi) * dlon)
        if not np.isfinite(k):  # a single-cell grid: no chart movement at all
            return 0.0
        return float(D / k * (1 + 1e-12))


def make_path_model(
    region: Region,
    start: Any,
    budget: float,
    *,
    path: PathOptions | None = None,
    cost: str = "nearest-neighbor",
    **options: Any,
) -> PathModel:
    """Build the path model of one robot (see :class:`PathModel`); validates every argument.

    ``start``: a cell index or ``(lat, lon)``. ``budget`` (>= 0) is in the unit of the path
    options. ``path`` (a :class:`~lrm_cvx.planning.request.PathOptions`) or its keywords
    ``metric``, ``speed``, ``stop_cost``, ``traversable``, ``closed``, ``end``:
    ``stop_cost`` (>= 0) is charged per sampling stop, start and end included; ``end`` is a cell
    index or ``(lat, lon)``. ``cost``: ``"nearest-neighbor"`` or ``"insertion"``.
    """
    if not isinstance(region, Region):
        raise PlanningError(f"region must be a Region, got {type(region).__name__}")
    request = PathOptions.from_kwargs(path, where="make_path_model", allowed=PATH_FIELDS[:-2],
                                      **options)
    return path_model(region, start, Fleet.check_budget(budget, request.unit), request, cost)


def path_model(region: Region, start: Any, budget: float, request: PathOptions,
               cost: str = "nearest-neighbor") -> PathModel:
    """:func:`make_path_model` of a request already read (``budget`` checked by
    :class:`~lrm_cvx.planning.request.Fleet`; ``request.sense_along`` is the planner's
    business, not the path model's)."""
    unit = request.unit
    budget = float(budget)
    cost = COST_REGISTRY.canonical(cost, "cost")
    start_cell = region.resolve_cell(start, "start")
    end_cell = None if request.end is None else region.resolve_cell(request.end, "end")
    if end_cell is not None and end_cell == start_cell:
        raise PlanningError("end must differ from start (use closed=True for a tour back to "
                            "the start)")
    kind, enter = traversable_mask(region, request.traversable)
    if not enter[start_cell]:
        raise PlanningError(f"start cell {start_cell} may not be entered (traversable mask)")
    if end_cell is not None and not enter[end_cell]:
        raise PlanningError(f"end cell {end_cell} may not be entered (traversable mask)")
    metric, speed, closed = request.metric, request.speed, request.closed
    geo = TravelGeometry(region, metric, speed)
    model = PathModel(region=region, start=start_cell, budget=budget, unit=unit, metric=metric,
                      speed=speed, stop_cost=request.stop_cost, closed=closed, end=end_cell,
                      traversable=kind, cost=cost, _enter=enter, _geo=geo,
                      _wrap=grid_wraps(region))
    if kind == "none":
        return model  # straight lines: a one-cell region plans the start alone (the paper's)
    _check_start_moves(model)
    travel = max(model.travel_budget, 0.0)
    # every point of a feasible route is within `radius` of the start, every leg <= `limit`
    # (a closed tour's leg is at most half of it: the rest of the tour is a way back)
    radius = limit = travel / 2 if closed else travel
    ellipse = None
    if end_cell is not None:
        to_end = float(model._lower_bound_from_start()[end_cell])
        radius = limit = max(radius, to_end)
        # every point x of a route start -> ... -> end within the travel budget has
        # d(start, x) + d(x, end) <= travel (straight-line lower bounds): the graph holds that
        # ellipse only (a disk of radius travel around the start has ~4x its cells; a replan en
        # route is such a route). An end beyond the budget keeps the disk.
        ellipse = travel if to_end <= travel and ELLIPSE_GRAPH else None
    model._graph = _Graph(model, radius, limit + model.tol, ellipse)
    return model


def _check_start_moves(model: PathModel) -> None:
    """PlanningError when the start has no enterable 8-neighbour (it cannot go anywhere)."""
    start = np.array([model.start], dtype=np.int64)
    if not _can_leave(model.region, model._enter, model._wrap, start)[0]:
        raise PlanningError(f"start cell {model.start} cannot reach any other cell (no "
                            "enterable neighbour)")


def _can_leave(region: Region, enter: np.ndarray, wrap: bool, cells: np.ndarray) -> np.ndarray:
    """``(len(cells),)`` bool: which ``cells`` have an enterable 8-neighbour (``enter``: the
    ``(L,)`` enterable cells; columns wrap when ``wrap``, as the travel graph's edges do)."""
    ny, nx = region.shape
    grid = region.cell_grid
    gi = region.grid_index[cells]
    out = np.zeros(cells.size, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if not dr and not dc:
                continue
            r = gi[:, 0] + dr
            c = gi[:, 1] + dc
            if wrap:
                c = np.mod(c, nx)
            inside = (r >= 0) & (r < ny) & (c >= 0) & (c < nx)
            nb = grid[np.clip(r, 0, ny - 1), np.clip(c, 0, nx - 1)]
            out |= inside & (nb >= 0) & enter[np.maximum(nb, 0)]
    return out


def startable_cells(region: Region, traversable: Any = None) -> np.ndarray:
    """``(n,)`` sorted int64 cells a robot may start from under ``traversable``.

    With straight lines (``traversable=None``, the paper) every valid cell; with a travel graph
    (``"valid"`` or a boolean ``(lat, lon)`` mask) the enterable cells with at least one
    enterable 8-neighbour (columns wrapping on a full-circle grid, as the travel graph's), since
    a start must reach another cell: exactly the starts :func:`make_path_model` accepts. A bad
    ``traversable`` raises its PlanningError (as :func:`traversable_mask`).
    """
    kind, enter = traversable_mask(region, traversable)
    cells = np.arange(region.n_cells, dtype=np.int64)
    if kind == "none":
        return cells
    ok = enter & _can_leave(region, enter, grid_wraps(region), cells)
    return np.flatnonzero(ok).astype(np.int64)
