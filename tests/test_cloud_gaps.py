"""``cloud_gaps``: moving clouds laid over a record (exact fraction per snapshot, only values
that exist hidden, the rest untouched, clustered in space and persistent in time, seeded)."""

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.errors import DataError
from lrm_cvx.io import cloud_gaps


def _record(T=40, ny=24, nx=30, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(T, ny, nx)).astype(np.float32)
    v[:, :5, :7] = np.nan  # land: never observed
    v[rng.random(v.shape) < 0.05] = np.nan  # a few gaps of its own
    return xr.DataArray(v, dims=("time", "lat", "lon"),
                        coords=dict(time=pd.date_range("2001-01-01", periods=T, freq="MS"),
                                    lat=np.arange(ny) * 2.0, lon=np.arange(nx) * 2.0),
                        attrs={"units": "K", "history": "made"}, name="sst")


@pytest.mark.parametrize("missing", [0.1, 0.3, 0.6])
def test_hides_that_fraction_of_each_snapshots_values_and_nothing_else(missing):
    da = _record()
    before = da.copy(deep=True)
    out = cloud_gaps(da, missing, seed=3)
    xr.testing.assert_identical(da, before)  # the input is not modified
    had, has = np.isfinite(da.values), np.isfinite(out.values)
    assert not (has & ~had).any()  # no value appears
    np.testing.assert_array_equal(out.values[has], da.values[has])  # the rest untouched
    hidden = (had & ~has).sum(axis=(1, 2))
    np.testing.assert_array_equal(hidden, np.round(missing * had.sum(axis=(1, 2))))
    assert out.dims == da.dims and out.name == da.name and out.attrs["units"] == "K"
    for c in da.coords:
        xr.testing.assert_identical(out[c], da[c])
    assert out.attrs["history"].startswith("made\n") and "cloud_gaps" in out.attrs["history"]


def test_clouds_are_clustered_in_space_and_persist_in_time():
    """Against independent gaps of the same fraction (a neighbour hidden with probability
    0.3, a cell hidden again the next snapshot with 0.3), clouds are patches that move."""
    da = _record(T=60, ny=40, nx=50)
    out = cloud_gaps(da, 0.3, seed=1, size=3.0, correlation=0.6)
    had = np.isfinite(da.values)
    h = had & ~np.isfinite(out.values)
    both = had[:, :, 1:] & had[:, :, :-1]
    neighbour = (h[:, :, 1:] & h[:, :, :-1] & both).sum() / (h[:, :, :-1] & both).sum()
    again = (h[1:] & h[:-1] & had[1:]).sum() / (h[:-1] & had[1:]).sum()
    assert neighbour > 0.6 and 0.35 < again < 0.9
    frozen = cloud_gaps(da, 0.3, seed=1, correlation=0.0)  # a new cover every snapshot
    hf = had & ~np.isfinite(frozen.values)
    again0 = (hf[1:] & hf[:-1] & had[1:]).sum() / (hf[:-1] & had[1:]).sum()
    assert abs(again0 - 0.3) < 0.05 < again - again0


def test_deterministic_given_the_seed():
    da = _record()
    a, b = cloud_gaps(da, 0.3, seed=5), cloud_gaps(da, 0.3, seed=5)
    np.testing.assert_array_equal(np.isfinite(a.values), np.isfinite(b.values))
    c = cloud_gaps(da, 0.3, seed=6)
    assert (np.isfinite(a.values) != np.isfinite(c.values)).any()
    assert cloud_gaps(da, 0.0).equals(da)


@pytest.mark.parametrize("kwargs, match", [
    (dict(missing=1.0), "missing must be in"),
    (dict(missing=-0.1), "missing must be >= 0"),
    (dict(missing=np.nan), "missing must be >= 0 and finite"),
    (dict(missing=0.3, size=0.0), r"size \(cells\) must be > 0"),
    (dict(missing=0.3, correlation=1.0), "correlation must be in"),
    # not numbers: a one-line DataError naming the argument, not a TypeError from float()
    (dict(missing="0.3"), "missing must be a number"),
    (dict(missing=None), "missing must be a number"),
    (dict(missing=0.3, size="3"), r"size \(cells\) must be a number"),
    (dict(missing=0.3, size=[3]), r"size \(cells\) must be a number"),
    (dict(missing=0.3, correlation=True), "correlation must be a number"),
    (dict(missing=0.3, seed="a"), "seed must be None, an int or a numpy Generator"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(DataError, match=match):
        cloud_gaps(_record(T=3), **kwargs)


def test_bad_data():
    with pytest.raises(DataError, match=r"\(time, y, x\) DataArray"):
        cloud_gaps(np.zeros((3, 4, 5)), 0.3)
    with pytest.raises(DataError, match=r"\(time, y, x\) DataArray"):
        cloud_gaps(_record().isel(time=0), 0.3)
    with pytest.raises(DataError, match="floats"):
        cloud_gaps(_record().fillna(0).astype(np.int32), 0.3)
