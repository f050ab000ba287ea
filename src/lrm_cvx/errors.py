"""Exceptions raised by lrm-cvx.

Every user error is an :class:`LrmError`, so ``except lrm_cvx.errors.LrmError`` catches all of
them; the subclasses say which step refused the input. Each also derives from the builtin a
scientific-Python user would expect (``ValueError``, ``RuntimeError``) so generic handlers work.
"""

from __future__ import annotations

__all__ = [
    "LrmError",
    "DataError",
    "RegionError",
    "ModelError",
    "NotFittedError",
    "PlanningError",
    "SolverError",
    "ConvergenceWarning",
]


class LrmError(Exception):
    """Base class of every error raised by lrm-cvx for bad input or an impossible request."""


class DataError(LrmError, ValueError):
    """Input data are unusable: wrong dims, all missing, corrupt or missing files, bad values."""


class RegionError(LrmError, ValueError):
    """A location is outside the grid or on a masked cell, or a grid/region does not match."""


class ModelError(LrmError, ValueError):
    """A model parameter or a model/data combination is invalid (e.g. rank too large)."""


class NotFittedError(ModelError, AttributeError):
    """A model method needs ``fit`` to have been called first."""


class PlanningError(LrmError, ValueError):
    """A planning request is invalid: negative budget, singular initial set, bad start cell."""


class SolverError(LrmError, RuntimeError):
    """A numerical solver failed; the message carries the solver's name and status."""


class ConvergenceWarning(UserWarning):
    """An iterative method stopped at its iteration limit before meeting its tolerance."""
