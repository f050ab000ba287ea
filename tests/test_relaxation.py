"""Tests of the path-aware relaxation (issue #16 item 1): validity by brute force, the dual
value against an independent cvxpy solve, the LP dual term, and bad input."""

from __future__ import annotations

import math

import cvxpy as cp
import numpy as np
import pytest
import scipy.optimize
from test_bound import _grid_Y, grid_distances, logdet, make_region, path_feasible_sets

from lrm_cvx.errors import PlanningError
from lrm_cvx.planning import bound as B
from lrm_cvx.planning import relaxation as R


def nn_tour_feasible_sets(D: np.ndarray, start: int, budget: float) -> set[frozenset]:
    """Every set P containing the start whose nearest-neighbour tour from the start (the
    paper's cost; ties to the lowest index) has length <= budget (exhaustive over subsets of
    the budget disk)."""
    near = [c for c in np.flatnonzero(D[start] <= budget + 1e-9).tolist() if c != start]
    out: set[frozenset] = set()
    import itertools

    for m in range(min(len(near), math.floor(budget + 1e-9)) + 1):  # m legs of length >= 1
        for sub in itertools.combinations(near, m):
            left, cur, cost = set(sub), start, 0.0
            while left:
                nxt = min(left, key=lambda c: (D[cur, c], c))
                cost += D[cur, nxt]
                cur = nxt
                left.discard(nxt)
            if cost <= budget + 1e-9:
                out.add(frozenset((start, *sub)))
    return out


@pytest.mark.parametrize("budget, k, ridge", [(2.3, 3, 0.0), (3.0, 2, 0.0), (3.6, 3, 0.01)])
def test_path_bound_covers_every_route_brute_force(budget, k, ridge):
    region = make_region(7, 7, masked=[(2, 3), (4, 1), (0, 0)])
    Y = _grid_Y(region, k, 3)
    start = int(region.cell_grid[3, 3])
    D = grid_distances(region)
    sets = path_feasible_sets(D, start, budget)
    if budget <= 3.0:
        sets |= nn_tour_feasible_sets(D, start, budget)
    best = max(logdet(ridge * np.eye(k) + Y[:, sorted(S)] @ Y[:, sorted(S)].T) for S in sets)
    for block in (1, 2):
        pb = R.path_relaxation_bound(Y, region, start, budget, ridge=ridge, block=block)
        assert pb.value >= best - 1e-7, (block, pb.value, best)
        assert pb.value <= pb.primal + 1e-4  # converged: dual meets the solver's primal


def _independent_cvxpy(Y, poly, ridge):
    """The relaxation written directly (dense Y diag(w) Y^T) over the polytope's rows."""
    k = Y.shape[0]
    Yc = Y[:, poly.cells]
    v = cp.Variable(poly.n_vars)
    w = v[: poly.cells.size]
    M = Yc @ cp.diag(w) @ Yc.T + ridge * np.eye(k)
    prob = cp.Problem(cp.Maximize(cp.log_det(M)),
                      [v >= 0, v <= 1, poly.A_ub @ v <= poly.b_ub, poly.A_eq @ v == poly.b_eq])
    prob.solve(solver="CLARABEL")
    assert prob.status == "optimal"
    return float(prob.value)


@pytest.mark.parametrize("seed", [0, 1])
def test_dual_value_equals_an_independent_cvxpy_solve(seed):
    region = make_region(6, 7, masked=[(1, 1), (4, 5)])
    Y = _grid_Y(region, 3, seed)
    start = int(region.cell_grid[3, 3])
    pb = R.path_relaxation_bound(Y, region, start, 3.5, block=2)
    poly = R.path_polytope(region, start, 3.5, block=2)
    assert pb.value == pytest.approx(_independent_cvxpy(Y, poly, 0.0), abs=1e-5)


def test_lp_dual_term_is_an_upper_bound_at_any_multipliers():
    region = make_region(6, 6)
    start = int(region.cell_grid[2, 2])
    poly = R.path_polytope(region, start, 4.0, block=2)
    rng = np.random.default_rng(0)
    g = rng.uniform(0, 1, poly.cells.size)
    c = np.zeros(poly.n_vars)
    c[: g.size] = g
    opt = -scipy.optimize.linprog(-c, A_ub=poly.A_ub, b_ub=poly.b_ub, A_eq=poly.A_eq,
                                  b_eq=poly.b_eq, bounds=(0, 1), method="highs").fun
    val, w = poly.support(g)
    assert val == pytest.approx(opt, abs=1e-7) and w is not None
    for _ in range(20):  # weak duality at random multipliers
        y_ub = rng.uniform(0, 1, poly.b_ub.size)
        y_eq = rng.normal(0, 1, poly.b_eq.size)
        assert poly.dual_value(g, y_ub, y_eq) >= opt - 1e-9


def test_path_bound_is_between_refined_plan_and_disk_bound():
    from lrm_cvx.planning.greedy import plan_greedy

    region = make_region(8, 9, masked=[(2, 3), (5, 5)])
    for seed in range(3):
        Y = _grid_Y(region, 3, seed)
        start = int(region.cell_grid[4, 4])
        plan = plan_greedy(Y, region, start, 6.0, progress=False)
        cert = B.plan_bound(Y, region, start, 6.0, plan=plan, tighten=False, refine=True)
        both = B.plan_bound(Y, region, start, 6.0, plan=plan, tighten=False, refine=True,
                            path_aware=True)
        assert both.bound <= cert.bound + 1e-12
        assert both.bound >= both.refined_information - 1e-9
        assert both.path_bound is not None and both.bound <= max(
            both.initial_information, both.path_bound) + 1e-12


def test_bad_input():
    region = make_region(6, 6)
    Y = _grid_Y(region, 2, 0)
    start = int(region.cell_grid[2, 2])
    with pytest.raises(PlanningError, match="coarser than the budget"):
        R.path_polytope(region, start, 2.0, block=4)
    with pytest.raises(PlanningError, match="block must be"):
        R.path_polytope(region, start, 2.0, block=0)
    with pytest.raises(PlanningError, match="max_edges"):
        R.path_polytope(region, start, 5.0, block=1, max_edges=10)
    with pytest.raises(PlanningError):
        R.path_relaxation_bound(Y, region, start, -1.0)
    # a budget below one step admits only the start cell: the bound covers it
    pb = R.path_relaxation_bound(Y, region, start, 0.5, ridge=0.1)
    y = Y[:, [start]]
    assert pb.n_candidates == 1 and pb.value >= logdet(0.1 * np.eye(2) + y @ y.T) - 1e-9


def test_solver_failure_falls_back_to_frank_wolfe_and_plan_bound_warns(monkeypatch):
    region = make_region(6, 6)
    Y = _grid_Y(region, 2, 0)
    start = int(region.cell_grid[2, 2])
    ref = R.path_relaxation_bound(Y, region, start, 3.0, block=1)
    monkeypatch.setattr(R, "_solve_cvx", lambda *a, **k: (None, "error: forced"))
    fw = R.path_relaxation_bound(Y, region, start, 3.0, block=1)
    assert fw.value >= ref.value - 1e-6 and math.isfinite(fw.value)  # valid, maybe looser

    def boom(*a, **k):
        raise PlanningError("forced failure")

    monkeypatch.setattr(R, "path_relaxation_bound", boom)
    disk = B.plan_bound(Y, region, start, 3.0, tighten=False, refine=False)
    with pytest.warns(UserWarning, match="path-aware"):
        c = B.plan_bound(Y, region, start, 3.0, tighten=False, refine=False, path_aware=True)
    assert c.bound == disk.bound and c.path_bound is None
