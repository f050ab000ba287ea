"""The paper's figures: metrics vs budget (Fig. 3) and predictions with error maps (Figs. 4-5).

Figures are sized for a two-column paper (single column 3.5 in, full width 7.2 in), use
colour-blind-safe colours and distinct markers so they read in grey-scale print too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import xarray as xr

from ._validation import atomic_output
from .coastlines import check_coast, draw_coast
from .errors import DataError

__all__ = ["plot_metrics", "plot_temporal_metrics", "plot_predictions", "plot_map",
           "plot_prediction_panels", "plot_backtest",
           "plot_demo_metrics", "save_figure", "METHOD_STYLE"]

# Okabe-Ito colours, one marker each: distinguishable in colour and in grey-scale print.
METHOD_STYLE: dict[str, dict[str, Any]] = {
    "greedy": {"color": "#D55E00", "marker": "o", "label": "greedy (ours)"},
    "transect-up": {"color": "#0072B2", "marker": "^", "label": "transect up"},
    "transect-down": {"color": "#56B4E9", "marker": "v", "label": "transect down"},
    "transect-left": {"color": "#009E73", "marker": "<", "label": "transect left"},
    "transect-right": {"color": "#CC79A7", "marker": ">", "label": "transect right"},
    "random": {"color": "#000000", "marker": "s", "label": "random walk"},
}
_PRINT_RC = {"font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "legend.fontsize": 7,
             "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.2,
             "lines.markersize": 3.5, "savefig.dpi": 300}


def _style(method: str, i: int) -> dict[str, Any]:
    if method in METHOD_STYLE:
        return METHOD_STYLE[method]
    cmap = matplotlib.colormaps["tab10"]
    return {"color": cmap(i % 10), "marker": "osD^v<>"[i % 7], "label": method}


def _panels(axes: Sequence[Any] | None, n: int, figsize: tuple[float, float],
            **layout: Any) -> tuple[Any, Any]:
    """``(figure, axes)``: the caller's ``axes`` and their figure, or ``n`` new side-by-side."""
    import matplotlib.pyplot as plt

    if axes is None:
        return plt.subplots(1, n, figsize=figsize, **layout)
    return axes[0].figure, axes


def _mse_label(results: xr.Dataset, label: str) -> str:
    """``label`` with the units of ``results["mse"]`` when it has them."""
    units = results["mse"].attrs.get("units")
    return f"{label} ({units})" if units else label


def plot_metrics(results: xr.Dataset, *, axes: Sequence[Any] | None = None,
                 title: str | None = None, log_mse: bool = True):
    """Fisher information and reconstruction MSE vs budget, mean +- standard error per method.

    ``results`` is the Dataset of :func:`lrm_cvx.evaluation.evaluate`. The MSE panel also draws
    the "complete" condition (fold-in from every observed cell), on a log scale by default
    because small budgets give errors orders of magnitude above the floor. Returns the figure.
    """
    import matplotlib.pyplot as plt

    from .evaluation import summary

    df = summary(results)
    with plt.rc_context(_PRINT_RC):
        fig, axes = _panels(axes, 2, (7.2, 2.6), constrained_layout=True)
        for i, (method, rows) in enumerate(df.groupby("method", sort=False)):
            st = _style(method, i)
            for ax, metric in zip(axes, ("information", "mse"), strict=True):
                x = rows["budget"].to_numpy()
                y = rows[f"{metric}_mean"].to_numpy()
                se = np.nan_to_num(rows[f"{metric}_se"].to_numpy())
                ax.plot(x, y, marker=st["marker"], color=st["color"], label=st["label"])
                ax.fill_between(x, y - se, y + se, color=st["color"], alpha=0.18, lw=0)
            if "mse_memoryless_mean" in rows:  # evaluate(temporal=...): memoryless dashed
                axes[1].plot(rows["budget"].to_numpy(), rows["mse_memoryless_mean"].to_numpy(),
                             marker=st["marker"], color=st["color"], ls="--", mfc="none",
                             label=f"{st['label']} (memoryless)")
        complete = float(results["complete_mse"].mean())
        axes[1].axhline(complete, color="0.4", ls="--", lw=1, label="complete")
        axes[0].set_ylabel("Fisher information (nats)")
        axes[1].set_ylabel(_mse_label(results, "reconstruction MSE"))
        for ax in axes:
            ax.set_xlabel("budget (grid cells)")
            ax.grid(alpha=0.3, lw=0.5)
        if log_mse:
            axes[1].set_yscale("log")
        axes[0].set_title("(a) information, higher is better")
        axes[1].set_title("(b) reconstruction error, lower is better")
        axes[1].legend(frameon=False, ncol=1, loc="upper right")
        if title:
            fig.suptitle(title)
    return fig


def plot_backtest(results: xr.Dataset, *, budget: float | None = None,
                  axes: Sequence[Any] | None = None, title: str | None = None):
    """A rolling-origin backtest (``evaluation.backtest``) block by block: (a) the
    reconstruction MSE, (b) and (c) the mean coverage of the 68 % and 95 % intervals, one line
    per method, with the bands of :data:`~lrm_cvx.evaluation.COVERAGE_BANDS` shaded and the
    nominal level dashed. ``budget``: the budget shown (default the middle one of ``results``;
    a budget not in ``results`` is a DataError). Returns the figure."""
    import matplotlib.pyplot as plt

    from .evaluation import COVERAGE_BANDS, summary

    if "origin" not in results.dims:
        raise DataError("plot_backtest needs a rolling-origin result (backtest(data, origins): "
                        "a Dataset with an 'origin' dim)")
    budgets = [float(b) for b in results["budget"].values]
    budget = budgets[len(budgets) // 2] if budget is None else float(budget)
    if budget not in budgets:
        raise DataError(f"budget must be one of the results' budgets {budgets}, got {budget:g}")
    df = summary(results, by_origin=True)
    df = df[df["budget"] == budget]
    times = results["origin_time"].values  # datetime64, or cftime objects (other calendars)
    labels = (list(np.datetime_as_string(times, unit="D")) if times.dtype.kind == "M"
              else [str(t) for t in times])
    with plt.rc_context(_PRINT_RC):
        fig, axes = _panels(axes, 3, (7.2, 2.9), layout="constrained")
        x = np.arange(len(labels))
        for i, (method, rows) in enumerate(df.groupby("method", sort=False)):
            st = _style(method, i)
            rows = rows.sort_values("origin")
            for ax, col in zip(axes, ("mse_mean", "coverage68_mean", "coverage95_mean"),
                               strict=True):
                ax.plot(rows["origin"].to_numpy(), rows[col].to_numpy(), marker=st["marker"],
                        color=st["color"], label=st["label"])
        for ax, level in zip(axes[1:], (68, 95), strict=True):
            lo, hi = COVERAGE_BANDS[level]
            ax.axhspan(lo, hi, color="0.85", lw=0, zorder=0)
            ax.axhline(level / 100, color="0.4", ls="--", lw=1)
            ax.set_ylabel(f"{level} % interval coverage")
        axes[0].set_ylabel(_mse_label(results, "reconstruction MSE"))
        for ax in axes:
            ax.set_xticks(x, labels, rotation=30, ha="right")
            ax.set_xlabel("test block (first time)")
            ax.grid(alpha=0.3, lw=0.5)
        axes[0].set_title(f"(a) error, budget {budget:g}")
        axes[1].set_title("(b) 68 % intervals")
        axes[2].set_title("(c) 95 % intervals")
        handles, names = axes[0].get_legend_handles_labels()
        fig.legend(handles, names, frameon=False, loc="outside lower center",
                   ncol=min(4, len(names)))
        if title:
            fig.suptitle(title)
    return fig


def plot_temporal_metrics(results: xr.Dataset, *, axes: Sequence[Any] | None = None,
                          title: str | None = None):
    """Memoryless vs temporal side by side for ``evaluate(temporal=...)`` results: (a) MSE vs
    budget per method, solid with the filter and dashed memoryless; (b) the filter's cut
    ``1 - mse / mse_memoryless``; (c) coverage of the 68 % / 95 % predictive intervals (filter:
    filled markers, memoryless: open) against the nominal levels. Results of
    ``evaluate(temporal=None)`` draw (a) and (c) without the memoryless lines. Returns the figure.
    """
    import matplotlib.pyplot as plt

    from .evaluation import summary

    df = summary(results)
    temporal = "mse_memoryless_mean" in df
    with plt.rc_context(_PRINT_RC):
        fig, axes = _panels(axes, 3, (10.5, 2.8), constrained_layout=True)
        for i, (method, rows) in enumerate(df.groupby("method", sort=False)):
            st = _style(method, i)
            x = rows["budget"].to_numpy()
            axes[0].plot(x, rows["mse_mean"], marker=st["marker"], color=st["color"],
                         label=st["label"])
            if temporal:
                axes[0].plot(x, rows["mse_memoryless_mean"], marker=st["marker"],
                             color=st["color"], ls="--", mfc="none")
                axes[1].plot(x, 100 * rows["temporal_cut"], marker=st["marker"],
                             color=st["color"])
            for level, ls in ((68, ":"), (95, "-")):
                if f"coverage{level}_mean" not in rows:
                    continue
                axes[2].plot(x, rows[f"coverage{level}_mean"], marker=st["marker"],
                             color=st["color"], ls=ls)
                if temporal:
                    axes[2].plot(x, rows[f"coverage{level}_memoryless_mean"], ls=ls,
                                 marker=st["marker"], color=st["color"], mfc="none", alpha=0.6)
        for level in (0.68, 0.95):
            axes[2].axhline(level, color="0.4", lw=0.8, ls="--")
        axes[0].set_ylabel(_mse_label(results, "MSE"))
        axes[0].set_yscale("log")
        axes[1].axhline(0.0, color="0.4", lw=0.8)
        axes[1].set_ylabel("error cut by the filter (%)")
        axes[2].set_ylabel("interval coverage")
        axes[0].set_title("(a) MSE: filter solid, memoryless dashed")
        axes[1].set_title("(b) 1 - MSE / MSE memoryless")
        axes[2].set_title("(c) coverage: 95% solid, 68% dotted")
        for ax in axes:
            ax.set_xlabel("budget (grid cells)")
            ax.grid(alpha=0.3, lw=0.5)
        axes[0].legend(frameon=False, fontsize="small")
        if title:
            fig.suptitle(title)
    return fig


_LAND = "0.82"  # face colour behind masked (NaN) cells: land or no data, light grey


def _coord_label(coord: xr.DataArray, name: str) -> str:
    """Axis label with units: ``latitude (deg N)`` from CF ``degrees_north`` and the like."""
    units = str(coord.attrs.get("units", "")).lower()
    known = {"degrees_north": "\N{DEGREE SIGN}N", "degree_north": "\N{DEGREE SIGN}N",
             "degrees_n": "\N{DEGREE SIGN}N", "degrees_east": "\N{DEGREE SIGN}E",
             "degree_east": "\N{DEGREE SIGN}E", "degrees_e": "\N{DEGREE SIGN}E"}
    if units in known:
        return f"{name} ({known[units]})"
    if not units and name in ("latitude", "longitude"):  # the Region's grids are in degrees
        return f"{name} (\N{DEGREE SIGN}{'N' if name == 'latitude' else 'E'})"
    return f"{name} ({units})" if units else name


def _units(da: xr.DataArray) -> str:
    return str(da.attrs.get("units", "")).strip()


def _with_units(label: str, units: str) -> str:
    return f"{label} ({units})" if units else label


MAX_MAP_ASPECT = 6.0
"""Widest width : height a map is drawn at; a thinner strip of a domain (5 x 100 cells) is
stretched in latitude up to this shape, else it is a line of pixels."""


def _spans(lat: Any, lon: Any) -> tuple[float, float]:
    """Extents in degrees of a grid's cell centres plus one cell: (latitude, longitude)."""
    lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
    span_lat = max(float(np.ptp(lat)), 1e-9) + (abs(lat[1] - lat[0]) if lat.size > 1 else 1)
    span_lon = max(float(np.ptp(lon)), 1e-9) + (abs(lon[1] - lon[0]) if lon.size > 1 else 1)
    return span_lat, span_lon


def map_layout(lat: Any, lon: Any, n_panels: int = 1, *, width: float = 7.5
               ) -> tuple[int, int, tuple[float, float]]:
    """``(nrows, ncols, figsize)`` for ``n_panels`` maps of one ``(lat, lon)`` grid in a
    figure ``width`` inches wide: side by side when the domain is about as tall as wide, one
    above the other when it is wide and thin (a 5 x 100 strip stays readable), each panel's
    height from the domain's aspect (degrees, as :func:`plot_map` draws them) plus room for
    its colour bar and labels."""
    span_lat, span_lon = _spans(lat, lon)
    aspect = min(span_lon / span_lat, MAX_MAP_ASPECT)  # width / height of one map as drawn
    stacked = n_panels > 1 and aspect > 1.6 * n_panels
    nrows, ncols = (n_panels, 1) if stacked else (1, n_panels)
    map_w = width / ncols - 1.3  # minus the colour bar and the latitude labels
    map_h = min(max(map_w / aspect, 0.9), 6.0)
    return nrows, ncols, (width, nrows * (map_h + 0.9))


def _readable_ticks(ax: Any) -> None:
    """At most one longitude tick per ~0.9 inch and latitude tick per ~0.35 inch of the axes,
    so labels never overlap whatever the figure's shape."""
    from matplotlib.ticker import MaxNLocator

    fig = ax.figure
    fig.canvas.draw_idle()
    box = ax.get_position()
    w_in, h_in = box.width * fig.get_figwidth(), box.height * fig.get_figheight()
    ax.xaxis.set_major_locator(MaxNLocator(nbins=max(2, int(w_in / 0.9)), steps=[1, 2, 5, 10]))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=max(2, int(h_in / 0.35)), steps=[1, 2, 5, 10]))


def plot_map(field: xr.DataArray, *, ax: Any = None, cmap: str = "viridis",
             route: xr.Dataset | None = None, label: str | None = None,
             coast: str | bool | None = "auto", **kwargs: Any):
    """One ``(lat, lon)`` map with labelled axes (degrees north / east, ticks spaced so their
    labels never overlap), masked (NaN) cells shaded grey, the coast (``coast``: ``"auto"``
    real coastlines where cartopy's shapefile or ``$LRM_CVX_COASTLINES`` is at hand, else the
    outline of the cells with values; ``"cartopy"``, ``"outline"`` or None, see
    :func:`lrm_cvx.coastlines.draw_coast`), a colour bar labelled ``label (units)`` unless
    ``add_colorbar=False``, and
    optionally a route (a Dataset with ``lat`` and ``lon`` per stop, start starred) drawn over
    it; returns the axes."""
    import matplotlib.pyplot as plt

    if not isinstance(field, xr.DataArray) or field.ndim != 2:
        raise DataError(f"field must be a (lat, lon) DataArray, got "
                        f"{getattr(field, 'dims', type(field).__name__)}")
    coast = check_coast(coast)
    if ax is None:
        _, ax = plt.subplots(figsize=(3.5, 3.0), constrained_layout=True)
    lat_dim, lon_dim = field.dims
    if kwargs.get("add_colorbar", True):
        name = label or str(field.attrs.get("long_name", field.name or "value"))
        kwargs.setdefault("cbar_kwargs", {"label": _with_units(name, _units(field))})
    mesh = field.plot.pcolormesh(ax=ax, cmap=cmap, add_labels=False, rasterized=True, **kwargs)
    cbar = getattr(mesh, "colorbar", None)
    if cbar is not None:  # a nearly constant field: plain numbers, not "1e-9 + 2.698e-1"
        cbar.formatter.set_useOffset(False)
        cbar.update_ticks()
    ax.set_facecolor(_LAND)
    draw_coast(ax, field[lat_dim].values, field[lon_dim].values, coast,
               valid=np.isfinite(field.values))
    if route is not None:
        ax.plot(route["lon"], route["lat"], "-", color="white", lw=1.6)
        ax.plot(route["lon"], route["lat"], "-o", color="#D55E00", lw=0.8, ms=1.8)
        ax.plot(route["lon"][:1], route["lat"][:1], "*", color="#D55E00", ms=7, mec="white",
                mew=0.6)
    ax.set_xlabel(_coord_label(field[lon_dim], "longitude"))
    ax.set_ylabel(_coord_label(field[lat_dim], "latitude"))
    span_lat, span_lon = _spans(field[lat_dim].values, field[lon_dim].values)
    stretch = max(1.0, span_lon / span_lat / MAX_MAP_ASPECT)  # a thin strip: drawn taller
    ax.set_aspect(1.0 * stretch, adjustable="box")
    _readable_ticks(ax)
    return ax


def plot_prediction_panels(truth: xr.DataArray, rows: Sequence[Mapping[str, Any]], *,
                           cmap: str = "RdBu_r", std_cmap: str = "magma_r",
                           coast: str | bool | None = "auto"):
    """Truth, prediction and standard deviation side by side, one row per setting.

    ``truth`` is the ``(lat, lon)`` snapshot (its ``units`` attr labels the colour bars);
    each row is a mapping with ``label`` (str), ``prediction`` and ``std`` (``(lat, lon)``
    DataArrays on the same grid) and optionally ``route`` (a Dataset with ``lat``/``lon``
    per stop), drawn over every panel of the row. Truth and predictions share one colour
    scale (symmetric about 0 when the data straddle it), the stds another; land / missing
    cells are grey; ``coast`` as in :func:`plot_map`. Returns the figure.
    """
    import matplotlib.pyplot as plt

    if not rows:
        raise DataError("rows must hold at least one {label, prediction, std} mapping")
    units = _units(truth)
    name = str(truth.attrs.get("long_name", truth.name or "value")).split(",")[0]
    lo, hi = np.nanpercentile(truth.values, [1, 99])
    if lo < 0 < hi:  # anomalies: a diverging scale centred on zero
        lo, hi = -max(-lo, hi), max(-lo, hi)
    smax = max(float(np.nanpercentile(r["std"].values, 99)) for r in rows)
    n = len(rows)
    ny, nx = truth.shape
    panel_w = 7.2 / 3
    panel_h = panel_w * ny / nx + 0.45
    with plt.rc_context(_PRINT_RC):
        fig, axes = plt.subplots(n, 3, figsize=(7.2, panel_h * n + 1.0), squeeze=False,
                                 sharex=True, sharey=True, constrained_layout=True)
        for i, row in enumerate(rows):
            route = row.get("route")
            plot_map(truth, ax=axes[i, 0], cmap=cmap, vmin=lo, vmax=hi, route=route,
                     add_colorbar=False, coast=coast)
            plot_map(row["prediction"], ax=axes[i, 1], cmap=cmap, vmin=lo, vmax=hi,
                     route=route, add_colorbar=False, coast=coast)
            plot_map(row["std"], ax=axes[i, 2], cmap=std_cmap, vmin=0, vmax=smax, route=route,
                     add_colorbar=False, coast=coast)
            axes[i, 0].set_title("truth (held-out snapshot)")
            axes[i, 1].set_title(f"prediction\n{row['label']}")
            axes[i, 2].set_title("standard deviation")
            for ax in axes[i, 1:]:
                ax.set_ylabel("")
            if i < n - 1:
                for ax in axes[i]:
                    ax.set_xlabel("")
        for cols, label, vmin, vmax, cm, ext in (
                (axes[:, :2], name, lo, hi, cmap, "both"),
                (axes[:, 2], "predictive std", 0, smax, std_cmap, "max")):
            mappable = matplotlib.cm.ScalarMappable(matplotlib.colors.Normalize(vmin, vmax),
                                                    cmap=cm)
            fig.colorbar(mappable, ax=cols, location="bottom", shrink=0.8, aspect=30,
                         label=_with_units(label, units), extend=ext)
        fig.suptitle(f"{name}, {np.datetime_as_string(truth['time'].values, unit='D')}"
                     if "time" in truth.coords else name)
    return fig


def plot_demo_metrics(table: Any, *, units: str = "", ax: Any = None):
    """Reconstruction MSE vs budget per setting (rows of :attr:`DemoResult.table`: columns
    ``setting``, ``budget``, ``mse_mean``, ``mse_se``), mean +- s.e., log scale. The first
    setting (the recommended one) is drawn thickest. Returns the figure."""
    import matplotlib.pyplot as plt

    with plt.rc_context(_PRINT_RC):
        if ax is None:
            fig, ax = plt.subplots(figsize=(7.2, 3.0), constrained_layout=True)
        else:
            fig = ax.figure
        colors = ["#D55E00", "#E69F00", "#000000", "#0072B2", "#56B4E9", "#009E73", "#CC79A7"]
        for i, (setting, rows) in enumerate(table.groupby("setting", sort=False)):
            x = rows["budget"].to_numpy()
            y = rows["mse_mean"].to_numpy()
            se = np.nan_to_num(rows["mse_se"].to_numpy())
            ax.plot(x, y, marker="osD^v<>"[i % 7], color=colors[i % len(colors)],
                    lw=2.0 if i == 0 else 1.0, ls="-" if i < 2 else "--", label=setting)
            ax.fill_between(x, y - se, y + se, color=colors[i % len(colors)], alpha=0.15, lw=0)
        ax.set_yscale("log")
        ax.set_xlabel("budget (grid cells)")
        ax.set_ylabel(_with_units("reconstruction MSE", f"{units}\N{SUPERSCRIPT TWO}"
                                  if units else ""))
        ax.grid(alpha=0.3, lw=0.5, which="both")
        ax.set_title("reconstruction error on held-out snapshots, lower is better")
        ax.legend(frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def plot_predictions(model: Any, snapshot: xr.DataArray, routes: Mapping[float, Sequence[int]],
                     *, ridge: float = 0.0, cmap: str = "viridis", error_cmap: str = "gray_r",
                     robots: Mapping[float, Sequence[int]] | None = None,
                     coast: str | bool | None = "auto"):
    """The qualitative figure: for each budget, the error heat map and the predicted map.

    ``snapshot`` is one test snapshot ``(lat, lon)`` on the model's grid; ``routes`` maps a
    budget to the route's cell indices. The prediction folds in the snapshot's values at the
    route's cells (cells it lacks are skipped); the error map is ``|prediction - snapshot|``
    on the snapshot's observed cells, darker = larger, as in the paper. ``robots`` (a fleet)
    maps a budget to the robot of each route entry (same length, -1 = padding): each robot's
    route is drawn as its own line. ``coast`` as in :func:`plot_map`.
    """
    import matplotlib.pyplot as plt

    region = model.region_
    values = region.stack(snapshot)
    lo, hi = np.nanpercentile(values, [2, 98])
    n = len(routes)
    with plt.rc_context(_PRINT_RC):
        fig, axes = plt.subplots(n, 2, figsize=(7.2, 2.3 * n + 0.8), squeeze=False,
                                 constrained_layout=True)
        errors = {}
        preds = {}
        for budget, cells in routes.items():
            cells = np.asarray(cells, dtype=np.int64)
            cells = cells[cells >= 0]
            seen = cells[np.isfinite(values[cells])]
            pred = model.complete((seen, values[seen]), ridge=ridge)["prediction"]
            preds[budget] = pred
            errors[budget] = abs(pred - snapshot).where(np.isfinite(snapshot))
        emax = max(float(e.quantile(0.98)) for e in errors.values())
        for row, (budget, cells) in enumerate(routes.items()):
            route = _route_lines(region, cells, None if robots is None else robots[budget])
            cells = np.asarray(cells, dtype=np.int64)
            cells = cells[cells >= 0]
            plot_map(errors[budget], ax=axes[row, 0], cmap=error_cmap, vmin=0, vmax=emax,
                     route=route, add_colorbar=False, coast=coast)
            plot_map(preds[budget], ax=axes[row, 1], cmap=cmap, vmin=lo, vmax=hi, route=route,
                     add_colorbar=False, coast=coast)
            axes[row, 0].set_title(f"|error|, budget {budget:g} ({len(cells)} cells)")
            axes[row, 1].set_title(f"prediction, budget {budget:g}")
        units = snapshot.attrs.get("units", "")
        for col, (label, vmin, vmax, cm) in enumerate(
            [("|prediction - truth|", 0, emax, error_cmap), ("prediction", lo, hi, cmap)]
        ):
            mappable = matplotlib.cm.ScalarMappable(
                matplotlib.colors.Normalize(vmin, vmax), cmap=cm)
            fig.colorbar(mappable, ax=axes[:, col], location="bottom", shrink=0.8,
                         label=f"{label} ({units})" if units else label,
                         extend="max" if col == 0 else "both")
    return fig


def _route_lines(region: Any, cells: Sequence[int], robot: Sequence[int] | None) -> xr.Dataset:
    """``lat``/``lon`` per route entry (padding ``-1`` dropped); with ``robot`` ids, a NaN row
    between robots so each robot's route is its own line."""
    cells = np.asarray(cells, dtype=np.int64)
    keep = cells >= 0
    lat = region.cell_lat[cells[keep]].astype(float)
    lon = region.cell_lon[cells[keep]].astype(float)
    if robot is not None:
        rid = np.asarray(robot, dtype=np.int64)[keep]
        breaks = np.flatnonzero(np.diff(rid) != 0) + 1
        lat = np.insert(lat, breaks, np.nan)
        lon = np.insert(lon, breaks, np.nan)
    return xr.Dataset({"lat": ("step", lat), "lon": ("step", lon)})


def save_figure(fig: Any, path: str | Path, formats: Sequence[str] = ("png", "pdf")) -> list[Path]:
    """Save ``fig`` as ``path`` with each suffix in ``formats`` (atomically); return the paths."""
    path = Path(path)
    out = []
    for fmt in formats:
        target = path.with_suffix(f".{fmt}")
        with atomic_output(target) as tmp:
            fig.savefig(tmp, format=fmt, bbox_inches="tight")
        out.append(target)
    return out
