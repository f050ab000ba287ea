"""Loaders of gridded snapshots and writers of the real file formats.

:func:`open_data` (any source), :func:`open_ndvi_cdr` (NOAA NDVI CDR), :func:`open_image_stack`
(RGB snapshots -> hue), their writers, and :func:`synthetic_field` / :func:`cloud_gaps` (planted
fields). Submodules are imported on first use, so ``import lrm_cvx.io`` stays cheap.
"""

from __future__ import annotations

from ..registry import lazy_attributes

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
    "open_data": ".generic",
    "open_ndvi_cdr": ".ndvi",
    "AVHRR_FLAGS": ".ndvi",
    "VIIRS_FLAGS": ".ndvi",
    "DEFAULT_MASK_FLAGS": ".ndvi",
    "open_image_stack": ".imagery",
    "synthetic_field": ".samples",
    "cloud_gaps": ".samples",
    "write_ndvi_cdr": ".ndvi",
    "write_image_stack": ".imagery",
}
"""Public name -> its module, imported on first use."""

__getattr__, __dir__ = lazy_attributes(__name__, _WHERE)
