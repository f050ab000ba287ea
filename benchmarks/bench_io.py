"""Benchmark the data layer at paper scale: synthetic field, writers, loaders.

1. ``synthetic_field(310, (1500, 1400))`` (the paper's NDVI subset);
2. ``write_ndvi_cdr`` -> 310 daily AVHRR CDR files, then ``open_ndvi_cdr`` lazily
   (``chunks={"time": 1}``) with a bbox and the default QA mask, and one time mean computed;
3. ``write_image_stack`` of a 298 x 1076 x 1629 field (the Fall-foliage stack), then
   ``open_image_stack`` (eager, with cloud/edge/no-data masks) and its time mean.

Prints seconds per step and the peak RSS. ``--small`` runs a quick smoke version.
Run under the shared lock: ``flock /tmp/lrm-bench.lock python benchmarks/bench_io.py``.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from lrm_cvx.io.imagery import field_bbox, open_image_stack, write_image_stack
from lrm_cvx.io.ndvi import open_ndvi_cdr
from lrm_cvx.io.samples import synthetic_field, write_ndvi_cdr


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def step(label: str, t0: float) -> float:
    now = time.perf_counter()
    print(f"{label:<48s} {now - t0:8.2f} s   peak RSS {peak_rss_gb():6.2f} GB", flush=True)
    return now


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--small", action="store_true", help="quick smoke run")
    args = parser.parse_args()
    if args.small:
        ndvi_shape, n_ndvi, img_shape, n_img = (150, 140), 20, (108, 163), 20
    else:
        ndvi_shape, n_ndvi, img_shape, n_img = (1500, 1400), 310, (1076, 1629), 298
    root = Path(tempfile.mkdtemp(prefix="lrm-bench-io-"))
    try:
        t = time.perf_counter()
        field = synthetic_field(n_ndvi, ndvi_shape, seed=0)
        t = step(f"synthetic_field {n_ndvi} x {ndvi_shape}", t)
        paths = write_ndvi_cdr(root / "cdr", field)
        t = step(f"write_ndvi_cdr {len(paths)} files", t)
        size_mb = sum(p.stat().st_size for p in paths) / 1e6
        print(f"  CDR files on disk: {size_mb:.0f} MB")
        bbox = field_bbox(field)  # outer edges: every cell centre is inside
        del field
        da = open_ndvi_cdr(str(root / "cdr" / "*.nc"), bbox=bbox, chunks={"time": 1})
        t = step(f"open_ndvi_cdr lazily {dict(da.sizes)}", t)
        mean = da.mean("time").values
        t = step("  time mean computed (dask)", t)
        print(f"  mean NDVI over the map: {np.nanmean(mean):.4f}")
        del da, mean

        t = time.perf_counter()
        field = synthetic_field(n_img, img_shape, seed=1, lat_range=(40.0, 48.0),
                                lon_range=(-80.0, -66.0))
        t = step(f"synthetic_field {n_img} x {img_shape}", t)
        paths = write_image_stack(root / "img", field, vmin=-0.2, vmax=1.0)
        t = step(f"write_image_stack {len(paths)} png", t)
        size_mb = sum(p.stat().st_size for p in paths) / 1e6
        print(f"  images on disk: {size_mb:.0f} MB")
        bbox = field_bbox(field)
        del field
        hue = open_image_stack(root / "img", bbox)
        t = step(f"open_image_stack {dict(hue.sizes)}", t)
        mean = hue.mean("time").values
        t = step("  time mean computed", t)
        print(f"  masked fraction: {float(np.isnan(hue.values).mean()):.3f}")
        del hue, mean
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"peak RSS {peak_rss_gb():.2f} GB")


if __name__ == "__main__":
    main()
