"""``GLRM(offset=True)`` fits the per-cell offset jointly with the factors (glrm/offset.py).

Against a naive alternating reference written from the objective (dense per-cell and per-time
least squares), the closed form of fully observed data (the column mean), the objective's
monotone decrease, the in-memory vs dask fits, and a planted field whose cells are clouded in
one season (values missing not at random), where the old centring was biased.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.offset import OFFSET_PRIOR_OBS

FIT = dict(progress=False, random_state=0)


def quiet(model, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return model.fit(*args, **kw)


def clouded(T=60, L=300, k=2, seed=0, noise=0.2):
    """``(truth, data with NaN)``, ``(T, L)``: a seasonal rank-``k`` field plus a per-cell mean;
    60 % of the cells lose 85 % of their values in the season when the first component is low
    (clouds in the wet season), every cell 10 % at random."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    X = np.vstack([np.sin(2 * np.pi * t / 12), np.cos(2 * np.pi * t / 12)]
                  + [0.5 * rng.standard_normal(T) for _ in range(k - 2)])
    Y = rng.standard_normal((k, L))
    truth = X.T @ Y + 2.0 * rng.standard_normal(L)
    cloudy = rng.random(L) < 0.6
    p = np.where((X[0][:, None] < -0.3) & cloudy[None, :], 0.85, 0.1)
    seen = rng.random((T, L)) > p
    seen[:, 0] = True  # every time has values
    data = np.where(seen, truth + noise * rng.standard_normal((T, L)), np.nan)
    return truth, data


def clouded_grid(seed: int, T: int = 36, ny: int = 20, nx: int = 15) -> xr.DataArray:
    """:func:`clouded` data as a ``(time, lat, lon)`` DataArray (for the dask fit)."""
    _, D = clouded(T=T, L=ny * nx, k=2, seed=seed)
    return xr.DataArray(D.reshape(T, ny, nx), dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T), "lat": np.arange(float(ny)),
                                "lon": np.arange(float(nx))})


def naive_joint(Z, M, X0, n_iter, lam_y=0.0, lam_x=0.0):
    """The objective of glrm/offset.py minimised by alternating dense least squares from
    ``X0``: per cell ``[y; o]`` with ridge ``(lam_y, ..., lam_y, n0)``, per time ``x`` with
    ``o`` fixed. ``Z`` the observed-mean-centred data (0 where ``M`` is False)."""
    k, T = X0.shape
    L = Z.shape[1]
    X, Y, o = X0.copy(), np.zeros((k, L)), np.zeros(L)
    ridge = np.diag(np.append(np.full(k, lam_y), OFFSET_PRIOR_OBS))
    for _ in range(n_iter):
        Xa = np.vstack([X, np.ones(T)])
        for j in range(L):
            A = Xa[:, M[:, j]]
            sol = np.linalg.solve(A @ A.T + ridge, A @ Z[M[:, j], j])
            Y[:, j], o[j] = sol[:k], sol[k]
        for t in range(T):
            B = Y[:, M[t]]
            X[:, t] = np.linalg.solve(B @ B.T + lam_x * np.eye(k), B @ (Z[t, M[t]] - o[M[t]]))
    return X, Y, o


def objective(Z, M, X, Y, o, lam_y=0.0, lam_x=0.0):
    R = np.where(M, Z - X.T @ Y - o, 0.0)
    return (np.sum(R ** 2) + lam_x * np.sum(X ** 2) + lam_y * np.sum(Y ** 2)
            + OFFSET_PRIOR_OBS * np.sum(o ** 2))


@pytest.mark.parametrize("reg", [None, "ridge"])
def test_equals_the_naive_alternating_reference(reg):
    _, D = clouded(T=30, L=80, k=3, seed=1)
    M = ~np.isnan(D)
    kw = dict(offset=True, reg=reg, **FIT)
    X0 = np.asarray(quiet(GLRM(3, max_iter=0, **kw), D).X_)  # the shared initialisation
    m = quiet(GLRM(3, max_iter=6, tol=0, **kw), D)
    mean = np.nanmean(D, axis=0)
    Z = np.where(M, D - mean, 0.0)
    lam = 1.0 if reg else 0.0
    X, Y, o = naive_joint(Z, M, X0, 6, lam, lam)
    np.testing.assert_allclose(m.offset_, mean + o, rtol=0, atol=1e-8)
    np.testing.assert_allclose(m._Xv.T @ m._Yv, X.T @ Y, rtol=0, atol=1e-8)
    assert m.objective_[-1] == pytest.approx(objective(Z, M, X, Y, o, lam, lam), rel=1e-10)


def test_objective_never_increases_and_the_offset_solves_its_normal_equation():
    for seed in range(4):
        _, D = clouded(T=40, L=120, k=3, seed=seed)
        m = quiet(GLRM(3, offset=True, max_iter=40, tol=0, **FIT), D)
        h = np.asarray(m.objective_)
        assert np.all(np.diff(h) <= 1e-10 * np.abs(h[:-1])), seed
    # after a Y step (a converged fit stops there) each cell's residuals sum to n0 o
    m = quiet(GLRM(3, offset=True, max_iter=500, tol=1e-10, **FIT), D)
    assert m.converged_
    M = ~np.isnan(D)
    o = m.offset_ - np.nanmean(D, axis=0)
    R = np.where(M, D - m.offset_ - m._Xv.T @ m._Yv, 0.0)
    np.testing.assert_allclose(R.sum(axis=0), OFFSET_PRIOR_OBS * o, atol=1e-8)


def test_fully_observed_the_offset_is_the_column_mean_and_the_fit_the_centred_one():
    rng = np.random.default_rng(3)
    D = rng.standard_normal((25, 3)) @ rng.standard_normal((3, 60)) + 4.0 * rng.random(60)
    D += 0.1 * rng.standard_normal(D.shape)
    m = quiet(GLRM(3, offset=True, max_iter=30, **FIT), D)
    mean = D.mean(axis=0)
    np.testing.assert_allclose(m.offset_, mean, rtol=0, atol=1e-10)
    c = quiet(GLRM(3, max_iter=30, **FIT), D - mean)  # the best rank-3 fit of centred data
    np.testing.assert_allclose(m._Xv.T @ m._Yv, c._Xv.T @ c._Yv, rtol=0, atol=1e-8)


def test_clouded_season_is_recovered_where_centring_was_biased():
    truth, D = clouded(seed=2)
    M = ~np.isnan(D)
    joint = quiet(GLRM(2, offset=True, max_iter=200, **FIT), D)
    # the old offset: the observed mean, then a plain low-rank fit of the centred data
    mean = np.nanmean(D, axis=0)
    centred = quiet(GLRM(2, max_iter=200, **FIT), D - mean)
    err_joint = (joint.reconstruct().astype(float) - truth)[~M]
    err_centred = (centred._Xv.T @ centred._Yv + mean - truth)[~M]
    mse_joint, mse_centred = np.mean(err_joint ** 2), np.mean(err_centred ** 2)
    assert mse_centred > 0.05  # the clouds bias the observed mean (noise var 0.04 on seen)
    assert mse_joint < 0.2 * mse_centred
    # the offset itself is the cell's mean over all times, not over the clear ones
    assert (np.mean((joint.offset_ - truth.mean(0)) ** 2)
            < 0.5 * np.mean((mean - truth.mean(0)) ** 2))


def test_dask_fit_is_the_in_memory_joint_fit():
    pytest.importorskip("dask")
    da = clouded_grid(seed=4)
    kw = dict(offset=True, scale=True, max_iter=15, tol=0, **FIT)
    ref = quiet(GLRM(2, **kw), da)
    out = quiet(GLRM(2, dask={"chunk_mb": 0.01, "block_mb": 0.05}, **kw),
                da.chunk({"time": 7}))
    assert np.abs(ref.offset_ - np.nanmean(ref.region_.stack(da), axis=0)).max() > 1e-3
    np.testing.assert_allclose(out.offset_, ref.offset_, rtol=0, atol=1e-6)
    np.testing.assert_allclose(out.objective_, ref.objective_, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(out.reconstruct()), np.asarray(ref.reconstruct()),
                               rtol=0, atol=1e-5)


def test_huber_inside_its_quadratic_zone_is_the_quadratic_joint_fit():
    """A Huber loss whose delta exceeds every residual is ``r^2``: its majorise-minimise steps
    with the offset's row (fit.x_block_offset, offset.OffsetRidge) are the exact ones."""
    from lrm_cvx.glrm.losses import Huber

    _, D = clouded(T=30, L=80, k=3, seed=5)
    kw = dict(offset=True, max_iter=8, tol=0, **FIT)
    quad = quiet(GLRM(3, **kw), D)
    huber = quiet(GLRM(3, loss=Huber(1e6), **kw), D)
    np.testing.assert_allclose(huber.offset_, quad.offset_, rtol=0, atol=1e-8)
    np.testing.assert_allclose(huber._Xv.T @ huber._Yv, quad._Xv.T @ quad._Yv, atol=1e-8)
    np.testing.assert_allclose(huber.objective_, quad.objective_, rtol=1e-10)


@pytest.mark.parametrize("loss", ["huber", "absolute", "quantile"])
def test_robust_losses_fit_the_offset_jointly_and_never_increase(loss):
    truth, D = clouded(T=40, L=150, k=2, seed=6)
    rng = np.random.default_rng(0)
    seen = np.flatnonzero(~np.isnan(D))
    D.flat[rng.choice(seen, 60, replace=False)] += 25.0  # gross errors (residual clouds)
    M = ~np.isnan(D)
    joint = quiet(GLRM(2, loss=loss, offset=True, max_iter=60, tol=0, **FIT), D)
    h = np.asarray(joint.objective_)
    assert np.all(np.diff(h) <= 1e-9 * np.abs(h[:-1]))
    mean = np.nanmean(D, axis=0)
    centred = quiet(GLRM(2, loss=loss, max_iter=60, tol=0, **FIT), D - mean)
    err_j = np.mean((joint.reconstruct().astype(float) - truth)[~M] ** 2)
    err_c = np.mean((centred._Xv.T @ centred._Yv + mean - truth)[~M] ** 2)
    assert err_j < 0.5 * err_c


def test_l1_factors_keep_the_observed_mean():
    _, D = clouded(T=30, L=80, k=2, seed=7)
    m = quiet(GLRM(2, offset=True, reg=(None, "l1"), max_iter=5, **FIT), D)
    np.testing.assert_allclose(m.offset_, np.nanmean(D, axis=0), rtol=1e-12)


def test_dask_robust_loss_is_the_in_memory_joint_fit():
    pytest.importorskip("dask")
    da = clouded_grid(seed=8)
    kw = dict(offset=True, loss="huber", reg=("ridge", None), max_iter=6, tol=0, **FIT)
    ref = quiet(GLRM(2, **kw), da)
    out = quiet(GLRM(2, dask={"chunk_mb": 0.01, "block_mb": 0.05}, **kw),
                da.chunk({"time": 7}))
    np.testing.assert_allclose(out.offset_, ref.offset_, rtol=0, atol=1e-6)
    np.testing.assert_allclose(out.objective_, ref.objective_, rtol=1e-7)
