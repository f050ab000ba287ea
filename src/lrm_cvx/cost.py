"""Path costs of sets of cells: the paper's nearest-neighbour tour, and cheapest insertion.

Points are cells at integer grid positions ``grid_index[cell] = (row, col)``; distances are
Euclidean in grid units. Squared distances are exact integers, so every nearest-neighbour
comparison (and every tie, which goes to the lowest cell index) is decided exactly.

* :func:`nearest_neighbor_tour` is the paper's cost ``C(P)``: an open path from the start,
  each step to the nearest unvisited cell.
* :class:`NearestNeighborCost` gives the greedy planner ``C(P + x) - C(P)`` for every candidate
  ``x`` at once, exactly (see ``docs/planning.md`` for the argument): the tour of ``P + x``
  follows the tour of ``P`` until the first step where ``x`` wins; only the tail after that step
  is recomputed, and only until it rejoins the old tour in the same state. Results are cached
  per candidate and, after a cell is added to ``P``, kept whenever provably unchanged.
* :class:`InsertionCost` is the cheaper alternative ``cost="insertion"``: the route is built by
  cheapest insertion, and a candidate's cost increase is that of inserting it at the best
  position of the current route (or appending it at the end).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from .errors import PlanningError
from .registry import Registry

__all__ = [
    "nearest_neighbor_tour",
    "route_length",
    "NearestNeighborCost",
    "InsertionCost",
    "make_cost",
    "COSTS",
    "COST_REGISTRY",
]

COST_REGISTRY = Registry("cost", PlanningError)
"""Path costs of the greedy planner (objects: incremental cost classes taking
``(grid_index, cells, pool)``), registered at the end of the module; ``COSTS`` is its
``choices()``."""

_TAIL = 8  # cached tail steps per candidate; longer tails are recomputed at every pick
_BIG = np.iinfo(np.int64).max


# --------------------------------------------------------------------------- helpers
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


@numba.njit(cache=True, nogil=True)
def _nn_order(rows, cols, ids):  # pragma: no cover - compiled
    """Positions (into the inputs) of the nearest-neighbour tour from input 0."""
    m = rows.shape[0]
    order = np.empty(m, dtype=np.int64)
    used = np.zeros(m, dtype=np.bool_)
    cur = 0
    used[0] = True
    order[0] = 0
    for step in range(1, m):
        best = -1
        bd = 0
        for j in range(m):
            if used[j]:
                continue
            dr = rows[j] - rows[cur]
            dc = cols[j] - cols[cur]
            dd = dr * dr + dc * dc
            if best < 0 or dd < bd or (dd == bd and ids[j] < ids[best]):
                best = j
                bd = dd
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
    pos = _nn_order(rows, cols, c)
    order = c[pos]
    return float(_path_length(rows[pos], cols[pos])), order


# --------------------------------------------------------------------------- NN kernels
@numba.njit(cache=True, nogil=True)
def _eval_nn(xr, xc, xid, t0, tr, tc, tid, r2, d, vis, tail):  # pragma: no cover - compiled
    """Exact cost increase of adding point x to the nearest-neighbour tour (tr, tc, tid).

    ``r2[t]`` / ``d[t]``: squared / plain length of step t (t < m-1). x must not win at any
    step before ``t0``. Returns ``(dc, t_star, j, q)``: cost increase, the step after which x
    is visited, the old position where the new tail rejoins the old tour (``m`` when it never
    does: it ends elsewhere than the old last cell), and the tail length
    (positions written to ``tail`` up to its size). ``vis`` is scratch (all False, left False).
    """
    m = tr.shape[0]
    t = t0
    dx = 0
    while t < m - 1:
        ar = tr[t] - xr
        ac = tc[t] - xc
        dx = ar * ar + ac * ac
        if dx < r2[t] or (dx == r2[t] and xid < tid[t + 1]):
            break
        t += 1
    if t == m - 1:
        ar = tr[m - 1] - xr
        ac = tc[m - 1] - xc
        return np.sqrt(float(ar * ar + ac * ac)), m - 1, m - 1, 0
    xpart = np.sqrt(float(dx))
    hi = t
    nvis = 0
    cr, cc = xr, xc
    cpos = -1
    q = 0
    cap = tail.shape[0]
    while True:
        bp = -1
        bd = 0
        for p in range(t + 1, hi + 1):
            if vis[p]:
                continue
            ar = tr[p] - cr
            ac = tc[p] - cc
            dd = ar * ar + ac * ac
            if bp < 0 or dd < bd or (dd == bd and tid[p] < tid[bp]):
                bp = p
                bd = dd
        if hi < m - 1:
            if cpos == hi:
                p = hi + 1
                dd = r2[hi]
                if bp < 0 or dd < bd or (dd == bd and tid[p] < tid[bp]):
                    bp = p
                    bd = dd
            else:
                for p in range(hi + 1, m):
                    ar = tr[p] - cr
                    ac = tc[p] - cc
                    dd = ar * ar + ac * ac
                    if bp < 0 or dd < bd or (dd == bd and tid[p] < tid[bp]):
                        bp = p
                        bd = dd
        xpart += np.sqrt(float(bd))
        vis[bp] = True
        nvis += 1
        if bp > hi:
            hi = bp
        if q < cap:
            tail[q] = bp
        q += 1
        cr = tr[bp]
        cc = tc[bp]
        cpos = bp
        if cpos == hi and nvis == hi - t:
            break  # rejoined: same current cell and same unvisited set as the old tour
        if nvis == m - 1 - t:
            break  # every cell visited, ending elsewhere than the old last cell
    for p in range(t + 1, hi + 1):
        vis[p] = False
    old = 0.0
    for i in range(t, hi):
        old += d[i]
    j = hi if cpos == hi and nvis == hi - t else m
    return xpart - old, t, j, q


@numba.njit(cache=True, nogil=True)
def _nn_eval_all(pr, pc, pid, active, t0s, tr, tc, tid, r2, d, dc, ts, js, tl, tails):
    # pragma: no cover - compiled
    """Fresh evaluation of every active candidate whose t0s >= 0 (scan starts at t0s)."""
    m = tr.shape[0]
    vis = np.zeros(m, dtype=np.bool_)
    cap = tails.shape[1]
    for i in range(pr.shape[0]):
        if not active[i] or t0s[i] < 0:
            continue
        v, t, j, q = _eval_nn(pr[i], pc[i], pid[i], t0s[i], tr, tc, tid, r2, d, vis, tails[i])
        dc[i] = v
        ts[i] = t
        js[i] = j
        tl[i] = q if q <= cap else -1


@numba.njit(cache=True, nogil=True)
def _nn_update(pr, pc, pid, active, otr, otc, otid, ntr, ntc, ntid, nr2, s, q_p, j_p,
               p_r, p_c, p_id, ts, js, tl, tails, t0s):  # pragma: no cover - compiled
    """After p joined the tour after old position s: keep provably unchanged candidates.

    Writes ``t0s[i] = -1`` when candidate i's cache stays valid (its positions are remapped to
    the new tour), else the step from which its fresh evaluation may start scanning.
    """
    for i in range(pr.shape[0]):
        if not active[i]:
            t0s[i] = -1
            continue
        xr = pr[i]
        xc = pc[i]
        t = ts[i]
        if t < s:
            t0s[i] = t
            q = tl[i]
            if js[i] <= s and q >= 0:
                ok = True
                cr, cc = xr, xc
                for u in range(q):
                    a = tails[i, u]
                    ar = p_r - cr
                    ac = p_c - cc
                    dp = ar * ar + ac * ac
                    ar = otr[a] - cr
                    ac = otc[a] - cc
                    dn = ar * ar + ac * ac
                    if dp < dn or (dp == dn and p_id < otid[a]):
                        ok = False
                        break
                    cr = otr[a]
                    cc = otc[a]
                if ok:
                    t0s[i] = -1
        elif t > j_p:
            t0s[i] = s
            ok = True
            for u in range(s, s + q_p + 1):
                ar = ntr[u] - xr
                ac = ntc[u] - xc
                dx = ar * ar + ac * ac
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


def _steps(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dr = np.diff(rows)
    dcol = np.diff(cols)
    r2 = np.ascontiguousarray(dr * dr + dcol * dcol, dtype=np.int64)
    return r2, np.sqrt(r2.astype(np.float64))


class _PoolCost:
    """Shared set-up of the incremental costs: the grid, the candidate pool and its state."""

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


class NearestNeighborCost(_PoolCost):
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
        t0s = np.zeros(n, dtype=np.int64)
        _nn_eval_all(self._pr, self._pc, self.pool, self.active, t0s, *self._tour_arrays(),
                     self._dc, self._ts, self._js, self._tl, self._tails)
        self.n_evaluated = int(self.active.sum())

    def _set_tour(self, tour: np.ndarray) -> None:
        self.tour = np.ascontiguousarray(tour, dtype=np.int64)
        self._tr = np.ascontiguousarray(self._g[self.tour, 0])
        self._tc = np.ascontiguousarray(self._g[self.tour, 1])
        self._r2, self._d = _steps(self._tr, self._tc)
        self.cost = float(_path_length(self._tr, self._tc))

    def _tour_arrays(self) -> tuple[np.ndarray, ...]:
        return self._tr, self._tc, self.tour, self._r2, self._d

    def increases(self) -> np.ndarray:
        """``C(P + x) - C(P)`` for every pool candidate, ``nan`` where inactive."""
        return np.where(self.active, self._dc, np.nan)

    def add(self, cell: int) -> None:
        """Add pool cell ``cell`` to ``P``: new tour, then refresh only the invalidated caches."""
        (where,) = np.nonzero(self.pool == int(cell))
        if where.size == 0 or not self.active[where[0]]:
            raise PlanningError(f"cell {cell} is not an active candidate of the pool")
        i = int(where[0])
        m = self.tour.size
        # p's own evaluation with an unbounded tail gives the new tour (exactness argument)
        tail = np.zeros(max(m, 1), dtype=np.int64)
        vis = np.zeros(m, dtype=np.bool_)
        _, s, j_p, q_p = _eval_nn(self._pr[i], self._pc[i], int(cell), 0, *self._tour_arrays(),
                                  vis, tail)
        s, j_p, q_p = int(s), int(j_p), int(q_p)
        old_tr, old_tc, old_tid = self._tr, self._tc, self.tour
        new_tour = np.concatenate(
            [old_tid[: s + 1], [int(cell)], old_tid[tail[:q_p]], old_tid[j_p + 1:]]
        )
        self.active[i] = False
        self._set_tour(new_tour)
        t0s = np.empty(self.pool.size, dtype=np.int64)
        _nn_update(self._pr, self._pc, self.pool, self.active, old_tr, old_tc, old_tid,
                   self._tr, self._tc, self.tour, self._r2, s, q_p, j_p,
                   self._pr[i], self._pc[i], int(cell), self._ts, self._js, self._tl,
                   self._tails, t0s)
        self.n_evaluated = int((t0s >= 0).sum())
        _nn_eval_all(self._pr, self._pc, self.pool, self.active, t0s, *self._tour_arrays(),
                     self._dc, self._ts, self._js, self._tl, self._tails)

    @property
    def route(self) -> np.ndarray:
        """The current tour (cell indices from the start)."""
        return self.tour.copy()


# --------------------------------------------------------------------------- insertion
@numba.njit(cache=True, nogil=True)
def _seg_eval(xr, xc, rr, rc, seg, lo, hi, bv, bp):  # pragma: no cover - compiled
    """Best (increase, position) over the route's segments lo..hi-1 and the incumbent."""
    for i in range(lo, hi):
        ar = rr[i] - xr
        ac = rc[i] - xc
        v = np.sqrt(float(ar * ar + ac * ac))
        ar = rr[i + 1] - xr
        ac = rc[i + 1] - xc
        v = v + np.sqrt(float(ar * ar + ac * ac)) - seg[i]
        if bp < 0 or v < bv or (v == bv and i < bp):
            bv = v
            bp = i
    return bv, bp


@numba.njit(cache=True, nogil=True)
def _ins_all(pr, pc, active, rr, rc, seg, sv, sp):  # pragma: no cover - compiled
    for i in range(pr.shape[0]):
        if active[i]:
            sv[i], sp[i] = _seg_eval(pr[i], pc[i], rr, rc, seg, 0, rr.shape[0] - 1, 0.0, -1)


@numba.njit(cache=True, nogil=True)
def _ins_update(pr, pc, active, rr, rc, seg, s, sv, sp):  # pragma: no cover - compiled
    """After inserting a cell after old position s (new route rr, rc): exact segment bests.

    Segments before s keep their position, s is split into new segments s and s+1 (s is the
    new segment from the old last cell when the cell was appended), later ones shift by one.
    """
    m = rr.shape[0]
    hi = min(s + 2, m - 1)
    for i in range(pr.shape[0]):
        if not active[i]:
            continue
        if sp[i] == s:
            sv[i], sp[i] = _seg_eval(pr[i], pc[i], rr, rc, seg, 0, m - 1, 0.0, -1)
            continue
        if sp[i] > s:
            sp[i] += 1
        sv[i], sp[i] = _seg_eval(pr[i], pc[i], rr, rc, seg, s, hi, sv[i], sp[i])


class InsertionCost(_PoolCost):
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
        self._set_route(nearest_neighbor_tour(g, cells)[1])
        self._sv = np.full(self.pool.size, np.inf)
        self._sp = np.full(self.pool.size, -1, dtype=np.int64)
        _ins_all(self._pr, self._pc, self.active, self._rr, self._rc, self._seg, self._sv,
                 self._sp)
        self.n_evaluated = int(self.active.sum())

    def _set_route(self, route: np.ndarray) -> None:
        self.tour = np.ascontiguousarray(route, dtype=np.int64)
        self._rr = np.ascontiguousarray(self._g[self.tour, 0])
        self._rc = np.ascontiguousarray(self._g[self.tour, 1])
        _, self._seg = _steps(self._rr, self._rc)
        self.cost = float(_path_length(self._rr, self._rc))

    def _best(self) -> tuple[np.ndarray, np.ndarray]:
        dr = self._pr - self._rr[-1]
        dc = self._pc - self._rc[-1]
        append = np.sqrt((dr * dr + dc * dc).astype(np.float64))
        use_seg = (self._sp >= 0) & (self._sv <= append)
        value = np.where(use_seg, self._sv, append)
        pos = np.where(use_seg, self._sp, self.tour.size - 1)
        return value, pos

    def increases(self) -> np.ndarray:
        """Cheapest insertion increase for every pool candidate, ``nan`` where inactive."""
        return np.where(self.active, self._best()[0], np.nan)

    def positions(self) -> np.ndarray:
        """Route position after which each candidate would be inserted (``m-1`` = append)."""
        return np.where(self.active, self._best()[1], -1)

    def add(self, cell: int) -> None:
        """Insert pool cell ``cell`` at its cheapest position and update every candidate."""
        (where,) = np.nonzero(self.pool == int(cell))
        if where.size == 0 or not self.active[where[0]]:
            raise PlanningError(f"cell {cell} is not an active candidate of the pool")
        i = int(where[0])
        s = int(self.positions()[i])
        self.active[i] = False
        self._set_route(np.insert(self.tour, s + 1, int(cell)))
        n_split = int((self.active & (self._sp == s)).sum())
        _ins_update(self._pr, self._pc, self.active, self._rr, self._rc, self._seg, s,
                    self._sv, self._sp)
        self.n_evaluated = n_split

    @property
    def route(self) -> np.ndarray:
        """The current route (cell indices from the start)."""
        return self.tour.copy()


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
