"""The one search of the validated choices (validation/search.py): its splitters, its loop and
the choices every ``"auto"`` makes through it, pinned on the bundled records and a planted one.

The pinned tables (``tests/pins/``) hold every choice and table value bit for bit; a change
of a choice or of any value fails here.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import GLRM
from lrm_cvx.datasets import load_sample
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.region import Region
from lrm_cvx.validation.designs import flown_sets
from lrm_cvx.validation.search import (
    Best,
    Decision,
    ForwardBlocks,
    HeldOutCells,
    InterleavedBlocks,
    OneStandardError,
    PairedGuard,
    RollingOrigin,
    search,
    selection_table,
)

PINS = Path(__file__).parent / "pins"


def _planted() -> xr.DataArray:
    """Two persistent latent modes on a small grid, daily: rank 3 with AR(1) is chosen."""
    return synthetic_dynamic_field(60, (8, 9), 2, seed=4, A=0.9 * np.eye(2),
                                   Q=0.1 * (1 - 0.81) * np.eye(2), freq="D", missing=0.1,
                                   noise=0.1)


def _fit(data: xr.DataArray, **kw) -> GLRM:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(random_state=0, progress=False, **kw).fit(data)


def _pin(name: str) -> xr.Dataset:
    return xr.load_dataset(PINS / f"{name}.nc")


@pytest.mark.parametrize(("name", "kernel"), [("sst", "gaussian x1.69"),
                                              ("hgt500", "gaussian x2.19")])
def test_temporal_and_spatial_auto_are_pinned_and_saved(name, kernel, tmp_path):
    model = _fit(load_sample(name), rank=5, temporal="auto", spatial="auto")
    assert model.selection_.attrs["choice"] == "none"
    assert model.kernel_selection_.attrs["choice"] == kernel
    xr.testing.assert_identical(model.selection_, _pin(f"{name}_selection"))
    xr.testing.assert_identical(model.kernel_selection_, _pin(f"{name}_kernel"))
    model.save(tmp_path / "model.nc")  # the tables travel with the model file
    back = GLRM.load(tmp_path / "model.nc")
    xr.testing.assert_identical(back.selection_, model.selection_)
    xr.testing.assert_identical(back.kernel_selection_, model.kernel_selection_)


@pytest.mark.parametrize(("name", "choice", "rank"), [("sst_rank", "rank 5 none", 5),
                                                      ("planted_rank", "rank 3 ar1:0.9 x2", 3)])
def test_rank_auto_is_pinned(name, choice, rank):
    data = load_sample("sst") if name == "sst_rank" else _planted()
    model = _fit(data, rank="auto", temporal="auto")
    assert model.selection_.attrs["choice"] == choice and model.rank_ == rank
    xr.testing.assert_identical(model.selection_, _pin(f"{name}_selection"))


@pytest.mark.parametrize(("name", "rmse"), [
    ("sst", (0.4517830101801136, 0.36962619478437986, 0.3387943236602003, 0.2926369071870525)),
    ("hgt500", (42.18314769302541, 32.017609766118916, 27.37952946330153, 20.048938433298385)),
    ("planted", (0.1036559143623305, 0.1076903655844934, 0.11063380839306351,
                 0.12318431676282623))])
def test_select_rank_is_pinned(name, rmse):
    """GLRM.select_rank returns the search's table over ``rank``: the held-out RMSEs pinned,
    the MSE the rule scored, the lowest one chosen."""
    data = _planted() if name == "planted" else load_sample(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = GLRM(rank=3, random_state=0, progress=False).select_rank(data, [1, 2, 3, 5])
    assert got["rank"].values.tolist() == [1, 2, 3, 5]
    assert got["rmse"].values.tolist() == list(rmse)
    assert got.attrs["choice"] == [1, 2, 3, 5][int(np.argmin(rmse))]
    assert set(got.data_vars) == {"mse", "ratio", "ucb", "admissible", "rmse"}
    assert got["mse"].dims == got["ratio"].dims == ("rank", "size")
    np.testing.assert_allclose(got["mse"].values[:, 0], np.square(rmse), rtol=1e-15)
    assert got["ratio"].values[0, 0] == 1.0 and got["admissible"].values.all()


def test_rolling_origin_windows_end_at_the_last_snapshot():
    assert RollingOrigin(3, 2).split(10) == [(4, 7), (7, 10)]
    assert RollingOrigin(4, 1).split(10) == [(6, 10)]
    # a refit needs 5 snapshots: one window of 3, then one shorter window, then none
    assert RollingOrigin(3, 2).split(8, lambda lo: lo >= 5) == [(5, 8)]
    assert RollingOrigin(3, 2).split(7, lambda lo: lo >= 5) == [(5, 7)]
    assert RollingOrigin(3, 2).split(6, lambda lo: lo >= 5) is None


def test_interleaved_blocks_hold_out_every_kth_snapshot_once():
    folds = InterleavedBlocks(3).split(11)
    assert len(folds) == 3
    tests = [test for _, test in folds]
    assert tests[0].tolist() == [0, 3, 6, 9] and tests[2].tolist() == [2, 5, 8]
    assert sorted(np.concatenate(tests).tolist()) == list(range(11))
    for train, test in folds:
        assert np.intersect1d(train, test).size == 0 and train.size + test.size == 11


def test_held_out_cells_are_the_observed_cells_a_design_leaves():
    region = Region.from_dataarray(load_sample("sst"))
    observed = np.random.default_rng(1).random(region.n_cells) < 0.7
    flown, held = HeldOutCells(max_scored=40).split(region, observed, 15, "route",
                                                    np.random.default_rng(3))
    assert np.array_equal(flown, flown_sets(region, 15, "route", np.random.default_rng(3)))
    assert held.size == 40 and np.all(np.diff(held) > 0)
    assert observed[held].all() and np.intersect1d(held, flown).size == 0
    _, every = HeldOutCells(max_scored=10**6).split(region, observed, 15, "route",
                                                    np.random.default_rng(3))
    assert np.array_equal(every, np.setdiff1d(np.flatnonzero(observed), flown))


def test_search_concatenates_the_splits_and_drops_what_a_split_lacks():
    rng = np.random.default_rng(0)
    days = {0: rng.uniform(1, 2, (2, 5)), 1: rng.uniform(1, 2, (2, 4))}

    def score(split):  # "c" only on the first split, "d" dropped by name
        out = {"ref": days[split], "a": 0.5 * days[split], "d": 0.1 * days[split]}
        return {**out, "c": days[split]} if split == 0 else out

    seen = []

    def rule(E, labels):
        seen.append((E.copy(), list(labels)))
        return PairedGuard(1.645, 0.01)(E)

    labels, E, d = search(score, [0, 1], rule, drop=lambda lab: lab == "d")
    assert labels == ["ref", "a"] and E.shape == (2, 2, 9)
    assert np.array_equal(E[0], np.concatenate([days[0], days[1]], axis=-1))
    assert seen[0][1] == labels and d.choice == d.best == 1
    table = selection_table(d, labels, [5, 15], what="day MSE", best=labels[d.best])
    assert table.attrs["choice"] == "a" and table["ratio"].values[1] == pytest.approx(0.5)
    assert "competes" not in table and table["mse"].attrs["long_name"] == "day MSE"


def test_one_standard_error_keeps_the_group_and_takes_the_most_cautious():
    rng = np.random.default_rng(1)
    base = 1.0 + 0.2 * rng.random((2, 40))
    noise = 0.01 * rng.standard_normal((2, 40))
    noise -= noise.mean(axis=-1, keepdims=True)
    E = np.stack([base, 0.8 * base, 0.8 * base * 1.001 + noise, 0.8 * base * 1.001 + noise])
    labels = ["none", "g x1", "g x2", "h x4"]  # "h x4": as cautious, another group
    rule = OneStandardError(PairedGuard(1.645, 0.01), group=lambda lab: lab[0],
                            caution=lambda lab: int(lab.split("x")[-1]) if "x" in lab else 0)
    d = rule(E, labels)
    assert isinstance(d, Decision) and d.best == 1 and d.choice == 2


@pytest.mark.parametrize(("name", "choice", "cells"), [
    ("sst", "risk+exchange", [109, 294, 285, 160, 410, 374]),
    ("planted", "gp-variance+exchange", [7, 9, 6, 45, 2, 43])])
def test_criterion_auto_is_pinned(name, choice, cells):
    from lrm_cvx.planning import place_sensors

    data = load_sample("sst") if name == "sst" else _planted()
    model = _fit(data, rank=3, spatial="exponential")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = place_sensors(model, 6, training=data)
    table = plan.refinement["selection"]
    assert table.attrs.pop("seconds") > 0  # the one attribute that is not a result
    assert table.attrs["choice"] == choice and plan.cells.tolist() == cells
    xr.testing.assert_identical(table, _pin(f"{name}_placement"))


def test_select_dynamics_is_pinned():
    from lrm_cvx.validation.blending import select_dynamics

    data = _planted()
    model = _fit(data, rank=3, temporal="ar1")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alpha, table = select_dynamics(model, data, sizes=(5, 15), apply=False)
    pin = _pin("planted_dynamics")
    assert alpha == pin.attrs["alpha"] == 1.0 and table.attrs["n_days"] == pin.attrs["n_days"]
    assert np.array_equal(table["alpha"].values, pin["alpha"].values)
    assert np.array_equal(table["total"].values, pin["mse"].values)
    assert np.array_equal(table["ucb"].values, pin["ucb"].values)
    assert table.attrs["choice"] == "1" and table.attrs["choice_alpha"] == alpha


def test_dynamics_blend_table_is_the_search_table_and_saved(tmp_path):
    """select_dynamics returns the table every validated choice returns; applied, it is the
    model's dynamics_selection_, which the model file carries back identically (and with it
    the blend calibrate's refits follow)."""
    from lrm_cvx.validation.blending import dynamics_alpha, select_dynamics

    data = synthetic_dynamic_field(24, (5, 6), 2, seed=1, A=0.9 * np.eye(2), freq="D",
                                   noise=0.1)
    model = _fit(data, rank=2, temporal="ar1", max_iter=20)
    assert model.dynamics_selection_ is None and dynamics_alpha(model) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alpha, table = select_dynamics(model, data, alphas=(0.5, 1.0), sizes=(3,), n_val=4,
                                       kinds=("scattered",))
    assert model.dynamics_selection_ is table and dynamics_alpha(model) == alpha
    assert table.attrs["choice"] == f"{alpha:g}" and table.attrs["choice_alpha"] == alpha
    assert set(table.data_vars) == {"mse", "ratio", "ucb", "admissible", "total"}
    assert table["ratio"].dims == table["mse"].dims == ("candidate", "size")
    model.save(tmp_path / "model.nc")
    back = GLRM.load(tmp_path / "model.nc")
    xr.testing.assert_identical(back.dynamics_selection_, table)
    assert back.selection_ is None and dynamics_alpha(back) == alpha
    from lrm_cvx.validation.calibration import refit_dynamics

    again = refit_dynamics(back, back, "ar1", back.X_["time"])  # calibrate's refits' blend
    assert again.blend == pytest.approx(alpha)
    np.testing.assert_array_equal(again.A, refit_dynamics(model, model, "ar1",
                                                          model.X_["time"]).A)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data)  # a new fit drops the old choice
    assert model.dynamics_selection_ is None


def test_best_takes_the_lowest_worst_ratio_without_a_guard():
    E = np.array([[[1.0, 1.2], [2.0, 2.0]], [[0.5, 0.7], [2.2, 2.2]], [[0.9, 1.0], [1.8, 2.0]]])
    d = Best()(E)
    worst = (E.mean(axis=-1) / E[0].mean(axis=-1)).max(axis=1)  # 1, 1.1 and 0.95
    assert d.choice == d.best == int(np.argmin(worst)) == 2
    assert d.admissible.all() and np.isnan(d.ucb).all() and d.n_cases == 2


def test_cv_residuals_folds_are_pinned():
    """The calibration's interleaved and forward folds and held-out cells are the search's
    splitters: the fold-in residuals on the planted record are those pinned."""
    from lrm_cvx.validation.calibration import cv_residuals

    data = _planted()
    model = _fit(data, rank=3, spatial="exponential", temporal="ar1")
    pin = np.load(PINS / "planted_cv_residuals.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        inter = cv_residuals(model, data, max_cells=40).z()
        forward = cv_residuals(model, data, folds="forward").z()
    assert np.array_equal(inter, pin["interleaved"])
    assert np.array_equal(forward, pin["forward"])


def test_forward_blocks_refit_on_everything_before_each_later_block():
    folds = ForwardBlocks(4).split(10)  # blocks 0-2, 3-5, 6-7, 8-9: the last two held out
    assert [test.tolist() for _, test in folds] == [[6, 7], [8, 9]]
    assert [train.tolist() for train, _ in folds] == [list(range(6)), list(range(8))]


@pytest.mark.parametrize(("name", "choice", "scale"), [
    ("planted", "x1 power 0.75", 0.6944122421230459),
    ("sst", "x4 power 0.75", 0.29391556924202805),
    ("hgt500", "x1.41 power 0.5", 1.0737591833218065)])
def test_calibration_choice_is_pinned_and_saved(name, choice, scale, tmp_path):
    """calibrate's residual factor and local power are the search's choice (the highest
    held-out log-likelihood): the choice and scale as the hand loop made them, the table
    pinned, saved with the model and read back identically."""
    from lrm_cvx.validation.calibration import calibrate

    data = _planted() if name == "planted" else load_sample(name)
    model = _fit(data, rank=3 if name == "planted" else 5, offset=True,
                 spatial="exponential")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(model, data, n_blocks=2, sizes=(5, 15), kinds=("route", "scattered"),
                        max_snapshots=1, max_cells=60, adaptive=False)
    table = cal.selection
    assert table.attrs["choice"] == choice and cal.scale == scale
    assert (float(table["residual_scale"].sel(candidate=choice)),
            float(table["local_power"].sel(candidate=choice))) == (cal.residual_scale,
                                                                   cal.local_power)
    assert float(table["scale"].sel(candidate=choice)) == cal.scale
    ll = table["mse"].values[:, 0]
    assert table.sizes == {"candidate": 45, "size": 1} and ll.argmax() == list(
        table["candidate"].values).index(choice)
    np.testing.assert_allclose(table["ratio"].values[:, 0], np.exp(ll - ll[0]), rtol=1e-12)
    xr.testing.assert_identical(table, _pin(f"{name}_calibration"))
    model.save(tmp_path / "model.nc")
    back = GLRM.load(tmp_path / "model.nc")
    xr.testing.assert_identical(back.calibration_.selection, table)
    assert back.calibration_.to_attrs().keys() == cal.to_attrs().keys()


def test_best_on_log_likelihoods_takes_the_highest_and_the_first_of_equals():
    """Log-likelihoods of either sign: the highest mean wins (a ratio to a negative reference
    would reverse the order), the first of equal ones, never a NaN."""
    E = np.array([[[-2.0]], [[0.5]], [[0.5]], [[np.nan]], [[-0.1]]])
    with pytest.warns(RuntimeWarning, match="empty slice"):  # the NaN candidate's mean
        d = Best(log_likelihood=True)(E)
    assert d.choice == d.best == 1
    np.testing.assert_allclose(d.ratio[:, 0], np.exp(E[:, 0, 0] + 2.0))
