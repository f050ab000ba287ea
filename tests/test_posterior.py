"""The latent belief (belief/posterior.py) against naive dense references on tiny problems."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist

from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel, empirical_moments
from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions
from lrm_cvx.glrm import GLRM
from lrm_cvx.spatial import ResidualCovariance


def problem(seed, k=3, L=25, offset=True, scale=True, per_cell=True):
    rng = np.random.default_rng(seed)
    Y = rng.normal(size=(k, L))
    off = rng.normal(10, 3, L) if offset else None
    sc = rng.uniform(0.5, 3.0, L) if scale else None
    nv = rng.uniform(0.2, 2.0, L) if per_cell else 0.7
    return rng, ObservationModel(Y, offset=off, scale=sc, noise_var=nv)


def naive_blr(obs, m0, P0, cells, values):
    """Dense Bayesian linear regression in fit units: solve the normal equations."""
    Y = obs.Y
    off = np.zeros(obs.n_cells) if obs.offset is None else obs.offset
    sc = np.ones(obs.n_cells) if obs.scale is None else obs.scale
    nv = np.broadcast_to(obs.noise_var, (obs.n_cells,))
    z = (values - off[cells]) / sc[cells]
    Ys = Y[:, cells]
    W = np.diag(1.0 / nv[cells])
    A = Ys @ W @ Ys.T + P0
    mean = np.linalg.solve(A, Ys @ W @ z + P0 @ m0)
    cov = np.linalg.inv(A)
    pred = sc * (Y.T @ mean) + off
    std = sc * np.sqrt(np.diag(Y.T @ cov @ Y))
    pstd = sc * np.sqrt(np.diag(Y.T @ cov @ Y) + nv)
    return mean, cov, pred, std, pstd


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("offset,scale,per_cell", [(True, True, True), (False, False, False),
                                                   (True, False, True)])
def test_update_equals_naive_bayesian_regression(seed, offset, scale, per_cell):
    rng, obs = problem(seed, offset=offset, scale=scale, per_cell=per_cell)
    k = obs.k
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + 0.3 * np.eye(k)
    m0 = rng.normal(size=k)
    cells = rng.choice(obs.n_cells, 6, replace=False)
    values = rng.normal(10, 4, 6)
    post = LatentPosterior.prior(obs, "custom", mean=m0, cov=S0).update(cells, values)
    mean, cov, pred, std, pstd = naive_blr(obs, m0, np.linalg.inv(S0), cells, values)
    np.testing.assert_allclose(post.mean, mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(post.cov, cov, rtol=1e-9, atol=1e-12)
    mu, sd = post.predict()
    np.testing.assert_allclose(mu, pred, rtol=1e-9)
    np.testing.assert_allclose(sd, std, rtol=1e-8)
    np.testing.assert_allclose(post.predictive_std(), pstd, rtol=1e-8)
    mc, sc_ = post.predict(cells=[3, 0])
    np.testing.assert_allclose(mc, pred[[3, 0]], rtol=1e-9)
    np.testing.assert_allclose(sc_, std[[3, 0]], rtol=1e-8)
    for sel in (None, [3, 0]):  # the one-pass maps equal the naive ones
        i = slice(None) if sel is None else sel
        ma, sa, pa = post.predict_all(cells=sel)
        np.testing.assert_allclose(ma, pred[i], rtol=1e-9)
        np.testing.assert_allclose(sa, std[i], rtol=1e-8)
        np.testing.assert_allclose(pa, pstd[i], rtol=1e-8)


def test_flat_prior_is_the_papers_least_squares_fold_in():
    rng, obs = problem(1, per_cell=False)
    cells = np.array([2, 5, 11, 17, 20])
    values = rng.normal(size=5)
    post = LatentPosterior.prior(obs, "flat").update(cells, values)
    z = (values - obs.offset[cells]) / obs.scale[cells]
    x = np.linalg.lstsq(obs.Y[:, cells].T, z, rcond=None)[0]
    np.testing.assert_allclose(post.mean, x, rtol=1e-10)
    Ys = obs.Y[:, cells]
    np.testing.assert_allclose(post.cov, 0.7 * np.linalg.inv(Ys @ Ys.T), rtol=1e-10)
    # the ridge prior: (Y_S Y_S^T + ridge I)^-1 Y_S z and sigma^2 (...)^-1
    r = LatentPosterior.prior(obs, "ridge", ridge=0.3).update(cells[:2], values[:2])
    A = Ys[:, :2] @ Ys[:, :2].T + 0.3 * np.eye(3)
    np.testing.assert_allclose(r.mean, np.linalg.solve(A, Ys[:, :2] @ z[:2]), rtol=1e-10)
    np.testing.assert_allclose(r.cov, 0.7 * np.linalg.inv(A), rtol=1e-10)
    assert LatentPosterior.prior(obs, "flat", ridge=0.3).precision[0, 0] == pytest.approx(
        0.3 / 0.7)
    # too few cells without a prior: a clear ModelError, not a LinAlgError
    few = LatentPosterior.prior(obs, "flat").update(cells[:2], values[:2])
    assert not few.is_proper
    with pytest.raises(ModelError, match="singular"):
        few.predict()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), split=st.integers(0, 8))
def test_sequential_updates_equal_one_batch(seed, split):
    rng, obs = problem(seed)
    cells = rng.integers(0, obs.n_cells, 8)  # repeats allowed: independent measurements
    values = rng.normal(10, 3, 8)
    p0 = LatentPosterior.prior(obs, "flat")
    batch = p0.update(cells, values)
    seq = p0.update(cells[:split], values[:split]).update(cells[split:], values[split:])
    np.testing.assert_allclose(seq.precision, batch.precision, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(seq.shift, batch.shift, rtol=1e-10, atol=1e-12)
    assert seq.cells.tolist() == batch.cells.tolist()


def test_batch_means_equal_one_update_per_snapshot():
    rng, obs = problem(6)
    cells = np.array([1, 4, 4, 9, 12, 20])
    V = rng.normal(10, 3, (5, cells.size))
    V[rng.random(V.shape) < 0.3] = np.nan
    V[0, :] = np.nan
    V[1, 1:] = np.nan  # one cell: improper without a prior
    for prior in (LatentPosterior.prior(obs, "flat"),
                  LatentPosterior.prior(obs, "custom", mean=np.ones(3), cov=2 * np.eye(3))):
        means, proper = prior.batch_means(cells, V)
        for t in range(V.shape[0]):
            post = prior.update(cells, V[t])
            assert proper[t] == post.is_proper
            if post.is_proper:
                np.testing.assert_allclose(means[t], post.mean, rtol=1e-9, atol=1e-12)
            else:
                assert np.isnan(means[t]).all()
    assert proper[0]  # with a prior even an empty snapshot is proper
    with pytest.raises(DataError):
        prior.batch_means(cells, V[:, :2])


def test_duplicates_are_repeated_independent_measurements():
    rng, obs = problem(3)
    cells = np.array([1, 4, 4, 9, 12])
    values = np.array([9.0, 10.0, 12.0, 11.0, 8.0])
    post = LatentPosterior.prior(obs, "flat").update(cells, values)
    mean, cov, *_ = naive_blr(obs, np.zeros(3), np.zeros((3, 3)), cells, values)
    np.testing.assert_allclose(post.mean, mean, rtol=1e-9)
    np.testing.assert_allclose(post.cov, cov, rtol=1e-9)


def test_float_cells_nan_values_and_empty_observations():
    rng, obs = problem(4)
    p0 = LatentPosterior.prior(obs, "ridge", ridge=1.0)
    with pytest.raises(DataError, match="12.7"):
        p0.update([12.7, 3], [1.0, 2.0])
    with pytest.raises(DataError, match="integer"):
        p0.update(np.array([True, False]), [1.0, 2.0])
    with pytest.raises(DataError, match=r"\[0, 25\)"):
        p0.update([25], [1.0])
    with pytest.raises(DataError, match="shape"):
        p0.update([1, 2], [1.0])
    with pytest.raises(DataError, match="finite"):
        p0.update([1, 2], [1.0, np.inf])
    a = p0.update([3.0, 7.0], [1.0, 2.0])  # integral floats are fine
    b = p0.update([3, 7], [1.0, 2.0])
    np.testing.assert_array_equal(a.mean, b.mean)
    assert p0.update([], []) is p0
    assert p0.update(np.array([], dtype=float), np.array([])) is p0
    c = p0.update([3, 5, 7], [1.0, np.nan, 2.0])
    assert c.n_dropped == 1 and c.cells.tolist() == [3, 7]
    np.testing.assert_array_equal(c.mean, b.mean)
    d = p0.update([5], [np.nan])
    assert d.n_dropped == 1 and d.cells.size == 0
    np.testing.assert_array_equal(d.mean, p0.mean)


def test_propagate_with_zero_dynamics_gives_back_the_prior_exactly():
    rng, obs = problem(5)
    k = obs.k
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + np.eye(k)
    m0 = rng.normal(size=k)
    prior = LatentPosterior.prior(obs, "custom", mean=m0, cov=S0)
    post = prior.update([1, 2, 3, 4], rng.normal(10, 2, 4))
    again = post.propagate(np.zeros((k, k)), S0, c=m0)
    np.testing.assert_array_equal(again.mean, prior.mean)
    np.testing.assert_array_equal(again.cov, prior.cov)
    np.testing.assert_array_equal(again.precision, prior.precision)
    assert again.cells.size == 0
    # and from a flat belief too
    flat = LatentPosterior.prior(obs, "flat")
    np.testing.assert_array_equal(flat.propagate(np.zeros((k, k)), S0, m0).cov, S0)
    # general A: the Kalman time update
    A = 0.5 * rng.normal(size=(k, k))
    Q = 0.1 * np.eye(k)
    nxt = post.propagate(A, Q)
    np.testing.assert_allclose(nxt.mean, A @ post.mean, rtol=1e-12)
    np.testing.assert_allclose(nxt.cov, A @ post.cov @ A.T + Q, rtol=1e-12)
    with pytest.raises(ModelError):
        flat.propagate(A, Q)  # an improper belief has no mean to move
    with pytest.raises(ModelError, match="A must be"):
        post.propagate(np.eye(k + 1), Q)


def test_empirical_prior_and_information_from_a_model():
    rng = np.random.default_rng(0)
    T, L, k = 20, 30, 3
    D = rng.normal(size=(T, k)) @ rng.normal(size=(k, L)) + 50 + 0.1 * rng.normal(size=(T, L))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = GLRM(k, progress=False, random_state=0, offset=True, scale=True,
                 noise="per-cell", max_iter=30).fit(D)
    p = LatentPosterior.prior(m)
    m0, S0 = empirical_moments(m._Xv)
    np.testing.assert_allclose(p.mean, m._Xv.mean(1))
    np.testing.assert_array_equal(p.cov, S0)
    info = p.information()
    np.testing.assert_allclose(info["prior_precision"], np.linalg.inv(S0), rtol=1e-8, atol=1e-12)
    # a new snapshot's noise: n / (n - k) times the fitted one (20 snapshots, rank 3 + offset)
    np.testing.assert_allclose(info["noise_var"], m.noise_var_ * 20 / 16, rtol=1e-12)
    np.testing.assert_allclose(info["target_weights"], m.scale_ ** 2)
    assert "spatial_cov" not in info
    assert LatentPosterior.prior(m, "flat").information()["prior_precision"] is None
    with pytest.raises(ModelError, match="kind"):
        LatentPosterior.prior(m, "gaussian")
    with pytest.raises(ModelError, match="needs the fitted model"):
        LatentPosterior.prior(p.obs_model, "empirical")
    with pytest.raises(ModelError, match="spatial"):
        p.predict(spatial=True)


# --------------------------------------------------------------------------- spatial
def grid_obs(seed, ny=5, nx=6, k=2, nugget=0.05):
    from lrm_cvx import Region

    rng = np.random.default_rng(seed)
    region = Region(lat=xr.DataArray(np.arange(ny) * 1.0, dims="lat",
                                     coords={"lat": np.arange(ny) * 1.0}),
                    lon=xr.DataArray(np.arange(nx) * 1.0, dims="lon",
                                     coords={"lon": np.arange(nx) * 1.0}),
                    mask=np.ones((ny, nx), bool))
    L = region.n_cells
    cov = ResidualCovariance("exponential", sill=0.4, range=1.6, nugget=nugget)
    obs = ObservationModel(rng.normal(size=(k, L)), offset=rng.normal(5, 1, L),
                           scale=rng.uniform(0.5, 2, L), noise_var=0.3, spatial_cov=cov,
                           region=region)
    return rng, obs


def gp_conditional(obs, m0, S0, cells, z):
    """Brute force: the joint Gaussian of f = Y^T x + r at every cell, conditioned on noisy z."""
    g = obs.region.grid_index.astype(float)
    K = obs.Y.T @ S0 @ obs.Y + obs.spatial_cov.covariance(cdist(g, g), nugget=False)
    mu = obs.Y.T @ m0
    A = K[np.ix_(cells, cells)] + obs.spatial_cov.nugget * np.eye(cells.size)
    mean = mu + K[:, cells] @ np.linalg.solve(A, z - mu[cells])
    var = np.diag(K - K[:, cells] @ np.linalg.solve(A, K[cells, :]))
    return mean, var


@pytest.mark.parametrize("seed,fft", [(0, False), (1, False), (2, False), (0, True),
                                      (1, True)])
def test_spatial_update_equals_the_gp_conditional(seed, fft, monkeypatch):
    if fft:  # the whole-map FFT kriging (spatial.krige_grid_fft) instead of direct kriging
        import lrm_cvx.spatial as sp

        monkeypatch.setattr(sp, "FFT_KRIGE_MIN_WORK", 0.0)
    rng, obs = grid_obs(seed)
    k = obs.k
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + 0.5 * np.eye(k)
    m0 = rng.normal(size=k)
    cells = rng.choice(obs.n_cells, 7, replace=False)
    values = rng.normal(5, 1, 7)
    prior = LatentPosterior.prior(obs, "custom", mean=m0, cov=S0)
    post = prior.update(cells[:3], values[:3]).update(cells[3:], values[3:])  # sequential
    z = (values - obs.offset[cells]) / obs.scale[cells]
    mean, var = gp_conditional(obs, m0, S0, cells, z)
    mu, sd = post.predict()
    np.testing.assert_allclose(mu, obs.scale * mean + obs.offset, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(sd ** 2, obs.scale ** 2 * var, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(post.predictive_std() ** 2,
                               obs.scale ** 2 * (var + obs.spatial_cov.nugget), rtol=1e-7)
    ma, sa, pa = post.predict_all()  # one kriging pass, the same three maps
    np.testing.assert_allclose(ma, obs.scale * mean + obs.offset, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(sa ** 2, obs.scale ** 2 * var, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(pa ** 2, obs.scale ** 2 * (var + obs.spatial_cov.nugget),
                               rtol=1e-7)
    # the trend-only prediction is the GLS latent posterior mapped through Y
    mt, _ = post.predict(spatial=False)
    np.testing.assert_allclose(mt, obs.scale * (obs.Y.T @ post.mean) + obs.offset, rtol=1e-10)
    info = post.information()
    assert info["spatial_cov"] is obs.spatial_cov
    np.testing.assert_allclose(info["prior_cov"], post.cov)
    # no observation: the prior field
    mu0, sd0 = prior.predict()
    np.testing.assert_allclose(mu0, obs.scale * (obs.Y.T @ m0) + obs.offset, rtol=1e-10)
    g = obs.region.grid_index.astype(float)
    np.testing.assert_allclose(
        sd0 ** 2, obs.scale ** 2 * (np.einsum("ai,ab,bi->i", obs.Y, S0, obs.Y)
                                    + obs.spatial_cov.sill), rtol=1e-10)
    del g


def test_spatial_repeats_are_averaged_into_one_observation():
    rng, obs = grid_obs(7)
    prior = LatentPosterior.prior(obs, "custom", cov=np.eye(2))
    a = prior.update([3, 3, 8], [5.0, 7.0, 4.0])
    b = prior.update([3, 8], [6.0, 4.0])
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12)
    np.testing.assert_allclose(a.predict()[0], b.predict()[0], rtol=1e-12)


# --------------------------------------------------------------------------- callers
def small_field(seed=0, T=16, ny=6, nx=7, k=2):
    rng = np.random.default_rng(seed)
    data = (rng.normal(size=(T, k)) @ rng.normal(size=(k, ny * nx)) + 50.0
            + np.linspace(0, 8, ny * nx) + 0.2 * rng.normal(size=(T, ny * nx)))
    data = data.reshape(T, ny, nx)
    data[rng.random(data.shape) < 0.2] = np.nan
    return xr.DataArray(data, dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T), "lat": np.arange(ny) * 1.0,
                                "lon": np.arange(nx) * 1.0}, attrs={"units": "K"})


def fit_model(da, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(2, progress=False, random_state=0, max_iter=40, **kw).fit(da)


@pytest.mark.parametrize("kw", [dict(offset=True), dict(offset=True, scale=True),
                                dict(offset=True, scale=True, noise="per-cell"), {}])
def test_complete_mse_is_in_data_units(kw):
    """complete_mse honours the model's offset and scale."""
    from lrm_cvx.evaluation import evaluate

    da = small_field()
    n_test = 4
    m = fit_model(da.isel(time=slice(None, -n_test)), **kw)
    ds = evaluate(da, model=m, n_test=n_test, budgets=(4.0,), n_starts=1,
                  methods=("greedy",), progress=False,
                  paper=True,
                  planning=PlanningOptions(random_trials=1, certify=False),
                  scoring=ScoringOptions(min_observations=2))
    # the paper's fold-in, with the model's offset/scale/noise
    Y = m._Yv
    off = np.zeros(m.n_cells_) if m.offset_ is None else m.offset_
    sc = np.ones(m.n_cells_) if m.scale_ is None else m.scale_
    nv = (np.full(m.n_cells_, m.noise_std_ ** 2) if m.noise_var_ is None else m.noise_var_)
    test = m.region_.stack(da.isel(time=slice(-n_test, None))).astype(float)
    ref = []
    for d in test:
        o = np.flatnonzero(np.isfinite(d))
        w = 1.0 / np.sqrt(nv[o])
        x = np.linalg.lstsq((Y[:, o] * w).T, w * (d[o] - off[o]) / sc[o], rcond=None)[0]
        pred = sc * (Y.T @ x) + off
        ref.append(np.mean((pred[o] - d[o]) ** 2))
    np.testing.assert_allclose(ds["complete_mse"].values, ref, rtol=1e-6)
    assert np.all(ds["complete_mse"].values < 1.0)  # not the square of the mean (50 K)
    # every plan's error is a fold-in from the plan's cells, also in data units
    plan_cells = ds["greedy_route"].values[0, 0]
    plan_cells = plan_cells[plan_cells >= 0]
    checked = 0
    for t, d in enumerate(test):
        o = plan_cells[np.isfinite(d[plan_cells])]
        got = float(ds["mse"].isel(method=0, budget=0, start=0, trial=0, test_time=t))
        if o.size < 2:
            assert np.isnan(got)
            continue
        obs_all = np.flatnonzero(np.isfinite(d))
        pred = m.complete((o, d[o]))["prediction"]
        pred = m.region_.stack(pred).astype(float)
        if np.isnan(got):  # rank-deficient plan cells
            continue
        assert got == pytest.approx(np.mean((pred[obs_all] - d[obs_all]) ** 2), rel=1e-5)
        checked += 1
    assert checked >= 2


def test_complete_pairs_edge_cases():
    m = fit_model(small_field())
    with pytest.raises(ModelError, match="singular"):
        m.complete(([], []))  # no observation, no prior: a clear error, no IndexError
    ds = m.complete(([], []), prior="empirical")  # the prior's map
    mu, _ = m.latent_prior("empirical").predict()
    np.testing.assert_allclose(m.region_.stack(ds["prediction"]), mu, rtol=1e-6)
    assert ds.attrs["n_observations"] == 0
    with pytest.raises(DataError, match="12.7"):
        m.complete({12.7: 50.0, 3: 51.0, 9: 49.0})
    with pytest.raises(DataError, match="12.7"):
        m.complete(([12.7, 3, 9], [50.0, 51.0, 49.0]))
    with pytest.raises(DataError, match="cells but"):
        m.complete(([1, 3], [50.0]))
    a = m.complete(([1, 3, 9, 4], [50.0, np.nan, 49.0, 52.0]))
    b = m.complete(([1, 9, 4], [50.0, 49.0, 52.0]))
    xr.testing.assert_identical(a, b)
    assert a.attrs["n_observations"] == 3
    # a repeated cell: two independent measurements (here equal to one with half the noise)
    c = m.complete(([1, 1, 9, 4], [50.0, 50.0, 49.0, 52.0]))
    assert c.attrs["n_observations"] == 4
    assert np.all(m.region_.stack(c["std"]) <= m.region_.stack(b["std"]) + 1e-12)


def test_plan_greedy_takes_the_posterior_as_prior():
    from lrm_cvx.errors import PlanningError
    from lrm_cvx.planning import PriorTerms, plan_greedy

    da = small_field(3)
    m = fit_model(da, offset=True, noise="per-cell", spatial="exponential")
    for crit, spatial in (("a-optimal", False), ("fisher", False), ("gp-variance", True)):
        terms = PriorTerms(**m.latent_prior("empirical", spatial=spatial).information())
        a = plan_greedy(m.Y_, m.region_, 5, 6.0, criterion=crit, initial="start",
                        progress=False, prior=terms)
        b = plan_greedy(m.Y_, m.region_, 5, 6.0, criterion=crit, initial="start",
                        progress=False, prior=m.latent_prior("empirical", spatial=spatial))
        assert a.cells.tolist() == b.cells.tolist()
    # a posterior that already saw cells plans around them (it differs from the prior's plan)
    post = m.latent_prior("empirical").update([5, 6, 12, 13], [50.0, 51.0, 52.0, 50.5])
    c = plan_greedy(m.Y_, m.region_, 5, 6.0, criterion="a-optimal", initial="start",
                    progress=False, prior=post)
    assert c.cells[0] == 5
    with pytest.raises(TypeError, match="noise_var"):  # the terms come with the prior only
        plan_greedy(m.Y_, m.region_, 5, 6.0, criterion="a-optimal", progress=False,
                    prior=post, noise_var=1.0)
    with pytest.raises(PlanningError, match="LatentPosterior"):
        plan_greedy(m.Y_, m.region_, 5, 6.0, progress=False, prior="empirical")


# ----------------------------------------------------------------------------- adaptive scale
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("spatial", [False, True])
def test_innovation_statistic_equals_the_dense_mahalanobis_norm(seed, spatial):
    from dataclasses import replace

    rng, obs = grid_obs(seed) if spatial else problem(seed, L=30)
    k, L = obs.k, obs.n_cells
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + 0.5 * np.eye(k)
    m0 = rng.normal(size=k)
    cells = np.sort(rng.choice(L, 9, replace=False))
    values = rng.normal(5, 2, cells.size)
    z = obs.to_fit_units(cells, values)
    Ys = obs.Y[:, cells]
    if spatial:
        g = obs.region.grid_index[cells].astype(float)
        R = obs.spatial_cov.covariance(cdist(g, g), nugget=False) + obs.spatial_cov.nugget * np.eye(
            cells.size)
    else:
        R = np.diag(np.broadcast_to(obs.noise_var, (L,))[cells])
    e = z - Ys.T @ m0
    q_ref = float(e @ np.linalg.solve(Ys.T @ S0 @ Ys + R, e))
    prior = LatentPosterior.from_moments(obs, m0, S0)
    q, n = prior.innovation(cells, values)
    assert n == cells.size and q == pytest.approx(q_ref, rel=1e-9)
    # a flat prior: the GLS residual sum of squares, k degrees of freedom fewer
    W = np.linalg.inv(R)
    beta = np.linalg.solve(Ys @ W @ Ys.T, Ys @ W @ z)
    r = z - Ys.T @ beta
    q, n = LatentPosterior.from_moments(obs).innovation(cells, values)
    assert n == cells.size - k and q == pytest.approx(float(r @ W @ r), rel=1e-8)
    # the adaptive scale: (nu s0 + q) / (nu + n) after the update, s0 without observations
    ad = replace(obs, variance_scale=1.7, adaptive_dof=4.0, scale_discount=0.5)
    p0 = LatentPosterior.from_moments(ad, m0, S0)
    assert p0.variance_scale == pytest.approx(1.7)
    post = p0.update(cells, values)
    s = (4.0 * 1.7 + q_ref) / (4.0 + cells.size)
    assert post.variance_scale == pytest.approx(s, rel=1e-9)
    # every output variance carries it; the mean does not change
    fixed = LatentPosterior.from_moments(replace(obs, variance_scale=s), m0, S0).update(
        cells, values)
    for a, b in zip(post.predict_all(), fixed.predict_all(), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9)
    # the next snapshot starts from the discounted evidence of this one
    nxt = post.propagate(np.zeros((k, k)), S0)
    assert nxt.scale_q == pytest.approx(0.5 * q_ref) and nxt.scale_n == pytest.approx(
        0.5 * cells.size)
    assert nxt.variance_scale == pytest.approx((4.0 * 1.7 + 0.5 * q_ref) / (4.0 + 4.5))
    two = post.propagate(np.zeros((k, k)), S0, steps=2)
    assert two.scale_n == pytest.approx(0.25 * cells.size)


def test_innovation_scale_is_unbiased_for_data_from_the_model():
    """q / n_eff averages the true variance scale on data drawn from the model."""
    rng, obs = grid_obs(7)
    k, L = obs.k, obs.n_cells
    S0 = np.eye(k) * 0.8
    prior = LatentPosterior.from_moments(obs, np.zeros(k), S0)
    g = obs.region.grid_index.astype(float)
    K = obs.Y.T @ S0 @ obs.Y + obs.spatial_cov.covariance(cdist(g, g), nugget=False)
    K += obs.spatial_cov.nugget * np.eye(L)
    Lk = np.linalg.cholesky(K)
    s_true = 2.5
    cells = np.arange(0, L, 2)
    qs, ns = [], []
    for _ in range(400):
        f = np.sqrt(s_true) * (Lk @ rng.standard_normal(L))
        vals = obs.offset + obs.scale * f
        q, n = prior.innovation(cells, vals[cells])
        qs.append(q)
        ns.append(n)
    assert np.sum(qs) / np.sum(ns) == pytest.approx(s_true, rel=0.05)


# --------------------------------------------------------------------------- many beliefs
@pytest.mark.parametrize("spatial,fft,local", [(True, False, False), (True, True, False),
                                               (True, False, True), (False, False, False)])
def test_predict_many_equals_one_prediction_per_belief(spatial, fft, local, monkeypatch):
    """One plan's test snapshots share their kriging system: the shared path (one variance,
    the residuals kriged together), the FFT fallback and the local (neighbour) kriging each
    give every belief's own ``predict_all`` and, spatially, the brute-force GP conditional."""
    import lrm_cvx.spatial as sp
    from lrm_cvx.belief.posterior import predict_many

    if fft:
        monkeypatch.setattr(sp, "FFT_KRIGE_MIN_WORK", 0.0)
    if local:
        monkeypatch.setattr(sp, "MAX_DIRECT", 3)
    rng, obs = grid_obs(3)
    if not spatial:
        obs = obs.without_spatial()
    k = obs.k
    B = rng.normal(size=(k, k))
    S0 = B @ B.T + 0.5 * np.eye(k)
    m0 = rng.normal(size=k)
    prior = LatentPosterior.prior(obs, "custom", mean=m0, cov=S0)
    cells = rng.choice(obs.n_cells, 7, replace=False)
    values = rng.normal(5, 1, (4, 7))
    beliefs = [prior.update(cells, v) for v in values]
    targets = np.sort(rng.choice(obs.n_cells, 11, replace=False))
    for where in (None, targets):
        mean, pstd = predict_many(beliefs, cells=where)
        means_only, none = predict_many(beliefs, cells=where, std=False)
        assert none is None
        for i, b in enumerate(beliefs):
            m1, _, p1 = b.predict_all(cells=where)
            np.testing.assert_allclose(mean[i], m1, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(means_only[i], m1, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(pstd[i], p1, rtol=1e-10)
            if spatial and not local and where is None:
                z = (values[i] - obs.offset[cells]) / obs.scale[cells]
                gm, gv = gp_conditional(obs, m0, S0, cells, z)
                np.testing.assert_allclose(mean[i], obs.scale * gm + obs.offset, rtol=1e-8)
                np.testing.assert_allclose(
                    pstd[i] ** 2, obs.scale ** 2 * (gv + obs.spatial_cov.nugget), rtol=1e-7)
    # beliefs at different cells (or one with a repeated cell) are predicted one by one
    mixed = beliefs[:2] + [prior.update(cells[:5], values[2, :5]),
                           prior.update(np.r_[cells, cells[:1]], np.r_[values[3], 4.0])]
    mean, pstd = predict_many(mixed, cells=targets)
    for i, b in enumerate(mixed):
        m1, _, p1 = b.predict_all(cells=targets)
        np.testing.assert_allclose(mean[i], m1, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(pstd[i], p1, rtol=1e-10)
    with pytest.raises(ModelError, match="at least one belief"):
        predict_many([])


@pytest.mark.parametrize("spatial", [True, False])
def test_fold_in_maps_equal_fold_in_snapshots(spatial):
    """Snapshots grouped by the cells they observe (sensors, one with a gap, one empty) give
    each snapshot's own fold-in map."""
    from lrm_cvx.belief.posterior import fold_in_maps, fold_in_snapshots

    rng, obs = grid_obs(11)
    if not spatial:
        obs = obs.without_spatial()
    k = obs.k
    prior = LatentPosterior.prior(obs, "custom", mean=rng.normal(size=k), cov=np.eye(k))
    V = np.full((6, obs.n_cells), np.nan)
    sensors = rng.choice(obs.n_cells, 8, replace=False)
    V[:, sensors] = rng.normal(5, 1, (6, 8))
    V[2, sensors[0]] = np.nan  # a gap
    V[4] = np.nan  # nothing observed: the prior's map
    want, *_ = fold_in_snapshots(prior, V)
    np.testing.assert_allclose(fold_in_maps(prior, V), want, rtol=1e-10, atol=1e-10)
    with pytest.raises(DataError, match="shape"):
        fold_in_maps(prior, V[:, :-1])


def test_pattern_groups_are_the_rows_with_equal_patterns():
    from lrm_cvx.belief.posterior import pattern_groups

    rng = np.random.default_rng(0)
    observed = rng.random((40, 11)) < 0.5
    observed[[3, 17, 29]] = observed[5]
    groups = pattern_groups(observed)
    assert sorted(t for g in groups for t in g) == list(range(40))
    for g in groups:
        assert g == sorted(g) and all((observed[t] == observed[g[0]]).all() for t in g)
    firsts = [observed[g[0]].tobytes() for g in groups]
    assert len(set(firsts)) == len(groups)  # distinct patterns, one group each
    assert [3, 5, 17, 29] in groups
    assert pattern_groups(np.zeros((0, 4), bool)) == []
