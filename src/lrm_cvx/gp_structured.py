"""The structured ``"gp-variance"`` oracle: exact gains without dense covariances on the grid.

:class:`StructuredGPVarianceOracle` scores the gp-variance criterion (the low-rank trend plus
GP residual model of :mod:`lrm_cvx.information`) at paper scale from the structure of the
prior covariance: whole-grid FFT convolutions set up once (:class:`_GridTerms`, kept for the
next plan of the same model, start and budget by a digest of its inputs) and one whitened row
per pick, each pick's convolution (or lag-table gather) shared by every fork of the set-up
(:class:`_PickCache`). :mod:`lrm_cvx.information` re-exports it and registers the criterion.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._blas import single_threaded_blas
from ._validation import array_digest, as_factor_matrix
from .errors import PlanningError
from .oracles import cells_array
from .spatial.kriging import GridConv, check_gp_inputs, gp_noise, gp_residual_cov, grid_rect

__all__ = ["StructuredGPVarianceOracle", "GP_PICK_CACHE_BYTES", "GP_DIRECT_MAX_CELLS",
           "LAG_TABLE_MAX_ENTRIES", "GRID_TERMS", "kept_residual_cov"]


class StructuredGPVarianceOracle:
    """Exact ``"gp-variance"`` gains without dense covariances (grid metric), for paper scale.

    Same criterion, gains and values as :class:`GPVarianceOracle` (total posterior variance
    ``V(P) = sum_i c_i C_P(i, i)`` of ``f = Y^T x + r`` over the targets; gain of ``x``
    ``N(x) / (C_P(x, x) + noise)``, ``N(x) = sum_i c_i C_P(i, x)^2``), computed from the
    structure of the prior covariance ``K(i, j) = y_i^T S0 y_j + k(|i - j|)``:

    * Sequential conditioning, whitened: ``C_P(i, x) = K(i, x) - F(i)^T F(x)``, ``F(i) in R^m``
      (``m = |P|``), ``F_m(i) = C_{P'}(i, p_m) / sqrt(C_{P'}(p_m, p_m) + noise)``; every row of
      ``F`` splits into a trend part ``E y_i`` and a local GP part ``Fk(i)`` (both bounded by the
      prior std, so nothing blows up for smooth kernels), giving
      ``C_P(i, x) = y_i^T a_x + e(i, x)``, ``a_x = S0 y_x - E^T F(x)``,
      ``e(i, x) = k(i, x) - Fk(i)^T F(x)``.
    * ``N(x) = a_x^T W a_x + 2 a_x^T (u(x) - Hk F(x)) + s(x) - 2 F(x)^T Rk(x)
      + F(x)^T Qk F(x)`` with ``W = sum_i c_i y_i y_i^T`` (all targets, ``k x k``),
      ``u(x) = sum_i c_i y_i k(i, x)``, ``s(x) = sum_i c_i k(i, x)^2`` (``k + 1`` FFT
      convolutions over the grid, once), ``Hk = sum_i c_i y_i Fk(i)^T``,
      ``Rk(x) = sum_i c_i Fk(i) k(i, x)``, ``Qk = sum_i c_i Fk(i) Fk(i)^T``. The trend part is
      formed from ``a_x`` directly, never as a difference of ``O(L)`` sums.
    * Adding pick ``p`` appends one row to ``F``, ``Fk``, ``Rk`` and one column to ``Hk``, ``Qk``,
      all from ``u``, ``Rk(p)`` and ``g(p, x) = sum_i c_i k(p, i) k(i, x)``: one FFT convolution
      per pick over the pool's bounding box plus ``cutoff_distance(truncation)`` (cells left out
      have both kernel factors ``< truncation * sill``: terms below ``truncation^2 sill^2``, the
      only approximation; ``u`` and ``s`` use ``1e-17``).

    Accuracy (tests, bench_gp_planner.py): gains of unobserved cells agree with the dense
    oracle to ~1e-12 relative; the tiny gains of already observed cells (``N / (C + noise)``,
    both ~0) to ~1e-13 of the largest gain, <= 3e-7 for a Gaussian kernel without nugget.
    Cost per pick ``O((m + k) n)`` for ``n`` pool cells plus one FFT of the window; memory
    ``3 m n`` float64 (``F``, ``Fk``, ``Rk``) plus ``O(k n)``. ``metric="km"`` is not supported
    (the kernel is not translation invariant on the lat/lon grid): use :class:`GPVarianceOracle`.
    """

    criterion = "gp-variance"

    def __init__(self, Y: Any, cells: Any = None, *, region: Any = None, spatial_cov: Any = None,
                 prior_cov: Any = None, pool: Any = None, targets: Any = None,
                 target_weights: Any = None, truncation: float = 1e-9,
                 boundary_tol: float = 0.0, **_: Any) -> None:
        self.Y = as_factor_matrix(Y)
        S0 = check_gp_inputs(self.Y, region, spatial_cov, prior_cov)
        if spatial_cov.metric != "grid":
            raise PlanningError("the structured gp-variance oracle needs spatial_cov.metric "
                                "'grid'; use GPVarianceOracle for 'km'")
        truncation = float(truncation)
        if not 0 < truncation < 1:
            raise PlanningError(f"truncation must be in (0, 1), got {truncation}")
        k, L = self.Y.shape
        self.pool = np.arange(L) if pool is None else np.unique(cells_array(pool, L))
        T = np.arange(L) if targets is None else np.unique(cells_array(targets, L))
        c = np.ones(L) if target_weights is None else np.asarray(target_weights, float)
        if c.shape != (L,) or np.any(c < 0) or not np.all(np.isfinite(c)):
            raise PlanningError(f"target_weights must be ({L},), finite and >= 0")
        cT = np.zeros(L)
        cT[T] = c[T]
        init = cells_array(cells, L)
        X = np.union1d(self.pool, init)
        self._X = X
        self.noise = gp_noise(spatial_cov)
        self.cov = spatial_cov
        gi = region.grid_index
        shape = region.shape
        gX = gi[X]
        self._gX = gX
        lo, hi = gX.min(axis=0), gX.max(axis=0)
        out = (int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
        self._oidx = (gX[:, 0] - out[0], gX[:, 1] - out[1])

        key = (array_digest(self.Y, cT, gi, X), shape, spatial_cov.model, spatial_cov.sill,
               spatial_cov.range, spatial_cov.anisotropy, truncation, float(boundary_tol),
               LAG_TABLE_MAX_ENTRIES)
        grid = GRID_TERMS.get(key)
        if grid is None:
            grid = self._grid_terms(cT, region, lo, hi, out, truncation, boundary_tol)
            GRID_TERMS.clear()  # one set-up kept: the latest plan's
            GRID_TERMS[key] = grid
        elif grid.bound is not None:
            self.boundary_bound = grid.bound
        self._grid = grid
        self._k2, self._wg, self._gconv, self._cwin = grid.k2, grid.wg, grid.gconv, grid.cwin
        self._W, self._uX, self._sX = grid.W, grid.uX, grid.sX
        self._YX = np.ascontiguousarray(self.Y[:, X])
        self._S0 = S0
        self._gcache = grid.picks  # g(p, .) of the picks, shared by every fork
        self._direct = False  # a pick's g by FFT (restricted forks: summed, _direct_rows)
        YT = self.Y if targets is None else self.Y[:, T]  # every cell: no gathered copy
        prior_var = np.einsum("ai,ab,bi->i", YT, S0, YT) + spatial_cov.sill
        self._value0 = float(cT[T] @ prior_var)
        self._reset()
        for p in init:
            self._condition(int(p))

    def _reset(self) -> None:
        """The state of no observation: the prior's trend coefficients, variances and value,
        no whitened row."""
        k, n = self._YX.shape
        self._a = self._S0 @ self._YX                # trend coefficients a_x
        self._hF = np.zeros((k, n))                  # Hk F(x)
        self._r = np.zeros(n)                        # F(x)^T Rk(x)
        self._q = np.zeros(n)                        # F(x)^T Qk F(x)
        self.cvar = np.einsum("an,an->n", self._YX, self._a) + self.cov.sill
        self._F = np.empty((0, n))                   # whitened C(P, x)
        self._Fk = np.empty((0, n))                  # its GP part
        self._Rk = np.empty((0, n))                  # sum_i c_i Fk(i) k(i, x)
        self._Qk = np.zeros((0, 0))                  # sum_i c_i Fk(i) Fk(i)^T
        self._Hk = np.zeros((k, 0))                  # sum_i c_i y_i Fk(i)^T
        self._m = 0
        self._value = self._value0
        self.cells: list[int] = []

    @property
    def k(self) -> int:
        return int(self.Y.shape[0])

    @property
    def uses_lag_table(self) -> bool:
        """Whether a pick's ``g(p, x)`` is gathered from the kernel's lag table (cheap) rather
        than convolved by FFT over the pool's window (exact; the cost of each pick)."""
        return self._k2 is not None

    def _grid_terms(self, cT: np.ndarray, region: Any, lo: np.ndarray, hi: np.ndarray,
                    out: tuple[int, int, int, int], truncation: float,
                    boundary_tol: float) -> _GridTerms:
        """The set-up's terms that do not depend on the prior covariance nor on the initial
        cells: ``u``, ``s``, ``W``, the lag table or the per-pick convolution (k + 1 FFT
        convolutions over the grid)."""
        spatial_cov, gi, shape = self.cov, region.grid_index, region.shape
        k, X = self.Y.shape[0], self._X

        def kern(d):
            return spatial_cov.covariance(d, nugget=False)

        cgrid = np.zeros(shape)
        cgrid[gi[:, 0], gi[:, 1]] = cT
        # u(x) and s(x) = sum_i c_i k(i, x)^2 over (almost) the whole grid: terms left out
        # are below 1e-17 sill each
        aniso = spatial_cov.anisotropy
        wb = grid_rect(lo, hi, spatial_cov.reach(1e-17), shape)
        sl = (slice(wb[0], wb[0] + wb[2]), slice(wb[1], wb[1] + wb[3]))
        conv = GridConv(wb, out, kern, aniso)
        uX = np.empty((k, X.size))
        buf = np.zeros(shape)
        for a in range(k):
            buf[gi[:, 0], gi[:, 1]] = cT * self.Y[a]
            uX[a] = conv(buf[sl])[self._oidx]
        del conv
        sX = GridConv(wb, out, lambda d: kern(d) ** 2, aniso)(cgrid[sl])[self._oidx]
        # g(p, x) = sum_i c_i k(p, i) k(i, x): with equal weights on the targets, the lattice
        # autocorrelation K2(x - p) of k minus the targets' complement (bounded below), a table
        # gather per pick; else one convolution per pick over the smaller window
        k2 = self._lag_table(cT, sX, spatial_cov, lo, hi, boundary_tol)
        wg = grid_rect(lo, hi, spatial_cov.reach(truncation), shape)
        return _GridTerms(uX=uX, sX=sX, W=(self.Y * cT) @ self.Y.T, k2=k2, wg=wg,
                          gconv=GridConv(wg, out, kern, aniso),
                          cwin=cgrid[wg[0]:wg[0] + wg[2], wg[1]:wg[1] + wg[3]],
                          bound=getattr(self, "boundary_bound", None),
                          picks=_PickCache(X.size))

    def _lag_table(self, cT: np.ndarray, sX: np.ndarray, cov: Any, lo: np.ndarray,
                   hi: np.ndarray, tol: float) -> tuple | None:
        """``(K2, off_r, off_c, c0)`` when ``g(p, x) = c0 K2(x - p)`` holds to ``tol``, else None.

        With every target weighted ``c0`` (and the rest 0),
        ``g(p, x) = c0 (K2(x - p) - B(p, x))``: ``K2(d) = sum_{i in Z^2} k(i) k(i - d)`` (the
        lattice autocorrelation of the kernel, one FFT over lags up to the pool's extent; the
        lattice is cut where both kernel factors of a left-out term are below ``3e-5 sill``)
        and ``B(p, x) = sum_{i not a target} k(p, i)
        k(i, x) <= sqrt(E(p) E(x))``, ``E(y) = K2(0) - s(y) / c0`` (Cauchy-Schwarz; ``s`` is
        exact). The table is used when ``max_y E(y) <= tol * K2(0)`` over the pool: every ``g``
        is then within ``tol K2(0) c0`` (``tol`` of the largest ``g``) of its exact value, the
        only approximation (``tol = 0``, the class default, switches the table off;
        :func:`make_oracle` passes :data:`GP_BOUNDARY_TOL`). Pools near the region's edge or
        among masked cells keep the exact per-pick convolution."""
        tol = float(tol)
        w = cT[cT > 0]
        if tol <= 0 or w.size == 0 or not np.allclose(w, w[0], rtol=1e-12, atol=0):
            return None
        c0 = float(w[0])
        ext = (hi - lo).astype(np.int64)
        reach = np.array([int(np.ceil(v / 2.0)) + 1 for v in cov.reach(1e-9)])  # k(i) k(i - d)
        R = ext + reach  # lattice half-widths covering the lags and the tail
        if float(2 * R[0] + 1) * float(2 * R[1] + 1) > LAG_TABLE_MAX_ENTRIES:
            # a kernel far longer than the pool (e.g. a degenerate fitted range of thousands of
            # cells): the lattice would not fit in memory, and most of K2(0) would come from
            # outside the region, which the boundary test rejects anyway: exact convolutions
            self.boundary_bound = float("inf")
            return None
        ar = np.arange(-R[0], R[0] + 1, dtype=np.float64)
        ac = np.arange(-R[1], R[1] + 1, dtype=np.float64)
        kgrid = cov.lattice(ar[:, None], ac[None, :])
        import scipy.fft as sfft

        shp = (sfft.next_fast_len(kgrid.shape[0] + ext[0], real=True),
               sfft.next_fast_len(kgrid.shape[1] + ext[1], real=True))
        F = sfft.rfft2(kgrid, s=shp, workers=-1)
        ac_full = sfft.irfft2(F * np.conj(F), s=shp, workers=-1)  # circular autocorrelation
        del F
        # lags -ext..ext (wrapped indices), arranged with lag 0 at (ext0, ext1)
        rr = np.r_[np.arange(shp[0] - ext[0], shp[0]), np.arange(0, ext[0] + 1)]
        cc = np.r_[np.arange(shp[1] - ext[1], shp[1]), np.arange(0, ext[1] + 1)]
        tab = ac_full[np.ix_(rr, cc)]
        del ac_full
        k2_0 = float(tab[ext[0], ext[1]])
        e_max = float(np.max(k2_0 - sX / c0)) if sX.size else 0.0
        self.boundary_bound = e_max / max(k2_0, 1e-300)
        if e_max > tol * k2_0:
            return None
        return np.ascontiguousarray(tab), int(ext[0]), int(ext[1]), c0

    def _kernel_table(self) -> np.ndarray:
        """The kernel at every grid offset within the window ``(2 n_rows - 1, 2 n_cols - 1)``
        (offset 0 at the centre; the pool's box lies inside the window), evaluated on the
        first pick that convolves and kept (every oracle of the same set-up shares it): each
        such pick's
        ``k(p, x)`` over the pool and over the window are then a gather and a slice of it,
        the same numbers as evaluating them, where every pick evaluated the whole window
        before."""
        if self._grid.ktab is None:
            n_rows, n_cols = self._wg[2], self._wg[3]
            self._grid.ktab = self.cov.lattice(
                np.arange(1 - n_rows, n_rows, dtype=np.float64)[:, None],
                np.arange(1 - n_cols, n_cols, dtype=np.float64)[None, :])
        return self._grid.ktab

    def _xpos(self, cells: np.ndarray) -> np.ndarray:
        return np.minimum(np.searchsorted(self._X, cells), self._X.size - 1)

    def _pos(self, candidates: Any) -> np.ndarray:
        if candidates is None:
            return self._xpos(self.pool)
        idx = np.asarray(candidates, dtype=np.int64).ravel()
        ppos = np.minimum(np.searchsorted(self.pool, idx), self.pool.size - 1)
        if idx.size and not np.array_equal(self.pool[ppos], idx):
            raise PlanningError("gp-variance candidates must be cells of the oracle's pool")
        return self._xpos(idx)

    def _grow(self) -> None:
        m = self._m
        if m == self._F.shape[0]:
            cap = max(8, 2 * m)
            for name in ("_F", "_Fk", "_Rk"):
                new = np.empty((cap, self._X.size))
                new[:m] = getattr(self, name)[:m]
                setattr(self, name, new)
            Q = np.zeros((cap, cap))
            Q[:m, :m] = self._Qk[:m, :m]
            self._Qk = Q
            H = np.zeros((self.k, cap))
            H[:, :m] = self._Hk[:, :m]
            self._Hk = H

    def _numerator(self, pos: np.ndarray) -> np.ndarray:
        """``N(x) = sum_i c_i C_P(i, x)^2``, ``C_P(i, x) = y_i^T a_x + e(i, x)``: trend, cross and
        GP parts (the trend part is never formed as a difference of large sums)."""
        a = self._a[:, pos]
        trend = np.einsum("an,an->n", a, self._W @ a)
        cross = 2.0 * np.einsum("an,an->n", a, self._uX[:, pos] - self._hF[:, pos])
        gp = self._sX[pos] - 2.0 * self._r[pos] + self._q[pos]
        return np.maximum(trend + cross + gp, 0.0)

    def _kernel_rows(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(k(p, x), g(p, x))`` over the oracle's cells for the cell ``p`` at position ``j``:
        a gather from the lag table, or a slice of the kernel's table and one convolution
        (kept in the picks' cache)."""
        gxp = self._gX[j]
        if self._k2 is not None:  # translation-invariant table (see _lag_table)
            kp = self.cov.lattice(self._gX[:, 0] - gxp[0], self._gX[:, 1] - gxp[1])
            tab, o0, o1, c0 = self._k2
            g = c0 * tab[self._oidx[0] - self._oidx[0][j] + o0,
                         self._oidx[1] - self._oidx[1][j] + o1]
            return kp, g
        # k(p, .) over the window, a slice of the kernel's table, then one convolution
        wg, ktab = self._wg, self._kernel_table()
        rp, cp = wg[2] - 1 - gxp[0], wg[3] - 1 - gxp[1]  # the table's offset 0 from p
        kp = ktab[self._gX[:, 0] + rp, self._gX[:, 1] + cp]
        g = self._gcache.get(j)
        if g is None and self._direct:  # a route's fork: its cells' rows summed directly
            self._direct_rows()
            g = self._gcache.get(j)
        if g is None:  # a cell no fork of this set-up has conditioned on yet
            g = self._gcache.put(j, self._gconv.product(self._window_of(j),
                                                        self._cwin)[self._oidx])
        return kp, g

    def covariance_blocks(self, rows: np.ndarray, cols: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
        """``(K(rows, cols), G(rows, cols))`` between the oracle's cells at the positions
        ``rows`` and ``cols`` (of its sorted cells): the prior covariance
        ``K(i, j) = y_i^T S0 y_j + k(i, j)`` and ``G(i, j) = sum_t c_t K(t, i) K(t, j)`` over
        the targets, ``G = p_i^T (W p_j + u(j)) + u(i)^T p_j + g(i, j)`` with ``p = S0 y``, from
        the set-up's sums (the lag table, or one convolution per row); ``k`` is gathered from
        the kernel's table. No matrix over all cells is formed: ``O(|rows| |cols|)`` memory."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        pr, pc = self._S0 @ self._YX[:, rows], self._S0 @ self._YX[:, cols]
        oi = self._oidx

        def lags(table: np.ndarray, o0: int, o1: int) -> np.ndarray:
            # table[x - p + (o0, o1)] for every (p, x) of rows x cols, by flat offsets
            w = table.shape[1]
            flat_c = oi[0][cols] * w + oi[1][cols]
            flat_r = oi[0][rows] * w + oi[1][rows] - (o0 * w + o1)
            return np.take(table, flat_c[None, :] - flat_r[:, None])

        K = pr.T @ self._YX[:, cols]
        K += lags(self._kernel_table(), self._wg[2] - 1, self._wg[3] - 1)
        if self._k2 is not None:
            tab, o0, o1, c0 = self._k2
            g = c0 * lags(tab, o0, o1)
        else:
            g = np.empty((rows.size, cols.size))
            for r, j in enumerate(rows):
                g[r] = self._kernel_rows(int(j))[1][cols]
        g += pr.T @ (self._W @ pc + self._uX[:, cols])
        g += self._uX[:, rows].T @ pc
        return K, g

    def g_diagonal(self, cols: np.ndarray) -> np.ndarray:
        """``G(i, i) = sum_t c_t K(t, i)^2`` of the oracle's cells at the positions ``cols``
        (the prior gain numerator of each cell)."""
        p = self._S0 @ self._YX[:, cols]
        return (np.einsum("an,an->n", p, self._W @ p + 2.0 * self._uX[:, cols])
                + self._sX[cols])

    def _condition(self, p: int) -> None:
        """Condition on an observation at ``p`` (a cell of ``X``): one whitened row."""
        j = int(self._xpos(np.array([p]))[0])
        self._grow()
        m = self._m
        F, Fk, Rk, Qk, Hk = (self._F[:m], self._Fk[:m], self._Rk[:m], self._Qk[:m, :m],
                             self._Hk[:, :m])
        den = self.cvar[j] + self.noise
        d = np.sqrt(den)
        self._value -= float(self._numerator(np.array([j]))[0]) / den
        ell = F[:, j].copy()
        ap = self._a[:, j].copy()
        kp, g = self._kernel_rows(j)
        fk = (kp - ell @ Fk) / d                                  # GP part of the new row
        phi = (ap @ self._YX) / d + fk                            # C_P(p, x) / d
        Rkp = Rk[:, j].copy()
        Ql = Qk @ ell
        gam = (Rkp - Ql) / d
        delta = (g[j] - 2.0 * ell @ Rkp + ell @ Ql) / den
        rk = (g - ell @ Rk) / d
        hcol = (self._uX[:, j] - Hk @ ell) / d
        self._q += phi * (2.0 * (gam @ F) + delta * phi)
        self._r += phi * rk
        self._hF += np.outer(hcol, phi)
        self._a -= np.outer(ap / d, phi)
        self.cvar -= phi * phi
        self._F[m] = phi
        self._Fk[m] = fk
        self._Rk[m] = rk
        self._Qk[:m, m] = gam
        self._Qk[m, :m] = gam
        self._Qk[m, m] = delta
        self._Hk[:, m] = hcol
        self._m = m + 1
        self.cells.append(int(p))

    def _window_of(self, j: int, rows: slice = slice(None)) -> np.ndarray:
        """``k(x_j, i)`` for the cells ``i`` of the window (its ``rows``, default all): a
        slice of the kernel's table."""
        wg, ktab = self._wg, self._kernel_table()
        r0 = wg[0] + wg[2] - 1 - int(self._gX[j, 0])  # the window's first row from x_j
        c0 = wg[1] + wg[3] - 1 - int(self._gX[j, 1])
        lo, hi, _ = rows.indices(wg[2])
        return ktab[r0 + lo:r0 + hi, c0:c0 + wg[3]]

    def _direct_rows(self) -> None:
        """``g(p, x) = sum_i c_i k(p, i) k(i, x)`` for every cell ``p`` of this oracle's cells
        not in its pick cache and every ``x`` of them, summed over the window directly (the
        kernel at each cell a slice of the kernel's table, the sums one matrix product per
        band of window rows): a restricted fork over a few cells
        (:data:`GP_DIRECT_MAX_CELLS`) gets every row it lacks for the cost of a few of the
        window's FFTs. The same sums as :meth:`GridConv.product`'s, in another order (rounding
        apart); into the pick cache, so each row is summed once."""
        n = self._X.size
        missing = np.array([j for j in range(n) if self._gcache.get(j) is None], dtype=np.int64)
        if missing.size == 0:
            return
        wg = self._wg
        root_c = np.sqrt(self._cwin)  # g = (k sqrt(c)) (k sqrt(c))^T: one symmetric product
        band = max(1, min(wg[2], int(_DIRECT_BAND_BYTES // (8 * n * wg[3]))))
        G = np.zeros((n, n))
        B = np.empty((n, band * wg[3]))
        # (few x long) @ (long x few): OpenBLAS's threads only contend (~10x slower loaded)
        with single_threaded_blas():
            for lo in range(0, wg[2], band):  # bands of window rows
                rows = slice(lo, min(lo + band, wg[2]))
                Bh = B[:, :(rows.stop - lo) * wg[3]]
                for x in range(n):  # k(x, i) sqrt(c_i) over the band: a slice of the table
                    np.multiply(self._window_of(x, rows), root_c[rows],
                                out=Bh[x].reshape(rows.stop - lo, wg[3]))
                G += Bh @ Bh.T
        for j in missing.tolist():
            self._gcache.put(j, G[j])

    def gains(self, candidates: Any = None) -> np.ndarray:
        """Total-variance decrease of each candidate (``(n,)``, default: the whole pool)."""
        pos = self._pos(candidates)
        num = self._numerator(pos)
        return num / np.maximum(self.cvar[pos] + self.noise, 1e-300)

    def add(self, cell: int) -> None:
        """Condition on an observation at ``cell`` (a pool or initial cell), ``O((m + k) n)``
        + one FFT."""
        if not self.covers([int(cell)]):
            self._pos([int(cell)])  # the error naming the pool
        self._condition(int(cell))

    _STATE = ("_F", "_Fk", "_Rk", "_Qk", "_Hk", "_q", "_r", "_hF", "_a", "cvar")
    """The arrays :meth:`_condition` changes (whitened rows and their sums)."""

    def fork(self) -> StructuredGPVarianceOracle:
        """A copy that conditions on its own (the set's whitened rows copied, the whole-grid
        terms shared): rival sets scored from one set-up (planning/lines.py)."""
        new = copy.copy(self)
        for name in self._STATE:
            setattr(new, name, getattr(self, name).copy())
        new.cells = list(self.cells)
        return new

    def fresh(self) -> StructuredGPVarianceOracle:
        """A fork conditioned on nothing (the prior): the whole-grid terms and the picks'
        convolutions shared, so rival sets of cells of this oracle's pool and initial cells
        (:meth:`covers`) are scored without a new set-up (planning/lines.py)."""
        new = copy.copy(self)
        new._reset()
        return new

    def restricted(self, cells: Any) -> StructuredGPVarianceOracle:
        """A fork with no observation whose pool is ``cells`` (cells :meth:`covers`): the
        set-up's terms gathered there, so conditioning costs ``O((m + k) |cells|)`` plus a
        pick's convolution, gathered from this set-up's when it has it. Its values are a fork's
        to rounding; the convolutions over ``cells`` are kept with the set-up, so the same
        rival routes on the next plan are not convolved again."""
        cells = np.unique(np.asarray(cells, dtype=np.int64))
        pos = self._xpos(cells)
        new = copy.copy(self)
        new.pool = new._X = cells
        new._gX = self._gX[pos]
        new._oidx = (self._oidx[0][pos], self._oidx[1][pos])
        new._uX, new._sX = self._uX[:, pos], self._sX[pos]
        new._YX = np.ascontiguousarray(self._YX[:, pos])
        subsets = self._grid.subsets
        key = array_digest(cells)
        cache = subsets.pop(key, None)  # the most recently used last
        if cache is None:
            cache = _PickCache(cells.size, parent=(self._grid.picks, pos))
            if len(subsets) >= 32:
                subsets.pop(next(iter(subsets)))
        subsets[key] = new._gcache = cache
        new._direct = cells.size <= GP_DIRECT_MAX_CELLS
        new._reset()
        return new

    def covers(self, cells: Any) -> bool:
        """Whether every cell of ``cells`` is one the oracle holds (its pool and initial
        cells), so :meth:`add` conditions on it."""
        cells = np.asarray(cells, dtype=np.int64).ravel()
        return bool(np.all(self._X[self._xpos(cells)] == cells)) if cells.size else True

    @property
    def value(self) -> float:
        """Total posterior variance over the targets for the current set."""
        return self._value


GP_PICK_CACHE_BYTES: float = 2.0 ** 28
"""Most bytes (256 MiB) a structured gp-variance oracle and its forks keep of the picks'
convolutions ``g(p, .)`` (:class:`_PickCache`); picks beyond it are convolved again when
another fork conditions on them."""


@dataclass
class _GridTerms:
    """What a structured oracle's set-up computes from the grid (:meth:`StructuredGPVariance
    Oracle._grid_terms`), shared by every oracle of the same set-up: ``u``, ``s`` and ``W``,
    the lag table ``k2`` (or None), the per-pick convolution ``gconv`` over the window ``wg``
    with the target weights ``cwin`` there, the lag table's ``bound``, the picks'
    convolutions ``picks``, the kernel's table ``ktab`` (evaluated on the first pick that
    convolves) and the convolutions over the cells of the oracles' ``restricted`` forks
    (``subsets``, by a digest of the cells)."""

    uX: np.ndarray
    sX: np.ndarray
    W: np.ndarray
    k2: tuple | None
    wg: tuple[int, int, int, int]
    gconv: GridConv
    cwin: np.ndarray
    bound: float | None
    picks: _PickCache
    ktab: np.ndarray | None = None
    subsets: dict[str, _PickCache] = field(default_factory=dict)


GRID_TERMS: dict[tuple, _GridTerms | np.ndarray] = {}
"""The latest gp-variance set-up's terms that depend on the model and the cells only, by a
digest of its inputs and by its covariance: a structured oracle's grid terms, or a dense
oracle's residual covariance block (:func:`kept_residual_cov`). The plans of a campaign's
days (the same model, start and budget; only the forecast's prior covariance changes) set up
once and share the picks' convolutions, the same numbers as computing them again."""


def kept_residual_cov(region: Any, spatial_cov: Any, rows: np.ndarray, cols: np.ndarray
                      ) -> np.ndarray:
    """:func:`~lrm_cvx.spatial.kriging.gp_residual_cov` of ``rows`` x ``cols``, kept in
    :data:`GRID_TERMS` (by a digest of the cells' coordinates and by the covariance) for the
    next set-up on the same cells: the dense gp-variance oracle's prior block without its
    trend part, which does not depend on the day's belief. Read-only: copy it to update it.

    Parameters
    ----------
    region : Region
        The grid of the cells.
    spatial_cov : ResidualCovariance
        The GP residual's covariance.
    rows, cols : numpy.ndarray
        Cell indices of the block's rows and columns.

    Returns
    -------
    numpy.ndarray
        ``(|rows|, |cols|)`` float64, read-only (the same array on a repeated call).
    """
    a = spatial_cov.points(region, rows)
    b = spatial_cov.points(region, cols)
    key = ("residual", array_digest(a, b), spatial_cov.model, spatial_cov.sill, spatial_cov.range,
           spatial_cov.anisotropy, spatial_cov.metric)
    block = GRID_TERMS.get(key)
    if block is None:
        block = gp_residual_cov(region, spatial_cov, rows, cols)
        block.flags.writeable = False
        GRID_TERMS.clear()  # one set-up kept: the latest plan's
        GRID_TERMS[key] = block
    return block



class _PickCache:
    """The convolutions ``g(p, x)`` over the pool of the cells a structured oracle has
    conditioned on, by position ``p`` in the oracle's cells, shared by its forks: a cell the
    greedy, a rival greedy or a rival route conditions on is convolved once (the same numbers
    as convolving it again). Holds at most :data:`GP_PICK_CACHE_BYTES`."""

    def __init__(self, n: int, parent: tuple[_PickCache, np.ndarray] | None = None) -> None:
        self._rows: dict[int, np.ndarray] = {}
        self._max = int(GP_PICK_CACHE_BYTES // max(8 * n, 1))
        self._parent = parent  # (the set-up's cache, these cells' positions in its cells)

    def get(self, j: int) -> np.ndarray | None:
        g = self._rows.get(j)
        if g is None and self._parent is not None:
            cache, pos = self._parent
            full = cache._rows.get(int(pos[j]))
            if full is not None:
                g = self.put(j, full[pos])
        return g

    def put(self, j: int, g: np.ndarray) -> np.ndarray:
        if len(self._rows) < self._max:
            self._rows[j] = g
        return g


GP_DIRECT_MAX_CELLS: int = 256
"""Most cells of a structured oracle's :meth:`~StructuredGPVarianceOracle.restricted` fork (a
rival route) whose picks' ``g`` over those cells are summed directly over the window (one pass
for all the rows it lacks) rather than convolved by one FFT over the window per pick."""

_DIRECT_BAND_BYTES = 2.0 ** 25
"""Bytes of the kernel's values held at once by a direct sum (:meth:`StructuredGPVariance
Oracle._direct_rows`): one band of window rows for every cell."""

LAG_TABLE_MAX_ENTRIES: float = 2.0 ** 26
"""Largest kernel lattice (entries, ~0.5 GB of float64) the structured oracle's lag table builds;
a longer kernel keeps the exact per-pick convolutions (``_lag_table``)."""
