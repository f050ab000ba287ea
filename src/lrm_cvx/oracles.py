"""The gain oracles of the paper's criteria: Fisher (D-optimal) and A-optimal.

Every candidate's gain at once in ``O(n k^2)`` compiled work, a rank-one (Sherman-Morrison)
update when a cell is added, everything in float64 (the formulas are in :mod:`lrm_cvx.information`,
which holds the criteria's registry, the GP-variance oracles and re-exports these names).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sps

from ._validation import as_factor_matrix, check_positive
from .belief.averaged import row_noise
from .errors import DataError, PlanningError

__all__ = ["fisher_information", "a_optimal_value", "FisherOracle", "AOptimalOracle",
           "cells_array", "row_factors", "whitened_rows", "row_information", "RowOracle",
           "check_pool_rows"]


def _gram(Y: np.ndarray, cells: np.ndarray, ridge: float) -> np.ndarray:
    """``ridge * I + Y[:, cells] Y[:, cells]^T`` as a ``(k, k)`` float64 matrix."""
    Yp = Y[:, cells]
    return ridge * np.eye(Y.shape[0]) + Yp @ Yp.T


def cells_array(cells: Any, n_cols: int) -> np.ndarray:
    arr = np.asarray(cells if cells is not None else [], dtype=np.int64).ravel()
    if arr.size and (arr.min() < 0 or arr.max() >= n_cols):
        raise PlanningError(f"cells must be column indices in [0, {n_cols}), got {arr}")
    return arr


def fisher_information(Y: Any, cells: Any, ridge: float = 0.0) -> float:
    """``log det(ridge I + sum_{p in cells} y_p y_p^T)``; ``-inf`` when the matrix is singular.

    ``Y`` is ``(k, L)`` (array or a model's ``Y_`` DataArray ``(component, cell)``), ``cells``
    column indices (repeats count twice), ``ridge >= 0``.
    """
    Y = as_factor_matrix(Y)
    ridge = check_positive(ridge, "ridge", error=PlanningError)
    cells = cells_array(cells, Y.shape[1])
    sign, logdet = np.linalg.slogdet(_gram(Y, cells, ridge))
    return float(logdet) if sign > 0 else -np.inf


def a_optimal_value(Y: Any, cells: Any, ridge: float) -> float:
    """Total prediction variance ``sum_i y_i^T (ridge I + sum_{p in cells} y_p y_p^T)^-1 y_i``.

    The sum runs over every column ``i`` of ``Y``; ``ridge`` must be ``> 0``. Lower is better;
    the A-optimal gain of a cell is the decrease of this value when the cell is added.
    """
    Y = as_factor_matrix(Y)
    ridge = check_positive(ridge, "ridge", error=PlanningError)
    if ridge <= 0:
        raise PlanningError("the a-optimal criterion needs ridge > 0 (e.g. ridge=1e-6)")
    cells = cells_array(cells, Y.shape[1])
    M = _gram(Y, cells, ridge)
    W = Y @ Y.T
    return float(np.trace(np.linalg.solve(M, W)))


# --------------------------------------------------------------------------- compiled kernels
_NO_SWS = np.empty((0, 0))  # the Fisher gains' third argument of :func:`_gains`


@numba.njit(cache=True, nogil=True)
def _gains(Y, S, SWS, idx, out):  # pragma: no cover - compiled
    """For ``y = Y[:, idx[j]]`` (idx empty: all columns in order), ``out[j] = log1p(y^T S y)``
    (Fisher: ``SWS`` empty) or ``(y^T SWS y) / (1 + y^T S y)`` (A-optimal)."""
    k = Y.shape[0]
    aopt = SWS.shape[0] > 0
    y = np.empty(k)
    for j in range(out.shape[0]):
        c = j if idx.shape[0] == 0 else idx[j]
        for a in range(k):
            y[a] = Y[a, c]
        q = 0.0
        r = 0.0
        for a in range(k):
            s = 0.0
            t = 0.0
            for b in range(k):
                s += S[a, b] * y[b]
                if aopt:
                    t += SWS[a, b] * y[b]
            q += y[a] * s
            r += y[a] * t
        out[j] = r / (1.0 + q) if aopt else np.log1p(q)


# --------------------------------------------------------------------------- oracles
def _inverse(M: np.ndarray, what: str, hint: str = "") -> tuple[np.ndarray, float]:
    """``(M^-1 symmetrised, log det M)`` of an information matrix; PlanningError naming
    ``what`` (its observations) when ``M`` is singular."""
    sign, logdet = np.linalg.slogdet(M)
    if sign <= 0 or np.linalg.cond(M) > 1e13:
        raise PlanningError(
            f"the information matrix of {what} is singular (rank {np.linalg.matrix_rank(M)} "
            f"< k = {M.shape[0]}); pass a small ridge (e.g. ridge=1e-6){hint}")
    S = np.linalg.inv(M)
    return 0.5 * (S + S.T), float(logdet)


class _Oracle:
    """Shared state: the factor matrix, the current set and ``S = M^-1`` in float64."""

    criterion: str = ""

    def __init__(self, Y: Any, ridge: float = 0.0, cells: Any = None, *,
                 prior_precision: Any = None, noise_var: Any = None) -> None:
        self.Y = as_factor_matrix(Y)
        k, L = self.Y.shape
        self.ridge = check_positive(ridge, "ridge", error=PlanningError)
        self.cells: list[int] = [int(c) for c in cells_array(cells, self.Y.shape[1])]
        self.Yw = self.Y
        if noise_var is not None:
            nv = np.asarray(noise_var, dtype=np.float64)
            if nv.ndim == 0:
                nv = np.full(L, float(nv))
            if nv.shape != (L,) or not np.all(np.isfinite(nv)) or np.any(nv <= 0):
                raise PlanningError(f"noise_var must be a positive scalar or ({L},) array")
            self.Yw = np.ascontiguousarray(self.Y / np.sqrt(nv))
        self.P0 = None
        if prior_precision is not None:
            P0 = np.asarray(prior_precision, dtype=np.float64)
            if P0.shape != (k, k) or not np.all(np.isfinite(P0)):
                raise PlanningError(f"prior_precision must be a finite ({k}, {k}) matrix")
            self.P0 = 0.5 * (P0 + P0.T)
        M = self._M(np.asarray(self.cells, dtype=np.int64))
        self.S, self._logdet = _inverse(M, f"the {len(self.cells)} initial cells",
                                        " or start with more cells")

    def _M(self, cells: np.ndarray) -> np.ndarray:
        """``P0 (or ridge I) + sum_{p in cells} w_p y_p y_p^T``."""
        if self.P0 is None:
            return _gram(self.Yw, cells, self.ridge)
        Yp = self.Yw[:, cells]
        return self.P0 + Yp @ Yp.T

    @property
    def k(self) -> int:
        return int(self.Y.shape[0])

    @property
    def fisher(self) -> float:
        """Fisher information (log det) of the current set, tracked by the rank-one updates."""
        return self._logdet

    def _idx(self, candidates: Any) -> np.ndarray:
        if candidates is None:
            return np.empty(0, dtype=np.int64)
        idx = np.ascontiguousarray(candidates, dtype=np.int64).ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= self.Y.shape[1]):
            raise PlanningError(f"candidates must be column indices in [0, {self.Y.shape[1]})")
        return idx

    def add(self, cell: int) -> None:
        """Add ``cell`` to the set: Sherman-Morrison update of ``S``, ``O(k^2)``."""
        y = self.Yw[:, int(cell)]
        u = self.S @ y
        q = float(y @ u)
        self.S -= np.outer(u, u) / (1.0 + q)
        self.S = 0.5 * (self.S + self.S.T)
        self._logdet += float(np.log1p(q))
        self.cells.append(int(cell))
        self._after_add()

    def _after_add(self) -> None:
        pass


class FisherOracle(_Oracle):
    """Gains ``I(P + x) - I(P) = log(1 + y_x^T M^-1 y_x)`` of the Fisher information.

    Parameters
    ----------
    Y : ``(k, L)`` factor matrix.
    ridge : ``>= 0``; ``M = ridge I + sum_P y_p y_p^T``.
    cells : the initial set ``P``; ``M`` must be nonsingular (else :class:`PlanningError`).
    """

    criterion = "fisher"

    def gains(self, candidates: Any = None) -> np.ndarray:
        """Gain of every column (``(L,)``) or of the given column indices (``(n,)``), float64."""
        idx = self._idx(candidates)
        out = np.empty(idx.size if candidates is not None else self.Y.shape[1])
        _gains(self.Yw, self.S, _NO_SWS, idx, out)
        return out

    @property
    def value(self) -> float:
        """The criterion's value for the current set: its Fisher information."""
        return self._logdet


class AOptimalOracle(_Oracle):
    """Gains of the A-optimal criterion: decrease of ``V(P) = sum_i y_i^T M^-1 y_i``.

    ``gain(x) = (y_x^T S W S y_x) / (1 + y_x^T S y_x)`` with ``S = M^-1`` and ``W = Y Y^T`` over
    all columns of ``Y`` (or ``weight`` when given, a ``(k, k)`` PSD matrix, or
    ``sum_i c_i y_i y_i^T`` with ``target_weights`` ``c``). Needs ``ridge > 0`` or a
    ``prior_precision``; with ``noise_var`` the candidates' ``y`` are ``y / sigma``.
    """

    criterion = "a-optimal"

    def __init__(self, Y: Any, ridge: float = 0.0, cells: Any = None, weight: Any = None, *,
                 prior_precision: Any = None, noise_var: Any = None,
                 target_weights: Any = None) -> None:
        if (check_positive(ridge, "ridge", error=PlanningError) <= 0
                and prior_precision is None):
            raise PlanningError("the a-optimal criterion needs ridge > 0 (e.g. ridge=1e-6) or "
                                "a prior_precision")
        super().__init__(Y, ridge, cells, prior_precision=prior_precision, noise_var=noise_var)
        if weight is not None:
            self.W = np.asarray(weight, dtype=np.float64)
        elif target_weights is not None:
            c = np.asarray(target_weights, dtype=np.float64)
            if c.shape != (self.Y.shape[1],) or np.any(c < 0):
                raise PlanningError(f"target_weights must be ({self.Y.shape[1]},) and >= 0")
            self.W = (self.Y * c) @ self.Y.T
        else:
            self.W = self.Y @ self.Y.T
        if self.W.shape != (self.k, self.k):
            raise PlanningError(f"weight must be ({self.k}, {self.k}), got {self.W.shape}")
        self._after_add()

    def _after_add(self) -> None:
        self.SWS = self.S @ self.W @ self.S
        self.SWS = 0.5 * (self.SWS + self.SWS.T)

    def gains(self, candidates: Any = None) -> np.ndarray:
        """Variance reduction of every column (``(L,)``) or of the given columns (``(n,)``)."""
        idx = self._idx(candidates)
        out = np.empty(idx.size if candidates is not None else self.Y.shape[1])
        _gains(self.Yw, self.S, self.SWS, idx, out)
        return out

    @property
    def value(self) -> float:
        """The criterion's value for the current set: total variance ``trace(S W)``."""
        return float(np.sum(self.S * self.W))


# --------------------------------------------------------------------------- averaged rows
def row_factors(Y: Any, rows: Any, noise_var: Any = None, errors: str = "independent"
                ) -> tuple[np.ndarray, np.ndarray]:
    """``(Yr (k, m), vr (m,))`` of averaged observations: ``rows`` ``(m, L)`` (sparse or dense)
    weights ``a`` over cells; observation ``a^T d`` has the row ``Yr = Y a`` and, from cell
    errors of variance ``noise_var`` (scalar or ``(L,)``; default 1), the noise variance
    ``vr = sum_j a_j^2 noise_var_j`` (``errors="independent"``) or ``(sum_j |a_j| sigma_j)^2``
    (``"shared"``; :func:`lrm_cvx.belief.averaged.row_noise`)."""
    Y = as_factor_matrix(Y)
    L = Y.shape[1]
    A = sps.csr_matrix(rows, dtype=np.float64)
    if A.shape[1] != L:
        raise PlanningError(f"rows must have {L} columns (one per cell), got {A.shape[1]}")
    nv = np.broadcast_to(np.asarray(1.0 if noise_var is None else noise_var, np.float64), (L,))
    Yr = np.ascontiguousarray(np.asarray(A @ Y.T).T)
    try:
        vr = row_noise(A, nv, errors)
    except DataError as err:  # the planner's error is PlanningError
        raise PlanningError(str(err)) from None
    return Yr, vr


def whitened_rows(Y: Any, rows: Any, noise_var: Any = None, errors: str = "independent"
                  ) -> np.ndarray:
    """``Yr / sqrt(vr)`` ``(k, m)`` of :func:`row_factors`: each averaged observation's row
    scaled to unit noise, so its Fisher information is ``log det(ridge I + Yw Yw^T)``."""
    Yr, vr = row_factors(Y, rows, noise_var, errors)
    return Yr / np.sqrt(np.maximum(vr, 1e-300))


def row_information(Y: Any, rows: Any, ridge: float = 0.0, noise_var: Any = None,
                    errors: str = "independent") -> float:
    """``log det(ridge I + sum_r Yr_r Yr_r^T / vr_r)`` of averaged observations (see
    :func:`row_factors`); for one-hot rows it is :func:`fisher_information`. ``-inf`` when
    singular."""
    ridge = check_positive(ridge, "ridge", error=PlanningError)
    Yw = whitened_rows(Y, rows, noise_var, errors)
    sign, logdet = np.linalg.slogdet(ridge * np.eye(Yw.shape[0]) + Yw @ Yw.T)
    return float(logdet) if sign > 0 else -np.inf


def check_pool_rows(pool: Any, rows: Any, L: int) -> tuple[np.ndarray, sps.csr_matrix]:
    """``(pool, rows)`` of a row oracle: the candidate cells (sorted, distinct) and their
    averaging rows as CSR ``(len(pool), L)``, one per pool cell (PlanningError otherwise)."""
    pool = cells_array(pool, L)
    if pool.size and np.any(np.diff(pool) <= 0):
        raise PlanningError("pool must be sorted distinct cells")
    A = sps.csr_matrix(rows, dtype=np.float64)
    if A.shape != (pool.size, L):
        raise PlanningError(f"rows must be ({pool.size}, {L}): one per pool cell")
    return pool, A


class RowOracle:
    """Fisher / A-optimal gains when a candidate's observation is an averaged row.

    Candidate cell ``pool[i]`` observes ``rows[i] @ d`` (a footprint's weights); ``extra_rows``
    (``(m, L)``) are observations already made (a towed sensor's legs); ``cells`` are pool
    cells already observed. The criterion is the one of :class:`FisherOracle` /
    :class:`AOptimalOracle` on the rows ``Y a`` with noise ``sum a^2 sigma^2``
    (:func:`row_factors`); the A-optimal target stays the cells' ``W = sum_i c_i y_i y_i^T``.
    ``pool_factors``: :func:`row_factors` of ``rows`` when already computed (a rebuild).
    ``gains``, ``add``, ``value`` and ``cells`` as the point oracles (cells are pool cells).
    """

    def __init__(self, criterion: str, Y: Any, ridge: float = 0.0, cells: Any = None, *,
                 pool: Any, rows: Any, extra_rows: Any = None, prior_precision: Any = None,
                 noise_var: Any = None, target_weights: Any = None, errors: str = "independent",
                 pool_factors: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        Yk = as_factor_matrix(Y)
        L = Yk.shape[1]
        self.pool, A = check_pool_rows(pool, rows, L)
        extra = sps.csr_matrix((0, L)) if extra_rows is None else sps.csr_matrix(extra_rows)
        Yp, vp = row_factors(Yk, A, noise_var, errors) if pool_factors is None else pool_factors
        Ye, ve = row_factors(Yk, extra, noise_var, errors)
        Yr, vr = np.hstack([Yp, Ye]), np.concatenate([vp, ve])
        self.cells: list[int] = [int(c) for c in cells_array(cells, L)]
        init = np.concatenate([self._pos(self.cells), self.pool.size
                               + np.arange(extra.shape[0])]).astype(np.int64)
        self._Yk, self._noise, self._errors = Yk, noise_var, errors
        self.criterion = criterion
        if criterion == "fisher":
            self.base: _Oracle = FisherOracle(Yr, ridge, init, prior_precision=prior_precision,
                                              noise_var=vr)
        elif criterion == "a-optimal":
            c = (np.ones(L) if target_weights is None
                 else np.asarray(target_weights, dtype=np.float64))
            if c.shape != (L,) or np.any(c < 0):
                raise PlanningError(f"target_weights must be ({L},) and >= 0")
            self.base = AOptimalOracle(Yr, ridge, init, (Yk * c) @ Yk.T,
                                       prior_precision=prior_precision, noise_var=vr)
        else:
            raise PlanningError(f"RowOracle takes 'fisher' or 'a-optimal', got {criterion!r}")

    def set_extra(self, extra_rows: Any) -> None:
        """Replace the observations already made (``extra_rows``, e.g. a towed sensor's legs
        after its route changed) and keep the observed pool cells: ``M`` and ``S = M^-1``
        recomputed in ``O((m + |cells|) k^2 + k^3)``, the pool's columns reused."""
        b = self.base
        Ye, ve = row_factors(self._Yk, sps.csr_matrix(extra_rows), self._noise, self._errors)
        Yw = np.hstack([b.Yw[:, self._pos(self.cells)], Ye / np.sqrt(ve)])
        M = (b.ridge * np.eye(b.k) if b.P0 is None else b.P0) + Yw @ Yw.T
        b.S, b._logdet = _inverse(M, f"the {Yw.shape[1]} observations")
        b._after_add()

    def _pos(self, cells: Any) -> np.ndarray:
        idx = np.asarray(cells, dtype=np.int64).ravel()
        pos = np.minimum(np.searchsorted(self.pool, idx), max(self.pool.size - 1, 0))
        if idx.size and (self.pool.size == 0 or not np.array_equal(self.pool[pos], idx)):
            raise PlanningError("candidates must be cells of the oracle's pool")
        return pos.astype(np.int64)

    @property
    def k(self) -> int:
        return self.base.k

    def gains(self, candidates: Any = None) -> np.ndarray:
        """Gain of each candidate (pool cells; default the whole pool), ``(n,)`` float64."""
        pos = np.arange(self.pool.size) if candidates is None else self._pos(candidates)
        return self.base.gains(pos)

    def add(self, cell: int) -> None:
        """Observe ``cell``'s row (a pool cell): rank-one update."""
        self.base.add(int(self._pos([int(cell)])[0]))
        self.cells.append(int(cell))

    @property
    def value(self) -> float:
        return self.base.value

    @property
    def fisher(self) -> float:
        return self.base.fisher
