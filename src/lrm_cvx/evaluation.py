"""The paper's evaluation protocol: planners x budgets x start cells x test snapshots.

Fit a GLRM on all snapshots but the last ``n_test``; for every method, budget and start cell
(and, for the random walk, every trial) plan a route, observe each test snapshot at the route's
cells (cells the snapshot lacks give no observation), fold the observations in, and score the
predicted map against the snapshot's observed cells. Results come back as an
``xarray.Dataset`` with dims ``(method, budget, start, trial, test_time)``.

The fold-in is the model's :class:`~lrm_cvx.glrm.posterior.LatentPosterior` (offset, scale,
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
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr
from tqdm.auto import tqdm

from ._blas import single_threaded_blas
from ._validation import as_factor_matrix, as_generator, atomic_output, check_positive
from .errors import DataError, ModelError, PlanningError
from .glrm.posterior import LatentPosterior, ObservationModel, check_cells
from .information import CRITERION_REGISTRY
from .region import Region
from .registry import Choices, Registry

__all__ = ["evaluate", "summary", "save_results", "METHODS", "GREEDY_VARIANTS",
           "METHOD_REGISTRY", "SnapshotStatistics", "foldin_mse", "path_label", "check_method",
           "plan_method"]

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


def check_method(m: str) -> str:
    """The canonical name of method ``m`` (aliases accepted); ModelError if unknown."""
    return METHOD_REGISTRY.canonical(m, "method")


@dataclass(frozen=True)
class SnapshotStatistics:
    """Sufficient statistics of the test snapshots for exact fold-in errors in data units.

    With ``z = (values - offset) / scale`` (fit units) and weights ``w = scale^2`` on each
    snapshot's observed cells ``O`` (1 without a scale), ``gram = sum_O w y y^T`` ``(n_test, k,
    k)``, ``cross = sum_O w z y`` ``(n_test, k)``, ``sq = sum_O w z^2`` ``(n_test,)`` and ``count
    = |O|``, so that the squared error of the map ``offset + scale * Y^T x`` over ``O`` is
    ``x^T gram x - 2 cross^T x + sq`` (:meth:`mse_many`). ``values`` ``(n_test, L)`` stay in data
    units (float32 with NaN); the statistics are float64.
    """

    values: np.ndarray
    gram: np.ndarray
    cross: np.ndarray
    sq: np.ndarray
    count: np.ndarray

    @classmethod
    def from_values(cls, Y: np.ndarray, values: np.ndarray, offset: np.ndarray | None = None,
                    scale: np.ndarray | None = None) -> SnapshotStatistics:
        """Statistics of ``values (n_test, L)`` (NaN = not observed) for factors ``Y (k, L)``
        and the model's ``offset``/``scale`` (``(L,)`` or None)."""
        observed = np.isfinite(values)
        z = values.astype(np.float64)
        if offset is not None:
            z -= offset
        if scale is not None:
            z /= scale
        d = np.where(observed, z, 0.0)
        del z
        w = observed.astype(np.float64)
        if scale is not None:
            w *= np.square(scale)
        gram = np.einsum("kl,jl,tl->tkj", Y, Y, w, optimize=True)
        dw = d * w
        return cls(values=values, gram=gram, cross=dw @ Y.T, sq=np.einsum("tl,tl->t", dw, d),
                   count=observed.sum(axis=1))

    def mse_many(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Mean squared errors (data units) of snapshots ``rows`` (``(m,)``) mapped from latent
        vectors ``x (m, k)`` over their observed cells (NaN for NaN ``x`` or no cell)."""
        G, b = self.gram[rows], self.cross[rows]
        err = (np.einsum("tk,tkj,tj->t", x, G, x) - 2.0 * np.einsum("tk,tk->t", b, x)
               + self.sq[rows])
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count[rows] > 0, np.maximum(err, 0.0) / self.count[rows],
                            np.nan)


def _plain_prior(Y: np.ndarray, ridge: float) -> LatentPosterior:
    """The paper's fold-in on bare factors: flat, or the ridge prior (unit noise)."""
    return LatentPosterior.prior(ObservationModel(Y), "ridge", ridge)


def foldin_mse(Y: np.ndarray, stats: SnapshotStatistics, cells: np.ndarray, ridge: float = 0.0,
               min_observations: int = 1, *, prior: LatentPosterior | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Fold each test snapshot in from its values at ``cells``; MSE over its observed cells.

    The fold-in is ``prior.update(cells, values)`` (default: the paper's least squares with
    ``ridge`` on ``Y``; pass a model's ``latent_prior(...)`` for its offset, scale, noise and
    prior, with ``stats`` built with the same offset and scale). ``O(n k^2 + k^2)`` per
    snapshot: the error comes from ``stats``, never from a map. Returns ``(mse, n_obs)``, each
    ``(n_test,)``; ``mse`` is NaN where a snapshot has fewer than ``max(min_observations, 1)``
    observations at ``cells`` or they do not determine ``x`` (flat prior, rank-deficient).
    """
    if prior is None:
        prior = _plain_prior(Y, ridge)
    elif ridge:
        raise ModelError("give ridge through the prior (latent_prior(ridge=...)), not both")
    if prior.obs_model.is_spatial:
        raise ModelError("foldin_mse is the trend-only fold-in; a spatial prior needs full maps")
    cells = check_cells(cells, stats.values.shape[1])
    vals = stats.values[:, cells].astype(np.float64)  # (n_test, n)
    n_obs = np.isfinite(vals).sum(axis=1)
    mse = np.full(len(n_obs), np.nan)
    ok = np.flatnonzero(n_obs >= max(min_observations, 1))
    if ok.size:
        means, _ = prior.batch_means(cells, vals[ok])  # every snapshot's fold-in at once
        mse[ok] = stats.mse_many(ok, means)
    return mse, n_obs


def _complete_mse(stats: SnapshotStatistics, prior: LatentPosterior) -> np.ndarray:
    """The "complete" condition: fold-in from every observed cell of each snapshot (data
    units; NaN where that does not determine ``x``)."""
    allc = np.arange(stats.values.shape[1])
    means, _ = prior.batch_means(allc, stats.values)
    return stats.mse_many(np.arange(len(stats.count)), means)


def _model_mse(prior: LatentPosterior, stats: SnapshotStatistics, cells: np.ndarray,
               min_observations: int) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`foldin_mse` for a model's belief (``GLRM.latent_prior``): the exact
    statistics path without the spatial residual; with it, full predicted maps (kriging) and
    the MSE over each snapshot's observed cells, ``O(n_test L k)`` (plus kriging) per plan."""
    if not prior.obs_model.is_spatial:
        return foldin_mse(prior.obs_model.Y, stats, cells, 0.0, min_observations, prior=prior)
    values = stats.values
    cells = check_cells(cells, values.shape[1])
    vals = values[:, cells].astype(np.float64)
    obs = np.isfinite(vals)
    n_obs = obs.sum(axis=1)
    mse = np.full(values.shape[0], np.nan)
    for t in np.flatnonzero(n_obs >= max(min_observations, 1)):
        post = prior.update(cells[obs[t]], vals[t, obs[t]])
        if not post.is_proper or stats.count[t] == 0:
            continue
        pred, _ = post.predict()
        mse[t] = float(np.nanmean((pred - values[t]) ** 2))
    return mse, n_obs


@dataclass(frozen=True)
class _CampaignPlan:
    """The first day's plan of a campaign, as much of a Plan as ``evaluate`` records."""

    information: float
    cost: float
    n: int
    route: np.ndarray

    @property
    def cells(self) -> range:
        return range(self.n)


_COVERAGE_CELLS = 4096  # held-out cells scored for coverage per snapshot (a fixed subset)


def _coverage_subset(values: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Per test snapshot, at most ``_COVERAGE_CELLS`` of its observed cells (sorted, a fixed
    seeded subset): the cells whose predictive interval ``evaluate`` scores."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(values.shape[0]):
        obs = np.flatnonzero(np.isfinite(values[t]))
        if obs.size > _COVERAGE_CELLS:
            obs = np.sort(rng.choice(obs, size=_COVERAGE_CELLS, replace=False))
        out.append(obs)
    return out


def _model_coverage(prior: LatentPosterior, values: np.ndarray, subsets: list[np.ndarray],
                    cells: np.ndarray, min_observations: int) -> np.ndarray:
    """Coverage of the central 68 % / 95 % predictive intervals (``mean +- z *
    predictive_std``, calibrated when the model is: glrm/calibration.py) over each test
    snapshot's held-out observed cells (its ``subsets`` entry minus the sampled ``cells``).
    Returns ``(n_test, 2)``, NaN where the snapshot has too few observations."""
    from .glrm.calibration import interval_coverage

    cells = check_cells(cells, values.shape[1])
    vals = values[:, cells].astype(np.float64)
    obs = np.isfinite(vals)
    n_obs = obs.sum(axis=1)
    out = np.full((values.shape[0], 2), np.nan)
    for t in np.flatnonzero(n_obs >= max(min_observations, 1)):  # a loop over snapshots
        post = prior.update(cells[obs[t]], vals[t, obs[t]])
        held = np.setdiff1d(subsets[t], cells, assume_unique=True)
        if not post.is_proper or held.size == 0:
            continue
        mean, _ = post.predict(cells=held)
        out[t] = interval_coverage(values[t, held], mean, post.predictive_std(cells=held))
    return out


def _check_temporal(temporal: Any) -> str | None:
    from .glrm.dynamics import temporal_value

    return temporal_value(temporal)


def _campaign_errors(model: Any, test: xr.DataArray, start: int, budget: float, method: str,
                     temporal: str | None, seed: int, spatial: Any, min_observations: int,
                     options: dict) -> tuple:
    """One campaign over the test snapshots (:func:`lrm_cvx.campaign.simulate_campaign`):
    ``(mse (n_test,), n_obs, coverage (n_test, 2), first day's information, cost, cells,
    route)``; ``mse`` NaN where a day has fewer than ``min_observations`` observations."""
    from .campaign import simulate_campaign

    ds = simulate_campaign(model, test, start, budget, method=method, temporal=temporal,
                           seed=seed, spatial=spatial, **options)
    n = ds["n_obs"].values
    ok = n >= max(min_observations, 1)
    mse = np.where(ok, ds["mse"].values, np.nan)
    cov = np.stack([ds["coverage68"].values, ds["coverage95"].values], axis=-1)
    cov[~ok] = np.nan
    route = ds["routes"].values[0]
    route = route[route >= 0]
    return (mse, n, cov, float(ds["information"].values[0]), float(ds["route_cost"].values[0]),
            int(np.unique(route).size), route)


def plan_method(method: str, Y: np.ndarray, region: Region, start: Any, budget: float,
                rng: np.random.Generator, criterion: str, cost: str, ridge: float,
                model: Any = None, fold_in: dict | None = None, path: dict | None = None
                ) -> Any:
    """One method's :class:`~lrm_cvx.planning.Plan` from ``start`` (a cell, or a list of
    cells: a fleet, ``budget`` per robot) under the path options ``path`` (only the
    non-default ones; :func:`_path_options`). ``method`` is canonical (:func:`check_method`);
    the ``greedy:<criterion>`` variants need ``model`` (their prior: the model's empirical
    latent prior); ``rng`` drives the random walk."""
    from .planning import plan_greedy, random_walk, transect

    path = dict(path or {})
    if method.startswith("greedy:"):
        crit = method.split(":", 1)[1]
        prior = model.latent_prior("empirical", spatial=crit == "gp-variance")
        return plan_greedy(Y, region, start, budget, criterion=crit, cost=cost, ridge=ridge,
                           progress=False, initial="start", prior=prior, **path)
    if method == "greedy":
        return plan_greedy(Y, region, start, budget, criterion=criterion, cost=cost,
                           ridge=ridge, progress=False, **path)
    if method.startswith("transect-"):
        return transect(region, start, budget, method.split("-", 1)[1], Y=Y, ridge=ridge,
                        **path)
    if method == "random":
        return random_walk(region, start, budget, rng, Y=Y, ridge=ridge, **path)
    raise ModelError(f"unknown method {method!r}; expected one of {METHODS}")


def _path_options(metric: Any, speed: Any, stop_cost: Any, traversable: Any,
                  closed: Any) -> dict[str, Any]:
    """The path model options of :func:`evaluate` checked before any work (the path model's
    PlanningErrors, naming the argument), as the keyword arguments every planner takes: only
    those that differ from the paper's, so the default calls stay exactly the paper's."""
    from .planning.paths import check_amount, check_metric

    metric, speed, unit = check_metric(metric, speed)
    out: dict[str, Any] = {}
    if metric != "grid":
        out["metric"] = metric
    if speed is not None:
        out["speed"] = speed
    stop_cost = check_amount(stop_cost, "stop_cost", unit)
    if stop_cost:
        out["stop_cost"] = stop_cost
    if not isinstance(closed, (bool, np.bool_)):
        raise PlanningError(f"closed must be True or False, got {closed!r}")
    if closed:
        out["closed"] = True
    if traversable is not None:
        if isinstance(traversable, str):
            if traversable.strip().lower() != "valid":
                raise PlanningError(f"traversable must be None, 'valid' or a boolean (lat, "
                                    f"lon) mask, got {traversable!r}")
            traversable = "valid"
        elif not isinstance(traversable, (xr.DataArray, np.ndarray)):
            raise PlanningError(f"traversable must be None, 'valid' or a boolean (lat, lon) "
                                f"mask, got {type(traversable).__name__}")
        out["traversable"] = traversable
    return out


def _int_arg(value: Any, name: str, minimum: int, error: type[Exception] = ModelError) -> int:
    """``value`` as an int >= ``minimum`` (bools, floats with a fraction, NaN refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float,
                                                                     np.floating)):
        raise error(f"{name} must be an integer >= {minimum}, got {value!r}")
    if not np.isfinite(value) or float(value) != int(value) or value < minimum:
        raise error(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


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
    temporal: str | None = None,
    metric: str = "grid",
    speed: float | None = None,
    stop_cost: float = 0.0,
    traversable: Any = None,
    closed: bool = False,
    n_robots: int = 1,
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

    The test snapshots are the last ``n_test`` *times*: data whose ``time`` coordinate is not
    sorted is sorted first (with a UserWarning); missing (NaT/NaN) or duplicated times raise
    DataError naming them. ``n_starts``, ``n_test``, ``n_jobs`` (and ``random_trials`` when
    ``"random"`` is among ``methods``) must be integers >= 1, ``methods`` non-empty without
    repeats, ``budgets`` finite, >= 0 and distinct (ModelError / DataError otherwise).

    Reconstruction options (issue #8, docs/reconstruction.md; defaults are the paper's):
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

    Persistent monitoring (issue 13, docs/monitoring.md): ``temporal=None`` (default) is the
    protocol above, each test snapshot folded in on its own. ``"ar1"``/``"seasonal"``: for every
    start, method, budget (and random trial) one campaign
    (:func:`~lrm_cvx.campaign.simulate_campaign`) runs over the test snapshots in time order,
    each day planned against the filter's forecast and assimilated by the filter (the model's
    ``dynamics_`` when of that kind, else estimated from ``X_``); ``mse``, ``n_obs`` and the
    coverage are the campaign's, and the same campaigns run memoryless through the same loop
    give ``mse_memoryless``, ``coverage68_memoryless``, ``coverage95_memoryless``.
    ``information``, ``cost``, ``n_cells`` and ``greedy_route`` are those of the first day's
    plan; ``bound`` is not computed (NaN).

    Path model (issue #15, docs/evaluation.md; defaults are the paper's): ``metric``
    (``"grid"`` or ``"km"``), ``speed`` (km/h: budgets in hours), ``stop_cost`` (budget unit
    per sampling stop), ``traversable`` (``None``, ``"valid"`` or a boolean ``(lat, lon)``
    DataArray) and ``closed`` are passed to every method, the greedy and the baselines alike.
    ``n_robots > 1``: every start is a fleet of ``n_robots`` distinct start cells (drawn with
    the seed; ``start_cell`` is the first robot's, ``fleet_start_cell`` ``(start, robot)`` all
    of them), each robot with the whole ``budget``; ``cost`` is the fleet's total and
    ``robot_cost`` ``(method, budget, start, trial, robot)`` each robot's. With a travel graph
    the starts are enterable cells with an enterable neighbour. Bad options raise
    PlanningError before the fit; ``temporal`` campaigns support only the paper's model. The
    options are recorded in the attrs (``metric``, ``speed``, ``stop_cost``, ``traversable``,
    ``closed``, ``n_robots``, ``budget_unit``).

    ``coverage68`` / ``coverage95`` ``(method, budget, start, trial, test_time)``: fraction of
    the held-out observed cells (at most 4096 per snapshot, a fixed subset, minus the sampled
    cells) inside the central 68 % / 95 % predictive interval of the fold-in used for ``mse``
    (calibrated when the model is: :func:`~lrm_cvx.glrm.calibration.calibrate`).

    Returns a Dataset with ``information``, ``cost``, ``n_cells`` ``(method, budget, start,
    trial)``, ``mse`` and ``n_obs`` ``(method, budget, start, trial, test_time)``, ``bound``
    ``(budget, start)``, ``complete_mse`` ``(test_time)``, the start cells, and the greedy
    routes (``greedy_route``, padded with -1) for the qualitative figures.
    """
    from .glrm import GLRM
    from .planning.paths import startable_cells

    if not isinstance(data, xr.DataArray) or data.ndim != 3:
        raise DataError("data must be a (time, lat, lon) DataArray")
    data = _time_ordered(data)
    if isinstance(methods, str):
        methods = (methods,)
    methods = tuple(check_method(m) for m in methods)
    if not methods:
        raise ModelError(f"methods must name at least one method of {METHODS}")
    if len(set(methods)) != len(methods):
        raise ModelError(f"methods must not repeat, got {list(methods)}")
    n_test = _int_arg(n_test, "n_test", 1, DataError)
    n_starts = _int_arg(n_starts, "n_starts", 1)
    if "random" in methods:
        random_trials = _int_arg(random_trials, "random_trials", 1)
    min_observations = _int_arg(min_observations, "min_observations", 0)
    n_jobs = _int_arg(n_jobs, "n_jobs", 1)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    fold_ridge = check_positive(fold_ridge, "fold_ridge", error=ModelError)
    temporal = _check_temporal(temporal)
    path = _path_options(metric, speed, stop_cost, traversable, closed)
    n_robots = _int_arg(n_robots, "n_robots", 1, PlanningError)
    if temporal is not None and (path or n_robots > 1):
        raise PlanningError("temporal campaigns support only the paper's path model: drop "
                            "metric, speed, stop_cost, traversable, closed and n_robots, or "
                            "temporal")
    model_params = dict(model_params or {})
    fold_in = dict(fold_in or {})
    bad = set(fold_in) - {"prior", "spatial", "ridge"}
    if bad:
        raise ModelError(f"fold_in keys must be among prior, spatial, ridge; got {sorted(bad)}")
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
    if certify not in (False, "fast", "tight", True):
        raise ModelError(f"certify must be False, 'fast' or 'tight', got {certify!r}")
    certify = "tight" if certify is True else certify
    if not 0 < n_test < data.sizes["time"]:
        raise DataError(f"n_test must be in [1, {data.sizes['time'] - 1}], got {n_test}")
    train, test = data.isel(time=slice(None, -n_test)), data.isel(time=slice(-n_test, None))
    if model is not None:
        _check_given_model(model, test)
    if model is None:
        model = GLRM(rank=rank, random_state=seed, progress=progress,
                     **model_params).fit(train)
    region = model.region_
    if region is None:
        raise ModelError("model must have been fitted on a DataArray (it has no region)")
    Y = as_factor_matrix(model.Y_, region)
    test_values = region.stack(test)
    # one observation model for every error: the model's offset / scale / noise (data units)
    stats = SnapshotStatistics.from_values(Y, test_values, getattr(model, "offset_", None),
                                           getattr(model, "scale_", None))
    use_model = bool(fold_in) or not model.is_plain_low_rank
    paper_prior = model.latent_prior(None, ridge=fold_ridge)  # the paper's fold-in
    fold_prior = (model.latent_prior(fold_in.get("prior"),
                                     ridge=float(fold_in.get("ridge", fold_ridge)),
                                     spatial=bool(fold_in.get("spatial", False)))
                  if use_model else paper_prior)
    rng = as_generator(seed)
    # the cells a robot may start from; a bad traversable raises here, before any plan
    candidates = startable_cells(region, path.get("traversable"))
    if n_starts * n_robots > candidates.size:
        where = ("valid cells" if "traversable" not in path else
                 "enterable cells with an enterable neighbour")
        raise DataError(f"n_starts={n_starts}" + (f" x n_robots={n_robots}" if n_robots > 1
                                                   else "")
                        + f" exceeds the {candidates.size} {where}")
    if n_robots == 1:
        starts = candidates[np.sort(rng.choice(candidates.size, size=n_starts, replace=False))]
        fleets = starts[:, None]
    else:  # distinct cells, each fleet's in ascending order
        fleets = np.sort(candidates[rng.choice(candidates.size, size=(n_starts, n_robots),
                                               replace=False)], axis=1)
        starts = fleets[:, 0]
    n_trials = random_trials if "random" in methods else 1
    shape = (len(methods), len(budgets), n_starts, n_trials)
    info = np.full(shape, np.nan)
    cost_ = np.full(shape, np.nan)
    n_cells = np.zeros(shape, dtype=np.int32)
    mse = np.full(shape + (n_test,), np.nan)
    n_obs = np.zeros(shape + (n_test,), dtype=np.int32)
    coverage = np.full(shape + (n_test, 2), np.nan)
    mse_ml = np.full(shape + (n_test,), np.nan) if temporal else None
    coverage_ml = np.full(shape + (n_test, 2), np.nan) if temporal else None
    cov_subsets = _coverage_subset(stats.values, seed)
    cov_values = stats.values.astype(np.float64)
    camp_opts = {"cost": cost, "ridge": ridge, "criterion": criterion}
    camp_spatial = fold_in.get("spatial") if "spatial" in fold_in else None
    bound = np.full((len(budgets), n_starts), np.nan)
    robot_cost = np.full(shape + (n_robots,), np.nan) if n_robots > 1 else None
    max_route = 0
    routes: dict[tuple[int, int], np.ndarray] = {}
    route_robots: dict[tuple[int, int], np.ndarray] = {}
    seeds = np.random.SeedSequence(seed).spawn(n_starts)

    def run_start(s: int) -> list[tuple]:
        out = []
        start_rng = np.random.default_rng(seeds[s])
        for b, budget in enumerate(budgets):
            for m, method in enumerate(methods):
                for trial in range(n_trials if method == "random" else 1):
                    if temporal is not None:
                        cseed = int(start_rng.integers(2**31))
                        runs = [_campaign_errors(model, test, int(starts[s]), budget, method,
                                                 tm, cseed, camp_spatial, min_observations,
                                                 camp_opts) for tm in (temporal, None)]
                        (e, n, c, inf, cst, ncell, route), ml = runs
                        plan = _CampaignPlan(inf, cst, ncell, route)
                        out.append((m, b, s, trial, plan, e, n, np.nan, c, ml[0], ml[2]))
                        continue
                    where = int(starts[s]) if n_robots == 1 else [int(c) for c in fleets[s]]
                    plan = plan_method(method, Y, region, where, budget, start_rng,
                                       criterion, cost, ridge, model, fold_in, path)
                    e, n = _model_mse(fold_prior, stats, plan.cells, min_observations)
                    c = _model_coverage(fold_prior, cov_values, cov_subsets, plan.cells,
                                        min_observations)
                    cert = (plan.certify(tighten=certify == "tight", refine=False).bound
                            if certify and method == "greedy" else np.nan)  # bound only
                    out.append((m, b, s, trial, plan, e, n, cert, c, None, None))
        return out

    jobs = range(n_starts)
    bar = tqdm(total=n_starts, desc="evaluate (starts)", disable=not progress)
    with warnings.catch_warnings(), single_threaded_blas(), \
            ThreadPoolExecutor(max_workers=max(1, n_jobs)) as pool:  # tiny k x k algebra
        # at small budgets the forced initial cells exceed the budget: expected, not news
        warnings.filterwarnings("ignore", message=r"(the|robot \d+.s) \d+ initial cells")
        for results in pool.map(run_start, jobs):
            for m, b, s, trial, plan, e, n, cert, c, e_ml, c_ml in results:
                info[m, b, s, trial] = plan.information
                cost_[m, b, s, trial] = plan.cost
                n_cells[m, b, s, trial] = len(plan.cells)
                if robot_cost is not None:
                    robot_cost[m, b, s, trial] = plan.robot_costs
                mse[m, b, s, trial] = e
                n_obs[m, b, s, trial] = n
                coverage[m, b, s, trial] = c
                if temporal is not None:
                    mse_ml[m, b, s, trial] = e_ml
                    coverage_ml[m, b, s, trial] = c_ml
                if methods[m] == "greedy":
                    bound[b, s] = cert
                    routes[(b, s)] = np.asarray(plan.route)
                    route_robots[(b, s)] = np.asarray(getattr(plan, "route_robot", []))
                    max_route = max(max_route, len(plan.route))
            bar.update()
    bar.close()

    greedy_route = np.full((len(budgets), n_starts, max(max_route, 1)), -1, dtype=np.int64)
    for (b, s), r in routes.items():
        greedy_route[b, s, : len(r)] = r
    unit = ("grid units" if "metric" not in path else "h" if "speed" in path else "km")
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
                     {"long_name": "path cost" + (" (the fleet's total)" if n_robots > 1
                                                  else ""),
                      "units": "grid cells" if unit == "grid units" else unit}),
            "n_cells": (("method", "budget", "start", "trial"), n_cells),
            "mse": (("method", "budget", "start", "trial", "test_time"), mse,
                    {"long_name": "mean squared reconstruction error over observed cells",
                     "units": f"({data.attrs.get('units', '1')})^2"}),
            "n_obs": (("method", "budget", "start", "trial", "test_time"), n_obs),
            "bound": (("budget", "start"), bound,
                      {"long_name": "certified upper bound on the information of any plan",
                       "units": "nats"}),
            "complete_mse": (("test_time",), _complete_mse(stats, paper_prior),
                             {"long_name": "fold-in error from every observed cell",
                              "units": f"({data.attrs.get('units', '1')})^2"}),
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
            "temporal": "none" if temporal is None else temporal,
            "metric": path.get("metric", "grid"),
            "speed": float(path.get("speed", np.nan)),
            "stop_cost": float(path.get("stop_cost", 0.0)),
            "traversable": ("none" if "traversable" not in path else "valid"
                            if isinstance(path["traversable"], str) else "mask"),
            "closed": int(bool(path.get("closed", False))),
            "n_robots": int(n_robots),
            "budget_unit": unit,
        },
    )
    if n_robots > 1:
        ds = ds.assign_coords(robot=np.arange(n_robots))
        ds["fleet_start_cell"] = (("start", "robot"), fleets)
        ds["fleet_start_lat"] = (("start", "robot"), region.cell_lat[fleets])
        ds["fleet_start_lon"] = (("start", "robot"), region.cell_lon[fleets])
        ds["robot_cost"] = (("method", "budget", "start", "trial", "robot"), robot_cost,
                            {"long_name": "each robot's path cost", "units": unit})
        route_robot = np.full(greedy_route.shape, -1, dtype=np.int64)
        for (b, s), r in route_robots.items():
            route_robot[b, s, : len(r)] = r
        ds["greedy_route_robot"] = (("budget", "start", "step"), route_robot,
                                    {"long_name": "robot of each greedy_route entry (-1: "
                                                  "padding)"})
    dims5 = ("method", "budget", "start", "trial", "test_time")
    for i, level in enumerate((68, 95)):
        ds[f"coverage{level}"] = (dims5, coverage[..., i], {
            "long_name": f"fraction of held-out observed cells inside the central {level}% "
                         "predictive interval"})
    if temporal is not None:
        ds["mse_memoryless"] = (dims5, mse_ml, {
            "long_name": "campaign MSE of the memoryless model through the same loop",
            "units": ds["mse"].attrs["units"]})
        for i, level in enumerate((68, 95)):
            ds[f"coverage{level}_memoryless"] = (dims5, coverage_ml[..., i])
    if use_model:
        cm = _complete_mse(stats, model.latent_prior(
            fold_in.get("prior"), ridge=float(fold_in.get("ridge", fold_ridge))))
        ds["complete_mse_model"] = (("test_time",), cm,
                                    {"long_name": "model fold-in error from every observed cell"})
    return ds


def summary(results: xr.Dataset) -> pd.DataFrame:
    """Mean and standard error of information and MSE per method and budget.

    Information averages the usable plans; MSE averages every (plan, test snapshot) pair with
    enough observations. Standard error = std / sqrt(count). ``coverage68_mean`` /
    ``coverage95_mean`` average the per-pair coverage. Results of ``evaluate(temporal=...)``
    put memoryless and temporal side by side: ``mse_memoryless_mean`` / ``_se``, the
    memoryless coverage, and ``temporal_cut`` = ``1 - mse / mse_memoryless`` over the pairs
    where both are defined (positive: the filter lowers the error). ``path`` describes the path
    model (:func:`path_label`: ``"grid"`` for the paper's).
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
                **_side_by_side(sel),
            })
    df = pd.DataFrame(rows)
    df["temporal"] = str(results.attrs.get("temporal", "none"))
    df["path"] = path_label(results.attrs)
    df["complete_mse"] = float(results["complete_mse"].mean())
    return df


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
    with atomic_output(paths["results"]) as tmp:
        results.to_netcdf(tmp, engine="netcdf4")
    with atomic_output(paths["summary"]) as tmp:
        summary(results).to_csv(tmp, index=False)
    return paths
