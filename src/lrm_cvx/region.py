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
from typing import Any, Literal

import numpy as np
import xarray as xr

from .errors import DataError, RegionError

__all__ = ["Region", "BBox", "EARTH_RADIUS_KM", "spatial_dims"]

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

        Valid cells are those observed (finite) at least once, or ``mask`` (a ``(lat, lon)``
        boolean array or DataArray, True = valid) when given.
        """
        if not isinstance(da, xr.DataArray):
            raise DataError(f"da must be an xarray.DataArray, got {type(da).__name__}")
        if da.ndim not in (2, 3):
            raise DataError(f"da must have dims (time, lat, lon) or (lat, lon), got {da.dims}")
        lat_dim, lon_dim = spatial_dims(da)
        if mask is None:
            observed = np.isfinite(da)
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
        return np.ascontiguousarray(flat[..., self._flat], dtype=np.float32)

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

        Raises :class:`RegionError` when a point lies outside the grid (by more than half a grid
        spacing) or its nearest grid position is masked.
        """
        lat_a, lon_a = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        rows = _nearest_index(self.lat.values, lat_a, "lat")
        cols = _nearest_index(self.lon.values, lon_a, "lon")
        cells = self.cell_grid[rows, cols]
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
            return int(self.cell_of(float(where[0]), float(where[1])))
        if isinstance(where, (int, np.integer)):
            return int(self.check_cells(where, name))
        raise RegionError(f"{name} must be a cell index or a (lat, lon) pair, got {where!r}")

    def distance(
        self, a: Any, b: Any, metric: Literal["grid", "km"] = "grid"
    ) -> np.ndarray | float:
        """Distance between cells ``a`` and ``b`` (broadcast).

        ``metric="grid"``: Euclidean distance in grid units between grid positions (the paper's
        cost). ``metric="km"``: great-circle distance between cell centres (haversine).
        """
        a = self.check_cells(a, "a")
        b = self.check_cells(b, "b")
        if metric == "grid":
            d = self.grid_index[a] - self.grid_index[b]
            out = np.hypot(d[..., 0], d[..., 1]).astype(np.float64)
        elif metric == "km":
            lat1, lat2 = np.radians(self.cell_lat[a]), np.radians(self.cell_lat[b])
            dlon = np.radians(self.cell_lon[b] - self.cell_lon[a])
            h = np.sin((lat2 - lat1) / 2) ** 2 + np.cos(lat1) * np.cos(lat2) * np.sin(dlon / 2) ** 2
            out = 2 * EARTH_RADIUS_KM * np.arcsin(np.sqrt(np.clip(h, 0, 1)))
        else:
            raise RegionError(f"metric must be 'grid' or 'km', got {metric!r}")
        return float(out) if np.ndim(out) == 0 else out

    # ------------------------------------------------------------------ subsets
    def in_bbox(self, bbox: BBox) -> np.ndarray:
        """``(L,)`` bool: cells whose centre lies inside ``bbox = (south, west, north, east)``.

        ``west > east`` denotes a box crossing the antimeridian.
        """
        south, west, north, east = _check_bbox(bbox)
        lat, lon = self.cell_lat, self.cell_lon
        inside_lat = (lat >= south) & (lat <= north)
        if west <= east:
            inside_lon = (lon >= west) & (lon <= east)
        else:
            inside_lon = (lon >= west) | (lon <= east)
        return inside_lat & inside_lon

    def subset(self, bbox: BBox) -> Region:
        """The region restricted to ``bbox``: its grid cropped to the box, cells outside masked."""
        south, west, north, east = _check_bbox(bbox)
        lat, lon = self.lat.values, self.lon.values
        rows = np.flatnonzero((lat >= south) & (lat <= north))
        if west <= east:
            cols = np.flatnonzero((lon >= west) & (lon <= east))
        else:
            cols = np.flatnonzero((lon >= west) | (lon <= east))
        if rows.size == 0 or cols.size == 0 or not self.mask[np.ix_(rows, cols)].any():
            raise RegionError(f"bbox {bbox} contains no valid cell of {self!r}")
        return Region(
            lat=self.lat.isel({self.dims[0]: rows}),
            lon=self.lon.isel({self.dims[1]: cols}),
            mask=self.mask[np.ix_(rows, cols)],
            attrs=dict(self.attrs),
            name=self.name,
        )

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


def _check_bbox(bbox: Any) -> tuple[float, float, float, float]:
    try:
        south, west, north, east = (float(v) for v in bbox)
    except (TypeError, ValueError):
        raise RegionError(
            f"bbox must be (south, west, north, east) in degrees, got {bbox!r}"
        ) from None
    if not (-90 <= south <= north <= 90):
        raise RegionError(f"bbox must have -90 <= south <= north <= 90, got {bbox!r}")
    return south, west, north, east


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
