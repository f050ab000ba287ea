"""The quadratic fast path: masked Gram statistics from zero-filled data and a packed mask.

For the quadratic loss every block problem needs only masked Gram statistics,
``G_j = sum_t m_tj x_t x_t^T`` and ``h_j = sum_t m_tj d_tj x_t`` for a cell (Y step), and the
same sums over cells for a time (X step). Two facts make them cheap at paper scale:

* **Zero-filled data.** With ``d_tj = 0`` wherever ``m_tj = 0``, the linear terms are plain
  products of the float32 data (``h = X D``), read straight from memory with no mask test.
* **A packed mask.** ``m_tj`` is 0/1, so the Grams are subset sums. The mask is packed once per
  fit into bytes of eight times (``codes[g, j]``, bit ``i`` = ``m_{8g+i, j}``). In the Y step
  ``G_j`` is then a sum of ``T/8`` table look-ups (each table holds the 256 subset sums of
  eight times' ``x_t x_t^T``); in the X step each cell's ``y_j y_j^T`` is added to one of 256
  bins per byte and the bins are folded into the times afterwards. Both replace ``T``
  multiply-adds per Gram entry by ``T/8`` additions.

:class:`MaskedData` carries the zero-filled data, the codes and the per-time sums of squares;
:func:`prepare` builds it in one pass (copying the data only when it holds values at masked
entries and may not be overwritten). Accumulation is in float64; results equal the direct
sums up to rounding.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np
from numba import prange

from .kernels import chol_solve_numpy, is_small, quad_value, ridge_vector, spd_solve

_FM = {"contract", "reassoc", "arcp", "nsz"}
GROUP = 8  # times per mask byte
COL_BLOCK = 512  # cells per block in the column (Y-step) kernels
ROW_BLOCK = 1024  # cells per block in the row (X-step) kernels


class MaskedData(NamedTuple):
    """Zero-filled data with its packed mask: what the quadratic kernels read.

    ``D (T, L)`` float32/float64 with 0 at unobserved entries; ``codes (ceil(T/8), L)`` uint8
    with bit ``i`` of ``codes[g, j]`` set when ``(8g + i, j)`` is observed; ``ssq_rows (T,)``
    the sum of squares of each time's observed values (float64).
    """

    D: np.ndarray
    codes: np.ndarray
    ssq_rows: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.D.shape

    def mask(self) -> np.ndarray:
        """The boolean observed mask ``(T, L)`` unpacked from ``codes``."""
        bits = np.unpackbits(self.codes, axis=0, count=self.D.shape[0], bitorder="little")
        return bits.view(bool)


def _nchunk() -> int:
    return max(2 * numba.get_num_threads(), 2)


class PassCounter:
    """Entries of ``D`` read by the kernel calls of this module (and ``check_data``'s scan):
    each call that reads all of a ``(T, L)`` data matrix adds ``T * L``, so
    ``entries / (T * L)`` is the number of full passes over the data (a chunked fit adds
    its chunks' sizes, so the ratio stays the number of passes). ``reset()`` before a fit."""

    def __init__(self) -> None:
        import threading

        self._lock = threading.Lock()
        self.entries = 0

    def add(self, D: np.ndarray) -> None:
        with self._lock:
            self.entries += int(D.shape[0]) * int(D.shape[1])

    def reset(self) -> None:
        with self._lock:
            self.entries = 0

    def passes(self, shape: tuple[int, int]) -> float:
        """Full passes over a ``(T, L)`` matrix read since the last reset."""
        return self.entries / max(int(shape[0]) * int(shape[1]), 1)


PASSES = PassCounter()


def pad_width(n: int) -> int:
    """``n`` rounded up to a multiple of 8 (one 512-bit vector of float64)."""
    return (n + 7) // 8 * 8


# --------------------------------------------------------------------------- preparation
@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _scan(D, M, codes):  # pragma: no cover - numba
    """Pack ``M`` into ``codes``; return the per-time sums of squares of the observed values
    ``(T,)`` and the number of unobserved entries whose value is not 0 (NaN included)."""
    T, L = D.shape
    ng = codes.shape[0]
    ssq = np.zeros(T)
    dirty = np.zeros(T, dtype=np.int64)
    for g in prange(ng):
        t0 = GROUP * g
        nt = min(GROUP, T - t0)
        for i in range(nt):
            acc = 0.0
            nd = 0
            for j in range(L):
                m = M[t0 + i, j]
                d = np.float64(D[t0 + i, j])
                acc += d * d if m else 0.0
                nd += 0 if (m or d == 0.0) else 1
            ssq[t0 + i] = acc
            dirty[t0 + i] = nd
        row = codes[g]
        if nt == GROUP:
            m0 = M[t0].view(np.uint8)
            m1 = M[t0 + 1].view(np.uint8)
            m2 = M[t0 + 2].view(np.uint8)
            m3 = M[t0 + 3].view(np.uint8)
            m4 = M[t0 + 4].view(np.uint8)
            m5 = M[t0 + 5].view(np.uint8)
            m6 = M[t0 + 6].view(np.uint8)
            m7 = M[t0 + 7].view(np.uint8)
            for j in range(L):
                row[j] = ((m0[j] | (m1[j] << 1)) | ((m2[j] << 2) | (m3[j] << 3))) | (
                    ((m4[j] << 4) | (m5[j] << 5)) | ((m6[j] << 6) | (m7[j] << 7)))
        else:
            row[:] = 0
            for i in range(nt):
                mi = M[t0 + i].view(np.uint8)
                for j in range(L):
                    row[j] |= mi[j] << i
    return ssq, dirty.sum()


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _zero_fill(D, M, out):  # pragma: no cover - numba
    """``out = where(M, D, 0)``; ``out`` may be ``D`` itself."""
    T, L = D.shape
    for t in prange(T):
        for j in range(L):
            out[t, j] = D[t, j] if M[t, j] else 0.0


def prepare(D: np.ndarray, M: np.ndarray, *, overwrite: bool = False) -> MaskedData:
    """:class:`MaskedData` of ``D (T, L)`` observed where ``M (T, L)`` is True.

    One pass packs the mask and finds whether ``D`` is already zero at every unobserved entry
    (as a zero-filled array with a mask, or a chunk of a dask fit, is); if not, the zeros are
    written into ``D`` itself when ``overwrite`` is True and into a copy otherwise. ``D`` is
    float32 or float64; a non-contiguous ``D`` is copied.
    """
    T, L = D.shape
    M = np.ascontiguousarray(M, dtype=np.bool_)
    if not D.flags.c_contiguous:  # the kernels stream rows
        D, overwrite = np.ascontiguousarray(D), True
    if is_small(D.size):  # numpy: same result, nothing to compile (kernels.SMALL_ENTRIES)
        codes = np.packbits(M, axis=0, bitorder="little")
        filled = np.where(M, D, 0).astype(D.dtype, copy=False)
        ssq = np.square(filled, dtype=np.float64).sum(axis=1)
        dirty = np.count_nonzero(~M & (D != 0))  # NaN != 0 counts, as in _scan
        PASSES.add(D)
        if dirty:
            if overwrite:
                D[...] = filled
            else:
                D = filled
            PASSES.add(D)
        return MaskedData(D, codes, ssq)
    codes = np.empty(((T + GROUP - 1) // GROUP, L), dtype=np.uint8)
    ssq, dirty = _scan(D, M, codes)
    PASSES.add(D)
    if dirty:
        out = D if overwrite else np.empty_like(D)
        _zero_fill(D, M, out)
        PASSES.add(D)
        D = out
    return MaskedData(D, codes, ssq)


# --------------------------------------------------------------------------- subset-sum tables
@numba.njit(cache=True)
def subset_tables(A, ng):  # pragma: no cover - numba
    """``TAB (ng, 256, w)``: ``TAB[g, c] = sum of A[8g + i] over the bits i of c``.

    ``A (T, w)`` float64; times past ``T`` count as zero rows. Each entry is one addition from
    the entry without its lowest bit.
    """
    T, w = A.shape
    TAB = np.zeros((ng, 256, w))
    for g in range(ng):
        for c in range(1, 256):
            low = c & (-c)
            i = 0
            while (1 << i) != low:
                i += 1
            t = GROUP * g + i
            prev = c ^ low
            if t < T:
                for p in range(w):
                    TAB[g, c, p] = TAB[g, prev, p] + A[t, p]
            else:
                for p in range(w):
                    TAB[g, c, p] = TAB[g, prev, p]
    return TAB


def pair_products(F: np.ndarray, pa: np.ndarray, pb: np.ndarray, width: int) -> np.ndarray:
    """``(T, width)`` float64: column ``p`` holds ``F[pa[p]] * F[pb[p]]`` (zero padding after)."""
    out = np.zeros((F.shape[1], width))
    out[:, : pa.size] = (F[pa] * F[pb]).T
    return out


# --------------------------------------------------------------------------- column kernels
@numba.njit(inline="always", cache=True, fastmath=_FM)
def _col_block(D, codes, s, n, Xt, TAB, hb, gb, acc):  # pragma: no cover - numba
    """For cells ``s..s+n``: ``hb[a, jj] = sum_t d_t,s+jj Xt[t, a]`` and
    ``gb[jj] = sum_g TAB[g, codes[g, s+jj]]`` (one table look-up per eight times)."""
    T = D.shape[0]
    ka = Xt.shape[1]
    ng, _, w = TAB.shape
    T8 = T - T % 8
    hb[:, :n] = 0.0
    for t0 in range(0, T8, 8):
        d0 = D[t0, s:s + n]
        d1 = D[t0 + 1, s:s + n]
        d2 = D[t0 + 2, s:s + n]
        d3 = D[t0 + 3, s:s + n]
        d4 = D[t0 + 4, s:s + n]
        d5 = D[t0 + 5, s:s + n]
        d6 = D[t0 + 6, s:s + n]
        d7 = D[t0 + 7, s:s + n]
        for a in range(ka):
            x0 = Xt[t0, a]
            x1 = Xt[t0 + 1, a]
            x2 = Xt[t0 + 2, a]
            x3 = Xt[t0 + 3, a]
            x4 = Xt[t0 + 4, a]
            x5 = Xt[t0 + 5, a]
            x6 = Xt[t0 + 6, a]
            x7 = Xt[t0 + 7, a]
            for jj in range(n):
                hb[a, jj] += ((np.float64(d0[jj]) * x0 + np.float64(d1[jj]) * x1)
                              + (np.float64(d2[jj]) * x2 + np.float64(d3[jj]) * x3)) + (
                    (np.float64(d4[jj]) * x4 + np.float64(d5[jj]) * x5)
                    + (np.float64(d6[jj]) * x6 + np.float64(d7[jj]) * x7))
    for t in range(T8, T):
        dt = D[t, s:s + n]
        for a in range(ka):
            x0 = Xt[t, a]
            for jj in range(n):
                hb[a, jj] += np.float64(dt[jj]) * x0
    for jj in range(n):
        acc[:] = 0.0
        for g in range(ng):
            cd = codes[g, s + jj]
            for p in range(w):
                acc[p] += TAB[g, cd, p]
        for p in range(w):
            gb[jj, p] = acc[p]


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _filled_rmatmul(D, codes, U, TAB, mu, usum, out):  # pragma: no cover - numba
    """``out (p, L) = (Z^T U)^T`` for ``Z = D0 + (1 - M) mu``: ``D0^T U + mu (usum - M^T U)``
    with ``usum = U.sum(0)`` and ``TAB = subset_tables(U)``."""
    L = D.shape[1]
    p = U.shape[1]
    w = TAB.shape[2]
    B = COL_BLOCK
    nblk = (L + B - 1) // B
    for ib in prange(nblk):
        s = ib * B
        n = min(s + B, L) - s
        hb = np.empty((p, B))
        gb = np.empty((B, w))
        acc = np.empty(w)
        _col_block(D, codes, s, n, U, TAB, hb, gb, acc)
        for q in range(p):
            for jj in range(n):
                out[q, s + jj] = hb[q, jj] + mu[s + jj] * (usum[q] - gb[jj, q])


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _y_step(D, codes, Xt, TAB, lam, pa, pb, Y, out, nchunk):  # pragma: no cover - numba
    """Fused quadratic Y step (Gram by table look-ups, then each cell's k x k solve).

    Returns ``(q_before, q_after, n_pinv)`` with ``q = sum_j y_j^T G_j y_j - 2 h_j . y_j``
    (the loss minus the observed sum of squares) at ``Y`` and at ``out``.
    """
    L = D.shape[1]
    k = Xt.shape[1]
    npair = pa.shape[0]
    w = TAB.shape[2]
    B = COL_BLOCK
    nblk = (L + B - 1) // B
    part = np.zeros((nchunk, 3))
    for c in prange(nchunk):
        hb = np.empty((k, B))
        gb = np.empty((B, w))
        acc = np.empty(w)
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
            _col_block(D, codes, s, n, Xt, TAB, hb, gb, acc)
            for jj in range(n):
                j = s + jj
                for p in range(npair):
                    A[pa[p], pb[p]] = gb[jj, p]
                    A[pb[p], pa[p]] = gb[jj, p]
                for a in range(k):
                    hv[a] = hb[a, jj]
                    y[a] = Y[a, j]
                fb += quad_value(A, hv, 0.0, y)
                npinv += spd_solve(A, hv, lam, Lc, z, y) == 1
                for a in range(k):
                    A[a, a] -= lam[a]
                fa += quad_value(A, hv, 0.0, y)
                for a in range(k):
                    out[a, j] = y[a]
        part[c, 0] = fb
        part[c, 1] = fa
        part[c, 2] = npinv
    return part[:, 0].sum(), part[:, 1].sum(), int(part[:, 2].sum())


# --------------------------------------------------------------------------- row kernel
@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _row_products(D, codes, W, V, pa, pb, nchunk, H, G):  # pragma: no cover - numba
    """Partial sums over ``nchunk`` cell ranges: ``H[c] (T, p1) = D W^T`` and
    ``G[c] (T, npair)``: ``sum_j m_tj V[pa, j] V[pb, j]``. Overwritten.

    The Gram part adds each cell's pair-product vector to one of 256 bins per mask byte, then
    folds every bin into the times whose bit it has set.
    """
    T, L = D.shape
    p1 = W.shape[0]
    npair = pa.shape[0]
    ng = codes.shape[0]
    B = ROW_BLOCK
    T4 = T - T % 4
    for ci in prange(nchunk):
        s0 = ci * L // nchunk
        e0 = (ci + 1) * L // nchunk
        wb = np.empty((p1, B))
        vb = np.empty((B, npair))
        S = np.zeros((ng, 256, npair))
        hc = np.zeros((T, p1))
        for b0 in range(s0, e0, B):
            n = min(b0 + B, e0) - b0
            for a in range(p1):
                for jj in range(n):
                    wb[a, jj] = W[a, b0 + jj]
            for jj in range(n):
                for p in range(npair):
                    vb[jj, p] = V[pa[p], b0 + jj] * V[pb[p], b0 + jj]
            for g in range(ng):
                for jj in range(n):
                    cd = codes[g, b0 + jj]
                    for p in range(npair):
                        S[g, cd, p] += vb[jj, p]
            for t0 in range(0, T4, 4):
                d0 = D[t0, b0:b0 + n]
                d1 = D[t0 + 1, b0:b0 + n]
                d2 = D[t0 + 2, b0:b0 + n]
                d3 = D[t0 + 3, b0:b0 + n]
                for a in range(p1):
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    a3 = 0.0
                    for jj in range(n):
                        v = wb[a, jj]
                        a0 += np.float64(d0[jj]) * v
                        a1 += np.float64(d1[jj]) * v
                        a2 += np.float64(d2[jj]) * v
                        a3 += np.float64(d3[jj]) * v
                    hc[t0, a] += a0
                    hc[t0 + 1, a] += a1
                    hc[t0 + 2, a] += a2
                    hc[t0 + 3, a] += a3
            for t in range(T4, T):
                dt = D[t, b0:b0 + n]
                for a in range(p1):
                    a0 = 0.0
                    for jj in range(n):
                        a0 += np.float64(dt[jj]) * wb[a, jj]
                    hc[t, a] += a0
        H[ci] = hc
        for t in range(T):
            g = t // GROUP
            bit = 1 << (t % GROUP)
            for p in range(npair):
                G[ci, t, p] = 0.0
            for cd in range(256):
                if cd & bit:
                    for p in range(npair):
                        G[ci, t, p] += S[g, cd, p]


def row_products(md: MaskedData, W: np.ndarray, V: np.ndarray, pa: np.ndarray,
                 pb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(D W^T (T, p1), G (T, npair))`` with ``G[t, p] = sum_j m_tj V[pa[p], j] V[pb[p], j]``.

    ``W (p1, L)`` and ``V (q, L)`` float64.
    """
    T = md.D.shape[0]
    if is_small(md.D.size):
        PASSES.add(md.D)
        D = md.D.astype(np.float64, copy=False)
        M = md.mask().astype(np.float64)
        H = D @ np.asarray(W, dtype=np.float64).T
        V = np.asarray(V, dtype=np.float64)
        return H, M @ (V[pa] * V[pb]).T
    nch = _nchunk()
    H = np.empty((nch, T, W.shape[0]))
    G = np.empty((nch, T, pa.size))
    PASSES.add(md.D)
    _row_products(md.D, md.codes, np.ascontiguousarray(W, dtype=np.float64),
                  np.ascontiguousarray(V, dtype=np.float64), pa, pb, nch, H, G)
    return H.sum(0), G.sum(0)


# --------------------------------------------------------------------------- public steps
def _pairs(k: int) -> tuple[np.ndarray, np.ndarray]:
    pa, pb = np.triu_indices(k)
    return pa.astype(np.int64), pb.astype(np.int64)


def y_step(md: MaskedData, X: np.ndarray, Y: np.ndarray, lam: Any,
           out: np.ndarray) -> tuple[float, float, int]:
    """Exact quadratic + ridge Y step into ``out (k, L)`` float64 (may be ``Y``).

    ``out[:, j] = argmin_y ||P_j(X^T y - d_j)||^2 + sum_a lam_a y_a^2`` (``lam`` a number or one
    per row). Returns the loss over
    observed entries at ``Y`` and at ``out`` (no ridge term) and the number of cells solved by
    the pseudo-inverse (fewer observations than the rank, no ridge).
    """
    k, T = X.shape
    pa, pb = _pairs(k)
    X = np.ascontiguousarray(X, dtype=np.float64)
    lam = ridge_vector(lam, k)
    if is_small(md.D.size):
        return _y_step_numpy(md, X, Y, lam, out, pa, pb)
    TAB = subset_tables(pair_products(X, pa, pb, pad_width(pa.size)), md.codes.shape[0])
    PASSES.add(md.D)
    before, after, npinv = _y_step(md.D, md.codes, np.ascontiguousarray(X.T), TAB, lam,
                                   pa, pb, Y, out, _nchunk())
    ssq = float(md.ssq_rows.sum())
    return before + ssq, after + ssq, npinv


def _y_step_numpy(md: MaskedData, X: np.ndarray, Y: np.ndarray, lam: np.ndarray, out: np.ndarray,
                  pa: np.ndarray, pb: np.ndarray) -> tuple[float, float, int]:
    """:func:`y_step` for small data with numpy (same Grams, same per-cell solves)."""
    PASSES.add(md.D)
    D = md.D.astype(np.float64, copy=False)
    M = md.mask().astype(np.float64)
    G = ((X[pa] * X[pb]) @ M).T  # (L, npair): sum_t m_tj x_ta x_tb
    h = D.T @ X.T  # (L, k)
    Yc = np.asarray(Y, dtype=np.float64)
    k = X.shape[0]
    A = np.empty((G.shape[0], k, k))
    A[:, pa, pb] = G
    A[:, pb, pa] = G

    def q(Ym: np.ndarray) -> float:  # sum_j y_j^T G_j y_j - 2 h_j . y_j
        return float(np.einsum("aj,jab,bj->", Ym, A, Ym) - 2.0 * np.einsum("ja,aj->", h, Ym))

    before = q(Yc)
    sol = np.empty((G.shape[0], k))
    flags = chol_solve_numpy(np.ascontiguousarray(G), h, lam, pa, pb, sol)
    out[...] = sol.T
    ssq = float(md.ssq_rows.sum())
    return before + ssq, q(out) + ssq, int(np.count_nonzero(flags == 1))


def x_stats(md: MaskedData, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X-step statistics ``(G (T, npair) packed, h (T, k), c (T,))``: ``sum_j m_tj y_j y_j^T``,
    ``sum_j m_tj d_tj y_j`` and ``sum_j m_tj d_tj^2`` (pairs in ``np.triu_indices`` order)."""
    pa, pb = _pairs(Y.shape[0])
    h, G = row_products(md, Y, Y, pa, pb)
    return G, h, md.ssq_rows.copy()


def filled_matmul(md: MaskedData, mu: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``Z @ V.T (T, p)`` for the mean-filled ``Z = where(M, D, mu[None, :])``, ``V (p, L)``.

    ``Z = D0 + mu - M * mu``, so ``Z V^T = D0 V^T + (V mu)^T - M (mu * V)^T``.
    """
    p = V.shape[0]
    Vm = np.vstack([V, mu[None, :]])
    pa = np.arange(p, dtype=np.int64)
    pb = np.full(p, p, dtype=np.int64)
    H, G = row_products(md, V, Vm, pa, pb)
    return H + (V @ mu)[None, :] - G


def filled_rmatmul(md: MaskedData, mu: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``(Z.T @ U).T (p, L)`` for the mean-filled ``Z``, ``U (T, p)``.

    ``Z^T U = D0^T U + mu (1^T U) - mu * (M^T U)``.
    """
    T, L = md.D.shape
    p = U.shape[1]
    U = np.ascontiguousarray(U, dtype=np.float64)
    mu = np.asarray(mu, dtype=np.float64)
    if is_small(md.D.size):
        PASSES.add(md.D)
        D = md.D.astype(np.float64, copy=False)
        M = md.mask().astype(np.float64)
        return (D.T @ U).T + np.outer(U.sum(axis=0), mu) - (M.T @ U).T * mu[None, :]
    A = np.zeros((T, pad_width(p)))
    A[:, :p] = U
    out = np.empty((p, L))
    PASSES.add(md.D)
    _filled_rmatmul(md.D, md.codes, U, subset_tables(A, md.codes.shape[0]),
                    np.ascontiguousarray(mu, dtype=np.float64), U.sum(axis=0), out)
    return out
