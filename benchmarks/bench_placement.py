"""Static placement defaults and speed.

    python benchmarks/bench_placement.py                 # every set, 15/30/60 sensors + speed
    python benchmarks/bench_placement.py --quick         # 15 sensors, no paper scale
    python benchmarks/bench_placement.py --dense         # also the dense L x L reference (6k)
    python benchmarks/bench_placement.py --paper-only    # the 2.1M-cell figure only
    python benchmarks/bench_placement.py --holdout       # accuracy on the 3 hold-out records
    python benchmarks/bench_placement.py --clouds 0.3    # accuracy, 30 % of training clouded
    python benchmarks/bench_placement.py --seeds --data storm_t_land_6hourly storm_slp_6hourly
                                                         # how often auto picks the test's best

**Accuracy.** On the six real records of ``benchmarks/generalization_data.py`` (none bundled),
the protocol of ``bench_generalization.py``: ``GLRM(5, offset=True, spatial="auto")``
fitted on all but the last 8 snapshots; every placement is scored by the same predictor, the
recommended fold-in (``complete(prior="empirical", spatial=True)``: ``fold_in_snapshots`` of
``model.latent_prior("empirical", spatial=True)``) from the sensors' values, as the test MSE
(mean over the 8 held-out snapshots of the mean squared error over every cell; data units^2).
Placements:

* ``auto`` (the default): ``place_sensors(model, n, training=train)``, i.e.
  ``criterion="auto"``: risk + exchange, gp-variance + exchange or the gp-variance greedy,
  whichever validates best on the training snapshots (rolling origin, ``planning/
  static_auto.py``), with its wall time (validation included) and its choice;
* ``risk+ex``: the former default, ``"risk"`` + the recommended exchange
  (``place_sensors(model.Y_, model.region_, n, prior=model, training=train)``);
* ``risk greedy``: the same without the exchange;
* ``gp-variance``: ``place_sensors(model, n, criterion="gp-variance")``, and ``gp-var+ex``
  with ``exchange=True``;
* ``fisher``: ``place_sensors(model, n, paper=True)`` (the paper's criterion);
* ``QR best``: PySensors ``SSPOR(basis=SVD(m), optimizer=QR())`` on the mean-filled training
  snapshots, the best **test** MSE over m in {5, 10, 15, 20, 30, n} (capped at T - 1), each m
  with PySensors' randomized SVD and with the exact SVD (``bench_static.qr_cells``): QR's best
  case, chosen with the test set.

Target: ``auto`` <= ``QR best`` at every set and n. The risk's exchange runs whatever the
number of sensors (on the training snapshots alone it lowered the error of all three storm
records at ``n >= T`` by 8-18 %). The risk on the model's own training snapshots scores a
new snapshot's errors (the fit's
residuals scaled by ``n / (n - k)``, ``planning/static.py``'s ``error_factor``).

**Speed.** The default (``auto``: validation, then the chosen placement) at 15/30/60 sensors on
the ~6k-cell synthetic record below (target <= 10 s at 60), then ``risk`` + exchange
(``exchange=True``) at 15/30/60 sensors on a ~6k-cell synthetic
record (80 x 100 grid, 72 % valid, 46 months of which 38 train; target <= 10 s at 60) and on
a planted ~6k-cell model (70 x 90 grid, the paper-scale set-up below, 38 training snapshots;
more swaps), beside
the dense ``L x L`` reference (``--dense``; the objective must match); and the scalable form at
paper scale (1500 x 1400 grid, ~2.0M cells, rank 5, a grid-metric exponential residual of
range 4 cells, 20 training snapshots): 200 sensors by ``criterion="auto"`` (above
``AUTO_MAX_CELLS`` it is ``"risk"`` without validation), wall time and peak memory (target
<= 60 s and <= 4 GB), in a child process so its peak RSS is its own.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_static import fit, qr_cells, score  # noqa: E402
from generalization_data import DATASETS, HOLDOUT_DATASETS, available, load  # noqa: E402

from lrm_cvx.planning import place_sensors  # noqa: E402

HOLDOUT = 8


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def accuracy(names: list[str], ns: tuple[int, ...], clouds: float = 0.0) -> list[tuple]:
    rows = []
    print(f"{'set':26s} {'n':>3s} {'auto':>9s} {'s':>5s} {'(choice)':>20s} {'QR best':>9s} "
          f"{'(modes)':>9s} {'risk+ex':>9s} {'risk grdy':>9s} {'gp-var+ex':>9s} "
          f"{'gp-var':>9s} {'fisher':>9s} {'auto vs QR':>10s}")
    for name in names:
        train = load(name, clouds=clouds).isel(time=slice(None, -HOLDOUT))
        test = load(name).isel(time=slice(-HOLDOUT, None))  # sensors read under clouds too
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = fit(train)
        values = model.region_.stack(test).astype(np.float64)
        T = train.sizes["time"]
        Y, region = model.Y_, model.region_
        for n in ns:
            t0 = time.perf_counter()
            auto = place_sensors(model, n, training=train)
            sec = time.perf_counter() - t0
            choice = auto.refinement["selection"].attrs["choice"]
            e = {"auto": score(model, values, auto.cells),
                 "risk+ex": score(model, values, place_sensors(
                     Y, region, n, prior=model, training=train).cells),
                 "risk greedy": score(model, values, place_sensors(
                     model, n, training=train, exchange=False).cells),
                 "gp-var+ex": score(model, values, place_sensors(
                     model, n, criterion="gp-variance", exchange=True).cells),
                 "gp-variance": score(model, values, place_sensors(
                     model, n, criterion="gp-variance").cells),
                 "fisher": score(model, values, place_sensors(model, n, paper=True).cells)}
            qr = {}
            for m in sorted({5, 10, 15, 20, 30, min(n, T - 1)}):
                if m <= T - 1:
                    for exact in (False, True):
                        key = f"{m}{' exact' if exact else ''}"
                        qr[key] = score(model, values, qr_cells(model, train, n, m, exact))
            best = min(qr, key=qr.get)
            rel = e["auto"] / qr[best] - 1
            rows.append((name, n, e, sec, qr[best], best, rel, choice))
            print(f"{name:26s} {n:3d} {e['auto']:9.4g} {sec:5.1f} {choice:>20s} "
                  f"{qr[best]:9.4g} {best:>9s} {e['risk+ex']:9.4g} {e['risk greedy']:9.4g} "
                  f"{e['gp-var+ex']:9.4g} {e['gp-variance']:9.4g} {e['fisher']:9.4g} "
                  f"{100 * rel:+9.1f}%{'' if rel <= 0 else '  NOT MET'}", flush=True)
    met = sum(r[6] <= 0 for r in rows)
    old = sum(r[2]["risk+ex"] <= r[4] for r in rows)
    print(f"auto <= QR best in {met} of {len(rows)} (set, n); risk+ex (the former default) "
          f"in {old} of {len(rows)}")
    return rows


def seed_picks(names: list[str], seeds=(0, 1, 2), ns=(15, 30, 60)) -> int:
    """How often ``criterion="auto"``'s validation picks the candidate with the lowest test
    MSE (each candidate placed on the full model and training, as ``auto`` would), over the
    model refitted with ``random_state`` in ``seeds`` (the refits inside the validation use
    it too); prints one line per case and the count."""
    from lrm_cvx.planning.static_auto import AUTO_CANDIDATES

    hits = total = 0
    for name in names:
        da = load(name)
        train, test = da.isel(time=slice(None, -HOLDOUT)), da.isel(time=slice(-HOLDOUT, None))
        for seed in seeds:
            model = fit(train, random_state=seed)
            values = model.region_.stack(test).astype(np.float64)
            for n in ns:
                choice = place_sensors(model, n, training=train).refinement[
                    "selection"].attrs["choice"]
                e = {}
                for lab, (crit, exchange) in AUTO_CANDIDATES.items():
                    plan = (place_sensors(model.Y_, model.region_, n, prior=model,
                                          training=train) if crit == "risk" else
                            place_sensors(model, n, criterion=crit, exchange=exchange))
                    e[lab] = score(model, values, plan.cells)
                best = min(e, key=e.get)
                hits, total = hits + (choice == best), total + 1
                print(f"{name:26s} seed {seed} n {n:3d}: choice {choice:20s} test's best "
                      f"{best:20s} " + " ".join(f"{k} {v:.4g}" for k, v in e.items()),
                      flush=True)
    print(f"the validation picked the test's best candidate {hits} of {total} times")
    return hits


def speed_6k(dense: bool) -> None:
    from lrm_cvx.glrm import GLRM
    from lrm_cvx.io.samples import synthetic_field

    da = synthetic_field(46, (80, 100), 5, missing=0.0, noise=0.1, land_fraction=0.72, seed=1)
    train = da.isel(time=slice(None, -HOLDOUT))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = GLRM(5, random_state=0, progress=False, offset=True,
                     spatial="exponential").fit(train)
    L = model.region_.n_cells
    for n in (15, 30, 60):
        t0 = time.perf_counter()
        plan = place_sensors(model, n, training=train)
        sec = time.perf_counter() - t0
        sel = plan.refinement["selection"]
        print(f"6k: {L} cells, {train.sizes['time']} training snapshots, {n} sensors: the "
              f"default (auto: {sel.attrs['choice']}, validation {sel.attrs['seconds']:.2f} s) "
              f"{sec:.2f} s" + (f"  target <= 10 s: {'ok' if sec <= 10 else 'MISSED'}"
                               if n == 60 else ""), flush=True)
    for n in (15, 30, 60):
        t0 = time.perf_counter()
        plan = place_sensors(model, n, training=train, exchange=True)
        sec = time.perf_counter() - t0
        line = (f"6k: {L} cells, {train.sizes['time']} training snapshots, {n} sensors: "
                f"risk + exchange ({plan.refinement['form']}, {plan.refinement['swaps']} swaps)"
                f" {sec:.2f} s, objective {plan.refinement['objective']:.6g}")
        if n == 60:
            line += f"  target <= 10 s: {'ok' if sec <= 10 else 'MISSED'}"
        if dense:
            t0 = time.perf_counter()
            ref = place_sensors(model, n, training=train, exchange=True, method="dense")
            line += (f"; dense reference {time.perf_counter() - t0:.1f} s, objective "
                     f"{ref.refinement['objective']:.6g}, same sensors "
                     f"{sorted(ref.cells.tolist()) == sorted(plan.cells.tolist())}")
        print(line, flush=True)


def _planted(shape: tuple[int, int], T: int) -> tuple:
    """``(Y, region, prior, train)``: bench_planner's planted smooth factors on a 95 % mask, a
    prior with a grid exponential residual (range 4 cells) and ``T`` training snapshots drawn
    from the trend plus white misfit (which the residual does not explain)."""
    from bench_planner import _problem

    from lrm_cvx.belief.posterior import LatentPosterior, ObservationModel
    from lrm_cvx.spatial import ResidualCovariance

    Y, region, _ = _problem(shape, 5, 0)
    rng = np.random.default_rng(0)
    k, L = Y.shape
    B = rng.normal(size=(k, k))
    S0 = B @ B.T / k + 0.1 * np.eye(k)
    cov = ResidualCovariance("exponential", sill=0.02, range=4.0, nugget=0.005)
    prior = LatentPosterior.from_moments(ObservationModel(Y=Y, spatial_cov=cov, region=region),
                                         np.zeros(k), S0)
    train = rng.multivariate_normal(np.zeros(k), S0, size=T) @ Y \
        + 0.1 * rng.normal(size=(T, L))
    return Y, region, prior, train


def speed_planted(dense: bool, n: int = 60) -> None:
    Y, region, prior, train = _planted((70, 90), 38)
    t0 = time.perf_counter()
    plan = place_sensors(Y, region, n, prior=prior, training=train, exchange=True)
    sec = time.perf_counter() - t0
    ref = plan.refinement
    line = (f"6k planted: {region.n_cells} cells, 38 training snapshots, {n} sensors: risk + "
            f"exchange ({ref['form']}, {ref['swaps']} swaps in {ref['sweeps']} sweeps) "
            f"{sec:.2f} s, objective {ref['objective']:.6g}  target <= 10 s: "
            f"{'ok' if sec <= 10 else 'MISSED'}")
    if dense:
        t0 = time.perf_counter()
        d = place_sensors(Y, region, n, prior=prior, training=train, exchange=True,
                          method="dense")
        line += (f"; dense reference {time.perf_counter() - t0:.1f} s, objective "
                 f"{d.refinement['objective']:.6g}, same sensors "
                 f"{sorted(d.cells.tolist()) == sorted(plan.cells.tolist())}")
    print(line, flush=True)


def paper_scale(n: int = 200, T: int = 20) -> None:
    t0 = time.perf_counter()
    Y, region, prior, train = _planted((1500, 1400), T)
    L = region.n_cells
    print(f"paper scale: {L} cells, {T} training snapshots, set-up "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    t0 = time.perf_counter()
    plan = place_sensors(Y, region, n, prior=prior, training=train, criterion="auto")
    sec = time.perf_counter() - t0
    ref = plan.refinement
    gib = _peak_gib()
    print(f"paper scale: auto -> {ref['selection'].attrs['skipped']}")
    print(f"paper scale: {n} sensors by criterion='auto' ({plan.criterion}, {ref['form']}, "
          f"{ref.get('n_candidates')} candidate cells, {plan.method}) in {sec:.1f} s "
          f"(target <= 60 s: {'ok' if sec <= 60 else 'MISSED'}); peak RSS of the process "
          f"{gib:.2f} GiB (target <= 4 GB: {'ok' if gib * 2**30 <= 4e9 else 'MISSED'})",
          flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="15 sensors, no paper scale")
    ap.add_argument("--dense", action="store_true", help="the dense reference at 6k too")
    ap.add_argument("--paper-only", action="store_true", help="the 2.1M-cell figure only")
    ap.add_argument("--speed-only", action="store_true", help="the speed figures only")
    ap.add_argument("--data", nargs="*", default=None)
    ap.add_argument("--holdout", action="store_true",
                    help="the accuracy table on the hold-out records only "
                         "(generalization_data.HOLDOUT_DATASETS; no speed figures)")
    ap.add_argument("--seeds", action="store_true",
                    help="how often the validation picks the test's best candidate over "
                         "random_state 0/1/2 (the storms by default; no other figures)")
    ap.add_argument("--clouds", type=float, default=0.0,
                    help="the accuracy table with this fraction of every training snapshot's "
                         "values hidden by moving clouds (e.g. 0.3; lrm_cvx.io.cloud_gaps); "
                         "the sensors read the test snapshots whole")
    args = ap.parse_args(argv)
    if not 0.0 <= args.clouds < 1.0:
        ap.error(f"--clouds must be in [0, 1), got {args.clouds}")
    if args.paper_only:
        paper_scale()
        return 0
    t0 = time.perf_counter()
    print(f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    ok = available()
    names = [n for n in (args.data or list(HOLDOUT_DATASETS if args.holdout else DATASETS))
             if ok.get(n, False)]
    if args.seeds:
        seed_picks([n for n in (args.data or ["storm_t_land_6hourly", "storm_slp_6hourly"])
                    if ok.get(n, False)])
        print(f"total {time.perf_counter() - t0:.0f} s")
        return 0
    if not args.speed_only:
        accuracy(names, (15,) if args.quick else (15, 30, 60), args.clouds)
    if args.holdout or args.clouds:
        print(f"total {time.perf_counter() - t0:.0f} s")
        return 0
    speed_6k(args.dense)
    speed_planted(args.dense)
    if not args.quick:
        subprocess.run([sys.executable, os.path.abspath(__file__), "--paper-only"],
                       check=False)
    print(f"total {time.perf_counter() - t0:.0f} s; load average at end "
          f"{os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
