"""The paper's full evaluation protocol at paper scale: wall time and peak memory.

Synthetic NDVI-like data of the paper's NDVI size (310 days over a 1500 x 1400 grid with a land
mask), optionally written as real NOAA CDR daily files and read back with ``open_ndvi_cdr``
(``--via-files``), then ``evaluate`` with the paper's settings: rank 5, 8 test snapshots,
budgets 5, 25, 50, 100, 200, 10 starts, 70 random-walk trials, all methods, certified bounds.

Usage::

    python benchmarks/bench_protocol.py            # paper scale (target: <= 15 min on 2 cores)
    python benchmarks/bench_protocol.py --small    # 60 days over 300 x 280, a smoke run
    python benchmarks/bench_protocol.py --sample   # the bundled real sample (sst)
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true")
    ap.add_argument("--sample", action="store_true")
    ap.add_argument("--via-files", action="store_true",
                    help="write CDR files and read them with open_ndvi_cdr")
    ap.add_argument("--certify", default="fast", choices=["fast", "tight", "none"])
    ap.add_argument("--out", default="benchmarks/output/protocol")
    args = ap.parse_args()

    from lrm_cvx import evaluate, load_sample, summary
    from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, save_results
    from lrm_cvx.io.samples import synthetic_field

    t0 = time.perf_counter()
    if args.sample:
        data = load_sample("sst")
        budgets, label = (5, 10, 20, 40), "sample sst (real)"
    else:
        n_times, shape = (60, (300, 280)) if args.small else (310, (1500, 1400))
        data = synthetic_field(n_times, shape, rank=5, missing=0.5, seed=0)
        label = f"synthetic NDVI {n_times} x {shape[0]} x {shape[1]}"
        if args.via_files:
            from lrm_cvx.io.ndvi import open_ndvi_cdr
            from lrm_cvx.io.samples import write_ndvi_cdr

            folder = Path(tempfile.mkdtemp(prefix="lrm-cdr-"))
            t = time.perf_counter()
            write_ndvi_cdr(folder, data, "2013-01-01")
            del data
            print(f"wrote CDR files in {time.perf_counter() - t:.1f} s to {folder}")
            t = time.perf_counter()
            data = open_ndvi_cdr(str(folder / "AVHRR-Land_*.nc")).load()
            print(f"read CDR files in {time.perf_counter() - t:.1f} s")
        budgets = (5, 25, 50, 100, 200)
    t_data = time.perf_counter() - t0
    print(f"{label}: data ready in {t_data:.1f} s, {float(np.isnan(data).mean()):.0%} missing")

    t1 = time.perf_counter()
    certify = False if args.certify == "none" else args.certify
    results = evaluate(data, rank=5, n_test=8, budgets=budgets, n_starts=10, seed=0,
                       progress=True, paper=True,
                       planning=PlanningOptions(random_trials=70, certify=certify),
                       scoring=ScoringOptions(min_observations=10))  # the paper's (Figs. 4-5)
    t_eval = time.perf_counter() - t1
    save_results(results, args.out)
    table = summary(results)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    info = table.pivot(index="budget", columns="method", values="information_mean")
    mse = table.pivot(index="budget", columns="method", values="mse_mean")
    base = [m for m in info.columns if m != "greedy"]
    wins_info = (info["greedy"].to_numpy()[:, None] > info[base].to_numpy()).all(axis=1)
    wins_mse = (mse["greedy"].to_numpy()[:, None] < mse[base].to_numpy()).all(axis=1)
    for b, wi, wm in zip(info.index, wins_info, wins_mse, strict=True):
        print(f"budget {b:6g}: greedy beats every baseline in information: {bool(wi)}; "
              f"in reconstruction MSE: {bool(wm)}")
    gap = (results["bound"] - results["information"].sel({"method": "greedy"}).isel(trial=0))
    print("certified gap of the greedy plans (nats), mean per budget:",
          {float(b): round(float(g), 3) for b, g in zip(results["budget"].values,
                                                         gap.mean("start").values, strict=True)})
    print(f"\nevaluate: {t_eval:.1f} s; total {time.perf_counter() - t0:.1f} s; "
          f"peak RSS {peak_gib():.2f} GiB")


if __name__ == "__main__":
    main()
