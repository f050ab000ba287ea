"""Route-shape search (refine's global move): the rasterised polyline against a fine-sampling
reference (near the polyline, every deeply crossed cell), the budget cut against a naive loop,
and the search's routes are feasible, scored exactly and deterministic; on a smooth field it
lifts refinement above the local moves."""

import math
import time
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from references import naive_tour
from test_refine import check_plan, make_region

from lrm_cvx.information import fisher_information
from lrm_cvx.planning import plan_greedy, refine
from lrm_cvx.planning.shapes import _prefix_within, polyline_cells, search_shapes

points = st.lists(st.tuples(st.floats(-3, 14), st.floats(-3, 14)), min_size=1, max_size=4)


def polyline_distance(pts, rc):
    """Chebyshev distance from each cell centre ``rc`` (m, 2) to the polyline (fine sampling)."""
    samples = np.vstack([a + np.linspace(0, 1, 4001)[:, None] * (b - a)
                         for a, b in pairwise(np.asarray(pts, float))] or [np.asarray(pts, float)])
    return np.abs(rc[:, None, :] - samples[None]).max(axis=2).min(axis=1)


@settings(max_examples=80, deadline=None)
@given(start=st.tuples(st.integers(0, 9), st.integers(0, 11)), rest=points,
       seed=st.integers(0, 1000))
def test_polyline_cells_is_a_staircase_along_the_polyline(start, rest, seed):
    ny, nx = 10, 12
    full = np.arange(ny * nx).reshape(ny, nx)
    pts = [start, *rest]
    cells = polyline_cells(np.asarray(pts, float), full)
    rc = np.column_stack(np.divmod(cells, nx))
    assert cells[0] == full[start]
    assert np.unique(cells).size == cells.size
    # every cell is near the polyline (a crossed cell, or a corner next to one) ...
    assert np.all(polyline_distance(pts, rc) <= 1.0 + 1e-9)
    # ... and every cell the polyline passes deep inside (centre within 1/4) is there
    allrc = np.column_stack(np.divmod(np.arange(ny * nx), nx))
    deep = np.flatnonzero(polyline_distance(pts, allrc) <= 0.25 - 1e-9)
    assert set(deep.tolist()) <= set(cells.tolist())
    # one straight leg inside the grid: a monotone 4-connected chain
    (r1, c1), *more = rest
    if not more and 0 <= r1 <= ny - 1 and 0 <= c1 <= nx - 1:
        step = np.diff(rc, axis=0)
        assert np.all(np.abs(step).sum(axis=1) == 1)
        assert np.all(step[:, 0] * np.sign(r1 - start[0]) >= 0)
        assert np.all(step[:, 1] * np.sign(c1 - start[1]) >= 0)
    # a mask only removes cells, keeping the order of the others
    rng = np.random.default_rng(seed)
    masked = np.where(rng.random((ny, nx)) < 0.3, -1, full)
    masked[start] = full[start]
    kept = polyline_cells(np.asarray(pts, float), masked)
    assert kept.tolist() == [c for c in cells.tolist() if masked.ravel()[c] >= 0]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), limit=st.floats(0, 20))
def test_prefix_within_is_the_longest_prefix_that_fits(seed, limit):
    rng = np.random.default_rng(seed)
    g = rng.integers(0, 8, size=(30, 2))
    cells = rng.permutation(30)[: rng.integers(1, 30)]
    got = _prefix_within(g, cells, limit)
    n, length = 1, 0.0
    while n < cells.size:
        length += math.dist(g[cells[n - 1]], g[cells[n]])
        if length > limit:
            break
        n += 1
    assert got.tolist() == cells[:n].tolist()


def smooth_instance(n=41, k=4, seed=0):
    """A smooth rank-k field on an n x n grid (length scale ~ n / 2), start at the centre."""
    rng = np.random.default_rng(seed)
    mask = np.ones((n, n), dtype=bool)
    region = make_region(mask)
    gi = region.grid_index.astype(float) / n
    Y = np.stack([np.cos(gi @ rng.normal(size=2) * 3 + rng.uniform(0, 6)) for _ in range(k)])
    start = int(np.flatnonzero((region.grid_index == [n // 2, n // 2]).all(1))[0])
    return region, Y, start


def test_search_shapes_routes_are_feasible_scored_exactly_and_deterministic():
    region, Y, start = smooth_instance()
    g = region.grid_index
    limit = 20.0 + 1e-9

    def value(cells):
        return fisher_information(Y, cells, 0.0)

    out = search_shapes(value, region.cell_grid, g, start, limit, samples=300,
                        rng=np.random.default_rng(3), deadline=time.perf_counter() + 1e6)
    route, v = out
    assert route[0] == start and np.unique(route).size == route.size
    assert math.fsum(math.dist(g[a], g[b]) for a, b in pairwise(route)) <= limit
    assert v == pytest.approx(value(route), abs=1e-12)
    again = search_shapes(value, region.cell_grid, g, start, limit, samples=300,
                          rng=np.random.default_rng(3), deadline=time.perf_counter() + 1e6)
    assert again[1] == v and np.array_equal(again[0], route)
    # with a cost of the caller's (here the nearest-neighbour tour), every route is cut to fit it
    tour = {}

    def fits(cells):
        tour[len(cells)] = naive_tour(g, [int(c) for c in cells])[0]
        return tour[len(cells)] <= limit

    nn_route, nn_v = search_shapes(value, region.cell_grid, g, start, limit, samples=300,
                                   rng=np.random.default_rng(3), deadline=1e18, fits=fits)
    assert naive_tour(g, [int(c) for c in nn_route])[0] <= limit
    assert nn_v == pytest.approx(value(nn_route), abs=1e-12) and nn_route[0] == start
    # the best of 300 random polylines is at least as good as any straight route tried alone
    best_line = max(value(_prefix_within(g, polyline_cells(
        np.array([g[start], g[start] + 40 * np.array([math.sin(a), math.cos(a)])]),
        region.cell_grid), limit)) for a in np.linspace(0, 2 * math.pi, 16, endpoint=False))
    assert v >= best_line - 1e-9


@pytest.mark.parametrize("cost", ["nearest-neighbor", "insertion"])
def test_shape_move_lifts_refinement_on_a_smooth_field(cost):
    """Smooth field, budget 20: the greedy's local optimum is not the best shape; refinement
    with the shape move ends strictly higher than with local moves only, and stays feasible."""
    region, Y, start = smooth_instance()
    plan = plan_greedy(Y, region, start, 20.0, cost=cost, progress=False)
    local = refine(plan, kicks=0, shapes=0, time_limit=1e6)
    shaped = refine(plan, kicks=0, shapes=300, time_limit=1e6)
    check_plan(shaped, plan, region, Y)
    assert shaped.refinement["shapes"] == 1
    assert shaped.information > local.information + 1e-6
