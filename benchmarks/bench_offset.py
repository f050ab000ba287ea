"""The joint offset (``GLRM(offset=True)``, glrm/offset.py) against centring by the observed mean.

A planted seasonal field whose cells are clouded in one season (values missing not at random):
the error of each fit against the truth on the missing entries and on all entries, the offset's
error against each cell's mean over all times, and the fit's time and rounds. Centring is the
old ``offset=True``: the observed mean, then a plain fit of the centred data.

The same on the generalization benchmark's real records (``--records``), every one fully
observed, with clouds planted where the value is high (a value above its cell's 70th percentile
is hidden with probability 0.8, any other with 0.05: warm water under deep convection, the
wet season's green NDVI): the MSE on the hidden entries, rank 5.

    python benchmarks/bench_offset.py            # T = 120 x 1,500 cells and T = 300 x 200,000
    python benchmarks/bench_offset.py --small    # the first only
    python benchmarks/bench_offset.py --records  # the nine records (six + three hold-out)
    python benchmarks/bench_offset.py --coads    # real gaps: COADS's SST climatology

``--coads``: a record whose gaps are real and not at random, the COADS monthly SST climatology
of Debian's ``ferret-datasets`` (ship reports, 12 months x 8,706 ocean cells; 2,554 cells lose
some months, mostly the winter ones at high latitudes and near the ice). The truth at the gaps
is unknown; the World Ocean Atlas surface temperature of the same package
(``ocean_atlas_subset.nc``, interpolated to COADS's grid: 0.65 K RMS from COADS where both
have values) stands in for it.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from lrm_cvx.glrm import GLRM


def clouded(T: int, L: int, k: int = 3, seed: int = 0, noise: float = 0.3,
            clouds: bool = True):
    """``(truth, data with NaN)`` ``(T, L)`` float32: the rank-``k`` seasonal field plus a
    per-cell mean; 60 % of the cells lose 85 % of their values when the first (seasonal)
    component is low, every cell 10 % at random (``clouds=False``: nothing is missing)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    X = np.vstack([np.sin(2 * np.pi * t / 12), np.cos(2 * np.pi * t / 12),
                   0.5 * rng.standard_normal((k - 2, T))])
    truth = (X.T @ rng.standard_normal((k, L)) + 2.0 * rng.standard_normal(L)).astype(np.float32)
    cloudy = rng.random(L) < 0.6
    p = np.where((X[0][:, None] < -0.3) & cloudy[None, :], 0.85, 0.1)
    seen = rng.random((T, L)) > p if clouds else np.ones((T, L), dtype=bool)
    data = np.where(seen, truth + noise * rng.standard_normal((T, L)).astype(np.float32), np.nan)
    return truth, data.astype(np.float32)


def fit(model: GLRM, data: np.ndarray) -> tuple[GLRM, float]:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data)
    return model, time.perf_counter() - t0


def run(T: int, L: int, k: int = 3, clouds: bool = True) -> None:
    truth, data = clouded(T, L, k, clouds=clouds)
    miss = np.isnan(data) if clouds else np.ones(data.shape, dtype=bool)  # score all if none
    full_mean = truth.mean(axis=0)
    kw = dict(max_iter=100, progress=False, random_state=0)
    fit(GLRM(k, offset=True, **kw), data[:, :50_000])  # compile the kernels outside the timing
    joint, tj = fit(GLRM(k, offset=True, **kw), data)
    t0 = time.perf_counter()  # centring's time includes its means and the centred copy
    mean = np.nanmean(data, axis=0)
    centred, _ = fit(GLRM(k, **kw), data - mean)
    tc = time.perf_counter() - t0
    rec_j = joint.reconstruct().astype(np.float64)
    rec_c = centred.X.T @ centred.Y + mean
    print(f"T={T} L={L:,} rank {k}, {np.isnan(data).mean():.0%} missing")
    print("fit          mse missing   mse all   offset mse   time s   rounds")
    for name, rec, off, t, m in (("joint", rec_j, joint.offset_, tj, joint),
                                 ("centring", rec_c, mean, tc, centred)):
        e = rec - truth
        print(f"{name:<10} {np.mean(e[miss] ** 2):12.5f} {np.mean(e ** 2):9.5f} "
              f"{np.mean((off - full_mean) ** 2):12.5f} {t:8.1f} {m.n_iter_:8d}")


def hide_high(D: np.ndarray, seed: int = 0, q: float = 0.7, p_high: float = 0.8,
              p_low: float = 0.05) -> np.ndarray:
    """The planted clouds of ``--records``: True where a value of ``D (T, L)`` is hidden."""
    rng = np.random.default_rng(seed)
    high = D > np.quantile(D, q, axis=0)
    return rng.random(D.shape) < np.where(high, p_high, p_low)


def records(rank: int = 5) -> None:
    from generalization_data import DATASETS, HOLDOUT_DATASETS, load

    from lrm_cvx.region import Region

    print(f"real records, clouds where the value is high, rank {rank}: MSE on hidden entries")
    print(f"{'record':<28} {'T':>4} {'cells':>6} {'hidden':>7} {'joint':>9} {'centring':>9} "
          f"{'change':>7}")
    for name in [*DATASETS, *HOLDOUT_DATASETS]:
        da = load(name)
        D = Region.from_dataarray(da).stack(da).astype(np.float64)
        hide = hide_high(D)
        data = np.where(hide, np.nan, D)
        mean = np.nanmean(data, axis=0)
        kw = dict(max_iter=200, progress=False, random_state=0)
        joint, _ = fit(GLRM(rank, offset=True, **kw), data)
        centred, _ = fit(GLRM(rank, **kw), data - mean)
        mj = np.mean((joint.reconstruct().astype(np.float64) - D)[hide] ** 2)
        mc = np.mean((centred.X.T @ centred.Y + mean - D)[hide] ** 2)
        print(f"{name:<28} {D.shape[0]:>4} {D.shape[1]:>6} {hide.mean():>7.0%} {mj:>9.4g} "
              f"{mc:>9.4g} {mj / mc - 1:>+7.0%}")


FERRET = "/usr/share/ferret-vis/data"


def coads(ranks: tuple[int, ...] = (1, 2, 3)) -> None:
    import xarray as xr

    sst = xr.open_dataset(f"{FERRET}/coads_climatology.cdf", decode_times=False).SST
    woa = xr.open_dataset(f"{FERRET}/ocean_atlas_subset.nc", decode_times=False).TEMP
    woa = woa.isel(ZAXLEVIT19=0).rename(YAX_SUBSET="COADSY", XAX_SUBSET="COADSX").interp(
        COADSY=sst.COADSY, COADSX=sst.COADSX)
    D, W = (np.asarray(a.values, dtype=np.float64).reshape(12, -1) for a in (sst, woa))
    cells = np.isfinite(D).any(axis=0) & np.isfinite(W).all(axis=0)
    D, W = D[:, cells], W[:, cells]
    gap = np.isnan(D)
    print(f"COADS SST climatology: {cells.sum():,} cells, {int((gap.any(axis=0)).sum()):,} with "
          f"gaps, {int(gap.sum()):,} missing values; COADS vs WOA where both have values: "
          f"{np.sqrt(np.mean((D - W)[~gap] ** 2)):.3f} K RMS")
    print("factors  rank   joint RMS (bias) vs WOA at the gaps   centring RMS (bias)")
    mean = np.nanmean(D, axis=0)
    for regs in ({}, {"reg": "ridge"}):
        for k in ranks:
            kw = dict(max_iter=500, progress=False, random_state=0, **regs)
            joint, _ = fit(GLRM(k, offset=True, **kw), D)
            centred, _ = fit(GLRM(k, **kw), D - mean)
            ej = (joint.reconstruct().astype(np.float64) - W)[gap]
            ec = (centred.X.T @ centred.Y + mean - W)[gap]
            print(f"{'ridge' if regs else 'none':<8} {k:>4}   {np.sqrt(np.mean(ej ** 2)):10.3f} "
                  f"({np.mean(ej):+.3f})            {np.sqrt(np.mean(ec ** 2)):10.3f} "
                  f"({np.mean(ec):+.3f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="the 1,500-cell field only")
    ap.add_argument("--records", action="store_true",
                    help="the generalization records with planted clouds instead")
    ap.add_argument("--coads", action="store_true",
                    help="COADS's SST climatology, real gaps (Debian ferret-datasets) instead")
    args = ap.parse_args()
    if args.records:
        records()
        return
    if args.coads:
        coads()
        return
    run(120, 1500)
    if not args.small:
        run(300, 200_000)
        run(300, 200_000, clouds=False)  # the cost when nothing is missing (the offset is the mean)


if __name__ == "__main__":
    main()
