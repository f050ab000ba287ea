"""The recommended campaign at paper scale: what a day of the field loop costs.

    python benchmarks/bench_recommended_campaign.py                  # 310 days x 1500 x 1400
    python benchmarks/bench_recommended_campaign.py --budgets 50 200 --days 3
    python benchmarks/bench_recommended_campaign.py --quick          # 60 days x 200 x 150

The planted daily record of ``bench_recommended_fit.py`` (``synthetic_field``: rank 5, every
cell land, 30 % of the values missing, noise 0.05) is fitted with
``GLRM(**GLRM.recommended_params(), rank=5)`` on all days but the last ``--days``. Then one
``simulate_campaign`` per budget flies those days from the cell nearest the grid's centre, as
``lrm-cvx monitor`` would: each day the recommended plan (``greedy:gp-variance`` under the
filter's forecast, with the check against straight lines), the samples assimilated and the map
predicted with its intervals. Printed per budget: the seconds per day, the peak RSS of the
campaign, the samples a day, the map's MSE and the coverage of its 68 % / 95 % intervals.
Figures: docs/benchmarks.md, "Persistent monitoring".
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_glrm import PeakRSS, rss_gib
from bench_recommended_fit import planted_record


def main() -> None:
    from lrm_cvx import GLRM
    from lrm_cvx.campaign import simulate_campaign

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="60 days x 200 x 150 cells")
    ap.add_argument("--budgets", type=int, nargs="+", default=[50], help="path budgets "
                    "(grid steps)")
    ap.add_argument("--days", type=int, default=3, help="campaign days (the last days of "
                    "the record; the model is fitted on the others)")
    a = ap.parse_args()
    t0 = time.perf_counter()
    da = planted_record(a.quick)
    n_times, shape = da.sizes["time"], da.shape[1:]
    print(f"data: {n_times} days x {shape} grid, generated in {time.perf_counter() - t0:.1f} s; "
          f"RSS {rss_gib():.2f} GiB", flush=True)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    model = GLRM(**{**GLRM.recommended_params(), "rank": 5, "random_state": 0,
                    "progress": False}).fit(da.isel(time=slice(None, -a.days)))
    kind = None if model.dynamics_ is None else model.dynamics_.kind
    print(f"recommended fit {time.perf_counter() - t0:.1f} s; temporal choice "
          f"{model.selection_.attrs['choice']!r}", flush=True)
    centre = np.array([shape[0] // 2, shape[1] // 2])
    start = int(np.argmin(np.abs(model.region_.grid_index - centre).sum(axis=1)))
    days = da.isel(time=slice(-a.days, None))
    for budget in a.budgets:
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            c = simulate_campaign(model, days, start, budget, temporal=kind, seed=0)
            secs = time.perf_counter() - t0
        print(f"budget {budget}: {secs / a.days:.1f} s a day ({a.days} days), peak RSS "
              f"{pk.peak:.2f} GiB, {float(c['n_obs'].mean()):.0f} samples a day, map MSE "
              f"{float(c['mse'].mean()):.4g}, coverage {float(c['coverage68'].mean()):.3f} / "
              f"{float(c['coverage95'].mean()):.3f}", flush=True)


if __name__ == "__main__":
    main()
