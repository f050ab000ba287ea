"""Reading NetCDF files from HTTP(S) and S3 servers without downloading them whole.

A URL is opened as a random-access file by fsspec and read lazily, so only the chunks covering
the bbox travel; an optional block cache keeps a sparse local copy. URL globs, retries,
timeouts (``$LRM_CVX_TIMEOUT``, ``$LRM_CVX_READ_TIMEOUT``) and the cache are described in
docs/data-formats.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import xarray as xr

from ..errors import DataError

__all__ = [
    "is_url",
    "url_name",
    "expand_urls",
    "remote_filesystem",
    "read_remote",
    "timeouts",
    "BLOCK_SIZE",
    "RETRIES",
    "BACKOFF",
    "TIMEOUT",
    "READ_TIMEOUT",
]

T = TypeVar("T")

BLOCK_SIZE = 128 * 1024
"""Bytes per ranged request (and per cached block). One 600 x 600 int16 HDF5 chunk compresses
to ~0.1-0.5 MB, so a read over-fetches at most one block past each chunk it needs."""
RETRIES = 3
"""Attempts after the first on a transient failure (connection reset or dropped, 5xx, 429)."""
BACKOFF = 0.5
"""Seconds before the first retry; doubled before each next one (0.5, 1, 2 s by default)."""
TIMEOUT = 60.0
"""HTTP: the longest one request may take, and the longest a read keeps retrying after timed
out tries (seconds; ``$LRM_CVX_TIMEOUT`` overrides it). A server that trickles a byte now and
then is abandoned after it."""
READ_TIMEOUT = 30.0
"""HTTP: seconds to connect, and seconds of silence while reading, before a try is abandoned
(a transient failure, so retried within :data:`TIMEOUT`); ``$LRM_CVX_READ_TIMEOUT`` overrides
it."""

_URL = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://")
_CACHE_ENV = "LRM_CVX_CACHE"
_TIMEOUT_ENV = {"total": "LRM_CVX_TIMEOUT", "read": "LRM_CVX_READ_TIMEOUT"}
_AWS_CREDENTIAL_ENV = ("AWS_ACCESS_KEY_ID", "AWS_PROFILE", "AWS_WEB_IDENTITY_TOKEN_FILE",
                       "AWS_CONTAINER_CREDENTIALS_RELATIVE_URI",
                       "AWS_CONTAINER_CREDENTIALS_FULL_URI")


def is_url(item: Any) -> bool:
    """True for a ``scheme://...`` string other than ``file://`` (read as a local path)."""
    if not isinstance(item, str):
        return False
    m = _URL.match(item)
    return m is not None and m["scheme"].lower() != "file"


def url_name(url: str) -> str:
    """The file name of ``url`` (last path segment, without query or fragment)."""
    return url.split("?", 1)[0].split("#", 1)[0].rstrip("/").rsplit("/", 1)[-1]


def _protocol(url: str) -> str:
    return _URL.match(url)["scheme"].lower()


def cache_folder(cache: Any) -> str | None:
    """The cache folder to use: ``cache`` (``~`` expanded), else ``$LRM_CVX_CACHE``, else None.

    ``cache=False`` turns the cache off even when the environment variable is set.
    """
    if cache is False:
        return None
    if cache is None or cache is True:
        cache = os.environ.get(_CACHE_ENV) or ("~/.cache/lrm-cvx" if cache is True else None)
    if cache is None:
        return None
    if not isinstance(cache, (str, os.PathLike)):
        raise DataError(f"cache must be a folder path, True, False or None; got {cache!r}")
    return str(Path(cache).expanduser())


def timeouts() -> tuple[float, float]:
    """``(total, read)``: :data:`TIMEOUT` and :data:`READ_TIMEOUT`, or the seconds set in
    ``$LRM_CVX_TIMEOUT`` and ``$LRM_CVX_READ_TIMEOUT`` (DataError naming a variable that is not
    a number > 0)."""
    out = []
    for key, default in (("total", TIMEOUT), ("read", READ_TIMEOUT)):
        text = os.environ.get(_TIMEOUT_ENV[key], "").strip()
        if not text:
            out.append(float(default))
            continue
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not (value > 0 and value != float("inf")):
            raise DataError(f"{_TIMEOUT_ENV[key]} must be a number of seconds > 0, got "
                            f"{text!r}")
        out.append(value)
    return out[0], out[1]


def remote_filesystem(url: str, storage_options: dict[str, Any] | None = None,
                      cache: Any = None):
    """The fsspec filesystem that reads ``url``, wrapped in a block cache when ``cache`` is set.

    ``storage_options`` go to the filesystem (s3fs: ``anon``, ``key``, ``secret``,
    ``endpoint_url``, ``client_kwargs``...; HTTP: ``headers``, ``client_kwargs``...). S3 is
    anonymous unless credentials are given there or in the usual environment (``AWS_*``
    variables, a profile); ``AWS_ENDPOINT_URL`` points it at another S3-compatible server.
    """
    import fsspec

    protocol = _protocol(url)
    if storage_options is not None and not isinstance(storage_options, dict):
        raise DataError(f"storage_options must be a dict, got {type(storage_options).__name__}")
    options = dict(storage_options or {})
    if protocol == "s3":
        if not any(k in options for k in ("anon", "key", "secret", "token", "profile")):
            options["anon"] = not any(os.environ.get(k) for k in _AWS_CREDENTIAL_ENV)
        if "endpoint_url" not in options and os.environ.get("AWS_ENDPOINT_URL"):
            options["endpoint_url"] = os.environ["AWS_ENDPOINT_URL"]
        options.setdefault("default_block_size", BLOCK_SIZE)
    elif protocol in ("http", "https"):
        options.setdefault("block_size", BLOCK_SIZE)
        client = dict(options.get("client_kwargs") or {})
        if "timeout" not in client:
            import aiohttp

            total, read = timeouts()
            client["timeout"] = aiohttp.ClientTimeout(total=total, sock_connect=read,
                                                      sock_read=read)
        options["client_kwargs"] = client
    try:
        fs = fsspec.filesystem(protocol, **options)
    except ImportError as exc:
        raise DataError(f"reading {protocol}:// URLs needs an extra package ({exc}); "
                        "install it with: pip install 'lrm-cvx[remote]'") from None
    except ValueError as exc:
        raise DataError(f"cannot read {url}: {exc}") from None
    folder = cache_folder(cache)
    if folder is not None:
        fs = fsspec.filesystem("blockcache", fs=fs, cache_storage=folder, check_files=False,
                               expiry_time=False)
    return fs


def _has_glob(url: str, protocol: str) -> bool:
    # "?" starts an HTTP query, so it is a wildcard only for object stores
    chars = "*[" if protocol in ("http", "https") else "*?["
    return any(c in url for c in chars)


def expand_urls(urls: Sequence[str], storage_options: dict[str, Any] | None = None,
                suffix: str = ".nc") -> list[str]:
    """Explicit URLs as they are; globs and folder URLs (ending in ``/``) listed on the server.

    A folder URL gives its files ending in ``suffix``. Raises DataError naming the URL when a
    glob matches nothing or the server cannot list it (HTTP: no HTML index page).
    """
    out: list[str] = []
    for url in urls:
        protocol = _protocol(url)
        folder = url.endswith("/")
        if not folder and not _has_glob(url, protocol):
            out.append(url)
            continue
        fs = remote_filesystem(url, storage_options)
        pattern = url.rstrip("/") + "/*" + suffix if folder else url

        def _glob(fs=fs, pattern=pattern) -> list[str]:
            return sorted(fs.glob(pattern))

        found = _with_retries(_glob, url)
        found = [p if is_url(p) else fs.unstrip_protocol(p) for p in found]
        if not found:
            how = ("" if protocol not in ("http", "https") else
                   " (HTTP globs need a server that lists the folder as an HTML page of links; "
                   "otherwise give the URLs one by one)")
            raise DataError(f"no file matches {url!r}{how}")
        out.extend(found)
    return out


# --------------------------------------------------------------------------- errors, retries
def _chain(exc: BaseException) -> Iterator[BaseException]:
    seen: set[int] = set()
    todo = [exc]
    while todo:
        e = todo.pop(0)
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        yield e
        todo.extend([e.__cause__, e.__context__])


def _classify(exc: BaseException) -> tuple[bool, str]:
    """``(transient, reason)`` for a failure anywhere in ``exc``'s chain.

    Transient (retried): a 5xx or 429 status, a connection reset, dropped or timed out. Not
    transient: other statuses (404, 403...), a refused connection, an unknown host, a file
    that is not NetCDF.
    """
    status = None
    refused = dropped = missing = timeout = None
    for e in _chain(exc):
        name = type(e).__name__
        code = getattr(e, "status", None)
        if status is None and isinstance(code, int) and 100 <= code < 600:
            status = code
        response = getattr(e, "response", None)
        if status is None and isinstance(response, dict):
            meta_code = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
            if isinstance(meta_code, int):
                status = meta_code
        if isinstance(e, ConnectionRefusedError) or name in (
                "EndpointConnectionError", "ConnectTimeoutError") or any(
                c.__name__ == "ClientConnectorError" for c in type(e).__mro__):
            refused = refused or e  # also an unknown host (ClientConnectorDNSError)
        if isinstance(e, (TimeoutError, asyncio.TimeoutError)) or name in (
                "ServerTimeoutError", "ReadTimeoutError", "SocketTimeoutError"):
            timeout = timeout or e
        if isinstance(e, (ConnectionResetError, BrokenPipeError,
                          asyncio.IncompleteReadError)) or name in (
                "ServerDisconnectedError", "ClientPayloadError", "ContentLengthError",
                "TransferEncodingError", "ConnectionClosedError", "ResponseStreamingError",
                "IncompleteRead"):
            dropped = dropped or e
        if isinstance(e, FileNotFoundError) or name in ("NoSuchKey", "NoSuchBucket"):
            missing = missing or e
    if status is not None:
        transient = status >= 500 or status == 429
        reason = f"HTTP status {status}" + (" (not found)" if status == 404 else "")
    elif refused is not None:
        transient, reason = False, f"connection refused or host unreachable ({refused})"
    elif dropped is not None:
        transient = True
        reason = f"connection dropped while reading ({type(dropped).__name__}: {dropped})"
    elif timeout is not None:
        total, read = timeouts()
        transient = True
        reason = (f"timed out: the server sent nothing for {read:g} s or a request took over "
                  f"{total:g} s ({type(timeout).__name__}{': ' if str(timeout) else ''}"
                  f"{timeout}); set {_TIMEOUT_ENV['read']} / {_TIMEOUT_ENV['total']} (seconds)"
                  " to wait longer")
    elif missing is not None:
        transient, reason = False, "not found (HTTP status 404)"
    else:
        transient, reason = False, f"{type(exc).__name__}: {exc}"
    return transient, reason


def _with_retries(func: Callable[[], T], url: str, retries: int | None = None,
                  backoff: float | None = None) -> T:
    """``func()``, again after ``backoff * 2**k`` s on a transient failure, at most ``retries``
    times (defaults: :data:`RETRIES`, :data:`BACKOFF`); any other failure, or the last, is a
    DataError naming ``url``."""
    retries = RETRIES if retries is None else int(retries)
    backoff = BACKOFF if backoff is None else float(backoff)
    start = time.monotonic()
    for attempt in range(retries + 1):
        try:
            return func()
        except DataError:
            _release_failed_reads()
            raise
        except Exception as exc:
            transient, reason = _classify(exc)
        # outside the except block: the failure's traceback (its frames hold the half-opened
        # h5py file and the remote file object under it) is gone, and nothing chains to it
        _release_failed_reads()
        if reason.startswith("timed out") and (
                time.monotonic() - start + backoff * 2**attempt > timeouts()[0]):
            transient = False  # timed out tries are retried within TIMEOUT s only
        if transient and attempt < retries:
            time.sleep(backoff * 2**attempt)
            continue
        tries = f" after {attempt + 1} attempts" if attempt else ""
        if url.startswith("s3://") and "status 403" in reason:
            tries += (" (S3 reads are anonymous unless credentials are in the environment "
                      "or storage_options)")
        raise DataError(f"cannot read {url}: {reason}{tries}")
    raise AssertionError("unreachable")  # pragma: no cover


def _release_failed_reads() -> None:
    """Free, now, what a read that failed inside h5py left behind.

    When a read fails inside ``H5Fopen`` (a connection dropped mid-file, a server without
    ranges), HDF5 2.0 keeps one reference to the file-access property list whose driver is
    h5py's Python file-object driver. HDF5 frees it only at process exit, from a C ``atexit``
    handler that runs after Python has shut down; the driver's free callback then takes the
    GIL of a finalized interpreter and the process dies with SIGSEGV (exit 139) after the right
    error was printed. So after a failure the file-object property lists nothing in Python
    holds any more are released here, while the interpreter is alive."""
    import gc

    gc.collect()  # the failed h5py objects: their own references go first
    lib = _hdf5_library()
    if lib is None:
        return
    import ctypes

    import h5py.h5fd
    import h5py.h5i

    found: list[int] = []
    callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int64, ctypes.c_void_p)(
        lambda hid, _: found.append(hid) or 0)
    lib.H5Iiterate(h5py.h5i.GENPROP_LST, callback, None)
    fileobj = int(h5py.h5fd.fileobj_driver)
    for hid in found:
        if lib.H5Pget_driver(hid) == fileobj:
            while lib.H5Iget_ref(hid) > 0 and lib.H5Idec_ref(hid) >= 0:
                pass


def _hdf5_library() -> Any:
    """The HDF5 library h5py loaded (ctypes), with the few signatures used here; None when it
    cannot be found (then nothing is released: the error is still raised)."""
    import ctypes

    import h5py  # noqa: F401  (loads the library)

    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            paths = {line.split()[-1] for line in maps if "libhdf5" in line}
    except OSError:  # pragma: no cover - not Linux
        return None
    paths = [p for p in paths if os.path.basename(p).startswith("libhdf5")
             and "_hl" not in os.path.basename(p)]
    if not paths:  # pragma: no cover
        return None
    lib = ctypes.CDLL(sorted(paths)[0])
    cb = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int64, ctypes.c_void_p)
    lib.H5Iiterate.argtypes = [ctypes.c_int, cb, ctypes.c_void_p]
    for name in ("H5Pget_driver", "H5Iget_ref", "H5Idec_ref"):
        getattr(lib, name).argtypes = [ctypes.c_int64]
    lib.H5Pget_driver.restype = ctypes.c_int64
    return lib


class _RecordingFile:
    """A file object that remembers the exception its ``read`` raised.

    h5py may turn an exception raised by a Python file object into its own OSError; keeping
    the original lets the error name the HTTP status or the dropped connection.
    """

    def __init__(self, f: Any):
        self._f = f
        self.recorded: BaseException | None = None

    def read(self, *args: Any) -> bytes:
        try:
            return self._f.read(*args)
        except BaseException as exc:
            self.recorded = exc
            raise

    def readinto(self, b: Any) -> int:
        data = self.read(len(b))
        b[: len(data)] = data
        return len(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def _engine(head: bytes, url: str) -> str:
    if head.startswith(b"\x89HDF"):
        return "h5netcdf"
    if head.startswith(b"CDF"):
        return "scipy"
    raise DataError(f"{url} is not a NetCDF file (it starts with {head[:8]!r}, neither HDF5 "
                    "nor NetCDF-3)")


def _no_ranges(url: str, size: Any = None) -> DataError:
    if size is None:  # a stream: no Content-Length, so no seeking
        return DataError(f"cannot read {url}: the server does not report the file's size (no "
                         "Content-Length), so the file cannot be read in place; download the "
                         "file and open the local copy")
    return DataError(f"cannot read {url}: the server does not support HTTP Range requests, which "
                     "reading a file in place needs; download the file and open the local copy")


def _probe_end(f: Any, url: str) -> None:
    """Read the last byte of the HTTP file ``f`` (then rewind): DataError when the server
    ignores ``Range`` requests or sends no size. h5py must never get a file object that fails
    mid-read: that is what left a crash for interpreter exit. A file of one block is read whole
    in one request and needs no ranges."""
    size = getattr(f, "size", None)
    if size is None:
        raise _no_ranges(url)
    if size > getattr(f, "blocksize", 0):
        f.seek(size - 1)
        try:
            f.read(1)
        except ValueError as exc:
            if "range" not in str(exc).lower():
                raise
            raise _no_ranges(url, size) from None
    f.seek(0)


def _check_ranges(fs: Any, url: str) -> None:
    """:func:`_probe_end` on a fresh uncached HTTP file, before a block cache sees the URL (a
    cache would record a failed block as read). A file already in the cache needs no server."""
    raw = getattr(fs, "fs", fs)  # the HTTP filesystem behind a block cache
    if raw is fs or _protocol(url) not in ("http", "https"):
        return
    with contextlib.suppress(Exception):
        if fs._check_file(url):
            return
    with raw.open(url, "rb") as f:
        _probe_end(f, url)


@contextlib.contextmanager
def open_remote_dataset(url: str, storage_options: dict[str, Any] | None = None,
                        cache: Any = None, **open_kwargs: Any) -> Iterator[xr.Dataset]:
    """``xr.open_dataset`` on ``url`` read lazily through fsspec; closed on exit.

    The engine is chosen from the file's first bytes (h5netcdf for NetCDF-4/HDF5, scipy for
    NetCDF-3). Errors are raised as they are; :func:`read_remote` turns them into DataError.
    """
    fs = remote_filesystem(url, storage_options, cache)
    _check_ranges(fs, url)
    f = fs.open(url, "rb")
    rec = _RecordingFile(f)
    ds = None
    failed = True
    try:
        engine = _engine(rec.read(8), url)
        if fs is getattr(fs, "fs", fs) and _protocol(url) in ("http", "https"):
            _probe_end(f, url)  # uncached: the probe's block is one h5py would read anyway
        rec.seek(0)
        try:
            ds = xr.open_dataset(rec, engine=engine, **open_kwargs)
        except Exception as exc:
            if rec.recorded is not None:
                raise exc from rec.recorded
            raise
        yield ds
        failed = False
    except Exception as exc:
        if rec.recorded is not None and exc.__cause__ is None:
            raise exc from rec.recorded
        raise
    finally:
        if ds is not None:
            ds.close()
        f.close()
        if failed and hasattr(fs, "pop_from_cache"):  # never keep blocks of a failed read
            with contextlib.suppress(Exception):
                fs.pop_from_cache(url)


def read_remote(url: str, func: Callable[[xr.Dataset], T], *,
                storage_options: dict[str, Any] | None = None, cache: Any = None,
                retries: int | None = None, backoff: float | None = None,
                **open_kwargs: Any) -> T:
    """``func(ds)`` on ``url`` opened lazily (see :func:`open_remote_dataset`), with retries.

    ``func`` must load what it returns (the file is closed afterwards): subset first, then
    ``.load()``, so only the chunks covering the subset are fetched. A transient failure
    (connection reset or dropped mid-read, HTTP 5xx/429) reopens and rereads the file after
    ``backoff``, ``2*backoff``, ... seconds, at most ``retries`` times; a 404, a refused
    connection, the last transient failure or a file that is not NetCDF raise one DataError
    naming the URL and the HTTP status where there is one. Nothing partial is returned.
    """

    def attempt() -> T:
        with open_remote_dataset(url, storage_options, cache, **open_kwargs) as ds:
            return func(ds)

    return _with_retries(attempt, url, retries, backoff)
