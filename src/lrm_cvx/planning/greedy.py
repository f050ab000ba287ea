"""The paper's generalized cost-benefit greedy planner (Zhang and Vorobeychik)."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from .._validation import as_factor_matrix, check_positive
from ..cost import COST_REGISTRY, make_cost
from ..errors import PlanningError
from ..information import CRITERION_REGISTRY, fisher_information, make_oracle
from ..region import Region
from .plan import Plan, check_region

__all__ = ["initial_cells", "plan_greedy"]

_TOL = 1e-9  # budget tolerance (grid units)
_MIN_DC = 1e-12  # floor of the cost increase in the ratio (NN tours can get shorter)
_POOL_SLACK = 1e-6  # a cell farther than budget + slack from the start is never feasible


def initial_cells(region: Region, start: int, k: int) -> np.ndarray:
    """The start cell plus its ``k - 1`` nearest valid cells, start first, ``(k,)`` int64.

    Nearest by Euclidean grid distance, ties to the lowest cell index; the others are ordered
    by (distance, index). ``k`` is the model's rank: Fisher information needs ``k`` cells.
    """
    start = int(region.check_cells(start, "start"))
    k = int(k)
    if k < 1:
        raise PlanningError(f"k must be >= 1, got {k}")
    if k > region.n_cells:
        raise PlanningError(f"the region has {region.n_cells} cells, fewer than the rank k = {k}")
    g = region.grid_index
    d = g - g[start]
    key = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) * np.int64(region.n_cells) + np.arange(
        region.n_cells, dtype=np.int64
    )
    if k < region.n_cells:
        part = np.argpartition(key, k - 1)[:k]
    else:
        part = np.arange(region.n_cells)
    return part[np.argsort(key[part], kind="stable")].astype(np.int64)


def _check_budget(budget: Any) -> float:
    """``budget`` as a float >= 0; a string or a bool is refused, not converted."""
    if isinstance(budget, (str, bytes, bool, np.bool_)):
        raise PlanningError(f"budget (grid units) must be a number, got {budget!r}")
    return check_positive(budget, "budget (grid units)", error=PlanningError)


def _budget_pool(region: Region, start: int, budget: float) -> np.ndarray:
    """Cells within ``budget`` (+ slack) of the start: the only ones any feasible plan reaches."""
    g = region.grid_index
    d = g - g[start]
    d2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float64)
    return np.flatnonzero(d2 <= (budget + _POOL_SLACK) ** 2).astype(np.int64)


def _prior_terms(prior: Any) -> dict[str, Any]:
    """The planner's keyword terms of a latent belief (``LatentPosterior.information()``)."""
    info = getattr(prior, "information", None)
    if not callable(info):
        raise PlanningError("prior must be a LatentPosterior (e.g. model.latent_prior("
                            f"'empirical')), got {type(prior).__name__}")
    return info()


def plan_greedy(
    Y: Any,
    region: Region,
    start: Any,
    budget: float,
    *,
    criterion: str = "fisher",
    cost: str = "nearest-neighbor",
    ridge: float = 0.0,
    progress: bool = True,
    prior_precision: Any = None,
    noise_var: Any = None,
    target_weights: Any = None,
    prior_cov: Any = None,
    spatial_cov: Any = None,
    targets: Any = None,
    initial: str = "nearest",
    prior: Any = None,
    refine: bool | dict[str, Any] = False,
) -> Plan:
    """The paper's cost-benefit greedy path planner.

    1. ``P`` = the start cell and its ``k - 1`` nearest cells (:func:`initial_cells`).
    2. Each iteration, for every valid cell ``x`` not in ``P`` with ``C(P + x) <= budget``
       (tolerance 1e-9): ``D_x = (I(P + x) - I(P)) / max(C(P + x) - C(P), 1e-12)``; the cell
       with the largest ``D_x`` joins ``P`` (ties to the lowest cell index).
    3. Stop when no candidate has ``D_x > 0``.

    Parameters
    ----------
    Y : ``(k, L)`` factor matrix (array, or a model's ``Y_`` DataArray ``(component, cell)``
        or ``(component, lat, lon)``).
    region : the :class:`~lrm_cvx.region.Region` of ``Y``'s cells.
    start : a cell index or a ``(lat, lon)`` pair.
    budget : path-length budget in grid units, ``>= 0``.
    criterion : ``"fisher"`` (log det gain, the paper) or ``"a-optimal"`` (decrease of the
        total prediction variance; needs ``ridge > 0``).
    cost : ``"nearest-neighbor"`` (the paper's ``C``, computed exactly) or ``"insertion"``
        (cheapest insertion route, cheaper and usually shorter).
    ridge : ``>= 0``, added to the information matrix (``ridge * I``).
    progress : show a tqdm progress bar.
    prior_precision, noise_var, target_weights : the fold-in's posterior (issue #8,
        docs/reconstruction.md): ``M = prior_precision + sum_P y_p y_p^T / noise_var_p``
        replaces ``ridge I + sum_P y_p y_p^T`` in ``"fisher"`` and ``"a-optimal"``, and the
        A-optimal target is ``sum_i target_weights_i y_i y_i^T``. ``GLRM.planner_kwargs()``
        returns them for a fitted model. Default None: the paper.
    prior_cov, spatial_cov, targets : for ``criterion="gp-variance"`` (the A-optimal criterion
        of the low-rank trend + GP residual model; :class:`~lrm_cvx.information.GPVarianceOracle`).
    initial : ``"nearest"`` (the paper: the start and its ``k - 1`` nearest cells are forced) or
        ``"start"`` (only the start cell: with a prior the information matrix is nonsingular
        from the start, so the budget is not spent on ``k - 1`` forced cells).
    prior : a :class:`~lrm_cvx.glrm.posterior.LatentPosterior` (``GLRM.latent_prior(...)``, a
        monitoring filter's forecast): its ``information()`` fills ``prior_precision``,
        ``noise_var``, ``target_weights`` and, when it has the spatial residual, ``prior_cov``
        and ``spatial_cov`` (giving one of those too is an error).
    refine : run :func:`lrm_cvx.planning.refine.refine` on the greedy plan (a local search
        of insertions and swaps that raises the information within the budget; Fisher only);
        a dict is passed to it as keyword arguments. ``plan.refinement`` records the gain.

    If the initial cells alone already exceed the budget, the plan is still returned (the
    paper's initial set is forced) with a warning. Raises :class:`PlanningError` for a bad
    budget, start, criterion or cost, or a singular initial set with ``ridge=0``.
    """
    region = check_region(region)
    Yk = as_factor_matrix(Y, region)
    k, _ = Yk.shape
    start_cell = region.resolve_cell(start, "start")
    budget = _check_budget(budget)
    criterion = CRITERION_REGISTRY.canonical(criterion, "criterion")  # aliases accepted
    cost = COST_REGISTRY.canonical(cost, "cost")
    if initial == "nearest":
        P0 = initial_cells(region, start_cell, k)
    elif initial == "start":
        P0 = np.array([start_cell], dtype=np.int64)
    else:
        raise PlanningError(f"initial must be 'nearest' or 'start', got {initial!r}")
    pool = _budget_pool(region, start_cell, budget)
    if prior is not None:
        terms = _prior_terms(prior)
        given = dict(prior_precision=prior_precision, noise_var=noise_var,
                     target_weights=target_weights, prior_cov=prior_cov, spatial_cov=spatial_cov)
        clash = sorted(key for key in terms if given.get(key) is not None)
        if clash:
            raise PlanningError(f"prior= already gives {clash}; pass either prior or those")
        prior_precision = terms.get("prior_precision")
        noise_var = terms.get("noise_var")
        target_weights = terms.get("target_weights")
        prior_cov = terms.get("prior_cov")
        spatial_cov = terms.get("spatial_cov")
    extra: dict[str, Any] = {}
    if criterion == "gp-variance":
        extra = dict(region=region, spatial_cov=spatial_cov, prior_cov=prior_cov, pool=pool,
                     targets=targets, target_weights=target_weights)
    else:
        if prior_precision is not None:
            extra["prior_precision"] = prior_precision
        if noise_var is not None:
            extra["noise_var"] = noise_var
        if target_weights is not None and criterion == "a-optimal":
            extra["target_weights"] = target_weights
    oracle = make_oracle(criterion, Yk, ridge, P0, **extra)
    coster = make_cost(cost, region.grid_index, P0, pool)
    if coster.cost > budget + _TOL:
        warnings.warn(
            f"the {k} initial cells (start and its {k - 1} nearest, needed for a rank-{k} "
            f"model) already cost {coster.cost:.4g} > budget {budget:.4g}",
            UserWarning,
            stacklevel=2,
        )
    cells = [int(c) for c in P0]
    hist: dict[str, list[float]] = {
        "cell": [], "gain": [], "cost_increase": [], "ratio": [], "cost": [], "n_evaluated": []
    }
    bar = tqdm(desc="greedy plan", unit="pick", disable=not progress, leave=False)
    try:
        while True:
            gains = oracle.gains(pool)
            dc = coster.increases()
            with np.errstate(invalid="ignore"):
                ok = coster.active & (coster.cost + dc <= budget + _TOL)
            ratio = np.where(ok, gains / np.maximum(np.where(ok, dc, 1.0), _MIN_DC), -np.inf)
            if ratio.size == 0:
                break
            best = int(np.argmax(ratio))
            if not ratio[best] > 0:
                break
            cell = int(pool[best])
            hist["cell"].append(cell)
            hist["gain"].append(float(gains[best]))
            hist["cost_increase"].append(float(dc[best]))
            hist["ratio"].append(float(ratio[best]))
            hist["n_evaluated"].append(int(getattr(coster, "n_evaluated", pool.size)))
            oracle.add(cell)
            coster.add(cell)
            cells.append(cell)
            hist["cost"].append(coster.cost)
            bar.update(1)
            bar.set_postfix(cost=f"{coster.cost:.1f}/{budget:g}", refresh=False)
    finally:
        bar.close()
    info = fisher_information(Yk, cells, ridge)
    history = {
        key: np.asarray(v, dtype=np.int64 if key in ("cell", "n_evaluated") else np.float64)
        for key, v in hist.items()
    }
    plan = Plan.build(
        region=region,
        cells=cells,
        route=coster.route,
        cost=coster.cost,
        information=info,
        criterion=criterion,
        budget=budget,
        start=start_cell,
        ridge=float(ridge),
        method="greedy",
        history=history,
        cost_function=cost,
        Y=Yk,
        posterior=prior_precision is not None or noise_var is not None,
    )
    if refine is not False and refine is not None:
        from .refine import refine as _refine

        opts = dict(refine) if isinstance(refine, dict) else {}
        if plan.posterior:
            opts.setdefault("prior_precision", prior_precision)
            opts.setdefault("noise_var", noise_var)
        plan = _refine(plan, **opts)
    return plan
