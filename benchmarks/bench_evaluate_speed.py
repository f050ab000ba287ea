"""Wall time of the shell's backtest, ``lrm-cvx evaluate``, as a new user runs it.

A record of the generalization benchmark (default: the planted regional warming record, 240
years x 1,813 cells) is written to a NetCDF file and ``lrm-cvx evaluate`` runs on it in this
process with the recommended defaults and the paper's protocol (budgets 5 / 25 / 50 / 100 /
200, 70 random walks per start), once memoryless and once with ``--temporal auto`` (the
filter's campaigns, every route re-planned every day). Fewer starts than the protocol's 10 keep
it a few minutes; the time per start is what scales.

Usage::

    PYTHONPATH=benchmarks python benchmarks/bench_evaluate_speed.py
    PYTHONPATH=benchmarks python benchmarks/bench_evaluate_speed.py --data sst_tropics_monthly \
        --starts 2 --temporal-starts 1 --random-trials 70
"""

from __future__ import annotations

import argparse
import contextlib
import io
import tempfile
import time
from pathlib import Path


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="planted_regional_warming_yearly",
                    help="a record of generalization_data (ALL_DATASETS)")
    ap.add_argument("--starts", type=int, default=2, help="starts of the memoryless run")
    ap.add_argument("--temporal-starts", type=int, default=1,
                    help="starts of the --temporal auto run (0: skip it)")
    ap.add_argument("--random-trials", type=int, default=70)
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()

    from generalization_data import ALL_DATASETS

    data = ALL_DATASETS[args.data].loader()
    folder = Path(tempfile.mkdtemp(prefix="lrm-evaluate-speed-"))
    path = folder / f"{args.data}.nc"
    data.to_netcdf(path)
    n_valid = int(data.notnull().any("time").sum())
    print(f"{args.data}: {data.sizes['time']} snapshots x {n_valid} cells "
          f"(lrm-cvx evaluate, the paper's budgets, {args.random_trials} random walks, "
          f"--jobs {args.jobs})")
    common = ["--random-trials", str(args.random_trials), "--jobs", str(args.jobs)]
    runs = [("memoryless", args.starts, [])]
    if args.temporal_starts:
        runs.append(("--temporal auto", args.temporal_starts, ["--temporal", "auto"]))
    for label, starts, extra in runs:
        seconds = run(path, folder / label.strip("-").replace(" ", "_"),
                      ["--starts", str(starts), *common, *extra])
        print(f"  {label:16s} {starts} start(s): {seconds:7.1f} s")


if __name__ == "__main__":
    main()
