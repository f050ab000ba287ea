"""Reconstruction error of the planners: route-constrained protocol and an
unconstrained comparison with QR pivoting (PySensors) and random cells.

    flock /tmp/lrm-bench.lock python benchmarks/bench_reconstruction.py [--small]

Data: the bundled real sample ``sst`` (``lrm_cvx.datasets.load_sample``; falls back to the
``eofs`` package's example file), a second real data set shipped with a package (``hgt500``:
500 hPa geopotential height, the ``eofs`` example ``hgt_djf.nc``), and synthetic data with a
rank-3 trend plus a spatially correlated (exponential GP) residual.

Route-constrained: ``evaluation.evaluate`` with the paper's model and fold-in ("paper"), and
with ``GLRM(offset=True, spatial="exponential")`` and the fold-in
``prior="empirical", spatial=True`` ("predictive") for every method, including the greedy
with the posterior criteria. Unconstrained: n cells without a route, picked by the cost-free
greedy (max gain each step) of each criterion, QR pivoting of the model's basis (PySensors
``SSPOR(QR)``, or ``scipy.linalg.qr(pivoting=True)`` when PySensors is missing) and random
cells; each selection is scored with the paper's fold-in and with the GP prediction.
Benchmark-only dependency: ``python-sensors`` (``pip install -e .[bench]``).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
import warnings

import numpy as np
import xarray as xr

from lrm_cvx.belief.posterior import fold_in_snapshots
from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, evaluate, summary
from lrm_cvx.glrm import GLRM
from lrm_cvx.information import GPVarianceOracle, make_oracle

warnings.filterwarnings("ignore")


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def load(name: str) -> tuple[xr.DataArray, str]:
    from lrm_cvx.datasets import load_sample

    return load_sample(name), "lrm_cvx.datasets.load_sample"


def synthetic(seed: int = 0, n: int = 30, T: int = 60, rank: int = 3) -> xr.DataArray:
    """Rank-3 smooth trend + exponential GP residual (range 4 cells, sill 0.3, nugget 0.02)."""
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pts = np.column_stack([r.ravel(), c.ravel()]).astype(float)
    basis = []
    for _ in range(rank):
        cen = rng.uniform(0, n, 2)
        basis.append(np.exp(-((pts - cen) ** 2).sum(1) / (2 * (n / 3) ** 2)))
    Yt = np.array(basis)
    Xt = rng.normal(size=(rank, T)) * np.array([3.0, 2.0, 1.0])[:, None]
    d = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1))
    Lc = np.linalg.cholesky(0.3 * np.exp(-d / 4.0) + 1e-9 * np.eye(n * n))
    resid = (Lc @ rng.normal(size=(n * n, T))).T + np.sqrt(0.02) * rng.normal(size=(T, n * n))
    vals = (Xt.T @ Yt + resid).reshape(T, n, n)
    land = np.ones((n, n), bool)
    land[:6, :6] = False  # a masked corner
    vals[:, ~land] = np.nan
    return xr.DataArray(vals.astype(np.float32), dims=("time", "lat", "lon"),
                        coords={"time": np.arange(T), "lat": np.arange(n) * 1.0,
                                "lon": np.arange(n) * 1.0}, name="synthetic")


# ---------------------------------------------------------------------------- routes
METHODS = ("greedy", "transect-up", "transect-down", "transect-left", "transect-right",
           "random")
NEW = ("greedy:a-optimal", "greedy:gp-variance")


def table(df, methods, budgets) -> None:
    print("  method               " + "".join(f"{b:>11g}" for b in budgets))
    for m in methods:
        row = df[df["method"] == m].set_index("budget")["mse_mean"]
        print(f"  {m:20s} " + "".join(f"{row.get(float(b), np.nan):11.4g}" for b in budgets))


def run_routes(name: str, da: xr.DataArray, budgets, n_starts, trials) -> None:
    # ridge 1e-6: the paper's Fisher greedy needs a nonsingular initial set (hgt500's is not)
    common = dict(budgets=budgets, n_starts=n_starts, progress=False, seed=0,
                  planning=PlanningOptions(random_trials=trials, certify=False, ridge=1e-6))
    t = time.perf_counter()
    paper = evaluate(da, methods=METHODS, paper=True,
                     scoring=ScoringOptions(min_observations=5), **common)
    t1 = time.perf_counter() - t
    t = time.perf_counter()
    pred = evaluate(da, methods=METHODS + NEW,
                    scoring=ScoringOptions(min_observations=5,
                                           model_params=dict(offset=True, spatial="exponential"),
                                           fold_in=dict(prior="empirical", spatial=True)),
                    **common)
    t2 = time.perf_counter() - t
    print(f"\n[{name}] route-constrained MSE (mean over {n_starts} starts x 8 test snapshots)")
    print(f"  paper model + paper fold-in ({t1:.1f} s; planner ridge 1e-6); complete condition "
          f"{float(paper.complete_mse.mean()):.4g}")
    table(summary(paper), METHODS, budgets)
    print(f"  predictive model (offset, empirical prior, GP residual) for every method "
          f"({t2:.1f} s); complete (low-rank, prior) {float(pred.complete_mse_model.mean()):.4g}")
    s = summary(pred)
    table(s, METHODS + NEW, budgets)
    rec = s[s["method"] == "greedy:gp-variance"].set_index("budget")["mse_mean"]
    for b in budgets:
        if b < 15:
            continue
        others = s[(s["budget"] == b) & s["method"].isin(METHODS[1:])]
        worst = others.set_index("method")["mse_mean"]
        print(f"  budget {b:g}: gp-variance {rec[float(b)]:.4g} vs best baseline "
              f"{worst.min():.4g} ({worst.idxmin()}): "
              f"{'beats all' if rec[float(b)] < worst.min() else 'does NOT beat all'}")


# ---------------------------------------------------------------------------- no route
def qr_cells(model: GLRM, train: xr.DataArray, n: int,
             modes: int | None = None) -> tuple[np.ndarray, str]:
    """QR pivoting on the SVD basis of the mean-filled training snapshots (``modes`` modes,
    default the model's rank)."""
    modes = model.rank if modes is None else min(modes, train.sizes["time"] - 1)
    region = model.region_
    D = region.stack(train).astype(np.float64)
    filled = np.where(np.isfinite(D), D, np.nanmean(D, axis=0))
    filled = np.where(np.isfinite(filled), filled, 0.0)
    try:
        import pysensors as ps

        sp = ps.SSPOR(basis=ps.basis.SVD(n_basis_modes=modes, random_state=0), n_sensors=n,
                      optimizer=ps.optimizers.QR())
        sp.fit(filled)
        return np.asarray(sp.get_selected_sensors()[:n], dtype=np.int64), "pysensors SSPOR(QR)"
    except ImportError:
        import scipy.linalg

        U, s, Vt = np.linalg.svd(filled - filled.mean(0), full_matrices=False)
        piv = scipy.linalg.qr(Vt[:modes], pivoting=True)[2]
        return piv[:n], "scipy.linalg.qr(pivoting=True)"


def cost_free_greedy(oracle, n: int, L: int) -> np.ndarray:
    picked: list[int] = []
    taken = np.zeros(L, bool)
    for _ in range(n):
        g = oracle.gains(np.arange(L))
        g[taken] = -np.inf
        j = int(np.argmax(g))
        picked.append(j)
        taken[j] = True
        oracle.add(j)
    return np.asarray(picked, dtype=np.int64)


def score(model, values, cells, prior, spatial, ridge=0.0) -> float:
    V = np.full(values.shape, np.nan)
    V[:, cells] = values[:, cells]
    try:
        pred, *_ = fold_in_snapshots(model.latent_prior(prior, ridge=ridge, spatial=spatial), V)
    except Exception:  # noqa: BLE001 - too few observations without a prior
        return np.nan
    return float(np.nanmean(np.nanmean((pred - values) ** 2, axis=1)))


def run_free(name: str, da: xr.DataArray, ns, n_random) -> None:
    train, test = da.isel(time=slice(None, -8)), da.isel(time=slice(-8, None))
    paper = GLRM(5, random_state=0, progress=False).fit(train)
    model = GLRM(5, random_state=0, progress=False, offset=True,
                 spatial="exponential").fit(train)
    region = model.region_
    L = region.n_cells
    vals = region.stack(test).astype(np.float64)
    Yp = paper.Y
    Y = model.Y
    kw_post = model.latent_prior("empirical").information()
    kw_gp = model.latent_prior("empirical", spatial=True).information()
    rng = np.random.default_rng(0)
    print(f"\n[{name}] unconstrained (no route), L = {L}; MSE with the paper's fold-in "
          f"(paper model) / the GP prediction (predictive model); complete (paper) "
          f"{score(paper, vals, np.arange(L), None, False):.4g}")
    head = "  n    " + "".join(f"{h:>22s}" for h in (
        "fisher (paper)", "a-optimal posterior", "gp-variance", "QR, 5 modes",
        "QR, n modes", "random"))
    print(head)
    how = ""
    for n in ns:
        sel = {}
        sel["fisher"] = cost_free_greedy(make_oracle("fisher", Yp, 1e-6), n, L)
        sel["aopt"] = cost_free_greedy(make_oracle(
            "a-optimal", Y, 0.0, prior_precision=kw_post["prior_precision"],
            noise_var=kw_post["noise_var"]), n, L)
        sel["gp"] = cost_free_greedy(GPVarianceOracle(
            Y, region=region, spatial_cov=kw_gp["spatial_cov"], prior_cov=kw_gp["prior_cov"]),
            n, L)
        sel["qr"], how = qr_cells(paper, train, n)
        sel["qrn"], _ = qr_cells(paper, train, n, modes=n)
        cells = []
        for key in ("fisher", "aopt", "gp", "qr", "qrn"):
            a = score(paper, vals, sel[key], None, False)
            b = score(model, vals, sel[key], "empirical", True)
            cells.append(f"{a:10.4g} /{b:10.4g}")
        ra, rb = [], []
        for _ in range(n_random):
            c = rng.choice(L, n, replace=False)
            ra.append(score(paper, vals, c, None, False))
            rb.append(score(model, vals, c, "empirical", True))
        cells.append(f"{np.nanmean(ra):10.4g} /{np.nanmean(rb):10.4g}")
        print(f"  {n:<4d} " + "".join(f"{c:>22s}" for c in cells))
    print(f"  (QR pivoting: {how} on the SVD basis with 5 or n modes (n modes capped at "
          f"T - 1); random: mean of {n_random} draws)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--small", action="store_true", help="quick smoke run")
    args = ap.parse_args(argv)
    if args.small:
        budgets, n_starts, trials, ns, n_random = (15, 30), 3, 3, (5, 20), 3
    else:
        budgets, n_starts, trials, ns, n_random = (5, 15, 30, 50), 10, 20, (5, 10, 20, 50), 20
    t0 = time.perf_counter()
    for name in ("sst", "hgt500", "synthetic"):
        if name == "synthetic":
            da, src = synthetic(), "30 x 30 grid, rank-3 trend + exponential GP residual"
        else:
            da, src = load(name)
        print(f"\n==== {name}: {dict(da.sizes)} from {src}")
        run_routes(name, da, budgets, n_starts, trials)
        run_free(name, da, ns, n_random)
        sys.stdout.flush()
    print(f"\ntotal {time.perf_counter() - t0:.1f} s, peak RSS {rss_gb():.2f} GB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
