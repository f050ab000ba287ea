"""The lrm-cvx command line: each command end to end on small files, and its error contract."""

import json

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.cli import main
from lrm_cvx.glrm import GLRM


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
    assert main(["-q", "fit", str(data_file), "--rank", "3", "-o", str(out)]) == 0
    return out


def test_fit_writes_a_loadable_model(model_file):
    model = GLRM.load(model_file)
    assert model.rank == 3 and model.region_.n_cells == 80


def test_plan_csv_and_geojson(model_file, tmp_path, capsys):
    csv = tmp_path / "route.csv"
    assert main(["-q", "plan", str(model_file), "--start", "41,-68", "--budget", "8",
                 "-o", str(csv)]) == 0
    route = pd.read_csv(csv)
    assert {"lat", "lon", "cell"} <= set(route.columns)
    assert route.iloc[0][["lat", "lon"]].tolist() == [41.0, -68.0]
    gj = tmp_path / "route.geojson"
    assert main(["-q", "plan", str(model_file), "--start", "41,-68", "--budget", "8",
                 "--cost", "insertion", "-o", str(gj)]) == 0
    doc = json.loads(gj.read_text())
    assert doc["type"] == "FeatureCollection"


def test_bound_reports_gap(model_file, capsys):
    assert main(["-q", "bound", str(model_file), "--start", "41,-68", "--budget", "8"]) == 0
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
                 "-o", str(out)]) == 0
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


def test_refuses_to_overwrite_input(data_file, capsys):
    assert main(["-q", "fit", str(data_file), "--rank", "3", "-o", str(data_file)]) == 2
    assert "overwrite" in capsys.readouterr().err
    assert xr.load_dataarray(data_file).sizes["time"] == 20


def test_demo_runs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["-q", "demo", "--out", str(out)]) == 0
    for name in ("results.nc", "summary.csv", "metrics.png", "metrics.pdf", "predictions.png"):
        assert (out / name).exists(), name
    assert str(out.resolve()) in capsys.readouterr().out
