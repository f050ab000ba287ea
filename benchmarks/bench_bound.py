"""Benchmark of the D-optimal relaxation bound and the plan certificate.

Paper scale: a 1500 x 1400 grid with a land mask (~2M cells), rank 5 planted smooth factors
from ``synthetic_field(..., return_truth=True)``, budget 200 grid units from a central cell:

* ``dopt_upper_bound`` over every cell with n = 201 (seconds, working set, dual gap);
* ``plan_bound`` (the budget disk, ~125k candidates) and, when the planner is available,
  the greedy plan's certified gap.

``--small`` runs a 300 x 280 grid with budget 40; ``--sample`` certifies the greedy plan at
budgets 5, 50, 100, 200 on the bundled real sample (``load_sample("sst")``, rank 5, three
starts; refinement ``SAMPLE_REFINE``: 20000 polyline shapes with
64 climbs and four chains of 150 kicks within 120 s), and with
``--path-aware [walk|flow]`` also the king-walk (default) or layered-block relaxation
(the certificate keeps the smaller bound). Every run also refines the greedy plan
(``refine``: its time and gain) and splits the certified gap into plan slack (greedy ->
refined) and bound slack (refined -> bound), and prints the convex floor (``convex_floor``
with the refined route in the pool: no convex relaxation containing every route is below it;
at paper scale also the floors of midpoint covers of several square sides, docs/certificate.md
§9). ``--window 50 100`` compares the king-walk
relaxation with the default bound on windows of the paper-scale field (docs/certificate.md §9).

Run under the shared lock::

    flock /tmp/lrm-bench.lock python benchmarks/bench_bound.py [--small|--sample]
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def central_cell(region) -> int:
    ny, nx = region.shape
    centre = np.array([ny // 2, nx // 2])
    d = np.abs(region.grid_index - centre).sum(axis=1)
    return int(np.argmin(d))


def greedy_certificate(Y, region, start, budget, ridge=0.0, path_aware=False, refine_opts=None):
    """Greedy plan, its refinement and the certificate of the refined plan (with the gap split
    into plan slack and bound slack), or None with the reason when the planner is missing."""
    try:
        from lrm_cvx.planning.greedy import plan_greedy
        from lrm_cvx.planning.refine import refine
    except ImportError as exc:
        return None, f"plan_greedy unavailable ({exc})"
    from lrm_cvx.planning.certificate import plan_bound

    t = time.perf_counter()
    plan = plan_greedy(Y, region, start, budget, ridge=ridge, progress=False)
    t_plan = time.perf_counter() - t
    t = time.perf_counter()
    refined = refine(plan, **(refine_opts or {}))
    t_refine = time.perf_counter() - t
    t = time.perf_counter()
    cert = plan_bound(Y, region, start, budget, ridge=ridge, plan=refined, path_aware=path_aware)
    return (plan, refined, cert, t_plan, t_refine, time.perf_counter() - t), ""


def midpoint_floors(Y, region, start, budget, n_routes=40_000, seed=1):
    """How fine a midpoint cover (docs/certificate.md §6) would have to be: ``n_routes`` random
    polyline routes are binned by the square of side ``s`` (``budget / 4`` as the cover's first
    squares, then halved four times; corner at the start) holding their midpoint (the point at
    half their arc length, Lemma 2); the best mixture within one square is reached by every
    convex relaxation that contains the routes with their midpoint there, so the largest over
    the squares is a floor for *any* bound of the form "max over midpoint squares of side s of
    a convex relaxation". Prints it per side."""
    from lrm_cvx.experimental.floor import route_mixture
    from lrm_cvx.planning.plan import path_cumulative
    from lrm_cvx.planning.shapes import polyline_route, random_polyline

    t = time.perf_counter()
    rng = np.random.default_rng(seed)
    g, cg = region.grid_index, region.cell_grid
    origin = g[start].astype(float)
    Yt = np.ascontiguousarray(Y.T)
    Ms = np.empty((n_routes, Y.shape[0], Y.shape[0]))
    mids = np.empty((n_routes, 2))
    for i in range(n_routes):
        r = polyline_route(np.asarray(random_polyline(rng, origin, budget, legs=(1, 4))), cg, g,
                           budget)
        p, c = g[r].astype(float), path_cumulative(g[r])  # c strictly increasing
        mids[i] = [np.interp(c[-1] / 2, c, p[:, 0]), np.interp(c[-1] / 2, c, p[:, 1])]
        mids[i] -= origin
        Ms[i] = Yt[r].T @ Yt[r]
    print(f"midpoint-pinned floors from {n_routes} random routes "
          f"({time.perf_counter() - t:.1f} s to sample):")
    for side in budget / 4 / 2.0 ** np.arange(5):
        _, inv, cnt = np.unique(np.floor(mids / side).astype(int), axis=0, return_inverse=True,
                                return_counts=True)
        inv = inv.ravel()
        best = (-np.inf, 0)
        for b in np.argsort(-cnt)[:400]:  # the 400 best-populated squares
            idx = np.flatnonzero(inv == b)
            if idx.size >= 2:
                v = route_mixture(Ms[idx], max_iter=500)[1]
                best = max(best, (v, idx.size))
        print(f"  squares of side {side:6.3f}: {cnt.size:5d} squares hold a midpoint; the best "
              f"mixture within one square {best[0]:.3f} nats ({best[1]} routes)")


def print_floor(Y, region, start, budget, refined) -> None:
    """The convex floor (docs/certificate.md §9) with the refined plan's route in the pool."""
    from lrm_cvx.experimental.floor import convex_floor

    t = time.perf_counter()
    f = convex_floor(Y, region, start, budget, routes=[refined.route], random_state=0)
    print(f"convex floor {f.value:.4f} nats ({time.perf_counter() - t:.1f} s, {f.pool} routes, "
          f"support {len(f.routes)}, pool gap {f.pool_gap:.1e}; best single route "
          f"{f.best_route:.4f}): every convex relaxation containing the routes is >= it, so "
          f"certifies the refined plan to no less than {f.value - refined.information:.3f} nats")


def run_synthetic(small: bool) -> None:
    from lrm_cvx.io.samples import synthetic_field
    from lrm_cvx.planning.certificate import plan_bound
    from lrm_cvx.planning.dopt import dopt_upper_bound
    from lrm_cvx.region import Region

    shape, budget = ((300, 280), 40.0) if small else ((1500, 1400), 200.0)
    t = time.perf_counter()
    da, truth = synthetic_field(
        1, shape, 5, land_fraction=0.95, missing=0.0, seed=0, return_truth=True
    )
    region = Region.from_dataarray(da[0], mask=truth["land_mask"])
    Y = region.stack(truth["Y"]).astype(np.float64)
    del da
    print(f"grid {shape[0]} x {shape[1]}, {region.n_cells} cells, rank 5 "
          f"(generated in {time.perf_counter() - t:.1f} s)")

    n = int(budget) + 1
    t = time.perf_counter()
    b = dopt_upper_bound(Y, n)
    print(f"dopt_upper_bound(all {b.n_candidates} cells, n={n}): {time.perf_counter() - t:.2f} s, "
          f"working set {b.n_working}, support {b.weights.nnz}, rounds {b.iterations} "
          f"(+{b.fw_iterations} Frank-Wolfe), dual gap {b.gap:.2e} nats, value {b.value:.6g}, "
          f"status {b.status}, solver {b.solver}")

    start = central_cell(region)
    for tighten in (False, True):
        t = time.perf_counter()
        cert = plan_bound(Y, region, start, budget, tighten=tighten)
        r = cert.relaxation
        print(f"plan_bound(start={start}, budget={budget:g}, tighten={tighten}): "
              f"{time.perf_counter() - t:.2f} s, {cert.n_candidates} candidates, n_max "
              f"{cert.n_max}, pieces {max(1, len(cert.leaves))}, largest piece: "
              f"{r.n_candidates} candidates, working set {r.n_working}, dual gap {r.gap:.2e}; "
              f"bound {cert.bound:.6g} nats")

    out, why = greedy_certificate(Y, region, start, budget)
    if out is None:
        print(f"greedy certificate: skipped, {why}")
    else:
        plan, refined, c, t_plan, t_ref, t_cert = out
        mv = refined.refinement or {}
        print(f"greedy plan: {len(plan.cells)} cells, cost {plan.cost:.2f}, "
              f"information {plan.information:.6g} nats ({t_plan:.1f} s)")
        print(f"refined plan: {len(refined.cells)} cells, cost {refined.cost:.2f}, information "
              f"{refined.information:.6g} nats ({t_ref:.1f} s, {mv.get('moves', 0)} moves)")
        print(f"certificate: bound {c.bound:.6g}, gap of the greedy "
              f"{c.plan_slack + c.bound_slack:.4g} = plan slack {c.plan_slack:.4g} + bound "
              f"slack {c.bound_slack:.4g} nats; "
              f"refined volume ratio {c.volume_ratio:.4f}, online bound {c.online_bound:.6g} "
              f"({t_cert:.2f} s)")
        print_floor(Y, region, start, budget, refined)
        midpoint_floors(Y, region, start, budget)
    print(f"peak RSS {rss_gb():.2f} GB")


def run_window(budgets: list[float]) -> None:
    """Walk relaxation at medium scale (docs/certificate.md §9): the ``(2B+5)^2`` window of the
    paper-scale planted field around its central cell (the same cells, factors and start as the
    paper-scale run within the budget disk), per budget: greedy, refined (defaults), the disk
    bound (§4), the default tightened bound (§6) and ``walk_relaxation_bound``."""
    from lrm_cvx.io.samples import synthetic_field
    from lrm_cvx.planning.certificate import plan_bound
    from lrm_cvx.planning.greedy import plan_greedy
    from lrm_cvx.planning.refine import refine
    from lrm_cvx.planning.relaxation import walk_relaxation_bound
    from lrm_cvx.region import Region

    da, truth = synthetic_field(
        1, (1500, 1400), 5, land_fraction=0.95, missing=0.0, seed=0, return_truth=True
    )
    full = Region.from_dataarray(da[0], mask=truth["land_mask"])
    sr, sc = full.grid_index[central_cell(full)]
    print("budget  cells(disk)  greedy     refined    disk §4    §6 bound   walk bound  "
          "walk primal  walks  walk s  §6 s  peak RSS GB")
    for budget in budgets:
        h = int(budget) + 2
        win = (slice(sr - h, sr + h + 1), slice(sc - h, sc + h + 1))
        region = Region.from_dataarray(da[0].isel(lat=win[0], lon=win[1]),
                                       mask=truth["land_mask"][win])
        Y = region.stack(truth["Y"][(slice(None), *win)]).astype(np.float64)
        start = int(np.flatnonzero((region.grid_index == [h, h]).all(axis=1))[0])
        plan = plan_greedy(Y, region, start, budget, progress=False)
        refined = refine(plan)
        disk = plan_bound(Y, region, start, budget, tighten=False, refine=False)
        t = time.perf_counter()
        cert = plan_bound(Y, region, start, budget, refine=False)
        t_cert = time.perf_counter() - t
        wb = walk_relaxation_bound(Y, region, start, budget)
        print(f"{budget:6g}  {cert.n_candidates:11d}  {plan.information:9.4f}  "
              f"{refined.information:9.4f}  {disk.bound:9.4f}  {cert.bound:9.4f}  "
              f"{wb.value:10.4f}  {wb.primal:11.4f}  {wb.walks:5d}  {wb.seconds:6.1f}  "
              f"{t_cert:4.1f}  {rss_gb():.2f}", flush=True)


# the sample is small: refinement may search longer than the paper-scale default (kicks=10,
# one chain, 2000 shapes with 8 climbs, 55 s): 20000 polyline shapes with 64 climbs, then four
# iterated-local-search chains of 150 kicks, within 120 s
SAMPLE_REFINE = {"kicks": 150, "restarts": 4, "shapes": 20000, "climbs": 64,
                 "time_limit": 120.0}


def run_sample(path_aware: bool = False) -> None:
    from lrm_cvx.datasets import load_sample
    from lrm_cvx.region import Region

    da = load_sample("sst")
    region = Region.from_dataarray(da)
    D = region.stack(da).astype(np.float64)  # (T, L) NaN = missing
    try:
        from lrm_cvx.glrm import GLRM

        model = GLRM(5, random_state=0, progress=False).fit(da.isel(time=slice(None, -8)))
        Y = region.stack(model.Y_).astype(np.float64) if model.Y_.ndim == 3 else np.asarray(
            model.Y_, float)
        how = "GLRM rank 5 (all but the last 8 snapshots)"
    except Exception as exc:  # noqa: BLE001 - fall back to a truncated SVD
        filled = np.where(np.isfinite(D), D, np.nanmean(D, axis=0, keepdims=True))
        filled = np.where(np.isfinite(filled), filled, np.nanmean(D))
        _, s, Vt = np.linalg.svd(filled, full_matrices=False)
        Y = s[:5, None] * Vt[:5]
        how = f"truncated SVD of the mean-filled matrix (GLRM unavailable: {exc})"
    print(f"sample 'sst': {da.sizes}, {region.n_cells} cells; factors: {how}; "
          f"refine{SAMPLE_REFINE}")
    rng = np.random.default_rng(0)
    starts = [central_cell(region), *map(int, rng.choice(region.n_cells, 2, replace=False))]
    from lrm_cvx.experimental.floor import convex_floor

    print("start  budget  cells  greedy     refined    bound      gap     plan slack  "
          "bound slack  refine s  total s  convex floor")
    for start in starts:
        for budget in (5.0, 50.0, 100.0, 200.0):
            t = time.perf_counter()
            out, why = greedy_certificate(Y, region, start, budget, path_aware=path_aware,
                                          refine_opts=SAMPLE_REFINE)
            if out is None:
                print(f"skipped: {why}")
                return
            plan, refined, c, t_plan, t_ref, t_cert = out
            total = time.perf_counter() - t
            floor = convex_floor(Y, region, start, budget, routes=[refined.route],
                                 random_state=0).value
            print(f"{start:5d}  {budget:6g}  {len(refined.cells):5d}  {plan.information:9.4f}  "
                  f"{refined.information:9.4f}  {c.bound:9.4f}  "
                  f"{c.plan_slack + c.bound_slack:6.3f}  {c.plan_slack:10.3f}  "
                  f"{c.bound_slack:11.3f}  {t_ref:8.2f}  {total:7.1f}  {floor:12.4f}"
                  + (f"  path bound {c.path_bound:.4f}" if c.path_bound is not None else ""))
    print(f"peak RSS {rss_gb():.2f} GB")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--small", action="store_true", help="quick smoke run")
    p.add_argument("--sample", action="store_true", help="certify greedy plans on sample data")
    p.add_argument("--path-aware", nargs="?", const="walk", default=False,
                   choices=["walk", "flow"],
                   help="--sample: also a path-aware relaxation (min of both bounds): "
                        "'walk' (default, the king-walk relaxation) or 'flow' (layered blocks)")
    p.add_argument("--window", nargs="+", type=float, metavar="BUDGET",
                   help="walk relaxation vs the default bound on windows of the paper-scale "
                        "field (e.g. --window 50 100; docs/certificate.md §9)")
    args = p.parse_args()
    warnings.simplefilter("default")
    if args.window:
        run_window(args.window)
    elif args.sample:
        pa = {"walk": "walk", "flow": True}.get(args.path_aware, False)
        run_sample(path_aware=pa)
    else:
        run_synthetic(args.small)


if __name__ == "__main__":
    main()
