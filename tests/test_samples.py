"""Synthetic planted field: shape, truth, missing fraction, determinism, bad input."""

import numpy as np
import pytest

from lrm_cvx.errors import DataError
from lrm_cvx.io.samples import synthetic_dynamic_field, synthetic_field


def test_shape_coords_and_planted_truth():
    da, truth = synthetic_field(20, (30, 40), rank=3, missing=0.0, noise=0.0, seed=3,
                                return_truth=True)
    assert da.dims == ("time", "lat", "lon") and da.shape == (20, 30, 40)
    assert da.dtype == np.float32
    assert np.all(np.diff(da["lat"].values) < 0) and np.all(np.diff(da["lon"].values) > 0)
    assert np.all(np.diff(da["time"].values).astype("timedelta64[D]").astype(int) == 1)
    land = truth["land_mask"]
    clean = np.einsum("kt,kyx->tyx", truth["X"], truth["Y"])
    np.testing.assert_allclose(da.values[:, land], np.clip(clean[:, land], -1, 1), atol=1e-5)
    assert np.isnan(da.values[:, ~land]).all()
    # the noise-free field has rank 3 on land
    s = np.linalg.svd(clean[:, land], compute_uv=False)
    assert s[3] < 1e-5 * s[0]


@pytest.mark.parametrize("missing", [0.2, 0.5])
def test_missing_fraction_and_fixed_land(missing):
    da, truth = synthetic_field(15, (50, 60), missing=missing, land_fraction=0.6, seed=1,
                                return_truth=True)
    land = truth["land_mask"]
    assert abs(land.mean() - 0.6) < 0.01
    frac = np.isnan(da.values[:, land]).mean()
    assert abs(frac - missing) < 0.01
    values = da.values
    assert np.nanmin(values) >= -1 and np.nanmax(values) <= 1


def test_deterministic_by_seed():
    a = synthetic_field(4, (10, 12), seed=7)
    b = synthetic_field(4, (10, 12), seed=7)
    c = synthetic_field(4, (10, 12), seed=8)
    np.testing.assert_array_equal(a.values, b.values)
    assert a.attrs == b.attrs
    assert not np.array_equal(np.nan_to_num(a.values), np.nan_to_num(c.values))


def test_bad_arguments():
    with pytest.raises(DataError, match="n_times"):
        synthetic_field(0, (4, 4))
    with pytest.raises(DataError, match="missing"):
        synthetic_field(2, (4, 4), missing=1.5)
    with pytest.raises(DataError, match="shape"):
        synthetic_field(2, (4,))


def test_dynamic_field_attrs_are_deterministic_and_name_the_seed():
    """The comment names the caller's seed, not the address of the Generator it shares."""
    a = synthetic_dynamic_field(5, (6, 7), seed=4)
    b = synthetic_dynamic_field(5, (6, 7), seed=4)
    assert a.attrs == b.attrs
    assert "seed 4;" in a.attrs["comment"] and "Generator" not in a.attrs["comment"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(missing="0.3"), "missing must be a number"),
    (dict(missing=-0.1), "missing must be >= 0"),
    (dict(land_fraction=None), "land_fraction must be a number"),
    (dict(land_fraction=1.2), r"land_fraction must be in \[0, 1\]"),
    (dict(noise="x"), "noise must be a number"),
    (dict(noise=np.inf), "noise must be >= 0 and finite"),
    (dict(seed="a"), "seed must be None, an int or a numpy Generator"),
])
@pytest.mark.parametrize("make", [synthetic_field, synthetic_dynamic_field])
def test_bad_arguments_are_one_line_data_errors(make, kwargs, match):
    with pytest.raises(DataError, match=match):
        make(3, (5, 6), **kwargs)
