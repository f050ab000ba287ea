"""Replanning en route: the flown part is kept, the rest is replanned from
where the robot is, and the stitched route stays feasible for the original path model (budget,
no-go cells, return home), checked against a brute-force recomputation of its length."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrm_cvx import GLRM, load_sample, plan_greedy
from lrm_cvx.errors import PlanningError
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import PathOptions
from lrm_cvx.replanning import route_feasible


@pytest.fixture(scope="module")
def setup():
    sst = load_sample("sst")
    train, test = sst.isel(time=slice(None, -3)), sst.isel(time=slice(-3, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                     progress=False).fit(train)
    return model, test


def _state_and_plan(model, day, starts, budget, **path):
    state = MonitorState.from_model(model)
    prior = state.planner_kwargs(time=day.time.values)
    plan = plan_greedy(model.Y_, model.region_, starts, budget, criterion="gp-variance",
                       initial="start", progress=False, **prior, path=PathOptions(**path))
    return state, plan


def _flown(plan, done):
    done = [done] if np.ndim(done) == 0 else done
    return np.concatenate([plan.route[plan.route_robot == r][:k] for r, k in enumerate(done)])


def _no_go(model):
    """A no-go band: the cells between 0 and 10 N are closed to the robots."""
    region = model.region_
    mask = np.zeros(region.shape, dtype=bool)
    gi = region.grid_index
    open_ = ~((region.cell_lat >= 0) & (region.cell_lat <= 10))
    mask[gi[:, 0], gi[:, 1]] = open_
    import xarray as xr

    return xr.DataArray(mask, dims=("lat", "lon"),
                        coords={"lat": region.lat.values, "lon": region.lon.values})


CASES = {
    "paper": dict(starts=(10.0, 200.0), budget=30.0, path={}),
    "fleet-km-closed": dict(starts=[(10.0, 200.0), (-20.0, 240.0)], budget=6000.0,
                            path=dict(metric="km", traversable="valid", closed=True)),
    "no-go-end": dict(starts=(20.0, 200.0), budget=8000.0,
                      path=dict(metric="km", traversable="mask", end=(30.0, 220.0))),
    "hours-stops": dict(starts=(-20.0, 240.0), budget=400.0,
                        path=dict(metric="km", speed=20.0, stop_cost=2.0, closed=True,
                                  traversable="valid")),
}


@pytest.mark.parametrize("case", list(CASES))
def test_replanned_route_keeps_the_flown_part_and_stays_feasible(setup, case):
    model, test = setup
    spec = dict(CASES[case])
    path = dict(spec["path"])
    if path.get("traversable") == "mask":
        path["traversable"] = _no_go(model)
    day = test.isel(time=0)
    state, plan = _state_and_plan(model, day, spec["starts"], spec["budget"], **path)
    region = model.region_
    assert route_feasible(plan, region) == []  # the checker agrees with the planner
    sizes = [int(np.count_nonzero(plan.route_robot == r)) for r in range(plan.n_robots)]
    done = [max(1, s // 3) for s in sizes]
    done = done[0] if plan.n_robots == 1 else done
    truth = region.stack(day)
    seen = _flown(plan, done)
    new = state.replan(plan, done, (seen, truth[seen]), time=day.time.values)
    assert route_feasible(new, region) == []
    for r, k in enumerate([done] if np.ndim(done) == 0 else done):
        np.testing.assert_array_equal(new.route[new.route_robot == r][:k],
                                      plan.route[plan.route_robot == r][:k])
        assert new.robot_costs[r] <= plan.path["budgets"][r] * (1 + 1e-9)
    assert new.path == plan.path and new.method.endswith("+replan")
    assert state.posterior.cells.size == int(np.isfinite(truth[seen]).sum())


def test_the_checker_catches_what_it_checks(setup):
    model, test = setup
    day = test.isel(time=0)
    _, plan = _state_and_plan(model, day, (10.0, 200.0), 3000.0, metric="km", closed=True,
                              traversable="valid")
    region = model.region_
    tight = plan.path["budgets"][0] * 0.5
    plan.path = {**dict(plan.path.items()), "budgets": [tight]}
    assert any("budget" in p for p in route_feasible(plan, region))
    plan.path = {**dict(plan.path.items()), "budgets": [3000.0]}
    plan.route[-1] = plan.route[-2]
    assert any("closed tour" in p for p in route_feasible(plan, region))


def test_a_finished_route_is_kept_and_a_spent_budget_is_an_error(setup):
    model, test = setup
    day = test.isel(time=0)
    state, plan = _state_and_plan(model, day, (10.0, 200.0), 2000.0, metric="km",
                                  closed=True, traversable="valid")
    whole = int(plan.route.size)
    same = state.replan(plan, whole)
    np.testing.assert_array_equal(same.route, plan.route)
    # a robot that has used (almost) all its budget away from home cannot replan
    plan.path = {**dict(plan.path.items()), "budgets": [float(plan.route_cost[1])]}
    with pytest.raises(PlanningError, match="spent its budget"):
        state.replan(plan, 2)
    for bad in (0, whole + 1, 1.5, [1, 1]):
        with pytest.raises(PlanningError, match="done"):
            state.replan(plan, bad)


@pytest.mark.parametrize("budget, path", [
    (5000.0, dict(metric="km", traversable="valid", end=(30.0, 220.0))),
    (9000.0, dict(metric="km", traversable="mask", end=(42.5, 232.5))),
    (14.0, dict(metric="grid", traversable="valid", end=(20.0, 220.0), stop_cost=0.5)),
])
def test_a_route_to_an_end_plans_on_the_ellipse_as_on_the_disk(setup, monkeypatch, budget,
                                                                 path):
    # the travel graph of a route to an end holds only the ellipse d(start, x) + d(x, end)
    # <= travel (what makes a replan fast); plans and distances are those of the disk graph
    from lrm_cvx.planning import paths

    model, test = setup
    region = model.region_
    path = dict(path)
    if path["traversable"] == "mask":
        path["traversable"] = _no_go(model)
    prior = MonitorState.from_model(model).planner_kwargs(time=test.time.values[0])
    out = {}
    for ellipse in (True, False):
        monkeypatch.setattr(paths, "ELLIPSE_GRAPH", ellipse)
        pm = paths.make_path_model(region, (20.0, 200.0), budget, **path)
        plan = plan_greedy(model.Y_, region, pm.start, budget, criterion="gp-variance",
                           initial="start", progress=False, **prior, path=PathOptions(**path))
        out[ellipse] = (pm, plan)
    (small, a), (disk, b) = out[True], out[False]
    assert a == b and route_feasible(a, region) == [] and len(a.stops) > 2
    assert small._graph.cells.size < disk._graph.cells.size
    inside = small._graph.cells
    d_small = small.distances(small.start, inside)
    d_disk = disk.distances(disk.start, inside)
    fits = d_disk + disk.distances(disk.end, inside) <= disk.travel_budget
    np.testing.assert_array_equal(d_small[fits], d_disk[fits])


@pytest.mark.parametrize("case", list(CASES) + ["sense-along"])
def test_a_plan_stored_in_the_state_file_reads_back_equal_and_replans_the_same(setup, case,
                                                                                tmp_path):
    model, test = setup
    spec = dict(CASES.get(case, dict(starts=(10.0, 200.0), budget=3000.0,
                                     path=dict(metric="km", sense_along=True, closed=True))))
    path = dict(spec["path"])
    if path.get("traversable") == "mask":
        path["traversable"] = _no_go(model)
    day = test.isel(time=0)
    state, plan = _state_and_plan(model, day, spec["starts"], spec["budget"], **path)
    state.current_plan, state.current_plan_time = plan, day.time.values
    model.save(tmp_path / "m.nc")
    state.model_path = str(tmp_path / "m.nc")
    state.save(tmp_path / "s.nc")
    back = MonitorState.load(tmp_path / "s.nc")
    stored = back.current_plan
    assert stored == plan and back.current_plan_time == day.time.values
    assert dict(stored.path) == dict(plan.path) and stored.history.keys() == plan.history.keys()
    if plan.traversable_mask is None:
        assert stored.traversable_mask is None
    else:
        np.testing.assert_array_equal(stored.traversable_mask, plan.traversable_mask)
    sizes = [int(np.count_nonzero(plan.route_robot == r)) for r in range(plan.n_robots)]
    done = [max(1, s // 2) for s in sizes]
    done = done[0] if plan.n_robots == 1 else done
    truth = model.region_.stack(day)
    seen = _flown(plan, done)
    a = state.replan(plan, done, (seen, truth[seen]), time=day.time.values)
    b = back.replan(None, done, (seen, truth[seen]))  # the stored plan, at its own time
    assert a == b and route_feasible(b, model.region_) == []
    assert back.current_plan is b and back.current_plan_time == day.time.values


def test_replanning_the_stored_plan_needs_one(setup):
    from lrm_cvx.errors import ModelError

    model, _ = setup
    with pytest.raises(ModelError, match="holds no plan"):
        MonitorState.from_model(model).replan(None, 1)


@pytest.mark.parametrize("budget, kept", [(15.0, "transect-up"), (30.0, "greedy")])
def test_a_plan_checked_against_lines_is_replanned_with_the_check(setup, tmp_path, budget,
                                                                   kept):
    """A plan made with ``refine="lines"`` (the recommended plan) is replanned with it: each
    robot's new route is the greedy's from where it is or, when strictly better under the
    criterion, the straight transect from there; the check survives the state file."""
    from lrm_cvx.planning.baselines import transect

    model, test = setup
    region = model.region_
    day = test.isel(time=0)
    truth = region.stack(day)
    starts = (10.0, 200.0)

    def fly(refine):
        state, plan = _state_and_plan(model, day, starts, budget)
        assert not plan.rivals  # a bare factor matrix: no check unless asked
        lined = plan_greedy(model.Y_, region, starts, budget, criterion="gp-variance",
                            initial="start", progress=False, refine="lines",
                            **state.planner_kwargs(time=day.time.values))
        assert set(lined.rivals["values"]) == {"greedy", "transect-up", "transect-down",
                                               "transect-left", "transect-right"}
        done = max(2, int(np.count_nonzero(lined.route_robot == 0)) // 3)
        seen = _flown(lined, done)
        new = state.replan(lined, done, (seen, truth[seen]), time=day.time.values,
                           refine=refine)
        return lined, done, new

    lined, done, auto = fly("auto")
    _, _, plain = fly(None)
    _, _, forced = fly("lines")
    assert auto == forced and auto.rivals == forced.rivals and not plain.rivals
    values, chosen = auto.rivals["values"], auto.rivals["chosen"]
    assert chosen == kept  # both branches below are exercised
    assert values[chosen] == min(values.values())  # gp-variance: the smaller the better
    here = int(lined.route[done - 1])
    tail = auto.route[done:]
    if chosen == "greedy":
        np.testing.assert_array_equal(tail, plain.route[done:])
    else:
        left = budget - float(lined.route_cost[done - 1])
        line = transect(region, here, left, chosen.split("-")[1], Y=model.Y_)
        np.testing.assert_array_equal(tail, line.route[1:])
    assert route_feasible(auto, region) == []
    state = MonitorState.from_model(model)
    state.current_plan, state.current_plan_time = auto, day.time.values
    model.save(tmp_path / "m.nc")
    state.model_path = str(tmp_path / "m.nc")
    state.save(tmp_path / "s.nc")
    assert MonitorState.load(tmp_path / "s.nc").current_plan.rivals == auto.rivals
    with pytest.raises(PlanningError, match="refine must be"):
        state.replan(auto, done, refine="local")


def test_a_plan_checked_against_rivals_is_replanned_with_them(setup, tmp_path):
    """A ``refine="rivals"`` plan (the recommended check) is replanned with the same check
    under ``refine="auto"``: the gentler greedy is among the new route's rivals, the new route
    is the best of them, and the check survives the state file."""
    model, test = setup
    region = model.region_
    day = test.isel(time=0)
    truth = region.stack(day)
    state = MonitorState.from_model(model)
    kw = state.planner_kwargs(time=day.time.values)
    plan = plan_greedy(model.Y_, region, 120, 15.0, criterion="gp-variance", initial="start",
                       progress=False, refine="rivals", **kw)
    assert plan.rivals["refine"] == "rivals" and "greedy-cost^0.5" in plan.rivals["values"]
    done = 4
    seen = _flown(plan, done)
    new = state.replan(plan, done, (seen, truth[seen]), time=day.time.values)
    assert new.rivals["refine"] == "rivals" and "greedy-cost^0.5" in new.rivals["values"]
    values = new.rivals["values"]
    assert values[new.rivals["chosen"]] == min(values.values())
    assert route_feasible(new, region) == []
    lined = state.replan(plan, done, refine="lines")  # asked for: the transects only
    assert "greedy-cost^0.5" not in lined.rivals["values"] and lined.rivals["refine"] == "lines"
    state.current_plan, state.current_plan_time = new, day.time.values
    model.save(tmp_path / "m.nc")
    state.model_path = str(tmp_path / "m.nc")
    state.save(tmp_path / "s.nc")
    assert MonitorState.load(tmp_path / "s.nc").current_plan.rivals == new.rivals


def test_a_kept_transect_is_replanned_with_the_greedys_cost(setup):
    """A morning plan where the check kept a straight transect (route cost ``"steps"``) is
    replanned, twice, with the greedy's own route cost (it failed: "cost must be one of ...,
    got 'steps'", in every campaign with ``replan_every`` whose plan was a transect)."""
    model, test = setup
    region = model.region_
    day = test.isel(time=0)
    truth = region.stack(day)
    state = MonitorState.from_model(model)
    plan = plan_greedy(model.Y_, region, (40.0, 230.0), 15.0, criterion="gp-variance",
                       initial="start", progress=False, refine="lines", cost="insertion",
                       **state.planner_kwargs(time=day.time.values))
    assert plan.method == "transect-down" and plan.cost_function == "steps"
    assert plan.rivals["cost_function"] == "insertion"
    for done in (3, 6):
        seen = plan.route[:done]
        plan = state.replan(plan, done, (seen, truth[seen]), time=day.time.values)
        assert plan.cost_function == "insertion" and plan.rivals["cost_function"] == "insertion"
        assert route_feasible(plan, region) == []


@settings(max_examples=12, deadline=None)
@given(start=st.integers(0, 10_000), budget=st.sampled_from([6.0, 10.0, 15.0]),
       frac=st.floats(0.2, 0.8), closed=st.booleans())
def test_replans_with_the_check_stay_feasible(setup, start, budget, frac, closed):
    """Property: whatever route the check keeps (the greedy's or a transect, morning and en
    route), the replanned plan keeps the flown entries and passes the brute-force check."""
    model, test = setup
    region = model.region_
    day = test.isel(time=0)
    truth = region.stack(day)
    state = MonitorState.from_model(model)
    plan = plan_greedy(model.Y_, region, start % region.n_cells, budget, criterion="gp-variance",
                       initial="start", progress=False, refine="lines",
                       path=PathOptions(closed=closed),
                       **state.planner_kwargs(time=day.time.values))
    if plan.route.size < 3:
        return
    done = min(plan.route.size - 1, max(2, int(frac * plan.route.size)))
    seen = plan.route[:done]
    new = state.replan(plan, done, (seen, truth[seen]), time=day.time.values)
    np.testing.assert_array_equal(new.route[:done], plan.route[:done])
    assert route_feasible(new, region) == []
    assert bool(new.rivals) == (not closed or int(new.route[done - 1]) == plan.start)
