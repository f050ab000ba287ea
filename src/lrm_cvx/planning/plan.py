"""The result of planning: the cells to sample, the route through them, and its exports."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import atomic_output

__all__ = ["Plan"]


def check_region(region: Any, name: str = "region") -> Any:
    """``region`` if it is a :class:`~lrm_cvx.region.Region`, else a :class:`PlanningError`
    naming it (a model fitted on a plain array has no region and cannot plan)."""
    from ..region import Region

    if isinstance(region, Region):
        return region
    from ..errors import PlanningError

    raise PlanningError(
        f"{name} must be a lrm_cvx.Region (the grid of the model's cells), got "
        f"{type(region).__name__}: a model fitted on a plain array has no region; fit it on a "
        "(time, lat, lon) DataArray or pass region=Region.from_dataarray(data)"
    )


def _path_cumulative(grid_index: np.ndarray) -> np.ndarray:
    """Cumulative Euclidean grid length ``(r,)`` of the path through ``grid_index`` ``(r, 2)``,
    summed in order from 0 exactly as :func:`lrm_cvx.cost.route_length` sums it."""
    g = np.asarray(grid_index, dtype=np.int64).reshape(-1, 2)
    if g.shape[0] == 0:
        return np.empty(0)
    d = np.diff(g, axis=0)
    steps = np.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float64))
    return np.cumsum(np.concatenate([[0.0], steps]))


@dataclass(eq=False, repr=False)
class Plan:
    """A sampling plan from ``start`` within ``budget``.

    Attributes
    ----------
    cells : ``(n,)`` int64, the distinct cells to observe in selection order (greedy: the
        initial cells first, then one per iteration; baselines: first visit order).
    route : ``(r,)`` int64, the cells in travel order from the start. Greedy with the
        nearest-neighbour cost: the nearest-neighbour tour of ``cells``; with the insertion
        cost: the cheapest-insertion route; random walk: the walk itself (cells may repeat);
        transect: the valid cells passed, in order.
    cost : length of the travel in grid units (the cost the budget constrains).
    information : Fisher information ``log det(ridge I + sum_cells y y^T)`` of ``cells``
        (``-inf`` if singular, ``nan`` when a baseline was built without ``Y``).
    criterion : the greedy's criterion (``"fisher"`` / ``"a-optimal"``), ``None`` for baselines.
    budget, start, ridge : the request (``start`` is a cell index).
    lat, lon, grid_index : ``(r,)``, ``(r,)``, ``(r, 2)`` coordinates of each *route* entry.
    history : per greedy iteration, arrays ``cell``, ``gain``, ``cost_increase``, ``ratio``,
        ``cost`` (route cost after the pick) and ``n_evaluated`` (candidates whose exact cost
        was recomputed); empty arrays for baselines.
    method : ``"greedy"``, ``"transect-up"`` (``-down``, ``-left``, ``-right``) or ``"random"``.
    route_cost : ``(r,)`` float64, the travel cost from the start to each route stop (the last
        one equals ``cost``): the grid-distance path along the route for the greedy and the
        random walk; the grid steps walked for a transect (steps across masked positions count).
    posterior : the greedy's criterion was computed on the fold-in's posterior (a prior
        precision or per-cell noise), not on ``ridge I + sum y y^T``.
    refinement : empty, or what :func:`~lrm_cvx.planning.refine.refine` gained:
        ``information_before`` / ``information_after`` (nats), ``moves`` accepted, ``inserted``,
        ``swapped``, ``rounds``, ``seconds`` (history keys ``refine_*`` list the moves).
    """

    cells: np.ndarray
    route: np.ndarray
    cost: float
    information: float
    criterion: str | None
    budget: float
    start: int
    ridge: float
    lat: np.ndarray
    lon: np.ndarray
    grid_index: np.ndarray
    history: dict[str, np.ndarray] = field(default_factory=dict)
    method: str = "greedy"
    cost_function: str = "nearest-neighbor"
    route_cost: np.ndarray = field(default_factory=lambda: np.empty(0))
    posterior: bool = False
    refinement: dict[str, Any] = field(default_factory=dict, compare=False)
    _Y: Any = field(default=None, repr=False, compare=False)
    _region: Any = field(default=None, repr=False, compare=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(
        cls,
        *,
        region: Any,
        cells: Any,
        route: Any,
        cost: float | None,
        information: float,
        criterion: str | None,
        budget: float,
        start: int,
        ridge: float,
        method: str,
        history: dict[str, np.ndarray] | None = None,
        cost_function: str = "nearest-neighbor",
        Y: Any = None,
        route_cost: Any = None,
        posterior: bool = False,
    ) -> Plan:
        """A plan with its coordinates looked up in ``region``.

        ``route_cost`` (cumulative cost at each route stop) defaults to the grid-distance path
        along ``route`` (summed in order, as the path costs are); ``cost`` defaults to its last
        value. A given ``cost`` must equal the last ``route_cost`` (to 1e-9 relative).
        """
        route = np.asarray(route, dtype=np.int64)
        gi = np.asarray(region.grid_index[route], dtype=np.int64)
        if route_cost is None:
            route_cost = _path_cumulative(gi)
        route_cost = np.asarray(route_cost, dtype=np.float64)
        if route_cost.shape != route.shape:
            raise ValueError(f"route_cost must have the route's shape {route.shape}")
        if cost is None:
            cost = float(route_cost[-1]) if route.size else 0.0
        if route.size and not np.isclose(route_cost[-1], cost, rtol=1e-9, atol=1e-9):
            raise ValueError(f"the route's cost {route_cost[-1]!r} differs from cost={cost!r}")
        if route.size:
            route_cost[-1] = float(cost)  # the same float, not one rounded differently
        return cls(
            cells=np.asarray(cells, dtype=np.int64),
            route=route,
            cost=float(cost),
            information=float(information),
            criterion=criterion,
            budget=float(budget),
            start=int(start),
            ridge=float(ridge),
            lat=np.asarray(region.cell_lat[route], dtype=np.float64),
            lon=np.asarray(region.cell_lon[route], dtype=np.float64),
            grid_index=gi,
            history=dict(history or {}),
            method=method,
            cost_function=cost_function,
            route_cost=route_cost,
            posterior=bool(posterior),
            _Y=Y,
            _region=region,
        )

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.cells.size)

    def __repr__(self) -> str:
        crit = f", criterion={self.criterion!r}" if self.criterion else ""
        return (
            f"Plan(method={self.method!r}{crit}, {len(self)} cells, route of "
            f"{self.route.size} stops, cost={self.cost:.4g} / budget={self.budget:.4g}, "
            f"information={self.information:.6g}, start={self.start})"
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Plan):
            return NotImplemented
        scalars = ("cost", "information", "criterion", "budget", "start", "ridge", "method",
                   "cost_function", "posterior")
        arrays = ("cells", "route", "lat", "lon", "grid_index", "route_cost")
        return (
            all(
                getattr(self, a) == getattr(other, a)
                or (isinstance(getattr(self, a), float) and np.isnan(getattr(self, a))
                    and np.isnan(getattr(other, a)))
                for a in scalars
            )
            and all(np.array_equal(getattr(self, a), getattr(other, a)) for a in arrays)
            and self.history.keys() == other.history.keys()
            and all(np.array_equal(self.history[k], other.history[k]) for k in self.history)
        )

    __hash__ = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ certificate
    def certify(self, **kwargs: Any) -> Any:
        """Upper bound on the achievable Fisher information and this plan's optimality gap.

        Calls :func:`lrm_cvx.planning.bound.plan_bound` with this plan's model, region, start,
        budget and ridge; keyword arguments are passed on (e.g. ``tol``). The certificate
        always bounds the **Fisher** information (``certificate.criterion == "fisher"``); its
        ``gap`` and ``volume_ratio`` are NaN when the plan was chosen for another criterion
        (``"a-optimal"``, ``"gp-variance"``, or Fisher on a posterior): a gap between two
        criteria means nothing (docs/certificate.md, "Which criterion is certified").

        For a Fisher greedy plan the certificate also splits the gap: ``greedy_information``,
        ``refined_information`` (this plan's refinement, or a :func:`refine` run here; pass
        ``refine=False`` to skip it), ``plan_slack`` (greedy -> refined) and ``bound_slack``
        (refined -> bound).
        """
        if self._Y is None or self._region is None:
            from ..errors import PlanningError

            raise PlanningError("this plan has no model Y attached: build it with Y to certify")
        from .bound import plan_bound

        return plan_bound(self._Y, self._region, self.start, self.budget, ridge=self.ridge,
                          plan=self, **kwargs)

    # ------------------------------------------------------------------ exports
    def to_dataframe(self) -> Any:
        """One row per route stop: order, cell, lat, lon, row, col, cumulative_cost."""
        import pandas as pd

        cum = self.route_cost
        if cum.shape != self.route.shape:  # a Plan built by hand without route_cost
            cum = _path_cumulative(self.grid_index)
        return pd.DataFrame(
            {
                "order": np.arange(self.route.size),
                "cell": self.route,
                "lat": self.lat,
                "lon": self.lon,
                "row": self.grid_index[:, 0] if self.route.size else np.empty(0, np.int64),
                "col": self.grid_index[:, 1] if self.route.size else np.empty(0, np.int64),
                "cumulative_cost": cum,
            }
        )

    def to_csv(self, path: str | Path) -> Path:
        """Write :meth:`to_dataframe` to ``path`` atomically; returns the path."""
        path = Path(path)
        with atomic_output(path) as tmp:
            self.to_dataframe().to_csv(tmp, index=False)
        return path

    def to_geojson(self, path: str | Path | None = None) -> dict[str, Any]:
        """GeoJSON FeatureCollection: the route as a LineString and each cell as a Point.

        Coordinates are ``[lon, lat]`` (RFC 7946). Point properties: ``cell``, ``order`` (first
        visit on the route), ``selection`` (index in ``cells``), ``start``. The collection's
        properties carry method, cost, budget and information. Written atomically when ``path``.
        """
        coords = [[float(lo), float(la)] for lo, la in zip(self.lon, self.lat, strict=True)]
        first: dict[int, int] = {}
        for i, c in enumerate(self.route.tolist()):
            first.setdefault(int(c), i)
        sel = {int(c): i for i, c in enumerate(self.cells.tolist())}
        features: list[dict[str, Any]] = [
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": coords},
                "properties": {"kind": "route", "cost": self.cost},
            }
        ]
        for c, i in first.items():
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Point", "coordinates": coords[i]},
                    "properties": {
                        "kind": "cell",
                        "cell": c,
                        "order": i,
                        "selection": sel.get(c),
                        "start": c == self.start,
                    },
                }
            )

        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        doc = {
            "type": "FeatureCollection",
            "features": features,
            "properties": {
                "method": self.method,
                "criterion": self.criterion,
                "cost_function": self.cost_function,
                "cost": num(self.cost),
                "budget": num(self.budget),
                "information": num(self.information),
                "ridge": self.ridge,
                "start": self.start,
                "n_cells": len(self),
            },
        }
        if path is not None:
            with atomic_output(path) as tmp:
                tmp.write_text(json.dumps(doc))
        return doc

    def plot(self, ax: Any = None, background: Any = None, **background_kw: Any) -> Any:
        """Draw the plan on a map: optional ``background`` (a ``(lat, lon)`` DataArray or array
        on the region's grid), the route line, the cells and the start (star). Returns ``ax``."""
        import matplotlib.pyplot as plt

        if ax is None:
            _, ax = plt.subplots()
        if background is not None:
            values = np.asarray(getattr(background, "values", background), dtype=float)
            if self._region is not None and values.ndim == 1:
                values = self._region.unstack(values).values
            if self._region is not None:
                lat, lon = self._region.lat.values, self._region.lon.values
            elif hasattr(background, "dims") and background.ndim == 2:
                lat = np.asarray(background[background.dims[0]].values)
                lon = np.asarray(background[background.dims[1]].values)
            else:
                raise ValueError("a plain-array background needs the plan's region")
            kw = {"shading": "nearest", "cmap": "viridis"} | background_kw
            mesh = ax.pcolormesh(lon, lat, values, **kw)
            ax.figure.colorbar(mesh, ax=ax, shrink=0.8)
        ax.plot(self.lon, self.lat, "-", color="white", lw=2.5, alpha=0.8, zorder=2)
        ax.plot(self.lon, self.lat, "-", color="crimson", lw=1.2, zorder=3, label="route")
        first = np.unique(self.route, return_index=True)[1]
        ax.scatter(self.lon[first], self.lat[first], s=14, color="black", zorder=4,
                   label="cells")
        if self.route.size:
            ax.scatter(self.lon[:1], self.lat[:1], s=120, marker="*", color="gold",
                       edgecolor="black", zorder=5, label="start")
        ax.set_xlabel("lon")
        ax.set_ylabel("lat")
        ax.set_title(f"{self.method}: {len(self)} cells, cost {self.cost:.3g}/{self.budget:.3g}")
        ax.legend(loc="best", fontsize="small")
        return ax
