"""The filter's own conformal thresholds: a conformal calibration of a model
with dynamics also calibrates the filter's intervals on forward-chained filter residuals, the
filter uses them, and campaigns score coverage with the intervals users get."""

from __future__ import annotations

import warnings
from dataclasses import asdict, replace

import numpy as np
import pytest

from lrm_cvx import GLRM
from lrm_cvx.belief.filter import LatentFilter
from lrm_cvx.campaign import simulate_campaign
from lrm_cvx.glrm.calibrated import Calibration, conformal_quantile, gaussian_multiplier
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.validation.calibration import calibrate, cv_residuals, refit_dynamics
from lrm_cvx.validation.search import ForwardBlocks

N_TEST = 6


@pytest.fixture(scope="module")
def persistent():
    """Daily, no season, strong persistence: ``temporal="auto"`` chooses AR(1)."""
    data = synthetic_dynamic_field(80 + N_TEST, (8, 9), 3, seed=2, A=0.95 * np.eye(3),
                                   Q=0.1 * (1 - 0.95 ** 2) * np.eye(3), freq="D",
                                   missing=0.1, noise=0.1)
    train = data.isel(time=slice(None, -N_TEST))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, temporal="auto", random_state=0, progress=False).fit(train)
    return data, train, model


def test_refit_dynamics_rebuilds_the_models_own_choice(persistent):
    """A refit on the same snapshots given the model's kind and blend has the model's dynamics:
    the filter's calibration folds run the filter the model will run."""
    _, train, model = persistent
    kind = model.selection_.attrs["choice_kind"]
    assert kind == "ar1" and model.dynamics_ is not None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sub = GLRM(**{**model.get_params(), "temporal": "ar1"}).fit(train)
    dyn = refit_dynamics(model, sub, kind, train["time"].values)
    np.testing.assert_allclose(dyn.A, model.dynamics_.A, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(dyn.Q, model.dynamics_.Q, rtol=1e-8, atol=1e-10)
    assert np.isclose(dyn.blend, model.dynamics_.blend)


def test_conformal_calibration_gives_the_filter_its_own_thresholds(persistent):
    _, train, model = persistent
    kw = dict(method="conformal", adaptive=False, residual=False, max_snapshots=2,
              max_cells=40, seed=3)
    cal = calibrate(model, train, temporal="auto", **kw)
    assert len(cal.temporal_quantiles) == 2 and cal.temporal_n_residuals > 100
    assert cal.temporal_scale is not None
    # the thresholds are the memoryless ones times the filter's score quantile relative to the
    # memoryless model's on the same forward-chained days and cells, in units of the filter's
    # calibrated std (the same folds, seed and cells as calibrate's own call)
    twin = cv_residuals(model, train, folds=ForwardBlocks(cal.n_blocks), sizes=(5, 15, 50),
                        kinds=("route", "scattered", "line"), max_snapshots=2,
                        temporal="ar1", max_cells=40, seed=3)
    zt, zm = twin.z(source="filter"), twin.z(source="memoryless")
    assert zt.size == zm.size == cal.temporal_n_residuals
    levels = [0.68, 0.95]
    rel = np.quantile(np.abs(zt), levels) / np.quantile(np.abs(zm), levels)
    expect = np.asarray(cal.quantiles) * rel * np.sqrt(cal.scale / cal.temporal_scale)
    np.testing.assert_allclose(cal.temporal_quantiles, expect, rtol=1e-12)
    # per design size: each size's own memoryless scores (the same fold-ins as calibrate's),
    # and the filter's are those times the same ratio
    records = cv_residuals(model, train, folds=ForwardBlocks(cal.n_blocks), sizes=(5, 15, 50),
                           kinds=("route", "scattered", "line"), max_snapshots=2,
                           max_cells=40, seed=3).select(1.0)
    per = np.array([conformal_quantile(np.concatenate([np.abs(r.z) for r in records
                                                       if r.size == size]) / np.sqrt(cal.scale),
                                       levels) for size in (5, 15, 50)])
    np.testing.assert_allclose(np.reshape(cal.size_quantiles, (3, 2)), per, rtol=1e-12)
    held = [np.mean([r.n_samples for r in records if r.size == size]) for size in (5, 15, 50)]
    np.testing.assert_allclose(cal.size_samples, held, rtol=1e-12)
    assert np.all(np.asarray(held) < [5, 15, 50])  # the record's gaps give no value
    np.testing.assert_allclose(np.reshape(cal.temporal_size_quantiles, (3, 2)),
                               per * rel * np.sqrt(cal.scale / cal.temporal_scale), rtol=1e-12)
    # the filter reads them (a belief with no sample yet: the smallest size's), the memoryless
    # filter and fold-ins the memoryless ones; with n samples, interpolated at n
    filt = LatentFilter.from_model(model)
    np.testing.assert_allclose(filt.interval_multipliers(), cal.temporal_size_quantiles[:2])
    mem = LatentFilter.from_model(model, memoryless=True)
    np.testing.assert_allclose(mem.interval_multipliers(), cal.size_quantiles[:2])
    V = model.region_.stack(train.isel(time=-1)).astype(float)
    cells = np.flatnonzero(np.isfinite(V))  # 45 of the region's 50 cells
    mem.assimilate((cells, V[cells]), time=train["time"].values[-1], force=True)
    assert mem.posterior.n_samples == cells.size == 45
    # (on this 50-cell region a "50" design that leaves cells to score is a transect of a few
    # cells: the counts, not the sizes, place the thresholds, sorted)
    order = np.argsort(held)
    np.testing.assert_allclose(mem.interval_multipliers(),
                               [np.interp(np.log(45), np.log(np.asarray(held)[order]),
                                          per[order, j]) for j in (0, 1)], rtol=1e-12)
    aci = LatentFilter.from_model(model).adaptive_conformal(gamma=0.05)  # alpha at its target
    np.testing.assert_allclose(aci.interval_multipliers(), cal.temporal_size_quantiles[:2])
    aci.aci.alpha = aci.aci.alpha + 0.01  # moved: the pooled table's, times the size's ratio
    ratio = np.asarray(cal.temporal_size_quantiles[:2]) / np.asarray(cal.temporal_quantiles)
    moved = [cal.for_filter().score_quantile(lv - 0.01) for lv in levels]
    np.testing.assert_allclose(aci.interval_multipliers(), np.asarray(moved) * ratio)
    # by default (and temporal=False) none: the filter uses the memoryless thresholds
    off = calibrate(model, train, **kw)
    assert off.temporal_quantiles == () and off.for_filter() is off
    np.testing.assert_allclose(LatentFilter.from_model(model).interval_multipliers(),
                               off.size_quantiles[:2])  # no sample yet: the smallest size's


def test_a_model_without_dynamics_gets_no_filter_thresholds(persistent):
    _, train, _ = persistent
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, random_state=0, progress=False).fit(train)
    cal = calibrate(model, train, method="conformal", adaptive=False, residual=False,
                    max_snapshots=1, max_cells=30)
    assert cal.temporal_quantiles == () and cal.temporal_n_residuals == 0


def test_filter_thresholds_round_trip_and_validate(tmp_path, persistent):
    cal = Calibration(method="conformal", levels=(0.68, 0.95), quantiles=(1.0, 2.0),
                      score_table=(0.5, 1.5), temporal_quantiles=(1.2, 2.5),
                      temporal_score_table=(0.7, 1.9), temporal_n_residuals=77)
    back = Calibration.from_attrs(cal.to_attrs())
    assert back == cal
    f = cal.for_filter()
    assert f.quantiles == (1.2, 2.5) and f.score_table == (0.7, 1.9)
    assert f.n_residuals == 77 and f.temporal_quantiles == ()
    with pytest.raises(Exception, match="temporal_quantiles"):
        Calibration(method="conformal", levels=(0.68, 0.95), quantiles=(1.0, 2.0),
                    temporal_quantiles=(1.0,))
    # saved with the model and loaded back identically
    model = persistent[2]
    saved = model.calibration_
    try:
        model.calibration_ = cal
        model.save(tmp_path / "m.nc")
    finally:
        model.calibration_ = saved
    np.testing.assert_equal(asdict(GLRM.load(tmp_path / "m.nc").calibration_), asdict(cal))


def test_a_loaded_monitor_state_keeps_the_filters_thresholds(tmp_path, persistent):
    """A state saved and loaded reads the same intervals as before: the filter's own
    thresholds (per size) and scale, or the memoryless ones for a memoryless state."""
    from lrm_cvx.monitor import MonitorState

    data, train, model = persistent
    cal = Calibration(method="conformal", levels=(0.68, 0.95), quantiles=(1.0, 2.0),
                      score_table=(0.5, 1.5), temporal_quantiles=(1.2, 2.5),
                      temporal_score_table=(0.7, 1.9), sizes="5,15,50",
                      size_quantiles=(1.1, 2.2, 1.0, 2.0, 0.9, 1.8),
                      temporal_size_quantiles=(1.3, 2.7, 1.2, 2.5, 1.1, 2.3),
                      scale=1.5, temporal_scale=0.8)
    saved = model.calibration_
    try:
        model.calibration_ = cal
        t = data["time"].values[train.sizes["time"]]
        V = model.region_.stack(data.sel(time=t)).astype(float)
        cells = np.flatnonzero(np.isfinite(V))[:15]
        for memoryless, expect in ((False, (1.2, 2.5)), (True, (1.0, 2.0))):
            state = MonitorState.from_model(model, memoryless=memoryless, online=False)
            state.assimilate((cells, V[cells]), time=t)
            np.testing.assert_allclose(state.interval_multipliers(), expect)
            state.save(tmp_path / f"s{memoryless}.nc")
            back = MonitorState.load(tmp_path / f"s{memoryless}.nc", model)
            np.testing.assert_allclose(back.interval_multipliers(), expect)
            assert back.posterior.variance_scale == state.posterior.variance_scale
            np.testing.assert_allclose(back.predict()["std"], state.predict()["std"])
    finally:
        model.calibration_ = saved


@pytest.mark.parametrize("temporal", [None, "auto"])
def test_campaign_coverage_uses_the_calibrated_interval(persistent, temporal):
    """The campaign's coverage is counted in the interval users get: with thresholds 0 and
    100 nothing and everything is covered; without a calibration the normal quantiles."""
    data, _, model = persistent
    test = data.isel(time=slice(-N_TEST, None))
    start = int(np.flatnonzero(np.isfinite(model.region_.stack(test)).all(axis=0))[0])
    saved = model.calibration_
    try:
        wide = Calibration(method="conformal", levels=(0.68, 0.95), quantiles=(50.0, 100.0),
                           temporal_quantiles=(50.0, 100.0))
        narrow = replace(wide, quantiles=(1e-12, 1e-12), temporal_quantiles=(1e-12, 1e-12))
        runs = {}
        for name, cal in (("wide", wide), ("narrow", narrow), ("none", None)):
            model.calibration_ = cal
            runs[name] = simulate_campaign(model, test, start, 12, temporal=temporal, seed=0,
                                           method="greedy", paper=True)
        assert np.all(runs["wide"]["coverage95"].values == 1.0)
        assert np.all(runs["narrow"]["coverage68"].values == 0.0)
        # no calibration: the normal quantiles, recomputed from the campaign's own maps
        st = LatentFilter.from_model(model, memoryless=temporal is None)
        region = model.region_
        V = region.stack(test)
        cov = []
        for i, t in enumerate(test["time"].values):
            route = runs["none"]["routes"].values[i]
            cells = np.unique(route[route >= 0])
            st.assimilate((cells, V[i, cells]), t)
            held = np.isfinite(V[i])
            held[cells] = False
            mean, _, pstd = st.posterior.predict_all()
            z = np.abs(mean[held] - V[i, held]) / pstd[held]
            cov.append(np.mean(z <= gaussian_multiplier(0.68)))
        np.testing.assert_allclose(runs["none"]["coverage68"].values, cov, rtol=1e-9)
    finally:
        model.calibration_ = saved


def test_auto_falls_back_when_no_block_can_carry_the_kind(persistent, monkeypatch):
    """temporal='auto' keeps the memoryless calibration when the forward-chained filter
    residuals cannot be made; a kind asked for by name says why."""
    import lrm_cvx.validation.calibration as C
    from lrm_cvx.errors import ModelError

    _, train, model = persistent
    real = C.cv_residuals

    def no_filter(*a, **kw):
        if kw.get("temporal") is not None:
            raise ModelError("calibration produced no held-out residuals")
        return real(*a, **kw)

    monkeypatch.setattr(C, "cv_residuals", no_filter)
    kw = dict(method="conformal", adaptive=False, residual=False, max_snapshots=1,
              max_cells=30)
    cal = calibrate(model, train, temporal="auto", **kw)
    assert cal.temporal_quantiles == () and cal.temporal_scale is None
    with pytest.raises(ModelError, match="no held-out"):
        calibrate(model, train, temporal="ar1", **kw)
