"""Tests of the D-optimal relaxation bound (planning/dopt.py) and the plan certificate
(planning/certificate.py).

References are written plainly here: brute force over all subsets, a direct cvxpy model of the
relaxation (``cp.log_det`` of the full weighted sum), and scans of the dual function.
"""

from __future__ import annotations

import itertools
import math
import warnings
from types import SimpleNamespace

import cvxpy as cp
import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lrm_cvx.errors import ConvergenceWarning, PlanningError
from lrm_cvx.planning import PathOptions
from lrm_cvx.planning import certificate as B
from lrm_cvx.planning import cover as C
from lrm_cvx.planning import dopt as D
from lrm_cvx.planning.dopt import certify_weights, dopt_upper_bound, dual_value
from lrm_cvx.planning.families import min_spacing_km, start_limit
from lrm_cvx.region import Region


# ----------------------------------------------------------------------------- helpers
def smooth_Y(k: int, L: int, seed: int, noise: float = 0.05) -> np.ndarray:
    """Smooth-ish factors (low-frequency cosines with random scales) plus a little noise."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 1, L)
    Y = np.vstack(
        [np.cos(np.pi * (j + rng.uniform(0, 1)) * x + rng.uniform(0, 6)) for j in range(k)]
    )
    Y *= 10.0 ** rng.uniform(-1, 1, k)[:, None]
    return Y + noise * rng.standard_normal((k, L))


def logdet(M: np.ndarray) -> float:
    s, v = np.linalg.slogdet(M)
    return v if s > 0 else -math.inf


def brute_force_best(Y: np.ndarray, n: int, ridge: float, cells=None) -> float:
    """max over subsets of at most n cells of log det(ridge I + sum y y^T)."""
    k, L = Y.shape
    cells = np.arange(L) if cells is None else np.asarray(cells)
    best = -math.inf
    for m in range(1, min(n, cells.size) + 1):
        for S in itertools.combinations(cells.tolist(), m):
            Ys = Y[:, list(S)]
            best = max(best, logdet(ridge * np.eye(k) + Ys @ Ys.T))
    return best


def plain_relaxation(Y: np.ndarray, n: float, ridge: float) -> float:
    """The relaxation written directly in cvxpy (fine for small L only)."""
    k, L = Y.shape
    w = cp.Variable(L)
    M = Y @ cp.diag(w) @ Y.T + ridge * np.eye(k)
    prob = cp.Problem(cp.Maximize(cp.log_det(M)), [w >= 0, w <= 1, cp.sum(w) <= n])
    try:
        prob.solve(solver="CLARABEL")
    except cp.error.SolverError:
        prob.solve(solver="SCS", eps_abs=1e-9, eps_rel=1e-9, max_iters=100_000)
    assert prob.status == "optimal", prob.status
    return float(prob.value)


def make_region(ny: int, nx: int, masked=()) -> Region:
    mask = np.ones((ny, nx), bool)
    for r, c in masked:
        mask[r, c] = False
    lat = xr.DataArray(np.arange(ny, dtype=float), dims=("lat",))
    lon = xr.DataArray(np.arange(nx, dtype=float), dims=("lon",))
    return Region(lat=lat, lon=lon, mask=mask)


# ----------------------------------------------------------------------------- relaxation
@pytest.mark.parametrize(
    "k, L, n, ridge, seed",
    [(2, 10, 2, 0.0, 0), (3, 12, 3, 0.0, 1), (3, 14, 5, 0.0, 2), (3, 16, 4, 0.1, 3),
     (2, 9, 1, 0.5, 4), (4, 12, 6, 0.0, 5)],
)
def test_bound_covers_brute_force_and_matches_plain_cvxpy(k, L, n, ridge, seed):
    Y = np.random.default_rng(seed).standard_normal((k, L))
    b = dopt_upper_bound(Y, n, ridge=ridge, tol=1e-5)
    best = brute_force_best(Y, n, ridge)
    assert b.value >= best - 1e-9
    assert b.primal <= b.value
    assert b.value == pytest.approx(plain_relaxation(Y, n, ridge), abs=1e-4)
    # the reported weights are feasible and give the reported primal value
    w = b.weights.toarray()
    assert w.shape == (L,) and np.all(w >= 0) and np.all(w <= 1) and w.sum() <= n + 1e-9
    assert logdet(ridge * np.eye(k) + (Y * w) @ Y.T) == pytest.approx(b.primal, abs=1e-9)


def test_fractional_n_and_candidates():
    Y = np.random.default_rng(7).standard_normal((3, 15))
    cand = np.array([0, 2, 3, 5, 8, 9, 11, 14])
    b = dopt_upper_bound(Y, 3.5, candidates=cand, tol=1e-5)
    assert b.value == pytest.approx(plain_relaxation(Y[:, cand], 3.5, 0.0), abs=1e-4)
    assert set(b.support.tolist()) <= set(cand.tolist())
    assert b.n_candidates == cand.size
    assert b.value >= brute_force_best(Y, 3, 0.0, cand) - 1e-9


def test_dual_function_bounds_the_optimum_at_random_points():
    rng = np.random.default_rng(11)
    k, L, n, ridge = 3, 40, 5.5, 0.2
    Y = smooth_Y(k, L, 3)
    opt = plain_relaxation(Y, n, ridge)
    for _ in range(20):
        # random Z: any positive definite matrix and nu >= 0 give an upper bound
        A = rng.standard_normal((k, k))
        Z = A @ A.T + 0.1 * np.eye(k)
        assert dual_value(Y, Z, rng.uniform(0, 3), n, ridge=ridge) >= opt - 1e-7
        # random feasible w: the closed-form certificate is an upper bound, primal a lower one
        w = rng.uniform(0, 1, L)
        w *= min(1.0, n / w.sum()) * rng.uniform(0.3, 1)
        value, primal = certify_weights(Y, w, n, ridge=ridge)
        assert value >= opt - 1e-7
        assert primal <= opt + 1e-7
        assert primal == pytest.approx(logdet(ridge * np.eye(k) + (Y * w) @ Y.T))


@pytest.mark.parametrize("n", [1.0, 2.0, 3.7, 6.0, 39.5, 50.0])
def test_closed_form_scale_and_multiplier_match_a_scan(n):
    rng = np.random.default_rng(int(n * 10))
    k, L, ridge = 3, 40, 0.3
    Y = rng.standard_normal((k, L))
    w = rng.uniform(0, 1, L) * min(1.0, n / L)
    M = ridge * np.eye(k) + (Y * w) @ Y.T
    Minv = np.linalg.inv(M)
    value, primal = certify_weights(Y, w, n, ridge=ridge)
    # closed form: t = k / S, nu = t * mu with mu from the sort
    g = np.einsum("ai,ab,bi->i", Y, Minv, Y)
    top, mu = D._top_sum(g, n)
    S = ridge * np.trace(Minv) + top
    t_best = k / S
    closed = dual_value(Y, t_best * Minv, t_best * mu, n, ridge=ridge)
    assert closed == pytest.approx(value, abs=1e-9)
    # brute-force scan over t and nu of g(t M^-1, nu) never goes below the closed form ...
    ts = t_best * np.exp(np.linspace(-1.5, 1.5, 61))
    nus = np.concatenate([[0.0], np.sort(g) * 1.0, np.linspace(0, g.max() * 1.2, 60)])
    scan = min(dual_value(Y, t * Minv, t * nu, n, ridge=ridge) for t in ts for nu in nus * 1)
    scan_scaled = min(
        dual_value(Y, t * Minv, t * nu, n, ridge=ridge) for t in ts for nu in np.sort(g)
    )
    assert scan >= closed - 1e-9
    assert scan_scaled >= closed - 1e-9
    # ... and reaches it (the breakpoints nu = g_(j) and the grid of t contain the optimum)
    fine_t = t_best * np.exp(np.linspace(-0.01, 0.01, 21))
    assert min(dual_value(Y, t * Minv, t * mu, n, ridge=ridge) for t in fine_t) == pytest.approx(
        closed, abs=1e-9
    )
    # the closed form matches log det M + k log(S / k)
    assert closed == pytest.approx(primal + k * math.log(S / k), abs=1e-9)


def test_top_sum_matches_sorting():
    rng = np.random.default_rng(0)
    g = rng.uniform(0, 1, 30)
    desc = np.sort(g)[::-1]
    for n in [0.3, 1, 2.5, 7, 29.9, 30, 45]:
        m = math.floor(n)
        expect = desc[:m].sum() + (n - m) * (desc[m] if m < g.size else 0.0)
        got, mu = D._top_sum(g, n)
        assert got == pytest.approx(expect)
        # mu minimises mu n + sum max(0, g - mu)
        def obj(x, n=n):
            return x * n + np.maximum(g - x, 0).sum()

        assert obj(mu) == pytest.approx(min(obj(x) for x in np.concatenate([[0], g])))


def test_dual_at_least_primal_converges_and_scale_invariant():
    Y = smooth_Y(4, 3000, 5)
    b = dopt_upper_bound(Y, 30, tol=1e-3)
    assert b.status == "optimal" and 0 <= b.gap <= 1e-3
    assert b.value >= b.primal
    s = 1000.0
    b2 = dopt_upper_bound(Y * s, 30, tol=1e-3)
    assert b2.value == pytest.approx(b.value + 2 * 4 * math.log(s), abs=1e-6)
    assert b2.primal == pytest.approx(b.primal + 2 * 4 * math.log(s), abs=1e-6)
    # with a ridge, scaling Y by s and ridge by s^2 shifts the value the same way
    b3 = dopt_upper_bound(Y, 30, ridge=0.01, tol=1e-3)
    b4 = dopt_upper_bound(Y * s, 30, ridge=0.01 * s * s, tol=1e-3)
    assert b4.value == pytest.approx(b3.value + 2 * 4 * math.log(s), abs=1e-6)


def test_column_generation_equals_solving_all_candidates_at_once():
    k, L, n = 5, 2500, 40
    Y = smooth_Y(k, L, 9)
    b = dopt_upper_bound(Y, n, tol=1e-6)
    assert b.n_working < L  # column generation did not need every cell
    # one cvxpy solve over every candidate at once (no working set, no scaling)
    w_all, status = D._solve_restricted(Y, np.zeros((k, k)), n, "CLARABEL")
    assert w_all is not None, status
    v_all, p_all = certify_weights(Y, D._feasible(w_all, n), n)
    assert b.primal == pytest.approx(p_all, abs=1e-5)
    assert b.value == pytest.approx(v_all, abs=1e-5)


def test_trivial_singular_and_bad_input():
    Y = np.random.default_rng(0).standard_normal((3, 8))
    b = dopt_upper_bound(Y, 20)
    assert b.status == "trivial" and b.gap == 0
    assert b.value == pytest.approx(logdet(Y @ Y.T))
    assert np.array_equal(b.weights.toarray(), np.ones(8))
    # rank 2 < k = 3 with no ridge: every plan has information -inf, so the bound is -inf
    Ysing = np.vstack([Y[:2], Y[0] + Y[1]])
    s = dopt_upper_bound(Ysing, 4)
    assert s.status == "singular" and s.value == -math.inf
    assert np.linalg.matrix_rank(Ysing) == 2  # so every subset's matrix is singular
    # a ridge makes it finite
    assert math.isfinite(dopt_upper_bound(Ysing, 4, ridge=0.1).value)
    for bad in [0, -1, math.nan, math.inf, "x"]:
        with pytest.raises(PlanningError, match="n must"):
            dopt_upper_bound(Y, bad)
    with pytest.raises(PlanningError, match="ridge"):
        dopt_upper_bound(Y, 2, ridge=-1e-3)
    with pytest.raises(PlanningError, match="candidates"):
        dopt_upper_bound(Y, 2, candidates=[0, 8])
    with pytest.raises(PlanningError, match="solver"):
        dopt_upper_bound(Y, 2, solver="MOSEK")


def test_inexact_solver_still_certifies(monkeypatch):
    """With every conic solve failing, the Frank-Wolfe iterate still yields a valid bound."""
    Y = smooth_Y(3, 120, 1)
    monkeypatch.setattr(D, "_solve_restricted", lambda *a, **k: (None, "forced failure"))
    opt = plain_relaxation(Y, 6, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        b = dopt_upper_bound(Y, 6, tol=1e-9, fw_iter=3)
    assert b.solver == "Frank-Wolfe"
    assert b.value >= opt - 1e-9 and b.primal <= opt + 1e-9


# ----------------------------------------------------------------------------- plan bound
def _grid_Y(region: Region, k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r, c = region.grid_index.T.astype(float)
    modes = [np.ones_like(r)] + [
        np.cos(rng.uniform(0.1, 0.8) * r + rng.uniform(0, 6)) * np.cos(rng.uniform(0.1, 0.8) * c)
        for _ in range(k - 1)
    ]
    return np.vstack(modes) + 0.05 * rng.standard_normal((k, region.n_cells))


@pytest.mark.parametrize("budget, k, ridge", [(0.5, 2, 0.0), (1.5, 2, 0.0), (2.3, 3, 0.0),
                                              (3.0, 2, 0.01), (1.0, 4, 0.0)])
def test_plan_bound_covers_every_feasible_set_brute_force(budget, k, ridge):
    from lrm_cvx.planning.greedy import initial_cells

    region = make_region(6, 6, masked=[(2, 3), (4, 1), (0, 0)])
    Y = _grid_Y(region, k, 3)
    start = int(region.cell_grid[2, 2])
    # the plain disk relaxation: bounds every set of <= n_max cells within the budget
    cert = B.plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6, tighten=False)
    d = region.distance(start, np.arange(region.n_cells))
    disk = np.flatnonzero(d <= budget)
    n_max = math.floor(budget) + 1
    assert cert.n_max == min(n_max, disk.size) and cert.n_candidates == disk.size
    best = brute_force_best(Y, n_max, ridge, disk)
    init = initial_cells(region, start, k)
    Yi = Y[:, init]
    best = max(best, logdet(ridge * np.eye(k) + Yi @ Yi.T))
    assert cert.bound >= best - 1e-9
    assert cert.initial_information == pytest.approx(logdet(ridge * np.eye(k) + Yi @ Yi.T))
    assert cert.information is None and "upper bound" in repr(cert)


def test_plan_bound_with_a_plan_reports_gap_and_online_bound():
    from types import SimpleNamespace

    region = make_region(7, 7, masked=[(1, 1)])
    k, budget = 3, 3.0
    Y = _grid_Y(region, k, 8)
    start = int(region.cell_grid[3, 3])
    # a feasible path: the start and three cells to its right
    cells = np.array([region.cell_grid[3, 3 + j] for j in range(4)])
    plan = SimpleNamespace(cells=cells, start=start, budget=budget)
    cert = B.plan_bound(Y, region, start, budget, plan=plan, tol=1e-6)
    info = logdet(Y[:, cells] @ Y[:, cells].T)
    assert cert.information == pytest.approx(info)
    assert cert.gap == pytest.approx(cert.bound - info) and cert.gap >= 0
    assert cert.volume_ratio == pytest.approx(math.exp(-cert.gap / k))
    # the online bound is an upper bound too: check it against brute force
    disk = np.flatnonzero(region.distance(start, np.arange(region.n_cells)) <= budget)
    best = brute_force_best(Y, 4, 0.0, disk)
    assert cert.online_bound is not None and cert.online_bound >= best - 1e-9
    assert cert.bound <= max(cert.initial_information, cert.relaxation.value) + 1e-12
    assert "certified gap" in repr(cert) and "<table>" in cert._repr_html_()
    # an infeasible plan (too many cells for the budget) is refused
    far = SimpleNamespace(cells=np.arange(10), start=start, budget=budget)
    with pytest.raises(PlanningError, match="not feasible"):
        B.plan_bound(Y, region, start, budget, plan=far)


def test_plan_bound_km_metric_uses_the_smallest_spacing():
    lat = xr.DataArray(np.linspace(40.0, 41.0, 6), dims=("lat",))
    lon = xr.DataArray(np.linspace(10.0, 11.5, 7), dims=("lon",))
    region = Region(lat=lat, lon=lon, mask=np.ones((6, 7), bool))
    Y = _grid_Y(region, 2, 1)
    start = int(region.cell_grid[3, 3])
    cand = np.arange(region.n_cells)
    D = region.distance(cand[:, None], cand[None, :], metric="km")
    dmin = D[~np.eye(cand.size, dtype=bool)].min()
    assert min_spacing_km(region, cand) == pytest.approx(dmin, rel=1e-8)
    assert min_spacing_km(region, cand) <= dmin
    budget = 2.5 * dmin
    cert = B.plan_bound(Y, region, start, budget, tol=1e-6, tighten=False,
                        path=PathOptions(metric="km"))
    disk = np.flatnonzero(D[start] <= budget)
    assert cert.n_max == 3 and cert.n_candidates == disk.size
    assert cert.bound >= brute_force_best(Y, 3, 0.0, disk) - 1e-9
    # tightened (distance limits from the start): still covers every path-feasible set
    tight = B.plan_bound(Y, region, start, budget, tol=1e-6, path=PathOptions(metric="km"))
    best = max(logdet(Y[:, sorted(S)] @ Y[:, sorted(S)].T)
               for S in path_feasible_sets(D, start, budget))
    assert best - 1e-9 <= tight.bound <= cert.bound + 1e-6


def test_plan_bound_bad_input():
    region = make_region(4, 4)
    Y = _grid_Y(region, 2, 0)
    with pytest.raises(PlanningError, match="budget"):
        B.plan_bound(Y, region, 0, -1.0)
    with pytest.raises(PlanningError, match="metric"):
        B.plan_bound(Y, region, 0, 2.0, path=PathOptions(metric="miles"))
    with pytest.raises(PlanningError, match="ridge"):
        B.plan_bound(Y, region, 0, 2.0, ridge=-1)


@st.composite
def planning_instances(draw):
    ny = draw(st.integers(8, 15))
    nx = draw(st.integers(8, 15))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    mask = rng.uniform(size=(ny, nx)) > draw(st.sampled_from([0.0, 0.1, 0.25]))
    valid = np.argwhere(mask)
    r, c = valid[rng.integers(len(valid))]
    masked = [tuple(p) for p in np.argwhere(~mask)]
    region = make_region(ny, nx, masked=masked)
    k = draw(st.integers(2, 4))
    budget = draw(st.floats(3.0, 20.0))
    return region, int(region.cell_grid[r, c]), k, budget, seed


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(planning_instances())
def test_plan_bound_covers_greedy_and_baseline_plans(instance):
    from lrm_cvx.planning import plan_greedy, random_walk, transect

    region, start, k, budget, seed = instance
    Y = _grid_Y(region, k, seed)
    cert = B.plan_bound(Y, region, start, budget, tighten={"max_pieces": 8})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        plans = [plan_greedy(Y, region, start, budget, progress=False)]
    plans += [transect(region, start, budget, d, Y=Y) for d in ("up", "down", "left", "right")]
    plans += [random_walk(region, start, budget, seed + j, Y=Y) for j in range(3)]
    for plan in plans:
        info = logdet(Y[:, plan.cells] @ Y[:, plan.cells].T)
        assert cert.bound >= info - 1e-9, (plan.method, cert.bound, info)
    greedy_cert = plans[0].certify(tighten={"max_pieces": 8})
    assert greedy_cert.gap >= -1e-9
    assert greedy_cert.bound <= cert.bound + 1e-9
    assert greedy_cert.information == pytest.approx(plans[0].information)


# ----------------------------------------------------------------------------- tightening
def path_feasible_sets(D: np.ndarray, start: int, budget: float) -> set[frozenset]:
    """Every set of cells an open path from ``start`` of length <= budget visits (exhaustive
    depth-first search over visiting orders; D is the full distance matrix)."""
    near = np.flatnonzero(D[start] <= budget + 1e-9).tolist()
    out: set[frozenset] = set()

    def dfs(cur: int, used: list[int], length: float) -> None:
        out.add(frozenset(used))
        for c in near:
            if c not in used and length + D[cur, c] <= budget + 1e-9:
                used.append(c)
                dfs(c, used, length + D[cur, c])
                used.pop()

    dfs(start, [start], 0.0)
    return out


def grid_distances(region: Region) -> np.ndarray:
    pos = region.grid_index.astype(float)
    return np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))


def random_levels(rng, N: int, J: tuple[int, ...]) -> tuple[list, list]:
    levels = [rng.integers(0, j + 1, N) for j in J]
    caps = [np.sort(rng.integers(1, 6, j).astype(float))[::-1] for j in J]
    return levels, caps


def test_polytope_lp_reduction_and_dual_term_match_the_full_lp():
    from scipy.optimize import linprog

    rng = np.random.default_rng(4)
    for trial in range(15):
        N = int(rng.integers(20, 200))
        poly = D._Polytope(float(rng.integers(3, 12)), N, *random_levels(rng, N, (3, 4)))
        g = rng.uniform(0, 1, N)
        if trial % 3 == 0:  # ties, as on a smooth field
            g = np.round(g, 1)
        A, b = poly._rows(np.arange(N))
        full = -linprog(-g, A_ub=A, b_ub=b, bounds=(0, 1), method="highs").fun
        top, (nu, mus) = poly.support(g)  # LP on the reduced cells, h evaluated on all
        assert top == pytest.approx(full, abs=1e-7)
        # h is an upper bound at any multipliers
        for _ in range(5):
            mus_r = [rng.uniform(0, 0.5, m.size) for m in mus]
            assert poly.h(g, rng.uniform(0, 0.5), mus_r) >= full - 1e-9
        idx, s = poly.vertex(g)
        v = np.zeros(N)
        v[idx] = s
        assert poly.is_feasible(v) and g @ v == pytest.approx(full, abs=1e-5)
        # uniform and projected designs are feasible
        assert poly.is_feasible(poly.uniform())
        assert poly.is_feasible(poly.project(rng.uniform(0, 1.2, N)))


def limited_cvxpy(Y, n, limits, ridge=0.0):
    k, L = Y.shape
    w = cp.Variable(L)
    cons = [w >= 0, w <= 1, cp.sum(w) <= n]
    for vals, thr, caps in limits:
        for t, c in zip(thr, caps, strict=True):
            cons.append(cp.sum(w[np.flatnonzero(vals >= t)]) <= c)
    prob = cp.Problem(cp.Maximize(cp.log_det(Y @ cp.diag(w) @ Y.T + ridge * np.eye(k))), cons)
    prob.solve(solver="CLARABEL")
    assert prob.status == "optimal"
    return float(prob.value)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_limits_relaxation_matches_cvxpy_brute_force_and_random_duals(seed):
    rng = np.random.default_rng(seed)
    k, L, n, ridge = 3, 14, 5, 0.05 * seed
    Y = rng.standard_normal((k, L))
    limits = [(rng.uniform(0, 10, L), [3.0, 6.0, 8.0], [4, 2, 1]),
              (rng.uniform(0, 5, L), [1.0, 2.5, 4.0], [4, 3, 1])]
    b = dopt_upper_bound(Y, n, limits=limits, ridge=ridge, tol=1e-6)
    opt = limited_cvxpy(Y, n, limits, ridge)
    assert b.value == pytest.approx(opt, abs=1e-4) and b.primal <= b.value
    w = b.weights.toarray()
    for vals, thr, caps in limits:
        for t, c in zip(thr, caps, strict=True):
            assert w[vals >= t].sum() <= c + 1e-9
    # brute force over the subsets that satisfy the limits
    best = -math.inf
    for m in range(1, n + 1):
        for S in itertools.combinations(range(L), m):
            S = list(S)
            if all((v[S] >= t).sum() <= c for v, thr, caps in limits
                   for t, c in zip(thr, caps, strict=True)):
                best = max(best, logdet(ridge * np.eye(k) + Y[:, S] @ Y[:, S].T))
    assert b.value >= best - 1e-9
    assert b.value <= dopt_upper_bound(Y, n, ridge=ridge, tol=1e-6).value + 1e-6
    # the dual function with the limits' multipliers bounds the optimum at random points
    for _ in range(10):
        A = rng.standard_normal((k, k))
        Z = A @ A.T + 0.1 * np.eye(k)
        nu = rng.uniform(0, 1)
        mus = [rng.uniform(0, 1, 3) for _ in limits]
        price = nu + sum(
            sum(mu_j * (v >= t) for mu_j, t in zip(mu, thr, strict=True)) for mu, (v, thr, _) in
            zip(mus, limits, strict=True)
        )
        q = np.einsum("ai,ab,bi->i", Y, Z, Y)
        dual = (-logdet(Z) - k + ridge * np.trace(Z) + nu * n
                + sum(mu @ np.asarray(c, float) for mu, (_, _, c) in zip(mus, limits, strict=True))
                + np.maximum(q - price, 0).sum())
        assert dual >= opt - 1e-7


def test_limits_bad_input():
    Y = np.random.default_rng(0).standard_normal((2, 6))
    v = np.arange(6.0)
    with pytest.raises(PlanningError, match="triple"):
        dopt_upper_bound(Y, 2, limits=[(v, [1.0])])
    with pytest.raises(PlanningError, match="shape"):
        dopt_upper_bound(Y, 2, limits=[(v[:3], [1.0], [1.0])])
    with pytest.raises(PlanningError, match="ascending"):
        dopt_upper_bound(Y, 2, limits=[(v, [2.0, 1.0], [1.0, 1.0])])
    with pytest.raises(PlanningError, match="caps"):
        dopt_upper_bound(Y, 2, limits=[(v, [1.0], [-1.0])])
    region = make_region(4, 4)
    Yr = _grid_Y(region, 2, 0)
    with pytest.raises(PlanningError, match="cover"):
        B.plan_bound(Yr, region, 0, 3.0, tighten={"cover": 0})
    with pytest.raises(PlanningError, match="max_pieces"):
        B.plan_bound(Yr, region, 0, 3.0, tighten={"max_pieces": 0})
    with pytest.raises(PlanningError, match="tighten"):
        B.plan_bound(Yr, region, 0, 3.0, tighten={"pieces": 3})


def test_path_limits_hold_on_random_paths():
    """The lemmas behind the tightening, checked on many random paths (no solver involved)."""
    rng = np.random.default_rng(5)
    region = make_region(25, 25)
    D = grid_distances(region)
    pos = region.grid_index.astype(float)
    for _trial in range(300):
        budget = float(rng.uniform(2, 12))
        Bp = budget + 1e-9 * max(1, budget)
        start = int(rng.integers(region.n_cells))
        # a random path: random cells near the current one while the budget lasts
        path, length = [start], 0.0
        while True:
            cur = path[-1]
            near = np.flatnonzero((D[cur] <= rng.uniform(1, 4)) & (D[cur] > 0))
            near = near[~np.isin(near, path)]
            if near.size == 0:
                break
            c = int(rng.choice(near))
            if length + D[cur, c] > budget:
                break
            path.append(c)
            length += D[cur, c]
        cells = np.array(path)
        n_max = math.floor(Bp) + 1
        thr, caps = start_limit(Bp, 1.0, n_max) or (np.zeros(0), np.zeros(0))
        d = D[start, cells]
        assert np.all((d[:, None] >= thr[None, :]).sum(axis=0) <= caps)
        # the midpoint (by arc length) and the square of the cover that holds it
        steps = D[cells[:-1], cells[1:]]
        arc = np.concatenate([[0.0], np.cumsum(steps)])
        T = arc[-1]
        j = min(int(np.searchsorted(arc, T / 2, side="right")) - 1, len(cells) - 2)
        if len(cells) == 1:
            mid = pos[start]
        else:
            t = (T / 2 - arc[j]) / steps[j]
            mid = pos[cells[j]] + t * (pos[cells[j + 1]] - pos[cells[j]])
        assert np.hypot(*(mid - pos[start])) <= T / 2 + 1e-9
        assert np.all(np.hypot(*(pos[cells] - mid).T) <= T / 2 + 1e-9)
        c0 = pos[start]
        squares = C._cover_squares(c0, Bp / 2, c0[0] - Bp / 2, c0[1] - Bp / 2, Bp, 4)
        squares = [c for q in squares for c in C._cover_squares(c0, Bp / 2, *q, 2)]
        holds = [q for q in squares if C.square_distance(mid[None], *q)[0] == 0]
        assert holds, "the cover misses the midpoint"
        sthr, scaps = C._square_limit(Bp, n_max)
        for q in holds:
            dq = C.square_distance(pos[cells], *q)
            assert np.all(dq <= Bp / 2 + 1e-9)
            assert np.all((dq[:, None] >= sthr[None, :]).sum(axis=0) <= scaps)
        # and the certificate's own plan check accepts it
        plan = SimpleNamespace(cells=cells, start=start)
        C.check_plan_limits(cells, np.array([-1]), region, D[start], (thr, caps),
                            [(*q, 0.0) for q in squares], Bp, n_max, plan)


@pytest.mark.parametrize("budget, k, ridge", [(2.3, 3, 0.0), (3.0, 2, 0.0), (3.6, 3, 0.0),
                                              (4.2, 3, 0.01), (4.5, 2, 0.0)])
def test_tightened_bound_covers_every_path_feasible_set_brute_force(budget, k, ridge):
    from lrm_cvx.planning.greedy import initial_cells

    region = make_region(7, 7, masked=[(2, 3), (4, 1), (0, 0)])
    Y = _grid_Y(region, k, 3)
    start = int(region.cell_grid[3, 3])
    sets = path_feasible_sets(grid_distances(region), start, budget)
    best = max(logdet(ridge * np.eye(k) + Y[:, sorted(S)] @ Y[:, sorted(S)].T) for S in sets)
    init = initial_cells(region, start, k)
    best = max(best, logdet(ridge * np.eye(k) + Y[:, init] @ Y[:, init].T))
    tight = B.plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6)
    loose = B.plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6, tighten=False)
    assert tight.tightened and len(tight.leaves) >= 4
    assert best - 1e-9 <= tight.bound <= loose.bound + 1e-6
    assert tight.bound < loose.bound - 0.1  # the tightening does something here
    # no refinement at all is valid too (and looser or equal)
    coarse = B.plan_bound(Y, region, start, budget, ridge=ridge, tol=1e-6,
                          tighten={"max_pieces": 1})
    assert best - 1e-9 <= coarse.bound and tight.bound <= coarse.bound + 1e-6
