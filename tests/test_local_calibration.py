"""Locally weighted intervals (``Calibration.local_power``): a spatial model's per-cell
``residual_spread_``, the calibration's validated power of it, and every predictive std that
carries it (the maps and plans do not)."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.belief.observation import ObservationModel
from lrm_cvx.belief.posterior import model_prior
from lrm_cvx.errors import ModelError
from lrm_cvx.glrm import GLRM
from lrm_cvx.glrm.calibrated import (
    Calibration,
    interval_factor,
    predictive_std,
)
from lrm_cvx.validation.calibration import LOCAL_POWERS, calibrate
from lrm_cvx.validation.designs import sample_sets

N_TEST = 12
_KW = {"method": "conformal", "n_blocks": 8, "max_snapshots": 2, "residual": False,
       "sizes": (15,), "kinds": ("scattered",), "folds": "interleaved"}


def _stormy_edges(T=84, ny=18, nx=18, calm=0.15, stormy=0.9, seed=0):
    """Rank 2 plus a white residual whose std is ``calm`` inside the central box and
    ``stormy`` outside (a fixed geography of variance), and the box's mask ``(L,)``."""
    rng = np.random.default_rng(seed)
    L = ny * nx
    Y = rng.normal(size=(2, L))
    X = rng.normal(size=(2, T)) * np.array([[2.0], [1.0]])
    yy, xx = np.divmod(np.arange(L), nx)
    centre = (abs(yy - ny / 2 + 0.5) < ny / 4) & (abs(xx - nx / 2 + 0.5) < nx / 4)
    amp = np.where(centre, calm, stormy)
    D = X.T @ Y + amp * rng.normal(size=(T, L))
    times = np.arange(T).astype("datetime64[D]").astype("datetime64[ns]")
    da = xr.DataArray(D.reshape(T, ny, nx), dims=("time", "lat", "lon"),
                      coords={"time": times, "lat": np.arange(ny) * 1.0,
                              "lon": np.arange(nx) * 1.0})
    return da, centre


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(rank=2, offset=True, spatial="exponential", progress=False,
                    random_state=0, **kw).fit(data)


@pytest.fixture(scope="module")
def stormy():
    data, centre = _stormy_edges()
    train = data.isel(time=slice(None, -N_TEST))
    model = _fit(train)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flat = calibrate(model, train, local=False, **_KW)
        local = calibrate(model, train, **_KW)
    return data, train, centre, model, flat, local


def _coverage_by_region(model, data, centre, seed=1):
    """68 % coverage of the fold-in's intervals at the unsampled cells of the test block,
    ``(calm, stormy)``, and the mean 68 % half-width."""
    V = model.region_.stack(data.isel(time=slice(-N_TEST, None))).astype(float)
    rng = np.random.default_rng(seed)
    prior = model_prior(model, "empirical", spatial=True)
    hits, count, widths = np.zeros(2), np.zeros(2), []
    for t in range(N_TEST):
        cells = sample_sets(model.region_, np.isfinite(V[t]), 15, "scattered", rng)
        held = np.setdiff1d(np.arange(V.shape[1]), cells)
        post = prior.update(cells, V[t, cells])
        m68 = post.interval_multipliers(0.68)[0]
        mean, _, pstd = post.predict_all(cells=held)
        inside = np.abs(V[t, held] - mean) <= m68 * pstd
        for j, part in enumerate((centre[held], ~centre[held])):
            hits[j] += inside[part].sum()
            count[j] += part.sum()
        widths.append(np.mean(m68 * pstd))
    return hits / count, float(np.mean(widths))


def test_residual_spread_is_the_shrunk_per_cell_residual_std(stormy):
    """Brute force: each cell's training residual (data minus the reconstruction), its
    variance shrunk towards the global one with NOISE_PRIOR_DF pseudo-observations (after the
    fit's uniform inflation), relative to the cells' mean variance."""
    from lrm_cvx.glrm.predictive import NOISE_PRIOR_DF

    data, train, centre, model, _, _ = stormy
    region = model.region_
    R = region.stack(train).astype(float) - region.stack(model.reconstruct()).astype(float)
    sse, n = (R * R).sum(axis=0), R.shape[0]
    g = float(model.noise_std_) ** 2
    inflate = g * n * R.shape[1] / sse.sum()
    var = (sse * inflate + NOISE_PRIOR_DF * g) / (n + NOISE_PRIOR_DF)
    np.testing.assert_allclose(model.residual_spread_, np.sqrt(var / var.mean()), rtol=1e-4)
    # the planted geography (stds 6:1), compressed by the shrinkage towards the global variance
    ratio = model.residual_spread_[~centre].mean() / model.residual_spread_[centre].mean()
    assert 2.0 < ratio < 6.0


def test_only_a_stationary_spatial_residual_gets_a_spread(stormy):
    data, train, *_ = stormy
    assert _fit(train, noise="per-cell").residual_spread_ is None  # noise_var_ per cell
    assert _fit(train, scale="residual").residual_spread_ is None  # scale_ per cell
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = GLRM(rank=2, offset=True, progress=False, random_state=0).fit(train)
        assert plain.residual_spread_ is None
        cal = calibrate(plain, train, **{**_KW, "method": "gaussian"})
    assert cal.local_power == 0.0  # nothing to weight by: the power is not validated


def test_the_calibration_validates_a_power_where_the_variance_has_a_geography(stormy):
    """Planted calm centre, stormy edges: the likelihood picks a power > 0, and its intervals
    cover both parts near 68 % where one stationary amplitude over-covers the calm centre and
    under-covers the edges; the pooled coverage stays, and the mean width is no larger."""
    data, train, centre, model, flat, local = stormy
    assert flat.local_power == 0.0
    assert local.local_power in LOCAL_POWERS and local.local_power >= 0.75
    model.calibration_ = flat
    (calm0, storm0), width0 = _coverage_by_region(model, data, centre)
    model.calibration_ = local
    (calm1, storm1), width1 = _coverage_by_region(model, data, centre)
    assert calm0 > 0.9 and storm0 < 0.63  # one amplitude: wrong in both parts
    assert abs(calm1 - 0.68) < 0.08 and abs(storm1 - 0.68) < 0.08
    assert width1 < width0


def test_a_homoscedastic_record_keeps_its_intervals_nearly_stationary():
    """White residual of one std: the spreads are noise around 1, and whichever power the
    likelihood takes moves no cell's predictive std by more than 20 %."""
    data, _ = _stormy_edges(calm=0.5, stormy=0.5, seed=3)
    train = data.isel(time=slice(None, -N_TEST))
    model = _fit(train)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(model, train, **_KW)
    factor = model.residual_spread_ ** cal.local_power
    assert np.all(np.abs(factor - 1.0) < 0.2)


def test_every_predictive_std_carries_the_factor_and_nothing_else_does(stormy):
    data, train, centre, model, _, local = stormy
    V = model.region_.stack(data.isel(time=-1)).astype(float)
    cells = np.arange(0, model.n_cells_, 7)
    flat = replace(local, local_power=0.0)  # the same scales, every cell alike
    model.calibration_ = flat
    m0, s0, p0 = model_prior(model, "empirical", spatial=True).update(
        cells, V[cells]).predict_all()
    model.calibration_ = local
    post = model_prior(model, "empirical", spatial=True).update(cells, V[cells])
    m1, s1, p1 = post.predict_all()
    f = model.residual_spread_ ** local.local_power
    np.testing.assert_allclose(interval_factor(model), f)
    np.testing.assert_array_equal(m1, m0)  # the map is unchanged
    np.testing.assert_array_equal(s1, s0)  # and the latent std
    np.testing.assert_allclose(p1, p0 * f, rtol=1e-12)  # the predictive std times the factor
    np.testing.assert_allclose(post.predictive_std(cells=cells[:5]), p1[cells[:5]], rtol=1e-12)
    # the model-level function agrees with the posterior's
    np.testing.assert_allclose(predictive_std(model, s1, spatial=True), p1, rtol=1e-10)
    # the filter's belief too
    from lrm_cvx.belief.filter import LatentFilter

    filt = LatentFilter.from_model(model, memoryless=True, spatial=True)
    np.testing.assert_array_equal(filt.posterior.obs_model.interval_factor, f)
    model.calibration_ = flat
    assert interval_factor(model) is None


def test_the_power_and_the_spread_are_saved_with_the_model(stormy, tmp_path):
    data, train, centre, model, flat, local = stormy
    model.calibration_ = local
    model.save(tmp_path / "m.nc")
    back = GLRM.load(tmp_path / "m.nc")
    assert back.calibration_.local_power == local.local_power
    np.testing.assert_array_equal(back.residual_spread_, model.residual_spread_)
    V = model.region_.stack(data.isel(time=-1)).astype(float)
    cells = np.arange(0, model.n_cells_, 5)
    a = model_prior(model, "empirical", spatial=True).update(cells, V[cells]).predict_all()
    b = model_prior(back, "empirical", spatial=True).update(cells, V[cells]).predict_all()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12)


def test_bad_powers_and_factors_are_one_line_errors(stormy):
    *_, model, flat, local = stormy
    for bad in (-0.5, float("nan"), "high"):
        with pytest.raises(ModelError, match="local_power"):
            replace(flat, local_power=bad)
    assert Calibration.from_attrs({**flat.to_attrs()}).local_power == 0.0
    old = {k: v for k, v in local.to_attrs().items() if k != "calibration_local_power"}
    assert Calibration.from_attrs(old).local_power == 0.0  # a file saved before the power
    obs = ObservationModel.from_model(model)
    with pytest.raises(ModelError, match="interval_factor"):
        replace(obs, interval_factor=np.ones(3))
    with pytest.raises(ModelError, match="interval_factor"):
        replace(obs, interval_factor=np.zeros(model.n_cells_))


def test_power_zero_is_the_global_calibration_bit_for_bit(stormy, monkeypatch):
    """With the grid reduced to power 0 the calibration is the one without the local score,
    field for field, and its intervals are the global ones bit for bit."""
    from dataclasses import asdict

    from lrm_cvx.validation import calibration as calibration_module

    data, train, centre, model, flat, _ = stormy
    monkeypatch.setattr(calibration_module, "LOCAL_POWERS", (0.0,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zero = calibrate(model, train, **_KW)
    np.testing.assert_equal(asdict(zero), asdict(flat))
    V = model.region_.stack(data.isel(time=-1)).astype(float)
    cells = np.arange(0, model.n_cells_, 7)
    model.calibration_ = zero
    assert interval_factor(model) is None
    a = model_prior(model, "empirical", spatial=True).update(cells, V[cells])
    model.calibration_ = replace(zero, local_power=0.0, temporal_scale=None)
    b = model_prior(model, "empirical", spatial=True).update(cells, V[cells])
    for x, y in zip(a.predict_all(), b.predict_all(), strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.interval_multipliers(), b.interval_multipliers())
