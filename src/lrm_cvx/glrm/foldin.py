"""Region completion (paper, Approach): fold a partially observed snapshot into the model.

A new snapshot ``d`` seen at cells ``S`` is a new row of ``D``; its latent column is

    x = argmin ||Y_S^T x - d_S||^2 (+ ridge ||x||^2) = (Y_S Y_S^T + ridge I)^-1 Y_S d_S

and the completed map is ``Y^T x``. With noise of standard deviation ``sigma`` on the
observations, ``Cov(x) = sigma^2 (Y_S Y_S^T + ridge I)^-1`` (for ``ridge > 0`` the posterior
covariance under the prior ``x ~ N(0, sigma^2 / ridge I)``), and the standard error of the
predicted mean at cell ``i`` is ``sqrt(y_i^T Cov(x) y_i)``. It does not include the noise of a new
observation at ``i`` (add ``sigma^2`` under the root for a predictive interval).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import check_positive
from ..errors import DataError, ModelError

__all__ = ["fold_in", "fold_in_many", "fold_in_posterior", "mean_std"]


def _check_Y(Y: Any) -> np.ndarray:
    Y = np.asarray(Y)
    if Y.ndim != 2 or not np.issubdtype(Y.dtype, np.floating):
        raise DataError(f"Y must be a (k, L) float matrix, got {Y.dtype} {Y.shape}")
    return Y



def _check_observations(Y, cells, values):
    """``(Y, cells int array, values float64)`` after checking shapes, indices and finiteness."""
    Y = _check_Y(Y)
    cells = np.asarray(cells)
    if cells.ndim != 1 or (cells.size and not np.issubdtype(cells.dtype, np.integer)):
        raise DataError(f"cells must be a 1-D array of integer cell indices, got {cells!r}")
    values = np.asarray(values, dtype=np.float64)
    if values.shape != cells.shape:
        raise DataError(f"values has shape {values.shape}, cells has shape {cells.shape}")
    L = Y.shape[1]
    if cells.size and (cells.min() < 0 or cells.max() >= L):
        raise DataError(f"cells must be in [0, {L}), got min {cells.min()} max {cells.max()}")
    if not np.all(np.isfinite(values)):
        raise DataError("values must be finite (drop unobserved cells instead of passing NaN)")
    return Y, cells, values

def _solve_system(A: np.ndarray, b: np.ndarray, ridge: float, n_obs: Any) -> tuple:
    """Solve ``A x = b`` (batched ``(..., k, k)``) checking that ``A`` is non-singular."""
    k = A.shape[-1]
    if ridge == 0.0:
        n_obs = np.atleast_1d(n_obs)
        if np.any(n_obs < k):
            raise ModelError(
                f"fold-in needs at least rank={k} observations per snapshot (got "
                f"{int(n_obs.min())}); pass ridge > 0 to regularise")
        w = np.linalg.eigvalsh(A)
        if np.any(w[..., 0] <= 1e-12 * np.maximum(w[..., -1], 1e-300)):
            raise ModelError("the observed cells' factors Y_S are rank-deficient; pass ridge > 0")
    Ainv = np.linalg.inv(A)
    x = np.einsum("...ab,...b->...a", Ainv, b)
    return x, Ainv


def fold_in(
    Y: np.ndarray,
    cells: Any,
    values: Any,
    ridge: float = 0.0,
    noise_std: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Latent column ``x (k,)`` and its covariance ``(k, k)`` from values at ``cells``.

    ``Y (k, L)`` the model's spatial factor; ``cells`` int indices ``(n,)``; ``values (n,)``
    finite. ``cov = sigma^2 (Y_S Y_S^T + ridge I)^-1`` with ``sigma = noise_std`` (1 when None:
    the unscaled inverse). Costs ``O(n k^2)``: only the ``n`` observed columns of ``Y`` are read.
    Fewer observations than ``k`` or a rank-deficient ``Y_S`` raises ModelError unless
    ``ridge > 0``.
    """
    Y, cells, values = _check_observations(Y, cells, values)
    k, L = Y.shape
    ridge = check_positive(ridge, "ridge", error=ModelError)
    Ys = np.asarray(Y[:, cells], dtype=np.float64)
    A = Ys @ Ys.T + ridge * np.eye(k)
    x, Ainv = _solve_system(A, Ys @ values, ridge, cells.size)
    sigma2 = 1.0 if noise_std is None else float(noise_std) ** 2
    return x, sigma2 * Ainv


def fold_in_many(
    Y: np.ndarray, values: np.ndarray, ridge: float = 0.0, noise_std: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fold in ``n`` snapshots at once: ``values (n, L)`` with NaN where unobserved.

    Returns ``x (n, k)``, ``cov (n, k, k)`` and the observation counts ``(n,)``. The k x k
    systems are built with matrix products (``O(n L k^2)``), never a loop over cells.
    """
    Y = _check_Y(Y)
    k, L = Y.shape
    V = np.asarray(values, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != L:
        raise DataError(f"values must have shape (n, {L}), got {V.shape}")
    if np.any(np.isinf(V)):
        raise DataError("values must be finite or NaN (unobserved)")
    ridge = check_positive(ridge, "ridge", error=ModelError)
    obs = ~np.isnan(V)
    pa, pb = np.triu_indices(k)
    Yf = np.asarray(Y, dtype=np.float64)
    G = obs.astype(np.float64) @ (Yf[pa] * Yf[pb]).T  # (n, npair)
    A = np.empty((V.shape[0], k, k))
    A[:, pa, pb] = G
    A[:, pb, pa] = G
    A += ridge * np.eye(k)
    b = np.where(obs, V, 0.0) @ Yf.T
    n_obs = obs.sum(axis=1)
    x, Ainv = _solve_system(A, b, ridge, n_obs)
    sigma2 = 1.0 if noise_std is None else float(noise_std) ** 2
    return x, sigma2 * Ainv, n_obs


def mean_std(Y: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Standard error of the predicted mean ``sqrt(y_i^T cov y_i)`` per cell.

    ``cov (k, k)`` -> ``(L,)``; ``cov (n, k, k)`` -> ``(n, L)``.
    """
    Y = np.asarray(Y, dtype=np.float64)
    if cov.ndim == 2:
        var = np.einsum("ai,ai->i", Y, cov @ Y)
    else:
        var = np.einsum("ai,nai->ni", Y, np.einsum("nab,bi->nai", cov, Y))
    return np.sqrt(np.maximum(var, 0.0))


def fold_in_posterior(
    Y: np.ndarray,
    cells: Any,
    values: Any,
    *,
    noise_var: Any = 1.0,
    prior_mean: Any = None,
    prior_precision: Any = None,
    ridge: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian posterior of the latent column ``x (k,)`` from values at ``cells``.

    Model: ``d_p = y_p^T x + e_p``, ``e_p ~ N(0, noise_var_p)`` independent, prior
    ``x ~ N(prior_mean, prior_precision^-1)`` (no prior when ``prior_precision`` is None; then
    ``ridge I`` is the precision, the paper's fold-in at ``ridge = 0``). ``noise_var`` is a scalar
    or a per-cell ``(L,)`` array (only the observed entries are read). Returns the posterior mean
    ``x = A^-1 (Y_S N^-1 d_S + P0 m0)`` and covariance ``A^-1`` with
    ``A = Y_S N^-1 Y_S^T + P0``, in ``O(n k^2)``. A singular ``A`` raises ModelError.
    """
    Y, cells, values = _check_observations(Y, cells, values)
    k, L = Y.shape
    ridge = check_positive(ridge, "ridge", error=ModelError)
    nv = np.asarray(noise_var, dtype=np.float64)
    if nv.ndim == 0:
        w = np.full(cells.size, 1.0 / float(nv)) if float(nv) > 0 else None
    elif nv.shape == (L,):
        w = 1.0 / nv[cells]
    else:
        raise DataError(f"noise_var must be a scalar or ({L},), got shape {nv.shape}")
    if w is None or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ModelError("noise_var must be > 0 and finite")
    Ys = np.asarray(Y[:, cells], dtype=np.float64)
    A = (Ys * w) @ Ys.T + ridge * np.eye(k)
    b = (Ys * w) @ values
    if prior_precision is not None:
        P0 = np.asarray(prior_precision, dtype=np.float64)
        if P0.shape != (k, k):
            raise ModelError(f"prior_precision must be ({k}, {k}), got {P0.shape}")
        A = A + P0
        if prior_mean is not None:
            m0 = np.asarray(prior_mean, dtype=np.float64)
            if m0.shape != (k,):
                raise ModelError(f"prior_mean must be ({k},), got {m0.shape}")
            b = b + P0 @ m0
    elif ridge == 0.0:
        if cells.size < k:
            raise ModelError(
                f"fold-in needs at least rank={k} observations (got {cells.size}); pass "
                "ridge > 0 or a prior")
    ev = np.linalg.eigvalsh(A)
    if ev[0] <= 1e-12 * max(ev[-1], 1e-300):
        raise ModelError("the fold-in system is singular: observe more cells or use a prior")
    Ainv = np.linalg.inv(A)
    Ainv = 0.5 * (Ainv + Ainv.T)
    return Ainv @ b, Ainv


# ---------------------------------------------------------------------------- predictive model
# Helpers of GLRM(offset=, scale=, noise="per-cell", spatial=): column statistics of the
# training data and of the training residuals, computed in blocks of cells so that no
# full-size float64 temporary of a (T, L) matrix is ever made.
_BLOCK = 1 << 16


def column_moments(D: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell observed mean, standard deviation (ddof 0) and count of ``D (T, L)`` under
    the mask ``M``; cells without observations get mean 0 and std 1."""
    T, L = D.shape
    mean = np.zeros(L)
    std = np.ones(L)
    count = np.zeros(L, dtype=np.int64)
    for lo in range(0, L, _BLOCK):
        sl = slice(lo, min(L, lo + _BLOCK))
        m = M[:, sl]
        d = np.where(m, D[:, sl], 0.0).astype(np.float64)
        n = m.sum(axis=0)
        mu = d.sum(axis=0) / np.maximum(n, 1)
        var = (np.where(m, d - mu, 0.0) ** 2).sum(axis=0) / np.maximum(n, 1)
        mean[sl] = mu
        sd = np.sqrt(var)
        std[sl] = np.where((n > 0) & (sd > 0), sd, 1.0)
        count[sl] = n
    return mean, std, count


def standardize(D: np.ndarray, M: np.ndarray, offset: np.ndarray | None,
                scale: np.ndarray | None) -> np.ndarray:
    """``(D - offset) / scale`` on the observed entries (0 elsewhere), a new array of D's float
    dtype (float32 stays float32)."""
    dtype = D.dtype if D.dtype in (np.float32, np.float64) else np.float64
    out = np.zeros(D.shape, dtype=dtype)
    L = D.shape[1]
    for lo in range(0, L, _BLOCK):
        sl = slice(lo, min(L, lo + _BLOCK))
        d = D[:, sl].astype(np.float64)
        if offset is not None:
            d = d - offset[sl]
        if scale is not None:
            d = d / scale[sl]
        out[:, sl] = np.where(M[:, sl], d, 0.0)
    return out


def residual_moments(D: np.ndarray, M: np.ndarray, X: np.ndarray,
                     Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell sum of squared training residuals ``sum_t (D_tj - x_t^T y_j)^2`` over the
    observed entries and their count, ``(L,)`` each."""
    T, L = D.shape
    sse = np.zeros(L)
    count = np.zeros(L, dtype=np.int64)
    for lo in range(0, L, _BLOCK):
        sl = slice(lo, min(L, lo + _BLOCK))
        m = M[:, sl]
        r = np.where(m, D[:, sl] - X.T @ Y[:, sl], 0.0)
        sse[sl] = (r * r).sum(axis=0)
        count[sl] = m.sum(axis=0)
    return sse, count


def shrink_noise(sse: np.ndarray, count: np.ndarray, global_var: float,
                 prior_df: float) -> np.ndarray:
    """Per-cell noise variance shrunk towards the global one:
    ``(sse_j + prior_df * global_var) / (count_j + prior_df)`` (the posterior mean of an
    inverse-gamma prior worth ``prior_df`` pseudo-observations). Cells with few observations stay
    near ``global_var``; cells never observed get it exactly."""
    return (sse + prior_df * global_var) / (count + prior_df)


def residual_sample(D: np.ndarray, M: np.ndarray, X: np.ndarray, Y: np.ndarray,
                    max_times: int = 20) -> np.ndarray:
    """Training residuals of at most ``max_times`` evenly spaced times, ``(t, L)`` float32 with
    NaN where unobserved (for the variogram fit; bounded memory at millions of cells)."""
    T = D.shape[0]
    rows = np.unique(np.linspace(0, T - 1, min(T, max_times)).round().astype(np.int64))
    R = (D[rows].astype(np.float64) - X[:, rows].T @ Y).astype(np.float32)
    R[~M[rows]] = np.nan
    return R
