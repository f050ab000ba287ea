"""Replanning en route vs planning once a day (issue #25, item 2), on the bundled ``sst``.

Two closed gliders over the ocean (km budgets, ocean cells only, back home), the filter
(``temporal="ar1"``, recommended setting), the last ``--days`` snapshots as the campaign. Each day:

* **once**: plan in the morning with the forecast as prior, fly it, assimilate every sample;
* **replan**: the same morning plan, but after every ``--every`` route entries the robots send
  what they measured, the state assimilates it and :meth:`MonitorState.replan` plans the rest
  (budget left, back home, same no-go cells).

Printed per day and on average: the map's MSE after the day's samples (K^2), samples taken,
replans and their mean time, and every route's brute-force feasibility check.

    python benchmarks/bench_replan.py [--days 8] [--every 4] [--budget 6000]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from lrm_cvx import GLRM, load_sample, plan_greedy
from lrm_cvx.monitor import MonitorState
from lrm_cvx.replanning import route_feasible

STARTS = [(10.0, 200.0), (-20.0, 240.0)]
PATH = {"metric": "km", "traversable": "valid", "closed": True}


def _mse(state, truth):
    mean = state.model.region_.stack(state.predict()["mean"])
    ok = np.isfinite(truth)
    return float(np.mean((mean[ok] - truth[ok]) ** 2))


def run_day(state, model, day, budget, every, replan):
    region = model.region_
    t = day.time.values
    truth = region.stack(day)
    prior = state.planner_kwargs(time=t)
    plan = plan_greedy(model.Y_, region, STARTS, budget, criterion="gp-variance",
                       initial="start", progress=False, **prior, **PATH)
    assert route_feasible(plan, region) == []
    sizes = [int(np.count_nonzero(plan.route_robot == r)) for r in range(plan.n_robots)]
    done = [1] * plan.n_robots
    sent = [0] * plan.n_robots  # route entries already assimilated
    n_replans, seconds = 0, 0.0
    while replan and any(d < s for d, s in zip(done, sizes, strict=True)):
        done = [min(d + every, s) for d, s in zip(done, sizes, strict=True)]
        new = [plan.route[plan.route_robot == r][sent[r]:done[r]] for r in range(plan.n_robots)]
        cells = np.concatenate(new)
        sent = list(done)
        tic = time.perf_counter()
        plan = state.replan(plan, done, (cells, truth[cells]), time=t, criterion="gp-variance")
        seconds += time.perf_counter() - tic
        n_replans += 1
        assert route_feasible(plan, region) == [], "a replanned route broke the path model"
        sizes = [int(np.count_nonzero(plan.route_robot == r)) for r in range(plan.n_robots)]
    rest = np.concatenate([plan.route[plan.route_robot == r][sent[r]:]
                           for r in range(plan.n_robots)]) if replan else plan.route
    if rest.size:
        state.assimilate((rest, truth[rest]), t, force=state.observed and state._dt(t) == 0)
    return _mse(state, truth), len(plan.stops), n_replans, seconds


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
    states = {"once": MonitorState.from_model(model), "replan": MonitorState.from_model(model)}
    rows = []
    for i in range(args.days):
        day = test.isel(time=i)
        row = {}
        for name, state in states.items():
            row[name] = run_day(state, model, day, args.budget, args.every,
                                replan=name == "replan")
        rows.append(row)
        print(f"day {str(day.time.values)[:10]}: once MSE {row['once'][0]:.4f} "
              f"({row['once'][1]} stops) | replan MSE {row['replan'][0]:.4f} "
              f"({row['replan'][1]} stops, {row['replan'][2]} replans, "
              f"{row['replan'][3] / max(row['replan'][2], 1):.2f} s each)")
    once = np.mean([r["once"][0] for r in rows])
    again = np.mean([r["replan"][0] for r in rows])
    print(f"mean MSE over {args.days} days: once {once:.4f}, replan {again:.4f} "
          f"({100 * (once - again) / once:+.1f}% error cut by replanning); every route "
          "passed the brute-force feasibility check")


if __name__ == "__main__":
    main()
