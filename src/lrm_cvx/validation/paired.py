"""The paired statistics of the validated choices (the bootstrap bound and the paired
differences of candidates scored on the same sample sets) and the validation designs they
share; the rules that read them are those of :mod:`lrm_cvx.validation.search`."""

from __future__ import annotations

import numpy as np

from ..errors import ModelError

__all__ = ["AUTO_DESIGNS", "AUTO_SIZES", "MAX_SCORED", "bootstrap_upper",
           "paired_difference", "shared_cases"]

AUTO_DESIGNS = ("route", "line", "scattered")
"""Sample designs of the validation days: a route, a transect, scattered cells."""
AUTO_SIZES = (5, 15, 50)
"""Samples per validation day."""
BOOTSTRAP_DRAWS = 2000
"""Resamples of the paired bootstrap of :func:`bootstrap_upper`."""
BOOTSTRAP_BLOCK = 1 << 21
"""Draw x case counts held at once (16 MiB)."""
BOOTSTRAP_SEED = 0
"""Its seed (the bound is a deterministic function of the errors)."""
MAX_SCORED = 256
"""Cells a validation day's map is scored on (a random subset of the unsampled observed cells:
the kriged maps cost ``O(cells)`` each)."""


def bootstrap_upper(E: np.ndarray, confidence: float, n_boot: int = BOOTSTRAP_DRAWS
                    ) -> np.ndarray:
    """``(n_candidates, n_sizes)`` one-sided upper confidence bound of each candidate's
    relative MSE change against candidate 0, ``mean(E_c) / mean(E_0) - 1`` over the cases
    (last axis, the NaN ones left out per size): the percentile ``Phi(confidence)`` of the
    paired bootstrap over the cases (one set of resamples for every candidate; seeded, so
    deterministic). A normal bound (mean + ``confidence`` standard errors) is symmetric, so
    one case where the reference fails badly widened it and rejected a candidate that was
    better on most days; the bootstrap follows the skew of the differences either way (an
    unfavourable outlier still raises the bound)."""
    from scipy.stats import norm

    if int(n_boot) < 1:
        raise ModelError(f"n_boot must be a positive number of bootstrap draws, got {n_boot!r}")
    level = float(norm.cdf(float(confidence)))
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    out = np.full(E.shape[:2], np.nan)
    for s in range(E.shape[1]):
        keep = np.isfinite(E[:, s]).all(axis=0)
        Es = E[:, s, keep]
        n = Es.shape[1]
        if n < 2:
            continue
        step = max(1, min(int(n_boot), BOOTSTRAP_BLOCK // n))  # draws per block of counts
        means = np.concatenate([  # (candidate, draw)
            Es @ rng.multinomial(n, np.full(n, 1.0 / n), size=min(step, int(n_boot) - b)).T
            for b in range(0, int(n_boot), step)], axis=1) / n
        with np.errstate(divide="ignore", invalid="ignore"):
            out[:, s] = np.quantile(means / means[0] - 1.0, level, axis=1)
    out[0] = 0.0
    return out


def shared_cases(E: np.ndarray) -> np.ndarray:
    """``E (n_candidates, ...)`` with a case NaN for every candidate where any candidate is NaN,
    so that every comparison reads the same cases."""
    return np.where(np.isfinite(E).all(axis=0), E, np.nan)


def paired_difference(E: np.ndarray, candidate: int | slice, reference: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error over the cases (last axis) of ``E[candidate] - E[reference]``,
    the paired differences of :func:`shared_cases`' errors: ``(..., n_sizes)`` each."""
    D = E[candidate] - E[reference]
    n = np.isfinite(D).sum(axis=-1)
    return np.nanmean(D, axis=-1), np.nanstd(D, axis=-1, ddof=1) / np.sqrt(n)
