"""``lrm-cvx monitor``: the field loop in a temporary folder, its refusals and a crash mid-write."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.cli import main
from lrm_cvx.glrm import GLRM
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import PathOptions


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("monitor")
    da = synthetic_dynamic_field(34, (6, 7), 3, seed=4, noise=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, progress=False, max_iter=20, temporal="ar1", offset=True).fit(
            da.isel(time=slice(0, 30)))
        other = GLRM(3, progress=False, max_iter=20, random_state=1).fit(
            da.isel(time=slice(0, 29)))
    model.save(folder / "model.nc")
    other.save(folder / "other.nc")
    da.isel(time=30).to_dataset(name="ndvi").to_netcdf(folder / "obs30.nc")
    day31 = da.isel(time=31).to_dataframe(name="value").reset_index().dropna()
    day31[["lat", "lon", "value"]].head(6).to_csv(folder / "obs31.csv", index=False)
    return folder, da, model


def _run(*argv):
    return main(["-q", *map(str, argv)])


def test_the_field_loop(files, tmp_path, capsys):
    folder, da, model = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    assert MonitorState.load(state).time == da.time.values[29]
    assert _run("monitor", "plan", state, "--start", da.lat.values[2], da.lon.values[3],
                "--budget", 4, "-o", tmp_path / "plan.csv") == 0
    plan = pd.read_csv(tmp_path / "plan.csv")
    assert {"cell", "lat", "lon"} <= set(plan.columns) and len(plan) >= 1
    assert _run("monitor", "plan", state, "--start", da.lat.values[2], da.lon.values[3],
                "--budget", 4, "-o", tmp_path / "plan.geojson") == 0
    assert _run("monitor", "assimilate", state, folder / "obs30.nc",
                "--time", "2013-01-31") == 0
    s = MonitorState.load(state)
    expected = MonitorState.from_model(model).assimilate(da.isel(time=30), da.time.values[30])
    np.testing.assert_allclose(s.posterior.mean, expected.posterior.mean, rtol=1e-10)
    assert _run("monitor", "assimilate", state, folder / "obs31.csv",
                "--time", "2013-02-01") == 0
    s = MonitorState.load(state)
    assert s.time == da.time.values[31] and s.posterior.cells.size == 6
    assert _run("monitor", "map", state, "-o", tmp_path / "map.nc") == 0
    with xr.open_dataset(tmp_path / "map.nc") as m:
        assert {"mean", "std", "predictive_std"} <= set(m.data_vars)
        assert m["mean"].dims == ("lat", "lon")
        assert m["time"].values == da.time.values[31]
    assert _run("monitor", "map", state, "-o", tmp_path / "fc.nc", "--forecast") == 0
    with xr.open_dataset(tmp_path / "fc.nc") as m:
        assert m["time"].values == da.time.values[32]
    assert _run("monitor", "map", state, "-o", tmp_path / "map.png") == 0
    assert (tmp_path / "map.png").stat().st_size > 1000


def test_out_of_order_times_are_refused(files, tmp_path, capsys):
    folder, da, _ = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    assert _run("monitor", "assimilate", state, folder / "obs31.csv", "--time", "2013-02-01") == 0
    before = state.read_bytes()
    capsys.readouterr()
    assert _run("monitor", "assimilate", state, folder / "obs30.nc",
                "--time", "2013-01-31") == 2
    err = capsys.readouterr().err
    assert "earlier than" in err and err.count("\n") == 1
    assert _run("monitor", "assimilate", state, folder / "obs31.csv",
                "--time", "2013-02-01") == 2
    assert state.read_bytes() == before  # nothing written
    assert _run("monitor", "assimilate", state, folder / "obs31.csv", "--time", "2013-02-01",
                "--force") == 0
    assert MonitorState.load(state).posterior.cells.size == 12


def test_init_at_a_time_then_assimilate_that_day(files, tmp_path):
    folder, da, _ = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state,
                "--time", "2013-02-01") == 0
    assert not MonitorState.load(state).observed
    assert _run("monitor", "assimilate", state, folder / "obs31.csv", "--time", "2013-02-01") == 0


def test_bad_input_exits_2_and_writes_nothing(files, tmp_path, capsys):
    folder, da, _ = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "other.nc", "--state", state) == 2
    assert "no dynamics" in capsys.readouterr().err and not state.exists()
    assert _run("monitor", "init", folder / "other.nc", "--state", state, "--memoryless") == 0
    assert MonitorState.load(state, GLRM.load(folder / "other.nc")).memoryless
    # a state of another model
    with pytest.raises(Exception, match="another model"):
        MonitorState.load(state, GLRM.load(folder / "model.nc"))
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 2  # exists
    assert "--overwrite" in capsys.readouterr().err
    # observations off the region
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"lat": [89.0], "lon": [0.0], "value": [0.3]}).to_csv(bad, index=False)
    before = state.read_bytes()
    assert _run("monitor", "assimilate", state, bad, "--time", "2013-02-01") == 2
    assert "lat=89" in capsys.readouterr().err
    assert state.read_bytes() == before
    # corrupt / truncated state
    trunc = tmp_path / "trunc.nc"
    trunc.write_bytes(before[: len(before) // 3])
    assert _run("monitor", "map", trunc, "-o", tmp_path / "m.nc") == 2
    assert "corrupt or truncated" in capsys.readouterr().err
    assert not (tmp_path / "m.nc").exists()
    assert _run("monitor", "plan", state, "--start", "0", "0", "--budget", "3",
                "-o", tmp_path / "p.txt") == 2
    assert _run("monitor", "assimilate", state, tmp_path / "none.csv", "--time", "2013-02-01") == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_crash_during_the_state_write_keeps_the_old_state(files, tmp_path, monkeypatch):
    folder, da, _ = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    before = state.read_bytes()
    real = xr.Dataset.to_netcdf

    def crash(self, path=None, *args, **kwargs):  # write half a file, then die
        real(self, path, *args, **kwargs)
        with open(path, "r+b") as f:
            f.truncate(100)
        raise OSError("simulated crash during the write")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", crash)
    assert _run("monitor", "assimilate", state, folder / "obs30.nc", "--time", "2013-01-31") == 2
    monkeypatch.undo()
    assert state.read_bytes() == before
    s = MonitorState.load(state)
    assert s.time == da.time.values[29] and s.posterior.cells.size == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.nc"]  # no temporary left


# ----------------------------------------------- a user's own record
def test_mid_month_stamps_are_kept(tmp_path):
    # a monthly record stamped mid-month (16 Jan 12:00, 15 Feb 00:00, 16 Mar 12:00, 16 Apr
    # 00:00, ...): the next time is the record's own April stamp, not 16 Apr 12:00
    rng = np.random.default_rng(0)
    starts = pd.date_range("2005-01-01", periods=37, freq="MS")
    mids = [a + (b - a) / 2 for a, b in zip(starts[:-1], starts[1:], strict=True)]
    da = xr.DataArray(rng.normal(size=(36, 4, 5)).astype(np.float32),
                      dims=("time", "lat", "lon"),
                      coords={"time": mids, "lat": np.arange(4.0), "lon": np.arange(5.0)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(2, temporal="ar1", progress=False, random_state=0).fit(
            da.isel(time=slice(0, 27)))
    state = MonitorState.from_model(model)
    assert pd.Timestamp(state.time) == pd.Timestamp("2007-03-16T12:00")
    assert state.next_time() == da.time.values[27]  # 2007-04-16T00:00


def test_a_360_day_calendar_date_is_a_valid_time(tmp_path, capsys):
    import cftime

    rng = np.random.default_rng(1)
    times = [cftime.datetime(2090 + i // 12, i % 12 + 1, 15, calendar="360_day")
             for i in range(40)]
    da = xr.DataArray(rng.normal(size=(40, 4, 5)).astype(np.float32),
                      dims=("time", "lat", "lon"),
                      coords={"time": times, "lat": np.arange(4.0), "lon": np.arange(5.0)})
    da.to_dataset(name="tas").to_netcdf(tmp_path / "tas.nc")
    model = tmp_path / "m.nc"
    # fit on a 360-day record up to a date that only that calendar has
    assert _run("fit", tmp_path / "tas.nc", "--rank", 2, "--temporal", "ar1", "--until",
                "2092-02-30", "-o", model) == 0
    assert "held out the last 14 of 40" in capsys.readouterr().out
    state = tmp_path / "s.nc"
    assert _run("monitor", "init", model, "--state", state) == 0
    assert _run("monitor", "plan", state, "--start", "1,1", "--budget", 3, "--time",
                "2092-04-30", "-o", tmp_path / "p.csv") == 0
    assert "plan for 2092-04-30" in capsys.readouterr().out
    assert _run("monitor", "plan", state, "--start", "1,1", "--budget", 3, "--time",
                "2092-04-31", "-o", tmp_path / "q.csv") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lrm-cvx monitor plan: error: --time") or "360_day calendar" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "q.csv").exists()


@pytest.mark.parametrize("argv, needle", [
    (["--hold-out", "39"], "leaves 1 of 40"),
    (["--until", "2000-01-01"], "keeps 0 of 40"),
    (["--until", "2091-13-01"], "360_day calendar"),
    (["--hold-out", "3", "--until", "2092-01-01"], "exclude each other"),
])
def test_fit_hold_out_bad_input(tmp_path, capsys, argv, needle):
    import cftime

    times = [cftime.datetime(2090 + i // 12, i % 12 + 1, 15, calendar="360_day")
             for i in range(40)]
    da = xr.DataArray(np.random.default_rng(2).normal(size=(40, 3, 4)).astype(np.float32),
                      dims=("time", "lat", "lon"),
                      coords={"time": times, "lat": np.arange(3.0), "lon": np.arange(4.0)})
    da.to_dataset(name="tas").to_netcdf(tmp_path / "tas.nc")
    assert _run("fit", tmp_path / "tas.nc", "--rank", 2, *argv, "-o", tmp_path / "m.nc") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "m.nc").exists()


# ------------------------------------------- one daily loop, every path model
def test_monitor_plan_takes_every_path_option_and_fleets(tmp_path, capsys):
    from lrm_cvx import load_sample
    from lrm_cvx.monitor import MonitorState
    from lrm_cvx.planning import plan_greedy
    from lrm_cvx.replanning import route_feasible

    sst = load_sample("sst")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                     progress=False).fit(sst.isel(time=slice(None, -3)))
    model.save(tmp_path / "m.nc")
    state = tmp_path / "s.nc"
    assert _run("monitor", "init", tmp_path / "m.nc", "--state", state) == 0
    out = tmp_path / "fleet.csv"
    assert _run("monitor", "plan", state, "--start", "10,200", "--start", "-20,240",
                "--budget", 6000, "--metric", "km", "--traversable", "valid", "--closed",
                "-o", out) == 0
    assert "2 robots" in capsys.readouterr().out
    # the same plan as the Python loop with the same path model
    s = MonitorState.load(state)
    expected = plan_greedy(model.Y_, model.region_, [(10.0, 200.0), (-20.0, 240.0)], 6000.0,
                           criterion="gp-variance", initial="start", progress=False, refine="lines",
                           path=PathOptions(metric="km", traversable="valid", closed=True),
                           **s.planner_kwargs())
    table = pd.read_csv(out)
    np.testing.assert_array_equal(table["cell"], expected.route)
    assert route_feasible(expected, model.region_) == []
    # hours, stop costs, a fixed end, sensing along: accepted, and a bad flag is one line
    assert _run("monitor", "plan", state, "--start", "10,200", "--budget", 100, "--metric",
                "km", "--speed", 20, "--stop-cost", 1, "--end", "20,220", "--sense-along",
                "-o", tmp_path / "h.geojson") == 0
    assert _run("monitor", "plan", state, "--start", "10,200", "--start", "-20,240",
                "--budget", 1, "--budget", 2, "--budget", 3, "-o", tmp_path / "x.csv") == 2
    assert "once per --start" in capsys.readouterr().err


# ------------------------------------------------- the record's calendar in the field loop
@pytest.fixture(scope="module")
def monthly(tmp_path_factory):
    """A model of a monthly record dated on the 15th (Mar - Dec 2009: no February of its own)
    and three samples."""
    folder = tmp_path_factory.mktemp("monthly")
    times = pd.date_range("2009-03-01", periods=10, freq="MS") + pd.Timedelta(days=14)
    da = xr.DataArray(np.random.default_rng(5).normal(size=(10, 4, 5)).astype(np.float32),
                      dims=("time", "lat", "lon"),
                      coords={"time": times, "lat": np.arange(4.0), "lon": np.arange(5.0)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        GLRM(2, temporal="ar1", progress=False, random_state=0).fit(da).save(folder / "m.nc")
    pd.DataFrame({"cell": [0, 3, 7], "value": [0.1, -0.2, 0.3]}).to_csv(folder / "obs.csv",
                                                                        index=False)
    return folder


def _state_after_january(monthly, tmp_path):
    """A state observed at 16 Jan 2010 12:00, a time off the record's stamps (the 15th)."""
    state = tmp_path / "s.nc"
    assert _run("monitor", "init", monthly / "m.nc", "--state", state) == 0
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time",
                "2010-01-16T12:00") == 0
    return state


def _plan(state, out, *argv):
    return _run("monitor", "plan", state, "--start", "1,1", "--budget", 3, "--criterion",
                "fisher", *argv, "-o", out)


def test_the_default_plan_time_is_the_records_next_stamp(monthly, tmp_path, capsys):
    state = _state_after_january(monthly, tmp_path)
    capsys.readouterr()
    assert _plan(state, tmp_path / "p.csv") == 0
    assert "plan for 2010-02-15T00:00:00:" in capsys.readouterr().out
    assert MonitorState.load(state).current_plan_time == np.datetime64("2010-02-15", "ns")
    assert _run("monitor", "map", state, "--forecast", "-o", tmp_path / "f.nc") == 0
    with xr.open_dataset(tmp_path / "f.nc") as m:
        assert m["time"].values == np.datetime64("2010-02-15", "ns")
    # replan --time: any time in the plan's month is the plan's day; another month is not
    assert _run("monitor", "replan", state, "--done", 1, "--time", "2010-02-15") == 0
    assert _run("monitor", "replan", state, "--done", 1, "--time", "2010-02-27T18:00") == 0
    before = state.read_bytes()
    capsys.readouterr()
    assert _run("monitor", "replan", state, "--done", 1, "--time", "2010-03-15") == 2
    assert "not the time of the stored plan" in capsys.readouterr().err
    assert state.read_bytes() == before


def test_an_observation_in_the_plans_month_is_the_plans_step(monthly, tmp_path, capsys):
    state = _state_after_january(monthly, tmp_path)
    assert _plan(state, tmp_path / "p.csv", "--time", "2010-02-16T12:00") == 0
    start = MonitorState.load(state)
    capsys.readouterr()
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time",
                "2010-02-15") == 0
    out = capsys.readouterr().out
    assert ("note: observations at 2010-02-15 belong to the snapshot at 2010-02-16T12:00:00 "
            "(monthly record)") in out
    s = MonitorState.load(state)
    expected = start.assimilate(([0, 3, 7], [0.1, -0.2, 0.3]), "2010-02-16T12:00")
    assert s.time == np.datetime64("2010-02-16T12:00", "ns")
    np.testing.assert_allclose(s.posterior.mean, expected.posterior.mean, rtol=1e-12)
    # the same month again is the same, already observed snapshot: refused, or with --force
    # added to it (no step, said in one line)
    before = state.read_bytes()
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time",
                "2010-02-20") == 2
    refused = capsys.readouterr()
    assert "equal to the state's time" in refused.err and refused.out == ""
    assert state.read_bytes() == before
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time", "2010-02-20",
                "--force") == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "--force" in line]
    assert notes == ["note: --force: the observations are added to the snapshot at "
                     "2010-02-16T12:00:00, already observed (no step)"]
    added = MonitorState.load(state)
    assert added.time == s.time and added.n_assimilated == s.n_assimilated + 3
    np.testing.assert_allclose(
        added.posterior.mean,
        expected.assimilate(([0, 3, 7], [0.1, -0.2, 0.3]), s.time, force=True).posterior.mean,
        rtol=1e-12)


def test_force_says_when_it_moves_more_than_the_next_stamp(monthly, tmp_path, capsys):
    state = _state_after_january(monthly, tmp_path)
    capsys.readouterr()
    # the ordinary step onto the record's next stamp: no note
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time", "2010-02-15",
                "--force") == 0
    assert "note" not in capsys.readouterr().out
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time", "2010-05-15",
                "--force") == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "--force" in line]
    assert notes == ["note: --force: the filter moves 3 steps, from 2010-02-15T00:00:00 to "
                     "2010-05-15T00:00:00 (the record's next stamp is 2010-03-15T00:00:00)"]
    assert _run("monitor", "assimilate", state, monthly / "obs.csv", "--time", "2010-04-15",
                "--force") == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "--force" in line]
    assert notes == ["note: --force: 2010-04-15T00:00:00 is earlier than the state's time "
                     "2010-05-15T00:00:00: the filter moves one step, to 2010-04-15T00:00:00"]
    assert MonitorState.load(state).time == np.datetime64("2010-04-15", "ns")


# --------------------------------------- a day's missions in one call, honest summaries, errors
@pytest.fixture(scope="module")
def spatial_state(files, tmp_path_factory):
    """A spatial (gp-variance) model of the small field and its monitor state: ``(folder,
    da, state)``; tests copy the state before changing it."""
    folder, da, _ = files
    out = tmp_path_factory.mktemp("spatial")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        GLRM(3, progress=False, max_iter=20, temporal="ar1", offset=True,
             spatial="exponential").fit(da.isel(time=slice(0, 30))).save(out / "model.nc")
    assert _run("monitor", "init", out / "model.nc", "--state", out / "state.nc") == 0
    return out, da, out / "state.nc"


def _starts(da):
    return ["--start", f"{da.lat.values[2]},{da.lon.values[3]}",
            "--start", f"{da.lat.values[0]},{da.lon.values[0]}"]


def _copy_state(spatial_state, tmp_path):
    import shutil

    state = tmp_path / "state.nc"
    shutil.copy(spatial_state[2], state)
    return state


def test_a_fleet_day_in_every_format_in_one_call_and_exported_again(spatial_state, tmp_path,
                                                                   capsys):
    import json

    import gpxpy
    from pymavlink import mavwp

    _, da, _ = spatial_state
    state = _copy_state(spatial_state, tmp_path)
    day = tmp_path / "day1"
    assert _run("monitor", "plan", state, *_starts(da), "--budget", 4, "-o", f"{day}/",
                "-o", tmp_path / "extra.kml") == 0
    names = sorted(p.name for p in day.iterdir())
    assert names == ["route.csv", "route.geojson", "route.gpx", "route.kml",
                     "route_robot0.plan", "route_robot0.waypoints", "route_robot1.plan",
                     "route_robot1.waypoints"]
    assert (tmp_path / "extra.kml").stat().st_size > 0
    table = pd.read_csv(day / "route.csv")
    gpx = gpxpy.parse((day / "route.gpx").read_text())
    assert len(gpx.routes) == 2
    for r in (0, 1):  # each robot's missions hold its own route, read back by their readers
        rows = table[table["robot"] == r]
        keep = np.r_[True, rows["cell"].to_numpy()[1:] != rows["cell"].to_numpy()[:-1]]
        lat = rows["lat"].to_numpy()[keep]
        items = json.loads((day / f"route_robot{r}.plan").read_text())["mission"]["items"]
        np.testing.assert_allclose([it["params"][4] for it in items], lat)
        loader = mavwp.MAVWPLoader()
        loader.load(str(day / f"route_robot{r}.waypoints"))
        np.testing.assert_allclose([loader.wp(i).x for i in range(1, loader.count())], lat,
                                   atol=1e-6)
        np.testing.assert_allclose([p.latitude for p in gpx.routes[r].points], lat)
    # the stored plan in other formats, without planning again: same route, state unchanged
    before = state.read_bytes()
    capsys.readouterr()
    assert _run("monitor", "export", state, "-o", tmp_path / "again.csv",
                "-o", tmp_path / "one.plan", "--robot", 1) == 0
    assert state.read_bytes() == before
    assert (tmp_path / "again.csv").read_bytes() == (day / "route.csv").read_bytes()
    assert (json.loads((tmp_path / "one.plan").read_text())
            == json.loads((day / "route_robot1.plan").read_text()))
    assert "(greedy)" in capsys.readouterr().out  # its method, not renamed by a replan


def test_a_robot_the_fleet_does_not_have_is_refused_before_planning(spatial_state, tmp_path,
                                                                    capsys, monkeypatch,
                                                                    inputs_unchanged):
    import lrm_cvx.planning

    _, da, _ = spatial_state
    state = _copy_state(spatial_state, tmp_path)
    inputs_unchanged.watch(state)

    def never(*args, **kwargs):
        raise AssertionError("planned before checking --robot")

    monkeypatch.setattr(lrm_cvx.planning, "plan_greedy", never)
    capsys.readouterr()
    assert _run("monitor", "plan", state, *_starts(da), "--budget", 4, "--robot", 2,
                "-o", tmp_path / "p.plan") == 2
    err = capsys.readouterr().err
    assert err.startswith("lrm-cvx monitor plan: error: --robot 2 ") and "2 robots" in err
    assert err.count("\n") == 1 and not (tmp_path / "p.plan").exists()


def test_a_budget_that_cannot_leave_the_start_is_one_line_per_robot(spatial_state, tmp_path,
                                                                   capsys, inputs_unchanged):
    _, da, _ = spatial_state
    state = _copy_state(spatial_state, tmp_path)
    inputs_unchanged.watch(state)
    capsys.readouterr()
    # the grid's cells are ~1100 km apart: 10 km reaches none
    assert _run("monitor", "plan", state, "--start", f"{da.lat.values[2]},{da.lon.values[3]}",
                "--budget", 10, "--metric", "km", "-o", tmp_path / "p.plan") == 2
    err = capsys.readouterr().err
    assert err.startswith("lrm-cvx monitor plan: error: the budget 10 km cannot reach any cell")
    assert "km away" in err and err.count("\n") == 1
    assert _run("monitor", "plan", state, *_starts(da), "--budget", 4, "--budget", 0.5,
                "-o", tmp_path / "p.csv") == 2
    err = capsys.readouterr().err
    assert "robot 1's budget 0.5 grid units cannot reach" in err and "1 grid units away" in err
    assert not (tmp_path / "p.csv").exists() and not (tmp_path / "p.plan").exists()


def test_summaries_report_each_plan_under_its_own_criterion(spatial_state, tmp_path, capsys):
    from lrm_cvx.information import CRITERION_REGISTRY, fisher_set_value, gp_variance_value

    _, da, _ = spatial_state
    state = _copy_state(spatial_state, tmp_path)
    start = ["--start", f"{da.lat.values[2]},{da.lon.values[3]}", "--budget", 4]
    capsys.readouterr()
    assert _run("monitor", "plan", state, *start, "-o", tmp_path / "g.csv") == 0
    line = capsys.readouterr().out.splitlines()[0]
    s = MonitorState.load(state)
    cells = s.current_plan.cells
    kw = s.planner_kwargs("gp-variance", s.current_plan_time)["prior"].information()
    args = (s.model.Y, s.model.region_, kw["spatial_cov"], kw["prior_cov"])
    prior = gp_variance_value(*args, [], None, kw["target_weights"])
    left = gp_variance_value(*args, cells, None, kw["target_weights"])
    assert "Fisher information" not in line
    assert f"variance removed {prior - left:.4g} (data units squared; {left:.4g} of " \
           f"{prior:.4g} left)" in line
    assert _run("monitor", "plan", state, *start, "--criterion", "fisher", "--overwrite",
                "-o", tmp_path / "g.csv") == 0
    line = capsys.readouterr().out.splitlines()[0]
    s = MonitorState.load(state)
    kw = s.planner_kwargs("fisher", s.current_plan_time)["prior"].information()
    kw = {k: v for k, v in kw.items() if v is not None}
    value = fisher_set_value(s.model.Y, s.current_plan.cells, 0.0, **kw)  # the posterior's
    assert f"Fisher information {value:.4f} nats" in line and "variance" not in line
    assert _run("monitor", "plan", state, *start, "--criterion", "a-optimal", "--overwrite",
                "-o", tmp_path / "g.csv") == 0
    line = capsys.readouterr().out.splitlines()[0]
    s = MonitorState.load(state)
    kw = s.planner_kwargs("a-optimal", s.current_plan_time)["prior"].information()
    kw = {k: v for k, v in kw.items() if v is not None}
    left = CRITERION_REGISTRY.get("a-optimal").value(s.model.Y, s.current_plan.cells, 0.0, **kw)
    assert f"a-optimal prediction variance left {left:.4g} (data units squared)" in line


def test_assimilate_reports_what_the_file_added_and_names_its_argument(files, tmp_path,
                                                                       capsys):
    folder, da, _ = files
    state = tmp_path / "state.nc"
    assert _run("monitor", "init", folder / "model.nc", "--state", state) == 0
    obs = folder / "obs31.csv"  # 6 rows
    assert _run("monitor", "assimilate", state, obs, "--time", "2013-02-01") == 0
    assert _run("monitor", "assimilate", state, obs, "--time", "2013-02-01", "--force") == 0
    out = capsys.readouterr().out.splitlines()
    added = [line for line in out if line.startswith("assimilated")]
    assert "assimilated 6 observation(s) from" in added[-2] and "(6 in all that day)" in added[-2]
    assert "assimilated 6 observation(s) from" in added[-1] and "(12 in all that day)" in added[-1]
    assert any(line.startswith("note: --force:") for line in out)  # no silent step
    bad = tmp_path / "bad.csv"
    bad.write_text("lat,lon,temp\n1,2,3\n")
    assert _run("monitor", "assimilate", state, bad, "--time", "2013-02-02") == 2
    err = capsys.readouterr().err
    assert err.startswith("lrm-cvx monitor assimilate: error: observations file ")
    assert "--observations" not in err


def test_init_help_says_how_the_dynamics_are_chosen(capsys):
    assert main(["monitor", "init", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(with --temporal)" not in text and "by default, --temporal auto" in text
