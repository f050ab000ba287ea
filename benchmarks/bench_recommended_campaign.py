"""The recommended campaign at paper scale: what a day of the field loop costs.

    python benchmarks/bench_recommended_campaign.py                  # 310 days x 1500 x 1400
    python benchmarks/bench_recommended_campaign.py --budgets 50 200 --days 3
    python benchmarks/bench_recommended_campaign.py --quick          # 60 days x 200 x 150
    python benchmarks/bench_recommended_campaign.py --model /tmp/m.pkl  # fit once, reuse it

The planted daily record of ``bench_recommended_fit.py`` (``synthetic_field``: rank 5, every
cell land, 30 % of the values missing, noise 0.05) is fitted with
``GLRM(**GLRM.recommended_params(), rank=5)`` on all days but the last ``--days``. Then one
``simulate_campaign`` per budget flies those days from the cell nearest the grid's centre, as
``lrm-cvx monitor`` would: each day the recommended plan (``greedy:gp-variance`` under the
filter's forecast, with the check against straight lines), the samples assimilated and the map
predicted with its intervals. Printed per budget: the seconds per day and their ratio to the
floor measured in the same run (the paper's plan at the same budget from the same start:
``plan_greedy(model, start, budget, paper=True)``, the best of two runs), the peak RSS of the
campaign, the samples a day, the map's MSE and the coverage of its 68 % / 95 % intervals.
``--model FILE`` loads the fitted model from FILE (a pickle) when it exists, else fits and
saves it there, so that runs on two versions of the package time the same model.
Figures: docs/benchmarks.md, "Persistent monitoring".
"""

from __future__ import annotations

import argparse
import os
import pickle
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
    ap.add_argument("--model", help="a pickle of the fitted model: loaded when it exists, "
                    "else written after the fit")
    a = ap.parse_args()
    t0 = time.perf_counter()
    da = planted_record(a.quick)
    n_times, shape = da.sizes["time"], da.shape[1:]
    print(f"data: {n_times} days x {shape} grid, generated in {time.perf_counter() - t0:.1f} s; "
          f"RSS {rss_gib():.2f} GiB", flush=True)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    if a.model and os.path.exists(a.model):
        with open(a.model, "rb") as f:
            model = pickle.load(f)
        print(f"model loaded from {a.model}", end="; ")
    else:
        model = GLRM(**{**GLRM.recommended_params(), "rank": 5, "random_state": 0,
                        "progress": False}).fit(da.isel(time=slice(None, -a.days)))
        if a.model:
            with open(a.model + ".part", "wb") as f:
                pickle.dump(model, f)
            os.replace(a.model + ".part", a.model)
    kind = None if model.dynamics_ is None else model.dynamics_.kind
    print(f"recommended fit {time.perf_counter() - t0:.1f} s; temporal choice "
          f"{model.selection_.attrs['choice']!r}", flush=True)
    centre = np.array([shape[0] // 2, shape[1] // 2])
    start = int(np.argmin(np.abs(model.region_.grid_index - centre).sum(axis=1)))
    days = da.isel(time=slice(-a.days, None))
    for budget in a.budgets:
        floor = min(paper_plan_seconds(model, start, budget) for _ in range(2))
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            c = simulate_campaign(model, days, start, budget, temporal=kind, seed=0)
            secs = time.perf_counter() - t0
        print(f"budget {budget}: {secs / a.days:.1f} s a day ({a.days} days) = "
              f"{secs / a.days / floor:.1f} x the paper's plan ({floor:.2f} s), peak RSS "
              f"{pk.peak:.2f} GiB, {float(c['n_obs'].mean()):.0f} samples a day, map MSE "
              f"{float(c['mse'].mean()):.4g}, coverage {float(c['coverage68'].mean()):.3f} / "
              f"{float(c['coverage95'].mean()):.3f}", flush=True)


def paper_plan_seconds(model, start: int, budget: float) -> float:
    """Seconds of the paper's plan (Fisher greedy on the factors) at ``budget`` from
    ``start``: the floor the campaign's day is compared with."""
    from lrm_cvx.planning import plan_greedy

    t0 = time.perf_counter()
    plan_greedy(model, start, budget, paper=True, progress=False)
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
