"""The monitoring filter: a Kalman filter on the latent vector of a fitted GLRM (issue 13).

:class:`MonitorState` carries the Gaussian belief about the current snapshot's latent vector
(a :class:`~lrm_cvx.glrm.posterior.LatentPosterior`, the same fold-in algebra as
``GLRM.complete``) from one field day to the next with the model's dynamics
(:class:`~lrm_cvx.glrm.dynamics.Dynamics`):

* **forecast** (predict step): ``x_t | past ~ N(A_n m + c, A_n S A_n^T + Q_n)``;
* **assimilate** (update step): the fold-in of today's observations into that prior;
* **predict**: the posterior mean and std maps; **planner_kwargs**: the prior of tomorrow's
  plan, so the planner targets what is still uncertain.

A model without dynamics gives the memoryless filter: every snapshot's prior is the empirical
prior ``N(mean(X_), cov(X_))`` (``A = 0``, ``Q = cov(X_)``), i.e. today's ``complete(...,
prior="empirical")``. docs/monitoring.md has the model and the field loop.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import re
from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from ._validation import atomic_output, read_netcdf
from .errors import DataError, ModelError, RegionError
from .glrm.dynamics import Dynamics, time_numbers
from .glrm.posterior import LatentPosterior, ObservationModel, empirical_moments

__all__ = ["MonitorState", "model_fingerprint", "memoryless_dynamics", "time_label"]

_FORMAT = "lrm-cvx MonitorState"
_FORMAT_VERSION = 1


# ----------------------------------------------------------------------------- helpers
def model_fingerprint(model: Any) -> str:
    """SHA-256 (hex, 16 chars) of the model's factors ``X_``, ``Y_`` (float64) and its
    offset/scale: a state is only valid with the model it was started from."""
    h = hashlib.sha256()
    for arr in (model._Xv, model._Yv, getattr(model, "offset_", None),
                getattr(model, "scale_", None)):
        if arr is not None:
            a = np.ascontiguousarray(np.asarray(arr, dtype=np.float64))
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()[:16]


def _model_times(model: Any) -> np.ndarray:
    X = model.X_
    if isinstance(X, xr.DataArray):
        return np.asarray(X[X.dims[1]].values)
    return np.arange(model._Xv.shape[1])


def memoryless_dynamics(model: Any) -> Dynamics:
    """``A = 0``, ``Q = cov(X_)``, mean ``mean(X_)``: each snapshot's prior is the empirical
    prior whatever came before (the memoryless model through the filter)."""
    X = model._Xv
    m0, S0 = empirical_moments(X)
    times = _model_times(model)
    t, kind, _ = time_numbers(times, "time")
    d = np.diff(t)
    step = float(np.median(d)) if d.size and np.all(d > 0) else 1.0
    k = X.shape[0]
    return Dynamics(kind="ar1", A=np.zeros((k, k)), Q=S0, mean=m0, initial_mean=X[:, -1].copy(),
                    initial_cov=S0, step=step, time_kind=kind, time=times[-1])


def _coerce_time(value: Any, kind: str, calendar: str | None, name: str = "time") -> Any:
    """``value`` (a string, datetime, cftime date or number) as a time of ``kind``."""
    if value is None:
        raise DataError(f"{name} is required")
    try:
        if kind == "datetime":
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
                    value, bool):
                raise TypeError("a number is not a date")
            ts = pd.Timestamp(str(value) if hasattr(value, "calendar") else value)
            if ts is pd.NaT:
                raise ValueError("NaT")
            return np.datetime64(ts.tz_localize(None) if ts.tzinfo else ts, "ns")
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
    return _coerce_time(value, kind, calendar, name)


_ISO_DATE = re.compile(r"^(-?\d{1,4})-(\d{1,2})-(\d{1,2})(?:[T ](\d{1,2})(?::(\d{1,2})"
                       r"(?::(\d{1,2}(?:\.\d*)?))?)?)?$")


def _time_to_str(t: Any) -> str:
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
    return _time_to_str(t)


# ----------------------------------------------------------------------------- the state
class MonitorState:
    """The filter's belief about the latent vector of the snapshot at ``time``.

    Build with ``model.monitor(time=None)`` or :meth:`from_model`. ``posterior`` is the
    :class:`~lrm_cvx.glrm.posterior.LatentPosterior` of the current snapshot (its ``cells`` and
    ``values`` are today's observations), ``observed`` whether the snapshot at ``time`` has
    been observed (the last fitted snapshot counts as observed; a state positioned at a later
    time by ``monitor(time=T)`` has not, so observations at ``T`` are accepted). Mutating
    methods return ``self``.
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
        _, self._time_kind, self._calendar = time_numbers(_model_times(model)[:1], "time")
        self.fingerprint = model_fingerprint(model)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(cls, model: Any, time: Any = None, *, dynamics: Dynamics | None = None,
                   spatial: bool | None = None, memoryless: bool | None = None) -> MonitorState:
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
        k = model._Yv.shape[0]
        if dynamics.rank != k:
            raise ModelError(f"dynamics have rank {dynamics.rank}, the model {k}")
        obs = ObservationModel.from_model(model, spatial=spatial)
        if not memoryless:  # the filter's own calibrated variance scale (glrm/calibration.py)
            from .glrm.calibration import variance_scale

            obs = replace(obs, variance_scale=variance_scale(model, temporal=True))
        P0 = dynamics.initial_cov
        jitter = 1e-9 * max(float(np.trace(dynamics.Q)), 1e-300) / k
        post = LatentPosterior.from_moments(obs, dynamics.initial_mean, P0 + jitter * np.eye(k))
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
        return _coerce_time(time, self._time_kind, self._calendar, name)

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
        """The time one step after the state's (one month for monthly data). Monthly data keep
        their own stamps: when every training snapshot of the next calendar month has the same
        day and time of day (mid-month records: 16 Jan 12:00, 15 Feb 00:00, ...), the next time
        takes them; otherwise the state's day and time one month on."""
        step = self.dynamics.step
        t = self.time
        monthly = self._time_kind != "numeric" and 27.0 <= step <= 32.0
        if self._time_kind == "datetime":
            ts = pd.Timestamp(t)
            ts = ts + (pd.DateOffset(months=1) if monthly else pd.Timedelta(days=step))
            if monthly and (stamp := self._month_stamp(ts.month)) is not None:
                ts = (ts.normalize().replace(day=1)
                      + pd.Timedelta(days=stamp[0] - 1, seconds=stamp[1]))
            return np.datetime64(ts, "ns")
        if self._time_kind == "cftime":
            if monthly:
                y, m = divmod(t.month, 12)
                stamp = self._month_stamp(m + 1)
                if stamp is not None:
                    first = t.replace(year=t.year + y, month=m + 1, day=1, hour=0, minute=0,
                                      second=0, microsecond=0)
                    return first + _dt.timedelta(days=stamp[0] - 1, seconds=stamp[1])
                try:
                    return t.replace(year=t.year + y, month=m + 1)
                except ValueError:
                    return t.replace(year=t.year + y, month=m + 1, day=28)
            return t + _dt.timedelta(days=step)
        return float(t) + step

    def _month_stamp(self, month: int) -> tuple[int, int] | None:
        """``(day, seconds into the day)`` shared by every training time in calendar
        ``month``, or None (no such time, or they differ)."""
        stamps = set()
        for v in np.asarray(_model_times(self.model)).ravel():
            if isinstance(v, np.datetime64):
                ts = pd.Timestamp(v)
            elif hasattr(v, "calendar"):
                ts = v
            else:
                return None
            if ts.month == month:
                stamps.add((int(ts.day), int(ts.hour) * 3600 + int(ts.minute) * 60
                            + int(ts.second)))
        return stamps.pop() if len(stamps) == 1 else None

    def _propagated(self, t: Any) -> LatentPosterior:
        """The belief about the snapshot at ``t`` before its observations."""
        dyn = self.dynamics
        if self._dt(t) == 0:
            return self.posterior
        n = dyn.n_steps(self.time, t)
        A, Q, c = dyn.transition(n, self.time, t)
        return self.posterior.propagate(A, Q, c, steps=n)

    # ------------------------------------------------------------------ maps
    def _dataset(self, mean: np.ndarray, std: np.ndarray, pstd: np.ndarray, t: Any,
                 kind: str) -> xr.Dataset:
        model = self.model
        region = model.region_
        if region is not None:
            unstack = lambda v, n: region.unstack(v, name=n)  # noqa: E731
        else:
            unstack = lambda v, n: xr.DataArray(  # noqa: E731
                v, dims=("cell",), coords={"cell": np.arange(v.size)}, name=n)
        ds = xr.Dataset({"mean": unstack(mean, "mean"), "std": unstack(std, "std"),
                         "predictive_std": unstack(pstd, "predictive_std")})
        ds["std"].attrs["long_name"] = "posterior std of the latent (noise-free) value"
        ds["predictive_std"].attrs["long_name"] = ("std of a new measurement (latent + spatial "
                                                   "residual + noise)")
        ds = ds.assign_coords(time=t)
        ds.attrs.update(kind=kind, memoryless=int(self.memoryless),
                        dynamics=self.dynamics.kind, n_observations=int(self._post_at(t)[1]))
        return ds

    def _post_at(self, t: Any) -> tuple[LatentPosterior, int]:
        if self._dt(t) == 0:
            return self.posterior, int(self.posterior.cells.size)
        return self._propagated(t), 0

    def forecast(self, time: Any = None) -> xr.Dataset:
        """The prior for the snapshot at ``time`` (default: the next step; the state's own time
        when it has not been observed yet) as a Dataset with ``mean``, ``std`` (latent +
        spatial residual) and ``predictive_std`` (plus noise: a new measurement) maps and a
        scalar ``time`` coordinate. Does not change the state."""
        t = self._default_time(time)
        post, _ = self._post_at(t)
        return self._dataset(*post.predict_all(), t, "forecast")

    def _default_time(self, time: Any) -> Any:
        if time is not None:
            t = self._coerce(time)
            if self._dt(t) < 0:
                raise DataError(f"time {time_label(t)} is earlier than the state's time "
                                f"{time_label(self.time)}: the filter forecasts forward only")
            return t
        return self.time if not self.observed else self.next_time()

    def replan(self, plan: Any, done: Any, observations: Any = None, *, time: Any = None,
               criterion: str | None = None, progress: bool = False) -> Any:
        """Replan the rest of ``plan`` en route: fold in ``observations`` (today's measurements
        so far) at ``time``, keep each robot's first ``done`` route entries, and plan the rest
        from where it is with the budget left and the same end (home for a closed tour), under
        the same path model. See :func:`lrm_cvx.replanning.replan`."""
        from .replanning import replan

        return replan(self, plan, done, observations, time=time, criterion=criterion,
                      progress=progress)

    def explore(self, plan: Any = None, *, forecast: bool = False, time: Any = None,
                tiles: str | None = "OpenStreetMap") -> Any:
        """An interactive ``folium.Map`` for notebooks: the belief's mean, ``std`` and
        ``predictive_std`` as layers (the posterior, or with ``forecast=True`` the forecast for
        ``time``), today's samples, and ``plan``'s routes when given. Needs folium
        (``lrm-cvx[explore]``)."""
        from .interactive import explore_map

        ds = self.forecast(time) if forecast else self.predict()
        region = self.model.region_
        if region is None:
            raise DataError("an interactive map needs a model fitted on gridded data")
        what = "forecast" if forecast else "posterior"
        fields = {f"{what} mean": (ds["mean"].values, "viridis"),
                  "std": (ds["std"].values, "magma"),
                  "predictive std": (ds["predictive_std"].values, "magma")}
        cells = np.asarray(self.posterior.cells, dtype=np.int64)
        values = np.asarray(self.posterior.values, dtype=np.float64)
        stops = [(region.cell_lat[c], region.cell_lon[c], f"cell {int(c)}: {v:.4g}")
                 for c, v in zip(cells, values, strict=True)]
        routes = [] if plan is None else [
            (plan.lat[plan.route_robot == r], plan.lon[plan.route_robot == r])
            for r in range(plan.n_robots)]
        return explore_map(region.lat.values, region.lon.values, fields, routes=routes,
                           stops=stops, tiles=tiles)

    def predict(self) -> xr.Dataset:
        """Posterior ``mean``, ``std`` and ``predictive_std`` maps of the snapshot at the
        state's time (a Dataset on ``(lat, lon)``, scalar ``time`` coordinate)."""
        return self._dataset(*self.posterior.predict_all(), self.time, "posterior")

    def planner_kwargs(self, criterion: str = "gp-variance", time: Any = None) -> dict:
        """Keyword arguments of :func:`~lrm_cvx.planning.plan_greedy` with the prior of the
        next plan: the forecast for ``time`` (default as :meth:`forecast`). ``criterion``
        ``"fisher"``/``"a-optimal"`` drop the spatial terms ``"gp-variance"`` needs."""
        post, _ = self._post_at(self._default_time(time))
        kw = post.information()
        if criterion != "gp-variance":
            kw = {k: v for k, v in kw.items() if k not in ("prior_cov", "spatial_cov")}
        elif "spatial_cov" not in kw:
            raise ModelError("criterion 'gp-variance' needs a model fitted with spatial=... "
                             "(use 'fisher' or 'a-optimal')")
        return kw

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
            from .glrm.posterior import check_cells

            return check_cells(cf, L, "observation cells"), v
        raise DataError("observations must be (cells, values), a (lat, lon) DataArray with NaN "
                        "where not observed, or a DataFrame with lat, lon, value; got "
                        f"{type(observations).__name__}")

    def assimilate(self, observations: Any, time: Any, *, force: bool = False) -> MonitorState:
        """Move the state to ``time`` and fold ``observations`` in (see
        :meth:`observation_cells` for the forms). A ``time`` earlier than or equal to the
        state's (already observed) time is refused unless ``force`` (then an equal time adds to
        the same snapshot and an earlier one counts as one step). NaN values are ignored and
        counted (``n_dropped``); a repeated cell is a repeated measurement. Returns ``self``."""
        t = self._coerce(time)
        self._check_order(t, force)
        cells, values = self.observation_cells(observations)
        prior = self._propagated(t) if (self._dt(t) != 0) else self.posterior
        post = prior.update(cells, values)
        dropped = int(np.count_nonzero(np.isnan(values)))
        self.posterior = post
        self.time = t
        self.observed = True
        self.n_assimilated += int(cells.size - dropped)
        self.n_dropped += dropped
        return self

    # ------------------------------------------------------------------ persistence
    def to_dataset(self) -> xr.Dataset:
        p = self.posterior
        dims2 = ("component", "component_b")
        ds = xr.Dataset({
            "precision": (dims2, p.precision), "shift": (("component",), p.shift),
            "base_precision": (dims2, p.base_precision),
            "base_shift": (("component",), p.base_shift),
            "cells": (("observation",), np.asarray(p.cells, dtype=np.int64)),
            "values": (("observation",), np.asarray(p.values, dtype=np.float64)),
        })
        dyn_vars, dyn_attrs = self.dynamics.to_dataset_vars()
        for name, value in dyn_vars.items():
            ds[name] = value
        ds.attrs = {
            "format": _FORMAT, "format_version": _FORMAT_VERSION,
            "fingerprint": self.fingerprint, "time": _time_to_str(self.time),
            "time_kind": self._time_kind, "calendar": self._calendar or "",
            "observed": int(self.observed), "memoryless": int(self.memoryless),
            "spatial": int(p.obs_model.is_spatial), "n_assimilated": self.n_assimilated,
            "n_dropped": self.n_dropped, "posterior_n_dropped": int(p.n_dropped),
            "day_q": float(p.day_q), "day_n": float(p.day_n), "scale_q": float(p.scale_q),
            "scale_n": float(p.scale_n),
            "model_path": str(getattr(self, "model_path", "") or ""),
            **dyn_attrs,
        }
        return ds

    def save(self, path: str | os.PathLike) -> None:
        """Write the state to NetCDF atomically (temporary file + rename): a failure leaves a
        previous file at ``path`` intact."""
        ds = self.to_dataset()
        with atomic_output(path) as tmp:
            ds.to_netcdf(tmp)

    @classmethod
    def load(cls, path: str | os.PathLike, model: Any = None) -> MonitorState:
        """Read a state written by :meth:`save`. ``model`` (default: the model file recorded in
        the state, ``model_path``) must be the model the state was started from (same
        fingerprint), else ModelError; a missing, corrupt or truncated file is a DataError."""
        spath = os.fspath(path)
        ds = read_netcdf(path, "state file", "MonitorState.save")
        need = ("precision", "shift", "base_precision", "base_shift", "cells", "values")
        if ds.attrs.get("format") != _FORMAT or any(n not in ds for n in need):
            raise DataError(f"{spath!r} is not an lrm-cvx monitor state file")
        if model is None:
            mpath = ds.attrs.get("model_path", "")
            if not mpath:
                raise ModelError(f"state file {spath!r} records no model file; pass the model")
            from .glrm import GLRM

            model = GLRM.load(mpath)
        elif isinstance(model, (str, os.PathLike)):
            from .glrm import GLRM

            mpath, model = os.fspath(model), GLRM.load(model)
        else:
            mpath = ds.attrs.get("model_path", "")
        fp = model_fingerprint(model)
        if fp != ds.attrs.get("fingerprint"):
            raise ModelError(f"state file {spath!r} belongs to another model (fingerprint "
                             f"{ds.attrs.get('fingerprint')}, this model's is {fp})")
        try:
            dynamics = Dynamics.from_dataset(ds)
            obs = ObservationModel.from_model(model, spatial=bool(int(ds.attrs["spatial"])))
            if not int(ds.attrs["memoryless"]):  # the filter's scale, as in from_model
                from .glrm.calibration import variance_scale

                obs = replace(obs, variance_scale=variance_scale(model, temporal=True))
            ev = [float(ds.attrs.get(key, 0.0)) for key in ("day_q", "day_n", "scale_q",
                                                            "scale_n")]
            post = LatentPosterior(obs, ds["precision"].values, ds["shift"].values,
                                   ds["base_precision"].values, ds["base_shift"].values,
                                   ds["cells"].values.astype(np.int64),
                                   ds["values"].values.astype(np.float64),
                                   int(ds.attrs.get("posterior_n_dropped", 0)), *ev)
            kind = str(ds.attrs["time_kind"])
            t = _coerce_time(ds.attrs["time"], kind, str(ds.attrs.get("calendar")) or None)
            if kind == "numeric":
                t = float(t)
        except (KeyError, ValueError) as exc:
            raise DataError(f"state file {spath!r} is incomplete or corrupt: {exc}") from None
        if dynamics is None:
            raise DataError(f"state file {spath!r} has no dynamics")
        dynamics = replace(dynamics, time=t)
        state = cls(model, post, t, dynamics, observed=bool(int(ds.attrs["observed"])),
                    memoryless=bool(int(ds.attrs["memoryless"])),
                    n_assimilated=int(ds.attrs["n_assimilated"]),
                    n_dropped=int(ds.attrs["n_dropped"]))
        state.model_path = mpath
        return state

    def __repr__(self) -> str:
        return (f"MonitorState(time={time_label(self.time)}, observed={self.observed}, "
                f"dynamics={'memoryless' if self.memoryless else self.dynamics.kind}, "
                f"n_obs_today={self.posterior.cells.size}, n_assimilated={self.n_assimilated})")


def _time_array(values: list) -> np.ndarray:
    if any(isinstance(v, np.datetime64) for v in values):
        return np.asarray(values, dtype="datetime64[ns]")
    if any(hasattr(v, "calendar") for v in values):
        arr = np.empty(len(values), dtype=object)
        arr[:] = values
        return arr
    return np.asarray(values, dtype=np.float64)
