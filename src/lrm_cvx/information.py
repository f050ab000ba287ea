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

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.sparse as sps
from scipy.linalg.blas import dger

from ._validation import as_factor_matrix
from .errors import PlanningError
from .gp_structured import (  # noqa: F401  (the structured oracle and its set-up: re-exported)
    GP_PICK_CACHE_BYTES,
    LAG_TABLE_MAX_ENTRIES,
    StructuredGPVarianceOracle,
    kept_residual_cov,
)
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
    gp_residual_cov,
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
        # K(rows, pool) = residual + trend: the residual block depends on the cells only and is
        # kept for the next set-up on them (a campaign's days); the trend is the day's prior
        if float(rows.size) * float(self.pool.size) <= GP_STRUCTURED_MIN_ENTRIES:
            C = kept_residual_cov(region, spatial_cov, rows, self.pool).copy()
        else:
            C = gp_residual_cov(region, spatial_cov, rows, self.pool)
        C += self.Y[:, rows].T @ S0 @ self.Y[:, self.pool]
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


GP_BOUNDARY_TOL: float = 1e-3
"""The structured oracle of :func:`make_oracle` takes ``g(p, x)`` from the kernel's lattice
autocorrelation (no per-pick FFT) when the targets' complement changes no ``g`` by more than
this fraction of the largest (``StructuredGPVarianceOracle._lag_table``)."""

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
