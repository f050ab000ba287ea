"""The gp-variance bound at paper scale: ``F(w)`` and its gradient from the covariance's structure.

Above :data:`~lrm_cvx.planning.varbound.DENSE_MAX` candidates the dense objective's two
candidates x candidates matrices do not fit. :class:`StructuredGPVarianceObjective` evaluates
the same ``F(w) = tr(G_SS (K_SS + s^2 diag(1/w_S))^-1)`` and gradient
``dF/dw_i = (G_ii - 2 G_iS A^-1 K_Si + K_iS A^-1 G_SS A^-1 K_Si) / s^2`` for weights ``w``
supported on a small set ``S``, with ``K`` and ``G`` between ``S`` and blocks of candidates
taken from the structured gp-variance oracle's set-up (the low-rank trend's ``k x k`` sums over
the targets, the residual's lag table or one convolution per cell of ``S``);
:func:`~lrm_cvx.planning.varbound.variance_relaxation` runs its Frank-Wolfe from the plan
while the support holds at most :data:`MAX_SUPPORT` cells. The bound (FW) of
docs/certificate.md §13 holds at any ``w >= 0``, so the support's size costs tightness, never
validity.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import cholesky, solve_triangular

from ..errors import PlanningError

__all__ = ["StructuredGPVarianceObjective", "structured_objective", "cholesky_lower",
           "MAX_SUPPORT"]

MAX_SUPPORT = 600
"""The most cells of weight a Frank-Wolfe iterate of a structured objective may have: it stops
before a larger one (a gradient costs ``O(|S|^2 N)`` for ``N`` candidates; the smallest bound
so far is kept)."""

_BLOCK = 1 << 22  # entries of one (support x candidates) block (32 MB)


def cholesky_lower(M: np.ndarray, what: str) -> np.ndarray:
    """The lower Cholesky factor of the symmetrised ``M``; a one-line PlanningError naming
    ``what`` when it is not positive definite."""
    try:
        return cholesky(0.5 * (M + M.T), lower=True)
    except np.linalg.LinAlgError:
        raise PlanningError(f"{what} is not positive definite: the variance bound cannot be "
                            "evaluated") from None


class StructuredGPVarianceObjective:
    """The gp-variance ``F(w)`` of :class:`~lrm_cvx.planning.varbound.GPVarianceObjective`
    without candidates x candidates matrices.

    ``oracle`` is a :class:`~lrm_cvx.gp_structured.StructuredGPVarianceOracle` whose sorted
    cells are ``cells`` (no initial observation); ``start`` (cells, optional) is the design
    Frank-Wolfe starts from (the plan being certified). Weights are given on positions of
    ``cells``, as for the dense objective; ``F`` costs ``O(|S|^3)``, a gradient over ``N``
    candidates ``O(|S|^2 N)`` in blocks of candidates."""

    sparse = True
    max_support = MAX_SUPPORT

    def __init__(self, oracle: Any, cells: np.ndarray, start: Any = None) -> None:
        self.cells = np.asarray(cells, dtype=np.int64)
        self._oracle = oracle
        self.noise = float(oracle.noise)
        self.prior_total = float(oracle.value)
        self.start = (np.zeros(0, np.int64) if start is None
                      else np.unique(np.asarray(start, dtype=np.int64)))

    def _solve(self, pos: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                             np.ndarray, np.ndarray]:
        """``(S, Gamma, chol(B), M)``: ``B = I + Gamma K_SS Gamma``, ``Gamma = sqrt(w_S)/s``,
        ``M = L^-1 Gamma G_SS Gamma L^-T`` (``F = tr M``)."""
        keep = w > 0
        S = pos[keep]
        gam = np.sqrt(w[keep] / self.noise)
        K, G = self._oracle.covariance_blocks(S, S)
        B = np.eye(S.size) + gam[:, None] * (0.5 * (K + K.T)) * gam[None, :]
        LB = cholesky_lower(B, "I + Gamma K Gamma")
        M = solve_triangular(LB, gam[:, None] * (0.5 * (G + G.T)) * gam[None, :], lower=True)
        M = solve_triangular(LB, M.T, lower=True)
        return S, gam, LB, 0.5 * (M + M.T)

    def value(self, pos: np.ndarray, w: np.ndarray) -> float:
        """``F`` at weights ``w`` on the positions ``pos`` (others 0)."""
        S, _, _, M = self._solve(pos, w)
        return float(np.trace(M)) if S.size else 0.0

    def value_grad(self, pos: np.ndarray, w: np.ndarray, at: np.ndarray
                   ) -> tuple[float, np.ndarray]:
        """``F`` at ``w`` on ``pos`` and its gradient at the positions ``at``, over blocks of
        ``at``."""
        at = np.asarray(at, dtype=np.int64)
        S, gam, LB, M = self._solve(pos, w)
        g0 = self._oracle.g_diagonal(at)
        if S.size == 0:
            return 0.0, g0 / self.noise
        out = np.empty(at.size)
        step = max(256, _BLOCK // S.size)
        for lo in range(0, at.size, step):
            b = at[lo:lo + step]
            K, G = self._oracle.covariance_blocks(S, b)
            a = solve_triangular(LB, gam[:, None] * K, lower=True)      # L^-1 Gamma K_Sb
            c = solve_triangular(LB, gam[:, None] * G, lower=True)      # L^-1 Gamma G_Sb
            t2 = np.einsum("ji,ji->i", a, c)
            t3 = np.einsum("ji,ji->i", a, M @ a)
            out[lo:lo + step] = g0[lo:lo + step] - 2.0 * t2 + t3
        return float(np.trace(M)), np.maximum(out, 0.0) / self.noise


def structured_objective(Y: np.ndarray, cells: np.ndarray, terms: dict[str, Any],
                         start: Any = None) -> StructuredGPVarianceObjective:
    """The gp-variance objective on ``cells`` (sorted, unique) from the structured oracle's
    set-up (grid metric). Its lag table is used only where it is exact to ``1e-9`` of its
    largest entry; else one convolution per cell of the support. The planner's kept set-up
    (``GRID_TERMS``) is left as it was."""
    from .. import gp_structured
    from ..gp_structured import StructuredGPVarianceOracle

    cov = terms.get("spatial_cov")
    if getattr(cov, "metric", None) != "grid":
        raise PlanningError(
            f"the gp-variance bound over {cells.size} candidate cells needs the structured "
            "objective, which needs spatial_cov.metric 'grid' (a smaller budget or region for "
            "'km'; criterion='fisher' scales)")
    kept = dict(gp_structured.GRID_TERMS)
    try:
        oracle = StructuredGPVarianceOracle(
            Y, None, region=terms.get("region"), spatial_cov=cov,
            prior_cov=terms.get("prior_cov"), pool=cells, targets=terms.get("targets"),
            target_weights=terms.get("target_weights"), boundary_tol=1e-9)
    finally:
        gp_structured.GRID_TERMS.clear()
        gp_structured.GRID_TERMS.update(kept)
    return StructuredGPVarianceObjective(oracle, cells, start)
