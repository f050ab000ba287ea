"""Deprecated alias: the route costs moved to :mod:`lrm_cvx.planning.routecost` (issue #27).

``lrm_cvx.cost.<name>`` still works for one release and warns (``DeprecationWarning``);
import from ``lrm_cvx.planning.routecost`` instead.
"""

from __future__ import annotations

import importlib
import warnings
from typing import Any

_MOVED = ("nearest_neighbor_tour", "route_length", "NearestNeighborCost", "InsertionCost",
          "make_cost", "COSTS", "COST_REGISTRY")

__all__ = list(_MOVED)


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        warnings.warn(f"lrm_cvx.cost.{name} moved to lrm_cvx.planning.routecost.{name}; "
                      "lrm_cvx.cost goes in the next release", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module("lrm_cvx.planning.routecost"), name)
    raise AttributeError(f"module 'lrm_cvx.cost' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
