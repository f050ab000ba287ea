"""Figures: labelled axes with units, colour bars with units, routes and masked cells drawn."""

from __future__ import annotations

import re

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
import xarray as xr  # noqa: E402

from lrm_cvx.errors import DataError  # noqa: E402
from lrm_cvx.plots import plot_demo_metrics, plot_map, plot_prediction_panels  # noqa: E402


@pytest.fixture
def field() -> xr.DataArray:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(4, 6)).astype(np.float32)
    v[0, :2] = np.nan  # "land"
    return xr.DataArray(
        v, dims=("lat", "lon"),
        coords={"lat": ("lat", [10.0, 15, 20, 25], {"units": "degrees_north"}),
                "lon": ("lon", [200.0, 205, 210, 215, 220, 225], {"units": "degrees_east"}),
                "time": np.datetime64("2005-01-15")},
        attrs={"units": "K", "long_name": "sea surface temperature anomaly"})


def _colorbar_labels(fig) -> list[str]:
    return [ax.get_xlabel() or ax.get_ylabel() for ax in fig.axes
            if ax.get_label() == "<colorbar>"]


def test_plot_map_labels_units_colorbar_route_and_mask(field):
    route = xr.Dataset({"lat": ("step", [10.0, 15.0]), "lon": ("step", [210.0, 215.0])})
    ax = plot_map(field, route=route)
    assert ax.get_xlabel() == "longitude (\N{DEGREE SIGN}E)"
    assert ax.get_ylabel() == "latitude (\N{DEGREE SIGN}N)"
    assert _colorbar_labels(ax.figure) == ["sea surface temperature anomaly (K)"]
    # the route is drawn at its coordinates; masked cells show the grey face colour
    xs = [tuple(line.get_xdata()) for line in ax.lines]
    assert (210.0, 215.0) in xs
    assert ax.get_facecolor()[:3] == pytest.approx(matplotlib.colors.to_rgb("0.82"))
    plt.close("all")


def test_plot_map_refuses_non_2d(field):
    with pytest.raises(DataError, match="field"):
        plot_map(field.expand_dims(t=2))
    with pytest.raises(DataError, match="field"):
        plot_map(field.values)


def test_prediction_panels_truth_prediction_std_side_by_side(field):
    rows = [{"label": f"setting {i}", "prediction": field * 0.5, "std": abs(field) * 0 + 0.1 * i,
             "route": xr.Dataset({"lat": ("step", [10.0, 20.0]), "lon": ("step", [200.0, 210.0])})}
            for i in (1, 2)]
    fig = plot_prediction_panels(field, rows)
    maps = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert len(maps) == 6
    titles = [ax.get_title() for ax in maps]
    assert titles[:3] == ["truth (held-out snapshot)", "prediction\nsetting 1",
                          "standard deviation"]
    assert all(ax.get_xlabel() == "longitude (\N{DEGREE SIGN}E)" for ax in maps[3:])
    assert maps[0].get_ylabel() == "latitude (\N{DEGREE SIGN}N)"
    assert all(len(ax.lines) >= 2 for ax in maps)  # the route over every panel
    labels = _colorbar_labels(fig)
    assert labels == ["sea surface temperature anomaly (K)", "predictive std (K)"]
    # truth and prediction share one colour scale, symmetric about zero for anomalies
    clims = {ax.collections[0].get_clim() for ax in maps if ax.get_title() != "standard deviation"}
    assert len(clims) == 1
    lo, hi = clims.pop()
    assert lo == pytest.approx(-hi)
    plt.close("all")


def test_prediction_panels_needs_rows(field):
    with pytest.raises(DataError, match="rows"):
        plot_prediction_panels(field, [])


def test_demo_metrics_axes_and_legend_order():
    table = pd.DataFrame({"setting": ["rec"] * 2 + ["paper"] * 2, "budget": [10.0, 20] * 2,
                          "mse_mean": [0.1, 0.05, 0.3, 0.2], "mse_se": [0.01] * 4})
    fig = plot_demo_metrics(table, units="K")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "budget (grid cells)"
    assert ax.get_ylabel() == "reconstruction MSE (K\N{SUPERSCRIPT TWO})"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["rec", "paper"]
    assert ax.get_yscale() == "log"
    plt.close("all")


def test_route_lines_break_between_robots():
    """A fleet's routes are separate lines: a NaN row where the robot changes, padding dropped."""
    from lrm_cvx.plots import _route_lines
    from lrm_cvx.region import Region

    da = xr.DataArray(np.zeros((3, 4)), dims=("lat", "lon"),
                      coords={"lat": [0.0, 1.0, 2.0], "lon": [10.0, 11.0, 12.0, 13.0]})
    region = Region.from_dataarray(da)
    cells = [0, 1, 2, 5, 6, -1]
    route = _route_lines(region, cells, [0, 0, 0, 1, 1, -1])
    lon = route["lon"].values
    assert np.isnan(lon[3]) and lon.size == 6
    np.testing.assert_array_equal(lon[[0, 1, 2, 4, 5]], region.cell_lon[[0, 1, 2, 5, 6]])
    single = _route_lines(region, cells, None)
    np.testing.assert_array_equal(single["lon"].values, region.cell_lon[[0, 1, 2, 5, 6]])


# --------------------------------------------- maps people read
def _tick_labels_overlap(ax) -> bool:
    fig = ax.figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for axis in (ax.xaxis, ax.yaxis):
        boxes = [t.get_window_extent(renderer) for t in axis.get_ticklabels()
                 if t.get_visible() and t.get_text()]
        for a, b in zip(boxes[:-1], boxes[1:], strict=True):
            if a.overlaps(b):
                return True
    return False


@pytest.mark.parametrize("shape, stacked", [((5, 100), True), ((30, 40), False),
                                            ((60, 12), False)])
def test_map_layout_follows_the_domain(shape, stacked):
    import matplotlib.pyplot as plt

    from lrm_cvx.plots import map_layout, plot_map

    lat = np.linspace(-10, 10, shape[0])
    lon = np.linspace(100, 100 + 20 * shape[1] / shape[0] * 1.0, shape[1])
    nrows, ncols, size = map_layout(lat, lon, 2)
    assert (nrows, ncols) == ((2, 1) if stacked else (1, 2))
    field = xr.DataArray(np.random.default_rng(0).normal(size=shape), dims=("lat", "lon"),
                         coords={"lat": lat, "lon": lon}, attrs={"units": "K"})
    fig, axes = plt.subplots(nrows, ncols, figsize=size, constrained_layout=True,
                             squeeze=False)
    for ax in axes.ravel():
        plot_map(field, ax=ax)
    for ax in axes.ravel():
        assert not _tick_labels_overlap(ax)
        box = ax.get_position()
        w, h = box.width * size[0], box.height * size[1]
        assert max(w, h) > 1.5 and min(w, h) > 0.5  # never a squashed strip
    plt.close(fig)


def test_plan_and_state_explore_layers(tmp_path):
    pytest.importorskip("folium")
    import warnings

    from lrm_cvx.glrm import GLRM
    from lrm_cvx.io.samples import synthetic_dynamic_field
    from lrm_cvx.monitor import MonitorState
    from lrm_cvx.planning import plan_greedy

    da = synthetic_dynamic_field(24, (6, 7), 3, seed=4, noise=0.03)
    da.attrs.update(long_name="sea surface temperature", units="K")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(3, progress=False, temporal="ar1", spatial="exponential",
                     offset=True).fit(da.isel(time=slice(0, 20)))
    region = model.region_
    plan = plan_greedy(model.Y_, region, (region.cell_lat[5], region.cell_lon[5]), 6,
                       progress=False)
    html = plan.explore(tiles=None).get_root().render()
    assert html.count("L.polyline") == 1 and html.count("L.circleMarker") == len(plan.stops)
    std = xr.DataArray(np.ones((6, 7)), dims=("lat", "lon"), name="prior std",
                       attrs={"units": "mK"})
    html = plan.explore(std, tiles=None).get_root().render()
    assert "sea surface temperature: prior std [mK]" in html
    assert not re.search(r"<(?:script|link)[^>]*(?:src|href)=\S*https?:", html)
    state = MonitorState.from_model(model)
    snap = model.region_.stack(da.isel(time=20))
    state.assimilate((plan.stops, snap[plan.stops]), da.time.values[20])
    fmap = state.explore(plan, tiles=None)
    html = fmap.get_root().render()
    assert html.count("L.imageOverlay") == 3  # mean, std, predictive std
    assert "posterior mean" in html and "predictive std" in html
    assert "sea surface temperature: predictive std [K]" in html
    n_seen = int(np.isfinite(snap[plan.stops]).sum())  # NaN values are not assimilated
    assert html.count("L.circleMarker") == n_seen == state.posterior.cells.size
    assert "L.control.layers" in html


def test_a_nearly_constant_map_has_a_plain_colour_bar():
    """A colour bar of a nearly constant field (a predictive std right after monitor init)
    reads plain numbers, not an offset label such as '1e-9+2.698e-1'."""
    import matplotlib

    matplotlib.use("Agg")
    from lrm_cvx.plots import plot_map

    values = 0.2698 + 1e-9 * np.random.default_rng(0).random((5, 6))
    field = xr.DataArray(values, dims=("lat", "lon"), name="std",
                         coords={"lat": np.arange(5.0), "lon": np.arange(6.0)})
    ax = plot_map(field, coast=None)
    ax.figure.canvas.draw()
    cbar_ax = ax.figure.axes[-1]
    assert cbar_ax is not ax
    assert cbar_ax.yaxis.get_offset_text().get_text() == ""
    assert cbar_ax.xaxis.get_offset_text().get_text() == ""
