"""Rival routes of a finished greedy route (``plan_greedy(refine="rivals")`` and ``"lines"``).

The route returned is the one with the best value of the planner's own criterion among the
greedy's route, the four straight transects from the same start and (``"rivals"``) the greedy with
the gentler ratio ``gain / increase ** RIVAL_EXPONENT`` (docs/planning.md, rival routes). Point
sensors only, no ``sense_along``, no ``end`` cell; :func:`applies` says why not otherwise.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import PlanningError
from ..information import (
    CRITERION_REGISTRY,
    GP_BOUNDARY_TOL,
    GP_STRUCTURED_MIN_ENTRIES,
    StructuredGPVarianceOracle,
    gp_variance_value,
    make_oracle,
)
from ..recommended import RECOMMENDED
from .baselines import DIRECTIONS, transect
from .plan import Plan
from .refiners import REFINERS, RefineContext
from .request import Fleet, PathOptions

__all__ = ["LINES", "RIVALS", "RIVAL_EXPONENT", "RIVAL_NAME", "CHECKS", "applies", "lines_run",
           "lines_where_possible", "route_values", "best_of_lines", "GP_TERMS", "union_oracle",
           "forked_values"]

LINES = "lines"
"""The ``refine=`` name of the check against the four straight transects."""
RIVALS = "rivals"
"""The ``refine=`` name of the check against the transects and the gentler greedy."""
CHECKS = (LINES, RIVALS)
RIVAL_EXPONENT = 0.5
"""The gentler greedy's cost exponent (``plan_greedy(cost_exponent=)``)."""
RIVAL_NAME = f"greedy-cost^{RIVAL_EXPONENT:g}"
"""The gentler greedy's route name in ``plan.rivals["values"]``."""

_REL_TOL = 1e-9  # a rival must beat the greedy by more than this (relative): ties keep the greedy


def applies(request: PathOptions) -> str | None:
    """None when straight-line rivals can be flown under ``request``, else the reason not."""
    if not request.sensor.is_point:
        return f"the sensor is {request.sensor.describe()!r}, not a point"
    if request.sense_along:
        return "sense_along=True"
    if request.end is not None:
        return "the routes must end at a given cell (end=)"
    return None


def lines_run(request: PathOptions, *, asked: bool, refine: str = LINES) -> bool:
    """Whether the check (``refine="lines"`` or ``"rivals"``) runs under ``request``: True
    where the rivals can fly; False where they cannot and the check was only the recommended
    default (it is then dropped); a :class:`PlanningError` naming the reason when the caller
    ``asked`` for it explicitly."""
    why = applies(request)
    if why is not None and asked:
        raise PlanningError(f"refine={refine!r} cannot run: {why}")
    return why is None


def lines_where_possible(request: PathOptions | None) -> str | None:
    """``refine=`` of a recommended plan under ``request`` (None: the paper's path model): the
    recommended check (``RECOMMENDED["refine"]``) where its rivals can be flown, else None (no
    check)."""
    if RECOMMENDED["refine"] not in CHECKS:
        return None
    return RECOMMENDED["refine"] if applies(request or PathOptions()) is None else None


GP_TERMS = ("region", "spatial_cov", "prior_cov", "targets", "target_weights")
"""The greedy's oracle terms (``extra``) a gp-variance route value reads."""


def route_values(criterion: str, Y: np.ndarray, ridge: float, routes: dict[str, Any],
                 extra: dict[str, Any], base: Any = None) -> dict[str, float]:
    """``criterion``'s value of observing each route's cells (name -> ``(n,)`` cell indices;
    log det for Fisher, total posterior variance for the variance criteria) with the greedy's
    oracle terms ``extra``. The gp-variance values on the grid metric come from one structured
    oracle set up on the routes' cells and forked per route, when its picks are gathers from
    the kernel's lag table (far from the region's edge: one set-up of the whole-grid terms
    serves all routes). Otherwise each pick costs an FFT over the oracle's window, and each
    route is scored by its own exact oracle over its own, smaller window (four transects span
    a cross whose bounding box is mostly empty). In km, and wherever the dense covariances are
    as small as :func:`~lrm_cvx.information.make_oracle` holds them densely (targets plus route
    times route below ``GP_STRUCTURED_MIN_ENTRIES``), the
    dense reference scores each route. ``base``: the greedy's structured oracle on its initial
    cells (:func:`~lrm_cvx.planning.greedy.plan_greedy`), or None; when it convolves each pick
    exactly and its cells hold every route's, each route is scored by a fork of it with no
    observation on the route's cells alone
    (:meth:`~lrm_cvx.information.StructuredGPVarianceOracle.restricted`): no new set-up, the
    cells the greedy passes conditioned on are not convolved again, nor the same route on the
    next plan of that set-up (the values equal those of the routes' own exact oracles to
    rounding)."""
    sets = {name: np.unique(np.asarray(c, dtype=np.int64)) for name, c in routes.items()}
    if CRITERION_REGISTRY.canonical(criterion, "criterion") != "gp-variance":
        return {name: float(make_oracle(criterion, Y, ridge, c, **extra).value)
                for name, c in sets.items()}
    terms = {key: extra.get(key) for key in GP_TERMS}
    n_targets = (Y.shape[1] if terms["targets"] is None
                 else np.unique(np.asarray(terms["targets"], dtype=np.int64)).size)
    small = all(float(n_targets + c.size) * c.size <= GP_STRUCTURED_MIN_ENTRIES
                for c in sets.values())
    if terms["spatial_cov"].metric != "grid" or small:
        return {name: gp_variance_value(Y, terms["region"], terms["spatial_cov"],
                                        terms["prior_cov"], c, terms["targets"],
                                        terms["target_weights"]) for name, c in sets.items()}
    if (isinstance(base, StructuredGPVarianceOracle) and not base.uses_lag_table
            and all(base.covers(c) for c in sets.values())):
        out = {}
        for name, cells in sets.items():  # a route's fork on its own cells
            out.update(forked_values(base.restricted(cells), {name: cells}))
        return out
    base = union_oracle(Y, sets, terms)
    if not base.uses_lag_table:  # exact per-pick FFTs: each route over its own window
        return {name: float(StructuredGPVarianceOracle(Y, cells, pool=cells, **terms).value)
                for name, cells in sets.items()}
    return forked_values(base, sets)


def union_oracle(Y: np.ndarray, sets: dict[str, np.ndarray],
                 terms: dict[str, Any]) -> StructuredGPVarianceOracle:
    """A structured gp-variance oracle with no observations, set up on the union of ``sets``
    (name -> sorted cell indices; ``terms``: the oracle's region, covariances and targets)."""
    union = np.unique(np.concatenate(list(sets.values())))
    return StructuredGPVarianceOracle(Y, [], pool=union, boundary_tol=GP_BOUNDARY_TOL, **terms)


def forked_values(base: StructuredGPVarianceOracle,
                  sets: dict[str, np.ndarray]) -> dict[str, float]:
    """Each set's total posterior variance from ``base`` (:func:`union_oracle`) forked per set
    and conditioned on its cells."""
    out = {}
    for name, cells in sets.items():
        oracle = base.fork()
        for c in cells.tolist():
            oracle.add(c)
        out[name] = float(oracle.value)
    return out


def best_of_lines(plan: Plan, Y: np.ndarray, region: Any, fleet: Fleet, request: PathOptions,
                  *, criterion: str, ridge: float, extra: dict[str, Any],
                  others: dict[str, Plan] | None = None, refine: str = LINES,
                  base: Any = None) -> Plan:
    """``plan`` (a greedy route) or the rival that is strictly better under ``criterion``
    (``extra``: the greedy's oracle terms): the straight transects from its starts and the
    ``others`` given (name -> plan; the gentler greedy of ``refine="rivals"``). The plan
    returned records the comparison in ``plan.rivals``: ``{"criterion", "values"`` (route name
    -> value), ``"chosen"``, ``"cost_function"`` (the greedy's, which a replan of a kept
    transect plans with), ``"refine"`` (the check, which a replan repeats)``}``; a transect
    keeps its ``method`` (``"transect-down"``, ...) and its ``cost_function`` (``"steps"``).
    ``base``: the greedy's oracle on its initial cells, shared with the routes' values
    (:func:`route_values`)."""
    lines_run(request, asked=True, refine=refine)
    maximize = CRITERION_REGISTRY.get(criterion, "criterion").maximize
    sign = 1.0 if maximize else -1.0
    plans = {"greedy": plan, **(others or {})}
    for d in DIRECTIONS:
        plans[f"transect-{d}"] = transect(region, fleet, None, d, Y=Y, ridge=ridge, path=request)
    values = route_values(criterion, Y, ridge, {name: p.cells for name, p in plans.items()},
                          extra, base=base)
    best = "greedy"
    for name, v in values.items():
        margin = _REL_TOL * max(1.0, abs(values[best]))
        if sign * (v - values[best]) > margin:
            best = name
    chosen = plans[best]
    if best != "greedy":  # the criterion it was chosen by, as the greedy's plan would say
        chosen.criterion, chosen.posterior = plan.criterion, plan.posterior
    chosen.rivals = {"criterion": criterion, "values": values, "chosen": best,
                     "cost_function": plan.cost_function, "refine": refine}
    return chosen


def _check_against(name: str) -> Callable[[Plan, dict[str, Any], RefineContext], Plan]:
    """The refiner ``name`` (:data:`LINES` or :data:`RIVALS`) of :data:`REFINERS`: the greedy's
    route or its best rival (:func:`best_of_lines`); ``"rivals"`` adds the gentler greedy."""
    def check(plan: Plan, options: dict[str, Any], context: RefineContext) -> Plan:
        others = {}
        if name == RIVALS and context.rival is not None:
            others[RIVAL_NAME] = context.rival(RIVAL_EXPONENT)
        return best_of_lines(plan, context.Y, context.region, context.fleet, context.request,
                             criterion=context.criterion, ridge=context.ridge,
                             extra=context.extra, others=others, refine=name,
                             base=context.base)
    return check


REFINERS.register(LINES, _check_against(LINES), description="the route or the straight "
                  "transect from its start that the plan's criterion prefers")
REFINERS.register(RIVALS, _check_against(RIVALS), description="as 'lines', with the greedy "
                  f"of cost exponent {RIVAL_EXPONENT:g} as one more rival")
