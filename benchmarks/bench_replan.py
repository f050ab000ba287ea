"""Replanning en route vs planning once a day, on the bundled ``sst``.

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

``--paper-scale`` (the target: a replan at paper scale, 2.1M cells, budget 200, km,
traversable, in <= 3 s on 2 cores): a planted field on the 1500 x 1400 grid (95 % of it
valid, 2.0M cells), a rank-5 model (offset, AR(1); criterion fisher, the monitor's default
without a spatial residual) fitted on 29 snapshots (``--model-cache`` keeps it), one glider
from the centre, km budget equivalent to 200 grid units, ``traversable="valid"``, closed. The
day's plan, then after half its route the samples so far are assimilated and the rest is
replanned, timed; beside it the same replan on the travel graph of before (a disk around the
robot instead of the ellipse its way home fits in). Printed: seconds beside the target, the
brute-force feasibility check, and the predicted quality of the day flown with each route and
without replanning (total latent variance of the map after the whole route, lower is better;
posterior log det, higher is better).

    python benchmarks/bench_replan.py --paper-scale [--model-cache /tmp/paper_model.nc]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_glider_campaign import PATH, STARTS, infeasible
from bench_planner import _km_per_grid_unit  # one grid step in km at the start

from lrm_cvx import GLRM, load_sample
from lrm_cvx.campaign import simulate_campaign
from lrm_cvx.monitor import MonitorState
from lrm_cvx.planning import PathOptions, plan_greedy
from lrm_cvx.replanning import route_feasible


def _paper_model(cache: str | None, small: bool):
    """A rank-5 model (offset, AR(1); no spatial residual: the planted field has none, a fitted
    one comes out degenerate) of a planted paper-scale field,
    fitted on all but the last snapshot; returns ``(model, truth (L,) of the last one)``."""
    import os

    import xarray as xr

    from lrm_cvx import Region
    from lrm_cvx.io.samples import synthetic_field

    n_times, shape = (30, (300, 280)) if small else (30, (1500, 1400))
    t0 = time.perf_counter()
    da, planted = synthetic_field(n_times, shape, rank=5, missing=0.5, noise=0.05,
                                  land_fraction=0.95, seed=0, return_truth=True)
    region = Region.from_dataarray(da, mask=planted["land_mask"])
    truth = region.stack(da.isel(time=-1)).astype(np.float64)
    if cache and os.path.exists(cache):
        model = GLRM.load(cache)
        if model.region_.n_cells == region.n_cells:
            print(f"field generated in {time.perf_counter() - t0:.1f} s; model loaded from "
                  f"{cache}", flush=True)
            return model, truth
    train = xr.DataArray(region.stack(da.isel(time=slice(0, -1))), dims=("time", "cell"),
                         coords={"time": da.time.values[:-1]})
    del da
    t1 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, offset=True, temporal="ar1", max_iter=5, random_state=0,
                     progress=False).fit(train, region=region)
    print(f"field generated in {t1 - t0:.1f} s, model fitted in {time.perf_counter() - t1:.1f}"
          " s", flush=True)
    if cache:
        model.save(cache)
    return model, truth


def _after_route(state, plan, done, t, truth):
    """Predicted quality of the day if ``plan`` is flown to its end from ``state`` (the samples
    of its first ``done`` entries already in): the total latent variance over all cells
    ``trace(S Y Y^T)`` (fit units) and the posterior log det ``-log det S`` of the day."""
    post = state._post_at(t)[0]
    cells = np.asarray(plan.route[done:][plan.waypoint[done:]], dtype=np.int64)
    post = post.update(cells, np.where(np.isfinite(truth[cells]), truth[cells], 0.0))
    S = post.cov
    Y = state.model.Y
    return float(np.sum(S * (Y @ Y.T))), float(-np.linalg.slogdet(S)[1])


def paper_scale(cache: str | None, small: bool, criterion: str, profile: bool) -> None:
    """The replan target at paper scale (see the module docstring)."""
    from lrm_cvx.planning import paths

    model, truth = _paper_model(cache, small)
    region = model.region_
    start = int(np.argmin(((region.grid_index - np.array(region.shape) // 2) ** 2).sum(1)))
    km = (40.0 if small else 200.0) * _km_per_grid_unit(region, start)
    print(f"grid {region.shape[0]} x {region.shape[1]}, {region.n_cells} cells, rank "
          f"{model.rank}; glider from cell {start}, budget {km:.1f} km (= "
          f"{40 if small else 200} grid units), traversable 'valid', closed, criterion "
          f"{criterion}", flush=True)
    plan_greedy(model.Y, region, start, km / 40, initial="start", progress=False, ridge=1e-6,
                stay=True, path=PathOptions(**PATH))  # compile the kernels outside the timings
    state = MonitorState.from_model(model)
    t_day = state.next_time()
    tic = time.perf_counter()
    plan = plan_greedy(model.Y, region, start, km, criterion=criterion, initial="start",
                       progress=False, **state.planner_kwargs(criterion, time=t_day),
                       path=PathOptions(**PATH))
    t_plan = time.perf_counter() - tic
    assert route_feasible(plan, region) == []
    done = plan.route.size // 2
    flown = plan.route[:done]
    obs = (flown, truth[flown])
    print(f"the day's plan: {t_plan:.2f} s, {plan.stops.size} stops, route of "
          f"{plan.route.size} entries, cost {plan.cost:.1f} km; the glider has flown {done} "
          f"entries ({plan.route_cost[done - 1]:.1f} km)", flush=True)
    rows = {}
    for name, ellipse in (("replan", True), ("replan, disk graph (before)", False)):
        paths.ELLIPSE_GRAPH = ellipse
        st = MonitorState.from_model(model)
        if profile and ellipse:
            import cProfile
            import pstats

            prof = cProfile.Profile()
            prof.enable()
        tic = time.perf_counter()
        new = st.replan(plan, done, obs, time=t_day, criterion=criterion)
        sec = time.perf_counter() - tic
        if profile and ellipse:
            prof.disable()
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)
        rows[name] = (sec, new, route_feasible(new, region),
                      _after_route(st, new, done, t_day, truth))
    paths.ELLIPSE_GRAPH = True
    stale = _after_route(st, plan, done, t_day, truth)  # the day's plan flown unchanged
    print(f"{'':28s} {'seconds':>8s} {'stops':>6s} {'cost km':>8s} {'feasible':>8s} "
          f"{'total variance':>14s} {'log det':>9s}")
    for name, (sec, new, bad, (var, ld)) in rows.items():
        print(f"{name:28s} {sec:8.2f} {new.stops.size:6d} {new.cost:8.1f} "
              f"{'yes' if not bad else 'NO':>8s} {var:14.6g} {ld:9.4f}")
    print(f"{'no replan (the day plan)':28s} {'':8s} {plan.stops.size:6d} {plan.cost:8.1f} "
          f"{'yes':>8s} {stale[0]:14.6g} {stale[1]:9.4f}")
    (sec, new, *_), (_, old, *_) = rows["replan"], rows["replan, disk graph (before)"]
    print(f"replan at paper scale: {sec:.2f} s (target <= 3 s: "
          f"{'met' if sec <= 3 else 'MISSED'}); the same route as the disk-graph replan: "
          f"{bool(np.array_equal(new.route, old.route))}")
    # no target: a fleet of two gliders (the second 75 grid units south-west), no-go band
    gi = region.grid_index
    off = 75
    second = int(np.argmin(((gi - (gi[start] - off)) ** 2).sum(1)))
    band = np.ones(region.shape, dtype=bool)
    row = (gi[start, 0] + gi[second, 0]) // 2
    band[row - 2:row + 3, : gi[start, 1] - 20] = False  # a wall between them, open to the east
    fleet = dict(PATH, traversable=band)
    st = MonitorState.from_model(model)
    tic = time.perf_counter()
    two = plan_greedy(model.Y, region, [start, second], km, criterion=criterion,
                      initial="start", progress=False,
                      **st.planner_kwargs(criterion, time=t_day), path=PathOptions(**fleet))
    t_two = time.perf_counter() - tic
    done2 = [int(np.count_nonzero(two.route_robot == r)) // 2 for r in range(2)]
    seen = np.concatenate([two.route[two.route_robot == r][:k] for r, k in enumerate(done2)])
    tic = time.perf_counter()
    new2 = st.replan(two, done2, (seen, truth[seen]), time=t_day, criterion=criterion)
    t_re2 = time.perf_counter() - tic
    ok = route_feasible(new2, region) == [] and route_feasible(two, region) == []
    print(f"fleet of 2 (no-go wall, closed): the day's plan {t_two:.2f} s, replan after "
          f"{done2} entries {t_re2:.2f} s (no target), routes feasible: {ok}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=8)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--budget", type=float, default=6000.0)
    ap.add_argument("--paper-scale", action="store_true",
                    help="only the paper-scale replan target (2.1M-cell grid, budget 200)")
    ap.add_argument("--small", action="store_true", help="--paper-scale on a 300 x 280 grid")
    ap.add_argument("--model-cache", default=None,
                    help="--paper-scale: the fitted model's file (loaded when it exists)")
    ap.add_argument("--criterion", default="fisher", help="--paper-scale criterion (default: "
                    "fisher, the monitor's for a model without a spatial residual)")
    ap.add_argument("--profile", action="store_true", help="--paper-scale: cProfile a replan")
    args = ap.parse_args()
    if args.paper_scale:
        paper_scale(args.model_cache, args.small, args.criterion, args.profile)
        return
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
                                       replan_every=every, path=PathOptions(**PATH))
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
