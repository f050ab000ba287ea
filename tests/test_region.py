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


# ---------------------------------------------------------------- longitudes, antimeridian
from lrm_cvx.region import EARTH_RADIUS_KM, geographic_order, to_geographic_order  # noqa: E402


def haversine_km(lat1, lon1, lat2, lon2):
    """Naive reference: great-circle distance (km) from the spherical law of haversines."""
    p1, p2, dl = np.radians(lat1), np.radians(lat2), np.radians(np.subtract(lon2, lon1))
    h = np.sin((p2 - p1) / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_KM * np.arcsin(np.sqrt(np.clip(h, 0, 1)))


def brute_nearest(region, lat, lon):
    """Naive reference: distance to the nearest grid position over ALL grid positions."""
    LA, LO = np.meshgrid(region.lat.values, region.lon.values, indexing="ij")
    d = haversine_km(lat, lon, LA.ravel(), LO.ravel())
    return int(np.argmin(d)), float(d.min())


def gc_dist_of_cell(region, cell, lat, lon):
    return float(haversine_km(lat, lon, region.cell_lat[cell], region.cell_lon[cell]))


def test_geographic_order_rules():
    # already geographic: untouched, in either convention
    for lon in (np.arange(-180, 180, 10.0), np.arange(0, 360, 10.0), np.arange(100, 200, 5.0)):
        order, new = geographic_order(lon)
        np.testing.assert_array_equal(order, np.arange(lon.size))
        np.testing.assert_array_equal(new, lon)
    # 0..360 with a gap around Greenwich: the widest gap goes to the edges, -180..180 values
    lon = np.r_[np.arange(0, 60, 10.0), np.arange(300, 360, 10.0)]
    order, new = geographic_order(lon)
    np.testing.assert_array_equal(new, np.arange(-60, 60, 10.0))
    np.testing.assert_array_equal(np.mod(lon[order], 360), np.mod(new, 360))
    # -180..180 with a gap across the Pacific data: 0..360 values
    lon = np.r_[np.arange(-180, -150, 10.0), np.arange(150, 180, 10.0)]
    order, new = geographic_order(lon)
    np.testing.assert_array_equal(new, np.arange(150, 210, 10.0))
    # a shuffled global axis is sorted, starting at its lowest value
    rng = np.random.default_rng(0)
    lon = rng.permutation(np.arange(-180, 180, 15.0))
    order, new = geographic_order(lon)
    np.testing.assert_array_equal(new, np.arange(-180, 180, 15.0))
    # a bbox west edge picks the convention of the box
    order, new = geographic_order(np.array([170.0, 175, -180, -175]), west=170)
    np.testing.assert_array_equal(new, [170, 175, 180, 185])
    order, new = geographic_order(np.array([350.0, 355, 0, 5]), west=-10)
    np.testing.assert_array_equal(new, [-10, -5, 0, 5])


def _global(lon_start, step=10.0, ny=5, lat0=-20.0, nt=2, seed=0):
    lon = lon_start + step * np.arange(int(round(360 / step)))
    lat = lat0 + 10.0 * np.arange(ny)
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(nt, ny, lon.size)).astype(np.float32)
    return xr.DataArray(values, dims=("time", "lat", "lon"),
                        coords={"time": np.arange(nt), "lat": lat, "lon": lon}, name="v")


@pytest.mark.parametrize("lon_start", [-180.0, 0.0, -175.0, 5.0])
def test_antimeridian_bbox_same_answer_in_both_conventions(lon_start):
    da = _global(lon_start)
    bbox = (-10, 160, 10, -160)  # crosses the antimeridian
    sub = to_geographic_order(da, bbox)
    lon = sub.lon.values
    assert np.all(np.diff(lon) > 0) and lon[0] >= 160 and lon[-1] <= 200
    # each kept column holds the source column of the same meridian
    for j, x in enumerate(lon):
        src = int(np.flatnonzero(np.isclose(np.mod(da.lon.values - x, 360), 0))[0])
        np.testing.assert_array_equal(sub.values[:, :, j], da.sel(lat=sub.lat).values[:, :, src])
    # the same box given in 0..360 selects the same cells with the same order
    other = to_geographic_order(da, (-10, 160, 10, 200))
    np.testing.assert_array_equal(other.values, sub.values)
    np.testing.assert_array_equal(other.lon.values, lon)
    # Region.subset of the full region follows the same rule
    region = Region.from_dataarray(da)
    np.testing.assert_array_equal(region.subset(bbox).lon.values, lon)


def test_open_data_antimeridian_netcdf_and_grid_distances(tmp_path):
    from lrm_cvx.io import open_data

    da = _global(-180.0, step=10.0)
    da.to_dataset().to_netcdf(tmp_path / "a.nc")
    sub = open_data(tmp_path / "a.nc", bbox=(-10, 150, 10, -150))
    np.testing.assert_array_equal(sub.lon.values, [150, 160, 170, 180, 190, 200, 210])
    region = Region.from_dataarray(sub)
    a, b = region.cell_of(0, 170), region.cell_of(0, -170)
    # neighbours across the antimeridian: 2 grid steps, 2 x 10 degrees of the equator
    assert region.distance(a, b) == pytest.approx(2.0)
    assert region.distance(a, b, metric="km") == pytest.approx(
        2 * np.pi * EARTH_RADIUS_KM * 20 / 360, rel=1e-9)
    # before the fix the columns of a wrapped box came out 30 degrees apart
    assert region.grid_index[b, 1] - region.grid_index[a, 1] == 2


def test_0_360_with_gap_is_put_in_order(tmp_path):
    from lrm_cvx.io import open_data

    lon = np.r_[np.arange(0, 40, 10.0), np.arange(320, 360, 10.0)]  # Greenwich in 0..360
    v = np.arange(2 * 2 * lon.size, dtype=np.float32).reshape(2, 2, lon.size)
    ds = xr.Dataset({"v": (("time", "lat", "lon"), v)},
                    coords={"time": [0, 1], "lat": [0.0, 10.0], "lon": lon})
    ds.to_netcdf(tmp_path / "g.nc")
    da = open_data(tmp_path / "g.nc")
    np.testing.assert_array_equal(da.lon.values, np.arange(-40, 40, 10.0))
    np.testing.assert_array_equal(da.values[..., 0], v[..., 4])  # 320 == -40 comes first
    region = Region.from_dataarray(da)
    # 350 and 0 are neighbours on the map and in the grid
    assert region.distance(region.cell_of(0, 350), region.cell_of(0, 0)) == 1.0
    assert region.cell_of(0, 359.9) == region.cell_of(0, -0.1) == region.cell_of(0, 0)
    with pytest.raises(DataError, match="geographic order"):
        Region.from_dataarray(xr.DataArray(v, dims=("time", "lat", "lon"),
                                           coords={"lat": [0.0, 10.0], "lon": lon}))


def test_cell_of_wraps_longitude_both_ways():
    lon = np.arange(100.0, 270.0, 5.0)  # 0..360 grid across the antimeridian
    region = Region.from_dataarray(_global(0.0).isel(lon=slice(0, 1)).pipe(
        lambda _: xr.DataArray(np.ones((1, 3, lon.size)), dims=("time", "lat", "lon"),
                               coords={"lat": [0.0, 5, 10], "lon": lon})))
    assert region.cell_of(5, -175) == region.cell_of(5, 185)
    assert region.cell_lon[region.cell_of(5, -175)] == 185
    assert region.cell_lon[region.cell_of(5, -176)] == 185
    assert region.cell_lon[region.cell_of(5, 184 - 360)] == 185
    with pytest.raises(RegionError, match="outside"):
        region.cell_of(5, 0.0)
    with pytest.raises(RegionError, match="lat=5, lon=-80"):
        region.cell_of([5, 5], [-175, -80])
    np.testing.assert_array_equal(
        region.cell_of([0, 10], [-175, 100.2]),
        [region.cell_of(0, 185), region.cell_of(10, 100)])


def test_cell_of_great_circle_beats_separate_axes():
    # coarse high-latitude grid: the point's latitude is nearest to row 60, but at 14 degrees of
    # longitude away the great circle is shorter to the poleward row 65
    lat = np.array([55.0, 60.0, 65.0])
    lon = np.array([0.0, 30.0])
    region = Region.from_dataarray(xr.DataArray(np.ones((3, 2)), dims=("lat", "lon"),
                                                coords={"lat": lat, "lon": lon}))
    q = (62.45, 14.0)
    cell = region.cell_of(*q)
    ref, dref = brute_nearest(region, *q)
    assert gc_dist_of_cell(region, cell, *q) == pytest.approx(dref, rel=1e-12)
    assert region.cell_lat[cell] == 65.0


def test_cell_of_row_beyond_the_latitude_bracket():
    # far from a meridian the nearest point on it lies poleward of the query's latitude
    # (tan(foot) = tan(lat) / cos(dlon)): (60.2, 19) is nearest to row 62 of column 0, not to
    # either row bracketing 60.2
    lat = np.arange(55.0, 66.0)
    region = Region.from_dataarray(xr.DataArray(np.ones((lat.size, 2)), dims=("lat", "lon"),
                                                coords={"lat": lat, "lon": [0.0, 40.0]}))
    cell = region.cell_of(60.2, 19.0)
    _, dref = brute_nearest(region, 60.2, 19.0)
    assert gc_dist_of_cell(region, cell, 60.2, 19.0) == pytest.approx(dref, rel=1e-12)
    assert (region.cell_lat[cell], region.cell_lon[cell]) == (62.0, 0.0)


def test_cell_of_masked_nearest_is_an_error_across_antimeridian():
    lon = np.array([170.0, 175, 180, 185, 190])
    v = np.ones((1, 2, 5))
    v[0, :, 3] = np.nan  # the 185 column never observed
    region = Region.from_dataarray(xr.DataArray(v, dims=("time", "lat", "lon"),
                                                coords={"lat": [0.0, 5], "lon": lon}))
    with pytest.raises(RegionError, match="masked"):
        region.cell_of(0, -175)
    assert region.cell_lon[region.cell_of(0, -170)] == 190


@st.composite
def grid_and_points(draw):
    ny = draw(st.integers(1, 6))
    nx = draw(st.integers(1, 7))
    dlat = draw(st.floats(0.5, 20.0))
    dlon = draw(st.floats(0.5, 40.0))
    if nx * dlon >= 360:
        dlon = 359.0 / nx
    lat0 = draw(st.floats(-89.0, 89.0 - dlat * (ny - 1))) if dlat * (ny - 1) < 178 else -89.0
    lat = lat0 + dlat * np.arange(ny)
    lat = lat[lat <= 89.5]
    if draw(st.booleans()):
        lat = lat[::-1]
    lon0 = draw(st.floats(-180.0, 359.0))
    lon = lon0 + dlon * np.arange(nx)
    n = draw(st.integers(1, 8))
    hl = 0.5 * (dlat if lat.size > 1 else 0.5)
    hx = 0.5 * (dlon if nx > 1 else 0.5)
    qlat = draw(arrays(np.float64, n, elements=st.floats(
        max(-90.0, lat.min() - 0.99 * hl), min(90.0, lat.max() + 0.99 * hl))))
    qoff = draw(arrays(np.float64, n, elements=st.floats(-0.99 * hx, lon[-1] - lon[0] + 0.99 * hx)))
    shift = draw(arrays(np.int64, n, elements=st.integers(-1, 1)))
    qlon = lon0 + qoff + 360.0 * shift  # the same meridians in other conventions
    return lat, lon, qlat, qlon


@settings(max_examples=150, deadline=None)
@given(grid_and_points())
def test_resolve_cell_is_the_brute_force_great_circle_nearest(case):
    lat, lon, qlat, qlon = case
    region = Region.from_dataarray(xr.DataArray(np.ones((lat.size, lon.size)),
                                                dims=("lat", "lon"),
                                                coords={"lat": lat, "lon": lon}))
    cells = np.atleast_1d(region.cell_of(qlat, qlon))
    for c, la, lo in zip(cells, qlat, qlon, strict=True):
        _, dref = brute_nearest(region, la, lo)
        assert gc_dist_of_cell(region, c, la, lo) <= dref * (1 + 1e-12) + 1e-9
        assert region.resolve_cell((la, lo)) == c


def test_cell_of_is_fast_on_a_2m_cell_grid():
    import time

    lat = np.linspace(60, 30, 1500)
    lon = np.linspace(170, 210, 1400)  # crosses the antimeridian in 0..360
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((1500, 1400), bool))
    rng = np.random.default_rng(0)
    qlat = rng.uniform(30, 60, 20000)
    qlon = rng.uniform(170, 210, 20000)
    qlon = np.where(qlon > 180, qlon - 360, qlon)
    t0 = time.perf_counter()
    cells = region.cell_of(qlat, qlon)
    assert time.perf_counter() - t0 < 2.0
    sample = rng.choice(20000, 5, replace=False)
    for k in sample:  # spot-check with the brute force on the full 2.1M positions
        _, dref = brute_nearest(region, qlat[k], qlon[k])
        assert gc_dist_of_cell(region, cells[k], qlat[k], qlon[k]) <= dref + 1e-9


def test_region_rejects_bad_coordinates():
    ones = np.ones((3, 3))
    for lat, lon, match in (([0.0, np.nan, 2], [0.0, 1, 2], "non-finite"),
                            ([0.0, 1, 2], [0.0, np.inf, 2], "non-finite"),
                            ([0.0, 2, 1], [0.0, 1, 2], "not monotonic"),
                            ([0.0, 1, 1], [0.0, 1, 2], "duplicated"),
                            ([0.0, 1, 2], [0.0, 360, 2], "same meridian")):
        da = xr.DataArray(ones, dims=("lat", "lon"), coords={"lat": lat, "lon": lon})
        with pytest.raises(DataError, match=match):
            Region.from_dataarray(da)


@settings(max_examples=80, deadline=None)
@given(grid_and_points(), st.integers(0, 2**32 - 1))
def test_cell_of_with_a_mask_is_brute_force_or_a_masked_error(case, seed):
    lat, lon, qlat, qlon = case
    mask = np.random.default_rng(seed).random((lat.size, lon.size)) < 0.7
    mask.flat[0] = True
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}), mask=mask)
    for la, lo in zip(qlat, qlon, strict=True):
        LA, LO = np.meshgrid(lat, lon, indexing="ij")
        d = haversine_km(la, lo, LA.ravel(), LO.ravel())
        nearest = np.flatnonzero(d <= d.min() * (1 + 1e-12) + 1e-9)  # exact ties included
        if not mask.ravel()[nearest].any():
            with pytest.raises(RegionError, match="masked"):
                region.cell_of(la, lo)
        elif mask.ravel()[nearest].all():
            c = region.cell_of(la, lo)
            assert gc_dist_of_cell(region, c, la, lo) <= d.min() * (1 + 1e-12) + 1e-9


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
@pytest.mark.parametrize("lead", [(), (3,), (37,), (2, 19)])
def test_stack_gathers_the_region_cells_as_float32(dtype, lead):
    """``stack`` (np.take, by blocks of rows for another dtype) against a fancy-index gather."""
    rng = np.random.default_rng(len(lead))
    values = (rng.normal(size=lead + (5, 7)) * 100).astype(dtype)
    mask = rng.random((5, 7)) < 0.6
    mask[0, 0] = True
    region = Region.from_dataarray(gridded(np.ones((1, 5, 7))), mask=mask)
    got = region.stack(values)
    ref = values.reshape(lead + (35,))[..., np.flatnonzero(mask)].astype(np.float32)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, ref)
    assert not np.shares_memory(got, values)
    full = Region.from_dataarray(gridded(np.ones((1, 5, 7))), mask=np.ones((5, 7), bool))
    got = full.stack(values)
    np.testing.assert_array_equal(got, values.reshape(lead + (35,)).astype(np.float32))
    assert not np.shares_memory(got, values)  # a copy even when every cell is in the region
