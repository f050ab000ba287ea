"""One path request: how the robots travel (:class:`PathOptions`) and who travels (:class:`Fleet`).

Every planner, baseline, the certificate, ``evaluate`` and the CLI read a request through these
two objects, validated here and nowhere else; a plan records both in :class:`PlanPath`. A new
path option goes here: a field of :class:`PathOptions`, its check in ``__post_init__``, its
summary in :meth:`PlanPath.describe`; the path model (``paths.py``) then reads it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._validation import check_positive
from ..errors import PlanningError
from .sensors import POINT, Sensor

__all__ = ["PathOptions", "Fleet", "PlanPath", "PATH_FIELDS", "METRICS", "check_metric",
           "check_amount", "pop_options", "resolve_starts", "resolve_budgets"]

METRICS = ("grid", "km")
"""Travel metrics: Euclidean grid units (the paper) and great-circle km."""

PATH_FIELDS = ("metric", "speed", "stop_cost", "traversable", "closed", "end", "sense_along",
               "sensor")
"""The keyword names of a path request (the fields of :class:`PathOptions`)."""


def check_metric(metric: Any, speed: Any) -> tuple[str, float | None, str]:
    """``(metric, speed, unit)`` after validation: metric lower-cased (one of :data:`METRICS`),
    speed a float km/h > 0 or None (only with ``"km"``), unit ``"grid units"``, ``"km"`` or
    ``"h"`` (the budget's); PlanningError naming the argument otherwise."""
    if not isinstance(metric, str) or metric.lower() not in METRICS:
        raise PlanningError(f"metric must be one of {list(METRICS)}, got {metric!r}")
    metric = metric.lower()
    if speed is None:
        return metric, None, "grid units" if metric == "grid" else "km"
    if metric != "km":
        raise PlanningError(
            f"speed (km/h) needs metric='km' (a budget in hours), got metric={metric!r}")
    if isinstance(speed, (str, bytes, bool, np.bool_)):
        raise PlanningError(f"speed must be a number of km/h > 0, got {speed!r}")
    try:
        v = float(speed)
    except (TypeError, ValueError):
        raise PlanningError(f"speed must be a number of km/h > 0, got {speed!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise PlanningError(f"speed must be a finite number of km/h > 0, got {speed!r}")
    return metric, v, "h"


def check_amount(value: Any, name: str, unit: str) -> float:
    """A budget or stop cost ``value`` in ``unit`` as a finite float >= 0 (PlanningError naming
    ``name (unit)``; a string or a bool is refused, not converted)."""
    return check_positive(value, f"{name} ({unit})", error=PlanningError, numbers_only=True)


def pop_options(kwargs: dict[str, Any], names: tuple[str, ...]) -> dict[str, Any]:
    """Remove and return the entries of ``kwargs`` named in ``names`` (a public function's
    ``**options`` split into the groups it hands on)."""
    return {key: kwargs.pop(key) for key in names if key in kwargs}


def _unexpected(where: str, names: Any) -> TypeError:
    """The TypeError Python raises for an unknown keyword argument of ``where``."""
    return TypeError(f"{where}() got an unexpected keyword argument {sorted(names)[0]!r}")


@dataclass(frozen=True, eq=False)
class PathOptions:
    """How every robot of a request travels (docs/planning.md, "Path models"); validated.

    ``metric``: ``"grid"`` (Euclidean grid units, the paper) or ``"km"`` (great circle);
    ``speed``: km/h (with ``"km"``), making the budget's unit hours; ``stop_cost`` (>= 0, budget
    unit) per sampling stop, start included; ``traversable``: None (straight lines), ``"valid"``
    or a boolean ``(lat, lon)`` mask (travel over the 8-connected enterable cells); ``closed``:
    return to the start; ``end``: a cell or ``(lat, lon)`` where every route finishes;
    ``sense_along``: every cell a route passes is observed; ``sensor``: what a stop observes
    (:class:`~lrm_cvx.planning.sensors.Sensor`, or a string such as ``"disc:5km"``: point,
    square / disc footprints, leg averages; docs/planning.md, "Sensors"). The defaults are the
    paper's.

    >>> PathOptions(metric="km", speed=2.0).unit
    'h'
    """

    metric: str = "grid"
    speed: float | None = None
    stop_cost: float = 0.0
    traversable: Any = None
    closed: bool = False
    end: Any = None
    sense_along: bool = False
    sensor: Any = POINT

    def __post_init__(self) -> None:
        metric, speed, unit = check_metric(self.metric, self.speed)
        stop_cost = check_amount(self.stop_cost, "stop_cost", unit)
        if not isinstance(self.closed, (bool, np.bool_)):
            raise PlanningError(f"closed must be True or False, got {self.closed!r}")
        if self.closed and self.end is not None:
            raise PlanningError("closed=True and end= exclude each other: a closed tour ends "
                                "at its start")
        if not isinstance(self.sense_along, (bool, np.bool_)):
            raise PlanningError(f"sense_along must be True or False, got {self.sense_along!r}")
        trav = self.traversable
        if isinstance(trav, str):
            if trav.strip().lower() != "valid":
                raise PlanningError(f"traversable must be None, 'valid' or a boolean (lat, "
                                    f"lon) mask, got {trav!r}")
            trav = "valid"
        elif trav is not None and not hasattr(trav, "shape"):
            raise PlanningError(f"traversable must be None, 'valid' or a boolean (lat, lon) "
                                f"mask, got {type(trav).__name__}")
        sensor = Sensor.of(self.sensor)
        if sensor.is_leg and self.sense_along:
            raise PlanningError("sensor='leg-average' already observes along the route: "
                                "sense_along=True does not combine with it")
        for name, value in (("sensor", sensor), ("metric", metric), ("speed", speed),
                            ("stop_cost", stop_cost),
                            ("traversable", trav), ("closed", bool(self.closed)),
                            ("sense_along", bool(self.sense_along))):
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_kwargs(cls, path: PathOptions | None = None, *, where: str = "plan",
                    allowed: tuple[str, ...] = PATH_FIELDS, **kwargs: Any) -> PathOptions:
        """The request of a public function's keywords: ``path`` (a :class:`PathOptions`, or
        None for the paper's) updated by ``kwargs`` (names among ``allowed``; another name is
        the TypeError of an unknown keyword argument of ``where``)."""
        bad = set(kwargs) - set(allowed)
        if bad:
            raise _unexpected(where, bad)
        if path is None:
            return cls(**kwargs)
        if not isinstance(path, PathOptions):
            raise PlanningError(f"path must be a PathOptions (or None), got "
                                f"{type(path).__name__}")
        unused = {f for f in PATH_FIELDS if f not in allowed and getattr(path, f) !=
                  getattr(_PAPER, f)}
        if unused:
            raise PlanningError(f"{where} does not support the path options {sorted(unused)}")
        return replace(path, **kwargs) if kwargs else path

    def resolved(self, region: Any) -> PathOptions:
        """These options with ``end`` as a cell index of ``region`` (RegionError naming it)."""
        if self.end is None:
            return self
        return replace(self, end=int(region.resolve_cell(self.end, "end")))

    # ------------------------------------------------------------------ reading
    @property
    def unit(self) -> str:
        """The budget's unit: ``"grid units"``, ``"km"`` or ``"h"``."""
        return "h" if self.speed is not None else "km" if self.metric == "km" else "grid units"

    @property
    def traversable_kind(self) -> str:
        """``"none"`` (straight lines), ``"valid"`` or ``"mask"``."""
        t = self.traversable
        return "none" if t is None else "valid" if isinstance(t, str) else "mask"

    @property
    def is_paper(self) -> bool:
        """Every option at the paper's default."""
        return not self.changed()

    def changed(self) -> dict[str, Any]:
        """The options that differ from the paper's, as keyword arguments (so a call with
        them is the paper's call when there are none)."""
        out = {}
        for f in PATH_FIELDS:
            value, default = getattr(self, f), getattr(_PAPER, f)
            if value is not None if default is None else value != default:
                out[f] = value
        return out

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PathOptions):
            return NotImplemented
        a, b = self.traversable, other.traversable
        same_mask = a is b or (isinstance(a, str) and a == b) or (
            a is not None and b is not None and not isinstance(a, str)
            and not isinstance(b, str) and np.array_equal(np.asarray(a), np.asarray(b)))
        return same_mask and all(_same(getattr(self, f), getattr(other, f)) for f in PATH_FIELDS
                                 if f != "traversable")

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        parts = [f"{k}={v!r}" if k != "traversable" or isinstance(v, str) else f"{k}=<mask>"
                 for k, v in self.changed().items()]
        return f"PathOptions({', '.join(parts)})"


_PAPER = PathOptions()


def _same(a: Any, b: Any) -> bool:
    """Equal option values (an ``end`` may be an array ``(lat, lon)``)."""
    if a is None or b is None:
        return a is b
    return bool(np.array_equal(np.asarray(a, dtype=object), np.asarray(b, dtype=object)))


@dataclass(frozen=True)
class Fleet:
    """Who travels: one start cell and one budget per robot, ``budgets`` in ``unit`` (the path
    options' unit: ``"grid units"``, ``"km"``, ``"h"``; ``"sensors"`` for a static placement).
    ``is_fleet``: the request named a list of starts (a fleet, even of one robot). Every budget
    of the package is checked here (>= 0 and finite; a string or a bool is refused).

    >>> Fleet((3, 8), (10.0, 12.5)).n_robots
    2
    """

    starts: tuple[int, ...]
    budgets: tuple[float, ...]
    is_fleet: bool = False
    unit: str = "grid units"

    def __post_init__(self) -> None:
        if len(self.budgets) != len(self.starts) and self.starts:
            raise PlanningError(f"budget has {len(self.budgets)} values but there are "
                                f"{len(self.starts)} starts: give one budget per robot, or one "
                                "number for all")
        object.__setattr__(self, "starts", tuple(int(s) for s in self.starts))
        object.__setattr__(self, "budgets", tuple(self.check_budget(b, self.unit)
                                                  for b in self.budgets))

    @property
    def n_robots(self) -> int:
        return len(self.starts)

    @classmethod
    def resolve(cls, region: Any, start: Any, budget: Any, unit: str = "grid units") -> Fleet:
        """The fleet of ``start`` (a cell index or ``(lat, lon)``: one robot; a list, 1-D
        integer array or ``(n, 2)`` array of those: a fleet; a list of two non-integer numbers
        is one ``[lat, lon]``; or a :class:`Fleet`, then ``budget`` is None) and ``budget`` (a
        number, or for a fleet one per robot, each >= 0 in ``unit``)."""
        if isinstance(start, Fleet):
            if budget is not None:
                raise PlanningError("a Fleet carries its budgets: pass budget=None")
            if start.unit != unit:
                return replace(start, unit=unit)
            return start
        starts, fleet = resolve_starts(region, start)
        return cls(tuple(starts), tuple(resolve_budgets(budget, len(starts), fleet)), fleet,
                   unit)

    @staticmethod
    def check_budget(budget: Any, unit: str = "grid units") -> float:
        """One budget as a float >= 0 in ``unit`` (a string or a bool is refused)."""
        return check_amount(budget, "budget", unit)


def resolve_starts(region: Any, start: Any) -> tuple[list[int], bool]:
    """``(cells, fleet)`` of :meth:`Fleet.resolve`: one start (a cell index or a ``(lat, lon)``
    tuple) or a fleet (a list, or a 1-D integer / ``(n, 2)`` array, of those)."""
    if start is None:
        raise PlanningError("start is required: a cell index, a (lat, lon) tuple, or a list "
                            "of those (one per robot)")
    if isinstance(start, np.ndarray):
        if start.ndim == 1 and np.issubdtype(start.dtype, np.integer):
            start = start.tolist()
        elif start.ndim == 2 and start.shape[1] == 2:
            start = [tuple(row) for row in start.tolist()]
    if isinstance(start, list):
        flat = all(isinstance(v, (int, float, np.integer, np.floating)) and
                   not isinstance(v, (bool, np.bool_)) for v in start)
        if len(start) == 2 and flat and not all(isinstance(v, (int, np.integer))
                                                for v in start):
            return [region.resolve_cell(tuple(start), "start")], False  # one [lat, lon]
        if not start:
            raise PlanningError("start must not be an empty list (one start per robot)")
        cells = [region.resolve_cell(tuple(v) if isinstance(v, list) else v, f"start[{i}]")
                 for i, v in enumerate(start)]
        return cells, True
    return [region.resolve_cell(start, "start")], False


def resolve_budgets(budget: Any, n: int, fleet: bool) -> list[Any]:
    """``budget`` (a number, or for a fleet a list / array of ``n``) as ``n`` values, one per
    robot (:class:`Fleet` checks them)."""
    if isinstance(budget, (list, tuple, np.ndarray)) and not fleet:
        raise PlanningError(f"budget must be a number for one robot, got {budget!r} (a list "
                            "of budgets needs a list of starts, one per robot)")
    if isinstance(budget, (list, tuple, np.ndarray)):
        values = list(np.asarray(budget, dtype=object).ravel())
        if len(values) != n:
            raise PlanningError(f"budget has {len(values)} values but there are {n} starts: "
                                "give one budget per robot, or one number for all")
        return values
    if budget is None:
        raise PlanningError("budget is required (a number, or one per robot)")
    return [budget] * n


# ------------------------------------------------------------------------------ plan.path
PAPER_PATH: dict[str, Any] = {
    "kind": "path", "metric": "grid", "speed": None, "stop_cost": 0.0, "traversable": "none",
    "closed": False, "end": None, "unit": "grid units", "sense_along": False,
}
"""The path description of the paper (and of plans built without one): an open straight-line
path in grid units, one robot, sensing only at its stops; :class:`PlanPath` adds the fleet."""


class PlanPath(Mapping):
    """A plan's path request: ``kind`` (``"path"`` or ``"static"``), its :class:`PathOptions`
    (``options``; None when only the description is known, e.g. a traversable mask of a plan
    built by hand) and :class:`Fleet` (``fleet``), seen as a read-only mapping of the plan's
    path description: ``kind``, ``metric``, ``speed``, ``stop_cost``, ``traversable``
    (``"none"``, ``"valid"`` or ``"mask"``), ``closed``, ``end``, ``unit``, ``sense_along``,
    ``starts``, ``budgets`` and ``n_robots`` (``dict(plan.path)`` is that description)."""

    __slots__ = ("_items", "_options")

    def __init__(self, description: Mapping[str, Any] | None = None, *,
                 options: PathOptions | None = None, **items: Any) -> None:
        out = dict(PAPER_PATH)
        given = dict(description or {}, **items)
        unknown = sorted(set(given) - set(out) - {"starts", "budgets", "n_robots"})
        if unknown:
            raise ValueError(f"unknown path options {unknown}")
        out.update({k: v for k, v in given.items() if k in out})
        out["starts"] = [int(s) for s in np.atleast_1d(np.asarray(given.get("starts", []),
                                                                   dtype=np.int64))]
        out["budgets"] = [float(b) for b in np.atleast_1d(np.asarray(given.get("budgets", []),
                                                                      dtype=np.float64))]
        out["n_robots"] = max(len(out["starts"]), 1) if out["kind"] != "static" else 1
        self._items = out
        self._options = options

    @classmethod
    def describe(cls, options: PathOptions, fleet: Fleet | None, *, kind: str = "path",
                 traversable: str | None = None) -> PlanPath:
        """The record of a plan made under ``options`` for ``fleet``; ``traversable``
        overrides the summary (``"mask"`` for a path model's mask)."""
        starts = list(fleet.starts) if fleet is not None else []
        budgets = list(fleet.budgets) if fleet is not None else []
        return cls(kind=kind, metric=options.metric, speed=options.speed,
                   stop_cost=float(options.stop_cost),
                   traversable=traversable or options.traversable_kind,
                   closed=bool(options.closed), end=None if options.end is None else
                   int(options.end), unit=options.unit, sense_along=bool(options.sense_along),
                   starts=starts, budgets=budgets, options=options)

    @classmethod
    def of(cls, path: Any) -> PlanPath:
        """``path`` as a :class:`PlanPath` (a mapping: the description)."""
        return path if isinstance(path, PlanPath) else cls(path)

    # ------------------------------------------------------------------ the request
    @property
    def kind(self) -> str:
        return str(self._items["kind"])

    @property
    def unit(self) -> str:
        return str(self._items["unit"])

    @property
    def fleet(self) -> Fleet:
        return Fleet(tuple(self._items["starts"]), tuple(self._items["budgets"]),
                     len(self._items["starts"]) > 1, self.unit)

    @property
    def options(self) -> PathOptions | None:
        """The path options (None for a static placement, or a mask that was not kept)."""
        if self._options is not None or self.kind == "static":
            return self._options
        d = self._items
        if d["traversable"] not in (None, "none", "valid"):
            return None
        return PathOptions(metric=d["metric"], speed=d["speed"], stop_cost=d["stop_cost"] or 0,
                           traversable=None if d["traversable"] in (None, "none") else "valid",
                           closed=bool(d["closed"]), end=d["end"],
                           sense_along=bool(d["sense_along"]))

    @property
    def sensor(self) -> Sensor:
        """What each stop observed (:class:`~lrm_cvx.planning.sensors.Sensor`; point when
        the plan's options were not kept)."""
        return self._options.sensor if self._options is not None else POINT

    @property
    def is_paper(self) -> bool:
        """The paper's model: one robot, open straight-line path in grid units, no stop cost,
        point sensing only at the stops (what :func:`~lrm_cvx.planning.refine.refine` supports)."""
        return all(self._items.get(key) == value for key, value in PAPER_PATH.items()) and \
            self._items.get("n_robots", 1) == 1 and self.sensor.is_point

    # ------------------------------------------------------------------ read-only mapping
    def __getitem__(self, key: str) -> Any:
        return self._items[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __repr__(self) -> str:
        return f"PlanPath({self._items!r})"

    __hash__ = None  # type: ignore[assignment]
