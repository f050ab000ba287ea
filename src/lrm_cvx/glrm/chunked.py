"""Out-of-core GLRM fit on dask: the same alternating minimisation as :mod:`.fit`, chunk by chunk.

The data never exist in memory as one ``(T, L)`` matrix. They are staged once into a scratch
directory as column chunks (all times x a block of cells, one ``.npy`` file of float32 per
chunk, ``T * L * 4`` bytes on disk) by :func:`lrm_cvx.io.staging.stage` (from dask data or
straight from CDR NDVI files). One preparation task per chunk then zero-fills it in place
(standardized with ``offset`` / ``scale``) and writes its packed mask beside it
(:func:`~.quadratic.prepare`), so every later task reads exactly what the in-memory kernels
read, with no NaN test, zero-fill or packing:

* Y step: the fused quadratic kernel (:func:`~.fit.quadratic_y_step`) or :func:`~.fit.y_block`
  per chunk (cells are independent given ``X``);
* X step: the chunk's Gram statistics (:func:`~.quadratic.x_stats` / :func:`~.fit.x_pass`)
  summed over chunks, then :func:`~.fit.solve_block` on the client (times are independent
  given ``Y``);
* predictive options: per-cell statistics of :mod:`.predictive` on each chunk's cells.

The Y step and the X-step statistics of a round are one task per chunk (one read of the data
per round, two passes over it in memory, as in memory; :data:`~.quadratic.PASSES` counts them).
Chunks of ``Y`` are persisted between rounds (in the workers' memory with a
``dask.distributed`` Client, in the client process with the threaded scheduler). Whatever
scheduler is active is used (``dask.compute`` / ``dask.persist``): the threaded default, or a
``distributed.Client`` (LocalCluster, dask-jobqueue, dask-kubernetes) when one exists. With a
cluster, the scratch directory must be on storage every worker can read (``scratch_dir``).

Same answer as the in-memory fit: the initialisation follows :func:`~.fit.initialize` step by
step (exact SVD of the mean-filled matrix below ``SMALL_SVD`` entries, computed from the
``T x T`` Gram matrix; above it the randomized SVD with the same Gaussian test matrix drawn from
the same generator, so the same range is found; ``init="random"`` draws the same factors), and
the rounds call the same kernels, so fits agree up to floating-point summation order.
"""

from __future__ import annotations

import shutil
import threading
from typing import Any

import numpy as np

from ..errors import DataError, ModelError
from ..io import staging
from ..io.staging import is_dask_backed
from ..region import Region
from . import offset as O
from . import quadratic as Q
from .dynamics import error_rows
from .fit import (
    SMALL_SVD,
    SSE_RTOL,
    FitOptions,
    FitResult,
    direct_sse,
    finish_convergence,
    free_parameters,
    gram_values,
    is_fast_capable,
    is_plain_quadratic,
    max_identifiable_rank,
    noise_std,
    objective,
    progress_bar,
    quadratic_loss,
    quadratic_ridge,
    quadratic_y_step,
    relative_decrease,
    solve_block,
    warn_sparse_cells,
    x_pass,
    y_block,
)
from .losses import Loss
from .predictive import (
    column_moments,
    moments_to_transform,
    residual_moments,
    residual_sample,
    scale_floor,
    standardize,
)
from .regularizers import Regularizer, ZeroReg

__all__ = ["fit_chunked", "is_dask_backed", "STAGING_KEYS"]

STAGING_KEYS = ("chunk_mb", "scratch_dir", "block_mb")
"""The staging's options (:func:`~lrm_cvx.io.staging.stage`), ``fit_chunked(staging_options=)``."""

_LOCK = threading.Lock()  # one compiled kernel at a time per process (they are parallel already)
_ZERO = ZeroReg()


# --------------------------------------------------------------------------- chunk tasks
_HEADER_LOCK = threading.Lock()


def _load(path: str) -> np.ndarray:
    """``np.load(path)`` of a chunk file that :func:`np.save` wrote, safe in dask's threads:
    the ``.npy`` header is parsed under a lock, because ``ast.literal_eval`` (which numpy
    parses it with) raced between threads in CPython 3.11 before 3.11.8 ("SystemError: AST
    constructor recursion depth mismatch", python/cpython gh-106905; seen in CI); the data are
    read outside it."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        with _HEADER_LOCK:
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        count = int(np.prod(shape, dtype=np.int64))
        data = np.fromfile(f, dtype=dtype, count=count)
    if data.size != count:
        raise OSError(f"{path}: truncated chunk file ({data.size} of {count} values)")
    return data.reshape(shape, order="F" if fortran else "C")


def _codes_path(path: str) -> str:
    return path[:-4] + "_codes.npy"


def _t_scales(path: str, offset: bool) -> tuple[np.ndarray, np.ndarray]:
    """A staged chunk's unfloored ``scale=True`` scales and observation counts per cell (the
    pass that finds the floor of all cells, :func:`~.predictive.scale_floor`, before
    :func:`_t_prepare` standardizes)."""
    D = _load(path)
    M = ~np.isnan(D)
    mean, std, count = column_moments(D, M)
    return moments_to_transform(offset, True, mean, std, floor=0.0)[1], count


def _t_prepare(path: str, offset: bool, scale: bool, floor: float = 0.0) -> dict:
    """Turn one staged chunk (float32, NaN = missing) into what every later task reads, in one
    read and one write: the zero-filled (with ``offset``/``scale``: standardized) data in place
    and its packed mask beside it (:func:`~.quadratic.prepare`). Returns the chunk's
    statistics: row / column counts, column sums (for the init's mean fill), per-time sums of
    squares, the last time's mask and, when asked, the cells' offset and scale."""
    D = _load(path)
    M = ~np.isnan(D)
    np.copyto(D, 0.0, where=~M)
    out: dict = {"colsum": D.sum(axis=0, dtype=np.float64)}
    if offset or scale:
        mean, std, _ = column_moments(D, M)
        off, sc = moments_to_transform(offset, scale, mean, std, floor=floor)
        D = standardize(D, M, off, sc)
        out["offset"], out["scale"] = off, sc
        # the transformed data's sums as GLRM.fit takes them: 0 when centred, else sums / scale
        out["colsum"] = np.zeros_like(out["colsum"]) if offset else out["colsum"] / sc
    md = Q.prepare(D, M, overwrite=True)
    np.save(path, md.D)
    np.save(_codes_path(path), md.codes)
    out.update(rows=M.sum(axis=1).astype(np.int64), cols=M.sum(axis=0).astype(np.int64),
               ssq_rows=md.ssq_rows, last=M[-1].copy(),
               error=np.packbits(M[error_rows(M.shape[0])], axis=1), n_cells=M.shape[1])
    return out


class _PackedRows:
    """The observed masks of the :func:`~.dynamics.error_rows` snapshots, bit-packed per column
    chunk; ``rows[t]`` unpacks the whole row of time ``t`` (``(L,)`` bool) on demand."""

    def __init__(self, n_times: int, chunks: list[tuple[np.ndarray, int]]) -> None:
        self.index = {int(t): i for i, t in enumerate(error_rows(n_times))}
        self.chunks = chunks

    def __getitem__(self, t: int) -> np.ndarray:
        i = self.index[int(t)]
        return np.concatenate([np.unpackbits(p[i], count=n).astype(bool)
                               for p, n in self.chunks])


def _md(path: str, ssq_rows: np.ndarray) -> Q.MaskedData:
    """The prepared chunk as :class:`~.quadratic.MaskedData` (one read, no pass over it)."""
    return Q.MaskedData(_load(path), _load(_codes_path(path)), ssq_rows)


def _t_gram(path, ssq, mu):
    md = _md(path, ssq)
    Z = np.where(md.mask(), md.D, mu[None, :]).astype(np.float64)
    return Z @ Z.T


def _t_range(path, ssq, mu, om_path):
    return Q.filled_matmul(_md(path, ssq), mu, _load(om_path))


def _t_power(path, ssq, mu, W):
    md = _md(path, ssq)
    return Q.filled_matmul(md, mu, Q.filled_rmatmul(md, mu, W))


def _t_project(path, ssq, mu, W):
    B = Q.filled_rmatmul(_md(path, ssq), mu, W)
    return B, B @ B.T


def _t_rotate(B, R, j0):
    C = R.T @ B
    a = np.abs(C)
    arg = np.argmax(a, axis=1)
    rows = np.arange(C.shape[0])
    return a[rows, arg], arg + j0, np.sign(C[rows, arg])


def _t_y0(B, R, scale, unobserved, minimizer):
    Y = scale[:, None] * (R.T @ B)
    if unobserved.size:
        Y[:, unobserved] = minimizer[:, None]
    return Y


def _t_load_y0(path, unobserved, minimizer):
    Y = _load(path)
    if unobserved.size:
        Y[:, unobserved] = minimizer[:, None]
    return Y


def _t_offset_row(Yc):
    """A chunk's ``[Y_c; 0]``: the joint offset's row (:mod:`.offset`), starting at centring."""
    return np.vstack([Yc, np.zeros((1, Yc.shape[1]))])


def _t_round(path, ssq, X, Yc, loss, reg_y, step, lams, joint=False):
    """Y step of one chunk, then its X-step statistics at the new ``Y`` (one read of the chunk;
    the quadratic + ridge path makes exactly two passes over it, as in memory). ``joint``:
    ``X`` and ``Yc`` carry the joint offset's row (:mod:`.offset`) and its own ridge."""
    md = _md(path, ssq)
    with _LOCK:
        if lams is not None:  # quadratic + ridge: the fused kernels on the packed mask
            ry = reg_y.value(Yc[:-1]) + O.penalty(Yc[-1]) if joint else reg_y.value(Yc)
            lam = O.row_ridges(lams[0], X.shape[0] - 1) if joint else lams[0]
            Yn, before, _ = quadratic_y_step(md, X, Yc, lam, None)
            G, h, c = Q.x_stats(md, Yn)
            return Yn, (before + ry, G, h, gram_values(G, h, c, X))
        D, M = md.D, md.mask()
        reg = O.OffsetRidge(reg_y, X.shape[0] - 1) if joint else reg_y
        Yn, fy = y_block(D, M, X, Yc, loss, reg, step0=step)
        G, h, f = x_pass(D, M, X, Yn, loss, step=step)
    return Yn, (fy, G, h, f)


def _t_fpass(path, ssq, X, Yc, loss, step):
    md = _md(path, ssq)
    with _LOCK:
        return x_pass(md.D, md.mask(), X, Yc, loss, step=step)[2]


def _t_final(path, ssq, X, Yc, loss, reg_y, unobserved, minimizer, need_loss, joint=False):
    """Final objective terms of one chunk: ``(Y_c, (loss, sse, reg_y))`` with unobserved cells
    set to the minimiser; the data are read only when ``need_loss`` (a non-quadratic fit)."""
    ry = reg_y.value(Yc[:-1]) + O.penalty(Yc[-1]) if joint else reg_y.value(Yc)
    f = sse = 0.0
    if need_loss:
        md = _md(path, ssq)
        with _LOCK:
            f = objective(md.D, md.mask(), X, Yc, loss, _ZERO, _ZERO)
    Yc = Yc.copy()
    if unobserved.size:
        Yc[:, unobserved] = minimizer[:, None]
    if need_loss:
        with _LOCK:
            sse = quadratic_loss(md, X, Yc)
    return Yc, (f, sse, ry)


def _t_residuals(path, ssq, X, Yc, moments, rows, direct):
    """Residual statistics of one chunk at the final factors: per-cell ``(sse, count)``
    (``moments``), the sampled times' residuals (``rows``, float32 NaN = missing) and the
    direct sum of squares (``direct``): the predictive options' and the SSE fallback's inputs,
    the same functions as in memory on the chunk's cells."""
    md = _md(path, ssq)
    M = md.mask()
    out = {}
    if moments:
        out["moments"] = residual_moments(md.D, M, X, Yc)
    if rows is not None:
        out["sample"] = residual_sample(md.D, M, X, Yc, max_times=int(rows))
    if direct:
        with _LOCK:
            out["sse"] = direct_sse(md.D, M, X, Yc)
    return out


def _add(parts):
    """Sum a list of equally structured tuples / arrays / floats."""
    first = parts[0]
    if isinstance(first, tuple):
        return tuple(_add([p[i] for p in parts]) for i in range(len(first)))
    out = first.copy() if isinstance(first, np.ndarray) else first
    for p in parts[1:]:
        out = out + p
    return out


def _tree_sum(items, fan_in: int = 16):
    """A dask tree reduction of delayed items with :func:`_add`."""
    import dask

    items = list(items)
    while len(items) > 1:
        items = [dask.delayed(_add, pure=False)(items[i: i + fan_in])
                 for i in range(0, len(items), fan_in)]
    return items[0]


# --------------------------------------------------------------------------- init
def _draw_rows(store: staging.ChunkStore, name: str, rng, rows: int, scale: float = 1.0
               ) -> list[str]:
    """Per-chunk files of ``scale * rng.standard_normal((rows, L))``, drawn one row at a time
    (the same numbers as one call: the generator fills row-major)."""
    paths = store.extra(name, rows)
    for i in range(rows):
        store.write_rows(paths, i, scale * rng.standard_normal(store.n_cells))
    return paths


def _svd_init(store, k, mus, ssqs, rng, unobs_local, minimizer, n_power=1, oversample=5):
    """``(X (k, T), [Y_c (k, Lc) delayed, persisted])`` as :func:`~.fit.initialize` (svd):
    one read of the data for the range, one per power iteration, one for the projection, each
    chunk through the compiled mean-filled products (no filled copy of the chunk)."""
    import dask

    T, L = store.n_times, store.n_cells
    d = dask.delayed
    files = store.files
    args = list(zip(files, ssqs, mus, strict=True))
    if T * L <= SMALL_SVD:
        gram = dask.compute(_tree_sum([d(_t_gram, pure=False)(*a) for a in args]))[0]
        ev, vec = np.linalg.eigh(gram)
        W = np.ascontiguousarray(vec[:, ::-1][:, :k])
    else:
        p = min(k + oversample, T, L)
        om = _draw_rows(store, "omega", rng, p)
        A = dask.compute(_tree_sum([d(_t_range, pure=False)(*a, o)
                                    for a, o in zip(args, om, strict=True)]))[0]
        W, _ = np.linalg.qr(A)
        for _ in range(n_power):
            A = dask.compute(_tree_sum([d(_t_power, pure=False)(*a, W) for a in args]))[0]
            W, _ = np.linalg.qr(A)
    proj = [d(_t_project, nout=2, pure=False)(*a, W) for a in args]
    *Bs, BBt = dask.persist(*[b for b, _ in proj], _tree_sum([bb for _, bb in proj]))
    BBt = dask.compute(BBt)[0]  # (persisted together: one read of each chunk, not two)
    ev, R = np.linalg.eigh(BBt)
    ev, R = ev[::-1][:k], np.ascontiguousarray(R[:, ::-1][:, :k])
    S = np.sqrt(np.maximum(ev, 0.0))  # singular values of the mean-filled matrix
    U = W @ R  # (T, k) left singular vectors
    # deterministic signs: largest |entry| of each right singular vector positive (lowest index)
    parts = dask.compute(*[d(_t_rotate, pure=False)(b, R, int(store.bounds[c]))
                           for c, b in enumerate(Bs)])
    amax = np.stack([p[0] for p in parts])  # (nchunk, k)
    best = np.zeros(k, dtype=np.int64)
    sign = np.ones(k)
    for i in range(k):
        top = amax[:, i].max()
        c = int(np.flatnonzero(amax[:, i] == top)[0])
        best[i] = parts[c][1][i]
        sign[i] = parts[c][2][i] if parts[c][2][i] != 0 else 1.0
    sq = np.sqrt(S)
    X = np.ascontiguousarray((sq * sign)[:, None] * U.T)
    # Y = sqrt(S) sign V^T with V^T = R^T B / S
    yscale = np.where(S > 0, sign / np.where(S > 0, sq, 1.0), 0.0)
    Ys = dask.persist(*[d(_t_y0, pure=False)(b, R, yscale, u, minimizer)
                        for b, u in zip(Bs, unobs_local, strict=True)])
    del Bs
    return X, list(Ys)


# --------------------------------------------------------------------------- the loop
def fit_chunked(
    data: Any,
    rank: int,
    loss: Loss,
    reg_x: Regularizer,
    reg_y: Regularizer,
    *,
    mask: Any = None,
    region: Region | None = None,
    keep_dask: bool = False,
    staging_options: dict | None = None,
    timings: dict | None = None,
    scale: bool = False,
    residual_moments: bool = False,
    residual_rows: int | None = None,
    extras: dict | None = None,
    fit: FitOptions | None = None,
) -> tuple[FitResult, Region | None, Any, str]:
    """Fit a GLRM to (dask-backed) ``data`` chunk by chunk; return ``(result, region, times,
    time_dim)``.

    Same problem, iteration, stopping rule and diagnostics as :func:`~.fit.fit_glrm` (compiled
    fast path only). ``data`` as in :func:`~lrm_cvx.io.staging.stage`. ``result.Y`` is a
    ``(k, L)`` float64 ndarray, or with ``keep_dask`` a dask array of the persisted column
    chunks. Scratch space: ``T * L * 4`` bytes (plus ``(k + 5) * L * 8`` for a randomized SVD
    init, ``k * L * 8`` for ``init="random"``) in ``scratch_dir`` (default: the system temp
    dir), removed at the end. ``timings``, when a dict, receives wall seconds: ``"stage"``
    (region + staging), ``"init"`` (statistics + initialisation), ``"rounds"`` (list, one per
    round) and ``"final"``.

    The predictive options of :class:`~.model.GLRM` chunk by chunk (each is per cell, so each
    column chunk computes its own cells' part with the in-memory functions of
    :mod:`.predictive`): ``offset`` / ``scale`` standardize the data while staging (the fit
    then sees ``(D - offset) / scale``); ``residual_moments`` (``noise="per-cell"``) and
    ``residual_rows`` (``spatial``: the number of sampled times) compute the residual
    statistics at the final factors. ``extras``, when a dict, receives ``"offset"``,
    ``"scale"``, ``"moments"`` (``(sse, count)``), ``"sample"`` and ``"last_mask"`` (the last
    time's observed mask, ``(L,)``) for :func:`~.predictive.set_predictive`, and
    ``"error_masks"`` (the masks of the :func:`~.dynamics.error_rows` snapshots, bit-packed,
    ``error_masks[t]`` a row) for the dynamics' errors-in-variables correction.

    ``fit``: the :class:`~.fit.FitOptions` (``max_iter``, ``tol``, ``init``, ``solver``,
    ``rng``, ``progress``, ``offset``; ``max_inner`` must stay 1; default: its defaults);
    ``staging_options``: the staging's ``chunk_mb``, ``scratch_dir``, ``block_mb``.
    """
    stage_kw = dict(zip(STAGING_KEYS, (256.0, None, 256.0), strict=True))
    unknown = sorted(set(staging_options or {}) - set(stage_kw))
    if unknown:
        raise TypeError(f"fit_chunked() got unexpected staging option(s) {unknown}; the staging "
                        f"options are {sorted(stage_kw)}")
    stage_kw.update(staging_options or {})
    o = FitOptions() if fit is None else fit
    if not isinstance(o, FitOptions) or o.max_inner != 1:
        raise TypeError("fit_chunked(fit=...) takes a FitOptions with max_inner=1")
    max_iter, tol, init, solver, progress, offset = (o.max_iter, o.tol, o.init, o.solver,
                                                     o.progress, o.offset)
    rng = np.random.default_rng() if o.rng is None else o.rng
    if solver not in ("auto", "fast", "cvxpy"):
        raise ModelError(f"solver must be 'auto', 'fast' or 'cvxpy', got {solver!r}")
    if solver == "cvxpy" or not is_fast_capable(loss, reg_x, reg_y):
        raise ModelError(f"the dask fit needs the compiled fast path; loss {loss!r} with "
                         f"{reg_x!r} / {reg_y!r} and solver={solver!r} do not have one")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ModelError(f"max_iter must be an integer >= 0, got {max_iter!r}")
    if not np.isfinite(tol) or tol < 0:
        raise ModelError(f"tol must be >= 0, got {tol!r}")
    if init not in ("svd", "random"):
        raise ModelError(f"init must be 'svd' or 'random', got {init!r}")
    if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)):
        raise ModelError(f"rank must be an integer, got {rank!r}")
    clock = _Clock(timings)
    store, region, times, tdim = staging.stage(data, mask=mask, region=region, timings=timings,
                                               **stage_kw)
    clock.mark("stage")
    try:
        res = _fit_store(store, int(rank), loss, reg_x, reg_y, max_iter, tol, init, rng,
                         progress, keep_dask, clock, offset=bool(offset), scale=bool(scale),
                         moments=bool(residual_moments), rows=residual_rows,
                         extras={} if extras is None else extras)
    finally:
        shutil.rmtree(store.directory, ignore_errors=True)
    return res, region, times, tdim


class _Clock:
    """Wall-clock phases into an optional dict (``mark(name)`` records the time since the
    previous mark; ``"rounds"`` is a list)."""

    def __init__(self, out: dict | None) -> None:
        import time

        self._now = time.perf_counter
        self.out = out
        self.t = self._now()
        if out is not None:
            out["rounds"] = []

    def mark(self, name: str) -> None:
        now = self._now()
        if self.out is not None:
            if name == "rounds":
                self.out["rounds"].append(now - self.t)
            else:
                self.out[name] = now - self.t
        self.t = now


def _fit_store(store, k, loss, reg_x, reg_y, max_iter, tol, init, rng, progress, keep_dask,
               clock=None, *, offset=False, scale=False, moments=False, rows=None, extras=None):
    import dask
    import dask.array as da

    d = dask.delayed
    T, L = store.n_times, store.n_cells
    files = store.files
    bounds = store.bounds
    extras = {} if extras is None else extras
    if k < 1 or k > min(T, L):
        raise ModelError(f"rank must be in [1, min(T, L)] = [1, {min(T, L)}], got {k}")
    floor = 0.0
    if scale:  # the floor of every cell's scale, as the in-memory fit's (one more read)
        parts = dask.compute(*[d(_t_scales, pure=False)(f, offset) for f in files])
        floor = scale_floor(np.concatenate([p[0] for p in parts]),
                            np.concatenate([p[1] for p in parts]))
    stats = dask.compute(*[d(_t_prepare, pure=False)(f, offset, scale, floor) for f in files])
    rows_n = np.sum([s["rows"] for s in stats], axis=0)
    cols = np.concatenate([s["cols"] for s in stats])
    n_obs = int(rows_n.sum())
    if n_obs == 0:
        raise DataError("data has no observed value (all missing / all NaN)")
    empty = np.flatnonzero(rows_n == 0)
    if empty.size:
        raise DataError(f"times {empty[:10].tolist()} have no observation; drop them first")
    L_obs = int(np.count_nonzero(cols))
    warn_sparse_cells(cols, k, offset, reg_y, stacklevel=6)
    kmax = max_identifiable_rank(n_obs, T, L_obs, offset=offset)
    if k > kmax:
        raise ModelError(f"rank {k} leaves no residual degrees of freedom: {n_obs} observed "
                         f"values vs {free_parameters(k, T, L_obs, offset=offset)} free "
                         f"parameters (T={T} times, {L_obs} observed cells); use rank <= "
                         f"{max(kmax, 1)} or more data")
    colsum = np.concatenate([s["colsum"] for s in stats])
    ssqs = [s["ssq_rows"] for s in stats]
    ssq = float(np.sum(ssqs))
    mu_g = float(colsum.sum() / n_obs)
    mu = np.where(cols > 0, colsum / np.maximum(cols, 1), mu_g)
    mus = [mu[bounds[c]: bounds[c + 1]] for c in range(len(files))]
    extras["last_mask"] = np.concatenate([s["last"] for s in stats])
    extras["error_masks"] = _PackedRows(T, [(s["error"], s["n_cells"]) for s in stats])
    extras["offset"] = np.concatenate([s["offset"] for s in stats]) if offset else None
    extras["scale"] = np.concatenate([s["scale"] for s in stats]) if scale else None
    scale_ = float(np.sqrt(ssq / n_obs))
    del stats, colsum
    loss = loss.with_scale(scale_)
    unobserved = np.flatnonzero(cols == 0)
    del cols
    unobs_local = [unobserved[(unobserved >= bounds[c]) & (unobserved < bounds[c + 1])]
                   - bounds[c] for c in range(len(files))]
    minimizer = np.asarray(reg_y.minimizer(k), dtype=np.float64)
    if init == "random":
        s = (max(scale_, 1e-12) ** 2 / k) ** 0.25
        X = s * rng.standard_normal((k, T))
        y0 = _draw_rows(store, "y0", rng, k, s)
        Ys = list(dask.persist(*[d(_t_load_y0, pure=False)(p, u, minimizer)
                                 for p, u in zip(y0, unobs_local, strict=True)]))
    else:
        X, Ys = _svd_init(store, k, mus, ssqs, rng, unobs_local, minimizer)
    clock = clock or _Clock(None)
    clock.mark("init")

    lam_y, lam_x = quadratic_ridge(loss, reg_y), quadratic_ridge(loss, reg_x)
    quad = lam_y is not None and lam_x is not None  # as fit_glrm: the fused quadratic path
    lams = (lam_y, lam_x) if quad else None
    joint = offset and O.supports(reg_x, reg_y)  # as fit_glrm: the offset as a factor
    if joint:
        Ys = list(dask.persist(*[d(_t_offset_row, pure=False)(y) for y in Ys]))
        minimizer = np.append(minimizer, 0.0)

    def factors(X):  # the factors the chunks see: with the offset's row when joint
        return O.augmented(X) if joint else X
    f_loss = None  # quadratic path: the loss at the current (X, Y) from the round's Gram
    history: list[float] = []
    converged = False
    n_iter = 0
    bar = progress_bar(progress, max_iter, "GLRM (dask)")
    try:
        for it in range(max_iter):
            Xr = factors(X)
            outs = [d(_t_round, nout=2, pure=False)(f, q, Xr, y, loss, reg_y, it, lams, joint)
                    for f, q, y in zip(files, ssqs, Ys, strict=True)]
            *Ys, tot = dask.persist(*[o[0] for o in outs], _tree_sum([o[1] for o in outs]))
            fy, G, h, f = dask.compute(tot)[0]
            del outs, tot
            history.append(fy + reg_x.value(X))
            f_loss = float(np.sum(f)) if quad else None  # loss at (X, Y_new)
            if it >= 1 and relative_decrease(history) < tol:
                converged = True
                break
            if joint:  # the offset's row of X stays fixed
                Xn = O.fixed_row_solve(G, h, reg_x.ridge_coefficient)
            else:
                Xn = np.array(solve_block(G, h, reg_x, X), dtype=np.float64)
            if quad:  # loss at (X_new, Y_new) from the same statistics, no pass
                f_loss = float(gram_values(G, h, np.sum(ssqs, axis=0), factors(Xn)).sum())
            elif not (loss.is_quadratic or loss.majorizer_exact):
                f2 = dask.compute(_tree_sum([d(_t_fpass, pure=False)(p, q, factors(Xn), y, loss,
                                                                      it + 1)
                                             for p, q, y in zip(files, ssqs, Ys,
                                                                strict=True)]))[0]
                worse = ~(f2 + reg_x.evaluate(Xn) <= f + reg_x.evaluate(X))
                Xn[:, worse] = X[:, worse]
            X = Xn
            n_iter = it + 1
            clock.mark("rounds")
            if bar is not None:
                bar.update(1)
                bar.set_postfix(objective=f"{history[-1]:.6g}")
    finally:
        if bar is not None:
            bar.close()
    need = f_loss is None
    Xr = factors(X)
    outs = [d(_t_final, nout=2, pure=False)(f, q, Xr, y, loss, reg_y, u, minimizer, need, joint)
            for f, q, y, u in zip(files, ssqs, Ys, unobs_local, strict=True)]
    *Ys, tot = dask.persist(*[o[0] for o in outs], _tree_sum([o[1] for o in outs]))
    fsum, sse, ry = dask.compute(tot)[0]
    if not need:  # the quadratic path (as fit_glrm): loss and SSE from the last statistics
        fsum, sse = f_loss, max(f_loss, 0.0)
    history.append(float(fsum) + reg_x.value(X) + ry)
    direct = sse <= SSE_RTOL * ssq  # the Gram identity cancelled: sum the residuals directly
    if moments or rows is not None or direct:
        res = dask.compute(*[d(_t_residuals, pure=False)(f, q, Xr, y, moments, rows, direct)
                             for f, q, y in zip(files, ssqs, Ys, strict=True)])
        if moments:
            extras["moments"] = tuple(np.concatenate([r["moments"][i] for r in res])
                                      for i in range(2))
        if rows is not None:
            extras["sample"] = np.concatenate([r["sample"] for r in res], axis=1)
        if direct:
            sse = float(sum(r["sse"] for r in res))
            if is_plain_quadratic(loss):
                history[-1] = sse + reg_x.value(X) + ry
    converged = finish_convergence(history, converged, max_iter, tol, stacklevel=6)
    widths = np.diff(bounds)
    k1 = k + 1 if joint else k
    if keep_dask:
        Y = da.concatenate([da.from_delayed(y, shape=(k1, int(w)), dtype=np.float64)
                            for y, w in zip(Ys, widths, strict=True)], axis=1)
    else:
        Y = np.concatenate(dask.compute(*Ys), axis=1)
    off = None
    if joint:  # the offset's correction, added to the staged observed mean (in data units)
        off = np.asarray(Y[k], dtype=np.float64)
        Y = Y[:k] if keep_dask else np.ascontiguousarray(Y[:k])
        sc = extras.get("scale")
        extras["offset"] = extras["offset"] + (off if sc is None else off * sc)
    clock.mark("final")
    return FitResult(
        X=np.ascontiguousarray(X), Y=Y, objective=history, n_iter=n_iter,
        converged=converged, unobserved_cells=unobserved.astype(np.int64), n_observed=n_obs,
        sse=float(sse), noise_std=noise_std(sse, n_obs, k, T, L_obs,
                                            extra=L_obs if offset else 0), solver="fast",
        offset=off,
    )
