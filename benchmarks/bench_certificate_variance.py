"""Benchmark of the variance certificate: the default plan's certified gap under its own
criterion (docs/certificate.md, "Variance criteria").

For each record (the bundled ``sst``, ``hgt500``, or a name of
``benchmarks/generalization_data.py``, e.g. ``sst_tropics_monthly``) the recommended model
``GLRM(rank=5, offset=True, spatial="auto")`` is fitted, and for each budget (15, 30, 60 grid
units) and five
start cells (evenly spread over the region's cells) the default plan of
``plan_greedy(model, start, budget)`` (gp-variance, rival routes kept) is certified by
``plan.certify()``. Printed per plan: the certified upper bound on the variance any plan of the
budget removes, the plan's value, the relative gap ``(bound - value) / bound``, the plan slack
(kept route over the greedy's), the Frank-Wolfe slack of the largest piece (relaxation bound
over its best design), which bound the largest piece took (``rank`` or ``relaxation``), the
seconds of the certificate and, as the reference measured in the
same run, the seconds of planning. Targets: relative gap <= 15 %.

Run under the shared lock::

    flock /tmp/lrm-bench.lock python benchmarks/bench_certificate_variance.py \
        [--records sst hgt500] [--budgets 15 30 60] [--starts 5] [--max-pieces 40] [--tol 1e-3]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from lrm_cvx import GLRM, load_sample, plan_greedy
    from lrm_cvx.recommended import RECOMMENDED

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", nargs="+", default=["sst", "hgt500"])
    ap.add_argument("--budgets", nargs="+", type=float, default=[15.0, 30.0, 60.0])
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--max-pieces", type=int, default=40)
    ap.add_argument("--cover", type=int, default=2)
    ap.add_argument("--tol", type=float, default=1e-3)
    args = ap.parse_args(argv)
    print(f"{'record':8} {'budget':>6} {'start':>6} {'bound':>11} {'value':>11} {'rel.gap':>8} "
          f"{'plan sl.':>9} {'FW sl.':>8} {'active':>10} {'pieces':>6} {'s':>6} {'plan s':>6}")
    gaps = []
    for name in args.records:
        data = _load(name, load_sample)
        model = GLRM(rank=5, offset=RECOMMENDED["offset"], spatial=RECOMMENDED["spatial"],
                     random_state=0, progress=False).fit(data)
        n = model.region_.n_cells
        starts = np.linspace(0, n - 1, args.starts + 2).astype(int)[1:-1]
        for budget in args.budgets:
            for start in starts.tolist():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    t0 = time.perf_counter()
                    plan = plan_greedy(model, start, budget, progress=False)
                    t_plan = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    cert = plan.certify(tol=args.tol, tighten={"max_pieces": args.max_pieces,
                                                               "cover": args.cover})
                dt = time.perf_counter() - t0
                relax = cert.relaxation
                fw = (relax.value - relax.primal) / relax.value if relax.value else 0.0
                active = getattr(relax, "active", "-")
                gaps.append(cert.relative_gap)
                print(f"{name:8} {budget:6g} {start:6d} {cert.bound:11.5g} "
                      f"{cert.information:11.5g} {100 * cert.relative_gap:7.2f}% "
                      f"{cert.plan_slack if cert.plan_slack is not None else float('nan'):9.3g} "
                      f"{100 * fw:7.2f}% {active:>10} {len(cert.leaves):6d} {dt:6.1f} "
                      f"{t_plan:6.1f}", flush=True)
    g = np.asarray(gaps, dtype=float)
    print(f"relative gap: median {100 * np.median(g):.2f} %, max {100 * g.max():.2f} %, "
          f"{int((g <= 0.15).sum())} of {g.size} plans within 15 %")
    return 0


def _load(name: str, load_sample):
    """A bundled sample, else a record of ``generalization_data`` (installed separately)."""
    from lrm_cvx.datasets import SAMPLES

    if name in SAMPLES:
        return load_sample(name)
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import generalization_data

    return generalization_data.load(name)


if __name__ == "__main__":
    raise SystemExit(main())
