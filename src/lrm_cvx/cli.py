"""The ``lrm-cvx`` command: thin wrappers over the public functions.

Defaults: the recommended setting (:data:`RECOMMENDED`) wherever ``--paper`` is not
given; ``--paper`` reproduces the paper, an explicit option always wins, and a recommended
default the input cannot take falls back with one printed ``note:`` line.

Contract (docs/cli.md): every failure prints one line ``lrm-cvx <cmd>: error: ...`` on stderr
and exits with status 2 (``--debug`` also prints the traceback); no command ever writes onto
one of its inputs (globs and folders expanded, compared as resolved files); every output is
written to a temporary file beside it and renamed into place (all of ``evaluate``'s outputs
together), and an existing output is replaced only with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import re
import sys
import traceback
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import atomic_outputs, guard_outputs
from .cli_common import (
    SENSOR_SUFFIXES,
    UsageError,
    add_common,
    add_output,
    add_path_options,
    add_plan_outputs,
    add_setting,
    add_starts_budgets,
    check_lat,
    check_plan_output,
    criterion_value,
    describe_plan,
    finite_number,
    guard_paths,
    load_model,
    mask_files,
    note,
    paper_setting,
    parse_floats,
    path_options,
    plan_outputs,
    read_observations_csv,
    read_traversable,
    starts_budgets,
    write_plan,
    write_plans,
)
from .errors import LrmError
from .recommended import RECOMMENDED, recommended_criterion  # the default unless --paper

__all__ = ["main", "build_parser", "RECOMMENDED"]

DEMO_DIR = Path("lrm-cvx-demo")

#: ``--certify`` levels: the library's ``certify="fast"|"tight"`` and ``"off"`` (False).
CERTIFY_LEVELS = ("fast", "tight", "off")

EVALUATION_FILES = ("results.nc", "summary.csv", "metrics.png", "metrics.pdf",
                    "predictions.png", "predictions.pdf")
BACKTEST_FILES = ("summary_by_origin.csv", "backtest.png", "backtest.pdf")
"""What ``evaluate --origins N`` (N > 1) writes besides :data:`EVALUATION_FILES`."""


# ---------------------------------------------------------------------------- arguments
def _bbox(text: str | None) -> tuple[float, float, float, float] | None:
    if text is None:
        return None
    south, west, north, east = parse_floats(text, 4, "--bbox S,W,N,E")
    check_lat(south, "--bbox south")
    check_lat(north, "--bbox north")
    if south >= north:
        raise UsageError(f"--bbox south ({south:g}) must be below north ({north:g}); the order "
                         "is S,W,N,E")
    return (south, west, north, east)


def _int_at_least(low: int):
    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}")
        return value

    convert.__name__ = f"int>={low}"
    return convert


def _rank(text: str) -> int | str:
    """``--rank``: an integer >= 1 or ``auto`` (chosen on the training snapshots)."""
    if text == "auto":
        return text
    try:
        return _int_at_least(1)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1 or 'auto', got {text!r}") \
            from None


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM_LIST = re.compile(rf"^,?{_NUM}(?:,{_NUM})*,?$")
_COORDINATE_FLAGS = {"--start": 2, "--end": 2, "--bbox": 4}


def _join_coordinates(argv: Sequence[str]) -> list[str]:
    """``--start -10 150`` / ``--start -10,150`` -> ``--start=-10,150`` (same for ``--bbox``).

    argparse reads ``-10,150`` as an option; joining the numbers after the flag into
    ``--flag=...`` accepts every southern or western coordinate, in ``LAT LON`` or ``LAT,LON``
    form.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok == "--":
            out.extend(argv[i:])
            break
        n = _COORDINATE_FLAGS.get(tok)
        parts: list[str] = []
        j = i + 1
        while n is not None and j < len(argv) and len(parts) < n and _NUM_LIST.match(argv[j]):
            parts += [v for v in argv[j].split(",") if v]
            j += 1
        if parts:
            out.append(f"{tok}={','.join(parts)}")
            i = j
        else:
            out.append(tok)
            i += 1
    return out


# ---------------------------------------------------------------------------- files
def _input_files(items: Sequence[str]) -> list[Path]:
    """Every file a data argument reads: globs expanded (as ``open_data`` does), a folder and
    every file in it, and the package file behind ``sample:NAME``."""
    from .io.generic import expand_paths

    files: list[Path] = []
    plain = []
    for item in items:
        text = str(item)
        if text.startswith("sample:"):
            from importlib import resources

            name = text.split(":", 1)[1]
            files.append(Path(str(resources.files("lrm_cvx") / "data" / f"{name}.nc")))
        else:
            plain.append(text)
    for path in expand_paths(plain) if plain else []:
        files.append(path)
        if path.is_dir():
            files.extend(q for q in sorted(path.iterdir()) if q.is_file())
    return files


def _load(args: argparse.Namespace):
    from .io import open_data

    return open_data(args.data, var=args.var, bbox=_bbox(args.bbox))


def _fitted_part(model, data):
    """``data`` without the snapshots after the model's last fitted one: DATA is "the data the
    model was fitted on", so the snapshots ``fit --hold-out`` / ``--until`` kept out stay out
    of the training (a note says how many were dropped)."""
    X = getattr(model, "X_", None)
    tdim = X.dims[-1] if hasattr(X, "dims") else None
    if tdim is None or tdim not in data.dims or tdim not in X.coords:
        return data
    last = X[tdim].values[-1]
    try:
        keep = np.asarray(data[tdim].values <= last, dtype=bool)
    except TypeError:  # times of different kinds (numbers against dates): take DATA as given
        return data
    if keep.all():
        return data
    if not keep.any():
        raise UsageError(f"DATA starts after the model's last fitted snapshot ({last}): give "
                         "the data the model was fitted on")
    note(f"DATA cut to the {int(keep.sum())} snapshots up to the model's last fitted one "
         f"({last}); the {int((~keep).sum())} later ones (held out of the fit) stay out")
    return data.isel({tdim: np.flatnonzero(keep)})


def _need_spatial(model, path: str, why: str) -> None:
    if getattr(model, "spatial_cov_", None) is None:
        raise UsageError(f"{why} needs a model fitted with a spatial covariance; {path} has none "
                         "(refit with 'lrm-cvx fit' without --paper, or with --spatial "
                         "exponential)")


def _canonical(choices, name: str) -> str:
    """``name`` with a registry alias resolved (``aopt`` -> ``a-optimal``) when the library's
    name list is alias-aware (:class:`lrm_cvx.registry.Choices`), else ``name``."""
    registry = getattr(choices, "_registry", None)
    found = registry.resolve(name) if registry is not None else None
    return found if isinstance(found, str) else name


def _pick(explicit, paper: bool, key: str, paper_default):
    """``explicit`` when given, else the paper's default with ``--paper``, else the
    recommended ``RECOMMENDED[key]``."""
    if explicit is not None:
        return explicit
    return paper_default if paper else RECOMMENDED[key]


def _prior(text: str | None):
    return None if text in (None, "none") else text


# ---------------------------------------------------------------------------- commands
_MODEL_FLAGS = ("offset", "scale", "noise", "spatial", "temporal")
"""The GLRM parameters the CLI has an option for (``--offset`` ...)."""


def _recommended_glrm() -> dict:
    """``GLRM.recommended_params()``: the GLRM parameters of ``RECOMMENDED``."""
    from .glrm import GLRM

    return GLRM.recommended_params()


def _model_params(args: argparse.Namespace) -> dict:
    """The GLRM parameters of ``fit`` / ``evaluate``: the explicit model options over the
    paper's defaults (``--paper``) or over the recommended ones (every GLRM parameter in
    ``RECOMMENDED``, so a key the recommended setting gains reaches the fit)."""
    from .glrm.predictive import NOISE_MODELS

    params: dict = {"offset": False, "spatial": None, "scale": False,
                    "noise": _first(NOISE_MODELS), "temporal": None}  # the paper's
    if not paper_setting(args):
        params.update(_recommended_glrm())
    explicit = {"offset": True if args.offset else None,
                "scale": _scale_option(args),
                "noise": args.noise, "spatial": args.spatial, "temporal": args.temporal,
                "anisotropy": args.anisotropy}
    params.update({k: v for k, v in explicit.items() if v is not None})
    params["temporal"] = _prior(params["temporal"])  # --temporal none: no dynamics
    return params


def _scale_option(args: argparse.Namespace) -> Any:
    """GLRM's ``scale`` from ``--scale`` (True) / ``--residual-scale`` (``"residual"``); None
    when neither is given."""
    if args.scale and args.residual_scale:
        raise UsageError("--scale and --residual-scale exclude each other: choose one")
    return True if args.scale else "residual" if args.residual_scale else None


def cmd_fit(args: argparse.Namespace) -> int:
    from .validation.selection import AutoUnavailable

    params = _model_params(args)
    (out,) = guard_paths([args.output], _input_files(args.data), args)
    data = _hold_out(_load(args), args)
    default_auto = params["temporal"] == "auto" and args.temporal is None

    def without_dynamics(why: str) -> None:  # the recommended default cannot run here
        note(f"the recommended temporal='auto' cannot run on these data ({why.split(';')[0]}); "
             "fitting without dynamics (--temporal ar1|seasonal asks for them)")
        params["temporal"] = None

    if default_auto:
        from .validation.selection import auto_unavailable

        if (why := auto_unavailable(data)) is not None:  # found before any fit
            without_dynamics(why)
    fit_kw = dict(rank=args.rank, loss=args.loss, max_iter=args.max_iter, tol=args.tol,
                  random_state=args.seed, progress=not args.quiet)
    try:
        model = _fit_model(data, params, **fit_kw)
    except AutoUnavailable as exc:  # a record too short for the validation's refits
        if not default_auto:
            raise
        without_dynamics(str(exc))
        model = _fit_model(data, params, **fit_kw)
    model.save(out)
    extras = [name if getattr(model, name) is True else f"{name}={getattr(model, name)}"
              for name in ("offset", "scale") if getattr(model, name)]
    if model.spatial:
        extras.append(f"spatial={model.spatial}")
    print(f"fitted rank-{model.rank_} GLRM{' (' + ', '.join(extras) + ')' if extras else ''} on "
          f"{data.sizes['time']} snapshots x {model.region_.n_cells} cells in {model.n_iter_} "
          f"iterations (noise std {model.noise_std_:.4g}); saved {out}")
    if getattr(model, "selection_", None) is not None:
        from .validation.selection import format_selection

        print(format_selection(model.selection_))
    if getattr(model, "kernel_selection_", None) is not None:
        from .validation.kernel_selection import format_kernel_selection

        print(format_kernel_selection(model.kernel_selection_))
    return 0


def _fit_model(data, params: dict, **kw):
    """``GLRM(**kw, **params).fit(data)``; the recommended ``calibration`` (the only way the CLI
    asks for one) runs after the fit and, on a record too short for its refits, is left out with
    one note instead of failing the fit."""
    from .glrm import GLRM
    from .validation.calibration import fit_then_try_calibrate

    model = GLRM(**kw, **params)
    if (why := fit_then_try_calibrate(model, data)) is not None:
        note(f"the recommended conformal calibration cannot run on these data ({why}); the "
             "intervals are uncalibrated")
    return model


def _hold_out(data, args: argparse.Namespace):
    """The snapshots ``fit`` trains on: all, all but the last ``--hold-out N``, or those at or
    before ``--until DATE`` (any calendar of the data); says what was held out."""
    n_all = data.sizes["time"]
    if args.hold_out is not None and args.until is not None:
        raise UsageError("--hold-out and --until exclude each other")
    if args.hold_out is not None:
        keep = n_all - args.hold_out
        if keep < 2:
            raise UsageError(f"--hold-out {args.hold_out} leaves {max(keep, 0)} of {n_all} "
                             "snapshots to fit on; at least 2 are needed")
    elif args.until is not None:
        from .belief.filter import parse_time

        until = parse_time(args.until, data["time"], "--until")
        keep = int(np.count_nonzero(data["time"].values <= until))
        if keep < 2:
            raise UsageError(f"--until {args.until} keeps {keep} of {n_all} snapshots (the "
                             f"first is {data['time'].values[0]}); at least 2 are needed")
    else:
        return data
    if keep < n_all:
        from .belief.filter import time_label

        times = data["time"].values
        print(f"held out the last {n_all - keep} of {n_all} snapshots ({time_label(times[keep])}"
              f" .. {time_label(times[-1])}); fitting on {keep}")
    return data.isel(time=slice(0, keep))


def _plan_from_args(args: argparse.Namespace):
    from .planning import plan_greedy
    from .planning.lines import lines_where_possible

    model = load_model(args.model)
    start, budget = starts_budgets(args)
    path = path_options(args)
    from .information import CRITERIA

    paper = paper_setting(args)
    criterion = _canonical(CRITERIA, _pick(args.criterion, paper, "criterion", "fisher"))
    fallback = recommended_criterion(getattr(model, "spatial_cov_", None) is not None)
    if args.criterion is None and not paper and fallback != criterion:
        note(f"model {args.model} has no spatial residual (fitted with --paper or without "
             f"--spatial), so the recommended {criterion} criterion cannot run; planning with "
             f"{fallback} (--criterion chooses)")
        criterion = fallback
    prior = _prior(_pick(args.prior, paper, "prior", None))
    initial = _pick(args.initial, paper, "initial", "nearest")
    kw: dict = {}
    if criterion == "gp-variance":
        _need_spatial(model, args.model, "--criterion gp-variance")
        if args.prior == "none":
            raise UsageError("--criterion gp-variance needs a prior: use --prior empirical (the "
                             "default for this criterion)")
        kw = model.planner_kwargs(prior=prior or "empirical", spatial=True)
    elif prior is not None:
        kw = model.planner_kwargs(prior=prior)
    plan = plan_greedy(model.Y_, model.region_, start, budget, criterion=criterion,
                       cost=args.cost, ridge=args.ridge, progress=not args.quiet,
                       initial=initial, path=path,
                       refine=None if paper else lines_where_possible(path), **kw)
    return model, plan, kw


def cmd_plan(args: argparse.Namespace) -> int:
    files = plan_outputs(args.output, len(args.start), args.robot)  # before any work
    guard_paths([f for f, _ in files], [args.model, *mask_files(args)], args)
    model, plan, kw = _plan_from_args(args)
    value = criterion_value(plan, model.Y_, model.region_, kw.get("prior"))
    print(describe_plan(plan, value))
    write_plans(plan, files, args)
    return 0


def cmd_place(args: argparse.Namespace) -> int:
    """Static placement (docs/planning.md "Static placement"): fixed sensors, no travel."""
    from .information import CRITERIA
    from .planning import place_sensors

    out = None
    if args.output:
        ins = [args.model, *mask_files(args), *(_input_files(args.data) if args.data else [])]
        guard_outputs([args.output], ins, overwrite=True)  # onto an input: said before the suffix
        check_plan_output(args.output, SENSOR_SUFFIXES)
        (out,) = guard_paths([args.output], ins, args)
    if args.paper:
        if args.criterion not in (None, "fisher") or args.exchange or args.data:
            raise UsageError("--paper is the paper's Fisher greedy: --criterion, --exchange "
                             "and DATA do not apply")
        criterion = "fisher"
    else:
        criterion = args.criterion or ("risk" if args.data else "gp-variance")
    if criterion != "risk":
        criterion = _canonical(CRITERIA, criterion)
        if criterion not in CRITERIA:
            raise UsageError(f"--criterion must be risk or one of {', '.join(CRITERIA)}, got "
                             f"{args.criterion!r}")
        if args.data:
            raise UsageError(f"DATA (training snapshots) is for --criterion risk, not "
                             f"{criterion}")
    elif not args.data:
        raise UsageError("--criterion risk needs DATA: the training snapshots (the same data "
                         "and --bbox as 'lrm-cvx fit')")
    model = load_model(args.model)
    if criterion == "gp-variance":
        _need_spatial(model, args.model, "--criterion gp-variance")
    kw: dict = {"training": _fitted_part(model, _load(args))} if criterion == "risk" else {}
    if args.traversable is not None:
        kw["traversable"] = read_traversable(args.traversable)
    if args.paper:  # the paper's Fisher greedy (no prior)
        plan = place_sensors(model, args.sensors, paper=True, progress=not args.quiet, **kw)
    elif args.criterion is None and criterion == "risk":
        # the recommended default: the criterion validated on DATA (risk + the exchange with
        # --exchange); on too short a record, risk without the validation
        from .planning.static_auto import auto_unavailable

        why = None if args.exchange else auto_unavailable(model, kw["training"].sizes["time"])
        if why is not None:  # the (Y, region, n) form's default: risk, the recommended exchange
            note(f"the recommended placement cannot validate its criterion on these data "
                 f"({why}); placing by risk")
        where = (model,) if why is None else (model.Y_, model.region_)
        plan = place_sensors(*where, args.sensors, exchange=True if args.exchange else None,
                             prior=None if why is None else model, sweeps=args.sweeps,
                             progress=not args.quiet, **kw)
    else:
        prior = model.latent_prior("empirical", spatial=getattr(model, "spatial_cov_", None)
                                   is not None and criterion in ("gp-variance", "risk"))
        plan = place_sensors(model.Y_, model.region_, args.sensors, criterion=criterion,
                             prior=prior, exchange=args.exchange, sweeps=args.sweeps,
                             progress=not args.quiet, **kw)
    ref = plan.refinement
    if "selection" in ref:  # the default: the criterion chosen on the training snapshots
        from .planning.static_auto import format_placement_selection

        print(format_placement_selection(ref["selection"]))
        criterion = plan.criterion or criterion
    text = f"{len(plan.cells)} sensors placed by the {criterion} greedy"
    if "objective" in ref:
        what = ("training squared error" if criterion == "risk"
                else "total posterior variance")
        text += f"; {what} {ref['objective']:.6g}"
    if plan.method == "greedy+exchange":
        text += (f"; exchange: {ref.get('swaps', 0)} swaps in {ref.get('sweeps', 0)} sweeps "
                 f"({'a local optimum' if ref.get('converged') else 'sweep limit reached'}), "
                 f"{ref.get('objective_before', np.nan):.6g} -> "
                 f"{ref.get('objective_after', np.nan):.6g}")
    print(text)
    if out is not None:
        write_plan(plan, out)
    return 0


def _stored_plan(args: argparse.Namespace) -> tuple[Any, Any, dict]:
    """``(model, plan, kw)`` of ``bound --state``: the plan stored in a monitor state file
    (planned or replanned) of the model ``MODEL``, and ``{"prior": PriorTerms}`` of the terms it
    carries (empty without)."""
    from .monitor import MonitorState
    from .planning.terms import PriorTerms

    if args.start is not None or args.budget is not None:
        raise UsageError("--state certifies the plan stored in the state file: --start and "
                         "--budget do not apply")
    model = load_model(args.model)
    state = MonitorState.load(args.state, model=model)
    if state.current_plan is None:
        raise UsageError(f"state file {args.state} holds no plan: run 'lrm-cvx monitor plan' "
                         "first")
    plan = state.current_plan
    terms = plan.criterion_terms
    return model, plan, {"prior": PriorTerms(**terms)} if terms else {}


def cmd_bound(args: argparse.Namespace) -> int:
    if args.state is not None:
        model, plan, kw = _stored_plan(args)
    elif args.start is None or args.budget is None:
        raise UsageError("bound needs --start and --budget (the plan to make and certify), or "
                         "--state STATE.nc (the plan stored there)")
    else:
        model, plan, kw = _plan_from_args(args)
    cert = plan.certify(tighten=args.certify == "tight",
                        criterion="fisher" if args.fisher else None)
    bounded = getattr(cert, "criterion", "fisher")
    who = "stored plan" if args.state is not None else "greedy plan"
    value = criterion_value(plan, model.Y_, model.region_, kw.get("prior"),  # a replan's rivals
                            reuse=not plan.method.endswith("+replan"))
    print(f"{who}: {describe_plan(plan, value)}")
    if bounded != "fisher":  # a variance criterion: variance removed, the data's unit squared
        print(f"certified upper bound on the {bounded} criterion (variance removed) of any "
              f"feasible plan: {cert.bound:.4f} unit^2")
        print(f"plan value: {cert.information:.4f} unit^2")
    else:
        print(f"certified upper bound on the {bounded} criterion of any feasible plan: "
              f"{cert.bound:.4f} nats")
    if not cert.comparable or cert.gap is None:
        print(f"optimality gap: not reported (the plan maximised {cert.plan_criterion}, the "
              f"certificate bounds {bounded})")
    elif bounded != "fisher":
        rel = cert.relative_gap
        print(f"optimality gap: {cert.gap:.4f} unit^2"
              + (f" ({100 * rel:.2f} % of the bound)" if rel is not None else ""))
    else:
        print(f"optimality gap: {cert.gap:.4f} nats (volume ratio per dimension "
              f"{cert.volume_ratio:.4f})")
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    (out,) = guard_paths([args.output], [args.model, args.observations], args)
    paper = paper_setting(args)
    model = load_model(args.model)
    prior = _prior(_pick(args.prior, paper, "prior", None))
    spatial = bool(args.spatial or (not paper and RECOMMENDED["fold_spatial"]))
    if args.spatial:
        _need_spatial(model, args.model, "--spatial")
    elif spatial and getattr(model, "spatial_cov_", None) is None:
        note(f"model {args.model} has no spatial residual (fitted with --paper or without "
             "--spatial), so the recommended kriged residual is left out; predicting with "
             f"the {prior or 'plain'} fold-in alone")
        spatial = False
    cells, values = read_observations_csv(args.observations, model.region_)
    result = model.complete((cells, values), ridge=args.ridge, prior=prior, spatial=spatial)
    with atomic_outputs([out], overwrite=True) as (tmp,):
        result.to_netcdf(tmp, engine="netcdf4")
    print(f"predicted {model.region_.n_cells} cells from {len(cells)} observations; "
          f"written to {out}")
    return 0


def _sorted_by_time(data):
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
        backtest,
        coverage_check,
        evaluate,
        summary,
    )
    from .plots import plot_backtest, plot_metrics, plot_predictions

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} is an existing file; give a folder")
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
    model = _fit_model(data.isel(time=slice(0, n_time - n_test)), model_params, rank=rank,
                       random_state=seed, progress=progress)
    kw = dict(rank=rank, n_test=n_test, budgets=budgets, n_starts=n_starts, methods=methods,
              random_trials=random_trials, min_observations=min_observations,
              criterion=criterion, cost=cost, ridge=ridge, fold_ridge=fold_ridge,
              certify=certify, seed=seed, n_jobs=n_jobs, progress=progress, model=model,
              model_params=model_params, fold_in=fold_in, n_robots=n_robots, path=path,
              temporal=temporal)
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
    from .evaluation import GREEDY_VARIANTS, METHODS

    paper = paper_setting(args)
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} is an existing file; give a folder")
    inputs = _input_files(args.data) + [Path(p) for p in mask_files(args)]
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
        methods = tuple(_canonical(known, m) for m in methods)
    elif paper:
        methods = METHODS
    else:  # the recommended greedy first, before the paper's methods
        methods = (RECOMMENDED["method"], *METHODS)
    params = _model_params(args)
    if args.temporal is None:  # evaluate's protocol is memoryless: no dynamics to choose
        params["temporal"] = None
    campaigns = params.get("temporal")  # --temporal K: the filter's campaigns, day by day
    fold_in = {"prior": _prior(_pick(args.prior, paper, "prior", None)),
               "spatial": bool(args.fold_spatial or (not paper and RECOMMENDED["fold_spatial"]))}
    fold_in = {k: v for k, v in fold_in.items() if v}
    if not params["spatial"]:
        if "greedy:gp-variance" in methods:
            raise UsageError("--methods greedy:gp-variance needs --spatial KERNEL (or the "
                             "recommended default: drop --paper)")
        if fold_in.get("spatial"):
            raise UsageError("--fold-spatial needs --spatial KERNEL (or the recommended "
                             "default: drop --paper)")
    data = _load(args)
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


# ---------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``lrm-cvx fit: error: ...`` and exit status 2."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")




def _add_data(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="+", help="NOAA NDVI CDR files, an image folder, a NetCDF "
                   "file with a (time, lat, lon) variable, or sample:NAME")
    p.add_argument("--var", help="variable name in a generic NetCDF file")
    p.add_argument("--bbox", help="region S,W,N,E in degrees (or S W N E; negative = south / "
                   "west; W > E crosses the antimeridian; required for images)")


def _add_model_options(p: argparse.ArgumentParser, *, fit: bool = True) -> None:
    from .glrm.dynamics import TEMPORAL
    from .glrm.predictive import NOISE_MODELS
    from .spatial import MODELS

    def default(key: str, paper: str, recommended: str | None = None) -> str:
        rec = recommended or str(RECOMMENDED.get(key, paper))
        return f"default: {rec}; {paper} with --paper" if rec != paper else f"default: {paper}"

    p.add_argument("--offset", action="store_true",
                   help="fit a per-cell mean (offset) (default: on; off with --paper)"
                   if RECOMMENDED.get("offset") else "fit a per-cell mean (offset)")
    p.add_argument("--scale", action="store_true",
                   help="divide the data by a per-cell std before the fit (floored at 0.1 x the "
                   "median cell's)")
    p.add_argument("--residual-scale", action="store_true",
                   help="a heteroscedastic residual: a per-cell scale of the training "
                   "residuals, after the fit (scale='residual')")
    p.add_argument("--noise", choices=NOISE_MODELS, default=None,
                   help=f"noise model ({default('noise', _first(NOISE_MODELS))})")
    p.add_argument("--spatial", choices=(*MODELS, "auto"), default=None, metavar="KERNEL",
                   help=f"also fit a GP covariance of the residuals ({', '.join(MODELS)}, or "
                   "auto: the family validated on the training residuals; "
                   f"{default('spatial', 'none')})")
    p.add_argument("--anisotropy", type=float, default=None, metavar="A",
                   help="a fixed --spatial kernel's east-west over north-south range (grid "
                   "cells; default 1: isotropic; --spatial auto validates its own)")
    p.add_argument("--temporal", choices=[t or "none" for t in TEMPORAL], default=None,
                   help="latent dynamics for persistent monitoring (docs/monitoring.md): auto "
                   "chooses none, ar1 or seasonal on the training snapshots by rolling-origin "
                   "validation and prints its table (" + (
                       f"{default('temporal', 'none')}; where auto cannot run on the data, "
                       "e.g. fewer than 8 regularly spaced snapshots, a note says so and none "
                       "is fitted)" if fit else "default: none, the protocol is memoryless, "
                       "with or without --paper; with it, each start's route is flown day "
                       "after day and the filter is scored beside the memoryless fold-in)"))


def _recommended_fit(fit: bool = True) -> str:
    """The GLRM parameters of ``RECOMMENDED`` as flags, for the help texts (``evaluate``
    fits no dynamics unless ``--temporal`` is given)."""
    flags = []
    params = _recommended_glrm()
    for key, value in params.items():
        if key in _MODEL_FLAGS and (fit or key != "temporal") and value not in (None, False):
            flag = f"--{key.replace('_', '-')}"
            if key == "scale" and value == "residual":
                flags.append("--residual-scale")
                continue
            flags.append(flag if value is True else f"{flag} {value}")
    if params.get("calibration") is not None:  # no flag: the recommended fit's own step
        flags.append("and the conformal interval calibration")
    return " ".join(flags)


def _first(names):
    """The default of a library name list (tuple or registry): its first entry."""
    return next(iter(names))


def _prior_choices() -> list[str]:
    from .glrm.predictive import PRIORS

    return [p or "none" for p in PRIORS]


def _add_plan(p: argparse.ArgumentParser) -> None:
    from .information import CRITERIA
    from .planning.routecost import COSTS

    p.add_argument("model", help="model file written by 'lrm-cvx fit'")
    add_starts_budgets(p)
    p.add_argument("--criterion", choices=CRITERIA, default=None,
                   help=f"planning criterion (default: {RECOMMENDED['criterion']}, or fisher "
                   "with a note when the model has no spatial residual; fisher with --paper)")
    p.add_argument("--cost", default=_first(COSTS), choices=COSTS,
                   help="path cost (default: %(default)s)")
    p.add_argument("--ridge", type=finite_number, default=0.0,
                   help="ridge added to the information")
    p.add_argument("--prior", choices=_prior_choices(), default=None,
                   help="plan with the fold-in's posterior under this prior (default: "
                   f"{RECOMMENDED['prior']}; none with --paper; gp-variance always uses "
                   "empirical)")
    p.add_argument("--initial", default=None,
                   help="forced initial cells: nearest (the start and its k-1 nearest cells, "
                   "the paper) or start (the start alone) (default: "
                   f"{RECOMMENDED['initial']}; nearest with --paper)")
    add_path_options(p, route=True)
    add_setting(p, f"--criterion {RECOMMENDED['criterion']} --prior {RECOMMENDED['prior']} "
                f"--initial {RECOMMENDED['initial']}",
                "--criterion fisher --prior none --initial nearest")


def build_parser() -> argparse.ArgumentParser:
    from .evaluation import GREEDY_VARIANTS, METHODS
    from .glrm.losses import LOSSES
    from .information import CRITERIA
    from .planning.routecost import COSTS

    parser = _Parser(
        prog="lrm-cvx",
        description="Persistent environmental monitoring with low-rank models: fit a GLRM, plan "
        "a sampling route, certify it, predict the map, evaluate like the paper. Every default "
        "is the recommended setting (docs/reconstruction.md); --paper reproduces the paper's "
        "setting, and an explicit option always wins.")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (for bug reports)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("fit", help="fit a GLRM to gridded snapshots")
    _add_data(p)
    p.add_argument("--rank", type=_rank, default=5,
                   help="components (default 5), or auto: chosen with the temporal model "
                        "(--temporal auto or none) by rolling-origin validation on the "
                        "training snapshots")
    p.add_argument("--loss", default="quadratic", choices=LOSSES)
    p.add_argument("--max-iter", type=_int_at_least(1), default=100)
    p.add_argument("--tol", type=finite_number, default=1e-4)
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    _add_model_options(p)
    add_setting(p, _recommended_fit(), "no offset, no spatial residual, no dynamics")
    p.add_argument("--hold-out", type=_int_at_least(0), default=None, metavar="N",
                   help="leave the last N snapshots out of the fit (to test or monitor on)")
    p.add_argument("--until", default=None, metavar="DATE",
                   help="fit on the snapshots at or before DATE only (YYYY-MM-DD[THH:MM], in "
                   "the data's calendar: 2093-02-30 is a 360-day date)")
    p.add_argument("-o", "--output", required=True, help="model file (.nc)")
    add_output(p)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("plan", help="plan a sampling route with the greedy planner (the "
                       "recommended one keeps a straight transect instead where its criterion "
                       "prefers one)")
    _add_plan(p)
    add_plan_outputs(p, required=False)
    add_output(p)
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("bound", help="certify the greedy plan's optimality gap")
    _add_plan(p)
    p.add_argument("--certify", choices=CERTIFY_LEVELS[:2], default="tight",
                   help="fast: the budget-disk relaxation; tight: with distance limits and "
                   "the midpoint cover (default)")
    p.add_argument("--fisher", action="store_true",
                   help="bound the Fisher information instead of the plan's own criterion")
    p.add_argument("--state", default=None, metavar="STATE.nc",
                   help="certify the plan stored in this monitor state file (by 'lrm-cvx "
                   "monitor plan' or 'replan') instead of planning one: no --start / --budget")
    for action in p._actions:  # --start / --budget: required unless --state
        if action.dest in ("start", "budget"):
            action.required = False
    p.set_defaults(func=cmd_bound)

    p = sub.add_parser("place", help="place fixed sensors (static placement, no travel)")
    p.add_argument("model", help="model file written by 'lrm-cvx fit'")
    p.add_argument("data", nargs="*", help="training snapshots for --criterion risk (the "
                   "data and --bbox the model was fitted on)")
    p.add_argument("--var", help="variable name in a generic NetCDF file")
    p.add_argument("--bbox", help="region S,W,N,E in degrees (as for 'lrm-cvx fit')")
    p.add_argument("--sensors", required=True, type=_int_at_least(1),
                   help="number of sensors to place")
    p.add_argument("--criterion", default=None, metavar="CRITERION",
                   help="risk (the fold-in's squared error over the training snapshots DATA; "
                   "the default when DATA is given, with the exchange on regions of at most "
                   "20,000 cells: the recommended placement) or a planning criterion "
                   f"({', '.join(CRITERIA)}; default gp-variance without DATA)")
    p.add_argument("--exchange", action="store_true",
                   help="after the greedy, swap sensors while a swap lowers the objective "
                   "(risk and gp-variance; on by default for the risk default)")
    p.add_argument("--paper", action="store_true",
                   help="the paper's placement: the Fisher greedy (no DATA, no exchange)")
    p.add_argument("--sweeps", type=_int_at_least(1), default=5,
                   help="exchange sweeps at most (default: %(default)s)")
    p.add_argument("--traversable", default=None, metavar="valid|PATH.nc",
                   help="cells that may hold a sensor: valid (all, default) or a NetCDF file "
                   "with one boolean (lat, lon) variable")
    p.add_argument("-o", "--output", help="sensors.csv or sensors.geojson")
    add_output(p)
    p.set_defaults(func=cmd_place)

    p = sub.add_parser("predict", help="predict the map from observations")
    p.add_argument("model", help="model file written by 'lrm-cvx fit'")
    p.add_argument("--observations", required=True,
                   help="CSV with columns value and cell, or value, lat and lon")
    p.add_argument("--ridge", type=finite_number, default=0.0)
    p.add_argument("--prior", choices=_prior_choices(), default=None,
                   help="fold-in prior; empirical: the training latent vectors' mean and "
                   f"covariance (default: {RECOMMENDED['prior']}; none with --paper)")
    p.add_argument("--spatial", action="store_true",
                   help="add the kriged GP residual (model fitted with a spatial covariance; "
                   "default: on when the model has one, else off with a note; off with "
                   "--paper)")
    add_setting(p, f"--prior {RECOMMENDED['prior']} --spatial",
                "--prior none, no kriged residual")
    p.add_argument("-o", "--output", required=True, help="output NetCDF map")
    add_output(p)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("evaluate", help="run the paper's evaluation protocol")
    _add_data(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--rank", type=_rank, default=5,
                   help="the protocol's rank (default 5, the paper's), or auto (with "
                        "--temporal auto or none)")
    p.add_argument("--n-test", type=_int_at_least(1), default=8)
    p.add_argument("--origins", type=_int_at_least(1), default=1,
                   help="a rolling-origin backtest: the protocol on the last ORIGINS blocks of "
                        "--n-test snapshots, each block's model fitted (and calibrated) on the "
                        "snapshots before it; summary.csv pools the blocks, "
                        "summary_by_origin.csv has a row per block (default 1: the last block)")
    p.add_argument("--budgets", default="5,25,50,100,200")
    p.add_argument("--starts", type=_int_at_least(1), default=10)
    p.add_argument("--random-trials", type=_int_at_least(1), default=70)
    p.add_argument("--min-observations", type=_int_at_least(0), default=10)
    p.add_argument("--methods", default=None,
                   help=f"comma-separated methods (default: {RECOMMENDED['method']} and the "
                   f"paper's {','.join(METHODS)}; the paper's alone with --paper); also "
                   f"{', '.join(GREEDY_VARIANTS)}")
    p.add_argument("--criterion", default=_first(CRITERIA), choices=CRITERIA,
                   help="criterion of the paper's 'greedy' method (default: %(default)s, with "
                   "or without --paper; the recommended greedy is the method "
                   f"{RECOMMENDED['method']})")
    p.add_argument("--cost", default=_first(COSTS), choices=COSTS,
                   help="path cost of the greedy (default: %(default)s)")
    p.add_argument("--ridge", type=finite_number, default=0.0,
                   help="the planners' information ridge")
    p.add_argument("--fold-ridge", type=finite_number, default=0.0, help="the fold-in's ridge")
    p.add_argument("--prior", choices=_prior_choices(), default=None,
                   help="fold-in prior of every prediction (default: "
                   f"{RECOMMENDED['prior']}; none with --paper)")
    p.add_argument("--fold-spatial", action="store_true",
                   help="predict with the kriged GP residual (needs --spatial; default: "
                   f"{'on' if RECOMMENDED['fold_spatial'] else 'off'}; off with --paper)")
    _add_model_options(p, fit=False)
    add_path_options(p)
    p.add_argument("--robots", type=_int_at_least(1), default=1,
                   help="robots per start (a fleet of distinct random start cells; the budget "
                   "is per robot; default 1)")
    p.add_argument("--seed", type=_int_at_least(0), default=0)
    p.add_argument("--jobs", type=_int_at_least(1), default=1, help="threads over start cells")
    p.add_argument("--certify", choices=CERTIFY_LEVELS, default="fast",
                   help="certified bounds of the greedy plans (default: %(default)s)")
    p.add_argument("--no-certify", dest="certify", action="store_const", const="off",
                   help="same as --certify off")
    add_setting(p, f"{_recommended_fit(fit=False)}, --prior {RECOMMENDED['prior']} --fold-spatial "
                f"and the method {RECOMMENDED['method']} first",
                "the paper's methods, model and fold-in")
    add_output(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="the whole pipeline on the bundled real sample data")
    p.add_argument("--out", default=str(DEMO_DIR), help="output folder (default ./lrm-cvx-demo)")
    p.set_defaults(func=cmd_demo)
    from .cli_monitor import add_monitor_parser  # monitor init|plan|assimilate|map

    add_monitor_parser(sub)
    for action in sub.choices.values():
        add_common(action)
    return parser


# ---------------------------------------------------------------------------- main
def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _describe(exc: BaseException) -> str:
    if isinstance(exc, LrmError):
        return _one_line(str(exc))
    if isinstance(exc, OSError) and exc.strerror:
        where = f": {exc.filename}" if exc.filename else ""
        return _one_line(f"{exc.strerror}{where}")
    if isinstance(exc, OSError):
        return _one_line(str(exc))
    return _one_line(f"unexpected {type(exc).__name__}: {exc} (rerun with --debug for the "
                     "traceback and report it)")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lrm-cvx`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser()
        args = parser.parse_args(_join_coordinates(argv))
    except SystemExit as exc:  # --help (0) or a one-line usage error (2)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except KeyboardInterrupt:
        print("lrm-cvx: interrupted", file=sys.stderr)
        return 130
    prefix = " ".join(["lrm-cvx", args.command]
                      + ([args.monitor_command] if args.command == "monitor" else []))

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prefix}: warning: {_one_line(str(message))}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        try:
            paper_setting(args)  # --paper --recommended: one line before any work
            return int(args.func(args) or 0)
        except KeyboardInterrupt:
            print(f"{prefix}: interrupted", file=sys.stderr)
            return 130
        except Exception as exc:  # every failure: one line, exit 2 (traceback with --debug)
            if args.debug:
                traceback.print_exc()
            print(f"{prefix}: error: {_describe(exc)}", file=sys.stderr)
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
