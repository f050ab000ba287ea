"""Replanning en route with and without the check against straight lines.

On the records of the generalization benchmark (``generalization_data``): the recommended model
(``bench_generalization.recommended_params``, rank 5) fitted on all but the last 8 snapshots,
then ``simulate_campaign(method="greedy:gp-variance", replan_every=EVERY)`` over those 8 days
from random starts, open grid routes. The morning plans are checked against the straight
transects in both arms; the arms differ only in the replans: ``replan(refine="auto")`` (the
default: the plan's check kept en route) against ``refine=None``. Printed per set and budget:
the mean map MSE of each arm, the change, the change per start and the seconds of each arm.

``--split train`` drops the test block first (the last 8 training snapshots are the campaign:
where the default was chosen); ``--split test`` is the benchmark's test block (reported).

    PYTHONPATH=benchmarks python benchmarks/bench_replan_lines.py --split test \
        [--data sst_tropics_monthly ...] [--starts 6] [--budgets 15 30] [--every 4]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_generalization import N_TEST, recommended_params
from generalization_data import ALL_DATASETS, DATASETS, HOLDOUT_DATASETS, load

import lrm_cvx.replanning as replanning
from lrm_cvx import GLRM
from lrm_cvx.campaign import simulate_campaign


def campaigns(model, days, starts, budget: float, every: int, refine) -> tuple[np.ndarray, float]:
    """Mean map MSE of each start's campaign with the replans' ``refine``, and the seconds."""
    original = replanning.replan

    def replan(*args, **kwargs):  # the campaign's replans, with the arm's check
        return original(*args, **{**kwargs, "refine": refine})

    replanning.replan = replan
    try:
        t = time.perf_counter()
        mse = [float(simulate_campaign(model, days, int(s), budget, method="greedy:gp-variance",
                                       temporal="ar1", replan_every=every, seed=0)["mse"].mean())
               for s in starts]
        return np.array(mse), time.perf_counter() - t
    finally:
        replanning.replan = original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--split", choices=("train", "test"), default="test")
    parser.add_argument("--data", nargs="+", default=[*DATASETS, *HOLDOUT_DATASETS],
                        choices=ALL_DATASETS, help="records (default: the six and the three "
                        "hold-outs)")
    parser.add_argument("--starts", type=int, default=6)
    parser.add_argument("--budgets", type=float, nargs="+", default=[15.0, 30.0])
    parser.add_argument("--every", type=int, default=4)
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    for name in args.data:
        data = load(name)
        if args.split == "train":
            data = data.isel(time=slice(None, -N_TEST))
        train, days = data.isel(time=slice(None, -N_TEST)), data.isel(time=slice(-N_TEST, None))
        model = GLRM(**recommended_params()).fit(train)
        starts = np.random.default_rng(0).choice(model.region_.n_cells, args.starts,
                                                 replace=False)
        for budget in args.budgets:
            kept, s_kept = campaigns(model, days, starts, budget, args.every, "auto")
            plain, s_plain = campaigns(model, days, starts, budget, args.every, None)
            change = kept.mean() / plain.mean() - 1
            print(f"{name:28s} {args.split:5s} {budget:4g}  check {kept.mean():.5g}  none "
                  f"{plain.mean():.5g}  change {100 * change:+.1f} %  per start "
                  f"{np.round(100 * (kept / plain - 1), 1).tolist()}  s {s_kept:.0f} / "
                  f"{s_plain:.0f}", flush=True)


if __name__ == "__main__":
    main()
