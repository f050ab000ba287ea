"""The noise of a new measurement in a spatial model (item 3a): the nugget's floor
(the fit's sub-cell variation), and the fitted model's posterior mean and predictive std
against a dense brute-force GP (trend prior + kernel + nugget) on tiny inputs."""

import copy
import warnings

import numpy as np
import pytest
import xarray as xr
from scipy.spatial.distance import cdist

from lrm_cvx import GLRM
from lrm_cvx.belief.posterior import LatentPosterior, empirical_moments
from lrm_cvx.errors import ModelError
from lrm_cvx.glrm.predictive import residual_sample
from lrm_cvx.spatial import ResidualCovariance, fit_residual_covariance
from lrm_cvx.spatial.covariance import cell_semivariance, cell_size


def smooth_field(T=30, ny=10, nx=12, seed=0):
    """A rank-2 trend plus a smooth (Gaussian-kernel, no nugget) residual: the exponential
    variogram's fitted nugget collapses to 0 on it."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:ny, 0:nx].astype(float)
    pats = np.stack([np.sin(xx / 3.0) + 0.1 * yy, np.cos(yy / 2.5) * 0.5 + xx / nx])
    g = np.column_stack([yy.ravel(), xx.ravel()])
    K = 0.3 * np.exp(-(cdist(g, g) / 3.0) ** 2) + 1e-8 * np.eye(g.shape[0])
    res = (np.linalg.cholesky(K) @ rng.standard_normal((g.shape[0], T))).T
    X = rng.normal(size=(T, 2)) * [2.0, 1.0]
    vals = 10.0 + X @ pats.reshape(2, -1) + res
    return xr.DataArray(vals.reshape(T, ny, nx).astype(np.float64), dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T), "lat": 30.0 + np.arange(ny),
                                "lon": 200.0 + np.arange(nx)})


@pytest.fixture(scope="module")
def fitted():
    data = smooth_field()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, offset=True, spatial="exponential", random_state=0,
                     progress=False).fit(data)
    return data, model


def test_cell_semivariance_equals_monte_carlo():
    rng = np.random.default_rng(1)
    for model, size in (("exponential", (1.0, 1.0)), ("matern32", (2.0, 0.5)),
                        ("gaussian", (1.0, 3.0))):
        cov = ResidualCovariance(model, sill=2.0, range=1.7, nugget=0.0)
        u = rng.random((400_000, 2)) * size
        w = rng.random((400_000, 2)) * size
        mc = np.mean(cov.semivariogram(np.linalg.norm(u - w, axis=1)))
        assert cell_semivariance(cov, size) == pytest.approx(mc, rel=5e-3)
        assert cov.cell_semivariance(size) == cell_semivariance(cov, size)


def test_the_nugget_no_longer_collapses(fitted):
    data, model = fitted
    region = model.region_
    V = region.stack(data).astype(np.float64)
    Z = (V - model.offset_) / 1.0
    R = residual_sample(Z, np.isfinite(Z), model._Xv, model._Yv)
    free = fit_residual_covariance(R, region, model="exponential", random_state=0)
    assert free.nugget < 1e-3 * free.sill  # the diagnosis: an exact interpolator
    cov = model.spatial_cov_
    floor = cov.cell_semivariance(cell_size(region, cov.metric))
    assert floor > 0.1 * float(cov.semivariogram(1.0))  # a sizeable part of the lag-1 variance
    assert cov.nugget >= floor * (1 - 1e-9)
    # the model's covariance is this function's fit with min_nugget="cell" to the residuals
    # times sqrt(n / (n - k)): 30 snapshots, k = rank 2 + the offset (calibrated.residual_dof)
    again = fit_residual_covariance(R * np.sqrt(30 / 27), region, model="exponential",
                                    random_state=0, min_nugget="cell")
    for name in ("sill", "range", "nugget"):
        assert getattr(again, name) == pytest.approx(getattr(cov, name), rel=1e-6)
    # a numeric floor is honoured; a bad one is a one-line error naming the argument
    assert fit_residual_covariance(R, region, min_nugget=0.05).nugget >= 0.05
    for bad in ("point", -1.0, np.nan):
        with pytest.raises(ModelError, match="min_nugget"):
            fit_residual_covariance(R, region, min_nugget=bad)


def test_cell_size_in_km_follows_the_grid():
    data = smooth_field(T=3, ny=4, nx=5)
    data = data.assign_coords(lat=60.0 + 2.0 * np.arange(4), lon=10.0 + 2.0 * np.arange(5))
    from lrm_cvx import Region

    region = Region.from_dataarray(data.isel(time=0))
    dy, dx = cell_size(region, "km")
    assert dy == pytest.approx(6371.0088 * np.radians(2.0), rel=1e-3)
    assert dx == pytest.approx(dy * np.cos(np.radians(region.cell_lat.mean())), rel=2e-2)
    assert cell_size(region, "grid") == (1.0, 1.0)


def brute_force(model, cells, values):
    """Dense GP: value = offset + y^T x + r + e, x ~ N(mean(X), cov(X)), r ~ GP(sill, range),
    e ~ N(0, nugget) (sill and nugget times the model's ``residual_inflation_`` and a new
    snapshot's ``n / (n - k)``: rank 2 + offset, 30 snapshots); the conditional of the
    noise-free value at every cell given the samples, and the std of a new measurement."""
    cov = model.spatial_cov_
    r = getattr(model, "residual_inflation_", 1.0) * (30 / 27)
    cov = ResidualCovariance(model=cov.model, sill=cov.sill * r, range=cov.range,
                             nugget=cov.nugget * r, metric=cov.metric)
    Y = model._Yv
    m0, S0 = empirical_moments(model._Xv)
    g = model.region_.grid_index.astype(float)
    K = Y.T @ S0 @ Y + cov.sill * cov.correlation(cdist(g, g))
    mu = Y.T @ m0
    A = K[np.ix_(cells, cells)] + cov.nugget * np.eye(cells.size)
    z = values - model.offset_[cells]
    mean = model.offset_ + mu + K[:, cells] @ np.linalg.solve(A, z - mu[cells])
    var = np.diag(K - K[:, cells] @ np.linalg.solve(A, K[cells, :]))
    return mean, np.sqrt(var), np.sqrt(var + cov.nugget)


@pytest.mark.parametrize("inflation", [1.0, 4.0])
@pytest.mark.parametrize("n", [3, 9])
def test_fitted_spatial_model_equals_the_brute_force_gp(fitted, n, inflation):
    """Also with a validated residual inflation (temporal="auto"'s ``residual_inflation_``):
    every variance of the residual and of a new measurement is that factor times."""
    data, model = fitted
    model = copy.copy(model)
    model.residual_inflation_ = inflation
    rng = np.random.default_rng(n)
    V = model.region_.stack(data.isel(time=-1)).astype(np.float64)
    cells = np.sort(rng.choice(model.n_cells_, n, replace=False))
    post = LatentPosterior.prior(model, "empirical").update(cells, V[cells])
    mean, std, pstd = post.predict_all()
    b_mean, b_std, b_pstd = brute_force(model, cells, V[cells])
    np.testing.assert_allclose(mean, b_mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(std, b_std, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(pstd, b_pstd, rtol=1e-7)
    np.testing.assert_allclose(post.predictive_std(), b_pstd, rtol=1e-7)
    # at the sampled cells: not an exact interpolator, and a new measurement's std is
    # sqrt(std^2 + noise) > 0
    nug = model.spatial_cov_.nugget * inflation * (30 / 27)
    assert np.all(std[cells] > 0.05 * np.sqrt(nug))
    np.testing.assert_allclose(pstd[cells], np.sqrt(std[cells] ** 2 + nug), rtol=1e-10)
    assert np.all(pstd[cells] >= np.sqrt(nug))
    # the model-level helper agrees (data units, uncalibrated)
    from lrm_cvx.glrm.calibrated import predictive_std

    np.testing.assert_allclose(predictive_std(model, std, spatial=True), pstd, rtol=1e-10)


def _edgy_field():
    data = smooth_field(seed=3)
    noisy = data.copy(deep=True)
    rng = np.random.default_rng(4)
    noisy[:, :, :4] += rng.normal(0, 1.0, noisy[:, :, :4].shape)  # a noisier western edge
    return noisy


@pytest.mark.parametrize("noise", ["global", "per-cell"])
def test_residual_scale_makes_the_spatial_residual_heteroscedastic(noise):
    """``scale="residual"``: the same low-rank fit, then ``r_j + e_j = s_j (g_j + e'_j)``,
    ``s`` the per-cell residual std relative to the global one; the fitted model's posterior
    equals a dense GP with that covariance, and the covariance is fitted to the residuals over
    ``s``."""
    from lrm_cvx.glrm.predictive import NOISE_PRIOR_DF, residual_moments, shrink_noise

    noisy = _edgy_field()
    kw = dict(rank=2, offset=True, spatial="exponential", random_state=0, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = GLRM(**kw).fit(noisy)
        model = GLRM(scale="residual", noise=noise, **kw).fit(noisy)
    region = model.region_
    Z = region.stack(noisy).astype(np.float64) - model.offset_
    # the low-rank fit is unchanged: reconstruct() equals the plain model's
    np.testing.assert_allclose(model.reconstruct().values, base.reconstruct().values,
                               rtol=1e-9, atol=1e-9)
    sse, cnt = residual_moments(Z, np.isfinite(Z), base._Xv, base._Yv)
    sig2 = base.noise_std_ ** 2
    s = np.sqrt(shrink_noise(sse * sig2 * cnt.sum() / sse.sum(), cnt, sig2, NOISE_PRIOR_DF)
                / sig2)
    np.testing.assert_allclose(model.scale_, s, rtol=1e-6)  # the fit's float32 residuals
    np.testing.assert_allclose(model._Yv * model.scale_, base._Yv, rtol=1e-12, atol=1e-14)
    west = region.grid_index[:, 1] < 4
    assert s[west].mean() > 1.4 * s[~west].mean()
    if noise == "per-cell":  # the per-cell noise in the new (standardised) fit units
        np.testing.assert_allclose(model.noise_var_ * s ** 2,
                                   shrink_noise(sse * sig2 * cnt.sum() / sse.sum(), cnt, sig2,
                                                NOISE_PRIOR_DF), rtol=1e-6)
    R = residual_sample(Z, np.isfinite(Z), base._Xv, base._Yv) / model.scale_
    R = R * np.sqrt(30 / 27)  # calibrated.residual_dof: 30 snapshots, rank 2 + offset
    again = fit_residual_covariance(R.astype(np.float32), region, model="exponential",
                                    random_state=0, min_nugget="cell")
    for name in ("sill", "range", "nugget"):
        assert getattr(again, name) == pytest.approx(getattr(model.spatial_cov_, name), rel=1e-6)

    cov, Y, s = model.spatial_cov_, base._Yv, model.scale_  # the dense GP in data units
    cov = ResidualCovariance(model=cov.model, sill=cov.sill * 30 / 27, range=cov.range,
                             nugget=cov.nugget * 30 / 27)  # a new snapshot's: n / (n - k)
    m0, S0 = empirical_moments(model._Xv)
    g = region.grid_index.astype(float)
    K = Y.T @ S0 @ Y + np.outer(s, s) * cov.sill * cov.correlation(cdist(g, g))
    rng = np.random.default_rng(5)
    cells = np.sort(rng.choice(model.n_cells_, 8, replace=False))
    V = region.stack(noisy.isel(time=-1)).astype(np.float64)
    mu = Y.T @ m0
    A = K[np.ix_(cells, cells)] + np.diag(cov.nugget * s[cells] ** 2)
    want = model.offset_ + mu + K[:, cells] @ np.linalg.solve(
        A, V[cells] - model.offset_[cells] - mu[cells])
    var = np.diag(K - K[:, cells] @ np.linalg.solve(A, K[cells, :]))
    post = LatentPosterior.prior(model, "empirical").update(cells, V[cells])
    mean, std, pstd = post.predict_all()
    np.testing.assert_allclose(mean, want, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(std, np.sqrt(var), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(pstd, np.sqrt(var + cov.nugget * s ** 2), rtol=1e-7)
    from lrm_cvx.glrm.calibrated import predictive_std

    np.testing.assert_allclose(predictive_std(model, std, spatial=True), pstd, rtol=1e-10)


def test_residual_scale_saves_refits_and_rejects_bad_values(tmp_path):
    from lrm_cvx.validation.refits import clone_model

    noisy = _edgy_field()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, offset=True, spatial="exponential", scale="residual",
                     random_state=0, progress=False).fit(noisy)
        path = tmp_path / "m.nc"
        model.save(path)
        back = GLRM.load(path)
        np.testing.assert_array_equal(back.scale_, model.scale_)
        np.testing.assert_array_equal(back._Yv, model._Yv)
        assert back.scale == "residual"
        again = clone_model(model).fit(noisy)
    np.testing.assert_allclose(again.scale_, model.scale_, rtol=1e-9)
    for bad in ("data", 2):
        with pytest.raises(ModelError, match="scale must be True, False or 'residual'"):
            GLRM(rank=2, scale=bad).fit(noisy)


def test_a_new_snapshot_errs_as_much_as_the_model_says():
    """A planted rank-10 field plus unit white noise, 25 training snapshots: a cell's 11
    parameters (factors and offset) absorb 11/25 of its training residuals' variance and err
    at a new time. ``spatial_cov_`` estimates the noise itself (residual_dof; the training
    residuals' variogram gives 14/25 of it), and a new snapshot's residual (its latent row
    fitted on every cell) has ``n / (n - k)`` times that variance (prediction_factor), which is
    what the fold-in, the plans and the intervals use (residual_factor, noise_variance)."""
    from lrm_cvx.glrm.calibrated import (
        noise_variance,
        prediction_factor,
        residual_dof,
        residual_factor,
    )

    rng = np.random.default_rng(0)
    ny, nx, k, T, new = 30, 40, 10, 25, 40
    L = ny * nx
    Y, X = rng.normal(size=(k, L)), rng.normal(size=(k, T + new))
    D = X.T @ Y + rng.normal(size=L) + rng.normal(size=(T + new, L))
    data = xr.DataArray(D.reshape(-1, ny, nx), dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T + new), "lat": np.arange(ny) * 1.0,
                                "lon": np.arange(nx) * 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=k, offset=True, spatial="exponential", random_state=0,
                     progress=False).fit(data.isel(time=slice(0, T)))
    assert residual_dof(model) == pytest.approx(25 / 14)
    assert prediction_factor(model) == pytest.approx(25 / 14)
    assert model.spatial_cov_.total_variance == pytest.approx(1.0, rel=0.12)
    Z = D[T:] - model.offset_
    latent = np.linalg.lstsq(model._Yv.T, Z.T, rcond=None)[0]
    oos = float(np.var(Z - (model._Yv.T @ latent).T))
    said = model.spatial_cov_.total_variance * residual_factor(model)
    assert oos == pytest.approx(said, rel=0.12)
    assert oos > 1.3 * model.spatial_cov_.total_variance  # what the factor is for
    assert noise_variance(model) == pytest.approx(model.noise_std_ ** 2 * 25 / 14)
    assert model.noise_std_ ** 2 == pytest.approx(1.0, rel=0.05)  # (its own dof correction)
