"""Coastlines on the static maps: the outline as before without cartopy, real coastlines from
an offline shapefile at the right coordinates in either longitude convention, a clear error
for ``coast="cartopy"`` without one, and the line cutting checked against a per-vertex loop."""

from __future__ import annotations

import sys
import warnings

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import xarray as xr  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from lrm_cvx import coastlines  # noqa: E402
from lrm_cvx.coastlines import COAST_ENV, check_coast, draw_coast, lines_in_extent  # noqa: E402
from lrm_cvx.errors import DataError  # noqa: E402
from lrm_cvx.plots import plot_map  # noqa: E402


@pytest.fixture(autouse=True)
def _no_user_coastlines(monkeypatch):
    monkeypatch.delenv(COAST_ENV, raising=False)
    yield
    plt.close("all")


@pytest.fixture
def no_cartopy(monkeypatch):
    """cartopy unavailable: ``import cartopy`` raises ImportError."""
    for name in [m for m in sys.modules if m == "cartopy" or m.startswith("cartopy.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "cartopy", None)
    monkeypatch.setitem(sys.modules, "cartopy.io", None)


def _field(lon, lat=(0.0, 5.0, 10.0, 15.0, 20.0)) -> xr.DataArray:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(len(lat), len(lon)))
    v[:2, :2] = np.nan  # "land" in a corner
    return xr.DataArray(v, dims=("lat", "lon"), coords={"lat": list(lat), "lon": list(lon)})


def _coast_lines(ax):
    return [ln for ln in ax.lines if ln.get_label() == "_coastlines"]


def _contour_vertices(ax):
    paths = [p for c in ax.collections if isinstance(c, matplotlib.contour.ContourSet)
             for p in c.get_paths()]
    return [np.asarray(p.vertices) for p in paths]


# ------------------------------------------------------------------ without cartopy
@pytest.mark.parametrize("coast", ["auto", "outline", True])
def test_without_cartopy_the_outline_is_drawn_as_before(no_cartopy, coast):
    field = _field([160.0, 170, 180, 190, 200])
    ax = plot_map(field, coast=coast)
    assert not _coast_lines(ax)
    # the reference: the contour plot_map drew before coastlines existed
    _, ref = plt.subplots()
    ref.contour(field.lon.values, field.lat.values, np.isfinite(field.values).astype(float),
                levels=[0.5], colors="0.25", linewidths=0.6)
    got, want = _contour_vertices(ax), _contour_vertices(ref)
    assert len(got) == len(want) >= 1
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("coast", [None, False])
def test_no_coast_draws_nothing(no_cartopy, coast):
    ax = plot_map(_field([160.0, 170, 180, 190, 200]), coast=coast)
    assert not _contour_vertices(ax) and not _coast_lines(ax)


def test_coast_cartopy_without_cartopy_is_a_one_line_error(no_cartopy):
    with pytest.raises(DataError, match=r"lrm-cvx\[maps\]") as err:
        plot_map(_field([160.0, 170, 180, 190, 200]), coast="cartopy")
    assert "\n" not in str(err.value) and COAST_ENV in str(err.value)


def test_bad_coast_names_the_choices():
    with pytest.raises(DataError, match="coast must be one of"):
        plot_map(_field([160.0, 170, 180, 190, 200]), coast="gshhs")
    assert check_coast(True) == "auto" and check_coast(False) is None


def test_a_missing_user_shapefile_is_named(monkeypatch, tmp_path):
    monkeypatch.setenv(COAST_ENV, str(tmp_path / "nope.shp"))
    with pytest.raises(DataError, match=f"{COAST_ENV}=.*nope.shp: no such shapefile"):
        plot_map(_field([160.0, 170, 180, 190, 200]))


def test_plan_plot_outlines_the_region_without_cartopy(no_cartopy):
    from lrm_cvx import Region
    from lrm_cvx.planning import plan_greedy

    rng = np.random.default_rng(0)
    mask = np.ones((6, 7), dtype=bool)
    mask[0, :3] = False
    lat, lon = np.linspace(10, 0, 6), np.linspace(30, 42, 7)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
    plan = plan_greedy(rng.standard_normal((3, region.n_cells)), region,
                       int(region.cell_grid[3, 3]), 5, progress=False)
    ax = plan.plot()
    _, ref = plt.subplots()
    ref.contour(lon, lat, mask.astype(float), levels=[0.5], colors="0.25", linewidths=0.6)
    got, want = _contour_vertices(ax), _contour_vertices(ref)
    assert len(got) == len(want) >= 1 and not _coast_lines(ax)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert not _contour_vertices(plan.plot(coast=None))


# ------------------------------------------------------------------ cutting lines
def test_lines_follow_the_grids_longitude_convention():
    # file convention -180..180: a line across the antimeridian and one across Greenwich
    pts = np.array([[170.0, 10.0], [-170.0, 10.0], [-10.0, 0.0], [10.0, 0.0]])
    starts = np.array([0, 2])
    x, y = lines_in_extent(pts, starts, (160.0, 200.0, 0.0, 20.0))  # a 0..360 grid
    np.testing.assert_allclose(x, [170.0, 190.0])
    np.testing.assert_allclose(y, [10.0, 10.0])
    x, y = lines_in_extent(pts, starts, (-20.0, 20.0, -5.0, 5.0))
    np.testing.assert_allclose(x, [-10.0, 10.0])
    # a global 0..360 grid: Greenwich's line at both edges, the other at 170..190
    x, y = lines_in_extent(pts, starts, (0.0, 360.0, -5.0, 15.0))
    runs = [tuple(r) for r in np.split(x, np.flatnonzero(np.isnan(x))) if r.size]
    runs = [tuple(v for v in r if not np.isnan(v)) for r in runs]
    assert sorted(runs) == [(-10.0, 10.0), (170.0, 190.0), (350.0, 370.0)]


def _reference(points, starts, extent):
    """Per line, per copy, per vertex: the runs of vertices inside or next to one inside."""
    west, east, south, north = extent
    bounds = [*starts, len(points)]
    runs = []
    for k in range(-4, 5):
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            lon = [points[a, 0]]
            for i in range(a + 1, b):
                d = points[i, 0] - points[i - 1, 0]
                while d >= 180:
                    d -= 360
                while d < -180:
                    d += 360
                lon.append(lon[-1] + d)
            xs = [v + 360 * k for v in lon]
            ys = list(points[a:b, 1])
            inside = [west <= x <= east and south <= y <= north
                      for x, y in zip(xs, ys, strict=True)]
            n = len(xs)
            run = []
            for i in range(n):
                if inside[i] or (i > 0 and inside[i - 1]) or (i < n - 1 and inside[i + 1]):
                    run.append((xs[i], ys[i]))
                elif run:
                    runs.append(run)
                    run = []
            if run:
                runs.append(run)
    return runs


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_cut_lines_match_a_per_vertex_loop(seed):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 9, size=rng.integers(1, 5))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    lon = np.concatenate([(rng.uniform(-180, 180) + np.cumsum(rng.uniform(-40, 40, s))
                           + 180) % 360 - 180 for s in sizes])
    lat = rng.uniform(-60, 60, sizes.sum())
    pts = np.column_stack([lon, lat])
    west = rng.uniform(-200, 300)
    south = rng.uniform(-70, 40)
    extent = (west, west + rng.uniform(5, 300), south, south + rng.uniform(5, 80))
    x, y = lines_in_extent(pts, starts, extent)
    cut = np.flatnonzero(np.isnan(x))
    got = [list(zip(a, b, strict=True))
           for a, b in zip(np.split(x, cut), np.split(y, cut), strict=True)]
    got = [[(u, v) for u, v in r if not np.isnan(u)] for r in got]
    got = [r for r in got if r]
    want = _reference(pts, starts, extent)
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.array(g), np.array(w), atol=1e-9)


def test_not_degrees_falls_back_or_refuses(no_cartopy, monkeypatch):
    # a grid in metres: "auto" draws the outline, "cartopy" says why it cannot
    field = _field([1e5, 2e5, 3e5, 4e5, 5e5], lat=(1e5, 2e5, 3e5, 4e5, 5e5))
    ax = plot_map(field, coast="auto")
    assert _contour_vertices(ax)
    _, ax = plt.subplots()
    with pytest.raises(DataError, match="not in degrees"):
        draw_coast(ax, field.lat.values, field.lon.values, "cartopy")


# ------------------------------------------------------------------ real shapefiles
def _write_shapefile(path, shape_type, lines):
    shapefile = pytest.importorskip("shapefile")
    with shapefile.Writer(str(path), shapeType=shape_type) as w:
        w.field("name", "C")
        for i, line in enumerate(lines):
            if shape_type == shapefile.POLYGON:
                w.poly([line])
            else:
                w.line([line])
            w.record(f"line {i}")
    return path.with_suffix(".shp")


@pytest.mark.parametrize("kind", ["POLYLINE", "POLYGON"])
def test_user_shapefile_lines_land_at_their_coordinates(monkeypatch, tmp_path, kind):
    shapefile = pytest.importorskip("shapefile")
    lines = [[[170.0, 10.0], [-170.0, 10.0]],   # across the antimeridian
             [[-10.0, 0.0], [10.0, 0.0]],       # across Greenwich
             [[0.0, 80.0], [5.0, 85.0]]]        # far north: not read for these maps
    if kind == "POLYGON":
        lines = [[[170.0, 10.0], [-170.0, 10.0], [-170.0, 12.0], [170.0, 10.0]]]
    shp = _write_shapefile(tmp_path / "coast", getattr(shapefile, kind), lines)
    monkeypatch.setenv(COAST_ENV, str(shp))
    # a 0..360 grid across the antimeridian
    ax = plot_map(_field([160.0, 170, 180, 190, 200]), coast="cartopy")
    (line,) = _coast_lines(ax)
    if kind == "POLYLINE":
        np.testing.assert_allclose(line.get_xdata(), [170.0, 190.0])
        np.testing.assert_allclose(line.get_ydata(), [10.0, 10.0])
    else:
        np.testing.assert_allclose(line.get_xdata(), [170.0, 190.0, 190.0, 170.0])
        np.testing.assert_allclose(line.get_ydata(), [10.0, 10.0, 12.0, 10.0])
    assert not _contour_vertices(ax)  # real coastlines replace the outline
    assert ax.get_xlim() == (155.0, 205.0)  # the axes keep the grid's limits
    if kind == "POLYLINE":  # a -180..180 grid around Greenwich
        ax = plot_map(_field([-20.0, -10, 0, 10, 20], lat=(-5.0, 0, 5)), coast="auto")
        (line,) = _coast_lines(ax)
        np.testing.assert_allclose(line.get_xdata(), [-10.0, 10.0])


def test_cartopy_data_dirs_are_found_never_downloaded(monkeypatch, tmp_path):
    cartopy = pytest.importorskip("cartopy")
    shapefile = pytest.importorskip("shapefile")
    from cartopy.io import Downloader

    def no_download(*args, **kwargs):
        raise AssertionError("a download was attempted")

    monkeypatch.setattr(Downloader, "acquire_resource", no_download)
    monkeypatch.setattr(coastlines, "DEBIAN_DATA_DIR", str(tmp_path / "debian"))
    monkeypatch.setitem(cartopy.config, "pre_existing_data_dir", tmp_path / "pre")
    monkeypatch.setitem(cartopy.config, "data_dir", tmp_path / "data")
    monkeypatch.setitem(cartopy.config, "repo_data_dir", tmp_path / "repo")
    assert coastlines.coastline_file(30.0) is None
    with pytest.raises(DataError, match="no coastline shapefile found offline"):
        plot_map(_field([160.0, 170, 180, 190, 200]), coast="cartopy")
    assert not _coast_lines(plot_map(_field([160.0, 170, 180, 190, 200])))  # auto: outline
    folder = tmp_path / "pre" / "shapefiles" / "natural_earth" / "physical"
    folder.mkdir(parents=True)
    shp = _write_shapefile(folder / "ne_110m_coastline", shapefile.POLYLINE,
                           [[[170.0, 10.0], [-170.0, 10.0]]])
    assert coastlines.coastline_file(30.0) == shp  # 50m wanted, 110m at hand
    (line,) = _coast_lines(plot_map(_field([160.0, 170, 180, 190, 200])))
    np.testing.assert_allclose(line.get_xdata(), [170.0, 190.0])


# ------------------------------------------------------------------ the CLI
def test_monitor_map_coast_option(no_cartopy, tmp_path, capsys):
    from lrm_cvx.cli import main
    from lrm_cvx.glrm import GLRM
    from lrm_cvx.io.samples import synthetic_dynamic_field

    da = synthetic_dynamic_field(12, (5, 6), 2, seed=4, noise=0.03)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        GLRM(2, progress=False, max_iter=10, temporal="ar1").fit(da).save(tmp_path / "m.nc")
    state = tmp_path / "state.nc"
    assert main(["-q", "monitor", "init", str(tmp_path / "m.nc"), "--state", str(state)]) == 0
    capsys.readouterr()
    out = tmp_path / "map.png"
    assert main(["-q", "monitor", "map", str(state), "-o", str(out), "--coast", "cartopy"]) == 2
    err = capsys.readouterr().err.strip()
    assert "coast='cartopy'" in err and "lrm-cvx[maps]" in err and "\n" not in err
    assert not out.exists()
    for coast in ("auto", "outline", "none"):
        assert main(["-q", "monitor", "map", str(state), "-o", str(out), "--coast", coast,
                     "--overwrite"]) == 0
        assert out.stat().st_size > 1000
