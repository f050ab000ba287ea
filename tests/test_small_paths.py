"""The numpy paths for small problems (kernels.SMALL_ENTRIES) equal the compiled kernels."""

from __future__ import annotations

import numpy as np
import pytest

from lrm_cvx.glrm import kernels as K
from lrm_cvx.glrm import quadratic as Q


def _data(seed: int, T: int, L: int, dtype, dirty: bool):
    rng = np.random.default_rng(seed)
    D = rng.normal(size=(T, L)).astype(dtype)
    M = rng.random((T, L)) < 0.7
    M[:, 0] = False  # a never-observed cell
    M[0, :3] = True
    if dirty:
        D[~M] = np.nan
    else:
        D[~M] = 0
    return D, M


def _both(monkeypatch, fn):
    """``fn()`` on the numpy path, then on the compiled path."""
    small = fn()
    monkeypatch.setattr(K, "SMALL_ENTRIES", -1)
    compiled = fn()
    monkeypatch.undo()
    return small, compiled


@pytest.mark.parametrize("k", [1, 3, 5])
@pytest.mark.parametrize("lam", [0.0, 0.4, "rows"])
def test_chol_solve_numpy_equals_compiled(k, lam):
    if lam == "rows":  # a ridge per row (the joint offset's, glrm/offset.py): only the last
        lam = np.append(np.zeros(k - 1), 0.7)
    rng = np.random.default_rng(k)
    n = 60
    B = rng.normal(size=(n, k, 2 * k))
    B[:10, :, k // 2 + 1:] = 0  # rank-deficient: pseudo-inverse
    A = B @ B.transpose(0, 2, 1)
    A[10] = 0  # empty
    A[11] = -np.eye(k)  # negative diagonal: "empty" in the kernel too
    pa, pb = K.pair_index(k)
    G = np.ascontiguousarray(A[:, pa, pb])
    h = rng.normal(size=(n, k))
    o1, o2 = np.empty((n, k)), np.empty((n, k))
    f1 = K.chol_solve_numpy(G, h, lam, pa, pb, o1)
    f2 = K.chol_solve_compiled(G, h, lam, pa, pb, o2)
    np.testing.assert_array_equal(f1, f2)
    np.testing.assert_allclose(o1, o2, rtol=1e-9, atol=1e-10)
    assert set(np.unique(f1)) >= ({0, 2} if np.all(lam) or k == 1 else {1, 2})
    # the solution solves the ridged system wherever Cholesky succeeded
    ok = f1 == 0
    Ar = A[ok] + np.diag(np.broadcast_to(lam, (k,)))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", Ar, o1[ok]), h[ok], atol=1e-8)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("T", [7, 8, 19])
@pytest.mark.parametrize("dirty", [False, True])
def test_prepare_numpy_equals_compiled(monkeypatch, dtype, T, dirty):
    D, M = _data(T, T, 33, dtype, dirty)
    a, b = _both(monkeypatch, lambda: Q.prepare(D.copy(), M))
    np.testing.assert_array_equal(a.codes, b.codes)
    np.testing.assert_array_equal(a.D, b.D)
    np.testing.assert_allclose(a.ssq_rows, b.ssq_rows, rtol=1e-12)
    assert a.D.dtype == b.D.dtype == dtype
    np.testing.assert_array_equal(a.mask(), M)
    # overwrite=True zero-fills the caller's array in place on both paths
    D1, D2 = D.copy(), D.copy()
    Q.prepare(D1, M, overwrite=True)
    monkeypatch.setattr(K, "SMALL_ENTRIES", -1)
    Q.prepare(D2, M, overwrite=True)
    np.testing.assert_array_equal(D1, D2)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("lam", [0.0, 0.3])
def test_y_step_row_products_filled_rmatmul_numpy_equal_compiled(monkeypatch, dtype, lam):
    T, L, k = 21, 40, 4
    D, M = _data(1, T, L, dtype, True)
    rng = np.random.default_rng(2)
    X, Y = rng.normal(size=(k, T)), rng.normal(size=(k, L))
    mu, U = rng.normal(size=L), rng.normal(size=(T, 3))
    pa, pb = Q._pairs(k)

    def run():
        md = Q.prepare(D.copy(), M)
        out = np.empty((k, L))
        losses = Q.y_step(md, X, Y, lam, out)
        return (out, losses, Q.row_products(md, Y, Y, pa, pb), Q.x_stats(md, Y),
                Q.filled_matmul(md, mu, Y), Q.filled_rmatmul(md, mu, U))

    a, b = _both(monkeypatch, run)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-8, atol=1e-9)
    assert a[1][2] == b[1][2]
    np.testing.assert_allclose(a[1][:2], b[1][:2], rtol=1e-9)
    for x, y in zip((*a[2], *a[3], a[4], a[5]), (*b[2], *b[3], b[4], b[5]), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9)
    # and the Y step is the exact per-cell ridge solve
    Dz = np.where(M, D, 0).astype(np.float64)
    for j in (0, 5, 17):
        Xo = X[:, M[:, j]]
        A = Xo @ Xo.T + lam * np.eye(k)
        ref = np.linalg.pinv(A) @ (Xo @ Dz[M[:, j], j])
        np.testing.assert_allclose(a[0][:, j], ref, rtol=1e-7, atol=1e-9)


def test_y_step_in_place(monkeypatch):
    """``out`` may be ``Y`` itself: the loss before is computed at the old ``Y``."""
    D, M = _data(3, 16, 25, np.float64, False)
    rng = np.random.default_rng(4)
    X, Y = rng.normal(size=(3, 16)), rng.normal(size=(3, 25))
    md = Q.prepare(D, M)
    ref = np.empty_like(Y)
    expect = Q.y_step(md, X, Y, 0.1, ref)
    Y2 = Y.copy()
    got = Q.y_step(md, X, Y2, 0.1, Y2)
    np.testing.assert_allclose(got, expect)
    np.testing.assert_allclose(Y2, ref)


@pytest.mark.parametrize("check", [True, False])
def test_data_stats_numpy_equals_compiled(monkeypatch, check):
    D, M = _data(5, 13, 29, np.float32, True)
    D[2, 3], M[2, 3] = np.inf, True
    a, b = _both(monkeypatch, lambda: K.data_stats(D, M, check))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(x, dtype=float), np.asarray(y, dtype=float),
                                   rtol=1e-6)
    assert int(a[2]) == (1 if check else 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("L", [5, 130])  # fewer cells than the kernel's 64 ranges, and more
def test_column_moments_and_standardize_numpy_equal_compiled(monkeypatch, dtype, L):
    """The compiled moments and standardization give the numpy path's numbers (the same sums
    in the same order), never read an unobserved entry (NaN), and overwrite ``D`` only when
    asked."""
    from lrm_cvx.glrm.predictive import column_moments, standardize

    D, M = _data(6, 23, L, dtype, True)
    M[:, 0] = False  # never observed: mean 0, std 1
    D[~M] = np.nan
    M[:, -1] = True  # a cell observed at every time ...
    D[:, -1] = 2.5  # ... that never varies: std 1
    rng = np.random.default_rng(7)
    off, sc = rng.normal(size=L), rng.uniform(0.5, 2.0, size=L)

    def run():
        mean, std, count = column_moments(D, M)
        full = standardize(D, M, off, sc)
        centred = standardize(D, M, mean, None)
        own = D.copy()
        same = standardize(own, M, off, sc, inplace=True)
        return mean, std, count, full, centred, own, same

    a, b = _both(monkeypatch, run)
    for x, y in zip(a[:5], b[:5], strict=True):
        np.testing.assert_array_equal(x, y)
    # against a direct reference
    Dm = np.where(M, D.astype(np.float64), np.nan)
    np.testing.assert_allclose(a[0][1:], np.nanmean(Dm[:, 1:], axis=0), rtol=1e-12)
    np.testing.assert_allclose(a[1][1:-1], np.nanstd(Dm[:, 1:-1], axis=0), rtol=1e-10)
    assert a[0][0] == 0 and a[1][0] == 1 and a[1][-1] == 1 and a[2][0] == 0
    np.testing.assert_array_equal(a[2], M.sum(axis=0))
    for r in (a, b):
        assert r[3].dtype == dtype and not np.isnan(r[3]).any()
        np.testing.assert_array_equal(r[3][~M], 0)
        np.testing.assert_allclose(r[3][M], ((Dm - off) / sc)[M], rtol=1e-6 if dtype ==
                                   np.float32 else 1e-14)
        assert r[6] is r[5]  # in place: D itself, the same numbers as a new array
        np.testing.assert_array_equal(r[5], r[3])
    assert np.isnan(D[~M]).all()  # not in place: the input untouched


def test_standardize_in_place_needs_a_writeable_float_array():
    from lrm_cvx.glrm.predictive import standardize

    D = np.ones((3, 4), dtype=np.int64)
    with pytest.raises(ValueError, match="inplace"):
        standardize(D, D > 0, None, None, inplace=True)
    F = np.ones((3, 4))
    F.setflags(write=False)
    with pytest.raises(ValueError, match="inplace"):
        standardize(F, F > 0, None, None, inplace=True)


@pytest.mark.parametrize("L", [9, (1 << 16) + 5])  # one block of cells, and two
def test_residual_sample_by_blocks_equals_the_whole_product(L):
    """The variogram's residual sample, computed in blocks of cells, is the whole product's to
    the bit, NaN where unobserved."""
    from lrm_cvx.glrm.predictive import residual_sample, sample_rows

    D, M = _data(8, 30, L, np.float32, True)
    rng = np.random.default_rng(9)
    X, Y = rng.normal(size=(4, 30)), rng.normal(size=(4, L))
    rows = sample_rows(30, 20)
    ref = (D[rows].astype(np.float64) - X[:, rows].T @ Y).astype(np.float32)
    ref[~M[rows]] = np.nan
    got = residual_sample(D, M, X, Y)
    assert got.dtype == np.float32 and got.shape == (rows.size, L)
    np.testing.assert_array_equal(got, ref)
