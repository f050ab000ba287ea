"""The paper's evaluation protocol: planners x budgets x start cells x test snapshots.

Fit a GLRM on all snapshots but the last ``n_test``; for every method, budget and start cell
(and, for the random walk, every trial) plan a route, observe each test snapshot at the route's
cells (cells the snapshot lacks give no observation), fold the observations in, and score the
predicted map against the snapshot's observed cells. Results come back as an
``xarray.Dataset`` with dims ``(method, budget, start, trial, test_time)``.

The reconstruction error of a fold-in is computed from per-snapshot sufficient statistics,
``G = Y_O Y_O^T``, ``b = Y_O d_O`` and ``c = d_O^T d_O`` over the snapshot's observed cells ``O``:
``MSE = (x^T G x - 2 b^T x + c) / |O|``. That is exact and costs ``O(k^2)`` per trial instead
of an ``O(L k)`` map, which makes thousands of trials at two million cells cheap.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr
from tqdm.auto import tqdm

from ._validation import as_factor_matrix, as_generator, atomic_output
from .errors import DataError, ModelError
from .information import CRITERION_REGISTRY
from .registry import Choices, Registry
from .region import Region

__all__ = ["evaluate", "summary", "save_results", "METHODS", "GREEDY_VARIANTS",
           "METHOD_REGISTRY", "SnapshotStatistics", "foldin_mse"]

METHOD_REGISTRY = Registry("method", ModelError)
"""Methods of :func:`evaluate` (objects: ``(planner, criterion)``); ``METHODS`` are the paper's
(the default), ``GREEDY_VARIANTS`` the greedy with a criterion and the model's predictive
fold-in (docs/reconstruction.md). ``greedy:<alias>`` is accepted for every criterion alias."""
METHOD_REGISTRY.register("greedy", ("greedy", None), description="the paper's cost-benefit "
                         "greedy (Fisher information, the paper's fold-in)")
for _d in ("up", "down", "left", "right"):
    METHOD_REGISTRY.register(f"transect-{_d}", (f"transect-{_d}", None),
                             description=f"straight transect going {_d} (a lawnmower at the "
                                         "edge)")
METHOD_REGISTRY.register("random", ("random", None), description="random walk on valid "
                         "8-neighbours (`random_trials` walks per start)")
METHODS: tuple[str, ...] = METHOD_REGISTRY.choices()
for _c in CRITERION_REGISTRY.entries():
    METHOD_REGISTRY.register(
        f"greedy:{_c.name}", ("greedy", _c.name),
        aliases=tuple(f"greedy:{a}" for a in _c.aliases),
        description=f"greedy with the `{_c.name}` criterion and the model's predictive fold-in",
    )
GREEDY_VARIANTS: tuple[str, ...] = Choices(tuple(m for m in METHOD_REGISTRY.choices()
                                                 if m not in METHODS), METHOD_REGISTRY)


def _check_method(m: str) -> str:
    """The canonical name of method ``m`` (aliases accepted); ModelError if unknown."""
    return METHOD_REGISTRY.canonical(m, "method")


@dataclass(frozen=True)
class SnapshotStatistics:
    """Sufficient statistics of the test snapshots for exact fold-in errors.

    ``values`` ``(n_test, L)`` float32 with NaN; ``gram`` ``(n_test, k, k)``, ``cross``
    ``(n_test, k)``, ``sq`` ``(n_test,)``, ``count`` ``(n_test,)`` over each snapshot's observed
    cells; all in float64.
    """

    values: np.ndarray
    gram: np.ndarray
    cross: np.ndarray
    sq: np.ndarray
    count: np.ndarray

    @classmethod
    def from_values(cls, Y: np.ndarray, values: np.ndarray) -> SnapshotStatistics:
        observed = np.isfinite(values)
        d = np.where(observed, values, 0.0).astype(np.float64)
        w = observed.astype(np.float64)
        gram = np.einsum("kl,jl,tl->tkj", Y, Y, w, optimize=True)
        return cls(values=values, gram=gram, cross=d @ Y.T, sq=(d * d).sum(axis=1),
                   count=observed.sum(axis=1))


def foldin_mse(Y: np.ndarray, stats: SnapshotStatistics, cells: np.ndarray, ridge: float = 0.0,
               min_observations: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Fold each test snapshot in from its values at ``cells``; MSE over its observed cells.

    Returns ``(mse, n_obs)``, each ``(n_test,)``; ``mse`` is NaN where a snapshot has fewer than
    ``max(min_observations, 1)`` observations at ``cells`` or the least-squares system is
    rank-deficient with ``ridge == 0`` (the paper's pseudo-inverse is then not unique).
    """
    cells = np.asarray(cells, dtype=np.int64)
    vals = stats.values[:, cells].astype(np.float64)  # (n_test, n)
    obs = np.isfinite(vals)
    n_obs = obs.sum(axis=1)
    Ys = Y[:, cells]
    k = Y.shape[0]
    mse = np.full(len(n_obs), np.nan)
    for t in np.flatnonzero(n_obs >= max(min_observations, 1)):
        Yo = Ys[:, obs[t]]
        A = Yo @ Yo.T + ridge * np.eye(k)
        rhs = Yo @ vals[t, obs[t]]
        if ridge == 0.0 and np.linalg.matrix_rank(A) < k:
            continue
        x = np.linalg.solve(A, rhs)
        err = x @ stats.gram[t] @ x - 2.0 * stats.cross[t] @ x + stats.sq[t]
        mse[t] = max(err, 0.0) / stats.count[t]
    return mse, n_obs


def _complete_mse(stats: SnapshotStatistics, ridge: float) -> np.ndarray:
    """The "complete" condition: fold-in from every observed cell of each snapshot."""
    k = stats.gram.shape[1]
    out = np.empty(len(stats.count))
    for t in range(len(out)):
        x = np.linalg.lstsq(stats.gram[t] + ridge * np.eye(k), stats.cross[t], rcond=None)[0]
        out[t] = max(stats.sq[t] - stats.cross[t] @ x, 0.0) / stats.count[t]
    return out


def _model_mse(model: Any, values: np.ndarray, cells: np.ndarray, fold_in: dict,
               min_observations: int) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`foldin_mse` but with the model's predictive options (offset, scale, per-cell
    noise, ``fold_in={"prior": ..., "spatial": ...}``): full maps, MSE over each snapshot's
    observed cells. ``O(n_test L k)`` (plus kriging) per plan."""
    from .glrm.predictive import posterior_complete

    cells = np.asarray(cells, dtype=np.int64)
    V = np.full(values.shape, np.nan)
    V[:, cells] = values[:, cells]
    n_obs = np.isfinite(V).sum(axis=1)
    mse = np.full(values.shape[0], np.nan)
    ok = np.flatnonzero(n_obs >= max(min_observations, 1))
    if ok.size == 0:
        return mse, n_obs
    try:
        pred, *_ = posterior_complete(model, V[ok], prior=fold_in.get("prior"),
                                      spatial=bool(fold_in.get("spatial", False)),
                                      ridge=float(fold_in.get("ridge", 0.0)))
    except ModelError:  # too few observations for a fold-in without prior
        return mse, n_obs
    err = (pred - values[ok]) ** 2
    mse[ok] = np.nanmean(err, axis=1)
    return mse, n_obs


def _plan(method: str, Y: np.ndarray, region: Region, start: int, budget: float,
          rng: np.random.Generator, criterion: str, cost: str, ridge: float,
          model: Any = None, fold_in: dict | None = None):
    from .planning import plan_greedy, random_walk, transect

    if method.startswith("greedy:"):
        crit = method.split(":", 1)[1]
        kw = model.planner_kwargs(prior="empirical", spatial=crit == "gp-variance")
        if crit != "gp-variance":
            kw = {k: v for k, v in kw.items() if k not in ("prior_cov", "spatial_cov")}
        return plan_greedy(Y, region, start, budget, criterion=crit, cost=cost, ridge=ridge,
                           progress=False, initial="start", **kw)
    if method == "greedy":
        return plan_greedy(Y, region, start, budget, criterion=criterion, cost=cost,
                           ridge=ridge, progress=False)
    if method.startswith("transect-"):
        return transect(region, start, budget, method.split("-", 1)[1], Y=Y, ridge=ridge)
    if method == "random":
        return random_walk(region, start, budget, rng, Y=Y, ridge=ridge)
    raise ModelError(f"unknown method {method!r}; expected one of {METHODS}")


def evaluate(
    data: xr.DataArray,
    *,
    rank: int = 5,
    n_test: int = 8,
    budgets: Sequence[float] = (5, 25, 50, 100, 200),
    n_starts: int = 10,
    methods: Sequence[str] = METHODS,
    random_trials: int = 70,
    min_observations: int = 10,
    criterion: str = "fisher",
    cost: str = "nearest-neighbor",
    ridge: float = 0.0,
    fold_ridge: float = 0.0,
    certify: bool | str = "fast",
    model: Any = None,
    seed: int = 0,
    n_jobs: int = 1,
    progress: bool = True,
    model_params: dict | None = None,
    fold_in: dict | None = None,
) -> xr.Dataset:
    """Run the paper's evaluation protocol on ``data`` ``(time, lat, lon)``.

    Parameters follow the paper: a rank-``rank`` GLRM fitted on all snapshots but the last
    ``n_test`` (or the given fitted ``model``, whose region must match ``data``), ``n_starts``
    seeded random valid start cells shared by every method, the random walk repeated
    ``random_trials`` times per start and budget, and (plan, snapshot) pairs with fewer than
    ``min_observations`` observations excluded from the error. ``ridge`` is the planners'
    information ridge, ``fold_ridge`` the fold-in's. ``certify`` attaches to each greedy plan
    the certified upper bound of :func:`lrm_cvx.planning.plan_bound`: ``"fast"`` (the budget
    disk relaxation, well under a second at paper scale), ``"tight"`` (with distance cuts and
    the midpoint cover: tighter, ~40 s a plan at paper scale) or ``False``.

    Reconstruction options (issue #8, docs/reconstruction.md; defaults are the paper's):
    ``methods`` may add ``"greedy:fisher"``, ``"greedy:a-optimal"``, ``"greedy:gp-variance"``:
    the greedy with a criterion on the model's posterior (``GLRM.planner_kwargs`` with the
    empirical prior; ``gp-variance`` also with the GP residual, needs ``spatial`` in
    ``model_params``), started from the start cell alone (``initial="start"``).
    ``model_params`` are extra GLRM parameters of the fit (``offset``,
    ``scale``, ``noise``, ``spatial``); ``fold_in`` (``{"prior": "empirical", "spatial": True}``)
    is the prediction used for every method's error. With either, errors come from full
    predicted maps and ``complete_mse_model`` is the model's fold-in (without the spatial
    term) from every observed cell.

    Returns a Dataset with ``information``, ``cost``, ``n_cells`` ``(method, budget, start,
    trial)``, ``mse`` and ``n_obs`` ``(method, budget, start, trial, test_time)``, ``bound``
    ``(budget, start)``, ``complete_mse`` ``(test_time)``, the start cells, and the greedy
    routes (``greedy_route``, padded with -1) for the qualitative figures.
    """
    from .glrm import GLRM

    if not isinstance(data, xr.DataArray) or data.ndim != 3:
        raise DataError("data must be a (time, lat, lon) DataArray")
    methods = tuple(_check_method(m) for m in methods)
    model_params = dict(model_params or {})
    fold_in = dict(fold_in or {})
    bad = set(fold_in) - {"prior", "spatial", "ridge"}
    if bad:
        raise ModelError(f"fold_in keys must be among prior, spatial, ridge; got {sorted(bad)}")
    budgets = tuple(float(b) for b in budgets)
    if not budgets or min(budgets) < 0:
        raise ModelError(f"budgets must be a non-empty sequence of numbers >= 0, got {budgets}")
    if certify not in (False, "fast", "tight", True):
        raise ModelError(f"certify must be False, 'fast' or 'tight', got {certify!r}")
    certify = "tight" if certify is True else certify
    if not 0 < n_test < data.sizes["time"]:
        raise DataError(f"n_test must be in [1, {data.sizes['time'] - 1}], got {n_test}")
    train, test = data.isel(time=slice(None, -n_test)), data.isel(time=slice(-n_test, None))
    if model is None:
        model = GLRM(rank=rank, random_state=seed, progress=progress,
                     **model_params).fit(train)
    region = model.region_
    if region is None:
        raise ModelError("model must have been fitted on a DataArray (it has no region)")
    Y = as_factor_matrix(model.Y_, region)
    test_values = region.stack(test)
    stats = SnapshotStatistics.from_values(Y, test_values)
    use_model = bool(fold_in) or not model.is_plain_low_rank
    test_values = test_values.astype(np.float64) if use_model else None
    rng = as_generator(seed)
    if n_starts > region.n_cells:
        raise DataError(f"n_starts={n_starts} exceeds the {region.n_cells} valid cells")
    starts = np.sort(rng.choice(region.n_cells, size=n_starts, replace=False))
    n_trials = random_trials if "random" in methods else 1
    shape = (len(methods), len(budgets), n_starts, n_trials)
    info = np.full(shape, np.nan)
    cost_ = np.full(shape, np.nan)
    n_cells = np.zeros(shape, dtype=np.int32)
    mse = np.full(shape + (n_test,), np.nan)
    n_obs = np.zeros(shape + (n_test,), dtype=np.int32)
    bound = np.full((len(budgets), n_starts), np.nan)
    max_route = 0
    routes: dict[tuple[int, int], np.ndarray] = {}
    seeds = np.random.SeedSequence(seed).spawn(n_starts)

    def run_start(s: int) -> list[tuple]:
        out = []
        start_rng = np.random.default_rng(seeds[s])
        for b, budget in enumerate(budgets):
            for m, method in enumerate(methods):
                for trial in range(n_trials if method == "random" else 1):
                    plan = _plan(method, Y, region, int(starts[s]), budget, start_rng,
                                 criterion, cost, ridge, model, fold_in)
                    if use_model:
                        e, n = _model_mse(model, test_values, plan.cells, fold_in,
                                          min_observations)
                    else:
                        e, n = foldin_mse(Y, stats, plan.cells, fold_ridge, min_observations)
                    cert = (plan.certify(tighten=certify == "tight").bound
                            if certify and method == "greedy" else np.nan)
                    out.append((m, b, s, trial, plan, e, n, cert))
        return out

    jobs = range(n_starts)
    bar = tqdm(total=n_starts, desc="evaluate (starts)", disable=not progress)
    with warnings.catch_warnings(), ThreadPoolExecutor(max_workers=max(1, n_jobs)) as pool:
        # at small budgets the forced initial cells exceed the budget: expected, not news
        warnings.filterwarnings("ignore", message=r"the \d+ initial cells")
        for results in pool.map(run_start, jobs):
            for m, b, s, trial, plan, e, n, cert in results:
                info[m, b, s, trial] = plan.information
                cost_[m, b, s, trial] = plan.cost
                n_cells[m, b, s, trial] = len(plan.cells)
                mse[m, b, s, trial] = e
                n_obs[m, b, s, trial] = n
                if methods[m] == "greedy":
                    bound[b, s] = cert
                    routes[(b, s)] = np.asarray(plan.route)
                    max_route = max(max_route, len(plan.route))
            bar.update()
    bar.close()

    greedy_route = np.full((len(budgets), n_starts, max(max_route, 1)), -1, dtype=np.int64)
    for (b, s), r in routes.items():
        greedy_route[b, s, : len(r)] = r
    # a plan counts for the information metric when it yields enough observations in at
    # least one test snapshot (the paper excludes trials with fewer than min_observations)
    usable = (n_obs >= min_observations).any(axis=-1)
    ds = xr.Dataset(
        {
            "information": (("method", "budget", "start", "trial"), info,
                            {"long_name": "Fisher information log det(sum Y_p Y_p^T)",
                             "units": "nats"}),
            "information_usable": (("method", "budget", "start", "trial"), usable),
            "cost": (("method", "budget", "start", "trial"), cost_,
                     {"long_name": "path cost", "units": "grid cells"}),
            "n_cells": (("method", "budget", "start", "trial"), n_cells),
            "mse": (("method", "budget", "start", "trial", "test_time"), mse,
                    {"long_name": "mean squared reconstruction error over observed cells",
                     "units": f"({data.attrs.get('units', '1')})^2"}),
            "n_obs": (("method", "budget", "start", "trial", "test_time"), n_obs),
            "bound": (("budget", "start"), bound,
                      {"long_name": "certified upper bound on the information of any plan",
                       "units": "nats"}),
            "complete_mse": (("test_time",), _complete_mse(stats, fold_ridge),
                             {"long_name": "fold-in error from every observed cell"}),
            "start_cell": (("start",), starts),
            "start_lat": (("start",), region.cell_lat[starts]),
            "start_lon": (("start",), region.cell_lon[starts]),
            "greedy_route": (("budget", "start", "step"), greedy_route),
        },
        coords={
            "method": list(methods),
            "budget": list(budgets),
            "start": np.arange(n_starts),
            "trial": np.arange(n_trials),
            "test_time": test["time"].values if "time" in test.coords else np.arange(n_test),
        },
        attrs={
            "title": "lrm-cvx evaluation (Ricci, Udell, Knepper protocol)",
            "rank": int(Y.shape[0]),
            "n_train": int(train.sizes["time"]),
            "n_test": int(n_test),
            "n_cells_region": int(region.n_cells),
            "min_observations": int(min_observations),
            "criterion": criterion,
            "cost_function": cost,
            "ridge": float(ridge),
            "fold_ridge": float(fold_ridge),
            "random_trials": int(random_trials),
            "seed": int(seed),
            "model_params": repr(model_params),
            "fold_in": repr(fold_in),
        },
    )
    if use_model:
        allc = np.arange(region.n_cells)
        cm, _ = _model_mse(model, test_values, allc, {**fold_in, "spatial": False}, 1)
        ds["complete_mse_model"] = (("test_time",), cm,
                                    {"long_name": "model fold-in error from every observed cell"})
    return ds


def summary(results: xr.Dataset) -> pd.DataFrame:
    """Mean and standard error of information and MSE per method and budget.

    Information averages the usable plans; MSE averages every (plan, test snapshot) pair with
    enough observations. Standard error = std / sqrt(count).
    """
    rows = []
    for method in results["method"].values:
        for budget in results["budget"].values:
            sel = results.sel({"method": method, "budget": budget})
            info = sel["information"].where(sel["information_usable"]).values.ravel()
            info = info[np.isfinite(info)]
            err = sel["mse"].values.ravel()
            err = err[np.isfinite(err)]
            rows.append({
                "method": str(method), "budget": float(budget),
                "information_mean": info.mean() if info.size else np.nan,
                "information_se": (info.std(ddof=1) / np.sqrt(info.size)
                                   if info.size > 1 else np.nan),
                "mse_mean": err.mean() if err.size else np.nan,
                "mse_se": err.std(ddof=1) / np.sqrt(err.size) if err.size > 1 else np.nan,
                "n_plans": int(info.size), "n_predictions": int(err.size),
                "mean_cells": float(sel["n_cells"].where(np.isfinite(sel["cost"])).mean()),
            })
    df = pd.DataFrame(rows)
    df["complete_mse"] = float(results["complete_mse"].mean())
    return df


def save_results(results: xr.Dataset, out_dir: Any) -> dict[str, Any]:
    """Write ``results.nc`` and ``summary.csv`` into ``out_dir`` atomically; return the paths."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"results": out / "results.nc", "summary": out / "summary.csv"}
    with atomic_output(paths["results"]) as tmp:
        results.to_netcdf(tmp, engine="netcdf4")
    with atomic_output(paths["summary"]) as tmp:
        summary(results).to_csv(tmp, index=False)
    return paths
