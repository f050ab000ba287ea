"""Out-of-core GLRM on dask: daily CDR-format files -> dask-backed DataArray -> GLRM.fit.

Writes ``--days`` synthetic daily NetCDF files (``lrm_cvx.io.samples.write_ndvi_cdr`` when
available, else an int16 + zlib CDR-like layout), opens them lazily (``open_ndvi_cdr`` when
available, else ``xarray.open_mfdataset``) with one chunk per day, and fits on a
``distributed.LocalCluster`` (processes, ``--workers`` x 1 thread, ``--memory-limit`` per worker).
Prints the seconds of each phase, seconds per round, and the peak resident memory of the whole
process tree (client + scheduler + workers; sampled with psutil every 0.2 s).

    flock /tmp/lrm-bench.lock /work/venv/bin/python benchmarks/bench_dask.py [--small]
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


def write_days(directory: str, days: int, shape: tuple[int, int], batch: int = 8) -> list[str]:
    """Daily files from ``synthetic_field`` generated ``batch`` days at a time (same seed: the
    same spatial modes and land mask; the time factors restart each batch)."""
    import pandas as pd

    from lrm_cvx.io import samples
    from lrm_cvx.io.samples import synthetic_field

    writer = getattr(samples, "write_ndvi_cdr", None)
    start = pd.Timestamp("2013-01-01")
    for d0 in range(0, days, batch):
        n = min(batch, days - d0)
        field = synthetic_field(n, shape, rank=5, seed=0,
                                start_date=start + pd.Timedelta(days=d0))
        if writer is not None:
            writer(directory, field)
        else:
            for i in range(n):
                day = field.isel(time=[i])
                stamp = pd.Timestamp(day.time.values[0]).strftime("%Y%m%d")
                enc = {"ndvi": {"dtype": "int16", "scale_factor": np.float32(1e-4),
                                "_FillValue": np.int16(-9999), "zlib": True, "complevel": 1}}
                day.to_dataset(name="ndvi").to_netcdf(
                    os.path.join(directory, f"AVHRR-Land_v005_NDVI_{stamp}.nc"), encoding=enc)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="quick smoke run")
    ap.add_argument("--days", type=int, default=365)
    ap.add_argument("--ny", type=int, default=2000)
    ap.add_argument("--nx", type=int, default=4000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--memory-limit", default="2GiB", help="per dask worker")
    ap.add_argument("--chunk-mb", type=float, default=128.0)
    ap.add_argument("--block-mb", type=float, default=64.0, help="input read per staging task")
    ap.add_argument("--scratch", default=None, help="directory for files and the column store")
    args = ap.parse_args()
    if args.small:
        args.days, args.ny, args.nx, args.rounds = 40, 120, 200, 3
        args.memory_limit, args.chunk_mb = "512MiB", 1.0

    import distributed

    from lrm_cvx.glrm import GLRM

    base = tempfile.mkdtemp(prefix="lrm-bench-dask-", dir=args.scratch)
    print(f"scratch {base}; grid {args.ny} x {args.nx}, {args.days} days, "
          f"{args.workers} workers x 1 thread, memory_limit {args.memory_limit}")
    try:
        files_dir = os.path.join(base, "files")
        os.makedirs(files_dir)
        t = time.perf_counter()
        files = write_days(files_dir, args.days, (args.ny, args.nx))
        t_write = time.perf_counter() - t
        size = sum(os.path.getsize(f) for f in files)
        print(f"write {len(files)} daily files: {t_write:.1f} s, {size / 2**30:.2f} GiB on disk")
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
                print(f"opened with {how}: {da.shape} {da.dtype}, chunks {da.data.chunksize}")
                opts = {"chunk_mb": args.chunk_mb, "block_mb": args.block_mb, "scratch_dir": base}
                t = time.perf_counter()  # warm-up: numba compiles in every worker
                import dask.array as dsa

                warm = dsa.from_array(np.random.default_rng(0).random((20, 2000)), chunks=5)
                GLRM(rank=5, max_iter=1, tol=0, progress=False, dask_options=opts).fit(warm)
                print(f"warm-up (compile in the workers): {time.perf_counter() - t:.1f} s")
                for label, iters in (("stage+init+1 round", 1),
                                     (f"stage+init+{args.rounds} rounds", args.rounds)):
                    t = time.perf_counter()
                    m = GLRM(rank=5, max_iter=iters, tol=0, random_state=0, progress=False,
                             dask_options=opts)
                    m.fit(da)
                    dt = time.perf_counter() - t
                    print(f"{label}: {dt:.1f} s")
                    if iters == 1:
                        t_one = dt
                    else:
                        per_round = (dt - t_one) / (iters - 1)
                L, T = m.n_cells_, m.n_times_
                gib = T * L * 4 / 2**30
                print(f"L = {L} cells, T = {T}: float32 matrix {gib:.2f} GiB "
                      f"(+ mask {T * L / 2**30:.2f} GiB as bool)")
                print(f"seconds per round (Y step + X step): {per_round:.1f} s")
                print(f"objective {m.objective_[0]:.6g} -> {m.objective_[-1]:.6g}, "
                      f"noise_std {m.noise_std_:.4f}")
            print(f"peak RSS of the process tree: {rss.peak / 2**30:.2f} GiB "
                  f"(at start {base_rss / 2**30:.2f} GiB); data / peak = "
                  f"{gib / (rss.peak / 2**30):.2f}")
        finally:
            client.close()
            cluster.close()
    finally:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
