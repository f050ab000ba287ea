"""Bad or unusual data inputs: each gives the named error class or the right answer,
and never changes an input file (every file under the test's folder is checksummed before and
after the call)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx.datasets import load_sample
from lrm_cvx.errors import DataError, RegionError
from lrm_cvx.io import open_data, open_ndvi_cdr
from lrm_cvx.io.samples import synthetic_field, write_ndvi_cdr


@pytest.fixture
def untouched(inputs_unchanged, tmp_path):
    """``with untouched():`` checksums every file under ``tmp_path`` (conftest's
    ``inputs_unchanged``) before the block and checks them after it."""

    @contextlib.contextmanager
    def guard():
        assert any(p.is_file() for p in tmp_path.rglob("*")), "the case must have input files"
        inputs_unchanged.watch(tmp_path)
        yield
        inputs_unchanged.check()

    return guard


def field(nt=3, ny=3, nx=4, lat=None, lon=None, time=None, seed=0) -> xr.DataArray:
    rng = np.random.default_rng(seed)
    lat = np.arange(ny, dtype=float) * 2.0 + 40 if lat is None else np.asarray(lat, float)
    lon = np.arange(nx, dtype=float) * 2.0 - 70 if lon is None else np.asarray(lon, float)
    time = np.arange(nt) if time is None else time
    values = rng.normal(size=(len(time), lat.size, lon.size)).astype(np.float32)
    return xr.DataArray(values, dims=("time", "lat", "lon"),
                        coords={"time": time, "lat": lat, "lon": lon}, name="sst",
                        attrs={"units": "K"})


def write(tmp_path: Path, da: xr.DataArray, name: str = "d.nc") -> Path:
    path = tmp_path / name
    da.to_dataset().to_netcdf(path)
    return path


# ------------------------------------------------------------------ in-memory objects
def test_dataarray_is_accepted_like_a_file(tmp_path, untouched):
    da = field()
    path = write(tmp_path, da)
    with untouched():
        from_file = open_data(path)
    from_memory = open_data(da)
    xr.testing.assert_identical(from_memory, from_file)


def test_dataset_is_accepted_and_var_picks(tmp_path, untouched):
    ds = field().to_dataset()
    ds["other"] = ds["sst"] * 2
    path = tmp_path / "two.nc"
    ds.to_netcdf(path)
    with untouched():
        np.testing.assert_array_equal(open_data(ds, var="other").values, 2 * ds["sst"].values)
        with pytest.raises(DataError, match="--var"):
            open_data(path)


def test_dataarray_with_wrong_dims(tmp_path, untouched):
    write(tmp_path, field())
    with untouched(), pytest.raises(DataError, match=r"\(time, lat, lon\)"):
        open_data(xr.DataArray(np.ones((2, 3)), dims=("time", "station")))


@pytest.mark.parametrize("paths", [None, 123, b"file.nc", {"a": 1}])
def test_paths_of_wrong_type(paths):
    with pytest.raises(DataError, match="paths must be"):
        open_data(paths)


def test_empty_list_of_paths():
    with pytest.raises(DataError, match="empty list"):
        open_data([])


# ------------------------------------------------------------------ bbox
@pytest.mark.parametrize("bbox, match", [
    ((44, -70, 40, -60), "south=44 is north of north=40"),
    ((-95, -70, 40, -60), "south=-95"),
    ((40, -70, 95, -60), "north=95"),
    ((40, float("nan"), 44, -60), "west=nan"),
    ((40, -70, 44), "four numbers"),
    ("40,-70,44,-60", "four numbers"),
])
def test_bad_bbox_names_the_bound(tmp_path, bbox, match, untouched):
    path = write(tmp_path, field())
    with untouched(), pytest.raises(DataError, match=match):
        open_data(path, bbox=bbox)


def test_bbox_outside_the_data(tmp_path, untouched):
    path = write(tmp_path, field())
    with untouched(), pytest.raises(DataError, match="holds no grid cell"):
        open_data(path, bbox=(0, 0, 10, 10))


def test_swapped_bbox_in_region_subset_names_the_bound():
    region = Region.from_dataarray(field())
    with pytest.raises(RegionError, match="south=44 is north of north=40"):
        region.subset((44, -70, 40, -60))


def test_antimeridian_bbox_on_0_360_file(tmp_path, untouched):
    lon = np.arange(0.0, 360.0, 10.0)
    da = field(lon=lon, lat=[-10.0, 0, 10])
    path = write(tmp_path, da)
    with untouched():
        out = open_data(path, bbox=(-10, 160, 10, -160))
    np.testing.assert_array_equal(out.lon.values, [160, 170, 180, 190, 200])
    np.testing.assert_array_equal(out.values, da.sel(lon=[160, 170, 180, 190, 200]).values)


def test_antimeridian_bbox_on_sample():
    out = open_data("sample:sst", bbox=(0, 170, 30, -170))
    lon = out.lon.values
    assert np.all(np.diff(lon) > 0) and lon.min() >= 170 and lon.max() <= 190
    ref = load_sample("sst").sel(lon=lon, lat=out.lat)
    np.testing.assert_array_equal(out.values, ref.values)


def test_antimeridian_bbox_on_ndvi_cdr(tmp_path, untouched):
    lon = np.arange(-179.5, 180.0, 1.0)
    f = synthetic_field(2, (4, lon.size), seed=0).clip(-0.09, 1)
    f = f.assign_coords(lon=lon)
    write_ndvi_cdr(tmp_path, f)
    with untouched():
        out = open_ndvi_cdr(tmp_path, bbox=(-90, 177, 90, -177))
        full = open_ndvi_cdr(tmp_path)
    np.testing.assert_allclose(out.lon.values, [177.5, 178.5, 179.5, 180.5, 181.5, 182.5])
    cols = [357, 358, 359, 0, 1, 2]
    np.testing.assert_array_equal(out.values, full.values[:, :, cols])


def test_swapped_bbox_on_ndvi_cdr(tmp_path, untouched):
    write_ndvi_cdr(tmp_path, synthetic_field(1, (4, 5), seed=0).clip(-0.09, 1))
    with untouched(), pytest.raises(DataError, match="south=.* is north of north"):
        open_ndvi_cdr(tmp_path, bbox=(50, -80, 40, -60))


# ------------------------------------------------------------------ coordinates
@pytest.mark.parametrize("lat, lon, match", [
    ([40.0, np.nan, 44], None, "lat has a non-finite value"),
    (None, [-70.0, -68, np.inf, -64], "lon has a non-finite value"),
    ([40.0, 44, 42], None, "lat is not monotonic at positions 1, 2"),
    ([40.0, 42, 42], None, "lat is duplicated"),
    (None, [-70.0, -68, -68, -64], "lon is duplicated"),
    (None, [-180.0, -90, 0, 180], "same meridian"),
])
def test_bad_coordinates(tmp_path, lat, lon, match, untouched):
    path = write(tmp_path, field(lat=lat, lon=lon))
    with untouched(), pytest.raises(DataError, match=match):
        open_data(path)


def test_shuffled_longitudes_are_sorted(tmp_path, untouched):
    da = field(lon=[-64.0, -70, -66, -68])
    path = write(tmp_path, da)
    with untouched():
        out = open_data(path)
    np.testing.assert_array_equal(out.lon.values, [-70, -68, -66, -64])
    np.testing.assert_array_equal(out.values, da.sortby("lon").values)


def test_descending_latitude_is_kept(tmp_path, untouched):
    da = field(lat=[44.0, 42, 40])
    path = write(tmp_path, da)
    with untouched():
        out = open_data(path)
    np.testing.assert_array_equal(out.lat.values, [44, 42, 40])
    np.testing.assert_array_equal(out.values, da.values)


def test_region_refuses_longitudes_out_of_geographic_order():
    da = field(lon=[0.0, 10, 300, 350])
    with pytest.raises(DataError, match="geographic order"):
        Region.from_dataarray(da)


@pytest.mark.parametrize("lat, bad", [([80.0, 85, 90, 95], "95 at position 3"),
                                      ([-100.0, -95, -90], "-100 at position 0")])
def test_latitude_beyond_a_pole_is_refused(tmp_path, lat, bad, untouched):
    da = field(lat=lat)
    path = write(tmp_path, da)
    with untouched(), pytest.raises(DataError, match=f"coordinate lat is {bad}, beyond a pole"):
        open_data(path)
    with pytest.raises(DataError, match=f"coordinate lat is {bad}") as err:
        Region.from_dataarray(da)  # what GLRM.fit builds from an in-memory record
    assert "\n" not in str(err.value) and "[-90, 90]" in str(err.value)


def test_latitude_in_degrees_north_is_checked_whatever_the_values():
    da = field(lat=np.arange(100.0), lon=[0.0, 1, 2, 3])
    Region.from_dataarray(da)  # a bare index 0, 1, 2, ... is a pixel grid, not degrees
    da["lat"].attrs["units"] = "degrees_north"
    with pytest.raises(DataError, match="coordinate lat is 91 at position 91"):
        Region.from_dataarray(da)


def test_latitudes_of_a_grid_in_metres_are_not_degrees(tmp_path, untouched):
    da = field(lat=[1e5, 2e5, 3e5], lon=[4e5, 5e5, 6e5, 7e5])
    path = write(tmp_path, da)
    with untouched():
        out = open_data(path)
    np.testing.assert_array_equal(out.lat.values, [1e5, 2e5, 3e5])


# ------------------------------------------------------------------ files
def test_empty_file(tmp_path, untouched):
    (tmp_path / "empty.nc").write_bytes(b"")
    with untouched(), pytest.raises(DataError, match="empty.nc is an empty file"):
        open_data(tmp_path / "empty.nc")


def test_corrupt_file(tmp_path, untouched):
    (tmp_path / "bad.nc").write_bytes(np.random.default_rng(0).bytes(4096))
    with untouched(), pytest.raises(DataError, match="bad.nc"):
        open_data(tmp_path / "bad.nc")


def test_truncated_netcdf(tmp_path, untouched):
    path = write(tmp_path, field(nt=50, ny=30, nx=40), "full.nc")
    data = path.read_bytes()
    (tmp_path / "cut.nc").write_bytes(data[: len(data) // 2])
    with untouched(), pytest.raises(DataError, match="cut.nc"):
        open_data(tmp_path / "cut.nc")


def test_wrong_variable_lists_the_available_ones(tmp_path, untouched):
    path = write(tmp_path, field())
    with untouched(), pytest.raises(DataError, match=r"no variable 'temp'.*\['sst'\]"):
        open_data(path, var="temp")


def test_file_without_a_gridded_variable(tmp_path, untouched):
    xr.Dataset({"x": ("station", [1.0, 2.0])}).to_netcdf(tmp_path / "st.nc")
    with untouched(), pytest.raises(DataError, match="cannot choose the variable"):
        open_data(tmp_path / "st.nc")


def test_variable_with_no_snapshot(tmp_path, untouched):
    path = write(tmp_path, field(time=np.arange(0)))
    with untouched(), pytest.raises(DataError, match="empty"):
        open_data(path)


def test_extra_dim_of_size_two(tmp_path, untouched):
    da = xr.concat([field(), field()], dim="depth").transpose("time", "depth", "lat", "lon")
    path = write(tmp_path, da)
    with untouched(), pytest.raises(DataError, match="extra dim 'depth' of size 2"):
        open_data(path)


def test_folder_inside_a_list(tmp_path, untouched):
    write(tmp_path, field())
    (tmp_path / "sub").mkdir()
    with untouched(), pytest.raises(DataError, match="is a folder"):
        open_data([tmp_path / "d.nc", tmp_path / "sub"])


def test_folder_without_data(tmp_path, untouched):
    (tmp_path / "notes.txt").write_text("nothing here")
    with untouched(), pytest.raises(DataError, match="no images and no NetCDF"):
        open_data(tmp_path)


# ------------------------------------------------------------------ values and times
def test_all_nan_snapshot_is_dropped_with_a_warning(tmp_path, untouched):
    da = field(nt=4)
    da[2] = np.nan
    path = write(tmp_path, da)
    with untouched(), pytest.warns(UserWarning, match="dropped 1 all-NaN snapshot"):
        out = open_data(path)
    np.testing.assert_array_equal(out.time.values, [0, 1, 3])
    np.testing.assert_array_equal(out.values, da.values[[0, 1, 3]])


def test_all_nan_everywhere(tmp_path, untouched):
    da = field() * np.nan
    path = write(tmp_path, da)
    with untouched(), pytest.raises(DataError, match="no finite value"):
        open_data(path)


def test_all_nan_inside_the_bbox(tmp_path, untouched):
    da = field()
    da[:, :, :2] = np.nan
    path = write(tmp_path, da)
    with untouched(), pytest.raises(DataError, match="no finite value.*bbox"):
        open_data(path, bbox=(40, -70, 44, -68))


def test_duplicate_times_in_one_file(tmp_path, untouched):
    path = write(tmp_path, field(time=np.array([0, 1, 1])))
    with untouched(), pytest.raises(DataError, match="time 1 occurs more than once"):
        open_data(path)


def test_duplicate_times_across_files(tmp_path, untouched):
    write(tmp_path, field(time=np.array([0, 1]), seed=1), "a.nc")
    write(tmp_path, field(time=np.array([1, 2]), seed=2), "b.nc")
    with untouched(), pytest.raises(DataError, match="occurs more than once"):
        open_data(str(tmp_path / "*.nc"))


def test_unsorted_times_are_sorted_with_a_warning(tmp_path, untouched):
    da = field(time=np.array([2, 0, 1]))
    path = write(tmp_path, da)
    with untouched(), pytest.warns(UserWarning, match="sorted by time"):
        out = open_data(path)
    np.testing.assert_array_equal(out.time.values, [0, 1, 2])
    np.testing.assert_array_equal(out.values, da.sortby("time").values)


def test_one_cell_region(tmp_path, untouched):
    da = field()
    path = write(tmp_path, da)
    with untouched():
        out = open_data(path, bbox=(41.5, -68.5, 42.5, -67.5))
    assert out.shape == (3, 1, 1)
    np.testing.assert_array_equal(out.values[:, 0, 0], da.values[:, 1, 1])
    region = Region.from_dataarray(out)
    assert region.n_cells == 1
    assert region.cell_of(42.1, -68.1) == 0
    assert region.distance(0, 0, metric="km") == 0.0
    with pytest.raises(RegionError, match="outside"):
        region.cell_of(43.0, -68.0)


# ------------------------------------------------------------------ locations
@pytest.mark.parametrize("where, match", [
    ((np.nan, -70.0), "lat must be finite"),
    ((40.0, np.inf), "lon must be finite"),
    (("north", "west"), "pair of numbers"),
    (1.5, "cell index or a"),
    ((60.0, -70.0), r"\(lat=60, lon=-70\) is outside"),
])
def test_bad_start_locations(where, match):
    region = Region.from_dataarray(field())
    with pytest.raises(RegionError, match=match):
        region.resolve_cell(where)


def test_unknown_sample_lists_available():
    with pytest.raises(DataError, match="available: hgt500, sst"):
        open_data("sample:nope")


# ------------------------------------------------------------------ images
@pytest.mark.parametrize("bbox, match", [
    ((48.0, -80.0, 40.0, -68.0), "south=48 is north of north=40"),
    ((-10.0, 170.0, 10.0, -170.0), r"antimeridian give east \+ 360 \(170 .. 190\)"),
])
def test_image_bbox_errors_name_the_bound(tmp_path, bbox, match, untouched):
    from lrm_cvx.io.imagery import open_image_stack, write_image_stack

    write_image_stack(tmp_path, synthetic_field(2, (6, 8), seed=0))
    with untouched(), pytest.raises(RegionError, match=match):
        open_image_stack(tmp_path, bbox)


def test_image_bbox_across_antimeridian_unwrapped(tmp_path, untouched):
    from lrm_cvx.io.imagery import open_image_stack, write_image_stack

    write_image_stack(tmp_path, synthetic_field(2, (6, 8), seed=0))
    with untouched():
        hue = open_image_stack(tmp_path, (-10.0, 170.0, 10.0, 190.0), edge_sigma=None)
    np.testing.assert_allclose(hue.lon.values, 170 + 2.5 * (np.arange(8) + 0.5))
    region = Region.from_dataarray(hue)
    assert region.cell_lon[region.cell_of(0.0, -178.0)] == pytest.approx(181.25)


# ------------------------------------------------------------------ NOAA CDR files
def test_ndvi_cdr_with_nan_latitude(tmp_path, untouched):
    f = synthetic_field(1, (4, 5), seed=0).clip(-0.09, 1)
    lat = f.lat.values.copy()
    lat[1] = np.nan
    write_ndvi_cdr(tmp_path, f.assign_coords(lat=lat))
    with untouched(), pytest.raises(DataError, match=r"AVHRR-Land.*lat has a non-finite"):
        open_ndvi_cdr(tmp_path)


def test_ndvi_cdr_empty_file(tmp_path, untouched):
    (tmp_path / "AVHRR-Land_v005_AVH13C1_NOAA-19_20130101_c20240101000000.nc").write_bytes(b"")
    with untouched(), pytest.raises(DataError, match="cannot read NDVI file .*20130101"):
        open_data(tmp_path)


def test_ndvi_cdr_bbox_in_the_other_convention(tmp_path, untouched):
    lon = np.arange(-179.5, 180.0, 1.0)
    f = synthetic_field(1, (3, lon.size), seed=1, missing=0.0, land_fraction=1.0)
    f = f.clip(-0.09, 1).assign_coords(lon=lon)
    write_ndvi_cdr(tmp_path, f)
    with untouched():
        out = open_data(tmp_path, bbox=(-90, 183, 90, 186))  # 0..360 box on -180..180 files
        full = open_data(tmp_path)
    np.testing.assert_allclose(out.lon.values, [183.5, 184.5, 185.5])
    np.testing.assert_array_equal(out.values, full.sel(lon=[-176.5, -175.5, -174.5]).values)


# ------------------------------------------------------------- a NaT time
def _with_nat() -> xr.DataArray:
    import pandas as pd

    rng = np.random.default_rng(0)
    t = pd.date_range("2000-01-01", periods=8, freq="D").values.copy()
    t[3] = np.datetime64("NaT")
    return xr.DataArray(rng.normal(size=(8, 4, 5)).astype(np.float32),
                        dims=("time", "lat", "lon"),
                        coords={"time": t, "lat": np.arange(4.0), "lon": np.arange(5.0)})


def test_nat_time_is_refused_by_open_data_and_fit(tmp_path):
    from lrm_cvx.glrm import GLRM

    da = _with_nat()
    with pytest.raises(DataError, match=r"time has 1 missing value\(s\) \(NaT\) at position"):
        open_data(da)
    da.to_netcdf(tmp_path / "nat.nc")
    with pytest.raises(DataError, match=r"NaT\) at position\(s\) \[3\]"):
        open_data(tmp_path / "nat.nc")
    with pytest.raises(DataError, match="NaT"):  # a plain fit never carries NaT into X_.time
        GLRM(2, progress=False).fit(da)


# ------------------------------------------------------------- hangs and unclear failures
@contextlib.contextmanager
def _unhelpful_server(kind: str):
    """A server on 127.0.0.1 that accepts connections and then never answers (``silent``) or
    answers with a status line and headers, then one byte of the body now and then
    (``trickle``); yields its URL."""
    import socket
    import threading

    stop = threading.Event()
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(8)
    sock.settimeout(0.05)
    conns = []

    def serve():
        while not stop.is_set():
            with contextlib.suppress(OSError):
                conn, _ = sock.accept()
                conns.append(conn)
                if kind == "trickle":
                    conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\n"
                                 b"Accept-Ranges: bytes\r\n\r\n")
            if kind == "trickle":
                for conn in conns:
                    with contextlib.suppress(OSError):
                        conn.send(b"\x89")
                stop.wait(0.1)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}/data.nc"
    finally:
        stop.set()
        thread.join(timeout=5)
        for conn in conns:
            conn.close()
        sock.close()


@pytest.mark.parametrize("kind", ["silent", "trickle"])
def test_a_server_that_never_answers_times_out_with_one_line(monkeypatch, kind):
    import time

    pytest.importorskip("aiohttp")
    pytest.importorskip("fsspec")
    monkeypatch.setenv("LRM_CVX_TIMEOUT", "1.5")
    monkeypatch.setenv("LRM_CVX_READ_TIMEOUT", "0.5")
    with _unhelpful_server(kind) as url:
        start = time.monotonic()
        with pytest.raises(DataError) as exc:
            open_data(url)
        took = time.monotonic() - start
    text = str(exc.value)
    assert "\n" not in text and text.startswith(f"cannot read {url}: timed out"), text
    assert "LRM_CVX_TIMEOUT" in text
    assert took < 6, took  # one timeout, a retry within LRM_CVX_TIMEOUT, never minutes


def test_a_bad_timeout_variable_is_named(monkeypatch):
    monkeypatch.setenv("LRM_CVX_READ_TIMEOUT", "soon")
    with pytest.raises(DataError, match="LRM_CVX_READ_TIMEOUT must be a number of seconds"):
        open_data("http://127.0.0.1:9/data.nc")


@pytest.mark.parametrize("kind", ["fifo", "loop"])
def test_a_fifo_or_symlink_loop_as_data_is_refused(tmp_path, kind):
    import os

    path = tmp_path / "d.nc"
    if kind == "fifo":
        os.mkfifo(path)  # reading it would wait for a writer forever
    else:
        path.symlink_to(path)
    needle = "is not a regular file" if kind == "fifo" else "is a symlink loop"
    with pytest.raises(DataError, match=f"data file {path} {needle}"):
        open_data(path)
    with pytest.raises(DataError, match=needle):
        open_data([write(tmp_path, field(), "ok.nc"), path])


def test_values_beyond_float32_are_named_not_called_missing(tmp_path, untouched):
    da = field().astype(np.float64)
    da[1, 1, 2] = 3e38  # still a float32: read as it is
    fits = write(tmp_path, da, "ok.nc")
    da[1, 1, 2] = 1e301
    path = write(tmp_path, da)
    with untouched():
        np.testing.assert_allclose(open_data(fits).values[1, 1, 2], 3e38, rtol=1e-6)
        with pytest.raises(DataError) as exc:
            open_data(path)
    text = str(exc.value)
    assert "all NaN" not in text and "\n" not in text
    assert "1 value(s) up to 1e+301" in text and "beyond float32" in text
    assert "rescale the data" in text
