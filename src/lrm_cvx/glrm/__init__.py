"""Generalized low rank models: ``D (T x L) ~ X^T Y`` fitted on the observed entries.

``GLRM`` is the estimator; :class:`~.posterior.LatentPosterior` is the fold-in's Gaussian belief
(every completion, the planner's prior, the monitoring filter); ``fold_in`` is its thin wrapper on
a bare factor matrix; losses and regularisers are small classes (see :mod:`.losses`,
:mod:`.regularizers`).
"""

from __future__ import annotations

from .fit import FitResult, fit_glrm
from .foldin import fold_in, fold_in_many
from .losses import Absolute, Huber, Loss, Quadratic, Quantile, get_loss
from .model import GLRM
from .posterior import LatentPosterior, ObservationModel
from .regularizers import (
    L1,
    CvxpyRegularizer,
    NonNegative,
    Regularizer,
    Ridge,
    ZeroReg,
    get_regularizer,
)

__all__ = [
    "GLRM",
    "fit_glrm",
    "FitResult",
    "fold_in",
    "fold_in_many",
    "LatentPosterior",
    "ObservationModel",
    "Loss",
    "Quadratic",
    "Huber",
    "Absolute",
    "Quantile",
    "get_loss",
    "Regularizer",
    "ZeroReg",
    "Ridge",
    "L1",
    "NonNegative",
    "CvxpyRegularizer",
    "get_regularizer",
]
