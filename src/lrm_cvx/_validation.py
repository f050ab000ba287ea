"""Small shared checks used at the edges of every module: seeds, factor matrices, atomic writes."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .errors import DataError, ModelError

__all__ = ["as_generator", "as_factor_matrix", "atomic_output", "atomic_outputs",
           "check_flag", "check_input_file", "check_positive", "check_target",
           "check_time_labels", "datetime_ns", "file_lock", "first_line", "guard_outputs",
           "is_symlink_loop", "read_netcdf", "remove_stale_temps", "same_file"]


def as_generator(random_state: Any, name: str = "random_state", *,
                 error: type[Exception] = ModelError) -> np.random.Generator:
    """A NumPy ``Generator`` from ``None``, an int seed, a ``SeedSequence`` or a ``Generator``;
    anything else raises ``error`` naming the argument ``name``."""
    if isinstance(random_state, np.random.Generator):
        return random_state
    if isinstance(random_state, np.random.RandomState):
        return np.random.default_rng(random_state.randint(0, 2**63 - 1))
    try:
        return np.random.default_rng(random_state)
    except (TypeError, ValueError) as exc:
        raise error(
            f"{name} must be None, an int or a numpy Generator, got {random_state!r}"
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


def check_ranks(ranks: Any) -> list[int]:
    """``ranks`` as a non-empty list of distinct integers >= 1 (ModelError naming ``ranks``
    otherwise)."""
    vals = np.atleast_1d(np.asarray(ranks, dtype=object)).ravel()
    ok = vals.size > 0
    for r in vals:  # a handful of ranks
        if (isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer, float))
                or not float(r).is_integer() or r < 1):
            ok = False
    if not ok:
        raise ModelError(f"ranks must be a non-empty sequence of positive integers (>= 1), "
                         f"got {ranks!r}")
    out = [int(r) for r in vals]
    if len(set(out)) != len(out):
        raise ModelError(f"ranks must not repeat, got {out}")
    return out


def check_flag(value: Any, name: str, *, error: type[Exception] = DataError) -> bool:
    """``value`` as a bool when it is one (``True``/``False``, numpy's too), else ``error``
    naming it: ``paper="yes"`` or ``paper=1`` is a caller's mistake, not a switch."""
    if not isinstance(value, (bool, np.bool_)):
        raise error(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_time_labels(times: Any, source: str = "data") -> None:
    """DataError when a time label is missing (NaT, NaN or None): a snapshot without a time
    cannot be ordered, stepped by the dynamics or named in a result."""
    import pandas as pd

    missing = np.flatnonzero(pd.isnull(np.asarray(times)))
    if missing.size:
        raise DataError(f"{source}: time has {missing.size} missing value(s) (NaT) at "
                        f"position(s) {missing[:10].tolist()}; drop those snapshots or fix "
                        "their times")


#: The first and last dates ``datetime64[ns]`` holds (as printed in messages).
NS_RANGE = ("1677-09-21", "2262-04-11")


def datetime_ns(value: Any, name: str = "time", *, label: str | None = None) -> np.datetime64:
    """``value`` (a string, datetime, cftime date or ``pandas.Timestamp``) as
    ``datetime64[ns]``.

    DataError when the date is outside the type's range (``NS_RANGE``) instead of wrapping
    around, naming ``label`` (default ``"{name} {value}"``); ValueError/TypeError as
    ``pandas.Timestamp`` raises them for a text that is no date.
    """
    import pandas as pd

    ts = pd.Timestamp(str(value) if hasattr(value, "calendar") else value)
    if ts is pd.NaT:
        raise ValueError("NaT")
    if ts.tzinfo:
        ts = ts.tz_localize(None)
    if not pd.Timestamp.min <= ts <= pd.Timestamp.max:
        what = label or f"{name} {value}"
        raise DataError(f"{what} is outside the dates a datetime64[ns] time coordinate can "
                        f"hold: {NS_RANGE[0]} to {NS_RANGE[1]}")
    return ts.as_unit("ns").to_datetime64()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _temp_beside(path: Path) -> Path:
    """An empty temporary file ``.NAME.PID.RANDOM.tmp`` in ``path``'s folder (same file system,
    so the rename is atomic), with the permissions a plain ``open(path, "w")`` would give
    (``mkstemp`` makes it 0600). The PID tells a later run whether its writer is still alive."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp",
                               dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
    except (AttributeError, OSError):  # pragma: no cover - platforms without fchmod
        pass
    os.close(fd)
    return Path(tmp)


#: A temporary file without a writer's PID (written before PIDs were recorded) is taken as
#: left by a killed write once it is this old (seconds).
STALE_AFTER = 60.0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. PermissionError: the process exists
        return True
    return True


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Delete the temporary files a killed write of ``path`` left beside it; return them.

    A temporary file ``.NAME.PID.RANDOM.tmp`` is stale when process PID is gone; an older one
    without a PID (``.NAME.RANDOM.tmp``) when it is more than :data:`STALE_AFTER` s old. A
    write in progress in another live process is never touched."""
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    head = f".{path.name}."
    for tmp in path.parent.iterdir():
        name = tmp.name
        if not (name.startswith(head) and name.endswith(".tmp")):
            continue
        pid, dot, _ = name[len(head):-len(".tmp")].partition(".")
        try:
            if dot and pid.isdigit():
                if _pid_alive(int(pid)):
                    continue
            elif time.time() - tmp.lstat().st_mtime < STALE_AFTER:
                continue
            if tmp.is_file():
                tmp.unlink()
                removed.append(tmp)
        except OSError:  # gone already, or not ours to remove
            continue
    return removed


def is_symlink_loop(path: str | os.PathLike) -> bool:
    """True when following ``path``'s symbolic links never ends (a link to itself, or links
    that lead to each other)."""
    try:
        os.stat(path)
    except OSError as exc:
        return exc.errno == errno.ELOOP
    return False


def check_input_file(path: str | os.PathLike, what: str, *,
                     error: type[Exception] = DataError) -> None:
    """``error`` naming ``what`` and ``path`` when ``path`` is a symlink loop or exists but is
    neither a regular file nor a folder (a FIFO, device or socket: reading one may wait
    forever). A missing path or a folder is left to the caller, which says what it expected."""
    name = os.fspath(path)
    if is_symlink_loop(path):
        raise error(f"{what} {name} is a symlink loop (its links lead back to themselves); "
                    "give the real file")
    if os.path.exists(path) and not (os.path.isfile(path) or os.path.isdir(path)):
        raise error(f"{what} {name} is not a regular file (a FIFO, device or socket); give a "
                    "file")


def check_target(path: str | os.PathLike) -> Path:
    """``path`` as a Path, refused (``IsADirectoryError`` / ``FileExistsError``) when it exists
    and is not a regular file: a folder, a device node, a FIFO, a socket or a symlink loop is
    never replaced by an output."""
    path = Path(path)
    if is_symlink_loop(path):
        raise FileExistsError(f"output {path} is a symlink loop (its links lead back to "
                              "themselves); give another file name")
    if path.is_dir():
        raise IsADirectoryError(f"output {path} is an existing folder; give a file name")
    if (path.exists() or path.is_symlink()) and not path.is_file():
        raise FileExistsError(f"output {path} exists and is not a regular file (a device, FIFO, "
                              "socket or broken link); refusing to replace it")
    return path


_SPACE_ERRORS = {errno.ENOSPC: "no space left on device",
                 errno.EFBIG: "file too large (a file-size limit such as 'ulimit -f')",
                 errno.EDQUOT: "disk quota exceeded"}


def _space_error(exc: BaseException, tmp: Path) -> int | None:
    """The errno (ENOSPC, EFBIG, EDQUOT) when a failed write of ``tmp`` ran out of room
    although the error ``exc`` does not say so.

    Libraries such as HDF5 report a full disk as a generic error ("NetCDF: HDF error"); a probe
    (appending 64 KiB to the temporary file) tells the cause."""
    if isinstance(exc, (KeyboardInterrupt, SystemExit)) or not tmp.exists():
        return None
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_APPEND)
    except OSError:
        return None
    try:
        left = memoryview(bytes(65536))
        while left:  # a short write stops at a limit; the next one reports it
            left = left[os.write(fd, left):]
        os.fsync(fd)
    except OSError as probe:
        return probe.errno if probe.errno in _SPACE_ERRORS else None
    finally:
        os.close(fd)
    return None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it onto ``path`` atomically.

    A failure leaves ``path`` untouched and removes the temporary file. With
    ``overwrite=False`` an existing ``path`` is an error. A symbolic link is kept: the file
    it points to is replaced.
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
    ``overwrite=False`` an existing target is a ``FileExistsError`` before anything is written;
    a target that exists and is not a regular file (folder, device, FIFO) is always refused.
    A write that fails for lack of room is an ``OSError`` saying so (ENOSPC, EFBIG, EDQUOT),
    whatever the writing library reported. Temporary files that a killed earlier write left
    beside a target are removed first (:func:`remove_stale_temps`). A target that is a
    symbolic link stays one: the file it points to is written (beside that file, so the
    rename stays atomic).
    """
    targets = [check_target(p) for p in paths]
    targets = [Path(os.path.realpath(p)) if p.is_symlink() else p for p in targets]
    for path in targets:
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
            remove_stale_temps(path)
            tmps.append(_temp_beside(path))
        try:
            yield list(tmps)
        except BaseException as exc:
            said = any(isinstance(e, OSError) and e.errno in _SPACE_ERRORS
                       for e in (exc, exc.__cause__, exc.__context__))
            for tmp, path in zip(tmps, targets, strict=False) if not said else ():
                code = _space_error(exc, tmp)
                if code is not None:
                    raise OSError(code, f"writing {path} failed: {_SPACE_ERRORS[code]}; the "
                                  "previous file, if any, is intact", str(path)) from exc
            raise
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


@contextlib.contextmanager
def file_lock(path: str | os.PathLike, *, timeout: float = 60.0, what: str = "file"
              ) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` for the block: a read-modify-write of a file that
    several processes update (a monitor state) never loses an update.

    The lock is an advisory ``flock`` on ``.NAME.lock`` beside ``path`` (``path`` itself is
    replaced by atomic renames, so its inode cannot carry the lock), removed again on release;
    a lock taken on a lock file that was removed meanwhile is dropped and taken again, so two
    holders never coexist. A process that cannot get it within ``timeout`` seconds raises
    ``TimeoutError`` naming ``what``. The kernel releases the lock when its process dies, so a
    killed writer never leaves it held. The lock belongs to the real file: a symbolic link to
    ``path`` and ``path`` itself take the same lock.
    """
    import fcntl

    path = Path(path)
    real = Path(os.path.realpath(path))
    lock = real.parent / f".{real.name}.lock"
    deadline = time.monotonic() + float(timeout)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() >= deadline:
                raise TimeoutError(
                    f"{what} {path} is being updated by another process (waited {timeout:g} s);"
                    " nothing was changed, run the command again") from None
            time.sleep(0.05)
            continue
        try:
            current = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)  # the holder before us removed this lock file: take the new one
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)  # releases the flock


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when ``a`` and ``b`` name the same file: equal resolved paths (symlinks, ``..``),
    or ``os.path.samefile`` (hard links) when both exist."""
    pa, pb = Path(a), Path(b)
    if os.path.realpath(pa) == os.path.realpath(pb):  # never raises on a symlink loop
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
    :func:`same_file`, so globs and folders must be expanded by the caller) or lies in an input
    folder (every file there is read as input), whatever
    ``overwrite`` says, an existing output unless ``overwrite`` (the message names ``flag``),
    and an output that exists but is not a regular file (:func:`check_target`). An input or
    output that is a symlink loop is refused naming it.
    """
    outs = [Path(p) for p in outputs]
    for inp in inputs:
        check_input_file(inp, "input")
    for out in outs:
        check_target(out)
    folders = [Path(p) for p in inputs if Path(p).is_dir()]
    for out in outs:
        for inp in inputs:
            if same_file(out, inp):
                raise FileExistsError(
                    f"refusing to overwrite the input file {inp} with the output {out}; choose "
                    "another output (--overwrite never replaces an input)")
        for folder in folders:
            if out.parent.is_dir() and same_file(out.parent, folder):
                raise FileExistsError(
                    f"refusing to write the output {out} into the input folder {folder}: every "
                    "file there is read as input; choose another folder")
        check_target(out)
        if out.exists() and not overwrite:
            raise FileExistsError(f"output {out} already exists; pass {flag} to replace it")
    return outs


def array_digest(*arrays: Any) -> str:
    """A digest of the arrays' dtypes, shapes and bytes: the key of an in-memory cache of work
    that depends only on those arrays' contents."""
    h = hashlib.blake2b(digest_size=20)
    for arr in arrays:
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        if a.size:  # an empty array has no bytes (and memoryview cannot cast it)
            h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def first_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message, or its class name when the message is blank."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _refuse_outside_data(path: str | os.PathLike, what: str, name: str) -> None:
    """DataError when the HDF5 file ``path`` would make a reader fetch bytes from other files:
    a dataset with external storage (raw data in another file), a virtual dataset (mapped
    from other files) or an external link. A NetCDF-3 file (not HDF5) has none of these."""
    import h5py

    if not h5py.is_hdf5(path):
        return
    why = "is untrusted input and must hold all its data itself"
    try:
        with h5py.File(path, "r") as f:
            links: list[str] = []
            f.visititems_links(lambda key, link: links.append(
                f"an external link {key!r} to {link.filename}:{link.path}")
                if isinstance(link, h5py.ExternalLink) else None)
            if links:  # before any object is visited: an external link is never followed
                raise DataError(f"{what} {name} is refused: it has {links[0]} (a {what} "
                                f"{why})")

            def check(key: str, obj: Any) -> None:
                if not isinstance(obj, h5py.Dataset):
                    return
                if obj.is_virtual:
                    sources = sorted({m.file_name for m in obj.virtual_sources()})
                    raise DataError(f"{what} {name} is refused: variable {key!r} is a virtual "
                                    f"dataset mapped from {', '.join(sources)} (a {what} {why})")
                if obj.external:
                    files = sorted({os.fsdecode(e[0]) for e in obj.external})
                    raise DataError(f"{what} {name} is refused: variable {key!r} uses external "
                                    f"storage in {', '.join(files)} (a {what} {why})")

            f.visititems(check)
    except DataError:
        raise
    except Exception as exc:
        raise DataError(f"{what} {name} is not a readable NetCDF file (corrupt or truncated?): "
                        f"{first_line(exc)}") from exc


def read_netcdf(path: str | os.PathLike, what: str, writer: str) -> xr.Dataset:
    """Load a whole NetCDF file written by ``writer`` (e.g. ``"GLRM.save"``) into memory.

    A folder, an empty, missing, truncated or corrupt file is a :class:`DataError` naming
    ``what`` (e.g. ``"model file"``) and the path; so is a symlink loop, a FIFO, device or
    socket (never opened: reading one may wait forever) and an HDF5 file that would pull data
    from other files (external storage, virtual datasets, external links): the file is
    untrusted input. The file is only read, never changed.
    """
    name = repr(os.fspath(path))
    check_input_file(path, what)
    if os.path.isdir(path):
        raise DataError(f"{what} {name} is a folder, expected a file written by {writer}")
    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise DataError(f"{what} {name} is empty (0 bytes)")
    if os.path.isfile(path):
        _refuse_outside_data(path, what, name)
    try:
        with xr.open_dataset(path) as f:
            return f.load()
    except FileNotFoundError:
        raise DataError(f"{what} {name} does not exist") from None
    except Exception as exc:
        raise DataError(f"{what} {name} is not a readable NetCDF file (corrupt or truncated?): "
                        f"{first_line(exc)}") from exc
