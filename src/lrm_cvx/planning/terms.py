"""The criterion's terms a planner reads: a prior belief or posterior keywords -> oracle inputs.

Shared by the greedy (:mod:`~lrm_cvx.planning.greedy`) and static placement
(:mod:`~lrm_cvx.planning.static`), so neither imports the other's internals.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ..errors import PlanningError
from ..region import Region

__all__ = ["PRIOR_TERMS", "PriorTerms", "split_prior", "prior_terms", "resolve_prior",
           "oracle_terms", "history_arrays"]

PRIOR_TERMS = ("prior_precision", "noise_var", "target_weights", "prior_cov", "spatial_cov",
               "targets")
"""The criterion's posterior terms a planner reads from its ``prior=`` (the fields of
:class:`PriorTerms`)."""


@dataclass(frozen=True, eq=False)
class PriorTerms:
    """The criterion's prior as explicit terms: what a planner's ``prior=`` takes besides a
    :class:`~lrm_cvx.belief.posterior.LatentPosterior` (``MonitorState.planner_kwargs()`` returns
    one as ``{"prior": PriorTerms(...)}``).

    Parameters
    ----------
    prior_precision : ``(k, k)`` array or None
        The fold-in's prior precision ``M0`` (docs/reconstruction.md): the information matrix
        of ``"fisher"`` and ``"a-optimal"`` is ``M0 + sum_P y_p y_p^T / noise_var_p``.
    noise_var : float, ``(L,)`` array or None
        The measurement noise variance, one value or one per cell.
    target_weights : ``(L,)`` array or None
        The A-optimal target ``sum_i target_weights_i y_i y_i^T`` (per-cell variances).
    prior_cov : ``(k, k)`` array or None
        The latent covariance of ``criterion="gp-variance"``.
    spatial_cov : a spatial covariance or None
        The GP residual of ``criterion="gp-variance"``.
    targets : ``(m,)`` cells or None
        The cells whose variance ``"gp-variance"`` sums (None: every cell).

    Examples
    --------
    >>> PriorTerms(noise_var=0.5).information()["noise_var"]
    0.5
    """

    prior_precision: Any = None
    noise_var: Any = None
    target_weights: Any = None
    prior_cov: Any = None
    spatial_cov: Any = None
    targets: Any = None

    def information(self) -> dict[str, Any]:
        """The terms as the planner's keyword dictionary (``targets`` aside), the form of
        ``LatentPosterior.information()``."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "targets"}

    def without_spatial(self) -> PriorTerms:
        """These terms without ``prior_cov`` and ``spatial_cov`` (the Fisher and A-optimal
        criteria's)."""
        return PriorTerms(self.prior_precision, self.noise_var, self.target_weights,
                          targets=self.targets)

    def same(self, other: Any) -> bool:
        """Whether ``other`` holds the same terms (arrays equal entry by entry)."""
        if not isinstance(other, PriorTerms):
            return False
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if a is b:
                continue
            if a is None or b is None:
                return False
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not np.array_equal(np.asarray(a), np.asarray(b)):
                    return False
            elif a != b:
                return False
        return True


def split_prior(prior: Any) -> tuple[Any, dict[str, Any]]:
    """``(belief, terms)`` of a planner's ``prior=``: a :class:`PriorTerms` gives its fields as
    ``terms`` (every name of :data:`PRIOR_TERMS`) and no belief; a belief (or None) is returned
    as it is, with every term None."""
    if isinstance(prior, PriorTerms):
        return None, {key: getattr(prior, key) for key in PRIOR_TERMS}
    return prior, dict.fromkeys(PRIOR_TERMS)


def prior_terms(prior: Any) -> dict[str, Any]:
    """Every term of :data:`PRIOR_TERMS` that a planner's ``prior=`` (a :class:`PriorTerms`, a
    belief or None) gives, None where it gives none."""
    belief, terms = split_prior(prior)
    targets = terms.pop("targets")
    return {**resolve_prior(belief, terms), "targets": targets}


def _prior_terms(prior: Any) -> dict[str, Any]:
    """The planner's keyword terms of a latent belief (``LatentPosterior.information()``)."""
    info = getattr(prior, "information", None)
    if not callable(info):
        raise PlanningError("prior must be a LatentPosterior (e.g. model.latent_prior("
                            f"'empirical')) or a PriorTerms, got {type(prior).__name__}")
    return info()


def resolve_prior(prior: Any, terms_given: dict[str, Any]) -> dict[str, Any]:
    """The criterion's keyword terms from ``prior`` (or the ones given directly)."""
    if prior is None:
        return terms_given
    terms = _prior_terms(prior)
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
