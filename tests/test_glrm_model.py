"""GLRM estimator: xarray edge, fold-in, completion, scoring, persistence, bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.belief import fold_in, fold_in_many
from lrm_cvx.errors import ConvergenceWarning, DataError, ModelError, NotFittedError
from lrm_cvx.glrm import GLRM, L1, Huber, Quadratic, Ridge, SolverOptions, SpatialOptions
from lrm_cvx.glrm.calibrated import prediction_factor
from lrm_cvx.region import Region


def field(T=12, ny=6, nx=7, k=2, noise=0.05, seed=0):
    rng = np.random.default_rng(seed)
    vals = (rng.standard_normal((T, k)) @ rng.standard_normal((k, ny * nx))).reshape(T, ny, nx)
    vals += noise * rng.standard_normal(vals.shape)
    vals[rng.random(vals.shape) < 0.3] = np.nan
    vals[:, 0, 0] = np.nan  # a cell never observed: left out of the region
    da = xr.DataArray(
        vals.astype(np.float32), dims=("time", "lat", "lon"),
        coords={"time": np.arange(T), "lat": np.linspace(50, 45, ny), "lon": np.arange(nx) + 5.},
        name="ndvi",
    )
    return da


def fitted(**kw):
    params = dict(rank=2, progress=False, random_state=0, max_iter=50, tol=1e-8)
    params.update(kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return GLRM(**params).fit(field())


def test_fit_dataarray_outputs():
    m = fitted()
    da = field()
    assert m.X_.dims == ("component", "time") and m.Y_.dims == ("component", "cell")
    assert m.Y_.sizes["cell"] == m.region_.n_cells == 6 * 7 - 1
    np.testing.assert_array_equal(m.Y_["lat"].values, m.region_.cell_lat)
    assert m.Y_grid.dims == ("component", "lat", "lon")
    assert np.isnan(m.Y_grid.values[:, 0, 0]).all()
    rec = m.reconstruct()
    assert rec.dims == ("time", "lat", "lon") and rec.shape == da.shape
    np.testing.assert_allclose(
        m.region_.stack(rec), (m.X_.values.T @ m.Y_.values).astype(np.float32), rtol=1e-6)
    assert m.objective_.ndim == 1 and m.n_iter_ >= 1 and m.noise_std_ > 0
    assert len(m.unobserved_cells_) == 0
    # array input gives ndarrays and the same factors
    mr = GLRM(rank=2, progress=False, random_state=0, max_iter=50, tol=1e-8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        mr.fit(m.region_.stack(da))
    assert isinstance(mr.X_, np.ndarray)
    np.testing.assert_allclose(mr.X_, m.X_.values)


def test_mask_input_is_not_copied_and_ignores_outside():
    rng = np.random.default_rng(1)
    D = rng.standard_normal((8, 30)).astype(np.float32)
    M = rng.random((8, 30)) < 0.6
    D2 = D.copy()
    D2[~M] = np.inf  # garbage outside the mask is ignored
    m = GLRM(rank=2, progress=False, random_state=0, max_iter=5, tol=0).fit(D2, mask=M)
    ref = GLRM(rank=2, progress=False, random_state=0, max_iter=5, tol=0).fit(
        np.where(M, D, np.nan))
    np.testing.assert_allclose(m.X_, ref.X_, rtol=1e-10)
    D_in, _, _, _, owned = m._prepare(D2, M, None)
    assert D_in is D2 and not owned
    assert np.isinf(D2[~M]).all()  # the fit zero-fills a copy, never the caller's array


def test_fit_leaves_callers_nan_arrays_alone():
    da = field()
    region = Region.from_dataarray(da)
    stacked = xr.DataArray(region.stack(da), dims=("time", "cell"))  # a view for the fit
    for data, kw in [(da, {}), (stacked, {"region": region}), (region.stack(da), {})]:
        keep = np.array(data, copy=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            GLRM(rank=2, progress=False, max_iter=3).fit(data, **kw)
        np.testing.assert_array_equal(np.asarray(data), keep)  # NaN still in place


def test_same_seed_same_result():
    rand = SolverOptions(init="random")
    a, b = fitted(solver=rand, random_state=3), fitted(solver=rand, random_state=3)
    np.testing.assert_array_equal(a.X_.values, b.X_.values)
    np.testing.assert_array_equal(a.Y_.values, b.Y_.values)


def test_fold_in_equals_lstsq_and_ridge_formula():
    rng = np.random.default_rng(2)
    Y = rng.standard_normal((3, 500))
    cells = np.array([4, 90, 33, 250, 7, 400])
    d = rng.standard_normal(6)
    x, cov = fold_in(Y, cells, d, noise_std=0.5)
    ref = np.linalg.lstsq(Y[:, cells].T, d, rcond=None)[0]
    np.testing.assert_allclose(x, ref, rtol=1e-10)
    np.testing.assert_allclose(cov, 0.25 * np.linalg.inv(Y[:, cells] @ Y[:, cells].T))
    xr_, _ = fold_in(Y, cells[:2], d[:2], ridge=0.3)
    A = Y[:, cells[:2]] @ Y[:, cells[:2]].T + 0.3 * np.eye(3)
    np.testing.assert_allclose(xr_, np.linalg.solve(A, Y[:, cells[:2]] @ d[:2]))
    with pytest.raises(ModelError):
        fold_in(Y, cells[:2], d[:2])
    with pytest.raises(ModelError):
        fold_in(np.ones((3, 10)), np.arange(5), np.ones(5))  # rank-deficient Y_S
    # batched version agrees
    V = np.full((2, 500), np.nan)
    V[0, cells] = d
    V[1, cells[:4]] = d[:4]
    xb, covb, n = fold_in_many(Y, V, noise_std=0.5)
    np.testing.assert_allclose(xb[0], x, rtol=1e-10)
    np.testing.assert_allclose(covb[0], cov, rtol=1e-10)
    assert n.tolist() == [6, 4]


def test_complete_outputs_and_std_shrinks():
    m = fitted()
    da = field()
    snap = da.isel(time=3)
    ds = m.complete(snap)
    assert ds["prediction"].dims == ("lat", "lon") and ds["std"].dims == ("lat", "lon")
    assert ds["x"].dims == ("component",) and ds.attrs["n_observations"] == int(
        np.isfinite(m.region_.stack(snap)).sum())
    # matches the fold-in on the same cells
    vals = m.region_.stack(snap)
    obs = np.flatnonzero(np.isfinite(vals))
    # the noise of a new snapshot: noise_std_^2 n / (n - k) (calibrated.prediction_factor),
    # n the observed values per observed cell (30 % missing), k the rank (no offset)
    D = field().values
    n = np.isfinite(D).sum() / np.isfinite(D).any(axis=0).sum()
    assert prediction_factor(m) == pytest.approx(n / (n - 2), rel=1e-12)
    s_new = m.noise_std_ * np.sqrt(n / (n - 2))
    assert ds.attrs["noise_std"] == pytest.approx(s_new, rel=1e-12)  # what docs/model.md adds
    x, cov = fold_in(m.Y_.values, obs, vals[obs], noise_std=s_new)
    np.testing.assert_allclose(ds["x"].values, x)
    np.testing.assert_allclose(m.region_.stack(ds["prediction"]), (m.Y_.values.T @ x), rtol=1e-6)
    y = m.Y_.values
    std_ref = np.sqrt(np.einsum("ai,ab,bi->i", y, cov, y))
    np.testing.assert_allclose(m.region_.stack(ds["std"]), std_ref, rtol=1e-5)
    # adding observations never increases the standard error
    s_few = m.complete({0: 1.0, 5: 0.2, 9: -0.3})["std"]
    s_more = m.complete({0: 1.0, 5: 0.2, 9: -0.3, 20: 0.5, 30: 0.1})["std"]
    assert np.all(m.region_.stack(s_more) <= m.region_.stack(s_few) + 1e-12)
    # tuple input equals mapping input
    a = m.complete((np.array([0, 5, 9]), np.array([1.0, 0.2, -0.3])))
    xr.testing.assert_allclose(a["prediction"], m.complete({0: 1.0, 5: 0.2, 9: -0.3})[
        "prediction"])
    # a stack of snapshots, vectorised, equals the single ones
    st = m.complete(da.isel(time=slice(2, 5)))
    assert st["prediction"].dims == ("time", "lat", "lon")
    xr.testing.assert_allclose(st["prediction"].isel(time=1, drop=True),
                               ds["prediction"].drop_vars("time", errors="ignore"))
    with pytest.raises(ModelError):
        m.complete({0: 1.0})  # fewer observations than the rank
    assert np.all(np.isfinite(m.region_.stack(m.complete({0: 1.0}, ridge=0.5)["prediction"])))


def test_array_model_complete_dims_cell():
    rng = np.random.default_rng(4)
    D = rng.standard_normal((6, 20))
    m = GLRM(rank=2, progress=False, max_iter=3, tol=0).fit(D)
    ds = m.complete(np.where(rng.random(20) < 0.5, D[0], np.nan))
    assert ds["prediction"].dims == ("cell",)
    ds2 = m.complete(np.where(rng.random((3, 20)) < 0.5, D[:3], np.nan))
    assert ds2["prediction"].dims == ("snapshot", "cell")


def test_score_holdout_and_select_rank():
    m = fitted()
    da = field()
    train, test = GLRM.holdout(da, 0.2, seed=0)
    n_obs = int(np.isfinite(da).sum())
    assert int(np.isfinite(train).sum()) + int(np.isfinite(test).sum()) == n_obs
    assert not bool((np.isfinite(train) & np.isfinite(test)).any())
    s = m.score(da)
    vals = m.region_.stack(da)
    ok = np.isfinite(vals)
    ref = np.mean(((m.X_.values.T @ m.Y_.values) - vals)[ok] ** 2)
    assert np.isclose(s, ref, rtol=1e-5)
    sel = GLRM(progress=False, max_iter=30, random_state=0).select_rank(da, [1, 2], seed=0)
    rmse = sel["rmse"].values
    assert sel["rank"].values.tolist() == [1, 2] and np.all(rmse > 0)
    assert rmse[1] < rmse[0]  # planted rank 2 beats rank 1
    assert sel.attrs["choice"] == 2
    np.testing.assert_allclose(rmse ** 2, sel["mse"].values[:, 0], rtol=1e-12)


def test_save_load_round_trip(tmp_path):
    m = fitted(loss=Huber(0.5), reg=(None, Ridge(0.01)))
    p = tmp_path / "model.nc"
    m.save(p)
    m2 = GLRM.load(p)
    xr.testing.assert_identical(m2.X_, m.X_)
    xr.testing.assert_identical(m2.Y_, m.Y_)
    assert m2.region_.equals(m.region_)
    np.testing.assert_array_equal(m2.objective_, m.objective_)
    assert m2.noise_std_ == m.noise_std_ and m2.get_params()["loss"] == Huber(0.5)
    obs = {0: 0.1, 3: 0.2, 8: 0.3}
    xr.testing.assert_identical(m.complete(obs), m2.complete(obs))
    bad = tmp_path / "other.nc"
    xr.Dataset({"a": ("x", [1.0])}).to_netcdf(bad)
    with pytest.raises(DataError, match="other.nc"):
        GLRM.load(bad)
    junk = tmp_path / "junk.nc"
    junk.write_text("not netcdf")
    with pytest.raises(DataError, match="junk.nc"):
        GLRM.load(junk)


def test_merged_settings_round_trip(tmp_path):
    """A model fitted with a non-default value of every merged setting (a pair of
    regularisers, a solver record with the random init, an anisotropic spatial record, dask
    options) loads back with the same parameters and the same predictions."""
    spatial = SpatialOptions("exponential", anisotropy=1.5)
    m = fitted(loss=Quadratic(), reg=(Ridge(0.1), L1(0.01)),
               solver=SolverOptions("fast", init="random"), spatial=spatial,
               dask={"chunk_mb": 0.5, "keep_dask": True}, max_iter=5)
    assert m.spatial_cov_.anisotropy == 1.5 and m.solver_ == "fast"
    m.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    assert back.get_params() == m.get_params()
    assert back.reg == (Ridge(0.1), L1(0.01)) and back.spatial == spatial
    assert back.solver == SolverOptions("fast", "random")
    assert back.dask == {"chunk_mb": 0.5, "keep_dask": True}
    assert back.spatial_cov_ == m.spatial_cov_
    obs = {0: 0.1, 3: 0.2, 8: 0.3}
    xr.testing.assert_identical(back.complete(obs, prior="empirical", spatial=True),
                                m.complete(obs, prior="empirical", spatial=True))
    # one regulariser is both factors': the same fit as the pair of it
    np.testing.assert_array_equal(fitted(reg="ridge", max_iter=5).Y,
                                  fitted(reg=("ridge", "ridge"), max_iter=5).Y)


def test_a_file_with_the_separate_settings_loads_merged(tmp_path):
    """A model file whose params hold ``reg_x``/``reg_y``, ``init``, ``anisotropy``,
    ``keep_dask``/``dask_options`` reads back with ``reg``, ``solver``, ``spatial``, ``dask``."""
    import json

    m = fitted(spatial="exponential", max_iter=3)
    m.save(tmp_path / "m.nc")
    with xr.open_dataset(tmp_path / "m.nc") as f:
        ds = f.load()
    params = {k: v for k, v in json.loads(ds.attrs["params"]).items()
              if k not in ("reg", "dask")}
    ds.attrs["params"] = json.dumps({**params, "reg_x": None, "reg_y": "ridge",
                                     "init": "random", "anisotropy": 2.0, "keep_dask": True,
                                     "dask_options": {"chunk_mb": 3}})
    ds.to_netcdf(tmp_path / "separate.nc")
    back = GLRM.load(tmp_path / "separate.nc")
    assert back.reg == (None, "ridge")
    assert back.solver == SolverOptions("auto", "random")
    assert back.spatial == SpatialOptions("exponential", 2.0)
    assert back.dask == {"chunk_mb": 3, "keep_dask": True}
    assert "init" not in back.get_params() and "anisotropy" not in back.get_params()


def test_custom_regulariser_saved_as_repr(tmp_path):
    import cvxpy as cp

    rng = np.random.default_rng(5)
    D = rng.standard_normal((6, 10))
    m = GLRM(rank=2, reg=(None, lambda V: 0.1 * cp.sum_squares(V)), progress=False, max_iter=2,
             tol=0).fit(D)
    assert m.solver_ == "cvxpy"
    m.save(tmp_path / "c.nc")
    with pytest.warns(UserWarning, match="custom"):
        m2 = GLRM.load(tmp_path / "c.nc")
    assert m2.reg[1] is None
    np.testing.assert_array_equal(m2.Y_, m.Y_)


def test_params_and_errors():
    m = GLRM(rank=3, loss="huber")
    assert m.get_params()["rank"] == 3 and "loss='huber'" in repr(m)
    assert m.set_params(rank=2).rank == 2
    with pytest.raises(ModelError):
        m.set_params(bogus=1)
    with pytest.raises(NotFittedError):
        m.complete({0: 1.0})
    rng = np.random.default_rng(6)
    D = rng.standard_normal((5, 8))
    with pytest.raises(ModelError):
        GLRM(rank=0, progress=False).fit(D)
    with pytest.raises(ModelError):
        GLRM(rank=6, progress=False).fit(D)
    with pytest.raises(ModelError):
        GLRM(loss="nope", progress=False).fit(D)
    with pytest.raises(DataError):
        GLRM(rank=1, progress=False).fit(np.full((3, 4), np.nan))
    bad = D.copy()
    bad[1, 1] = np.inf
    with pytest.raises(DataError):
        GLRM(rank=1, progress=False).fit(bad)
    with pytest.raises(DataError):
        GLRM(rank=1, progress=False).fit(D[0])
    with pytest.raises(DataError):
        GLRM(rank=1, progress=False).fit(xr.DataArray(D, dims=("a", "b")))
    with pytest.raises(DataError):
        GLRM(rank=1, progress=False).fit(D, mask=np.ones((2, 2), bool))
    D2 = D.copy()
    D2[2] = np.nan
    with pytest.raises(DataError, match="no observation"):
        GLRM(rank=1, progress=False).fit(D2)
    D3 = D.copy()
    D3[rng.random(D.shape) < 0.4] = np.nan
    D3[:, 0] = D[:, 0]
    with pytest.warns(ConvergenceWarning):
        GLRM(rank=2, progress=False, max_iter=1, tol=1e-12,
             solver=SolverOptions(init="random")).fit(D3)


def test_region_given_with_unobserved_cell():
    da = field()
    region = Region.from_dataarray(da, mask=np.ones((6, 7), bool))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        m = GLRM(rank=2, progress=False, max_iter=5).fit(da, region=region)
    assert m.unobserved_cells_.tolist() == [0]
    assert np.all(m.Y_.values[:, 0] == 0)


def test_is_plain_low_rank_tracks_the_predictive_options():
    assert fitted().is_plain_low_rank
    for kw in ({"offset": True}, {"scale": True}, {"noise": "per-cell"}):
        m = fitted(**kw)
        assert not m.is_plain_low_rank
        # so complete() goes through the predictive model, not the plain least squares
        obs = {0: 1.0, 5: 2.0, 9: -1.0}
        plain = fitted().complete(obs)
        assert not np.allclose(m.complete(obs)["std"].values, plain["std"].values,
                               equal_nan=True)


def test_negative_or_non_numeric_weights_and_ridge_are_named():
    with pytest.raises(ModelError, match="Ridge weight"):
        Ridge(-1.0)
    with pytest.raises(ModelError, match="L1 weight"):
        L1("heavy")
    with pytest.raises(ModelError, match="ridge"):
        fitted().complete({0: 1.0, 5: 2.0}, ridge=-0.5)
    Y = np.eye(2, 5)
    with pytest.raises(ModelError, match="ridge"):
        fold_in(Y, [0, 1], [1.0, 2.0], ridge=float("nan"))
