"""Information of a set of cells under a fitted low rank model, and incremental gain oracles.

The paper measures a set of cells ``P`` by its Fisher information
``I(P) = log det(ridge * I + sum_{p in P} y_p y_p^T)`` with ``y_p`` the column of the model's
``Y`` (``k x L``) for cell ``p``. The greedy planner needs, at every step, the gain of adding each
candidate cell; the oracles here return every candidate's gain at once in ``O(n k^2)`` compiled
work and take a rank-one (Sherman-Morrison) update when a cell is added. Everything stays in
float64: float32 inverses change the greedy's picks.

Two criteria share one interface (:class:`FisherOracle`, :class:`AOptimalOracle`):

* ``"fisher"`` (D-optimal, the paper's): gain ``log(1 + y_x^T M^-1 y_x)`` (matrix determinant
  lemma), which equals ``I(P + x) - I(P)``.
* ``"a-optimal"``: the reduction of the total prediction variance
  ``V(P) = sum_i y_i^T M^-1 y_i`` over all cells ``i`` when ``x`` is added,
  ``(y_x^T S W S y_x) / (1 + y_x^T S y_x)`` with ``S = M^-1`` and ``W = Y Y^T``.
  It needs ``ridge > 0`` (``V`` is infinite for a singular ``M``).

Posterior versions (docs/reconstruction.md): both oracles accept a prior precision
``P0`` (``(k, k)``, replacing ``ridge I``) and per-cell noise variances ``noise_var`` (weights
``w_p = 1 / sigma_p^2``): ``M = P0 + sum_P w_p y_p y_p^T`` is then the posterior precision of the
fold-in, and the A-optimal target ``W = sum_i c_i y_i y_i^T`` may weight cells
(``target_weights``, e.g. the squared per-cell scale). Internally the candidates' columns are
``sqrt(w) y`` so the gain formulas are unchanged. :class:`GPVarianceOracle` (``"gp-variance"``)
is the A-optimal criterion of the low-rank trend + GP residual model.
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import scipy.sparse as sps
from scipy.linalg.blas import dger

from ._validation import as_factor_matrix
from .errors import PlanningError
from .oracles import (  # noqa: F401  (the Fisher and A-optimal oracles: re-exported)
    AOptimalOracle,
    FisherOracle,
    RowOracle,
    a_optimal_value,
    cells_array,
    check_pool_rows,
    fisher_information,
    row_factors,
    row_information,
)
from .registry import Registry
from .spatial.kriging import (  # noqa: F401  (GridConv and the GP helpers: the old location)
    GridConv,
    check_gp_inputs,
    gp_latent_cov,
    gp_noise,
    grid_rect,
)

__all__ = [
    "fisher_information",
    "a_optimal_value",
    "FisherOracle",
    "AOptimalOracle",
    "make_oracle",
    "GPVarianceOracle",
    "gp_variance_value",
    "StructuredGPVarianceOracle",
    "TrendGPVarianceOracle",
    "gp_residual_share",
    "GP_RESIDUAL_TOL",
    "GP_BOUNDARY_TOL",
    "GP_STRUCTURED_MIN_ENTRIES",
    "CRITERIA",
    "CRITERION_REGISTRY",
    "CriterionSpec",
    "fisher_set_value",
    "gp_noise",
    "gp_latent_cov",
    "check_gp_inputs",
    "GridConv",
    "RowOracle",
    "RowGPVarianceOracle",
    "make_row_oracle",
    "row_cov",
    "row_information",
    "row_factors",
]

Criterion = Literal["fisher", "a-optimal", "gp-variance"]
CRITERION_REGISTRY = Registry("criterion", PlanningError)
"""Every planning criterion (entries: :class:`CriterionSpec`), registered at the end of the
module; ``CRITERIA`` is its ``choices()``."""


def make_oracle(
    criterion: str, Y: Any, ridge: float = 0.0, cells: Any = None, **kwargs: Any
) -> FisherOracle | AOptimalOracle | GPVarianceOracle | StructuredGPVarianceOracle:
    """The gain oracle for ``criterion`` (a name or alias of :data:`CRITERION_REGISTRY`:
    ``"fisher"``, ``"a-optimal"`` (alias ``"aopt"``) or ``"gp-variance"``) started at ``cells``;
    ``kwargs`` go to the oracle (``prior_precision``, ``noise_var``, ...).

    ``"gp-variance"``: the dense :class:`GPVarianceOracle` up to
    :data:`GP_STRUCTURED_MIN_ENTRIES` covariances, :class:`StructuredGPVarianceOracle` (same
    gains, no dense matrices) above it when the metric is ``"grid"``; ``gp_method="dense"`` or
    ``"structured"`` forces one."""
    return CRITERION_REGISTRY.get(criterion).oracle(Y, ridge, cells, **kwargs)


# --------------------------------------------------------------------------- GP variance
def gp_variance_value(Y: Any, region: Any, spatial_cov: Any, prior_cov: Any, cells: Any,
                      targets: Any = None, target_weights: Any = None) -> float:
    """Total posterior variance ``sum_{i in targets} c_i Var(f_i | d_cells)`` of the latent
    field ``f = Y^T x + r``, ``x ~ N(., prior_cov)``, ``r ~ GP(spatial_cov)``, observed with
    noise :func:`gp_noise` at ``cells``. Dense reference (``O(|targets| n)`` memory)."""
    Y = as_factor_matrix(Y)
    S0 = check_gp_inputs(Y, region, spatial_cov, prior_cov)
    L = Y.shape[1]
    T = np.arange(L) if targets is None else np.asarray(targets, dtype=np.int64)
    c = np.ones(T.size) if target_weights is None else np.asarray(target_weights, float)[T]
    P = cells_array(cells, L)
    prior = np.einsum("ai,ab,bi->i", Y[:, T], S0, Y[:, T]) + spatial_cov.sill
    if P.size == 0:
        return float(c @ prior)
    KPP = gp_latent_cov(Y, S0, region, spatial_cov, P, P) + gp_noise(spatial_cov) * np.eye(P.size)
    KTP = gp_latent_cov(Y, S0, region, spatial_cov, T, P)
    red = np.einsum("ip,ip->i", KTP, np.linalg.solve(KPP, KTP.T).T)
    return float(c @ (prior - red))


class GPVarianceOracle:
    """A-optimal gains of the low-rank trend + GP residual model (``"gp-variance"``).

    The predictive model of ``GLRM(spatial=...)`` with ``complete(prior="empirical",
    spatial=True)`` is a Gaussian process ``f = Y^T x + r`` (``x ~ N(m0, prior_cov)``,
    ``r ~ GP(spatial_cov)``). The gain of observing ``x`` is the decrease of the total posterior
    variance over the targets, ``sum_i c_i C(i, x)^2 / (C(x, x) + nugget)`` with ``C`` the
    current posterior covariance. ``C(rows, pool)`` is held densely (rows = targets plus pool)
    and updated by a rank-one step per added cell, so gains and updates are
    ``O(|rows| |pool|)``: exact for regions up to ~10^4 cells; pass ``targets`` (a subsample of
    cells whose variance is summed) to bound the cost on larger regions.
    """

    criterion = "gp-variance"

    def __init__(self, Y: Any, cells: Any = None, *, region: Any = None, spatial_cov: Any = None,
                 prior_cov: Any = None, pool: Any = None, targets: Any = None,
                 target_weights: Any = None, max_entries: float = 1e8, **_: Any) -> None:
        self.Y = as_factor_matrix(Y)
        S0 = check_gp_inputs(self.Y, region, spatial_cov, prior_cov)
        L = self.Y.shape[1]
        self.pool = (np.arange(L) if pool is None
                     else np.unique(cells_array(pool, L)))
        T = np.arange(L) if targets is None else np.unique(cells_array(targets, L))
        rows = np.union1d(T, self.pool)
        if rows.size * self.pool.size > max_entries:
            raise PlanningError(
                f"the gp-variance criterion would hold {rows.size} x {self.pool.size} posterior "
                f"covariances (> {max_entries:.0e}): pass targets= (a subsample of cells) or "
                "use criterion='a-optimal'")
        c = np.ones(L) if target_weights is None else np.asarray(target_weights, float)
        self._tpos = np.searchsorted(rows, T)
        self._tw = c[T]
        self._pool_in_rows = np.searchsorted(rows, self.pool)
        self.noise = gp_noise(spatial_cov)
        self.cells: list[int] = [int(v) for v in cells_array(cells, L)]
        C = gp_latent_cov(self.Y, S0, region, spatial_cov, rows, self.pool)
        prior_var = np.einsum("ai,ab,bi->i", self.Y[:, T], S0, self.Y[:, T]) + spatial_cov.sill
        self._value = float(self._tw @ prior_var)
        if self.cells:
            P = np.asarray(self.cells, dtype=np.int64)
            KPP = gp_latent_cov(self.Y, S0, region, spatial_cov, P, P)
            KPP += self.noise * np.eye(P.size)
            Lp = np.linalg.cholesky(KPP)
            from scipy.linalg import solve_triangular

            A = solve_triangular(Lp, gp_latent_cov(self.Y, S0, region, spatial_cov, P, rows),
                                 lower=True)
            C -= A.T @ A[:, self._pool_in_rows]
            self._value -= float(self._tw @ np.einsum("pi,pi->i", A[:, self._tpos],
                                                      A[:, self._tpos]))
        self.C = C

    @property
    def k(self) -> int:
        return int(self.Y.shape[0])

    def _pos(self, candidates: Any) -> np.ndarray:
        if candidates is None:
            return np.arange(self.pool.size)
        idx = np.asarray(candidates, dtype=np.int64).ravel()
        pos = np.searchsorted(self.pool, idx)
        pos = np.minimum(pos, self.pool.size - 1)
        if idx.size and not np.array_equal(self.pool[pos], idx):
            raise PlanningError("gp-variance candidates must be cells of the oracle's pool")
        return pos

    def gains(self, candidates: Any = None) -> np.ndarray:
        """Total-variance decrease of each candidate (``(n,)``, default: the whole pool)."""
        pos = self._pos(candidates)
        # views where the candidates are the whole pool or the targets all rows: no copy of C
        whole = pos.size == self.pool.size and np.array_equal(pos, np.arange(pos.size))
        Ct = self.C if whole else self.C[:, pos]
        if self._tpos.size != self.C.shape[0]:
            Ct = Ct[self._tpos]
        num = np.einsum("t,tp,tp->p", self._tw, Ct, Ct)
        den = self.C[self._pool_in_rows[pos], pos] + self._noise_at(pos)
        return num / np.maximum(den, 1e-300)

    def _noise_at(self, pos: Any) -> Any:
        """Noise variance of the candidates at pool positions ``pos`` (the nugget; per row for
        :class:`RowGPVarianceOracle`)."""
        return self.noise if np.ndim(self.noise) == 0 else self.noise[pos]

    def add(self, cell: int) -> None:
        """Condition on an observation at ``cell`` (a pool cell; its row's, for the row
        oracle): rank-one update."""
        j = int(self._pos([int(cell)])[0])
        col = self.C[:, j].copy()
        den = col[self._pool_in_rows[j]] + self._noise_at(j)
        self._value -= float(self._tw @ (col[self._tpos] ** 2)) / den
        # C -= col col[pool]^T / den in place (BLAS rank-one update on the Fortran view: no
        # (rows, pool) temporary); a copy only if C is not C-contiguous float64
        self.C = dger(-1.0 / den, col[self._pool_in_rows], col, a=self.C.T, overwrite_a=1).T
        self.cells.append(int(cell))

    @property
    def value(self) -> float:
        """Total posterior variance over the targets for the current set."""
        return self._value


# --------------------------------------------------------------------------- averaged rows
def row_cov(Y: np.ndarray, S0: np.ndarray, region: Any, spatial_cov: Any, B1: Any, B2: Any
            ) -> np.ndarray:
    """``B1 K B2^T`` (dense ``(m1, m2)``): the prior covariance of the noise-free averaged
    observations ``B1 f`` and ``B2 f`` of the latent field (``K`` of :func:`gp_latent_cov`,
    computed on the cells the rows touch only)."""
    B1, B2 = sps.csc_matrix(B1), sps.csc_matrix(B2)
    U1 = np.flatnonzero(np.diff(B1.indptr))
    U2 = np.flatnonzero(np.diff(B2.indptr))
    if U1.size == 0 or U2.size == 0:
        return np.zeros((B1.shape[0], B2.shape[0]))
    K = gp_latent_cov(Y, S0, region, spatial_cov, U1, U2)
    return np.asarray((B2[:, U2] @ (B1[:, U1] @ K).T).T)


class RowGPVarianceOracle(GPVarianceOracle):
    """``"gp-variance"`` when a candidate's observation is an averaged row (a footprint).

    Candidate ``pool[i]`` observes ``z_i = rows[i] @ f + e_i``, ``Var(e_i) = nugget
    sum_j rows[i, j]^2`` (``errors="independent"``; ``"shared"``: ``nugget (sum_j rows[i,
    j])^2``); ``extra_rows`` are observations already
    made (a towed sensor's legs), ``cells`` pool cells already observed. ``C`` holds the
    posterior covariances of the targets' values and of the pool's noise-free observations
    with the pool's observations (``(|targets| + |pool|, |pool|)``, dense), prior ``B1 K B2^T``
    (:func:`row_cov`); gains ``sum_t c_t C(t, x)^2 / (C(x, x) + Var(e_x))`` and rank-one updates
    as :class:`GPVarianceOracle`, whose values it equals for one-hot rows."""

    def __init__(self, Y: Any, cells: Any = None, *, region: Any = None, spatial_cov: Any = None,
                 prior_cov: Any = None, pool: Any = None, rows: Any = None,
                 extra_rows: Any = None, targets: Any = None, target_weights: Any = None,
                 errors: str = "independent", max_entries: float = 1e8, **_: Any) -> None:
        self.Y = as_factor_matrix(Y)
        S0 = check_gp_inputs(self.Y, region, spatial_cov, prior_cov)
        L = self.Y.shape[1]
        self.pool, A = check_pool_rows(pool, rows, L)
        T = np.arange(L) if targets is None else np.unique(cells_array(targets, L))
        n_rows = T.size + self.pool.size
        if n_rows * self.pool.size > max_entries:
            raise PlanningError(
                f"the gp-variance criterion would hold {n_rows} x {self.pool.size} posterior "
                f"covariances (> {max_entries:.0e}): pass targets= (a subsample of cells) or "
                "use criterion='a-optimal'")
        c = np.ones(L) if target_weights is None else np.asarray(target_weights, float)
        self._tpos = np.arange(T.size)
        self._tw = c[T]
        self._pool_in_rows = T.size + np.arange(self.pool.size)
        nug = gp_noise(spatial_cov)
        self.noise = row_factors(self.Y, A, nug, errors)[1]
        R = sps.vstack([sps.csr_matrix((np.ones(T.size), (np.arange(T.size), T)),
                                       shape=(T.size, L)), A]).tocsr()
        C = row_cov(self.Y, S0, region, spatial_cov, R, A)
        prior_var = np.einsum("ai,ab,bi->i", self.Y[:, T], S0, self.Y[:, T]) + spatial_cov.sill
        self._value = float(self._tw @ prior_var)
        self.cells: list[int] = [int(v) for v in cells_array(cells, L)]
        parts = [A[self._pos(self.cells)]] if self.cells else []
        if extra_rows is not None:
            parts.append(sps.csr_matrix(extra_rows, dtype=np.float64))
        B0 = sps.vstack(parts).tocsr() if parts else None
        if B0 is not None and B0.shape[0]:
            K00 = row_cov(self.Y, S0, region, spatial_cov, B0, B0)
            K00[np.diag_indices_from(K00)] += row_factors(self.Y, B0, nug, errors)[1]
            from scipy.linalg import solve_triangular

            Lc = np.linalg.cholesky(0.5 * (K00 + K00.T))
            W = solve_triangular(Lc, row_cov(self.Y, S0, region, spatial_cov, B0, R),
                                 lower=True)
            C -= W.T @ W[:, self._pool_in_rows]
            self._value -= float(self._tw @ np.einsum("pi,pi->i", W[:, self._tpos],
                                                      W[:, self._tpos]))
        self.C = C


def make_row_oracle(criterion: str, Y: Any, ridge: float = 0.0, cells: Any = None, *,
                    pool: Any, rows: Any, extra_rows: Any = None, **kwargs: Any
                    ) -> RowOracle | RowGPVarianceOracle:
    """The gain oracle of ``criterion`` when each candidate ``pool[i]`` observes the averaged
    row ``rows[i]`` (``(|pool|, L)``, a sensor's footprints; see
    :mod:`lrm_cvx.planning.sensors`), with observations ``extra_rows`` (``(m, L)``) and pool
    ``cells`` already made. ``kwargs``: the criterion's terms as for :func:`make_oracle`
    (``prior_precision``, ``noise_var``, ``target_weights``; for ``"gp-variance"``
    ``region``, ``spatial_cov``, ``prior_cov``, ``targets``: the dense oracle)."""
    criterion = CRITERION_REGISTRY.canonical(criterion, "criterion")
    if criterion == "gp-variance":
        if kwargs.pop("gp_method", "auto") not in ("auto", "dense"):
            raise PlanningError("a sensor footprint needs the dense gp-variance oracle "
                                "(gp_method='auto' or 'dense')")
        return RowGPVarianceOracle(Y, cells, pool=pool, rows=rows, extra_rows=extra_rows,
                                   **kwargs)
    allowed = {"prior_precision", "noise_var", "target_weights", "pool_factors", "errors"}
    return RowOracle(criterion, Y, ridge, cells, pool=pool, rows=rows, extra_rows=extra_rows,
                     **{k: v for k, v in kwargs.items() if k in allowed})


# --------------------------------------------------------------------------- GP variance, scalable
GP_STRUCTURED_MIN_ENTRIES: float = 2e7
"""``make_oracle("gp-variance")`` switches from the dense :class:`GPVarianceOracle` to
:class:`StructuredGPVarianceOracle` when the dense one would hold more than this many
covariances (``|targets + pool| x |pool|``) and the covariance's metric is ``"grid"``."""


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

        key = (_digest(self.Y, cT, gi, X), shape, spatial_cov.model, spatial_cov.sill,
               spatial_cov.range, spatial_cov.anisotropy, truncation, float(boundary_tol),
               LAG_TABLE_MAX_ENTRIES)
        grid = _GRID_TERMS.get(key)
        if grid is None:
            grid = self._grid_terms(cT, region, lo, hi, out, truncation, boundary_tol)
            _GRID_TERMS.clear()  # one set-up kept: the latest plan's
            _GRID_TERMS[key] = grid
        elif grid.bound is not None:
            self.boundary_bound = grid.bound
        self._grid = grid
        self._k2, self._wg, self._gconv, self._cwin = grid.k2, grid.wg, grid.gconv, grid.cwin
        self._W, self._uX, self._sX = grid.W, grid.uX, grid.sX
        self._YX = np.ascontiguousarray(self.Y[:, X])
        self._S0 = S0
        self._gcache = grid.picks  # g(p, .) of the picks, shared by every fork
        prior_var = np.einsum("ai,ab,bi->i", self.Y[:, T], S0, self.Y[:, T]) + spatial_cov.sill
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

    def _condition(self, p: int) -> None:
        """Condition on an observation at ``p`` (a cell of ``X``): one whitened row."""
        j = int(self._xpos(np.array([p]))[0])
        self._grow()
        m = self._m
        F, Fk, Rk, Qk, Hk = (self._F[:m], self._Fk[:m], self._Rk[:m], self._Qk[:m, :m],
                             self._Hk[:, :m])
        gxp = self._gX[j]
        den = self.cvar[j] + self.noise
        d = np.sqrt(den)
        self._value -= float(self._numerator(np.array([j]))[0]) / den
        ell = F[:, j].copy()
        ap = self._a[:, j].copy()
        if self._k2 is not None:  # translation-invariant table (see _lag_table)
            kp = self.cov.lattice(self._gX[:, 0] - gxp[0], self._gX[:, 1] - gxp[1])
            tab, o0, o1, c0 = self._k2
            g = c0 * tab[self._oidx[0] - self._oidx[0][j] + o0,
                         self._oidx[1] - self._oidx[1][j] + o1]
        else:  # k(p, .) over the window, a slice of the kernel's table, then one convolution
            wg, ktab = self._wg, self._kernel_table()
            rp, cp = wg[2] - 1 - gxp[0], wg[3] - 1 - gxp[1]  # the table's offset 0 from p
            kp = ktab[self._gX[:, 0] + rp, self._gX[:, 1] + cp]
            g = self._gcache.get(j)
            if g is None:  # a cell no fork of this set-up has conditioned on yet
                win = ktab[wg[0] + rp:wg[0] + rp + wg[2], wg[1] + cp:wg[1] + cp + wg[3]]
                g = self._gcache.put(j, self._gconv.product(win, self._cwin)[self._oidx])
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
        key = _digest(cells)
        cache = subsets.pop(key, None)  # the most recently used last
        if cache is None:
            cache = _PickCache(cells.size, parent=(self._grid.picks, pos))
            if len(subsets) >= 32:
                subsets.pop(next(iter(subsets)))
        subsets[key] = new._gcache = cache
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


_GRID_TERMS: dict[tuple, _GridTerms] = {}
"""The latest structured set-up's grid terms, by a digest of its factors, target weights,
grid and cells and by its covariance: the plans of a campaign's days (the same model, start
and budget; only the forecast's prior covariance changes) set up once and share the picks'
convolutions, the same numbers as computing them again."""


def _digest(*arrays: np.ndarray) -> str:
    """A digest of the arrays' bytes, shapes and dtypes."""
    h = hashlib.blake2b(digest_size=20)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


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


GP_BOUNDARY_TOL: float = 1e-3
"""The structured oracle of :func:`make_oracle` takes ``g(p, x)`` from the kernel's lattice
autocorrelation (no per-pick FFT) when the targets' complement changes no ``g`` by more than
this fraction of the largest (``StructuredGPVarianceOracle._lag_table``)."""

LAG_TABLE_MAX_ENTRIES: float = 2.0 ** 26
"""Largest kernel lattice (entries, ~0.5 GB of float64) the structured oracle's lag table builds;
a longer kernel keeps the exact per-pick convolutions (``_lag_table``)."""

GP_RESIDUAL_TOL: float = 1e-6
"""``make_oracle("gp-variance")`` (``gp_method="auto"``, structured size, grid metric) plans with
:class:`TrendGPVarianceOracle` when the spatial residual changes no prior gain of the pool by
more than this fraction (:func:`gp_residual_share`)."""


def _residual_terms(Yk: np.ndarray, region: Any, spatial_cov: Any, P: np.ndarray,
                    cT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u (k, |P|), s (|P|))``: ``u(x) = sum_i c_i y_i k(i, x)``, ``s(x) = sum_i c_i
    k(i, x)^2`` at the cells ``P`` by ``k + 1`` FFT convolutions over the grid (terms below
    ``1e-17`` sill left out)."""
    k = Yk.shape[0]
    if spatial_cov.sill <= 0:
        return np.zeros((k, P.size)), np.zeros(P.size)
    gi = region.grid_index
    shape = region.shape
    gP = gi[P]
    lo, hi = gP.min(axis=0), gP.max(axis=0)
    out = (int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    oidx = (gP[:, 0] - out[0], gP[:, 1] - out[1])
    wb = grid_rect(lo, hi, spatial_cov.reach(1e-17), shape)
    sl = (slice(wb[0], wb[0] + wb[2]), slice(wb[1], wb[1] + wb[3]))

    def kern(d):
        return spatial_cov.covariance(d, nugget=False)

    conv = GridConv(wb, out, kern, spatial_cov.anisotropy)
    buf = np.zeros(shape)
    u = np.empty((k, P.size))
    for j in range(k):
        buf[gi[:, 0], gi[:, 1]] = cT * Yk[j]
        u[j] = conv(buf[sl])[oidx]
    buf[gi[:, 0], gi[:, 1]] = cT
    sx = GridConv(wb, out, lambda d: kern(d) ** 2, spatial_cov.anisotropy)(buf[sl])[oidx]
    return u, sx


def _share(S: np.ndarray, YP: np.ndarray, W: np.ndarray, u: np.ndarray, sx: np.ndarray
           ) -> float:
    a = S @ YP
    trend = np.einsum("an,an->n", a, W @ a)
    extra = 2.0 * np.einsum("an,an->n", a, u) + sx
    return float(np.max(np.abs(extra) / np.maximum(trend + extra, 1e-300))) if sx.size else 0.0


def _targets_weights(L: int, targets: Any, target_weights: Any) -> np.ndarray:
    T = np.arange(L) if targets is None else np.unique(cells_array(targets, L))
    c = np.ones(L) if target_weights is None else np.asarray(target_weights, float)
    cT = np.zeros(L)
    cT[T] = c[T]
    return cT


def gp_residual_share(Y: Any, region: Any, spatial_cov: Any, prior_cov: Any, pool: Any,
                      targets: Any = None, target_weights: Any = None) -> float:
    """Largest relative change, over the ``pool`` cells, of the prior ``"gp-variance"`` gain
    numerator ``N(x) = sum_i c_i K(i, x)^2`` that the *correlation* of the spatial residual
    makes: ``N(x) = T(x) + 2 a_x^T u(x) + s(x)`` with the trend part
    ``T(x) = a_x^T W a_x`` (``a_x = S0 y_x``, ``W = sum_i c_i y_i y_i^T``), ``u(x) = sum_i c_i
    y_i k(i, x)`` and ``s(x) = sum_i c_i k(i, x)^2`` (``k`` the residual covariance without its
    nugget; ``k + 1`` FFT convolutions over the grid, exact up to rounding and terms below
    ``1e-17`` sill). Returns ``max_x |2 a_x^T u(x) + s(x)| / N(x)``: the prior gains of the
    exact criterion and of :class:`TrendGPVarianceOracle` (the residual as independent noise,
    same denominators) differ by at most this fraction. Grid metric only."""
    Yk = as_factor_matrix(Y)
    S0 = check_gp_inputs(Yk, region, spatial_cov, prior_cov)
    if spatial_cov.metric != "grid":
        raise PlanningError("gp_residual_share needs spatial_cov.metric 'grid'")
    L = Yk.shape[1]
    P = np.unique(cells_array(pool, L)) if pool is not None else np.arange(L)
    cT = _targets_weights(L, targets, target_weights)
    u, sx = _residual_terms(Yk, region, spatial_cov, P, cT)
    return _share(S0, Yk[:, P], (Yk * cT) @ Yk.T, u, sx)


class TrendGPVarianceOracle(AOptimalOracle):
    """``"gp-variance"`` with the spatial residual as independent noise (planning surrogate).

    The residual ``r`` keeps its variance (``sill``) but loses its correlation: the observation
    noise is ``sill + nugget``, so the gain of ``x`` is ``a_x^T W a_x / (y_x^T S y_x + sill +
    nugget)`` (``S`` the latent posterior covariance, ``a_x = S y_x``, ``W = sum_i c_i y_i
    y_i^T``): the A-optimal oracle, ``O(k^2)`` per candidate, no grid convolution. Its gain
    numerators leave out exactly the residual's terms ``2 a_x^T u(x) + s(x)`` of the exact
    criterion (same denominators): :func:`make_oracle` uses it only when their share
    (:func:`gp_residual_share`) is at most :data:`GP_RESIDUAL_TOL`; :meth:`residual_share`
    re-measures it after the picks (with the prior ``s(x)``). ``value``: the total
    posterior variance of ``f`` over the targets under this surrogate (``trace(S W) + sill
    sum_i c_i``)."""

    criterion = "gp-variance"

    def __init__(self, Y: Any, cells: Any = None, *, region: Any = None, spatial_cov: Any = None,
                 prior_cov: Any = None, pool: Any = None, targets: Any = None,
                 target_weights: Any = None, share_terms: Any = None, **_: Any) -> None:
        Yk = as_factor_matrix(Y)
        S0 = check_gp_inputs(Yk, region, spatial_cov, prior_cov)
        L = Yk.shape[1]
        cT = _targets_weights(L, targets, target_weights)
        P0 = np.linalg.inv(S0)
        noise = gp_noise(spatial_cov) + float(spatial_cov.sill)
        super().__init__(Yk, 0.0, cells, prior_precision=0.5 * (P0 + P0.T), noise_var=noise,
                         target_weights=cT)
        self.pool = np.arange(L) if pool is None else np.unique(cells_array(pool, L))
        self._resid = float(spatial_cov.sill) * float(cT.sum())
        self._share_terms = share_terms  # (u, s) at the pool cells, when already computed
        if share_terms is None and spatial_cov.metric == "grid":
            self._share_terms = _residual_terms(Yk, region, spatial_cov, self.pool, cT)
        self.prior_residual_share = self.residual_share()

    def residual_share(self) -> float:
        """:func:`gp_residual_share` at the current latent covariance (after the picks so far):
        the largest relative change of a pool cell's gain numerator the residual's
        correlation would make now (NaN for the ``"km"`` metric)."""
        if self._share_terms is None:
            return float("nan")
        u, sx = self._share_terms
        return _share(self.S, self.Y[:, self.pool], self.W, u, sx)

    @property
    def value(self) -> float:
        """Total posterior variance over the targets (surrogate: residual variance kept)."""
        return float(np.sum(self.S * self.W)) + self._resid


def _gp_oracle(Y: Any, cells: Any, gp_method: str = "auto", **kwargs: Any
               ) -> GPVarianceOracle | StructuredGPVarianceOracle | TrendGPVarianceOracle:
    """Dense, structured or trend gp-variance oracle (see :func:`make_oracle`)."""
    if gp_method not in ("auto", "dense", "structured", "trend"):
        raise PlanningError("gp_method must be 'auto', 'dense', 'structured' or 'trend', got "
                            f"{gp_method!r}")
    if gp_method == "auto":
        Yk = as_factor_matrix(Y)
        L = Yk.shape[1]
        pool, targets = kwargs.get("pool"), kwargs.get("targets")
        n_pool = L if pool is None else np.unique(cells_array(pool, L)).size
        if pool is None or targets is None:  # every cell is a row (no 2M-cell union1d)
            n_rows = L
        else:
            T = np.unique(cells_array(targets, L))
            n_rows = np.union1d(T, np.asarray(pool, dtype=np.int64)).size
        metric = getattr(kwargs.get("spatial_cov"), "metric", "grid")
        big = float(n_rows) * float(n_pool) > GP_STRUCTURED_MIN_ENTRIES
        gp_method = "structured" if big and metric == "grid" else "dense"
        if gp_method == "structured":
            kwargs.setdefault("boundary_tol", GP_BOUNDARY_TOL)
            st = StructuredGPVarianceOracle(Y, cells=cells, **kwargs)
            pos = st._xpos(st.pool)  # the residual's share of the prior gains, from its terms
            S0 = check_gp_inputs(st.Y, kwargs.get("region"), kwargs.get("spatial_cov"),
                                  kwargs.get("prior_cov"))
            terms = (st._uX[:, pos], st._sX[pos])
            if _share(S0, st.Y[:, st.pool], st._W, *terms) > GP_RESIDUAL_TOL:
                return st
            del st
            return TrendGPVarianceOracle(Y, cells=cells, share_terms=terms, **kwargs)
    if gp_method == "trend":
        return TrendGPVarianceOracle(Y, cells=cells, **kwargs)
    if gp_method == "structured":
        kwargs.setdefault("boundary_tol", GP_BOUNDARY_TOL)
        return StructuredGPVarianceOracle(Y, cells=cells, **kwargs)
    return GPVarianceOracle(Y, cells=cells, **kwargs)


# --------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class CriterionSpec:
    """A registered planning criterion.

    ``oracle(Y, ridge, cells, **kwargs)`` -> gain oracle (``gains``, ``add``, ``value``);
    ``value(Y, cells, ridge, **kwargs)`` -> the criterion's value of a set, from scratch;
    ``maximize``: a gain is ``value(P + x) - value(P)`` (True) or ``value(P) - value(P + x)``;
    ``certified``: :meth:`Plan.certify` bounds this criterion (``plan_bound``: Fisher only).
    """

    oracle: Callable[..., Any]
    value: Callable[..., float]
    maximize: bool
    certified: bool


def _posterior_matrix(Y: Any, cells: Any, ridge: float, prior_precision: Any,
                      noise_var: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(Y (k, L), M (k, k))`` with ``M = P0 + sum_P y_p y_p^T / noise_var_p`` from scratch
    (``P0 = ridge I`` without a prior precision)."""
    Yk = as_factor_matrix(Y)
    nv = np.broadcast_to(np.asarray(1.0 if noise_var is None else noise_var, float),
                         (Yk.shape[1],))
    Yw = Yk / np.sqrt(nv)
    P = cells_array(cells, Yk.shape[1])
    P0 = (ridge * np.eye(Yk.shape[0]) if prior_precision is None
          else np.asarray(prior_precision, float))
    return Yk, P0 + Yw[:, P] @ Yw[:, P].T


def fisher_set_value(Y: Any, cells: Any, ridge: float = 0.0, *, prior_precision: Any = None,
                      noise_var: Any = None, **_: Any) -> float:
    """``log det M(cells)`` from scratch: :func:`fisher_information` of ``cells`` (``(n,)``
    cell indices of ``Y`` ``(k, L)``), or with a prior precision ``(k, k)`` / per-cell noise
    variance the log det of the posterior precision (``-inf`` when it is not positive)."""
    if prior_precision is None and noise_var is None:
        return fisher_information(Y, cells, ridge)
    _, M = _posterior_matrix(Y, cells, ridge, prior_precision, noise_var)
    sign, logdet = np.linalg.slogdet(M)
    return float(logdet) if sign > 0 else -np.inf


def _aopt_set_value(Y: Any, cells: Any, ridge: float = 0.0, *, prior_precision: Any = None,
                    noise_var: Any = None, target_weights: Any = None, weight: Any = None,
                    **_: Any) -> float:
    """``trace(M(cells)^-1 W)`` from scratch."""
    if prior_precision is None and noise_var is None and target_weights is None \
            and weight is None:
        return a_optimal_value(Y, cells, ridge)
    Yk, M = _posterior_matrix(Y, cells, ridge, prior_precision, noise_var)
    if weight is not None:
        W = np.asarray(weight, float)
    elif target_weights is not None:
        W = (Yk * np.asarray(target_weights, float)) @ Yk.T
    else:
        W = Yk @ Yk.T
    return float(np.trace(np.linalg.solve(M, W)))


def _gp_set_value(Y: Any, cells: Any, ridge: float = 0.0, *, region: Any = None,
                  spatial_cov: Any = None, prior_cov: Any = None, targets: Any = None,
                  target_weights: Any = None, **_: Any) -> float:
    return gp_variance_value(Y, region, spatial_cov, prior_cov, cells, targets, target_weights)


CRITERION_REGISTRY.register(
    "fisher",
    CriterionSpec(oracle=FisherOracle, value=fisher_set_value, maximize=True, certified=True),
    description="D-optimal, the paper's: log det of the information matrix "
                "`ridge I + sum y y^T` (or the fold-in's posterior precision)",
)
CRITERION_REGISTRY.register(
    "a-optimal",
    CriterionSpec(oracle=AOptimalOracle, value=_aopt_set_value, maximize=False,
                  certified=False),
    description="decrease of the total prediction variance `sum_i y_i^T M^-1 y_i` "
                "(needs `ridge > 0` or a prior)",
    aliases=("aopt", "a_optimal"),
)
CRITERION_REGISTRY.register(
    "gp-variance",
    CriterionSpec(oracle=lambda Y, ridge=0.0, cells=None, **kw: _gp_oracle(Y, cells, **kw),
                  value=_gp_set_value, maximize=False, certified=False),
    description="decrease of the total posterior variance of the low-rank trend + GP "
                "residual model (needs `spatial_cov`, `prior_cov`)",
)
CRITERIA: tuple[str, ...] = CRITERION_REGISTRY.choices()
"""Canonical criterion names (``in`` accepts aliases); the registry's ``choices()``."""
