"""Kriging of the GP residual: direct, local (Vecchia-style) and whole-grid FFT, and the GP
pieces the gp-variance criterion and static placement share.

No dense ``L x L`` matrix is ever built (see the package docstring). :class:`GridConv` is the
exact FFT convolution on a grid rectangle (the FFT kriging and the structured gp-variance
oracle); :func:`gp_noise`, :func:`gp_latent_cov` and :func:`check_gp_inputs` are the GP model
of the planners' criterion (moved here from ``information``, which keeps the old names).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, Literal

import numba
import numpy as np
import scipy.linalg
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from .._validation import check_positive
from ..errors import DataError, ModelError, PlanningError, SolverError
from ..region import EARTH_RADIUS_KM, Region
from .covariance import MODELS, ResidualCovariance, arc_distance, chord_distance

__all__ = ["krige", "krige_many", "krige_grid_fft", "krige_core", "check_cov",
           "jittered_cholesky", "prepare_kriging", "GridConv", "gp_noise", "gp_latent_cov",
           "gp_residual_cov", "check_gp_inputs", "grid_rect", "FFT_KRIGE_MIN_WORK",
           "FFT_KRIGE_VAR_TOL", "FFT_KRIGE_REACH", "MAX_DIRECT"]

_SQRT3 = np.sqrt(3.0)
_SQRT5 = np.sqrt(5.0)
_CHUNK_BYTES = 200_000_000
MAX_DIRECT = 2000
"""Direct kriging (one Cholesky of the observations) up to this many observations."""


# ---------------------------------------------------------------------------- kriging
def check_cov(cov: Any) -> ResidualCovariance:
    if not isinstance(cov, ResidualCovariance):
        raise ModelError(f"cov must be a ResidualCovariance, got {type(cov).__name__}")
    return cov


def jittered_cholesky(K: np.ndarray, scale: float, what: str) -> np.ndarray:
    """Lower Cholesky factor; adds a tiny jitter (1e-10 .. 1e-6 of ``scale``) when ``K`` is
    numerically singular (duplicate cells without a nugget, a smooth gaussian model)."""
    for jitter in (0.0, 1e-10, 1e-8, 1e-6):
        try:
            A = K + (jitter * scale) * np.eye(K.shape[-1]) if jitter else K
            return np.linalg.cholesky(A)
        except np.linalg.LinAlgError:
            continue
    raise SolverError(f"the {what} covariance is not positive definite even with jitter 1e-6")


def _chunk(total: int, per_item: int) -> int:
    return int(max(1, min(total, _CHUNK_BYTES // max(per_item, 1))))


def _spatial_cov_inplace(cov: ResidualCovariance, d: np.ndarray) -> np.ndarray:
    """``sill * rho(d / range)`` written over the float64 array ``d`` (saves big temporaries)."""
    h = d
    h *= 1.0 / cov.range
    if cov.model == "exponential":
        np.negative(h, out=h)
        np.exp(h, out=h)
    elif cov.model == "gaussian":
        h *= h
        np.negative(h, out=h)
        np.exp(h, out=h)
    else:
        h *= _SQRT3 if cov.model == "matern32" else _SQRT5
        e = np.exp(-h)
        if cov.model == "matern52":
            e *= 1.0 + h + h * h / 3.0
        else:
            e *= 1.0 + h
        h[...] = e
    h *= cov.sill
    return h


def krige_core(
    cov: ResidualCovariance,
    obs_xyz: np.ndarray,
    Z: np.ndarray,
    tgt_xyz: np.ndarray,
    *,
    method: str,
    neighbors: int,
    cutoff: float | None,
    want_var: bool,
    Ys: np.ndarray | None = None,
    Yt: Callable[[np.ndarray], np.ndarray] | None = None,
    cov_x: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple kriging of ``Z`` (``(n, r)``: r snapshots sharing the ``n`` observations) at the
    targets. Returns mean ``(r, n_targets)`` and the latent variance ``(n_targets,)``.

    With ``Ys`` (``(k, n)``, the trend basis at the observations), ``Yt(idx)`` (``(k, len(idx))``
    basis at those targets) and ``cov_x`` (GLS covariance of the trend coefficients), the
    variance gets the universal-kriging term ``u^T cov_x u`` with ``u = y_t - Ys C^-1 k_t``."""
    metric = cov.metric
    n, r = Z.shape
    nt = tgt_xyz.shape[0]
    mean = np.zeros((r, nt))
    var = np.full(nt, cov.sill) if want_var else None
    trend = Ys is not None and want_var

    def add_trend(sel: np.ndarray, u: np.ndarray) -> None:
        var[sel] += np.einsum("kc,kl,lc->c", u, cov_x, u)

    if n == 0:
        if trend:
            for lo in range(0, nt, 100_000):
                sel = np.arange(lo, min(nt, lo + 100_000))
                add_trend(sel, Yt(sel))
        return mean, var
    # targets near at least one observation; the rest keep the prior
    if cutoff is not None and cov.sill > 0:
        reach = chord_distance(cov.cutoff_distance(cutoff), metric)
        tree = cKDTree(obs_xyz)
        if np.isfinite(reach):
            dnear, _ = tree.query(tgt_xyz, k=1, distance_upper_bound=reach * (1 + 1e-12))
            near = np.flatnonzero(np.isfinite(dnear))
            if trend:
                far = np.flatnonzero(~np.isfinite(dnear))
                for lo in range(0, far.size, 100_000):
                    sel = far[lo:lo + 100_000]
                    add_trend(sel, Yt(sel))
        else:
            near = np.arange(nt)
    else:
        tree = None
        near = np.arange(nt)
    if near.size == 0 or cov.sill == 0:
        if trend and cov.sill == 0:  # pure nugget: GLS trend only
            for lo in range(0, near.size, 100_000):
                sel = near[lo:lo + 100_000]
                add_trend(sel, Yt(sel))
        return mean, var

    if method == "direct":
        K = cov.covariance(arc_distance(cdist(obs_xyz, obs_xyz), metric))
        np.fill_diagonal(K, cov.sill + cov.nugget)
        Lc = jittered_cholesky(K, cov.total_variance, "observation")
        alpha = scipy.linalg.cho_solve((Lc, True), Z)  # (n, r)
        W = scipy.linalg.solve_triangular(Lc, Ys.T, lower=True) if trend else None  # (n, k)
        c = _chunk(near.size, 24 * n)
        for lo in range(0, near.size, c):
            sel = near[lo:lo + c]
            Kts = _spatial_cov_inplace(cov, arc_distance(cdist(tgt_xyz[sel], obs_xyz), metric))
            mean[:, sel] = (Kts @ alpha).T
            if want_var:
                V = scipy.linalg.solve_triangular(Lc, Kts.T, lower=True, check_finite=False)
                var[sel] -= np.einsum("ij,ij->j", V, V)
                if trend:
                    add_trend(sel, Yt(sel) - W.T @ V)
        return mean, var

    # local (nearest-neighbour) kriging: one small system per target, compiled; consecutive
    # targets with the same neighbour set (common on a grid) share one factorisation
    m = int(min(neighbors, n))
    tree = tree if tree is not None else cKDTree(obs_xyz)
    c = _chunk(near.size, 8 * m * (6 + r))
    model_id = MODELS.index(cov.model)
    for lo in range(0, near.size, c):
        sel = near[lo:lo + c]
        dist, idx = tree.query(tgt_xyz[sel], k=m)
        dist = np.asarray(dist, dtype=np.float64).reshape(sel.size, m)
        idx = np.asarray(idx, dtype=np.int64).reshape(sel.size, m)
        order = np.argsort(idx, axis=1, kind="stable")
        idx = np.ascontiguousarray(np.take_along_axis(idx, order, axis=1))
        dist = np.ascontiguousarray(arc_distance(np.take_along_axis(dist, order, axis=1), metric))
        w = np.empty((sel.size, m))
        v = np.empty(sel.size)
        status = _local_weights(idx, dist, obs_xyz, model_id, cov.sill, cov.range, cov.nugget,
                                metric == "km", w, v)
        if status < 0:
            raise SolverError(
                "a neighbourhood covariance is not positive definite even with jitter 1e-6"
            )
        mean[:, sel] = np.einsum("cm,cmr->rc", w, Z[idx])
        if want_var:
            var[sel] = v
            if trend:
                add_trend(sel, Yt(sel) - np.einsum("kcm,cm->kc", Ys[:, idx], w))
    return mean, var


FFT_KRIGE_MIN_WORK: float = 2e7
""":func:`krige_grid_fft` replaces direct kriging of a whole grid-metric region when
``n_obs x n_targets`` exceeds this (``LatentPosterior.predict``)."""
FFT_KRIGE_VAR_TOL: float = 1e-6
"""Variance tolerance of :func:`krige_grid_fft`, relative to the nugget."""


def grid_rect(lo: np.ndarray, hi: np.ndarray, margin: tuple[float, float],
              shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Grid rectangle ``(row0, col0, n_rows, n_cols)`` of ``[lo - margin, hi + margin]``
    (``margin`` per axis: a covariance's ``reach``), clipped to the grid."""
    mr, mc = (int(np.ceil(v)) if np.isfinite(v) else max(shape) for v in margin)
    r0, c0 = max(int(lo[0]) - mr, 0), max(int(lo[1]) - mc, 0)
    r1, c1 = min(int(hi[0]) + mr, shape[0] - 1), min(int(hi[1]) + mc, shape[1] - 1)
    return r0, c0, r1 - r0 + 1, c1 - c0 + 1


FFT_KRIGE_DIRECT_RATIO: float = 0.1
""":func:`krige_grid_fft` forms each ``k(t, o_j)`` from the kernel's lag table and takes its
products with the weights by BLAS (exact, no transform) when ``n_targets x n_obs`` is at most
this times ``n_images x S log2 S`` (``S`` the FFT's size, ``n_images <= n_obs + k + 2`` the
convolutions the FFT path would run): the direct path reads each ``k(t, o_j)`` twice and
multiplies it into every image, a transform pair costs ``~ 5 S log2 S`` flops per image."""

FFT_KRIGE_REACH: float = 1e-17
""":func:`krige_grid_fft` convolves over the observations' bounding box grown by the
covariance's ``reach(FFT_KRIGE_REACH)``; beyond it every kernel value is below this fraction of
the sill, and the residual's kriged mean and variance reduction there are 0."""


def krige_grid_fft(cov: ResidualCovariance, region: Region, obs_cells: np.ndarray,
                   z: np.ndarray, *, Ys: np.ndarray | None = None, Yall: np.ndarray | None = None,
                   cov_x: np.ndarray | None = None, var_tol: float = FFT_KRIGE_VAR_TOL
                   ) -> tuple[np.ndarray, np.ndarray, int]:
    """Kriging of the residuals ``z`` (``(n,)``, at the distinct ``obs_cells``) at *every*
    cell of a grid-metric region by FFT convolutions (no distance matrix to the targets).

    The residual covariance at the observations is ``C = sill R + nugget I``; with
    ``R = U diag(mu) U^T`` and ``lambda = sill mu + nugget``, for a target ``t`` with
    ``k_t = (k(t, o_j))_j`` and projections ``p_m(t) = u_m^T k_t`` (one convolution each):

    * mean ``k_t^T C^-1 z = sum_j alpha_j k(t, o_j)``: one convolution, exact (up to rounding);
    * variance reduction ``k_t^T C^-1 k_t = sum_m p_m^2 / lambda_m``: the leading ``M``
      eigenvectors exactly, the rest through ``||k_t||^2 - sum_{m<=M} p_m^2`` (one convolution
      with ``k^2``) at the weight ``1 / nugget``: an over-estimate by at most
      ``(lambda_{M+1} - nugget) / nugget^2 * max_t ||k_t||^2``, and ``M`` is the smallest for
      which that is ``<= var_tol * nugget`` (the predictive variance is >= the nugget);
    * universal kriging (``Ys (k, n)`` the trend basis at the observations, ``Yall (k, L)`` at
      every cell, ``cov_x`` the GLS covariance of the trend coefficients): ``+ u_t^T cov_x
      u_t``, ``u_t = y_t - Ys C^-1 k_t``, ``Ys C^-1 k_t`` by ``k`` convolutions with the
      weights ``C^-1 Ys^T`` (exact).

    The convolutions cover the observations' bounding box grown by the covariance's
    ``reach(FFT_KRIGE_REACH)`` (:data:`FFT_KRIGE_REACH`; every ``k_t`` beyond it is below
    ``1e-17`` sill, taken as 0), and the mean, the ``M`` projections and the trend's ``k``
    share one batched transform (:meth:`GridConv.many`).

    Returns ``(mean (L,), latent variance (L,), M)`` in the region's cell order. Needs a
    nugget > 0 and ``metric="grid"``.
    """
    if cov.metric != "grid":
        raise ModelError("krige_grid_fft needs metric='grid'")
    nug = float(cov.nugget)
    if not nug > 0:
        raise ModelError("krige_grid_fft needs a nugget > 0")
    obs_cells = np.asarray(obs_cells, dtype=np.int64)
    z = np.asarray(z, dtype=np.float64).ravel()
    gi = region.grid_index
    shape = region.shape
    go = gi[obs_cells]
    xo = cov.points(region, obs_cells)
    R = cov.covariance(cdist(xo, xo), nugget=False) / cov.sill
    np.fill_diagonal(R, 1.0)
    mu, U = np.linalg.eigh(0.5 * (R + R.T))
    mu = np.maximum(mu, 0.0)
    lam = cov.sill * mu + nug
    alpha = U @ ((U.T @ z) / lam)
    lo, hi = go.min(axis=0), go.max(axis=0)
    window = (int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    out = grid_rect(lo, hi, cov.reach(FFT_KRIGE_REACH), shape)
    near = np.flatnonzero((gi[:, 0] >= out[0]) & (gi[:, 0] < out[0] + out[2])
                          & (gi[:, 1] >= out[1]) & (gi[:, 1] < out[1] + out[3]))
    loc = (go[:, 0] - window[0], go[:, 1] - window[1])
    rows, cols = gi[near, 0] - out[0], gi[near, 1] - out[1]

    def kern(d):
        return cov.covariance(d, nugget=False)

    n, n_near = z.size, near.size
    whole = n_near == gi.shape[0]  # every cell within reach: slices instead of gathers

    def cells(lo: int, hi: int) -> Any:
        return slice(lo, hi) if whole else near[lo:hi]

    conv_work = float(np.prod(_fft_shape(window, out))) if n_near else 0.0
    n_img = n + 2 + (0 if Ys is None else Ys.shape[0])  # at most: mean, k^2, M <= n, trend
    direct = float(n_near) * n <= (FFT_KRIGE_DIRECT_RATIO * n_img * conv_work
                                   * np.log2(max(conv_work, 2.0)))
    # ||k_t||^2: one convolution with k^2 (either way: the same leading eigenvectors)
    img = np.zeros(window[2:])
    np.add.at(img, loc, 1.0)
    kk = np.zeros(gi.shape[0])
    kk[near] = GridConv(window, out, lambda d: kern(d) ** 2, cov.anisotropy)(img)[rows, cols]
    if direct:  # k(t, o_j) gathered from the kernel's lag table, products by BLAS
        tab, dr0, dc0 = lag_table(window, out, kern, cov.anisotropy)
        step = _chunk(n_near, 8 * (2 * n + z.size + 8))
        go_r = np.ascontiguousarray(go[:, 0] + dr0, dtype=np.int64)
        go_c = np.ascontiguousarray(go[:, 1] + dc0, dtype=np.int64)

        def kernel_rows(lo: int, hi: int) -> np.ndarray:
            t = near[lo:hi]
            return _gather_lags(tab, np.ascontiguousarray(gi[t, 0], dtype=np.int64),
                                np.ascontiguousarray(gi[t, 1], dtype=np.int64), go_r, go_c)
    else:
        conv = GridConv(window, out, kern, cov.anisotropy)
    kmax = float(np.max(kk)) if kk.size else 0.0
    # leading eigenvectors: those whose weight differs from 1/nugget by more than the
    # tolerance allows (the error is <= (lambda_cut - nugget) / nugget^2 * max_t ||k_t||^2)
    thresh = var_tol * nug ** 3 / max(kmax, 1e-300)
    trend = Ys is not None and Yall is not None and cov_x is not None
    order = np.argsort(-lam)
    lead = order[(lam[order] - nug) > thresh]
    # the weights of every product with k: alpha, the leading eigenvectors and, for
    # universal kriging, C^-1 Ys^T (Ys C^-1 k_t = sum_j (C^-1 Ys^T)_j k(t, o_j), exact)
    weights = [alpha[:, None], U[:, lead]]
    if trend:
        weights.append(U @ ((U.T @ Ys.T) / lam[:, None]))
    weights = np.concatenate(weights, axis=1)
    scale = 1.0 / lam[lead] - 1.0 / nug
    mean = np.zeros(gi.shape[0])
    red = kk / nug
    u = np.array(Yall, dtype=np.float64, copy=True) if trend else None

    def fold(q0: int, P: np.ndarray, at: Any) -> None:
        """Images ``q0, q0 + 1, ...`` (rows of ``P``) at the cells ``at``, in image order."""
        for q, pq in enumerate(P, start=q0):
            if q == 0:
                mean[at] = pq
            elif q <= lead.size:
                red[at] += scale[q - 1] * pq * pq
            else:
                u[q - 1 - lead.size, at] -= pq

    if direct:
        for lo in range(0, n_near, step):
            fold(0, weights.T @ kernel_rows(lo, lo + step), cells(lo, lo + step))
    else:
        for q0, P in conv.many(weights.T, loc, (rows, cols)):
            fold(q0, P, cells(0, n_near))
    var = np.full(gi.shape[0], float(cov.sill))
    var -= red
    if trend:
        var += np.einsum("kc,kl,lc->c", u, cov_x, u)
    return mean, var, int(lead.size)


@numba.njit(cache=True)
def _gather_lags(tab: np.ndarray, tr: np.ndarray, tc: np.ndarray, orr: np.ndarray,
                 oc: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``K[j, t] = tab[tr[t] - orr[j], tc[t] - oc[j]]`` (the lag table's offsets folded into
    ``orr``, ``oc``): the kernel between observations and targets, no index temporaries (one
    observation's row at a time: the targets' neighbouring cells read neighbouring lags)."""
    K = np.empty((orr.size, tr.size))
    for j in range(orr.size):
        for t in range(tr.size):
            K[j, t] = tab[tr[t] - orr[j], tc[t] - oc[j]]
    return K


@numba.njit(cache=True)
def _rho_nb(model_id: int, h: float) -> float:
    if model_id == 0:
        return np.exp(-h)
    if model_id == 1:
        s = _SQRT3 * h
        return (1.0 + s) * np.exp(-s)
    if model_id == 2:
        s = _SQRT5 * h
        return (1.0 + s + s * s / 3.0) * np.exp(-s)
    return np.exp(-h * h)


@numba.njit(cache=True)
def _chol_inplace(A: np.ndarray, m: int) -> bool:
    """Lower Cholesky factor of ``A[:m, :m]`` in place (lower triangle); False if not PD."""
    for j in range(m):
        s = A[j, j]
        for q in range(j):
            s -= A[j, q] * A[j, q]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        A[j, j] = d
        for i in range(j + 1, m):
            s = A[i, j]
            for q in range(j):
                s -= A[i, q] * A[j, q]
            A[i, j] = s / d
    return True


@numba.njit(cache=True)
def _local_weights(idx, dist, xyz, model_id, sill, scale, nugget, km, w_out, var_out):
    """Kriging weights ``w_t = K_t^-1 k_t`` and latent variances ``sill - k_t^T w_t`` of each
    target ``t`` from its neighbours ``idx[t]`` (sorted) at distances ``dist[t]``. Returns the
    number of factorisations that needed jitter, or -1 when one failed even with jitter."""
    c, m = idx.shape
    dim = xyz.shape[1]
    K = np.empty((m, m))
    Lf = np.empty((m, m))
    y = np.empty(m)
    two_r = 2.0 * EARTH_RADIUS_KM
    jittered = 0
    have = False
    for t in range(c):
        same = have
        if have:
            for i in range(m):
                if idx[t, i] != idx[t - 1, i]:
                    same = False
                    break
        if not same:
            for i in range(m):
                for j in range(i):
                    d2 = 0.0
                    for q in range(dim):
                        diff = xyz[idx[t, i], q] - xyz[idx[t, j], q]
                        d2 += diff * diff
                    d = np.sqrt(d2)
                    if km:
                        d = two_r * np.arcsin(min(1.0, d / two_r))
                    K[i, j] = sill * _rho_nb(model_id, d / scale)
                K[i, i] = sill + nugget
            ok = False
            for jitter in (0.0, 1e-10, 1e-8, 1e-6):
                for i in range(m):
                    for j in range(i + 1):
                        Lf[i, j] = K[i, j]
                    Lf[i, i] += jitter * (sill + nugget)
                if _chol_inplace(Lf, m):
                    ok = True
                    if jitter > 0:
                        jittered += 1
                    break
            if not ok:
                return -1
            have = True
        # y = L^-1 k_t ; w = L^-T y ; var = sill - |y|^2
        acc = 0.0
        for i in range(m):
            s = sill * _rho_nb(model_id, dist[t, i] / scale)
            for q in range(i):
                s -= Lf[i, q] * y[q]
            y[i] = s / Lf[i, i]
            acc += y[i] * y[i]
        var_out[t] = sill - acc
        for i in range(m - 1, -1, -1):
            s = y[i]
            for q in range(i + 1, m):
                s -= Lf[q, i] * w_out[t, q]
            w_out[t, i] = s / Lf[i, i]
    return jittered


def _check_method(method: str) -> str:
    if method not in ("auto", "direct", "neighbors"):
        raise ModelError(f"method must be 'auto', 'direct' or 'neighbors', got {method!r}")
    return method


def prepare_kriging(
    cov: Any, region: Region, cells: Any, targets: Any, neighbors: int, cutoff: float | None,
    method: str,
) -> tuple[ResidualCovariance, np.ndarray, np.ndarray, int, float | None, str]:
    cov = check_cov(cov)
    if not isinstance(region, Region):
        raise DataError(f"region must be a Region, got {type(region).__name__}")
    cells = region.check_cells(np.ravel(cells), "cells")
    if np.unique(cells).size != cells.size:
        raise DataError("cells has repeated cell indices: give one value per observed cell")
    tg = (np.arange(region.n_cells) if targets is None
          else region.check_cells(np.ravel(targets), "targets"))
    if int(neighbors) < 1:
        raise ModelError(f"neighbors must be >= 1, got {neighbors!r}")
    if cutoff is not None:
        cutoff = check_positive(cutoff, "cutoff", strict=True, error=ModelError)
    return cov, cells, tg, int(neighbors), cutoff, _check_method(method)


def krige_many(
    cov: ResidualCovariance,
    region: Region,
    cells: Any,
    values: Any,
    *,
    targets: Any = None,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple (zero-mean) kriging of several snapshots observed at (subsets of) the same cells.

    ``values`` is ``(m, n)`` with NaN where a snapshot did not observe ``cells[j]``; snapshots
    with the same pattern share one factorisation. Returns mean and std ``(m, n_targets)``
    float64 (targets default to all L cells). ``method="auto"`` solves with all observations
    (``"direct"``: one ``n x n`` Cholesky, targets streamed in ~200 MB chunks) when ``n <= 2000``
    and with each target's ``neighbors`` nearest observations otherwise. Targets farther than
    ``cov.cutoff_distance(cutoff)`` from every observation get mean 0 and the prior std without a
    solve (``cutoff=None`` disables that). The std is that of the latent residual (it is 0 at an
    observed cell when ``nugget == 0``); ``include_nugget=True`` adds the nugget, for predicting a
    new measurement.
    """
    cov, cells, tg, neighbors, cutoff, method = prepare_kriging(
        cov, region, cells, targets, neighbors, cutoff, method)
    V = np.asarray(values, dtype=np.float64)
    if V.ndim == 1:
        V = V[None, :]
    if V.ndim != 2 or V.shape[1] != cells.size:
        raise DataError(
            f"values must be (m, n) with n = len(cells) = {cells.size}, got shape {V.shape}"
        )
    if np.isinf(V).any():
        raise DataError("values has infinite entries")
    obs = np.isfinite(V)
    patterns, inv = np.unique(obs, axis=0, return_inverse=True)
    inv = inv.ravel()
    tgt_xyz = cov.points(region, tg)
    all_xyz = cov.points(region, cells)
    mean = np.zeros((V.shape[0], tg.size))
    var = np.empty((V.shape[0], tg.size)) if return_std else None
    for p, pat in enumerate(patterns):
        rows = np.flatnonzero(inv == p)
        n = int(pat.sum())
        meth = method if method != "auto" else ("direct" if n <= MAX_DIRECT else "neighbors")
        mu, vv = krige_core(cov, all_xyz[pat], V[np.ix_(rows, np.flatnonzero(pat))].T, tgt_xyz,
                             method=meth, neighbors=neighbors, cutoff=cutoff, want_var=return_std)
        mean[rows] = mu
        if return_std:
            var[rows] = vv
    if not return_std:
        return mean, None
    if include_nugget:
        var += cov.nugget
    return mean, np.sqrt(np.maximum(var, 0.0))


def krige(
    cov: ResidualCovariance,
    region: Region,
    cells: Any,
    values: Any,
    *,
    targets: Any = None,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple kriging of the residual at ``targets`` (default all L cells) from ``values`` at
    ``cells`` (``(n,)``, NaN = not observed): mean and std ``(n_targets,)``; see
    :func:`krige_many` for the options (std is ``None`` when ``return_std=False``)."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1:
        raise DataError(f"values must be 1-D (one per cell), got shape {v.shape}")
    mean, std = krige_many(cov, region, cells, v[None, :], targets=targets, neighbors=neighbors,
                           method=method, cutoff=cutoff, include_nugget=include_nugget,
                           return_std=return_std)
    return mean[0], (None if std is None else std[0])


# ---------------------------------------------------------------------------- FFT convolution
def _fft_shape(window: tuple[int, int, int, int], out: tuple[int, int, int, int]
               ) -> tuple[int, int]:
    """The FFT size of :class:`GridConv`'s linear convolution of ``window`` onto ``out``."""
    import scipy.fft as sfft

    return (sfft.next_fast_len(window[2] + out[2] - 1, real=True),
            sfft.next_fast_len(window[3] + out[3] - 1, real=True))


def lag_table(window: tuple[int, int, int, int], out: tuple[int, int, int, int], h: Any,
              anisotropy: float = 1.0) -> tuple[np.ndarray, int, int]:
    """``(tab, dr0, dc0)``: ``h`` at every grid offset from a cell of ``window`` to a cell of
    ``out`` (rectangles as in :class:`GridConv`), ``h(x - i) = tab[dr - dr0, dc - dc0]`` for
    the row and column offsets ``(dr, dc)`` of ``x - i``: the table :class:`GridConv`
    transforms, and the direct products of :func:`krige_grid_fft` gather from."""
    r0, c0, a, b = window
    o_r, o_c, oa, ob = out
    dr0, dc0 = o_r - r0 - a + 1, o_c - c0 - b + 1
    dr = np.arange(dr0, o_r + oa - r0, dtype=np.float64)
    dc = np.arange(dc0, o_c + ob - c0, dtype=np.float64) / anisotropy
    return h(np.sqrt(dr[:, None] ** 2 + dc[None, :] ** 2)), int(dr0), int(dc0)


class GridConv:
    """``out[x] = sum_{i in window} f[i] h(|i - x|)`` for ``x`` in an output rectangle, by FFT.

    ``window`` and ``out`` are grid rectangles ``(row0, col0, n_rows, n_cols)`` (grid units);
    ``h`` a function of the grid distance ``sqrt(dr^2 + (dc / anisotropy)^2)`` (a covariance's,
    :class:`~lrm_cvx.spatial.ResidualCovariance`). Linear (not circular) convolution: the FFT
    size is ``window + out - 1`` per axis, so the result is exact up to float rounding.
    """

    def __init__(self, window: tuple[int, int, int, int], out: tuple[int, int, int, int],
                 h: Any, anisotropy: float = 1.0) -> None:
        import scipy.fft as sfft

        self.a, self.b, self.oa, self.ob = window[2], window[3], out[2], out[3]
        self.s = _fft_shape(window, out)
        self.H = sfft.rfft2(lag_table(window, out, h, anisotropy)[0], s=self.s)

    def __call__(self, f: np.ndarray) -> np.ndarray:
        import scipy.fft as sfft

        full = sfft.irfft2(sfft.rfft2(f, s=self.s, workers=-1) * self.H, s=self.s, workers=-1)
        return full[self.a - 1:self.a - 1 + self.oa, self.b - 1:self.b - 1 + self.ob]

    def many(self, weights: np.ndarray, loc: tuple[np.ndarray, np.ndarray],
             at: tuple[np.ndarray, np.ndarray]) -> Iterator[tuple[int, np.ndarray]]:
        """The convolution of each row of ``weights`` (``(B, n)``, values at the window's
        cells ``loc``, ``(rows, cols)`` within it) read at the output cells ``at``, by chunks
        of images transformed together (one batched ``rfft2`` / ``irfft2`` per
        ``_CHUNK_BYTES``): yields ``(first image, (b, |at|) values)``; each image is the same
        convolution as :meth:`__call__`."""
        import scipy.fft as sfft

        weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
        n_img = weights.shape[0]
        step = _chunk(n_img, 32 * self.s[0] * self.s[1])
        r, c = at[0] + self.a - 1, at[1] + self.b - 1
        for lo in range(0, n_img, step):
            w = weights[lo:lo + step]
            buf = np.zeros((w.shape[0], *self.s))
            np.add.at(buf, (np.arange(w.shape[0])[:, None], loc[0][None, :], loc[1][None, :]),
                      w)
            spec = sfft.rfft2(buf, axes=(-2, -1), workers=-1, overwrite_x=True)
            del buf
            spec *= self.H
            full = sfft.irfft2(spec, s=self.s, axes=(-2, -1), workers=-1, overwrite_x=True)
            del spec
            yield lo, full[:, r, c]

    def product(self, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
        """``self(f1 * f2)``, the same numbers, with the product written straight into the
        zero-padded transform's input and the spectra multiplied in place (no window-sized
        temporaries)."""
        import scipy.fft as sfft

        buf = np.zeros(self.s)
        np.multiply(f1, f2, out=buf[:self.a, :self.b])
        spec = sfft.rfft2(buf, workers=-1, overwrite_x=True)
        spec *= self.H
        full = sfft.irfft2(spec, s=self.s, workers=-1, overwrite_x=True)
        return full[self.a - 1:self.a - 1 + self.oa, self.b - 1:self.b - 1 + self.ob]


# ---------------------------------------------------------------------------- the GP criterion
def gp_noise(spatial_cov: Any) -> float:
    """Observation noise of the GP criterion: the nugget, floored at 1e-9 x the total variance
    (a fitted nugget of ~0 would make the posterior variance at observed cells exactly 0)."""
    return max(float(spatial_cov.nugget), 1e-9 * float(spatial_cov.total_variance))


def gp_residual_cov(region: Any, spatial_cov: Any, rows: np.ndarray, cols: np.ndarray
                    ) -> np.ndarray:
    """``sill rho(d_ij)`` (``(|rows|, |cols|)``): the GP residual's covariance between the
    cells ``rows`` and ``cols`` without its nugget, the part of :func:`gp_latent_cov` that does
    not depend on the latent prior."""
    a = spatial_cov.points(region, rows)
    b = spatial_cov.points(region, cols)
    return spatial_cov.covariance(arc_distance(cdist(a, b), spatial_cov.metric), nugget=False)


def gp_latent_cov(Y: np.ndarray, S0: np.ndarray, region: Any, spatial_cov: Any,
                   rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``K(rows, cols) = y_i^T S0 y_j + sill rho(d_ij)``: prior covariance of the latent field
    (low-rank trend with prior ``N(., S0)`` plus the GP residual without its nugget,
    :func:`gp_residual_cov`)."""
    K = gp_residual_cov(region, spatial_cov, rows, cols)
    K += Y[:, rows].T @ S0 @ Y[:, cols]
    return K


def check_gp_inputs(Y: np.ndarray, region: Any, spatial_cov: Any, prior_cov: Any
                    ) -> np.ndarray:
    """The gp-variance criterion's inputs checked (PlanningError naming the missing one): a
    Region, a ResidualCovariance and a finite ``(k, k)`` prior covariance of the latent vector
    (``k = Y.shape[0]``); returns the symmetrised prior covariance ``S0``."""
    if not isinstance(region, Region):
        raise PlanningError("the gp-variance criterion needs the region")
    if not isinstance(spatial_cov, ResidualCovariance):
        raise PlanningError("the gp-variance criterion needs spatial_cov (a ResidualCovariance, "
                            "e.g. model.spatial_cov_ of GLRM(spatial='exponential'))")
    k = Y.shape[0]
    S0 = np.asarray(prior_cov, dtype=np.float64) if prior_cov is not None else None
    if S0 is None or S0.shape != (k, k) or not np.all(np.isfinite(S0)):
        raise PlanningError(f"the gp-variance criterion needs prior_cov, a ({k}, {k}) matrix "
                            "(the prior covariance of x, e.g. from prior='empirical')")
    return 0.5 * (S0 + S0.T)
