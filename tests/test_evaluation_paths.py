"""evaluate() with the path model: options passed to every method, fleets of starts,
recorded options, early errors; the defaults keep the paper's results."""

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import DataError, PlanningError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate, path_label, summary
from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import PathOptions, plan_greedy, random_walk, transect

METHODS = ("greedy", "transect-up", "transect-right", "random")


def planted(seed=0, T=20, ny=8, nx=10, k=3):
    rng = np.random.default_rng(seed)
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, ny * nx))
    data = (X.T @ Y + 0.05 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    data[rng.random(data.shape) < 0.15] = np.nan
    data[:, :3, :3] = np.nan  # "land" never observed
    return xr.DataArray(
        data.astype(np.float32), dims=("time", "lat", "lon"), name="sst",
        coords={"time": np.arange(T), "lat": 10.0 + 2 * np.arange(ny),
                "lon": 150.0 + 2 * np.arange(nx)}, attrs={"units": "K"})


COMMON = dict(rank=3, n_test=3, n_starts=3, seed=4,
              progress=False, methods=METHODS, paper=True,
              planning=PlanningOptions(random_trials=2, certify=False),
              scoring=ScoringOptions(min_observations=2))  # the paper's fold-in


@pytest.fixture(scope="module")
def model():
    da = planted()
    return GLRM(rank=3, random_state=4, progress=False).fit(da.isel(time=slice(None, -3)))


def test_explicit_defaults_are_the_paper(model):
    da = planted()
    paper = evaluate(da, budgets=(3, 6), model=model, **COMMON)
    explicit = evaluate(da, budgets=(3, 6), model=model, n_robots=1,
                        path=PathOptions(metric="grid", speed=None, stop_cost=0.0,
                                         traversable=None, closed=False),
                        **COMMON)
    xr.testing.assert_identical(paper, explicit)
    assert paper.attrs["metric"] == "grid" and paper.attrs["n_robots"] == 1
    assert paper.attrs["traversable"] == "none" and paper.attrs["closed"] == 0
    assert np.isnan(paper.attrs["speed"]) and paper["cost"].attrs["units"] == "grid cells"
    assert "robot" not in paper.dims and (summary(paper)["path"] == "grid").all()


def test_fleet_evaluation_passes_the_path_model_to_every_method(model):
    da = planted()
    allowed = np.ones((8, 10), dtype=bool)
    allowed[5:, 6] = False  # a wall the robots may not cross
    mask = xr.DataArray(allowed, dims=("lat", "lon"),
                        coords={"lat": da["lat"].values, "lon": da["lon"].values})
    opts = dict(path=PathOptions(metric="km", stop_cost=20.0, traversable=mask, closed=True))
    budgets = (800.0, 1600.0)
    ds = evaluate(da, budgets=budgets, model=model, n_robots=2, **opts, **COMMON)
    region = model.region_
    fleets = ds["fleet_start_cell"].values
    assert fleets.shape == (3, 2) and ds.sizes["robot"] == 2
    assert all(len(set(f)) == 2 for f in fleets.tolist())
    assert len({c for f in fleets.tolist() for c in f}) == 6  # distinct across fleets too
    gi = region.grid_index[fleets.ravel()]
    assert allowed[gi[:, 0], gi[:, 1]].all()  # starts on enterable cells
    np.testing.assert_array_equal(ds["start_cell"], fleets[:, 0])
    rc = ds["robot_cost"]
    done = np.isfinite(ds["cost"])
    np.testing.assert_allclose(rc.sum("robot").where(done), ds["cost"].where(done), rtol=1e-12)
    within = (rc <= ds["budget"] * (1 + 1e-9)) | ~np.isfinite(rc)
    assert bool(within.drop_sel({"method": "greedy"}).all())  # the baselines always
    # the greedy too, once the budget pays its forced initial cells (the paper's warning)
    assert bool(within.sel({"method": "greedy", "budget": 1600.0}).all())
    assert ds.attrs["metric"] == "km" and ds.attrs["traversable"] == "mask"
    assert ds.attrs["closed"] == 1 and ds.attrs["n_robots"] == 2
    assert ds.attrs["stop_cost"] == 20.0 and ds["cost"].attrs["units"] == "km"
    assert set(summary(ds)["path"]) == {"km, stop 20 km, traversable mask, closed, 2 robots"}
    # every method ran with these options: recompute one fleet's plans directly
    Y = model.Y_
    s, b = 1, 1
    cells = [int(c) for c in fleets[s]]
    greedy = plan_greedy(Y, region, cells, budgets[b], progress=False, **opts)
    assert ds["information"].sel({"method": "greedy"}).values[b, s, 0] == pytest.approx(
        greedy.information)
    route = ds["greedy_route"].values[b, s]
    np.testing.assert_array_equal(route[route >= 0], greedy.route)
    np.testing.assert_array_equal(ds["greedy_route_robot"].values[b, s][route >= 0],
                                  greedy.route_robot)
    for d in ("up", "right"):
        t = transect(region, cells, budgets[b], d, Y=Y, **opts)
        assert ds["cost"].sel({"method": f"transect-{d}"}).values[b, s, 0] == pytest.approx(t.cost)
        for sub in t.robots:
            assert sub.route[0] == sub.route[-1]  # closed
            rows, cols = region.grid_index[sub.route].T
            assert allowed[rows, cols].all()
    # deterministic given the seed
    again = evaluate(da, budgets=budgets, model=model, n_robots=2, **opts, **COMMON)
    xr.testing.assert_identical(ds, again)


def test_random_baseline_fleets_follow_the_start_generator(model):
    da = planted()
    ds = evaluate(da, budgets=(5.0,), model=model, n_robots=3,
                  path=PathOptions(closed=True, traversable="valid"),
                  **dict(COMMON, methods=("random",)))
    costs = ds["robot_cost"].values[0, 0]  # (start, trial, robot)
    assert np.isfinite(costs).all() and (costs <= 5.0 + 1e-9).all()
    assert ds["n_cells"].values.min() >= 3  # each robot observes at least its start
    fleet = [int(c) for c in ds["fleet_start_cell"].values[0]]
    plan = random_walk(model.region_, fleet, 5.0, 0,
                       path=PathOptions(closed=True, traversable="valid"))
    assert plan.n_robots == 3 and all(r.route[-1] == r.route[0] for r in plan.robots)


@pytest.mark.parametrize("kw, error, match", [
    (dict(metric="miles"), PlanningError, "metric"),
    (dict(speed=1.5), PlanningError, "speed"),
    (dict(metric="km", speed=0), PlanningError, "speed"),
    (dict(stop_cost=-1.0), PlanningError, "stop_cost"),
    (dict(closed="yes"), PlanningError, "closed"),
    (dict(traversable="land"), PlanningError, "traversable"),
    (dict(traversable=[[True]]), PlanningError, "traversable"),
    (dict(n_robots=0), PlanningError, "n_robots"),
    (dict(n_robots=1.5), PlanningError, "n_robots"),
    (dict(end=3), PlanningError, "temporal"),
    (dict(sense_along=True), PlanningError, "temporal"),
])
def test_bad_options_fail_before_the_fit(kw, error, match, monkeypatch):
    def no_fit(*args, **kwargs):  # the errors come before any work
        raise AssertionError("fitted before checking the path options")

    monkeypatch.setattr(GLRM, "fit", no_fit)
    n_robots = kw.pop("n_robots", 1)
    with pytest.raises(error, match=match):
        evaluate(planted(), budgets=(3,), n_robots=n_robots, path=PathOptions(**kw), **COMMON)


def test_bad_mask_and_too_many_robots(model):
    da = planted()
    wrong = xr.DataArray(np.ones((7, 10), dtype=bool), dims=("lat", "lon"))
    with pytest.raises(PlanningError, match="traversable mask has shape"):
        evaluate(da, budgets=(3,), model=model, path=PathOptions(traversable=wrong), **COMMON)
    with pytest.raises(DataError, match="n_robots"):
        evaluate(da, budgets=(3,), model=model, n_robots=40, **COMMON)


def test_path_label():
    assert path_label({}) == "grid"
    assert path_label({"metric": "km", "speed": 1.5, "stop_cost": 0.5, "budget_unit": "h",
                       "traversable": "valid", "closed": 1, "n_robots": 3}) == (
        "km, speed 1.5 km/h, stop 0.5 h, traversable valid, closed, 3 robots")
