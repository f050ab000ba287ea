"""Path planning: the greedy planner, the paper's baselines, the Plan result and its bound."""

from __future__ import annotations

from ..registry import lazy_attributes
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


# the certificate module (cvxpy, scipy) is imported only when used
__getattr__, __dir__ = lazy_attributes(
    __name__, {"plan_bound": ".certificate", "dopt_upper_bound": ".dopt"})
