"""Upper bounds for the variance-reduction criteria (``"gp-variance"``, ``"a-optimal"``).

The variance reduction is concave in the observation weights, so every Frank-Wolfe iterate gives a
certified upper bound over any polytope of feasible plans; the derivation is in
docs/certificate.md §13.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import cho_solve, eigh, solve_triangular

from .._validation import as_factor_matrix
from ..errors import PlanningError
from .dopt import Polytope, top_sum, top_vertex
from .varbound_structured import cholesky_lower as _cholesky

__all__ = ["VarianceBound", "AOptimalObjective", "GPVarianceObjective", "variance_relaxation",
           "variance_objective", "VARIANCE_CRITERIA"]

VARIANCE_CRITERIA = ("a-optimal", "gp-variance")
"""The criteria :func:`variance_relaxation` bounds (canonical names)."""

_CVX_MAX = 25  # cvxpy polishes a piece of at most this many candidates (by default)
_BLOCK = 1 << 25  # entries of one (cells x targets) block of K (256 MB)
DENSE_MAX = 10_000
"""The most cells the dense gp-variance objective reads (two dense cells x cells matrices, 0.8 GB
each at this size); above it the structured objective (:mod:`.varbound_structured`, grid metric;
a ``"km"`` residual is refused in one line)."""
DENSE_MAX_ENTRIES = 1 << 27
"""The most (cells x targets) covariances the dense gp-variance objective sums into ``G``
(``2^27``, about 1 GB of kernel evaluations); beyond it, on a grid-metric residual, the
structured objective, whose set-up does not grow with the cells times the targets."""
RANK_MAX = 1500
"""The most candidates of a piece whose rank (Ky Fan) bound
:meth:`GPVarianceObjective.rank_bound` is computed (an ``O(N^3)`` eigensolve: about 0.25 s at
1,500 candidates, 3 s at 4,000 on 2 cores, more than a Frank-Wolfe at ``evaluate``'s
tolerance); larger pieces get the Frank-Wolfe bound only."""
RANK_MARGIN = 1e-10
"""Relative safety margin added to the rank bound (see :meth:`GPVarianceObjective.rank_bound`)."""


@dataclass(frozen=True, eq=False)
class VarianceBound:
    """A certified upper bound on the variance reduction of every design in a polytope.

    ``value`` is the smallest Frank-Wolfe bound (FW) over the designs tried (valid whatever
    the solvers did) or, when smaller, the rank (Ky Fan) bound of a dense gp-variance piece;
    ``active`` says which one ``value`` is (``"relaxation"`` or ``"rank"``). ``primal`` is ``F``
    at the best feasible design found (``weights``, over cell indices), so the relaxation's
    optimum lies in ``[primal, value]`` when ``active == "relaxation"``. Units: the
    criterion's (variance removed, the data's unit squared)."""

    value: float
    primal: float
    gap: float
    weights: dict[int, float]
    n_candidates: int
    iterations: int
    solve_time: float
    solver: str
    status: str
    active: str = "relaxation"

    def __repr__(self) -> str:
        return (f"VarianceBound(value={self.value:.6g}, primal={self.primal:.6g}, "
                f"gap={self.gap:.3g}, candidates={self.n_candidates}, "
                f"iterations={self.iterations}, {self.solve_time:.2f} s, solver={self.solver}, "
                f"status={self.status!r}, active={self.active!r})")


# ----------------------------------------------------------------------------- objectives
class AOptimalObjective:
    """``F(w) = tr(W P0^-1) - tr(W M(w)^-1)`` on the cells ``cells`` (k-dimensional latent).

    ``Y`` (k, L), ``P0`` (k, k) prior precision, ``noise_var`` scalar or (L,), ``W`` (k, k) the
    target matrix ``sum_t c_t y_t y_t^T``."""

    def __init__(self, Y: np.ndarray, cells: np.ndarray, P0: np.ndarray, noise_var: Any,
                 W: np.ndarray) -> None:
        self.cells = np.asarray(cells, dtype=np.int64)
        nv = np.broadcast_to(np.asarray(noise_var, dtype=np.float64), (Y.shape[1],))
        self.A = np.ascontiguousarray(Y[:, self.cells] / np.sqrt(nv[self.cells]))
        self.P0 = 0.5 * (P0 + P0.T)
        self.W = 0.5 * (W + W.T)
        Lp = _cholesky(self.P0, "the prior precision")
        self.prior_total = float(np.trace(cho_solve((Lp, True), self.W)))

    def _inv(self, pos: np.ndarray, w: np.ndarray) -> np.ndarray:
        M = self.P0 + (self.A[:, pos] * w) @ self.A[:, pos].T
        Lm = _cholesky(M, "the posterior precision")
        return cho_solve((Lm, True), np.eye(M.shape[0]))

    def value(self, pos: np.ndarray, w: np.ndarray) -> float:
        """``F`` at weights ``w`` on the positions ``pos`` (others 0)."""
        keep = w > 0
        Minv = self._inv(pos[keep], w[keep])
        return self.prior_total - float(np.sum(Minv * self.W))

    def value_grad(self, pos: np.ndarray, w: np.ndarray, at: np.ndarray
                   ) -> tuple[float, np.ndarray]:
        """``F`` at ``w`` on ``pos`` and its gradient at the positions ``at``."""
        keep = w > 0
        Minv = self._inv(pos[keep], w[keep])
        Z = Minv @ self.W @ Minv
        Aa = self.A[:, at]
        return (self.prior_total - float(np.sum(Minv * self.W)),
                np.einsum("ai,ab,bi->i", Aa, Z, Aa))

    def cvx_model(self, pos: np.ndarray) -> tuple[Any, Any, Any]:
        """``(w, objective, constraints)`` of cvxpy for ``F`` on the positions ``pos``."""
        import cvxpy as cp

        w = cp.Variable(pos.size, nonneg=True)
        A = self.A[:, pos]
        M = self.P0 + A @ cp.diag(w) @ A.T
        R = _sqrt_psd(self.W)
        return w, self.prior_total - cp.matrix_frac(R, 0.5 * (M + M.T)), []


class GPVarianceObjective:
    """``F(w) = tr(G_SS (K_SS + s^2 diag(1/w_S))^-1)`` on the cells ``cells`` (observation
    space: the field's prior covariance ``K`` and ``G = K_{.T} C K_{T.}`` on ``cells`` only).
    """

    def __init__(self, K: np.ndarray, G: np.ndarray, noise: float, prior_total: float,
                 cells: np.ndarray) -> None:
        self.cells = np.asarray(cells, dtype=np.int64)
        self.K = 0.5 * (K + K.T)
        self.G = 0.5 * (G + G.T)
        self.noise = float(noise)
        self.prior_total = float(prior_total)

    def _solve(self, pos: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                             np.ndarray]:
        """``(S, Gamma, chol(B))`` with ``B = I + Gamma K_SS Gamma``, ``Gamma = sqrt(w_S)/s``."""
        keep = w > 0
        S = pos[keep]
        gam = np.sqrt(w[keep] / self.noise)
        B = np.eye(S.size) + gam[:, None] * self.K[np.ix_(S, S)] * gam[None, :]
        return S, gam, _cholesky(B, "I + Gamma K Gamma")

    def value(self, pos: np.ndarray, w: np.ndarray) -> float:
        S, gam, LB = self._solve(pos, w)
        if S.size == 0:
            return 0.0
        X = solve_triangular(LB, gam[:, None] * self.G[np.ix_(S, S)] * gam[None, :],
                             lower=True)
        X = solve_triangular(LB, X.T, lower=True)
        return float(np.trace(X))

    def value_grad(self, pos: np.ndarray, w: np.ndarray, at: np.ndarray
                   ) -> tuple[float, np.ndarray]:
        S, gam, LB = self._solve(pos, w)
        g0 = np.diag(self.G)[at]
        if S.size == 0:
            return 0.0, g0 / self.noise
        # X = Q K_{S,at}, Q = (K_SS + D)^-1 = Gamma B^-1 Gamma
        X = gam[:, None] * cho_solve((LB, True), gam[:, None] * self.K[np.ix_(S, at)])
        GS = self.G[np.ix_(S, at)]
        t2 = np.einsum("ji,ji->i", X, GS)
        t3 = np.einsum("ji,ji->i", X, self.G[np.ix_(S, S)] @ X)
        Y = gam[:, None] * self.G[np.ix_(S, S)] * gam[None, :]
        F = float(np.trace(cho_solve((LB, True), Y)))
        return F, np.maximum(g0 - 2.0 * t2 + t3, 0.0) / self.noise

    def rank_bound(self, pos: np.ndarray, n: float) -> float:
        """The rank (Ky Fan) bound: the sum of the ``floor(n)`` largest eigenvalues of
        ``M = L^-1 G_CC L^-T``, ``L L^T = K_CC + s^2 I``, on the candidates ``C`` at the
        positions ``pos``; at least ``F(1_P)`` for every set ``P`` of at most ``n`` of them.

        Observing ``P`` removes ``tr(C^1/2 R_P C^1/2)`` (target weights ``C``), ``R_P =
        K_TP (K_PP + s^2 I)^-1 K_PT``, of rank at most ``|P|`` and below ``R_C`` in PSD order;
        by Weyl's monotonicity its trace is at most the ``|P|`` largest eigenvalues of
        ``C^1/2 R_C C^1/2``, whose nonzero eigenvalues are ``M``'s. One Cholesky factor and
        one eigensolve in float64, ``O(N^3)``: callers skip it above :data:`RANK_MAX`
        candidates. A relative margin :data:`RANK_MARGIN` (times ``n`` times the largest
        eigenvalue) covers the eigensolver's backward error (Weyl: ``O(N eps ||M||)`` per
        eigenvalue) and the factor's (``O(cond(K_CC + s^2 I) eps)`` relative, under the
        margin for condition numbers up to about ``1e5``)."""
        pos = np.asarray(pos, dtype=np.int64)
        m = min(math.floor(float(n) + 1e-9), pos.size)
        if m <= 0:
            return 0.0
        A = self.K[np.ix_(pos, pos)] + self.noise * np.eye(pos.size)
        L = _cholesky(A, "K + s^2 I on the candidates")
        X = solve_triangular(L, self.G[np.ix_(pos, pos)], lower=True)
        M = solve_triangular(L, X.T, lower=True)
        lam = eigh(0.5 * (M + M.T), eigvals_only=True,
                   subset_by_index=[pos.size - m, pos.size - 1])
        top = float(np.sum(np.maximum(lam, 0.0)))
        return top + RANK_MARGIN * m * float(max(lam.max(), 0.0))

    def cvx_model(self, pos: np.ndarray) -> tuple[Any, Any, Any]:
        """cvxpy model in the whitened latent ``z = chol(K_pos)^-1 f_pos``: ``F = tr(R^T R) -
        tr(R^T (I + L^T diag(w) L / s^2)^-1 R)`` with ``R R^T = L^-1 G L^-T``."""
        import cvxpy as cp

        Kp = self.K[np.ix_(pos, pos)]
        L = _cholesky(Kp, "the field's prior covariance on the candidates")
        Li = solve_triangular(L, np.eye(pos.size), lower=True)
        Wz = Li @ self.G[np.ix_(pos, pos)] @ Li.T
        R = _sqrt_psd(Wz)
        w = cp.Variable(pos.size, nonneg=True)
        P = np.eye(pos.size) + (L.T / self.noise) @ cp.diag(w) @ L
        return w, float(np.sum(R * R)) - cp.matrix_frac(R, 0.5 * (P + P.T)), []


def _sqrt_psd(W: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(0.5 * (W + W.T))
    keep = lam > lam.max(initial=0.0) * 1e-14
    return V[:, keep] * np.sqrt(lam[keep])


def variance_objective(criterion: str, Y: np.ndarray, cells: np.ndarray, ridge: float,
                       terms: dict[str, Any], *, structured: bool | None = None,
                       start: Any = None) -> Any:
    """The objective of ``criterion`` on the cells ``cells`` from the planner's oracle terms
    ``terms`` (``prior_precision``, ``noise_var``, ``target_weights`` for ``"a-optimal"``;
    ``region``, ``spatial_cov``, ``prior_cov``, ``targets``, ``target_weights`` for
    ``"gp-variance"``).

    gp-variance on a grid-metric residual over more than :data:`DENSE_MAX` cells or more than
    :data:`DENSE_MAX_ENTRIES` cells x targets (or with ``structured=True``) gets the structured
    objective of :mod:`lrm_cvx.planning.varbound_structured`
    (no cells x cells matrix; Frank-Wolfe starts at the cells ``start``, e.g. the plan);
    ``structured=False`` keeps the dense one."""
    from ..information import check_gp_inputs, gp_latent_cov, gp_noise

    Y = as_factor_matrix(Y)
    k, L = Y.shape
    tw = terms.get("target_weights")
    if criterion == "a-optimal":
        P0 = terms.get("prior_precision")
        if P0 is None:
            if not ridge > 0:
                raise PlanningError("the a-optimal bound needs ridge > 0 or a prior precision "
                                    "(the prior variance is infinite otherwise)")
            P0 = ridge * np.eye(k)
        c = np.ones(L) if tw is None else np.asarray(tw, dtype=np.float64)
        W = (Y * c) @ Y.T
        nv = terms.get("noise_var")
        return AOptimalObjective(Y, cells, np.asarray(P0, float), 1.0 if nv is None else nv, W)
    if criterion != "gp-variance":
        raise PlanningError(f"the variance bound covers {VARIANCE_CRITERIA}, not {criterion!r}")
    region, cov = terms.get("region"), terms.get("spatial_cov")
    S0 = check_gp_inputs(Y, region, cov, terms.get("prior_cov"))
    targets = terms.get("targets")
    T = np.arange(L) if targets is None else np.unique(np.asarray(targets, dtype=np.int64))
    c = (np.ones(L) if tw is None else np.asarray(tw, dtype=np.float64))[T]
    cells = np.asarray(cells, dtype=np.int64)
    grid_metric = getattr(cov, "metric", None) == "grid"
    if structured is None:
        structured = grid_metric and (cells.size > DENSE_MAX
                                      or float(cells.size) * T.size > DENSE_MAX_ENTRIES)
    if not structured and cells.size > DENSE_MAX:
        raise PlanningError(
            f"the gp-variance bound forms dense covariances over the {cells.size} cells a plan "
            f"of this budget may observe ({2 * 8 * cells.size ** 2 / 1e9:.3g} GB); with "
            f"spatial_cov.metric {cov.metric!r} it covers at most {DENSE_MAX} (a smaller budget "
            "or region, or a 'grid' metric; criterion='fisher' scales)")
    if structured:
        from .varbound_structured import structured_objective

        return structured_objective(Y, np.unique(cells), dict(terms, prior_cov=S0), start)
    K = gp_latent_cov(Y, S0, region, cov, cells, cells)
    G = np.zeros_like(K)
    step = max(1, _BLOCK // max(cells.size, 1))  # targets a block: cells x step entries
    for lo in range(0, T.size, step):  # G = K_cT C K_Tc, summed over blocks of targets
        KcT = gp_latent_cov(Y, S0, region, cov, cells, T[lo:lo + step])
        G += (KcT * c[lo:lo + step]) @ KcT.T
    prior = float(c @ (np.einsum("ai,ab,bi->i", Y[:, T], S0, Y[:, T]) + cov.sill))
    return GPVarianceObjective(K, G, gp_noise(cov), prior, cells)


# ----------------------------------------------------------------------------- relaxation
def _fw_bound(obj: Any, pos: np.ndarray, poly: Polytope, w: np.ndarray
              ) -> tuple[float, float, np.ndarray, np.ndarray]:
    """``(bound (FW), F(w), gradient, a maximising vertex)`` at any ``w >= 0`` on the
    positions ``pos``: the bound is ``F(w) + max_v g . v - g . w`` with ``max_v g . v`` the
    exact top-n sum or the LP's dual value evaluated exactly (an upper bound whatever HiGHS
    returned)."""
    F, g = obj.value_grad(pos, w, pos)
    sup, v = _support(poly, g)
    return F + sup - float(g @ w), F, g, v


def _support(poly: Polytope, g: np.ndarray) -> tuple[float, np.ndarray]:
    """``(upper bound on max_{v in poly} g . v, a feasible maximiser v)``: one LP at most."""
    v = np.zeros(poly.N)
    if not poly.limited:
        idx, s = top_vertex(g, poly.n)
        v[idx] = s
        return top_sum(g, poly.n)[0], v
    nu, mus, x = poly.lp(g)
    return poly.h(g, nu, mus), poly.project(x)


def variance_relaxation(obj: Any, pos: np.ndarray, poly: Polytope, *, iters: int = 60,
                        tol: float = 1e-3, polish: bool | None = None,
                        solver: str = "CLARABEL", rank_bound: bool = True) -> VarianceBound:
    """Certified upper bound on ``max F(w)`` over ``poly`` (weights on ``obj``'s cells at the
    positions ``pos``): the smallest (FW) bound over Frank-Wolfe's iterates (from the
    prior gains' vertex, parabolic line search, ``iters`` steps or until the relative
    gap ``(bound - F) / bound <= tol``) and, when ``polish`` (default: at most 25 candidates;
    then at most 10 Frank-Wolfe steps), over cvxpy's solution of the same relaxation
    (projected into the polytope). A structured objective
    (:class:`~lrm_cvx.planning.varbound_structured.StructuredGPVarianceObjective`) starts at
    its ``start`` cells' indicator (projected into the polytope) when the piece holds some,
    stops before an iterate with more than its ``max_support`` cells of weight and is not
    polished.

    With ``rank_bound`` (default) an objective with a ``rank_bound`` method (the dense
    gp-variance one, on at most :data:`RANK_MAX` candidates) also bounds the piece by the rank
    (Ky Fan) bound with the polytope's count limit; ``value`` is the smaller of the two
    (``active``: ``"rank"`` or ``"relaxation"``) and Frank-Wolfe stops once it is within
    ``tol`` of the best design. The structured objective and a-optimal get the (FW) bound
    only."""
    t0 = time.perf_counter()
    pos = np.asarray(pos, dtype=np.int64)
    if pos.size == 0:
        return VarianceBound(0.0, 0.0, 0.0, {}, 0, 0, 0.0, "none", "empty")
    # start at the vertex of the prior gains (sparse iterates: the support grows by a vertex
    # a step), not at the uniform design
    sparse = getattr(obj, "sparse", False)  # the structured objective: small supports
    if polish is None:
        polish = pos.size <= _CVX_MAX and not sparse
    if polish:  # a few first-order steps, then the conic solve does the rest
        iters = min(iters, 10)
    ind = (np.isin(obj.cells[pos], obj.start).astype(np.float64) if sparse
           else np.zeros(0))
    if ind.any():  # the structured objective starts at the plan's cells (in the polytope)
        w = poly.project(ind)
    else:
        w = _support(poly, obj.value_grad(pos, np.zeros(pos.size), pos)[1])[1]
    rank = (obj.rank_bound(pos, poly.n)
            if rank_bound and hasattr(obj, "rank_bound") and pos.size <= RANK_MAX else math.inf)
    best_val, best_primal, best_w = rank, -math.inf, w
    steps = 0
    used = "Frank-Wolfe (structured)" if sparse else "Frank-Wolfe"
    for _ in range(iters):
        steps += 1
        val, F, g, v = _fw_bound(obj, pos, poly, w)
        best_val = min(best_val, val)
        if F > best_primal:
            best_primal, best_w = F, w
        if best_val - best_primal <= tol * max(abs(best_val), 1e-300):
            break
        d = v - w
        slope = float(g @ d)
        if not slope > 0:
            break
        gam = 1.0
        for _ in range(4):  # parabola through F(0), F'(0), F(gam); concave: curvature >= 0
            Fg = obj.value(pos, w + gam * d)
            curv = (F + slope * gam - Fg) / gam ** 2
            step = gam if curv <= 0 else min(gam, slope / (2.0 * curv))
            if step >= gam * 0.999:
                break
            gam = step
        w = np.maximum(w + gam * d, 0.0)
        if sparse and np.count_nonzero(w) > obj.max_support:  # its gradient costs |S|^2 N
            break
    if polish and best_val - best_primal > tol * max(abs(best_val), 1e-300):
        wc = _cvx_solve(obj, pos, poly, solver)
        if wc is not None:
            used = f"Frank-Wolfe + {solver}"
            val, F, _, _ = _fw_bound(obj, pos, poly, wc)
            best_val = min(best_val, val)
            if F > best_primal:
                best_primal, best_w = F, wc
    weights = {int(obj.cells[p]): float(x) for p, x in zip(pos, best_w, strict=True) if x > 0}
    gap = max(best_val - best_primal, 0.0)
    status = "optimal" if gap <= tol * max(abs(best_val), 1e-300) else "inexact"
    return VarianceBound(float(best_val), float(best_primal), float(gap), weights, int(pos.size),
                         steps, time.perf_counter() - t0, used, status,
                         "rank" if best_val == rank else "relaxation")


def _cvx_solve(obj: Any, pos: np.ndarray, poly: Polytope, solver: str) -> np.ndarray | None:
    """cvxpy's maximiser of ``F`` over ``poly`` (projected into it), or None if it failed."""
    import cvxpy as cp

    w, objective, cons = obj.cvx_model(pos)
    cons = cons + [w <= 1, cp.sum(w) <= poly.n]
    if poly.limited:
        A, b = poly._rows(np.arange(pos.size))
        cons.append(A[1:] @ w <= b[1:])
    prob = cp.Problem(cp.Maximize(objective), cons)
    opts = ({"tol_gap_abs": 1e-11, "tol_gap_rel": 1e-11, "tol_feas": 1e-11}
            if solver == "CLARABEL" else {})
    with warnings.catch_warnings():  # an inaccurate solution is still a design to certify at
        warnings.simplefilter("ignore")
        try:
            prob.solve(solver=solver, **opts)
        except (cp.error.SolverError, ValueError, ArithmeticError):
            try:
                prob.solve(solver=solver)
            except (cp.error.SolverError, ValueError, ArithmeticError):
                return None
    if w.value is None or prob.status not in ("optimal", "optimal_inaccurate"):
        return None
    return poly.project(np.asarray(w.value, dtype=np.float64))
