"""What the variance certificate costs at paper scale today (docs/certificate.md §13).

    python benchmarks/bench_certificate_variance_scale.py [--shape 1500 1400] \
        [--budgets 15 25 35 200]

A planted rank-5 factor matrix on a ``1500 x 1400`` grid of valid cells (2.1M, the paper's
scale; the certificate reads the factors, the residual covariance and the latent prior, not
the data), an exponential residual of range 5 cells, identity latent prior. For each budget
from the cell nearest the grid's centre: the recommended criterion's plan (``gp-variance``,
``initial="start"``) and its certificate ``plan.certify(tighten=False, tol=1e-2)``; printed:
the candidates (cells a plan may observe), seconds to plan (the reference measured in the same
run) and to certify, the certificate's peak RSS, Frank-Wolfe steps and relative gap, or the
one-line refusal above ``varbound.DENSE_MAX`` cells.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import xarray as xr
from bench_glrm import PeakRSS, rss_gib


def main() -> None:
    from lrm_cvx import Region, plan_greedy
    from lrm_cvx.errors import PlanningError
    from lrm_cvx.spatial import ResidualCovariance

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", type=int, nargs=2, default=[1500, 1400])
    ap.add_argument("--budgets", type=float, nargs="+", default=[15.0, 25.0, 35.0, 200.0])
    a = ap.parse_args()
    ny, nx = a.shape
    lat, lon = np.linspace(-60.0, 60.0, ny), np.linspace(0.0, 180.0, nx)
    region = Region(lat=xr.DataArray(lat, dims="lat", coords={"lat": lat}),
                    lon=xr.DataArray(lon, dims="lon", coords={"lon": lon}),
                    mask=np.ones((ny, nx), bool))
    Y = np.random.default_rng(0).standard_normal((5, region.n_cells))
    terms = dict(spatial_cov=ResidualCovariance("exponential", 0.5, 5.0, 0.1),
                 prior_cov=np.eye(5))
    start = int(region.cell_grid[ny // 2, nx // 2])
    print(f"{region.n_cells} cells; RSS {rss_gib():.2f} GiB", flush=True)
    print(f"{'budget':>6} {'cand.':>8} {'plan s':>7} {'cert s':>7} {'peak GiB':>8} "
          f"{'FW steps':>8} {'rel.gap':>8}", flush=True)
    warnings.simplefilter("ignore")
    for budget in a.budgets:
        t0 = time.perf_counter()
        plan = plan_greedy(Y, region, start, budget, criterion="gp-variance", initial="start",
                           progress=False, **terms)
        t_plan = time.perf_counter() - t0
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            try:
                cert = plan.certify(tighten=False, tol=1e-2)
                what = (f"{cert.n_candidates:8d} {t_plan:7.1f} {time.perf_counter() - t0:7.1f} "
                        f"{pk.peak:8.2f} {cert.relaxation.iterations:8d} "
                        f"{100 * cert.relative_gap:7.2f}%")
            except PlanningError as exc:
                what = f"{'-':>8} {t_plan:7.1f} {time.perf_counter() - t0:7.1f} refused: {exc}"
        print(f"{budget:6g} {what}", flush=True)


if __name__ == "__main__":
    main()
