"""What ``GLRM(temporal="auto")`` costs beside a plain fit ("adds at most the
time of two more fits").

    python benchmarks/bench_selection.py                   # 5k, 50k, 200k cells, 120 months
    python benchmarks/bench_selection.py --cells 5000      # one size
    python benchmarks/bench_selection.py --repeat 1        # one timing per size (default 3)

A planted monthly field (rank 5: a seasonal cycle, AR(1) anomalies, an exponential GP residual
of range 3 cells and white noise) on a square grid. Per size: the wall time of
``GLRM(5, offset=True, spatial="exponential").fit`` (the recommended model without dynamics),
of the same with ``temporal="auto"``, the extra time and the extra in units of the plain fit
(each time the least of ``--repeat`` runs: the first run pays one-time costs and the machine is
shared).
The selection refits the model twice (on the snapshots before each of its two validation
windows, fewer than the full fit sees; one residual covariance, fitted on the first refit's
residuals, serves both) and scores its candidates' campaigns at a fixed number of cells
(``MAX_SCORED``) with one batch of filters for all candidates, so its scoring cost does not grow
with the cell count while the refits do. Measured 2026-11-26 (2 cores, idle; docs/benchmarks.md):
extra 1.29 / 1.43 / 1.58 fits at 5k / 50k / 200k cells (plain fits 0.26 / 0.46 / 1.03 s; an
earlier idle run 1.66 / 1.53 / 1.64); before the batched filters and the shared covariance
4.55 / 2.15 / 2.31.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd
import xarray as xr


def planted(n_cells: int, T: int = 120, rank: int = 5, seed: int = 0) -> xr.DataArray:
    """``(time, lat, lon)`` monthly field of about ``n_cells`` cells (see module docstring)."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    n = int(round(np.sqrt(n_cells)))
    Y = np.stack([gaussian_filter(rng.normal(size=(n, n)), 8).ravel() for _ in range(rank)])
    Y /= Y.std(axis=1, keepdims=True)
    month = np.arange(T) % 12
    season = np.stack([np.cos(2 * np.pi * (month - j) / 12) for j in range(rank)]) * 2.0
    anom = np.zeros((rank, T))
    for t in range(1, T):
        anom[:, t] = 0.7 * anom[:, t - 1] + rng.normal(size=rank)
    X = season + anom
    resid = np.stack([gaussian_filter(rng.normal(size=(n, n)), 1.5).ravel() for _ in range(T)])
    D = X.T @ Y + 0.3 * resid / resid.std() + 0.1 * rng.normal(size=(T, n * n))
    times = pd.date_range("2000-01-01", periods=T, freq="MS")
    return xr.DataArray(D.reshape(T, n, n).astype(np.float32), dims=("time", "lat", "lon"),
                        coords={"time": times, "lat": np.linspace(-30, 30, n),
                                "lon": np.linspace(0, 60, n)}, name="planted")


def main() -> None:
    from lrm_cvx import GLRM

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs="*", default=[5_000, 50_000, 200_000])
    ap.add_argument("--times", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=3, help="timings per size (the least kept)")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    print(f"{'cells':>8} {'fit s':>8} {'auto s':>8} {'extra s':>8} {'extra / fit':>12}  choice")
    for n_cells in args.cells:
        data = planted(n_cells, args.times)
        kw = dict(rank=5, offset=True, spatial="exponential", random_state=0, progress=False)
        fit = total = np.inf
        for _ in range(max(1, args.repeat)):  # the least of each: the machine is shared
            t0 = time.perf_counter()
            GLRM(**kw).fit(data)
            t1 = time.perf_counter()
            auto = GLRM(**kw, temporal="auto").fit(data)
            t2 = time.perf_counter()
            fit, total = min(fit, t1 - t0), min(total, t2 - t1)
        print(f"{data.sizes['lat'] * data.sizes['lon']:8d} {fit:8.2f} {total:8.2f} "
              f"{total - fit:8.2f} {(total - fit) / fit:12.2f}  "
              f"{auto.selection_.attrs['choice']}", flush=True)


if __name__ == "__main__":
    main()
