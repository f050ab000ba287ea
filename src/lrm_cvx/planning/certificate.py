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
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import scipy.sparse as sps

from .._validation import as_factor_matrix
from ..errors import PlanningError, SolverError
from .dopt import (
    DIST_EPS,
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
from .families import NUDGE as _NUDGE
from .families import (
    cap_ladder,
    describe_path,
    family,
    leg_family,
    leg_midpoint_limits,
    min_spacing_km,
    path_spec,
    start_limit,
)
from .request import PathOptions
from .sensors import footprint_factors, observation_rows, observed_cells
from .terms import prior_terms

__all__ = ["PlanCertificate", "plan_bound"]

# the old names (bound.py and the tests import them)
_start_limit, _cap_ladder, _min_spacing_km = start_limit, cap_ladder, min_spacing_km


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

    ``criterion`` is what the bound bounds: ``"fisher"`` (``log det(ridge I + sum y y^T)``,
    nats) or a variance criterion (``"gp-variance"``, ``"a-optimal"``: the variance removed,
    ``unit == "unit^2"``; then ``information`` is the plan's value, ``initial_information``
    the initial set's, ``relaxation`` a :class:`~lrm_cvx.planning.varbound.VarianceBound`,
    ``volume_ratio`` None and ``greedy_information`` / ``refined_information`` the greedy's
    and the kept route's values; docs/certificate.md §13). ``plan_criterion`` is what the
    plan was chosen for (``None`` for a baseline, which
    optimises nothing and is judged by its Fisher information as in the paper; ``"fisher
    (posterior)"`` for a Fisher greedy on the fold-in's posterior). When the two differ
    (``comparable`` is False) ``information`` is still the plan's Fisher information but
    ``gap`` and ``volume_ratio`` are NaN: a gap between different criteria means nothing.

    ``towed``: for a towed (leg-average) sensor, the most observations a plan makes and the
    most leg cells they average in all (docs/certificate.md §12; ``n_max`` is then the
    observations and ``initial_information`` is ``-inf``: no forced set is covered); else None.
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
    towed: tuple[int, int] | None = None  # a towed sensor's (observations, leg cells) limits

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

    @property
    def unit(self) -> str:
        """The unit of ``bound``, ``information`` and ``gap``: ``"nats"`` (Fisher) or
        ``"unit^2"`` (variance removed, the data's unit squared)."""
        return "nats" if self.criterion == "fisher" else "unit^2"

    def _variance_rows(self) -> list[tuple[str, str]]:
        """(label, text) rows of a variance criterion's certificate."""
        rows = [("upper bound", f"{self.bound:.6g} unit^2 of variance removed by any plan "
                                f"({self.criterion})")]
        if self.information is not None and not self.comparable:
            who = self.plan_criterion
            rows += [("plan value", f"{self.information:.6g} unit^2 removed"),
                     ("no gap", f"the plan was chosen for the {who} criterion, the bound is on "
                                f"{self.criterion}")]
        elif self.information is not None:
            rel = self.relative_gap
            rows += [("plan value", f"{self.information:.6g} unit^2 removed"),
                     ("certified gap", f"{self.gap:.4g} unit^2"
                      + (f" ({100 * rel:.2f} % of the bound)" if rel is not None else ""))]
            if self.refined_information is not None:
                rows += [("greedy / kept route", f"{self.greedy_information:.6g} / "
                                                 f"{self.refined_information:.6g} unit^2"),
                         ("gap split", f"plan slack {self.plan_slack:.4g} + bound slack "
                                       f"{self.bound_slack:.4g} unit^2")]
        r = self.relaxation
        rows.append(("relaxation", f"{r.value:.6g} (primal {r.primal:.6g}, status {r.status}, "
                                   f"{r.solver})"))
        if self.path.get("kind", "path") == "path" and self.path.get("n_robots", 1) == 1:
            rows.append(("initial set", f"{self.initial_information:.6g} unit^2"))
        rows.append(("cells", f"at most {self.n_max} out of {self.n_candidates} candidates "
                              "within the budget"))
        if self.tightened:
            rows.append(("tightened", f"distance limits, midpoint cover of {len(self.leaves)} "
                                      "squares"))
        model = describe_path(self.path)
        if model:
            rows.append(("path model", model))
        return rows

    def __repr__(self) -> str:
        if self.criterion != "fisher":
            head = (f"PlanCertificate(start={self.start}, budget={self.budget:g} "
                    f"({self.metric}), criterion={self.criterion}, k={self.k})")
            return "\n".join([head] + [f"  {a:<20} {b}" for a, b in self._variance_rows()])
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
        if self.towed is None and self.path.get("kind", "path") == "path" and \
                self.path.get("n_robots", 1) == 1:
            # (a fleet's and a static placement's forced cells are inside the relaxation)
            lines.append(f"  initial set          {self.initial_information:.6g} nats")
        if self.online_bound is not None:
            lines.append(f"  online bound         {self.online_bound:.6g} nats")
        if self.towed is not None:
            lines.append(f"  towed sensor: at most {self.towed[0]} observations averaging "
                         f"{self.towed[1]} leg cells in all, out of {self.n_candidates} "
                         f"candidates")
        else:
            lines.append(
                f"  at most {self.n_max} cells out of {self.n_candidates} candidates "
                f"within the budget"
            )
        if self.tightened:
            lines.append(f"  tightened: distance limits, midpoint cover of "
                         f"{len(self.leaves)} squares")
        model = describe_path(self.path)
        if model:
            lines.append(f"  path model           {model}")
        return "\n".join(lines)

    def _repr_html_(self) -> str:
        if self.criterion != "fisher":
            body = "".join(f"<tr><td>{a}</td><td>{b}</td></tr>" for a, b in self._variance_rows())
            return f"<table><caption>PlanCertificate ({self.criterion})</caption>{body}</table>"
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
        ]
        if self.towed is not None:
            rows.append(("towed: observations / leg cells / candidates",
                         f"{self.towed[0]} / {self.towed[1]} / {self.n_candidates}"))
        else:
            rows += [("initial set (nats)", f"{self.initial_information:.6g}"),
                     ("max cells / candidates", f"{self.n_max} / {self.n_candidates}")]
        rows += [
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
        return _variance_certificate(Y, region, spec, plan, bounded, terms, ridge,
                                     cover if tighten else 0, max_pieces, tighten, tol, solver)
    if sensor.is_leg:  # the observations depend on the legs (docs §12)
        if path_aware:
            warnings.warn("path_aware bounds point stops: a towed sensor's certificate is "
                          "docs/certificate.md §12's", UserWarning, stacklevel=2)
        return _towed_bound(Y, region, spec, sensor, plan, ridge, {"solver": solver,
                                                                   "tol": tol},
                            cover if tighten else 0, max_pieces)
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
    start_lim, start_lv = _start_limits(fam, tighten, n_max, cand)
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
            plan, Y, region, refine if fam.paper and sensor.is_point else False, metric,
            plan_criterion,
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


_TERM_KEYS = ("prior_precision", "noise_var", "target_weights", "region", "spatial_cov",
              "prior_cov", "targets", "pool")


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


def _variance_certificate(Y: np.ndarray, region: Any, spec: Any, plan: Any, criterion: str,
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
                and _plan_criterion(plan) == criterion):
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
    obj = variance_objective(criterion, Y, universe, ridge, terms)

    def at(c: np.ndarray) -> np.ndarray:
        return np.searchsorted(universe, c)

    def value(c: np.ndarray) -> float:
        c = np.unique(c)
        return obj.value(at(c), np.ones(c.size))

    init_value = value(init) if init.size else -math.inf
    start_lim, start_lv = _start_limits(fam, tighten, n_max, cand)
    opts = {"tol": tol, "solver": solver}

    def relax(_Y: Any, c: np.ndarray, poly: _Polytope, _ridge: float, **o: Any) -> Any:
        return variance_relaxation(obj, at(c), poly, **o)

    leaves: list[tuple[float, float, float, float]] = []
    if cover and fam.cover_budget is not None and fam.cover_budget >= 2.0:
        centre = region.grid_index[spec.starts[0]].astype(np.float64)
        relaxed, leaves = _midpoint_cover(Y, region, cand, start_lv, start_lim, centre,
                                          fam.cover_budget, n_max, ridge, cover, max_pieces,
                                          init_value, opts, relax)
    else:
        levels, caps = ([start_lv], [start_lim[1]]) if start_lim else ([], [])
        relaxed = relax(Y, cand, _Polytope(n_max, cand.size, levels, caps), ridge, **opts)
    bound = max(init_value, relaxed.value)
    information = gap = greedy_v = refined_v = None
    plan_criterion = _plan_criterion(plan) if plan is not None else None
    if plan is not None:
        _check_plan_feasible(cells, init, cand, n_max, plan, fam.budget_text, 0.0)
        _check_plan_limits(cells, init, region, fam.dist, start_lim, leaves, fam.cover_budget,
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


def _towed_bound(Y: np.ndarray, region: Any, spec: Any, sensor: Any, plan: Any, ridge: float,
                 opts: dict[str, Any], cover: int = 0, max_pieces: int = 40
                 ) -> PlanCertificate:
    """The certificate of a towed (leg-average) sensor (docs/certificate.md §12).

    An observation averaging the ``m`` distinct cells of its leg has the whitened row ``u =
    sum y / sqrt m`` (independent cell errors) or ``sum y / m`` (shared), and ``u u^T <= sum
    y y^T`` over the leg (``1 / m`` of it when shared) by Cauchy-Schwarz. So a plan's
    information is at most ``log det(ridge I + sum_c w_c y_c y_c^T)`` with ``0 <= w_c <=
    rows`` (a cell is in at most one leg per observation) and ``sum w_c`` at most the leg
    cells in all (shared: the observations), which the count-only relaxation bounds (weights
    up to ``rows``: the columns scaled by ``sqrt rows``, the total divided by it). One robot
    adds Lemma 9's limits from the start and, on straight legs with ``cover`` > 0, the
    maximum over Lemma 10's midpoint cover (``max_pieces`` relaxations at most)."""
    from ..oracles import row_information

    k = Y.shape[0]
    fam = leg_family(spec, region, k)
    independent = sensor.errors == "independent"
    total = fam.cells if independent else fam.rows

    def limited(limits: Any, dist: np.ndarray) -> tuple[list, list]:
        """One level family from ``limits`` at the candidates' ``dist`` (caps per row)."""
        thr, caps_i, caps_s = limits
        cap = caps_i if independent else caps_s
        keep = cap < total  # a cap at the total adds nothing
        if not keep.any():
            return [], []
        return ([np.searchsorted(thr[keep], dist, side="right")], [cap[keep] / fam.rows])

    levels, caps = [], []
    if fam.limits is not None:  # Lemma 9: the leg cells beyond each distance from the start
        levels, caps = limited(fam.limits, fam.dist[fam.cand])
    Yc = math.sqrt(fam.rows) * np.ascontiguousarray(Y[:, fam.cand], dtype=np.float64)
    mid = (leg_midpoint_limits(fam.cover_span) if cover and fam.cover_span is not None
           and fam.cover_span >= 2.0 else None)
    leaves: list[tuple[float, float, float, float]] = []
    if mid is None:
        relax = _relaxation(Yc, np.arange(fam.cand.size),
                            _Polytope(total / fam.rows, fam.cand.size, levels, caps), ridge,
                            **opts)
    else:  # Lemma 10: the midpoint cover (one robot on straight legs)
        pos = region.grid_index[fam.cand].astype(np.float64)
        reach = fam.cover_span / 2 + math.sqrt(2.0) / 2  # a leg cell's centre from c

        def solve(q: tuple[float, float, float]) -> Bound:
            dq = _square_distance(pos, *q)
            sel = np.flatnonzero(dq <= reach * (1 + 1e-12) + 1e-12)
            lv_q, cap_q = limited(mid, dq[sel])
            poly = _Polytope(total / fam.rows, sel.size, [lv[sel] for lv in levels] + lv_q,
                             caps + cap_q)
            return _relaxation(Yc, sel, poly, ridge, **opts)

        relax, leaves = _cover_max(solve, region.grid_index[spec.starts[0]].astype(np.float64),
                                   fam.cover_span / 2, cover, max_pieces, -math.inf)
    bound = float(relax.value)
    information = gap = ratio = None
    plan_criterion = _plan_criterion(plan) if plan is not None else None
    if plan is not None:
        rows = observation_rows(plan)
        robot_costs = getattr(plan, "robot_costs", None)
        costs = np.atleast_1d(np.asarray(plan.cost if robot_costs is None else robot_costs,
                                         dtype=np.float64))
        over = [float(c) > b + DIST_EPS * max(1.0, b)
                for c, b in zip(costs, spec.budgets, strict=False)]
        outside = np.setdiff1d(observed_cells(rows), fam.cand)
        if any(over) or outside.size or rows.shape[0] > fam.rows:
            raise PlanningError(
                f"the towed plan is not a route within {fam.budget_text}: its route costs "
                f"{', '.join(f'{c:g}' for c in costs)}, {outside.size} of its leg cells lie "
                f"beyond the budget's reach and it makes {rows.shape[0]} observations (at most "
                f"{fam.rows}); the certificate does not cover it")
        if leaves:
            _check_towed_cover(rows, region, leaves, fam.cover_span, mid, independent)
        information = float(row_information(Y, rows, ridge, errors=sensor.errors))
        if plan_criterion in (None, "fisher"):
            gap, ratio = _gap(bound, information, k)
        else:
            gap, ratio = math.nan, math.nan
    return PlanCertificate(
        bound=bound, information=information, gap=gap, volume_ratio=ratio, n_max=fam.rows,
        n_candidates=int(fam.cand.size), k=k,
        start=int(spec.starts[0]), budget=float(sum(spec.budgets)), ridge=ridge,
        metric=spec.metric, initial_information=-math.inf, relaxation=relax,
        criterion="fisher", plan_criterion=plan_criterion, path=spec.summary(),
        towed=(int(fam.rows), int(fam.cells)), leaves=tuple(leaves), tightened=bool(leaves))


def _start_limits(fam: Any, tighten: bool, n_max: int, cand: np.ndarray) -> tuple[Any, Any]:
    """``(limits, levels)``: the family's count limits by distance from the start (its own, or
    Lemma 10's from its minimum spacing) and each candidate's level in them; ``(None, None)``
    without ``tighten`` or a distance to limit by."""
    start_lim = None
    if tighten and fam.limits is not None:
        start_lim = fam.limits
    elif tighten and fam.dist is not None and math.isfinite(fam.d_min) and fam.d_min > 0:
        start_lim = start_limit(fam.travel, fam.d_min, n_max, fam.ways)
    start_lv = (
        np.searchsorted(start_lim[0], fam.dist[cand], side="right") if start_lim else None
    )
    return start_lim, start_lv


def _check_towed_cover(rows: Any, region: Any, leaves: list[tuple[float, float, float, float]],
                       span: float, limits: tuple[np.ndarray, np.ndarray, np.ndarray],
                       independent: bool) -> None:
    """A towed plan's legs (``rows``, one per observation) lie in some piece of the midpoint
    cover: every leg cell within ``span / 2 + sqrt 2 / 2`` of the piece and Lemma 10's counts
    (cells once per leg; shared errors: the legs) within the caps; else PlanningError."""
    leg, cell = sps.csr_matrix(rows).nonzero()
    thr, caps_i, caps_s = limits
    if _in_some_piece(region.grid_index[cell].astype(np.float64), leaves,
                      span / 2 + math.sqrt(2.0) / 2, thr, caps_i if independent else caps_s,
                      None if independent else leg):
        return
    raise PlanningError("the towed plan's legs lie in no piece of the midpoint cover "
                        "(docs/certificate.md §12, Lemma 10); the certificate does not cover "
                        "it")


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


def _square_limit(Bp: float, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance limits from the midpoint's square: at most ``floor(Bp - 2 s) + 2`` cells at
    distance ``>= s > 0`` from it (grid units, ``d_min = 1``); ascending thresholds."""
    thr, caps = [], []
    for c in cap_ladder(2, n_max)[::-1]:
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
    opts: dict[str, Any], relax: Any = None,
) -> tuple[Bound, list[tuple[float, float, float, float]]]:
    """Max over a cover of the possible path midpoints of the relaxation restricted to each piece.

    The midpoint lies in the closed disk ``B(start, Bp / 2)``, tiled by squares of side
    ``Bp / (2 cover)`` with a corner at the start. Piece ``Q``: the candidates within ``Bp / 2``
    of ``Q``, the start's distance limits and ``Q``'s distance limits. The piece with the largest
    bound is split into four (children keep ``min(own, parent)``: both bound the midpoints in
    the child) until ``max_pieces`` relaxations have been solved or it is below ``floor_value``
    (the initial set's information, which the certificate takes the maximum with anyway).
    Returns the largest piece's :class:`Bound` and every final piece ``(r0, c0, side, value)``.
    ``relax(Y, cells, polytope, ridge, **opts)`` solves a piece (default: the Fisher
    relaxation; a variance criterion's is :func:`~lrm_cvx.planning.varbound.
    variance_relaxation`).
    """
    relax = _relaxation if relax is None else relax
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
        return relax(Y, cand[sel], poly, ridge, **opts)

    return _cover_max(solve, centre, half, cover, max_pieces, floor_value)


def _cover_max(solve: Any, centre: np.ndarray, half: float, cover: int, max_pieces: int,
               floor_value: float) -> tuple[Bound, list[tuple[float, float, float, float]]]:
    """Max of ``solve(square)`` over squares covering the disk ``B(centre, half)`` where a
    route's midpoint lies: ``2 cover x 2 cover`` squares of side ``half / cover`` first, then the
    piece with the largest bound split into four (children keep ``min(own, parent)``: both
    bound the midpoints in the child) until ``max_pieces`` relaxations have been solved, the
    piece is under half a grid unit wide, or its bound is below ``floor_value``. Returns the
    largest piece's :class:`Bound` and every final piece ``(r0, c0, side, value)``."""
    squares = _cover_squares(centre, half, centre[0] - half, centre[1] - half, 2 * half,
                             2 * cover)
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
    if not _in_some_piece(region.grid_index[cells].astype(np.float64), leaves, Bp / 2,
                          *_square_limit(Bp, n_max)):
        raise PlanningError(msg + "no piece of the midpoint cover holds it; the certificate "
                            "does not cover it")


def _in_some_piece(pos: np.ndarray, leaves: list[tuple[float, float, float, float]],
                   reach: float, thr: np.ndarray, caps: np.ndarray,
                   groups: np.ndarray | None = None) -> bool:
    """Whether some final piece ``(r0, c0, side, value)`` of a midpoint cover holds the points
    ``pos (m, 2)``: all within ``reach`` of the square, and at most ``caps[j]`` of them at
    distance ``>= thr[j]`` for every ``j`` (``groups (m,)``: count the distinct groups with
    such a point instead, a towed plan's legs under shared errors)."""
    for r0, c0, h, _ in leaves:
        dq = _square_distance(pos, r0, c0, h)
        if np.any(dq > reach * (1 + 1e-12) + 1e-12):
            continue
        beyond = dq[:, None] >= thr[None, :]  # (points, thresholds)
        counts = (beyond.sum(axis=0) if groups is None else
                  np.array([np.unique(groups[beyond[:, j]]).size for j in range(thr.size)]))
        if np.all(counts <= caps):
            return True
    return False


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
