"""Benchmark of sensors that see more than a point (docs/planning.md "Sensors").

At the paper's scale (1500 x 1400 grid, ~2.0M valid cells, rank 5): the footprint rows of every
cell a budget-200 plan may visit (one KD-tree query), the greedy with the point sensor against
a disc footprint and a towed sensor, and the fold-in of the plan's averaged observations.
Prints seconds, stops, rows and information; peak RSS at the end.

``--certificate``: the certificate of a disc plan (budget 200) at that scale: seconds, the
candidates whose footprint rows it builds, and the peak RSS before and after it; then the
towed sensor's certificate (docs/certificate.md §12) of a towed plan at budget 50 and 200,
and the point plan's bound beside it.

``--quality``: what the sensors buy on the bundled SST record (5 degree cells, fitted on the
first 40 monthly snapshots, rank 5, the empirical prior): one plan per sensor from (10, 210),
then each of the last 10 snapshots is observed through it (``plan.observe``) and folded in;
the mean squared error of the map over the observed cells, with the plain model (independent
cell errors) and with the GP residual (``spatial="exponential"``: the averages' covariance
``a^T K b``).

    flock /tmp/bench.lock python benchmarks/bench_sensors.py [--small] [--quality] [--certificate]
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np

from lrm_cvx import Region
from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel
from lrm_cvx.io.samples import synthetic_field
from lrm_cvx.planning import PathOptions, plan_greedy
from lrm_cvx.planning.greedy import budget_pool
from lrm_cvx.planning.sensors import footprint_matrix, plan_observations

RIDGE = 1e-6


def _problem(shape: tuple[int, int], rank: int) -> tuple[np.ndarray, Region, int, object]:
    da, truth = synthetic_field(1, shape, rank, seed=0, return_truth=True, missing=0.0,
                                land_fraction=0.95)
    region = Region.from_dataarray(da, mask=truth["land_mask"])
    Y = region.stack(truth["Y"]).astype(np.float64)
    gi = region.grid_index
    start = int(np.argmin(((gi - np.array(shape) // 2) ** 2).sum(1)))
    return Y, region, start, region.stack(da.isel(time=0)).astype(np.float64)


def quality() -> None:
    """Reconstruction error on the bundled SST record: point, disc, square and towed sensors."""
    from lrm_cvx import GLRM, load_sample

    sst = load_sample("sst")
    train, test = sst.isel(time=slice(0, 40)), sst.isel(time=slice(40, 50))
    for spatial in (None, "exponential"):
        model = GLRM(rank=5, random_state=0, progress=False, spatial=spatial).fit(train)
        V = model.region_.stack(test).astype(np.float64)
        prior = model.latent_prior("empirical", spatial=spatial is not None)
        print(f"SST, {'GP residual' if spatial else 'independent cell errors'}:")
        for budget in (8.0, 15.0, 30.0):
            for sensor in ("point", "disc:1200km", "square:1200km", "leg-average",
                           "disc:1200km,errors=shared", "square:1200km,errors=shared",
                           "leg-average,errors=shared"):
                plan = plan_greedy(model.Y_, model.region_, (10, 210), budget, prior=prior,
                                   initial="start", progress=False, path=PathOptions(sensor=sensor))
                err = []
                for t in range(V.shape[0]):
                    rows, vals = plan.observe(V[t])
                    mean = prior.update_rows(rows, vals, plan.sensor.errors).predict()[0]
                    ok = np.isfinite(V[t])
                    err.append(float(np.mean((mean[ok] - V[t][ok]) ** 2)))
                print(f"  budget {budget:4.0f} {plan.sensor.describe():>29s}: "
                      f"{plan.stops.size:3d} stops, {rows.nnz:4d} cells seen, "
                      f"mse {np.mean(err):.4f}")


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def certificate(Y: np.ndarray, region: Region, start: int, width: float) -> None:
    """The footprint plan's certificate (docs/certificate.md §11): time, candidates, memory."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = plan_greedy(Y, region, start, 200.0, ridge=RIDGE, progress=False,
                           path=PathOptions(sensor=f"disc:{width}km"))
    before = _peak_gib()
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cert = plan.certify()
    print(f"certificate of the disc plan (budget 200, {plan.stops.size} stops): "
          f"{time.perf_counter() - t:.1f} s, {cert.n_candidates} candidates, bound "
          f"{cert.bound:.3f}, information {cert.information:.3f}; peak RSS {before:.2f} GiB "
          f"before it, {_peak_gib():.2f} GiB after")
    for budget in (50.0, 200.0):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            towed = plan_greedy(Y, region, start, budget, ridge=RIDGE, progress=False,
                                path=PathOptions(sensor="towed"))
            point = plan_greedy(Y, region, start, budget, ridge=RIDGE, progress=False)
            t = time.perf_counter()
            cert = towed.certify()
            sec = time.perf_counter() - t
            pcert = point.certify(refine=False)
        print(f"towed plan, budget {budget:g} ({towed.stops.size} stops): certificate "
              f"{sec:.1f} s, {cert.n_candidates} candidates, at most {cert.towed[0]} "
              f"observations of {cert.towed[1]} leg cells; bound {cert.bound:.3f}, information "
              f"{cert.information:.3f}, gap {cert.gap:.3f} nats (volume ratio "
              f"{cert.volume_ratio:.3f}); the point plan: bound {pcert.bound:.3f}, information "
              f"{pcert.information:.3f}; peak RSS {_peak_gib():.2f} GiB")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--small", action="store_true", help="a 300 x 280 grid")
    ap.add_argument("--quality", action="store_true",
                    help="only the reconstruction error on the bundled SST record")
    ap.add_argument("--certificate", action="store_true",
                    help="only the certificates of a disc plan at budget 200 and of towed "
                         "plans at budgets 50 and 200")
    args = ap.parse_args()
    if args.quality:
        quality()
        return
    shape = (300, 280) if args.small else (1500, 1400)
    Y, region, start, truth = _problem(shape, 5)
    dlat = abs(float(region.lat[1] - region.lat[0])) * 111.195
    width = 3.0 * dlat  # a disc about three cells wide
    print(f"grid {shape}, {region.n_cells} valid cells, rank {Y.shape[0]}, cell ~{dlat:.2f} km, "
          f"disc {width:.2f} km wide")
    if args.certificate:
        certificate(Y, region, start, width)
        return
    pool = budget_pool(region, start, 200.0)
    t = time.perf_counter()
    A = footprint_matrix(region, f"disc:{width}km", pool)
    print(f"footprint rows of the {pool.size} cells within budget 200: "
          f"{time.perf_counter() - t:.2f} s, {A.nnz / pool.size:.1f} cells per footprint")
    for budget in (50.0, 200.0):
        for sensor in ("point", f"disc:{width}km", "leg-average"):
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                plan = plan_greedy(Y, region, start, budget, ridge=RIDGE, progress=False,
                                   path=PathOptions(sensor=sensor))
            sec = time.perf_counter() - t
            print(f"budget {budget:5.0f}  {plan.sensor.describe():>14s}: {sec:6.2f} s, "
                  f"{plan.stops.size:4d} stops, information {plan.information:9.3f}")
    t = time.perf_counter()
    rows, values = plan_observations(plan, truth)
    post = LatentPosterior.prior(ObservationModel(Y, noise_var=0.01), "ridge", RIDGE)
    post = post.update_rows(rows, values)
    print(f"fold-in of the last plan's {rows.shape[0]} averaged observations: "
          f"{time.perf_counter() - t:.2f} s (mean finite: {bool(np.isfinite(post.mean).all())})")
    print(f"peak RSS {_peak_gib():.2f} GiB")


if __name__ == "__main__":
    main()
