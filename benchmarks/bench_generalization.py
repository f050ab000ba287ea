"""Generalization benchmark : the recommended setting on real records the
project has never seen.

    python benchmarks/bench_generalization.py            # every set, budgets 15/30/60,
                                                         # 10 starts, 5 random walks per start
    python benchmarks/bench_generalization.py --quick    # budget 15, 3 starts, 3 random walks
    python benchmarks/bench_generalization.py --data storm_slp_6hourly navy_uwnd_global_monthly
    python benchmarks/bench_generalization.py --holdout  # the three hold-out records
    python benchmarks/bench_generalization.py --coverage --temporal auto --last 46 --data ...
                                                         # a short record: the last 46 only
    python benchmarks/bench_generalization.py --residual-growth --data sst_tropics_yearly
    python benchmarks/bench_generalization.py --training-only --quick   # validation-style run
    python benchmarks/bench_generalization.py --clouds 0.3   # 30 % of every snapshot clouded

The data sets are those of ``benchmarks/generalization_data.py`` (data shipped inside PyPI and
Debian packages; that module's docstring has the install commands). Per set, the
protocol: the last 8 snapshots held out, the recommended setting
(``lrm_cvx.recommended.RECOMMENDED``'s model keys, :func:`recommended_params`: offset,
``spatial="auto"`` (the residual's family validated on the training residuals),
``temporal="auto"``, ``calibration="conformal"``, rank 5 (``--rank auto``: the rank validated
with the temporal model, ``GLRM(rank="auto")``); empirical prior
with kriging for every method's map, ``greedy:gp-variance``), against the four transects and
the random walk from the same starts.

For each set one ``evaluate(..., temporal="auto")`` runs a campaign over the 8 test snapshots
per start, budget and method, through the filter the model chose on its training snapshots
(validation/selection.py; the choice is printed) and memoryless through the same loop (the same
starts and data). ``--modes ar1,seasonal,auto`` also runs the fixed kinds (the seasonal one on
monthly sets only), each fitted with its ``temporal=``. Printed per set and budget:

* test MSE of the greedy: memoryless and per temporal mode;
* per temporal mode the best baseline (lowest MSE among the transects and the random walk) and
  the greedy's relative difference to it (negative: the greedy wins);
* coverage of the 68 % / 95 % predictive intervals at the held-out (unsampled) observed cells
  of the greedy's maps, per temporal mode;
* ``auto_vs_mem`` (and ``ar1_vs_mem`` / ``seas_vs_mem``): the greedy's MSE change from
  memoryless (negative: better), and ``auto_vs_mem_ub`` its one-sided 95 % upper bound from the
  paired per-start differences (the campaigns share their starts; the target: <= +2 %);
* ``vs_all_ub_auto``: the paired upper bound of the greedy's change against each baseline, the
  worst of the five (negative: it beats every baseline with 95 % confidence).

Cost: the full run 437 s for the six sets on the idle 2-core machine (navy 185 s);
``--modes ar1,seasonal,auto`` about three times that.

MSE is in the data's units squared. A final line per set gives the wall time. ``--out DIR`` also
writes every ``summary`` table as CSV.

``--coverage`` runs instead the rolling-origin coverage check: for each of
``--origins`` consecutive test blocks of 8 snapshots at the end of the record, the model is
fitted on the snapshots before the block and calibrated on them only
(``calibrate(model, train, method="conformal", **CALIBRATE_KW)``: cross-validated,
design-matched fold-ins),
then ``evaluate`` runs the greedy's memoryless campaign (budget 15, 2 starts) through the
block. Printed per set: the mean 68 % / 95 % coverage over the blocks and the lowest block's
95 % coverage, for the uncalibrated intervals (``raw``), the Gaussian variance scale from the
same folds (``gaussian``) and the per-level conformal thresholds (``conformal``); the targets
are 0.63-0.73 / 0.93-0.97 / >= 0.90. Cost: 229-465 s for the six sets (3 blocks; the
calibration is ~90 % of it), ``--quick`` 2 blocks.

``--aci``: the monitor loop (``temporal="ar1"`` filter, conformal calibration) through the last
24 snapshots, with the offline thresholds and with online ACI (``gamma`` 0.02, 0.05)
(:func:`aci_coverage`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import pandas as pd

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from generalization_data import (  # noqa: E402
    ALL_DATASETS,
    DATASETS,
    HOLDOUT_DATASETS,
    PLANTED_DATASETS,
    SHORT_DATASETS,
    available,
    install_commands,
    load,
)

warnings.filterwarnings("ignore")

RECOMMENDED = "greedy:gp-variance"
BASELINES = ("transect-up", "transect-down", "transect-left", "transect-right", "random")
RANK, N_TEST = 5, 8
RANK_OVERRIDE = None
"""``--rank``: the recommended model's rank instead of the protocol's :data:`RANK` (an integer,
or ``"auto"``: ``GLRM(rank="auto")``, validated with the temporal model). :data:`RANK` stays
the rank of the fixed-kind checks (the memoryless coverage variant, ``--aci``, ``--modes
ar1``)."""


LAST: int | None = None
"""``--last N``: every record cut to its last ``N`` snapshots (a short record)."""
TRAINING_ONLY: bool = False
"""``--training-only``: every record without its last ``N_TEST`` snapshots (the test block),
so a run is a validation on the training snapshots (diagnostics that must not see the test)."""


CLOUDS: float = 0.0
"""``--clouds F``: that fraction of every snapshot's values hidden by moving clouds
(``generalization_data.load``), in training and test alike."""


def load_record(name: str):
    """The data set ``name`` (``ALL_DATASETS``; with :data:`CLOUDS` gaps), without its test
    block under :data:`TRAINING_ONLY`, then cut to its last :data:`LAST` snapshots."""
    data = load(name, clouds=CLOUDS)
    if TRAINING_ONLY:
        data = data.isel(time=slice(None, -N_TEST))
    return data if LAST is None else data.isel(time=slice(-int(LAST), None))


def recommended_params(**override) -> dict:
    """The recommended GLRM parameters (``lrm_cvx.recommended.RECOMMENDED``'s model keys: offset,
    spatial residual, ``temporal="auto"``, calibration) at rank :data:`RANK` (or
    :data:`RANK_OVERRIDE`), ``override`` applied; a fixed temporal kind (``--modes ar1``) is
    fitted at :data:`RANK` (``rank="auto"`` validates with ``temporal="auto"`` or none)."""
    from lrm_cvx import GLRM

    params = {**GLRM.recommended_params(), "rank": RANK if RANK_OVERRIDE is None
              else RANK_OVERRIDE, "random_state": 0, "progress": False, **override}
    if params.get("rank") == "auto" and params.get("temporal") not in (None, "auto"):
        params["rank"] = RANK
    return params


def run_set(name: str, budgets: tuple, n_starts: int, random_trials: int,
            out: str | None = None, n_jobs: int = 1, modes: tuple = ("auto",),
            **params) -> tuple[pd.DataFrame, dict]:
    """Fit and evaluate one data set; returns the tidy table (one row per temporal mode, budget,
    method) and timings. ``modes``: the temporal models run (``"auto"``: the recommended
    setting; ``"ar1"`` / ``"seasonal"``: the fixed kinds, for the record). The memoryless rows
    come from the first mode's campaigns (memoryless through the same loop: the same starts
    and data). ``params``: GLRM parameters over the recommended ones (e.g. ``spatial``)."""
    from lrm_cvx import GLRM, evaluate
    from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, summary

    d = ALL_DATASETS[name]
    data = load_record(name)
    train = data.isel(time=slice(None, -N_TEST))
    modes = [m for m in modes if m != "seasonal" or d.seasonal]
    frames, times = [], {}
    for temporal in modes:
        t0 = time.perf_counter()
        model = GLRM(**recommended_params(temporal=temporal, **params)).fit(train)
        t1 = time.perf_counter()
        if temporal == "auto":
            print(f"[{name}] temporal='auto' chose {model.selection_.attrs['choice']!r}",
                  flush=True)
        if getattr(model, "kernel_selection_", None) is not None:
            print(f"[{name}] spatial='auto' chose "
                  f"{model.kernel_selection_.attrs['choice']!r}", flush=True)
        res = evaluate(data, model=model, n_test=N_TEST, budgets=budgets, n_starts=n_starts,
                       methods=(RECOMMENDED,) + BASELINES, progress=False,
                       temporal=temporal, seed=0,
                       planning=PlanningOptions(random_trials=random_trials, certify=False,
                                                n_jobs=n_jobs),
                       scoring=ScoringOptions(min_observations=1,
                                              fold_in={"prior": "empirical", "spatial": True}))
        times[temporal] = (t1 - t0, time.perf_counter() - t1)
        table = summary(res).merge(paired_bounds(res), on=["method", "budget"], how="left")
        table["set"] = name
        if out:
            os.makedirs(out, exist_ok=True)
            table.to_csv(os.path.join(out, f"{name}_{temporal}.csv"), index=False)
        if not frames:  # memoryless rows: the same campaigns, memoryless through the same loop
            mem = table.copy()
            mem["temporal"] = "none"
            mem["mse_mean"] = mem["mse_memoryless_mean"]
            for c in ("68", "95"):
                mem[f"coverage{c}_mean"] = mem[f"coverage{c}_memoryless_mean"]
            frames.append(mem)
        frames.append(table)
    return pd.concat(frames, ignore_index=True), times


def paired_upper(a, b, z: float = 1.645) -> float:
    """One-sided 95 % upper bound of ``mean(a) / mean(b) - 1`` from paired per-start values
    ``a``, ``b`` ``(n_starts,)`` (the campaigns share their starts, so the start-to-start spread
    cancels: tighter than the unpaired bound of two means' standard errors)."""
    import numpy as np

    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size < 2:
        return float("nan")
    d = a - b
    return float((d.mean() + z * d.std(ddof=1) / np.sqrt(d.size)) / b.mean())


def paired_bounds(res) -> pd.DataFrame:
    """Per budget, paired per-start upper bounds (:func:`paired_upper`) on the campaigns of one
    ``evaluate``: ``mem_ub`` on the greedy's row (its MSE against its memoryless twin's) and,
    on each baseline's row, ``greedy_ub`` (the greedy against that baseline). Per-start values
    average the test snapshots and the random walks."""
    import numpy as np

    def per_start(var, method, budget):
        return (res[var].sel({"method": method, "budget": budget})
                .mean([d for d in ("trial", "test_time") if d in res[var].dims]).values)

    rows = []
    for budget in res["budget"].values:
        g = per_start("mse", RECOMMENDED, budget)
        mem = (paired_upper(g, per_start("mse_memoryless", RECOMMENDED, budget))
               if "mse_memoryless" in res else np.nan)
        rows.append({"method": RECOMMENDED, "budget": float(budget), "mem_ub": mem})
        rows += [{"method": m, "budget": float(budget),
                  "greedy_ub": paired_upper(g, per_start("mse", m, budget))}
                 for m in BASELINES]
    return pd.DataFrame(rows)


def report(name: str, tidy: pd.DataFrame) -> pd.DataFrame:
    """One row per budget: greedy MSE per temporal mode, best baseline, coverage, and
    ``complete``: the map MSE of the paper's fold-in from every observed cell (``complete_mse``,
    what sampling everything would give the memoryless least-squares map)."""
    rows = []
    for budget, by_budget in tidy.groupby("budget"):
        row = {"set": name, "budget": int(budget)}
        for temporal, t in by_budget.groupby("temporal", sort=False):
            t = t.set_index("method")
            g = float(t.loc[RECOMMENDED, "mse_mean"])
            base = t.loc[list(BASELINES), "mse_mean"].astype(float)
            best = base.idxmin()
            tag = {"none": "mem", "ar1": "ar1", "seasonal": "seas", "auto": "auto"}[temporal]
            row[f"greedy_{tag}"] = g
            row[f"best_base_{tag}"] = f"{float(base[best]):.4g} ({best.replace('transect-', 't-')})"
            row[f"vs_best_{tag}"] = f"{100 * (g / float(base[best]) - 1):+.0f}%"
            if temporal != "none" and "greedy_ub" in t:  # paired bound against every baseline
                worst = float(t.loc[list(BASELINES), "greedy_ub"].max())
                row[f"vs_all_ub_{tag}"] = f"{100 * worst:+.0f}%"
            row[f"cov68/95_{tag}"] = (f"{float(t.loc[RECOMMENDED, 'coverage68_mean']):.2f}/"
                                      f"{float(t.loc[RECOMMENDED, 'coverage95_mean']):.2f}")
        if "complete_mse" in by_budget:  # the paper's fold-in from every observed cell
            row["complete"] = float(by_budget["complete_mse"].iloc[0])
        for tag in ("ar1", "seas", "auto"):
            if f"greedy_{tag}" in row:
                change = row[f"greedy_{tag}"] / row["greedy_mem"] - 1
                row[f"{tag}_vs_mem"] = f"{100 * change:+.0f}%"
                mine = by_budget[(by_budget["temporal"] == {"seas": "seasonal"}.get(tag, tag))
                                 & (by_budget["method"] == RECOMMENDED)]
                if "mem_ub" in mine:  # paired per-start bound (the target: <= +2 %)
                    row[f"{tag}_vs_mem_ub"] = f"{100 * float(mine['mem_ub'].iloc[0]):+.0f}%"
        rows.append(row)
    return pd.DataFrame(rows)


def origin_split(data, origin: int, block: int = N_TEST):
    """``(train, through)``: the snapshots before ``origin`` (what the fit and the calibration
    see) and those up to the end of the test block ``[origin, origin + block)``."""
    return data.isel(time=slice(None, origin)), data.isel(time=slice(None, origin + block))


def calibrated_variants(model, train, levels=(0.68, 0.95), seed: int = 0, **kw) -> dict:
    """``{"raw": None, "gaussian": ..., "conformal": ...}``: the calibrations compared, from one
    ``calibrate(method="conformal")`` on ``train`` only (the Gaussian one is the same without
    its conformal thresholds)."""
    from dataclasses import replace

    from lrm_cvx.validation.calibration import calibrate

    cal = calibrate(model, train, method="conformal", levels=levels, seed=seed, **kw)
    gauss = replace(cal, method="gaussian", levels=(), quantiles=(), score_table=(),
                    size_quantiles=(), temporal_size_quantiles=())
    return {"raw": None, "gaussian": gauss, "conformal": cal}


CALIBRATE_KW = {"n_blocks": 8, "max_snapshots": 2, "max_cells": 300}
"""The calibration's cost settings in the coverage check (conformal's default forward folds:
the 4 blocks of the record's second half, 2 held-out snapshots each, at most 300 scored cells
per fold-in; ``--folds interleaved``: 4 interleaved folds)."""


def filter_variants(model, train, seed: int = 0, **kw) -> dict:
    """``{"raw": None, "shared": ..., "filter": ...}`` for a model with dynamics: one
    ``calibrate(method="conformal", temporal="auto")`` on ``train`` only, its intervals under
    the filter with the memoryless thresholds (``shared``: the default calibration) or the
    filter's own (``filter``: ``temporal_scale`` and ``temporal_quantiles``)."""
    from dataclasses import replace

    from lrm_cvx.validation.calibration import calibrate

    cal = calibrate(model, train, method="conformal", temporal="auto", seed=seed, **kw)
    # the default calibrate(method="conformal")
    shared = replace(cal, temporal_scale=None, temporal_quantiles=(), temporal_score_table=(),
                     temporal_size_quantiles=(), temporal_n_residuals=0)
    return {"raw": None, "shared": shared, "filter": cal}


def rolling_coverage(data, n_origins: int = 3, block: int = N_TEST, budget: int = 15,
                     n_starts: int = 2, seed: int = 0, calibrate_kw: dict | None = None,
                     temporal: str | None = None) -> pd.DataFrame:
    """Coverage of the greedy's intervals on ``n_origins`` rolling test blocks (module
    docstring): one row per block and calibration variant, with ``cov68``, ``cov95`` (mean
    over the block's campaigns and snapshots) and the calibration's cost in seconds.
    ``temporal="auto"``: the recommended model (its ``temporal="auto"`` and ``spatial``
    choices made on the snapshots before the block), the recommended calibration's keywords
    (``RECOMMENDED["calibration"]``, ``calibrate_kw`` ignored) and its filter's campaigns, the
    variants of :func:`filter_variants`."""
    from lrm_cvx import GLRM, evaluate
    from lrm_cvx.evaluation import PlanningOptions, ScoringOptions, summary

    T = data.sizes["time"]
    rows = []
    for b in range(n_origins):
        origin = T - (n_origins - b) * block
        train, through = origin_split(data, origin, block)
        if temporal is None:
            model = GLRM(rank=RANK, offset=True, spatial="exponential", random_state=0,
                         progress=False).fit(train)
        else:
            model = GLRM(**recommended_params(temporal=temporal, calibration=None)).fit(train)
        t0 = time.perf_counter()
        if temporal is None:
            kw = CALIBRATE_KW if calibrate_kw is None else calibrate_kw
            variants = calibrated_variants(model, train, seed=seed, **kw)
        else:  # the recommended calibration's own keywords (intervals only)
            from lrm_cvx.recommended import RECOMMENDED as SETTING

            kw = {k: v for k, v in SETTING["calibration"].items()
                  if k not in ("method", "temporal")}  # filter_variants sets both
            variants = filter_variants(model, train, seed=seed, **kw)
        cost = time.perf_counter() - t0
        for name, cal in variants.items():
            model.calibration_ = cal
            res = evaluate(through, model=model, n_test=block, budgets=(budget,),
                           n_starts=n_starts, methods=(RECOMMENDED,),
                           progress=False, seed=seed, temporal=temporal,
                           planning=PlanningOptions(certify=False),
                           scoring=ScoringOptions(min_observations=1,
                                                  fold_in={"prior": "empirical", "spatial": True}))
            row = summary(res).iloc[0]
            rows.append({"block": b, "origin": origin, "variant": name,
                         "cov68": float(row["coverage68_mean"]),
                         "cov95": float(row["coverage95_mean"]),
                         "mse": float(row["mse_mean"]), "calibrate_s": cost})
    return pd.DataFrame(rows)


def aci_coverage(data, n_days: int = 3 * N_TEST, size: int = 15,
                 gammas: tuple = (None, 0.02, 0.05), seed: int = 0) -> pd.DataFrame:
    """The monitor loop with and without online ACI: the ``temporal="ar1"`` model fitted and
    conformally calibrated on all but the last ``n_days`` snapshots, then ``MonitorState``
    through them, one route-like set of ``size`` cells a day (the same cells for every
    ``gamma``); coverage of the posterior's intervals at the day's other observed cells. One
    row per ``gamma`` (None: the offline thresholds, no ACI): mean 68 / 95 % coverage and the
    lowest 8-day block's 95 %."""
    import numpy as np

    from lrm_cvx import GLRM
    from lrm_cvx.glrm.calibrated import interval_coverage
    from lrm_cvx.monitor import MonitorState
    from lrm_cvx.validation.calibration import calibrate
    from lrm_cvx.validation.designs import sample_sets

    train, test = data.isel(time=slice(None, -n_days)), data.isel(time=slice(-n_days, None))
    model = GLRM(rank=RANK, offset=True, spatial="exponential", temporal="ar1", random_state=0,
                 progress=False).fit(train)
    calibrate(model, train, method="conformal", seed=seed, **CALIBRATE_KW)
    V = model.region_.stack(test).astype(float)
    rng = np.random.default_rng(seed)
    days = [sample_sets(model.region_, np.isfinite(V[i]), size, "route", rng)
            for i in range(n_days)]
    rows = []
    for gamma in gammas:
        state = MonitorState.from_model(model, online=False)
        if gamma:
            state.adaptive_conformal(gamma=gamma)
        cov = []
        for i, t in enumerate(test["time"].values):  # a loop over days
            cells = days[i]
            state.assimilate((cells, V[i, cells]), time=t)
            held = np.setdiff1d(np.flatnonzero(np.isfinite(V[i])), cells)
            mean, _, pstd = state.posterior.predict_all(cells=held)
            cov.append(interval_coverage(V[i, held], mean, pstd,
                                         multipliers=state.interval_multipliers()))
        c = np.array(cov)
        blocks = c[: n_days // N_TEST * N_TEST, 1].reshape(-1, N_TEST).mean(axis=1)
        rows.append({"gamma": "none" if gamma is None else gamma, "cov68": c[:, 0].mean(),
                     "cov95": c[:, 1].mean(), "cov95_min_block": blocks.min()})
    return pd.DataFrame(rows)


def coverage_report(name: str, table: pd.DataFrame) -> pd.DataFrame:
    """Per variant: mean 68 % / 95 % coverage over the blocks and the lowest block's 95 %."""
    out = table.groupby("variant", sort=False).agg(
        cov68_mean=("cov68", "mean"), cov95_mean=("cov95", "mean"),
        cov95_min_block=("cov95", "min"), mse=("mse", "mean"))
    out.insert(0, "set", name)
    return out.reset_index()


def forecast_vs_posterior(data, n_starts: int = 3, budget: float = 15.0) -> pd.DataFrame:
    """Per temporal mode (memoryless, the model's ``temporal="auto"`` choice): the campaign's
    mean map MSE of the morning forecast and of the posterior after the day's samples over the
    last ``N_TEST`` snapshots, ``n_starts`` starts, greedy gp-variance (a
    posterior never worse than its forecast on average), with a 95 % interval of the change
    from the paired (start, day) differences."""
    import numpy as np

    from lrm_cvx import GLRM
    from lrm_cvx.campaign import simulate_campaign

    train, test = data.isel(time=slice(None, -N_TEST)), data.isel(time=slice(-N_TEST, None))
    model = GLRM(**recommended_params()).fit(train)
    valid = np.flatnonzero(np.isfinite(model.region_.stack(test.isel(time=0))))
    starts = np.random.default_rng(0).choice(valid, size=n_starts, replace=False)
    rows = []
    for temporal in (None, "auto"):
        runs = [simulate_campaign(model, test, int(s), budget, temporal=temporal)
                for s in starts]
        fcs = np.concatenate([r["mse_forecast"].values for r in runs])  # (start, day) pairs
        posts = np.concatenate([r["mse"].values for r in runs])
        fc, post = fcs.mean(), posts.mean()
        d = posts - fcs  # paired: the same day's map before and after its samples
        change, half = post / fc - 1, 1.96 * d.std(ddof=1) / np.sqrt(d.size) / fc
        rows.append({"temporal": "none" if temporal is None else
                     f"auto ({model.selection_.attrs['choice']})", "forecast": fc,
                     "posterior": post, "change": f"{100 * change:+.1f}%",
                     "ci95": f"{100 * (change - half):+.1f}..{100 * (change + half):+.1f}%",
                     "days_worse": f"{np.mean(d > 0):.2f}"})
    return pd.DataFrame(rows)


def residual_growth(data, step: int = 4) -> pd.DataFrame:
    """How a new snapshot's residual compares with what the model predicts, by training length:
    the memoryless model of the coverage check (rank :data:`RANK`, offset, exponential
    residual) refitted on the first ``n`` snapshots, the next ``step`` folded in with every cell
    observed (the latent row fitted to all of them: the residual the basis leaves); per ``n``
    the in-sample residual variance, the predicted one (the spatial covariance's sill + nugget
    times ``residual_factor``), the out-of-sample one, and ``oos / predicted``. A ratio that
    grows with ``n`` is a record whose later blocks are further from their past than the
    earlier blocks were (the forward folds' conformal thresholds then under-cover)."""
    import numpy as np

    from lrm_cvx import GLRM
    from lrm_cvx.belief.posterior import fold_in_snapshots
    from lrm_cvx.glrm.calibrated import residual_factor

    T = data.sizes["time"]
    rows = []
    for n in range(max(8, T // 4), T - step + 1, step):
        model = GLRM(rank=RANK, offset=True, spatial="exponential", random_state=0,
                     progress=False).fit(data.isel(time=slice(None, n)))
        prior = model.latent_prior("empirical", spatial=False)
        errors = []
        for part in (slice(None, n), slice(n, n + step)):
            V = model.region_.stack(data.isel(time=part)).astype(np.float64)
            pred, *_ = fold_in_snapshots(prior, V)
            errors.append(float(np.nanmean((pred - V) ** 2)))
        cov, factor = model.spatial_cov_, residual_factor(model)
        predicted = (cov.sill + cov.nugget) * factor
        rows.append({"n": n, "factor": factor, "in_sample": errors[0],
                     "predicted": predicted, "out_of_sample": errors[1],
                     "oos_over_predicted": errors[1] / predicted})
    return pd.DataFrame(rows)


def _per_set(names: list, table_of, fmt: str) -> None:
    """Print ``table_of(data)`` (a DataFrame) for each set of ``names``, with its wall time."""
    for name in names:
        t0 = time.perf_counter()
        table = table_of(load_record(name))
        table.insert(0, "set", name)
        print(table.to_string(index=False, float_format=fmt.format))
        print(f"[{name}] {time.perf_counter() - t0:.0f} s\n", flush=True)


def main() -> None:
    global RANK_OVERRIDE, LAST, TRAINING_ONLY, CLOUDS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="budget 15 only, 3 starts, 3 random walks per start")
    ap.add_argument("--data", nargs="*", default=None,
                    help=f"data sets (default: all of {list(DATASETS)}; also "
                         f"{list(SHORT_DATASETS)}, {list(HOLDOUT_DATASETS)} and the planted "
                         f"{list(PLANTED_DATASETS)})")
    ap.add_argument("--holdout", action="store_true",
                    help=f"the hold-out sets {list(HOLDOUT_DATASETS)} instead (no choice was "
                         "made on them)")
    ap.add_argument("--starts", type=int, default=None)
    ap.add_argument("--trials", type=int, default=None, help="random walks per start")
    ap.add_argument("--jobs", type=int, default=1, help="evaluate's n_jobs")
    ap.add_argument("--out", default=None, help="write the summary tables as CSV here")
    ap.add_argument("--coverage", action="store_true",
                    help="the rolling-origin coverage check instead (module docstring)")
    ap.add_argument("--aci", action="store_true",
                    help="the monitor loop with / without online ACI (aci_coverage)")
    ap.add_argument("--folds", default="forward", choices=("interleaved", "forward"),
                    help="the coverage check's calibration folds (calibrate(folds=))")
    ap.add_argument("--temporal", default=None, choices=("auto",),
                    help="the coverage check under the recommended filter (temporal='auto')")
    ap.add_argument("--origins", type=int, default=None,
                    help="test blocks of the coverage check (default 3; --quick 2)")
    ap.add_argument("--modes", default="auto",
                    help="temporal models run, comma-separated (default auto, the recommended "
                         "setting; ar1,seasonal,auto adds the fixed kinds)")
    ap.add_argument("--spatial", default=None,
                    help="the GLRM's spatial= instead of the recommended one (e.g. auto)")
    ap.add_argument("--rank", default=None,
                    help="the recommended GLRM's rank instead of its own (auto): an integer "
                         f"({RANK}: the protocol's) or auto")
    ap.add_argument("--forecast", action="store_true",
                    help="posterior vs forecast map MSE of the campaigns (forecast_vs_posterior)")
    ap.add_argument("--last", type=int, default=None,
                    help="cut every record to its last N snapshots (a short record)")
    ap.add_argument("--training-only", action="store_true",
                    help="drop every record's test block first (a validation-style run)")
    ap.add_argument("--residual-growth", action="store_true",
                    help="a new snapshot's residual over the predicted one, by training length "
                         "(residual_growth)")
    ap.add_argument("--clouds", type=float, default=0.0,
                    help="hide this fraction of every snapshot's values under moving clouds "
                         "(e.g. 0.3; lrm_cvx.io.cloud_gaps)")
    args = ap.parse_args()
    if not 0.0 <= args.clouds < 1.0:
        ap.error(f"--clouds must be in [0, 1), got {args.clouds}")
    CLOUDS = args.clouds
    if args.rank is not None:
        RANK_OVERRIDE = args.rank if args.rank == "auto" else int(args.rank)
    if args.last is not None and args.last < 2:
        ap.error(f"--last must be at least 2 snapshots, got {args.last}")
    LAST, TRAINING_ONLY = args.last, args.training_only

    budgets = (15,) if args.quick else (15, 30, 60)
    n_starts = args.starts or (3 if args.quick else 10)
    trials = args.trials or (3 if args.quick else 5)
    names = args.data or list(HOLDOUT_DATASETS if args.holdout else DATASETS)
    ok = available()
    missing = [n for n in names if not ok.get(n, False)]
    if missing:
        print(f"not installed: {missing}; install with: {' ; '.join(install_commands())}")
        names = [n for n in names if n not in missing]

    if args.forecast:
        print(f"campaigns over the last {N_TEST} snapshots, greedy {RECOMMENDED} budget 15, "
              "3 starts: map MSE of the morning forecast vs the posterior after the samples",
              flush=True)
        _per_set(names, forecast_vs_posterior, "{:.4g}")
        return
    if args.residual_growth:
        print(f"rank {RANK}, offset, exponential residual refitted on the first n snapshots; "
              "the next 4 folded in with every cell observed", flush=True)
        _per_set(names, residual_growth, "{:.4g}")
        return
    if args.aci:
        print(f"monitor loop (ar1 filter, conformal calibration) through the last {3 * N_TEST} "
              "snapshots, a 15-cell route a day; coverage at the other cells", flush=True)
        _per_set(names, aci_coverage, "{:.3f}")
        return
    if args.coverage:
        origins = args.origins or (2 if args.quick else 3)
        starts = args.starts or 2
        rank = recommended_params()["rank"] if args.temporal else RANK
        print(f"rolling origin: {origins} blocks of {N_TEST} snapshots, rank {rank}, greedy "
              f"{RECOMMENDED} budget 15, {starts} starts, {args.temporal or 'memoryless'}; "
              "calibrated on the "
              f"snapshots before each block only ({args.folds} folds)", flush=True)
        t_all = time.perf_counter()
        for name in names:
            t0 = time.perf_counter()
            kw = {**CALIBRATE_KW, "folds": args.folds}
            if args.folds == "interleaved":
                kw["n_blocks"] = 4
            table = rolling_coverage(load_record(name),
                                     n_origins=origins, n_starts=starts, calibrate_kw=kw,
                                     temporal=args.temporal)
            if args.out:
                os.makedirs(args.out, exist_ok=True)
                table.to_csv(os.path.join(args.out, f"{name}_coverage.csv"), index=False)
            with pd.option_context("display.width", 250, "display.max_columns", 30):
                print(coverage_report(name, table).to_string(
                    index=False, float_format=lambda v: f"{v:.3f}"))
            print(f"[{name}] {time.perf_counter() - t0:.0f} s (calibrate "
                  f"{table.groupby('block')['calibrate_s'].first().sum():.0f} s)\n", flush=True)
        print(f"total {time.perf_counter() - t_all:.0f} s")
        return

    print(f"rank {recommended_params()['rank']}, last {N_TEST} snapshots held out, budgets "
          f"{budgets}, {n_starts} starts, "
          f"{trials} random walks per start; greedy = {RECOMMENDED}, the recommended GLRM "
          f"({recommended_params()}), empirical prior with kriging"
          + (f"; {CLOUDS:g} of every snapshot's values under clouds" if CLOUDS else ""),
          flush=True)
    t_all = time.perf_counter()
    tables = []
    for name in names:
        t0 = time.perf_counter()
        tidy, times = run_set(name, budgets, n_starts, trials, args.out, args.jobs,
                              modes=tuple(m.strip() for m in args.modes.split(",")),
                              **({"spatial": args.spatial} if args.spatial else {}))
        table = report(name, tidy)
        tables.append(table)
        with pd.option_context("display.width", 250, "display.max_columns", 30):
            print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
        fits = ", ".join(f"{k}: fit {a:.1f} s + evaluate {b:.0f} s" for k, (a, b) in times.items())
        print(f"[{name}] {time.perf_counter() - t0:.0f} s ({fits})\n", flush=True)
    print(f"total {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
