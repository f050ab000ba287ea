"""Tools of the generalization benchmark (benchmarks/): the yearly records' calendar-year
means and the residual-growth diagnostic, against a by-hand reference and a planted field."""

import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_generalization as bg  # noqa: E402
import generalization_data as gd  # noqa: E402


def test_yearly_means_keep_complete_years_only():
    times = pd.date_range("2000-03-01", periods=34, freq="MS")  # Mar 2000 .. Dec 2002
    rng = np.random.default_rng(0)
    vals = rng.normal(size=(34, 2, 3))
    vals[20, 0, 0] = np.nan  # a missing month: the year's mean of the others
    da = xr.DataArray(vals, dims=("time", "lat", "lon"),
                      coords=dict(time=times, lat=[0.0, 1.0], lon=[0.0, 1.0, 2.0]))
    out = gd._yearly_means(da)
    assert out["time"].dt.year.values.tolist() == [2001, 2002]  # 2000 has 10 months only
    assert (out["time"].dt.month.values == 7).all() and (out["time"].dt.day.values == 1).all()
    for j, year in enumerate((2001, 2002)):
        idx = np.flatnonzero(times.year == year)
        np.testing.assert_allclose(out.values[j], np.nanmean(vals[idx], axis=0), rtol=1e-12)


def test_residual_growth_is_near_one_on_a_stationary_planted_field():
    """Rank 5 plus white noise, stationary: a new snapshot's residual is what the model
    predicts (ratio near 1 at every training length); a field whose later snapshots carry
    a pattern the early ones lack has a ratio far above 1 at the end."""
    rng = np.random.default_rng(3)
    T, ny, nx = 36, 14, 16
    basis = rng.normal(size=(5, ny * nx))
    noise = 0.5
    F = rng.normal(size=(T, 5)) @ basis + noise * rng.normal(size=(T, ny * nx))
    da = xr.DataArray(F.reshape(T, ny, nx), dims=("time", "lat", "lon"),
                      coords=dict(time=pd.date_range("2000-01-01", periods=T, freq="YS"),
                                  lat=np.arange(ny) * 1.0, lon=np.arange(nx) * 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = bg.residual_growth(da)
    assert table["n"].tolist() == list(range(9, 33, 4))
    # on 9 snapshots (k = 6) n / (n - k) over-states it (0.66): with every cell observed the
    # new latent row absorbs part of the loadings' error
    long = table["n"] >= 13
    np.testing.assert_allclose(table.loc[long, "oos_over_predicted"], 1.0, atol=0.3)
    # the noise variance, measured out of sample, is what the model predicts
    np.testing.assert_allclose(table.loc[long, "out_of_sample"],
                               noise**2 * table.loc[long, "factor"], rtol=0.3)
    shifted = da.copy()
    shifted[-8:] += 3 * noise * rng.normal(size=(ny, nx))  # a new pattern in the last 8
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grown = bg.residual_growth(shifted)
    assert grown["oos_over_predicted"].iloc[-1] > 3 * table["oos_over_predicted"].iloc[-1]


def test_load_record_drops_the_test_block_then_keeps_the_last(monkeypatch):
    times = pd.date_range("2000-01-01", periods=30, freq="MS")
    da = xr.DataArray(np.arange(30.0)[:, None, None] * np.ones((1, 2, 2)),
                      dims=("time", "lat", "lon"), coords=dict(time=times, lat=[0.0, 1.0],
                                                               lon=[0.0, 1.0]))
    fake = gd.Dataset(lambda: da, "test", "monthly", "none", "none")
    monkeypatch.setitem(bg.ALL_DATASETS, "fake", fake)
    assert bg.load_record("fake").sizes["time"] == 30
    monkeypatch.setattr(bg, "TRAINING_ONLY", True)
    assert bg.load_record("fake")[:, 0, 0].values.tolist() == list(range(30 - bg.N_TEST))
    monkeypatch.setattr(bg, "LAST", 5)
    assert bg.load_record("fake")[:, 0, 0].values.tolist() == list(range(17, 22))
    monkeypatch.setattr(bg, "TRAINING_ONLY", False)
    assert bg.load_record("fake")[:, 0, 0].values.tolist() == list(range(25, 30))
    monkeypatch.setattr(sys, "argv", ["bench_generalization.py", "--last", "0"])
    with pytest.raises(SystemExit):
        bg.main()


def test_smooth_noise_has_unit_variance_and_the_spectrum_asked_for():
    """Each field is centred and of unit std; a white spectrum gives (nearly) uncorrelated
    neighbours, a Gaussian one of width 4 cells strongly correlated ones."""
    rng = np.random.default_rng(0)
    white = gd._smooth_noise(rng, (64, 64), 3, lambda k2: np.ones_like(k2))
    smooth = gd._smooth_noise(rng, (64, 64), 3, lambda k2: np.exp(-0.5 * k2 * 16.0))
    for f in (white, smooth):
        np.testing.assert_allclose(f.mean(axis=(1, 2)), 0.0, atol=1e-12)
        np.testing.assert_allclose(f.std(axis=(1, 2)), 1.0, rtol=1e-12)

    def lag1(f):
        return float(np.mean(f[:, :, 1:] * f[:, :, :-1]))

    assert abs(lag1(white)) < 0.05 and lag1(smooth) > 0.9


def test_the_planted_regional_warming_record():
    """240 years on a 360-day calendar, no gaps, deterministic per seed; the planted warming
    (4 x^2.3 K from 1900, amplified poleward and over land) shows in the data: the last 8
    years are more than 2 K warmer than 1860-1899 in the south, more than 5 K in the north."""
    da = gd.load_planted_regional_warming_yearly()
    assert da.dims == ("time", "lat", "lon") and da.shape == (240, 37, 49)
    assert da.attrs["cadence"] == "yearly" and da.attrs["units"] == "degC"
    assert da["time"].dt.calendar == "360_day" and bool(da.notnull().all())
    xr.testing.assert_identical(da, gd.load_planted_regional_warming_yearly())
    assert not da.equals(gd.load_planted_regional_warming_yearly(seed=8))
    change = (da.isel(time=slice(-8, None)).mean("time")
              - da.isel(time=slice(0, 40)).mean("time"))  # 1860-1899: no forcing yet
    south, north = float(change.isel(lat=0).mean()), float(change.isel(lat=-1).mean())
    assert 2.0 < south < north and north > 5.0
    assert "planted_regional_warming_yearly" in gd.PLANTED_DATASETS
