"""Small shared checks used at the edges of every module: seeds, factor matrices, atomic writes."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .errors import DataError, ModelError

__all__ = ["as_generator", "as_factor_matrix", "atomic_output", "check_positive"]


def as_generator(random_state: Any) -> np.random.Generator:
    """A NumPy ``Generator`` from ``None``, an int seed, a ``SeedSequence`` or a ``Generator``."""
    if isinstance(random_state, np.random.Generator):
        return random_state
    if isinstance(random_state, np.random.RandomState):
        return np.random.default_rng(random_state.randint(0, 2**63 - 1))
    try:
        return np.random.default_rng(random_state)
    except (TypeError, ValueError) as exc:
        raise ModelError(
            f"random_state must be None, an int or a numpy Generator, got {random_state!r}"
        ) from exc


def as_factor_matrix(Y: Any, region: Any = None, name: str = "Y") -> np.ndarray:
    """The ``(k, L)`` float64 factor matrix from an array or a model's ``Y_`` DataArray.

    Accepts an ndarray ``(k, L)``, a DataArray ``(component, cell)``, or a DataArray
    ``(component, lat, lon)`` (stacked with ``region``). Checks that it is finite and, when a
    region is given, that it has one column per valid cell.
    """
    if isinstance(Y, xr.DataArray):
        if Y.ndim == 3:
            if region is None:
                raise DataError(f"{name} with dims {Y.dims} needs a region to be stacked")
            values = region.stack(Y).astype(np.float64)
        elif Y.ndim == 2:
            values = np.asarray(Y.values, dtype=np.float64)
        else:
            raise DataError(f"{name} must have dims (component, cell), got {Y.dims}")
    else:
        values = np.asarray(Y, dtype=np.float64)
    if values.ndim != 2:
        raise DataError(f"{name} must be a (k, L) matrix, got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise DataError(f"{name} has non-finite entries")
    if region is not None and values.shape[1] != region.n_cells:
        raise DataError(
            f"{name} has {values.shape[1]} columns, the region has {region.n_cells} cells"
        )
    return np.ascontiguousarray(values)


def check_positive(
    value: Any, name: str, *, strict: bool = False, error: type[Exception] = DataError
) -> float:
    """``value`` as a finite float, >= 0 (or > 0 when ``strict``), else ``error`` naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (strict and v == 0):
        raise error(f"{name} must be {'> 0' if strict else '>= 0'} and finite, got {value!r}")
    return v


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it onto ``path`` atomically.

    A failure leaves ``path`` untouched and removes the temporary file. With
    ``overwrite=False`` an existing ``path`` is an error.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(f"refusing to overwrite existing file {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
