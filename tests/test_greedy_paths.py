"""plan_greedy on every path model against a naive greedy, fleets, sensing along the
route, static placement, and the Plan of all of these."""

import json
import math
import warnings
import zlib
from itertools import combinations

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError, RegionError
from lrm_cvx.information import fisher_information
from lrm_cvx.planning import PathOptions, Plan, PriorTerms, place_sensors, plan_greedy, refine
from lrm_cvx.planning.paths import make_path_model
from lrm_cvx.planning.request import PATH_FIELDS


# --------------------------------------------------------------------------- helpers
def make_region(mask, lat0=40.0):
    ny, nx = mask.shape
    lat = lat0 + np.arange(ny, dtype=float)
    lon = 10.0 + np.arange(nx, dtype=float)
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


def logdet(Y, cells, ridge):
    M = ridge * np.eye(Y.shape[0]) + Y[:, cells] @ Y[:, cells].T
    sign, value = np.linalg.slogdet(M)
    return value if sign > 0 else -np.inf


def naive_greedy(Y, region, starts, budgets, ridge, cost="nearest-neighbor", initial="nearest",
                 guide=None, sense_along=False, **opts):
    """The joint greedy literally: every robot's cost of every candidate set recomputed from
    scratch (``route_cost(order(P + x))``, or every insertion position), every log det too.

    Ratios within 1e-12 (relative) of the best are ties: a cost increase is a difference of
    float sums, so ratios equal in exact arithmetic (two robots appending the same cell at the
    same distance, a detour equal to a straight step) may differ in their last bits, here or in
    the planner. Ties go to ``guide``'s pick (the planner's ``(cell, robot)`` at that step)
    when it is one of them, else to the lowest cell, then robot.

    ``sense_along``: the observed set is every cell of every robot's current expanded route
    (``sensed_route``); a candidate's gain is its own gain on that set; observed cells are
    not candidates."""
    from lrm_cvx.planning.plan import sensed_route

    k, L = Y.shape
    models = [make_path_model(region, s, b, cost=cost, **opts)
              for s, b in zip(starts, budgets, strict=True)]
    P, taken = [], set()
    for m in models:
        c = m.initial_cells(k) if initial == "nearest" else [m.start] + (
            [] if m.end is None else [m.end])
        keep = [int(x) for x in c if int(x) in (m.start, m.end) or int(x) not in taken]
        taken.update(keep)
        P.append(keep)
    routes = [list(m.order(p)) for m, p in zip(models, P, strict=True)]

    def options(r, x):  # (cost of P_r + x, new route)
        m = models[r]
        if cost == "nearest-neighbor":
            new = list(m.order(P[r] + [x]))
            return m.route_cost(new), new
        # cheapest insertion: the position of least increase d(a, x) + d(x, b) - d(a, b)
        # (the closing leg of a tour included; after the last stop of an open path without
        # end: d(last, x)), ties to the earliest; the new route's cost from scratch
        route = routes[r]
        seq = route + [route[0]] if m.closed else route
        best = None
        for i in range(len(seq) - 1):
            a, b = seq[i], seq[i + 1]
            with np.errstate(invalid="ignore"):  # inf - inf: x unreachable
                inc = (m.distances(a, [x])[0] + m.distances(x, [b])[0]
                       - m.distances(a, [b])[0])
            if best is None or inc < best[0]:
                best = (inc, i)
        if not m.closed and m.end is None:
            inc = m.distances(route[-1], [x])[0]
            if best is None or inc < best[0]:
                best = (inc, len(route) - 1)
        if best is None or not np.isfinite(best[0]):
            return np.inf, None
        new = route[: best[1] + 1] + [x] + route[best[1] + 1:]
        return m.route_cost(new), new

    union = [c for p in P for c in p]
    union = list(dict.fromkeys(union))
    step = 0
    while True:
        seen = list(union)
        if sense_along:
            for r, m in enumerate(models):
                seen += sensed_route(m, routes[r])[0].tolist()
            seen = list(dict.fromkeys(seen))
        v0 = logdet(Y, seen, ridge)
        found = []
        for r, m in enumerate(models):
            c0 = m.route_cost(routes[r])
            enter = m.enterable()
            for x in range(L):
                if x in seen or not enter[x] or x == m.end:
                    continue
                c1, new = options(r, x)
                if not c1 <= m.budget + m.tol:
                    continue
                ratio = (logdet(Y, seen + [x], ridge) - v0) / max(c1 - c0, 1e-12)
                if ratio > 0:
                    found.append((ratio, x, r, new))
        if not found:
            return P, routes, models
        top = max(f[0] for f in found)
        near = [f for f in found if top - f[0] <= 1e-12 * top]
        want = guide[step] if guide is not None and step < len(guide) else None
        pick = [f for f in near if (f[1], f[2]) == want]
        _, x, r, new = pick[0] if pick else min(near, key=lambda f: (f[1], f[2]))
        step += 1
        P[r].append(x)
        union.append(x)
        routes[r] = new


def greedy(Y, region, start, budget, **kw):
    """plan_greedy with the cases' path keywords gathered into one PathOptions."""
    path = {key: kw.pop(key) for key in PATH_FIELDS if key in kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        if path:
            kw["path"] = PathOptions(**path)
        return plan_greedy(Y, region, start, budget, progress=False, **kw)


def random_case(rng, ny=None, nx=None, p=0.8):
    ny = ny or int(rng.integers(4, 9))
    nx = nx or int(rng.integers(4, 9))
    mask = rng.random((ny, nx)) < p
    mask[0, 0] = True
    region = make_region(mask)
    return region


MODELS = [
    dict(),
    dict(closed=True),
    dict(stop_cost=0.5),
    dict(metric="km", scale=111.0),
    dict(metric="km", speed=50.0, scale=111.0 / 50.0, stop_cost=0.1),
    dict(traversable="valid"),
    dict(traversable="valid", closed=True),
    dict(traversable="mask"),
    dict(metric="km", traversable="valid", closed=True, scale=111.0),
    dict(end="far"),
    dict(end="far", traversable="valid"),
]


def _opts(region, rng, model, starts):
    opts = dict(model)
    scale = opts.pop("scale", 1.0)
    if opts.get("traversable") == "mask":
        m = rng.random(region.shape) < 0.85
        gi = region.grid_index
        for s in starts:
            m[gi[s, 0], gi[s, 1]] = True
        opts["traversable"] = xr.DataArray(m, dims=("lat", "lon"),
                                           coords={"lat": region.lat, "lon": region.lon})
    if opts.get("end") == "far":
        d = ((region.grid_index - region.grid_index[starts[0]]) ** 2).sum(1)
        opts["end"] = int(np.argsort(d, kind="stable")[min(3, d.size - 1)])
    return opts, scale


@pytest.mark.parametrize("model", MODELS, ids=lambda m: ",".join(f"{k}={v}" for k, v in m.items()
                                                                if k != "scale") or "paper")
@pytest.mark.parametrize("cost", ["nearest-neighbor", "insertion"])
def test_greedy_equals_naive_for_every_path_model(model, cost):
    rng = np.random.default_rng(zlib.crc32(f"{model}{cost}".encode()))
    runs = picks = 0
    for trial in range(8):
        region = random_case(rng)
        L = region.n_cells
        if L < 8:
            continue
        k = int(rng.integers(1, 4))
        n_robots = 1 if trial < 3 else int(rng.integers(2, 4))
        starts = [int(s) for s in rng.choice(L, n_robots, replace=False)]
        opts, scale = _opts(region, rng, model, starts)
        if "end" in opts and opts["end"] in starts:
            continue
        budgets = [float(scale * rng.choice([3.0, 4.5, 6.0, 8.0])) for _ in starts]
        ridge = 1e-3 if rng.random() < 0.5 else 0.0
        Y = rng.standard_normal((k, L))
        try:
            plan = greedy(Y, region, starts if n_robots > 1 else starts[0],
                          budgets if n_robots > 1 else budgets[0], ridge=1e-3 + ridge,
                          cost=cost, **opts)
        except PlanningError:  # e.g. a start on a masked island: the naive must fail too
            with pytest.raises(PlanningError):
                naive_greedy(Y, region, starts, budgets, 1e-3 + ridge, cost, **opts)
            continue
        robot = plan.history.get("robot", np.zeros(plan.history["cell"].size, np.int64))
        guide = list(zip(plan.history["cell"].tolist(), robot.tolist(), strict=True))
        P, routes, models = naive_greedy(Y, region, starts, budgets, 1e-3 + ridge, cost,
                                         guide=guide, **opts)
        subs = plan.robots
        assert len(subs) == n_robots
        for r, sub in enumerate(subs):
            assert sorted(sub.stops.tolist()) == sorted(P[r]), (model, cost, r)
            stops = sub.route[sub.waypoint].tolist()
            if models[r].closed:
                stops = stops[:-1]
            assert stops == [int(c) for c in routes[r]], (model, cost, r)
            assert sub.cost == pytest.approx(models[r].route_cost(routes[r]), rel=1e-9)
            if len(P[r]) > len(models[r].initial_cells(k)):
                assert sub.cost <= budgets[r] + models[r].tol
        union = list(dict.fromkeys(c for p in P for c in p))
        assert sorted(plan.cells.tolist()) == sorted(union)
        assert plan.information == pytest.approx(fisher_information(Y, union, 1e-3 + ridge))
        runs += 1
        picks += len(union)
    assert runs >= 5 and picks > 3 * runs


@pytest.mark.parametrize("opts", [dict(), dict(cost="insertion"),
                                  dict(cost="insertion", closed=True),
                                  dict(traversable="valid", closed=True),
                                  dict(metric="km", end="far")], ids=str)
def test_sense_along_greedy_equals_naive(opts):
    rng = np.random.default_rng(zlib.crc32(str(opts).encode()))
    runs = 0
    for trial in range(6):
        region = random_case(rng, p=0.9)
        L = region.n_cells
        n_robots = 1 if trial < 3 else 2
        starts = [int(s) for s in rng.choice(L, n_robots, replace=False)]
        kw, _ = _opts(region, rng, opts, starts)
        if "end" in kw and kw["end"] in starts:
            continue
        scale = 111.0 if kw.get("metric") == "km" else 1.0
        budgets = [float(scale * rng.choice([4.0, 6.0, 8.0])) for _ in starts]
        Y = rng.standard_normal((2, L))
        cost = kw.pop("cost", "nearest-neighbor")
        plan = greedy(Y, region, starts, budgets, ridge=1e-2, cost=cost, sense_along=True,
                      initial="start", **kw)
        robot = plan.history["robot"] if n_robots > 1 else np.zeros(plan.history["cell"].size,
                                                                    np.int64)
        guide = list(zip(plan.history["cell"].tolist(), robot.tolist(), strict=True))
        P, routes, _ = naive_greedy(Y, region, starts, budgets, 1e-2, cost, initial="start",
                                    guide=guide, sense_along=True, **kw)
        assert [sorted(s.stops.tolist()) for s in plan.robots] == [sorted(p) for p in P]
        runs += 1
    assert runs >= 4


# --------------------------------------------------------------------------- fleets
@pytest.fixture(scope="module")
def sea():
    """A 12 x 14 grid with an island (masked) and a traversable mask with a wall."""
    rng = np.random.default_rng(7)
    mask = np.ones((12, 14), dtype=bool)
    mask[4:7, 5:8] = False
    region = make_region(mask)
    Y = rng.standard_normal((3, region.n_cells))
    cg = region.cell_grid
    return Y, region, [int(cg[1, 1]), int(cg[10, 12]), int(cg[2, 12])]


def test_fleet_plan_contents(sea):
    Y, region, starts = sea
    plan = greedy(Y, region, starts, [900.0, 700.0, 500.0], metric="km", closed=True,
                  traversable="valid")
    assert plan.n_robots == 3 and plan.path["n_robots"] == 3
    assert plan.path["starts"] == starts and plan.path["budgets"] == [900.0, 700.0, 500.0]
    assert plan.path["unit"] == "km" and plan.path["closed"] and plan.path["kind"] == "path"
    assert plan.cost == pytest.approx(plan.robot_costs.sum())
    df = plan.to_dataframe()
    assert list(df.columns) == ["robot", "order", "cell", "lat", "lon", "row", "col", "waypoint",
                                "cumulative_cost"]
    gi = region.grid_index
    for r, sub in enumerate(plan.robots):
        rows = df[df["robot"] == r]
        assert rows["order"].tolist() == list(range(len(rows)))
        assert rows["cell"].iloc[0] == starts[r] == rows["cell"].iloc[-1]  # closed tour
        assert rows["cumulative_cost"].iloc[-1] == plan.robot_costs[r] == sub.cost
        assert sub.cost <= sub.budget * (1 + 1e-9)
        # with a graph consecutive rows are 8-neighbours, and every one is a valid cell
        steps = np.abs(np.diff(gi[rows["cell"].to_numpy()], axis=0))
        assert steps.max() <= 1 and np.all(steps.sum(1) >= 1)
        # km: the haversine length of consecutive rows is the cost
        la, lo = np.radians(rows["lat"].to_numpy()), np.radians(rows["lon"].to_numpy())
        h = (np.sin(np.diff(la) / 2) ** 2
             + np.cos(la[:-1]) * np.cos(la[1:]) * np.sin(np.diff(lo) / 2) ** 2)
        km = 2 * 6371.0088 * np.arcsin(np.sqrt(h))
        assert km.sum() == pytest.approx(sub.cost, rel=1e-7)  # graph steps rounded up ~1e-8
        assert np.all(np.diff(rows["cumulative_cost"]) >= -1e-12)
    # cells taken by one robot are never stops of another
    assert len(set(plan.stops.tolist())) == plan.stops.size
    # joint information, and the sub-plans' own
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells))
    doc = plan.to_geojson()
    lines = [f for f in doc["features"] if f["geometry"]["type"] == "LineString"]
    points = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert len(lines) == 3 and [f["properties"]["robot"] for f in lines] == [0, 1, 2]
    assert sorted(f["properties"]["cell"] for f in points) == sorted(plan.stops.tolist())
    assert sum(f["properties"]["start"] for f in points) == 3
    json.dumps(doc)
    # the history says which robot picked each cell
    assert plan.history["robot"].size == plan.history["cell"].size
    for sub in plan.robots:
        assert set(sub.history["cell"].tolist()) <= set(sub.stops.tolist())


def test_fleet_two_gliders_gain_more_than_one(sea):
    Y, region, starts = sea
    one = greedy(Y, region, starts[0], 8.0, closed=True)
    two = greedy(Y, region, starts[:2], 8.0, closed=True)
    assert two.information > one.information
    assert two.robots[0].cost <= 8 + 1e-9 and two.robots[1].cost <= 8 + 1e-9


def test_from_robots_joins_plans(sea):
    Y, region, starts = sea
    a = greedy(Y, region, starts[0], 6.0, ridge=1e-3)
    b = greedy(Y, region, starts[1], 5.0, ridge=1e-3)
    fleet = Plan.from_robots([a, b])
    assert fleet.n_robots == 2 and fleet.cost == pytest.approx(a.cost + b.cost)
    assert fleet.information == pytest.approx(
        fisher_information(Y, list(dict.fromkeys([*a.cells, *b.cells])), 1e-3))
    assert fleet.robots[0].route.tolist() == a.route.tolist()
    assert fleet.robots[1].cost == b.cost and fleet.path["starts"] == starts[:2]
    df = fleet.to_dataframe()
    assert df.groupby("robot")["cumulative_cost"].last().tolist() == [a.cost, b.cost]
    with pytest.raises(PlanningError, match="path model"):
        Plan.from_robots([a, greedy(Y, region, starts[1], 5.0, closed=True)])
    with pytest.raises(PlanningError, match="list of Plan"):
        Plan.from_robots([])


def test_fleet_start_forms(sea):
    Y, region, starts = sea
    latlon = [(float(region.cell_lat[s]), float(region.cell_lon[s])) for s in starts[:2]]
    ref = greedy(Y, region, starts[:2], 6.0)
    assert greedy(Y, region, latlon, 6.0) == ref
    assert greedy(Y, region, np.array(starts[:2]), [6.0, 6.0]) == ref
    # a single (lat, lon) tuple is one start, a list of one is a fleet of one
    one = greedy(Y, region, latlon[0], 6.0)
    assert one.n_robots == 1 and one.start == starts[0]
    assert greedy(Y, region, [latlon[0]], 6.0).stops.tolist() == one.stops.tolist()


# --------------------------------------------------------------------------- sense along
@pytest.mark.parametrize("opts", [dict(), dict(traversable="valid"),
                                  dict(traversable="valid", closed=True, metric="km"),
                                  dict(cost="insertion", closed=True)])
def test_sense_along_information_counts_every_route_cell(sea, opts):
    Y, region, starts = sea
    budget = 800.0 if opts.get("metric") == "km" else 9.0
    plan = greedy(Y, region, starts[:2], budget, ridge=1e-3, sense_along=True, **opts)
    plain = greedy(Y, region, starts[:2], budget, ridge=1e-3, **opts)
    assert plan.path["sense_along"]
    assert set(plan.cells.tolist()) == set(plan.route.tolist())
    assert set(plan.stops.tolist()) <= set(plan.cells.tolist())
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells, 1e-3))
    assert plan.information >= fisher_information(Y, plan.stops, 1e-3) - 1e-9
    assert plain.cells.tolist() == plain.stops.tolist()
    for sub in plan.robots:
        assert sub.cost <= sub.budget * (1 + 1e-9)
        cum = sub.route_cost
        assert np.all(np.diff(cum) >= -1e-12) and cum[-1] == sub.cost
    # the straight legs pass the cells they cross: consecutive entries are 8-neighbours
    # wherever the crossed position is a valid cell (the sea grid's island is masked)
    steps = np.abs(np.diff(plan.grid_index, axis=0))
    same = np.diff(plan.route_robot) == 0
    assert steps[same].max() <= (1 if opts.get("traversable") else 3)


@pytest.mark.parametrize("traversable", [None, "valid"])
def test_sense_along_a_long_leg_observes_the_cells_passed(sea, traversable):
    Y, region, starts = sea
    cg = region.cell_grid
    end = int(cg[10, 12])
    plan = greedy(Y, region, starts[0], 16.0, ridge=1e-3, end=end, initial="start",
                  sense_along=True, traversable=traversable)
    passed = plan.route[~plan.waypoint]
    assert passed.size >= 5 and set(passed.tolist()) <= set(plan.cells.tolist())
    assert not set(passed.tolist()) & set(plan.stops.tolist())
    assert plan.route[-1] == end and plan.route[0] == starts[0]
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells, 1e-3))
    assert plan.information > fisher_information(Y, plan.stops, 1e-3)  # the cells passed add
    steps = np.abs(np.diff(plan.grid_index, axis=0))
    assert steps.max() <= 1 or traversable is None


def test_line_cells_are_the_crossed_squares():
    from lrm_cvx.planning.plan import line_cells

    region = make_region(np.ones((8, 10), dtype=bool))
    cg = region.cell_grid
    cells, t = line_cells(region, int(cg[0, 0]), int(cg[4, 4]))  # the diagonal: its corners
    assert region.grid_index[cells].tolist() == [[1, 1], [2, 2], [3, 3]]
    assert t.tolist() == [0.25, 0.5, 0.75]
    cells, t = line_cells(region, int(cg[2, 1]), int(cg[2, 8]))
    assert region.grid_index[cells, 1].tolist() == list(range(2, 8))
    cells, _ = line_cells(region, int(cg[0, 0]), int(cg[1, 2]))  # row 0.5 crossed at col 1
    assert region.grid_index[cells].tolist() == [[0, 1], [1, 1]]
    assert line_cells(region, int(cg[0, 0]), int(cg[0, 1]))[0].size == 0


# --------------------------------------------------------------------------- static placement
def test_static_single_sensor_is_the_brute_force_best():
    rng = np.random.default_rng(11)
    for _ in range(10):
        region = random_case(rng, 5, 6)
        k = int(rng.integers(1, 4))
        Y = rng.standard_normal((k, region.n_cells))
        plan = place_sensors(Y, region, 1, ridge=0.1)
        values = [logdet(Y, [c], 0.1) for c in range(region.n_cells)]
        assert plan.cells.tolist() == [int(np.argmax(values))]
        if k == 1:  # ridge 0: the QR start, i.e. the largest |y|
            assert place_sensors(Y, region, 1).cells.tolist() == [int(np.argmax(np.abs(Y[0])))]


def test_static_pairs_brute_force_and_naive_greedy():
    rng = np.random.default_rng(12)
    for _ in range(6):
        region = random_case(rng, 5, 5)
        L = region.n_cells
        Y = rng.standard_normal((2, L))
        # naive greedy: every log det from scratch
        P = []
        for _ in range(6):
            vals = [logdet(Y, P + [c], 0.05) if c not in P else -np.inf for c in range(L)]
            P.append(int(np.argmax(vals)))
        plan = place_sensors(Y, region, 6, ridge=0.05)
        assert plan.cells.tolist() == P
        assert plan.path["kind"] == "static" and plan.cost == 6 and plan.budget == 6
        assert plan.information == pytest.approx(logdet(Y, P, 0.05))
        # greedy's pair is within the usual factor of the best pair (brute force)
        best2 = max(logdet(Y, list(c), 0.05) for c in combinations(range(L), 2))
        assert logdet(Y, P[:2], 0.05) <= best2 + 1e-9
    # ridge 0: the rank's k cells come from the pivoted QR, then the greedy
    Y = rng.standard_normal((3, region.n_cells))
    plan = place_sensors(Y, region, 5)
    assert len(plan) == 5 and np.isfinite(plan.information)
    with pytest.raises(PlanningError, match="n_sensors"):
        place_sensors(Y, region, 2)  # fewer sensors than the rank with ridge 0
    df = plan.to_dataframe()  # fixed sensors: their own columns, not a route's
    assert df["sensor"].tolist() == [0, 1, 2, 3, 4]
    assert df["cell"].tolist() == plan.cells.tolist() and "cumulative_cost" not in df
    assert plan.route.tolist() == plan.cells.tolist()


def test_static_mask_and_prior():
    rng = np.random.default_rng(13)
    region = random_case(rng, 6, 6, p=1.0)
    Y = rng.standard_normal((2, region.n_cells))
    sites = np.zeros(region.shape, dtype=bool)
    sites[:, :3] = True
    plan = place_sensors(Y, region, 4, ridge=1e-2,
                         traversable=xr.DataArray(sites, dims=("lat", "lon"),
                                                  coords={"lat": region.lat, "lon": region.lon}))
    assert np.all(region.grid_index[plan.cells, 1] < 3)
    post = place_sensors(Y, region, 3, prior=PriorTerms(prior_precision=np.eye(2)))
    assert post.posterior and len(post) == 3
    with pytest.raises(PlanningError, match="traversable"):
        place_sensors(Y, region, 3, traversable=np.ones((2, 2), dtype=bool))


# --------------------------------------------------------------------------- bad input
def test_bad_path_inputs_name_the_argument(sea):
    Y, region, starts = sea
    land = np.ones(region.shape, dtype=bool)
    gi = region.grid_index
    land[gi[starts[0], 0], gi[starts[0], 1]] = False
    cases = [
        (dict(start=starts[:2], budget=[3.0]), "budget"),
        (dict(start=starts[:2], budget=[3.0, 4.0, 5.0]), "budget"),
        (dict(start=starts[0], budget=[3.0]), "budget"),
        (dict(start=[], budget=3.0), "start"),
        (dict(closed=True, end=starts[1]), "closed"),
        (dict(metric="miles"), "metric"),
        (dict(speed=0.0, metric="km"), "speed"),
        (dict(speed=5.0), "speed"),
        (dict(stop_cost=-1.0), "stop_cost"),
        (dict(traversable=np.ones((3, 3), dtype=bool)), "traversable"),
        (dict(traversable=land), "start"),
        (dict(sense_along="yes"), "sense_along"),
        (dict(path="teleport"), "path"),
        (dict(start=None), "start"),
    ]
    for kw, word in cases:
        args = dict(start=starts[0], budget=5.0) | kw
        with pytest.raises((PlanningError, RegionError)) as info:
            greedy(Y, region, args.pop("start"), args.pop("budget"), **args)
        assert word in str(info.value), (kw, str(info.value))


def test_traversable_mask_is_kept(sea):
    Y, region, starts = sea
    m = np.ones(region.shape, dtype=bool)
    m[:, 9] = False  # a wall with no gap
    plan = greedy(Y, region, starts[0], 12.0, traversable=m)
    gi = region.grid_index
    np.testing.assert_array_equal(plan.traversable_mask[gi[:, 0], gi[:, 1]],
                                  m[gi[:, 0], gi[:, 1]])
    assert np.all(gi[plan.route, 1] < 9)  # the route never crosses the wall
    assert greedy(Y, region, starts[0], 12.0).traversable_mask is None


def test_refine_refuses_other_path_models(sea):
    Y, region, starts = sea
    for kw in (dict(closed=True), dict(metric="km"), dict(stop_cost=0.5)):
        budget = 500.0 if kw.get("metric") == "km" else 6.0
        plan = greedy(Y, region, starts[0], budget, ridge=1e-3, **kw)
        with pytest.raises(PlanningError, match="paper's path model"):
            refine(plan)
    fleet = greedy(Y, region, starts[:2], 6.0, ridge=1e-3)
    with pytest.raises(PlanningError, match="paper's path model"):
        refine(fleet)
    with pytest.raises(PlanningError, match="paper's path model"):
        greedy(Y, region, starts[0], 6.0, ridge=1e-3, closed=True, refine=True)


def test_default_plan_has_the_papers_path(sea):
    Y, region, starts = sea
    plan = greedy(Y, region, starts[0], 6.0)
    assert plan.path == {"kind": "path", "metric": "grid", "speed": None, "stop_cost": 0.0,
                         "traversable": "none", "closed": False, "end": None,
                         "unit": "grid units", "sense_along": False, "starts": [starts[0]],
                         "budgets": [6.0], "n_robots": 1}
    assert plan.robots == [plan] and plan.stops.tolist() == plan.cells.tolist()
    assert plan.waypoint.all() and (plan.route_robot == 0).all()
    assert plan.robot_costs.tolist() == [plan.cost]
    assert "robot" not in plan.history


def test_plot_fleet(sea):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Y, region, starts = sea
    plan = greedy(Y, region, starts, 5.0, closed=True, sense_along=True)
    ax = plan.plot()
    labels = [line.get_label() for line in ax.lines]
    assert {"robot 0", "robot 1", "robot 2"} <= set(labels)
    plt.close("all")
    assert math.isfinite(plan.information)


# --------------------------------------------------------------------------- properties
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=100, deadline=None, suppress_health_check=list(HealthCheck))
@given(seed=st.integers(0, 10_000), model=st.sampled_from(MODELS),
       n_robots=st.integers(1, 3), sense_along=st.booleans(),
       cost=st.sampled_from(["nearest-neighbor", "insertion"]))
def test_plan_invariants_on_every_path_model(seed, model, n_robots, sense_along, cost):
    rng = np.random.default_rng(seed)
    region = random_case(rng)
    L = region.n_cells
    n_robots = min(n_robots, L)
    starts = [int(s) for s in rng.choice(L, n_robots, replace=False)]
    opts, scale = _opts(region, rng, model, starts)
    if "end" in opts and opts["end"] in starts:
        return
    budget = float(scale * rng.uniform(0, 9))
    Y = rng.standard_normal((int(rng.integers(1, 4)), L))
    try:
        plan = greedy(Y, region, starts, budget, ridge=1e-3, cost=cost, sense_along=sense_along,
                      **opts)
    except PlanningError as exc:  # only for a start (or end) that cannot move
        assert "cannot reach" in str(exc) or "reach only" in str(exc), str(exc)
        return
    models = plan._path_models
    df = plan.to_dataframe()
    gi = region.grid_index
    for r, sub in enumerate(plan.robots):
        rows = df[df["robot"] == r]
        cum = rows["cumulative_cost"].to_numpy()
        assert rows["cell"].iloc[0] == starts[r]
        assert cum[0] == pytest.approx(opts.get("stop_cost", 0.0))
        if sub.cost > budget + models[r].tol:
            # the forced initial cells alone exceed the budget (a warning); with a travel
            # graph cut at the budget's reach their legs may even be unreachable (inf)
            assert sub.history["cell"].size == 0
            continue
        assert np.all(np.diff(cum) >= -1e-9 * max(1.0, budget))
        assert cum[-1] == plan.robot_costs[r] == sub.cost
        assert sub.cost == pytest.approx(models[r].route_cost(
            sub.route[sub.waypoint][:-1] if models[r].closed else sub.route[sub.waypoint]),
            rel=1e-9, abs=1e-9)
        if sub.history["cell"].size:  # beyond the forced cells: within the budget
            assert sub.cost <= budget + models[r].tol
        if models[r].closed:
            assert rows["cell"].iloc[-1] == starts[r]
        if models[r].end is not None:
            assert rows["cell"].iloc[-1] == models[r].end
        if models[r].traversable != "none":
            cells = rows["cell"].to_numpy()
            assert models[r].enterable()[cells].all()
            steps = np.abs(np.diff(gi[cells], axis=0))
            assert steps.size == 0 or steps.max() <= 1
    expected = list(dict.fromkeys(plan.stops.tolist() + (plan.route.tolist() if sense_along
                                                        else [])))
    assert plan.cells.tolist() == expected
    assert plan.information == pytest.approx(fisher_information(Y, plan.cells, 1e-3))


@pytest.mark.parametrize("closed", [False, True])
def test_forced_initial_cells_beyond_a_tiny_budget_have_a_finite_route(closed):
    """A budget smaller than one step: the rank's forced cells lie outside the travel graph's
    reach; the plan warns, and its cost is the true route through the graph (finite, equal to
    the expanded route's last cumulative cost; every row an enterable 8-neighbour step)."""
    mask = np.ones((6, 7), dtype=bool)
    mask[2, 1:5] = False  # a wall to walk around
    region = make_region(mask)
    Y = np.random.default_rng(3).normal(size=(4, region.n_cells))
    with pytest.warns(UserWarning, match="initial cells"):
        plan = plan_greedy(Y, region, 3, 0.5, progress=False,
                           path=PathOptions(metric="km", traversable="valid", closed=closed))
    assert np.isfinite(plan.cost) and plan.cost > 0.5
    df = plan.to_dataframe()
    assert df["cumulative_cost"].iloc[-1] == pytest.approx(plan.cost)
    gi = region.grid_index[df["cell"].to_numpy()]
    assert np.abs(np.diff(gi, axis=0)).max() <= 1
    assert len(plan.cells) == 4


def test_fleet_certificate_reports_the_total_budget():
    """A fleet's certificate, like its Plan, reports the robots' total budget and bounds the
    joint information."""
    region = make_region(np.ones((6, 7), dtype=bool))
    Y = np.random.default_rng(5).normal(size=(3, region.n_cells))
    plan = plan_greedy(Y, region, [0, region.n_cells - 1], [4.0, 2.5], progress=False)
    cert = plan.certify(tighten=False)
    assert plan.budget == pytest.approx(6.5) and cert.budget == pytest.approx(plan.budget)
    assert cert.bound >= plan.information - 1e-9
