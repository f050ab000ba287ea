"""The path model (planning/paths.py) against from-scratch references on small random grids."""

import heapq
import itertools
import math

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError, RegionError
from lrm_cvx.planning.paths import make_path_model, startable_cells, travel_distance
from lrm_cvx.planning.routecost import InsertionCost, NearestNeighborCost
from lrm_cvx.region import _haversine

R_KM = 6371.0088


# --------------------------------------------------------------------------- fixtures
def grid_region(ny, nx, mask, lat0=40.0, lon0=-10.0, dlat=1.0, dlon=1.5):
    lat = lat0 + dlat * np.arange(ny)
    lon = lon0 + dlon * np.arange(nx)
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"), coords=dict(lat=lat, lon=lon))
    return Region.from_dataarray(da, mask=mask)


def random_region(rng, max_side=8, keep=0.85, wrap=False):
    while True:
        ny, nx = (int(v) for v in rng.integers(3, max_side + 1, 2))
        if wrap:
            nx = int(rng.integers(4, 9))
        mask = rng.random((ny, nx)) < keep
        if mask.sum() >= 5:
            break
    if wrap:
        return grid_region(ny, nx, mask, lat0=-30.0, lon0=0.0, dlat=10.0, dlon=360.0 / nx)
    return grid_region(ny, nx, mask, lat0=float(rng.uniform(-60, 50)), dlat=float(
        rng.uniform(0.5, 2)), dlon=float(rng.uniform(0.5, 2)))


def random_trav(rng, region, kind):
    if kind == "mask":
        m = rng.random(region.shape) < 0.85
        return xr.DataArray(m, dims=("lat", "lon"),
                            coords=dict(lat=region.lat.values, lon=region.lon.values))
    return kind


def enter_of(region, tr):
    """(L,) enterable cells of a traversable argument (reference: read the mask directly)."""
    if tr is None or isinstance(tr, str):
        return np.ones(region.n_cells, bool)
    gi = region.grid_index
    return np.asarray(tr.values)[gi[:, 0], gi[:, 1]]


def py_dijkstra(region, enter, metric, speed, src, wrap=False):
    """Plain heapq Dijkstra over the 8-connected enterable cells (reference)."""
    grid = region.cell_grid
    ny, nx = region.shape
    gi = region.grid_index
    dist = {src: 0.0}
    heap = [(0.0, src)]
    done = set()
    while heap:
        d, a = heapq.heappop(heap)
        if a in done:
            continue
        done.add(a)
        r0, c0 = gi[a]
        for dr, dc in itertools.product((-1, 0, 1), repeat=2):
            if not dr and not dc:
                continue
            r, c = r0 + dr, c0 + dc
            if wrap:
                c %= nx
            if not (0 <= r < ny and 0 <= c < nx) or grid[r, c] < 0 or not enter[grid[r, c]]:
                continue
            b = int(grid[r, c])
            if metric == "grid":
                w = math.hypot(dr, dc)
            else:
                w = float(_haversine(region.cell_lat[a], region.cell_lon[a], region.cell_lat[b],
                                     region.cell_lon[b]))
                if speed:
                    w /= speed
            if d + w < dist.get(b, np.inf):
                dist[b] = d + w
                heapq.heappush(heap, (d + w, b))
    out = np.full(region.n_cells, np.inf)
    for k, v in dist.items():
        out[k] = v
    return out


# --------------------------------------------------------------------------- references
def naive_nn_order(D, cells, end=None):
    """NN order of cells (start first) by the distance lookup D[(a, b)], ties lowest index."""
    rest = [c for c in cells[1:] if c != end]
    cur, order = cells[0], [cells[0]]
    while rest:
        nxt = min(rest, key=lambda c: (D(cur, c), c))
        rest.remove(nxt)
        order.append(nxt)
        cur = nxt
    return order + ([end] if end is not None else [])


def naive_route_cost(D, route, closed, stop_cost):
    legs = [D(a, b) for a, b in itertools.pairwise(route)]
    if closed:
        legs.append(D(route[-1], route[0]))
    return math.fsum(legs) + stop_cost * len(route)


def dist_lookup(model):
    cache = {}

    def D(a, b):
        a, b = int(a), int(b)
        if a not in cache:
            cache[a] = model.distances(a)
        return float(cache[a][b])

    return D


COMBOS = list(itertools.product(
    [("grid", None), ("km", None), ("km", 4.0)],
    [None, "valid", "mask"],
    [(False, False), (True, False), (False, True)],  # (closed, with end)
    [0.0, 0.7],
    ["nearest-neighbor", "insertion"],
))


@pytest.mark.parametrize("metric_speed, trav, shape, stop_cost, cost", COMBOS)
def test_incremental_costs_equal_from_scratch(metric_speed, trav, shape, stop_cost, cost):
    """Every candidate's increase, after every addition, equals route_cost(P + x) -
    route_cost(P) recomputed from scratch (NN: the tour of the set; insertion: the best
    position of the naive route, ties earliest); the coster's route and cost match."""
    metric, speed = metric_speed
    closed, with_end = shape
    rng = np.random.default_rng(hash((metric, speed, trav, shape, stop_cost, cost)) % 2**32)
    n_checked = 0
    for rep in range(4):
        region = random_region(rng, wrap=(rep == 3))
        tr = random_trav(rng, region, trav) if trav else None
        enter = enter_of(region, tr)
        if not enter.any():
            continue
        cands = np.flatnonzero(enter)
        start = int(rng.choice(cands))
        end = int(rng.choice(cands[cands != start])) if with_end else None
        try:
            model = make_path_model(region, start, 1e9, metric=metric, speed=speed,
                                    stop_cost=stop_cost, traversable=tr, closed=closed,
                                    end=end, cost=cost)
        except PlanningError as exc:
            assert "cannot reach" in str(exc)
            continue
        D = dist_lookup(model)
        k = int(rng.integers(1, 4))
        try:
            P0 = model.initial_cells(k)
        except PlanningError:
            continue
        pool = np.arange(region.n_cells) if rng.random() < 0.7 else np.sort(
            rng.permutation(region.n_cells)[: region.n_cells // 2 + 1])
        c = model.coster(P0, pool)
        route = naive_nn_order(D, [int(v) for v in P0], end)
        scale = 1.0 if metric == "grid" else 1e3 if speed is None else 10.0
        for _ in range(8):
            if cost == "nearest-neighbor":
                route = naive_nn_order(D, route, end)
            assert c.route.tolist() == route
            base = naive_route_cost(D, route, closed, stop_cost)
            assert c.cost == pytest.approx(base, rel=1e-12, abs=1e-9)
            assert c.cost == model.route_cost(c.route)
            inc = c.increases()
            best_pos = {}
            for i, x in enumerate(pool.tolist()):
                feasible = x not in route and np.isfinite(D(start, x)) and enter[x]
                assert c.active[i] == feasible
                if not feasible:
                    assert np.isnan(inc[i])
                    continue
                if cost == "nearest-neighbor":
                    ref = naive_route_cost(D, naive_nn_order(D, route + [x], end), closed,
                                           stop_cost) - base
                else:
                    seq = route + [route[0]] if closed else route
                    opts = [(D(a, x) + D(x, b) - D(a, b), s)
                            for s, (a, b) in enumerate(itertools.pairwise(seq))]
                    if not closed and end is None:
                        opts.append((D(route[-1], x), len(route) - 1))
                    v, s = min(opts)
                    best_pos[x] = s
                    ref = v + stop_cost
                if np.isfinite(ref):
                    assert inc[i] == pytest.approx(ref, rel=1e-9, abs=1e-9 * scale)
                else:
                    assert not np.isfinite(inc[i]) or inc[i] > 1e8
                n_checked += 1
            act = np.flatnonzero(c.active & np.isfinite(inc))
            if not act.size:
                break
            pick = int(pool[rng.choice(act)])
            c.add(pick)
            if cost == "nearest-neighbor":
                route = route + [pick]
            else:
                s = best_pos[pick]
                route = route[: s + 1] + [pick] + route[s + 1:]
    assert n_checked > 20


def test_default_model_is_cost_py():
    """The paper's model (grid, straight lines, open, no stop cost) gives cost.py's numbers."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        region = random_region(rng)
        model = make_path_model(region, 0, 50.0)
        assert model.is_default
        P0 = model.initial_cells(3)
        from lrm_cvx.planning.greedy import initial_cells

        assert P0.tolist() == initial_cells(region, 0, 3).tolist()
        pool = np.arange(region.n_cells)
        for cost, cls in (("nn", NearestNeighborCost), ("insertion", InsertionCost)):
            m = make_path_model(region, 0, 50.0, cost=cost)
            a, b = m.coster(P0, pool), cls(region.grid_index, P0, pool)
            assert isinstance(a, cls)
            for _ in range(4):
                np.testing.assert_array_equal(a.increases(), b.increases())
                act = np.flatnonzero(a.active)
                if not act.size:
                    break
                x = int(pool[rng.choice(act)])
                a.add(x)
                b.add(x)
            assert a.cost == b.cost == m.route_cost(a.route)
            a.deactivate(int(pool[np.flatnonzero(a.active)[0]])) if a.active.any() else None


# --------------------------------------------------------------------------- distances
def test_travel_distance_metrics():
    rng = np.random.default_rng(4)
    region = random_region(rng)
    a = rng.integers(0, region.n_cells, 12)
    b = rng.integers(0, region.n_cells, 12)
    np.testing.assert_allclose(travel_distance(region, a, b), region.distance(a, b, "grid"),
                               rtol=1e-15)
    km = travel_distance(region, a, b, metric="km")
    np.testing.assert_allclose(km, region.distance(a, b, "km"), rtol=1e-12)
    np.testing.assert_allclose(travel_distance(region, a, b, "km", speed=2.5), km / 2.5,
                               rtol=1e-15)
    np.testing.assert_array_equal(travel_distance(region, a, b, "km"),
                                  travel_distance(region, b, a, "km"))  # exactly symmetric
    assert travel_distance(region, a[:, None], b[None, :]).shape == (12, 12)
    # the antimeridian: 179.5 E and 179.5 W are one degree apart
    da = xr.DataArray(np.zeros((1, 2)), dims=("lat", "lon"),
                      coords=dict(lat=[0.0], lon=[179.5, 180.5]))
    reg = Region.from_dataarray(da)
    assert float(travel_distance(reg, 0, 1, "km")) == pytest.approx(
        2 * math.pi * R_KM / 360, rel=1e-9)


@pytest.mark.parametrize("metric, speed", [("grid", None), ("km", None), ("km", 3.0)])
def test_graph_distances_equal_plain_dijkstra(metric, speed):
    rng = np.random.default_rng(5)
    for rep in range(12):
        region = random_region(rng, wrap=rep % 3 == 0)
        tr = random_trav(rng, region, "mask" if rep % 2 else "valid")
        enter = enter_of(region, tr)
        if not enter.any():
            continue
        start = int(rng.choice(np.flatnonzero(enter)))
        try:
            model = make_path_model(region, start, 1e9, metric=metric, speed=speed,
                                    traversable=tr)
        except PlanningError:
            continue
        ref = py_dijkstra(region, enter, metric, speed, start, wrap=model._wrap)
        got = model.distances(start)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
        fin = np.isfinite(ref)
        assert np.all(got[fin] >= ref[fin] - 1e-9)  # rounded up, never shorter
        np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-9, atol=64 * 2.0 ** -20)
        # exact symmetry: d(a, b) == d(b, a) bit for bit
        for b in np.flatnonzero(fin)[:6]:
            assert model.distances(int(b), [start])[0] == got[b]
        # a cell it may not enter is never reachable
        assert not np.isfinite(got[~enter]).any()


def test_wrap_connects_first_and_last_column():
    nx = 8
    mask = np.ones((3, nx), bool)
    mask[:, 3:5] = False  # a wall in the middle: the only way round is across the seam
    region = grid_region(3, nx, mask, lat0=-10, lon0=0.0, dlat=10.0, dlon=45.0)
    grid = region.cell_grid
    a, b = int(grid[1, 2]), int(grid[1, 5])
    model = make_path_model(region, a, 100.0, traversable="valid")
    assert model._wrap
    assert model.distances(a, [b])[0] == pytest.approx(5.0)  # 2 -> 1 -> 0 -> 7 -> 6 -> 5
    cells, cum, way = model.expand([a, b])
    cols = region.grid_index[cells, 1]
    assert cols.tolist() == [2, 1, 0, 7, 6, 5]
    # not a full circle: no wrap, the wall blocks
    region2 = grid_region(3, nx, mask, lat0=-10, lon0=0.0, dlat=10.0, dlon=40.0)
    m2 = make_path_model(region2, a, 100.0, traversable="valid")
    assert not m2._wrap
    assert np.isinf(m2.distances(a, [b])[0])
    assert b not in m2.candidates()


def naive_startable(region, tr, wrap):
    """Reference: per cell, enterable and one of its 8 grid neighbours a valid enterable cell."""
    enter = enter_of(region, tr)
    grid = region.cell_grid
    ny, nx = region.shape
    out = []
    for cell, (r0, c0) in enumerate(region.grid_index):
        if tr is None:  # straight lines: every valid cell starts
            out.append(cell)
            continue
        if not enter[cell]:
            continue
        for dr, dc in itertools.product((-1, 0, 1), repeat=2):
            r, c = r0 + dr, c0 + dc
            if wrap:
                c %= nx
            if (dr or dc) and 0 <= r < ny and 0 <= c < nx and grid[r, c] >= 0 \
                    and enter[grid[r, c]]:
                out.append(cell)
                break
    return np.array(out, dtype=np.int64)


@pytest.mark.parametrize("wrap", [False, True])
def test_startable_cells_naive_reference(wrap):
    # sparse masks (many isolated cells), wrapped and not; every start it lists is accepted by
    # make_path_model, every other cell refused
    rng = np.random.default_rng(41 + wrap)
    isolated = 0
    for _ in range(25):
        region = random_region(rng, keep=0.45, wrap=wrap)
        for kind in (None, "valid", "mask"):
            tr = random_trav(rng, region, kind) if kind else None
            got = startable_cells(region, tr)
            ref = naive_startable(region, tr, wrap)
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, ref)
            isolated += region.n_cells - got.size
            for cell in range(region.n_cells):
                if cell in got:
                    make_path_model(region, cell, 3.0, traversable=tr)
                else:
                    with pytest.raises(PlanningError, match="start"):
                        make_path_model(region, cell, 3.0, traversable=tr)
    assert isolated > 0  # the masks did leave cells with nowhere to go


def test_startable_cells_wrap_seam():
    # a valid cell in the first column whose only valid neighbour is across the seam
    nx = 8
    mask = np.zeros((3, nx), bool)
    mask[1, 0] = mask[1, nx - 1] = True
    ring = grid_region(3, nx, mask, lat0=-10, lon0=0.0, dlat=10.0, dlon=45.0)
    assert startable_cells(ring, "valid").tolist() == [0, 1]
    flat = grid_region(3, nx, mask, lat0=-10, lon0=0.0, dlat=10.0, dlon=40.0)
    assert startable_cells(flat, "valid").size == 0
    assert startable_cells(flat, None).tolist() == [0, 1]
    with pytest.raises(PlanningError, match="traversable"):
        startable_cells(flat, np.ones((2, 2), bool))


# --------------------------------------------------------------------------- routes
@st.composite
def routes(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    region = random_region(rng, wrap=draw(st.booleans()))
    metric, speed = draw(st.sampled_from([("grid", None), ("km", None), ("km", 5.0)]))
    trav = draw(st.sampled_from([None, "valid", "mask"]))
    tr = random_trav(rng, region, trav) if trav else None
    closed = draw(st.booleans())
    stop_cost = draw(st.sampled_from([0.0, 0.5]))
    return rng, region, metric, speed, tr, closed, stop_cost


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(routes())
def test_expand_properties(args):
    rng, region, metric, speed, tr, closed, stop_cost = args
    enter = enter_of(region, tr)
    if not enter.any():
        return
    start = int(rng.choice(np.flatnonzero(enter)))
    try:
        model = make_path_model(region, start, 1e9, metric=metric, speed=speed,
                                stop_cost=stop_cost, traversable=tr, closed=closed)
    except PlanningError:
        return
    reach = np.flatnonzero(np.isfinite(model.distances(start)) & enter)
    others = rng.permutation(reach[reach != start])[: int(rng.integers(0, 5))]
    stops = [start] + others.tolist()
    cells, cum, way = model.expand(stops)
    assert cum[-1] == model.route_cost(stops)
    assert cum[0] == stop_cost
    assert np.all(np.diff(cum) >= -1e-12)
    assert cells[way].tolist() == stops + ([start] if closed else [])
    if closed:
        assert cells[-1] == start and way[-1]
    if tr is not None:
        gi = region.grid_index[cells]
        dr = np.abs(np.diff(gi[:, 0]))
        dc = np.abs(np.diff(gi[:, 1]))
        if model._wrap:
            dc = np.minimum(dc, region.shape[1] - dc)
        assert np.all(dr <= 1) and np.all(dc <= 1)
        assert np.all(enter[cells])
    if metric == "km":
        hav = _haversine(region.cell_lat[cells[:-1]], region.cell_lon[cells[:-1]],
                         region.cell_lat[cells[1:]], region.cell_lon[cells[1:]])
        travel = math.fsum(hav) / (speed or 1.0)
        n_stop = len(stops)
        assert cum[-1] == pytest.approx(travel + stop_cost * n_stop, rel=1e-9,
                                        abs=len(cells) * 2.0 ** -19)


def test_route_cost_hand_checked():
    mask = np.ones((3, 4), bool)
    region = grid_region(3, 4, mask)
    g = region.cell_grid
    s, a, b = int(g[0, 0]), int(g[0, 3]), int(g[2, 3])
    m = make_path_model(region, s, 100.0, stop_cost=0.5, closed=True)
    assert m.route_cost([s, a, b]) == pytest.approx(3 + 2 + math.hypot(2, 3) + 1.5)
    m = make_path_model(region, s, 100.0, stop_cost=0.5, end=b)
    assert m.route_cost([s, a]) == pytest.approx(3 + 2 + 1.5)
    assert m.route_cost([s, a, b]) == m.route_cost([s, a])
    assert m.order([s, b, a]).tolist() == [s, a, b]
    # through the graph around a wall
    mask2 = mask.copy()
    mask2[0:2, 1] = False
    region2 = grid_region(3, 4, mask2)
    g2 = region2.cell_grid
    m = make_path_model(region2, int(g2[0, 0]), 100.0, traversable="valid")
    cells, cum, way = m.expand([int(g2[0, 0]), int(g2[0, 2])])
    assert region2.grid_index[cells].tolist() == [[0, 0], [1, 0], [2, 1], [1, 2], [0, 2]]
    assert way.tolist() == [True, False, False, False, True]
    assert cum[-1] == pytest.approx(2 + 2 * math.sqrt(2), abs=1e-5)


# --------------------------------------------------------------------------- candidates
@pytest.mark.parametrize("closed, with_end", [(False, False), (True, False), (False, True)])
@pytest.mark.parametrize("trav", [None, "valid"])
def test_candidates_brute_force(closed, with_end, trav):
    rng = np.random.default_rng(6)
    for _ in range(8):
        region = random_region(rng)
        start = int(rng.integers(region.n_cells))
        end = int((start + 1 + rng.integers(region.n_cells - 1)) % region.n_cells) \
            if with_end else None
        budget = float(rng.uniform(0, 6))
        try:
            model = make_path_model(region, start, budget, stop_cost=0.3, traversable=trav,
                                    closed=closed, end=end)
        except PlanningError:
            continue
        full = make_path_model(region, start, 1e9, stop_cost=0.3, traversable=trav,
                               closed=closed, end=end)
        ref = [x for x in range(region.n_cells) if x not in (start, end)
               and full.route_cost([start, x]) <= budget + 1e-9]
        assert model.candidates().tolist() == ref


def test_initial_cells():
    rng = np.random.default_rng(7)
    for _ in range(10):
        region = random_region(rng)
        start = int(rng.integers(region.n_cells))
        for metric in ("grid", "km"):
            model = make_path_model(region, start, 0.0, metric=metric)
            P = model.initial_cells(4)
            d = model.distances(start)
            assert P[0] == start and len(set(P.tolist())) == 4
            rest = sorted((d[x], x) for x in range(region.n_cells) if x != start)
            assert P[1:].tolist() == [x for _, x in rest[:3]]
        # a graph with budget 0 grows until it holds k cells
        try:
            model = make_path_model(region, start, 0.0, traversable="valid")
        except PlanningError:
            continue
        full = make_path_model(region, start, 1e9, traversable="valid")
        d = full.distances(start)
        k = min(4, int(np.isfinite(d).sum()))
        P = model.initial_cells(k)
        rest = sorted((d[x], x) for x in np.flatnonzero(np.isfinite(d)) if x != start)
        assert P[1:].tolist() == [x for _, x in rest[: k - 1]]
    end_model = make_path_model(region, 0, 5.0, end=region.n_cells - 1)
    assert end_model.initial_cells(3)[:2].tolist() == [0, region.n_cells - 1]


# --------------------------------------------------------------------------- certificate
@pytest.mark.parametrize("metric, speed", [("grid", None), ("km", None), ("km", 2.0)])
@pytest.mark.parametrize("trav", [None, "valid"])
@pytest.mark.parametrize("closed", [False, True])
def test_grid_budget_bound_brute_force(metric, speed, trav, closed):
    """No feasible route's stop polyline (chart) is longer than grid_budget_bound()."""
    rng = np.random.default_rng(8)
    n_tight = 0
    for _ in range(6):
        region = random_region(rng, max_side=7)
        start = int(rng.integers(region.n_cells))
        budget = float(rng.uniform(1, 5)) * (1.0 if metric == "grid" else 120.0 / (speed or 1))
        try:
            model = make_path_model(region, start, budget, metric=metric, speed=speed,
                                    stop_cost=0.1, traversable=trav, closed=closed)
        except PlanningError:
            continue
        bound = model.grid_budget_bound()
        cand = model.candidates()
        longest = 0.0
        for r in range(1, 4):
            for perm in itertools.permutations(cand[:8].tolist(), r):
                stops = [start, *perm]
                if model.route_cost(stops) > budget + 1e-9:
                    continue
                seq = stops + [start] if closed else stops
                chart = sum(float(model.chart_distance(a, b)) for a, b in itertools.pairwise(seq))
                longest = max(longest, chart)
        assert longest <= bound
        n_tight += longest > 0.3 * bound
    if metric == "grid":
        assert n_tight > 0


# --------------------------------------------------------------------------- bad input
def test_bad_inputs():
    rng = np.random.default_rng(9)
    region = random_region(rng)
    with pytest.raises(PlanningError, match="metric"):
        make_path_model(region, 0, 5, metric="miles")
    with pytest.raises(PlanningError, match="speed"):
        make_path_model(region, 0, 5, metric="km", speed=0)
    with pytest.raises(PlanningError, match="speed"):
        make_path_model(region, 0, 5, metric="km", speed=-1.0)
    with pytest.raises(PlanningError, match="speed"):
        make_path_model(region, 0, 5, speed=2.0)
    with pytest.raises(PlanningError, match="stop_cost"):
        make_path_model(region, 0, 5, stop_cost=-0.1)
    with pytest.raises(PlanningError, match="stop_cost"):
        make_path_model(region, 0, 5, stop_cost=np.nan)
    with pytest.raises(PlanningError, match="budget"):
        make_path_model(region, 0, -1)
    with pytest.raises(PlanningError, match="budget"):
        make_path_model(region, 0, "5")
    with pytest.raises(PlanningError, match="closed"):
        make_path_model(region, 0, 5, closed=True, end=1)
    with pytest.raises(PlanningError, match="traversable"):
        make_path_model(region, 0, 5, traversable="land")
    with pytest.raises(PlanningError, match="traversable.*shape"):
        make_path_model(region, 0, 5, traversable=np.ones((2, 2), bool))
    with pytest.raises(PlanningError, match="boolean"):
        make_path_model(region, 0, 5, traversable=np.ones(region.shape))
    shifted = xr.DataArray(np.ones(region.shape, bool), dims=("lat", "lon"),
                           coords=dict(lat=region.lat.values + 0.5, lon=region.lon.values))
    with pytest.raises(PlanningError, match="lat"):
        make_path_model(region, 0, 5, traversable=shifted)
    no_go = np.ones(region.shape, bool)
    r, c = region.grid_index[0]
    no_go[r, c] = False
    with pytest.raises(PlanningError, match="start"):
        make_path_model(region, 0, 5, traversable=no_go)
    with pytest.raises(PlanningError, match="end"):
        make_path_model(region, 1, 5, traversable=no_go, end=0)
    island = np.zeros(region.shape, bool)
    island[r, c] = True
    with pytest.raises(PlanningError, match="cannot reach"):
        make_path_model(region, 0, 5, traversable=island)
    with pytest.raises(RegionError):
        make_path_model(region, region.n_cells, 5)
    with pytest.raises(PlanningError, match="cost"):
        make_path_model(region, 0, 5, cost="tsp")
    model = make_path_model(region, 0, 5, closed=True)
    with pytest.raises(PlanningError, match="start"):
        model.route_cost([1, 0])
    with pytest.raises(PlanningError, match="repeat"):
        model.route_cost([0, 1, 1])
    c = model.coster([0], np.arange(region.n_cells))
    with pytest.raises(PlanningError, match="active"):
        c.add(0)


def test_start_as_lat_lon_and_deactivate():
    rng = np.random.default_rng(10)
    region = random_region(rng)
    cell = 3
    model = make_path_model(region, (region.cell_lat[cell], region.cell_lon[cell]), 1000.0,
                            metric="km", closed=True)
    assert model.start == cell and model.unit == "km" and model.traversable == "none"
    pool = model.candidates()
    c = model.coster([cell], pool)
    c.deactivate(int(pool[0]))
    assert not c.active[0] and np.isnan(c.increases()[0])
    assert make_path_model(region, cell, 1.0, metric="km", speed=2).unit == "h"


@pytest.mark.parametrize("trav, closed, with_end", [(None, True, False), ("valid", False, True),
                                                    ("mask", True, False), (None, False, True)])
def test_nn_cache_reuse_long_routes(trav, closed, with_end):
    """Many additions (the cached-candidate updates of cost.py's argument, on matrix lookups):
    every increase still equals the from-scratch NN tour difference, and most candidates are
    kept without re-evaluation at some step."""
    rng = np.random.default_rng(11)
    kept = 0
    for _ in range(5):
        region = random_region(rng, max_side=10, keep=0.9)
        tr = random_trav(rng, region, trav) if trav else None
        enter = enter_of(region, tr)
        cands = np.flatnonzero(enter)
        if cands.size < 6:
            continue
        start = int(cands[0])
        end = int(cands[-1]) if with_end else None
        try:
            model = make_path_model(region, start, 1e9, metric="km", stop_cost=2.0,
                                    traversable=tr, closed=closed, end=end)
        except PlanningError:
            continue
        D = dist_lookup(model)
        pool = np.arange(region.n_cells)
        P0 = [start] + ([end] if end is not None else [])
        c = model.coster(P0, pool)
        route = naive_nn_order(D, P0, end)
        for _ in range(18):
            base = naive_route_cost(D, route, closed, 2.0)
            inc = c.increases()
            assert c.route.tolist() == route
            for i in np.flatnonzero(c.active):
                x = int(pool[i])
                ref = naive_route_cost(D, naive_nn_order(D, route + [x], end), closed, 2.0) - base
                assert inc[i] == pytest.approx(ref, rel=1e-9, abs=1e-6)
            act = np.flatnonzero(c.active & np.isfinite(inc))
            if not act.size:
                break
            pick = int(pool[rng.choice(act)])
            c.add(pick)
            kept += int(c.active.sum()) - c.n_evaluated
            route = naive_nn_order(D, route + [pick], end)
    assert kept > 0
