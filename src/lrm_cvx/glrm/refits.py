"""Refits of a fitted model on part of its training snapshots: the unfitted copy every
validation refits (:func:`clone_model`) and the snapshots stacked on the model's region
(:func:`training_values`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import DataError, ModelError

__all__ = ["clone_model", "training_values"]


def clone_model(model: Any, **override: Any):
    """An unfitted copy of ``model`` (its class and parameters, ``override`` applied; a
    refit never calibrates itself: ``calibration`` None unless overridden, and a fitted
    ``spatial="auto"`` model's refits keep the family and anisotropy it chose,
    ``kernel_selection_``: the
    kernel is shared by every candidate a refit compares, and choosing it again per refit
    would cost four variogram fits each); a fitted ``rank="auto"`` model's refits keep its
    ``rank_``."""
    params = model.get_params()
    if "calibration" in params:
        params["calibration"] = None
    if params.get("rank") == "auto" and getattr(model, "rank_", None) is not None:
        params["rank"] = int(model.rank_)
    if params.get("spatial") == "auto" and getattr(model, "spatial_cov_", None) is not None:
        params["spatial"] = model.spatial_cov_.model
        params["anisotropy"] = float(model.spatial_cov_.anisotropy)
    params = {**params, "progress": False, **override}
    return type(model)(**params)


def training_values(model: Any, data: Any, dtype: Any = np.float64):
    """``(region, V)``: the model's region and ``data`` stacked to ``V (T, L)`` of ``dtype``."""
    import xarray as xr

    if not isinstance(data, xr.DataArray) or data.ndim != 3:
        raise DataError("data must be a (time, lat, lon) DataArray (the training snapshots)")
    region = getattr(model, "region_", None)
    if region is None:
        raise ModelError("a validation refit needs a model fitted on a DataArray (with a "
                         "region)")
    return region, region.stack(data).astype(dtype, copy=False)
