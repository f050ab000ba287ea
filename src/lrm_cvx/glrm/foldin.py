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

from ..errors import DataError, ModelError

__all__ = ["fold_in", "fold_in_many", "mean_std"]


def _check_Y(Y: Any) -> np.ndarray:
    Y = np.asarray(Y)
    if Y.ndim != 2 or not np.issubdtype(Y.dtype, np.floating):
        raise DataError(f"Y must be a (k, L) float matrix, got {Y.dtype} {Y.shape}")
    return Y


def _check_ridge(ridge: Any) -> float:
    try:
        r = float(ridge)
    except (TypeError, ValueError):
        raise ModelError(f"ridge must be a number >= 0, got {ridge!r}") from None
    if not np.isfinite(r) or r < 0:
        raise ModelError(f"ridge must be a number >= 0, got {ridge!r}")
    return r


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
    Y = _check_Y(Y)
    k, L = Y.shape
    cells = np.asarray(cells)
    if cells.ndim != 1 or (cells.size and not np.issubdtype(cells.dtype, np.integer)):
        raise DataError(f"cells must be a 1-D array of integer cell indices, got {cells!r}")
    values = np.asarray(values, dtype=np.float64)
    if values.shape != cells.shape:
        raise DataError(f"values has shape {values.shape}, cells has shape {cells.shape}")
    if cells.size and (cells.min() < 0 or cells.max() >= L):
        raise DataError(f"cells must be in [0, {L}), got min {cells.min()} max {cells.max()}")
    if not np.all(np.isfinite(values)):
        raise DataError("values must be finite (drop unobserved cells instead of passing NaN)")
    ridge = _check_ridge(ridge)
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
    ridge = _check_ridge(ridge)
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
