"""``plan_greedy(refine="lines")``: the greedy's route against the four straight transects from
its start, decided by the plan's own criterion (planning/lines.py).

Every criterion value is recomputed from scratch by the registry's reference (``fisher``:
``log det``; ``gp-variance``: the dense posterior variance), so an oracle built wrongly for a
rival, a wrong sign (maximise / minimise) or a rival left out fails here.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx.cli_common import describe_plan
from lrm_cvx.errors import PlanningError
from lrm_cvx.information import CRITERION_REGISTRY, gp_variance_value
from lrm_cvx.planning import PathOptions, PriorTerms, plan_greedy, transect
from lrm_cvx.planning.baselines import CYCLE_AFTER, DIRECTIONS
from lrm_cvx.planning.lines import lines_where_possible, route_values
from lrm_cvx.region import Region
from lrm_cvx.spatial import ResidualCovariance


def grid_region(ny: int, nx: int, holes: tuple = ()) -> Region:
    mask = np.ones((ny, nx), bool)
    for r, c in holes:
        mask[r, c] = False
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords={"lat": np.arange(ny, dtype=float),
                              "lon": np.arange(nx, dtype=float)})
    return Region.from_dataarray(da, mask=mask)


def gp_terms(k: int, seed: int, anisotropy: float = 1.0) -> dict:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(k, k))
    cov = ResidualCovariance("exponential", sill=1.0, range=2.0, nugget=0.1,
                            anisotropy=anisotropy)
    return dict(prior_cov=A @ A.T / k + 0.1 * np.eye(k), spatial_cov=cov)


def reference(criterion: str, Y, region, cells, ridge=0.0, **terms) -> float:
    """The criterion's value of ``cells`` from scratch (the registry's reference)."""
    if criterion == "gp-variance":
        return gp_variance_value(Y, region, terms["spatial_cov"], terms["prior_cov"], cells)
    return CRITERION_REGISTRY.get(criterion).value(Y, cells, ridge, **terms)


def check_best_of_lines(plan, greedy, criterion, Y, region, start, budget, ridge=0.0,
                        others=None, **terms):
    """``plan`` is the best of the greedy's route, the ``others`` (name -> plan) and the four
    transects by the reference."""
    maximize = CRITERION_REGISTRY.get(criterion).maximize
    routes = {"greedy": greedy, **(others or {})}
    routes.update({f"transect-{d}": transect(region, start, budget, d) for d in DIRECTIONS})
    ref = {name: reference(criterion, Y, region, p.cells, ridge, **terms)
           for name, p in routes.items()}
    for name, v in ref.items():  # the recorded values are the criterion's
        assert plan.rivals["values"][name] == pytest.approx(v, rel=1e-8, abs=1e-9)
    best = max(ref.values()) if maximize else min(ref.values())
    got = ref[plan.rivals["chosen"]]
    assert got == pytest.approx(best, rel=1e-8, abs=1e-9)
    assert plan.rivals["cost_function"] == greedy.cost_function  # what a replan plans with
    said = describe_plan(plan)  # the CLI's line names a kept transect
    if plan.rivals["chosen"] == "greedy":  # ties keep the greedy, bit for bit
        np.testing.assert_array_equal(plan.route, greedy.route)
        assert "beat the greedy" not in said
    else:
        assert f"{plan.rivals['chosen']}: its {criterion} value beat the greedy route's" in said
        chosen = routes[plan.rivals["chosen"]]
        np.testing.assert_array_equal(plan.route, chosen.route)
        assert plan.method == chosen.method and plan.criterion == criterion
        assert plan.posterior == greedy.posterior
        worse = ref["greedy"] < got if maximize else ref["greedy"] > got
        assert worse  # a transect is taken only when strictly better
    return plan.rivals["chosen"]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), budget=st.sampled_from([3.0, 5.0, 8.0]),
       start=st.integers(0, 41))
def test_fisher_lines_keep_the_best_route_by_its_own_value(seed, budget, start):
    region = grid_region(6, 7)
    Y = np.random.default_rng(seed).normal(size=(3, region.n_cells))
    kw = dict(criterion="fisher", ridge=1e-2, initial="start", progress=False)
    plan = plan_greedy(Y, region, start, budget, refine="lines", **kw)
    greedy = plan_greedy(Y, region, start, budget, **kw)
    check_best_of_lines(plan, greedy, "fisher", Y, region, start, budget, ridge=1e-2)
    assert plan.cost <= budget + 1e-9
    cert = plan.certify(tighten=False)  # a kept transect is certified like any plan
    assert cert.bound >= plan.information - 1e-9


@pytest.mark.parametrize("anisotropy", [1.0, 5.0])
def test_gp_variance_lines_keep_the_best_route_and_can_change_it(anisotropy):
    """Over several fields and starts the check is right every time, and at least once a
    transect beats the greedy (so the check is not a no-op on this criterion)."""
    region = grid_region(9, 10, holes=((0, 0), (4, 5)))
    chosen = []
    for seed in range(6):
        Y = np.random.default_rng(seed).normal(size=(3, region.n_cells)) * 0.5
        terms = gp_terms(3, seed, anisotropy)
        for start in (3, 40, 77):
            kw = dict(criterion="gp-variance", initial="start", progress=False,
                      prior=PriorTerms(**terms))
            plan = plan_greedy(Y, region, start, 8.0, refine="lines", **kw)
            greedy = plan_greedy(Y, region, start, 8.0, **kw)
            chosen.append(check_best_of_lines(plan, greedy, "gp-variance", Y, region, start,
                                              8.0, **terms))
    assert "greedy" in chosen
    assert any(c != "greedy" for c in chosen), chosen


@pytest.mark.parametrize("criterion", ["gp-variance", "fisher"])
def test_rivals_add_the_gentler_greedy_and_keep_the_best(criterion):
    """``refine="rivals"``: the best of the greedy, the greedy with ``cost_exponent=0.5`` and the
    four transects by the reference values; the gentler greedy's route is taken as it is (a
    greedy plan) and is chosen at least once, so the rival is not a no-op."""
    region = grid_region(9, 10, holes=((0, 0), (4, 5)))
    chosen = []
    for seed in range(5):
        Y = np.random.default_rng(seed).normal(size=(3, region.n_cells)) * 0.5
        terms = gp_terms(3, seed) if criterion == "gp-variance" else {}
        ridge = 0.0 if terms else 1e-2
        for start in (3, 40, 77):
            kw = dict(criterion=criterion, initial="start", progress=False, ridge=ridge,
                      prior=PriorTerms(**terms) if terms else None)
            plan = plan_greedy(Y, region, start, 8.0, refine="rivals", **kw)
            greedy = plan_greedy(Y, region, start, 8.0, **kw)
            gentle = plan_greedy(Y, region, start, 8.0, cost_exponent=0.5, **kw)
            assert plan.rivals["refine"] == "rivals"
            chosen.append(check_best_of_lines(plan, greedy, criterion, Y, region, start, 8.0,
                                              ridge, others={"greedy-cost^0.5": gentle},
                                              **terms))
            if plan.rivals["chosen"] == "greedy-cost^0.5":
                assert plan.method == "greedy"
                np.testing.assert_array_equal(plan.cells, gentle.cells)
    assert "greedy-cost^0.5" in chosen, chosen


@pytest.mark.parametrize("metric,small", [("grid", False), ("grid", True), ("km", False)])
def test_route_values_of_gp_variance_are_the_dense_oracles(metric, small, monkeypatch):
    """Grid: structured oracles on the routes' cells, or the dense reference where its
    covariances are small; km: the dense reference. Each value is a fresh dense oracle's,
    whatever the order of the routes."""
    import lrm_cvx.planning.lines as lines
    from lrm_cvx.information import StructuredGPVarianceOracle, make_oracle

    built = []
    init = StructuredGPVarianceOracle.__init__
    monkeypatch.setattr(StructuredGPVarianceOracle, "__init__",
                        lambda self, *a, **k: built.append(1) or init(self, *a, **k))
    if not small:
        monkeypatch.setattr(lines, "GP_STRUCTURED_MIN_ENTRIES", 0.0)
    region = grid_region(12, 13)
    Y = np.random.default_rng(3).normal(size=(2, region.n_cells))
    terms = gp_terms(2, 3)
    if metric == "km":
        terms["spatial_cov"] = ResidualCovariance("exponential", sill=1.0, range=250.0,
                                                  nugget=0.1, metric="km")
    routes = {"a": np.array([4, 7, 7, 20, 29]), "b": np.array([29, 30, 31]),  # a repeat once
              "c": np.array([100, 4]), "d": np.array([150])}
    got = route_values("gp-variance", Y, 0.0, routes, dict(region=region, **terms))
    assert bool(built) == (metric == "grid" and not small)
    for name, cells in routes.items():
        want = make_oracle("gp-variance", Y, 0.0, np.unique(cells), region=region,
                           gp_method="dense", **terms).value
        assert got[name] == pytest.approx(want, rel=1e-10), name


@pytest.mark.parametrize("far_from_edge", [False, True])
def test_route_values_fork_one_oracle_only_when_its_picks_are_table_gathers(monkeypatch,
                                                                            far_from_edge):
    """Routes far from the region's edge share one set-up (forked: the lag table's gathers);
    near it each route gets its own exact oracle. Either way each value is the dense
    oracle's."""
    import lrm_cvx.planning.lines as lines
    from lrm_cvx.information import StructuredGPVarianceOracle, make_oracle

    monkeypatch.setattr(lines, "GP_STRUCTURED_MIN_ENTRIES", 0.0)  # not the small-region path
    forks = []
    fork = StructuredGPVarianceOracle.fork
    monkeypatch.setattr(StructuredGPVarianceOracle, "fork",
                        lambda self: forks.append(1) or fork(self))
    n = 50 if far_from_edge else 12
    region = grid_region(n, n)
    Y = np.random.default_rng(7).normal(size=(3, region.n_cells))
    terms = gp_terms(3, 4)
    terms["spatial_cov"] = ResidualCovariance("exponential", sill=1.0, range=1.0, nugget=0.1)
    c0 = region.n_cells // 2 + n // 2 if far_from_edge else 0  # the centre, or a corner
    routes = {"line": c0 + np.arange(6), "column": c0 + n * np.arange(6),
              "patch": c0 + np.array([0, 1, n, n + 1, 2 * n + 2])}
    got = route_values("gp-variance", Y, 0.0, routes, dict(region=region, **terms))
    assert bool(forks) == far_from_edge
    for name, cells in routes.items():
        want = make_oracle("gp-variance", Y, 0.0, np.unique(cells), region=region,
                           gp_method="dense", **terms).value
        assert got[name] == pytest.approx(want, rel=1e-10), name


def test_a_forked_oracle_conditions_on_its_own():
    from lrm_cvx.information import make_oracle

    region = grid_region(10, 11)
    Y = np.random.default_rng(5).normal(size=(3, region.n_cells))
    terms = gp_terms(3, 5)
    kw = dict(region=region, pool=np.arange(0, region.n_cells, 3), gp_method="structured",
              **terms)
    base = make_oracle("gp-variance", Y, 0.0, [0, 3], **kw)
    before, gains = base.value, base.gains().copy()
    fork = base.fork()
    for c in (30, 60, 93):
        fork.add(c)
    fresh = make_oracle("gp-variance", Y, 0.0, [0, 3, 30, 60, 93], **kw)
    assert fork.value == pytest.approx(fresh.value, rel=1e-10)
    np.testing.assert_allclose(fork.gains(), fresh.gains(), rtol=1e-8, atol=1e-12)
    assert base.value == before and base.cells == [0, 3]  # the original is untouched
    np.testing.assert_array_equal(base.gains(), gains)


def test_lines_under_path_options_are_feasible_transects_of_that_model():
    region = grid_region(8, 8)
    Y = np.random.default_rng(1).normal(size=(3, region.n_cells))
    for opts in (dict(closed=True), dict(stop_cost=0.5), dict(traversable="valid")):
        plan = plan_greedy(Y, region, 27, 7.0, criterion="fisher", ridge=1e-2, initial="start",
                           refine="lines", progress=False, path=PathOptions(**opts))
        assert plan.cost <= 7.0 + 1e-9 and set(plan.rivals["values"]) == {
            "greedy", *(f"transect-{d}" for d in DIRECTIONS)}


def test_lines_refuse_what_a_transect_cannot_fly():
    region = grid_region(6, 6)
    Y = np.random.default_rng(0).normal(size=(3, region.n_cells))
    kw = dict(criterion="fisher", ridge=1e-2, initial="start", progress=False, refine="lines")
    with pytest.raises(PlanningError, match="refine='lines' cannot run: the routes must end"):
        plan_greedy(Y, region, 7, 6.0, path=PathOptions(end=30), **kw)
    with pytest.raises(PlanningError, match="refine='lines' cannot run: sense_along"):
        plan_greedy(Y, region, 7, 6.0, path=PathOptions(sense_along=True), **kw)
    with pytest.raises(PlanningError, match="refine='rivals' cannot run: sense_along"):
        plan_greedy(Y, region, 7, 6.0, path=PathOptions(sense_along=True),
                    **{**kw, "refine": "rivals"})
    with pytest.raises(PlanningError, match="not a point"):
        plan_greedy(Y, region, 7, 6.0, path=PathOptions(sensor="leg-average"), **kw)
    with pytest.raises(PlanningError, match=r"refine must be True, False, one of \['"):
        plan_greedy(Y, region, 7, 6.0, criterion="fisher", refine="straight")
    assert lines_where_possible(PathOptions(end=3)) is None
    assert lines_where_possible(None) == "rivals"


def test_the_cli_and_the_methods_follow_the_recommended_refine(monkeypatch):
    """``lines_where_possible`` (the CLI's and the greedy methods' refine) reads
    ``RECOMMENDED["refine"]``: without the check there, no check anywhere."""
    from lrm_cvx.recommended import RECOMMENDED

    monkeypatch.setitem(RECOMMENDED, "refine", None)
    assert lines_where_possible(None) is None


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_a_transect_on_a_huge_budget_stops_when_it_would_only_repeat(direction):
    """The lawnmower covers a full grid and stops in its cycle (budget 1e9 would otherwise walk
    1e9 steps: the hang refine="lines" met under `lrm-cvx plan --budget 1e9`)."""
    region = grid_region(5, 7)
    plan = transect(region, 8, 1e9, direction)
    assert set(plan.cells.tolist()) == set(range(region.n_cells))
    # past CYCLE_AFTER steps at most one more pass of the 4 x 35 states
    assert CYCLE_AFTER <= plan.cost <= CYCLE_AFTER + 4 * region.n_cells
    longer = transect(region, 8, float(CYCLE_AFTER - 3), direction)  # the paper's walk
    assert longer.cost == CYCLE_AFTER - 3
    small = transect(region, 8, 6.0, direction)  # a short walk is unchanged: 6 steps
    assert small.cost == 6.0 and len(small.route) == 7
