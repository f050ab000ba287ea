"""Spatial residual model: covariance closed forms, variogram fit, kriging vs dense brute force,
GLS fold-in, cut-off and neighbour paths, persistence, errors, determinism."""

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import gamma as gamma_fn
from scipy.special import kv

from lrm_cvx import Region
from lrm_cvx.belief.foldin import gls_fold_in, residual_correction
from lrm_cvx.errors import DataError, LrmError, ModelError, RegionError
from lrm_cvx.spatial import (
    MODELS,
    ResidualCovariance,
    correlation,
    empirical_variogram,
    fit_residual_covariance,
    krige,
    krige_many,
)


# ---------------------------------------------------------------------------- helpers
def make_region(ny, nx, mask=None, dlat=0.1, dlon=0.1):
    da = xr.DataArray(
        np.zeros((ny, nx), np.float32), dims=("lat", "lon"),
        coords={"lat": 40.0 + dlat * np.arange(ny), "lon": -70.0 + dlon * np.arange(nx)},
    )
    return Region.from_dataarray(da, mask=mask if mask is None else np.asarray(mask, bool))


def dense_distance(region, metric="grid"):
    L = region.n_cells
    a = np.arange(L)
    return np.asarray(region.distance(a[:, None], a[None, :], metric=metric))


def simulate_gp(cov, region, n_draws, seed, metric="grid"):
    """(n_draws, L) draws of the GP (spatial part + nugget) by a dense Cholesky."""
    D = dense_distance(region, metric)
    K = cov.covariance(D)
    Lc = np.linalg.cholesky(K + 1e-10 * np.eye(K.shape[0]))
    rng = np.random.default_rng(seed)
    return (Lc @ rng.standard_normal((K.shape[0], n_draws))).T


def brute_simple_kriging(cov, D, cells, values, targets=None):
    """Latent simple kriging with dense matrices and np.linalg.solve."""
    targets = np.arange(D.shape[0]) if targets is None else targets
    C = cov.sill * correlation(cov.model, D[np.ix_(cells, cells)] / cov.range)
    C = C + cov.nugget * np.eye(len(cells))
    k = cov.sill * correlation(cov.model, D[np.ix_(targets, cells)] / cov.range)
    mean = k @ np.linalg.solve(C, values)
    var = cov.sill - np.einsum("ij,ji->i", k, np.linalg.solve(C, k.T))
    return mean, np.sqrt(np.maximum(var, 0))


def matern_kv(h, nu):
    """Matern correlation through the Bessel function (independent of the closed forms)."""
    h = np.asarray(h, float)
    s = np.sqrt(2 * nu) * h
    with np.errstate(invalid="ignore"):
        out = 2 ** (1 - nu) / gamma_fn(nu) * s**nu * kv(nu, s)
    return np.where(h == 0, 1.0, out)


# ---------------------------------------------------------------------------- covariance models
def test_correlations_equal_closed_forms_and_bessel_matern():
    h = np.linspace(0, 6, 61)
    np.testing.assert_allclose(correlation("exponential", h), matern_kv(h, 0.5), rtol=1e-10)
    np.testing.assert_allclose(correlation("matern32", h), matern_kv(h, 1.5), rtol=1e-10)
    np.testing.assert_allclose(correlation("matern52", h), matern_kv(h, 2.5), rtol=1e-10)
    np.testing.assert_allclose(correlation("gaussian", h), np.exp(-h**2), rtol=1e-14)
    np.testing.assert_allclose(correlation("exponential", h), np.exp(-h), rtol=1e-14)


@pytest.mark.parametrize("model", MODELS)
def test_covariance_semivariogram_and_cutoff(model):
    cov = ResidualCovariance(model, sill=2.0, range=3.0, nugget=0.5)
    d = np.array([[0.0, 1.0], [4.5, 30.0]])
    c = cov.covariance(d)
    assert c.shape == d.shape
    rho = correlation(model, d / 3.0)
    np.testing.assert_allclose(c, 2.0 * rho + 0.5 * (d == 0))
    np.testing.assert_allclose(cov.covariance(d, nugget=False), 2.0 * rho)
    # gamma(d) = C(0) - C(d) for d > 0, and 0 at d = 0
    g = cov.semivariogram(d)
    np.testing.assert_allclose(g[d > 0], 2.5 - c[d > 0])
    assert g[0, 0] == 0
    for rel in (1e-6, 0.05):
        dc = cov.cutoff_distance(rel)
        np.testing.assert_allclose(cov.correlation(dc), rel, rtol=1e-8)
    assert cov.effective_range == pytest.approx(cov.cutoff_distance(0.05))
    assert cov.total_variance == 2.5


def test_attrs_round_trip_through_netcdf(tmp_path):
    cov = ResidualCovariance("matern32", sill=0.3, range=12.5, nugget=0.01, metric="km")
    ds = xr.Dataset({"a": ("x", [1.0])}, attrs={"other": 1, **cov.to_attrs()})
    path = tmp_path / "m.nc"
    ds.to_netcdf(path)
    with xr.open_dataset(path) as back:
        cov2 = ResidualCovariance.from_attrs(dict(back.attrs))
    assert cov2 == cov
    r = repr(cov)
    assert "matern32" in r and "12.5 km" in r and "0.3" in r
    with pytest.raises(ModelError, match="spatial_range"):
        ResidualCovariance.from_attrs({"spatial_model": "exponential"})


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"range": -1.0}, "range"),
        ({"range": 0.0}, "range"),
        ({"sill": -0.1}, "sill"),
        ({"nugget": np.nan}, "nugget"),
        ({"model": "spherical"}, "model"),
        ({"metric": "miles"}, "metric"),
        ({"sill": 0.0, "nugget": 0.0}, "sill \\+ nugget"),
    ],
)
def test_bad_covariance_parameters_raise(kwargs, match):
    base = {"model": "exponential", "sill": 1.0, "range": 2.0, "nugget": 0.1}
    with pytest.raises(ModelError, match=match):
        ResidualCovariance(**{**base, **kwargs})


# ---------------------------------------------------------------------------- variogram fit
@pytest.fixture(scope="module")
def gp_data():
    region = make_region(30, 30)
    truth = {m: ResidualCovariance(m, sill=1.0, range=4.0, nugget=0.1) for m in MODELS}
    return region, truth, {m: simulate_gp(truth[m], region, 50, seed=3) for m in MODELS}


@pytest.mark.parametrize("model", MODELS)
def test_variogram_fit_recovers_parameters(gp_data, model):
    region, truth, draws = gp_data
    R = draws[model].astype(np.float32)
    R[:, ::7] = np.nan  # missing entries are skipped
    fit = fit_residual_covariance(R, region, model=model, random_state=0)
    assert fit.model == model and fit.metric == "grid"
    assert fit.range == pytest.approx(4.0, rel=0.3)
    assert fit.sill == pytest.approx(1.0, rel=0.3)
    assert abs(fit.nugget - 0.1) < 0.1
    vg = fit.variogram
    assert vg.n_pairs > 50_000 and np.all(np.diff(vg.distance) > 0)
    assert vg.distance.max() <= vg.max_distance
    # the fitted model goes through the binned points
    np.testing.assert_allclose(fit.semivariogram(vg.distance), vg.gamma, atol=0.08)


def test_variogram_matches_truth_and_standardize_is_scale_invariant(gp_data):
    region, truth, draws = gp_data
    R = draws["exponential"]
    vg = empirical_variogram(R, region, spacing="linear", n_bins=10, max_distance=12.0)
    np.testing.assert_allclose(vg.gamma, truth["exponential"].semivariogram(vg.distance),
                               rtol=0.15)
    # rescaling each time's residuals changes nothing after per-time standardisation
    # (beyond the final rescale by the mean per-time variance)
    scale = np.linspace(0.5, 3.0, R.shape[0])[:, None]
    a = fit_residual_covariance(R, region, standardize=True, random_state=1)
    b = fit_residual_covariance(R * scale, region, standardize=True, random_state=1)
    assert b.range == pytest.approx(a.range, rel=1e-6)
    ratio = np.mean((R * scale).std(axis=1) ** 2) / np.mean(R.std(axis=1) ** 2)
    assert b.sill == pytest.approx(a.sill * ratio, rel=0.02)


def test_variogram_fit_km_metric():
    region = make_region(25, 25, dlat=0.05, dlon=0.05)
    truth = ResidualCovariance("exponential", sill=1.0, range=20.0, nugget=0.05, metric="km")
    R = simulate_gp(truth, region, 40, seed=5, metric="km")
    fit = fit_residual_covariance(R, region, metric="km", random_state=0)
    assert fit.metric == "km"
    assert fit.range == pytest.approx(20.0, rel=0.3)
    assert fit.sill == pytest.approx(1.0, rel=0.3)


def test_fit_is_deterministic(gp_data):
    region, _, draws = gp_data
    R = draws["matern32"]
    a = fit_residual_covariance(R, region, model="matern32", random_state=7, max_pairs=5000)
    b = fit_residual_covariance(R, region, model="matern32", random_state=7, max_pairs=5000)
    c = fit_residual_covariance(R, region, model="matern32", random_state=8, max_pairs=5000)
    assert a == b
    np.testing.assert_array_equal(a.variogram.gamma, b.variogram.gamma)
    assert a != c


def test_fit_bad_inputs(gp_data):
    region, _, draws = gp_data
    R = draws["exponential"]
    with pytest.raises(DataError, match="all NaN"):
        fit_residual_covariance(np.full_like(R, np.nan), region)
    with pytest.raises(DataError, match="columns"):
        fit_residual_covariance(R[:, :-1], region)
    with pytest.raises(DataError, match="constant"):
        fit_residual_covariance(np.ones_like(R), region)
    with pytest.raises(ModelError, match="model"):
        fit_residual_covariance(R, region, model="spherical")
    with pytest.raises(ModelError, match="max_distance"):
        fit_residual_covariance(R, region, max_distance=-3)
    with pytest.raises(ModelError, match="n_bins"):
        fit_residual_covariance(R, region, n_bins=2)


# ---------------------------------------------------------------------------- kriging
@pytest.fixture(scope="module")
def small():
    mask = np.ones((14, 16), bool)
    mask[3:6, 4:9] = False  # a lake: cells are not the grid positions
    region = make_region(14, 16, mask=mask)
    rng = np.random.default_rng(11)
    cells = np.sort(rng.choice(region.n_cells, 40, replace=False))
    values = rng.standard_normal(40)
    return region, cells, values


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("nugget", [0.0, 0.2])
@pytest.mark.parametrize("method", ["direct", "neighbors"])
def test_krige_equals_dense_brute_force(small, model, nugget, method):
    region, cells, values = small
    cov = ResidualCovariance(model, sill=1.5, range=3.0, nugget=nugget)
    D = dense_distance(region)
    ref_m, ref_s = brute_simple_kriging(cov, D, cells, values)
    # neighbors >= n: every target uses all observations, so it equals the exact solve
    mean, std = krige(cov, region, cells, values, method=method, neighbors=1000, cutoff=None)
    tol = 1e-5 if model == "gaussian" and nugget == 0 else 1e-8
    np.testing.assert_allclose(mean, ref_m, atol=tol)
    np.testing.assert_allclose(std, ref_s, atol=max(tol, 1e-6))


def test_krige_km_metric_equals_brute_force(small):
    region, cells, values = small
    cov = ResidualCovariance("matern52", sill=1.0, range=25.0, nugget=0.05, metric="km")
    ref_m, ref_s = brute_simple_kriging(cov, dense_distance(region, "km"), cells, values)
    for method in ("direct", "neighbors"):
        mean, std = krige(cov, region, cells, values, method=method, neighbors=100, cutoff=None)
        np.testing.assert_allclose(mean, ref_m, atol=1e-8)
        np.testing.assert_allclose(std, ref_s, atol=1e-7)


def test_local_neighbors_equal_brute_force_on_nearest_sets(small):
    region, cells, values = small
    cov = ResidualCovariance("exponential", sill=1.0, range=4.0, nugget=0.1)
    D = dense_distance(region)
    m = 6
    mean, std = krige(cov, region, cells, values, method="neighbors", neighbors=m, cutoff=None)
    checked = 0
    for t in range(region.n_cells):
        order = np.argsort(D[t, cells], kind="stable")
        dsorted = D[t, cells][order]
        if dsorted[m - 1] == dsorted[m]:
            continue  # a tie at the boundary: the neighbour set is not unique
        near = order[:m]
        rm, rs = brute_simple_kriging(cov, D, cells[near], values[near], targets=np.array([t]))
        assert mean[t] == pytest.approx(rm[0], abs=1e-9)
        assert std[t] == pytest.approx(rs[0], abs=1e-8)
        checked += 1
    assert checked > region.n_cells // 3


def test_cutoff_equals_exact_where_it_applies():
    region = make_region(60, 60)
    rng = np.random.default_rng(2)
    corner = np.flatnonzero((region.grid_index < 15).all(axis=1))  # a route in one corner
    cells = rng.choice(corner, 15, replace=False)
    values = rng.standard_normal(15)
    cov = ResidualCovariance("exponential", sill=1.0, range=1.5, nugget=0.1)
    exact_m, exact_s = krige(cov, region, cells, values, cutoff=None)
    for method in ("direct", "neighbors"):
        m, s = krige(cov, region, cells, values, cutoff=1e-6, method=method, neighbors=15)
        np.testing.assert_allclose(m, exact_m, atol=1e-5)
        np.testing.assert_allclose(s, exact_s, atol=1e-5)
        # far targets got exactly the prior, without a solve
        reach = cov.cutoff_distance(1e-6)
        D = np.asarray(region.distance(np.arange(region.n_cells)[:, None], cells[None, :]))
        far = D.min(axis=1) > reach
        assert far.sum() > region.n_cells // 4
        assert np.all(m[far] == 0) and np.all(s[far] == 1.0)


def test_std_at_observed_cells_and_nugget_convention(small):
    region, cells, values = small
    cov0 = ResidualCovariance("exponential", sill=1.0, range=3.0, nugget=0.0)
    mean, std = krige(cov0, region, cells, values)
    np.testing.assert_allclose(mean[cells], values, atol=1e-9)
    np.testing.assert_allclose(std[cells], 0.0, atol=1e-6)
    cov = ResidualCovariance("exponential", sill=1.0, range=3.0, nugget=0.3)
    _, std = krige(cov, region, cells, values)
    assert np.all(std[cells] < np.sqrt(0.3))  # the latent value is known better than one reading
    _, std_n = krige(cov, region, cells, values, include_nugget=True)
    np.testing.assert_allclose(std_n, np.sqrt(std**2 + 0.3), rtol=1e-12)
    assert np.all(std <= 1.0 + 1e-12) and np.all(std_n <= np.sqrt(1.3) + 1e-12)


def test_targets_subset_and_no_std(small):
    region, cells, values = small
    cov = ResidualCovariance("matern32", sill=1.0, range=3.0, nugget=0.1)
    full_m, full_s = krige(cov, region, cells, values)
    tg = np.array([5, 0, 77, 5])
    m, s = krige(cov, region, cells, values, targets=tg)
    np.testing.assert_allclose(m, full_m[tg], atol=1e-12)
    np.testing.assert_allclose(s, full_s[tg], atol=1e-12)
    m2, s2 = krige(cov, region, cells, values, targets=tg, return_std=False)
    assert s2 is None
    np.testing.assert_allclose(m2, m, atol=1e-12)


def test_nan_values_are_unobserved_and_krige_many_groups_patterns(small):
    region, cells, values = small
    cov = ResidualCovariance("matern52", sill=1.0, range=3.0, nugget=0.05)
    rng = np.random.default_rng(4)
    V = rng.standard_normal((5, cells.size))
    V[1, :10] = np.nan
    V[3, :10] = np.nan
    V[4, :] = np.nan
    mean, std = krige_many(cov, region, cells, V)
    assert mean.shape == std.shape == (5, region.n_cells)
    for i in range(5):
        ok = np.isfinite(V[i])
        m, s = krige(cov, region, cells[ok], V[i, ok])
        np.testing.assert_allclose(mean[i], m, atol=1e-10)
        np.testing.assert_allclose(std[i], s, atol=1e-10)
        m2, _ = krige(cov, region, cells, V[i])  # NaN in krige means "not observed" too
        np.testing.assert_allclose(m2, m, atol=1e-10)
    np.testing.assert_array_equal(mean[4], 0.0)
    np.testing.assert_allclose(std[4], 1.0)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 25),
    model=st.sampled_from(MODELS),
    rng_=st.floats(0.5, 6.0),
    nugget=st.floats(0.01, 1.0),
)
def test_direct_and_all_neighbors_agree(seed, n, model, rng_, nugget):
    region = make_region(9, 11)
    rng = np.random.default_rng(seed)
    cells = rng.choice(region.n_cells, n, replace=False)
    values = rng.standard_normal(n)
    cov = ResidualCovariance(model, sill=1.0, range=rng_, nugget=nugget)
    a = krige(cov, region, cells, values, method="direct", cutoff=None)
    b = krige(cov, region, cells, values, method="neighbors", neighbors=n, cutoff=None)
    np.testing.assert_allclose(a[0], b[0], atol=1e-8)
    np.testing.assert_allclose(a[1], b[1], atol=1e-7)


def test_krige_bad_inputs(small):
    region, cells, values = small
    cov = ResidualCovariance("exponential", sill=1.0, range=3.0, nugget=0.1)
    with pytest.raises(DataError, match="len\\(cells\\)"):
        krige(cov, region, cells, values[:-1])
    with pytest.raises(RegionError, match="cells"):
        krige(cov, region, np.r_[cells[:-1], region.n_cells], values)
    with pytest.raises(RegionError, match="targets"):
        krige(cov, region, cells, values, targets=[-1])
    with pytest.raises(DataError, match="repeated"):
        krige(cov, region, np.r_[cells[:-1], cells[0]], values)
    with pytest.raises(DataError, match="infinite"):
        krige(cov, region, cells, np.r_[values[:-1], np.inf])
    with pytest.raises(ModelError, match="neighbors"):
        krige(cov, region, cells, values, neighbors=0)
    with pytest.raises(ModelError, match="method"):
        krige(cov, region, cells, values, method="fast")
    with pytest.raises(ModelError, match="ResidualCovariance"):
        krige({"sill": 1}, region, cells, values)
    assert issubclass(RegionError, LrmError)


# ---------------------------------------------------------------------------- trend + residual
def test_gls_fold_in_equals_brute_force(small):
    region, cells, values = small
    rng = np.random.default_rng(9)
    Y = rng.standard_normal((3, region.n_cells))
    cov = ResidualCovariance("matern32", sill=0.7, range=2.5, nugget=0.2)
    D = dense_distance(region)
    C = cov.covariance(D[np.ix_(cells, cells)])
    Ci = np.linalg.inv(C)
    Ys = Y[:, cells]
    for ridge in (0.0, 0.5):
        A = Ys @ Ci @ Ys.T + ridge * np.eye(3)
        x_ref = np.linalg.solve(A, Ys @ Ci @ values)
        x, cov_x = gls_fold_in(Y, cells, values, cov, region, ridge=ridge)
        np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cov_x, np.linalg.inv(A), rtol=1e-9, atol=1e-12)
    with pytest.raises(ModelError, match="singular"):
        gls_fold_in(Y, cells[:2], values[:2], cov, region)
    with pytest.raises(DataError, match="values has"):
        gls_fold_in(Y, cells, values[:3], cov, region)
    with pytest.raises(DataError, match="columns"):
        gls_fold_in(Y[:, :-1], cells, values, cov, region)


@pytest.mark.parametrize("method", ["direct", "neighbors"])
def test_universal_kriging_equals_augmented_system(small, method):
    region, cells, values = small
    rng = np.random.default_rng(10)
    Y = rng.standard_normal((2, region.n_cells))
    cov = ResidualCovariance("exponential", sill=1.0, range=3.0, nugget=0.1)
    D = dense_distance(region)
    n, k = cells.size, 2
    C = cov.covariance(D[np.ix_(cells, cells)])
    A = np.block([[C, Y[:, cells].T], [Y[:, cells], np.zeros((k, k))]])
    Kt = cov.sill * cov.correlation(D[:, cells])  # (L, n), latent cross-covariance
    sol = np.linalg.solve(A, np.vstack([Kt.T, Y]))  # (n + k, L)
    lam, mu = sol[:n], sol[n:]
    ref_pred = lam.T @ values
    ref_var = cov.sill - np.einsum("nl,ln->l", lam, Kt) - np.einsum("kl,kl->l", mu, Y)
    pred, std = residual_correction(Y, cells, values, cov, region, fold_in="gls", method=method,
                                    neighbors=n, cutoff=None)
    np.testing.assert_allclose(pred, ref_pred, atol=1e-9)
    np.testing.assert_allclose(std, np.sqrt(ref_var), atol=1e-8)
    # with the cut-off the far targets keep the trend term: still equal within tolerance
    pred_c, std_c = residual_correction(Y, cells, values, cov, region, method=method,
                                        neighbors=n)
    np.testing.assert_allclose(pred_c, ref_pred, atol=1e-5)
    np.testing.assert_allclose(std_c, np.sqrt(ref_var), atol=1e-5)


def test_ols_regression_kriging_equals_brute_force(small):
    region, cells, values = small
    rng = np.random.default_rng(12)
    Y = rng.standard_normal((3, region.n_cells))
    cov = ResidualCovariance("gaussian", sill=1.0, range=2.0, nugget=0.1)
    Ys = Y[:, cells]
    x = np.linalg.lstsq(Ys.T, values, rcond=None)[0]
    ref_m, ref_s = brute_simple_kriging(cov, dense_distance(region), cells, values - Ys.T @ x)
    pred, std = residual_correction(Y, cells, values, cov, region, fold_in="ols", cutoff=None)
    np.testing.assert_allclose(pred, Y.T @ x + ref_m, atol=1e-8)
    np.testing.assert_allclose(std, ref_s, atol=1e-8)
    with pytest.raises(ModelError, match="fold_in"):
        residual_correction(Y, cells, values, cov, region, fold_in="wls")


def test_low_rank_plus_kriging_beats_low_rank_alone():
    """Synthetic truth = rank-3 field + spatially correlated GP residual on a 30 x 30 grid."""
    region = make_region(30, 30)
    L, k, T = region.n_cells, 3, 80
    rng = np.random.default_rng(0)
    gi = region.grid_index / 30.0
    Y = np.vstack([np.ones(L), np.sin(3 * gi[:, 0]) + gi[:, 1], np.cos(4 * gi[:, 1]) * gi[:, 0]])
    truth_cov = ResidualCovariance("exponential", sill=0.5, range=4.0, nugget=0.02)
    draws = simulate_gp(truth_cov, region, T + 10, seed=1)
    X = 2.0 * rng.standard_normal((k, T + 10))
    data = X.T @ Y + draws
    train, test = data[:T], data[T:]
    # the "GLRM": a rank-k truncated SVD of the training data, residuals = data - reconstruction
    U, s, Vt = np.linalg.svd(train, full_matrices=False)
    Yhat = Vt[:k] * s[:k, None] / np.sqrt(T)
    resid = train - train @ np.linalg.pinv(Yhat) @ Yhat
    cov = fit_residual_covariance(resid.astype(np.float32), region, random_state=0)
    assert cov.range == pytest.approx(4.0, rel=0.5)
    errs = {"low-rank": [], "ols": [], "gls": []}
    for i, d in enumerate(test):
        cells = np.sort(np.random.default_rng(100 + i).choice(L, 150, replace=False))
        held = np.setdiff1d(np.arange(L), cells)
        x = np.linalg.lstsq(Yhat[:, cells].T, d[cells], rcond=None)[0]
        errs["low-rank"].append(np.sqrt(np.mean((Yhat[:, held].T @ x - d[held]) ** 2)))
        for f in ("ols", "gls"):
            pred, std = residual_correction(Yhat, cells, d[cells], cov, region, fold_in=f,
                                            targets=held)
            errs[f].append(np.sqrt(np.mean((pred - d[held]) ** 2)))
            z = (pred - d[held]) / np.sqrt(std**2 + cov.nugget)
            assert 0.6 < np.sqrt(np.mean(z**2)) < 1.5  # the std is calibrated, roughly
    rmse = {key: float(np.mean(v)) for key, v in errs.items()}
    assert rmse["ols"] < 0.8 * rmse["low-rank"]
    assert rmse["gls"] < 0.8 * rmse["low-rank"]
    assert rmse["gls"] <= rmse["ols"] * 1.05


# ----------------------------------------------------------------------------- FFT kriging
@pytest.mark.parametrize("sill,rng_range,nugget", [(1.1e-5, 30.0, 2.4e-3), (0.5, 4.0, 0.05),
                                                   (0.3, 10.0, 0.01)])
def test_krige_grid_fft_equals_direct_kriging(sill, rng_range, nugget):
    import xarray as xr

    from lrm_cvx import Region
    from lrm_cvx import spatial as sp

    rng = np.random.default_rng(3)
    ny, nx = 30, 34
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    region = Region.from_dataarray(da, mask=rng.random((ny, nx)) > 0.1)
    L = region.n_cells
    cov = sp.ResidualCovariance("exponential", sill=sill, range=rng_range, nugget=nugget)
    obs = np.sort(rng.choice(L, 60, replace=False))
    z = rng.normal(0, np.sqrt(sill + nugget), obs.size)
    Y = rng.normal(size=(3, L))
    B = rng.normal(size=(3, 3))
    cx = 0.01 * B @ B.T
    m1, v1 = sp._krige_core(cov, sp._coords(region, "grid", obs), z[:, None],
                            sp._coords(region, "grid"), method="direct", neighbors=32,
                            cutoff=None, want_var=True, Ys=Y[:, obs],
                            Yt=lambda sel: Y[:, sel], cov_x=cx)
    m2, v2, M = sp.krige_grid_fft(cov, region, obs, z, Ys=Y[:, obs], Yall=Y, cov_x=cx)
    assert 0 < M <= obs.size
    np.testing.assert_allclose(m2, m1[0], rtol=0, atol=1e-12 * np.sqrt(sill + nugget))
    np.testing.assert_allclose(v2, v1, rtol=0, atol=sp.FFT_KRIGE_VAR_TOL * nugget)
    km = sp.ResidualCovariance("exponential", sill=sill, range=100.0, nugget=nugget, metric="km")
    with pytest.raises(ModelError, match="grid"):
        sp.krige_grid_fft(km, region, obs, z)


@pytest.mark.parametrize("ratio", [0.0, np.inf])
def test_krige_grid_fft_beyond_the_kernels_reach_equals_direct_kriging(ratio, monkeypatch):
    """Observations in one corner of a large grid and a short range: the products cover only
    the observations' box grown by the kernel's reach, and every cell (inside or beyond) still
    gets the direct kriging's mean and variance, by the batched FFTs (ratio 0) and by the
    lag table's products (ratio inf) alike."""
    import xarray as xr

    from lrm_cvx import Region
    from lrm_cvx import spatial as sp

    monkeypatch.setattr(sp.kriging, "FFT_KRIGE_DIRECT_RATIO", ratio)
    rng = np.random.default_rng(8)
    ny, nx = 150, 140
    da = xr.DataArray(np.zeros((ny, nx)), dims=("lat", "lon"),
                      coords=dict(lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    region = Region.from_dataarray(da, mask=rng.random((ny, nx)) > 0.1)
    L = region.n_cells
    cov = sp.ResidualCovariance("exponential", sill=0.4, range=1.5, nugget=0.05,
                                anisotropy=1.5)
    gi = region.grid_index
    box = np.flatnonzero((gi[:, 0] >= 5) & (gi[:, 0] < 17) & (gi[:, 1] >= 6) & (gi[:, 1] < 20))
    obs = np.sort(rng.choice(box, 40, replace=False))
    rect = sp.kriging.grid_rect(gi[obs].min(axis=0), gi[obs].max(axis=0),
                                cov.reach(sp.kriging.FFT_KRIGE_REACH), region.shape)
    assert rect[2] * rect[3] < 0.5 * ny * nx  # the convolutions skip most of the grid
    z = rng.normal(0, 0.6, obs.size)
    Y = rng.normal(size=(3, L))
    B = rng.normal(size=(3, 3))
    cx = 0.01 * B @ B.T
    m1, v1 = sp._krige_core(cov, cov.points(region, obs), z[:, None],
                            cov.points(region, np.arange(L)), method="direct", neighbors=32,
                            cutoff=None, want_var=True, Ys=Y[:, obs],
                            Yt=lambda sel: Y[:, sel], cov_x=cx)
    m2, v2, _ = sp.krige_grid_fft(cov, region, obs, z, Ys=Y[:, obs], Yall=Y, cov_x=cx,
                                  var_tol=0.0)
    np.testing.assert_allclose(m2, m1[0], rtol=0, atol=1e-12 * np.sqrt(0.45))
    np.testing.assert_allclose(v2, v1, rtol=0, atol=1e-12)
    far = (gi[:, 0] > 100) & (gi[:, 1] > 100)
    assert np.all(m2[far] == 0.0) and np.abs(m1[0][far]).max() < 1e-15
