"""The plan family of a path request: every set of cells a feasible plan can observe.

Turns a request (:class:`~lrm_cvx.planning.request.PathOptions` and
:class:`~lrm_cvx.planning.request.Fleet`, or a plan's ``path`` record) into the candidate cells,
count limits and start distance limits that :mod:`lrm_cvx.planning.dopt` needs
(:class:`Family`). Proofs: docs/certificate.md §4-6 and §10.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import PlanningError
from .dopt import DIST_EPS
from .paths import make_path_model, path_model
from .request import Fleet, PathOptions, PlanPath
from .sensors import POINT

NUDGE = 1e-6  # radii sit this far (in d_min) inside their cap's interval, away from rounding

__all__ = ["PathSpec", "path_spec", "Family", "family", "LegFamily", "leg_family", "leg_limits",
           "leg_midpoint_limits",
           "describe_path",
           "is_paper_description", "min_spacing_km", "start_limit", "cap_ladder", "NUDGE"]


def describe_path(path: dict[str, Any]) -> str:
    """One line for a non-paper path model (empty for the paper's)."""
    if not path or is_paper_description(path):
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
class PathSpec:
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


def _starts_list(x: Any) -> Any:
    """The certificate's reading of ``start``: a tuple of cell indices is a fleet (a tuple
    with a float is one ``(lat, lon)``); else as :meth:`Fleet.resolve` reads it."""
    if isinstance(x, tuple) and not (
        len(x) == 2 and any(isinstance(v, (float, np.floating)) for v in x)
    ):
        return list(x)
    return x


def is_paper_description(desc: Any) -> bool:
    """``plan.path`` describes the paper's path model (the default): the caller's
    keywords (e.g. ``metric="km"``) then apply."""
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


def path_spec(region: Any, plan: Any, start: Any, budget: Any, request: PathOptions,
               kind: str, n_sensors: Any) -> PathSpec:
    """The path model of the request: ``plan.path`` when the plan has one, else ``request``
    (``kind`` ``"path"`` or ``"static"``, ``n_sensors`` for the latter)."""
    desc = getattr(plan, "path", None) if plan is not None else None
    if isinstance(desc, Mapping) and desc and not is_paper_description(desc):
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
            raise PlanningError(f"the number of fixed sensors (budget, with start=None) must be "
                                f"an integer >= 1, got {n!r}")
        return PathSpec("static", request, Fleet((), ()), int(n))
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
    return PathSpec("path", request, fleet, None, tuple(models) if models else None)


@dataclass(frozen=True)
class Family:
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


def family(spec: PathSpec, region: Any, k: int) -> Family:
    """The candidates and count limits of ``spec`` (proofs: docs/certificate.md §10)."""
    L = region.n_cells
    if spec.kind == "static":
        return Family(np.arange(L, dtype=np.int64), min(spec.n_sensors, L),
                       np.zeros(0, np.int64), None, math.inf, math.inf, None, False,
                       f"{spec.n_sensors} sensors")
    if spec.paper:
        return _paperfamily(spec, region, k)
    parts = [_robotfamily(spec, region, k, r) for r in range(len(spec.starts))]
    if len(parts) == 1:
        return parts[0]
    # a fleet: each robot's cells are its initial set or a feasible route's; the union of
    # the robots' sets lies in the union of their candidates and holds at most the sum
    cand = np.unique(np.concatenate([np.union1d(p.cand, p.init) for p in parts]))
    n_max = min(cand.size, sum(max(p.n_max, p.init.size) for p in parts))
    text = "fleet budgets " + ", ".join(f"{b:g}" for b in spec.budgets)
    dist, limits = _fleet_limits(parts, n_max)
    return Family(cand, n_max, np.zeros(0, np.int64), dist, math.inf, math.inf, None, False,
                   text, 1, limits)


@dataclass(frozen=True)
class LegFamily:
    """What every route of a towed (leg-average) sensor can observe (docs/certificate.md §12).

    ``cand``: every cell a route may pass; ``rows``: the most observations a plan makes (one
    per stop and a closed tour's return to its start, over the fleet); ``cells``: the
    most leg cells in all (the sum over the observations of the distinct cells each averages).
    """

    cand: np.ndarray
    rows: int
    cells: int
    budget_text: str
    # one robot: its distance of every cell from the start (L,) and the limits on the leg
    # cells beyond each threshold, (thresholds, caps with independent errors, caps shared)
    dist: np.ndarray | None = None
    limits: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    # one robot on straight legs: the chart-length bound G of its polyline (the midpoint
    # cover's, Lemma 10), else None
    cover_span: float | None = None


#: Half the most thresholds of Lemma 9's limits (:func:`leg_limits`), and of Lemma 10's
#: (:func:`leg_midpoint_limits`, one relaxation per piece of the midpoint cover: fewer).
LEG_LADDER, MIDPOINT_LADDER = 40, 10


def leg_limits(span: float, shift: float, unit: float, straight: bool, ladder: int = LEG_LADDER
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Lemma 9 (docs/certificate.md §12): limits on a route's leg cells beyond distance ``r``
    from the start, ``(thresholds, caps_independent, caps_shared)``, ascending thresholds.

    A leg cell whose distance is ``>= r`` is passed at arc length ``>= rho = r - shift``
    (``shift = sqrt 2 / 2`` for straight legs: a crossed cell holds a point of the segment;
    0 on a travel graph, whose legs pass through cell centres), so only the route's last
    ``span - rho`` of arc (``x`` legs' worth, ``x = (span - rho) / unit``) reaches them. Straight
    legs: every whole leg there is at least 1 long and crosses at most ``sqrt 2 l + 1`` cells,
    the one leg cut at ``rho`` fewer than ``sqrt 2 l + 3``, so the leg cells beyond ``r`` (a
    cell counted once per leg through it) are at most ``floor(sqrt 2 x + floor(x) + 3)``; over a
    travel graph a leg of travel ``l`` passes at most ``l / unit + 1`` cells: at most ``2
    floor(x) + 1``. The legs with a cell beyond ``r`` end past ``rho``, at least ``unit``
    apart: at most ``floor(x) + 1`` (the cap of the shared-error weights, each leg's summing to
    1). Thresholds are nudged up against rounding; the caps are computed from the un-nudged
    ones. Any subset of the limits is valid, so ``floor(x)`` runs over a ladder of at most
    ``2 ladder`` values (:func:`cap_ladder`, dense at the far thresholds) rather than every
    integer. None when the route cannot reach beyond its first cell."""
    if not (math.isfinite(span) and unit > 0) or span < unit:
        return None
    thr, ci, cs = [], [], []
    for m in cap_ladder(1, int(math.floor(span / unit)) + 2, ladder) - 1:
        m = int(m)  # floor(x) = m: x just below m + 1
        x = m + 1 - NUDGE
        r = span + shift - x * unit
        if r <= 0:
            continue
        cap_i = (math.floor(math.sqrt(2.0) * x + m + 3) if straight else 2 * m + 1)
        thr.append(r * (1 + 1e-12) + 1e-12)
        ci.append(cap_i)
        cs.append(m + 1)
    if not thr:
        return None
    order = np.argsort(thr)
    return (np.asarray(thr)[order], np.asarray(ci, dtype=np.float64)[order],
            np.asarray(cs, dtype=np.float64)[order])


def leg_midpoint_limits(span: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Lemma 10 (docs/certificate.md §12): limits on a straight-leg route's leg cells at
    chart distance ``>= s`` from a square holding its midpoint ``c``, ``(thresholds,
    caps_independent, caps_shared)``, ascending thresholds; ``span`` the chart-length bound
    ``G`` of the route.

    Such a cell is crossed at a point ``>= rho = s - sqrt 2 / 2`` from ``c``, hence at arc
    length ``>= rho`` from the midpoint's, in the route's last or first ``G / 2 - rho`` of arc.
    Each stretch is Lemma 9's (its whole legs at least 1 long, one leg cut), so each holds
    at most Lemma 9's cap with ``x = G / 2 - rho``; the start's own observation (a cell at arc
    0) adds one cell and one leg: twice :func:`leg_limits` on ``span / 2``, plus 1 (on a
    ladder of :data:`MIDPOINT_LADDER`)."""
    half = leg_limits(span / 2, math.sqrt(2.0) / 2, 1.0, straight=True, ladder=MIDPOINT_LADDER)
    if half is None:
        return None
    thr, ci, cs = half
    return thr, 2 * ci + 1, 2 * cs + 1


def leg_family(spec: PathSpec, region: Any, k: int) -> LegFamily:
    """The candidates and counts of a towed sensor's plans under ``spec`` (docs/certificate.md
    §12, Lemma 8): per robot, the cells a route may pass are those of sensing along (Lemma 5,
    or the straight legs' crossed cells); its observations are at most its stop count (Lemma
    6), a closed tour's return leg added, and at most one more than the legs its travel
    allows; a leg of chart length ``l`` crosses at most ``sqrt 2 l + 1`` cells (straight legs,
    chart length ``<= G``) and a travel-graph leg of travel ``l`` at most ``l / d_min + 1``,
    so the leg cells are at most ``floor(sqrt 2 G)`` (or ``floor(travel / d_min)``) plus the
    observations. A fleet adds its robots' counts over the union of their candidates."""
    if spec.kind != "path":
        raise PlanningError("a towed sensor observes along routes: path='static' has none")
    # one path model per robot for both families (they do not depend on the sensor or on
    # sensing along): a travel graph's distances are found once
    models = spec.models or tuple(path_model(region, s, b, spec.options)
                                  for s, b in zip(spec.starts, spec.budgets, strict=True))
    stops_spec = replace(spec, options=replace(spec.options, sensor=POINT), models=models)
    pass_spec = replace(stops_spec, options=replace(stops_spec.options, sense_along=True))
    cand, rows, cells = [], 0, 0
    dist = limits = span = None
    for r in range(len(spec.starts)):
        stops = _robotfamily(stops_spec, region, k, r)
        passed = _robotfamily(pass_spec, region, k, r)
        # one observation per stop, and a closed tour's return leg; each leg travels at
        # least d_min, so at most floor(travel / d_min) legs follow the start's own cell
        n_rows = stops.n_max + int(spec.closed)
        if math.isfinite(stops.d_min) and stops.d_min > 0:
            n_rows = min(n_rows, 1 + math.floor(stops.travel / stops.d_min + 1e-9))
        pm = models[r]
        if pm.traversable == "none":  # straight legs: the chart argument
            G = float(pm.grid_budget_bound()) * (1 + 1e-9) + 1e-9
            if getattr(pm, "_wrap", True) or not math.isfinite(G):
                raise PlanningError("the towed sensor's certificate bounds the cells a leg "
                                    "crosses on the grid's chart: a grid whose longitudes "
                                    "wrap has no such bound; give traversable='valid'")
            along = math.floor(math.sqrt(2.0) * G)
            if len(spec.starts) == 1:  # Lemmas 9 and 10 on the chart
                dist = np.asarray(pm.chart_distance(pm.start, np.arange(region.n_cells)),
                                  dtype=np.float64)
                limits = leg_limits(G, math.sqrt(2.0) / 2, 1.0, straight=True)
                span = G
        elif math.isfinite(passed.d_min) and passed.d_min > 0:
            along = math.floor(passed.travel / passed.d_min + 1e-9)
            if len(spec.starts) == 1 and passed.dist is not None:  # Lemma 9 on the graph
                dist = passed.dist
                limits = leg_limits(passed.travel, 0.0, passed.d_min, straight=False)
        else:  # no spacing: every observation may average every candidate
            along = n_rows * passed.cand.size
        cand.append(passed.cand)
        rows += n_rows
        cells += min(along + n_rows, n_rows * passed.cand.size)
    text = (f"budget={spec.budgets[0]:g}" if len(spec.starts) == 1 else
            "fleet budgets " + ", ".join(f"{b:g}" for b in spec.budgets))
    return LegFamily(np.unique(np.concatenate(cand)).astype(np.int64), int(rows), int(cells),
                     text, dist, limits, span)


def _fleet_limits(parts: list[Family], n_max: int
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
        lim = start_limit(p.travel, p.d_min, max(p.n_max, 2), p.ways)
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


def _paperfamily(spec: PathSpec, region: Any, k: int) -> Family:
    """The paper's path (grid or km, straight lines, open, no stop cost)."""

    start, budget, metric = spec.starts[0], spec.budgets[0], spec.metric
    L = region.n_cells
    dist = np.asarray(region.distance(start, np.arange(L), metric=metric), dtype=np.float64)
    Bp = budget + DIST_EPS * max(1.0, budget)  # every path cost the planners accept is <= Bp
    cand = np.flatnonzero(dist <= Bp)
    d_min = 1.0 if metric == "grid" else min_spacing_km(region, cand)
    n_max = min(cand.size, math.floor(Bp / d_min) + 1) if d_min > 0 else cand.size
    init = _paper_initial_cells(region, start, budget, k)
    return Family(cand, int(n_max), init, dist, d_min, Bp, Bp if metric == "grid" else None,
                   True, f"budget={budget:g}")


def _paper_initial_cells(region: Any, start: int, budget: float, k: int) -> np.ndarray:
    """The greedy's forced initial set on the paper's path: start + k-1 nearest (grid)."""
    return np.asarray(make_path_model(region, start, budget).initial_cells(k), np.int64)


def _robotfamily(spec: PathSpec, region: Any, k: int, r: int) -> Family:
    """One robot of any path model: candidates by travel distance, count by spacing and stop
    cost, the start's limits in the model's travel distance (docs/certificate.md §10)."""
    start, budget = spec.starts[r], spec.budgets[r]
    if spec.models is not None:  # the plan's own model (keeps a traversable mask)
        pm = spec.models[r]
    else:
        pm = path_model(region, start, budget, spec.options)
    if spec.sense_along and pm.traversable == "none":
        return _straight_sensingfamily(spec, pm, region, k)
    c = spec.stop_cost
    Bp = budget + DIST_EPS * max(1.0, budget)
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
    return Family(cand, n_max, init, np.where(np.isfinite(d_s), d_s, np.inf), d_min, travel,
                   cover_budget, False, f"budget={budget:g} ({pm.unit})",
                   2 if spec.closed else 1)


def _straight_sensingfamily(spec: PathSpec, pm: Any, region: Any, k: int) -> Family:
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
        return Family(np.arange(L, dtype=np.int64), L, init, None, math.inf, math.inf,
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
    return Family(cand, n_max, init, None, math.inf, math.inf, None, False, text)


def _spacing(region: Any, cand: np.ndarray, spec: PathSpec) -> float:
    """Smallest travel distance between two distinct candidates, in the budget's unit."""
    if spec.metric == "grid":
        return 1.0
    d = min_spacing_km(region, cand)
    return d / spec.speed if spec.speed is not None else d


def min_spacing_km(region: Any, cand: np.ndarray) -> float:
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


def cap_ladder(lo: int, hi: int, count: int = 10) -> np.ndarray:
    """About ``2 count`` integer caps in ``[lo, hi)``: geometric (dense near ``lo``) + linear."""
    if hi <= lo:
        return np.zeros(0, np.int64)
    geo = np.geomspace(lo, max(hi - 1, lo), count)
    lin = np.linspace(lo, max(hi - 1, lo), count)
    return np.unique(np.round(np.concatenate([geo, lin])).astype(np.int64))


def start_limit(Bp: float, d_min: float, n_max: int, ways: int = 1
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
    for c in cap_ladder(1, n_max)[::-1]:
        r = (Bp - (c - NUDGE) * d_min) / ways
        if r <= 0:
            continue
        cap = math.floor((Bp - ways * r) / d_min) + 1
        thr.append(r * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    if not thr:
        return None
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)
