"""Campaigns under the whole path model and fleets: every method plans every
day under the same path request, the routes flown are feasible (a brute-force recomputation of
their length, their cells and their end), the default request is the paper's loop, and bad
requests fail with one line."""

from __future__ import annotations

import dataclasses
import inspect
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import GLRM, load_sample, plan_greedy
from lrm_cvx.campaign import _simulate_campaign, posterior_campaign, simulate_campaign
from lrm_cvx.errors import PlanningError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate, path_label
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import random_walk, transect
from lrm_cvx.planning.request import PathOptions
from lrm_cvx.replanning import route_feasible

STARTS = [(10.0, 200.0), (-20.0, 240.0)]
BUDGETS = [4000.0, 3000.0]
N_DAYS = 3


@pytest.fixture(scope="module")
def sst():
    return load_sample("sst")


@pytest.fixture(scope="module")
def model(sst):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(5, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                    progress=False).fit(sst.isel(time=slice(None, -N_DAYS)))


@pytest.fixture(scope="module")
def test_days(sst):
    return sst.isel(time=slice(-N_DAYS, None))


@pytest.fixture(scope="module")
def no_go(model):
    """Ocean cells between 0 and 10 N are closed to the robots."""
    region = model.region_
    mask = np.zeros(region.shape, dtype=bool)
    gi = region.grid_index
    mask[gi[:, 0], gi[:, 1]] = ~((region.cell_lat >= 0) & (region.cell_lat <= 10))
    return xr.DataArray(mask, dims=("lat", "lon"),
                        coords={"lat": region.lat.values, "lon": region.lon.values})


def _robot_routes(ds, day):
    """Each robot's route on ``day`` from the campaign's Dataset (padding dropped)."""
    route = ds["routes"].values[day]
    robot = ds["route_robot"].values[day] if "route_robot" in ds else np.zeros_like(route)
    keep = route >= 0
    return [route[keep & (robot == r)] for r in range(int(ds.attrs["n_robots"]))]


def _brute_force_problems(ds, model, mask, starts, budgets):
    """``route_feasible`` on every day's flown routes, rebuilt from the Dataset alone (no stop
    cost, so the stop flags do not matter)."""
    region = model.region_
    problems = []
    for day in range(ds.sizes["time"]):
        routes = _robot_routes(ds, day)
        route = np.concatenate(routes)
        robot = np.concatenate([np.full(r.size, i) for i, r in enumerate(routes)])
        fake = SimpleNamespace(
            path={"metric": "km", "traversable": "mask", "closed": True, "stop_cost": 0.0,
                  "budgets": budgets, "starts": starts, "end": None},
            route=route, route_robot=robot, waypoint=np.ones(route.size, bool),
            n_robots=len(routes), budget=sum(budgets), start=starts[0],
            traversable_mask=mask.values)
        problems += [f"day {day}: {p}" for p in route_feasible(fake, region)]
    return problems


@pytest.mark.parametrize("method, every", [("greedy:gp-variance", None),
                                           ("greedy:gp-variance", 3), ("transect-up", None),
                                           ("random", None)])
def test_closed_km_fleet_with_no_go_cells_is_feasible_every_day(model, test_days, no_go,
                                                                method, every):
    ds = simulate_campaign(model, test_days, STARTS, BUDGETS, method=method, replan_every=every,
                           seed=2, path=PathOptions(metric="km", traversable=no_go, closed=True))
    region = model.region_
    starts = [region.resolve_cell(s) for s in STARTS]
    assert _brute_force_problems(ds, model, no_go, starts, BUDGETS) == []
    assert np.all(ds["robot_cost"].values <= np.array(BUDGETS) + 1e-6)
    blocked = ~no_go.values[region.grid_index[:, 0], region.grid_index[:, 1]]
    for day in range(N_DAYS):
        routes = _robot_routes(ds, day)
        assert all(r.size and r[0] == s and r[-1] == s for r, s in zip(routes, starts,
                                                                        strict=True))
        assert not blocked[np.concatenate(routes)].any()  # no-go cells never entered
    assert ds.attrs["n_robots"] == 2 and ds.attrs["closed"] == 1
    assert ds.attrs["traversable"] == "mask" and ds.attrs["budget"] == BUDGETS
    assert path_label(ds.attrs) == "km, traversable mask, closed, 2 robots"
    if every:
        assert ds.attrs["replan_every"] == every and ds["n_replans"].sum() > 0


def test_default_request_is_the_papers_loop(model, test_days):
    """The default call equals the explicit paper request, and a naive re-implementation of the
    loop (forecast, plan_greedy on it, assimilate the plan's cells) day by day."""
    base = simulate_campaign(model, test_days, 40, 12.0, method="greedy:fisher")
    same = simulate_campaign(model, test_days, 40, 12.0, method="greedy:fisher",
                             path=PathOptions(metric="grid", closed=False))
    for name in base.data_vars:
        np.testing.assert_array_equal(base[name].values, same[name].values)
    assert "route_robot" not in base and base.attrs["budget"] == 12.0
    assert base.attrs["start"] == 40 and path_label(base.attrs) == "grid"
    state = MonitorState.from_model(model)
    V = model.region_.stack(test_days).astype(np.float64)
    for i, t in enumerate(test_days.time.values):
        plan = plan_greedy(model.Y, model.region_, 40, 12.0, criterion="fisher",
                           initial="start", progress=False, refine="lines",
                           **state.planner_kwargs(criterion="fisher", time=t))
        route = base["routes"].values[i]
        np.testing.assert_array_equal(route[route >= 0], plan.route)
        cells = np.unique(plan.cells)
        state.assimilate((cells, V[i, cells]), t)
        mean = state.posterior.predict_all()[0]
        ok = np.isfinite(V[i])
        assert base["mse"].values[i] == pytest.approx(np.mean((mean - V[i])[ok] ** 2),
                                                      rel=1e-12)


def test_first_day_is_a_direct_plan_greedy_call(model, test_days, no_go):
    path = PathOptions(metric="km", traversable=no_go, closed=True, stop_cost=50.0,
                       sense_along=True)
    ds = simulate_campaign(model, test_days, STARTS, BUDGETS, method="greedy:gp-variance",
                           path=path)
    prior = MonitorState.from_model(model).planner_kwargs(time=test_days.time.values[0])
    plan = plan_greedy(model.Y, model.region_, STARTS, BUDGETS, criterion="gp-variance",
                       initial="start", progress=False, **prior, path=path)
    route = ds["routes"].values[0]
    np.testing.assert_array_equal(route[route >= 0], plan.route)
    np.testing.assert_array_equal(ds["route_robot"].values[0][route >= 0], plan.route_robot)
    np.testing.assert_allclose(ds["robot_cost"].values[0], plan.robot_costs)
    assert ds["information"].values[0] == plan.information
    # sensing along: every cell passed is observed (the finite ones count)
    truth = model.region_.stack(test_days.isel(time=0))
    passed = np.unique(plan.route)
    assert set(plan.cells.tolist()) == set(passed.tolist())
    assert ds["n_obs"].values[0] == np.count_nonzero(np.isfinite(truth[passed]))
    assert ds.attrs["sense_along"] == 1 and ds.attrs["stop_cost"] == 50.0


def test_baselines_follow_the_path_model_as_their_direct_calls(model, test_days, no_go):
    region = model.region_
    path = PathOptions(metric="km", traversable=no_go, closed=True)
    tr = simulate_campaign(model, test_days, STARTS, BUDGETS, method="transect-up", path=path)
    direct = transect(region, STARTS, BUDGETS, "up", Y=model.Y, path=path)
    for day in range(N_DAYS):  # a transect flies the same route every day
        route = tr["routes"].values[day]
        np.testing.assert_array_equal(route[route >= 0], direct.route)
    np.testing.assert_allclose(tr["robot_cost"].values[0], direct.robot_costs)
    rnd = simulate_campaign(model, test_days, STARTS, BUDGETS, method="random", seed=7,
                            path=path)
    gen = np.random.default_rng(7)  # one stream, drawn day after day
    for day in range(N_DAYS):
        walk = random_walk(region, STARTS, BUDGETS, gen, Y=model.Y, path=path)
        route = rnd["routes"].values[day]
        np.testing.assert_array_equal(route[route >= 0], walk.route)
    # sensing along changes nothing for a baseline: its route passes only its own cells
    along = simulate_campaign(model, test_days, STARTS, BUDGETS, method="transect-up",
                              path=dataclasses.replace(path, sense_along=True))
    np.testing.assert_array_equal(along["mse"].values, tr["mse"].values)


def test_evaluate_campaigns_take_the_path_model_and_fleets(sst, model):
    kw = dict(model=model, n_test=N_DAYS, budgets=(3000.0,), n_starts=1,
              progress=False, temporal="ar1",
              methods=("greedy:gp-variance", "transect-up"),
              path=PathOptions(metric="km", traversable="valid", closed=True), n_robots=2, seed=1,
              planning=PlanningOptions(random_trials=1, certify=False),
              scoring=ScoringOptions(min_observations=1,
                                     fold_in={"prior": "empirical", "spatial": True}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = evaluate(sst, **kw)
    fleet = [int(c) for c in res["fleet_start_cell"].values[0]]
    direct = simulate_campaign(model, sst.isel(time=slice(-N_DAYS, None)), fleet, 3000.0,
                               method="transect-up",
                               path=PathOptions(metric="km", traversable="valid", closed=True))
    sel = {"method": "transect-up", "start": 0, "trial": 0, "budget": 3000.0}
    np.testing.assert_allclose(res["mse"].sel(sel).values, direct["mse"].values)
    np.testing.assert_allclose(res["robot_cost"].sel(sel).values, direct["robot_cost"][0])
    g = res["robot_cost"].sel({**sel, "method": "greedy:gp-variance"}).values
    assert np.all(g <= 3000.0 + 1e-6) and np.all(np.isfinite(res["mse_memoryless"]))
    assert res.attrs["closed"] == 1 and res.attrs["n_robots"] == 2 and res.attrs["end"] == -1


def test_bad_requests_fail_in_one_line(model, test_days):
    with pytest.raises(PlanningError, match="budget has 1 values but there are 2 starts"):
        simulate_campaign(model, test_days, STARTS, [4000.0], path=PathOptions(metric="km"))
    with pytest.raises(PlanningError, match="'transect-up' cannot finish at a fixed end"):
        simulate_campaign(model, test_days, 40, 9.0, method="transect-up", path=PathOptions(end=45))
    with pytest.raises(PlanningError, match="metric"):
        simulate_campaign(model, test_days, 40, 9.0, path=PathOptions(metric="miles"))
    with pytest.raises(PlanningError, match="replan_every"):
        simulate_campaign(model, test_days, 40, 9.0, replan_every=0)
    with pytest.raises(PlanningError, match="replan_every needs a greedy"):
        simulate_campaign(model, test_days, 40, 9.0, method="random", replan_every=2)
    with pytest.raises(TypeError, match="unexpected keyword argument 'refine'"):
        simulate_campaign(model, test_days, 40, 9.0, refine=True)
    data = load_sample("sst")
    with pytest.raises(PlanningError, match="cannot finish at a fixed end"):
        evaluate(data, model=model, n_test=N_DAYS, temporal="ar1", budgets=(9,),
                 methods=("greedy:gp-variance", "random"), progress=False, path=PathOptions(end=45))
    with pytest.raises(PlanningError, match="temporal campaigns only"):
        evaluate(data, model=model, n_test=N_DAYS, budgets=(9,), progress=False,
                 path=PathOptions(sense_along=True))


def test_fixed_end_fleet_and_attrs_round_trip_through_netcdf(sst, model, test_days, tmp_path):
    end = (-12.5, 200.0)
    ds = simulate_campaign(model, test_days, STARTS, [9000.0, 9000.0], method="greedy:fisher",
                           temporal=None,
                           path=PathOptions(metric="km", traversable="valid", end=end))
    cell = model.region_.resolve_cell(end)
    for day in range(N_DAYS):
        assert all(r[-1] == cell for r in _robot_routes(ds, day))  # every robot ends there
    assert ds.attrs["end"] == cell and ds.attrs["closed"] == 0
    ds.to_netcdf(tmp_path / "campaign.nc")
    back = xr.load_dataset(tmp_path / "campaign.nc")
    assert list(back.attrs["start"]) == [model.region_.resolve_cell(s) for s in STARTS]
    np.testing.assert_array_equal(back["route_robot"].values, ds["route_robot"].values)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = evaluate(sst, model=model, n_test=N_DAYS, budgets=(9000.0,), n_starts=1,
                       progress=False, temporal="ar1",
                       methods=("greedy:fisher",),
                       path=PathOptions(metric="km", traversable="valid", end=end),
                       planning=PlanningOptions(certify=False),
                       scoring=ScoringOptions(min_observations=1))
    assert res.attrs["end"] == cell and np.isfinite(res["mse"]).all()


@pytest.mark.parametrize("method", ["greedy:gp-variance", "transect-up"])
def test_a_footprint_campaign_observes_one_average_per_stop(model, test_days, method):
    """With a disc sensor, day 1 folds in the truth averaged over each stop's footprint: the
    campaign's first map equals the memoryless state updated by hand with those averages."""
    from lrm_cvx.planning.planners import planner_for
    from lrm_cvx.planning.request import Fleet
    from lrm_cvx.planning.sensors import plan_observations

    ds = simulate_campaign(model, test_days.isel(time=[0]), (0.0, 200.0), 10.0, method=method,
                           temporal=None, path=PathOptions(sensor="disc:1500km"))
    assert ds.attrs["sensor"] == "disc 1500 km"
    region = model.region_
    state = MonitorState.from_model(model, memoryless=True)
    path = PathOptions(sensor="disc:1500km")
    planner = planner_for(method)
    prior = (state.planner_kwargs(criterion=planner.criterion)["prior"]
             if getattr(planner, "model_prior", False) else None)
    plan = planner.plan(model.Y, region, Fleet.resolve(region, (0.0, 200.0), 10.0), path,
                        rng=np.random.default_rng(0), ridge=0.0, prior=prior)
    np.testing.assert_array_equal(ds["routes"].values[0, : len(plan.route)], plan.route)
    truth = region.stack(test_days.isel(time=0)).astype(np.float64)
    rows, vals = plan_observations(plan, truth)
    assert rows.shape[0] == len(plan.cells) and (rows.getnnz(axis=1) > 1).any()
    # one average per stop, by hand: the mean of the truth over the covered cells
    dense = rows.toarray()
    for r, v in zip(dense, vals, strict=True):
        covered = (r > 0) & np.isfinite(truth)
        assert np.isclose(v, np.average(truth[covered], weights=r[covered]))
    state.assimilate_rows(rows, vals, test_days.time.values[0], errors="independent")
    mean = state.posterior.predict_all()[0]
    observed = np.isfinite(truth)
    assert np.isclose(ds["mse"].values[0], np.mean((mean - truth)[observed] ** 2))


def test_replanning_en_route_refuses_a_footprint_sensor(model, test_days):
    with pytest.raises(PlanningError, match="footprint or towed sensor"):
        simulate_campaign(model, test_days, (0.0, 200.0), 10.0, replan_every=2,
                          path=PathOptions(sensor="disc:1500km"))


def test_the_forecast_error_is_the_morning_map_before_the_samples(model, test_days):
    """``mse_forecast`` of day 1 is the error of the filter's forecast from the last fitted
    snapshot, computed by hand (the posterior's ``mse`` folds the day's samples in)."""
    ds = simulate_campaign(model, test_days, (0.0, 200.0), 10.0, temporal="ar1")
    state = MonitorState.from_model(model)
    t = state._coerce(test_days.time.values[0])
    mean = state._propagated(t).predict()[0]
    truth = model.region_.stack(test_days.isel(time=0)).astype(np.float64)
    ok = np.isfinite(truth)
    assert np.isclose(ds["mse_forecast"].values[0], np.mean((mean - truth)[ok] ** 2))
    assert np.all(np.isfinite(ds["mse_forecast"].values))


def _count_forecast_maps(monkeypatch):
    """A list that grows by one at every map a latent belief predicts (``predict``)."""
    from lrm_cvx.belief.posterior import LatentPosterior

    calls = []
    predict = LatentPosterior.predict

    def counted(self, *args, **kwargs):
        calls.append(1)
        return predict(self, *args, **kwargs)

    monkeypatch.setattr(LatentPosterior, "predict", counted)
    return calls


def test_a_campaign_without_the_forecast_score_skips_the_map_and_keeps_the_rest(
        model, test_days, monkeypatch):
    """``posterior_campaign`` builds no forecast map and drops ``mse_forecast``; every other
    output (routes, maps' errors, coverage, information) is the same bit for bit."""
    calls = _count_forecast_maps(monkeypatch)
    full = simulate_campaign(model, test_days, (0.0, 200.0), 10.0, temporal="ar1")
    assert len(calls) == N_DAYS  # the default scores the morning map of every day
    calls.clear()
    lean = posterior_campaign(model, test_days, (0.0, 200.0), 10.0, temporal="ar1")
    assert not calls and "mse_forecast" not in lean
    xr.testing.assert_identical(full.drop_vars("mse_forecast"), lean)


def test_the_campaign_body_takes_the_public_settings_and_defaults():
    """``simulate_campaign`` forwards to one body: the same settings, names and defaults, plus
    ``score_forecast`` (which only ``posterior_campaign`` turns off)."""
    public = inspect.signature(simulate_campaign).parameters
    body = dict(inspect.signature(_simulate_campaign).parameters)
    assert body.pop("score_forecast").default is True
    assert [(p.name, p.kind, p.default) for p in body.values()] == [
        (p.name, p.kind, p.default) for p in public.values()]


def test_evaluate_builds_no_forecast_map(sst, model, monkeypatch):
    """``evaluate`` reads the campaign's posterior errors only: no day builds a forecast map."""
    calls = _count_forecast_maps(monkeypatch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = evaluate(sst, model=model, n_test=N_DAYS, budgets=(9000.0,), n_starts=1,
                       planning=PlanningOptions(certify=False), progress=False,
                       scoring=ScoringOptions(min_observations=1), temporal="ar1",
                       methods=("greedy:fisher",))
    assert np.isfinite(res["mse"]).all() and not calls
