"""Generalized low rank models: ``D (T x L) ~ X^T Y`` fitted on the observed entries.

``GLRM`` is the estimator; ``fold_in`` is the low-level region completion used by the planner's
evaluation; losses and regularisers are small classes (see :mod:`.losses`, :mod:`.regularizers`).
"""

from __future__ import annotations

from .fit import FitResult, fit_glrm
from .foldin import fold_in, fold_in_many, mean_std
from .losses import Absolute, Huber, Loss, Quadratic, Quantile, get_loss
from .model import GLRM
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
    "mean_std",
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
