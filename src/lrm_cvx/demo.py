"""``lrm-cvx demo``: the whole pipeline on the bundled SST sample in well under a minute.

Fits the recommended and the paper's model on all winters but the last ``n_test``, scores both
and the baselines on the held-out winters, and writes the results, a summary and two figures.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._blas import single_threaded_blas
from .recommended import RECOMMENDED as SETTING  # the setting; RECOMMENDED here is its label
from .validation.selection import format_selection

__all__ = ["run_demo", "DemoResult", "DEMO_SETTINGS", "RECOMMENDED", "PAPER", "format_summary"]

#: The demo's protocol (a reduced version of the paper's: same model rank and test split).
DEMO_SETTINGS: dict[str, Any] = {
    "sample": "sst", "rank": 5, "n_test": 8, "budgets": (10.0, 20.0, 40.0), "n_starts": 6,
    "random_trials": 10, "min_observations": 5, "seed": 0,
}
#: Labels of the two settings in the summary (the recommended one is listed first).
RECOMMENDED = "recommended: gp-variance greedy + GP fold-in"
PAPER = "paper: Fisher greedy + least-squares fold-in"
BASELINES = ("random", "transect-up", "transect-down", "transect-left", "transect-right")
_BASELINE_LABEL = {"random": "random walk", **{f"transect-{d}": f"transect {d}"
                                               for d in ("up", "down", "left", "right")}}


@dataclass
class DemoResult:
    """What :func:`run_demo` produced: the summary table (``setting``, ``budget``, ``mse_mean``,
    ``mse_se``, ``n``; recommended setting first), its one-screen text, the written files and
    the seconds per stage."""

    table: Any
    text: str
    paths: list[Path] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


def _mse_rows(results: Any, method: str, setting: str) -> list[dict]:
    rows = []
    for budget in results["budget"].values:
        err = results["mse"].sel({"method": method, "budget": budget}).values.ravel()
        err = err[np.isfinite(err)]
        rows.append({"setting": setting, "budget": float(budget),
                     "mse_mean": float(err.mean()) if err.size else np.nan,
                     "mse_se": float(err.std(ddof=1) / np.sqrt(err.size)) if err.size > 1
                     else np.nan, "n": int(err.size)})
    return rows


def format_summary(table: Any, *, units: str = "", title: str = "", notes: Sequence[str] = ()
                   ) -> str:
    """The summary as one screen of text: one row per setting, one column per budget (mean
    MSE +- standard error), in the table's row order (recommended first)."""
    budgets = sorted(table["budget"].unique())
    settings = list(dict.fromkeys(table["setting"]))
    width = max(len(s) for s in settings)
    unit = f" ({units})^2" if units else ""
    lines = [title] if title else []
    lines.append(f"reconstruction MSE{unit}, mean +- s.e. over start cells x test snapshots")
    head = f"{'setting':<{width}}" + "".join(f"{f'budget {b:g}':>18}" for b in budgets)
    lines += [head, "-" * len(head)]
    for s in settings:
        rows = table[table["setting"] == s].set_index("budget")
        cells = []
        for b in budgets:
            m, se = rows.loc[b, "mse_mean"], rows.loc[b, "mse_se"]
            cells.append(f"{m:.4f} +- {se:.4f}" if np.isfinite(m) else "n/a")
        lines.append(f"{s:<{width}}" + "".join(f"{c:>18}" for c in cells))
    lines += list(notes)
    return "\n".join(lines)


def run_demo(out_dir: str | Path, *, progress: Callable[[str], None] | None = print,
             settings: dict[str, Any] | None = None) -> DemoResult:
    """Run the demo pipeline and write its outputs into ``out_dir`` (created if needed).

    ``progress`` receives one line per stage (None: silent). ``settings`` overrides entries of
    :data:`DEMO_SETTINGS` (tests use a smaller protocol). Returns a :class:`DemoResult`.
    BLAS runs single-threaded meanwhile (tiny matrices; see ``lrm_cvx._blas``).
    """
    with single_threaded_blas():
        return _run_demo(out_dir, progress=progress, settings=settings)


def _run_demo(out_dir: str | Path, *, progress: Callable[[str], None] | None,
              settings: dict[str, Any] | None) -> DemoResult:
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    say = progress or (lambda _msg: None)

    def lap(name: str, t0: float) -> float:
        now = time.perf_counter()
        timings[name] = now - t0
        return now

    import pandas as pd

    from ._validation import atomic_output
    from .datasets import load_sample
    from .errors import DataError
    from .evaluation import PlanningOptions, ScoringOptions, evaluate
    from .glrm import GLRM
    from .planning import plan_greedy

    cfg = {**DEMO_SETTINGS, **(settings or {})}
    bad = set(cfg) - set(DEMO_SETTINGS)
    if bad:
        raise DataError(f"unknown demo settings {sorted(bad)}; expected among "
                        f"{sorted(DEMO_SETTINGS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = lap("imports", t_start)

    data = load_sample(cfg["sample"])
    units = data.attrs.get("units", "")
    n_test, rank, seed = int(cfg["n_test"]), int(cfg["rank"]), int(cfg["seed"])
    train = data.isel(time=slice(None, -n_test))
    say(f"sample {cfg['sample']!r}: {dict(data.sizes)} {data.attrs.get('long_name', '')} "
        f"({units}); training on {train.sizes['time']}, testing on the last {n_test} snapshots")
    rec = GLRM(rank, offset=SETTING["offset"], spatial=SETTING["spatial"], random_state=seed,
               temporal=SETTING["temporal"], progress=False).fit(train)
    t = lap("fit recommended", t)
    paper = GLRM(rank, random_state=seed, progress=False).fit(train)
    t = lap("fit paper", t)
    say(f"fitted rank-{rank} GLRMs ({timings['fit recommended'] + timings['fit paper']:.1f} s)")

    common = dict(rank=rank, n_test=n_test, budgets=cfg["budgets"], n_starts=int(cfg["n_starts"]),
                  seed=seed, progress=False)
    trials, least = int(cfg["random_trials"]), int(cfg["min_observations"])
    fold_in = {"prior": SETTING["prior"], "spatial": SETTING["fold_spatial"]}
    res_rec = evaluate(data, model=rec, methods=(SETTING["method"], *BASELINES),
                       planning=PlanningOptions(random_trials=trials, certify=False),
                       scoring=ScoringOptions(fold_in=fold_in, min_observations=least), **common)
    t = lap("evaluate recommended", t)
    res_paper = evaluate(data, model=paper, methods=("greedy",), paper=True,
                         planning=PlanningOptions(random_trials=trials, certify="fast"),
                         scoring=ScoringOptions(min_observations=least), **common)
    t = lap("evaluate paper (+ certify)", t)
    say(f"evaluated {len(cfg['budgets'])} budgets x {cfg['n_starts']} starts x {n_test} test "
        f"snapshots ({timings['evaluate recommended'] + timings[list(timings)[-1]]:.1f} s)")

    rows = _mse_rows(res_rec, SETTING["method"], RECOMMENDED)
    rows += _mse_rows(res_paper, "greedy", PAPER)
    for m in BASELINES:
        rows += _mse_rows(res_rec, m, _BASELINE_LABEL[m])
    table = pd.DataFrame(rows)
    bound = res_paper["bound"].mean("start").values
    info = res_paper["information"].isel(method=0, trial=0).mean("start").values
    notes = ["paper's greedy Fisher information / certified bound (nats): " + ", ".join(
        f"{float(i):.1f}/{float(b):.1f}" for i, b in zip(info, bound, strict=True)),
        f"recommended = GLRM(offset={SETTING['offset']}, spatial={SETTING['spatial']!r}: "
        f"{rec.spatial_cov_.model} chosen), greedy "
        f"{SETTING['criterion']!r} from the",
        f"  start cell, fold-in prior={SETTING['prior']!r}, spatial={SETTING['fold_spatial']} "
        "(docs/reconstruction.md);",
        "  paper = GLRM(5), greedy Fisher, least-squares fold-in; baselines: recommended fold-in",
        f"budget in grid cells; {cfg['n_starts']} start cells, {cfg['random_trials']} random "
        f"walks each, {n_test} held-out snapshots",
        "monitoring: " + format_selection(rec.selection_, short=True)]
    text = format_summary(table, units=units, notes=notes,
                          title=f"lrm-cvx demo: {data.attrs.get('long_name', data.name)}")

    paths = []
    for name, res in (("results_recommended.nc", res_rec), ("results_paper.nc", res_paper)):
        with atomic_output(out / name) as tmp:
            res.to_netcdf(tmp, engine="netcdf4")
        paths.append(out / name)
    with atomic_output(out / "summary.csv") as tmp:
        table.to_csv(tmp, index=False)
    with atomic_output(out / "summary.txt") as tmp:
        Path(tmp).write_text(text + "\n")
    paths += [out / "summary.csv", out / "summary.txt"]
    t = lap("write results", t)

    # qualitative figure: the first start cell, smallest and largest budget, first test winter
    from .plots import plot_demo_metrics, plot_prediction_panels, save_figure

    region = rec.region_
    start = int(res_rec["start_cell"].values[0])
    snap = data.isel(time=train.sizes["time"])
    values = region.stack(snap)
    kw = rec.planner_kwargs(prior=SETTING["prior"], spatial=True)
    panel_rows = []
    budgets = cfg["budgets"]
    for b in sorted({budgets[0], budgets[-1]}):
        plan = plan_greedy(rec.Y_, region, start, b, criterion=SETTING["criterion"],
                           initial=SETTING["initial"], refine=SETTING["refine"],
                           progress=False, **kw)
        panel_rows.append(_panel(rec, values, plan.route, region, f"recommended, budget {b:g}",
                                 units, prior=SETTING["prior"], spatial=SETTING["fold_spatial"]))
    route = res_paper["greedy_route"].sel(budget=budgets[-1]).isel(start=0).values
    route = route[route >= 0]
    panel_rows.append(_panel(paper, values, route, region,
                             f"paper, budget {budgets[-1]:g}", units))
    t = lap("plan figure routes", t)
    figs = save_figure(plot_prediction_panels(snap, panel_rows), out / "predictions")
    figs += save_figure(plot_demo_metrics(table, units=units), out / "metrics")
    paths += figs
    t = lap("figures", t)
    timings["total"] = time.perf_counter() - t_start
    say("stage seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    return DemoResult(table=table, text=text, paths=paths, timings=timings)


def _panel(model: Any, values: np.ndarray, route: Any, region: Any, label: str, units: str,
           **complete_kw: Any) -> dict:
    """One row of the predictions figure: fold the snapshot in at the route's cells."""
    import xarray as xr

    route = np.asarray(route, dtype=np.int64)
    seen = np.unique(route[np.isfinite(values[route])])
    ds = model.complete((seen, values[seen]), **complete_kw)
    truth = region.unstack(values)
    err = float(np.nanmean((ds["prediction"].values - truth.values) ** 2))
    unit = f" {units}\N{SUPERSCRIPT TWO}" if units else ""
    return {"label": f"{label}, MSE {err:.3g}{unit}", "prediction": ds["prediction"],
            "std": ds["std"],
            "route": xr.Dataset({"lat": ("step", region.cell_lat[route]),
                                 "lon": ("step", region.cell_lon[route])})}
