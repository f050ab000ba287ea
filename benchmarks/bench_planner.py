"""Benchmark of the greedy planner at the paper's scale (1500 x 1400 grid, ~2.1M cells, rank 5).

Prints seconds, |P| and Fisher information for budgets 5, 50, 100, 200 with the exact
nearest-neighbour cost and with cheapest insertion, then the speed-up over a naive
implementation (every tour and log det from scratch) on a 60 x 60 grid, and peak RSS.

Path-model targets (``--paths-only`` runs only these): a glider-like path model at paper scale,
``metric="km"`` with the km budget equivalent to 200 grid units at the start,
``traversable="valid"``, ``closed=True``: one robot <= 15 s, a fleet of 3 <= 30 s, peak memory
<= 4 GB; each figure is printed beside its target.

    flock /tmp/bench.lock python benchmarks/bench_planner.py [--small] [--paths-only]
"""

from __future__ import annotations

import argparse
import math
import resource
import time
import warnings

import numpy as np

from lrm_cvx import Region
from lrm_cvx.io.samples import synthetic_field
from lrm_cvx.planning import PathOptions, place_sensors, plan_greedy

RIDGE = 1e-6  # the planted factors are so smooth that 5 adjacent cells are singular


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _problem(shape: tuple[int, int], rank: int, seed: int) -> tuple[np.ndarray, Region, int]:
    """Planted smooth factors Y (rank, L) on a land mask, and a central land start cell."""
    da, truth = synthetic_field(1, shape, rank, seed=seed, return_truth=True, missing=0.0,
                                land_fraction=0.95)  # ~2.0M of the 2.1M cells
    region = Region.from_dataarray(da, mask=truth["land_mask"])
    Y = region.stack(truth["Y"]).astype(np.float64)
    centre = np.array(shape) // 2
    gi = region.grid_index
    d2 = ((gi - centre) ** 2).sum(1)
    return Y, region, int(np.argmin(d2))


def _naive_greedy(
    Y: np.ndarray, g: np.ndarray, start: int, budget: float, ridge: float
) -> list[int]:
    """Reference: every NN tour and every log det recomputed from scratch for every cell."""

    def tour_cost(cells: list[int]) -> float:
        cur, rest, total = cells[0], set(cells[1:]), []
        while rest:
            nxt = min(rest, key=lambda c: (int(((g[c] - g[cur]) ** 2).sum()), c))
            total.append(math.dist(g[cur], g[nxt]))
            rest.remove(nxt)
            cur = nxt
        return math.fsum(total)

    def logdet(cells: list[int]) -> float:
        return float(np.linalg.slogdet(ridge * np.eye(k) + Y[:, cells] @ Y[:, cells].T)[1])

    k, L = Y.shape
    d2 = ((g - g[start]) ** 2).sum(1)
    P = [int(c) for c in np.lexsort((np.arange(L), d2))[:k]]
    while True:
        c0, i0, best = tour_cost(P), logdet(P), (0.0, -1)
        for x in range(L):
            if x in P or d2[x] > (budget + 1e-6) ** 2:
                continue
            c1 = tour_cost(P + [x])
            if c1 > budget + 1e-9:
                continue
            ratio = (logdet(P + [x]) - i0) / max(c1 - c0, 1e-12)
            if ratio > best[0]:
                best = (ratio, x)
        if best[1] < 0:
            return P
        P.append(best[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--small", action="store_true", help="quick smoke run (300 x 280)")
    parser.add_argument("--paths-only", action="store_true",
                        help="only the path-model targets")
    args = parser.parse_args()
    shape = (300, 280) if args.small else (1500, 1400)
    budgets = (5, 50) if args.small else (5, 50, 100, 200)
    warnings.simplefilter("ignore", UserWarning)

    t0 = time.perf_counter()
    Y, region, start = _problem(shape, 5, seed=0)
    print(f"grid {shape[0]} x {shape[1]}, {region.n_cells} land cells, rank {Y.shape[0]}, "
          f"start cell {start} at {tuple(region.grid_index[start].tolist())}, ridge {RIDGE:g}; "
          f"setup {time.perf_counter() - t0:.1f} s")
    if args.paths_only:
        _path_targets(Y, region, start, 40.0 if args.small else 200.0)
        print(f"peak RSS {_peak_gib():.2f} GiB (target <= 4 GB = 3.73 GiB)")
        return
    # compile once, outside the timings
    plan_greedy(Y[:, :200], _small_region(region, 200), 0, 3, ridge=RIDGE, progress=False)
    plan_greedy(Y[:, :200], _small_region(region, 200), 0, 3, cost="insertion", ridge=RIDGE,
                progress=False)

    # the planted factors are very smooth (the greedy walks a nearly straight line); a noisy
    # copy (30% of each mode's spread, like a fitted model's Y) gives scattered picks and
    # irregular nearest-neighbour tours
    noisy = Y + 0.3 * Y.std(axis=1, keepdims=True) * np.random.default_rng(0).standard_normal(
        Y.shape)
    print(f"{'Y':>7} {'cost':>17} {'budget':>6} {'seconds':>8} {'|P|':>5} {'route cost':>10} "
          f"{'information':>11} {'recomputed/pick':>15}")
    for label, factors in (("planted", Y), ("noisy", noisy)):
        for cost in ("nearest-neighbor", "insertion"):
            for budget in budgets:
                t = time.perf_counter()
                plan = plan_greedy(factors, region, start, budget, cost=cost, ridge=RIDGE,
                                   progress=False)
                sec = time.perf_counter() - t
                ev = plan.history["n_evaluated"]
                per = f"{ev.mean():15.0f}" if ev.size else " " * 15
                print(f"{label:>7} {cost:>17} {budget:6g} {sec:8.2f} {len(plan):5d} "
                      f"{plan.cost:10.2f} {plan.information:11.4f} {per}")

    # speed-up over the naive implementation on a 60 x 60 grid
    Ys, rs, ss = _problem((60, 60), 5, seed=1)
    nb = 12.0 if args.small else 20.0
    t = time.perf_counter()
    fast = plan_greedy(Ys, rs, ss, nb, ridge=RIDGE, progress=False)
    t_fast = time.perf_counter() - t
    t = time.perf_counter()
    ref = _naive_greedy(Ys, rs.grid_index, ss, nb, RIDGE)
    t_naive = time.perf_counter() - t
    same = list(fast.cells) == ref
    print(f"60 x 60 grid ({rs.n_cells} cells), budget {nb:g}: fast {t_fast:.3f} s, naive "
          f"{t_naive:.1f} s, speed-up {t_naive / t_fast:.0f}x, same picks: {same} "
          f"(|P| = {len(fast)})")
    _path_targets(Y, region, start, 40.0 if args.small else 200.0)
    print(f"peak RSS {_peak_gib():.2f} GiB (target <= 4 GB = 3.73 GiB)")


def _km_per_grid_unit(region: Region, start: int) -> float:
    """Mean great-circle length (km) of one row step and one column step at the start."""
    from lrm_cvx.planning.paths import travel_distance

    g = region.grid_index[start]
    out = []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        r, c = g[0] + dr, g[1] + dc
        if 0 <= r < region.shape[0] and 0 <= c < region.shape[1] and region.cell_grid[r, c] >= 0:
            out.append(float(travel_distance(region, start, int(region.cell_grid[r, c]),
                                             metric="km")))
    return float(np.mean(out))


def _nearest_valid(region: Region, row: int, col: int) -> int:
    gi = region.grid_index
    return int(np.argmin((gi[:, 0] - row) ** 2 + (gi[:, 1] - col) ** 2))


def _path_targets(Y: np.ndarray, region: Region, start: int, grid_budget: float) -> None:
    """The path-model target: km budget equivalent to ``grid_budget`` grid units,
    traversable="valid",
    closed tours; one robot (target 15 s) and a fleet of 3 (target 30 s), on the noisy
    factors (scattered picks, like a fitted model's)."""
    noisy = Y + 0.3 * Y.std(axis=1, keepdims=True) * np.random.default_rng(0).standard_normal(
        Y.shape)
    km = grid_budget * _km_per_grid_unit(region, start)
    path = PathOptions(metric="km", traversable="valid", closed=True)
    opts = dict(path=path, ridge=RIDGE, progress=False)
    # compile the path model's kernels once, outside the timings
    small = _small_region(region, 400)
    plan_greedy(Y[:, :400], small, 0, 3 * _km_per_grid_unit(region, start), **opts)
    g = region.grid_index[start]
    off = int(0.75 * grid_budget)
    fleet = [start, _nearest_valid(region, g[0] - off, g[1] - off),
             _nearest_valid(region, g[0] + off, g[1] + off)]
    print(f"path model: metric km, budget {km:.1f} km (= {grid_budget:g} grid units "
          f"x {km / grid_budget:.3f} km), traversable 'valid', closed tours")
    print(f"{'robots':>6} {'cost':>17} {'seconds':>8} {'target':>7} {'|P|':>5} "
          f"{'robot costs (km)':>28} {'information':>11} {'route rows':>10}")
    for starts, target in (([start], 15.0), (fleet, 30.0)):
        for cost in ("nearest-neighbor", "insertion"):
            t = time.perf_counter()
            plan = plan_greedy(noisy, region, starts if len(starts) > 1 else starts[0], km,
                               cost=cost, **opts)
            sec = time.perf_counter() - t
            ok = "ok" if sec <= target else "MISSED"
            costs = " ".join(f"{c:.1f}" for c in plan.robot_costs)
            assert all(c <= km * (1 + 1e-9) for c in plan.robot_costs)
            print(f"{len(starts):6d} {cost:>17} {sec:8.2f} {target:5.0f} s {len(plan):5d} "
                  f"{costs:>28} {plan.information:11.4f} {plan.route.size:10d}  {ok}")
    # no targets: sensing along the route (one robot) and a static placement of as many
    # sensors as the route has stops
    t = time.perf_counter()
    plan = plan_greedy(noisy, region, start, km, ridge=RIDGE, progress=False,
                       path=PathOptions(metric="km", traversable="valid", closed=True,
                                        sense_along=True))
    print(f"sense_along, 1 robot: {time.perf_counter() - t:.2f} s, {plan.stops.size} stops, "
          f"{len(plan)} cells observed, information {plan.information:.4f}")
    t = time.perf_counter()
    static = place_sensors(noisy, region, 200, ridge=RIDGE)
    print(f"static placement of 200 sensors over all {region.n_cells} cells: "
          f"{time.perf_counter() - t:.2f} s, information {static.information:.4f}")
    print(f"peak RSS so far {_peak_gib():.2f} GiB")


def _small_region(region: Region, n: int) -> Region:
    """A region of the first ``n`` cells of ``region`` (for compiling the kernels)."""
    mask = np.zeros(region.shape, dtype=bool)
    gi = region.grid_index[:n]
    mask[gi[:, 0], gi[:, 1]] = True
    return Region(lat=region.lat, lon=region.lon, mask=mask)


if __name__ == "__main__":
    main()
