"""Interactive maps in the field: a legend in the record's units, nothing loaded from the internet
without online tiles, and a base map from a local tile folder or MBTiles file."""

from __future__ import annotations

import base64
import json
import re
import sqlite3
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from lrm_cvx import interactive
from lrm_cvx.errors import DataError
from lrm_cvx.interactive import explore_map, record_label

pytest.importorskip("folium")

ROOT = Path(__file__).resolve().parents[1]
LAT = np.array([40.0, 41.0, 42.0, 43.0])
LON = np.array([10.0, 11.0, 12.0, 13.0, 14.0])
VALUES = np.add.outer(LAT, LON)


def _html(fmap, tmp_path) -> str:
    out = tmp_path / "map.html"
    fmap.save(str(out))
    return out.read_text(encoding="utf-8")


def _web_assets(html: str) -> list[str]:
    """Every script ``src`` and link ``href`` of the page that points at the web."""
    tags = re.findall(r"<(?:script|link)\b[^>]*>", html, flags=re.IGNORECASE)
    return [t for t in tags if re.search(r"""(?:src|href)\s*=\s*["']?\s*(?:https?:)?//""", t)]


def _inline_tiles(html: str) -> dict[str, str]:
    m = re.search(r"\._inlineTiles = (\{.*?\});", html)
    assert m, "no inline tile layer in the page"
    return json.loads(m[1])


def _legends(html: str) -> list[str]:
    """The HTML of each legend entry of the page."""
    return [json.loads(t) for t in re.findall(r'\[\w+, ("(?:[^"\\]|\\.)*")\],', html)]


def test_the_saved_map_loads_nothing_from_the_web_and_has_a_legend_in_units(tmp_path):
    fmap = explore_map(LAT, LON, {"posterior mean": (VALUES, "viridis", "K"),
                                  "std": (VALUES / 10, "magma", "K")},
                       routes=[(LAT, LON[:4])], stops=[(41.0, 12.0, "cell 7")], tiles=None,
                       quantity="sea surface temperature")
    html = _html(fmap, tmp_path)
    assert _web_assets(html) == []
    assert "L.tileLayer" not in html
    assert "L.Map.include" in html or "L.map" in html  # Leaflet itself is in the page
    mean, std = _legends(html)
    assert "sea surface temperature: posterior mean [K]" in mean
    assert "sea surface temperature: std [K]" in std
    assert "<span>50</span><span>53.5</span><span>57</span>" in mean  # lat + lon: 50 .. 57
    assert "linear-gradient" in mean


def test_folium_default_map_would_load_from_the_web(tmp_path):
    """The check above is not vacuous: folium's own page links its assets from CDNs."""
    import folium

    assert _web_assets(_html(folium.Map(tiles=None), tmp_path))


def test_a_legend_without_units_says_so(tmp_path):
    html = _html(explore_map(LAT, LON, {"background": (VALUES, "viridis")}, tiles=None),
                 tmp_path)
    assert "background (units not given)" in _legends(html)[0]


def test_record_label_reads_long_name_and_units():
    assert record_label({"long_name": "sea surface temperature", "units": "K"}, "sst") == (
        "sea surface temperature", "K")
    assert record_label({}, "sst") == ("sst", None)
    assert record_label({}) == (None, None)


@pytest.mark.parametrize("online", [True, False])
def test_auto_tiles_are_online_tiles_only_when_the_server_answers(tmp_path, monkeypatch, online):
    monkeypatch.setattr(interactive, "_online", lambda timeout=1.0: online)
    html = _html(explore_map(LAT, LON, {"v": (VALUES, "viridis", "K")}), tmp_path)
    assert ("tile.openstreetmap.org" in html) is online
    assert ("L.tileLayer" in html) is online
    assert _web_assets(html) == []


def _mbtiles(path: Path, zooms: range, fmt: str = "png") -> dict[tuple[int, int, int], bytes]:
    """An MBTiles file whose every tile's bytes name its XYZ address; returns those bytes."""
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE metadata (name text, value text)")
    con.execute("CREATE TABLE tiles (zoom_level integer, tile_column integer, tile_row integer, "
                "tile_data blob)")
    con.execute("INSERT INTO metadata VALUES ('format', ?)", (fmt,))
    tiles = {}
    for z in zooms:
        for x in range(2 ** z):
            for y in range(2 ** z):
                tiles[z, x, y] = f"tile {z}/{x}/{y}".encode()
                con.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)",
                            (z, x, 2 ** z - 1 - y, tiles[z, x, y]))  # TMS rows, south first
    con.commit()
    con.close()
    return tiles


def test_mbtiles_tiles_over_the_extent_are_written_into_the_page(tmp_path):
    source = tmp_path / "sea charts #1?.mbtiles"  # a name a file: URI must escape
    tiles = _mbtiles(source, range(0, 4))
    html = _html(explore_map(LAT, LON, {"v": (VALUES, "viridis", "K")}, tiles=source),
                 tmp_path)
    assert _web_assets(html) == []
    inline = _inline_tiles(html)
    # 40..43 N, 10..14 E lies in the north-east tile at zoom 1: XYZ row 0 (north first), which
    # MBTiles stores as TMS row 1
    assert "1/1/0" in inline and "1/0/0" not in inline and "1/1/1" not in inline
    for key, url in inline.items():
        z, x, y = map(int, key.split("/"))
        assert url == "data:image/png;base64," + base64.b64encode(tiles[z, x, y]).decode()
    assert {int(k.split("/")[0]) for k in inline} == {0, 1, 2, 3}
    assert '"maxNativeZoom": 3' in html


def test_a_tile_folder_is_written_into_the_page_within_the_tile_budget(tmp_path, monkeypatch):
    folder = tmp_path / "tiles"
    for z in range(0, 9):
        for x, y in zip(*(a.ravel() for a in np.meshgrid(
                *interactive._tile_range(z, 39.0, 8.0, 44.0, 16.0))), strict=True):
            f = folder / str(z) / str(x) / f"{y}.png"
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(f"tile {z}/{x}/{y}".encode())
    monkeypatch.setattr(interactive, "_MAX_TILES", 20)
    html = _html(explore_map(LAT, LON, {"v": (VALUES, "viridis", "K")}, tiles=str(folder)),
                 tmp_path)
    inline = _inline_tiles(html)
    assert 0 < len(inline) <= 20
    zooms = sorted({int(k.split("/")[0]) for k in inline})
    assert zooms == list(range(zooms[-1] + 1)) and zooms[-1] < 8  # coarsest first, bounded
    key = next(iter(inline))
    assert base64.b64decode(inline[key].split(",", 1)[1]) == f"tile {key}".encode()


def test_a_tile_source_across_the_antimeridian_wraps_its_columns():
    cols, rows = interactive._tile_range(2, 40.0, 170.0, 44.0, 190.0)
    assert cols.tolist() == [0, 3] and rows.tolist() == [1]


@pytest.mark.parametrize("make, match", [
    (lambda p: p / "nowhere.mbtiles", "no such folder"),
    (lambda p: (_mbtiles(p / "v.mbtiles", range(1), fmt="pbf"), p / "v.mbtiles")[1],
     "'pbf' tiles"),
    (lambda p: (p / "bad.mbtiles").write_text("not sqlite") and p / "bad.mbtiles",
     "not an MBTiles file"),
    (lambda p: (p / "far" / "3" / "0" / "0.png").parent.mkdir(parents=True) or
     (p / "far" / "3" / "0" / "0.png").write_bytes(b"x") and p / "far", "has no tile over"),
    (lambda p: (p / "fine" / "12" / "0").mkdir(parents=True) or p / "fine",
     r"coarsest zoom level of .* \(12\) needs \d+ tiles"),
])
def test_a_bad_tile_source_is_one_clear_line(tmp_path, make, match):
    source = make(tmp_path)
    with pytest.raises(DataError, match=match) as err:
        explore_map(LAT, LON, {"v": (VALUES, "viridis", "K")}, tiles=source)
    assert "\n" not in str(err.value) and "tiles=" in str(err.value)


def test_leaflet_is_package_data_with_its_licence():
    root = resources.files("lrm_cvx") / "data" / "leaflet"
    assert "BSD 2-Clause" in (root / "LICENSE").read_text(encoding="utf-8")
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    globs = globs["tool"]["setuptools"]["package-data"]["lrm_cvx"]
    pkg = ROOT / "src" / "lrm_cvx"
    shipped = {p for g in globs for p in pkg.glob(g)}
    for name in ("leaflet.js", "leaflet.css", "LICENSE", "images/layers.png"):
        assert pkg / "data" / "leaflet" / name in shipped
