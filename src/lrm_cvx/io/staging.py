"""Staging: a ``(T, L)`` matrix written once to disk as column chunks (the input of the
out-of-core fit, :mod:`lrm_cvx.glrm.chunked`).

:func:`stage` writes float32 values (NaN = missing) as ``.npy`` column files in one streaming
pass over dask data, or straight from NOAA CDR NDVI files with the loader's own decoding rules
(docs/scaling.md).
"""

from __future__ import annotations

import functools
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from ..errors import DataError, RegionError
from ..region import Region

__all__ = ["ChunkStore", "stage", "cdr_source", "is_dask_backed"]


def is_dask_backed(data: Any) -> bool:
    """True when ``data`` is a dask collection (a dask array, or a DataArray backed by one)."""
    try:
        import dask
    except ImportError:
        return False
    return bool(dask.is_dask_collection(data))


# --------------------------------------------------------------------------- staging
@dataclass
class ChunkStore:
    """Column chunks of the staged ``(T, L)`` matrix: ``files[c]`` holds columns
    ``bounds[c]:bounds[c + 1]`` as a ``(T, Lc)`` float32 ``.npy`` file, NaN = missing."""

    directory: str
    n_times: int
    bounds: np.ndarray
    files: list[str]

    @property
    def n_cells(self) -> int:
        return int(self.bounds[-1])

    @property
    def n_chunks(self) -> int:
        return len(self.files)

    def extra(self, name: str, rows: int, dtype: Any = np.float64) -> list[str]:
        """Create ``(rows, Lc)`` per-chunk files ``name_c.npy`` (for test matrices, init)."""
        paths = []
        for c in range(self.n_chunks):
            p = os.path.join(self.directory, f"{name}_{c:05d}.npy")
            w = int(self.bounds[c + 1] - self.bounds[c])
            np.lib.format.open_memmap(p, mode="w+", dtype=dtype, shape=(rows, w)).flush()
            paths.append(p)
        return paths

    def write_rows(self, paths: list[str], row: int, values: np.ndarray) -> None:
        """Write one ``(L,)`` row split over the per-chunk files ``paths``."""
        for c, p in enumerate(paths):
            mm = np.lib.format.open_memmap(p, mode="r+")
            mm[row] = values[self.bounds[c]: self.bounds[c + 1]]
            mm.flush()
            del mm


def _time_blocks(arr: Any, row_bytes: int, block_mb: float) -> list[tuple[int, int]]:
    """``[(t0, t1), ...]`` covering ``range(T)``: consecutive input time chunks grouped up to
    ``block_mb`` MB (a chunk larger than that is split), so each block reads whole chunks once."""
    T = int(arr.shape[0])
    budget = max(1, int(block_mb * 2**20 // max(row_bytes, 1)))  # rows per block
    chunks = getattr(arr, "chunks", None)
    edges = np.cumsum((0, *chunks[0])) if chunks is not None else np.array([0, T])
    blocks: list[tuple[int, int]] = []
    t0 = 0
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        a, b = int(a), int(b)
        if b - a > budget:  # a chunk larger than a block: close the open block, split it
            if t0 < a:
                blocks.append((t0, a))
            blocks.extend((s, min(s + budget, b)) for s in range(a, b, budget))
            t0 = b
        elif b - t0 > budget:
            blocks.append((t0, a))
            t0 = a
    if t0 < T:
        blocks.append((t0, T))
    return [(a, b) for a, b in blocks if b > a]


def _pwrite_all(fd: int, buf: np.ndarray, offset: int) -> None:
    """Write all of the contiguous ``buf`` at byte ``offset`` of ``fd`` (pwrite may be short)."""
    view = memoryview(buf).cast("B")
    done = 0
    while done < len(view):
        done += os.pwrite(fd, view[done:], offset + done)


def _pread_all(fd: int, buf: np.ndarray, offset: int) -> None:
    """Fill the contiguous ``buf`` from byte ``offset`` of ``fd`` (preadv may be short)."""
    view = memoryview(buf).cast("B")
    done = 0
    while done < len(view):
        n = os.preadv(fd, [view[done:]], offset + done)
        if n <= 0:
            raise DataError(f"staged file ended early at byte {offset + done}")
        done += n


class _Deferred:
    """A dask collection carried into a task unevaluated (dask does not look inside): the task
    computes it with the synchronous scheduler, so the thousands of tiny decode tasks of a
    staging block cost what the decoding costs, without the scheduler's overhead."""

    def __init__(self, obj: Any) -> None:
        self.obj = obj

    def value(self) -> np.ndarray:
        if is_dask_backed(self.obj):
            return np.asarray(self.obj.compute(scheduler="sync"))
        return np.asarray(self.obj)


def _deferred(obj: Any) -> Any:
    """``obj`` wrapped for :func:`_value`, its graph culled to what it needs (a slice of an
    array otherwise carries the whole input's graph into every task)."""
    if obj is None or not is_dask_backed(obj):
        return obj
    import dask

    return _Deferred(dask.optimize(obj)[0])


def _value(obj: Any) -> Any:
    return obj.value() if isinstance(obj, _Deferred) else obj


def _t_valid(block) -> np.ndarray:
    """Task: which cells of one time block are observed at least once (flattened grid)."""
    b = _value(block)
    return np.isfinite(b).any(axis=0).ravel()


def _valid_cells(arr: Any, block_mb: float) -> np.ndarray:
    """``isfinite(arr).any(axis=0)`` by time blocks, one task per block (see :class:`_Deferred`)."""
    import dask

    itemsize = max(4, np.dtype(arr.dtype).itemsize)
    blocks = _time_blocks(arr, itemsize * int(np.prod(arr.shape[1:])), block_mb)
    parts = dask.compute(*[dask.delayed(_t_valid, pure=False)(_deferred(arr[t0:t1]))
                           for t0, t1 in blocks])
    return np.logical_or.reduce(parts).reshape(arr.shape[1:])


def _write_block(block, mblock, index, t0, files, bounds, offsets) -> int:
    """Task: write the rows ``t0:t0 + len(block)`` of every column file from one input block
    (``(tb, ...)`` data, optional mask, ``index`` of the region's cells in the flattened
    grid); return the block's number of infs. Rows of a C-ordered ``(T, Lc)`` file are one
    contiguous byte range, written with ``pwrite`` (disjoint ranges: tasks run in parallel,
    in threads or worker processes, with no lock)."""
    block, mblock = _value(block), _value(mblock)
    tb = block.shape[0]
    flat = np.asarray(block).reshape(tb, -1)
    if index is not None:
        flat = np.take(flat, index, axis=1)
    flat = np.asarray(flat, dtype=np.float32)
    del block
    if mblock is not None:
        flat = np.where(np.asarray(mblock).reshape(tb, -1), flat, np.float32(np.nan))
    n_inf = int(np.count_nonzero(np.isinf(flat)))
    for c, path in enumerate(files):
        lo, hi = int(bounds[c]), int(bounds[c + 1])
        fd = os.open(path, os.O_WRONLY)
        try:
            _pwrite_all(fd, np.ascontiguousarray(flat[:, lo:hi]), offsets[c] + t0 * (hi - lo) * 4)
        finally:
            os.close(fd)
    return n_inf


def _parallel_slots() -> int:
    """Threads of the active scheduler: the workers' with a distributed Client, else the
    machine's cores (dask's threaded default)."""
    try:
        from distributed import get_client

        return max(1, sum(get_client().nthreads().values()))
    except (ImportError, ValueError):
        return max(1, os.cpu_count() or 1)


def _stream_stage(arr, mask, index, blocks, files, bounds, offsets) -> int:
    """Stage ``arr`` block of times by block of times into the column files; return the
    number of infs. Each block is one task that computes its input (the files' decoding, on
    the active dask scheduler) and writes its rows into every column file itself, so the data
    never travel through the client. Blocks run in waves of twice the scheduler's threads:
    at most that many blocks are in memory at once."""
    import dask

    d = dask.delayed
    idx = None if index is None else d(index, pure=True)  # shipped once, not per task
    wave = 2 * _parallel_slots()
    n_inf = 0
    for w0 in range(0, len(blocks), wave):
        tasks = []
        for t0, t1 in blocks[w0: w0 + wave]:
            mb = None if mask is None else _deferred(mask[t0:t1])
            tasks.append(d(_write_block, pure=False)(_deferred(arr[t0:t1]), mb, idx, t0, files,
                                                      bounds, offsets))
        n_inf += int(sum(dask.compute(*tasks)))
    return n_inf


# ----------------------------------------------------- file-level staging of CDR NDVI files
_NC_LOCK = threading.Lock()  # netCDF4 / HDF5 are not thread-safe: one read at a time per process


def cdr_source(data: Any) -> dict | None:
    """The daily files behind ``data`` when it is exactly what :func:`~lrm_cvx.io.open_ndvi_cdr`
    returned lazily (local files; its dask graph untouched), else None."""
    src = getattr(data, "encoding", {}).get("lrm_cvx_cdr")
    if (src is None or not is_dask_backed(data) or getattr(data.data, "name", None) != src["name"]
            or tuple(data.shape) != tuple(src["shape"])):
        return None
    return src


def _sel_span(sel: Any, n: int) -> tuple[int, int, np.ndarray | None]:
    """``(lo, hi, pick)``: the index span ``lo:hi`` that selector ``sel`` (a slice or an index
    array over ``n``) covers, and the positions to take from it (None: all of it, in order)."""
    if isinstance(sel, slice):
        lo, hi, step = sel.indices(n)
        if step == 1:
            return lo, max(lo, hi), None
        sel = np.arange(lo, hi, step)
    sel = np.asarray(sel, dtype=np.int64)
    lo = int(sel.min())
    return lo, int(sel.max()) + 1, sel - lo


_CDR_DIMS = ("time", "latitude", "longitude")
_ENC_KEYS = ("scale_factor", "add_offset", "_FillValue", "valid_range")


def _h5_chunks(path: str, rows: Any, cols: Any) -> tuple | None:
    """The raw (still compressed) HDF5 chunks of NDVI and QA covering the window ``rows x
    cols`` of CDR file ``path``: ``(tiles, layout, spans, enc)`` with ``tiles`` a list of
    ``(row0, col0, ndvi_bytes, qa_bytes)`` (the tile's first grid row and column), ``layout =
    (chunk_rows, chunk_cols, deflate, shuffle)``, ``spans`` the :func:`_sel_span` of ``rows``
    and ``cols`` and ``enc`` the file's NDVI/QA encoding (:func:`~lrm_cvx.io.ndvi.file_encoding`).

    Read with h5py's ``read_direct_chunk``: only the bytes on disk are copied (under h5py's
    lock); inflating them (zlib releases the GIL) and decoding happen outside any lock, in
    parallel. None when the file is not laid out the way this reader decodes (int16
    little-endian, tiled one day deep, deflate and/or shuffle only, the same tiles for NDVI and
    QA, dims (time, latitude, longitude)) or cannot be opened: the caller then reads it with
    netCDF4 (:func:`~lrm_cvx.io.ndvi.read_window`), which reads every layout and names the file
    in its errors."""
    import h5py

    from .ndvi import file_encoding

    try:
        f = h5py.File(path, "r")
    except Exception:  # noqa: BLE001 - read_window reports it, naming the file
        return None
    try:
        dsets, layout, attrs = [], None, []
        for var in ("NDVI", "QA"):
            d = f.get(var)
            if not isinstance(d, h5py.Dataset) or d.ndim != 3 or d.shape[0] != 1:
                return None
            dims = tuple(d.dims[i][0].name.lstrip("/") if len(d.dims[i]) == 1 else ""
                         for i in range(3))
            if (dims != _CDR_DIMS or d.dtype != np.dtype("<i2") or d.chunks is None
                    or d.chunks[0] != 1 or d.compression not in (None, "gzip") or d.fletcher32
                    or d.scaleoffset is not None or d.external):
                return None
            lay = (int(d.chunks[1]), int(d.chunks[2]), d.compression == "gzip", bool(d.shuffle))
            if layout not in (None, lay) or (dsets and d.shape != dsets[0].shape):
                return None
            layout = lay
            dsets.append(d)
            attrs.append({k: (lambda a: a.item() if a.size == 1 else a)(np.asarray(d.attrs[k]))
                          for k in _ENC_KEYS if k in d.attrs})
        enc = file_encoding(attrs[0], attrs[1])
        ny, nx = (int(n) for n in dsets[0].shape[1:])
        (r0, r1, rp), (c0, c1, cp) = _sel_span(rows, ny), _sel_span(cols, nx)
        if not (0 <= r0 < r1 <= ny and 0 <= c0 < c1 <= nx):
            return None
        cr, cc = layout[:2]
        tiles = []
        for tr in range(r0 // cr * cr, r1, cr):
            for tc in range(c0 // cc * cc, c1, cc):
                parts = []
                for d in dsets:
                    fmask, buf = d.id.read_direct_chunk((0, tr, tc))
                    if fmask:  # a filter was skipped for this chunk: let netCDF4 read it
                        return None
                    parts.append(buf)
                tiles.append((tr, tc, parts[0], parts[1]))
    except Exception:  # noqa: BLE001 - e.g. an unallocated chunk: the general reader
        return None
    finally:
        f.close()
    return tiles, layout, ((r0, r1, rp), (c0, c1, cp)), enc


@numba.njit(nogil=True, cache=True)
def _decode_tile(nd, qa, shuffled, cc, n, i0, i1, j0, j1, values, qa_ok, nan, out, oi, oj,
                 seen, track):  # pragma: no cover - numba
    """Decode rows ``i0:i1`` x columns ``j0:j1`` of one inflated tile (``n`` int16 values of
    NDVI ``nd`` and QA ``qa`` as little-endian bytes, byte-shuffled or not; ``cc`` columns a
    tile row) into ``out[oi:, oj:]``: ``values[ndvi]`` where ``qa_ok[qa]``, else ``nan``
    (:func:`~lrm_cvx.io.ndvi.decode_day` bit for bit); with ``track``, ``seen`` |= finite."""
    for i in range(i0, i1):
        r = oi + i - i0
        for j in range(j0, j1):
            k = i * cc + j
            if shuffled:
                a = np.int64(nd[k]) | (np.int64(nd[n + k]) << 8)
                b = np.int64(qa[k]) | (np.int64(qa[n + k]) << 8)
            else:
                a = np.int64(nd[2 * k]) | (np.int64(nd[2 * k + 1]) << 8)
                b = np.int64(qa[2 * k]) | (np.int64(qa[2 * k + 1]) << 8)
            v = values[a] if qa_ok[b] else nan
            c = oj + j - j0
            out[r, c] = v
            if track and v == v:
                seen[r, c] = True


def _zlib() -> Any:
    """The zlib module that inflates fastest here: ``isal.isal_zlib`` (Intel ISA-L, the same
    bytes as zlib, 2-3x faster; optional) when installed, else the standard library's."""
    try:
        from isal import isal_zlib

        return isal_zlib
    except ImportError:
        import zlib

        return zlib


def _inflate(buf: bytes, deflate: bool, nbytes: int, path: str) -> np.ndarray:
    """One raw HDF5 chunk as ``nbytes`` bytes (inflated when ``deflate``, by :func:`_zlib`;
    the GIL is released while inflating); a DataError naming ``path`` when it is corrupt or
    short."""
    z = _zlib()
    try:
        raw = z.decompress(buf, 15, nbytes) if deflate else buf  # output size known
    except z.error as exc:
        raise DataError(f"cannot read NDVI file {path}: a compressed chunk is corrupt "
                        f"({exc})") from None
    if len(raw) != nbytes:
        raise DataError(f"cannot read NDVI file {path}: a chunk holds {len(raw)} bytes, "
                        f"expected {nbytes}")
    return np.frombuffer(raw, dtype=np.uint8)


def _t_stage_days(days, src, rows, cols, index, files, bounds, offsets, track) -> dict:
    """Task: read, decode and write the days ``days`` (indices into ``src["files"]``).

    Each day's bbox window of raw NDVI and QA is read as its raw HDF5 chunks
    (:func:`_h5_chunks`, h5py's lock held only while copying the compressed bytes), inflated
    with zlib (GIL released) and decoded tile by tile by table lookup in one compiled pass
    (:func:`_decode_tile`: the rules of :func:`open_ndvi_cdr` via
    :func:`~lrm_cvx.io.ndvi.decode_tables`; with ``track`` it also ORs the finite cells).
    Files in another layout are read with netCDF4 under a per-process lock
    (:func:`~lrm_cvx.io.ndvi.read_window`) and decoded with :func:`~lrm_cvx.io.ndvi.decode_day`.
    The region's cells are taken and row ``t`` of every column file is written with ``pwrite``.
    Returns the CPU seconds of this thread in read / inflate / decode / write (CPU, not wall:
    on a shared machine wall time also counts the time other processes held the core) and,
    with ``track``, the packed OR of finite cells."""
    import time

    from .ndvi import decode_day, decode_tables, read_window

    clock = time.thread_time
    secs = {"read": 0.0, "inflate": 0.0, "decode": 0.0, "write": 0.0}
    seen = None
    nan = np.float32(np.nan)
    fds = [os.open(p, os.O_WRONLY) for p in files]
    try:
        for t in days:
            path = src["files"][t]
            prod = src["products"][t]
            t0 = clock()
            raw = _h5_chunks(path, rows, cols)
            t1 = clock()
            t_inf = 0.0
            if raw is None:
                with _NC_LOCK:
                    nd, qa, enc = read_window(path, rows, cols)
                t1 = clock()
                win = decode_day(nd, qa, decode_tables(prod, tuple(src["flags"][prod]), enc))
                del nd, qa
                fin = np.isfinite(win) if track else None
            else:
                tiles, (cr, cc, deflate, shuffled), spans, enc = raw
                (r0, r1, rp), (c0, c1, cp) = spans
                values, qa_ok = decode_tables(prod, tuple(src["flags"][prod]), enc)
                span = _scratch("span", (r1 - r0) * (c1 - c0), np.float32).reshape(
                    r1 - r0, c1 - c0)
                direct = rp is None and cp is None  # the span is the window
                if track and direct and seen is None:
                    seen = np.zeros(span.shape, dtype=np.bool_)
                sink = seen if (track and direct) else np.zeros((1, 1), dtype=np.bool_)
                n = cr * cc
                for tr, tc, bn, bq in tiles:
                    ti = clock()
                    a = _inflate(bn, deflate, 2 * n, path)
                    b = _inflate(bq, deflate, 2 * n, path)
                    t_inf += clock() - ti
                    i0, i1 = max(r0 - tr, 0), min(r1 - tr, cr)
                    j0, j1 = max(c0 - tc, 0), min(c1 - tc, cc)
                    _decode_tile(a, b, shuffled, cc, n, i0, i1, j0, j1, values, qa_ok, nan,
                                 span, tr + i0 - r0, tc + j0 - c0, sink, track and direct)
                del tiles, raw
                if direct:
                    win, fin = span, None
                else:
                    win = span if rp is None else span[rp]
                    win = win if cp is None else win[:, cp]
                    fin = np.isfinite(win) if track else None
            if fin is not None:
                seen = fin if seen is None else np.logical_or(seen, fin, out=seen)
            row = win.ravel()
            if index is not None:
                row = np.take(row, index, out=_scratch("take", index.size, np.float32))
            t2 = clock()
            for c, fd in enumerate(fds):
                lo, hi = int(bounds[c]), int(bounds[c + 1])
                _pwrite_all(fd, row[lo:hi], offsets[c] + t * (hi - lo) * 4)
            t3 = clock()
            secs["read"] += t1 - t0
            secs["inflate"] += t_inf
            secs["decode"] += t2 - t1 - t_inf
            secs["write"] += t3 - t2
    finally:
        for fd in fds:
            os.close(fd)
    if track:
        secs["seen"] = np.packbits(seen.ravel()) if seen is not None else None
    return secs


def _run_tasks(fn, items, on_done=None, **shared) -> list:
    """``[fn(i, **shared) for i in items]`` in parallel: on the workers of an active
    ``distributed`` Client (``shared`` scattered to them once, not shipped with every task),
    else on threads of this process (one per core; the decoding and writing release the GIL,
    the netCDF4 reads are serialised by :data:`_NC_LOCK`). Items start in order;
    ``on_done(item, result)``, when given, is called in this thread as each task finishes."""
    try:
        from distributed import get_client

        client = get_client()
    except (ImportError, ValueError):
        client = None
    if client is not None:
        sent = {k: client.scatter(v, broadcast=True) for k, v in shared.items()}
        futs = client.map(fn, items, pure=False, **sent)
        if on_done is not None:
            from distributed import as_completed

            where = {f.key: i for i, f in enumerate(futs)}
            for f in as_completed(futs):
                on_done(items[where[f.key]], f.result())
        return client.gather(futs)
    from concurrent.futures import ThreadPoolExecutor, as_completed

    with ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1)) as ex:
        futs = [ex.submit(fn, i, **shared) for i in items]
        if on_done is not None:
            where = {f: i for i, f in enumerate(futs)}
            for f in as_completed(futs):
                on_done(items[where[f]], f.result())
        return [f.result() for f in futs]


def _new_files(directory: str, T: int, bounds: np.ndarray, prefix: str = "data"
               ) -> tuple[list[str], list[int]]:
    """Empty ``(T, Lc)`` float32 ``.npy`` column files; their paths and data byte offsets."""
    files, offsets = [], []
    for c in range(bounds.size - 1):
        p = os.path.join(directory, f"{prefix}_{c:05d}.npy")
        mm = np.lib.format.open_memmap(p, mode="w+", dtype=np.float32,
                                       shape=(T, int(bounds[c + 1] - bounds[c])))
        offsets.append(int(mm.offset))
        mm.flush()
        del mm
        files.append(p)
    return files, offsets


def _bounds(L: int, T: int, chunk_mb: float) -> np.ndarray:
    width = max(1, min(L, int(chunk_mb * 2**20 / (4 * T))))
    return np.append(np.arange(0, L, width), L).astype(np.int64)


@numba.njit(nogil=True, cache=True)
def _gather(src, cols, out, j0):  # pragma: no cover - numba
    """``out[j0:j0 + len(cols)] = src[cols]`` without a temporary."""
    for j in range(cols.size):
        out[j0 + j] = src[cols[j]]


_SCRATCH = threading.local()


def _scratch(key: str, n: int, dtype: Any) -> np.ndarray:
    """A 1-D buffer of ``n`` items of ``dtype`` kept per thread under ``key`` and reused by
    the next call: staging's per-day and per-row buffers are written again and again, and a
    fresh multi-megabyte array costs a page fault per 4 KiB the first time it is touched
    (glibc maps and unmaps large blocks), about as much CPU as the decoding itself."""
    dtype = np.dtype(dtype)
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None:
        bufs = _SCRATCH.bufs = {}
    buf = bufs.get(key)
    if buf is None or buf.size < n * dtype.itemsize:
        buf = bufs[key] = np.empty(n * dtype.itemsize, dtype=np.uint8)
    return buf[: n * dtype.itemsize].view(dtype)


def _t_compact(job, files, bounds, offsets, new, noffs, T) -> None:
    """Task: write compacted column file ``c`` of ``job = (c, g)`` (the region's cells ``g``,
    grid indices into the whole-grid files ``files``; only this chunk's slice of the region is
    shipped to a worker) from the staged files (page cache), row by row: each source
    file contributes one contiguous run of its columns, so row ``t`` is one ``preadv`` of that
    span per source file, a gather of the kept columns and one ``pwrite``. The two row buffers
    are reused (this thread's :func:`_scratch`): no fresh pages to fault in, nothing held but
    a row (plain reads, not a memory map: mapped pages count as the worker's memory and a
    LocalCluster paused its workers)."""
    c, g = job
    owner = np.searchsorted(bounds, g, side="right") - 1
    cuts = np.flatnonzero(np.diff(owner)) + 1
    runs = []
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, g.size], strict=True):
        o = int(owner[a])
        cells = g[a:b] - int(bounds[o])
        lo, hi = int(cells[0]), int(cells[-1]) + 1
        runs.append((o, int(a), lo, hi, cells - lo))
    width = max(hi - lo for _, _, lo, hi, _ in runs)
    src = _scratch("compact_src", width, np.float32)
    row = _scratch("compact_row", g.size, np.float32)
    fds = {o: os.open(files[o], os.O_RDONLY) for o, *_ in runs}
    out = os.open(new[c], os.O_WRONLY)
    try:
        for t in range(T):
            for o, a, lo, hi, sel in runs:
                w = int(bounds[o + 1] - bounds[o])
                _pread_all(fds[o], src[: hi - lo], offsets[o] + (t * w + lo) * 4)
                _gather(src, sel, row, a)
            _pwrite_all(out, row, noffs[c] + t * g.size * 4)
    finally:
        for fd in (*fds.values(), out):
            os.close(fd)


def _stage_cdr(data, src, region, chunk_mb, directory, timings) -> tuple[list[str], np.ndarray,
                                                                         Region]:
    """Stage the CDR files of ``src`` straight into column files (one read of each file).

    Without ``region`` the whole bbox grid is staged while the observed cells are OR-ed per
    task; when some cell is never observed the files are compacted to the region's cells
    (a read of the staged files from the page cache, far cheaper than decoding)."""
    import time

    from .ndvi import window_index

    T = int(data.shape[0])
    grid = tuple(int(n) for n in data.shape[1:])
    rows, cols = window_index(src["files"][0], src["bbox"])
    track = region is None
    index = None if track else np.flatnonzero(region.mask.ravel())
    L = int(np.prod(grid)) if track else int(index.size)
    bounds = _bounds(L, T, chunk_mb)
    files, offsets = _new_files(directory, T, bounds)
    n_tasks = min(T, 4 * _parallel_slots())
    parts = [list(range(T))[i::n_tasks] for i in range(n_tasks)]  # interleaved: balanced
    clock = time.perf_counter()
    cpu0 = time.process_time()
    task = functools.partial(_t_stage_days, src=src, rows=rows, cols=cols, files=files,
                             bounds=bounds, offsets=offsets, track=track)
    res = _run_tasks(task, parts, index=index)  # the region's cells: sent to a worker once
    if timings is not None:
        for k in ("read", "inflate", "decode", "write"):
            timings[f"stage_{k}"] = float(sum(r[k] for r in res))
        timings["stage_pass"] = time.perf_counter() - clock
        timings["stage_pass_cpu"] = time.process_time() - cpu0
    if not track:
        return files, bounds, region
    seen = np.zeros(int(np.prod(grid)), dtype=bool)
    for r in res:
        if r["seen"] is not None:
            seen |= np.unpackbits(r["seen"], count=seen.size).astype(bool)
    if not seen.any():
        raise DataError("da has no finite value: every cell is missing (all NaN)")
    region = Region.from_dataarray(data, mask=seen.reshape(grid))
    if seen.all():
        return files, bounds, region
    index = np.flatnonzero(seen)
    nb = _bounds(int(index.size), T, chunk_mb)
    new, noffs = _new_files(directory, T, nb, prefix="compact")
    clock = time.perf_counter()
    cpu0 = time.process_time()
    # each whole-grid file is removed as soon as the last compacted file reading it is
    # written: the page cache never holds both copies of the matrix
    first = np.searchsorted(bounds, index[nb[:-1]], side="right") - 1
    last = np.searchsorted(bounds, index[nb[1:] - 1], side="right") - 1
    readers = np.zeros(len(files), dtype=np.int64)
    for a, b in zip(first, last, strict=True):
        readers[a: b + 1] += 1

    def done(job: tuple, _: Any) -> None:
        c = job[0]
        for o in range(int(first[c]), int(last[c]) + 1):
            readers[o] -= 1
            if readers[o] == 0:
                os.remove(files[o])

    for o in np.flatnonzero(readers == 0):  # whole files of never-observed cells
        os.remove(files[o])
    _run_tasks(functools.partial(_t_compact, files=files, bounds=bounds, offsets=offsets,
                                 new=new, noffs=noffs, T=T),
               [(c, index[nb[c]: nb[c + 1]]) for c in range(nb.size - 1)], on_done=done)
    if timings is not None:
        timings["stage_compact"] = time.perf_counter() - clock
        timings["stage_compact_cpu"] = time.process_time() - cpu0
    final = []
    for c, n in enumerate(new):
        p = os.path.join(directory, f"data_{c:05d}.npy")
        os.replace(n, p)
        final.append(p)
    return final, nb, region


def stage(
    data: Any,
    *,
    mask: Any = None,
    region: Region | None = None,
    chunk_mb: float = 256.0,
    scratch_dir: str | None = None,
    block_mb: float = 256.0,
    timings: dict | None = None,
) -> tuple[ChunkStore, Region | None, Any, str]:
    """Stage ``data`` into column chunks on disk; return ``(store, region, times, time_dim)``.

    ``data``: a ``(time, lat, lon)`` DataArray (dask-backed or not; the region's valid cells are
    those observed at least once, computed as a dask reduction, unless ``region`` is given), a
    ``(time, cell)`` DataArray with ``region``, or a ``(T, L)`` (dask) array with NaN, optionally
    with a boolean ``mask`` of the same shape (True = observed). Column chunks hold about
    ``chunk_mb`` MB of float32 each. Staging streams: the input is read in blocks of about
    ``block_mb`` MB of consecutive times (whole input time chunks); one task per block, on the
    active dask scheduler (workers or threads), computes the block, takes the region's cells
    and writes the block's rows into every column file. Peak memory is about ``3 * block_mb``
    per scheduler thread, independent of ``T x L`` (no all-to-all rechunk, nothing through the
    client).
    The caller removes ``store.directory`` when done.

    A DataArray exactly as :func:`~lrm_cvx.io.open_ndvi_cdr` returned it lazily (local files)
    is staged from the files themselves (:func:`cdr_source`): one task per group of days reads
    each day's window as raw HDF5 chunks (:func:`_h5_chunks`; netCDF4 for other layouts),
    inflates and decodes it by table lookup with the loader's own rules and writes its rows
    (threads of this process, or the workers of an active distributed Client); the same
    matrix, bit for bit, at the cost of one read of each file. A corrupt or truncated file is
    a DataError naming it. ``timings``, when a dict, then receives the tasks' summed CPU
    seconds ``stage_read`` / ``stage_inflate`` / ``stage_decode`` / ``stage_write`` and the
    wall and CPU seconds ``stage_pass`` / ``stage_pass_cpu`` (and ``stage_compact`` /
    ``stage_compact_cpu`` when never-observed cells were dropped).
    """
    import xarray as xr

    if not (np.isfinite(block_mb) and block_mb > 0):
        raise DataError(f"block_mb must be > 0, got {block_mb!r}")
    if not (np.isfinite(chunk_mb) and chunk_mb > 0):
        raise DataError(f"chunk_mb must be > 0, got {chunk_mb!r}")
    times, tdim = None, "time"
    index = None
    src = cdr_source(data) if isinstance(data, xr.DataArray) and mask is None else None
    if src is not None:
        if region is not None and tuple(data.shape[1:]) != region.shape:
            raise RegionError(f"data grid is {data.shape[1:]}, the region's is {region.shape}")
        tdim = str(data.dims[0])
        directory = tempfile.mkdtemp(prefix="lrm-dask-", dir=scratch_dir)
        try:
            files, bounds, region = _stage_cdr(data, src, region, chunk_mb, directory, timings)
        except BaseException:
            shutil.rmtree(directory, ignore_errors=True)
            raise
        return (ChunkStore(directory, int(data.shape[0]), bounds, files), region,
                data[tdim], tdim)
    if isinstance(data, xr.DataArray):
        if mask is not None:
            raise DataError("mask is only accepted with an array; a DataArray uses NaN")
        if data.ndim not in (2, 3):
            raise DataError(f"data must have dims (time, lat, lon), got {data.dims}")
        tdim = str(data.dims[0])
        times = data[tdim] if tdim in data.coords else xr.DataArray(
            np.arange(data.shape[0]), dims=(tdim,))
        if data.ndim == 3:
            if region is None:
                valid = _valid_cells(data.data, block_mb)
                if not valid.any():
                    raise DataError("da has no finite value: every cell is missing (all NaN)")
                region = Region.from_dataarray(data, mask=valid)
            elif tuple(data.shape[1:]) != region.shape:
                raise RegionError(f"data grid is {data.shape[1:]}, the region's is "
                                  f"{region.shape}")
            index = np.flatnonzero(region.mask.ravel())
        else:
            if data.dims[-1] != "cell" or region is None:
                raise DataError("a 2-D DataArray must have dims (time, cell) and come with a "
                                f"region, got {data.dims}")
            if data.shape[1] != region.n_cells:
                raise RegionError(f"data has {data.shape[1]} cells, the region has "
                                  f"{region.n_cells}")
        arr = data.data
    else:
        arr = data
        if getattr(arr, "ndim", None) != 2:
            raise DataError(f"data must be a (T, L) array or a (time, lat, lon) DataArray, got "
                            f"shape {getattr(arr, 'shape', None)}")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise DataError(f"data must be numeric, got dtype {arr.dtype}")
        if mask is not None:
            if tuple(mask.shape) != tuple(arr.shape):
                raise DataError(f"mask has shape {tuple(mask.shape)}, data has shape "
                                f"{tuple(arr.shape)}")
            if mask.dtype != np.bool_:
                raise DataError(f"mask must be boolean (True = observed), got dtype {mask.dtype}")
    T = int(arr.shape[0])
    L = int(index.size) if index is not None else int(arr.shape[1])
    if T == 0 or L == 0:
        raise DataError(f"data is empty, shape {tuple(arr.shape)}")
    width = max(1, min(L, int(chunk_mb * 2**20 / (4 * T))))
    bounds = np.append(np.arange(0, L, width), L).astype(np.int64)
    directory = tempfile.mkdtemp(prefix="lrm-dask-", dir=scratch_dir)
    try:
        files, offsets = _new_files(directory, T, bounds)
        itemsize = max(4, np.dtype(arr.dtype).itemsize)
        row_bytes = itemsize * int(np.prod(arr.shape[1:]))
        blocks = _time_blocks(arr, row_bytes, block_mb)
        n_inf = _stream_stage(arr, mask, index, blocks, files, bounds, offsets)
        if n_inf:
            raise DataError(f"data has {n_inf} non-finite observed values (inf); use NaN or the "
                            "mask for missing entries")
    except BaseException:
        shutil.rmtree(directory, ignore_errors=True)
        raise
    return ChunkStore(directory, T, bounds, files), region, times, tdim
