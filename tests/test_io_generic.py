"""open_data dispatches on the source and normalises any NetCDF to (time, lat, lon)."""

import numpy as np
import pytest
import xarray as xr

from lrm_cvx.errors import DataError
from lrm_cvx.io import open_data
from lrm_cvx.io.samples import synthetic_field, write_ndvi_cdr


def test_sample_and_bbox():
    da = open_data("sample:sst", bbox=(0, 150, 30, 200))
    assert da.dims == ("time", "lat", "lon")
    assert float(da.lat.min()) >= 0 and float(da.lat.max()) <= 30
    assert float(da.lon.min()) >= 150 and float(da.lon.max()) <= 200


def test_cdr_files_are_recognised(tmp_path):
    f = synthetic_field(2, (6, 8), seed=0).clip(-0.09, 1)
    write_ndvi_cdr(tmp_path, f)
    da = open_data([str(tmp_path / "*.nc")])
    assert da.name == "ndvi" and da.shape == (2, 6, 8)
    assert "mask_flags" in da.attrs


def test_generic_netcdf_renames_and_picks_variable(tmp_path):
    values = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 4, 3)
    ds = xr.Dataset(
        {"temp": (("time", "longitude", "latitude"), values),
         "other": (("time",), [1.0, 2.0])},
        coords={"time": [0, 1], "latitude": [10.0, 11.0, 12.0], "longitude": [1.0, 2, 3, 4]},
    )
    path = tmp_path / "f.nc"
    ds.to_netcdf(path)
    da = open_data(path)
    assert da.dims == ("time", "lat", "lon") and da.dtype == np.float32
    np.testing.assert_array_equal(da.values, values.transpose(0, 2, 1))
    ds["temp2"] = ds["temp"] * 2
    ds.to_netcdf(tmp_path / "g.nc")
    with pytest.raises(DataError, match="--var"):
        open_data(tmp_path / "g.nc")
    assert float(open_data(tmp_path / "g.nc", var="temp2").max()) == 2 * values.max()
    with pytest.raises(DataError, match="no variable 'nope'"):
        open_data(tmp_path / "g.nc", var="nope")


def test_errors(tmp_path):
    with pytest.raises(DataError, match="no file matches"):
        open_data(str(tmp_path / "*.nc"))
    with pytest.raises(DataError, match="not found"):
        open_data(tmp_path / "missing.nc")
    bad = tmp_path / "bad.nc"
    bad.write_bytes(b"not a netcdf file")
    with pytest.raises(DataError, match="bad.nc"):
        open_data(bad)
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "snapshot-2015-09-15T00_00_00Z.png").write_bytes(b"")
    with pytest.raises(DataError, match="bbox"):
        open_data(tmp_path / "img")
