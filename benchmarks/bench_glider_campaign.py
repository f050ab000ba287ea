"""On the bundled ``sst``: a two-glider campaign under the whole path model.

Two closed gliders over the ocean (great-circle km, ``traversable="valid"``: ocean cells only,
``closed=True``: each returns to its deployment cell, a km budget per glider, ``sense_along``:
a glider measures every cell it passes, as the baselines, which step cell to cell, do anyway;
``--stops-only`` turns it off) fly one campaign
(:func:`~lrm_cvx.campaign.simulate_campaign`) over the last ``--days`` snapshots. Every method
plans every day under that same path model and fleet:

* **filter**: ``greedy:gp-variance`` on the ``ar1`` filter's forecast (the recommended model,
  ``GLRM(5, offset=True, spatial="exponential", temporal="ar1")`` fitted on the first
  snapshots); **filter + replan**: the same, replanning en route every ``--every`` route
  entries (``replan_every``);
* **memoryless**: the same greedy, every day's prior the empirical prior (``temporal=None``);
* **filter (auto)**: the same greedy on the filter of ``temporal="auto"`` (the recommended
  setting: the temporal model chosen by rolling-origin validation on the training winters);
* **baselines**: the four transects and the random walk (``--walks`` seeds), predicted by the same
  filter; the best of them by mean MSE over every deployment is "best baseline".

Deployments: the fixed pair of start cells below, then ``--pairs - 1`` seeded random pairs of
ocean cells (one pair's figures depend much on where the gliders start).

``temporal="seasonal"`` is tried too: it needs monthly or daily data, and the sample holds one
November-March mean per winter, so it is reported as not applicable.

Prints the mean MSE (K^2, over each snapshot's observed cells) per method, the per-day wins, the
brute-force feasibility of every route flown (:func:`~lrm_cvx.replanning.route_feasible`) and
the wall time of a daily cycle (plan + assimilate + predict) of the fleet. Target: <= 10 s on
2 cores.

    python benchmarks/bench_glider_campaign.py [--days 30] [--budget 6000] [--every 4]
        [--stops-only]
"""

from __future__ import annotations

import argparse
import time
import warnings
from types import SimpleNamespace

import numpy as np

from lrm_cvx import GLRM, load_sample
from lrm_cvx.campaign import simulate_campaign
from lrm_cvx.errors import ModelError
from lrm_cvx.planning import PathOptions
from lrm_cvx.planning.paths import startable_cells
from lrm_cvx.replanning import route_feasible

STARTS = [(10.0, 200.0), (-20.0, 240.0)]  # two ocean cells of the sample (12.5N 200E, 22.5S 240E)
PATH = {"metric": "km", "traversable": "valid", "closed": True, "sense_along": True}
BASELINES = ("transect-up", "transect-down", "transect-left", "transect-right", "random")


def infeasible(ds, region, budgets):
    """Brute-force check of every day's flown routes (rebuilt from the Dataset)."""
    starts = [int(s) for s in ds.attrs["start"]]
    out = []
    for day in range(ds.sizes["time"]):
        route, robot = ds["routes"].values[day], ds["route_robot"].values[day]
        keep = route >= 0
        fake = SimpleNamespace(
            path={"metric": "km", "traversable": "valid", "closed": True, "stop_cost": 0.0,
                  "budgets": budgets, "starts": starts, "end": None},
            route=route[keep], route_robot=robot[keep], waypoint=np.ones(keep.sum(), bool),
            n_robots=len(starts), budget=sum(budgets), start=starts[0], traversable_mask=None)
        out += route_feasible(fake, region)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--budget", type=float, default=6000.0, help="km per glider")
    ap.add_argument("--every", type=int, default=4, help="route entries between replans")
    ap.add_argument("--walks", type=int, default=5, help="random-walk seeds")
    ap.add_argument("--pairs", type=int, default=5,
                    help="deployments: the fixed pair of starts, then seeded random pairs")
    ap.add_argument("--stops-only", action="store_true",
                    help="the greedy senses at its stops only (sense_along=False; the baselines "
                         "step cell to cell, so they observe every cell they pass either way)")
    args = ap.parse_args()
    if args.stops_only:
        PATH["sense_along"] = False
    sst = load_sample("sst")
    n = sst.sizes["time"]
    days = min(args.days, n - 10)
    if days < args.days:
        print(f"the sample has {n} snapshots: {days} held out as days (10 kept to fit)")
    train, test = sst.isel(time=slice(None, -days)), sst.isel(time=slice(-days, None))
    budgets = [args.budget] * len(STARTS)
    print(f"sst: {sst.sizes['lat']} x {sst.sizes['lon']} grid, {n} winters; fit on the first "
          f"{n - days} ({str(train.time.values[0])[:4]}-{str(train.time.values[-1])[:4]}), "
          f"campaign over the last {days} ({str(test.time.values[0])[:4]}-"
          f"{str(test.time.values[-1])[:4]}); 2 closed gliders, {args.budget:g} km each, "
          "ocean cells only")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                     progress=False).fit(train)
        auto = GLRM(5, offset=True, spatial="exponential", temporal="auto", random_state=0,
                    progress=False).fit(train)  # the recommended setting: validated choice
    auto_name = f"filter (auto: {auto.selection_.attrs['choice']})"
    region = model.region_
    pairs = [STARTS]
    if args.pairs > 1:  # more deployments: seeded pairs of ocean cells a glider can leave
        cand = startable_cells(region, "valid")
        rng = np.random.default_rng(0)
        pairs += [[int(c) for c in rng.choice(cand, 2, replace=False)]
                  for _ in range(args.pairs - 1)]
    common = dict(method="greedy:gp-variance", path=PathOptions(**PATH))
    rep = f"filter + replan every {args.every}"
    mse, n_obs, seconds, problems, used = {}, {}, {}, [], 0.0

    def run(name, starts, fitted=model, **kw):
        nonlocal used
        tic = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = simulate_campaign(fitted, test, starts, budgets, **{**common, **kw})
        seconds.setdefault(name, []).append((time.perf_counter() - tic) / days)
        mse.setdefault(name, []).append(ds["mse"].values)
        n_obs.setdefault(name, []).append(float(ds["n_obs"].mean()))
        problems.extend(infeasible(ds, region, budgets))
        used = max(used, float(ds["robot_cost"].max()))

    for p, starts in enumerate(pairs):
        run("filter", starts, temporal="ar1")
        run(rep, starts, temporal="ar1", replan_every=args.every)
        run("memoryless", starts, temporal=None)
        run(auto_name, starts, fitted=auto, temporal="auto")
        if p == 0:
            try:
                run("filter (seasonal)", starts, temporal="seasonal")
            except ModelError as exc:
                print(f"temporal='seasonal' not applicable: {exc}")
        for b in BASELINES:
            for s in range(args.walks) if b == "random" else (0,):
                run("random (mean of walks)" if b == "random" else b, starts, method=b,
                    temporal="ar1", seed=s)
    # (pair, day); the random walks of a pair averaged
    mse = {k: np.asarray(v).reshape(len(v) // args.walks, args.walks, days).mean(axis=1)
           if k.startswith("random") else np.asarray(v) for k, v in mse.items()}
    seconds = {k: float(np.mean(v)) for k, v in seconds.items()}
    n_obs = {k: float(np.mean(v)) for k, v in n_obs.items()}
    base = {k: v for k, v in mse.items() if k.startswith(("transect", "random"))}
    best = min(base, key=lambda k: float(np.nanmean(base[k])))
    floor = complete_floor(model, test)
    print(f"\n{len(pairs)} deployment(s) (pairs of start cells: "
          + "; ".join(str([region.resolve_cell(c) for c in pr]) for pr in pairs)
          + f"), sensing along the route: {PATH['sense_along']}")
    print(f"mean MSE over {days} days (K^2; the complete-data floor, every observed cell "
          f"folded in memoryless, is {floor:.4f}), cells observed a day, wall time per daily "
          "cycle of the fleet (plan + assimilate + predict):")
    for name, v in sorted(mse.items(), key=lambda kv: float(np.nanmean(kv[1]))):
        tag = "  <- best baseline" if name == best else ""
        per = " / ".join(f"{float(np.nanmean(r)):.4f}" for r in v) if len(pairs) > 1 else ""
        print(f"  {name:28s} {np.nanmean(v):.4f}  {n_obs[name]:5.1f} cells  "
              f"{seconds[name]:.3f} s/day{tag}" + (f"   per deployment {per}" if per else ""))
    trio = {"filter": mse["filter"], "memoryless": mse["memoryless"], best: mse[best]}
    wins = np.argmin(np.stack([v.ravel() for v in trio.values()]), axis=0)
    n = wins.size
    print(f"\nper-day wins over {n} deployment-days (lowest MSE of filter / memoryless / best "
          "baseline): " + ", ".join(f"{k} {int(np.sum(wins == i))}" for i, k in enumerate(trio)))
    for a, b in (("filter", "memoryless"), ("filter", best), (rep, "filter"),
                 (rep, best)):
        w = int(np.sum(mse[a] < mse[b]))
        cut = 100 * (1 - np.nanmean(mse[a]) / np.nanmean(mse[b]))
        print(f"  {a} beats {b} on {w} of {n} days ({cut:+.1f}% mean MSE cut)")
    print(f"\nroutes flown: {len(pairs)} deployments x {days} days x 2 gliders x every method, "
          f"{'all feasible' if not problems else problems[:3]} (brute-force check: km length "
          f"<= budget, ocean cells only, back home); longest glider route {used:.0f} km "
          f"of {args.budget:g}")
    worst = max(seconds.values())
    print(f"daily cycle of the fleet: filter {seconds['filter']:.3f} s, with replanning "
          f"{seconds[rep]:.3f} s, slowest method {worst:.3f} s (target <= 10 s on 2 cores: "
          f"{'met' if worst <= 10 else 'MISSED'})")


def complete_floor(model, test) -> float:
    """Mean MSE of the memoryless fold-in of every observed cell of each snapshot (what no
    route can beat by much: the model's own error)."""
    region = model.region_
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(test.sizes["time"]):
            snap = test.isel(time=i)
            pred = region.stack(model.complete(snap, prior="empirical")["prediction"])
            truth = region.stack(snap)
            ok = np.isfinite(truth)
            out.append(float(np.mean((pred[ok] - truth[ok]) ** 2)))
    return float(np.mean(out))

if __name__ == "__main__":
    main()
