"""The paper's baselines: straight transects and the random walk.

Both move on the grid from the start cell and return a :class:`Plan` whose ``cells`` are the
distinct valid cells visited (first-visit order) and whose ``route`` is the travel itself.
Directions are geographic: ``"up"`` is north (increasing latitude), ``"down"`` south,
``"left"`` west (decreasing longitude), ``"right"`` east, whatever the grid's row order.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import as_factor_matrix, as_generator
from ..errors import LrmError, PlanningError
from ..information import fisher_information
from ..region import Region
from .greedy import _check_budget
from .plan import Plan, check_region

__all__ = ["transect", "random_walk", "DIRECTIONS"]

DIRECTIONS: tuple[str, ...] = ("up", "down", "left", "right")
_TOL = 1e-9


def _axis_sign(values: np.ndarray) -> int:
    """+1 when the coordinate increases with the grid index, -1 when it decreases."""
    return -1 if values.size > 1 and values[-1] < values[0] else 1


def _information(Y: Any, region: Region, cells: list[int], ridge: float) -> tuple[Any, float]:
    if Y is None:
        return None, float("nan")
    Yk = as_factor_matrix(Y, region)
    return Yk, fisher_information(Yk, cells, ridge)


def _first_visits(route: list[int]) -> list[int]:
    return list(dict.fromkeys(route))


def transect(
    region: Region,
    start: Any,
    budget: float,
    direction: str,
    *,
    Y: Any = None,
    ridge: float = 0.0,
) -> Plan:
    """A straight transect from ``start``, one grid step (cost 1) at a time.

    ``direction`` is ``"up"`` (north), ``"down"``, ``"left"`` (west) or ``"right"``. The walk
    makes ``floor(budget + 1e-9)`` steps. When the next step would leave the grid it instead
    steps once orthogonally (east for up/down transects, south for left/right ones; the other
    way when that is off the grid too, and from then on) and reverses direction (a lawnmower).
    Every grid position passed is observed; masked positions are crossed (their steps count)
    but are not among the plan's cells. The plan's ``cost`` is the number of steps walked up to
    the last observed (valid) cell: steps over masked positions after it observe nothing and
    are not part of the plan. ``Y`` (optional) gives the plan's Fisher information.
    """
    if direction not in DIRECTIONS:
        raise PlanningError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    region = check_region(region)
    start_cell = region.resolve_cell(start, "start")
    budget = _check_budget(budget)
    ny, nx = region.shape
    north = _axis_sign(region.lat.values)  # row step that goes north
    east = _axis_sign(region.lon.values)  # col step that goes east
    step = {"up": (north, 0), "down": (-north, 0), "left": (0, -east), "right": (0, east)}
    d = np.array(step[direction])
    orth = np.array(step["right"] if direction in ("up", "down") else step["down"])
    grid = region.cell_grid
    pos = region.grid_index[start_cell].copy()
    inside = lambda p: 0 <= p[0] < ny and 0 <= p[1] < nx  # noqa: E731
    route = [start_cell]
    route_cost = [0.0]
    n_steps = math.floor(budget + _TOL)
    moves = 0
    for _ in range(n_steps):
        if inside(pos + d):
            pos = pos + d
        else:
            if not inside(pos + orth):
                orth = -orth
            d = -d
            if inside(pos + orth):
                pos = pos + orth
            elif inside(pos + d):  # a one-wide grid: just turn back
                pos = pos + d
            else:
                break  # a single grid position: nowhere to go
        moves += 1
        c = int(grid[pos[0], pos[1]])
        if c >= 0:
            route.append(c)
            route_cost.append(float(moves))
    cells = _first_visits(route)
    Yk, info = _information(Y, region, cells, ridge)
    return Plan.build(
        region=region, cells=cells, route=route, cost=route_cost[-1], information=info,
        route_cost=route_cost,
        criterion=None, budget=budget, start=start_cell, ridge=float(ridge),
        method=f"transect-{direction}", cost_function="steps", Y=Yk,
        history={},
    )


def _neighbours(grid: np.ndarray, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
    """Valid 8-neighbours of a grid position: their cell indices (ascending) and step lengths."""
    ny, nx = grid.shape
    r0, r1 = max(row - 1, 0), min(row + 2, ny)
    c0, c1 = max(col - 1, 0), min(col + 2, nx)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    cells = grid[r0:r1, c0:c1]
    keep = (cells >= 0) & ~((rr == row) & (cc == col))
    lengths = np.where((rr != row) & (cc != col), math.sqrt(2.0), 1.0)
    return cells[keep], lengths[keep]


def random_walk(
    region: Region,
    start: Any,
    budget: float,
    rng: Any = None,
    *,
    Y: Any = None,
    ridge: float = 0.0,
) -> Plan:
    """The paper's random-sampling baseline: a random walk on valid 8-neighbours.

    From the last cell, the neighbours are the valid (unmasked) cells among its 8 grid
    neighbours whose step (1, or sqrt 2 diagonally) still fits in the remaining budget. A
    random unvisited one is taken if any, else a random one among them; the walk stops when no
    neighbour fits. The cost is the walk's Euclidean length in grid units. ``rng``: a seed or
    ``numpy.random.Generator`` (deterministic given a seed).
    """
    region = check_region(region)
    start_cell = region.resolve_cell(start, "start")
    budget = _check_budget(budget)
    try:
        gen = as_generator(rng)
    except LrmError:
        raise PlanningError(f"rng must be None, an int seed or a numpy Generator, got {rng!r}") \
            from None
    grid = region.cell_grid
    gi = region.grid_index
    route = [start_cell]
    route_cost = [0.0]
    visited = {start_cell}
    cost = 0.0
    cur = start_cell
    while True:
        nb, lengths = _neighbours(grid, int(gi[cur, 0]), int(gi[cur, 1]))
        fits = cost + lengths <= budget + _TOL
        nb, lengths = nb[fits], lengths[fits]
        if nb.size == 0:
            break
        fresh = np.array([c not in visited for c in nb.tolist()], dtype=bool)
        pick = np.flatnonzero(fresh) if fresh.any() else np.arange(nb.size)
        j = int(pick[gen.integers(pick.size)])
        cur = int(nb[j])
        cost += float(lengths[j])
        route.append(cur)
        route_cost.append(cost)
        visited.add(cur)
    cells = _first_visits(route)
    Yk, info = _information(Y, region, cells, ridge)
    return Plan.build(
        region=region, cells=cells, route=route, cost=cost, information=info, criterion=None,
        route_cost=route_cost,
        budget=budget, start=start_cell, ridge=float(ridge), method="random",
        cost_function="path", Y=Yk, history={},
    )
