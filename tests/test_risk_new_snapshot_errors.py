"""The static risk scores a placement on a *new* snapshot's errors (planning/static.py,
``error_factor`` / ``fitted_on``): when the training snapshots are the model's own, each
cell's fitted parameters have absorbed part of their residuals, so the residual part of the
training errors is scaled by ``n / (n - k)``. Checked against new snapshots of a planted field
and against the risk recomputed on hand-inflated data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.glrm import GLRM
from lrm_cvx.planning import place_sensors
from lrm_cvx.planning import static as st

SIGMA = 0.5


def _planted(seed: int, T: int, ny: int = 30, nx: int = 40, rank: int = 2):
    """``(draw, factors)``: ``draw(T)`` gives ``T`` snapshots of one rank-``rank`` field plus a
    per-cell mean and white noise of std :data:`SIGMA`, on fixed coordinates."""
    rng = np.random.default_rng(seed)
    lat, lon = np.arange(ny) * 1.0, np.arange(nx) * 1.0
    Y = rng.normal(size=(rank, ny, nx))
    mean = rng.normal(size=(ny, nx))

    def draw(n: int, t0: int = 0) -> xr.DataArray:
        x = rng.normal(size=(n, rank, 1, 1)) * 2.0
        f = mean + (x * Y[None]).sum(1) + SIGMA * rng.normal(size=(n, ny, nx))
        return xr.DataArray(f, dims=("time", "lat", "lon"),
                            coords=dict(time=np.arange(t0, t0 + n), lat=lat, lon=lon))

    return draw


def _fit(train: xr.DataArray, **kw) -> GLRM:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(2, offset=True, random_state=0, progress=False, **kw).fit(train)


def _errors(model, train, inflate: bool):
    Y = np.asarray(model.Y_, np.float64)
    gp, obs = st._fold_in_from_prior(model, Y, model.region_)
    R = st.training_residuals(train, model.region_, obs, gp.mean,
                              model=model if inflate else None)
    fitted = np.asarray(model.X_, np.float64).T @ Y - gp.mean
    return R, fitted


def _by_hand(model, data):
    """``(c, V, fitted)``: the model's error factor, ``data`` stacked ``(T, L)`` (NaN gaps) and
    the model's fitted values in data units (offset included), for the references by hand."""
    V = model.region_.stack(data).astype(np.float64)
    fitted = (np.asarray(model.X_, np.float64).T @ np.asarray(model.Y_, np.float64)
              + np.asarray(model.offset_, np.float64))
    return st.error_factor(model), V, fitted


def test_the_scaled_training_residual_is_a_new_snapshots_residual():
    """Rank 2 + offset on 14 snapshots: ``k = 3``, ``c = 14 / 11``. The training residuals'
    variance is ``(11 / 14) sigma^2``; a new snapshot's residual (least-squares fold-in of
    the fitted ``Y`` from every cell) about ``(14 / 11) sigma^2``. The scaled residuals match
    the new snapshots' within 10 %, the raw ones are ~40 % short."""
    draw = _planted(0, 14)
    train = draw(14)
    model = _fit(train)
    c = st.error_factor(model)
    assert c == pytest.approx(14 / 11)
    R, fitted = _errors(model, train, inflate=True)
    R0, _ = _errors(model, train, inflate=False)
    scaled, raw = np.var(R - fitted), np.var(R0 - fitted)
    assert scaled == pytest.approx(c ** 2 * raw, rel=1e-9)
    # new snapshots of the same field, folded in by least squares from every cell
    new = model.region_.stack(draw(60, t0=100)).astype(np.float64)
    Y = np.asarray(model.Y_, np.float64)
    Z = new - np.asarray(model.offset_, np.float64)
    x, *_ = np.linalg.lstsq(Y.T, Z.T, rcond=None)
    fresh = np.var(Z - x.T @ Y)
    assert fresh > 1.2 * SIGMA ** 2  # the premise: a new snapshot errs more than sigma^2
    assert scaled == pytest.approx(fresh, rel=0.10)
    assert raw < 0.7 * fresh


def test_the_risk_is_the_risk_of_the_inflated_data_and_only_on_the_fit_snapshots():
    """``risk_objective(model, train)`` on the model's own snapshots (some values missing) equals
    the plain risk of the data whose residuals were inflated and whose gaps were filled with
    the fitted values by hand (passed as an array, so nothing is inflated or filled again); on
    other times, or as an array, the errors are as given (gaps at the prior mean)."""
    draw = _planted(1, 16, ny=8, nx=9)
    train = draw(16)
    rng = np.random.default_rng(5)
    train = train.where(rng.random(train.shape) > 0.1)
    model = _fit(train, spatial="exponential")
    c, V, fitted_data = _by_hand(model, train)
    inflated = np.where(np.isfinite(V), fitted_data + c * (V - fitted_data), fitted_data)
    cells = [3, 17, 40, 55]
    J = st.risk_objective(model, train, cells)
    assert st.fitted_on(model, train)
    assert J == pytest.approx(st.risk_objective(model, inflated, cells), rel=1e-9)
    plain = st.risk_objective(model, V, cells)  # an array: the errors as given
    assert not st.fitted_on(model, V)
    raw_filled = np.where(np.isfinite(V), V, fitted_data)  # the gaps filled, not inflated
    assert J > st.risk_objective(model, raw_filled, cells) * 1.02
    assert np.isnan(V).any() and not np.isnan(inflated).any()
    other = train.assign_coords(time=train["time"].values + 1000)
    assert not st.fitted_on(model, other)
    assert st.risk_objective(model, other, cells) == pytest.approx(plain, rel=1e-12)


def test_place_sensors_records_the_factor_and_its_objective():
    draw = _planted(2, 12, ny=8, nx=9)
    train = draw(12)
    model = _fit(train, spatial="exponential")
    plan = place_sensors(model, 5, training=train, criterion="risk")
    assert plan.refinement["training_error_factor"] == pytest.approx(12 / 9)
    assert plan.refinement["objective"] == pytest.approx(
        st.risk_objective(model, train, plan.cells), rel=1e-8)
    as_given = place_sensors(model, 5, training=train.values, criterion="risk")
    assert as_given.refinement["training_error_factor"] == 1.0
    assert as_given.refinement["objective"] == pytest.approx(
        st.risk_objective(model, train.values, as_given.cells), rel=1e-8)


def test_a_gap_in_the_training_is_the_fitted_value_not_the_mean():
    """Clouds over a planted field (``io.cloud_gaps``, 30 % of each snapshot): the risk on the
    clouded snapshots, gaps filled with the model's fitted values, is nearer the risk on the
    same snapshots without clouds than the risk with the gaps at the prior mean (the old
    rule), for every one of six random placements; the prior-mean gaps make every sensor
    under a cloud read the mean."""
    from lrm_cvx.io import cloud_gaps

    draw = _planted(3, 40, ny=20, nx=24)
    clean = draw(40)
    cloudy = cloud_gaps(clean, 0.3, seed=0)
    model = _fit(cloudy, spatial="exponential")
    region = model.region_
    c, V, fitted_data = _by_hand(model, cloudy)
    gaps_at_mean = fitted_data + c * (V - fitted_data)  # an array: NaN -> the prior mean
    rng = np.random.default_rng(0)
    for _ in range(6):
        cells = np.sort(rng.choice(region.n_cells, 12, replace=False))
        J_clean = st.risk_objective(model, clean, cells)  # the same times: inflated too
        J_fill = st.risk_objective(model, cloudy, cells)
        J_mean = st.risk_objective(model, gaps_at_mean, cells)
        assert abs(J_fill - J_clean) < 0.5 * abs(J_mean - J_clean)
