"""The variance certificate on every plan the product makes: replanned plans, plans read back
from a monitor state file, every path model the planner supports, and ``lrm-cvx bound --state``.

The certificate's inputs (the criterion's terms) travel with the plan: a replan carries the
day's prior before its observations, a state file stores and reads them back, and a plan
without them is refused in one line naming what is missing.
"""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import GLRM, plan_greedy
from lrm_cvx.errors import PlanningError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions
from lrm_cvx.information import CRITERION_REGISTRY, gp_variance_value
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import PathOptions, place_sensors
from lrm_cvx.planning.terms import PriorTerms, prior_terms
from lrm_cvx.replanning import plan_from_variables, plan_variables

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_certificate_variance import GP, GP_TERMS, REGION, RIDGE, START, Y, reduction  # noqa: E402,E501

FAST = dict(tighten=False)  # the budget-disk relaxation: valid, and quick


@pytest.fixture(scope="module")
def spatial(tmp_path_factory):
    """A spatial (gp-variance) model of a small synthetic field, saved: ``(model, path, da)``."""
    folder = tmp_path_factory.mktemp("certificate")
    da = synthetic_dynamic_field(34, (6, 7), 3, seed=4, noise=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, progress=False, max_iter=20, temporal="ar1", offset=True,
                     spatial="exponential").fit(da.isel(time=slice(0, 30)))
    model.save(folder / "model.nc")
    return model, folder / "model.nc", da


def _day_plan(model, criterion="gp-variance", budget=4.0, **path):
    state = MonitorState.from_model(model)
    t = state.plan_time(None)
    kw = state.planner_kwargs(criterion, t)
    plan = plan_greedy(model.Y_, model.region_, 14, budget, criterion=criterion,
                       initial="start", progress=False, **kw, **path)
    return state, t, plan


def _gp_removed(model, kw, cells):
    kw = prior_terms(kw["prior"])
    args = (model.Y, model.region_, kw["spatial_cov"], kw["prior_cov"])
    return (gp_variance_value(*args, [], None, kw["target_weights"])
            - gp_variance_value(*args, cells, None, kw["target_weights"]))


# ------------------------------------------------------------------------- replanned plans
def test_a_replanned_plan_is_certified_under_the_days_prior(spatial):
    model, _, _ = spatial
    state, t, plan = _day_plan(model)
    new = state.replan(plan, 2, time=t)
    assert new.method == "greedy+replan"
    cert = new.certify(**FAST)
    assert cert.criterion == "gp-variance" and cert.comparable
    assert math.isfinite(cert.gap) and 0 <= cert.gap <= cert.bound
    # the value is the whole route's under the day's prior before the replan
    kw = state.planner_kwargs("gp-variance", t)
    assert cert.information == pytest.approx(_gp_removed(model, kw, new.cells), rel=1e-9)
    # the same relaxation as the original plan's (same start, budget, path model and terms)
    assert cert.bound == pytest.approx(plan.certify(**FAST).bound, rel=1e-12)
    assert set(new.criterion_terms) == {"spatial_cov", "prior_cov"}


def test_a_replan_under_another_criterion_carries_that_criterions_terms(spatial):
    model, _, _ = spatial
    state, t, plan = _day_plan(model)
    new = state.replan(plan, 2, time=t, criterion="a-optimal")
    cert = new.certify(**FAST)
    assert cert.criterion == "a-optimal" and math.isfinite(cert.gap) and cert.gap >= 0
    terms = prior_terms(state.planner_kwargs("a-optimal", t)["prior"])
    kw = {k: terms[k] for k in ("prior_precision", "noise_var", "target_weights")}
    crit = CRITERION_REGISTRY.get("a-optimal")
    removed = (crit.value(model.Y, [], 0.0, **kw) - crit.value(model.Y, new.cells, 0.0, **kw))
    assert cert.information == pytest.approx(removed, rel=1e-9)


# ------------------------------------------------------------------------- stored plans
@pytest.mark.parametrize("criterion", ["gp-variance", "a-optimal"])
def test_a_plan_read_back_from_a_state_file_carries_its_terms(spatial, tmp_path, criterion):
    model, _, _ = spatial
    state, t, plan = _day_plan(model, criterion)
    state.current_plan, state.current_plan_time = plan, t
    state.save(tmp_path / "state.nc")
    back = MonitorState.load(tmp_path / "state.nc", model=model).current_plan
    assert back == plan
    want, got = plan.criterion_terms, back.criterion_terms
    assert set(got) == set(want)
    for key, v in want.items():
        if key == "spatial_cov":
            assert got[key] == v
        else:
            np.testing.assert_array_equal(got[key], v)
    assert back.certify(**FAST).bound == plan.certify(**FAST).bound
    assert back.certify(**FAST).gap == plan.certify(**FAST).gap


def test_a_plan_saved_without_terms_is_refused_in_one_line(spatial):
    model, _, _ = spatial
    for criterion, needle in (("gp-variance", "the plan carries none"),
                              ("a-optimal", "planned on a posterior whose terms")):
        _, _, plan = _day_plan(model, criterion)
        variables, attrs = plan_variables(plan)
        ds = xr.Dataset({k: v for k, v in variables.items() if not k.startswith("plan_term_")},
                        attrs={k: v for k, v in attrs.items() if not k.startswith("plan_term")})
        old = plan_from_variables(ds, model.region_, model.Y)
        assert old.criterion_terms is None
        with pytest.raises(PlanningError, match=needle) as err:
            old.certify(**FAST)
        assert "\n" not in str(err.value)
        # its own terms, given, certify it as the saved plan would be
        terms = plan.criterion_terms
        assert old.certify(prior=PriorTerms(**terms), **FAST).bound == plan.certify(**FAST).bound


# ------------------------------------------------------------------------- path models
MASK = np.ones((5, 5), bool)
MASK[1, 1:4] = False
NO_GO = xr.DataArray(MASK, dims=("lat", "lon"),
                     coords={"lat": REGION.lat.values, "lon": REGION.lon.values})
PATHS = {
    "closed tour": dict(path=PathOptions(closed=True)),
    "fleet": dict(start=[0, 24], budget=[2.0, 2.0]),
    "no-go cells": dict(path=PathOptions(traversable=NO_GO)),
    "km": dict(path=PathOptions(metric="km"), budget=300.0),
    "hours": dict(path=PathOptions(metric="km", speed=100.0), budget=3.0),
    "stop cost": dict(path=PathOptions(stop_cost=0.5)),
    "fixed end": dict(path=PathOptions(end=0)),
    "sense along": dict(path=PathOptions(sense_along=True)),
    "static": dict(static=True),
}


@pytest.mark.parametrize("name", list(PATHS))
@pytest.mark.parametrize("criterion", ["gp-variance", "a-optimal"])
def test_every_path_model_gets_a_finite_valid_gap(name, criterion):
    kw = dict(PATHS[name])
    start, budget = kw.pop("start", START), kw.pop("budget", 3.0)
    terms = GP if criterion == "gp-variance" else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kw.pop("static", False):  # fixed sensors: the placement of as many as the budget
            plan = place_sensors(Y, REGION, 4, criterion=criterion, ridge=RIDGE, **terms)
        else:
            plan = plan_greedy(Y, REGION, start, budget, criterion=criterion, ridge=RIDGE,
                               initial="start", progress=False, **terms, **kw)
    cert = plan.certify(tighten={"cover": 1, "max_pieces": 1}, tol=0.1)  # looser, as valid
    assert cert.criterion == criterion and cert.comparable
    assert cert.information == pytest.approx(reduction(criterion, plan.cells), rel=1e-9)
    assert math.isfinite(cert.gap) and 0 <= cert.gap <= cert.bound
    for robot in plan.robots:  # each robot's route under the fleet's terms
        assert robot.criterion_terms is not None


@pytest.mark.parametrize("sensor", ["disc:100km", "leg-average"])
def test_a_sensor_without_a_variance_bound_is_refused_in_one_line(sensor):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = plan_greedy(Y, REGION, START, 3, criterion="gp-variance", initial="start",
                           progress=False, path=PathOptions(sensor=sensor), **GP)
    with pytest.raises(PlanningError, match="point sensors only") as err:
        plan.certify()
    assert "\n" not in str(err.value) and "criterion='fisher'" in str(err.value)
    assert math.isfinite(plan.certify(criterion="fisher", tighten=False).bound)


def test_many_cells_take_the_structured_gp_bound_and_km_is_refused_in_one_line(monkeypatch):
    from lrm_cvx.planning import varbound
    from lrm_cvx.spatial import ResidualCovariance

    plan = plan_greedy(Y, REGION, START, 3, criterion="gp-variance", initial="start",
                       progress=False, **GP)
    dense = plan.certify(tighten=False)
    monkeypatch.setattr(varbound, "DENSE_MAX", 10)
    cert = plan.certify(tighten=False)  # a grid-metric residual: the structured objective
    assert cert.relaxation.solver == "Frank-Wolfe (structured)"
    assert cert.information == pytest.approx(dense.information, rel=1e-10)
    assert cert.bound >= dense.relaxation.primal - 1e-9
    km = ResidualCovariance("exponential", 0.5, 300.0, 0.1, metric="km")
    plan = plan_greedy(Y, REGION, START, 3, criterion="gp-variance", initial="start",
                       progress=False, prior=PriorTerms(spatial_cov=km, prior_cov=np.eye(2)))
    with pytest.raises(PlanningError, match="covers at most 10") as err:
        plan.certify(tighten=False)
    assert "\n" not in str(err.value) and "criterion='fisher'" in str(err.value)
    assert "'km'" in str(err.value)
    assert math.isfinite(plan.certify(criterion="fisher", tighten=False).bound)


def test_the_gp_objective_sums_its_targets_in_blocks(monkeypatch):
    from lrm_cvx.planning import varbound

    cells = np.arange(10)
    whole = varbound.variance_objective("gp-variance", Y, cells, RIDGE,
                                        dict(GP_TERMS, region=REGION))
    monkeypatch.setattr(varbound, "_BLOCK", 30)  # three targets a block: nine blocks
    blocks = varbound.variance_objective("gp-variance", Y, cells, RIDGE,
                                         dict(GP_TERMS, region=REGION))
    np.testing.assert_allclose(blocks.G, whole.G, rtol=1e-12, atol=1e-12 * np.abs(whole.G).max())
    w = np.linspace(0.2, 1.0, cells.size)
    assert blocks.value(cells, w) == pytest.approx(whole.value(cells, w), rel=1e-12)


# ------------------------------------------------------------------------- CLI
def _run(*argv):
    from lrm_cvx.cli import main

    return main(["-q", *map(str, argv)])


def test_cli_bound_certifies_the_stored_and_the_replanned_plan(spatial, tmp_path, capsys):
    _, model_path, da = spatial
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", model_path, "--state", state) == 0
    start = ["--start", f"{da.lat.values[2]},{da.lon.values[3]}", "--budget", 4]
    assert _run("monitor", "plan", state, *start, "-o", tmp_path / "p.csv") == 0
    for step in ("planned", "replanned"):
        if step == "replanned":
            assert _run("monitor", "replan", state, "--done", 2, "-o", tmp_path / "r.csv") == 0
        capsys.readouterr()
        assert _run("bound", model_path, "--state", state, "--certify", "fast") == 0
        out = capsys.readouterr().out
        assert out.startswith("stored plan: ")
        gap = next(x for x in out.splitlines() if x.startswith("optimality gap"))
        assert "unit^2" in gap and "% of the bound" in gap, step
        # the stored plan's own certificate, computed in Python
        s = MonitorState.load(state)
        cert = s.current_plan.certify(tighten=False)
        assert f"{cert.gap:.4f} unit^2" in gap


def test_cli_bound_state_bad_input_is_one_line(spatial, tmp_path, capsys, inputs_unchanged):
    _, model_path, da = spatial
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", model_path, "--state", state) == 0
    inputs_unchanged.watch(model_path, state)
    capsys.readouterr()
    cases = [
        (["--state", state], "holds no plan"),
        (["--state", state, "--start", "1,1", "--budget", 2], "--start and --budget do not"),
        ([], "bound needs --start and --budget"),
    ]
    for argv, needle in cases:
        assert _run("bound", model_path, *argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("lrm-cvx bound: error:") and needle in err and "\n" not in err


# ------------------------------------------------------------------------- evaluate
def test_evaluate_reports_the_recommended_methods_gap_beside_the_papers():
    from test_evaluation import planted

    from lrm_cvx.evaluation import evaluate

    kw = dict(rank=2, n_test=2, budgets=(3, 6), n_starts=2, seed=1,
              methods=("greedy:gp-variance", "greedy"), progress=False,
              scoring=ScoringOptions(min_observations=1,
                                     model_params={"offset": True, "spatial": "exponential"}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = evaluate(planted(), planning=PlanningOptions(certify="fast"),
                      **kw)
        off = evaluate(planted(), planning=PlanningOptions(certify=False),
                       **kw)
    bound, value = ds["recommended_bound"], ds["recommended_value"]
    assert bound.dims == ds["bound"].dims == ("budget", "start")
    assert bound.attrs["method"] == "greedy:gp-variance" and bound.attrs["units"] == "(K)^2"
    assert bool(np.isfinite(bound).all()) and bool((value > 0).all())
    assert bool((bound >= value - 1e-9).all())  # a valid bound on the plan's own value
    assert bool(np.isfinite(ds["bound"]).all())  # the paper's Fisher bound, as before
    assert bool(np.isnan(off["recommended_bound"]).all())
    assert bool(np.isnan(off["recommended_value"]).all())
    # where the dense bound does not reach, the structured one: valid, the rest unchanged
    from lrm_cvx.planning import varbound

    with pytest.MonkeyPatch.context() as mp, warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        mp.setattr(varbound, "DENSE_MAX", 5)
        big = evaluate(planted(), planning=PlanningOptions(certify="fast"),
                       **kw)
    assert not any("gap is not reported" in str(w.message) for w in seen)
    assert bool((big["recommended_bound"] >= big["recommended_value"] - 1e-9).all())
    np.testing.assert_allclose(big["recommended_value"], value, rtol=1e-9)
    np.testing.assert_array_equal(big["bound"].values, ds["bound"].values)
    # the maps and plans are the same with or without the certificate
    np.testing.assert_array_equal(ds["mse"].values, off["mse"].values)
    np.testing.assert_array_equal(ds["greedy_route"].values, off["greedy_route"].values)
