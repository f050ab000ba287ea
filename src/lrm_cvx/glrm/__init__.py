"""Generalized low rank models: ``D (T x L) ~ X^T Y`` fitted on the observed entries.

``GLRM`` is the estimator; losses and regularisers are small classes (see :mod:`.losses`,
:mod:`.regularizers`). What the model believes about a new snapshot is in :mod:`lrm_cvx.belief`,
the choices validated on its record in :mod:`lrm_cvx.validation`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..registry import lazy_attributes

if TYPE_CHECKING:  # the names of _LAZY, for readers and type checkers
    from .fit import FitResult, fit_glrm
    from .losses import Absolute, Huber, Loss, Quadratic, Quantile, get_loss
    from .model import GLRM
    from .options import SolverOptions, SpatialOptions
    from .regularizers import (
        L1,
        CvxpyRegularizer,
        NonNegative,
        Regularizer,
        Ridge,
        ZeroReg,
        get_regularizer,
    )

_LAZY = {
    "GLRM": ".model",
    "SolverOptions": ".options",
    "SpatialOptions": ".options",
    "fit_glrm": ".fit",
    "FitResult": ".fit",
    **dict.fromkeys(("Loss", "Quadratic", "Huber", "Absolute", "Quantile", "get_loss"),
                    ".losses"),
    **dict.fromkeys(("Regularizer", "ZeroReg", "Ridge", "L1", "NonNegative",
                     "CvxpyRegularizer", "get_regularizer"), ".regularizers"),
}
"""Public name -> its module, imported on first use (the fit imports cvxpy and numba, which
``import lrm_cvx`` does not need)."""

__all__ = ["GLRM", "SolverOptions", "SpatialOptions", "fit_glrm", "FitResult", "Loss",
           "Quadratic", "Huber", "Absolute", "Quantile", "get_loss", "Regularizer", "ZeroReg",
           "Ridge", "L1", "NonNegative", "CvxpyRegularizer", "get_regularizer"]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
