"""The per-cell offset fitted jointly with the factors (``GLRM(offset=True)``, fast path).

The fit first centres each cell by its observed mean ``m``, then fits the correction ``o`` as
one more factor: ``D - m ~ X^T Y + 1 o^T = [X; 1]^T [Y; o]``, a rank-``k + 1`` model whose last
row of ``X`` is held at 1. The Y step is the ordinary quadratic Y step at rank ``k + 1`` (each
cell's factors and offset solved together, exactly); the X step solves the first ``k`` rows
with the last one fixed (:func:`fixed_row_solve`). Both are exact block minimisers of

    sum_{(t, j) observed} (D_tj - m_j - x_t . y_j - o_j)^2 + reg_x + reg_y + n0 sum_j o_j^2,

so the objective never increases. ``n0 = OFFSET_PRIOR_OBS``: the offset's prior is worth one
observation at the cell's observed mean (``o`` shrinks by ``n_j / (n_j + 1)``). A robust loss
(Huber, absolute, quantile) takes the same two steps on its quadratic majoriser
(:class:`OffsetRidge`, ``fit.x_block_offset``).

Why not the observed mean alone: when values are missing not at random (clouds in the wet
season, ice that hides the sea in winter) a cell's observed mean is biased towards the season
it is seen in, and the centred low-rank fit cannot absorb that bias (a constant in time needs a
row of ``X``). For fully observed data the two coincide (the best rank-``k`` affine fit centres
the columns, and then ``o = 0``). Why the prior: without it the completion of a cell seen a
few times may have no minimiser (its unobserved entries run off to infinity while ``Y`` and
``o`` cancel on the observed ones; seen on a 12 x 15 record at rank 3 with 7-12 values per
cell); one pseudo-observation makes every step's problem strictly convex in ``o``.
"""

from __future__ import annotations

import numpy as np

from . import kernels as K
from .regularizers import Regularizer

__all__ = ["OFFSET_PRIOR_OBS", "augmented", "row_ridges", "penalty", "fixed_row_solve",
           "OffsetRidge", "supports"]

OFFSET_PRIOR_OBS = 1.0  # the offset's ridge: one pseudo-observation at the observed mean


def augmented(X: np.ndarray) -> np.ndarray:
    """``[X; 1] (k + 1, T)`` float64 C-contiguous: the factors with the offset's row."""
    k, T = X.shape
    out = np.empty((k + 1, T))
    out[:k] = X
    out[k] = 1.0
    return out


def row_ridges(lam: float, k: int) -> np.ndarray:
    """The Y step's ridge of each row of ``[Y; o]``, ``(k + 1,)``: ``lam`` (the regulariser of
    ``Y``, 0 without one) for the factors, :data:`OFFSET_PRIOR_OBS` for the offset."""
    return np.append(np.full(k, float(lam or 0.0)), OFFSET_PRIOR_OBS)


def penalty(o: np.ndarray) -> float:
    """The offset's term of the objective, ``n0 sum_j o_j^2``."""
    return OFFSET_PRIOR_OBS * float(np.dot(o, o))


def fixed_row_solve(G: np.ndarray, h: np.ndarray, lam: float) -> np.ndarray:
    """The X step with the last row of ``[X; 1]`` fixed: ``(k, T)``.

    ``G (T, npair)`` (packed, ``np.triu_indices(k + 1)`` order) and ``h (T, k + 1)`` are the
    X-step statistics at ``[Y; o]`` (:func:`~.quadratic.x_stats`). Each time solves
    ``(G_yy + lam I) x = h_y - G_yo``: the first ``k`` normal equations with ``x_k = 1`` (the
    same batched Cholesky, pseudo-inverse fallback, as the unconstrained step)."""
    T, k1 = h.shape
    k = k1 - 1
    pa, pb = np.triu_indices(k1)
    inner = pb < k  # pairs (a, b), a <= b < k: np.triu_indices(k) order
    cross = (pb == k) & (pa < k)  # pairs (a, k), a = 0 .. k - 1
    Gk = np.ascontiguousarray(G[:, inner])
    rhs = np.ascontiguousarray(h[:, :k] - G[:, cross])
    qa, qb = K.pair_index(k)
    out = np.empty((T, k))
    K.chol_solve(Gk, rhs, float(lam), qa, qb, out)
    return np.ascontiguousarray(out.T)


def supports(reg_x: Regularizer, reg_y: Regularizer) -> bool:
    """True when both regularisers are ridge-type (none or ridge): the joint offset's steps are
    then the fast path's normal equations with one more row (L1 and non-negativity keep the
    observed mean: their coordinate descent has no fixed row)."""
    return reg_x.ridge_coefficient is not None and reg_y.ridge_coefficient is not None


class OffsetRidge(Regularizer):
    """The regulariser of ``[Y; o]`` in the fast path's Y step (robust losses): ``reg``'s ridge
    on the factors' rows, :data:`OFFSET_PRIOR_OBS` on the offset's (``ridge_coefficient`` one
    per row, :func:`~.kernels.ridge_vector`)."""

    name = "offset-ridge"
    serializable = False

    def __init__(self, reg: Regularizer, k: int) -> None:
        self.reg = reg
        self.ridge_coefficient = row_ridges(reg.ridge_coefficient, k)

    def evaluate(self, F: np.ndarray) -> np.ndarray:
        return self.reg.evaluate(F[:-1]) + OFFSET_PRIOR_OBS * np.square(F[-1])
