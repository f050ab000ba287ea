"""The plan certificate's result: the bound, the plan's value, the gap and their reports.

:class:`PlanCertificate` is what :func:`~lrm_cvx.planning.certificate.plan_bound` returns for every
path model, sensor and bounded criterion (docs/certificate.md); :func:`gap_and_ratio` and
:func:`chosen_criterion` are the two readings of a plan every certificate shares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .dopt import Bound
from .families import describe_path

__all__ = ["PlanCertificate", "gap_and_ratio", "chosen_criterion"]


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
        return gap_and_ratio(self.bound, self.refined_information, self.k)[0]

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
        kind = "rank bound" if getattr(r, "active", "") == "rank" else "relaxation bound"
        rows.append(("relaxation", f"{r.value:.6g} ({kind}; primal {r.primal:.6g}, status "
                                   f"{r.status}, {r.solver})"))
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


def gap_and_ratio(bound: float, information: float, k: int) -> tuple[float, float]:
    """``(gap, volume_ratio)`` of a plan of Fisher ``information`` under ``bound`` (nats) in
    ``k`` dimensions: ``bound - information`` and ``exp(-gap / k)`` (0 for an infinite gap;
    ``(0, 1)`` when every feasible plan is singular, so this one is optimal)."""
    if bound == -math.inf and information == -math.inf:
        return 0.0, 1.0  # every feasible plan is singular: this one is optimal
    gap = bound - information
    return float(gap), float(math.exp(-gap / k)) if math.isfinite(gap) else 0.0


def chosen_criterion(plan: Any) -> str | None:
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

