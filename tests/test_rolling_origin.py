"""``backtest``: the rolling-origin backtest of the evaluation protocol."""

import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from test_evaluation import planted

from lrm_cvx import cli
from lrm_cvx.cli import main
from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.evaluation import (
    PlanningOptions,
    ScoringOptions,
    backtest,
    evaluate,
    save_results,
    summary,
)
from lrm_cvx.glrm import GLRM

PAPER = dict(rank=3, n_test=4, budgets=(3, 8), n_starts=2,
             seed=1, progress=False, paper=True,
             planning=PlanningOptions(random_trials=2),
             scoring=ScoringOptions(min_observations=4))


@pytest.fixture(scope="module")
def rolled():
    return backtest(planted(), 3, **PAPER)


def test_each_block_is_the_protocol_run_on_the_snapshots_up_to_it(rolled):
    """Block b equals evaluate() on the data cut after block b: same model, starts, plans,
    errors; the blocks tile the last 12 snapshots."""
    da = planted()
    T = da.sizes["time"]
    assert rolled.sizes["origin"] == 3 and rolled.attrs["origins"] == 3
    assert list(rolled["test_time"].values) == list(da["time"].values[T - 12:])
    for b in range(3):
        end = T - (2 - b) * 4
        alone = evaluate(da.isel(time=slice(None, end)), **PAPER)
        block = rolled.isel(origin=b).sel(test_time=alone["test_time"])
        for name in ("mse", "n_obs", "complete_mse", "coverage95"):
            np.testing.assert_array_equal(block[name].values, alone[name].values)
        np.testing.assert_array_equal(block["information"].values, alone["information"].values)
        assert int(block["n_train"]) == end - 4
        assert block["origin_time"].values == alone["test_time"].values[0]
        # the other blocks' times are empty in this block
        other = rolled.isel(origin=b).drop_sel(test_time=alone["test_time"].values)
        assert bool(np.isnan(other["mse"]).all())


def test_summary_pools_the_blocks_and_splits_them_on_request(rolled):
    pooled = summary(rolled).set_index(["method", "budget"])
    err = rolled.sel({"method": "random", "budget": 8.0})["mse"].values
    err = err[np.isfinite(err)]
    assert pooled.loc[("random", 8.0), "mse_mean"] == pytest.approx(err.mean())
    assert pooled.loc[("random", 8.0), "n_predictions"] == err.size
    per = summary(rolled, by_origin=True)
    assert list(per.columns[:3]) == ["origin", "origin_time", "n_train"]
    assert len(per) == 3 * len(pooled)
    for b in range(3):
        row = per[(per["origin"] == b) & (per["method"] == "random") & (per["budget"] == 8.0)]
        e = rolled.isel(origin=b).sel({"method": "random", "budget": 8.0})["mse"].values
        assert float(row["mse_mean"].iloc[0]) == pytest.approx(np.nanmean(e))
    with pytest.raises(ModelError, match="by_origin"):
        summary(rolled, by_origin="yes")


def test_save_results_writes_a_row_per_block(rolled, tmp_path):
    paths = save_results(rolled, tmp_path)
    back = xr.load_dataset(paths["results"])
    assert back.sizes["origin"] == 3 and list(back["n_train"].values) == [12, 16, 20]
    text = paths["summary_by_origin"].read_text()
    assert text.startswith("origin,origin_time,n_train,method,budget")


def test_no_block_sees_its_own_or_later_snapshots():
    """Poison the last block (and its model's every choice and calibration would move): the
    earlier blocks, recommended setting (spatial="auto", conformal calibration), are unchanged."""
    da = planted()
    kw = dict(rank=3, n_test=4, budgets=(5,), n_starts=2,
              seed=0, progress=False, methods=("greedy:gp-variance", "random"),
              planning=PlanningOptions(random_trials=1),
              scoring=ScoringOptions(min_observations=4))
    clean = backtest(da, 2, **kw)
    poisoned = da.copy()
    poisoned[-4:] = 50.0 + 10.0 * np.random.default_rng(0).normal(size=poisoned[-4:].shape)
    bad = backtest(poisoned, 2, **kw)
    first = clean.isel(origin=0).dropna("test_time", how="all", subset=["complete_mse"])
    again = bad.isel(origin=0).sel(test_time=first["test_time"])
    for name in ("mse", "coverage68", "coverage95", "information"):
        np.testing.assert_array_equal(first[name].values, again[name].values)
    assert not np.allclose(clean.isel(origin=1)["mse"].values, bad.isel(origin=1)["mse"].values,
                           equal_nan=True)


def test_a_given_model_lends_its_parameters_only():
    """A model fitted on every snapshot (the test blocks too) is refitted per block: the
    result equals the one from the same parameters without a model."""
    da = planted()
    leaky = GLRM(rank=3, random_state=1, progress=False).fit(da)
    given = backtest(da, 2, model=leaky, **{k: v for k, v in PAPER.items() if k != "rank"})
    fresh = backtest(da, 2, **PAPER)
    xr.testing.assert_equal(given["mse"], fresh["mse"])


@pytest.mark.parametrize(("origins", "match"), [(0, "origins"), (2.5, "origins"),
                                                (6, "origins=6")])
def test_bad_origins_name_the_argument(origins, match):
    with pytest.raises(DataError, match=match):
        backtest(planted(), origins, **PAPER)


def test_cli_backtest_writes_both_summaries(tmp_path, capsys):
    from test_cli import TINY

    out = tmp_path / "ev"
    assert main(["-q", "evaluate", "sample:sst", *TINY, "--paper", "--methods", "greedy,random",
                 "--certify", "off", "--origins", "2", "--out", str(out)]) == 0
    got = xr.load_dataset(out / "results.nc")
    assert got.sizes["origin"] == 2
    assert (out / "summary_by_origin.csv").read_text().startswith("origin,")
    assert sorted(p.name for p in out.iterdir()) == sorted(cli.EVALUATION_FILES
                                                           + cli.BACKTEST_FILES)
    assert (out / "predictions.png").exists()
    printed = capsys.readouterr().out
    assert "coverage over 2 blocks (holds: mean 68 % in 0.63-0.73, mean 95 % in 0.93-0.97" \
        in printed
    from lrm_cvx.evaluation import coverage_check

    check = coverage_check(got)
    rows = printed.split("coverage over")[1].splitlines()[2:2 + len(check)]  # after the header
    for line, (method, verdict) in zip(rows, check[["method", "verdict"]].itertuples(
            index=False), strict=True):  # each row's verdict, as computed, in order
        assert line.split()[0] == method and line.rstrip().endswith(verdict)
    for bad, says in (("0", "--origins: must be an integer >= 1"),
                      ("1000", "--origins 1000 blocks of --n-test 2 need")):
        assert main(["-q", "evaluate", "sample:sst", *TINY, "--paper", "--origins", bad,
                     "--out", str(tmp_path / "x")]) != 0
        assert says in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_blocks_with_routes_of_other_lengths_stack():
    """A block whose longest greedy route is shorter (its ``step`` dim) is padded like a
    route: -1 in integer variables, NaN in floats, False in booleans."""
    from lrm_cvx.evaluation import _padded

    def block(n_steps, t0):
        return xr.Dataset(
            {"greedy_route": (("budget", "step"), np.arange(2 * n_steps).reshape(2, n_steps)),
             "step_cost": (("budget", "step"), np.ones((2, n_steps))),
             "visited": (("budget", "step"), np.ones((2, n_steps), bool)),
             "mse": (("budget", "test_time"), np.ones((2, 2)))},
            coords={"budget": [5.0, 10.0], "test_time": [t0, t0 + 1]})

    a, b = _padded([block(3, 0), block(5, 2)])
    out = xr.concat([a, b], dim="origin", join="outer")
    assert out.sizes["step"] == 5
    np.testing.assert_array_equal(out["greedy_route"].isel(origin=0).values,
                                  [[0, 1, 2, -1, -1], [3, 4, 5, -1, -1]])
    assert out["greedy_route"].dtype.kind == "i" and out["visited"].dtype == bool
    assert np.isnan(out["step_cost"].isel(origin=0, step=[3, 4])).all()
    assert not out["visited"].isel(origin=0, step=[3, 4]).any()
    np.testing.assert_array_equal(out["greedy_route"].isel(origin=1).values,
                                  block(5, 2)["greedy_route"].values)


def test_backtest_figure_draws_each_blocks_summary(rolled):
    import matplotlib

    matplotlib.use("Agg")
    from lrm_cvx.evaluation import COVERAGE_BANDS
    from lrm_cvx.plots import plot_backtest

    fig = plot_backtest(rolled, budget=8.0)
    per = summary(rolled, by_origin=True)
    per = per[(per["budget"] == 8.0) & (per["method"] == "random")].sort_values("origin")
    for ax, col in zip(fig.axes, ("mse_mean", "coverage68_mean", "coverage95_mean"),
                       strict=True):
        line = next(ln for ln in ax.get_lines() if ln.get_label() == "random walk"
                    or ln.get_label() == "random")
        np.testing.assert_allclose(line.get_ydata(), per[col].to_numpy())
    band = fig.axes[2].patches[0]  # the shaded band, in data units along y
    assert (band.get_y(), band.get_y() + band.get_height()) == pytest.approx(COVERAGE_BANDS[95])
    with pytest.raises(DataError, match="budget"):
        plot_backtest(rolled, budget=4.0)
    with pytest.raises(DataError, match="origins"):
        plot_backtest(rolled.isel(origin=0))


def test_campaigns_roll_too():
    """Filter campaigns (``temporal=``) through the rolling origin: each block's campaign is
    the one evaluate() runs on the snapshots up to it, memoryless twin included."""
    da = planted()
    kw = dict(rank=3, n_test=4, budgets=(5,), n_starts=1, seed=0,
              progress=False, methods=("greedy:fisher",), temporal="ar1",
              planning=PlanningOptions(certify=False),
              scoring=ScoringOptions(min_observations=4, model_params={"offset": True},
                                     fold_in={"prior": "empirical"}))
    rolled = backtest(da, 2, **kw)
    alone = evaluate(da.isel(time=slice(None, -4)), **kw)
    block = rolled.isel(origin=0).sel(test_time=alone["test_time"])
    for name in ("mse", "mse_memoryless"):
        np.testing.assert_array_equal(block[name].values, alone[name].values)
    assert summary(rolled, by_origin=True)["temporal_cut"].notna().all()


def test_coverage_check_against_the_blocks_by_hand(rolled):
    from lrm_cvx.evaluation import LOWEST_BLOCK_95, coverage_check

    check = coverage_check(rolled).set_index(["method", "budget"])
    for (method, budget), row in check.iterrows():
        sel = rolled.sel({"method": method, "budget": budget})
        with warnings.catch_warnings():  # a block with no valid prediction: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            c68 = np.array([np.nanmean(sel["coverage68"].isel(origin=b).values)
                            for b in range(3)])
            c95 = np.array([np.nanmean(sel["coverage95"].isel(origin=b).values)
                            for b in range(3)])
        assert row["blocks"] == 3
        assert row["cov68"] == pytest.approx(np.nanmean(c68))  # over the blocks with some
        assert row["cov95"] == pytest.approx(np.nanmean(c95))
        assert row["cov95_lowest_block"] == pytest.approx(np.nanmin(c95))
        assert row["holds"] == bool(np.isfinite(c95).all()
                                    and 0.63 <= np.mean(c68) <= 0.73
                                    and 0.93 <= np.mean(c95) <= 0.97
                                    and c95.min() >= LOWEST_BLOCK_95)
        assert (row["verdict"] == "holds") == row["holds"]
    with pytest.raises(DataError, match="origins"):
        coverage_check(rolled.isel(origin=0))


@pytest.mark.parametrize("c68, c95, verdict", [
    ((0.68, 0.70, 0.66), (0.95, 0.96, 0.94), "holds"),
    ((0.80, 0.82, 0.78), (0.98, 0.99, 0.97), "68 % too wide; 95 % too wide"),
    ((0.50, 0.55, 0.60), (0.95, 0.95, 0.95), "68 % too narrow"),
    ((0.68, 0.68, 0.68), (0.99, 0.99, 0.85), "a block's 95 % below 0.9"),
    ((0.60, 0.60, 0.60), (0.92, 0.92, 0.80), "68 % too narrow; 95 % too narrow; "
                                             "a block's 95 % below 0.9"),
    ((np.nan, 0.7, 0.7), (np.nan, 0.95, 0.95), "no intervals"),
])
def test_coverage_verdict_says_which_way_a_miss_goes(rolled, c68, c95, verdict):
    """Planted per-block coverages (each block's every campaign and day alike): the verdict
    names each miss and its side."""
    from lrm_cvx.evaluation import coverage_check

    ds = rolled.copy()
    for name, values in (("coverage68", c68), ("coverage95", c95)):
        planted = xr.DataArray(np.array(values, float), dims="origin")
        ds[name] = (xr.zeros_like(rolled[name]) + planted).transpose(*rolled[name].dims)
    check = coverage_check(ds)
    assert (check["verdict"] == verdict).all()
    assert (check["holds"] == (verdict == "holds")).all()


def test_backtest_checks_evaluates_keywords_before_any_fit():
    with pytest.raises(TypeError, match="n_tests"):
        backtest(planted(), 2, n_tests=4)
    with pytest.raises(DataError, match="n_test"):
        backtest(planted(), 2, n_test=0)


def test_a_360_day_calendar_backtests_and_saves(tmp_path):
    """Climate-model records keep their calendar: the blocks' first times are cftime dates,
    saved and loaded back, and the figure labels them."""
    import cftime
    import matplotlib

    matplotlib.use("Agg")
    from lrm_cvx.plots import plot_backtest

    da = planted()
    da = da.assign_coords(time=[cftime.Datetime360Day(1900 + i, 7, 1)
                                for i in range(da.sizes["time"])])
    res = backtest(da, 2, **{**PAPER, "budgets": (3,), "n_starts": 1})
    want = [cftime.Datetime360Day(1916, 7, 1), cftime.Datetime360Day(1920, 7, 1)]
    assert list(res["origin_time"].values) == want
    back = xr.load_dataset(save_results(res, tmp_path)["results"])
    assert list(back["origin_time"].values) == want
    labels = [t.get_text() for t in plot_backtest(res).axes[0].get_xticklabels()]
    assert labels[0].startswith("1916-07-01")


def test_cli_evaluate_with_temporal_flies_the_filters_campaigns(tmp_path):
    """``evaluate --temporal K`` runs ``evaluate(temporal=K)``: each start's route flown day
    after day, the filter scored beside the memoryless fold-in (before, the flag fitted
    dynamics the memoryless protocol never used); without it the protocol stays memoryless."""
    from test_cli import TINY

    args = ["-q", "evaluate", "sample:sst", *TINY, "--paper", "--methods", "greedy,random",
            "--certify", "off"]
    assert main([*args, "--temporal", "ar1", "--out", str(tmp_path / "ar1")]) == 0
    assert main([*args, "--out", str(tmp_path / "plain")]) == 0
    ar1 = pd.read_csv(tmp_path / "ar1" / "summary.csv")
    plain = pd.read_csv(tmp_path / "plain" / "summary.csv")
    assert (ar1["temporal"] == "ar1").all() and (plain["temporal"] == "none").all()
    assert "mse_memoryless_mean" in ar1 and "mse_memoryless_mean" not in plain
    assert not np.allclose(ar1["mse_mean"], ar1["mse_memoryless_mean"])  # the filter flew
    assert xr.load_dataset(tmp_path / "ar1" / "results.nc").attrs["temporal"] == "ar1"


@pytest.mark.parametrize("n_robots", [1, 2])
def test_campaigns_say_nothing_of_forced_initial_cells_over_budget(n_robots):
    """At a budget below the paper's forced initial cells (the start and its k - 1 nearest)
    the protocol is silent, as it is memoryless (an expected case, not news): before, the
    filter's campaigns printed the planner's warning once per start, day and block. Both
    forms of the warning: one robot's, and a fleet's ("robot r's ...")."""
    from lrm_cvx import load_sample

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = evaluate(load_sample("sst"), paper=True, rank=3, n_test=2, n_starts=2,
                      budgets=(1.0,), methods=("greedy",),
                      progress=False, temporal="ar1", n_robots=n_robots,
                      planning=PlanningOptions(random_trials=1, certify=False),
                      scoring=ScoringOptions(min_observations=1))
    assert ds.attrs["temporal"] == "ar1" and ds.attrs["n_robots"] == n_robots
    assert not [w for w in caught if "initial cells" in str(w.message)]
