"""Campaigns: plan, observe, assimilate and score day after day.

:func:`simulate_campaign` replays a field campaign on held-out snapshots: for each snapshot in
time order the filter (:class:`~lrm_cvx.monitor.MonitorState`) forecasts, the planner plans
with the forecast as its prior, the true snapshot is observed at the plan's cells, the
observations are assimilated and the map is predicted and scored. ``temporal=None`` runs the
memoryless model through the same loop (every day's prior is the empirical prior), so the two
compare on the same footing. Every method plans under the same path request
(:class:`~lrm_cvx.planning.request.PathOptions`: km or grid units, stop cost, no-go cells,
closed tours, a fixed end, sensing along) and fleet (:class:`~lrm_cvx.planning.request.Fleet`);
``replan_every=k`` replans en route (:func:`~lrm_cvx.replanning.replan`) every ``k`` route
entries.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import xarray as xr

from ._validation import as_generator, check_flag
from .errors import DataError, ModelError, PlanningError
from .glrm.dynamics import check_times, temporal_value
from .glrm.dynamics import estimate as estimate_dynamics
from .monitor import MonitorState
from .planning.planners import (
    GreedyPlanner,
    Planner,
    Refined,
    check_method,
    planner_for,
    recommended_method,
)
from .planning.request import Fleet, PathOptions
from .planning.sensors import observed_cells, plan_observations
from .planning.terms import PriorTerms
from .recommended import RECOMMENDED

__all__ = ["simulate_campaign", "posterior_campaign", "method_request", "path_attrs",
           "CAMPAIGN_OPTIONS"]

CAMPAIGN_OPTIONS = ("cost", "ridge", "criterion")
"""The planner options of :func:`simulate_campaign` (besides the path)."""


def _dynamics_for(model: Any, temporal: Any) -> tuple[Any, bool]:
    """``(dynamics, memoryless)``: the model's ``dynamics_`` when it is of kind ``temporal``,
    else estimated from ``X_`` (the model is not modified)."""
    from .glrm.dynamics import Dynamics

    if isinstance(temporal, Dynamics):
        return temporal, False
    temporal = temporal_value(temporal)
    if temporal is None:
        return None, True
    if temporal == "auto":  # the model's own: its validated choice (validation/selection.py) or fit
        dyn = getattr(model, "dynamics_", None)
        return dyn, dyn is None
    dyn = getattr(model, "dynamics_", None)
    if dyn is not None and dyn.kind == temporal:
        return dyn, False
    X = model.X_
    times = X[X.dims[1]] if isinstance(X, xr.DataArray) else np.arange(model.X.shape[1])
    return estimate_dynamics(temporal, model.X, times), False


def _is_greedy(planner: Planner) -> bool:
    return isinstance(planner, (GreedyPlanner, Refined))


def method_request(method: str, planner: Planner, path: PathOptions) -> PathOptions:
    """The path request ``planner`` (of ``method``) runs under when every method shares
    ``path``: ``path`` itself for a greedy planner; for a baseline (a transect, the random
    walk) ``path`` without ``sense_along``, which changes nothing for them (their routes step
    between 8-neighbours, so every cell they pass is a route cell and observed already).
    A baseline cannot finish at a fixed ``end``: PlanningError naming the method."""
    if _is_greedy(planner):
        return path
    if path.end is not None:
        raise PlanningError(f"method {method!r} cannot finish at a fixed end (end=): only the "
                            "greedy methods take end; use closed=True or drop the method")
    return replace(path, sense_along=False) if path.sense_along else path


def path_attrs(path: PathOptions, n_robots: int = 1) -> dict[str, Any]:
    """The path request as netCDF-safe attrs (the keys of ``evaluate``'s attrs, which
    :func:`~lrm_cvx.evaluation.path_label` reads, plus ``end`` (-1: none) and
    ``sense_along``)."""
    return {
        "metric": path.metric,
        "speed": float(np.nan if path.speed is None else path.speed),
        "stop_cost": float(path.stop_cost),
        "traversable": path.traversable_kind,
        "closed": int(bool(path.closed)),
        "end": -1 if path.end is None else int(path.end),
        "sense_along": int(bool(path.sense_along)),
        "n_robots": int(n_robots),
        "budget_unit": path.unit,
        "sensor": path.sensor.describe(),
    }


def _day_terms(state: MonitorState, t: Any, planner: Planner) -> PriorTerms | None:
    """The prior terms of day ``t``'s plan: a planner on the model's belief (the
    ``greedy:<criterion>`` methods) plans on the state's belief about ``t`` (the forecast once
    the state has observed an earlier day); the paper's greedy and the baselines ignore it
    (None)."""
    if not getattr(planner, "model_prior", False):
        return None
    return state.planner_kwargs(criterion=planner.criterion, time=t)["prior"]


def _same_terms(a: PriorTerms | None, b: PriorTerms | None) -> bool:
    """Whether two days' prior terms are equal (arrays entry by entry)."""
    if a is None or b is None:
        return a is b
    return a.same(b)


def _plan_day(state: MonitorState, t: Any, planner: Planner, fleet: Fleet, path: PathOptions,
              rng: np.random.Generator, ridge: float, last: tuple | None = None
              ) -> tuple[Any, PriorTerms | None]:
    """Day ``t``'s plan by ``planner`` for ``fleet`` under ``path`` (:func:`_day_terms`) and its
    terms. ``last``, the previous day's ``(plan, terms)``, is kept when the planner does not
    draw from ``rng`` and the terms are the same (the memoryless model's every day, and the
    planners that ignore the belief): the same inputs give the same route."""
    terms = _day_terms(state, t, planner)
    if last is not None and not planner.uses_rng and _same_terms(terms, last[1]):
        return last
    model = state.model
    return (planner.plan(model.Y, model.region_, fleet, path, rng=rng, ridge=ridge,
                         prior=terms), terms)


def _observed_entries(plan: Any, sel: np.ndarray) -> np.ndarray:
    """The cells observed at route entries ``sel``: every entry with ``sense_along``, else the
    sampling stops."""
    cells = np.asarray(plan.route, dtype=np.int64)[sel]
    if plan.path.get("sense_along"):
        return cells
    return cells[np.asarray(plan.waypoint, dtype=bool)[sel]]


def _fly_replanning(state: MonitorState, plan: Any, t: Any, truth: np.ndarray, every: int,
                    criterion: str) -> tuple[Any, np.ndarray, int]:
    """Fly ``plan`` on day ``t``: after every ``every`` route entries of each robot, assimilate
    what was observed and replan the rest (:func:`~lrm_cvx.replanning.replan`: budget left,
    same end, same path model). Returns ``(flown plan, cells observed, replans)``; each cell
    is assimilated once."""
    from .replanning import replan

    n = plan.n_robots
    seen = np.empty(0, dtype=np.int64)

    def sizes(p: Any) -> list[int]:
        return np.bincount(p.route_robot, minlength=n).tolist()

    def fresh(p: Any, lo: list[int], hi: list[int]) -> np.ndarray:
        """The cells observed at each robot's route entries ``lo[r]:hi[r]`` not seen yet."""
        nonlocal seen
        sel = np.concatenate([np.flatnonzero(p.route_robot == r)[lo[r]:hi[r]]
                              for r in range(n)])
        cells = np.unique(_observed_entries(p, sel))
        cells = cells[~np.isin(cells, seen)]
        seen = np.union1d(seen, cells)
        return cells

    def fold(cells: np.ndarray) -> None:
        state.assimilate_today((cells, truth[cells]), t)

    size, done, sent, n_replans = sizes(plan), [1] * n, [0] * n, 0
    while any(d < s for d, s in zip(done, size, strict=True)):
        done = [min(d + every, s) for d, s in zip(done, size, strict=True)]
        cells = fresh(plan, sent, done)
        sent = list(done)
        if done == size:  # the whole route is flown: nothing left to replan
            fold(cells)
            break
        plan = replan(state, plan, done, (cells, truth[cells]) if cells.size else None,
                      time=t, criterion=criterion)
        n_replans += 1
        size = sizes(plan)
    if state.time_after(t) != 0:  # nothing assimilated today yet (a route of its start alone)
        fold(fresh(plan, [0] * n, size))
    return plan, seen, n_replans


def _check_every(replan_every: Any, replan: bool, planner: Planner, method: str) -> int:
    """``replan_every`` as an int >= 1, or 0 for None (PlanningError naming it)."""
    if replan_every is None:
        return 0
    if isinstance(replan_every, (bool, np.bool_)) or not isinstance(
            replan_every, (int, np.integer)) or replan_every < 1:
        raise PlanningError(f"replan_every must be None or an integer >= 1 (route entries "
                            f"between replans), got {replan_every!r}")
    if not getattr(planner, "model_prior", False):
        raise PlanningError(f"replan_every needs a greedy method on the filter's belief "
                            f"(greedy:<criterion>), got method {method!r}")
    if not replan:
        raise PlanningError("replan_every replans every day's route en route: it needs "
                            "replan=True")
    return int(replan_every)


def simulate_campaign(
    model: Any,
    test_data: xr.DataArray,
    start: Any,
    budget: Any,
    *,
    method: str | None = None,
    temporal: Any = RECOMMENDED["temporal"],
    replan: bool = True,
    seed: Any = 0,
    spatial: bool | None = None,
    path: PathOptions | None = None,
    replan_every: int | None = None,
    paper: bool = False,
    criterion: str = "fisher",
    cost: str = "nearest-neighbor",
    ridge: float = 0.0,
) -> xr.Dataset:
    """Replay a campaign over the snapshots of ``test_data`` ``(time, lat, lon)``.

    ``model``: a fitted GLRM with a region (``test_data`` on its grid, its times after the
    model's last fitted time, sorted and unique). ``start``: a cell index or ``(lat, lon)``, or
    a list of those (a fleet, one per robot); ``budget``: a number (every robot) or one per
    robot, in the path model's unit. ``method``: any method of
    :data:`~lrm_cvx.planning.planners.METHOD_REGISTRY` (``"greedy:fisher"``,
    ``"greedy:a-optimal"``, ``"greedy:gp-variance"`` plan with the filter's forecast as prior;
    ``"greedy"``, the transects and ``"random"`` ignore it). Default None: the recommended
    method (``RECOMMENDED["method"]``, today ``"greedy:gp-variance"``), ``"greedy:fisher"``
    (the forecast as prior, Fisher criterion) for a model without a spatial residual;
    ``paper=True``: the paper's ``"greedy"`` (the filter still assimilates and predicts; an
    explicit ``method`` wins). ``paper`` must be True or False.
    ``temporal``: ``"auto"`` (default, ``RECOMMENDED["temporal"]``: the model's own temporal
    model: its validated choice when fitted with ``temporal="auto"``, else its ``dynamics_``,
    else memoryless), None (memoryless), ``"ar1"`` or ``"seasonal"`` (the model's ``dynamics_``
    when of that kind, else estimated from ``X_``), or a
    :class:`~lrm_cvx.glrm.dynamics.Dynamics` (e.g. the true dynamics of a planted field, in the
    model's latent coordinates).
    ``replan=False`` plans once, on the first day, and flies that route every day.
    ``criterion`` (for ``"greedy"``), ``cost`` and ``ridge`` are the planner's, ``path`` (a
    :class:`~lrm_cvx.planning.request.PathOptions`) the path model of
    :func:`~lrm_cvx.planning.plan_greedy`, which **every** method follows (the baselines cannot
    take ``end``; ``sense_along`` changes nothing for them, see :func:`method_request`). With
    ``sense_along`` every cell passed is observed.
    ``replan_every``: replan en route after every ``k`` route entries of each robot
    (:func:`~lrm_cvx.replanning.replan`: what was observed so far is assimilated, the rest is
    planned with the budget left, the same end and path model and the plan's check against
    straight lines); greedy methods on the filter's belief only. ``spatial``: use the model's
    spatial residual (None: when it has one).

    Each day: forecast, plan, observe the true snapshot at the plan's cells (cells it lacks
    give no observation), assimilate, predict. Returns a Dataset over ``time`` with ``mse``
    (over the snapshot's observed cells, like ``evaluate``), ``mse_heldout``, ``mse_forecast``
    (the morning forecast's map before the day's samples, same cells: a posterior should not be
    worse than it on average), ``coverage68``, ``coverage95`` (fraction of the observed cells
    *not sampled* inside the central 68 % / 95 % predictive interval, ``mean +- z *
    predictive_std``, ``z`` the state's ``interval_multipliers``: the calibration's conformal
    thresholds, else the normal quantiles), ``n_obs``, ``information`` (the morning plan's
    criterion value), ``logdet_cov`` (log det of the latent posterior
    covariance), ``route_cost`` and ``routes`` ``(time, stop)`` (the route flown, padded with
    -1); for a fleet also ``route_robot`` ``(time, stop)`` and ``robot_cost`` ``(time,
    robot)``, with ``replan_every`` ``n_replans``. The attrs record the method, the budget(s),
    start(s) and the path model (:func:`path_attrs`).
    """
    return _simulate_campaign(model, test_data, start, budget, method=method, temporal=temporal,
                              replan=replan, seed=seed, spatial=spatial, path=path,
                              replan_every=replan_every, paper=paper, criterion=criterion,
                              cost=cost, ridge=ridge, score_forecast=True)


def posterior_campaign(model: Any, test_data: xr.DataArray, start: Any, budget: Any,
                       **settings: Any) -> xr.Dataset:
    """:func:`simulate_campaign` without the morning forecast maps: the Dataset lacks
    ``mse_forecast``, every other output is the same bit for bit (``evaluate``'s campaigns,
    which score the posterior only).

    Parameters
    ----------
    model, test_data, start, budget
        As :func:`simulate_campaign`.
    method, temporal, replan, seed, spatial, path : (``**settings``) as simulate_campaign
    replan_every, paper, criterion, cost, ridge : (``**settings``) as simulate_campaign

    Returns
    -------
    xarray.Dataset
        :func:`simulate_campaign`'s Dataset without ``mse_forecast``.
    """
    return _simulate_campaign(model, test_data, start, budget, score_forecast=False, **settings)


def _simulate_campaign(
    model: Any,
    test_data: xr.DataArray,
    start: Any,
    budget: Any,
    *,
    method: str | None = None,
    temporal: Any = RECOMMENDED["temporal"],
    replan: bool = True,
    seed: Any = 0,
    spatial: bool | None = None,
    path: PathOptions | None = None,
    replan_every: int | None = None,
    paper: bool = False,
    criterion: str = "fisher",
    cost: str = "nearest-neighbor",
    ridge: float = 0.0,
    score_forecast: bool = True,
) -> xr.Dataset:
    """:func:`simulate_campaign` (the same settings and defaults), and ``score_forecast``:
    False (:func:`posterior_campaign`) builds no forecast map and leaves ``mse_forecast`` out of
    the result, every other output the same bit for bit."""
    request = PathOptions.from_kwargs(path, where="simulate_campaign")
    paper = check_flag(paper, "paper", error=PlanningError)
    if method is None:
        residual = getattr(model, "spatial_cov_", None) is not None and spatial is not False
        method = "greedy" if paper else recommended_method(residual)
    method = check_method(method)
    planner = planner_for(method, criterion=criterion, cost=cost)
    ridge = float(ridge)
    every = _check_every(replan_every, replan, planner, method)
    rng = as_generator(seed)
    dynamics, memoryless = _dynamics_for(model, temporal)
    model._check_fitted()
    region = model.region_
    if region is None:
        raise ModelError("simulate_campaign needs a model fitted on gridded (lat, lon) data")
    if not isinstance(test_data, xr.DataArray) or test_data.ndim != 3:
        raise DataError("test_data must be a (time, lat, lon) DataArray")
    tdim = test_data.dims[0]
    if tdim not in test_data.coords:
        raise DataError(f"test_data has no coordinate on its {tdim!r} dim")
    check_times(test_data[tdim], f"test_data[{tdim!r}]")
    V = region.stack(test_data).astype(np.float64)  # (T, L), checks the grid
    request = method_request(method, planner, request.resolved(region))
    if every and not request.sensor.is_point:
        raise PlanningError("replan_every replans from point samples: it does not take a "
                            f"footprint or towed sensor yet (sensor: {request.sensor.describe()})")
    fleet = Fleet.resolve(region, start, budget, request.unit)
    times = test_data[tdim].values
    # the belief forecast to the first test snapshot (DataError if it is not after the fit's)
    state = MonitorState.from_model(model, times[0], dynamics=dynamics,
                                    memoryless=memoryless, spatial=spatial, online=False)

    T = V.shape[0]
    out = {name: np.full(T, np.nan) for name in (
        "mse", "mse_heldout", "mse_forecast", "coverage68", "coverage95", "information",
        "logdet_cov", "route_cost") if score_forecast or name != "mse_forecast"}
    n_obs = np.zeros(T, dtype=np.int64)
    n_replans = np.zeros(T, dtype=np.int64)
    robot_cost = np.full((T, fleet.n_robots), np.nan)
    routes: list[tuple[np.ndarray, np.ndarray]] = []
    plan = last = None
    for i in range(T):  # days, in time order
        t = state.plan_time(times[i])  # coerced to the filter's time kind
        if replan or plan is None:
            last = _plan_day(state, t, planner, fleet, request, rng, ridge, last)
            plan = last[0]
        information = float(getattr(plan, "information", np.nan))
        forecast = state.belief(t).predict()[0] if score_forecast else None
        if every:
            flown, cells, n_replans[i] = _fly_replanning(state, plan, t, V[i], every,
                                                         planner.criterion)
            vals = V[i, cells]
        elif plan.sensor.is_point:
            flown = plan
            cells = np.unique(np.asarray(plan.cells, dtype=np.int64))
            vals = V[i, cells]
            state.assimilate((cells, vals), t)
        else:  # a footprint / towed sensor: one averaged value per observation
            flown = plan
            rows, vals = plan_observations(plan, V[i])
            state.assimilate_rows(rows, vals, t, errors=plan.sensor.errors)
            cells = observed_cells(rows)
        post = state.posterior
        n_obs[i] = int(np.count_nonzero(np.isfinite(vals)))
        truth = V[i]
        observed = np.isfinite(truth)
        mean, _, pstd = post.predict_all()  # one kriging pass for both maps
        err = (mean - truth) ** 2
        if observed.any():
            out["mse"][i] = float(np.mean(err[observed]))
            if forecast is not None:
                out["mse_forecast"][i] = float(np.mean((forecast - truth)[observed] ** 2))
        held = observed.copy()
        held[cells] = False
        if held.any():
            out["mse_heldout"][i] = float(np.mean(err[held]))
            z = np.abs(mean[held] - truth[held]) / np.maximum(pstd[held], 1e-300)
            m68, m95 = state.interval_multipliers((0.68, 0.95))  # conformal / ACI half-widths
            out["coverage68"][i] = float(np.mean(z <= m68))
            out["coverage95"][i] = float(np.mean(z <= m95))
        out["information"][i] = information
        out["route_cost"][i] = float(getattr(flown, "cost", np.nan))
        robot_cost[i] = np.asarray(flown.robot_costs, dtype=np.float64)
        if post.is_proper:
            out["logdet_cov"][i] = float(np.linalg.slogdet(post.cov)[1])
        routes.append((np.asarray(flown.route, dtype=np.int64),
                       np.asarray(flown.route_robot, dtype=np.int64)))
    return _dataset(out, n_obs, n_replans, robot_cost, routes, times, fleet, request, every,
                    dict(method=method, temporal=temporal, replan=replan, seed=seed,
                         memoryless=memoryless, dynamics=dynamics))


def _padded(rows: list[np.ndarray]) -> np.ndarray:
    """``(T, width)`` int64 of the rows, padded with -1."""
    width = max((r.size for r in rows), default=0)
    out = np.full((len(rows), width), -1, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, : r.size] = r
    return out


def _dataset(out: dict, n_obs: np.ndarray, n_replans: np.ndarray, robot_cost: np.ndarray,
             routes: list, times: np.ndarray, fleet: Fleet, path: PathOptions, every: int,
             run: dict) -> xr.Dataset:
    """The campaign's Dataset over ``time`` (:func:`simulate_campaign`)."""
    ds = xr.Dataset({name: ("time", v) for name, v in out.items()}, coords={"time": times})
    ds["n_obs"] = ("time", n_obs)
    ds["routes"] = (("time", "stop"), _padded([r for r, _ in routes]))
    ds["routes"].attrs["long_name"] = "route cell indices, padded with -1"
    if "mse_forecast" in ds:
        ds["mse_forecast"].attrs["long_name"] = (
            "MSE of the forecast map, before the day's samples")
    for level in ("68", "95"):
        ds[f"coverage{level}"].attrs["long_name"] = (
            f"fraction of held-out observed cells in the central {level} % predictive interval")
    ds["route_cost"].attrs["units"] = path.unit
    if fleet.is_fleet:
        ds["route_robot"] = (("time", "stop"), _padded([r for _, r in routes]),
                             {"long_name": "robot of each route entry (-1: padding)"})
        ds["robot_cost"] = (("time", "robot"), robot_cost,
                            {"long_name": "each robot's route cost", "units": path.unit})
    if every:
        ds["n_replans"] = ("time", n_replans)
    temporal, dynamics = run["temporal"], run["dynamics"]
    one = not fleet.is_fleet
    ds.attrs.update(method=run["method"], temporal=str(temporal), replan=int(bool(run["replan"])),
                    budget=float(fleet.budgets[0]) if one else list(fleet.budgets),
                    start=int(fleet.starts[0]) if one else list(fleet.starts),
                    seed=str(run["seed"]),
                    dynamics="memoryless" if run["memoryless"] else dynamics.kind,
                    replan_every=int(every), **path_attrs(path, fleet.n_robots))
    if not isinstance(temporal, (str, type(None))):
        ds.attrs["temporal"] = "given"
    return ds

