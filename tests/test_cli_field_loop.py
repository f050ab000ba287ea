"""The glider campaign through the CLI alone (items 1-2): ``fit --hold-out``, ``monitor
init``, then each day ``monitor plan`` (km budgets, closed tours, a no-go band, two robots),
``monitor replan`` after part of the route with the samples taken so far, ``monitor assimilate``
of the rest and ``monitor map``. Every route is checked by the brute-force feasibility checker
and against the no-go band and the homes; the CLI's replan equals ``MonitorState.replan``."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import load_sample
from lrm_cvx.cli import main
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning.request import PlanPath
from lrm_cvx.replanning import route_feasible

STARTS = ["10,200", "-20,240"]
BUDGETS = ["3000", "2500"]
N_DAYS = 3


def _run(*argv):
    return main(["-q", *map(str, argv)])


def _no_go_band(region) -> xr.DataArray:
    """Travel allowed everywhere but the band 5 S - 5 N (False = no-go)."""
    lat = region.lat.values[:, None] * np.ones((1, region.lon.size))
    return xr.DataArray(~((lat >= -5) & (lat <= 5)), dims=("lat", "lon"),
                        coords={"lat": region.lat.values, "lon": region.lon.values},
                        name="may_enter")


def _check_routes(plan, region, allowed):
    assert route_feasible(plan, region) == []  # budget (legs from coordinates), no-go, home
    gi = region.grid_index[plan.route]
    assert allowed[gi[:, 0], gi[:, 1]].all(), "a robot entered a no-go cell"
    for r in range(plan.n_robots):
        route = plan.route[plan.route_robot == r]
        assert route[0] == route[-1] == plan.path["starts"][r]  # a closed tour returns home
        assert plan.robot_costs[r] <= plan.path["budgets"][r] * (1 + 1e-9)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Run the whole campaign once; the tests read what it recorded."""
    folder = tmp_path_factory.mktemp("field")
    sst = load_sample("sst")
    model, state = folder / "model.nc", folder / "state.nc"
    assert _run("fit", "sample:sst", "--rank", 5, "--recommended", "--temporal", "ar1",
                "--seed", 0, "--hold-out", N_DAYS, "-o", model) == 0
    assert _run("monitor", "init", model, "--state", state) == 0
    region = MonitorState.load(state).model.region_
    band = _no_go_band(region)
    band.to_dataset().to_netcdf(folder / "nogo.nc")
    allowed = band.values
    days = []
    for i in range(N_DAYS):
        day = sst.isel(time=-N_DAYS + i)
        t = str(day.time.values)[:19]
        truth = region.stack(day).astype(np.float64)
        before = MonitorState.load(state)
        assert _run("monitor", "plan", state, "--time", t, *[a for s in STARTS
                                                             for a in ("--start", s)],
                    *[a for b in BUDGETS for a in ("--budget", b)], "--metric", "km",
                    "--closed", "--traversable", folder / "nogo.nc",
                    "-o", folder / f"plan{i}.csv") == 0
        planned = MonitorState.load(state)
        plan = planned.current_plan
        table = pd.read_csv(folder / f"plan{i}.csv")
        np.testing.assert_array_equal(table["cell"], plan.route)
        sizes = [int(np.count_nonzero(plan.route_robot == r)) for r in range(plan.n_robots)]
        done = [max(2, s // 2) for s in sizes]
        flown = np.concatenate([plan.route[plan.route_robot == r][:k]
                                for r, k in enumerate(done)])
        flown = flown[np.isfinite(truth[flown])]
        pd.DataFrame({"cell": flown, "value": truth[flown]}).to_csv(folder / f"obs{i}.csv",
                                                                    index=False)
        reference = MonitorState.load(state)  # the Python loop on the same state
        expected = reference.replan(None, done, (flown, truth[flown]))
        assert _run("monitor", "replan", state, "--done", *done, "--observations",
                    folder / f"obs{i}.csv", "-o", folder / f"replan{i}.csv") == 0
        replanned = MonitorState.load(state)
        new = replanned.current_plan
        rest = np.concatenate([new.route[new.route_robot == r][k:] for r, k in enumerate(done)])
        rest = rest[np.isfinite(truth[rest])]
        pd.DataFrame({"cell": rest, "value": truth[rest]}).to_csv(folder / f"rest{i}.csv",
                                                                  index=False)
        assert _run("monitor", "assimilate", state, folder / f"rest{i}.csv", "--time", t,
                    "--force") == 0
        assert _run("monitor", "map", state, "-o", folder / f"map{i}.nc") == 0
        days.append(dict(t=day.time.values, before=before, plan=plan, done=done, new=new,
                         expected=expected, reference=reference, replanned=replanned,
                         table=pd.read_csv(folder / f"replan{i}.csv"), after=MonitorState.load(
                             state), n_flown=flown.size, n_rest=rest.size,
                         map=xr.open_dataset(folder / f"map{i}.nc").load()))
    assert _run("monitor", "map", state, "-o", folder / "map.png") == 0
    return dict(folder=folder, region=region, allowed=allowed, days=days, state=state)


def test_every_route_is_feasible_and_avoids_the_no_go_band(campaign):
    region, allowed = campaign["region"], campaign["allowed"]
    for d in campaign["days"]:
        assert d["plan"].n_robots == 2 and d["plan"].path["traversable"] == "mask"
        assert d["plan"].path["unit"] == "km" and d["plan"].path["closed"]
        _check_routes(d["plan"], region, allowed)
        _check_routes(d["new"], region, allowed)


def test_the_cli_replan_is_the_python_replan(campaign):
    for d in campaign["days"]:
        assert d["new"] == d["expected"]  # every array, the path and the scalars
        np.testing.assert_array_equal(d["table"]["cell"], d["expected"].route)
        np.testing.assert_allclose(d["replanned"].posterior.mean,
                                   d["reference"].posterior.mean, rtol=0, atol=0)
        for r, k in enumerate(d["done"]):  # the flown part is kept
            np.testing.assert_array_equal(d["new"].route[d["new"].route_robot == r][:k],
                                          d["plan"].route[d["plan"].route_robot == r][:k])
        assert d["new"].method == "greedy+replan" and d["new"].path == d["plan"].path


def test_the_state_advances_day_by_day(campaign):
    days = campaign["days"]
    for i, d in enumerate(days):
        assert d["replanned"].time == d["t"] and d["after"].time == d["t"]
        assert d["replanned"].n_assimilated == d["before"].n_assimilated + d["n_flown"]
        assert d["after"].n_assimilated == d["replanned"].n_assimilated + d["n_rest"]
        assert d["after"].current_plan == d["new"] and d["after"].current_plan_time == d["t"]
        assert d["map"]["time"].values == d["t"] and d["map"]["mean"].dims == ("lat", "lon")
        if i:
            assert d["before"].time == days[i - 1]["t"]
    assert (campaign["folder"] / "map.png").stat().st_size > 1000


def test_the_stored_plan_reads_back_equal(campaign, tmp_path):
    s = MonitorState.load(campaign["state"])
    s.save(tmp_path / "again.nc")
    again = MonitorState.load(tmp_path / "again.nc")
    assert again.current_plan == s.current_plan
    np.testing.assert_array_equal(again.current_plan.traversable_mask, campaign["allowed"]
                                  & campaign["region"].mask)


def _err(capsys):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_replan_refusals_are_one_line_and_change_nothing(campaign, tmp_path, capsys):
    folder = campaign["folder"]
    state = tmp_path / "s.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    capsys.readouterr()
    assert _run("monitor", "replan", state, "--done", 2) == 2
    assert "holds no plan" in _err(capsys)
    t = str(campaign["days"][0]["t"])[:19]
    assert _run("monitor", "plan", state, "--time", t, "--start", STARTS[0], "--start",
                STARTS[1], "--budget", 3000, "--metric", "km", "--closed", "--traversable",
                folder / "nogo.nc", "-o", tmp_path / "p.csv") == 0
    capsys.readouterr()
    before = state.read_bytes()
    size = int(np.count_nonzero(MonitorState.load(state).current_plan.route_robot == 0))
    cases = [(["--done", size + 1, 2], "done[0] must be in [1, "),
             (["--done", 2], "one count per robot"),
             (["--done", 2, 2, "--observations", folder / "obs0.csv", "--time",
               "2012-01-16"], "not the time of the stored plan"),
             (["--done", 2, 2, "-o", tmp_path / "x.txt"], "-o must end in")]
    for argv, needle in cases:
        assert _run("monitor", "replan", state, *argv) == 2
        assert needle in _err(capsys)
        assert state.read_bytes() == before and not (tmp_path / "x.txt").exists()
    # a robot that has spent its budget away from home cannot replan: an error, not a route
    s = MonitorState.load(state)
    plan = s.current_plan
    first = np.flatnonzero(plan.route_robot == 0)
    plan.path = PlanPath({**dict(plan.path.items()), "budgets": [
        float(plan.route_cost[first[1]]), plan.path["budgets"][1]]}, options=plan.path.options)
    s.save(state)
    before = state.read_bytes()
    assert _run("monitor", "replan", state, "--done", 2, 1) == 2
    assert "spent its budget" in _err(capsys)
    assert state.read_bytes() == before
    # the state moved on to the next day: the stored plan is stale
    s = MonitorState.load(state)
    s.assimilate((np.array([0]), np.array([0.0])), campaign["days"][1]["t"])
    s.save(state)
    assert _run("monitor", "replan", state, "--done", 1, 1) == 2
    assert "has moved on" in _err(capsys)


def test_a_yearly_record_plans_for_its_next_stamp_and_replans_within_the_year(campaign,
                                                                              tmp_path, capsys):
    # sample:sst holds one January mean a year (15 Jan 12:00 or 16 Jan 00:00): the default
    # plan after 15 Jan 2009 12:00 is for the held-out 15 Jan 2010 12:00, and any time of 2010
    # is that plan's snapshot
    folder = campaign["folder"]
    state = tmp_path / "s.nc"
    t = campaign["days"][0]["t"]
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    capsys.readouterr()
    assert _run("monitor", "plan", state, "--start", STARTS[0], "--budget", 3000, "--metric",
                "km", "-o", tmp_path / "p.csv") == 0
    assert f"plan for {str(t)[:19]}:" in capsys.readouterr().out
    assert MonitorState.load(state).current_plan_time == t
    assert _run("monitor", "replan", state, "--done", 2, "--time", "2010-06-30") == 0
    assert MonitorState.load(state).current_plan_time == t
    assert _run("monitor", "replan", state, "--done", 2, "--time", "2011-01-15") == 2
    assert "not the time of the stored plan" in capsys.readouterr().err
