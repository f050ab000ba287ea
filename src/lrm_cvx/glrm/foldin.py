"""Region completion (paper, Approach) on a bare factor matrix: thin wrappers of
:class:`~lrm_cvx.glrm.posterior.LatentPosterior`.

A new snapshot ``d`` seen at cells ``S`` is a new row of ``D``; its latent column is

    x = argmin ||Y_S^T x - d_S||^2 (+ ridge ||x||^2) = (Y_S Y_S^T + ridge I)^-1 Y_S d_S

and the completed map is ``Y^T x``. With noise of standard deviation ``sigma`` on the
observations, ``Cov(x) = sigma^2 (Y_S Y_S^T + ridge I)^-1`` (for ``ridge > 0`` the posterior
covariance under the prior ``x ~ N(0, sigma^2 / ridge I)``). For a fitted model use
``GLRM.complete`` or ``GLRM.latent_prior`` (offset, scale, per-cell noise, priors, spatial
residual).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import check_positive
from ..errors import DataError, ModelError
from .posterior import LatentPosterior, ObservationModel

__all__ = ["fold_in", "fold_in_many"]


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
