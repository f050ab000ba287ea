"""``lrm-cvx monitor``: the field loop from a shell (``init``, ``plan``, ``replan``,
``export``, ``assimilate``, ``map``; docs/cli.md).

The state file is always replaced atomically; errors follow ``lrm-cvx``'s conventions (one line on
stderr, exit status 2; nothing is written).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import numpy as np

from .cli_common import (
    UsageError,
    add_common,
    add_output,
    add_path_options,
    add_plan_criterion,
    add_plan_outputs,
    add_setting,
    add_starts_budgets,
    criterion_value,
    default_criterion,
    describe_plan,
    guard_paths,
    load_model,
    mask_files,
    note,
    paper_setting,
    path_options,
    pick,
    plan_outputs,
    plan_route,
    read_observations_csv,
    require_plan,
    starts_budgets,
    write_plans,
)
from .errors import LrmError

__all__ = ["add_monitor_parser"]

_MAP_SUFFIXES = (".nc", ".png", ".pdf")


#: Seconds a command waits for another one updating the same state file before it gives up
#: (nothing changed; run it again).
LOCK_TIMEOUT = 60.0


def _load_state(path: str):
    from .monitor import MonitorState

    return MonitorState.load(path)


def _save_state(state: Any, path: str | Path) -> None:
    state.save(path)


def _state_lock(path: str | Path):
    """The state file's lock: ``init``, ``plan``, ``replan`` and ``assimilate`` read, change
    and write the state under it, so two commands on one state run one after the other and no
    update is lost."""
    from ._validation import file_lock

    return file_lock(path, timeout=LOCK_TIMEOUT, what="state file")


def _guard_state_outputs(out: str | list[str], state: Any, args: argparse.Namespace) -> Any:
    """``out`` (one path, or a list) after the output checks, with the state file *and the
    model file it points to* as inputs: neither is ever replaced by a plan or a map,
    ``--overwrite`` or not."""
    inputs = [args.state] + ([state.model_path] if getattr(state, "model_path", "") else [])
    if isinstance(out, list):
        return guard_paths(out, inputs, args)
    (path,) = guard_paths([out], inputs, args)
    return path


# ----------------------------------------------------------------------------- commands
def cmd_monitor_init(args: argparse.Namespace) -> int:
    (out,) = guard_paths([args.state], [args.model], args)
    with _state_lock(out):
        return _init_locked(args, out)


def _init_locked(args: argparse.Namespace, out: Path) -> int:
    from .monitor import MonitorState

    model = load_model(args.model)
    if args.memoryless and args.temporal:
        raise UsageError("--memoryless and --temporal exclude each other")
    dynamics = None
    if args.temporal:  # estimated from the model's X_ (the model file is not changed)
        from .glrm.dynamics import estimate

        X = model.X_
        dynamics = estimate(args.temporal, model.X, X[X.dims[1]])
    elif (not args.memoryless and getattr(model, "dynamics_", None) is None
          and getattr(model, "selection_", None) is None):  # auto may choose memoryless
        raise UsageError(f"model {args.model} has no dynamics: pass --temporal ar1 (or seasonal) "
                         "to estimate them from the model, or --memoryless")
    memoryless = True if args.memoryless else None
    online = not args.offline_intervals
    state = MonitorState.from_model(model, dynamics=dynamics, memoryless=memoryless,
                                    online=online)
    if args.time is not None:  # --time in the record's calendar, named in its errors
        state = MonitorState.from_model(model, time=state.as_time(args.time, "--time"),
                                        dynamics=dynamics, memoryless=memoryless,
                                        online=online)
    state.model_path = os.path.abspath(args.model)
    _save_state(state, out)
    kind = "memoryless" if state.memoryless else state.dynamics.kind
    print(f"monitor state ({kind}) at time {_label(state.time)} written to {out}")
    return 0


def cmd_monitor_plan(args: argparse.Namespace) -> int:
    files = plan_outputs(args.output, len(args.start), args.robot)
    start, budget = starts_budgets(args)  # the request first: a bad flag costs no state read
    path = path_options(args)
    outs = [f for f, _ in files]
    guard_paths(outs, [args.state, *mask_files(args)], args)
    with _state_lock(args.state):  # the plan is stored in the state: read, plan, write back
        state = _load_state(args.state)
        _parse_time_option(state, args)
        _guard_state_outputs(outs, state, args)
        plan, t, kw = _plan_day(state, args, start, budget, path)
        value = criterion_value(plan, state.model.Y, state.model.region_, kw.get("prior"))
        print(f"plan for {_label(t)}: {describe_plan(plan, value)}")
        write_plans(plan, files, args)
        state.current_plan, state.current_plan_time = plan, t
        _save_state(state, args.state)
    print(f"plan stored in {args.state} (lrm-cvx monitor replan replans it en route)")
    return 0


def _plan_day(state: Any, args: argparse.Namespace, start: Any, budget: Any,
              path: Any) -> tuple[Any, Any, dict]:
    """``(plan, time, terms)``: the greedy plan of ``monitor plan`` with the forecast as prior; the
    recommended criterion and initial cells unless ``--paper`` or given explicitly."""
    model = state.model
    paper = paper_setting(args)
    criterion = args.criterion
    if criterion is None:
        criterion = default_criterion(paper, state.posterior.obs_model.is_spatial,
                                      f"state {args.state}: its model has")
    initial = pick(args.initial, paper, "initial", "nearest")
    kw = state.planner_kwargs(criterion=criterion, time=args.time)
    plan = plan_route(model.Y, model.region_, start, budget, args, criterion=criterion,
                      initial=initial, path=path, paper=paper, **kw)
    return plan, state.plan_time(args.time), kw


def cmd_monitor_replan(args: argparse.Namespace) -> int:
    inputs = [args.state] + ([args.observations] if args.observations else [])
    files = plan_outputs(args.output, 1)  # suffixes and repeats; the robots once read
    guard_paths([f for f, _ in files], inputs, args)
    with _state_lock(args.state):  # read, assimilate, replan and write back as one step
        state = _load_state(args.state)
        plan, t, files = _stored_plan(state, args)
        if args.time is not None and not state.same_snapshot(args.time, t, "--time"):
            raise UsageError(f"--time {args.time} is not the time of the stored plan "
                             f"({_label(t)}): observations for a different day cannot replan it")
        if state.time_after(t) < 0:
            raise UsageError(f"the stored plan is for {_label(t)} but the state has moved on to "
                             f"{_label(state.time)}: plan the new day with 'lrm-cvx monitor plan'")
        done = args.done[0] if len(args.done) == 1 else list(args.done)
        obs = None
        if args.observations is not None:
            obs = _read_observations(args.observations, state.model.region_, args.var)
        before = state.n_assimilated
        kw = state.planner_kwargs(criterion=args.criterion or plan.criterion, time=t)
        new = state.replan(None, done, obs, criterion=args.criterion, progress=not args.quiet)
        if obs is not None:
            print(f"assimilated {state.n_assimilated - before} observation(s) at {_label(t)}")
        value = criterion_value(new, state.model.Y, state.model.region_, kw.get("prior"),
                                reuse=False)
        print(f"replan for {_label(t)}: {describe_plan(new, value)} (the whole route, under "
              "the day's prior before this call)")
        write_plans(new, files, args)
        _save_state(state, args.state)
    print(f"plan stored in {args.state}")
    return 0


def _stored_plan(state: Any, args: argparse.Namespace) -> tuple[Any, Any, list]:
    """``(plan, time, files)``: the plan ``monitor plan`` stored in ``state`` (one line when
    there is none) and the output files of ``-o`` for its robots, checked."""
    plan, t = require_plan(state, args.state), state.current_plan_time
    files = plan_outputs(args.output, plan.n_robots, args.robot)
    _guard_state_outputs([f for f, _ in files], state, args)
    return plan, t, files


def cmd_monitor_export(args: argparse.Namespace) -> int:
    """Write the plan stored in the state (planned or replanned) in the formats of ``-o``,
    without planning again; the state is not changed."""
    files = plan_outputs(args.output, 1)  # suffixes and repeats; the robots once read
    guard_paths([f for f, _ in files], [args.state], args)
    state = _load_state(args.state)
    plan, t, files = _stored_plan(state, args)
    try:  # its criterion under the day's prior
        kw = state.planner_kwargs(criterion=plan.criterion, time=t)
        value = criterion_value(plan, state.model.Y, state.model.region_, kw.get("prior"),
                                reuse=False)
    except LrmError:  # the state has moved past the plan's day: its cells' own Fisher
        value = (f"Fisher information {plan.information:.4f} nats of its cells alone (the "
                 f"state has moved on to {_label(state.time)}, past the plan's prior)")
    print(f"plan for {_label(t)} ({plan.method}): {describe_plan(plan, value)}")
    write_plans(plan, files, args)
    return 0


def _read_observations(path: str, region: Any, var: str | None,
                       what: str = "--observations") -> Any:
    """``(cells, values)`` from a CSV (``value`` + ``cell`` or ``lat``, ``lon``), or a
    ``(lat, lon)`` DataArray from a NetCDF file (NaN where not observed); errors name the
    argument as ``what``."""
    from ._validation import check_input_file

    check_input_file(path, what)  # a FIFO would be waited on forever
    p = Path(path)
    if not p.exists():
        raise UsageError(f"{what} {path} does not exist")
    if p.suffix.lower() in (".nc", ".nc4", ".netcdf"):
        import xarray as xr

        from .errors import DataError

        try:
            with xr.open_dataset(p) as f:
                ds = f.load()
        except Exception as exc:
            raise DataError(f"{path} is not a readable NetCDF file: {exc}") from None
        names = [var] if var else [n for n in ds.data_vars if ds[n].ndim >= 2]
        if len(names) != 1 or names[0] not in ds:
            raise UsageError(f"{path}: pick the observation variable with --var (found "
                             f"{list(ds.data_vars)})")
        da = ds[names[0]]
        extra = [d for d in da.dims if da.sizes[d] == 1 and d not in ("lat", "lon")]
        da = da.squeeze(extra, drop=True) if extra else da
        if da.ndim != 2:
            raise UsageError(f"{path}: variable {names[0]!r} must be a (lat, lon) map, got dims "
                             f"{da.dims}")
        return da
    return read_observations_csv(path, region, what)


def cmd_monitor_assimilate(args: argparse.Namespace) -> int:
    with _state_lock(args.state):  # read, update and write back with no other writer between
        state = _load_state(args.state)
        sensor = _assimilate_sensor(args, state)
        obs = _read_observations(args.observations, state.model.region_, args.var,
                                 "observations file")
        before, added_before = state.n_dropped, state.n_assimilated
        t, notes = _observation_time(state, args)
        if sensor.is_point:
            state.assimilate(obs, t, force=args.force)
        else:  # each value is the footprint's average around its cell
            from .planning.sensors import footprint_matrix

            if not isinstance(obs, tuple):
                raise UsageError("--sensor with a footprint reads a CSV of footprint centres "
                                 "(value and cell or lat, lon), not a NetCDF map")
            cells, values = obs
            rows = footprint_matrix(state.model.region_, sensor, cells)
            state.assimilate_rows(rows, values, t, force=args.force,
                                  errors=sensor.errors)
        _save_state(state, args.state)
    _print_notes(notes)
    p = state.posterior
    n_today = int(p.cells.size) + (0 if p.rows is None else int(p.rows.shape[0]))
    dropped = state.n_dropped - before
    note = f"; {dropped} NaN value(s) ignored" if dropped else ""
    what = "" if sensor.is_point else f" ({sensor.describe()} footprint averages)"
    added = state.n_assimilated - added_before
    print(f"assimilated {added} observation(s){what} from {args.observations} at "
          f"{_label(state.time)} ({n_today} in all that day){note}; state {args.state} updated")
    if state.aci is not None:
        m68, m95 = state.interval_multipliers((0.68, 0.95))
        print(f"intervals recalibrated online ({state.aci.n_days} day(s) scored): 68 % = mean "
              f"+- {m68:.3g} x predictive_std, 95 % +- {m95:.3g} x")
    return 0


def _assimilate_sensor(args: argparse.Namespace, state: Any) -> Any:
    """The sensor whose readings ``monitor assimilate`` folds in: ``--sensor``, else the
    stored plan's (the day's route was planned for it), else a point."""
    from .planning.sensors import POINT, Sensor

    if args.sensor is not None:
        sensor = Sensor.of(args.sensor)
    else:
        plan = getattr(state, "current_plan", None)
        sensor = plan.sensor if plan is not None else POINT
    if sensor.is_leg:
        raise UsageError("monitor assimilate takes point or footprint readings; for a towed "
                         "(leg-average) sensor give each leg's cells as points")
    return sensor


def cmd_monitor_map(args: argparse.Namespace) -> int:

    suffix = Path(args.output).suffix.lower()
    if suffix not in _MAP_SUFFIXES:
        raise UsageError(f"-o must end in .nc, .png or .pdf, got {Path(args.output).name!r}")
    guard_paths([args.output], [args.state], args)
    state = _load_state(args.state)
    out = _guard_state_outputs(args.output, state, args)
    _parse_time_option(state, args)
    ds = state.forecast(args.time) if args.forecast else state.predict()
    what = "forecast" if args.forecast else "posterior"
    if suffix == ".nc":
        from ._validation import atomic_output

        with atomic_output(out) as tmp:
            ds.to_netcdf(tmp)
    else:
        if state.model.region_ is None:
            raise UsageError("a map image needs a model fitted on gridded data")
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from .plots import map_layout, plot_map, save_figure

        region = state.model.region_
        nrows, ncols, size = map_layout(region.lat.values, region.lon.values, 2)
        fig, axes = plt.subplots(nrows, ncols, figsize=size, constrained_layout=True,
                                 squeeze=False)
        axes = axes.ravel()
        units = str(ds["mean"].attrs.get("units", "")).strip()
        coast = None if args.coast == "none" else args.coast
        plot_map(ds["mean"], ax=axes[0], label=f"{what} mean", coast=coast)
        axes[0].set_title(f"{what} mean, {_label(ds['time'].values)}", fontsize=9)
        plot_map(ds["predictive_std"], ax=axes[1], cmap="magma", label="predictive std",
                 coast=coast)
        axes[1].set_title(f"predictive std{f' ({units})' if units else ''}, "
                          f"{_label(ds['time'].values)}", fontsize=9)
        save_figure(fig, out, formats=(suffix[1:],))
        plt.close(fig)
    print(f"{what} map at {_label(ds['time'].values)} written to {out}")
    return 0


def _parse_time_option(state: Any, args: argparse.Namespace) -> None:
    """``args.time`` read in the record's calendar (errors name ``--time``)."""
    if args.time is not None:
        args.time = state.as_time(args.time, "--time")


def _observation_time(state: Any, args: argparse.Namespace) -> tuple[Any, list[str]]:
    """``(time, notes)``: the time ``monitor assimilate`` folds the observations in at
    (``--time``, or the stored plan's time, or the state's own, when ``--time`` lies in its
    period: its calendar month for a monthly record) and the lines to print once done: that
    move, and with ``--force`` what a move other than one step onto the record's next stamp
    does."""
    t = state.observation_time(args.time, "--time")
    notes = []
    if state.time_after(t) != state.time_after(args.time, "--time"):
        notes.append(f"observations at {args.time} belong to the snapshot at {_label(t)} "
                     f"({state.record_calendar.describe()} record)")
    if args.force and (what := state.forced_move(t)) is not None:
        notes.append(f"--force: {what}")
    return t, notes


def _print_notes(notes: list[str]) -> None:
    for text in notes:
        note(text)


def _label(t: Any) -> str:
    from .belief.filter import time_label

    t = t.item() if isinstance(t, np.ndarray) and t.ndim == 0 and t.dtype == object else t
    if isinstance(t, np.ndarray) and t.ndim == 0:
        t = t[()]
    return time_label(t)


# ----------------------------------------------------------------------------- parser
def add_monitor_parser(sub: Any) -> None:
    """Add ``monitor init|plan|replan|export|assimilate|map`` to ``lrm-cvx``'s subcommands."""
    from .information import CRITERIA
    from .recommended import RECOMMENDED

    p = sub.add_parser("monitor", help="the field loop: a filter state carried from day to day "
                       "(init, plan, replan, export, assimilate, map)")
    msub = p.add_subparsers(dest="monitor_command", required=True, metavar="STEP")

    q = msub.add_parser("init", help="start a monitor state after the model's last snapshot")
    q.add_argument("model", help="model file written by 'lrm-cvx fit': the temporal model "
                   "fit chose (by default, --temporal auto: ar1, seasonal or none) carries the "
                   "state from day to day; a model fitted with --paper or --temporal none "
                   "needs --temporal or --memoryless here")
    q.add_argument("--state", required=True, help="state file to write (.nc)")
    q.add_argument("--time", default=None,
                   help="position the state at this time (default: the last fitted snapshot)")
    q.add_argument("--temporal", choices=("ar1", "seasonal"), default=None,
                   help="estimate these dynamics from the model's latent vectors (default: the "
                   "model's own, fitted with temporal=...)")
    q.add_argument("--memoryless", action="store_true",
                   help="no dynamics: every day's prior is the empirical prior")
    q.add_argument("--offline-intervals", action="store_true",
                   help="keep the model's calibrated interval thresholds all campaign (default: "
                   "each assimilate first recalibrates them online from the forecast's errors "
                   "at the day's samples)")
    add_output(q)
    q.set_defaults(func=cmd_monitor_init)

    q = msub.add_parser("plan", help="plan the next route with the state's forecast as prior")
    q.add_argument("state", help="state file written by 'lrm-cvx monitor init'")
    add_starts_budgets(q)
    q.add_argument("--initial", default=None, choices=("start", "nearest"),
                   help="forced initial cells: start (the start alone) or nearest (the start "
                   "and its k-1 nearest cells, the paper) (default: "
                   f"{RECOMMENDED['initial']}; nearest with --paper)")
    add_plan_criterion(q)
    q.add_argument("--time", default=None,
                   help="plan for this time (default: the next step, or the state's time if "
                   "not observed yet)")
    add_path_options(q, route=True)
    add_setting(q, f"--criterion {RECOMMENDED['criterion']} --initial "
                f"{RECOMMENDED['initial']} (the forecast is always the prior)",
                "--criterion fisher --initial nearest (the forecast is still the prior)")
    add_plan_outputs(q, required=True)
    add_output(q)
    q.set_defaults(func=cmd_monitor_plan)

    q = msub.add_parser("replan", help="replan the rest of the stored plan en route: fold in "
                        "the samples taken so far, keep the flown part (and the plan's check "
                        "against rival routes, for routes with no fixed end)")
    q.add_argument("state", help="state file holding a plan ('lrm-cvx monitor plan'; replaced "
                   "atomically)")
    q.add_argument("--done", required=True, type=int, nargs="+", action="extend",
                   metavar="K", help="route entries each robot has flown (its start counts: "
                   "the first K rows of its route in the plan); one K per robot of a fleet")
    q.add_argument("--observations", default=None, help="the samples taken so far: CSV with "
                   "value and cell or lat, lon columns, or a NetCDF (lat, lon) map with NaN "
                   "where not observed (as 'monitor assimilate')")
    q.add_argument("--time", default=None, help="time of the observations (default, and the "
                   "only one accepted: the stored plan's)")
    q.add_argument("--var", default=None, help="variable of a NetCDF observations file")
    q.add_argument("--criterion", choices=CRITERIA, default=None,
                   help="planning criterion (default: the stored plan's)")
    add_plan_outputs(q, required=False)
    add_output(q)
    q.set_defaults(func=cmd_monitor_replan)

    q = msub.add_parser("export", help="write the plan stored in the state (by monitor plan "
                        "or replan) in other formats, without planning again")
    q.add_argument("state", help="state file holding a plan (read only)")
    add_plan_outputs(q, required=True)
    add_output(q)
    q.set_defaults(func=cmd_monitor_export)

    q = msub.add_parser("assimilate", help="fold a day's observations into the state")
    q.add_argument("state", help="state file (replaced atomically)")
    q.add_argument("observations", help="CSV with value and cell or lat, lon columns, or a "
                   "NetCDF (lat, lon) map with NaN where not observed")
    q.add_argument("--time", required=True, help="time of the observations")
    q.add_argument("--force", action="store_true",
                   help="accept a time earlier than or equal to the state's")
    q.add_argument("--var", default=None, help="variable of a NetCDF observations file")
    q.add_argument("--sensor", default=None, metavar="SPEC",
                   help="each value is the average over this footprint around its cell "
                   "(e.g. disc:5km, square:1km; 'point' for point readings; default: the "
                   "sensor of the plan stored by monitor plan, else point)")
    q.set_defaults(func=cmd_monitor_assimilate)

    q = msub.add_parser("map", help="write the posterior (or forecast) mean and std maps")
    q.add_argument("state", help="state file")
    q.add_argument("-o", "--output", required=True, help="map.nc or map.png")
    q.add_argument("--forecast", action="store_true",
                   help="the forecast for --time (default the next step) instead of the "
                   "posterior")
    q.add_argument("--time", default=None, help="time of the forecast")
    q.add_argument("--coast", choices=["auto", "cartopy", "outline", "none"], default="auto",
                   help="coast on a .png/.pdf map: auto = real coastlines where cartopy's "
                   "Natural Earth shapefile (or $LRM_CVX_COASTLINES) is at hand offline, else "
                   "the outline of the cells with values (default auto)")
    add_output(q)
    q.set_defaults(func=cmd_monitor_map)
    for action in msub.choices.values():
        add_common(action)
