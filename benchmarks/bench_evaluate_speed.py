"""Wall time of ``evaluate``: the library's temporal protocol and the shell's backtest.

Two rows, each with its reference measured in the same run (the machine is shared, so seconds
alone are noisy; the ratio is the figure):

* ``--library`` (default on): ``evaluate(data, temporal="auto")`` with its defaults (fit,
  validation and calibration included; 70 random walks) at budgets 15 / 30 / 60 from 4 starts
  on a 5,760-cell record of 46 monthly snapshots (``synthetic_field(46, (80, 100))`` with 72 %
  land, the placement benchmark's record), beside the memoryless protocol on the same record
  and settings (target: the temporal run <= 30 s).
* the shell's backtest: a record of the generalization benchmark (default: the planted
  regional warming record, 240 years x 1,813 cells) is written to a NetCDF file and
  ``lrm-cvx evaluate`` runs on it in this process with the recommended defaults and the
  paper's budgets (5 / 25 / 50 / 100 / 200), once memoryless and once with
  ``--temporal auto`` (the filter's campaigns, every route re-planned every day), the
  temporal run's ratio to the memoryless one printed. ``--origins 3 --temporal-starts 10
  --random-trials 10`` is the rolling-origin backtest of the docs (target: <= 300 s).

Usage::

    PYTHONPATH=benchmarks python benchmarks/bench_evaluate_speed.py
    PYTHONPATH=benchmarks python benchmarks/bench_evaluate_speed.py --no-library \
        --starts 2 --temporal-starts 1 --random-trials 70
    PYTHONPATH=benchmarks python benchmarks/bench_evaluate_speed.py --no-library --starts 0 \
        --temporal-starts 10 --random-trials 10 --origins 3
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import tempfile
import time
import warnings
from pathlib import Path

LIBRARY_BUDGETS = (15, 30, 60)
LIBRARY_STARTS = 4
LIBRARY_TARGET = 30.0  # seconds, the temporal run
BACKTEST_TARGET = 300.0  # seconds, the shell's rolling-origin backtest (3 origins, 10 starts)


def run(path: Path, out: Path, extra: list[str]) -> float:
    """Seconds of one ``lrm-cvx evaluate`` run (its printed table swallowed)."""
    from lrm_cvx.cli import main

    args = ["evaluate", str(path), "--out", str(out), "-q", "--overwrite", *extra]
    t = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(args)
    if code not in (0, None):
        raise SystemExit(f"lrm-cvx {' '.join(args)} failed ({code})")
    return time.perf_counter() - t


def library_record():
    """The 5,760-cell record of 46 monthly snapshots (rank 5, 10 % noise, 72 % land)."""
    from lrm_cvx.io.samples import synthetic_field

    return synthetic_field(46, (80, 100), 5, missing=0.0, noise=0.1, land_fraction=0.72,
                           seed=1)


def library_row(random_trials: int) -> None:
    """``evaluate(data, temporal="auto")`` with its defaults at budgets 15 / 30 / 60 from 4
    starts, and the memoryless protocol on the same record, timed in the same run."""
    from lrm_cvx import PlanningOptions, evaluate

    data = library_record()
    n_valid = int(data.notnull().any("time").sum())
    kw = {"budgets": LIBRARY_BUDGETS, "n_starts": LIBRARY_STARTS, "progress": False,
          "planning": PlanningOptions(random_trials=random_trials)}
    print(f"library: {data.sizes['time']} snapshots x {n_valid} cells, evaluate(data, ...) "
          f"with its defaults, budgets {LIBRARY_BUDGETS}, {LIBRARY_STARTS} starts, "
          f"{random_trials} random walks", flush=True)
    floor = None
    for label, extra in (("memoryless", {}), ('temporal="auto"', {"temporal": "auto"})):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t = time.perf_counter()
            evaluate(data, **kw, **extra)
            sec = time.perf_counter() - t
        floor = floor or sec
        verdict = ""
        if label != "memoryless":
            verdict = (f"  target <= {LIBRARY_TARGET:g} s: "
                       f"{'ok' if sec <= LIBRARY_TARGET else 'MISSED'}")
        print(f"  {label:18s} {sec:7.1f} s  ({sec / floor:4.2f} x the memoryless protocol)"
              + verdict, flush=True)


def shell_rows(args: argparse.Namespace) -> None:
    """The shell's ``lrm-cvx evaluate`` on a generalization record, memoryless and temporal."""
    from generalization_data import ALL_DATASETS

    data = ALL_DATASETS[args.data].loader()
    folder = Path(tempfile.mkdtemp(prefix="lrm-evaluate-speed-"))
    path = folder / f"{args.data}.nc"
    data.to_netcdf(path)
    n_valid = int(data.notnull().any("time").sum())
    print(f"{args.data}: {data.sizes['time']} snapshots x {n_valid} cells "
          f"(lrm-cvx evaluate, the paper's budgets, {args.random_trials} random walks, "
          f"--jobs {args.jobs}, --origins {args.origins})", flush=True)
    common = ["--random-trials", str(args.random_trials), "--jobs", str(args.jobs),
              "--origins", str(args.origins)]
    runs = []
    if args.starts:
        runs.append(("memoryless", args.starts, []))
    if args.temporal_starts:
        runs.append(("--temporal auto", args.temporal_starts, ["--temporal", "auto"]))
    per_start = {}
    for label, starts, extra in runs:
        seconds = run(path, folder / label.strip("-").replace(" ", "_"),
                      ["--starts", str(starts), *common, *extra])
        per_start[label] = seconds / starts
        line = f"  {label:16s} {starts} start(s): {seconds:7.1f} s"
        if label != "memoryless" and "memoryless" in per_start:
            line += (f"  ({per_start[label] / per_start['memoryless']:4.2f} x the memoryless "
                     "run per start)")
        if label != "memoryless" and args.origins == 3 and starts == 10:
            line += (f"  target <= {BACKTEST_TARGET:g} s: "
                     f"{'ok' if seconds <= BACKTEST_TARGET else 'MISSED'}")
        print(line, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--library", action=argparse.BooleanOptionalAction, default=True,
                    help="the evaluate(data, temporal='auto') row on the 5,760-cell record")
    ap.add_argument("--library-trials", type=int, default=70,
                    help="random walks of the library row (evaluate's default: 70)")
    ap.add_argument("--data", default="planted_regional_warming_yearly",
                    help="a record of generalization_data (ALL_DATASETS)")
    ap.add_argument("--starts", type=int, default=2,
                    help="starts of the shell's memoryless run (0: skip it)")
    ap.add_argument("--temporal-starts", type=int, default=1,
                    help="starts of the shell's --temporal auto run (0: skip it)")
    ap.add_argument("--random-trials", type=int, default=70)
    ap.add_argument("--origins", type=int, default=1,
                    help="rolling-origin blocks of the shell's runs (3: the docs' backtest)")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)
    if args.library:
        library_row(args.library_trials)
    if args.starts or args.temporal_starts:
        shell_rows(args)


if __name__ == "__main__":
    main()
