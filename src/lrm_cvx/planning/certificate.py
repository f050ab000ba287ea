"""The plan certificate: an upper bound on the Fisher information of every feasible plan.

A plan's cells are either the greedy's forced initial set or the stops (and, with
``sense_along``, the pass-through cells) of a route within the budget of its path model. This
module turns the path model into what the relaxation of :mod:`lrm_cvx.planning.dopt` needs: the
candidate cells (every cell some feasible route can observe), a count limit ``n_max`` (budget,
smallest spacing, stop cost) and nested distance limits (how many cells a route of bounded
length can hold far from its start or from its midpoint). Fleets add their robots' counts over
the union of their candidates; a static placement is the count-only bound over all valid cells.
See ``docs/certificate.md`` §4-6 and §10 for the proofs.

Data flows one way: paths -> greedy / baselines -> Plan -> certificate. This module imports
neither the planner nor :class:`~lrm_cvx.planning.plan.Plan` at module level.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .._validation import as_factor_matrix
from ..errors import PlanningError, SolverError
from .dopt import (
    _DIST_EPS,
    Bound,
    _check_n_ridge,
    _chol,
    _inv_lower,
    _leverages,
    _moment,
    _Polytope,
    _relaxation,
    _top_sum,
)
from .paths import make_path_model, path_model
from .request import Fleet, PathOptions, PlanPath

__all__ = ["PlanCertificate", "plan_bound"]


@dataclass(frozen=True, eq=False)
class PlanCertificate:
    """Upper bound on the Fisher information of every plan from ``start`` within ``budget``.

    ``bound = max(initial_information, relaxation.value)``: a plan of the greedy planner is
    either its forced initial set (information ``initial_information``) or a set of at most
    ``n_max`` cells within ``budget`` of the start (covered by the relaxation). ``gap =
    bound - information`` (nats, >= 0 for every feasible plan) and ``volume_ratio =
    exp(-gap / k)``: the plan's information-ellipsoid volume relative to the bound's, per
    dimension (1 = certified optimal). ``online_bound`` is the submodularity bound
    ``f(P) + sum of the n_max largest marginal gains at P`` (see docs/certificate.md), when a
    plan was given; it is reported beside and ``bound`` already takes the smaller of the two.
    ``tightened``: the relaxation had the path's distance limits (docs/certificate.md §6);
    ``leaves``: the final squares of the midpoint cover ``(row0, col0, side, value)``, whose
    largest value is ``relaxation.value`` (empty without the cover).

    ``criterion`` is what the bound bounds: always ``"fisher"`` (``log det(ridge I + sum y
    y^T)``). ``plan_criterion`` is what the plan was chosen for (``None`` for a baseline, which
    optimises nothing and is judged by its Fisher information as in the paper; ``"fisher
    (posterior)"`` for a Fisher greedy on the fold-in's posterior). When the two differ
    (``comparable`` is False) ``information`` is still the plan's Fisher information but
    ``gap`` and ``volume_ratio`` are NaN: a gap between different criteria means nothing.
    """

    bound: float
    information: float | None
    gap: float | None
    volume_ratio: float | None
    n_max: int
    n_candidates: int
    k: int
    start: int
    budget: float
    ridge: float
    metric: str
    initial_information: float
    relaxation: Bound
    online_bound: float | None = None
    tightened: bool = False
    leaves: tuple[tuple[float, float, float, float], ...] = field(default=(), repr=False)
    criterion: str = "fisher"
    plan_criterion: str | None = None
    greedy_information: float | None = None
    refined_information: float | None = None
    refine_moves: int | None = None
    path_bound: float | None = None  # the path-aware relaxation's dual bound (path_aware=True)
    path: dict[str, Any] = field(default_factory=dict, repr=False)  # the path model bounded

    @property
    def plan_slack(self) -> float | None:
        """``refined_information - greedy_information`` (nats, >= 0): what a local search on
        the plan found; the part of the gap due to the planner."""
        if self.greedy_information is None or self.refined_information is None:
            return None
        if self.refined_information == self.greedy_information:
            return 0.0
        return float(self.refined_information - self.greedy_information)

    @property
    def bound_slack(self) -> float | None:
        """``bound - refined_information`` (nats, >= 0): the part of the gap nothing found yet,
        an upper limit on what the relaxation over-counts plus what the search missed."""
        if self.refined_information is None:
            return None
        return _gap(self.bound, self.refined_information, self.k)[0]

    @property
    def comparable(self) -> bool:
        """The plan was chosen for the bounded criterion (or is a baseline): the gap means
        something. False for a-optimal, gp-variance and posterior-Fisher plans."""
        return self.plan_criterion in (None, self.criterion)

    @property
    def relative_gap(self) -> float | None:
        """``gap / |bound|`` when both are finite (a unit-free view of the gap)."""
        if self.gap is None or not np.isfinite(self.gap) or not np.isfinite(self.bound) \
                or self.bound == 0:
            return None
        return self.gap / abs(self.bound)

    def __repr__(self) -> str:
        lines = [
            f"PlanCertificate(start={self.start}, budget={self.budget:g} "
            f"({self.metric}), k={self.k}, ridge={self.ridge:g})",
            f"  upper bound          {self.bound:.6g} nats (on the {self.criterion} "
            f"information of any plan)",
        ]
        if self.information is not None and not self.comparable:
            lines += [
                f"  plan information     {self.information:.6g} nats (Fisher)",
                f"  no gap: the plan was chosen for the {self.plan_criterion} criterion, the "
                f"bound is on {self.criterion}",
            ]
        elif self.information is not None:
            lines += [
                f"  plan information     {self.information:.6g} nats",
                f"  certified gap        {self.gap:.4g} nats",
                f"  volume ratio         {self.volume_ratio:.4f} (per dimension, 1 = optimal)",
            ]
            if self.refined_information is not None:
                lines += [
                    f"  greedy information   {self.greedy_information:.6g} nats",
                    f"  refined information  {self.refined_information:.6g} nats "
                    f"({self.refine_moves} moves)",
                    f"  gap split            plan slack {self.plan_slack:.4g} + bound slack "
                    f"{self.bound_slack:.4g} nats",
                ]
        lines.append(
            f"  relaxation           {self.relaxation.value:.6g} (primal "
            f"{self.relaxation.primal:.6g}, status {self.relaxation.status})")
        if self.path.get("kind", "path") == "path" and self.path.get("n_robots", 1) == 1:
            # (a fleet's and a static placement's forced cells are inside the relaxation)
            lines.append(f"  initial set          {self.initial_information:.6g} nats")
        if self.online_bound is not None:
            lines.append(f"  online bound         {self.online_bound:.6g} nats")
        lines.append(
            f"  at most {self.n_max} cells out of {self.n_candidates} candidates "
            f"within the budget"
        )
        if self.tightened:
            lines.append(f"  tightened: distance limits, midpoint cover of "
                         f"{len(self.leaves)} squares")
        model = _describe_path(self.path)
        if model:
            lines.append(f"  path model           {model}")
        return "\n".join(lines)

    def _repr_html_(self) -> str:
        rows = [("upper bound (nats)", f"{self.bound:.6g}"),
                ("bounded criterion", self.criterion)]
        if self.information is not None and not self.comparable:
            rows += [("plan criterion", str(self.plan_criterion)),
                     ("plan Fisher information (nats)", f"{self.information:.6g}"),
                     ("certified gap", "none: different criteria")]
        elif self.information is not None:
            rows += [
                ("plan information (nats)", f"{self.information:.6g}"),
                ("certified gap (nats)", f"{self.gap:.4g}"),
                ("volume ratio (per dim.)", f"{self.volume_ratio:.4f}"),
            ]
            if self.refined_information is not None:
                rows += [
                    ("greedy / refined information (nats)",
                     f"{self.greedy_information:.6g} / {self.refined_information:.6g}"),
                    ("plan slack / bound slack (nats)",
                     f"{self.plan_slack:.4g} / {self.bound_slack:.4g}"),
                ]
        rows += [
            ("relaxation value / primal", f"{self.relaxation.value:.6g} / "
                                          f"{self.relaxation.primal:.6g}"),
            ("initial set (nats)", f"{self.initial_information:.6g}"),
            ("max cells / candidates", f"{self.n_max} / {self.n_candidates}"),
            ("start, budget", f"{self.start}, {self.budget:g} ({self.metric})"),
        ]
        if self.online_bound is not None:
            rows.append(("online bound (nats)", f"{self.online_bound:.6g}"))
        body = "".join(f"<tr><td>{a}</td><td>{b}</td></tr>" for a, b in rows)
        return f"<table><caption>PlanCertificate</caption>{body}</table>"


# ----------------------------------------------------------------------------- plan bound
def plan_bound(
    Y: Any,
    region: Any,
    start: Any,
    budget: Any,
    *,
    ridge: float = 0.0,
    plan: Any = None,
    path: PathOptions | str | None = None,
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL",
    tol: float = 1e-3,
    tighten: bool = True,
    cover: int = 2,
    max_pieces: int = 40,
    refine: bool | dict[str, Any] = True,
    path_aware: bool | str | dict[str, Any] = False,
    **options: Any,
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
    split into four while at most ``max_pieces`` relaxations have been solved. ``tighten=False``
    gives the plain disk relaxation. When the plan is given, the submodularity online bound is
    computed too and the smaller one is kept. Proofs in docs/certificate.md.

    **Every path model** (issue #15, docs/certificate.md §10). ``path`` (a
    :class:`~lrm_cvx.planning.request.PathOptions`) or its keywords in ``**options``
    (``metric``, ``speed``, ``stop_cost``, ``traversable``, ``closed``, ``end``,
    ``sense_along``) describe the route as in :func:`~lrm_cvx.planning.plan_greedy` (``budget``
    in the path model's unit: grid units, km or hours); ``start`` and ``budget`` may be lists (a
    fleet); ``path="static"`` with ``n_sensors`` (in ``**options``) bounds every placement of
    ``n_sensors`` cells anywhere in the region. When a ``plan`` with a ``path`` description is
    given, its path model is used and these keywords are ignored. The candidates are the cells
    some feasible route can observe (shortest travel distances: ``d(start, x) + d(x, back) +
    stop costs <= budget``, ``back`` = nothing, the start of a closed tour or the ``end``); the
    count limit uses the smallest spacing and the stop cost; the start's distance limits use the
    path model's travel distances; the midpoint cover needs ``metric="grid"``. A fleet's bound
    is the count-only relaxation over the union of its robots' candidates with their count
    limits summed (valid, looser than one robot's).

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
    """
    from ..information import fisher_information

    region = _check_region(region)
    Y = as_factor_matrix(Y, region)
    k, L = Y.shape
    _, ridge = _check_n_ridge(1.0, ridge)
    if not isinstance(cover, (int, np.integer)) or cover < 1:
        raise PlanningError(f"cover must be an integer >= 1, got {cover!r}")
    if not isinstance(max_pieces, (int, np.integer)) or max_pieces < 1:
        raise PlanningError(f"max_pieces must be an integer >= 1, got {max_pieces!r}")
    n_sensors = options.pop("n_sensors", None)
    kind = "path"
    if isinstance(path, str) or path is None:
        kind = {"route": "path", "static": "static", None: "path"}.get(path)
        if kind is None:
            raise PlanningError(f"path must be 'route' or 'static', got {path!r}")
        path = None
    request = PathOptions.from_kwargs(path, where="plan_bound", **options)
    spec = _path_spec(region, plan, start, budget, request, kind, n_sensors)
    fam = _family(spec, region, k)
    cand, n_max, init = fam.cand, fam.n_max, fam.init
    # a fleet's certificate reports the total budget, as Plan.budget does
    budget0 = float(sum(spec.budgets)) if spec.budgets else float(spec.n_sensors)
    start0 = spec.starts[0] if spec.starts else -1
    metric = spec.metric if spec.kind == "path" else "sensors"
    init_info = float(fisher_information(Y, init, ridge=ridge)) if init.size else -math.inf
    opts = {"solver": solver, "tol": tol}
    leaves: list[tuple[float, float, float, float]] = []
    start_lim = None
    if tighten and fam.limits is not None:
        start_lim = fam.limits
    elif tighten and fam.dist is not None and math.isfinite(fam.d_min) and fam.d_min > 0:
        start_lim = _start_limit(fam.travel, fam.d_min, n_max, fam.ways)
    start_lv = (
        np.searchsorted(start_lim[0], fam.dist[cand], side="right") if start_lim else None
    )
    if tighten and fam.cover_budget is not None and fam.cover_budget >= 2.0:
        centre = region.grid_index[spec.starts[0]].astype(np.float64)
        relax, leaves = _midpoint_cover(
            Y, region, cand, start_lv, start_lim, centre, fam.cover_budget, n_max, ridge,
            cover, max_pieces, init_info, opts,
        )
    else:
        levels, caps = ([start_lv], [start_lim[1]]) if start_lim else ([], [])
        relax = _relaxation(Y, cand, _Polytope(n_max, cand.size, levels, caps), ridge, **opts)
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
        _check_plan_feasible(cells, init, cand, n_max, plan, fam.budget_text, 0.0)
        _check_plan_limits(cells, init, region, fam.dist, start_lim, leaves,
                           fam.cover_budget, n_max, plan)
        information = float(fisher_information(Y, cells, ridge=ridge))
        online = _online_bound(Y, cells, cand, n_max, ridge, information)
        if online is not None:
            bound = min(bound, max(init_info, online))
        plan_criterion = _plan_criterion(plan)
        greedy_info, refined_info, n_moves, rcells = _refined(
            plan, Y, region, refine if fam.paper else False, metric, plan_criterion,
            information)
        if refined_info is not None and refined_info > information:
            online_r = _online_bound(Y, rcells, cand, n_max, ridge, refined_info)
            if online_r is not None:
                bound = min(bound, max(init_info, online_r))
        if plan_criterion in (None, "fisher"):
            gap, ratio = _gap(bound, information, k)
        else:  # a bound on Fisher information says nothing of another criterion's gap
            gap, ratio = math.nan, math.nan
    return PlanCertificate(
        bound=float(bound), information=information, gap=gap, volume_ratio=ratio,
        n_max=int(n_max), n_candidates=int(cand.size), k=k, start=int(start0),
        budget=float(budget0), ridge=ridge, metric=metric, initial_information=init_info,
        relaxation=relax, online_bound=online, tightened=bool(tighten and (
            start_lim is not None or bool(leaves))), leaves=tuple(leaves),
        criterion="fisher", plan_criterion=_plan_criterion(plan) if plan is not None else None,
        greedy_information=greedy_info, refined_information=refined_info,
        refine_moves=n_moves, path_bound=path_value, path=spec.summary(),
    )


# ----------------------------------------------------------------------------- path models
def _describe_path(path: dict[str, Any]) -> str:
    """One line for a non-paper path model (empty for the paper's)."""
    if not path or _is_paper_description(path):
        return ""
    if path.get("kind") == "static":
        return f"static placement of {path.get('n_sensors')} sensors"
    parts = [str(path.get("metric", "grid"))]
    if path.get("speed") is not None:
        parts.append(f"{path['speed']:g} km/h (budget in hours)")
    if path.get("stop_cost"):
        parts.append(f"stop cost {path['stop_cost']:g}")
    if path.get("traversable") not in (None, "none"):
        parts.append(f"travel graph ({path['traversable']})")
    if path.get("closed"):
        parts.append("closed")
    if path.get("end") is not None:
        parts.append(f"end {path['end']}")
    if path.get("sense_along"):
        parts.append("sensing along")
    if path.get("n_robots", 1) > 1:
        parts.append(f"{path['n_robots']} robots (union bound: counts added, limits from the "
                     "nearest start)")
    return ", ".join(parts)


@dataclass(frozen=True)
class _PathSpec:
    """What the certificate needs to know of a plan's path model (validated): the request's
    :class:`PathOptions` and :class:`Fleet` (none for a static placement)."""

    kind: str  # "path" or "static"
    options: PathOptions
    fleet: Fleet
    n_sensors: int | None
    models: tuple[Any, ...] | None = None  # the plan's own PathModels, one per robot

    starts = property(lambda self: self.fleet.starts)
    budgets = property(lambda self: self.fleet.budgets)
    metric = property(lambda self: self.options.metric)
    speed = property(lambda self: self.options.speed)
    stop_cost = property(lambda self: self.options.stop_cost)
    traversable = property(lambda self: self.options.traversable)
    closed = property(lambda self: self.options.closed)
    end = property(lambda self: self.options.end)
    sense_along = property(lambda self: self.options.sense_along)

    @property
    def paper(self) -> bool:
        """The paper's path model (one robot, open, straight lines, no stop cost)."""
        return self.kind == "path" and len(self.starts) == 1 and self.options.is_paper

    def summary(self) -> dict[str, Any]:
        trav = self.traversable
        return {
            "kind": self.kind, "metric": self.metric, "speed": self.speed,
            "stop_cost": self.stop_cost,
            "traversable": trav if trav is None or isinstance(trav, str) else "mask",
            "closed": self.closed, "end": self.end, "sense_along": self.sense_along,
            "starts": list(self.starts), "budgets": list(self.budgets),
            "n_robots": len(self.starts), "n_sensors": self.n_sensors,
        }


def _check_region(region: Any) -> Any:
    from .plan import check_region  # Plan's module is a leaf: no cycle through here

    return check_region(region)


def _starts_list(x: Any) -> Any:
    """The certificate's reading of ``start``: a tuple of cell indices is a fleet (a tuple
    with a float is one ``(lat, lon)``); else as :meth:`Fleet.resolve` reads it."""
    if isinstance(x, tuple) and not (
        len(x) == 2 and any(isinstance(v, (float, np.floating)) for v in x)
    ):
        return list(x)
    return x


def _is_paper_description(desc: Any) -> bool:
    """``plan.path`` describes the paper's path model (old plans, the default): the caller's
    keywords (e.g. ``metric="km"``) then apply, as before issue #15."""
    trav = desc.get("traversable")
    return (desc.get("kind", "path") == "path" and int(desc.get("n_robots", 1) or 1) == 1
            and desc.get("metric", "grid") == "grid" and desc.get("speed") is None
            and not desc.get("stop_cost") and (trav is None or trav == "none")
            and not desc.get("closed") and desc.get("end") is None
            and not desc.get("sense_along"))


def _plan_request(plan: Any, desc: Any) -> PathOptions:
    """The path options of a plan's path record (a :class:`PlanPath` or its mapping); a
    traversable mask the record does not keep is the plan's ``traversable_mask``, else
    ``"valid"`` (enterable = valid & mask: travel over all valid cells is never longer, so it
    gives a valid, looser certificate)."""
    if isinstance(desc, PlanPath) and desc.options is not None:
        return desc.options
    trav = desc.get("traversable")
    if isinstance(trav, str) and trav.lower() == "none":
        trav = None
    elif isinstance(trav, str) and trav == "mask":
        mask = desc.get("mask", getattr(plan, "traversable_mask", None))
        trav = mask if mask is not None else "valid"
    return PathOptions(metric=desc.get("metric", "grid"), speed=desc.get("speed"),
                       stop_cost=desc.get("stop_cost", 0.0) or 0.0, traversable=trav,
                       closed=bool(desc.get("closed", False)), end=desc.get("end"),
                       sense_along=bool(desc.get("sense_along", False)))


def _path_spec(region: Any, plan: Any, start: Any, budget: Any, request: PathOptions,
               kind: str, n_sensors: Any) -> _PathSpec:
    """The path model of the request: ``plan.path`` when the plan has one, else ``request``
    (``kind`` ``"path"`` or ``"static"``, ``n_sensors`` for the latter)."""
    desc = getattr(plan, "path", None) if plan is not None else None
    if isinstance(desc, Mapping) and desc and not _is_paper_description(desc):
        kind = desc.get("kind", "path")
        start = desc.get("starts") or getattr(plan, "start", start)
        budget = desc.get("budgets") or getattr(plan, "budget", budget)
        n_sensors = desc.get("n_sensors")
        if kind == "static":
            budgets = list(np.atleast_1d(budget))
            if n_sensors is None:
                n_sensors = (int(round(budgets[0])) if budgets
                             else int(np.unique(plan.cells).size))
            request = PathOptions()
        else:
            request = _plan_request(plan, desc)
    elif plan is not None and getattr(plan, "start", None) is not None and start is None:
        start = plan.start
    if kind == "static":
        n = n_sensors
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PlanningError(f"n_sensors must be an integer >= 1 for path='static', "
                                f"got {n!r}")
        return _PathSpec("static", request, Fleet((), ()), int(n))
    start = _starts_list(start)
    if (isinstance(budget, (list, tuple, np.ndarray)) and len(budget) == 1
            and isinstance(start, (list, np.ndarray)) and len(start) > 1):
        budget = budget[0]  # one budget for every robot of a fleet
    if not isinstance(start, (list, np.ndarray)) and isinstance(budget, (list, tuple,
                                                                         np.ndarray)):
        start = [start]  # a one-robot fleet: plan.path's lists
    fleet = Fleet.resolve(region, start, budget, request.unit)
    request = request.resolved(region)
    models = getattr(plan, "_path_models", None) if plan is not None else None
    if models is not None and (len(models) != fleet.n_robots or any(
            int(m.start) != c for m, c in zip(models, fleet.starts, strict=True))):
        models = None
    return _PathSpec("path", request, fleet, None, tuple(models) if models else None)


@dataclass(frozen=True)
class _Family:
    """Every plan's cells: the initial set ``init`` or at most ``n_max`` of ``cand``.

    ``dist`` (L,) and ``travel``: the start's distance limits (no more than
    ``floor((travel - r) / d_min) + 1`` cells at distance ``>= r``); None: no limits.
    ``cover_budget``: grid length of the path the midpoint cover may assume (None: no cover).
    """

    cand: np.ndarray
    n_max: int
    init: np.ndarray
    dist: np.ndarray | None
    d_min: float
    travel: float
    cover_budget: float | None
    paper: bool
    budget_text: str
    ways: int = 1  # 2: a closed tour comes back, so the start's limits count both ways
    limits: tuple[np.ndarray, np.ndarray] | None = None  # precomputed limits on ``dist``


def _family(spec: _PathSpec, region: Any, k: int) -> _Family:
    """The candidates and count limits of ``spec`` (proofs: docs/certificate.md §10)."""
    L = region.n_cells
    if spec.kind == "static":
        return _Family(np.arange(L, dtype=np.int64), min(spec.n_sensors, L),
                       np.zeros(0, np.int64), None, math.inf, math.inf, None, False,
                       f"{spec.n_sensors} sensors")
    if spec.paper:
        return _paper_family(spec, region, k)
    parts = [_robot_family(spec, region, k, r) for r in range(len(spec.starts))]
    if len(parts) == 1:
        return parts[0]
    # a fleet: each robot's cells are its initial set or a feasible route's; the union of
    # the robots' sets lies in the union of their candidates and holds at most the sum
    cand = np.unique(np.concatenate([np.union1d(p.cand, p.init) for p in parts]))
    n_max = min(cand.size, sum(max(p.n_max, p.init.size) for p in parts))
    text = "fleet budgets " + ", ".join(f"{b:g}" for b in spec.budgets)
    dist, limits = _fleet_limits(parts, n_max)
    return _Family(cand, n_max, np.zeros(0, np.int64), dist, math.inf, math.inf, None, False,
                   text, 1, limits)


def _fleet_limits(parts: list[_Family], n_max: int
                  ) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """A fleet's distance limits on ``D(x) = min_r d_r(x)`` (distance to the nearest start).

    A cell with ``D(x) >= rho`` is at least ``rho`` from its own robot's start, so robot r
    holds at most ``max(#{init_r : D >= rho}, floor((T_r - w_r rho) / d_r) + 1)`` of them
    (its initial set, or a route: Lemma 1, ``w_r = 2`` for a closed tour, none when
    ``w_r rho > T_r``); the fleet holds at most the sum. ``(None, None)`` when a robot has no
    distance limits (sensing along straight legs).
    """
    if any(p.dist is None or not (math.isfinite(p.d_min) and p.d_min > 0) for p in parts):
        return None, None
    D = np.min(np.stack([p.dist for p in parts]), axis=0)
    thr = []
    for p in parts:
        lim = _start_limit(p.travel, p.d_min, max(p.n_max, 2), p.ways)
        if lim is not None:
            thr.append(lim[0])
    if not thr:
        return D, None
    thr = np.unique(np.concatenate(thr))
    caps = np.zeros(thr.size)
    for p in parts:
        route = np.where(p.ways * thr <= p.travel,
                         np.floor((p.travel - p.ways * thr) / p.d_min + 1e-9) + 1, 0.0)
        init = (D[p.init][:, None] >= thr[None, :]).sum(axis=0) if p.init.size else 0
        caps += np.maximum(route, init)
    keep = caps < n_max  # a cap at the count limit adds nothing
    if not keep.any():
        return D, None
    return D, (thr[keep], caps[keep])


def _paper_family(spec: _PathSpec, region: Any, k: int) -> _Family:
    """The paper's path (grid or km, straight lines, open, no stop cost): as issue #5."""

    start, budget, metric = spec.starts[0], spec.budgets[0], spec.metric
    L = region.n_cells
    dist = np.asarray(region.distance(start, np.arange(L), metric=metric), dtype=np.float64)
    Bp = budget + _DIST_EPS * max(1.0, budget)  # every path cost the planners accept is <= Bp
    cand = np.flatnonzero(dist <= Bp)
    d_min = 1.0 if metric == "grid" else _min_spacing_km(region, cand)
    n_max = min(cand.size, math.floor(Bp / d_min) + 1) if d_min > 0 else cand.size
    init = _paper_initial_cells(region, start, budget, k)
    return _Family(cand, int(n_max), init, dist, d_min, Bp, Bp if metric == "grid" else None,
                   True, f"budget={budget:g}")


def _paper_initial_cells(region: Any, start: int, budget: float, k: int) -> np.ndarray:
    """The greedy's forced initial set on the paper's path: start + k-1 nearest (grid)."""
    return np.asarray(make_path_model(region, start, budget).initial_cells(k), np.int64)


def _robot_family(spec: _PathSpec, region: Any, k: int, r: int) -> _Family:
    """One robot of any path model: candidates by travel distance, count by spacing and stop
    cost, the start's limits in the model's travel distance (docs/certificate.md §10)."""
    start, budget = spec.starts[r], spec.budgets[r]
    if spec.models is not None:  # the plan's own model (keeps a traversable mask)
        pm = spec.models[r]
    else:
        pm = path_model(region, start, budget, spec.options)
    if spec.sense_along and pm.traversable == "none":
        return _straight_sensing_family(spec, pm, region, k)
    c = spec.stop_cost
    Bp = budget + _DIST_EPS * max(1.0, budget)
    d_s = np.asarray(pm.distances(start), dtype=np.float64)
    if spec.closed:
        d_back = d_s
    elif spec.end is not None:
        d_back = np.asarray(pm.distances(spec.end), dtype=np.float64)
    else:
        d_back = np.zeros_like(d_s)
    fixed = 1 + int(spec.end is not None and spec.end != start)  # stops every route has
    with np.errstate(invalid="ignore"):
        through = d_s + d_back + c * fixed  # the cheapest route observing x on its way
        stop = through + c  # ... and stopping at x
    reach = stop if not spec.sense_along else through
    cand = np.flatnonzero(np.isfinite(reach) & (reach <= Bp))
    cand = np.union1d(cand, [start] + ([spec.end] if spec.end is not None else []))
    d_min = _spacing(region, cand, spec)
    travel = max(Bp - c * fixed, 0.0)  # no route travels farther
    if d_min <= 0 or not math.isfinite(d_min):
        n_max = cand.size
    elif spec.sense_along:  # stops pay c, pass-through cells only their spacing
        n_max = math.floor(travel / d_min) + 1
    else:  # n stops: n c + (n - 1) d_min <= budget
        n_max = math.floor((Bp + d_min) / (c + d_min))
    n_max = int(max(1, min(cand.size, n_max)))
    init = np.asarray(pm.initial_cells(k), dtype=np.int64)
    # the straight chart path through the observed cells is no longer than the travel in
    # grid units (a travel graph's steps are the Euclidean grid lengths of 8-neighbour moves)
    # (km: PathModel.grid_budget_bound's curvature argument). Not on a grid that wraps: the
    # cover's squares live on the unwrapped chart.
    cover_budget = None
    if not getattr(pm, "_wrap", True):
        cover_budget = travel if spec.metric == "grid" else float(pm.grid_budget_bound()) * (
            1 + 1e-9)
        if not math.isfinite(cover_budget):
            cover_budget = None
    return _Family(cand, n_max, init, np.where(np.isfinite(d_s), d_s, np.inf), d_min, travel,
                   cover_budget, False, f"budget={budget:g} ({pm.unit})",
                   2 if spec.closed else 1)


def _straight_sensing_family(spec: _PathSpec, pm: Any, region: Any, k: int) -> _Family:
    """Sensing along straight legs (``sense_along`` without a travel graph).

    The observed cells are those whose unit square a leg's chart segment crosses
    (:func:`~lrm_cvx.planning.plan.line_cells`): a segment from ``(r0, c0)`` to ``(r1, c1)``
    crosses at most ``|r1 - r0| + |c1 - c0| + 1 <= sqrt 2 l + 1`` squares, consecutive legs
    share their stop, so a route whose stops' chart polyline has length ``<= G``
    (:meth:`PathModel.grid_budget_bound`; the travel itself on the grid) observes at most
    ``floor(sqrt 2 G) + 1`` cells, each within ``sqrt 2 / 2`` of a point of the polyline:
    ``chart(start, x) + chart(x, back) <= G + sqrt 2``. No distance limits. On a grid whose
    longitudes wrap the chart argument does not apply: every cell, no count limit.
    """
    L = region.n_cells
    start = pm.start
    init = np.asarray(pm.initial_cells(k), dtype=np.int64)
    text = f"budget={pm.budget:g} ({pm.unit})"
    G = float(pm.grid_budget_bound()) * (1 + 1e-9) + 1e-9
    if getattr(pm, "_wrap", True) or not math.isfinite(G):
        return _Family(np.arange(L, dtype=np.int64), L, init, None, math.inf, math.inf,
                       None, False, text)
    everything = np.arange(L)
    cs = np.asarray(pm.chart_distance(start, everything), dtype=np.float64)
    if spec.closed:
        cb = cs
    elif spec.end is not None:
        cb = np.asarray(pm.chart_distance(spec.end, everything), dtype=np.float64)
    else:
        cb = np.zeros(L)
    cand = np.flatnonzero(cs + cb <= G + math.sqrt(2.0) * (1 + 1e-9))
    cand = np.union1d(cand, [start] + ([spec.end] if spec.end is not None else []))
    n_max = int(max(1, min(cand.size, math.floor(math.sqrt(2.0) * G) + 1)))
    return _Family(cand, n_max, init, None, math.inf, math.inf, None, False, text)


def _spacing(region: Any, cand: np.ndarray, spec: _PathSpec) -> float:
    """Smallest travel distance between two distinct candidates, in the budget's unit."""
    if spec.metric == "grid":
        return 1.0
    d = _min_spacing_km(region, cand)
    return d / spec.speed if spec.speed is not None else d


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
    greedy plan, or ``(None, None, None, plan cells)``."""
    cells = np.asarray(plan.cells, dtype=np.int64)
    if plan_criterion != "fisher" or metric != "grid":
        return None, None, None, cells
    done = getattr(plan, "refinement", None) or {}
    if done:
        return float(done["information_before"]), float(information), int(done["moves"]), cells
    if refine is False or refine is None or not hasattr(plan, "cost_function"):
        return None, None, None, cells
    from .plan import REFINERS  # the search registers itself: no import of the planner

    opts = dict(refine) if isinstance(refine, dict) else {}
    better = REFINERS.get("local")(plan, dict(opts, Y=Y, region=region), {})
    moves = int(better.refinement.get("moves", 0)) if better is not plan else 0
    return (float(information), max(float(better.information), float(information)), moves,
            np.asarray(better.cells, dtype=np.int64))


def _plan_criterion(plan: Any) -> str | None:
    """The criterion a plan was chosen for, canonical (``None``: a baseline)."""
    crit = getattr(plan, "criterion", None)
    if crit is None:
        return None
    if crit == "risk":  # static placement on the training error (planning/static.py)
        return crit
    from ..information import CRITERION_REGISTRY

    crit = CRITERION_REGISTRY.canonical(crit, "plan.criterion")
    if crit == "fisher" and getattr(plan, "posterior", False):
        return "fisher (posterior)"
    return crit


# ----------------------------------------------------------------------------- path limits
_NUDGE = 1e-6  # radii sit this far (in d_min) inside their cap's interval, away from rounding


def _cap_ladder(lo: int, hi: int, count: int = 10) -> np.ndarray:
    """About ``2 count`` integer caps in ``[lo, hi)``: geometric (dense near ``lo``) + linear."""
    if hi <= lo:
        return np.zeros(0, np.int64)
    geo = np.geomspace(lo, max(hi - 1, lo), count)
    lin = np.linspace(lo, max(hi - 1, lo), count)
    return np.unique(np.round(np.concatenate([geo, lin])).astype(np.int64))


def _start_limit(Bp: float, d_min: float, n_max: int, ways: int = 1
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """Distance limits from the start: ``(thresholds, caps)``, ascending thresholds.

    A path of length ``<= Bp`` from the start holds at most ``floor((Bp - r) / d_min) + 1`` cells
    at distance ``>= r`` from the start. For a cap ``c`` the largest such set has ``r`` just
    above ``Bp - c d_min``; the cap is recomputed from ``r`` (not assumed), and the threshold is
    nudged up so that float distances cannot put a cell into a set it does not belong to.
    ``ways=2``: a closed tour, which also travels ``>= r`` back from the last such cell, holds
    at most ``floor((Bp - 2 r) / d_min) + 1`` (docs/certificate.md §10).
    """
    thr, caps = [], []
    for c in _cap_ladder(1, n_max)[::-1]:
        r = (Bp - (c - _NUDGE) * d_min) / ways
        if r <= 0:
            continue
        cap = math.floor((Bp - ways * r) / d_min) + 1
        thr.append(r * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    if not thr:
        return None
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)


def _square_limit(Bp: float, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance limits from the midpoint's square: at most ``floor(Bp - 2 s) + 2`` cells at
    distance ``>= s > 0`` from it (grid units, ``d_min = 1``); ascending thresholds."""
    thr, caps = [], []
    for c in _cap_ladder(2, n_max)[::-1]:
        s = (Bp - c + 1 + 2 * _NUDGE) / 2
        if s <= 0:
            continue
        cap = math.floor(Bp - 2 * s) + 2
        thr.append(s * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)


def _square_distance(points: np.ndarray, r0: float, c0: float, h: float) -> np.ndarray:
    """Euclidean distance (grid units) from ``points`` (m, 2) to the square ``[r0, r0+h] x
    [c0, c0+h]`` (0 inside)."""
    pr, pc = points[:, 0], points[:, 1]
    dr = np.maximum(np.maximum(r0 - pr, pr - (r0 + h)), 0.0)
    dc = np.maximum(np.maximum(c0 - pc, pc - (c0 + h)), 0.0)
    return np.hypot(dr, dc)


def _cover_squares(
    centre: np.ndarray, radius: float, r0: float, c0: float, h: float, parts: int
) -> list[tuple[float, float, float]]:
    """The ``parts x parts`` sub-squares of ``[r0, r0+h] x [c0, c0+h]`` meeting the disk
    ``B(centre, radius)``, as ``(r0, c0, side)``."""
    s = h / parts
    out = []
    for a in range(parts):
        for b in range(parts):
            q = (r0 + a * s, c0 + b * s, s)
            if _square_distance(centre[None, :], *q)[0] <= radius:
                out.append(q)
    return out


def _midpoint_cover(
    Y: np.ndarray, region: Any, cand: np.ndarray, start_lv: np.ndarray | None,
    start_lim: tuple[np.ndarray, np.ndarray] | None, centre: np.ndarray, Bp: float,
    n_max: int, ridge: float, cover: int, max_pieces: int, floor_value: float,
    opts: dict[str, Any],
) -> tuple[Bound, list[tuple[float, float, float, float]]]:
    """Max over a cover of the possible path midpoints of the relaxation restricted to each piece.

    The midpoint lies in the closed disk ``B(start, Bp / 2)``, tiled by squares of side
    ``Bp / (2 cover)`` with a corner at the start. Piece ``Q``: the candidates within ``Bp / 2``
    of ``Q``, the start's distance limits and ``Q``'s distance limits. The piece with the largest
    bound is split into four (children keep ``min(own, parent)``: both bound the midpoints in
    the child) until ``max_pieces`` relaxations have been solved or it is below ``floor_value``
    (the initial set's information, which the certificate takes the maximum with anyway).
    Returns the largest piece's :class:`Bound` and every final piece ``(r0, c0, side, value)``.
    """
    pos = region.grid_index[cand].astype(np.float64)
    sq_thr, sq_caps = _square_limit(Bp, n_max)
    half = Bp / 2

    def solve(q: tuple[float, float, float]) -> Bound:
        dq = _square_distance(pos, *q)
        sel = np.flatnonzero(dq <= half * (1 + 1e-12) + 1e-12)
        levels = [np.searchsorted(sq_thr, dq[sel], side="right")]
        caps = [sq_caps]
        if start_lv is not None:
            levels.append(start_lv[sel])
            caps.append(start_lim[1])
        poly = _Polytope(n_max, sel.size, levels, caps)
        return _relaxation(Y, cand[sel], poly, ridge, **opts)

    side = Bp / cover  # 2 cover squares across the disk's diameter Bp
    squares = _cover_squares(centre, half, centre[0] - half, centre[1] - half, Bp, 2 * cover)
    del side
    pieces: list[tuple[tuple[float, float, float], Bound, float]] = []
    for q in squares:
        b = solve(q)
        pieces.append((q, b, b.value))
    solved = len(pieces)
    while True:
        i = max(range(len(pieces)), key=lambda j: (pieces[j][2], -j))
        q, b, val = pieces[i]
        children = _cover_squares(centre, half, q[0], q[1], q[2], 2)
        if val <= floor_value or solved + len(children) > max_pieces or q[2] < 0.5:
            break
        new = []
        for c in children:
            bc = solve(c)
            new.append((c, bc if bc.value < val else b, min(bc.value, val)))
        solved += len(children)
        pieces[i: i + 1] = new
    i = max(range(len(pieces)), key=lambda j: (pieces[j][2], -j))
    leaves = [(q[0], q[1], q[2], v) for q, _, v in pieces]
    return pieces[i][1], leaves


def _check_plan_limits(
    cells: np.ndarray, init: np.ndarray, region: Any, dist: np.ndarray,
    start_lim: tuple[np.ndarray, np.ndarray] | None,
    leaves: list[tuple[float, float, float, float]], Bp: float | None, n_max: int, plan: Any,
) -> None:
    """A covered plan satisfies the start's distance limits and lies in some piece's set."""
    if set(cells.tolist()) == set(init.tolist()):
        return
    cells = np.unique(cells)
    length = f"{Bp:.6g}" if Bp is not None else "the budget"
    msg = f"the plan is not a path of length <= {length} from start={plan.start}: "
    if start_lim is not None:
        d = dist[cells]
        counts = (d[:, None] >= start_lim[0][None, :]).sum(axis=0)
        if np.any(counts > start_lim[1]):
            raise PlanningError(msg + "too many cells far from the start; the certificate "
                                "does not cover it")
    if not leaves:
        return
    pos = region.grid_index[cells].astype(np.float64)
    sq_thr, sq_caps = _square_limit(Bp, n_max)
    for r0, c0, h, _ in leaves:
        dq = _square_distance(pos, r0, c0, h)
        if np.all(dq <= Bp / 2 * (1 + 1e-12) + 1e-12) and np.all(
            (dq[:, None] >= sq_thr[None, :]).sum(axis=0) <= sq_caps
        ):
            return
    raise PlanningError(msg + "no piece of the midpoint cover holds it; the certificate does "
                        "not cover it")


def _gap(bound: float, information: float, k: int) -> tuple[float, float]:
    if bound == -math.inf and information == -math.inf:
        return 0.0, 1.0  # every feasible plan is singular: this one is optimal
    gap = bound - information
    return float(gap), float(math.exp(-gap / k)) if math.isfinite(gap) else 0.0


def _check_plan_feasible(
    cells: np.ndarray, init: np.ndarray, cand: np.ndarray, n_max: int, plan: Any,
    budget: float, slack: float,
) -> None:
    """The certificate covers the initial set and plans of <= n_max cells in the budget disk."""
    if set(cells.tolist()) == set(init.tolist()):
        return
    inside = np.isin(cells, cand)
    if not inside.all() or np.unique(cells).size > n_max:
        raise PlanningError(
            f"the plan is not feasible for start={plan.start}, "
            f"{budget if isinstance(budget, str) else f'budget={budget:g}'}: "
            f"{int((~inside).sum())} of its cells lie farther than the budget from the start "
            f"or it holds more than {n_max} cells; the certificate does not cover it"
        )


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
    top, _ = _top_sum(gains, float(n_max))
    return f_S + top


def _min_spacing_km(region: Any, cand: np.ndarray) -> float:
    """Smallest great-circle distance (km) between two distinct candidate cells (KD-tree)."""
    if cand.size < 2:
        return math.inf
    from scipy.spatial import cKDTree

    lat = np.radians(region.cell_lat[cand])
    lon = np.radians(region.cell_lon[cand])
    xyz = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    _, nn = cKDTree(xyz).query(xyz, k=2)
    d = np.asarray(region.distance(cand, cand[nn[:, 1]], metric="km"), dtype=np.float64)
    # chord and great-circle distances are monotone in each other; shave rounding off
    return float(d.min()) * (1 - 1e-9)
