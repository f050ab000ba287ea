"""Helpers the ``lrm-cvx`` commands share (:mod:`lrm_cvx.cli` and its ``cli_*`` modules).

Argument readers (``LAT,LON``, finite numbers, integers), the output guard of the CLI contract
(never onto an input, ``--overwrite``, a folder that can take the file), the common options, the
defaults (recommended, or the paper's with ``--paper``), loading a model, reading an
observations CSV, planning a route, and describing / writing a plan. Errors a user can fix are
:class:`UsageError` (one line, exit status 2; docs/cli.md).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import first_line, guard_outputs
from .errors import LrmError

__all__ = ["UsageError", "parse_floats", "check_lat", "parse_start", "finite_number",
           "add_common", "add_output", "check_writable", "guard_paths", "load_model",
           "read_observations_csv", "describe_plan", "criterion_value", "write_plan",
           "PLAN_SUFFIXES",
           "SENSOR_SUFFIXES", "check_plan_output", "add_plan_outputs",
           "plan_outputs", "write_plans", "check_robot", "FOLDER_SUFFIXES", "starts_budgets",
           "read_traversable", "path_options", "metric_choices", "add_path_options",
           "mask_files", "add_starts_budgets", "add_setting", "paper_setting", "note",
           "int_at_least", "CERTIFY_LEVELS", "pick", "none_value", "first", "canonical",
           "prior_choices", "default_criterion", "add_plan_criterion", "plan_route",
           "require_plan"]


class UsageError(LrmError, ValueError):
    """A command-line argument is malformed."""


def parse_floats(text: str, n: int | None, what: str) -> list[float]:
    """Comma-separated finite numbers (``n`` of them unless None); UsageError naming ``what``."""
    try:
        values = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise UsageError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if n is not None and len(values) != n:
        raise UsageError(f"{what} must have {n} comma-separated numbers, got {text!r}")
    if not values:
        raise UsageError(f"{what} needs at least one number, got {text!r}")
    if not all(np.isfinite(values)):
        raise UsageError(f"{what} must be finite numbers, got {text!r}")
    return values


def check_lat(value: float, what: str) -> None:
    """UsageError unless ``value`` is a latitude in [-90, 90] (``what``: the flag)."""
    if not -90 <= value <= 90:
        raise UsageError(f"{what} latitude must be in [-90, 90], got {value:g} "
                         "(latitude comes first)")


def parse_start(text: str, flag: str = "--start") -> tuple[float, float]:
    """``LAT,LON`` of ``flag`` (``--start``, ``--end``) as a ``(lat, lon)`` tuple."""
    lat, lon = parse_floats(text, 2, f"{flag} LAT,LON")
    check_lat(lat, flag)
    return (lat, lon)


def finite_number(text: str) -> float:
    """argparse ``type=``: a finite float (ArgumentTypeError otherwise)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def int_at_least(low: int):
    """argparse ``type=``: an integer ``>= low`` (ArgumentTypeError otherwise)."""
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


def add_common(p: argparse.ArgumentParser) -> None:
    """-q and --debug after the command too (SUPPRESS keeps the global value otherwise)."""
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="no progress bars")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="print the traceback of an error")


def add_setting(p: argparse.ArgumentParser, recommended: str, paper: str) -> None:
    """``--paper`` and ``--recommended``: the recommended setting is the default,
    ``--paper`` reproduces the paper; ``--recommended`` is kept so old scripts still run.
    ``recommended`` / ``paper``: what each means for this command (read with
    :func:`paper_setting`)."""
    p.add_argument("--paper", action="store_true",
                   help=f"the paper's setting: {paper}; explicit options still win")
    p.add_argument("--recommended", action="store_true",
                   help="the recommended setting of docs/reconstruction.md, now the default "
                   f"(accepted for old scripts): {recommended}; explicit options still win")


def paper_setting(args: argparse.Namespace) -> bool:
    """True with ``--paper``, False otherwise (the recommended default); UsageError when
    ``--paper`` and ``--recommended`` are both given."""
    paper = bool(getattr(args, "paper", False))
    if paper and getattr(args, "recommended", False):
        raise UsageError("--paper and --recommended exclude each other (the recommended "
                         "setting is the default; --paper reproduces the paper)")
    return paper


def note(text: str) -> None:
    """One printed line ``note: ...``: a default changed because this input cannot take it."""
    print(f"note: {text}")


#: ``--certify`` levels: the library's ``certify="fast"|"tight"`` and ``"off"`` (False).
CERTIFY_LEVELS = ("fast", "tight", "off")


def pick(explicit: Any, paper: bool, key: str, paper_default: Any) -> Any:
    """``explicit`` when given, else the paper's default with ``--paper``, else the
    recommended ``RECOMMENDED[key]``."""
    from .recommended import RECOMMENDED

    if explicit is not None:
        return explicit
    return paper_default if paper else RECOMMENDED[key]


def none_value(text: str | None) -> str | None:
    """An option's value with the word ``none`` read as None (``--prior none``,
    ``--temporal none``)."""
    return None if text in (None, "none") else text


def first(names: Any) -> Any:
    """The default of a library name list (tuple or registry): its first entry."""
    return next(iter(names))


def canonical(choices: Any, name: str) -> str:
    """``name`` with a registry alias resolved (``aopt`` -> ``a-optimal``) when the library's
    name list is alias-aware (:class:`lrm_cvx.registry.Choices`), else ``name``."""
    registry = getattr(choices, "_registry", None)
    found = registry.resolve(name) if registry is not None else None
    return found if isinstance(found, str) else name


def prior_choices() -> list[str]:
    """The ``--prior`` choices: the fold-in's priors, ``none`` for the flat one."""
    from .glrm.predictive import PRIORS

    return [p or "none" for p in PRIORS]


def default_criterion(paper: bool, spatial: bool, who: str) -> str:
    """The planning criterion when ``--criterion`` is not given: fisher with ``--paper``, else
    the recommended one, or fisher with a note when the model has no spatial residual
    (``spatial`` False); ``who`` starts the note (``"model m.nc has"``)."""
    from .recommended import RECOMMENDED, recommended_criterion

    if paper:
        return "fisher"
    criterion = recommended_criterion(spatial)
    if criterion != RECOMMENDED["criterion"]:
        note(f"{who} no spatial residual (fitted with --paper or without --spatial), so the "
             f"recommended {RECOMMENDED['criterion']} criterion cannot run; planning with "
             f"{criterion} (--criterion chooses)")
    return criterion


def add_output(p: argparse.ArgumentParser) -> None:
    """``--overwrite`` (a command that writes files)."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files (never an input file)")


def check_writable(paths: Sequence[Path]) -> None:
    """Fail before any work when an output's existing folder cannot take a new file."""
    import tempfile

    for folder in {p.parent for p in paths}:
        if folder.is_dir():
            fd, probe = tempfile.mkstemp(prefix=".lrm-cvx-probe.", dir=folder)
            os.close(fd)
            os.unlink(probe)
        elif folder.exists():
            raise NotADirectoryError(f"cannot write into {folder}: it is a file, not a folder")


def guard_paths(outputs: Sequence[str | Path], inputs: Sequence[str | Path],
                args: argparse.Namespace) -> list[Path]:
    """The resolved ``outputs`` after the CLI's checks: no glob pattern, never one of
    ``inputs``, an existing file only with ``args.overwrite``, a folder that can take it."""
    for out in outputs:
        if any(c in Path(out).name for c in "*?["):
            raise UsageError(f"output {out} looks like a glob pattern; give one file name")
    outs = guard_outputs(outputs, inputs, overwrite=args.overwrite)
    check_writable(outs)
    return outs


def load_model(path: str, *, need_region: bool = True) -> Any:
    """The GLRM saved at ``path``; UsageError when ``need_region`` and it has no lat/lon grid."""
    from .glrm import GLRM

    model = GLRM.load(path)
    if need_region and model.region_ is None:
        raise UsageError(f"model {path} was fitted on a plain array and has no region (lat/lon "
                         "grid); refit it with 'lrm-cvx fit' on gridded data")
    return model


def read_observations_csv(path: str, region: Any, what: str = "--observations"
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``(cells, values)`` of an observations CSV: a ``value`` column and ``cell`` or
    ``lat``,``lon`` columns (UsageError naming the argument as ``what`` otherwise)."""
    import pandas as pd

    try:
        obs = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot read {what} {path}: {first_line(exc)}") from None
    if "value" not in obs:
        raise UsageError(f"{what} {path} needs a 'value' column and "
                         f"'cell' or 'lat','lon' columns; it has {list(obs.columns)}")
    if obs.empty:
        raise UsageError(f"{what} {path} has no rows")
    numeric = obs.apply(pd.to_numeric, errors="coerce")
    for col in ("value", "cell", "lat", "lon"):
        if col in obs and (numeric[col].isna() & obs[col].notna()).any():
            raise UsageError(f"{what} {path}: column {col!r} must hold numbers")
    has_coords = {"lat", "lon"} <= set(obs.columns)
    if "cell" in obs:
        cells = region.check_cells(numeric["cell"].to_numpy(), "cell")
        if has_coords:  # both given: they must name the same cells
            at = np.atleast_1d(region.cell_of(numeric["lat"].to_numpy(),
                                              numeric["lon"].to_numpy()))
            bad = np.flatnonzero(at != cells)
            if bad.size:
                i = int(bad[0])
                raise UsageError(
                    f"{what} {path}: {bad.size} row(s) give a 'cell' that is not at "
                    f"their 'lat','lon' (row {i + 1}: cell {int(cells[i])}, but lat "
                    f"{numeric['lat'].iloc[i]:g}, lon {numeric['lon'].iloc[i]:g} is cell "
                    f"{int(at[i])}); give one of the two")
    elif has_coords:
        cells = np.atleast_1d(region.cell_of(numeric["lat"].to_numpy(),
                                             numeric["lon"].to_numpy()))
    else:
        raise UsageError(f"{what} {path} needs a 'cell' column or 'lat' "
                         f"and 'lon' columns; it has {list(obs.columns)}")
    return cells, numeric["value"].to_numpy(dtype=float)


def criterion_value(plan: Any, Y: Any, region: Any, prior: Any, *,
                    reuse: bool = True) -> str:
    """``plan`` under its own criterion, with units, for :func:`describe_plan`: Fisher, the log
    det of the (posterior) information in nats; gp-variance, the total posterior variance the
    route removes, in the data's units squared; a-optimal, the total prediction variance left
    (in the data's units squared with the fold-in's noise, else in units of the noise).
    ``Y`` / ``region`` / ``prior``: the factor matrix, region and prior it was planned
    with (``plan_greedy``'s ``prior=``); the value of the check against rival routes is reused
    when it was computed for the whole plan (``reuse``; a replan's is for the new part)."""
    from .information import gp_variance_value
    from .planning.lines import GP_TERMS, route_values
    from .planning.terms import prior_terms

    criterion = plan.criterion or "fisher"
    rivals = getattr(plan, "rivals", None) or {}
    sensor = getattr(plan, "sensor", None)
    if sensor is not None and not sensor.is_point:  # averaged rows: the Fisher log det of them
        return f"Fisher information {plan.information:.4f} nats" + (
            f" (of the footprint averages; planned by the {criterion} criterion)"
            if criterion != "fisher" else "")
    gp = criterion == "gp-variance"
    terms = prior_terms(prior)
    extra = ({**{k: terms.get(k) for k in GP_TERMS}, "region": region} if gp else
             {k: terms[k] for k in ("prior_precision", "noise_var")
              if terms.get(k) is not None})
    if criterion == "a-optimal" and terms.get("target_weights") is not None:
        extra["target_weights"] = terms["target_weights"]
    values = rivals.get("values") or {}
    if reuse and rivals.get("criterion") == criterion and rivals.get("chosen") in values:
        value = float(values[rivals["chosen"]])
    else:
        value = route_values(criterion, np.asarray(Y), float(plan.ridge),
                             {"plan": np.asarray(plan.cells)}, extra)["plan"]
    if gp:
        before = gp_variance_value(np.asarray(Y), region, extra["spatial_cov"],
                                   extra["prior_cov"], [], extra["targets"],
                                   extra["target_weights"])
        return (f"variance removed {before - value:.4g} (data units squared; "
                f"{value:.4g} of {before:.4g} left)")
    if criterion == "a-optimal":  # with the fold-in's noise: its variance; else noise units
        unit = ("data units squared" if terms.get("noise_var") is not None
                else "in units of the noise variance")
        return f"a-optimal prediction variance left {value:.4g} ({unit})"
    text = f"Fisher information {value:.4f} nats"
    return text + (" (fewer informative cells than the rank)" if not np.isfinite(value)
                   else "")


def describe_plan(plan: Any, value: str | None = None) -> str:
    """One line about a :class:`~lrm_cvx.planning.Plan`: cells, cost against the budget(s)
    (each robot's for a fleet), the plan's value (``value``, from :func:`criterion_value`;
    default its Fisher information) and the non-default path options."""
    if value is None:  # plan.information: the Fisher log det (nats) of the plan's cells
        value = f"Fisher information {plan.information:.4f} nats"
        if not np.isfinite(plan.information):
            value += " (fewer informative cells than the rank)"
        if plan.criterion not in (None, "fisher"):
            value += f", planned by the {plan.criterion} criterion"
    path = getattr(plan, "path", None) or {}
    sensor = getattr(plan, "sensor", None)
    unit = path.get("unit", "grid units")
    budgets = path.get("budgets") or [plan.budget]
    costs = np.atleast_1d(getattr(plan, "robot_costs", [plan.cost]))
    if len(costs) != len(budgets):
        costs, budgets = np.array([plan.cost]), [plan.budget]
    over = bool(np.any(costs > np.asarray(budgets, dtype=float) + 1e-9))
    within = "> (forced initial cells)" if over else "<="
    if len(costs) == 1:
        text = f"cost {plan.cost:.3f} {within} budget {plan.budget:g}"
    else:  # a fleet: each robot's cost and budget
        text = f"{len(costs)} robots, costs " + ", ".join(
            f"{c:.3f}/{b:g}" for c, b in zip(costs, budgets, strict=True)) + \
            f" (total {plan.cost:.3f}; {'over' if over else 'within'} the budgets)"
    if unit != "grid units":
        text += f" {unit}"
    extras = ["closed" if path.get("closed") else "",
              f"traversable {path['traversable']}" if path.get("traversable", "none") != "none"
              else "",
              f"ends at cell {path['end']}" if path.get("end") is not None else "",
              "sensing along the route" if path.get("sense_along") else "",
              f"sensor {sensor.describe()}" if sensor is not None and not sensor.is_point
              else "",
              _kept_line(getattr(plan, "rivals", None) or {})]
    extras = [e for e in extras if e]
    return f"{len(plan.cells)} cells, {text}, {value}" + (f" ({', '.join(extras)})" if extras
                                                         else "")


def _kept_line(rivals: dict) -> str:
    """What the check against rival routes kept, when not the greedy's route."""
    chosen = str(rivals.get("chosen", "greedy"))  # a fleet's: "robot 0: greedy, robot 1: ..."
    if all(part.split(": ")[-1] == "greedy" for part in chosen.split(", ")):
        return ""
    return f"{chosen}: its {rivals['criterion']} value beat the greedy route's"


#: ``-o`` of a plan: a table, GeoJSON, or a mission file an autopilot or GIS loads.
PLAN_SUFFIXES = (".csv", ".geojson", ".json", ".plan", ".waypoints", ".gpx", ".kml")
#: ``-o`` of a static placement (no route, so no mission file).
SENSOR_SUFFIXES = (".csv", ".geojson", ".json")


def check_plan_output(path: str, suffixes: Sequence[str] = PLAN_SUFFIXES) -> None:
    """UsageError unless ``path`` ends in one of ``suffixes``."""
    if Path(path).suffix.lower() not in suffixes:
        raise UsageError(f"-o must end in {', '.join(suffixes)}; got {Path(path).name!r}")


#: The formats ``-o FOLDER/`` writes, one file of each (``.json`` is GeoJSON again).
FOLDER_SUFFIXES = (".csv", ".geojson", ".plan", ".waypoints", ".gpx", ".kml")
#: Mission formats that hold one vehicle: a fleet's is one file per robot (``NAME_robotR``).
ONE_VEHICLE_SUFFIXES = (".plan", ".waypoints")
#: The file name (before its suffix) of each format ``-o FOLDER/`` writes.
FOLDER_STEM = "route"


def add_plan_outputs(p: argparse.ArgumentParser, *, required: bool) -> None:
    """``-o`` of a route (repeatable: several formats at once; ``FOLDER/``: every format),
    ``--altitude`` and ``--robot`` (read with :func:`plan_outputs`)."""
    from .planning.missions import DEFAULT_ALTITUDE

    p.add_argument("-o", "--output", action="append", required=required,
                   metavar="FILE|FOLDER/",
                   help="write the route: route.csv, route.geojson, or a mission: route.plan "
                   "(QGroundControl), route.waypoints (MAVLink QGC WPL 110), route.gpx, "
                   "route.kml; repeat -o for several files; a folder (ending in /) gets every "
                   f"format ({', '.join(FOLDER_STEM + s for s in FOLDER_SUFFIXES)}). A "
                   "fleet's .plan / .waypoints are one file per robot (route_robot0.plan, ...)")
    p.add_argument("--altitude", type=finite_number, default=None,
                   help="mission altitude in m above home (.plan, .waypoints; default "
                   f"{DEFAULT_ALTITUDE:g}) or above ground (.gpx, .kml; default none)")
    p.add_argument("--robot", type=int, default=None,
                   help="write the .plan / .waypoints of this robot of a fleet only, under the "
                   "name given (default: every robot, one file each; .gpx, .kml, .csv and "
                   ".geojson hold every robot)")


def check_robot(robot: int | None, n_robots: int) -> None:
    """UsageError unless ``--robot`` is None or a robot of a fleet of ``n_robots``."""
    if robot is not None and not 0 <= robot < n_robots:
        raise UsageError(f"--robot {robot} is not a robot of this plan: it has {n_robots} "
                         f"robot{'s' if n_robots > 1 else ''} (--robot 0"
                         f"{f' to {n_robots - 1}' if n_robots > 1 else ''})")


def plan_outputs(outputs: Sequence[str] | None, n_robots: int,
                 robot: int | None = None) -> list[tuple[Path, int | None]]:
    """Each file ``-o`` asks for, with the robot it holds (None: every robot): a file by its
    suffix (:data:`PLAN_SUFFIXES`), a folder (``FOLDER/``, the slash written) as
    :data:`FOLDER_SUFFIXES` under :data:`FOLDER_STEM`; a one-vehicle format of a fleet of
    ``n_robots`` is one file per robot (``NAME_robotR``) unless ``robot`` picks one. Checks
    ``robot`` and refuses a file asked for twice (UsageError), all before any work."""
    check_robot(robot, n_robots)
    files: list[tuple[Path, int | None]] = []
    for out in outputs or []:
        if str(out).endswith(("/", os.sep)):
            paths = [Path(out) / f"{FOLDER_STEM}{s}" for s in FOLDER_SUFFIXES]
        else:
            check_plan_output(out)
            paths = [Path(out)]
        for path in paths:
            if path.suffix.lower() not in ONE_VEHICLE_SUFFIXES:
                files.append((path, None))
            elif robot is not None or n_robots == 1:
                files.append((path, robot or 0))
            else:
                files += [(path.with_name(f"{path.stem}_robot{r}{path.suffix}"), r)
                          for r in range(n_robots)]
    seen: set[Path] = set()
    for path, _ in files:
        key = Path(os.path.abspath(path))
        if key in seen:
            raise UsageError(f"-o asks for {path} twice; give each output once")
        seen.add(key)
    return files


def write_plans(plan: Any, files: Sequence[tuple[Path, int | None]],
                args: argparse.Namespace) -> None:
    """Write ``plan`` to each of :func:`plan_outputs`' files (checked outputs; each atomic),
    making the folder of a ``-o FOLDER/`` that does not exist yet."""
    noted = False
    for path, robot in files:
        path.parent.mkdir(parents=True, exist_ok=True)
        noted = write_plan(plan, path, args, robot=robot, altitude_noted=noted) or noted


def write_plan(plan: Any, out: Path, args: argparse.Namespace | None = None, *,
               robot: int | None = None, altitude_noted: bool = False) -> bool:
    """Write ``plan`` by ``out``'s suffix (checked by the caller): CSV, GeoJSON, or a mission
    file (:func:`lrm_cvx.planning.missions.write_mission`, ``args.altitude``; ``robot``, by
    default ``args.robot``, else 0). Returns True when it printed the default altitude's note
    (not again when ``altitude_noted``)."""
    suffix = out.suffix.lower()
    noted = False
    if suffix == ".csv":
        plan.to_csv(out)
    elif suffix in (".geojson", ".json"):
        plan.to_geojson(out)
    else:
        from .planning.missions import DEFAULT_ALTITUDE, write_mission

        altitude = getattr(args, "altitude", None)
        if robot is None:
            robot = getattr(args, "robot", None) or 0
        write_mission(plan, out, robot=robot, altitude=altitude)
        if altitude is None and suffix in ONE_VEHICLE_SUFFIXES and not altitude_noted:
            print(f"mission altitude {DEFAULT_ALTITUDE:g} m above home (the default; set "
                  "--altitude)")
            noted = True
    what = "sensors" if plan.path.get("kind") == "static" else "route"
    who = f" (robot {robot})" if suffix in ONE_VEHICLE_SUFFIXES and plan.n_robots > 1 else ""
    print(f"{what}{who} written to {out}")
    return noted


# ----------------------------------------------------------------------- the path request
def starts_budgets(args: argparse.Namespace) -> tuple[object, object]:
    """``--start`` once (one robot) or several times (a fleet), ``--budget`` once (every robot)
    or once per start: the ``start`` / ``budget`` of ``plan_greedy``."""
    starts = args.start if isinstance(args.start, list) else [args.start]
    budgets = args.budget if isinstance(args.budget, list) else [args.budget]
    if len(budgets) not in (1, len(starts)):
        raise UsageError(f"--budget must be given once (every robot) or once per --start "
                         f"({len(starts)} starts), got {len(budgets)} budgets")
    points = [parse_start(s) for s in starts]
    if len(points) == 1:
        return points[0], budgets[0]
    return points, (budgets[0] if len(budgets) == 1 else budgets)


def read_traversable(text: str | None):
    """``--traversable``: None, ``"valid"``, or a NetCDF file holding one boolean (or 0/1)
    ``(lat, lon)`` variable (True = the robot may enter), read as a DataArray."""
    if text is None or text.strip().lower() == "valid":
        return None if text is None else "valid"
    from ._validation import read_netcdf

    ds = read_netcdf(text, "--traversable mask file", "a (lat, lon) boolean mask")
    names = [v for v in ds.data_vars if ds[v].ndim == 2]
    if len(names) != 1:
        raise UsageError(f"--traversable {text} must hold exactly one 2-D (lat, lon) variable "
                         f"(True = may enter), found {list(ds.data_vars)}")
    mask = ds[names[0]]
    if mask.dtype != bool:
        values = np.asarray(mask.values)
        if not np.issubdtype(values.dtype, np.number) or not np.isin(values, (0, 1)).all():
            raise UsageError(f"--traversable {text}: variable {names[0]!r} must be boolean or "
                             f"0/1 (True = may enter), got dtype {values.dtype}")
        mask = mask.astype(bool)
    return mask


def path_options(args: argparse.Namespace, *, fleet_end: bool = True):
    """The path request of ``plan`` / ``bound`` / ``evaluate``: one
    :class:`~lrm_cvx.planning.request.PathOptions` read from the flags (the paper's when none
    is given)."""
    from .planning.request import PathOptions

    end = getattr(args, "end", None) if fleet_end else None
    return PathOptions(
        metric=args.metric, speed=args.speed, stop_cost=args.stop_cost or 0.0,
        traversable=None if args.traversable is None else read_traversable(args.traversable),
        closed=bool(args.closed), end=None if end is None else parse_start(end, "--end"),
        sense_along=bool(getattr(args, "sense_along", False)),
        sensor=getattr(args, "sensor", None))


def metric_choices() -> tuple[str, ...]:
    try:
        from .planning.paths import METRICS
    except ImportError:  # pragma: no cover - the path model defines them
        return ("grid", "km")
    return tuple(METRICS)


def add_starts_budgets(p: argparse.ArgumentParser) -> None:
    """``--start`` (repeated for a fleet) and ``--budget`` (once, or once per start): the
    robots of ``plan``, ``bound`` and ``monitor plan`` (read with :func:`starts_budgets`)."""
    p.add_argument("--start", required=True, action="append",
                   help="start location LAT,LON or LAT LON in degrees (e.g. --start -10 150); "
                   "repeat it for a fleet, one --start per robot")
    p.add_argument("--budget", required=True, type=finite_number, action="append",
                   help="path budget in the metric's unit (grid cells; km with --metric km; "
                   "hours with --speed), once for every robot or once per --start")


def add_path_options(p: argparse.ArgumentParser, *, route: bool = False) -> None:
    """The path model (docs/planning.md): budget unit, travel graph, closed tours; with
    ``route`` also ``--end`` and ``--sense-along`` (plan, bound, monitor plan)."""
    p.add_argument("--metric", default="grid", choices=metric_choices(),
                   help="budget unit: grid (grid cells, the paper; default) or km (great-circle "
                   "km between cell centres)")
    p.add_argument("--speed", type=finite_number, default=None,
                   help="speed in km/h (with --metric km): the budget is then in hours")
    p.add_argument("--stop-cost", type=finite_number, default=0.0,
                   help="cost of each sampling stop in the budget's unit (time on station; "
                   "default 0)")
    p.add_argument("--traversable", default=None, metavar="valid|PATH.nc",
                   help="travel only through enterable cells: valid (the model's cells) or a "
                   "NetCDF file with one boolean (lat, lon) variable (True = may enter)")
    p.add_argument("--closed", action="store_true",
                   help="closed tours: every route returns to its start")
    if route:  # plan and monitor plan (not evaluate: a fleet's starts vary there)
        p.add_argument("--end", default=None,
                       help="LAT,LON where every route must finish (a sampling stop; not with "
                       "--closed)")
        p.add_argument("--sense-along", action="store_true",
                       help="observe every cell the route passes, not only its stops")
        p.add_argument("--sensor", default=None,
                       metavar="KIND[:SIZEkm][,altitude=KM,fov=DEG][,errors=shared]",
                       help="what a stop observes: point (default), square:SIZEkm or "
                       "disc:SIZEkm (the mean of the cells in a footprint SIZE km wide, "
                       "growing by 2 altitude tan(fov/2)), or leg-average (a towed sensor: "
                       "the mean of the cells of each leg); errors=shared: the average keeps "
                       "the cells' noise (a model fitted without --spatial)")


def mask_files(args: argparse.Namespace) -> list[str]:
    """The ``--traversable`` mask file, an input (never overwritten), or nothing."""
    t = getattr(args, "traversable", None)
    return [] if t is None or t.strip().lower() == "valid" else [t]



# ----------------------------------------------------------------------- the route planner
def add_plan_criterion(p: argparse.ArgumentParser) -> None:
    """``--criterion``, ``--cost`` and ``--ridge`` of the greedy route planner (plan, bound,
    monitor plan; read with :func:`default_criterion` and :func:`plan_route`)."""
    from .information import CRITERIA
    from .planning.routecost import COSTS
    from .recommended import RECOMMENDED

    p.add_argument("--criterion", choices=CRITERIA, default=None,
                   help=f"planning criterion (default: {RECOMMENDED['criterion']}, or fisher "
                   "with a note when the model has no spatial residual; fisher with --paper)")
    p.add_argument("--cost", default=first(COSTS), choices=COSTS,
                   help="path cost (default: %(default)s)")
    p.add_argument("--ridge", type=finite_number, default=0.0,
                   help="ridge added to the information")


def plan_route(Y: Any, region: Any, start: Any, budget: Any, args: argparse.Namespace, *,
               criterion: str, initial: str, path: Any, paper: bool, **terms: Any) -> Any:
    """The greedy plan of ``plan`` / ``bound`` / ``monitor plan``: ``--cost``, ``--ridge`` and
    the progress bar from ``args``, the recommended check against rival routes where the path
    request allows it unless ``--paper``; ``terms``: the criterion's prior terms."""
    from .planning import plan_greedy
    from .planning.lines import lines_where_possible

    return plan_greedy(Y, region, start, budget, criterion=criterion, cost=args.cost,
                       ridge=args.ridge, progress=not args.quiet, initial=initial, path=path,
                       refine=None if paper else lines_where_possible(path), **terms)


def require_plan(state: Any, path: str) -> Any:
    """The plan stored in the monitor state read from ``path``; UsageError when it holds
    none."""
    if state.current_plan is None:
        raise UsageError(f"state file {path} holds no plan: run 'lrm-cvx monitor plan' first")
    return state.current_plan
