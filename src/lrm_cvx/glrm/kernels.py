"""Compiled kernels of the GLRM fit for any loss: one pass builds every block's Gram.

The plain quadratic loss has its own, faster kernels in :mod:`.quadratic`. The kernels here read
the data ``D`` (float32/float64, ``(T, L)``) together with a boolean mask ``M`` (True =
observed) and never look at ``D`` where ``M`` is False, so unobserved entries may hold anything
(zeros, NaN). Accumulation is in float64.

A pass evaluates, at the current factors, every observed residual ``r = x_t . y_j - d_tj``, the
loss ``f(r)`` and a quadratic majoriser ``q(r') = a (r' - z)^2 + const >= f(r')`` of the loss at
``r`` (see :func:`majorize`). The weighted normal equations of that majoriser are accumulated as
packed Gram matrices ``G`` (the ``k(k+1)/2`` distinct entries, pair ``p`` = ``(pa[p], pb[p])``)
and right-hand sides ``h``:  ``G_j = sum_t a x_t x_t^T``, ``h_j = sum_t a (d_tj + z) x_t``.
For the quadratic loss ``a = 1, z = 0``: the normal equations of the exact block problem.

Loss codes (set by each loss class as its ``kernel_spec``): 0 quadratic ``r^2``; 1 Huber
``r^2`` / ``2 delta |r| - delta^2`` (cvxpy's ``huber``); 2 absolute ``|r|``; 3 quantile
``tau max(-r, 0) + (1 - tau) max(r, 0)``. ``p0``/``p1`` are the loss's parameters.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

_FM = {"contract", "reassoc", "arcp", "nsz"}  # no 'nnan': unobserved entries may be NaN
BLOCK_COLS = 256  # cells per block in the column (Y-step) kernel
BLOCK_ROWS = 2048  # cells per block in the row (X-step) kernel
#: Problems with at most this many entries (``T * L`` data entries, ``n * k * k`` for a batch of
#: small solves) take the vectorised numpy paths instead of the compiled kernels: the same
#: results (tested equal) without compiling (the first compile of the quadratic fit's kernels
#: costs 40-100 s on a 2-core machine; the bundled samples are 2-4e4 entries).
SMALL_ENTRIES = 1 << 20


def is_small(entries: int) -> bool:
    """Whether a problem of ``entries`` entries takes the numpy path (see SMALL_ENTRIES)."""
    return int(entries) <= SMALL_ENTRIES


def pair_index(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column index of each of the ``k(k+1)/2`` upper-triangle Gram entries."""
    pa, pb = np.triu_indices(k)
    return pa.astype(np.int64), pb.astype(np.int64)


@numba.njit(inline="always", cache=True)
def majorize(code: int, p0: float, p1: float, r: float) -> tuple[float, float, float]:
    """Loss value ``f(r)``, curvature ``a`` and shift ``z`` of a quadratic majoriser at ``r``.

    ``a (r' - z)^2 + c >= f(r')`` for all ``r'`` with equality at ``r' = r`` (exact for
    codes 0 and 1; for codes 2 and 3, ``|r|`` is clipped below at ``p1`` (absolute) or ``p1``
    (quantile eps) and equality holds only for ``|r| >= eps``).
    """
    if code == 0:
        return r * r, 1.0, 0.0
    ar = abs(r)
    if code == 1:
        if ar <= p0:
            return r * r, 1.0, 0.0
        return 2.0 * p0 * ar - p0 * p0, p0 / ar, 0.0
    if code == 2:
        e = max(ar, p1)
        return ar, 0.5 / e, 0.0
    # quantile: 0.5 |r| + (0.5 - tau) r <= r^2 / (4e) + (0.5 - tau) r + const
    tau = p0
    e = max(ar, p1)
    f = tau * max(-r, 0.0) + (1.0 - tau) * max(r, 0.0)
    return f, 0.25 / e, -(0.5 - tau) * 2.0 * e


@numba.njit(inline="always", cache=True, fastmath=_FM)
def _residuals(D, M, t, s, n, xt, yb, wb, vb, rb):  # pragma: no cover - numba
    """For cells ``s..s+n`` at time ``t``: ``wb`` 0/1 observed, ``vb`` data (0 if unobserved),
    ``rb`` residual ``x_t . y_j - d``; vectorised over cells."""
    k = xt.shape[0]
    for jj in range(n):
        m = M[t, s + jj]
        d = D[t, s + jj] if m else 0.0
        wb[jj] = 1.0 if m else 0.0
        vb[jj] = d
        rb[jj] = -d
    for a in range(k):
        xa = xt[a]
        for jj in range(n):
            rb[jj] += xa * yb[a, jj]


@numba.njit(inline="always", cache=True, fastmath=_FM)
def _weights(code, p0, p1, n, wb, vb, rb, fb):  # pragma: no cover - numba
    """Turn ``(wb, vb, rb)`` into majoriser weights ``wb = w a`` and targets ``vb = w a (d + z)``
    and add the loss to ``fb`` per cell."""
    if code == 0:
        for jj in range(n):
            fb[jj] += wb[jj] * rb[jj] * rb[jj]
    else:
        for jj in range(n):
            fv, av, zv = majorize(code, p0, p1, rb[jj])
            w = wb[jj]
            fb[jj] += fv if w != 0.0 else 0.0
            wb[jj] = w * av
            vb[jj] = w * av * (vb[jj] + zv)


@numba.njit(inline="always", cache=True, fastmath=_FM)
def _weights_sum(code, p0, p1, n, wb, vb, rb):  # pragma: no cover - numba
    """As :func:`_weights` but returns the summed loss."""
    fs = 0.0
    if code == 0:
        for jj in range(n):
            fs += wb[jj] * rb[jj] * rb[jj]
    else:
        for jj in range(n):
            fv, av, zv = majorize(code, p0, p1, rb[jj])
            w = wb[jj]
            fs += fv if w != 0.0 else 0.0
            wb[jj] = w * av
            vb[jj] = w * av * (vb[jj] + zv)
    return fs


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def col_pass(D, M, X, Yc, j0, j1, code, p0, p1, pa, pb, G, h, f):  # pragma: no cover - numba
    """Y-step pass over cells ``j0..j1``: ``G (c, npair)``, ``h (c, k)``, ``f (c,)`` (loss sums).

    ``X (k, T)`` float64; ``Yc (k, c)`` the current columns of cells ``j0..j1``.
    Cells go in parallel blocks of ``BLOCK_COLS``; inside a block the loop runs over times.
    """
    T = D.shape[0]
    k = X.shape[0]
    npair = pa.shape[0]
    c = j1 - j0
    nblk = (c + BLOCK_COLS - 1) // BLOCK_COLS
    for ib in prange(nblk):
        s = j0 + ib * BLOCK_COLS
        e = min(s + BLOCK_COLS, j1)
        n = e - s
        yb = np.empty((k, n))
        for a in range(k):
            for jj in range(n):
                yb[a, jj] = Yc[a, s - j0 + jj]
        gb = np.zeros((npair, n))
        hb = np.zeros((k, n))
        fb = np.zeros(n)
        wb = np.empty(n)
        vb = np.empty(n)
        xt = np.empty(k)
        xx = np.empty(npair)
        rb = np.empty(n)
        for t in range(T):
            for a in range(k):
                xt[a] = X[a, t]
            for p in range(npair):
                xx[p] = xt[pa[p]] * xt[pb[p]]
            _residuals(D, M, t, s, n, xt, yb, wb, vb, rb)
            _weights(code, p0, p1, n, wb, vb, rb, fb)
            for p in range(npair):
                xp = xx[p]
                for jj in range(n):
                    gb[p, jj] += wb[jj] * xp
            for a in range(k):
                xa = xt[a]
                for jj in range(n):
                    hb[a, jj] += vb[jj] * xa
        for jj in range(n):
            o = s - j0 + jj
            for p in range(npair):
                G[o, p] = gb[p, jj]
            for a in range(k):
                h[o, a] = hb[a, jj]
            f[o] = fb[jj]


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def row_pass(D, M, X, Y, code, p0, p1, pa, pb, nchunk, G, h, f):  # pragma: no cover - numba
    """X-step pass: partial sums ``G (nchunk, T, npair)``, ``h (nchunk, T, k)``, ``f (nchunk, T)``.

    The cells are split into ``nchunk`` ranges processed in parallel, each in blocks of
    ``BLOCK_ROWS`` cells so that the block of ``Y`` stays in cache while all times are read.
    The caller sums over the first axis. Buffers must be zeroed by the caller.
    """
    T, L = D.shape
    k = X.shape[0]
    npair = pa.shape[0]
    for c in prange(nchunk):
        s = c * L // nchunk
        e = (c + 1) * L // nchunk
        yb = np.empty((k, BLOCK_ROWS))
        yy = np.empty((npair, BLOCK_ROWS))
        wb = np.empty(BLOCK_ROWS)
        vb = np.empty(BLOCK_ROWS)
        rb = np.empty(BLOCK_ROWS)
        xt = np.empty(k)
        for b0 in range(s, e, BLOCK_ROWS):
            n = min(b0 + BLOCK_ROWS, e) - b0
            for a in range(k):
                for jj in range(n):
                    yb[a, jj] = Y[a, b0 + jj]
            for p in range(npair):
                for jj in range(n):
                    yy[p, jj] = yb[pa[p], jj] * yb[pb[p], jj]
            for t in range(T):
                for a in range(k):
                    xt[a] = X[a, t]
                _residuals(D, M, t, b0, n, xt, yb, wb, vb, rb)
                fs = _weights_sum(code, p0, p1, n, wb, vb, rb)
                f[c, t] += fs
                for p in range(npair):
                    acc = 0.0
                    for jj in range(n):
                        acc += wb[jj] * yy[p, jj]
                    G[c, t, p] += acc
                for a in range(k):
                    acc = 0.0
                    for jj in range(n):
                        acc += vb[jj] * yb[a, jj]
                    h[c, t, a] += acc


def ridge_vector(lam, k: int) -> np.ndarray:
    """The ridge of each of ``k`` rows, ``(k,)`` float64: a number for every row, or one per row
    (the joint offset's row has its own, :mod:`.offset`)."""
    lam = np.asarray(lam, dtype=np.float64)
    return np.full(k, float(lam)) if lam.ndim == 0 else np.ascontiguousarray(lam)


def chol_solve(G, h, lam, pa, pb, out):
    """Solve ``(G_j + diag(lam)) y_j = h_j`` for every block entry into ``out (n, k)``
    (``lam`` a number or ``(k,)``: :func:`ridge_vector`); returns the ``(n,)`` int8 flags (0
    Cholesky, 1 pseudo-inverse, 2 empty). Small batches take :func:`chol_solve_numpy`, large
    ones the compiled :func:`chol_solve_compiled`."""
    n, k = h.shape
    lam = ridge_vector(lam, k)
    if is_small(n * k * k):
        return chol_solve_numpy(G, h, lam, pa, pb, out)
    return _chol_solve_compiled(G, h, lam, pa, pb, out)


def chol_solve_numpy(G, h, lam, pa, pb, out):
    """:func:`chol_solve_compiled` vectorised over the batch with numpy: the same Cholesky with
    the same breakdown test (pivot ``<= 1e-12`` of the largest diagonal entry), the entries
    that break down solved by the pseudo-inverse, all-zero systems give ``y = 0``."""
    n, k = h.shape
    A = np.empty((n, k, k))
    A[:, pa, pb] = G
    A[:, pb, pa] = G
    idx = np.arange(k)
    A[:, idx, idx] += ridge_vector(lam, k)
    scale = np.maximum(A[:, idx, idx].max(axis=1, initial=0.0), 0.0)
    flags = np.where(scale == 0.0, 2, 0).astype(np.int8)
    Lc = np.zeros((n, k, k))
    for a in range(k):
        s = A[:, a, a] - np.einsum("nb,nb->n", Lc[:, a, :a], Lc[:, a, :a])
        broke = (s <= 1e-12 * scale) & (flags == 0)
        flags[broke] = 1
        Lc[:, a, a] = np.sqrt(np.where(flags == 0, s, 1.0))
        if a + 1 < k:
            s2 = A[:, a + 1:, a] - np.einsum("nib,nb->ni", Lc[:, a + 1:, :a], Lc[:, a, :a])
            Lc[:, a + 1:, a] = s2 / Lc[:, a, a][:, None]
    y = np.zeros((n, k))
    ok = flags == 0
    if ok.any():
        Lo = Lc[ok]
        z = np.empty((Lo.shape[0], k))
        hv = np.asarray(h, dtype=np.float64)[ok]
        for a in range(k):
            z[:, a] = (hv[:, a] - np.einsum("nb,nb->n", Lo[:, a, :a], z[:, :a])) / Lo[:, a, a]
        yo = np.empty_like(z)
        for a in range(k - 1, -1, -1):
            yo[:, a] = (z[:, a] - np.einsum("nb,nb->n", Lo[:, a + 1:, a], yo[:, a + 1:])
                        ) / Lo[:, a, a]
        y[ok] = yo
    bad = flags == 1
    if bad.any():
        y[bad] = np.einsum("nij,nj->ni", np.linalg.pinv(A[bad]), h[bad])
    out[...] = y
    return flags


def chol_solve_compiled(G, h, lam, pa, pb, out):
    """:func:`_chol_solve_compiled` with ``lam`` a number or ``(k,)`` (:func:`ridge_vector`)."""
    return _chol_solve_compiled(G, h, ridge_vector(lam, h.shape[1]), pa, pb, out)


@numba.njit(parallel=True, cache=True)
def _chol_solve_compiled(G, h, lam, pa, pb, out):  # pragma: no cover - numba
    """Solve ``(G_j + diag(lam)) y_j = h_j`` for every block entry; ``out (n, k)``.

    ``G (n, npair)`` packed, ``lam (k,)``. A per-entry k x k Cholesky; when it breaks down (fewer
    observations than k and no ridge) the minimum-norm solution via ``pinv``; an all-zero
    system (never observed, no ridge) gives ``y = 0``. Returns ``(n,)`` int8 flags:
    0 Cholesky, 1 pseudo-inverse, 2 empty. Work buffers are per thread chunk, not per entry.
    """
    n, npair = G.shape
    k = h.shape[1]
    flags = np.zeros(n, dtype=np.int8)
    nchunk = min(n, 64)
    for c in prange(nchunk):
        A = np.empty((k, k))
        Lc = np.zeros((k, k))
        z = np.empty(k)
        y = np.empty(k)
        hv = np.empty(k)
        for j in range(c * n // nchunk, (c + 1) * n // nchunk):
            for p in range(npair):
                A[pa[p], pb[p]] = G[j, p]
                A[pb[p], pa[p]] = G[j, p]
            for a in range(k):
                hv[a] = h[j, a]
            flags[j] = spd_solve(A, hv, lam, Lc, z, y)
            for a in range(k):
                out[j, a] = y[a]
    return flags


def data_stats(D, M, check):
    """Observed counts per time ``(T,)`` and per cell ``(L,)``, the number of non-finite
    observed entries (when ``check``, else 0) and each cell's sum of observed entries ``(L,)``
    (float64); numpy for small data, :func:`data_stats_compiled` for large."""
    if not is_small(D.size):
        return data_stats_compiled(D, M, check)
    M = np.asarray(M, dtype=np.bool_)
    rows = M.sum(axis=1, dtype=np.int64)
    cols = M.sum(axis=0, dtype=np.int64)
    nbad = int(np.count_nonzero(M & ~np.isfinite(D))) if check else 0
    with np.errstate(invalid="ignore", over="ignore"):
        csum = np.where(M, D, 0).sum(axis=0, dtype=np.float64)
    return rows, cols, np.int64(nbad), csum


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def data_stats_compiled(D, M, check):  # pragma: no cover - numba
    """One pass: observed counts per time ``(T,)`` and per cell ``(L,)``, the number of
    non-finite observed entries (when ``check``, else 0) and the sum of the observed entries of
    each cell ``(L,)``. Cells split into disjoint ranges."""
    T, L = D.shape
    nch = 64
    rows_part = np.zeros((nch, T), dtype=np.int64)
    cols = np.zeros(L, dtype=np.int64)
    csum = np.zeros(L)
    bad = np.zeros(nch, dtype=np.int64)
    for c in prange(nch):
        s = c * L // nch
        e = (c + 1) * L // nch
        n = e - s
        cc = np.zeros(n, dtype=np.int32)
        for t in range(T):
            m = M[t, s:e].view(np.uint8)
            d = D[t, s:e]
            cnt = 0
            for jj in range(n):
                mj = m[jj]
                cnt += mj
                cc[jj] += mj
                csum[s + jj] += np.float64(d[jj]) if mj else 0.0
            rows_part[c, t] = cnt
            if check:
                nb = 0
                for jj in range(n):
                    nb += 1 if (m[jj] and not np.isfinite(d[jj])) else 0
                bad[c] += nb
        for jj in range(n):
            cols[s + jj] = cc[jj]
    return rows_part.sum(axis=0), cols, bad.sum(), csum


@numba.njit(parallel=True, cache=True)
def column_moments_compiled(D, M):  # pragma: no cover - numba
    """Per-cell observed sum ``(L,)``, sum of squares about the mean ``(L,)`` (float64) and
    count ``(L,)`` of ``D (T, L)`` under ``M``: two passes over each range of cells, times in
    order (the sums of numpy's row-by-row reduction; no fastmath). Unobserved entries are never
    read."""
    T, L = D.shape
    nch = 64
    csum = np.zeros(L)
    css = np.zeros(L)
    cols = np.zeros(L, dtype=np.int64)
    for c in prange(nch):
        s = c * L // nch
        e = (c + 1) * L // nch
        for t in range(T):
            for j in range(s, e):
                if M[t, j]:
                    cols[j] += 1
                    csum[j] += np.float64(D[t, j])
        mu = np.empty(e - s)
        for j in range(s, e):
            mu[j - s] = csum[j] / max(cols[j], 1)
        for t in range(T):
            for j in range(s, e):
                if M[t, j]:
                    r = np.float64(D[t, j]) - mu[j - s]
                    css[j] += r * r
    return csum, css, cols


@numba.njit(parallel=True, cache=True)
def standardize_compiled(D, M, offset, scale, out):  # pragma: no cover - numba
    """``out = (D - offset) / scale`` on the observed entries (in float64, then cast to
    ``out``'s dtype), 0 elsewhere; ``out`` may be ``D`` itself. Ranges of cells in parallel."""
    T, L = D.shape
    nch = 64
    for c in prange(nch):
        s = c * L // nch
        e = (c + 1) * L // nch
        for t in range(T):
            for j in range(s, e):
                if M[t, j]:
                    out[t, j] = (np.float64(D[t, j]) - offset[j]) / scale[j]
                else:
                    out[t, j] = 0.0


# --------------------------------------------------------------------------- small systems
# One k x k solve and the Gram identity ``y^T G y - 2 h . y + c`` (the quadratic loss of ``y``
# from its block's statistics); shared with the quadratic kernels in ``quadratic.py``.


@numba.njit(inline="always", cache=True)
def spd_solve(A, hv, lam, Lc, z, y):  # pragma: no cover - numba
    """Solve ``(A + diag(lam)) y = hv`` for one ``k x k`` system in place (``A`` is modified;
    ``lam (k,)`` the ridge of each row).

    Cholesky; when it breaks down (singular without ridge) the minimum-norm ``pinv``
    solution; an all-zero system gives ``y = 0``. Returns 0 (Cholesky), 1 (pinv), 2 (empty).
    """
    k = hv.shape[0]
    scale = 0.0
    for a in range(k):
        A[a, a] += lam[a]
        scale = max(scale, A[a, a])
    if scale == 0.0:
        for a in range(k):
            y[a] = 0.0
        return 2
    for a in range(k):
        s = A[a, a]
        for b in range(a):
            s -= Lc[a, b] * Lc[a, b]
        if s <= 1e-12 * scale:
            P = np.linalg.pinv(A)
            for i in range(k):
                acc = 0.0
                for b in range(k):
                    acc += P[i, b] * hv[b]
                y[i] = acc
            return 1
        Lc[a, a] = np.sqrt(s)
        for i in range(a + 1, k):
            s2 = A[i, a]
            for b in range(a):
                s2 -= Lc[i, b] * Lc[a, b]
            Lc[i, a] = s2 / Lc[a, a]
    for a in range(k):
        s = hv[a]
        for b in range(a):
            s -= Lc[a, b] * z[b]
        z[a] = s / Lc[a, a]
    for a in range(k - 1, -1, -1):
        s = z[a]
        for b in range(a + 1, k):
            s -= Lc[b, a] * y[b]
        y[a] = s / Lc[a, a]
    return 0


@numba.njit(inline="always", cache=True)
def quad_value(A, hv, c, y):  # pragma: no cover - numba
    """``y^T A y - 2 hv . y + c`` (``A`` symmetric, full)."""
    k = hv.shape[0]
    v = c
    for a in range(k):
        s = 0.0
        for b in range(k):
            s += A[a, b] * y[b]
        v += y[a] * (s - 2.0 * hv[a])
    return v
