"""The certificate of a variance criterion (docs/certificate.md, "Variance criteria").

``plan_bound(criterion="gp-variance" | "a-optimal")``: the variance removed by any plan of the
path model, bounded over the Fisher certificate's candidates, count and distance limits and
midpoint cover, each piece by the Frank-Wolfe dual bound of :mod:`lrm_cvx.planning.varbound`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import PlanningError
from .cover import (
    check_plan_feasible,
    check_plan_limits,
    limited_relaxation,
    midpoint_cover,
    start_limits,
)
from .dopt import Polytope
from .families import family
from .plan_certificate import PlanCertificate, chosen_criterion

__all__ = ["variance_certificate"]

_TERM_KEYS = ("prior_precision", "noise_var", "target_weights", "region", "spatial_cov",
              "prior_cov", "targets", "pool")
"""The criterion terms a variance certificate reads (``prior=`` or the plan's own)."""


def variance_certificate(Y: np.ndarray, region: Any, spec: Any, plan: Any, criterion: str,
                         terms: dict[str, Any] | None, ridge: float, cover: int,
                         max_pieces: int, tighten: bool, tol: float, solver: str
                         ) -> PlanCertificate:
    """The certificate of a variance criterion (docs/certificate.md, "Variance criteria"): the
    Fisher certificate's candidates, count and distance limits and midpoint cover, each piece
    bounded by :func:`~lrm_cvx.planning.varbound.variance_relaxation`."""
    from .varbound import variance_objective, variance_relaxation

    k = Y.shape[0]
    if plan is not None:
        pY = getattr(plan, "_Y", None)
        if pY is not None and (np.shape(pY) != Y.shape or not np.array_equal(pY, Y)):
            raise PlanningError("the plan was made with another model (its Y differs from the "
                                "one given): certify it with its own model")
    if terms is None:
        terms = getattr(plan, "_terms", None) if plan is not None else None
        if terms is None and criterion == "gp-variance":
            why = "no plan gives them" if plan is None else "the plan carries none"
            raise PlanningError(f"the gp-variance bound needs the criterion's terms ({why}): "
                                "pass prior=PriorTerms(spatial_cov=..., prior_cov=...)")
        if (terms is None and plan is not None and getattr(plan, "posterior", False)
                and chosen_criterion(plan) == criterion):
            raise PlanningError(f"this {criterion} plan was planned on a posterior whose terms "
                                "it does not carry (saved without them): pass prior="
                                "PriorTerms(prior_precision=..., noise_var=...)")
    if not isinstance(terms, dict | type(None)):
        raise PlanningError(f"terms must be a dict of the criterion's terms, got {terms!r}")
    unknown = sorted(set(terms or {}) - set(_TERM_KEYS))
    if unknown:
        raise PlanningError(f"terms has unknown keys {unknown}; expected some of {_TERM_KEYS}")
    terms = dict(terms or {})
    terms["region"] = region
    fam = family(spec, region, k)
    cand, n_max, init = fam.cand, fam.n_max, fam.init
    cells = (np.asarray(plan.cells, dtype=np.int64) if plan is not None
             else np.zeros(0, np.int64))
    universe = np.unique(np.concatenate([cand, init, cells]))
    obj = variance_objective(criterion, Y, universe, ridge, terms, start=cells)

    def at(c: np.ndarray) -> np.ndarray:
        return np.searchsorted(universe, c)

    def value(c: np.ndarray) -> float:
        c = np.unique(c)
        return obj.value(at(c), np.ones(c.size))

    init_value = value(init) if init.size else -math.inf
    start_lim, start_lv = start_limits(fam, tighten, n_max, cand)
    opts = {"tol": tol, "solver": solver}

    def relax(_Y: Any, c: np.ndarray, poly: Polytope, _ridge: float, **o: Any) -> Any:
        return variance_relaxation(obj, at(c), poly, **o)

    leaves: list[tuple[float, float, float, float]] = []
    if cover and fam.cover_budget is not None and fam.cover_budget >= 2.0:
        centre = region.grid_index[spec.starts[0]].astype(np.float64)
        relaxed, leaves = midpoint_cover(Y, region, cand, start_lv, start_lim, centre,
                                          fam.cover_budget, n_max, ridge, cover, max_pieces,
                                          init_value, opts, relax)
    else:
        levels, caps = ([start_lv], [start_lim[1]]) if start_lim else ([], [])
        relaxed = limited_relaxation(Y, cand, n_max, levels, caps, ridge, relax, **opts)
    bound = max(init_value, relaxed.value)
    information = gap = greedy_v = refined_v = None
    plan_criterion = chosen_criterion(plan) if plan is not None else None
    if plan is not None:
        check_plan_feasible(cells, init, cand, n_max, plan, fam.budget_text)
        check_plan_limits(cells, init, region, fam.dist, start_lim, leaves, fam.cover_budget,
                           n_max, plan)
        information = value(cells)
        if plan_criterion in (None, criterion):
            gap = bound - information
            if -1e-9 * max(abs(bound), 1.0) <= gap < 0:  # rounding at an optimal plan
                gap = 0.0
            rivals = getattr(plan, "rivals", None) or {}
            if rivals.get("criterion") == criterion and "greedy" in rivals.get("values", {}):
                refined_v = information
                greedy_v = (information if rivals.get("chosen") == "greedy"
                            else obj.prior_total - float(rivals["values"]["greedy"]))
        else:  # a bound on another criterion says nothing of this plan's gap
            gap = math.nan
    budget0 = float(sum(spec.budgets)) if spec.budgets else float(spec.n_sensors)
    return PlanCertificate(
        bound=float(bound), information=information, gap=gap, volume_ratio=None,
        n_max=int(n_max), n_candidates=int(cand.size), k=k,
        start=int(spec.starts[0] if spec.starts else -1), budget=budget0, ridge=ridge,
        metric=spec.metric if spec.kind == "path" else "sensors",
        initial_information=float(init_value), relaxation=relaxed,
        tightened=bool(start_lim is not None or leaves), leaves=tuple(leaves),
        criterion=criterion, plan_criterion=plan_criterion, greedy_information=greedy_v,
        refined_information=refined_v, path=spec.summary())
