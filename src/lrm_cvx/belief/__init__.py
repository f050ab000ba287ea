"""The belief: what the model says about a snapshot given a few observations.

The Gaussian posterior of the latent vector (:class:`~.posterior.LatentPosterior`: every
completion, the planner's prior, the monitoring filter), the observation model of point and
averaged rows, the fold-in on a bare factor matrix, and the filter that carries the belief from
one snapshot to the next with the model's dynamics. Importing this package registers the
fold-in that ``GLRM.complete`` and ``GLRM.latent_prior`` run in
:data:`~lrm_cvx.glrm.hooks.HOOKS`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..glrm.hooks import HOOKS
from ..registry import Deferred, lazy_attributes

if TYPE_CHECKING:  # the names of _LAZY, for readers and type checkers
    from .foldin import fold_in, fold_in_many
    from .posterior import LatentPosterior, ObservationModel

_LAZY = {"fold_in": ".foldin", "fold_in_many": ".foldin", "LatentPosterior": ".posterior",
         "ObservationModel": ".posterior"}
"""Public name -> its module, imported on first use."""

__all__ = ["fold_in", "fold_in_many", "LatentPosterior", "ObservationModel"]

HOOKS.register("model-prior", Deferred("lrm_cvx.belief.posterior:model_prior"),
               description="the belief over a new snapshot's latent vector (latent_prior)")
HOOKS.register("fold-in-snapshots", Deferred("lrm_cvx.belief.posterior:fold_in_snapshots"),
               description="the fold-in of whole snapshots (complete)")


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
