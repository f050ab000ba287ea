"""Evaluation protocol: exact fold-in errors, protocol invariants, summary, persistence."""

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.evaluation import (
    PlanningOptions,
    ScoringOptions,
    SnapshotStatistics,
    evaluate,
    foldin_mse,
    save_results,
    summary,
)


def brute_force_mse(Y, values, cells, ridge=0.0):
    """Fold in by least squares, predict the whole map, MSE over the observed cells."""
    out = []
    for v in values:
        seen = [c for c in cells if np.isfinite(v[c])]
        A = Y[:, seen]
        if ridge:
            x = np.linalg.solve(A @ A.T + ridge * np.eye(len(Y)), A @ v[seen])
        else:
            x = np.linalg.lstsq(A.T, v[seen], rcond=None)[0]
        pred = Y.T @ x
        ok = np.isfinite(v)
        out.append(np.mean((pred[ok] - v[ok]) ** 2))
    return np.array(out)


@pytest.mark.parametrize("ridge", [0.0, 0.3])
def test_foldin_mse_matches_brute_force(ridge):
    rng = np.random.default_rng(0)
    k, L = 3, 200
    Y = rng.normal(size=(k, L))
    values = (rng.normal(size=(4, k)) @ Y + 0.1 * rng.normal(size=(4, L))).astype(np.float32)
    values[rng.random(values.shape) < 0.3] = np.nan
    stats = SnapshotStatistics.from_values(Y, values)
    cells = rng.choice(L, 25, replace=False)
    mse, n_obs = foldin_mse(Y, stats, cells, ridge=ridge)
    np.testing.assert_array_equal(n_obs, np.isfinite(values[:, cells]).sum(axis=1))
    np.testing.assert_allclose(mse, brute_force_mse(Y, values.astype(float), cells, ridge),
                               rtol=1e-6)


def test_foldin_mse_excludes_too_few_observations():
    rng = np.random.default_rng(1)
    Y = rng.normal(size=(2, 30))
    values = rng.normal(size=(2, 30)).astype(np.float32)
    values[0, :20] = np.nan
    stats = SnapshotStatistics.from_values(Y, values)
    mse, n_obs = foldin_mse(Y, stats, np.arange(25), min_observations=10)
    assert n_obs.tolist() == [5, 25]
    assert np.isnan(mse[0]) and np.isfinite(mse[1])


def planted(seed=0, T=24, ny=9, nx=11, k=3):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(k, T))
    Yg = rng.normal(size=(k, ny * nx))
    data = (X.T @ Yg + 0.05 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    data[rng.random(data.shape) < 0.2] = np.nan
    data[:, 0, :3] = np.nan  # a small "land" area never observed
    return xr.DataArray(
        data.astype(np.float32), dims=("time", "lat", "lon"), name="sst",
        coords={"time": np.arange(T), "lat": np.arange(ny) * 1.0, "lon": np.arange(nx) * 1.0},
        attrs={"units": "K"},
    )


@pytest.fixture(scope="module")
def results():  # the paper's protocol (its fold-in is the floor complete_mse bounds)
    return evaluate(planted(), rank=3, n_test=4, budgets=(3, 8, 15), n_starts=3,
                    seed=1, progress=False, paper=True,
                    planning=PlanningOptions(random_trials=4),
                    scoring=ScoringOptions(min_observations=4))


def test_protocol_invariants(results):
    ds = results
    assert ds["mse"].dims == ("method", "budget", "start", "trial", "test_time")
    assert ds.sizes["test_time"] == 4 and ds.sizes["trial"] == 4
    budgets = ds["budget"].broadcast_like(ds["cost"])
    done = np.isfinite(ds["cost"])
    assert bool((ds["cost"].where(done) <= budgets + 1e-9).where(done, True).all())
    # non-random methods run one trial only
    assert bool(np.isnan(ds["cost"].sel({"method": "greedy"}).isel(trial=slice(1, None))).all())
    # excluded exactly where too few observations
    enough = ds["n_obs"] >= ds.attrs["min_observations"]
    assert bool((np.isfinite(ds["mse"]) <= enough).all())
    assert bool((ds["n_obs"] <= ds["n_cells"]).all())
    # the certified bound holds for the greedy plans
    greedy = ds["information"].sel({"method": "greedy"}).isel(trial=0)
    assert bool((ds["bound"] >= greedy - 1e-6).all())
    # the complete condition minimises each snapshot's error: a floor for every plan
    assert bool((ds["mse"] >= ds["complete_mse"] - 1e-9).where(np.isfinite(ds["mse"]), True).all())


def test_protocol_is_deterministic(results):
    again = evaluate(planted(), rank=3, n_test=4, budgets=(3, 8, 15), n_starts=3,
                     seed=1, progress=False, paper=True,
                     planning=PlanningOptions(random_trials=4),
                     scoring=ScoringOptions(min_observations=4))
    xr.testing.assert_identical(results, again)


def test_summary_matches_manual_mean(results):
    df = summary(results).set_index(["method", "budget"])
    sel = results.sel({"method": "random", "budget": 8.0})
    err = sel["mse"].values[np.isfinite(sel["mse"].values)]
    row = df.loc[("random", 8.0)]
    assert row["mse_mean"] == pytest.approx(err.mean())
    assert row["mse_se"] == pytest.approx(err.std(ddof=1) / np.sqrt(err.size))
    assert row["n_predictions"] == err.size


def test_save_results_round_trip(results, tmp_path):
    paths = save_results(results, tmp_path)
    back = xr.load_dataset(paths["results"])
    xr.testing.assert_allclose(back.drop_vars("method"), results.drop_vars("method"))
    assert paths["summary"].read_text().startswith("method,budget")


def test_bad_arguments():
    da = planted()
    with pytest.raises(DataError, match="n_test"):
        evaluate(da, n_test=0, progress=False)
    with pytest.raises(ModelError, match="method"):
        evaluate(da, rank=3, methods=("greedy", "spiral"), progress=False)
    with pytest.raises(DataError):
        evaluate(da.isel(time=0), progress=False)


def test_a_budget_whose_plans_are_all_unscored_warns():
    """Plans of 2 grid units observe 3 cells, fewer than min_observations=10: every error at
    that budget is NaN, and one warning says why (none for the budget that scores)."""
    with pytest.warns(UserWarning, match="budget 2: no plan observes min_observations=10"):
        ds = evaluate(planted(), rank=3, n_test=4, budgets=(2, 40), n_starts=2,
                      seed=1, progress=False, paper=True,
                      planning=PlanningOptions(random_trials=1),
                      scoring=ScoringOptions(min_observations=10))
    assert np.isnan(ds["mse"].sel(budget=2)).all()
    assert np.isfinite(ds["mse"].sel(budget=40)).any()
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        evaluate(planted(), rank=3, n_test=4, budgets=(40,), n_starts=2,
                 seed=1, progress=False, paper=True,
                 planning=PlanningOptions(random_trials=1),
                 scoring=ScoringOptions(min_observations=10))


@pytest.mark.parametrize("spatial", ["exponential", None])
def test_model_scores_equal_one_fold_in_per_snapshot(spatial):
    """A plan's MSE and interval coverage on the test snapshots (the snapshots that observe
    the same cells share one kriging system) equal a plain loop: fold each snapshot in, predict
    its map and its held-out cells, score them."""
    from lrm_cvx import GLRM
    from lrm_cvx.glrm.calibrated import interval_coverage
    from lrm_cvx.scoring import coverage_subset, model_coverage, model_mse, model_scores

    rng = np.random.default_rng(5)
    T, ny, nx, k = 30, 8, 9, 2
    data = (rng.normal(size=(T, k)) @ rng.normal(size=(k, ny * nx)) + 10.0
            + 0.3 * rng.normal(size=(T, ny * nx))).reshape(T, ny, nx)
    da = xr.DataArray(data, dims=("time", "lat", "lon"),
                      coords={"time": np.arange(T), "lat": np.arange(ny) * 1.0,
                              "lon": np.arange(nx) * 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(k, offset=True, spatial=spatial, progress=False, random_state=0,
                     max_iter=30).fit(da.isel(time=slice(0, 24)))
    test = da.isel(time=slice(24, None)).values.reshape(6, -1).copy()
    cells = rng.choice(ny * nx, 12, replace=False)
    test[1, cells[:3]] = np.nan  # two snapshots see fewer of the plan's cells
    test[4, cells[5]] = np.nan
    test[2, cells] = np.nan  # one sees none of them
    test[3, rng.choice(ny * nx, 20, replace=False)] = np.nan  # gaps elsewhere
    prior = model.latent_prior("empirical", spatial=spatial is not None)
    stats = SnapshotStatistics.from_values(np.asarray(model.Y_), test,
                                           np.asarray(model.offset_).ravel(), None)
    subsets = coverage_subset(test, seed=0)
    mse, n_obs, cov = model_scores(prior, test, cells, 4, stats=stats, subsets=subsets)
    want_mse, want_cov = np.full(6, np.nan), np.full((6, 2), np.nan)
    for t in range(6):
        seen = cells[np.isfinite(test[t, cells])]
        if seen.size < 4:
            continue
        post = prior.update(seen, test[t, seen])
        want_mse[t] = np.nanmean((post.predict()[0] - test[t]) ** 2)
        held = np.setdiff1d(subsets[t], cells)
        want_cov[t] = interval_coverage(test[t, held], post.predict(cells=held)[0],
                                        post.predictive_std(cells=held),
                                        multipliers=post.interval_multipliers())
    np.testing.assert_array_equal(n_obs, np.isfinite(test[:, cells]).sum(axis=1))
    assert np.isnan(mse[2]) and np.isfinite(mse[[0, 1, 3, 4, 5]]).all()
    np.testing.assert_allclose(mse, want_mse, rtol=1e-9)
    np.testing.assert_allclose(cov, want_cov, rtol=0, atol=1e-12)
    assert 0 < np.nanmin(cov[:, 1]) and np.nanmax(cov[:, 0]) < 1  # intervals that can miss
    np.testing.assert_allclose(model_mse(prior, stats, cells, 4)[0], mse, rtol=1e-12)
    np.testing.assert_allclose(model_coverage(prior, test, subsets, cells, 4), cov, rtol=0)
