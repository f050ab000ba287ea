"""On the bundled ``sst`` sample: a glider fleet's closed campaign in km.

``evaluate`` with ``metric="km"``, ``traversable="valid"`` (the gliders stay in the ocean),
``closed=True`` (each returns to its deployment cell) and ``n_robots=2`` (budget per robot):
the recommended setting (``greedy:gp-variance`` on ``GLRM(offset=True, spatial="exponential")``
with the empirical-prior kriged fold-in) against every baseline (transects and the random walk
under the same path model, predicted with the same fold-in). Also one glider vs two.
Prints the MSE table (data units, K^2) and whether the recommended greedy beats every baseline at
every budget (target: yes).

Usage::

    flock /tmp/bench.lock python benchmarks/bench_campaign.py            # 10 starts, 20 trials
    flock /tmp/bench.lock python benchmarks/bench_campaign.py --quick    # 4 starts, 5 trials
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

BASELINES = ("transect-up", "transect-down", "transect-left", "transect-right", "random")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--budgets", default="2000,4000,8000,16000", help="km per robot")
    ap.add_argument("--robots", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from lrm_cvx import load_sample
    from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate, summary
    from lrm_cvx.glrm import GLRM
    from lrm_cvx.planning import PathOptions

    budgets = tuple(float(b) for b in args.budgets.split(","))
    n_starts, trials = (4, 5) if args.quick else (10, 20)
    data = load_sample("sst")
    n_test, rank = 8, 5
    train = data.isel(time=slice(None, -n_test))
    t0 = time.perf_counter()
    rec = GLRM(rank, offset=True, spatial="exponential", random_state=args.seed,
               progress=False).fit(train)
    path = dict(metric="km", traversable="valid", closed=True)
    common = dict(rank=rank, n_test=n_test, budgets=budgets, n_starts=n_starts,
                  seed=args.seed, progress=False,
                  model=rec,
                  path=PathOptions(**path),
                  planning=PlanningOptions(random_trials=trials, certify=False),
                  scoring=ScoringOptions(min_observations=1,
                                         fold_in={"prior": "empirical", "spatial": True}))
    pd.set_option("display.width", 200)
    results = {}
    for n_robots in sorted({1, args.robots}):
        t = time.perf_counter()
        ds = evaluate(data, methods=("greedy:gp-variance", *BASELINES), n_robots=n_robots,
                      **common)
        results[n_robots] = ds
        print(f"\n== {n_robots} robot(s), {summary(ds)['path'].iloc[0]}: "
              f"{time.perf_counter() - t:.1f} s")
        table = summary(ds).pivot(index="budget", columns="method", values="mse_mean")
        table = table[["greedy:gp-variance", *BASELINES]]
        print("MSE (K^2) per budget (km per robot):")
        print(table.to_string(float_format=lambda v: f"{v:.4f}"))
        best = table[list(BASELINES)].min(axis=1)
        beats = table["greedy:gp-variance"] < best
        print("recommended greedy beats every baseline: "
              + ", ".join(f"{b:g} km {'yes' if ok else 'NO'} (best baseline "
                          f"{table[list(BASELINES)].loc[b].idxmin()} {best.loc[b]:.4f})"
                          for b, ok in beats.items()))
        # routes stay in the ocean and return; each robot within its budget
        cost = ds["robot_cost"] if "robot_cost" in ds else ds["cost"].expand_dims(robot=[0])
        over = float((cost - ds["budget"]).max())
        print(f"largest robot cost - budget: {over:.3g} km (<= 0: within budget)")
    if len(results) == 2:
        one, two = (summary(results[n]).set_index(["method", "budget"]) for n in
                    sorted(results))
        g = "greedy:gp-variance"
        rows = pd.DataFrame({
            "mse 1 glider": one.loc[g]["mse_mean"], f"mse {args.robots} gliders":
            two.loc[g]["mse_mean"], "cells 1": one.loc[g]["mean_cells"],
            f"cells {args.robots}": two.loc[g]["mean_cells"]})
        print(f"\nrecommended greedy, 1 vs {args.robots} gliders:")
        print(rows.to_string(float_format=lambda v: f"{v:.4f}"))
    print(f"\ntotal {time.perf_counter() - t0:.1f} s; complete-data floor "
          f"{float(np.nanmean(results[args.robots]['complete_mse'])):.4f} K^2")


if __name__ == "__main__":
    main()
