"""Scores of a plan on held-out snapshots: exact fold-in errors from sufficient statistics,
and the coverage of the predictive intervals (the arithmetic of :mod:`lrm_cvx.evaluation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .belief.posterior import (
    LatentPosterior,
    ObservationModel,
    check_cells,
    pattern_groups,
    predict_many,
)
from .errors import ModelError
from .glrm.calibrated import interval_coverage

__all__ = ["SnapshotStatistics", "foldin_mse", "plain_prior", "complete_mse", "model_mse",
           "COVERAGE_CELLS", "coverage_subset", "model_coverage", "model_scores"]


@dataclass(frozen=True)
class SnapshotStatistics:
    """Sufficient statistics of the test snapshots for exact fold-in errors in data units.

    With ``z = (values - offset) / scale`` (fit units) and weights ``w = scale^2`` on each
    snapshot's observed cells ``O`` (1 without a scale), ``gram = sum_O w y y^T`` ``(n_test, k,
    k)``, ``cross = sum_O w z y`` ``(n_test, k)``, ``sq = sum_O w z^2`` ``(n_test,)`` and ``count
    = |O|``, so that the squared error of the map ``offset + scale * Y^T x`` over ``O`` is
    ``x^T gram x - 2 cross^T x + sq`` (:meth:`mse_many`). ``values`` ``(n_test, L)`` stay in data
    units (float32 with NaN); the statistics are float64.
    """

    values: np.ndarray
    gram: np.ndarray
    cross: np.ndarray
    sq: np.ndarray
    count: np.ndarray

    @classmethod
    def from_values(cls, Y: np.ndarray, values: np.ndarray, offset: np.ndarray | None = None,
                    scale: np.ndarray | None = None) -> SnapshotStatistics:
        """Statistics of ``values (n_test, L)`` (NaN = not observed) for factors ``Y (k, L)``
        and the model's ``offset``/``scale`` (``(L,)`` or None)."""
        observed = np.isfinite(values)
        z = values.astype(np.float64)
        if offset is not None:
            z -= offset
        if scale is not None:
            z /= scale
        d = np.where(observed, z, 0.0)
        del z
        w = observed.astype(np.float64)
        if scale is not None:
            w *= np.square(scale)
        gram = np.einsum("kl,jl,tl->tkj", Y, Y, w, optimize=True)
        dw = d * w
        return cls(values=values, gram=gram, cross=dw @ Y.T, sq=np.einsum("tl,tl->t", dw, d),
                   count=observed.sum(axis=1))

    def mse_many(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Mean squared errors (data units) of snapshots ``rows`` (``(m,)``) mapped from latent
        vectors ``x (m, k)`` over their observed cells (NaN for NaN ``x`` or no cell)."""
        G, b = self.gram[rows], self.cross[rows]
        err = (np.einsum("tk,tkj,tj->t", x, G, x) - 2.0 * np.einsum("tk,tk->t", b, x)
               + self.sq[rows])
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count[rows] > 0, np.maximum(err, 0.0) / self.count[rows],
                            np.nan)


def plain_prior(Y: np.ndarray, ridge: float) -> LatentPosterior:
    """The paper's fold-in on bare factors: flat, or the ridge prior (unit noise)."""
    return LatentPosterior.prior(ObservationModel(Y), "ridge", ridge)


def foldin_mse(Y: np.ndarray, stats: SnapshotStatistics, cells: np.ndarray, ridge: float = 0.0,
               min_observations: int = 1, *, prior: LatentPosterior | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Fold each test snapshot in from its values at ``cells``; MSE over its observed cells.

    The fold-in is ``prior.update(cells, values)`` (default: the paper's least squares with
    ``ridge`` on ``Y``; pass a model's ``latent_prior(...)`` for its offset, scale, noise and
    prior, with ``stats`` built with the same offset and scale). ``O(n k^2 + k^2)`` per
    snapshot: the error comes from ``stats``, never from a map. Returns ``(mse, n_obs)``, each
    ``(n_test,)``; ``mse`` is NaN where a snapshot has fewer than ``max(min_observations, 1)``
    observations at ``cells`` or they do not determine ``x`` (flat prior, rank-deficient).
    """
    if prior is None:
        prior = plain_prior(Y, ridge)
    elif ridge:
        raise ModelError("give ridge through the prior (latent_prior(ridge=...)), not both")
    if prior.obs_model.is_spatial:
        raise ModelError("foldin_mse is the trend-only fold-in; a spatial prior needs full maps")
    cells = check_cells(cells, stats.values.shape[1])
    vals = stats.values[:, cells].astype(np.float64)  # (n_test, n)
    n_obs = np.isfinite(vals).sum(axis=1)
    mse = np.full(len(n_obs), np.nan)
    ok = np.flatnonzero(n_obs >= max(min_observations, 1))
    if ok.size:
        means, _ = prior.batch_means(cells, vals[ok])  # every snapshot's fold-in at once
        mse[ok] = stats.mse_many(ok, means)
    return mse, n_obs


def complete_mse(stats: SnapshotStatistics, prior: LatentPosterior) -> np.ndarray:
    """The "complete" condition: fold-in from every observed cell of each snapshot (data
    units; NaN where that does not determine ``x``)."""
    allc = np.arange(stats.values.shape[1])
    means, _ = prior.batch_means(allc, stats.values)
    return stats.mse_many(np.arange(len(stats.count)), means)


def model_mse(prior: LatentPosterior, stats: SnapshotStatistics, cells: np.ndarray,
               min_observations: int) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`foldin_mse` for a model's belief (``GLRM.latent_prior``): the exact
    statistics path without the spatial residual; with it, full predicted maps (kriging) and
    the MSE over each snapshot's observed cells, ``O(n_test L k)`` (plus kriging) per plan."""
    mse, n_obs, _ = model_scores(prior, stats.values, cells, min_observations, stats=stats)
    return mse, n_obs


def model_scores(prior: LatentPosterior, values: np.ndarray, cells: np.ndarray,
                 min_observations: int, *, stats: SnapshotStatistics | None = None,
                 subsets: list[np.ndarray] | None = None
                 ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray | None]:
    """``(mse, n_obs, coverage)`` of one plan's ``cells`` on the test snapshots ``values
    (n_test, L)``: with ``stats`` (of ``values``) :func:`model_mse`'s errors, with ``subsets``
    (:func:`coverage_subset`) :func:`model_coverage`'s (each None when not asked), from one
    fold-in per snapshot. The snapshots that observe the same cells of the plan share one
    kriging system (:func:`~lrm_cvx.belief.posterior.predict_many`)."""
    cells = check_cells(cells, values.shape[1])
    vals = values[:, cells].astype(np.float64)
    obs = np.isfinite(vals)
    n_obs = obs.sum(axis=1)
    spatial = prior.obs_model.is_spatial
    mse = None
    if stats is not None and spatial:
        mse = np.full(values.shape[0], np.nan)
    elif stats is not None:
        mse, _ = foldin_mse(prior.obs_model.Y, stats, cells, 0.0, min_observations, prior=prior)
    cov = None if subsets is None else np.full((values.shape[0], 2), np.nan)
    if not (spatial and stats is not None) and cov is None:
        return mse, n_obs, cov
    enough = np.flatnonzero(n_obs >= max(min_observations, 1))
    for group in pattern_groups(obs[enough]):
        ts = enough[group].tolist()
        posts = [prior.update(cells[obs[t]], vals[t, obs[t]]) for t in ts]
        keep = [i for i, p in enumerate(posts) if p.is_proper]
        if not keep:
            continue
        posts, ts = [posts[i] for i in keep], [ts[i] for i in keep]
        if spatial and stats is not None:
            pred, _ = predict_many(posts, std=False)
            for i, t in enumerate(ts):
                if stats.count[t] > 0:
                    mse[t] = float(np.nanmean((pred[i] - values[t]) ** 2))
        if cov is None:
            continue
        held = [np.setdiff1d(subsets[t], cells, assume_unique=True) for t in ts]
        union = np.unique(np.concatenate(held))
        if union.size == 0:
            continue
        mean, pstd = predict_many(posts, cells=union)
        for i, t in enumerate(ts):
            if held[i].size:
                at = np.searchsorted(union, held[i])
                cov[t] = interval_coverage(values[t, held[i]], mean[i, at], pstd[i, at],
                                           multipliers=posts[i].interval_multipliers())
    return mse, n_obs, cov


COVERAGE_CELLS = 4096  # held-out cells scored for coverage per snapshot (a fixed subset)


def coverage_subset(values: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Per test snapshot, at most ``COVERAGE_CELLS`` of its observed cells (sorted, a fixed
    seeded subset): the cells whose predictive interval ``evaluate`` scores."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(values.shape[0]):
        obs = np.flatnonzero(np.isfinite(values[t]))
        if obs.size > COVERAGE_CELLS:
            obs = np.sort(rng.choice(obs, size=COVERAGE_CELLS, replace=False))
        out.append(obs)
    return out


def model_coverage(prior: LatentPosterior, values: np.ndarray, subsets: list[np.ndarray],
                    cells: np.ndarray, min_observations: int) -> np.ndarray:
    """Coverage of the central 68 % / 95 % predictive intervals (``mean +- z *
    predictive_std``, calibrated when the model is: validation/calibration.py; ``z`` a conformal
    calibration's per-level threshold when it has one) over each test
    snapshot's held-out observed cells (its ``subsets`` entry minus the sampled ``cells``).
    Returns ``(n_test, 2)``, NaN where the snapshot has too few observations."""
    return model_scores(prior, values, cells, min_observations, subsets=subsets)[2]
