"""A path-aware relaxation of the plan certificate.

Cells are aggregated into blocks and every route is mapped to a unit flow in a layered, acyclic
block graph; the bound reported is a Lagrange dual value, valid at any iterate whatever the LP
solver returned (docs/certificate.md §9).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.csgraph

from .._validation import as_factor_matrix
from ..errors import PlanningError
from .dopt import (
    _CLARABEL_OPTS,
    _DIST_EPS,
    _SCS_OPTS,
    _chol,
    _inv_lower,
    _leverages,
    _moment,
    _moment_map,
    _solve_in_turn,
)

_LP_METHOD = "highs-ipm"

__all__ = ["PathBound", "PathPolytope", "WalkBound", "path_polytope", "path_relaxation_bound",
           "walk_relaxation_bound"]


@dataclass(frozen=True, eq=False)
class PathBound:
    """A certified upper bound (nats) on the path-aware relaxation.

    ``value`` is the smallest dual value over the designs tried; ``primal`` the
    ``log det M(w)`` of the solver's (approximately feasible) design, for diagnostics only;
    ``block`` the block side (grid units), ``n_blocks``, ``n_layers``, ``n_edges`` the size of
    the layered graph; ``solver`` what produced the best design; ``seconds`` wall time.
    """

    value: float
    primal: float
    block: int
    n_blocks: int
    n_layers: int
    n_edges: int
    n_candidates: int
    n_max: int
    solver: str
    status: str
    seconds: float


@dataclass(frozen=True, eq=False)
class PathPolytope:
    """The LP ``max g^T w`` over ``v = [w (N), x (E), t (nodes)]``, ``0 <= v <= 1``,
    ``A_ub v <= b_ub``, ``A_eq v = b_eq``. ``cells`` are the candidate cells (w's order)."""

    cells: np.ndarray
    A_ub: scipy.sparse.csr_array
    b_ub: np.ndarray
    A_eq: scipy.sparse.csr_array
    b_eq: np.ndarray
    block: int
    n_blocks: int
    n_layers: int
    n_edges: int
    n_max: int

    @property
    def n_vars(self) -> int:
        return int(self.A_eq.shape[1])

    def dual_value(self, g: np.ndarray, y_ub: np.ndarray, y_eq: np.ndarray) -> float:
        """Weak-duality bound on ``max g^T w`` at any multipliers (``y_ub`` clipped to >= 0):
        ``b_ub.y_ub + b_eq.y_eq + sum_j max(0, c_j - (A^T y)_j)`` (every variable in [0, 1])."""
        y_ub = np.maximum(np.asarray(y_ub, float), 0.0)
        y_eq = np.asarray(y_eq, float)
        c = np.zeros(self.n_vars)
        c[: self.cells.size] = g
        red = c - self.A_ub.T @ y_ub - self.A_eq.T @ y_eq
        return float(self.b_ub @ y_ub + self.b_eq @ y_eq + np.maximum(red, 0.0).sum())

    def support(self, g: np.ndarray) -> tuple[float, np.ndarray | None]:
        """``(upper bound on max g^T w, an optimal w or None)`` by HiGHS and exact duality."""
        c = np.zeros(self.n_vars)
        c[: self.cells.size] = g
        res = scipy.optimize.linprog(
            -c, A_ub=self.A_ub, b_ub=self.b_ub, A_eq=self.A_eq, b_eq=self.b_eq,
            bounds=(0.0, 1.0), method=_LP_METHOD,
        )
        if res.status != 0 or res.ineqlin is None:
            # y = 0 is dual feasible: the bound is sum max(0, g) (valid, loose)
            return float(np.maximum(g, 0.0).sum()), None
        val = self.dual_value(g, -res.ineqlin.marginals, -res.eqlin.marginals)
        return val, np.clip(res.x[: self.cells.size], 0.0, 1.0)


def _isqrt(d2: np.ndarray) -> np.ndarray:
    """Exact ``floor(sqrt(d2))`` of non-negative integers (vectorised)."""
    r = np.floor(np.sqrt(d2.astype(np.float64))).astype(np.int64)
    r -= (r * r > d2).astype(np.int64)
    r += ((r + 1) * (r + 1) <= d2).astype(np.int64)
    return r


def _layout(gi: np.ndarray, start_rc: np.ndarray, b: int, Lmax: int):
    """Blocks of side ``b``: per-cell block id, caps, pairs (A, B, delta) and earliest layers."""
    br = gi // b
    key, blk = np.unique(br[:, 0] * (1 << 32) + br[:, 1], return_inverse=True)
    blk = blk.ravel()
    nB = key.size
    bpos = np.column_stack([key >> 32, key & ((1 << 32) - 1)]).astype(np.int64)
    sb = start_rc // b
    S = int(np.flatnonzero((bpos[:, 0] == sb[0]) & (bpos[:, 1] == sb[1]))[0])
    cap = np.bincount(blk, minlength=nB)
    # least distance between cells of two blocks (a lower bound: the full squares are used)
    gap = np.abs(bpos[:, None, :] - bpos[None, :, :]) * b - (b - 1)
    gap = np.where(bpos[:, None, :] == bpos[None, :, :], 0, np.maximum(gap, 0))
    d2 = (gap * gap).sum(axis=2)
    delta = _isqrt(d2)
    np.fill_diagonal(delta, 1)  # a leg inside a block has length >= 1 (distinct cells)
    allowed = delta <= Lmax
    np.fill_diagonal(allowed, cap >= 2)
    W = np.where(allowed & ~np.eye(nB, dtype=bool), delta, 0).astype(float)
    early = scipy.sparse.csgraph.dijkstra(scipy.sparse.csr_array(W), indices=S)
    A, B = np.nonzero(allowed)
    dl = delta[A, B]
    ok = np.isfinite(early[A]) & (early[A] + dl <= Lmax)
    A, B, dl = A[ok], B[ok], dl[ok]
    e = np.where(np.isfinite(early), early, Lmax + 1).astype(np.int64)
    return blk, nB, S, cap, A, B, dl, e


def path_polytope(
    region: Any, start: int, budget: float, *, block: int | None = None,
    max_edges: int = 20_000,
) -> PathPolytope:
    """The layered block-flow polytope of every route from ``start`` within ``budget``
    (grid metric). ``block=None`` picks the smallest block side whose graph has at most
    ``max_edges`` edges. Raises :class:`PlanningError` for a block coarser than the budget or
    a graph that exceeds ``max_edges`` at the requested block."""
    budget = float(budget)
    if not (math.isfinite(budget) and budget >= 0):
        raise PlanningError(f"budget must be >= 0 and finite, got {budget!r}")
    Bp = budget + _DIST_EPS * max(1.0, budget)
    gi_all = np.asarray(region.grid_index, dtype=np.int64)
    d = gi_all - gi_all[start]
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    cand = np.flatnonzero(d2.astype(np.float64) <= Bp * Bp)
    Lmax = math.floor(Bp)
    n_max = int(min(cand.size, Lmax + 1))
    gi = gi_all[cand]
    if block is not None:
        if not isinstance(block, (int, np.integer)) or block < 1:
            raise PlanningError(f"block must be an integer >= 1 (grid units), got {block!r}")
        if block > max(1.0, budget):
            raise PlanningError(
                f"block = {block} grid units is coarser than the budget ({budget:g}): the "
                "relaxation could not bind; use a block side <= budget"
            )
        sides = [int(block)]
    else:
        sides = list(range(1, max(2, math.ceil(budget) + 1)))
    for b in sides:
        blk, nB, S, cap, A, B, dl, e = _layout(gi, gi_all[start], b, Lmax)
        counts = Lmax - dl - e[A] + 1
        E = int(counts.sum())
        if E <= max_edges:
            break
    else:
        raise PlanningError(
            f"the layered block graph has {E} edges > max_edges = {max_edges} at block = "
            f"{sides[-1]}; raise max_edges or the block side"
        )
    # nodes (A, l) for l in [e_A, Lmax]
    nl = np.maximum(Lmax - e + 1, 0)
    off = np.concatenate([[0], np.cumsum(nl)])
    n_nodes = int(off[-1])
    rep = np.repeat(np.arange(A.size), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lay = e[A][rep] + (np.arange(E) - first[rep])  # tail layer
    tail = off[A][rep] + lay - e[A][rep]
    hlay = lay + dl[rep]
    head = off[B][rep] + hlay - e[B][rep]
    hblk = B[rep]
    N = cand.size
    # variables: w (N) | x (E) | t (n_nodes)
    xs = N + np.arange(E)
    ts = N + E + np.arange(n_nodes)
    A_eq = scipy.sparse.csr_array(
        (np.concatenate([np.ones(E), -np.ones(E), np.ones(n_nodes)]),
         (np.concatenate([tail, head, np.arange(n_nodes)]), np.concatenate([xs, xs, ts]))),
        shape=(n_nodes, N + E + n_nodes),
    )
    b_eq = np.zeros(n_nodes)
    b_eq[off[S]] = 1.0  # (S, 0): e_S = 0
    isS = (np.arange(nB) == S).astype(float)
    rows = np.concatenate([blk, hblk, nB + hblk, np.full(N, 2 * nB)])
    cols = np.concatenate([np.arange(N), xs, xs, np.arange(N)])
    vals = np.concatenate([np.ones(N), -np.ones(E), np.ones(E), np.ones(N)])
    A_ub = scipy.sparse.csr_array((vals, (rows, cols)), shape=(2 * nB + 1, N + E + n_nodes))
    b_ub = np.concatenate([isS, cap - isS, [float(n_max)]])
    return PathPolytope(cand, A_ub, b_ub, A_eq, b_eq, int(b), int(nB), Lmax + 1, E, n_max)


def _solve_cvx(Yw: np.ndarray, C: np.ndarray, poly: PathPolytope, solver: str
               ) -> tuple[np.ndarray | None, str]:
    """The full relaxation ``max log det(C + sum_j w_j y_j y_j^T)`` over the path polytope in
    cvxpy (Clarabel settings of bound.py, then SCS). Returns ``(w, status)``."""
    import cvxpy as cp

    k, N = Yw.shape
    F, Esc = _moment_map(Yw)
    v = cp.Variable(poly.n_vars)
    w = v[:N]
    Mexpr = cp.reshape(C.ravel() + Esc @ (F @ w), (k, k), order="C")
    cons = [v >= 0, v <= 1, poly.A_ub @ v <= poly.b_ub, poly.A_eq @ v == poly.b_eq]
    prob = cp.Problem(cp.Maximize(cp.log_det(Mexpr)), cons)
    attempts = [("CLARABEL", o) for o in _CLARABEL_OPTS] if solver == "CLARABEL" else []
    attempts.append(("SCS", _SCS_OPTS))
    value, name, status = _solve_in_turn(prob, w, attempts)
    if value is None:
        return None, status
    return np.clip(value, 0.0, 1.0), f"{name} {status}"


def _dual_at(Yc: np.ndarray, M: np.ndarray, poly: PathPolytope, ridge: float
             ) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """``(log det M + k log(S/k), g, LP optimum w)``; ``(inf, None, None)`` if M is singular."""
    k = M.shape[0]
    L = _chol(M)
    if L is None:
        return math.inf, None, None
    logdet = 2.0 * float(np.log(np.diag(L)).sum())
    Linv = _inv_lower(L)
    g = _leverages(Yc, Linv)
    top, wv = poly.support(g)
    S = ridge * float((Linv * Linv).sum()) + top
    if not (np.isfinite(S) and S > 0 and np.isfinite(logdet)):
        return math.inf, g, wv
    return logdet + k * math.log(S / k), g, wv


def path_relaxation_bound(
    Y: Any, region: Any, start: Any, budget: float, *, ridge: float = 0.0,
    block: int | None = None, max_edges: int = 20_000, solver: str = "CLARABEL",
    cvx_max_vars: int = 400_000, fw_steps: int = 8, warm: np.ndarray | None = None,
) -> PathBound:
    """Dual bound of the path-aware relaxation (grid metric): the Fisher information of every
    route from ``start`` within ``budget`` (the cells of an open path of length ``<= budget``
    through distinct cells) is at most ``value``.

    Designs tried: ``warm`` (weights over the candidates, e.g. the disk relaxation's), the
    cvxpy solve of the full relaxation when it has at most ``cvx_max_vars`` variables, and
    ``fw_steps`` Frank-Wolfe steps with the LP oracle. Each design ``M`` yields a valid bound;
    the smallest is returned. Raises :class:`PlanningError` when no design is nonsingular.
    """
    t0 = time.perf_counter()
    Y = as_factor_matrix(Y, region)
    start = region.resolve_cell(start, "start")
    if not (math.isfinite(float(ridge)) and ridge >= 0):
        raise PlanningError(f"ridge must be >= 0 and finite, got {ridge!r}")
    poly = path_polytope(region, start, budget, block=block, max_edges=max_edges)
    Yc = np.ascontiguousarray(Y[:, poly.cells], dtype=np.float64)
    N = poly.cells.size
    best, primal, used, status = math.inf, -math.inf, "none", "no design"
    designs: list[tuple[str, np.ndarray]] = []
    if warm is not None:
        designs.append(("warm", np.asarray(warm, float)))
    w_uni = np.full(N, min(1.0, poly.n_max / N))
    designs.append(("uniform", w_uni))
    Mref = None
    for name, w in designs:
        M = _moment(Yc, np.arange(N), w, ridge)
        val, g, wv = _dual_at(Yc, M, poly, ridge)
        if val < best:
            best, used, status = val, name, "dual"
        if Mref is None and _chol(M) is not None:
            Mref = M
    w_cvx = None
    if poly.n_vars <= cvx_max_vars and Mref is not None:
        A = _inv_lower(_chol(Mref))  # congruence: the solver sees M(w_ref) = I
        w_cvx, st = _solve_cvx(A @ Yc, ridge * (A @ A.T), poly, solver)
        status = st
        if w_cvx is not None:
            M = _moment(Yc, np.arange(N), w_cvx, ridge)
            val, _, _ = _dual_at(Yc, M, poly, ridge)
            Lc = _chol(M)
            if Lc is not None:
                primal = 2.0 * float(np.log(np.diag(Lc)).sum())
            if val < best:
                best, used = val, st
    if w_cvx is None and Mref is not None:  # Frank-Wolfe with the LP oracle
        _, _, wv = _dual_at(Yc, Mref, poly, ridge)
        w = wv if wv is not None else w_uni
        for it in range(fw_steps):
            M = _moment(Yc, np.arange(N), w, ridge)
            val, g, s = _dual_at(Yc, M, poly, ridge)
            if val < best:
                best, used = val, f"frank-wolfe {it}"
            if g is None or s is None:
                break
            Lw = _chol(M)
            primal = max(primal, 2.0 * float(np.log(np.diag(Lw)).sum()))
            Ms = _moment(Yc, np.arange(N), s, ridge)
            lam = np.linalg.eigvals(np.linalg.solve(M, Ms)).real
            gams = np.linspace(0.0, 1.0, 201)
            f = np.log(np.maximum(1e-300, 1.0 + gams[:, None] * (lam[None, :] - 1.0))).sum(1)
            w = w + gams[int(np.argmax(f))] * (s - w)
    if not math.isfinite(best):
        raise PlanningError(
            "the path-aware relaxation has no nonsingular design (fewer than k cells reachable "
            "with ridge = 0); use the disk bound"
        )
    return PathBound(
        value=float(best), primal=float(primal), block=poly.block, n_blocks=poly.n_blocks,
        n_layers=poly.n_layers, n_edges=poly.n_edges, n_candidates=int(N), n_max=poly.n_max,
        solver=used, status=status, seconds=time.perf_counter() - t0,
    )


# ----------------------------------------------------------------------------- king walks
# docs/certificate.md §9, "A walk relaxation": a leg of Euclidean length d is max(|dr|, |dc|)
# <= d king moves, so every route within the budget passes through its cells on a king walk of
# at most floor(B') unit steps from the start. The walk polytope is used through its exact
# pricing oracle (a dynamic program over steps), never as an explicit layered graph.
_KING = tuple((dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0))


class _KingWalks:
    """Best king walk from the start for per-visit rewards (every visit is paid, revisits too).

    Positions are the grid positions within Chebyshev distance ``steps`` of the start (land
    included: a walk may pass anywhere in the plane); ``cells`` (N,) are the candidates, their
    window positions ``pos`` (N,). ``best(r)`` returns ``(value, visits)``: the largest
    ``sum_t r[p_t]`` over walks ``p_0 = start, ..., p_T``, ``T <= steps`` (exact, by dynamic
    programming), and the visit counts (N,) of one optimal walk.
    """

    def __init__(self, region: Any, start: int, cells: np.ndarray, steps: int) -> None:
        ny, nx = region.shape
        s = np.asarray(region.grid_index[start], dtype=np.int64)
        self.r0, self.c0 = max(0, s[0] - steps), max(0, s[1] - steps)
        r1, c1 = min(ny, s[0] + steps + 1), min(nx, s[1] + steps + 1)
        self.shape = (r1 - self.r0, c1 - self.c0)
        gi = np.asarray(region.grid_index[cells], dtype=np.int64)
        self.pos = (gi[:, 0] - self.r0) * self.shape[1] + (gi[:, 1] - self.c0)
        self.s = (int(s[0] - self.r0), int(s[1] - self.c0))
        self.steps = int(steps)

    def best(self, r: np.ndarray) -> tuple[float, np.ndarray]:
        h, w = self.shape
        R = np.zeros(h * w)
        np.add.at(R, self.pos, np.maximum(np.asarray(r, float), 0.0))
        R = R.reshape(h, w)
        F = np.zeros((h, w))
        arg = np.full((self.steps + 1, h, w), -1, np.int8)
        pad = np.full((h + 2, w + 2), -np.inf)
        for T in range(1, self.steps + 1):
            pad[1:-1, 1:-1] = R + F
            cand = np.stack([pad[1 + dr: 1 + dr + h, 1 + dc: 1 + dc + w] for dr, dc in _KING])
            j = np.argmax(cand, axis=0)
            top = np.take_along_axis(cand, j[None], 0)[0]
            arg[T] = np.where(top > 0, j, -1)
            F = np.maximum(top, 0.0)
        value = float(R[self.s] + F[self.s])
        vis = np.zeros((h, w))
        p = self.s
        vis[p] += 1
        for T in range(self.steps, 0, -1):
            j = int(arg[T][p])
            if j < 0:
                break
            p = (p[0] + _KING[j][0], p[1] + _KING[j][1])
            vis[p] += 1
        return value, vis.ravel()[self.pos]


@dataclass(frozen=True, eq=False)
class WalkBound:
    """Dual bound (nats) of the walk relaxation: ``value`` valid whatever the solvers did;
    ``primal`` the best ``log det M(w)`` of a design in the relaxation; ``walks`` columns used;
    ``rounds`` conic solves; ``seconds`` wall time; ``history`` the bound after each design."""

    value: float
    primal: float
    n_candidates: int
    n_max: int
    walks: int
    rounds: int
    seconds: float
    history: tuple[float, ...] = ()


class _WalkLP:
    """``max g.w`` over ``{0 <= w <= 1, A w <= b (count and distance rows), w <= V theta,
    theta >= 0, sum theta = 1}``: column generation over king walks (columns of ``V``) with an
    exact dual bound at every round::

        max g.w  <=  b.y + sum_i max(0, g_i - (A^T y)_i - lam_i) + max_walk lam.visits

    for any ``y >= 0``, ``lam >= 0`` (Lagrangian of the linking rows ``w <= visits``; the last
    term is exact by :class:`_KingWalks`)."""

    def __init__(self, walks: _KingWalks, A: scipy.sparse.csr_array, b: np.ndarray) -> None:
        self.walks, self.A, self.b = walks, A, b
        self.V = np.zeros((A.shape[1], 0))

    def add(self, vis: np.ndarray) -> None:
        if self.V.shape[1] and np.any(np.all(self.V == vis[:, None], axis=0)):
            return
        self.V = np.column_stack([self.V, vis])

    def bound(self, g: np.ndarray, y: np.ndarray, lam: np.ndarray) -> tuple[float, np.ndarray]:
        y, lam = np.maximum(y, 0.0), np.maximum(lam, 0.0)
        red = g - self.A.T @ y - lam
        walk, vis = self.walks.best(lam)
        return float(self.b @ y + np.maximum(red, 0.0).sum() + walk), vis

    def support(self, g: np.ndarray, rounds: int = 60) -> tuple[float, np.ndarray]:
        """``(upper bound on max g.w, the last master's w)``."""
        N = g.size
        if self.V.shape[1] == 0:
            self.add(self.walks.best(g)[1])
        best, w = math.inf, np.zeros(N)
        scale = float(np.abs(g).max()) or 1.0
        for _ in range(rounds):
            m = self.V.shape[1]
            A_ub = scipy.sparse.vstack([
                scipy.sparse.hstack([self.A, scipy.sparse.csr_array((self.A.shape[0], m))]),
                scipy.sparse.hstack([scipy.sparse.eye_array(N),
                                     scipy.sparse.csr_array(-self.V)]),
            ]).tocsr()
            b_ub = np.concatenate([self.b, np.zeros(N)])
            A_eq = np.concatenate([np.zeros(N), np.ones(m)])[None, :]
            bounds = [(0.0, 1.0)] * N + [(0.0, None)] * m
            res = scipy.optimize.linprog(
                -np.concatenate([g, np.zeros(m)]) / scale, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq,
                b_eq=[1.0], bounds=bounds, method="highs")
            if res.status != 0 or res.ineqlin is None:
                y, lam = np.zeros(self.A.shape[0]), np.maximum(g, 0.0)
                val, vis = self.bound(g, y, lam)
                return min(best, val), w
            dual = -np.asarray(res.ineqlin.marginals) * scale
            y, lam = dual[: self.A.shape[0]], dual[self.A.shape[0]:]
            w = np.clip(res.x[:N], 0.0, 1.0)
            val, vis = self.bound(g, y, lam)
            best = min(best, val)
            if best - (-res.fun * scale) <= 1e-9 * max(1.0, abs(best)):
                break
            n_before = self.V.shape[1]
            self.add(vis)
            if self.V.shape[1] == n_before:
                break
        return best, w


def _count_rows(n_max: int, levels: list[np.ndarray], caps: list[np.ndarray], N: int
                ) -> tuple[scipy.sparse.csr_array, np.ndarray]:
    from .dopt import _Polytope

    return _Polytope(n_max, N, levels, caps)._rows(np.arange(N))


def walk_relaxation_bound(
    Y: Any, region: Any, start: Any, budget: float, *, ridge: float = 0.0,
    rounds: int = 6, lp_rounds: int = 60, limits: bool = True,
) -> WalkBound:
    """Dual bound of the walk relaxation (grid metric, the paper's open path): the Fisher
    information of every route from ``start`` within ``budget`` is at most ``value``.

    The relaxation: ``max log det M(w)`` over ``w`` with ``0 <= w <= 1``, ``sum w <= n_max``,
    Lemma 1's distance limits (``limits=True``) and ``w <= visits`` of a convex combination of
    king walks of ``floor(B')`` steps from the start (docs/certificate.md §9). Each design
    ``M`` gives ``log det M + k log(S / k)`` with ``S = ridge tr M^-1 + `` an exact dual bound
    on ``max g.w`` (:class:`_WalkLP`); designs: the disk relaxation's (with the limits), then
    ``rounds`` cvxpy solves over the walks generated so far. Raises :class:`PlanningError`
    for a budget that no nonsingular design fits.
    """
    from .dopt import _Polytope, _relaxation
    from .families import start_limit

    t0 = time.perf_counter()
    Y = as_factor_matrix(Y, region)
    k = Y.shape[0]
    start = region.resolve_cell(start, "start")
    budget = float(budget)
    if not (math.isfinite(budget) and budget >= 0):
        raise PlanningError(f"budget must be >= 0 and finite, got {budget!r}")
    if not (math.isfinite(float(ridge)) and ridge >= 0):
        raise PlanningError(f"ridge must be >= 0 and finite, got {ridge!r}")
    Bp = budget + _DIST_EPS * max(1.0, budget)
    dist = np.asarray(region.distance(start, np.arange(region.n_cells), metric="grid"), float)
    cells = np.flatnonzero(dist <= Bp)
    steps = math.floor(Bp)
    n_max = int(min(cells.size, steps + 1))
    N = cells.size
    levels, caps = [], []
    lim = start_limit(Bp, 1.0, n_max) if limits else None
    if lim is not None:
        levels.append(np.searchsorted(lim[0], dist[cells], side="right"))
        caps.append(lim[1])
    A, b = _count_rows(n_max, levels, caps, N)
    lp = _WalkLP(_KingWalks(region, start, cells, steps), A, b)
    Yc = np.ascontiguousarray(Y[:, cells], dtype=np.float64)

    def evaluate(M: np.ndarray) -> tuple[float, float]:
        L = _chol(M)
        if L is None:
            return math.inf, -math.inf
        Linv = _inv_lower(L)
        g = _leverages(Yc, Linv)
        top, _ = lp.support(g, lp_rounds)
        S = ridge * float((Linv * Linv).sum()) + top
        logdet = 2.0 * float(np.log(np.diag(L)).sum())
        if not (np.isfinite(S) and S > 0):
            return math.inf, logdet
        return logdet + k * math.log(max(S, 1e-300) / k), logdet

    disk = _relaxation(Y, cells, _Polytope(n_max, N, levels, caps), ridge, tol=1e-4)
    hist = []
    best, primal = math.inf, -math.inf
    if math.isfinite(disk.value):
        w0 = disk.weights.toarray()[cells]
        val, _ = evaluate(_moment(Yc, np.arange(N), w0, ridge))
        best = min(best, val)
        hist.append(val)
    used = 0
    for _ in range(rounds):
        w = _solve_walk_cvx(Yc, ridge, A, b, lp.V, n_max)
        if w is None:
            break
        used += 1
        val, ld = evaluate(_moment(Yc, np.arange(N), w, ridge))
        hist.append(val)
        primal = max(primal, ld)
        best = min(best, val)
        if best - primal <= 1e-3:
            break
    if not math.isfinite(best):
        raise PlanningError("the walk relaxation has no nonsingular design (fewer than k cells "
                            "reachable with ridge = 0); use the disk bound")
    return WalkBound(value=float(best), primal=float(primal), n_candidates=int(N),
                     n_max=n_max, walks=int(lp.V.shape[1]), rounds=used,
                     seconds=time.perf_counter() - t0, history=tuple(hist))


def _solve_walk_cvx(Yc: np.ndarray, ridge: float, A: Any, b: np.ndarray, V: np.ndarray,
                    n_max: int) -> np.ndarray | None:
    """``max log det M(w)`` over the walks ``V`` found so far (a restriction of the walk
    relaxation: its design is feasible), congruence-scaled; ``None`` when the solvers fail.
    The returned ``w`` is made feasible for the rows ``A w <= b`` by scaling down."""
    import cvxpy as cp

    k, N = Yc.shape
    m = V.shape[1]
    w0 = np.minimum(1.0, V.mean(axis=1))
    M0 = _moment(Yc, np.arange(N), w0, ridge) + 1e-9 * np.eye(k)
    L0 = _chol(M0)
    if L0 is None:
        return None
    T = _inv_lower(L0)
    Yw = T @ Yc
    F, Esc = _moment_map(Yw)
    C = ridge * (T @ T.T)
    w = cp.Variable(N)
    th = cp.Variable(m)
    Mexpr = cp.reshape(C.ravel() + Esc @ (F @ w), (k, k), order="C")
    cons = [w >= 0, w <= 1, th >= 0, cp.sum(th) == 1, w <= V @ th, A @ w <= b]
    prob = cp.Problem(cp.Maximize(cp.log_det(Mexpr)), cons)
    attempts = [("CLARABEL", o) for o in _CLARABEL_OPTS] + [("SCS", _SCS_OPTS)]
    wv = _solve_in_turn(prob, w, attempts)[0]
    if wv is None:
        return None
    wv = np.clip(wv, 0.0, 1.0)
    wv[wv < 1e-9] = 0.0
    over = A @ wv
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(over > b, b / over, 1.0)
    return wv * min(1.0, float(f.min()) if f.size else 1.0)
