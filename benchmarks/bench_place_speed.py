"""The default static placement's wall time: ``place_sensors(model, n, training=train)``.

    python benchmarks/bench_place_speed.py               # 15 and 30 sensors on both records
    python benchmarks/bench_place_speed.py --n 15        # one count
    python benchmarks/bench_place_speed.py --profile     # also the top of a cProfile

Two records, each fitted as ``bench_static.fit`` does (``GLRM(5, offset=True,
spatial=RECOMMENDED["spatial"])``, i.e. the residual's kernel validated) on all but the last 8
snapshots:

* ``monthly 5.8k``: the synthetic record of ``bench_placement.py``'s speed figures
  (``synthetic_field(46, (80, 100), 5, land_fraction=0.72)``: 5,760 cells, 38 training
  snapshots);
* ``yearly 1.8k``: ``planted_regional_warming_yearly`` of ``generalization_data.py`` (1,813
  cells, 232 training years).

Each count is placed by a fresh call with its defaults (``criterion="auto"``: the criterion
validated on the training snapshots, then run on the full model), and the seconds are printed
beside a **floor measured in the same run**: the one placement the default ends with, run
alone (``place_sensors(model, n, criterion=<chosen>, exchange=<chosen>)``, no validation), and
the ratio of the two. Target: <= 2 s for each count. The load average is printed at the start
and the end (the machine is shared: compare ratios).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_static import fit  # noqa: E402

from lrm_cvx.planning import place_sensors  # noqa: E402

HOLDOUT = 8
TARGET_S = 2.0


def records() -> dict:
    """``{name: training snapshots}`` of the two records (module docstring)."""
    from generalization_data import available, load

    from lrm_cvx.io.samples import synthetic_field

    out = {"monthly 5.8k": synthetic_field(46, (80, 100), 5, missing=0.0, noise=0.1,
                                           land_fraction=0.72, seed=1)}
    if available().get("planted_regional_warming_yearly", False):
        out["yearly 1.8k"] = load("planted_regional_warming_yearly")
    return {k: v.isel(time=slice(None, -HOLDOUT)) for k, v in out.items()}


def floor(model, train, n: int, choice: str) -> tuple[float, float]:
    """Wall and CPU seconds of the chosen criterion's placement alone (no validation)."""
    from lrm_cvx.planning.static_auto import AUTO_CANDIDATES

    crit, exchange = AUTO_CANDIDATES[choice]
    t0, c0 = time.perf_counter(), time.process_time()
    if crit == "risk":
        place_sensors(model, n, training=train, criterion="risk",
                      exchange=exchange == "auto" or bool(exchange))
    else:
        place_sensors(model, n, criterion=crit, exchange=bool(exchange))
    return time.perf_counter() - t0, time.process_time() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="*", default=[15, 30])
    ap.add_argument("--profile", action="store_true", help="print the top of a cProfile of "
                    "each call, sorted by cumulative time")
    args = ap.parse_args(argv)
    print(f"load average at start {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    for name, train in records().items():
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = fit(train)
        print(f"{name}: {model.region_.n_cells} cells, {train.sizes['time']} training "
              f"snapshots, fit {time.perf_counter() - t0:.1f} s", flush=True)
        for n in args.n:
            prof = cProfile.Profile() if args.profile else None
            t0, c0 = time.perf_counter(), time.process_time()
            if prof:
                prof.enable()
            plan = place_sensors(model, n, training=train)
            if prof:
                prof.disable()
            sec, cpu = time.perf_counter() - t0, time.process_time() - c0
            sel = plan.refinement["selection"]
            choice = sel.attrs["choice"]
            ref, ref_cpu = floor(model, train, n, choice)
            print(f"{name}: {n} sensors by the default in {sec:.2f} s, {cpu:.2f} CPU-s "
                  f"(validation {sel.attrs['seconds']:.2f} s; choice {choice}); floor (the "
                  f"chosen placement alone) {ref:.2f} s, {ref_cpu:.2f} CPU-s; ratio "
                  f"{sec / ref:.1f} (CPU {cpu / ref_cpu:.1f}); target <= "
                  f"{TARGET_S:g} s: {'ok' if sec <= TARGET_S else 'MISSED'}; cells "
                  f"{np.sort(plan.cells)[:6].tolist()}...", flush=True)
            if prof:
                pstats.Stats(prof).sort_stats("cumtime").print_stats(25)
    print(f"load average at end {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
