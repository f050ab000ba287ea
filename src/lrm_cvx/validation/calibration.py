"""Calibrated predictive uncertainty.

A fitted GLRM's predictive interval for a held-out cell is ``mean +- z * sqrt(s * (std^2 +
noise))``: ``std`` the posterior std of the latent value (trend + kriged residual), ``noise``
the variance of a new measurement (the spatial nugget with ``spatial=True``, else the noise
variance, in data units), and ``s`` a variance scale estimated here.

Training residuals under-state the error of a fold-in on a *new* snapshot (the factors were
fitted to the training snapshots), so ``s`` is estimated from cross-validated fold-in residuals
instead: the training snapshots are split into ``n_blocks`` interleaved folds (every
``n_blocks``-th snapshot; contiguous blocks leave out a whole period of a persistent record,
whose state the other blocks' prior has not seen, and over-state the error); for each fold the
model (same parameters, same region) is refitted on the other folds, and each held-out snapshot
of the fold (at most ``max_snapshots``) is folded in from route-like (spatially clustered) and
scattered sample sets of several sizes; the residuals at the snapshot's other observed cells,
standardized by the refitted model's own predictive std, are pooled. ``s`` is chosen so that the
pooled standardized residuals hit the nominal 68% and 95% quantiles of a standard normal (the
geometric mean of the two quantile ratios, squared): it targets the coverage that is reported,
and is 1 for data drawn exactly from the model. Scaling every variance component of the model
(prior covariance, noise, spatial covariance) by ``s`` leaves posterior means unchanged and
scales every posterior and predictive variance by ``s``, so ``s`` is applied to the variances
only.

The filter (``MonitorState``) uses the same scale unless a separate one is asked for
(``calibrate(..., temporal="ar1")``): then forward-chaining folds (the model refitted with its
dynamics on the snapshots before a block, the filter run through the block in time order, one
sample set per snapshot) give the filter's scale relative to the memoryless model's on the same
days and cells (``temporal_scale``). Measured on held-out campaigns the shared scale was the
better estimate (docs/monitoring.md).

The result is :class:`Calibration`, stored on the model as ``calibration_`` and saved with its
NetCDF file (attributes ``calibration_*``; the table of the choice of the residual's factor and
local power, ``Calibration.selection``, as variables ``calibration_selection_*``).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .._validation import as_generator
from ..errors import ModelError
from ..glrm.calibrated import (
    RESIDUAL_FACTORS,
    SCORE_GRID,
    Calibration,
    check_level,
    conformal_quantile,
    interval_coverage,
    predictive_std,
)
from .blending import blend_dynamics, dynamics_alpha, memoryless_cov
from .designs import ALL_KINDS, SET_KINDS
from .refits import clone_model, refit_carries, training_values, validation_view
from .search import (
    Best,
    ForwardBlocks,
    HeldOutCells,
    InterleavedBlocks,
    search,
    selection_table,
)

__all__ = ["calibrate", "cv_residuals", "CVResiduals", "Residual", "fit_scale", "Z68", "Z95",
           "fit_adaptive_scale", "DOF_GRID", "DISCOUNT_GRID", "LOCAL_POWERS", "conformal_scores",
           "calibrate_with", "fit_then_try_calibrate", "refit_dynamics"]

Z68 = 0.994457883209753   # two-sided 68% normal quantile: P(|z| < Z68) = 0.68
Z95 = 1.959963984540054   # two-sided 95%


def fit_scale(z: Any) -> float:
    """Variance scale ``s`` so ``z / sqrt(s)`` hits the 68% and 95% normal quantiles:
    ``s = (q68 / Z68) * (q95 / Z95)`` with ``q`` the empirical quantiles of ``|z|``."""
    z = np.abs(np.asarray(z, dtype=np.float64).ravel())
    z = z[np.isfinite(z)]
    if z.size < 20:
        raise ModelError(f"calibration needs at least 20 held-out residuals, got {z.size}")
    q68, q95 = np.quantile(z, [0.68, 0.95])
    s = float(q68 / Z68 * q95 / Z95)
    if not (np.isfinite(s) and s > 0):
        raise ModelError("calibration failed: the held-out residuals are all zero")
    return s


# ----------------------------------------------------------------------------- estimation
def _use_spatial(model: Any, spatial: bool | None) -> bool:
    if spatial is None:
        return getattr(model, "spatial_cov_", None) is not None
    return bool(spatial)


def _standardized(model: Any, values: np.ndarray, cells: np.ndarray, pred: np.ndarray,
                  latent_std: np.ndarray, spatial: bool, temporal: bool = False) -> np.ndarray:
    held = np.isfinite(values)
    held[cells] = False
    sd = predictive_std(model, latent_std, spatial, temporal)
    sd = sd[held] if np.ndim(sd) else np.full(int(held.sum()), float(sd))
    return (values[held] - pred[held]) / sd


class Residual(NamedTuple):
    """One fold-in's (or one filter day's) standardized held-out residuals and what they were
    standardized by: a row of :class:`CVResiduals`."""

    z: np.ndarray
    """Standardized residuals at the scored cells (uncalibrated predictive std)."""
    q: float
    """Innovation statistic of the samples (NaN for the filter's days)."""
    n_eff: float
    """Samples the innovation statistic counts (0 for the filter's days)."""
    t: int
    """The snapshot (index into the training snapshots)."""
    log_sd: float
    """Sum of the log predictive stds the residuals were divided by."""
    size: int
    """The design size."""
    n_samples: int
    """Samples that gave a value (fewer than ``size`` where the snapshot has gaps)."""
    spread: np.ndarray
    """The refit's ``residual_spread_`` at the scored cells (ones without one)."""
    rho: float
    """The factor of the refit's residual and noise variances (1: as validated)."""
    source: str
    """``"fold-in"`` (a held-out snapshot folded in), ``"filter"`` or ``"memoryless"`` (the
    filter and its memoryless twin through the same forward block on the same cells)."""


SOURCES = ("fold-in", "filter", "memoryless")


@dataclass(frozen=True)
class CVResiduals:
    """The result of :func:`cv_residuals`: one :class:`Residual` row per fold-in, per factor
    ``rho`` and per source, in the order they were made."""

    rows: tuple[Residual, ...]

    @property
    def rhos(self) -> tuple[float, ...]:
        """The factors ``rho`` present, in order."""
        return tuple(dict.fromkeys(r.rho for r in self.rows))

    def select(self, rho: float = 1.0, source: str | None = None) -> list[Residual]:
        """The rows of factor ``rho`` and ``source`` (None: the first source present)."""
        if source is None:
            source = self.rows[0].source if self.rows else "fold-in"
        if source not in SOURCES:
            raise ModelError(f"source must be one of {SOURCES}, got {source!r}")
        return [r for r in self.rows if r.rho == rho and r.source == source]

    def z(self, rho: float = 1.0, source: str | None = None) -> np.ndarray:
        """The concatenated standardized residuals of :meth:`select`."""
        rows = self.select(rho, source)
        return np.concatenate([r.z for r in rows]) if rows else np.empty(0)


def cv_residuals(model: Any, data: Any, *,
                 folds: str | InterleavedBlocks | ForwardBlocks = "interleaved",
                 sizes: Sequence[int] = (5, 15, 50), kinds: Sequence[str] = SET_KINDS,
                 max_snapshots: int = 3, prior: str = "empirical", spatial: bool | None = None,
                 temporal: str | None = None, seed: Any = 0,
                 residual_scales: Sequence[float] | None = None,
                 max_cells: int | None = None, local_power: float = 0.0) -> CVResiduals:
    """Standardized cross-validated fold-in residuals (see the module docstring).

    ``data`` ``(time, lat, lon)``: the snapshots ``model`` was fitted on (its region is used).
    ``max_snapshots`` held-out snapshots per block (evenly spaced) are folded in from one set
    of each size and kind. With ``temporal`` (``"ar1"``/``"seasonal"``), forward-chaining folds
    and the filter instead (:func:`lrm_cvx.monitor`), one set per snapshot (kinds and sizes
    cycled). The residuals are standardized by the *uncalibrated* predictive std of the
    refitted model. Returns one :class:`CVResiduals` table: a :class:`Residual` row per
    fold-in (``source="fold-in"``: its standardized residuals, the innovation statistic of its
    samples, :meth:`~lrm_cvx.belief.posterior.LatentPosterior.innovation`, the snapshot, the
    sum of the log predictive stds, its design size, the samples that gave a value and the
    refit's ``residual_spread_`` at the scored cells); with ``temporal`` a row per day for
    the filter (``source="filter"``) and one for the memoryless model through the same loop
    on the same cells (``"memoryless"``). ``residual_scales`` (memoryless): the same fold-ins
    (same cells) also with the refitted model's residual and noise variances multiplied by
    each ``rho`` (the rows' ``rho``; default 1 only).
    ``max_cells`` (memoryless): score at most that many of each fold-in's held-out cells (a
    seeded random subset; None: all), which bounds the kriging cost on large grids. ``folds``:
    the search's splitter, :class:`~.search.InterleavedBlocks` ``(n)`` (every ``n``-th snapshot,
    refitted on all the others) or :class:`~.search.ForwardBlocks` ``(n)`` (the contiguous
    blocks of the record's second half, each refitted on the snapshots before it: the fold-in
    of a *future* snapshot, as a test block after the training is; less training data per
    refit, so wider on stationary records); ``"interleaved"`` / ``"forward"`` are those with 8
    blocks. With ``temporal`` the blocks are always forward (the filter runs forward in time).
    ``local_power`` (with ``temporal``): the residuals divided by each refit's
    ``residual_spread_`` to that power (the calibration's locally weighted intervals).
    """
    from ..belief.posterior import model_prior

    model, data, _ = validation_view(model, data)  # a large region: a window of it
    region, V = training_values(model, data)
    T = V.shape[0]
    if isinstance(folds, str):
        if folds not in ("interleaved", "forward"):
            raise ModelError(f"folds must be 'interleaved' or 'forward', got {folds!r}")
        folds = ForwardBlocks(8) if folds == "forward" else InterleavedBlocks(8)
    if not isinstance(folds, InterleavedBlocks | ForwardBlocks):
        raise ModelError("folds must be 'interleaved', 'forward', InterleavedBlocks(n) or "
                         f"ForwardBlocks(n), got {folds!r}")
    forward = temporal is not None or isinstance(folds, ForwardBlocks)
    n_blocks = folds.n_blocks if isinstance(folds, ForwardBlocks) else folds.n_folds
    if not 2 <= int(n_blocks) <= T // 2:
        raise ModelError(f"n_blocks must be in [2, {T // 2}] for {T} snapshots, got {n_blocks}")
    for kind in kinds:
        if kind not in ALL_KINDS:
            raise ModelError(f"kinds must be among {ALL_KINDS}, got {kind!r}")
    sizes = [int(s) for s in sizes]
    if not sizes or min(sizes) < 1:
        raise ModelError(f"sizes must be positive integers, got {sizes}")
    spatial = _use_spatial(model, spatial)
    rng = as_generator(seed)
    # contiguous blocks, forward chaining from half the record on; or every n_blocks-th
    # snapshot held out, refitted on all the others
    folds = (ForwardBlocks(n_blocks) if forward else InterleavedBlocks(n_blocks)).split(T)
    holdout = HeldOutCells(region.n_cells if max_cells is None else int(max_cells))
    out: list[Residual] = []
    rank = int(model.rank_)
    offset = getattr(model, "offset_", None) is not None
    too_short = 0  # blocks whose refit could not carry the model's rank (a short record)
    finite = np.isfinite(V)  # (T, L): what each refit would see
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for train_idx, block in folds:
            if not refit_carries(finite[train_idx], rank, offset):
                too_short += 1
                continue
            has_t = "temporal" in model.get_params()
            # the filter's refits are fitted with AR(1) (no nested selection), then given the
            # model's kind and blend (refit_dynamics)
            sub = clone_model(model, **({"temporal": "ar1" if temporal is not None else None}
                                        if has_t else {}))
            sub.fit(data.isel(time=train_idx), region=region)
            sub.calibration_ = None  # the validated inflation is the model's, as the dynamics
            sub.residual_inflation_ = float(getattr(model, "residual_inflation_", 1.0))
            if temporal is not None:
                sub.dynamics_ = refit_dynamics(model, sub, temporal,
                                               data["time"].values[train_idx])
                if sub.dynamics_ is None:  # this block's history cannot carry the kind
                    continue
                out.extend(_filter_residuals(sub, data.isel(time=block), V[block], block, sizes,
                                             kinds, spatial, rng, max_cells, local_power))
                continue
            spread = _spread(sub, region.n_cells)
            pick = block[np.unique(np.linspace(0, block.size - 1,
                                               min(block.size, max_snapshots)).round()
                                   .astype(int))]
            base = model_prior(sub, prior, spatial=spatial)
            rhos = [1.0] if residual_scales is None else [float(r) for r in residual_scales]
            bases = {rho: base if rho == 1.0 else _rescaled(base, rho) for rho in rhos}
            for t in pick:
                observed = np.isfinite(V[t])
                for size in sizes:
                    for kind in kinds:
                        # the design's cells (gaps give no value) and those scored
                        cells, hidx = holdout.split(region, observed, size, kind, rng)
                        recs = []
                        for rho, b in bases.items():
                            post = b.update(cells, V[t, cells])
                            if not post.is_proper or hidx.size == 0:
                                break
                            mean, _, pstd = post.predict_all(cells=hidx)
                            q, n_eff = b.innovation(cells, V[t, cells])
                            recs.append(Residual((V[t, hidx] - mean) / pstd, q, n_eff, int(t),
                                                 float(np.sum(np.log(pstd))), size,
                                                 post.n_samples, spread[hidx], rho, "fold-in"))
                        if len(recs) == len(bases):
                            out.extend(recs)
    if not out:
        if too_short:
            raise ModelError(f"calibration cannot refit rank {rank} on the snapshots before "
                             f"{too_short} of its {len(folds)} blocks (a record of {T} is too "
                             "short for them); pass fewer n_blocks or a lower rank")
        raise ModelError("calibration produced no held-out residuals")
    if temporal is None:  # rows per fold-in in the order of the factors
        rhos = [float(r) for r in (residual_scales or (1.0,))]
        out = [r for rho in rhos for r in out if r.rho == rho]
    return CVResiduals(tuple(out))


def _spread(model: Any, n_cells: int) -> np.ndarray:
    """``model.residual_spread_`` ``(L,)``, ones when it has none."""
    spread = getattr(model, "residual_spread_", None)
    return np.ones(n_cells) if spread is None else np.asarray(spread, dtype=np.float64)


def _powered(records: Sequence[Residual], power: float) -> list[Residual]:
    """:func:`cv_residuals` rows (:class:`Residual`) as the intervals of ``local_power =
    power`` see them: each residual divided by its cell's spread to ``power``, and the log
    predictive stds (the standardization's Jacobian) raised by as much."""
    if power == 0.0:
        return list(records)
    out = []
    for r in records:
        f = np.asarray(r.spread, dtype=np.float64) ** power
        out.append(r._replace(z=r.z / f, log_sd=r.log_sd + float(np.sum(np.log(f)))))
    return out


def _rescaled(prior: Any, rho: float) -> Any:
    """``prior`` with its observation model's residual and noise variances times ``rho``."""
    from dataclasses import replace

    from ..belief.posterior import LatentPosterior

    obs = prior.obs_model
    nv = obs.noise_var * rho if np.ndim(obs.noise_var) else float(obs.noise_var) * rho
    cov = obs.spatial_cov
    if cov is not None:
        cov = replace(cov, sill=cov.sill * rho, nugget=cov.nugget * rho)
    new = replace(obs, noise_var=nv, spatial_cov=cov, ref_var=None)
    return LatentPosterior(new, prior.precision, prior.shift, prior.base_precision,
                           prior.base_shift)


LOCAL_POWERS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""The powers of a cell's ``residual_spread_`` a calibration validates for its intervals
(``Calibration.local_power``)."""


DOF_GRID = (1.0, 4.0, 16.0, 64.0, 256.0, 1024.0)
DISCOUNT_GRID = (0.0, 0.5, 0.8, 0.95, 1.0)


def _innovation_evidence(records: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray, Any]:
    """``(q, n, evidence)``: each record's innovation statistic and count (0 where it has
    none) and ``evidence(discount) -> (E_q, E_n)``, the mean ``q`` and ``n`` per earlier
    snapshot ``t' < t`` weighted by ``discount^(t - t')`` (0 with ``discount`` 0)."""
    q = np.array([float(r[1]) for r in records])
    n = np.array([float(r[2]) for r in records])
    t = np.array([int(r[3]) if len(r) > 3 else 0 for r in records])
    ok = np.isfinite(q) & (n > 0)
    q, n = np.where(ok, q, 0.0), np.where(ok, n, 0.0)
    snaps = np.unique(t)
    qbar = np.array([q[t == u].mean() for u in snaps])
    nbar = np.array([n[t == u].mean() for u in snaps])
    gap = t[:, None] - snaps[None, :]  # (records, snapshots): steps back to each earlier one

    def evidence(disc: float) -> tuple[np.ndarray, np.ndarray]:
        if disc == 0.0:
            return np.zeros(len(records)), np.zeros(len(records))
        w = np.where(gap > 0, disc ** np.maximum(gap, 0).astype(np.float64), 0.0)
        return w @ qbar, w @ nbar

    return q, n, evidence


def fit_adaptive_scale(records: Sequence[tuple], dofs: Sequence[float] = DOF_GRID,
                       discounts: Sequence[float] = DISCOUNT_GRID
                       ) -> tuple[float, float | None, float, float]:
    """``(scale, dof, discount, gain)``: the adaptive scale of :class:`Calibration` from
    cross-validated :class:`Residual` rows ``(z, q, n_eff, t, ...)`` of :func:`cv_residuals`.

    A record's variance scale is ``s_i = (dof scale + E_q + q_i) / (dof + E_n + n_i)``, with
    ``E_q``, ``E_n`` the evidence of the records of *earlier* snapshots ``t' < t`` (their mean
    ``q`` and ``n`` per snapshot, weighted by ``discount^(t - t')``; what ``MonitorState``
    carries from day to day). For each ``(dof, discount)`` of the grids (and the fixed scale,
    ``dof = None``) the base ``scale`` solves the quantile rule of :func:`fit_scale` for the
    residuals standardized by ``s_i`` (a fixed point); the pair with the highest mean Gaussian
    log-likelihood of the held-out residuals under ``N(0, s_i)`` wins. ``gain`` is its
    log-likelihood per residual minus the fixed scale's (>= 0)."""
    z = [np.asarray(r[0], dtype=np.float64) for r in records]
    q, n, evidence = _innovation_evidence(records)
    sizes = np.array([zi.size for zi in z])
    zall = np.concatenate(z)

    def scales(s0: float, dof: float | None, eq: np.ndarray, en: np.ndarray) -> np.ndarray:
        if dof is None:
            return np.full(len(z), s0)
        return (dof * s0 + eq + q) / (dof + en + n)

    def loglik(s_i: np.ndarray) -> float:
        si = np.repeat(s_i, sizes)
        return float(np.mean(-0.5 * np.log(si) - 0.5 * zall * zall / si))

    best = None
    base_ll = None
    zero = np.zeros(len(z))
    for dof in (None, *dofs):
        for disc in ((0.0,) if dof is None else discounts):
            eq, en = evidence(float(disc)) if dof is not None else (zero, zero)
            s0 = fit_scale(zall)
            for _ in range(30):  # fixed point of the quantile rule
                f = fit_scale(zall / np.sqrt(np.repeat(scales(s0, dof, eq, en), sizes)))
                s0 *= f
                if abs(f - 1.0) < 1e-4 or dof is None:
                    break
            ll = loglik(scales(s0, dof, eq, en))
            if dof is None:
                base_ll = ll
            if best is None or ll > best[3]:
                best = (s0, dof, float(disc), ll)
    return float(best[0]), best[1], best[2], float(best[3] - base_ll)


def _record_scales(records: Sequence[tuple], scale: float, dof: float | None,
                   discount: float) -> np.ndarray:
    """The variance scale ``s_i`` of each record under ``(scale, dof, discount)``
    (:func:`fit_adaptive_scale`'s model; ``scale`` for all when ``dof`` is None)."""
    if dof is None:
        return np.full(len(records), float(scale))
    q, n, evidence = _innovation_evidence(records)
    eq, en = evidence(float(discount))
    return (dof * scale + eq + q) / (dof + en + n)


def _loglik(records: Sequence[tuple], scale: float, dof: float | None, discount: float
            ) -> float:
    """Mean Gaussian log-likelihood of the records' residuals under the scales that
    ``(scale, dof, discount)`` give them (:func:`fit_adaptive_scale`'s model)."""
    z = [np.asarray(r[0], dtype=np.float64) for r in records]
    sizes = np.array([zi.size for zi in z])
    zall = np.concatenate(z)
    si = np.repeat(_record_scales(records, scale, dof, discount), sizes)
    # the density of the raw residuals (data units): the standardization's Jacobian counts,
    # so models with different predictive stds (residual scales) compare on the same footing
    logsd = sum(float(r[4]) for r in records) if all(len(r) > 4 for r in records) else 0.0
    return float(np.mean(-0.5 * np.log(si) - 0.5 * zall * zall / si) - logsd / zall.size)


def conformal_scores(records: Sequence[tuple], scale: float, dof: float | None,
                     discount: float) -> np.ndarray:
    """Non-conformity scores ``|y - mean| / predictive_std`` of cross-validated records (the
    standardized residuals of :func:`cv_residuals`' rows), standardized by the
    *calibrated* predictive std (each record's variance scale ``s_i``): what a calibrated
    model's intervals are measured in."""
    z = [np.asarray(r[0], dtype=np.float64) for r in records]
    sizes = np.array([zi.size for zi in z])
    si = np.repeat(_record_scales(records, scale, dof, discount), sizes)
    return np.abs(np.concatenate(z)) / np.sqrt(si)


def refit_dynamics(model: Any, sub: Any, kind: str, times: Any) -> Any:
    """Dynamics of ``kind`` for ``sub`` (a refit of ``model`` on its first snapshots, fitted
    with ``temporal="ar1"``; ``times`` its time coordinate) made as ``model``'s own were: blended
    by the ``temporal="auto"`` choice's ``alpha`` or ``select_dynamics``'
    (:func:`~.blending.dynamics_alpha`). None when ``sub``'s history cannot carry the kind (a
    season on less than two years)."""
    from ..glrm.dynamics import kind_dynamics

    base = kind_dynamics(kind, sub, times)
    if base is None:
        return None
    sel = getattr(model, "selection_", None)
    if sel is not None and sel.attrs.get("choice_kind") == kind:
        alpha = float(sel.attrs["choice_alpha"])
    else:
        alpha = dynamics_alpha(model)
    return base if alpha is None else blend_dynamics(base, alpha, memoryless_cov(sub, base))


def _filter_residuals(sub: Any, block_data: Any, Vb: np.ndarray, block: np.ndarray,
                      sizes: list[int], kinds: Sequence[str], spatial: bool,
                      rng: np.random.Generator, max_cells: int | None = None,
                      local_power: float = 0.0) -> list[Residual]:
    """Standardized residuals of the filter run through one block (snapshots ``block``) in
    time order, and of the memoryless model through the same loop on the same cells: a
    ``"filter"`` and a ``"memoryless"`` :class:`Residual` per day (at most ``max_cells``
    random held-out cells per day; divided by ``sub``'s ``residual_spread_`` to
    ``local_power``)."""
    region = sub.region_
    spread = _spread(sub, region.n_cells)
    factor = spread ** float(local_power)
    from ..belief.filter import LatentFilter

    states = (LatentFilter.from_model(sub, spatial=spatial),
              LatentFilter.from_model(sub, memoryless=True, spatial=spatial))
    times = block_data["time"].values
    combos = [(s, k) for s in sizes for k in kinds]
    out = []
    for i, t in enumerate(times):
        size, kind = combos[i % len(combos)]
        # the design's cells (gaps give no value) and those scored
        cells, hidx = HeldOutCells(region.n_cells if max_cells is None else int(max_cells)
                                   ).split(region, np.isfinite(Vb[i]), size, kind, rng)
        for state, source in zip(states, ("filter", "memoryless"), strict=True):
            state.assimilate((cells, Vb[i, cells]), time=t)
            mean, _, pstd = state.posterior.predict_all(cells=hidx)
            sd = pstd * factor[hidx]
            out.append(Residual((Vb[i, hidx] - mean) / sd, float("nan"), 0.0, int(block[i]),
                                float(np.sum(np.log(sd))), size,
                                int(np.isfinite(Vb[i, cells]).sum()), spread[hidx], 1.0,
                                source))
    return out


def _size_quantiles(records: Sequence[tuple], scores: np.ndarray, sizes: Sequence[int],
                    levels: Sequence[float], pooled: np.ndarray) -> dict[str, tuple]:
    """The per-size fields of :class:`Calibration`: ``size_quantiles``, the ``(len(sizes),
    len(levels))`` conformal thresholds of each design size's own scores, flattened
    (``scores``: the records' concatenated, in order; a size without scores takes the pooled
    thresholds), and ``size_samples``, the mean number of samples that gave a value in that
    size's fold-ins (its size without one)."""
    size_of = np.array([int(r[5]) for r in records])
    n_of = np.array([float(r[6]) for r in records])
    of_size = np.repeat(size_of, [np.size(r[0]) for r in records])
    out = np.empty((len(sizes), len(levels)))
    n_mean = np.empty(len(sizes))
    for i, size in enumerate(sizes):
        own = scores[of_size == int(size)]
        out[i] = np.atleast_1d(conformal_quantile(own, levels)) if own.size else pooled
        n_mean[i] = n_of[size_of == int(size)].mean() if own.size else float(size)
    return {"size_quantiles": tuple(out.ravel()), "size_samples": tuple(n_mean)}


def _choice_table(decision: Any, labels: list[str], candidates: dict[str, tuple],
                  fits: dict[str, tuple], n_residuals: int) -> Any:
    """The table of :func:`calibrate`'s choice (``Calibration.selection``): the search's
    over ``candidate`` (coordinates ``residual_scale`` and ``local_power``) and one size (0:
    every design size pooled), the mean log-likelihood in ``mse``, the likelihood ratio to
    the first candidate per residual in ``ratio`` and each candidate's fitted ``scale``."""
    ds = selection_table(
        decision, labels, [0],
        what="mean Gaussian log-likelihood of the held-out residuals (data units; higher is "
             "better)",
        coords={"residual_scale": ("candidate", [float(candidates[lab][0]) for lab in labels]),
                "local_power": ("candidate", [float(candidates[lab][1]) for lab in labels])},
        data_vars={"scale": (("candidate",), [float(fits[lab][0]) for lab in labels])},
        n_residuals=int(n_residuals))
    ds["ratio"].attrs["long_name"] = f"likelihood ratio to {labels[0]!r} per residual"
    ds["scale"].attrs["long_name"] = "the variance scale fitted to the candidate's residuals"
    return ds


def calibrate_with(model: Any, data: Any, calibration: Any) -> Calibration:
    """:func:`calibrate` as ``GLRM(calibration=...)`` asks (``calibration``: a method name or a
    dict of its keywords; the seed is the model's ``random_state``)."""
    kw = {"method": calibration} if isinstance(calibration, str) else dict(calibration)
    return calibrate(model, data, **{"seed": model.random_state, **kw})


def fit_then_try_calibrate(model: Any, data: Any) -> str | None:
    """Fit the unfitted ``model`` on ``data``, then run its ``calibration`` where it can: None
    on success (or without one), else the reason it cannot run on ``data`` (e.g. a record too
    short for its refits; the model is kept, uncalibrated, its ``calibration`` None). For a
    calibration that is a default the user did not ask for: the caller notes the reason
    instead of failing."""
    from ..errors import LrmError

    cal = model.calibration
    model.set_params(calibration=None).fit(data)
    if cal is None:
        return None
    try:
        calibrate_with(model, data, cal)
    except LrmError as err:
        return str(err).split(";")[0]
    model.calibration = cal
    return None


def calibrate(model: Any, data: Any, *, n_blocks: int | None = None,
              sizes: Sequence[int] = (5, 15, 50),
              kinds: Sequence[str] = ALL_KINDS, max_snapshots: int = 3,
              temporal: str | None | bool = None, adaptive: bool = True,
              residual: bool = True, local: bool = True, method: str = "gaussian",
              levels: Sequence[float] = (0.68, 0.95), max_cells: int | None = None,
              folds: str | None = None, seed: Any = 0) -> Calibration:
    """Estimate the model's variance scale from cross-validated fold-in residuals on its
    training snapshots ``data`` and store it as ``model.calibration_`` (returned).

    ``method="conformal"``: in addition, split conformal prediction on the same
    cross-validated, design-matched fold-ins (route-like, scattered and transect-like sample
    sets of each size; every residual from a model refitted without its snapshot): the
    scores ``|y - mean| / predictive_std`` (calibrated std) give each nominal level of
    ``levels`` its own half-width, the ``ceil((n + 1) level)``-th smallest score
    (:func:`~lrm_cvx.glrm.calibrated.conformal_quantile`; ``Calibration.quantiles``), and a
    table of score quantiles serves other levels and the online ACI of ``MonitorState``. The
    adaptive scale then carries no evidence between snapshots (``discount`` 0), so a fold-in's
    predictive std is standardized as in the calibration (the filter adapts online instead:
    ``MonitorState.adaptive_conformal``). One
    variance scale cannot hit both the 68 % and the 95 % quantile when the residuals are
    heavier-tailed than a normal (it targets their geometric mean); the per-level thresholds
    do, with coverage ``>= level`` for scores exchangeable with the test's. Each design size
    of ``sizes`` also gets its own thresholds from its fold-ins alone
    (``Calibration.size_quantiles``, placed at the mean number of samples that gave a value,
    ``size_samples``): a belief holding ``n`` samples takes them interpolated in ``log n``
    (clamped to their range), since a standardized error can shrink as the
    samples grow denser (the 6-hourly storms of ``bench_generalization.py``); the filter's are
    the memoryless ones per size times its ratio below. ``levels``: each in (0, 1).
    Intervals: ``LatentPosterior.interval(level)`` / ``interval_coverage``;
    ``predictive_std`` itself keeps the Gaussian scale. ``max_cells``, ``folds``: see
    :func:`cv_residuals`; ``folds=None`` is ``"forward"`` for the conformal
    method (the fold-in of a snapshot *after* its refit's training, as a test block after the
    training is: on the two 6-hourly storm records of ``bench_generalization.py`` the
    interleaved folds under-stated the next block's error and covered 0.78 / 0.83 at 95 %,
    forward-chained 0.97 / 0.96) and ``"interleaved"`` for the Gaussian one (as measured in
    docs/monitoring.md).

    ``adaptive`` (default): also estimate a per-snapshot scale (:func:`fit_adaptive_scale`,
    ``Calibration.dof``; None when the fixed scale fits the held-out residuals best): each
    snapshot's predictive variances are then rescaled by how surprising its own samples were
    under the prior (the conjugate update of the scale by the standardized innovations), so a
    calm period gets narrower intervals and a stormy one wider ones, memoryless or filtered.
    ``residual`` (default): also re-estimate the residual and noise variances by a factor
    ``Calibration.residual_scale`` among the one grid of the factor,
    :data:`~lrm_cvx.glrm.calibrated.RESIDUAL_FACTORS`, on top of the model's validated
    ``residual_inflation_`` (the same cross-validated
    fold-ins redone with each; the factor whose scaled residuals have the highest Gaussian
    log-likelihood *of the raw residuals* wins): the fitted nugget and sill come from training
    residuals, which
    under-state a new snapshot's.
    ``local`` (default; a model with a ``residual_spread_``: a spatial residual of one
    stationary amplitude): also choose ``Calibration.local_power`` among
    :data:`LOCAL_POWERS` on the same log-likelihood, jointly with the residual's factor. Each
    cell's predictive std is then its spread to that power times the stationary one, so cells
    whose residual varies more get wider intervals and calm cells narrower ones (locally
    weighted conformal prediction, Lei et al. 2018). The maps, plans and the pooled coverage
    stay as they were; what changes is which cells the intervals cover (docs/monitoring.md).
    The factor and the power are chosen by the one search
    (:func:`~lrm_cvx.validation.search.search`: one split, the pooled fold-ins; the
    :class:`~lrm_cvx.validation.search.Best` log-likelihood); its table is
    ``Calibration.selection`` (saved with the model file).

    The filter (``MonitorState``) uses the same scale by default: measured on held-out
    campaigns (docs/monitoring.md) that calibrates it as well as the memoryless fold-in, while a
    separate forward-chaining estimate (``temporal="auto"``: when the model has dynamics;
    ``"ar1"``/``"seasonal"``: always) trains on less data and was too noisy to be better.
    With ``temporal`` a conformal calibration also gives the filter its own thresholds
    (``Calibration.temporal_quantiles``, used by the filter's intervals through
    ``Calibration.for_filter``): the memoryless thresholds times the filter's score quantile
    relative to the memoryless model's on the same forward-chained days and cells (each refit
    given the model's temporal kind and blend, :func:`refit_dynamics`). The recommended
    calibration asks for them (``RECOMMENDED["calibration"]["temporal"] = "auto"``): rolling
    origin under the ``temporal="auto"`` filter on the six records of
    ``bench_generalization.py`` (``--coverage --temporal auto``, docs/benchmarks.md) they met
    the coverage targets where the shared ones missed storm SLP's. ``"auto"`` on a record
    whose forward blocks cannot carry the model's kind (a season on a short record) keeps the
    memoryless calibration; a kind named explicitly raises.
    Costs ``n_blocks`` refits plus ``n_blocks * max_snapshots * len(sizes) * len(kinds)``
    fold-ins (and ``n_blocks // 2`` refits more with ``temporal``); on a region of more than
    ``refits.VALIDATION_MAX_CELLS`` cells all of them read one window of it
    (:func:`~lrm_cvx.validation.refits.validation_view`). ``n_blocks`` (None): 8,
    fewer on a short record (half its snapshots, at least 2).
    """
    if method not in ("gaussian", "conformal"):
        raise ModelError(f"method must be 'gaussian' or 'conformal', got {method!r}")
    if folds is None:
        folds = "forward" if method == "conformal" else "interleaved"
    levels = tuple(check_level(lv, "levels") for lv in np.atleast_1d(levels))
    if method == "conformal" and not levels:
        raise ModelError("levels must hold at least one level in (0, 1)")
    if n_blocks is None:  # 8 folds, fewer on a short record (each fold keeps 2 snapshots)
        n_snapshots = np.shape(data)[0] if np.ndim(data) else 0  # cv_residuals checks data
        n_blocks = max(2, min(8, n_snapshots // 2))
    if folds not in ("interleaved", "forward"):
        raise ModelError(f"folds must be 'interleaved' or 'forward', got {folds!r}")
    splitter = (ForwardBlocks if folds == "forward" else InterleavedBlocks)(n_blocks)
    kw = dict(sizes=sizes, kinds=kinds, max_snapshots=max_snapshots)
    rhos = RESIDUAL_FACTORS if residual else (1.0,)
    conformal_fit = method == "conformal"
    residuals = cv_residuals(model, data, seed=seed, residual_scales=rhos,
                             max_cells=max_cells, folds=splitter, **kw)
    by_rho = {rho: residuals.select(rho) for rho in residuals.rhos}
    powers = LOCAL_POWERS if local and getattr(model, "residual_spread_", None) is not None \
        else (0.0,)
    # the residual's factor jointly with the local power: a specification of the one search
    # (one split, the pooled cross-validated fold-ins; the highest log-likelihood wins)
    candidates = {f"x{rho:g} power {power:g}": (rho, power) for rho in by_rho
                  for power in powers}
    fits: dict[str, tuple] = {}

    def loglik(split: CVResiduals) -> dict[str, np.ndarray]:
        """The mean log-likelihood ``(1, 1)`` of each candidate's scaled residuals (its
        scale fitted to them, kept in ``fits``)."""
        out = {}
        for label, (rho, power) in candidates.items():
            records = _powered(split.select(rho), power)
            if adaptive:
                # conformal: no evidence carried between snapshots (discount 0), so the scores
                # are standardized exactly as a memoryless fold-in's predictive std
                fits[label] = fit_adaptive_scale(records, discounts=(0.0,) if conformal_fit
                                                 else DISCOUNT_GRID)
            else:
                fits[label] = (fit_scale(np.concatenate([r[0] for r in records])), None, 0.0,
                               0.0)
            out[label] = np.array([[_loglik(records, *fits[label][:3])]])
        return out

    labels, _, decision = search(loglik, [residuals], Best(log_likelihood=True))
    chosen_label = labels[decision.choice]
    rho, power = candidates[chosen_label]
    scale, dof, discount, gain = fits[chosen_label]
    conformal: dict[str, Any] = {}
    if method == "conformal":
        chosen = _powered(by_rho[rho], power)
        scores = conformal_scores(chosen, scale, dof, discount)
        pooled = np.atleast_1d(conformal_quantile(scores, levels))
        conformal = dict(method="conformal", levels=levels, quantiles=tuple(pooled),
                         score_table=tuple(np.quantile(scores, SCORE_GRID)),
                         **_size_quantiles(chosen, scores, sizes, levels, pooled))
    z = np.concatenate([r[0] for r in by_rho[1.0]])
    raw = interval_coverage(z, 0.0, 1.0)
    auto = temporal == "auto"
    if auto:
        dyn = getattr(model, "dynamics_", None)
        temporal = None if dyn is None else dyn.kind
    elif temporal is False:
        temporal = None
    t_scale, t_raw = None, np.full(2, np.nan)
    t_conformal: dict[str, Any] = {}
    zt = zm = None
    if temporal is not None:
        # forward chaining trains on less data than the final model: take from it only the
        # filter's scale *relative* to the memoryless model's on the same days and cells
        try:
            twin = cv_residuals(model, data, seed=seed, temporal=temporal,
                                max_cells=max_cells, local_power=power,
                                folds=ForwardBlocks(n_blocks), **kw)
            zt, zm = twin.z(source="filter"), twin.z(source="memoryless")
        except ModelError:  # no forward block's history carries the kind (a short record)
            if not auto:  # asked for by name: say so; "auto": the memoryless calibration
                raise
    if zt is not None:
        t_scale = scale * fit_scale(zt) / fit_scale(zm)
        t_raw = interval_coverage(zt, 0.0, 1.0)
        if method == "conformal":  # and its thresholds relative to the memoryless ones, in
            # units of the filter's calibrated std (sqrt(t_scale) instead of sqrt(scale))
            at, am = np.abs(zt[np.isfinite(zt)]), np.abs(zm[np.isfinite(zm)])
            unit = np.sqrt(scale / t_scale)

            def ratio(p: Any) -> np.ndarray:
                return unit * np.quantile(at, p) / np.quantile(am, p)

            per_size = np.reshape(conformal["size_quantiles"], (len(sizes), len(levels)))
            t_conformal = dict(
                temporal_quantiles=tuple(np.asarray(conformal["quantiles"]) * ratio(levels)),
                temporal_size_quantiles=tuple((per_size * ratio(levels)).ravel()),
                temporal_score_table=tuple(np.asarray(conformal["score_table"])
                                           * ratio(SCORE_GRID)),
                temporal_n_residuals=int(at.size))
    cal = Calibration(scale=scale, temporal_scale=t_scale, n_residuals=int(z.size),
                      coverage68_raw=float(raw[0]), coverage95_raw=float(raw[1]),
                      temporal_coverage68_raw=float(t_raw[0]),
                      temporal_coverage95_raw=float(t_raw[1]), n_blocks=int(n_blocks),
                      sizes=",".join(str(int(s)) for s in sizes), dof=dof,
                      discount=float(discount), dof_loglik_gain=float(gain),
                      residual_scale=float(rho), local_power=float(power), **conformal,
                      **t_conformal, selection=_choice_table(decision, labels, candidates,
                                                             fits, int(z.size)))
    model.calibration_ = cal
    return cal
