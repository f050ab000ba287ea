"""Interactive maps for notebooks and the field: folium (Leaflet) layers of the belief, its
uncertainty and the routes, each field with a legend in its units.

Plain arrays in, a ``folium.Map`` out (:meth:`Plan.explore`, :meth:`MonitorState.explore`).
folium is an optional extra; the map works offline (docs/monitoring.md).
"""

from __future__ import annotations

import base64
import os
import socket
import sqlite3
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataError

__all__ = ["explore_map", "field_image", "record_label"]

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


_ONLINE_TILES = "OpenStreetMap"
_TILE_HOST = ("tile.openstreetmap.org", 443)
_MAX_TILES = 256  # tiles inlined from a local source, all zoom levels together
_BLANK_TILE = "data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7"
_TILE_MIME = {"png": "image/png", "jpg": "image/jpeg", "jpeg": "image/jpeg",
              "webp": "image/webp"}


def _online(timeout: float = 1.0) -> bool:
    """Whether the OpenStreetMap tile server accepts a connection within ``timeout`` s."""
    try:
        with socket.create_connection(_TILE_HOST, timeout=timeout):
            return True
    except OSError:
        return False


def _leaflet_assets() -> tuple[str, str]:
    """``(script, style)``: Leaflet's JS and CSS from the package, the CSS's images inlined
    as data URLs and the source-map comment dropped (nothing fetched when the page opens)."""
    root = resources.files("lrm_cvx") / "data" / "leaflet"
    js = (root / "leaflet.js").read_text(encoding="utf-8")
    js = "\n".join(line for line in js.splitlines()
                   if not line.startswith("//# sourceMappingURL"))
    css = (root / "leaflet.css").read_text(encoding="utf-8")
    for name in ("layers.png", "layers-2x.png"):
        data = base64.b64encode((root / "images" / name).read_bytes()).decode("ascii")
        css = css.replace(f"url(images/{name})", f"url(data:image/png;base64,{data})")
    return js, css


def _tile_range(z: int, south: float, west: float, north: float,
                east: float) -> tuple[np.ndarray, np.ndarray]:
    """The Web Mercator tile columns (wrapped to ``0 .. 2**z - 1``) and rows covering a box at
    zoom ``z``; ``west .. east`` may run past 180 (continuous longitudes)."""
    n = 2 ** z

    def row(lat: float) -> int:
        phi = np.radians(np.clip(lat, -85.0511, 85.0511))
        return int(np.clip((1 - np.log(np.tan(phi) + 1 / np.cos(phi)) / np.pi) / 2 * n,
                           0, n - 1))

    if east - west >= 360.0:
        cols = np.arange(n)
    else:
        c0 = int(np.floor((west + 180.0) / 360.0 * n))
        c1 = int(np.floor((east + 180.0) / 360.0 * n))
        cols = np.unique(np.arange(c0, c1 + 1) % n)
    return cols, np.arange(row(north), row(south) + 1)


def _local_tiles(source: Path, bounds: tuple[float, float, float, float],
                 label: str) -> dict[str, str]:
    """``{"z/x/y": data URL}`` of the tiles of a local source covering ``bounds`` (S, W, N,
    E), zoom levels from the coarsest up while the total stays within ``_MAX_TILES``.

    ``source`` is a folder of ``{z}/{x}/{y}.png`` (or ``.jpg``) files (XYZ rows, north first)
    or an MBTiles file (SQLite; its TMS rows, south first, are flipped here)."""
    mbtiles = source.is_file()
    if mbtiles:
        try:
            con = sqlite3.connect(source.resolve().as_uri() + "?mode=ro", uri=True)
            meta = dict(con.execute("SELECT name, value FROM metadata").fetchall())
            zooms = [int(r[0]) for r in con.execute(
                "SELECT DISTINCT zoom_level FROM tiles ORDER BY zoom_level")]
        except sqlite3.DatabaseError as exc:
            raise DataError(f"{label}: {source} is not an MBTiles file ({exc})") from None
        fmt = str(meta.get("format", "png")).lower()
        if fmt not in _TILE_MIME:
            con.close()
            raise DataError(f"{label}: {source} holds {fmt!r} tiles; a base map needs raster "
                            f"tiles ({', '.join(sorted(_TILE_MIME))})")
    else:
        zooms = sorted(int(d.name) for d in source.iterdir() if d.is_dir() and d.name.isdigit())
    out: dict[str, str] = {}
    looked = 0
    try:
        for z in zooms:
            cols, rows = _tile_range(z, *bounds)
            if looked + cols.size * rows.size > _MAX_TILES:
                if looked == 0:
                    raise DataError(f"{label}: the coarsest zoom level of {source} ({z}) needs "
                                    f"{cols.size * rows.size} tiles over the map's extent, more "
                                    f"than the {_MAX_TILES} a page holds; add coarser levels")
                break
            looked += cols.size * rows.size
            for x in cols.tolist():
                for y in rows.tolist():
                    if mbtiles:
                        hit = con.execute("SELECT tile_data FROM tiles WHERE zoom_level=? AND "
                                          "tile_column=? AND tile_row=?",
                                          (z, x, 2 ** z - 1 - y)).fetchone()
                        data, mime = (hit[0] if hit else None), _TILE_MIME[fmt]
                    else:
                        data = mime = None
                        for ext in ("png", "jpg", "jpeg"):
                            f = source / str(z) / str(x) / f"{y}.{ext}"
                            if f.is_file():
                                data, mime = f.read_bytes(), _TILE_MIME[ext]
                                break
                    if data:
                        out[f"{z}/{x}/{y}"] = (f"data:{mime};base64,"
                                               + base64.b64encode(data).decode("ascii"))
    finally:
        if mbtiles:
            con.close()
    if not out:
        raise DataError(f"{label}: {source} has no tile over the map's extent (S, W, N, E = "
                        f"{', '.join(f'{b:.4g}' for b in bounds)}; zoom levels {zooms})")
    return out


def _legend_html(name: str, units: str | None, cmap: str, lo: float, hi: float) -> str:
    """A legend box: ``name [units]``, the colour ramp and its ends."""
    import html

    import matplotlib

    ramp = matplotlib.colormaps[cmap](np.linspace(0.0, 1.0, 11))
    stops = ", ".join(matplotlib.colors.to_hex(c) for c in ramp)
    mid = (lo + hi) / 2
    title = html.escape(name) + (f" [{html.escape(units)}]" if units else " (units not given)")
    return (f'<div style="font-weight:bold;margin-bottom:2px">{title}</div>'
            f'<div style="height:12px;width:180px;background:linear-gradient(to right, {stops})'
            '"></div><div style="display:flex;justify-content:space-between;width:180px">'
            f"<span>{lo:.4g}</span><span>{mid:.4g}</span><span>{hi:.4g}</span></div>")


def _base_map(folium: Any, tiles: Any, bounds: tuple[float, float, float, float]) -> Any:
    """The ``tiles`` argument of ``folium.Map`` for :func:`explore_map`'s ``tiles``."""
    if isinstance(tiles, str) and tiles == "auto":
        return _ONLINE_TILES if _online() else None
    if tiles is None:
        return None
    local = isinstance(tiles, os.PathLike) or (
        isinstance(tiles, str) and "://" not in tiles
        and (tiles.lower().endswith(".mbtiles") or os.sep in tiles or Path(tiles).is_dir()))
    if not local:
        return tiles  # a folium / xyzservices provider name or a URL template
    from folium.template import Template

    source = Path(tiles).expanduser()
    label = f"tiles={str(tiles)!r}"
    if not source.exists():
        raise DataError(f"{label}: no such folder of {{z}}/{{x}}/{{y}}.png tiles or MBTiles "
                        "file")
    data = _local_tiles(source, bounds, label)
    zooms = sorted({int(k.split("/")[0]) for k in data})
    layer = folium.TileLayer("{z}/{x}/{y}", attr=f"local tiles: {source.name}",
                             name="local tiles", min_zoom=0, max_zoom=19,
                             max_native_zoom=zooms[-1], min_native_zoom=zooms[0])
    layer._template = Template(_INLINE_TILES_JS)
    layer.inline_tiles = data
    layer.blank_tile = _BLANK_TILE
    return layer


_INLINE_TILES_JS = """
{% macro script(this, kwargs) %}
    var {{ this.get_name() }} = L.tileLayer("", {{ this.options|tojavascript }});
    {{ this.get_name() }}._inlineTiles = {{ this.inline_tiles|tojson }};
    {{ this.get_name() }}.getTileUrl = function (c) {
        return this._inlineTiles[c.z + "/" + c.x + "/" + c.y] || {{ this.blank_tile|tojson }};
    };
{% endmacro %}
"""

_LEGEND_JS = """
{% macro script(this, kwargs) %}
    (function () {
        var map = {{ this._parent.get_name() }};
        var entries = [{% for layer, html in this.entries %}
            [{{ layer }}, {{ html|tojson }}],{% endfor %}
        ];
        var legend = L.control({position: "bottomright"});
        legend.onAdd = function () {
            var box = L.DomUtil.create("div", "lrm-cvx-legend");
            box.style.cssText = "background:rgba(255,255,255,0.85);padding:6px 8px;"
                + "font:12px/1.3 sans-serif;border-radius:4px";
            entries.forEach(function (e) {
                var item = L.DomUtil.create("div", "lrm-cvx-legend-item", box);
                item.innerHTML = e[1];
                e.push(item);
            });
            return box;
        };
        legend.addTo(map);
        function sync() {
            entries.forEach(function (e) {
                e[2].style.display = map.hasLayer(e[0]) ? "" : "none";
            });
        }
        map.on("overlayadd overlayremove layeradd layerremove", sync);
        sync();
    })();
{% endmacro %}
"""

_ASSETS_TEMPLATE = """
{% macro header(this, kwargs) %}
    <script>{{ this.script_text }}</script>
    <style>{{ this.style_text }}</style>
{% endmacro %}
"""


def _offline_assets(folium: Any, fmap: Any) -> None:
    """Leaflet written into the page's head and folium's web assets dropped from ``fmap``."""
    from branca.element import MacroElement
    from jinja2 import Template

    fmap.default_js = []
    fmap.default_css = []
    assets = MacroElement()
    assets._name = "LeafletAssets"
    assets._template = Template(_ASSETS_TEMPLATE)
    assets.script_text, assets.style_text = _leaflet_assets()
    fmap.add_child(assets, name="leaflet_assets")


def record_label(attrs: Mapping[str, Any], name: Any = None) -> tuple[str | None, str | None]:
    """``(quantity, units)`` of a record from its attributes: ``long_name`` (else ``name``) and
    ``units``, None where not given; what :func:`explore_map`'s legends show."""
    quantity = attrs.get("long_name") or name
    units = attrs.get("units")
    return (None if quantity is None else str(quantity)), (None if units is None else str(units))


def explore_map(lat: np.ndarray, lon: np.ndarray,
                fields: Mapping[str, tuple[Any, ...]] | None = None, *,
                routes: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                stops: Sequence[tuple[float, float, str]] = (),
                opacity: float = 0.75, tiles: Any = "auto",
                quantity: str | None = None) -> Any:
    """A ``folium.Map`` of a ``(lat, lon)`` grid, ready for a notebook or ``.save("map.html")``.

    Parameters
    ----------
    lat, lon : numpy.ndarray
        The grid's 1-D axes (degrees; longitudes may run past 180 across the antimeridian).
    fields : mapping, optional
        ``name -> (values (lat, lon), cmap[, units])``: one image layer each, the first one
        shown and the others a click away in the layer control; the shown layers' legends
        (``name [units]``, the colour ramp and its range) sit in the bottom-right corner.
    routes : sequence of (lat, lon) arrays
        One polyline per route, its start starred.
    stops : sequence of (lat, lon, tooltip)
        A circle per sampling stop.
    opacity : float
        Opacity of the field layers.
    quantity : str, optional
        What the fields measure (e.g. the record's ``long_name``), on top of every legend.
    tiles : str, path or None
        The base map. ``"auto"`` (default): OpenStreetMap tiles when the tile server answers
        within a second, else none (offline). ``None``: no base map. A folder of
        ``{z}/{x}/{y}.png`` tiles (XYZ scheme) or an ``.mbtiles`` file: its tiles over the
        map's extent are written into the page (zoom levels from the coarsest up, 256 tiles
        at most; deeper zooms enlarge the finest level), so the map needs no network. Any
        other string: a folium tile provider name or a ``https://.../{z}/{x}/{y}.png`` URL
        template (online).

    Returns
    -------
    folium.Map
        Leaflet's script and style sheet are part of the page; with a local or no base map
        the saved HTML loads nothing from the internet.
    """
    folium = _folium()
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if lat.ndim != 1 or lon.ndim != 1 or lat.size < 2 or lon.size < 2:
        raise DataError("explore_map needs the grid's 1-D lat and lon axes (2 values at least)")
    dlat, dlon = abs(lat[1] - lat[0]), abs(lon[1] - lon[0])
    south, north = lat.min() - dlat / 2, lat.max() + dlat / 2
    west, east = lon.min() - dlon / 2, lon.max() + dlon / 2
    pad_lat, pad_lon = (north - south) / 4, (east - west) / 4  # room to pan on local tiles
    base = _base_map(folium, tiles, (max(south - pad_lat, -85.0), west - pad_lon,
                                     min(north + pad_lat, 85.0), east + pad_lon))
    fmap = folium.Map(location=[(south + north) / 2, (west + east) / 2], tiles=base,
                      control_scale=True)
    _offline_assets(folium, fmap)
    fmap.fit_bounds([[south, west], [north, east]])
    order = np.argsort(-lat)  # image rows north first
    legends = []
    for i, (name, spec) in enumerate((fields or {}).items()):
        values, cmap = spec[0], spec[1]
        units = spec[2] if len(spec) > 2 else None
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (lat.size, lon.size):
            raise DataError(f"layer {name!r} has shape {values.shape}, the grid is "
                            f"{(lat.size, lon.size)}")
        rgba, lo, hi = field_image(values[order][:, np.argsort(lon)], cmap)
        layer = folium.raster_layers.ImageOverlay(
            rgba, bounds=[[south, west], [north, east]], opacity=opacity,
            name=f"{name} ({lo:.3g} .. {hi:.3g}{' ' + units if units else ''})",
            mercator_project=True, show=i == 0,
        ).add_to(fmap)
        title = name if quantity is None else f"{quantity}: {name}"
        legends.append((layer, _legend_html(title, units, cmap, lo, hi)))
    for r, (rlat, rlon) in enumerate(routes):
        rlat = np.asarray(rlat, dtype=np.float64)
        rlon = _unwrapped(rlon)
        if rlat.size == 0:
            continue
        colour = _ROUTE_COLOURS[r % len(_ROUTE_COLOURS)]
        group = folium.FeatureGroup(name=f"route {r}" if len(routes) > 1 else "route")
        folium.PolyLine(np.column_stack([rlat, rlon]).tolist(), color=colour, weight=3,
                        opacity=0.9).add_to(group)
        star = folium.DivIcon(html=f'<div style="font-size:22px;line-height:22px;color:{colour};'
                              'text-shadow:0 0 2px #000">&#9733;</div>',
                              icon_size=(22, 22), icon_anchor=(11, 11))
        folium.Marker([float(rlat[0]), float(rlon[0])], tooltip=f"start of route {r}",
                      icon=star).add_to(group)
        group.add_to(fmap)
    if len(stops):
        group = folium.FeatureGroup(name="samples")
        for la, lo_, tip in stops:
            folium.CircleMarker([float(la), float(lo_)], radius=3, color="black", weight=1,
                                fill=True, fill_opacity=0.9, tooltip=tip).add_to(group)
        group.add_to(fmap)
    folium.LayerControl(collapsed=False).add_to(fmap)
    if legends:
        from branca.element import MacroElement
        from jinja2 import Template

        legend = MacroElement()
        legend._name = "Legend"
        legend._template = Template(_LEGEND_JS)
        legend.entries = [(layer.get_name(), text) for layer, text in legends]
        fmap.add_child(legend, name="legend")
    return fmap
