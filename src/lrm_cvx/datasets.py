"""Real sample data shipped with the package (see ``data/README.md`` for provenance).

``load_sample(name)`` returns a ``(time, lat, lon)`` float32 DataArray (latitude ascending,
NaN where there is no data, e.g. over land for sea-surface temperature).
"""

from __future__ import annotations

from importlib import resources

import xarray as xr

from .errors import DataError

__all__ = ["SAMPLES", "list_samples", "load_sample"]

SAMPLES: dict[str, str] = {
    "sst": "Sea-surface temperature anomalies (K), NOAA ERSST, November-March means of 50 "
           "winters 1963-2012, 18 x 30 grid (5 degrees) over the tropical and North Pacific; "
           "NaN over land.",
    "hgt500": "500 hPa geopotential height (m), NCEP/NCAR Reanalysis 1, December-February means "
              "of 65 winters 1948-2012, 29 x 49 grid (2.5 degrees) over the North Atlantic and "
              "Europe; fully observed.",
}


def list_samples() -> dict[str, str]:
    """The bundled samples: name -> one-line description."""
    return dict(SAMPLES)


def load_sample(name: str) -> xr.DataArray:
    """Load the bundled sample ``name`` (see :func:`list_samples`) into memory."""
    if name not in SAMPLES:
        raise DataError(f"unknown sample {name!r}; available: {', '.join(sorted(SAMPLES))}")
    ref = resources.files("lrm_cvx") / "data" / f"{name}.nc"
    with resources.as_file(ref) as path:
        if not path.exists():
            raise DataError(f"sample file {path} is missing: reinstall lrm-cvx")
        ds = xr.load_dataset(path, engine="netcdf4")
    da = ds[name]
    for key in ("source", "license", "history", "Conventions"):
        if key in ds.attrs:
            da.attrs.setdefault(key, ds.attrs[key])
    da.attrs["sample"] = name
    return da
