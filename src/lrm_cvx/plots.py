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
from .errors import DataError

__all__ = ["plot_metrics", "plot_predictions", "plot_map", "save_figure", "METHOD_STYLE"]

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
        if axes is None:
            fig, axes = plt.subplots(1, 2, figsize=(7.2, 2.6), constrained_layout=True)
        else:
            fig = axes[0].figure
        for i, (method, rows) in enumerate(df.groupby("method", sort=False)):
            st = _style(method, i)
            for ax, metric in zip(axes, ("information", "mse"), strict=True):
                x = rows["budget"].to_numpy()
                y = rows[f"{metric}_mean"].to_numpy()
                se = np.nan_to_num(rows[f"{metric}_se"].to_numpy())
                ax.plot(x, y, marker=st["marker"], color=st["color"], label=st["label"])
                ax.fill_between(x, y - se, y + se, color=st["color"], alpha=0.18, lw=0)
        complete = float(results["complete_mse"].mean())
        axes[1].axhline(complete, color="0.4", ls="--", lw=1, label="complete")
        axes[0].set_ylabel("Fisher information (nats)")
        units = results["mse"].attrs.get("units")
        axes[1].set_ylabel(f"reconstruction MSE ({units})" if units else "reconstruction MSE")
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


def plot_map(field: xr.DataArray, *, ax: Any = None, cmap: str = "viridis",
             route: xr.Dataset | None = None, **kwargs: Any):
    """One ``(lat, lon)`` map (colour bar unless ``add_colorbar=False``), optionally with a
    route (a Dataset with ``lat`` and ``lon`` per stop) drawn; returns the mappable's axes."""
    import matplotlib.pyplot as plt

    if field.ndim != 2:
        raise DataError(f"field must be a (lat, lon) DataArray, got dims {field.dims}")
    if ax is None:
        _, ax = plt.subplots(figsize=(3.5, 3.0), constrained_layout=True)
    field.plot.pcolormesh(ax=ax, cmap=cmap, add_labels=False, rasterized=True, **kwargs)
    if route is not None:
        ax.plot(route["lon"], route["lat"], "-", color="white", lw=1.6)
        ax.plot(route["lon"], route["lat"], "-o", color="#D55E00", lw=0.8, ms=1.8)
        ax.plot(route["lon"][:1], route["lat"][:1], "*", color="#D55E00", ms=7, mec="white",
                mew=0.6)
    ax.set_aspect("equal", adjustable="box")
    return ax


def plot_predictions(model: Any, snapshot: xr.DataArray, routes: Mapping[float, Sequence[int]],
                     *, ridge: float = 0.0, cmap: str = "viridis", error_cmap: str = "gray_r"):
    """The qualitative figure: for each budget, the error heat map and the predicted map.

    ``snapshot`` is one test snapshot ``(lat, lon)`` on the model's grid; ``routes`` maps a
    budget to the route's cell indices. The prediction folds in the snapshot's values at the
    route's cells (cells it lacks are skipped); the error map is ``|prediction - snapshot|``
    on the snapshot's observed cells, darker = larger, as in the paper.
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
            cells = np.asarray(cells, dtype=np.int64)
            cells = cells[cells >= 0]
            route = xr.Dataset({"lat": ("step", region.cell_lat[cells]),
                                "lon": ("step", region.cell_lon[cells])})
            plot_map(errors[budget], ax=axes[row, 0], cmap=error_cmap, vmin=0, vmax=emax,
                     route=route, add_colorbar=False)
            plot_map(preds[budget], ax=axes[row, 1], cmap=cmap, vmin=lo, vmax=hi, route=route,
                     add_colorbar=False)
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
