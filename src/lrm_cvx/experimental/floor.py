"""The convex floor: how tight any convex relaxation of the route constraint can be.

The best mixture of found routes is a lower limit on every convex relaxation's bound, so
``floor - I(plan)`` is a gap no convex relaxation can go below (docs/certificate.md §9, "The
convex floor"). Routes come from :mod:`~lrm_cvx.planning.shapes`; the mixture is found by
column generation.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validation import as_factor_matrix, as_generator, check_positive
from ..errors import PlanningError
from ..planning.plan import check_region, path_cumulative
from ..planning.shapes import hill_climb, polyline_route, random_polyline

__all__ = ["ConvexFloor", "convex_floor", "route_mixture"]


@dataclass(frozen=True, eq=False)
class ConvexFloor:
    """The best mixture of routes found (``convex_floor``).

    ``value`` (nats): ``log det(ridge I + sum_j weights_j M_j)``, reached by every convex
    relaxation that contains the routes; ``best_route`` the largest single route's information
    in the pool; ``routes`` the routes with positive weight (cell indices in visiting order)
    and ``weights`` theirs (sum 1); ``pool_gap`` (nats, ``>= 0``) how far ``value`` can be below
    the best mixture *of the pool* (the Frank-Wolfe gap); ``pool`` the number of routes
    considered; ``seconds`` wall time.
    """

    value: float
    best_route: float
    routes: tuple[np.ndarray, ...]
    weights: np.ndarray
    pool_gap: float
    pool: int
    budget: float
    start: int
    seconds: float

    def __repr__(self) -> str:
        return (f"ConvexFloor(value={self.value:.4f}, best_route={self.best_route:.4f}, "
                f"support={len(self.routes)}, pool={self.pool}, pool_gap={self.pool_gap:.2e})")


def _logdet(M: np.ndarray) -> float:
    """``log det M`` (nats), ``-inf`` when ``M`` is singular to working precision (a rank-
    deficient sum of outer products has roundoff eigenvalues, not a meaningful log det)."""
    ev = np.linalg.eigvalsh(0.5 * (M + M.T))
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return -math.inf
    return float(np.log(ev).sum())


def route_mixture(
    moments: np.ndarray, *, ridge: float = 0.0, weights: np.ndarray | None = None,
    max_iter: int = 5000, tol: float = 1e-9,
) -> tuple[np.ndarray, float, float]:
    """Best mixture of route moment matrices: ``max log det(ridge I + sum_j lam_j M_j)`` over
    the simplex.

    ``moments`` ``(m, k, k)`` positive semidefinite. Multiplicative D-optimal updates
    (``lam_j <- lam_j tr(M^-1 M_j) / sum_i lam_i tr(M^-1 M_i)``, a step accepted only if the
    objective does not fall, else halved towards the current weights), from ``weights`` or
    uniform, until the Frank-Wolfe gap ``max_j d_j - sum_j lam_j d_j`` (``d_j =
    tr(M^-1 M_j)``; an upper bound on the suboptimality, by concavity) is below ``tol``.
    Returns ``(weights (m,), value (nats), gap (nats))``; value ``-inf`` if no mixture is
    nonsingular.
    """
    Ms = np.asarray(moments, dtype=np.float64)
    if Ms.ndim != 3 or Ms.shape[1] != Ms.shape[2] or Ms.shape[0] == 0:
        raise PlanningError(f"moments must be a nonempty (m, k, k) array, got shape {Ms.shape}")
    m, k, _ = Ms.shape
    ridge = check_positive(ridge, "ridge", error=PlanningError, numbers_only=True)
    lam = np.full(m, 1.0 / m) if weights is None else np.asarray(weights, dtype=np.float64)
    if lam.shape != (m,) or np.any(lam < 0) or not lam.sum() > 0:
        raise PlanningError(f"weights must be ({m},) nonnegative with a positive sum")
    lam = lam / lam.sum()
    R = ridge * np.eye(k)

    def value_at(lam: np.ndarray) -> tuple[float, np.ndarray]:
        M = R + np.einsum("i,ijk->jk", lam, Ms)
        return _logdet(M), M

    f, M = value_at(lam)
    if not math.isfinite(f):
        lam = np.full(m, 1.0 / m)  # the uniform mixture is nonsingular if any mixture is
        f, M = value_at(lam)
        if not math.isfinite(f):
            return lam, -math.inf, math.inf
    gap = math.inf
    for _ in range(max_iter):
        d = np.einsum("jk,ikj->i", np.linalg.inv(M), Ms)
        gap = float(d.max() - lam @ d)
        if gap <= tol:
            break
        new = lam * d
        new /= new.sum()
        step = 1.0
        while step > 1e-6:
            cand = (1.0 - step) * lam + step * new
            fc, Mc = value_at(cand)
            if fc >= f:
                lam, f, M = cand, fc, Mc
                break
            step /= 2
        else:
            break
    return lam, f, max(gap, 0.0)


def _check_routes(routes: Any, region: Any, start: int, budget: float) -> list[np.ndarray]:
    """Each route as int64 cells: valid (``Region.check_cells``), distinct, from ``start``, of
    path length ``<= budget`` up to the planners' tolerance (``B' = budget + 1e-9 max(1,
    budget)``, which every certificate covers, so a plan's own route is accepted)."""
    limit = budget + 1e-9 * max(1.0, budget)
    out = []
    for j, r in enumerate(routes):
        r = region.check_cells(np.asarray(r).reshape(-1), f"routes[{j}]")
        if r.size == 0 or np.unique(r).size != r.size:
            raise PlanningError(f"routes[{j}] must be a nonempty sequence of distinct cells")
        if int(r[0]) != start:
            raise PlanningError(f"routes[{j}] must begin at the start cell {start}, "
                                f"got {int(r[0])}")
        length = float(path_cumulative(region.grid_index[r])[-1])
        if length > limit:
            raise PlanningError(f"routes[{j}] has path length {length:.6g} > budget {budget:g} "
                                "(grid units, in the given order)")
        out.append(r)
    return out


def convex_floor(
    Y: Any, region: Any, start: Any, budget: float, *, ridge: float = 0.0,
    routes: Any = (), samples: int = 4000, rounds: int = 8, climbs: int = 4,
    random_state: int | np.random.Generator | None = 0, time_limit: float | None = None,
) -> ConvexFloor:
    """The best mixture of routes from ``start`` within ``budget`` (grid units) found by column
    generation: a value every convex relaxation containing the routes reaches (module doc).

    ``Y`` ``(k, L)`` factors (or the model's ``Y_``); ``routes``: extra routes to include (cell
    indices in visiting order from ``start``, checked: distinct valid cells, path length
    ``<= budget``), e.g. ``[plan.route]``. ``samples`` random polylines (1-4 legs) seed the
    pool; each of ``rounds`` prices ``samples // 4`` fresh polylines by ``tr(M^-1 M_P)`` at the
    current mixture, hill-climbs the ``climbs`` best and adds them. ``time_limit`` (s) stops the
    rounds early (the result is still a valid floor: every route in it is feasible).
    """
    t0 = time.perf_counter()
    region = check_region(region)
    Y = as_factor_matrix(Y, region)
    k = Y.shape[0]
    start = region.resolve_cell(start, "start")
    budget = check_positive(budget, "budget", strict=True, error=PlanningError,
                            numbers_only=True)
    ridge = check_positive(ridge, "ridge", error=PlanningError, numbers_only=True)
    for name, v, lo in (("samples", samples, 1), ("rounds", rounds, 0), ("climbs", climbs, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise PlanningError(f"{name} must be an integer >= {lo}, got {v!r}")
    if time_limit is not None:
        time_limit = check_positive(time_limit, "time_limit", strict=True, error=PlanningError,
                                    numbers_only=True)
    rng = as_generator(random_state)
    g = np.asarray(region.grid_index)
    cell_grid = np.asarray(region.cell_grid)
    origin = g[start].astype(np.float64)
    deadline = math.inf if time_limit is None else t0 + float(time_limit)
    Yt = np.ascontiguousarray(Y.T)

    def route_of(pts: list[np.ndarray]) -> np.ndarray:
        return polyline_route(np.asarray(pts), cell_grid, g, budget)

    seen: set[bytes] = set()

    def distinct(rs: list[np.ndarray]) -> list[np.ndarray]:
        """The routes not yet in the pool (a duplicate would only split a weight)."""
        out = []
        for r in rs:
            key = r.tobytes()
            if key not in seen:
                seen.add(key)
                out.append(r)
        return out

    pool = distinct(_check_routes(routes, region, start, budget))
    pool += distinct([route_of(random_polyline(rng, origin, budget, legs=(1, 4)))
                      for _ in range(int(samples))])
    moments = np.stack([Yt[r].T @ Yt[r] for r in pool])
    singles = np.array([_logdet(ridge * np.eye(k) + M) for M in moments])
    lam, value, gap = route_mixture(moments, ridge=ridge)
    for _ in range(int(rounds)):
        if time.perf_counter() > deadline or not math.isfinite(value):
            break
        M = ridge * np.eye(k) + np.einsum("i,ijk->jk", lam, moments)
        q = np.einsum("ij,jk,ik->i", Yt, np.linalg.inv(M), Yt)  # leverage of each cell

        def score(pts: list[np.ndarray], q: np.ndarray = q) -> float:
            return float(q[route_of(pts)].sum())

        cands = [random_polyline(rng, origin, budget, legs=(1, 4))
                 for _ in range(max(1, int(samples) // 4))]
        scores = np.array([score(p) for p in cands])
        new = []
        for j in np.argsort(-scores, kind="stable")[: int(climbs)]:
            _, pts = hill_climb(score, cands[j], scores[j], budget, deadline)
            new.append(route_of(pts))
        new = distinct(new)
        if not new:
            continue
        pool += new
        add = np.stack([Yt[r].T @ Yt[r] for r in new])
        moments = np.concatenate([moments, add])
        singles = np.concatenate([singles, [_logdet(ridge * np.eye(k) + M) for M in add]])
        lam0 = np.concatenate([lam * 0.9, np.full(len(new), 0.1 / len(new))])
        lam, value, gap = route_mixture(moments, ridge=ridge, weights=lam0)
    keep = np.flatnonzero(lam > 1e-6 * lam.max())
    weights = lam[keep] / lam[keep].sum()
    # the value of exactly the mixture returned (dropping negligible weights changes it a hair)
    value = _logdet(ridge * np.eye(k) + np.einsum("i,ijk->jk", weights, moments[keep]))
    return ConvexFloor(
        value=float(value), best_route=float(singles.max()),
        routes=tuple(pool[i] for i in keep), weights=weights,
        pool_gap=float(gap), pool=len(pool), budget=budget, start=int(start),
        seconds=time.perf_counter() - t0,
    )
