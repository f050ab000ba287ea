"""Old location of the convex floor (moved to :mod:`lrm_cvx.experimental.floor`).

Importing this module warns (DeprecationWarning) and re-exports the names; removed in the next
release.
"""

from __future__ import annotations

import warnings

from ..experimental.floor import ConvexFloor, convex_floor, route_mixture  # deprecated shim

__all__ = ["ConvexFloor", "convex_floor", "route_mixture"]

warnings.warn("lrm_cvx.planning.floor moved to lrm_cvx.experimental.floor",
              DeprecationWarning, stacklevel=2)
