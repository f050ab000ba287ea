"""Plan refinement: a local search that raises a plan's information within its budget.

Insert and swap moves, with route repair after every accepted move; a move is accepted only when
the information rises strictly and the exact path cost stays within the budget. The start cell
is never moved (docs/planning.md, "Refinement").
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .._validation import as_factor_matrix
from ..errors import PlanningError
from ..information import fisher_set_value
from .plan import Plan, check_region, is_paper_path
from .refiners import REFINERS, RefineContext
from .routecost import (
    NearestNeighborCost,
    insertion_costs,
    nearest_neighbor_tour,
    repair_route,
    route_length,
)
from .terms import PriorTerms, prior_terms

__all__ = ["refine"]

_TOL = 1e-9  # budget tolerance, as in the greedy
_EPS = 1e-9  # strict improvement (nats)
_CHUNK = 4096


class _Fisher:
    """``log det(M0 + sum_P yw yw^T)`` (plain: ``M0 = ridge I``; posterior: a prior precision
    and per-cell noise), with the closed-form information of swaps and insertions."""

    def __init__(self, Y: np.ndarray, ridge: float, prior_precision: Any, noise_var: Any):
        k, L = Y.shape
        self.Y, self.ridge = Y, float(ridge)
        self.kw: dict[str, Any] = {}
        if noise_var is not None:
            nv = np.broadcast_to(np.asarray(noise_var, float), (L,))
            if not np.all(np.isfinite(nv)) or np.any(nv <= 0):
                raise PlanningError(f"noise_var must be a positive scalar or ({L},) array")
            self.Yw = np.ascontiguousarray(Y / np.sqrt(nv))
            self.kw["noise_var"] = noise_var
        else:
            self.Yw = Y
        if prior_precision is not None:
            M0 = np.asarray(prior_precision, float)
            if M0.shape != (k, k) or not np.all(np.isfinite(M0)):
                raise PlanningError(f"prior_precision must be a finite ({k}, {k}) matrix")
            self.M0 = 0.5 * (M0 + M0.T)
            self.kw["prior_precision"] = prior_precision
        else:
            self.M0 = self.ridge * np.eye(k)

    def value(self, cells: np.ndarray) -> float:
        return float(fisher_set_value(self.Y, cells, self.ridge, **self.kw))

    def inverse(self, cells: np.ndarray) -> np.ndarray | None:
        Yp = self.Yw[:, cells]
        M = self.M0 + Yp @ Yp.T
        try:
            S = np.linalg.inv(M)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(S)) or np.linalg.cond(M) > 1e13:
            return None
        return 0.5 * (S + S.T)

    def leverages(self, S: np.ndarray, cand: np.ndarray) -> np.ndarray:
        out = np.empty(cand.size)
        for a in range(0, cand.size, _CHUNK * 16):
            Yc = self.Yw[:, cand[a:a + _CHUNK * 16]]
            out[a:a + Yc.shape[1]] = np.einsum("ij,ij->j", Yc, S @ Yc)
        return out


# ----------------------------------------------------------------------------- refine
def _shortlist(g: np.ndarray, pool: np.ndarray, in_plan: np.ndarray, lev: np.ndarray,
               cells: np.ndarray, size: int, radius: float) -> np.ndarray:
    """Positions in ``pool``: the ``size`` largest leverages plus every cell within
    ``radius`` of a plan cell (not in the plan)."""
    free = np.flatnonzero(~in_plan)
    if free.size == 0:
        return free
    top = free[np.argsort(-lev[free], kind="stable")[:size]]
    near = np.zeros(0, np.int64)
    if radius > 0:
        from scipy.spatial import cKDTree

        tree = cKDTree(g[pool[free]].astype(np.float64))
        hits = tree.query_ball_point(g[cells].astype(np.float64), radius + 1e-9)
        if len(hits):
            near = free[np.unique(np.concatenate([np.asarray(h, np.int64) for h in hits]))]
    return np.union1d(top, near)


def refine(
    plan: Plan,
    Y: Any = None,
    region: Any = None,
    *,
    max_rounds: int = 200,
    shortlist: int = 256,
    radius: float = 2.0,
    time_limit: float = 55.0,
    refill: int = 8,
    restart: bool = True,
    kicks: int = 10,
    restarts: int = 1,
    shapes: int = 2000,
    climbs: int = 8,
    seed: int | None = 0,
    prior: Any = None,
) -> Plan:
    """Local search on ``plan`` (insert / swap stops, route repair) that raises its Fisher
    information and keeps its exact path cost within ``plan.budget``.

    Parameters
    ----------
    plan : a greedy :class:`Plan` (criterion ``"fisher"``; a posterior-Fisher plan needs its
        ``prior``). Its cost model (``plan.cost_function``) is kept:
        ``"nearest-neighbor"`` (the cost of a set is its nearest-neighbour tour from the start)
        or ``"insertion"`` (the cost is the length of the kept route, repaired by 2-opt and
        Or-opt after every move).
    Y, region : the model's ``(k, L)`` factors and region; default: the plan's own.
    max_rounds : at most this many accepted moves.
    shortlist : swap candidates = this many cells of largest leverage ``y^T M^-1 y`` plus every
        cell within ``radius`` (grid units) of a plan cell.
    time_limit : seconds; the search stops (keeping the best plan so far) when exceeded.
    refill : when no insertion or swap helps, try this many "drop and refill" moves per round:
        remove a stop (smallest information loss first), then add shortlisted cells greedily
        (the greedy's ratio, exact costs) while they fit; kept if the information rises.
    restart : also run the greedy from the start cell alone (``initial="start"``, a ridge of
        1e-9 of the mean ``|y|^2`` only to rank the first picks) and start the search from it
        when its exact information is higher and its cost fits: this rescues plans whose
        forced initial set already exceeds the budget (tiny budgets).
    kicks : after the local search converges, this many perturbations (iterated local search):
        remove a random stretch of 5-20% of the route's stops, refill greedily (the removed
        cells excluded), search again; the result is kept only when it beats the best plan.
    restarts : independent chains of ``kicks`` kicks (iterated local search restarted from the
        local optimum, chain ``j`` seeded with ``seed + j``; the time left is split evenly); the
        best plan over all chains is kept.
    shapes : after the local search converges, score this many random polyline routes from the
        start (2-4 legs, :func:`~lrm_cvx.planning.shapes.search_shapes`; at most 10 per square
        grid unit of budget, as few distinct shapes fit a small one), hill-climb the best
        ``climbs`` of them (moving and inserting waypoints), and run the local search from the
        best route found; it replaces the plan when it ends higher. A global move: on smooth
        fields the best route's shape (an L, a hook, a loop) can be far from the greedy's.
        Uses at most a third of ``time_limit``; 0 skips it.
    climbs : how many of the best shapes are hill-climbed.
    seed : seeds the kicks and the shapes (``numpy.random.default_rng``); the result is
        deterministic given it (and a ``time_limit`` that is not reached).
    prior : the prior of a posterior-Fisher plan, as :func:`~lrm_cvx.planning.plan_greedy` takes
        it (a belief or a :class:`~lrm_cvx.planning.terms.PriorTerms`; its ``prior_precision``
        and ``noise_var`` are read).

    Returns a new :class:`Plan` (``method`` unchanged) whose ``information`` is ``>=`` the
    input's and ``cost <= budget + 1e-9`` (or the input itself when no move helped), with
    ``refinement = {"information_before", "information_after", "criterion_before",
    "criterion_after", "moves", "inserted", "swapped", "restarted", "refilled", "kicks",
    "shapes", "rounds", "seconds"}`` and history keys ``refine_move`` (1 insert, 2 swap, 3 restart,
    4 drop-and-refill, 5 kick, 6 shape), ``refine_cell_in``, ``refine_cell_out``, ``refine_value``
    (criterion after each move).
    """
    if not isinstance(plan, Plan):
        raise PlanningError(f"plan must be a Plan, got {type(plan).__name__}")
    region = check_region(plan._region if region is None else region)
    Y = plan._Y if Y is None else Y
    if Y is None:
        raise PlanningError("Y is required: the plan has no model attached")
    Yk = as_factor_matrix(Y, region)
    if plan.criterion not in ("fisher",):
        raise PlanningError(
            f"refine supports Fisher plans (criterion 'fisher'), got criterion="
            f"{plan.criterion!r}")
    terms = prior_terms(prior)
    prior_precision, noise_var = terms["prior_precision"], terms["noise_var"]
    if plan.posterior and prior_precision is None and noise_var is None:
        raise PlanningError("this plan's Fisher criterion is on the fold-in's posterior: "
                            "pass its prior (prior=) to refine it")
    if not is_paper_path(plan.path):
        raise PlanningError(
            "refine supports only the paper's path model (one robot, metric 'grid', no "
            "traversable, not closed, no end, stop_cost 0, no sense_along, not static); "
            f"this plan's path is {plan.path.get('kind')!r} with {plan.path.get('n_robots')} "
            f"robot(s), metric {plan.path.get('metric')!r}, traversable "
            f"{plan.path.get('traversable')!r}, closed={plan.path.get('closed')}")
    if plan.cost_function not in ("nearest-neighbor", "insertion"):
        raise PlanningError(f"cannot refine a plan with cost {plan.cost_function!r}")
    for name, v in (("max_rounds", max_rounds), ("shortlist", shortlist), ("refill", refill),
                    ("kicks", kicks), ("shapes", shapes), ("climbs", climbs)):
        if not isinstance(v, (int, np.integer)) or v < 0:
            raise PlanningError(f"{name} must be an integer >= 0, got {v!r}")
    if isinstance(restarts, bool) or not isinstance(restarts, (int, np.integer)) \
            or restarts < 1:
        raise PlanningError(f"restarts must be an integer >= 1, got {restarts!r}")
    if not np.isfinite(radius) or radius < 0 or not time_limit > 0:
        raise PlanningError("radius must be >= 0 and time_limit > 0")

    t0 = time.perf_counter()
    g = np.ascontiguousarray(region.grid_index, dtype=np.int64)
    budget = float(plan.budget)
    limit = budget + _TOL
    nn = plan.cost_function == "nearest-neighbor"
    crit = _Fisher(Yk, plan.ridge, prior_precision, noise_var)
    start = int(plan.start)
    cells = np.asarray(plan.cells, dtype=np.int64)
    if cells.size == 0 or cells[0] != start:
        cells = np.concatenate([[start], cells[cells != start]])
    route = np.asarray(plan.route, dtype=np.int64)
    from .greedy import budget_pool

    pool = budget_pool(region, start, budget)
    value = crit.value(cells)
    before = value
    cost = float(plan.cost)
    if not nn:  # a route: repair it first (only ever shortens it)
        r = repair_route(g, route)
        if route_length(g, r) < cost:
            route, cost = r, route_length(g, r)
    moves: list[tuple[int, int, int, float]] = []
    if restart and len(cells) > 1:
        alt = _restart(Yk, region, start, budget, plan, crit)
        if alt is not None and alt[2] <= limit and alt[3] > value + _EPS:
            cells, route, cost, value = alt
            moves.append((3, -1, -1, value))
    deadline = t0 + time_limit
    ls = dict(g=g, pool=pool, limit=limit, nn=nn, crit=crit, size=shortlist, radius=radius,
              start=start, refill=refill, deadline=deadline)
    (cells, route, cost, value), found, rounds = _search((cells, route, cost, value), max_rounds,
                                                         **ls)
    moves += found
    if shapes and len(moves) < max_rounds:
        shaped = _shape_restart(region, shapes, climbs, seed, time_limit, **ls)
        if shaped is not None and shaped[3] > value + _EPS:
            state, found, r = _search(shaped, max_rounds - len(moves) - 1, **ls)
            rounds += r
            cells, route, cost, value = state
            moves.append((6, -1, -1, shaped[3]))
            moves += found
    # iterated local search: ``restarts`` independent chains of ``kicks`` kicks, each from the
    # local optimum above, the remaining time split evenly; the best plan over all is kept
    local = (cells, route, cost, value)
    t_kick = time.perf_counter()
    for j in range(restarts if kicks else 0):
        rng = np.random.default_rng(seed if j == 0 or seed is None else seed + j)
        chain_end = min(deadline, t_kick + (j + 1) * (deadline - t_kick) / restarts)
        cur = local
        for _ in range(kicks):
            if time.perf_counter() > chain_end or len(moves) >= max_rounds:
                break
            kicked = _kick(cur, rng, **ls)
            if kicked is None:
                continue
            state, found, r = _search(kicked, max_rounds - len(moves), **ls)
            rounds += r
            if state[2] <= limit and state[3] > cur[3] + _EPS:
                cur = state
                if state[3] > value + _EPS:
                    cells, route, cost, value = state
                    moves.append((5, -1, -1, value))
    if not moves and cost == plan.cost:
        return plan
    info = float(fisher_set_value(Yk, cells, plan.ridge))
    hist = dict(plan.history)
    hist["refine_move"] = np.array([m[0] for m in moves], dtype=np.int64)
    hist["refine_cell_in"] = np.array([m[1] for m in moves], dtype=np.int64)
    hist["refine_cell_out"] = np.array([m[2] for m in moves], dtype=np.int64)
    hist["refine_value"] = np.array([m[3] for m in moves], dtype=np.float64)
    out = Plan.build(
        region=region, cells=cells, route=route, cost=cost, information=info,
        criterion=plan.criterion, budget=budget, start=start, ridge=plan.ridge,
        method=plan.method, history=hist, cost_function=plan.cost_function, Y=Yk,
        posterior=plan.posterior,
    )
    out.refinement = {
        "information_before": float(plan.information),
        "information_after": info,
        "criterion_before": float(before),
        "criterion_after": float(value),
        "moves": len(moves),
        "inserted": int(sum(m[0] == 1 for m in moves)),
        "swapped": int(sum(m[0] == 2 for m in moves)),
        "restarted": int(sum(m[0] == 3 for m in moves)),
        "refilled": int(sum(m[0] == 4 for m in moves)),
        "kicks": int(sum(m[0] == 5 for m in moves)),
        "shapes": int(sum(m[0] == 6 for m in moves)),
        "rounds": rounds,
        "seconds": time.perf_counter() - t0,
    }
    return out


def _best_insert(g, pool, in_plan, lev, cells, route, cost, limit, value, nn, crit):
    """The feasible insertion of largest gain per unit cost increase (the greedy's ratio),
    verified from scratch; ``None`` when none raises the information."""
    free = np.flatnonzero(~in_plan)
    if free.size == 0:
        return None
    gain = np.log1p(lev[free])
    if nn:
        coster = NearestNeighborCost(g, cells, pool[free])
        new_cost = coster.cost + coster.increases()
    else:
        inc, pos = insertion_costs(g, route, pool[free])
        new_cost = cost + inc
    ok = (new_cost <= limit) & (gain > _EPS)
    if not ok.any():
        return None
    dc = new_cost - cost
    ratio = np.where(ok, gain / np.maximum(dc, 1e-12), -np.inf)
    for b in np.argsort(-ratio, kind="stable")[:8]:
        if not ok[b]:
            break
        x = int(pool[free[b]])
        new_cells = np.append(cells, x)
        c, r = _exact_route(g, new_cells, None if nn else np.insert(route, int(pos[b]) + 1, x))
        v = crit.value(new_cells)
        if c <= limit and v > value + _EPS:
            return 1, x, -1, new_cells, r, c, v
    return None


def _best_swap(g, pool, in_plan, lev, S, cells, route, limit, value, nn, crit, size, radius,
               start):
    """The feasible swap ``P - x + y`` of largest information (closed form over every pair of
    stops ``x`` and shortlisted ``y``, exact costs by one incremental oracle per ``x``),
    verified from scratch; ``None`` when none raises the information."""
    short = _shortlist(g, pool, in_plan, lev, cells, size, radius)
    if short.size == 0:
        return None
    ys = pool[short]
    Yw = crit.Yw
    Yp = Yw[:, cells]
    SYp = S @ Yp
    q = np.einsum("ij,ij->j", Yp, SYp)  # leverages of the stops (< 1)
    A = Yw[:, ys].T @ SYp  # (ny, m)
    g0 = lev[short]
    removable = (cells != start) & (q < 1 - 1e-10)
    best = None
    order = np.argsort(q, kind="stable")  # cheapest removals first
    for xi in order:
        if not removable[xi]:
            continue
        loss = np.log1p(-q[xi])  # I(P - x) - I(P), <= 0
        gain = np.log1p(g0 + A[:, xi] ** 2 / (1.0 - q[xi]))
        new_val = value + loss + gain
        target = value + _EPS if best is None else best[6] + _EPS
        cand = np.flatnonzero(new_val > target)
        if cand.size == 0:
            continue
        rest = np.delete(cells, xi)
        if nn:
            coster = NearestNeighborCost(g, rest, ys[cand])
            new_cost = coster.cost + coster.increases()
        else:
            r0 = route[route != cells[xi]]
            inc, pos = insertion_costs(g, r0, ys[cand])
            new_cost = route_length(g, r0) + inc
        ok = np.flatnonzero(new_cost <= limit)
        if ok.size == 0:
            continue
        for b in ok[np.argsort(-new_val[cand[ok]], kind="stable")][:4]:
            y = int(ys[cand[b]])
            new_cells = np.append(rest, y)
            c, r = _exact_route(g, new_cells, None if nn else np.insert(r0, int(pos[b]) + 1, y))
            v = crit.value(new_cells)
            if c <= limit and v > target:
                best = (2, y, int(cells[xi]), new_cells, r, c, v)
                break
    return best


def _restart(Yk, region, start, budget, plan, crit):
    """``(cells, route, cost, value)`` of the greedy from the start cell alone, or ``None``."""
    from .greedy import plan_greedy

    guide = 1e-9 * float(np.mean(np.sum(crit.Yw * crit.Yw, axis=0))) + plan.ridge
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            alt = plan_greedy(crit.Yw, region, start, budget, ridge=guide, initial="start",
                              cost=plan.cost_function, progress=False)
    except PlanningError:
        return None
    cells = np.asarray(alt.cells, dtype=np.int64)
    return cells, np.asarray(alt.route, np.int64), float(alt.cost), crit.value(cells)


def _best_refill(g, pool, in_plan, lev, S, cells, route, limit, value, nn, crit, size, radius,
                 start, tries):
    """Drop a stop and refill greedily (ratio of gain to exact cost increase) from the
    shortlist; the first that raises the information, verified from scratch."""
    if tries <= 0:
        return None
    short = _shortlist(g, pool, in_plan, lev, cells, size, radius)
    if short.size == 0:
        return None
    ys = pool[short]
    Yp = crit.Yw[:, cells]
    q = np.einsum("ij,ij->j", Yp, S @ Yp)
    removable = np.flatnonzero((cells != start) & (q < 1 - 1e-10))
    for xi in removable[np.argsort(q[removable], kind="stable")][:tries]:
        rest = np.delete(cells, xi)
        Sx = crit.inverse(rest)
        if Sx is None:
            continue
        r = route[route != cells[xi]]
        new_cells, rr, c = _fill(g, rest, r, ys, limit, nn, crit, Sx)
        if new_cells.size <= rest.size:
            continue
        v = crit.value(new_cells)
        if c <= limit and v > value + _EPS:
            return 4, int(new_cells[-1]), int(cells[xi]), new_cells, rr, c, v
    return None


def _search(state, max_rounds, *, g, pool, limit, nn, crit, size, radius, start, refill,
            deadline):
    """Best-improvement local search from ``state = (cells, route, cost, value)``: insert, then
    swap, then drop-and-refill, until none improves. Returns ``(state, moves, rounds)``."""
    cells, route, cost, value = state
    moves: list[tuple[int, int, int, float]] = []
    rounds = 0
    while len(moves) < max_rounds and time.perf_counter() < deadline:
        rounds += 1
        S = crit.inverse(cells)
        if S is None:
            break
        in_plan = np.isin(pool, cells)
        lev = crit.leverages(S, pool)
        move = _best_insert(g, pool, in_plan, lev, cells, route, cost, limit, value, nn, crit)
        if move is None:
            move = _best_swap(g, pool, in_plan, lev, S, cells, route, limit, value, nn, crit,
                              size, radius, start)
        if move is None:
            move = _best_refill(g, pool, in_plan, lev, S, cells, route, limit, value, nn, crit,
                                size, radius, start, refill)
        if move is None:
            break
        kind, cin, cout, cells, route, cost, value = move
        moves.append((kind, cin, cout, value))
    return (cells, route, cost, value), moves, rounds


def _shape_restart(region, samples, climbs, seed, time_limit, *, g, start, limit, nn, crit,
                   deadline, **_):
    """The best polyline route (:mod:`.shapes`) as a feasible ``(cells, route, cost, value)``
    under the plan's cost (for a nearest-neighbour plan every route is cut to a prefix whose
    tour fits), or ``None``. Searches for at most a third of ``time_limit``."""
    from .shapes import search_shapes

    stop = min(deadline, time.perf_counter() + time_limit / 3)
    samples = min(samples, 10 * math.ceil(limit) ** 2)  # few distinct shapes fit a small budget
    fits = (lambda cells: nearest_neighbor_tour(g, cells)[0] <= limit) if nn else None
    found = search_shapes(crit.value, region.cell_grid, g, start, limit, samples=samples,
                          climbs=climbs, rng=np.random.default_rng(seed), deadline=stop,
                          fits=fits)
    if found is None:
        return None
    route = found[0]
    c, rr = _exact_route(g, route, None if nn else route)
    return (route, rr, c, crit.value(route)) if c <= limit else None


def _kick(state, rng, *, g, pool, limit, nn, crit, size, radius, start, **_):
    """Remove a random stretch of the route (not the start) and refill greedily without the
    removed cells: ``(cells, route, cost, value)`` of a feasible plan, or ``None``."""
    cells, route, cost, value = state
    m = route.size
    if m < 3:
        return None
    n_out = max(1, int(round(rng.uniform(0.05, 0.2) * (m - 1))))
    a = int(rng.integers(1, m - n_out + 1))
    out = route[a:a + n_out]
    rest_route = np.concatenate([route[:a], route[a + n_out:]])
    rest = cells[~np.isin(cells, out)]
    S = crit.inverse(rest)
    if S is None:
        return None
    free = ~np.isin(pool, cells)
    lev = crit.leverages(S, pool)
    short = _shortlist(g, pool, ~free, lev, rest, size, radius)
    ys = pool[short]
    filled = _fill(g, rest, rest_route, ys, limit, nn, crit, S)
    if filled is None:
        return None
    new_cells, r, c = filled
    if c > limit:
        return None
    return new_cells, r, c, crit.value(new_cells)


def _fill(g, rest, r, ys, limit, nn, crit, Sx):
    """Add cells of ``ys`` to ``rest`` greedily (gain / exact cost increase) while they fit:
    ``(cells, route, cost)`` (route exact: the NN tour, or the repaired route)."""
    if nn:
        coster = NearestNeighborCost(g, rest, ys)
        cur = coster.cost
    else:
        cur = route_length(g, r)
    active = np.ones(ys.size, dtype=bool)
    new_cells = rest
    Yc = crit.Yw[:, ys]
    while True:
        gain = np.log1p(np.einsum("ij,ij->j", Yc, Sx @ Yc))
        if nn:
            dc = coster.increases()
        else:
            dc, pos = insertion_costs(g, r, ys)
        ok = active & (cur + dc <= limit) & (gain > _EPS)
        if not ok.any():
            break
        ratio = np.where(ok, gain / np.maximum(np.where(ok, dc, 1.0), 1e-12), -np.inf)
        b = int(np.argmax(ratio))
        y = int(ys[b])
        active[b] = False
        new_cells = np.append(new_cells, y)
        u = Sx @ crit.Yw[:, y]
        Sx = Sx - np.outer(u, u) / (1.0 + float(crit.Yw[:, y] @ u))
        if nn:
            coster.add(y)
            cur = coster.cost
        else:
            r = np.insert(r, int(pos[b]) + 1, y)
            cur = route_length(g, r)
    c, rr = _exact_route(g, new_cells, None if nn else r)
    return new_cells, rr, c


def _exact_route(g: np.ndarray, cells: np.ndarray, route: np.ndarray | None
                 ) -> tuple[float, np.ndarray]:
    """``(cost, route)`` of a plan's cells under its cost: the nearest-neighbour tour of
    ``cells`` (``route`` None), else ``route`` repaired by 2-opt and Or-opt."""
    if route is None:
        return nearest_neighbor_tour(g, cells)
    r = repair_route(g, route)
    return route_length(g, r), r


def refine_plan(plan: Plan, options: bool | dict[str, Any], context: RefineContext) -> Plan:
    """:func:`refine` of ``plan`` with ``options`` (True or a dict of its keyword arguments),
    a posterior plan's ``prior_precision`` / ``noise_var`` taken from ``context.terms`` (the
    greedy's resolved prior terms) unless a ``prior`` is given: ``plan_greedy(refine=...)`` and
    :class:`~lrm_cvx.planning.planners.Refined`."""
    opts = dict(options) if isinstance(options, dict) else {}
    if plan.posterior and opts.get("prior") is None:
        opts["prior"] = PriorTerms(prior_precision=context.terms.get("prior_precision"),
                                   noise_var=context.terms.get("noise_var"))
    return refine(plan, **opts)


REFINERS.register("local", refine_plan, description="insert / swap / refill / kick / shape local "
                  "search on the paper's path model (refine)")
