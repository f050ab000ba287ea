"""Temporal dynamics of the latent vectors: AR(1) and seasonal AR(1) on ``X``.

A fitted GLRM gives one latent column ``x_t (k,)`` per snapshot. For persistent monitoring the
columns are modelled as a linear-Gaussian process, so yesterday's posterior is today's prior:

* ``"ar1"``: ``x_t - mu = A (x_{t-1} - mu) + w_t``, ``w_t ~ N(0, Q)``;
* ``"seasonal"``: ``x_t - m_{s(t)} = A (x_{t-1} - m_{s(t-1)}) + w_t`` with ``m_s`` the mean of
  ``X`` over the snapshots of season ``s`` (month of year for monthly data, day of year for
  daily data; from the time coordinate, cftime calendars included).

Irregular time coordinates: the *step* is the median spacing of the fitted times. ``A`` and
``Q`` are estimated from the consecutive pairs whose spacing rounds to one step (other pairs are
left out), and a forecast ``n = max(1, round(dt / step))`` steps ahead uses ``A^n`` and
``Q_n = sum_{j<n} A^j Q A^j^T``. So monthly data (28-31 day months) count one step per month,
and a missed month counts two. Times are converted to days (datetime64 or cftime) or used as
plain numbers (a numeric or missing time coordinate: one unit = one number).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import DataError, ModelError
from ..registry import Registry

__all__ = ["Dynamics", "estimate_ar1", "estimate_seasonal", "TEMPORAL", "temporal_value",
           "time_numbers", "rts_smooth", "check_times", "seasons", "error_rows",
           "blend_moments", "foldin_covs", "kind_dynamics"]

TEMPORAL = Registry("temporal", ModelError)
"""The temporal models (``GLRM(temporal=...)``, ``evaluate``, campaigns, the CLI's
``--temporal``): the object is the estimator of the dynamics (None: snapshots independent).
Read through :func:`temporal_value`; ``ar1`` and ``seasonal`` are registered below their
estimators."""
TEMPORAL.register("none", None, description="snapshots independent: no dynamics (the paper's "
                  "model; pass `None`)", aliases=(None,))
MAX_RADIUS = 0.99  # spectral radius of A is forced below this
_MIN_SNAPSHOTS = 3
ERROR_ROWS = 64  # snapshots whose fold-in covariances average into the error covariance S_e


def error_rows(n_times: int) -> np.ndarray:
    """The (at most :data:`ERROR_ROWS`) evenly spaced snapshots whose fold-in covariances
    estimate the columns' error covariance ``S_e`` (same rows in memory and on dask)."""
    return np.unique(np.linspace(0, n_times - 1, min(n_times, ERROR_ROWS)).round().astype(int))


def foldin_covs(Y: np.ndarray, weights: Any, masks: Any) -> list[np.ndarray | None]:
    """``(Y_O W Y_O^T)^-1`` ``(k, k)`` per snapshot of the cells ``O`` of each row of ``masks``
    (bool ``(L,)`` rows, e.g. ``mask[t]`` for the :func:`error_rows`), ``W = diag(weights)``
    (inverse noise variances, ``(L,)`` or a scalar); None where the cells do not determine the
    latent vector (fewer than ``k`` or a condition number >= 1e12). One matrix product over
    blocks of cells for all snapshots (no per-snapshot fancy indexing of ``Y``)."""
    masks = list(masks)
    k, L = Y.shape
    iu = np.triu_indices(k)
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64), (L,))
    G = np.zeros((len(masks), iu[0].size))
    counts = np.zeros(len(masks), dtype=np.int64)
    for lo in range(0, L, 1 << 16):
        sl = slice(lo, min(L, lo + (1 << 16)))
        B = np.stack([np.asarray(m[sl], dtype=bool) for m in masks])
        G += B.astype(np.float64) @ (Y[iu[0], sl] * Y[iu[1], sl] * w[sl]).T
        counts += B.sum(axis=1)
    out: list[np.ndarray | None] = []
    for g, n in zip(G, counts, strict=True):
        Gm = np.zeros((k, k))
        Gm[iu] = g
        Gm = Gm + np.triu(Gm, 1).T
        if n < k or np.linalg.cond(Gm) >= 1e12:
            out.append(None)
            continue
        C = np.linalg.inv(Gm)
        out.append(0.5 * (C + C.T))
    return out


# ----------------------------------------------------------------------------- times
def _is_cftime(values: np.ndarray) -> bool:
    return values.dtype == object and values.size > 0 and hasattr(values.flat[0], "calendar")


def time_numbers(times: Any, name: str = "time") -> tuple[np.ndarray, str, str | None]:
    """``(t (T,) float64, kind, calendar)``: times in days since the first (``kind``
    ``"datetime"`` or ``"cftime"``) or as plain numbers (``kind`` ``"numeric"``)."""
    values = np.asarray(getattr(times, "values", times))
    if values.ndim != 1:
        raise DataError(f"{name} must be a 1-D time coordinate, got shape {values.shape}")
    if values.size == 0:
        return np.zeros(0), "numeric", None
    if np.issubdtype(values.dtype, np.datetime64):
        ns = values.astype("datetime64[ns]")
        if np.any(np.isnat(ns)):
            raise DataError(f"{name} has missing (NaT) entries")
        t = (ns - ns[0]).astype("timedelta64[ns]").astype(np.int64) / 86400e9
        return t.astype(np.float64), "datetime", None
    if _is_cftime(values):
        t0 = values[0]
        t = np.array([(v - t0).total_seconds() / 86400.0 for v in values])  # few times only
        return t, "cftime", str(t0.calendar)
    if np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating):
        t = values.astype(np.float64)
        if not np.all(np.isfinite(t)):
            raise DataError(f"{name} has missing or non-finite entries")
        return t - t[0], "numeric", None
    raise DataError(f"{name} must hold datetimes, cftime dates or numbers, got dtype "
                    f"{values.dtype}")


def check_times(times: Any, name: str = "time") -> np.ndarray:
    """Days (or numbers) of ``times`` after checking they are strictly increasing.

    Unsorted or duplicated times are refused (DataError naming the first offending position):
    the dynamics need one snapshot per time, in order; sort the data (``data.sortby("time")``)
    and merge duplicates first.
    """
    if times is None:
        raise DataError(f"{name}: temporal dynamics need a time coordinate, got none")
    t, _, _ = time_numbers(times, name)
    d = np.diff(t)
    if np.any(d == 0):
        i = int(np.flatnonzero(d == 0)[0]) + 1
        raise DataError(f"{name} is duplicated at position {i}: one snapshot per time is needed")
    if np.any(d < 0):
        i = int(np.flatnonzero(d < 0)[0]) + 1
        raise DataError(f"{name} is not sorted (position {i} is earlier than {i - 1}); sort the "
                        "data by time first")
    return t


def seasons(times: Any, season: str) -> np.ndarray:
    """Season index per time: ``"month"`` -> 0..11, ``"dayofyear"`` -> 0..365."""
    import xarray as xr

    values = np.asarray(getattr(times, "values", times))
    if season not in ("month", "dayofyear"):
        raise ModelError(f"unknown season {season!r}")
    if np.issubdtype(values.dtype, np.datetime64):  # numpy, no pandas round trip (the filter
        if season == "month":                        # asks once a step)
            return values.astype("datetime64[M]").astype(np.int64) % 12
        day = values.astype("datetime64[D]")
        return (day - day.astype("datetime64[Y]")).astype(np.int64)
    da = xr.DataArray(values, dims=("t",))
    if season == "month":
        return da.dt.month.values.astype(np.int64) - 1
    if season == "dayofyear":
        return da.dt.dayofyear.values.astype(np.int64) - 1
    raise ModelError(f"unknown season {season!r}")


def _years_per_season(times: Any, s: np.ndarray, n_seasons: int) -> np.ndarray:
    """Distinct years in which each season present in ``s`` is seen (a 6-hourly record of a
    few weeks sees each day of year 4 times, but in one year: no season to learn)."""
    import xarray as xr

    values = np.asarray(getattr(times, "values", times))
    years = xr.DataArray(values, dims=("t",)).dt.year.values.astype(np.int64)
    pairs = np.unique(s.astype(np.int64) * 100_000 + (years - years.min()))
    return np.bincount(pairs // 100_000, minlength=n_seasons)[np.unique(s)]


# ----------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class Dynamics:
    """Linear-Gaussian dynamics of the latent vector.

    ``x' - m(t') = A^n (x - m(t)) + w``, ``w ~ N(0, Q_n)``, ``n`` steps between ``t`` and ``t'``
    (module docstring). ``m(t)`` is ``mean`` for ``kind="ar1"`` and ``season_means[s(t)]`` for
    ``kind="seasonal"``. ``initial_mean`` / ``initial_cov`` are the belief at ``time`` (the
    last fitted snapshot). ``step`` is in days (or time-coordinate units for ``time_kind``
    ``"numeric"``).
    """

    kind: str
    A: np.ndarray                       # (k, k)
    Q: np.ndarray                       # (k, k) PSD
    mean: np.ndarray                    # (k,)
    initial_mean: np.ndarray            # (k,)
    initial_cov: np.ndarray             # (k, k)
    step: float = 1.0
    time_kind: str = "numeric"
    season: str | None = None           # "month" | "dayofyear" for kind="seasonal"
    season_means: np.ndarray | None = None   # (n_seasons, k)
    shrinkage: float = 0.0
    n_pairs: int = 0
    blend: float = 1.0                  # validated blend towards the memoryless prior
    time: Any = field(default=None, compare=False)  # time of the initial belief
    error_cov: np.ndarray | None = field(default=None, compare=False)  # (k, k) S_e corrected for

    def __post_init__(self) -> None:
        k = np.asarray(self.A).shape[0]
        for name, shape in (("A", (k, k)), ("Q", (k, k)), ("mean", (k,)),
                            ("initial_mean", (k,)), ("initial_cov", (k, k))):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != shape:
                raise ModelError(f"Dynamics.{name} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ModelError(f"Dynamics.{name} has non-finite entries")
            object.__setattr__(self, name, arr)
        if self.kind not in ("ar1", "seasonal"):
            raise ModelError(f"Dynamics.kind must be 'ar1' or 'seasonal', got {self.kind!r}")
        if self.kind == "seasonal" and (self.season_means is None or self.season is None):
            raise ModelError("seasonal dynamics need season and season_means")
        if not (np.isfinite(self.step) and self.step > 0):
            raise ModelError(f"Dynamics.step must be > 0, got {self.step!r}")

    @property
    def rank(self) -> int:
        return int(self.A.shape[0])

    def season_mean(self, time: Any) -> np.ndarray:
        """``m(t)`` ``(k,)`` at one time."""
        if self.kind == "ar1":
            return self.mean
        s = int(seasons(np.asarray([time]), self.season)[0])
        return self.season_means[s]

    def n_steps(self, t_from: Any, t_to: Any) -> int:
        """Steps between two times: ``max(1, round(dt / step))`` for ``dt > 0``, 0 for ``dt = 0``
        (the same snapshot), and 1 for ``dt < 0`` (only reached with ``force``)."""
        t, _, _ = time_numbers(_as_time_array([t_from, t_to]), "time")
        dt = float(t[1] - t[0])
        if dt == 0:
            return 0
        return max(1, int(round(dt / self.step))) if dt > 0 else 1

    def transition(self, n: int, t_from: Any = None, t_to: Any = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A_n, Q_n, c)`` for ``n`` steps: ``x' = A_n x + c + w``, ``w ~ N(0, Q_n)``."""
        k = self.rank
        An, Qn = np.eye(k), np.zeros((k, k))
        for _ in range(int(n)):  # n is a small number of steps
            Qn = self.A @ Qn @ self.A.T + self.Q
            An = self.A @ An
        if n == 0:
            return An, Qn, np.zeros(k)
        m_from = self.season_mean(t_from) if self.kind == "seasonal" else self.mean
        m_to = self.season_mean(t_to) if self.kind == "seasonal" else self.mean
        return An, 0.5 * (Qn + Qn.T), m_to - An @ m_from

    def stationary_cov(self) -> np.ndarray:
        """The stationary covariance ``S = A S A^T + Q`` (discrete Lyapunov equation)."""
        import scipy.linalg

        S = scipy.linalg.solve_discrete_lyapunov(self.A, self.Q)
        return 0.5 * (S + S.T)

    def transformed(self, T: Any, shift: Any = None) -> Dynamics:
        """The same dynamics for the latent vector ``x' = T x + shift`` (``T`` invertible
        ``(k, k)``): ``A' = T A T^-1``, ``Q' = T Q T^T``, means ``T m + shift``. Maps planted
        dynamics into a fitted model's latent coordinates (``Y_fit ~ T^-T Y_true``)."""
        T = np.asarray(T, dtype=np.float64)
        k = self.rank
        if T.shape != (k, k):
            raise ModelError(f"T must be ({k}, {k}), got {T.shape}")
        Ti = np.linalg.inv(T)
        b = np.zeros(k) if shift is None else np.asarray(shift, dtype=np.float64)
        sm = None if self.season_means is None else self.season_means @ T.T + b
        return replace(self, A=T @ self.A @ Ti, Q=T @ self.Q @ T.T, mean=T @ self.mean + b,
                       initial_mean=T @ self.initial_mean + b,
                       initial_cov=T @ self.initial_cov @ T.T, season_means=sm,
                       error_cov=(None if self.error_cov is None
                                  else T @ self.error_cov @ T.T))

    def with_initial(self, mean: np.ndarray, cov: np.ndarray, time: Any = None) -> Dynamics:
        return replace(self, initial_mean=np.asarray(mean, float),
                       initial_cov=np.asarray(cov, float), time=time)

    # ------------------------------------------------------------------ NetCDF
    def to_dataset_vars(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """``(variables, attrs)`` to merge into the model's NetCDF file (prefix ``dynamics_``)."""
        dims2 = ("component", "component_b")
        out = {
            "dynamics_A": (dims2, self.A),
            "dynamics_Q": (dims2, self.Q),
            "dynamics_mean": (("component",), self.mean),
            "dynamics_initial_mean": (("component",), self.initial_mean),
            "dynamics_initial_cov": (dims2, self.initial_cov),
        }
        if self.season_means is not None:
            out["dynamics_season_means"] = (("season", "component"), self.season_means)
        if self.error_cov is not None:
            out["dynamics_error_cov"] = (dims2, np.asarray(self.error_cov, dtype=np.float64))
        attrs = {"dynamics_kind": self.kind, "dynamics_step": float(self.step),
                 "dynamics_time_kind": self.time_kind,
                 "dynamics_season": self.season or "", "dynamics_shrinkage": self.shrinkage,
                 "dynamics_n_pairs": int(self.n_pairs), "dynamics_blend": float(self.blend)}
        return out, attrs

    @classmethod
    def from_dataset(cls, ds: Any, time: Any = None) -> Dynamics | None:
        """The dynamics stored by :meth:`to_dataset_vars`, or None when the file has none."""
        if "dynamics_kind" not in ds.attrs:
            return None
        try:
            sm = ds["dynamics_season_means"].values if "dynamics_season_means" in ds else None
            return cls(
                kind=str(ds.attrs["dynamics_kind"]), A=ds["dynamics_A"].values,
                Q=ds["dynamics_Q"].values, mean=ds["dynamics_mean"].values,
                initial_mean=ds["dynamics_initial_mean"].values,
                initial_cov=ds["dynamics_initial_cov"].values,
                step=float(ds.attrs["dynamics_step"]),
                time_kind=str(ds.attrs.get("dynamics_time_kind", "numeric")),
                season=str(ds.attrs.get("dynamics_season", "")) or None, season_means=sm,
                shrinkage=float(ds.attrs.get("dynamics_shrinkage", 0.0)),
                n_pairs=int(ds.attrs.get("dynamics_n_pairs", 0)),
                blend=float(ds.attrs.get("dynamics_blend", 1.0)), time=time,
                error_cov=(ds["dynamics_error_cov"].values if "dynamics_error_cov" in ds
                           else None))
        except KeyError as exc:
            raise DataError(f"the model file's dynamics are incomplete (missing {exc})") from None


def _as_time_array(values: list) -> np.ndarray:
    if any(isinstance(v, np.datetime64) for v in values):
        return np.asarray(values, dtype="datetime64[ns]")
    arr = np.empty(len(values), dtype=object)
    arr[:] = values
    if not _is_cftime(arr):
        try:
            return np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise DataError(f"times {values!r} are neither datetimes nor numbers") from None
    return arr


# ----------------------------------------------------------------------------- estimation
def _check_X(X: Any, times: Any) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(getattr(X, "values", X), dtype=np.float64)
    if X.ndim != 2:
        raise ModelError(f"X must be a (k, T) matrix of latent columns, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ModelError("X has non-finite entries")
    k, T = X.shape
    if T < _MIN_SNAPSHOTS:
        raise ModelError(f"temporal dynamics need at least {_MIN_SNAPSHOTS} fitted snapshots, "
                         f"got {T}")
    if times is None:
        raise DataError("times: temporal dynamics need a time coordinate, got none")
    t = check_times(times, "times")
    if t.size != T:
        raise DataError(f"times has {t.size} entries, X has {T} columns")
    return X, t


def _step_pairs(t: np.ndarray) -> tuple[float, np.ndarray]:
    """Median step and the indices ``i`` of pairs ``(i-1, i)`` one step apart."""
    d = np.diff(t)
    step = float(np.median(d))
    ok = np.flatnonzero(np.round(d / step) == 1) + 1
    return step, ok


def _fit_var(Z: np.ndarray, idx: np.ndarray, shrinkage: float,
             error_cov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(A, Q)`` of ``z_i = A z_{i-1} + w`` over pairs ``idx``: ridge least squares with
    ``shrinkage * tr(Z0 Z0^T) / k`` towards 0, ``A`` scaled to spectral radius <= MAX_RADIUS,
    ``Q`` the residual covariance with eigenvalues clipped to be PSD.

    ``error_cov`` ``(k, k)`` (None: 0): the covariance ``S_e`` of the estimation error of each
    column (the columns are noisy estimates ``z + e``; errors-in-variables bias least squares
    towards 0). Then the bias-corrected Yule-Walker estimate ``A = C1 (C0 - S_e)^-1`` (``C0 =
    Z0 Z0^T / n``, ``C1 = Z1 Z0^T / n``, the same ridge) and ``Q = R - S_e - A S_e A^T`` (``R``
    the residual covariance: ``z1 + e1 - A (z0 + e0)`` has covariance ``Q + S_e + A S_e A^T``).
    ``S_e`` is capped at half of ``C0`` in the whitened sense (eigenvalues of
    ``C0^-1/2 S_e C0^-1/2`` <= 0.5), so ``C0 - S_e`` stays well conditioned.
    """
    k = Z.shape[0]
    n = idx.size
    if n < 2:
        raise ModelError(f"temporal dynamics need at least 2 pairs of snapshots one time step "
                         f"apart, got {n}")
    Z0, Z1 = Z[:, idx - 1], Z[:, idx]
    G = Z0 @ Z0.T
    lam = float(shrinkage) * max(np.trace(G), 1e-300) / k
    Se = np.zeros((k, k)) if error_cov is None else _cap_error_cov(G / n, error_cov)
    A = np.linalg.solve(G - n * Se + lam * np.eye(k), Z0 @ Z1.T).T
    rho = float(np.max(np.abs(np.linalg.eigvals(A)))) if k else 0.0
    if rho > MAX_RADIUS:
        A = A * (MAX_RADIUS / rho)
    R = Z1 - A @ Z0
    Q = R @ R.T / max(n - 1, 1) - Se - A @ Se @ A.T
    Q = 0.5 * (Q + Q.T)
    w, V = np.linalg.eigh(Q)
    floor = 1e-9 * max(float(np.max(w)), 1e-300)
    if error_cov is not None:  # the correction may overshoot: floor relative to the raw noise
        floor = max(floor, 1e-3 * float(np.trace(R @ R.T)) / max(n - 1, 1) / k)
    Q = (V * np.maximum(w, floor)) @ V.T
    return A, 0.5 * (Q + Q.T)


def _cap_error_cov(C0: np.ndarray, Se: Any) -> np.ndarray:
    """``S_e`` symmetrised, PSD, and scaled down so ``C0^-1/2 S_e C0^-1/2 <= 0.5``."""
    k = C0.shape[0]
    Se = np.asarray(Se, dtype=np.float64)
    if Se.shape != (k, k) or not np.all(np.isfinite(Se)):
        raise ModelError(f"error_cov must be a finite ({k}, {k}) matrix, got shape {Se.shape}")
    w, V = np.linalg.eigh(0.5 * (Se + Se.T))
    Se = (V * np.maximum(w, 0.0)) @ V.T
    c0w, c0v = np.linalg.eigh(0.5 * (C0 + C0.T))
    if c0w.min() <= 0:
        return np.zeros((k, k))
    W = c0v / np.sqrt(c0w)  # C0^-1/2 (up to rotation)
    top = float(np.max(np.linalg.eigvalsh(W.T @ Se @ W)))
    return Se * min(1.0, 0.5 / top) if top > 0 else Se


_BLEND_GRID = np.linspace(0.0, 1.0, 11)


def _stationary_cov(Z: np.ndarray) -> np.ndarray:
    """Covariance (ddof 1) of the columns of ``Z`` plus 1e-9 x its mean eigenvalue (as the
    empirical prior of :func:`~lrm_cvx.belief.posterior.empirical_moments`)."""
    k = Z.shape[0]
    S = np.atleast_2d(np.cov(Z))
    return S + 1e-9 * max(np.trace(S), 1e-300) / k * np.eye(k)


def blend_moments(A: np.ndarray, Q: np.ndarray, S0: np.ndarray, lam: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """``(lam A, (1 - lam^2) S0 + lam^2 Q)``: ``lam = 0`` is the memoryless prior ``N(mu, S0)``
    every step, ``lam = 1`` the AR(1) fit; every blend is stable with a PSD noise."""
    return lam * A, (1.0 - lam * lam) * S0 + lam * lam * Q


def _choose_blend(Z: np.ndarray, idx: np.ndarray, shrinkage: float, validation: float,
                  error_cov: np.ndarray | None = None) -> float:
    """The blend of :func:`blend_moments` with the best one-step Gaussian predictive log-likelihood
    on the last ``validation`` fraction of the pairs, with ``A``, ``Q``, ``S0`` estimated on
    the pairs and columns before them (1.0 when there are too few pairs to validate)."""
    k = Z.shape[0]
    n = idx.size
    nv = int(round(validation * n))
    if nv < 3 or n - nv < max(3, k + 1):
        return 1.0
    tr, va = idx[: n - nv], idx[n - nv:]
    A, Q = _fit_var(Z, tr, shrinkage, error_cov)
    S0 = _stationary_cov(Z[:, : va[0]])
    R0 = Z[:, va - 1]
    Z1 = Z[:, va]
    best, best_nll = 1.0, np.inf
    for lam in _BLEND_GRID:  # 11 k x k evaluations
        Al, Ql = blend_moments(A, Q, S0, float(lam))
        r = Z1 - Al @ R0
        sign, logdet = np.linalg.slogdet(Ql)
        if sign <= 0:
            continue
        nll = 0.5 * (logdet + np.mean(np.sum(r * np.linalg.solve(Ql, r), axis=0)))
        if nll < best_nll - 1e-12:
            best, best_nll = float(lam), nll
    return best


def _check_validation(validation: Any) -> float | None:
    if validation is None:
        return None
    try:
        v = float(validation)
    except (TypeError, ValueError):
        raise ModelError(f"validation must be None or a fraction in (0, 1), got "
                         f"{validation!r}") from None
    if not 0.0 < v < 1.0:
        raise ModelError(f"validation must be None or a fraction in (0, 1), got {validation!r}")
    return v


def _check_shrinkage(shrinkage: Any) -> float:
    try:
        s = float(shrinkage)
    except (TypeError, ValueError):
        raise ModelError(f"shrinkage must be a number >= 0, got {shrinkage!r}") from None
    if not (np.isfinite(s) and s >= 0):
        raise ModelError(f"shrinkage must be a number >= 0, got {shrinkage!r}")
    return s


def _opt_cov(c: Any) -> np.ndarray | None:
    return None if c is None else np.asarray(c, dtype=np.float64)


def _time_kind(times: Any) -> str:
    return time_numbers(times, "times")[1]


def _last_time(times: Any) -> Any:
    values = np.asarray(getattr(times, "values", times))
    return values[-1]


def _fit_anomalies(Z: np.ndarray, idx: np.ndarray, shrinkage: float, validation: Any,
                   error_cov: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """``(A, Q, blend)`` of the anomalies ``Z (k, T)``: the VAR(1) fit on the pairs ``idx``,
    blended towards the stationary prior by the validated factor (1 without validation)."""
    A, Q = _fit_var(Z, idx, shrinkage, error_cov)
    lam = 1.0
    if validation is not None:
        lam = _choose_blend(Z, idx, shrinkage, validation, error_cov)
        A, Q = blend_moments(A, Q, _stationary_cov(Z), lam)
    return A, Q, lam


def estimate_ar1(X: Any, times: Any, shrinkage: float = 1e-3,
                 initial_cov: Any = None, validation: float | None = None,
                 error_cov: Any = None) -> Dynamics:
    """AR(1) dynamics ``x_t - mu = A (x_{t-1} - mu) + w`` of the columns of ``X (k, T)``.

    ``mu`` is the mean column; ``A`` the least-squares fit over the consecutive pairs one step
    apart with a ridge ``shrinkage * tr(Z0 Z0^T) / k`` towards 0, scaled down if needed so its
    spectral radius is <= 0.99; ``Q`` the residual covariance (made PSD). The initial belief is
    the last column with ``initial_cov`` (default zeros: the last fitted snapshot is taken as
    known). ``times`` ``(T,)``: strictly increasing datetimes, cftime dates or numbers.

    ``validation`` (a fraction, e.g. 0.2; None: off): choose a blend ``lam`` in [0, 1] towards
    the memoryless prior, ``A_lam = lam A``, ``Q_lam = (1 - lam^2) S0 + lam^2 Q`` (``S0`` the
    covariance of the columns), by the one-step predictive log-likelihood of the last
    ``validation`` fraction of the pairs (``A``, ``Q``, ``S0`` fitted on the earlier ones),
    then apply it to the fit on all pairs (``blend``). ``lam = 0`` is exactly the memoryless
    filter; data without persistence get a small ``lam``.

    ``error_cov`` ``(k, k)`` (None: off): the average covariance of the columns' estimation
    error (for a fitted model, the fold-in covariance ``sigma^2 (Y_O Y_O^T)^-1`` averaged over
    the snapshots); ``A`` and ``Q`` are then bias-corrected for it (:func:`_fit_var`).
    """
    shrinkage = _check_shrinkage(shrinkage)
    validation = _check_validation(validation)
    X, t = _check_X(X, times)
    k = X.shape[0]
    step, idx = _step_pairs(t)
    mu = X.mean(axis=1)
    Z = X - mu[:, None]
    A, Q, lam = _fit_anomalies(Z, idx, shrinkage, validation, error_cov)
    P0 = np.zeros((k, k)) if initial_cov is None else np.asarray(initial_cov, dtype=np.float64)
    return Dynamics(kind="ar1", A=A, Q=Q, mean=mu, initial_mean=X[:, -1].copy(),
                    initial_cov=P0, step=step, time_kind=_time_kind(times),
                    shrinkage=shrinkage, n_pairs=int(idx.size), blend=lam,
                    time=_last_time(times), error_cov=_opt_cov(error_cov))


def estimate_seasonal(X: Any, times: Any, shrinkage: float = 1e-3,
                      initial_cov: Any = None, validation: float | None = None,
                      error_cov: Any = None) -> Dynamics:
    """Seasonal AR(1): ``m_s`` = mean of ``X``'s columns per season, AR(1) on the anomalies.

    The season is the month of year when the median step is 27-32 days (monthly data) and the
    day of year when it is at most 1.5 days (daily data); other steps, or a time coordinate
    that is not dates, raise ModelError. The seasons must be seen at least twice (median count
    over the seasons present: two years of data); seasons never seen get the overall mean.
    ``validation``: as :func:`estimate_ar1` on the anomalies (``lam = 0``: the seasonal means
    with the anomalies' covariance, every step); ``error_cov``: as :func:`estimate_ar1`.
    """
    shrinkage = _check_shrinkage(shrinkage)
    validation = _check_validation(validation)
    X, t = _check_X(X, times)
    _, kind, _ = time_numbers(times, "times")
    if kind == "numeric":
        raise ModelError("temporal='seasonal' needs a datetime (or cftime) time coordinate")
    step, idx = _step_pairs(t)
    if 27.0 <= step <= 32.0:
        season, n_seasons = "month", 12
    elif step <= 1.5:
        season, n_seasons = "dayofyear", 366
    else:
        raise ModelError(f"temporal='seasonal' needs monthly or daily data; the median time "
                         f"step is {step:g} days (use temporal='ar1')")
    s = seasons(times, season)
    k = X.shape[0]
    counts = np.bincount(s, minlength=n_seasons)
    if np.median(_years_per_season(times, s, n_seasons)) < 2:
        raise ModelError("temporal='seasonal' needs the seasons seen in at least two years "
                         "(two years of data); use temporal='ar1'")
    sums = np.zeros((n_seasons, k))
    np.add.at(sums, s, X.T)
    means = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None],
                     X.mean(axis=1)[None, :])
    Z = X - means[s].T
    A, Q, lam = _fit_anomalies(Z, idx, shrinkage, validation, error_cov)
    P0 = np.zeros((k, k)) if initial_cov is None else np.asarray(initial_cov, dtype=np.float64)
    return Dynamics(kind="seasonal", A=A, Q=Q, mean=X.mean(axis=1),
                    initial_mean=X[:, -1].copy(), initial_cov=P0, step=step, time_kind=kind,
                    season=season, season_means=means, shrinkage=shrinkage,
                    n_pairs=int(idx.size), blend=lam, time=_last_time(times),
                    error_cov=_opt_cov(error_cov))


TEMPORAL.register("ar1", estimate_ar1, description="AR(1) on the latent vector around its "
                  "mean, the blend towards the memoryless prior validated")
TEMPORAL.register("seasonal", estimate_seasonal, description="AR(1) around per-season means "
                  "(month or day of year; needs two years of dated snapshots)")
TEMPORAL.register("auto", "auto", description="chosen on the training snapshots by rolling-"
                  "origin validation among none, ar1 and seasonal and their blends")


def temporal_value(temporal: Any, argument: str = "temporal") -> str | None:
    """The canonical name of ``temporal`` (None for no dynamics): the one check of a temporal
    choice; an unknown one is a ModelError listing the choices."""
    canon = TEMPORAL.canonical(temporal, argument)
    return None if canon == "none" else canon


DEFAULT_VALIDATION = 0.2


def estimate(temporal: str, X: Any, times: Any, shrinkage: float = 1e-3,
             initial_cov: Any = None, validation: float | None = DEFAULT_VALIDATION,
             error_cov: Any = None) -> Dynamics:
    """Dispatch on ``temporal`` (``"ar1"`` or ``"seasonal"``); anything else is a ModelError.

    The model's dynamics (``GLRM(temporal=...)``, ``fit_dynamics``, campaigns, the CLI) come
    from here, with the blend towards the memoryless prior validated on the last 20 % of the
    pairs by default (``validation=None``: the plain AR(1) fit)."""
    kind = temporal_value(temporal)
    if kind is None:
        raise ModelError(f"temporal must be 'ar1' or 'seasonal' to estimate dynamics, got "
                         f"{temporal!r}")
    if kind == "auto":
        raise ModelError("temporal='auto' is chosen by GLRM.fit from the training snapshots "
                         "(validation/selection.py); estimate needs 'ar1' or 'seasonal'")
    return TEMPORAL.get(kind)(X, times, shrinkage, initial_cov, validation, error_cov)


def kind_dynamics(kind: str, model: Any, times: Any) -> Dynamics | None:
    """The unblended dynamics of ``kind`` for a fitted ``model`` with AR(1) ``dynamics_``
    (their shrinkage, initial and error covariances do not depend on the kind; ``times`` its
    time coordinate), or None when the record cannot carry that kind (a season on yearly data
    or on less than two years): how ``temporal="auto"`` and the calibration's refits get each
    candidate's dynamics."""
    base = model.dynamics_
    try:
        return estimate(kind, model._Xv, times, shrinkage=base.shrinkage,
                        initial_cov=base.initial_cov, validation=None,
                        error_cov=getattr(base, "error_cov", None))
    except ModelError:
        return None


def rts_smooth(G: Any, b: Any, A: Any, Q: Any, mean: Any = None, P0: Any = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel smoother of ``x_t - mean = A (x_{t-1} - mean) + w_t``,
    ``w_t ~ N(0, Q)``, given per-step information-form observations ``G_t x_t ~ b_t``
    (``G (T, k, k)`` PSD, ``b (T, k)``: e.g. ``G_t = Y_O W Y_O^T``, ``b_t = Y_O W z`` of a
    snapshot's observed cells, the fold-in's terms). ``x_0 ~ N(mean, P0)`` (default the
    stationary covariance). Returns the smoothed means ``(T, k)`` and covariances
    ``(T, k, k)``: the exact joint Gaussian posterior's marginals (a loop over time steps).
    Used to smooth the fitted latent columns with the AR prior (docs/monitoring.md)."""
    G = np.asarray(G, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    A = np.asarray(A, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    T, k = b.shape
    if G.shape != (T, k, k) or A.shape != (k, k) or Q.shape != (k, k):
        raise ModelError(f"rts_smooth needs G (T, k, k), b (T, k), A and Q (k, k); got "
                         f"{G.shape}, {b.shape}, {A.shape}, {Q.shape}")
    mu = np.zeros(k) if mean is None else np.asarray(mean, dtype=np.float64)
    if P0 is None:
        import scipy.linalg

        P0 = scipy.linalg.solve_discrete_lyapunov(A, Q)
    P0 = np.asarray(P0, dtype=np.float64)
    mf = np.empty((T, k))
    Pf = np.empty((T, k, k))
    mp = np.empty((T, k))
    Pp = np.empty((T, k, k))
    m, P = mu.copy(), P0
    for t in range(T):  # forward filter in information form
        if t > 0:
            m = mu + A @ (mf[t - 1] - mu)
            P = A @ Pf[t - 1] @ A.T + Q
        mp[t], Pp[t] = m, 0.5 * (P + P.T)
        Pinv = np.linalg.inv(Pp[t])
        Ppost = np.linalg.inv(0.5 * (Pinv + Pinv.T) + G[t])
        mf[t] = Ppost @ (Pinv @ m + b[t])
        Pf[t] = 0.5 * (Ppost + Ppost.T)
    ms, Ps = mf.copy(), Pf.copy()
    for t in range(T - 2, -1, -1):  # backward pass
        J = Pf[t] @ A.T @ np.linalg.inv(Pp[t + 1])
        ms[t] = mf[t] + J @ (ms[t + 1] - mp[t + 1])
        Ps[t] = Pf[t] + J @ (Ps[t + 1] - Pp[t + 1]) @ J.T
        Ps[t] = 0.5 * (Ps[t] + Ps[t].T)
    return ms, Ps
