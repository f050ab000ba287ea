"""`lrm-cvx plan|bound|evaluate` with the path model: the same plans and results as
the Python API, fleets from repeated --start, and one-line errors for bad options."""

import json

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.cli import main
from lrm_cvx.datasets import load_sample
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import PathOptions, plan_greedy

STARTS = [["--start", "10", "-150"], ["--start", "-5,-120"]]
PY_STARTS = [(10, 210), (-5, 240)]


@pytest.fixture(scope="module")
def sst_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("sst_paths") / "model.nc"
    assert main(["-q", "fit", "sample:sst", "--rank", "3", "--paper", "-o", str(path)]) == 0
    return path


def _plan(model_file, argv, tmp_path, name="route.csv"):
    out = tmp_path / name
    assert main(["-q", "plan", str(model_file), *argv, "--paper", "-o", str(out)]) == 0
    return out


@pytest.mark.parametrize("flags, python", [
    (["--metric", "km", "--traversable", "valid", "--closed"],
     dict(metric="km", traversable="valid", closed=True)),
    (["--metric", "km", "--speed", "20", "--stop-cost", "5"],
     dict(metric="km", speed=20.0, stop_cost=5.0)),
    (["--metric", "km", "--traversable", "valid", "--sense-along", "--end", "0", "-170"],
     dict(metric="km", traversable="valid", sense_along=True, end=(0, 190))),
])
def test_fleet_plan_matches_plan_greedy(sst_model, tmp_path, flags, python):
    budget = "400" if "--speed" in flags else "6000"
    route = _plan(sst_model, [*STARTS[0], *STARTS[1], "--budget", budget, *flags], tmp_path)
    model = GLRM.load(sst_model)
    plan = plan_greedy(model.Y_, model.region_, PY_STARTS, float(budget), progress=False,
                       path=PathOptions(**python))
    got = pd.read_csv(route)
    ref = plan.to_dataframe()
    for col in ("robot", "order", "cell", "waypoint"):
        np.testing.assert_array_equal(got[col], ref[col])
    np.testing.assert_allclose(got["cumulative_cost"], ref["cumulative_cost"], rtol=1e-12)
    assert set(got["robot"]) == {0, 1}


def test_one_budget_per_start_and_the_printed_line(sst_model, tmp_path, capsys):
    route = _plan(sst_model, [*STARTS[0], "--budget", "3000", *STARTS[1], "--budget", "7000",
                              "--metric", "km", "--traversable", "valid", "--closed"], tmp_path)
    line = capsys.readouterr().out.splitlines()[0]
    assert "2 robots" in line and "/3000" in line and "/7000" in line and "km" in line
    assert "closed" in line and "traversable valid" in line
    df = pd.read_csv(route)
    model = GLRM.load(sst_model)
    plan = plan_greedy(model.Y_, model.region_, PY_STARTS, [3000.0, 7000.0], progress=False,
                       path=PathOptions(metric="km", traversable="valid", closed=True))
    np.testing.assert_array_equal(df["cell"], plan.route)
    for r, budget in enumerate((3000, 7000)):
        rows = df[df["robot"] == r]
        assert rows["cell"].iloc[0] == rows["cell"].iloc[-1]  # closed tours return
        assert rows["cumulative_cost"].iloc[-1] <= budget + 1e-6
        lat, lon = np.radians(rows["lat"].to_numpy()), np.radians(rows["lon"].to_numpy())
        h = (np.sin(np.diff(lat) / 2) ** 2
             + np.cos(lat[:-1]) * np.cos(lat[1:]) * np.sin(np.diff(lon) / 2) ** 2)
        km = 2 * 6371.0088 * np.arcsin(np.sqrt(h))
        assert rows["cumulative_cost"].iloc[-1] == pytest.approx(km.sum(), rel=1e-6)
        # every row in the ocean: a valid cell of the model
        assert (rows["cell"] >= 0).all() and (rows["cell"] < model.region_.n_cells).all()


def test_geojson_has_a_line_per_robot(sst_model, tmp_path):
    out = _plan(sst_model, [*STARTS[0], *STARTS[1], "--budget", "6000", "--metric", "km",
                            "--closed"], tmp_path, "route.geojson")
    doc = json.loads(out.read_text())
    lines = [f for f in doc["features"] if f["geometry"]["type"] == "LineString"]
    assert len(lines) == 2


def test_traversable_mask_file(sst_model, tmp_path):
    model = GLRM.load(sst_model)
    region = model.region_
    allowed = np.asarray(region.mask).copy()
    allowed[:, 20:22] = False  # a forbidden band of longitudes east of the start
    mask = xr.DataArray(allowed, dims=("lat", "lon"),
                        coords={"lat": region.lat.values, "lon": region.lon.values},
                        name="enterable")
    path = tmp_path / "mask.nc"
    mask.to_netcdf(path)
    flags = ["--budget", "5000", "--metric", "km", "--traversable", str(path), "--closed"]
    route = _plan(sst_model, [*STARTS[0], *flags], tmp_path)
    plan = plan_greedy(model.Y_, region, PY_STARTS[0], 5000.0, progress=False,
                       path=PathOptions(metric="km", traversable=mask, closed=True))
    df = pd.read_csv(route)
    np.testing.assert_array_equal(df["cell"], plan.route)
    assert allowed[df["row"], df["col"]].all()
    # a 0/1 mask works too; a non-binary one is refused with one line
    mask.astype(np.int8).to_netcdf(tmp_path / "mask01.nc")
    _plan(sst_model, [*STARTS[0], *flags[:-2], str(tmp_path / "mask01.nc"), "--closed"],
          tmp_path, "r01.csv")
    (mask.astype(float) * 0.5).to_netcdf(tmp_path / "half.nc")
    assert main(["-q", "plan", str(sst_model), *STARTS[0], *flags[:-2],
                 str(tmp_path / "half.nc")]) == 2


@pytest.mark.parametrize("argv, message", [
    ([*STARTS[0], *STARTS[1], "--budget", "1", "--budget", "2", "--budget", "3"],
     "--budget must be given once"),
    ([*STARTS[0], "--budget", "50", "--speed", "2"], "speed"),
    ([*STARTS[0], "--budget", "50", "--metric", "km", "--speed", "0"], "speed"),
    ([*STARTS[0], "--budget", "50", "--stop-cost", "-1"], "stop_cost"),
    ([*STARTS[0], "--budget", "50", "--closed", "--end", "0", "-170"], "end"),
    ([*STARTS[0], "--budget", "50", "--metric", "miles"], "metric"),
    ([*STARTS[0], "--budget", "50", "--traversable", "nowhere.nc"], "does not exist"),
])
def test_bad_path_options_exit_2_with_one_line(sst_model, argv, message, capsys):
    assert main(["-q", "plan", str(sst_model), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lrm-cvx plan: error:") and message in err[0]


def test_bound_takes_the_path_options(sst_model, capsys):
    assert main(["-q", "bound", str(sst_model), *STARTS[0], "--budget", "6000", "--metric",
                 "km", "--traversable", "valid", "--closed", "--certify", "fast",
                 "--paper"]) == 0
    out = capsys.readouterr().out
    assert "upper bound" in out and "km" in out


def test_bound_certifies_a_footprint_plan(sst_model, capsys):
    """``lrm-cvx bound --sensor disc:...``: the footprint plan's certificate (its Fisher
    information with footprint rows, below the bound); a towed sensor's too (its leg rows,
    docs/certificate.md §12), with a gap of at least 0."""
    import re

    assert main(["-q", "bound", str(sst_model), *STARTS[0], "--budget", "8", "--paper",
                 "--sensor", "disc:300km", "--certify", "fast"]) == 0
    out = capsys.readouterr().out
    assert "upper bound" in out and "gap" in out
    assert main(["-q", "bound", str(sst_model), *STARTS[0], "--budget", "8", "--paper",
                 "--sensor", "leg-average", "--ridge", "1e-3"]) == 0
    out = capsys.readouterr().out
    assert "sensor leg-average" in out
    assert float(re.search(r"optimality gap: ([-0-9.]+) nats", out).group(1)) >= 0


TINY = ["--rank", "3", "--n-test", "2", "--starts", "2", "--random-trials", "2",
        "--budgets", "3000,6000", "--min-observations", "1", "--certify", "off"]


def test_evaluate_path_options_match_python(tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["-q", "evaluate", "sample:sst", *TINY, "--paper", "--metric", "km",
                 "--traversable", "valid", "--closed", "--robots", "2", "--stop-cost", "10",
                 "--methods", "greedy,transect-up,random", "--out", str(out)]) == 0
    got = xr.load_dataset(out / "results.nc")
    ref = evaluate(load_sample("sst"), rank=3, n_test=2, n_starts=2,
                   budgets=(3000, 6000), progress=False,
                   methods=("greedy", "transect-up", "random"), n_robots=2,
                   paper=True,
                   path=PathOptions(metric="km", traversable="valid", closed=True, stop_cost=10.0),
                   planning=PlanningOptions(random_trials=2, certify=False),
                   scoring=ScoringOptions(min_observations=1, model_params={"noise": "global"}))
    np.testing.assert_allclose(got["mse"], ref["mse"], rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(got["robot_cost"], ref["robot_cost"], rtol=1e-12)
    np.testing.assert_array_equal(got["fleet_start_cell"], ref["fleet_start_cell"])
    np.testing.assert_array_equal(got["greedy_route"], ref["greedy_route"])
    assert got.attrs["n_robots"] == 2 and got.attrs["metric"] == "km"
    summary = pd.read_csv(out / "summary.csv")
    assert (summary["path"] == "km, stop 10 km, traversable valid, closed, 2 robots").all()
