"""The algebra of averaged observations (sensor footprints, towed sensors).

An averaged observation is ``z = B f + e`` over the snapshot's latent field (``B (m, L)`` sparse
weights); plain arrays in, arrays out, called by
:class:`~lrm_cvx.belief.posterior.LatentPosterior` (``update_rows``, ``predict``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sps
from scipy.spatial.distance import cdist

from ..errors import DataError

__all__ = ["check_rows", "fit_rows", "row_noise", "row_terms", "row_kriging", "ERRORS"]

ERRORS = ("independent", "shared")
"""How the cell errors inside one averaged observation relate: independent (the model's
assumption: averaging ``n`` cells divides the noise variance by ``n``) or shared (equal within
the observation: the average keeps the cells' noise; a conservative bound when the residuals
are spatially correlated and no GP residual is fitted)."""

_NOISE_FLOOR = 1e-30


def check_rows(rows: Any, L: int, values: Any = None, name: str = "rows"
               ) -> sps.csr_matrix | tuple[sps.csr_matrix, np.ndarray]:
    """``rows`` (averaging weights, sparse or dense ``(m, L)``) as a float64 CSR matrix with
    finite entries and no empty row (DataError naming ``name`` otherwise); with ``values``,
    ``(rows, values)``, the values an ``(m,)`` float64 array, finite or NaN."""
    try:
        A = sps.csr_matrix(rows, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DataError(f"{name} must be an (m, {L}) matrix of weights: {err}") from None
    if A.shape[1] != L:
        raise DataError(f"{name} must have {L} columns (one per cell), got shape {A.shape}")
    if not np.all(np.isfinite(A.data)):
        raise DataError(f"{name} must be finite")
    A.eliminate_zeros()
    if A.shape[0] and np.any(np.diff(A.indptr) == 0):
        raise DataError(f"{name} has a row without any weight (an observation of no cell)")
    if values is None:
        return A
    v = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if v.shape != (A.shape[0],):
        raise DataError(f"values has shape {v.shape}, {name} has {A.shape[0]} rows")
    if np.isinf(v).any():
        raise DataError("values must be finite (NaN marks a missing value)")
    return A, v


def row_noise(B: Any, noise_var: Any, errors: str = "independent") -> np.ndarray:
    """``(m,)`` noise variance of each averaged observation ``B_i f + e_i`` from the cells'
    noise variances ``noise_var`` (scalar or ``(L,)``): ``sum_j B_ij^2 noise_var_j``
    (``errors="independent"``) or ``(sum_j |B_ij| sqrt(noise_var_j))^2`` (``"shared"``)."""
    if errors not in ERRORS:
        raise DataError(f"errors must be one of {list(ERRORS)}, got {errors!r}")
    B = sps.csr_matrix(B)
    nv = np.broadcast_to(np.asarray(noise_var, np.float64), (B.shape[1],))
    if errors == "independent":
        return np.asarray(B.multiply(B) @ nv, dtype=np.float64).ravel()
    return np.asarray(abs(B) @ np.sqrt(nv), dtype=np.float64).ravel() ** 2


def fit_rows(rows: sps.csr_matrix, values: Any, offset: Any, scale: Any, noise_var: Any,
             errors: str = "independent") -> tuple[sps.csr_matrix, np.ndarray, np.ndarray]:
    """Averaged observations in fit units: ``values = rows @ data`` (data units) is
    ``rows @ offset + B f + e`` with ``B = rows diag(scale)`` (offset / scale None: 0 / 1);
    returns ``(B, z, noise)``, ``noise`` the variances of ``e`` (:func:`row_noise` of the
    cells' ``noise_var``)."""
    z = np.asarray(values, dtype=np.float64)
    if offset is not None:
        z = z - rows @ offset
    B = rows if scale is None else sps.csr_matrix(rows @ sps.diags(scale))
    return B, z, row_noise(B, noise_var, errors)


def _observation_cov(B: sps.spmatrix, noise: np.ndarray, spatial_cov: Any, region: Any
                     ) -> tuple[np.ndarray, sps.csr_matrix, np.ndarray]:
    """``(C, B_U, U)``: the observations' covariance ``B K B^T + diag(noise)`` (dense
    ``(m, m)``), ``B`` on the cells it touches ``U`` and those cells."""
    from .. import spatial as sp

    cov = spatial_cov
    Bc = sps.csc_matrix(B)
    U = np.flatnonzero(np.diff(Bc.indptr))
    BU = Bc[:, U].tocsr()
    xyz = cov.points(region, U)
    K = cov.covariance(sp.arc_distance(cdist(xyz, xyz), cov.metric), nugget=False)
    C = np.asarray((BU @ (BU @ K).T).T)
    C[np.diag_indices_from(C)] += noise
    return 0.5 * (C + C.T), BU, U


def row_terms(Y: np.ndarray, B: Any, z: np.ndarray, noise: np.ndarray, spatial_cov: Any = None,
              region: Any = None) -> tuple[np.ndarray, np.ndarray, float]:
    """``(Yr W Yr^T, Yr W z, z^T W z)`` of averaged observations ``z = B f + e`` (fit units,
    ``Yr = Y B^T``, ``noise`` the ``(m,)`` variances of ``e``, :func:`row_noise`):
    ``W = diag(1 / noise)``, or with the spatial residual ``W = (B K B^T + diag(noise))^-1``
    (GLS; ``noise`` then from the nugget)."""
    B = sps.csr_matrix(B)
    Yr = np.asarray(B @ Y.T).T
    if spatial_cov is None:
        w = 1.0 / np.maximum(np.asarray(noise, np.float64), _NOISE_FLOOR)
        Yw = Yr * w
        return Yw @ Yr.T, Yw @ z, float(z @ (w * z))
    from .. import spatial as sp

    C, _, _ = _observation_cov(B, noise, spatial_cov, region)
    Lc = sp.jittered_cholesky(C, spatial_cov.total_variance, "observation")
    Ws = scipy.linalg.solve_triangular(Lc, Yr.T, lower=True)
    zs = scipy.linalg.solve_triangular(Lc, z, lower=True)
    return Ws.T @ Ws, Ws.T @ zs, float(zs @ zs)


def row_kriging(Y: np.ndarray, B: Any, z: np.ndarray, noise: np.ndarray, m: np.ndarray,
                S: np.ndarray, spatial_cov: Any, region: Any, cells: Any = None,
                chunk: int = 16384) -> tuple[np.ndarray, np.ndarray]:
    """``(mean, var)`` of the noise-free value ``f`` at ``cells`` (default all; fit units)
    given averaged observations ``z = B f + e`` (``Var(e) = diag(noise)``) and the latent
    posterior ``N(m, S)`` (their
    GLS): universal kriging with the Bayesian trend, ``mean = y_t^T m + k_t^T C^-1 (z - Yr^T
    m)``, ``var = sill - k_t^T C^-1 k_t + u_t^T S u_t``, ``u_t = y_t - Yr C^-1 k_t``,
    ``k_t = B k(U, t)``; dense over the covered cells ``U``, targets in chunks."""
    from .. import spatial as sp

    cov = spatial_cov
    B = sps.csr_matrix(B)
    Yr = np.asarray(B @ Y.T).T
    C, BU, U = _observation_cov(B, noise, cov, region)
    Lc = sp.jittered_cholesky(C, cov.total_variance, "observation")
    alpha = scipy.linalg.cho_solve((Lc, True), z - Yr.T @ m)
    xyzU = cov.points(region, U)
    tg = np.arange(Y.shape[1]) if cells is None else np.asarray(cells, dtype=np.int64)
    mu = Y[:, tg].T @ m
    var = np.empty(tg.size)
    for s0 in range(0, tg.size, chunk):  # chunks of targets, never a loop over cells
        t = tg[s0:s0 + chunk]
        d = sp.arc_distance(cdist(xyzU, cov.points(region, t)), cov.metric)
        kt = np.asarray(BU @ cov.covariance(d, nugget=False))  # (m, c)
        mu[s0:s0 + t.size] += kt.T @ alpha
        W = scipy.linalg.solve_triangular(Lc, kt, lower=True)
        u = Y[:, t] - Yr @ scipy.linalg.cho_solve((Lc, True), kt)
        var[s0:s0 + t.size] = (cov.sill - np.einsum("nc,nc->c", W, W)
                               + np.einsum("ac,ab,bc->c", u, S, u))
    return mu, np.maximum(var, 0.0)
