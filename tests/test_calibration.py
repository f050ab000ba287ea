"""Calibrated predictive uncertainty (validation/calibration.py)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr
from scipy.stats import norm

from lrm_cvx.errors import ModelError
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import (
    Calibration,
    interval_coverage,
    prediction_factor,
    predictive_std,
)
from lrm_cvx.monitor import MonitorState
from lrm_cvx.validation.calibration import calibrate, fit_scale
from lrm_cvx.validation.designs import sample_sets


def _planted(T=60, ny=16, nx=20, k=3, noise=0.3, seed=0):
    """Data drawn exactly from the model the fold-in assumes: x_t ~ N(0, S), d = Y^T x + e."""
    rng = np.random.default_rng(seed)
    L = ny * nx
    Y = rng.normal(size=(k, L))
    S = np.diag([2.0, 1.0, 0.5])[:k, :k]
    X = np.linalg.cholesky(S) @ rng.normal(size=(k, T))
    D = X.T @ Y + noise * rng.normal(size=(T, L))
    times = np.arange(T).astype("datetime64[D]").astype("datetime64[ns]")
    return xr.DataArray(D.reshape(T, ny, nx).astype(np.float64), dims=("time", "lat", "lon"),
                        coords={"time": times, "lat": np.arange(ny) * 1.0,
                                "lon": np.arange(nx) * 1.0})


def _coverage_on_test(model, test, sizes=(5, 15, 40), seed=0):
    """Pooled held-out coverage of the model's fold-in (empirical prior) on ``test``."""
    region = model.region_
    V = region.stack(test).astype(np.float64)
    rng = np.random.default_rng(seed)
    hits = np.zeros(2)
    count = 0
    for t in range(V.shape[0]):
        for size in sizes:
            for kind in ("route", "scattered"):
                cells = sample_sets(region, np.isfinite(V[t]), size, kind, rng)
                ds = model.complete((cells, V[t, cells]), prior="empirical")
                pred = region.stack(ds["prediction"])
                std = region.stack(ds["std"])
                held = np.isfinite(V[t])
                held[cells] = False
                cov = interval_coverage(V[t, held], pred[held],
                                        predictive_std(model, std)[held])
                hits += cov * held.sum()
                count += held.sum()
    return hits / count


def test_fit_scale_recovers_a_planted_variance():
    z = np.random.default_rng(1).normal(scale=2.0, size=20000)
    assert fit_scale(z) == pytest.approx(4.0, rel=0.05)
    # the scaled residuals hit the nominal coverage
    cov = interval_coverage(z, 0.0, np.sqrt(fit_scale(z)))
    assert cov == pytest.approx([0.68, 0.95], abs=0.01)


def test_interval_coverage_counts_by_hand():
    values = np.array([0.0, 0.5, 1.5, 2.5, np.nan])
    cov = interval_coverage(values, 0.0, 1.0)  # |z| <= 0.994 and <= 1.96
    assert cov == pytest.approx([2 / 4, 3 / 4])
    assert np.isnan(interval_coverage([np.nan], 0.0, 1.0)).all()
    # agrees with the normal cdf on a large Gaussian sample
    z = np.random.default_rng(0).normal(size=50000)
    lv = 2 * norm.cdf(1.0) - 1
    assert interval_coverage(z, 0, 1, levels=(lv,))[0] == pytest.approx(lv, abs=0.01)


def test_fit_scale_refuses_too_few_residuals():
    with pytest.raises(ModelError, match="at least 20"):
        fit_scale(np.ones(5))


def test_calibration_attrs_round_trip_and_validation():
    cal = Calibration(scale=1.7, temporal_scale=None, n_residuals=10, coverage95_raw=0.8)
    back = Calibration.from_attrs(cal.to_attrs())
    assert back == cal
    assert Calibration.from_attrs({}) is None
    assert Calibration(scale=2.0, temporal_scale=3.0).variance_scale(temporal=True) == 3.0
    assert Calibration(scale=2.0).variance_scale(temporal=True) == 2.0
    with pytest.raises(ModelError, match="scale"):
        Calibration(scale=-1.0)


def test_sample_sets_route_is_clustered_and_scattered_is_not():
    data = _planted(T=4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0).fit(data)
    region = model.region_
    observed = np.ones(region.n_cells, bool)
    observed[:50] = False
    rng = np.random.default_rng(0)
    route = sample_sets(region, observed, 12, "route", rng)
    scat = sample_sets(region, observed, 12, "scattered", rng)
    assert route.size == scat.size == 12 and observed[route].all() and observed[scat].all()
    g = region.grid_index.astype(float)

    def spread(c):
        return np.mean(np.linalg.norm(g[c][:, None] - g[c][None], axis=-1))

    assert spread(route) < spread(scat)


def test_planted_gaussian_model_is_near_nominal_and_calibrate_keeps_it():
    data = _planted()
    train, test = data.isel(time=slice(None, -10)), data.isel(time=slice(-10, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0).fit(train)
    raw = _coverage_on_test(model, test)
    assert raw[1] >= 0.9 and raw[0] >= 0.6  # data drawn exactly from the model
    cal = calibrate(model, train, n_blocks=6, sizes=(5, 15, 40), max_snapshots=3)
    assert model.calibration_ is cal
    assert 0.7 < cal.scale < 1.4  # cross-validation finds the model nearly right
    after = _coverage_on_test(model, test)
    assert 0.92 <= after[1] <= 0.98 and 0.62 <= after[0] <= 0.76


def test_overconfident_model_is_inflated_to_nominal():
    """A model whose noise estimate is 3x too small: calibration restores the coverage."""
    data = _planted(noise=0.6, seed=3)
    train, test = data.isel(time=slice(None, -10)), data.isel(time=slice(-10, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0).fit(train)
    model.noise_std_ = model.noise_std_ / 3.0
    raw = _coverage_on_test(model, test)
    assert raw[1] < 0.8
    cal = calibrate(model, train, n_blocks=6, sizes=(5, 15, 40), max_snapshots=3)
    # cv refits estimate their own noise; the scale only fixes what they get wrong, so check
    # the effect on the (deliberately broken) model through a scale fitted on its own errors
    assert cal.scale > 0
    from lrm_cvx.validation.calibration import _standardized

    region = model.region_
    V = region.stack(train).astype(float)
    rng = np.random.default_rng(5)
    model.calibration_ = None  # the broken model's own errors, uncalibrated
    zs = []
    for t in range(0, V.shape[0], 5):
        cells = sample_sets(region, np.isfinite(V[t]), 15, "scattered", rng)
        ds = model.complete((cells, V[t, cells]), prior="empirical")
        zs.append(_standardized(model, V[t], cells, region.stack(ds["prediction"]),
                                region.stack(ds["std"]), False))
    model.calibration_ = Calibration(scale=fit_scale(np.concatenate(zs)))
    after = _coverage_on_test(model, test)
    assert 0.9 <= after[1] <= 0.99


def test_calibration_scales_complete_std_and_survives_save_load(tmp_path):
    data = _planted(T=20)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0).fit(data)
    cells = np.arange(0, 300, 7)
    vals = model.region_.stack(data.isel(time=3))[cells]
    before = model.complete((cells, vals), prior="empirical")
    model.calibration_ = Calibration(scale=4.0)
    after = model.complete((cells, vals), prior="empirical")
    np.testing.assert_allclose(after["prediction"], before["prediction"])
    np.testing.assert_allclose(after["std"], 2.0 * before["std"], rtol=1e-10)
    path = tmp_path / "m.nc"
    model.save(path)
    loaded = GLRM.load(path)
    assert loaded.calibration_.scale == 4.0 and loaded.calibration_.temporal_scale is None
    np.testing.assert_allclose(loaded.complete((cells, vals), prior="empirical")["std"],
                               after["std"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data)
    assert model.calibration_ is None  # a refit invalidates it


def test_blend_dynamics_endpoints_and_select_dynamics():
    from lrm_cvx.belief.posterior import empirical_moments
    from lrm_cvx.io.samples import synthetic_dynamic_field
    from lrm_cvx.validation.blending import blend_dynamics, select_dynamics

    data = synthetic_dynamic_field(30, (8, 10), rank=2, missing=0.1, noise=0.05, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(data)
    dyn = model.dynamics_
    S = empirical_moments(model._Xv)[1]
    assert blend_dynamics(dyn, 1.0, S).A == pytest.approx(dyn.A)
    d0 = blend_dynamics(dyn, 0.0, S)
    # alpha = 0: the filter's forecast is the memoryless empirical prior, whatever came before
    a = MonitorState.from_model(model, dynamics=d0).forecast()
    b = MonitorState.from_model(model, memoryless=True).forecast()
    np.testing.assert_allclose(a["mean"].values, b["mean"].values, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(a["std"].values, b["std"].values, rtol=1e-6, equal_nan=True)
    with pytest.raises(ModelError, match="alpha"):
        blend_dynamics(dyn, 1.5, S)
    from lrm_cvx.glrm.dynamics import estimate_ar1
    from lrm_cvx.validation.blending import unblended_dynamics

    base = unblended_dynamics(model)  # the plain fit, without the fit's own blend
    plain = estimate_ar1(model._Xv, model.X_["time"], initial_cov=dyn.initial_cov,
                         error_cov=dyn.error_cov)
    np.testing.assert_allclose(base.A, plain.A)
    np.testing.assert_allclose(base.Q, plain.Q)
    alpha, table = select_dynamics(model, data, alphas=(0.0, 1.0), sizes=(3, 10), n_val=6)
    # candidates: the given alphas, 0 and the fit's own blend
    total = table["total"].swap_dims(candidate="alpha")
    assert set(total["alpha"].values) == {0.0, 1.0, round(dyn.blend, 12)}
    assert table.sizes["size"] == 2 and alpha in set(total["alpha"].values)
    # the choice never does worse than memoryless on the validation snapshots, at any size
    assert np.all(total.sel(alpha=alpha).values <= total.sel(alpha=0.0).values + 1e-12)
    assert model.dynamics_selection_.attrs["choice_alpha"] == alpha
    # one rule: the applied dynamics are the *unblended* estimate blended by alpha (the fit's
    # blend does not compose with it)
    np.testing.assert_allclose(model.dynamics_.A, alpha * plain.A, atol=1e-12)
    np.testing.assert_allclose(model.dynamics_.Q, (1 - alpha ** 2) * S + alpha ** 2 * plain.Q,
                               rtol=1e-9, atol=1e-12)
    assert model.dynamics_.blend == pytest.approx(alpha)


def test_filter_scale_is_used_by_the_monitor_state():
    from lrm_cvx.io.samples import synthetic_dynamic_field

    data = synthetic_dynamic_field(40, (8, 10), rank=2, missing=0.1, noise=0.05, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(data)
    before = MonitorState.from_model(model).forecast()
    cal = calibrate(model, data, n_blocks=4, sizes=(5, 20), max_snapshots=2, temporal="ar1",
                    adaptive=False, residual=False)  # a pure variance scale
    assert cal.temporal_scale is not None and cal.temporal_scale > 0
    after = MonitorState.from_model(model).forecast()
    np.testing.assert_allclose(after["predictive_std"].values,
                               np.sqrt(cal.temporal_scale) * before["predictive_std"].values,
                               rtol=1e-10)
    # the memoryless state uses the memoryless scale
    ml0 = Calibration(scale=1.0)
    model.calibration_ = ml0
    base = MonitorState.from_model(model, memoryless=True).forecast()
    model.calibration_ = cal
    ml = MonitorState.from_model(model, memoryless=True).forecast()
    np.testing.assert_allclose(ml["std"].values, np.sqrt(cal.scale) * base["std"].values,
                               rtol=1e-10)


def test_fit_adaptive_scale_finds_informative_innovations():
    """Per-snapshot scales that the innovations reveal: a finite dof and a likelihood gain;
    innovations unrelated to the held-out scale: (nearly) the fixed scale."""
    from lrm_cvx.validation.calibration import fit_adaptive_scale

    rng = np.random.default_rng(0)
    n = 30
    rec_info, rec_noise = [], []
    for t in range(80):
        s_t = np.exp(rng.normal(0, 0.6))  # stormy and calm snapshots
        z = np.sqrt(s_t) * rng.standard_normal(400)
        q = s_t * rng.chisquare(n)
        rec_info.append((z, q, n, t))
        rec_noise.append((z, rng.chisquare(n), n, t))
    scale, dof, disc, gain = fit_adaptive_scale(rec_info)
    assert dof is not None and dof <= 16 and gain > 0.01
    # the scales it implies calibrate the held-out residuals snapshot by snapshot
    s_i = np.array([(dof * scale + r[1]) / (dof + r[2]) for r in rec_info])
    cover = np.mean([np.mean(np.abs(r[0]) / np.sqrt(s) <= 1.96)
                     for r, s in zip(rec_info, s_i, strict=True)])
    assert abs(cover - 0.95) < 0.02
    _, dof2, _, gain2 = fit_adaptive_scale(rec_noise)
    assert dof2 is None or dof2 >= 32
    assert gain2 < 0.01


def test_calibration_attrs_keep_the_adaptive_scale():
    cal = Calibration(scale=1.3, dof=16.0, discount=0.8, dof_loglik_gain=0.01)
    back = Calibration.from_attrs(cal.to_attrs())
    assert back.dof == 16.0 and back.discount == 0.8
    assert Calibration.from_attrs(Calibration(scale=1.1).to_attrs()).dof is None


def test_select_dynamics_keeps_memoryless_without_significant_gain():
    from lrm_cvx.io.samples import synthetic_dynamic_field
    from lrm_cvx.validation.blending import select_dynamics

    data = synthetic_dynamic_field(40, (8, 10), rank=2, missing=0.1, noise=0.05, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(data)
    # an impossible guard (no harm at all allowed, with a huge confidence): memoryless
    alpha, table = select_dynamics(model, data, alphas=(0.5, 1.0), sizes=(3,), n_val=6,
                                   confidence=50.0, tolerance=0.0, apply=False)
    assert alpha == 0.0
    ucb = table["ucb"].swap_dims(candidate="alpha")
    assert np.all(ucb.sel(alpha=0.0).values == 0.0) and table.attrs["n_days"] == 12  # 2 windows
    # no guard: the plain best worst ratio
    alpha2, table2 = select_dynamics(model, data, alphas=(0.5, 1.0), sizes=(3,), n_val=6,
                                     confidence=0.0, tolerance=np.inf, apply=False)
    total = table2["total"].swap_dims(candidate="alpha")
    ratio = (total / total.sel(alpha=0.0)).max("size")
    assert alpha2 == float(ratio.idxmin())
    with pytest.raises(ModelError, match="n_folds"):
        select_dynamics(model, data, n_folds=0)


def test_residual_scale_multiplies_the_residual_and_noise_variances():
    from lrm_cvx.belief.posterior import ObservationModel

    data = _planted(T=20)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, spatial="exponential", progress=False, random_state=0).fit(data)
    base = ObservationModel.from_model(model)
    model.calibration_ = Calibration(scale=1.0, residual_scale=2.0)
    obs = ObservationModel.from_model(model)
    assert obs.spatial_cov.sill == pytest.approx(2 * base.spatial_cov.sill)
    assert obs.spatial_cov.nugget == pytest.approx(2 * base.spatial_cov.nugget)
    assert obs.spatial_cov.range == base.spatial_cov.range
    plain = ObservationModel.from_model(model, spatial=False)
    assert plain.noise_var == pytest.approx(2 * float(model.noise_std_) ** 2
                                            * prediction_factor(model))  # a new snapshot's
    back = Calibration.from_attrs(model.calibration_.to_attrs())
    assert back.residual_scale == 2.0


def test_one_grid_of_the_residual_factor(monkeypatch):
    """temporal='auto' tries the whole doublings of the one grid of the residual factor and
    calibrate(residual=True) all of it, on top of the model's residual_inflation_ (which the
    residual factor multiplies)."""
    from lrm_cvx.glrm.calibrated import RESIDUAL_FACTORS, residual_factor
    from lrm_cvx.validation import calibration as calibration_module
    from lrm_cvx.validation.selection import AUTO_INFLATIONS

    assert AUTO_INFLATIONS == (1.0, 2.0, 4.0, 8.0)
    assert set(AUTO_INFLATIONS) < set(RESIDUAL_FACTORS) and min(RESIDUAL_FACTORS) < 1.0
    assert not hasattr(calibration_module, "RESIDUAL_SCALES")
    asked = []

    def spy(*args, **kw):
        asked.append(kw["residual_scales"])
        raise ModelError("stop")

    monkeypatch.setattr(calibration_module, "cv_residuals", spy)
    for residual in (True, False):
        with pytest.raises(ModelError, match="stop"):
            calibrate(object(), np.zeros((20, 3, 3)), residual=residual)
    assert asked == [RESIDUAL_FACTORS, (1.0,)]
    data = _planted(T=20, ny=6, nx=7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0, max_iter=5).fit(data)
    one = residual_factor(model)
    model.residual_inflation_ = 4.0
    model.calibration_ = Calibration(scale=1.0, residual_scale=1.41)
    assert residual_factor(model) == pytest.approx(4.0 * 1.41 * one)


def test_adaptive_scale_is_carried_by_the_monitor_state_and_saved(tmp_path):
    from lrm_cvx.io.samples import synthetic_dynamic_field

    data = synthetic_dynamic_field(30, (8, 10), rank=2, missing=0.1, noise=0.05, seed=4)
    train, test = data.isel(time=slice(None, -3)), data.isel(time=slice(-3, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, temporal="ar1", progress=False, random_state=0).fit(train)
    model.calibration_ = Calibration(scale=1.5, dof=8.0, discount=0.5)
    state = MonitorState.from_model(model)
    region = model.region_
    V = region.stack(test).astype(float)
    qs, ns = [], []
    for i, t in enumerate(test["time"].values):
        cells = np.flatnonzero(np.isfinite(V[i]))[::5]
        prior = state._propagated(state._coerce(t))
        q, n = prior.innovation(cells, V[i, cells])
        state.assimilate((cells, V[i, cells]), time=t)
        qs.append(q)
        ns.append(n)
    # the day's scale: (dof s0 + discounted earlier evidence + today's) / (dof + ...)
    eq = 0.25 * qs[0] + 0.5 * qs[1]
    en = 0.25 * ns[0] + 0.5 * ns[1]
    s_day = (8.0 * 1.5 + eq + qs[2]) / (8.0 + en + ns[2])
    assert state.posterior.variance_scale == pytest.approx(s_day, rel=1e-9)
    path = tmp_path / "state.nc"
    model_path = tmp_path / "model.nc"
    model.save(model_path)
    state.model_path = str(model_path)
    state.save(path)
    back = MonitorState.load(path, model)
    assert back.posterior.variance_scale == pytest.approx(s_day, rel=1e-9)
    np.testing.assert_allclose(back.predict()["predictive_std"].values,
                               state.predict()["predictive_std"].values, rtol=1e-9,
                               equal_nan=True)


def test_fit_calibration_parameter_equals_calibrating_after_the_fit(tmp_path):
    """``GLRM(calibration="conformal")`` is ``calibrate(model, train, method="conformal")`` run
    at the end of the fit: same calibration (its refits do not calibrate themselves), saved
    and loaded with the parameter; a bad value is one error before any fitting."""
    data = _planted(T=16, ny=8, nx=10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        auto = GLRM(rank=3, progress=False, random_state=0, offset=True,
                    calibration="conformal").fit(data)
        plain = GLRM(rank=3, progress=False, random_state=0, offset=True).fit(data)
        ref = calibrate(plain, data, method="conformal", seed=0)
    assert auto.calibration_ is not None
    np.testing.assert_equal(auto.calibration_.to_attrs(), ref.to_attrs())
    np.testing.assert_array_equal(auto._Yv, plain._Yv)
    path = tmp_path / "m.nc"
    auto.save(path)
    loaded = GLRM.load(path)
    assert loaded.calibration == "conformal"
    np.testing.assert_equal(loaded.calibration_.to_attrs(), ref.to_attrs())
    with pytest.raises(ModelError, match="calibration must be one of"):
        GLRM(rank=3, progress=False, calibration="isotonic").fit(data)
    with pytest.raises(ModelError, match="unknown calibrate.*'resid'"):
        GLRM(rank=3, progress=False, calibration={"method": "conformal", "resid": 1}).fit(data)
    # a dict of calibrate() keywords: the intervals' calibration without touching the maps
    kw = {"method": "conformal", "residual": False, "adaptive": False}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        keyed = GLRM(rank=3, progress=False, random_state=0, offset=True,
                     calibration=kw).fit(data)
        ref2 = calibrate(plain, data, seed=0, **kw)
    np.testing.assert_equal(keyed.calibration_.to_attrs(), ref2.to_attrs())
    assert keyed.calibration_.residual_scale == 1.0
    keyed.save(tmp_path / "k.nc")
    assert GLRM.load(tmp_path / "k.nc").calibration == kw


def test_default_folds_shrink_on_a_short_record():
    """``n_blocks=None``: 8 folds, half the snapshots on a short record (a 10-snapshot record
    calibrates with 5 folds instead of failing); an explicit count out of range still fails."""
    data = _planted(T=10, ny=8, nx=10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=3, progress=False, random_state=0).fit(data)
        cal = calibrate(model, data, sizes=(5,), max_snapshots=1)
        ref = calibrate(model, data, n_blocks=5, sizes=(5,), max_snapshots=1)
    assert cal.to_attrs()["calibration_n_blocks"] == 5
    np.testing.assert_equal(cal.to_attrs(), ref.to_attrs())
    with pytest.raises(ModelError, match="n_blocks must be in"):
        calibrate(model, data, n_blocks=8)


def test_a_short_record_calibrates_on_the_blocks_its_refits_can_carry(monkeypatch):
    """The forward folds refit on the snapshots before each block: on a short record the
    earliest blocks cannot carry the model's rank and are skipped (the residuals come from
    the others, equal to a calibration that never had them); with none left, one ModelError
    says why (before, the refit's own error surfaced, naming the refit's snapshot count)."""
    from lrm_cvx.validation.calibration import cv_residuals
    from lrm_cvx.validation.refits import refit_carries
    from lrm_cvx.validation.search import ForwardBlocks

    data = _planted(T=12, ny=6, nx=7, k=3)
    model = GLRM(rank=5, offset=True, random_state=0, progress=False).fit(data)
    V = model.region_.stack(data)
    blocks = np.array_split(np.arange(12), 6)[3:]  # the forward folds of n_blocks=6
    kept = [b for b in blocks if refit_carries(np.isfinite(V[:b[0]]), 5, True)]
    assert 0 < len(kept) < len(blocks)  # the first block is too early for rank 5
    refits = []
    fit = GLRM.fit

    def counted(self, data, *a, **k):
        refits.append(data.sizes["time"])
        return fit(self, data, *a, **k)

    monkeypatch.setattr(GLRM, "fit", counted)
    z = cv_residuals(model, data, folds=ForwardBlocks(6), sizes=(5,),
                     kinds=("scattered",), max_snapshots=1).z()
    monkeypatch.undo()
    assert refits == [int(b[0]) for b in kept]  # exactly the blocks that can be refitted
    assert z.size > 0 and np.all(np.isfinite(z))
    cal = calibrate(model, data, n_blocks=6, sizes=(5,), kinds=("scattered",), max_snapshots=2,
                    method="conformal", folds="forward", residual=False, adaptive=False)
    assert cal.scale > 0
    deep = GLRM(rank=10, offset=True, random_state=0, progress=False).fit(data)
    with pytest.raises(ModelError, match="cannot refit rank 10 on the snapshots before") as err:
        cv_residuals(deep, data, folds=ForwardBlocks(6), sizes=(5,), kinds=("scattered",))
    assert "\n" not in str(err.value)
    # the folds are the search's splitters: the names are those with 8 blocks, and anything
    # else is one line naming the argument
    from lrm_cvx.validation.search import InterleavedBlocks, RollingOrigin

    cheap = dict(sizes=(5,), kinds=("scattered",), max_snapshots=1, seed=1)
    with pytest.raises(ModelError, match=r"n_blocks must be in \[2, 6\] for 12 snapshots, got 8"):
        cv_residuals(model, data, folds="interleaved", **cheap)  # the name: 8 blocks
    assert np.all(np.isfinite(cv_residuals(model, data, folds=InterleavedBlocks(6), **cheap).z()))
    for bad in ("sideways", RollingOrigin(2, 2)):
        with pytest.raises(ModelError, match="folds must be") as err:
            cv_residuals(model, data, folds=bad, **cheap)
        assert "\n" not in str(err.value)


def test_cv_residuals_returns_one_table_of_rows():
    """cv_residuals gives one CVResiduals for every setting: rows per fold-in and factor (the
    same cells for every factor), or per filter day for the filter and its memoryless twin."""
    from lrm_cvx.validation.calibration import CVResiduals, cv_residuals
    from lrm_cvx.validation.search import ForwardBlocks, InterleavedBlocks

    data = _planted(T=16, ny=6, nx=7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(rank=2, progress=False, random_state=0, max_iter=10).fit(data)
        cheap = dict(sizes=(5, 9), kinds=("scattered",), max_snapshots=1, seed=2)
        res = cv_residuals(model, data, folds=InterleavedBlocks(4), residual_scales=(1.0, 2.0),
                           **cheap)
        filt = cv_residuals(model, data, folds=ForwardBlocks(4), temporal="ar1", **cheap)
    assert isinstance(res, CVResiduals) and isinstance(filt, CVResiduals)
    assert res.rhos == (1.0, 2.0) and {r.source for r in res.rows} == {"fold-in"}
    one, two = res.select(1.0), res.select(2.0)
    assert len(one) == len(two) == 4 * 2  # 4 folds x 1 snapshot x 2 sizes
    assert [(r.t, r.size, r.z.size) for r in one] == [(r.t, r.size, r.z.size) for r in two]
    assert not np.array_equal(one[0].z, two[0].z)  # the factor changes the fold-in
    assert all(np.isfinite(r.q) and r.n_eff > 0 and r.spread.shape == r.z.shape for r in one)
    np.testing.assert_array_equal(res.z(), np.concatenate([r.z for r in one]))
    f, m = filt.select(source="filter"), filt.select(source="memoryless")
    assert len(f) == len(m) > 0 and filt.select(source="fold-in") == []
    assert [(r.t, r.size, r.z.size) for r in f] == [(r.t, r.size, r.z.size) for r in m]
    assert min(r.t for r in f) >= 8  # the forward blocks: the record's second half
    with pytest.raises(ModelError, match="source must be one of"):
        filt.select(source="twin")
