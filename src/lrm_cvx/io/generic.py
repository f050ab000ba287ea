"""One entry point for every data source the command line accepts.

``open_data`` recognises NOAA NDVI CDR files by name, image folders by content, bundled samples by
``sample:NAME``, and otherwise opens NetCDF files with a ``(time, lat, lon)`` variable.
"""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from ..errors import DataError

__all__ = ["open_data", "open_netcdf"]

_CDR_NAME = re.compile(r"^(AVHRR|VIIRS)-Land_v\d{3}")
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff"}
_RENAME = {"latitude": "lat", "longitude": "lon", "y": "lat", "x": "lon"}


def _expand(paths: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out: list[Path] = []
    for item in items:
        text = str(item)
        matches = sorted(glob.glob(text)) if any(c in text for c in "*?[") else [text]
        if not matches:
            raise DataError(f"no file matches {text!r}")
        out.extend(Path(m) for m in matches)
    return out


def _bbox_select(da: xr.DataArray, bbox: Sequence[float] | None) -> xr.DataArray:
    if bbox is None:
        return da
    south, west, north, east = (float(v) for v in bbox)
    lat, lon = da["lat"].values, da["lon"].values
    rows = (lat >= south) & (lat <= north)
    cols = (lon >= west) & (lon <= east) if west <= east else (lon >= west) | (lon <= east)
    if not rows.any() or not cols.any():
        raise DataError(
            f"bbox {tuple(bbox)} lies outside the data (lat {lat.min():g}..{lat.max():g}, "
            f"lon {lon.min():g}..{lon.max():g})"
        )
    return da.isel(lat=np.flatnonzero(rows), lon=np.flatnonzero(cols))


def open_netcdf(paths: Sequence[Path], var: str | None = None,
                bbox: Sequence[float] | None = None) -> xr.DataArray:
    """A ``(time, lat, lon)`` float32 DataArray from generic NetCDF file(s)."""
    try:
        if len(paths) == 1:
            ds = xr.open_dataset(paths[0])
        else:
            ds = xr.open_mfdataset([str(p) for p in paths], combine="by_coords")
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read NetCDF {', '.join(map(str, paths))}: {exc}") from None
    ds = ds.rename({k: v for k, v in _RENAME.items() if k in ds.dims and v not in ds.dims})
    if var is None:
        candidates = [n for n, v in ds.data_vars.items()
                      if {"time", "lat", "lon"} <= set(v.dims)]
        if len(candidates) != 1:
            raise DataError(
                f"{paths[0]}: cannot choose the variable (found {candidates or 'none'} with dims "
                "time, lat, lon); pass var / --var"
            )
        var = candidates[0]
    if var not in ds:
        raise DataError(f"{paths[0]} has no variable {var!r}; it has {list(ds.data_vars)}")
    da = ds[var]
    extra = [d for d in da.dims if d not in ("time", "lat", "lon")]
    for d in extra:
        if da.sizes[d] != 1:
            raise DataError(f"variable {var!r} has extra dim {d!r} of size {da.sizes[d]}")
    da = da.squeeze(extra, drop=True)
    if set(da.dims) != {"time", "lat", "lon"}:
        raise DataError(f"variable {var!r} must have dims (time, lat, lon), got {da.dims}")
    da = _bbox_select(da.transpose("time", "lat", "lon"), bbox)
    return da.astype(np.float32).load()


def open_data(paths: Any, *, var: str | None = None, bbox: Sequence[float] | None = None,
              chunks: Any = None) -> xr.DataArray:
    """Open any supported source as a ``(time, lat, lon)`` DataArray.

    ``paths`` is ``sample:NAME`` (bundled samples), NOAA CDR NDVI files (by name), a folder of
    RGB images (needs ``bbox = (south, west, north, east)``), or NetCDF file(s) with a
    ``(time, lat, lon)`` variable (``var`` picks it when there are several).
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if len(items) == 1 and str(items[0]).startswith("sample:"):
        from ..datasets import load_sample

        da = load_sample(str(items[0]).split(":", 1)[1])
        return _bbox_select(da, bbox)
    files = _expand(items)
    if len(files) == 1 and files[0].is_dir():
        folder = files[0]
        images = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in _IMAGE_SUFFIXES]
        if images:
            if bbox is None:
                raise DataError(f"images in {folder} need a bbox (south, west, north, east)")
            from .imagery import open_image_stack

            return open_image_stack(images, bbox)
        files = sorted(folder.glob("*.nc"))
        if not files:
            raise DataError(f"folder {folder} holds no images and no NetCDF files")
    missing = [str(p) for p in files if not p.exists()]
    if missing:
        raise DataError(f"file not found: {missing[0]}")
    if all(_CDR_NAME.match(p.name) for p in files):
        from .ndvi import open_ndvi_cdr

        return open_ndvi_cdr([str(p) for p in files], bbox=bbox, chunks=chunks)
    if all(p.suffix.lower() in _IMAGE_SUFFIXES for p in files):
        if bbox is None:
            raise DataError("images need a bbox (south, west, north, east)")
        from .imagery import open_image_stack

        return open_image_stack(files, bbox)
    return open_netcdf(files, var=var, bbox=bbox)
