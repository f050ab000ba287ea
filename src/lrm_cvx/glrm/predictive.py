"""The predictive options of :class:`~lrm_cvx.glrm.GLRM` (docs/reconstruction.md).

All opt-in; the paper's model is the default and untouched:

* ``offset`` / ``scale``: the fit sees ``(D - offset_) / scale_`` per cell (``offset_`` = each
  cell's observed mean, ``scale_`` its observed std, or its RMS without ``offset``); predictions
  are mapped back, ``pred = scale_ * z + offset_``. The offset is known at fold-in.
* ``scale="residual"``: a heteroscedastic residual (an ice edge or a coast varies more than the
  open sea). The low-rank fit is unchanged; after it, ``scale_`` is each cell's training
  residual std relative to the global one (:func:`residual_scale`: the per-cell variance shrunk
  as below), ``Y_`` becomes ``Y_ / scale_`` and the spatial covariance is fitted to the
  residuals over ``scale_``. So ``value = offset + scale_ (Y_^T x + r + e)`` with a stationary
  ``r + e``, the same observation equation as ``scale=True`` (every fold-in, planner and
  interval takes it as it is), and :meth:`reconstruct` is the unscaled fit's.
* ``noise="per-cell"``: ``noise_var_`` (fit units), each cell's training residual variance
  shrunk towards the global one (:func:`shrink_noise`, ``NOISE_PRIOR_DF``
  pseudo-observations), inflated by the same degrees-of-freedom factor as ``noise_std_``.
* ``spatial``: a stationary covariance of the residuals (``spatial_cov_``), for the low-rank
  trend + GP residual prediction (universal kriging with a Bayesian trend prior), fitted to the
  training residuals scaled by the degrees-of-freedom factor of ``noise_std_``
  (:func:`~lrm_cvx.glrm.calibrated.residual_dof`): it estimates the residual's covariance,
  not the smaller one of residuals the fit has already absorbed part of. Its nugget (the
  noise of a new measurement) is bounded below by the fit's sub-cell variation
  (``min_nugget="cell"`` of :func:`~lrm_cvx.spatial.fit_residual_covariance`), so it never
  collapses to 0 on smooth fields.
* ``prior="empirical"`` at fold-in: ``x ~ N(mean(X), cov(X))`` over the training times.

At a new snapshot the residual and noise variances are those above times
:func:`~lrm_cvx.glrm.calibrated.prediction_factor`, ``n / (n - k)``: each cell's ``k`` fitted
parameters (its factors and offset, from its ``n`` training snapshots) err, and that error adds
to the new residual, as in a least-squares prediction interval (applied with the validated
factors, :func:`~lrm_cvx.glrm.calibrated.residual_factor`).

The fold-in itself (every option above) is :mod:`.posterior`; this module fits the options and
saves them with the model.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import xarray as xr

from ..errors import ModelError
from .calibrated import residual_dof
from .hooks import HOOKS
from .kernels import column_moments_compiled, is_small, standardize_compiled
from .offset import augmented
from .options import spatial_options

__all__ = ["fit_predictive", "PREDICTIVE_ATTRS", "NOISE_PRIOR_DF", "NOISE_MODELS", "PRIORS",
           "column_moments", "standardize", "residual_moments", "shrink_noise", "residual_sample",
           "check_options", "moments_to_transform", "set_predictive", "sample_rows",
           "residual_scale", "residual_covariance", "SCALE_FLOOR", "scale_floor",
           "residual_spread", "spread_model"]

CALIBRATIONS = (None, "gaussian", "conformal")  # GLRM(calibration=): calibrate after the fit
NOISE_PRIOR_DF = 10.0  # pseudo-observations of the global variance in each per-cell estimate
NOISE_MODELS = ("global", "per-cell")
SCALE_FLOOR = 0.1
"""``GLRM(scale=True)`` floors a cell's std at this fraction of the median cell std: a cell
(nearly) constant in training (sea ice that never melted: std 5e-7 of a 0-1 fraction) would
turn a later change of 0.1 into 2e5 fit units, and one such sample wreck a whole map."""
PRIORS = (None, "empirical")


def _check_params(model: Any) -> None:
    if not isinstance(model.offset, (bool, np.bool_)):
        raise ModelError(f"offset must be True or False, got {model.offset!r}")
    if not (isinstance(model.scale, (bool, np.bool_)) or model.scale == "residual"):
        raise ModelError(f"scale must be True, False or 'residual', got {model.scale!r}")
    if model.noise not in NOISE_MODELS:
        raise ModelError(f"noise must be one of {NOISE_MODELS}, got {model.noise!r}")
    _check_calibration(getattr(model, "calibration", None))
    spatial_options(model.spatial)


def _check_calibration(value: Any) -> None:
    """``GLRM(calibration=)``: None, a method name or a dict of ``calibrate`` keywords."""
    import inspect

    if isinstance(value, dict):
        names = set(inspect.signature(HOOKS.get("calibrate")).parameters) - {"model", "data"}
        bad = sorted(set(value) - names)
        if bad:
            raise ModelError(f"calibration: unknown calibrate() keyword(s) {bad}; choose from "
                             f"{sorted(names)}")
        value = value.get("method", "gaussian")
    if value not in CALIBRATIONS:
        raise ModelError(f"calibration must be one of {CALIBRATIONS} or a dict of calibrate() "
                         f"keywords, got {value!r}")


def check_options(model: Any, has_region: bool) -> None:
    """Validate the predictive options of ``model`` before a fit (ModelError); ``spatial``
    needs a region (a model fitted on a DataArray)."""
    _check_params(model)
    if model.spatial is not None and not has_region:
        raise ModelError("spatial= needs a model fitted on a DataArray (with a region)")


def data_scale(model: Any) -> bool:
    """``GLRM(scale=True)``: the data divided by their per-cell std before the fit (not
    ``"residual"``, which scales after it)."""
    return isinstance(model.scale, (bool, np.bool_)) and bool(model.scale)


def wants_residual_moments(model: Any) -> bool:
    """The per-cell residual statistics are needed (``noise="per-cell"``,
    ``scale="residual"``, or a stationary spatial residual: its ``residual_spread_``)."""
    return model.noise == "per-cell" or model.scale == "residual" or spread_model(model)


def spread_model(model: Any) -> bool:
    """The model gets a ``residual_spread_``: a spatial residual with one stationary amplitude
    (``noise="global"``, no ``scale="residual"``), whose intervals a calibration may widen per
    cell (``Calibration.local_power``)."""
    return (model.spatial is not None and model.noise == "global"
            and model.scale != "residual")


def residual_spread(cell_var: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``residual_spread_`` ``(L,)``: each cell's shrunk training residual std
    (:func:`shrink_noise`) relative to their root mean square over the observed cells (1 for
    a cell never observed, whose variance is the global one). A calibration raises it to its
    validated ``local_power`` to widen the intervals of cells whose residual varies more
    (locally weighted conformal prediction, Lei et al. 2018); the maps and plans do not use it."""
    seen = np.asarray(count) > 0
    ref = float(np.mean(cell_var[seen])) if seen.any() else 1.0
    return np.sqrt(np.asarray(cell_var, dtype=np.float64) / max(ref, 1e-300))


def scale_floor(std: np.ndarray, count: np.ndarray) -> float:
    """The least per-cell scale of ``GLRM(scale=True)``: :data:`SCALE_FLOOR` times the median
    of ``std`` (the unfloored scales) over the cells with observations (0 when none)."""
    seen = np.asarray(std)[np.asarray(count) > 0]
    return SCALE_FLOOR * float(np.median(seen)) if seen.size else 0.0


def moments_to_transform(offset: bool, scale: bool, mean: np.ndarray, std: np.ndarray,
                         count: np.ndarray | None = None, floor: float | None = None
                         ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(offset_, scale_)`` from the per-cell observed mean, std and count
    (:func:`column_moments`): the mean when ``offset``; the std when ``scale`` (the RMS about
    zero without ``offset``), floored at ``floor`` (None: :func:`scale_floor` of these cells,
    which needs ``count``; a chunked fit passes the floor of all its cells)."""
    if scale and not offset:  # RMS about zero
        rms = np.sqrt(std ** 2 + mean ** 2)
        std = np.where(rms > 0, rms, 1.0)
    if scale:
        if floor is None:
            if count is None:
                raise ValueError("moments_to_transform needs count or floor")
            floor = scale_floor(std, count)
        std = np.maximum(std, floor)
    return (mean if offset else None), (std if scale else None)


def fit_predictive(model: Any, D: np.ndarray, M: np.ndarray, region: Any, stage: str,
                   pre: dict | None = None, inplace: bool = False) -> dict | None:
    """Called by ``GLRM.fit``: ``stage="before"`` returns ``{"data": transformed D}`` (or None
    when neither offset nor scale is asked; ``inplace``: ``D`` itself, overwritten, when it is
    the fit's own copy); ``stage="after"`` sets ``noise_var_`` and ``spatial_cov_`` from the
    residuals of the (transformed) training data."""
    if stage == "before":
        check_options(model, region is not None)
        model._pending_offset = model._pending_scale = model._pending_correction = None
        if not (model.offset or data_scale(model)):
            return None
        mean, std, count = column_moments(D, M)
        off, sc = moments_to_transform(model.offset, data_scale(model), mean, std, count)
        model._pending_offset, model._pending_scale = off, sc
        return {"data": standardize(D, M, off, sc, inplace=inplace)}
    X, Y = model._Xv, model._Yv
    correction = getattr(model, "_pending_correction", None)
    if correction is not None:  # the joint offset: the residuals of [X; 1]^T [Y; o]
        X, Y = augmented(X), np.vstack([Y, correction])
    moments = residual_moments(D, M, X, Y) if wants_residual_moments(model) else None
    sample = residual_sample(D, M, X, Y) if model.spatial is not None else None
    set_predictive(model, region, getattr(model, "_pending_offset", None),
                   getattr(model, "_pending_scale", None), moments, sample)
    return None


def add_joint_offset(model: Any, correction: np.ndarray | None) -> None:
    """The fit's joint offset (:mod:`.offset`): ``correction (L,)`` (fit units; None: centring
    only) is added to the pending ``offset_`` (times the pending ``scale_``) and kept for the
    residual statistics after the fit (:func:`fit_predictive`, those of the joint model)."""
    model._pending_correction = correction
    if correction is None:
        return
    sc = getattr(model, "_pending_scale", None)
    model._pending_offset = model._pending_offset + (correction if sc is None
                                                     else correction * sc)


def set_predictive(model: Any, region: Any, offset: np.ndarray | None,
                   scale: np.ndarray | None, moments: tuple[np.ndarray, np.ndarray] | None,
                   sample: np.ndarray | None) -> None:
    """Set ``offset_``, ``scale_``, ``noise_var_`` and ``spatial_cov_`` of a fitted ``model``
    from statistics of the (transformed) training data: ``moments = (sse, count)`` of
    :func:`residual_moments` (for ``noise="per-cell"``) and ``sample`` of
    :func:`residual_sample` (for ``spatial``). Shared by the in-memory and the dask fit, which
    computes the same statistics chunk by chunk. ``residual_inflation_`` starts at 1 (the
    variances as fitted; ``temporal="auto"`` validates a factor, validation/selection.py)."""
    model.offset_, model.scale_ = offset, scale
    model.noise_var_ = model.residual_spread_ = None
    model.residual_inflation_ = 1.0
    model.spatial_cov_ = model.kernel_selection_ = None
    if sample is not None:
        sample = _dof_corrected(sample, model)
    if moments is not None:
        sse, cnt = moments
        total = float(sse.sum())
        inflate = model.noise_std_ ** 2 * max(int(cnt.sum()), 1) / total if total > 0 else 1.0
        cell_var = shrink_noise(sse * inflate, cnt, model.noise_std_ ** 2, NOISE_PRIOR_DF)
        if model.noise == "per-cell":
            model.noise_var_ = cell_var
        if spread_model(model):
            model.residual_spread_ = residual_spread(cell_var, cnt)
        if model.scale == "residual":
            rs = residual_scale(cell_var, model.noise_std_ ** 2)
            _divide_factor(model, rs)
            model.scale_ = rs
            if model.noise_var_ is not None:  # in the new fit units
                model.noise_var_ = model.noise_var_ / rs ** 2
            if sample is not None:
                sample = (sample / rs).astype(sample.dtype)
    spatial = spatial_options(model.spatial)
    if spatial is not None and spatial.model == "auto":  # validated on the residuals
        model.spatial_cov_, model.kernel_selection_ = HOOKS.get("select-kernel")(
            sample, region, seed=model.random_state)
    elif spatial is not None:
        from ..spatial import fit_residual_covariance

        model.spatial_cov_ = fit_residual_covariance(
            sample, region, model=spatial.model, random_state=0, min_nugget="cell",
            anisotropy=spatial.anisotropy)


# ---------------------------------------------------------------------------- predictive model
# Helpers of GLRM(offset=, scale=, noise="per-cell", spatial=): column statistics of the
# training data and of the training residuals, computed in blocks of cells so that no
# full-size float64 temporary of a (T, L) matrix is ever made.
_BLOCK = 1 << 16


def column_moments(D: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell observed mean, standard deviation (ddof 0) and count of ``D (T, L)`` under
    the mask ``M``; cells without observations get mean 0 and std 1. Large data takes one
    compiled two-pass kernel (:func:`~.kernels.column_moments_compiled`, the same sums)."""
    T, L = D.shape
    if not is_small(D.size) and D.dtype in (np.float32, np.float64):
        csum, css, count = column_moments_compiled(D, np.asarray(M, dtype=np.bool_))
        n = np.maximum(count, 1)
        sd = np.sqrt(css / n)
        return csum / n, np.where((count > 0) & (sd > 0), sd, 1.0), count
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
                scale: np.ndarray | None, *, inplace: bool = False) -> np.ndarray:
    """``(D - offset) / scale`` on the observed entries (0 elsewhere), of D's float dtype
    (float32 stays float32): a new array, or ``D`` itself overwritten when ``inplace`` (a copy
    the caller owns; the fit's gathered training data, so no second full-size copy)."""
    dtype = D.dtype if D.dtype in (np.float32, np.float64) else np.float64
    if inplace and (D.dtype != dtype or not D.flags.writeable):
        raise ValueError("standardize(inplace=True) needs a writeable float32/float64 D")
    out = D if inplace else np.zeros(D.shape, dtype=dtype)
    L = D.shape[1]
    if not is_small(D.size) and D.dtype == dtype and D.flags.c_contiguous:
        standardize_compiled(D, np.asarray(M, dtype=np.bool_),
                             np.zeros(L) if offset is None else np.asarray(offset, np.float64),
                             np.ones(L) if scale is None else np.asarray(scale, np.float64),
                             out)
        return out
    for lo in range(0, L, _BLOCK):
        sl = slice(lo, min(L, lo + _BLOCK))
        d = D[:, sl].astype(np.float64)
        if offset is not None:
            d = d - offset[sl]
        if scale is not None:
            d = d / scale[sl]
        out[:, sl] = np.where(M[:, sl], d, 0.0)
    return out


def residual_scale(cell_var: np.ndarray, global_var: float) -> np.ndarray:
    """``GLRM(scale="residual")``'s ``scale_`` ``(L,)``: ``sqrt(cell_var / global_var)``, each
    cell's (shrunk, :func:`shrink_noise`) training residual variance relative to the global one;
    the shrinkage bounds it away from 0 on cells that never vary."""
    return np.sqrt(np.asarray(cell_var, dtype=np.float64) / max(float(global_var), 1e-300))


def _divide_factor(model: Any, rs: np.ndarray) -> None:
    """``Y_ <- Y_ / rs`` column by column, keeping its type (numpy, DataArray, dask)."""
    Y = model.Y_
    if isinstance(Y, xr.DataArray):
        model.Y_ = Y.copy(data=Y.data / rs)
    else:
        model.Y_ = Y / rs


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


def sample_rows(T: int, max_times: int = 20) -> np.ndarray:
    """The times :func:`residual_sample` uses: at most ``max_times`` evenly spaced of ``T``."""
    return np.unique(np.linspace(0, T - 1, min(T, max_times)).round().astype(np.int64))


def residual_sample(D: np.ndarray, M: np.ndarray, X: np.ndarray, Y: np.ndarray,
                    max_times: int = 20) -> np.ndarray:
    """Training residuals of at most ``max_times`` evenly spaced times, ``(t, L)`` float32 with
    NaN where unobserved (for the variogram fit; bounded memory at millions of cells)."""
    rows = sample_rows(D.shape[0], max_times)
    Xr = np.ascontiguousarray(X[:, rows].T)
    R = np.empty((rows.size, D.shape[1]), dtype=np.float32)
    for lo in range(0, D.shape[1], _BLOCK):  # no (t, L) float64 temporary
        sl = slice(lo, min(D.shape[1], lo + _BLOCK))
        R[:, sl] = D[rows, sl].astype(np.float64) - Xr @ Y[:, sl]
    R[~M[rows]] = np.nan
    return R


def _dof_corrected(sample: np.ndarray, model: Any) -> np.ndarray:
    """Training residuals times ``sqrt(residual_dof(model))``, in their dtype: the residuals'
    variance, not the fit's leftovers, for the variogram of ``spatial_cov_``."""
    out = np.empty_like(sample)  # the product in float64, written to the sample's dtype
    return np.multiply(sample, np.sqrt(residual_dof(model)), out=out, casting="same_kind")


def residual_covariance(model: Any, V: np.ndarray, family: Any, *, max_pairs: int = 200_000
                        ) -> Any:
    """The spatial residual covariance (``family``: a fixed family's name or
    :class:`~.options.SpatialOptions`, with its anisotropy) of a fitted ``model`` from its
    training values ``V (T, L)`` (data units, NaN = missing): what the fit's ``spatial=family``
    sets (the variogram of the residuals of :func:`sample_rows`, ``min_nugget="cell"``), with at
    most ``max_pairs`` pairs. Only those rows of ``V`` are read (``temporal="auto"``'s refit
    fits it once, with fewer pairs, for all its refits)."""
    from ..spatial import fit_residual_covariance

    spatial = spatial_options(family)
    rows = sample_rows(V.shape[0])
    D = V[rows]
    M = ~np.isnan(D)
    D = standardize(D, M, getattr(model, "offset_", None), getattr(model, "scale_", None))
    R = _dof_corrected(residual_sample(D, M, model._Xv[:, rows], model._Yv,
                                       max_times=rows.size), model)
    return fit_residual_covariance(R, model.region_, model=spatial.model, random_state=0,
                                   min_nugget="cell", max_pairs=max_pairs,
                                   anisotropy=spatial.anisotropy)


class _PredictiveIO:
    """Save / restore the predictive attributes with the model's NetCDF file."""

    names = ("offset", "scale", "noise_var", "residual_spread")

    def arrays(self, model: Any) -> dict[str, np.ndarray]:
        out = {}
        for name in self.names:
            arr = getattr(model, name + "_", None)
            if arr is not None:
                out["predictive_" + name] = np.asarray(arr, dtype=np.float64)
        return out

    def attrs(self, model: Any) -> dict[str, Any]:
        cov = getattr(model, "spatial_cov_", None)
        out = {} if cov is None else cov.to_attrs()
        return {**out, "residual_inflation": float(getattr(model, "residual_inflation_", 1.0))}

    def restore(self, model: Any, ds: Any) -> None:
        from ..spatial import ResidualCovariance

        for name in self.names:
            key = "predictive_" + name
            setattr(model, name + "_", ds[key].values.astype(np.float64) if key in ds else None)
        model.spatial_cov_ = (ResidualCovariance.from_attrs(ds.attrs)
                              if "spatial_model" in ds.attrs else None)
        model.residual_inflation_ = float(ds.attrs.get("residual_inflation", 1.0))


PREDICTIVE_ATTRS = _PredictiveIO()
