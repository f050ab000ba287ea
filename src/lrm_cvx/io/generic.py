"""One entry point for every data source the command line accepts.

``open_data`` recognises NOAA NDVI CDR files by name, image folders by content, bundled samples by
``sample:NAME``, and otherwise opens NetCDF files with a ``(time, lat, lon)`` variable.
"""

from __future__ import annotations

import glob
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .._validation import check_input_file, check_time_labels
from ..errors import DataError
from ..region import to_geographic_order

__all__ = ["open_data", "open_netcdf", "expand_paths"]

_CDR_NAME = re.compile(r"^(AVHRR|VIIRS)-Land_v\d{3}")
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff"}
_RENAME = {"latitude": "lat", "longitude": "lon", "y": "lat", "x": "lon"}


def expand_paths(paths: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """Local paths with globs expanded. URLs are left out: they are not local files (so the
    CLI's input guard skips them) and :func:`lrm_cvx.io.remote.expand_urls` lists them."""
    from .remote import is_url

    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out: list[Path] = []
    for item in items:
        if is_url(item):
            continue
        text = str(item)
        matches = sorted(glob.glob(text)) if any(c in text for c in "*?[") else [text]
        if not matches:
            raise DataError(f"no file matches {text!r}")
        out.extend(Path(m) for m in matches)
    return out


def _bbox_select(da: xr.DataArray, bbox: Sequence[float] | None) -> xr.DataArray:
    """Crop to ``bbox`` with columns in geographic order (see ``region.to_geographic_order``)."""
    return to_geographic_order(da, bbox, DataError)


def _normalise(da: xr.DataArray, source: str, bbox: Sequence[float] | None, *,
               lazy: bool = False) -> xr.DataArray:
    """Checks and normal form shared by every generic source: ``(time, lat, lon)`` float32.

    Renames latitude/longitude/y/x, squeezes extra size-1 dims, refuses empty axes and
    duplicated times, sorts an unsorted time axis (with a warning), checks and orders the grid
    (:func:`lrm_cvx.region.to_geographic_order`), loads (unless ``lazy``) and drops all-NaN
    snapshots with a warning.
    """
    name = da.name if da.name is not None else "data"
    da = da.rename({k: v for k, v in _RENAME.items() if k in da.dims and v not in da.dims})
    if not {"time", "lat", "lon"} <= set(da.dims):
        raise DataError(f"{source}: variable {name!r} must have dims (time, lat, lon) "
                        f"(or latitude/longitude, y/x), got {da.dims}")
    extra = [d for d in da.dims if d not in ("time", "lat", "lon")]
    for d in extra:
        if da.sizes[d] != 1:
            raise DataError(f"{source}: variable {name!r} has extra dim {d!r} of size "
                            f"{da.sizes[d]}; select one (e.g. da.isel({d}=0))")
    da = da.squeeze(extra, drop=True)
    if set(da.dims) != {"time", "lat", "lon"}:
        raise DataError(f"{source}: variable {name!r} must have dims (time, lat, lon), "
                        f"got {da.dims}")
    da = da.transpose("time", "lat", "lon")
    empty = [d for d in da.dims if da.sizes[d] == 0]
    if empty:
        raise DataError(f"{source}: variable {name!r} is empty (dim {empty[0]!r} has size 0)")
    if "time" in da.coords:
        check_time_labels(da["time"].values, source)
        index = da.indexes["time"]
        if not index.is_unique:
            dup = index[index.duplicated()][0]
            raise DataError(f"{source}: time {dup} occurs more than once; each snapshot needs "
                            "its own time (drop or average the duplicates)")
        if not index.is_monotonic_increasing:
            warnings.warn(f"{source}: time is not sorted; snapshots were sorted by time",
                          UserWarning, stacklevel=3)
            da = da.sortby("time")
    da = _bbox_select(da, bbox)
    source_da = da
    try:
        with np.errstate(over="ignore"):  # a value beyond float32 is reported below
            da = da.astype(np.float32)
            if not lazy:
                da = da.load()
    except Exception as exc:  # netCDF4/HDF5 raise several types for truncated data
        raise DataError(f"cannot read {source}: {exc}") from None
    if lazy:
        return da
    _refuse_float32_overflow(source_da, da, source, name)
    finite = np.isfinite(da.values).reshape(da.shape[0], -1).any(axis=1)
    if not finite.any():
        raise DataError(f"{source}: variable {name!r} has no finite value (all NaN"
                        f"{' inside bbox ' + str(tuple(bbox)) if bbox is not None else ''})")
    if not finite.all():
        dropped = da["time"].values[~finite] if "time" in da.coords else np.flatnonzero(~finite)
        more = " ..." if dropped.size > 5 else ""
        warnings.warn(f"{source}: dropped {int((~finite).sum())} all-NaN snapshot(s) "
                      f"(time {', '.join(map(str, dropped[:5]))}{more})",
                      UserWarning, stacklevel=3)
        da = da.isel(time=np.flatnonzero(finite))
    return da


def _refuse_float32_overflow(original: xr.DataArray, cast: xr.DataArray, source: str,
                             name: Any) -> None:
    """DataError when finite values of ``original`` became inf in its float32 ``cast``: data
    are held in float32 (max 3.4e38), so such values would read as missing."""
    if not (np.issubdtype(original.dtype, np.floating) and original.dtype.itemsize > 4):
        return
    if not np.isinf(cast.values).any():  # the usual case: nothing read twice
        return
    values = np.asarray(original.values)
    over = np.isinf(cast.values) & np.isfinite(values)
    if over.any():
        top = float(np.abs(values[over]).max())
        raise DataError(f"{source}: variable {name!r} has {int(over.sum())} value(s) up to "
                        f"{top:.3g} in magnitude, beyond float32 (max "
                        f"{float(np.finfo(np.float32).max):.3g}), which lrm-cvx holds data in; "
                        "rescale the data (other units) or mask them (NaN) if they are fill "
                        "values")


def _choose_var(ds: xr.Dataset, var: str | None, source: str) -> xr.DataArray:
    ds = ds.rename({k: v for k, v in _RENAME.items() if k in ds.dims and v not in ds.dims})
    if var is None:
        candidates = [n for n, v in ds.data_vars.items()
                      if {"time", "lat", "lon"} <= set(v.dims)]
        if len(candidates) != 1:
            raise DataError(
                f"{source}: cannot choose the variable (found {candidates or 'none'} with dims "
                f"time, lat, lon among {list(ds.data_vars)}); pass var / --var"
            )
        var = candidates[0]
    if var not in ds.data_vars:
        raise DataError(f"{source} has no variable {var!r}; it has {list(ds.data_vars)}")
    return ds[var]


def _open_netcdf_urls(urls: Sequence[str], var: str | None, bbox: Sequence[float] | None,
                      storage_options: dict[str, Any] | None, cache: Any) -> xr.DataArray:
    """:func:`open_netcdf` for URLs: each file opened lazily, subset to ``bbox``, loaded (with
    retries, :func:`lrm_cvx.io.remote.read_remote`), then the pieces combined by coords."""
    from .remote import read_remote

    def subset(ds: xr.Dataset, url: str) -> xr.DataArray:
        da = _choose_var(ds, var, url)
        return to_geographic_order(da.rename(
            {k: v for k, v in _RENAME.items() if k in da.dims and v not in da.dims}),
            bbox, DataError).load()

    pieces = [read_remote(u, lambda ds, u=u: subset(ds, u), storage_options=storage_options,
                          cache=cache) for u in urls]
    source = ", ".join(urls)
    if len(pieces) == 1:
        da = pieces[0]
    else:
        name = pieces[0].name
        try:
            da = xr.combine_by_coords([p.to_dataset(name=name) for p in pieces])[name]
        except Exception as exc:
            raise DataError(f"cannot combine {source}: {exc}") from None
    return _normalise(da, source, None)


def open_netcdf(paths: Sequence[Path], var: str | None = None,
                bbox: Sequence[float] | None = None) -> xr.DataArray:
    """A ``(time, lat, lon)`` float32 DataArray from generic NetCDF file(s).

    Raises DataError naming the file for an empty, corrupt or truncated file, a missing or
    ambiguous variable, wrong dims, bad coordinates (NaN/inf, duplicated, non-monotonic lat)
    or duplicated times.
    """
    source = ", ".join(map(str, paths))
    for p in paths:
        if p.is_file() and p.stat().st_size == 0:
            raise DataError(f"{p} is an empty file (0 bytes), not NetCDF")
    try:
        if len(paths) == 1:
            ds = xr.open_dataset(paths[0])
        else:
            ds = xr.open_mfdataset([str(p) for p in paths], combine="by_coords")
    except Exception as exc:  # netCDF4/HDF5/xarray raise several types for a bad file
        raise DataError(f"cannot read NetCDF {source}: {exc}") from None
    with ds:
        return _normalise(_choose_var(ds, var, source), source, bbox)


def open_data(paths: Any, *, var: str | None = None, bbox: Sequence[float] | None = None,
              chunks: Any = None, storage_options: dict[str, Any] | None = None,
              cache: Any = None) -> xr.DataArray:
    """Open any supported source as a ``(time, lat, lon)`` DataArray.

    ``paths`` is ``sample:NAME`` (bundled samples), NOAA CDR NDVI files (by name), a folder of
    RGB images (needs ``bbox = (south, west, north, east)``), NetCDF file(s) with a
    ``(time, lat, lon)`` variable (``var`` picks it when there are several), or an in-memory
    ``xarray.DataArray`` / ``Dataset`` (put through the same checks). ``bbox`` longitudes may
    use either convention; ``west > east`` crosses the antimeridian, and the columns of the
    result are always in geographic (eastward, contiguous) order.

    Paths may also be URLs (``https://``, ``s3://``, globs of them; NOAA CDR NDVI or NetCDF
    files, not images): each file is opened lazily over HTTP Range requests / S3 ranged GETs,
    subset to ``bbox`` and loaded, so only the chunks covering the box travel.
    ``storage_options`` go to fsspec (e.g. ``{"endpoint_url": ...}``; S3 is anonymous unless
    credentials are in the environment) and ``cache`` is a folder for fsspec's block cache
    (default ``$LRM_CVX_CACHE``). See :mod:`lrm_cvx.io.remote`.
    """
    if isinstance(paths, xr.DataArray):
        return _normalise(paths, "DataArray", bbox)
    if isinstance(paths, xr.Dataset):
        return _normalise(_choose_var(paths, var, "Dataset"), "Dataset", bbox)
    if isinstance(paths, (bytes, bytearray)) or paths is None or not isinstance(
            paths, (str, os.PathLike, list, tuple)):
        raise DataError(
            "paths must be a file path, a glob pattern, a folder, 'sample:NAME', a list of "
            f"those, or an xarray DataArray/Dataset; got {type(paths).__name__}"
        )
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not items:
        raise DataError("paths is an empty list: give at least one file")
    if len(items) == 1 and str(items[0]).startswith("sample:"):
        from ..datasets import load_sample

        return _normalise(load_sample(str(items[0]).split(":", 1)[1]), str(items[0]), bbox)
    from .remote import expand_urls, is_url

    urls = [str(i) for i in items if is_url(i)]
    if urls:
        if len(urls) != len(items):
            raise DataError("paths mixes URLs and local files; give one kind at a time")
        urls = expand_urls(urls, storage_options)
        names = [u.split("?", 1)[0].rstrip("/").rsplit("/", 1)[-1] for u in urls]
        if all(_CDR_NAME.match(n) for n in names):
            from .ndvi import open_ndvi_cdr

            return open_ndvi_cdr(urls, bbox=bbox, chunks=chunks,
                                 storage_options=storage_options, cache=cache)
        if any(Path(n).suffix.lower() in _IMAGE_SUFFIXES for n in names):
            raise DataError(f"images are read from local folders only, not from {urls[0]}")
        return _open_netcdf_urls(urls, var, bbox, storage_options, cache)
    files = expand_paths(items)
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
    for p in files:  # a symlink loop or a FIFO, device or socket: reading one may hang
        check_input_file(p, "data file")
    missing = [str(p) for p in files if not p.exists()]
    if missing:
        raise DataError(f"file not found: {missing[0]}")
    folders = [str(p) for p in files if p.is_dir()]
    if folders:
        raise DataError(f"{folders[0]} is a folder; give it alone or give its files")
    if all(_CDR_NAME.match(p.name) for p in files):
        from .ndvi import open_ndvi_cdr

        return open_ndvi_cdr([str(p) for p in files], bbox=bbox, chunks=chunks)
    if all(p.suffix.lower() in _IMAGE_SUFFIXES for p in files):
        if bbox is None:
            raise DataError("images need a bbox (south, west, north, east)")
        from .imagery import open_image_stack

        return open_image_stack(files, bbox)
    return open_netcdf(files, var=var, bbox=bbox)
