"""What the variance certificate costs at paper scale (docs/certificate.md §13).

    python benchmarks/bench_certificate_variance_scale.py [--shape 1500 1400] \
        [--budgets 5 15 200] [--tol 1e-2]

A planted rank-5 factor matrix on a ``1500 x 1400`` grid of valid cells (2.1M, the paper's
scale; the certificate reads the factors, the residual covariance and the latent prior, not
the data), an exponential residual of range 5 cells, identity latent prior. For each budget
from the cell nearest the grid's centre: the recommended criterion's plan (``gp-variance``,
``initial="start"``) and its certificate ``plan.certify(tighten=False, tol=TOL)``; printed:
the candidates (cells a plan may observe), seconds to plan (the reference, measured in the same
run) and to certify and their ratio, the certificate's peak RSS (of the whole process),
Frank-Wolfe steps, the relaxation's solver (the structured objective at this scale) and the
relative gap, or a one-line refusal."""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np
import xarray as xr
from bench_glrm import PeakRSS, rss_gib


def main() -> None:
    from lrm_cvx import Region, plan_greedy
    from lrm_cvx.errors import PlanningError
    from lrm_cvx.planning import PriorTerms
    from lrm_cvx.spatial import ResidualCovariance

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=2, default=[1500, 1400])
    ap.add_argument("--budgets", type=float, nargs="+", default=[5.0, 15.0, 200.0])
    ap.add_argument("--tol", type=float, default=1e-2,
                    help="the Frank-Wolfe's relative gap to stop at (default 1e-2)")
    a = ap.parse_args()
    ny, nx = a.shape
    lat, lon = np.linspace(-60.0, 60.0, ny), np.linspace(0.0, 180.0, nx)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((ny, nx), bool))
    Y = np.random.default_rng(0).standard_normal((5, region.n_cells))
    prior = PriorTerms(spatial_cov=ResidualCovariance("exponential", 0.5, 5.0, 0.1),
                       prior_cov=np.eye(5))
    start = int(region.cell_grid[ny // 2, nx // 2])
    print(f"{region.n_cells} cells; RSS {rss_gib():.2f} GiB; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)
    print(f"{'budget':>6} {'cand.':>8} {'plan s':>7} {'cert s':>7} {'ratio':>6} {'peak GiB':>8} "
          f"{'FW steps':>8} {'rel.gap':>8}  solver", flush=True)
    warnings.simplefilter("ignore")
    for budget in a.budgets:
        t0 = time.perf_counter()
        plan = plan_greedy(Y, region, start, budget, criterion="gp-variance", initial="start",
                           progress=False, prior=prior)
        t_plan = time.perf_counter() - t0
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            try:
                cert = plan.certify(tighten=False, tol=a.tol)
                t_cert = time.perf_counter() - t0
                what = (f"{cert.n_candidates:8d} {t_plan:7.1f} {t_cert:7.1f} "
                        f"{t_cert / t_plan:6.2f} {pk.peak:8.2f} "
                        f"{cert.relaxation.iterations:8d} {100 * cert.relative_gap:7.2f}%  "
                        f"{cert.relaxation.solver}")
            except PlanningError as exc:
                what = f"{'-':>8} {t_plan:7.1f} {time.perf_counter() - t0:7.1f} refused: {exc}"
        print(f"{budget:6g} {what}", flush=True)


if __name__ == "__main__":
    main()
