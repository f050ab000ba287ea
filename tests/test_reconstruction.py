"""Reconstruction-targeted options against brute-force references."""

import warnings

import numpy as np
import pytest
import xarray as xr
from references import naive_tour
from scipy.spatial.distance import cdist

from lrm_cvx import Region
from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel, empirical_moments
from lrm_cvx.errors import ModelError, PlanningError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import prediction_factor
from lrm_cvx.glrm.offset import OFFSET_PRIOR_OBS
from lrm_cvx.glrm.predictive import NOISE_PRIOR_DF, shrink_noise
from lrm_cvx.information import (
    AOptimalOracle,
    FisherOracle,
    GPVarianceOracle,
    gp_variance_value,
)
from lrm_cvx.planning import PriorTerms, plan_greedy
from lrm_cvx.spatial import ResidualCovariance


def field(seed=0, T=30, ny=10, nx=12, k=3, missing=0.15):
    """Low-rank + offset + smooth correlated residual, some missing entries."""
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    pts = np.column_stack([r.ravel(), c.ravel()]).astype(float)
    Lc = np.linalg.cholesky(0.3 * np.exp(-cdist(pts, pts) / 2.5) + 1e-9 * np.eye(ny * nx))
    data = (rng.normal(size=(T, k)) @ rng.normal(size=(k, ny * nx))
            + 5.0 + np.linspace(0, 3, ny * nx) + (Lc @ rng.normal(size=(ny * nx, T))).T
            + 0.05 * rng.normal(size=(T, ny * nx)))
    data = data.reshape(T, ny, nx)
    data[rng.random(data.shape) < missing] = np.nan
    data[:, 0, :2] = np.nan
    return xr.DataArray(data, dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T), "lat": np.arange(ny) * 1.0,
                                "lon": np.arange(nx) * 1.0})


@pytest.fixture(scope="module")
def data():
    return field()


def cells_of(model, da):
    """Grid DataArray -> (L,) float64 over the model's cells (Region.stack gives float32)."""
    gi = model.region_.grid_index
    return np.asarray(da.values, dtype=np.float64)[..., gi[:, 0], gi[:, 1]]


def fit(da, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(3, progress=False, random_state=0, max_iter=50, **kw).fit(da)


def snapshot_obs(model, seed=1, n=25):
    rng = np.random.default_rng(seed)
    cells = np.sort(rng.choice(model.n_cells_, n, replace=False))
    vals = rng.normal(size=n) + 6.0
    return cells, vals


# --------------------------------------------------------------------------- offset / scale
def test_offset_is_joint_scale_is_observed_std_and_fold_in_matches(data):
    m = fit(data, offset=True, scale=True)
    D = m.region_.stack(data).astype(float)
    np.testing.assert_allclose(m.scale_, np.nanstd(D, axis=0), rtol=1e-10)
    # the offset is fitted with the factors (glrm/offset.py): the observed mean plus a
    # correction o that satisfies its normal equation, sum of observed residuals = n0 o
    o = (m.offset_ - np.nanmean(D, axis=0)) / m.scale_
    R0 = (D - m.offset_) / m.scale_ - m._Xv.T @ m._Yv
    assert m.converged_  # the fit stopped after a Y step: its normal equations hold (float32 data)
    np.testing.assert_allclose(np.nansum(R0, axis=0), OFFSET_PRIOR_OBS * o, atol=1e-5)  # f32
    assert np.abs(o).max() > 1e-4  # missing entries: the observed mean is not the optimum
    # the low-rank part was fitted to the standardised data
    Z = (D - m.offset_) / m.scale_
    R = (D - m.offset_ - m.scale_ * (m._Xv.T @ m._Yv)) / m.scale_
    assert np.nanmean(R ** 2) < np.nanvar(Z)
    assert m.score(D) == pytest.approx(np.nanmean((m.scale_ * R) ** 2), rel=1e-6)  # data units
    cells, vals = snapshot_obs(m)
    ds = m.complete((cells, vals))
    Y = m._Yv
    z = (vals - m.offset_[cells]) / m.scale_[cells]
    x = np.linalg.lstsq(Y[:, cells].T, z, rcond=None)[0]
    ref = m.scale_ * (Y.T @ x) + m.offset_
    got = cells_of(m, ds["prediction"])
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-8)
    s2 = m.noise_std_ ** 2 * prediction_factor(m)  # a new snapshot's noise
    cov = s2 * np.linalg.inv(Y[:, cells] @ Y[:, cells].T)
    std_ref = m.scale_ * np.sqrt(np.einsum("ai,ab,bi->i", Y, cov, Y))
    np.testing.assert_allclose(cells_of(m, ds["std"]), std_ref, rtol=1e-6)


def _nearly_constant(data, cells=((3, 4), (6, 7), (8, 2)), std=1e-6, seed=5):
    """``data`` with ``cells`` (grid rows, cols) nearly constant: sea ice that never melted."""
    out = data.copy()
    rng = np.random.default_rng(seed)
    for r, c in cells:
        out[:, r, c] = 5.0 + std * rng.normal(size=data.shape[0])
    return out


def test_scale_floors_the_std_of_nearly_constant_cells(data, monkeypatch):
    """``scale=True`` divides by the per-cell std, floored at SCALE_FLOOR x the median one;
    a nearly constant training cell that then moves by a typical amount must not wreck the
    map (without the floor its fit-unit value is ~1e6 and the fold-in is garbage)."""
    from lrm_cvx.glrm import predictive

    train = _nearly_constant(data.isel(time=slice(0, 25)))
    D = fit(train, offset=True).region_.stack(train).astype(float)
    std = np.nanstd(D, axis=0)
    floor = predictive.SCALE_FLOOR * np.median(std)
    low = std < floor
    assert low.sum() == 3
    test = cells_of(fit(train, offset=True), data.isel(time=27))  # the constant cells move

    def map_error(model, cells):
        got = cells_of(model, model.complete((cells, test[cells]))["prediction"])
        return np.nanmean((got - test) ** 2)

    rng = np.random.default_rng(2)
    m = fit(train, offset=True, scale=True)
    np.testing.assert_allclose(m.scale_, np.maximum(std, floor), rtol=1e-10)
    others = np.flatnonzero(~low & np.isfinite(test))
    cells = np.sort(np.concatenate([rng.choice(others, 20, replace=False),
                                    np.flatnonzero(low)]))
    without = map_error(m, np.setdiff1d(cells, np.flatnonzero(low)))
    assert map_error(m, cells) < 3 * without  # the three samples cost little
    monkeypatch.setattr(predictive, "SCALE_FLOOR", 0.0)  # the mutation: no floor
    bare = fit(train, offset=True, scale=True)
    assert bare.scale_.min() < 1e-5
    assert map_error(bare, cells) > 100 * without


def test_offset_only_prediction_adds_the_mean(data):
    m = fit(data, offset=True)
    assert m.scale_ is None
    cells, vals = snapshot_obs(m, seed=3)
    Y = m._Yv
    x = np.linalg.lstsq(Y[:, cells].T, vals - m.offset_[cells], rcond=None)[0]
    got = cells_of(m, m.complete((cells, vals))["prediction"])
    np.testing.assert_allclose(got, Y.T @ x + m.offset_, rtol=1e-8)


def test_default_model_is_unchanged(data):
    m = fit(data)
    assert m.offset_ is None and m.scale_ is None and m.noise_var_ is None
    cells, vals = snapshot_obs(m)
    Y = m._Yv
    x = np.linalg.lstsq(Y[:, cells].T, vals, rcond=None)[0]
    ds = m.complete((cells, vals))
    np.testing.assert_allclose(cells_of(m, ds["prediction"]), Y.T @ x, rtol=1e-8)
    assert "prior" not in ds.attrs


# --------------------------------------------------------------------------- per-cell noise
def test_per_cell_noise_and_weighted_fold_in(data):
    m = fit(data, noise="per-cell")
    D = m.region_.stack(data).astype(float)
    R = D - m._Xv.T @ m._Yv
    sse = np.nansum(R ** 2, axis=0)
    cnt = np.isfinite(R).sum(axis=0)
    inflate = m.noise_std_ ** 2 * cnt.sum() / sse.sum()
    ref = (sse * inflate + NOISE_PRIOR_DF * m.noise_std_ ** 2) / (cnt + NOISE_PRIOR_DF)
    np.testing.assert_allclose(m.noise_var_, ref, rtol=1e-10)
    got = shrink_noise(np.array([0.0, 40.0]), np.array([0, 1000]), 2.0, 3.0)
    np.testing.assert_allclose(got, [2.0, 46.0 / 1003.0])  # unobserved -> global
    cells, vals = snapshot_obs(m)
    Y = m._Yv
    w = 1.0 / np.sqrt(m.noise_var_[cells])
    x = np.linalg.lstsq((Y[:, cells] * w).T, vals * w, rcond=None)[0]  # weighted LS
    ds = m.complete((cells, vals))
    np.testing.assert_allclose(cells_of(m, ds["prediction"]), Y.T @ x, rtol=1e-8)


# --------------------------------------------------------------------------- Bayesian fold-in
def gaussian_conditional(mu, K, obs, d, noise):
    """Brute force: condition the joint Gaussian (field at all cells) on noisy obs."""
    Kso = K[:, obs]
    A = K[np.ix_(obs, obs)] + noise * np.eye(obs.size)
    mean = mu + Kso @ np.linalg.solve(A, d - mu[obs])
    cov = K - Kso @ np.linalg.solve(A, Kso.T)
    return mean, np.sqrt(np.maximum(np.diag(cov), 0))


def test_empirical_prior_fold_in_equals_gaussian_posterior(data):
    m = fit(data)
    m0, S0 = empirical_moments(m._Xv)
    np.testing.assert_allclose(m0, m._Xv.mean(1))
    np.testing.assert_allclose(S0, np.cov(m._Xv), rtol=1e-6)
    cells, vals = snapshot_obs(m, n=4)  # fewer than... fine with a prior, even below rank
    cells, vals = cells[:2], vals[:2]
    Y = m._Yv
    ds = m.complete((cells, vals), prior="empirical")
    mean, std = gaussian_conditional(Y.T @ m0, Y.T @ S0 @ Y, cells, vals,
                                     m.noise_std_ ** 2 * prediction_factor(m))  # a new snapshot's
    np.testing.assert_allclose(cells_of(m, ds["prediction"]), mean, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(cells_of(m, ds["std"]), std, rtol=1e-6, atol=1e-9)
    with pytest.raises(ModelError):  # without a prior two cells cannot fix a rank-3 x
        m.complete((cells, vals))


def test_fold_in_posterior_low_level():
    rng = np.random.default_rng(0)
    Y = rng.normal(size=(3, 20))
    cells = np.array([1, 4, 7, 9, 15])
    d = rng.normal(size=5)
    nv = rng.uniform(0.5, 2, size=20)
    P0 = np.eye(3) * 0.7
    m0 = np.array([1.0, -1.0, 0.5])
    obs = ObservationModel(Y, noise_var=nv)
    post = LatentPosterior.from_moments(obs, m0, precision=P0).update(cells, d)
    x, cov = post.mean, post.cov
    W = np.diag(1 / nv[cells])
    A = Y[:, cells] @ W @ Y[:, cells].T + P0
    np.testing.assert_allclose(cov, np.linalg.inv(A), rtol=1e-10)
    np.testing.assert_allclose(x, np.linalg.solve(A, Y[:, cells] @ W @ d + P0 @ m0), rtol=1e-10)


# --------------------------------------------------------------------------- spatial
def test_spatial_complete_equals_gp_conditional(data):
    m = fit(data, offset=True, spatial="exponential")
    cov = m.spatial_cov_
    assert isinstance(cov, ResidualCovariance) and cov.range > 0
    f = prediction_factor(m)  # a new snapshot's residual
    cov = ResidualCovariance(cov.model, sill=cov.sill * f, range=cov.range,
                             nugget=cov.nugget * f)
    cells, vals = snapshot_obs(m, n=12)
    Y = m._Yv
    m0, S0 = empirical_moments(m._Xv)
    g = m.region_.grid_index.astype(float)
    K = Y.T @ S0 @ Y + cov.covariance(cdist(g, g), nugget=False)
    mean, std = gaussian_conditional(Y.T @ m0, K, cells, vals - m.offset_[cells],
                                     cov.nugget)
    ds = m.complete((cells, vals), prior="empirical", spatial=True)
    np.testing.assert_allclose(cells_of(m, ds["prediction"]), mean + m.offset_,
                               rtol=1e-5, atol=1e-5 * cov.total_variance)
    np.testing.assert_allclose(cells_of(m, ds["std"]) ** 2, std ** 2,
                               rtol=1e-5, atol=1e-5 * cov.total_variance)
    with pytest.raises(ModelError):
        fit(data).complete((cells, vals), spatial=True)


def test_save_load_keeps_predictive_options(data, tmp_path):
    m = fit(data, offset=True, scale=True, noise="per-cell", spatial="matern32")
    m.save(tmp_path / "m.nc")
    m2 = GLRM.load(tmp_path / "m.nc")
    assert (m2.offset, m2.scale, m2.noise, m2.spatial) == (True, True, "per-cell", "matern32")
    np.testing.assert_array_equal(m2.offset_, m.offset_)
    np.testing.assert_array_equal(m2.scale_, m.scale_)
    np.testing.assert_array_equal(m2.noise_var_, m.noise_var_)
    assert m2.spatial_cov_ == m.spatial_cov_
    cells, vals = snapshot_obs(m)
    a = m.complete((cells, vals), prior="empirical", spatial=True)
    b = m2.complete((cells, vals), prior="empirical", spatial=True)
    np.testing.assert_allclose(a["prediction"].values, b["prediction"].values, equal_nan=True)
    m3 = fit(data)
    m3.save(tmp_path / "p.nc")
    m4 = GLRM.load(tmp_path / "p.nc")
    assert m4.offset_ is None and m4.spatial_cov_ is None


def test_bad_options(data):
    with pytest.raises(ModelError):
        fit(data, noise="cell")
    with pytest.raises(ModelError):
        fit(data, spatial="spherical")
    m = fit(data)
    with pytest.raises(ModelError):
        m.complete(snapshot_obs(m), prior="flat")


# --------------------------------------------------------------------------- oracles
@pytest.fixture(scope="module")
def factors():
    rng = np.random.default_rng(5)
    Y = rng.normal(size=(3, 40))
    A = rng.normal(size=(3, 3))
    P0 = A @ A.T + 0.5 * np.eye(3)
    nv = rng.uniform(0.2, 3.0, 40)
    c = rng.uniform(0.5, 2.0, 40)
    return Y, P0, nv, c


def _M(Y, P0, nv, cells):
    Ys = Y[:, cells] / np.sqrt(nv[cells])
    return P0 + Ys @ Ys.T


def test_posterior_fisher_and_aopt_gains_equal_value_differences(factors):
    Y, P0, nv, c = factors
    W = (Y * c) @ Y.T
    fo = FisherOracle(Y, 0.0, [], prior_precision=P0, noise_var=nv)
    ao = AOptimalOracle(Y, 0.0, [], prior_precision=P0, noise_var=nv, target_weights=c)
    cells: list[int] = []
    for add in (3, 17, 8, 30):
        M = _M(Y, P0, nv, np.array(cells, dtype=int))
        ld0 = np.linalg.slogdet(M)[1]
        v0 = np.trace(np.linalg.solve(M, W))
        gf, ga = fo.gains(), ao.gains()
        for x in range(Y.shape[1]):
            M1 = _M(Y, P0, nv, np.array(cells + [x]))
            assert gf[x] == pytest.approx(np.linalg.slogdet(M1)[1] - ld0, rel=1e-9, abs=1e-12)
            assert ga[x] == pytest.approx(v0 - np.trace(np.linalg.solve(M1, W)),
                                          rel=1e-8, abs=1e-12)
        assert ao.value == pytest.approx(v0, rel=1e-9)
        fo.add(add)
        ao.add(add)
        cells.append(add)


def test_prior_free_oracles_unchanged(factors):
    Y, *_ = factors
    a = FisherOracle(Y, 1e-3, [0, 1, 2]).gains()
    Yc = Y.copy()
    M = 1e-3 * np.eye(3) + Yc[:, :3] @ Yc[:, :3].T
    ref = np.log1p(np.einsum("ai,ab,bi->i", Yc, np.linalg.inv(M), Yc))
    np.testing.assert_allclose(a, ref, rtol=1e-10)


def grid_region(ny, nx, mask=None):
    mask = np.ones((ny, nx), bool) if mask is None else mask
    return Region(lat=xr.DataArray(np.arange(ny) * 1.0, dims="lat",
                                   coords={"lat": np.arange(ny) * 1.0}),
                  lon=xr.DataArray(np.arange(nx) * 1.0, dims="lon",
                                   coords={"lon": np.arange(nx) * 1.0}), mask=mask)


def brute_total_variance(Y, region, cov, S0, cells, c):
    """Independent reference: the dense posterior covariance of the latent field."""
    g = region.grid_index.astype(float)
    K = Y.T @ S0 @ Y + cov.covariance(cdist(g, g), nugget=False)
    noise = max(cov.nugget, 1e-9 * cov.total_variance)
    if len(cells):
        P = np.asarray(cells)
        K = K - K[:, P] @ np.linalg.solve(K[np.ix_(P, P)] + noise * np.eye(P.size), K[P, :])
    return float(c @ np.diag(K))


def test_gp_variance_oracle_gains_equal_value_differences():
    rng = np.random.default_rng(2)
    mask = np.ones((6, 7), bool)
    mask[0, :2] = False
    region = grid_region(6, 7, mask)
    L = region.n_cells
    Y = rng.normal(size=(2, L))
    S0 = np.array([[1.0, 0.3], [0.3, 0.5]])
    cov = ResidualCovariance("exponential", sill=0.4, range=1.7, nugget=0.05)
    c = rng.uniform(0.5, 1.5, L)
    pool = np.arange(3, L - 2)
    o = GPVarianceOracle(Y, [0, 1], region=region, spatial_cov=cov, prior_cov=S0, pool=pool,
                         target_weights=c)
    cells = [0, 1]
    for add in (10, 20, 5):
        v0 = brute_total_variance(Y, region, cov, S0, cells, c)
        assert o.value == pytest.approx(v0, rel=1e-9)
        assert gp_variance_value(Y, region, cov, S0, cells, target_weights=c) == pytest.approx(
            v0, rel=1e-9)
        g = o.gains(pool)
        for j, x in enumerate(pool):
            if x in cells:
                continue
            ref = v0 - brute_total_variance(Y, region, cov, S0, cells + [int(x)], c)
            assert g[j] == pytest.approx(ref, rel=1e-7, abs=1e-10)
        o.add(add)
        cells.append(add)
    with pytest.raises(PlanningError):
        o.gains([0])  # not in the pool
    with pytest.raises(PlanningError):
        GPVarianceOracle(Y, [], region=region, spatial_cov=None, prior_cov=S0)


# --------------------------------------------------------------------------- greedy vs naive
def naive_greedy(value, g, start, budget, k):
    """k forced cells (the start and its k - 1 nearest; k = 1: the start alone)."""
    L = g.shape[0]
    d2 = ((g - g[start]) ** 2).sum(1)
    P = [int(q) for q in np.lexsort((np.arange(L), d2))[:k]]
    while True:
        v0, c0 = value(P), naive_tour(g, P)[0]
        best = None
        for x in range(L):
            if x in P or d2[x] > (budget + 1e-6) ** 2:
                continue
            c1 = naive_tour(g, P + [x])[0]
            if c1 > budget + 1e-9:
                continue
            ratio = (value(P + [x]) - v0) / max(c1 - c0, 1e-12)
            if best is None or ratio > best[0]:
                best = (ratio, x)
        if best is None or not best[0] > 0:
            return P
        P.append(best[1])


@pytest.mark.parametrize("seed", range(6))
def test_greedy_posterior_criteria_equal_naive(seed):
    rng = np.random.default_rng(seed)
    ny, nx = rng.integers(5, 9, size=2)
    mask = rng.random((ny, nx)) > 0.15
    region = grid_region(int(ny), int(nx), mask)
    L = region.n_cells
    k = int(rng.integers(2, 4))
    Y = rng.normal(size=(k, L))
    A = rng.normal(size=(k, k))
    P0 = A @ A.T + 0.3 * np.eye(k)
    S0 = np.linalg.inv(P0)
    nv = rng.uniform(0.3, 2.0, L)
    cov = ResidualCovariance("exponential", sill=0.5, range=1.5, nugget=0.1)
    g = region.grid_index
    start = int(rng.integers(L))
    budget = float(rng.integers(3, 10))
    W = Y @ Y.T

    def neg_aopt(P):
        M = _M(Y, P0, nv, np.array(P, dtype=int))
        return -np.trace(np.linalg.solve(M, W))

    def neg_gp(P):
        return -brute_total_variance(Y, region, cov, S0, P, np.ones(L))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pa = plan_greedy(Y, region, start, budget, criterion="a-optimal", progress=False,
                         prior=PriorTerms(prior_precision=P0, noise_var=nv))
        pg = plan_greedy(Y, region, start, budget, criterion="gp-variance", progress=False,
                         prior=PriorTerms(prior_cov=S0, spatial_cov=cov))
        ps = plan_greedy(Y, region, start, budget, criterion="gp-variance", progress=False,
                         initial="start", prior=PriorTerms(prior_cov=S0, spatial_cov=cov))
    assert pa.cells.tolist() == naive_greedy(neg_aopt, g, start, budget, k)
    assert pg.cells.tolist() == naive_greedy(neg_gp, g, start, budget, k)
    assert ps.cells.tolist() == naive_greedy(neg_gp, g, start, budget, 1)
    assert ps.cells[0] == start


# --------------------------------------------------------------------------- scalable gp-variance
@pytest.mark.parametrize("anisotropy", [1.0, 2.5])
def test_grid_convolution_equals_brute_force(anisotropy):
    from lrm_cvx.information import GridConv

    rng = np.random.default_rng(0)
    win, out = (2, 3, 7, 9), (4, 5, 3, 4)

    def h(d):
        return np.exp(-np.asarray(d) / 1.7)

    f = rng.normal(size=(7, 9))
    got = GridConv(win, out, h, anisotropy)(f)
    ref = np.zeros((3, 4))
    for a in range(3):
        for b in range(4):
            for i in range(7):
                for j in range(9):
                    ref[a, b] += f[i, j] * h(np.hypot(win[0] + i - out[0] - a,
                                                      (win[1] + j - out[1] - b) / anisotropy))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-13)


def _brute_gains(Y, region, cov, S0, cells, c, pool):
    """sum_i c_i C(i, x)^2 / (C(x, x) + noise) from the dense posterior covariance."""
    g = region.grid_index.astype(float)
    K = Y.T @ S0 @ Y + cov.covariance(cdist(g, g), nugget=False)
    noise = max(cov.nugget, 1e-9 * cov.total_variance)
    if len(cells):
        P = np.asarray(cells)
        K = K - K[:, P] @ np.linalg.solve(K[np.ix_(P, P)] + noise * np.eye(P.size), K[P, :])
    C = K[:, pool]
    return (c[:, None] * C * C).sum(0) / (C[pool, np.arange(pool.size)] + noise)


@pytest.mark.parametrize("seed,model", [(0, "exponential"), (1, "matern32"), (2, "gaussian"),
                                        (3, "exponential")])
def test_structured_gp_oracle_equals_dense_and_brute_force(seed, model):
    from lrm_cvx.information import StructuredGPVarianceOracle

    rng = np.random.default_rng(seed)
    ny, nx = (int(v) for v in rng.integers(9, 15, size=2))
    region = grid_region(ny, nx, rng.random((ny, nx)) > 0.2)
    L = region.n_cells
    k = int(rng.integers(1, 5))
    Y = rng.normal(size=(k, L))
    A = rng.normal(size=(k, k))
    S0 = A @ A.T + 0.2 * np.eye(k)
    cov = ResidualCovariance(model, sill=float(rng.uniform(0.2, 1.0)),
                             range=float(rng.uniform(0.8, 3.0)),
                             nugget=float(rng.choice([0.0, 0.05])))
    c = rng.uniform(0.5, 1.5, L)
    T = np.sort(rng.choice(L, L // 2, replace=False)) if seed % 2 else None
    cw = c if T is None else np.where(np.isin(np.arange(L), T), c, 0.0)
    pool = np.sort(rng.choice(L, L // 2, replace=False))
    init = [int(v) for v in rng.choice(L, 2, replace=False)]  # not necessarily in the pool
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0, pool=pool, targets=T,
              target_weights=c)
    d = GPVarianceOracle(Y, init, **kw)
    s = StructuredGPVarianceOracle(Y, init, **kw)
    cells = list(init)
    for _ in range(8):
        gd, gs = d.gains(pool), s.gains(pool)
        gb = _brute_gains(Y, region, cov, S0, cells, cw, pool)
        # unobserved cells: relative 1e-9; already observed ones (gain ~ 0, N / (C + noise)
        # with both tiny): 1e-9 of the largest gain, 1e-6 for the Gaussian kernel without nugget
        new = ~np.isin(pool, cells)
        np.testing.assert_allclose(gs[new], gb[new], rtol=1e-9)
        np.testing.assert_allclose(gs[new], gd[new], rtol=1e-9)
        tol = 1e-6 if model == "gaussian" and cov.nugget == 0 else 1e-9
        np.testing.assert_allclose(gs, gb, rtol=0, atol=tol * gb.max())
        np.testing.assert_allclose(s.gains(pool[::3]), gs[::3], rtol=0, atol=0)
        assert s.value == pytest.approx(d.value, rel=1e-10)
        assert s.value == pytest.approx(brute_total_variance(Y, region, cov, S0, cells, cw),
                                        rel=1e-10)
        best = int(pool[np.argmax(gd)])
        assert best == int(pool[np.argmax(gs)])
        d.add(best)
        s.add(best)
        cells.append(best)
    assert s.cells == cells
    with pytest.raises(PlanningError):
        s.gains([int(np.setdiff1d(np.arange(L), pool)[0])])


def test_structured_gp_truncation_is_the_only_approximation():
    """On a grid much larger than the covariance's reach the g-window is clipped; the
    default truncation (1e-9) still agrees with the dense oracle, a coarse one does not."""
    from lrm_cvx.information import StructuredGPVarianceOracle

    rng = np.random.default_rng(7)
    region = grid_region(40, 36)
    L = region.n_cells
    Y = rng.normal(size=(2, L))
    S0 = np.diag([1.0, 0.3])
    cov = ResidualCovariance("exponential", sill=1.0, range=0.7, nugget=0.01)
    gi = region.grid_index
    pool = np.flatnonzero((np.abs(gi[:, 0] - 20) <= 2) & (np.abs(gi[:, 1] - 18) <= 2))
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0, pool=pool)
    d = GPVarianceOracle(Y, [int(pool[0])], **kw)
    exact = StructuredGPVarianceOracle(Y, [int(pool[0])], **kw)
    coarse = StructuredGPVarianceOracle(Y, [int(pool[0])], truncation=0.5, **kw)
    assert exact._wg[2] < 40 and exact._wg[3] < 36  # the window really is clipped
    for add in (int(pool[7]), int(pool[20])):
        d.add(add)
        exact.add(add)
        coarse.add(add)
    np.testing.assert_allclose(exact.gains(pool), d.gains(pool), rtol=1e-9)
    assert np.max(np.abs(coarse.gains(pool) / d.gains(pool) - 1)) > 1e-6
    with pytest.raises(PlanningError):
        StructuredGPVarianceOracle(Y, [], truncation=1.5, **kw)


def test_make_oracle_switches_to_structured_and_greedy_picks_are_unchanged(monkeypatch):
    import lrm_cvx.information as info

    rng = np.random.default_rng(11)
    region = grid_region(9, 10, rng.random((9, 10)) > 0.15)
    L = region.n_cells
    Y = rng.normal(size=(2, L))
    S0 = np.array([[1.0, 0.2], [0.2, 0.4]])
    cov = ResidualCovariance("exponential", sill=0.5, range=1.5, nugget=0.1)
    kw = dict(region=region, spatial_cov=cov, prior_cov=S0)
    assert type(info.make_oracle("gp-variance", Y, 0.0, [0], **kw)) is GPVarianceOracle
    assert type(info.make_oracle("gp-variance", Y, 0.0, [0], gp_method="structured", **kw)
                ) is info.StructuredGPVarianceOracle
    with pytest.raises(PlanningError):
        info.make_oracle("gp-variance", Y, 0.0, [0], gp_method="sparse", **kw)
    km = ResidualCovariance("exponential", sill=0.5, range=100.0, metric="km")
    with pytest.raises(PlanningError):
        info.StructuredGPVarianceOracle(Y, [0], region=region, spatial_cov=km, prior_cov=S0)
    start = int(rng.integers(L))
    plans = {}
    for thr in (1e30, 0.0):
        monkeypatch.setattr(info, "GP_STRUCTURED_MIN_ENTRIES", thr)
        assert type(info.make_oracle("gp-variance", Y, 0.0, [0], **kw)) is (
            GPVarianceOracle if thr else info.StructuredGPVarianceOracle)
        # km metric always stays dense
        assert type(info.make_oracle("gp-variance", Y, 0.0, [0], region=region,
                                     spatial_cov=km, prior_cov=S0)) is GPVarianceOracle
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plans[thr] = [plan_greedy(Y, region, start, 7.0, criterion="gp-variance",
                                      progress=False, initial=ini,
                                      prior=PriorTerms(prior_cov=S0,
                                                       spatial_cov=cov)).cells.tolist()
                          for ini in ("nearest", "start")]

    def neg_gp(P):
        return -brute_total_variance(Y, region, cov, S0, P, np.ones(L))

    assert plans[0.0] == plans[1e30]
    assert plans[0.0][1] == naive_greedy(neg_gp, region.grid_index, start, 7.0, 1)


# --------------------------------------------------------------------------- evaluation
def test_evaluate_with_predictive_options(data):
    kw = dict(rank=3, n_test=4, budgets=(6.0,), n_starts=2,
              progress=False, seed=0,
              planning=PlanningOptions(random_trials=2, certify=False))
    ds = evaluate(data, methods=("greedy", "greedy:a-optimal", "greedy:gp-variance", "random"),
                  scoring=ScoringOptions(min_observations=4,
                                         model_params=dict(offset=True, spatial="exponential"),
                                         fold_in=dict(prior="empirical", spatial=True)),
                  **kw)
    assert "complete_mse_model" in ds
    assert np.isfinite(ds["mse"].sel({"method": "greedy:gp-variance"})).any()
    # the error of one plan equals a manual completion with the same model
    train = data.isel(time=slice(None, -4))
    test = data.isel(time=slice(-4, None))
    m = GLRM(3, random_state=0, progress=False, offset=True, spatial="exponential").fit(train)
    start = int(ds["start_cell"][0])
    plan = plan_greedy(m.Y_, m.region_, start, 6.0, criterion="a-optimal", progress=False,
                       initial="start", refine="lines", **m.planner_kwargs())
    vals = m.region_.stack(test)
    t = 0
    obs = {int(c): float(vals[t, c]) for c in plan.cells if np.isfinite(vals[t, c])}
    pred = cells_of(m, m.complete(obs, prior="empirical", spatial=True)["prediction"])
    ref = np.nanmean((pred - vals[t]) ** 2)
    got = float(ds["mse"].sel({"method": "greedy:a-optimal"}).isel(budget=0, start=0,
                                                                     trial=0, test_time=t))
    assert got == pytest.approx(ref, rel=1e-6)
    # the paper's protocol is untouched
    base = evaluate(data, methods=("greedy",), paper=True,
                    scoring=ScoringOptions(min_observations=4), **kw)
    assert "complete_mse_model" not in base
