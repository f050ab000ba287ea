"""The paper's generalized cost-benefit greedy planner (Zhang and Vorobeychik).

``plan_greedy(Y, region, start, budget)`` on a bare factor matrix is the paper's planner (Fisher
criterion, the start and its ``k - 1`` nearest cells forced, no prior: ``Y`` carries no belief);
``plan_greedy(model, start, budget)`` on a fitted GLRM is the recommended planner
(the criterion, prior and initial cells of :data:`lrm_cvx.recommended.RECOMMENDED`), and
``paper=True`` the paper's again.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import scipy.sparse as sps
from tqdm.auto import tqdm

from .._validation import as_factor_matrix, check_flag
from ..errors import ModelError, PlanningError
from ..information import (
    CRITERION_REGISTRY,
    fisher_information,
    make_oracle,
    make_row_oracle,
    row_factors,
    row_information,
)
from ..recommended import RECOMMENDED, recommended_criterion
from ..region import Region
from .lines import CHECKS, RIVAL_EXPONENT, lines_run
from .paths import path_model
from .plan import Plan, check_region
from .refiners import REFINERS, RefineContext
from .request import Fleet, PathOptions, PlanPath
from .routecost import COST_REGISTRY
from .sensors import footprint_matrix, leg_matrix
from .terms import PRIOR_TERMS, history_arrays, oracle_terms, resolve_prior, split_prior

__all__ = ["initial_cells", "plan_greedy", "check_budget", "budget_pool", "resolve_prior",
           "PRIOR_TERMS"]

_TOL = 1e-9  # budget tolerance (grid units)
_MIN_DC = 1e-12  # floor of the cost increase in the ratio (NN tours can get shorter)
_POOL_SLACK = 1e-6  # a cell farther than budget + slack from the start is never feasible


def initial_cells(region: Region, start: int, k: int) -> np.ndarray:
    """The start cell plus its ``k - 1`` nearest valid cells, start first, ``(k,)`` int64.

    Nearest by Euclidean grid distance, ties to the lowest cell index; the others are ordered
    by (distance, index). ``k`` is the model's rank: Fisher information needs ``k`` cells.
    """
    start = int(region.check_cells(start, "start"))
    k = int(k)
    if k < 1:
        raise PlanningError(f"k must be >= 1, got {k}")
    if k > region.n_cells:
        raise PlanningError(f"the region has {region.n_cells} cells, fewer than the rank k = {k}")
    g = region.grid_index
    d = g - g[start]
    key = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) * np.int64(region.n_cells) + np.arange(
        region.n_cells, dtype=np.int64
    )
    if k < region.n_cells:
        part = np.argpartition(key, k - 1)[:k]
    else:
        part = np.arange(region.n_cells)
    return part[np.argsort(key[part], kind="stable")].astype(np.int64)


def check_budget(budget: Any) -> float:
    """The paper's ``budget`` (grid units) as a float >= 0; a string or a bool is refused."""
    return Fleet.check_budget(budget)


def budget_pool(region: Region, start: int, budget: float) -> np.ndarray:
    """``(n,)`` int64 cells within Euclidean grid distance ``budget`` (+ slack) of ``start``:
    the only ones any feasible plan of the paper's model reaches (a superset of its
    candidates)."""
    g = region.grid_index
    d = g - g[start]
    d2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float64)
    return np.flatnonzero(d2 <= (budget + _POOL_SLACK) ** 2).astype(np.int64)


def _robot_initial(models: list[Any], k: int, initial: str) -> list[np.ndarray]:
    """Each robot's forced cells: its model's ``initial_cells(k)`` (``initial="nearest"``) or
    its start (and end) only; a cell already forced for an earlier robot is left out (the
    robot's own start and end are always kept: every route has them)."""
    taken: set[int] = set()
    out = []
    for m in models:
        if initial == "nearest" and getattr(m, "is_default", False):
            c = initial_cells(m.region, m.start, k)  # the same cells, O(L) not O(L log L)
        elif initial == "nearest":
            c = np.asarray(m.initial_cells(k), dtype=np.int64)
        else:
            c = np.array([m.start] + ([] if m.end is None or m.end == m.start else [m.end]),
                         dtype=np.int64)
        keep = [int(x) for x in c if int(x) in (m.start, m.end) or int(x) not in taken]
        taken.update(keep)
        out.append(np.asarray(keep, dtype=np.int64))
    return out


def _is_fitted_model(obj: Any) -> bool:
    """A fitted GLRM, by duck typing (planning does not import the model class)."""
    return hasattr(obj, "Y_") and hasattr(obj, "region_")


def _model_call(model: Any, region: Any, start: Any, budget: Any) -> tuple[Any, Any, Any]:
    """``(region, start, budget)`` of ``plan_greedy(model, start, budget)`` and
    ``plan_greedy(model, region, start, budget)``: the region defaults to ``model.region_``."""
    if region is not None and not isinstance(region, Region):  # (model, start[, budget])
        if start is None:
            start = region
        elif budget is None:
            start, budget = region, start
        else:
            raise PlanningError("plan_greedy(model, start, budget): give the region as a "
                                f"Region or leave it out, got {type(region).__name__}")
        region = None
    if region is None:
        region = getattr(model, "region_", None)
        if region is None:
            raise PlanningError("plan_greedy(model, ...): the model has no region (fitted on an "
                                "array): pass region= or fit it on a (time, lat, lon) DataArray")
    return region, start, budget


def _model_defaults(model: Any, criterion: str | None, initial: str | None, prior: Any,
                    terms_given: dict[str, Any], paper: bool) -> tuple[str, str, Any]:
    """``(criterion, initial, prior)`` of a plan on a fitted ``model``: the given ones, else the
    paper's (``paper=True``: Fisher, nearest cells, no prior) or the recommended setting's
    (its criterion, initial cells and prior; a model without a spatial residual plans with
    Fisher on that prior, since the gp-variance criterion needs the residual)."""
    if paper:
        return criterion or "fisher", initial or "nearest", prior
    spatial = getattr(model, "spatial_cov_", None) is not None
    if criterion is None:
        criterion = recommended_criterion(spatial)
    initial = initial or RECOMMENDED["initial"]
    given = any(v is not None for key, v in terms_given.items() if key != "targets")
    if prior is None and not given:
        gp = CRITERION_REGISTRY.canonical(criterion, "criterion") == "gp-variance"
        try:
            prior = model.latent_prior(RECOMMENDED["prior"], spatial=spatial and gp)
        except ModelError as exc:
            raise PlanningError(f"plan_greedy(model, ...): {exc}") from None
    return criterion, initial, prior


def plan_greedy(
    Y: Any,
    region: Region | None = None,
    start: Any = None,
    budget: Any = None,
    *,
    criterion: str | None = None,
    cost: str = "nearest-neighbor",
    ridge: float = 0.0,
    progress: bool = True,
    initial: str | None = None,
    prior: Any = None,
    refine: bool | str | dict[str, Any] | None = None,
    path: PathOptions | None = None,
    paper: bool = False,
    cost_exponent: float = 1.0,
    stay: bool = False,
) -> Plan:
    """The paper's cost-benefit greedy path planner, for one robot or a fleet, on any path model.

    Two call forms:

    * ``plan_greedy(Y, region, start, budget)`` with a factor matrix: ``Y`` carries no belief,
      so the defaults are the paper's (``criterion="fisher"``, ``initial="nearest"``, no prior).
    * ``plan_greedy(model, start, budget)`` (or ``(model, region, start, budget)``) with a
      fitted GLRM: **the default is the recommended planner** of
      :data:`lrm_cvx.recommended.RECOMMENDED` (today the ``"gp-variance"`` criterion on the
      model's empirical prior with the GP residual, from the start cell alone,
      ``initial="start"``); a model without a spatial residual plans with ``"fisher"`` on its
      empirical prior. ``paper=True`` is the paper's planner on ``model.Y_``, unchanged.
      ``region`` defaults to ``model.region_``; an explicit ``criterion``, ``initial``,
      ``prior`` (or prior terms) wins over both defaults. ``paper`` must be True or False.

    1. ``P`` = the start cell and its ``k - 1`` nearest cells (the path model's
       ``initial_cells``; :func:`initial_cells` for the paper's).
    2. Each iteration, for every candidate cell ``x`` not in ``P`` with ``C(P + x) <= budget``
       (tolerance 1e-9): ``D_x = (I(P + x) - I(P)) / max(C(P + x) - C(P), 1e-12) ** e``
       (``e = cost_exponent``, 1 in the paper); the cell with the largest ``D_x`` joins ``P``
       (ties to the lowest cell index).
    3. Stop when no candidate has ``D_x > 0``.

    ``C`` is the path model's exact route cost (:func:`lrm_cvx.planning.paths.make_path_model`):
    the paper's is the nearest-neighbour open path in grid units, straight lines between
    stops. With all path options at their defaults the result is the paper's, bit for bit.

    Fleets (``start`` a list): one path model per robot; every robot's initial cells are forced
    (a cell already forced for an earlier robot is left out; its start is always kept); each
    step adds the ``(cell, robot)`` pair with the largest gain per unit of **that robot's**
    cost increase, the gain counted jointly (one information oracle for the union of all
    robots' cells), ties to the lowest cell then the lowest robot. A cell taken by one robot is
    no longer a candidate of the others. ``plan.robots`` gives each robot's sub-plan.

    Parameters
    ----------
    Y : ``(k, L)`` factor matrix (array, or a model's ``Y_`` DataArray ``(component, cell)``
        or ``(component, lat, lon)``), or a fitted GLRM (the recommended defaults above).
    region : the :class:`~lrm_cvx.region.Region` of ``Y``'s cells (a model's ``region_`` when
        left out with a model).
    start : a cell index or a ``(lat, lon)`` tuple (one robot), or a **list** of those, one per
        robot (a fleet; also a 1-D integer array of cells or an ``(n, 2)`` array of lat/lon). A
        list of two non-integer numbers is read as one ``[lat, lon]``.
    budget : the path budget, ``>= 0``, in the path model's unit (grid units; km with
        ``metric="km"``; hours with ``speed``): a number (every robot) or a list, one per robot.
    criterion : ``"fisher"`` (log det gain, the paper) or ``"a-optimal"`` (decrease of the
        total prediction variance; needs ``ridge > 0``), or ``"gp-variance"``. Default None:
        ``"fisher"`` for ``Y``, the recommended criterion for a model.
    cost : ``"nearest-neighbor"`` (the paper's ``C``, computed exactly) or ``"insertion"``
        (cheapest insertion route, cheaper and usually shorter).
    ridge : ``>= 0``, added to the information matrix (``ridge * I``).
    progress : show a tqdm progress bar.
    initial : ``"nearest"`` (the paper: the start and its ``k - 1`` nearest cells are forced) or
        ``"start"`` (only the start cell, and the ``end`` cell when given: with a prior the
        information matrix is nonsingular from the start, so the budget is not spent on
        ``k - 1`` forced cells). Default None: ``"nearest"`` for ``Y``, the recommended
        ``"start"`` for a model.
    prior : the criterion's prior: a :class:`~lrm_cvx.belief.posterior.LatentPosterior`
        (``GLRM.latent_prior(...)``, a monitoring filter's forecast) or a
        :class:`~lrm_cvx.planning.terms.PriorTerms` (``prior_precision``, ``noise_var``,
        ``target_weights``; ``prior_cov``, ``spatial_cov`` and ``targets`` for
        ``"gp-variance"``; ``GLRM.planner_kwargs()`` gives one as ``{"prior": ...}``). With a
        prior, ``M = prior_precision + sum_P y_p y_p^T / noise_var_p`` replaces
        ``ridge I + sum_P y_p y_p^T`` in ``"fisher"`` and ``"a-optimal"``, and the A-optimal
        target is ``sum_i target_weights_i y_i y_i^T`` (docs/reconstruction.md). Default None:
        the paper's (no prior) for ``Y``, the recommended prior for a model.
    refine : ``True`` / ``"local"`` (or a dict of its keyword arguments): run
        :func:`lrm_cvx.planning.refine.refine` on the greedy plan (a local search of insertions
        and swaps that raises the information within the budget; Fisher and the paper's path
        model only). ``"lines"``: return the straight transect from the start that beats the
        greedy's route under the plan's own criterion, if one does (any criterion and path
        model, point sensors, no ``end``; :mod:`~lrm_cvx.planning.lines`; ``plan.rivals``
        records the values). ``"rivals"``: the same check with one more rival, the greedy's
        route with ``cost_exponent=0.5`` (a second greedy pass; its name in
        ``plan.rivals["values"]`` is ``"greedy-cost^0.5"``, its ``method`` stays
        ``"greedy"``). Default None: nothing for ``Y``, the recommended ``"rivals"`` for a
        model (where the path options allow it).
    path : the path model, a :class:`~lrm_cvx.planning.request.PathOptions` (docs/planning.md,
        "Path models" and "Sensors": metric, speed, stop costs, travel graph, closed tours,
        end cell, sensing along the route, the sensor's footprint). Default None: the paper's.
    paper : True: the paper's planner on a model's ``Y_`` (Fisher, nearest cells, no prior).
    cost_exponent : ``e`` in ``[0, 1]``, the exponent of the cost increase in the greedy's
        ratio (step 2): 1 (default) is the paper's gain per unit cost, 0 the plain gain, in
        between a gentler discount of long detours.
    stay : a robot whose budget reaches no cell beyond its start (with no
        forced initial cell to take it away) stays there, a route of its start alone (a
        replan at the end of a route); default False: :class:`PlanningError` naming the
        nearest cell's distance and the budget a route to it needs.

    If the initial cells alone already exceed a robot's budget, the plan is still returned
    (the paper's initial set is forced) with a warning. Raises :class:`PlanningError` for a bad
    budget, start, criterion, cost or path option, a budget that cannot leave the start (unless
    ``stay``), or a singular initial set with ``ridge=0``.
    """
    paper = check_flag(paper, "paper", error=PlanningError)
    refine = _check_refine(refine)
    cost_exponent = _check_exponent(cost_exponent)
    stay = check_flag(stay, "stay", error=PlanningError)
    default_refine = False  # the recommended check is skipped where it cannot run
    prior, terms_given = split_prior(prior)
    if _is_fitted_model(Y):
        model = Y
        region, start, budget = _model_call(model, region, start, budget)
        Y = model.Y_
        criterion, initial, prior = _model_defaults(model, criterion, initial, prior,
                                                    terms_given, paper)
        if refine is None and not paper:
            refine = RECOMMENDED["refine"]
            default_refine = True
    elif hasattr(Y, "latent_prior") and hasattr(Y, "fit"):
        raise PlanningError("plan_greedy(model, ...): the model is not fitted")
    elif region is None:
        raise PlanningError("plan_greedy(Y, region, start, budget): region is missing (or pass "
                            "a fitted GLRM: plan_greedy(model, start, budget))")
    region = check_region(region)
    if isinstance(path, str):
        raise PlanningError(f"path must be a PathOptions or None, got {path!r} (fixed sensors: "
                            "lrm_cvx.planning.place_sensors)")
    request = PathOptions.from_kwargs(path, where="plan_greedy")
    criterion = criterion or "fisher"  # Y alone: the paper's defaults
    initial = initial or "nearest"
    Yk = as_factor_matrix(Y, region)
    k, L = Yk.shape
    fleet = Fleet.resolve(region, start, budget, request.unit)
    starts, budgets = list(fleet.starts), list(fleet.budgets)
    criterion = CRITERION_REGISTRY.canonical(criterion, "criterion")  # aliases accepted
    cost = COST_REGISTRY.canonical(cost, "cost")
    if initial not in ("nearest", "start"):
        raise PlanningError(f"initial must be 'nearest' or 'start', got {initial!r}")
    request = request.resolved(region)
    if refine in CHECKS and not lines_run(request, asked=not default_refine, refine=refine):
        refine = None
    models = [path_model(region, s, b, request, cost) for s, b in zip(starts, budgets,
                                                                       strict=True)]
    if initial == "nearest" and k > region.n_cells:
        raise PlanningError(f"the region has {region.n_cells} cells, fewer than the rank k = {k}")
    P0s = _robot_initial(models, k, initial)
    cands = [np.asarray(m.candidates(), dtype=np.int64) for m in models]
    if not stay and (initial == "start" or k == 1):
        _check_leaves(models, P0s, cands, fleet.is_fleet)
    tols = [float(getattr(m, "tol", _TOL)) for m in models]  # 1e-9 (x budget off the grid)
    union_pool = cands[0] if len(cands) == 1 else np.unique(np.concatenate(cands))
    idx = [np.searchsorted(union_pool, c) for c in cands]
    targets = terms_given.pop("targets")
    terms = resolve_prior(prior, terms_given)
    posterior = terms["prior_precision"] is not None or terms["noise_var"] is not None
    sense_along = request.sense_along
    sensor = request.sensor
    if not sensor.is_point and refine is not None:
        raise PlanningError("refine supports the point sensor only, not "
                            f"sensor={sensor.describe()!r}")
    pick = dict(Yk=Yk, models=models, P0s=P0s, cands=cands, union_pool=union_pool, idx=idx,
                budgets=budgets, tols=tols, fleet=fleet, criterion=criterion, ridge=ridge,
                sensor=sensor, region=region, terms=terms, targets=targets,
                sense_along=sense_along, progress=progress)
    build = dict(criterion=criterion, ridge=float(ridge), cost=cost, posterior=posterior,
                 fleet=fleet, request=request)
    *picked, extra, first = _picks(cost_exponent, **pick, keep=refine in CHECKS)
    plan = _route_plan(Yk, region, models, *picked, **build)
    if refine is not None:  # refine.py and lines.py register the refinements

        def rival(exponent: float) -> Plan:  # from the greedy's set-up (``first``)
            *again, _, _ = _picks(exponent, **pick, extra=extra, warn=False, start=first)
            return _route_plan(Yk, region, models, *again, **build)

        context = RefineContext(terms=terms, Y=Yk, region=region, fleet=fleet, request=request,
                                criterion=criterion, ridge=ridge, extra=extra,
                                rival=None if cost_exponent == RIVAL_EXPONENT else rival,
                                base=first)
        name, opts = (refine, {}) if isinstance(refine, str) else ("local", refine)
        plan = REFINERS.get(name, "refine")(plan, opts, context)
    plan._terms = extra  # the criterion's terms, which plan.certify() bounds
    return plan


def _check_leaves(models: list[Any], P0s: list[np.ndarray], cands: list[np.ndarray],
                  is_fleet: bool) -> None:
    """PlanningError when a robot has its start alone and no candidate: its budget cannot
    reach any cell beyond the start (the message names, for every such robot, the nearest
    cell's distance and the cheapest route to it, in the budget's unit). A start that can reach
    no other cell at all is left alone (a one-cell region plans its start)."""
    stuck = []
    for r, (m, P0, cand) in enumerate(zip(models, P0s, cands, strict=True)):
        if P0.size != 1 or cand.size:
            continue
        try:  # the nearest cell by the path model's distance (its travel graph grows to it)
            nearest = int(m.initial_cells(2)[1])
        except PlanningError:
            continue
        need = float(m.route_cost([m.start, nearest]))
        unit = getattr(m, "unit", "grid units")
        how = [f"the nearest cell is {float(m.distances(m.start, [nearest])[0]):.4g} {unit} away"]
        if m.closed or m.stop_cost:
            how.append(f"a route to it costs {need:.4g} {unit}"
                       f"{' (there and back)' if m.closed else ''}"
                       f"{' with the stop costs' if m.stop_cost else ''}")
        who = f"robot {r}'s budget" if is_fleet else "the budget"
        stuck.append(f"{who} {m.budget:g} {unit} cannot reach any cell beyond its start: "
                     f"{', '.join(how)}; give a budget of at least {need:.4g} {unit}")
    if stuck:
        raise PlanningError("; ".join(stuck))


def _picks(exponent: float, *, Yk, models, P0s, cands, union_pool, idx, budgets, tols, fleet,
           criterion, ridge, sensor, region, terms, targets, sense_along, progress,
           extra: dict[str, Any] | None = None, warn: bool = True, start: Any = None,
           keep: bool = False) -> tuple:
    """One greedy pass from the initial cells ``P0s``: each step adds the feasible
    ``(cell, robot)`` of largest gain per ``cost increase ** exponent`` (1: the paper's
    cost-benefit ratio; 0: the plain gain). Returns ``(costers, stops, stop_robot, sense,
    hist, extra, first)``: the first five for :func:`_route_plan`, ``extra`` the oracle's terms
    (computed unless given), ``first`` (with ``keep``, for an oracle that forks: the
    structured gp-variance one) a fork of the oracle on the initial cells, before the picks.
    ``start``: such a fork, which the pass forks instead of setting up its oracle again (the
    same numbers: a rival pass shares the set-up and the picks' convolutions)."""
    k, L = Yk.shape
    # (robot, stop) pairs: a cell is a stop of one robot, except starts shared by two robots
    stops = [int(c) for P in P0s for c in P]
    stop_robot = [r for r, P in enumerate(P0s) for _ in P]
    costers = [m.coster(P0, c) for m, P0, c in zip(models, P0s, cands, strict=True)]
    init = list(dict.fromkeys(stops))
    gp_pool = union_pool
    sense = _Sensing(models, L) if sense_along else None
    if sense is not None:
        for r, cst in enumerate(costers):
            sense.update(r, cst.route)
        init = list(dict.fromkeys(init + sense.observed().tolist()))
        if criterion == "gp-variance":  # pass-through cells must be cells of the GP pool
            gp_pool = np.union1d(union_pool, sense.reach())
    if not sensor.is_point:  # every cell the oracle may observe has its row
        gp_pool = np.union1d(union_pool, np.asarray(init, dtype=np.int64))
        if sense is not None:
            gp_pool = np.union1d(gp_pool, sense.reach())
    if extra is None:
        extra = oracle_terms(criterion, region, gp_pool, terms, targets)
    feed = None if sensor.is_point else _SensorRows(sensor, region, models, gp_pool, criterion,
                                                   Yk, ridge, extra)
    if start is not None and feed is None:
        oracle = start.fork()
    else:
        oracle = (make_oracle(criterion, Yk, ridge, init, **extra) if feed is None
                  else feed.oracle(init, costers))
    first = oracle.fork() if keep and feed is None and hasattr(oracle, "fork") else None
    for r, cst in enumerate(costers):  # cells forced for other robots are taken
        if len(costers) > 1:
            for c in set(stops):
                _take(cst, cands[r], c)
        if warn and cst.cost > budgets[r] + tols[r]:
            who = f"robot {r}'s " if fleet.is_fleet else ""
            warnings.warn(
                f"{who}{P0s[r].size} initial cells (start and its nearest, needed for a "
                f"rank-{k} model) already cost {cst.cost:.4g} > budget {budgets[r]:.4g}",
                UserWarning,
                stacklevel=3,
            )
    hist: dict[str, list[float]] = {
        "cell": [], "gain": [], "cost_increase": [], "ratio": [], "cost": [], "n_evaluated": []
    }
    if fleet.is_fleet:
        hist["robot"] = []
    bar = tqdm(desc="greedy plan", unit="pick", disable=not progress, leave=False)
    try:
        while True:
            gains = oracle.gains(union_pool)
            if sense is not None:
                gains = np.where(sense.counts[union_pool] > 0, 0.0, gains)
            best: tuple[float, int, int, int] | None = None  # (ratio, cell, robot, position)
            for r, cst in enumerate(costers):
                dc = cst.increases()
                with np.errstate(invalid="ignore"):
                    ok = cst.active & (cst.cost + dc <= budgets[r] + tols[r])
                g = gains if len(costers) == 1 else gains[idx[r]]
                den = np.maximum(np.where(ok, dc, 1.0), _MIN_DC)
                if exponent != 1.0:
                    den = den ** exponent
                ratio = np.where(ok, g / den, -np.inf)
                if ratio.size == 0:
                    continue
                b = int(np.argmax(ratio))
                if not ratio[b] > 0:
                    continue
                cand = (float(ratio[b]), int(cands[r][b]), r, b)
                if best is None or cand[0] > best[0] or (cand[0] == best[0]
                                                         and cand[1] < best[1]):
                    best = cand
                    best_dc, best_gain = float(dc[b]), float(g[b])
            if best is None:
                break
            _, cell, r, _ = best
            cst = costers[r]
            hist["cell"].append(cell)
            hist["gain"].append(best_gain)
            hist["cost_increase"].append(best_dc)
            hist["ratio"].append(best[0])
            hist["n_evaluated"].append(int(getattr(cst, "n_evaluated", cands[r].size)))
            cst.add(cell)
            for j, other in enumerate(costers):
                if j != r:
                    _take(other, cands[j], cell)
            if feed is not None and feed.legs:  # a towed sensor: the legs changed
                oracle = feed.oracle([], costers)
            elif sense is None:
                oracle.add(cell)
            else:
                added, removed = sense.update(r, cst.route)
                if removed.size:  # a re-ordered route no longer passes some cells
                    oracle = (make_oracle(criterion, Yk, ridge, sense.observed(), **extra)
                              if feed is None else feed.oracle(sense.observed(), costers))
                else:
                    for c in added.tolist():
                        oracle.add(c)
            stops.append(cell)
            stop_robot.append(r)
            if fleet.is_fleet:
                hist["robot"].append(r)
            hist["cost"].append(cst.cost)
            bar.update(1)
            bar.set_postfix(cost=f"{cst.cost:.1f}/{budgets[r]:g}", refresh=False)
    finally:
        bar.close()
    return costers, stops, stop_robot, sense, hist, extra, first


def _take(coster: Any, pool: np.ndarray, cell: int) -> None:
    """Deactivate ``cell`` in ``coster`` (a fleet-mate took it) when it is an active candidate."""
    i = int(np.searchsorted(pool, cell))
    if i < pool.size and pool[i] == cell and coster.active[i]:
        coster.deactivate(int(cell))


class _Sensing:
    """Cells observed along the robots' routes (``sense_along``): per-robot sets and counts."""

    def __init__(self, models: list[Any], L: int) -> None:
        self.models = models
        self.counts = np.zeros(L, dtype=np.int32)
        self.sets: list[np.ndarray] = [np.empty(0, np.int64) for _ in models]

    def update(self, r: int, route: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Robot ``r``'s route changed: ``(newly observed, no longer observed)`` cells."""
        from .plan import sensed_route

        cells = np.unique(sensed_route(self.models[r], route)[0])
        old = self.sets[r]
        touched = np.union1d(old, cells)
        before = self.counts[touched] > 0
        self.counts[old] -= 1
        self.counts[cells] += 1
        after = self.counts[touched] > 0
        self.sets[r] = cells
        return touched[after & ~before], touched[before & ~after]

    def observed(self) -> np.ndarray:
        return np.flatnonzero(self.counts > 0).astype(np.int64)

    def reach(self) -> np.ndarray:
        """Every cell a route may pass: within each robot's budget of its start."""
        out = [np.flatnonzero(np.isfinite(m.distances(m.start))
                              & (m.distances(m.start) <= m.budget + _POOL_SLACK))
               for m in self.models]
        return np.unique(np.concatenate(out)).astype(np.int64)


class _SensorRows:
    """The greedy's oracle under a sensor that is not a point (docs/planning.md, "Sensors"):
    each candidate of ``pool`` observes its footprint's averaged row; a towed sensor
    (``legs``) observes the legs of the current routes and candidates are scored by their own
    cell (a candidate's leg depends on where the route takes it), the oracle rebuilt from the
    routes' legs after each pick."""

    def __init__(self, sensor: Any, region: Region, models: list[Any], pool: np.ndarray,
                 criterion: str, Yk: np.ndarray, ridge: float, extra: dict[str, Any]) -> None:
        self.legs = sensor.is_leg
        self.region, self.models, self.pool = region, models, pool
        self.criterion, self.Yk, self.ridge = criterion, Yk, ridge
        self.extra = dict(extra, errors=sensor.errors)
        n, L = pool.size, region.n_cells
        self.rows = (footprint_matrix(region, sensor, pool) if sensor.has_footprint else
                     sps.csr_matrix((np.ones(n), (np.arange(n), pool)), shape=(n, L)))
        self._factors: tuple[np.ndarray, np.ndarray] | None = None
        self._oracle: Any = None  # a towed sensor's Fisher / A-optimal oracle

    def leg_rows(self, costers: list[Any]) -> sps.csr_matrix:
        """The legs of the robots' current routes (one averaged row per stop)."""
        from .plan import sensed_route

        parts = [sensed_route(m, c.route) for m, c in zip(self.models, costers, strict=True)]
        robot = np.concatenate([np.full(p[0].size, r) for r, p in enumerate(parts)])
        return leg_matrix(np.concatenate([p[0] for p in parts]),
                          np.concatenate([p[2] for p in parts]), robot, self.region.n_cells)

    def oracle(self, cells: Any, costers: list[Any]) -> Any:
        """The oracle with ``cells`` (pool cells) observed, or the legs of the routes (an
        existing Fisher / A-optimal oracle is updated in place: its pool columns are kept)."""
        legs = self.leg_rows(costers) if self.legs else None
        if self.legs and self._oracle is not None:
            self._oracle.set_extra(legs)
            return self._oracle
        extra = {k: v for k, v in self.extra.items() if k != "pool"}  # the GP pool: ours
        if self.criterion != "gp-variance":  # the pool's rows are computed once
            if self._factors is None:
                self._factors = row_factors(self.Yk, self.rows, extra.get("noise_var"),
                                            extra["errors"])
            extra["pool_factors"] = self._factors
        oracle = make_row_oracle(self.criterion, self.Yk, self.ridge,
                                 [] if self.legs else cells, pool=self.pool, rows=self.rows,
                                 extra_rows=legs, **extra)
        if self.legs and hasattr(oracle, "set_extra"):
            self._oracle = oracle
        return oracle


def _route_plan(Yk, region, models, costers, stops, stop_robot, sense, hist, *, criterion,
                ridge, cost, posterior, fleet, request) -> Plan:
    """The :class:`Plan` of one greedy pass's final routes."""
    from .plan import sensed_route

    sense_along, budgets = request.sense_along, list(fleet.budgets)
    sensor = request.sensor

    routes, cums, ways, robot = [], [], [], []
    for r, (m, cst) in enumerate(zip(models, costers, strict=True)):
        cells, cum, way = (sensed_route(m, cst.route) if sense_along or sensor.is_leg
                           else m.expand(cst.route))
        routes.append(np.asarray(cells, np.int64))
        cums.append(np.asarray(cum, np.float64))
        ways.append(np.asarray(way, bool))
        robot.append(np.full(len(cells), r, np.int64))
    cells = list(dict.fromkeys(list(stops) + (np.concatenate(routes).tolist() if sense_along
                                              else [])))
    if sensor.is_point:
        info = fisher_information(Yk, cells, ridge)
    else:  # the averaged rows the sensor observed
        rows = (leg_matrix(np.concatenate(routes), np.concatenate(ways),
                           np.concatenate(robot), region.n_cells) if sensor.is_leg
                else footprint_matrix(region, sensor, cells))
        info = row_information(Yk, rows, ridge, errors=sensor.errors)
    path = PlanPath.describe(request, fleet, traversable=models[0].traversable)
    robot_costs = np.array([c.cost for c in costers], dtype=np.float64)
    n = len(models)
    plan = Plan.build(
        region=region,
        cells=cells,
        route=np.concatenate(routes),
        cost=float(robot_costs.sum()) if n > 1 else float(robot_costs[0]),
        information=info,
        criterion=criterion,
        budget=float(sum(budgets)) if n > 1 else budgets[0],
        start=models[0].start,
        ridge=ridge,
        method="greedy",
        history=history_arrays(hist),
        cost_function=cost,
        Y=Yk,
        posterior=posterior,
        route_cost=np.concatenate(cums),
        path=path,
        route_robot=np.concatenate(robot),
        waypoint=np.concatenate(ways),
        stops=stops,
        stop_robot=stop_robot,
        robot_costs=robot_costs,
        path_models=models,
    )
    return plan


def _check_exponent(value: Any) -> float:
    """``cost_exponent`` as a float in ``[0, 1]``; PlanningError otherwise."""
    try:
        e = float(value)
    except (TypeError, ValueError):
        e = float("nan")
    if isinstance(value, bool) or not 0.0 <= e <= 1.0:
        raise PlanningError(f"cost_exponent must be a number in [0, 1], got {value!r}")
    return e


def _check_refine(refine: Any) -> Any:
    """``refine`` as None (no refinement), the name of a refinement of :data:`REFINERS` or a
    dict of the local search's options (True is ``"local"``); PlanningError otherwise."""
    if refine is None or refine is False:
        return None
    if refine is True:
        return "local"
    if isinstance(refine, str) and refine in REFINERS:
        return REFINERS.canonical(refine, "refine")
    if isinstance(refine, dict):
        return refine
    raise PlanningError(f"refine must be True, False, one of {list(REFINERS)} or a dict of the "
                        f"local search's options, got {refine!r}")


