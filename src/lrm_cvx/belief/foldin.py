"""Region completion (paper, Approach) on a bare factor matrix: thin wrappers of
:class:`~lrm_cvx.belief.posterior.LatentPosterior`.

The completed map is ``Y^T x`` with ``x`` the (ridge) least-squares fit at the observed cells;
:func:`gls_fold_in` and :func:`residual_correction` are the same fold-in under the GP residual
covariance. For a fitted model use ``GLRM.complete`` or ``GLRM.latent_prior``.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from .._validation import as_factor_matrix, check_positive
from ..errors import DataError, ModelError
from ..region import Region
from ..spatial.covariance import ResidualCovariance
from ..spatial.kriging import MAX_DIRECT, check_cov, krige_core, prepare_kriging
from .posterior import LatentPosterior, ObservationModel

__all__ = ["fold_in", "fold_in_rows", "fold_in_many", "gls_fold_in", "residual_correction"]


def _belief(Y: Any, ridge: float, noise_std: float | None) -> LatentPosterior:
    Y = np.asarray(Y)
    if Y.ndim != 2 or not np.issubdtype(Y.dtype, np.floating):
        raise DataError(f"Y must be a (k, L) float matrix, got {Y.dtype} {Y.shape}")
    ridge = check_positive(ridge, "ridge", error=ModelError)
    sigma2 = 1.0 if noise_std is None else float(noise_std) ** 2
    return LatentPosterior.prior(ObservationModel(Y, noise_var=sigma2), "ridge", ridge)


def fold_in(
    Y: np.ndarray,
    cells: Any,
    values: Any,
    ridge: float = 0.0,
    noise_std: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Latent column ``x (k,)`` and its covariance ``(k, k)`` from values at ``cells``.

    ``Y (k, L)`` the model's spatial factor; ``cells`` integer indices ``(n,)``; ``values (n,)``
    (NaN dropped). ``cov = sigma^2 (Y_S Y_S^T + ridge I)^-1`` with ``sigma = noise_std`` (1 when
    None: the unscaled inverse). ``O(n k^2)``. Fewer observations than ``k`` or a rank-deficient
    ``Y_S`` raises ModelError unless ``ridge > 0``.
    """
    post = _belief(Y, ridge, noise_std).update(cells, values)
    return post.mean, post.cov


def fold_in_rows(Y: np.ndarray, rows: Any, values: Any, ridge: float = 0.0,
                 noise_std: float | None = None, errors: str = "independent"
                 ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fold_in` of averaged observations: ``values[i]`` is ``rows[i] @ d`` (``rows``
    ``(m, L)`` weights, e.g. a sensor footprint's). Weighted least squares on the rows
    ``Y a_i`` with weights ``1 / sum_j a_ij^2`` (independent cell errors averaged):
    ``x = (sum_i w_i Y a_i a_i^T Y^T + ridge I)^-1 sum_i w_i Y a_i v_i``,
    ``cov = sigma^2 (...)^-1``; one-hot rows give :func:`fold_in` exactly. ``errors="shared"``:
    weights ``1 / (sum_j |a_ij|)^2`` (equal cell errors within an observation)."""
    post = _belief(Y, ridge, noise_std).update_rows(rows, values, errors)
    return post.mean, post.cov


def fold_in_many(
    Y: np.ndarray, values: np.ndarray, ridge: float = 0.0, noise_std: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fold in ``n`` snapshots at once: ``values (n, L)`` with NaN where unobserved.

    Returns ``x (n, k)``, ``cov (n, k, k)`` and the observation counts ``(n,)`` (a loop over
    snapshots, each ``O(n_obs k^2)``).
    """
    base = _belief(Y, ridge, noise_std)
    k, L = base.obs_model.Y.shape
    V = np.asarray(values, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != L:
        raise DataError(f"values must have shape (n, {L}), got {V.shape}")
    if np.any(np.isinf(V)):
        raise DataError("values must be finite or NaN (unobserved)")
    x = np.empty((V.shape[0], k))
    cov = np.empty((V.shape[0], k, k))
    n_obs = (~np.isnan(V)).sum(axis=1)
    for t in range(V.shape[0]):
        obs = np.flatnonzero(~np.isnan(V[t]))
        post = base.update(obs, V[t, obs])
        x[t], cov[t] = post.mean, post.cov
    return x, cov, n_obs


# ------------------------------------------------------------------- GLS and the GP residual
def _observations(Y: Any, cells: Any, values: Any, region: Region, cov: Any):
    cov = check_cov(cov)
    if not isinstance(region, Region):
        raise DataError(f"region must be a Region, got {type(region).__name__}")
    Y = as_factor_matrix(Y, region)
    cells = region.check_cells(np.ravel(cells), "cells")
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size != cells.size:
        raise DataError(f"values has {v.size} entries, cells has {cells.size}")
    if np.isinf(v).any():
        raise DataError("values has infinite entries")
    if np.unique(cells).size != cells.size:
        raise DataError("cells has repeated cell indices: give one value per observed cell")
    ok = np.isfinite(v)
    return cov, Y, cells[ok], v[ok]


def gls_fold_in(
    Y: Any, cells: Any, values: Any, cov: ResidualCovariance, region: Region, ridge: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised-least-squares fold-in of a new snapshot under the GP residual covariance.

    ``x = (Y_S C^-1 Y_S^T + ridge I)^-1 Y_S C^-1 d_S`` with ``C = K_SS + nugget I`` (``n x n``,
    one Cholesky), and ``cov_x = (Y_S C^-1 Y_S^T + ridge I)^-1``, the covariance of ``x`` (the
    posterior covariance under a ``N(0, I / ridge)`` prior when ``ridge > 0``). ``Y`` is
    ``(k, L)``; NaN values are ignored. Returns ``x (k,)`` and ``cov_x (k, k)``.
    """
    cov, Y, cells, d = _observations(Y, cells, values, region, cov)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    x, cov_x = _gls(Y, cells, d, cov, region, ridge)
    return x, cov_x


def _gls(Y, cells, d, cov, region, ridge):
    """GLS fold-in: the posterior of :class:`~lrm_cvx.belief.posterior.LatentPosterior` with the
    GP residual and the prior precision ``ridge I`` (flat at 0). Returns ``(x, cov_x)``."""
    k = Y.shape[0]
    if cells.size == 0 and ridge == 0:
        raise ModelError("gls_fold_in needs at least one observation or ridge > 0")
    obs = ObservationModel(Y, spatial_cov=cov, region=region)
    post = LatentPosterior.from_moments(obs, precision=ridge * np.eye(k)).update(cells, d)
    if not post.is_proper:
        raise ModelError(
            f"the GLS normal matrix is singular: {cells.size} observations do not determine "
            f"rank {k} factors (observe more cells or set ridge > 0)")
    return post.mean, post.cov


def residual_correction(
    Y: Any,
    cells: Any,
    values: Any,
    cov: ResidualCovariance,
    region: Region,
    *,
    fold_in: Literal["gls", "ols"] = "gls",
    targets: Any = None,
    ridge: float = 0.0,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Prediction ``Y_t^T x + kriged residual`` at ``targets`` (default all cells) and its std.

    ``fold_in="gls"`` (universal kriging): ``x`` from :func:`gls_fold_in`, and the std includes
    the trend-estimation term, so it is the exact BLUP error under the model. ``fold_in="ols"``
    (regression kriging): the paper's fold-in ``x = (Y_S Y_S^T + ridge I)^-1 Y_S d_S``, then
    simple kriging of ``d_S - Y_S^T x``; its std is the residual's kriging std only (the trend is
    treated as known, so it is optimistic). NaN values are ignored.
    """
    cov, Y, cells, d = _observations(Y, cells, values, region, cov)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    if fold_in not in ("gls", "ols"):
        raise ModelError(f"fold_in must be 'gls' or 'ols', got {fold_in!r}")
    cov, _, tg, neighbors, cutoff, method = prepare_kriging(
        cov, region, cells, targets, neighbors, cutoff, method)
    k = Y.shape[0]
    Ys = Y[:, cells]
    if fold_in == "gls":
        x, cov_x = _gls(Y, cells, d, cov, region, ridge)
    else:
        G = Ys @ Ys.T + ridge * np.eye(k)
        x, *_ = np.linalg.lstsq(G, Ys @ d, rcond=None)
        cov_x = None
    res = d - Ys.T @ x
    n = cells.size
    meth = method if method != "auto" else ("direct" if n <= MAX_DIRECT else "neighbors")
    trend = fold_in == "gls"
    mu, var = krige_core(
        cov, cov.points(region, cells), res[:, None], cov.points(region, tg),
        method=meth, neighbors=neighbors, cutoff=cutoff, want_var=return_std,
        Ys=Ys if trend else None, Yt=(lambda sel: Y[:, tg[sel]]) if trend else None, cov_x=cov_x,
    )
    pred = Y[:, tg].T @ x + mu[0]
    if not return_std:
        return pred, None
    if include_nugget:
        var = var + cov.nugget
    return pred, np.sqrt(np.maximum(var, 0.0))
