"""Campaigns: plan, observe, assimilate and score day after day (issue 13, step 4).

:func:`simulate_campaign` replays a field campaign on held-out snapshots: for each snapshot in
time order the filter (:class:`~lrm_cvx.monitor.MonitorState`) forecasts, the planner plans
with the forecast as its prior, the true snapshot is observed at the plan's cells, the
observations are assimilated and the map is predicted and scored. ``temporal=None`` runs the
memoryless model (every day's prior is the empirical prior) through the same loop, so the two
compare on the same footing.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import xarray as xr

from ._validation import as_generator, check_positive
from .errors import DataError, ModelError
from .glrm.dynamics import check_times, temporal_value
from .glrm.dynamics import estimate as estimate_dynamics
from .monitor import MonitorState

__all__ = ["simulate_campaign"]

_Z68 = 0.9944578832097535  # central 68 % interval of a standard normal
_Z95 = 1.959963984540054  # central 95 %


def _dynamics_for(model: Any, temporal: Any) -> tuple[Any, bool]:
    """``(dynamics, memoryless)``: the model's ``dynamics_`` when it is of kind ``temporal``,
    else estimated from ``X_`` (the model is not modified)."""
    from .glrm.dynamics import Dynamics

    if isinstance(temporal, Dynamics):
        return temporal, False
    temporal = temporal_value(temporal)
    if temporal is None:
        return None, True
    if temporal == "auto":  # the model's own validated choice (glrm/selection.py)
        if getattr(model, "selection_", None) is None:
            raise ModelError("temporal='auto' campaigns need a model fitted with "
                             "GLRM(temporal='auto') (its choice is validated on the training "
                             "snapshots)")
        dyn = model.dynamics_
        return dyn, dyn is None
    dyn = getattr(model, "dynamics_", None)
    if dyn is not None and dyn.kind == temporal:
        return dyn, False
    X = model.X_
    times = X[X.dims[1]] if isinstance(X, xr.DataArray) else np.arange(model.X.shape[1])
    return estimate_dynamics(temporal, model.X, times), False


def _plan_day(state: MonitorState, method: str, start: int, budget: float,
              rng: np.random.Generator, options: dict) -> Any:
    """One day's plan by the method's planner (:data:`~lrm_cvx.planning.planners.
    METHOD_REGISTRY`): a planner on the model's belief (the ``greedy:<criterion>`` methods)
    plans on the state's forecast, with the other ``options`` of ``plan_greedy``; the paper's
    greedy and the baselines on the paper's path model."""
    from .planning import plan_greedy
    from .planning.planners import planner_for
    from .planning.request import Fleet

    model = state.model
    Y, region = model.Y, model.region_
    cost = options.get("cost", "nearest-neighbor")
    ridge = float(options.get("ridge", 0.0))
    planner = planner_for(method, criterion=options.get("criterion", "fisher"), cost=cost)
    if getattr(planner, "model_prior", False):
        kw = state.planner_kwargs(criterion=planner.criterion)
        extra = {k: v for k, v in options.items() if k not in ("cost", "ridge", "criterion")}
        return plan_greedy(Y, region, start, budget, criterion=planner.criterion, cost=cost,
                           ridge=ridge, progress=False, initial=planner.initial, **kw, **extra)
    return planner.plan(Y, region, Fleet.resolve(region, start, budget), rng=rng, ridge=ridge)


def simulate_campaign(
    model: Any,
    test_data: xr.DataArray,
    start: Any,
    budget: float,
    *,
    method: str = "greedy:gp-variance",
    temporal: str | None = "ar1",
    replan: bool = True,
    seed: Any = 0,
    spatial: bool | None = None,
    **planner_options: Any,
) -> xr.Dataset:
    """Replay a campaign over the snapshots of ``test_data`` ``(time, lat, lon)``.

    ``model``: a fitted GLRM with a region (``test_data`` on its grid, its times after the
    model's last fitted time, sorted and unique). ``start``: a cell index or ``(lat, lon)``.
    ``method``: any method of :data:`~lrm_cvx.planning.planners.METHOD_REGISTRY`
    (``"greedy:fisher"``, ``"greedy:a-optimal"``, ``"greedy:gp-variance"`` plan with the
    filter's forecast as prior; ``"greedy"``, the transects and ``"random"`` ignore it).
    ``temporal``: None (memoryless), ``"ar1"`` or ``"seasonal"`` (the model's ``dynamics_`` when
    of that kind, else estimated from ``X_``), or a :class:`~lrm_cvx.glrm.dynamics.Dynamics`
    (e.g. the true dynamics of a planted field, in the model's latent coordinates).
    ``replan=False`` plans once, on the first day, and flies that route every day.
    ``planner_options``: ``cost``, ``ridge``, ``criterion`` (for ``"greedy"``) and other
    :func:`~lrm_cvx.planning.plan_greedy` options. ``spatial``: use the model's spatial residual
    (None: when it has one).

    Each day: forecast, plan, observe the true snapshot at the plan's cells (cells it lacks
    give no observation), assimilate, predict. Returns a Dataset over ``time`` with ``mse``
    (over the snapshot's observed cells, like ``evaluate``), ``mse_heldout``, ``coverage68``,
    ``coverage95`` (fraction of the observed cells *not sampled* inside the central 68 % / 95 %
    predictive interval, ``mean +- z * predictive_std``), ``n_obs``, ``information`` (the
    plan's criterion value), ``logdet_cov`` (log det of the latent posterior covariance),
    ``route_cost`` and ``routes`` ``(time, stop)`` (the plan's route, padded with -1).
    """
    from .planning.planners import check_method

    method = check_method(method)
    budget = check_positive(budget, "budget")
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
    start_cell = region.resolve_cell(start, "start")
    state = MonitorState.from_model(model, dynamics=dynamics, memoryless=memoryless,
                                    spatial=spatial)
    times = test_data[tdim].values
    state._check_order(state._coerce(times[0], f"test_data[{tdim!r}]"), force=False)

    T = V.shape[0]
    out = {name: np.full(T, np.nan) for name in (
        "mse", "mse_heldout", "coverage68", "coverage95", "information", "logdet_cov",
        "route_cost")}
    n_obs = np.zeros(T, dtype=np.int64)
    routes: list[np.ndarray] = []
    plan = None
    for i in range(T):  # days, in time order
        t = state._coerce(times[i])
        if replan or plan is None:
            state_for_plan = state
            if state.observed:  # plan against the forecast for day t
                state_for_plan = _positioned(state, t)
            plan = _plan_day(state_for_plan, method, start_cell, budget, rng, planner_options)
        cells = np.unique(np.asarray(plan.cells, dtype=np.int64))
        vals = V[i, cells]
        state.assimilate((cells, vals), t)
        post = state.posterior
        n_obs[i] = int(np.count_nonzero(np.isfinite(vals)))
        truth = V[i]
        observed = np.isfinite(truth)
        mean, _, pstd = post.predict_all()  # one kriging pass for both maps
        err = (mean - truth) ** 2
        if observed.any():
            out["mse"][i] = float(np.mean(err[observed]))
        held = observed.copy()
        held[cells] = False
        if held.any():
            out["mse_heldout"][i] = float(np.mean(err[held]))
            z = np.abs(mean[held] - truth[held]) / np.maximum(pstd[held], 1e-300)
            out["coverage68"][i] = float(np.mean(z <= _Z68))
            out["coverage95"][i] = float(np.mean(z <= _Z95))
        out["information"][i] = float(getattr(plan, "information", np.nan))
        out["route_cost"][i] = float(getattr(plan, "cost", np.nan))
        if post.is_proper:
            out["logdet_cov"][i] = float(np.linalg.slogdet(post.cov)[1])
        routes.append(np.asarray(plan.route, dtype=np.int64))
    width = max((r.size for r in routes), default=0)
    R = np.full((T, width), -1, dtype=np.int64)
    for i, r in enumerate(routes):
        R[i, : r.size] = r
    coords = {"time": times}
    ds = xr.Dataset({name: ("time", v) for name, v in out.items()}, coords=coords)
    ds["n_obs"] = ("time", n_obs)
    ds["routes"] = (("time", "stop"), R)
    ds["routes"].attrs["long_name"] = "route cell indices, padded with -1"
    ds["coverage68"].attrs["long_name"] = "fraction of held-out observed cells in mean +- 1 std"
    ds["coverage95"].attrs["long_name"] = "fraction of held-out observed cells in mean +- 1.96 std"
    ds.attrs.update(method=method, temporal=str(temporal), replan=int(bool(replan)),
                    budget=budget, start=int(start_cell), seed=str(seed),
                    dynamics="memoryless" if memoryless else dynamics.kind)
    if not isinstance(temporal, (str, type(None))):
        ds.attrs["temporal"] = "given"
    return ds


def _positioned(state: MonitorState, t: Any) -> MonitorState:
    """A shallow view of ``state`` holding the forecast for ``t`` (not yet observed)."""
    view = MonitorState.__new__(MonitorState)
    view.__dict__.update(state.__dict__)
    view.posterior = state._propagated(t)
    view.time, view.observed = t, False
    return view
