"""Plan exports, equality and the certificate hook."""

import json

import matplotlib
import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.planning import Plan, plan_greedy, random_walk, transect

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    mask = rng.random((12, 14)) < 0.9
    mask[6, 7] = True
    lat = np.linspace(10, 0, 12)
    lon = np.linspace(30, 43, 14)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
    Y = rng.standard_normal((3, region.n_cells))
    start = int(region.cell_grid[6, 7])
    return Y, region, start, plan_greedy(Y, region, start, 15, progress=False)


def test_dataframe(setup):
    _, region, start, plan = setup
    df = plan.to_dataframe()
    assert list(df.columns) == ["order", "cell", "lat", "lon", "row", "col", "cumulative_cost"]
    assert len(df) == plan.route.size and df["cell"].tolist() == plan.route.tolist()
    assert df["cumulative_cost"].iloc[0] == 0 and np.all(np.diff(df["cumulative_cost"]) > 0)
    assert df["cumulative_cost"].iloc[-1] == pytest.approx(plan.cost)
    np.testing.assert_array_equal(df[["row", "col"]].values, region.grid_index[plan.route])
    np.testing.assert_array_equal(df["lat"], region.cell_lat[plan.route])


def test_csv_roundtrip(setup, tmp_path):
    plan = setup[3]
    path = plan.to_csv(tmp_path / "sub" / "plan.csv")
    back = pd.read_csv(path)
    pd.testing.assert_frame_equal(back, plan.to_dataframe(), check_dtype=False)
    assert sorted(p.name for p in path.parent.iterdir()) == ["plan.csv"]  # no temp file left


def test_geojson(setup, tmp_path):
    plan = setup[3]
    doc = plan.to_geojson(tmp_path / "plan.geojson")
    assert json.loads((tmp_path / "plan.geojson").read_text()) == doc
    assert doc["type"] == "FeatureCollection"
    line = doc["features"][0]["geometry"]
    assert line["type"] == "LineString"
    # GeoJSON order: lon first
    assert line["coordinates"] == [[lo, la] for lo, la in zip(plan.lon, plan.lat, strict=True)]
    points = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert sorted(f["properties"]["cell"] for f in points) == sorted(plan.cells.tolist())
    assert [f["properties"]["start"] for f in points].count(True) == 1
    assert doc["properties"]["n_cells"] == len(plan)
    # a walk that revisits cells: one point per distinct cell
    walk = random_walk(setup[1], setup[2], 12, 3)
    pts = [f for f in walk.to_geojson()["features"] if f["geometry"]["type"] == "Point"]
    assert len(pts) == len(walk)
    assert np.isnan(walk.information) and walk.to_geojson()["properties"]["information"] is None


def test_plot(setup):
    import matplotlib.pyplot as plt

    Y, region, _, plan = setup
    ax = plan.plot(background=region.unstack(Y[0]))
    assert ax.lines and len(ax.collections) >= 3  # background mesh, cells, start
    ax2 = plan.plot(background=Y[1])  # a cell vector on the plan's region
    assert ax2 is not ax
    plt.close("all")


def test_len_repr_eq(setup):
    Y, region, start, plan = setup
    assert len(plan) == plan.cells.size
    text = repr(plan)
    assert "greedy" in text and f"{len(plan)} cells" in text and "budget=15" in text
    assert plan == plan_greedy(Y, region, start, 15, progress=False)
    assert plan != plan_greedy(Y, region, start, 12, progress=False)
    assert transect(region, start, 5, "up") == transect(region, start, 5, "up")
    assert plan != "a plan"


def test_certify_calls_plan_bound(setup, monkeypatch):
    from lrm_cvx.planning import bound

    Y, region, start, plan = setup
    seen = {}

    def fake(Y_, region_, start_, budget_, *, ridge=0.0, plan=None, **kw):
        seen.update(Y=Y_, region=region_, start=start_, budget=budget_, ridge=ridge, plan=plan,
                    kw=kw)
        return "certificate"

    monkeypatch.setattr(bound, "plan_bound", fake)
    assert plan.certify(tol=1e-2) == "certificate"
    np.testing.assert_array_equal(seen["Y"], Y)
    assert seen["region"] is region and seen["start"] == start and seen["budget"] == 15
    assert seen["plan"] is plan and seen["kw"] == {"tol": 1e-2} and seen["ridge"] == 0.0


def test_certify_without_model_fails(setup):
    from lrm_cvx.errors import PlanningError

    walk = transect(setup[1], setup[2], 4, "left")
    with pytest.raises(PlanningError, match="no model"):
        walk.certify()
    assert isinstance(walk, Plan)
