"""Path planning: the greedy planner, the paper's baselines, the Plan result and its bound."""

from __future__ import annotations

from typing import Any

from .baselines import random_walk, transect
from .greedy import initial_cells, plan_greedy
from .plan import Plan
from .planners import (
    METHOD_REGISTRY,
    GreedyPlanner,
    Planner,
    RandomWalk,
    Refined,
    StaticPlacement,
    Transect,
)
from .refine import refine
from .request import Fleet, PathOptions, PlanPath
from .sensors import Sensor, plan_observations
from .static import place_sensors
from .terms import PriorTerms

__all__ = [
    "Plan",
    "plan_greedy",
    "place_sensors",
    "refine",
    "initial_cells",
    "transect",
    "random_walk",
    "plan_bound",
    "dopt_upper_bound",
    "PathOptions",
    "PriorTerms",
    "Fleet",
    "PlanPath",
    "Sensor",
    "plan_observations",
    "Planner",
    "GreedyPlanner",
    "StaticPlacement",
    "Transect",
    "RandomWalk",
    "Refined",
    "METHOD_REGISTRY",
]


def __getattr__(name: str) -> Any:
    # the certificate module (cvxpy, scipy) is imported only when used
    if name == "plan_bound":
        from .certificate import plan_bound

        return plan_bound
    if name == "dopt_upper_bound":
        from .dopt import dopt_upper_bound

        return dopt_upper_bound
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
