"""Plan exports, equality and the certificate hook."""

import json
import math

import matplotlib
import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.errors import PlanningError
from lrm_cvx.planning import PathOptions, Plan, PriorTerms, plan_greedy, random_walk, transect

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
    assert list(df.columns) == ["robot", "order", "cell", "lat", "lon", "row", "col", "waypoint",
                                "cumulative_cost"]
    assert (df["robot"] == 0).all() and df["waypoint"].all()
    assert df["order"].tolist() == list(range(len(df)))
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
    from lrm_cvx.planning import certificate as bound

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


# ---------------------------------------------------------------------- bad input
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@st.composite
def small_instances(draw):
    ny, nx = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    seed = draw(st.integers(0, 10_000))
    rng = np.random.default_rng(seed)
    mask = rng.random((ny, nx)) < draw(st.sampled_from([0.6, 0.85, 1.0]))
    mask.flat[draw(st.integers(0, ny * nx - 1))] = True
    lat = np.linspace(10, 0, ny) if draw(st.booleans()) else np.linspace(0, 10, ny)
    lon = np.linspace(30, 30 + nx - 1, nx)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
    start = draw(st.integers(0, region.n_cells - 1))
    budget = draw(st.one_of(st.integers(0, 14).map(float), st.floats(0, 14)))
    return region, start, budget, seed


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(inst=small_instances(), direction=st.sampled_from(["up", "down", "left", "right"]))
def test_last_cumulative_cost_is_the_plan_cost(inst, direction):
    """Every planner and baseline: the route's cumulative cost ends exactly at plan.cost, is
    non-decreasing from 0, and never exceeds the budget."""
    region, start, budget, seed = inst
    plans = [transect(region, start, budget, direction), random_walk(region, start, budget, seed)]
    Y = np.random.default_rng(seed).standard_normal((1, region.n_cells))
    gi = region.grid_index.astype(float)
    nearest = np.delete(np.sqrt(((gi - gi[start]) ** 2).sum(axis=1)), start)
    for cost in ("nearest-neighbor", "insertion"):
        try:
            plans.append(plan_greedy(Y, region, start, budget, cost=cost, ridge=1e-6,
                                     progress=False))
        except PlanningError as exc:  # only a budget below the nearest cell's distance
            assert "cannot reach any cell beyond its start" in str(exc)
            assert nearest.size and budget < nearest.min()
    for plan in plans:
        cum = plan.to_dataframe()["cumulative_cost"].to_numpy()
        assert cum[0] == 0.0 and cum[-1] == plan.cost, plan
        assert np.all(np.diff(cum) >= 0) and plan.cost <= budget + 1e-9
        if plan.method == "greedy" or plan.method == "random":
            # a straight-line path through the route: the cumulative cost is its length
            steps = np.sqrt((np.diff(plan.grid_index, axis=0) ** 2).sum(axis=1))
            np.testing.assert_allclose(np.diff(cum), steps, rtol=1e-12, atol=1e-12)
        else:  # a transect's steps are grid moves (>= the straight distance between stops)
            straight = np.sqrt((np.diff(plan.grid_index, axis=0) ** 2).sum(axis=1))
            assert np.all(np.diff(cum) >= straight - 1e-12)


def test_transect_with_a_turn_over_masked_cells_counts_the_walked_steps():
    mask = np.ones((3, 3), dtype=bool)
    mask[0, 1] = mask[0, 2] = False  # the turn at the top edge crosses two masked positions
    lat = np.linspace(10, 0, 3)  # row 0 is north
    lon = np.linspace(30, 32, 3)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
    start = int(region.cell_grid[2, 1])
    plan = transect(region, start, 4, "up")  # (2,1) (1,1) (0,1)x (0,2)x (1,2)
    assert plan.cost == 4
    assert plan.to_dataframe()["cumulative_cost"].tolist() == [0.0, 1.0, 4.0]
    # the old export summed straight distances between stops: 1 + sqrt(2) != 4


def test_plan_built_without_route_cost_and_inconsistent_cost(setup):
    Y, region, start, plan = setup
    kw = dict(region=region, cells=plan.cells, route=plan.route, information=0.0,
              criterion=None, budget=20.0, start=start, ridge=0.0, method="greedy")
    built = Plan.build(cost=None, **kw)
    assert built.cost == plan.cost
    with pytest.raises(ValueError, match="differs"):
        Plan.build(cost=plan.cost + 1.0, **kw)


# ---------------------------------------------------------------------- figures
@pytest.fixture(scope="module")
def tiny():
    rng = np.random.default_rng(4)
    lat, lon = np.linspace(5, 0, 6), np.linspace(0, 5, 6)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((6, 6), dtype=bool))
    Y = rng.standard_normal((2, region.n_cells))
    return Y, region, int(region.cell_grid[3, 3])


def test_certify_fisher_plan_reports_its_gap(tiny):
    Y, region, start = tiny
    plan = plan_greedy(Y, region, start, 4, ridge=1e-3, progress=False)
    cert = plan.certify(tighten=False)
    assert cert.criterion == "fisher" and cert.plan_criterion == "fisher" and cert.comparable
    assert cert.information == pytest.approx(plan.information)
    assert np.isfinite(cert.gap) and cert.gap >= -1e-9
    assert cert.gap == pytest.approx(cert.bound - plan.information)
    assert "certified gap" in repr(cert)


@pytest.mark.parametrize("criterion", ["a-optimal", "aopt"])
def test_certify_a_optimal_plan_names_the_criterion_and_gives_no_gap(tiny, criterion):
    Y, region, start = tiny
    plan = plan_greedy(Y, region, start, 4, criterion=criterion, ridge=1e-3, progress=False)
    assert plan.criterion == "a-optimal"  # the alias is stored under its canonical name
    cert = plan.certify(tighten=False, criterion="fisher")
    assert cert.criterion == "fisher" and cert.plan_criterion == "a-optimal"
    assert not cert.comparable
    assert math.isnan(cert.gap) and math.isnan(cert.volume_ratio) and cert.relative_gap is None
    # the plan's Fisher information is still reported, and the bound still bounds it
    assert cert.information == pytest.approx(plan.information)
    assert cert.information <= cert.bound + 1e-9
    text = repr(cert)
    assert "no gap" in text and "a-optimal" in text and "certified gap" not in text
    assert "different criteria" in cert._repr_html_()


def test_certify_posterior_fisher_plan_gives_no_gap(tiny):
    Y, region, start = tiny
    plan = plan_greedy(Y, region, start, 4, initial="start", progress=False,
                       prior=PriorTerms(prior_precision=np.eye(2)))
    assert plan.posterior
    cert = plan.certify(tighten=False)
    assert cert.plan_criterion == "fisher (posterior)" and math.isnan(cert.gap)


def test_certify_baseline_is_judged_by_fisher(tiny):
    Y, region, start = tiny
    walk = transect(region, start, 4, "up", Y=Y, ridge=1e-3)
    cert = walk.certify(tighten=False)
    assert cert.plan_criterion is None and cert.comparable and np.isfinite(cert.gap)


# ---------------------------------------------------------------------- path models
def test_fleet_csv_roundtrip_and_closed_tours(setup, tmp_path):
    Y, region, start, _ = setup
    other = int(region.cell_grid[2, 3]) if region.cell_grid[2, 3] >= 0 else 0
    plan = plan_greedy(Y, region, [start, other], 600.0, ridge=1e-6, progress=False,
                       path=PathOptions(metric="km", traversable="valid", closed=True,
                                        stop_cost=10.0, sense_along=True))
    back = pd.read_csv(plan.to_csv(tmp_path / "fleet.csv"))
    pd.testing.assert_frame_equal(back, plan.to_dataframe(), check_dtype=False)
    for r, rows in back.groupby("robot"):
        assert rows["cell"].iloc[0] == rows["cell"].iloc[-1] == plan.path["starts"][r]
        assert rows["cumulative_cost"].iloc[0] == 10.0  # the start's stop cost
        assert rows["cumulative_cost"].iloc[-1] == pytest.approx(plan.robot_costs[r], rel=1e-12)
        assert rows["cumulative_cost"].iloc[-1] <= 600.0 * (1 + 1e-9)
    assert plan == plan_greedy(Y, region, [start, other], 600.0, ridge=1e-6, progress=False,
                               path=PathOptions(metric="km", traversable="valid", closed=True,
                                                stop_cost=10.0, sense_along=True))
    assert plan != plan_greedy(Y, region, [start, other], 600.0, ridge=1e-6, progress=False,
                               path=PathOptions(metric="km", traversable="valid", closed=True,
                                                stop_cost=10.0))
    doc = plan.to_geojson()
    assert doc["properties"]["path"]["closed"] and doc["properties"]["n_robots"] == 2
    assert "2 robots" in repr(plan)


def test_plan_built_by_hand_gets_the_papers_path(setup):
    Y, region, start, plan = setup
    built = Plan.build(region=region, cells=plan.cells, route=plan.route, cost=None,
                       information=0.0, criterion=None, budget=20.0, start=start, ridge=0.0,
                       method="greedy")
    assert built.path["kind"] == "path" and built.path["starts"] == [start]
    assert built.n_robots == 1 and built.robots == [built]
    assert built.stops.tolist() == built.cells.tolist() and built.waypoint.all()
