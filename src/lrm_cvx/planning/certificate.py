"""The plan certificate: an upper bound on the Fisher information of every feasible plan.

A plan's cells are either the greedy's forced initial set or the stops (and, with
``sense_along``, the pass-through cells) of a route within the budget of its path model.
:func:`plan_bound` turns the path model into what the relaxation of
:mod:`lrm_cvx.planning.dopt` needs: the candidate cells (every cell some feasible route can
observe, :mod:`~lrm_cvx.planning.families`), a count limit ``n_max`` (budget, smallest spacing,
stop cost) and nested distance limits (how many cells a route of bounded length can hold far
from its start or from its midpoint, :mod:`~lrm_cvx.planning.cover`). Fleets add their robots'
counts over the union of their candidates; a static placement is the count-only bound over all
valid cells. A towed sensor's certificate is :mod:`~lrm_cvx.planning.towed_certificate`'s, a
variance criterion's :mod:`~lrm_cvx.planning.variance_certificate`'s; every one returns a
:class:`~lrm_cvx.planning.plan_certificate.PlanCertificate`. See ``docs/certificate.md`` §4-6
and §10 for the proofs.

Data flows one way: paths -> greedy / baselines -> Plan -> certificate. This module imports
neither the planner nor :class:`~lrm_cvx.planning.plan.Plan` at module level.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Literal

import numpy as np

from .._validation import as_factor_matrix
from ..errors import PlanningError, SolverError
from .cover import (
    check_plan_feasible,
    check_plan_limits,
    limited_relaxation,
    midpoint_cover,
    start_limits,
)
from .dopt import _check_n_ridge, _chol, _inv_lower, _leverages, _moment, top_sum
from .families import family, path_spec
from .plan_certificate import PlanCertificate, chosen_criterion, gap_and_ratio
from .request import PathOptions
from .sensors import footprint_factors
from .terms import prior_terms
from .towed_certificate import towed_certificate
from .variance_certificate import variance_certificate

__all__ = ["PlanCertificate", "plan_bound"]


# ----------------------------------------------------------------------------- plan bound
def plan_bound(
    Y: Any,
    region: Any,
    start: Any,
    budget: Any,
    *,
    ridge: float = 0.0,
    plan: Any = None,
    path: PathOptions | None = None,
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL",
    tol: float = 1e-3,
    tighten: bool | dict[str, int] = True,
    refine: bool | dict[str, Any] = True,
    path_aware: bool | str | dict[str, Any] = False,
    criterion: str | None = "fisher",
    prior: Any = None,
) -> PlanCertificate:
    """Upper bound on the Fisher information of every plan from ``start`` within ``budget``.

    Every plan of ``plan_greedy`` (any cost, since each is the length of a path from the start
    through all the plan's cells), ``transect`` and ``random_walk`` is either the greedy's forced
    initial set (start plus its k-1 nearest cells) or the cells visited by a path from the start
    of length ``<= budget``. The latter are at most ``n_max = floor(budget / d_min) + 1`` cells
    within ``budget`` of the start (``d_min`` = the smallest distance between two candidate
    cells, 1 grid unit for ``metric="grid"``), so ``bound = max(I(initial set), relaxation)``.

    With ``tighten=True`` (default) the relaxation also gets the path's *distance limits*: at
    most ``floor((budget - r) / d_min) + 1`` cells at distance ``>= r`` from the start, for a
    ladder of radii ``r``; and for ``metric="grid"`` (and ``budget >= 2``) the *midpoint cover*:
    the path's midpoint lies in one of the squares of side ``budget / (2 cover)`` that tile the
    disk of radius ``budget / 2`` around the start, the plan then lies within ``budget / 2`` of
    that square and holds at most ``floor(budget - 2 s) + 2`` cells at distance ``>= s`` from it.
    The bound is the maximum of one relaxation per square; the square with the largest bound is
    split into four while at most ``max_pieces`` relaxations have been solved. ``tighten`` may
    be a dict ``{"cover": 2, "max_pieces": 40}`` (the defaults; integers >= 1) to set those two;
    ``tighten=False`` gives the plain disk relaxation. When the plan is given, the
    submodularity online bound is computed too and the smaller one is kept. Proofs in
    docs/certificate.md.

    **Every path model** (docs/certificate.md §10). ``path`` (a
    :class:`~lrm_cvx.planning.request.PathOptions`) describes the route as in
    :func:`~lrm_cvx.planning.plan_greedy` (``budget`` in the path model's unit: grid units, km
    or hours); ``start`` and ``budget`` may be lists (a fleet); ``start=None`` without a plan
    bounds fixed sensors: every placement of ``budget`` (an integer >= 1) cells anywhere in the
    region. When a ``plan`` with a ``path`` description is given, its path model is used and
    ``path`` is ignored. The candidates are the cells
    some feasible route can observe (shortest travel distances: ``d(start, x) + d(x, back) +
    stop costs <= budget``, ``back`` = nothing, the start of a closed tour or the ``end``); the
    count limit uses the smallest spacing and the stop cost; the start's distance limits use the
    path model's travel distances; the midpoint cover needs ``metric="grid"``. A fleet's bound
    is the count-only relaxation over the union of its robots' candidates with their count
    limits summed (valid, looser than one robot's).

    **Sensors** (docs/certificate.md §11): with a footprint sensor (``"square"`` /
    ``"disc"``, the plan's or ``sensor=``) each stop observes its footprint's averaged row, a
    function of the stop alone, so the same relaxation bounds it with every cell's whitened
    footprint row (:func:`~lrm_cvx.planning.sensors.footprint_factors`) in place of its
    column of ``Y``; ``information`` is then the plan's footprint Fisher information (noise 1
    per cell, as the planner's). A towed (leg-average) sensor's observations depend on the
    legs, not on the stops (§12): by Cauchy-Schwarz each is at most the sum of ``y y^T`` over
    its leg's cells (``1 / m`` of it for ``errors="shared"``), so the bound is the count-only
    relaxation with weights up to the observations' count and a total of the leg cells a
    route within the budget can pass (``towed``: those two limits). For one robot it adds
    the leg cells' distance limits from the start and, on straight legs (``tighten=True``),
    the midpoint cover with Lemma 10's limits (``cover``, ``max_pieces`` as for points). It
    covers every route within the budget (a plan whose forced initial cells exceed it is
    refused), with no online bound or refinement.

    The bound is on the **Fisher** information (``criterion="fisher"``). For a plan chosen for
    another criterion (``plan.criterion`` ``"a-optimal"`` / ``"gp-variance"``, or
    ``plan.posterior``) the certificate reports the plan's Fisher information but
    ``gap = volume_ratio = nan``.

    **Gap split.** For a Fisher greedy plan (``metric="grid"``) the certificate also reports
    ``greedy_information`` (the plan before refinement), ``refined_information`` (after
    :func:`~lrm_cvx.planning.refine.refine`: the plan's own refinement when it was refined,
    else one run here when ``refine`` is true; a dict is passed to it as keyword arguments),
    ``plan_slack = refined - greedy`` and ``bound_slack = bound - refined``; the online bound
    at the refined plan is used as well (valid at any set). Refinement exists for the paper's
    path model only: for every other model these are None.

    ``path_aware=True`` (opt-in, grid metric, the paper's path model) also computes the
    path-aware relaxation of :mod:`lrm_cvx.planning.relaxation` (a dict passes options to
    ``path_relaxation_bound``) and keeps the smaller valid bound (``path_bound``); if it
    fails, a warning says the disk bound is used. ``path_aware="walk"`` (or a dict with
    ``"method": "walk"``) uses the king-walk relaxation ``walk_relaxation_bound`` instead
    (tighter on small regions; its columns are dense, so not for paper scale).

    **Variance criteria** (docs/certificate.md, "Variance criteria"): ``criterion=
    "gp-variance"`` or ``"a-optimal"`` bounds that criterion instead, the variance removed
    (the data's unit squared) by any plan of the same path model, over the same candidates,
    count and distance limits and midpoint cover, by the Frank-Wolfe dual bound of
    :mod:`lrm_cvx.planning.varbound`. ``prior`` is the criterion's prior as the planner read it
    (a :class:`~lrm_cvx.planning.terms.PriorTerms` or a belief: ``prior_precision``,
    ``noise_var``, ``target_weights``; for gp-variance ``spatial_cov``, ``prior_cov``,
    ``targets``); default: the terms the plan was planned with. Point sensors only; no online
    bound, no ``path_aware``; ``gap = bound - value`` and ``relative_gap = gap / bound``;
    ``greedy_information`` / ``refined_information`` are the greedy's route's and the kept
    route's values when the planner compared rival routes (``plan.rivals``).
    """
    from ..information import fisher_information
    from ..region import check_region

    region = check_region(region)
    Y = as_factor_matrix(Y, region)
    k, L = Y.shape
    _, ridge = _check_n_ridge(1.0, ridge)
    tighten, cover, max_pieces = _check_tighten(tighten)
    terms = None if prior is None else {key: v for key, v in prior_terms(prior).items()
                                        if v is not None}
    static = plan is None and start is None
    request = PathOptions.from_kwargs(path, where="plan_bound")
    plan_sensor = getattr(getattr(plan, "path", None), "sensor", None)
    sensor = plan_sensor if plan_sensor is not None else request.sensor
    spec = path_spec(region, plan, start, budget, request, "static" if static else "path",
                     budget if static else None)
    bounded = _bound_criterion(criterion)
    if bounded != "fisher":
        if not sensor.is_point:
            raise PlanningError(f"the {bounded} bound covers point sensors only, not "
                                f"sensor={sensor.describe()!r} (criterion='fisher' bounds it)")
        if path_aware:
            raise PlanningError(f"path_aware bounds the Fisher criterion only, not {bounded!r}")
        return variance_certificate(Y, region, spec, plan, bounded, terms, ridge,
                                    cover if tighten else 0, max_pieces, tighten, tol, solver)
    if sensor.is_leg:  # the observations depend on the legs (docs §12)
        if path_aware:
            warnings.warn("path_aware bounds point stops: a towed sensor's certificate is "
                          "docs/certificate.md §12's", UserWarning, stacklevel=2)
        return towed_certificate(Y, region, spec, sensor, plan, ridge,
                                 {"solver": solver, "tol": tol}, cover if tighten else 0,
                                 max_pieces)
    fam = family(spec, region, k)
    if sensor.has_footprint:  # each cell's footprint row replaces its own (docs §11)
        Y = _footprint_columns(Y, region, sensor, fam, plan, path_aware)
    cand, n_max, init = fam.cand, fam.n_max, fam.init
    # a fleet's certificate reports the total budget, as Plan.budget does
    budget0 = float(sum(spec.budgets)) if spec.budgets else float(spec.n_sensors)
    start0 = spec.starts[0] if spec.starts else -1
    metric = spec.metric if spec.kind == "path" else "sensors"
    init_info = float(fisher_information(Y, init, ridge=ridge)) if init.size else -math.inf
    opts = {"solver": solver, "tol": tol}
    leaves: list[tuple[float, float, float, float]] = []
    start_lim, start_lv = start_limits(fam, tighten, n_max, cand)
    if tighten and fam.cover_budget is not None and fam.cover_budget >= 2.0:
        centre = region.grid_index[spec.starts[0]].astype(np.float64)
        relax, leaves = midpoint_cover(
            Y, region, cand, start_lv, start_lim, centre, fam.cover_budget, n_max, ridge,
            cover, max_pieces, init_info, opts,
        )
    else:
        levels, caps = ([start_lv], [start_lim[1]]) if start_lim else ([], [])
        relax = limited_relaxation(Y, cand, n_max, levels, caps, ridge, **opts)
    bound = max(init_info, relax.value)
    path_value = None
    if path_aware:
        if fam.paper:
            path_value = _path_aware(Y, region, spec.starts[0], budget0, ridge, metric,
                                     path_aware)
        else:
            warnings.warn("path_aware=True needs the paper's path model (grid, open, one "
                          "robot); the disk bound is used", UserWarning, stacklevel=2)
        if path_value is not None:
            bound = min(bound, max(init_info, path_value))

    information = gap = ratio = online = None
    greedy_info = refined_info = n_moves = None
    if plan is not None:
        cells = np.asarray(plan.cells, dtype=np.int64)
        check_plan_feasible(cells, init, cand, n_max, plan, fam.budget_text)
        check_plan_limits(cells, init, region, fam.dist, start_lim, leaves,
                          fam.cover_budget, n_max, plan)
        information = float(fisher_information(Y, cells, ridge=ridge))
        online = _online_bound(Y, cells, cand, n_max, ridge, information)
        if online is not None:
            bound = min(bound, max(init_info, online))
        plan_criterion = chosen_criterion(plan)
        greedy_info, refined_info, n_moves, rcells = _refined(
            plan, Y, region, refine if fam.paper and sensor.is_point else False, metric,
            plan_criterion,
            information)
        if refined_info is not None and refined_info > information:
            online_r = _online_bound(Y, rcells, cand, n_max, ridge, refined_info)
            if online_r is not None:
                bound = min(bound, max(init_info, online_r))
        if plan_criterion in (None, "fisher"):
            gap, ratio = gap_and_ratio(bound, information, k)
        else:  # a bound on Fisher information says nothing of another criterion's gap
            gap, ratio = math.nan, math.nan
    return PlanCertificate(
        bound=float(bound), information=information, gap=gap, volume_ratio=ratio,
        n_max=int(n_max), n_candidates=int(cand.size), k=k, start=int(start0),
        budget=float(budget0), ridge=ridge, metric=metric, initial_information=init_info,
        relaxation=relax, online_bound=online, tightened=bool(tighten and (
            start_lim is not None or bool(leaves))), leaves=tuple(leaves),
        criterion="fisher", plan_criterion=chosen_criterion(plan) if plan is not None else None,
        greedy_information=greedy_info, refined_information=refined_info,
        refine_moves=n_moves, path_bound=path_value, path=spec.summary(),
    )


def _bound_criterion(criterion: Any) -> str:
    """The criterion a certificate bounds, canonical: ``"fisher"`` (None), ``"a-optimal"`` or
    ``"gp-variance"``; PlanningError otherwise."""
    from ..information import CRITERION_REGISTRY
    from .varbound import VARIANCE_CRITERIA

    if criterion is None:
        return "fisher"
    try:
        name = CRITERION_REGISTRY.canonical(criterion, "criterion")
    except (PlanningError, TypeError):
        name = None
    if name not in ("fisher", *VARIANCE_CRITERIA):
        raise PlanningError("criterion must be 'fisher', 'a-optimal' or 'gp-variance' (the "
                            f"criteria a certificate bounds), got {criterion!r}")
    return name


def _check_tighten(tighten: Any) -> tuple[bool, int, int]:
    """``(tighten, cover, max_pieces)`` of :func:`plan_bound`'s ``tighten``: True / False (the
    default cover 2 and 40 pieces) or a dict of ``cover`` and ``max_pieces`` (integers >= 1)."""
    opts = {"cover": 2, "max_pieces": 40}
    if isinstance(tighten, dict):
        unknown = sorted(set(tighten) - set(opts))
        if unknown:
            raise PlanningError(f"tighten takes the keys {sorted(opts)}, got {unknown}")
        opts.update(tighten)
        tighten = True
    elif not isinstance(tighten, (bool, np.bool_)):
        raise PlanningError(f"tighten must be True, False or a dict of cover and max_pieces, "
                            f"got {tighten!r}")
    for name, value in opts.items():
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                or value < 1:
            raise PlanningError(f"{name} must be an integer >= 1, got {value!r}")
    return bool(tighten), int(opts["cover"]), int(opts["max_pieces"])


def _footprint_columns(Y: np.ndarray, region: Any, sensor: Any, fam: Any, plan: Any,
                       path_aware: Any) -> np.ndarray:
    """``Y`` with the whitened footprint row (:func:`~lrm_cvx.planning.sensors.
    footprint_factors`) in place of the column of every cell the certificate reads: the
    family's candidates and initial cells and the plan's stops (every cell for a path-aware
    bound, which walks the grid). The other columns are zero and never read, so the
    footprint matrix grows with the cells a plan may visit, not with the region."""
    if path_aware:
        return footprint_factors(Y, region, sensor)
    parts = [fam.cand, fam.init]
    if plan is not None:
        parts.append(np.asarray(plan.cells, dtype=np.int64))
    cells = np.unique(np.concatenate(parts).astype(np.int64))
    U = np.zeros_like(Y, dtype=np.float64)
    if cells.size:
        U[:, cells] = footprint_factors(Y, region, sensor, cells=cells)
    return U


def _path_aware(Y: np.ndarray, region: Any, start: int, budget: float, ridge: float,
                metric: str, opts: Any) -> float | None:
    """The path-aware relaxation's dual bound, or None (with a warning) when it fails."""
    from . import relaxation

    if metric != "grid":
        warnings.warn("path_aware=True needs metric='grid'; the disk bound is used",
                      UserWarning, stacklevel=3)
        return None
    if isinstance(opts, str) and opts != "walk":
        raise PlanningError(f"path_aware must be a bool, 'walk' or a dict, got {opts!r}")
    kw = dict(opts) if isinstance(opts, dict) else {}
    method = kw.pop("method", "walk" if opts == "walk" else "flow")
    if method not in ("walk", "flow"):
        raise PlanningError(f"path_aware method must be 'walk' or 'flow', got {method!r}")
    walk = method == "walk"
    try:
        if walk:  # the king-walk relaxation (docs/certificate.md §9, "walk relaxation")
            return float(relaxation.walk_relaxation_bound(Y, region, start, budget,
                                                          ridge=ridge, **kw).value)
        return float(relaxation.path_relaxation_bound(Y, region, start, budget, ridge=ridge,
                                                      **kw).value)
    except (PlanningError, SolverError) as exc:
        warnings.warn(f"path-aware relaxation failed ({exc}); the disk bound (looser) is used",
                      UserWarning, stacklevel=3)
        return None


def _refined(plan: Any, Y: np.ndarray, region: Any, refine: Any, metric: str,
             plan_criterion: str | None, information: float
             ) -> tuple[float | None, float | None, int | None, np.ndarray]:
    """``(greedy information, refined information, moves, refined cells)`` of a Fisher
    greedy plan, or ``(None, None, None, plan cells)`` (also for a transect that
    ``refine="rivals"`` kept: the local search refines greedy routes only)."""
    cells = np.asarray(plan.cells, dtype=np.int64)
    if plan_criterion != "fisher" or metric != "grid" or getattr(plan, "method",
                                                                 "greedy") != "greedy":
        return None, None, None, cells
    done = getattr(plan, "refinement", None) or {}
    if done:
        return float(done["information_before"]), float(information), int(done["moves"]), cells
    if refine is False or refine is None or not hasattr(plan, "cost_function"):
        return None, None, None, cells
    from .refiners import REFINERS, RefineContext  # the search registers itself

    opts = dict(refine) if isinstance(refine, dict) else {}
    better = REFINERS.get("local")(plan, dict(opts, Y=Y, region=region), RefineContext())
    moves = int(better.refinement.get("moves", 0)) if better is not plan else 0
    return (float(information), max(float(better.information), float(information)), moves,
            np.asarray(better.cells, dtype=np.int64))


def _online_bound(
    Y: np.ndarray, cells: np.ndarray, cand: np.ndarray, n_max: int, ridge: float, f_S: float
) -> float | None:
    """``f(S) + sum of the n_max largest gains log(1 + y^T M_S^-1 y)`` over candidates not in S.

    Valid for any set S with finite information because log det is monotone submodular:
    ``f(O) <= f(S u O) <= f(S) + sum_{x in O \\ S} (f(S + x) - f(S))`` and ``|O| <= n_max``.
    """
    if not math.isfinite(f_S):
        return None
    M = _moment(Y, cells, np.ones(cells.size), ridge)
    L = _chol(M)
    if L is None:
        return None
    others = np.setdiff1d(cand, cells)
    if others.size == 0:
        return f_S
    gains = np.log1p(_leverages(np.ascontiguousarray(Y[:, others]), _inv_lower(L)))
    top, _ = top_sum(gains, float(n_max))
    return f_S + top
