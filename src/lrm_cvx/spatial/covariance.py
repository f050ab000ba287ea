"""The GP residual model: covariance functions, the empirical semivariogram and its fit.

``C(d) = sill * rho(d / range) + nugget * [d == 0]`` between cells at distance ``d`` (grid units
or great-circle km, see the package docstring); :func:`fit_residual_covariance` fits it to a
model's training residuals. :func:`cell_xyz` and :func:`arc_distance` place cells so that
KD-tree chord distances map to the metric's distances (the kriging and the GP criterion share
them).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Literal

import numpy as np
from scipy.optimize import brentq, least_squares

from .._validation import as_generator, check_positive
from ..errors import DataError, ModelError, SolverError
from ..region import EARTH_RADIUS_KM, Region
from ..registry import Registry

__all__ = ["MODELS", "KERNEL_REGISTRY", "ResidualCovariance", "EmpiricalVariogram",
           "correlation", "empirical_variogram", "fit_residual_covariance", "cell_xyz",
           "arc_distance", "chord_distance", "cell_size", "cell_semivariance",
           "axis_variograms", "estimate_anisotropy", "anisotropy_from_variograms",
           "check_anisotropy",
           "AXIS_LAGS", "MAX_ANISOTROPY"]

Model = Literal["exponential", "matern32", "matern52", "gaussian"]
Metric = Literal["grid", "km"]
_METRICS = ("grid", "km")
_SQRT3 = np.sqrt(3.0)
_SQRT5 = np.sqrt(5.0)
_ATTR_PREFIX = "spatial_"


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
    """A stationary covariance ``C(d) = sill rho(d / range) + nugget [d == 0]``, isotropic or
    geometrically anisotropic along the grid's axes.

    Parameters
    ----------
    model : ``"exponential"``, ``"matern32"``, ``"matern52"`` or ``"gaussian"``.
    sill : partial sill, the spatially predictable variance (data units squared), ``>= 0``.
    range : scale parameter ``> 0`` in ``metric`` units (grid cells or km).
    nugget : variance of the spatially unpredictable part (noise), ``>= 0``.
    metric : ``"grid"`` (grid units) or ``"km"`` (great-circle kilometres).
    anisotropy : the range along the grid's columns (east-west) over the range along its rows
        (north-south, ``range``); ``d = sqrt(dr^2 + (dc / anisotropy)^2)`` for grid offsets
        ``(dr, dc)``. 1 (the default) is isotropic; another value needs ``metric="grid"``.
        Zonal bands of the atmosphere and ocean make residuals correlate further east-west
        than north-south (:func:`estimate_anisotropy`).
    variogram : the empirical variogram it was fitted to, if any (not compared, not stored).
    """

    model: str
    sill: float
    range: float
    nugget: float = 0.0
    metric: str = "grid"
    variogram: EmpiricalVariogram | None = field(default=None, compare=False, repr=False)
    anisotropy: float = 1.0

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
        object.__setattr__(self, "anisotropy", check_anisotropy(self.anisotropy, self.metric))

    # ------------------------------------------------------------------ geometry
    @property
    def is_isotropic(self) -> bool:
        """Whether the covariance is the same in every direction (``anisotropy == 1``)."""
        return self.anisotropy == 1.0

    def points(self, region: Region, cells: np.ndarray | None = None) -> np.ndarray:
        """:func:`cell_xyz` of ``cells`` with the columns shrunk by ``anisotropy``: their
        Euclidean distances are this covariance's distances (chords in km)."""
        return cell_xyz(region, self.metric, cells, self.anisotropy)

    def lattice(self, dr: Any, dc: Any) -> np.ndarray:
        """The spatial part (no nugget) at grid offsets ``dr`` (rows) and ``dc`` (columns),
        broadcast together (grid metric)."""
        dr = np.asarray(dr, dtype=np.float64)
        dc = np.asarray(dc, dtype=np.float64) / self.anisotropy
        return self.covariance(np.sqrt(dr * dr + dc * dc), nugget=False)

    def reach(self, rel: float) -> tuple[float, float]:
        """Grid half-widths ``(rows, columns)`` beyond which the spatial part is below
        ``rel * sill`` (:meth:`cutoff_distance` along each axis, grid metric)."""
        c = self.cutoff_distance(rel)
        return c, c * self.anisotropy

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

    def cell_semivariance(self, size: tuple[float, float] = (1.0, 1.0)) -> float:
        """Mean semivariance between two points of one ``size = (dy, dx)`` cell (metric units):
        the variance of a point value about its cell's mean (:func:`cell_semivariance`)."""
        return cell_semivariance(self, size)

    def cutoff_distance(self, rel: float = 1e-6) -> float:
        """Distance (metric units) beyond which the spatial covariance is below ``rel * sill``
        (north-south; :meth:`reach` gives both axes of an anisotropic covariance)."""
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
            f"{_ATTR_PREFIX}anisotropy": float(self.anisotropy),
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
            # isotropic files may lack the attribute
            anisotropy=float(np.asarray(attrs.get(f"{_ATTR_PREFIX}anisotropy", 1.0)).item()),
        )

    def __repr__(self) -> str:
        unit = "cells" if self.metric == "grid" else "km"
        aniso = "" if self.is_isotropic else f", anisotropy={self.anisotropy:.3g}"
        return (
            f"ResidualCovariance({self.model}, sill={self.sill:.4g}, range={self.range:.4g} "
            f"{unit}, nugget={self.nugget:.4g}{aniso})"
        )


# ---------------------------------------------------------------------------- geometry
def _check_metric(metric: str) -> str:
    if metric not in _METRICS:
        raise ModelError(f"metric must be 'grid' or 'km', got {metric!r}")
    return metric


def check_anisotropy(value: Any, metric: str = "grid") -> float:
    """``value`` as a finite anisotropy > 0 for ``metric`` (ModelError naming it otherwise)."""
    number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_))
    a = float(value) if number else np.nan
    if not (np.isfinite(a) and a > 0):
        raise ModelError(f"anisotropy must be a finite number > 0 (the east-west over the "
                         f"north-south range), got {value!r}")
    if a != 1.0 and metric != "grid":
        raise ModelError(f"anisotropy {a:g} needs metric='grid' (an anisotropic great-circle "
                         "covariance is not supported)")
    return a


def cell_xyz(region: Region, metric: str, cells: np.ndarray | None = None,
             anisotropy: float = 1.0) -> np.ndarray:
    """Point coordinates whose Euclidean distances map monotonically onto ``metric`` distances.

    ``grid``: ``(n, 2)`` (row, col / anisotropy). ``km``: ``(n, 3)`` points on a sphere of the
    Earth's radius (Euclidean = chord length; see :func:`arc_distance`).
    """
    gi = region.grid_index if cells is None else region.grid_index[cells]
    if metric == "grid":
        xy = gi.astype(np.float64)
        if anisotropy != 1.0:
            xy[:, 1] /= anisotropy
        return xy
    lat = np.radians(region.lat.values[gi[:, 0]])
    lon = np.radians(region.lon.values[gi[:, 1]])
    cl = np.cos(lat)
    return EARTH_RADIUS_KM * np.column_stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)])


def arc_distance(chord: np.ndarray, metric: str) -> np.ndarray:
    """Metric distance from the Euclidean distance between :func:`cell_xyz` points."""
    if metric == "grid":
        return chord
    return 2.0 * EARTH_RADIUS_KM * np.arcsin(np.clip(chord / (2.0 * EARTH_RADIUS_KM), 0.0, 1.0))


def chord_distance(d: float, metric: str) -> float:
    """Inverse of :func:`arc_distance` (infinite beyond half the circumference)."""
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
    diag = float(arc_distance(np.linalg.norm(xyz[0] - xyz[1]), "km"))
    return max(diag / 2.0, _min_step(region, "km"))


_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(24)


def cell_size(region: Region, metric: str) -> tuple[float, float]:
    """``(dy, dx)`` of a typical cell in ``metric`` units: ``(1, 1)`` in grid units; in km the
    median latitude / longitude spacing at the median cell latitude."""
    if _check_metric(metric) == "grid":
        return 1.0, 1.0
    lat = np.radians(np.asarray(region.lat.values, dtype=np.float64))
    lon = np.radians(np.asarray(region.lon.values, dtype=np.float64))
    dlat = float(np.median(np.abs(np.diff(lat)))) if lat.size > 1 else 0.0
    dlon = float(np.median(np.abs(np.diff(lon)))) if lon.size > 1 else 0.0
    dy = EARTH_RADIUS_KM * dlat
    dx = EARTH_RADIUS_KM * dlon * float(np.cos(np.radians(np.median(region.cell_lat))))
    step = _min_step(region, metric)
    return (dy if dy > 0 else step), (dx if dx > 0 else step)


def cell_semivariance(cov: ResidualCovariance, size: tuple[float, float] = (1.0, 1.0)) -> float:
    """``gamma_bar(v, v) = E gamma(|u - w|)`` for ``u``, ``w`` uniform in one ``(dy, dx)`` cell
    (the spatial part only; metric units): the variance of a point value about the mean of its
    cell under ``cov`` continued below the grid step (the change of support of geostatistics,
    Journel & Huijbregts 1978). Each coordinate difference has the triangular density
    ``2 (a - s) / a^2`` on ``[0, a]``; 24 x 24 Gauss-Legendre nodes (relative error < 1e-3 for
    the exponential's kink at 0)."""
    dy, dx = (float(v) for v in size)
    sy = 0.5 * dy * (_GL_NODES + 1.0)
    sx = 0.5 * dx * (_GL_NODES + 1.0)
    wy = _GL_WEIGHTS * 0.5 * dy * 2.0 * (dy - sy) / dy ** 2
    wx = _GL_WEIGHTS * 0.5 * dx * 2.0 * (dx - sx) / dx ** 2
    d = np.hypot(sy[:, None], sx[None, :] / cov.anisotropy)
    g = cov.sill * (1.0 - cov.correlation(d))
    return float(wy @ g @ wx)


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
    anisotropy: float = 1.0,
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
        cols = gi[i, 1] + np.rint(rad * np.cos(ang) * anisotropy).astype(np.int64)
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
            d = np.hypot(dg[:, 0], dg[:, 1] / anisotropy).astype(np.float64)
        else:
            chord = np.linalg.norm(cell_xyz(region, metric, i) - cell_xyz(region, metric, j),
                                   axis=1)
            d = arc_distance(chord, metric)
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
    anisotropy: float = 1.0,
) -> EmpiricalVariogram:
    """Binned Matheron semivariogram ``gamma(h) = mean of (r_t(i) - r_t(j))^2 / 2`` of ``(T, L)``
    residuals (NaN = missing) from at most ``max_pairs`` random same-time pairs within
    ``max_distance`` (default: half the region's diagonal). ``spacing="log"`` uses geometric bins
    from one grid step (short lags carry the range information); ``standardize`` divides each time
    by its standard deviation, then rescales gamma by the mean per-time variance. Empty bins are
    dropped. ``anisotropy`` (grid metric): distances ``sqrt(dr^2 + (dc / anisotropy)^2)``, the
    column offsets drawn that much longer. Deterministic given ``random_state``."""
    metric = _check_metric(metric)
    anisotropy = check_anisotropy(anisotropy, metric)
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
    d, half = _sample_pairs(r, region, metric, max_distance, max_pairs, spacing, rng, scale,
                            anisotropy)
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


def _fit_curve(model: str, h: np.ndarray, g: np.ndarray, w: np.ndarray,
               floor: float = 0.0) -> np.ndarray:
    """``(sill, range, nugget)`` of ``model``'s semivariogram fitted by weighted least squares
    (weights ``w``) to the semivariances ``g`` at lags ``h`` (both scaled to about 1), from
    three starting ranges, the nugget bounded below by ``floor``."""

    def resid(p: np.ndarray) -> np.ndarray:
        sill, rng_, nug = p
        return w * (nug + sill * (1.0 - correlation(model, h / rng_)) - g)

    upper = [10.0 * g.max() + 1.0, 10.0, 2.0 * g.max() + 1.0]
    nug0 = max(min(0.5 * g[0], 0.5 * g.max()), floor)
    sill0 = max(g.max() - nug0, 1e-3)
    return _best_fit(resid, [[sill0, r0, nug0] for r0 in _START_RANGES],
                     [0.0, 1e-3, floor], upper)


_START_RANGES = (0.05, 0.2, 1.0)  # starting ranges of the variogram fits (x the largest lag)


def _best_fit(resid: Any, starts: list, lower: list, upper: list) -> np.ndarray:
    """The parameters of the lowest-cost ``scipy.optimize.least_squares`` fit of ``resid``
    within the bounds over the starting points ``starts`` (the first wins ties)."""
    best = None
    for x0 in starts:
        sol = least_squares(resid, x0=x0, bounds=(lower, upper), method="trf", x_scale="jac",
                            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        if best is None or sol.cost < best.cost - 1e-15:
            best = sol
    return best.x


AXIS_LAGS = (1, 2, 3, 4, 6, 8, 11, 16, 23, 32)
"""Grid lags of the directional variograms :func:`estimate_anisotropy` fits."""
MAX_ANISOTROPY = 8.0
"""The estimated anisotropy is clipped to ``[1 / MAX_ANISOTROPY, MAX_ANISOTROPY]``."""
MIN_SPATIAL_SHARE = 0.05
"""Below this share of the total variance correlated one cell away (on both axes) the
anisotropy is 1: a nearly pure nugget has no ranges to compare."""
_AXIS_ENTRIES = 20_000_000  # residual entries read per lag and axis (rows are subsampled)


def axis_variograms(residuals: Any, region: Region,
                    lags: Any = AXIS_LAGS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directional semivariograms of ``(T, L)`` residuals along the grid's rows (north-south)
    and columns (east-west): ``(lags (K,), gamma (2, K), counts (2, K))`` over every pair of
    finite cells ``lag`` cells apart on one axis (the lags that fit the grid; evenly spaced
    rows are used when ``T * L`` is large)."""
    r = _as_residuals(residuals, region)
    ny, nx = region.shape
    lags = np.array([int(v) for v in lags if 0 < int(v) < max(ny, nx)], dtype=np.int64)
    n_rows = max(1, min(r.shape[0], _AXIS_ENTRIES // max(region.n_cells, 1)))
    rows = np.unique(np.linspace(0, r.shape[0] - 1, n_rows).round().astype(np.int64))
    gi = region.grid_index
    grid = np.full((ny, nx), np.nan)
    sums = np.zeros((2, lags.size))
    counts = np.zeros((2, lags.size))
    for t in rows:  # at most 20 residual snapshots in a fit's sample
        grid[gi[:, 0], gi[:, 1]] = r[t]
        for j, lag in enumerate(lags):
            for axis in (0, 1):
                if lag >= grid.shape[axis]:
                    continue
                d = grid[lag:] - grid[:-lag] if axis == 0 else grid[:, lag:] - grid[:, :-lag]
                ok = np.isfinite(d)
                sums[axis, j] += 0.5 * float(np.sum(d[ok] ** 2))
                counts[axis, j] += int(ok.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = sums / counts
    return lags, gamma, counts


def estimate_anisotropy(residuals: Any, region: Region, *, model: Model = "exponential",
                        lags: Any = AXIS_LAGS) -> float:
    """The east-west over the north-south range of ``model`` fitted jointly to the residuals'
    two directional variograms (:func:`axis_variograms`; one sill and one nugget, a range per
    axis; grid units), clipped to ``[1 / MAX_ANISOTROPY, MAX_ANISOTROPY]``; 1 when an axis has
    fewer than 3 lags with pairs, less than ``MIN_SPATIAL_SHARE`` of the variance is
    correlated one cell away, or a practical range is outside one cell to the axis's largest
    lag (the lags cannot measure it). The ratio of directional ranges is the classical estimate
    of a geometric anisotropy along known axes (Isaaks & Srivastava 1989, ch. 7); here the
    axes are the grid's, and sharing the sill and nugget keeps the two ranges comparable."""
    return anisotropy_from_variograms(*axis_variograms(residuals, region, lags), model=model)


def anisotropy_from_variograms(lag: np.ndarray, gamma: np.ndarray, counts: np.ndarray, *,
                               model: Model = "exponential") -> float:
    """:func:`estimate_anisotropy` from the directional variograms of :func:`axis_variograms`
    (computed once for every family ``spatial="auto"`` fits)."""
    model = KERNEL_REGISTRY.canonical(model, "model")
    ok = (counts > 0) & np.isfinite(gamma)
    if (ok.sum(axis=1) < 3).any():
        return 1.0
    g_scale = float(np.average(gamma[ok], weights=counts[ok]))
    if not g_scale > 0:
        return 1.0
    top = float(lag.max())
    h = [lag[ok[a]] / top for a in (0, 1)]
    g = [gamma[a][ok[a]] / g_scale for a in (0, 1)]
    w = [np.sqrt(counts[a][ok[a]] / counts[ok].sum()) for a in (0, 1)]

    def resid(p: np.ndarray) -> np.ndarray:
        sill, nug, r0, r1 = p
        return np.concatenate([w[a] * (nug + sill * (1.0 - correlation(model, h[a] / r)) - g[a])
                               for a, r in ((0, r0), (1, r1))])

    gmax = max(float(g[0].max()), float(g[1].max()))
    nug0 = 0.5 * min(float(g[0][0]), float(g[1][0]), gmax)
    x = _best_fit(resid, [[max(gmax - nug0, 1e-3), nug0, r0, r0] for r0 in _START_RANGES],
                  [0.0, 0.0, 1e-3, 1e-3], [10.0 * gmax + 1.0, 2.0 * gmax + 1.0, 10.0, 10.0])
    sill, nug, ranges = x[0], x[1], x[2:]
    # comparable ranges only: the correlated share one cell away is at least
    # MIN_SPATIAL_SHARE of the variance, and each axis's practical range (correlation 0.05)
    # lies between one cell and its largest lag (beyond, the lags seen cannot measure it)
    near = [sill * float(correlation(model, 1.0 / (r * top))) for r in ranges]
    reach = [r * top * _scaled_cutoff(model, 0.05) for r in ranges]
    tops = [float(lag[ok[a]].max()) for a in (0, 1)]
    if not (max(near) > MIN_SPATIAL_SHARE * (sill + nug)
            and all(1.0 <= e <= t for e, t in zip(reach, tops, strict=True))):
        return 1.0
    a = ranges[1] / ranges[0]
    return float(np.clip(a, 1.0 / MAX_ANISOTROPY, MAX_ANISOTROPY))


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
    min_nugget: float | Literal["cell"] | None = None,
    anisotropy: float = 1.0,
) -> ResidualCovariance:
    """Fit ``sill``, ``range`` and ``nugget`` of ``model`` to the residuals' empirical variogram.

    ``residuals`` is ``(T, L)`` (training data minus the low-rank reconstruction, NaN = missing).
    The binned semivariogram (:func:`empirical_variogram`) is fitted by
    ``scipy.optimize.least_squares`` with bin weights proportional to the pair counts, from three
    starting ranges (the best fit wins). The range is bounded to ``[1e-3, 10] * max_distance``:
    a range much beyond the largest lag is not identifiable. Deterministic given ``random_state``.
    ``anisotropy`` (grid metric): the fitted covariance's, fixed (distances as
    :class:`ResidualCovariance` measures them; ``range`` is then the north-south range).

    ``min_nugget``: a lower bound of the nugget (data units squared; None: 0). ``"cell"`` (what
    ``GLRM(spatial=...)`` uses) bounds it by the fitted covariance's own sub-cell semivariance
    (:func:`cell_semivariance` of a typical cell, :func:`cell_size`), refitted to a fixed point:
    a grid's variogram has no lag below one cell, so on smooth fields the fitted nugget
    collapses to 0 and the GP interpolates the
    samples exactly, with a zero predictive std at every sampled cell. A new measurement is a
    point value, which differs from its cell's modelled value by at least that sub-cell
    variation; the bound is > 0 whenever the sill is, is scale-free, and needs no other
    estimate (the GLRM's noise is the residual's *total* variance, sill plus nugget, so it cannot
    split them; cross-validated kriging and the variogram's intercept see no lag below a cell
    either and collapse with the fit).
    """
    model = KERNEL_REGISTRY.canonical(model, "model")
    vg = empirical_variogram(
        residuals, region, metric=metric, max_pairs=max_pairs, n_bins=n_bins,
        max_distance=max_distance, spacing=spacing, standardize=standardize,
        random_state=random_state, anisotropy=anisotropy,
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

    def fit(floor: float) -> np.ndarray:
        return _fit_curve(model, h, g, w, floor)

    def build(p: np.ndarray) -> ResidualCovariance:
        sill, rng_, nug = p
        if sill + nug <= 0:
            raise SolverError("the variogram fit (scipy least_squares) returned a zero "
                              "covariance")
        return ResidualCovariance(
            model=model, sill=float(sill * g_scale), range=float(rng_ * vg.max_distance),
            nugget=float(nug * g_scale), metric=vg.metric, variogram=vg,
            anisotropy=anisotropy)

    if isinstance(min_nugget, str):
        if min_nugget != "cell":
            raise ModelError(f"min_nugget must be a number >= 0, 'cell' or None, got "
                             f"{min_nugget!r}")
        size = cell_size(region, vg.metric)
        floor = 0.0
        for _ in range(20):  # fixed point: the bound is the sub-cell variation of the fit
            out = build(fit(floor / g_scale))
            need = out.cell_semivariance(size)
            if out.nugget > need * (1 + 1e-6) and floor == 0.0:
                return out  # the unconstrained fit already holds the bound
            if abs(need - floor) <= 1e-3 * need:
                break
            floor = 0.5 * (floor + need) if floor > 0 else need  # damped
        return out if out.nugget >= need else replace(out, nugget=need)
    floor = 0.0 if min_nugget is None else check_positive(min_nugget, "min_nugget",
                                                          error=ModelError)
    out = build(fit(floor / g_scale))
    return out if out.nugget >= floor else replace(out, nugget=floor)
