"""The steps of the estimator that the packages above the model provide.

The model and its fit know nothing of the belief (:mod:`lrm_cvx.belief`) or of the validated
choices (:mod:`lrm_cvx.validation`), which sit above them in the layers. :class:`~.model.GLRM`
looks those steps up here by name; each package registers its own when it is imported, and
importing ``lrm_cvx`` imports both, so the steps are always there (as the planner looks its
refinements up in :data:`~lrm_cvx.planning.refiners.REFINERS`).
"""

from __future__ import annotations

from ..errors import ModelError
from ..registry import Registry

__all__ = ["HOOKS"]

HOOKS = Registry("model hook", ModelError)
"""``name -> function`` of the steps :class:`~.model.GLRM` delegates upwards.

Registered by :mod:`lrm_cvx.belief`: ``"model-prior"`` and ``"fold-in-snapshots"`` (the
fold-in behind ``latent_prior`` and ``complete``). Registered by :mod:`lrm_cvx.validation`:
``"check-auto-data"``, ``"choose-rank"``, ``"validate-choices"``, ``"validation-window"``,
``"clone-model"``, ``"calibrate"``, ``"select-kernel"`` and ``"select-rank"`` (``rank=``,
``temporal=``, ``spatial="auto"`` and ``calibration=``)."""
