"""The scalable form of the static placement's ``"risk"`` / ``"gp-variance"`` greedy and exchange:
no ``L x L`` covariance, exact on the grid metric.

The dense reference (``planning/static.py``, ``_State``) keeps the posterior covariance ``C``
(``L x L``). Here the prior covariance ``C0 = Y^T S0 Y + K`` (low-rank trend plus the stationary
GP residual ``K(i, j) = sill rho(|i - j|)``, grid units) is never formed. With ``S`` the sensors,
``G = C0[:, S]``, ``A = C0[S, S] + N_S`` and ``M2 = C0 W C0`` (``W = diag(w)``, the error
weights), the posterior is ``C = C0 - G A^-1 G^T`` and every quantity the gains need is kept only
at the **candidate** cells ``X`` (``p`` of them):

* ``cd = diag C``, ``cc = diag(C W C)`` (``p``), the training errors ``Z`` and ``P = Z W C``
  (``T x p``; the risk only), ``G[X]`` and ``M2[X, S]`` (``p x n``), ``A^-1`` and ``M2[S, S]``.
* Adding ``x`` is the dense code's rank-one step with ``a = C[X, x] = C0[X, x] - G h``
  (``h = A^-1 G[x]``) and ``q = (C W C)[X, x] = M2[X, x] - M2[X, S] h - G A^-1 (M2[S, x] -
  M2[S, S] h)``; removing a sensor (exchange) the exact un-conditioning
  ``C + v v^T / M_jj`` (``v = G m``, ``m = A^-1 e_j``) with ``(C W v)[X] = M2[X, S] m -
  G A^-1 M2[S, S] m``. ``O((n + T) p)`` per step.
* The sums over **all** cells are FFT convolutions on the grid (``scipy.fft``, linear; the
  kernel cut where it is below ``1e-16`` of the sill, i.e. exact in float64):
  ``U = Y W K`` (``k`` convolutions), ``s(x) = sum_i w_i k(i, x)^2`` (one), ``R W K``
  (``T``, the risk only), once; and per new sensor ``x`` the column
  ``(K W K)[X, x] = sum_i w_i k(., i) k(i, x)`` by one FFT over a window of radius ``2c``
  around ``x`` (``c`` where the kernel falls below ``1e-12`` of the sill; the kernel column
  ``k(X, x)`` is taken from the same window). Columns are cached. The rank-2 updates of ``Z``
  and ``P`` are in-place BLAS calls (memory-bound: they set the pace at paper scale).

So the picks equal the dense reference's (tests compare them on tiny grids, where the windows
cover the grid); memory is ``O((n + T) p + (T + k) L)``. Candidate cells default to every allowed
cell; above ``max_candidates`` they are thinned to a regular sub-lattice (every cell still
counts in the objective; the sensors stand on the lattice). The ``metric="km"`` residual is not
translation invariant on the lat/lon grid: it keeps the dense form.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

MAX_CANDIDATES: int = 200_000
"""Candidate cells of the scalable form; larger allowed sets are thinned to a sub-lattice."""

_CUT_SUM = 1e-16  # kernel cut of the once-only full-grid sums (relative to the sill)
_CUT_PICK = 1e-12  # kernel cut of the per-sensor window
_FFT_CELLS = 1 << 21  # padded grid cells per batched FFT of the once-only sums (~64 MB of
# temporaries; one grid at a time at paper scale)


def _kernel_table(cov: Any, radius: tuple[int, int]) -> np.ndarray:
    """The kernel (no nugget) on the lattice offsets ``-radius..radius`` (per axis)."""
    o_r = np.arange(-radius[0], radius[0] + 1, dtype=np.float64)
    o_c = np.arange(-radius[1], radius[1] + 1, dtype=np.float64)
    return cov.lattice(o_r[:, None], o_c[None, :])


def _radius(cov: Any, rel: float, shape: tuple[int, int]) -> tuple[int, int]:
    """Lattice radii ``(rows, columns)`` beyond which ``k < rel * sill``, capped at the grid's
    extent."""
    cap = max(shape)
    return tuple(int(min(np.ceil(c), cap)) if np.isfinite(c) else cap
                 for c in cov.reach(rel))


class FactoredState:
    """Posterior state of the static greedy at the candidate cells (see the module docstring).

    ``Y (k, L)``, ``S0 (k, k)``, ``cov`` a grid-metric ResidualCovariance or None (no
    residual), ``noise (L,)``, ``w (L,)``, ``R (T, L)`` the prior errors (None: the total
    posterior variance), ``pool (p,)`` sorted candidate cells, ``region`` for the grid."""

    def __init__(self, Y: np.ndarray, S0: np.ndarray, cov: Any, noise: np.ndarray,
                 w: np.ndarray, R: np.ndarray | None, pool: np.ndarray, region: Any) -> None:
        self.Y, self.S0 = Y, 0.5 * (S0 + S0.T)
        self.k, self.L = Y.shape
        self.pool = np.asarray(pool, dtype=np.int64)
        p = self.pool.size
        self.noise = np.asarray(noise, np.float64)[self.pool]
        self.w = w
        gi = region.grid_index
        self.shape = tuple(region.shape)
        self.gX = gi[self.pool]
        self.posgrid = np.full(self.shape, -1, dtype=np.int64)
        self.posgrid[self.gX[:, 0], self.gX[:, 1]] = np.arange(p)
        self.YX = np.ascontiguousarray(Y[:, self.pool])
        self.SY = self.S0 @ self.YX  # S0 y_x (k, p)
        Wk = (Y * w) @ Y.T
        self.cov = cov if cov is not None and float(cov.sill) > 0 else None
        if self.cov is not None:
            import scipy.fft as sfft

            r = _radius(self.cov, _CUT_SUM, self.shape)
            ktab = _kernel_table(self.cov, r)
            ny, nx = self.shape
            shp = (sfft.next_fast_len(ny + 2 * r[0], real=True),
                   sfft.next_fast_len(nx + 2 * r[1], real=True))
            KF = sfft.rfft2(ktab, s=shp)
            grid = np.zeros(self.shape)

            def full_sum(vals: np.ndarray, F: np.ndarray = KF) -> np.ndarray:
                """``sum_i vals_i k(i, x)`` at the candidates (linear convolution, exact)."""
                grid[gi[:, 0], gi[:, 1]] = vals
                out = sfft.irfft2(sfft.rfft2(grid, s=shp, workers=-1) * F, s=shp, workers=-1)
                return out[r[0] + self.gX[:, 0], r[1] + self.gX[:, 1]]

            def full_sums(rows: np.ndarray, out: np.ndarray) -> None:
                """``out (m, p) +=`` the ``full_sum`` of each row of ``rows (m, L)``, one
                batched FFT per block of rows (the same transforms: bit for bit)."""
                for a in range(0, rows.shape[0], batch):
                    block = rows[a:a + batch]
                    grids = np.zeros((block.shape[0], *self.shape))
                    grids[:, gi[:, 0], gi[:, 1]] = block
                    conv = sfft.irfft2(sfft.rfft2(grids, s=shp, axes=(-2, -1), workers=-1) * KF,
                                       s=shp, axes=(-2, -1), workers=-1)
                    out[a:a + batch] += conv[:, r[0] + self.gX[:, 0], r[1] + self.gX[:, 1]]

            batch = max(1, _FFT_CELLS // (shp[0] * shp[1]))
            self.U = np.zeros((self.k, p))
            full_sums(w * Y, self.U)
            s = full_sum(w, sfft.rfft2(ktab ** 2, s=shp))
            self.sill = float(self.cov.sill)
            rp = _radius(self.cov, _CUT_PICK, self.shape)
            self._rp = rp
            self._ktab_p = _kernel_table(self.cov, rp)
            self._pshape = tuple(sfft.next_fast_len(4 * v + 1, real=True) for v in rp)
            self._pF = sfft.rfft2(self._ktab_p, s=self._pshape)
            pad = ((2 * rp[0],) * 2, (2 * rp[1],) * 2)
            self._wpad = np.pad(self._wgrid(region, w), pad)
            self._pospad = np.pad(self.posgrid, pad, constant_values=-1)
        else:
            self.U = np.zeros((self.k, p))
            s = np.zeros(p)
            self.sill = 0.0
        self.SWS = self.S0 @ Wk @ self.S0
        self.cd = np.einsum("ap,ap->p", self.YX, self.SY) + self.sill
        self.cc = (np.einsum("ap,ap->p", self.YX, self.SWS @ self.YX)
                   + 2.0 * np.einsum("ap,ap->p", self.SY, self.U) + s)
        self.R = R
        if R is not None:
            RW = R * w
            RWC0 = ((RW @ Y.T) @ self.S0) @ self.YX
            if self.cov is not None:
                full_sums(RW, RWC0)
            self.RX = np.ascontiguousarray(R[:, self.pool])
            self.RWC0 = RWC0
            self.Z = self.RX.copy()
            self.P = RWC0.copy()
            self.value = float(np.einsum("tl,tl,l->", R, R, w))
        else:
            self.Z = self.P = None
            self.value = float(w @ (np.einsum("al,ab,bl->l", Y, self.S0, Y) + self.sill))
        self.cells: list[int] = []
        self._spos: list[int] = []
        self._Gt = np.zeros((0, p))  # C0[S, X] (rows: sensors in state order; capacity grows)
        self._Mt = np.zeros((0, p))  # M2[S, X]
        self.Ainv = np.zeros((0, 0))
        self.A2 = np.zeros((0, 0))
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._cc0, self._value0 = self.cc.copy(), self.value

    @staticmethod
    def _wgrid(region: Any, w: np.ndarray) -> np.ndarray:
        g = np.zeros(tuple(region.shape))
        gi = region.grid_index
        g[gi[:, 0], gi[:, 1]] = w
        return g

    # ------------------------------------------------------------------ prior columns
    def reserve(self, n: int) -> None:
        """Room for ``n`` sensors in the factors (no regrowth while adding them)."""
        m = len(self._spos)
        if n > self._Gt.shape[0]:
            for name in ("_Gt", "_Mt"):
                new = np.zeros((n, self.pool.size))
                new[:m] = getattr(self, name)[:m]
                setattr(self, name, new)

    def _columns(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(C0[X, x], M2[X, x])`` of the candidate at position ``j`` (cached)."""
        hit = self._cache.get(j)
        if hit is not None:
            return hit
        sy = self.SY[:, j]
        c0 = self.YX.T @ sy
        m2 = self.YX.T @ (self.SWS @ self.YX[:, j] + self.S0 @ self.U[:, j]) + self.U.T @ sy
        if self.cov is not None:
            gx = self.gX[j]
            pr, pc = self._rp
            r0, c0i = int(gx[0]) + 2 * pr, int(gx[1]) + 2 * pc  # x in the padded grids
            # the kernel column k(X, x): cells beyond the window have k < 1e-12 sill
            pos = self._pospad[r0 - pr:r0 + pr + 1, c0i - pc:c0i + pc + 1]
            ok = pos >= 0
            c0[pos[ok]] += self._ktab_p[ok]
            win = self._wpad[r0 - pr:r0 + pr + 1, c0i - pc:c0i + pc + 1] * self._ktab_p
            import scipy.fft as sfft

            # the full convolution: offsets -2rp..2rp around x (per axis)
            g = sfft.irfft2(sfft.rfft2(win, s=self._pshape) * self._pF,
                            s=self._pshape)[:4 * pr + 1, :4 * pc + 1]
            pos = self._pospad[r0 - 2 * pr:r0 + 2 * pr + 1, c0i - 2 * pc:c0i + 2 * pc + 1]
            ok = pos >= 0
            m2[pos[ok]] += g[ok]
        self._cache[j] = (c0, m2)
        return c0, m2

    # ------------------------------------------------------------------ objective
    def gains(self) -> np.ndarray:
        """``(p,)`` exact decrease of the objective from adding each candidate."""
        d = self.cd + self.noise
        if self.Z is None:
            return self.cc / d
        cross = np.einsum("tp,tp->p", self.Z, self.P)
        zz = np.einsum("tp,tp->p", self.Z, self.Z)
        return 2.0 * cross / d - zz * self.cc / d ** 2

    def _rank_one(self, alpha: float, a: np.ndarray, q: np.ndarray, aw: float,
                  b: np.ndarray | None, zwa: np.ndarray | None) -> None:
        """``C += alpha a a^T`` (``Z += alpha b a^T``), ``P``, ``cc``, ``cd`` kept exact."""
        self.cc += 2.0 * alpha * a * q + alpha ** 2 * aw * a * a
        self.cd += alpha * a * a
        if self.Z is not None:
            # P += alpha (zwa a^T + b q^T) + alpha^2 aw b a^T and Z += alpha b a^T, in place
            U = np.column_stack([alpha * zwa + alpha ** 2 * aw * b, alpha * b])
            _add_product(self.P, U, np.vstack([a, q]))
            _add_product(self.Z, (alpha * b)[:, None], a[None, :])
            self.value += 2.0 * alpha * float(b @ zwa) + alpha ** 2 * aw * float(b @ b)
        else:
            self.value += alpha * aw

    def add(self, j: int) -> None:
        """Condition on a sensor at candidate position ``j``."""
        c0, m2 = self._columns(j)
        n = len(self._spos)
        Gt, Mt = self._Gt[:n], self._Mt[:n]
        gS = Gt[:, j]
        h = self.Ainv @ gS
        a = c0 - Gt.T @ h
        dd = float(a[j] + self.noise[j])
        q = m2 - Mt.T @ h - Gt.T @ (self.Ainv @ (Mt[:, j] - self.A2 @ h))
        aw = float(self.cc[j])
        b = None if self.Z is None else self.Z[:, j].copy()
        zwa = None if self.Z is None else self.P[:, j].copy()
        self._rank_one(-1.0 / dd, a, q, aw, b, zwa)
        # the factors of A^-1 = (C0[S, S] + N)^-1 (block inverse, Schur complement dd)
        Ai = np.empty((n + 1, n + 1))
        Ai[:n, :n] = self.Ainv + np.outer(h, h) / dd
        Ai[:n, n] = Ai[n, :n] = -h / dd
        Ai[n, n] = 1.0 / dd
        self.Ainv = Ai
        m2S = m2[self._spos] if n else np.zeros(0)
        A2 = np.empty((n + 1, n + 1))
        A2[:n, :n] = self.A2
        A2[:n, n] = A2[n, :n] = m2S
        A2[n, n] = m2[j]
        self.A2 = A2
        if n == self._Gt.shape[0]:
            self.reserve(max(8, 2 * n))
        self._Gt[n] = c0
        self._Mt[n] = m2
        self._spos.append(int(j))
        self.cells.append(int(self.pool[j]))

    def remove(self, j: int) -> None:
        """Forget the sensor at candidate position ``j`` (exact un-conditioning)."""
        jj = self._spos.index(int(j))
        n = len(self._spos)
        Gt, Mt = self._Gt[:n], self._Mt[:n]
        m = self.Ainv[:, jj].copy()
        Mjj = float(m[jj])
        v = Gt.T @ m
        A2m = self.A2 @ m
        q = Mt.T @ m - Gt.T @ (self.Ainv @ A2m)
        aw = float(m @ A2m)
        if self.Z is not None:
            S = np.asarray(self._spos)
            RS = self.RX[:, S]
            b = RS @ m
            zwa = self.RWC0[:, S] @ m - RS @ (self.Ainv @ A2m)
        else:
            b = zwa = None
        self._rank_one(1.0 / Mjj, v, q, aw, b, zwa)
        # the last sensor takes slot jj (O(p), no shift of the factors)
        perm = np.arange(n - 1)
        if jj < n - 1:
            perm[jj] = n - 1
            self._Gt[jj] = self._Gt[n - 1]
            self._Mt[jj] = self._Mt[n - 1]
            self._spos[jj] = self._spos[n - 1]
            self.cells[jj] = self.cells[n - 1]
        self.Ainv = self.Ainv[np.ix_(perm, perm)] - np.outer(m[perm], m[perm]) / Mjj
        self.A2 = self.A2[np.ix_(perm, perm)]
        self._spos.pop()
        self.cells.pop()

    def rebuild(self, positions: list[int]) -> None:
        """The state of the sensors at ``positions`` from the prior (no drift)."""
        self.cd = np.einsum("ap,ap->p", self.YX, self.SY) + self.sill
        self.cc = self._cc0.copy()
        if self.R is not None:
            self.Z = self.RX.copy()
            self.P = self.RWC0.copy()
        self.value = self._value0
        self.cells, self._spos = [], []
        self.Ainv, self.A2 = np.zeros((0, 0)), np.zeros((0, 0))
        for j in positions:
            self.add(int(j))


def _add_product(C: np.ndarray, U: np.ndarray, V: np.ndarray) -> None:
    """``C += U @ V`` in place (``C (T, p)`` C-contiguous; BLAS dgemm on ``C^T``, no ``T x p``
    temporary)."""
    from scipy.linalg.blas import dgemm

    out = dgemm(1.0, V.T, U.T, beta=1.0, c=C.T, overwrite_c=1)
    if not np.shares_memory(out, C):  # not updated in place (never for C-contiguous C)
        C[...] = out.T


def greedy(state: FactoredState, n: int, hist: dict[str, list]) -> None:
    """Add the candidate of largest gain (ties: the lowest cell) until ``n`` sensors."""
    state.reserve(n)
    active = np.ones(state.pool.size, dtype=bool)
    active[state._spos] = False
    while len(state.cells) < n:
        g = np.where(active, state.gains(), -np.inf)
        j = int(np.argmax(g))
        if not np.isfinite(g[j]):
            break
        state.add(j)
        active[j] = False
        for key, v in (("cell", int(state.pool[j])), ("gain", g[j]), ("cost_increase", 1.0),
                       ("ratio", g[j]), ("cost", float(len(state.cells))),
                       ("n_evaluated", int(active.sum()) + 1), ("objective", state.value)):
            hist[key].append(v)


def exchange(state: FactoredState, sweeps: int, rel_tol: float) -> dict[str, Any]:
    """The dense exchange (``static._exchange``) on the factored state: each sensor in turn is
    removed and replaced by the best candidate if that beats putting it back by more than
    ``rel_tol`` of the objective; sweeps until none changes; the state is rebuilt per sweep."""
    t0 = time.perf_counter()
    start = list(state._spos)
    order = list(start)
    state.rebuild(order)
    before = state.value
    moves: dict[str, list] = {"exchange_out": [], "exchange_in": [], "exchange_gain": []}
    done, n_sweeps = False, 0
    for n_sweeps in range(1, sweeps + 1):
        if n_sweeps > 1:
            state.rebuild(order)
        changed = False
        for i in range(len(order)):
            s = order[i]
            state.remove(s)
            g = state.gains()
            g[state._spos] = -np.inf
            x = int(np.argmax(g))
            tol = rel_tol * max(abs(state.value), 1e-300)
            if x != s and g[x] > g[s] + tol:
                state.add(x)
                moves["exchange_out"].append(int(state.pool[s]))
                moves["exchange_in"].append(int(state.pool[x]))
                moves["exchange_gain"].append(float(g[x] - g[s]))
                order[i] = x
                changed = True
            else:
                state.add(s)
        if not changed:
            done = True
            break
    return finish_exchange(state, order, start, before, moves, n_sweeps, done, t0)


def finish_exchange(state: Any, final: Any, start: Any, before: float, moves: dict[str, list],
                    n_sweeps: int, done: bool, t0: float) -> dict[str, Any]:
    """The exchange's report (both forms, dense and scalable): ``state`` rebuilt on the
    ``final`` sensors, or back on ``start`` when rounding made the swaps worse (never worse)."""
    state.rebuild(final)
    after = state.value
    if after > before:  # every swap lowered it by > tol: only rounding; keep the start then
        state.rebuild(start)
        after = before
        moves = {key: [] for key in moves}
    return dict(method="exchange", objective_before=before, objective_after=after,
                swaps=len(moves["exchange_out"]), sweeps=n_sweeps, converged=done,
                seconds=time.perf_counter() - t0, moves=moves)


def candidate_pool(region: Any, allowed: np.ndarray, max_candidates: int) -> np.ndarray:
    """``allowed`` (sorted cells), thinned to the sub-lattice of stride ``s`` (both axes, the
    smallest ``s`` leaving at most ``max_candidates`` cells) when it has more."""
    if allowed.size <= max_candidates:
        return allowed
    gi = region.grid_index[allowed]
    s = int(np.ceil(np.sqrt(allowed.size / max_candidates)))
    while True:
        keep = allowed[(gi[:, 0] % s == 0) & (gi[:, 1] % s == 0)]
        if keep.size <= max_candidates:
            return keep
        s += 1
