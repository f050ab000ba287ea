"""The plan certificate bounds every route of every path model.

Reference: on tiny grids, every set of stops a route within the budget can visit, found by an
exhaustive depth-first search over visiting orders with the exact route cost (travel over a
distance matrix built here, independently of ``planning/paths.py``: Euclidean grid units,
haversine km or hours, or Floyd-Warshall shortest paths over the 8-neighbour graph; the way
back of a closed tour, the leg to ``end``, ``stop_cost`` per stop). The certificate's bound
must be at least the best Fisher information over those sets (the TRUE optimal route cost
decides feasibility, not the planner's heuristic order), and at least the forced initial set's.
"""

from __future__ import annotations

import ast
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import PlanningError
from lrm_cvx.planning import PathOptions
from lrm_cvx.planning.certificate import plan_bound
from lrm_cvx.region import Region

# ----------------------------------------------------------------------------- references


def logdet(Y: np.ndarray, cells, ridge: float) -> float:
    Ys = Y[:, sorted(cells)]
    s, v = np.linalg.slogdet(ridge * np.eye(Y.shape[0]) + Ys @ Ys.T)
    return v if s > 0 else -math.inf


def make_region(ny: int, nx: int, masked=(), lat0: float = 0.0, step: float = 1.0) -> Region:
    mask = np.ones((ny, nx), bool)
    for r, c in masked:
        mask[r, c] = False
    lat = xr.DataArray(lat0 + step * np.arange(ny, dtype=float), dims=("lat",))
    lon = xr.DataArray(10.0 + step * np.arange(nx, dtype=float), dims=("lon",))
    return Region(lat=lat, lon=lon, mask=mask)


def field_Y(region: Region, k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r, c = region.grid_index.T.astype(float)
    modes = [np.ones_like(r)] + [
        np.cos(rng.uniform(0.2, 1.2) * r + rng.uniform(0, 6))
        * np.cos(rng.uniform(0.2, 1.2) * c + rng.uniform(0, 6))
        for _ in range(k - 1)
    ]
    return np.vstack(modes) + 0.1 * rng.standard_normal((k, region.n_cells))


def straight(region: Region, metric: str, speed: float | None) -> np.ndarray:
    """Straight-line distance matrix in the budget's unit."""
    L = region.n_cells
    if metric == "grid":
        p = region.grid_index.astype(float)
        return np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
    a = np.arange(L)
    D = np.asarray(region.distance(a[:, None], a[None, :], metric="km"), dtype=float)
    return D / speed if speed else D


def graph(region: Region, D: np.ndarray) -> np.ndarray:
    """Floyd-Warshall shortest paths over the 8-neighbour graph of the valid cells."""
    p = region.grid_index
    adj = (np.abs(p[:, None, 0] - p[None, :, 0]) <= 1) & (np.abs(p[:, None, 1] - p[None, :, 1])
                                                           <= 1)
    G = np.where(adj, D, np.inf)
    for m in range(region.n_cells):
        G = np.minimum(G, G[:, m:m + 1] + G[m:m + 1, :])
    return G


def route_sets(D: np.ndarray, start: int, budget: float, stop_cost: float = 0.0,
               closed: bool = False, end: int | None = None) -> set[frozenset]:
    """Every set of stops (start and end included) of some route with cost <= budget."""
    tol = 1e-9 * max(1.0, budget)
    out: set[frozenset] = set()
    n_end = 0 if end is None else 1

    def dfs(cur: int, used: list[int], travel: float) -> None:
        n = len(used) + n_end
        if closed:
            total = travel + D[cur, start] + stop_cost * n
        elif end is not None:
            total = travel + D[cur, end] + stop_cost * n
        else:
            total = travel + stop_cost * n
        if total <= budget + tol:
            out.add(frozenset(used + ([end] if end is not None else [])))
        for x in range(D.shape[0]):
            if x in used or x == end:
                continue
            t = travel + D[cur, x]
            if t + stop_cost * (n + 1) <= budget + tol:
                used.append(x)
                dfs(x, used, t)
                used.pop()

    dfs(start, [start], 0.0)
    return out


def nearest(D: np.ndarray, start: int, k: int, end: int | None = None) -> list[int]:
    """The greedy's forced set: start (and end) + the nearest cells (ties: lowest index)."""
    fixed = [start] + ([end] if end is not None else [])
    d = D[start].copy()
    d[fixed] = np.inf
    ok = np.flatnonzero(np.isfinite(d))
    more = ok[np.lexsort((ok, d[ok]))][: max(k - len(fixed), 0)]
    return fixed + more.tolist()


def best_over(Y: np.ndarray, family, ridge: float) -> float:
    return max(logdet(Y, S, ridge) for S in family)


# ----------------------------------------------------------------------------- one robot
MASKED = [(1, 2), (2, 2), (3, 2)]  # a wall: with a travel graph, detours are longer

CASES = {
    # name: (path options, budget, make_D)
    "grid stop_cost": (dict(stop_cost=0.5), 4.0, "straight"),
    "grid closed": (dict(closed=True), 5.0, "straight"),
    "grid end": (dict(end=(2, 4)), 4.5, "straight"),
    "grid closed stop_cost": (dict(closed=True, stop_cost=0.3), 5.0, "straight"),
    "km": (dict(metric="km"), 330.0, "straight"),
    "hours closed": (dict(metric="km", speed=20.0, closed=True), 28.0, "straight"),
    "hours stop_cost end": (dict(metric="km", speed=20.0, stop_cost=1.0, end=(0, 3)), 30.0,
                            "straight"),
    "graph valid": (dict(traversable="valid"), 4.0, "graph"),
    "graph valid closed": (dict(traversable="valid", closed=True), 6.0, "graph"),
    "graph km stop_cost": (dict(traversable="valid", metric="km", stop_cost=30.0), 420.0,
                           "graph"),
}


def _instance(opts: dict, budget: float, kind: str, k: int, seed: int):
    region = make_region(5, 5, masked=MASKED)
    Y = field_Y(region, k, seed)
    start = int(region.cell_grid[2, 1])
    o = dict(opts)
    end = o.pop("end", None)
    end_cell = None if end is None else int(region.cell_grid[end])
    metric, speed = o.get("metric", "grid"), o.get("speed")
    D = straight(region, metric, speed)
    if kind == "graph":
        D = graph(region, D)
    sets = route_sets(D, start, budget, o.get("stop_cost", 0.0), o.get("closed", False),
                      end_cell)
    return region, Y, start, end_cell, o, D, sets


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("k, ridge, seed", [(2, 0.0, 0), (3, 0.05, 1)])
def test_bound_covers_every_route_brute_force(name, k, ridge, seed):
    opts, budget, kind = CASES[name]
    region, Y, start, end, o, D, sets = _instance(opts, budget, kind, k, seed)
    assert len(sets) > 3, "the instance should admit several routes"
    cert = plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6,
                      path=PathOptions(end=end, **o))
    best = best_over(Y, sets, ridge)
    init = nearest(D, start, k, end)
    best_init = logdet(Y, init, ridge)
    assert cert.bound >= best - 1e-7, (name, cert.bound, best)
    assert cert.bound >= best_init - 1e-7
    assert cert.initial_information == pytest.approx(best_init)
    # every feasible stop set lies in the candidates and within the count limit
    union = set().union(*sets)
    assert cert.n_candidates >= len(union)
    assert cert.n_max >= max(len(S) for S in sets)
    assert cert.path["kind"] == "path" and cert.path["n_robots"] == 1
    # the bound is not vacuous: the plain count over all cells is looser or equal
    loose = plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6, tighten=False,
                       path=PathOptions(end=end, **o))
    assert loose.bound >= cert.bound - 1e-6


def test_closed_tour_stops_lie_within_half_the_budget():
    region = make_region(5, 5)
    Y = field_Y(region, 2, 3)
    start = int(region.cell_grid[2, 2])
    budget = 3.0
    cert = plan_bound(Y, region, start, budget, tol=1e-6, path=PathOptions(closed=True))
    open_ = plan_bound(Y, region, start, budget, tol=1e-6, path=PathOptions(stop_cost=1e-12))
    D = straight(region, "grid", None)
    assert cert.n_candidates == int((2 * D[start] <= budget + 1e-9).sum())
    assert open_.n_candidates == int((D[start] <= budget + 1e-9).sum())
    assert cert.n_candidates < open_.n_candidates


def test_closed_tour_distance_limits_hold_on_random_tours():
    """Lemma 1 both ways: a closed tour of length T holds at most floor((T - 2 r)) + 1 cells
    at distance >= r from its start (grid units, distinct integer points)."""
    from lrm_cvx.planning.families import start_limit

    rng = np.random.default_rng(0)
    for _ in range(300):
        m = int(rng.integers(2, 12))
        pts = np.unique(rng.integers(-6, 7, (m, 2)), axis=0)
        pts = pts[np.any(pts != 0, axis=1)]
        tour = np.vstack([[0, 0], pts[rng.permutation(len(pts))], [0, 0]]).astype(float)
        T = float(np.hypot(*np.diff(tour, axis=0).T).sum())
        lim = start_limit(T * (1 + 1e-12), 1.0, len(pts) + 1, ways=2)
        if lim is None:
            continue
        d = np.hypot(pts[:, 0], pts[:, 1])
        counts = (d[:, None] >= lim[0][None, :]).sum(axis=0)
        assert np.all(counts <= lim[1])
        # and the two-way limit is tighter than the one-way one at the same radius
        one = np.floor(T - lim[0]) + 1
        assert np.all(lim[1] <= one)


def test_end_restricts_candidates_to_the_ellipse_and_stop_cost_caps_the_count():
    region = make_region(5, 5)
    Y = field_Y(region, 2, 4)
    start, end = int(region.cell_grid[2, 0]), int(region.cell_grid[2, 4])
    D = straight(region, "grid", None)
    cert = plan_bound(Y, region, start, 5.0, tol=1e-6, path=PathOptions(end=end))
    ellipse = np.flatnonzero(D[start] + D[:, end] <= 5.0 + 1e-9)
    assert cert.n_candidates == ellipse.size
    # stop_cost 2, budget 5: n stops cost 2 n + (n - 1) >= ... -> at most 2 stops
    capped = plan_bound(Y, region, start, 5.0, tol=1e-6, path=PathOptions(stop_cost=2.0))
    assert capped.n_max == 2


def route_orders(D: np.ndarray, start: int, budget: float, closed: bool = False):
    """Every visiting order (start first) of a route with cost <= budget (no stop cost)."""
    tol = 1e-9 * max(1.0, budget)

    def dfs(used: list[int], travel: float):
        back = D[used[-1], start] if closed else 0.0
        if travel + back <= budget + tol:
            yield list(used)
        for x in range(D.shape[0]):
            if x not in used and travel + D[used[-1], x] <= budget + tol:
                used.append(x)
                yield from dfs(used, travel + D[used[-2], x])
                used.pop()

    yield from dfs([start], 0.0)


@pytest.mark.parametrize("closed, budget", [(False, 2.9), (True, 4.2)])
def test_sensing_along_straight_legs_covers_every_route(closed, budget):
    """``sense_along`` without a travel graph observes every cell a leg crosses
    (``plan.line_cells``): more cells than stops, so the count limit is sqrt 2 per unit."""
    from lrm_cvx.planning.plan import line_cells

    region = make_region(5, 6, masked=[(0, 5)])
    Y = field_Y(region, 2, 11)
    start = int(region.cell_grid[2, 2])
    D = straight(region, "grid", None)
    seen: set[frozenset] = set()
    for order in route_orders(D, start, budget, closed):
        legs = list(zip(order[:-1], order[1:], strict=True))
        if closed and len(order) > 1:
            legs.append((order[-1], start))
        cells = set(order)
        for a, b in legs:
            cells.update(line_cells(region, a, b)[0].tolist())
        seen.add(frozenset(cells))
    best = best_over(Y, seen, 0.0)
    if not closed:  # more cells than a stops-only route of this length can hold
        assert max(len(S) for S in seen) > math.floor(budget) + 1
    cert = plan_bound(Y, region, start, budget, tol=1e-6,
                      path=PathOptions(closed=closed, sense_along=True))
    assert cert.bound >= best - 1e-7
    assert cert.n_max >= max(len(S) for S in seen)
    assert cert.n_candidates >= len(set().union(*seen))


# ----------------------------------------------------------------------------- fleet, static
@pytest.mark.parametrize("closed, budgets", [(False, [2.5, 3.0]), (True, [4.0, 5.0])])
def test_fleet_of_two_covers_every_pair_of_routes(closed, budgets):
    region = make_region(5, 5, masked=MASKED)
    k, ridge = 2, 0.0
    Y = field_Y(region, k, 5)
    starts = [int(region.cell_grid[0, 0]), int(region.cell_grid[4, 4])]
    D = straight(region, "grid", None)
    fams = []
    for s, b in zip(starts, budgets, strict=True):
        fams.append(list(route_sets(D, s, b, closed=closed)) + [frozenset(nearest(D, s, k))])
    best = max(logdet(Y, A | B, ridge) for A in fams[0] for B in fams[1])
    cert = plan_bound(Y, region, starts, budgets, ridge=ridge, tol=1e-6,
                      path=PathOptions(closed=closed))
    assert cert.bound >= best - 1e-7
    assert cert.path["n_robots"] == 2
    # the fleet's distance limits (nearest start) only tighten the count-only union bound
    loose = plan_bound(Y, region, starts, budgets, ridge=ridge, tol=1e-6, tighten=False,
                       path=PathOptions(closed=closed))
    assert cert.bound <= loose.bound + 1e-6
    # two robots can do what one does
    assert cert.bound >= best_over(Y, fams[0], ridge) - 1e-7


def test_static_placement_bound_covers_every_placement():
    region = make_region(3, 4)
    k, n = 2, 3
    Y = field_Y(region, k, 6)
    best = max(logdet(Y, S, 0.0) for S in itertools.combinations(range(region.n_cells), n))
    cert = plan_bound(Y, region, None, n, tol=1e-6)  # no start: fixed sensors
    assert cert.bound >= best - 1e-7
    assert cert.n_max == n and cert.n_candidates == region.n_cells
    with pytest.raises(PlanningError, match="number of fixed sensors"):
        plan_bound(Y, region, None, 0)


# ----------------------------------------------------------------------------- planner's plans
PLANS = [
    dict(stop_cost=0.4),
    dict(closed=True),
    dict(end=(4, 3)),
    dict(metric="km", speed=15.0),
    dict(traversable="valid", closed=True),
    dict(traversable="valid", sense_along=True),
    dict(sense_along=True),
    dict(sense_along=True, closed=True, metric="km"),
    dict(metric="km", traversable="valid", sense_along=True, closed=True),
]


@pytest.mark.parametrize("opts", PLANS, ids=lambda o: ",".join(f"{a}={b}" for a, b in o.items()))
def test_certify_bounds_greedy_plans_of_every_model(opts):
    from lrm_cvx.planning import plan_greedy

    region = make_region(6, 6, masked=MASKED)
    Y = field_Y(region, 3, 7)
    o = dict(opts)
    if "end" in o:
        o["end"] = int(region.cell_grid[o["end"]])
    budget = 6.0 if o.get("metric", "grid") == "grid" else (40.0 if "speed" in o else 600.0)
    plan = plan_greedy(Y, region, int(region.cell_grid[2, 1]), budget, ridge=0.01,
                       progress=False, path=PathOptions(**o))
    cert = plan.certify(tol=1e-5)
    assert cert.information == pytest.approx(plan.information)
    assert cert.bound >= plan.information - 1e-7 and cert.gap >= -1e-7
    assert cert.plan_slack is None  # refinement exists for the paper's path only
    assert cert.path["closed"] == bool(o.get("closed", False))


def test_certify_bounds_fleet_and_static_plans():
    from lrm_cvx.planning import place_sensors, plan_greedy

    region = make_region(6, 6, masked=MASKED)
    Y = field_Y(region, 3, 8)
    starts = [int(region.cell_grid[0, 0]), int(region.cell_grid[5, 5])]
    fleet = plan_greedy(Y, region, starts, [5.0, 4.0], ridge=0.01, progress=False,
                        path=PathOptions(closed=True))
    cert = fleet.certify(tol=1e-5)
    assert cert.bound >= fleet.information - 1e-7 and cert.path["n_robots"] == 2
    static = place_sensors(Y, region, 6, ridge=0.01)
    cs = static.certify(tol=1e-5)
    assert cs.path["kind"] == "static" and cs.n_max == 6
    assert cs.bound >= static.information - 1e-7


def test_a_plan_outside_its_model_is_refused():
    from lrm_cvx.planning import plan_greedy

    region = make_region(6, 6)
    Y = field_Y(region, 2, 9)
    start = int(region.cell_grid[2, 2])
    plan = plan_greedy(Y, region, start, 6.0, ridge=0.01, progress=False,
                       path=PathOptions(closed=True))
    # the same cells do not fit a closed tour of half the budget
    with pytest.raises(PlanningError, match="not"):
        plan_bound(Y, region, start, 2.0, ridge=0.01, plan=_with_budget(plan, 2.0))


def _with_budget(plan, budget):
    import copy

    p = copy.copy(plan)
    p.path = dict(plan.path, budgets=[budget])
    p._path_models = None
    return p


def test_bad_path_options():
    region = make_region(4, 4)
    Y = field_Y(region, 2, 0)
    with pytest.raises(PlanningError, match="speed"):
        plan_bound(Y, region, 0, 3.0, path=PathOptions(speed=2.0))
    with pytest.raises(PlanningError, match="closed"):
        plan_bound(Y, region, 0, 3.0, path=PathOptions(closed=True, end=5))
    with pytest.raises(PlanningError, match="budget"):
        plan_bound(Y, region, [0, 5], [3.0, 2.0, 1.0])
    with pytest.raises(PlanningError, match="stop_cost"):
        plan_bound(Y, region, 0, 3.0, path=PathOptions(stop_cost=-1.0))
    with pytest.raises(PlanningError, match="path"):
        plan_bound(Y, region, 0, 3.0, path="teleport")


def test_certificate_modules_do_not_import_the_planner():
    """Data flows one way: paths -> greedy/baselines -> Plan -> certificate. The certificate
    and the relaxation import neither the greedy nor the baselines (refinement, which splits
    the gap of a paper-path plan, is imported when used), and paths.py imports none of them."""
    root = Path(__file__).resolve().parents[1] / "src" / "lrm_cvx" / "planning"
    for name in ("certificate.py", "plan_certificate.py", "cover.py", "towed_certificate.py",
                 "variance_certificate.py", "dopt.py", "relaxation.py", "paths.py"):
        tree = ast.parse((root / name).read_text())
        anywhere = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        top = {n.module or "" for n in tree.body if isinstance(n, ast.ImportFrom)}
        assert not anywhere & {"greedy", "baselines"}, (name, anywhere)
        assert not top & {"plan", "refine", "bound", "certificate"} - {name[:-3]}, (name, top)
