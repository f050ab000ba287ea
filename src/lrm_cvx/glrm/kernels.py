"""Compiled kernels of the GLRM fit: one pass over ``(T, L)`` data builds every block's Gram.

All kernels read the data ``D`` (float32/float64, ``(T, L)``) together with a boolean mask ``M``
(True = observed) and never look at ``D`` where ``M`` is False, so unobserved entries may hold
anything (zeros, NaN). Accumulation is in float64.

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
QBLOCK_COLS = 512  # cells per block of the quadratic Y-step kernel (wide rows: memory streams)
QBLOCK_ROWS = 1024  # cells per block of the quadratic X-step kernel


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


@numba.njit(parallel=True, cache=True)
def chol_solve(G, h, lam, pa, pb, out):  # pragma: no cover - numba
    """Solve ``(G_j + lam I) y_j = h_j`` for every block entry; ``out (n, k)``.

    ``G (n, npair)`` packed. A per-entry k x k Cholesky; when it breaks down (fewer
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
            flags[j] = _spd_solve(A, hv, lam, Lc, z, y)
            for a in range(k):
                out[j, a] = y[a]
    return flags


@numba.njit(parallel=True, cache=True)
def mask_stats(D, M, check):  # pragma: no cover - numba
    """Observed counts per time ``(T,)`` and per cell ``(L,)``, and the number of non-finite
    observed entries when ``check`` (else 0). One pass; cells split into disjoint ranges."""
    T, L = D.shape
    nch = 64
    rows_part = np.zeros((nch, T), dtype=np.int64)
    cols = np.zeros(L, dtype=np.int64)
    bad = np.zeros(nch, dtype=np.int64)
    for c in prange(nch):
        s = c * L // nch
        e = (c + 1) * L // nch
        for t in range(T):
            cnt = 0
            nb = 0
            for j in range(s, e):
                if M[t, j]:
                    cnt += 1
                    cols[j] += 1
                    if check and not np.isfinite(D[t, j]):
                        nb += 1
            rows_part[c, t] = cnt
            bad[c] += nb
    return rows_part.sum(axis=0), cols, bad.sum()


@numba.njit(inline="always", cache=True)
def _filled_rows(D, M, mu, t0, nt, s, n, zb):  # pragma: no cover - numba
    """``zb[i, jj] = Z[t0 + i, s + jj]`` for ``i < nt``, ``Z = where(M, D, mu)``."""
    for i in range(nt):
        for jj in range(n):
            zb[i, jj] = D[t0 + i, s + jj] if M[t0 + i, s + jj] else mu[s + jj]


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def filled_matmul(D, M, mu, Vt, nchunk):  # pragma: no cover - numba
    """``Z @ Vt.T``, ``Z = where(M, D, mu[None, :])`` (mean-filled); ``Vt (p, L)`` -> ``(T, p)``.

    Used by the randomized SVD initialisation. Cell ranges in parallel, four times at a time.
    """
    T, L = D.shape
    p = Vt.shape[0]
    B = QBLOCK_ROWS
    T4 = T - T % 4
    part = np.zeros((nchunk, T, p))
    for c in prange(nchunk):
        s0 = c * L // nchunk
        e0 = (c + 1) * L // nchunk
        zb = np.empty((4, B))
        vb = np.empty((p, B))
        for b0 in range(s0, e0, B):
            n = min(b0 + B, e0) - b0
            for q in range(p):
                for jj in range(n):
                    vb[q, jj] = Vt[q, b0 + jj]
            for t0 in range(0, T, 4):
                nt = 4 if t0 < T4 else T - t0
                _filled_rows(D, M, mu, t0, nt, b0, n, zb)
                if nt == 4:
                    for q in range(p):
                        a0 = 0.0
                        a1 = 0.0
                        a2 = 0.0
                        a3 = 0.0
                        for jj in range(n):
                            v = vb[q, jj]
                            a0 += zb[0, jj] * v
                            a1 += zb[1, jj] * v
                            a2 += zb[2, jj] * v
                            a3 += zb[3, jj] * v
                        part[c, t0, q] += a0
                        part[c, t0 + 1, q] += a1
                        part[c, t0 + 2, q] += a2
                        part[c, t0 + 3, q] += a3
                else:
                    for i in range(nt):
                        for q in range(p):
                            acc = 0.0
                            for jj in range(n):
                                acc += zb[i, jj] * vb[q, jj]
                            part[c, t0 + i, q] += acc
    return part.sum(axis=0)


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def filled_rmatmul(D, M, mu, U):  # pragma: no cover - numba
    """``(Z.T @ U).T`` with ``Z = where(M, D, mu[None, :])``; ``U (T, p)`` -> ``(p, L)``."""
    T, L = D.shape
    p = U.shape[1]
    B = QBLOCK_COLS
    T4 = T - T % 4
    out = np.empty((p, L))
    nblk = (L + B - 1) // B
    for ib in prange(nblk):
        s = ib * B
        n = min(s + B, L) - s
        zb = np.empty((4, B))
        ob = np.zeros((p, B))
        for t0 in range(0, T, 4):
            nt = 4 if t0 < T4 else T - t0
            _filled_rows(D, M, mu, t0, nt, s, n, zb)
            if nt == 4:
                for q in range(p):
                    u0 = U[t0, q]
                    u1 = U[t0 + 1, q]
                    u2 = U[t0 + 2, q]
                    u3 = U[t0 + 3, q]
                    for jj in range(n):
                        ob[q, jj] += (zb[0, jj] * u0 + zb[1, jj] * u1) + (
                            zb[2, jj] * u2 + zb[3, jj] * u3)
            else:
                for i in range(nt):
                    for q in range(p):
                        u = U[t0 + i, q]
                        for jj in range(n):
                            ob[q, jj] += zb[i, jj] * u
        for q in range(p):
            for jj in range(n):
                out[q, s + jj] = ob[q, jj]
    return out


@numba.njit(parallel=True, cache=True)
def data_stats(D, M, check):  # pragma: no cover - numba
    """One pass: observed counts per time ``(T,)`` and per cell ``(L,)``, the number of
    non-finite observed entries (when ``check``, else 0), the sum of the observed entries of
    each cell ``(L,)`` and the sum of squares of all observed entries (0 when there are
    non-finite ones). Cells split into disjoint ranges."""
    T, L = D.shape
    nch = 64
    rows_part = np.zeros((nch, T), dtype=np.int64)
    cols = np.zeros(L, dtype=np.int64)
    csum = np.zeros(L)
    bad = np.zeros(nch, dtype=np.int64)
    ssq = np.zeros(nch)
    for c in prange(nch):
        s = c * L // nch
        e = (c + 1) * L // nch
        sq = 0.0
        for t in range(T):
            cnt = 0
            nb = 0
            for j in range(s, e):
                if M[t, j]:
                    d = np.float64(D[t, j])  # float64 square of float32 data
                    cnt += 1
                    cols[j] += 1
                    csum[j] += d
                    sq += d * d
                    if check and not np.isfinite(d):
                        nb += 1
            rows_part[c, t] = cnt
            bad[c] += nb
        ssq[c] = sq
    nbad = bad.sum()
    return rows_part.sum(axis=0), cols, nbad, csum, ssq.sum() if nbad == 0 else 0.0


@numba.njit(parallel=True, cache=True)
def column_means(D, M, fallback):  # pragma: no cover - numba
    """Mean of the observed entries of each cell ``(L,)`` (``fallback`` where never observed)
    and the sum of squares of all observed entries."""
    T, L = D.shape
    out = np.empty(L)
    nblk = (L + BLOCK_COLS - 1) // BLOCK_COLS
    ssq = np.zeros(nblk)
    for ib in prange(nblk):
        s = ib * BLOCK_COLS
        e = min(s + BLOCK_COLS, L)
        acc = np.zeros(e - s)
        cnt = np.zeros(e - s)
        sq = 0.0
        for t in range(T):
            for j in range(s, e):
                if M[t, j]:
                    d = D[t, j]
                    acc[j - s] += d
                    cnt[j - s] += 1.0
                    sq += d * d
        ssq[ib] = sq
        for j in range(s, e):
            out[j] = acc[j - s] / cnt[j - s] if cnt[j - s] > 0 else fallback
    return out, ssq.sum()


# --------------------------------------------------------------------------- quadratic fast path
# For the quadratic loss the block problems need only the masked Gram statistics, which the
# kernels below build without residuals: per column ``G_j = sum_t m_tj x_t x_t^T``,
# ``h_j = sum_t m_tj d_tj x_t`` and ``c_j = sum_t m_tj d_tj^2``. The loss of any ``y`` is then
# ``y^T G_j y - 2 h_j . y + c_j`` (the Gram identity), so the objective before and after a step
# costs no extra pass. The Y step processes times eight at a time (one read-modify-write of each
# accumulator per eight FMAs; ~5-10% faster than four at k = 5), the X step four at a time
# (eight was slower there).


@numba.njit(inline="always", cache=True)
def _spd_solve(A, hv, lam, Lc, z, y):  # pragma: no cover - numba
    """Solve ``(A + lam I) y = hv`` for one ``k x k`` system in place (``A`` is modified).

    Cholesky; when it breaks down (singular without ridge) the minimum-norm ``pinv``
    solution; an all-zero system gives ``y = 0``. Returns 0 (Cholesky), 1 (pinv), 2 (empty).
    """
    k = hv.shape[0]
    scale = 0.0
    for a in range(k):
        A[a, a] += lam
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
def _quad_value(A, hv, c, y):  # pragma: no cover - numba
    """``y^T A y - 2 hv . y + c`` (``A`` symmetric, full)."""
    k = hv.shape[0]
    v = c
    for a in range(k):
        s = 0.0
        for b in range(k):
            s += A[a, b] * y[b]
        v += y[a] * (s - 2.0 * hv[a])
    return v


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def quad_y_step(D, M, X, Y, lam, pa, pb, out, nchunk):  # pragma: no cover - numba
    """Exact quadratic Y step: ``out[:, j] = argmin_y ||P_j(X^T y - d_j)||^2 + lam ||y||^2``.

    ``D (T, L)``, ``M (T, L)`` bool, ``X (k, T)`` float64, ``Y (k, L)`` the current columns
    (may be the same array as ``out``). One fused pass: per block of cells the Gram entries,
    ``h`` and ``c`` are accumulated over all times, then each cell's k x k system is solved in
    place. Returns ``(loss_before, loss_after, n_pinv)``: the quadratic loss over observed
    entries at ``Y`` and at ``out`` (Gram identity; no ridge term) and the number of cells
    solved by the pseudo-inverse.
    """
    T, L = D.shape
    k = X.shape[0]
    npair = pa.shape[0]
    B = QBLOCK_COLS
    XX = np.empty((T, npair))
    Xt = np.empty((T, k))
    for t in range(T):
        for a in range(k):
            Xt[t, a] = X[a, t]
        for p in range(npair):
            XX[t, p] = X[pa[p], t] * X[pb[p], t]
    part = np.zeros((nchunk, 3))
    nblk = (L + B - 1) // B
    T8 = T - T % 8
    for c in prange(nchunk):
        gb = np.empty((npair, B))
        hb = np.empty((k, B))
        cb = np.empty(B)
        mb = np.empty((8, B))
        db = np.empty((8, B))
        A = np.empty((k, k))
        Lc = np.zeros((k, k))
        z = np.empty(k)
        y = np.empty(k)
        hv = np.empty(k)
        fb = 0.0
        fa = 0.0
        npinv = 0
        for ib in range(c * nblk // nchunk, (c + 1) * nblk // nchunk):
            s = ib * B
            n = min(s + B, L) - s
            gb[:, :n] = 0.0
            hb[:, :n] = 0.0
            cb[:n] = 0.0
            for t0 in range(0, T8, 8):
                for i in range(8):
                    for jj in range(n):
                        m = M[t0 + i, s + jj]
                        d = D[t0 + i, s + jj]
                        mb[i, jj] = 1.0 if m else 0.0
                        db[i, jj] = d if m else 0.0
                for p in range(npair):
                    x0 = XX[t0, p]
                    x1 = XX[t0 + 1, p]
                    x2 = XX[t0 + 2, p]
                    x3 = XX[t0 + 3, p]
                    x4 = XX[t0 + 4, p]
                    x5 = XX[t0 + 5, p]
                    x6 = XX[t0 + 6, p]
                    x7 = XX[t0 + 7, p]
                    for jj in range(n):
                        gb[p, jj] += ((mb[0, jj] * x0 + mb[1, jj] * x1)
                                      + (mb[2, jj] * x2 + mb[3, jj] * x3)) + (
                            (mb[4, jj] * x4 + mb[5, jj] * x5)
                            + (mb[6, jj] * x6 + mb[7, jj] * x7))
                for a in range(k):
                    x0 = Xt[t0, a]
                    x1 = Xt[t0 + 1, a]
                    x2 = Xt[t0 + 2, a]
                    x3 = Xt[t0 + 3, a]
                    x4 = Xt[t0 + 4, a]
                    x5 = Xt[t0 + 5, a]
                    x6 = Xt[t0 + 6, a]
                    x7 = Xt[t0 + 7, a]
                    for jj in range(n):
                        hb[a, jj] += ((db[0, jj] * x0 + db[1, jj] * x1)
                                      + (db[2, jj] * x2 + db[3, jj] * x3)) + (
                            (db[4, jj] * x4 + db[5, jj] * x5)
                            + (db[6, jj] * x6 + db[7, jj] * x7))
                for jj in range(n):
                    cb[jj] += ((db[0, jj] * db[0, jj] + db[1, jj] * db[1, jj])
                               + (db[2, jj] * db[2, jj] + db[3, jj] * db[3, jj])) + (
                        (db[4, jj] * db[4, jj] + db[5, jj] * db[5, jj])
                        + (db[6, jj] * db[6, jj] + db[7, jj] * db[7, jj]))
            for t in range(T8, T):
                for jj in range(n):
                    m = M[t, s + jj]
                    d = D[t, s + jj]
                    mb[0, jj] = 1.0 if m else 0.0
                    db[0, jj] = d if m else 0.0
                for p in range(npair):
                    x0 = XX[t, p]
                    for jj in range(n):
                        gb[p, jj] += mb[0, jj] * x0
                for a in range(k):
                    x0 = Xt[t, a]
                    for jj in range(n):
                        hb[a, jj] += db[0, jj] * x0
                for jj in range(n):
                    cb[jj] += db[0, jj] * db[0, jj]
            for jj in range(n):
                j = s + jj
                for p in range(npair):
                    A[pa[p], pb[p]] = gb[p, jj]
                    A[pb[p], pa[p]] = gb[p, jj]
                for a in range(k):
                    hv[a] = hb[a, jj]
                    y[a] = Y[a, j]
                fb += _quad_value(A, hv, cb[jj], y)
                npinv += _spd_solve(A, hv, lam, Lc, z, y) == 1
                for a in range(k):
                    A[a, a] -= lam
                fa += _quad_value(A, hv, cb[jj], y)
                for a in range(k):
                    out[a, j] = y[a]
        part[c, 0] = fb
        part[c, 1] = fa
        part[c, 2] = npinv
    return part[:, 0].sum(), part[:, 1].sum(), int(part[:, 2].sum())


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def quad_x_stats(D, M, Y, pa, pb, nchunk, G, h, c):  # pragma: no cover - numba
    """X-step statistics of the quadratic loss, partial sums over ``nchunk`` cell ranges.

    ``G (nchunk, T, npair)``: ``sum_j m_tj y_j y_j^T`` packed; ``h (nchunk, T, k)``:
    ``sum_j m_tj d_tj y_j``; ``c (nchunk, T)``: ``sum_j m_tj d_tj^2``. Overwritten (no need to
    zero). The caller sums over the first axis.
    """
    T, L = D.shape
    k = Y.shape[0]
    npair = pa.shape[0]
    B = QBLOCK_ROWS
    T4 = T - T % 4
    for ci in prange(nchunk):
        s0 = ci * L // nchunk
        e0 = (ci + 1) * L // nchunk
        yb = np.empty((k, B))
        yy = np.empty((npair, B))
        mb = np.empty((4, B))
        db = np.empty((4, B))
        Gc = np.zeros((T, npair))
        hc = np.zeros((T, k))
        cc = np.zeros(T)
        for b0 in range(s0, e0, B):
            n = min(b0 + B, e0) - b0
            for a in range(k):
                for jj in range(n):
                    yb[a, jj] = Y[a, b0 + jj]
            for p in range(npair):
                for jj in range(n):
                    yy[p, jj] = yb[pa[p], jj] * yb[pb[p], jj]
            for t0 in range(0, T4, 4):
                for i in range(4):
                    for jj in range(n):
                        m = M[t0 + i, b0 + jj]
                        d = D[t0 + i, b0 + jj]
                        mb[i, jj] = 1.0 if m else 0.0
                        db[i, jj] = d if m else 0.0
                for p in range(npair):
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    a3 = 0.0
                    for jj in range(n):
                        v = yy[p, jj]
                        a0 += mb[0, jj] * v
                        a1 += mb[1, jj] * v
                        a2 += mb[2, jj] * v
                        a3 += mb[3, jj] * v
                    Gc[t0, p] += a0
                    Gc[t0 + 1, p] += a1
                    Gc[t0 + 2, p] += a2
                    Gc[t0 + 3, p] += a3
                for a in range(k):
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    a3 = 0.0
                    for jj in range(n):
                        v = yb[a, jj]
                        a0 += db[0, jj] * v
                        a1 += db[1, jj] * v
                        a2 += db[2, jj] * v
                        a3 += db[3, jj] * v
                    hc[t0, a] += a0
                    hc[t0 + 1, a] += a1
                    hc[t0 + 2, a] += a2
                    hc[t0 + 3, a] += a3
                for i in range(4):
                    acc = 0.0
                    for jj in range(n):
                        acc += db[i, jj] * db[i, jj]
                    cc[t0 + i] += acc
            for t in range(T4, T):
                for jj in range(n):
                    m = M[t, b0 + jj]
                    d = D[t, b0 + jj]
                    mb[0, jj] = 1.0 if m else 0.0
                    db[0, jj] = d if m else 0.0
                for p in range(npair):
                    acc = 0.0
                    for jj in range(n):
                        acc += mb[0, jj] * yy[p, jj]
                    Gc[t, p] += acc
                for a in range(k):
                    acc = 0.0
                    for jj in range(n):
                        acc += db[0, jj] * yb[a, jj]
                    hc[t, a] += acc
                acc = 0.0
                for jj in range(n):
                    acc += db[0, jj] * db[0, jj]
                cc[t] += acc
        G[ci] = Gc
        h[ci] = hc
        c[ci] = cc
