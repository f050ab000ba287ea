"""NOAA CDR NDVI loader: round trips through the writer, QA bits, ranges, bbox, errors."""

import netCDF4
import numpy as np
import pandas as pd
import pytest
import xarray as xr

from lrm_cvx.errors import DataError
from lrm_cvx.io.ndvi import AVHRR_FLAG_NAMES, DEFAULT_MASK_FLAGS, open_ndvi_cdr, parse_cdr_name
from lrm_cvx.io.samples import synthetic_field, write_ndvi_cdr


def field(n=3, shape=(12, 16), seed=0):
    f = synthetic_field(n, shape, missing=0.3, land_fraction=0.9, seed=seed,
                        lat_range=(0.0, 12.0), lon_range=(10.0, 26.0))
    return f.clip(-0.09, 1.0)  # inside the CDR valid_range (-0.1 .. 1)


def raw_qa(shape, seed=0):
    """Random int16 QA with every bit pattern, including the sign bit (polar flag)."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 1 << 16, size=shape, dtype=np.uint32).astype(np.uint16).view(np.int16)


def test_values_scale_and_round_trip(tmp_path):
    f = field()
    write_ndvi_cdr(tmp_path, f)
    g = open_ndvi_cdr(str(tmp_path / "*.nc"))
    assert g.dims == ("time", "lat", "lon") and g.dtype == np.float32
    expected = np.rint(f.values * 1e4) / 1e4
    np.testing.assert_array_equal(np.isnan(g.values), np.isnan(f.values))
    np.testing.assert_allclose(g.values, expected, atol=1e-6)
    np.testing.assert_array_equal(g["time"].values, f["time"].values)
    np.testing.assert_allclose(g["lat"], f["lat"], atol=1e-5)
    assert g.attrs["units"] == "1" and "AVHRR" in g.attrs["mask_flags"]
    assert len(g.attrs["source_files"].splitlines()) == 3


@pytest.mark.parametrize("flag", AVHRR_FLAG_NAMES)
def test_each_avhrr_flag_masks_exactly_its_bit(tmp_path, flag):
    f = field(n=2)
    f = f.fillna(0.5)  # every cell valid in NDVI, so only QA decides
    qa = raw_qa(f.shape, seed=1)
    qa[qa == -32767] = 0  # keep the QA fill value out of this test
    write_ndvi_cdr(tmp_path, f, qa=qa)
    g = open_ndvi_cdr(tmp_path, mask_flags=[flag])
    bit = AVHRR_FLAG_NAMES.index(flag) + 1
    expected = ((qa.view(np.uint16).astype(np.int64) >> bit) & 1).astype(bool)
    np.testing.assert_array_equal(np.isnan(g.values), expected)


def test_default_flags_and_fill_and_range(tmp_path):
    f = field(n=1).fillna(0.4)
    qa = np.zeros(f.shape, dtype=np.int16)
    qa[0, 0, 0] = 2       # cloudy
    qa[0, 0, 1] = 64      # night: not masked by default
    qa[0, 0, 2] = 1 << 9  # ch2_invalid
    qa[0, 0, 3] = -32767  # QA fill: unusable
    paths = write_ndvi_cdr(tmp_path, f, qa=qa)
    with netCDF4.Dataset(paths[0], "a") as nc:
        nc["NDVI"].set_auto_maskandscale(False)
        nc["NDVI"][0, 1, 0] = -9999   # fill
        nc["NDVI"][0, 1, 1] = 10001   # above valid_range
        nc["NDVI"][0, 1, 2] = -1001   # below valid_range
        nc["NDVI"][0, 1, 3] = -1000   # on the edge: valid
    g = open_ndvi_cdr(paths).values[0]
    assert np.isnan(g[0, 0]) and not np.isnan(g[0, 1]) and np.isnan(g[0, 2])
    assert np.isnan(g[0, 3])
    assert np.isnan(g[1, 0]) and np.isnan(g[1, 1]) and np.isnan(g[1, 2])
    assert g[1, 3] == pytest.approx(-0.1)
    assert np.isfinite(g[2:]).all()
    assert set(DEFAULT_MASK_FLAGS["AVHRR"]) >= {"cloudy", "water", "sunglint", "cloud_shadow"}


def test_viirs_layout(tmp_path):
    f = field(n=1).fillna(0.3)
    qa = np.zeros(f.shape, dtype=np.int16)
    qa[0, 0, 0] = 1                    # cloud state cloudy
    qa[0, 0, 1] = 2                    # mixed
    qa[0, 0, 2] = 3                    # "not set": not cloudy
    qa[0, 0, 3] = 1 << 10              # internal cloud flag
    qa[0, 0, 4] = 1 << 2               # shadow
    qa[0, 0, 5] = 3 << 3               # sea water
    qa[0, 0, 6] = 1 << 3               # land (class 1): fine
    qa[0, 0, 7] = np.int16(-32768)     # bit 15 snow/ice
    qa[0, 0, 8] = 3 << 6               # high aerosol: not masked by default
    paths = write_ndvi_cdr(tmp_path, f, product="VIIRS", qa=qa)
    assert paths[0].name.startswith("VIIRS-Land_v001_NPP13C1_S-NPP_")
    g = open_ndvi_cdr(paths).values[0, 0, :9]
    np.testing.assert_array_equal(np.isnan(g), [1, 1, 0, 1, 1, 1, 0, 1, 0])
    g2 = open_ndvi_cdr(paths, mask_flags=["high_aerosol"]).values[0, 0, :9]
    np.testing.assert_array_equal(np.isnan(g2), [0, 0, 0, 0, 0, 0, 0, 0, 1])


def test_mixed_products_sorted_by_time(tmp_path):
    f = field(n=4)
    write_ndvi_cdr(tmp_path, f.isel(time=slice(2, 4)), product="VIIRS")
    write_ndvi_cdr(tmp_path, f.isel(time=slice(0, 2)), product="AVHRR")
    files = sorted(tmp_path.glob("*.nc"), reverse=True)
    g = open_ndvi_cdr(files)
    np.testing.assert_array_equal(g["time"].values, f["time"].values)
    assert g.attrs["products"] == "AVHRR VIIRS"


def test_bbox_keeps_cells_whose_centre_is_inside(tmp_path):
    f = field()
    write_ndvi_cdr(tmp_path, f)
    bbox = (3.0, 14.0, 7.5, 20.2)
    g = open_ndvi_cdr(tmp_path, bbox=bbox)
    lat, lon = f["lat"].values, f["lon"].values
    rows = (lat >= 3.0) & (lat <= 7.5)
    cols = (lon >= 14.0) & (lon <= 20.2)
    np.testing.assert_allclose(g["lat"], lat[rows], atol=1e-5)
    np.testing.assert_allclose(g["lon"], lon[cols], atol=1e-5)
    lazy = open_ndvi_cdr(tmp_path, bbox=bbox, chunks={"time": 1})
    assert lazy.chunks is not None
    xr.testing.assert_identical(lazy.compute(), g)


def test_parse_name():
    m = parse_cdr_name("AVHRR-Land_v005-preliminary_AVH13C1_NOAA-19_20131231_c20140107.nc")
    assert m["product"] == "AVHRR" and m["platform"] == "NOAA-19"
    assert m["date"] == pd.Timestamp("2013-12-31")
    m = parse_cdr_name("VIIRS-Land_v001_JP113C1_NOAA-20_20200101_c20200301.nc")
    assert m["product"] == "VIIRS"
    with pytest.raises(DataError, match="the date 28000624 is outside .* 2262-04-11"):
        parse_cdr_name("AVHRR-Land_v005_AVH13C1_NOAA-19_28000624_c20140107.nc")  # not wrapped


def test_errors_name_the_problem(tmp_path):
    with pytest.raises(DataError, match="no NOAA CDR NDVI file"):
        open_ndvi_cdr(str(tmp_path / "*.nc"))
    f = field(n=2)
    paths = write_ndvi_cdr(tmp_path, f)
    with pytest.raises(DataError, match="outside"):
        open_ndvi_cdr(paths, bbox=(50, 50, 60, 60))
    stray = tmp_path / "x.nc"
    stray.touch()
    with pytest.raises(DataError, match="not a NOAA CDR"):
        open_ndvi_cdr([stray])
    stray.unlink()
    # truncated file: the message names it
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[: len(data) // 3])
    with pytest.raises(DataError, match=paths[1].name):
        open_ndvi_cdr(paths)
    # a file without QA
    other = tmp_path / "other"
    p = write_ndvi_cdr(other, f.isel(time=slice(0, 1)))[0]
    ds = xr.open_dataset(p, mask_and_scale=False).load()
    ds.drop_vars("QA").to_netcdf(other / "tmp.nc")
    (other / "tmp.nc").replace(p)
    with pytest.raises(DataError, match="'QA'"):
        open_ndvi_cdr(p)
    # wrong dims
    flat = ds.isel(time=0)
    flat.to_netcdf(other / "tmp.nc")
    (other / "tmp.nc").replace(p)
    with pytest.raises(DataError, match="dims"):
        open_ndvi_cdr(p)
    # all masked
    allq = tmp_path / "allq"
    write_ndvi_cdr(allq, f, qa=np.full(f.shape, 2, dtype=np.int16))
    with pytest.raises(DataError, match="masked"):
        open_ndvi_cdr(allq)
    with pytest.raises(DataError, match="unknown AVHRR QA flag"):
        open_ndvi_cdr(allq, mask_flags=["clouds"])
