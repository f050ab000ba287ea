"""The variance certificate: plan_bound(criterion="gp-variance" / "a-optimal") and certify().

Validity against brute force over every feasible route on tiny grids, the Frank-Wolfe bound
against an independent cvxpy solution of the same relaxation, the relaxed objective at a plan's
indicator against the planner's own value, and the bad inputs' one-line errors.
"""

from __future__ import annotations

import functools
import itertools
import math

import cvxpy as cp
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError
from lrm_cvx.information import a_optimal_value, gp_latent_cov, gp_variance_value
from lrm_cvx.planning import PathOptions, PriorTerms, plan_bound, plan_greedy, transect, varbound
from lrm_cvx.planning.dopt import Polytope
from lrm_cvx.planning.varbound import _fw_bound, variance_objective, variance_relaxation
from lrm_cvx.spatial import ResidualCovariance

RIDGE = 0.1
COV = ResidualCovariance("exponential", 0.5, 2.0, 0.1)


def grid(ny: int = 5, nx: int = 5) -> Region:
    lat, lon = np.linspace(ny - 1, 0, ny), np.linspace(0, nx - 1, nx)
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                  mask=np.ones((ny, nx), bool))


REGION = grid()
Y = np.random.default_rng(3).standard_normal((2, REGION.n_cells))
START = int(REGION.cell_grid[2, 2])
GP_TERMS = dict(spatial_cov=COV, prior_cov=np.eye(2))
GP = dict(prior=PriorTerms(**GP_TERMS))


def reduction(criterion: str, cells) -> float:
    """The planner's value of observing ``cells``: variance removed (reference functions)."""
    cells = np.asarray(sorted(set(int(c) for c in cells)), dtype=np.int64)
    if criterion == "gp-variance":
        return (gp_variance_value(Y, REGION, COV, np.eye(2), [])
                - gp_variance_value(Y, REGION, COV, np.eye(2), cells))
    return a_optimal_value(Y, [], RIDGE) - a_optimal_value(Y, cells, RIDGE)


def route_length(pos: np.ndarray, order, closed: bool) -> float:
    pts = pos[list(order)]
    legs = np.hypot(*np.diff(pts, axis=0).T).sum()
    return float(legs + (np.hypot(*(pts[-1] - pts[0])) if closed else 0.0))


def best_route_value(criterion: str, start: int, budget: float, closed: bool) -> float:
    """Exhaustive: the best value of the cells of any route from ``start`` of length <=
    ``budget`` (every ordering of every set of cells within reach)."""
    pos = REGION.grid_index.astype(float)
    d = np.hypot(*(pos - pos[start]).T)
    reach = [int(c) for c in np.flatnonzero(d <= budget + 1e-9) if c != start]
    best = -math.inf
    m = 0
    while True:
        found = False
        for S in itertools.combinations(reach, m):
            if any(route_length(pos, (start, *perm), closed) <= budget + 1e-9
                   for perm in itertools.permutations(S)):
                found = True
                best = max(best, reduction(criterion, (start, *S)))
        if not found:
            return best
        m += 1


# ------------------------------------------------------------------------- validity
@pytest.mark.parametrize("criterion", ["gp-variance", "a-optimal"])
@pytest.mark.parametrize(("budget", "closed", "tight"),
                         [(2.5, False, {"tighten": {"cover": 1, "max_pieces": 4}}),
                          (3.0, True, {"tighten": False})])
def test_bound_is_above_every_feasible_route(criterion, budget, closed, tight):
    kw = GP if criterion == "gp-variance" else {}
    plan = plan_greedy(Y, REGION, START, budget, criterion=criterion, ridge=RIDGE, initial="start",
                       progress=False, path=PathOptions(closed=closed), **kw)
    cert = plan.certify(**tight)  # the midpoint cover (one square a quarter) or not
    assert cert.criterion == criterion and cert.comparable
    best = best_route_value(criterion, START, budget, closed)
    assert cert.bound >= best - 1e-9
    assert cert.information <= best + 1e-9  # the plan is one of the routes
    assert cert.gap == pytest.approx(cert.bound - cert.information, abs=1e-9)
    assert 0 <= cert.relative_gap < 1


def test_bound_covers_the_forced_initial_set_and_a_fleet():
    # initial="nearest": the plan may be the forced set, which lies beyond a tiny budget
    plan = plan_greedy(Y, REGION, START, 0.5, criterion="gp-variance", ridge=RIDGE,
                       progress=False, **GP)
    cert = plan.certify()
    assert cert.bound >= reduction("gp-variance", plan.cells) - 1e-9
    assert cert.initial_information == pytest.approx(reduction("gp-variance", plan.cells))
    # a fleet of two: the union of two routes' cells, each within its own budget
    a, b = int(REGION.cell_grid[0, 0]), int(REGION.cell_grid[4, 4])
    fleet = plan_greedy(Y, REGION, [a, b], [1.5, 1.5], criterion="gp-variance",
                        initial="start", progress=False, **GP)
    cert = fleet.certify()
    pos = REGION.grid_index.astype(float)
    best = -math.inf
    near = {s: [int(c) for c in np.flatnonzero(np.hypot(*(pos - pos[s]).T) <= 1.5 + 1e-9)
                if c != s] for s in (a, b)}

    def routes(s):
        for m in range(3):
            for S in itertools.combinations(near[s], m):
                if any(route_length(pos, (s, *p), False) <= 1.5 + 1e-9
                       for p in itertools.permutations(S)):
                    yield (s, *S)

    for ra in routes(a):
        for rb in routes(b):
            best = max(best, reduction("gp-variance", ra + rb))
    assert cert.bound >= best - 1e-9 and cert.information <= best + 1e-9


@pytest.mark.parametrize("criterion", ["gp-variance", "a-optimal"])
def test_relaxed_objective_at_a_plan_is_the_planners_value(criterion):
    kw = GP if criterion == "gp-variance" else {}
    plan = plan_greedy(Y, REGION, START, 4, criterion=criterion, ridge=RIDGE, initial="start",
                       progress=False, **kw)
    cert = plan.certify(tighten=False, tol=1e-2)
    assert cert.information == pytest.approx(reduction(criterion, plan.cells), rel=1e-10)


# ------------------------------------------------------------------------- against cvxpy
def cvx_optimum(criterion: str, cells: np.ndarray, n: float) -> float:
    """The relaxation's optimum by cvxpy, built here from the model's matrices (latent form:
    the trend's prior plus, for gp-variance, the residual field on the candidates)."""
    if criterion == "a-optimal":
        W = Y @ Y.T
        w = cp.Variable(cells.size, nonneg=True)
        A = Y[:, cells]
        M = RIDGE * np.eye(2) + A @ cp.diag(w) @ A.T
        lam, V = np.linalg.eigh(W)
        R = V * np.sqrt(np.maximum(lam, 0))
        obj = np.trace(W) / RIDGE - cp.matrix_frac(R, 0.5 * (M + M.T))
    else:
        T = np.arange(REGION.n_cells)
        K = gp_latent_cov(Y, np.eye(2), REGION, COV, cells, cells)
        KcT = gp_latent_cov(Y, np.eye(2), REGION, COV, cells, T)
        L = np.linalg.cholesky(K)
        Li = np.linalg.inv(L)
        Wz = Li @ KcT @ KcT.T @ Li.T
        lam, V = np.linalg.eigh(0.5 * (Wz + Wz.T))
        R = V * np.sqrt(np.maximum(lam, 0))
        w = cp.Variable(cells.size, nonneg=True)
        P = np.eye(cells.size) + (L.T / COV.nugget) @ cp.diag(w) @ L
        obj = float(np.trace(Wz)) - cp.matrix_frac(R, 0.5 * (P + P.T))
    prob = cp.Problem(cp.Maximize(obj), [w <= 1, cp.sum(w) <= n])
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    return float(prob.value)


@settings(max_examples=4, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), n=st.sampled_from([1.0, 2.5, 4.0]),
       criterion=st.sampled_from(["gp-variance", "a-optimal"]))
def test_frank_wolfe_bound_equals_the_cvxpy_optimum(seed, n, criterion):
    rng = np.random.default_rng(seed)
    cells = np.sort(rng.choice(REGION.n_cells, 8, replace=False))
    terms = dict(GP_TERMS, region=REGION) if criterion == "gp-variance" else {}
    obj = variance_objective(criterion, Y, cells, RIDGE, terms)
    b = variance_relaxation(obj, np.arange(cells.size), Polytope(n, cells.size), iters=40,
                            tol=1e-9, polish=True, rank_bound=False)
    opt = cvx_optimum(criterion, cells, n)
    assert b.value >= opt * (1 - 1e-7)  # a valid bound (cvxpy's value is accurate to ~1e-8)
    assert b.value == pytest.approx(opt, rel=1e-6)  # and tight at convergence
    assert b.primal <= b.value


def test_frank_wolfe_alone_is_a_valid_bound_at_any_iterate():
    cells = np.arange(12)
    obj = variance_objective("gp-variance", Y, cells, RIDGE, dict(GP_TERMS, region=REGION))
    poly = Polytope(3, cells.size)
    exact = variance_relaxation(obj, cells, poly, iters=30, tol=1e-9, polish=True,
                                rank_bound=False)
    for iters in (1, 3, 10):
        b = variance_relaxation(obj, cells, poly, iters=iters, polish=False, rank_bound=False)
        assert b.value >= exact.primal - 1e-9 and b.primal <= exact.value + 1e-9
    best = max(obj.value(np.asarray(S), np.ones(3))
               for S in itertools.combinations(range(cells.size), 3))
    assert exact.value >= best - 1e-9


# ------------------------------------------------------------------------- the object
def test_certify_defaults_to_the_plans_criterion_and_fisher_is_one_keyword_away():
    plan = plan_greedy(Y, REGION, START, 3, criterion="gp-variance", initial="start",
                       refine="rivals", progress=False, **GP)
    cert = plan.certify(tighten={"cover": 1, "max_pieces": 4})
    assert cert.criterion == "gp-variance" and cert.unit == "unit^2"
    assert np.isfinite(cert.gap) and cert.relative_gap == pytest.approx(cert.gap / cert.bound)
    # the gap split: the greedy's route vs the route kept, then the bound's slack
    assert cert.greedy_information <= cert.refined_information + 1e-12
    assert cert.refined_information == cert.information
    assert cert.plan_slack + cert.bound_slack == pytest.approx(
        cert.bound - cert.greedy_information)
    text = repr(cert)
    assert "certified gap" in text and "unit^2" in text and "nats" not in text
    assert "gp-variance" in cert._repr_html_()
    fisher = plan.certify(criterion="fisher", tighten=False)
    assert fisher.criterion == "fisher" and math.isnan(fisher.gap)
    assert fisher.bound == plan_bound(Y, REGION, START, 3, plan=plan, tighten=False).bound


def test_baseline_and_fisher_plans_under_a_variance_bound():
    walk = transect(REGION, START, 2, "up", Y=Y, ridge=RIDGE)
    cert = plan_bound(Y, REGION, START, 2, plan=walk, criterion="a-optimal", ridge=RIDGE)
    assert cert.comparable and cert.gap >= 0
    assert cert.information == pytest.approx(reduction("a-optimal", walk.cells))
    fisher = plan_greedy(Y, REGION, START, 2, ridge=RIDGE, progress=False)
    cert = plan_bound(Y, REGION, START, 2, plan=fisher, criterion="a-optimal", ridge=RIDGE)
    assert not cert.comparable and math.isnan(cert.gap) and "no gap" in repr(cert)


# ------------------------------------------------------------------------- bad input
def test_bad_inputs_get_one_line_errors():
    plan = plan_greedy(Y, REGION, START, 2, criterion="gp-variance", initial="start",
                       progress=False, **GP)
    other = np.random.default_rng(9).standard_normal(Y.shape)
    cases = {
        "another model": (lambda: plan_bound(other, REGION, START, 2, plan=plan,
                                             criterion="gp-variance"), "another model"),
        "criterion": (lambda: plan.certify(criterion="risk"), "criterion must be"),
        "no terms": (lambda: plan_bound(Y, REGION, START, 2, criterion="gp-variance"),
                     "needs the criterion's terms"),
        "unknown prior": (lambda: plan.certify(prior={"spatial": COV}), "PriorTerms"),
        "footprint": (lambda: plan_bound(Y, REGION, START, 2, criterion="gp-variance", **GP,
                                         path=PathOptions(sensor="disc:1")), "point sensors only"),
        "path_aware": (lambda: plan.certify(path_aware=True), "Fisher criterion only"),
        "no ridge": (lambda: plan_bound(Y, REGION, START, 2, criterion="a-optimal"),
                     "ridge > 0"),
    }
    for name, (call, match) in cases.items():
        with pytest.raises(PlanningError, match=match) as err:
            call()
        assert "\n" not in str(err.value), name


# ------------------------------------------------------------------------- CLI
def test_cli_bound_reports_the_variance_gap_and_fisher_on_request(tmp_path, capsys):
    from lrm_cvx import GLRM, load_sample
    from lrm_cvx.cli import main

    path = tmp_path / "model.nc"
    GLRM(rank=2, offset=True, spatial="exponential", random_state=0,
         progress=False).fit(load_sample("sst").isel(time=slice(0, 20))).save(path)
    argv = ["-q", "bound", str(path), "--start", "10,-150", "--budget", "2", "--certify",
            "fast"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "gp-variance criterion (variance removed)" in out and "unit^2" in out
    gap = next(x for x in out.splitlines() if x.startswith("optimality gap"))
    assert "% of the bound" in gap and "not reported" not in gap
    assert main([*argv, "--fisher"]) == 0
    out = capsys.readouterr().out
    assert "fisher criterion" in out and "nats" in out and "not reported" in out


def test_objective_takes_a_dataarray_factor_matrix():
    cells = np.arange(6)
    a = variance_objective("a-optimal", Y, cells, RIDGE, {})
    b = variance_objective("a-optimal", xr.DataArray(Y, dims=("rank", "cell")), cells, RIDGE, {})
    w = np.linspace(0.1, 1.0, 6)
    assert a.value(cells, w) == b.value(cells, w)


# ------------------------------------------------------------------------- structured objective
def structured_case(kind: str) -> tuple[np.ndarray, dict, np.ndarray]:
    """``(Y, terms, cells)``: an interior pool with equal target weights (the residual's lag
    table) or a pool along the grid's edge with unequal weights (a convolution per cell)."""
    rng = np.random.default_rng(11)
    if kind == "lag-table":
        region = grid(30, 30)
        cov = ResidualCovariance("gaussian", 0.5, 2.0, 0.1)
        cells = np.sort(region.cell_grid[11:19, 11:19].ravel())
        tw = None
    else:
        region = grid(6, 7)
        cov = COV
        cells = np.arange(region.n_cells)
        tw = rng.uniform(0.5, 2.0, region.n_cells)
    Yk = rng.standard_normal((3, region.n_cells))
    terms = dict(region=region, spatial_cov=cov, prior_cov=np.eye(3) + 0.2,
                 target_weights=tw)
    return Yk, terms, cells


@pytest.mark.parametrize("kind", ["lag-table", "convolution"])
def test_structured_objective_equals_the_dense_one(kind):
    Yk, terms, cells = structured_case(kind)
    dense = variance_objective("gp-variance", Yk, cells, 0.0, terms, structured=False)
    fast = variance_objective("gp-variance", Yk, cells, 0.0, terms, structured=True)
    assert fast._oracle.uses_lag_table == (kind == "lag-table")
    assert fast.prior_total == pytest.approx(dense.prior_total, rel=1e-12)
    rng = np.random.default_rng(4)
    pos = np.arange(cells.size)
    for w in (np.where(rng.random(cells.size) < 0.3, rng.uniform(0.0, 2.0, cells.size), 0.0),
              np.where(rng.random(cells.size) < 0.2, 1.0, 1e-6 * rng.random(cells.size)),
              np.zeros(cells.size)):
        Fd, gd = dense.value_grad(pos, w, pos)
        Fs, gs = fast.value_grad(pos, w, pos)
        assert Fs == pytest.approx(Fd, rel=1e-9, abs=1e-12)
        assert fast.value(pos, w) == pytest.approx(Fd, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(gs, gd, rtol=1e-9, atol=1e-9 * np.max(np.abs(gd)))


def test_structured_bound_is_the_dense_bound_and_covers_every_route(monkeypatch):
    cells = np.arange(REGION.n_cells)
    terms = dict(GP_TERMS, region=REGION)
    dense = variance_objective("gp-variance", Y, cells, RIDGE, terms, structured=False)
    fast = variance_objective("gp-variance", Y, cells, RIDGE, terms, structured=True)
    poly = Polytope(3, cells.size)
    rng = np.random.default_rng(8)
    for _ in range(3):  # (FW) at the same weights: the same bound
        w = poly.project(np.where(rng.random(cells.size) < 0.4, rng.random(cells.size), 0.0))
        assert _fw_bound(fast, cells, poly, w)[0] == pytest.approx(
            _fw_bound(dense, cells, poly, w)[0], rel=1e-9)
    # the structured Frank-Wolfe (small supports) bounds the dense relaxation's optimum
    exact = variance_relaxation(dense, cells, poly, iters=60, tol=1e-9, polish=False,
                                rank_bound=False)
    b = variance_relaxation(fast, cells, poly, iters=5, tol=1e-9)
    assert b.solver == "Frank-Wolfe (structured)"
    assert b.value >= exact.primal - 1e-9 and b.primal <= exact.value + 1e-9
    fast.max_support = 4  # it stops before an iterate of more cells: still a bound
    small = variance_relaxation(fast, cells, poly, iters=10, tol=1e-9)
    assert small.iterations < b.iterations and len(small.weights) <= 4
    assert small.value >= exact.primal - 1e-9 and small.value >= b.value - 1e-9
    # the certificate through the structured objective is above every route of the 5x5 grid
    monkeypatch.setattr(varbound, "DENSE_MAX", 0)
    plan = plan_greedy(Y, REGION, START, 2.5, criterion="gp-variance", initial="start",
                       progress=False, **GP)
    cert = plan.certify(tighten=False)
    assert cert.relaxation.solver == "Frank-Wolfe (structured)"
    assert cert.bound >= best_route_value("gp-variance", START, 2.5, False) - 1e-9
    assert cert.information == pytest.approx(reduction("gp-variance", plan.cells), rel=1e-10)


# ------------------------------------------------------------------------- the rank bound
@settings(max_examples=6, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4))
def test_rank_bound_is_above_every_set_of_at_most_n_cells(seed, n):
    rng = np.random.default_rng(seed)
    cells = np.sort(rng.choice(REGION.n_cells, 9, replace=False))
    obj = variance_objective("gp-variance", Y, cells, RIDGE, dict(GP_TERMS, region=REGION))
    pos = np.arange(cells.size)
    rank = obj.rank_bound(pos, n)
    best = max(reduction("gp-variance", cells[list(S)])
               for m in range(1, n + 1) for S in itertools.combinations(range(cells.size), m))
    assert rank >= best * (1 - 1e-12)
    assert rank <= obj.value(pos, np.ones(cells.size)) * (1 + 1e-8)  # <= observing them all
    # the piece's bound is min(FW, rank): still above every set, and the rank bound when lower
    b = variance_relaxation(obj, pos, Polytope(n, cells.size), iters=3, polish=False)
    fw = variance_relaxation(obj, pos, Polytope(n, cells.size), iters=3, polish=False,
                             rank_bound=False)
    assert b.value >= best * (1 - 1e-12) and b.value <= fw.value * (1 + 1e-12)
    assert b.active == ("rank" if rank < fw.value else "relaxation")
    assert fw.active == "relaxation"


def test_rank_bound_is_the_top_eigenvalues_of_the_weighted_posterior_reduction():
    cells = np.arange(0, REGION.n_cells, 2)
    tw = np.random.default_rng(5).random(REGION.n_cells) + 0.5
    terms = dict(GP_TERMS, region=REGION, target_weights=tw)
    obj = variance_objective("gp-variance", Y, cells, RIDGE, terms)
    # naive reference over all targets: C^1/2 K_TC (K_CC + s^2 I)^-1 K_CT C^1/2
    T = np.arange(REGION.n_cells)
    K = gp_latent_cov(Y, np.eye(2), REGION, COV, cells, cells)
    KTc = gp_latent_cov(Y, np.eye(2), REGION, COV, T, cells)
    R = KTc @ np.linalg.solve(K + COV.nugget * np.eye(cells.size), KTc.T)
    lam = np.sort(np.linalg.eigvalsh(np.sqrt(tw)[:, None] * R * np.sqrt(tw)[None, :]))[::-1]
    for n in (1, 3, 7.5):
        ref = lam[:math.floor(n)].sum()
        assert obj.rank_bound(np.arange(cells.size), n) == pytest.approx(ref, rel=1e-9)
    assert obj.rank_bound(np.arange(cells.size), 0.5) == 0.0


@pytest.mark.parametrize("tight", [{"cover": 1, "max_pieces": 4}, False])
def test_certificate_with_the_rank_bound_is_above_every_route_and_says_which_bound(
        monkeypatch, tight):
    plan = plan_greedy(Y, REGION, START, 1.5, criterion="gp-variance", initial="start",
                       progress=False, **GP)
    cert = plan.certify(tighten=tight)
    assert cert.bound >= best_route_value("gp-variance", START, 1.5, False) - 1e-9
    # the count limit (2 of 9 cells) bites: the rank bound is the largest piece's and is said
    assert cert.relaxation.active == "rank" and "(rank bound;" in str(cert)
    # without it the same certificate is the Frank-Wolfe one, higher
    fw_only = functools.partial(variance_relaxation, rank_bound=False)
    monkeypatch.setattr(varbound, "variance_relaxation", fw_only)
    loose = plan.certify(tighten=tight)
    assert loose.relaxation.active == "relaxation" and "(relaxation bound;" in str(loose)
    assert cert.bound < loose.bound * (1 - 1e-3)
