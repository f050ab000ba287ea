"""A planted low-rank field, plus the writers of the real file formats, at any size.

:func:`synthetic_field` builds an NDVI-like ``(time, lat, lon)`` DataArray whose noise-free part
is exactly rank ``k`` (``X.T @ Y``), with a fixed land mask and spatially correlated cloud gaps,
so tests and benchmarks know the truth. The writers live beside their readers and are re-exported
here: :func:`write_ndvi_cdr` (``io/ndvi.py``, daily NOAA CDR NetCDF files) and
:func:`write_image_stack` (``io/imagery.py``, Worldview-style RGB snapshots).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from .._validation import as_generator, check_positive
from ..errors import DataError
from .imagery import write_image_stack
from .ndvi import write_ndvi_cdr

__all__ = ["synthetic_field", "synthetic_dynamic_field", "cloud_gaps", "write_ndvi_cdr",
           "write_image_stack"]

_CHUNK = 8  # time steps generated per matrix product


# --------------------------------------------------------------------------- smooth fields
def _rbf_basis(n: int, spacing: float) -> np.ndarray:
    """``(n, g)`` float32 Gaussian bumps on ``[0, 1]`` every ``spacing``; rows unit L2 norm.

    ``A @ G @ B.T`` with ``G`` iid N(0, 1) is then a smooth random field whose value at every
    pixel is exactly N(0, 1) (the rows have unit norm), at the cost of two small matrix products.
    """
    centres = np.arange(-spacing, 1.0 + 1.5 * spacing, spacing)
    u = (np.arange(n) + 0.5) / n
    basis = np.exp(-0.5 * ((u[:, None] - centres[None, :]) / spacing) ** 2)
    basis /= np.linalg.norm(basis, axis=1, keepdims=True)
    return basis.astype(np.float32)


def _smooth_field(rng: np.random.Generator, ay: np.ndarray, ax: np.ndarray) -> np.ndarray:
    """One smooth standard-normal ``(ny, nx)`` float32 field on the bases ``ay``, ``ax``."""
    g = rng.standard_normal((ay.shape[1], ax.shape[1]), dtype=np.float32)
    return (ay @ g) @ ax.T


def _time_factors(rng: np.random.Generator, rank: int, n_times: int) -> np.ndarray:
    """``(rank, T)`` float64: a level with a slow trend, then seasonal modes with slow drifts."""
    t = np.arange(n_times, dtype=np.float64)
    years = t / 365.25
    X = np.empty((rank, n_times))
    X[0] = 1.0 + rng.uniform(-0.05, 0.05) * years
    for k in range(1, rank):
        harmonic = 1 + (k - 1) // 2 % 2  # annual, annual, semi-annual, semi-annual, ...
        phase = rng.uniform(0, 2 * np.pi)
        walk = np.cumsum(rng.standard_normal(n_times)) / np.sqrt(max(n_times, 1))
        X[k] = np.sin(2 * np.pi * harmonic * years + phase) + 0.5 * walk
        X[k] /= max(np.abs(X[k]).max(), 1e-12)
    return X


def _grid(n: int, lo: float, hi: float, descending: bool) -> np.ndarray:
    step = (hi - lo) / n
    centres = lo + (np.arange(n) + 0.5) * step
    return centres[::-1].copy() if descending else centres


class _Clouds:
    """Moving cloud cover on a grid: a smooth standard-normal field on the bases ``ay``
    ``(ny, gy)``, ``ax`` ``(nx, gx)`` (:func:`_rbf_basis`) that evolves as an AR(1) of lag-one
    correlation ``rho`` from one snapshot to the next; the cells where it is highest are cloudy.
    One draw of ``rng`` at construction and one per :meth:`advance`, so a caller interleaving
    other draws keeps its random stream."""

    def __init__(self, rng: np.random.Generator, ay: np.ndarray, ax: np.ndarray,
                 rho: float) -> None:
        self.rng, self.rho, self.ay, self.ax = rng, np.float32(rho), ay, ax
        self.g = rng.standard_normal((self.ay.shape[1], self.ax.shape[1]), dtype=np.float32)

    def advance(self) -> None:
        """The next snapshot's cover (AR(1) step of the underlying white field)."""
        self.g *= self.rho
        self.g += np.sqrt(1 - self.rho * self.rho) * self.rng.standard_normal(
            self.g.shape, dtype=np.float32)

    def cover(self) -> np.ndarray:
        """``(ny * nx,)`` float32: today's cloud field (standard normal at every cell)."""
        return ((self.ay @ self.g) @ self.ax.T).ravel()


FIELD_OPTIONS: dict[str, Any] = {
    "lat_range": (-35.0, 37.5), "lon_range": (-18.0, 52.0), "start_date": "2013-01-01",
    "dtype": np.float32, "name": "ndvi", "time_factors": None, "clip": True,
    "mode_amplitudes": None,
}
"""The less common options of :func:`synthetic_field` and their defaults."""


def synthetic_field(
    n_times: int,
    shape: tuple[int, int],
    rank: int = 5,
    *,
    missing: float = 0.5,
    noise: float = 0.05,
    land_fraction: float = 0.7,
    seed: Any = 0,
    return_truth: bool = False,
    **options: Any,
) -> xr.DataArray | tuple[xr.DataArray, dict[str, Any]]:
    """A planted rank-``rank`` NDVI-like field ``(time, lat, lon)`` with land mask and cloud gaps.

    The noise-free field is ``X.T @ Y``: ``Y`` has ``rank`` smooth spatial modes (mode 0 a base
    greenness in about [0.1, 0.8], others +-0.2 down to +-0.05), ``X`` ``(rank, T)`` a level with
    a slow trend and seasonal sinusoids (random phases, annual and semi-annual) with slow random
    drifts. Gaussian noise of std ``noise`` is added and values are clipped to [-1, 1] (unless
    ``clip=False``: then the field is exactly low rank plus noise). Cells off
    a smooth random land mask (``land_fraction`` of the grid) are always NaN; on land, thresholded
    smooth random fields that evolve from day to day (AR(1), correlation 0.6) hide ``missing`` of
    the cells each day (exactly, up to one cell; estimated from a subsample on large grids).

    Grid: ``lat`` descending (north first, like the CDR), ``lon`` ascending, cell centres of
    ``shape`` equal cells spanning ``lat_range`` x ``lon_range``; ``time`` daily from
    ``start_date``. Built one chunk of days at a time into one preallocated array, so memory is
    about the output's size (paper scale 310 x 1500 x 1400: 2.6 GB float32).

    ``time_factors`` ``(rank, n_times)``: use these as ``X`` instead of the built-in level +
    seasonal factors (e.g. a planted AR(1) process, :func:`synthetic_dynamic_field`).
    ``mode_amplitudes`` ``(rank - 1,)``: the max-abs amplitudes of modes ``1..rank-1``
    (default ``0.2 x 0.6^(k-1)``, floored at 0.05); e.g. equal amplitudes give modes of
    comparable weight.

    With ``return_truth`` also returns ``{"X": (rank, T) float64, "Y": (rank, ny, nx) float32,
    "land_mask": (ny, nx) bool, "noise": noise}``; ``X.T @ Y`` is the noise-free field.

    ``options`` (keywords, defaults in :data:`FIELD_OPTIONS`): ``lat_range`` / ``lon_range``
    (degrees), ``start_date``, ``dtype`` (a float dtype), ``name`` (of the DataArray),
    ``time_factors``, ``clip``, ``mode_amplitudes`` as above.
    """
    unknown = sorted(set(options) - set(FIELD_OPTIONS))
    if unknown:
        raise TypeError(f"synthetic_field() got unexpected keyword argument(s) {unknown}; "
                        f"its options are {sorted(FIELD_OPTIONS)}")
    opts = {**FIELD_OPTIONS, **options}
    lat_range, lon_range, start_date = opts["lat_range"], opts["lon_range"], opts["start_date"]
    dtype, name, time_factors = opts["dtype"], opts["name"], opts["time_factors"]
    clip, mode_amplitudes = opts["clip"], opts["mode_amplitudes"]
    n_times = _check_int(n_times, "n_times", 1)
    try:
        ny, nx = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise DataError(f"shape must be (ny, nx), got {shape!r}") from None
    if ny < 1 or nx < 1:
        raise DataError(f"shape must be positive, got {shape!r}")
    rank = _check_int(rank, "rank", 1)
    missing = _check_fraction(missing, "missing")
    land_fraction = _check_fraction(land_fraction, "land_fraction")
    noise = check_positive(noise, "noise", numbers_only=True)
    if land_fraction == 0.0:
        raise DataError("land_fraction must be > 0: the field would be all NaN")
    dtype = np.dtype(dtype)
    if dtype.kind != "f":
        raise DataError(f"dtype must be a float dtype, got {dtype}")
    try:
        start = pd.Timestamp(start_date)
    except (TypeError, ValueError):
        raise DataError(f"start_date must be a date, got {start_date!r}") from None

    rng = as_generator(seed, "seed", error=DataError)
    # spatial modes, land mask, time factors: small
    ay_m, ax_m = _rbf_basis(ny, 0.2), _rbf_basis(nx, 0.2)
    ay_f, ax_f = _rbf_basis(ny, 0.08), _rbf_basis(nx, 0.08)
    Y = np.empty((rank, ny, nx), dtype=np.float32)
    base = _smooth_field(rng, ay_m, ax_m)
    Y[0] = 0.45 + 0.35 * np.tanh(0.8 * base)
    if mode_amplitudes is None:
        amplitudes = np.maximum(0.2 * 0.6 ** np.arange(rank - 1), 0.05)
    else:
        amplitudes = np.asarray(mode_amplitudes, dtype=np.float64).ravel()
        if amplitudes.shape != (rank - 1,) or not np.all(np.isfinite(amplitudes)) or np.any(
                amplitudes <= 0):
            raise DataError(f"mode_amplitudes must be {rank - 1} finite numbers > 0, got "
                            f"{mode_amplitudes!r}")
    for k in range(1, rank):
        mode = _smooth_field(rng, ay_f if k % 2 else ay_m, ax_f if k % 2 else ax_m)
        mode /= max(float(np.abs(mode).max()), 1e-12)
        Y[k] = amplitudes[k - 1] * mode
    if time_factors is None:
        X = _time_factors(rng, rank, n_times)
    else:
        X = np.asarray(time_factors, dtype=np.float64)
        if X.shape != (rank, n_times) or not np.all(np.isfinite(X)):
            raise DataError(f"time_factors must be a finite ({rank}, {n_times}) array, got "
                            f"shape {X.shape}")

    land_field = _smooth_field(rng, _rbf_basis(ny, 0.1), _rbf_basis(nx, 0.1))
    land = _top_fraction(land_field, land_fraction)
    land_idx = np.flatnonzero(land.ravel())

    out = np.empty((n_times, ny, nx), dtype=dtype)
    flat_out = out.reshape(n_times, ny * nx)
    Yf = Y.reshape(rank, ny * nx)
    Xc = X.astype(np.float32)
    clouds = _Clouds(rng, _rbf_basis(ny, 0.04), _rbf_basis(nx, 0.04), 0.6)
    sub = land_idx[:: max(1, land_idx.size // 200_000)]
    noise32 = np.float32(noise)
    off_land = ~land.ravel()
    buf = np.empty((min(_CHUNK, n_times), ny * nx), dtype=np.float32)
    for t0 in range(0, n_times, _CHUNK):
        t1 = min(t0 + _CHUNK, n_times)
        chunk = buf[: t1 - t0]
        np.matmul(Xc[:, t0:t1].T, Yf, out=chunk)
        for i, t in enumerate(range(t0, t1)):
            row = chunk[i]
            if noise32 > 0:
                row += noise32 * rng.standard_normal(ny * nx, dtype=np.float32)
            if clip:
                np.clip(row, -1.0, 1.0, out=row)
            if t > 0:
                clouds.advance()
            if missing > 0:
                cloud = clouds.cover()
                if missing >= 1:
                    row[:] = np.nan
                else:
                    if sub.size == land_idx.size:
                        threshold = np.quantile(cloud[land_idx], 1.0 - missing)
                    else:
                        threshold = np.quantile(cloud[sub], 1.0 - missing)
                    row[cloud > threshold] = np.nan
            row[off_land] = np.nan
            flat_out[t] = row
    del buf

    lat = _grid(ny, float(lat_range[0]), float(lat_range[1]), descending=True)
    lon = _grid(nx, float(lon_range[0]), float(lon_range[1]), descending=False)
    da = xr.DataArray(
        out,
        dims=("time", "lat", "lon"),
        coords={
            "time": ("time", pd.date_range(start, periods=n_times, freq="D").values.astype(
                "datetime64[ns]"), {"standard_name": "time", "long_name": "time"}),
            "lat": ("lat", lat, {"units": "degrees_north", "standard_name": "latitude",
                                 "long_name": "latitude"}),
            "lon": ("lon", lon, {"units": "degrees_east", "standard_name": "longitude",
                                 "long_name": "longitude"}),
        },
        name=name,
        attrs={
            "units": "1",
            "long_name": "synthetic normalized difference vegetation index",
            "valid_min": -1.0,
            "valid_max": 1.0,
            "source": "lrm_cvx.io.samples.synthetic_field",
            "comment": (
                f"planted rank-{rank} field plus Gaussian noise (std {noise:g}); "
                f"NaN off land ({land_fraction:g} of the grid) and under synthetic "
                f"clouds ({missing:g} of land cells each day); seed {seed!r}"
            ),
        },
    )
    if return_truth:
        truth = {"X": X, "Y": Y, "land_mask": land, "noise": noise}
        return da, truth
    return da


def cloud_gaps(data: xr.DataArray, missing: float, *, size: float = 3.0,
               correlation: float = 0.6, seed: Any = 0) -> xr.DataArray:
    """``data`` ``(time, y, x)`` with moving clouds: in each snapshot, ``missing`` of the cells
    that hold a value (rounded to a whole cell) are set to NaN where a smooth random cloud
    field is highest. The field is made of Gaussian bumps every ``size`` cells (so clouds are a
    few ``size`` across) and evolves as an AR(1) of lag-one ``correlation`` between snapshots,
    the generator of :func:`synthetic_field`'s gaps. For testing what a method does on real
    values under realistic missingness (spatially clustered, moving, missing at random). A new
    array (``data`` is not modified), its attrs kept with a line added to ``history``;
    deterministic given ``seed``."""
    if not isinstance(data, xr.DataArray) or data.ndim != 3:
        raise DataError(f"data must be a (time, y, x) DataArray, got "
                        f"{type(data).__name__} with {getattr(data, 'ndim', '?')} dims")
    if data.dtype.kind != "f":
        raise DataError(f"data must hold floats (NaN marks a gap), got dtype {data.dtype}")
    missing = _check_fraction(missing, "missing", below_one=True)
    correlation = _check_fraction(correlation, "correlation", below_one=True)
    size = check_positive(size, "size (cells)", strict=True, numbers_only=True)
    T, ny, nx = data.shape
    rng = as_generator(seed, "seed", error=DataError)
    clouds = _Clouds(rng, _rbf_basis(ny, size / ny), _rbf_basis(nx, size / nx),
                     correlation)
    values = np.array(data.values, order="C", copy=True)
    flat = values.reshape(T, ny * nx)  # a view: C order
    for t in range(T):
        if t > 0:
            clouds.advance()
        valid = np.flatnonzero(np.isfinite(flat[t]))
        n_hide = int(round(missing * valid.size))
        if n_hide:
            cover = clouds.cover()[valid]
            flat[t, valid[np.argsort(-cover, kind="stable")[:n_hide]]] = np.nan
    out = data.copy(data=values)
    note = (f"cloud_gaps: {missing:g} of each snapshot's values hidden by moving clouds "
            f"(size {size:g} cells, correlation {correlation:g}, seed {seed!r})")
    out.attrs["history"] = "\n".join(filter(None, [str(data.attrs.get("history", "")), note]))
    return out


def _stable_dynamics(rng: np.random.Generator, rank: int) -> np.ndarray:
    """A random symmetric ``(rank, rank)`` matrix with eigenvalues in [0.6, 0.95]."""
    R, _ = np.linalg.qr(rng.standard_normal((rank, rank)))
    return (R * rng.uniform(0.6, 0.95, rank)) @ R.T


def synthetic_dynamic_field(
    n_times: int,
    shape: tuple[int, int],
    rank: int = 3,
    *,
    A: Any = None,
    Q: Any = None,
    seasonal_period: int | None = None,
    seasonal_amplitude: float = 0.5,
    trend: float | tuple[float, float] = 0.0,
    freq: str = "D",
    missing: float = 0.5,
    noise: float = 0.02,
    seed: Any = 0,
    return_truth: bool = False,
    clip: bool = False,
    **field_options: Any,
) -> xr.DataArray | tuple[xr.DataArray, dict[str, Any]]:
    """A planted rank-``rank`` field whose latent columns follow known AR(1) dynamics.

    ``x_t = mu + s_t + f_t + z_t``, ``z_t = A z_{t-1} + w_t``, ``w_t ~ N(0, Q)``, ``z_0`` drawn
    from the stationary distribution; ``mu = (1, 0, ..., 0)`` (mode 0 of :func:`synthetic_field`
    is the base level), ``s_t`` a seasonal cycle of ``seasonal_period`` steps (random phase per
    component, amplitude ``seasonal_amplitude``; level mode excluded) or 0, ``f_t`` a forced
    trend on mode 1 (a warming record's): ``trend = amount`` or ``(amount, onset)``, 0 until
    the fraction ``onset`` of the record (default 0.5), then a quadratic ramp reaching
    ``amount`` (latent units; the stationary std is about 0.32) at the last snapshot, so the
    last snapshots lie beyond every earlier one. Defaults: ``A``
    symmetric with eigenvalues in [0.6, 0.95] (strong persistence), ``Q = 0.1 (I - A A^T)``
    (stationary covariance ``0.1 I`` when ``A`` is symmetric). The rest (spatial modes,
    land mask, clouds, noise) is :func:`synthetic_field` with these ``time_factors``; ``freq``
    ``"D"`` (daily), ``"MS"`` (monthly, month starts) or ``"YS"`` (yearly, year starts) sets
    the time coordinate. Values are
    not clipped (``clip=False``, unlike :func:`synthetic_field`): the field is exactly the planted
    linear-Gaussian model plus noise, so the dynamics are recoverable from it.

    With ``return_truth`` also returns the truth of :func:`synthetic_field` plus ``"A"``,
    ``"Q"``, ``"mu"``, ``"seasonal"`` ``(rank, T)``, ``"trend"`` ``(rank, T)`` and ``"Z"``
    ``(rank, T)`` (the AR part).
    """
    n_times = _check_int(n_times, "n_times", 1)
    rank = _check_int(rank, "rank", 1)
    rng = as_generator(seed, "seed", error=DataError)
    if A is None:
        A = _stable_dynamics(rng, rank)
    A = np.asarray(A, dtype=np.float64)
    if A.shape != (rank, rank) or not np.all(np.isfinite(A)):
        raise DataError(f"A must be a finite ({rank}, {rank}) matrix, got shape {A.shape}")
    if np.max(np.abs(np.linalg.eigvals(A))) >= 1:
        raise DataError("A must be stable (spectral radius < 1)")
    if Q is None:
        Q = 0.1 * (np.eye(rank) - A @ A.T)  # stationary covariance 0.1 I for a symmetric A
        Q = 0.5 * (Q + Q.T)
    Q = np.asarray(Q, dtype=np.float64)
    if Q.shape != (rank, rank) or not np.all(np.isfinite(Q)):
        raise DataError(f"Q must be a finite ({rank}, {rank}) matrix, got shape {Q.shape}")
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    if w.min() < -1e-12 * max(w.max(), 1e-300):
        raise DataError("Q must be positive semi-definite")
    Qh = V * np.sqrt(np.maximum(w, 0.0))
    if freq not in ("D", "MS", "YS"):
        raise DataError(f"freq must be 'D', 'MS' or 'YS', got {freq!r}")
    try:
        trend, onset = (float(trend), 0.5) if np.ndim(trend) == 0 else map(float, trend)
    except (TypeError, ValueError):  # not numbers, or not exactly two of them
        raise DataError(f"trend must be a number or (amount, onset), got {trend!r}") from None
    if not np.isfinite(trend):
        raise DataError(f"trend must be a finite number, got {trend!r}")
    if not 0.0 <= onset < 1.0:
        raise DataError(f"trend's onset must be in [0, 1), got {onset!r}")
    if trend != 0.0 and rank < 2:
        raise DataError("trend needs rank >= 2 (it drives mode 1; mode 0 is the base level)")
    import scipy.linalg

    S0 = scipy.linalg.solve_discrete_lyapunov(A, Q)
    w0, V0 = np.linalg.eigh(0.5 * (S0 + S0.T))
    Z = np.empty((rank, n_times))
    z = (V0 * np.sqrt(np.maximum(w0, 0.0))) @ rng.standard_normal(rank)
    for t in range(n_times):  # a recursion over time (few steps), not over cells
        if t > 0:
            z = A @ z + Qh @ rng.standard_normal(rank)
        Z[:, t] = z
    mu = np.zeros(rank)
    mu[0] = 1.0
    seasonal = np.zeros((rank, n_times))
    if seasonal_period is not None:
        period = _check_int(seasonal_period, "seasonal_period", 2)
        phase = rng.uniform(0, 2 * np.pi, rank)
        seasonal = float(seasonal_amplitude) * np.sin(
            2 * np.pi * np.arange(n_times)[None, :] / period + phase[:, None])
        seasonal[0] = 0.0
    forced = np.zeros((rank, n_times))
    if trend != 0.0:
        t0 = onset * (n_times - 1)
        ramp = np.clip((np.arange(n_times) - t0) / max(n_times - 1 - t0, 1e-12), 0.0, None)
        forced[1] = trend * ramp ** 2
    X = mu[:, None] + seasonal + forced + Z
    out = synthetic_field(n_times, shape, rank, missing=missing, noise=noise, seed=rng,
                          return_truth=True, time_factors=X, clip=clip, **field_options)
    da, truth = out
    if freq != "D":
        start = pd.Timestamp(field_options.get("start_date", "2013-01-01"))
        da = da.assign_coords(time=("time", pd.date_range(start, periods=n_times, freq=freq)
                                    .values.astype("datetime64[ns]"), da.time.attrs))
    da.attrs["source"] = "lrm_cvx.io.samples.synthetic_dynamic_field"
    da.attrs["comment"] = (  # the caller's seed, not the shared Generator's address
        da.attrs["comment"].replace(f"seed {rng!r}", f"seed {seed!r}")
        + f"; latent AR(1) dynamics, seasonal period {seasonal_period}"
        + (f"; forced trend {trend:g} on mode 1 from {onset:g} of the record" if trend else ""))
    if return_truth:
        truth.update(A=A, Q=Q, mu=mu, seasonal=seasonal, trend=forced, Z=Z)
        return da, truth
    return da


def _top_fraction(field: np.ndarray, fraction: float) -> np.ndarray:
    """Boolean mask of the ``round(fraction * size)`` largest entries (at least one); ties low."""
    flat = field.ravel()
    n = max(1, int(round(fraction * flat.size)))
    order = np.argsort(-flat, kind="stable")[:n]
    mask = np.zeros(flat.size, dtype=bool)
    mask[order] = True
    return mask.reshape(field.shape)


def _check_fraction(value: Any, name: str, *, below_one: bool = False) -> float:
    """``value`` as a float in [0, 1] ([0, 1) when ``below_one``), else a DataError naming it
    (a string, None or a bool included: not converted)."""
    v = check_positive(value, name, numbers_only=True)
    if v > 1.0 or (below_one and v == 1.0):
        raise DataError(f"{name} must be in [0, {'1)' if below_one else '1]'}, got {value!r}")
    return v


def _check_int(value: Any, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise DataError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)
