"""The result of planning: the cells to sample, the route through them, and its exports."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import atomic_output
from ..errors import PlanningError
from ..region import check_region
from .refiners import REFINERS  # noqa: F401  (re-exported: its first home)
from .request import PAPER_PATH, PlanPath

__all__ = ["Plan", "PAPER_PATH"]


def path_cumulative(grid_index: np.ndarray) -> np.ndarray:
    """Cumulative Euclidean grid length ``(r,)`` of the path through ``grid_index`` ``(r, 2)``,
    summed in order from 0 exactly as :func:`~lrm_cvx.planning.routecost.route_length` sums it."""
    g = np.asarray(grid_index, dtype=np.int64).reshape(-1, 2)
    if g.shape[0] == 0:
        return np.empty(0)
    d = np.diff(g, axis=0)
    steps = np.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float64))
    return np.cumsum(np.concatenate([[0.0], steps]))


def path_dict(starts: Any, budgets: Any, **options: Any) -> PlanPath:
    """A plan's ``path`` record (:class:`~lrm_cvx.planning.request.PlanPath`, a read-only
    mapping): :data:`PAPER_PATH` updated by ``options`` plus ``starts`` / ``budgets`` (lists,
    one per robot) and ``n_robots``."""
    return PlanPath(options, starts=starts, budgets=budgets)


def is_paper_path(path: Any) -> bool:
    """True when ``path`` (a plan's path record or its mapping) is the paper's model: one
    robot, open straight-line path in grid units, no stop cost, sensing only at the stops
    (what :func:`refine` supports)."""
    return PlanPath.of(path).is_paper


def _robot_last(route_robot: np.ndarray, n_robots: int) -> np.ndarray:
    """Index of the last route entry of each robot ``(n_robots,)`` (-1 for an empty route)."""
    last = np.full(n_robots, -1, dtype=np.int64)
    if route_robot.size:
        idx = np.arange(route_robot.size)
        np.maximum.at(last, route_robot, idx)
    return last


def line_cells(region: Any, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells strictly between cells ``a`` and ``b`` that the straight segment between their
    grid positions crosses, in travel order, and where ``(k,)`` each is along it (``t`` in
    (0, 1), the middle of the segment's stretch in the cell). A segment through a grid corner
    passes diagonally (consecutive positions are 8-neighbours); masked positions are skipped.
    """
    g = region.grid_index
    p0 = g[int(a)].astype(np.float64)
    d = g[int(b)].astype(np.float64) - p0
    ts = [np.array([0.0, 1.0])]
    for axis in (0, 1):
        if d[axis] != 0:
            lo, hi = sorted((p0[axis], p0[axis] + d[axis]))
            h = np.arange(np.floor(lo) + 0.5, hi, 1.0)
            ts.append((h - p0[axis]) / d[axis])
    t = np.unique(np.clip(np.concatenate(ts), 0.0, 1.0))
    mid = 0.5 * (t[1:] + t[:-1])[1:-1]  # the first and last stretches are a's and b's cells
    if mid.size == 0:
        return np.empty(0, np.int64), np.empty(0)
    pos = np.rint(p0[None, :] + mid[:, None] * d[None, :]).astype(np.int64)
    cells = region.cell_grid[pos[:, 0], pos[:, 1]]
    keep = (cells >= 0) & (cells != a) & (cells != b)
    return cells[keep].astype(np.int64), mid[keep]


def sensed_route(model: Any, stops: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The route a sensing-along robot observes: ``model.expand(stops)`` and, without a travel
    graph (``model.traversable == "none"``), the cells each straight leg crosses
    (:func:`line_cells`) as pass-through entries (``waypoint=False``), their cumulative cost
    interpolated along the leg's straight-line travel. Returns ``(cells, cumulative_cost,
    waypoint)`` like ``expand``."""
    cells, cum, way = (np.asarray(v) for v in model.expand(np.asarray(stops, np.int64)))
    if getattr(model, "traversable", "none") != "none" or cells.size < 2:
        return cells.astype(np.int64), cum.astype(np.float64), way.astype(bool)
    from .paths import travel_distance

    region = model.region
    out_c, out_k, out_w = [cells[:1]], [cum[:1]], [way[:1]]
    for i in range(cells.size - 1):
        a, b = int(cells[i]), int(cells[i + 1])
        mid, t = line_cells(region, a, b)
        if mid.size:
            leg = float(travel_distance(region, a, b, metric=model.metric, speed=model.speed))
            out_c.append(mid)
            out_k.append(np.minimum(cum[i] + t * leg, cum[i + 1]))
            out_w.append(np.zeros(mid.size, bool))
        out_c.append(cells[i + 1:i + 2])
        out_k.append(cum[i + 1:i + 2])
        out_w.append(way[i + 1:i + 2])
    return (np.concatenate(out_c).astype(np.int64), np.concatenate(out_k).astype(np.float64),
            np.concatenate(out_w).astype(bool))


@dataclass(eq=False, repr=False)
class Plan:
    """A sampling plan from ``start`` within ``budget``.

    Attributes
    ----------
    cells : ``(n,)`` int64, the distinct cells to observe in selection order (greedy: the
        initial cells first, then one per iteration; baselines: first visit order).
    route : ``(r,)`` int64, the cells in travel order from the start. Greedy with the
        nearest-neighbour cost: the nearest-neighbour tour of ``cells``; with the insertion
        cost: the cheapest-insertion route; random walk: the walk itself (cells may repeat);
        transect: the valid cells passed, in order.
    cost : the route's cost (the one the budget constrains) in ``path["unit"]``: grid units
        for the paper; km, hours, or the number of sensors of a static placement.
    information : Fisher information ``log det(ridge I + sum_cells y y^T)`` of ``cells``
        (``-inf`` if singular, ``nan`` when a baseline was built without ``Y``).
    criterion : the greedy's criterion (``"fisher"`` / ``"a-optimal"``), ``None`` for baselines
        (a transect kept by ``refine="rivals"`` / ``"lines"`` carries the criterion that chose
        it).
    budget, start, ridge : the request (``start`` is a cell index: the first robot's for a
        fleet, ``-1`` for a static placement; ``budget`` is the robots' total).
    lat, lon, grid_index : ``(r,)``, ``(r,)``, ``(r, 2)`` coordinates of each *route* entry.
    history : per greedy iteration, arrays ``cell``, ``gain``, ``cost_increase``, ``ratio``,
        ``cost`` (route cost after the pick) and ``n_evaluated`` (candidates whose exact cost
        was recomputed); empty arrays for baselines.
    method : ``"greedy"``, ``"transect-up"`` (``-down``, ``-left``, ``-right``) or ``"random"``.
    route_cost : ``(r,)`` float64, the travel cost from the start to each route stop (the last
        one equals ``cost``): the grid-distance path along the route for the greedy and the
        random walk; the grid steps walked for a transect (steps across masked positions count).
    posterior : the greedy's criterion was computed on the fold-in's posterior (a prior
        precision or per-cell noise), not on ``ridge I + sum y y^T``.
    refinement : empty, or what :func:`~lrm_cvx.planning.refine.refine` gained:
        ``information_before`` / ``information_after`` (nats), ``moves`` accepted, ``inserted``,
        ``swapped``, ``rounds``, ``seconds`` (history keys ``refine_*`` list the moves).
    rivals : empty, or the greedy's check against rival routes (``refine="rivals"`` or
        ``"lines"``, :mod:`~lrm_cvx.planning.lines`): ``criterion``, ``values`` (route name ->
        criterion value: ``"greedy"``, ``"greedy-cost^0.5"``, ``"transect-up"``, ...),
        ``chosen`` (this plan's name there), ``cost_function`` (the greedy's route cost, which
        a replan uses) and ``refine`` (the check, which a replan repeats).
    path : the path request (:class:`~lrm_cvx.planning.request.PlanPath`: ``options``, a
        ``PathOptions``, and ``fleet``), a read-only mapping of ``kind`` (``"path"`` or
        ``"static"``), ``metric``, ``speed``, ``stop_cost``, ``traversable`` (``"none"``,
        ``"valid"``, ``"mask"``), ``closed``, ``end``, ``unit`` (of ``cost`` / ``budget``),
        ``sense_along``, ``starts`` and ``budgets`` (one per robot) and ``n_robots``. Default:
        :data:`PAPER_PATH`.
    route_robot, waypoint : ``(r,)`` per route entry: the robot travelling it, and whether it
        is a sampling stop (False for a pass-through cell of a travel graph or of
        ``sense_along``). A closed tour's route ends with its start again.
    stops, stop_robot : ``(s,)`` the sampling stops in selection order and their robot (a cell
        is the stop of one robot, except a start shared by two robots). ``cells`` is every
        distinct observed cell: the stops, then (``sense_along``) the cells passed.
    robot_costs : ``(n_robots,)`` each robot's cost; ``cost`` is their sum and ``budget`` the
        sum of the robots' budgets. ``route_cost`` restarts at each robot's start (at its stop
        cost) and ends at its cost.
    criterion_terms : (read-only) the criterion's terms the plan is judged under, which
        :meth:`certify` bounds (see the property).
    """

    cells: np.ndarray
    route: np.ndarray
    cost: float
    information: float
    criterion: str | None
    budget: float
    start: int
    ridge: float
    lat: np.ndarray
    lon: np.ndarray
    grid_index: np.ndarray
    history: dict[str, np.ndarray] = field(default_factory=dict)
    method: str = "greedy"
    cost_function: str = "nearest-neighbor"
    route_cost: np.ndarray = field(default_factory=lambda: np.empty(0))
    posterior: bool = False
    refinement: dict[str, Any] = field(default_factory=dict, compare=False)
    rivals: dict[str, Any] = field(default_factory=dict, compare=False)
    path: PlanPath | Any = field(default_factory=dict)
    route_robot: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    waypoint: np.ndarray = field(default_factory=lambda: np.empty(0, bool))
    stops: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    stop_robot: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    robot_costs: np.ndarray = field(default_factory=lambda: np.empty(0))
    _Y: Any = field(default=None, repr=False, compare=False)
    _region: Any = field(default=None, repr=False, compare=False)
    _path_models: Any = field(default=None, repr=False, compare=False)
    _terms: Any = field(default=None, repr=False, compare=False)  # the criterion's terms

    def __post_init__(self) -> None:
        # plans built the old way (baselines, by hand): the paper's path model, one robot
        self.path = (PlanPath.of(self.path) if self.path
                     else PlanPath(starts=[self.start], budgets=[self.budget]))
        r = np.asarray(self.route).size
        if np.asarray(self.route_robot).size != r:
            self.route_robot = np.zeros(r, dtype=np.int64)
        if np.asarray(self.waypoint).size != r:
            self.waypoint = np.ones(r, dtype=bool)
        if np.asarray(self.stops).size == 0 and np.asarray(self.cells).size:
            self.stops = np.asarray(self.cells, dtype=np.int64)
        if np.asarray(self.stop_robot).size != np.asarray(self.stops).size:
            self.stop_robot = np.zeros(np.asarray(self.stops).size, dtype=np.int64)
        if np.asarray(self.robot_costs).size == 0:
            self.robot_costs = np.array([float(self.cost)])

    @property
    def traversable_mask(self) -> np.ndarray | None:
        """``(ny, nx)`` bool: where the robots may travel (``path["traversable"] == "mask"``,
        from the plan's path models; masked grid positions False), else None."""
        if self.path.get("traversable") != "mask":
            return None
        if not self._path_models:  # a plan read back from a file: its request's mask
            opts = self.path.options
            trav = None if opts is None else opts.traversable
            if trav is None or isinstance(trav, str):
                return None
            return np.asarray(getattr(trav, "values", trav), dtype=bool).copy()
        region = self._region
        enter = np.asarray(self._path_models[0].enterable(), dtype=bool)
        out = np.zeros(region.shape, dtype=bool)
        gi = region.grid_index
        out[gi[:, 0], gi[:, 1]] = enter
        return out

    @property
    def sensor(self) -> Any:
        """What each stop observed (:class:`~lrm_cvx.planning.sensors.Sensor`; point by
        default)."""
        return PlanPath.of(self.path).sensor

    def observation_rows(self) -> Any:
        """The sensor's observations as averaging rows over the region's cells, ``(n, L)``
        scipy.sparse CSR, each row summing to 1 (one-hot for a point sensor: one per cell of
        ``cells``; a footprint per cell of ``cells``; a towed sensor one per stop). The truth
        a plan observes is ``rows @ truth`` (:func:`lrm_cvx.planning.sensors.observe` handles
        cells without a value)."""
        from .sensors import observation_rows

        return observation_rows(self)

    def observe(self, truth: Any) -> tuple[Any, np.ndarray]:
        """What the plan's sensor reads of a snapshot: ``(rows, values)``, one averaged value
        per observation (:meth:`observation_rows`, re-weighted over the cells with a value; a
        footprint without any reads NaN). ``truth``: the region's ``(L,)`` values or a
        ``(lat, lon)`` DataArray on its grid."""
        from .sensors import plan_observations

        if hasattr(truth, "dims"):
            truth = self._region.stack(truth)
        return plan_observations(self, np.asarray(truth, dtype=np.float64))

    @property
    def criterion_terms(self) -> dict[str, Any] | None:
        """The criterion's terms the plan is judged under, which :meth:`certify` bounds (a
        copy; None when the plan carries none): ``prior_precision``, ``noise_var``,
        ``target_weights`` and, for ``"gp-variance"``, ``spatial_cov``, ``prior_cov``,
        ``targets`` (the ones given). A greedy plan carries the terms it was planned with,
        a replanned plan the day's prior before the replan's observations, and a plan stored
        in a monitor state file reads them back."""
        if self._terms is None:
            return None
        return {key: v for key, v in self._terms.items()
                if key not in ("region", "pool") and v is not None}

    @property
    def n_robots(self) -> int:
        """Number of robots (1 for a single route and for static placement)."""
        return int(self.path.get("n_robots", 1))

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(
        cls,
        *,
        region: Any,
        cells: Any,
        route: Any,
        cost: float | None,
        information: float,
        criterion: str | None,
        budget: float,
        start: int,
        ridge: float,
        method: str,
        history: dict[str, np.ndarray] | None = None,
        cost_function: str = "nearest-neighbor",
        Y: Any = None,
        route_cost: Any = None,
        posterior: bool = False,
        path: PlanPath | Any = None,
        route_robot: Any = None,
        waypoint: Any = None,
        stops: Any = None,
        stop_robot: Any = None,
        robot_costs: Any = None,
        path_models: Any = None,
    ) -> Plan:
        """A plan with its coordinates looked up in ``region``.

        ``route_cost`` (cumulative cost at each route entry) defaults to the grid-distance path
        along each robot's route (summed in order, as the path costs are); each robot's cost
        (``robot_costs``) defaults to its last value and ``cost`` to their sum. A given
        ``cost`` / ``robot_costs`` must equal those last values (to 1e-9 relative).
        ``route_robot`` defaults to one robot, ``waypoint`` to all True, ``stops`` to ``cells``,
        ``path`` to the paper's (:func:`path_dict` with ``start`` and ``budget``).
        """
        route = np.asarray(route, dtype=np.int64)
        gi = np.asarray(region.grid_index[route], dtype=np.int64)
        rr = (np.zeros(route.size, np.int64) if route_robot is None
              else np.asarray(route_robot, dtype=np.int64))
        if rr.shape != route.shape:
            raise ValueError(f"route_robot must have the route's shape {route.shape}")
        n_robots = int(path.get("n_robots", 1)) if path else 1
        n_robots = max(n_robots, int(rr.max()) + 1 if rr.size else 1)
        if route_cost is None:
            route_cost = np.zeros(route.size)
            for r in range(n_robots):
                sel = np.flatnonzero(rr == r)
                route_cost[sel] = path_cumulative(gi[sel])
        route_cost = np.asarray(route_cost, dtype=np.float64).copy()
        if route_cost.shape != route.shape:
            raise ValueError(f"route_cost must have the route's shape {route.shape}")
        last = _robot_last(rr, n_robots)
        ends = np.where(last >= 0, route_cost[np.maximum(last, 0)], 0.0)
        if robot_costs is None:
            if n_robots == 1 and cost is not None:
                robot_costs = np.array([float(cost)])
            else:
                robot_costs = ends
        robot_costs = np.asarray(robot_costs, dtype=np.float64).ravel()
        if robot_costs.size != n_robots:
            raise ValueError(f"robot_costs must have one cost per robot ({n_robots})")
        if cost is None:
            cost = float(robot_costs.sum()) if n_robots > 1 else float(robot_costs[0])
        has = last >= 0
        if not np.allclose(ends[has], robot_costs[has], rtol=1e-9, atol=1e-9):
            raise ValueError(f"the route's cost {ends[has]!r} differs from cost="
                             f"{robot_costs[has]!r}")
        total = float(robot_costs.sum()) if n_robots > 1 else float(robot_costs[0])
        if not np.isclose(total, cost, rtol=1e-9, atol=1e-9):
            raise ValueError(f"the robots' costs add to {total!r}, not cost={cost!r}")
        route_cost[last[has]] = robot_costs[has]  # the same floats, not ones rounded differently
        cells = np.asarray(cells, dtype=np.int64)
        return cls(
            cells=cells,
            route=route,
            cost=float(cost),
            information=float(information),
            criterion=criterion,
            budget=float(budget),
            start=int(start),
            ridge=float(ridge),
            lat=np.asarray(region.cell_lat[route], dtype=np.float64),
            lon=np.asarray(region.cell_lon[route], dtype=np.float64),
            grid_index=gi,
            history=dict(history or {}),
            method=method,
            cost_function=cost_function,
            route_cost=route_cost,
            posterior=bool(posterior),
            path=PlanPath.of(path) if path else PlanPath(starts=[start], budgets=[budget]),
            route_robot=rr,
            waypoint=(np.ones(route.size, bool) if waypoint is None
                      else np.asarray(waypoint, dtype=bool)),
            stops=cells.copy() if stops is None else np.asarray(stops, dtype=np.int64),
            stop_robot=np.asarray([] if stop_robot is None else stop_robot, dtype=np.int64),
            robot_costs=robot_costs,
            _Y=Y,
            _region=region,
            _path_models=path_models,
        )

    @classmethod
    def from_robots(cls, plans: Any, *, Y: Any = None, ridge: float | None = None,
                    method: str | None = None) -> Plan:
        """One fleet plan from per-robot plans (robot ``i`` = ``plans[i]``), e.g. a baseline
        run once per robot. The routes are concatenated; ``cells`` / ``stops`` are the distinct
        cells in robot order; ``information`` is the **joint** Fisher information of all cells
        (``Y``: default the first plan's model; ``nan`` without one; ``ridge``: default the
        first plan's). Every plan must be on the same region and path model (``metric``,
        ``traversable``, ...), one robot each."""
        from ..information import fisher_information

        plans = list(plans)
        if not plans or not all(isinstance(p, Plan) for p in plans):
            raise PlanningError("plans must be a non-empty list of Plan, one per robot")
        region = plans[0]._region
        if region is None or any(p._region is None or p._region.n_cells != region.n_cells
                                 for p in plans):
            raise PlanningError("plans must all carry the same region")
        base = {k: v for k, v in plans[0].path.items() if k not in ("starts", "budgets",
                                                                     "n_robots")}
        for p in plans:
            if p.n_robots != 1:
                raise PlanningError("each plan of from_robots must be a single robot's plan")
            other = {k: v for k, v in p.path.items() if k in base}
            if other != base:
                raise PlanningError(f"plans must share one path model, got {base} and {other}")
        ridge = float(plans[0].ridge if ridge is None else ridge)
        Yk = Y if Y is not None else plans[0]._Y
        cells = list(dict.fromkeys(int(c) for p in plans for c in p.cells))
        stops = [int(c) for p in plans for c in p.stops]
        stop_robot = [r for r, p in enumerate(plans) for _ in p.stops]
        if Yk is not None:
            from .._validation import as_factor_matrix

            Yk = as_factor_matrix(Yk, region)
            info = fisher_information(Yk, cells, ridge)
        else:
            info = float("nan")
        starts = [p.start for p in plans]
        budgets = [p.budget for p in plans]
        path = PlanPath(base, starts=starts, budgets=budgets,
                        options=PlanPath.of(plans[0].path).options)
        methods = list(dict.fromkeys(p.method for p in plans))
        return cls.build(
            region=region, cells=cells, route=np.concatenate([p.route for p in plans]),
            cost=None, information=info, criterion=plans[0].criterion,
            budget=float(sum(budgets)), start=starts[0], ridge=ridge,
            method=method or "+".join(methods), history={},
            cost_function=plans[0].cost_function, Y=Yk,
            route_cost=np.concatenate([p.route_cost for p in plans]),
            posterior=plans[0].posterior, path=path,
            route_robot=np.concatenate([np.full(p.route.size, r, np.int64)
                                        for r, p in enumerate(plans)]),
            waypoint=np.concatenate([p.waypoint for p in plans]),
            stops=stops, stop_robot=stop_robot,
            robot_costs=[p.cost for p in plans],
        )

    @property
    def robots(self) -> list[Plan]:
        """One sub-plan per robot (``[self]`` for one robot): its route, stops, observed cells,
        cost and budget; ``information`` is that robot's cells' own Fisher information."""
        if self.n_robots == 1:
            return [self]
        from ..information import fisher_information

        out = []
        sense = bool(self.path.get("sense_along"))
        budgets = self.path.get("budgets", [])
        starts = self.path.get("starts", [])
        for r in range(self.n_robots):
            on = self.route_robot == r
            stops = self.stops[self.stop_robot == r]
            cells = list(dict.fromkeys(stops.tolist() + (self.route[on].tolist() if sense
                                                         else [])))
            info = (fisher_information(self._Y, cells, self.ridge) if self._Y is not None
                    else float("nan"))
            path = PlanPath(self.path, starts=[starts[r]], budgets=[budgets[r]],
                            options=PlanPath.of(self.path).options)
            hist = {}
            if "robot" in self.history:
                pick = self.history["robot"] == r
                hist = {k: v[pick] for k, v in self.history.items() if k != "robot"}
            out.append(Plan.build(
                region=self._region, cells=cells, route=self.route[on],
                cost=float(self.robot_costs[r]), information=info, criterion=self.criterion,
                budget=float(budgets[r]), start=int(starts[r]), ridge=self.ridge,
                method=self.method, history=hist, cost_function=self.cost_function, Y=self._Y,
                route_cost=self.route_cost[on], posterior=self.posterior, path=path,
                waypoint=self.waypoint[on], stops=stops,
                path_models=None if self._path_models is None else [self._path_models[r]],
            ))
            out[-1]._terms = self._terms  # one robot's route under the fleet's criterion
        return out

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.cells.size)

    def __repr__(self) -> str:
        crit = f", criterion={self.criterion!r}" if self.criterion else ""
        if self.n_robots > 1:
            crit += f", {self.n_robots} robots"
        if self.path.get("kind") == "static":
            crit += ", static"
        return (
            f"Plan(method={self.method!r}{crit}, {len(self)} cells, route of "
            f"{self.route.size} {'stops' if self.waypoint.all() else 'entries'}, "
            f"cost={self.cost:.4g} / budget={self.budget:.4g}, "
            f"information={self.information:.6g}, start={self.start})"
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Plan):
            return NotImplemented
        scalars = ("cost", "information", "criterion", "budget", "start", "ridge", "method",
                   "cost_function", "posterior")
        arrays = ("cells", "route", "lat", "lon", "grid_index", "route_cost", "route_robot",
                  "waypoint", "stops", "stop_robot", "robot_costs")
        return (
            self.path == other.path
            and all(
                getattr(self, a) == getattr(other, a)
                or (isinstance(getattr(self, a), float) and np.isnan(getattr(self, a))
                    and np.isnan(getattr(other, a)))
                for a in scalars
            )
            and all(np.array_equal(getattr(self, a), getattr(other, a)) for a in arrays)
            and self.history.keys() == other.history.keys()
            and all(np.array_equal(self.history[k], other.history[k]) for k in self.history)
        )

    __hash__ = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ certificate
    def certify(self, criterion: str | None = None, **kwargs: Any) -> Any:
        """Upper bound on the plan's criterion over every feasible plan, and its optimality gap.

        Calls :func:`lrm_cvx.planning.certificate.plan_bound` with this plan's model, region, start,
        budget and ridge; keyword arguments are passed on (e.g. ``tol``). ``criterion``: the
        criterion bounded, by default the plan's own: ``"gp-variance"`` / ``"a-optimal"``
        plans get a bound on the variance they remove (with the terms they were planned
        with), every other plan (Fisher, a baseline) the bound on the **Fisher** information;
        ``criterion="fisher"`` gives the Fisher certificate of any plan. Its ``gap`` and
        ``volume_ratio`` are NaN when the plan was chosen for another criterion than the one
        bounded: a gap between two criteria means nothing (docs/certificate.md, "Which
        criterion is certified").

        For a Fisher greedy plan the certificate also splits the gap: ``greedy_information``,
        ``refined_information`` (this plan's refinement, or a :func:`refine` run here; pass
        ``refine=False`` to skip it), ``plan_slack`` (greedy -> refined) and ``bound_slack``
        (refined -> bound).
        """
        if self._Y is None or self._region is None:
            from ..errors import PlanningError

            raise PlanningError("this plan has no model Y attached: build it with Y to certify")
        from .certificate import plan_bound

        if criterion is None:
            criterion = (self.criterion if self.criterion in ("a-optimal", "gp-variance")
                         else "fisher")
        if criterion != "fisher":  # plan_bound's default is the Fisher certificate
            kwargs["criterion"] = criterion
        return plan_bound(self._Y, self._region, self.start, self.budget, ridge=self.ridge,
                          plan=self, **kwargs)

    # ------------------------------------------------------------------ exports
    def _order(self) -> np.ndarray:
        """Position of each route entry within its robot's route ``(r,)``."""
        order = np.empty(self.route.size, dtype=np.int64)
        for r in range(self.n_robots):
            sel = np.flatnonzero(self.route_robot == r)
            order[sel] = np.arange(sel.size)
        return order

    def to_dataframe(self) -> Any:
        """One row per route entry: ``robot, order, cell, lat, lon, row, col, waypoint,
        cumulative_cost`` (a static placement: one row per sensor, ``sensor, cell, lat, lon,
        gain``, see :func:`~lrm_cvx.planning.missions.sensors_dataframe`). ``order`` counts
        within each robot's route; ``waypoint`` is False for
        a pass-through cell; a closed tour's last row is its start again; each robot's last
        ``cumulative_cost`` is its cost (in ``path["unit"]``)."""
        import pandas as pd

        if self.path.get("kind") == "static":  # fixed sensors: their own columns
            from .missions import sensors_dataframe

            return sensors_dataframe(self)
        cum = self.route_cost
        if cum.shape != self.route.shape:  # a Plan built by hand without route_cost
            cum = path_cumulative(self.grid_index)
        return pd.DataFrame(
            {
                "robot": self.route_robot,
                "order": self._order(),
                "cell": self.route,
                "lat": self.lat,
                "lon": self.lon,
                "row": self.grid_index[:, 0] if self.route.size else np.empty(0, np.int64),
                "col": self.grid_index[:, 1] if self.route.size else np.empty(0, np.int64),
                "waypoint": self.waypoint,
                "cumulative_cost": cum,
            }
        )

    def to_csv(self, path: str | Path) -> Path:
        """Write :meth:`to_dataframe` to ``path`` atomically; returns the path."""
        path = Path(path)
        with atomic_output(path) as tmp:
            self.to_dataframe().to_csv(tmp, index=False)
        return path

    def to_geojson(self, path: str | Path | None = None) -> dict[str, Any]:
        """GeoJSON FeatureCollection: each robot's route as a LineString and each sampling stop
        as a Point (a static placement: a Point per sensor, no LineString).

        Coordinates are ``[lon, lat]`` with longitudes in [-180, 180) (RFC 7946); a route that
        crosses the antimeridian is a MultiLineString cut there, as RFC 7946 section 3.1.9 asks:
        the cut points are interpolated exactly on the meridian (``[180, lat]`` ending one part,
        ``[-180, lat]`` starting the next) and each part stays on its side; a route that only
        touches the meridian stays one LineString (see
        :func:`lrm_cvx.planning.missions.split_antimeridian`). LineString properties: ``kind``
        ``"route"``, ``robot``, ``cost``, ``budget``. Point properties: ``cell``, ``robot``,
        ``order`` (first visit on its robot's route), ``selection`` (index in ``stops``),
        ``start`` (a sensor: ``kind`` ``"sensor"``, ``sensor``, ``cell``, ``gain``). The
        collection's properties carry method, cost, budget, information and the path model
        (and ``sensor``, e.g. ``"disc 5 km"``, when it is not a point). Written atomically when
        ``path``.
        """
        from .missions import plan_geojson

        doc = plan_geojson(self)
        if not self.sensor.is_point:
            doc.setdefault("properties", {})["sensor"] = self.sensor.describe()
        if path is not None:
            with atomic_output(path) as tmp:
                tmp.write_text(json.dumps(doc))
        return doc

    def to_mission(self, path: str | Path, *, robot: int = 0, altitude: float | None = None,
                   speed: float | None = None, hold: float = 0.0) -> Path:
        """Write the route as a mission file by ``path``'s suffix: ``.plan`` (QGroundControl),
        ``.waypoints`` (MAVLink ``QGC WPL 110``), ``.gpx`` or ``.kml``; ``altitude`` in m
        (default 50 m above home for the autopilot formats). See
        :mod:`lrm_cvx.planning.missions`."""
        from .missions import write_mission

        return write_mission(self, path, robot=robot, altitude=altitude, speed=speed,
                             hold=hold)

    def explore(self, background: Any = None, *, cmap: str = "viridis",
                tiles: Any = "auto") -> Any:
        """An interactive ``folium.Map`` of the plan, for a notebook or a field laptop.

        Each robot's route is a line (its start starred), each sampling stop a circle and, when
        given, ``background`` a layer with a legend in its units. Needs folium
        (``lrm-cvx[explore]``).

        Parameters
        ----------
        background : xarray.DataArray or numpy.ndarray, optional
            A field on the region's grid, ``(lat, lon)`` or one value per cell (e.g. a
            prediction or its std). A DataArray's ``name`` labels the layer and its ``units``
            attribute the legend; otherwise the units of the record the region came from.
        cmap : str
            Matplotlib colour map of ``background``.
        tiles : str, path or None
            The base map: ``"auto"`` (default) OpenStreetMap when its tile server answers,
            else none; ``None`` none; a ``{z}/{x}/{y}.png`` folder or an ``.mbtiles`` file
            written into the page for offline use; see :func:`lrm_cvx.interactive.explore_map`.

        Returns
        -------
        folium.Map
            Shown inline in a notebook; ``.save("plan.html")`` writes a page that, without
            online tiles, loads nothing from the internet.

        Examples
        --------
        >>> std = state.predict()["std"]  # doctest: +SKIP
        >>> fmap = plan.explore(std, tiles="tiles/")  # doctest: +SKIP
        >>> fmap.save("plan.html")  # doctest: +SKIP
        """
        from ..interactive import explore_map, record_label

        region = check_region(self._region, "the plan's region")
        fields = {}
        quantity, units = record_label(region.attrs, region.name)
        if background is not None:
            values = np.asarray(getattr(background, "values", background), dtype=float)
            if values.ndim == 1:
                values = region.unstack(values).values
            name = str(getattr(background, "name", None) or "background")
            attrs = getattr(background, "attrs", None)
            if attrs is not None and "units" in attrs:
                units = str(attrs["units"])
            fields[name] = (values, cmap, units)
        routes = [(self.lat[self.route_robot == r], self.lon[self.route_robot == r])
                  for r in range(self.n_robots if self.path.get("kind") != "static" else 0)]
        first = np.unique(self.route, return_index=True)[1]
        first = first[np.isin(self.route[first], self.stops) & self.waypoint[first]]
        stops = [(self.lat[i], self.lon[i], f"cell {int(self.route[i])}") for i in first]
        return explore_map(region.lat.values, region.lon.values, fields, routes=routes,
                           stops=stops, tiles=tiles, quantity=quantity)

    def plot(self, ax: Any = None, background: Any = None, *, coast: Any = "auto",
             **background_kw: Any) -> Any:
        """Draw the plan on a map: optional ``background`` (a ``(lat, lon)`` DataArray or array
        on the region's grid), the coast (``coast``: ``"auto"`` real coastlines where a
        shapefile is at hand offline, else the outline of the region's cells; ``"cartopy"``,
        ``"outline"`` or None, see :func:`lrm_cvx.coastlines.draw_coast`), the route line,
        the cells and the start (star). Returns ``ax``."""
        import matplotlib.pyplot as plt

        from ..coastlines import check_coast, draw_coast

        coast = check_coast(coast)
        if ax is None:
            _, ax = plt.subplots()
        grid = None if self._region is None else (
            self._region.lat.values, self._region.lon.values, self._region.mask)
        if background is not None:
            values = np.asarray(getattr(background, "values", background), dtype=float)
            if self._region is not None and values.ndim == 1:
                values = self._region.unstack(values).values
            if self._region is not None:
                lat, lon = self._region.lat.values, self._region.lon.values
            elif hasattr(background, "dims") and background.ndim == 2:
                lat = np.asarray(background[background.dims[0]].values)
                lon = np.asarray(background[background.dims[1]].values)
            else:
                raise ValueError("a plain-array background needs the plan's region")
            kw = {"shading": "nearest", "cmap": "viridis"} | background_kw
            mesh = ax.pcolormesh(lon, lat, values, **kw)
            ax.figure.colorbar(mesh, ax=ax, shrink=0.8)
            if grid is None:
                grid = (lat, lon, np.isfinite(values))
        if grid is not None:
            draw_coast(ax, grid[0], grid[1], coast, valid=grid[2])
        colours = ["crimson", "royalblue", "darkorange", "seagreen", "purple", "saddlebrown"]
        for r in range(self.n_robots):
            sel = np.flatnonzero(self.route_robot == r)
            label = "route" if self.n_robots == 1 else f"robot {r}"
            ax.plot(self.lon[sel], self.lat[sel], "-", color="white", lw=2.5, alpha=0.8,
                    zorder=2)
            ax.plot(self.lon[sel], self.lat[sel], "-", color=colours[r % len(colours)], lw=1.2,
                    zorder=3, label=label)
        is_stop = self.waypoint & np.isin(self.route, self.stops)
        first = np.unique(self.route, return_index=True)[1]
        first = first[is_stop[first]]
        ax.scatter(self.lon[first], self.lat[first], s=14, color="black", zorder=4,
                   label="stops" if self.n_robots > 1 or self.path.get("sense_along")
                   else "cells")
        heads = np.flatnonzero(self._order() == 0) if self.path.get("kind") != "static" \
            else np.empty(0, np.int64)
        if heads.size:
            ax.scatter(self.lon[heads], self.lat[heads], s=120, marker="*", color="gold",
                       edgecolor="black", zorder=5, label="start")
        ax.set_xlabel("lon")
        ax.set_ylabel("lat")
        ax.set_title(f"{self.method}: {len(self)} cells, cost {self.cost:.3g}/{self.budget:.3g}")
        ax.legend(loc="best", fontsize="small")
        return ax
