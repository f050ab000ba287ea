"""A model's calibration as it is stored and applied (the estimation is
validation/calibration.py).

:class:`Calibration` holds the variance scales (``calibration_`` on a model, NetCDF attributes
``calibration_*``, its choice's table variables ``calibration_selection_*``);
:func:`variance_scale`, :func:`noise_variance`, :func:`predictive_std` and
:func:`interval_coverage` are what every predictive variance and coverage reads. They sit below
the posterior and the model, which read them, while the estimation refits models and runs the
filter above them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from ..errors import ModelError

__all__ = ["Calibration", "variance_scale", "noise_variance", "residual_factor", "residual_dof",
           "prediction_factor", "predictive_std", "parameters_per_cell",
           "interval_coverage", "conformal_quantile", "check_level", "gaussian_multiplier",
           "AdaptiveConformal", "SCORE_GRID", "level_index", "ONLINE_GAMMA",
           "interval_factor", "RESIDUAL_FACTORS"]

_PREFIX = "calibration_"
_TUPLES = ("levels", "quantiles", "score_table", "temporal_quantiles", "temporal_score_table",
           "size_quantiles", "temporal_size_quantiles", "size_samples")
METHODS = ("gaussian", "conformal")
SCORE_GRID = tuple(np.round(np.r_[np.arange(0.01, 0.99, 0.01), np.arange(0.99, 0.9991, 0.001)],
                            6).tolist())
"""Probabilities at which a conformal calibration stores the score quantiles (for other levels
and for adaptive conformal inference)."""


def level_index(levels: Any, level: float) -> int | None:
    """The position of ``level`` among ``levels`` (equal to 1e-12), or None."""
    for i, known in enumerate(levels):
        if abs(float(known) - float(level)) < 1e-12:
            return i
    return None


def check_level(level: Any, name: str = "level") -> float:
    """``level`` as a float in the open interval (0, 1), else a one-line ModelError naming
    ``name``."""
    try:
        lv = float(level)
    except (TypeError, ValueError):
        raise ModelError(f"{name} must be a number in (0, 1), got {level!r}") from None
    if not 0.0 < lv < 1.0:
        raise ModelError(f"{name} must be in (0, 1), got {lv:g}")
    return lv


def gaussian_multiplier(level: Any) -> Any:
    """``z`` with ``P(|N(0, 1)| <= z) = level`` (scalar or array; 0 at level 0, inf at 1)."""
    from scipy.stats import norm

    return norm.ppf(0.5 + 0.5 * np.asarray(level, dtype=np.float64))


def conformal_quantile(scores: Any, level: Any) -> Any:
    """Split-conformal threshold of the non-conformity ``scores`` (``(..., n)``, the last axis
    the calibration set; NaN ignored): the ``k``-th smallest, ``k = ceil((n + 1) level)``, i.e.
    the empirical quantile at ``ceil((n + 1) level) / n``; ``inf`` when ``k > n``. For scores
    exchangeable with a new one, ``P(new <= threshold) >= level``, and ``< level + 1 / (n + 1)``
    when there are no ties (Vovk et al. 2005; Lei et al. 2018). ``level`` in (0, 1), a scalar
    or ``(m,)`` (then a trailing axis of length m). Vectorised over the leading axes."""
    checked = [check_level(v) for v in np.atleast_1d(np.asarray(level, dtype=object))]
    lv = np.asarray(checked[0] if np.ndim(level) == 0 else checked, dtype=np.float64)
    S = np.sort(np.asarray(scores, dtype=np.float64), axis=-1)  # NaN last
    n = np.sum(np.isfinite(S) | np.isinf(S), axis=-1)  # non-NaN count per row
    k = np.ceil((n[..., None] + 1) * np.atleast_1d(lv)) - 1  # 0-based index
    ok = k < n[..., None]
    idx = np.where(ok, k, 0).astype(np.int64)
    q = np.take_along_axis(S, idx, axis=-1) if S.ndim else S
    q = np.where(ok, q, np.inf)
    return q[..., 0] if lv.ndim == 0 else q


@dataclass(frozen=True)
class Calibration:
    """Variance scales of a model's predictive distribution, estimated by cross-validation.

    ``scale``: multiplier of the memoryless fold-in's predictive variance; ``temporal_scale``:
    of the filter's (None when not estimated: the filter then uses ``scale``). ``dof``: prior
    degrees of freedom of the per-snapshot scale (None: the scale is fixed); with it each
    snapshot's variances are scaled by ``(dof * scale + q) / (dof + n)``, ``q`` the squared
    norm of the standardized innovations of its ``n`` observations
    (:meth:`~lrm_cvx.belief.posterior.LatentPosterior.innovation`), plus the earlier snapshots'
    ``q`` and ``n`` weighted by ``discount`` per step (0: each snapshot on its own; carried by
    ``MonitorState``). ``dof_loglik_gain``: the cross-validated Gaussian log-likelihood per
    residual gained over the fixed scale. ``n_residuals``
    and ``coverage68_raw`` / ``coverage95_raw`` (the cross-validated coverage before scaling)
    document the estimate; ``n_blocks`` and ``sizes`` how it was made. A conformal calibration
    holds ``levels``, their thresholds ``quantiles`` and the ``score_table``; for a model with
    dynamics also the filter's own (``temporal_quantiles``, ``temporal_score_table``, from
    ``temporal_n_residuals`` forward-chained filter residuals: the filter's maps are tighter or
    looser than a memoryless fold-in's), which :meth:`for_filter` puts in their place.
    ``local_power``: each cell's predictive std is multiplied by the model's
    ``residual_spread_`` (its training residual std relative to the cells' rms) to this power,
    validated among :data:`~lrm_cvx.validation.calibration.LOCAL_POWERS` (0: every cell alike; 1:
    the std in proportion to the cell's residual std): locally weighted intervals, which cover
    calm and stormy cells alike where the residual's amplitude varies over the region.
    ``size_quantiles`` (and the filter's ``temporal_size_quantiles``): the thresholds of each
    design size of ``sizes`` (row-major ``(len(design_sizes), len(levels))``, flattened), from
    the fold-ins of that size alone, whose samples gave ``size_samples`` values on average
    (fewer than the size on snapshots with gaps); a belief holding ``n`` samples takes its
    threshold interpolated in ``log n`` between those counts (:meth:`multiplier`): a
    standardized residual can shrink as the samples grow denser, so one pooled threshold
    over-covers at large budgets.
    ``selection``: the table of the choice of ``residual_scale`` and ``local_power`` (the
    one search's, :func:`~lrm_cvx.validation.search.selection_table`; None when not made
    here), saved with the model file beside the other validated choices' tables.
    """

    scale: float = 1.0
    temporal_scale: float | None = None
    n_residuals: int = 0
    coverage68_raw: float = float("nan")
    coverage95_raw: float = float("nan")
    temporal_coverage68_raw: float = float("nan")
    temporal_coverage95_raw: float = float("nan")
    n_blocks: int = 0
    sizes: str = ""
    dof: float | None = None
    discount: float = 0.0
    residual_scale: float = 1.0
    local_power: float = 0.0
    dof_loglik_gain: float = 0.0
    method: str = "gaussian"
    levels: tuple = ()
    quantiles: tuple = ()
    score_table: tuple = ()
    temporal_quantiles: tuple = ()
    temporal_score_table: tuple = ()
    temporal_n_residuals: int = 0
    size_quantiles: tuple = ()
    temporal_size_quantiles: tuple = ()
    size_samples: tuple = ()
    selection: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ModelError(f"Calibration.method must be one of {METHODS}, got {self.method!r}")
        for name in _TUPLES:
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if len(self.levels) != len(self.quantiles):
            raise ModelError("Calibration.levels and quantiles must have the same length")
        if self.temporal_quantiles and len(self.temporal_quantiles) != len(self.levels):
            raise ModelError("Calibration.temporal_quantiles must have one entry per level")
        for lv in self.levels:
            check_level(lv, "levels")
        n_sizes = len(self.design_sizes) * len(self.levels)
        for name in ("size_quantiles", "temporal_size_quantiles"):
            got = len(getattr(self, name))
            if got and got != n_sizes:
                raise ModelError(f"Calibration.{name} must hold one entry per design size "
                                 f"({self.sizes!r}) and level ({len(self.levels)}): "
                                 f"{n_sizes}, got {got}")
        n = np.asarray(self.size_samples)
        if n.size and (n.size != len(self.design_sizes) or not np.all(np.isfinite(n) & (n > 0))):
            raise ModelError("Calibration.size_samples must hold one count > 0 per design size "
                             f"({self.sizes!r}), got {self.size_samples}")
        try:
            lp = float(self.local_power)
        except (TypeError, ValueError):
            lp = float("nan")
        if not (np.isfinite(lp) and lp >= 0):
            raise ModelError(f"Calibration.local_power must be a finite number >= 0, got "
                             f"{self.local_power!r}")
        object.__setattr__(self, "local_power", lp)
        for name in ("scale", "temporal_scale", "dof", "residual_scale"):
            v = getattr(self, name)
            if v is None:
                continue
            if not (np.isfinite(v) and v > 0):
                raise ModelError(f"Calibration.{name} must be a finite number > 0, got {v!r}")
            object.__setattr__(self, name, float(v))

    def for_filter(self) -> Calibration:
        """The calibration the filter's intervals use: the filter's conformal thresholds in
        place of the memoryless ones when they were estimated, else ``self``."""
        if not self.temporal_quantiles:
            return self
        return replace(self, quantiles=self.temporal_quantiles,
                       score_table=self.temporal_score_table,
                       n_residuals=self.temporal_n_residuals,
                       size_quantiles=self.temporal_size_quantiles,
                       temporal_quantiles=(), temporal_score_table=(),
                       temporal_size_quantiles=())

    @property
    def design_sizes(self) -> tuple[int, ...]:
        """The sample-set sizes of the calibration's fold-ins (parsed from ``sizes``)."""
        return tuple(int(v) for v in self.sizes.split(",") if v.strip())

    def variance_scale(self, temporal: bool = False) -> float:
        """The scale for the memoryless fold-in or (``temporal=True``) the filter."""
        if temporal and self.temporal_scale is not None:
            return self.temporal_scale
        return self.scale

    @property
    def is_conformal(self) -> bool:
        """True for a conformal calibration (per-level interval multipliers)."""
        return self.method == "conformal" and bool(self.levels or self.score_table)

    def score_quantile(self, level: float) -> float:
        """The conformal threshold of the calibrated scores at ``level`` (in (0, 1)): exact at
        the calibrated ``levels``, else interpolated in the stored ``score_table``
        (:data:`SCORE_GRID`; clamped to its ends; inf beyond ``1 - 1 / (n + 1)``). A Gaussian
        calibration: the normal quantile."""
        lv = check_level(level)
        j = level_index(self.levels, lv)
        if j is not None:
            return self.quantiles[j]
        if not self.score_table:
            return float(gaussian_multiplier(lv))
        if self.n_residuals and lv > 1.0 - 1.0 / (self.n_residuals + 1):
            return float("inf")
        return float(np.interp(lv, SCORE_GRID, self.score_table))

    def multiplier(self, level: float, n_samples: int | None = None) -> float:
        """Half-width of the central ``level`` interval in units of the calibrated predictive
        std: the conformal threshold for a conformal calibration, else the normal quantile.
        ``n_samples`` (the samples a belief holds): at a calibrated level with per-size
        thresholds (``size_quantiles``), the threshold interpolated linearly in ``log n``
        between the design sizes (at the samples their fold-ins held, ``size_samples``; the
        nearest size's outside them); else the pooled one."""
        if not self.is_conformal:
            return float(gaussian_multiplier(check_level(level)))
        lv = check_level(level)
        j = level_index(self.levels, lv)
        if n_samples is not None and self.size_quantiles and j is not None:
            return self._size_threshold(j, int(n_samples))
        return self.score_quantile(lv)

    def _size_threshold(self, j: int, n: int) -> float:
        """Level ``j``'s threshold at ``n`` samples from ``size_quantiles`` (placed at
        ``size_samples``, else at the design sizes)."""
        sizes = np.asarray(self.size_samples or self.design_sizes, dtype=np.float64)
        q = np.asarray(self.size_quantiles, dtype=np.float64).reshape(sizes.size, -1)[:, j]
        order = np.argsort(sizes)
        sizes, q = sizes[order], q[order]
        if np.isinf(q).any():  # a size with too few scores for the level: interp cannot
            return float(q[np.argmin(np.abs(np.log(sizes) - np.log(max(n, 1))))])
        return float(np.interp(np.log(max(n, 1)), np.log(sizes), q))

    def to_attrs(self) -> dict[str, Any]:
        """Flat NetCDF attributes ``calibration_*`` (None stored as NaN; the tuples as 1-D
        arrays, left out when empty). The ``selection`` table is not among them: the model
        file stores it as variables (:func:`~lrm_cvx.glrm.modelfile.validation_tables`)."""
        out = {}
        for key, value in ((f.name, getattr(self, f.name)) for f in fields(self)
                           if f.name != "selection"):
            if key in _TUPLES:
                if value:
                    out[_PREFIX + key] = np.asarray(value, dtype=np.float64)
                continue
            out[_PREFIX + key] = float("nan") if value is None else value
        return out

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any]) -> Calibration | None:
        """The calibration stored by :meth:`to_attrs`, or None when ``attrs`` hold none
        (its ``selection`` None: :func:`~lrm_cvx.glrm.modelfile.restore_validation_tables`
        sets it from the model file)."""
        if _PREFIX + "scale" not in attrs:
            return None
        kw: dict[str, Any] = {}
        for key in cls.__dataclass_fields__:
            if key != "selection" and _PREFIX + key in attrs:
                v = attrs[_PREFIX + key]
                if key in ("temporal_scale", "dof"):
                    v = None if not np.isfinite(float(v)) else float(v)
                elif key in ("n_residuals", "n_blocks", "temporal_n_residuals"):
                    v = int(v)
                elif key in ("sizes", "method"):
                    v = str(v)
                elif key in _TUPLES:
                    v = tuple(np.atleast_1d(np.asarray(v, dtype=np.float64)).tolist())
                else:
                    v = float(v)
                kw[key] = v
        return cls(**kw)


# ----------------------------------------------------------------------------- applying it
def variance_scale(model: Any, temporal: bool = False) -> float:
    """The model's calibrated variance scale (1.0 when it was not calibrated)."""
    cal = getattr(model, "calibration_", None)
    return 1.0 if cal is None else cal.variance_scale(temporal)


def parameters_per_cell(model: Any) -> tuple[float, int] | None:
    """``(n, k)`` of a fitted model: ``n`` the mean number of observed training snapshots per
    observed cell, ``k`` the parameters fitted per cell (the rank, plus 1 with an offset);
    None when the model does not say (a stand-in without ``n_observed_``)."""
    n_obs = getattr(model, "n_observed_", None)
    rank = getattr(model, "rank_", None)
    if n_obs is None or rank is None:
        return None
    cells = int(model.n_cells_) - int(np.asarray(getattr(model, "unobserved_cells_", ())).size)
    k = int(rank) + (1 if getattr(model, "offset_", None) is not None else 0)
    return float(n_obs) / max(cells, 1), k


def residual_dof(model: Any) -> float:
    """``n / (n - k)`` (:func:`parameters_per_cell`): a cell's training residuals, orthogonal
    to its ``k`` fitted parameters, hold ``(n - k) / n`` of the residual's variance, so the
    spatial covariance is fitted to them times ``sqrt(n / (n - k))`` (the correction of
    ``noise_std_``). 1 for a model that does not say."""
    nk = parameters_per_cell(model)
    if nk is None:
        return 1.0
    n, k = nk
    return n / max(n - k, 1.0)


def prediction_factor(model: Any) -> float:
    """The variance of a new snapshot's residual relative to the residual variance: ``n / (n -
    k)`` again (:func:`residual_dof`). A cell's ``k`` parameters estimated from its ``n``
    snapshots err by ``sigma^2 (X X^T)^-1``, which adds ``x^T (X X^T)^-1 x sigma^2`` at a new
    time ``x``: ``k / (n - k - 1)`` for Gaussian latent rows (the inverse-Wishart mean), more
    than the ``k / n`` of a training time (the leverage of least squares). On planted fields
    (rank + white noise, 8 seeds each) ``n / (n - k)`` matched the measured ratio within 5 %
    from rank 3 on 12 snapshots to rank 12 on 40 (tests/test_predictive_noise.py checks one).
    Small at paper scale (rank 5, 300 snapshots: 1.02), 2.2 at rank 12 on 24 snapshots:
    without it a high-rank model fitted on a short record is over-confident, and the
    conformal calibration, whose forward refits see shorter records than the final model,
    over-covers (docs/benchmarks.md)."""
    return residual_dof(model)


RESIDUAL_FACTORS = (0.5, 0.71, 1.0, 1.41, 2.0, 2.83, 4.0, 5.66, 8.0)
"""The one grid of the validated factor of a model's fitted residual and noise variances
(:func:`residual_factor`). ``temporal="auto"`` tries its whole doublings from 1 with every
temporal candidate (``validation.selection.AUTO_INFLATIONS``: scored with the dynamics by the
day-map MSE, stored as ``residual_inflation_``); a calibration then tries all of it on top
(scored by the held-out log-likelihood, stored as ``Calibration.residual_scale``)."""


def residual_factor(model: Any) -> float:
    """The factor of the model's fitted residual and noise variances in every fold-in, plan
    and interval, the one place the validated factor is read: the variance of a new
    snapshot's residual (:func:`prediction_factor`, ``n / (n - k)``) times the factor of
    :data:`RESIDUAL_FACTORS` validated with the dynamics (``residual_inflation_``,
    ``temporal="auto"``) and the calibration's step on top of it (``residual_scale``)."""
    cal = getattr(model, "calibration_", None)
    rho = 1.0 if cal is None else float(getattr(cal, "residual_scale", 1.0) or 1.0)
    inflation = float(getattr(model, "residual_inflation_", 1.0) or 1.0)
    return rho * inflation * prediction_factor(model)


def noise_variance(model: Any, spatial: bool = False) -> Any:
    """Variance of a new measurement around the latent value, in data units: the spatial
    nugget with ``spatial=True``, else ``noise_var_`` (per cell) or ``noise_std_^2``, times
    the validated residual factor (:func:`residual_factor`) and ``scale_^2`` when the model
    was fitted with ``scale``. A scalar or ``(L,)``."""
    if spatial:
        cov = getattr(model, "spatial_cov_", None)
        if cov is None:
            raise ModelError("spatial=True needs a model fitted with spatial=...")
        nv: Any = float(cov.nugget)
    else:
        nv = getattr(model, "noise_var_", None)
        nv = float(model.noise_std_) ** 2 if nv is None else np.asarray(nv, dtype=np.float64)
    nv = nv * residual_factor(model)
    sc = getattr(model, "scale_", None)
    return nv if sc is None else nv * np.asarray(sc, dtype=np.float64) ** 2


def interval_factor(model: Any) -> np.ndarray | None:
    """The per-cell factor of a fitted model's predictive stds, ``(L,)``: its
    ``residual_spread_`` to the power of its calibration's validated ``local_power``; None
    when either is missing or the power is 0 (every cell alike)."""
    cal = getattr(model, "calibration_", None)
    power = float(getattr(cal, "local_power", 0.0) or 0.0)
    spread = getattr(model, "residual_spread_", None)
    if power == 0.0 or spread is None:
        return None
    return np.asarray(spread, dtype=np.float64) ** power


def predictive_std(model: Any, std: Any, spatial: bool = False,
                   temporal: bool = False) -> np.ndarray:
    """Calibrated std of a new measurement: ``sqrt(std^2 + s * noise)``.

    ``std`` ``(..., L)`` (data units) is the posterior std of the latent value as returned by
    ``complete`` / ``MonitorState.predict`` (which already carry the scale ``s``: the
    observation model's ``variance_scale``); ``noise`` is :func:`noise_variance`; ``s`` the
    model's :func:`variance_scale`; times the calibration's per-cell factor
    (:func:`interval_factor`, ``std`` then ``(..., L)``). Equals
    ``LatentPosterior.predictive_std``.
    """
    s = np.asarray(std, dtype=np.float64)
    out = np.sqrt(s * s + variance_scale(model, temporal) * noise_variance(model, spatial))
    factor = interval_factor(model)
    return out if factor is None else out * factor


def interval_coverage(values: Any, mean: Any, std: Any,
                      levels: Sequence[float] = (0.68, 0.95),
                      multipliers: Sequence[float] | None = None) -> np.ndarray:
    """Fraction of the finite ``values`` inside ``mean +- z_level * std`` per level.

    ``values``, ``mean``, ``std`` broadcast together; NaN values are left out. ``multipliers``
    (one per level; default the normal quantiles ``z_level``) are the half-widths in units of
    ``std``: a conformal calibration's (``LatentPosterior.interval_multipliers``). Returns
    ``(len(levels),)`` (NaN when no value is finite).
    """
    if multipliers is None:
        multipliers = [float(gaussian_multiplier(check_level(lv, "levels"))) for lv in levels]
    elif len(multipliers) != len(levels):
        raise ModelError(f"multipliers must have one entry per level ({len(levels)}), got "
                         f"{len(multipliers)}")
    v = np.asarray(values, dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    sd = np.asarray(std, dtype=np.float64)
    z = np.abs(v - m) / np.where(sd > 0, sd, np.nan)
    z = z[np.isfinite(v)]
    if z.size == 0:
        return np.full(len(levels), np.nan)
    z = np.where(np.isnan(z), np.inf, z)
    return np.array([float(np.mean(z <= float(m))) for m in multipliers])


# ----------------------------------------------------------------------------- online (ACI)
ONLINE_GAMMA = 0.1
"""Step size of the online calibration ``MonitorState`` runs by default
(:class:`AdaptiveConformal`): chosen on rolling 30-day campaigns of some of the generalization
benchmark's records and reported on the others (docs/monitoring.md, "Online calibration")."""
_ATTRS = ("levels", "gamma", "alpha", "days", "miss")


class AdaptiveConformal:
    """Adaptive conformal inference (Gibbs & Candes 2021) for a stream of days.

    For each nominal ``level`` the miscoverage target is ``a = 1 - level`` and the working
    level ``alpha_t`` starts at ``a``; the interval of day ``t`` is ``mean +- m(alpha_t) *
    predictive_std`` with ``m(alpha) = calibration.score_quantile(1 - alpha)`` (the offline
    conformal scores; the normal quantile without a conformal calibration), ``inf`` for
    ``alpha_t <= 0`` and ``0`` for ``alpha_t >= 1``. After the day's samples are scored (their
    standardized forecast residuals ``|y - mean| / predictive_std``, *before* they are
    assimilated), ``alpha_{t+1} = alpha_t + gamma (a - err_t)`` with ``err_t`` the fraction of
    the day's samples outside the interval (the batch form of the update). Whatever the data,
    the long-run miscoverage satisfies ``|mean(err) - a| <= (max(alpha_1, 1 - alpha_1) +
    gamma) / (gamma T)`` (their Proposition 4.1)."""

    def __init__(self, levels: Sequence[float] = (0.68, 0.95), gamma: float = 0.01,
                 calibration: Calibration | None = None, alpha: Sequence[float] | None = None,
                 n_days: int = 0, miss_sum: Sequence[float] | None = None) -> None:
        self.levels = tuple(check_level(lv, "levels") for lv in levels)
        if not self.levels:
            raise ModelError("levels must hold at least one level in (0, 1)")
        g = float(gamma)
        if not (np.isfinite(g) and 0.0 < g <= 1.0):
            raise ModelError(f"gamma must be in (0, 1], got {gamma!r}")
        self.gamma = g
        self.calibration = calibration
        self.target = np.array([1.0 - lv for lv in self.levels])
        self.alpha = self.target.copy() if alpha is None else np.asarray(alpha, np.float64)
        if self.alpha.shape != self.target.shape or not np.all(np.isfinite(self.alpha)):
            raise ModelError(f"alpha must be {len(self.levels)} finite numbers, got {alpha!r}")
        self.n_days = int(n_days)
        self.miss_sum = (np.zeros(len(self.levels)) if miss_sum is None
                         else np.asarray(miss_sum, dtype=np.float64))
        if self.miss_sum.shape != self.target.shape or self.n_days < 0:
            raise ModelError(f"miss_sum must be {len(self.levels)} numbers and n_days >= 0, "
                             f"got {miss_sum!r}, {n_days!r}")

    def multipliers(self, n_samples: int | None = None) -> np.ndarray:
        """The current half-widths ``m(alpha_t)`` per level (units of the predictive std). With
        ``n_samples`` (the belief's) and per-size thresholds in the calibration, each is scaled
        by the level's threshold at ``n_samples`` relative to its pooled one."""
        out = np.empty(len(self.levels))
        cal = self.calibration
        for i, a in enumerate(self.alpha):
            if 1.0 - a >= 1.0:  # alpha <= 0, or too small to leave 1 - alpha below 1
                out[i] = np.inf
            elif 1.0 - a <= 0.0:
                out[i] = 0.0
            elif cal is not None:
                out[i] = cal.multiplier(1.0 - a)
                pooled = cal.multiplier(self.levels[i])
                if n_samples is not None and cal.size_quantiles and np.isfinite(pooled):
                    out[i] *= cal.multiplier(self.levels[i], n_samples) / pooled
            else:
                out[i] = float(gaussian_multiplier(1.0 - a))
        return out

    def multiplier(self, level: float) -> float:
        """The current half-width of ``level`` (one of ``levels``)."""
        i = level_index(self.levels, check_level(level))
        if i is not None:
            return float(self.multipliers()[i])
        raise ModelError(f"level {level!r} is not tracked (levels {self.levels})")

    def update(self, scores: Any, n_samples: int | None = None) -> np.ndarray:
        """Score one day: ``scores`` the standardized absolute residuals of its samples (NaN
        ignored) under a belief holding ``n_samples`` (:meth:`multipliers`). Updates ``alpha``
        and returns the day's miss fraction per level (NaN, and no update, when no score is
        finite)."""
        z = np.asarray(scores, dtype=np.float64).ravel()
        z = z[~np.isnan(z)]
        if z.size == 0:
            return np.full(len(self.levels), np.nan)
        err = np.mean(z[None, :] > self.multipliers(n_samples)[:, None], axis=1)
        self.alpha = self.alpha + self.gamma * (self.target - err)
        self.n_days += 1
        self.miss_sum = self.miss_sum + err
        return err

    @property
    def coverage(self) -> np.ndarray:
        """Mean daily coverage so far per level (NaN before the first day)."""
        if self.n_days == 0:
            return np.full(len(self.levels), np.nan)
        return 1.0 - self.miss_sum / self.n_days

    def to_attrs(self, prefix: str = "aci_") -> dict[str, Any]:
        """The state as flat NetCDF attributes ``{prefix}levels``, ``gamma``, ``alpha``,
        ``days``, ``miss`` (what :meth:`from_attrs` reads back equal)."""
        values = (np.asarray(self.levels, dtype=np.float64), self.gamma,
                  np.asarray(self.alpha, dtype=np.float64), self.n_days,
                  np.asarray(self.miss_sum, dtype=np.float64))
        return {prefix + key: v for key, v in zip(_ATTRS, values, strict=True)}

    @classmethod
    def from_attrs(cls, attrs: Any, calibration: Calibration | None = None,
                   prefix: str = "aci_") -> AdaptiveConformal | None:
        """The state stored by :meth:`to_attrs` in ``attrs`` (None when they hold none), its
        multipliers read from ``calibration``. A ModelError names a corrupt entry."""
        if prefix + "levels" not in attrs:
            return None
        try:
            levels = np.atleast_1d(np.asarray(attrs[prefix + "levels"], dtype=np.float64))
            return cls(levels, float(attrs[prefix + "gamma"]), calibration,
                       alpha=np.atleast_1d(np.asarray(attrs[prefix + "alpha"], np.float64)),
                       n_days=int(attrs[prefix + "days"]),
                       miss_sum=np.atleast_1d(np.asarray(attrs[prefix + "miss"], np.float64)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"the online calibration's {prefix}* entries are incomplete or "
                             f"corrupt: {exc}") from None

    def __repr__(self) -> str:
        al = ", ".join(f"{lv:g}: {a:.4f}" for lv, a in zip(self.levels, self.alpha, strict=True))
        return f"AdaptiveConformal(gamma={self.gamma:g}, alpha={{{al}}}, days={self.n_days})"
