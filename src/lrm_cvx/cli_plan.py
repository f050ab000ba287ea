"""``lrm-cvx plan``, ``bound``, ``place`` and ``predict``: a route, its certificate, fixed
sensors and a map from a fitted model.

``plan`` and ``bound`` plan the greedy route (the recommended criterion, prior and initial cells
unless ``--paper`` or given); ``bound`` certifies it, or the plan a monitor state stores;
``place`` places fixed sensors (by default the criterion validated on the training snapshots);
``predict`` folds observations into a map.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from ._validation import atomic_outputs, guard_outputs
from .cli_common import (
    CERTIFY_LEVELS,
    SENSOR_SUFFIXES,
    UsageError,
    add_output,
    add_path_options,
    add_plan_criterion,
    add_plan_outputs,
    add_setting,
    add_starts_budgets,
    canonical,
    check_plan_output,
    criterion_value,
    default_criterion,
    describe_plan,
    finite_number,
    guard_paths,
    int_at_least,
    load_model,
    mask_files,
    none_value,
    note,
    paper_setting,
    path_options,
    pick,
    plan_outputs,
    plan_route,
    prior_choices,
    read_observations_csv,
    read_traversable,
    require_plan,
    starts_budgets,
    write_plan,
    write_plans,
)
from .cli_fit import input_files, load_data
from .recommended import RECOMMENDED

__all__ = ["cmd_plan", "cmd_bound", "cmd_place", "cmd_predict", "add_plan_parsers"]


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
    """UsageError unless the model (read from ``path``) has a spatial residual, which ``why``
    needs."""
    if getattr(model, "spatial_cov_", None) is None:
        raise UsageError(f"{why} needs a model fitted with a spatial covariance; {path} has none "
                         "(refit with 'lrm-cvx fit' without --paper, or with --spatial "
                         "exponential)")


def _plan_from_args(args: argparse.Namespace) -> tuple[Any, Any, dict]:
    """``(model, plan, kw)`` of ``plan`` / ``bound``: the greedy plan of the model ``MODEL`` and
    the criterion's prior terms it was planned with (empty without)."""
    from .information import CRITERIA

    model = load_model(args.model)
    start, budget = starts_budgets(args)
    path = path_options(args)
    paper = paper_setting(args)
    if args.criterion is not None:
        criterion = canonical(CRITERIA, args.criterion)
    else:
        criterion = default_criterion(paper, getattr(model, "spatial_cov_", None) is not None,
                                      f"model {args.model} has")
    prior = none_value(pick(args.prior, paper, "prior", None))
    initial = pick(args.initial, paper, "initial", "nearest")
    kw: dict = {}
    if criterion == "gp-variance":
        _need_spatial(model, args.model, "--criterion gp-variance")
        if args.prior == "none":
            raise UsageError("--criterion gp-variance needs a prior: use --prior empirical (the "
                             "default for this criterion)")
        kw = model.planner_kwargs(prior=prior or "empirical", spatial=True)
    elif prior is not None:
        kw = model.planner_kwargs(prior=prior)
    plan = plan_route(model.Y_, model.region_, start, budget, args, criterion=criterion,
                      initial=initial, path=path, paper=paper, **kw)
    return model, plan, kw


def cmd_plan(args: argparse.Namespace) -> int:
    """``lrm-cvx plan``: the greedy route from ``--start`` within ``--budget``, to ``-o``."""
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
        ins = [args.model, *mask_files(args), *(input_files(args.data) if args.data else [])]
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
        criterion = canonical(CRITERIA, criterion)
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
    kw: dict = {"training": _fitted_part(model, load_data(args))} if criterion == "risk" else {}
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
    plan = require_plan(state, args.state)
    terms = plan.criterion_terms
    return model, plan, {"prior": PriorTerms(**terms)} if terms else {}


def cmd_bound(args: argparse.Namespace) -> int:
    """``lrm-cvx bound``: the greedy plan (or the plan a monitor state stores) and its
    certified optimality gap."""
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
    """``lrm-cvx predict``: the map folded in from ``--observations``, written to ``-o``."""
    (out,) = guard_paths([args.output], [args.model, args.observations], args)
    paper = paper_setting(args)
    model = load_model(args.model)
    prior = none_value(pick(args.prior, paper, "prior", None))
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


def _add_plan(p: argparse.ArgumentParser) -> None:
    """The model, route and criterion options of ``plan`` and ``bound``."""
    p.add_argument("model", help="model file written by 'lrm-cvx fit'")
    add_starts_budgets(p)
    add_plan_criterion(p)
    p.add_argument("--prior", choices=prior_choices(), default=None,
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


def add_plan_parsers(sub: Any) -> None:
    """Add ``plan``, ``bound``, ``place`` and ``predict`` to ``lrm-cvx``'s subcommands."""
    from .information import CRITERIA

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
    p.add_argument("--sensors", required=True, type=int_at_least(1),
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
    p.add_argument("--sweeps", type=int_at_least(1), default=5,
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
    p.add_argument("--prior", choices=prior_choices(), default=None,
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
