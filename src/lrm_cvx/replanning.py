"""Replanning en route: the robot folds in what it has measured and plans the rest of its
route with the budget it has left, the same end and the same path model.

The stitched route is feasible whenever the original was; a fleet is replanned robot by robot
(docs/monitoring.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import PlanningError
from .information import fisher_information
from .planning import Plan, plan_greedy
from .planning.lines import CHECKS, LINES
from .planning.request import PathOptions
from .planning.terms import PriorTerms

__all__ = ["replan", "route_feasible", "plan_variables", "plan_from_variables"]

_TOL = 1e-9


def _done_per_robot(plan: Any, done: int | Sequence[int]) -> list[int]:
    n = plan.n_robots
    values = [done] if np.ndim(done) == 0 else list(done)
    if len(values) != n:
        raise PlanningError(f"done must give one count per robot ({n}), got {done!r}")
    out = []
    for r, k in enumerate(values):
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise PlanningError(f"done[{r}] must be an integer (route entries flown), got {k!r}")
        size = int(np.count_nonzero(plan.route_robot == r))
        if not 1 <= int(k) <= size:
            raise PlanningError(f"done[{r}] must be in [1, {size}] (robot {r}'s route has "
                                f"{size} entries, its start counts as flown), got {k}")
        out.append(int(k))
    return out


def _path_options(plan: Any) -> dict[str, Any]:
    path = plan.path
    if path.get("kind") == "static":
        raise PlanningError("a static placement has no route to replan")
    opts: dict[str, Any] = {"metric": path.get("metric", "grid"),
                            "stop_cost": float(path.get("stop_cost", 0.0) or 0.0),
                            "sense_along": bool(path.get("sense_along", False))}
    if path.get("speed") is not None:
        opts["speed"] = path["speed"]
    kind = path.get("traversable", "none")
    if kind == "valid":
        opts["traversable"] = "valid"
    elif kind == "mask":
        opts["traversable"] = plan.traversable_mask
    return opts


def replan(state: Any, plan: Any, done: int | Sequence[int], observations: Any = None, *,
           time: Any = None, criterion: str | None = None, cost: str | None = None,
           ridge: float | None = None, refine: Any = "auto", progress: bool = False) -> Any:
    """The plan with each robot's first ``done`` route entries kept (flown) and the rest
    replanned from where the robot is, after folding ``observations`` (today's measurements
    so far, any form :meth:`MonitorState.assimilate` takes) into ``state`` at ``time``.

    ``done``: route entries flown (one count for one robot, one per robot for a fleet; the
    start counts, so ``done >= 1``). ``criterion`` defaults to the original plan's, ``cost`` and
    ``ridge`` likewise. ``refine``: ``"auto"`` (default) repeats the plan's own check of its
    route against rivals (``plan.rivals["refine"]``: ``"rivals"`` for the recommended plan,
    the straight transects from where the robot is and the gentler greedy; ``"lines"``, the
    transects only; :mod:`~lrm_cvx.planning.lines`), none when the plan had none;
    ``"lines"`` / ``"rivals"`` always, None never. The check needs a route with no fixed end,
    so a robot heading for its end or home skips it. Raises PlanningError when a robot has
    spent its budget (or cannot get back to its end with what is left): nothing is changed
    then.
    """
    if refine not in ("auto", *CHECKS, None, False):
        raise PlanningError(f"refine must be 'auto', 'lines', 'rivals' or None, got {refine!r}")
    if refine == "auto":  # a plan saved before "rivals" existed was checked against lines
        refine = plan.rivals.get("refine", LINES) if plan.rivals else None
    done_r = _done_per_robot(plan, done)
    opts = _path_options(plan)
    region = state.model.region_
    if region is None:
        raise PlanningError("replanning needs a model fitted on gridded data")
    Y = state.model.Y  # (k, L) float64
    path = plan.path
    starts = [int(s) for s in (path.get("starts") or [plan.start])]
    budgets = [float(b) for b in (path.get("budgets") or [plan.budget])]
    closed, end = bool(path.get("closed")), path.get("end")
    criterion = criterion or plan.criterion or "fisher"
    # a kept transect's cost is "steps": its replan plans with the greedy's route cost
    cost = cost or plan.rivals.get("cost_function") or plan.cost_function or "nearest-neighbor"
    ridge = float(plan.ridge if ridge is None else ridge)
    pieces = []  # per robot: the flown part and where it stands
    for r, k in enumerate(done_r):
        sel = np.flatnonzero(plan.route_robot == r)
        here = int(plan.route[sel[k - 1]])
        spent = float(plan.route_cost[sel[k - 1]])
        left = budgets[r] - spent
        goal = starts[r] if closed else (None if end is None else int(end))
        finished = k == sel.size  # the whole route is flown: nothing to replan
        if not finished and (left < -_TOL or (goal is not None and goal != here
                                              and left <= _TOL)):
            unit = f" {path.get('unit')}" if path.get("unit") else ""
            raise PlanningError(f"robot {r} has spent its budget ({spent:.6g} of "
                                f"{budgets[r]:.6g}{unit}) at route entry {k - 1}: nothing "
                                "left to replan")
        pieces.append((sel[:k], here, spent, max(left, 0.0), None if finished else goal,
                       finished))
    # the certificate's terms: the day's prior before this call's observations (the belief the
    # whole route is judged under), for the replan's criterion
    day_terms = _criterion_terms(state.belief(time).information(), criterion, region)
    if observations is not None:
        if time is None:
            raise PlanningError("time is required with observations (the day they belong to)")
        state.assimilate_today(observations, time)
        time = state.time
    base = state.belief(time)
    new_plans, taken = [], []
    for _, here, _, left, goal, finished in pieces:
        if finished:
            new_plans.append(None)
            continue
        post = base
        if taken:  # the earlier robots' new stops: planned, so count them as observed
            cells = np.asarray(taken, dtype=np.int64)
            mean = post.predict(cells=cells)[0] if post.is_proper else np.zeros(cells.size)
            post = post.update(cells, mean)
        kw = post.information()
        if criterion != "gp-variance":
            kw = {key: v for key, v in kw.items() if key not in ("prior_cov", "spatial_cov")}
        ends: dict[str, Any] = {}
        if goal is not None:
            ends = {"closed": True} if goal == here else {"end": goal}
        check = refine if refine and "end" not in ends else None
        new = plan_greedy(Y, region, here, left, criterion=criterion, cost=cost, ridge=ridge,
                          initial="start", refine=check, progress=progress, stay=True,
                          path=PathOptions(**opts, **ends), prior=PriorTerms(**kw))
        new_plans.append(new)
        taken += [int(c) for c in new.stops if int(c) != here]
    out = _stitch(plan, pieces, new_plans, Y, region, criterion, ridge, cost)
    out._terms = day_terms
    return out


def _criterion_terms(info: dict[str, Any], criterion: str, region: Any) -> dict[str, Any]:
    """The terms of ``criterion`` a certificate reads (:func:`~lrm_cvx.planning.terms.
    oracle_terms` without the oracle's candidate pool) from a belief's ``information()``."""
    from .planning.terms import PRIOR_TERMS, oracle_terms

    t = {key: info.get(key) for key in PRIOR_TERMS}
    if criterion == "gp-variance" and t["spatial_cov"] is None:
        return {}  # the replan itself refuses this criterion
    terms = oracle_terms(criterion, region, np.empty(0, np.int64), t, None)
    terms.pop("pool", None)
    return terms


def _stitch(plan: Any, pieces: list, new_plans: list, Y: np.ndarray, region: Any,
            criterion: str, ridge: float, cost: str) -> Any:
    """One plan: each robot's flown entries, then its new route after the current cell (the
    plan's ``cost_function``: the greedy's ``cost`` the rest was planned with)."""
    route, route_cost, robot, waypoint, stops, stop_robot, costs = [], [], [], [], [], [], []
    empty = np.empty(0, np.int64)
    for r, ((flown, _, spent, *_), new) in enumerate(zip(pieces, new_plans, strict=True)):
        first_cost = float(new.route_cost[0]) if new is not None and new.route_cost.size else 0.
        tail = new.route[1:] if new is not None else empty
        route += [plan.route[flown], tail]
        route_cost += [plan.route_cost[flown],
                       spent + new.route_cost[1:] - first_cost if new is not None
                       else np.empty(0)]
        waypoint += [plan.waypoint[flown], new.waypoint[1:] if new is not None
                     else np.empty(0, bool)]
        robot.append(np.full(flown.size + tail.size, r, np.int64))
        flown_cells = set(plan.route[flown][plan.waypoint[flown]].tolist())
        old = [int(c) for c in plan.stops[plan.stop_robot == r] if int(c) in flown_cells]
        fresh = [] if new is None else [int(c) for c in new.stops if int(c) not in flown_cells]
        stops += old + fresh
        stop_robot += [r] * (len(old) + len(fresh))
        costs.append(spent + new.cost - first_cost if tail.size else spent)
    cells = list(dict.fromkeys(stops + (np.concatenate(route).tolist()
                                        if plan.path.get("sense_along") else [])))
    out = Plan.build(
        region=region, cells=cells, route=np.concatenate(route), cost=None,
        information=fisher_information(Y, cells, ridge), criterion=criterion,
        budget=plan.budget, start=plan.start, ridge=ridge, method=f"{plan.method}+replan",
        cost_function=cost, Y=Y, route_cost=np.concatenate(route_cost),
        posterior=True, path=plan.path, route_robot=np.concatenate(robot),
        waypoint=np.concatenate(waypoint), stops=stops, stop_robot=stop_robot,
        robot_costs=costs, path_models=plan._path_models)  # the same path model
    out.rivals = _rivals(new_plans, criterion)
    return out


def _rivals(new_plans: list, criterion: str) -> dict[str, Any]:
    """The robots' checks against rival routes (``plan.rivals`` of one robot; for a fleet
    the route names are prefixed ``"robot r: "``), empty when none ran."""
    checks = {r: p.rivals for r, p in enumerate(new_plans) if p is not None and p.rivals}
    if not checks:
        return {}
    if len(new_plans) == 1:
        return dict(checks[0])
    return {"criterion": criterion,
            "values": {f"robot {r}: {name}": v for r, c in checks.items()
                       for name, v in c["values"].items()},
            "chosen": ", ".join(f"robot {r}: {c['chosen']}" for r, c in checks.items()),
            "cost_function": next(iter(checks.values()))["cost_function"],
            "refine": next(iter(checks.values())).get("refine", LINES)}


def route_feasible(plan: Any, region: Any, *, tol: float = 1e-6) -> list[str]:
    """Brute-force check of a plan's routes against its own path model: what is wrong (an
    empty list when nothing is). Each robot's leg lengths are recomputed from the cell
    coordinates (grid units: Euclidean row/column steps; km: haversine; hours: km / speed),
    summed with the stop
    costs and compared with its budget; every route cell must be enterable (``traversable``);
    a closed tour must end at its start and a fixed end at ``end``."""
    from .region import EARTH_RADIUS_KM

    problems = []
    path = plan.path
    budgets = path.get("budgets") or [plan.budget]
    starts = path.get("starts") or [plan.start]
    metric = path.get("metric", "grid")
    enter = None
    if path.get("traversable") == "mask":
        m = plan.traversable_mask
        gi = region.grid_index
        enter = m[gi[:, 0], gi[:, 1]]
    stop_cost = float(path.get("stop_cost", 0.0) or 0.0)
    speed = path.get("speed")
    for r in range(plan.n_robots):
        sel = np.flatnonzero(plan.route_robot == r)
        cells = plan.route[sel]
        if metric == "grid":
            g = region.grid_index[cells].astype(float)
            legs = np.hypot(np.diff(g[:, 0]), np.diff(g[:, 1]))
        else:
            la, lo = np.radians(region.cell_lat[cells]), np.radians(region.cell_lon[cells])
            h = (np.sin(np.diff(la) / 2) ** 2
                 + np.cos(la[:-1]) * np.cos(la[1:]) * np.sin(np.diff(lo) / 2) ** 2)
            legs = 2 * EARTH_RADIUS_KM * np.arcsin(np.sqrt(np.clip(h, 0, 1)))
            if speed is not None:  # a budget in hours
                legs = legs / float(speed)
        n_stops = int(np.count_nonzero(plan.waypoint[sel]))
        total = float(legs.sum()) + stop_cost * n_stops
        if total > float(budgets[r]) * (1 + tol) + tol:
            problems.append(f"robot {r}: route length {total:.6g} > budget {budgets[r]:.6g}")
        if enter is not None and not enter[cells].all():
            problems.append(f"robot {r}: enters a no-go cell")
        if path.get("closed") and cells.size and cells[-1] != int(starts[r]):
            problems.append(f"robot {r}: a closed tour that does not end at its start")
        if path.get("end") is not None and cells.size and cells[-1] != int(path["end"]):
            problems.append(f"robot {r}: does not end at the fixed end")
    return problems


# ----------------------------------------------------------------------------- the stored plan
_PLAN_ARRAYS = ("cells", "route", "route_cost", "route_robot", "waypoint", "stops",
                "stop_robot", "robot_costs")
_PLAN_DIMS = {"cells": "plan_cell", "route": "plan_entry", "route_cost": "plan_entry",
              "route_robot": "plan_entry", "waypoint": "plan_entry", "stops": "plan_stop",
              "stop_robot": "plan_stop", "robot_costs": "plan_robot"}


def plan_variables(plan: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(variables, attributes)`` holding ``plan`` in a NetCDF file (``plan_`` prefixed, own
    dimensions): its arrays and history, its path model (the traversable mask as a
    ``(plan_lat, plan_lon)`` int8 grid), its check against rival routes (``plan.rivals``)
    and scalars. :func:`plan_from_variables` reads it back
    equal (``==``). Booleans are stored as int8, ``None`` as an absent attribute or ``-1``."""
    out: dict[str, Any] = {}
    for name in _PLAN_ARRAYS:
        v = np.asarray(getattr(plan, name))
        out[f"plan_{name}"] = ((_PLAN_DIMS[name],), v.astype(np.int8) if v.dtype == bool else v)
    for key, v in plan.history.items():
        out[f"plan_history_{key}"] = ((f"plan_pick_{key}",), np.asarray(v))
    path = dict(plan.path.items())
    mask = plan.traversable_mask
    if mask is not None:
        out["plan_traversable"] = (("plan_lat", "plan_lon"), np.asarray(mask).astype(np.int8))
    out["plan_starts"] = (("plan_robot",), np.asarray(path["starts"], dtype=np.int64))
    out["plan_budgets"] = (("plan_robot",), np.asarray(path["budgets"], dtype=np.float64))
    attrs: dict[str, Any] = {
        "plan_cost": float(plan.cost), "plan_information": float(plan.information),
        "plan_criterion": plan.criterion or "", "plan_budget": float(plan.budget),
        "plan_start": int(plan.start), "plan_ridge": float(plan.ridge),
        "plan_method": plan.method, "plan_cost_function": plan.cost_function,
        "plan_posterior": int(plan.posterior), "plan_kind": path["kind"],
        "plan_metric": path["metric"], "plan_stop_cost": float(path["stop_cost"] or 0.0),
        "plan_traversable_kind": str(path["traversable"]), "plan_closed": int(path["closed"]),
        "plan_end": -1 if path["end"] is None else int(path["end"]), "plan_unit": path["unit"],
        "plan_sense_along": int(path["sense_along"]),
        "plan_sensor": plan.sensor.spec(),
    }
    if path.get("speed") is not None:
        attrs["plan_speed"] = float(path["speed"])
    terms = getattr(plan, "_terms", None)
    if terms is not None:  # the criterion's terms, which the plan's certificate bounds
        saved = [key for key in _TERM_ARRAYS if terms.get(key) is not None]
        for key in saved:
            v = np.asarray(terms[key], dtype=np.int64 if key == "targets" else np.float64)
            out[f"plan_term_{key}"] = (tuple(f"plan_term_{key}_{i}" for i in range(v.ndim)), v)
        if terms.get("spatial_cov") is not None:
            saved.append("spatial_cov")
            attrs.update({f"plan_term_{k}": v for k, v in terms["spatial_cov"].to_attrs().items()})
        attrs["plan_terms"] = " ".join(saved) or "none"
    if plan.rivals:  # the check against rival routes: route names as a coordinate
        names = list(plan.rivals["values"])
        out["plan_rival_value"] = (("plan_rival",), np.array(
            [plan.rivals["values"][n] for n in names], dtype=np.float64))
        out["plan_rival"] = (("plan_rival",), np.array(names, dtype=str))
        attrs["plan_rivals_criterion"] = str(plan.rivals["criterion"])
        attrs["plan_rivals_chosen"] = str(plan.rivals["chosen"])
        attrs["plan_rivals_cost_function"] = str(plan.rivals["cost_function"])
        attrs["plan_rivals_refine"] = str(plan.rivals.get("refine", LINES))
    return out, attrs


def plan_from_variables(ds: Any, region: Any, Y: Any) -> Any:
    """The :class:`~lrm_cvx.planning.Plan` that :func:`plan_variables` wrote into ``ds`` (a
    Dataset), on ``region`` with the factor matrix ``Y``; None when ``ds`` holds no plan."""
    from .planning.request import PathOptions, PlanPath

    if "plan_route" not in ds:
        return None
    a = ds.attrs
    arr = {name: np.asarray(ds[f"plan_{name}"].values) for name in _PLAN_ARRAYS}
    history = {str(n)[len("plan_history_"):]: np.asarray(ds[n].values) for n in ds.data_vars
               if str(n).startswith("plan_history_")}
    kind = str(a["plan_traversable_kind"])
    end = int(a["plan_end"])
    speed = float(a["plan_speed"]) if "plan_speed" in a else None
    desc = {"kind": str(a["plan_kind"]), "metric": str(a["plan_metric"]), "speed": speed,
            "stop_cost": float(a["plan_stop_cost"]), "traversable": kind,
            "closed": bool(int(a["plan_closed"])), "end": None if end < 0 else end,
            "unit": str(a["plan_unit"]), "sense_along": bool(int(a["plan_sense_along"])),
            "starts": ds["plan_starts"].values.tolist(),
            "budgets": ds["plan_budgets"].values.tolist()}
    options = None
    if desc["kind"] != "static":
        trav: Any = None if kind == "none" else "valid"
        if kind == "mask":
            trav = np.asarray(ds["plan_traversable"].values).astype(bool)
        options = PathOptions(metric=desc["metric"], speed=speed, stop_cost=desc["stop_cost"],
                              traversable=trav, closed=desc["closed"], end=desc["end"],
                              sense_along=desc["sense_along"],
                              sensor=str(a.get("plan_sensor", "point")))
    plan = Plan.build(
        region=region, cells=arr["cells"], route=arr["route"], cost=float(a["plan_cost"]),
        information=float(a["plan_information"]), criterion=str(a["plan_criterion"]) or None,
        budget=float(a["plan_budget"]), start=int(a["plan_start"]),
        ridge=float(a["plan_ridge"]), method=str(a["plan_method"]), history=history,
        cost_function=str(a["plan_cost_function"]), Y=Y, route_cost=arr["route_cost"],
        posterior=bool(int(a["plan_posterior"])), path=PlanPath(desc, options=options),
        route_robot=arr["route_robot"], waypoint=arr["waypoint"].astype(bool),
        stops=arr["stops"], stop_robot=arr["stop_robot"], robot_costs=arr["robot_costs"])
    if "plan_rival_value" in ds:
        plan.rivals = {"criterion": str(a["plan_rivals_criterion"]),
                       "values": dict(zip([str(n) for n in ds["plan_rival"].values],
                                          ds["plan_rival_value"].values.tolist(), strict=True)),
                       "chosen": str(a["plan_rivals_chosen"]),
                       "cost_function": str(a["plan_rivals_cost_function"]),
                       "refine": str(a.get("plan_rivals_refine", LINES))}
    if "plan_terms" in a:  # a plan saved with its criterion's terms
        plan._terms = _read_terms(ds, region)
    return plan


_TERM_ARRAYS = ("prior_precision", "noise_var", "target_weights", "prior_cov", "targets")


def _read_terms(ds: Any, region: Any) -> dict[str, Any]:
    """The criterion's terms :func:`plan_variables` wrote (``plan_term_*``)."""
    from .spatial import ResidualCovariance

    keys = str(ds.attrs["plan_terms"]).split()
    terms: dict[str, Any] = {}
    for key in keys:
        if key == "spatial_cov":
            pre = "plan_term_"
            terms[key] = ResidualCovariance.from_attrs(
                {k[len(pre):]: v for k, v in ds.attrs.items() if k.startswith(pre)})
            terms["region"] = region
        elif key in _TERM_ARRAYS:
            v = np.asarray(ds[f"plan_term_{key}"].values)
            terms[key] = float(v) if v.ndim == 0 else v
    return terms
