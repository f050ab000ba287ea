"""Tests of the convex floor: the mixture solver against cvxpy, the routes'
feasibility, and the theorem it rests on (every convex route relaxation reaches the best
mixture of routes), checked by brute force over every route on tiny grids."""

from __future__ import annotations

import math
import warnings

import cvxpy as cp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from test_bound import _grid_Y, grid_distances, logdet, make_region, path_feasible_sets

from lrm_cvx.errors import PlanningError, RegionError
from lrm_cvx.experimental.floor import convex_floor, route_mixture
from lrm_cvx.planning import relaxation as R
from lrm_cvx.planning.plan import path_cumulative


def moments_of(Y: np.ndarray, sets) -> np.ndarray:
    return np.stack([Y[:, sorted(S)] @ Y[:, sorted(S)].T for S in sets])


def cvxpy_mixture(Ms: np.ndarray, ridge: float) -> float:
    lam = cp.Variable(Ms.shape[0], nonneg=True)
    M = sum(lam[j] * Ms[j] for j in range(Ms.shape[0])) + ridge * np.eye(Ms.shape[1])
    prob = cp.Problem(cp.Maximize(cp.log_det(M)), [cp.sum(lam) == 1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "Solution may be inaccurate"
        prob.solve(solver="CLARABEL")
    # Clarabel may stop short of its own tolerance on a mixture at the boundary of singular
    # moments (hypothesis found seed=5074, m=2, k=4, rank=2: "optimal_inaccurate", 3e-11 off);
    # its value is still checked against the solver's to 1e-5 by the caller
    assert prob.status in ("optimal", "optimal_inaccurate"), prob.status
    return float(prob.value)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), m=st.integers(1, 12), k=st.integers(2, 4),
       rank=st.integers(1, 4), ridge=st.sampled_from([0.0, 0.05]))
@example(seed=10, m=8, k=2, rank=2, ridge=0.0)  # 5000 steps leave a gap of 1.27e-4 here
@example(seed=5074, m=2, k=4, rank=2, ridge=0.0)  # Clarabel: "optimal_inaccurate"
def test_route_mixture_matches_cvxpy(seed, m, k, rank, ridge):
    """Random rank-deficient PSD matrices (as a short route's are): the multiplicative solver's
    value equals an independent cvxpy solve, never exceeds it, and its gap bounds the
    distance to it."""
    rng = np.random.default_rng(seed)
    Ms = np.stack([(A := rng.normal(size=(k, rank))) @ A.T for _ in range(m)])
    # enough steps for the multiplicative updates' slow tail on rank-deficient moments
    lam, value, gap = route_mixture(Ms, ridge=ridge, max_iter=50_000)
    if ridge == 0 and np.linalg.matrix_rank(Ms.sum(0)) < k:  # every mixture is singular
        assert value == -math.inf
        return
    assert lam.min() >= 0 and lam.sum() == pytest.approx(1.0)
    assert value == pytest.approx(logdet(ridge * np.eye(k) + np.einsum("i,ijk->jk", lam, Ms)))
    ref = cvxpy_mixture(Ms, ridge)
    assert value <= ref + 1e-6
    assert value >= ref - max(gap, 0.0) - 1e-6
    # converged: within 1e-5 of cvxpy, or within the solver's own certified gap when that is
    # looser (hypothesis found seed=10, m=8, k=2, rank=2: 1.37e-5 off with its gap bounding it)
    assert gap <= 1e-4 and value == pytest.approx(ref, abs=max(1e-5, gap + 1e-6))
    singles = [logdet(ridge * np.eye(k) + M) for M in Ms]
    assert value >= max(singles) - 1e-9


@pytest.mark.parametrize("budget, k, ridge", [(2.3, 3, 0.0), (3.0, 2, 0.0), (3.6, 3, 0.01)])
def test_convex_relaxations_reach_the_best_mixture_of_every_route(budget, k, ridge):
    """The theorem behind the floor, by brute force: the best mixture over *every* route of a
    tiny grid is at most each convex path-aware relaxation (layered flow, king walk) and at
    least the best single route; the floor from sampled routes is at most that mixture."""
    region = make_region(7, 7, masked=[(2, 3), (4, 1), (0, 0)])
    Y = _grid_Y(region, k, 3)
    start = int(region.cell_grid[3, 3])
    sets = sorted(path_feasible_sets(grid_distances(region), start, budget), key=sorted)
    Ms = moments_of(Y, sets)
    _, hull, _ = route_mixture(Ms, ridge=ridge)
    best = max(logdet(ridge * np.eye(k) + M) for M in Ms)
    assert hull >= best - 1e-9
    flow = R.path_relaxation_bound(Y, region, start, budget, ridge=ridge, block=1)
    assert flow.value >= hull - 1e-7
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        walk = R.walk_relaxation_bound(Y, region, start, budget, ridge=ridge)
    assert walk.value >= hull - 1e-7
    floor = convex_floor(Y, region, start, budget, ridge=ridge, samples=300, rounds=3,
                         random_state=1)
    assert floor.value <= hull + 1e-9
    assert floor.value >= floor.best_route - 1e-9


def check_floor(f, Y, region, start, budget, ridge=0.0):
    """Every route is a path from the start through distinct valid cells within the budget,
    and ``value`` is exactly the information of the mixture returned."""
    g = region.grid_index
    assert len(f.routes) == f.weights.size >= 1
    assert f.weights.min() > 0 and f.weights.sum() == pytest.approx(1.0)
    for r in f.routes:
        assert r[0] == start
        assert np.unique(r).size == r.size and r.min() >= 0 and r.max() < region.n_cells
        assert path_cumulative(g[r])[-1] <= budget + 1e-12
    M = ridge * np.eye(Y.shape[0]) + sum(
        w * Y[:, r] @ Y[:, r].T for r, w in zip(f.routes, f.weights, strict=True))
    assert f.value == pytest.approx(logdet(M), abs=1e-9)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), budget=st.floats(1.5, 12.0))
def test_floor_routes_are_feasible_and_value_exact(seed, budget):
    rng = np.random.default_rng(seed)
    masked = [tuple(rc) for rc in rng.integers(0, 9, size=(8, 2)) if tuple(rc) != (4, 4)]
    region = make_region(9, 9, masked=masked)
    Y = _grid_Y(region, 3, seed)
    start = int(region.cell_grid[4, 4])
    f = convex_floor(Y, region, start, budget, samples=60, rounds=2, random_state=seed)
    if math.isfinite(f.value):
        check_floor(f, Y, region, start, budget)
    else:  # no mixture is nonsingular, so no single route is either
        assert f.best_route == -math.inf


def test_floor_is_deterministic_and_includes_the_given_route():
    """Same seed, same floor; a route passed in is in the pool, so the floor is at least its
    information (here a hand-made L that random polylines rarely produce)."""
    region = make_region(15, 15)
    Y = _grid_Y(region, 3, 7)
    start = int(region.cell_grid[7, 7])
    cg = region.cell_grid
    L = np.array([cg[7, 7], *(cg[7 - i, 7] for i in range(1, 5)), *(cg[3, 7 + j]
                  for j in range(1, 5))])
    a = convex_floor(Y, region, start, 8.0, routes=[L], samples=200, rounds=2, random_state=3)
    b = convex_floor(Y, region, start, 8.0, routes=[L], samples=200, rounds=2, random_state=3)
    assert a.value == b.value and len(a.routes) == len(b.routes)
    assert all(np.array_equal(x, y) for x, y in zip(a.routes, b.routes, strict=True))
    assert a.value >= logdet(Y[:, L] @ Y[:, L].T) - 1e-9
    assert a.best_route >= logdet(Y[:, L] @ Y[:, L].T) - 1e-9
    check_floor(a, Y, region, start, 8.0)
    # a plan's route may use the planners' tolerance: 8 > 8 - 1e-10 is accepted, 8.5 is not
    assert convex_floor(Y, region, start, 8.0 - 1e-10, routes=[L], samples=5, rounds=0,
                        random_state=3).value >= logdet(Y[:, L] @ Y[:, L].T) - 1e-9
    with pytest.raises(PlanningError, match="path length"):
        convex_floor(Y, region, start, 7.5, routes=[L], samples=5, rounds=0)


def test_on_a_smooth_field_the_floor_is_far_above_every_single_route():
    """The reason a convex relaxation cannot certify a path plan on a smooth field: routes in
    different directions see complementary directions of the factor space. Here the factors are
    the monomials 1, r, c, r^2, c^2 (scaled): a straight route sees 1, s, s^2 only, mixtures of a
    row and a column see all five."""
    region = make_region(41, 41)
    r, c = (region.grid_index.astype(float) - 20.0).T / 20.0
    Y = np.vstack([np.ones_like(r), r, c, r * r, c * c])
    start = int(region.cell_grid[20, 20])
    f = convex_floor(Y, region, start, 20.0, samples=400, rounds=4, random_state=0)
    check_floor(f, Y, region, start, 20.0)
    assert f.value > f.best_route + 3.0


def test_floor_bad_input():
    region = make_region(6, 6, masked=[(0, 0)])
    Y = _grid_Y(region, 2, 0)
    start = int(region.cell_grid[3, 3])
    cg = region.cell_grid
    with pytest.raises(PlanningError, match="region"):
        convex_floor(Y, "region", start, 3.0)
    for bad in (0.0, -1.0, float("nan"), "3", True):
        with pytest.raises(PlanningError, match="budget"):
            convex_floor(Y, region, start, bad)
    with pytest.raises(PlanningError, match="ridge"):
        convex_floor(Y, region, start, 3.0, ridge=-1.0)
    for name, bad in (("samples", 0), ("rounds", -1), ("climbs", 1.5), ("time_limit", 0)):
        with pytest.raises(PlanningError, match=name):
            convex_floor(Y, region, start, 3.0, **{name: bad})
    with pytest.raises(RegionError, match="start"):
        convex_floor(Y, region, region.n_cells + 3, 3.0)
    with pytest.raises(PlanningError, match=r"routes\[0\].*begin at the start"):
        convex_floor(Y, region, start, 3.0, routes=[[cg[3, 4], start]])
    with pytest.raises(PlanningError, match=r"routes\[0\].*path length"):
        convex_floor(Y, region, start, 3.0, routes=[[start, cg[3, 4], cg[3, 5], cg[1, 5]]])
    with pytest.raises(RegionError, match=r"routes\[0\]"):
        convex_floor(Y, region, start, 3.0, routes=[[start, region.n_cells]])
    with pytest.raises(PlanningError, match=r"routes\[1\].*distinct"):
        convex_floor(Y, region, start, 3.0, routes=[[start], [start, cg[3, 4], start]])
    with pytest.raises(PlanningError, match="moments"):
        route_mixture(np.zeros((0, 2, 2)))
    with pytest.raises(PlanningError, match="ridge"):
        route_mixture(np.stack([np.eye(2)] * 2), ridge=-1.0)
    with pytest.raises(PlanningError, match="weights"):
        route_mixture(np.stack([np.eye(2)] * 2), weights=np.array([-1.0, 2.0]))
