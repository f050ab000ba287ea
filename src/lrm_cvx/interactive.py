"""Interactive maps for notebooks (issue #25, item 4): folium (Leaflet) layers of the belief,
its uncertainty and the routes, switchable in a layer control.

Plain arrays in, a ``folium.Map`` out: :meth:`Plan.explore` and :meth:`MonitorState.explore`
call :func:`explore_map` with their own fields and routes. folium is an optional extra
(``pip install "lrm-cvx[explore]"``); without it the call says how to get it. Longitudes are
kept continuous (a route or grid across the antimeridian is drawn unbroken: Leaflet accepts
longitudes beyond 180), and fields are drawn as image overlays on the Web Mercator map.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .errors import DataError

__all__ = ["explore_map", "field_image"]

_ROUTE_COLOURS = ["#D55E00", "#0072B2", "#009E73", "#CC79A7", "#E69F00", "#56B4E9"]


def _folium() -> Any:
    try:
        import folium
    except ImportError:  # pragma: no cover - the extra is part of the dev install
        raise ImportError("interactive maps need folium: pip install 'lrm-cvx[explore]'"
                          ) from None
    return folium


def field_image(values: np.ndarray, cmap: str = "viridis", vmin: float | None = None,
                vmax: float | None = None) -> tuple[np.ndarray, float, float]:
    """``(rgba (ny, nx, 4) uint8, vmin, vmax)``: a ``(lat, lon)`` field coloured by ``cmap``
    with NaN cells transparent, rows north first (as an image overlay wants them)."""
    import matplotlib

    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise DataError(f"a map layer must be a (lat, lon) field, got shape {values.shape}")
    finite = np.isfinite(values)
    if not finite.any():
        raise DataError("a map layer has no finite value")
    lo = float(np.nanmin(values)) if vmin is None else float(vmin)
    hi = float(np.nanmax(values)) if vmax is None else float(vmax)
    scaled = (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values)
    rgba = matplotlib.colormaps[cmap](np.clip(np.nan_to_num(scaled), 0, 1), bytes=True)
    rgba[~finite, 3] = 0
    return rgba, lo, hi


def _unwrapped(lon: np.ndarray) -> np.ndarray:
    """Longitudes made continuous along a route (each leg the short way round)."""
    lon = np.asarray(lon, dtype=np.float64)
    if lon.size < 2:
        return lon
    steps = (np.diff(lon) + 180.0) % 360.0 - 180.0
    return np.concatenate([lon[:1], lon[0] + np.cumsum(steps)])


def explore_map(lat: np.ndarray, lon: np.ndarray,
                fields: Mapping[str, tuple[np.ndarray, str]] | None = None, *,
                routes: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                stops: Sequence[tuple[float, float, str]] = (),
                opacity: float = 0.75, tiles: str | None = "OpenStreetMap") -> Any:
    """A ``folium.Map`` of a ``(lat, lon)`` grid: one image layer per ``fields`` entry
    (``name -> (values (lat, lon), cmap)``; the first one shown, the others a click away), one
    polyline per route (``(lat, lon)`` arrays, its start starred), a circle per stop
    (``lat, lon, tooltip``), and a layer control. ``tiles=None`` draws no base map (offline)."""
    folium = _folium()
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if lat.ndim != 1 or lon.ndim != 1 or lat.size < 2 or lon.size < 2:
        raise DataError("explore_map needs the grid's 1-D lat and lon axes (2 values at least)")
    dlat, dlon = abs(lat[1] - lat[0]), abs(lon[1] - lon[0])
    south, north = lat.min() - dlat / 2, lat.max() + dlat / 2
    west, east = lon.min() - dlon / 2, lon.max() + dlon / 2
    fmap = folium.Map(location=[(south + north) / 2, (west + east) / 2], tiles=tiles,
                      control_scale=True)
    fmap.fit_bounds([[south, west], [north, east]])
    order = np.argsort(-lat)  # image rows north first
    for i, (name, (values, cmap)) in enumerate((fields or {}).items()):
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (lat.size, lon.size):
            raise DataError(f"layer {name!r} has shape {values.shape}, the grid is "
                            f"{(lat.size, lon.size)}")
        rgba, lo, hi = field_image(values[order][:, np.argsort(lon)], cmap)
        folium.raster_layers.ImageOverlay(
            rgba, bounds=[[south, west], [north, east]], opacity=opacity,
            name=f"{name} ({lo:.3g} .. {hi:.3g})", mercator_project=True, show=i == 0,
        ).add_to(fmap)
    for r, (rlat, rlon) in enumerate(routes):
        rlat = np.asarray(rlat, dtype=np.float64)
        rlon = _unwrapped(rlon)
        if rlat.size == 0:
            continue
        colour = _ROUTE_COLOURS[r % len(_ROUTE_COLOURS)]
        group = folium.FeatureGroup(name=f"route {r}" if len(routes) > 1 else "route")
        folium.PolyLine(np.column_stack([rlat, rlon]).tolist(), color=colour, weight=3,
                        opacity=0.9).add_to(group)
        folium.Marker([float(rlat[0]), float(rlon[0])], tooltip=f"start of route {r}",
                      icon=folium.Icon(color="orange", icon="star")).add_to(group)
        group.add_to(fmap)
    if len(stops):
        group = folium.FeatureGroup(name="samples")
        for la, lo_, tip in stops:
            folium.CircleMarker([float(la), float(lo_)], radius=3, color="black", weight=1,
                                fill=True, fill_opacity=0.9, tooltip=tip).add_to(group)
        group.add_to(fmap)
    folium.LayerControl(collapsed=False).add_to(fmap)
    return fmap
