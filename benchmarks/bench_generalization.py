"""Generalization benchmark (issue #24, item 5): the recommended setting on real records the
project has never seen.

    python benchmarks/bench_generalization.py            # every set, budgets 15/30/60,
                                                         # 10 starts, 5 random walks per start
    python benchmarks/bench_generalization.py --quick    # budget 15, 3 starts, 3 random walks
    python benchmarks/bench_generalization.py --data storm_slp_6hourly navy_uwnd_global_monthly

The data sets are those of ``benchmarks/generalization_data.py`` (data shipped inside PyPI and
Debian packages; that module's docstring has the install commands). Per set, the issue's
protocol: rank 5, the last 8 snapshots held out, the recommended setting (``offset=True,
spatial="exponential"``, empirical prior with kriging for every method's map,
``greedy:gp-variance``), against the four transects and the random walk from the same starts.

For each set one ``evaluate(..., temporal="ar1")`` runs a campaign over the 8 test snapshots per
start, budget and method, through the AR(1) filter and memoryless through the same loop (so
memoryless and ``ar1`` see the same starts and the same data); for monthly sets a second
``evaluate(..., temporal="seasonal")`` (month-of-year means plus AR(1) anomalies), and for every
set ``temporal="auto"`` (the choice validated on the training snapshots, glrm/selection.py; the
choice is printed). Each model is
fitted on the training snapshots with its ``temporal=`` (the fit's own validated blend towards
memoryless; ``select_dynamics`` and ``calibrate`` are *not* applied: this is what a new user gets
from the documented recommended setting). Printed per set and budget:

* test MSE of the greedy: memoryless, ``ar1``, ``seasonal``;
* per temporal mode the best baseline (lowest MSE among the transects and the random walk) and
  the greedy's relative difference to it (negative: the greedy wins);
* coverage of the 68 % / 95 % predictive intervals at the held-out (unsampled) observed cells
  of the greedy's maps, per temporal mode;
* ``ar1_vs_mem`` / ``seas_vs_mem``: the greedy's MSE change from memoryless (negative: better).

Cost: ``--quick`` 43-104 s wall (30-46 s CPU) for the six sets on the shared 2-core machine; full
run does about 12x the campaigns (3 budgets, 10 starts, 5 random walks), ~10-15 min on 2 idle
cores (estimate from the quick run's CPU time; ``--jobs 2`` runs evaluate's starts in parallel).

MSE is in the data's units squared. A final line per set gives the wall time. ``--out DIR`` also
writes every ``summary`` table as CSV.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import pandas as pd

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from generalization_data import DATASETS, SHORT_DATASETS, available, install_commands  # noqa: E402

warnings.filterwarnings("ignore")

RECOMMENDED = "greedy:gp-variance"
BASELINES = ("transect-up", "transect-down", "transect-left", "transect-right", "random")
RANK, N_TEST = 5, 8


def run_set(name: str, budgets: tuple, n_starts: int, random_trials: int,
            out: str | None = None, n_jobs: int = 1) -> tuple[pd.DataFrame, dict]:
    """Fit and evaluate one data set; returns the tidy table (one row per temporal mode, budget,
    method) and timings."""
    from lrm_cvx import GLRM, evaluate
    from lrm_cvx.evaluation import summary

    d = {**DATASETS, **SHORT_DATASETS}[name]
    data = d.loader()
    train = data.isel(time=slice(None, -N_TEST))
    modes = ["ar1"] + (["seasonal"] if d.seasonal else []) + ["auto"]
    frames, times = [], {}
    for temporal in modes:
        t0 = time.perf_counter()
        model = GLRM(rank=RANK, offset=True, spatial="exponential", temporal=temporal,
                     random_state=0, progress=False).fit(train)
        t1 = time.perf_counter()
        if temporal == "auto":
            print(f"[{name}] temporal='auto' chose {model.selection_.attrs['choice']!r}",
                  flush=True)
        res = evaluate(data, model=model, n_test=N_TEST, budgets=budgets, n_starts=n_starts,
                       methods=(RECOMMENDED,) + BASELINES, random_trials=random_trials,
                       min_observations=1, certify=False, progress=False, temporal=temporal,
                       seed=0, n_jobs=n_jobs, fold_in={"prior": "empirical", "spatial": True})
        times[temporal] = (t1 - t0, time.perf_counter() - t1)
        table = summary(res)
        table["set"] = name
        if out:
            os.makedirs(out, exist_ok=True)
            table.to_csv(os.path.join(out, f"{name}_{temporal}.csv"), index=False)
        # memoryless rows: the same campaigns, memoryless through the same loop (from the ar1 run)
        if temporal == "ar1":
            mem = table.copy()
            mem["temporal"] = "none"
            mem["mse_mean"] = mem["mse_memoryless_mean"]
            for c in ("68", "95"):
                mem[f"coverage{c}_mean"] = mem[f"coverage{c}_memoryless_mean"]
            frames.append(mem)
        frames.append(table)
    return pd.concat(frames, ignore_index=True), times


def report(name: str, tidy: pd.DataFrame) -> pd.DataFrame:
    """One row per budget: greedy MSE per temporal mode, best baseline, coverage."""
    rows = []
    for budget, by_budget in tidy.groupby("budget"):
        row = {"set": name, "budget": int(budget)}
        for temporal, t in by_budget.groupby("temporal", sort=False):
            t = t.set_index("method")
            g = float(t.loc[RECOMMENDED, "mse_mean"])
            base = t.loc[list(BASELINES), "mse_mean"].astype(float)
            best = base.idxmin()
            tag = {"none": "mem", "ar1": "ar1", "seasonal": "seas", "auto": "auto"}[temporal]
            row[f"greedy_{tag}"] = g
            row[f"best_base_{tag}"] = f"{float(base[best]):.4g} ({best.replace('transect-', 't-')})"
            row[f"vs_best_{tag}"] = f"{100 * (g / float(base[best]) - 1):+.0f}%"
            row[f"cov68/95_{tag}"] = (f"{float(t.loc[RECOMMENDED, 'coverage68_mean']):.2f}/"
                                      f"{float(t.loc[RECOMMENDED, 'coverage95_mean']):.2f}")
        for tag in ("ar1", "seas", "auto"):
            if f"greedy_{tag}" in row:
                change = row[f"greedy_{tag}"] / row["greedy_mem"] - 1
                row[f"{tag}_vs_mem"] = f"{100 * change:+.0f}%"
        rows.append(row)
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="budget 15 only, 3 starts, 3 random walks per start")
    ap.add_argument("--data", nargs="*", default=None,
                    help=f"data sets (default: all of {list(DATASETS)}; also "
                         f"{list(SHORT_DATASETS)})")
    ap.add_argument("--starts", type=int, default=None)
    ap.add_argument("--trials", type=int, default=None, help="random walks per start")
    ap.add_argument("--jobs", type=int, default=1, help="evaluate's n_jobs")
    ap.add_argument("--out", default=None, help="write the summary tables as CSV here")
    args = ap.parse_args()

    budgets = (15,) if args.quick else (15, 30, 60)
    n_starts = args.starts or (3 if args.quick else 10)
    trials = args.trials or (3 if args.quick else 5)
    names = args.data or list(DATASETS)
    ok = available()
    missing = [n for n in names if not ok.get(n, False)]
    if missing:
        print(f"not installed: {missing}; install with: {' ; '.join(install_commands())}")
        names = [n for n in names if n not in missing]

    print(f"rank {RANK}, last {N_TEST} snapshots held out, budgets {budgets}, {n_starts} starts, "
          f"{trials} random walks per start; greedy = {RECOMMENDED}, offset + exponential "
          "spatial residual, empirical prior with kriging", flush=True)
    t_all = time.perf_counter()
    tables = []
    for name in names:
        t0 = time.perf_counter()
        tidy, times = run_set(name, budgets, n_starts, trials, args.out, args.jobs)
        table = report(name, tidy)
        tables.append(table)
        with pd.option_context("display.width", 250, "display.max_columns", 30):
            print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
        fits = ", ".join(f"{k}: fit {a:.1f} s + evaluate {b:.0f} s" for k, (a, b) in times.items())
        print(f"[{name}] {time.perf_counter() - t0:.0f} s ({fits})\n", flush=True)
    print(f"total {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
