"""Spatial residual model: low-rank trend plus a stationary Gaussian-process residual.

The paper's completion predicts a new snapshot by the least-squares fold-in ``Y^T x`` and
leaves spatial locality as future work. This module adds it (issue #8, item 4): the residuals of
the low-rank model are modelled as a zero-mean stationary Gaussian process with an isotropic
covariance of the distance between cells,

``C(d) = sill * rho(d / range) + nugget * [d == 0]``,

with ``rho`` one of ``exponential``, ``matern32``, ``matern52``, ``gaussian`` (``range`` is the
scale parameter, not the "practical range"; ``sill`` is the partial sill, ``nugget`` the
variance that no neighbour can predict: noise and sub-cell variation). The parameters come from
a binned empirical semivariogram of the training residuals fitted by weighted least squares
(:func:`fit_residual_covariance`). A new snapshot is predicted as trend + kriged residual
(:func:`residual_correction`), with the trend estimated either by the paper's fold-in ("ols",
regression kriging) or by generalised least squares under the GP covariance ("gls", universal
kriging, :func:`gls_fold_in`).

Scaling (L up to ~2M cells): no dense ``L x L`` matrix is ever built. :func:`krige` factors the
``n x n`` observation covariance once and streams targets in chunks of bounded memory
(``"direct"``), or solves a small system per target over its ``neighbors`` nearest observations
(``"neighbors"``, Vecchia-style local kriging, for many observations). Targets farther than the
covariance's cut-off distance (where ``rho < cutoff``) from every observation get the prior
(mean 0, variance ``sill``) without any solve: this is what makes 2M targets cheap.

Distances are in grid units (``metric="grid"``, the paper's) or great-circle kilometres
(``metric="km"``: cells are placed on a sphere and chord distances in the KD-tree are mapped to
arc lengths, which preserves neighbour order). Predictions are of the latent (noise-free)
residual; ``include_nugget=True`` adds the nugget to the variance to predict a new measurement.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal

import numba
import numpy as np
import scipy.linalg
from scipy.optimize import brentq, least_squares
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from ._validation import as_factor_matrix, as_generator, check_positive
from .errors import DataError, ModelError, SolverError
from .region import EARTH_RADIUS_KM, Region
from .registry import Registry

__all__ = [
    "MODELS",
    "KERNEL_REGISTRY",
    "ResidualCovariance",
    "EmpiricalVariogram",
    "correlation",
    "empirical_variogram",
    "fit_residual_covariance",
    "krige",
    "krige_many",
    "gls_fold_in",
    "residual_correction",
]

Model = Literal["exponential", "matern32", "matern52", "gaussian"]
Metric = Literal["grid", "km"]
_METRICS = ("grid", "km")
_SQRT3 = np.sqrt(3.0)
_SQRT5 = np.sqrt(5.0)
_ATTR_PREFIX = "spatial_"
_CHUNK_BYTES = 200_000_000
_MAX_DIRECT = 2000


# ---------------------------------------------------------------------------- covariance models
def correlation(model: str, h: Any) -> np.ndarray:
    """Correlation ``rho(h)`` of ``model`` at scaled distance ``h = d / range >= 0``."""
    h = np.asarray(h, dtype=np.float64)
    if model == "exponential":
        return np.exp(-h)
    if model == "matern32":
        s = _SQRT3 * h
        return (1.0 + s) * np.exp(-s)
    if model == "matern52":
        s = _SQRT5 * h
        return (1.0 + s + s * s / 3.0) * np.exp(-s)
    if model == "gaussian":
        return np.exp(-h * h)
    raise ModelError(f"model must be one of {MODELS}, got {model!r}")


KERNEL_REGISTRY = Registry("spatial model", ModelError)
"""Spatial covariance models (objects: their correlation ``rho(h)`` at scaled distance
``h = d / range``); ``MODELS`` is its ``choices()`` (the order is the compiled kernels' id)."""
KERNEL_REGISTRY.register("exponential", partial(correlation, "exponential"),
                         description="`exp(-h)` (Matern 1/2)")
KERNEL_REGISTRY.register("matern32", partial(correlation, "matern32"),
                         description="`(1 + sqrt(3) h) exp(-sqrt(3) h)`")
KERNEL_REGISTRY.register("matern52", partial(correlation, "matern52"),
                         description="`(1 + sqrt(5) h + 5 h^2 / 3) exp(-sqrt(5) h)`")
KERNEL_REGISTRY.register("gaussian", partial(correlation, "gaussian"),
                         description="`exp(-h^2)`")
MODELS: tuple[str, ...] = KERNEL_REGISTRY.choices()
"""Canonical spatial model names; the registry's ``choices()``."""


def _scaled_cutoff(model: str, rel: float) -> float:
    """Scaled distance ``h`` beyond which ``rho(h) < rel`` (rho is decreasing)."""
    if model == "exponential":
        return float(np.log(1.0 / rel))
    if model == "gaussian":
        return float(np.sqrt(np.log(1.0 / rel)))
    hi = 2.0 * np.log(1.0 / rel) + 10.0
    return float(brentq(lambda h: float(correlation(model, h)) - rel, 0.0, hi, xtol=1e-12))


@dataclass(frozen=True)
class EmpiricalVariogram:
    """Binned empirical semivariogram: mean distance, ``gamma`` and pair count of each bin."""

    distance: np.ndarray
    gamma: np.ndarray
    counts: np.ndarray
    max_distance: float
    metric: str

    @property
    def n_pairs(self) -> int:
        """Number of pairs used over all bins."""
        return int(self.counts.sum())


@dataclass(frozen=True)
class ResidualCovariance:
    """A stationary isotropic covariance ``C(d) = sill rho(d / range) + nugget [d == 0]``.

    Parameters
    ----------
    model : ``"exponential"``, ``"matern32"``, ``"matern52"`` or ``"gaussian"``.
    sill : partial sill, the spatially predictable variance (data units squared), ``>= 0``.
    range : scale parameter ``> 0`` in ``metric`` units (grid cells or km).
    nugget : variance of the spatially unpredictable part (noise), ``>= 0``.
    metric : ``"grid"`` (grid units) or ``"km"`` (great-circle kilometres).
    variogram : the empirical variogram it was fitted to, if any (not compared, not stored).
    """

    model: str
    sill: float
    range: float
    nugget: float = 0.0
    metric: str = "grid"
    variogram: EmpiricalVariogram | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "model", KERNEL_REGISTRY.canonical(self.model, "model"))
        if self.metric not in _METRICS:
            raise ModelError(f"metric must be 'grid' or 'km', got {self.metric!r}")
        object.__setattr__(self, "sill", check_positive(self.sill, "sill", error=ModelError))
        object.__setattr__(
            self, "range", check_positive(self.range, "range", strict=True, error=ModelError)
        )
        object.__setattr__(self, "nugget", check_positive(self.nugget, "nugget", error=ModelError))
        if self.sill + self.nugget <= 0:
            raise ModelError("sill + nugget must be > 0 (a covariance of zero variance)")

    # ------------------------------------------------------------------ evaluation
    @property
    def total_variance(self) -> float:
        """``sill + nugget``: the prior variance of a new measurement."""
        return self.sill + self.nugget

    def correlation(self, d: Any) -> np.ndarray:
        """``rho(d / range)`` of the spatial part at distances ``d`` (any shape, metric units)."""
        return correlation(self.model, np.asarray(d, dtype=np.float64) / self.range)

    def covariance(self, d: Any, *, nugget: bool = True) -> np.ndarray:
        """``sill rho(d / range)`` plus the nugget where ``d == 0`` (unless ``nugget=False``)."""
        d = np.asarray(d, dtype=np.float64)
        c = self.sill * self.correlation(d)
        if nugget and self.nugget:
            c = c + self.nugget * (d == 0)
        return c

    def semivariogram(self, d: Any) -> np.ndarray:
        """``gamma(d) = nugget [d > 0] + sill (1 - rho(d / range))``."""
        d = np.asarray(d, dtype=np.float64)
        return self.nugget * (d > 0) + self.sill * (1.0 - self.correlation(d))

    def cutoff_distance(self, rel: float = 1e-6) -> float:
        """Distance (metric units) beyond which the spatial covariance is below ``rel * sill``."""
        rel = check_positive(rel, "rel", strict=True, error=ModelError)
        if rel >= 1:
            return 0.0
        return self.range * _scaled_cutoff(self.model, rel)

    @property
    def effective_range(self) -> float:
        """Distance at which the correlation falls to 0.05 (the geostatistical practical range)."""
        return self.cutoff_distance(0.05)

    # ------------------------------------------------------------------ persistence
    def to_attrs(self) -> dict[str, Any]:
        """Flat NetCDF-safe attributes (``spatial_model``, ``spatial_sill``, ...)."""
        return {
            f"{_ATTR_PREFIX}model": self.model,
            f"{_ATTR_PREFIX}sill": float(self.sill),
            f"{_ATTR_PREFIX}range": float(self.range),
            f"{_ATTR_PREFIX}nugget": float(self.nugget),
            f"{_ATTR_PREFIX}metric": self.metric,
        }

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any]) -> ResidualCovariance:
        """Inverse of :meth:`to_attrs` (extra keys are ignored)."""
        keys = ("model", "sill", "range", "nugget", "metric")
        missing = [f"{_ATTR_PREFIX}{k}" for k in keys if f"{_ATTR_PREFIX}{k}" not in attrs]
        if missing:
            raise ModelError(f"attrs do not hold a spatial covariance: missing {missing}")
        get = {k: attrs[f"{_ATTR_PREFIX}{k}"] for k in keys}
        return cls(
            model=str(get["model"]),
            sill=float(np.asarray(get["sill"]).item()),
            range=float(np.asarray(get["range"]).item()),
            nugget=float(np.asarray(get["nugget"]).item()),
            metric=str(get["metric"]),
        )

    def __repr__(self) -> str:
        unit = "cells" if self.metric == "grid" else "km"
        return (
            f"ResidualCovariance({self.model}, sill={self.sill:.4g}, range={self.range:.4g} "
            f"{unit}, nugget={self.nugget:.4g})"
        )


# ---------------------------------------------------------------------------- geometry
def _check_metric(metric: str) -> str:
    if metric not in _METRICS:
        raise ModelError(f"metric must be 'grid' or 'km', got {metric!r}")
    return metric


def _coords(region: Region, metric: str, cells: np.ndarray | None = None) -> np.ndarray:
    """Point coordinates whose Euclidean distances map monotonically onto ``metric`` distances.

    ``grid``: ``(n, 2)`` (row, col). ``km``: ``(n, 3)`` points on a sphere of the Earth's radius
    (Euclidean = chord length; see :func:`_arc`).
    """
    gi = region.grid_index if cells is None else region.grid_index[cells]
    if metric == "grid":
        return gi.astype(np.float64)
    lat = np.radians(region.lat.values[gi[:, 0]])
    lon = np.radians(region.lon.values[gi[:, 1]])
    cl = np.cos(lat)
    return EARTH_RADIUS_KM * np.column_stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)])


def _arc(chord: np.ndarray, metric: str) -> np.ndarray:
    """Metric distance from the Euclidean distance between :func:`_coords` points."""
    if metric == "grid":
        return chord
    return 2.0 * EARTH_RADIUS_KM * np.arcsin(np.clip(chord / (2.0 * EARTH_RADIUS_KM), 0.0, 1.0))


def _chord(d: float, metric: str) -> float:
    """Inverse of :func:`_arc` (infinite beyond half the circumference)."""
    if metric == "grid":
        return d
    if d >= np.pi * EARTH_RADIUS_KM:
        return np.inf
    return float(2.0 * EARTH_RADIUS_KM * np.sin(d / (2.0 * EARTH_RADIUS_KM)))


def _min_step(region: Region, metric: str) -> float:
    """Smallest distance between grid neighbours (1 in grid units)."""
    if metric == "grid":
        return 1.0
    lat = np.radians(region.lat.values)
    lon = np.radians(region.lon.values)
    steps = []
    if lat.size > 1:
        steps.append(np.abs(np.diff(lat)).min())
    if lon.size > 1:
        steps.append(np.abs(np.diff(lon)).min() * np.cos(np.abs(lat).max()))
    step = EARTH_RADIUS_KM * min(steps) if steps else 1.0
    return float(step) if step > 0 else 1.0


def _default_max_distance(region: Region, metric: str) -> float:
    """Half the region's diagonal extent."""
    ny, nx = region.shape
    if metric == "grid":
        return max(float(np.hypot(ny - 1, nx - 1)) / 2.0, 1.0)
    lat, lon = np.radians(region.cell_lat), np.radians(region.cell_lon)
    pts = np.array([[lat.min(), lon.min()], [lat.max(), lon.max()]])
    xyz = EARTH_RADIUS_KM * np.column_stack(
        [np.cos(pts[:, 0]) * np.cos(pts[:, 1]), np.cos(pts[:, 0]) * np.sin(pts[:, 1]),
         np.sin(pts[:, 0])]
    )
    diag = float(_arc(np.linalg.norm(xyz[0] - xyz[1]), "km"))
    return max(diag / 2.0, _min_step(region, "km"))


# ---------------------------------------------------------------------------- variogram fit
def _as_residuals(residuals: Any, region: Region) -> np.ndarray:
    r = np.asarray(getattr(residuals, "values", residuals))
    if r.ndim == 1:
        r = r[None, :]
    if r.ndim != 2:
        raise DataError(f"residuals must be a (T, L) matrix, got shape {r.shape}")
    if r.shape[1] != region.n_cells:
        raise DataError(
            f"residuals have {r.shape[1]} columns, the region has {region.n_cells} cells"
        )
    if not np.issubdtype(r.dtype, np.floating):
        r = r.astype(np.float64)
    return r


def _sample_pairs(
    r: np.ndarray, region: Region, metric: str, max_distance: float, max_pairs: int,
    spacing: str, rng: np.random.Generator, scale: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Random ``(time, cell, cell)`` pairs within ``max_distance``: distances and half squared
    differences. Anchors are uniform over cells and times, offsets have a uniform (or
    log-uniform) length and uniform direction on the grid; bounded, vectorised work."""
    T, L = r.shape
    ny, nx = region.shape
    grid = region.cell_grid
    gi = region.grid_index
    step = _min_step(region, metric)
    radius = max_distance / step  # in grid units (km: the largest grid offset that can fit)
    radius = min(radius, float(np.hypot(ny, nx)))
    lo = 0.5
    if radius <= lo:
        raise ModelError(
            f"max_distance={max_distance:g} is below one grid step ({step:g}): no pair fits"
        )
    dists: list[np.ndarray] = []
    halves: list[np.ndarray] = []
    got = 0
    for _ in range(8):
        b = max(2 * (max_pairs - got), 1024)
        t = rng.integers(0, T, size=b)
        i = rng.integers(0, L, size=b)
        if spacing == "log":
            rad = np.exp(rng.uniform(np.log(lo), np.log(radius), size=b))
        else:
            rad = rng.uniform(lo, radius, size=b)
        ang = rng.uniform(0.0, 2.0 * np.pi, size=b)
        rows = gi[i, 0] + np.rint(rad * np.sin(ang)).astype(np.int64)
        cols = gi[i, 1] + np.rint(rad * np.cos(ang)).astype(np.int64)
        ok = (rows >= 0) & (rows < ny) & (cols >= 0) & (cols < nx)
        t, i, rows, cols = t[ok], i[ok], rows[ok], cols[ok]
        j = grid[rows, cols]
        ok = (j >= 0) & (j != i)
        t, i, j = t[ok], i[ok], j[ok]
        a = r[t, i].astype(np.float64)
        c = r[t, j].astype(np.float64)
        ok = np.isfinite(a) & np.isfinite(c)
        t, i, j, a, c = t[ok], i[ok], j[ok], a[ok], c[ok]
        if metric == "grid":
            dg = gi[i] - gi[j]
            d = np.hypot(dg[:, 0], dg[:, 1]).astype(np.float64)
        else:
            d = _arc(np.linalg.norm(_coords(region, metric, i) - _coords(region, metric, j),
                                    axis=1), metric)
        ok = (d > 0) & (d <= max_distance)
        diff = a[ok] - c[ok]
        if scale is not None:
            diff = diff * scale[t[ok]]
        dists.append(d[ok])
        halves.append(0.5 * diff * diff)
        got += int(ok.sum())
        if got >= max_pairs:
            break
    d = np.concatenate(dists)[:max_pairs]
    h = np.concatenate(halves)[:max_pairs]
    return d, h


def empirical_variogram(
    residuals: Any,
    region: Region,
    *,
    metric: Metric = "grid",
    max_pairs: int = 200_000,
    n_bins: int = 20,
    max_distance: float | None = None,
    spacing: Literal["log", "linear"] = "log",
    standardize: bool = False,
    random_state: Any = 0,
) -> EmpiricalVariogram:
    """Binned Matheron semivariogram ``gamma(h) = mean of (r_t(i) - r_t(j))^2 / 2`` of ``(T, L)``
    residuals (NaN = missing) from at most ``max_pairs`` random same-time pairs within
    ``max_distance`` (default: half the region's diagonal). ``spacing="log"`` uses geometric bins
    from one grid step (short lags carry the range information); ``standardize`` divides each time
    by its standard deviation, then rescales gamma by the mean per-time variance. Empty bins are
    dropped. Deterministic given ``random_state``."""
    metric = _check_metric(metric)
    r = _as_residuals(residuals, region)
    max_pairs = int(max_pairs)
    n_bins = int(n_bins)
    if max_pairs < 10:
        raise ModelError(f"max_pairs must be >= 10, got {max_pairs}")
    if n_bins < 3:
        raise ModelError(f"n_bins must be >= 3 (three parameters are fitted), got {n_bins}")
    if spacing not in ("log", "linear"):
        raise ModelError(f"spacing must be 'log' or 'linear', got {spacing!r}")
    if max_distance is None:
        max_distance = _default_max_distance(region, metric)
    max_distance = check_positive(max_distance, "max_distance", strict=True, error=ModelError)
    rng = as_generator(random_state)
    scale = None
    var_scale = 1.0
    if standardize:
        sd = np.array([np.nanstd(r[t]) if np.isfinite(r[t]).any() else np.nan
                       for t in range(r.shape[0])])
        good = np.isfinite(sd) & (sd > 0)
        if not good.any():
            raise DataError("residuals have no time with a finite, non-constant row")
        scale = np.where(good, 1.0 / np.where(good, sd, 1.0), np.nan)
        var_scale = float(np.mean(sd[good] ** 2))
    d, half = _sample_pairs(r, region, metric, max_distance, max_pairs, spacing, rng, scale)
    ok = np.isfinite(half)
    d, half = d[ok], half[ok]
    if d.size == 0:
        raise DataError(
            "residuals have no pair of finite values within max_distance "
            "(are they all NaN, or the region a single cell?)"
        )
    step = _min_step(region, metric)
    if spacing == "log":
        edges = np.geomspace(0.999 * min(step, max_distance), max_distance, n_bins + 1)
        edges[0] = 0.0
    else:
        edges = np.linspace(0.0, max_distance, n_bins + 1)
    b = np.clip(np.searchsorted(edges, d, side="left") - 1, 0, n_bins - 1)
    counts = np.bincount(b, minlength=n_bins)
    sum_d = np.bincount(b, weights=d, minlength=n_bins)
    sum_g = np.bincount(b, weights=half, minlength=n_bins)
    keep = counts > 0
    return EmpiricalVariogram(
        distance=sum_d[keep] / counts[keep],
        gamma=var_scale * sum_g[keep] / counts[keep],
        counts=counts[keep].astype(np.int64),
        max_distance=float(max_distance),
        metric=metric,
    )


def fit_residual_covariance(
    residuals: Any,
    region: Region,
    *,
    model: Model = "exponential",
    metric: Metric = "grid",
    max_pairs: int = 200_000,
    n_bins: int = 20,
    max_distance: float | None = None,
    spacing: Literal["log", "linear"] = "log",
    standardize: bool = False,
    random_state: Any = 0,
) -> ResidualCovariance:
    """Fit ``sill``, ``range`` and ``nugget`` of ``model`` to the residuals' empirical variogram.

    ``residuals`` is ``(T, L)`` (training data minus the low-rank reconstruction, NaN = missing).
    The binned semivariogram (:func:`empirical_variogram`) is fitted by
    ``scipy.optimize.least_squares`` with bin weights proportional to the pair counts, from three
    starting ranges (the best fit wins). The range is bounded to ``[1e-3, 10] * max_distance``:
    a range much beyond the largest lag is not identifiable. Deterministic given ``random_state``.
    """
    model = KERNEL_REGISTRY.canonical(model, "model")
    vg = empirical_variogram(
        residuals, region, metric=metric, max_pairs=max_pairs, n_bins=n_bins,
        max_distance=max_distance, spacing=spacing, standardize=standardize,
        random_state=random_state,
    )
    if vg.distance.size < 3:
        raise DataError(
            f"only {vg.distance.size} non-empty variogram bins: too few pairs of finite residuals "
            "to fit a covariance (need 3)"
        )
    g_scale = float(np.average(vg.gamma, weights=vg.counts))
    if not g_scale > 0:
        raise DataError("residuals are spatially constant (zero semivariance): nothing to fit")
    h = vg.distance / vg.max_distance
    g = vg.gamma / g_scale
    w = np.sqrt(vg.counts / vg.counts.sum())

    def resid(p: np.ndarray) -> np.ndarray:
        sill, rng_, nug = p
        return w * (nug + sill * (1.0 - correlation(model, h / rng_)) - g)

    nug0 = min(0.5 * g[0], 0.5 * g.max())
    sill0 = max(g.max() - nug0, 1e-3)
    lower = [0.0, 1e-3, 0.0]
    upper = [10.0 * g.max() + 1.0, 10.0, 2.0 * g.max() + 1.0]
    best = None
    for r0 in (0.05, 0.2, 1.0):
        sol = least_squares(resid, x0=[sill0, r0, nug0], bounds=(lower, upper), method="trf",
                            x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        if best is None or sol.cost < best.cost - 1e-15:
            best = sol
    sill, rng_, nug = best.x
    if sill + nug <= 0:
        raise SolverError("the variogram fit (scipy least_squares) returned a zero covariance")
    return ResidualCovariance(
        model=model, sill=float(sill * g_scale), range=float(rng_ * vg.max_distance),
        nugget=float(nug * g_scale), metric=vg.metric, variogram=vg,
    )


# ---------------------------------------------------------------------------- kriging
def _check_cov(cov: Any) -> ResidualCovariance:
    if not isinstance(cov, ResidualCovariance):
        raise ModelError(f"cov must be a ResidualCovariance, got {type(cov).__name__}")
    return cov


def _cholesky(K: np.ndarray, scale: float, what: str) -> np.ndarray:
    """Lower Cholesky factor; adds a tiny jitter (1e-10 .. 1e-6 of ``scale``) when ``K`` is
    numerically singular (duplicate cells without a nugget, a smooth gaussian model)."""
    for jitter in (0.0, 1e-10, 1e-8, 1e-6):
        try:
            A = K + (jitter * scale) * np.eye(K.shape[-1]) if jitter else K
            return np.linalg.cholesky(A)
        except np.linalg.LinAlgError:
            continue
    raise SolverError(f"the {what} covariance is not positive definite even with jitter 1e-6")


def _chunk(total: int, per_item: int) -> int:
    return int(max(1, min(total, _CHUNK_BYTES // max(per_item, 1))))


def _spatial_cov_inplace(cov: ResidualCovariance, d: np.ndarray) -> np.ndarray:
    """``sill * rho(d / range)`` written over the float64 array ``d`` (saves big temporaries)."""
    h = d
    h *= 1.0 / cov.range
    if cov.model == "exponential":
        np.negative(h, out=h)
        np.exp(h, out=h)
    elif cov.model == "gaussian":
        h *= h
        np.negative(h, out=h)
        np.exp(h, out=h)
    else:
        h *= _SQRT3 if cov.model == "matern32" else _SQRT5
        e = np.exp(-h)
        if cov.model == "matern52":
            e *= 1.0 + h + h * h / 3.0
        else:
            e *= 1.0 + h
        h[...] = e
    h *= cov.sill
    return h


def _krige_core(
    cov: ResidualCovariance,
    obs_xyz: np.ndarray,
    Z: np.ndarray,
    tgt_xyz: np.ndarray,
    *,
    method: str,
    neighbors: int,
    cutoff: float | None,
    want_var: bool,
    Ys: np.ndarray | None = None,
    Yt: Callable[[np.ndarray], np.ndarray] | None = None,
    cov_x: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple kriging of ``Z`` (``(n, r)``: r snapshots sharing the ``n`` observations) at the
    targets. Returns mean ``(r, n_targets)`` and the latent variance ``(n_targets,)``.

    With ``Ys`` (``(k, n)``, the trend basis at the observations), ``Yt(idx)`` (``(k, len(idx))``
    basis at those targets) and ``cov_x`` (GLS covariance of the trend coefficients), the
    variance gets the universal-kriging term ``u^T cov_x u`` with ``u = y_t - Ys C^-1 k_t``."""
    metric = cov.metric
    n, r = Z.shape
    nt = tgt_xyz.shape[0]
    mean = np.zeros((r, nt))
    var = np.full(nt, cov.sill) if want_var else None
    trend = Ys is not None and want_var

    def add_trend(sel: np.ndarray, u: np.ndarray) -> None:
        var[sel] += np.einsum("kc,kl,lc->c", u, cov_x, u)

    if n == 0:
        if trend:
            for lo in range(0, nt, 100_000):
                sel = np.arange(lo, min(nt, lo + 100_000))
                add_trend(sel, Yt(sel))
        return mean, var
    # targets near at least one observation; the rest keep the prior
    if cutoff is not None and cov.sill > 0:
        reach = _chord(cov.cutoff_distance(cutoff), metric)
        tree = cKDTree(obs_xyz)
        if np.isfinite(reach):
            dnear, _ = tree.query(tgt_xyz, k=1, distance_upper_bound=reach * (1 + 1e-12))
            near = np.flatnonzero(np.isfinite(dnear))
            if trend:
                far = np.flatnonzero(~np.isfinite(dnear))
                for lo in range(0, far.size, 100_000):
                    sel = far[lo:lo + 100_000]
                    add_trend(sel, Yt(sel))
        else:
            near = np.arange(nt)
    else:
        tree = None
        near = np.arange(nt)
    if near.size == 0 or cov.sill == 0:
        if trend and cov.sill == 0:  # pure nugget: GLS trend only
            for lo in range(0, near.size, 100_000):
                sel = near[lo:lo + 100_000]
                add_trend(sel, Yt(sel))
        return mean, var

    if method == "direct":
        K = cov.covariance(_arc(cdist(obs_xyz, obs_xyz), metric))
        np.fill_diagonal(K, cov.sill + cov.nugget)
        Lc = _cholesky(K, cov.total_variance, "observation")
        alpha = scipy.linalg.cho_solve((Lc, True), Z)  # (n, r)
        W = scipy.linalg.solve_triangular(Lc, Ys.T, lower=True) if trend else None  # (n, k)
        c = _chunk(near.size, 24 * n)
        for lo in range(0, near.size, c):
            sel = near[lo:lo + c]
            Kts = _spatial_cov_inplace(cov, _arc(cdist(tgt_xyz[sel], obs_xyz), metric))
            mean[:, sel] = (Kts @ alpha).T
            if want_var:
                V = scipy.linalg.solve_triangular(Lc, Kts.T, lower=True, check_finite=False)
                var[sel] -= np.einsum("ij,ij->j", V, V)
                if trend:
                    add_trend(sel, Yt(sel) - W.T @ V)
        return mean, var

    # local (nearest-neighbour) kriging: one small system per target, compiled; consecutive
    # targets with the same neighbour set (common on a grid) share one factorisation
    m = int(min(neighbors, n))
    tree = tree if tree is not None else cKDTree(obs_xyz)
    c = _chunk(near.size, 8 * m * (6 + r))
    model_id = MODELS.index(cov.model)
    for lo in range(0, near.size, c):
        sel = near[lo:lo + c]
        dist, idx = tree.query(tgt_xyz[sel], k=m)
        dist = np.asarray(dist, dtype=np.float64).reshape(sel.size, m)
        idx = np.asarray(idx, dtype=np.int64).reshape(sel.size, m)
        order = np.argsort(idx, axis=1, kind="stable")
        idx = np.ascontiguousarray(np.take_along_axis(idx, order, axis=1))
        dist = np.ascontiguousarray(_arc(np.take_along_axis(dist, order, axis=1), metric))
        w = np.empty((sel.size, m))
        v = np.empty(sel.size)
        status = _local_weights(idx, dist, obs_xyz, model_id, cov.sill, cov.range, cov.nugget,
                                metric == "km", w, v)
        if status < 0:
            raise SolverError(
                "a neighbourhood covariance is not positive definite even with jitter 1e-6"
            )
        mean[:, sel] = np.einsum("cm,cmr->rc", w, Z[idx])
        if want_var:
            var[sel] = v
            if trend:
                add_trend(sel, Yt(sel) - np.einsum("kcm,cm->kc", Ys[:, idx], w))
    return mean, var


FFT_KRIGE_MIN_WORK: float = 2e7
""":func:`krige_grid_fft` replaces direct kriging of a whole grid-metric region when
``n_obs x n_targets`` exceeds this (``LatentPosterior.predict``)."""
FFT_KRIGE_VAR_TOL: float = 1e-6
"""Variance tolerance of :func:`krige_grid_fft`, relative to the nugget."""


def krige_grid_fft(cov: ResidualCovariance, region: Region, obs_cells: np.ndarray,
                   z: np.ndarray, *, Ys: np.ndarray | None = None, Yall: np.ndarray | None = None,
                   cov_x: np.ndarray | None = None, var_tol: float = FFT_KRIGE_VAR_TOL
                   ) -> tuple[np.ndarray, np.ndarray, int]:
    """Kriging of the residuals ``z`` (``(n,)``, at the distinct ``obs_cells``) at *every*
    cell of a grid-metric region by FFT convolutions (no distance matrix to the targets).

    The residual covariance at the observations is ``C = sill R + nugget I``; with
    ``R = U diag(mu) U^T`` and ``lambda = sill mu + nugget``, for a target ``t`` with
    ``k_t = (k(t, o_j))_j`` and projections ``p_m(t) = u_m^T k_t`` (one convolution each):

    * mean ``k_t^T C^-1 z = sum_j alpha_j k(t, o_j)``: one convolution, exact (up to rounding);
    * variance reduction ``k_t^T C^-1 k_t = sum_m p_m^2 / lambda_m``: the leading ``M``
      eigenvectors exactly, the rest through ``||k_t||^2 - sum_{m<=M} p_m^2`` (one convolution
      with ``k^2``) at the weight ``1 / nugget``: an over-estimate by at most
      ``(lambda_{M+1} - nugget) / nugget^2 * max_t ||k_t||^2``, and ``M`` is the smallest for
      which that is ``<= var_tol * nugget`` (the predictive variance is >= the nugget);
    * universal kriging (``Ys (k, n)`` the trend basis at the observations, ``Yall (k, L)`` at
      every cell, ``cov_x`` the GLS covariance of the trend coefficients): ``+ u_t^T cov_x
      u_t``, ``u_t = y_t - Ys C^-1 k_t``, ``Ys C^-1 k_t`` by ``k`` convolutions with the
      weights ``C^-1 Ys^T`` (exact).

    Returns ``(mean (L,), latent variance (L,), M)`` in the region's cell order. Needs a
    nugget > 0 and ``metric="grid"``.
    """
    from .information import GridConv

    if cov.metric != "grid":
        raise ModelError("krige_grid_fft needs metric='grid'")
    nug = float(cov.nugget)
    if not nug > 0:
        raise ModelError("krige_grid_fft needs a nugget > 0")
    obs_cells = np.asarray(obs_cells, dtype=np.int64)
    z = np.asarray(z, dtype=np.float64).ravel()
    gi = region.grid_index
    shape = region.shape
    go = gi[obs_cells]
    xo = go.astype(np.float64)
    R = cov.covariance(cdist(xo, xo), nugget=False) / cov.sill
    np.fill_diagonal(R, 1.0)
    mu, U = np.linalg.eigh(0.5 * (R + R.T))
    mu = np.maximum(mu, 0.0)
    lam = cov.sill * mu + nug
    alpha = U @ ((U.T @ z) / lam)
    lo, hi = go.min(axis=0), go.max(axis=0)
    window = (int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    out = (0, 0, int(shape[0]), int(shape[1]))
    loc = (go[:, 0] - window[0], go[:, 1] - window[1])

    def kern(d):
        return cov.covariance(d, nugget=False)

    conv = GridConv(window, out, kern)
    img = np.zeros(window[2:])
    rows, cols = gi[:, 0], gi[:, 1]

    def apply(c: GridConv, w: np.ndarray) -> np.ndarray:
        img[...] = 0.0
        np.add.at(img, loc, w)
        return c(img)[rows, cols]

    mean = apply(conv, alpha)
    kk = apply(GridConv(window, out, lambda d: kern(d) ** 2), np.ones(z.size))
    kmax = float(np.max(kk)) if kk.size else 0.0
    # leading eigenvectors: those whose weight differs from 1/nugget by more than the
    # tolerance allows (the error is <= (lambda_cut - nugget) / nugget^2 * max_t ||k_t||^2)
    thresh = var_tol * nug ** 3 / max(kmax, 1e-300)
    trend = Ys is not None and Yall is not None and cov_x is not None
    order = np.argsort(-lam)
    lead = order[(lam[order] - nug) > thresh]
    var = np.full(gi.shape[0], float(cov.sill))
    red = kk / nug
    for m in lead:
        p = apply(conv, U[:, m])
        red += (1.0 / lam[m] - 1.0 / nug) * p * p
    var -= red
    if trend:  # Ys C^-1 k_t = sum_j (C^-1 Ys^T)_j k(t, o_j): k convolutions, exact
        CY = U @ ((U.T @ Ys.T) / lam[:, None])
        u = np.array(Yall, dtype=np.float64, copy=True)
        for a in range(Ys.shape[0]):
            u[a] -= apply(conv, CY[:, a])
        var += np.einsum("kc,kl,lc->c", u, cov_x, u)
    return mean, var, int(lead.size)


@numba.njit(cache=True)
def _rho_nb(model_id: int, h: float) -> float:
    if model_id == 0:
        return np.exp(-h)
    if model_id == 1:
        s = _SQRT3 * h
        return (1.0 + s) * np.exp(-s)
    if model_id == 2:
        s = _SQRT5 * h
        return (1.0 + s + s * s / 3.0) * np.exp(-s)
    return np.exp(-h * h)


@numba.njit(cache=True)
def _chol_inplace(A: np.ndarray, m: int) -> bool:
    """Lower Cholesky factor of ``A[:m, :m]`` in place (lower triangle); False if not PD."""
    for j in range(m):
        s = A[j, j]
        for q in range(j):
            s -= A[j, q] * A[j, q]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        A[j, j] = d
        for i in range(j + 1, m):
            s = A[i, j]
            for q in range(j):
                s -= A[i, q] * A[j, q]
            A[i, j] = s / d
    return True


@numba.njit(cache=True)
def _local_weights(idx, dist, xyz, model_id, sill, scale, nugget, km, w_out, var_out):
    """Kriging weights ``w_t = K_t^-1 k_t`` and latent variances ``sill - k_t^T w_t`` of each
    target ``t`` from its neighbours ``idx[t]`` (sorted) at distances ``dist[t]``. Returns the
    number of factorisations that needed jitter, or -1 when one failed even with jitter."""
    c, m = idx.shape
    dim = xyz.shape[1]
    K = np.empty((m, m))
    Lf = np.empty((m, m))
    y = np.empty(m)
    two_r = 2.0 * EARTH_RADIUS_KM
    jittered = 0
    have = False
    for t in range(c):
        same = have
        if have:
            for i in range(m):
                if idx[t, i] != idx[t - 1, i]:
                    same = False
                    break
        if not same:
            for i in range(m):
                for j in range(i):
                    d2 = 0.0
                    for q in range(dim):
                        diff = xyz[idx[t, i], q] - xyz[idx[t, j], q]
                        d2 += diff * diff
                    d = np.sqrt(d2)
                    if km:
                        d = two_r * np.arcsin(min(1.0, d / two_r))
                    K[i, j] = sill * _rho_nb(model_id, d / scale)
                K[i, i] = sill + nugget
            ok = False
            for jitter in (0.0, 1e-10, 1e-8, 1e-6):
                for i in range(m):
                    for j in range(i + 1):
                        Lf[i, j] = K[i, j]
                    Lf[i, i] += jitter * (sill + nugget)
                if _chol_inplace(Lf, m):
                    ok = True
                    if jitter > 0:
                        jittered += 1
                    break
            if not ok:
                return -1
            have = True
        # y = L^-1 k_t ; w = L^-T y ; var = sill - |y|^2
        acc = 0.0
        for i in range(m):
            s = sill * _rho_nb(model_id, dist[t, i] / scale)
            for q in range(i):
                s -= Lf[i, q] * y[q]
            y[i] = s / Lf[i, i]
            acc += y[i] * y[i]
        var_out[t] = sill - acc
        for i in range(m - 1, -1, -1):
            s = y[i]
            for q in range(i + 1, m):
                s -= Lf[q, i] * w_out[t, q]
            w_out[t, i] = s / Lf[i, i]
    return jittered


def _check_method(method: str) -> str:
    if method not in ("auto", "direct", "neighbors"):
        raise ModelError(f"method must be 'auto', 'direct' or 'neighbors', got {method!r}")
    return method


def _prepare(
    cov: Any, region: Region, cells: Any, targets: Any, neighbors: int, cutoff: float | None,
    method: str,
) -> tuple[ResidualCovariance, np.ndarray, np.ndarray, int, float | None, str]:
    cov = _check_cov(cov)
    if not isinstance(region, Region):
        raise DataError(f"region must be a Region, got {type(region).__name__}")
    cells = region.check_cells(np.ravel(cells), "cells")
    if np.unique(cells).size != cells.size:
        raise DataError("cells has repeated cell indices: give one value per observed cell")
    tg = (np.arange(region.n_cells) if targets is None
          else region.check_cells(np.ravel(targets), "targets"))
    if int(neighbors) < 1:
        raise ModelError(f"neighbors must be >= 1, got {neighbors!r}")
    if cutoff is not None:
        cutoff = check_positive(cutoff, "cutoff", strict=True, error=ModelError)
    return cov, cells, tg, int(neighbors), cutoff, _check_method(method)


def krige_many(
    cov: ResidualCovariance,
    region: Region,
    cells: Any,
    values: Any,
    *,
    targets: Any = None,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple (zero-mean) kriging of several snapshots observed at (subsets of) the same cells.

    ``values`` is ``(m, n)`` with NaN where a snapshot did not observe ``cells[j]``; snapshots
    with the same pattern share one factorisation. Returns mean and std ``(m, n_targets)``
    float64 (targets default to all L cells). ``method="auto"`` solves with all observations
    (``"direct"``: one ``n x n`` Cholesky, targets streamed in ~200 MB chunks) when ``n <= 2000``
    and with each target's ``neighbors`` nearest observations otherwise. Targets farther than
    ``cov.cutoff_distance(cutoff)`` from every observation get mean 0 and the prior std without a
    solve (``cutoff=None`` disables that). The std is that of the latent residual (it is 0 at an
    observed cell when ``nugget == 0``); ``include_nugget=True`` adds the nugget, for predicting a
    new measurement.
    """
    cov, cells, tg, neighbors, cutoff, method = _prepare(
        cov, region, cells, targets, neighbors, cutoff, method)
    V = np.asarray(values, dtype=np.float64)
    if V.ndim == 1:
        V = V[None, :]
    if V.ndim != 2 or V.shape[1] != cells.size:
        raise DataError(
            f"values must be (m, n) with n = len(cells) = {cells.size}, got shape {V.shape}"
        )
    if np.isinf(V).any():
        raise DataError("values has infinite entries")
    obs = np.isfinite(V)
    patterns, inv = np.unique(obs, axis=0, return_inverse=True)
    inv = inv.ravel()
    tgt_xyz = _coords(region, cov.metric, tg)
    all_xyz = _coords(region, cov.metric, cells)
    mean = np.zeros((V.shape[0], tg.size))
    var = np.empty((V.shape[0], tg.size)) if return_std else None
    for p, pat in enumerate(patterns):
        rows = np.flatnonzero(inv == p)
        n = int(pat.sum())
        meth = method if method != "auto" else ("direct" if n <= _MAX_DIRECT else "neighbors")
        mu, vv = _krige_core(cov, all_xyz[pat], V[np.ix_(rows, np.flatnonzero(pat))].T, tgt_xyz,
                             method=meth, neighbors=neighbors, cutoff=cutoff, want_var=return_std)
        mean[rows] = mu
        if return_std:
            var[rows] = vv
    if not return_std:
        return mean, None
    if include_nugget:
        var += cov.nugget
    return mean, np.sqrt(np.maximum(var, 0.0))


def krige(
    cov: ResidualCovariance,
    region: Region,
    cells: Any,
    values: Any,
    *,
    targets: Any = None,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Simple kriging of the residual at ``targets`` (default all L cells) from ``values`` at
    ``cells`` (``(n,)``, NaN = not observed): mean and std ``(n_targets,)``; see
    :func:`krige_many` for the options (std is ``None`` when ``return_std=False``)."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1:
        raise DataError(f"values must be 1-D (one per cell), got shape {v.shape}")
    mean, std = krige_many(cov, region, cells, v[None, :], targets=targets, neighbors=neighbors,
                           method=method, cutoff=cutoff, include_nugget=include_nugget,
                           return_std=return_std)
    return mean[0], (None if std is None else std[0])


# ---------------------------------------------------------------------------- trend + residual
def _observations(Y: Any, cells: Any, values: Any, region: Region, cov: Any):
    cov = _check_cov(cov)
    if not isinstance(region, Region):
        raise DataError(f"region must be a Region, got {type(region).__name__}")
    Y = as_factor_matrix(Y, region)
    cells = region.check_cells(np.ravel(cells), "cells")
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size != cells.size:
        raise DataError(f"values has {v.size} entries, cells has {cells.size}")
    if np.isinf(v).any():
        raise DataError("values has infinite entries")
    if np.unique(cells).size != cells.size:
        raise DataError("cells has repeated cell indices: give one value per observed cell")
    ok = np.isfinite(v)
    return cov, Y, cells[ok], v[ok]


def gls_fold_in(
    Y: Any, cells: Any, values: Any, cov: ResidualCovariance, region: Region, ridge: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised-least-squares fold-in of a new snapshot under the GP residual covariance.

    ``x = (Y_S C^-1 Y_S^T + ridge I)^-1 Y_S C^-1 d_S`` with ``C = K_SS + nugget I`` (``n x n``,
    one Cholesky), and ``cov_x = (Y_S C^-1 Y_S^T + ridge I)^-1``, the covariance of ``x`` (the
    posterior covariance under a ``N(0, I / ridge)`` prior when ``ridge > 0``). ``Y`` is
    ``(k, L)``; NaN values are ignored. Returns ``x (k,)`` and ``cov_x (k, k)``.
    """
    cov, Y, cells, d = _observations(Y, cells, values, region, cov)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    x, cov_x = _gls(Y, cells, d, cov, region, ridge)
    return x, cov_x


def _gls(Y, cells, d, cov, region, ridge):
    """GLS fold-in: the posterior of :class:`~lrm_cvx.glrm.posterior.LatentPosterior` with the
    GP residual and the prior precision ``ridge I`` (flat at 0). Returns ``(x, cov_x)``."""
    from .glrm.posterior import LatentPosterior, ObservationModel

    k = Y.shape[0]
    if cells.size == 0 and ridge == 0:
        raise ModelError("gls_fold_in needs at least one observation or ridge > 0")
    obs = ObservationModel(Y, spatial_cov=cov, region=region)
    post = LatentPosterior.from_moments(obs, precision=ridge * np.eye(k)).update(cells, d)
    if not post.is_proper:
        raise ModelError(
            f"the GLS normal matrix is singular: {cells.size} observations do not determine "
            f"rank {k} factors (observe more cells or set ridge > 0)")
    return post.mean, post.cov


def residual_correction(
    Y: Any,
    cells: Any,
    values: Any,
    cov: ResidualCovariance,
    region: Region,
    *,
    fold_in: Literal["gls", "ols"] = "gls",
    targets: Any = None,
    ridge: float = 0.0,
    neighbors: int = 32,
    method: Literal["auto", "direct", "neighbors"] = "auto",
    cutoff: float | None = 1e-6,
    include_nugget: bool = False,
    return_std: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Prediction ``Y_t^T x + kriged residual`` at ``targets`` (default all cells) and its std.

    ``fold_in="gls"`` (universal kriging): ``x`` from :func:`gls_fold_in`, and the std includes
    the trend-estimation term, so it is the exact BLUP error under the model. ``fold_in="ols"``
    (regression kriging): the paper's fold-in ``x = (Y_S Y_S^T + ridge I)^-1 Y_S d_S``, then
    simple kriging of ``d_S - Y_S^T x``; its std is the residual's kriging std only (the trend is
    treated as known, so it is optimistic). NaN values are ignored.
    """
    cov, Y, cells, d = _observations(Y, cells, values, region, cov)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    if fold_in not in ("gls", "ols"):
        raise ModelError(f"fold_in must be 'gls' or 'ols', got {fold_in!r}")
    cov, _, tg, neighbors, cutoff, method = _prepare(
        cov, region, cells, targets, neighbors, cutoff, method)
    k = Y.shape[0]
    Ys = Y[:, cells]
    if fold_in == "gls":
        x, cov_x = _gls(Y, cells, d, cov, region, ridge)
    else:
        G = Ys @ Ys.T + ridge * np.eye(k)
        x, *_ = np.linalg.lstsq(G, Ys @ d, rcond=None)
        cov_x = None
    res = d - Ys.T @ x
    n = cells.size
    meth = method if method != "auto" else ("direct" if n <= _MAX_DIRECT else "neighbors")
    trend = fold_in == "gls"
    mu, var = _krige_core(
        cov, _coords(region, cov.metric, cells), res[:, None], _coords(region, cov.metric, tg),
        method=meth, neighbors=neighbors, cutoff=cutoff, want_var=return_std,
        Ys=Ys if trend else None, Yt=(lambda sel: Y[:, tg[sel]]) if trend else None, cov_x=cov_x,
    )
    pred = Y[:, tg].T @ x + mu[0]
    if not return_std:
        return pred, None
    if include_nugget:
        var = var + cov.nugget
    return pred, np.sqrt(np.maximum(var, 0.0))
