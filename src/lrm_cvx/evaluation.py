"""The paper's evaluation protocol: planners x budgets x start cells x test snapshots.

Fit a GLRM on all snapshots but the last ``n_test``; for every method, budget and start cell
(and, for the random walk, every trial) plan a route, observe each test snapshot at the route's
cells (cells the snapshot lacks give no observation), fold the observations in, and score the
predicted map against the snapshot's observed cells. Results come back as an
``xarray.Dataset`` with dims ``(method, budget, start, trial, test_time)``.

The fold-in is the model's :class:`~lrm_cvx.belief.posterior.LatentPosterior` (offset, scale,
per-cell noise, prior). Its reconstruction error is computed from per-snapshot sufficient
statistics in data units, ``G = Y_O W Y_O^T``, ``b = Y_O W z_O`` and ``c = z_O^T W z_O`` over the
snapshot's observed cells ``O`` (``z = (d - offset) / scale``, ``W = diag(scale^2)``):
``MSE = (x^T G x - 2 b^T x + c) / |O|``. That is exact and costs ``O(k^2)`` per trial instead
of an ``O(L k)`` map, which makes thousands of trials at two million cells cheap; only the
spatial residual (``fold_in={"spatial": True}``) needs full kriged maps.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr
from tqdm.auto import tqdm

from ._blas import single_threaded_blas
from ._validation import as_factor_matrix, as_generator, check_flag
from .belief.posterior import LatentPosterior
from .errors import DataError, ModelError, PlanningError
from .evaluation_tables import (
    COVERAGE_BANDS,
    LOWEST_BLOCK_95,
    PlanningOptions,
    ProtocolResults,
    ScoringOptions,
    check_int,
    coverage_check,
    options_of,
    path_label,
    save_results,
    summary,
)
from .planning.planners import (
    GREEDY_VARIANTS,
    METHOD_REGISTRY,
    METHODS,
    check_method,
    needs_spatial,
    planner_for,
    recommended_method,
)
from .planning.request import PATH_FIELDS, Fleet, PathOptions
from .recommended import RECOMMENDED
from .region import Region
from .scoring import (
    SnapshotStatistics,
    complete_mse,
    coverage_subset,
    foldin_mse,
    model_scores,
)
from .validation.calibration import fit_then_try_calibrate
from .validation.selection import memoryless_twin

__all__ = ["evaluate", "backtest", "EvaluationProtocol", "PlanningOptions", "ScoringOptions",
           "summary", "save_results", "METHODS",
           "coverage_check", "COVERAGE_BANDS", "LOWEST_BLOCK_95",
           "GREEDY_VARIANTS", "METHOD_REGISTRY", "SnapshotStatistics", "foldin_mse", "path_label",
           "check_method", "plan_method"]

@dataclass(frozen=True)
class _CampaignPlan:
    """The first day's plan of a campaign, as much of a Plan as ``evaluate`` records."""

    information: float
    cost: float
    n: int
    route: np.ndarray
    robot_costs: np.ndarray
    route_robot: np.ndarray

    @property
    def cells(self) -> range:
        return range(self.n)


def _check_temporal(temporal: Any) -> str | None:
    from .glrm.dynamics import temporal_value

    return temporal_value(temporal)


def _campaign_errors(model: Any, test: xr.DataArray, start: Any, budget: float, method: str,
                     temporal: str | None, seed: int, spatial: Any, min_observations: int,
                     options: dict, path: PathOptions | None = None) -> tuple:
    """One campaign over the test snapshots (:func:`lrm_cvx.campaign.simulate_campaign`) from
    ``start`` (a cell, or a list of cells: a fleet, ``budget`` each) under ``path``:
    ``(mse (n_test,), n_obs, coverage (n_test, 2), the first day's plan as a _CampaignPlan)``;
    ``mse`` NaN where a day has fewer than ``min_observations`` observations."""
    from .campaign import posterior_campaign

    # evaluate never reads mse_forecast: its campaigns build no forecast map
    ds = posterior_campaign(model, test, start, budget, method=method, temporal=temporal,
                            seed=seed, spatial=spatial, path=path, **options)
    n = ds["n_obs"].values
    ok = n >= max(min_observations, 1)
    mse = np.where(ok, ds["mse"].values, np.nan)
    cov = np.stack([ds["coverage68"].values, ds["coverage95"].values], axis=-1)
    cov[~ok] = np.nan
    route = ds["routes"].values[0]
    keep = route >= 0
    robots = (ds["route_robot"].values[0][keep] if "route_robot" in ds
              else np.zeros(int(keep.sum()), np.int64))
    costs = (ds["robot_cost"].values[0] if "robot_cost" in ds
             else ds["route_cost"].values[:1])
    first = _CampaignPlan(float(ds["information"].values[0]), float(ds["route_cost"].values[0]),
                          int(np.unique(route[keep]).size), route[keep], costs, robots)
    return mse, n, cov, first


def plan_method(method: str, Y: np.ndarray, region: Region, start: Any, budget: float,
                rng: np.random.Generator, criterion: str, cost: str, ridge: float,
                model: Any = None, fold_in: dict | None = None, path: Any = None) -> Any:
    """One method's :class:`~lrm_cvx.planning.Plan` from ``start`` (a cell, or a list of
    cells: a fleet, ``budget`` per robot) under the path request ``path`` (a
    :class:`~lrm_cvx.planning.request.PathOptions` or a dict of its keywords): the method's
    planner looked up in :data:`~lrm_cvx.planning.planners.METHOD_REGISTRY`; the
    ``greedy:<criterion>`` variants need ``model`` (their prior: the model's empirical latent
    prior); ``rng`` drives the random walk."""
    planner = planner_for(method, criterion=criterion, cost=cost)
    request = (path if isinstance(path, PathOptions)
               else PathOptions.from_kwargs(None, where="plan_method", **dict(path or {})))
    fleet = Fleet.resolve(region, start, budget, request.unit)
    return planner.plan(Y, region, fleet, request, rng=rng, ridge=ridge,
                        prior=planner.prior_of(model))


def _time_ordered(data: xr.DataArray) -> xr.DataArray:
    """``data`` with ``time`` first and sorted by its coordinate (UserWarning when it was not
    sorted: the protocol tests on the *last* times, never on the past). DataError for no
    ``time`` dim, missing (NaN/NaT) or duplicated times (named)."""
    if "time" not in data.dims:
        raise DataError(f"data must have a 'time' dim (time, lat, lon), got dims {data.dims}")
    if data.dims[0] != "time":
        data = data.transpose("time", ...)
    if "time" not in data.coords:
        return data
    index = pd.Index(data["time"].values)
    missing = np.flatnonzero(pd.isna(index))
    if missing.size:
        raise DataError(f"data's time coordinate has {missing.size} missing values (NaN/NaT) "
                        f"at positions {missing[:10].tolist()}")
    dup = index[index.duplicated()].unique()
    if dup.size:
        raise DataError(f"data's time coordinate has {dup.size} duplicated times, e.g. "
                        f"{[str(v) for v in dup[:5]]}; drop or average them first")
    if not index.is_monotonic_increasing:
        warnings.warn("data's time coordinate is not sorted: sorted by time, so the test "
                      "snapshots are the last n_test times", UserWarning, stacklevel=3)
        data = data.isel(time=np.argsort(index.values, kind="stable"))
    return data


def _recommended_params() -> dict[str, Any]:
    """The GLRM parameters of the recommended setting (the keys of ``RECOMMENDED`` that are
    GLRM parameters), without ``temporal``: the protocol folds every test snapshot in on its
    own, so the fit has no dynamics to choose unless ``temporal=`` asks for them."""
    from .glrm import GLRM

    return {k: v for k, v in GLRM.recommended_params().items() if k != "temporal"}


def _recommended_methods() -> tuple[str, ...]:
    """The default ``methods``: the recommended method, then the paper's (``METHODS``)."""
    first = recommended_method(spatial=True)
    return (first, *(m for m in METHODS if m != first))


def _check_given_model(model: Any, test: xr.DataArray) -> None:
    """A fitted GLRM with a region (ModelError otherwise); UserWarning when it was fitted on
    any of the test times (its errors would be scored on training data)."""
    from .glrm import GLRM

    if not isinstance(model, GLRM):
        raise ModelError(f"model must be a fitted GLRM, got {type(model).__name__}")
    if not hasattr(model, "X_"):
        raise ModelError("model is not fitted yet: call model.fit(train) first, or pass "
                         "model=None to fit on all but the last n_test times")
    X = model.X_
    if isinstance(X, xr.DataArray) and "time" in test.coords and X.dims[1] in X.coords:
        seen = np.intersect1d(np.asarray(X[X.dims[1]].values), np.asarray(test["time"].values))
        if seen.size:
            warnings.warn(f"model was fitted on {seen.size} of the {test.sizes['time']} test "
                          "times: their errors are training errors, not predictions",
                          UserWarning, stacklevel=3)


_EVALUATE_PATH = PATH_FIELDS
"""The path options ``evaluate`` passes to every method (``end`` and ``sense_along``: with
``temporal`` campaigns only)."""


@dataclass(frozen=True)
class _Fitted:
    """What every plan of a protocol run shares: the model and its test statistics."""

    model: Any
    region: Region
    Y: np.ndarray
    train: xr.DataArray
    test: xr.DataArray
    stats: SnapshotStatistics
    use_model: bool
    paper_prior: LatentPosterior
    fold_prior: LatentPosterior

    twin: Any  # the campaigns' memoryless twin (validation.selection.memoryless_twin)


@dataclass(eq=False)
class EvaluationProtocol:
    """The paper's evaluation protocol as an object: the data split (``n_test``), the model
    (``rank``, or a fitted ``model``), the requests (``budgets``, ``n_starts`` start cells,
    ``n_robots`` per start, the path request ``path``), the ``methods`` (names of
    :data:`~lrm_cvx.planning.planners.METHOD_REGISTRY`) and how they plan (``planning``, a
    :class:`PlanningOptions`), the fit and the prediction (``scoring``, a
    :class:`ScoringOptions`) and ``temporal`` campaigns; ``methods`` and the scoring's
    ``model_params`` and ``fold_in`` left None are the recommended setting's (``paper=True``:
    the paper's); validated when built, :meth:`run` returns the Dataset of :func:`evaluate`
    (which is ``EvaluationProtocol(data, ...).run()``; every argument is documented there).

    >>> EvaluationProtocol(da, budgets=(5, 25), methods=("greedy", "random")).run()
    """

    data: xr.DataArray
    rank: int = 5
    n_test: int = 8
    budgets: Sequence[float] = (5, 25, 50, 100, 200)
    n_starts: int = 10
    methods: Sequence[str] | None = None
    model: Any = None
    seed: int = 0
    temporal: str | None = None
    n_robots: int = 1
    path: PathOptions | None = None
    planning: PlanningOptions | None = None
    scoring: ScoringOptions | None = None
    progress: bool = True
    paper: bool = False

    def __post_init__(self) -> None:
        self._check()

    # ------------------------------------------------------------------ validation
    def _check(self) -> None:
        """Every argument checked (and normalised) before any work: the named errors of
        :func:`evaluate`."""
        if not isinstance(self.data, xr.DataArray) or self.data.ndim != 3:
            raise DataError("data must be a (time, lat, lon) DataArray")
        self.data = _time_ordered(self.data)
        self.paper = check_flag(self.paper, "paper", error=ModelError)
        # the defaults left to the protocol (None): the paper's with paper=True, else the
        # recommended setting; _fit adapts the recommended ones to a model without a residual
        self.planning = options_of(self.planning, PlanningOptions, "planning")
        scoring = options_of(self.scoring, ScoringOptions, "scoring")
        model_params, fold_in = scoring.model_params, scoring.fold_in
        self._defaults = {"methods": self.methods is None, "fold_in": fold_in is None}
        if self.methods is None:
            self.methods = METHODS if self.paper else _recommended_methods()
        self._defaults["model_params"] = model_params is None and self.model is None
        if model_params is None and self.model is None and not self.paper:
            model_params = _recommended_params()
        if fold_in is None and not self.paper:
            fold_in = {"prior": RECOMMENDED["prior"],
                       "spatial": bool(RECOMMENDED["fold_spatial"])}
        self.scoring = replace(scoring, model_params=dict(model_params or {}),
                               fold_in=dict(fold_in or {}))
        self.methods = _check_methods(self.methods)
        self.n_test = check_int(self.n_test, "n_test", 1, DataError)
        self.n_starts = check_int(self.n_starts, "n_starts", 1)
        if "random" in self.methods:
            check_int(self.planning.random_trials, "random_trials", 1)
        self.temporal = _check_temporal(self.temporal)
        self.path = PathOptions.from_kwargs(self.path, where="evaluate",
                                            allowed=_EVALUATE_PATH)
        self.n_robots = check_int(self.n_robots, "n_robots", 1, PlanningError)
        if self.temporal is None and (self.path.end is not None or self.path.sense_along):
            raise PlanningError("end and sense_along apply to temporal campaigns only (pass "
                                "temporal='ar1' or 'seasonal', or drop them)")
        if self.temporal is not None:  # a method that cannot follow the path fails here
            from .campaign import method_request

            for m in self.methods:
                method_request(m, planner_for(m), self.path)
        self.budgets = _check_budgets(self.budgets)
        if not 0 < self.n_test < self.data.sizes["time"]:
            raise DataError(f"n_test must be in [1, {self.data.sizes['time'] - 1}], got "
                            f"{self.n_test}")

    # ------------------------------------------------------------------ the steps
    def run(self) -> xr.Dataset:
        """Fit (or take the model), draw the starts, plan and score every (method, budget,
        start, trial), and return the Dataset of :func:`evaluate`."""
        fit = self._fit()
        starts, fleets = self._starts(fit.region)
        results = self._plan_all(fit, starts, fleets)
        self._warn_unscored(results)
        return self._dataset(fit, starts, fleets, results)

    def _warn_unscored(self, res: ProtocolResults) -> None:
        """One UserWarning per budget at which no plan reaches ``min_observations`` on any
        test snapshot: every error there is NaN, which a table alone would not explain."""
        m = max(self.scoring.min_observations, 1)
        for b, budget in enumerate(self.budgets):
            if not (res.n_obs[:, b] >= m).any():
                warnings.warn(f"budget {budget:g}: no plan observes min_observations={m} "
                              "cells on any test snapshot, so every error at this budget is "
                              "NaN; raise the budget or lower min_observations",
                              UserWarning, stacklevel=4)

    def _fit(self) -> _Fitted:
        """The split, the model (fitted on the training snapshots unless given) and the test
        snapshots' statistics and fold-in beliefs."""
        from .glrm import GLRM

        data, n_test = self.data, self.n_test
        train, test = data.isel(time=slice(None, -n_test)), data.isel(time=slice(-n_test, None))
        model = self.model
        if model is not None:
            _check_given_model(model, test)
        if model is None:
            params = dict(self.scoring.model_params)
            if self.temporal == "auto":  # the choice is validated on the training snapshots
                params.setdefault("temporal", "auto")
            model = GLRM(rank=self.rank, random_state=self.seed, progress=self.progress,
                         **params)
            if not self._defaults["model_params"]:  # an asked-for calibration fails loudly
                model.fit(train)
            elif (why := fit_then_try_calibrate(model, train)) is not None:
                # the recommended calibration, a default: a record too short for it warns
                warnings.warn(f"the recommended conformal calibration cannot run on these "
                              f"data ({why}); the intervals are uncalibrated", UserWarning,
                              stacklevel=4)
        region = model.region_
        if region is None:
            raise ModelError("model must have been fitted on a DataArray (it has no region)")
        self._without_residual(model)
        Y = as_factor_matrix(model.Y_, region)
        test_values = region.stack(test)
        # one observation model for every error: the model's offset / scale / noise (data units)
        stats = SnapshotStatistics.from_values(Y, test_values, getattr(model, "offset_", None),
                                               getattr(model, "scale_", None))
        fold_in = self.scoring.fold_in
        use_model = bool(fold_in) or not model.is_plain_low_rank
        ridge = self.scoring.fold_ridge
        paper_prior = model.latent_prior(None, ridge=ridge)  # the paper's fold-in
        fold_prior = (model.latent_prior(fold_in.get("prior"),
                                         ridge=float(fold_in.get("ridge", ridge)),
                                         spatial=bool(fold_in.get("spatial", False)))
                      if use_model else paper_prior)
        return _Fitted(model, region, Y, train, test, stats, use_model, paper_prior, fold_prior,
                       memoryless_twin(model))

    def _without_residual(self, model: Any) -> None:
        """The recommended defaults for a model without a spatial residual: a default method
        on the residual (``greedy:gp-variance``) becomes ``greedy:fisher`` (the empirical prior,
        Fisher criterion), the default fold-in drops the kriged residual; one UserWarning says
        so. Explicit ``methods`` / ``fold_in`` and ``paper=True`` are left alone."""
        if self.paper or getattr(model, "spatial_cov_", None) is not None:
            return
        changed = []
        if self._defaults["methods"] and any(needs_spatial(m) for m in self.methods):
            fallback = recommended_method(spatial=False)
            methods = [fallback if needs_spatial(m) else m for m in self.methods]
            self.methods = tuple(dict.fromkeys(methods))
            changed.append(f"method {RECOMMENDED['method']!r} -> {fallback!r}")
        if self._defaults["fold_in"] and self.scoring.fold_in.get("spatial"):
            self.scoring = replace(self.scoring, fold_in={**self.scoring.fold_in,
                                                          "spatial": False})
            changed.append("fold-in without the kriged residual")
        if changed:
            warnings.warn("the model has no spatial residual, so the recommended setting falls "
                          "back: " + ", ".join(changed) + " (fit GLRM(spatial="
                          f"{RECOMMENDED['spatial']!r}) for the whole recommended setting, or "
                          "pass paper=True)", UserWarning, stacklevel=5)

    def _starts(self, region: Region) -> tuple[np.ndarray, np.ndarray]:
        """``(starts (n_starts,), fleets (n_starts, n_robots))``: seeded distinct cells a robot
        may start from (a bad traversable raises here, before any plan)."""
        from .planning.paths import startable_cells

        n_starts, n_robots = self.n_starts, self.n_robots
        rng = as_generator(self.seed)
        candidates = startable_cells(region, self.path.traversable)
        if n_starts * n_robots > candidates.size:
            where = ("valid cells" if self.path.traversable is None else
                     "enterable cells with an enterable neighbour")
            raise DataError(f"n_starts={n_starts}" + (f" x n_robots={n_robots}" if n_robots > 1
                                                       else "")
                            + f" exceeds the {candidates.size} {where}")
        if n_robots == 1:
            starts = candidates[np.sort(rng.choice(candidates.size, size=n_starts,
                                                   replace=False))]
            return starts, starts[:, None]
        # distinct cells, each fleet's in ascending order
        fleets = np.sort(candidates[rng.choice(candidates.size, size=(n_starts, n_robots),
                                               replace=False)], axis=1)
        return fleets[:, 0], fleets

    def _plan_all(self, fit: _Fitted, starts: np.ndarray, fleets: np.ndarray) -> ProtocolResults:
        """Every start's plans and errors (threads over starts, one seeded stream each)."""
        n_trials = self.planning.random_trials if "random" in self.methods else 1
        out = ProtocolResults.empty(len(self.methods), len(self.budgets), self.n_starts, n_trials,
                             self.n_test, self.n_robots, self.temporal is not None)
        seeds = np.random.SeedSequence(self.seed).spawn(self.n_starts)
        cov = (coverage_subset(fit.stats.values, self.seed),
               fit.stats.values.astype(np.float64))
        p = self.planning
        planners = [planner_for(m, criterion=p.criterion, cost=p.cost) for m in self.methods]
        bar = tqdm(total=self.n_starts, desc="evaluate (starts)", disable=not self.progress)
        with warnings.catch_warnings(), single_threaded_blas(), \
                ThreadPoolExecutor(max_workers=max(1, p.n_jobs)) as pool:  # tiny k x k
            # at small budgets the forced initial cells exceed the budget: expected, not news
            warnings.filterwarnings("ignore", message=r"(robot \d+.s )?\d+ initial cells")
            jobs = [(s, np.random.default_rng(seeds[s]), starts[s], fleets[s])
                    for s in range(self.n_starts)]
            for results in pool.map(lambda job: self._run_start(fit, planners, cov, *job),
                                    jobs):
                for row in results:
                    out.record(row, self.methods)
                bar.update()
        bar.close()
        return out

    def _run_start(self, fit: _Fitted, planners: list[Any], cov: tuple, s: int,
                   start_rng: np.random.Generator, start: Any, fleet: np.ndarray
                   ) -> list[tuple]:
        """One start's rows ``(m, b, s, trial, plan, mse, n_obs, bound, coverage, mse_ml,
        coverage_ml)`` over budgets x methods x trials, in the protocol's order."""
        out = []
        n_trials = self.planning.random_trials if "random" in self.methods else 1
        for b, budget in enumerate(self.budgets):
            for m, method in enumerate(self.methods):
                for trial in range(n_trials if method == "random" else 1):
                    if self.temporal is not None:
                        robots = ([int(c) for c in fleet] if self.n_robots > 1
                                  else int(start))
                        out.append((m, b, s, trial, *self._campaign(fit, robots, budget,
                                                                     method, start_rng)))
                        continue
                    robots = Fleet(tuple(int(c) for c in fleet), (budget,) * fleet.size,
                                   self.n_robots > 1, self.path.unit)
                    planner = planners[m]
                    plan = planner.plan(fit.Y, fit.region, robots, self.path, rng=start_rng,
                                        ridge=self.planning.ridge,
                                        prior=planner.prior_of(fit.model))
                    out.append((m, b, s, trial, plan, *self._score(fit, plan, method, cov)))
        return out

    @property
    def _own_method(self) -> str | None:
        """The recommended method when it is among ``methods`` and its criterion has a
        certificate (a variance criterion), else None."""
        rec = recommended_method(spatial=True)
        return rec if rec in self.methods and rec in _VARIANCE_METHODS else None

    def _score(self, fit: _Fitted, plan: Any, method: str, cov: tuple) -> tuple:
        """``(mse, n_obs, certificate, coverage, None, None)`` of one plan on the test snapshots
        (the certificate of the paper's greedy and of the recommended method, else None)."""
        e, n, c = model_scores(fit.fold_prior, cov[1], plan.cells,
                               self.scoring.min_observations,
                               stats=fit.stats, subsets=cov[0])
        certify = self.planning.certify
        cert = None  # the paper's greedy: its Fisher bound; the recommended method: its own
        if certify and method == "greedy":
            cert = plan.certify(tighten=certify == "tight", refine=False)
        elif certify and method == self._own_method:
            try:
                cert = plan.certify(tighten=certify == "tight", refine=False, tol=_VARIANCE_TOL)
            except PlanningError as exc:  # too many cells for the dense variance bound
                if "at most" not in str(exc):
                    raise
                warnings.warn(f"{method}'s gap is not reported (NaN): {exc}", UserWarning,
                              stacklevel=2)
        return e, n, cert, c, None, None

    def _campaign(self, fit: _Fitted, start: Any, budget: float, method: str,
                  start_rng: np.random.Generator) -> tuple:
        """``(plan, mse, n_obs, None, coverage, mse_memoryless, coverage_memoryless)`` of one
        campaign from ``start`` (a cell, or a fleet's cells) under the protocol's path request
        and its memoryless twin (the same seed): run once when the model's own temporal model
        is memoryless and its twin is itself, the same campaign."""
        cseed = int(start_rng.integers(2**31))
        fold_in, p = self.scoring.fold_in, self.planning
        spatial = fold_in.get("spatial") if "spatial" in fold_in else None
        options = {"cost": p.cost, "ridge": p.ridge, "criterion": p.criterion}
        pairs = ((fit.model, self.temporal), (fit.twin, None))
        runs = [_campaign_errors(m, fit.test, start, budget, method, tm, cseed, spatial,
                                 self.scoring.min_observations, options, self.path)
                for m, tm in pairs[: 1 if self._twin_is_model(fit) else 2]]
        (e, n, c, first), ml = runs[0], runs[-1]
        # the twin's intervals: the model's calibration was made for its inflated variances
        ml_cov = ml[2] if fit.twin is fit.model else np.full_like(ml[2], np.nan)
        return first, e, n, None, c, ml[0], ml_cov

    def _twin_is_model(self, fit: _Fitted) -> bool:
        """Whether the memoryless twin's campaigns are the model's own: ``temporal="auto"``
        on a model that chose no dynamics, and a twin that is the model itself."""
        return (fit.twin is fit.model and self.temporal == "auto"
                and getattr(fit.model, "dynamics_", None) is None)

    def _dataset(self, fit: _Fitted, starts: np.ndarray, fleets: np.ndarray,
                 res: ProtocolResults) -> xr.Dataset:
        """The results as the Dataset of :func:`evaluate`."""
        data, region, path, n_robots = self.data, fit.region, self.path, self.n_robots
        unit = path.unit
        units = f"({data.attrs.get('units', '1')})^2"
        dims4 = ("method", "budget", "start", "trial")
        ds = xr.Dataset(
            {
                "information": (dims4, res.info,
                                {"long_name": "Fisher information log det(sum Y_p Y_p^T)",
                                 "units": "nats"}),
                "information_usable": (dims4, (res.n_obs >= self.scoring.min_observations).any(
                    axis=-1)),  # enough observations in at least one test snapshot
                "cost": (dims4, res.cost,
                         {"long_name": "path cost" + (" (the fleet's total)" if n_robots > 1
                                                      else ""),
                          "units": "grid cells" if unit == "grid units" else unit}),
                "n_cells": (dims4, res.n_cells),
                "mse": (dims4 + ("test_time",), res.mse,
                        {"long_name": "mean squared reconstruction error over observed cells",
                         "units": units}),
                "n_obs": (dims4 + ("test_time",), res.n_obs),
                "bound": (("budget", "start"), res.bound,
                          {"long_name": "certified upper bound on the information of any "
                                        "plan", "units": "nats"}),
                "recommended_bound": (("budget", "start"), res.own_bound, {
                    "long_name": "certified upper bound on the variance any plan removes, "
                                 "under the recommended method's criterion", "units": units,
                    "method": self._own_method or ""}),
                "recommended_value": (("budget", "start"), res.own_value, {
                    "long_name": "variance the recommended method's plan removes, under its "
                                 "criterion", "units": units, "method": self._own_method or ""}),
                "complete_mse": (("test_time",), complete_mse(fit.stats, fit.paper_prior),
                                 {"long_name": "fold-in error from every observed cell",
                                  "units": units}),
                "start_cell": (("start",), starts),
                "start_lat": (("start",), region.cell_lat[starts]),
                "start_lon": (("start",), region.cell_lon[starts]),
                "greedy_route": (("budget", "start", "step"), res.padded(res.routes)),
            },
            coords={
                "method": list(self.methods),
                "budget": list(self.budgets),
                "start": np.arange(self.n_starts),
                "trial": np.arange(res.info.shape[3]),
                "test_time": (fit.test["time"].values if "time" in fit.test.coords
                              else np.arange(self.n_test)),
            },
            attrs=self._attrs(fit),
        )
        if n_robots > 1:
            ds = ds.assign_coords(robot=np.arange(n_robots))
            ds["fleet_start_cell"] = (("start", "robot"), fleets)
            ds["fleet_start_lat"] = (("start", "robot"), region.cell_lat[fleets])
            ds["fleet_start_lon"] = (("start", "robot"), region.cell_lon[fleets])
            ds["robot_cost"] = (dims4 + ("robot",), res.robot_cost,
                                {"long_name": "each robot's path cost", "units": unit})
            ds["greedy_route_robot"] = (("budget", "start", "step"),
                                        res.padded(res.route_robots),
                                        {"long_name": "robot of each greedy_route entry (-1: "
                                                      "padding)"})
        dims5 = dims4 + ("test_time",)
        for i, level in enumerate((68, 95)):
            ds[f"coverage{level}"] = (dims5, res.coverage[..., i], {
                "long_name": f"fraction of held-out observed cells inside the central {level}% "
                             "predictive interval"})
        if self.temporal is not None:
            ds["mse_memoryless"] = (dims5, res.mse_ml, {
                "long_name": "campaign MSE of the memoryless model through the same loop",
                "units": ds["mse"].attrs["units"]})
            for i, level in enumerate((68, 95)):
                ds[f"coverage{level}_memoryless"] = (dims5, res.coverage_ml[..., i])
        if fit.use_model:
            fold_in = self.scoring.fold_in
            cm = complete_mse(fit.stats, fit.model.latent_prior(
                fold_in.get("prior"),
                ridge=float(fold_in.get("ridge", self.scoring.fold_ridge))))
            ds["complete_mse_model"] = (("test_time",), cm, {
                "long_name": "model fold-in error from every observed cell"})
        return ds

    def _attrs(self, fit: _Fitted) -> dict[str, Any]:
        """The Dataset's attrs: the protocol's settings and the path request."""
        path = self.path
        return {
            "title": "lrm-cvx evaluation (Ricci, Udell, Knepper protocol)",
            "rank": int(fit.Y.shape[0]),
            "n_train": int(fit.train.sizes["time"]),
            "n_test": int(self.n_test),
            "n_cells_region": int(fit.region.n_cells),
            "min_observations": int(self.scoring.min_observations),
            "criterion": self.planning.criterion,
            "cost_function": self.planning.cost,
            "ridge": float(self.planning.ridge),
            "fold_ridge": float(self.scoring.fold_ridge),
            "random_trials": int(self.planning.random_trials),
            "seed": int(self.seed),
            "model_params": repr(self.scoring.model_params),
            "fold_in": repr(self.scoring.fold_in),
            "temporal": "none" if self.temporal is None else self.temporal,
            "metric": path.metric,
            "speed": float(np.nan if path.speed is None else path.speed),
            "stop_cost": float(path.stop_cost),
            "traversable": path.traversable_kind,
            "closed": int(bool(path.closed)),
            "n_robots": int(self.n_robots),
            "budget_unit": path.unit,
            **({"end": -1 if path.end is None else int(path.resolved(fit.region).end),
                "sense_along": int(bool(path.sense_along))} if self.temporal else {}),
        }


_VARIANCE_METHODS = ("greedy:gp-variance", "greedy:a-optimal")
"""Greedy methods with a certificate under their own (variance) criterion."""
_VARIANCE_TOL = 1e-2  # the Frank-Wolfe stop: the bound is valid at any iterate, 1 % looser


def _check_methods(methods: Any) -> tuple[str, ...]:
    """``methods`` as canonical names, non-empty, without repeats (ModelError)."""
    if isinstance(methods, str):
        methods = (methods,)
    methods = tuple(check_method(m) for m in methods)
    if not methods:
        raise ModelError(f"methods must name at least one method of {METHODS}")
    if len(set(methods)) != len(methods):
        raise ModelError(f"methods must not repeat, got {list(methods)}")
    return methods


def _check_budgets(budgets: Any) -> tuple[float, ...]:
    """``budgets`` as distinct finite floats >= 0 (ModelError)."""
    try:
        budgets = tuple(float(b) for b in np.atleast_1d(np.asarray(budgets, dtype=object)))
    except (TypeError, ValueError):
        raise ModelError(f"budgets must be a non-empty sequence of numbers >= 0, got "
                         f"{budgets!r}") from None
    if not budgets or min(budgets) < 0 or not np.all(np.isfinite(budgets)):
        raise ModelError(f"budgets must be a non-empty sequence of finite numbers >= 0, got "
                         f"{budgets}")
    if len(set(budgets)) != len(budgets):
        raise ModelError(f"budgets must not repeat, got {list(budgets)}")
    return budgets


def evaluate(
    data: xr.DataArray,
    *,
    rank: int = 5,
    n_test: int = 8,
    budgets: Sequence[float] = (5, 25, 50, 100, 200),
    n_starts: int = 10,
    methods: Sequence[str] | None = None,
    model: Any = None,
    seed: int = 0,
    temporal: str | None = None,
    n_robots: int = 1,
    path: PathOptions | None = None,
    planning: PlanningOptions | None = None,
    scoring: ScoringOptions | None = None,
    progress: bool = True,
    paper: bool = False,
) -> xr.Dataset:
    """Run the paper's evaluation protocol on ``data`` ``(time, lat, lon)``.

    ``criterion``, ``cost``, ``ridge``, ``random_trials``, ``certify`` and ``n_jobs`` below are
    fields of ``planning`` (a :class:`PlanningOptions`); ``model_params``, ``fold_in``,
    ``fold_ridge`` and ``min_observations`` fields of ``scoring`` (a :class:`ScoringOptions`),
    e.g. ``evaluate(da, scoring=ScoringOptions(min_observations=4))``.

    **Defaults**: the recommended setting of docs/reconstruction.md
    (:data:`lrm_cvx.recommended.RECOMMENDED`, read at run time) wherever an argument is left
    out: ``model_params`` its GLRM parameters (today ``offset=True, spatial="auto"`` and the
    conformal interval calibration; no ``temporal``: the protocol is memoryless unless
    ``temporal=`` is given), ``methods`` its method (today ``"greedy:gp-variance"``) followed by
    the paper's ``METHODS`` (the paper's greedy, the transects, the random walk), ``fold_in``
    its prediction (today ``{"prior": "empirical", "spatial": True}``: the empirical prior and
    the kriged residual). A model without a spatial residual (a given ``model``, or
    ``model_params`` without ``spatial``) keeps the empirical prior; the default method becomes
    ``"greedy:fisher"`` and the default fold-in drops the kriged residual, with one UserWarning.
    ``paper=True`` is the paper's setting, unchanged: ``GLRM(rank)``, ``methods=METHODS``, the
    least-squares fold-in (``model_params={}``, ``fold_in={}``). An explicit argument wins over
    both (a given ``model_params`` / ``fold_in`` / ``methods`` replaces that default as a
    whole); ``paper`` must be True or False (ModelError).

    Parameters follow the paper: a rank-``rank`` GLRM fitted on all snapshots but the last
    ``n_test`` (or the given fitted ``model``, whose region must match ``data``), ``n_starts``
    seeded random valid start cells shared by every method, the random walk repeated
    ``random_trials`` times per start and budget, and (plan, snapshot) pairs with fewer than
    ``min_observations`` observations excluded from the error. ``ridge`` is the planners'
    information ridge, ``fold_ridge`` the fold-in's. ``certify`` attaches to each greedy plan
    the certified upper bound of :func:`lrm_cvx.planning.plan_bound`: ``"fast"`` (the budget
    disk relaxation, well under a second at paper scale), ``"tight"`` (with distance cuts and
    the midpoint cover: tighter, ~40 s a plan at paper scale) or ``False``. The recommended
    method's plans (``"greedy:gp-variance"``) get the certificate of their own criterion the
    same way: ``recommended_bound`` and ``recommended_value`` ``(budget, start)`` (variance
    removed, the data's units squared; NaN, with a warning, where a plan may observe more
    cells than :data:`~lrm_cvx.planning.varbound.DENSE_MAX` and the residual's metric is km).

    The test snapshots are the last ``n_test`` *times*: data whose ``time`` coordinate is not
    sorted is sorted first (with a UserWarning); missing (NaT/NaN) or duplicated times raise
    DataError naming them. ``n_starts``, ``n_test``, ``n_jobs`` (and ``random_trials`` when
    ``"random"`` is among ``methods``) must be integers >= 1, ``methods`` non-empty without
    repeats, ``budgets`` finite, >= 0 and distinct (ModelError / DataError otherwise).

    Reconstruction options (docs/reconstruction.md; defaults above):
    ``methods`` may add ``"greedy:fisher"``, ``"greedy:a-optimal"``, ``"greedy:gp-variance"``:
    the greedy with a criterion on the model's posterior (``GLRM.planner_kwargs`` with the
    empirical prior; ``gp-variance`` also with the GP residual, needs ``spatial`` in
    ``model_params``), started from the start cell alone (``initial="start"``).
    ``model_params`` are extra GLRM parameters of the fit (``offset``,
    ``scale``, ``noise``, ``spatial``); ``fold_in`` (``{"prior": "empirical", "spatial": True}``)
    is the prediction used for every method's error (its ``ridge`` defaults to ``fold_ridge``).
    With either, ``complete_mse_model`` is the model's fold-in with that prior (without the
    spatial term) from every observed cell. Every error, ``complete_mse`` (the paper's fold-in
    from every observed cell) included, is in the data's units (the model's offset and scale
    are undone).

    Persistent monitoring (docs/monitoring.md): ``temporal=None`` (default) is the
    protocol above, each test snapshot folded in on its own. ``"ar1"``/``"seasonal"``: for every
    start, method, budget (and random trial) one campaign
    (:func:`~lrm_cvx.campaign.simulate_campaign`) runs over the test snapshots in time order,
    each day planned against the filter's forecast and assimilated by the filter (the model's
    ``dynamics_`` when of that kind, else estimated from ``X_``); ``mse``, ``n_obs`` and the
    coverage are the campaign's, and the same campaigns run memoryless through the same loop
    give ``mse_memoryless``, ``coverage68_memoryless``, ``coverage95_memoryless``: the model as
    ``temporal=None`` fits it (a ``temporal="auto"`` model's validated residual inflation,
    part of that choice, is set back to 1; its coverage is then NaN: the model's calibration
    was made for the inflated variances).
    ``information``, ``cost``, ``n_cells`` and ``greedy_route`` are those of the first day's
    plan; ``bound`` is not computed (NaN). Campaigns take the whole path model below and
    fleets: every method of a campaign plans every day under the same path request
    and fleet.

    Path model (docs/evaluation.md; defaults are the paper's): ``path``, a
    :class:`~lrm_cvx.planning.request.PathOptions` (``metric``, ``speed``, ``stop_cost``,
    ``traversable``, ``closed`` and, with ``temporal`` campaigns, ``end`` (greedy methods only)
    and ``sense_along`` (every cell passed is observed; a baseline's route already passes only
    its own cells)), is passed to every method, the greedy and the baselines alike.
    ``n_robots > 1``: every start is a fleet of ``n_robots`` distinct start cells (drawn with
    the seed; ``start_cell`` is the first robot's, ``fleet_start_cell`` ``(start, robot)`` all
    of them), each robot with the whole ``budget``; ``cost`` is the fleet's total and
    ``robot_cost`` ``(method, budget, start, trial, robot)`` each robot's. With a travel graph
    the starts are enterable cells with an enterable neighbour. Bad options raise
    PlanningError before the fit. The options are recorded in the attrs (``metric``,
    ``speed``, ``stop_cost``, ``traversable``, ``closed``, ``n_robots``, ``budget_unit``; with
    ``temporal`` also ``end``, -1 for none, and ``sense_along``).

    ``coverage68`` / ``coverage95`` ``(method, budget, start, trial, test_time)``: fraction of
    the held-out observed cells (at most 4096 per snapshot, a fixed subset, minus the sampled
    cells) inside the central 68 % / 95 % predictive interval of the fold-in used for ``mse``
    (calibrated when the model is: :func:`~lrm_cvx.validation.calibration.calibrate`).

    Returns a Dataset with ``information``, ``cost``, ``n_cells`` ``(method, budget, start,
    trial)``, ``mse`` and ``n_obs`` ``(method, budget, start, trial, test_time)``, ``bound``,
    ``recommended_bound`` and ``recommended_value`` ``(budget, start)``, ``complete_mse``
    ``(test_time)``, the start cells, and the greedy routes (``greedy_route``, padded with -1)
    for the qualitative figures.

    A rolling-origin backtest of the protocol (its test block repeated back in time, each
    block's model fitted on the snapshots before it) is :func:`backtest`.

    Parameters
    ----------
    planning : PlanningOptions, optional
        How the methods plan: ``criterion``, ``cost``, ``ridge``, ``random_trials``,
        ``certify`` and ``n_jobs`` (threads over the start cells); None: the defaults above.
    scoring : ScoringOptions, optional
        How each plan is scored: ``model_params``, ``fold_in``, ``fold_ridge`` and
        ``min_observations``; None: the defaults above.
    progress : bool
        Show progress bars.
    """
    request = PathOptions.from_kwargs(path, where="evaluate", allowed=_EVALUATE_PATH)
    return EvaluationProtocol(data, rank=rank, n_test=n_test, budgets=budgets,
                              n_starts=n_starts, methods=methods, model=model, seed=seed,
                              temporal=temporal, n_robots=n_robots, path=request,
                              planning=planning, scoring=scoring, progress=progress,
                              paper=paper).run()


def backtest(data: xr.DataArray, origins: int = 3, *, model: Any = None,
             **kwargs: Any) -> xr.Dataset:
    """The rolling-origin backtest of :func:`evaluate`: its protocol on each of the last
    ``origins`` blocks of ``n_test`` snapshots of ``data`` (time-sorted), as if each were the
    test.

    Block ``b``'s model, with every choice it validates (``temporal="auto"``,
    ``spatial="auto"``, ``rank="auto"``) and its calibration, is fitted on the snapshots
    before the block only, so no choice and no interval ever sees the snapshots it is scored
    on. A given ``model`` lends its parameters only: each block fits a fresh copy (its class
    and ``get_params()``; the choices it made on its own training are made again). ``kwargs``
    are :func:`evaluate`'s (``n_test``, ``budgets``, ``methods``, ``temporal``, path options,
    ...), checked before any fit.

    Returns the blocks' Datasets stacked on a new ``origin`` dimension, with coordinates
    ``origin_time`` (the block's first test time) and ``n_train``; ``test_time`` is the union
    of the blocks' times, NaN where a block has none, so a pooled mean counts every (plan,
    snapshot) once. :func:`summary` pools the blocks, ``summary(results, by_origin=True)``
    gives one row per block, :func:`coverage_check` says whether the intervals hold.
    ``origins`` must be an integer >= 1 that leaves at least ``n_test`` snapshots before the
    first block (DataError naming it).
    """
    from dataclasses import fields

    n_origins = check_int(origins, "origins", 1, DataError)
    request = PathOptions.from_kwargs(kwargs.pop("path", None), where="backtest",
                                      allowed=_EVALUATE_PATH)
    known = {f.name for f in fields(EvaluationProtocol)} - {"data", "model", "path"}
    bad = set(kwargs) - known
    if bad:
        raise TypeError(f"backtest() got an unexpected keyword argument {sorted(bad)[0]!r}")
    kw = {**kwargs, "path": request}
    protocol = EvaluationProtocol(data, model=model, **kw)  # every argument checked first
    return _rolling_origin(protocol.data, n_origins, protocol.n_test, model, kw)


def _padded(parts: list[xr.Dataset]) -> list[xr.Dataset]:
    """``parts`` with every dimension that has no coordinate (a route's ``step``, a fleet's
    ``robot``) padded at its end to the longest part's size: -1 in integer variables (the
    routes' padding), NaN in floats, False in booleans."""
    dims = {d for p in parts for d in p.dims if d not in p.coords}
    longest = {d: max(p.sizes.get(d, 0) for p in parts) for d in dims}
    out = []
    for p in parts:
        for d, n in longest.items():
            short = n - p.sizes.get(d, n)
            if short <= 0:
                continue
            fixed = {}
            for name, v in p.data_vars.items():
                if d not in v.dims:
                    continue
                fill = (-1 if np.issubdtype(v.dtype, np.integer) else
                        False if v.dtype == bool else np.nan)
                fixed[name] = v.pad({d: (0, short)}, constant_values=fill).astype(v.dtype)
            p = p.drop_vars(list(fixed)).assign(fixed)  # not aligned with the short ones
        out.append(p)
    return out


def _rolling_origin(data: xr.DataArray, n_origins: int, n_test: int, model: Any,
                    kw: dict) -> xr.Dataset:
    """:func:`backtest`: the protocol on each of the last
    ``n_origins`` blocks of ``n_test`` snapshots of the time-sorted ``data``, every block's
    model fitted on the snapshots before it, stacked on an ``origin`` dimension."""
    T = data.sizes["time"]
    if (n_origins + 1) * n_test > T:
        raise DataError(f"origins={n_origins} test blocks of n_test={n_test} snapshots need "
                        f"at least {(n_origins + 1) * n_test} snapshots (n_test of them to "
                        f"fit the first block's model on), the data have {T}")
    parts, n_train = [], []
    for b in range(n_origins):
        end = T - (n_origins - 1 - b) * n_test
        part = data.isel(time=slice(None, end))
        fitted = None
        if model is not None:  # its parameters, refitted on the snapshots before the block
            params = {**model.get_params(), "progress": bool(kw.get("progress", True))}
            fitted = type(model)(**params).fit(part.isel(time=slice(None, end - n_test)))
        parts.append(EvaluationProtocol(part, model=fitted, **kw).run())
        n_train.append(end - n_test)
    out = xr.concat(_padded(parts), dim="origin", join="outer", combine_attrs="drop_conflicts")
    first = [r["test_time"].values[0] for r in parts]
    out = out.assign_coords(origin=np.arange(n_origins), origin_time=("origin", first),
                            n_train=("origin", np.asarray(n_train, dtype=np.int64)))
    out["origin_time"].attrs["long_name"] = "first test time of the block"
    out["n_train"].attrs["long_name"] = "training snapshots of the block's model"
    out.attrs.update(origins=int(n_origins), n_test=int(n_test))
    return out

