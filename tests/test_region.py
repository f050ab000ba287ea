"""Region: numbering, stack/unstack round trip, locations, distances, subsets, persistence."""

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lrm_cvx import Region
from lrm_cvx.errors import DataError, LrmError, RegionError


def gridded(values, lat=None, lon=None, attrs=None):
    values = np.asarray(values, dtype=np.float32)
    ny, nx = values.shape[-2:]
    lat = np.linspace(40.0, 40.0 + ny - 1, ny) if lat is None else lat
    lon = np.linspace(-70.0, -70.0 + nx - 1, nx) if lon is None else lon
    dims = ("time", "lat", "lon")[-values.ndim:]
    coords = {"lat": ("lat", lat, {"units": "degrees_north"}), "lon": ("lon", lon)}
    return xr.DataArray(values, dims=dims, coords=coords, attrs=attrs or {}, name="ndvi")


def test_cells_are_observed_cells_in_row_major_order():
    v = np.full((2, 3, 4), np.nan)
    observed = [(0, 3), (1, 0), (1, 2), (2, 1)]
    for t, (r, c) in enumerate(observed):
        v[t % 2, r, c] = t
    region = Region.from_dataarray(gridded(v))
    assert region.n_cells == 4
    assert region.shape == (3, 4)
    np.testing.assert_array_equal(region.grid_index, observed)
    np.testing.assert_array_equal(region.cell_lat, [40, 41, 41, 42])
    np.testing.assert_array_equal(region.cell_lon, [-67, -70, -68, -69])
    grid = region.cell_grid
    assert grid[0, 3] == 0 and grid[2, 1] == 3 and (grid >= 0).sum() == 4


def test_explicit_mask_overrides_observations():
    da = gridded(np.ones((2, 2, 3)))
    mask = np.array([[True, False, True], [False, False, True]])
    region = Region.from_dataarray(da, mask=mask)
    np.testing.assert_array_equal(region.grid_index, [[0, 0], [0, 2], [1, 2]])


@settings(max_examples=40, deadline=None)
@given(
    arrays(np.float32, st.tuples(st.integers(1, 4), st.integers(1, 6), st.integers(1, 6)),
           elements=st.one_of(st.just(np.nan), st.floats(-1, 1, width=32)))
)
def test_stack_unstack_round_trip(values):
    if not np.isfinite(values).any():
        with pytest.raises(DataError):
            Region.from_dataarray(gridded(values))
        return
    da = gridded(values, attrs={"units": "1"})
    da = da.assign_coords(time=np.arange(values.shape[0]))
    region = Region.from_dataarray(da)
    D = region.stack(da)
    assert D.dtype == np.float32 and D.shape == (values.shape[0], region.n_cells)
    # every stacked column is observed at least once
    assert np.isfinite(D).any(axis=0).all()
    back = region.unstack(D, coords={"time": da.time})
    xr.testing.assert_identical(back, da)


def test_unstack_keeps_leading_coords_of_cell_dataarray():
    da = gridded(np.arange(12.0).reshape(1, 3, 4))
    region = Region.from_dataarray(da)
    Y = xr.DataArray(np.ones((2, region.n_cells)), dims=("component", "cell"),
                     coords={"component": [0, 1], **region.cell_coords()}, name="Y")
    grid = region.unstack(Y)
    assert grid.dims == ("component", "lat", "lon")
    np.testing.assert_array_equal(grid.component, [0, 1])
    np.testing.assert_array_equal(region.stack(Y), Y.values)


def test_stack_rejects_other_grid():
    region = Region.from_dataarray(gridded(np.ones((1, 3, 4))))
    with pytest.raises(RegionError, match="grid"):
        region.stack(gridded(np.ones((1, 3, 5))))
    with pytest.raises(RegionError, match="differs"):
        region.stack(gridded(np.ones((1, 3, 4)), lat=np.arange(3.0)))


def test_wrong_dims_and_all_nan_are_clear_errors():
    with pytest.raises(DataError, match="lat, lon"):
        Region.from_dataarray(xr.DataArray(np.ones((2, 3)), dims=("time", "station")))
    with pytest.raises(DataError, match="all NaN"):
        Region.from_dataarray(gridded(np.full((2, 3, 3), np.nan)))
    with pytest.raises(DataError):
        Region.from_dataarray(np.ones((2, 3, 3)))
    assert issubclass(RegionError, LrmError) and issubclass(RegionError, ValueError)


def test_cell_of_nearest_and_errors():
    v = np.ones((1, 3, 4))
    v[0, 1, 1] = np.nan
    region = Region.from_dataarray(gridded(v))
    assert region.cell_of(40.2, -69.9) == 0
    assert region.cell_of(42.4, -66.6) == region.n_cells - 1
    np.testing.assert_array_equal(region.cell_of([40, 41], [-70, -70]), [0, 4])
    with pytest.raises(RegionError, match="masked"):
        region.cell_of(41.0, -69.0)
    with pytest.raises(RegionError, match="outside"):
        region.cell_of(50.0, -69.0)
    with pytest.raises(RegionError, match="outside"):
        region.cell_of(41.0, -60.0)
    assert region.resolve_cell((41.0, -70.0)) == 4
    assert region.resolve_cell(3) == 3
    with pytest.raises(RegionError):
        region.resolve_cell(region.n_cells)


def test_distances_grid_and_km():
    region = Region.from_dataarray(gridded(np.ones((1, 5, 5))))
    a, b = region.cell_of(40, -70), region.cell_of(43, -66)
    assert region.distance(a, b) == pytest.approx(5.0)
    d = region.distance(np.arange(region.n_cells), a)
    ref = np.hypot(*(region.grid_index - region.grid_index[a]).T)
    np.testing.assert_allclose(d, ref)
    # one degree of latitude is ~111.19 km on the mean sphere
    c = region.cell_of(41, -70)
    assert region.distance(a, c, metric="km") == pytest.approx(111.195, rel=1e-4)
    with pytest.raises(RegionError):
        region.distance(a, b, metric="miles")


def test_subset_and_in_bbox():
    region = Region.from_dataarray(gridded(np.ones((1, 5, 6))))
    bbox = (40.5, -69.5, 42.0, -67.0)  # south, west, north, east
    inside = region.in_bbox(bbox)
    ref = ((region.cell_lat >= 40.5) & (region.cell_lat <= 42)
           & (region.cell_lon >= -69.5) & (region.cell_lon <= -67))
    np.testing.assert_array_equal(inside, ref)
    sub = region.subset(bbox)
    assert sub.shape == (2, 3) and sub.n_cells == inside.sum()
    with pytest.raises(RegionError, match="no valid cell"):
        region.subset((10, 10, 11, 11))
    with pytest.raises(RegionError, match="south"):
        region.subset((42, -70, 40, -60))


def test_dataset_round_trip():
    v = np.ones((1, 4, 5))
    v[0, 2, 3] = np.nan
    region = Region.from_dataarray(gridded(v))
    again = Region.from_dataset(region.to_dataset())
    assert again.equals(region)
    np.testing.assert_array_equal(again.grid_index, region.grid_index)
