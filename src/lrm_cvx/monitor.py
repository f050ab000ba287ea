"""The monitoring filter: a Kalman filter on the latent vector of a fitted GLRM.

:class:`MonitorState` carries the Gaussian belief about the current snapshot's latent vector
(a :class:`~lrm_cvx.belief.posterior.LatentPosterior`, the same fold-in algebra as
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

import os
from dataclasses import replace
from typing import Any

import numpy as np
import xarray as xr

from ._validation import atomic_output, read_netcdf
from .belief.filter import (
    LatentFilter,
    coerce_time,
    filter_observation_model,
    model_fingerprint,
    time_label,
    time_to_str,
)
from .belief.posterior import LatentPosterior
from .errors import DataError, ModelError
from .glrm.calibrated import ONLINE_GAMMA, AdaptiveConformal
from .glrm.dynamics import Dynamics
from .planning.terms import PriorTerms
from .recommended import recommended_criterion

__all__ = ["MonitorState"]

_FORMAT = "lrm-cvx MonitorState"
_FORMAT_VERSION = 1


# ----------------------------------------------------------------------------- the state
class MonitorState(LatentFilter):
    """The filter's belief about the latent vector of the snapshot at ``time``.

    Build with :meth:`from_model` (inherited from the filter core,
    :class:`~lrm_cvx.belief.filter.LatentFilter`, which also holds ``assimilate``). ``posterior``
    is the :class:`~lrm_cvx.belief.posterior.LatentPosterior` of the current snapshot (its
    ``cells`` and ``values`` are today's observations), ``observed`` whether the snapshot at
    ``time`` has been observed (the last fitted snapshot counts as observed; a state positioned
    at a later time by ``from_model(model, time=T)`` has not, so observations at ``T`` are
    accepted). Mutating methods return ``self``.

    ``current_plan`` is the day's route plan (a :class:`~lrm_cvx.planning.Plan`, or None) and
    ``current_plan_time`` the time it was planned for: what ``lrm-cvx monitor plan`` stored
    and ``monitor replan`` replans; :meth:`save` writes them into the state file (``plan_*``
    variables) and :meth:`load` reads them back equal.
    """

    current_plan: Any = None
    current_plan_time: Any = None

    @classmethod
    def from_model(cls, model: Any, time: Any = None, *, dynamics: Any = None,
                   spatial: bool | None = None, memoryless: bool | None = None,
                   online: bool = True) -> MonitorState:
        """A state after the last fitted snapshot, or forecast to ``time`` (see
        :meth:`LatentFilter.from_model <lrm_cvx.belief.filter.LatentFilter.from_model>`).

        ``online`` (default True): the intervals recalibrate themselves day by day
        (:meth:`adaptive_conformal` with ``gamma`` :data:`~lrm_cvx.glrm.calibrated.ONLINE_GAMMA`):
        each :meth:`assimilate` first scores the forecast at the day's sampled cells, before
        they are assimilated, and moves the 68 % and 95 % thresholds towards their nominal
        coverage, starting from the model's offline (conformal) thresholds; the state file
        carries them. ``online=False``: the offline thresholds throughout. The maps, plans
        and the belief are the same either way."""
        state = super().from_model(model, time, dynamics=dynamics, spatial=spatial,
                                   memoryless=memoryless)
        if online:
            state.adaptive_conformal(gamma=ONLINE_GAMMA)
        return state

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
        t = self.plan_time(time)
        return self._dataset(*self.belief(t).predict_all(), t, "forecast")

    def belief(self, time: Any = None) -> LatentPosterior:
        """The latent belief about the snapshot at ``time`` (default as :meth:`forecast`): the
        posterior when ``time`` is the state's own time, else the forecast carried there. What
        a plan for that snapshot targets (:meth:`planner_kwargs`, replanning). Does not change
        the state."""
        return self._post_at(self.plan_time(time))[0]

    def assimilate_today(self, observations: Any, time: Any) -> MonitorState:
        """:meth:`assimilate` ``observations`` at ``time``, *added* to the snapshot when the
        state has already observed ``time`` (more of today's measurements: a replan en route),
        else as a new day (in time order). Returns ``self``."""
        t = self._coerce(time)
        return self.assimilate(observations, t, force=bool(self.observed and self._dt(t) == 0))

    def time_after(self, time: Any, name: str = "time") -> float:
        """How far ``time`` lies after the state's time, in the filter's time unit (negative:
        before it; 0: the state's own snapshot). ``name`` labels a bad time's error."""
        return self._dt(self._coerce(time, name))

    def plan_time(self, time: Any = None) -> Any:
        """The snapshot a plan for ``time`` is for: ``time`` (not before the state's), or by
        default the next step, the state's own time while it is not observed yet."""
        if time is not None:
            t = self._coerce(time)
            if self._dt(t) < 0:
                raise DataError(f"time {time_label(t)} is earlier than the state's time "
                                f"{time_label(self.time)}: the filter forecasts forward only")
            return t
        return self.time if not self.observed else self.next_time()

    def as_time(self, time: Any, name: str = "time") -> Any:
        """``time`` (a string, date or number) as a time of the model's record, in its
        calendar; DataError naming ``name`` otherwise (a date the record's type cannot hold
        included)."""
        return self._coerce(time, name)

    def same_snapshot(self, a: Any, b: Any, name: str = "time") -> bool:
        """Whether times ``a`` and ``b`` lie in the period of one stamp of the record (its
        calendar month for a monthly record, its day for a daily one: see
        :class:`~lrm_cvx.belief.calendar.RecordCalendar`). ``name`` labels a bad ``a``'s error."""
        return self.record_calendar.same_period(self._coerce(a, name), self._coerce(b))

    def observation_time(self, time: Any, name: str = "time") -> Any:
        """The snapshot observations taken at ``time`` belong to: the stored plan's time
        (``current_plan_time``) when ``time`` lies in its period, else the state's own time
        when ``time`` lies in the period of the state's snapshot, else ``time``."""
        t = self._coerce(time, name)
        cal = self.record_calendar
        plan_t = self.current_plan_time
        if plan_t is not None and cal.same_period(t, plan_t):
            return plan_t
        if cal.same_period(t, self.time):
            return self.time
        return t

    def forced_move(self, time: Any) -> str | None:
        """What assimilating at ``time`` with ``force`` does when it is not the ordinary step
        onto the record's next stamp (one line for the user), else None."""
        t = self._coerce(time)
        here, there = time_label(self.time), time_label(t)
        dt = self._dt(t)
        if dt == 0:
            return (f"the observations are added to the snapshot at {here}, already observed "
                    "(no step)") if self.observed else None
        if dt < 0:
            return (f"{there} is earlier than the state's time {here}: the filter moves one "
                    f"step, to {there}")
        n = self.dynamics.n_steps(self.time, t)
        nxt = self.next_time() if self.observed else self.time
        if n == 1 and self._dt(nxt) == dt:
            return None
        other = "" if self._dt(nxt) == dt else f" (the record's next stamp is {time_label(nxt)})"
        return f"the filter moves {n} step{'s' if n > 1 else ''}, from {here} to {there}{other}"

    def replan(self, plan: Any, done: Any, observations: Any = None, *, time: Any = None,
               criterion: str | None = None, refine: Any = "auto",
               progress: bool = False) -> Any:
        """Replan the rest of ``plan`` en route: fold in ``observations`` (today's measurements
        so far) at ``time``, keep each robot's first ``done`` route entries, and plan the rest
        from where it is with the budget left and the same end (home for a closed tour), under
        the same path model and, by default, the same check against rival routes. See
        :func:`lrm_cvx.replanning.replan`.

        ``plan=None`` replans ``current_plan`` (ModelError when there is none), and ``time``
        then defaults to ``current_plan_time``. The new plan becomes ``current_plan``, planned
        for ``time`` (default as :meth:`forecast`)."""
        from .replanning import replan

        if plan is None:
            if self.current_plan is None:
                raise ModelError("the state holds no plan to replan: plan the day first "
                                 "(lrm-cvx monitor plan)")
            plan = self.current_plan
        if time is None and plan is self.current_plan:
            time = self.current_plan_time
        new = replan(self, plan, done, observations, time=time, criterion=criterion,
                     refine=refine, progress=progress)
        self.current_plan = new
        self.current_plan_time = self.time if observations is not None else \
            self.plan_time(time)
        return new

    def explore(self, plan: Any = None, *, forecast: bool = False, time: Any = None,
                tiles: Any = "auto") -> Any:
        """An interactive ``folium.Map`` of the belief, for a notebook or a field laptop.

        The belief's mean, ``std`` and ``predictive_std`` are layers (the posterior, or with
        ``forecast=True`` the forecast for ``time``), each with a legend in the record's units
        (its ``long_name`` and ``units`` attributes); today's samples are circles and
        ``plan``'s routes lines. Needs folium (``lrm-cvx[explore]``).

        Parameters
        ----------
        plan : Plan, optional
            Routes to draw.
        forecast : bool
            Draw the forecast for ``time`` instead of the posterior.
        time : optional
            The forecast's time (``forecast=True``).
        tiles : str, path or None
            The base map: ``"auto"`` (default) OpenStreetMap when its tile server answers,
            else none; ``None`` none; a ``{z}/{x}/{y}.png`` folder or an ``.mbtiles`` file
            written into the page for offline use; see :func:`lrm_cvx.interactive.explore_map`.

        Returns
        -------
        folium.Map
            Shown inline in a notebook; ``.save("state.html")`` writes a page that, without
            online tiles, loads nothing from the internet.

        Examples
        --------
        >>> fmap = state.explore(plan, tiles="charts.mbtiles")  # doctest: +SKIP
        >>> fmap.save("state.html")  # doctest: +SKIP
        """
        from .interactive import explore_map, record_label

        ds = self.forecast(time) if forecast else self.predict()
        region = self.model.region_
        if region is None:
            raise DataError("an interactive map needs a model fitted on gridded data")
        what = "forecast" if forecast else "posterior"
        quantity, units = record_label(region.attrs, region.name)
        fields = {f"{what} mean": (ds["mean"].values, "viridis", units),
                  "std": (ds["std"].values, "magma", units),
                  "predictive std": (ds["predictive_std"].values, "magma", units)}
        cells = np.asarray(self.posterior.cells, dtype=np.int64)
        values = np.asarray(self.posterior.values, dtype=np.float64)
        stops = [(region.cell_lat[c], region.cell_lon[c], f"cell {int(c)}: {v:.4g}")
                 for c, v in zip(cells, values, strict=True)]
        routes = [] if plan is None else [
            (plan.lat[plan.route_robot == r], plan.lon[plan.route_robot == r])
            for r in range(plan.n_robots)]
        return explore_map(region.lat.values, region.lon.values, fields, routes=routes,
                           stops=stops, tiles=tiles, quantity=quantity)

    def predict(self) -> xr.Dataset:
        """Posterior ``mean``, ``std`` and ``predictive_std`` maps of the snapshot at the
        state's time (a Dataset on ``(lat, lon)``, scalar ``time`` coordinate)."""
        return self._dataset(*self.posterior.predict_all(), self.time, "posterior")

    def planner_kwargs(self, criterion: str | None = None, time: Any = None) -> dict:
        """Keyword arguments of :func:`~lrm_cvx.planning.plan_greedy` with the prior of the
        next plan, ``{"prior": PriorTerms(...)}``: the forecast for ``time`` (default as
        :meth:`forecast`). ``criterion``
        ``"fisher"``/``"a-optimal"`` drop the spatial terms ``"gp-variance"`` needs; None (the
        default) is the recommended criterion (``RECOMMENDED["criterion"]``) when the state
        has the spatial residual it needs, else ``"fisher"``."""
        kw = self.belief(time).information()
        if criterion is None:
            criterion = recommended_criterion("spatial_cov" in kw)
        if criterion != "gp-variance":
            kw = {k: v for k, v in kw.items() if k not in ("prior_cov", "spatial_cov")}
        elif "spatial_cov" not in kw:
            raise ModelError("criterion 'gp-variance' needs a model fitted with spatial=... "
                             "(use 'fisher' or 'a-optimal')")
        return {"prior": PriorTerms(**kw)}

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
        if p.rows is not None and p.rows.shape[0] > 0:  # today's averaged observations
            coo = p.rows.tocoo()
            ds["row_index"] = (("row_entry",), coo.row.astype(np.int64))
            ds["row_cell"] = (("row_entry",), coo.col.astype(np.int64))
            ds["row_weight"] = (("row_entry",), coo.data.astype(np.float64))
            ds["row_values"] = (("averaged",), np.asarray(p.row_values, dtype=np.float64))
            ds["row_noise"] = (("averaged",), np.asarray(p.row_noise, dtype=np.float64))
        dyn_vars, dyn_attrs = self.dynamics.to_dataset_vars()
        for name, value in dyn_vars.items():
            ds[name] = value
        ds.attrs = {
            "format": _FORMAT, "format_version": _FORMAT_VERSION,
            "fingerprint": self.fingerprint, "time": time_to_str(self.time),
            "time_kind": self._time_kind, "calendar": self._calendar or "",
            "observed": int(self.observed), "memoryless": int(self.memoryless),
            "spatial": int(p.obs_model.is_spatial), "n_assimilated": self.n_assimilated,
            "n_dropped": self.n_dropped, "posterior_n_dropped": int(p.n_dropped),
            "day_q": float(p.day_q), "day_n": float(p.day_n), "scale_q": float(p.scale_q),
            "scale_n": float(p.scale_n),
            "model_path": str(getattr(self, "model_path", "") or ""),
            **dyn_attrs,
        }
        if self.current_plan is not None:  # the day's route plan (lrm-cvx monitor replan)
            from .replanning import plan_variables

            variables, attrs = plan_variables(self.current_plan)
            for name, value in variables.items():
                ds[name] = value
            ds.attrs.update(attrs, plan_time=time_to_str(self.current_plan_time))
        ds.attrs["online_calibration"] = int(self.aci is not None)
        if self.aci is not None:  # the online conformal state (adaptive_conformal)
            ds.attrs.update(self.aci.to_attrs())
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
        the state, ``model_path``; a relative one is taken from the state file's folder, a URL
        is refused) must be the model the state was started from (same fingerprint), else
        ModelError; a missing, corrupt or truncated file is a DataError."""
        spath = os.fspath(path)
        ds = read_netcdf(path, "state file", "MonitorState.save")
        need = ("precision", "shift", "base_precision", "base_shift", "cells", "values")
        if ds.attrs.get("format") != _FORMAT or any(n not in ds for n in need):
            raise DataError(f"{spath!r} is not an lrm-cvx monitor state file")
        if model is None:
            mpath = ds.attrs.get("model_path", "")
            if not mpath:
                raise ModelError(f"state file {spath!r} records no model file; pass the model")
            mpath = _recorded_model_path(spath, str(mpath))
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
            obs = filter_observation_model(model, bool(int(ds.attrs["spatial"])),
                                           bool(int(ds.attrs["memoryless"])))
            ev = [float(ds.attrs.get(key, 0.0)) for key in ("day_q", "day_n", "scale_q",
                                                            "scale_n")]
            post = LatentPosterior(obs, ds["precision"].values, ds["shift"].values,
                                   ds["base_precision"].values, ds["base_shift"].values,
                                   ds["cells"].values.astype(np.int64),
                                   ds["values"].values.astype(np.float64),
                                   int(ds.attrs.get("posterior_n_dropped", 0)), *ev,
                                   *_saved_rows(ds, obs.n_cells))
            kind = str(ds.attrs["time_kind"])
            t = coerce_time(ds.attrs["time"], kind, str(ds.attrs.get("calendar")) or None)
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
        if "plan_route" in ds:
            from .replanning import plan_from_variables

            try:
                state.current_plan = plan_from_variables(ds, model.region_, model.Y)
                pt = coerce_time(ds.attrs["plan_time"], kind,
                                 str(ds.attrs.get("calendar")) or None)
            except (KeyError, ValueError) as exc:
                raise DataError(f"state file {spath!r} holds an incomplete or corrupt plan: "
                                f"{exc}") from None
            state.current_plan_time = float(pt) if kind == "numeric" else pt
        try:
            state.aci = AdaptiveConformal.from_attrs(ds.attrs, post.obs_model.calibration)
            online = int(ds.attrs.get("online_calibration", 1))
        except (ModelError, TypeError, ValueError) as exc:
            raise DataError(f"state file {spath!r}: {exc}") from None
        if state.aci is None and online:  # a state file without one: from the offline ones
            state.adaptive_conformal(gamma=ONLINE_GAMMA)
        return state

    def __repr__(self) -> str:
        return (f"MonitorState(time={time_label(self.time)}, observed={self.observed}, "
                f"dynamics={'memoryless' if self.memoryless else self.dynamics.kind}, "
                f"n_obs_today={self.posterior.cells.size}, n_assimilated={self.n_assimilated})")


def _recorded_model_path(spath: str, mpath: str) -> str:
    """The model file a state file at ``spath`` records as ``mpath``: a relative path is
    resolved against the state file's folder (not the current one); a URL is a DataError (a
    state file is untrusted input: it must not make the command contact a server)."""
    if "://" in mpath:
        raise DataError(f"state file {spath!r} records its model as the URL {mpath!r}; a "
                        "state's model must be a local file: pass the model file")
    if not os.path.isabs(mpath):
        mpath = os.path.join(os.path.dirname(os.path.abspath(spath)), mpath)
    return mpath


def _saved_rows(ds: xr.Dataset, n_cells: int) -> tuple:
    """``(rows, row_values, row_noise)`` of the averaged observations a state file holds (the
    posterior's defaults when none)."""
    if "row_values" not in ds:
        return None, np.zeros(0), np.zeros(0)
    import scipy.sparse as sps

    values = ds["row_values"].values.astype(np.float64)
    rows = sps.csr_matrix((ds["row_weight"].values, (ds["row_index"].values,
                                                     ds["row_cell"].values)),
                          shape=(values.size, n_cells))
    return rows, values, ds["row_noise"].values.astype(np.float64)
