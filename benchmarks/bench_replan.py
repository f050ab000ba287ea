"""Replanning en route vs planning once a day (issue #25, item 2), on the bundled ``sst``.

Two closed gliders over the ocean (km budgets, ocean cells only, back home, measuring every cell
they pass), the filter (``temporal="ar1"``, recommended setting), the last ``--days`` snapshots
as the campaign, run by :func:`~lrm_cvx.campaign.simulate_campaign`. Each day:

* **once**: plan in the morning with the forecast as prior, fly it, assimilate every sample;
* **replan**: the same morning plan, but after every ``--every`` route entries the robots send
  what they measured, the state assimilates it and :func:`~lrm_cvx.replanning.replan` plans the
  rest (budget left, back home, same no-go cells): ``simulate_campaign(replan_every=...)``.

Printed per day and on average: the map's MSE after the day's samples (K^2), cells observed,
replans, the wall time of a day, and every flown route's brute-force feasibility check.

    python benchmarks/bench_replan.py [--days 8] [--every 4] [--budget 6000]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_glider_campaign import PATH, STARTS, infeasible

from lrm_cvx import GLRM, load_sample
from lrm_cvx.campaign import simulate_campaign


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=8)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--budget", type=float, default=6000.0)
    args = ap.parse_args()
    sst = load_sample("sst")
    train, test = sst.isel(time=slice(None, -args.days)), sst.isel(time=slice(-args.days, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                     progress=False).fit(train)
    budgets = [args.budget] * len(STARTS)
    runs, seconds = {}, {}
    for name, every in (("once", None), ("replan", args.every)):
        tic = time.perf_counter()
        runs[name] = simulate_campaign(model, test, STARTS, budgets,
                                       method="greedy:gp-variance", temporal="ar1",
                                       replan_every=every, **PATH)
        seconds[name] = (time.perf_counter() - tic) / args.days
    once, again = runs["once"], runs["replan"]
    for i in range(args.days):
        print(f"day {str(test.time.values[i])[:10]}: once MSE {once['mse'].values[i]:.4f} "
              f"({int(once['n_obs'].values[i])} cells) | replan MSE "
              f"{again['mse'].values[i]:.4f} ({int(again['n_obs'].values[i])} cells, "
              f"{int(again['n_replans'].values[i])} replans)")
    a, b = float(once["mse"].mean()), float(again["mse"].mean())
    better = int(np.sum(again["mse"].values < once["mse"].values))
    worse = int(np.sum(again["mse"].values > once["mse"].values))
    problems = infeasible(once, model.region_, budgets) + infeasible(again, model.region_,
                                                                     budgets)
    print(f"mean MSE over {args.days} days: once {a:.4f}, replan {b:.4f} "
          f"({100 * (a - b) / a:+.1f}% error cut by replanning; better on {better} days, worse "
          f"on {worse}); {float(again['n_replans'].mean()):.1f} replans a day; a day takes "
          f"{seconds['once']:.2f} s once, {seconds['replan']:.2f} s replanning; "
          + ("every route passed the brute-force feasibility check" if not problems
             else f"INFEASIBLE: {problems[:3]}"))


if __name__ == "__main__":
    main()
