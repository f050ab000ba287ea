"""The greedy planner against a naive implementation that recomputes everything from scratch."""

import math
import warnings
from itertools import pairwise

import numpy as np
import pytest
import xarray as xr
from references import naive_tour

from lrm_cvx import Region
from lrm_cvx.errors import DataError, PlanningError, RegionError
from lrm_cvx.information import fisher_information
from lrm_cvx.planning import initial_cells, plan_greedy
from lrm_cvx.planning.routecost import nearest_neighbor_tour


# --------------------------------------------------------------------------- references
def logdet(Y, cells, ridge):
    sign, value = np.linalg.slogdet(ridge * np.eye(Y.shape[0]) + Y[:, cells] @ Y[:, cells].T)
    return value if sign > 0 else -np.inf


def neg_total_variance(Y, cells, ridge):
    M = ridge * np.eye(Y.shape[0]) + Y[:, cells] @ Y[:, cells].T
    return -np.trace(np.linalg.solve(M, Y @ Y.T))


def naive_greedy(Y, g, start, budget, criterion, ridge, cost, exponent=1.0):
    """The paper's algorithm literally: every cell, every tour and every criterion value
    recomputed from scratch at every iteration (the ratio's cost raised to ``exponent``)."""
    k, L = Y.shape
    d2 = ((g - g[start]) ** 2).sum(1)
    P = [int(c) for c in np.lexsort((np.arange(L), d2))[:k]]
    value = logdet if criterion == "fisher" else neg_total_variance
    route = naive_tour(g, P)[1]

    def length(r):
        return math.fsum(math.dist(g[a], g[b]) for a, b in pairwise(r))

    while True:
        i0 = value(Y, P, ridge)
        c0 = naive_tour(g, P)[0] if cost == "nearest-neighbor" else length(route)
        best = None
        for x in range(L):
            if x in P:
                continue
            pos = None
            if cost == "nearest-neighbor":
                c1 = naive_tour(g, P + [x])[0]
            else:  # every insertion position, route lengths from scratch
                options = [length(route[: i + 1] + [x] + route[i + 1:]) for i in range(len(route))]
                pos = int(np.argmin(options))
                c1 = options[pos]
            if c1 > budget + 1e-9:
                continue
            ratio = (value(Y, P + [x], ridge) - i0) / max(c1 - c0, 1e-12) ** exponent
            if best is None or ratio > best[0]:
                best = (ratio, x, pos)
        if best is None or not best[0] > 0:
            return P, route
        P.append(best[1])
        if cost == "insertion":
            route.insert(best[2] + 1, best[1])


def make_region(mask, lat_descending=False):
    ny, nx = mask.shape
    lat = np.arange(ny, dtype=float)[::-1] if lat_descending else np.arange(ny, dtype=float)
    return Region(
        lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
        lon=xr.DataArray(np.arange(nx, dtype=float) + 10, dims="lon",
                         coords={"lon": np.arange(nx, dtype=float) + 10}),
        mask=mask,
    )


# --------------------------------------------------------------------------- initial set
def test_initial_cells_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(50):
        mask = rng.random((7, 9)) < 0.7
        mask[3, 4] = True
        region = make_region(mask)
        g = region.grid_index
        start = int(rng.integers(region.n_cells))
        k = int(rng.integers(1, min(region.n_cells, 8) + 1))
        d2 = ((g - g[start]) ** 2).sum(1)
        ref = sorted(range(region.n_cells), key=lambda c: (d2[c], c))[:k]
        got = initial_cells(region, start, k)
        assert got[0] == start and got.tolist() == ref
    with pytest.raises(PlanningError, match="fewer than the rank"):
        initial_cells(make_region(np.eye(3, dtype=bool)), 0, 4)


def test_initial_cells_ties_to_lowest_index():
    region = make_region(np.ones((5, 5), dtype=bool))
    # centre (2,2) = cell 12; its 4 neighbours at distance 1: cells 7, 11, 13, 17
    assert initial_cells(region, 12, 3).tolist() == [12, 7, 11]
    assert initial_cells(region, 12, 6).tolist() == [12, 7, 11, 13, 17, 6]


# --------------------------------------------------------------------------- equality with naive
def test_greedy_equals_naive_on_random_instances():
    rng = np.random.default_rng(12345)
    n_runs = 0
    seen = set()
    picks = 0
    for _ in range(130):
        ny, nx = (int(v) for v in rng.integers(3, 21, 2))
        mask = rng.random((ny, nx)) < rng.uniform(0.6, 1.0)
        if mask.sum() < 8:
            continue
        region = make_region(mask, lat_descending=bool(rng.random() < 0.5))
        k = int(rng.integers(2, 6))
        Y = rng.standard_normal((k, region.n_cells))
        start = int(rng.integers(region.n_cells))
        budget = float(rng.choice([0.0, 2.0, 3.5, 5.0, 8.0, 12.0, 20.0, 30.0]))
        criterion = str(rng.choice(["fisher", "a-optimal"]))
        cost = str(rng.choice(["nearest-neighbor", "insertion"]))
        ridge = 1e-3 if criterion == "a-optimal" or rng.random() < 0.3 else 0.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # initial cells over a tiny budget
            plan = plan_greedy(Y, region, start, budget, criterion=criterion, cost=cost,
                               ridge=ridge, progress=False)
        ref, ref_route = naive_greedy(Y, region.grid_index, start, budget, criterion, ridge, cost)
        assert plan.cells.tolist() == ref, (criterion, cost, budget)
        if cost == "insertion":
            assert plan.route.tolist() == ref_route
        else:
            assert plan.route.tolist() == naive_tour(region.grid_index, ref)[1]
        if len(ref) > k:
            assert plan.cost <= budget + 1e-9
        n_runs += 1
        seen.add((criterion, cost))
        picks += len(ref) - k
    assert n_runs >= 100 and len(seen) == 4 and picks > 500


# --------------------------------------------------------------------------- plan contents
@pytest.fixture
def problem():
    rng = np.random.default_rng(3)
    mask = rng.random((15, 18)) < 0.85
    mask[7, 9] = True
    region = make_region(mask, lat_descending=True)
    Y = rng.standard_normal((3, region.n_cells))
    start = int(region.cell_grid[7, 9])
    return Y, region, start


def test_plan_contents(problem):
    Y, region, start = problem
    plan = plan_greedy(Y, region, start, 25.0, progress=False)
    cost, order = nearest_neighbor_tour(region.grid_index, plan.cells)
    assert plan.start == start and plan.cells[0] == start
    assert plan.cells[:3].tolist() == initial_cells(region, start, 3).tolist()
    assert plan.route.tolist() == order.tolist() and plan.cost == cost <= 25.0 + 1e-9
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells))
    assert len(np.unique(plan.cells)) == len(plan) > 3
    h = plan.history
    assert h["cell"].tolist() == plan.cells[3:].tolist()
    # the Fisher gains add up to the information gained beyond the initial set
    assert h["gain"].sum() == pytest.approx(
        plan.information - fisher_information(Y, plan.cells[:3]), rel=1e-9)
    np.testing.assert_allclose(h["ratio"], h["gain"] / np.maximum(h["cost_increase"], 1e-12))
    assert h["cost"][-1] == pytest.approx(plan.cost)
    np.testing.assert_array_equal(plan.lat, region.cell_lat[plan.route])
    np.testing.assert_array_equal(plan.grid_index, region.grid_index[plan.route])
    assert plan.method == "greedy" and plan.criterion == "fisher"
    # no feasible cell is left with a positive ratio: adding any cell breaks the budget
    P = list(plan.cells)
    for x in range(region.n_cells):
        if x not in P:
            assert nearest_neighbor_tour(region.grid_index, P + [x])[0] > 25.0 + 1e-9


def test_plan_inputs_as_dataarrays_and_latlon_start(problem):
    Y, region, start = problem
    ref = plan_greedy(Y, region, start, 10.0, progress=False)
    da_cell = xr.DataArray(Y, dims=("component", "cell"))
    grid = region.unstack(Y, dims=("component",))  # (component, lat, lon), NaN off-region
    latlon = (float(region.cell_lat[start]), float(region.cell_lon[start]))
    for Yin, s in ((da_cell, start), (grid, latlon)):
        plan = plan_greedy(Yin, region, s, 10.0, progress=False)
        assert plan.cells.tolist() == ref.cells.tolist() and plan.start == start


def test_budget_below_initial_cost_warns_and_returns_initial_set(problem):
    Y, region, start = problem
    with pytest.warns(UserWarning, match="initial cells"):
        plan = plan_greedy(Y, region, start, 0.0, progress=False)
    assert plan.cells.tolist() == initial_cells(region, start, 3).tolist()
    assert plan.history["cell"].size == 0


@pytest.mark.parametrize("exponent", [0.0, 0.5, 0.8])
def test_cost_exponent_equals_naive(exponent):
    """``cost_exponent`` (the gentler greedy of ``refine="rivals"``) against the naive loop with
    the same ratio ``gain / increase ** e``; e = 0 is the plain-gain greedy."""
    rng = np.random.default_rng(7)
    picks, differ = 0, 0
    for _ in range(25):
        ny, nx = (int(v) for v in rng.integers(4, 12, 2))
        region = make_region(rng.random((ny, nx)) < 0.85)
        if region.n_cells < 8:
            continue
        Y = rng.standard_normal((3, region.n_cells))
        start = int(rng.integers(region.n_cells))
        budget = float(rng.choice([5.0, 8.0, 12.0]))
        criterion = str(rng.choice(["fisher", "a-optimal"]))
        cost = str(rng.choice(["nearest-neighbor", "insertion"]))
        kw = dict(criterion=criterion, cost=cost, ridge=1e-3, progress=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            plan = plan_greedy(Y, region, start, budget, cost_exponent=exponent, **kw)
            paper = plan_greedy(Y, region, start, budget, **kw)
        ref, ref_route = naive_greedy(Y, region.grid_index, start, budget, criterion, 1e-3,
                                      cost, exponent)
        assert plan.cells.tolist() == ref, (criterion, cost, budget)
        if cost == "insertion":
            assert plan.route.tolist() == ref_route
        assert plan.cost <= budget + 1e-9
        picks += len(ref) - 3
        differ += plan.cells.tolist() != paper.cells.tolist()
    assert picks > 100 and differ >= 3  # the exponent changes the picks


def test_greedy_errors(problem):
    Y, region, start = problem
    for bad in (-1.0, np.nan, np.inf, "ten"):
        with pytest.raises(PlanningError, match="budget"):
            plan_greedy(Y, region, start, bad, progress=False)
    with pytest.raises(DataError):
        plan_greedy(Y[:, :-1], region, start, 5, progress=False)
    with pytest.raises(RegionError):
        plan_greedy(Y, region, region.n_cells, 5, progress=False)
    with pytest.raises(PlanningError, match="criterion"):
        plan_greedy(Y, region, start, 5, criterion="e-opt", progress=False)
    with pytest.raises(PlanningError, match="cost"):
        plan_greedy(Y, region, start, 5, cost="tsp", progress=False)
    for bad in (-0.1, 1.5, np.nan, "half", True, None):
        with pytest.raises(PlanningError, match=r"cost_exponent must be a number in \[0, 1\]"):
            plan_greedy(Y, region, start, 5, cost_exponent=bad, progress=False)
    with pytest.raises(PlanningError, match="ridge > 0"):
        plan_greedy(Y, region, start, 5, criterion="a-optimal", progress=False)
    Z = Y.copy()
    Z[:, :] = Z[:, :1]  # every column equal: the initial set is singular
    with pytest.raises(PlanningError, match="ridge"):
        plan_greedy(Z, region, start, 5, progress=False)
    assert len(plan_greedy(Z, region, start, 5, ridge=1e-6, progress=False)) >= 3


def test_insertion_plan_route_and_cost(problem):
    Y, region, start = problem
    plan = plan_greedy(Y, region, start, 30.0, cost="insertion", progress=False)
    steps = np.diff(region.grid_index[plan.route], axis=0)
    assert plan.cost == pytest.approx(np.hypot(*steps.T).sum()) and plan.cost <= 30 + 1e-9
    assert sorted(plan.route.tolist()) == sorted(plan.cells.tolist())
    assert plan.route[0] == start and plan.cost_function == "insertion"
