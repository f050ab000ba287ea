"""lrm-cvx: persistent environmental monitoring with low-rank models.

Load gridded snapshots, fit a generalized low rank model, plan where a robot should sample under a
path budget, certify the plan's optimality gap, and predict the whole map from a few observations.
"""

from __future__ import annotations

from . import accessor as _accessor  # noqa: F401  (registers the .lrm accessor)
from . import errors
from .region import Region

__version__ = "0.1.0"
__all__ = ["Region", "errors", "__version__"]
