"""RGB image stacks (e.g. NASA Worldview snapshots) <-> hue in degrees, with masks.

:func:`open_image_stack` reads a stack into a float32 ``(time, lat, lon)`` DataArray of hue in
``[0, 360)`` with NaN where a pixel is cloud, no data or a lighting artefact (the masking rules
are in docs/data-formats.md); :func:`write_image_stack` writes any field as such snapshots.
"""

from __future__ import annotations

import glob
import os
import re
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from .._validation import atomic_output, check_positive, datetime_ns
from ..errors import DataError, RegionError
from ..region import check_bbox

__all__ = [
    "open_image_stack",
    "write_image_stack",
    "hue_to_value",
    "field_bbox",
    "IMAGE_SUFFIXES",
    "DEFAULT_SATURATION_MIN",
    "DEFAULT_VALUE_MAX",
    "DEFAULT_DARK_MAX",
    "DEFAULT_EDGE_SIGMA",
    "DEFAULT_EDGE_LOW",
    "DEFAULT_EDGE_HIGH",
    "DEFAULT_EDGE_DILATE",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
"""File name endings (case-insensitive) taken from a folder."""

DEFAULT_SATURATION_MIN = 0.2
"""Clouds are greyish: saturation below 0.2 (foliage, water and most land are above 0.25)."""
DEFAULT_VALUE_MAX = 0.6
"""... and bright: value above 0.6 (~153/255); dark grey (shadow, haze over water) is kept."""
DEFAULT_DARK_MAX = 0.05
"""No-data fill is black: value below 0.05 (~13/255), above JPEG noise around 0, below the
darkest real land or water (dark forest and deep water have value ~0.1-0.2)."""
DEFAULT_EDGE_SIGMA = 2.0
"""Canny Gaussian smoothing (pixels): ignores pixel-scale texture, keeps swath seams, glint
and cloud borders."""
DEFAULT_EDGE_LOW = 0.1
"""Canny hysteresis thresholds on the Sobel magnitude of the smoothed value (skimage's own
defaults for float images). With ``sigma = 2`` a straight step of height ``dv`` gives a
magnitude of about ``1.6 dv``, so steps of value above ~0.12 (~32/255) seed an edge."""
DEFAULT_EDGE_HIGH = 0.2
DEFAULT_EDGE_DILATE = 2
"""Edges are grown by 2 pixels (a disk) to cover the blurred band on both sides."""

_TIFF = {".tif", ".tiff"}
_GRAY_MODES = {"1", "L", "LA", "La", "I", "I;16", "I;16B", "I;16L", "I;16N", "F"}
_DATE = re.compile(
    r"(?<!\d)(\d{4})-(\d{2})-(\d{2})(?:T(\d{2})[_:\-]?(\d{2})[_:\-]?(\d{2}))?(?!\d)"
)
_READ_ERRORS = (OSError, ValueError, SyntaxError, EOFError, struct.error, IndexError, KeyError)
_PIL_FORMATS = {"png": "PNG", "jpg": "JPEG", "jpeg": "JPEG", "tif": "TIFF", "tiff": "TIFF"}


# --------------------------------------------------------------------------- arguments
def _check_bbox(bbox: Any) -> tuple[float, float, float, float]:
    """``(south, west, north, east)`` as floats with south < north and west < east.

    An image's box must not wrap: give one crossing the antimeridian with ``east`` beyond 180
    (e.g. 170 .. 190), so its columns get increasing longitudes.
    """
    south, west, north, east = check_bbox(bbox, RegionError)
    if south == north:
        raise RegionError(f"bbox must have south < north for an image, got {bbox!r}")
    if west > east:
        raise RegionError(
            f"bbox west={west:g} is east of east={east:g}: an image's bbox must have "
            f"west < east; for one crossing the antimeridian give east + 360 "
            f"({west:g} .. {east + 360:g})")
    if not (west < east and east - west <= 360.0):
        raise RegionError(f"bbox must have west < east <= west + 360, got {bbox!r}")
    return south, west, north, east


def _check_unit(value: Any, name: str) -> float:
    v = check_positive(value, name)
    if v > 1.0:
        raise DataError(f"{name} must be in [0, 1], got {value!r}")
    return v


def _list_files(paths_or_folder: Any) -> list[Path]:
    """Image files from a folder, a file, a glob pattern or a sequence of those."""
    if isinstance(paths_or_folder, (str, os.PathLike)):
        items = [paths_or_folder]
    else:
        try:
            items = list(paths_or_folder)
        except TypeError:
            raise DataError(
                f"paths_or_folder must be a folder, a file, a glob or a list of files, "
                f"got {paths_or_folder!r}"
            ) from None
    files: list[Path] = []
    for item in items:
        text = os.fspath(item)
        path = Path(text)
        if path.is_dir():
            found = sorted(
                p for p in path.iterdir()
                if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
                and p.is_file()
            )
            if not found:
                raise DataError(f"folder {path} holds no image ({', '.join(IMAGE_SUFFIXES)})")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        elif any(c in text for c in "*?["):
            matches = [Path(m) for m in sorted(glob.glob(text)) if Path(m).is_file()]
            if not matches:
                raise DataError(f"no file matches {text!r}")
            files.extend(matches)
        else:
            raise DataError(f"image file or folder not found: {text}")
    if not files:
        raise DataError("paths_or_folder names no image file")
    return files


def _parse_time(path: Path) -> np.datetime64:
    """The first ``YYYY-MM-DD[THH_MM_SS]`` in the file name (Worldview ``snapshot-...Z.jpg``)."""
    match = _DATE.search(path.name)
    if match is None:
        raise DataError(
            f"cannot find a date YYYY-MM-DD in the file name {path}; pass times=[...]"
        )
    y, m, d, hh, mm, ss = match.groups()
    text = f"{y}-{m}-{d}" + (f"T{hh}:{mm}:{ss}" if hh is not None else "T00:00:00")
    try:
        stamp = pd.Timestamp(text)
    except (ValueError, OverflowError):
        raise DataError(f"invalid date {match.group(0)!r} in the file name {path}") from None
    return datetime_ns(stamp, label=f"the date {match.group(0)!r} in the file name {path}")


def _times(files: list[Path], times: Any) -> np.ndarray:
    if times is None:
        return np.array([_parse_time(p) for p in files], dtype="datetime64[ns]")
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        raise DataError(f"times must be a list of dates, one per image, got {times!r}")
    if len(times) != len(files):
        raise DataError(f"times has {len(times)} dates but there are {len(files)} images")
    try:
        stamps = pd.to_datetime(list(times))
    except (TypeError, ValueError, OverflowError) as exc:
        raise DataError(f"times must be dates: {exc}") from None
    for i in np.flatnonzero((stamps < pd.Timestamp.min) | (stamps > pd.Timestamp.max))[:1]:
        datetime_ns(stamps[i], label=f"times[{i}] = {stamps[i]}")  # refused, not wrapped
    values = stamps.values.astype("datetime64[ns]")
    if np.isnat(values).any():
        raise DataError(f"times has a missing date (NaT) at index {int(np.isnat(values).argmax())}")
    return values


# --------------------------------------------------------------------------- reading
class _NotTiffRGB(Exception):
    """tifffile could not give an RGB array: let Pillow try (palette, grayscale, JPEG-in-TIFF)."""


def _tiff_layout(shape: tuple[int, ...]) -> tuple[int, int, bool]:
    """``(ny, nx, planar)`` of an RGB(A) TIFF array shape."""
    if len(shape) == 3 and shape[-1] in (3, 4):
        return shape[0], shape[1], False
    if len(shape) == 3 and shape[0] in (3, 4):
        return shape[1], shape[2], True
    raise _NotTiffRGB(f"array shape {shape}")


def _tiff_probe(path: Path) -> tuple[int, int]:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            shape = tuple(int(s) for s in tf.series[0].shape)
    except Exception as exc:  # tifffile raises many kinds on corrupt files
        raise _NotTiffRGB(str(exc)) from None
    ny, nx, _ = _tiff_layout(shape)
    return ny, nx


def _tiff_read(path: Path) -> np.ndarray:
    """(Geo)TIFFs of any bit depth and band layout via tifffile, as ``(ny, nx, 3 or 4)``."""
    import tifffile

    try:
        arr = np.asarray(tifffile.imread(path, series=0))
    except Exception as exc:  # tifffile raises many kinds on corrupt files
        raise _NotTiffRGB(str(exc)) from None
    _, _, planar = _tiff_layout(arr.shape)
    if planar:
        arr = np.moveaxis(arr, 0, -1)
    if arr.dtype.kind == "f":
        arr = np.clip(np.nan_to_num(arr, nan=0.0), 0.0, 1.0)
    elif arr.dtype.kind != "u":
        raise DataError(f"{path} has pixel type {arr.dtype}; expected unsigned integers or "
                        "floats in [0, 1]")
    return arr


def _grayscale(path: Path, mode: str) -> DataError:
    return DataError(
        f"{path} is a grayscale image (mode {mode}); an RGB image is needed to compute hue"
    )


def _probe(path: Path) -> tuple[int, int]:
    """``(rows, columns)`` from the header; DataError for unreadable or grayscale images."""
    from PIL import Image

    if path.suffix.lower() in _TIFF:
        try:
            return _tiff_probe(path)
        except _NotTiffRGB:
            pass
    try:
        with Image.open(path) as im:
            mode, (nx, ny) = im.mode, im.size
    except (*_READ_ERRORS, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read image {path}: {exc}") from None
    if mode in _GRAY_MODES:
        raise _grayscale(path, mode)
    return ny, nx


def _read(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``(rgb (ny, nx, 3), nodata (ny, nx) bool or None)``; nodata is where alpha == 0.

    TIFFs go through tifffile first (keeps 16-bit and band-separate GeoTIFFs exact), everything
    else (and TIFFs tifffile cannot turn into RGB) through Pillow.
    """
    from PIL import Image

    arr = None
    if path.suffix.lower() in _TIFF:
        try:
            arr = _tiff_read(path)
        except _NotTiffRGB:
            arr = None
    if arr is None:
        try:
            with Image.open(path) as im:
                mode = im.mode
                if mode in _GRAY_MODES:
                    raise _grayscale(path, mode)
                if mode in ("P", "PA"):
                    rgba = mode == "PA" or "transparency" in im.info
                    im = im.convert("RGBA" if rgba else "RGB")
                elif mode == "RGBa":
                    im = im.convert("RGBA")
                elif mode not in ("RGB", "RGBA"):
                    im = im.convert("RGB")
                arr = np.asarray(im)
        except (*_READ_ERRORS, Image.DecompressionBombError) as exc:
            raise DataError(f"cannot read image {path}: {exc}") from None
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise DataError(f"{path} decoded to shape {arr.shape}; expected (rows, columns, 3 or 4)")
    nodata = arr[..., 3] == 0 if arr.shape[-1] == 4 else None
    return arr[..., :3], nodata


def _hue_into(
    row: np.ndarray, rgb: np.ndarray, nodata: np.ndarray | None, *, saturation_min: float,
    value_max: float, dark_max: float, edge_sigma: float | None, edge_low: float,
    edge_high: float, edge_dilate: int,
) -> None:
    """Write the masked hue (degrees, float32) of one ``(ny, nx, 3)`` image into ``row``."""
    from skimage.color import rgb2hsv

    hsv = rgb2hsv(rgb)  # float64 (ny, nx, 3), h, s, v in [0, 1]
    s, v = hsv[..., 1], hsv[..., 2]
    np.multiply(hsv[..., 0], 360.0, out=row, casting="same_kind")
    row[row >= np.float32(360.0)] = 0.0  # float32 rounding of hue just below 1
    mask = s < saturation_min
    mask &= v > value_max
    mask |= v < dark_max
    if nodata is not None:
        mask |= nodata
    if edge_sigma is not None:
        from skimage.feature import canny

        edges = canny(v, sigma=edge_sigma, low_threshold=edge_low, high_threshold=edge_high)
        if edge_dilate > 0 and edges.any():
            from scipy.ndimage import binary_dilation
            from skimage.morphology import disk

            edges = binary_dilation(edges, structure=disk(edge_dilate))
        mask |= edges
    row[mask] = np.nan


def open_image_stack(
    paths_or_folder: str | os.PathLike | Sequence[str | os.PathLike],
    bbox: Sequence[float],
    times: Sequence[Any] | None = None,
    *,
    saturation_min: float = DEFAULT_SATURATION_MIN,
    value_max: float = DEFAULT_VALUE_MAX,
    dark_max: float = DEFAULT_DARK_MAX,
    edge_sigma: float | None = DEFAULT_EDGE_SIGMA,
    edge_low: float = DEFAULT_EDGE_LOW,
    edge_high: float = DEFAULT_EDGE_HIGH,
    edge_dilate: int = DEFAULT_EDGE_DILATE,
    name: str = "hue",
) -> xr.DataArray:
    """Hue in degrees ``[0, 360)`` of a stack of RGB images, NaN where masked.

    Parameters
    ----------
    paths_or_folder : a folder (its ``.png/.jpg/.jpeg/.tif/.tiff`` files, sorted by name), an
        image file, a glob pattern, or a sequence of files/patterns. PNG, JPEG and (Geo)TIFF are
        read with Pillow (tifffile for TIFFs Pillow cannot decode); RGBA alpha 0 is no data;
        grayscale images are refused (hue needs colour).
    bbox : ``(south, west, north, east)`` in degrees spanned by every image (the edges of the
        outer pixels, as in a Worldview download), so the top row is the north.
    times : one date per image, in the order of ``paths_or_folder`` (after the folder's sort by
        name); by default parsed from the file names (the first ``YYYY-MM-DD``, with an optional
        ``THH_MM_SS`` as in Worldview's ``snapshot-2013-09-01T00_00_00Z.jpg``).
    saturation_min, value_max : cloud rule ``s < saturation_min and v > value_max``.
    dark_max : no-data rule ``v < dark_max``.
    edge_sigma, edge_low, edge_high, edge_dilate : lighting-artefact rule: Canny edges of ``v``
        (Gaussian ``edge_sigma`` pixels, hysteresis thresholds on the Sobel magnitude of ``v``),
        dilated by a disk of radius ``edge_dilate`` pixels. ``edge_sigma=None`` disables it.

    Returns
    -------
    float32 DataArray ``(time, lat, lon)`` sorted by time; ``lat`` descending from
    ``north - dlat/2``, ``lon`` ascending from ``west + dlon/2`` (pixel centres). Attributes
    record the source files and every threshold used. Images are decoded one at a time into
    one preallocated array, so memory is about the output's size plus one image.

    Raises
    ------
    DataError : no image, unreadable or grayscale image, images of different sizes, a name
        without a date (and no ``times``), ``times`` of the wrong length, duplicate dates.
    RegionError : invalid ``bbox``.
    """
    south, west, north, east = _check_bbox(bbox)
    saturation_min = _check_unit(saturation_min, "saturation_min")
    value_max = _check_unit(value_max, "value_max")
    dark_max = _check_unit(dark_max, "dark_max")
    if edge_sigma is not None:
        edge_sigma = check_positive(edge_sigma, "edge_sigma", strict=True)
        edge_low = check_positive(edge_low, "edge_low")
        edge_high = check_positive(edge_high, "edge_high")
        if edge_high < edge_low:
            raise DataError(f"edge_high ({edge_high}) must be >= edge_low ({edge_low})")
        if isinstance(edge_dilate, bool) or not isinstance(edge_dilate, (int, np.integer)) \
                or edge_dilate < 0:
            raise DataError(f"edge_dilate must be an integer >= 0, got {edge_dilate!r}")
        edge_dilate = int(edge_dilate)

    files = _list_files(paths_or_folder)
    stamps = _times(files, times)
    order = np.argsort(stamps, kind="stable")
    files = [files[i] for i in order]
    stamps = stamps[order]
    dup = np.flatnonzero(stamps[1:] == stamps[:-1])
    if dup.size:
        i = int(dup[0])
        raise DataError(
            f"{files[i]} and {files[i + 1]} have the same time {pd.Timestamp(stamps[i])}"
        )

    shapes = [_probe(p) for p in files]
    for p, shape in zip(files, shapes, strict=True):
        if shape != shapes[0]:
            raise DataError(
                f"images differ in size: {files[0]} is {shapes[0][0]} x {shapes[0][1]} pixels "
                f"(rows x columns) but {p} is {shape[0]} x {shape[1]}"
            )
    ny, nx = shapes[0]
    out = np.empty((len(files), ny, nx), dtype=np.float32)
    params = dict(saturation_min=saturation_min, value_max=value_max, dark_max=dark_max,
                  edge_sigma=edge_sigma, edge_low=edge_low, edge_high=edge_high,
                  edge_dilate=edge_dilate)
    for t, path in enumerate(files):
        rgb, nodata = _read(path)
        if rgb.shape[:2] != (ny, nx):
            raise DataError(
                f"images differ in size: {files[0]} is {ny} x {nx} pixels but {path} decoded "
                f"to {rgb.shape[0]} x {rgb.shape[1]}"
            )
        _hue_into(out[t], rgb, nodata, **params)
        del rgb, nodata

    dlat, dlon = (north - south) / ny, (east - west) / nx
    lat = north - (np.arange(ny) + 0.5) * dlat
    lon = west + (np.arange(nx) + 0.5) * dlon
    attrs: dict[str, Any] = {
        "units": "degree",
        "long_name": "hue",
        "valid_min": 0.0,
        "valid_max": 360.0,
        "source": "RGB image stack read by lrm_cvx.io.open_image_stack",
        "source_files": "\n".join(str(p) for p in files),
        "bbox": [south, west, north, east],
        "saturation_min": saturation_min,
        "value_max": value_max,
        "dark_max": dark_max,
        "edge_masking": "none" if edge_sigma is None else "canny",
        "comment": (
            "HSV hue (skimage.color.rgb2hsv) x 360, NaN where s < saturation_min and "
            "v > value_max (cloud), v < dark_max or alpha == 0 (no data)"
            + ("" if edge_sigma is None else
               ", or within edge_dilate pixels of a Canny edge of v (lighting artefact)")
        ),
    }
    if edge_sigma is not None:
        attrs.update(edge_sigma=edge_sigma, edge_low_threshold=edge_low,
                     edge_high_threshold=edge_high, edge_dilate=edge_dilate)
    return xr.DataArray(
        out,
        dims=("time", "lat", "lon"),
        coords={
            "time": ("time", stamps, {"standard_name": "time", "long_name": "time"}),
            "lat": ("lat", lat, {"units": "degrees_north", "standard_name": "latitude",
                                 "long_name": "latitude", "axis": "Y"}),
            "lon": ("lon", lon, {"units": "degrees_east", "standard_name": "longitude",
                                 "long_name": "longitude", "axis": "X"}),
        },
        name=name,
        attrs=attrs,
    )


# --------------------------------------------------------------------------- writing
def _check_span(start_hue: Any, hue_span: Any) -> tuple[float, float]:
    try:
        start, span = float(start_hue), float(hue_span)
    except (TypeError, ValueError):
        raise DataError(f"start_hue and hue_span must be numbers, got {start_hue!r}, "
                        f"{hue_span!r}") from None
    if not (np.isfinite(start) and np.isfinite(span) and 0.0 < abs(span) < 360.0):
        raise DataError(
            f"hue_span must be in (-360, 0) or (0, 360) degrees and start_hue finite, got "
            f"start_hue={start_hue!r}, hue_span={hue_span!r}"
        )
    return start % 360.0, span


def hue_to_value(hue: Any, vmin: float, vmax: float, *, start_hue: float = 0.0,
                 hue_span: float = 300.0) -> Any:
    """Invert :func:`write_image_stack`'s encoding: ``vmin + d / hue_span * (vmax - vmin)``.

    ``d`` is the hue's angular distance from ``start_hue`` in the direction of ``hue_span``;
    hues in the unused arc are split at its middle (just below ``start_hue`` maps slightly
    below ``vmin``). Works on arrays and DataArrays (NaN stays NaN).
    """
    start, span = _check_span(start_hue, hue_span)
    d = ((hue - start) if span > 0 else (start - hue)) % 360.0
    d = xr.where(d > 0.5 * (abs(span) + 360.0), d - 360.0, d) if isinstance(d, xr.DataArray) \
        else np.where(d > 0.5 * (abs(span) + 360.0), d - 360.0, d)
    return vmin + d / abs(span) * (vmax - vmin)


def _grid_edges(coord: np.ndarray, what: str) -> tuple[float, float]:
    if coord.size < 2:
        raise DataError(f"field_bbox needs at least 2 {what} values, got {coord.size}")
    step = np.abs(np.diff(coord)).mean()
    return float(coord.min() - step / 2), float(coord.max() + step / 2)


def field_bbox(field: xr.DataArray) -> tuple[float, float, float, float]:
    """``(south, west, north, east)`` spanned by a ``(..., lat, lon)`` grid of cell centres.

    Pass it to :func:`open_image_stack` to read back :func:`write_image_stack`'s images on the
    field's own grid (for an equally spaced grid).
    """
    from ..region import spatial_dims

    ydim, xdim = spatial_dims(field)
    if ydim not in field.coords or xdim not in field.coords:
        raise DataError(f"field needs {ydim} and {xdim} coordinates for a bbox")
    south, north = _grid_edges(np.asarray(field[ydim].values, dtype=np.float64), str(ydim))
    west, east = _grid_edges(np.asarray(field[xdim].values, dtype=np.float64), str(xdim))
    return south, west, north, east


def _encode(a: np.ndarray, vmin: float, scale: float, start: float, span: float,
            value: float) -> np.ndarray:
    """``(ny, nx, 3)`` uint8 RGB of hue ``start + span * clip((a - vmin) * scale, 0, 1)``.

    HSV -> RGB with s = 1: channel ``n`` (R 5, G 3, B 1) is
    ``v * (1 - clip(min(k, 4 - k), 0, 1))`` with ``k = (n + h / 60) mod 6``. NaN -> white.
    """
    frac = np.subtract(a, np.float32(vmin), dtype=np.float32)
    frac *= np.float32(scale)
    nan = np.isnan(frac)
    frac[nan] = 0.0
    np.clip(frac, 0.0, 1.0, out=frac)
    h6 = frac  # reuse: hue / 60 in [0, 6)
    h6 *= np.float32(span / 60.0)
    h6 += np.float32(start / 60.0)
    np.mod(h6, np.float32(6.0), out=h6)
    rgb = np.empty(a.shape + (3,), dtype=np.uint8)
    level = np.float32(255.0 * value)
    k = np.empty_like(h6)
    f = np.empty_like(h6)
    for c, n in enumerate((5.0, 3.0, 1.0)):
        np.add(h6, np.float32(n), out=k)
        np.mod(k, np.float32(6.0), out=k)
        np.subtract(np.float32(4.0), k, out=f)
        np.minimum(f, k, out=f)
        np.clip(f, 0.0, 1.0, out=f)
        np.subtract(np.float32(1.0), f, out=f)
        f *= level
        np.rint(f, out=f)
        rgb[..., c] = f
    rgb[nan] = 255
    return rgb


def write_image_stack(
    folder: str | os.PathLike,
    field: xr.DataArray,
    *,
    vmin: float | None = None,
    vmax: float | None = None,
    fmt: str = "png",
    start_hue: float = 0.0,
    hue_span: float = 300.0,
    value: float = 0.8,
    prefix: str = "snapshot-",
    compress_level: int = 1,
    jpeg_quality: int = 95,
    overwrite: bool = True,
) -> list[Path]:
    """Write a ``(time, lat, lon)`` field as RGB snapshots whose hue encodes it linearly.

    Each time step becomes ``folder/{prefix}YYYY-MM-DDTHH_MM_SSZ.{fmt}`` (Worldview's naming)
    of hue ``start_hue + hue_span * (x - vmin) / (vmax - vmin)`` degrees (values clipped to
    ``[vmin, vmax]``; defaults: the field's finite min and max), saturation 1 and HSV value
    ``value`` (0.8 keeps pixels clear of the cloud and no-data rules), and NaN as white cloud
    pixels (s = 0, v = 1). The top row is the north (rows are flipped if ``lat`` ascends).
    :func:`open_image_stack` with ``bbox=field_bbox(field)`` and :func:`hue_to_value` recover
    the field up to 8-bit quantisation (hue step <= 0.15 degrees at value 0.8) away from
    masked edges. ``fmt`` is ``png`` (``compress_level`` 0-9), ``jpg``/``jpeg`` (lossy,
    ``jpeg_quality``, no chroma subsampling) or ``tif``/``tiff`` (uncompressed). Each file is
    written atomically; work is per image in float32. Returns the paths in time order.
    """
    from PIL import Image

    from ..region import spatial_dims

    fmt_key = str(fmt).lower().lstrip(".")
    if fmt_key not in _PIL_FORMATS:
        raise DataError(f"fmt must be one of {sorted(_PIL_FORMATS)}, got {fmt!r}")
    start, span = _check_span(start_hue, hue_span)
    value = check_positive(value, "value", strict=True)
    if value > 1.0:
        raise DataError(f"value must be in (0, 1], got {value!r}")
    if not isinstance(field, xr.DataArray) or field.ndim != 3 or "time" not in field.dims:
        raise DataError(
            f"field must be a (time, lat, lon) DataArray, got "
            f"{getattr(field, 'dims', type(field).__name__)}"
        )
    if "time" not in field.coords:
        raise DataError("field needs a time coordinate to name the images")
    field = field.transpose("time", ...)
    ydim, xdim = spatial_dims(field)
    flip_y = ydim in field.coords and field.sizes[ydim] > 1 and \
        float(field[ydim][0]) < float(field[ydim][-1])
    flip_x = xdim in field.coords and field.sizes[xdim] > 1 and \
        float(field[xdim][0]) > float(field[xdim][-1])

    try:
        stamps = pd.DatetimeIndex(pd.to_datetime(field["time"].values))
    except (TypeError, ValueError) as exc:
        raise DataError(f"field's time coordinate must hold dates: {exc}") from None
    if stamps.isna().any():
        raise DataError("field's time coordinate has a missing date (NaT)")
    names = [f"{prefix}{ts:%Y-%m-%dT%H_%M_%S}Z.{fmt_key}" for ts in stamps]
    if len(set(names)) != len(names):
        raise DataError("field has two time steps in the same second; file names would clash")

    def frame(t: int) -> np.ndarray:
        return np.asarray(field.isel(time=t).values, dtype=np.float32)

    if vmin is None or vmax is None:
        lo, hi = np.inf, -np.inf
        for t in range(field.sizes["time"]):
            a = frame(t)
            lo_t, hi_t = np.fmin.reduce(a, axis=None), np.fmax.reduce(a, axis=None)
            if np.isfinite(lo_t):
                lo, hi = min(lo, float(lo_t)), max(hi, float(hi_t))
        if not np.isfinite(lo):
            raise DataError("field is all NaN: pass vmin and vmax to write it")
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
        if vmax == vmin:
            vmax = vmin + 1.0
    vmin, vmax = float(vmin), float(vmax)
    if not (np.isfinite(vmin) and np.isfinite(vmax) and vmax > vmin):
        raise DataError(f"need finite vmin < vmax, got vmin={vmin!r}, vmax={vmax!r}")

    pil_format = _PIL_FORMATS[fmt_key]
    if pil_format == "PNG":
        save_kw: dict[str, Any] = {"compress_level": int(compress_level)}
    elif pil_format == "JPEG":
        save_kw = {"quality": int(jpeg_quality), "subsampling": 0}
    else:
        save_kw = {}
    out_dir = Path(folder)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for t, name in enumerate(names):
        a = frame(t)
        if flip_y:
            a = a[::-1]
        if flip_x:
            a = a[:, ::-1]
        rgb = _encode(a, vmin, 1.0 / (vmax - vmin), start, span, value)
        path = out_dir / name
        with atomic_output(path, overwrite=overwrite) as tmp:
            Image.fromarray(rgb).save(tmp, format=pil_format, **save_kw)
        written.append(path)
    return written
