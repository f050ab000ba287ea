"""Plan refinement: never lowers information, never breaks the budget, and finds more optima
than the greedy alone on tiny instances (brute force over every feasible set)."""

import itertools
import math
import warnings
from itertools import pairwise

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from references import naive_tour

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError
from lrm_cvx.information import fisher_information
from lrm_cvx.planning import PriorTerms, plan_greedy, refine
from lrm_cvx.planning.routecost import or_opt, repair_route, two_opt


def make_region(mask):
    ny, nx = mask.shape
    lat = np.arange(ny, dtype=float)
    lon = np.arange(nx, dtype=float) + 10
    return Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                  lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)


def path_length(g, route):
    return math.fsum(math.dist(g[a], g[b]) for a, b in pairwise(route))


def instance(seed, ny, nx, k, smooth=True):
    rng = np.random.default_rng(seed)
    mask = rng.random((ny, nx)) < rng.uniform(0.6, 1.0)
    mask[ny // 2, nx // 2] = True
    if mask.sum() < k + 2:
        mask[:] = True
    region = make_region(mask)
    L = region.n_cells
    if smooth:  # smooth factors, as fitted fields are: nearby cells are alike
        gi = region.grid_index.astype(float)
        f = rng.normal(size=(k, 3))
        Y = np.stack([np.cos(gi @ rng.normal(size=2) * 0.7 + f[i, 0]) + 0.3 * f[i, 1]
                      for i in range(k)]) + 0.2 * rng.normal(size=(k, L))
    else:
        Y = rng.normal(size=(k, L))
    start = int(np.flatnonzero((region.grid_index == [ny // 2, nx // 2]).all(1))[0])
    return region, Y, start


def check_plan(plan, before, region, Y):
    g = region.grid_index
    assert plan.cells[0] == plan.start == before.start
    assert np.unique(plan.cells).size == plan.cells.size
    assert np.array_equal(np.sort(plan.route), np.sort(plan.cells))
    # the exact cost of the refined plan, from scratch
    if plan.cost_function == "nearest-neighbor":
        cost, order = naive_tour(g, [int(c) for c in plan.cells])
        assert order == plan.route.tolist()
    else:
        cost = path_length(g, plan.route.tolist())
    assert plan.cost == pytest.approx(cost, abs=1e-9)
    info = fisher_information(Y, plan.cells, plan.ridge)
    assert plan.information == pytest.approx(info, abs=1e-9)
    assert plan.information >= before.information - 1e-12
    if plan is not before:
        r = plan.refinement
        assert r["information_before"] == before.information
        assert r["information_after"] == plan.information
        assert r["moves"] == plan.history["refine_move"].size
        if r["moves"]:
            assert cost <= plan.budget + 1e-9
            assert plan.information > before.information
        else:  # only the route was repaired (a route cost): same cells, shorter
            assert plan.cost_function == "insertion"
            assert set(plan.cells.tolist()) == set(before.cells.tolist())
            assert plan.cost < before.cost


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), ny=st.integers(3, 8), nx=st.integers(3, 8),
       k=st.integers(1, 3), budget=st.floats(0.0, 12.0), ridge=st.sampled_from([0.0, 1e-3]),
       cost=st.sampled_from(["nearest-neighbor", "insertion"]), smooth=st.booleans())
def test_refine_never_lowers_information_nor_breaks_budget(seed, ny, nx, k, budget, ridge,
                                                           cost, smooth):
    region, Y, start = instance(seed, ny, nx, k, smooth)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            plan = plan_greedy(Y, region, start, budget, ridge=max(ridge, 1e-9) if k > 1
                               else ridge, cost=cost, progress=False)
        except PlanningError:
            return  # singular initial set
    out = refine(plan, shortlist=8, radius=1.5)
    check_plan(out, plan, region, Y)
    again = plan_greedy(Y, region, start, budget, ridge=plan.ridge, cost=cost, progress=False,
                        refine=dict(shortlist=8, radius=1.5)) if plan.cost <= budget + 1e-9 \
        else None
    if again is not None:
        assert again == out  # plan_greedy(refine=...) is refine(plan_greedy(...)), deterministic


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), ny=st.integers(4, 8), nx=st.integers(4, 8),
       k=st.integers(2, 3), budget=st.floats(2.0, 14.0),
       cost=st.sampled_from(["nearest-neighbor", "insertion"]))
def test_refine_restarts_never_lower_information_nor_break_budget(seed, ny, nx, k, budget,
                                                                  cost):
    """Several iterated-local-search chains: still feasible and never below the input; chain 0
    is the single chain of ``restarts=1`` (same seed), so with no time limit binding the best
    over the chains is at least the single chain's."""
    region, Y, start = instance(seed, ny, nx, k, True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = plan_greedy(Y, region, start, budget, ridge=1e-6, cost=cost, progress=False)
    one = refine(plan, shortlist=8, radius=1.5, kicks=3, time_limit=1e6)
    many = refine(plan, shortlist=8, radius=1.5, kicks=3, restarts=3, time_limit=1e6)
    check_plan(many, plan, region, Y)
    assert many.information >= one.information - 1e-12
    assert many == refine(plan, shortlist=8, radius=1.5, kicks=3, restarts=3, time_limit=1e6)


def brute_force(region, Y, start, budget, ridge):
    """Largest Fisher information over every set holding the start whose nearest-neighbour
    tour costs <= budget (+1e-9)."""
    g = region.grid_index
    d = np.hypot(*(g - g[start]).T)
    pool = [int(c) for c in np.flatnonzero(d <= budget + 1e-9) if c != start]
    n_max = math.floor(budget + 1e-9)  # at most floor(budget) legs of length >= 1
    best = -np.inf
    for r in range(0, min(n_max, len(pool)) + 1):
        for sub in itertools.combinations(pool, r):
            cells = [start, *sub]
            v = fisher_information(Y, cells, ridge)
            if v > best and naive_tour(g, cells)[0] <= budget + 1e-9:
                best = v
    return best


def test_refine_reaches_brute_force_optimum_more_often_than_greedy():
    """Tiny instances: the refined plan equals the brute-force optimum at least as often as
    the greedy plan (and is never worse); the counts are printed (-s)."""
    n_greedy = n_refined = n = 0
    for seed in range(30):
        region, Y, start = instance(seed, 5, 5, 2)
        budget = float(3 + seed % 3)
        ridge = 1e-3
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plan = plan_greedy(Y, region, start, budget, ridge=ridge, progress=False)
        if plan.cost > budget + 1e-9:
            continue
        out = refine(plan)
        check_plan(out, plan, region, Y)
        opt = brute_force(region, Y, start, budget, ridge)
        assert out.information <= opt + 1e-9  # the refined plan is feasible
        n += 1
        n_greedy += plan.information >= opt - 1e-9
        n_refined += out.information >= opt - 1e-9
    print(f"\nbrute-force optimum reached on {n} tiny instances: greedy {n_greedy}, "
          f"refined {n_refined}")
    assert n >= 20
    assert n_refined >= n_greedy
    assert n_refined > n_greedy  # refinement does find optima the greedy misses


def test_route_repair_only_shortens_and_keeps_the_stops():
    rng = np.random.default_rng(3)
    g = rng.integers(0, 30, size=(40, 2))
    g = np.unique(g, axis=0)
    for _ in range(20):
        route = rng.permutation(g.shape[0])[:12]
        for fix in (two_opt, or_opt, repair_route):
            r = fix(g, route)
            assert r[0] == route[0]
            assert sorted(r.tolist()) == sorted(route.tolist())
            assert path_length(g, r.tolist()) <= path_length(g, route.tolist()) + 1e-9
        # on 6 stops the repaired path is no longer than the best of a few random orders
        small = route[:6]
        best = min(path_length(g, [small[0], *p]) for p in itertools.permutations(small[1:]))
        assert path_length(g, repair_route(g, small).tolist()) <= 1.3 * best + 1e-9


def test_refine_bad_input():
    region, Y, start = instance(0, 5, 5, 2)
    plan = plan_greedy(Y, region, start, 4.0, ridge=1e-3, progress=False)
    with pytest.raises(PlanningError, match="plan must be a Plan"):
        refine("plan")
    with pytest.raises(PlanningError, match="max_rounds"):
        refine(plan, max_rounds=-1)
    for name in ("shapes", "climbs"):
        for bad in (-1, 1.5, "2"):
            with pytest.raises(PlanningError, match=name):
                refine(plan, **{name: bad})
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(PlanningError, match="restarts"):
            refine(plan, restarts=bad)
    aopt = plan_greedy(Y, region, start, 4.0, ridge=1e-3, criterion="aopt", progress=False)
    with pytest.raises(PlanningError, match="Fisher"):
        refine(aopt)
    assert refine(plan, max_rounds=0, restart=False) is plan


@pytest.mark.parametrize("seed", range(3))
def test_certificate_splits_the_gap_and_bounds_the_refined_plan(seed):
    """``gap = plan_slack + bound_slack``, both >= 0; the bound covers the refined plan."""
    region, Y, start = instance(seed, 9, 9, 3)
    budget = float(4 + 2 * seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = plan_greedy(Y, region, start, budget, ridge=1e-6, progress=False)
        cert = plan.certify(tighten={"max_pieces": 2})
        done = plan_greedy(Y, region, start, budget, ridge=1e-6, progress=False, refine=True)
        cert2 = done.certify(tighten={"max_pieces": 2})
    assert cert.greedy_information == pytest.approx(plan.information)
    assert cert.refined_information >= cert.greedy_information
    assert cert.plan_slack >= 0 and cert.bound_slack >= -1e-9
    assert cert.gap == pytest.approx(cert.plan_slack + cert.bound_slack, abs=1e-9)
    assert cert.bound >= cert.refined_information - 1e-9
    # an already refined plan: its own refinement is reported, the gap is its own
    assert cert2.greedy_information == pytest.approx(plan.information)
    assert cert2.refined_information == pytest.approx(done.information)
    assert cert2.gap == pytest.approx(cert2.bound_slack, abs=1e-9)
    assert cert2.refined_information == pytest.approx(cert.refined_information)
    assert "gap split" in repr(cert) and "plan slack" in cert._repr_html_()
    # no split without refinement, nor for another criterion
    assert plan.certify(refine=False, tighten=False).refined_information is None
    aopt = plan_greedy(Y, region, start, budget, ridge=1e-6, criterion="aopt", progress=False)
    c3 = aopt.certify(tighten=False)
    assert c3.plan_slack is None and c3.bound_slack is None


def test_refine_posterior_fisher_plan_raises_its_own_criterion():
    """A Fisher plan on the fold-in's posterior is refined on that posterior (the criterion it
    was chosen for), never lowering it; without the posterior terms refine refuses."""
    from lrm_cvx.information import fisher_set_value

    region, Y, start = instance(3, 9, 9, 3)
    P0, nv = 0.5 * np.eye(3), np.linspace(0.5, 2.0, Y.shape[1])
    kw = dict(prior=PriorTerms(prior_precision=P0, noise_var=nv), progress=False,
              initial="start")
    plan = plan_greedy(Y, region, start, 8.0, **kw)
    out = plan_greedy(Y, region, start, 8.0, refine=True, **kw)
    value = lambda c: fisher_set_value(Y, c, 0.0, prior_precision=P0, noise_var=nv)  # noqa: E731
    assert value(out.cells) >= value(plan.cells) - 1e-12
    assert out.refinement["criterion_after"] == pytest.approx(value(out.cells))
    assert out.cost <= 8.0 + 1e-9 and out.posterior
    with pytest.raises(PlanningError, match="posterior"):
        refine(plan)
    again = refine(plan, prior=kw["prior"])  # the prior given: the same search as refine=True
    assert again.cells.tolist() == out.cells.tolist()
