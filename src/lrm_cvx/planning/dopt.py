"""The D-optimal design relaxation and its solver-independent dual bound.

The continuous relaxation ``max log det(ridge I + sum_i w_i y_i y_i^T)`` over ``0 <= w <= 1``,
``sum_i w_i <= n`` (and nested count limits) is solved on a working set grown by column
generation; the reported bound is a Lagrange dual value valid for any ``w``. Regions, paths and
plans are :mod:`lrm_cvx.planning.certificate`'s business; derivations in docs/certificate.md §1-3.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Literal

import numba
import numpy as np
import scipy.linalg
import scipy.sparse

from .._validation import as_factor_matrix, first_line
from ..errors import ConvergenceWarning, PlanningError, SolverError

__all__ = [
    "Bound",
    "dopt_upper_bound",
    "dual_value",
    "certify_weights",
]

_SOLVERS = ("CLARABEL", "SCS")
# Clarabel settings tried in turn: its defaults fail on unscaled problems, and equilibration is
# what most often breaks it on the congruence-scaled working-set problems
_TIGHT = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10}
_CLARABEL_OPTS = (
    {"max_step_fraction": 0.9, "chordal_decomposition_enable": False, "equilibrate_enable": False,
     **_TIGHT},
    {"max_step_fraction": 0.9, "chordal_decomposition_enable": False, **_TIGHT},
    {"max_step_fraction": 0.9, "chordal_decomposition_enable": False},
)
_SCS_OPTS = {"eps_abs": 1e-7, "eps_rel": 1e-7, "max_iters": 20000}
_FW_LIMITED = 4  # Frank-Wolfe steps when the relaxation has count limits (one LP each)
_DIST_EPS = 1e-9  # slack on budget comparisons: the bound must cover float-rounded path costs
DIST_EPS = _DIST_EPS
"""Slack on budget comparisons (public name for the plan families of ``families.py``)."""


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class Bound:
    """A certified upper bound on the D-optimal relaxation (all values in nats).

    ``value`` is the dual bound (valid whatever the solvers did), ``primal = log det M(w)`` is the
    relaxation's value at the returned feasible ``weights``, so the relaxation optimum lies in
    ``[primal, value]`` and ``gap = value - primal``. ``weights`` is a 1-D ``scipy.sparse``
    ``coo_array`` over cell indices (length ``L``, the columns of ``Y``) holding the nonzero
    ``w``. ``status`` is ``"optimal"`` (gap <= tol), ``"inexact"`` (valid bound, gap > tol),
    ``"trivial"`` (n >= number of candidates: w = 1 everywhere) or ``"singular"`` (every
    feasible M(w) is singular, so every plan has information -inf and the bound is -inf).
    """

    value: float
    primal: float
    gap: float
    weights: scipy.sparse.coo_array
    n: float
    k: int
    ridge: float
    n_candidates: int
    n_working: int
    iterations: int
    fw_iterations: int
    solve_time: float
    solver: str
    status: str
    history: tuple[tuple[float, float], ...] = field(default=(), repr=False)

    @property
    def support(self) -> np.ndarray:
        """Cell indices with a nonzero weight, ascending."""
        return np.asarray(self.weights.coords[0])

    def __repr__(self) -> str:
        return (
            f"Bound(value={self.value:.6g} nats, primal={self.primal:.6g}, gap={self.gap:.3g}, "
            f"n={self.n:g}, k={self.k}, candidates={self.n_candidates}, "
            f"working set={self.n_working}, support={self.weights.nnz}, "
            f"iterations={self.iterations} (+{self.fw_iterations} Frank-Wolfe), "
            f"{self.solve_time:.2f} s, solver={self.solver}, status={self.status!r})"
        )


# ----------------------------------------------------------------------------- kernels
@numba.njit(cache=True, nogil=True)
def _leverages_kernel(Y: np.ndarray, Linv: np.ndarray, out: np.ndarray) -> None:
    """``out[i] = ||Linv @ Y[:, i]||^2`` for every column (Linv lower triangular, k x k)."""
    k, N = Y.shape
    y = np.empty(k)
    for i in range(N):
        for a in range(k):
            y[a] = Y[a, i]
        s = 0.0
        for a in range(k):
            v = 0.0
            for b in range(a + 1):
                v += Linv[a, b] * y[b]
            s += v * v
        out[i] = s


def _leverages(Y: np.ndarray, Linv: np.ndarray) -> np.ndarray:
    """``g_i = y_i^T M^-1 y_i`` for all columns of ``Y`` (k, N), with ``M^-1 = Linv^T Linv``."""
    out = np.empty(Y.shape[1])
    _leverages_kernel(Y, np.ascontiguousarray(np.tril(Linv)), out)
    return out


def _chol(M: np.ndarray) -> np.ndarray | None:
    """Lower Cholesky factor of a symmetric matrix, or None when it is not positive definite."""
    try:
        return np.linalg.cholesky(0.5 * (M + M.T))
    except np.linalg.LinAlgError:
        return None


def _inv_lower(L: np.ndarray) -> np.ndarray:
    """Inverse of a small lower-triangular matrix (LAPACK trtri; scipy's solve_triangular
    costs milliseconds of overhead per call)."""
    inv, info = scipy.linalg.lapack.dtrtri(np.asarray(L, dtype=np.float64), lower=1)
    if info != 0:
        return scipy.linalg.solve_triangular(L, np.eye(L.shape[0]), lower=True)
    return np.tril(inv)


def _top_sum(g: np.ndarray, n: float) -> tuple[float, float]:
    """Sum of the ``n`` largest entries of ``g >= 0`` (fractional ``n``) and the optimal ``mu``.

    ``min_{mu >= 0} mu n + sum_i max(0, g_i - mu)`` is piecewise linear with slope
    ``n - #{g_i > mu}``; its minimum is at ``mu = g_(m+1)`` (the (m+1)-th largest, m = floor n)
    and equals ``sum_{j <= m} g_(j) + (n - m) g_(m+1)``; when ``n >= N`` it is ``sum g`` at
    ``mu = 0``.
    """
    N = g.size
    m = math.floor(n)
    f = n - m
    if m >= N:
        return float(g.sum()), 0.0
    q = m + 1
    if q < N:
        top = g[np.argpartition(g, N - q)[N - q:]]
    else:
        top = g
    top = np.sort(top)[::-1]
    return float(top[:m].sum() + f * top[m]), float(top[m])


# ----------------------------------------------------------------------------- the polytope
class _Polytope:
    """Feasible weights ``{0 <= w <= 1, sum w <= n, nested count limits}`` over N candidates.

    Each limit family ``f`` gives every candidate a level ``level_f[i] in 0..J_f`` and caps
    ``caps_f`` (J_f,): ``sum_{i: level_f[i] >= j} w_i <= caps_f[j-1]`` for ``j = 1..J_f`` (the
    sets are nested, e.g. "farther than r_j from the start"). With multipliers ``nu >= 0`` for
    the sum and ``mu_f >= 0`` for the limits, the dual term of the relaxation is
    ``h = nu n + sum_f mu_f . caps_f + sum_i max(0, g_i - price_i)`` with
    ``price_i = nu + sum_f sum_{j <= level_f[i]} mu_fj``; ``min h = max_{v in polytope} g . v``
    (LP duality). ``h`` at *any* multipliers is an upper bound, so the multipliers may come from
    an inexact LP solver: ``support`` evaluates ``h`` exactly over all N candidates.
    """

    def __init__(self, n: float, N: int, levels: Any = (), caps: Any = ()) -> None:
        self.n = float(n)
        self.N = int(N)
        self.levels = [np.ascontiguousarray(lv, dtype=np.int64) for lv in levels]
        self.caps = [np.asarray(c, dtype=np.float64) for c in caps]
        # effective cap of a cell of level l: min(n, caps[0..l-1]) (the sets are nested)
        self.eff = [
            np.concatenate([[self.n], np.minimum.accumulate(np.minimum(c, self.n))])
            for c in self.caps
        ]

    @property
    def limited(self) -> bool:
        return bool(self.levels)

    def subset(self, idx: np.ndarray) -> _Polytope:
        return _Polytope(self.n, idx.size, [lv[idx] for lv in self.levels], self.caps)

    # -- dual side
    def price(self, nu: float, mus: list[np.ndarray], idx: Any = None) -> np.ndarray:
        """``price_i = nu + sum_f sum_{j <= level_f[i]} mu_fj`` (for ``idx`` or all cells)."""
        n_out = self.N if idx is None else len(idx)
        p = np.full(n_out, float(nu))
        for lv, mu in zip(self.levels, mus, strict=True):
            cum = np.concatenate([[0.0], np.cumsum(mu)])
            p += cum[lv if idx is None else lv[idx]]
        return p

    def h(self, g: np.ndarray, nu: float, mus: list[np.ndarray]) -> float:
        """The dual term at ``(nu, mus)``: an upper bound on ``max g . v`` over the polytope."""
        val = nu * self.n + sum(float(mu @ c) for mu, c in zip(mus, self.caps, strict=True))
        return val + float(np.maximum(g - self.price(nu, mus), 0.0).sum())

    # -- the linear program max g . v over the polytope
    def _reduce(self, g: np.ndarray) -> np.ndarray:
        """Cells that suffice for the LP: the top ``cap + 1`` cells by ``g`` of each level class.

        Cells with equal levels in every family are interchangeable in the constraints, so an
        optimal v uses the largest ``g`` of each class, at most ``cap = min(n, caps)`` of them.
        One more cell per class makes the reduced LP's multipliers optimal for the full LP too:
        that cell has ``v < 1`` or ties, so complementary slackness gives ``g <= price`` on it,
        hence on every dropped cell of its class (same price, smaller ``g``).
        """
        cls = np.zeros(self.N, np.int64)
        cap = np.full(self.N, self.n)
        for lv, eff in zip(self.levels, self.eff, strict=True):
            cls = cls * (eff.size) + lv
            cap = np.minimum(cap, eff[lv])
        order = np.lexsort((np.arange(self.N), -g, cls))
        cs = cls[order]
        first = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
        start_of = np.repeat(first, np.diff(np.r_[first, cs.size]))
        rank = np.arange(cs.size) - start_of
        keep = rank < np.ceil(cap[order] - 1e-9) + 1
        return np.sort(order[keep])

    def _rows(self, idx: np.ndarray) -> tuple[scipy.sparse.csr_array, np.ndarray]:
        """Constraint matrix (sum row, then each family's nested sets) and caps, cells ``idx``."""
        m = idx.size
        r_parts, c_parts = [np.zeros(m, np.int64)], [np.arange(m)]
        b = [self.n]
        off = 1
        for lv, c in zip(self.levels, self.caps, strict=True):
            lvl = lv[idx]
            tot = int(lvl.sum())
            cells = np.repeat(np.arange(m), lvl)
            starts = np.repeat(np.cumsum(lvl) - lvl, lvl)
            r_parts.append(off + np.arange(tot) - starts)
            c_parts.append(cells)
            b.extend(c.tolist())
            off += c.size
        rows = np.concatenate(r_parts)
        cols = np.concatenate(c_parts)
        A = scipy.sparse.csr_array((np.ones(rows.size), (rows, cols)), shape=(off, m))
        return A, np.asarray(b)

    def lp(self, g: np.ndarray, idx: Any = None) -> tuple[float, list[np.ndarray], np.ndarray]:
        """Multipliers ``(nu, mus)`` of ``max g . v`` over the polytope restricted to ``idx``
        (all cells by default) and a maximising vertex ``v`` (N,) (zero off ``idx``)."""
        from scipy.optimize import linprog

        cells = np.arange(self.N) if idx is None else np.asarray(idx)
        sub = cells[self.subset(cells)._reduce(g[cells])] if cells.size else cells
        v = np.zeros(self.N)
        if sub.size == 0:
            return 0.0, [np.zeros(c.size) for c in self.caps], v
        A, b = self._rows(sub)
        scale = float(g[sub].max()) or 1.0
        res = linprog(-g[sub] / scale, A_ub=A, b_ub=b, bounds=(0.0, 1.0), method="highs")
        if res.status != 0 or res.x is None:
            raise SolverError(f"HiGHS failed on the count-limit LP: {res.message}")
        y = np.maximum(-np.asarray(res.ineqlin.marginals), 0.0) * scale
        mus, off = [], 1
        for c in self.caps:
            mus.append(y[off: off + c.size])
            off += c.size
        v[sub] = res.x
        return float(y[0]), mus, v

    def support(self, g: np.ndarray) -> tuple[float, Any]:
        """An upper bound on ``max_{v in polytope} g . v`` (exact up to the LP's duals)."""
        if not self.limited:
            return _top_sum(g, self.n)
        nu, mus, _ = self.lp(g)
        return self.h(g, nu, mus), (nu, mus)

    def vertex(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A feasible maximiser of ``g . v`` (indices, weights); ties to the lowest index."""
        if not self.limited:
            return _top_vertex(g, self.n)
        _, _, v = self.lp(g)
        v = self.project(v)
        idx = np.flatnonzero(v)
        return idx, v[idx]

    def project(self, w: np.ndarray) -> np.ndarray:
        """Clip to [0, 1], drop interior-point zeros, scale down until every limit holds."""
        w = np.clip(np.asarray(w, dtype=np.float64), 0.0, 1.0)
        w[w < 1e-6] = 0.0
        factor = 1.0
        s = w.sum()
        if s > self.n:
            factor = self.n / s
        for lv, c in zip(self.levels, self.caps, strict=True):
            per = np.bincount(lv, weights=w, minlength=c.size + 1)
            sums = np.cumsum(per[::-1])[::-1][1: c.size + 1]  # sets level >= j, j = 1..J
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(sums > c, c / sums, 1.0)
            factor = min(factor, float(r.min()) if r.size else 1.0)
        if factor < 1.0:
            w *= factor * (1 - 1e-12)
        return w

    def is_feasible(self, w: np.ndarray, rtol: float = 1e-12) -> bool:
        if np.any(w < 0) or np.any(w > 1) or w.sum() > self.n * (1 + rtol):
            return False
        for lv, c in zip(self.levels, self.caps, strict=True):
            per = np.bincount(lv, weights=w, minlength=c.size + 1)
            sums = np.cumsum(per[::-1])[::-1][1: c.size + 1]
            if np.any(sums > c * (1 + rtol) + rtol):
                return False
        return True

    def uniform(self) -> np.ndarray:
        """A feasible design with every weight positive: ``w_i = min(1, n/N, caps_j/|S_j|)``."""
        w = np.full(self.N, min(1.0, self.n / self.N))
        for lv, c in zip(self.levels, self.caps, strict=True):
            per = np.bincount(lv, minlength=c.size + 1).astype(np.float64)
            size = np.cumsum(per[::-1])[::-1][1: c.size + 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(size > 0, c / size, np.inf)
            lim = np.concatenate([[np.inf], np.minimum.accumulate(ratio)])
            w = np.minimum(w, lim[lv])
        return w


def _dual_from_M(
    Yc: np.ndarray, M: np.ndarray, n: float | _Polytope, ridge: float
) -> tuple[float, float, np.ndarray, Any] | None:
    """Dual certificate at ``Z = t M^-1``: ``(value, logdet M, g, mu)`` or None if M is singular.

    With ``g_i = y_i^T M^-1 y_i`` and ``S = ridge tr M^-1 + top-n sum of g`` (with count limits:
    the polytope's dual term ``h`` at the LP's multipliers), the dual function minimised over the
    scale ``t`` (``t = k / S``) and ``nu = t mu`` is ``log det M + k log(S / k)``.
    """
    k = M.shape[0]
    L = _chol(M)
    if L is None:
        return None
    logdet = 2.0 * float(np.log(np.diag(L)).sum())
    Linv = _inv_lower(L)
    g = _leverages(Yc, Linv)
    if isinstance(n, _Polytope):
        top, mu = n.support(g)
    else:
        top, mu = _top_sum(g, n)
    S = ridge * float((Linv * Linv).sum()) + top
    if not (np.isfinite(S) and S > 0 and np.isfinite(logdet)):
        return None
    # S >= k holds exactly for every feasible w (S >= tr(M^-1 M(w)) = k); a value below k
    # can only be rounding, so the gap is clamped at zero.
    gap = k * math.log(max(S, k) / k)
    return logdet + gap, logdet, g, mu


def _moment(Yc: np.ndarray, idx: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """``ridge I + sum_j w_j y_idx[j] y_idx[j]^T`` (k x k)."""
    Ys = Yc[:, idx]
    M = (Ys * w) @ Ys.T
    M = 0.5 * (M + M.T)
    M[np.diag_indices_from(M)] += ridge
    return M


# ----------------------------------------------------------------------------- public helpers
def dual_value(Y: Any, Z: Any, nu: float, n: float, *, ridge: float = 0.0) -> float:
    """Lagrange dual function ``g(Z, nu)`` of the relaxation over all columns of ``Y`` (k, N).

    ``g(Z, nu) = -log det Z - k + ridge tr Z + nu n + sum_i max(0, y_i^T Z y_i - nu)`` is an
    upper bound on the relaxation's optimum for every ``Z`` positive definite and ``nu >= 0``.
    Returns ``+inf`` when ``Z`` is not positive definite.
    """
    Y = as_factor_matrix(Y)
    Z = np.asarray(Z, dtype=np.float64)
    k = Y.shape[0]
    if Z.shape != (k, k):
        raise PlanningError(f"Z must be {k} x {k}, got shape {Z.shape}")
    if not (np.isfinite(nu) and nu >= 0):
        raise PlanningError(f"nu must be >= 0 and finite, got {nu!r}")
    C = _chol(Z)
    if C is None:
        return math.inf
    logdetZ = 2.0 * float(np.log(np.diag(C)).sum())
    q = ((C.T @ Y) ** 2).sum(axis=0)  # y^T Z y with Z = C C^T
    return float(
        -logdetZ - k + ridge * np.trace(Z) + nu * n + np.maximum(q - nu, 0.0).sum()
    )


def certify_weights(
    Y: Any, weights: Any, n: float, *, candidates: Any = None, ridge: float = 0.0
) -> tuple[float, float]:
    """``(dual bound, primal)`` of the relaxation at any feasible weights (no solver involved).

    ``weights`` is a dense ``(L,)`` vector over the cells of ``Y`` (zero off ``candidates``)
    or a 1-D sparse array; it must satisfy ``0 <= w <= 1`` and ``sum w <= n``.
    """
    Y = as_factor_matrix(Y)
    n, ridge = _check_n_ridge(n, ridge)
    cand = _check_candidates(candidates, Y.shape[1])
    w = weights.toarray() if scipy.sparse.issparse(weights) else np.asarray(weights, float)
    if w.shape != (Y.shape[1],):
        raise PlanningError(f"weights must have shape ({Y.shape[1]},), got {w.shape}")
    if np.any(w < 0) or np.any(w > 1) or w.sum() > n * (1 + 1e-12):
        raise PlanningError("weights must satisfy 0 <= w <= 1 and sum(w) <= n")
    off = np.ones(Y.shape[1], bool)
    off[cand] = False
    if np.any(w[off] != 0):
        raise PlanningError("weights must be zero off the candidate cells")
    idx = np.flatnonzero(w)
    M = _moment(Y, idx, w[idx], ridge)
    out = _dual_from_M(np.ascontiguousarray(Y[:, cand]), M, n, ridge)
    if out is None:
        return math.inf, -math.inf
    return out[0], out[1]


# ----------------------------------------------------------------------------- validation
def _check_n_ridge(n: Any, ridge: Any) -> tuple[float, float]:
    try:
        n = float(n)
    except (TypeError, ValueError):
        raise PlanningError(f"n must be a number of cells, got {n!r}") from None
    if not (math.isfinite(n) and n > 0):
        raise PlanningError(f"n must be > 0 and finite, got {n!r}")
    try:
        ridge = float(ridge)
    except (TypeError, ValueError):
        raise PlanningError(f"ridge must be a number, got {ridge!r}") from None
    if not (math.isfinite(ridge) and ridge >= 0):
        raise PlanningError(f"ridge must be >= 0 and finite, got {ridge!r}")
    return n, ridge


def _check_candidates(candidates: Any, L: int) -> np.ndarray:
    if candidates is None:
        return np.arange(L, dtype=np.int64)
    arr = np.asarray(candidates)
    if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
        raise PlanningError(f"candidates must be a 1-D array of cell indices, got {arr!r}")
    if arr.size == 0:
        raise PlanningError("candidates is empty: no cell can be observed")
    if arr.min() < 0 or arr.max() >= L:
        raise PlanningError(f"candidates must be cell indices in [0, {L})")
    return np.unique(arr.astype(np.int64))


# ----------------------------------------------------------------------------- first order
def _line_search(lam: np.ndarray) -> float:
    """argmax over [0, 1] of ``sum_j log(1 + gamma (lam_j - 1))`` (concave), by bisection."""
    d = lam - 1.0

    def slope(gam: float) -> float:
        return float((d / (1.0 + gam * d)).sum())

    if slope(0.0) <= 0:
        return 0.0
    if np.all(lam > 1e-12) and slope(1.0) >= 0:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if slope(mid) > 0:
            lo = mid
        else:
            hi = mid
    return lo


def _top_vertex(g: np.ndarray, n: float) -> tuple[np.ndarray, np.ndarray]:
    """Maximiser of ``<g, s>`` over ``{0 <= s <= 1, sum s <= n}``: the top-n cells (ties low)."""
    N = g.size
    m = math.floor(n)
    f = n - m
    q = min(N, m + (1 if f > 0 else 0))
    if q < N:
        # stable order: largest g first, then lowest index
        part = np.argpartition(-g, q - 1)[:q]
        cut = g[part].min()
        pool = np.flatnonzero(g >= cut)
    else:
        pool = np.arange(N)
    order = pool[np.lexsort((pool, -g[pool]))][:q]
    s = np.ones(q)
    if q > m:
        s[-1] = f
    return order, s


# public names of the feasible set and its exact top-n oracle (the variance bound reuses them)
Polytope = _Polytope
top_sum = _top_sum
top_vertex = _top_vertex


def _frank_wolfe(
    Yc: np.ndarray, n: float | _Polytope, ridge: float, iters: int, tol: float
) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float]]]:
    """Frank-Wolfe with exact line search from a uniform design; returns (w, M, history).

    Each step costs one pass over the candidates (leverages, then the top-n vertex, or one LP
    on the reduced cells when there are count limits); the iterate's dual bound is free. Used to
    pick the working set and as the fallback certificate.
    """
    k, N = Yc.shape
    poly = n if isinstance(n, _Polytope) else None
    if poly is None:
        w = np.full(N, min(1.0, n / N))
        B = (Yc @ Yc.T) * w[0]
    else:
        w = poly.uniform()
        B = (Yc * w) @ Yc.T
    M = B + ridge * np.eye(k)
    hist: list[tuple[float, float]] = []
    for _ in range(iters):
        L = _chol(M)
        if L is None:
            break
        Linv = _inv_lower(L)
        g = _leverages(Yc, Linv)
        if poly is None:
            top, _ = _top_sum(g, n)
            idx, s = _top_vertex(g, n)
        else:
            nu, mus, v = poly.lp(g)
            top = poly.h(g, nu, mus)
            v = poly.project(v)
            idx = np.flatnonzero(v)
            s = v[idx]
        S = ridge * float((Linv * Linv).sum()) + top
        logdet = 2.0 * float(np.log(np.diag(L)).sum())
        hist.append((logdet + k * math.log(max(S, k) / k), logdet))
        if S - k <= tol:
            break
        Bs = (Yc[:, idx] * s) @ Yc[:, idx].T
        Ms = Bs + ridge * np.eye(k)
        A = Linv @ Ms @ Linv.T
        lam = np.linalg.eigvalsh(0.5 * (A + A.T))
        gam = _line_search(lam)
        if gam <= 0:
            break
        w *= 1.0 - gam
        w[idx] += gam * s
        B = (1.0 - gam) * B + gam * Bs
        M = B + ridge * np.eye(k)
    return w, M, hist


# ----------------------------------------------------------------------------- cvxpy
def _moment_map(Yw: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_array]:
    """``M(w) - C = Y diag(w) Y^T`` as an affine map of ``w`` without forming it:
    ``vec(M) = E @ (F @ w)`` (row-major), with ``F[(a, b), j] = y_aj y_bj`` over the k(k+1)/2
    pairs ``a <= b`` and ``E`` the constant 0/1 ``(k*k, k(k+1)/2)`` scatter into both halves."""
    k = Yw.shape[0]
    iu, ju = np.triu_indices(k)
    F = Yw[iu] * Yw[ju]  # (p, m)
    p = iu.size
    rows = np.concatenate([iu * k + ju, ju * k + iu])  # row-major positions a*k + b
    cols = np.concatenate([np.arange(p), np.arange(p)])
    keep = np.ones(rows.size, bool)
    keep[p:] = iu != ju  # diagonal entries once
    E = scipy.sparse.csr_array(
        (np.ones(int(keep.sum())), (rows[keep], cols[keep])), shape=(k * k, p)
    )
    return F, E


def _solve_restricted(
    Yw: np.ndarray, C: np.ndarray, n: float, solver: str, verbose: bool = False,
    rows: tuple[Any, np.ndarray] | None = None,
) -> tuple[np.ndarray | None, str]:
    """Relaxation over the columns of ``Yw`` (k, m) with constant term ``C``, in cvxpy.

    ``M(w) = C + sum_j w_j y_j y_j^T`` is an affine map of ``w``: its k(k+1)/2 distinct entries
    are ``F w`` with ``F[(a, b), j] = y_aj y_bj``, scattered into the k x k matrix by a constant
    0/1 matrix, so the model never forms ``Y diag(w) Y^T``. ``rows = (A, b)`` adds the linear
    count limits ``A w <= b``. Returns ``(w, status)``; ``w`` is None when the solver failed.
    """
    import cvxpy as cp

    limit_rows = rows
    k, m = Yw.shape
    F, E = _moment_map(Yw)
    w = cp.Variable(m)
    vecM = C.ravel() + E @ (F @ w)
    Mexpr = cp.reshape(vecM, (k, k), order="C")
    cons = [w >= 0, w <= 1, cp.sum(w) <= n]
    if limit_rows is not None and limit_rows[0].shape[0]:
        cons.append(limit_rows[0] @ w <= limit_rows[1])
    prob = cp.Problem(cp.Maximize(cp.log_det(Mexpr)), cons)
    opts = _CLARABEL_OPTS if solver == "CLARABEL" else (_SCS_OPTS,)
    value, _, status = _solve_in_turn(prob, w, [(solver, o) for o in opts], verbose=verbose)
    return value, status


def _solve_in_turn(prob: Any, w: Any, attempts: Any, *, verbose: bool | int = False
                  ) -> tuple[np.ndarray | None, str, str]:
    """Solve the cvxpy problem ``prob`` with each ``(solver, options)`` of ``attempts`` in turn.

    Returns ``(value of w, solver, status)`` of the first attempt whose status is ``optimal`` or
    ``optimal_inaccurate`` with a value of the variable ``w``; otherwise ``(None, "", status)``
    of the last attempt (``"error: ..."`` when it raised, ``"not run"`` without attempts).
    """
    import cvxpy as cp

    status = "not run"
    for solver, opts in attempts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "solution may be inaccurate"
                prob.solve(solver=solver, verbose=verbose, **opts)
        except (cp.error.SolverError, ValueError, ArithmeticError) as exc:
            status = f"error: {first_line(exc)[:80]}"
            continue
        status = str(prob.status)
        if w.value is not None and status in ("optimal", "optimal_inaccurate"):
            return np.asarray(w.value, dtype=np.float64), solver, status
    return None, "", status


def _feasible(w: np.ndarray, n: float) -> np.ndarray:
    """Project a solver's ``w`` onto the feasible set by clipping and scaling down."""
    w = np.clip(w, 0.0, 1.0)
    w[w < 1e-6] = 0.0  # interior-point zeros; dropping them keeps w feasible
    s = w.sum()
    if s > n:
        w *= n / s
    return w


# ----------------------------------------------------------------------------- main entry
def dopt_upper_bound(
    Y: Any,
    n: float,
    *,
    candidates: Any = None,
    ridge: float = 0.0,
    limits: Any = None,
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL",
    tol: float = 1e-3,
    max_iter: int = 30,
    fw_iter: int = 25,
    verbose: bool | int = False,
) -> Bound:
    """Certified upper bound on ``log det(ridge I + sum_{p in P} y_p y_p^T)`` over ``|P| <= n``.

    Parameters
    ----------
    Y : ``(k, L)`` factor matrix (ndarray or ``(component, cell)`` DataArray).
    n : the largest number of cells a plan may hold (> 0; fractional allowed).
    candidates : int array of the cell indices a plan may use; all ``L`` cells by default.
    ridge : ``>= 0``, added to the information matrix (as in ``fisher_information``).
    limits : optional nested count limits, a sequence of ``(values, thresholds, caps)``:
        ``values`` ``(L,)`` per cell (e.g. distance from the start), ``thresholds`` ascending
        ``(J,)``, ``caps`` ``(J,) >= 0``; every plan holds at most ``caps[j]`` cells with
        ``values >= thresholds[j]``. The relaxation gets the linear constraints
        ``sum_{values_i >= thresholds_j} w_i <= caps_j`` and the dual their multipliers.
    solver : conic solver for the working-set problems; the other one is the fallback.
    tol : target gap (nats) between the dual bound and the primal value.
    max_iter : column-generation rounds (each one cvxpy solve plus one pass over candidates).
    fw_iter : Frank-Wolfe passes over all candidates used to pick the first working set.

    Returns a :class:`Bound`; ``value`` is valid even when the solvers are inexact (it is a
    Lagrange dual value, not a solver's claim). Raises :class:`SolverError` only when no
    feasible weight with a finite ``log det`` could be found.
    """
    Y = as_factor_matrix(Y)
    k, L = Y.shape
    n, ridge = _check_n_ridge(n, ridge)
    cand = _check_candidates(candidates, L)
    poly = _polytope_from_limits(n, cand, limits, L)
    return _relaxation(Y, cand, poly, ridge, solver=solver, tol=tol, max_iter=max_iter,
                       fw_iter=fw_iter, verbose=verbose)


def _polytope_from_limits(n: float, cand: np.ndarray, limits: Any, L: int) -> _Polytope:
    """Validate ``limits`` (see :func:`dopt_upper_bound`) and give each candidate its levels."""
    if limits is None:
        return _Polytope(n, cand.size)
    levels, caps = [], []
    for f, item in enumerate(limits):
        try:
            values, thr, cap = item
        except (TypeError, ValueError):
            raise PlanningError(
                f"limits[{f}] must be a (values, thresholds, caps) triple"
            ) from None
        values = np.asarray(values, dtype=np.float64)
        thr = np.atleast_1d(np.asarray(thr, dtype=np.float64))
        cap = np.atleast_1d(np.asarray(cap, dtype=np.float64))
        if values.shape != (L,):
            raise PlanningError(f"limits[{f}] values must have shape ({L},), got {values.shape}")
        if thr.ndim != 1 or thr.shape != cap.shape:
            raise PlanningError(f"limits[{f}] thresholds and caps must be 1-D of equal length")
        if not (np.all(np.isfinite(thr)) and np.all(np.diff(thr) > 0)):
            raise PlanningError(f"limits[{f}] thresholds must be finite and strictly ascending")
        if not (np.all(np.isfinite(cap)) and np.all(cap >= 0)):
            raise PlanningError(f"limits[{f}] caps must be finite and >= 0")
        if np.any(np.isnan(values[cand])):
            raise PlanningError(f"limits[{f}] values must not be NaN on the candidates")
        levels.append(np.searchsorted(thr, values[cand], side="right"))
        caps.append(cap)
    return _Polytope(n, cand.size, levels, caps)


def _relaxation(
    Y: np.ndarray,
    cand: np.ndarray,
    poly: _Polytope,
    ridge: float,
    *,
    solver: str = "CLARABEL",
    tol: float = 1e-3,
    max_iter: int = 30,
    fw_iter: int = 25,
    verbose: bool | int = False,
) -> Bound:
    """:func:`dopt_upper_bound` on validated input: candidates ``cand``, feasible set ``poly``."""
    t0 = time.perf_counter()
    k, L = Y.shape
    n = poly.n
    solver = str(solver).upper()
    if solver not in _SOLVERS:
        raise PlanningError(f"solver must be one of {_SOLVERS}, got {solver!r}")
    if not (math.isfinite(tol) and tol > 0):
        raise PlanningError(f"tol must be > 0 and finite, got {tol!r}")
    N = cand.size
    Yc = np.ascontiguousarray(Y[:, cand])
    limited = poly.limited
    what: float | _Polytope = poly if limited else n

    def result(value, primal, idx, wv, status, n_working=0, iters=0, fw=0, used="none",
               hist=()) -> Bound:
        nz = wv > 0
        weights = scipy.sparse.coo_array(
            (wv[nz], (cand[idx[nz]],)), shape=(L,)
        )
        gap = 0.0 if value == primal else value - primal
        return Bound(
            value=float(value), primal=float(primal), gap=float(gap), weights=weights, n=n,
            k=k, ridge=ridge, n_candidates=N, n_working=int(n_working), iterations=iters,
            fw_iterations=fw, solve_time=time.perf_counter() - t0, solver=used,
            status=status, history=tuple(hist),
        )

    # singular: fewer than k independent candidates and no ridge -> every M(w) is singular
    G = Yc @ Yc.T
    if ridge == 0 and np.linalg.matrix_rank(G) < k:
        return result(-math.inf, -math.inf, np.arange(0), np.zeros(0), "singular")
    if n >= N and poly.is_feasible(np.ones(N)):
        # w = 1 on every candidate is feasible, hence optimal (log det is monotone)
        M = G + ridge * np.eye(k)
        out = _dual_from_M(Yc, M, what, ridge)
        if out is None:
            raise SolverError("information matrix of all candidates is not positive definite")
        return result(out[1], out[1], np.arange(N), np.ones(N), "trivial")

    # 1. Frank-Wolfe warm start over all candidates
    # with count limits each Frank-Wolfe step solves an LP: a few steps pick the working set
    fw_n = min(fw_iter, _FW_LIMITED) if limited else fw_iter
    w_fw, M_fw, hist = _frank_wolfe(Yc, what, ridge, fw_n, max(tol, 0.01))
    fw_done = len(hist)
    out = _dual_from_M(Yc, M_fw, what, ridge)
    if out is None:
        raise SolverError(
            "Frank-Wolfe warm start lost positive definiteness; no feasible design to certify"
        )
    best_val, best_primal = out[0], out[1]
    fw_support = np.flatnonzero(w_fw)
    best_w = (fw_support, w_fw[fw_support])
    g, M_ref = out[2], M_fw

    # 2. column generation on a working set, solved in cvxpy
    nc = math.ceil(n)
    m0 = min(N, 2 * nc + 20 * k)
    batch = max(nc, 10 * k)
    # first working set: the Frank-Wolfe iterate's main support plus the top leverages
    # (with count limits: the top reduced leverages g - price, which respect the limits)
    heavy = np.flatnonzero(w_fw >= 1e-3)
    if heavy.size > 2 * m0:
        heavy = heavy[np.argsort(-w_fw[heavy], kind="stable")[: 2 * m0]]
    if limited:
        nu, mus = out[3]
        score = g - poly.price(nu, mus)
        first = np.argsort(-score, kind="stable")[:m0]
    else:
        first = _top_vertex(g, m0)[0]
    W = np.union1d(first, heavy)
    status_msgs: list[str] = []
    used = "Frank-Wolfe"
    iters = 0
    for it in range(max_iter):
        if it > 0 and best_val - best_primal <= tol:
            break
        iters = it + 1
        Lr = _chol(M_ref)
        A = _inv_lower(Lr)  # congruence: A M_ref A^T = I keeps the conic problem well scaled
        Yw = A @ Yc[:, W]
        C = ridge * (A @ A.T)
        rows = poly.subset(W)._rows(np.arange(W.size)) if limited else None
        if rows is not None:  # the sum row is already in the model
            rows = (rows[0][1:], rows[1][1:])
        wW = None
        for s in (solver,) + tuple(x for x in _SOLVERS if x != solver):
            wW, st = _solve_restricted(Yw, C, n, s, verbose > 1, rows=rows)
            if wW is not None:
                used = s
                break
            status_msgs.append(f"{s}: {st}")
        if wW is None:
            break
        if limited:
            wW = poly.subset(W).project(wW)
        else:
            wW = _feasible(wW, n)
        nzw = wW > 0
        M = _moment(Yc, W[nzw], wW[nzw], ridge)
        out = _dual_from_M(Yc, M, what, ridge)
        if out is None:
            status_msgs.append("working-set solution singular")
            break
        val, primal, g, _ = out
        if verbose:
            print(f"[dopt] round {iters}: |W|={W.size} value={val:.8g} primal={primal:.8g} "
                  f"gap={val - primal:.3g} ({used})")
        hist.append((val, primal))
        best_val = min(best_val, val)
        if primal > best_primal:
            best_primal, best_w = primal, (W[nzw], wW[nzw])
        M_ref = M
        if best_val - best_primal <= tol:
            break
        inW = np.zeros(N, bool)
        inW[W] = True
        if limited:
            # violators: positive reduced cost at the working set's LP multipliers
            nu, mus, _ = poly.lp(g, W)
            rc = g - poly.price(nu, mus)
            viol = np.flatnonzero((rc > 1e-9 * max(float(g.max()), 1e-300)) & ~inW)
            key = rc
        else:
            # violators: cells outside W whose leverage beats W's marginal (ceil(n)-th) one
            gW = np.sort(g[W])[::-1]
            tau = gW[nc - 1] if W.size >= nc else 0.0
            viol = np.flatnonzero((g > tau * (1 + 1e-9)) & ~inW)
            key = g
        if viol.size == 0:
            status_msgs.append("no violator left: working-set solve is inexact")
            break
        if viol.size > batch:
            viol = viol[np.argsort(-key[viol], kind="stable")[:batch]]
        W = np.union1d(W, viol)

    gap = best_val - best_primal
    status = "optimal" if gap <= tol else "inexact"
    if status == "inexact":
        note = "; ".join(status_msgs[-3:])
        warnings.warn(
            f"D-optimal bound gap {gap:.3g} nats > tol={tol:g} after {iters} rounds "
            f"({note or 'iteration limit'}); the bound is still valid",
            ConvergenceWarning,
            stacklevel=3,
        )
    idx, wv = best_w
    return result(best_val, best_primal, idx, wv, status, W.size, iters, fw_done, used, hist)


# public name of the relaxation on validated input (the certificates solve it piece by piece)
solve_relaxation = _relaxation
