"""The belief: what the model says about a snapshot given a few observations.

The Gaussian posterior of the latent vector (:class:`~.posterior.LatentPosterior`: every
completion, the planner's prior, the monitoring filter), the observation model of point and
averaged rows, the fold-in on a bare factor matrix, and the filter that carries the belief from
one snapshot to the next with the model's dynamics.
"""

from __future__ import annotations

from .foldin import fold_in, fold_in_many
from .posterior import LatentPosterior, ObservationModel

__all__ = ["fold_in", "fold_in_many", "LatentPosterior", "ObservationModel"]
