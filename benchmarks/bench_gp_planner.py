"""Benchmark of the scalable ``"gp-variance"`` planner (StructuredGPVarianceOracle).

1. Agreement with the dense reference (GPVarianceOracle) on 120 x 110 and 300 x 280 grids: same
   greedy picks,
   largest relative gain difference, and the time of both (the dense/structured crossover).
2. Paper scale: 1500 x 1400 grid (~2.0M land cells), noisy planted rank-5 factors (like a fitted
   model's ``Y``), exponential residual covariance of range 5 and 20 cells, budgets 50 and 200,
   ``initial="start"``, cheapest-insertion and nearest-neighbour costs: oracle set-up seconds,
   total plan seconds, seconds per pick, |P|, peak RSS, and the seconds of the recommended
   planner (``refine="rivals"``: the greedy, a second greedy pass with ``cost_exponent=0.5``,
   the four straight transects and the six routes' criterion values, planning/lines.py)
   with the route it keeps.
3. The check's route scoring (``planning/lines.route_values``) on the six routes of the
   recommended plan (range 5): its seconds, whether one oracle's picks were lag-table gathers
   (then one set-up is forked per route), the seconds of that one forked oracle for every
   case, and the largest relative difference of the values.

    flock /tmp/lrm-bench.lock python benchmarks/bench_gp_planner.py [--small]
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np

from lrm_cvx import Region
from lrm_cvx.information import GPVarianceOracle, StructuredGPVarianceOracle
from lrm_cvx.io.samples import synthetic_field
from lrm_cvx.planning import PriorTerms, plan_greedy
from lrm_cvx.planning.greedy import budget_pool
from lrm_cvx.spatial import ResidualCovariance

S0 = np.diag([1.0, 0.5, 0.25, 0.12, 0.06])  # prior covariance of x (decaying mode variances)


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _problem(shape: tuple[int, int], seed: int) -> tuple[np.ndarray, Region, int]:
    """Noisy planted rank-5 factors with unit-std rows, a land mask and a central start."""
    da, truth = synthetic_field(1, shape, 5, seed=seed, return_truth=True, missing=0.0,
                                land_fraction=0.95)
    region = Region.from_dataarray(da, mask=truth["land_mask"])
    Y = region.stack(truth["Y"]).astype(np.float64)
    Y = Y + 0.3 * Y.std(axis=1, keepdims=True) * np.random.default_rng(seed).standard_normal(
        Y.shape)
    Y /= Y.std(axis=1, keepdims=True)
    centre = np.array(shape) // 2
    d2 = ((region.grid_index - centre) ** 2).sum(1)
    return Y, region, int(np.argmin(d2))


def _cov(rng: float) -> ResidualCovariance:
    return ResidualCovariance("exponential", sill=0.5, range=rng, nugget=0.01)


def agreement(shape: tuple[int, int], budget: float) -> None:
    Y, region, start = _problem(shape, 1)
    pool = budget_pool(region, start, budget)
    for r in (2.0, 6.0):
        cov = _cov(r)
        kw = dict(region=region, spatial_cov=cov, prior_cov=S0, pool=pool)
        out = {}
        for name, cls in (("dense", GPVarianceOracle), ("structured", StructuredGPVarianceOracle)):
            t = time.perf_counter()
            o = cls(Y, [start], **kw)
            picks, gains = [], []
            for _ in range(30):  # cost-free greedy: the max gain each step
                g = o.gains(pool)
                b = int(np.argmax(g))
                picks.append(int(pool[b]))
                gains.append(g)
                o.add(int(pool[b]))
            out[name] = (time.perf_counter() - t, picks, gains, o.value)
        (td, pd, gd, vd), (ts, ps, gs, vs) = out["dense"], out["structured"]
        rel = max(float(np.max(np.abs(a - b)) / np.max(np.abs(a)))
                  for a, b in zip(gd, gs, strict=True))
        print(f"{shape[0]} x {shape[1]} grid ({region.n_cells} cells), range {r:g}, pool "
              f"{pool.size}, 30 picks: same picks {pd == ps}, max |gain diff| / max gain "
              f"{rel:.1e}, value rel diff {abs(vd - vs) / abs(vd):.1e}; dense {td:.2f} s, "
              f"structured {ts:.2f} s")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            plans = []
            for thr in (1e30, 0.0):
                import lrm_cvx.information as info
                old = info.GP_STRUCTURED_MIN_ENTRIES
                info.GP_STRUCTURED_MIN_ENTRIES = thr
                try:
                    plans.append(plan_greedy(Y, region, start, budget, criterion="gp-variance",
                                             initial="start", cost="insertion", progress=False,
                                             prior=PriorTerms(prior_cov=S0, spatial_cov=cov)))
                finally:
                    info.GP_STRUCTURED_MIN_ENTRIES = old
        print(f"  plan_greedy budget {budget:g} (insertion): dense and structured picks equal: "
              f"{plans[0].cells.tolist() == plans[1].cells.tolist()} (|P| = {len(plans[0])})")


def route_scoring(shape: tuple[int, int], budget: float) -> None:
    """Item 3 of the module docstring: one row per grid and budget."""
    import lrm_cvx.planning.lines as lines

    Y, region, start = _problem(shape, 0)
    cov = _cov(5.0)
    seen: dict = {}
    real = lines.route_values

    def spy(*args):
        seen["args"] = args
        return real(*args)

    lines.route_values = spy
    try:
        plan_greedy(Y, region, start, budget, criterion="gp-variance", initial="start",
                    cost="insertion", progress=False, refine="rivals",
                    prior=PriorTerms(prior_cov=S0, spatial_cov=cov))
    finally:
        lines.route_values = real
    criterion, Yr, ridge, routes, extra = seen["args"]
    t = time.perf_counter()
    values = real(criterion, Yr, ridge, routes, extra)
    t_now = time.perf_counter() - t
    terms = {key: extra.get(key) for key in lines.GP_TERMS}
    sets = {name: np.unique(np.asarray(c, dtype=np.int64)) for name, c in routes.items()}
    t = time.perf_counter()
    base = lines.union_oracle(Yr, sets, terms)
    one = lines.forked_values(base, sets)
    t_one = time.perf_counter() - t
    diff = max(abs(values[n] - one[n]) / abs(one[n]) for n in one)
    print(f"{shape[0]:>5} x {shape[1]:<5} {budget:6g} {sum(c.size for c in sets.values()):6d} "
          f"{str(base.uses_lag_table):>9} {t_now:9.2f} {t_one:12.2f} {diff:9.1e}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--small", action="store_true", help="quick smoke run (300 x 280)")
    args = parser.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    agreement((60, 55) if args.small else (120, 110), 12.0 if args.small else 25.0)
    if not args.small:  # a larger region: clipped FFT windows, 80k targets (dense: 3.6e7)
        agreement((300, 280), 12.0)

    print(f"{'grid':>13} {'budget':>6} {'cells':>6} {'lag table':>9} {'scoring s':>9} "
          f"{'one oracle s':>12} {'rel diff':>9}")
    for shape, budget in ([((300, 280), 50.0)] if args.small else
                          [((400, 400), 120.0), ((700, 650), 40.0), ((700, 650), 120.0),
                           ((1500, 1400), 200.0)]):
        route_scoring(shape, budget)

    shape = (300, 280) if args.small else (1500, 1400)
    budgets = (20, 50) if args.small else (50, 200)
    t0 = time.perf_counter()
    Y, region, start = _problem(shape, 0)
    print(f"grid {shape[0]} x {shape[1]}, {region.n_cells} land cells, rank 5, start "
          f"{tuple(region.grid_index[start].tolist())}; setup {time.perf_counter() - t0:.1f} s")
    print(f"{'range':>5} {'budget':>6} {'cost':>17} {'pool':>7} {'oracle set-up s':>15} "
          f"{'plan s':>8} {'|P|':>4} {'s/pick':>7} {'route':>7} {'rivals s':>8} {'kept':>15} "
          f"{'peak GiB':>8}")
    for r in (5.0, 20.0):
        cov = _cov(r)
        for budget in budgets:
            pool = budget_pool(region, start, budget)
            t = time.perf_counter()
            StructuredGPVarianceOracle(Y, [start], region=region, spatial_cov=cov, prior_cov=S0,
                                       pool=pool)
            t_setup = time.perf_counter() - t
            for cost in ("insertion", "nearest-neighbor"):
                if cost == "nearest-neighbor" and budget > 50 and r > 5 and not args.small:
                    continue  # the exact NN cost: once is enough
                t = time.perf_counter()
                plan = plan_greedy(Y, region, start, budget, criterion="gp-variance",
                                   initial="start", cost=cost, progress=False,
                                   prior=PriorTerms(prior_cov=S0, spatial_cov=cov))
                sec = time.perf_counter() - t
                n = max(len(plan) - 1, 1)
                t = time.perf_counter()
                best = plan_greedy(Y, region, start, budget, criterion="gp-variance",
                                   initial="start", cost=cost, progress=False, refine="rivals",
                                   prior=PriorTerms(prior_cov=S0, spatial_cov=cov))
                t_rivals = time.perf_counter() - t
                print(f"{r:5g} {budget:6g} {cost:>17} {pool.size:7d} {t_setup:15.2f} "
                      f"{sec:8.2f} {len(plan):4d} {(sec - t_setup) / n:7.3f} "
                      f"{plan.cost:7.2f} {t_rivals:8.2f} {best.rivals['chosen']:>15} "
                      f"{_peak_gib():8.2f}", flush=True)
    print(f"peak RSS {_peak_gib():.2f} GiB")


if __name__ == "__main__":
    main()
