"""Certified upper bounds on the Fisher information of any plan (issue #5).

The paper quotes only the worst-case guarantee ``1/2 (1 - 1/e)`` of its greedy planner. This
module measures the real gap. Every plan the planners can return is a set of at most ``n`` cells
out of a candidate set, so its Fisher information ``log det(ridge I + sum_{p in P} y_p y_p^T)`` is
at most the optimum of the continuous D-optimal design relaxation (Joshi & Boyd, "Sensor
selection via convex optimization")::

    maximise  log det M(w),   M(w) = ridge I + sum_i w_i y_i y_i^T
    subject to  0 <= w <= 1,  sum_i w_i <= n.

The relaxation is modelled in cvxpy on a small working set of cells that grows by column
generation (the cells whose leverage ``g_i = y_i^T M(w)^-1 y_i`` violates optimality), warm
started by a vectorised Frank-Wolfe over all candidates. The reported bound does not trust any
solver: it is the Lagrange dual function evaluated at ``Z = t M(w)^-1`` with the best scale ``t``
and multiplier ``nu`` (closed forms), which bounds the relaxation for *any* ``w``::

    log det M*  <=  log det M(w) + k log(S / k),
    S = ridge tr M(w)^-1 + (sum of the n largest g_i over all candidates).

``plan_bound`` tightens the relaxation with the path's geometry (distance limits from the start
and from a cover of the path's possible midpoints; linear count limits whose multipliers enter
the dual). See ``docs/certificate.md`` for the derivations and the proofs that the plan bound
covers every plan of the greedy planner and the baselines.
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

from .._validation import as_factor_matrix
from ..errors import ConvergenceWarning, PlanningError, SolverError

__all__ = [
    "Bound",
    "PlanCertificate",
    "dopt_upper_bound",
    "plan_bound",
    "dual_value",
    "certify_weights",
]

_SOLVERS = ("CLARABEL", "SCS")
# Clarabel settings tried in turn (DESIGN.md: its defaults fail on unscaled problems; on the
# congruence-scaled working-set problems equilibration is what most often breaks it)
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


@dataclass(frozen=True, eq=False)
class PlanCertificate:
    """Upper bound on the Fisher information of every plan from ``start`` within ``budget``.

    ``bound = max(initial_information, relaxation.value)``: a plan of the greedy planner is
    either its forced initial set (information ``initial_information``) or a set of at most
    ``n_max`` cells within ``budget`` of the start (covered by the relaxation). ``gap =
    bound - information`` (nats, >= 0 for every feasible plan) and ``volume_ratio =
    exp(-gap / k)``: the plan's information-ellipsoid volume relative to the bound's, per
    dimension (1 = certified optimal). ``online_bound`` is the submodularity bound
    ``f(P) + sum of the n_max largest marginal gains at P`` (see docs/certificate.md), when a
    plan was given; it is reported beside and ``bound`` already takes the smaller of the two.
    ``tightened``: the relaxation had the path's distance limits (docs/certificate.md §6);
    ``leaves``: the final squares of the midpoint cover ``(row0, col0, side, value)``, whose
    largest value is ``relaxation.value`` (empty without the cover).

    ``criterion`` is what the bound bounds: always ``"fisher"`` (``log det(ridge I + sum y
    y^T)``). ``plan_criterion`` is what the plan was chosen for (``None`` for a baseline, which
    optimises nothing and is judged by its Fisher information as in the paper; ``"fisher
    (posterior)"`` for a Fisher greedy on the fold-in's posterior). When the two differ
    (``comparable`` is False) ``information`` is still the plan's Fisher information but
    ``gap`` and ``volume_ratio`` are NaN: a gap between different criteria means nothing.
    """

    bound: float
    information: float | None
    gap: float | None
    volume_ratio: float | None
    n_max: int
    n_candidates: int
    k: int
    start: int
    budget: float
    ridge: float
    metric: str
    initial_information: float
    relaxation: Bound
    online_bound: float | None = None
    tightened: bool = False
    leaves: tuple[tuple[float, float, float, float], ...] = field(default=(), repr=False)
    criterion: str = "fisher"
    plan_criterion: str | None = None
    greedy_information: float | None = None
    refined_information: float | None = None
    refine_moves: int | None = None
    path_bound: float | None = None  # the path-aware relaxation's dual bound (path_aware=True)

    @property
    def plan_slack(self) -> float | None:
        """``refined_information - greedy_information`` (nats, >= 0): what a local search on
        the plan found; the part of the gap due to the planner."""
        if self.greedy_information is None or self.refined_information is None:
            return None
        if self.refined_information == self.greedy_information:
            return 0.0
        return float(self.refined_information - self.greedy_information)

    @property
    def bound_slack(self) -> float | None:
        """``bound - refined_information`` (nats, >= 0): the part of the gap nothing found yet,
        an upper limit on what the relaxation over-counts plus what the search missed."""
        if self.refined_information is None:
            return None
        return _gap(self.bound, self.refined_information, self.k)[0]

    @property
    def comparable(self) -> bool:
        """The plan was chosen for the bounded criterion (or is a baseline): the gap means
        something. False for a-optimal, gp-variance and posterior-Fisher plans."""
        return self.plan_criterion in (None, self.criterion)

    @property
    def relative_gap(self) -> float | None:
        """``gap / |bound|`` when both are finite (a unit-free view of the gap)."""
        if self.gap is None or not np.isfinite(self.gap) or not np.isfinite(self.bound) \
                or self.bound == 0:
            return None
        return self.gap / abs(self.bound)

    def __repr__(self) -> str:
        lines = [
            f"PlanCertificate(start={self.start}, budget={self.budget:g} "
            f"({self.metric}), k={self.k}, ridge={self.ridge:g})",
            f"  upper bound          {self.bound:.6g} nats (on the {self.criterion} "
            f"information of any plan)",
        ]
        if self.information is not None and not self.comparable:
            lines += [
                f"  plan information     {self.information:.6g} nats (Fisher)",
                f"  no gap: the plan was chosen for the {self.plan_criterion} criterion, the "
                f"bound is on {self.criterion}",
            ]
        elif self.information is not None:
            lines += [
                f"  plan information     {self.information:.6g} nats",
                f"  certified gap        {self.gap:.4g} nats",
                f"  volume ratio         {self.volume_ratio:.4f} (per dimension, 1 = optimal)",
            ]
            if self.refined_information is not None:
                lines += [
                    f"  greedy information   {self.greedy_information:.6g} nats",
                    f"  refined information  {self.refined_information:.6g} nats "
                    f"({self.refine_moves} moves)",
                    f"  gap split            plan slack {self.plan_slack:.4g} + bound slack "
                    f"{self.bound_slack:.4g} nats",
                ]
        lines += [
            f"  relaxation           {self.relaxation.value:.6g} (primal "
            f"{self.relaxation.primal:.6g}, status {self.relaxation.status})",
            f"  initial set          {self.initial_information:.6g} nats",
        ]
        if self.online_bound is not None:
            lines.append(f"  online bound         {self.online_bound:.6g} nats")
        lines.append(
            f"  at most {self.n_max} cells out of {self.n_candidates} candidates "
            f"within the budget"
        )
        if self.tightened:
            lines.append(f"  tightened: distance limits, midpoint cover of "
                         f"{len(self.leaves)} squares")
        return "\n".join(lines)

    def _repr_html_(self) -> str:
        rows = [("upper bound (nats)", f"{self.bound:.6g}"),
                ("bounded criterion", self.criterion)]
        if self.information is not None and not self.comparable:
            rows += [("plan criterion", str(self.plan_criterion)),
                     ("plan Fisher information (nats)", f"{self.information:.6g}"),
                     ("certified gap", "none: different criteria")]
        elif self.information is not None:
            rows += [
                ("plan information (nats)", f"{self.information:.6g}"),
                ("certified gap (nats)", f"{self.gap:.4g}"),
                ("volume ratio (per dim.)", f"{self.volume_ratio:.4f}"),
            ]
            if self.refined_information is not None:
                rows += [
                    ("greedy / refined information (nats)",
                     f"{self.greedy_information:.6g} / {self.refined_information:.6g}"),
                    ("plan slack / bound slack (nats)",
                     f"{self.plan_slack:.4g} / {self.bound_slack:.4g}"),
                ]
        rows += [
            ("relaxation value / primal", f"{self.relaxation.value:.6g} / "
                                          f"{self.relaxation.primal:.6g}"),
            ("initial set (nats)", f"{self.initial_information:.6g}"),
            ("max cells / candidates", f"{self.n_max} / {self.n_candidates}"),
            ("start, budget", f"{self.start}, {self.budget:g} ({self.metric})"),
        ]
        if self.online_bound is not None:
            rows.append(("online bound (nats)", f"{self.online_bound:.6g}"))
        body = "".join(f"<tr><td>{a}</td><td>{b}</td></tr>" for a, b in rows)
        return f"<table><caption>PlanCertificate</caption>{body}</table>"


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
    w = cp.Variable(m)
    vecM = C.ravel() + E @ (F @ w)
    Mexpr = cp.reshape(vecM, (k, k), order="C")
    cons = [w >= 0, w <= 1, cp.sum(w) <= n]
    if limit_rows is not None and limit_rows[0].shape[0]:
        cons.append(limit_rows[0] @ w <= limit_rows[1])
    prob = cp.Problem(cp.Maximize(cp.log_det(Mexpr)), cons)
    attempts = _CLARABEL_OPTS if solver == "CLARABEL" else (_SCS_OPTS,)
    status = "not run"
    for opts in attempts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "solution may be inaccurate"
                prob.solve(solver=solver, verbose=verbose, **opts)
        except (cp.error.SolverError, ValueError, ArithmeticError) as exc:
            status = f"error: {str(exc).splitlines()[0][:80]}"
            continue
        status = str(prob.status)
        if w.value is not None and status in ("optimal", "optimal_inaccurate"):
            return np.asarray(w.value, dtype=np.float64), status
    return None, status


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


# ----------------------------------------------------------------------------- plan bound
def plan_bound(
    Y: Any,
    region: Any,
    start: Any,
    budget: float,
    *,
    ridge: float = 0.0,
    plan: Any = None,
    metric: Literal["grid", "km"] = "grid",
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL",
    tol: float = 1e-3,
    tighten: bool = True,
    cover: int = 2,
    max_pieces: int = 40,
    refine: bool | dict[str, Any] = True,
    path_aware: bool | dict[str, Any] = False,
) -> PlanCertificate:
    """Upper bound on the Fisher information of every plan from ``start`` within ``budget``.

    Every plan of ``plan_greedy`` (any cost, since each is the length of a path from the start
    through all the plan's cells), ``transect`` and ``random_walk`` is either the greedy's forced
    initial set (start plus its k-1 nearest cells) or the cells visited by a path from the start
    of length ``<= budget``. The latter are at most ``n_max = floor(budget / d_min) + 1`` cells
    within ``budget`` of the start (``d_min`` = the smallest distance between two candidate
    cells, 1 grid unit for ``metric="grid"``), so ``bound = max(I(initial set), relaxation)``.

    With ``tighten=True`` (default) the relaxation also gets the path's *distance limits*: at
    most ``floor((budget - r) / d_min) + 1`` cells at distance ``>= r`` from the start, for a
    ladder of radii ``r``; and for ``metric="grid"`` (and ``budget >= 2``) the *midpoint cover*:
    the path's midpoint lies in one of the squares of side ``budget / (2 cover)`` that tile the
    disk of radius ``budget / 2`` around the start, the plan then lies within ``budget / 2`` of
    that square and holds at most ``floor(budget - 2 s) + 2`` cells at distance ``>= s`` from it.
    The bound is the maximum of one relaxation per square; the square with the largest bound is
    split into four while at most ``max_pieces`` relaxations have been solved. ``tighten=False``
    gives the plain disk relaxation. When the plan is given, the submodularity online bound is
    computed too and the smaller one is kept. Proofs in docs/certificate.md.

    The bound is on the **Fisher** information (``criterion="fisher"``). For a plan chosen for
    another criterion (``plan.criterion`` ``"a-optimal"`` / ``"gp-variance"``, or
    ``plan.posterior``) the certificate reports the plan's Fisher information but
    ``gap = volume_ratio = nan``.

    **Gap split.** For a Fisher greedy plan (``metric="grid"``) the certificate also reports
    ``greedy_information`` (the plan before refinement), ``refined_information`` (after
    :func:`~lrm_cvx.planning.refine.refine`: the plan's own refinement when it was refined,
    else one run here when ``refine`` is true; a dict is passed to it as keyword arguments),
    ``plan_slack = refined - greedy`` and ``bound_slack = bound - refined``; the online bound
    at the refined plan is used as well (valid at any set).

    ``path_aware=True`` (opt-in, grid metric) also computes the path-aware relaxation of
    :mod:`lrm_cvx.planning.relaxation` (a dict passes options to ``path_relaxation_bound``)
    and keeps the smaller valid bound (``path_bound``); if it fails, a warning says the disk
    bound is used.

    ``budget`` is in grid units (``metric="grid"``) or km (``metric="km"``).
    """
    from ..information import fisher_information
    from .greedy import _check_budget, initial_cells
    from .plan import check_region

    region = check_region(region)
    Y = as_factor_matrix(Y, region)
    k, L = Y.shape
    start = region.resolve_cell(start, "start")
    budget = _check_budget(budget)
    _, ridge = _check_n_ridge(1.0, ridge)
    if metric not in ("grid", "km"):
        raise PlanningError(f"metric must be 'grid' or 'km', got {metric!r}")
    if not isinstance(cover, (int, np.integer)) or cover < 1:
        raise PlanningError(f"cover must be an integer >= 1, got {cover!r}")
    if not isinstance(max_pieces, (int, np.integer)) or max_pieces < 1:
        raise PlanningError(f"max_pieces must be an integer >= 1, got {max_pieces!r}")

    dist = np.asarray(region.distance(start, np.arange(L), metric=metric), dtype=np.float64)
    slack = _DIST_EPS * max(1.0, budget)
    Bp = budget + slack  # every path cost the planners accept is <= Bp
    cand = np.flatnonzero(dist <= Bp)
    if metric == "grid":
        d_min = 1.0
    else:
        d_min = _min_spacing_km(region, cand)
    n_max = min(cand.size, math.floor(Bp / d_min) + 1) if d_min > 0 else cand.size

    init = np.asarray(initial_cells(region, start, k), dtype=np.int64)
    init_info = float(fisher_information(Y, init, ridge=ridge))
    opts = {"solver": solver, "tol": tol}
    leaves: list[tuple[float, float, float, float]] = []
    start_lim = _start_limit(Bp, d_min, n_max) if tighten and math.isfinite(d_min) else None
    start_lv = (
        np.searchsorted(start_lim[0], dist[cand], side="right") if start_lim else None
    )
    if tighten and metric == "grid" and Bp >= 2.0:
        centre = region.grid_index[start].astype(np.float64)
        relax, leaves = _midpoint_cover(
            Y, region, cand, start_lv, start_lim, centre, Bp, n_max, ridge, cover,
            max_pieces, init_info, opts,
        )
    else:
        levels, caps = ([start_lv], [start_lim[1]]) if start_lim else ([], [])
        relax = _relaxation(Y, cand, _Polytope(n_max, cand.size, levels, caps), ridge, **opts)
    bound = max(init_info, relax.value)
    path_value = None
    if path_aware:
        path_value = _path_aware(Y, region, start, budget, ridge, metric, path_aware)
        if path_value is not None:
            bound = min(bound, max(init_info, path_value))

    information = gap = ratio = online = None
    if plan is not None:
        cells = np.asarray(plan.cells, dtype=np.int64)
        _check_plan_feasible(cells, init, cand, n_max, plan, budget, slack)
        _check_plan_limits(cells, init, region, dist, start_lim, leaves, Bp, n_max, plan)
        information = float(fisher_information(Y, cells, ridge=ridge))
        online = _online_bound(Y, cells, cand, n_max, ridge, information)
        if online is not None:
            bound = min(bound, max(init_info, online))
        plan_criterion = _plan_criterion(plan)
        greedy_info, refined_info, n_moves, rcells = _refined(
            plan, Y, region, refine, metric, plan_criterion, information)
        if refined_info is not None and refined_info > information:
            online_r = _online_bound(Y, rcells, cand, n_max, ridge, refined_info)
            if online_r is not None:
                bound = min(bound, max(init_info, online_r))
        if plan_criterion in (None, "fisher"):
            gap, ratio = _gap(bound, information, k)
        else:  # a bound on Fisher information says nothing of another criterion's gap
            gap, ratio = math.nan, math.nan
    return PlanCertificate(
        bound=float(bound), information=information, gap=gap, volume_ratio=ratio,
        n_max=int(n_max), n_candidates=int(cand.size), k=k, start=int(start), budget=budget,
        ridge=ridge, metric=metric, initial_information=init_info, relaxation=relax,
        online_bound=online, tightened=bool(tighten), leaves=tuple(leaves),
        criterion="fisher", plan_criterion=_plan_criterion(plan) if plan is not None else None,
        greedy_information=greedy_info if plan is not None else None,
        refined_information=refined_info if plan is not None else None,
        refine_moves=n_moves if plan is not None else None,
        path_bound=path_value,
    )


def _path_aware(Y: np.ndarray, region: Any, start: int, budget: float, ridge: float,
                metric: str, opts: Any) -> float | None:
    """The path-aware relaxation's dual bound, or None (with a warning) when it fails."""
    from . import relaxation

    if metric != "grid":
        warnings.warn("path_aware=True needs metric='grid'; the disk bound is used",
                      UserWarning, stacklevel=3)
        return None
    kw = dict(opts) if isinstance(opts, dict) else {}
    try:
        return float(relaxation.path_relaxation_bound(Y, region, start, budget, ridge=ridge,
                                                      **kw).value)
    except (PlanningError, SolverError) as exc:
        warnings.warn(f"path-aware relaxation failed ({exc}); the disk bound (looser) is used",
                      UserWarning, stacklevel=3)
        return None



def _refined(plan: Any, Y: np.ndarray, region: Any, refine: Any, metric: str,
             plan_criterion: str | None, information: float
             ) -> tuple[float | None, float | None, int | None, np.ndarray]:
    """``(greedy information, refined information, moves, refined cells)`` of a Fisher
    greedy plan, or ``(None, None, None, plan cells)``."""
    cells = np.asarray(plan.cells, dtype=np.int64)
    if plan_criterion != "fisher" or metric != "grid":
        return None, None, None, cells
    done = getattr(plan, "refinement", None) or {}
    if done:
        return float(done["information_before"]), float(information), int(done["moves"]), cells
    if refine is False or refine is None or not hasattr(plan, "cost_function"):
        return None, None, None, cells
    from .refine import refine as _refine

    opts = dict(refine) if isinstance(refine, dict) else {}
    better = _refine(plan, Y, region, **opts)
    moves = int(better.refinement.get("moves", 0)) if better is not plan else 0
    return (float(information), max(float(better.information), float(information)), moves,
            np.asarray(better.cells, dtype=np.int64))


def _plan_criterion(plan: Any) -> str | None:
    """The criterion a plan was chosen for, canonical (``None``: a baseline)."""
    crit = getattr(plan, "criterion", None)
    if crit is None:
        return None
    from ..information import CRITERION_REGISTRY

    crit = CRITERION_REGISTRY.canonical(crit, "plan.criterion")
    if crit == "fisher" and getattr(plan, "posterior", False):
        return "fisher (posterior)"
    return crit


# ----------------------------------------------------------------------------- path limits
_NUDGE = 1e-6  # radii sit this far (in d_min) inside their cap's interval, away from rounding


def _cap_ladder(lo: int, hi: int, count: int = 10) -> np.ndarray:
    """About ``2 count`` integer caps in ``[lo, hi)``: geometric (dense near ``lo``) + linear."""
    if hi <= lo:
        return np.zeros(0, np.int64)
    geo = np.geomspace(lo, max(hi - 1, lo), count)
    lin = np.linspace(lo, max(hi - 1, lo), count)
    return np.unique(np.round(np.concatenate([geo, lin])).astype(np.int64))


def _start_limit(Bp: float, d_min: float, n_max: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Distance limits from the start: ``(thresholds, caps)``, ascending thresholds.

    A path of length ``<= Bp`` from the start holds at most ``floor((Bp - r) / d_min) + 1`` cells
    at distance ``>= r`` from the start. For a cap ``c`` the largest such set has ``r`` just
    above ``Bp - c d_min``; the cap is recomputed from ``r`` (not assumed), and the threshold is
    nudged up so that float distances cannot put a cell into a set it does not belong to.
    """
    thr, caps = [], []
    for c in _cap_ladder(1, n_max)[::-1]:
        r = Bp - (c - _NUDGE) * d_min
        if r <= 0:
            continue
        cap = math.floor((Bp - r) / d_min) + 1
        thr.append(r * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    if not thr:
        return None
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)


def _square_limit(Bp: float, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance limits from the midpoint's square: at most ``floor(Bp - 2 s) + 2`` cells at
    distance ``>= s > 0`` from it (grid units, ``d_min = 1``); ascending thresholds."""
    thr, caps = [], []
    for c in _cap_ladder(2, n_max)[::-1]:
        s = (Bp - c + 1 + 2 * _NUDGE) / 2
        if s <= 0:
            continue
        cap = math.floor(Bp - 2 * s) + 2
        thr.append(s * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)


def _square_distance(points: np.ndarray, r0: float, c0: float, h: float) -> np.ndarray:
    """Euclidean distance (grid units) from ``points`` (m, 2) to the square ``[r0, r0+h] x
    [c0, c0+h]`` (0 inside)."""
    pr, pc = points[:, 0], points[:, 1]
    dr = np.maximum(np.maximum(r0 - pr, pr - (r0 + h)), 0.0)
    dc = np.maximum(np.maximum(c0 - pc, pc - (c0 + h)), 0.0)
    return np.hypot(dr, dc)


def _cover_squares(
    centre: np.ndarray, radius: float, r0: float, c0: float, h: float, parts: int
) -> list[tuple[float, float, float]]:
    """The ``parts x parts`` sub-squares of ``[r0, r0+h] x [c0, c0+h]`` meeting the disk
    ``B(centre, radius)``, as ``(r0, c0, side)``."""
    s = h / parts
    out = []
    for a in range(parts):
        for b in range(parts):
            q = (r0 + a * s, c0 + b * s, s)
            if _square_distance(centre[None, :], *q)[0] <= radius:
                out.append(q)
    return out


def _midpoint_cover(
    Y: np.ndarray, region: Any, cand: np.ndarray, start_lv: np.ndarray | None,
    start_lim: tuple[np.ndarray, np.ndarray] | None, centre: np.ndarray, Bp: float,
    n_max: int, ridge: float, cover: int, max_pieces: int, floor_value: float,
    opts: dict[str, Any],
) -> tuple[Bound, list[tuple[float, float, float, float]]]:
    """Max over a cover of the possible path midpoints of the relaxation restricted to each piece.

    The midpoint lies in the closed disk ``B(start, Bp / 2)``, tiled by squares of side
    ``Bp / (2 cover)`` with a corner at the start. Piece ``Q``: the candidates within ``Bp / 2``
    of ``Q``, the start's distance limits and ``Q``'s distance limits. The piece with the largest
    bound is split into four (children keep ``min(own, parent)``: both bound the midpoints in
    the child) until ``max_pieces`` relaxations have been solved or it is below ``floor_value``
    (the initial set's information, which the certificate takes the maximum with anyway).
    Returns the largest piece's :class:`Bound` and every final piece ``(r0, c0, side, value)``.
    """
    pos = region.grid_index[cand].astype(np.float64)
    sq_thr, sq_caps = _square_limit(Bp, n_max)
    half = Bp / 2

    def solve(q: tuple[float, float, float]) -> Bound:
        dq = _square_distance(pos, *q)
        sel = np.flatnonzero(dq <= half * (1 + 1e-12) + 1e-12)
        levels = [np.searchsorted(sq_thr, dq[sel], side="right")]
        caps = [sq_caps]
        if start_lv is not None:
            levels.append(start_lv[sel])
            caps.append(start_lim[1])
        poly = _Polytope(n_max, sel.size, levels, caps)
        return _relaxation(Y, cand[sel], poly, ridge, **opts)

    side = Bp / cover  # 2 cover squares across the disk's diameter Bp
    squares = _cover_squares(centre, half, centre[0] - half, centre[1] - half, Bp, 2 * cover)
    del side
    pieces: list[tuple[tuple[float, float, float], Bound, float]] = []
    for q in squares:
        b = solve(q)
        pieces.append((q, b, b.value))
    solved = len(pieces)
    while True:
        i = max(range(len(pieces)), key=lambda j: (pieces[j][2], -j))
        q, b, val = pieces[i]
        children = _cover_squares(centre, half, q[0], q[1], q[2], 2)
        if val <= floor_value or solved + len(children) > max_pieces or q[2] < 0.5:
            break
        new = []
        for c in children:
            bc = solve(c)
            new.append((c, bc if bc.value < val else b, min(bc.value, val)))
        solved += len(children)
        pieces[i: i + 1] = new
    i = max(range(len(pieces)), key=lambda j: (pieces[j][2], -j))
    leaves = [(q[0], q[1], q[2], v) for q, _, v in pieces]
    return pieces[i][1], leaves


def _check_plan_limits(
    cells: np.ndarray, init: np.ndarray, region: Any, dist: np.ndarray,
    start_lim: tuple[np.ndarray, np.ndarray] | None,
    leaves: list[tuple[float, float, float, float]], Bp: float, n_max: int, plan: Any,
) -> None:
    """A covered plan satisfies the start's distance limits and lies in some piece's set."""
    if set(cells.tolist()) == set(init.tolist()):
        return
    cells = np.unique(cells)
    msg = f"the plan is not a path of length <= {Bp:.6g} from start={plan.start}: "
    if start_lim is not None:
        d = dist[cells]
        counts = (d[:, None] >= start_lim[0][None, :]).sum(axis=0)
        if np.any(counts > start_lim[1]):
            raise PlanningError(msg + "too many cells far from the start; the certificate "
                                "does not cover it")
    if not leaves:
        return
    pos = region.grid_index[cells].astype(np.float64)
    sq_thr, sq_caps = _square_limit(Bp, n_max)
    for r0, c0, h, _ in leaves:
        dq = _square_distance(pos, r0, c0, h)
        if np.all(dq <= Bp / 2 * (1 + 1e-12) + 1e-12) and np.all(
            (dq[:, None] >= sq_thr[None, :]).sum(axis=0) <= sq_caps
        ):
            return
    raise PlanningError(msg + "no piece of the midpoint cover holds it; the certificate does "
                        "not cover it")


def _gap(bound: float, information: float, k: int) -> tuple[float, float]:
    if bound == -math.inf and information == -math.inf:
        return 0.0, 1.0  # every feasible plan is singular: this one is optimal
    gap = bound - information
    return float(gap), float(math.exp(-gap / k)) if math.isfinite(gap) else 0.0


def _check_plan_feasible(
    cells: np.ndarray, init: np.ndarray, cand: np.ndarray, n_max: int, plan: Any,
    budget: float, slack: float,
) -> None:
    """The certificate covers the initial set and plans of <= n_max cells in the budget disk."""
    if set(cells.tolist()) == set(init.tolist()):
        return
    inside = np.isin(cells, cand)
    if not inside.all() or np.unique(cells).size > n_max:
        raise PlanningError(
            f"the plan is not feasible for start={plan.start}, budget={budget:g}: "
            f"{int((~inside).sum())} of its cells lie farther than the budget from the start "
            f"or it holds more than {n_max} cells; the certificate does not cover it"
        )


def _online_bound(
    Y: np.ndarray, cells: np.ndarray, cand: np.ndarray, n_max: int, ridge: float, f_S: float
) -> float | None:
    """``f(S) + sum of the n_max largest gains log(1 + y^T M_S^-1 y)`` over candidates not in S.

    Valid for any set S with finite information because log det is monotone submodular:
    ``f(O) <= f(S u O) <= f(S) + sum_{x in O \\ S} (f(S + x) - f(S))`` and ``|O| <= n_max``.
    """
    if not math.isfinite(f_S):
        return None
    M = _moment(Y, cells, np.ones(cells.size), ridge)
    L = _chol(M)
    if L is None:
        return None
    others = np.setdiff1d(cand, cells)
    if others.size == 0:
        return f_S
    gains = np.log1p(_leverages(np.ascontiguousarray(Y[:, others]), _inv_lower(L)))
    top, _ = _top_sum(gains, float(n_max))
    return f_S + top


def _min_spacing_km(region: Any, cand: np.ndarray) -> float:
    """Smallest great-circle distance (km) between two distinct candidate cells (KD-tree)."""
    if cand.size < 2:
        return math.inf
    from scipy.spatial import cKDTree

    lat = np.radians(region.cell_lat[cand])
    lon = np.radians(region.cell_lon[cand])
    xyz = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    _, nn = cKDTree(xyz).query(xyz, k=2)
    d = np.asarray(region.distance(cand, cand[nn[:, 1]], metric="km"), dtype=np.float64)
    # chord and great-circle distances are monotone in each other; shave rounding off
    return float(d.min()) * (1 - 1e-9)
