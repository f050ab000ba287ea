"""The lrm-cvx command line: each command end to end on small files, and its error contract."""

import argparse
import json

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import cli
from lrm_cvx.cli import main
from lrm_cvx.datasets import load_sample
from lrm_cvx.evaluation import METHODS, PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.losses import LOSSES
from lrm_cvx.glrm.predictive import PRIORS
from lrm_cvx.information import CRITERIA
from lrm_cvx.planning import plan_greedy
from lrm_cvx.planning.routecost import COSTS
from lrm_cvx.spatial import MODELS


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    rng = np.random.default_rng(0)
    T, ny, nx, k = 20, 8, 10, 3
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, ny * nx))
    v = (X.T @ Y + 0.05 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    v[rng.random(v.shape) < 0.2] = np.nan
    da = xr.DataArray(v.astype(np.float32), dims=("time", "lat", "lon"), name="temp",
                      coords={"time": np.arange(T), "lat": 40 + np.arange(ny) * 0.5,
                              "lon": -70 + np.arange(nx) * 0.5}, attrs={"units": "K"})
    path = tmp_path_factory.mktemp("data") / "field.nc"
    da.to_netcdf(path)
    return path


@pytest.fixture(scope="module")
def model_file(data_file):
    out = data_file.parent / "model.nc"
    assert main(["-q", "fit", str(data_file), "--rank", "3", "--paper", "-o", str(out)]) == 0
    return out


def test_fit_writes_a_loadable_model(model_file):
    model = GLRM.load(model_file)
    assert model.rank == 3 and model.region_.n_cells == 80


def test_plan_csv_and_geojson(model_file, tmp_path, capsys):
    csv = tmp_path / "route.csv"
    assert main(["-q", "plan", str(model_file), "--start", "41,-68", "--budget", "8",
                 "--paper", "-o", str(csv)]) == 0
    route = pd.read_csv(csv)
    assert {"lat", "lon", "cell"} <= set(route.columns)
    assert route.iloc[0][["lat", "lon"]].tolist() == [41.0, -68.0]
    gj = tmp_path / "route.geojson"
    assert main(["-q", "plan", str(model_file), "--start", "41,-68", "--budget", "8",
                 "--cost", "insertion", "--paper", "-o", str(gj)]) == 0
    doc = json.loads(gj.read_text())
    assert doc["type"] == "FeatureCollection"


def test_bound_reports_gap(model_file, capsys):
    assert main(["-q", "bound", str(model_file), "--start", "41,-68", "--budget", "8",
                 "--paper"]) == 0
    out = capsys.readouterr().out
    assert "upper bound" in out and "gap" in out


def test_predict_from_csv(model_file, data_file, tmp_path):
    da = xr.load_dataarray(data_file)
    snap = da.isel(time=-1)
    obs = snap.to_dataframe().dropna().reset_index()[["lat", "lon", "temp"]].head(12)
    obs = obs.rename(columns={"temp": "value"})
    obs_path = tmp_path / "obs.csv"
    obs.to_csv(obs_path, index=False)
    out = tmp_path / "map.nc"
    assert main(["-q", "predict", str(model_file), "--observations", str(obs_path),
                 "--paper", "-o", str(out)]) == 0
    pred = xr.load_dataset(out)
    assert {"prediction", "std"} <= set(pred.data_vars)
    ref = GLRM.load(model_file)
    cells = ref.region_.cell_of(obs["lat"].to_numpy(), obs["lon"].to_numpy())
    expected = ref.complete((cells, obs["value"].to_numpy()))["prediction"]
    np.testing.assert_allclose(pred["prediction"], expected, rtol=1e-5, atol=1e-6)


def test_fit_spatial_and_predict_with_prior(data_file, tmp_path):
    model_path = tmp_path / "gp.nc"
    assert main(["-q", "fit", str(data_file), "--rank", "3", "--offset", "--spatial",
                 "exponential", "-o", str(model_path)]) == 0
    model = GLRM.load(model_path)
    assert model.offset and model.spatial_cov_ is not None
    obs = pd.DataFrame({"cell": [0, 5, 17, 30, 44, 61, 70], "value": np.linspace(-1, 1, 7)})
    obs.to_csv(tmp_path / "obs.csv", index=False)
    out = tmp_path / "map.nc"
    assert main(["-q", "predict", str(model_path), "--observations", str(tmp_path / "obs.csv"),
                 "--prior", "empirical", "--spatial", "-o", str(out)]) == 0
    expected = model.complete((obs["cell"].to_numpy(), obs["value"].to_numpy()),
                              prior="empirical", spatial=True)
    np.testing.assert_allclose(xr.load_dataset(out)["prediction"], expected["prediction"],
                               rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["fit", "/nonexistent/file.nc", "-o", "m.nc"], "not found"),
        (["plan", "MODEL", "--start", "41", "--budget", "5"], "LAT,LON"),
        (["plan", "MODEL", "--start", "10,10", "--budget", "5"], "outside"),
        (["plan", "MODEL", "--start", "41,-68", "--budget", "-1"], "budget"),
        (["plan", "DATA", "--start", "41,-68", "--budget", "5"], ""),
    ],
)
def test_user_errors_exit_2_with_one_line(argv, message, model_file, data_file, capsys):
    argv = [str(model_file) if a == "MODEL" else str(data_file) if a == "DATA" else a
            for a in argv]
    assert main(["-q", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert message in err


def test_plan_writes_every_robot_in_several_formats(model_file, tmp_path, capsys):
    fleet = ["plan", str(model_file), "--start", "41,-68", "--start", "43,-66", "--budget", "3",
             "--paper"]
    assert main(["-q", *fleet, "-o", str(tmp_path / "r.csv"), "-o", str(tmp_path / "r.plan"),
                 "-o", f"{tmp_path / 'all'}/"]) == 0
    table = pd.read_csv(tmp_path / "r.csv")
    for r in (0, 1):  # one QGroundControl mission per robot, each with its own route
        items = json.loads((tmp_path / f"r_robot{r}.plan").read_text())["mission"]["items"]
        rows = table[table["robot"] == r]
        assert [it["params"][4] for it in items] == rows["lat"].tolist()
        assert (tmp_path / "all" / f"route_robot{r}.waypoints").exists()
    assert not (tmp_path / "r.plan").exists()
    assert {p.suffix for p in (tmp_path / "all").iterdir()} == {
        ".csv", ".geojson", ".plan", ".waypoints", ".gpx", ".kml"}
    # --robot picks one robot under the name given; a robot the fleet lacks: one line, no plan
    assert main(["-q", *fleet, "--robot", "1", "-o", str(tmp_path / "one.plan")]) == 0
    assert (tmp_path / "one.plan").read_text() == (tmp_path / "r_robot1.plan").read_text()
    capsys.readouterr()
    assert main(["-q", *fleet, "--robot", "2", "-o", str(tmp_path / "two.plan")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lrm-cvx plan: error: --robot 2 ") and err.count("\n") == 1
    assert main(["-q", *fleet, "-o", str(tmp_path / "x.csv"), "-o", str(tmp_path / "x.csv")]) == 2
    assert "twice" in capsys.readouterr().err and not (tmp_path / "x.csv").exists()


def test_plan_with_a_budget_that_cannot_leave_the_start_is_an_error(model_file, tmp_path,
                                                                   capsys):
    out = tmp_path / "r.csv"
    # the grid is 0.5 degrees (about 55 km): 10 km reaches no cell
    assert main(["-q", "plan", str(model_file), "--start", "41,-68", "--budget", "10",
                 "--metric", "km", "--initial", "start", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lrm-cvx plan: error: the budget 10 km cannot reach any cell beyond "
                          "its start: the nearest cell is ") and "km away" in err
    assert not out.exists()


def test_refuses_to_overwrite_input(data_file, capsys):
    assert main(["-q", "fit", str(data_file), "--rank", "3", "-o", str(data_file)]) == 2
    assert "overwrite" in capsys.readouterr().err
    assert xr.load_dataarray(data_file).sizes["time"] == 20


def test_demo_runs(tmp_path, capsys, monkeypatch):
    from lrm_cvx import demo

    # the full protocol is timed by benchmarks/bench_first_run.py; a smaller one here
    for key, value in {"budgets": (10.0, 20.0), "n_starts": 2, "random_trials": 2}.items():
        monkeypatch.setitem(demo.DEMO_SETTINGS, key, value)
    out = tmp_path / "demo"
    assert main(["-q", "demo", "--out", str(out)]) == 0
    for name in ("results_recommended.nc", "results_paper.nc", "summary.csv", "summary.txt",
                 "metrics.png", "metrics.pdf", "predictions.png"):
        assert (out / name).exists(), name
    printed = capsys.readouterr().out
    assert str(out.resolve()) in printed
    assert printed.index("recommended:") < printed.index("paper:")  # recommended setting first


# ------------------------------------------------------------------ parity with the Python API
TINY = ["--rank", "3", "--n-test", "2", "--starts", "1", "--random-trials", "1",
        "--budgets", "5,10", "--min-observations", "1"]


@pytest.fixture(scope="module")
def sst_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("sst") / "model.nc"
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--recommended", "-o", str(path)]) == 0
    return path


def _subparser(name):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _choices(name, dest):
    return next(a.choices for a in _subparser(name)._actions if a.dest == dest)


def test_choices_come_from_the_library_constants():
    assert tuple(_choices("plan", "criterion")) == tuple(CRITERIA)
    assert tuple(_choices("evaluate", "criterion")) == tuple(CRITERIA)
    assert tuple(_choices("plan", "cost")) == tuple(COSTS)
    assert tuple(_choices("fit", "spatial")) == (*MODELS, "auto")
    assert tuple(_choices("evaluate", "spatial")) == (*MODELS, "auto")
    assert sorted(_choices("fit", "loss")) == sorted(LOSSES)
    assert [None if c == "none" else c for c in _choices("predict", "prior")] == list(PRIORS)


def test_fit_recommended_is_the_documented_setting(sst_model):
    model = GLRM.load(sst_model)
    assert model.offset is True and model.spatial == cli.RECOMMENDED["spatial"] == "auto"
    assert model.spatial_cov_ is not None and model.offset_ is not None
    table = model.kernel_selection_  # the family validated on the residuals, saved
    choice = table.attrs["choice"]
    assert choice in table["kernel"].values and choice.split()[0] == model.spatial_cov_.model
    assert float(table["anisotropy"].sel(kernel=choice)) == model.spatial_cov_.anisotropy
    assert model.temporal == cli.RECOMMENDED["temporal"] == "auto"
    assert model.selection_.attrs["choice"] in model.selection_["candidate"].values


def test_fit_prints_the_temporal_choice(tmp_path, capsys):
    path = tmp_path / "model.nc"
    assert main(["fit", "sample:sst", "--rank", "3", "--temporal", "auto", "--quiet", "-o",
                 str(path)]) == 0
    out = capsys.readouterr().out
    model = GLRM.load(path)
    assert f"temporal='auto' chose {model.selection_.attrs['choice']!r}" in out
    for candidate in model.selection_["candidate"].values:
        assert f"\n{candidate} " in out  # one row per candidate
    assert f"spatial='auto' chose {model.kernel_selection_.attrs['choice']!r}" in out


@pytest.mark.parametrize("flags, python", [
    (["--recommended"], dict(criterion="gp-variance", initial="start", prior="empirical",
                             spatial=True)),
    (["--criterion", "a-optimal", "--prior", "empirical", "--initial", "start"],
     dict(criterion="a-optimal", initial="start", prior="empirical", spatial=False)),
    # the paper's setting; its options given explicitly to plan_greedy
    (["--paper"], dict(criterion="fisher", initial="nearest")),
    (["--paper", "--criterion", "a-optimal", "--ridge", "0.5", "--cost", "insertion"],
     dict(criterion="a-optimal", initial="nearest", ridge=0.5, cost="insertion")),
    (["--paper", "--criterion", "aopt", "--ridge", "0.5"],
     dict(criterion="a-optimal", initial="nearest", ridge=0.5)),
    # no flag: the recommended setting; an explicit option beats either setting
    ([], dict(criterion="gp-variance", initial="start", prior="empirical", spatial=True)),
    (["--criterion", "fisher"], dict(criterion="fisher", initial="start", prior="empirical")),
    (["--paper", "--criterion", "gp-variance", "--initial", "start"],
     dict(criterion="gp-variance", initial="start", prior="empirical", spatial=True)),
    (["--recommended", "--initial", "nearest", "--prior", "none", "--criterion", "a-optimal",
      "--ridge", "0.5"], dict(criterion="a-optimal", initial="nearest", ridge=0.5)),
])
def test_plan_flags_match_plan_greedy(sst_model, tmp_path, flags, python):
    route = tmp_path / "route.csv"
    assert main(["-q", "plan", str(sst_model), "--start", "10", "-150", "--budget", "12",
                 *flags, "-o", str(route)]) == 0
    model = GLRM.load(sst_model)
    prior, spatial = python.pop("prior", None), python.pop("spatial", False)
    kw = {}
    if prior:
        kw = model.planner_kwargs(prior=prior, spatial=spatial)
    refine = None if "--paper" in flags else "rivals"  # the recommended check against rivals
    plan = plan_greedy(model.Y_, model.region_, (10, 210), 12, progress=False, refine=refine,
                       **python, **kw)
    np.testing.assert_array_equal(pd.read_csv(route)["cell"], plan.route)


def test_plan_overwrite(sst_model, tmp_path, capsys):
    route = tmp_path / "route.csv"
    route.write_text("old")
    argv = ["-q", "plan", str(sst_model), "--start", "10,-150", "--budget", "6", "-o", str(route)]
    assert main(argv) == 2 and "--overwrite" in capsys.readouterr().err
    assert route.read_text() == "old"
    assert main([*argv, "--overwrite"]) == 0
    assert "cell" in pd.read_csv(route)


def test_bound_tight_is_at_most_fast(sst_model, capsys):
    bounds = {}
    for level in ("fast", "tight"):
        assert main(["-q", "bound", str(sst_model), "--start", "10,-150", "--budget", "8",
                     "--paper", "--certify", level]) == 0
        line = next(x for x in capsys.readouterr().out.splitlines() if "upper bound" in x)
        bounds[level] = float(line.split(":")[-1].split()[0])
    assert bounds["tight"] <= bounds["fast"] + 1e-9


def test_predict_recommended_matches_complete(sst_model, tmp_path):
    obs = pd.DataFrame({"cell": [3, 40, 77, 150, 222, 300], "value": np.linspace(-1, 1, 6)})
    obs.to_csv(tmp_path / "obs.csv", index=False)
    out = tmp_path / "map.nc"
    assert main(["-q", "predict", str(sst_model), "--observations", str(tmp_path / "obs.csv"),
                 "--recommended", "-o", str(out)]) == 0
    model = GLRM.load(sst_model)
    ref = model.complete((obs["cell"].to_numpy(), obs["value"].to_numpy()), prior="empirical",
                         spatial=True)
    got = xr.load_dataset(out)
    np.testing.assert_allclose(got["prediction"], ref["prediction"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(got["std"], ref["std"], rtol=1e-6, atol=1e-9)


def test_evaluate_recommended_matches_python(tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["-q", "evaluate", "sample:sst", *TINY, "--recommended", "--certify", "off",
                 "--out", str(out)]) == 0
    got = xr.load_dataset(out / "results.nc")
    assert list(got["method"].values) == [cli.RECOMMENDED["method"], *METHODS]
    ref = evaluate(load_sample("sst"), rank=3, n_test=2, n_starts=1,
                   budgets=(5, 10), progress=False,
                   methods=("greedy:gp-variance", *METHODS),
                   planning=PlanningOptions(random_trials=1, certify=False),
                   scoring=ScoringOptions(min_observations=1, model_params={
                       "offset": True, "spatial": "auto", "noise": "global"},
                                          fold_in={"prior": "empirical", "spatial": True}))
    np.testing.assert_allclose(got["mse"], ref["mse"], rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(got["greedy_route"], ref["greedy_route"])
    summary = pd.read_csv(out / "summary.csv")
    assert summary["method"].iloc[0] == "greedy:gp-variance"
    assert "greedy:gp-variance" in capsys.readouterr().out


def test_evaluate_methods_cost_ridge_certify(tmp_path):
    out = tmp_path / "ev"
    assert main(["-q", "evaluate", "sample:sst", *TINY, "--paper", "--methods",
                 "greedy,greedy:fisher,greedy:aopt,random", "--cost", "insertion",
                 "--ridge", "0.1", "--fold-ridge", "0.01", "--prior", "empirical", "--offset",
                 "--certify", "fast", "--out", str(out)]) == 0
    got = xr.load_dataset(out / "results.nc")
    assert list(got["method"].values) == ["greedy", "greedy:fisher", "greedy:a-optimal",
                                          "random"]
    assert got.attrs["cost_function"] == "insertion" and got.attrs["ridge"] == 0.1
    assert got.attrs["fold_ridge"] == 0.01 and "empirical" in got.attrs["fold_in"]
    assert "'offset': True" in got.attrs["model_params"]
    assert np.isfinite(got["bound"]).all()
    # --no-certify is kept as an alias of --certify off
    assert main(["-q", "evaluate", "sample:sst", *TINY, "--paper", "--methods", "greedy",
                 "--no-certify",
                 "--out", str(out), "--overwrite"]) == 0
    assert np.isnan(xr.load_dataset(out / "results.nc")["bound"]).all()


def test_docs_name_every_command_and_flag():
    from pathlib import Path

    text = (Path(__file__).parents[1] / "docs" / "cli.md").read_text()
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name, p in sub.choices.items():
        if f"lrm-cvx {name}" not in text:
            missing.append(name)
        if name == "monitor":  # its own page (cli_monitor.py); only named here
            continue
        for action in p._actions:
            long = [o for o in action.option_strings if o.startswith("--")]
            if long and long[0] not in ("--help",) and f"`{long[0]}" not in text:
                missing.append(f"{name} {long[0]}")
    assert not missing, f"docs/cli.md does not mention {missing}"


def test_fit_temporal_stores_the_same_dynamics_as_python(data_file, tmp_path):
    """`fit --temporal ar1` saves the dynamics GLRM(temporal="ar1") estimates in Python."""
    out = tmp_path / "dyn.nc"
    assert main(["-q", "fit", str(data_file), "--rank", "3", "--temporal", "ar1", "--paper",
                 "-o", str(out)]) == 0
    saved = GLRM.load(out)
    da = xr.open_dataarray(data_file)
    ref = GLRM(rank=3, temporal="ar1", random_state=0, progress=False).fit(da)
    assert saved.dynamics_ is not None and saved.dynamics_.kind == "ar1"
    np.testing.assert_allclose(saved.dynamics_.A, ref.dynamics_.A, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(saved.dynamics_.Q, ref.dynamics_.Q, rtol=1e-6, atol=1e-12)
    plain = tmp_path / "plain.nc"
    assert main(["-q", "fit", str(data_file), "--rank", "3", "--paper", "-o", str(plain)]) == 0
    assert GLRM.load(plain).dynamics_ is None
