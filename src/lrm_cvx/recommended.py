"""The recommended setting of docs/reconstruction.md: one dict that the CLI and the demo read.

Fit ``GLRM(offset=True, spatial="auto")`` (the residual's covariance family validated on the
training residuals: the exponential unless a smoother one is better by 2 %,
validation/kernel_selection.py), plan with the gp-variance criterion from the
start cell alone and keep a rival route instead of the greedy's when that criterion prefers it
(``refine="rivals"``: the four straight transects and the greedy with a gentler cost discount;
``method`` is its name in ``evaluate``), predict with the
empirical prior and the kriged GP residual (``fold_spatial``); a model for monitoring chooses
its temporal model on the training snapshots (``temporal="auto"``, validation/selection.py) and
calibrates its intervals conformally on them (``calibration``, validation/calibration.py). It is the
default of the CLI and of the library wherever a call has a fitted model to take it from
(``--paper`` / ``paper=True`` give the paper's setting); ``lrm_cvx.demo`` runs it beside the
paper's. Plain data, so it sits at the base of the layers.
"""

from __future__ import annotations

from typing import Any

__all__ = ["RECOMMENDED", "RESIDUAL_CRITERIA", "recommended_criterion"]

RECOMMENDED: dict[str, Any] = {
    "offset": True, "spatial": "auto", "criterion": "gp-variance",
    "method": "greedy:gp-variance", "initial": "start", "prior": "empirical",
    "fold_spatial": True, "temporal": "auto",
    # the greedy's route is checked under its own criterion against the four straight
    # transects from its start and the greedy with cost exponent 0.5
    # (planning/lines.py; docs/benchmarks.md)
    "refine": "rivals",
    # conformal intervals from forward folds of the training snapshots, the filter's own
    # thresholds for a model with dynamics (temporal="auto": closer to the coverage targets
    # under the filter, rolling origin, docs/benchmarks.md); the maps and plans are those of
    # the uncalibrated model (no residual re-weighting: it helped the storms' maps and hurt
    # sea ice's)
    "calibration": {"method": "conformal", "residual": False, "adaptive": False,
                    "max_snapshots": 2, "max_cells": 300, "temporal": "auto"},
}

RESIDUAL_CRITERIA = ("gp-variance",)
"""The criteria that plan on the model's GP residual (a model without one cannot run them)."""


def recommended_criterion(spatial: bool) -> str:
    """The recommended criterion for a model with (``spatial=True``) or without a GP residual.

    Parameters
    ----------
    spatial : bool
        Whether the model (or belief) has the spatial residual.

    Returns
    -------
    str
        ``RECOMMENDED["criterion"]`` (read now), or ``"fisher"`` when that criterion plans on
        the residual and there is none.

    Examples
    --------
    >>> recommended_criterion(spatial=False)
    'fisher'
    """
    criterion = RECOMMENDED["criterion"]
    return "fisher" if not spatial and criterion in RESIDUAL_CRITERIA else criterion
