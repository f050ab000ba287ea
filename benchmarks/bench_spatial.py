"""Benchmark of the spatial residual model at paper scale (~2M cells).

A 1414 x 1414 grid (1,999,396 cells), exponential covariance with range 20 cells:

* ``krige`` of 200 observations to every cell: scattered uniformly (the cut-off reaches nearly
  every target: direct path over all targets) and along a route in a budget-200 disk around the
  centre (the cut-off skips the far targets), plus the scattered case with ``cutoff=None``;
* ``krige`` of 5000 scattered observations with the local ``neighbors=32`` path;
* ``residual_correction`` (GLS fold-in, rank 5, universal-kriging std) for the route case;
* ``fit_residual_covariance`` and ``estimate_anisotropy`` on ``(20, L)`` float32 residuals
  (timing only), and the scattered kriging with an anisotropic covariance (east-west range 3
  times the north-south one).

``--small`` runs a 300 x 300 grid. Run under the shared lock::

    flock /tmp/lrm-bench.lock python benchmarks/bench_spatial.py [--small]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
import xarray as xr


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def main() -> None:
    from lrm_cvx.belief.foldin import residual_correction
    from lrm_cvx.region import Region
    from lrm_cvx.spatial import (
        ResidualCovariance,
        estimate_anisotropy,
        fit_residual_covariance,
        krige,
    )

    ap = argparse.ArgumentParser()
    ap.add_argument("--small", action="store_true")
    args = ap.parse_args()
    n_side = 300 if args.small else 1414
    da = xr.DataArray(np.zeros((n_side, n_side), np.float32), dims=("lat", "lon"),
                      coords={"lat": np.linspace(30, 50, n_side),
                              "lon": np.linspace(-100, -75, n_side)})
    region = Region.from_dataarray(da)
    L = region.n_cells
    rng = np.random.default_rng(0)
    cov = ResidualCovariance("exponential", sill=1.0, range=20.0, nugget=0.05)
    print(f"grid {n_side} x {n_side}, L = {L:,} cells, {cov!r}, "
          f"cut-off distance {cov.cutoff_distance(1e-6):.0f} cells; start RSS {rss_gb():.2f} GB")

    scattered = np.sort(rng.choice(L, 200, replace=False))
    centre = np.array(region.shape) // 2
    radius = 200.0 if not args.small else 60.0
    disk = np.flatnonzero(np.hypot(*(region.grid_index - centre).T) <= radius)
    route = np.sort(rng.choice(disk, 200, replace=False))
    values = rng.standard_normal(200)

    def run(label, fn):
        t = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t
        print(f"{label:<58s} {dt:7.2f} s   peak RSS {rss_gb():5.2f} GB")
        return out

    run("krige 200 scattered -> all cells (cutoff 1e-6)",
        lambda: krige(cov, region, scattered, values))
    m, s = run(f"krige 200 route (disk r={radius:g}) -> all cells (cutoff 1e-6)",
               lambda: krige(cov, region, route, values))
    print(f"    targets at the prior (no solve): {np.mean(s == np.sqrt(cov.sill)):.1%}")
    run("krige 200 scattered -> all cells (cutoff None)",
        lambda: krige(cov, region, scattered, values, cutoff=None))
    many = np.sort(rng.choice(L, 5000, replace=False))
    run("krige 5000 scattered, neighbors=32 -> all cells",
        lambda: krige(cov, region, many, rng.standard_normal(5000)))
    Y = rng.standard_normal((5, L))
    run("residual_correction gls, rank 5, 200 route -> all cells",
        lambda: residual_correction(Y, route, values, cov, region))
    R = rng.standard_normal((20, L), dtype=np.float32)
    fit = run("fit_residual_covariance (20, L) float32, 200k pairs",
              lambda: fit_residual_covariance(R, region, random_state=0))
    print(f"    fitted {fit!r} (white noise: expect a nugget-dominated fit)")
    a = run("estimate_anisotropy (20, L) float32 (directional variograms)",
            lambda: estimate_anisotropy(R, region))
    print(f"    anisotropy {a:g} (white noise: expect 1)")
    aniso = ResidualCovariance("exponential", sill=1.0, range=20.0, nugget=0.05, anisotropy=3.0)
    run("krige 200 scattered -> all cells, anisotropy 3 (cutoff 1e-6)",
        lambda: krige(aniso, region, scattered, values))


if __name__ == "__main__":
    main()
