"""The joint offset (``GLRM(offset=True)``, glrm/offset.py) against centring by the observed mean.

A planted seasonal field whose cells are clouded in one season (values missing not at random):
the error of each fit against the truth on the missing entries and on all entries, the offset's
error against each cell's mean over all times, and the fit's time and rounds. Centring is the
old ``offset=True``: the observed mean, then a plain fit of the centred data.

    python benchmarks/bench_offset.py            # T = 120 x 1,500 cells and T = 300 x 200,000
    python benchmarks/bench_offset.py --small    # the first only
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from lrm_cvx.glrm import GLRM


def clouded(T: int, L: int, k: int = 3, seed: int = 0, noise: float = 0.3):
    """``(truth, data with NaN)`` ``(T, L)`` float32: the rank-``k`` seasonal field plus a
    per-cell mean; 60 % of the cells lose 85 % of their values when the first (seasonal)
    component is low, every cell 10 % at random."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    X = np.vstack([np.sin(2 * np.pi * t / 12), np.cos(2 * np.pi * t / 12),
                   0.5 * rng.standard_normal((k - 2, T))])
    truth = (X.T @ rng.standard_normal((k, L)) + 2.0 * rng.standard_normal(L)).astype(np.float32)
    cloudy = rng.random(L) < 0.6
    p = np.where((X[0][:, None] < -0.3) & cloudy[None, :], 0.85, 0.1)
    seen = rng.random((T, L)) > p
    data = np.where(seen, truth + noise * rng.standard_normal((T, L)).astype(np.float32), np.nan)
    return truth, data.astype(np.float32)


def fit(model: GLRM, data: np.ndarray) -> tuple[GLRM, float]:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data)
    return model, time.perf_counter() - t0


def run(T: int, L: int, k: int = 3) -> None:
    truth, data = clouded(T, L, k)
    miss = np.isnan(data)
    mean = np.nanmean(data, axis=0)
    full_mean = truth.mean(axis=0)
    kw = dict(max_iter=100, progress=False, random_state=0)
    joint, tj = fit(GLRM(k, offset=True, **kw), data)
    centred, tc = fit(GLRM(k, **kw), data - mean)
    rec_j = joint.reconstruct().astype(np.float64)
    rec_c = centred.X.T @ centred.Y + mean
    print(f"T={T} L={L:,} rank {k}, {miss.mean():.0%} missing")
    print("fit          mse missing   mse all   offset mse   time s   rounds")
    for name, rec, off, t, m in (("joint", rec_j, joint.offset_, tj, joint),
                                 ("centring", rec_c, mean, tc, centred)):
        e = rec - truth
        print(f"{name:<10} {np.mean(e[miss] ** 2):12.5f} {np.mean(e ** 2):9.5f} "
              f"{np.mean((off - full_mean) ** 2):12.5f} {t:8.1f} {m.n_iter_:8d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="the 1,500-cell field only")
    args = ap.parse_args()
    run(120, 1500)
    if not args.small:
        run(300, 200_000)


if __name__ == "__main__":
    main()
