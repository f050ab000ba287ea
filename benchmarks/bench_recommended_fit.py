"""The recommended fit at paper scale: what its validations cost beside the fit itself.

    python benchmarks/bench_recommended_fit.py            # 310 days x 1500 x 1400 (2.1M cells)
    python benchmarks/bench_recommended_fit.py --whole    # the validations over every cell
    python benchmarks/bench_recommended_fit.py --quick --max-cells 5000   # 60 x 200 x 150
    python benchmarks/bench_recommended_fit.py --rank auto   # the rank validated too
    python benchmarks/bench_recommended_fit.py --dask        # the out-of-core fit

A planted daily record (``synthetic_field``: rank 5, every cell land (as ``bench_glrm.py``), 30 %
of the values missing, noise 0.05) as
a ``(time, lat, lon)`` DataArray, fitted with ``GLRM(**GLRM.recommended_params(), rank=5)``
(offset, ``spatial="auto"``, ``temporal="auto"``, the conformal calibration) in three timed
stages, each with the peak RSS of the process during it:

1. the fit with ``temporal="auto"`` and no calibration (the factors, the offset, the kernel's
   choice and the temporal selection);
2. ``select_temporal`` once more on that model, alone (its time is taken off stage 1's: the
   ``fit`` line is the fit without its validations);
3. ``calibrate_with`` (the recommended calibration) on that model.

The two validations refit the model on parts of the record. Above
``refits.VALIDATION_MAX_CELLS`` cells (200,000) they read a window of the grid holding that
many cells (``refits.validation_window``); ``--whole`` lifts the cap (every cell),
``--max-cells N`` sets it. The choice and the calibration's thresholds are printed, so the
two runs can be compared. With ``--rank auto`` the rank is chosen with the temporal model on
a reference fit (of the window) before the real fit, and stage 2 is
not run: the ``fit`` line then includes its validations. Figures: docs/benchmarks.md, "The
recommended fit at paper scale".
"""

from __future__ import annotations

import argparse
import gc
import time
import warnings

import numpy as np
import xarray as xr
from bench_glrm import PeakRSS, rss_gib


def planted_record(quick: bool = False) -> xr.DataArray:
    """The planted daily record ``(time, lat, lon)`` of the recommended setting's paper-scale
    benchmarks: ``synthetic_field`` of 310 days x 1500 x 1400 (``quick``: 60 x 200 x 150), rank
    5, every cell land, 30 % of the values missing, noise 0.05, days from 2000-01-01."""
    from lrm_cvx.io.samples import synthetic_field

    n_times, shape = (60, (200, 150)) if quick else (310, (1500, 1400))
    da = synthetic_field(n_times, shape, rank=5, missing=0.3, noise=0.05, land_fraction=1.0,
                         seed=0)
    return da.assign_coords(time=np.datetime64("2000-01-01", "ns")
                            + np.arange(n_times) * np.timedelta64(1, "D"))


def main() -> None:
    from lrm_cvx import GLRM
    from lrm_cvx.validation import refits
    from lrm_cvx.validation.calibration import calibrate_with
    from lrm_cvx.validation.selection import select_temporal

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="60 days x 200 x 150 cells")
    ap.add_argument("--whole", action="store_true",
                    help="validate on every cell (no window)")
    ap.add_argument("--max-cells", type=int, default=None,
                    help="refits.VALIDATION_MAX_CELLS for this run")
    ap.add_argument("--dask", action="store_true", help="the record as a dask array (chunks "
                    "of 16 days): the out-of-core fit")
    ap.add_argument("--rank", default="5", help="the rank: an integer, or auto (validated "
                    "with the temporal model, on a reference fit)")
    a = ap.parse_args()
    if a.whole:
        refits.VALIDATION_MAX_CELLS = 10**12
    elif a.max_cells is not None:
        refits.VALIDATION_MAX_CELLS = int(a.max_cells)
    t0 = time.perf_counter()
    da = planted_record(a.quick)
    n_times, shape = da.sizes["time"], da.shape[1:]
    if a.dask:
        da = da.chunk({"time": 16})
    print(f"data: {n_times} days x {shape} grid, {da.dtype}, generated in "
          f"{time.perf_counter() - t0:.1f} s; RSS {rss_gib():.2f} GiB", flush=True)
    warnings.simplefilter("ignore")
    w = np.random.default_rng(0).random((8, 60)).astype(np.float32)  # numba warm-up
    GLRM(rank=2, max_iter=2, progress=False).fit(w, mask=w > 0.2)
    rank = a.rank if a.rank == "auto" else int(a.rank)
    params = {**GLRM.recommended_params(), "rank": rank, "random_state": 0, "progress": False}
    cal = params.pop("calibration")
    secs, peaks = {}, {}

    def timed(stage, run):
        gc.collect()
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            out = run()
            secs[stage], peaks[stage] = time.perf_counter() - t0, pk.peak
        return out

    model = timed("fit", lambda: GLRM(**params).fit(da))
    window = refits.validation_window(model.region_, refits.VALIDATION_MAX_CELLS)
    cells = model.region_.n_cells if window is None else model.region_.crop(*window).n_cells
    print(f"  {model.region_.n_cells} cells; the validations read {cells} "
          f"({'every cell' if window is None else f'rows {window[0]}, cols {window[1]}'})",
          flush=True)
    if rank == "auto":  # the fit's selection ran on its reference fit: not separable
        stages = ("fit", "calibrate")
    else:
        stages = ("fit", "select_temporal", "calibrate")
        timed("select_temporal", lambda: select_temporal(model, da, seed=model.random_state))
    timed("calibrate", lambda: calibrate_with(model, da, cal))
    if "select_temporal" in secs:
        secs["fit"] -= secs["select_temporal"]  # the fit above ran the same selection
    for stage in stages:
        print(f"  {stage:16s} {secs[stage]:7.1f} s  peak RSS {peaks[stage]:.2f} GiB", flush=True)
    total = sum(secs.values())
    extra = secs.get("select_temporal", 0.0) + secs["calibrate"]
    share = ("" if rank == "auto"  # the fit line holds the rank's validation itself
             else f"; the validations {extra:.1f} s = {extra / secs['fit']:.2f} fits")
    print(f"recommended fit {total:.1f} s, peak RSS {max(peaks.values()):.2f} GiB{share}")
    c = model.calibration_
    line = (f"choice {model.selection_.attrs['choice']!r}, rank {model.rank_}, kernel "
            f"{model.spatial_cov_.model}; "
            f"conformal 68 / 95 % thresholds {c.quantiles[0]:.3f} / {c.quantiles[1]:.3f}")
    if c.temporal_quantiles:
        line += f" (filter {c.temporal_quantiles[0]:.3f} / {c.temporal_quantiles[1]:.3f})"
    print(line)


if __name__ == "__main__":
    main()
