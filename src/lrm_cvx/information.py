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
"""

from __future__ import annotations

from typing import Any, Literal

import numba
import numpy as np

from ._validation import as_factor_matrix, check_positive
from .errors import PlanningError

__all__ = [
    "fisher_information",
    "a_optimal_value",
    "FisherOracle",
    "AOptimalOracle",
    "make_oracle",
    "CRITERIA",
]

Criterion = Literal["fisher", "a-optimal"]
CRITERIA: tuple[str, ...] = ("fisher", "a-optimal")


def _gram(Y: np.ndarray, cells: np.ndarray, ridge: float) -> np.ndarray:
    """``ridge * I + Y[:, cells] Y[:, cells]^T`` as a ``(k, k)`` float64 matrix."""
    Yp = Y[:, cells]
    return ridge * np.eye(Y.shape[0]) + Yp @ Yp.T


def _cells_array(cells: Any, n_cols: int) -> np.ndarray:
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
    cells = _cells_array(cells, Y.shape[1])
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
    cells = _cells_array(cells, Y.shape[1])
    M = _gram(Y, cells, ridge)
    W = Y @ Y.T
    return float(np.trace(np.linalg.solve(M, W)))


# --------------------------------------------------------------------------- compiled kernels
@numba.njit(cache=True, nogil=True)
def _fisher_gains(Y, S, idx, out):  # pragma: no cover - compiled
    """out[j] = log1p(y^T S y) for y = Y[:, idx[j]] (idx < 0: all columns in order)."""
    k = Y.shape[0]
    n = out.shape[0]
    y = np.empty(k)
    for j in range(n):
        c = j if idx.shape[0] == 0 else idx[j]
        for a in range(k):
            y[a] = Y[a, c]
        q = 0.0
        for a in range(k):
            s = 0.0
            for b in range(k):
                s += S[a, b] * y[b]
            q += y[a] * s
        out[j] = np.log1p(q)


@numba.njit(cache=True, nogil=True)
def _aopt_gains(Y, S, SWS, idx, out):  # pragma: no cover - compiled
    """out[j] = (y^T SWS y) / (1 + y^T S y) for y = Y[:, idx[j]]."""
    k = Y.shape[0]
    n = out.shape[0]
    y = np.empty(k)
    for j in range(n):
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
                t += SWS[a, b] * y[b]
            q += y[a] * s
            r += y[a] * t
        out[j] = r / (1.0 + q)


# --------------------------------------------------------------------------- oracles
class _Oracle:
    """Shared state: the factor matrix, the current set and ``S = M^-1`` in float64."""

    criterion: str = ""

    def __init__(self, Y: Any, ridge: float = 0.0, cells: Any = None) -> None:
        self.Y = as_factor_matrix(Y)
        self.ridge = check_positive(ridge, "ridge", error=PlanningError)
        self.cells: list[int] = [int(c) for c in _cells_array(cells, self.Y.shape[1])]
        M = _gram(self.Y, np.asarray(self.cells, dtype=np.int64), self.ridge)
        sign, logdet = np.linalg.slogdet(M)
        if sign <= 0 or np.linalg.cond(M) > 1e13:
            raise PlanningError(
                f"the information matrix of the {len(self.cells)} initial cells is singular "
                f"(rank {np.linalg.matrix_rank(M)} < k = {self.Y.shape[0]}); "
                "pass a small ridge (e.g. ridge=1e-6) or start with more cells"
            )
        self.S = np.linalg.inv(M)
        self.S = 0.5 * (self.S + self.S.T)
        self._logdet = float(logdet)

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
        y = self.Y[:, int(cell)]
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
        _fisher_gains(self.Y, self.S, idx, out)
        return out

    @property
    def value(self) -> float:
        """The criterion's value for the current set: its Fisher information."""
        return self._logdet


class AOptimalOracle(_Oracle):
    """Gains of the A-optimal criterion: decrease of ``V(P) = sum_i y_i^T M^-1 y_i``.

    ``gain(x) = (y_x^T S W S y_x) / (1 + y_x^T S y_x)`` with ``S = M^-1`` and ``W = Y Y^T`` over
    all columns of ``Y`` (or ``weight`` when given, a ``(k, k)`` PSD matrix). Needs ``ridge > 0``.
    """

    criterion = "a-optimal"

    def __init__(self, Y: Any, ridge: float, cells: Any = None, weight: Any = None) -> None:
        if check_positive(ridge, "ridge", error=PlanningError) <= 0:
            raise PlanningError("the a-optimal criterion needs ridge > 0 (e.g. ridge=1e-6)")
        super().__init__(Y, ridge, cells)
        self.W = self.Y @ self.Y.T if weight is None else np.asarray(weight, dtype=np.float64)
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
        _aopt_gains(self.Y, self.S, self.SWS, idx, out)
        return out

    @property
    def value(self) -> float:
        """The criterion's value for the current set: total variance ``trace(S W)``."""
        return float(np.sum(self.S * self.W))


def make_oracle(
    criterion: str, Y: Any, ridge: float = 0.0, cells: Any = None, **kwargs: Any
) -> FisherOracle | AOptimalOracle:
    """The gain oracle for ``criterion`` (``"fisher"`` or ``"a-optimal"``) started at ``cells``."""
    if criterion == "fisher":
        return FisherOracle(Y, ridge, cells)
    if criterion in ("a-optimal", "aopt", "a_optimal"):
        return AOptimalOracle(Y, ridge, cells, **kwargs)
    raise PlanningError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
