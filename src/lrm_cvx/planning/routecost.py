"""Route costs, one home: nearest-neighbour tours, cheapest insertion, 2-opt and Or-opt.

Every algorithm works on grid coordinates (the paper's Euclidean grid cost) and on distance
matrices (any metric, built by :mod:`lrm_cvx.planning.paths`), with exact incremental costs
``C(P + x) - C(P)`` for every candidate at once (docs/planning.md); one compiled kernel per
algorithm serves both inputs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
import numpy as np
from numba.extending import overload

from ..errors import PlanningError
from ..registry import Registry

__all__ = [
    "nearest_neighbor_tour",
    "nearest_neighbor_order",
    "route_length",
    "insertion_costs",
    "two_opt",
    "or_opt",
    "two_opt_matrix",
    "or_opt_matrix",
    "repair_route",
    "NearestNeighborCost",
    "InsertionCost",
    "MatrixRouteCost",
    "make_cost",
    "COSTS",
    "COST_REGISTRY",
]

COST_REGISTRY = Registry("cost", PlanningError)
"""Path costs of the greedy planner (objects: incremental cost classes taking
``(grid_index, cells, pool)``), registered at the end of the module; ``COSTS`` is its
``choices()``."""

_TAIL = 8  # cached tail steps per candidate; longer tails are recomputed at every pick


# --------------------------------------------------------------------------- geometry
# A geometry is four arrays (A, B, C, D): points (pr, pc, tr, tc), the candidates' and the
# tour's rows and columns; or a matrix (DT, S, ts, ts), candidate-to-slot and slot-to-slot
# distances and the tour's slots (D unused). The overloads below pick the kind by A.ndim.
def _cand(A, B, i):  # pragma: no cover - compiled through the overload below
    """Cursor at candidate ``i``: its ``(row, col)``, or its matrix row of distances (a view)."""
    raise NotImplementedError


def _stop(A, B, C, D, a):  # pragma: no cover - compiled through the overload below
    """Cursor at tour position ``a``: its ``(row, col)``, or its matrix row (a view)."""
    raise NotImplementedError


def _key(A, B, C, D, cur, b):  # pragma: no cover - compiled through the overload below
    """Distance key from cursor ``cur`` (:func:`_cand`, :func:`_stop`; possibly of another
    tour over the same candidates) to tour position ``b``."""
    raise NotImplementedError


def _len(A, key):  # pragma: no cover - compiled through the overload below
    """Length of a distance key."""
    raise NotImplementedError


def _back(A, cur, back):  # pragma: no cover - compiled through the overload below
    """Matrices: distance from cursor ``cur`` to slot ``back`` (the start of a closed tour, or
    the end); points never close a tour (0.0, never called)."""
    raise NotImplementedError


_OPTS = {"cache": True, "nogil": True}


@overload(_cand, inline="always", jit_options=_OPTS)
def _cand_impl(A, B, i):  # pragma: no cover - compiled
    if A.ndim == 1:
        return lambda A, B, i: (A[i], B[i])
    return lambda A, B, i: A[i]


@overload(_stop, inline="always", jit_options=_OPTS)
def _stop_impl(A, B, C, D, a):  # pragma: no cover - compiled
    if A.ndim == 1:
        return lambda A, B, C, D, a: (C[a], D[a])
    return lambda A, B, C, D, a: B[C[a]]


@overload(_key, inline="always", jit_options=_OPTS)
def _key_impl(A, B, C, D, cur, b):  # pragma: no cover - compiled
    if A.ndim == 1:
        def points(A, B, C, D, cur, b):
            dr = C[b] - cur[0]
            dc = D[b] - cur[1]
            return dr * dr + dc * dc
        return points
    return lambda A, B, C, D, cur, b: cur[C[b]]


@overload(_len, inline="always", jit_options=_OPTS)
def _len_impl(A, key):  # pragma: no cover - compiled
    if A.ndim == 1:
        return lambda A, key: np.sqrt(float(key))
    return lambda A, key: key


@overload(_back, inline="always", jit_options=_OPTS)
def _back_impl(A, cur, back):  # pragma: no cover - compiled
    if A.ndim == 1:
        return lambda A, cur, back: 0.0
    return lambda A, cur, back: cur[back]


def _grid(grid_index: Any) -> np.ndarray:
    g = np.ascontiguousarray(grid_index, dtype=np.int64)
    if g.ndim != 2 or g.shape[1] != 2:
        raise PlanningError(f"grid_index must be (L, 2) (row, col), got shape {g.shape}")
    return g


def _cells(cells: Any, n: int, name: str = "cells") -> np.ndarray:
    arr = np.ascontiguousarray(np.atleast_1d(np.asarray(cells)), dtype=np.int64).ravel()
    if arr.size == 0:
        raise PlanningError(f"{name} must contain at least one cell (the start)")
    if arr.min() < 0 or arr.max() >= n:
        raise PlanningError(f"{name} must be cell indices in [0, {n}), got {arr}")
    if np.unique(arr).size != arr.size:
        raise PlanningError(f"{name} must not repeat a cell")
    return arr


def _steps(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared (exact int64) and plain lengths of the steps of the path through the points."""
    dr = np.diff(rows)
    dcol = np.diff(cols)
    r2 = np.ascontiguousarray(dr * dr + dcol * dcol, dtype=np.int64)
    return r2, np.sqrt(r2.astype(np.float64))


# --------------------------------------------------------------------------- tours
@numba.njit(cache=True, nogil=True, inline="always")
def _nearest(A, B, C, D, here, lo, hi, done, ids):  # pragma: no cover - compiled
    """``(position, key)`` of the nearest tour position in ``lo..hi-1`` not ``done`` from cursor
    ``here``, ties to the lowest of ``ids``; position -1 when every one is done."""
    bp = -1
    bd = 0
    for p in range(lo, hi):
        if done[p]:
            continue
        dd = _key(A, B, C, D, here, p)
        if bp < 0 or dd < bd or (dd == bd and ids[p] < ids[bp]):
            bp = p
            bd = dd
    return bp, bd


@numba.njit(cache=True, nogil=True)
def _nn_order(A, B, C, D, ids):  # pragma: no cover - compiled
    """Positions (into the tour) of the nearest-neighbour order from position 0."""
    m = ids.shape[0]
    order = np.empty(m, dtype=np.int64)
    used = np.zeros(m, dtype=np.bool_)
    cur = 0
    used[0] = True
    order[0] = 0
    for step in range(1, m):
        best = _nearest(A, B, C, D, _stop(A, B, C, D, cur), 0, m, used, ids)[0]
        used[best] = True
        order[step] = best
        cur = best
    return order


@numba.njit(cache=True, nogil=True)
def _path_length(rows, cols):  # pragma: no cover - compiled
    """Sequential sum of the step lengths of the path through the points in order."""
    total = 0.0
    for i in range(rows.shape[0] - 1):
        dr = rows[i + 1] - rows[i]
        dc = cols[i + 1] - cols[i]
        total += np.sqrt(float(dr * dr + dc * dc))
    return total


def route_length(grid_index: Any, route: Any) -> float:
    """Length in grid units of the open path through ``route`` (cell indices) in order."""
    g = _grid(grid_index)
    r = _cells(route, g.shape[0], "route")
    return float(_path_length(g[r, 0].copy(), g[r, 1].copy()))


def nearest_neighbor_tour(grid_index: Any, cells: Any) -> tuple[float, np.ndarray]:
    """The paper's cost: nearest-neighbour open path through ``cells`` from ``cells[0]``.

    Each step goes to the nearest unvisited cell (Euclidean grid distance), ties to the lowest
    cell index. Returns ``(cost, order)``: the path length in grid units (steps summed in
    order) and the visiting order as cell indices (``order[0] == cells[0]``). ``O(m^2)``.
    """
    g = _grid(grid_index)
    c = _cells(cells, g.shape[0])
    rows, cols = g[c, 0].copy(), g[c, 1].copy()
    pos = _nn_order(rows, cols, rows, cols, c)
    order = c[pos]
    return float(_path_length(rows[pos], cols[pos])), order


def nearest_neighbor_order(D: np.ndarray, ids: Any) -> np.ndarray:
    """Positions of the nearest-neighbour order from position 0 over the ``(m, m)`` float
    distance matrix ``D`` (any metric); ties go to the lowest of ``ids`` ``(m,)`` (cells)."""
    D = np.ascontiguousarray(D, dtype=np.float64)
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    slots = np.arange(ids.size, dtype=np.int64)
    return _nn_order(D, D, slots, slots, ids)


# --------------------------------------------------------------------------- NN kernels
@numba.njit(cache=True, nogil=True)
def _nn_eval(A, B, C, D, i, xid, t0, tid, r2, d, back, vis, tail):  # pragma: no cover - compiled
    """Exact cost increase of adding candidate i (cell ``xid``) to the nearest-neighbour tour.

    ``tid[p]``: the cell at tour position p; ``r2[t]`` / ``d[t]``: key / length of step t.
    ``back``: the slot the route returns to after the tour (start or end; matrices only), -1
    when open. x must not win at any step before ``t0``. Returns ``(dc, t_star, j, q)``: cost
    increase, the step after which x is visited, the old position where the new tail rejoins
    the old tour (``m`` when it never does) and the tail length (positions written to ``tail``
    up to its size). ``vis`` is scratch (all False, left False).
    """
    m = tid.shape[0]
    t = t0
    dx = 0
    here = _cand(A, B, i)
    while t < m - 1:
        dx = _key(A, B, C, D, here, t)
        if dx < r2[t] or (dx == r2[t] and xid < tid[t + 1]):
            break
        t += 1
    if t == m - 1:
        inc = _len(A, _key(A, B, C, D, here, m - 1))
        if back >= 0:
            inc += _back(A, here, back) - _back(A, _stop(A, B, C, D, m - 1), back)
        return inc, m - 1, m - 1, 0
    xpart = _len(A, dx)
    hi = t
    nvis = 0
    cpos = -1
    q = 0
    cap = tail.shape[0]
    while True:
        bp, bd = _nearest(A, B, C, D, here, t + 1, hi + 1, vis, tid)
        if hi < m - 1:
            if cpos == hi:
                p = hi + 1
                dd = r2[hi]
                if bp < 0 or dd < bd or (dd == bd and tid[p] < tid[bp]):
                    bp = p
                    bd = dd
            else:
                for p in range(hi + 1, m):
                    dd = _key(A, B, C, D, here, p)
                    if bp < 0 or dd < bd or (dd == bd and tid[p] < tid[bp]):
                        bp = p
                        bd = dd
        xpart += _len(A, bd)
        vis[bp] = True
        nvis += 1
        if bp > hi:
            hi = bp
        if q < cap:
            tail[q] = bp
        q += 1
        cpos = bp
        here = _stop(A, B, C, D, bp)
        if cpos == hi and nvis == hi - t:
            break  # rejoined: same current cell and same unvisited set as the old tour
        if nvis == m - 1 - t:
            break  # every cell visited, ending elsewhere than the old last cell
    for p in range(t + 1, hi + 1):
        vis[p] = False
    old = 0.0
    for k in range(t, hi):
        old += d[k]
    rejoined = cpos == hi and nvis == hi - t
    inc = xpart - old
    if not rejoined and back >= 0:
        inc += _back(A, here, back) - _back(A, _stop(A, B, C, D, m - 1), back)
    return inc, t, hi if rejoined else m, q


@numba.njit(cache=True, nogil=True)
def _nn_eval_all(A, B, C, D, pid, active, t0s, tid, r2, d, back, dc, ts, js, tl, tails):
    # pragma: no cover - compiled
    """Fresh evaluation of every active candidate whose ``t0s >= 0`` (scan starts at t0s);
    caches ``(t_star, j, tail)`` (tails longer than ``tails.shape[1]``: ``tl = -1``)."""
    m = tid.shape[0]
    vis = np.zeros(m, dtype=np.bool_)
    cap = tails.shape[1]
    for i in range(pid.shape[0]):
        if not active[i] or t0s[i] < 0:
            continue
        v, t, j, q = _nn_eval(A, B, C, D, i, pid[i], t0s[i], tid, r2, d, back, vis, tails[i])
        dc[i] = v
        ts[i] = t
        js[i] = j
        tl[i] = q if q <= cap else -1


@numba.njit(cache=True, nogil=True)
def _nn_update(A, B, Co, Do, Cn, Dn, pid, active, otid, ntid, nr2, s, q_p, j_p, p_id, ts, js,
               tl, tails, t0s):  # pragma: no cover - compiled
    """After p (cell ``p_id``) joined the tour after old position s (new position s + 1; the
    old tour ``(Co, Do)``, the new ``(Cn, Dn)``), its tail rejoining at ``j_p``: ``t0s[i] = -1``
    where candidate i's cache provably stays valid (its positions are remapped to the new tour),
    else the step from which its fresh evaluation may start scanning. A closing leg is
    unchanged in both kept cases: the tour's last cell is."""
    for i in range(pid.shape[0]):
        if not active[i]:
            t0s[i] = -1
            continue
        t = ts[i]
        if t < s:
            t0s[i] = t
            q = tl[i]
            if js[i] <= s and q >= 0:
                ok = True
                here = _cand(A, B, i)
                for u in range(q):
                    a = tails[i, u]
                    dp = _key(A, B, Cn, Dn, here, s + 1)
                    dn = _key(A, B, Co, Do, here, a)
                    if dp < dn or (dp == dn and p_id < otid[a]):
                        ok = False
                        break
                    here = _stop(A, B, Co, Do, a)
                if ok:
                    t0s[i] = -1
        elif t > j_p:
            t0s[i] = s
            ok = True
            here = _cand(A, B, i)
            for u in range(s, s + q_p + 1):
                dx = _key(A, B, Cn, Dn, here, u)
                if dx < nr2[u] or (dx == nr2[u] and pid[i] < ntid[u + 1]):
                    ok = False
                    break
            if ok:
                t0s[i] = -1
                ts[i] = t + 1
                js[i] = js[i] + 1
                for u in range(tl[i]):
                    tails[i, u] += 1
        else:
            t0s[i] = s


# --------------------------------------------------------------------------- insertion kernels
@numba.njit(cache=True, nogil=True)
def _seg_best(A, B, C, D, i, seg, lo, hi, bv, bp):  # pragma: no cover - compiled
    """Best (increase, position) of inserting candidate i into the route's segments lo..hi-1
    (the route is the tour) and the incumbent ``(bv, bp)``; ties to the earliest."""
    here = _cand(A, B, i)
    for k in range(lo, hi):
        v = _len(A, _key(A, B, C, D, here, k)) + _len(A, _key(A, B, C, D, here, k + 1)) - seg[k]
        if bp < 0 or v < bv or (v == bv and k < bp):
            bv = v
            bp = k
    return bv, bp


@numba.njit(cache=True, nogil=True)
def _ins_all(A, B, C, D, active, seg, sv, sp, bv0):  # pragma: no cover - compiled
    for i in range(active.shape[0]):
        if active[i]:
            sv[i], sp[i] = _seg_best(A, B, C, D, i, seg, 0, seg.shape[0], bv0, -1)


@numba.njit(cache=True, nogil=True)
def _ins_update(A, B, C, D, active, seg, s, sv, sp, bv0):  # pragma: no cover - compiled
    """After inserting a stop after old position s: exact segment bests. Segments before s keep
    their position, s is split into new segments s and s+1 (s is the new segment from the old
    last stop when it was appended), later ones shift by one; a candidate whose best was s is
    rescanned."""
    nseg = seg.shape[0]
    hi = min(s + 2, nseg)
    for i in range(active.shape[0]):
        if not active[i]:
            continue
        if sp[i] == s:
            sv[i], sp[i] = _seg_best(A, B, C, D, i, seg, 0, nseg, bv0, -1)
            continue
        if sp[i] > s:
            sp[i] += 1
        sv[i], sp[i] = _seg_best(A, B, C, D, i, seg, s, hi, sv[i], sp[i])


def _cheapest(sv: np.ndarray, sp: np.ndarray, append: np.ndarray, m: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Best segment or appending after the last of ``m`` stops (segment wins ties)."""
    use_seg = (sp >= 0) & (sv <= append)
    return np.where(use_seg, sv, append), np.where(use_seg, sp, m - 1)


def insertion_costs(grid_index: Any, route: Any, cand: Any) -> tuple[np.ndarray, np.ndarray]:
    """Cheapest insertion of each candidate cell into the open path ``route`` (between two
    consecutive stops, or appended): ``(increase (n,), position after which it goes (n,))``,
    grid units, ties to the earliest position, a segment before appending."""
    g = np.ascontiguousarray(grid_index, dtype=np.int64)
    route = np.asarray(route, dtype=np.int64)
    cand = np.asarray(cand, dtype=np.int64)
    rr, rc = np.ascontiguousarray(g[route, 0]), np.ascontiguousarray(g[route, 1])
    pr, pc = np.ascontiguousarray(g[cand, 0]), np.ascontiguousarray(g[cand, 1])
    sv = np.full(cand.size, np.inf)
    sp = np.full(cand.size, -1, dtype=np.int64)
    _ins_all(pr, pc, rr, rc, np.ones(cand.size, dtype=np.bool_), _steps(rr, rc)[1], sv, sp,
             0.0)
    dr, dc = pr - rr[-1], pc - rc[-1]
    return _cheapest(sv, sp, np.sqrt((dr * dr + dc * dc).astype(np.float64)), route.size)


# --------------------------------------------------------------------------- 2-opt / Or-opt
def two_opt_matrix(D: np.ndarray, route: Any, max_iter: int = 1000) -> np.ndarray:
    """2-opt on an open path with a fixed first stop over the distance matrix ``D`` (``route``
    indexes it): reverse ``route[i+1 .. j]`` while some reversal shortens the path (the best
    one each pass), vectorised over all ``(i, j)``."""
    r = np.array(route, copy=True)
    m = r.size
    if m < 3:
        return r
    i = np.arange(m - 1)[:, None]
    j = np.arange(m)[None, :]
    nxt = np.minimum(j + 1, m - 1)
    for _ in range(max_iter):
        dij = D[np.ix_(r, r)]
        seg = dij[np.arange(1, m), np.arange(m - 1)]  # (m-1,) steps
        a_next = dij[np.minimum(i + 1, m - 1), nxt]  # d(r[i+1], r[j+1])
        delta = dij[i, j] - seg[i]
        delta = delta + np.where(j < m - 1, a_next - seg[np.minimum(j, m - 2)], 0.0)
        delta = np.where(j > i + 1, delta, 0.0)
        b = int(np.argmin(delta))
        if not delta.flat[b] < -1e-10:
            break
        bi, bj = divmod(b, m)
        r[bi + 1:bj + 1] = r[bi + 1:bj + 1][::-1].copy()
    return r


def or_opt_matrix(D: np.ndarray, route: Any, max_iter: int = 1000) -> np.ndarray:
    """Or-opt over the distance matrix ``D`` (``route`` indexes it): move one stop (not the
    first) to the position where the open path is shortest, the best move each pass,
    vectorised over all (stop, position) pairs."""
    r = np.array(route, copy=True)
    m = r.size
    if m < 3:
        return r
    s = np.arange(1, m)
    prev, nxt = s - 1, s + 1
    q = np.arange(m)[None, :]
    qn = q + 1
    has_next = qn < m
    bad = (q == s[:, None]) | (q == s[:, None] - 1)
    # when q+1 == s the segment (q, q+1) does not exist after removing s: use (q, s+1)
    fix = qn == s[:, None]
    alt_next = np.minimum(s + 1, m - 1)[:, None]
    for _ in range(max_iter):
        Dr = D[np.ix_(r, r)]
        save = Dr[prev, s] + np.where(nxt < m, Dr[s, np.minimum(nxt, m - 1)]
                                      - Dr[prev, np.minimum(nxt, m - 1)], 0.0)
        # insert after position q (q != s, q != s-1), into the path without s
        add = Dr[s[:, None], q] + np.where(has_next, Dr[s[:, None], np.minimum(qn, m - 1)]
                                            - Dr[q, np.minimum(qn, m - 1)], 0.0)
        add = np.where(fix & (s[:, None] + 1 < m),
                       Dr[s[:, None], q] + Dr[s[:, None], alt_next] - Dr[q, alt_next], add)
        add = np.where(fix & (s[:, None] + 1 >= m), Dr[s[:, None], q], add)
        delta = np.where(bad, 0.0, add - save[:, None])
        b = int(np.argmin(delta))
        if not delta.flat[b] < -1e-10:
            break
        si, qi = divmod(b, m)
        stop = r[s[si]]
        rest = np.delete(r, s[si])
        pos = qi if qi < s[si] else qi - 1
        r = np.insert(rest, pos + 1, stop)
    return r


def _hypot_matrix(grid_index: Any, route: np.ndarray) -> np.ndarray:
    """``(m, m)`` Euclidean grid distances (``np.hypot``) between the stops of ``route``."""
    p = np.asarray(grid_index)[route].astype(np.float64)
    return np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])


def two_opt(grid_index: Any, route: Any, max_iter: int = 1000) -> np.ndarray:
    """:func:`two_opt_matrix` on grid coordinates: the reordered ``route`` (cells, the first
    stop fixed), never longer."""
    route = np.asarray(route)
    D = _hypot_matrix(grid_index, route)
    return route[two_opt_matrix(D, np.arange(route.size), max_iter)]


def or_opt(grid_index: Any, route: Any, max_iter: int = 1000) -> np.ndarray:
    """:func:`or_opt_matrix` on grid coordinates: the reordered ``route`` (cells, the first stop
    fixed), never longer."""
    route = np.asarray(route)
    D = _hypot_matrix(grid_index, route)
    return route[or_opt_matrix(D, np.arange(route.size), max_iter)]


def repair_route(grid_index: Any, route: Any) -> np.ndarray:
    """2-opt then Or-opt until neither shortens the open path (each only shortens it)."""
    route = np.asarray(route)
    best, best_len = route, route_length(grid_index, route)
    for _ in range(20):
        r = or_opt(grid_index, two_opt(grid_index, best))
        length = route_length(grid_index, r)
        if not length < best_len - 1e-10:
            break
        best, best_len = r, length
    return best


# --------------------------------------------------------------------------- oracles
class _PoolCost:
    """Shared state of the incremental costs: the candidate pool and its active mask."""

    pool: np.ndarray
    active: np.ndarray

    def _init_pool(self, grid_index: Any, cells: Any, pool: Any) -> tuple[np.ndarray, np.ndarray]:
        g = _grid(grid_index)
        self._g = g
        cells = _cells(cells, g.shape[0])
        self.pool = np.ascontiguousarray(pool, dtype=np.int64).ravel()
        if self.pool.size and (self.pool.min() < 0 or self.pool.max() >= g.shape[0]):
            raise PlanningError("pool must hold cell indices of grid_index")
        self._pr = np.ascontiguousarray(g[self.pool, 0])
        self._pc = np.ascontiguousarray(g[self.pool, 1])
        self.active = ~np.isin(self.pool, cells)
        return g, cells

    def _index(self, cell: int) -> int:
        (where,) = np.nonzero(self.pool == int(cell))
        if where.size == 0 or not self.active[where[0]]:
            raise PlanningError(f"cell {cell} is not an active candidate of the pool")
        return int(where[0])

    def deactivate(self, cell: int) -> None:
        """A fleet-mate took ``cell``: it is no longer a candidate (the route is unchanged)."""
        self.active[self.pool == int(cell)] = False


class _PointCost(_PoolCost):
    """The tour of the coordinate costs: its cells, their grid positions and step lengths."""

    def _set_tour(self, tour: np.ndarray) -> None:
        self.tour = np.ascontiguousarray(tour, dtype=np.int64)
        self._tr = np.ascontiguousarray(self._g[self.tour, 0])
        self._tc = np.ascontiguousarray(self._g[self.tour, 1])
        self._r2, self._d = _steps(self._tr, self._tc)
        self.cost = float(_path_length(self._tr, self._tc))

    def _geometry(self) -> tuple[np.ndarray, ...]:
        return self._pr, self._pc, self._tr, self._tc

    @property
    def route(self) -> np.ndarray:
        """The current route (cell indices from the start)."""
        return self.tour.copy()


class NearestNeighborCost(_PointCost):
    """Exact nearest-neighbour tour cost increases ``C(P + x) - C(P)`` for a candidate pool.

    Parameters
    ----------
    grid_index : ``(L, 2)`` int (row, col) of every cell.
    cells : the initial set ``P``, start first (the tour starts there).
    pool : candidate cell indices ``(n,)``; cells of ``P`` in it are inactive.

    ``increases()`` returns ``(n,)`` float64 (``nan`` for inactive candidates); ``add(cell)``
    adds a pool cell to ``P``. ``tour`` and ``cost`` describe the current tour.
    """

    name = "nearest-neighbor"

    def __init__(self, grid_index: Any, cells: Any, pool: Any) -> None:
        g, cells = self._init_pool(grid_index, cells, pool)
        n = self.pool.size
        self._dc = np.full(n, np.nan)
        self._ts = np.zeros(n, dtype=np.int64)
        self._js = np.zeros(n, dtype=np.int64)
        self._tl = np.zeros(n, dtype=np.int64)
        self._tails = np.zeros((n, _TAIL), dtype=np.int64)
        self._set_tour(nearest_neighbor_tour(g, cells)[1])
        self._refresh(np.zeros(n, dtype=np.int64))
        self.n_evaluated = int(self.active.sum())

    def _refresh(self, t0s: np.ndarray) -> None:
        _nn_eval_all(*self._geometry(), self.pool, self.active, t0s, self.tour, self._r2,
                     self._d, -1, self._dc, self._ts, self._js, self._tl, self._tails)

    def increases(self) -> np.ndarray:
        """``C(P + x) - C(P)`` for every pool candidate, ``nan`` where inactive."""
        return np.where(self.active, self._dc, np.nan)

    def add(self, cell: int) -> None:
        """Add pool cell ``cell`` to ``P``: new tour, then refresh only the invalidated caches."""
        i = self._index(cell)
        m = self.tour.size
        # p's own evaluation with an unbounded tail gives the new tour (exactness argument)
        tail = np.zeros(max(m, 1), dtype=np.int64)
        vis = np.zeros(m, dtype=np.bool_)
        _, s, j_p, q_p = _nn_eval(*self._geometry(), i, int(cell), 0, self.tour, self._r2,
                                  self._d, -1, vis, tail)
        s, j_p, q_p = int(s), int(j_p), int(q_p)
        old_tr, old_tc, old_tid = self._tr, self._tc, self.tour
        new_tour = np.concatenate(
            [old_tid[: s + 1], [int(cell)], old_tid[tail[:q_p]], old_tid[j_p + 1:]]
        )
        self.active[i] = False
        self._set_tour(new_tour)
        t0s = np.empty(self.pool.size, dtype=np.int64)
        _nn_update(self._pr, self._pc, old_tr, old_tc, self._tr, self._tc, self.pool,
                   self.active, old_tid, self.tour, self._r2, s, q_p, j_p, int(cell), self._ts,
                   self._js, self._tl, self._tails, t0s)
        self.n_evaluated = int((t0s >= 0).sum())
        self._refresh(t0s)


class InsertionCost(_PointCost):
    """Cheapest-insertion route costs: ``C(P + x) - C(P)`` = the cheapest way to add x.

    The route starts as the nearest-neighbour tour of the initial cells. A candidate x can be
    inserted between consecutive route cells ``r_i, r_{i+1}`` (increase ``d(r_i, x) +
    d(x, r_{i+1}) - d(r_i, r_{i+1})``, position ``i``) or appended after the last cell
    ``r_{m-1}`` (increase ``d(r_{m-1}, x)``, position ``m-1``); the smallest increase wins,
    ties (equal floats) to the earliest position. ``add`` inserts the cell there. Each
    candidate's best segment is cached; an update is exact and ``O(1)`` per candidate unless
    its best segment was the one split, which is then rescanned.
    """

    name = "insertion"

    def __init__(self, grid_index: Any, cells: Any, pool: Any) -> None:
        g, cells = self._init_pool(grid_index, cells, pool)
        self._set_tour(nearest_neighbor_tour(g, cells)[1])
        self._sv = np.full(self.pool.size, np.inf)
        self._sp = np.full(self.pool.size, -1, dtype=np.int64)
        _ins_all(*self._geometry(), self.active, self._d, self._sv, self._sp, 0.0)
        self.n_evaluated = int(self.active.sum())

    def _best(self) -> tuple[np.ndarray, np.ndarray]:
        dr = self._pr - self._tr[-1]
        dc = self._pc - self._tc[-1]
        append = np.sqrt((dr * dr + dc * dc).astype(np.float64))
        return _cheapest(self._sv, self._sp, append, self.tour.size)

    def increases(self) -> np.ndarray:
        """Cheapest insertion increase for every pool candidate, ``nan`` where inactive."""
        return np.where(self.active, self._best()[0], np.nan)

    def positions(self) -> np.ndarray:
        """Route position after which each candidate would be inserted (``m-1`` = append)."""
        return np.where(self.active, self._best()[1], -1)

    def add(self, cell: int) -> None:
        """Insert pool cell ``cell`` at its cheapest position and update every candidate."""
        i = self._index(cell)
        s = int(self.positions()[i])
        self.active[i] = False
        self._set_tour(np.insert(self.tour, s + 1, int(cell)))
        n_split = int((self.active & (self._sp == s)).sum())
        _ins_update(*self._geometry(), self.active, self._d, s, self._sv, self._sp, 0.0)
        self.n_evaluated = n_split


class MatrixRouteCost(_PoolCost):
    """Exact ``route_cost(P + x) - route_cost(P)`` for every candidate of a pool, on travel
    distances of any metric (the path model's coster, :meth:`~.paths.PathModel.coster`).

    Parameters
    ----------
    cells0 : ``(m,)`` the initial stops, start first (checked by the caller).
    pool : ``(n,)`` candidate cells.
    to_pool : ``to_pool(cell) -> (n,)`` travel distances from ``cell`` to every pool cell.
    between : ``between(cell, cells) -> (k,)`` travel distances from ``cell`` to ``cells``.
    nn : the nearest-neighbour tour (True) or cheapest insertion (False).
    closed, end : the route returns to the start / ends at cell ``end`` (None: open).
    stop_cost : charged per candidate stop; ``sum_route(legs, n_stops)`` the route's cost.
    reachable : ``(n,)`` bool, pool cells that may be entered.

    Attributes: ``pool``, ``active (n,) bool``, ``cost`` (current route cost, stops and closure
    included), ``route`` (ordered stops, start first; closed: start not repeated; with ``end``:
    end last), ``n_evaluated`` (candidates re-evaluated at the last update). Distances from the
    pool to the route's stops are an ``(n, m)`` matrix, one column per stop.
    """

    def __init__(self, cells0: np.ndarray, pool: np.ndarray,
                 to_pool: Callable[[int], np.ndarray],
                 between: Callable[[int, np.ndarray], np.ndarray], *, nn: bool, closed: bool,
                 end: int | None, stop_cost: float,
                 sum_route: Callable[[np.ndarray, int], float], reachable: np.ndarray) -> None:
        self.closed, self.end, self.stop_cost = closed, end, stop_cost
        self._to_pool, self._between, self._sum_route = to_pool, between, sum_route
        if end is not None:
            cells0 = np.concatenate([cells0[cells0 != end], [end]])
        self.pool = pool
        n = self.pool.size
        self._cap = max(16, 2 * cells0.size)
        self._DT = np.full((n, self._cap), np.inf)
        self._S = np.full((self._cap, self._cap), np.inf)
        self._slot_cell = np.full(self._cap, -1, dtype=np.int64)
        self._m = 0
        for c in cells0:
            self._new_slot(int(c))
        reach = np.isfinite(self._DT[:, 0]) & reachable
        self.active = reach & ~np.isin(self.pool, cells0)
        self._slot_of = {int(c): k for k, c in enumerate(cells0)}
        self._end_slot = self._slot_of[end] if end is not None else -1
        self._back = 0 if closed else self._end_slot
        self._nn = nn
        tour_cells = cells0[cells0 != end] if end is not None else cells0
        slots = np.array([self._slot_of[int(c)] for c in tour_cells], dtype=np.int64)
        slots = slots[nearest_neighbor_order(self._S[np.ix_(slots, slots)].copy(), tour_cells)]
        if not self._nn and end is not None:
            slots = np.append(slots, self._end_slot)
        self._set_tour(slots)
        self._dc = np.full(n, np.nan)
        if self._nn:
            self._tstar = np.zeros(n, dtype=np.int64)
            self._js = np.zeros(n, dtype=np.int64)
            self._tl = np.zeros(n, dtype=np.int64)
            self._tails = np.zeros((n, _TAIL), dtype=np.int64)
            self._nn_refresh(np.zeros(n, dtype=np.int64))
        else:
            self._sv = np.full(n, np.inf)
            self._sp = np.full(n, -1, dtype=np.int64)
            _ins_all(self._DT, self._S, self._seq, self._seq, self.active, self._seg, self._sv,
                     self._sp, np.inf)
        self.n_evaluated = int(self.active.sum())

    def _new_slot(self, cell: int) -> int:
        k = self._m
        if k == self._cap:
            cap = 2 * self._cap
            DT = np.empty((self.pool.size, cap))  # columns >= k are written before use
            DT[:, :k] = self._DT
            S = np.empty((cap, cap))
            S[:k, :k] = self._S
            sc = np.full(cap, -1, dtype=np.int64)
            sc[:k] = self._slot_cell
            self._DT, self._S, self._slot_cell, self._cap = DT, S, sc, cap
        self._DT[:, k] = self._to_pool(cell)
        row = self._between(cell, self._slot_cell[:k])
        self._S[k, :k] = row
        self._S[:k, k] = row
        self._S[k, k] = 0.0
        self._slot_cell[k] = cell
        self._m = k + 1
        return k

    def _set_tour(self, slots: np.ndarray) -> None:
        """NN: the tour's slots (end excluded); insertion: the route's slots (end last)."""
        slots = np.ascontiguousarray(slots, dtype=np.int64)
        route_slots = slots
        if self._nn and self.end is not None:
            route_slots = np.append(slots, self._end_slot)
        self._ts = slots
        self._tid = self._slot_cell[slots].copy()
        self._r = self._S[slots[:-1], slots[1:]].copy()
        self._route_slots = route_slots
        seq = np.append(route_slots, 0) if self.closed else route_slots
        self._seq = np.ascontiguousarray(seq, dtype=np.int64)
        self._seg = self._S[self._seq[:-1], self._seq[1:]].copy()
        self.cost = self._sum_route(self._seg, route_slots.size)

    def _nn_refresh(self, t0s: np.ndarray) -> None:
        _nn_eval_all(self._DT, self._S, self._ts, self._ts, self.pool, self.active, t0s, self._tid,
                     self._r, self._r, self._back, self._dc, self._tstar, self._js, self._tl,
                     self._tails)

    @property
    def route(self) -> np.ndarray:
        """The ordered stops (start first; closed: start not repeated; end last)."""
        return self._slot_cell[self._route_slots].copy()

    def _open(self) -> bool:
        return self.end is None and not self.closed

    def increases(self) -> np.ndarray:
        """``(n,)`` exact ``route_cost(P + x) - route_cost(P)``, ``nan`` where inactive."""
        if self._nn:
            inc = self._dc
        elif self._open():
            inc = _cheapest(self._sv, self._sp, self._DT[:, self._ts[-1]], self._ts.size)[0]
        else:
            inc = self._sv
        return np.where(self.active, inc + self.stop_cost, np.nan)

    def _positions(self) -> np.ndarray:
        if self._open():
            return _cheapest(self._sv, self._sp, self._DT[:, self._ts[-1]], self._ts.size)[1]
        return self._sp.copy()

    def add(self, cell: int) -> None:
        """Add pool cell ``cell`` to the route and update every candidate's increase exactly."""
        i = self._index(cell)
        cell = int(cell)
        if self._nn:
            m = self._ts.size
            vis = np.zeros(m, dtype=np.bool_)
            tail = np.empty(m, dtype=np.int64)
            _, s, j, q = _nn_eval(self._DT, self._S, self._ts, self._ts, i, cell, 0, self._tid,
                                  self._r, self._r, self._back, vis, tail)
            s, j, q = int(s), int(j), int(q)
            self.active[i] = False
            k = self._new_slot(cell)
            old, old_tid = self._ts, self._tid
            new = np.concatenate([old[: s + 1], [k], old[tail[:q]], old[j + 1:]])
            self._set_tour(new)
            t0s = np.empty(self.pool.size, dtype=np.int64)
            _nn_update(self._DT, self._S, old, old, self._ts, self._ts, self.pool,
                       self.active, old_tid, self._tid, self._r, s, q, j, cell, self._tstar,
                       self._js, self._tl, self._tails, t0s)
            self.n_evaluated = int((t0s >= 0).sum())
            self._nn_refresh(t0s)
        else:
            s = int(self._positions()[i])
            self.active[i] = False
            k = self._new_slot(cell)
            self._set_tour(np.insert(self._route_slots, s + 1, k))
            self.n_evaluated = int((self.active & (self._sp == s)).sum())
            _ins_update(self._DT, self._S, self._seq, self._seq, self.active, self._seg, s,
                        self._sv, self._sp, np.inf)


COST_REGISTRY.register(
    "nearest-neighbor", NearestNeighborCost,
    description="the paper's `C(P)`: nearest-neighbour open path from the start, exact "
                "incremental costs",
    aliases=("nn", "nearest_neighbor"),
)
COST_REGISTRY.register(
    "insertion", InsertionCost,
    description="cheapest-insertion route: add each cell where it lengthens the route least",
)
COSTS: tuple[str, ...] = COST_REGISTRY.choices()
"""Canonical cost names (``in`` accepts aliases); the registry's ``choices()``."""


def make_cost(cost: str, grid_index: Any, cells: Any, pool: Any) -> Any:
    """The incremental cost oracle for ``cost`` (a name or alias of :data:`COST_REGISTRY`:
    ``"nearest-neighbor"`` (alias ``"nn"``) or ``"insertion"``)."""
    return COST_REGISTRY.get(cost)(grid_index, cells, pool)
