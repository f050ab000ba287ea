"""The monitoring filter against a naive dense Kalman filter and the
memoryless fold-in; observations in every form; save/load; bad input."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.belief.posterior import empirical_moments
from lrm_cvx.errors import DataError, ModelError, RegionError
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import prediction_factor
from lrm_cvx.glrm.dynamics import Dynamics
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.monitor import MonitorState


@pytest.fixture(scope="module")
def field():
    return synthetic_dynamic_field(36, (7, 8), 3, seed=4, noise=0.03)


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(3, progress=False, max_iter=30, random_state=0, **kw).fit(data)


@pytest.fixture(scope="module")
def model(field):
    return _fit(field.isel(time=slice(0, 30)), temporal="ar1", offset=True, scale=True,
                noise="per-cell")


@pytest.fixture(scope="module")
def plain(field):
    return _fit(field.isel(time=slice(0, 30)))


def _naive_kalman(m, P, A, Q, c, H, R, z):
    """One dense predict + update step (textbook form, no information-form shortcuts)."""
    m = A @ m + c
    P = A @ P @ A.T + Q
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    m = m + K @ (z - H @ m)
    P = (np.eye(len(m)) - K @ H) @ P
    return m, 0.5 * (P + P.T)


def test_filter_matches_a_naive_kalman_filter(model, field):
    """Offset, scale and per-cell noise: z = (v - offset) / scale, R = diag(noise_var)."""
    rng = np.random.default_rng(0)
    dyn = model.dynamics_
    state = MonitorState.from_model(model)
    Y = model._Yv
    off, sc, nv = model.offset_, model.scale_, model.noise_var_ * prediction_factor(model)
    m = dyn.initial_mean.copy()
    P = dyn.initial_cov + 1e-9 * np.trace(dyn.Q) / 3 * np.eye(3)
    days = [30, 31, 33, 34]  # a missed day: two steps
    prev = field.time.values[29]
    for day in days:
        t = field.time.values[day]
        cells = rng.choice(model.n_cells_, 6, replace=False)
        vals = rng.normal(0.4, 0.1, 6)
        n = int((t - prev) / np.timedelta64(1, "D"))
        An = np.linalg.matrix_power(dyn.A, n)
        Qn = sum(np.linalg.matrix_power(dyn.A, j) @ dyn.Q @ np.linalg.matrix_power(dyn.A, j).T
                 for j in range(n))
        c = dyn.mean - An @ dyn.mean
        m, P = _naive_kalman(m, P, An, Qn, c, Y[:, cells].T, np.diag(nv[cells]),
                             (vals - off[cells]) / sc[cells])
        state.assimilate((cells, vals), t)
        np.testing.assert_allclose(state.posterior.mean, m, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(state.posterior.cov, P, rtol=1e-7, atol=1e-12)
        prev = t
    ds = state.predict()
    mean = model.region_.stack(ds["mean"])
    std = model.region_.stack(ds["std"])
    np.testing.assert_allclose(mean, sc * (Y.T @ m) + off, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(std, sc * np.sqrt(np.einsum("ai,ab,bi->i", Y, P, Y)), rtol=1e-4)
    pstd = model.region_.stack(ds["predictive_std"])
    np.testing.assert_allclose(pstd, sc * np.sqrt(np.einsum("ai,ab,bi->i", Y, P, Y) + nv),
                               rtol=1e-4)


def test_forecast_is_the_propagated_belief(model):
    state = MonitorState.from_model(model)
    dyn = model.dynamics_
    ds = state.forecast()
    assert ds["time"].values == state.time + np.timedelta64(1, "D")
    P0 = dyn.initial_cov + 1e-9 * np.trace(dyn.Q) / 3 * np.eye(3)
    m1 = dyn.A @ dyn.initial_mean + dyn.mean - dyn.A @ dyn.mean
    P1 = dyn.A @ P0 @ dyn.A.T + dyn.Q
    Y, sc, off = model._Yv, model.scale_, model.offset_
    np.testing.assert_allclose(model.region_.stack(ds["mean"]), sc * (Y.T @ m1) + off,
                               rtol=1e-5)
    np.testing.assert_allclose(model.region_.stack(ds["std"]),
                               sc * np.sqrt(np.einsum("ai,ab,bi->i", Y, P1, Y)), rtol=1e-4)
    assert np.all(model.region_.stack(ds["predictive_std"]) > model.region_.stack(ds["std"]))
    assert state.posterior.cells.size == 0 and state.observed  # forecast does not move it


def test_zero_dynamics_reproduce_the_memoryless_fold_in(plain, field):
    """A = 0, Q = cov(X_), mean(X_): every day is complete(..., prior="empirical")."""
    m0, S0 = empirical_moments(plain._Xv)
    k = 3
    dyn = Dynamics(kind="ar1", A=np.zeros((k, k)), Q=S0, mean=m0,
                   initial_mean=plain._Xv[:, -1], initial_cov=S0, step=1.0,
                   time_kind="datetime")
    explicit = MonitorState.from_model(plain, dynamics=dyn)
    default = MonitorState.from_model(plain)  # a model without dynamics: memoryless
    assert default.memoryless
    rng = np.random.default_rng(1)
    for day in (30, 31, 32):
        snap = field.isel(time=day)
        keep = xr.DataArray(rng.random(snap.shape) < 0.2, dims=snap.dims, coords=snap.coords)
        obs = snap.where(keep)
        ref = plain.complete(obs, prior="empirical")
        for state in (explicit, default):
            state.assimilate(obs, snap.time.values)
            ds = state.predict()
            np.testing.assert_allclose(ds["mean"].values, ref["prediction"].values,
                                       rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(ds["std"].values, ref["std"].values, rtol=1e-8,
                                       atol=1e-12)


def test_observation_forms_agree(model, field):
    snap = field.isel(time=30)
    region = model.region_
    vals = region.stack(snap).astype(np.float64)
    cells = np.flatnonzero(np.isfinite(vals))[:8]
    t = snap.time.values
    a = MonitorState.from_model(model).assimilate((cells, vals[cells]), t)
    grid = region.unstack(np.where(np.isin(np.arange(vals.size), cells), vals, np.nan))
    b = MonitorState.from_model(model).assimilate(grid, t)
    table = pd.DataFrame({"lat": region.cell_lat[cells], "lon": region.cell_lon[cells],
                          "value": vals[cells]})
    c = MonitorState.from_model(model).assimilate(table, str(pd.Timestamp(t).date()))
    for s in (b, c):
        np.testing.assert_allclose(s.posterior.mean, a.posterior.mean, rtol=1e-12)
        assert s.n_assimilated == 8
    # NaN values are ignored and counted
    table.loc[0, "value"] = np.nan
    d = MonitorState.from_model(model).assimilate(table, t)
    assert d.n_assimilated == 7 and d.n_dropped == 1


def test_time_order_is_enforced(model, field):
    state = MonitorState.from_model(model)
    t30, t31 = field.time.values[30], field.time.values[31]
    with pytest.raises(DataError, match="earlier than"):
        state.assimilate(([0], [0.3]), field.time.values[10])
    with pytest.raises(DataError, match="equal to"):
        state.assimilate(([0], [0.3]), field.time.values[29])  # the last fitted snapshot
    state.assimilate(([0], [0.3]), t31)
    with pytest.raises(DataError, match="earlier than"):
        state.assimilate(([1], [0.3]), t30)
    before = state.posterior.mean.copy()
    state.assimilate(([1], [0.3]), t31, force=True)  # more observations of the same day
    assert state.posterior.cells.tolist() == [0, 1]
    assert not np.allclose(before, state.posterior.mean)
    with pytest.raises(DataError, match="time must be a date"):
        state.assimilate(([1], [0.3]), "not a date")


def test_public_belief_api_of_replanning(model, field):
    """``belief`` / ``plan_time`` / ``time_after`` / ``assimilate_today``: the public form of
    what replanning and the CLI read (the forecast's belief, the day a plan is for, more of
    today's observations added to the same snapshot)."""
    state = MonitorState.from_model(model)
    t29, t30, t31 = field.time.values[29:32]
    assert state.plan_time() == t30 and state.plan_time(t31) == t31
    assert state.time_after(t31) == 2 and state.time_after(t29) == 0
    assert state.time_after(field.time.values[27]) == -2
    with pytest.raises(DataError, match="--time"):
        state.time_after("not a date", "--time")
    prior = state.belief()  # tomorrow's forecast, the state unchanged
    dyn = model.dynamics_
    np.testing.assert_allclose(prior.mean, dyn.A @ dyn.initial_mean + dyn.mean
                               - dyn.A @ dyn.mean, rtol=1e-9)
    assert state.time == t29 and state.posterior.cells.size == 0
    ref = MonitorState.from_model(model).assimilate(([0], [0.3]), t30).assimilate(([1], [0.2]), t30,
                                                                    force=True)
    state.assimilate_today(([0], [0.3]), t30)  # a new day: in time order
    state.assimilate_today(([1], [0.2]), t30)  # more of it: added, not refused
    assert state.posterior.cells.tolist() == [0, 1]
    np.testing.assert_allclose(state.posterior.mean, ref.posterior.mean, rtol=1e-12)
    np.testing.assert_allclose(state.belief(t30).mean, state.posterior.mean)  # today: posterior
    with pytest.raises(DataError, match="earlier than"):
        state.assimilate_today(([2], [0.1]), t29)


def test_monitor_at_a_time_accepts_that_day(model, field):
    t = field.time.values[32]
    state = MonitorState.from_model(model, time=t)
    assert not state.observed and state.time == t
    # three steps from the last fitted day (29)
    A3 = np.linalg.matrix_power(model.dynamics_.A, 3)
    np.testing.assert_allclose(state.posterior.mean,
                               A3 @ model.dynamics_.initial_mean
                               + model.dynamics_.mean - A3 @ model.dynamics_.mean)
    ds = state.forecast()
    assert ds["time"].values == t
    state.assimilate(([0, 1, 2], [0.3, 0.4, 0.5]), t)
    assert state.observed


def test_bad_observations(model, field):
    state = MonitorState.from_model(model)
    t = field.time.values[30]
    region = model.region_
    with pytest.raises(RegionError, match="outside the region"):
        state.assimilate(([0, model.n_cells_ + 3], [0.1, 0.2]), t)
    with pytest.raises(RegionError, match="masked"):
        masked = np.argwhere(~region.mask)[0]
        state.assimilate(pd.DataFrame({"lat": [region.lat.values[masked[0]]],
                                       "lon": [region.lon.values[masked[1]]],
                                       "value": [0.2]}), t)
    with pytest.raises(RegionError):
        state.assimilate(pd.DataFrame({"lat": [80.0], "lon": [0.0], "value": [0.2]}), t)
    grid = xr.full_like(field.isel(time=30), np.nan)
    r, c = np.argwhere(~region.mask)[0]
    grid[r, c] = 0.5
    with pytest.raises(RegionError, match="masked cell"):
        state.assimilate(grid, t)
    with pytest.raises(DataError, match="lat, lon, value"):
        state.assimilate(pd.DataFrame({"lat": [0.0], "value": [1.0]}), t)
    with pytest.raises(DataError, match="integer"):
        state.assimilate(([0.5], [0.1]), t)
    with pytest.raises(DataError, match="observations must be"):
        state.assimilate([1, 2, 3], t)
    assert state.posterior.cells.size == 0 and state.time == field.time.values[29]


def test_duplicate_cells_are_repeated_measurements(plain, field):
    t = field.time.values[30]
    once = MonitorState.from_model(plain).assimilate(([3, 3], [0.4, 0.4]), t)
    twice = (MonitorState.from_model(plain).assimilate(([3], [0.4]), t)
             .assimilate(([3], [0.4]), t, force=True))
    np.testing.assert_allclose(once.posterior.precision, twice.posterior.precision)


def test_planner_kwargs_have_the_forecast_prior(model, plain):
    state = MonitorState.from_model(model)
    kw = state.planner_kwargs(criterion="fisher")["prior"]
    P1 = np.linalg.inv(state._propagated(state.next_time()).cov)
    np.testing.assert_allclose(kw.prior_precision, P1, rtol=1e-6)
    np.testing.assert_allclose(kw.noise_var, model.noise_var_ * prediction_factor(model))
    np.testing.assert_allclose(kw.target_weights, model.scale_ ** 2)
    assert kw.spatial_cov is None
    with pytest.raises(ModelError, match="gp-variance"):
        state.planner_kwargs(criterion="gp-variance")
    from lrm_cvx.planning import plan_greedy

    for crit in ("fisher", "a-optimal"):
        plan = plan_greedy(model._Yv, model.region_, 0, 5, criterion=crit, progress=False,
                           initial="start", **state.planner_kwargs(criterion=crit))
        assert plan.cells.size >= 1


def test_planner_kwargs_gp_variance(field):
    model = _fit(field.isel(time=slice(0, 30)), temporal="ar1", spatial="exponential")
    state = MonitorState.from_model(model)
    kw = state.planner_kwargs()
    f = prediction_factor(model)  # a new snapshot's residual (calibrated.prediction_factor)
    assert kw["prior"].spatial_cov == replace(model.spatial_cov_,
                                              sill=model.spatial_cov_.sill * f,
                                              nugget=model.spatial_cov_.nugget * f)
    np.testing.assert_allclose(kw["prior"].prior_cov, state._propagated(state.next_time()).cov)
    from lrm_cvx.planning import plan_greedy

    plan = plan_greedy(model._Yv, model.region_, 0, 4, criterion="gp-variance",
                       progress=False, initial="start", **kw)
    state.assimilate((plan.cells, model.region_.stack(field.isel(time=30))[plan.cells]),
                     field.time.values[30])
    assert np.isfinite(state.predict()["std"]).any()


def test_save_load_round_trip(model, plain, field, tmp_path):
    state = MonitorState.from_model(model)
    state.assimilate(([0, 5, 9], [0.3, np.nan, 0.5]), field.time.values[31])
    path = tmp_path / "state.nc"
    state.save(path)
    back = MonitorState.load(path, model)
    assert back.time == state.time and back.observed and back.n_dropped == 1
    np.testing.assert_allclose(back.posterior.mean, state.posterior.mean, rtol=1e-12)
    np.testing.assert_allclose(back.posterior.cov, state.posterior.cov, rtol=1e-10)
    np.testing.assert_array_equal(back.posterior.cells, state.posterior.cells)
    xr.testing.assert_allclose(back.forecast(), state.forecast())
    with pytest.raises(ModelError, match="another model"):
        MonitorState.load(path, plain)
    with pytest.raises(ModelError, match="no model file"):
        MonitorState.load(path)
    data = path.read_bytes()
    (tmp_path / "trunc.nc").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="corrupt or truncated"):
        MonitorState.load(tmp_path / "trunc.nc", model)
    with pytest.raises(DataError, match="does not exist"):
        MonitorState.load(tmp_path / "nope.nc", model)
    xr.Dataset({"a": ("x", [1.0])}).to_netcdf(tmp_path / "other.nc")
    with pytest.raises(DataError, match="not an lrm-cvx monitor state"):
        MonitorState.load(tmp_path / "other.nc", model)


def test_save_is_atomic(model, field, tmp_path, monkeypatch):
    path = tmp_path / "state.nc"
    state = MonitorState.from_model(model)
    state.save(path)
    before = path.read_bytes()
    state.assimilate(([0], [0.3]), field.time.values[30])

    def boom(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", boom)
    with pytest.raises(OSError):
        state.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert MonitorState.load(path, model).time == field.time.values[29]
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def test_seasonal_and_monthly_states(tmp_path):
    da = synthetic_dynamic_field(40, (5, 6), 2, seed=0, seasonal_period=12, freq="MS")
    model = _fit(da.isel(time=slice(0, 36)), temporal="seasonal")
    state = MonitorState.from_model(model)
    nxt = state.next_time()
    assert pd.Timestamp(nxt) == pd.Timestamp(da.time.values[36])
    ds = state.forecast()
    dyn = model.dynamics_
    m = dyn.season_mean(nxt) + dyn.A @ (dyn.initial_mean - dyn.season_mean(state.time))
    np.testing.assert_allclose(model.region_.stack(ds["mean"]), model._Yv.T @ m, rtol=1e-5)
    state.assimilate(da.isel(time=36), da.time.values[36])
    state.save(tmp_path / "s.nc")
    back = MonitorState.load(tmp_path / "s.nc", model)
    assert back.dynamics.kind == "seasonal"
    np.testing.assert_allclose(back.posterior.mean, state.posterior.mean)


def test_model_without_region_and_numeric_times(field):
    from lrm_cvx.region import Region

    D = Region.from_dataarray(field).stack(field).astype(np.float64)
    model = _fit(D[:30], temporal="ar1")
    state = MonitorState.from_model(model)
    assert state.time == 29
    state.assimilate((np.arange(10), D[30, :10]), 30)
    ds = state.predict()
    assert ds["mean"].dims == ("cell",) and float(ds["time"]) == 30.0


def test_cftime_calendar_end_to_end(tmp_path):
    da = synthetic_dynamic_field(40, (5, 6), 2, seed=0, seasonal_period=12, freq="MS")
    times = xr.date_range("2001-01-01", periods=40, freq="MS", calendar="noleap",
                          use_cftime=True)
    da = da.assign_coords(time=times)
    model = _fit(da.isel(time=slice(0, 36)), temporal="seasonal")
    assert model.dynamics_.time_kind == "cftime"
    state = MonitorState.from_model(model)
    assert state.next_time() == times[36]
    state.assimilate(da.isel(time=36), da.time.values[36])
    state.assimilate(da.isel(time=37), "2004-02-01")  # a string in the model's calendar
    assert state.time == times[37]
    model.save(tmp_path / "m.nc")
    state.save(tmp_path / "s.nc")
    back = MonitorState.load(tmp_path / "s.nc", GLRM.load(tmp_path / "m.nc"))
    assert back.time == times[37] and back.forecast()["time"].values == times[38]
    with pytest.raises(DataError, match="forward only"):
        back.forecast("2003-01-01")


def test_model_fingerprint_is_remembered_until_a_refit(field):
    """The remembered fingerprint equals a fresh hash, and a refit (new factor arrays) is
    hashed again: a state started from the old factors cannot pass for the new ones."""
    import hashlib

    from lrm_cvx.belief.filter import model_fingerprint

    def fresh(m):
        h = hashlib.sha256()
        for arr in (m.X, m.Y, m.offset_, m.scale_):
            if arr is not None:
                a = np.ascontiguousarray(np.asarray(arr, dtype=np.float64))
                h.update(str(a.shape).encode())
                h.update(a.tobytes())
        return h.hexdigest()[:16]

    m = _fit(field.isel(time=slice(0, 20)), offset=True)
    first = model_fingerprint(m)
    assert first == fresh(m) == model_fingerprint(m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m.fit(field.isel(time=slice(10, 30)))
    assert model_fingerprint(m) == fresh(m) != first
