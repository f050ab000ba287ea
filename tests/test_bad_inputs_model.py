"""Bad and unusual inputs of the GLRM model and of ``evaluate``.

Each case asserts the named error class or the correct result against a naive numpy
reference; file inputs are checksummed before and after (``inputs_unchanged``).
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM, SolverOptions, SpatialOptions
from lrm_cvx.glrm.fit import free_parameters, max_identifiable_rank
from lrm_cvx.io.samples import synthetic_field

FAST = dict(max_iter=200, tol=1e-13, progress=False, random_state=0)


def low_rank(T=12, L=15, k=2, seed=0):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((T, k)) @ rng.standard_normal((k, L))


def per_cell(L=15, seed=1):
    rng = np.random.default_rng(seed)
    return 50.0 + 3.0 * rng.standard_normal(L), rng.uniform(0.5, 3.0, L)


def quiet_fit(model, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return model.fit(*args, **kw)


@pytest.fixture(scope="module")
def field():
    return synthetic_field(14, (6, 7), rank=2, seed=3, missing=0.2, dtype=np.float64)


# --------------------------------------------------------------------------- data units
@pytest.mark.parametrize("offset,scale", [(False, False), (True, False), (False, True),
                                          (True, True)])
def test_reconstruct_and_score_in_data_units_exact(offset, scale):
    """Exactly low-rank data plus a per-cell mean (and spread): the fit reproduces the data in
    its own units, and score is ~0 (it was the squared mean, ~2500, before)."""
    Z = low_rank()
    mu, sd = per_cell()
    D = Z * sd + mu
    # without an offset the mean is one more rank-one term; centring at rank 2 is exact
    rank = 2 if offset else 3
    m = quiet_fit(GLRM(rank=rank, offset=offset, scale=scale, **FAST), D)
    rec = m.reconstruct()
    assert np.max(np.abs(rec - D)) < 1e-3 * np.abs(D).max()
    assert m.score(D) < 1e-8
    # naive reference of the definition: scale_ * X^T Y + offset_
    ref = np.asarray(m.X_).T @ np.asarray(m.Y_)
    if scale:
        ref = ref * m.scale_
    if offset:
        ref = ref + m.offset_
    np.testing.assert_allclose(rec, ref.astype(np.float32), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("offset,scale", [(True, False), (True, True)])
def test_score_equals_naive_mse_with_missing_and_mask(offset, scale):
    rng = np.random.default_rng(5)
    mu, sd = per_cell()
    D = (low_rank() + 0.3 * rng.standard_normal((12, 15))) * sd + mu
    M = rng.random(D.shape) > 0.25
    m = quiet_fit(GLRM(rank=2, offset=offset, scale=scale, **FAST), np.where(M, D, np.nan))
    naive = float(np.mean((m.reconstruct().astype(np.float64) - D)[M] ** 2))
    assert m.score(D, mask=M) == pytest.approx(naive, rel=1e-5)
    assert m.score(np.where(M, D, np.nan)) == pytest.approx(naive, rel=1e-5)
    assert naive < 1.0  # in the data's units: far below the squared mean (~2500)


def test_select_rank_in_data_units_matches_naive_holdout():
    mu, _ = per_cell()
    rng = np.random.default_rng(7)
    D = low_rank() + mu + 0.2 * rng.standard_normal((12, 15))
    base = GLRM(rank=1, offset=True, **FAST)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = base.select_rank(D, [1, 3], fraction=0.2, seed=4)
        exact = base.select_rank(low_rank() + mu, [3], fraction=0.2, seed=4)
    train, test = GLRM.holdout(D, 0.2, seed=4)
    obs = ~np.isnan(test)
    for r in (1, 3):
        ref = quiet_fit(GLRM(rank=r, offset=True, **FAST), train)
        naive = np.sqrt(np.mean((ref.reconstruct().astype(np.float64) - test)[obs] ** 2))
        assert float(out["rmse"].sel(rank=r)) == pytest.approx(naive, rel=1e-3)
    assert float(out["rmse"].sel(rank=3)) < 1.0  # data units: not the mean (~50)
    # the offset's observed means add one rank: rank 3 is exact
    assert float(exact["rmse"].sel(rank=3)) < 1e-3


def test_reconstruct_dataarray_keeps_coords_and_units(field):
    m = quiet_fit(GLRM(rank=2, offset=True, scale=True, **FAST), field + 100.0)
    rec = m.reconstruct()
    assert isinstance(rec, xr.DataArray) and rec.dims == field.dims
    np.testing.assert_array_equal(rec["time"].values, field["time"].values)
    err = float(((rec - (field + 100.0)) ** 2).mean())
    assert err == pytest.approx(m.score(field + 100.0), rel=1e-4)
    assert err < 1.0


def test_loaded_model_reconstructs_in_data_units(tmp_path):
    mu, _ = per_cell()
    D = low_rank() + mu
    m = quiet_fit(GLRM(rank=2, offset=True, **FAST), D)
    m.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    np.testing.assert_allclose(back.reconstruct(), m.reconstruct())
    assert back.score(D) < 1e-8


# --------------------------------------------------------------------------- magnitudes
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_one_huge_value_warns_and_noise_is_not_zero(dtype):
    rng = np.random.default_rng(0)
    D = low_rank(20, 30) + 0.1 * rng.standard_normal((20, 30))
    D[3, 4] = 1e20
    with pytest.warns(UserWarning, match=r"1e\+20"):
        m = GLRM(rank=2, max_iter=5, progress=False, random_state=0).fit(D.astype(dtype))
    assert np.isfinite(m.noise_std_) and m.noise_std_ > 0
    assert np.isfinite(m.objective_[-1]) and m.objective_[-1] > 0


def test_values_overflowing_float64_are_refused():
    D = low_rank(8, 10)
    D[2, 3] = 1e300
    D[2, 4] = 1e300
    with pytest.raises(DataError, match="overflow"):
        GLRM(rank=2, max_iter=3, progress=False).fit(D)


def test_observed_inf_is_refused_with_count():
    D = low_rank(8, 10)
    D[0, 0] = np.inf
    D[1, 1] = -np.inf
    with pytest.raises(DataError, match="2 non-finite"):
        GLRM(rank=2, max_iter=3, progress=False).fit(D)


def test_inf_outside_the_mask_is_ignored():
    D = low_rank(8, 10)
    M = np.ones(D.shape, bool)
    M[0, 0] = False
    Dm = D.copy()
    Dm[0, 0] = np.inf
    m = quiet_fit(GLRM(rank=2, **FAST), Dm, mask=M)
    assert m.score(D, mask=M) < 1e-10
    assert Dm[0, 0] == np.inf  # the caller's array is untouched


def test_noise_std_is_the_dof_corrected_residual_rms():
    rng = np.random.default_rng(2)
    D = low_rank(10, 12) + 0.2 * rng.standard_normal((10, 12))
    m = quiet_fit(GLRM(rank=2, **FAST), D)
    sse = float(((m.reconstruct().astype(np.float64) - D) ** 2).sum())
    p = 2 * (10 + 12) - 4
    assert m.noise_std_ == pytest.approx(np.sqrt(sse / (D.size - p)), rel=1e-4)


def test_offset_counts_in_the_noise_degrees_of_freedom():
    rng = np.random.default_rng(2)
    D = low_rank(10, 12) + 50 + 0.2 * rng.standard_normal((10, 12))
    m = quiet_fit(GLRM(rank=2, offset=True, **FAST), D)
    sse = float(((m.reconstruct().astype(np.float64) - D) ** 2).sum())
    p = free_parameters(2, 10, 12, offset=True)
    assert p == 2 * 22 - 4 + 12
    assert m.noise_std_ == pytest.approx(np.sqrt(sse / (D.size - p)), rel=1e-3)


# --------------------------------------------------------------------------- identifiability
def test_rank_equal_to_number_of_snapshots_is_refused():
    with pytest.raises(ModelError, match=r"rank 3.*T=3"):
        GLRM(rank=3, progress=False).fit(low_rank(3, 15))


def test_single_snapshot_is_refused():
    with pytest.raises(ModelError, match=r"T=1.*more snapshots"):
        GLRM(rank=1, progress=False).fit(low_rank(1, 15, k=1))


def test_rank_equal_to_number_of_cells_is_refused():
    with pytest.raises(ModelError, match="not identifiable"):
        GLRM(rank=3, progress=False).fit(low_rank(12, 3))


@pytest.mark.parametrize("shape,rank", [((4, 15), 5), ((12, 3), 4)])
def test_rank_above_times_or_cells_is_refused(shape, rank):
    with pytest.raises(ModelError, match=r"rank must be in \[1, min\(T, L\)\]"):
        GLRM(rank=rank, progress=False).fit(low_rank(*shape))


def test_offset_at_rank_t_minus_one_is_refused():
    with pytest.raises(ModelError, match="per-cell offset"):
        GLRM(rank=2, offset=True, progress=False).fit(low_rank(3, 15) + 10)


def test_sparse_data_without_residual_dof_is_refused():
    D = low_rank(10, 40, k=3)
    rng = np.random.default_rng(0)
    D[rng.random(D.shape) < 0.8] = np.nan
    D[:, 0] = 1.0  # every time keeps an observation
    n_obs = int(np.isfinite(D).sum())
    L_obs = int(np.isfinite(D).any(axis=0).sum())
    kmax = max_identifiable_rank(n_obs, 10, L_obs)
    assert n_obs <= free_parameters(kmax + 1, 10, L_obs)
    with pytest.raises(ModelError, match=f"use rank <= {kmax}"):
        GLRM(rank=kmax + 1, progress=False).fit(D)


def test_largest_identifiable_rank_fits_with_positive_noise():
    rng = np.random.default_rng(1)
    D = low_rank(4, 15) + 0.1 * rng.standard_normal((4, 15))
    m = quiet_fit(GLRM(rank=3, **FAST), D)  # T - 1
    assert m.noise_std_ > 0.01


# --------------------------------------------------------------------------- missing data
def test_all_nan_array_is_refused():
    with pytest.raises(DataError, match="no observed value"):
        GLRM(rank=1, progress=False).fit(np.full((5, 6), np.nan))


def test_all_nan_dataarray_is_refused(field):
    with pytest.raises(DataError, match="all NaN"):
        GLRM(rank=1, progress=False).fit(field * np.nan)


def test_one_all_nan_time_is_refused_naming_it(field):
    bad = field.where(field["time"] != field["time"][4])
    with pytest.raises(DataError, match="2013-01-05"):
        GLRM(rank=2, progress=False).fit(bad)


def test_one_all_nan_row_is_refused_naming_its_position():
    D = low_rank(8, 10)
    D[5] = np.nan
    with pytest.raises(DataError, match=r"positions \[5\]"):
        GLRM(rank=2, progress=False).fit(D)


# ------------------------------------------------- score / holdout / select_rank
@pytest.fixture(scope="module")
def plain():
    return quiet_fit(GLRM(rank=2, **FAST), low_rank())


@pytest.mark.parametrize("data,mask,match", [
    (np.zeros((3, 3)), None, "shape"),
    (np.full((12, 15), np.nan), None, "no observed"),
    (np.where(np.eye(12, 15) > 0, np.inf, 0.0), None, "inf"),
    (np.zeros((12, 15)), np.ones((12, 15), dtype=np.int8), "boolean"),
    ("text", None, "numeric"),
])
def test_score_bad_inputs(plain, data, mask, match):
    with pytest.raises(DataError, match=match):
        plain.score(data, mask=mask)


@pytest.mark.parametrize("ranks", [[], [0], [1.5], ["a"], [2, 2], [True]])
def test_select_rank_bad_ranks(plain, ranks):
    with pytest.raises(ModelError, match="ranks"):
        plain.select_rank(low_rank(), ranks)


def test_select_rank_unidentifiable_rank_is_refused(plain):
    with pytest.raises(ModelError, match="rank"):
        plain.select_rank(low_rank(4, 15), [4])


@pytest.mark.parametrize("data,fraction,match", [
    (np.array([[1.0, np.inf], [1.0, 2.0]]), 0.1, "infinite"),
    (np.ones(4), 0.1, "2 dims"),
    ("abc", 0.1, "numeric"),
    (np.ones((3, 3)), 1.0, "fraction"),
    (np.ones((3, 3)), 0.0, "fraction"),
])
def test_holdout_bad_inputs(data, fraction, match):
    with pytest.raises(DataError, match=match):
        GLRM.holdout(data, fraction)


# --------------------------------------------------------------------------- load
@pytest.fixture(scope="module")
def saved(tmp_path_factory, field):
    path = tmp_path_factory.mktemp("model") / "m.nc"
    quiet_fit(GLRM(rank=2, **FAST), field).save(path)
    with xr.open_dataset(path) as f:
        ds = f.load()
    return path, ds


@pytest.mark.parametrize("var", ["X", "Y", "objective", "unobserved_cells", "region_mask"])
def test_load_missing_variable(saved, tmp_path, inputs_unchanged, var):
    bad = tmp_path / "bad.nc"
    ds = saved[1].drop_vars(var)
    ds.encoding = {}
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match=rf"bad\.nc.*missing the variable.*'{var}'"):
        GLRM.load(bad)


def test_load_missing_attribute(saved, tmp_path, inputs_unchanged):
    ds = saved[1].copy()
    ds.attrs = {k: v for k, v in ds.attrs.items() if k != "noise_std"}
    bad = tmp_path / "bad.nc"
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match="noise_std"):
        GLRM.load(bad)


def test_load_newer_format_version(saved, tmp_path, inputs_unchanged):
    ds = saved[1].copy()
    ds.attrs = {**ds.attrs, "format_version": 99}
    bad = tmp_path / "new.nc"
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match="format_version 99.*newer"):
        GLRM.load(bad)


@pytest.mark.parametrize("content,match", [
    (None, "truncated"),  # the first half of a real model file
    (b"", "empty"),
    (b"not a netcdf file at all\n" * 10, "not a readable NetCDF"),
])
def test_load_truncated_empty_or_garbage(saved, tmp_path, inputs_unchanged, content, match):
    bad = tmp_path / "bad.nc"
    if content is None:
        raw = saved[0].read_bytes()
        content = raw[: len(raw) // 2]
    bad.write_bytes(content)
    inputs_unchanged.watch(bad, saved[0])
    with pytest.raises(DataError, match=match):
        GLRM.load(bad)


def test_load_a_data_file_is_not_a_model(field, tmp_path, inputs_unchanged):
    path = tmp_path / "data.nc"
    field.to_netcdf(path)
    inputs_unchanged.watch(path)
    with pytest.raises(DataError, match="not an lrm-cvx GLRM model"):
        GLRM.load(path)


def test_load_inconsistent_factors(saved, tmp_path, inputs_unchanged):
    ds = saved[1].copy()
    ds = ds.isel(component=slice(0, 1)).assign(X=saved[1]["X"].rename(component="c2"))
    bad = tmp_path / "bad.nc"
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match="inconsistent factors"):
        GLRM.load(bad)


@pytest.mark.parametrize("kind", ["missing", "folder"])
def test_load_missing_file_or_folder(tmp_path, kind):
    target = tmp_path / "nope.nc" if kind == "missing" else tmp_path
    with pytest.raises(DataError, match="does not exist" if kind == "missing" else "folder"):
        GLRM.load(target)


def test_load_round_trip_reads_only(saved, inputs_unchanged):
    inputs_unchanged.watch(saved[0])
    m = GLRM.load(saved[0])
    assert m.noise_std_ == pytest.approx(float(saved[1].attrs["noise_std"]))


# --------------------------------------------------------------------------- evaluate
EV = dict(rank=2, n_test=3, budgets=(3.0,), n_starts=2, methods=("greedy", "random"),
          progress=False, paper=True,
          planning=PlanningOptions(random_trials=2, certify=False),
          scoring=ScoringOptions(min_observations=1))


def test_evaluate_sorts_unsorted_times(field):
    ref = evaluate(field, **EV)
    perm = np.random.default_rng(0).permutation(field.sizes["time"])
    with pytest.warns(UserWarning, match="not sorted"):
        out = evaluate(field.isel(time=perm), **EV)
    last = np.sort(field["time"].values)[-3:]
    np.testing.assert_array_equal(out["test_time"].values, last)  # never tests on the past
    np.testing.assert_allclose(out["mse"].values, ref["mse"].values, equal_nan=True)


def test_evaluate_refuses_duplicated_times(field):
    idx = [0, 1, 2, 3, 3] + list(range(4, field.sizes["time"]))
    with pytest.raises(DataError, match="duplicated times.*2013-01-04"):
        evaluate(field.isel(time=idx), **EV)


def test_evaluate_refuses_missing_times(field):
    t = field["time"].values.copy()
    t[2] = np.datetime64("NaT")
    with pytest.raises(DataError, match="NaN/NaT"):
        evaluate(field.assign_coords(time=t), **EV)


def test_evaluate_needs_a_time_dim(field):
    with pytest.raises(DataError, match="'time' dim"):
        evaluate(field.rename(time="t"), **EV)


@pytest.mark.parametrize("bad,error,match", [
    (dict(n_starts=0), ModelError, "n_starts"),
    (dict(n_starts=-2), ModelError, "n_starts"),
    (dict(n_starts=1.5), ModelError, "n_starts"),
    (dict(planning=PlanningOptions(random_trials=0)), ModelError, "random_trials"),
    (dict(methods=()), ModelError, "methods"),
    (dict(methods=("greedy", "greedy")), ModelError, "repeat"),
    (dict(budgets=()), ModelError, "budgets"),
    (dict(budgets=(np.inf,)), ModelError, "finite"),
    (dict(budgets=(np.nan, 3.0)), ModelError, "finite"),
    (dict(budgets=(-1.0,)), ModelError, "budgets"),
    (dict(budgets=(3.0, 3.0)), ModelError, "repeat"),
    (dict(n_test=0), DataError, "n_test"),
    (dict(n_test=14), DataError, "n_test"),
    (dict(planning={"ridge": 1.0}), ModelError, "planning must be a PlanningOptions"),
    (dict(scoring=PlanningOptions()), ModelError, "scoring must be a ScoringOptions"),
])
def test_evaluate_bad_arguments(field, bad, error, match):
    with pytest.raises(error, match=match):
        evaluate(field, **{**EV, **bad})


@pytest.mark.parametrize("record, bad, match", [
    (PlanningOptions, dict(n_jobs=0), "n_jobs must be an integer >= 1"),
    (PlanningOptions, dict(ridge=-1.0), "ridge"),
    (PlanningOptions, dict(random_trials=-1), "random_trials"),
    (PlanningOptions, dict(random_trials=1.5), "random_trials"),
    (PlanningOptions, dict(certify="yes"), "certify must be False, 'fast' or 'tight'"),
    (PlanningOptions, dict(criterion=3), "criterion must be a string"),
    (ScoringOptions, dict(fold_ridge=np.nan), "fold_ridge"),
    (ScoringOptions, dict(min_observations=-1), "min_observations"),
    (ScoringOptions, dict(fold_in={"prior": "empirical", "kriging": True}), "fold_in keys"),
    (ScoringOptions, dict(model_params=["offset"]), "model_params must be a dict"),
])
def test_evaluation_options_refuse_bad_values_naming_the_field(record, bad, match):
    with pytest.raises(ModelError, match=match) as info:
        record(**bad)
    assert "\n" not in str(info.value)


def test_evaluation_options_normalise_their_values():
    p = PlanningOptions(ridge=1, random_trials=3.0, certify=True, n_jobs=np.int64(2))
    assert (p.ridge, p.random_trials, p.certify, p.n_jobs) == (1.0, 3, "tight", 2)
    assert type(p.random_trials) is int and type(p.n_jobs) is int
    s = ScoringOptions(fold_ridge=0, min_observations=np.int32(4))
    assert (s.fold_ridge, s.min_observations, type(s.min_observations)) == (0.0, 4, int)
    with pytest.raises(AttributeError):
        p.ridge = 2.0  # frozen


@pytest.mark.parametrize("record, bad, match", [
    (SolverOptions, dict(name="nope"), "solver name must be 'auto', 'fast' or 'cvxpy'"),
    (SolverOptions, dict(name=None), "solver name must be"),
    (SolverOptions, dict(init="zeros"), "init must be 'svd' or 'random', got 'zeros'"),
    (SpatialOptions, dict(model="spline"), "spatial model must be 'auto' or one of"),
    (SpatialOptions, dict(model="exponential", anisotropy=0.0), "anisotropy must be a finite"),
    (SpatialOptions, dict(model="exponential", anisotropy="wide"), "anisotropy must be"),
    (SpatialOptions, dict(model="auto", anisotropy=2.0), "applies to a fixed spatial family"),
])
def test_glrm_options_refuse_bad_values_naming_the_field(record, bad, match):
    with pytest.raises(ModelError, match=match) as info:
        record(**bad)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("bad, match", [
    (dict(solver=3), "solver must be 'auto', 'fast', 'cvxpy' or a SolverOptions"),
    (dict(solver="nope"), "solver name must be"),
    (dict(spatial={"model": "exponential"}), "spatial must be None, 'auto', one of"),
    (dict(reg=("ridge",)), r"reg must be one regulariser or a pair \(reg_x, reg_y\)"),
    (dict(reg=["ridge", None, "l1"]), "reg must be one regulariser or a pair"),
    (dict(dask=5), "dask must be None or a mapping"),
    (dict(dask={"chunk": 1}), r"dask: unknown option\(s\) \['chunk'\]"),
    (dict(dask={"keep_dask": "yes"}), r"dask\['keep_dask'\] must be True or False"),
])
def test_glrm_refuses_a_bad_merged_setting_in_one_line(field, bad, match):
    with pytest.raises(ModelError, match=match) as info:
        GLRM(rank=2, **FAST, **bad).fit(field)
    assert "\n" not in str(info.value)


def test_evaluate_random_trials_zero_is_fine_without_random(field):
    planning = PlanningOptions(random_trials=0, certify=False)
    out = evaluate(field, **{**EV, "methods": ("greedy",), "planning": planning})
    assert out.sizes["trial"] == 1 and np.isfinite(out["mse"].values).any()


def test_load_zero_noise_file_warns(saved, tmp_path, inputs_unchanged):
    ds = saved[1].copy()
    ds.attrs = {**ds.attrs, "noise_std": 0.0}
    path = tmp_path / "zero.nc"
    ds.to_netcdf(path)
    inputs_unchanged.watch(path)
    with pytest.warns(UserWarning, match="noise_std 0"):
        GLRM.load(path)


@pytest.mark.parametrize("model,match", [(GLRM(rank=2), "not fitted"), ("m.nc", "GLRM")])
def test_evaluate_refuses_an_unfitted_or_foreign_model(field, model, match):
    with pytest.raises(ModelError, match=match):
        evaluate(field, model=model, **EV)


def test_evaluate_warns_when_the_model_saw_the_test_times(field):
    full = quiet_fit(GLRM(rank=2, max_iter=5, progress=False), field)
    with pytest.warns(UserWarning, match="fitted on 3 of the 3 test times"):
        evaluate(field, model=full, **{**EV, "methods": ("greedy",)})


@pytest.mark.parametrize("tol", ["a", None, -1.0, np.nan])
def test_fit_bad_tol(tol):
    with pytest.raises(ModelError, match="tol"):
        GLRM(rank=1, tol=tol, progress=False).fit(low_rank(5, 6, k=1))


def test_inf_only_snapshot_is_refused_with_count():
    D = low_rank(8, 10)
    D[3] = np.inf
    with pytest.raises(DataError, match="10 non-finite"):
        GLRM(rank=2, progress=False).fit(D)


def test_snapshot_masked_out_entirely_is_refused():
    D = low_rank(8, 10)
    M = np.ones(D.shape, bool)
    M[6] = False
    with pytest.raises(DataError, match=r"positions \[6\]"):
        GLRM(rank=2, progress=False).fit(D, mask=M)


# ------------------------------------------------------------- a constant field
def test_constant_field_warns_and_its_empirical_fold_in_returns_the_constant():
    import pandas as pd

    da = xr.DataArray(np.full((10, 6, 7), 3.0, np.float32), dims=("time", "lat", "lon"),
                      coords={"time": pd.date_range("2000", periods=10),
                              "lat": np.arange(6.0), "lon": np.arange(7.0)})
    with pytest.warns(UserWarning, match="do not vary over time"):
        model = GLRM(2, random_state=0, progress=False).fit(da)
    for ridge in (0.0, 1e-3):  # prior='empirical' was asked: no "use prior='empirical'" error
        out = model.complete(([0, 5, 9], [3.0, 3.0, 3.0]), prior="empirical", ridge=ridge)
        np.testing.assert_allclose(out["prediction"].values, 3.0, rtol=1e-9)
    # a field that varies keeps its prior: no warning, the same moments as before
    rng = np.random.default_rng(0)
    varied = da + xr.DataArray(rng.normal(size=da.shape), dims=da.dims)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        GLRM(2, random_state=0, progress=False).fit(varied)


def test_cells_with_at_most_rank_values_warn_unless_y_is_penalised():
    """A cell with at most ``rank`` values (``rank + 1`` with an offset) has factors that
    interpolate them: a warning counts such cells (fit.warn_sparse_cells), in memory and on
    dask; a ridge on Y bounds them and silences it; more values silence it."""
    rng = np.random.default_rng(2)
    D = low_rank(T=12, L=15) + 0.1 * rng.standard_normal((12, 15))
    D[2:, :3] = np.nan  # three cells seen twice
    for params, count in ((dict(rank=2), 3), (dict(rank=1, offset=True), 3),
                          (dict(rank=1), 0), (dict(rank=2, reg=(None, "ridge")), 0)):
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            GLRM(**params, max_iter=5, progress=False, random_state=0).fit(D)
        hits = [w for w in got if "observed values (rank" in str(w.message)]
        assert len(hits) == (1 if count else 0), params
        if count:
            assert str(hits[0].message).startswith(f"{count} of 15 cells have at most 2 ")
            assert hits[0].filename == __file__
    da = pytest.importorskip("dask.array")
    with pytest.warns(UserWarning, match="3 of 15 cells have at most 2 observed values") as rec:
        GLRM(rank=2, max_iter=2, progress=False, random_state=0).fit(
            da.from_array(D, chunks=(4, -1)))
    assert any(w.filename == __file__ for w in rec if "observed values" in str(w.message))


# --------------------------------------------------------------- model files are untrusted input
def _swap_dataset(path, name, **create):
    """Replace the variable ``name`` of the HDF5 file ``path`` by a dataset made with
    ``create`` (``external=...`` or ``layout=...``), keeping its attributes and dimensions, so
    netCDF readers take it for the original variable."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "r+") as h:
        old = h[name]
        shape, dtype = old.shape, old.dtype
        attrs = {k: v for k, v in old.attrs.items()
                 if k not in ("DIMENSION_LIST", "_Netcdf4Dimid")}
        scales = [old.dims[i][0].name for i in range(old.ndim)]
        for i, scale in enumerate(scales):
            old.dims[i].detach_scale(h[scale])
        del h[name]
        if "layout" in create:
            new = h.create_virtual_dataset(name, create["layout"])
        else:
            new = h.create_dataset(name, shape=shape, dtype=dtype, external=create["external"])
        for k, v in attrs.items():
            new.attrs[k] = v
        for i, scale in enumerate(scales):
            new.dims[i].attach_scale(h[scale])
    return shape


def _secret(tmp_path, n):
    """A file outside the model ("the password file") whose bytes are recognisable floats."""
    path = tmp_path / "secret.bin"
    np.arange(n, dtype="<f8").tofile(path)
    return path


def _one_line_refusal(exc_info, path, *needles):
    text = str(exc_info.value)
    assert "\n" not in text and repr(str(path)) in text, text
    for needle in needles:
        assert needle in text, (needle, text)


def test_load_refuses_external_storage(saved, tmp_path, inputs_unchanged):
    import shutil

    bad = tmp_path / "external.nc"
    shutil.copy(saved[0], bad)
    n = int(np.prod(saved[1]["Y"].shape))
    secret = _secret(tmp_path, n)
    _swap_dataset(bad, "Y", external=[(str(secret), 0, 8 * n)])
    with xr.open_dataset(bad) as f:  # the crafted file reads the other file's bytes as Y
        np.testing.assert_array_equal(f["Y"].values.ravel(), np.arange(n))
    inputs_unchanged.watch(bad, secret)
    with pytest.raises(DataError) as exc:
        GLRM.load(bad)
    _one_line_refusal(exc, bad, "variable 'Y' uses external storage", str(secret))


def test_load_refuses_a_virtual_dataset(saved, tmp_path, inputs_unchanged):
    import shutil

    h5py = pytest.importorskip("h5py")
    shape = saved[1]["Y"].shape
    source = tmp_path / "source.h5"
    with h5py.File(source, "w") as f:
        f["data"] = np.arange(np.prod(shape), dtype=np.float64).reshape(shape)
    layout = h5py.VirtualLayout(shape=shape, dtype="f8")
    layout[:] = h5py.VirtualSource(str(source), "data", shape=shape)
    bad = tmp_path / "virtual.nc"
    shutil.copy(saved[0], bad)
    _swap_dataset(bad, "Y", layout=layout)
    with xr.open_dataset(bad) as f:
        assert f["Y"].values[0, 1] == 1.0  # read from the other file
    inputs_unchanged.watch(bad, source)
    with pytest.raises(DataError) as exc:
        GLRM.load(bad)
    _one_line_refusal(exc, bad, "variable 'Y' is a virtual dataset", str(source))


def test_load_refuses_an_external_link(saved, tmp_path, inputs_unchanged):
    import shutil

    h5py = pytest.importorskip("h5py")
    source = tmp_path / "other.h5"
    with h5py.File(source, "w") as f:
        f.create_group("g")["v"] = np.arange(3.0)
    bad = tmp_path / "linked.nc"
    shutil.copy(saved[0], bad)
    with h5py.File(bad, "r+") as f:
        f["extra"] = h5py.ExternalLink(str(source), "/g")
    GLRM.load(saved[0])  # the same file without the link loads
    inputs_unchanged.watch(bad, source)
    with pytest.raises(DataError) as exc:
        GLRM.load(bad)
    _one_line_refusal(exc, bad, "external link 'extra'", str(source))


def test_load_netcdf3_model_is_not_taken_for_hdf5(saved, tmp_path, inputs_unchanged):
    # NetCDF-3 has no external storage: a classic file loads as before
    ds = saved[1].copy()
    ds.encoding = {}
    for v in ds.variables.values():
        v.encoding = {}
    path = tmp_path / "classic.nc"
    ds.to_netcdf(path, format="NETCDF3_64BIT")
    assert path.read_bytes()[:3] == b"CDF"
    inputs_unchanged.watch(path)
    np.testing.assert_allclose(GLRM.load(path).Y_.values, saved[1]["Y"].values)


def test_load_refuses_non_finite_factors(saved, tmp_path, inputs_unchanged):
    ds = saved[1].copy()
    X = ds["X"].values.copy()
    X[1, 3] = np.nan
    ds["X"] = (ds["X"].dims, X)
    bad = tmp_path / "nan.nc"
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match=r"nan\.nc' has 1 non-finite value.*factor X"):
        GLRM.load(bad)


@pytest.mark.parametrize("attr", ["params", "region_attrs"])
def test_load_deeply_nested_json_attribute(saved, tmp_path, inputs_unchanged, attr):
    ds = saved[1].copy()
    depth = 100_000
    ds.attrs = {**ds.attrs, attr: '{"a": ' * depth + "1" + "}" * depth}
    bad = tmp_path / "deep.nc"
    ds.to_netcdf(bad)
    inputs_unchanged.watch(bad)
    with pytest.raises(DataError, match=f"'{attr}' is JSON nested too deeply"):
        GLRM.load(bad)


def test_load_refuses_a_fifo_and_a_symlink_loop(tmp_path):
    fifo = tmp_path / "model.nc"
    os.mkfifo(fifo)  # opening it would wait for a writer forever
    with pytest.raises(DataError, match="model.nc is not a regular file"):
        GLRM.load(fifo)
    loop = tmp_path / "loop.nc"
    loop.symlink_to(loop)
    with pytest.raises(DataError, match="loop.nc is a symlink loop"):
        GLRM.load(loop)
