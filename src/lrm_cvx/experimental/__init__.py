"""Research tools, used by the tests and the benchmarks, not by the planners.

:mod:`.floor` (``convex_floor``, ``route_mixture``): the best mixture of feasible routes, a value
every convex route relaxation reaches (how tight a convex certificate can be, docs/certificate.md
§9). This layer sits above ``planning`` (it builds on its plans and route shapes) and nothing in
the package imports it; APIs here may change without a deprecation period.
"""

from __future__ import annotations

from .floor import ConvexFloor, convex_floor, route_mixture

__all__ = ["ConvexFloor", "convex_floor", "route_mixture"]
