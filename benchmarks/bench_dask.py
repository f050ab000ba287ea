"""Out-of-core GLRM on dask: daily CDR-format files -> dask-backed DataArray -> GLRM.fit.

Writes ``--days`` synthetic daily NOAA CDR NetCDF files (``lrm_cvx.io.samples.write_ndvi_cdr``,
int16 + zlib, ``--land-fraction`` of the cells ever observed), opens them lazily
(``open_ndvi_cdr``, one chunk a day) and fits rank 5 on a ``distributed.LocalCluster``
(processes, ``--workers`` x 1 thread, ``--memory-limit`` per worker): one fit of ``--rounds``
iterations with tol=0. Prints the seconds of each phase (region + streaming stage, init, every
round, final pass) and the peak resident memory of the whole process tree (client + scheduler +
workers; psutil every 0.2 s) next to the size of the float32 matrix.

    flock /tmp/bench.lock python benchmarks/bench_dask.py [--small] [--stage-only [--floors]]
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import tempfile
import threading
import time
import warnings

import numpy as np


class TreeRSS:
    """Peak of the summed RSS of this process and all its descendants."""

    def __init__(self, every: float = 0.2) -> None:
        import psutil

        self.proc = psutil.Process()
        self.peak = 0
        self.every = every
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> int:
        total = 0
        for p in [self.proc, *self.proc.children(recursive=True)]:
            try:
                total += p.memory_info().rss
            except Exception:
                pass
        self.peak = max(self.peak, total)
        return total

    def _run(self) -> None:
        while not self._stop.is_set():
            self.sample()
            time.sleep(self.every)

    def __enter__(self) -> TreeRSS:
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()


def write_days(directory: str, days: int, shape: tuple[int, int], batch: int = 8,
               land_fraction: float = 0.7) -> list[str]:
    """Daily files from ``synthetic_field`` generated ``batch`` days at a time (same seed: the
    same spatial modes and land mask; the time factors restart each batch)."""
    import pandas as pd

    from lrm_cvx.io.samples import synthetic_field, write_ndvi_cdr

    start = pd.Timestamp("2013-01-01")
    for d0 in range(0, days, batch):
        n = min(batch, days - d0)
        field = synthetic_field(n, shape, rank=5, seed=0, land_fraction=land_fraction,
                                start_date=start + pd.Timedelta(days=d0))
        write_ndvi_cdr(directory, field)
        del field
    return sorted(glob.glob(os.path.join(directory, "*.nc")))


def open_days(files: list[str]):
    try:
        from lrm_cvx.io import open_ndvi_cdr

        return open_ndvi_cdr(files, chunks={"time": 1}), "open_ndvi_cdr"
    except (ImportError, AttributeError, ModuleNotFoundError):
        import xarray as xr

        ds = xr.open_mfdataset(files, combine="nested", concat_dim="time",
                               chunks={"time": 1}, parallel=False)
        name = "NDVI" if "NDVI" in ds else "ndvi"
        return ds[name], "xarray.open_mfdataset"


def load() -> str:
    """The machine's load averages (1, 5, 15 min) and cores: the cores are shared."""
    a, b, c = os.getloadavg()
    return f"load {a:.1f} / {b:.1f} / {c:.1f} on {os.cpu_count()} cores"


def cpu_seconds() -> float:
    """User + system CPU seconds so far of this process (all its threads) and of its live
    children (a LocalCluster's worker processes and nanny)."""
    import psutil

    total = 0.0
    me = psutil.Process()
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def stage_split(tm: dict, nbytes: int) -> str:
    """The file-level staging's split (seconds summed over its tasks) and what bounds it."""
    keys = [k for k in ("read", "inflate", "decode", "write") if f"stage_{k}" in tm]
    busy = sum(tm[f"stage_{k}"] for k in keys)
    mb = nbytes / 2**20
    what = {"read": "read (h5py raw chunks, serial)", "inflate": "inflate (zlib)",
            "decode": "decode+OR", "write": "write (pwrite)"}
    cpu = tm.get("stage_pass_cpu")
    return (f"file-level staging pass {tm['stage_pass']:.1f} s "
            f"({mb / tm['stage_pass']:.0f} MB/s)"
            + (f", CPU {cpu:.1f} s" if cpu is not None else "")
            + "; CPU seconds of the tasks' threads (MB/s per CPU-second): "
            + ", ".join(f"{what[k]} {tm[f'stage_{k}']:.1f} s "
                        f"({mb / max(tm[f'stage_{k}'], 1e-9):.0f})" for k in keys)
            + f"; sum {busy:.1f} s"
            + (f"; compaction to the region's cells {tm['stage_compact']:.1f} s "
               f"(CPU {tm.get('stage_compact_cpu', float('nan')):.1f} s)"
               if "stage_compact" in tm else ""))


def floors(files: list[str], scratch: str, chunk_mb: float, days: int = 24) -> dict:
    """The raw floors of staging, in MB/s of float32 staged (one float32 per grid cell):

    * ``disk``: the files read from disk with a cold cache (this benchmark's own files are
      written back, then dropped from the page cache with ``posix_fadvise(DONTNEED)``; no
      global cache drop), 16 MiB reads on one thread; the files' bytes scaled by the ratio of
      float32 bytes to file bytes;
    * ``chunks``: h5py's raw-chunk read of ``days`` files from the page cache (serial: h5py's
      lock), the part of the pass no second thread can share;
    * ``inflate1:<module>`` / ``inflate2:<module>``: inflating those days' chunks on 1 and 2
      threads with the standard library's zlib and (when installed) ``isal.isal_zlib``;
    * ``decode2``: the compiled table decode of the inflated tiles on 2 threads;
    * ``write2``: :func:`write_floor`, writing the whole matrix into the page cache.
    Each with the load average when measured."""
    from concurrent.futures import ThreadPoolExecutor

    from lrm_cvx.io import ndvi as N
    from lrm_cvx.io.staging import _decode_tile, _h5_chunks

    out: dict = {}
    f32 = None
    size = sum(os.path.getsize(f) for f in files)
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
    t = time.perf_counter()
    got = 0
    for f in files:
        with open(f, "rb", buffering=0) as fh:
            while True:
                b = fh.read(16 << 20)
                if not b:
                    break
                got += len(b)
    dt = time.perf_counter() - t
    sample = files[: min(days, len(files))]
    t = time.perf_counter()
    raws = [_h5_chunks(f, slice(None), slice(None)) for f in sample]
    t_chunks = time.perf_counter() - t
    if any(r is None for r in raws):
        out["note"] = "files not in the raw-chunk layout"
        return out
    (r0, r1, _), (c0, c1, _) = raws[0][2]
    cells = (r1 - r0) * (c1 - c0)
    f32 = 4 * cells * len(files)
    ratio = f32 / size
    out["disk"] = (got / dt / 2**20, got / dt * ratio / 2**20, load())
    mb = 4 * cells * len(sample) / 2**20
    out["chunks"] = (mb / t_chunks, load())
    import zlib

    from lrm_cvx.io.staging import _zlib

    bufs = [b for r in raws for (_, _, bn, bq) in r[0] for b in (bn, bq)]
    nbytes = 2 * raws[0][1][0] * raws[0][1][1]
    mods = [zlib] if _zlib() is zlib else [zlib, _zlib()]
    for z in mods:
        for n in (1, 2):
            t = time.perf_counter()
            c = time.process_time()
            with ThreadPoolExecutor(n) as ex:
                inflated = list(ex.map(lambda b, z=z: z.decompress(b, 15, nbytes), bufs,
                                       chunksize=16))
            dt = time.perf_counter() - t
            out[f"inflate{n}:{z.__name__}"] = (mb / dt, mb / (time.process_time() - c), load())
    cr, cc, _, shuffled = raws[0][1]
    enc = raws[0][3]
    tables = N.decode_tables("AVHRR", N.DEFAULT_MASK_FLAGS["AVHRR"], enc)
    spans = [np.empty((r1 - r0, c1 - c0), np.float32) for _ in range(2)]
    seen = [np.zeros((r1 - r0, c1 - c0), bool) for _ in range(2)]
    tiles = [(r[0][i][0], r[0][i][1]) for r in raws for i in range(len(r[0]))]
    jobs = list(zip(tiles, inflated[0::2], inflated[1::2], strict=True))

    def dec(k):
        for (tr, tc), a, b in jobs[k::2]:
            i1, j1 = min(r1 - tr, cr), min(c1 - tc, cc)
            _decode_tile(np.frombuffer(a, np.uint8), np.frombuffer(b, np.uint8), shuffled, cc,
                         cr * cc, 0, i1, 0, j1, *tables, np.float32(np.nan), spans[k], tr, tc,
                         seen[k], True)

    dec(0)  # compile / load the kernel
    t = time.perf_counter()
    with ThreadPoolExecutor(2) as ex:
        list(ex.map(dec, (0, 1)))
    out["decode2"] = (mb / (time.perf_counter() - t), load())
    out["ratio"] = ratio
    out["write2"] = write_floor(scratch, len(files), cells, chunk_mb)
    return out


def write_floor(scratch: str, T: int, L: int, chunk_mb: float) -> tuple:
    """``pwrite`` of a ``(T, L)`` float32 matrix in the staging's layout and order (day by
    day, a row slice into every ``chunk_mb`` column file; 2 threads, one reused row buffer):
    the page-cache write cost alone, at full size (on this VM first-touched memory costs more
    than a small test shows). Returns (MB/s, MB/s per CPU-second, load)."""
    from concurrent.futures import ThreadPoolExecutor

    from lrm_cvx.io.staging import _bounds, _new_files, _pwrite_all

    d = tempfile.mkdtemp(prefix="write-floor-", dir=scratch)
    try:
        bounds = _bounds(L, T, chunk_mb)
        files, offsets = _new_files(d, T, bounds)
        row = np.random.default_rng(0).random(L, dtype=np.float32)

        def days(k):
            fds = [os.open(p, os.O_WRONLY) for p in files]
            try:
                for t in range(k, T, 2):
                    for c, fd in enumerate(fds):
                        lo, hi = int(bounds[c]), int(bounds[c + 1])
                        _pwrite_all(fd, row[lo:hi], offsets[c] + t * (hi - lo) * 4)
            finally:
                for fd in fds:
                    os.close(fd)

        t = time.perf_counter()
        c = time.process_time()
        with ThreadPoolExecutor(2) as ex:
            list(ex.map(days, (0, 1)))
        dt, cpu = time.perf_counter() - t, time.process_time() - c
    finally:
        shutil.rmtree(d, ignore_errors=True)
    mb = T * L * 4 / 2**20
    return mb / dt, mb / cpu, load()


def print_floors(fl: dict, files: list[str]) -> None:
    if "disk" not in fl:
        print(f"floors: not measured ({fl.get('note')})")
        return
    print(f"raw floors, MB/s of staged float32 (files are {fl['ratio']:.1f}x smaller than "
          "the float32 they hold):")
    print(f"  disk, cold cache, 1 reader: {fl['disk'][0]:.0f} MB/s of file bytes = "
          f"{fl['disk'][1]:.0f} MB/s float32  [{fl['disk'][2]}]")
    print(f"  h5py raw-chunk reads, page cache, serial: {fl['chunks'][0]:.0f} MB/s  "
          f"[{fl['chunks'][1]}]")
    for k in sorted(k for k in fl if k.startswith("inflate")):
        n, mod = k[len("inflate"):].split(":")
        print(f"  inflate with {mod}, {n} thread(s): {fl[k][0]:.0f} MB/s ({fl[k][1]:.0f} MB/s "
              f"per CPU-second)  [{fl[k][2]}]")
    print(f"  compiled decode + OR, 2 threads: {fl['decode2'][0]:.0f} MB/s  "
          f"[{fl['decode2'][1]}]")
    print(f"  pwrite of the whole matrix into the page cache (staging layout and order), "
          f"2 threads: {fl['write2'][0]:.0f} MB/s ({fl['write2'][1]:.0f} MB/s per CPU-second)"
          f"  [{fl['write2'][2]}]")


def stage_only(files: list[str], args, base: str) -> None:
    """Open the files lazily and stage them (no fit); print MB/s, the split, the CPU seconds
    and the load next to the raw floors."""
    import xarray as xr  # noqa: F401

    from lrm_cvx.io import open_ndvi_cdr, staging
    from lrm_cvx.io.staging import cdr_source, stage

    if args.stdlib_zlib:
        import zlib

        staging._zlib = lambda: zlib
    print(f"inflating with {staging._zlib().__name__}")
    if args.floors:
        print_floors(floors(files, base, args.chunk_mb), files)
    da = open_ndvi_cdr(files, chunks={"time": 1})
    assert cdr_source(da) is not None
    print(f"before staging: {load()}", flush=True)
    with TreeRSS() as rss:
        tm: dict = {}
        cpu = cpu_seconds()
        t = time.perf_counter()
        store, region, *_ = stage(da, chunk_mb=args.chunk_mb, scratch_dir=base, timings=tm)
        total = time.perf_counter() - t
        cpu = cpu_seconds() - cpu
    T, L = store.n_times, store.n_cells
    nbytes = T * L * 4
    try:
        gb = nbytes / 2**30
        print(f"L = {L} cells, T = {T}: float32 matrix {gb:.2f} GiB in "
              f"{store.n_chunks} column chunks")
        print(f"staging (file level, region found in the same pass): {total:.1f} s = "
              f"{nbytes / 2**20 / total:.0f} MB/s of staged float32 "
              f"(target >= 120 MB/s); peak RSS of the process tree {rss.peak / 2**30:.2f} GiB")
        print(f"  CPU {cpu:.1f} s = {cpu / gb:.2f} CPU-s per GiB ({cpu / total:.2f} cores busy "
              f"on average); with both cores to itself: ~{cpu / 2:.0f} s = "
              f"{nbytes / 2**20 / (cpu / 2):.0f} MB/s; after staging: {load()}")
        print(stage_split(tm, nbytes))
    finally:
        shutil.rmtree(store.directory, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="quick smoke run")
    ap.add_argument("--days", type=int, default=365)
    ap.add_argument("--ny", type=int, default=2000)
    ap.add_argument("--nx", type=int, default=4000)
    ap.add_argument("--land-fraction", type=float, default=1.0,
                    help="share of grid cells ever observed (1.0: the matrix is T x ny*nx)")
    ap.add_argument("--rounds", type=int, default=3, help="max_iter of the fit (tol=0)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--memory-limit", default="2GiB", help="per dask worker")
    ap.add_argument("--chunk-mb", type=float, default=128.0)
    ap.add_argument("--block-mb", type=float, default=256.0, help="input read per staging block")
    ap.add_argument("--scratch", default=None, help="directory for files and the column store")
    ap.add_argument("--files", default=None, help="reuse daily files in this folder (not removed)")
    ap.add_argument("--stage-only", action="store_true",
                    help="only stage the files into column chunks (file-level path) and print "
                         "MB/s with the read / decode / write split; no cluster, no fit")
    ap.add_argument("--stdlib-zlib", action="store_true",
                    help="inflate with the standard library's zlib even when isal is installed")
    ap.add_argument("--floors", action="store_true",
                    help="with --stage-only: first measure the raw floors (cold disk read, "
                         "h5py chunk reads, zlib inflate on 1 and 2 threads, decode)")
    ap.add_argument("--cluster", action="store_true",
                    help="with --stage-only: stage on the LocalCluster's workers, not threads")
    args = ap.parse_args()
    if args.small:
        args.days, args.ny, args.nx, args.rounds = 40, 120, 200, 3
        args.memory_limit, args.chunk_mb, args.block_mb = "512MiB", 1.0, 1.0

    import resource

    import dask.array as dsa
    import distributed

    from lrm_cvx.glrm import GLRM

    base = tempfile.mkdtemp(prefix="lrm-bench-dask-", dir=args.scratch)
    print(f"scratch {base}; grid {args.ny} x {args.nx}, {args.days} days, land fraction "
          f"{args.land_fraction}; {args.workers} workers x 1 thread, memory_limit "
          f"{args.memory_limit}; chunk_mb {args.chunk_mb}, block_mb {args.block_mb}", flush=True)
    try:
        if args.files:
            files = sorted(glob.glob(os.path.join(args.files, "*.nc")))
            print(f"reusing {len(files)} files in {args.files}")
        else:
            files_dir = os.path.join(base, "files")
            os.makedirs(files_dir)
            t = time.perf_counter()
            files = write_days(files_dir, args.days, (args.ny, args.nx),
                               land_fraction=args.land_fraction)
            print(f"write {len(files)} daily files: {time.perf_counter() - t:.1f} s", flush=True)
        size = sum(os.path.getsize(f) for f in files)
        print(f"daily files on disk: {size / 2**30:.2f} GiB", flush=True)
        if args.stage_only and not args.cluster:
            stage_only(files, args, base)
            return
        import dask

        # distributed's default MALLOC_TRIM_THRESHOLD_=65536 unmaps every large temporary
        dask.config.set({"distributed.nanny.pre-spawn-environ":
                         {"MALLOC_TRIM_THRESHOLD_": str(2**30)}})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cluster = distributed.LocalCluster(
                n_workers=args.workers, threads_per_worker=1, processes=True,
                memory_limit=args.memory_limit, dashboard_address=None)
        client = distributed.Client(cluster)
        try:
            with TreeRSS() as rss:
                base_rss = rss.sample()
                da, how = open_days(files)
                print(f"opened with {how}: {da.shape} {da.dtype}, chunks {da.data.chunksize}",
                      flush=True)
                opts = {"chunk_mb": args.chunk_mb, "block_mb": args.block_mb, "scratch_dir": base}
                t = time.perf_counter()  # warm-up: numba compiles in every worker
                warm = dsa.from_array(np.random.default_rng(0).random((20, 2000)), chunks=5)
                GLRM(rank=5, max_iter=1, tol=0, progress=False, dask=opts).fit(warm)
                print(f"warm-up (compile in the workers): {time.perf_counter() - t:.1f} s",
                      flush=True)
                if args.stage_only:
                    stage_only(files, args, base)
                    return
                rss.peak = 0
                timings: dict = {}
                t = time.perf_counter()
                m = GLRM(rank=5, max_iter=args.rounds, tol=0, random_state=0, progress=False,
                         dask={**opts, "timings": timings})
                m.fit(da)
                total = time.perf_counter() - t
            L, T = m.n_cells_, m.n_times_
            gib = T * L * 4 / 2**30
            rounds = timings["rounds"]
            print(f"L = {L} cells, T = {T}: float32 matrix {gib:.2f} GiB "
                  f"(+ mask {T * L / 2**30:.2f} GiB as bool)")
            print(f"region reduction + streaming stage: {timings['stage']:.1f} s "
                  f"({T * L * 4 / 2**20 / timings['stage']:.0f} MB/s of staged float32)")
            if "stage_read" in timings:
                print(stage_split(timings, T * L * 4))
            print(f"statistics + randomized-SVD init: {timings['init']:.1f} s")
            print(f"rounds (Y step + X step): {', '.join(f'{r:.1f}' for r in rounds)} s; "
                  f"mean {np.mean(rounds):.1f} s per round")
            print(f"final objective pass + Y gather: {timings['final']:.1f} s; fit total "
                  f"{total:.1f} s")
            print(f"objective {m.objective_[0]:.6g} -> {m.objective_[-1]:.6g}, "
                  f"noise_std {m.noise_std_:.4f}")
            client_hwm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
            print(f"peak RSS of the process tree during the fit: {rss.peak / 2**30:.2f} GiB "
                  f"(tree at start {base_rss / 2**30:.2f} GiB; client process high-water mark "
                  f"{client_hwm:.2f} GiB); data / peak = {gib / (rss.peak / 2**30):.2f}")
        finally:
            client.close()
            cluster.close()
    finally:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
