"""Loaders of gridded snapshots and writers of the real file formats.

- :func:`open_data` (``io/generic.py``): any of the sources below, ``sample:NAME`` or a NetCDF
  file with a ``(time, lat, lon)`` variable, chosen from the paths.
- :func:`open_ndvi_cdr` (``io/ndvi.py``): NOAA Climate Data Record NDVI daily NetCDF files
  (AVHRR v5 and VIIRS v1) -> DataArray ``(time, lat, lon)`` with QA-bit masking.
- :func:`open_image_stack` (``io/imagery.py``): RGB snapshots (e.g. NASA Worldview) -> hue in
  degrees with cloud, edge and no-data masks.
- :func:`write_ndvi_cdr`, :func:`write_image_stack`: writers of the two real formats, beside
  their readers.
- :func:`synthetic_field` (``io/samples.py``): a planted low-rank field for tests, benchmarks
  and notebooks; :func:`cloud_gaps`: its moving clouds laid over any record.

Submodules are imported on first use, so ``import lrm_cvx.io`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "open_data",
    "open_ndvi_cdr",
    "open_image_stack",
    "synthetic_field",
    "cloud_gaps",
    "write_ndvi_cdr",
    "write_image_stack",
    "AVHRR_FLAGS",
    "VIIRS_FLAGS",
    "DEFAULT_MASK_FLAGS",
]

_WHERE = {
    "open_data": "generic",
    "open_ndvi_cdr": "ndvi",
    "AVHRR_FLAGS": "ndvi",
    "VIIRS_FLAGS": "ndvi",
    "DEFAULT_MASK_FLAGS": "ndvi",
    "open_image_stack": "imagery",
    "synthetic_field": "samples",
    "cloud_gaps": "samples",
    "write_ndvi_cdr": "ndvi",
    "write_image_stack": "imagery",
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        module = importlib.import_module(f"{__name__}.{_WHERE[name]}")
        value = getattr(module, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
