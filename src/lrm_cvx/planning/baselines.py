"""The paper's baselines: straight transects and the random walk, under any path model.

Both move on the grid from the start cell one step at a time (``"up"`` is north, ``"left"`` west,
whatever the grid's row order) and return a :class:`Plan` of the distinct valid cells visited.
They obey the planners' path model (:mod:`lrm_cvx.planning.paths`); with every option at its
default the plans are exactly the paper's.
"""

from __future__ import annotations

import math
import weakref
from typing import Any

import numpy as np

from .._validation import as_factor_matrix, as_generator
from ..errors import LrmError, PlanningError
from ..information import fisher_information
from ..region import Region
from .plan import Plan, check_region
from .request import Fleet, PathOptions, PlanPath

__all__ = ["transect", "random_walk", "DIRECTIONS"]

DIRECTIONS: tuple[str, ...] = ("up", "down", "left", "right")
_TOL = 1e-9
_SQRT2 = math.sqrt(2.0)


def _axis_sign(values: np.ndarray) -> int:
    """+1 when the coordinate increases with the grid index, -1 when it decreases."""
    return -1 if values.size > 1 and values[-1] < values[0] else 1


def _information(Y: Any, region: Region, cells: list[int], ridge: float) -> tuple[Any, float]:
    if Y is None:
        return None, float("nan")
    Yk = as_factor_matrix(Y, region)
    return Yk, fisher_information(Yk, cells, ridge)


# ---------------------------------------------------------------------------- path model
class _Geometry:
    """What a baseline walk needs from the path model: the step costs between grid positions,
    the positions it may enter, the stop cost, and whether it must come back.

    ``enter`` is ``None`` without a travel graph (``traversable=None``: a transect crosses
    masked positions as in the paper, the random walk steps on valid cells) or the ``(ny, nx)``
    bool grid of enterable positions (valid and allowed by ``traversable``); with it, columns
    wrap on a grid spanning the full circle of longitude (``wrap``), as the planners' travel
    graph does. Step costs are the path model's straight-line distances between the positions'
    centres (:func:`lrm_cvx.planning.paths.travel_distance`: 1 or sqrt 2 grid units, haversine
    km, or hours), not rounded.
    """

    def __init__(self, region: Region, *, metric: str = "grid", speed: float | None = None,
                 stop_cost: float = 0.0, closed: bool = False,
                 enter: np.ndarray | None = None, wrap: bool = False,
                 grid: np.ndarray | None = None) -> None:
        self.region = region
        self.grid = region.cell_grid if grid is None else grid  # (ny, nx) cell or -1
        self.stop_cost = float(stop_cost)
        self.closed = bool(closed)
        self.enter = enter
        self.wrap = bool(wrap and enter is not None)
        self.ny, self.nx = region.shape
        self._paths = None
        if metric != "grid" or speed is not None:
            from .paths import TravelGeometry

            self._paths = TravelGeometry(region, metric, speed)

    def move(self, p: np.ndarray) -> np.ndarray | None:
        """Grid position ``p`` (column wrapped on a full circle) if the walk may enter it."""
        if self.wrap:
            p = np.array([p[0], p[1] % self.nx])
        if not (0 <= p[0] < self.ny and 0 <= p[1] < self.nx):
            return None
        if self.enter is not None and not self.enter[p[0], p[1]]:
            return None
        return p

    def steps(self, r0: int, c0: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Cost of the steps from grid position ``(r0, c0)`` to each 8-neighbour ``(rows,
        cols)`` (budget unit)."""
        if self._paths is None:
            return np.where((rows != r0) & (cols != c0), _SQRT2, 1.0)
        n = rows.size
        return self._paths.position_pairs(np.full(n, r0, np.int64), np.full(n, c0, np.int64),
                                          rows, cols)

    def step(self, p: np.ndarray, q: np.ndarray) -> float:
        return float(self.steps(int(p[0]), int(p[1]), np.array([q[0]]), np.array([q[1]]))[0])

    def fits(self, travel: float, stops: float, step: Any, new_stop: Any,
             budget: float) -> Any:
        """Whether a step (cost ``step``, ``new_stop`` for a first visit) fits the budget after
        ``travel`` + ``stops``; for a closed tour, with the way back along the same path."""
        if self.closed:
            return 2.0 * (travel + step) + (stops + new_stop) <= budget + _TOL
        return travel + stops + (step + new_stop) <= budget + _TOL


CYCLE_AFTER = 100_000
"""Steps after which a transect stops at a repeated state (a cycle) rather than walk on."""

BASELINE_FIELDS = ("metric", "speed", "stop_cost", "traversable", "closed", "sensor")
"""The path options the baselines follow (no ``end``, no ``sense_along``); a ``sensor`` only
changes what each stop observes (``plan.observation_rows()``), not the route."""


def _path_setup(region: Region, start: int, budget: float, request: PathOptions
                ) -> tuple[_Geometry, PlanPath | None]:
    """One robot's walk geometry under ``request`` (checked as
    :func:`~lrm_cvx.planning.paths.make_path_model` checks it, without building its travel
    graph) and the plan's path record (None for the paper's model: the Plan's default)."""
    if request.is_paper:
        return _Geometry(region), None
    from .paths import grid_wraps, traversable_mask

    kind, ok = traversable_mask(region, request.traversable)
    grid = region.cell_grid
    enter = None
    if kind != "none":
        if not ok[start]:
            raise PlanningError(f"start cell {start} may not be entered (traversable mask)")
        enter = (grid >= 0) & ok[np.maximum(grid, 0)]
    geo = _Geometry(region, metric=request.metric, speed=request.speed,
                    stop_cost=request.stop_cost, closed=request.closed, enter=enter,
                    wrap=grid_wraps(region), grid=grid)
    return geo, PlanPath.describe(request, Fleet((start,), (budget,)), traversable=kind)


def _request(where: str, region: Any, start: Any, budget: Any, path: Any
             ) -> tuple[Region, PathOptions, Fleet]:
    """The baseline's request read once: region, path options, fleet."""
    region = check_region(region)
    request = PathOptions.from_kwargs(path, where=where, allowed=BASELINE_FIELDS)
    return region, request, Fleet.resolve(region, start, budget, request.unit)


def _finish(region: Region, positions: list[np.ndarray], step_costs: list[float],
            geo: _Geometry, *, trim: bool) -> tuple[list[int], list[float], list[bool], float]:
    """The route of a walk through grid ``positions`` (steps costing ``step_costs``): valid
    positions only, each with its cumulative cost (travel + a stop cost at each first visit)
    and whether it is a first visit (a sampling stop). A closed walk first drops trailing
    masked positions (``trim``), then retraces its steps back to the start; an open walk ends
    at its last valid position. Returns ``(route, route_cost, waypoint, cost)``."""
    grid = geo.grid
    cells = [int(grid[p[0], p[1]]) for p in positions]
    if geo.closed:
        if trim:
            last = max(i for i, c in enumerate(cells) if c >= 0)
            positions, cells, step_costs = positions[:last + 1], cells[:last + 1], \
                step_costs[:last]
        cells = cells + cells[-2::-1]
        step_costs = step_costs + step_costs[::-1]
    route: list[int] = []
    route_cost: list[float] = []
    waypoint: list[bool] = []
    seen: set[int] = set()
    travel = 0.0
    stops = 0.0
    for i, c in enumerate(cells):
        if i:
            travel += step_costs[i - 1]
        if c < 0:
            continue
        first = c not in seen
        if first:
            seen.add(c)
            stops += geo.stop_cost
        route.append(c)
        route_cost.append(travel + stops)
        waypoint.append(first)
    if geo.closed and len(route) > 1:
        waypoint[-1] = True  # the tour ends at its start, a stop again
    return route, route_cost, waypoint, route_cost[-1]


def _build(region: Region, route: list[int], route_cost: list[float], waypoint: list[bool],
           cost: float, *, Y: Any, ridge: float, budget: float, start: int, method: str,
           cost_function: str, record: PlanPath | None) -> Plan:
    cells = list(dict.fromkeys(route))
    Yk, info = _information(Y, region, cells, ridge)
    extra: dict[str, Any] = {}
    if record is not None:
        extra = {"path": record, "waypoint": waypoint}
    return Plan.build(
        region=region, cells=cells, route=route, cost=cost, information=info,
        route_cost=route_cost, criterion=None, budget=budget, start=start,
        ridge=float(ridge), method=method, cost_function=cost_function, Y=Yk, history={},
        **extra,
    )


def _per_robot(one: Any, fleet: Fleet, Y: Any, ridge: float, method: str) -> Plan:
    """``one(start_i, budget_i)`` per robot of ``fleet``; a fleet request (``start`` a list,
    as :func:`~lrm_cvx.planning.plan_greedy` reads it) of several robots is joined by
    :meth:`Plan.from_robots` (joint information)."""
    plans = [one(c, b) for c, b in zip(fleet.starts, fleet.budgets, strict=True)]
    if len(plans) == 1:
        return plans[0]
    return Plan.from_robots(plans, Y=Y, ridge=float(ridge), method=method)


# ---------------------------------------------------------------------------- transect
def transect(
    region: Region,
    start: Any,
    budget: Any,
    direction: str,
    *,
    Y: Any = None,
    ridge: float = 0.0,
    path: PathOptions | None = None,
) -> Plan:
    """A straight transect from ``start``, one grid step at a time (a lawnmower at the edges).

    ``direction`` is ``"up"`` (north), ``"down"``, ``"left"`` (west) or ``"right"``. When the
    next step would leave the grid (or, with ``traversable``, enter a cell the robot may not
    enter) it instead steps once orthogonally (east for up/down transects, south for left/right
    ones; the other way when that is blocked too, and from then on) and reverses direction. It
    walks while the next step fits the budget (the paper's grid: ``floor(budget + 1e-9)`` unit
    steps). A walk of more than :data:`CYCLE_AFTER` steps (a budget far beyond the region's
    size) stops at the first state (position, heading, turn side) it repeats after that: from
    there it would only repeat a cycle, and every cell it can reach has been observed.

    Path model (as :func:`~lrm_cvx.planning.plan_greedy`: ``path`` a
    :class:`~lrm_cvx.planning.request.PathOptions`): ``metric`` ``"grid"``
    (each step costs 1) or ``"km"`` (the haversine distance between the two positions' centres),
    ``speed`` (km/h, with ``"km"``) for a budget in hours; ``stop_cost`` (budget unit) is
    charged at each cell's first visit, the start included; ``traversable`` (``"valid"`` or a
    boolean ``(lat, lon)`` DataArray) makes non-enterable cells turn the transect like the grid
    edge; ``closed=True`` walks out while the budget still pays the way back along the same
    path, then retraces it (the route ends at the start).

    Without ``traversable`` every grid position passed is observed; masked positions are
    crossed (their steps count) but are not among the plan's cells. The plan's ``cost`` is the
    cost walked up to the last observed (valid) cell: steps over masked positions after it
    observe nothing and are not part of the plan (a closed transect turns back at that cell).
    ``start`` a list (and ``budget`` a number or one per start): one transect per robot,
    joined by :meth:`Plan.from_robots`. ``Y`` (optional) gives the plan's Fisher information.
    """
    if direction not in DIRECTIONS:
        raise PlanningError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    region, request, fleet = _request("transect", region, start, budget, path)
    return _per_robot(lambda s, b: _transect(region, s, b, direction, request, Y, ridge),
                      fleet, Y, ridge, f"transect-{direction}")


def _transect(region: Region, start_cell: int, budget: float, direction: str,
              request: PathOptions, Y: Any, ridge: float) -> Plan:
    """One robot's transect (:func:`transect`)."""
    geo, record = _path_setup(region, start_cell, budget, request)
    north = _axis_sign(region.lat.values)  # row step that goes north
    east = _axis_sign(region.lon.values)  # col step that goes east
    step = {"up": (north, 0), "down": (-north, 0), "left": (0, -east), "right": (0, east)}
    d = np.array(step[direction])
    orth = np.array(step["right"] if direction in ("up", "down") else step["down"])
    grid = geo.grid
    pos = region.grid_index[start_cell].copy()
    positions = [pos]
    step_costs: list[float] = []
    seen = {start_cell}
    travel, stops = 0.0, geo.stop_cost
    states = set()  # (position, heading, turn side) once past CYCLE_AFTER steps
    while True:
        if len(step_costs) >= CYCLE_AFTER:
            state = (*pos.tolist(), *d.tolist(), *orth.tolist())
            if state in states:
                break  # the walk is a function of its state: it would only repeat a cycle
            states.add(state)
        nxt = geo.move(pos + d)
        if nxt is None:  # the grid's edge or a cell it may not enter: turn
            if geo.move(pos + orth) is None:
                orth = -orth
            d = -d
            nxt = geo.move(pos + orth)
            if nxt is None:
                nxt = geo.move(pos + d)  # a one-wide corridor: just turn back
            if nxt is None:
                break  # a single position: nowhere to go
        s = geo.step(pos, nxt)
        c = int(grid[nxt[0], nxt[1]])
        new = geo.stop_cost if c >= 0 and c not in seen else 0.0
        if not geo.fits(travel, stops, s, new, budget):
            break
        pos = nxt
        positions.append(pos)
        step_costs.append(s)
        travel += s
        stops += new
        if c >= 0:
            seen.add(c)
    route, route_cost, waypoint, cost = _finish(region, positions, step_costs, geo, trim=True)
    return _build(region, route, route_cost, waypoint, cost, Y=Y, ridge=ridge, budget=budget,
                  start=start_cell, method=f"transect-{direction}", cost_function="steps",
                  record=record)


# ---------------------------------------------------------------------------- random walk
_STEP_ROWS = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
_STEP_COLS = np.array([-1, 0, 1, -1, 1, -1, 0, 1])  # the 8 neighbours in row-major order


def _neighbours(grid: np.ndarray, row: int, col: int, enter: np.ndarray | None,
                wrap: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid (with ``enter``: enterable) 8-neighbours of a grid position: their cell indices
    (ascending), rows and columns (columns wrapped on a full-circle grid when ``wrap``)."""
    ny, nx = grid.shape
    rr, cc = row + _STEP_ROWS, col + _STEP_COLS
    if wrap:
        cc %= nx
        inside = (rr >= 0) & (rr < ny) & ~((rr == row) & (cc == col))
    else:
        inside = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
    rr, cc = rr[inside], cc[inside]
    cells = grid[rr, cc]
    keep = cells >= 0
    if enter is not None:
        keep &= enter[rr, cc]
    cells, rr, cc = cells[keep], rr[keep], cc[keep]
    if wrap:  # wrapped columns break the row-major order
        order = np.argsort(cells, kind="stable")
        return cells[order], rr[order], cc[order]
    return cells, rr, cc


def random_walk(
    region: Region,
    start: Any,
    budget: Any,
    rng: Any = None,
    *,
    Y: Any = None,
    ridge: float = 0.0,
    path: PathOptions | None = None,
) -> Plan:
    """The paper's random-sampling baseline: a random walk on valid 8-neighbours.

    From the last cell, the neighbours are the valid (unmasked; with ``traversable``,
    enterable) cells among its 8 grid neighbours whose step still fits the budget (with
    ``stop_cost`` added for a cell not yet visited; for ``closed=True``, with the way back
    along the walk). A random unvisited one is taken if any, else a random one among them; the
    walk stops when no neighbour fits. A step costs 1 or sqrt 2 grid units (``metric="grid"``,
    the paper), the haversine km between the cells' centres (``"km"``), or that divided by
    ``speed`` (hours). A closed walk then retraces its steps to the start. ``rng``: a seed or
    ``numpy.random.Generator`` (deterministic given a seed). ``start`` a list: one walk per
    robot (drawn in robot order from ``rng``), joined by :meth:`Plan.from_robots`.
    """
    region = check_region(region)
    try:
        gen = as_generator(rng)
    except LrmError:
        raise PlanningError(f"rng must be None, an int seed or a numpy Generator, got {rng!r}") \
            from None
    region, request, fleet = _request("random_walk", region, start, budget, path)
    return _per_robot(lambda s, b: _random_walk(region, s, b, gen, request, Y, ridge), fleet,
                      Y, ridge, "random")


def _random_walk(region: Region, start_cell: int, budget: float, gen: np.random.Generator,
                 request: PathOptions, Y: Any, ridge: float) -> Plan:
    """One robot's random walk (:func:`random_walk`): each step in Python over the (at most 8)
    neighbours of :func:`_steps_from`, the same draws from ``gen`` as the walk's definition."""
    geo, record = _path_setup(region, start_cell, budget, request)
    table = _STEPS.setdefault(region, {}) if record is None else {}  # the paper's: shared
    gi = region.grid_index
    positions = [gi[start_cell]]
    step_costs: list[float] = []
    visited = {start_cell}
    travel, stops, stop_cost = 0.0, geo.stop_cost, geo.stop_cost
    cur = start_cell
    while True:
        steps = table.get(cur)
        if steps is None:
            steps = table[cur] = _steps_from(geo, int(gi[cur, 0]), int(gi[cur, 1]))
        fresh, stale = [], []
        for c, length in steps:
            new = 0.0 if c in visited else stop_cost
            if geo.fits(travel, stops, length, new, budget):
                (stale if c in visited else fresh).append((c, length, new))
        if not (fresh or stale):
            break
        pick = fresh or stale  # a random unvisited neighbour if any (in neighbour order)
        cur, length, new = pick[int(gen.integers(len(pick)))]
        travel += length
        stops += new
        positions.append(gi[cur])
        step_costs.append(length)
        visited.add(cur)
    route, route_cost, waypoint, cost = _finish(region, positions, step_costs, geo, trim=False)
    return _build(region, route, route_cost, waypoint, cost, Y=Y, ridge=ridge, budget=budget,
                  start=start_cell, method="random", cost_function="path", record=record)


_STEPS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""Per region, the paper's path model's :func:`_steps_from` of each cell a walk reached."""


def _steps_from(geo: _Geometry, row: int, col: int) -> list[tuple[int, float]]:
    """``(cell, step cost)`` of every neighbour a walk may step to from grid position ``(row,
    col)`` (:func:`_neighbours` order)."""
    nb, rows, cols = _neighbours(geo.grid, row, col, geo.enter, geo.wrap)
    return list(zip(nb.tolist(), geo.steps(row, col, rows, cols).tolist(), strict=True))
