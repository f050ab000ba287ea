"""Helpers the ``lrm-cvx`` commands share (:mod:`lrm_cvx.cli` and :mod:`lrm_cvx.cli_monitor`).

Argument readers (``LAT,LON``, finite numbers), the output guard of the CLI contract (never onto
an input, ``--overwrite``, a folder that can take the file), the common options, loading a
model, reading an observations CSV, and describing / writing a plan. Errors a user can fix are
:class:`UsageError` (one line, exit status 2; docs/cli.md).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import guard_outputs
from .errors import LrmError

__all__ = ["UsageError", "parse_floats", "check_lat", "parse_start", "finite_number",
           "add_common", "add_output", "check_writable", "guard_paths", "load_model",
           "read_observations_csv", "describe_plan", "write_plan", "PLAN_SUFFIXES",
           "SENSOR_SUFFIXES", "check_plan_output", "add_mission_options", "starts_budgets",
           "read_traversable", "path_options", "metric_choices", "add_path_options",
           "mask_files", "add_starts_budgets", "add_setting", "paper_setting", "note"]


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


def add_common(p: argparse.ArgumentParser) -> None:
    """-q and --debug after the command too (SUPPRESS keeps the global value otherwise)."""
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="no progress bars")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="print the traceback of an error")


def add_setting(p: argparse.ArgumentParser, recommended: str, paper: str) -> None:
    """``--paper`` and ``--recommended`` (issue #24): the recommended setting is the default,
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


def read_observations_csv(path: str, region: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(cells, values)`` of an observations CSV: a ``value`` column and ``cell`` or
    ``lat``,``lon`` columns (UsageError naming ``--observations`` otherwise)."""
    import pandas as pd

    try:
        obs = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot read --observations {path}: "
                         f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                         ) from None
    if "value" not in obs:
        raise UsageError(f"--observations {path} needs a 'value' column and "
                         f"'cell' or 'lat','lon' columns; it has {list(obs.columns)}")
    if obs.empty:
        raise UsageError(f"--observations {path} has no rows")
    numeric = obs.apply(pd.to_numeric, errors="coerce")
    for col in ("value", "cell", "lat", "lon"):
        if col in obs and (numeric[col].isna() & obs[col].notna()).any():
            raise UsageError(f"--observations column {col!r} must hold numbers")
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
                    f"--observations {path}: {bad.size} row(s) give a 'cell' that is not at "
                    f"their 'lat','lon' (row {i + 1}: cell {int(cells[i])}, but lat "
                    f"{numeric['lat'].iloc[i]:g}, lon {numeric['lon'].iloc[i]:g} is cell "
                    f"{int(at[i])}); give one of the two")
    elif has_coords:
        cells = np.atleast_1d(region.cell_of(numeric["lat"].to_numpy(),
                                             numeric["lon"].to_numpy()))
    else:
        raise UsageError(f"--observations {path} needs a 'cell' column or 'lat' "
                         f"and 'lon' columns; it has {list(obs.columns)}")
    return cells, numeric["value"].to_numpy(dtype=float)


def describe_plan(plan: Any) -> str:
    """One line about a :class:`~lrm_cvx.planning.Plan`: cells, cost against the budget(s)
    (each robot's for a fleet), the criterion value and the non-default path options."""
    # plan.information is always the Fisher log det (nats) of the plan's cells, whatever
    # criterion chose them; -inf while fewer cells than the rank are observed
    value = f"Fisher information {plan.information:.4f} nats"
    if not np.isfinite(plan.information):
        value += " (fewer informative cells than the rank)"
    if plan.criterion != "fisher":
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


def add_mission_options(p: argparse.ArgumentParser) -> None:
    """``--altitude`` and ``--robot`` of the mission files (.plan, .waypoints, .gpx, .kml)."""
    from .planning.missions import DEFAULT_ALTITUDE

    p.add_argument("--altitude", type=finite_number, default=None,
                   help="mission altitude in m above home (.plan, .waypoints; default "
                   f"{DEFAULT_ALTITUDE:g}) or above ground (.gpx, .kml; default none)")
    p.add_argument("--robot", type=int, default=0,
                   help="which robot of a fleet a .plan / .waypoints mission is for "
                   "(default 0; .gpx and .kml hold every robot)")


def write_plan(plan: Any, out: Path, args: argparse.Namespace | None = None) -> None:
    """Write ``plan`` by ``out``'s suffix (checked by the caller): CSV, GeoJSON, or a mission
    file (:func:`lrm_cvx.planning.missions.write_mission`, ``args.altitude`` / ``args.robot``).
    """
    suffix = out.suffix.lower()
    if suffix == ".csv":
        plan.to_csv(out)
    elif suffix in (".geojson", ".json"):
        plan.to_geojson(out)
    else:
        from .planning.missions import DEFAULT_ALTITUDE, write_mission

        altitude = getattr(args, "altitude", None)
        write_mission(plan, out, robot=getattr(args, "robot", 0), altitude=altitude)
        if altitude is None and suffix in (".plan", ".waypoints"):
            print(f"mission altitude {DEFAULT_ALTITUDE:g} m above home (the default; set "
                  "--altitude)")
    print(f"{'sensors' if plan.path.get('kind') == 'static' else 'route'} written to {out}")


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
