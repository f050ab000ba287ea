"""The grid and its valid cells: every later step speaks in this module's cell indices.

A :class:`Region` is a rectilinear ``(lat, lon)`` grid plus a boolean mask of valid cells
(observed at least once, or given). Valid cells are numbered ``0 .. L-1`` in row-major order of
the grid, so the lowest cell index is also the first in reading order; ties anywhere in the
toolkit go to the lowest index. The region converts between gridded DataArrays ``(..., lat, lon)``
and the flat matrix view ``(..., L)`` that the algorithms use.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal

import numpy as np
import xarray as xr

from .errors import DataError, RegionError

__all__ = [
    "Region", "BBox", "EARTH_RADIUS_KM", "spatial_dims", "check_bbox", "check_coords",
    "geographic_order", "lon_in_box", "to_geographic_order", "check_region",
]

BBox = tuple[float, float, float, float]
"""``(south, west, north, east)`` in degrees, the order NASA Worldview uses."""

EARTH_RADIUS_KM = 6371.0088
"""Mean Earth radius (IUGG) used by the great-circle ``metric="km"``."""

_LAT_NAMES = ("lat", "latitude", "y")
_LON_NAMES = ("lon", "longitude", "x")


def spatial_dims(da: xr.DataArray) -> tuple[Hashable, Hashable]:
    """Names of the ``(lat, lon)`` dims of ``da``: its last two, which must look spatial."""
    if da.ndim < 2:
        raise DataError(f"expected dims (..., lat, lon), got {da.dims}")
    lat, lon = da.dims[-2], da.dims[-1]
    if str(lat).lower() not in _LAT_NAMES or str(lon).lower() not in _LON_NAMES:
        raise DataError(
            f"expected the last two dims to be (lat, lon) (or latitude/longitude, y/x), "
            f"got {da.dims}"
        )
    return lat, lon


def _grid_coord(da: xr.DataArray, dim: Hashable) -> np.ndarray:
    values = np.asarray(da[dim].values if dim in da.coords else np.arange(da.sizes[dim]))
    return values.astype(np.float64)


@dataclass(frozen=True, eq=False)
class Region:
    """A rectilinear grid and its valid cells.

    Parameters
    ----------
    lat, lon : 1-D coordinate DataArrays of the grid (``ny`` and ``nx`` values), attributes kept.
    mask : ``(ny, nx)`` bool, True where the cell is valid (part of the region).
    attrs : attributes of the data the region came from (e.g. units), copied to ``unstack``.
    name : the data variable's name, copied to ``unstack``.
    """

    lat: xr.DataArray
    lon: xr.DataArray
    mask: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)
    name: Hashable | None = None

    def __post_init__(self) -> None:
        mask = np.asarray(self.mask, dtype=bool)
        if mask.shape != (self.lat.size, self.lon.size):
            raise RegionError(
                f"mask has shape {mask.shape}, expected (lat, lon) = "
                f"({self.lat.size}, {self.lon.size})"
            )
        if not mask.any():
            raise DataError("the region has no valid cell (every cell is masked or never observed)")
        mask.setflags(write=False)
        object.__setattr__(self, "mask", mask)
        lat_v = np.asarray(self.lat.values, dtype=np.float64)
        lon_v = np.asarray(self.lon.values, dtype=np.float64)
        check_coords(lat_v, lon_v, "region grid")
        if _is_degrees(lon_v):
            order, _ = geographic_order(lon_v)
            if not np.array_equal(order, np.arange(lon_v.size)):
                raise DataError(
                    f"coordinate lon ({lon_v.min():g} .. {lon_v.max():g}) is not in geographic "
                    "order: columns must run eastward and be contiguous (the widest gap between "
                    "meridians at the edges). Open the data with lrm_cvx.io.open_data, or "
                    "reorder it with lrm_cvx.region.to_geographic_order(da)"
                )
        elif _first_bad_step(lon_v) is not None:
            raise DataError("coordinate lon must be strictly monotonic")
        object.__setattr__(self, "_sphere", bool(
            _is_degrees(lon_v) and np.all(np.abs(lat_v) <= 90.0)))
        flat = np.flatnonzero(mask.ravel())
        rows, cols = np.divmod(flat, mask.shape[1])
        grid_index = np.column_stack([rows, cols]).astype(np.int64)
        grid_index.setflags(write=False)
        object.__setattr__(self, "_flat", flat)
        object.__setattr__(self, "grid_index", grid_index)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_dataarray(cls, da: xr.DataArray, mask: Any = None) -> Region:
        """Region of a ``(time, lat, lon)`` or ``(lat, lon)`` DataArray.

        Valid cells are those observed (not NaN) at least once, or ``mask`` (a ``(lat, lon)``
        boolean array or DataArray, True = valid) when given.
        """
        if not isinstance(da, xr.DataArray):
            raise DataError(f"da must be an xarray.DataArray, got {type(da).__name__}")
        if da.ndim not in (2, 3):
            raise DataError(f"da must have dims (time, lat, lon) or (lat, lon), got {da.dims}")
        lat_dim, lon_dim = spatial_dims(da)
        if mask is None:
            # an inf is a value, not a gap: its cell stays in the region, so the fit names it
            # (check_data) instead of dropping a cell of fill values without a word
            observed = da.notnull()
            if da.ndim == 3:
                observed = observed.any(da.dims[0])
            mask = np.asarray(observed.values, dtype=bool)
            if not mask.any():
                raise DataError("da has no finite value: every cell is missing (all NaN)")
        else:
            mask = np.asarray(getattr(mask, "values", mask))
            if mask.shape != (da.sizes[lat_dim], da.sizes[lon_dim]):
                raise RegionError(
                    f"mask has shape {mask.shape}, expected (lat, lon) = "
                    f"({da.sizes[lat_dim]}, {da.sizes[lon_dim]})"
                )
            if mask.dtype != bool:
                raise RegionError(f"mask must be boolean, got dtype {mask.dtype}")
        lat = xr.DataArray(_grid_coord(da, lat_dim), dims=(lat_dim,), name=lat_dim)
        lon = xr.DataArray(_grid_coord(da, lon_dim), dims=(lon_dim,), name=lon_dim)
        check_coords(lat.values, lon.values, "da", geographic=_geographic(da, lat_dim, lon.values))
        if lat_dim in da.coords:
            lat.attrs.update(da[lat_dim].attrs)
        if lon_dim in da.coords:
            lon.attrs.update(da[lon_dim].attrs)
        lat = lat.assign_coords({lat_dim: lat.values})
        lon = lon.assign_coords({lon_dim: lon.values})
        return cls(lat=lat, lon=lon, mask=mask, attrs=dict(da.attrs), name=da.name)

    # ------------------------------------------------------------------ basic geometry
    @property
    def n_cells(self) -> int:
        """L, the number of valid cells."""
        return int(self.grid_index.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``, the grid's shape."""
        return (int(self.lat.size), int(self.lon.size))

    @property
    def dims(self) -> tuple[Hashable, Hashable]:
        """Names of the grid's ``(lat, lon)`` dims."""
        return (self.lat.dims[0], self.lon.dims[0])

    @property
    def cell_lat(self) -> np.ndarray:
        """Latitude of each valid cell's centre, ``(L,)`` degrees."""
        return self.lat.values[self.grid_index[:, 0]]

    @property
    def cell_lon(self) -> np.ndarray:
        """Longitude of each valid cell's centre, ``(L,)`` degrees."""
        return self.lon.values[self.grid_index[:, 1]]

    @property
    def cell_grid(self) -> np.ndarray:
        """``(ny, nx)`` int64 array: the cell index at each grid position, -1 where masked."""
        grid = np.full(self.shape[0] * self.shape[1], -1, dtype=np.int64)
        grid[self._flat] = np.arange(self.n_cells)
        return grid.reshape(self.shape)

    @cached_property
    def cell_lookup(self) -> np.ndarray:
        """:attr:`cell_grid` built once and read-only (for repeated neighbourhood look-ups)."""
        grid = self.cell_grid
        grid.setflags(write=False)
        return grid

    def __repr__(self) -> str:
        ny, nx = self.shape
        return (
            f"Region({ny} x {nx} grid, {self.n_cells} valid cells, "
            f"lat {self.lat.values.min():.4g}..{self.lat.values.max():.4g}, "
            f"lon {self.lon.values.min():.4g}..{self.lon.values.max():.4g})"
        )

    def equals(self, other: Region) -> bool:
        """True when both regions have the same grid coordinates and mask."""
        return (
            isinstance(other, Region)
            and self.shape == other.shape
            and np.array_equal(self.lat.values, other.lat.values)
            and np.array_equal(self.lon.values, other.lon.values)
            and np.array_equal(self.mask, other.mask)
        )

    # ------------------------------------------------------------------ stack / unstack
    def _check_grid(self, da: xr.DataArray) -> None:
        lat_dim, lon_dim = spatial_dims(da)
        if (da.sizes[lat_dim], da.sizes[lon_dim]) != self.shape:
            raise RegionError(
                f"data grid is {da.sizes[lat_dim]} x {da.sizes[lon_dim]}, "
                f"the region's is {self.shape[0]} x {self.shape[1]}"
            )
        for dim, ref in ((lat_dim, self.lat), (lon_dim, self.lon)):
            if dim in da.coords and not np.allclose(
                np.asarray(da[dim].values, dtype=np.float64), ref.values, rtol=0, atol=1e-6
            ):
                raise RegionError(f"data coordinate {dim!r} differs from the region's grid")

    def stack(self, da: xr.DataArray | np.ndarray) -> np.ndarray:
        """Matrix view of gridded data: ``(..., lat, lon)`` -> ``(..., L)`` float32, NaN = missing.

        A DataArray whose last dim is ``cell`` (already stacked) is returned as float32 values.
        """
        if isinstance(da, xr.DataArray):
            if da.dims and da.dims[-1] == "cell":
                values = np.asarray(da.values, dtype=np.float32)
                if values.shape[-1] != self.n_cells:
                    raise RegionError(
                        f"data has {values.shape[-1]} cells, the region has {self.n_cells}"
                    )
                return values
            self._check_grid(da)
            values = da.values
        else:
            values = np.asarray(da)
            if values.shape[-2:] != self.shape:
                raise RegionError(
                    f"array ends in shape {values.shape[-2:]}, the region's grid is {self.shape}"
                )
        lead = values.shape[:-2]
        flat = values.reshape(lead + (-1,))
        if flat.dtype == np.float32:  # np.take gathers 5-10x faster than fancy indexing
            return np.take(flat, self._flat, axis=-1)
        out = np.empty(lead + (self.n_cells,), dtype=np.float32)
        src, dst = flat.reshape(-1, flat.shape[-1]), out.reshape(-1, self.n_cells)
        for lo in range(0, src.shape[0], 16):  # no full-size temporary of another dtype
            dst[lo:lo + 16] = np.take(src[lo:lo + 16], self._flat, axis=-1)
        return out

    def unstack(
        self,
        values: np.ndarray | xr.DataArray,
        *,
        dims: Sequence[Hashable] | None = None,
        coords: dict[Hashable, Any] | None = None,
        name: Hashable | None = None,
        attrs: dict[str, Any] | None = None,
    ) -> xr.DataArray:
        """Gridded view of cell values: ``(..., L)`` -> ``(..., lat, lon)``, NaN off the region.

        ``values`` may be a DataArray whose last dim is ``cell`` (its other dims and coords are
        kept) or an array with leading dims named by ``dims``. The grid's coordinates and the
        region's attributes (or ``attrs``) are attached.
        """
        lead_coords: dict[Hashable, Any] = {}
        if isinstance(values, xr.DataArray):
            if values.dims[-1] != "cell":
                raise DataError(f"values must end in dim 'cell', got {values.dims}")
            dims = values.dims[:-1]
            lead_coords = {
                k: v for k, v in values.coords.items() if "cell" not in v.dims
            }
            name = values.name if name is None else name
            attrs = dict(values.attrs) if attrs is None else attrs
            values = values.values
        values = np.asarray(values)
        if values.shape[-1] != self.n_cells:
            raise RegionError(
                f"values have {values.shape[-1]} cells, the region has {self.n_cells}")
        lead = values.shape[:-1]
        if dims is None:
            dims = {0: (), 1: ("time",)}.get(len(lead), tuple(f"dim_{i}" for i in range(len(lead))))
        if len(dims) != len(lead):
            raise DataError(f"dims {tuple(dims)} do not match the leading shape {lead}")
        dtype = np.result_type(values.dtype, np.float32)
        out = np.full(lead + (self.shape[0] * self.shape[1],), np.nan, dtype=dtype)
        out[..., self._flat] = values
        lat_dim, lon_dim = self.dims
        all_coords = {**lead_coords, **(coords or {}), lat_dim: self.lat, lon_dim: self.lon}
        return xr.DataArray(
            out.reshape(lead + self.shape),
            dims=tuple(dims) + (lat_dim, lon_dim),
            coords=all_coords,
            name=self.name if name is None else name,
            attrs=dict(self.attrs if attrs is None else attrs),
        )

    def cell_coords(self) -> dict[str, tuple[str, np.ndarray]]:
        """Coordinates for a ``cell`` dim: the cell index and each cell's lat and lon."""
        return {
            "cell": ("cell", np.arange(self.n_cells)),
            "lat": ("cell", self.cell_lat),
            "lon": ("cell", self.cell_lon),
        }

    # ------------------------------------------------------------------ locations
    def cell_of(self, lat: Any, lon: Any) -> Any:
        """Cell index of the grid position nearest to ``(lat, lon)`` (scalars or arrays).

        On a grid in degrees the nearest position is the one at the smallest great-circle
        distance, with longitudes compared modulo 360 (a query at -175 finds a grid column at
        185; 359.9 finds -0.1); ties go to the lowest cell index. Vectorised: binary search on
        the two 1-D axes, a few candidates per point. Raises :class:`RegionError` when a point
        lies outside the grid (by more than half a grid spacing) or its nearest grid position is
        masked (the nearest *valid* cell is not substituted).
        """
        try:
            lat_a, lon_a = np.broadcast_arrays(np.asarray(lat, dtype=np.float64),
                                               np.asarray(lon, dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise RegionError(
                f"lat and lon must be numbers or arrays of one shape: {exc}") from None
        for what, values in (("lat", lat_a), ("lon", lon_a)):
            if not np.all(np.isfinite(values)):
                bad = np.ravel(values)[np.flatnonzero(~np.isfinite(np.ravel(values)))[0]]
                raise RegionError(f"{what} must be finite, got {bad}")
        if self._sphere:
            r, c = _nearest_sphere(self.lat.values.astype(np.float64),
                                   self.lon.values.astype(np.float64),
                                   np.ravel(lat_a), np.ravel(lon_a))
            rows, cols = r.reshape(lat_a.shape), c.reshape(lat_a.shape)
        else:
            rows = _nearest_index(self.lat.values, lat_a, "lat")
            cols = _nearest_index(self.lon.values, lon_a, "lon")
        flat = np.asarray(rows, dtype=np.int64) * self.shape[1] + np.asarray(cols, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self._flat, flat), self._flat.size - 1)
        cells = np.where(self._flat[pos] == flat, pos, -1)
        if np.any(cells < 0):
            bad = np.flatnonzero(np.ravel(cells < 0))[0]
            raise RegionError(
                f"location (lat={np.ravel(lat_a)[bad]:g}, lon={np.ravel(lon_a)[bad]:g}) is on a "
                "masked cell (never observed or excluded by the mask)"
            )
        return int(cells) if cells.ndim == 0 else cells

    def check_cells(self, cells: Any, name: str = "cells") -> np.ndarray:
        """``cells`` as an int64 array after checking every index is a valid cell."""
        arr = np.asarray(cells)
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise RegionError(f"{name} must be integer cell indices, got dtype {arr.dtype}")
        arr = arr.astype(np.int64)
        if arr.size and (arr.min() < 0 or arr.max() >= self.n_cells):
            raise RegionError(f"{name} must be cell indices in [0, {self.n_cells}), got {arr}")
        return arr

    def resolve_cell(self, where: Any, name: str = "start") -> int:
        """A cell index from either an index or a ``(lat, lon)`` pair."""
        if isinstance(where, (tuple, list, np.ndarray)) and np.size(where) == 2:
            try:
                lat, lon = (float(v) for v in np.ravel(np.asarray(where, dtype=object)))
            except (TypeError, ValueError):
                raise RegionError(
                    f"{name} must be a cell index or a (lat, lon) pair of numbers, got {where!r}"
                ) from None
            return int(self.cell_of(lat, lon))
        if isinstance(where, (int, np.integer)):
            return int(self.check_cells(where, name))
        raise RegionError(f"{name} must be a cell index or a (lat, lon) pair, got {where!r}")

    def distance(
        self, a: Any, b: Any, metric: Literal["grid", "km"] = "grid"
    ) -> np.ndarray | float:
        """Distance between cells ``a`` and ``b`` (broadcast).

        ``metric="grid"``: Euclidean distance in grid units between grid positions (the paper's
        cost; columns are in geographic order, so this follows the map, but a global grid's
        seam is not wrapped). ``metric="km"``: great-circle distance between cell centres
        (haversine; wraps across the antimeridian).
        """
        a = self.check_cells(a, "a")
        b = self.check_cells(b, "b")
        if metric == "grid":
            d = self.grid_index[a] - self.grid_index[b]
            out = np.hypot(d[..., 0], d[..., 1]).astype(np.float64)
        elif metric == "km":
            out = _haversine(self.cell_lat[a], self.cell_lon[a], self.cell_lat[b], self.cell_lon[b])
        else:
            raise RegionError(f"metric must be 'grid' or 'km', got {metric!r}")
        return float(out) if np.ndim(out) == 0 else out

    # ------------------------------------------------------------------ subsets
    def in_bbox(self, bbox: BBox) -> np.ndarray:
        """``(L,)`` bool: cells whose centre lies inside ``bbox = (south, west, north, east)``.

        Longitudes compare modulo 360 (either convention); ``west > east`` crosses the
        antimeridian.
        """
        south, west, north, east = check_bbox(bbox)
        lat, lon = self.cell_lat, self.cell_lon
        return (lat >= south) & (lat <= north) & lon_in_box(lon, west, east)

    def subset(self, bbox: BBox) -> Region:
        """The region restricted to ``bbox``: its grid cropped to the box, cells outside masked.

        Columns stay in geographic order and the longitudes follow the rule of
        :func:`geographic_order` with the box's ``west`` (so the result matches
        ``open_data(..., bbox=bbox)`` of the same data).
        """
        south, west, north, east = check_bbox(bbox)
        lat, lon = self.lat.values, self.lon.values.astype(np.float64)
        rows = np.flatnonzero((lat >= south) & (lat <= north))
        cols = np.flatnonzero(lon_in_box(lon, west, east)) if _is_degrees(lon) else \
            np.flatnonzero((lon >= west) & (lon <= east))
        if rows.size == 0 or cols.size == 0 or not self.mask[np.ix_(rows, cols)].any():
            raise RegionError(f"bbox {bbox} contains no valid cell of {self!r}")
        new_lon = lon[cols]
        if _is_degrees(lon):
            order, new_lon = geographic_order(lon[cols], west)
            cols = cols[order]
        lon_dim = self.dims[1]
        lon_da = self.lon.isel({lon_dim: cols}).copy(data=new_lon.astype(self.lon.dtype))
        lon_da = lon_da.assign_coords({lon_dim: lon_da.values})
        return Region(
            lat=self.lat.isel({self.dims[0]: rows}),
            lon=lon_da,
            mask=self.mask[np.ix_(rows, cols)],
            attrs=dict(self.attrs),
            name=self.name,
        )

    def crop(self, rows: slice, cols: slice) -> Region:
        """The region restricted to a window of its grid: rows ``rows`` and columns ``cols``
        (slices of grid positions, step 1), coordinates and attributes kept. Its cells are this
        region's cells inside the window, in the same (row-major) order."""
        if not (isinstance(rows, slice) and isinstance(cols, slice)) or \
                rows.step not in (None, 1) or cols.step not in (None, 1):
            raise RegionError(f"rows and cols must be slices of step 1, got {rows!r}, {cols!r}")
        mask = self.mask[rows, cols]
        if not mask.any():
            raise RegionError(f"the window rows {rows}, cols {cols} holds no valid cell of "
                              f"{self!r}")
        return Region(lat=self.lat.isel({self.dims[0]: rows}),
                      lon=self.lon.isel({self.dims[1]: cols}), mask=mask,
                      attrs=dict(self.attrs), name=self.name)

    # ------------------------------------------------------------------ persistence
    def to_dataset(self) -> xr.Dataset:
        """The region as a Dataset (grid coordinates and an int8 ``region_mask``) for NetCDF."""
        lat_dim, lon_dim = self.dims
        mask = xr.DataArray(
            self.mask.astype(np.int8),
            dims=(lat_dim, lon_dim),
            coords={lat_dim: self.lat, lon_dim: self.lon},
            attrs={"long_name": "valid cells of the region", "flag_values": [0, 1],
                   "flag_meanings": "masked valid"},
        )
        return xr.Dataset({"region_mask": mask})

    @classmethod
    def from_dataset(cls, ds: xr.Dataset, attrs: dict[str, Any] | None = None,
                     name: Hashable | None = None) -> Region:
        """Inverse of :meth:`to_dataset`."""
        if "region_mask" not in ds:
            raise DataError("dataset has no 'region_mask' variable: not saved by lrm-cvx")
        mask = ds["region_mask"]
        lat_dim, lon_dim = mask.dims
        return cls(
            lat=mask[lat_dim].reset_coords(drop=True).astype(np.float64),
            lon=mask[lon_dim].reset_coords(drop=True).astype(np.float64),
            mask=mask.values.astype(bool),
            attrs=dict(attrs or {}),
            name=name,
        )


def check_bbox(bbox: Any, error: type[Exception] = RegionError) -> BBox:
    """``bbox`` as four finite floats ``(south, west, north, east)``; else ``error`` naming a bound.

    Latitudes must lie in [-90, 90] with ``south <= north``; longitudes may use either the
    -180..180 or the 0..360 convention, and ``west > east`` means the box crosses the
    antimeridian (e.g. ``(-10, 170, 10, -170)``).
    """
    try:
        south, west, north, east = (float(v) for v in bbox)
    except (TypeError, ValueError):
        raise error(
            f"bbox must be four numbers (south, west, north, east) in degrees, got {bbox!r}"
        ) from None
    for label, v in (("south", south), ("west", west), ("north", north), ("east", east)):
        if not np.isfinite(v):
            raise error(f"bbox {label}={v:g} must be finite (bbox = {bbox!r})")
    for label, v in (("south", south), ("north", north)):
        if not -90 <= v <= 90:
            raise error(f"bbox {label}={v:g} must be a latitude in [-90, 90] (bbox = {bbox!r})")
    if south > north:
        raise error(
            f"bbox south={south:g} is north of north={north:g}: the order is "
            f"(south, west, north, east); did you mean ({north:g}, {west:g}, {south:g}, {east:g})?"
        )
    return south, west, north, east


def lon_in_box(lon: Any, west: float, east: float) -> np.ndarray:
    """Boolean mask of longitudes inside ``[west, east]`` going east, in any convention.

    Compares modulo 360, so a box given in -180..180 selects data in 0..360 and vice versa;
    ``west > east`` crosses the antimeridian; a box 360 degrees wide or more keeps everything.
    """
    lon = np.asarray(lon, dtype=np.float64)
    width = east - west if west <= east else east - west + 360.0
    if width >= 360.0:
        return np.ones(lon.shape, dtype=bool)
    return np.mod(lon - west, 360.0) <= width + 1e-9


def _geographic(da: xr.DataArray, lat_dim: Hashable, lon: np.ndarray) -> bool:
    """True when ``da``'s latitudes are degrees north, so they must lie in [-90, 90]: its
    ``lat_dim`` coordinate says so in its ``units`` (``degrees_north``, CF), or it is not a
    bare index ``0, 1, 2, ...`` (a pixel grid) and the longitudes look like degrees
    (:func:`_is_degrees`)."""
    if lat_dim not in da.coords:
        return False
    units = str(da[lat_dim].attrs.get("units", "")).lower().replace(" ", "_")
    if units in ("degrees_north", "degree_north", "degrees_n", "degree_n", "degreesn",
                 "degreen"):
        return True
    lat = np.asarray(da[lat_dim].values, dtype=np.float64)
    index = lat.size > 0 and np.array_equal(lat, np.arange(lat.size, dtype=np.float64))
    return not index and _is_degrees(np.asarray(lon, dtype=np.float64))


def _is_degrees(lon: np.ndarray) -> bool:
    """True when a longitude axis looks like degrees east (the periodic rules apply).

    Values within -360..720 spanning at most 360 degrees; anything else (an index axis of a
    grid without coordinates, metres) is a plain axis: no wrap, no great circles.
    """
    return bool(lon.size and np.all(np.isfinite(lon)) and lon.min() >= -360.0
                and lon.max() <= 720.0 and lon.max() - lon.min() <= 360.0 + 1e-9)


def _first_bad_step(values: np.ndarray) -> int | None:
    """Index ``i`` where ``values`` stops being strictly monotonic (``values[i], values[i+1]``)."""
    if values.size < 2:
        return None
    d = np.diff(values)
    sign = 1.0 if d[0] > 0 else -1.0
    bad = np.flatnonzero(~(d * sign > 0))
    return int(bad[0]) if bad.size else None


def check_coords(lat: Any, lon: Any, where: str = "data",
                 error: type[Exception] = DataError, *, geographic: bool = False) -> None:
    """Check grid axes: finite, ``lat`` strictly monotonic, no duplicated ``lon`` (modulo 360)
    and, with ``geographic`` (``lat`` given in degrees north), every latitude in [-90, 90].

    Raises ``error`` naming the coordinate, the position and the value.
    """
    for name, values in (("lat", lat), ("lon", lon)):
        values = np.asarray(values, dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise error(f"{where}: coordinate {name} has a non-finite value ({values[bad[0]]}) "
                        f"at position {bad[0]}")
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    beyond = np.flatnonzero(np.abs(lat) > 90.0) if geographic else np.zeros(0, dtype=np.int64)
    if beyond.size:
        i = int(beyond[0])
        raise error(f"{where}: coordinate lat is {lat[i]:g} at position {i}, beyond a pole; "
                    "latitudes must lie in [-90, 90] degrees north (are lat and lon swapped?)")
    i = _first_bad_step(lat)
    if i is not None:
        kind = "duplicated" if lat[i] == lat[i + 1] else "not monotonic"
        raise error(f"{where}: coordinate lat is {kind} at positions {i}, {i + 1} "
                    f"({lat[i]:g}, {lat[i + 1]:g}); expected strictly increasing or decreasing "
                    "values (sort with da.sortby('lat'))")
    key = np.mod(lon, 360.0) if _is_degrees(lon) else lon
    order = np.argsort(key, kind="stable")
    dup = np.flatnonzero(np.diff(key[order]) == 0)
    if dup.size:
        a, b = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
        raise error(f"{where}: coordinate lon is duplicated at positions {a}, {b} "
                    f"({lon[a]:g} and {lon[b]:g} are the same meridian)")


def geographic_order(lon: Any, west: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Column order and longitudes that put a longitude axis in geographic order.

    Returns ``(order, new_lon)``: ``lon[order]`` runs eastward and is contiguous (the widest
    gap between neighbouring meridians is the one left outside, at the edges), and ``new_lon``
    is strictly increasing: the same meridians, unwrapped by multiples of 360. Rule for the
    values: with ``west`` (a bbox's west edge) the first lies in ``[west, west + 360)``, i.e.
    the box's own convention; otherwise an axis already in geographic order keeps its values,
    and a reordered one is put in -180..180 when it fits, else 0..360. Axes that are not
    degrees (values outside -360..720) are only required to be strictly increasing.
    """
    lon = np.asarray(lon, dtype=np.float64)
    n = lon.size
    if n == 0:
        return np.arange(0), lon.copy()
    if not _is_degrees(lon):
        return np.arange(n), lon.copy()
    key = np.mod(lon, 360.0)
    s_order = np.argsort(key, kind="stable")
    sk = key[s_order]
    gaps = np.diff(np.append(sk, sk[0] + 360.0))  # gaps[i]: from sk[i] east to the next
    span = lon[-1] - lon[0]
    steps = np.diff(lon)
    keep = bool(np.all(steps > 0) and span < 360.0
                and (n == 1 or steps.max() <= 360.0 - span + 1e-9))
    if keep:
        order = np.arange(n)
    else:
        widest = np.flatnonzero(gaps >= gaps.max() - 1e-9)
        starts = (widest + 1) % n
        start = starts[np.argmin(lon[s_order[starts]])]  # ties: the lowest original value first
        order = s_order[np.roll(np.arange(n), -start)]
    lo = lon[order]
    new = lo[0] + np.concatenate([[0.0], np.cumsum(np.mod(np.diff(lo), 360.0))])
    if west is not None:
        new -= 360.0 * np.floor((new[0] - west + 1e-9) / 360.0)  # first in [west, west+360)
    elif not keep:
        new += -360.0 * np.floor((new[0] + 180.0) / 360.0)  # first in [-180, 180)
        if new[-1] > 180.0:
            new += -360.0 * np.floor(new[0] / 360.0)  # first in [0, 360)
            if new[-1] > 360.0:
                new += -360.0 * np.floor((new[0] + 180.0) / 360.0)
    return order, new


def to_geographic_order(da: xr.DataArray, bbox: Any = None,
                        error: type[Exception] = DataError) -> xr.DataArray:
    """``da`` (dims ``(..., lat, lon)``) cropped to ``bbox`` with columns in geographic order.

    Checks the grid axes (:func:`check_coords`), keeps the rows and columns whose centre lies in
    ``bbox = (south, west, north, east)`` (longitudes modulo 360; ``west > east`` crosses the
    antimeridian) and reorders / relabels the columns by :func:`geographic_order`: eastward,
    contiguous, strictly increasing longitudes (a box 170..-170 on -180..180 data gives
    170..190; -10..10 on 0..360 data gives -10..10). Coordinate attributes are kept.
    """
    lat_dim, lon_dim = spatial_dims(da)
    name = da.name if da.name is not None else "data"
    lat = _grid_coord(da, lat_dim)
    lon = _grid_coord(da, lon_dim)
    check_coords(lat, lon, f"variable {name!r}", error, geographic=_geographic(da, lat_dim, lon))
    rows = np.arange(lat.size)
    cols = np.arange(lon.size)
    west = None
    if bbox is not None:
        south, west, north, east = check_bbox(bbox, error)
        rows = np.flatnonzero((lat >= south) & (lat <= north))
        inside = lon_in_box(lon, west, east) if _is_degrees(lon) else (lon >= west) & (lon <= east)
        cols = np.flatnonzero(inside)
        if rows.size == 0 or cols.size == 0:
            raise error(
                f"bbox {tuple(bbox)} holds no grid cell of {name!r} (lat {lat.min():g}.."
                f"{lat.max():g}, lon {lon.min():g}..{lon.max():g})"
            )
    new_lon = lon[cols]
    if lon_dim in da.coords and _is_degrees(lon):
        order, new_lon = geographic_order(lon[cols], west)
        cols = cols[order]
    if rows.size < lat.size:
        da = da.isel({lat_dim: rows})
    if cols.size < lon.size or not np.array_equal(cols, np.arange(lon.size)):
        da = da.isel({lon_dim: cols})
    if lon_dim in da.coords and not np.array_equal(np.asarray(da[lon_dim].values, np.float64),
                                                   new_lon):
        attrs = dict(da[lon_dim].attrs)
        da = da.assign_coords({lon_dim: (lon_dim, new_lon.astype(da[lon_dim].dtype), attrs)})
    return da


def _haversine(lat1: np.ndarray, lon1: np.ndarray, lat2: np.ndarray,
               lon2: np.ndarray) -> np.ndarray:
    """Great-circle distance in km between points given in degrees (broadcast)."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dlon = np.radians(lon2 - lon1)
    h = np.sin((p2 - p1) / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dlon / 2) ** 2
    return 2 * EARTH_RADIUS_KM * np.arcsin(np.sqrt(np.clip(h, 0, 1)))


def _bracket(axis: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the two entries of a strictly monotonic ``axis`` around each point."""
    n = axis.size
    if n > 1 and axis[1] < axis[0]:
        pos = np.searchsorted(axis[::-1], points)
        lo = np.clip(pos - 1, 0, n - 1)
        hi = np.clip(pos, 0, n - 1)
        return n - 1 - lo, n - 1 - hi
    pos = np.searchsorted(axis, points)
    return np.clip(pos - 1, 0, n - 1), np.clip(pos, 0, n - 1)


def _half_step(axis: np.ndarray) -> float:
    return 0.5 * (float(np.abs(np.diff(axis)).max()) if axis.size > 1 else 0.5)


def _nearest_sphere(glat: np.ndarray, glon: np.ndarray, lat: np.ndarray,
                    lon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the grid position nearest (great circle) to each point.

    ``glon`` is strictly increasing degrees spanning < 360; queries wrap modulo 360. Candidates
    are the two columns around the point's longitude and, for each, the rows around the point's
    latitude and around the foot of the perpendicular from the point to that column's meridian
    (distance along a meridian is unimodal about that foot); ties go to the lowest flat index.
    Raises RegionError for a point more than half a grid spacing outside the grid.
    """
    hlat, hlon = _half_step(glat), _half_step(glon)
    lo, hi = glat.min() - hlat, glat.max() + hlat
    outside = (lat < lo) | (lat > hi) | (np.abs(lat) > 90)
    if np.any(outside):
        k = np.flatnonzero(outside)[0]
        raise RegionError(f"location (lat={lat[k]:g}, lon={lon[k]:g}) is outside the grid "
                          f"(lat {lo:g} .. {hi:g})")
    nx = glon.size
    q = glon[0] + np.mod(lon - glon[0], 360.0)  # in [glon0, glon0 + 360)
    pos = np.searchsorted(glon, q, side="right")  # glon[pos-1] <= q
    left = np.clip(pos - 1, 0, nx - 1)
    right = np.where(pos < nx, pos, 0)
    d_left = q - glon[left]
    d_right = np.where(pos < nx, glon[np.minimum(pos, nx - 1)] - q, glon[0] + 360.0 - q)
    if np.any(np.minimum(d_left, d_right) > hlon + 1e-9):
        k = np.flatnonzero(np.minimum(d_left, d_right) > hlon + 1e-9)[0]
        raise RegionError(
            f"location (lat={lat[k]:g}, lon={lon[k]:g}) is outside the grid (lon "
            f"{glon[0] - hlon:g} .. {glon[-1] + hlon:g}, modulo 360)")
    phi = np.radians(lat)
    cand_r, cand_c = [], []
    for col, dl in ((left, d_left), (right, d_right)):
        foot = np.degrees(np.arctan2(np.sin(phi), np.cos(phi) * np.cos(np.radians(dl))))
        foot = np.clip(foot, -90.0, 90.0)
        for centre in (lat, foot):
            for row in _bracket(glat, centre):
                cand_r.append(row)
                cand_c.append(col)
    rows = np.stack(cand_r, axis=-1)
    cols = np.stack(cand_c, axis=-1)
    dist = _haversine(lat[:, None], q[:, None], glat[rows], glon[cols])
    flat = rows * nx + cols
    best = dist.min(axis=1, keepdims=True)
    pick = np.where(dist <= best, flat, np.iinfo(np.int64).max).min(axis=1)
    return np.divmod(pick, nx)


def _nearest_index(grid: np.ndarray, points: np.ndarray, what: str) -> np.ndarray:
    """Index of the nearest value of a monotonic 1-D ``grid`` for each point, checking bounds."""
    if not np.all(np.isfinite(points)):
        raise RegionError(f"{what} must be finite, got {points}")
    idx = np.abs(points[..., None] - grid).argmin(axis=-1) if grid.size < 4096 else None
    if idx is None:  # large grids: binary search on the sorted grid
        order = np.argsort(grid, kind="stable")
        sg = grid[order]
        pos = np.clip(np.searchsorted(sg, points), 1, sg.size - 1)
        left = sg[pos - 1]
        right = sg[pos]
        pos = np.where(np.abs(points - left) <= np.abs(right - points), pos - 1, pos)
        idx = order[pos]
    half = 0.5 * (np.abs(np.diff(grid)).max() if grid.size > 1 else 0.5)
    lo, hi = grid.min() - half, grid.max() + half
    outside = (points < lo) | (points > hi)
    if np.any(outside):
        bad = np.ravel(points)[np.flatnonzero(np.ravel(outside))[0]]
        raise RegionError(f"{what}={bad:g} is outside the grid ({lo:g} .. {hi:g})")
    return idx


def check_region(region: Any, name: str = "region") -> Any:
    """``region`` if it is a :class:`~lrm_cvx.region.Region`, else a :class:`PlanningError`
    naming it (a model fitted on a plain array has no region and cannot plan)."""
    if isinstance(region, Region):
        return region
    from .errors import PlanningError

    raise PlanningError(
        f"{name} must be a lrm_cvx.Region (the grid of the model's cells), got "
        f"{type(region).__name__}: a model fitted on a plain array has no region; fit it on a "
        "(time, lat, lon) DataArray or pass region=Region.from_dataarray(data)"
    )
