"""Transects and the random walk under the path model: km / hour step costs, stop
costs, cells they may not enter, closed out-and-back tours, fleets; defaults unchanged."""

import math

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError, RegionError
from lrm_cvx.information import fisher_information
from lrm_cvx.planning import PathOptions, Plan, random_walk, transect
from lrm_cvx.planning.plan import PAPER_PATH
from lrm_cvx.region import EARTH_RADIUS_KM

DIRS = ("up", "down", "left", "right")


def make_region(mask, lat0=-10.0, lon0=150.0, step=2.0, lat_descending=True):
    ny, nx = mask.shape
    lat = lat0 + step * np.arange(ny, dtype=float)
    lat = lat[::-1].copy() if lat_descending else lat
    lon = lon0 + step * np.arange(nx, dtype=float)
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


def as_mask(region, allowed):
    """A (lat, lon) boolean DataArray on the region's grid."""
    return xr.DataArray(allowed, dims=("lat", "lon"),
                        coords={"lat": region.lat.values, "lon": region.lon.values})


def haversine(lat1, lon1, lat2, lon2):
    """Naive great-circle distance (km), written independently of the library."""
    p1, p2, dl = math.radians(lat1), math.radians(lat2), math.radians(lon2 - lon1)
    h = math.sin((p2 - p1) / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_KM * math.asin(math.sqrt(min(h, 1.0)))


def reference_cost(plan, speed=None, stop_cost=0.0):
    """Travel (haversine between consecutive route rows, / speed) + a stop cost per first
    visit, recomputed from the plan's coordinates; cumulative ``(r,)``."""
    out, total, seen = [], 0.0, set()
    for i, c in enumerate(plan.route.tolist()):
        if i:
            km = haversine(plan.lat[i - 1], plan.lon[i - 1], plan.lat[i], plan.lon[i])
            total += km / speed if speed else km
        if c not in seen:
            seen.add(c)
            total += stop_cost
        out.append(total)
    return np.array(out)


def neighbours_only(region, plan):
    g = region.grid_index[plan.route]
    return bool(np.all(np.abs(np.diff(g, axis=0)).max(axis=1) == 1)) if len(g) > 1 else True


# ---------------------------------------------------------------- defaults unchanged
def test_defaults_are_the_paper_and_explicit_defaults_change_nothing():
    region = make_region(np.random.default_rng(0).random((7, 8)) < 0.8)
    Y = np.random.default_rng(1).standard_normal((2, region.n_cells))
    start = int(region.n_cells // 2)
    for d in DIRS:
        a = transect(region, start, 9.5, d, Y=Y)
        b = transect(region, start, 9.5, d, Y=Y,
                     path=PathOptions(metric="grid", speed=None, stop_cost=0.0, traversable=None,
                                      closed=False))
        assert a == b and a.path == dict(PAPER_PATH, starts=[start], budgets=[9.5], n_robots=1)
    a = random_walk(region, start, 9.5, 3, Y=Y)
    assert a == random_walk(region, start, 9.5, 3, Y=Y,
                            path=PathOptions(metric="grid", stop_cost=0, closed=False))


def test_defaults_are_bit_identical_to_the_baselines_before_the_path_model():
    """Routes, costs and cumulative costs of 200 default plans on random masked grids hash to
    the digest computed with the pre-#15 implementation (git 3ac9058:baselines.py)."""
    import hashlib

    h = hashlib.sha256()
    rng = np.random.default_rng(2024)
    for t in range(40):
        mask = rng.random((int(rng.integers(1, 10)), int(rng.integers(1, 10)))) < 0.7
        mask[0, 0] = True
        ny, nx = mask.shape
        lat, lon = np.arange(ny, dtype=float)[::-1].copy(), np.arange(nx, dtype=float)
        region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                        lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
        s, b = int(rng.integers(region.n_cells)), float(rng.uniform(0, 30))
        plans = [transect(region, s, b, d) for d in DIRS] + [random_walk(region, s, b, t)]
        for p in plans:
            h.update(p.route.astype("<i8").tobytes())
            h.update(np.float64(p.cost).astype("<f8").tobytes())
            h.update(p.route_cost.astype("<f8").tobytes())
    assert h.hexdigest() == "abe235100d44e306fefbf1aeea28ade394d32f44ab6a9eaed9856839a2542638"


def test_the_path_model_branch_reproduces_the_paper_branch():
    """metric="GRID" takes the path-model code path (validated by paths.py) but is the same
    model: identical routes, costs and cells as the paper's branch."""
    rng = np.random.default_rng(2)
    for trial in range(20):
        region = make_region(rng.random((6, 7)) < 0.75)
        start = int(rng.integers(region.n_cells))
        budget = float(rng.uniform(0, 15))
        for d in DIRS:
            a, b = transect(region, start, budget, d), transect(region, start, budget, d,
                                                                path=PathOptions(metric="GRID"))
            assert a.route.tolist() == b.route.tolist() and a.cost == b.cost
            np.testing.assert_array_equal(a.route_cost, b.route_cost)
        a, b = random_walk(region, start, budget, trial), random_walk(region, start, budget, trial,
                                                                      path=PathOptions(metric="Grid"))
        assert a.route.tolist() == b.route.tolist() and a.cost == b.cost


# ---------------------------------------------------------------- costs
@pytest.mark.parametrize("speed, stop_cost", [(None, 0.0), (None, 40.0), (1.5, 0.5)])
def test_km_costs_are_haversine_sums_plus_stops(speed, stop_cost):
    region = make_region(np.ones((6, 9), dtype=bool), lat0=30, step=3.0)
    start = int(region.cell_grid[3, 4])
    budget = 2500.0 if speed is None else 1500.0
    plans = [transect(region, start, budget, d,
                      path=PathOptions(metric="km", speed=speed, stop_cost=stop_cost))
             for d in DIRS]
    plans += [random_walk(region, start, budget, s,
                          path=PathOptions(metric="km", speed=speed,
                                           stop_cost=stop_cost)) for s in range(5)]
    for plan in plans:
        ref = reference_cost(plan, speed, stop_cost)
        np.testing.assert_allclose(plan.route_cost, ref, rtol=1e-12, atol=1e-9)
        assert plan.cost == pytest.approx(ref[-1], rel=1e-12)
        assert plan.route_cost[0] == stop_cost
        assert plan.cost <= budget + 1e-9
        assert plan.path["unit"] == ("h" if speed else "km") and plan.path["metric"] == "km"
        assert neighbours_only(region, plan)
    # an east-west km step is shorter at high latitude: the transect walks farther there
    north = make_region(np.ones((3, 30), dtype=bool), lat0=60, step=1.0)
    equator = make_region(np.ones((3, 30), dtype=bool), lat0=-1, step=1.0)
    far = transect(north, int(north.cell_grid[1, 0]), 800.0, "right", path=PathOptions(metric="km"))
    near = transect(equator, int(equator.cell_grid[1, 0]), 800.0, "right",
                    path=PathOptions(metric="km"))
    assert len(far.route) > len(near.route)
    assert len(near.route) - 1 == math.floor(800.0 / haversine(0, 150, 0, 151))


def test_transect_stops_at_the_first_step_that_does_not_fit():
    region = make_region(np.ones((1, 12), dtype=bool), lat0=0, step=1.0)
    step = haversine(0, 150, 0, 151)
    plan = transect(region, 0, 3 * step + 5 * 10.0 - 1e-6, "right",
                    path=PathOptions(metric="km", stop_cost=10.0))
    # start stop + 3 steps with 3 stops = 3 step + 40 fits; a 4th step needs 4 step + 50
    assert plan.route.tolist() == [0, 1, 2, 3]
    assert plan.cost == pytest.approx(3 * step + 40.0)


# ---------------------------------------------------------------- cells it may not enter
def test_transect_turns_at_a_cell_it_may_not_enter_like_at_the_edge():
    region = make_region(np.ones((5, 5), dtype=bool))  # row 0 is north
    allowed = np.ones((5, 5), dtype=bool)
    allowed[0, :] = False  # the top row is land
    start = int(region.cell_grid[3, 1])
    plan = transect(region, start, 6, "up", path=PathOptions(traversable=as_mask(region, allowed)))
    # the same lawnmower as on the grid without its top row
    small = make_region(np.ones((4, 5), dtype=bool))
    ref = transect(small, int(small.cell_grid[2, 1]), 6, "up")
    got = [(r - 1, c) for r, c in region.grid_index[plan.route].tolist()]
    assert got == [tuple(p) for p in small.grid_index[ref.route].tolist()]
    assert plan.path["traversable"] == "mask"
    # without a travel graph it crosses into the masked row as the paper does
    assert 0 in region.grid_index[transect(region, start, 6, "up").route][:, 0]


def test_transect_with_valid_turns_at_masked_cells_instead_of_crossing():
    mask = np.ones((6, 3), dtype=bool)
    mask[2, 1] = False  # a hole in the column
    region = make_region(mask)
    start = int(region.cell_grid[5, 1])
    crossing = transect(region, start, 4, "up")
    assert [tuple(p) for p in region.grid_index[crossing.route].tolist()] == [
        (5, 1), (4, 1), (3, 1), (1, 1)]
    turning = transect(region, start, 5, "up", path=PathOptions(traversable="valid"))
    assert [tuple(p) for p in region.grid_index[turning.route].tolist()] == [
        (5, 1), (4, 1), (3, 1), (3, 2), (4, 2), (5, 2)]
    assert turning.cost == 5 and neighbours_only(region, turning)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), closed=st.booleans(), km=st.booleans(),
       budget=st.floats(0, 30))
def test_routes_never_enter_forbidden_cells_and_fit_the_budget(seed, closed, km, budget):
    rng = np.random.default_rng(seed)
    ny, nx = int(rng.integers(2, 9)), int(rng.integers(2, 9))
    mask = rng.random((ny, nx)) < 0.85
    allowed = rng.random((ny, nx)) < 0.7
    r, c = int(rng.integers(ny)), int(rng.integers(nx))
    mask[r, c] = allowed[r, c] = True
    region = make_region(mask)
    start = int(region.cell_grid[r, c])
    kw = dict(traversable=as_mask(region, allowed), closed=closed,
              stop_cost=float(rng.choice([0.0, 0.3])))
    if km:
        kw.update(metric="km")
        budget *= 150.0  # ~ 220 km per 2-degree step
    enterable = allowed & mask
    plans = [transect(region, start, budget, d, path=PathOptions(**kw)) for d in DIRS]
    plans.append(random_walk(region, start, budget, seed, path=PathOptions(**kw)))
    for plan in plans:
        rows, cols = region.grid_index[plan.route].T
        assert enterable[rows, cols].all()
        assert neighbours_only(region, plan)
        assert plan.cost <= budget + 1e-9 or plan.route.size == 1
        assert plan.route[0] == start
        if closed:
            assert plan.route[-1] == start
            assert plan.route.tolist() == plan.route.tolist()[::-1]  # out and back
            assert plan.waypoint[-1] and plan.path["closed"]
        assert set(plan.cells.tolist()) == set(plan.route.tolist())
        assert plan.cells.tolist() == plan.route[plan.waypoint].tolist()[: len(plan.cells)]


def test_random_walk_steps_only_to_enterable_neighbours_and_stops_when_none_fits():
    mask = np.ones((5, 5), dtype=bool)
    allowed = np.zeros((5, 5), dtype=bool)
    allowed[2, :] = True  # a one-wide channel
    region = make_region(mask)
    start = int(region.cell_grid[2, 2])
    plan = random_walk(region, start, 7, 0, path=PathOptions(traversable=as_mask(region, allowed)))
    assert set(region.grid_index[plan.route][:, 0].tolist()) == {2}
    assert plan.cost == 7
    # from an isolated enterable cell the walk has nowhere to go: a one-cell plan
    lone = np.zeros((5, 5), dtype=bool)
    lone[0, 0] = True
    single = random_walk(region, 0, 5, 0, path=PathOptions(traversable=as_mask(region, lone)))
    assert single.route.tolist() == [0] and single.cost == 0


# ---------------------------------------------------------------- closed tours
def test_closed_transect_goes_out_half_and_retraces():
    region = make_region(np.ones((1, 20), dtype=bool), lat0=0, step=1.0)
    plan = transect(region, 0, 9.0, "right", path=PathOptions(closed=True, traversable="valid"))
    assert plan.route.tolist() == [0, 1, 2, 3, 4, 3, 2, 1, 0]
    assert plan.cost == 8 and plan.cells.tolist() == [0, 1, 2, 3, 4]
    assert plan.waypoint.tolist() == [True] * 5 + [False] * 3 + [True]
    # stop costs are paid once per observed cell, the way back observes nothing new
    plan = transect(region, 0, 9.0, "right", path=PathOptions(closed=True, stop_cost=0.5))
    # k cells out: 2 (k - 1) + 0.5 k <= 9 -> k = 4
    assert plan.route.tolist() == [0, 1, 2, 3, 2, 1, 0] and plan.cost == 8.0


def test_closed_transect_without_graph_turns_back_at_its_last_observed_cell():
    mask = np.ones((1, 10), dtype=bool)
    mask[0, 3:] = False
    mask[0, 9] = True
    region = make_region(mask)
    plan = transect(region, 0, 10, "right",
                    path=PathOptions(closed=True))  # masked positions crossed
    assert plan.route.tolist() == [0, 1, 2, 1, 0] and plan.cost == 4
    plan = transect(region, 0, 18, "right", path=PathOptions(closed=True))
    assert plan.route.tolist() == [0, 1, 2, 3, 2, 1, 0] and plan.cost == 18


def test_closed_random_walk_returns_within_budget_in_hours():
    region = make_region(np.ones((8, 8), dtype=bool), lat0=40, step=1.0)
    for seed in range(10):
        plan = random_walk(region, 27, 300.0, seed,
                           path=PathOptions(metric="km", speed=2.0, stop_cost=3.0, closed=True,
                                            traversable="valid"))
        assert plan.route[0] == plan.route[-1] == 27 and plan.cost <= 300.0 + 1e-9
        np.testing.assert_allclose(plan.route_cost, reference_cost(plan, 2.0, 3.0), rtol=1e-12)
        out = plan.route[: (plan.route.size + 1) // 2]
        assert plan.route[(plan.route.size - 1) // 2:].tolist() == out[::-1].tolist()
        # it turned back because no further step leaves enough budget for the way back
        m = out.size - 1
        lat, lon = region.cell_lat, region.cell_lon
        travel = sum(haversine(lat[a], lon[a], lat[b], lon[b]) / 2.0
                     for a, b in zip(out[:-1], out[1:], strict=True))
        stops = 3.0 * len(set(out.tolist()))
        r, c = region.grid_index[out[m]]
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if (dr or dc) and 0 <= r + dr < 8 and 0 <= c + dc < 8:
                    n = int(region.cell_grid[r + dr, c + dc])
                    step = haversine(lat[out[m]], lon[out[m]], lat[n], lon[n]) / 2.0
                    new = 0.0 if n in set(out.tolist()) else 3.0
                    assert 2 * (travel + step) + stops + new > 300.0 + 1e-9


# ---------------------------------------------------------------- longitude wrap
def test_travel_graph_wraps_longitude_on_a_full_circle():
    lat = np.array([1.0, -1.0])
    lon = np.arange(0.0, 360.0, 10.0)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((2, 36), dtype=bool))
    start = int(region.cell_grid[0, 34])
    wrapped = transect(region, start, 3.0, "right", path=PathOptions(traversable="valid"))
    assert region.grid_index[wrapped.route][:, 1].tolist() == [34, 35, 0, 1]
    paper = transect(region, start, 3.0, "right")  # no graph: turns at the grid's edge
    assert region.grid_index[paper.route].tolist() == [[0, 34], [0, 35], [1, 35], [1, 34]]


# ---------------------------------------------------------------- fleets
def test_fleet_is_one_baseline_per_robot_joined():
    region = make_region(np.ones((6, 8), dtype=bool))
    Y = np.random.default_rng(3).standard_normal((3, region.n_cells))
    starts, budgets = [3, 40], [4.0, 6.0]
    fleet = transect(region, starts, budgets, "down", Y=Y, path=PathOptions(closed=True))
    one = [transect(region, s, b, "down", Y=Y, path=PathOptions(closed=True)) for s, b in
           zip(starts, budgets, strict=True)]
    assert fleet == Plan.from_robots(one, Y=Y, ridge=0.0, method="transect-down")
    assert fleet.n_robots == 2 and fleet.method == "transect-down"
    np.testing.assert_array_equal(fleet.robot_costs, [p.cost for p in one])
    assert fleet.information == pytest.approx(fisher_information(Y, fleet.cells))
    for sub, ref in zip(fleet.robots, one, strict=True):
        assert sub.route.tolist() == ref.route.tolist() and sub.cost == ref.cost
    # random walks draw from one generator in robot order: deterministic given the seed
    a = random_walk(region, starts, 1000.0, 7, path=PathOptions(metric="km", traversable="valid"))
    gen = np.random.default_rng(7)
    ref = [random_walk(region, s, 1000.0, gen, path=PathOptions(metric="km", traversable="valid"))
           for s in starts]
    assert a == random_walk(region, starts, 1000.0, 7,
                            path=PathOptions(metric="km", traversable="valid"))
    assert [r.route.tolist() for r in a.robots] == [p.route.tolist() for p in ref]
    assert all(p.route.size > 3 for p in ref)
    assert (a.robot_costs <= 1000.0 + 1e-9).all() and a.method == "random"
    df = a.to_dataframe()
    assert df["robot"].tolist() == [0] * ref[0].route.size + [1] * ref[1].route.size


# ---------------------------------------------------------------- bad input
def test_bad_path_options_are_clear_errors():
    region = make_region(np.ones((4, 4), dtype=bool))
    allowed = np.ones((4, 4), dtype=bool)
    allowed[0, 0] = False
    cases = [
        (dict(metric="miles"), "metric"),
        (dict(speed=2.0), "speed"),
        (dict(metric="km", speed=0.0), "speed"),
        (dict(metric="km", speed=-1), "speed"),
        (dict(stop_cost=-0.5), "stop_cost"),
        (dict(traversable="land"), "traversable"),
        (dict(traversable=np.ones((3, 4), dtype=bool)), "traversable"),
        (dict(traversable=as_mask(region, allowed)), "may not be entered"),
        (dict(closed="yes"), "closed"),
    ]
    for kw, match in cases:
        for fn in (lambda **k: transect(region, 0, 5, "up", path=PathOptions(**k)),
                   lambda **k: random_walk(region, 0, 5, 0, path=PathOptions(**k))):
            with pytest.raises(PlanningError, match=match):
                fn(**kw)
    with pytest.raises(PlanningError, match="budget"):
        transect(region, [0, 5], [1.0, 2.0, 3.0], "up")
    with pytest.raises(PlanningError, match="budget"):
        random_walk(region, 0, [1.0, 2.0], 0)
    with pytest.raises((PlanningError, RegionError)):
        transect(region, [0, 99], 3.0, "up")


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), ny=st.integers(1, 5), nx=st.integers(1, 5),
       wrap=st.booleans(), with_enter=st.booleans())
def test_neighbours_are_the_valid_enterable_cells_of_the_3x3_window(seed, ny, nx, wrap,
                                                                   with_enter):
    """Against a loop over the 3 x 3 window: valid, enterable, not the cell itself, columns
    wrapped on a full circle; ascending cell indices, a wrapped duplicate kept twice."""
    from lrm_cvx.planning.baselines import _neighbours

    rng = np.random.default_rng(seed)
    grid = np.where(rng.random((ny, nx)) < 0.3, -1, np.arange(ny * nx).reshape(ny, nx))
    enter = rng.random((ny, nx)) < 0.7 if with_enter else None
    for row in range(ny):
        for col in range(nx):
            want = []
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    r, c = row + dr, col + dc
                    if wrap:
                        c %= nx
                    if (r, c) == (row, col) or not (0 <= r < ny and 0 <= c < nx):
                        continue
                    if grid[r, c] >= 0 and (enter is None or enter[r, c]):
                        want.append((int(grid[r, c]), r, c))
            want.sort(key=lambda w: w[0])  # stable: the window's order among equal cells
            cells, rows, cols = _neighbours(grid, row, col, enter, wrap)
            assert list(zip(cells.tolist(), rows.tolist(), cols.tolist(), strict=True)) == want
