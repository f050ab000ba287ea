"""The predictive options of :class:`~lrm_cvx.glrm.GLRM` (issue #8, docs/reconstruction.md).

All opt-in; the paper's model is the default and untouched:

* ``offset`` / ``scale``: the fit sees ``(D - offset_) / scale_`` per cell (``offset_`` = each
  cell's observed mean, ``scale_`` its observed std, or its RMS without ``offset``); predictions
  are mapped back, ``pred = scale_ * z + offset_``. The offset is known at fold-in.
* ``noise="per-cell"``: ``noise_var_`` (fit units), each cell's training residual variance
  shrunk towards the global one (:func:`~.foldin.shrink_noise`, ``NOISE_PRIOR_DF``
  pseudo-observations), inflated by the same degrees-of-freedom factor as ``noise_std_``.
* ``spatial``: a stationary covariance of the training residuals (``spatial_cov_``), for the
  low-rank trend + GP residual prediction (universal kriging with a Bayesian trend prior).
* ``prior="empirical"`` at fold-in: ``x ~ N(mean(X), cov(X))`` over the training times.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from scipy.spatial.distance import cdist

from ..errors import ModelError
from .foldin import (
    column_moments,
    fold_in_posterior,
    mean_std,
    residual_moments,
    residual_sample,
    shrink_noise,
    standardize,
)

__all__ = ["fit_predictive", "posterior_complete", "empirical_prior", "planner_terms",
           "PREDICTIVE_ATTRS", "NOISE_PRIOR_DF", "NOISE_MODELS", "PRIORS"]

NOISE_PRIOR_DF = 10.0  # pseudo-observations of the global variance in each per-cell estimate
NOISE_MODELS = ("global", "per-cell")
PRIORS = (None, "empirical")


def _check_params(model: Any) -> None:
    from ..spatial import MODELS

    for name in ("offset", "scale"):
        if not isinstance(getattr(model, name), (bool, np.bool_)):
            raise ModelError(f"{name} must be True or False, got {getattr(model, name)!r}")
    if model.noise not in NOISE_MODELS:
        raise ModelError(f"noise must be one of {NOISE_MODELS}, got {model.noise!r}")
    if model.spatial is not None and model.spatial not in MODELS:
        raise ModelError(f"spatial must be None or one of {MODELS}, got {model.spatial!r}")


def fit_predictive(model: Any, D: np.ndarray, M: np.ndarray, region: Any, stage: str,
                   pre: dict | None = None) -> dict | None:
    """Called by ``GLRM.fit``: ``stage="before"`` returns ``{"data": transformed D}`` (or None
    when neither offset nor scale is asked); ``stage="after"`` sets ``noise_var_`` and
    ``spatial_cov_`` from the residuals of the (transformed) training data."""
    if stage == "before":
        _check_params(model)
        if model.spatial is not None and region is None:
            raise ModelError("spatial= needs a model fitted on a DataArray (with a region)")
        model._pending_offset = model._pending_scale = None
        if not (model.offset or model.scale):
            return None
        mean, std, count = column_moments(D, M)
        if model.scale and not model.offset:  # RMS about zero
            rms = np.sqrt(std ** 2 + mean ** 2)
            std = np.where(rms > 0, rms, 1.0)
        off = mean if model.offset else None
        sc = std if model.scale else None
        model._pending_offset, model._pending_scale = off, sc
        return {"data": standardize(D, M, off, sc)}
    model.offset_ = getattr(model, "_pending_offset", None)
    model.scale_ = getattr(model, "_pending_scale", None)
    model.noise_var_ = None
    model.spatial_cov_ = None
    X, Y = model._Xv, model._Yv
    if model.noise == "per-cell":
        sse, cnt = residual_moments(D, M, X, Y)
        total = float(sse.sum())
        inflate = model.noise_std_ ** 2 * max(int(cnt.sum()), 1) / total if total > 0 else 1.0
        model.noise_var_ = shrink_noise(sse * inflate, cnt, model.noise_std_ ** 2,
                                        NOISE_PRIOR_DF)
    if model.spatial is not None:
        from ..spatial import fit_residual_covariance

        R = residual_sample(D, M, X, Y)
        model.spatial_cov_ = fit_residual_covariance(R, region, model=model.spatial,
                                                     random_state=0)
    return None


def empirical_prior(model: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean (k,), precision (k, k), covariance (k, k))`` of the training columns of ``X``
    (covariance with ddof 1, plus 1e-9 x its trace so it is invertible)."""
    X = model._Xv
    k, T = X.shape
    if T < 2:
        raise ModelError("prior='empirical' needs a model fitted on at least 2 times")
    S0 = np.atleast_2d(np.cov(X))
    S0 = S0 + 1e-9 * max(np.trace(S0), 1e-300) / k * np.eye(k)
    P0 = np.linalg.inv(S0)
    return X.mean(axis=1), 0.5 * (P0 + P0.T), S0


def _prior_terms(model: Any, prior: Any, ridge: float, sigma2: float):
    if prior not in PRIORS:
        raise ModelError(f"prior must be one of {PRIORS}, got {prior!r}")
    k = model._Yv.shape[0]
    if prior == "empirical":
        m0, P0, _ = empirical_prior(model)
        return m0, P0
    if ridge > 0:  # the paper's ridge, i.e. the prior N(0, sigma^2 / ridge I)
        return np.zeros(k), (ridge / sigma2) * np.eye(k)
    return None, None


def _noise(model: Any) -> Any:
    nv = getattr(model, "noise_var_", None)
    return nv if nv is not None else max(model.noise_std_, 1e-300) ** 2


def posterior_complete(model: Any, V: np.ndarray, *, ridge: float = 0.0, prior: Any = None,
                       spatial: bool = False):
    """Predict snapshots ``V (n, L)`` (NaN = not observed) with the predictive options.

    Returns ``pred (n, L)``, ``std (n, L)`` (posterior std of the latent value, data units),
    ``x (n, k)`` and the observation counts ``(n,)``.
    """
    Y = model._Yv
    k, L = Y.shape
    off = getattr(model, "offset_", None)
    sc = getattr(model, "scale_", None)
    Z = V
    if off is not None:
        Z = Z - off
    if sc is not None:
        Z = Z / sc
    if spatial:
        cov = getattr(model, "spatial_cov_", None)
        if cov is None:
            raise ModelError("spatial=True needs a model fitted with spatial='exponential' "
                             "(or another covariance model)")
        sigma2 = cov.total_variance
    else:
        sigma2 = model.noise_std_ ** 2
    m0, P0 = _prior_terms(model, prior, ridge, max(sigma2, 1e-300))
    n = V.shape[0]
    pred = np.empty((n, L))
    std = np.empty((n, L))
    xs = np.empty((n, k))
    counts = np.zeros(n, dtype=np.int64)
    for t in range(n):  # loop over snapshots (few), never over cells
        obs = np.flatnonzero(np.isfinite(Z[t]))
        if np.any(np.isinf(V[t, obs])):
            raise ModelError("observed values must be finite")
        counts[t] = obs.size
        if spatial:
            pred[t], var, xs[t] = _spatial_one(model, Y, obs, Z[t, obs], m0, P0)
        else:
            x, cx = fold_in_posterior(Y, obs, Z[t, obs], noise_var=_noise(model),
                                      prior_mean=m0, prior_precision=P0)
            xs[t] = x
            pred[t] = Y.T @ x
            var = mean_std(Y, cx) ** 2
        std[t] = np.sqrt(np.maximum(var, 0.0))
    if sc is not None:
        pred *= sc
        std *= sc
    if off is not None:
        pred += off
    return pred, std, xs, counts


def _spatial_one(model, Y, obs, d, m0, P0):
    """Universal kriging with a Bayesian trend prior: GLS posterior of ``x`` under
    ``C = K_SS + nugget I`` and the prior, then simple kriging of ``d - Y_S^T x`` with the
    trend-uncertainty term. Equals the GP conditional of ``Y^T x + r`` with
    ``x ~ N(m0, P0^-1)``, ``r ~ GP(cov)`` (tested by brute force)."""
    from .. import spatial as sp

    cov = model.spatial_cov_
    region = model.region_
    k = Y.shape[0]
    Ys = Y[:, obs]
    xyz = sp._coords(region, cov.metric, obs)
    C = cov.covariance(sp._arc(cdist(xyz, xyz), cov.metric))
    np.fill_diagonal(C, cov.total_variance)
    Lc = sp._cholesky(C, cov.total_variance, "observation")
    Ws = scipy.linalg.solve_triangular(Lc, Ys.T, lower=True)
    zs = scipy.linalg.solve_triangular(Lc, d, lower=True)
    A = Ws.T @ Ws
    b = Ws.T @ zs
    if P0 is not None:
        A = A + P0
        b = b + P0 @ m0
    ev = np.linalg.eigvalsh(A)
    if ev[0] <= 1e-12 * max(ev[-1], 1e-300):
        raise ModelError(f"{obs.size} observations do not determine the rank-{k} trend: "
                         "observe more cells or use prior='empirical'")
    cov_x = np.linalg.inv(A)
    cov_x = 0.5 * (cov_x + cov_x.T)
    x = cov_x @ b
    res = d - Ys.T @ x
    meth = "direct" if obs.size <= sp._MAX_DIRECT else "neighbors"
    mu, var = sp._krige_core(
        cov, xyz, res[:, None], sp._coords(region, cov.metric, None), method=meth,
        neighbors=32, cutoff=1e-6, want_var=True, Ys=Ys, Yt=lambda sel: Y[:, sel], cov_x=cov_x)
    return Y.T @ x + mu[0], var, x


def planner_terms(model: Any, prior: Any = "empirical", spatial: bool = False) -> dict:
    """Keyword arguments of :func:`~lrm_cvx.planning.plan_greedy` that make its criterion
    match this model's prediction: ``prior_precision``, ``noise_var`` (fit units),
    ``target_weights`` (``scale_^2``: variance in data units), and, with ``spatial``,
    ``prior_cov`` and ``spatial_cov`` for the ``"gp-variance"`` criterion."""
    if spatial:
        cov = getattr(model, "spatial_cov_", None)
        if cov is None:
            raise ModelError("spatial=True needs a model fitted with spatial=...")
        sigma2 = cov.total_variance
    else:
        sigma2 = model.noise_std_ ** 2
    out: dict[str, Any] = {}
    if prior == "empirical":
        _, P0, S0 = empirical_prior(model)
    elif prior is None:
        S0 = None
        P0 = None
    else:
        raise ModelError(f"prior must be one of {PRIORS}, got {prior!r}")
    out["prior_precision"] = P0
    out["noise_var"] = _noise(model) if not spatial else sigma2
    sc = getattr(model, "scale_", None)
    out["target_weights"] = None if sc is None else sc ** 2
    if spatial:
        if S0 is None:
            raise ModelError("the gp-variance criterion needs prior='empirical'")
        out["prior_cov"] = S0
        out["spatial_cov"] = model.spatial_cov_
    return out


class _PredictiveIO:
    """Save / restore the predictive attributes with the model's NetCDF file."""

    names = ("offset", "scale", "noise_var")

    def arrays(self, model: Any) -> dict[str, np.ndarray]:
        out = {}
        for name in self.names:
            arr = getattr(model, name + "_", None)
            if arr is not None:
                out["predictive_" + name] = np.asarray(arr, dtype=np.float64)
        return out

    def attrs(self, model: Any) -> dict[str, Any]:
        cov = getattr(model, "spatial_cov_", None)
        return {} if cov is None else cov.to_attrs()

    def restore(self, model: Any, ds: Any) -> None:
        from ..spatial import ResidualCovariance

        for name in self.names:
            key = "predictive_" + name
            setattr(model, name + "_", ds[key].values.astype(np.float64) if key in ds else None)
        model.spatial_cov_ = (ResidualCovariance.from_attrs(ds.attrs)
                              if "spatial_model" in ds.attrs else None)


PREDICTIVE_ATTRS = _PredictiveIO()
