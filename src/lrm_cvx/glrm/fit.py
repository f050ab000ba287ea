"""Alternating minimisation of a GLRM on a ``(T, L)`` matrix: init, X and Y steps, convergence.

The problem (paper, Approach): with ``Omega`` the observed entries,

    minimise  sum_{(t, j) in Omega} loss(x_t . y_j - D_tj) + sum_t reg_x(x_t) + sum_j reg_y(y_j)

over ``X (k, T)`` and ``Y (k, L)``. Given ``X`` the cells are independent (Y step); given ``Y``
the times are independent (X step). Data arrive as ``D`` (float32 or float64, ``(T, L)``) plus a
boolean mask ``M`` (True = observed). The fit reads ``D`` zero-filled at unobserved entries with
the mask packed into bits (:mod:`.quadratic`); ``D`` is copied only when it holds values (NaN)
at unobserved entries and may not be overwritten.

Block solvers, chosen by capability (never by name):

- fast path (``solver="auto"``/``"fast"``) for a loss with a compiled quadratic majoriser
  (``kernel_spec``) and a regulariser with a closed form (``ridge_coefficient``) or a separable
  prox. One compiled pass over the data builds every column's (or row's) k x k Gram matrix of
  the majoriser; then a batched k x k Cholesky (ridge / none) or exact coordinate descent on the
  k x k system (L1, non-negative). For the quadratic loss this is the exact block minimiser,
  with the Grams built from the packed mask by subset-sum tables (:mod:`.quadratic`).
  For Huber, absolute and quantile losses it is one majorisation-minimisation (IRLS) step per
  block per iteration (``max_inner`` of them), which never increases the objective; the L1-type
  losses floor ``|r|`` at a tiny ``eps`` so their step is checked per column and reverted
  where the objective went up.
- cvxpy path (``solver="cvxpy"`` or a custom cvxpy regulariser): each block's subproblem is a
  cvxpy problem over a batch of columns, compiled once with parameters (DPP) and re-solved for
  every batch with Clarabel (SCS as fallback; :mod:`.cvxpy_blocks`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields
from typing import Any

import numba
import numpy as np
from scipy.linalg import solve_triangular

from .._validation import check_time_labels
from ..errors import ConvergenceWarning, DataError, ModelError
from . import kernels as K
from . import offset as O
from . import quadratic as Q
from .cvxpy_blocks import cvxpy_columns
from .losses import Loss
from .regularizers import Regularizer

__all__ = [
    "FitResult",
    "fit_glrm",
    "FitOptions",
    "objective",
    "y_block",
    "x_block",
    "x_pass",
    "solve_block",
    "cvxpy_y_block",
    "cvxpy_x_block",
    "initialize",
    "is_fast_capable",
    "check_data",
    "check_magnitude",
    "warn_sparse_cells",
    "free_parameters",
    "max_identifiable_rank",
    "noise_std",
    "is_plain_quadratic",
    "quadratic_ridge",
    "gram_values",
    "quadratic_y_step",
    "quadratic_loss",
    "relative_decrease",
    "direct_sse",
]

Y_CHUNK = 1 << 17  # cells per Y-step chunk (bounds the Gram buffers to ~30 MB)
SMALL_SVD = 4_000_000  # exact SVD of the mean-filled matrix below this many entries


@dataclass
class FitResult:
    """Learned factors and diagnostics of :func:`fit_glrm`."""

    X: np.ndarray  # (k, T) float64
    Y: np.ndarray  # (k, L) float64
    objective: list[float] = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False
    unobserved_cells: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_observed: int = 0
    sse: float = 0.0  # sum of squared residuals on observed entries
    noise_std: float = 0.0
    solver: str = "fast"
    offset: np.ndarray | None = None  # (L,) the joint offset's correction to the centring


# --------------------------------------------------------------------------- data checks
F32_MAX = float(np.finfo(np.float32).max)


def check_data(D: np.ndarray, M: np.ndarray, rank: int, *, check_finite: bool = True,
               offset: bool = False, times=None):
    """Validate ``D``/``M`` and the rank; return ``(row_counts, col_counts)``.

    Raises DataError (wrong dims, all missing, inf among observed values, a time with no
    observation, values so large that their per-cell sums overflow float64) or ModelError (rank
    < 1 or > min(T, L), or a rank that leaves no residual degrees of freedom, see
    :func:`max_identifiable_rank`: the noise level would not be identifiable). ``offset``: a
    per-cell mean is fitted too (``L_obs`` more parameters). ``times``: labels of the rows,
    used to name empty times in the message.
    """
    if D.ndim != 2:
        raise DataError(f"data must be a (time, cell) matrix, got shape {D.shape}")
    if M.shape != D.shape or M.dtype != np.bool_:
        raise DataError(f"mask must be a boolean array of shape {D.shape}, got "
                        f"{M.dtype} {M.shape}")
    T, L = D.shape
    if T == 0 or L == 0:
        raise DataError(f"data is empty, shape {D.shape}")
    if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)):
        raise ModelError(f"rank must be an integer, got {rank!r}")
    if rank < 1 or rank > min(T, L):
        raise ModelError(f"rank must be in [1, min(T, L)] = [1, {min(T, L)}], got {rank}")
    if times is not None:
        check_time_labels(times)  # no NaT
    rows, cols, nbad, colsum = K.data_stats(D, M, check_finite)
    Q.PASSES.add(D)  # one full read of the data (counted, see quadratic.PassCounter)
    if rows.sum() == 0:
        raise DataError("data has no observed value (all missing / all NaN)")
    if nbad:
        raise DataError(f"data has {nbad} non-finite observed values (inf); use NaN or the "
                        "mask for missing entries")
    empty = np.flatnonzero(rows == 0)
    if empty.size:
        names = empty[:10].tolist() if times is None else [
            str(v) for v in np.asarray(times)[empty[:10]]]
        where = "at positions " if times is None else ""
        raise DataError(f"times {where}{names} ({empty.size} in all) have no observation (all "
                        "NaN); drop them first (e.g. da.dropna('time', how='all'))")
    if not np.all(np.isfinite(colsum)):
        raise DataError(f"data values are too large: their sums overflow float64 (largest "
                        f"|value| {_max_abs(D, M):.3g}); rescale the data or mask fill values")
    n_obs = int(rows.sum())
    L_obs = int(np.count_nonzero(cols))
    kmax = max_identifiable_rank(n_obs, T, L_obs, offset=offset)
    if rank > kmax:
        p = free_parameters(rank, T, L_obs, offset=offset)
        hint = (f"use rank <= {kmax} or more data" if kmax >= 1 else
                "no rank works: fit on more snapshots (at least 2, more than the rank)")
        raise ModelError(
            f"rank {rank} leaves no residual degrees of freedom: {n_obs} observed values vs "
            f"{p} free parameters (T={T} times, {L_obs} observed cells"
            f"{', a per-cell offset' if offset else ''}); the model interpolates the data and "
            f"the noise level is not identifiable; {hint}")
    return DataStats(rows, cols, colsum)


def free_parameters(k: int, T: int, L_obs: int, *, offset: bool = False) -> int:
    """Free parameters of a rank-``k`` factorisation of ``T`` times x ``L_obs`` observed cells,
    ``k (T + L_obs) - k^2``, plus ``L_obs`` when a per-cell offset is fitted."""
    return k * (T + L_obs) - k * k + (L_obs if offset else 0)


def max_identifiable_rank(n_obs: int, T: int, L_obs: int, *, offset: bool = False) -> int:
    """The largest rank whose fit leaves residual degrees of freedom (``n_obs`` greater than
    :func:`free_parameters`), so the noise level is identifiable; 0 when none does."""
    ks = np.arange(1, max(min(T, L_obs), 0) + 1, dtype=np.int64)
    ok = ks[n_obs > free_parameters(ks, T, L_obs, offset=offset)]
    return int(ok.max()) if ok.size else 0


def _max_abs(D: np.ndarray, M: np.ndarray, rows: int = 256) -> float:
    """Largest ``|D|`` over the observed entries, in row blocks (no full-size temporary)."""
    best = 0.0
    for t0 in range(0, D.shape[0], rows):
        blk = np.abs(np.where(M[t0:t0 + rows], D[t0:t0 + rows], 0).astype(np.float64))
        best = max(best, float(np.nanmax(blk, initial=0.0)))
    return best


def check_magnitude(ssq: float, D: np.ndarray, M: np.ndarray, stacklevel: int = 3) -> None:
    """Refuse a sum of squares that overflows float64 (DataError) and warn (UserWarning naming
    the largest magnitude) when it would overflow float32: the statistics are kept in float64,
    but such values are usually unmasked fill values and dominate a least-squares fit."""
    if not np.isfinite(ssq):
        raise DataError(f"data values are too large: their sum of squares overflows float64 "
                        f"(largest |value| {_max_abs(D, M):.3g}); rescale the data or mask "
                        "fill values")
    if ssq > F32_MAX:
        warnings.warn(
            f"data has observed values up to {_max_abs(D, M):.3g} in magnitude: their sum of "
            f"squares ({ssq:.3g}) overflows float32; statistics are computed in float64, but "
            "such values (unmasked fill values?) dominate a least-squares fit: mask them (NaN) "
            "or rescale the data", UserWarning, stacklevel=stacklevel)


def warn_sparse_cells(cols: np.ndarray, rank: int, offset: bool, reg_y: Regularizer,
                      stacklevel: int = 3) -> None:
    """Warn (UserWarning) when cells with values have at most ``rank`` of them (``rank + 1``
    with an offset) and ``Y`` has no penalty: such a cell's factors interpolate its few values,
    and its predictions at other times can be far off (COADS's SST climatology at rank 2: the
    174 cells seen in 2 of 12 months predict their other months with 944 K RMS;
    benchmarks/bench_offset.py ``--coads``). A ridge on ``Y`` or a lower rank bounds them."""
    if reg_y.ridge_coefficient != 0.0:  # a ridge, L1 or non-negativity: not a plain solve
        return
    few = int(np.count_nonzero((cols > 0) & (cols <= rank + int(bool(offset)))))
    if few:
        warnings.warn(
            f"{few} of {int(np.count_nonzero(cols))} cells have at most "
            f"{rank + int(bool(offset))} observed values (rank {rank}"
            f"{' plus the offset' if offset else ''}): their factors interpolate those values "
            "and their predictions at other times can be far off; use reg=(None, 'ridge'), a lower "
            "rank, or drop cells with few values", UserWarning, stacklevel=stacklevel)


class DataStats(tuple):
    """``(row_counts, col_counts)`` as returned by :func:`check_data`, carrying the per-cell sums
    of the observed values (``colsum``, ``(L,)``) from the same pass, so :func:`fit_glrm` needs
    no second pass for the column means."""

    def __new__(cls, rows, cols, colsum=None):
        self = super().__new__(cls, (rows, cols))
        self.colsum = colsum
        return self


def is_fast_capable(loss: Loss, *regs: Regularizer) -> bool:
    """True when the compiled path can fit this loss and these regularisers.

    It needs the loss's compiled majoriser and, per regulariser, a closed form (ridge) or a
    separable prox. An L1-type loss (``smoothing``) with a non-smooth regulariser (no closed
    form) is left to cvxpy: IRLS combined with a kinked penalty can stall off the optimum.
    """
    if loss.kernel_spec is None:
        return False
    for r in regs:
        if r.ridge_coefficient is None and (loss.smoothing or not r.separable_prox):
            return False
    return True


# --------------------------------------------------------------------------- normal equations
def _unpack(G: np.ndarray, k: int) -> np.ndarray:
    pa, pb = K.pair_index(k)
    A = np.empty((G.shape[0], k, k))
    A[:, pa, pb] = G
    A[:, pb, pa] = G
    return A


def _coordinate_descent(G, h, reg, F0, max_sweeps=1000, tol=1e-13):
    """Exactly minimise ``y^T A y - 2 h^T y + g(y)`` for every row of ``h (n, k)``.

    Cyclic coordinate descent with ``g``'s scalar prox (vectorised over the ``n`` systems):
    coordinate ``i`` is ``prox_{g, 1/(2 A_ii)}(c_i / A_ii)``. Monotone and convergent for a
    convex separable ``g``. A zero diagonal (nothing observed) gives ``g``'s minimiser.
    """
    n, k = h.shape
    A = _unpack(G, k)
    y = np.ascontiguousarray(F0.T, dtype=np.float64).copy()
    diag = np.einsum("nii->ni", A).copy()
    empty = diag <= 0
    safe = np.where(empty, 1.0, diag)
    zero = reg.minimizer(k)
    for _ in range(max_sweeps):
        change = 0.0
        for i in range(k):
            c = h[:, i] - np.einsum("nj,nj->n", A[:, i, :], y) + diag[:, i] * y[:, i]
            new = reg.prox(c / safe[:, i], 0.5 / safe[:, i])
            new = np.where(empty[:, i], zero[i], new)
            change = max(change, float(np.max(np.abs(new - y[:, i]), initial=0.0)))
            y[:, i] = new
        if change <= tol * (1.0 + float(np.max(np.abs(y), initial=0.0))):
            break
    return y.T


def _solve_normal(G, h, reg, F0):
    """Minimiser of the majorised block problem for each column: ``(k, n)``."""
    k = h.shape[1]
    lam = reg.ridge_coefficient
    if lam is not None:
        pa, pb = K.pair_index(k)
        out = np.empty((h.shape[0], k))
        K.chol_solve(G, h, lam, pa, pb, out)  # a number, or one per row (.offset)
        return out.T
    if reg.separable_prox:
        return _coordinate_descent(G, h, reg, F0)
    raise ModelError(f"{reg!r} has no closed form or prox: use solver='cvxpy'")


def _mm_block(pass_fn, F, loss, reg, max_inner, inner_tol, step0=0, solve=None):
    """Minimise one block by (majorised) normal equations; return ``(F_new, objective_before)``.

    ``pass_fn(F) -> (G, h, f)`` evaluates the loss ``f`` per column at ``F`` and the Gram of
    its quadratic majoriser. Quadratic loss: one exact solve. Otherwise up to ``max_inner``
    MM steps; inexact majorisers keep a column's old value when its objective went up.
    ``solve(G, h, reg, F)``: the majoriser's minimiser (default :func:`_solve_normal`).
    """
    solve = solve or _solve_normal
    G, h, f = pass_fn(F, loss.smoothed(step0))
    cur = f + reg.evaluate(F)
    first = float(cur.sum())
    for it in range(max_inner):
        Fn = np.array(solve(G, h, reg, F), dtype=np.float64)
        last = it == max_inner - 1
        if loss.is_quadratic or (last and loss.majorizer_exact):
            return Fn, first
        G2, h2, f2 = pass_fn(Fn, loss.smoothed(step0 + it + 1))
        new = f2 + reg.evaluate(Fn)
        if not loss.majorizer_exact:
            worse = ~(new <= cur)
            if worse.any():
                Fn[:, worse] = F[:, worse]
                G2[worse], h2[worse], new[worse] = G[worse], h[worse], cur[worse]
        dec = float(cur.sum() - new.sum())
        F, G, h, cur = Fn, G2, h2, new
        if dec <= inner_tol * max(abs(float(cur.sum())), 1e-300) and (
            not loss.smoothing or loss.smoothed(step0 + it + 1) == loss.smoothed(step0 + it + 2)
        ):
            break
    return F, first


def is_plain_quadratic(loss) -> bool:
    """True for the plain quadratic loss ``r^2`` (compiled code 0, its own majoriser)."""
    return bool(loss.is_quadratic and loss.kernel_spec is not None and loss.kernel_spec[0] == 0)


def quadratic_ridge(loss, reg) -> float | None:
    """The ridge weight when the block problem is exactly quadratic + ridge (else None)."""
    if not is_plain_quadratic(loss):
        return None
    lam = reg.ridge_coefficient
    return None if lam is None else float(lam)


def _nchunk() -> int:
    return max(4 * numba.get_num_threads(), 4)


def gram_values(G, h, c, F):
    """Quadratic loss per column by the Gram identity: ``f_i^T G_i f_i - 2 h_i . f_i + c_i``.

    ``G (n, npair)`` packed, ``h (n, k)``, ``c (n,)``, ``F (k, n)``; returns ``(n,)``.
    """
    k = h.shape[1]
    A = _unpack(G, k)
    Ft = np.ascontiguousarray(F.T)
    return np.einsum("ni,nij,nj->n", Ft, A, Ft) - 2.0 * np.einsum("ni,ni->n", h, Ft) + c


def quadratic_y_step(md, X, Y, lam, out):
    """Exact quadratic + ridge Y step on prepared data; ``(Y_new, loss_before, loss_after)``
    (no ridge term)."""
    Yc = np.ascontiguousarray(Y, dtype=np.float64)
    direct = (out is not None and out.dtype == np.float64 and out.ndim == 2
              and out.flags.c_contiguous)
    res = out if direct else np.empty(Yc.shape)
    before, after, _ = Q.y_step(md, X, Yc, lam, res)
    if out is not None and not direct:
        out[...] = res
        res = out
    return res, before, after


def _quad_x(md, X, Y, lam):
    """Exact quadratic + ridge X step on prepared data; ``(X_new, loss_before, loss_after)``
    (no ridge term)."""
    G, h, c = Q.x_stats(md, Y)
    pa, pb = K.pair_index(h.shape[1])
    out = np.empty(h.shape)
    K.chol_solve(G, h, lam, pa, pb, out)
    Xn = np.ascontiguousarray(out.T)
    return Xn, float(gram_values(G, h, c, X).sum()), float(gram_values(G, h, c, Xn).sum())


def _quad_x_offset(md, X, Ya, lam):
    """:func:`_quad_x` of the joint offset (:mod:`.offset`): the first ``k`` rows of
    ``[X; 1]`` given ``Ya = [Y; o]``; the losses include the offset."""
    G, h, cc = Q.x_stats(md, Ya)
    Xn = O.fixed_row_solve(G, h, lam)
    return (Xn, float(gram_values(G, h, cc, O.augmented(X)).sum()),
            float(gram_values(G, h, cc, O.augmented(Xn)).sum()))


def quadratic_loss(md, X, Y) -> float:
    """The quadratic loss over observed entries at ``(X, Y)`` (Gram identity, one pass)."""
    G, h, c = Q.x_stats(md, Y)
    return float(gram_values(G, h, c, np.asarray(X, dtype=np.float64)).sum())


def y_block(D, M, X, Y, loss, reg, *, max_inner=1, inner_tol=0.0, out=None, step0=0):
    """Y step of the fast path: update every cell's column given ``X``.

    Returns ``(Y_new (k, L), objective_before)`` where the objective is the loss over observed
    entries at ``(X, Y)`` plus ``reg(Y)``. ``out`` may be ``Y`` itself (in-place update).
    The quadratic loss with ridge / no regulariser uses one fused compiled pass (Gram, solve
    and objective per cell, no intermediate buffers).
    """
    k, L = Y.shape
    lam = quadratic_ridge(loss, reg)
    if lam is not None:
        rv = reg.value(Y)
        res, before, _ = quadratic_y_step(Q.prepare(D, M), X, Y, lam, out)
        return res, before + rv
    pa, pb = K.pair_index(k)
    npair = pa.size
    X = np.ascontiguousarray(X, dtype=np.float64)
    out = np.empty_like(Y) if out is None else out
    total = 0.0
    for j0 in range(0, L, Y_CHUNK):
        j1 = min(j0 + Y_CHUNK, L)
        c = j1 - j0

        def pass_fn(F, lo, j0=j0, j1=j1, c=c):
            code, p0, p1 = lo.kernel_spec
            G = np.empty((c, npair))
            h = np.empty((c, k))
            f = np.empty(c)
            Fc = np.ascontiguousarray(F, dtype=np.float64)
            K.col_pass(D, M, X, Fc, j0, j1, code, p0, p1, pa, pb, G, h, f)
            return G, h, f

        Fn, first = _mm_block(pass_fn, np.array(Y[:, j0:j1]), loss, reg, max_inner, inner_tol,
                              step0)
        out[:, j0:j1] = Fn
        total += first
    return out, total


def _x_pass_fn(D, M, Y, lift=None):
    """The X step's ``pass_fn`` for :func:`_mm_block`: the majoriser's Grams of every time at the
    factors ``lift(F)`` (default ``F``) against ``Y``, one compiled pass over the data."""
    k, T = Y.shape[0], D.shape[0]
    pa, pb = K.pair_index(k)
    nchunk = _nchunk()
    Y = np.ascontiguousarray(Y, dtype=np.float64)

    def pass_fn(F, lo):
        code, p0, p1 = lo.kernel_spec
        Fc = lift(F) if lift else np.ascontiguousarray(F, dtype=np.float64)
        G = np.zeros((nchunk, T, pa.size))
        h = np.zeros((nchunk, T, k))
        f = np.zeros((nchunk, T))
        K.row_pass(D, M, Fc, Y, code, p0, p1, pa, pb, nchunk, G, h, f)
        return G.sum(0), h.sum(0), f.sum(0)

    return pass_fn


def x_block_offset(D, M, X, Ya, loss, reg, *, max_inner=1, inner_tol=0.0, step0=0):
    """:func:`x_block` of the joint offset (:mod:`.offset`, ridge-type ``reg``): the first ``k``
    rows of ``[X; 1]`` given ``Ya = [Y; o]``, the majoriser's normal equations solved with the
    last row fixed. Returns ``(X_new (k, T), objective_before)``."""
    lam = reg.ridge_coefficient
    return _mm_block(_x_pass_fn(D, M, Ya, lift=O.augmented), np.array(X, dtype=np.float64),
                     loss, reg, max_inner, inner_tol, step0,
                     solve=lambda G, h, reg, F: O.fixed_row_solve(G, h, lam))


def x_block(D, M, X, Y, loss, reg, *, max_inner=1, inner_tol=0.0, step0=0):
    """X step of the fast path: update every time's column given ``Y``.

    Returns ``(X_new (k, T), objective_before)`` (loss at ``(X, Y)`` plus ``reg(X)``).
    """
    lam = quadratic_ridge(loss, reg)
    if lam is not None:
        Xn, before, _ = _quad_x(Q.prepare(D, M), X, Y, lam)
        return Xn, before + reg.value(X)
    return _mm_block(_x_pass_fn(D, M, Y), np.array(X, dtype=np.float64), loss, reg, max_inner,
                     inner_tol, step0)


def x_pass(D, M, X, Y, loss, step=0):
    """Sufficient statistics of the X step over the columns of ``D``: ``(G, h, f)``.

    ``G (T, k(k+1)/2)`` packs each time's Gram of the loss's quadratic majoriser at ``(X, Y)``,
    ``h (T, k)`` its linear term and ``f (T,)`` the loss per time. They add up over column
    chunks, which is how a chunked (dask) fit reduces the X step.
    """
    k, T = X.shape
    lo = loss.smoothed(step)
    if is_plain_quadratic(lo):
        G, h, c = Q.x_stats(Q.prepare(D, M), Y)
        return G, h, gram_values(G, h, c, np.asarray(X, dtype=np.float64))
    pa, pb = K.pair_index(k)
    nchunk = _nchunk()
    code, p0, p1 = lo.kernel_spec
    G = np.zeros((nchunk, T, pa.size))
    h = np.zeros((nchunk, T, k))
    f = np.zeros((nchunk, T))
    K.row_pass(D, M, np.ascontiguousarray(X, dtype=np.float64),
               np.ascontiguousarray(Y, dtype=np.float64), code, p0, p1, pa, pb, nchunk, G, h, f)
    return G.sum(0), h.sum(0), f.sum(0)


def solve_block(G, h, reg, F0):
    """Minimiser of the (majorised) block problem for each of ``n`` columns: ``(k, n)``.

    ``G (n, k(k+1)/2)`` and ``h (n, k)`` as returned by :func:`x_pass`; ``F0 (k, n)`` is the
    starting point for regularisers solved by coordinate descent.
    """
    return np.ascontiguousarray(_solve_normal(G, h, reg, F0))


def objective(D, M, X, Y, loss, reg_x, reg_y) -> float:
    """The GLRM objective at ``(X, Y)``: loss over observed entries plus both regularisers."""
    return _loss_sum(D, M, X, Y, loss) + reg_x.value(X) + reg_y.value(Y)


def _loss_sum(D, M, X, Y, loss) -> float:
    if loss.kernel_spec is None:
        R = X.T @ Y - np.where(M, D, 0.0)
        return float(np.sum(np.where(M, loss.evaluate(R), 0.0)))
    if loss.kernel_spec[0] == 0:
        return quadratic_loss(Q.prepare(D, M), X, Y)
    k, T = X.shape
    code, p0, p1 = loss.kernel_spec
    pa, pb = K.pair_index(k)
    nchunk = _nchunk()
    G = np.zeros((nchunk, T, pa.size))
    h = np.zeros((nchunk, T, k))
    f = np.zeros((nchunk, T))
    K.row_pass(D, M, np.ascontiguousarray(X, dtype=np.float64),
               np.ascontiguousarray(Y, dtype=np.float64), code, p0, p1, pa, pb, nchunk, G, h, f)
    return float(f.sum())


# --------------------------------------------------------------------------- cvxpy path
def cvxpy_y_block(D, M, X, Y, loss, reg, cache: dict | None = None):
    """Y step by cvxpy (batches of columns); returns ``(Y_new, objective_before)``."""
    before = _loss_sum(D, M, X, Y, loss) + reg.value(Y)
    A = np.asarray(X.T, dtype=np.float64)
    out = cvxpy_columns(D, M, A, loss, reg, {} if cache is None else cache, "Y-step")
    return out, before


def cvxpy_x_block(D, M, X, Y, loss, reg, cache: dict | None = None):
    """X step by cvxpy (batches of times): the Y step of the transposed problem."""
    before = _loss_sum(D, M, X, Y, loss) + reg.value(X)
    A = np.asarray(Y.T, dtype=np.float64)
    out = cvxpy_columns(D.T, M.T, A, loss, reg, {} if cache is None else cache, "X-step")
    return out, before


# --------------------------------------------------------------------------- initialisation
def initialize(md, rank, init, rng, mu, scale, *, n_power=1, oversample=5):
    """Initial ``(X, Y)``: SVD of the mean-filled matrix (``init="svd"``) or Gaussian.

    ``md`` is the :class:`~.quadratic.MaskedData` of the data. The mean-filled matrix has each
    cell's missing entries replaced by its observed mean ``mu``. Below ``SMALL_SVD`` entries an
    exact SVD, else a randomized SVD with ``n_power`` power iterations using compiled products
    (never materialising the filled matrix). The singular values are split evenly:
    ``X = sqrt(S) U^T``, ``Y = sqrt(S) V^T``.
    """
    T, L = md.shape
    k = rank
    if init == "random":
        s = (max(scale, 1e-12) ** 2 / k) ** 0.25
        return s * rng.standard_normal((k, T)), s * rng.standard_normal((k, L))
    if init != "svd":
        raise ModelError(f"init must be 'svd' or 'random', got {init!r}")
    if T * L <= SMALL_SVD:
        Z = np.where(md.mask(), md.D, mu[None, :]).astype(np.float64)
        U, S, Vt = _exact_svd(Z, k)
    else:
        p = min(k + oversample, T, L)
        Om = rng.standard_normal((p, L))
        Qr, _ = np.linalg.qr(Q.filled_matmul(md, mu, Om))
        del Om
        for _ in range(n_power):
            Wq, _ = _orth_rows(Q.filled_rmatmul(md, mu, Qr))  # rows span Z^T Q, (p, L)
            Qr, _ = np.linalg.qr(Q.filled_matmul(md, mu, Wq))
            del Wq
        Qb, Rm = _orth_rows(Q.filled_rmatmul(md, mu, Qr))  # B = Q^T Z = Rm Qb, (p, L)
        Ur, S, Vrt = np.linalg.svd(Rm)
        U = (Qr @ Ur)[:, :k]
        Vt = Vrt[:k] @ Qb
        S = S[:k]
    # deterministic signs: largest |entry| of each right singular vector positive
    sign = np.sign(Vt[np.arange(k), np.argmax(np.abs(Vt), axis=1)])
    sign[sign == 0] = 1.0
    sq = np.sqrt(np.maximum(S, 0.0))
    X = (sq * sign)[:, None] * U.T
    Y = (sq * sign)[:, None] * Vt
    return np.ascontiguousarray(X), np.ascontiguousarray(Y)


def _exact_svd(Z: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The leading ``k`` singular triplets of ``Z (T, L)``. A wide (or tall) matrix goes through
    the eigendecomposition of its small Gram matrix (LAPACK's SVD of a 72 x 50k matrix took
    1-5 s, its Gram 0.1-0.3 s) when the ``k`` values are well conditioned (``S_k / S_1 >=
    1e-4``: the Gram squares the condition number); otherwise a plain SVD."""
    T, L = Z.shape
    if min(T, L) * 8 <= max(T, L):
        wide = T <= L
        G = Z @ Z.T if wide else Z.T @ Z
        w, E = np.linalg.eigh(G)
        w, E = w[::-1][:k], E[:, ::-1][:, :k]
        if w[0] > 0 and w[-1] >= 1e-8 * w[0]:
            S = np.sqrt(w)
            if wide:
                return E, S, (E.T @ Z) / S[:, None]
            return (Z @ E) / S[None, :], S, E.T
    U, S, Vt = np.linalg.svd(Z, full_matrices=False)
    return U[:, :k], S[:k], Vt[:k]


def _orth_rows(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``W (p, L) = R @ Q`` with ``Q`` orthonormal rows: Cholesky QR applied twice (two small
    Gram products and triangular solves instead of a Householder QR of the tall ``W.T``, ~50x
    faster at L = 2M); falls back to Householder QR when ``W`` is (numerically) rank-deficient."""
    try:
        R = np.eye(W.shape[0])
        Wq = W
        for _ in range(2):
            C = np.linalg.cholesky(Wq @ Wq.T)
            Wq = solve_triangular(C, Wq, lower=True, check_finite=False)
            R = R @ C
        if np.all(np.isfinite(Wq)):
            return np.ascontiguousarray(Wq), R
    except np.linalg.LinAlgError:
        pass
    Qh, Rh = np.linalg.qr(W.T)
    return np.ascontiguousarray(Qh.T), Rh.T


# --------------------------------------------------------------------------- the loop
@dataclass(frozen=True)
class FitOptions:
    """How the alternating minimisation runs (:func:`fit_glrm`, and ``fit_chunked`` but for
    ``max_inner``): ``max_iter`` rounds at most, stop when the relative decrease of the
    objective falls below ``tol``, ``init`` ``"svd"`` | ``"random"``, ``solver`` ``"auto"`` |
    ``"fast"`` | ``"cvxpy"``, ``rng`` (a numpy Generator; None: fresh entropy), ``progress``
    (a tqdm bar), ``max_inner`` majorise-minimise steps per block and round, ``offset`` (``D``
    is already centred by a fitted per-cell mean: counted in ``noise_std``'s degrees of
    freedom)."""

    max_iter: int = 100
    tol: float = 1e-4
    init: str = "svd"
    solver: str = "auto"
    rng: Any = None
    progress: bool = False
    max_inner: int = 1
    offset: bool = False

    @classmethod
    def from_kwargs(cls, function: str, options: dict[str, Any],
                    exclude: tuple[str, ...] = ()) -> FitOptions:
        """The options from keyword arguments; a TypeError names any other keyword, as a
        signature would."""
        known = {f.name for f in fields(cls)} - set(exclude)
        unknown = sorted(set(options) - known)
        if unknown:
            raise TypeError(f"{function}() got unexpected keyword argument(s) {unknown}; "
                            f"the fit options are {sorted(known)}")
        return cls(**options)


def fit_glrm(
    D: np.ndarray,
    M: np.ndarray,
    rank: int,
    loss: Loss,
    reg_x: Regularizer,
    reg_y: Regularizer,
    *,
    stats: tuple[np.ndarray, np.ndarray] | None = None,
    overwrite_data: bool = False,
    **options: Any,
) -> FitResult:
    """Fit ``X (k, T)``, ``Y (k, L)`` to ``D`` on the entries where ``M`` is True.

    ``options``: the :class:`FitOptions` as keywords (``max_iter``, ``tol``, ``init``,
    ``solver``, ``rng``, ``progress``, ``max_inner``, ``offset``).

    ``D`` is read through its zero-filled form (:func:`~.quadratic.prepare`): a ``D`` that
    holds values (NaN) at unobserved entries is copied once, or zero-filled in place when
    ``overwrite_data`` is True. ``stats`` is :func:`check_data`'s result when already known.
    ``offset``: ``D`` is already centred by each cell's observed mean (counted in the degrees of
    freedom of ``noise_std``); on the fast path with ridge-type regularisers the fit then
    refines the offset jointly with the factors (:mod:`.offset`), and ``FitResult.offset`` is
    the correction ``(L,)`` to add to the observed mean (in ``D``'s units; None otherwise: the
    cvxpy path, L1 or non-negative factors keep the observed mean).

    Each iteration is a Y step then an X step. The objective recorded for iteration ``i`` is
    evaluated at the factors after ``i`` rounds (``objective[0]`` at the initialisation);
    iteration stops when its relative decrease falls below ``tol`` or after ``max_iter``
    rounds (ConvergenceWarning when ``tol > 0``). Cells never observed get ``reg_y``'s
    minimiser (zero) and are listed in ``unobserved_cells``.
    """
    o = FitOptions.from_kwargs("fit_glrm", options)
    max_iter, tol, init, solver, progress, max_inner, offset = (
        o.max_iter, o.tol, o.init, o.solver, o.progress, o.max_inner, o.offset)
    rng = np.random.default_rng() if o.rng is None else o.rng
    if solver not in ("auto", "fast", "cvxpy"):
        raise ModelError(f"solver must be 'auto', 'fast' or 'cvxpy', got {solver!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ModelError(f"max_iter must be an integer >= 0, got {max_iter!r}")
    if (isinstance(tol, (bool, np.bool_)) or not isinstance(tol, (int, float, np.integer,
                                                                   np.floating))
            or not np.isfinite(tol) or tol < 0):
        raise ModelError(f"tol must be a finite number >= 0, got {tol!r}")
    if getattr(stats, "colsum", None) is None:
        stats = check_data(D, M, rank, offset=offset)
    rows, cols = stats
    T, L = D.shape
    fast = solver != "cvxpy" and is_fast_capable(loss, reg_x, reg_y)
    if solver == "fast" and not fast:
        raise ModelError(f"no fast path for loss {loss!r} with {reg_x!r} / {reg_y!r}")
    n_obs = int(rows.sum())
    mu_global = float(stats.colsum.sum() / n_obs)
    mu = np.where(cols > 0, stats.colsum / np.maximum(cols, 1), mu_global)
    md = Q.prepare(D, M, overwrite=overwrite_data)
    D = md.D  # zero-filled from here on
    ssq = float(md.ssq_rows.sum())  # float64 sums (a float32 sum overflows at |d| ~ 1e19)
    check_magnitude(ssq, D, M, stacklevel=4)
    warn_sparse_cells(cols, rank, offset, reg_y, stacklevel=4)
    scale = float(np.sqrt(ssq / n_obs))
    loss = loss.with_scale(scale)
    X, Y = initialize(md, rank, init, rng, mu, scale)
    unobserved = np.flatnonzero(cols == 0)
    Y[:, unobserved] = reg_y.minimizer(rank)[:, None]
    lam_y, lam_x = quadratic_ridge(loss, reg_y), quadratic_ridge(loss, reg_x)
    quad = fast and lam_y is not None and lam_x is not None
    f_loss = None  # quadratic path: loss at the current (X, Y) from the last step's Gram

    joint = fast and offset and O.supports(reg_x, reg_y)  # the offset as a factor (.offset)
    if joint:
        ridges = O.row_ridges(lam_y, rank)
        Ya = np.zeros((rank + 1, L))  # [Y; o], Y a view of its first k rows
        Ya[:rank] = Y
        Y = Ya[:rank]
    cache: dict = {}
    history: list[float] = []
    converged = False
    n_iter = 0
    bar = progress_bar(progress, max_iter, "GLRM")
    try:
        for it in range(max_iter):
            if joint and quad:
                ry = reg_y.value(Y) + O.penalty(Ya[rank])  # at the factors before the step
                _, lb, f_loss = quadratic_y_step(md, O.augmented(X), Ya, ridges, Ya)
                fy = lb + ry
            elif joint:  # a robust loss: majorise-minimise with the offset's row
                _, fy = y_block(D, M, O.augmented(X), Ya, loss, O.OffsetRidge(reg_y, rank),
                                max_inner=max_inner, out=Ya, step0=it * max_inner)
            elif quad:
                ry = reg_y.value(Y)
                Y, lb, f_loss = quadratic_y_step(md, X, Y, lam_y, Y)
                fy = lb + ry
            elif fast:
                Y, fy = y_block(D, M, X, Y, loss, reg_y, max_inner=max_inner, out=Y,
                                step0=it * max_inner)
            else:
                Y, fy = cvxpy_y_block(D, M, X, Y, loss, reg_y, cache)
            history.append(fy + reg_x.value(X))
            if it >= 1 and relative_decrease(history) < tol:
                converged = True
                break
            if joint and quad:
                X, _, f_loss = _quad_x_offset(md, X, Ya, lam_x)
            elif joint:
                X, _ = x_block_offset(D, M, X, Ya, loss, reg_x, max_inner=max_inner,
                                      step0=it * max_inner)
            elif quad:
                X, _, f_loss = _quad_x(md, X, Y, lam_x)
            elif fast:
                X, _ = x_block(D, M, X, Y, loss, reg_x, max_inner=max_inner,
                               step0=it * max_inner)
            else:
                X, _ = cvxpy_x_block(D, M, X, Y, loss, reg_x, cache)
            n_iter = it + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(objective=f"{history[-1]:.6g}")
    finally:
        if bar is not None:
            bar.close()
    if f_loss is None:
        f_loss = _loss_sum(D, M, *((O.augmented(X), Ya) if joint else (X, Y)), loss)
    history.append(f_loss + reg_x.value(X) + reg_y.value(Y)
                   + (O.penalty(Ya[rank]) if joint else 0.0))
    converged = finish_convergence(history, converged, max_iter, tol, stacklevel=4)
    Y[:, unobserved] = reg_y.minimizer(rank)[:, None]  # (unobserved columns add no loss)
    off = None
    if joint:
        Ya[rank, unobserved] = 0.0
        off = Ya[rank].copy()
        Y = np.ascontiguousarray(Ya[:rank])
    Xs, Ys = (O.augmented(X), Ya) if joint else (X, Y)  # the residuals' factors
    sse = max(f_loss, 0.0) if is_plain_quadratic(loss) else quadratic_loss(md, Xs, Ys)
    if sse <= SSE_RTOL * ssq:  # the Gram identity cancelled: sum the residuals directly
        sse = direct_sse(D, M, Xs, Ys)
        if is_plain_quadratic(loss):
            history[-1] = sse + reg_x.value(X) + reg_y.value(Y) + (O.penalty(off) if joint
                                                                   else 0.0)
    return FitResult(
        X=X, Y=Y, objective=history, n_iter=n_iter, converged=converged,
        unobserved_cells=unobserved.astype(np.int64), n_observed=n_obs, sse=sse,
        noise_std=noise_std(sse, n_obs, rank, T, L - unobserved.size,
                            extra=(L - unobserved.size) if offset else 0),
        solver="fast" if fast else "cvxpy", offset=off,
    )


# --------------------------------------------------------------------------- shared by both drivers
def progress_bar(progress: bool, total: int, desc: str):
    """A tqdm bar over the rounds, or None."""
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="it")


def relative_decrease(history: list[float]) -> float:
    """``(prev - cur) / |prev|`` of the last two objectives (0 when ``prev`` is 0)."""
    prev, cur = history[-2], history[-1]
    if prev == 0:
        return 0.0
    return (prev - cur) / abs(prev)


def finish_convergence(history: list[float], converged: bool, max_iter: int, tol: float,
                       stacklevel: int) -> bool:
    """Convergence after the last objective is appended; ConvergenceWarning when ``tol > 0``
    was not reached within ``max_iter`` rounds."""
    if not converged and max_iter >= 1 and len(history) >= 2:
        converged = relative_decrease(history) < tol
    if not converged and tol > 0:
        warnings.warn(
            f"GLRM fit stopped at max_iter={max_iter} before the relative decrease of the "
            f"objective fell below tol={tol}", ConvergenceWarning, stacklevel=stacklevel)
    return bool(converged)


def noise_std(sse: float, n_obs: int, k: int, T: int, L_obs: int, extra: int = 0) -> float:
    """RMS training residual with a degrees-of-freedom correction: ``sqrt(SSE / (n_obs - p))``,
    ``p = k (T + L_obs) - k^2 + extra`` free parameters (``extra``: e.g. ``L_obs`` per-cell
    offsets). ModelError when ``n_obs <= p``: the fit interpolates the data and the noise level
    is not identifiable (:func:`check_data` refuses such a rank before fitting)."""
    p = k * (T + L_obs) - k * k + extra
    if n_obs <= p:
        raise ModelError(f"rank {k} leaves no residual degrees of freedom ({n_obs} observed "
                         f"values, {p} free parameters, T={T}): the noise level is not "
                         "identifiable; use a lower rank or more data")
    return float(np.sqrt(max(sse, 0.0) / (n_obs - p)))


SSE_RTOL = 1e-8  # below this fraction of the data's sum of squares the SSE is summed directly


def direct_sse(D: np.ndarray, M: np.ndarray, X: np.ndarray, Y: np.ndarray) -> float:
    """Sum of squared residuals over observed entries, from the residuals themselves (one
    compiled pass, float64): exact where the Gram identity ``y^T G y - 2 h.y + c`` cancels
    (a fit that explains all but a 1e-8 fraction of the data's energy)."""
    k, T = X.shape
    pa, pb = K.pair_index(k)
    nchunk = _nchunk()
    G = np.zeros((nchunk, T, pa.size))
    h = np.zeros((nchunk, T, k))
    f = np.zeros((nchunk, T))
    Q.PASSES.add(D)
    K.row_pass(D, M, np.ascontiguousarray(X, dtype=np.float64),
               np.ascontiguousarray(Y, dtype=np.float64), 0, 0.0, 0.0, pa, pb, nchunk, G, h, f)
    return float(f.sum())


class _Quad(Loss):
    kernel_spec = (0, 0.0, 0.0)


_QUAD = _Quad()

