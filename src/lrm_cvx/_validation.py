"""Small shared checks used at the edges of every module: seeds, factor matrices, atomic writes."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .errors import DataError, ModelError

__all__ = ["as_generator", "as_factor_matrix", "atomic_output", "atomic_outputs",
           "check_positive", "guard_outputs", "read_netcdf", "same_file"]


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
    value: Any, name: str, *, strict: bool = False, error: type[Exception] = DataError,
    numbers_only: bool = False,
) -> float:
    """``value`` as a finite float, >= 0 (or > 0 when ``strict``), else ``error`` naming it.

    ``numbers_only``: a string, bytes or a bool is refused, not converted (budgets, stop
    costs: ``"5"`` or ``True`` is a caller's mistake, not a number)."""
    if numbers_only and isinstance(value, (str, bytes, bool, np.bool_)):
        raise error(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (strict and v == 0):
        raise error(f"{name} must be {'> 0' if strict else '>= 0'} and finite, got {value!r}")
    return v


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _temp_beside(path: Path) -> Path:
    """An empty temporary file in ``path``'s folder (same file system, so the rename is atomic),
    with the permissions a plain ``open(path, "w")`` would give (``mkstemp`` makes it 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
    except (AttributeError, OSError):  # pragma: no cover - platforms without fchmod
        pass
    os.close(fd)
    return Path(tmp)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it onto ``path`` atomically.

    A failure leaves ``path`` untouched and removes the temporary file. With
    ``overwrite=False`` an existing ``path`` is an error.
    """
    with atomic_outputs([path], overwrite=overwrite) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_outputs(
    paths: Sequence[str | os.PathLike], *, overwrite: bool = True
) -> Iterator[list[Path]]:
    """All-or-nothing write of several files: yield one temporary path beside each of ``paths``.

    When the block succeeds every temporary file is renamed onto its target (``os.replace``,
    atomic per file); when it raises, no target is touched and every temporary file is removed,
    so a failure while writing the third output leaves the first two as they were. With
    ``overwrite=False`` an existing target is a ``FileExistsError`` before anything is written.
    """
    targets = [Path(p) for p in paths]
    for path in targets:
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder; give a file name")
        if not overwrite and path.exists():
            raise FileExistsError(f"refusing to overwrite existing file {path}")
    tmps: list[Path] = []
    created: list[Path] = []  # folders made here, removed again (when empty) on failure
    done = False
    try:
        for path in targets:
            missing = [d for d in (path.parent, *path.parent.parents) if not d.exists()]
            path.parent.mkdir(parents=True, exist_ok=True)
            created += missing
            tmps.append(_temp_beside(path))
        yield list(tmps)
        for tmp, path in zip(tmps, targets, strict=True):
            os.replace(tmp, path)
        done = True
    finally:
        for tmp in tmps:
            if tmp.exists():
                tmp.unlink()
        if not done:
            for folder in created:  # deepest first
                with contextlib.suppress(OSError):
                    folder.rmdir()


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when ``a`` and ``b`` name the same file: equal resolved paths (symlinks, ``..``),
    or ``os.path.samefile`` (hard links) when both exist."""
    pa, pb = Path(a), Path(b)
    if pa.resolve() == pb.resolve():
        return True
    try:
        return os.path.samefile(pa, pb)
    except OSError:
        return False


def guard_outputs(
    outputs: Sequence[str | os.PathLike],
    inputs: Sequence[str | os.PathLike] = (),
    *,
    overwrite: bool = False,
    flag: str = "--overwrite",
) -> list[Path]:
    """Check, before any work, that writing ``outputs`` loses nothing; return them as Paths.

    Refuses (``FileExistsError``) an output that is one of ``inputs`` (compared with
    :func:`same_file`, so globs and folders must be expanded by the caller) whatever
    ``overwrite`` says, an existing output unless ``overwrite`` (the message names ``flag``),
    and (``IsADirectoryError``) an output that is an existing folder.
    """
    outs = [Path(p) for p in outputs]
    for out in outs:
        for inp in inputs:
            if same_file(out, inp):
                raise FileExistsError(
                    f"refusing to overwrite the input file {inp} with the output {out}; choose "
                    "another output (--overwrite never replaces an input)")
        if out.is_dir():
            raise IsADirectoryError(f"output {out} is an existing folder; give a file name")
        if out.exists() and not overwrite:
            raise FileExistsError(f"output {out} already exists; pass {flag} to replace it")
    return outs


def read_netcdf(path: str | os.PathLike, what: str, writer: str) -> xr.Dataset:
    """Load a whole NetCDF file written by ``writer`` (e.g. ``"GLRM.save"``) into memory.

    A folder, an empty, missing, truncated or corrupt file is a :class:`DataError` naming
    ``what`` (e.g. ``"model file"``) and the path; the file is only read, never changed.
    """
    name = repr(os.fspath(path))
    if os.path.isdir(path):
        raise DataError(f"{what} {name} is a folder, expected a file written by {writer}")
    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise DataError(f"{what} {name} is empty (0 bytes)")
    try:
        with xr.open_dataset(path) as f:
            return f.load()
    except FileNotFoundError:
        raise DataError(f"{what} {name} does not exist") from None
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{what} {name} is not a readable NetCDF file (corrupt or truncated?): "
                        f"{first}") from exc
