"""The registry of refinements that improve a finished plan (a leaf module: the greedy, the
certificate's gap split and the refinements themselves meet here without importing each
other)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import PlanningError
from ..registry import Registry

__all__ = ["REFINERS", "RefineContext"]

REFINERS = Registry("refinement", PlanningError)
"""Refinements of a finished plan, ``name -> refiner(plan, options, context) -> Plan``
(``options``: a dict of keyword arguments, empty for the defaults; ``context``: a
:class:`RefineContext`). :mod:`~lrm_cvx.planning.refine` registers ``"local"`` (the local
search), :mod:`~lrm_cvx.planning.lines` ``"lines"`` and ``"rivals"`` (the route against its
straight and gentler rivals). ``plan_greedy(refine=name)`` and the certificate's gap split look
a refinement up here, so neither imports it."""


@dataclass(frozen=True)
class RefineContext:
    """What a refiner reads besides the plan: the criterion's resolved prior ``terms``; from the
    greedy also its factor matrix ``Y``, ``region``, ``fleet``, path ``request``, ``criterion``,
    ``ridge``, oracle terms ``extra``, ``rival(exponent)``, the greedy rerun with another
    cost exponent (None when that is the exponent it ran with), and ``base``, the greedy's
    oracle on its initial cells (kept for the checks against rival routes, which start from
    it)."""

    terms: Mapping[str, Any] = field(default_factory=dict)
    Y: Any = None
    region: Any = None
    fleet: Any = None
    request: Any = None
    criterion: str = "fisher"
    ridge: float = 0.0
    extra: Mapping[str, Any] = field(default_factory=dict)
    rival: Callable[[float], Any] | None = None
    base: Any = None
