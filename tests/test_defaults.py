"""The recommended setting is the library's default wherever the paper's is not
asked for (``paper=True``); explicit arguments win over both; ``paper`` must be a bool.

Every default is compared with the same call spelled out explicitly (outputs equal), so a
default that drifts from RECOMMENDED, or a ``paper=True`` that drifts from the paper, fails.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

import lrm_cvx  # noqa: F401  (registers the .lrm accessor)
from lrm_cvx.campaign import simulate_campaign
from lrm_cvx.errors import ModelError, PlanningError
from lrm_cvx.evaluation import METHODS, PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import place_sensors, plan_greedy
from lrm_cvx.recommended import RECOMMENDED

N_TEST = 4
EV = dict(rank=3, n_test=N_TEST, budgets=(3, 8), n_starts=2,
          seed=1, progress=False,
          planning=PlanningOptions(random_trials=2, certify=False),
          scoring=ScoringOptions(min_observations=3))


def ev(**scoring) -> dict:
    """``EV`` with these fields of its scoring."""
    return dict(EV, scoring=ScoringOptions(min_observations=3, **scoring))


def planted(seed=0, T=20, ny=8, nx=9, k=3):
    """A rank-``k`` field plus a smooth (spatially correlated) residual and noise."""
    rng = np.random.default_rng(seed)
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, ny * nx))
    yy, xx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    smooth = np.sin(yy / 2.0 + rng.normal(size=(T, 1, 1))) * np.cos(xx / 3.0)
    data = ((X.T @ Y).reshape(T, ny, nx) + 0.3 * smooth
            + 0.05 * rng.normal(size=(T, ny, nx)))
    data[rng.random(data.shape) < 0.15] = np.nan
    data[:, :2, :2] = np.nan  # "land" never observed
    return xr.DataArray(data.astype(np.float32), dims=("time", "lat", "lon"), name="sst",
                        coords={"time": np.arange(T), "lat": 1.0 * np.arange(ny),
                                "lon": 1.0 * np.arange(nx)}, attrs={"units": "K"})


def quiet(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kw)


@pytest.fixture(scope="module")
def data():
    return planted()


@pytest.fixture(scope="module")
def train(data):
    return data.isel(time=slice(None, -N_TEST))


@pytest.fixture(scope="module")
def spatial_model(train):
    return quiet(GLRM(3, offset=True, spatial="exponential", random_state=0,
                      progress=False).fit, train)


@pytest.fixture(scope="module")
def plain_model(train):
    return quiet(GLRM(3, random_state=0, progress=False).fit, train)


def recommended_params():
    """The GLRM parameters of RECOMMENDED, spelled out (evaluate leaves out temporal)."""
    names = set(GLRM().get_params()) - {"temporal"}
    return {key: value for key, value in RECOMMENDED.items() if key in names}


RECOMMENDED_FOLD_IN = {"prior": RECOMMENDED["prior"], "spatial": RECOMMENDED["fold_spatial"]}


# ------------------------------------------------------------------------------ evaluate
def test_evaluate_default_is_the_recommended_setting_spelled_out(data):
    default = quiet(evaluate, data, **EV)
    explicit = quiet(evaluate, data, methods=(RECOMMENDED["method"], *METHODS),
                     **ev(model_params=recommended_params(), fold_in=RECOMMENDED_FOLD_IN))
    xr.testing.assert_identical(default, explicit)
    assert list(default["method"].values) == [RECOMMENDED["method"], *METHODS]
    assert "spatial" in default.attrs["model_params"] and "complete_mse_model" in default
    # and it is not the paper's: another model, another fold-in, another error
    paper = evaluate(data, paper=True, **EV)
    sel = {"method": "transect-up"}
    assert not np.allclose(default["mse"].sel(sel), paper["mse"].sel(sel), equal_nan=True)


def test_evaluate_paper_is_the_old_default_bit_for_bit(data):
    """``paper=True`` is the paper's protocol: GLRM(rank), the
    paper's METHODS, the least-squares fold-in (the old defaults, given explicitly)."""
    paper = evaluate(data, paper=True, **EV)
    old = evaluate(data, methods=METHODS, **ev(model_params={}, fold_in={}))
    xr.testing.assert_identical(paper, old)
    assert list(paper["method"].values) == list(METHODS)
    assert "complete_mse_model" not in paper and paper.attrs["model_params"] == "{}"


def test_evaluate_explicit_arguments_win_over_paper(data):
    kw = dict(methods=("greedy:gp-variance", "greedy"),
              **ev(model_params=recommended_params(), fold_in=RECOMMENDED_FOLD_IN))
    a = quiet(evaluate, data, paper=True, **kw)
    b = quiet(evaluate, data, paper=False, **kw)
    xr.testing.assert_identical(a, b)
    # one explicit argument: only that one wins, the others stay the paper's
    c = evaluate(data, paper=True, methods=("greedy", "random"), **EV)
    d = evaluate(data, methods=("greedy", "random"), **ev(model_params={}, fold_in={}))
    xr.testing.assert_identical(c, d)


def test_evaluate_model_without_residual_falls_back_with_one_warning(data, plain_model):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = evaluate(data, model=plain_model, **EV)
    fallback = [w for w in caught if "no spatial residual" in str(w.message)]
    assert len(fallback) == 1 and fallback[0].category is UserWarning
    assert fallback[0].filename == __file__  # points at the caller
    want = evaluate(data, model=plain_model, methods=("greedy:fisher", *METHODS),
                    **ev(fold_in={"prior": RECOMMENDED["prior"], "spatial": False}))
    xr.testing.assert_identical(got, want)
    # explicit choices and paper=True never warn
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        evaluate(data, model=plain_model, paper=True, **EV)
        evaluate(data, model=plain_model, methods=("greedy",),
                 **ev(fold_in={"prior": "empirical"}))


def test_evaluate_model_with_residual_takes_the_whole_recommended_setting(data,
                                                                          spatial_model):
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no fallback
        got = evaluate(data, model=spatial_model, **EV)
    want = evaluate(data, model=spatial_model, methods=(RECOMMENDED["method"], *METHODS),
                    **ev(fold_in=RECOMMENDED_FOLD_IN))
    xr.testing.assert_identical(got, want)


@pytest.mark.parametrize("bad", ["yes", 1, None, np.float64(1.0)])
def test_paper_must_be_a_bool(data, spatial_model, test_data, bad):
    with pytest.raises(ModelError, match="paper must be True or False"):
        evaluate(data, paper=bad, **EV)
    with pytest.raises(PlanningError, match="paper must be True or False"):
        plan_greedy(spatial_model, 5, 6.0, paper=bad, progress=False)
    with pytest.raises(PlanningError, match="paper must be True or False"):
        simulate_campaign(spatial_model, test_data, 5, 6.0, paper=bad)
    with pytest.raises(PlanningError, match="paper must be True or False"):
        place_sensors(spatial_model, 4, paper=bad)


# ------------------------------------------------------------------------------ plan_greedy
def same_plan(a, b):
    np.testing.assert_array_equal(a.route, b.route)
    np.testing.assert_array_equal(a.cells, b.cells)
    assert a.criterion == b.criterion and a.cost == pytest.approx(b.cost, abs=0)
    assert a.information == b.information or (np.isnan(a.information)
                                               and np.isnan(b.information))


def test_plan_greedy_on_a_model_is_the_recommended_planner(spatial_model):
    m = spatial_model
    got = plan_greedy(m, 5, 9.0, progress=False)
    want = plan_greedy(m.Y_, m.region_, 5, 9.0, criterion=RECOMMENDED["criterion"],
                       initial=RECOMMENDED["initial"], refine=RECOMMENDED["refine"],
                       progress=False,
                       **m.planner_kwargs(prior=RECOMMENDED["prior"], spatial=True))
    assert got.rivals["criterion"] == "gp-variance" and len(got.rivals["values"]) == 6
    same_plan(got, want)
    # the region may be given, start / budget by keyword
    same_plan(plan_greedy(m, m.region_, 5, 9.0, progress=False), want)
    same_plan(plan_greedy(m, start=5, budget=9.0, progress=False), want)
    same_plan(plan_greedy(m, 5, budget=9.0, progress=False), want)
    # the accessor plans on the model the same way
    same_plan(xr.DataArray([0.0]).lrm.plan(m, 5, 9.0, progress=False), want)


def test_plan_greedy_paper_is_the_bare_factor_matrix(spatial_model):
    m = spatial_model
    paper = plan_greedy(m, 5, 9.0, paper=True, progress=False)
    same_plan(paper, plan_greedy(m.Y_, m.region_, 5, 9.0, progress=False))
    same_plan(paper, plan_greedy(m.Y_, m.region_, 5, 9.0, criterion="fisher",
                                 initial="nearest", progress=False))
    assert paper.criterion == "fisher" and not paper.posterior and not paper.rivals


def test_plan_greedy_explicit_arguments_win(spatial_model):
    m = spatial_model
    # over paper=True
    a = plan_greedy(m, 5, 9.0, paper=True, criterion="a-optimal", initial="start", ridge=1e-3,
                    progress=False)
    b = plan_greedy(m.Y_, m.region_, 5, 9.0, criterion="a-optimal", initial="start",
                    ridge=1e-3, progress=False)
    same_plan(a, b)
    # over the recommended criterion: the recommended prior stays, without the residual terms
    c = plan_greedy(m, 5, 9.0, criterion="fisher", progress=False)
    d = plan_greedy(m.Y_, m.region_, 5, 9.0, criterion="fisher", initial="start",
                    prior=m.latent_prior("empirical"), refine="rivals", progress=False)
    same_plan(c, d)
    # a given prior wins over the recommended one
    flat = m.latent_prior(None)
    same_plan(plan_greedy(m, 5, 9.0, criterion="fisher", prior=flat, ridge=1e-3,
                          progress=False),
              plan_greedy(m.Y_, m.region_, 5, 9.0, criterion="fisher", initial="start",
                          prior=flat, ridge=1e-3, refine="rivals", progress=False))


def test_plan_greedy_model_without_residual_plans_fisher_on_the_empirical_prior(plain_model):
    m = plain_model
    got = plan_greedy(m, 5, 9.0, progress=False)
    want = plan_greedy(m.Y_, m.region_, 5, 9.0, criterion="fisher", initial="start",
                       refine="lines", progress=False, **m.planner_kwargs(prior="empirical"))
    same_plan(got, want)
    assert got.rivals["chosen"] == "greedy"  # else the plan is a transect's
    assert got.criterion == "fisher" and got.posterior


def test_plan_greedy_bad_model_calls(train):
    with pytest.raises(PlanningError, match="not fitted"):
        plan_greedy(GLRM(3), 5, 9.0)
    arr = quiet(GLRM(2, random_state=0, progress=False).fit,
                train.values.reshape(train.sizes["time"], -1))
    with pytest.raises(PlanningError, match="no region"):
        plan_greedy(arr, 5, 9.0)
    with pytest.raises(PlanningError, match="region is missing"):
        plan_greedy(np.ones((2, 10)), start=0, budget=3.0)


# ------------------------------------------------------------------------------ campaigns
@pytest.fixture(scope="module")
def test_data(data):
    return data.isel(time=slice(-N_TEST, None))


def test_campaign_default_method(spatial_model, plain_model, test_data):
    kw = dict(temporal=None, seed=0)
    xr.testing.assert_identical(
        simulate_campaign(spatial_model, test_data, 5, 6.0, **kw),
        simulate_campaign(spatial_model, test_data, 5, 6.0, method=RECOMMENDED["method"], **kw))
    # without a residual the recommended gp-variance cannot run: Fisher on the forecast
    plain = simulate_campaign(plain_model, test_data, 5, 6.0, **kw)
    xr.testing.assert_identical(
        plain, simulate_campaign(plain_model, test_data, 5, 6.0, method="greedy:fisher", **kw))
    assert plain.attrs["method"] == "greedy:fisher"
    # the same when the residual is switched off
    xr.testing.assert_identical(
        simulate_campaign(spatial_model, test_data, 5, 6.0, spatial=False, **kw),
        simulate_campaign(spatial_model, test_data, 5, 6.0, spatial=False,
                          method="greedy:fisher", **kw))
    # paper=True: the paper's greedy; an explicit method wins
    xr.testing.assert_identical(
        simulate_campaign(spatial_model, test_data, 5, 6.0, paper=True, **kw),
        simulate_campaign(spatial_model, test_data, 5, 6.0, method="greedy", **kw))
    xr.testing.assert_identical(
        simulate_campaign(spatial_model, test_data, 5, 6.0, paper=True, method="transect-up",
                          **kw),
        simulate_campaign(spatial_model, test_data, 5, 6.0, method="transect-up", **kw))


def test_monitor_planner_kwargs_default(spatial_model, plain_model):
    s = MonitorState.from_model(spatial_model)
    got, want = s.planner_kwargs()["prior"], s.planner_kwargs(criterion="gp-variance")["prior"]
    assert got.same(want) and got.spatial_cov is not None
    p = MonitorState.from_model(plain_model)
    got, want = p.planner_kwargs()["prior"], p.planner_kwargs(criterion="fisher")["prior"]
    assert got.same(want) and got.spatial_cov is None and got.noise_var is not None
    with pytest.raises(ModelError, match="gp-variance"):
        p.planner_kwargs(criterion="gp-variance")  # explicit: still refused without residual


def test_evaluate_default_calibrates_and_warns_on_a_record_too_short(data):
    """evaluate's own recommended fit calibrates its intervals as ``GLRM(calibration=...)``
    does; on a record too short for the calibration's refits (6 training snapshots) it warns
    once and scores the uncalibrated intervals, equal to an uncalibrated recommended run."""
    short = data.isel(time=slice(0, 6 + N_TEST))
    params = {k: v for k, v in recommended_params().items() if k != "calibration"}
    with pytest.warns(UserWarning, match="calibration cannot run") as caught:
        got = evaluate(short, **EV)
    assert sum("calibration cannot run" in str(w.message) for w in caught) == 1
    ref = quiet(evaluate, short, **ev(model_params=params))
    np.testing.assert_array_equal(got["mse"].values, ref["mse"].values)
    np.testing.assert_array_equal(got["coverage95"].values, ref["coverage95"].values)
