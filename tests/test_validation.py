"""Shared edge checks: seeds, factor matrices, atomic writes."""

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import Region
from lrm_cvx._validation import as_factor_matrix, as_generator, atomic_output, check_positive
from lrm_cvx.errors import DataError, ModelError, PlanningError


def test_as_generator_is_deterministic():
    assert as_generator(3).random() == as_generator(3).random()
    g = np.random.default_rng(1)
    assert as_generator(g) is g
    with pytest.raises(ModelError, match="random_state"):
        as_generator("seed")


def test_as_factor_matrix_accepts_cell_and_grid_forms():
    da = xr.DataArray(np.ones((1, 2, 3)), dims=("time", "lat", "lon"))
    da[0, 0, 1] = np.nan
    region = Region.from_dataarray(da)
    Y = np.arange(10.0).reshape(2, 5)
    np.testing.assert_array_equal(as_factor_matrix(Y, region), Y)
    Ycell = xr.DataArray(Y, dims=("component", "cell"))
    np.testing.assert_array_equal(as_factor_matrix(Ycell, region), Y)
    Ygrid = region.unstack(Y, dims=("component",))
    np.testing.assert_array_equal(as_factor_matrix(Ygrid, region), Y)
    with pytest.raises(DataError, match="columns"):
        as_factor_matrix(Y[:, :4], region)
    with pytest.raises(DataError, match="non-finite"):
        as_factor_matrix(np.array([[np.nan]]))
    with pytest.raises(DataError, match="region"):
        as_factor_matrix(Ygrid)


def test_check_positive():
    assert check_positive("2.5", "budget") == 2.5
    with pytest.raises(PlanningError, match="budget"):
        check_positive(-1, "budget", error=PlanningError)
    with pytest.raises(DataError, match="> 0"):
        check_positive(0, "ridge", strict=True)


@pytest.mark.parametrize("bad", ["2.5", b"2", True, np.bool_(False)])
def test_check_positive_numbers_only(bad):
    # a string or a bool is refused (not converted) with the same message as a non-number
    with pytest.raises(PlanningError, match=r"^budget \(km\) must be a number, got "):
        check_positive(bad, "budget (km)", error=PlanningError, numbers_only=True)
    assert check_positive(np.float32(2.5), "budget", numbers_only=True) == 2.5
    assert check_positive(3, "budget", numbers_only=True) == 3.0
    with pytest.raises(DataError, match="must be >= 0 and finite"):
        check_positive(np.inf, "budget", numbers_only=True)


def test_atomic_output_replaces_only_on_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_output(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert list(tmp_path.iterdir()) == [target]
    with atomic_output(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"
    with pytest.raises(FileExistsError):
        with atomic_output(target, overwrite=False):
            pass


def test_read_netcdf_names_what_and_path_for_every_unreadable_file(tmp_path):
    """Folder, empty, missing and garbage files are DataErrors naming the kind of file; a good
    file loads whole and equal to what was written."""
    from lrm_cvx._validation import read_netcdf

    good = tmp_path / "good.nc"
    ds = xr.Dataset({"a": ("x", [1.0, 2.0])}, attrs={"format": "t"})
    ds.to_netcdf(good)
    xr.testing.assert_identical(read_netcdf(good, "state file", "W"), ds)
    (tmp_path / "empty.nc").write_bytes(b"")
    (tmp_path / "junk.nc").write_bytes(b"not netcdf\n" * 10)
    cases = {tmp_path: "is a folder, expected a file written by W",
             tmp_path / "empty.nc": "empty",
             tmp_path / "nope.nc": "does not exist",
             tmp_path / "junk.nc": "not a readable NetCDF file"}
    for path, match in cases.items():
        with pytest.raises(DataError, match=match) as err:
            read_netcdf(path, "state file", "W")
        assert "state file" in str(err.value)


def test_first_line_of_an_exception_message():
    from lrm_cvx._validation import first_line

    assert first_line(ValueError("  bad value\nthe traceback's detail")) == "bad value"
    assert first_line(OSError()) == "OSError"
    assert first_line(RuntimeError(" \n ")) == "RuntimeError"


def test_array_digest_tells_contents_shapes_and_dtypes_apart():
    from lrm_cvx._validation import array_digest

    a = np.arange(6.0)
    assert array_digest(a) == array_digest(a.copy())
    assert array_digest(a) != array_digest(a.reshape(2, 3))  # same bytes, other shape
    assert array_digest(a) != array_digest(a.astype(np.float32))
    b = a.copy()
    b[3] += 1e-12
    assert array_digest(a) != array_digest(b)
    empty = np.empty((0, 2))
    assert array_digest(empty) != array_digest(np.empty((0, 3)))  # empty arrays digest too
    assert array_digest(a, empty) != array_digest(a)
