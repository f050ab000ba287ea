"""The limits a certificate's relaxation takes, and the midpoint cover.

A route of bounded length holds few cells far from its start or from its midpoint: count limits
by distance from the start (the plan family's), the cover of the midpoint's possible positions by
squares (one relaxation per square, the largest split further), and the checks that a given plan
lies within them. :func:`limited_relaxation` solves one relaxation over candidates with nested
count limits; the Fisher, towed and variance certificates all build on it (docs/certificate.md
§4-6).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import PlanningError
from .dopt import Bound, Polytope, solve_relaxation
from .families import NUDGE, cap_ladder, start_limit

__all__ = ["limited_relaxation", "start_limits", "square_distance", "midpoint_cover",
           "cover_max", "in_some_piece", "check_plan_feasible", "check_plan_limits"]


def limited_relaxation(Y: np.ndarray, cells: np.ndarray, n: float, levels: list,
                       caps: list, ridge: float, relax: Any = None, **opts: Any) -> Any:
    """The relaxation over the columns ``cells`` of ``Y`` with at most ``n`` cells in all and,
    for each level family ``levels[f]`` (a level per cell), at most ``caps[f][j]`` cells at a
    level above ``j``. ``relax(Y, cells, polytope, ridge, **opts)`` solves it (default: the
    Fisher relaxation of :mod:`lrm_cvx.planning.dopt`; a variance criterion's is
    :func:`~lrm_cvx.planning.varbound.variance_relaxation`)."""
    relax = solve_relaxation if relax is None else relax
    return relax(Y, cells, Polytope(n, cells.size, levels, caps), ridge, **opts)


def start_limits(fam: Any, tighten: bool, n_max: int, cand: np.ndarray) -> tuple[Any, Any]:
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


def _square_limit(Bp: float, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance limits from the midpoint's square: at most ``floor(Bp - 2 s) + 2`` cells at
    distance ``>= s > 0`` from it (grid units, ``d_min = 1``); ascending thresholds."""
    thr, caps = [], []
    for c in cap_ladder(2, n_max)[::-1]:
        s = (Bp - c + 1 + 2 * NUDGE) / 2
        if s <= 0:
            continue
        cap = math.floor(Bp - 2 * s) + 2
        thr.append(s * (1 + 1e-12) + 1e-12)
        caps.append(cap)
    return np.asarray(thr), np.asarray(caps, dtype=np.float64)


def square_distance(points: np.ndarray, r0: float, c0: float, h: float) -> np.ndarray:
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
            if square_distance(centre[None, :], *q)[0] <= radius:
                out.append(q)
    return out


def midpoint_cover(
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
    pos = region.grid_index[cand].astype(np.float64)
    sq_thr, sq_caps = _square_limit(Bp, n_max)
    half = Bp / 2

    def solve(q: tuple[float, float, float]) -> Bound:
        dq = square_distance(pos, *q)
        sel = np.flatnonzero(dq <= half * (1 + 1e-12) + 1e-12)
        levels = [np.searchsorted(sq_thr, dq[sel], side="right")]
        caps = [sq_caps]
        if start_lv is not None:
            levels.append(start_lv[sel])
            caps.append(start_lim[1])
        return limited_relaxation(Y, cand[sel], n_max, levels, caps, ridge, relax, **opts)

    return cover_max(solve, centre, half, cover, max_pieces, floor_value)


def cover_max(solve: Any, centre: np.ndarray, half: float, cover: int, max_pieces: int,
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


def check_plan_feasible(
    cells: np.ndarray, init: np.ndarray, cand: np.ndarray, n_max: int, plan: Any, budget: Any,
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


def check_plan_limits(
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
    if not in_some_piece(region.grid_index[cells].astype(np.float64), leaves, Bp / 2,
                          *_square_limit(Bp, n_max)):
        raise PlanningError(msg + "no piece of the midpoint cover holds it; the certificate "
                            "does not cover it")


def in_some_piece(pos: np.ndarray, leaves: list[tuple[float, float, float, float]],
                   reach: float, thr: np.ndarray, caps: np.ndarray,
                   groups: np.ndarray | None = None) -> bool:
    """Whether some final piece ``(r0, c0, side, value)`` of a midpoint cover holds the points
    ``pos (m, 2)``: all within ``reach`` of the square, and at most ``caps[j]`` of them at
    distance ``>= thr[j]`` for every ``j`` (``groups (m,)``: count the distinct groups with
    such a point instead, a towed plan's legs under shared errors)."""
    for r0, c0, h, _ in leaves:
        dq = square_distance(pos, r0, c0, h)
        if np.any(dq > reach * (1 + 1e-12) + 1e-12):
            continue
        beyond = dq[:, None] >= thr[None, :]  # (points, thresholds)
        counts = (beyond.sum(axis=0) if groups is None else
                  np.array([np.unique(groups[beyond[:, j]]).size for j in range(thr.size)]))
        if np.all(counts <= caps):
            return True
    return False
