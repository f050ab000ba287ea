"""The registry of local searches that improve a finished plan (a leaf module: the greedy, the
certificate's gap split and the search itself meet here without importing each other)."""

from __future__ import annotations

from ..errors import PlanningError
from ..registry import Registry

__all__ = ["REFINERS"]

REFINERS = Registry("refinement", PlanningError)
"""Local searches that improve a finished plan, ``name -> refine(plan, options, terms) -> Plan``
(``options``: True or a dict of keyword arguments; ``terms``: the criterion's resolved prior
terms). :mod:`~lrm_cvx.planning.refine` registers ``"local"``. ``plan_greedy(refine=...)`` and
the certificate's gap split look the refinement up here, so neither imports the search (which
itself runs the greedy)."""
