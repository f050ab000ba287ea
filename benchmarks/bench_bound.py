"""Benchmark of the D-optimal relaxation bound and the plan certificate (issue #5).

Paper scale: a 1500 x 1400 grid with a land mask (~2M cells), rank 5 planted smooth factors
from ``synthetic_field(..., return_truth=True)``, budget 200 grid units from a central cell:

* ``dopt_upper_bound`` over every cell with n = 201 (seconds, working set, dual gap);
* ``plan_bound`` (the budget disk, ~125k candidates) and, when the planner is available,
  the greedy plan's certified gap.

``--small`` runs a 300 x 280 grid with budget 40; ``--sample`` certifies the greedy plan at
budgets 5, 50, 100, 200 on the bundled real sample (``load_sample("sst")``, rank 5).

Run under the shared lock::

    flock /tmp/lrm-bench.lock /work/venv/bin/python benchmarks/bench_bound.py [--small|--sample]
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


def greedy_certificate(Y, region, start, budget, ridge=0.0):
    """Greedy plan and its certificate, or None with the reason when the planner is missing."""
    try:
        from lrm_cvx.planning.greedy import plan_greedy
    except ImportError as exc:
        return None, f"plan_greedy unavailable ({exc})"
    from lrm_cvx.planning.bound import plan_bound

    t = time.perf_counter()
    plan = plan_greedy(Y, region, start, budget, ridge=ridge, progress=False)
    t_plan = time.perf_counter() - t
    t = time.perf_counter()
    cert = plan_bound(Y, region, start, budget, ridge=ridge, plan=plan)
    return (plan, cert, t_plan, time.perf_counter() - t), ""


def run_synthetic(small: bool) -> None:
    from lrm_cvx.io.samples import synthetic_field
    from lrm_cvx.planning.bound import dopt_upper_bound, plan_bound
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
        plan, c, t_plan, t_cert = out
        print(f"greedy plan: {len(plan.cells)} cells, cost {plan.cost:.2f}, "
              f"information {c.information:.6g} nats ({t_plan:.1f} s); certified gap "
              f"{c.gap:.4g} nats, volume ratio {c.volume_ratio:.4f}, online bound "
              f"{c.online_bound:.6g} ({t_cert:.2f} s)")
    print(f"peak RSS {rss_gb():.2f} GB")


def run_sample() -> None:
    from lrm_cvx.datasets import load_sample

    from lrm_cvx.region import Region

    da = load_sample("sst")
    region = Region.from_dataarray(da)
    D = region.stack(da).astype(np.float64)  # (T, L) NaN = missing
    try:
        from lrm_cvx.glrm import GLRM

        model = GLRM(5).fit(da)
        Y = np.asarray(model.Y_.values if hasattr(model.Y_, "values") else model.Y_, float)
        if Y.ndim == 3:
            Y = region.stack(model.Y_).astype(np.float64)
        how = "GLRM rank 5"
    except Exception as exc:  # noqa: BLE001 - fall back to a truncated SVD
        filled = np.where(np.isfinite(D), D, np.nanmean(D, axis=0, keepdims=True))
        filled = np.where(np.isfinite(filled), filled, np.nanmean(D))
        _, s, Vt = np.linalg.svd(filled, full_matrices=False)
        Y = s[:5, None] * Vt[:5]
        how = f"truncated SVD of the mean-filled matrix (GLRM unavailable: {exc})"
    print(f"sample 'sst': {da.sizes}, {region.n_cells} cells; factors: {how}")
    start = central_cell(region)
    print("budget  cells  information  bound      gap (nats)  volume ratio  online bound  s")
    for budget in (5.0, 50.0, 100.0, 200.0):
        t = time.perf_counter()
        out, why = greedy_certificate(Y, region, start, budget)
        if out is None:
            print(f"skipped: {why}")
            return
        plan, c, t_plan, t_cert = out
        print(f"{budget:6g}  {len(plan.cells):5d}  {c.information:11.5g}  {c.bound:9.5g}  "
              f"{c.gap:10.4g}  {c.volume_ratio:12.4f}  {c.online_bound:12.5g}  "
              f"{time.perf_counter() - t:.1f}")
    print(f"peak RSS {rss_gb():.2f} GB")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--small", action="store_true", help="quick smoke run")
    p.add_argument("--sample", action="store_true", help="certify greedy plans on sample data")
    args = p.parse_args()
    warnings.simplefilter("default")
    if args.sample:
        run_sample()
    else:
        run_synthetic(args.small)


if __name__ == "__main__":
    main()
