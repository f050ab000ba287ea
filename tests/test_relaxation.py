"""Tests of the path-aware relaxation: validity by brute force, the dual
value against an independent cvxpy solve, the LP dual term, and bad input."""

from __future__ import annotations

import math

import cvxpy as cp
import numpy as np
import pytest
import scipy.optimize
from test_bound import _grid_Y, grid_distances, logdet, make_region, path_feasible_sets

from lrm_cvx.errors import PlanningError
from lrm_cvx.planning import certificate as B
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


# ----------------------------------------------------------------------------- king walks
def _all_walk_values(region, start, steps, r_cells, cells):
    """Brute force: the largest per-visit reward over every king walk of <= steps moves
    inside the grid box (every walk enumerated)."""
    import itertools

    ny, nx = region.shape
    r = np.zeros((ny, nx))
    for c, v in zip(cells, r_cells, strict=True):
        r[tuple(region.grid_index[c])] += max(v, 0.0)
    s = tuple(region.grid_index[start])
    moves = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)]
    best = r[s]
    for T in range(1, steps + 1):
        for seq in itertools.product(moves, repeat=T):
            p, val, ok = s, r[s], True
            for a, b in seq:
                p = (p[0] + a, p[1] + b)
                if not (0 <= p[0] < ny and 0 <= p[1] < nx):
                    ok = False
                    break
                val += r[p]
            if ok:
                best = max(best, val)
    return best


@pytest.mark.parametrize("seed", range(3))
def test_king_walk_dynamic_program_is_exact(seed):
    region = make_region(5, 5, masked=[(1, 2), (3, 3)])
    start = int(region.cell_grid[2, 2])
    cells = np.arange(region.n_cells)
    rng = np.random.default_rng(seed)
    r = rng.normal(0.2, 1.0, cells.size)
    walks = R._KingWalks(region, start, cells, 3)
    val, vis = walks.best(r)
    assert val == pytest.approx(_all_walk_values(region, start, 3, r, cells), abs=1e-12)
    assert vis[cells == start][0] >= 1 and vis.sum() <= 4  # start + at most 3 moves
    assert float(np.maximum(r, 0) @ vis) == pytest.approx(val, abs=1e-12)  # the walk found


def _explicit_walk_polytope(region, start, budget, cells):
    """The layered king-walk polytope written out (nodes = grid position x step): variables
    [w (N), x (edges), t (nodes)], w_i <= [i = start] + inflow(i), sum w <= floor(B) + 1."""
    import scipy.sparse as sp

    ny, nx = region.shape
    steps = math.floor(budget + 1e-9)
    P = ny * nx
    node = -np.ones((P, steps + 1), np.int64)
    s = tuple(region.grid_index[start])
    rr, cc = np.divmod(np.arange(P), nx)
    cheb = np.maximum(abs(rr - s[0]), abs(cc - s[1]))
    ok = cheb[:, None] <= np.arange(steps + 1)[None, :]
    node[ok] = np.arange(ok.sum())
    nN = int(ok.sum())
    tails, heads = [], []
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            if (a, b) == (0, 0):
                continue
            r2, c2 = rr + a, cc + b
            inside = (r2 >= 0) & (r2 < ny) & (c2 >= 0) & (c2 < nx)
            p, q = np.flatnonzero(inside), (r2 * nx + c2)[inside]
            for lay in range(steps):
                u, v = node[p, lay], node[q, lay + 1]
                m = (u >= 0) & (v >= 0)
                tails.append(u[m])
                heads.append(v[m])
    tail, head = np.concatenate(tails), np.concatenate(heads)
    E, N = tail.size, cells.size
    A_eq = sp.csr_array((np.r_[np.ones(E), -np.ones(E), np.ones(nN)],
                         (np.r_[tail, head, np.arange(nN)],
                          np.r_[N + np.arange(E), N + np.arange(E), N + E + np.arange(nN)])),
                        shape=(nN, N + E + nN))
    b_eq = np.zeros(nN)
    b_eq[node[s[0] * nx + s[1], 0]] = 1
    pos_of = {tuple(region.grid_index[c]): j for j, c in enumerate(cells)}
    node_pos = np.repeat(np.arange(P), ok.sum(1))
    hp = node_pos[head]
    hc = np.array([pos_of.get((int(p // nx), int(p % nx)), -1) for p in hp])
    m = hc >= 0
    A_ub = sp.csr_array((np.r_[np.ones(N), -np.ones(m.sum()), np.ones(N)],
                         (np.r_[np.arange(N), hc[m], np.full(N, N)],
                          np.r_[np.arange(N), N + np.flatnonzero(m), np.arange(N)])),
                        shape=(N + 1, N + E + nN))
    b_ub = np.r_[(cells == start).astype(float), min(N, steps + 1)]
    return A_ub, b_ub, A_eq, b_eq


def test_walk_lp_equals_the_explicit_layered_polytope():
    """Column generation with the exact oracle reaches the LP optimum over the explicit
    layered graph; its dual bound is never below it."""
    region = make_region(6, 6, masked=[(1, 1), (4, 2)])
    start = int(region.cell_grid[3, 3])
    budget = 3.5
    D = grid_distances(region)
    cells = np.flatnonzero(D[start] <= budget + 1e-9)
    A_ub, b_ub, A_eq, b_eq = _explicit_walk_polytope(region, start, budget, cells)
    rows, caps = R._count_rows(min(cells.size, 4), [], [], cells.size)
    rng = np.random.default_rng(0)
    for _ in range(4):
        g = rng.uniform(0, 1, cells.size) ** 3
        c = np.zeros(A_ub.shape[1])
        c[: g.size] = g
        opt = -scipy.optimize.linprog(-c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq,
                                      bounds=(0, 1), method="highs").fun
        lp = R._WalkLP(R._KingWalks(region, start, cells, 3), rows, caps)
        val, w = lp.support(g, 200)
        assert val >= opt - 1e-9
        assert val == pytest.approx(opt, abs=1e-7)
        assert w.sum() <= 4 + 1e-9


@pytest.mark.parametrize("budget, k, ridge", [(2.3, 3, 0.0), (3.0, 2, 0.0), (3.6, 3, 0.01)])
def test_walk_bound_covers_every_route_brute_force(budget, k, ridge):
    region = make_region(7, 7, masked=[(2, 3), (4, 1), (0, 0)])
    Y = _grid_Y(region, k, 3)
    start = int(region.cell_grid[3, 3])
    D = grid_distances(region)
    sets = path_feasible_sets(D, start, budget) | nn_tour_feasible_sets(D, start, budget)
    best = max(logdet(ridge * np.eye(k) + Y[:, sorted(S)] @ Y[:, sorted(S)].T) for S in sets)
    wb = R.walk_relaxation_bound(Y, region, start, budget, ridge=ridge)
    assert wb.value >= best - 1e-7, (wb.value, best)
    assert wb.value <= wb.primal + 1e-3  # converged: the dual meets a feasible design


def test_walk_bound_equals_an_independent_cvxpy_solve():
    """The dual value equals the relaxation over the explicit layered polytope (no distance
    limits: ``limits=False``), solved directly by cvxpy."""
    region = make_region(6, 6, masked=[(1, 1), (4, 2)])
    Y = _grid_Y(region, 3, 1)
    start = int(region.cell_grid[3, 3])
    budget = 3.5
    D = grid_distances(region)
    cells = np.flatnonzero(D[start] <= budget + 1e-9)
    A_ub, b_ub, A_eq, b_eq = _explicit_walk_polytope(region, start, budget, cells)
    v = cp.Variable(A_ub.shape[1])
    w = v[: cells.size]
    M = Y[:, cells] @ cp.diag(w) @ Y[:, cells].T
    prob = cp.Problem(cp.Maximize(cp.log_det(M)),
                      [v >= 0, v <= 1, A_ub @ v <= b_ub, A_eq @ v == b_eq])
    prob.solve(solver="CLARABEL")
    assert prob.status == "optimal"
    wb = R.walk_relaxation_bound(Y, region, start, budget, limits=False, rounds=10)
    assert wb.value >= prob.value - 1e-6
    assert wb.value == pytest.approx(prob.value, abs=2e-3)


def test_walk_bound_in_the_certificate():
    from lrm_cvx.planning.greedy import plan_greedy

    region = make_region(8, 9, masked=[(2, 3), (5, 5)])
    Y = _grid_Y(region, 3, 0)
    start = int(region.cell_grid[4, 4])
    plan = plan_greedy(Y, region, start, 6.0, progress=False)
    cert = B.plan_bound(Y, region, start, 6.0, plan=plan, refine=True)
    walk = B.plan_bound(Y, region, start, 6.0, plan=plan, refine=True, path_aware="walk")
    assert walk.bound <= cert.bound + 1e-12
    assert walk.bound >= walk.refined_information - 1e-9
    assert walk.path_bound is not None
    with pytest.raises(PlanningError, match="path_aware"):
        B.plan_bound(Y, region, start, 6.0, refine=False, path_aware="wlak")
    with pytest.raises(PlanningError, match="method"):
        B.plan_bound(Y, region, start, 6.0, refine=False, path_aware={"method": "x"})
    with pytest.raises(PlanningError, match="budget"):
        R.walk_relaxation_bound(Y, region, start, -1.0)


@pytest.mark.parametrize("seed", range(4))
def test_walk_bound_is_above_the_refined_plan_on_random_instances(seed):
    from lrm_cvx.planning.greedy import plan_greedy
    from lrm_cvx.planning.refine import refine

    rng = np.random.default_rng(seed)
    ny, nx = rng.integers(6, 10, size=2)
    masked = [tuple(p) for p in rng.integers(0, [ny, nx], size=(4, 2))
              if tuple(p) != (ny // 2, nx // 2)]
    region = make_region(int(ny), int(nx), masked=masked)
    Y = _grid_Y(region, 3, seed) + 0.3 * rng.normal(size=(3, region.n_cells))
    start = int(region.cell_grid[ny // 2, nx // 2])
    budget = float(rng.uniform(4.0, 9.0))
    plan = refine(plan_greedy(Y, region, start, budget, ridge=1e-6, progress=False),
                  kicks=5, restarts=2)
    wb = R.walk_relaxation_bound(Y, region, start, budget, ridge=1e-6)
    if plan.cost <= budget + 1e-9:  # a route within the budget (not the forced initial set)
        assert wb.value >= plan.information - 1e-7
    assert wb.value <= wb.primal + 1e-2
