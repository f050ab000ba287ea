"""The criterion's terms a planner reads: a prior belief or posterior keywords -> oracle inputs.

Shared by the greedy (:mod:`~lrm_cvx.planning.greedy`) and static placement
(:mod:`~lrm_cvx.planning.static`), so neither imports the other's internals.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import PlanningError
from ..region import Region

__all__ = ["PRIOR_TERMS", "resolve_prior", "oracle_terms", "history_arrays"]

PRIOR_TERMS = ("prior_precision", "noise_var", "target_weights", "prior_cov", "spatial_cov",
               "targets")
"""The criterion's posterior terms a planner takes as keywords (or from ``prior=``)."""


def _prior_terms(prior: Any) -> dict[str, Any]:
    """The planner's keyword terms of a latent belief (``LatentPosterior.information()``)."""
    info = getattr(prior, "information", None)
    if not callable(info):
        raise PlanningError("prior must be a LatentPosterior (e.g. model.latent_prior("
                            f"'empirical')), got {type(prior).__name__}")
    return info()


def resolve_prior(prior: Any, terms_given: dict[str, Any]) -> dict[str, Any]:
    """The criterion's keyword terms from ``prior`` (or the ones given directly)."""
    if prior is None:
        return terms_given
    terms = _prior_terms(prior)
    clash = sorted(key for key in terms if terms_given.get(key) is not None)
    if clash:
        raise PlanningError(f"prior= already gives {clash}; pass either prior or those")
    return {key: terms.get(key) for key in terms_given}


def oracle_terms(criterion: str, region: Region, pool: np.ndarray, t: dict[str, Any],
                 targets: Any) -> dict[str, Any]:
    """The keyword arguments of ``make_oracle(criterion, ...)`` from the resolved terms ``t``
    (``pool``: the candidate cells of the GP-variance oracle)."""
    if criterion == "gp-variance":
        return dict(region=region, spatial_cov=t["spatial_cov"], prior_cov=t["prior_cov"],
                    pool=pool, targets=targets, target_weights=t["target_weights"])
    extra: dict[str, Any] = {}
    if t["prior_precision"] is not None:
        extra["prior_precision"] = t["prior_precision"]
    if t["noise_var"] is not None:
        extra["noise_var"] = t["noise_var"]
    if t["target_weights"] is not None and criterion == "a-optimal":
        extra["target_weights"] = t["target_weights"]
    return extra


def history_arrays(hist: dict[str, list[float]]) -> dict[str, np.ndarray]:
    """A planner's per-pick history lists as arrays (cells, counts and robots int64)."""
    return {key: np.asarray(v, dtype=np.int64 if key in ("cell", "n_evaluated", "robot")
                            else np.float64) for key, v in hist.items()}
