"""The certificate of a towed (leg-average) sensor (docs/certificate.md §12).

A towed sensor's observations depend on the legs of the route, not on its stops: each is
bounded by the sum of ``y y^T`` over its leg's cells, so the count-only relaxation with weights
up to the observations' count bounds every route within the budget; one robot adds the leg
cells' distance limits and, on straight legs, the midpoint cover with Lemma 10's limits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.sparse as sps

from ..errors import PlanningError
from .cover import cover_max, in_some_piece, limited_relaxation, square_distance
from .dopt import DIST_EPS, Bound
from .families import leg_family, leg_midpoint_limits
from .plan_certificate import PlanCertificate, chosen_criterion, gap_and_ratio
from .sensors import observation_rows, observed_cells

__all__ = ["towed_certificate"]


def towed_certificate(Y: np.ndarray, region: Any, spec: Any, sensor: Any, plan: Any,
                      ridge: float, opts: dict[str, Any], cover: int = 0, max_pieces: int = 40
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
        relax = limited_relaxation(Yc, np.arange(fam.cand.size), total / fam.rows, levels, caps,
                                   ridge, **opts)
    else:  # Lemma 10: the midpoint cover (one robot on straight legs)
        pos = region.grid_index[fam.cand].astype(np.float64)
        reach = fam.cover_span / 2 + math.sqrt(2.0) / 2  # a leg cell's centre from c

        def solve(q: tuple[float, float, float]) -> Bound:
            dq = square_distance(pos, *q)
            sel = np.flatnonzero(dq <= reach * (1 + 1e-12) + 1e-12)
            lv_q, cap_q = limited(mid, dq[sel])
            return limited_relaxation(Yc, sel, total / fam.rows, [lv[sel] for lv in levels] + lv_q,
                                      caps + cap_q, ridge, **opts)

        relax, leaves = cover_max(solve, region.grid_index[spec.starts[0]].astype(np.float64),
                                   fam.cover_span / 2, cover, max_pieces, -math.inf)
    bound = float(relax.value)
    information = gap = ratio = None
    plan_criterion = chosen_criterion(plan) if plan is not None else None
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
            gap, ratio = gap_and_ratio(bound, information, k)
        else:
            gap, ratio = math.nan, math.nan
    return PlanCertificate(
        bound=bound, information=information, gap=gap, volume_ratio=ratio, n_max=fam.rows,
        n_candidates=int(fam.cand.size), k=k,
        start=int(spec.starts[0]), budget=float(sum(spec.budgets)), ridge=ridge,
        metric=spec.metric, initial_information=-math.inf, relaxation=relax,
        criterion="fisher", plan_criterion=plan_criterion, path=spec.summary(),
        towed=(int(fam.rows), int(fam.cells)), leaves=tuple(leaves), tightened=bool(leaves))


def _check_towed_cover(rows: Any, region: Any, leaves: list[tuple[float, float, float, float]],
                       span: float, limits: tuple[np.ndarray, np.ndarray, np.ndarray],
                       independent: bool) -> None:
    """A towed plan's legs (``rows``, one per observation) lie in some piece of the midpoint
    cover: every leg cell within ``span / 2 + sqrt 2 / 2`` of the piece and Lemma 10's counts
    (cells once per leg; shared errors: the legs) within the caps; else PlanningError."""
    leg, cell = sps.csr_matrix(rows).nonzero()
    thr, caps_i, caps_s = limits
    if in_some_piece(region.grid_index[cell].astype(np.float64), leaves,
                      span / 2 + math.sqrt(2.0) / 2, thr, caps_i if independent else caps_s,
                      None if independent else leg):
        return
    raise PlanningError("the towed plan's legs lie in no piece of the midpoint cover "
                        "(docs/certificate.md §12, Lemma 10); the certificate does not cover "
                        "it")
