"""NOAA Climate Data Record (CDR) of daily NDVI -> ``(time, lat, lon)`` DataArray with QA masking.

AVHRR v5 and VIIRS v1 files are told apart by name; NDVI and QA bits are decoded from the raw
integers, so a QA fill value is never mistaken for a flag. File names and QA bits are described
in docs/data-formats.md.
"""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from .._validation import atomic_output, datetime_ns
from ..errors import DataError
from ..region import check_bbox, check_coords, geographic_order, lon_in_box

__all__ = [
    "open_ndvi_cdr",
    "write_ndvi_cdr",
    "parse_cdr_name",
    "decode_qa",
    "AVHRR_FLAGS",
    "VIIRS_FLAGS",
    "DEFAULT_MASK_FLAGS",
    "NDVI_SCALE",
    "NDVI_FILL",
    "NDVI_VALID_RANGE",
    "QA_FILL",
]

NDVI_SCALE = 1e-4
NDVI_FILL = -9999
NDVI_VALID_RANGE = (-1000, 10000)
QA_FILL = -32767

AVHRR_FLAG_NAMES = (
    "cloudy cloud_shadow water sunglint dense_dark_vegetation night ch1_to_5_valid ch1_invalid "
    "ch2_invalid ch3_invalid ch4_invalid ch5_invalid rho3_invalid BRDF_corr_problem polar_flag"
).split()
AVHRR_FLAGS: dict[str, int] = {name: 1 << (i + 1) for i, name in enumerate(AVHRR_FLAG_NAMES)}
"""AVHRR v5 QA flag name -> bit mask (bit 1 cloudy ... bit 15 polar_flag)."""

VIIRS_FLAGS: dict[str, str] = {
    "cloudy": "cloud state (bits 0-1) cloudy or mixed, or the internal cloud flag (bit 10)",
    "cloud_shadow": "bit 2",
    "water": "land/water class (bits 3-5) other than land (0) or land-and-desert (1)",
    "high_aerosol": "aerosol quantity (bits 6-7) high (3)",
    "thin_cirrus": "thin cirrus (bits 8-9) not none (0)",
    "snow_ice": "bit 15",
}
"""VIIRS v1 QA flag names this loader understands, with the bits they test."""

DEFAULT_MASK_FLAGS: dict[str, tuple[str, ...]] = {
    "AVHRR": ("cloudy", "cloud_shadow", "water", "sunglint", "ch1_invalid", "ch2_invalid",
              "ch3_invalid", "ch4_invalid", "ch5_invalid"),
    "VIIRS": ("cloudy", "cloud_shadow", "water", "snow_ice"),
}
"""Flags that make a cell unusable by default, per product."""

_NAME = re.compile(
    r"^(?P<product>AVHRR|VIIRS)-Land_v(?P<version>\d{3})(?:-preliminary)?_"
    r"(?P<code>AVH13C1|NPP13C1|JP113C1)_(?P<platform>[A-Za-z0-9-]+)_(?P<date>\d{8})_c\d+\.nc$"
)


def parse_cdr_name(path: str | os.PathLike) -> dict[str, Any]:
    """``{"product", "platform", "date"}`` from a CDR file name; DataError if it is not one."""
    name = _name(path)
    m = _NAME.match(name)
    if m is None:
        raise DataError(
            f"{name!r} is not a NOAA CDR NDVI file name (expected "
            "AVHRR-Land_v005_AVH13C1_<PLATFORM>_<YYYYMMDD>_c<proc>.nc or "
            "VIIRS-Land_v001_NPP13C1_S-NPP_<YYYYMMDD>_c<proc>.nc)"
        )
    try:
        date = pd.Timestamp(m["date"])
    except ValueError:
        raise DataError(f"{name!r}: {m['date']} is not a valid date") from None
    datetime_ns(date, label=f"{name!r}: the date {m['date']}")  # refused, not wrapped
    return {"product": m["product"], "platform": m["platform"], "date": date}


def decode_qa(qa_raw: Any, product: str, flags: Iterable[str]) -> Any:
    """Boolean array, True where any of ``flags`` is set in the raw int16 QA of ``product``.

    Works on numpy, dask and xarray objects alike (only bitwise operations). The QA fill value
    (-32767) is not decoded here: callers treat it as "no QA", i.e. unusable.
    """
    q = qa_raw.astype(np.int32) & 0xFFFF
    out = None
    for flag in flags:
        if product == "AVHRR":
            if flag not in AVHRR_FLAGS:
                raise DataError(f"unknown AVHRR QA flag {flag!r}; known: {AVHRR_FLAG_NAMES}")
            hit = (q & AVHRR_FLAGS[flag]) != 0
        elif product == "VIIRS":
            if flag == "cloudy":
                state = q & 0b11
                hit = (state == 1) | (state == 2) | ((q & (1 << 10)) != 0)
            elif flag == "cloud_shadow":
                hit = (q & (1 << 2)) != 0
            elif flag == "water":
                hit = ((q >> 3) & 0b111) > 1
            elif flag == "high_aerosol":
                hit = ((q >> 6) & 0b11) == 3
            elif flag == "thin_cirrus":
                hit = ((q >> 8) & 0b11) != 0
            elif flag == "snow_ice":
                hit = (q & (1 << 15)) != 0
            else:
                raise DataError(f"unknown VIIRS QA flag {flag!r}; known: {list(VIIRS_FLAGS)}")
        else:
            raise DataError(f"unknown product {product!r}")
        out = hit if out is None else (out | hit)
    if out is None:
        out = q != q  # nothing to mask
    return out


def _expand(paths_or_glob: Any, storage_options: dict[str, Any] | None = None
            ) -> list[Path | str]:
    """Local files as Paths (globs and folders expanded) and URLs as strings (see
    :func:`lrm_cvx.io.remote.expand_urls` for URL globs and folders)."""
    from .remote import expand_urls, is_url

    items = [paths_or_glob] if isinstance(paths_or_glob, (str, os.PathLike)) else list(
        paths_or_glob)
    files: list[Path | str] = []
    for item in items:
        if is_url(item):
            files.extend(expand_urls([item], storage_options))
            continue
        p = Path(item)
        if p.is_dir():
            files.extend(sorted(p.glob("*.nc")))
        elif any(c in str(item) for c in "*?["):
            files.extend(Path(f) for f in sorted(glob.glob(str(item))))
        else:
            if not p.exists():
                raise DataError(f"NDVI file not found: {p}")
            files.append(p)
    if not files:
        raise DataError(f"no NOAA CDR NDVI file matches {paths_or_glob!r}")
    return files


def _name(path: Path | str) -> str:
    from .remote import is_url, url_name

    return url_name(path) if is_url(path) else Path(path).name


def _resolve_flags(mask_flags: Any, products: set[str]) -> dict[str, tuple[str, ...]]:
    if mask_flags is None or (isinstance(mask_flags, str) and mask_flags == "default"):
        return {p: DEFAULT_MASK_FLAGS[p] for p in products}
    if isinstance(mask_flags, dict):
        missing = products - set(mask_flags)
        if missing:
            raise DataError(f"mask_flags has no entry for product(s) {sorted(missing)}")
        return {p: tuple(mask_flags[p]) for p in products}
    flags = (mask_flags,) if isinstance(mask_flags, str) else tuple(mask_flags)
    return {p: flags for p in products}


def _bbox_index(lat: np.ndarray, lon: np.ndarray, bbox: Sequence[float] | None, name: str):
    """Row and column selectors for ``bbox`` and the longitudes of the selected columns.

    Columns come back in geographic order (``region.geographic_order``): a box crossing the
    antimeridian (``west > east``) on the CDR's -180..180 grid gives e.g. 170..190.
    """
    check_coords(lat, lon, name, DataError)
    if bbox is None:
        order, new_lon = geographic_order(lon)
        cols = slice(None) if np.array_equal(order, np.arange(lon.size)) else order
        return slice(None), cols, new_lon
    south, west, north, east = check_bbox(bbox, DataError)
    rows = np.flatnonzero((lat >= south) & (lat <= north))
    cols = np.flatnonzero(lon_in_box(lon, west, east))
    if rows.size == 0 or cols.size == 0:
        raise DataError(
            f"bbox {tuple(bbox)} lies outside the data of {name} "
            f"(lat {lat.min():g}..{lat.max():g}, lon {lon.min():g}..{lon.max():g})"
        )
    order, new_lon = geographic_order(lon[cols], west)
    cols = cols[order]
    # contiguous runs become slices: they keep the read lazy and cheap
    row_sel = slice(rows[0], rows[-1] + 1) if np.all(np.diff(rows) == 1) else rows
    col_sel = slice(cols[0], cols[-1] + 1) if np.all(np.diff(cols) == 1) else cols
    return row_sel, col_sel, new_lon


def _decode_file(ds: xr.Dataset, name: str, product: str, flags: tuple[str, ...],
                 bbox: Sequence[float] | None) -> xr.DataArray:
    for var in ("NDVI", "QA"):
        if var not in ds.variables:
            raise DataError(f"{name}: no {var!r} variable (has {sorted(ds.variables)})")
    ndvi_raw, qa_raw = ds["NDVI"], ds["QA"]
    expected = {"time", "latitude", "longitude"}
    for var in (ndvi_raw, qa_raw):
        if set(var.dims) != expected:
            raise DataError(f"{name}: {var.name} has dims {var.dims}, expected "
                            "(time, latitude, longitude)")
    lat = np.asarray(ds["latitude"].values, dtype=np.float64)
    lon = np.asarray(ds["longitude"].values, dtype=np.float64)
    rows, cols, new_lon = _bbox_index(lat, lon, bbox, name)
    sel = {"latitude": rows, "longitude": cols}
    ndvi_raw = ndvi_raw.transpose("time", "latitude", "longitude").isel(sel)
    qa_raw = qa_raw.transpose("time", "latitude", "longitude").isel(sel)
    enc = file_encoding(ds["NDVI"].attrs, ds["QA"].attrs)
    usable = _ndvi_ok(ndvi_raw, enc) & _qa_ok(qa_raw, product, flags, enc)
    ndvi = _ndvi_value(ndvi_raw, enc).where(usable)
    ndvi = ndvi.astype(np.float32).rename({"latitude": "lat", "longitude": "lon"})
    return ndvi.assign_coords(lon=new_lon)


# ----------------------------------------------------------- decoding rules (the only copy)
def file_encoding(ndvi_attrs: Any, qa_attrs: Any) -> tuple:
    """``(scale, offset, fill, vmin, vmax, qa_fill)`` of a file's NDVI / QA attributes."""
    vmin, vmax = ndvi_attrs.get("valid_range", NDVI_VALID_RANGE)
    return (float(ndvi_attrs.get("scale_factor", NDVI_SCALE)),
            float(ndvi_attrs.get("add_offset", 0.0)),
            int(ndvi_attrs.get("_FillValue", NDVI_FILL)), int(vmin), int(vmax),
            int(qa_attrs.get("_FillValue", QA_FILL)))


def _ndvi_ok(ndvi_raw: Any, enc: tuple) -> Any:
    """Raw NDVI that is not fill and inside ``valid_range``."""
    _, _, fill, vmin, vmax, _ = enc
    return (ndvi_raw != fill) & (ndvi_raw >= vmin) & (ndvi_raw <= vmax)


def _qa_ok(qa_raw: Any, product: str, flags: tuple[str, ...], enc: tuple) -> Any:
    """QA present (not fill) with none of ``flags`` set."""
    return (qa_raw != enc[5]) & ~decode_qa(qa_raw, product, flags)


def _ndvi_value(ndvi_raw: Any, enc: tuple) -> Any:
    """Physical NDVI, float32 arithmetic: ``raw * scale + offset``."""
    return ndvi_raw.astype(np.float32) * np.float32(enc[0]) + np.float32(enc[1])


_LUTS: dict = {}


def decode_tables(product: str, flags: tuple[str, ...], enc: tuple
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(values, qa_ok)``: the decoding rules above evaluated once on all 65 536 int16 codes.

    ``values[u]`` (float32) is the NDVI of raw code ``u`` (``raw.view(uint16)``), NaN where
    the raw value is unusable; ``qa_ok[u]`` is True where QA code ``u`` is usable. A day then
    decodes as ``where(qa_ok[qa.view(uint16)], values[ndvi.view(uint16)], NaN)``, bit for bit
    what :func:`open_ndvi_cdr` gives (the same functions computed each code's entry).
    """
    key = (product, tuple(flags), enc)
    if key not in _LUTS:
        codes = np.arange(65536, dtype=np.uint32).astype(np.uint16).view(np.int16)
        values = np.where(_ndvi_ok(codes, enc), _ndvi_value(codes, enc), np.float32(np.nan))
        _LUTS[key] = (values.astype(np.float32), np.asarray(_qa_ok(codes, product, flags, enc)))
    return _LUTS[key]


def decode_day(ndvi_raw: np.ndarray, qa_raw: np.ndarray, tables: tuple[np.ndarray, np.ndarray]
               ) -> np.ndarray:
    """One day's raw int16 NDVI and QA (same shape) -> float32 NDVI, NaN where unusable
    (table lookups from :func:`decode_tables`; numpy releases the GIL)."""
    values, qa_ok = tables
    out = np.take(values, np.asarray(ndvi_raw, dtype=np.int16).view(np.uint16))
    bad = ~np.take(qa_ok, np.asarray(qa_raw, dtype=np.int16).view(np.uint16))
    np.copyto(out, np.float32(np.nan), where=bad)
    return out


def window_index(path: str | os.PathLike, bbox: Sequence[float] | None) -> tuple[Any, Any]:
    """``(rows, cols)`` of ``bbox`` in the grid of CDR file ``path`` (as :func:`open_ndvi_cdr`
    selects them: geographic column order)."""
    import netCDF4

    with netCDF4.Dataset(str(path)) as nc:
        lat = np.asarray(nc.variables["latitude"][:], dtype=np.float64)
        lon = np.asarray(nc.variables["longitude"][:], dtype=np.float64)
    rows, cols, _ = _bbox_index(lat, lon, bbox, _name(path))
    return rows, cols


def read_window(path: str | os.PathLike, rows: Any, cols: Any
                ) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Raw ``(NDVI, QA, encoding)`` of one CDR file's window ``rows x cols`` (slices or index
    arrays, as :func:`_bbox_index` gives them) as ``(ny, nx)`` int16 arrays, with netCDF4
    (not thread-safe: callers serialise calls in one process)."""
    import netCDF4

    try:
        nc = netCDF4.Dataset(str(path))
    except Exception as exc:
        raise DataError(f"cannot read NDVI file {path}: {exc}") from None
    try:
        out = []
        for var in ("NDVI", "QA"):
            if var not in nc.variables:
                raise DataError(f"{_name(path)}: no {var!r} variable")
            v = nc.variables[var]
            v.set_auto_maskandscale(False)
            dims = tuple(v.dimensions)
            if set(dims) != {"time", "latitude", "longitude"}:
                raise DataError(f"{_name(path)}: {var} has dims {dims}, expected "
                                "(time, latitude, longitude)")
            span = {"time": 0}
            for d, sel in (("latitude", rows), ("longitude", cols)):
                span[d] = sel if isinstance(sel, slice) else slice(int(sel.min()),
                                                                   int(sel.max()) + 1)
            a = np.asarray(v[tuple(span[d] for d in dims)])
            a = a.transpose([[d for d in dims if d != "time"].index(x)
                             for x in ("latitude", "longitude")])
            if not isinstance(rows, slice):
                a = a[np.asarray(rows) - int(np.min(rows))]
            if not isinstance(cols, slice):
                a = a[:, np.asarray(cols) - int(np.min(cols))]
            out.append(np.ascontiguousarray(a, dtype=np.int16))
        enc = file_encoding({k: v_.getncattr(k) for v_ in (nc.variables["NDVI"],)
                         for k in v_.ncattrs()},
                        {k: nc.variables["QA"].getncattr(k)
                         for k in nc.variables["QA"].ncattrs()})
    except DataError:
        raise
    except Exception as exc:
        raise DataError(f"cannot decode NDVI file {path}: {exc}") from None
    finally:
        nc.close()
    return out[0], out[1], enc


def open_ndvi_cdr(
    paths_or_glob: Any,
    bbox: Sequence[float] | None = None,
    mask_flags: Any = None,
    chunks: Any = None,
    *,
    storage_options: dict[str, Any] | None = None,
    cache: Any = None,
) -> xr.DataArray:
    """Daily NOAA CDR NDVI files -> ``(time, lat, lon)`` float32 NDVI in [-1, 1], NaN if unusable.

    Parameters
    ----------
    paths_or_glob : a glob pattern, a folder, a path, a URL (``https://``, ``s3://``; globs and
        folder URLs as :func:`lrm_cvx.io.remote.expand_urls` lists them) or a list of them
        (AVHRR v5 and VIIRS v1 files may be mixed; each file's QA is decoded with its own
        product's layout).
    bbox : ``(south, west, north, east)`` in degrees; cells whose centre lies inside are kept.
        Each file is subset before anything is read, so a small box of the 3600 x 7200 global
        grid costs little.
    mask_flags : flag names that make a cell unusable: None = :data:`DEFAULT_MASK_FLAGS`
        (cloudy, cloud shadow, water, sunglint, any channel invalid for AVHRR; cloudy, cloud
        shadow, water, snow/ice for VIIRS), a sequence applied to every product, or a dict
        ``{"AVHRR": [...], "VIIRS": [...]}``. Fill values, values outside ``valid_range`` and a
        missing QA always make a cell unusable.
    chunks : None loads each file's subset into memory as it is read (memory = the result);
        a dask chunk spec (e.g. ``{"time": 1}``) returns a lazy dask-backed DataArray (for a
        URL, the bbox subset is read when opened and then chunked).
    storage_options : options of the URLs' fsspec filesystem (e.g. ``{"anon": False}``,
        ``{"endpoint_url": ...}`` for another S3 server, HTTP ``headers``); S3 is anonymous
        unless credentials are in the environment.
    cache : a folder for fsspec's block cache of URLs (e.g. ``"~/.cache/lrm-cvx"``; default
        ``$LRM_CVX_CACHE`` if set; False: none). Only the blocks read are stored.

    A URL is read with HTTP Range requests / S3 ranged GETs fetching only the chunks covering
    ``bbox``, retried on transient failures; a 404, a refused or dropped connection is a
    DataError naming the URL (:func:`lrm_cvx.io.remote.read_remote`).
    The time of each file is its date in the file name; files are sorted by time. Attributes
    record units, the flags used, the products and the source files.
    """
    from .remote import is_url, read_remote

    files = _expand(paths_or_glob, storage_options)
    meta = [parse_cdr_name(f) for f in files]
    order = np.argsort([m["date"].value for m in meta], kind="stable")
    files = [files[i] for i in order]
    meta = [meta[i] for i in order]
    products = {m["product"] for m in meta}
    flags = _resolve_flags(mask_flags, products)
    arrays = []
    for path, m in zip(files, meta, strict=True):
        time = [np.datetime64(m["date"], "ns")]
        if is_url(path):
            def subset(ds: xr.Dataset, m: dict = m, path: Any = path) -> xr.DataArray:
                da = _decode_file(ds, _name(path), m["product"], flags[m["product"]], bbox)
                return da.load()

            da = read_remote(str(path), subset, storage_options=storage_options, cache=cache,
                             mask_and_scale=False, decode_times=False)
            da = da.assign_coords(time=time)
            if chunks is not None:  # the file's dim names as the local path takes them
                names = {"latitude": "lat", "longitude": "lon"}
                da = da.chunk({names.get(k, k): v for k, v in chunks.items()}
                              if isinstance(chunks, dict) else chunks)
            arrays.append(da)
            continue
        try:
            ds = xr.open_dataset(path, mask_and_scale=False, decode_times=False,
                                 chunks=chunks, engine="netcdf4")
        except Exception as exc:  # netCDF4/HDF5 raise several types for a corrupt file
            raise DataError(f"cannot read NDVI file {path}: {exc}") from None
        try:
            da = _decode_file(ds, _name(path), m["product"], flags[m["product"]], bbox)
            da = da.assign_coords(time=time)
            if chunks is None:
                da = da.load()
        except DataError:
            ds.close()
            raise
        except Exception as exc:
            ds.close()
            raise DataError(f"cannot decode NDVI file {path}: {exc}") from None
        if chunks is None:
            ds.close()
        arrays.append(da)
    ref = arrays[0]
    for path, da in zip(files, arrays, strict=True):
        if da.shape[1:] != ref.shape[1:] or not (
            np.allclose(da["lat"], ref["lat"]) and np.allclose(da["lon"], ref["lon"])
        ):
            raise DataError(f"{_name(path)} has a different grid than {_name(files[0])}")
    out = xr.concat(arrays, dim="time", join="override", coords="minimal", compat="override")
    out.name = "ndvi"
    out["lat"] = out["lat"].astype(np.float64)
    out["lon"] = out["lon"].astype(np.float64)
    out["lat"].attrs = {"standard_name": "latitude", "units": "degrees_north", "axis": "Y"}
    out["lon"].attrs = {"standard_name": "longitude", "units": "degrees_east", "axis": "X"}
    out["time"].attrs = {"standard_name": "time", "axis": "T"}
    out.attrs = {
        "long_name": "normalized difference vegetation index",
        "units": "1",
        "valid_min": -1.0,
        "valid_max": 1.0,
        "source": "NOAA Climate Data Record of AVHRR/VIIRS Normalized Difference Vegetation Index",
        "products": " ".join(sorted(products)),
        "mask_flags": "; ".join(f"{p}: {' '.join(f)}" for p, f in sorted(flags.items())),
        "source_files": "\n".join(_name(p) for p in files),
    }
    if chunks is not None and not any(is_url(p) for p in files):
        # what the file-level staging (io.staging.stage) needs to read the files itself; valid
        # only while out.data is this very graph (any operation renames it)
        out.encoding["lrm_cvx_cdr"] = {
            "files": [str(p) for p in files], "products": [m["product"] for m in meta],
            "flags": flags, "bbox": None if bbox is None else tuple(float(b) for b in bbox),
            "name": out.data.name, "shape": tuple(out.shape)}
    if chunks is None and not np.isfinite(out.values).any():
        raise DataError(
            f"every cell is masked in {len(files)} file(s) (bbox {bbox}, flags "
            f"{out.attrs['mask_flags']}): nothing usable"
        )
    return out


# --------------------------------------------------------------------------- writers
_CDR_EPOCH = np.datetime64("1981-01-01", "D")


def _cdr_name(product: str, platform: str, day: pd.Timestamp) -> str:
    stamp = day.strftime("%Y%m%d")
    if product == "AVHRR":
        return f"AVHRR-Land_v005_AVH13C1_{platform}_{stamp}_c20240101000000.nc"
    code = "JP113C1" if platform == "NOAA-20" else "NPP13C1"
    return f"VIIRS-Land_v001_{code}_{platform}_{stamp}_c20240101000000.nc"


def write_ndvi_cdr(
    folder: Any,
    field: xr.DataArray,
    start_date: Any = None,
    *,
    product: str = "AVHRR",
    platform: str | None = None,
    qa: np.ndarray | None = None,
    complevel: int = 1,
    chunks: tuple[int, int] | None = (512, 512),
) -> list:
    """Write ``field`` ``(time, lat, lon)`` as daily NOAA CDR NDVI NetCDF files, one per time.

    Files carry the real names, dims (``time`` of length 1 in days since 1981-01-01,
    ``latitude``, ``longitude``), ``NDVI`` int16 (scale 1e-4, fill -9999, ``valid_range``
    [-1000, 10000]) and ``QA`` int16 in the ``product``'s layout ("AVHRR" v5 flag bits or
    "VIIRS" v1 bit fields). Without ``qa``, a NaN cell is written as fill with its cloud flag
    set (AVHRR bit 1; VIIRS cloud state 1) and other cells with a clear QA; ``qa`` (int16,
    the field's shape) is written verbatim. Dates come from ``field.time`` or, when given,
    consecutive days from ``start_date``. Each file is written atomically; returns the paths.
    ``chunks`` is the HDF5 tile ``(rows, cols)`` of NDVI and QA (clipped to the grid; the real
    AVHRR files are tiled), compressed with zlib at ``complevel`` (0: none); ``None`` writes
    them contiguous (untiled, uncompressed).
    """
    import netCDF4

    if product not in ("AVHRR", "VIIRS"):
        raise DataError(f"product must be 'AVHRR' or 'VIIRS', got {product!r}")
    if not isinstance(field, xr.DataArray) or field.ndim != 3:
        raise DataError("field must be a (time, lat, lon) DataArray")
    platform = platform or ("NOAA-19" if product == "AVHRR" else "S-NPP")
    n_times = field.shape[0]
    if start_date is not None:
        days = pd.date_range(pd.Timestamp(start_date), periods=n_times, freq="D")
    elif "time" in field.coords and np.issubdtype(field["time"].dtype, np.datetime64):
        days = pd.DatetimeIndex(field["time"].values)
    else:
        raise DataError("field has no datetime time coordinate: pass start_date")
    if qa is not None and np.shape(qa) != field.shape:
        raise DataError(f"qa must have the field's shape {field.shape}, got {np.shape(qa)}")
    if chunks is not None and (len(chunks) != 2 or min(int(c) for c in chunks) < 1):
        raise DataError(f"chunks must be (rows, cols) of positive ints or None, got {chunks!r}")
    lat = np.asarray(field[field.dims[1]].values, dtype=np.float32)
    lon = np.asarray(field[field.dims[2]].values, dtype=np.float32)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cloud_bit = AVHRR_FLAGS["cloudy"] if product == "AVHRR" else 1
    if chunks is None:
        layout: dict[str, Any] = {"contiguous": True}
    else:
        layout = {"zlib": complevel > 0, "complevel": max(complevel, 1),
                  "chunksizes": (1, min(lat.size, int(chunks[0])), min(lon.size, int(chunks[1])))}
    paths = []
    for t in range(n_times):
        values = np.asarray(field[t].values, dtype=np.float32)
        bad = ~np.isfinite(values)
        raw = np.rint(np.clip(np.nan_to_num(values), -1.0, 1.0) * 1e4).astype(np.int16)
        raw[bad] = NDVI_FILL
        q = (np.asarray(qa[t], dtype=np.int16) if qa is not None
             else np.where(bad, np.int16(cloud_bit), np.int16(0)).astype(np.int16))
        path = folder / _cdr_name(product, platform, days[t])
        with atomic_output(path) as tmp:
            with netCDF4.Dataset(tmp, "w", format="NETCDF4") as nc:
                nc.createDimension("time", 1)
                nc.createDimension("latitude", lat.size)
                nc.createDimension("longitude", lon.size)
                tv = nc.createVariable("time", "f8", ("time",))
                tv.units, tv.standard_name = "days since 1981-01-01 00:00:00", "time"
                tv[:] = [(np.datetime64(days[t], "D") - _CDR_EPOCH).astype(float)]
                for name, values_1d, units in (("latitude", lat, "degrees_north"),
                                               ("longitude", lon, "degrees_east")):
                    v = nc.createVariable(name, "f4", (name,))
                    v.units, v.standard_name = units, name
                    v[:] = values_1d
                dims = ("time", "latitude", "longitude")
                nv = nc.createVariable("NDVI", "i2", dims, fill_value=NDVI_FILL, **layout)
                nv.set_auto_maskandscale(False)
                nv.long_name = "NOAA Climate Data Record of Normalized Difference Vegetation Index"
                nv.units = "1"
                nv.scale_factor = np.float32(1e-4)
                nv.add_offset = np.float32(0.0)
                nv.valid_range = np.array(NDVI_VALID_RANGE, dtype=np.int16)
                nv[0] = raw
                qv = nc.createVariable("QA", "i2", dims, fill_value=QA_FILL, **layout)
                qv.set_auto_maskandscale(False)
                qv.long_name = "quality assurance"
                if product == "AVHRR":
                    masks = np.array([AVHRR_FLAGS[n] for n in AVHRR_FLAG_NAMES], np.uint16)
                    qv.flag_masks = masks.view(np.int16)  # 2, 4, ..., 16384, -32768
                    qv.flag_meanings = " ".join(AVHRR_FLAG_NAMES)
                else:
                    qv.comment = ("bits 0-1 cloud state, 2 cloud shadow, 3-5 land/water, "
                                  "6-7 aerosol, 8-9 thin cirrus, 10 cloud, 15 snow/ice")
                qv[0] = q
                nc.title = f"synthetic {product} CDR NDVI written by lrm_cvx.io.samples"
                nc.Conventions = "CF-1.6"
        paths.append(path)
    return paths
