"""The filter core of persistent monitoring: a Kalman filter on a fitted GLRM's latent vector.

:class:`LatentFilter` carries the Gaussian belief about the current snapshot's latent vector (a
:class:`~lrm_cvx.belief.posterior.LatentPosterior`) from one snapshot to the next with the model's
dynamics (:class:`~lrm_cvx.glrm.dynamics.Dynamics`): ``from_model`` starts it after the last
fitted snapshot, ``assimilate`` moves it to a time (predict step) and folds observations in
(update step). It lives in ``glrm`` so the calibration (``select_dynamics``, the temporal
scale) runs the same filter as :class:`lrm_cvx.monitor.MonitorState`, which adds the maps, the
planner's prior and the state file on top.
"""

from __future__ import annotations

import hashlib
import re
import weakref
from dataclasses import replace
from typing import Any, NamedTuple, Self

import numpy as np
import pandas as pd
import xarray as xr

from ..errors import DataError, ModelError, RegionError
from ..glrm.calibrated import AdaptiveConformal, level_index, variance_scale
from ..glrm.dynamics import Dynamics, time_numbers
from .posterior import (
    LatentPosterior,
    ObservationModel,
    check_cells,
    empirical_moments,
    inverse_stack,
    point_terms,
    propagate_moments,
    symmetric_part,
)

__all__ = ["LatentFilter", "filter_observation_model", "model_fingerprint",
           "memoryless_dynamics", "time_label", "coerce_time", "time_to_str", "initial_cov",
           "FilterBatch", "batch_start", "batch_transitions", "batch_step"]


# ----------------------------------------------------------------------------- helpers
_FINGERPRINTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def model_fingerprint(model: Any) -> str:
    """SHA-256 (hex, 16 chars) of the model's factors ``X_``, ``Y_`` (float64) and its
    offset/scale: a state is only valid with the model it was started from. Remembered per
    model while its arrays are the same objects (a refit makes new ones): hashing ``X``, ``Y``
    is O(L) and a validation builds many states from one model."""
    arrays = (model.X, model.Y, getattr(model, "offset_", None), getattr(model, "scale_", None))
    try:
        refs, fp = _FINGERPRINTS[model]
        if all((r is None and a is None) or (r is not None and r() is a)
               for r, a in zip(refs, arrays, strict=True)):
            return fp
    except (KeyError, TypeError):
        pass
    h = hashlib.sha256()
    for arr in arrays:
        if arr is not None:
            a = np.ascontiguousarray(np.asarray(arr, dtype=np.float64))
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    fp = h.hexdigest()[:16]
    try:
        _FINGERPRINTS[model] = (tuple(None if a is None else weakref.ref(a) for a in arrays),
                                fp)
    except TypeError:  # an object that cannot be weakly referenced: not remembered
        pass
    return fp


def _model_times(model: Any) -> np.ndarray:
    X = model.X_
    if isinstance(X, xr.DataArray):
        return np.asarray(X[X.dims[1]].values)
    return np.arange(model.X.shape[1])


def memoryless_dynamics(model: Any) -> Dynamics:
    """``A = 0``, ``Q = cov(X_)``, mean ``mean(X_)``: each snapshot's prior is the empirical
    prior whatever came before (the memoryless model through the filter)."""
    X = model.X
    m0, S0 = empirical_moments(X)
    times = _model_times(model)
    t, kind, _ = time_numbers(times, "time")
    d = np.diff(t)
    step = float(np.median(d)) if d.size and np.all(d > 0) else 1.0
    k = X.shape[0]
    return Dynamics(kind="ar1", A=np.zeros((k, k)), Q=S0, mean=m0, initial_mean=X[:, -1].copy(),
                    initial_cov=S0, step=step, time_kind=kind, time=times[-1])


def initial_cov(dynamics: Dynamics) -> np.ndarray:
    """The covariance ``(k, k)`` of a filter's first belief (:meth:`LatentFilter.from_model`):
    the dynamics' ``initial_cov`` plus a jitter of ``1e-9 tr(Q) / k`` (a singular initial
    covariance, e.g. the last snapshot's fold-in from few cells, stays invertible)."""
    k = dynamics.rank
    jitter = 1e-9 * max(float(np.trace(dynamics.Q)), 1e-300) / k
    return dynamics.initial_cov + jitter * np.eye(k)


def coerce_time(value: Any, kind: str, calendar: str | None, name: str = "time") -> Any:
    """``value`` (a string, datetime, cftime date or number) as a time of ``kind``."""
    if value is None:
        raise DataError(f"{name} is required")
    try:
        if kind == "datetime":
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
                    value, bool):
                raise TypeError("a number is not a date")
            from .._validation import datetime_ns

            return datetime_ns(value, name)  # DataError outside datetime64[ns]'s range
        if kind == "cftime":
            import cftime

            if hasattr(value, "calendar"):
                return value
            m = _ISO_DATE.match(str(value).strip())
            if m is None:  # read by the calendar itself: 2093-02-30 is a 360-day date
                raise ValueError("expected YYYY-MM-DD[THH[:MM[:SS]]]")
            y, mo, d, h, mi, sec = (int(float(g)) if g else 0 for g in m.groups())
            return cftime.datetime(y, mo, d, h, mi, sec, calendar=calendar or "standard")
        v = float(value)
        if not np.isfinite(v):
            raise ValueError("not finite")
        return v
    except DataError:
        raise
    except (TypeError, ValueError, OverflowError) as exc:
        expected = {"datetime": "a date such as '2020-03-01'",
                    "cftime": f"a date in the {calendar} calendar",
                    "numeric": "a number"}[kind]
        raise DataError(f"{name} must be {expected} (the model's time coordinate), got "
                        f"{value!r}: {exc}") from None


def parse_time(value: Any, times: Any, name: str = "time") -> Any:
    """``value`` (a string such as ``"2093-02-30"``, a date or a number) as a time of the same
    kind and calendar as ``times`` (a time coordinate); DataError naming ``name`` otherwise."""
    _, kind, calendar = time_numbers(np.asarray(getattr(times, "values", times))[:1], name)
    return coerce_time(value, kind, calendar, name)


_ISO_DATE = re.compile(r"^(-?\d{1,4})-(\d{1,2})-(\d{1,2})(?:[T ](\d{1,2})(?::(\d{1,2})"
                       r"(?::(\d{1,2}(?:\.\d*)?))?)?)?$")


def time_to_str(t: Any) -> str:
    if isinstance(t, np.datetime64):
        return str(np.datetime64(t, "ns"))
    if hasattr(t, "calendar"):
        return t.isoformat()
    return repr(float(t))


def time_label(t: Any) -> str:
    """A time for messages and labels: a datetime64 to the second, a cftime date in ISO form,
    a number as its repr."""
    if isinstance(t, np.datetime64):
        return str(np.datetime64(t, "s"))
    return time_to_str(t)


# ----------------------------------------------------------------------------- the filter
def filter_observation_model(model: Any, spatial: bool | None,
                             memoryless: bool) -> ObservationModel:
    """The observation model a filter over ``model`` reads: the model's, with (unless
    ``memoryless``) the filter's own calibrated variance scale and conformal thresholds
    (``Calibration.for_filter``, glrm/calibration.py). One place for a new state and a loaded
    one."""
    obs = ObservationModel.from_model(model, spatial=spatial)
    if memoryless:
        return obs
    cal = obs.calibration
    return replace(obs, variance_scale=variance_scale(model, temporal=True),
                   calibration=None if cal is None else cal.for_filter())


class LatentFilter:
    """The filter's belief about the latent vector of the snapshot at ``time``.

    Build with :meth:`from_model`. ``posterior`` is the
    :class:`~lrm_cvx.belief.posterior.LatentPosterior` of the current snapshot (its ``cells`` and
    ``values`` are today's observations), ``observed`` whether the snapshot at ``time`` has
    been observed (the last fitted snapshot counts as observed; a state positioned at a later
    time by ``from_model(model, time=T)`` has not, so observations at ``T`` are accepted).
    Mutating methods return ``self``.
    """

    def __init__(self, model: Any, posterior: LatentPosterior, time: Any, dynamics: Dynamics,
                 *, observed: bool = True, memoryless: bool = False,
                 n_assimilated: int = 0, n_dropped: int = 0) -> None:
        self.model = model
        self.posterior = posterior
        self.time = time
        self.dynamics = dynamics
        self.observed = bool(observed)
        self.memoryless = bool(memoryless)
        self.n_assimilated = int(n_assimilated)
        self.n_dropped = int(n_dropped)
        self.aci: AdaptiveConformal | None = None  # online interval calibration
        _, self._time_kind, self._calendar = time_numbers(_model_times(model)[:1], "time")
        self.fingerprint = model_fingerprint(model)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(cls, model: Any, time: Any = None, *, dynamics: Dynamics | None = None,
                   spatial: bool | None = None, memoryless: bool | None = None) -> Self:
        """A state after the last fitted snapshot (belief ``N(x_T, initial_cov)``), or
        forecast to ``time`` (not yet observed there).

        ``dynamics``: default the model's ``dynamics_``; ``memoryless=True`` (default when the
        model has none) uses :func:`memoryless_dynamics`. ``spatial``: use the model's spatial
        residual (None: whenever it has one)."""
        model._check_fitted()
        if memoryless is None:
            memoryless = dynamics is None and getattr(model, "dynamics_", None) is None
        if memoryless:
            dynamics = memoryless_dynamics(model)
        elif dynamics is None:
            dynamics = getattr(model, "dynamics_", None)
            if dynamics is None:
                raise ModelError("the model has no dynamics_: fit it with temporal='ar1' (or "
                                 "call model.fit_dynamics()), or pass memoryless=True")
        if not isinstance(dynamics, Dynamics):
            raise ModelError(f"dynamics must be a Dynamics, got {type(dynamics).__name__}")
        k = model.Y.shape[0]
        if dynamics.rank != k:
            raise ModelError(f"dynamics have rank {dynamics.rank}, the model {k}")
        obs = filter_observation_model(model, spatial, memoryless)
        post = LatentPosterior.from_moments(obs, dynamics.initial_mean, initial_cov(dynamics))
        t_last = _model_times(model)[-1]
        state = cls(model, post, t_last, dynamics, observed=True, memoryless=memoryless)
        if time is not None:
            t = state._coerce(time)
            state._check_order(t, force=False)
            state.posterior = state._propagated(t)
            state.time, state.observed = t, False
        return state

    # ------------------------------------------------------------------ time handling
    def _coerce(self, time: Any, name: str = "time") -> Any:
        return coerce_time(time, self._time_kind, self._calendar, name)

    def _dt(self, t: Any) -> float:
        tt, _, _ = time_numbers(_time_array([self.time, t]), "time")
        return float(tt[1] - tt[0])

    def _check_order(self, t: Any, force: bool) -> None:
        dt = self._dt(t)
        if force or dt > 0 or (dt == 0 and not self.observed):
            return
        raise DataError(f"time {time_label(t)} is {'equal to' if dt == 0 else 'earlier than'} "
                        f"the state's time {time_label(self.time)}: observations must come in "
                        "time order (pass force=True / --force to override)")

    def next_time(self) -> Any:
        """The record's next stamp after the state's time: one step of the record's cadence,
        with the record's own day-of-month (or fraction of the month, or day-of-year)
        convention (:class:`lrm_cvx.belief.calendar.RecordCalendar`): monthly on the 15th ->
        the 15th of the next month, CF mid-month stamps -> the next month's mid-month stamp,
        daily -> the next day."""
        return self.record_calendar.next_stamp(self.time)

    @property
    def record_calendar(self) -> Any:
        """The :class:`~lrm_cvx.belief.calendar.RecordCalendar` of the model's training times."""
        from .calendar import RecordCalendar

        cached = getattr(self, "_record_calendar", None)
        if cached is None or cached[0] is not self.model:
            cached = (self.model, RecordCalendar.of(_model_times(self.model),
                                                    self.dynamics.step))
            self._record_calendar = cached
        return cached[1]

    def _propagated(self, t: Any) -> LatentPosterior:
        """The belief about the snapshot at ``t`` before its observations."""
        dyn = self.dynamics
        if self._dt(t) == 0:
            return self.posterior
        n = dyn.n_steps(self.time, t)
        A, Q, c = dyn.transition(n, self.time, t)
        return self.posterior.propagate(A, Q, c, steps=n)


    # ------------------------------------------------------------------ online conformal
    def adaptive_conformal(self, levels: Any = (0.68, 0.95), gamma: float = 0.01) -> Self:
        """Switch on adaptive conformal inference (Gibbs & Candes 2021,
        :class:`~lrm_cvx.glrm.calibrated.AdaptiveConformal`): from now on each
        :meth:`assimilate` first scores the forecast's standardized residuals at the day's
        sampled cells (before they are assimilated) and moves each level's working
        miscoverage by ``gamma`` towards the target, so the intervals' long-run coverage holds
        even when the record drifts away from the calibration. The multipliers start from the
        model's conformal calibration (``calibrate(..., method="conformal")``), else the normal
        quantiles (the filter's own thresholds, ``Calibration.for_filter``, unless memoryless).
        ``MonitorState.from_model`` switches it on by default (``online=True``). Returns
        ``self``."""
        self.aci = AdaptiveConformal(np.atleast_1d(levels), gamma,
                                     self.posterior.obs_model.calibration)
        return self

    def interval_multipliers(self, levels: Any = (0.68, 0.95)) -> np.ndarray:
        """Half-widths (units of the predictive std) of the central ``levels`` intervals: the
        online ACI's current ones for the levels it tracks, else the posterior's
        (:meth:`~lrm_cvx.belief.posterior.LatentPosterior.interval_multipliers`)."""
        lv = np.atleast_1d(levels)
        out = self.posterior.interval_multipliers(lv)
        if self.aci is not None:
            tracked = self.aci.multipliers(self.posterior.n_samples)
            for i, v in enumerate(lv):
                j = level_index(self.aci.levels, v)
                if j is not None:
                    out[i] = tracked[j]
        return out

    def _score_forecast(self, prior: LatentPosterior, cells: np.ndarray,
                        values: np.ndarray) -> None:
        """ACI: score the day's samples under the forecast ``prior``, then update."""
        keep = ~np.isnan(values)
        if self.aci is None or not keep.any() or not prior.is_proper:
            return
        mean, _, pstd = prior.predict_all(cells=cells[keep])
        self.aci.update(np.abs(values[keep] - mean) / pstd, prior.n_samples)

    # ------------------------------------------------------------------ assimilation
    def observation_cells(self, observations: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(cells int64, values float64)`` from ``(cells, values)``, a ``(lat, lon)``
        DataArray with NaN where not observed, or a DataFrame with ``lat``, ``lon``, ``value``
        columns. Points outside the grid or on masked cells raise RegionError naming them."""
        region = self.model.region_
        L = self.model.n_cells_
        if isinstance(observations, pd.DataFrame):
            missing = {"lat", "lon", "value"} - set(observations.columns)
            if missing:
                raise DataError(f"observations table needs columns lat, lon, value; missing "
                                f"{sorted(missing)}")
            if region is None:
                raise DataError("lat/lon observations need a model fitted with a region")
            try:
                values = observations["value"].to_numpy(dtype=np.float64)
                lat = observations["lat"].to_numpy(dtype=np.float64)
                lon = observations["lon"].to_numpy(dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise DataError(f"observations lat, lon, value must be numbers: {exc}") from None
            if values.size == 0:
                return np.zeros(0, np.int64), np.zeros(0)
            cells = np.atleast_1d(region.cell_of(lat, lon)).astype(np.int64)
            return cells, values
        if isinstance(observations, xr.Dataset):
            names = list(observations.data_vars)
            if len(names) != 1:
                raise DataError(f"observations Dataset must have one data variable, got {names}")
            observations = observations[names[0]]
        if isinstance(observations, xr.DataArray):
            da = observations
            if da.dims and da.dims[-1] == "cell":
                vals = np.asarray(da.values, dtype=np.float64).reshape(-1)
                if vals.size != L:
                    raise DataError(f"observations have {vals.size} cells, the model has {L}")
            else:
                if region is None:
                    raise DataError("gridded observations need a model fitted with a region")
                if da.ndim != 2:
                    raise DataError(f"observations must have dims (lat, lon), got {da.dims}")
                grid = np.asarray(da.values, dtype=np.float64)
                vals = region.stack(da).astype(np.float64)  # checks the grid
                off = np.isfinite(grid) & ~region.mask
                if off.any():
                    r, c = np.argwhere(off)[0]
                    raise RegionError(
                        f"observations at {int(off.sum())} masked cell(s) outside the region, "
                        f"e.g. (lat={float(region.lat.values[r]):g}, "
                        f"lon={float(region.lon.values[c]):g})")
                vals = grid.reshape(-1)[region._flat]
            cells = np.flatnonzero(~np.isnan(vals))
            return cells, vals[cells]
        if isinstance(observations, tuple) and len(observations) == 2:
            cells, values = observations
            c = np.asarray(cells)
            if c.size and (not np.issubdtype(c.dtype, np.number) or c.dtype == np.bool_):
                raise DataError(f"observation cells must be integer indices, got dtype {c.dtype}")
            cf = c.astype(np.float64).reshape(-1)
            bad = np.flatnonzero(~np.isfinite(cf) | (cf < 0) | (cf >= L))
            if bad.size:
                raise RegionError(f"observation cells {cf[bad][:5].tolist()} are outside the "
                                  f"region's {L} cells")
            v = np.asarray(values, dtype=np.float64).reshape(-1)
            if v.shape != cf.shape:
                raise DataError(f"observation values have {v.size} entries, cells {cf.size}")
            return check_cells(cf, L, "observation cells"), v
        raise DataError("observations must be (cells, values), a (lat, lon) DataArray with NaN "
                        "where not observed, or a DataFrame with lat, lon, value; got "
                        f"{type(observations).__name__}")

    def assimilate(self, observations: Any, time: Any, *, force: bool = False) -> Self:
        """Move the state to ``time`` and fold ``observations`` in (see
        :meth:`observation_cells` for the forms). A ``time`` earlier than or equal to the
        state's (already observed) time is refused unless ``force`` (then an equal time adds to
        the same snapshot and an earlier one counts as one step). NaN values are ignored and
        counted (``n_dropped``); a repeated cell is a repeated measurement. Returns ``self``."""
        t = self._coerce(time)
        self._check_order(t, force)
        cells, values = self.observation_cells(observations)
        prior = self._propagated(t) if (self._dt(t) != 0) else self.posterior
        self._score_forecast(prior, cells, values)  # ACI (when on): before assimilating
        post = prior.update(cells, values)
        dropped = int(np.count_nonzero(np.isnan(values)))
        self.posterior = post
        self.time = t
        self.observed = True
        self.n_assimilated += int(cells.size - dropped)
        self.n_dropped += dropped
        return self


    def assimilate_rows(self, rows: Any, values: Any, time: Any, *, force: bool = False,
                        errors: str = "independent") -> Self:
        """:meth:`assimilate` of averaged observations (a sensor footprint, a towed sensor's
        legs): ``values[i]`` (data units) is ``rows[i] @`` the snapshot (``rows`` ``(m, L)``
        weights; ``errors``: a sensor's, see
        :meth:`~lrm_cvx.belief.posterior.LatentPosterior.update_rows`). Returns ``self``."""
        t = self._coerce(time)
        self._check_order(t, force)
        v = np.atleast_1d(np.asarray(values, dtype=np.float64))
        prior = self._propagated(t) if (self._dt(t) != 0) else self.posterior
        post = prior.update_rows(rows, v, errors)
        dropped = int(np.count_nonzero(np.isnan(v)))
        self.posterior = post
        self.time = t
        self.observed = True
        self.n_assimilated += int(v.size - dropped)
        self.n_dropped += dropped
        return self


# ----------------------------------------------------------------------------- many filters
class FilterBatch(NamedTuple):
    """The latent beliefs of filters of one model with different dynamics that assimilate the
    same observations (the candidates of ``temporal="auto"``, glrm/selection.py): means ``(n,
    k)``, covariances ``(n, k, k)`` (fit units), the resolved ``dynamics`` (memoryless ones
    built), the shared observation model, the beliefs' ``time`` and each filter's ``weight``
    ``(n,)`` of the observations' information: ``1 / inflation``, a filter whose residual and
    noise variances are ``inflation`` times the shared model's (``residual_inflation_``)."""

    obs: ObservationModel
    mean: np.ndarray
    cov: np.ndarray
    dynamics: list[Dynamics]
    time: Any
    weight: np.ndarray


def batch_start(model: Any, dynamics: list[Dynamics | None], *,
                spatial: bool | None = None, inflation: Any = None) -> FilterBatch:
    """The first beliefs of ``LatentFilter.from_model(model, dynamics=d, memoryless=d is None,
    spatial=spatial)`` for each ``d`` of ``dynamics``, stacked. Only what the latent belief
    depends on is kept: the filter's variance scale and interval thresholds change no mean or
    latent covariance, so one observation model serves all. ``inflation`` ``(n,)`` (default
    1): each filter's residual and noise variances relative to ``model``'s (>= 1 trusts the
    latent update less; it changes no kriging weight)."""
    model._check_fitted()
    dyns = [memoryless_dynamics(model) if d is None else d for d in dynamics]
    k = model.Y.shape[0]
    if any(d.rank != k for d in dyns):
        raise ModelError(f"dynamics must have the model's rank {k}")
    obs = ObservationModel.from_model(model, spatial=spatial)
    mean = np.stack([d.initial_mean for d in dyns])
    cov = symmetric_part(np.stack([initial_cov(d) for d in dyns]))
    infl = np.ones(len(dyns)) if inflation is None else np.asarray(inflation, np.float64)
    if infl.shape != (len(dyns),) or not np.all(np.isfinite(infl) & (infl > 0)):
        raise ModelError(f"inflation must hold {len(dyns)} finite numbers > 0, got {inflation!r}")
    return FilterBatch(obs, mean, cov, dyns, _model_times(model)[-1], 1.0 / infl)


def batch_transitions(dynamics: list[Dynamics], t_from: Any, t_to: Any
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, Q, c)`` stacked ``(n, k, k), (n, k, k), (n, k)``: each filter's transition from
    ``t_from`` to the later time ``t_to`` (as :meth:`LatentFilter.assimilate` moves it)."""
    out = [d.transition(d.n_steps(t_from, t_to), t_from, t_to) for d in dynamics]
    return tuple(np.stack(parts) for parts in zip(*out, strict=True))


def batch_step(batch: FilterBatch, transition: tuple[np.ndarray, np.ndarray, np.ndarray],
               cells: np.ndarray, values: np.ndarray, time: Any = None) -> FilterBatch:
    """Every filter of ``batch`` moved by ``transition`` (:func:`batch_transitions`, to a
    later snapshot) and updated with the point observations ``values`` (data units, NaN
    ignored) at ``cells``: the algebra of ``LatentFilter.assimilate`` (propagate, then add the
    observations' information), the observations' terms (the ``n x n`` GLS with the spatial
    residual) computed once for all filters. ModelError when a belief is singular."""
    mean, cov = propagate_moments(batch.mean, batch.cov, *transition)
    keep = ~np.isnan(values)
    cells, values = np.asarray(cells)[keep], np.asarray(values, dtype=np.float64)[keep]
    if cells.size:
        P0, ok = inverse_stack(cov)
        if not ok.all():
            raise ModelError("a forecast covariance is singular")
        G, b, _, _ = point_terms(batch.obs, cells, values)
        w = batch.weight
        cov, ok = inverse_stack(symmetric_part(P0 + w[:, None, None] * G))
        if not ok.all():
            raise ModelError("a filter's belief is singular after its observations")
        mean = (cov @ ((P0 @ mean[..., None])[..., 0] + w[:, None] * b)[..., None])[..., 0]
    return batch._replace(mean=mean, cov=cov, time=time)


def _time_array(values: list) -> np.ndarray:
    if any(isinstance(v, np.datetime64) for v in values):
        return np.asarray(values, dtype="datetime64[ns]")
    if any(hasattr(v, "calendar") for v in values):
        arr = np.empty(len(values), dtype=object)
        arr[:] = values
        return arr
    return np.asarray(values, dtype=np.float64)
