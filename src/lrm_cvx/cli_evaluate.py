"""``lrm-cvx evaluate`` and ``demo``: the paper's protocol on a record, and the first-run
pipeline on the bundled sample.

``evaluate`` fits the model on all but the last ``--n-test`` snapshots (or each block of a
rolling-origin backtest), runs :func:`lrm_cvx.evaluation.evaluate` and writes every table and
figure in one all-or-nothing step; ``demo`` runs :func:`lrm_cvx.demo.run_demo`.
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import atomic_outputs, guard_outputs
from .cli_common import (
    CERTIFY_LEVELS,
    UsageError,
    add_output,
    add_path_options,
    add_setting,
    canonical,
    finite_number,
    first,
    guard_paths,
    int_at_least,
    mask_files,
    none_value,
    paper_setting,
    parse_floats,
    path_options,
    pick,
    prior_choices,
)
from .cli_fit import (
    add_data,
    add_model_options,
    fit_model,
    input_files,
    load_data,
    model_params,
    rank_value,
    recommended_fit,
)
from .recommended import RECOMMENDED

__all__ = ["EVALUATION_FILES", "BACKTEST_FILES", "DEMO_DIR", "cmd_evaluate", "cmd_demo",
           "add_evaluate_parsers"]


DEMO_DIR = Path("lrm-cvx-demo")
"""Where ``demo`` writes by default."""

EVALUATION_FILES = ("results.nc", "summary.csv", "metrics.png", "metrics.pdf",
                    "predictions.png", "predictions.pdf")
"""What ``evaluate`` writes in its ``--out`` folder."""
BACKTEST_FILES = ("summary_by_origin.csv", "backtest.png", "backtest.pdf")
"""What ``evaluate --origins N`` (N > 1) writes besides :data:`EVALUATION_FILES`."""


def _sorted_by_time(data: Any) -> Any:
    """``data`` in time order (a warning when it was not), so the test snapshots are the last."""
    if "time" in data.coords and data.sizes["time"] > 1:
        t = data["time"].to_index()
        if not t.is_monotonic_increasing:
            warnings.warn("the time coordinate is not sorted; sorting it so the test snapshots "
                          "are the last in time", UserWarning, stacklevel=2)
            data = data.sortby("time")
    return data


def _run_evaluation(data, out_dir: Path, *, rank: int, n_test: int, budgets, n_starts: int,
                    random_trials: int, min_observations: int, criterion: str, seed: int,
                    certify: bool | str, progress: bool, methods: Sequence[str] | None = None,
                    cost: str = "nearest-neighbor", ridge: float = 0.0, fold_ridge: float = 0.0,
                    model_params: dict | None = None, fold_in: dict | None = None,
                    n_jobs: int = 1, inputs: Sequence[str | Path] = (),
                    overwrite: bool = True, n_robots: int = 1, path: Any = None,
                    origins: int = 1, temporal: str | None = None) -> list[Path]:
    """Fit, evaluate, summarise and draw everything in memory, then write every output in one
    all-or-nothing step (:func:`~lrm_cvx._validation.atomic_outputs`); returns the paths.
    ``path``: the path request of :func:`~lrm_cvx.evaluation.evaluate` (a
    :class:`~lrm_cvx.planning.request.PathOptions`), ``n_robots`` per start; ``origins`` > 1:
    the rolling-origin backtest (the figure of routes shows the last block); ``temporal``:
    the campaigns' dynamics (``evaluate(temporal=...)``: each start's route flown day after
    day, the filter scored beside the memoryless fold-in), None for the memoryless protocol."""
    import matplotlib.pyplot as plt

    from .evaluation import (
        COVERAGE_BANDS,
        LOWEST_BLOCK_95,
        METHODS,
        PlanningOptions,
        ScoringOptions,
        backtest,
        coverage_check,
        evaluate,
        summary,
    )
    from .plots import plot_backtest, plot_metrics, plot_predictions

    out_dir = Path(out_dir)
    data = _sorted_by_time(data)
    n_time = data.sizes["time"]
    if not 0 < n_test < n_time:
        raise UsageError(f"--n-test must be in [1, {n_time - 1}] (the data have {n_time} "
                         f"snapshots), got {n_test}")
    if (origins + 1) * n_test > n_time:
        raise UsageError(f"--origins {origins} blocks of --n-test {n_test} need at least "
                         f"{(origins + 1) * n_test} snapshots, the data have {n_time}")
    methods = tuple(methods or tuple(METHODS))
    model_params = {k: v for k, v in (model_params or {}).items() if v not in (None, False)}
    fold_in = dict(fold_in or {})
    model = fit_model(data.isel(time=slice(0, n_time - n_test)), model_params, rank=rank,
                       random_state=seed, progress=progress)
    planning = PlanningOptions(criterion=criterion, cost=cost, ridge=ridge,
                               random_trials=random_trials, certify=certify, n_jobs=n_jobs)
    scoring = ScoringOptions(model_params=model_params, fold_in=fold_in, fold_ridge=fold_ridge,
                             min_observations=min_observations)
    kw = dict(rank=rank, n_test=n_test, budgets=budgets, n_starts=n_starts, methods=methods,
              seed=seed, progress=progress, model=model, n_robots=n_robots, path=path,
              temporal=temporal, planning=planning, scoring=scoring)
    results = backtest(data, origins, **kw) if origins > 1 else evaluate(data, **kw)
    table = summary(results)
    last = results.isel(origin=-1) if "origin" in results.dims else results
    figures = {"metrics": plot_metrics(results)}
    if "origin" in results.dims:
        figures["backtest"] = plot_backtest(results)
    if "greedy" in methods:
        # qualitative figure: the first start cell, three budgets, the first test snapshot
        bvals = results["budget"].values
        chosen = [bvals[i] for i in sorted({0, len(bvals) // 2, len(bvals) - 1})]
        routes = {float(b): last["greedy_route"].sel(budget=b).isel(start=0).values
                  for b in chosen}
        robots = None
        if "greedy_route_robot" in last:
            robots = {float(b): last["greedy_route_robot"].sel(budget=b).isel(start=0).values
                      for b in chosen}
        figures["predictions"] = plot_predictions(model, data.isel(time=n_time - n_test), routes,
                                                  robots=robots)
    tables = {"summary": table}
    if "origin" in results.dims:
        tables["summary_by_origin"] = summary(results, by_origin=True)
    targets = [out_dir / "results.nc", *(out_dir / f"{name}.csv" for name in tables)]
    n_data = len(targets)
    targets += [out_dir / f"{name}.{fmt}" for name in figures for fmt in ("png", "pdf")]
    guard_outputs(targets, inputs, overwrite=overwrite)
    try:
        with atomic_outputs(targets, overwrite=overwrite) as tmps:
            results.to_netcdf(tmps[0], engine="netcdf4")
            for tmp, frame in zip(tmps[1:n_data], tables.values(), strict=True):
                frame.to_csv(tmp, index=False)
            for tmp, target in zip(tmps[n_data:], targets[n_data:], strict=True):
                figures[target.stem].savefig(tmp, format=target.suffix[1:], bbox_inches="tight")
    finally:
        for fig in figures.values():
            plt.close(fig)
    with np.printoptions(precision=4):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
        if "origin" in results.dims:  # do the intervals hold block by block?
            check = coverage_check(results)
            (lo68, hi68), (lo95, hi95) = COVERAGE_BANDS[68], COVERAGE_BANDS[95]
            print(f"\ncoverage over {results.sizes['origin']} blocks (holds: mean 68 % in "
                  f"{lo68:g}-{hi68:g}, mean 95 % in {lo95:g}-{hi95:g}, no block's 95 % below "
                  f"{LOWEST_BLOCK_95:g}):")
            width = int(check["verdict"].str.len().max())  # the verdicts left-aligned
            print(check.to_string(index=False, float_format=lambda v: f"{v:.3f}",
                                  formatters={"verdict": lambda v: str(v).ljust(width)}))
    print("wrote " + ", ".join(str(p) for p in targets))
    return targets


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``lrm-cvx evaluate``: the paper's protocol (or a rolling-origin backtest) on ``DATA``,
    its tables and figures written to ``--out``."""
    from .evaluation import GREEDY_VARIANTS, METHODS

    paper = paper_setting(args)
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} is an existing file; give a folder")
    inputs = input_files(args.data) + [Path(p) for p in mask_files(args)]
    names = EVALUATION_FILES + (BACKTEST_FILES if args.origins > 1 else ())
    guard_paths([out_dir / name for name in names], inputs, args)
    path = path_options(args, fleet_end=False)
    budgets = parse_floats(args.budgets, None, "--budgets")
    if min(budgets) < 0:
        raise UsageError(f"--budgets must be numbers >= 0, got {args.budgets!r}")
    if args.methods is not None:
        known = METHODS + GREEDY_VARIANTS  # alias-aware when the library's lists are
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        bad = [m for m in methods if m not in known]
        if bad or not methods:
            raise UsageError(f"--methods: unknown method {bad[0] if bad else args.methods!r}; "
                             f"choose from {', '.join(known)}")
        methods = tuple(canonical(known, m) for m in methods)
    elif paper:
        methods = METHODS
    else:  # the recommended greedy first, before the paper's methods
        methods = (RECOMMENDED["method"], *METHODS)
    params = model_params(args)
    if args.temporal is None:  # evaluate's protocol is memoryless: no dynamics to choose
        params["temporal"] = None
    campaigns = params.get("temporal")  # --temporal K: the filter's campaigns, day by day
    fold_in = {"prior": none_value(pick(args.prior, paper, "prior", None)),
               "spatial": bool(args.fold_spatial or (not paper and RECOMMENDED["fold_spatial"]))}
    fold_in = {k: v for k, v in fold_in.items() if v}
    if not params["spatial"]:
        if "greedy:gp-variance" in methods:
            raise UsageError("--methods greedy:gp-variance needs --spatial KERNEL (or the "
                             "recommended default: drop --paper)")
        if fold_in.get("spatial"):
            raise UsageError("--fold-spatial needs --spatial KERNEL (or the recommended "
                             "default: drop --paper)")
    data = load_data(args)
    _run_evaluation(data, out_dir, rank=args.rank, n_test=args.n_test, budgets=budgets,
                    n_starts=args.starts, random_trials=args.random_trials,
                    min_observations=args.min_observations, criterion=args.criterion,
                    seed=args.seed, certify=False if args.certify == "off" else args.certify,
                    progress=not args.quiet, methods=methods, cost=args.cost, ridge=args.ridge,
                    fold_ridge=args.fold_ridge, model_params=params, fold_in=fold_in,
                    n_jobs=args.jobs, inputs=inputs, overwrite=args.overwrite,
                    n_robots=args.robots, path=path, origins=args.origins,
                    temporal=campaigns)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The recommended setting beside the paper's on the SST sample (``lrm_cvx.demo``)."""
    from .demo import run_demo

    out = Path(args.out)
    result = run_demo(out, progress=None if args.quiet else print)
    print(result.text)
    print("wrote " + ", ".join(p.name for p in result.paths))
    print(f"demo finished in {result.timings['total']:.1f} s; outputs in {out.resolve()}")
    return 0


def add_evaluate_parsers(sub: Any) -> None:
    """Add ``evaluate`` and ``demo`` to ``lrm-cvx``'s subcommands."""
    from .evaluation import GREEDY_VARIANTS, METHODS
    from .information import CRITERIA
    from .planning.routecost import COSTS

    p = sub.add_parser("evaluate", help="run the paper's evaluation protocol")
    add_data(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--rank", type=rank_value, default=5,
                   help="the protocol's rank (default 5, the paper's), or auto (with "
                        "--temporal auto or none)")
    p.add_argument("--n-test", type=int_at_least(1), default=8)
    p.add_argument("--origins", type=int_at_least(1), default=1,
                   help="a rolling-origin backtest: the protocol on the last ORIGINS blocks of "
                        "--n-test snapshots, each block's model fitted (and calibrated) on the "
                        "snapshots before it; summary.csv pools the blocks, "
                        "summary_by_origin.csv has a row per block (default 1: the last block)")
    p.add_argument("--budgets", default="5,25,50,100,200")
    p.add_argument("--starts", type=int_at_least(1), default=10)
    p.add_argument("--random-trials", type=int_at_least(1), default=70)
    p.add_argument("--min-observations", type=int_at_least(0), default=10)
    p.add_argument("--methods", default=None,
                   help=f"comma-separated methods (default: {RECOMMENDED['method']} and the "
                   f"paper's {','.join(METHODS)}; the paper's alone with --paper); also "
                   f"{', '.join(GREEDY_VARIANTS)}")
    p.add_argument("--criterion", default=first(CRITERIA), choices=CRITERIA,
                   help="criterion of the paper's 'greedy' method (default: %(default)s, with "
                   "or without --paper; the recommended greedy is the method "
                   f"{RECOMMENDED['method']})")
    p.add_argument("--cost", default=first(COSTS), choices=COSTS,
                   help="path cost of the greedy (default: %(default)s)")
    p.add_argument("--ridge", type=finite_number, default=0.0,
                   help="the planners' information ridge")
    p.add_argument("--fold-ridge", type=finite_number, default=0.0, help="the fold-in's ridge")
    p.add_argument("--prior", choices=prior_choices(), default=None,
                   help="fold-in prior of every prediction (default: "
                   f"{RECOMMENDED['prior']}; none with --paper)")
    p.add_argument("--fold-spatial", action="store_true",
                   help="predict with the kriged GP residual (needs --spatial; default: "
                   f"{'on' if RECOMMENDED['fold_spatial'] else 'off'}; off with --paper)")
    add_model_options(p, fit=False)
    add_path_options(p)
    p.add_argument("--robots", type=int_at_least(1), default=1,
                   help="robots per start (a fleet of distinct random start cells; the budget "
                   "is per robot; default 1)")
    p.add_argument("--seed", type=int_at_least(0), default=0)
    p.add_argument("--jobs", type=int_at_least(1), default=1, help="threads over start cells")
    p.add_argument("--certify", choices=CERTIFY_LEVELS, default="fast",
                   help="certified bounds of the greedy plans (default: %(default)s)")
    p.add_argument("--no-certify", dest="certify", action="store_const", const="off",
                   help="same as --certify off")
    add_setting(p, f"{recommended_fit(fit=False)}, --prior {RECOMMENDED['prior']} --fold-spatial "
                f"and the method {RECOMMENDED['method']} first",
                "the paper's methods, model and fold-in")
    add_output(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="the whole pipeline on the bundled real sample data")
    p.add_argument("--out", default=str(DEMO_DIR), help="output folder (default ./lrm-cvx-demo)")
    p.set_defaults(func=cmd_demo)
