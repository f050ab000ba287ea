"""Coastlines on the maps: real coastlines where a shapefile is at hand, the valid-cell
outline otherwise.

A shapefile is found offline, never downloaded (``$LRM_CVX_COASTLINES``, then cartopy's data
folders; docs/monitoring.md), read with pyshp and drawn without changing the axes' limits.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataError

__all__ = ["COAST_CHOICES", "COAST_ENV", "check_coast", "coastline_file", "coastline_xy",
           "draw_coast", "lines_in_extent"]

COAST_CHOICES = ("auto", "cartopy", "outline", None)
"""``coast=``: ``"auto"`` real coastlines when a shapefile is found offline, else the outline;
``"cartopy"`` real coastlines or an error saying how to get them; ``"outline"`` the outline of
the cells with values (the coast as the data know it); ``None`` nothing."""
COAST_ENV = "LRM_CVX_COASTLINES"
DEBIAN_DATA_DIR = "/usr/share/cartopy/data"  # Debian's python-cartopy-data (GSHHS c, l)
_HOW = (f"pip install 'lrm-cvx[maps]' and put Natural Earth's ne_110m_coastline.shp in "
        f"cartopy.config['pre_existing_data_dir']/shapefiles/natural_earth/physical/, or set "
        f"{COAST_ENV}=/path/to/coastline.shp")


def check_coast(coast: Any) -> str | None:
    """``coast`` normalised: True -> ``"auto"``, False -> None; else one of
    :data:`COAST_CHOICES` or a :class:`DataError` naming them."""
    if coast is True:
        return "auto"
    if coast is False or coast is None:
        return None
    if isinstance(coast, str) and coast in COAST_CHOICES:
        return coast
    raise DataError(f"coast must be one of 'auto', 'cartopy', 'outline' or None, got {coast!r}")


def _candidates(span: float) -> list[tuple[tuple[str, ...], dict[str, str]]]:
    """Cartopy downloader specs, finest fitting scale first for a map ``span`` degrees wide."""
    ne = ["10m", "50m", "110m"] if span <= 20 else (
        ["50m", "110m", "10m"] if span <= 90 else ["110m", "50m", "10m"])
    gshhs = ["i", "l", "c"] if span <= 20 else (["l", "c", "i"] if span <= 90 else ["c", "l"])
    return ([(("shapefiles", "natural_earth", r, "physical", "coastline"),
              {"resolution": r, "category": "physical", "name": "coastline"}) for r in ne]
            + [(("shapefiles", "gshhs", s, "1"), {"scale": s, "level": "1"}) for s in gshhs])


def coastline_file(span: float = 360.0) -> Path | None:
    """The coastline shapefile at hand for a map ``span`` degrees wide, or None.

    ``$LRM_CVX_COASTLINES`` first (a missing file is a :class:`DataError`), then the files
    cartopy would use, looked up with its downloaders' own paths (pre-existing data dir, data
    dir, its repository data, Debian's data dir) but never downloaded; None without cartopy or
    without any of the files."""
    env = os.environ.get(COAST_ENV, "").strip()
    if env:
        path = Path(env).expanduser()
        if not path.is_file():
            raise DataError(f"{COAST_ENV}={env}: no such shapefile")
        return path
    try:
        import cartopy
        from cartopy.io import Downloader
    except ImportError:
        return None
    configs = [cartopy.config] + [
        {**cartopy.config, "data_dir": d} for d in (cartopy.config.get("repo_data_dir"),
                                                    DEBIAN_DATA_DIR) if d]
    for spec, keys in _candidates(span):
        try:
            loader = Downloader.from_config(spec)
        except Exception:  # noqa: BLE001 - a user's own downloader config: skip that kind
            continue
        for config in configs:
            fmt = {"config": config, **keys}
            paths = [loader.target_path(fmt)]
            if config is cartopy.config:
                paths.insert(0, loader.pre_downloaded_path(fmt))
            for p in paths:
                if p is not None and Path(p).is_file():
                    return Path(p)
    return None


@functools.lru_cache(maxsize=8)
def _read_band(path: str, mtime: float, south: float, north: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(points (n, 2) lon/lat, starts)`` of every line / ring of ``path`` whose record's box
    meets the latitude band; ``starts`` the index of each part's first point."""
    try:
        import shapefile
    except ImportError:
        raise DataError(f"reading {path} needs pyshp: {_HOW}") from None
    pts, starts, n = [], [], 0
    with shapefile.Reader(path) as reader:
        for shape in reader.iterShapes(bbox=(-1e4, south, 1e4, north)):
            if shape is None or not shape.points:
                continue
            xy = np.asarray(shape.points, dtype=np.float64)[:, :2]
            pts.append(xy)
            starts.append(np.asarray(shape.parts, dtype=np.int64) + n)
            n += len(xy)
    if not pts:
        return np.empty((0, 2)), np.empty(0, np.int64)
    return np.concatenate(pts), np.concatenate(starts)


def coastline_xy(path: str | Path, extent: tuple[float, float, float, float]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)``: the coastlines of ``path`` near ``extent = (west, east, south, north)``
    (degrees, ``west < east`` in the grid's own longitude convention, e.g. 100..300), lines
    separated by NaN, longitudes moved into the extent's window (every copy 360 degrees apart
    that meets it) and each line cut to the vertices inside plus one either side."""
    path = Path(path)
    pts, starts = _read_band(str(path), path.stat().st_mtime, float(extent[2]),
                             float(extent[3]))
    return lines_in_extent(pts, starts, extent)


def lines_in_extent(points: np.ndarray, starts: np.ndarray,
                    extent: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`coastline_xy` on lines in memory: ``points`` ``(n, 2)`` lon/lat in degrees (any
    longitude convention), ``starts`` the index of each line's first point (sorted, first 0)."""
    west, east, south, north = map(float, extent)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    starts = np.asarray(starts, dtype=np.int64)
    if not len(pts):
        return np.empty(0), np.empty(0)
    lon, lat = pts[:, 0], pts[:, 1]
    first = np.zeros(len(pts), dtype=bool)
    first[starts] = True
    part = np.cumsum(first) - 1
    # each line made continuous in longitude (each step the short way round)
    step = (np.diff(lon, prepend=lon[0]) + 180.0) % 360.0 - 180.0
    step[first] = 0.0
    run = np.cumsum(step)
    lon = lon[starts][part] + run - run[starts][part]
    ks = np.arange(np.ceil((west - lon.max()) / 360.0), np.floor((east - lon.min()) / 360.0) + 1)
    if not ks.size:
        return np.empty(0), np.empty(0)
    x = (lon[None, :] + 360.0 * ks[:, None]).ravel()
    y = np.tile(lat, ks.size)
    first = np.tile(first, ks.size)
    inside = (x >= west) & (x <= east) & (y >= south) & (y <= north)
    keep = inside.copy()
    keep[1:] |= inside[:-1] & ~first[1:]   # the vertex after an inside one, same line
    keep[:-1] |= inside[1:] & ~first[1:]   # the vertex before an inside one, same line
    idx = np.flatnonzero(keep)
    if not idx.size:
        return np.empty(0), np.empty(0)
    new_run = np.ones(idx.size, dtype=bool)
    new_run[1:] = (np.diff(idx) > 1) | first[idx[1:]]
    new_run[0] = False
    pos = np.arange(idx.size) + np.cumsum(new_run)
    out_x = np.full(idx.size + int(new_run.sum()), np.nan)
    out_y = out_x.copy()
    out_x[pos], out_y[pos] = x[idx], y[idx]
    return out_x, out_y


def _extent(lat: np.ndarray, lon: np.ndarray) -> tuple[float, float, float, float]:
    """Cell edges of a grid's centres: ``(west, east, south, north)``."""
    def edges(v: np.ndarray) -> tuple[float, float]:
        half = abs(float(v[1] - v[0])) / 2 if v.size > 1 else 0.5
        return float(v.min()) - half, float(v.max()) + half
    west, east = edges(lon)
    south, north = edges(lat)
    return west, east, south, north


def _in_degrees(lat: np.ndarray, lon: np.ndarray) -> bool:
    return bool(np.all(np.abs(lat) <= 90.0) and np.all((lon >= -360.0) & (lon <= 720.0)))


def draw_coast(ax: Any, lat: Any, lon: Any, coast: Any = "auto", *,
               valid: np.ndarray | None = None, color: str = "0.25", linewidth: float = 0.6
               ) -> str | None:
    """Draw the coast on ``ax`` (longitude x, latitude y in degrees, ``lat``/``lon`` the grid's
    1-D cell centres) and say what was drawn: ``"coastlines"``, ``"outline"`` or None.

    ``coast`` as in :data:`COAST_CHOICES`. The outline is the 0.5 contour of ``valid``
    (``(lat, lon)`` bool, True where a cell has a value), drawn when some cells are masked.
    ``"cartopy"`` without a shapefile at hand (or on a grid not in degrees) raises a one-line
    :class:`DataError` saying how to get one."""
    coast = check_coast(coast)
    if coast is None:
        return None
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if coast in ("auto", "cartopy"):
        degrees = _in_degrees(lat, lon)
        west, east, south, north = _extent(lat, lon)
        path = coastline_file(max(east - west, north - south)) if degrees else None
        if path is None and coast == "cartopy":
            why = ("the grid is not in degrees" if not degrees
                   else "no coastline shapefile found offline")
            raise DataError(f"coast='cartopy': {why}; {_HOW}")
        if path is not None:
            from matplotlib import patheffects
            from matplotlib.lines import Line2D

            x, y = coastline_xy(path, (west, east, south, north))
            # add_artist: the axes' data limits stay the grid's; a pale halo keeps the line
            # visible on dark colours too
            halo = patheffects.withStroke(linewidth=linewidth + 1.2, foreground="white",
                                          alpha=0.6)
            ax.add_artist(Line2D(x, y, color=color, linewidth=linewidth, zorder=2.5,
                                 label="_coastlines", path_effects=[halo]))
            return "coastlines"
    if valid is None:
        return None
    valid = np.asarray(valid, dtype=bool)
    if valid.any() and not valid.all() and min(valid.shape) > 1:
        ax.contour(lon, lat, valid.astype(float), levels=[0.5], colors=color,
                   linewidths=linewidth)
        return "outline"
    return None
