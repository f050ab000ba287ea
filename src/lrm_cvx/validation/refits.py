"""Refits of a fitted model on part of its training snapshots: the unfitted copy every
validation refits (:func:`clone_model`), the snapshots stacked on the model's region
(:func:`training_values`), and the window of a large region the validations read
(:func:`validation_view`)."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from ..errors import DataError, ModelError
from ..glrm.options import SpatialOptions, spatial_options

__all__ = ["clone_model", "training_values", "validation_window", "validation_view",
           "validation_data", "refit_carries", "VALIDATION_MAX_CELLS"]

VALIDATION_MAX_CELLS = 200_000
"""The most cells a validation's refits read (``temporal="auto"``, the calibration,
``select_dynamics``): a larger region is validated on a window of its grid holding about this
many cells (:func:`validation_window`). Each refit is a whole fit of the cells it reads: on the
paper's 2.1M cells the recommended fit took 440 s at a 15 GiB peak with every cell validated,
103 s at 9 GiB with a window of 200,000 cells, a square of about 450 (63 s at 6.8 GiB since
the fit's own passes were compiled; docs/benchmarks.md, "The recommended fit at paper
scale")."""


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
    spatial = spatial_options(params.get("spatial"))  # "auto" or SpatialOptions("auto")
    if (spatial is not None and spatial.model == "auto"
            and getattr(model, "spatial_cov_", None) is not None):
        params["spatial"] = SpatialOptions(model.spatial_cov_.model,
                                           float(model.spatial_cov_.anisotropy))
    params = {**params, "progress": False, **override}
    return type(model)(**params)


def refit_carries(observed: np.ndarray, rank: int, offset: bool) -> bool:
    """Whether a rank-``rank`` refit on snapshots observed where ``observed`` ``(t, L)`` (bool)
    is True leaves residual degrees of freedom: the fit's own check
    (:func:`~lrm_cvx.glrm.fit.max_identifiable_rank`), made before a validation refits, so a
    short record skips what it cannot refit instead of failing with the refit's error."""
    from ..glrm.fit import max_identifiable_rank

    M = np.asarray(observed, dtype=bool)
    n_obs, L_obs = int(np.count_nonzero(M)), int(np.count_nonzero(M.any(axis=0)))
    t = int(M.shape[0])
    return 1 <= rank <= min(t, L_obs) and max_identifiable_rank(n_obs, t, L_obs,
                                                                offset=offset) >= rank


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


def validation_window(region: Any, max_cells: int = VALIDATION_MAX_CELLS
                      ) -> tuple[slice, slice] | None:
    """``(rows, cols)``: the grid window a validation of a model of ``region`` reads, or None
    when the region has at most ``max_cells`` cells (the whole region is read).

    The window is the smallest square of grid positions (clipped to the grid) centred on the
    valid cells' median row and column that holds at least ``max_cells`` valid cells: one
    contiguous piece of the region at its own resolution, so the validations' routes and
    transects are flown over neighbouring cells as a campaign's are, and the residual's
    covariance is seen at the lags a campaign samples. Deterministic; ``O(grid)``."""
    max_cells = int(max_cells)
    if max_cells < 1:
        raise ModelError(f"max_cells must be a positive integer, got {max_cells}")
    if region.n_cells <= max_cells:
        return None
    mask = region.mask
    ny, nx = mask.shape
    area = np.zeros((ny + 1, nx + 1), dtype=np.int64)  # summed-area table of the valid cells
    area[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0, dtype=np.int64), axis=1)
    rc, cc = (int(np.median(region.grid_index[:, i])) for i in (0, 1))

    def box(h: int) -> tuple[int, int, int, int]:
        return max(0, rc - h), min(ny, rc + h + 1), max(0, cc - h), min(nx, cc + h + 1)

    def count(h: int) -> int:
        r0, r1, c0, c1 = box(h)
        return int(area[r1, c1] - area[r0, c1] - area[r1, c0] + area[r0, c0])

    lo, hi = 0, max(ny, nx)  # count(hi) is every cell
    while lo < hi:  # the smallest half-width holding max_cells
        mid = (lo + hi) // 2
        lo, hi = (mid + 1, hi) if count(mid) < max_cells else (lo, mid)
    r0, r1, c0, c1 = box(lo)
    return slice(r0, r1), slice(c0, c1)


def validation_view(model: Any, data: Any, values: np.ndarray | None = None,
                    max_cells: int | None = None) -> tuple[Any, Any, np.ndarray | None]:
    """``(view, data, values)``: what a validation of the fitted ``model`` on its training
    ``data`` ``(time, lat, lon)`` reads. For a region of at most ``max_cells`` cells
    (:data:`VALIDATION_MAX_CELLS`) the arguments themselves. Else the window of
    :func:`validation_window`: ``view`` a shallow copy of ``model`` whose region is the window
    (its refits, clones of ``model``, fit the window's cells only; its factors ``Y_`` are
    dropped, so a validation cannot read the whole region's), ``data`` cropped
    to it (lazily for dask: only the window is ever loaded), and ``values`` (``data`` stacked
    ``(T, L)``, when given) the window's columns. A validation writes its result on ``model``,
    never on the view."""
    import xarray as xr

    region = getattr(model, "region_", None)
    if region is None or not isinstance(data, xr.DataArray) or data.ndim != 3:
        return model, data, values  # the validation raises its own error on such input
    window = validation_window(region, VALIDATION_MAX_CELLS if max_cells is None
                               else max_cells)
    if window is None:
        return model, data, values
    rows, cols = window
    sub = region.crop(rows, cols)
    view = copy.copy(model)
    view.region_, view.n_cells_ = sub, sub.n_cells
    view.Y_ = None  # the whole region's factors: no validation may read them
    data = _crop(data, rows, cols)
    if values is not None and np.shape(values)[-1:] == (region.n_cells,):  # else: the
        gi = region.grid_index  # validation's own check of its shape raises
        inside = ((gi[:, 0] >= rows.start) & (gi[:, 0] < rows.stop)
                  & (gi[:, 1] >= cols.start) & (gi[:, 1] < cols.stop))
        values = np.asarray(values)[:, inside]
    return view, data, values


def validation_data(data: Any, region: Any) -> tuple[Any, Any]:
    """``(data, region)`` (``data``'s region) cropped to the window of
    :func:`validation_window`, or the whole of them when the region holds at most
    :data:`VALIDATION_MAX_CELLS` cells: what a validation that fits its own reference model
    reads (``rank="auto"``'s, before the real fit)."""
    window = validation_window(region, VALIDATION_MAX_CELLS)
    if window is None:
        return data, region
    return _crop(data, *window), region.crop(*window)


def _crop(data: Any, rows: slice, cols: slice) -> Any:
    """``data`` ``(time, lat, lon)`` at the window's grid positions (lazily for dask)."""
    from ..region import spatial_dims

    lat_dim, lon_dim = spatial_dims(data)
    return data.isel({lat_dim: rows, lon_dim: cols})
