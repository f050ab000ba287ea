"""Route-shape search: a global move for plan refinement.

A route is the sequence of valid cells a polyline from the start passes through, cut at the
budget; random polylines of 2-4 legs are scored by the exact Fisher information and the best are
hill-climbed by moving and inserting waypoints. Every route returned is a path from the start of
length ``<= limit`` over valid cells, in visiting order.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .plan import path_cumulative

__all__ = ["hill_climb", "polyline_cells", "polyline_route", "random_polyline", "search_shapes"]

_SAMPLES_PER_UNIT = 4  # polyline samples per grid unit (enough to catch every crossed cell)
_COMPASS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def polyline_cells(points: np.ndarray, cell_grid: np.ndarray) -> np.ndarray:
    """Valid cells a polyline passes through, first visits in order.

    ``points`` ``(m, 2)`` are (row, col) grid positions (floats; ``points[0]`` the start's
    centre), ``cell_grid`` ``(ny, nx)`` the cell index at each position (-1 where masked, as
    ``Region.cell_grid``). Each leg is sampled at ``1/4`` grid unit and rounded to cells; a
    diagonal jump between consecutive cells gets the corner cell in between (so consecutive
    cells of the staircase are 4-neighbours), positions outside the grid or masked are dropped,
    and a cell passed twice keeps its first visit. Returns cell indices ``(n,)``.
    """
    p = np.asarray(points, dtype=np.float64)
    seg = np.diff(p, axis=0)
    steps = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) * _SAMPLES_PER_UNIT), 1)
    steps = steps.astype(np.int64)
    leg = np.repeat(np.arange(len(seg)), steps)
    frac = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps) + 1) / \
        np.repeat(steps, steps)
    pts = np.vstack([p[:1], p[leg] + seg[leg] * frac[:, None]])
    rc = np.rint(pts).astype(np.int64)
    keep = np.ones(len(rc), dtype=bool)
    keep[1:] = np.any(rc[1:] != rc[:-1], axis=1)
    rc = rc[keep]
    # a diagonal move (both coordinates change) goes through the corner (row_prev, col_next)
    diag = np.flatnonzero(np.all(rc[1:] != rc[:-1], axis=1))
    if diag.size:
        corners = np.column_stack([rc[diag, 0], rc[diag + 1, 1]])
        rc = np.insert(rc, diag + 1, corners, axis=0)
    ny, nx = cell_grid.shape
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < ny) & (rc[:, 1] >= 0) & (rc[:, 1] < nx)
    rc = rc[inside]
    cells = cell_grid[rc[:, 0], rc[:, 1]]
    cells = cells[cells >= 0]
    _, first = np.unique(cells, return_index=True)
    return cells[np.sort(first)]


def _prefix_within(g: np.ndarray, cells: np.ndarray, limit: float) -> np.ndarray:
    """The longest prefix of the ordered ``cells`` whose path length is ``<= limit``."""
    length = path_cumulative(g[cells])
    return cells[: int(np.searchsorted(length, limit, side="right"))]


def polyline_route(points: np.ndarray, cell_grid: np.ndarray, grid_index: np.ndarray,
                   limit: float) -> np.ndarray:
    """The route along a polyline: its valid cells (:func:`polyline_cells`) cut to the longest
    prefix of path length ``<= limit`` (grid units). Cell indices ``(n,)`` in visiting order."""
    return _prefix_within(grid_index, polyline_cells(points, cell_grid), limit)


def random_polyline(rng: np.random.Generator, origin: np.ndarray, limit: float,
                    legs: tuple[int, int] = (2, 4)) -> list[np.ndarray]:
    """A random polyline from ``origin`` (row, col): ``legs[0]..legs[1]`` legs, directions
    uniform, lengths uniform in ``[0.05, 1] limit``, the last leg stretched so the polyline is
    ``>= 1.5 limit`` long (the budget, not the polyline, ends the route). Waypoints ``(2,)``."""
    n = int(rng.integers(legs[0], legs[1] + 1))
    angles = rng.uniform(0.0, 2 * np.pi, n)
    lengths = rng.uniform(0.05, 1.0, n) * limit
    lengths[-1] += max(0.0, 1.5 * limit - lengths.sum())
    pts = [np.asarray(origin, dtype=np.float64)]
    for a, ln in zip(angles, lengths, strict=True):
        pts.append(pts[-1] + ln * np.array([np.sin(a), np.cos(a)]))
    return pts


def search_shapes(
    value: Callable[[np.ndarray], float],
    cell_grid: np.ndarray,
    grid_index: np.ndarray,
    start: int,
    limit: float,
    *,
    samples: int,
    climbs: int = 8,
    rng: np.random.Generator,
    deadline: float,
    fits: Callable[[np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, float] | None:
    """Best route found over polylines from ``start``: ``(route, information)`` or ``None``.

    ``value(route)`` is the information of a cell set (nats); ``limit`` the path-length budget
    (grid units, the tolerance included). ``samples`` random polylines (2-4 legs, directions
    uniform, lengths uniform in ``[0.05, 1] limit``, the last leg stretched so the polyline is
    ``>= 1.5 limit`` long and the budget, not the polyline, ends the route); the ``climbs`` best
    are hill-climbed: each waypoint (not the start) moves by ``+-step`` along rows or columns,
    and a waypoint may be inserted at a leg's midpoint, while the information rises; the step
    starts at ``limit / 12`` and halves down to 1. Stops at ``deadline`` (``time.perf_counter``).
    ``fits(cells)``: whether the caller's cost of a cell set (e.g. its nearest-neighbour tour)
    is within the budget; a route is then cut further, to the longest prefix found by bisection
    that fits (verified, so every route returned fits).
    """
    g = np.asarray(grid_index)
    s0 = g[start].astype(np.float64)

    def route_of(points: list[np.ndarray]) -> np.ndarray:
        r = polyline_route(np.asarray(points), cell_grid, g, limit)
        if fits is None or r.size <= 1 or fits(r):
            return r
        lo, hi = 1, r.size - 1  # r[:lo] fits (the start alone), r[:hi + 1] does not
        while lo < hi:
            m = (lo + hi + 1) // 2
            if fits(r[:m]):
                lo = m
            else:
                hi = m - 1
        return r[:lo]

    def score(points: list[np.ndarray]) -> float:
        r = route_of(points)
        return value(r) if r.size else -np.inf

    found: list[tuple[float, list[np.ndarray]]] = []
    for _ in range(samples):
        if time.perf_counter() > deadline:
            break
        pts = random_polyline(rng, s0, limit)
        v = score(pts)
        if np.isfinite(v):
            found.append((v, pts))
    if not found:
        return None
    found.sort(key=lambda t: -t[0])
    best_v, best_pts = found[0]
    for v, pts in found[:climbs]:
        v, pts = hill_climb(score, pts, v, limit, deadline)
        if v > best_v:
            best_v, best_pts = v, pts
    return route_of(best_pts), float(best_v)


def hill_climb(score: Callable[[list[np.ndarray]], float], pts: list[np.ndarray], v: float,
               limit: float, deadline: float, max_points: int = 8
               ) -> tuple[float, list[np.ndarray]]:
    """Compass search on the waypoints of ``pts`` (value ``v = score(pts)``): each waypoint but
    the first moves ``+-step`` along rows or columns and a waypoint may be inserted at a leg's
    midpoint (up to ``max_points``) while ``score`` rises; the step starts at ``limit / 12`` and
    halves down to 1 grid unit. Stops at ``deadline``. Returns ``(value, waypoints)``."""
    step = max(1.0, limit / 12)
    while step >= 1.0 and time.perf_counter() < deadline:
        improved = False
        for i in range(1, len(pts)):
            for d in _COMPASS:
                new = [q.copy() for q in pts]
                new[i] = new[i] + step * d
                w = score(new)
                if w > v + 1e-9:
                    pts, v, improved = new, w, True
        if len(pts) < max_points:
            for i in range(1, len(pts)):
                mid = 0.5 * (pts[i - 1] + pts[i])
                for d in _COMPASS:
                    new = [*pts[:i], mid + step * d, *pts[i:]]
                    w = score(new)
                    if w > v + 1e-9:
                        pts, v, improved = new, w, True
                        break
                if len(pts) >= max_points:
                    break
        if not improved:
            step /= 2
    return v, pts
