"""The cvxpy path of the fit: a block subproblem (the X or Y step) over a batch of columns,
compiled once with parameters (DPP) and re-solved for every batch with Clarabel (SCS as
fallback). :mod:`.fit` uses it for ``solver="cvxpy"`` or a custom cvxpy regulariser.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from ..errors import SolverError
from .losses import Loss
from .regularizers import Regularizer

__all__ = ["cvxpy_columns"]

_OK = (cp.OPTIMAL,)


def _solve_problem(prob: cp.Problem, what: str) -> None:
    """Solve with Clarabel, falling back to SCS; SolverError with the status on failure."""
    status = None
    try:
        prob.solve(solver=cp.CLARABEL)
        status = prob.status
    except cp.error.SolverError as exc:
        status = f"error ({exc})"
    if status in _OK:
        return
    try:
        prob.solve(solver=cp.SCS, eps=1e-9, max_iters=100_000)
        if prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return
        status = f"Clarabel: {status}; SCS: {prob.status}"
    except cp.error.SolverError as exc:
        status = f"Clarabel: {status}; SCS: error ({exc})"
    raise SolverError(f"cvxpy {what} subproblem failed: {status}")


class _CvxBatch:
    """A block subproblem over ``nb`` columns, compiled once (DPP) and re-solved per batch.

    Column ``j`` has residual ``P_j @ v_j - d_j`` with parameters ``P_j = diag(w_j) A``
    (``A`` the other factor's transpose, ``w_j`` the 0/1 observation weights) and
    ``d_j = w_j * data_j``; unobserved entries thus have residual 0 and loss 0.
    """

    def __init__(self, m: int, k: int, nb: int, loss: Loss, reg: Regularizer) -> None:
        self.P = [cp.Parameter((m, k)) for _ in range(nb)]
        self.d = cp.Parameter((m, nb))
        self.V = cp.Variable((k, nb))
        terms = [loss.cvxpy(self.P[j] @ self.V[:, j] - self.d[:, j]) for j in range(nb)]
        reg_expr, cons = reg.cvxpy(self.V)
        self.prob = cp.Problem(cp.Minimize(cp.sum(cp.hstack(terms)) + reg_expr), cons)
        self.nb, self.m, self.k = nb, m, k

    def solve(self, A: np.ndarray, W: np.ndarray, Dw: np.ndarray, what: str) -> np.ndarray:
        """``A (m, k)``; ``W``, ``Dw`` ``(m, n)`` with ``n <= nb``; returns ``V (k, n)``."""
        n = W.shape[1]
        for j in range(self.nb):
            self.P[j].value = A * W[:, j : j + 1] if j < n else np.zeros((self.m, self.k))
        d = np.zeros((self.m, self.nb))
        d[:, :n] = Dw
        self.d.value = d
        _solve_problem(self.prob, what)
        return np.asarray(self.V.value)[:, :n]


def _batch_size(m: int, n: int) -> int:
    return int(max(1, min(256, n, 20_000 // max(m, 1))))


def cvxpy_columns(D, M, A, loss, reg, cache, role):
    """Solve every column of ``D (m, n)`` (mask ``M``) for its factor column, ``A (m, k)`` the
    other factor's transpose, in cached DPP batches; returns ``(k, n)``."""
    m, n = D.shape
    k = A.shape[1]
    nb = _batch_size(m, n)
    key = (role, m, k, nb)
    if key not in cache:
        cache[key] = _CvxBatch(m, k, nb, loss, reg)
    prob = cache[key]
    out = np.empty((k, n))
    for j0 in range(0, n, nb):
        j1 = min(j0 + nb, n)
        W = M[:, j0:j1].astype(np.float64)
        Dw = np.where(M[:, j0:j1], D[:, j0:j1], 0.0)
        out[:, j0:j1] = prob.solve(A, W, Dw, role)
    return out
