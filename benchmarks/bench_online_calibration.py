"""Online calibration of the monitor loop's intervals over a 30-day campaign.

    python benchmarks/bench_online_calibration.py             # every record, ~15 min
    python benchmarks/bench_online_calibration.py --quick     # the choice records only
    python benchmarks/bench_online_calibration.py --data sst_tropics_monthly --gammas 0.02,0.1

Per record of the generalization benchmark (``generalization_data.py``: the six of
``DATASETS``, the three hold-outs and the three short records): the recommended model
(``temporal="auto"``, rank 5) fitted and conformally calibrated with the recommended calibration
(``RECOMMENDED["calibration"]``: the filter's own thresholds) on every snapshot before the last
``--days`` (30; a record shorter than twice that: its second half, said in the output), then
:class:`~lrm_cvx.monitor.MonitorState` through those days in time order, one route-like set of
15 cells a day (the same cells for every variant). Each day the posterior's 68 % / 95 %
intervals (``state.interval_multipliers()``) are scored at the day's other observed cells.

Variants: ``global offline`` (``calibrate(..., local=False)`` and ``online=False``: the loop
before this work), ``local offline`` (the locally weighted score, ``Calibration.local_power``
validated on the training snapshots, with the calibration's thresholds all campaign) and
``local online g`` (both, with adaptive conformal inference of step ``g``,
``MonitorState.adaptive_conformal``: the default loop at ``g = ONLINE_GAMMA``).
Printed per record and variant: mean coverage (targets 0.63-0.73 / 0.93-0.97), the worst block
of 5 days' distance from the level (targets <= 0.10 / 0.04), the 68 % coverage of the calm and
the stormy third of the cells (by their training residual std; target within 0.08 of 0.68),
and the posterior map's MSE at the scored cells with its ratio to ``global offline`` (both move
only the intervals: 1 exactly).

The step was chosen on the records of :data:`CHOICE` and is reported on the others.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np
import pandas as pd

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_generalization import recommended_params  # noqa: E402
from generalization_data import (  # noqa: E402
    DATASETS,
    HOLDOUT_DATASETS,
    SHORT_DATASETS,
    available,
    load,
)

warnings.filterwarnings("ignore")

CHOICE = ("sst_tropics_monthly", "wind10m_pacific_monthly", "navy_uwnd_global_monthly")
"""The records the online step (``ONLINE_GAMMA``) was chosen on."""
BLOCK, SIZE = 5, 15


def campaign(data, n_days: int = 30, gammas: tuple = (0.02, 0.05, 0.1), size: int = SIZE,
             seed: int = 0) -> tuple[pd.DataFrame, dict]:
    """One campaign through the last ``n_days`` snapshots of ``data`` (module docstring);
    returns the table (one row per variant) and facts of the run (days, fit seconds)."""
    from lrm_cvx import GLRM
    from lrm_cvx.glrm.calibrated import interval_coverage
    from lrm_cvx.monitor import MonitorState
    from lrm_cvx.recommended import RECOMMENDED
    from lrm_cvx.validation.calibration import calibrate
    from lrm_cvx.validation.designs import sample_sets

    T = data.sizes["time"]
    n_days = min(int(n_days), T // 2)
    train, test = data.isel(time=slice(None, -n_days)), data.isel(time=slice(-n_days, None))
    t0 = time.perf_counter()
    model = GLRM(**recommended_params(calibration=None)).fit(train)
    cals = {local: calibrate(model, train, seed=seed, local=local,
                             **RECOMMENDED["calibration"]) for local in (False, True)}
    fit_s = time.perf_counter() - t0
    region = model.region_
    Vt = region.stack(train).astype(float)
    spread = np.nanstd(Vt - region.stack(model.reconstruct()).astype(float), axis=0)
    order = np.argsort(spread, kind="stable")
    third = np.zeros(spread.size, dtype=np.int64)
    third[order[spread.size // 3: 2 * spread.size // 3]] = 1
    third[order[2 * spread.size // 3:]] = 2
    V = region.stack(test).astype(float)
    rng = np.random.default_rng(seed)
    days = [sample_sets(region, np.isfinite(V[i]), size, "route", rng) for i in range(n_days)]
    variants = [("global offline", False, None), ("local offline", True, None)] + [
        (f"local online {g:g}", True, g) for g in gammas]
    rows, mse_ref = [], None
    for name, local, gamma in variants:
        model.calibration_ = cals[local]
        state = MonitorState.from_model(model, online=False)
        if gamma is not None:
            state.adaptive_conformal(gamma=gamma)
        cov, sq, hits = [], [], {0: [], 2: []}
        for i, t in enumerate(test["time"].values):  # the days, in time order
            cells = days[i]
            state.assimilate((cells, V[i, cells]), time=t)
            held = np.setdiff1d(np.flatnonzero(np.isfinite(V[i])), cells)
            mean, _, pstd = state.posterior.predict_all(cells=held)
            m = state.interval_multipliers()
            cov.append(interval_coverage(V[i, held], mean, pstd, multipliers=m))
            sq.append((V[i, held] - mean) ** 2)
            inside = np.abs(V[i, held] - mean) <= m[0] * pstd
            for k in hits:
                hits[k].append(inside[third[held] == k])
        c = np.array(cov)
        nb = n_days // BLOCK
        blocks = c[: nb * BLOCK].reshape(nb, BLOCK, 2).mean(axis=1)
        mse = float(np.mean(np.concatenate(sq)))
        mse_ref = mse if mse_ref is None else mse_ref
        rows.append({"variant": name, "cov68": c[:, 0].mean(), "cov95": c[:, 1].mean(),
                     "worst5_68": np.abs(blocks[:, 0] - 0.68).max(),
                     "worst5_95": np.abs(blocks[:, 1] - 0.95).max(),
                     "calm68": np.concatenate(hits[0]).mean(),
                     "stormy68": np.concatenate(hits[2]).mean(),
                     "mse": mse, "mse_ratio": mse / mse_ref})
    kind = model.dynamics_.kind if getattr(model, "dynamics_", None) is not None else "none"
    return pd.DataFrame(rows), {"days": n_days, "train": T - n_days, "fit_s": fit_s,
                                "dynamics": kind, "power": cals[True].local_power}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the choice records only")
    ap.add_argument("--data", nargs="*", default=None)
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--gammas", default="0.02,0.05,0.1")
    args = ap.parse_args()
    names = args.data or (list(CHOICE) if args.quick else
                          [*DATASETS, *HOLDOUT_DATASETS, *SHORT_DATASETS])
    ok = available()
    names = [n for n in names if ok.get(n, False)]
    gammas = tuple(float(g) for g in args.gammas.split(","))
    print(f"monitor loop, {args.days}-day campaigns (last snapshots), a {SIZE}-cell route a day; "
          f"worst block of {BLOCK} days; load {os.getloadavg()[0]:.1f}", flush=True)
    t_all = time.perf_counter()
    for name in names:
        t0 = time.perf_counter()
        table, facts = campaign(load(name), args.days, gammas)
        role = "choice" if name in CHOICE else "report"
        short = " (shorter than twice the campaign: its second half)" \
            if facts["days"] < args.days else ""
        print(f"[{name}] {role}; {facts['days']} days after {facts['train']} training "
              f"snapshots{short}; dynamics {facts['dynamics']}; local power {facts['power']:g}; "
              f"fit + calibrate "
              f"{facts['fit_s']:.0f} s")
        table.insert(0, "set", name)
        with pd.option_context("display.width", 250):
            print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
        print(f"[{name}] {time.perf_counter() - t0:.0f} s\n", flush=True)
    print(f"total {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
