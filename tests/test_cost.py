"""Path costs against from-scratch references: NN tours, exact candidate costs, insertion."""

import math
from itertools import pairwise

import numpy as np
import pytest
from references import naive_tour

from lrm_cvx.errors import PlanningError
from lrm_cvx.planning.routecost import (
    InsertionCost,
    NearestNeighborCost,
    make_cost,
    nearest_neighbor_tour,
    route_length,
)


def random_grid(rng, max_side=14, keep=0.8):
    while True:
        ny, nx = (int(v) for v in rng.integers(2, max_side + 1, 2))
        mask = rng.random((ny, nx)) < keep
        if mask.sum() >= 4:
            flat = np.flatnonzero(mask.ravel())
            return np.column_stack(np.divmod(flat, nx)).astype(np.int64)


def test_nearest_neighbor_tour_hand_checked():
    g = np.array([[5, 5], [4, 5], [5, 6], [5, 3], [9, 9]])
    cost, order = nearest_neighbor_tour(g, [0, 1, 2, 3, 4])
    # from (5,5): (4,5) and (5,6) both at 1 -> lowest index 1; then (5,6) at sqrt 2;
    # then (5,3) at 3; then (9,9) at sqrt(16 + 36)
    assert order.tolist() == [0, 1, 2, 3, 4]
    assert cost == pytest.approx(1 + math.sqrt(2) + 3 + math.sqrt(52))
    cost, order = nearest_neighbor_tour(g, [4, 3, 0])
    assert order.tolist() == [4, 0, 3]
    assert nearest_neighbor_tour(g, [2]) == (0.0, pytest.approx(np.array([2])))


def test_nearest_neighbor_tour_matches_naive_on_random_grids():
    rng = np.random.default_rng(0)
    for _ in range(150):
        g = random_grid(rng)
        cells = [int(c) for c in rng.permutation(len(g))[: rng.integers(1, len(g) + 1)]]
        cost, order = nearest_neighbor_tour(g, cells)
        ref_cost, ref_order = naive_tour(g, cells)
        assert order.tolist() == ref_order
        assert cost == pytest.approx(ref_cost, rel=1e-12, abs=1e-12)
        assert route_length(g, order) == cost


def test_nearest_neighbor_tour_bad_input():
    g = np.zeros((3, 2), dtype=int)
    with pytest.raises(PlanningError, match="repeat"):
        nearest_neighbor_tour(g, [0, 0])
    with pytest.raises(PlanningError, match="at least one"):
        nearest_neighbor_tour(g, [])
    with pytest.raises(PlanningError):
        nearest_neighbor_tour(g, [3])
    with pytest.raises(PlanningError, match="grid_index"):
        nearest_neighbor_tour(np.zeros((3, 3)), [0])


def test_exact_nn_increases_match_from_scratch_tours():
    """Every candidate's C(P + x) - C(P), through many additions (cache reuse), equals a
    from-scratch tour; includes negative increases (NN tours can get shorter)."""
    rng = np.random.default_rng(1)
    n_negative = n_checked = n_reused = 0
    for _ in range(120):
        g = random_grid(rng, max_side=13)
        L = len(g)
        P = [int(c) for c in rng.permutation(L)[: rng.integers(1, min(L, 5) + 1)]]
        pool = np.arange(L) if rng.random() < 0.7 else np.sort(rng.permutation(L)[: L // 2 + 1])
        oracle = NearestNeighborCost(g, P, pool)
        for _ in range(min(L - len(P), 14)):
            c0, order = naive_tour(g, P)
            assert oracle.tour.tolist() == order
            assert oracle.cost == pytest.approx(c0, abs=1e-9)
            inc = oracle.increases()
            for j, x in enumerate(pool):
                if x in P:
                    assert np.isnan(inc[j])
                    continue
                ref = naive_tour(g, P + [int(x)])[0] - c0
                assert inc[j] == pytest.approx(ref, abs=1e-9)
                n_negative += ref < -1e-9
                n_checked += 1
            free = [int(x) for x in pool if x not in P]
            if not free:
                break
            x = free[int(rng.integers(len(free)))]
            oracle.add(x)
            n_reused += oracle.n_evaluated < len(free) - 1
            P.append(x)
    assert n_checked > 10000
    assert n_negative > 50  # the suite exercises cost decreases
    assert n_reused > 100  # and the cache reuse after additions


def test_nn_cost_rejects_cells_outside_pool():
    g = np.array([[0, 0], [0, 1], [0, 2]])
    oracle = make_cost("nearest-neighbor", g, [0], [1, 2])
    with pytest.raises(PlanningError):
        oracle.add(0)
    oracle.add(2)
    with pytest.raises(PlanningError):
        oracle.add(2)
    with pytest.raises(PlanningError, match="cost"):
        make_cost("tsp", g, [0], [1])


def naive_insertion(g, route, x):
    """Cheapest insertion by trying every position: (increase from whole-route lengths,
    position by the documented rule: smallest local increase, exact ties to the earliest)."""
    base = math.fsum(math.dist(g[a], g[b]) for a, b in pairwise(route))
    whole, local = [], []
    for i in range(len(route)):
        new = route[: i + 1] + [x] + route[i + 1:]
        whole.append(math.fsum(math.dist(g[a], g[b]) for a, b in pairwise(new)) - base)
        a = g[route[i]]
        if i + 1 < len(route):
            b = g[route[i + 1]]
            local.append(math.dist(a, g[x]) + math.dist(g[x], b) - math.dist(a, b))
        else:
            local.append(math.dist(a, g[x]))
    return min(whole), int(np.argmin(local))


def test_insertion_increases_and_route_match_naive():
    rng = np.random.default_rng(2)
    n_checked = 0
    for _ in range(100):
        g = random_grid(rng, max_side=11)
        L = len(g)
        P = [int(c) for c in rng.permutation(L)[: rng.integers(1, min(L, 4) + 1)]]
        oracle = InsertionCost(g, P, np.arange(L))
        route = naive_tour(g, P)[1]
        for _ in range(min(L - len(P), 10)):
            assert oracle.tour.tolist() == route
            assert oracle.cost == pytest.approx(route_length(g, route))
            inc, pos = oracle.increases(), oracle.positions()
            for x in range(L):
                if x in route:
                    continue
                ref_inc, ref_pos = naive_insertion(g, route, x)
                assert inc[x] == pytest.approx(ref_inc, abs=1e-9)
                assert pos[x] == ref_pos
                n_checked += 1
            x = [c for c in range(L) if c not in route][int(rng.integers(L - len(route)))]
            route.insert(int(pos[x]) + 1, x)
            oracle.add(x)
    assert n_checked > 3000


def test_insertion_hand_checked():
    g = np.array([[0, 0], [0, 4], [1, 2], [0, 6]])
    oracle = InsertionCost(g, [0, 1], [2, 3])
    # (1,2) between (0,0) and (0,4): 2*sqrt(5) - 4; appending after (0,4): sqrt(5)
    np.testing.assert_allclose(oracle.increases(), [2 * math.sqrt(5) - 4, 2.0])
    np.testing.assert_array_equal(oracle.positions(), [0, 1])
    oracle.add(2)
    assert oracle.tour.tolist() == [0, 2, 1]
    assert oracle.cost == pytest.approx(2 * math.sqrt(5))
