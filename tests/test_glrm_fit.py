"""GLRM fitting core: kernels vs naive references, fast path vs cvxpy, monotone objective."""

from __future__ import annotations

import numpy as np
import pytest

from lrm_cvx.errors import DataError, ModelError
from lrm_cvx.glrm import kernels as K
from lrm_cvx.glrm import quadratic as Q
from lrm_cvx.glrm.fit import (
    cvxpy_x_block,
    cvxpy_y_block,
    fit_glrm,
    is_fast_capable,
    objective,
    x_block,
    x_pass,
    y_block,
)
from lrm_cvx.glrm.losses import Absolute, Huber, Quadratic, Quantile
from lrm_cvx.glrm.regularizers import L1, NonNegative, Ridge, ZeroReg


def planted(T=30, L=80, k=3, noise=0.1, missing=0.5, seed=0):
    rng = np.random.default_rng(seed)
    X0 = rng.standard_normal((k, T))
    Y0 = rng.standard_normal((k, L))
    truth = X0.T @ Y0
    D = truth + noise * rng.standard_normal((T, L))
    M = rng.random((T, L)) >= missing
    M[:, 0] |= ~M.any(axis=1)  # every time observed at least once
    D[~M] = np.nan
    return D, M, truth


def naive_y_step(D, M, X, lam):
    """Per column: the minimum-norm minimiser of ||P_j(X^T y - d_j)||^2 + lam ||y||^2."""
    k = X.shape[0]
    out = np.zeros((k, D.shape[1]))
    for j in range(D.shape[1]):
        obs = M[:, j]
        A = X[:, obs] @ X[:, obs].T + lam * np.eye(k)
        out[:, j] = np.linalg.pinv(A) @ (X[:, obs] @ D[obs, j].astype(np.float64))
    return out


@pytest.mark.parametrize("lam", [0.0, 0.7])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_y_step_equals_naive_solve(lam, dtype):
    rng = np.random.default_rng(1)
    T, L, k = 17, 600, 4  # L > one block, ragged last block
    D = rng.standard_normal((T, L)).astype(dtype)
    M = rng.random((T, L)) < 0.7
    M[:k, :] = True  # each cell observed >= k times so lam=0 is well-posed
    D_nan = np.where(M, D, np.nan).astype(dtype)  # NaN outside the mask must be ignored
    X = rng.standard_normal((k, T))
    Y = rng.standard_normal((k, L))
    reg = Ridge(lam) if lam else ZeroReg()
    Yf, f_before = y_block(D_nan, M, X, Y, Quadratic(), reg)
    ref = naive_y_step(D.astype(np.float64), M, X, lam)
    tol = 1e-4 if dtype == np.float32 else 1e-9
    np.testing.assert_allclose(Yf, ref, rtol=tol, atol=tol)
    R = np.where(M, X.T @ Y - D, 0.0)
    assert np.isclose(f_before, np.sum(R**2) + reg.value(Y), rtol=1e-6)


def test_compiled_x_step_equals_naive_solve():
    rng = np.random.default_rng(2)
    T, L, k = 9, 5000, 3
    D = rng.standard_normal((T, L))
    M = rng.random((T, L)) < 0.5
    X = rng.standard_normal((k, T))
    Y = rng.standard_normal((k, L))
    Xf, _ = x_block(D, M, X, Y, Quadratic(), Ridge(0.2))
    ref = naive_y_step(D.T.copy(), M.T.copy(), Y, 0.2)
    np.testing.assert_allclose(Xf, ref, rtol=1e-9, atol=1e-9)


def test_gram_kernel_weights_match_majoriser_definition():
    rng = np.random.default_rng(3)
    T, L, k = 7, 50, 2
    D = rng.standard_normal((T, L))
    M = rng.random((T, L)) < 0.6
    X = rng.standard_normal((k, T))
    Y = rng.standard_normal((k, L))
    loss = Huber(0.5)
    code, p0, p1 = loss.kernel_spec
    pa, pb = K.pair_index(k)
    G = np.empty((L, pa.size))
    h = np.empty((L, k))
    f = np.empty(L)
    K.col_pass(D, M, X, Y, 0, L, code, p0, p1, pa, pb, G, h, f)
    R = X.T @ Y - D
    a = np.where(np.abs(R) <= 0.5, 1.0, 0.5 / np.abs(R)) * M
    Gref = np.einsum("tj,at,bt->jab", a, X, X)[:, pa, pb]
    href = np.einsum("tj,tj,at->ja", a, D, X)
    np.testing.assert_allclose(G, Gref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(h, href, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f, np.sum(loss.evaluate(R) * M, axis=0), rtol=1e-12)


LOSSES = [Quadratic(), Huber(0.5), Absolute(), Quantile(0.8)]
REGS = [ZeroReg(), Ridge(0.3), L1(0.3), NonNegative()]


@pytest.mark.parametrize("loss", LOSSES, ids=repr)
@pytest.mark.parametrize("reg", REGS, ids=repr)
def test_fast_block_matches_cvxpy_block(loss, reg):
    """Each block subproblem: the fast path's objective equals cvxpy's (relative 1e-4)."""
    if not is_fast_capable(loss, reg):
        pytest.skip("pair is fitted by the cvxpy path only (documented)")
    D, M, _ = planted(T=12, L=30, k=3, noise=0.3, seed=4)
    rng = np.random.default_rng(5)
    X = rng.standard_normal((3, 12))
    Y = np.abs(rng.standard_normal((3, 30)))
    lo = loss.with_scale(1.0)
    z = ZeroReg()
    Yf, _ = y_block(D, M, X, Y, lo, reg, max_inner=3000, inner_tol=1e-13)
    Yc, _ = cvxpy_y_block(D, M, X, Y, lo, reg)
    of, oc = objective(D, M, X, Yf, lo, z, reg), objective(D, M, X, Yc, lo, z, reg)
    assert of <= oc * (1 + 1e-4) + 1e-9
    assert abs(of - oc) <= 1e-4 * abs(oc)
    Xf, _ = x_block(D, M, X, Y, lo, reg, max_inner=3000, inner_tol=1e-13)
    Xc, _ = cvxpy_x_block(D, M, X, Y, lo, reg)
    of, oc = objective(D, M, Xf, Y, lo, reg, z), objective(D, M, Xc, Y, lo, reg, z)
    assert abs(of - oc) <= 1e-4 * abs(oc)


def test_fast_and_cvxpy_fits_reach_same_objective():
    D, M, _ = planted(T=12, L=30, k=2, noise=0.2, seed=6)
    kw = dict(max_iter=15, tol=0.0, rng=np.random.default_rng(0))
    a = fit_glrm(D, M, 2, Quadratic(), Ridge(0.1), Ridge(0.1), solver="fast", **kw)
    kw["rng"] = np.random.default_rng(0)
    b = fit_glrm(D, M, 2, Quadratic(), Ridge(0.1), Ridge(0.1), solver="cvxpy", **kw)
    assert b.solver == "cvxpy" and a.solver == "fast"
    np.testing.assert_allclose(a.objective, b.objective, rtol=1e-4)


def test_custom_cvxpy_regulariser_uses_cvxpy_path():
    import cvxpy as cp

    D, M, _ = planted(T=10, L=20, k=2, seed=7)
    res = fit_glrm(D, M, 2, Quadratic(), ZeroReg(), _wrap(lambda V: 0.1 * cp.sum_squares(V)),
                   max_iter=5, tol=0.0, rng=np.random.default_rng(0))
    ref = fit_glrm(D, M, 2, Quadratic(), ZeroReg(), Ridge(0.1), max_iter=5, tol=0.0,
                   rng=np.random.default_rng(0))
    assert res.solver == "cvxpy"
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-4)


def _wrap(fn):
    from lrm_cvx.glrm.regularizers import get_regularizer

    return get_regularizer(fn)


@pytest.mark.parametrize(
    "loss,reg",
    [(Quadratic(), ZeroReg()), (Quadratic(), L1(0.5)), (Huber(0.3), NonNegative()),
     (Absolute(), Ridge(0.1)), (Quantile(0.3), ZeroReg())],
    ids=repr,
)
def test_objective_non_increasing(loss, reg):
    D, M, _ = planted(T=20, L=60, k=3, noise=0.3, seed=8)
    D[0, :5] += 5.0  # a few outliers
    res = fit_glrm(D, M, 3, loss, reg, reg, max_iter=25, tol=0.0,
                   rng=np.random.default_rng(0), init="random")
    h = np.asarray(res.objective)
    assert np.all(np.isfinite(h[1:]))
    assert np.all(np.diff(h[1:]) <= 1e-10 * np.abs(h[1:-1]))


def test_full_observation_recovers_truncated_svd_subspace():
    rng = np.random.default_rng(9)
    T, L, k = 15, 40, 3
    D = rng.standard_normal((T, L)) + 3 * rng.standard_normal((T, k)) @ rng.standard_normal(
        (k, L))
    M = np.ones_like(D, dtype=bool)
    res = fit_glrm(D, M, k, Quadratic(), ZeroReg(), ZeroReg(), max_iter=500, tol=1e-13,
                   rng=rng, init="random")
    _, _, Vt = np.linalg.svd(D)
    Qf, _ = np.linalg.qr(res.Y.T)
    cos = np.linalg.svd(Qf.T @ Vt[:k].T, compute_uv=False)
    assert np.allclose(cos, 1.0, atol=1e-6)  # principal angles ~ 0


def test_planted_heldout_rmse_near_noise_level():
    noise = 0.1
    D, M, truth = planted(T=60, L=400, k=3, noise=noise, missing=0.5, seed=10)
    res = fit_glrm(D, M, 3, Quadratic(), ZeroReg(), ZeroReg(), max_iter=200, tol=1e-9,
                   rng=np.random.default_rng(0))
    Dfull = truth + noise * np.random.default_rng(10).standard_normal(truth.shape)
    pred = res.X.T @ res.Y
    # held-out entries: error against a fresh noisy draw ~ noise * sqrt(1 + small)
    rmse_noisy = np.sqrt(np.mean((pred - Dfull)[~M] ** 2))
    assert rmse_noisy <= 1.10 * noise * np.sqrt(2) and np.sqrt(
        np.mean((pred - truth)[~M] ** 2)) <= 0.5 * noise
    assert abs(res.noise_std - noise) <= 0.1 * noise


def test_unobserved_cell_gets_zero_and_is_flagged():
    D, M, _ = planted(T=10, L=20, k=2, seed=11)
    D[:, 4] = np.nan
    M[:, 4] = False
    res = fit_glrm(D, M, 2, Quadratic(), ZeroReg(), ZeroReg(), max_iter=5, tol=0.0,
                   rng=np.random.default_rng(0))
    assert res.unobserved_cells.tolist() == [4]
    assert np.all(res.Y[:, 4] == 0) and np.all(np.isfinite(res.Y))


def test_randomized_svd_init_matches_exact(monkeypatch):
    import lrm_cvx.glrm.fit as F

    D, M, _ = planted(T=25, L=300, k=3, noise=0.01, missing=0.0, seed=12)
    exact = F.fit_glrm(D, M, 3, Quadratic(), ZeroReg(), ZeroReg(), max_iter=0, tol=0,
                       rng=np.random.default_rng(0))
    monkeypatch.setattr(F, "SMALL_SVD", 0)
    rand = F.fit_glrm(D, M, 3, Quadratic(), ZeroReg(), ZeroReg(), max_iter=0, tol=0,
                      rng=np.random.default_rng(0))
    np.testing.assert_allclose(rand.X.T @ rand.Y, exact.X.T @ exact.Y, atol=1e-3)


def test_bad_inputs_raise():
    D, M, _ = planted(T=6, L=10, k=2, seed=13)
    q, z = Quadratic(), ZeroReg()
    with pytest.raises(ModelError):
        fit_glrm(D, M, 0, q, z, z)
    with pytest.raises(ModelError):
        fit_glrm(D, M, 7, q, z, z)
    bad = D.copy()
    bad[0, 0] = np.inf
    Mb = M.copy()
    Mb[0, 0] = True
    with pytest.raises(DataError, match="inf"):
        fit_glrm(bad, Mb, 2, q, z, z)
    with pytest.raises(DataError, match="no observ"):
        fit_glrm(D, np.zeros_like(M), 2, q, z, z)
    M2 = M.copy()
    M2[3] = False
    with pytest.raises(DataError, match="times"):
        fit_glrm(D, M2, 2, q, z, z)
    with pytest.raises(DataError):
        fit_glrm(D[0], M[0], 1, q, z, z)
    with pytest.raises(ModelError):
        fit_glrm(D, M, 2, q, z, z, solver="nope")


# --------------------------------------------------------------------------- quadratic fast path
def _masked(rng, T, L, dtype, p_obs=0.6):
    D = rng.standard_normal((T, L)).astype(dtype)
    M = rng.random((T, L)) < p_obs
    D_nan = np.where(M, D, np.nan).astype(dtype)  # NaN outside the mask must be ignored
    return D, M, D_nan


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("T", [1, 13, 16])
def test_prepare_packs_mask_and_zero_fills_without_touching_input(dtype, T):
    rng = np.random.default_rng(10)
    D, M, D_nan = _masked(rng, T, 1100, dtype)
    keep = D_nan.copy()
    md = Q.prepare(D_nan, M)
    np.testing.assert_array_equal(md.mask(), M)  # bytes of eight times, ragged last byte
    assert md.codes.shape == ((T + 7) // 8, 1100)
    np.testing.assert_array_equal(md.D, np.where(M, D, 0))
    assert md.D.dtype == dtype and md.D is not D_nan
    np.testing.assert_array_equal(D_nan, keep)  # the caller's array is left alone (NaN kept)
    np.testing.assert_allclose(md.ssq_rows, (np.where(M, D, 0).astype(np.float64) ** 2).sum(1),
                               rtol=1e-10)
    clean = np.where(M, D, 0).astype(dtype)
    assert Q.prepare(clean, M).D is clean  # already zero-filled: no copy
    own = D_nan.copy()
    assert Q.prepare(own, M, overwrite=True).D is own and not np.isnan(own).any()
    Ft = np.asfortranarray(D_nan)  # column-major input: a C-ordered zero-filled copy
    mdf = Q.prepare(Ft, np.asfortranarray(M))
    assert mdf.D.flags.c_contiguous and np.isnan(Ft[~M]).all()
    np.testing.assert_array_equal(mdf.D, md.D)
    np.testing.assert_array_equal(mdf.codes, md.codes)


@pytest.mark.parametrize("lam", [0.0, 0.3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("T", [23, 5, 16])
def test_quad_y_kernel_equals_naive(lam, dtype, T):
    rng = np.random.default_rng(11)
    # times go eight at a time (one mask byte, one table): 23 = 2 * 8 + ragged tail,
    # 5 = tail only, 16 = no tail; L spans 3 blocks with a ragged last one
    L, k = 1300, 4
    D, M, D_nan = _masked(rng, T, L, dtype)
    M[:, 5] = False  # never observed
    M[:, 7] = False
    M[:2, 7] = True  # fewer observations than k: pinv without ridge
    D_nan = np.where(M, D, np.nan).astype(dtype)
    X = rng.standard_normal((k, T))
    Y = rng.standard_normal((k, L))
    md = Q.prepare(D_nan, M)
    out = np.empty_like(Y)
    before, after, npinv = Q.y_step(md, X, Y, lam, out)
    ref = naive_y_step(D, M, X, lam)
    np.testing.assert_allclose(out, ref, rtol=1e-8, atol=1e-8)
    assert np.all(out[:, 5] == 0.0)
    nobs = M.sum(axis=0)  # generic X: singular exactly when 0 < observations < k
    assert npinv == (int(np.sum((nobs > 0) & (nobs < k))) if lam == 0 else 0)
    assert T != 23 or npinv == (1 if lam == 0 else 0)
    D64 = D.astype(np.float64)
    loss = lambda F: float(np.sum(np.where(M, X.T @ F - D64, 0.0) ** 2))  # noqa: E731
    assert np.isclose(before, loss(Y), rtol=1e-10)
    assert np.isclose(after, loss(out), rtol=1e-10)
    # in place (out is Y) gives the same
    Y2 = Y.copy()
    Q.y_step(md, X, Y2, lam, Y2)
    np.testing.assert_array_equal(Y2, out)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize(("T", "k"), [(13, 3), (21, 7)])
def test_quad_x_stats_equals_naive(dtype, T, k):
    rng = np.random.default_rng(12)
    L = 2500  # three row blocks, ragged last
    D, M, D_nan = _masked(rng, T, L, dtype, 0.4)
    Y = rng.standard_normal((k, L))
    pa, pb = K.pair_index(k)
    G, h, c = Q.x_stats(Q.prepare(D_nan, M), Y)
    W = M.astype(np.float64)
    Dz = np.where(M, D, 0).astype(np.float64)
    Gfull = np.einsum("tj,aj,bj->tab", W, Y, Y)
    np.testing.assert_allclose(G, Gfull[:, pa, pb], rtol=1e-10)
    np.testing.assert_allclose(h, Dz @ Y.T, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(c, (Dz**2).sum(1), rtol=1e-10)


def test_x_pass_quadratic_matches_generic_kernel():
    rng = np.random.default_rng(13)
    T, L, k = 10, 700, 3
    D, M, D_nan = _masked(rng, T, L, np.float32)
    X = rng.standard_normal((k, T))
    Y = rng.standard_normal((k, L))
    G, h, f = x_pass(D_nan, M, X, Y, Quadratic())
    R = np.where(M, X.T @ Y - D.astype(np.float64), 0.0)
    np.testing.assert_allclose(f, (R**2).sum(1), rtol=1e-9)
    pa, pb = K.pair_index(k)
    nch = 4
    G2, h2, f2 = np.zeros((nch, T, pa.size)), np.zeros((nch, T, k)), np.zeros((nch, T))
    K.row_pass(D_nan, M, X, Y, 0, 0.0, 0.0, pa, pb, nch, G2, h2, f2)
    np.testing.assert_allclose(G, G2.sum(0), rtol=1e-10)
    np.testing.assert_allclose(h, h2.sum(0), rtol=1e-9, atol=1e-9)


def test_chol_solve_equals_numpy_and_pinv():
    rng = np.random.default_rng(14)
    n, k = 300, 4
    pa, pb = K.pair_index(k)
    B = rng.standard_normal((n, k, 6))
    A = B @ B.transpose(0, 2, 1)
    A[3] = np.outer(B[3, :, 0], B[3, :, 0])  # rank one: pinv
    A[4] = 0.0  # empty
    h = rng.standard_normal((n, k))
    h[3] = B[3, :, 0] * 2.0
    h[4] = 0.0
    out = np.empty((n, k))
    flags = K.chol_solve(np.ascontiguousarray(A[:, pa, pb]), h, 0.0, pa, pb, out)
    ok = np.ones(n, bool)
    ok[[3, 4]] = False
    np.testing.assert_allclose(out[ok], np.linalg.solve(A[ok], h[ok][..., None])[..., 0],
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out[3], np.linalg.pinv(A[3]) @ h[3], rtol=1e-8, atol=1e-10)
    assert np.all(out[4] == 0) and flags[3] == 1 and flags[4] == 2 and flags[ok].max() == 0
    out2 = np.empty((n, k))
    K.chol_solve(np.ascontiguousarray(A[:, pa, pb]), h, 0.5, pa, pb, out2)
    ref = np.linalg.solve(A + 0.5 * np.eye(k), h[..., None])[..., 0]
    np.testing.assert_allclose(out2, ref, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_filled_products_and_data_stats_equal_numpy(dtype):
    rng = np.random.default_rng(15)
    T, L, p = 11, 2300, 3
    D, M, D_nan = _masked(rng, T, L, dtype, 0.5)
    M[:, 9] = False
    mu = rng.standard_normal(L)
    Z = np.where(M, D.astype(np.float64), mu[None, :])
    V = rng.standard_normal((p, L))
    U = rng.standard_normal((T, p))
    md = Q.prepare(D_nan, M)
    np.testing.assert_allclose(Q.filled_matmul(md, mu, V), Z @ V.T, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(Q.filled_rmatmul(md, mu, U), (Z.T @ U).T, rtol=1e-9, atol=1e-9)
    rows, cols, nbad, colsum = K.data_stats(D_nan, M, True)
    Dz = np.where(M, D, 0).astype(np.float64)
    np.testing.assert_array_equal(rows, M.sum(1))
    np.testing.assert_array_equal(cols, M.sum(0))
    np.testing.assert_allclose(colsum, Dz.sum(0), rtol=1e-10, atol=1e-12)
    assert nbad == 0
    D_nan[0, np.flatnonzero(M[0])[0]] = np.inf
    assert K.data_stats(D_nan, M, True)[2] == 1


@pytest.mark.parametrize("reg", [ZeroReg(), Ridge(0.4)])
def test_quadratic_fit_history_sse_and_determinism(reg):
    D, M, _ = planted(T=26, L=300, k=3, seed=5)
    M[:, 3] = False  # unobserved cell
    D = D.astype(np.float32)
    kw = dict(max_iter=6, tol=0.0, rng=None)
    res = fit_glrm(D, M, 3, Quadratic(), reg, reg, **{**kw, "rng": np.random.default_rng(0)})
    res2 = fit_glrm(D, M, 3, Quadratic(), reg, reg, **{**kw, "rng": np.random.default_rng(0)})
    np.testing.assert_array_equal(res.X, res2.X)
    np.testing.assert_array_equal(res.Y, res2.Y)
    h = np.array(res.objective)
    assert len(h) == 7 and np.all(np.diff(h) <= 1e-10 * np.abs(h[:-1]))
    # the final objective (from the last step's Gram) equals a direct evaluation
    direct = objective(D, M, res.X, res.Y, Quadratic(), reg, reg)
    R = np.where(M, res.X.T @ res.Y - np.nan_to_num(D.astype(np.float64)), 0.0)
    assert np.isclose(h[-1], direct, rtol=1e-10)
    assert np.isclose(h[-1], np.sum(R**2) + reg.value(res.X) + reg.value(res.Y), rtol=1e-9)
    assert np.isclose(res.sse, np.sum(R**2), rtol=1e-9)
    assert np.all(res.Y[:, 3] == 0) and 3 in res.unobserved_cells
    # history entries are the objective after i rounds: round 1 by a fresh 1-round fit
    one = fit_glrm(D, M, 3, Quadratic(), reg, reg, max_iter=1, tol=0.0,
                   rng=np.random.default_rng(0))
    assert np.isclose(one.objective[-1], h[1], rtol=1e-10)


def test_noise_identifiability_brute_force():
    """max_identifiable_rank is the largest k with n_obs > k (T + L_obs) - k^2 (+ L_obs with an
    offset), by brute force over small shapes; noise_std refuses n_obs <= p."""
    from lrm_cvx.glrm.fit import max_identifiable_rank, noise_std

    for T in range(1, 7):
        for L in range(1, 7):
            for n_obs in range(1, T * L + 1):
                for off in (False, True):
                    ok = [k for k in range(1, min(T, L) + 1)
                          if n_obs > k * (T + L) - k * k + (L if off else 0)]
                    assert max_identifiable_rank(n_obs, T, L, offset=off) == max(ok, default=0)
    with pytest.raises(ModelError, match="not identifiable"):
        noise_std(1.0, 20, 2, 2, 10)
    assert noise_std(4.0, 21, 2, 2, 10) == pytest.approx(2.0)
