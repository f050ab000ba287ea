"""The window of a large region the validations read (validation/refits.py: ``validation_window``,
``validation_view``; ``Region.crop``): checked against a brute-force search, and by poisoning
every cell outside the window (the validations' results must not move)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import xarray as xr

from lrm_cvx import GLRM, Region
from lrm_cvx.errors import ModelError, RegionError
from lrm_cvx.io.samples import synthetic_dynamic_field
from lrm_cvx.validation import refits
from lrm_cvx.validation.blending import (
    blend_dynamics,
    memoryless_cov,
    select_dynamics,
    unblended_dynamics,
)
from lrm_cvx.validation.refits import validation_view, validation_window


def _grid(mask: np.ndarray) -> xr.DataArray:
    ny, nx = mask.shape
    return xr.DataArray(np.where(mask, 1.0, np.nan), dims=("lat", "lon"),
                        coords={"lat": np.linspace(-10, 10, ny), "lon": np.linspace(0, 30, nx)})


def _brute_window(mask: np.ndarray, cap: int):
    """The smallest clipped square around the valid cells' median row and column holding
    ``cap`` valid cells, by counting every half-width."""
    rows, cols = np.nonzero(mask)
    rc, cc = int(np.median(rows)), int(np.median(cols))
    ny, nx = mask.shape
    for h in range(max(ny, nx) + 1):
        r0, r1, c0, c1 = max(0, rc - h), min(ny, rc + h + 1), max(0, cc - h), min(nx, cc + h + 1)
        if mask[r0:r1, c0:c1].sum() >= cap:
            return slice(r0, r1), slice(c0, c1)
    raise AssertionError("unreachable")


@pytest.mark.parametrize("seed", range(8))
def test_window_is_the_smallest_square_holding_the_cap(seed):
    rng = np.random.default_rng(seed)
    ny, nx = rng.integers(5, 40, size=2)
    mask = rng.random((ny, nx)) < rng.uniform(0.2, 1.0)
    mask[rng.integers(ny), rng.integers(nx)] = True
    region = Region.from_dataarray(_grid(mask))
    n = region.n_cells
    assert validation_window(region, n) is None  # small enough: the whole region
    for cap in {1, max(1, n // 3), max(1, n - 1)} - {n}:
        rows, cols = validation_window(region, cap)
        assert (rows, cols) == _brute_window(mask, cap)
        assert mask[rows, cols].sum() >= cap


def test_crop_keeps_the_cells_in_order():
    rng = np.random.default_rng(0)
    mask = rng.random((12, 15)) < 0.7
    data = _grid(mask).expand_dims(time=3) * np.arange(1, 4)[:, None, None]
    data = data + xr.DataArray(rng.standard_normal(mask.shape), dims=("lat", "lon"))
    region = Region.from_dataarray(data)
    rows, cols = slice(2, 9), slice(4, 13)
    sub = region.crop(rows, cols)
    gi = region.grid_index
    inside = (gi[:, 0] >= 2) & (gi[:, 0] < 9) & (gi[:, 1] >= 4) & (gi[:, 1] < 13)
    np.testing.assert_array_equal(sub.stack(data.isel(lat=rows, lon=cols)),
                                  region.stack(data)[:, inside])
    np.testing.assert_array_equal(sub.cell_lat, region.cell_lat[inside])
    np.testing.assert_array_equal(sub.cell_lon, region.cell_lon[inside])
    with pytest.raises(RegionError, match="slices of step 1"):
        region.crop(slice(0, 9, 2), cols)
    empty = np.zeros_like(mask)
    empty[0, 0] = True
    with pytest.raises(RegionError, match="no valid cell"):
        Region.from_dataarray(_grid(empty)).crop(slice(5, 9), slice(5, 9))
    with pytest.raises(ModelError, match="max_cells"):
        validation_window(region, 0)


@pytest.fixture(scope="module")
def field():
    """Monthly, 14 x 16 cells, a season and persistence."""
    return synthetic_dynamic_field(60, (14, 16), 3, seed=4, seasonal_period=12,
                                   seasonal_amplitude=0.8, A=0.7 * np.eye(3),
                                   Q=0.05 * np.eye(3), freq="MS", missing=0.1, noise=0.2)


CAP = 60


def _poisoned_outside(data: xr.DataArray, rows: slice, cols: slice) -> xr.DataArray:
    """``data`` with every value outside the window replaced by large noise (same gaps)."""
    noise = 50.0 * np.random.default_rng(1).standard_normal(data.shape)
    out = data.copy(data=np.where(np.isfinite(data.values), noise, np.nan))
    out[:, rows, cols] = data[:, rows, cols]
    return out


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GLRM(**{"rank": 3, "offset": True, "spatial": "exponential", "random_state": 0,
                       "progress": False, **kw}).fit(data)


def test_validations_read_only_the_window(field, monkeypatch):
    """With a cap below the region's cells, ``temporal="auto"``'s table and the conformal
    calibration are those of the window: poisoning every other cell moves neither (without
    the window both move: the last assertion)."""
    cal = {"method": "conformal", "residual": False, "adaptive": False, "max_snapshots": 2,
           "max_cells": 40, "temporal": "auto"}
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", CAP)
    clean = _fit(field, temporal="auto", calibration=cal)
    rows, cols = validation_window(clean.region_, CAP)
    assert clean.region_.crop(rows, cols).n_cells < clean.region_.n_cells
    poisoned = _fit(_poisoned_outside(field, rows, cols), temporal="auto", calibration=cal)
    assert not np.allclose(clean.Y, poisoned.Y)  # the model itself did see the poison
    xr.testing.assert_identical(clean.selection_, poisoned.selection_)
    assert clean.calibration_ == poisoned.calibration_
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", 10**9)
    whole = _fit(_poisoned_outside(field, rows, cols), temporal="auto", calibration=cal)
    assert not whole.selection_.identical(clean.selection_)
    assert whole.calibration_ != clean.calibration_


def test_select_dynamics_reads_only_the_window_and_applies_to_the_model(field, monkeypatch):
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", CAP)
    clean = _fit(field, temporal="ar1")
    rows, cols = validation_window(clean.region_, CAP)
    poisoned_data = _poisoned_outside(field, rows, cols)
    poisoned = _fit(poisoned_data, temporal="ar1")
    a, table = select_dynamics(clean, field, seed=0, apply=True)
    b, table_p = select_dynamics(poisoned, poisoned_data, seed=0, apply=True)
    assert a == b
    np.testing.assert_array_equal(table["total"].values, table_p["total"].values)
    # the chosen blend is applied to the whole model (not to the window's view)
    ref = _fit(field, temporal="ar1")
    base = unblended_dynamics(ref)
    expected = blend_dynamics(base, a, memoryless_cov(ref, base))
    np.testing.assert_allclose(clean.dynamics_.A, expected.A)
    assert clean.dynamics_selection_.attrs["choice_alpha"] == a


def test_view_of_a_small_region_is_the_model_itself(field):
    model = _fit(field)
    values = model.region_.stack(field)
    view, data, vals = validation_view(model, field, values)
    assert view is model and data is field and vals is values


def test_view_crops_model_data_and_values(field):
    model = _fit(field)
    values = model.region_.stack(field)
    view, data, vals = validation_view(model, field, values, max_cells=CAP)
    rows, cols = validation_window(model.region_, CAP)
    assert view is not model and view.Y_ is None and model.Y_ is not None
    assert view.region_.n_cells == view.n_cells_ >= CAP
    np.testing.assert_array_equal(vals, view.region_.stack(data))
    xr.testing.assert_identical(data, field.isel(lat=rows, lon=cols))


def test_dask_input_validates_on_the_same_window(field, monkeypatch):
    """A dask-backed record (the out-of-core fit) is validated on the window's values only
    and chooses as in memory."""
    pytest.importorskip("dask")
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", CAP)
    mem = _fit(field, temporal="auto")
    lazy = _fit(field.chunk({"time": 12}), temporal="auto")
    assert mem.selection_.attrs["choice"] == lazy.selection_.attrs["choice"]
    np.testing.assert_allclose(lazy.selection_["mse"], mem.selection_["mse"], rtol=1e-6)


def test_fit_above_the_cap_transforms_its_own_copy_in_place(field, monkeypatch):
    """Above the cap the fit does not keep its stacked data for ``temporal="auto"`` (the
    validation stacks its window) and standardizes its gathered copy in place: the same model,
    selection included, as keeping the stacked copy; the caller's data untouched."""
    from lrm_cvx.glrm import model as model_mod
    from lrm_cvx.glrm import predictive

    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", CAP)
    calls = []
    plain = predictive.standardize

    def spy(*args, **kw):
        calls.append(kw.get("inplace", False))
        return plain(*args, **kw)

    monkeypatch.setattr(predictive, "standardize", spy)
    before = field.copy(deep=True)
    lean = _fit(field, temporal="auto")
    assert calls[0] is True  # the main fit's transform: in place
    xr.testing.assert_identical(field, before)
    monkeypatch.setattr(model_mod, "_keeps_stacked", lambda *a: True)
    calls.clear()
    kept = _fit(field, temporal="auto")
    assert calls[0] is False
    for name in ("X_", "Y_", "offset_"):
        np.testing.assert_array_equal(np.asarray(getattr(lean, name)),
                                      np.asarray(getattr(kept, name)))
    assert lean.spatial_cov_ == kept.spatial_cov_
    xr.testing.assert_identical(lean.selection_, kept.selection_)
    monkeypatch.undo()  # at or below the cap the stacked copy is kept for the selection
    assert model_mod._keeps_stacked("auto", np.zeros((2, 3)), lean.region_)
    assert not model_mod._keeps_stacked(None, np.zeros((2, 3)), lean.region_)


def test_rank_auto_fits_its_reference_model_on_the_window(field, monkeypatch):
    """``rank="auto"``'s reference fit reads the window above the cap (as its refits do), so
    poisoning every other cell leaves its table (rank and temporal choice) unchanged; without
    the cap the table sees the poison."""
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", CAP)
    rows, cols = validation_window(Region.from_dataarray(field), CAP)
    data, region = refits.validation_data(field, Region.from_dataarray(field))
    assert region.n_cells == Region.from_dataarray(field).crop(rows, cols).n_cells
    assert data.shape[1:] == (rows.stop - rows.start, cols.stop - cols.start)
    shapes = []
    plain_fit = GLRM.fit

    def spy(self, data, *args, **kw):
        shapes.append(data.shape[1:])
        return plain_fit(self, data, *args, **kw)

    monkeypatch.setattr(GLRM, "fit", spy)
    clean = _fit(field, rank="auto", temporal="auto")
    monkeypatch.setattr(GLRM, "fit", plain_fit)
    assert shapes[0] == field.shape[1:] and len(shapes) > 2  # the model, then the reference
    assert shapes[1] == data.shape[1:]  # the reference model: the window's grid ...
    assert set(shapes[2:]) == {(region.n_cells,)}  # ... its refits: the window's cells
    poisoned = _fit(_poisoned_outside(field, rows, cols), rank="auto", temporal="auto")
    xr.testing.assert_identical(clean.selection_, poisoned.selection_)
    assert clean.region_.n_cells == Region.from_dataarray(field).n_cells  # the model: all
    monkeypatch.setattr(refits, "VALIDATION_MAX_CELLS", 10**9)
    assert refits.validation_data(field, Region.from_dataarray(field))[0] is field
    whole = _fit(_poisoned_outside(field, rows, cols), rank="auto", temporal="auto")
    assert not whole.selection_.identical(clean.selection_)
