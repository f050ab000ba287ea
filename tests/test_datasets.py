"""Bundled real samples load as documented."""

import numpy as np
import pytest

from lrm_cvx.datasets import list_samples, load_sample
from lrm_cvx.errors import DataError


@pytest.mark.parametrize("name, shape", [("sst", (50, 18, 30)), ("hgt500", (65, 29, 49))])
def test_samples_load_with_cf_metadata(name, shape):
    da = load_sample(name)
    assert da.dims == ("time", "lat", "lon") and da.shape == shape
    assert da.dtype == np.float32
    assert np.all(np.diff(da["lat"].values) > 0)
    assert da.attrs["units"] and "NOAA" in da.attrs["source"] + da.attrs["license"]
    assert np.isfinite(da).any()


def test_sst_is_nan_over_land_and_fully_observed_at_sea():
    da = load_sample("sst")
    sea = np.isfinite(da).any("time")
    assert 0.5 < float(sea.mean()) < 0.95
    # a cell at sea is observed at every time: land is the only gap
    assert bool(np.isfinite(da).where(sea, True).all())
    # anomalies (K): the record averages near zero and stays within a few kelvin
    assert abs(float(da.mean())) < 0.5 and float(abs(da).max()) < 10


def test_unknown_sample_lists_the_names():
    with pytest.raises(DataError, match="hgt500"):
        load_sample("ndvi-world")
    assert set(list_samples()) == {"sst", "hgt500"}
