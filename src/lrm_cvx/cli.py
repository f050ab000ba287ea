"""The ``lrm-cvx`` command: thin wrappers over the public functions.

User errors (bad arguments, unreadable files, impossible requests) exit with status 2 and one
line on stderr; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .errors import LrmError

__all__ = ["main", "build_parser"]

DEMO_DIR = Path("lrm-cvx-demo")


class UsageError(LrmError, ValueError):
    """A command-line argument is malformed."""


def _floats(text: str, n: int | None, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UsageError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if n is not None and len(values) != n:
        raise UsageError(f"{what} must have {n} comma-separated numbers, got {text!r}")
    return values


def _start(text: str) -> tuple[float, float]:
    lat, lon = _floats(text, 2, "--start LAT,LON")
    return (lat, lon)


def _load(args: argparse.Namespace):
    from .io import open_data

    bbox = tuple(_floats(args.bbox, 4, "--bbox S,W,N,E")) if args.bbox else None
    return open_data(args.data, var=args.var, bbox=bbox)


def _load_model(path: str):
    from .glrm import GLRM

    return GLRM.load(path)


def _check_output(path: str | Path, inputs: Sequence[str | Path] = ()) -> Path:
    out = Path(path)
    for p in inputs:
        if Path(p).exists() and out.exists() and out.resolve() == Path(p).resolve():
            raise UsageError(f"refusing to overwrite the input file {p}; choose another -o")
    return out


# ---------------------------------------------------------------------------- commands
def cmd_fit(args: argparse.Namespace) -> int:
    from .glrm import GLRM

    data = _load(args)
    out = _check_output(args.output, args.data)
    model = GLRM(rank=args.rank, loss=args.loss, max_iter=args.max_iter, tol=args.tol,
                 offset=args.offset, spatial=args.spatial, random_state=args.seed,
                 progress=not args.quiet).fit(data)
    model.save(out)
    print(f"fitted rank-{args.rank} GLRM on {data.sizes['time']} snapshots x "
          f"{model.region_.n_cells} cells in {model.n_iter_} iterations "
          f"(noise std {model.noise_std_:.4g}); saved {out}")
    return 0


def _plan_from_args(args: argparse.Namespace):
    from .planning import plan_greedy

    model = _load_model(args.model)
    return model, plan_greedy(model.Y_, model.region_, _start(args.start), args.budget,
                              criterion=args.criterion, cost=args.cost, ridge=args.ridge,
                              progress=not args.quiet)


def cmd_plan(args: argparse.Namespace) -> int:
    _, plan = _plan_from_args(args)
    print(f"{len(plan.cells)} cells, cost {plan.cost:.3f} <= budget {plan.budget:g}, "
          f"information {plan.information:.4f} nats")
    if args.output:
        out = _check_output(args.output, [args.model])
        suffix = out.suffix.lower()
        if suffix == ".csv":
            plan.to_csv(out)
        elif suffix in (".geojson", ".json"):
            plan.to_geojson(out)
        else:
            raise UsageError(f"-o must end in .csv or .geojson, got {out.name!r}")
        print(f"route written to {out}")
    return 0


def cmd_bound(args: argparse.Namespace) -> int:
    _, plan = _plan_from_args(args)
    cert = plan.certify()
    print(f"greedy plan: {len(plan.cells)} cells, information {plan.information:.4f} nats")
    print(f"certified upper bound on any feasible plan: {cert.bound:.4f} nats")
    print(f"optimality gap: {cert.gap:.4f} nats (volume ratio per dimension "
          f"{cert.volume_ratio:.4f})")
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    import pandas as pd

    from ._validation import atomic_output

    model = _load_model(args.model)
    try:
        obs = pd.read_csv(args.observations)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot read --observations {args.observations}: {exc}") from None
    if "value" not in obs:
        raise UsageError("--observations needs a 'value' column and 'cell' or 'lat','lon'")
    if "cell" in obs:
        cells = model.region_.check_cells(obs["cell"].to_numpy(), "cell")
    elif {"lat", "lon"} <= set(obs.columns):
        cells = np.atleast_1d(model.region_.cell_of(obs["lat"].to_numpy(), obs["lon"].to_numpy()))
    else:
        raise UsageError("--observations needs a 'cell' column or 'lat' and 'lon' columns")
    result = model.complete((cells, obs["value"].to_numpy(dtype=float)), ridge=args.ridge,
                            prior=args.prior, spatial=args.spatial)
    out = _check_output(args.output, [args.model, args.observations])
    with atomic_output(out) as tmp:
        result.to_netcdf(tmp, engine="netcdf4")
    print(f"predicted {model.region_.n_cells} cells from {len(cells)} observations; "
          f"written to {out}")
    return 0


def _run_evaluation(data, out_dir: Path, *, rank: int, n_test: int, budgets, n_starts: int,
                    random_trials: int, min_observations: int, criterion: str, seed: int,
                    certify: bool, progress: bool) -> None:
    from .evaluation import evaluate, save_results, summary
    from .glrm import GLRM
    from .plots import plot_metrics, plot_predictions, save_figure

    n_train = data.sizes["time"] - n_test
    model = GLRM(rank=rank, random_state=seed, progress=progress).fit(
        data.isel(time=slice(0, n_train)))
    results = evaluate(data, rank=rank, n_test=n_test, budgets=budgets, n_starts=n_starts,
                       random_trials=random_trials, min_observations=min_observations,
                       criterion=criterion, seed=seed, certify=certify, progress=progress,
                       model=model)
    paths = save_results(results, out_dir)
    figs = save_figure(plot_metrics(results), out_dir / "metrics")
    # qualitative figure: the first start cell, three budgets, the first test snapshot
    budgets = results["budget"].values
    chosen = [budgets[i] for i in sorted({0, len(budgets) // 2, len(budgets) - 1})]
    routes = {float(b): results["greedy_route"].sel(budget=b).isel(start=0).values for b in chosen}
    if "greedy" in results["method"].values:
        snap = data.isel(time=n_train)
        figs += save_figure(plot_predictions(model, snap, routes), out_dir / "predictions")
    table = summary(results)
    with np.printoptions(precision=4):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print("wrote " + ", ".join(str(p) for p in [*paths.values(), *figs]))


def cmd_evaluate(args: argparse.Namespace) -> int:
    data = _load(args)
    _run_evaluation(data, Path(args.out), rank=args.rank, n_test=args.n_test,
                    budgets=_floats(args.budgets, None, "--budgets"), n_starts=args.starts,
                    random_trials=args.random_trials, min_observations=args.min_observations,
                    criterion=args.criterion, seed=args.seed, certify=not args.no_certify,
                    progress=not args.quiet)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .datasets import load_sample

    t0 = time.perf_counter()
    out = Path(args.out)
    data = load_sample("sst")
    print(f"sample 'sst': {dict(data.sizes)} ({data.attrs.get('long_name', data.name)})")
    _run_evaluation(data, out, rank=5, n_test=8, budgets=(5, 10, 20, 40), n_starts=10,
                    random_trials=20, min_observations=5, criterion="fisher", seed=0,
                    certify=True, progress=not args.quiet)
    print(f"demo finished in {time.perf_counter() - t0:.1f} s; outputs in {out.resolve()}")
    return 0


# ---------------------------------------------------------------------------- parser
def _add_data(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="+", help="NOAA NDVI CDR files, an image folder, a NetCDF "
                   "file with a (time, lat, lon) variable, or sample:NAME")
    p.add_argument("--var", help="variable name in a generic NetCDF file")
    p.add_argument("--bbox", help="region S,W,N,E in degrees (required for images)")


def _add_plan(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="model file written by 'lrm-cvx fit'")
    p.add_argument("--start", required=True, help="start location LAT,LON (degrees)")
    p.add_argument("--budget", required=True, type=float, help="path budget in grid cells")
    p.add_argument("--criterion", default="fisher", choices=["fisher", "a-optimal"])
    p.add_argument("--cost", default="nearest-neighbor", choices=["nearest-neighbor", "insertion"])
    p.add_argument("--ridge", type=float, default=0.0, help="ridge added to the information")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lrm-cvx",
        description="Persistent environmental monitoring with low-rank models: fit a GLRM, plan "
        "a sampling route, certify it, predict the map, evaluate like the paper.")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("fit", help="fit a GLRM to gridded snapshots")
    _add_data(p)
    p.add_argument("--rank", type=int, default=5)
    p.add_argument("--loss", default="quadratic")
    p.add_argument("--max-iter", type=int, default=100)
    p.add_argument("--tol", type=float, default=1e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--offset", action="store_true", help="fit a per-cell mean (offset)")
    p.add_argument("--spatial", choices=["exponential", "matern32", "matern52", "gaussian"],
                   help="also fit a GP covariance of the residuals")
    p.add_argument("-o", "--output", required=True, help="model file (.nc)")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("plan", help="plan a sampling route with the greedy planner")
    _add_plan(p)
    p.add_argument("-o", "--output", help="route.csv or route.geojson")
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("bound", help="certify the greedy plan's optimality gap")
    _add_plan(p)
    p.set_defaults(func=cmd_bound)

    p = sub.add_parser("predict", help="predict the map from observations")
    p.add_argument("model")
    p.add_argument("--observations", required=True,
                   help="CSV with columns value and cell, or value, lat and lon")
    p.add_argument("--ridge", type=float, default=0.0)
    p.add_argument("--prior", choices=["empirical"], default=None,
                   help="Bayesian fold-in with the training latent vectors' mean and covariance")
    p.add_argument("--spatial", action="store_true",
                   help="add the kriged GP residual (model fitted with a spatial covariance)")
    p.add_argument("-o", "--output", required=True, help="output NetCDF map")
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("evaluate", help="run the paper's evaluation protocol")
    _add_data(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--rank", type=int, default=5)
    p.add_argument("--n-test", type=int, default=8)
    p.add_argument("--budgets", default="5,25,50,100,200")
    p.add_argument("--starts", type=int, default=10)
    p.add_argument("--random-trials", type=int, default=70)
    p.add_argument("--min-observations", type=int, default=10)
    p.add_argument("--criterion", default="fisher", choices=["fisher", "a-optimal"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-certify", action="store_true", help="skip the certified bounds")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="the whole pipeline on the bundled real sample data")
    p.add_argument("--out", default=str(DEMO_DIR), help="output folder (default ./lrm-cvx-demo)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (LrmError, FileNotFoundError, FileExistsError, PermissionError) as exc:
        print(f"lrm-cvx {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
