"""The settings records and the tables of the evaluation protocol.

:class:`PlanningOptions` (how the methods plan) and :class:`ScoringOptions` (how each plan is
scored) group the protocol's secondary settings, validated once when built, as
:class:`~lrm_cvx.planning.request.PathOptions` does for the path model.
:class:`ProtocolResults` holds the ``(method, budget, start, trial[, test_time])`` arrays an
:class:`~lrm_cvx.evaluation.EvaluationProtocol` run fills; :func:`summary` reduces the
Dataset of :func:`~lrm_cvx.evaluation.evaluate` (or of a rolling-origin
:func:`~lrm_cvx.evaluation.backtest`) to one row per method and budget, :func:`coverage_check`
says whether a backtest's intervals hold, :func:`path_label` describes the path model and
:func:`save_results` writes the Dataset and its tables. :mod:`lrm_cvx.evaluation` re-exports
every public name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from ._validation import atomic_output, check_flag, check_positive
from .errors import DataError, ModelError

__all__ = ["PlanningOptions", "ScoringOptions", "ProtocolResults", "summary", "coverage_check",
           "COVERAGE_BANDS", "LOWEST_BLOCK_95", "path_label", "save_results"]


def check_int(value: Any, name: str, minimum: int, error: type[Exception] = ModelError) -> int:
    """``value`` as an int >= ``minimum`` (bools, floats with a fraction, NaN refused; ``error``
    naming ``name`` otherwise)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float,
                                                                     np.floating)):
        raise error(f"{name} must be an integer >= {minimum}, got {value!r}")
    if not np.isfinite(value) or float(value) != int(value) or value < minimum:
        raise error(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def options_of(value: Any, cls: type, name: str) -> Any:
    """``value`` as a ``cls`` record (None: its defaults); ModelError naming ``name``
    otherwise."""
    if value is None:
        return cls()
    if not isinstance(value, cls):
        raise ModelError(f"{name} must be a {cls.__name__} (or None), got "
                         f"{type(value).__name__}")
    return value


@dataclass(frozen=True)
class PlanningOptions:
    """How the protocol's methods plan (docs/evaluation.md); validated when built.

    ``criterion`` and ``cost``: the paper's greedy's criterion and cost function (filled in
    where a method leaves them open); ``ridge`` (>= 0): every planner's information ridge;
    ``random_trials``: the random walk's repeats per start and budget (an integer >= 0, >= 1
    when ``"random"`` is among the protocol's methods);
    ``certify``: the certified bound attached to the greedy's plans, ``"fast"``, ``"tight"``
    (``True`` is ``"tight"``) or ``False``; ``n_jobs`` (an integer >= 1): threads over the
    start cells. The defaults are the paper's. A bad value raises ModelError naming the field.

    >>> PlanningOptions(random_trials=5, certify=False).random_trials
    5
    """

    criterion: str = "fisher"
    cost: str = "nearest-neighbor"
    ridge: float = 0.0
    random_trials: int = 70
    certify: bool | str = "fast"
    n_jobs: int = 1

    def __post_init__(self) -> None:
        for name in ("criterion", "cost"):
            if not isinstance(getattr(self, name), str):
                raise ModelError(f"{name} must be a string, got {getattr(self, name)!r}")
        if self.certify not in (False, "fast", "tight", True):
            raise ModelError(f"certify must be False, 'fast' or 'tight', got {self.certify!r}")
        object.__setattr__(self, "ridge", check_positive(self.ridge, "ridge", error=ModelError))
        object.__setattr__(self, "random_trials", check_int(self.random_trials,
                                                            "random_trials", 0))
        object.__setattr__(self, "certify", "tight" if self.certify is True else self.certify)
        object.__setattr__(self, "n_jobs", check_int(self.n_jobs, "n_jobs", 1))


@dataclass(frozen=True)
class ScoringOptions:
    """How the protocol scores each plan on the test snapshots (docs/evaluation.md);
    validated when built.

    ``model_params``: extra GLRM parameters of the model fitted for the prediction
    (``offset``, ``scale``, ``noise``, ``spatial``); ``fold_in``: the prediction (a dict with
    keys among ``prior``, ``spatial``, ``ridge``), its ``ridge`` defaulting to ``fold_ridge``
    (>= 0), the paper's fold-in's ridge; ``min_observations`` (an integer >= 0): (plan,
    snapshot) pairs with fewer observations are left out of the error. ``model_params`` and
    ``fold_in`` left None are the recommended setting's (``evaluate(paper=True)``: the
    paper's). A bad value raises ModelError naming the field.

    >>> ScoringOptions(min_observations=4, fold_in={"prior": "empirical"}).min_observations
    4
    """

    model_params: dict | None = None
    fold_in: dict | None = None
    fold_ridge: float = 0.0
    min_observations: int = 10

    def __post_init__(self) -> None:
        for name in ("model_params", "fold_in"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, dict):
                raise ModelError(f"{name} must be a dict or None, got {type(value).__name__}")
        bad = set(self.fold_in or {}) - {"prior", "spatial", "ridge"}
        if bad:
            raise ModelError(f"fold_in keys must be among prior, spatial, ridge; got "
                             f"{sorted(bad)}")
        object.__setattr__(self, "fold_ridge", check_positive(self.fold_ridge, "fold_ridge",
                                                              error=ModelError))
        object.__setattr__(self, "min_observations", check_int(self.min_observations,
                                                               "min_observations", 0))


@dataclass
class ProtocolResults:
    """The arrays a protocol run fills, ``(method, budget, start, trial[, test_time])``."""

    info: np.ndarray
    cost: np.ndarray
    n_cells: np.ndarray
    mse: np.ndarray
    n_obs: np.ndarray
    coverage: np.ndarray
    mse_ml: np.ndarray | None
    coverage_ml: np.ndarray | None
    bound: np.ndarray
    robot_cost: np.ndarray | None
    own_bound: np.ndarray
    own_value: np.ndarray
    routes: dict = field(default_factory=dict)
    route_robots: dict = field(default_factory=dict)

    @classmethod
    def empty(cls, n_methods: int, n_budgets: int, n_starts: int, n_trials: int, n_test: int,
              n_robots: int, temporal: bool) -> ProtocolResults:
        shape = (n_methods, n_budgets, n_starts, n_trials)
        return cls(
            info=np.full(shape, np.nan), cost=np.full(shape, np.nan),
            n_cells=np.zeros(shape, dtype=np.int32), mse=np.full(shape + (n_test,), np.nan),
            n_obs=np.zeros(shape + (n_test,), dtype=np.int32),
            coverage=np.full(shape + (n_test, 2), np.nan),
            mse_ml=np.full(shape + (n_test,), np.nan) if temporal else None,
            coverage_ml=np.full(shape + (n_test, 2), np.nan) if temporal else None,
            bound=np.full((n_budgets, n_starts), np.nan),
            robot_cost=np.full(shape + (n_robots,), np.nan) if n_robots > 1 else None,
            own_bound=np.full((n_budgets, n_starts), np.nan),
            own_value=np.full((n_budgets, n_starts), np.nan),
        )

    def record(self, row: tuple, methods: tuple[str, ...]) -> None:
        """Store one row of :meth:`EvaluationProtocol._run_start`."""
        m, b, s, trial, plan, e, n, cert, c, e_ml, c_ml = row
        if cert is not None and methods[m] != "greedy":
            self.own_bound[b, s] = cert.bound  # the recommended method's own criterion
            self.own_value[b, s] = cert.information
        at = (m, b, s, trial)
        self.info[at] = plan.information
        self.cost[at] = plan.cost
        self.n_cells[at] = len(plan.cells)
        if self.robot_cost is not None:
            self.robot_cost[at] = plan.robot_costs
        self.mse[at] = e
        self.n_obs[at] = n
        self.coverage[at] = c
        if self.mse_ml is not None:
            self.mse_ml[at] = e_ml
            self.coverage_ml[at] = c_ml
        if methods[m] == "greedy":
            self.bound[b, s] = np.nan if cert is None else cert.bound
            self.routes[(b, s)] = np.asarray(plan.route)
            self.route_robots[(b, s)] = np.asarray(getattr(plan, "route_robot", []))

    def padded(self, entries: dict) -> np.ndarray:
        """``(budget, start, step)`` int64 of the greedy's ``entries``, padded with -1."""
        width = max([len(r) for r in self.routes.values()] + [1])
        out = np.full(self.bound.shape + (width,), -1, dtype=np.int64)
        for (b, s), r in entries.items():
            out[b, s, : len(r)] = r
        return out



def summary(results: xr.Dataset, by_origin: bool = False) -> pd.DataFrame:
    """Mean and standard error of information and MSE per method and budget.

    A rolling-origin result (:func:`backtest`) is pooled over its blocks; with
    ``by_origin`` there is one row per block, method and budget instead (columns ``origin``,
    ``origin_time``, ``n_train`` first). ``by_origin`` on a result of one block is that block.

    Information averages the usable plans; MSE averages every (plan, test snapshot) pair with
    enough observations. Standard error = std / sqrt(count). ``coverage68_mean`` /
    ``coverage95_mean`` average the per-pair coverage. Results of ``evaluate(temporal=...)``
    put memoryless and temporal side by side: ``mse_memoryless_mean`` / ``_se``, the
    memoryless coverage, and ``temporal_cut`` = ``1 - mse / mse_memoryless`` over the pairs
    where both are defined (positive: the filter lowers the error). ``path`` describes the path
    model (:func:`path_label`: ``"grid"`` for the paper's).
    """
    by_origin = check_flag(by_origin, "by_origin", error=ModelError)
    if by_origin and "origin" in results.dims:
        tables = []
        for i in range(results.sizes["origin"]):
            block = results.isel(origin=i)
            table = summary(block)
            table.insert(0, "n_train", int(block["n_train"]))
            table.insert(0, "origin_time", block["origin_time"].values)
            table.insert(0, "origin", int(block["origin"]))
            tables.append(table)
        return pd.concat(tables, ignore_index=True)
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
                **_side_by_side(sel),
            })
    df = pd.DataFrame(rows)
    df["temporal"] = str(results.attrs.get("temporal", "none"))
    df["path"] = path_label(results.attrs)
    df["complete_mse"] = float(results["complete_mse"].mean())
    return df


COVERAGE_BANDS = {68: (0.63, 0.73), 95: (0.93, 0.97)}
"""Where the mean coverage of calibrated 68 % / 95 % intervals should fall over a rolling-origin
backtest: :func:`coverage_check`, ``plots.plot_backtest``."""
LOWEST_BLOCK_95 = 0.90
"""The lowest 95 % coverage one block of a backtest may show."""


def coverage_check(results: xr.Dataset) -> pd.DataFrame:
    """Whether the intervals of a rolling-origin backtest (:func:`backtest`) hold, per
    method and budget: ``cov68`` / ``cov95`` the mean over the blocks of each block's mean
    coverage, ``cov95_lowest_block``, ``mse`` the mean of the blocks' mean MSE, and ``holds``:
    both means inside :data:`COVERAGE_BANDS` and no block's 95 % below
    :data:`LOWEST_BLOCK_95`. A block without coverage (an uncalibrated memoryless twin) leaves
    ``holds`` False. ``verdict`` says which way a miss goes (a user can live with intervals too
    wide, not with intervals too narrow): ``"holds"``, else the misses joined by ``"; "``
    (``"68 % too wide"``, ``"95 % too narrow"``, ``"a block's 95 % below 0.9"``, ...), or
    ``"no intervals"``. DataError for a result of one block."""
    if "origin" not in results.dims:
        raise DataError("coverage_check needs a rolling-origin result (backtest(data, "
                        "origins): a Dataset with an 'origin' dim)")
    per = summary(results, by_origin=True)
    out = per.groupby(["method", "budget"], sort=False).agg(
        blocks=("origin", "nunique"), cov68=("coverage68_mean", "mean"),
        cov95=("coverage95_mean", "mean"), cov95_lowest_block=("coverage95_mean", "min"),
        mse=("mse_mean", "mean")).reset_index()
    (lo68, hi68), (lo95, hi95) = COVERAGE_BANDS[68], COVERAGE_BANDS[95]
    complete = per.groupby(["method", "budget"], sort=False)["coverage95_mean"].apply(
        lambda c: bool(c.notna().all())).to_numpy()
    out["holds"] = (complete & out["cov68"].between(lo68, hi68).to_numpy()
                    & out["cov95"].between(lo95, hi95).to_numpy()
                    & (out["cov95_lowest_block"] >= LOWEST_BLOCK_95).to_numpy())
    out["verdict"] = [_coverage_verdict(row, ok) for row, ok in
                      zip(out.itertuples(index=False), complete, strict=True)]
    return out


def _coverage_verdict(row: Any, complete: bool) -> str:
    """:func:`coverage_check`'s ``verdict`` of one method and budget."""
    if not (complete and np.isfinite(row.cov68) and np.isfinite(row.cov95)):
        return "no intervals"
    misses = []
    for level, value in ((68, row.cov68), (95, row.cov95)):
        lo, hi = COVERAGE_BANDS[level]
        if value < lo:
            misses.append(f"{level} % too narrow")
        elif value > hi:
            misses.append(f"{level} % too wide")
    if row.cov95_lowest_block < LOWEST_BLOCK_95:
        misses.append(f"a block's 95 % below {LOWEST_BLOCK_95:g}")
    return "; ".join(misses) or "holds"


def path_label(attrs: dict[str, Any]) -> str:
    """A short description of the path model recorded in ``evaluate``'s attrs: ``"grid"``
    for the paper's, else e.g. ``"km, speed 1.5 km/h, stop 0.5 h, traversable valid, closed,
    2 robots"`` (the ``path`` column of :func:`summary`)."""
    parts = [str(attrs.get("metric", "grid"))]
    speed = attrs.get("speed", np.nan)
    if speed is not None and np.isfinite(speed):
        parts.append(f"speed {float(speed):g} km/h")
    if attrs.get("stop_cost", 0.0):
        parts.append(f"stop {float(attrs['stop_cost']):g} {attrs.get('budget_unit', '')}".strip())
    if attrs.get("traversable", "none") != "none":
        parts.append(f"traversable {attrs['traversable']}")
    if attrs.get("closed", 0):
        parts.append("closed")
    if int(attrs.get("n_robots", 1)) > 1:
        parts.append(f"{int(attrs['n_robots'])} robots")
    return ", ".join(parts)


def _finite_mean(v: Any) -> float:
    v = np.asarray(v, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else np.nan


def _side_by_side(sel: xr.Dataset) -> dict[str, float]:
    """Coverage columns and, for temporal results, the memoryless columns of one row."""
    out: dict[str, float] = {}
    for level in (68, 95):
        if f"coverage{level}" in sel:
            out[f"coverage{level}_mean"] = _finite_mean(sel[f"coverage{level}"].values)
    if "mse_memoryless" in sel:
        ml = sel["mse_memoryless"].values.ravel()
        tm = sel["mse"].values.ravel()
        both = np.isfinite(ml) & np.isfinite(tm)
        f = ml[np.isfinite(ml)]
        out["mse_memoryless_mean"] = float(f.mean()) if f.size else np.nan
        out["mse_memoryless_se"] = (float(f.std(ddof=1) / np.sqrt(f.size)) if f.size > 1
                                    else np.nan)
        out["temporal_cut"] = (float(1.0 - tm[both].mean() / ml[both].mean())
                               if both.any() and ml[both].mean() > 0 else np.nan)
        for level in (68, 95):
            out[f"coverage{level}_memoryless_mean"] = _finite_mean(
                sel[f"coverage{level}_memoryless"].values)
    return out


def save_results(results: xr.Dataset, out_dir: Any) -> dict[str, Any]:
    """Write ``results.nc`` and ``summary.csv`` into ``out_dir`` atomically; return the paths."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"results": out / "results.nc", "summary": out / "summary.csv"}
    if "origin" in results.dims:  # a rolling-origin backtest: also one row per block
        paths["summary_by_origin"] = out / "summary_by_origin.csv"
    with atomic_output(paths["results"]) as tmp:
        results.to_netcdf(tmp, engine="netcdf4")
    with atomic_output(paths["summary"]) as tmp:
        summary(results).to_csv(tmp, index=False)
    if "summary_by_origin" in paths:
        with atomic_output(paths["summary_by_origin"]) as tmp:
            summary(results, by_origin=True).to_csv(tmp, index=False)
    return paths
